"""The frames of ``pocoloco bench quality`` for the post-processing probes: the same frames, GT
subsets and poses as :func:`pocoloco.evaluation.evaluate.evaluate`, so their numbers pair with it."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from pocoloco.data import format as fmt
from pocoloco.data.poses import MeanShapeCache
from pocoloco.evaluation.baselines import select_frames, subset

FRAME_KEYS = ["points", "normals", "labels", "joints", "frame_index", "body_vertices", "vtransf"]


def quality_frames(method, data, split: str, num_frames: int, num_points: int) -> Iterator[tuple[int, str, str, np.ndarray, Any]]:
    """Per chosen frame of ``split``: (index, key ``subject/split/sequence/frame``, subject, the
    (num_points, 3) float64 GT subset the bench scores against, ``method``'s pose of it)."""
    layout = fmt.DatasetLayout(data)
    frames = layout.iter_frames(split, layout.subjects())
    cache = MeanShapeCache()
    for i, (subject, sequence, path) in enumerate(frames[k] for k in select_frames(frames, num_frames)):
        fr = fmt.read_frame(path, FRAME_KEYS, allow_missing=True)
        gt = fr.points[subset(fr.num_points, num_points, (0, i))].astype(np.float64)
        pose = method.pose_from_frame(path, subject, frame=fr, cache=cache)
        yield i, f"{subject}/{split}/{sequence}/{fr.frame_index:06d}", subject, gt, pose
