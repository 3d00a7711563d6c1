"""What every sampler shares: the denoiser protocol, per-sample seeded noise, sampling timesteps
(spacings) and :class:`SamplerRun`, the bookkeeping of one sampling run (validation, denoiser
calls in float64, x0 clipping, known points, progress).

The samplers themselves live in :mod:`~pocoloco.diffusion.samplers` (DDPM, DDIM, DPM-Solver++)
and :mod:`~pocoloco.diffusion.unipc` (UniPC); their conventions are described in the former's
module docstring. Shapes: ``noise`` / samples ``(B, N, C)`` (any ``(B, ...)`` works), timesteps
passed to the denoiser ``(B,)`` int64 in ``[0, T)``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import Any, Literal, Protocol

import numpy as np
import torch

from pocoloco.diffusion.schedules import (
    PREDICTION_TYPES,
    NoiseSchedule,
    PredictionType,
    pred_to_eps_x0,
)

__all__ = ["ALPHA_BAR_MIN", "KARRAS_RHO", "SPACINGS", "Denoiser", "PerSampleRNG", "ProgressFn", "SamplerRun", "Spacing",
           "StepInfo", "make_noise", "make_timesteps", "randn_like", "resolve_timesteps"]  # fmt: skip

Spacing = Literal["trailing", "linspace", "karras", "lambda"]
SPACINGS: tuple[str, ...] = ("trailing", "linspace", "karras", "lambda")
#: What the samplers use instead of abar = 0 (a zero-terminal-SNR schedule, e.g. a last beta
#: of 1), as diffusers does for such schedules: keeps x0 = (x - sqrt(1-abar) eps) / sqrt(abar)
#: and DPM-Solver's log-SNR finite. Positive abar are used unchanged, so this is a no-op for the
#: built-in schedules (smallest abar at T = 1000: "four" 4.2e-3, "linear" 4.0e-5, "cosine" 2.4e-9).
ALPHA_BAR_MIN = 2.0**-24
#: rho of the "karras" spacing (Karras et al. 2022, eq. 5; their value, also diffusers')
KARRAS_RHO = 7.0


class Denoiser(Protocol):
    """A network seen by the samplers: ``fn(x_t, t, cond) -> model output``.

    Args:
        x_t: (B, N, C) noisy points.
        t: (B,) int64 timesteps in [0, T).
        cond: conditioning (e.g. (B, J, 3) joints), passed through untouched; may be None.
    Returns:
        (B, N, C) prediction of the kind named by ``prediction_type`` ("epsilon", "sample" =
        x0, or "v_prediction"). A denoiser may declare it as a ``prediction_type`` attribute;
        the samplers' ``prediction_type`` argument overrides it.
    """

    def __call__(self, x_t: torch.Tensor, t: torch.Tensor, cond: Any) -> torch.Tensor: ...


@dataclass(frozen=True)
class StepInfo:
    """What the ``progress`` callback receives after each sampler step.

    Attributes:
        index: step index, 0-based.
        num_steps: total number of steps.
        t: the timestep the denoiser was evaluated at in this step.
        x: (B, N, C) the state after the step (in noise.dtype).
        x0_pred: (B, N, C) the denoiser's x0 estimate at this step (in noise.dtype).
    """

    index: int
    num_steps: int
    t: int
    x: torch.Tensor
    x0_pred: torch.Tensor


ProgressFn = Callable[[StepInfo], None]


# -- randomness --------------------------------------------------------------------------------


class PerSampleRNG:
    """One ``torch.Generator`` per sample, seeded by ``seeds`` (EDM2's StackedRandomGenerator).

    Draws for sample k only consume generator k, so sample k's noise does not depend on the
    batch it is in.
    """

    def __init__(self, seeds: Sequence[int], device: torch.device | str | None = None) -> None:
        seeds = [int(s) for s in seeds]
        if not seeds:
            raise ValueError("seeds must be a non-empty sequence of ints")
        self.seeds = tuple(seeds)
        self.device = torch.device(device if device is not None else "cpu")
        self.generators = [torch.Generator(self.device).manual_seed(s) for s in seeds]

    def __len__(self) -> int:
        return len(self.generators)

    def randn(
        self,
        shape_per_sample: Sequence[int],
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """Standard normal noise of shape (B, *shape_per_sample), B = len(seeds)."""
        shape = tuple(shape_per_sample)
        out = torch.stack([torch.randn(shape, generator=g, dtype=dtype, device=self.device) for g in self.generators])
        return out.to(device) if device is not None else out

    def randn_like(self, x: torch.Tensor) -> torch.Tensor:
        """Standard normal noise with x's shape (B, ...), dtype and device; B must be len(seeds)."""
        if x.shape[0] != len(self):
            raise ValueError(f"batch size {x.shape[0]} does not match the {len(self)} seeds of the RNG")
        return self.randn(x.shape[1:], dtype=x.dtype, device=x.device)


def make_noise(
    shape_per_sample: Sequence[int],
    seeds: Sequence[int],
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """(B, *shape_per_sample) standard normal noise, sample k drawn from a generator seeded seeds[k].

    Use :class:`PerSampleRNG` instead when the sampler is stochastic, so the initial noise and
    the sampler's noise come from one continuing stream per sample.
    """
    return PerSampleRNG(seeds, device).randn(shape_per_sample, dtype=dtype, device=device)


def randn_like(x: torch.Tensor, rng: PerSampleRNG | torch.Generator | None) -> torch.Tensor:
    """Standard normal noise shaped like ``x`` (its dtype and device) from ``rng``: a
    :class:`PerSampleRNG` (one stream per sample), a ``torch.Generator``, or None (torch's global one)."""
    if isinstance(rng, PerSampleRNG):
        return rng.randn_like(x)
    if rng is None:
        return torch.randn(x.shape, dtype=x.dtype, device=x.device)
    return torch.randn(x.shape, generator=rng, dtype=x.dtype, device=rng.device).to(x.device)


# -- timesteps ---------------------------------------------------------------------------------


def _sigma_spaced(alphas_cumprod: torch.Tensor | np.ndarray, steps: int, spacing: str) -> list[int]:
    """Timesteps at "karras" / "lambda" noise levels, rounded to the nearest training step.

    In the VE view sigma_t = sqrt((1 - abar_t) / abar_t) (= e^{-lambda_t}): "karras" places
    sigma_max^(1/rho) .. sigma_min^(1/rho) evenly (Karras et al. 2022, eq. 5, rho = 7), "lambda"
    places log sigma (minus the half log-SNR) evenly (Lu et al. 2022, sec. 3.3). sigma_max and
    sigma_min are those of t = T-1 and t = 0, so the first step is the noisiest training step
    and the last one t = 0. Each sigma is mapped to a fractional t by interpolating log sigma_t
    linearly in t and then rounded, as diffusers' ``use_karras_sigmas`` / ``use_lu_lambdas`` do;
    where rounding makes two timesteps equal (many steps), the later ones are pushed up by one so
    the list stays strictly decreasing.
    """
    abar = np.clip(np.asarray(torch.as_tensor(alphas_cumprod, dtype=torch.float64).cpu()), ALPHA_BAR_MIN, None)
    log_sigmas = 0.5 * np.log((1.0 - abar) / abar)  # (T,) increasing in t
    T = len(log_sigmas)
    if not np.all(np.diff(log_sigmas) > 0):
        raise ValueError("the 'karras' and 'lambda' spacings need alphas_cumprod strictly decreasing in t")
    ramp = np.linspace(0.0, 1.0, steps)
    lo, hi = log_sigmas[0], log_sigmas[-1]
    if spacing == "karras":
        s_min, s_max = np.exp(lo) ** (1.0 / KARRAS_RHO), np.exp(hi) ** (1.0 / KARRAS_RHO)
        target = KARRAS_RHO * np.log(s_max + ramp * (s_min - s_max))
    else:
        target = hi + ramp * (lo - hi)
    ts = np.round(np.interp(target, log_sigmas, np.arange(T, dtype=np.float64))).astype(np.int64)
    for i in range(steps - 2, -1, -1):  # strictly decreasing: push collisions up
        ts[i] = max(ts[i], ts[i + 1] + 1)
    if ts[0] > T - 1:
        raise ValueError(f"{steps} steps do not fit the {spacing!r} spacing of {T} training timesteps")
    return [int(t) for t in ts]


def half_log_snr(alpha_bar: float) -> float:
    """lambda = log(alpha / sigma) = 0.5 log(abar / (1 - abar)), the time variable of the
    DPM-Solver and UniPC updates (Lu et al. 2022, eq. 3); ``alpha_bar`` in (0, 1)."""
    return 0.5 * float(np.log(alpha_bar / (1.0 - alpha_bar)))


def make_timesteps(
    num_train_timesteps: int,
    steps: int,
    spacing: Spacing = "trailing",
    alphas_cumprod: torch.Tensor | np.ndarray | None = None,
) -> list[int]:
    """Descending sampling timesteps in [0, T).

    - "trailing" (Lin et al. 2024, Table 2): ``round(T - k T / steps) - 1``, k = 0 .. steps-1;
      T = 1000, steps = 50 -> [999, 979, ..., 19].
    - "linspace": DPM-Solver's ``linspace(0, T-1, steps+1)`` rounded, reversed, last (0) dropped.
    - "karras" / "lambda": even in sigma^(1/7) / in log-SNR, from t = T-1 down to t = 0 (see
      ``_sigma_spaced``); they put more steps at low noise and need ``alphas_cumprod`` (T,).

    All four match diffusers' schedulers (``timestep_spacing``, ``use_karras_sigmas``,
    ``use_lu_lambdas``) whenever rounding does not collide.
    """
    T = int(num_train_timesteps)
    if not 1 <= steps <= T:
        raise ValueError(f"steps must be in [1, {T}], got {steps}")
    if spacing == "trailing":
        ts = np.round(T - np.arange(steps) * (T / steps)).astype(np.int64) - 1
    elif spacing == "linspace":
        ts = np.linspace(0, T - 1, steps + 1).round()[::-1][:-1].astype(np.int64)
    elif spacing in ("karras", "lambda"):
        if alphas_cumprod is None or len(alphas_cumprod) != T:
            raise ValueError(f"the {spacing!r} spacing needs alphas_cumprod of length T = {T}")
        return _sigma_spaced(alphas_cumprod, steps, spacing)
    else:
        raise ValueError(f"unknown timestep spacing {spacing!r} (expected one of {', '.join(SPACINGS)})")
    return [int(t) for t in ts]


def resolve_timesteps(
    schedule: NoiseSchedule, steps: int | None, spacing: Spacing, timesteps: Sequence[int] | None
) -> list[int]:
    """The timesteps a sampler visits: an explicit strictly decreasing ``timesteps`` list in [0, T)
    if given, else ``make_timesteps`` with ``steps`` (None: all T) and ``spacing``."""
    T = schedule.num_timesteps
    if timesteps is None:
        return make_timesteps(T, T if steps is None else steps, spacing, schedule.alphas_cumprod)
    ts = [int(t) for t in timesteps]
    if not ts or any(not 0 <= t < T for t in ts) or any(a <= b for a, b in pairwise(ts)):
        raise ValueError(f"timesteps must be a non-empty strictly decreasing sequence in [0, {T})")
    return ts


# -- one sampling run --------------------------------------------------------------------------


class SamplerRun:
    """State shared by the samplers: validation, denoiser calls, known points, progress.

    Attributes (besides the arguments): ``timesteps`` (the visited steps), ``ab`` (abar at each,
    kept away from 0), ``ab_prev`` (abar of the next step, 1 after the last), ``lam`` (half
    log-SNR lambda = log(alpha / sigma) at each) and ``calls`` (denoiser calls so far).
    """

    def __init__(
        self,
        denoiser: Denoiser,
        schedule: NoiseSchedule,
        noise: torch.Tensor,
        cond: Any,
        prediction_type: PredictionType | None,
        timesteps: list[int],
        clip: float | None,
        rng: PerSampleRNG | torch.Generator | None,
        known: tuple[torch.Tensor, torch.Tensor] | None,
        progress: ProgressFn | None,
    ) -> None:
        if not isinstance(noise, torch.Tensor) or not noise.is_floating_point() or noise.ndim < 2:
            raise ValueError("noise must be a floating-point tensor of shape (B, N, C)")
        if prediction_type is None:
            prediction_type = getattr(denoiser, "prediction_type", "epsilon")
        if prediction_type not in PREDICTION_TYPES:
            raise ValueError(f"prediction_type must be one of {PREDICTION_TYPES}, got {prediction_type!r}")
        if clip is not None and not clip > 0:
            raise ValueError(f"clip must be positive or None, got {clip}")
        if isinstance(rng, PerSampleRNG) and len(rng) != noise.shape[0]:
            raise ValueError(f"rng has {len(rng)} seeds but noise has batch size {noise.shape[0]}")
        self.denoiser, self.schedule, self.cond = denoiser, schedule, cond
        self.prediction_type, self.clip, self.rng, self.progress = prediction_type, clip, rng, progress
        self.dtype, self.device = noise.dtype, noise.device
        self.timesteps = timesteps
        self.calls = 0
        # abar per step and the "previous" abar (1 after the last step), kept away from 0
        ab = [schedule.alpha_bar(t) or ALPHA_BAR_MIN for t in timesteps]
        self.ab, self.ab_prev = ab, [*ab[1:], 1.0]
        self.lam = [half_log_snr(a) for a in ab]
        self.mask = self.x0_known = None
        if known is not None:
            mask, x0k = known
            if mask.shape != noise.shape[:2] or mask.dtype != torch.bool:
                raise ValueError(f"known mask must be a bool tensor of shape {tuple(noise.shape[:2])}")
            if x0k.shape != noise.shape:
                raise ValueError(f"known x0 must have the noise's shape {tuple(noise.shape)}, got {tuple(x0k.shape)}")
            self.mask = mask.to(self.device).view(*mask.shape, *([1] * (noise.ndim - 2)))
            self.x0_known = x0k.to(device=self.device, dtype=torch.float64)

    def model_eps_x0(self, x: torch.Tensor, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Evaluate the denoiser at step i; return float64 (eps, x0), x0 clipped if asked."""
        t = torch.full((x.shape[0],), self.timesteps[i], dtype=torch.long, device=self.device)
        out = self.denoiser(x.to(self.dtype), t, self.cond)
        self.calls += 1
        if out.shape != x.shape:
            raise ValueError(f"denoiser output shape {tuple(out.shape)} does not match x shape {tuple(x.shape)}")
        a, s = self.ab[i] ** 0.5, (1.0 - self.ab[i]) ** 0.5
        eps, x0 = pred_to_eps_x0(out.to(torch.float64), x, a, s, self.prediction_type)
        if self.clip is not None:
            x0 = x0.clamp(-self.clip, self.clip)
            eps = (x - a * x0) / s
        return eps, x0

    def randn_like(self, x: torch.Tensor) -> torch.Tensor:
        """Fresh noise in the model dtype (so streams match diffusers'), returned as float64."""
        return randn_like(x.to(self.dtype), self.rng).to(torch.float64)

    def impose_known(self, x: torch.Tensor, ab: float, eps: torch.Tensor | None = None) -> torch.Tensor:
        """Replace the known points by q(x_s | x0_known) at abar_s = ab (exact x0 when ab == 1)."""
        if self.mask is None:
            return x
        if ab >= 1.0:
            noisy = self.x0_known
        else:
            eps = self.randn_like(x) if eps is None else eps
            noisy = ab**0.5 * self.x0_known + (1.0 - ab) ** 0.5 * eps
        return torch.where(self.mask, noisy, x)

    def ancestral_step(self, x: torch.Tensor, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        """One ancestral DDPM step from timesteps[i] to the next (Ho et al. 2020, eq. 6-7: the
        posterior mean from x0_hat, plus its variance's noise unless the next step is x0), known
        points re-imposed; returns (x_s, x0_hat)."""
        ab_t, ab_s = self.ab[i], self.ab_prev[i]
        _, x0 = self.model_eps_x0(x, i)
        b = 1.0 - ab_t / ab_s
        x = (ab_s**0.5 * b / (1.0 - ab_t)) * x0 + ((1.0 - b) ** 0.5 * (1.0 - ab_s) / (1.0 - ab_t)) * x
        if ab_s < 1.0:
            x = x + (b * (1.0 - ab_s) / (1.0 - ab_t)) ** 0.5 * self.randn_like(x)
        return self.impose_known(x, ab_s), x0

    def keep_known(self, x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        """x with the known points taken from ``ref`` (a state they were already imposed on)."""
        return x if self.mask is None else torch.where(self.mask, ref, x)

    def start(self, noise: torch.Tensor) -> torch.Tensor:
        """The float64 initial state, known points noised to the first timestep with fresh noise
        (``noise`` may be a partially noised sample rather than pure noise, see ``timesteps``)."""
        return self.impose_known(noise.to(torch.float64), self.ab[0])

    def report(self, i: int, x: torch.Tensor, x0: torch.Tensor) -> None:
        if self.progress is not None:
            self.progress(StepInfo(i, len(self.timesteps), self.timesteps[i], x.to(self.dtype), x0.to(self.dtype)))
