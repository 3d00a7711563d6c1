"""Samplers for the discrete diffusion process: ancestral DDPM, DDIM, DPM-Solver++ (2M and 3M),
deterministic (ODE) or stochastic (SDE), and UniPC (:mod:`~pocoloco.diffusion.unipc`).

Every sampler is a pure function of ``(denoiser, schedule, noise, cond)`` plus options; the
network, the process (:class:`~pocoloco.diffusion.schedules.NoiseSchedule`) and the sampler are
separate pieces (as in EDM and diffusers). Shapes: ``noise`` / samples ``(B, N, C)`` (any
``(B, ...)`` works), timesteps passed to the denoiser ``(B,)`` int64 in ``[0, T)``. Every sampler
calls the denoiser exactly once per step (NFE = steps).

Conventions:

- The state is accumulated in float64; the denoiser sees ``x`` in ``noise.dtype`` and the
  result is returned in ``noise.dtype``.
- Timesteps: ``steps`` sampling steps are placed with the "trailing" spacing of Lin et al.
  2024 (Table 2) by default, ``round(T - k T / steps) - 1`` for ``k = 0 .. steps-1``, so the
  first step is always the noisiest training step ``T - 1``. ``"linspace"`` is DPM-Solver's
  ``linspace(0, T-1, steps+1)`` rounded, reversed, last (0) dropped. ``"karras"`` (even in
  sigma^(1/7), Karras et al. 2022) and ``"lambda"`` (even in log-SNR, Lu et al. 2022) run from
  T-1 down to t = 0 and put more steps at low noise. All match diffusers' schedulers with the same
  ``timestep_spacing`` / ``use_karras_sigmas`` / ``use_lu_lambdas``
  (:func:`~pocoloco.diffusion.sampler_base.make_timesteps`). An explicit descending ``timesteps``
  list overrides the spacing (e.g. ``range(99, -1, -1)`` to denoise from t = 99, as in pose
  editing).
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
from typing import Any, Literal

import numpy as np
import torch

from pocoloco.diffusion.sampler_base import (
    ALPHA_BAR_MIN,
    Denoiser,
    PerSampleRNG,
    ProgressFn,
    SamplerRun,
    half_log_snr,
    Spacing,
    StepInfo,
    make_noise,
    make_timesteps,
    resolve_timesteps,
)
from pocoloco.diffusion.schedules import NoiseSchedule, PredictionType
from pocoloco.diffusion.unipc import sample_unipc

__all__ = ["ALPHA_BAR_MIN", "SAMPLERS", "SAMPLER_STEPS", "Denoiser", "PerSampleRNG", "SamplerKind", "StepInfo",
           "check_sampler", "make_noise", "make_timesteps", "sample", "sample_ddim", "sample_ddpm", "sample_dpmpp",
           "sample_unipc"]  # fmt: skip

SamplerKind = Literal["ddpm", "ddim", "dpm++", "dpm++sde", "dpm++3m", "dpm++3msde", "unipc", "few-step"]

#: sampler names accepted by :func:`sample` (and ``pocoloco sample --sampler``) -> default number of
#: steps. ddpm is the ancestral sampler strided to 100 steps (``steps=1000`` is the paper's DDPM).
#: The default, dpm++sde (SDE-DPM-Solver++ 2M), takes 25 steps (25 network calls): for the shipped
#: `medium` model 10 steps are +13.7 % above DDPM-1000's Chamfer and 25 match it (+0.1 %) at ~75x
#: less time (BENCHMARKS.md, "Sampler steps for the shipped default"); ``--steps 10`` is the fast
#: setting. The deterministic DDIM / DPM++ are ~24 % worse (BENCHMARKS.md, "Few-step sampling"). The
#: deterministic higher-order solvers (unipc: UniPC-2 bh2; dpm++3m) reach their ODE's answer in ~10
#: steps, but that answer stays ~6-14 % above DDPM-1000; dpm++3msde (SDE-DPM-Solver++ 3M) is no
#: better than dpm++sde at <= 10 steps (BENCHMARKS.md, "Few-step samplers, <= 10 network calls").
#: few-step: the sampler of a distilled student (:mod:`~pocoloco.diffusion.few_step`, issue 42), 4 calls.
SAMPLER_STEPS: dict[str, int] = {"dpm++": 20, "dpm++sde": 25, "ddim": 50, "ddpm": 100, "unipc": 10, "dpm++3m": 15,
                                 "dpm++3msde": 25, "few-step": 4}  # fmt: skip


def check_sampler(sampler: str, steps: int | None, num_timesteps: int) -> None:
    """One-line ValueError unless ``sampler`` is known and ``steps`` (None = its default) fits in
    [1, num_timesteps]."""
    if sampler not in SAMPLER_STEPS:
        raise ValueError(f"unknown sampler {sampler!r}; choose one of: {', '.join(SAMPLER_STEPS)}")
    if steps is not None and not 1 <= steps <= num_timesteps:
        raise ValueError(f"steps must be in [1, {num_timesteps}] (the model's training timesteps), got {steps}")


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
    run = SamplerRun(denoiser, schedule, noise, cond, prediction_type,
               resolve_timesteps(schedule, steps, spacing, timesteps), clip, rng, known, progress)  # fmt: skip
    x = run.start(noise)
    for i in range(len(run.timesteps)):
        x, x0 = run.ancestral_step(x, i)
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
    renoise: float | None = None,
    spacing: Spacing = "trailing",
    timesteps: Sequence[int] | None = None,
    clip: float | None = None,
    rng: PerSampleRNG | torch.Generator | None = None,
    known: tuple[torch.Tensor, torch.Tensor] | None = None,
    progress: ProgressFn | None = None,
    end_at: int | None = None,
) -> torch.Tensor:
    """DDIM sampling (Song et al. 2021, eq. 12 and 16).

    x_s = sqrt(abar_s) x0_hat + sqrt(1 - abar_s - sigma^2) eps_hat + sigma z,
    sigma = eta sqrt((1 - abar_s) / (1 - abar_t)) sqrt(1 - abar_t / abar_s).
    eta = 0 is deterministic; eta = 1 equals strided ancestral DDPM. ``renoise`` r in [0, 1] sets
    sigma = r sqrt(1 - abar_s) instead (eta must stay 0): the share of fresh noise in the re-noised
    state, r = 1 the consistency models' multistep sampler (:mod:`~pocoloco.diffusion.few_step`).
    With ``clip``, eps_hat is re-derived from the clipped x0_hat (GLIDE; diffusers'
    ``use_clipped_model_output=True``). ``end_at``: stop at the state of that timestep (below the
    last visited one) instead of x0, e.g. to take a chain's last call separately (a distillation's
    gradient). Other arguments as in :func:`sample_ddpm`.
    """
    if eta < 0:
        raise ValueError(f"eta must be >= 0, got {eta}")
    if renoise is not None and not 0.0 <= renoise <= 1.0:
        raise ValueError(f"renoise must be in [0, 1], got {renoise}")
    if renoise is not None and eta:
        raise ValueError("give eta or renoise, not both")
    run = SamplerRun(denoiser, schedule, noise, cond, prediction_type,
               resolve_timesteps(schedule, steps, spacing, timesteps), clip, rng, known, progress)  # fmt: skip
    if end_at is not None:
        if not 0 <= int(end_at) < run.timesteps[-1]:
            raise ValueError(f"end_at must be in [0, {run.timesteps[-1]}), below the last timestep, got {end_at}")
        run.ab_prev[-1] = schedule.alpha_bar(int(end_at))
    x = run.start(noise)
    for i in range(len(run.timesteps)):
        ab_t, ab_s = run.ab[i], run.ab_prev[i]
        eps, x0 = run.model_eps_x0(x, i)
        if renoise is None:
            sigma = eta * ((1.0 - ab_s) / (1.0 - ab_t) * (1.0 - ab_t / ab_s)) ** 0.5
        else:
            sigma = renoise * (1.0 - ab_s) ** 0.5
        x = ab_s**0.5 * x0 + max(1.0 - ab_s - sigma**2, 0.0) ** 0.5 * eps
        if sigma > 0:
            x = x + sigma * run.randn_like(x)
        x = run.impose_known(x, ab_s)
        run.report(i, x, x0)
    return x.to(run.dtype)


#: below this many steps DPM-Solver++(3M) drops to second order on its second-to-last step, as
#: diffusers' ``lower_order_final`` does ("stabilises sampling for steps < 15")
LOWER_ORDER_BELOW = 15


def dpmpp_coefficients(h: float, eta: float, d2: str = "exact") -> tuple[float, float, float, float]:
    """(A, c0, c1, c2) of one DPM-Solver++ step in half log-SNR from lambda_t to lambda_s = lambda_t + h:
    ``x_s = A (sigma_s / sigma_t) x_t + alpha_s (c0 D0 + c1 D1 + c2 D2)`` (+ noise if eta > 0).

    The data-prediction exponential integrator (Lu et al. 2022, DPM-Solver++ eq. 8-9) is
    ``x_s = (sigma_s / sigma_t) x_t + alpha_s int_0^h e^{-(h-u)} x0(u) du`` for the ODE (eta = 0) and,
    for the SDE (eta = 1; same paper, Appendix; Gonzalez et al. 2023), ``(sigma_s / sigma_t) e^{-h} x_t
    + 2 alpha_s int_0^h e^{-2(h-u)} x0(u) du + sigma_s sqrt(1 - e^{-2h}) z``; in general (the family
    of k-diffusion's ``eta``) ``(sigma_s / sigma_t) e^{-eta h} x_t + (1 + eta) alpha_s
    int_0^h e^{-(1 + eta)(h-u)} x0(u) du + sigma_s sqrt(1 - e^{-2 eta h}) z``, which keeps the
    marginals for any eta >= 0. Expanding x0 to second order, x0(u) = D0 + D1 u / h + D2 u^2 / h^2
    (D1 = h x0', D2 = h^2 x0'' / 2), gives with H = (1 + eta) h and phi2(H) = (H - 1 + e^{-H}) / H^2:
    c0 = 1 - e^{-H}, c1 = 1 - c0 / H, c2 = 1 - 2 phi2(H) ("exact", the integral of the quadratic),
    or c2 = 1/2 - phi2(H) ("half": the coefficient of Lu et al.'s multistep third-order code and
    of diffusers' DPMSolverMultistepScheduler(solver_order=3), and k-diffusion's 3M SDE, which
    amounts to taking D2 = h^2 x0'' instead of h^2 x0'' / 2; it leaves the step second order).
    """
    H = (1.0 + eta) * h
    c0 = -float(np.expm1(-H))
    c1 = 1.0 - c0 / H
    phi2 = (H - c0) / H**2
    if d2 == "exact":
        c2 = 1.0 - 2.0 * phi2
    elif d2 == "half":
        c2 = 0.5 - phi2
    else:
        raise ValueError(f"d2 must be 'exact' or 'half', got {d2!r}")
    return float(np.exp(-eta * h)), c0, c1, c2


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
    eta: float = 1.0,
    d2: Literal["exact", "half"] = "exact",
    spacing: Spacing = "trailing",
    timesteps: Sequence[int] | None = None,
    clip: float | None = None,
    rng: PerSampleRNG | torch.Generator | None = None,
    known: tuple[torch.Tensor, torch.Tensor] | None = None,
    progress: ProgressFn | None = None,
) -> torch.Tensor:
    """DPM-Solver++(2M / 3M), multistep, data-prediction form (Lu et al. 2022, Algorithm 2 and
    Appendix), or its SDE variant SDE-DPM-Solver++(2M / 3M) (diffusers' "sde-dpmsolver++").

    With alpha = sqrt(abar), sigma = sqrt(1 - abar), lambda = log(alpha / sigma),
    h = lambda_s - lambda_t and the x0 estimates m0, m1, m2 of this step and the two before
    (h0, h1 their lambda gaps, r0 = h0 / h, r1 = h1 / h):

    - order 1 (DDIM, and every first step): D0 = m0.
    - order 2 (2M, "midpoint"): ``x_s = (sigma_s / sigma_t) x_t + alpha_s c0 (D0 + D1 / 2)``,
      D1 = (m0 - m1) / r0.
    - order 3 (3M): ``x_s = (sigma_s / sigma_t) x_t + alpha_s (c0 D0 + c1 D1 + c2 D2)`` with the
      quadratic through m0, m1, m2 in lambda: D1 = D1_0 + r0 / (r0 + r1) (D1_0 - D1_1),
      D2 = (D1_0 - D1_1) / (r0 + r1), D1_0 = (m0 - m1) / r0, D1_1 = (m1 - m2) / r1; coefficients
      from :func:`dpmpp_coefficients` (``d2`` chooses c2: "exact" or diffusers' "half").

    ``stochastic=True`` integrates the reverse SDE instead (same D's, coefficients of H = 2h, and
    ``x_s`` gains the factor e^{-h} on x_t and ``+ sigma_s sqrt(1 - e^{-2h}) z``, z ~ N(0, I) from
    ``rng``); like ancestral DDPM it re-injects noise, which corrects an imperfect denoiser's
    errors instead of carrying them along the ODE. ``eta`` (stochastic only) scales the noise
    between the ODE (0) and the SDE (1, default) or beyond (H = (1 + eta) h, factor e^{-eta h},
    noise sigma_s sqrt(1 - e^{-2 eta h}); :func:`dpmpp_coefficients`). The order ramps up over the first steps (one x0
    estimate more per step); with fewer than 15 steps the second-to-last step is at most second
    order (diffusers' ``lower_order_final``). The last step goes to sigma = 0 and returns x0_hat
    ("final_sigmas_type='zero'" in diffusers, which also makes it first order). An abar of
    exactly 0 is replaced by ALPHA_BAR_MIN so lambda stays finite. In the ODE form ``rng`` is only
    used for the known points' noise.

    Note: diffusers 0.42's "sde-dpmsolver++" with solver_order=3 has the sign of the 1/2 in its
    D2 coefficient flipped (-1/2 - phi2(2h) instead of 1/2 - phi2(2h)); the 3M SDE here is
    therefore checked against a slow reference, not against diffusers.
    Other arguments as in :func:`sample_ddpm`.
    """
    if order not in (1, 2, 3):
        raise ValueError(f"order must be 1, 2 or 3, got {order}")
    if d2 not in ("exact", "half"):
        raise ValueError(f"d2 must be 'exact' or 'half', got {d2!r}")
    if not eta >= 0:
        raise ValueError(f"eta must be >= 0, got {eta}")
    eta = float(eta) if stochastic else 0.0
    run = SamplerRun(denoiser, schedule, noise, cond, prediction_type,
                     resolve_timesteps(schedule, steps, spacing, timesteps), clip, rng, known, progress)  # fmt: skip
    n, lam = len(run.timesteps), run.lam
    x = run.start(noise)
    hist: list[torch.Tensor] = []  # x0 estimates, newest last
    for i in range(n):
        _, x0 = run.model_eps_x0(x, i)
        hist = [*hist[-2:], x0]
        ab_s = run.ab_prev[i]
        if ab_s >= 1.0:  # final step to sigma = 0
            x = x0
        else:
            a_s, s_s, s_t = ab_s**0.5, (1.0 - ab_s) ** 0.5, (1.0 - run.ab[i]) ** 0.5
            h = half_log_snr(ab_s) - lam[i]
            p = min(order, len(hist), 2 if (i == n - 2 and n < LOWER_ORDER_BELOW) else order)
            A, c0, c1, c2 = dpmpp_coefficients(h, eta, d2)
            if p == 1:
                update = c0 * x0
            elif p == 2:
                r0 = (lam[i] - lam[i - 1]) / h
                update = c0 * (x0 + (0.5 / r0) * (x0 - hist[-2]))
            else:
                r0, r1 = (lam[i] - lam[i - 1]) / h, (lam[i - 1] - lam[i - 2]) / h
                d1_0, d1_1 = (x0 - hist[-2]) / r0, (hist[-2] - hist[-3]) / r1
                dd2 = (d1_0 - d1_1) / (r0 + r1)
                update = c0 * x0 + c1 * (d1_0 + r0 * dd2) + c2 * dd2
            x = (A * s_s / s_t) * x + a_s * update
            if eta > 0:
                x = x + (s_s * (-np.expm1(-2.0 * eta * h)) ** 0.5) * run.randn_like(x)
        x = run.impose_known(x, ab_s)
        run.report(i, x, x0)
    return x.to(run.dtype)


#: sampler kind -> (function, preset keyword arguments); :func:`sample`'s keywords override presets
SAMPLERS: dict[str, tuple[Callable[..., torch.Tensor], dict[str, Any]]] = {
    "ddpm": (sample_ddpm, {}),
    "ddim": (sample_ddim, {}),
    "dpm++": (sample_dpmpp, {}),
    "dpm++sde": (sample_dpmpp, {"stochastic": True}),
    "dpm++3m": (sample_dpmpp, {"order": 3}),
    "dpm++3msde": (sample_dpmpp, {"order": 3, "stochastic": True}),
    "unipc": (sample_unipc, {}),
    "few-step": (sample_ddim, {"steps": 4, "renoise": 0.0}),  # a distilled student's (diffusion.few_step)
}


def sample(
    kind: SamplerKind,
    denoiser: Denoiser,
    schedule: NoiseSchedule,
    noise: torch.Tensor,
    cond: Any = None,
    **kwargs: Any,
) -> torch.Tensor:
    """Dispatch to the sampler named ``kind`` (:data:`SAMPLERS`): :func:`sample_ddpm` ("ddpm"),
    :func:`sample_ddim` ("ddim"), :func:`sample_dpmpp` ("dpm++"; "dpm++sde" = ``stochastic=True``;
    "dpm++3m" / "dpm++3msde" = ``order=3``), :func:`sample_unipc` ("unipc") or
    :func:`sample_ddim` on a student's grid with ``renoise`` ("few-step", :mod:`~pocoloco.diffusion.few_step`); keyword arguments are
    forwarded and override the kind's presets."""
    if kind not in SAMPLERS:
        raise ValueError(f"unknown sampler kind {kind!r} (expected one of {sorted(SAMPLERS)})")
    fn, preset = SAMPLERS[kind]
    return fn(denoiser, schedule, noise, cond, **{**preset, **kwargs})
