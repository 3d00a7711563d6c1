"""Samplers for the discrete diffusion process: ancestral DDPM, DDIM and DPM-Solver++ (2M),
deterministic (ODE) or stochastic (SDE).

Every sampler is a pure function of ``(denoiser, schedule, noise, cond)`` plus options; the
network, the process (:class:`~pocoloco.diffusion.schedules.NoiseSchedule`) and the sampler are
separate pieces (as in EDM and diffusers). Shapes: ``noise`` / samples ``(B, N, C)`` (any
``(B, ...)`` works), timesteps passed to the denoiser ``(B,)`` int64 in ``[0, T)``.

Conventions:

- The state is accumulated in float64; the denoiser sees ``x`` in ``noise.dtype`` and the
  result is returned in ``noise.dtype``.
- Timesteps: ``steps`` sampling steps are placed with the "trailing" spacing of Lin et al.
  2024 (Table 2) by default, ``round(T - k T / steps) - 1`` for ``k = 0 .. steps-1``, so the
  first step is always the noisiest training step ``T - 1``. ``"linspace"`` is DPM-Solver's
  ``linspace(0, T-1, steps+1)`` rounded, reversed, last (0) dropped. Both match diffusers'
  schedulers with the same ``timestep_spacing``. An explicit descending ``timesteps`` list
  overrides both (e.g. ``range(99, -1, -1)`` to denoise from t = 99, as in pose editing).
- Randomness: pass ``rng=PerSampleRNG(seeds)`` and build the initial noise with the *same*
  object (``noise = rng.randn((N, C))``): every sample then owns one ``torch.Generator`` whose
  stream continues through the sampler, so sample k is identical whatever the batch it is in
  (EDM2's ``StackedRandomGenerator``). A plain ``torch.Generator`` or ``None`` (global RNG) also
  work, without that guarantee.
- Inpainting / completion (RePaint, Lugmayr et al. 2022, without resampling): ``known=(mask,
  x0_known)`` with ``mask (B, N)`` bool and ``x0_known (B, N, C)``. Before the first step and
  after every step the known points are replaced by ``q(x_s | x0_known)`` at the new time ``s``
  (fresh noise each time; at the end they equal ``x0_known`` exactly).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import numpy as np
import torch

from pocoloco.diffusion.schedules import (
    PREDICTION_TYPES,
    NoiseSchedule,
    PredictionType,
    pred_to_eps_x0,
)

Spacing = Literal["trailing", "linspace"]
SamplerKind = Literal["ddpm", "ddim", "dpm++", "dpm++sde"]
#: What the samplers use instead of abar = 0 (a zero-terminal-SNR schedule, e.g. a last beta
#: of 1), as diffusers does for such schedules: keeps x0 = (x - sqrt(1-abar) eps) / sqrt(abar)
#: and DPM-Solver's log-SNR finite. Positive abar are used unchanged, so this is a no-op for the
#: built-in schedules (smallest abar at T = 1000: "four" 4.2e-3, "linear" 4.0e-5, "cosine" 2.4e-9).
ALPHA_BAR_MIN = 2.0**-24

#: sampler names accepted by :func:`sample` (and ``pocoloco sample --sampler``) -> default number of
#: steps. ddpm is the ancestral sampler strided to 100 steps (``steps=1000`` is the paper's DDPM).
#: The default, dpm++sde (SDE-DPM-Solver++ 2M, 25 steps), is within 4 % of DDPM-1000 at 28x less
#: time for the shipped model; the deterministic DDIM / DPM++ are ~24 % worse (BENCHMARKS.md,
#: "Few-step sampling").
SAMPLER_STEPS: dict[str, int] = {"dpm++": 20, "dpm++sde": 25, "ddim": 50, "ddpm": 100}


def check_sampler(sampler: str, steps: int | None, num_timesteps: int) -> None:
    """One-line ValueError unless ``sampler`` is known and ``steps`` (None = its default) fits in
    [1, num_timesteps]."""
    if sampler not in SAMPLER_STEPS:
        raise ValueError(f"unknown sampler {sampler!r}; choose one of: {', '.join(SAMPLER_STEPS)}")
    if steps is not None and not 1 <= steps <= num_timesteps:
        raise ValueError(f"steps must be in [1, {num_timesteps}] (the model's training timesteps), got {steps}")


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


def _randn_like(x: torch.Tensor, rng: PerSampleRNG | torch.Generator | None) -> torch.Tensor:
    if isinstance(rng, PerSampleRNG):
        return rng.randn_like(x)
    if rng is None:
        return torch.randn(x.shape, dtype=x.dtype, device=x.device)
    return torch.randn(x.shape, generator=rng, dtype=x.dtype, device=rng.device).to(x.device)


# -- timesteps ---------------------------------------------------------------------------------


def make_timesteps(num_train_timesteps: int, steps: int, spacing: Spacing = "trailing") -> list[int]:
    """Descending sampling timesteps in [0, T) (see the module docstring for the spacings).

    Example: T = 1000, steps = 50, "trailing" -> [999, 979, ..., 19].
    """
    T = int(num_train_timesteps)
    if not 1 <= steps <= T:
        raise ValueError(f"steps must be in [1, {T}], got {steps}")
    if spacing == "trailing":
        ts = np.round(T - np.arange(steps) * (T / steps)).astype(np.int64) - 1
    elif spacing == "linspace":
        ts = np.linspace(0, T - 1, steps + 1).round()[::-1][:-1].astype(np.int64)
    else:
        raise ValueError(f"unknown timestep spacing {spacing!r} (expected 'trailing' or 'linspace')")
    return [int(t) for t in ts]


def _resolve_timesteps(
    schedule: NoiseSchedule, steps: int | None, spacing: Spacing, timesteps: Sequence[int] | None
) -> list[int]:
    T = schedule.num_timesteps
    if timesteps is None:
        return make_timesteps(T, T if steps is None else steps, spacing)
    ts = [int(t) for t in timesteps]
    if not ts or any(not 0 <= t < T for t in ts) or any(a <= b for a, b in zip(ts, ts[1:], strict=False)):
        raise ValueError(f"timesteps must be a non-empty strictly decreasing sequence in [0, {T})")
    return ts


# -- shared machinery --------------------------------------------------------------------------


class _Run:
    """State shared by the three samplers: validation, denoiser calls, known points, progress."""

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
        # abar per step and the "previous" abar (1 after the last step), kept away from 0
        ab = [schedule.alpha_bar(t) or ALPHA_BAR_MIN for t in timesteps]
        self.ab, self.ab_prev = ab, [*ab[1:], 1.0]
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
        return _randn_like(x.to(self.dtype), self.rng).to(torch.float64)

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

    def start(self, noise: torch.Tensor) -> torch.Tensor:
        """The float64 initial state, known points noised to the first timestep with fresh noise
        (``noise`` may be a partially noised sample rather than pure noise, see ``timesteps``)."""
        return self.impose_known(noise.to(torch.float64), self.ab[0])

    def report(self, i: int, x: torch.Tensor, x0: torch.Tensor) -> None:
        if self.progress is not None:
            self.progress(StepInfo(i, len(self.timesteps), self.timesteps[i], x.to(self.dtype), x0.to(self.dtype)))


# -- samplers ----------------------------------------------------------------------------------


@torch.no_grad()
def sample_ddpm(
    denoiser: Denoiser,
    schedule: NoiseSchedule,
    noise: torch.Tensor,
    cond: Any = None,
    *,
    prediction_type: PredictionType | None = None,
    steps: int | None = None,
    spacing: Spacing = "trailing",
    timesteps: Sequence[int] | None = None,
    clip: float | None = None,
    rng: PerSampleRNG | torch.Generator | None = None,
    known: tuple[torch.Tensor, torch.Tensor] | None = None,
    progress: ProgressFn | None = None,
) -> torch.Tensor:
    """Ancestral DDPM sampling (Ho et al. 2020, Algorithm 2), posterior variance "fixed small".

    Each step draws x_s ~ q(x_s | x_t, x0_hat) (eq. 6-7) with s the next sampling timestep:
    mean = sqrt(abar_s) b / (1 - abar_t) x0_hat + sqrt(1 - b) (1 - abar_s) / (1 - abar_t) x_t,
    variance = b (1 - abar_s) / (1 - abar_t), with b = 1 - abar_t / abar_s (= beta_t when
    unstrided). ``steps=None`` runs all T steps as in the paper; a smaller ``steps`` strides
    the chain (= DDIM with eta = 1). No noise is added on the last step.

    Args:
        denoiser: see :class:`Denoiser`.
        schedule: the diffusion process.
        noise: (B, N, C) initial x_T ~ N(0, I).
        cond: conditioning passed to the denoiser.
        prediction_type: overrides ``denoiser.prediction_type`` (default "epsilon").
        steps, spacing, timesteps: which timesteps to visit (module docstring).
        clip: clamp x0_hat to [-clip, clip] (None: no clipping).
        rng: randomness for the ancestral noise (module docstring).
        known: (mask (B, N) bool, x0_known (B, N, C)) points to keep (inpainting).
        progress: called with a :class:`StepInfo` after every step.
    Returns:
        (B, N, C) samples in noise.dtype.
    """
    run = _Run(denoiser, schedule, noise, cond, prediction_type,
               _resolve_timesteps(schedule, steps, spacing, timesteps), clip, rng, known, progress)  # fmt: skip
    x = run.start(noise)
    for i in range(len(run.timesteps)):
        ab_t, ab_s = run.ab[i], run.ab_prev[i]
        _, x0 = run.model_eps_x0(x, i)
        b = 1.0 - ab_t / ab_s
        x = (ab_s**0.5 * b / (1.0 - ab_t)) * x0 + ((1.0 - b) ** 0.5 * (1.0 - ab_s) / (1.0 - ab_t)) * x
        if ab_s < 1.0:
            x = x + (b * (1.0 - ab_s) / (1.0 - ab_t)) ** 0.5 * run.randn_like(x)
        x = run.impose_known(x, ab_s)
        run.report(i, x, x0)
    return x.to(run.dtype)


@torch.no_grad()
def sample_ddim(
    denoiser: Denoiser,
    schedule: NoiseSchedule,
    noise: torch.Tensor,
    cond: Any = None,
    *,
    prediction_type: PredictionType | None = None,
    steps: int = 50,
    eta: float = 0.0,
    spacing: Spacing = "trailing",
    timesteps: Sequence[int] | None = None,
    clip: float | None = None,
    rng: PerSampleRNG | torch.Generator | None = None,
    known: tuple[torch.Tensor, torch.Tensor] | None = None,
    progress: ProgressFn | None = None,
) -> torch.Tensor:
    """DDIM sampling (Song et al. 2021, eq. 12 and 16).

    x_s = sqrt(abar_s) x0_hat + sqrt(1 - abar_s - sigma^2) eps_hat + sigma z,
    sigma = eta sqrt((1 - abar_s) / (1 - abar_t)) sqrt(1 - abar_t / abar_s).
    eta = 0 is deterministic; eta = 1 equals strided ancestral DDPM. With ``clip``, eps_hat is
    re-derived from the clipped x0_hat (GLIDE; diffusers' ``use_clipped_model_output=True``).
    Other arguments as in :func:`sample_ddpm`.
    """
    if eta < 0:
        raise ValueError(f"eta must be >= 0, got {eta}")
    run = _Run(denoiser, schedule, noise, cond, prediction_type,
               _resolve_timesteps(schedule, steps, spacing, timesteps), clip, rng, known, progress)  # fmt: skip
    x = run.start(noise)
    for i in range(len(run.timesteps)):
        ab_t, ab_s = run.ab[i], run.ab_prev[i]
        eps, x0 = run.model_eps_x0(x, i)
        sigma = eta * ((1.0 - ab_s) / (1.0 - ab_t) * (1.0 - ab_t / ab_s)) ** 0.5
        x = ab_s**0.5 * x0 + max(1.0 - ab_s - sigma**2, 0.0) ** 0.5 * eps
        if sigma > 0:
            x = x + sigma * run.randn_like(x)
        x = run.impose_known(x, ab_s)
        run.report(i, x, x0)
    return x.to(run.dtype)


@torch.no_grad()
def sample_dpmpp(
    denoiser: Denoiser,
    schedule: NoiseSchedule,
    noise: torch.Tensor,
    cond: Any = None,
    *,
    prediction_type: PredictionType | None = None,
    steps: int = 20,
    order: int = 2,
    stochastic: bool = False,
    spacing: Spacing = "trailing",
    timesteps: Sequence[int] | None = None,
    clip: float | None = None,
    rng: PerSampleRNG | torch.Generator | None = None,
    known: tuple[torch.Tensor, torch.Tensor] | None = None,
    progress: ProgressFn | None = None,
) -> torch.Tensor:
    """DPM-Solver++(2M), multistep, data-prediction form (Lu et al. 2022, Algorithm 2), or its
    SDE variant SDE-DPM-Solver++(2M) (same paper, Appendix; diffusers' "sde-dpmsolver++").

    With alpha = sqrt(abar), sigma = sqrt(1 - abar), lambda = log(alpha / sigma) and
    h = lambda_s - lambda_t:
    x_s = (sigma_s / sigma_t) x_t - alpha_s (e^{-h} - 1) (D0 + D1 / 2),
    D0 = x0_hat_t, D1 = (x0_hat_t - x0_hat_prev) h / h_prev (D1 = 0 for order 1 and for the first
    step). ``stochastic=True`` integrates the reverse SDE instead:
    x_s = (sigma_s / sigma_t) e^{-h} x_t + alpha_s (1 - e^{-2h}) (D0 + D1 / 2)
    + sigma_s sqrt(1 - e^{-2h}) z, z ~ N(0, I) from ``rng``; like ancestral DDPM it re-injects
    noise, which corrects an imperfect denoiser's errors instead of carrying them along the ODE.
    The last step goes to sigma = 0 and returns x0_hat ("final_sigmas_type='zero'" in
    diffusers, which also makes it first order). An abar of exactly 0 is replaced by
    ALPHA_BAR_MIN so lambda stays finite. In the ODE form ``rng`` is only used for the known
    points' noise.
    Other arguments as in :func:`sample_ddpm`.
    """
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order}")
    run = _Run(denoiser, schedule, noise, cond, prediction_type,
               _resolve_timesteps(schedule, steps, spacing, timesteps), clip, rng, known, progress)  # fmt: skip
    lam = [0.5 * np.log(ab / (1.0 - ab)) for ab in run.ab]
    x = run.start(noise)
    x0_last: torch.Tensor | None = None
    for i in range(len(run.timesteps)):
        _, x0 = run.model_eps_x0(x, i)
        ab_s = run.ab_prev[i]
        if ab_s >= 1.0:  # final step to sigma = 0
            x = x0
        else:
            a_s, s_s, s_t = ab_s**0.5, (1.0 - ab_s) ** 0.5, (1.0 - run.ab[i]) ** 0.5
            h = lam[i + 1] - lam[i]
            d = x0
            if order == 2 and x0_last is not None:
                r = (lam[i] - lam[i - 1]) / h
                d = x0 + (0.5 / r) * (x0 - x0_last)
            if stochastic:
                x = (s_s / s_t * np.exp(-h)) * x + (-a_s * np.expm1(-2.0 * h)) * d
                x = x + (s_s * (-np.expm1(-2.0 * h)) ** 0.5) * run.randn_like(x)
            else:
                x = (s_s / s_t) * x + (-a_s * np.expm1(-h)) * d
        x0_last = x0
        x = run.impose_known(x, ab_s)
        run.report(i, x, x0)
    return x.to(run.dtype)


def sample(
    kind: SamplerKind,
    denoiser: Denoiser,
    schedule: NoiseSchedule,
    noise: torch.Tensor,
    cond: Any = None,
    **kwargs: Any,
) -> torch.Tensor:
    """Dispatch to :func:`sample_ddpm` ("ddpm"), :func:`sample_ddim` ("ddim") or
    :func:`sample_dpmpp` ("dpm++", "dpm++sde" = ``stochastic=True``); keyword arguments are
    forwarded."""
    samplers = {"ddpm": sample_ddpm, "ddim": sample_ddim, "dpm++": sample_dpmpp, "dpm++sde": sample_dpmpp}
    if kind not in samplers:
        raise ValueError(f"unknown sampler kind {kind!r} (expected one of {sorted(samplers)})")
    if kind == "dpm++sde":
        kwargs = {**kwargs, "stochastic": True}
    return samplers[kind](denoiser, schedule, noise, cond, **kwargs)
