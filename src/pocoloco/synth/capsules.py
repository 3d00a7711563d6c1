"""The capsule collider of the cloth simulation (``ClothSimSettings.collider="capsules"``):
16 capsules fitted to the rest body's parts and skinned to it, so they follow the posed body.
Analytic and cheap, but inscribed in the body, so cloth can sink into concave regions (the
exact deforming mesh is the default collider; ``synth.cloth_sim``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..body.anny_body import AnnyBody
from ..body.skeleton import joint_index
from .sdf import signed_distance_fn

#: (start joint, end joint, body parts (joints) whose vertices fit the radius, lateral side)
_CAPSULE_SPECS: tuple[tuple[str, str, tuple[str, ...], int], ...] = (
    ("left_hip", "left_knee", ("left_hip",), 0),
    ("right_hip", "right_knee", ("right_hip",), 0),
    ("left_knee", "left_ankle", ("left_knee",), 0),
    ("right_knee", "right_ankle", ("right_knee",), 0),
    ("left_shoulder", "left_elbow", ("left_shoulder",), 0),
    ("right_shoulder", "right_elbow", ("right_shoulder",), 0),
    ("left_elbow", "left_wrist", ("left_elbow",), 0),
    ("right_elbow", "right_wrist", ("right_elbow",), 0),
    ("pelvis", "spine2", ("pelvis", "spine1", "left_hip", "right_hip"), +1),
    ("pelvis", "spine2", ("pelvis", "spine1", "left_hip", "right_hip"), -1),
    ("spine2", "neck", ("spine2", "spine3", "left_collar", "right_collar"), +1),
    ("spine2", "neck", ("spine2", "spine3", "left_collar", "right_collar"), -1),
    ("spine1", "spine2", ("pelvis", "spine1", "spine2"), 0),
    ("spine3", "neck", ("spine3", "neck", "left_collar", "right_collar"), 0),
)


@dataclass
class CapsuleRig:
    """Capsules skinned to the body.

    anchors: (K, 2, A) body vertex indices per capsule end; offsets (K, 2, A, 3)
    rest offsets from those vertices to the end point; radius (K,).
    """

    anchors: np.ndarray
    offsets: np.ndarray
    radius: np.ndarray

    def endpoints(self, vertices: np.ndarray, vtransf: np.ndarray) -> np.ndarray:
        """(K, 2, 3) capsule end points on one posed body (V, 3)/(V, 3, 3)."""
        p = vertices[self.anchors] + np.einsum("keaij,keaj->keai", vtransf[self.anchors], self.offsets)
        return p.mean(2)


def fit_capsules(body: AnnyBody, percentile: float = 90.0, num_anchors: int = 8) -> CapsuleRig:
    """Fit the capsule rig to ``body``'s rest pose (see ``_CAPSULE_SPECS``)."""
    tv, tj, vj = body.template, body.template_joints, body.vertex_joint
    anchors, offsets, radii = [], [], []
    for a_name, b_name, parts, side in _CAPSULE_SPECS:
        part = np.isin(vj, [joint_index(p) for p in parts])
        if side:
            part &= np.sign(tv[:, 0]) == side
        pts = tv[part]
        ja, jb = tj[joint_index(a_name)], tj[joint_index(b_name)]
        # axis ends: centroids of the part's cross-sections near each joint
        t = (pts - ja) @ (jb - ja) / ((jb - ja) @ (jb - ja))
        a = pts[(t > 0.05) & (t < 0.2)].mean(0)
        b = pts[(t > 0.8) & (t < 0.95)].mean(0)
        d = b - a
        t = np.clip((pts - a) @ d / (d @ d), 0.0, 1.0)
        dist = np.linalg.norm(pts - (a + t[:, None] * d), axis=1)
        radii.append(_inscribe(a, b, float(np.percentile(dist, percentile)), body))
        idx = np.flatnonzero(part)
        ends_a, ends_o = [], []
        for e in (a, b):
            nn = idx[np.argsort(np.linalg.norm(tv[idx] - e, axis=1))[:num_anchors]]
            ends_a.append(nn)
            ends_o.append(e - tv[nn])
        anchors.append(ends_a)
        offsets.append(ends_o)
    return CapsuleRig(np.array(anchors), np.array(offsets, dtype=np.float32), np.array(radii, dtype=np.float32))


def _inscribe(a: np.ndarray, b: np.ndarray, radius: float, body: AnnyBody, tol: float = 0.003) -> float:
    """Shrink a capsule's radius until its surface pokes out of the rest body by
    at most ``tol`` (a capsule outside the skin would shove the cloth)."""
    d = b - a
    n = d / np.linalg.norm(d)
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    ang = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    ring = np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * w  # (24, 3)
    sdf = signed_distance_fn(body.template, body.faces)
    axis = a + np.linspace(0, 1, 12)[:, None] * d  # (12, 3)
    for _ in range(30):
        side = (axis[:, None] + radius * ring[None]).reshape(-1, 3)
        pts = np.concatenate([side, a - radius * n[None], b + radius * n[None]])
        out = sdf(pts).max()
        if out <= tol or radius < 0.01:
            break
        radius = max(radius - max(out - tol, 0.002), 0.01)
    return radius


def quat_z_to(d: np.ndarray) -> np.ndarray:
    """(K, 4) xyzw quaternions rotating +Z onto directions d (K, 3)."""
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d)
    w = 1.0 + d[:, 2]
    q = np.concatenate([axis, w[:, None]], 1)
    flip = w < 1e-6
    q[flip] = [1.0, 0.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)
