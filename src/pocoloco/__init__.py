"""pocoloco: point-cloud models of clothed humans in loose clothing.

The public API (imported on first use, so ``import pocoloco`` stays light)::

    import pocoloco

    model = pocoloco.load("default")               # PocoLoco trained on `medium`; "default:pop", a folder
    pose = pocoloco.Pose.load("demo:skirt_a")      # a shipped pose; a joints file, a dataset frame ...
    clouds = model.sample(pose, num_points=4096, seeds=[0, 1, 2])
    clouds.points.shape                            # (3, 4096, 3): three plausible garments, metres

- :func:`load`: any checkpoint as a :class:`~pocoloco.methods.Method` (PocoLoco, POP, CloSET, the hybrid).
- :class:`Pose`: one pose (:meth:`Pose.load`, :meth:`Pose.from_joints`).
- :meth:`Method.sample <pocoloco.methods.Method.sample>`: clouds for a pose, one per seed.
- :func:`write_ply`: a cloud (and its normals) as a PLY file.
"""

from __future__ import annotations

import importlib
import os
from typing import Any

__version__ = "0.1.0"

__all__ = ["Method", "Pose", "SampledClouds", "__version__", "load", "write_ply"]

#: public name -> the module it lives in (imported when first asked for, by name: the package's root
#: is no layer, and must not make every layer import the top ones)
_LAZY = {
    "Pose": "pocoloco.data.poses",
    "Method": "pocoloco.methods",
    "SampledClouds": "pocoloco.methods",
    "write_ply": "pocoloco.data.published",
}


def load(name_or_path: str | os.PathLike = "default", device: str = "cpu", use_ema: bool = True) -> "Method":  # noqa: F821
    """A trained model, ready to sample: ``"default"`` (the shipped PocoLoco), ``"default:pop"``,
    ``"default:closet"``, ``"default:hybrid"``, ``"default:fast"`` / ``"default:hybrid-fast"`` (4 network
    calls), or the path of a checkpoint, checkpoints or run
    folder (any method). ``device``: ``"cpu"``, ``"cuda"``, ...; ``use_ema``: the averaged weights
    (as trained models are evaluated) or the raw ones. A one-line ``ValueError`` for an unknown
    name, a missing or damaged checkpoint."""
    shipped = importlib.import_module("pocoloco.engine.shipped")
    methods = importlib.import_module("pocoloco.methods")
    return methods.load_method(shipped.resolve_ckpt_arg(os.fspath(name_or_path)), device=device, use_ema=use_ema)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'pocoloco' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
