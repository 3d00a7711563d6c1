"""The one fixed skeleton every model in pocoloco is conditioned on.

24 joints in the SMPL order the papers use (PocoLoco conditions on the 3D
positions of these joints; POP/CloSET on the posed body). Each joint is the
*head* of one bone of the anny rig (``anny.Anny().bone_labels``), so joint
positions are ``bone_poses[..., :3, 3]`` of that bone.

Coordinates everywhere in pocoloco: metres, **Z up**, the body faces **-Y**
in its rest pose, +X is the body's left. The root (pelvis) is joint 0.
"""

from __future__ import annotations

JOINT_NAMES: tuple[str, ...] = (
    "pelvis",  # 0
    "left_hip",  # 1
    "right_hip",  # 2
    "spine1",  # 3
    "left_knee",  # 4
    "right_knee",  # 5
    "spine2",  # 6
    "left_ankle",  # 7
    "right_ankle",  # 8
    "spine3",  # 9
    "left_foot",  # 10
    "right_foot",  # 11
    "neck",  # 12
    "left_collar",  # 13
    "right_collar",  # 14
    "head",  # 15
    "left_shoulder",  # 16
    "right_shoulder",  # 17
    "left_elbow",  # 18
    "right_elbow",  # 19
    "left_wrist",  # 20
    "right_wrist",  # 21
    "left_hand",  # 22
    "right_hand",  # 23
)

#: Parent joint index of each joint (-1 for the root), as in SMPL.
JOINT_PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
)  # fmt: skip

NUM_JOINTS = len(JOINT_NAMES)

#: The anny bone whose head is each joint. The same bone carries the joint's
#: rotation when a motion poses the body (see ``AnnyBody.pose``).
ANNY_BONE_OF_JOINT: dict[str, str] = {
    "pelvis": "root",
    "left_hip": "upperleg01.L",
    "right_hip": "upperleg01.R",
    "spine1": "spine04",
    "left_knee": "lowerleg01.L",
    "right_knee": "lowerleg01.R",
    "spine2": "spine03",
    "left_ankle": "foot.L",
    "right_ankle": "foot.R",
    "spine3": "spine01",
    "left_foot": "toe3-1.L",
    "right_foot": "toe3-1.R",
    "neck": "neck01",
    "left_collar": "clavicle.L",
    "right_collar": "clavicle.R",
    "head": "head",
    "left_shoulder": "upperarm01.L",
    "right_shoulder": "upperarm01.R",
    "left_elbow": "lowerarm01.L",
    "right_elbow": "lowerarm01.R",
    "left_wrist": "wrist.L",
    "right_wrist": "wrist.R",
    "left_hand": "finger3-1.L",
    "right_hand": "finger3-1.R",
}

#: Pairs of (left, right) joint indices, for mirroring motions.
MIRROR_PAIRS: tuple[tuple[int, int], ...] = tuple(
    (i, JOINT_NAMES.index("right" + n[4:]))
    for i, n in enumerate(JOINT_NAMES)
    if n.startswith("left")
)


#: Bone lengths (metres; bone k joins joint k + 1 to its parent) of anny's rest skeleton at its
#: phenotype extremes (a young child to a tall heavy adult): a real skeleton's bones lie far inside
#: [BONE_LENGTH_RANGE_M[0] / 2, 2 * BONE_LENGTH_RANGE_M[1]].
BONE_LENGTH_RANGE_M: tuple[tuple[float, ...], tuple[float, ...]] = (
    (0.040, 0.040, 0.023, 0.099, 0.099, 0.032, 0.115, 0.115, 0.093, 0.049, 0.049, 0.038,
     0.019, 0.019, 0.033, 0.052, 0.052, 0.074, 0.074, 0.081, 0.081, 0.036, 0.036),
    (0.129, 0.129, 0.106, 0.653, 0.653, 0.093, 0.525, 0.525, 0.314, 0.199, 0.199, 0.199,
     0.119, 0.119, 0.129, 0.177, 0.177, 0.361, 0.361, 0.311, 0.311, 0.134, 0.134),
)  # fmt: skip


def joint_index(name: str) -> int:
    """Index of a joint by name; a clear error for unknown names."""
    try:
        return JOINT_NAMES.index(name)
    except ValueError:
        raise ValueError(f"unknown joint {name!r}; known joints: {', '.join(JOINT_NAMES)}") from None
