"""Discrete-time Gaussian diffusion: beta schedules and the forward process.

The forward process of DDPM (Ho et al. 2020, eq. 4) is
``q(x_t | x_0) = N(sqrt(abar_t) x_0, (1 - abar_t) I)`` with ``abar_t = prod_{s<=t} (1 - beta_s)``
and timesteps indexed ``t = 0 .. T-1`` (index ``t`` is the paper's step ``t + 1``;
"``t = -1``" is the clean data, ``abar = 1``).

Everything here is shape-generic: data ``x`` is ``(B, ...)`` (in pocoloco ``(B, N, C)``:
batch, points, channels) and timesteps ``t`` are integer tensors of shape ``(B,)``.
Schedule tables are float64 on the CPU; per-sample coefficients are gathered in float64 and
cast to the data's dtype and device at the last moment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch

BetaKind = Literal["linear", "four", "cosine"]
PredictionType = Literal["epsilon", "sample", "v_prediction"]
PREDICTION_TYPES: tuple[str, ...] = ("epsilon", "sample", "v_prediction")


def make_betas(
    kind: BetaKind, T: int = 1000, beta_start: float = 1e-4, beta_end: float = 0.02
) -> torch.Tensor:
    """Return the (T,) float64 betas of a named schedule.

    - ``"linear"``: ``linspace(beta_start, beta_end, T)`` (Ho et al. 2020); abar_{T-1} ~ 4e-5.
    - ``"four"``: the quartic schedule of PocoLoco (the code's version; the paper's
      ``(t/10000)^4`` is a typo): ``linspace(beta_start**0.25, beta_end**0.25, T) ** 4``;
      abar_{T-1} ~ 0.004 at the defaults.
    - ``"cosine"``: Nichol & Dhariwal 2021, eq. 17, ``s = 0.008``, betas clipped at 0.999
      (``beta_start`` / ``beta_end`` are ignored).
    """
    if T < 1:
        raise ValueError(f"T must be >= 1, got {T}")
    if kind == "linear":
        return torch.linspace(beta_start, beta_end, T, dtype=torch.float64)
    if kind == "four":
        return torch.linspace(beta_start**0.25, beta_end**0.25, T, dtype=torch.float64) ** 4
    if kind == "cosine":
        s = 0.008
        steps = torch.arange(T + 1, dtype=torch.float64) / T
        abar = torch.cos((steps + s) / (1 + s) * math.pi / 2) ** 2
        return (1 - abar[1:] / abar[:-1]).clamp(max=0.999)
    raise ValueError(f"unknown beta schedule kind {kind!r} (expected 'linear', 'four' or 'cosine')")


def _check_prediction_type(prediction_type: str) -> None:
    if prediction_type not in PREDICTION_TYPES:
        raise ValueError(f"prediction_type must be one of {PREDICTION_TYPES}, got {prediction_type!r}")


@dataclass(frozen=True, eq=False)
class NoiseSchedule:
    """The tables of a discrete diffusion process with ``T = len(betas)`` steps (all (T,) float64).

    Build it with :meth:`from_betas` or :meth:`from_kind`.

    Attributes:
        betas: beta_t.
        alphas: 1 - beta_t.
        alphas_cumprod: abar_t = prod_{s<=t} alpha_s.
        alphas_cumprod_prev: abar_{t-1}, with abar_{-1} = 1.
        sqrt_alphas_cumprod: sqrt(abar_t).
        sqrt_one_minus_alphas_cumprod: sqrt(1 - abar_t).
        posterior_variance: variance of q(x_{t-1} | x_t, x_0), "fixed small" in Ho et al.
            (eq. 7): beta_t (1 - abar_{t-1}) / (1 - abar_t); zero at t = 0.
        posterior_log_variance_clipped: its log with the t = 0 entry replaced by the t = 1 one
            (finite everywhere, as in the DDPM reference code).
        posterior_mean_coef1: coefficient of x_0 in the posterior mean (eq. 7).
        posterior_mean_coef2: coefficient of x_t in the posterior mean (eq. 7).
    """

    betas: torch.Tensor
    alphas: torch.Tensor
    alphas_cumprod: torch.Tensor
    alphas_cumprod_prev: torch.Tensor
    sqrt_alphas_cumprod: torch.Tensor
    sqrt_one_minus_alphas_cumprod: torch.Tensor
    posterior_variance: torch.Tensor
    posterior_log_variance_clipped: torch.Tensor
    posterior_mean_coef1: torch.Tensor
    posterior_mean_coef2: torch.Tensor

    @classmethod
    def from_betas(cls, betas: torch.Tensor) -> NoiseSchedule:
        """Build every table from (T,) betas in (0, 1] (cast to float64 on the CPU)."""
        betas = torch.as_tensor(betas).detach().to(device="cpu", dtype=torch.float64)
        if betas.ndim != 1 or betas.numel() < 2:
            raise ValueError(f"betas must be a 1-D tensor with at least 2 entries, got shape {tuple(betas.shape)}")
        if not bool(((betas > 0) & (betas <= 1)).all()):
            raise ValueError("betas must all lie in (0, 1]")
        alphas = 1.0 - betas
        abar = torch.cumprod(alphas, dim=0)
        abar_prev = torch.cat([abar.new_ones(1), abar[:-1]])
        post_var = betas * (1.0 - abar_prev) / (1.0 - abar)
        post_log_var = torch.log(torch.cat([post_var[1:2], post_var[1:]]))
        return cls(
            betas=betas,
            alphas=alphas,
            alphas_cumprod=abar,
            alphas_cumprod_prev=abar_prev,
            sqrt_alphas_cumprod=abar.sqrt(),
            sqrt_one_minus_alphas_cumprod=(1.0 - abar).sqrt(),
            posterior_variance=post_var,
            posterior_log_variance_clipped=post_log_var,
            posterior_mean_coef1=betas * abar_prev.sqrt() / (1.0 - abar),
            posterior_mean_coef2=(1.0 - abar_prev) * alphas.sqrt() / (1.0 - abar),
        )

    @classmethod
    def from_kind(
        cls, kind: BetaKind = "four", T: int = 1000, beta_start: float = 1e-4, beta_end: float = 0.02
    ) -> NoiseSchedule:
        """``NoiseSchedule.from_betas(make_betas(kind, T, beta_start, beta_end))``."""
        return cls.from_betas(make_betas(kind, T, beta_start, beta_end))

    @property
    def num_timesteps(self) -> int:
        """T, the number of training timesteps."""
        return int(self.betas.shape[0])

    def alpha_bar(self, t: int) -> float:
        """abar_t as a Python float for one integer timestep; ``t = -1`` gives 1 (clean data)."""
        if not -1 <= t < self.num_timesteps:
            raise ValueError(f"timestep must be in [-1, {self.num_timesteps}), got {t}")
        return 1.0 if t < 0 else float(self.alphas_cumprod[t])

    # -- per-sample gathers ------------------------------------------------------------------

    def _check_t(self, t: torch.Tensor, x: torch.Tensor) -> None:
        if t.ndim != 1 or t.shape[0] != x.shape[0]:
            raise ValueError(f"t must have shape (B,) = ({x.shape[0]},), got {tuple(t.shape)}")
        if t.dtype.is_floating_point or t.dtype == torch.bool:
            raise ValueError(f"t must be an integer tensor, got {t.dtype}")

    @staticmethod
    def _gather(table: torch.Tensor, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """table[t] as (B, 1, ..., 1) broadcastable to ``like``, in like's dtype and device."""
        vals = table[t.detach().to("cpu", torch.long)]
        return vals.to(device=like.device, dtype=like.dtype).view(-1, *([1] * (like.ndim - 1)))

    def add_noise(self, x0: torch.Tensor, eps: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Sample q(x_t | x_0) (Ho et al. eq. 4): ``sqrt(abar_t) x0 + sqrt(1 - abar_t) eps``.

        Args:
            x0: (B, ...) clean data.
            eps: (B, ...) standard normal noise.
            t: (B,) integer timesteps in [0, T).
        Returns:
            (B, ...) noisy data x_t.
        """
        if x0.shape != eps.shape:
            raise ValueError(f"x0 and eps must have the same shape, got {tuple(x0.shape)} and {tuple(eps.shape)}")
        self._check_t(t, x0)
        return self._gather(self.sqrt_alphas_cumprod, t, x0) * x0 + self._gather(
            self.sqrt_one_minus_alphas_cumprod, t, x0
        ) * eps

    def snr(self, t: torch.Tensor) -> torch.Tensor:
        """Signal-to-noise ratio abar_t / (1 - abar_t): (B,) float64 on t's device."""
        abar = self.alphas_cumprod[t.detach().to("cpu", torch.long)]
        return (abar / (1.0 - abar)).to(t.device)

    def velocity(self, x0: torch.Tensor, eps: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """v = sqrt(abar_t) eps - sqrt(1 - abar_t) x0 (Salimans & Ho 2022, sec. 4): (B, ...)."""
        self._check_t(t, x0)
        return self._gather(self.sqrt_alphas_cumprod, t, x0) * eps - self._gather(
            self.sqrt_one_minus_alphas_cumprod, t, x0
        ) * x0

    def training_target(
        self, x0: torch.Tensor, eps: torch.Tensor, t: torch.Tensor, prediction_type: PredictionType
    ) -> torch.Tensor:
        """What a network of the given prediction type should output for (x0, eps, t): (B, ...)."""
        _check_prediction_type(prediction_type)
        if prediction_type == "epsilon":
            return eps
        if prediction_type == "sample":
            return x0
        return self.velocity(x0, eps, t)

    def pred_to_eps_x0(
        self,
        model_out: torch.Tensor,
        x_t: torch.Tensor,
        t: torch.Tensor,
        prediction_type: PredictionType,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Convert a network output at (x_t, t) into the implied (eps, x0), both (B, ...).

        epsilon: x0 = (x_t - sqrt(1-abar) eps) / sqrt(abar);
        sample:  eps = (x_t - sqrt(abar) x0) / sqrt(1-abar);
        v:       x0 = sqrt(abar) x_t - sqrt(1-abar) v,  eps = sqrt(abar) v + sqrt(1-abar) x_t.
        """
        _check_prediction_type(prediction_type)
        if model_out.shape != x_t.shape:
            raise ValueError(
                f"model output shape {tuple(model_out.shape)} does not match x_t shape {tuple(x_t.shape)}"
            )
        self._check_t(t, x_t)
        a = self._gather(self.sqrt_alphas_cumprod, t, x_t)
        s = self._gather(self.sqrt_one_minus_alphas_cumprod, t, x_t)
        return pred_to_eps_x0(model_out, x_t, a, s, prediction_type)


def pred_to_eps_x0(
    model_out: torch.Tensor,
    x_t: torch.Tensor,
    a: torch.Tensor | float,
    s: torch.Tensor | float,
    prediction_type: str,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(eps, x0) from a model output with a = sqrt(abar_t), s = sqrt(1 - abar_t) (scalars or broadcastable)."""
    if prediction_type == "epsilon":
        return model_out, (x_t - s * model_out) / a
    if prediction_type == "sample":
        return (x_t - a * model_out) / s, model_out
    if prediction_type == "v_prediction":
        return a * model_out + s * x_t, a * x_t - s * model_out
    raise ValueError(f"prediction_type must be one of {PREDICTION_TYPES}, got {prediction_type!r}")
