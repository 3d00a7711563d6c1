"""Fitting a new outfit to one scan with a trained POP (paper Sec. 3.3, Eq. 7): the network is
frozen; only a new geometric feature tensor is optimised, from the mean of the trained outfits."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from pocoloco.engine.trainer import frozen
from pocoloco.methods.pop.losses import pop_losses
from pocoloco.models.pop import POP, POPBatch, POPLossWeights

__all__ = ["POPFit", "fit_unseen_outfit"]


@dataclass
class POPFit:
    """Result of ``fit_unseen_outfit``: features (1, Cg, Ri, Ri) and the loss per step."""

    features: torch.Tensor
    losses: list[float] = field(default_factory=list)


def fit_unseen_outfit(model: POP, scan_points, scan_normals, pose_vertices, body_vertices, vtransf, steps: int = 400,
                      lr: float = 5e-4, normal_weight: float | None = None, init: torch.Tensor | None = None,
                      progress=None, weights: POPLossWeights = POPLossWeights()) -> POPFit:  # fmt: skip
    """Fit a new outfit to one scan (paper Eq. 7, Sec. 3.3): the network is frozen (eval
    mode, no gradients); only a new geometric feature tensor, initialised to the mean
    of the trained outfits' tensors, is optimised with Adam (``lr``: by default the paper's rate
    for the feature tensors) on the training loss ``weights``.

    scan_points, scan_normals: (N, 3) pelvis-centred scan; pose_vertices, body_vertices:
    (V, 3); vtransf: (V, 3, 3). Use ``model.add_outfit(fit.features)`` to animate it.
    init: (1, Cg, Ri, Ri) start instead of the mean outfit. progress: optional
    ``callable(done_steps, steps, loss)``.
    The model's parameters, buffers and training flag are left unchanged.
    """
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    ref = model.geom
    as_t = lambda a: torch.as_tensor(np.asarray(a) if not torch.is_tensor(a) else a, dtype=ref.dtype, device=ref.device)  # noqa: E731
    y = as_t(scan_points)
    if y.ndim != 2 or y.shape[1] != 3:
        raise ValueError(f"scan_points must have shape (N, 3), got {tuple(y.shape)}")
    ny = None if scan_normals is None else as_t(scan_normals)
    batch = POPBatch(as_t(pose_vertices)[None], as_t(body_vertices)[None], as_t(vtransf)[None],
                     torch.zeros(1, dtype=torch.long), y[None], None if ny is None else ny[None])  # fmt: skip
    start = model.geom.detach().mean(0, keepdim=True) if init is None else init.detach().to(model.geom)
    if tuple(start.shape) != (1, *model.geom.shape[1:]):
        raise ValueError(f"init must have shape {(1, *model.geom.shape[1:])}, got {tuple(start.shape)}")
    G = nn.Parameter(start.clone())
    opt = torch.optim.Adam([G], lr=float(lr))
    fit = POPFit(G.data)
    with frozen(model):
        for _ in range(steps):
            opt.zero_grad(set_to_none=True)
            out = model(batch, geom=G)
            loss = pop_losses(out, batch.scan_points, batch.scan_normals, weights, normal_weight)
            loss.total.backward()
            opt.step()
            fit.losses.append(float(loss.total.detach()))
            if progress is not None:
                progress(len(fit.losses), steps, fit.losses[-1])
    fit.features = G.detach().clone()
    return fit
