"""UniPC: a unified predictor-corrector multistep sampler (Zhao et al. 2023, "UniPC: A Unified
Predictor-Corrector Framework for Fast Sampling of Diffusion Models"), data-prediction form.

Conventions (timesteps, randomness, known points, float64 state) are those of
:mod:`~pocoloco.diffusion.samplers`. One denoiser call per step: the corrector UniC reuses the
model output the next predictor step needs anyway, so NFE = steps.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import torch

from pocoloco.diffusion.sampler_base import (
    Denoiser,
    PerSampleRNG,
    ProgressFn,
    SamplerRun,
    half_log_snr,
    Spacing,
    resolve_timesteps,
)
from pocoloco.diffusion.schedules import NoiseSchedule, PredictionType

__all__ = ["UniPCVariant", "sample_unipc", "unipc_rhos"]

UniPCVariant = Literal["bh1", "bh2"]


def unipc_rhos(h: float, rks: Sequence[float], variant: UniPCVariant) -> np.ndarray:
    """The UniPC weights a for ratios r_1 .. r_K (Zhao et al. 2023, Theorem 3.1 / eq. 8).

    In the data-prediction form (hh = -h), B(h) = hh ("bh1") or e^{hh} - 1 ("bh2"), and the
    weights solve R a = g / B(h) with R[i, k] = r_k^i (i = 0 .. K-1) and
    g_i = hh i! phi_{i+1}(hh) (i = 1 .. K), phi_1(z) = (e^z - 1) / z, phi_{k+1}(z) = (phi_k(z) - 1 / k!) / z.
    A single weight (K = 1) is 1/2, the limit h -> 0 of the solve, as in the authors' code.

    Returns:
        (K,) float64 weights.
    """
    K = len(rks)
    if K == 1:
        return np.array([0.5])
    hh = -float(h)
    if variant == "bh1":
        B = hh
    elif variant == "bh2":
        B = float(np.expm1(hh))
    else:
        raise ValueError(f"variant must be 'bh1' or 'bh2', got {variant!r}")
    phi, fact, g = float(np.expm1(hh)) / hh, 1.0, []
    for i in range(1, K + 1):
        phi = (phi - 1.0 / fact) / hh  # phi_{i+1}
        g.append(hh * fact * phi)  # fact = i!
        fact *= i + 1
    R = np.vander(np.asarray(rks, dtype=np.float64), K, increasing=True).T  # R[i, k] = r_k^i
    return np.linalg.solve(R, np.asarray(g) / B)


def _unipc_update(
    x_s: torch.Tensor,
    m: list[torch.Tensor],
    lams: list[float],
    lam_t: float,
    ab_t: float,
    ab_s: float,
    order: int,
    variant: UniPCVariant,
    m_t: torch.Tensor | None = None,
) -> torch.Tensor:
    """One UniP-p step (``m_t`` None) or UniC-p correction (``m_t`` the x0 estimate at the end point)
    from lambda_s = lams[-1] to lambda_t, in data prediction (Zhao et al. 2023, Algorithm 2):

    x_t = (sigma_t / sigma_s) x_s - alpha_t (e^{-h} - 1) m_s - alpha_t B(h) sum_k a_k D_k,
    D_k = (m_{s-k} - m_s) / r_k, r_k = (lambda_{s-k} - lambda_s) / h for k = 1 .. p-1 (UniP), plus
    D_p = m_t - m_s with r_p = 1 for UniC (which solves for p weights instead of p-1).
    m and lams: x0 estimates and lambdas of the steps so far, newest (s) last.
    """
    h = lam_t - lams[-1]
    a_t, s_t, s_s = ab_t**0.5, (1.0 - ab_t) ** 0.5, (1.0 - ab_s) ** 0.5
    x = (s_t / s_s) * x_s - (a_t * float(np.expm1(-h))) * m[-1]
    rks = [(lams[-1 - k] - lams[-1]) / h for k in range(1, order)]
    ds = [(m[-1 - k] - m[-1]) / r for k, r in zip(range(1, order), rks, strict=True)]
    if m_t is not None:
        rks, ds = [*rks, 1.0], [*ds, m_t - m[-1]]
    if not ds:
        return x
    B = -h if variant == "bh1" else float(np.expm1(-h))
    rhos = unipc_rhos(h, rks, variant)
    return x - (a_t * B) * sum(float(r) * d for r, d in zip(rhos, ds, strict=True))


@torch.no_grad()
def sample_unipc(
    denoiser: Denoiser,
    schedule: NoiseSchedule,
    noise: torch.Tensor,
    cond: Any = None,
    *,
    prediction_type: PredictionType | None = None,
    steps: int = 10,
    order: int = 2,
    variant: UniPCVariant = "bh2",
    spacing: Spacing = "trailing",
    timesteps: Sequence[int] | None = None,
    clip: float | None = None,
    rng: PerSampleRNG | torch.Generator | None = None,
    known: tuple[torch.Tensor, torch.Tensor] | None = None,
    progress: ProgressFn | None = None,
) -> torch.Tensor:
    """UniPC-p (Zhao et al. 2023): multistep predictor UniP-p plus corrector UniC-p, data
    prediction, B(h) of ``variant`` ("bh2", e^{-h} - 1, recommended by the authors for >= 10
    steps; "bh1", -h, for fewer). Deterministic (an ODE solver).

    Step i evaluates the denoiser once at the predicted x_i, then (i > 0) corrects x_i with UniC of
    the previous step's order using that same output (the output is not re-evaluated at the
    corrected point, so NFE = steps), then predicts x_{i+1} from the corrected x_i with UniP of
    order min(order, i + 1, steps - i) (warm-up, and lower orders at the end as diffusers'
    ``lower_order_final``). The last step goes to sigma = 0 and returns x0_hat; it is not
    corrected. ``progress`` sees the predicted (uncorrected) states, as diffusers' ``prev_sample``.
    Matches diffusers' ``UniPCMultistepScheduler(predict_x0=True, solver_type=variant)``. Known
    points are imposed on the predicted state; the corrector keeps them. Other arguments as in
    :func:`~pocoloco.diffusion.samplers.sample_ddpm`.
    """
    if order not in (1, 2, 3):
        raise ValueError(f"order must be 1, 2 or 3, got {order}")
    if variant not in ("bh1", "bh2"):
        raise ValueError(f"variant must be 'bh1' or 'bh2', got {variant!r}")
    run = SamplerRun(denoiser, schedule, noise, cond, prediction_type,
                     resolve_timesteps(schedule, steps, spacing, timesteps), clip, rng, known, progress)  # fmt: skip
    n = len(run.timesteps)
    x = run.start(noise)
    ms: list[torch.Tensor] = []  # x0 estimates, newest last
    x_s, p_prev = x, 0  # the corrected state of the previous step and its predictor order
    for i in range(n):
        _, m_t = run.model_eps_x0(x, i)
        if i > 0:  # UniC: correct x_i with the output at the predicted x_i
            x_c = _unipc_update(x_s, ms, run.lam[:i], run.lam[i], run.ab[i], run.ab[i - 1], p_prev, variant, m_t)
            x = run.keep_known(x_c, x)
        ms = [*ms[-(order - 1) :], m_t] if order > 1 else [m_t]
        p = min(order, i + 1, n - i)
        x_s, p_prev = x, p
        ab_s = run.ab_prev[i]
        if ab_s >= 1.0:  # final step to sigma = 0
            x = m_t
        else:
            x = _unipc_update(x, ms, run.lam[: i + 1], half_log_snr(ab_s), ab_s, run.ab[i], p, variant)
        x = run.impose_known(x, ab_s)
        run.report(i, x, m_t)
    return x.to(run.dtype)
