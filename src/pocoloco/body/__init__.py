"""Body model adapter (anny), the fixed 24-joint skeleton, skinning."""

from .anny_body import PHENOTYPE_KEYS, AnnyBody, PosedBody, load_anny_model
from .skeleton import ANNY_BONE_OF_JOINT, JOINT_NAMES, JOINT_PARENTS, NUM_JOINTS, joint_index

__all__ = [
    "ANNY_BONE_OF_JOINT", "JOINT_NAMES", "JOINT_PARENTS", "NUM_JOINTS", "PHENOTYPE_KEYS",
    "AnnyBody", "PosedBody", "joint_index", "load_anny_model",
]
