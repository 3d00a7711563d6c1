"""PocoLoco: pose-conditioned point-cloud diffusion (presets, training task, sampling, the method)."""

from pocoloco.methods.pocoloco.config import (
           TRAIN_PRESETS,
           PocoLocoTrainConfig,
           train_preset,
)
from pocoloco.methods.pocoloco.method import (
           LoadedDenoiser,
           PocoLocoMethod,
           load_denoiser,
)
from pocoloco.methods.pocoloco.sampling import DEFAULT_CLIP, sample_clouds
from pocoloco.methods.pocoloco.training import PocoLocoTask

__all__ = ["DEFAULT_CLIP", "TRAIN_PRESETS", "LoadedDenoiser", "PocoLocoMethod", "load_denoiser", "PocoLocoTask", "PocoLocoTrainConfig", "sample_clouds",
           "train_preset"]
