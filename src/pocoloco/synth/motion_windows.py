"""Motion histories of a synthetic dataset's sequences (issue 41): the whole body motion before and
through the stored frames, from which every frame's motion window is cut. The full simulated motion
(the blend from rest and the warm-up before the first stored frame included) is redrawn from the
sequence's seed and checked against its ``motion.npz``; the rest pose holds before that."""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np

from ..data.card import SPLITS, DatasetLayout
from ..data.format import read_motion, read_sequence_meta
from ..data.motion_window import MotionHistory, MotionWindow, read_motion_history, write_motion_history
from .histories import own_motion, synth_source


def sequence_history(dataset: str | os.PathLike, subject: str, split: str, sequence: str) -> MotionHistory:
    """The :class:`MotionHistory` of ``subject/split/sequence`` of a dataset made by ``pocoloco data
    synth``; its row ``first + i`` is exactly stored frame i's skeleton."""
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
    return MotionHistory(np.asarray(joints, np.float32), float(config.fps), full.num_frames - config.frames_per_sequence)


def sequence_windows(dataset: str | os.PathLike, subject: str, split: str, sequence: str,
                     seconds: float = 2.0, hz: float = 8.0) -> list[MotionWindow]:  # fmt: skip
    """One :class:`MotionWindow` per stored frame of ``subject/split/sequence``."""
    history = sequence_history(dataset, subject, split, sequence)
    count = len(read_motion(DatasetLayout(dataset).motion_path(subject, split, sequence)).joint_rotvecs)
    return [history.window(i, seconds, hz) for i in range(count)]


def write_motion_histories(dataset: str | os.PathLike, progress: Callable[[int, int], None] | None = None
                           ) -> tuple[int, int]:  # fmt: skip
    """Write every sequence's ``motion_history.npz`` (atomically; present, readable ones are kept, so
    a killed run resumes). Returns (written, kept)."""
    layout = DatasetLayout(dataset)
    synth_source(dataset)  # a one-line error for a dataset that was not synthesised
    todo = [(s, sp, q) for s in layout.subjects() for sp in SPLITS for q in layout.sequences(s, sp)]
    written = kept = 0
    for k, (subject, split, sequence) in enumerate(todo):
        path = layout.motion_history_path(subject, split, sequence)
        try:
            read_motion_history(path)
            kept += 1
        except (OSError, ValueError):
            write_motion_history(path, sequence_history(dataset, subject, split, sequence))
            written += 1
        if progress is not None:
            progress(k + 1, len(todo))
    return written, kept
