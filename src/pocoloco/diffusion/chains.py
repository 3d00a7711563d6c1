"""Reverse chains that start part-way (SDEdit) or keep known points with resampling (RePaint):
what completion, editing and animation run on any method's :class:`~pocoloco.methods.base.PointPrior`.

Step convention: ``t`` is the 1-based step of the paper, ``1 <= t <= T``. A chain starts at the
samplers' 0-based timestep index ``t - 1``: ``t = 1`` is the least noisy step (one denoiser call at
abar_0 = 1 - beta_0), ``t = T`` means *pure noise*, exactly what the from-scratch samplers do (they
treat N(0, I) as x at index T - 1, although abar_{T-1} = 0.004 > 0 for the "four" schedule), so
``t = T`` forgets the source entirely.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from pocoloco.diffusion.sampler_base import PerSampleRNG, SamplerRun
from pocoloco.diffusion.samplers import SAMPLER_STEPS, check_sampler
from pocoloco.diffusion.schedules import NoiseSchedule

__all__ = ["chain_timesteps", "renoise", "repaint_resampling"]


def chain_timesteps(t: int, num_timesteps: int, sampler: str, steps: int | None = None) -> list[int]:
    """Descending timestep indices of a reverse chain that starts at step ``t`` (1-based, see the
    module docstring): ``steps`` of them with the samplers' "trailing" spacing over the first
    ``t`` indices, ``round(t - k t / steps) - 1`` for ``k = 0 .. steps-1`` (so the first is
    ``t - 1`` and, for ``t = T``, the list equals the from-scratch sampler's).

    ``steps=None``: every index for ddpm, else ``min(t, default)`` (dpm++ 20, ddim 50).
    """

    check_sampler(sampler, None, num_timesteps)
    if not 1 <= t <= num_timesteps:
        raise ValueError(f"t must be in [1, {num_timesteps}] (the model's training timesteps), got {t}")
    if steps is None:
        default = SAMPLER_STEPS[sampler]
        steps = t if default is None else min(t, default)
    if not 1 <= steps <= t:
        raise ValueError(f"steps must be in [1, t={t}] for a chain starting at step t, got {steps}")
    ts = np.round(t - np.arange(steps) * (t / steps)).astype(np.int64) - 1
    return [int(x) for x in ts]


def renoise(schedule: NoiseSchedule, x0: Any, noise: torch.Tensor, t: int) -> torch.Tensor:
    """SDEdit's start (Meng et al. 2022): ``x_t ~ q(x_t | x0) = N(sqrt(abar) x0, (1 - abar) I)`` at
    index ``t - 1`` (DDPM eq. 4), with ``noise`` (B, N, C) as the Gaussian draw; x0 (B, N, C) in the
    normalised frame. Returns the state in ``noise``'s dtype."""
    ab = schedule.alpha_bar(t - 1)
    x = math.sqrt(ab) * torch.as_tensor(x0, dtype=torch.float64, device=noise.device) + math.sqrt(1 - ab) * noise.double()
    return x.to(noise.dtype)


def repaint_resampling(model: torch.nn.Module, schedule: NoiseSchedule, noise: torch.Tensor, cond: Any,
                       timesteps: list[int], rng: PerSampleRNG | None, prediction_type: str | None,
                       known: tuple[torch.Tensor, torch.Tensor] | None, resample: int,
                       jump: int) -> torch.Tensor:  # fmt: skip
    """Ancestral DDPM over ``timesteps`` (descending) with RePaint's resampling (Lugmayr et al.
    2022, Algorithm 1): the chain is cut into segments of ``jump`` steps; each segment is run,
    then the state is diffused back to the segment's start with q(x_a | x_b) (all points; the
    known ones are then re-imposed at a) and the segment is run again, ``resample`` passes in all.
    noise: (B, N, C) the state at ``timesteps[0]``; returns (B, N, C) in noise.dtype.
    Denoiser calls: ``len(timesteps) * resample``.
    """

    run = SamplerRun(model, schedule, noise, cond, prediction_type, list(timesteps), None, rng, known, None)
    x = run.start(noise)
    S = len(run.timesteps)
    for a in range(0, S, jump):
        b = min(a + jump, S)
        for rep in range(resample):
            for i in range(a, b):  # ancestral steps, as sample_ddpm
                x, _ = run.ancestral_step(x, i)
            if rep < resample - 1:  # jump back up from the segment's end b to its start a
                ratio = run.ab[a] / run.ab_prev[b - 1]
                x = ratio**0.5 * x + (1.0 - ratio) ** 0.5 * run.randn_like(x)
                x = run.impose_known(x, run.ab[a])
    return x.to(run.dtype)
