"""Networks: the PocoLoco denoiser and shared layers (attention, positional encodings)."""

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
    "PocoLocoDenoiser",
    "PocoLocoDenoiserConfig",
    "attention",
    "dense_attention",
    "denoiser_preset",
    "nerf_encoding",
    "positional_encoding",
    "positional_encoding_dim",
    "timestep_embedding",
    "transformer_encoding",
]
