"""The few-step sampler of a distilled student (issue 42): 1, 2 or 4 network calls.

A student (:mod:`pocoloco.methods.pocoloco.distill`) is a denoiser whose x0 estimate at the
timesteps of its grid (the ``calls``-step "trailing" grid, e.g. 999, 749, 499, 249 for 4) is the
end of the teacher's deterministic sampling path through that state, i.e. a consistency function
(Song et al. 2023) learnt at a few times only. Sampling (Song et al. 2023, Algorithm 1, with the
re-noising of DDIM, Song et al. 2021, eq. 12)::

    x0 = f(x_T, T)
    for each later grid time s:   x_s = sqrt(abar_s) x0 + sqrt(1 - abar_s) (sqrt(1 - r^2) eps_hat + r z)
                                  x0  = f(x_s, s)

``eps_hat = (x_t - sqrt(abar_t) x0) / sqrt(1 - abar_t)`` is the noise the last state implies and
``z`` fresh noise: ``renoise`` r = 0 is deterministic (DDIM, eta 0: one answer per initial noise),
r = 1 the consistency models' multistep sampler (every step fresh noise). The grids of 1 and 2
calls are sub-grids of 4's (999; 999, 499), so one student trained on the 4-call grid samples with
1, 2 or 4 calls. The state is kept in float64 as in :mod:`pocoloco.diffusion.samplers`.
"""

from __future__ import annotations

from typing import Any

import torch

from pocoloco.diffusion.sampler_base import Denoiser, make_timesteps
from pocoloco.diffusion.samplers import sample_ddim
from pocoloco.diffusion.schedules import NoiseSchedule

__all__ = ["check_student_calls", "sample_few_step", "student_grid"]


def student_grid(num_timesteps: int, calls: int) -> list[int]:
    """The timesteps a student with ``calls`` network calls visits: the trailing grid
    ``round(T - k T / calls) - 1`` (T = 1000, 4 calls: [999, 749, 499, 249])."""
    return make_timesteps(num_timesteps, calls, "trailing")


def check_student_calls(calls: int, trained_calls: int, num_timesteps: int = 1000) -> None:
    """One-line ValueError unless ``calls`` network calls visit only timesteps the student was
    trained at (its grid of ``trained_calls``)."""
    trained = student_grid(num_timesteps, trained_calls)
    if not isinstance(calls, int) or calls < 1 or not set(student_grid(num_timesteps, calls)) <= set(trained):
        ok = [n for n in range(1, trained_calls + 1) if set(student_grid(num_timesteps, n)) <= set(trained)]
        raise ValueError(f"--steps {calls}: this distilled model was trained for {trained_calls} calls and samples "
                         f"with {', '.join(map(str, ok))} (its timesteps {trained})")  # fmt: skip


def sample_few_step(
    denoiser: Denoiser,
    schedule: NoiseSchedule,
    noise: torch.Tensor,
    cond: Any = None,
    *,
    steps: int = 4,
    renoise: float = 0.0,
    **kwargs: Any,
) -> torch.Tensor:
    """Few-step sampling with a distilled student (see the module docstring): DDIM's update
    (:func:`~pocoloco.diffusion.samplers.sample_ddim`) over the ``steps``-call trailing grid
    (:func:`student_grid`) with ``renoise`` r in [0, 1] of fresh noise in each re-noised state
    (0: deterministic). ``kwargs``: ``sample_ddim``'s (prediction_type, timesteps, clip, rng, known,
    progress). Returns (B, N, C) samples in ``noise.dtype``."""
    return sample_ddim(denoiser, schedule, noise, cond, steps=steps, renoise=renoise, **kwargs)
