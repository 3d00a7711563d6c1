"""Benchmark of the virtual capture: seconds per frame for the anny body + a skirt-like tube.

Usage:
    python benchmarks/bench_capture.py [--points 10000 40000 100000] [--repeats 5]
                                       [--out benchmarks/results/capture.json]

Each configuration is captured ``--repeats`` times (after one warm-up capture
that also pays open3d's import); the median wall time is reported, with the
loose-garment share of the points. Timings are wall-clock on whatever else the
machine is running: run on an idle machine for comparable numbers.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np

from pocoloco.body import AnnyBody
from pocoloco.synth.capture import (
    LABEL_BODY,
    LABEL_GARMENT,
    CaptureMesh,
    CaptureSettings,
    capture_frame,
    loose_share,
    open_tube,
)
from pocoloco.utils.atomic import write_json_atomic


def bench_meshes(body: AnnyBody) -> list[CaptureMesh]:
    """The rest-pose anny body and a flared open tube around its hips (a synthetic skirt)."""
    face_part = body.vertex_joint[body.faces[:, 0]]
    tv, tf = open_tube(-0.03, -0.6, (0.20, 0.13), (0.34, 0.30), center_xy=(0.0, -0.015), n_around=96, n_down=24)
    return [CaptureMesh(body.template, body.faces, LABEL_BODY, face_part), CaptureMesh(tv, tf, LABEL_GARMENT, None)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, nargs="+", default=[10000, 40000, 100000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=os.path.join("benchmarks", "results", "capture.json"))
    args = parser.parse_args()
    if args.repeats < 1:
        raise SystemExit("--repeats must be >= 1")

    meshes = bench_meshes(AnnyBody())
    capture_frame(meshes, CaptureSettings(num_points=1000))  # warm-up: open3d import
    rows = []
    for n in args.points:
        settings = CaptureSettings(num_points=n)
        times = []
        for r in range(args.repeats):
            t0 = time.perf_counter()
            scan = capture_frame(meshes, CaptureSettings(**{**settings.__dict__, "seed": r}))
            times.append(time.perf_counter() - t0)
        rows.append({
            "num_points": n, "num_cameras": settings.num_cameras, "median_s": statistics.median(times),
            "min_s": min(times), "max_s": max(times), "loose_share_percent": loose_share(scan.labels),
            "num_stored": int(len(scan.points)),
        })

    print(f"{'points':>8} {'cameras':>8} {'median s':>9} {'min s':>7} {'max s':>7} {'loose %':>8}")
    for r in rows:
        print(f"{r['num_points']:>8} {r['num_cameras']:>8} {r['median_s']:>9.3f} {r['min_s']:>7.3f} "
              f"{r['max_s']:>7.3f} {r['loose_share_percent']:>8.1f}")
    result = {
        "benchmark": "capture_frame, anny rest body (27,420 triangles) + open tube skirt (4,416 triangles)",
        "repeats": args.repeats, "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(), "load_avg_1min": os.getloadavg()[0], "rows": rows,
    }
    write_json_atomic(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
