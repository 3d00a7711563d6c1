"""The baselines every evaluation compares a model with, and which frames are evaluated.

* **nearest-frame** (:class:`NearestFrameBaseline`): the training frame of the same subject whose
  root-aligned joints are nearest to the query (optionally also turned about the vertical axis),
  its scan moved onto the query root.
* **posed body** (:func:`posed_body_baseline`): N points on the frame's posed minimally-clothed body.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from pocoloco.data import format as fmt
from pocoloco.ops.sampling import sample_surface

__all__ = ["NEAREST_ALIGNS", "NearestFrameBaseline", "posed_body_baseline", "select_frames", "subset"]


# ------------------------------------------------------------------------------------- frames
def select_frames(frames: Sequence[Any], num: int) -> list[int]:
    """Indices of ``num`` frames evenly spaced over ``frames`` (all of them if num is 0 or too large)."""
    n = len(frames)
    if num <= 0 or num >= n:
        return list(range(n))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, num)})


def subset(n: int, k: int, seed: Sequence[int]) -> np.ndarray:
    """Sorted indices of min(k, n) of n items drawn without replacement from ``default_rng(seed)``."""
    return np.sort(np.random.default_rng(list(seed)).choice(n, size=min(k, n), replace=False))


#: how ``NearestFrameBaseline`` aligns a training pose to the query before comparing
NEAREST_ALIGNS = ("root", "yaw")


def _yaw_to_match(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Angles theta (F,) of the rotations R_y(theta) about the vertical (y) axis minimising
    sum_j |R_y(theta) src_fj - dst_j|^2 (2-D Procrustes in the x-z plane; closed form).

    src: (F, J, 3) root-aligned joints; dst: (J, 3). R_y(theta) maps (x, z) to
    (cos x + sin z, -sin x + cos z)."""
    a = (dst[None, :, 0] * src[..., 0] + dst[None, :, 2] * src[..., 2]).sum(-1)
    b = (dst[None, :, 0] * src[..., 2] - dst[None, :, 2] * src[..., 0]).sum(-1)
    return np.arctan2(b, a)


def _rotate_y(x: np.ndarray, theta: float | np.ndarray) -> np.ndarray:
    """x: (..., 3) rotated by R_y(theta) (see ``_yaw_to_match``); theta broadcasts over x[..., 0]."""
    c, s = np.cos(theta), np.sin(theta)
    out = np.array(x, dtype=np.float64, copy=True)
    out[..., 0] = c * x[..., 0] + s * x[..., 2]
    out[..., 2] = -s * x[..., 0] + c * x[..., 2]
    return out


class NearestFrameBaseline:
    """The training frame nearest in pose: argmin_f sum_j |(k_j - k_root) - A_f(k'_fj - k'_f,root)|^2,
    over the frames of one subject (``subject=``) or of all.

    ``align="root"`` (default): A_f = identity, the poses compared after moving the roots together.
    ``align="yaw"``: A_f = the rotation about the vertical axis that best fits frame f to the query
    (closed form), so a query facing a direction no training frame faces still finds its pose.
    Reads only the joints of every training frame at construction (fast); the chosen frame's
    points are read on demand and moved by the same rigid motion onto the query pose.
    """

    def __init__(self, root: str | os.PathLike, subjects: Sequence[str] | None = None, root_joint: int = 0,
                 align: str = "root"):  # fmt: skip
        if align not in NEAREST_ALIGNS:
            raise ValueError(f"nearest-frame alignment must be one of {', '.join(NEAREST_ALIGNS)}, got {align!r}")
        self.align = align

        layout = fmt.DatasetLayout(root)
        chosen = sorted(subjects) if subjects else layout.subjects()
        self.frames = layout.iter_frames("train", chosen)
        if not self.frames:
            raise ValueError(f"{root}: no training frames for the nearest-frame baseline")
        self.root_joint = root_joint
        joints = np.stack([fmt.read_frame(p, ["joints"]).joints for _, _, p in self.frames]).astype(np.float64)
        self.joints = joints  # (F, J, 3)
        self.aligned = joints - joints[:, root_joint : root_joint + 1]  # (F, J, 3)
        self.subject_of = np.array([s for s, _, _ in self.frames])  # (F,)

    def nearest(self, joints: np.ndarray, subject: str | None = None) -> tuple[int, float, float]:
        """(index into ``frames``, RMS joint distance in metres, yaw angle in radians applied to
        that frame: 0 unless ``align="yaw"``) of the nearest training pose (among ``subject``'s
        frames if given)."""
        q = np.asarray(joints, np.float64)
        q = q - q[self.root_joint]
        if self.align == "yaw":
            theta = _yaw_to_match(self.aligned, q)  # (F,)
            cand = _rotate_y(self.aligned, theta[:, None])
        else:
            theta, cand = np.zeros(len(self.aligned)), self.aligned
        d2 = ((cand - q[None]) ** 2).sum(-1).mean(-1)  # (F,)
        if subject is not None:
            if not (self.subject_of == subject).any():
                raise ValueError(f"no training frames of subject {subject!r} for the nearest-frame baseline")
            d2 = np.where(self.subject_of == subject, d2, np.inf)
        i = int(np.argmin(d2))
        return i, float(math.sqrt(d2[i])), float(theta[i])

    def predict(self, joints: np.ndarray, num_points: int, seed: Sequence[int],
                subject: str | None = None) -> dict[str, Any]:  # fmt: skip
        """N points (+ normals, labels) of the nearest training frame, moved onto the query root."""
        i, rms, theta = self.nearest(joints, subject)
        fr = fmt.read_frame(self.frames[i][2], ["points", "normals", "joints", "labels"], allow_missing=True)
        sel = subset(fr.points.shape[0], num_points, seed)
        src_root = fr.joints[self.root_joint].astype(np.float64)
        dst_root = np.asarray(joints, np.float64)[self.root_joint]
        points = _rotate_y(fr.points[sel] - src_root, theta) + dst_root
        normals = _rotate_y(fr.normals[sel], theta)
        return {"points": points, "normals": normals.astype(fr.normals.dtype),
                "source": str(self.frames[i][2]), "labels": None if fr.labels is None else fr.labels[sel],
                "pose_rms_m": rms, "yaw_deg": math.degrees(theta)}  # fmt: skip


def posed_body_baseline(frame, faces: np.ndarray, num_points: int, seed: int) -> dict[str, Any]:
    """N points sampled area-uniformly on a frame's posed minimally-clothed body, with face normals."""
    s = sample_surface(frame.body_vertices.astype(np.float64), faces, num_points, seed=seed)
    return {"points": s.points, "normals": s.normals}
