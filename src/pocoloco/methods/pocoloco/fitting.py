"""Fitting an outfit PocoLoco never saw (issue "a PocoLoco that wins", item 2): the network is frozen;
only a new outfit code (one row of the outfit embedding, :mod:`pocoloco.models.conditioning`) is
optimised with the diffusion loss (PocoLoco paper Eq. 7: epsilon-prediction MSE at random t) on one
or a few scans of the garment, each with the pose (joints) it was captured in. The code starts from
a given code (``pocoloco fit`` passes the trained outfit nearest to the first scan) or the mean of
the trained outfits' codes, as POP's geometric features do (POP Sec. 3.3); an optional L2 pull to
the start (``anchor``) keeps a fit to one pose from drifting to codes that only explain that pose.
Unlike POP's deterministic fit, the fitted model then *samples* the new outfit in any pose.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from pocoloco.engine.trainer import frozen
from pocoloco.data.dataset import Normalisation
from pocoloco.diffusion import NoiseSchedule, diffusion_loss
from pocoloco.models.conditioning import PoseCondition

__all__ = ["CodeFit", "fit_outfit_code"]


@dataclass
class CodeFit:
    """features: the fitted (D,) outfit code; losses: the diffusion loss of every step."""

    features: torch.Tensor
    losses: list[float] = field(default_factory=list)


def fit_outfit_code(model: nn.Module, normalisation: Normalisation, config, scans: Sequence[tuple[np.ndarray, np.ndarray]],
                    shape: Sequence[float] | None = None, steps: int = 400, lr: float = 1e-2, batch_size: int = 8,
                    num_points: int | None = None, seed: int = 0, init: torch.Tensor | None = None,
                    anchor: float = 0.0, progress=None) -> CodeFit:  # fmt: skip
    """Optimise a new outfit code against ``scans``: [(points (P, 3) metres, joints (24, 3) metres)],
    or [(points, joints, body (K, 3) metres)] for a model that reads the posed body (``body_points``).

    Each step draws ``batch_size`` clouds (a scan each, round robin, ``num_points`` of its points,
    default the model's training N), normalises them with their pose, and takes one Adam step on the
    code only. ``shape``: the (S,) body shape of the scans' body (models conditioned on it).
    ``init``: the (D,) start code (default: the mean of the trained codes); ``anchor``: weight of
    ``mean((code - init)^2)`` added to the loss (0 = plain diffusion loss).
    The model's parameters, buffers and training flag are left unchanged.
    """
    who = getattr(model, "who", None)
    if who is None or who.outfit_embed is None:
        raise ValueError("this PocoLoco model has no outfit codes (train it with --outfit-codes) to fit")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    if not scans:
        raise ValueError("fitting needs at least one scan")
    if not (anchor >= 0.0 and np.isfinite(anchor)):
        raise ValueError(f"anchor must be a finite number >= 0, got {anchor!r}")
    weight = who.outfit_embed.weight
    device, dtype = weight.device, weight.dtype
    N = int(num_points or config.num_points)
    rng = np.random.default_rng([seed, 8])
    clouds = []
    for points, joints, *body in scans:
        p, j = normalisation.normalise(np.asarray(points, np.float32), np.asarray(joints, np.float32))
        b = None
        if body and body[0] is not None:
            b = torch.as_tensor(normalisation.normalise(np.asarray(body[0], np.float32), np.asarray(joints, np.float32))[0],
                                dtype=dtype)  # fmt: skip
        clouds.append((torch.as_tensor(p, dtype=dtype), torch.as_tensor(j, dtype=dtype), b))
    schedule = NoiseSchedule.from_kind(config.schedule, config.num_timesteps)
    gen = torch.Generator(device).manual_seed(int(seed))
    start = weight.detach().mean(0) if init is None else torch.as_tensor(init).detach().to(weight).reshape(-1)
    if start.shape != weight.shape[1:]:
        raise ValueError(f"init must be a code of shape {tuple(weight.shape[1:])}, got {tuple(torch.as_tensor(init).shape)}")
    code = nn.Parameter(start.clone())  # (D,)
    opt = torch.optim.Adam([code], lr=lr)
    shape_t = None if shape is None else torch.as_tensor(np.asarray(shape, np.float32), dtype=dtype, device=device)
    fit = CodeFit(code.data)
    with frozen(model):
        for step in range(steps):
            xs, js, bs = [], [], []
            for b in range(batch_size):
                p, j, body = clouds[(step * batch_size + b) % len(clouds)]
                sel = torch.from_numpy(rng.choice(len(p), N, replace=len(p) < N))
                xs.append(p[sel])
                js.append(j)
                bs.append(body)
            x0, joints = torch.stack(xs).to(device), torch.stack(js).to(device)  # (B, N, 3), (B, J, 3)
            B = x0.shape[0]
            body = None if bs[0] is None else torch.stack(bs).to(device)  # (B, K, 3)
            cond = PoseCondition(joints, None, None if shape_t is None else shape_t.expand(B, -1),
                                 code[None].expand(B, -1), body)  # fmt: skip
            loss, _ = diffusion_loss(model, x0, cond, schedule, config.prediction_type, generator=gen)
            if anchor > 0.0:
                loss = loss + anchor * (code - start).square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            fit.losses.append(float(loss.detach()))
            if progress is not None:
                progress(len(fit.losses), steps, fit.losses[-1])
    fit.features = code.detach().clone()
    return fit
