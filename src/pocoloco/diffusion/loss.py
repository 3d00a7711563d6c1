"""The denoising training loss (Ho et al. 2020, eq. 14 "L_simple"), optionally min-SNR weighted.

Shapes: x0 (B, N, C), t (B,). The loss of sample b is the mean over its (N, C) entries of the
squared error between the network output and the target of its prediction type; the batch
loss is the mean over b of ``w_b * mse_b``.
"""

from __future__ import annotations

from typing import Any, Literal

import torch

from pocoloco.diffusion.sampler_base import Denoiser
from pocoloco.diffusion.schedules import PREDICTION_TYPES, NoiseSchedule, PredictionType

Weighting = Literal["none", "min_snr"]


def min_snr_weight(snr: torch.Tensor, prediction_type: PredictionType, gamma: float = 5.0) -> torch.Tensor:
    """Min-SNR-gamma loss weights (Hang et al. 2023, eq. 8 and sec. 3.4) for each prediction type.

    The weight makes every parametrisation equal to the x0-MSE weighted by min(SNR, gamma):
    epsilon: min(SNR, gamma) / SNR;  sample (x0): min(SNR, gamma);  v: min(SNR, gamma) / (SNR + 1).

    Args:
        snr: (B,) signal-to-noise ratios abar / (1 - abar).
    Returns:
        (B,) weights, same dtype and device as snr.
    """
    if prediction_type not in PREDICTION_TYPES:
        raise ValueError(f"prediction_type must be one of {PREDICTION_TYPES}, got {prediction_type!r}")
    if not gamma > 0:
        raise ValueError(f"min_snr_gamma must be positive, got {gamma}")
    clipped = snr.clamp(max=gamma)
    if prediction_type == "epsilon":
        return clipped / snr
    if prediction_type == "sample":
        return clipped
    return clipped / (snr + 1.0)


def diffusion_loss(
    denoiser: Denoiser,
    x0: torch.Tensor,
    cond: Any,
    schedule: NoiseSchedule,
    prediction_type: PredictionType = "epsilon",
    weighting: Weighting = "none",
    min_snr_gamma: float = 5.0,
    generator: torch.Generator | None = None,
    t: torch.Tensor | None = None,
    noise: torch.Tensor | None = None,
    as_tensors: bool = False,
) -> tuple[torch.Tensor, dict[str, float]]:
    """One Monte-Carlo estimate of the diffusion training loss.

    Draws t ~ U{0, .., T-1} (``torch.randint``) and then noise ~ N(0, I) (``torch.randn``), in
    that order, from ``generator`` (global RNG if None), unless ``t`` / ``noise`` are given;
    forms x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) noise and regresses the denoiser's output
    on the target of ``prediction_type`` (noise, x0 or v).

    Args:
        denoiser: ``fn(x_t (B,N,C), t (B,) int64, cond) -> (B,N,C)``.
        x0: (B, N, C) clean data.
        cond: conditioning passed through to the denoiser.
        schedule: the diffusion process.
        prediction_type: "epsilon", "sample" or "v_prediction".
        weighting: "none" (L_simple) or "min_snr" (:func:`min_snr_weight`).
        min_snr_gamma: gamma of min-SNR weighting.
        generator: RNG for t and noise (on x0's device).
        t: optional (B,) int64 timesteps to use instead of random ones.
        noise: optional (B, N, C) noise to use instead of random noise.
        as_tensors: logs as detached 0-d tensors on x0's device (no host synchronisation, for
            GPU training; an empty quarter is NaN instead of absent).
    Returns:
        (loss, logs): the scalar loss (differentiable) and floats ``loss``, ``mse`` (unweighted)
        and ``mse_q0`` .. ``mse_q3``, the unweighted MSE of the samples whose t falls in each
        quarter of [0, T) (a key is absent when no sample fell in that quarter).
    """
    if prediction_type not in PREDICTION_TYPES:
        raise ValueError(f"prediction_type must be one of {PREDICTION_TYPES}, got {prediction_type!r}")
    if weighting not in ("none", "min_snr"):
        raise ValueError(f"weighting must be 'none' or 'min_snr', got {weighting!r}")
    if not x0.is_floating_point() or x0.ndim < 2:
        raise ValueError("x0 must be a floating-point tensor of shape (B, N, C)")
    B, T = x0.shape[0], schedule.num_timesteps
    if t is None:
        t = torch.randint(0, T, (B,), generator=generator, device=x0.device)
    elif t.shape != (B,) or t.dtype.is_floating_point or int(t.min()) < 0 or int(t.max()) >= T:
        raise ValueError(f"t must be a (B,) = ({B},) integer tensor with values in [0, {T})")
    if noise is None:
        noise = torch.randn(x0.shape, generator=generator, device=x0.device, dtype=x0.dtype)
    elif noise.shape != x0.shape:
        raise ValueError(f"noise must have x0's shape {tuple(x0.shape)}, got {tuple(noise.shape)}")

    x_t = schedule.add_noise(x0, noise, t)
    target = schedule.training_target(x0, noise, t, prediction_type)
    out = denoiser(x_t, t, cond)
    if out.shape != x0.shape:
        raise ValueError(f"denoiser output shape {tuple(out.shape)} does not match x0 shape {tuple(x0.shape)}")
    mse_b = (out - target).pow(2).flatten(1).mean(dim=1)  # (B,)
    if weighting == "min_snr":
        w = min_snr_weight(schedule.snr(t), prediction_type, min_snr_gamma).to(mse_b.dtype)
        loss = (w * mse_b).mean()
    else:
        loss = mse_b.mean()

    quarter = (t * 4) // T
    if as_tensors:  # no host sync: 0-d tensors, NaN for a quarter no sample fell in
        m = mse_b.detach().float()
        sums = torch.zeros(4, device=m.device).index_add_(0, quarter, m)
        counts = torch.zeros(4, device=m.device).index_add_(0, quarter, torch.ones_like(m))
        means = sums / counts
        return loss, {"loss": loss.detach(), "mse": m.mean(), **{f"mse_q{q}": means[q] for q in range(4)}}
    logs = {"loss": float(loss.detach()), "mse": float(mse_b.detach().mean())}
    for q in range(4):
        sel = quarter == q
        if bool(sel.any()):
            logs[f"mse_q{q}"] = float(mse_b.detach()[sel].mean())
    return loss, logs
