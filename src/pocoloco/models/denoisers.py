"""The denoiser networks PocoLoco can be trained with, by architecture name.

- ``"transformer"``: :class:`~pocoloco.models.pocoloco.PocoLocoDenoiser`, the paper's network
  (self-attention over the N point tokens: O(N^2) per layer).
- ``"latent"``: :class:`~pocoloco.models.latent.LatentDenoiser`, read / compute / write through M
  latent tokens (O(N M + M^2) per layer).

Both take ``forward(x (B, N, C), t (B,), joints (B, J, 3)) -> (B, N, C)`` and configs with the same
conventions (``point_channels``, ``num_joints``, ``replace``, ``to_dict``). What the output means
(noise, x0 or v) is the diffusion's business, not the network's: the training config's
``prediction_type``, handed to the loss and the samplers by the method.
"""

from __future__ import annotations

from typing import Any

from torch import nn

from pocoloco.models.latent import LatentDenoiser, LatentDenoiserConfig
from pocoloco.models.pocoloco import PocoLocoDenoiser, PocoLocoDenoiserConfig

__all__ = ["ARCHITECTURES", "build_denoiser", "denoiser_config_from_dict"]

#: architecture name -> (config class, network class)
ARCHITECTURES: dict[str, tuple[type, type[nn.Module]]] = {
    "transformer": (PocoLocoDenoiserConfig, PocoLocoDenoiser),
    "latent": (LatentDenoiserConfig, LatentDenoiser),
}


def _check(architecture: str) -> None:
    if architecture not in ARCHITECTURES:
        raise ValueError(f"unknown denoiser architecture {architecture!r}; choose one of: {', '.join(ARCHITECTURES)}")


def denoiser_config_from_dict(architecture: str, d: dict[str, Any]):
    """The denoiser config of ``architecture`` from its ``to_dict()`` (unknown keys: one-line error;
    an older checkpoint's legacy fields are dropped, :meth:`pocoloco.utils.config.Config.from_dict`)."""
    _check(architecture)
    return ARCHITECTURES[architecture][0].from_dict(d)


def build_denoiser(architecture: str, config: Any) -> nn.Module:
    """A fresh network of ``architecture`` (initialised from torch's global RNG)."""
    _check(architecture)
    cfg_cls, net_cls = ARCHITECTURES[architecture]
    if not isinstance(config, cfg_cls):
        raise ValueError(f"a {architecture} denoiser needs a {cfg_cls.__name__}, got {type(config).__name__}")
    return net_cls(config)
