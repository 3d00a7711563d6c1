"""Benchmark of the body-surface machinery on the anny UV layout (pocoloco.body.surface).

Usage:
    OMP_NUM_THREADS=1 python benchmarks/bench_surface.py [--resolutions 128 256 512]
        [--batch 4] [--repeats 3] [--out benchmarks/results/surface.json]

For each resolution R: ``rasterize_uv`` wall time (all faces, numpy), the valid-pixel and
overlapping-pixel counts (all faces and body component only), and ``position_map`` of a
batch of posed bodies (torch). The slow ``rasterize_uv_reference`` is timed at R = 16
only. Median of --repeats runs after one warm-up; building the anny body is not timed.
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np
import torch

from pocoloco.body import NUM_JOINTS, AnnyBody
from pocoloco.body.surface import (
    largest_component_faces,
    position_map,
    rasterize_uv,
    rasterize_uv_reference,
)
from pocoloco.utils.atomic import write_json_atomic
from pocoloco.utils.timing import median_seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolutions", type=int, nargs="+", default=[128, 256, 512])
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=os.path.join("benchmarks", "results", "surface.json"))
    args = parser.parse_args()
    if args.repeats < 1 or args.batch < 1 or min(args.resolutions) < 1:
        raise SystemExit("--repeats, --batch and --resolutions must be >= 1")

    body = AnnyBody()
    uv, uv_faces = body.uv, body.uv_faces
    body_only = largest_component_faces(body.faces)
    rot = np.random.default_rng(0).normal(scale=0.2, size=(args.batch, NUM_JOINTS, 3)).astype(np.float32)
    verts = torch.from_numpy(body.pose(rot).vertices)  # (B, V, 3)

    rows = []
    for R in args.resolutions:
        r = rasterize_uv(uv, uv_faces, R)
        rb = rasterize_uv(uv, uv_faces, R, face_mask=body_only)
        rows.append({
            "resolution": R,
            "rasterize_s": median_seconds(lambda: rasterize_uv(uv, uv_faces, R), args.repeats),
            "position_map_s": median_seconds(lambda: position_map(verts, body.faces, r), args.repeats),
            "valid_pixels": r.num_valid, "overlapping_pixels": r.num_overlapping,
            "valid_pixels_body_only": rb.num_valid, "faces_hit": int(np.unique(r.face_idx[r.mask]).size),
        })
    ref_s = median_seconds(lambda: rasterize_uv_reference(uv, uv_faces, 16), 1)
    fast16 = median_seconds(lambda: rasterize_uv(uv, uv_faces, 16), args.repeats)

    print(f"{'R':>5} {'raster s':>9} {'posmap s':>9} {'valid':>8} {'body only':>9} {'overlap':>8} {'faces hit':>9}")
    for w in rows:
        print(f"{w['resolution']:>5} {w['rasterize_s']:>9.4f} {w['position_map_s']:>9.4f} {w['valid_pixels']:>8} "
              f"{w['valid_pixels_body_only']:>9} {w['overlapping_pixels']:>8} {w['faces_hit']:>9}")
    print(f"R=16: rasterize_uv {fast16:.4f} s, rasterize_uv_reference {ref_s:.2f} s")
    result = {
        "benchmark": f"pocoloco.body.surface on anny 0.6 UVs ({len(uv_faces)} faces); position_map batch {args.batch}",
        "torch_threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(), "load_avg_1min": os.getloadavg()[0], "repeats": args.repeats,
        "rows": rows, "reference_r16": {"rasterize_s": fast16, "reference_s": ref_s},
    }
    write_json_atomic(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
