"""The few-step sampler of a distilled student (issue 42): 1 to 4 network calls, and its teacher's finishing call.

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
r = 1 the consistency models' multistep sampler (every step fresh noise). A student trained on the
4-call grid samples with any 1 to 4 calls (:func:`sampling_grid`): its grid's first time, the next
ones, and its last (2 calls: 999, 249; 3: 999, 749, 249): ending at the least noisy time it knows
is worth more than the even spacing (2 calls on 999, 249: Chamfer x1.14 of the 25-call teacher on
quarter ``medium`` v3 test, on the trailing 999, 499: x1.29). The state is kept in float64 as in
:mod:`pocoloco.diffusion.samplers`.

**The teacher's finishing call** (``polish``): the student's clouds are right in the large but
fuzzy at the scale of a centimetre or two, where its teacher is at its best. SDEdit (Meng et al.
2022) at a low step does that last part: the student's x0 is re-noised to step ``t`` (1-based, as
the apps' chains; 5 of 1,000 by default, a noise of ~6 mm) with fresh noise and the *teacher*
gives its x0 estimate there, in one call (at a higher t its estimate, a posterior mean, smooths
the student's fuzz away but shrinks the cloud toward its inside). With ``calls`` >= 3 network
calls in all, the student spends ``calls - 1`` as above and the teacher the last
(:func:`polished_grid`: 4 calls = the student at 999, 749, 249, then the teacher).
"""

from __future__ import annotations

from typing import Any

import torch

from pocoloco.diffusion.sampler_base import Denoiser, PerSampleRNG, make_timesteps, randn_like
from pocoloco.diffusion.samplers import sample_ddim
from pocoloco.diffusion.schedules import NoiseSchedule

__all__ = ["allowed_calls", "check_student_calls", "polish", "polished_grid", "sample_few_step", "sampling_grid",
           "student_grid"]


def student_grid(num_timesteps: int, calls: int) -> list[int]:
    """The timesteps a student with ``calls`` network calls visits: the trailing grid
    ``round(T - k T / calls) - 1`` (T = 1000, 4 calls: [999, 749, 499, 249])."""
    return make_timesteps(num_timesteps, calls, "trailing")


def sampling_grid(num_timesteps: int, calls: int, trained_calls: int) -> list[int]:
    """The timesteps a student trained for ``trained_calls`` visits with ``calls`` (1 ..
    ``trained_calls``) of its own calls: its grid's first ``calls - 1`` times and its last (4-call
    student: 1 call [999], 2 [999, 249], 3 [999, 749, 249], 4 the whole grid)."""
    grid = student_grid(num_timesteps, trained_calls)
    if not isinstance(calls, int) or not 1 <= calls <= trained_calls:
        raise ValueError(f"calls must be in [1, {trained_calls}], got {calls}")
    return grid[:1] if calls == 1 else grid[: calls - 1] + grid[-1:]


def polished_grid(num_timesteps: int, calls: int, trained_calls: int) -> list[int] | None:
    """The student's timesteps when its teacher makes the last of ``calls`` network calls: its
    :func:`sampling_grid` of ``calls - 1`` (4 of a 4-call student: [999, 749, 249]; 5: the whole
    grid); None where the teacher does not finish (fewer than 3 calls in all, or more than the
    grid's + 1)."""
    if not isinstance(calls, int) or not 3 <= calls <= trained_calls + 1:
        return None
    return sampling_grid(num_timesteps, calls - 1, trained_calls)


def allowed_calls(trained_calls: int, polish: bool = False) -> list[int]:
    """The numbers of network calls a student of ``trained_calls`` samples with: 1 .. its grid,
    and with a finishing teacher (``polish``) one more."""
    return list(range(1, trained_calls + 1 + bool(polish)))


def check_student_calls(calls: int, trained_calls: int, num_timesteps: int = 1000, polish: bool = False) -> None:
    """One-line ValueError unless a student trained for ``trained_calls`` samples with ``calls``
    network calls (:func:`allowed_calls`)."""
    ok = allowed_calls(trained_calls, polish)
    if not isinstance(calls, int) or calls not in ok:
        trained = student_grid(num_timesteps, trained_calls)
        raise ValueError(f"--steps {calls}: this distilled model was trained for {trained_calls} calls and samples "
                         f"with {ok[0]} to {ok[-1]} (its timesteps {trained}"
                         f"{'; from 3 calls its teacher makes the last' if polish else ''})")  # fmt: skip


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


def polish(
    teacher: Denoiser,
    schedule: NoiseSchedule,
    x0: torch.Tensor,
    cond: Any,
    t: int,
    rng: PerSampleRNG | torch.Generator | None,
    *,
    prediction_type: str | None = None,
    clip: float | None = None,
) -> torch.Tensor:
    """The teacher's finishing call (module docstring): ``x0`` (B, N, C) re-noised to 1-based step
    ``t`` with ``rng``'s fresh noise, ``x_t = sqrt(abar) x0 + sqrt(1 - abar) z`` (DDPM eq. 4), and
    the teacher's x0 estimate there (one DDIM step to the end). Returns (B, N, C) in x0's dtype."""
    T = schedule.num_timesteps
    if not 1 <= int(t) <= T:
        raise ValueError(f"polish t must be in [1, {T}], got {t}")
    ab = schedule.alpha_bar(int(t) - 1)
    x = ab**0.5 * x0.double() + (1.0 - ab) ** 0.5 * randn_like(x0, rng).double()
    return sample_ddim(teacher, schedule, x.to(x0.dtype), cond, prediction_type=prediction_type,
                       timesteps=[int(t) - 1], clip=clip)  # fmt: skip
