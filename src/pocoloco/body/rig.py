"""anny's linear blend skinning driven by the 24 skeleton joints alone (numpy; no anny needed).

anny skins each vertex with 9 of its 104 bones: ``v = sum_k w_vk A_b(vk) [r_v; 1]`` with
``A_b = bone_pose_b @ inv(rest_bone_pose_b)`` and ``r_v`` the subject's rest vertex. Only the 24
skeleton bones are posed (``AnnyBody.run_anny``); every other bone keeps its rest orientation
relative to its reference, so its transform is that of its nearest skeleton ancestor ``j(b)``
times a constant of the subject: ``A_b = A_j(b) @ C_b`` for every pose (checked against anny in
the tests to 1e-6 m). A :class:`SkeletonRig` holds ``r``, ``w``, the bone of each weight, ``j(b)``
and ``C_b``; given the 24 per-joint transforms ``A_j`` of a frame it rebuilds the posed vertices
and POP's per-vertex ``vtransf = sum_k w_vk A_b(vk)[:3, :3]`` exactly, which lets a training
pack store a posed body in 24 x 12 numbers (``pocoloco data pack --bodies``).

Shapes: T frames, V vertices, K weights per vertex, B bones, J = 24 joints. Transforms are
3 x 4 affine matrices ``[R | t]`` in anny's posed frame (the posed pelvis at the origin).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

__all__ = ["SkeletonRig", "compose_affine"]


def compose_affine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3, 4) @ (..., 3, 4) as 4 x 4 affine maps: ``[Ra Rb | Ra tb + ta]``."""
    r = a[..., :3] @ b[..., :3]
    t = (a[..., :3] @ b[..., 3:])[..., 0] + a[..., 3]
    return np.concatenate([r, t[..., None]], axis=-1)


@dataclass(frozen=True)
class SkeletonRig:
    """One subject's skinning reduced to the skeleton (module docstring).

    rest_vertices: (V, 3) float32 anny rest vertices of the subject (anny's rest frame).
    weights:       (V, K) float32 skinning weights (rows sum to 1).
    bones:         (V, K) int64 bone of each weight, in [0, B).
    bone_joint:    (B,) int64 skeleton joint whose transform moves each bone, in [0, 24).
    bone_offsets:  (B, 3, 4) float64 constant ``C_b`` with ``A_b = A_j(b) @ C_b``.
    """

    rest_vertices: np.ndarray
    weights: np.ndarray
    bones: np.ndarray
    bone_joint: np.ndarray
    bone_offsets: np.ndarray

    def __post_init__(self):
        V = self.rest_vertices.shape[0]
        B = self.bone_offsets.shape[0]
        if self.rest_vertices.shape != (V, 3) or self.weights.shape != self.bones.shape or self.weights.shape[0] != V:
            raise ValueError(f"rig arrays disagree: rest {self.rest_vertices.shape}, weights {self.weights.shape}, "
                             f"bones {self.bones.shape}")  # fmt: skip
        if self.bone_joint.shape != (B,) or self.bone_offsets.shape != (B, 3, 4):
            raise ValueError(f"rig bone arrays disagree: bone_joint {self.bone_joint.shape}, offsets {self.bone_offsets.shape}")
        if self.bones.size and (self.bones.min() < 0 or self.bones.max() >= B):
            raise ValueError(f"rig bone indices outside [0, {B})")
        if self.bone_joint.size and (self.bone_joint.min() < 0 or self.bone_joint.max() >= 24):
            raise ValueError("rig bone_joint outside the 24 skeleton joints")

    @property
    def num_vertices(self) -> int:
        return int(self.rest_vertices.shape[0])

    @functools.cached_property
    def _per_joint(self) -> tuple[np.ndarray, np.ndarray]:
        """The weights folded onto the joints: ``M_v = sum_j A_j D_vj`` with ``D_vj = sum_{k: j(b_vk)
        = j} w_vk C_b(vk)`` (as 4 x 4 affine maps), kept as ``P = D_vj [r_v; 1]`` (V, 24 * 4) and the
        linear parts of ``D`` (V * 3, 24 * 3), float32: a frame is then two small matrix products."""
        V, K = self.weights.shape
        c = np.zeros((self.bone_offsets.shape[0], 4, 4))
        c[:, :3], c[:, 3, 3] = self.bone_offsets, 1.0
        d = np.zeros((V, 24, 4, 4))
        rows = np.repeat(np.arange(V), K)
        np.add.at(d, (rows, self.bone_joint[self.bones].ravel()),
                  self.weights.astype(np.float64).reshape(-1)[:, None, None] * c[self.bones.ravel()])  # fmt: skip
        rest_h = np.concatenate([self.rest_vertices.astype(np.float64), np.ones((V, 1))], axis=1)
        p = np.einsum("vjab,vb->vja", d, rest_h).reshape(V, 24 * 4)
        lin = d[:, :, :3, :3].transpose(0, 3, 1, 2).reshape(V * 3, 24 * 3)  # [v, c] x [j, b]
        return p.astype(np.float32), np.ascontiguousarray(lin, np.float32)

    def pose(self, joint_transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(T, 24, 3, 4) per-joint transforms ``A_j`` -> posed vertices (T, V, 3) and ``vtransf``
        (T, V, 3, 3), float32 (two matrix products a frame; :meth:`pose_reference` is the same
        per bone, in float64)."""
        a = np.asarray(joint_transforms, np.float32)
        if a.ndim != 4 or a.shape[1:] != (24, 3, 4):
            raise ValueError(f"joint_transforms must have shape (T, 24, 3, 4), got {a.shape}")
        p, lin = self._per_joint
        T, V = a.shape[0], self.num_vertices
        # A as [j, b] x [a]: translation column included for positions, rotation only for vtransf
        verts = np.stack([p @ a[t].transpose(0, 2, 1).reshape(24 * 4, 3) for t in range(T)])
        rot = a[:, :, :, :3].transpose(0, 1, 3, 2).reshape(T, 24 * 3, 3)  # [j, b] x [a]
        vt = np.stack([(lin @ rot[t]).reshape(V, 3, 3).transpose(0, 2, 1) for t in range(T)])
        return verts, np.ascontiguousarray(vt)

    def pose_reference(self, joint_transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`pose` bone by bone, as anny skins (``A_b = A_j(b) C_b``, 9 bones a vertex), in float64."""
        a = np.asarray(joint_transforms, np.float64)
        if a.ndim != 4 or a.shape[1:] != (24, 3, 4):
            raise ValueError(f"joint_transforms must have shape (T, 24, 3, 4), got {a.shape}")
        per_bone = compose_affine(a[:, self.bone_joint], self.bone_offsets[None])  # (T, B, 3, 4)
        blended = np.einsum("vk,tvkij->tvij", self.weights.astype(np.float64), per_bone[:, self.bones])  # (T, V, 3, 4)
        verts = np.einsum("tvij,vj->tvi", blended[..., :3], self.rest_vertices.astype(np.float64)) + blended[..., 3]
        return verts.astype(np.float32), np.ascontiguousarray(blended[..., :3], np.float32)
