"""POP training data and the plain training step: dataset frames -> pelvis-centred samples ->
batches, the optimiser (paper SupMat A.2) and one optimisation step.

Shapes: B batch, V body vertices, N scan points.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from pocoloco.body.skeleton import NUM_JOINTS
from pocoloco.body.surface import pose_mean_shape
from pocoloco.data.format import DatasetLayout, read_frame, read_motion, read_subject
from pocoloco.data.motion_window import MotionWindow, heading_of, motion_features
from pocoloco.methods.pop.losses import check_scan, normal_weight_at, pop_losses
from pocoloco.models.pop import POP, POPBatch, POPLossWeights

__all__ = ["MOTION_SCALE_M", "POPDataset", "POPSample", "collate_pop", "make_optimizer", "pop_motion_features",
           "pop_sample_from_frame", "train_step"]

#: the length unit of POP's motion features (POP's frames are pelvis-centred metres, not normalised)
MOTION_SCALE_M = 0.25


def pop_motion_features(window: MotionWindow, joints: np.ndarray) -> np.ndarray:
    """(J, F) motion-window features in POP's frame (pelvis-centred, world-aligned; lengths in units
    of ``MOTION_SCALE_M``) for the pose ``joints`` (J, 3) the window ends on."""
    return motion_features(window, heading_of(joints), MOTION_SCALE_M)


def make_optimizer(model: POP, lr: float = 3e-4, lr_features: float = 5e-4, lr_motion: float | None = None
                   ) -> torch.optim.Adam:  # fmt: skip
    """Adam with ``lr`` for the network and ``lr_features`` for G (SupMat A.2's rates by default);
    ``lr_motion``: the motion encoder's own rate (None: ``lr``)."""
    motion = [p for n, p in model.named_parameters() if n.startswith("motion_in.")] if lr_motion is not None else []
    network = [p for p in model.network_parameters() if all(p is not q for q in motion)]
    groups = [{"params": network, "lr": lr}, {"params": [model.geom], "lr": lr_features}]
    return torch.optim.Adam(groups + ([{"params": motion, "lr": lr_motion}] if motion else []))


def train_step(model: POP, optimizer: torch.optim.Optimizer, batch: POPBatch, step: int,
               weights: POPLossWeights = POPLossWeights(), normal_start: int = 0) -> dict[str, float]:  # fmt: skip
    """One optimisation step on ``batch`` (model in training mode); returns the losses as floats.
    The normal term is on from step ``normal_start`` and then needs ``scan_normals``."""
    model.train()
    wn = normal_weight_at(weights, normal_start, step)
    check_scan(batch.scan_points, batch.scan_normals, batch.body_vertices.shape[0], need_normals=True)
    optimizer.zero_grad(set_to_none=True)
    out = model(batch)
    losses = pop_losses(out, batch.scan_points, batch.scan_normals, weights, normal_weight=wn)
    losses.total.backward()
    optimizer.step()
    return losses.as_floats()


@dataclass
class POPSample:
    """One pelvis-centred training frame (numpy float32): pose_vertices (V, 3), body_vertices
    (V, 3), vtransf (V, 3, 3), scan_points (N, 3), scan_normals (N, 3), outfit id; motion (J, F)
    motion-window features (:func:`pop_motion_features`) or None."""

    pose_vertices: np.ndarray
    body_vertices: np.ndarray
    vtransf: np.ndarray
    scan_points: np.ndarray
    scan_normals: np.ndarray
    outfit: int
    motion: np.ndarray | None = None


def pop_sample_from_frame(frame, outfit: int, num_points: int, rng: np.random.Generator | None = None,
                          pose_vertices: np.ndarray | None = None, num_vertices: int | None = None,
                          src: str = "frame", motion: np.ndarray | None = None) -> POPSample:  # fmt: skip
    """A dataset ``Frame`` -> ``POPSample``: subtract the root joint (joints[0]) from the
    scan and body (POP's frames are pelvis-centred) and draw ``num_points`` scan points
    without replacement (all of them, in order, when ``rng`` is None and N == num_points).

    pose_vertices: (V, 3) body for the pose encoder, already centred on its own root
    joint (the posed mean shape); None = the subject's centred body. motion: (J, F) the frame's
    motion-window features (:func:`pop_motion_features`), passed through.
    """
    if frame.body_vertices is None or frame.vtransf is None:
        raise ValueError(f"{src}: POP needs body_vertices and vtransf (synthetic data); the frame has none")
    if frame.joints is None or np.shape(frame.joints) != (NUM_JOINTS, 3):
        raise ValueError(f"{src}: joints must have shape ({NUM_JOINTS}, 3), got {np.shape(frame.joints)}")
    V = frame.body_vertices.shape[0]
    if num_vertices is not None and V != num_vertices:
        raise ValueError(f"{src}: body has {V} vertices, the model expects {num_vertices}")
    if frame.vtransf.shape != (V, 3, 3):
        raise ValueError(f"{src}: vtransf must have shape ({V}, 3, 3), got {frame.vtransf.shape}")
    if frame.points is None or frame.normals is None:
        raise ValueError(f"{src}: POP needs scan points and normals")
    N = frame.points.shape[0]
    if N < num_points:
        raise ValueError(f"{src}: scan has {N} points, fewer than the {num_points} POP samples per frame")
    if rng is None:
        if N != num_points:
            raise ValueError(f"{src}: pass rng to subsample {N} scan points to {num_points}")
        sel = np.arange(N)
    else:
        sel = np.sort(rng.choice(N, num_points, replace=False))
    root = np.asarray(frame.joints[0], np.float32)
    body = (frame.body_vertices - root).astype(np.float32)
    if pose_vertices is None:
        pose = body
    else:
        pose = np.asarray(pose_vertices, np.float32)
        if pose.shape != (V, 3):
            raise ValueError(f"{src}: pose_vertices must have shape ({V}, 3), got {pose.shape}")
    return POPSample(pose, body, np.asarray(frame.vtransf, np.float32), (frame.points[sel] - root).astype(np.float32),
                     np.asarray(frame.normals[sel], np.float32), int(outfit), motion)  # fmt: skip


def collate_pop(samples: Sequence[POPSample]) -> POPBatch:
    """Stack samples (same V and N) into a torch ``POPBatch``."""
    if not samples:
        raise ValueError("collate_pop needs at least one sample")
    st = lambda k: torch.from_numpy(np.stack([getattr(s, k) for s in samples]))  # noqa: E731
    if len({s.motion is None for s in samples}) > 1:
        raise ValueError("collate_pop: some samples have a motion window and some not")
    try:
        return POPBatch(st("pose_vertices"), st("body_vertices"), st("vtransf"),
                        torch.tensor([s.outfit for s in samples], dtype=torch.long),
                        st("scan_points"), st("scan_normals"),
                        None if samples[0].motion is None else st("motion"))  # fmt: skip
    except ValueError as e:
        raise ValueError(f"collate_pop: samples differ in shape ({e})") from None


class POPDataset(torch.utils.data.Dataset):
    """POP samples from a pocoloco dataset folder (``pocoloco.data.format``).

    Every subject is one outfit (ids in sorted subject order, or ``outfits`` given);
    frames need body_vertices and vtransf. With ``pose_input="mean_shape"`` the pose
    encoder's body is the anny mean shape posed with the sequence's ``motion.npz``
    (``pose_mean_shape``; posed once per sequence and cached), centred on its root joint.
    Item i draws ``num_points`` scan points with a generator seeded by (seed, i, epoch).
    """

    def __init__(self, root: str | os.PathLike, split: str = "train", subjects: Sequence[str] | None = None,
                 num_points: int = 40000, pose_input: str = "mean_shape", seed: int = 0,
                 outfits: dict[str, int] | None = None):  # fmt: skip
        self.layout = DatasetLayout(root)
        subs = list(subjects) if subjects is not None else self.layout.subjects()
        if not subs:
            raise ValueError(f"{os.fspath(root)}: no subjects")
        if pose_input not in ("mean_shape", "subject"):
            raise ValueError(f"pose_input must be 'mean_shape' or 'subject', got {pose_input!r}")
        self.outfits = dict(outfits) if outfits is not None else {s: i for i, s in enumerate(sorted(subs))}
        missing = [s for s in subs if s not in self.outfits]
        if missing:
            raise ValueError(f"no outfit id for subjects {missing}")
        self.num_points, self.pose_input, self.seed, self.split, self.epoch = num_points, pose_input, seed, split, 0
        self.subject_assets = {s: read_subject(self.layout.subject_path(s)) for s in subs}
        self.items: list[tuple[str, str, int]] = []
        for s in subs:
            for q in self.layout.sequences(s, split):
                self.items += [(s, q, i) for i in self.layout.frame_indices(s, split, q)]
        if not self.items:
            raise ValueError(f"{os.fspath(root)}: no '{split}' frames for subjects {subs}")
        self._pose_cache: dict[tuple[str, str], np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.items)

    def _mean_shape_vertices(self, subject: str, seq: str, frame_index: int) -> np.ndarray:
        key = (subject, seq)
        if key not in self._pose_cache:
            m = read_motion(self.layout.motion_path(subject, self.split, seq))
            posed = pose_mean_shape(m.joint_rotvecs)
            self._pose_cache[key] = (posed.vertices - posed.joints[:, :1]).astype(np.float32)  # (T, V, 3)
        verts = self._pose_cache[key]
        if frame_index >= len(verts):
            raise ValueError(f"{subject}/{seq}: frame {frame_index} is beyond motion.npz ({len(verts)} frames)")
        return verts[frame_index]

    def __getitem__(self, i: int) -> POPSample:
        s, q, fi = self.items[i]
        path = self.layout.frame_path(s, self.split, q, fi)
        frame = read_frame(path, ("points", "normals", "joints", "frame_index", "body_vertices", "vtransf"),
                           allow_missing=True)  # fmt: skip
        pose = self._mean_shape_vertices(s, q, int(frame.frame_index)) if self.pose_input == "mean_shape" else None
        rng = np.random.default_rng([self.seed, i, self.epoch])
        return pop_sample_from_frame(frame, self.outfits[s], self.num_points, rng, pose, src=os.fspath(path))
