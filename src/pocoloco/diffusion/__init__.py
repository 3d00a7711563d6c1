"""Gaussian diffusion for point clouds: beta schedules, the training loss and samplers.

- :mod:`~pocoloco.diffusion.schedules`: ``make_betas`` ("linear", PocoLoco's quartic "four",
  "cosine") and ``NoiseSchedule`` (forward process, posterior, eps/x0/v conversions).
- :mod:`~pocoloco.diffusion.loss`: ``diffusion_loss`` (L_simple, optional min-SNR-gamma).
- :mod:`~pocoloco.diffusion.samplers`: pure-function samplers ``sample_ddpm`` (the paper's
  1000-step ancestral sampler), ``sample_ddim``, ``sample_dpmpp`` (DPM-Solver++ 2M / 3M, ODE or
  SDE), ``sample_unipc`` (:mod:`~pocoloco.diffusion.unipc`) and the ``sample`` dispatcher.
- :mod:`~pocoloco.diffusion.sampler_base`: what they share: per-sample seeded noise
  (``PerSampleRNG``, ``make_noise``), timestep spacings (``make_timesteps``), ``SamplerRun``.
"""

from pocoloco.diffusion.loss import diffusion_loss, min_snr_weight
from pocoloco.diffusion.samplers import (
    ALPHA_BAR_MIN,
    SAMPLER_STEPS,
    SAMPLERS,
    Denoiser,
    PerSampleRNG,
    StepInfo,
    check_sampler,
    make_noise,
    make_timesteps,
    sample,
    sample_ddim,
    sample_ddpm,
    sample_dpmpp,
    sample_unipc,
)
from pocoloco.diffusion.schedules import PREDICTION_TYPES, NoiseSchedule, make_betas

__all__ = [
    "ALPHA_BAR_MIN",
    "PREDICTION_TYPES",
    "SAMPLERS",
    "SAMPLER_STEPS",
    "Denoiser",
    "NoiseSchedule",
    "PerSampleRNG",
    "StepInfo",
    "check_sampler",
    "diffusion_loss",
    "make_betas",
    "make_noise",
    "make_timesteps",
    "min_snr_weight",
    "sample",
    "sample_ddim",
    "sample_ddpm",
    "sample_dpmpp",
    "sample_unipc",
]
