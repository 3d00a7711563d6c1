"""Motion windows of a synthetic dataset's frames (issue 41): the last seconds of the body's motion
before a stored frame, from the sequence's full simulated motion (the blend from rest and the
warm-up before its first stored frame included, redrawn from the sequence's seed and checked
against its ``motion.npz``; the rest pose before that)."""

from __future__ import annotations

import os

import numpy as np

from ..data.format import DatasetLayout, read_motion, read_sequence_meta
from ..data.motion_window import MotionWindow, motion_window
from .histories import own_motion, synth_source


def sequence_windows(dataset: str | os.PathLike, subject: str, split: str, sequence: str,
                     seconds: float = 2.0, hz: float = 8.0) -> list[MotionWindow]:  # fmt: skip
    """One :class:`MotionWindow` per stored frame of ``subject/split/sequence`` of a dataset made by
    ``pocoloco data synth``; frame i's current sample is exactly its stored skeleton."""
    from .pipeline import subject_assets

    _, config = synth_source(dataset)
    spec = next((s for s in config.subjects if s.name == subject), None)
    if spec is None:
        raise ValueError(f"{dataset}: no subject {subject!r}")
    layout = DatasetLayout(dataset)
    record = read_sequence_meta(layout.sequence_meta_path(subject, split, sequence))
    stored = read_motion(layout.motion_path(subject, split, sequence))
    body, _ = subject_assets(spec, config)
    full = own_motion(config, body, split, {**record, "name": sequence}, stored)
    joints = body.pose_joints(full.joint_rotvecs) + np.asarray(full.root_translation, np.float32)[:, None]
    first = full.num_frames - config.frames_per_sequence
    return [motion_window(joints, first + i, config.fps, seconds, hz) for i in range(len(stored.joint_rotvecs))]
