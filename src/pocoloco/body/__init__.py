"""Body model adapter (anny), the fixed 24-joint skeleton, skinning; ``surface``:
UV rasterisation, position maps, barycentric sampling and local frames (POP/CloSET).

The skeleton constants import instantly; ``AnnyBody`` and friends load torch
and are imported on first use.
"""

from .skeleton import (
    ANNY_BONE_OF_JOINT,
    JOINT_NAMES,
    JOINT_PARENTS,
    NUM_JOINTS,
    joint_index,
)

__all__ = [
    "ANNY_BONE_OF_JOINT", "JOINT_NAMES", "JOINT_PARENTS", "NUM_JOINTS", "PHENOTYPE_KEYS",
    "AnnyBody", "PosedBody", "joint_index", "load_anny_model",
]
_LAZY = {"AnnyBody", "PosedBody", "PHENOTYPE_KEYS", "load_anny_model"}


def __getattr__(name: str):
    if name in _LAZY:
        from . import anny_body

        return getattr(anny_body, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
