"""Benchmark of the skeleton rig: a posed body (vertices + POP's ``vtransf``) from 24 joint transforms.

Usage:
    python benchmarks/bench_rig.py [--frames 32] [--repeats 5] [--out benchmarks/results/rig.json]

A ``pocoloco data pack --bodies`` pack stores per frame only the 24 skeleton joints' skinning
transforms; POP / CloSET training rebuilds the posed body from them (``SkeletonRig.pose``). This
times, for one anny subject and --frames random poses (batch of all frames, one call each):

* ``anny``: ``AnnyBody.pose`` -- anny's own forward pass over its 104 bones, what the body would
  cost without a pack (and what the dataset generator runs);
* ``reference``: ``SkeletonRig.pose_reference`` -- the same skinning bone by bone, float64;
* ``rig``: ``SkeletonRig.pose`` -- the weights folded onto the joints, two float32 matrix products
  a frame (the joint transforms of the frames are given, as a pack gives them).

Each row: median milliseconds per frame over --repeats runs (after one warm-up), the ratio against
anny, and the largest vertex / vtransf difference from anny (mm / unitless). Torch and BLAS use the
threads given by OMP_NUM_THREADS.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys

import numpy as np

from pocoloco.body.anny_body import NUM_JOINTS, AnnyBody
from pocoloco.utils.atomic import write_json_atomic
from pocoloco.utils.timing import median_seconds


def bench(frames: int, repeats: int, seed: int = 0) -> list[dict]:
    body = AnnyBody({"gender": 1.0, "age": 0.45, "weight": 0.45, "height": 0.5})
    rot = np.random.default_rng(seed).normal(0, 0.4, (frames, NUM_JOINTS, 3)).astype(np.float32)
    rig = body.skeleton_rig()
    transforms = body.joint_transforms(rot)
    anny = body.pose(rot)
    anny_verts = anny.vertices - anny.joints[:, :1]  # the rig works in anny's frame (pelvis at the origin)
    rows = []
    for name, fn in [
        ("anny", lambda: body.pose(rot)),
        ("reference", lambda: rig.pose_reference(transforms)),
        ("rig", lambda: rig.pose(transforms)),
    ]:
        seconds = median_seconds(fn, repeats)
        if name == "anny":
            err_v = err_t = 0.0
        else:
            verts, vtransf = fn()
            err_v = float(np.abs(verts - anny_verts).max()) * 1000.0
            err_t = float(np.abs(vtransf - anny.vtransf).max())
        rows.append({"method": name, "ms_per_frame": 1000.0 * seconds / frames,
                     "max_vertex_error_mm": err_v, "max_vtransf_error": err_t})  # fmt: skip
    base = rows[0]["ms_per_frame"]
    for r in rows:
        r["speedup_vs_anny"] = base / r["ms_per_frame"]
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default="benchmarks/results/rig.json")
    args = ap.parse_args()
    rows = bench(args.frames, args.repeats)
    print(f"posed body from 24 joint transforms, {args.frames} frames a call, "
          f"median of {args.repeats} (OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')})")  # fmt: skip
    print(f"{'method':<10} {'ms/frame':>9} {'vs anny':>8} {'max |dv| mm':>12} {'max |dT|':>9}")
    for r in rows:
        print(f"{r['method']:<10} {r['ms_per_frame']:9.2f} {r['speedup_vs_anny']:7.1f}x "
              f"{r['max_vertex_error_mm']:12.2e} {r['max_vtransf_error']:9.2e}")  # fmt: skip
    write_json_atomic(args.out, {
        "benchmark": "rig",
        "command": "OMP_NUM_THREADS=%s python benchmarks/bench_rig.py %s" % (os.environ.get("OMP_NUM_THREADS", ""), " ".join(sys.argv[1:])),
        "frames": args.frames, "repeats": args.repeats,
        "threads": os.environ.get("OMP_NUM_THREADS"), "machine": platform.processor() or platform.machine(),
        "rows": rows,
    })  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
