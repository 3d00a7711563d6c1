"""Networks: the PocoLoco denoiser, its linear-in-N latent variant and shared layers (attention, encodings)."""

from pocoloco.models.latent import (
    LATENT_PRESETS,
    LatentDenoiser,
    LatentDenoiserConfig,
    latent_preset,
)
from pocoloco.models.layers import (
    attention,
    dense_attention,
    nerf_encoding,
    positional_encoding,
    positional_encoding_dim,
    timestep_embedding,
    transformer_encoding,
)
from pocoloco.models.pocoloco import (
    DENOISER_PRESETS,
    PocoLocoDenoiser,
    PocoLocoDenoiserConfig,
    denoiser_preset,
)

__all__ = [
    "DENOISER_PRESETS",
    "LATENT_PRESETS",
    "LatentDenoiser",
    "LatentDenoiserConfig",
    "PocoLocoDenoiser",
    "PocoLocoDenoiserConfig",
    "attention",
    "dense_attention",
    "denoiser_preset",
    "latent_preset",
    "nerf_encoding",
    "positional_encoding",
    "positional_encoding_dim",
    "timestep_embedding",
    "transformer_encoding",
]
