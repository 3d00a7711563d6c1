"""Writing sampled clouds to a folder (``pocoloco sample``): one PLY per cloud, a PNG, a JSON."""

from __future__ import annotations

import os
import re
import shutil
import uuid
from pathlib import Path
from typing import Any

from pocoloco.data.poses import Pose

from pocoloco.data.published import write_ply
from pocoloco.methods.base import SampledClouds
from pocoloco.utils.atomic import output_folder, write_json_atomic
from pocoloco.viz.render import render_grid

__all__ = ["write_samples"]

_SAMPLE_FILE = re.compile(r"^sample_(\d+)\.ply$")


def write_samples(
    out: str | os.PathLike, clouds: SampledClouds, settings: dict[str, Any], render: bool = True,
    *, pose: Pose | None = None,
) -> Path:
    """Write ``sample_000.ply`` .. (points + normals if any), ``hypotheses.png`` (every cloud from
    the front and the side, up to 8 clouds per row) and ``sample.json`` (``settings``).

    ``pose``: the pose the clouds were drawn for, or None. Its joints orient the normals the
    picture is shaded with (for clouds without normals) and, with its posed body where it has one,
    find the loose garment the picture tints (:func:`pocoloco.viz.render.garment_weights`).

    A new ``out`` folder is filled under a temporary name and renamed into place, so it appears
    complete or not at all. An existing ``out`` folder gets each file replaced atomically;
    ``sample_*.ply`` files of an earlier, larger run are removed. Returns ``out``.
    """
    out = output_folder(out)
    fresh = not out.exists()
    target = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}" if fresh else out
    K = clouds.points.shape[0]
    try:
        target.mkdir(parents=True, exist_ok=True)
        for k in range(K):
            nrm = None if clouds.normals is None else clouds.normals[k]
            write_ply(target / f"sample_{k:03d}.ply", clouds.points[k], normals=nrm)
        if render:
            panels = [(clouds.points[k], None, None if clouds.normals is None else clouds.normals[k],
                       f"sample {k}") for k in range(K)]  # fmt: skip
            render_grid(panels, target / "hypotheses.png", views=("front", "side"), ncols=min(K, 8), fit=True,
                        joints=None if pose is None else pose.joints,
                        body=None if pose is None else pose.body_vertices)  # fmt: skip
        write_json_atomic(target / "sample.json", settings)
        if fresh:
            os.replace(target, out)
    except BaseException:
        if fresh:
            shutil.rmtree(target, ignore_errors=True)
        raise
    for p in out.iterdir():  # stale clouds of an earlier run with more samples
        m = _SAMPLE_FILE.match(p.name)
        if m and int(m.group(1)) >= K:
            p.unlink()
    return out
