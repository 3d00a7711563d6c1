"""Paired probe behind ``--even`` for PocoLoco: its points are samples with no spot on a surface to
spread, so ``predict_clouds`` spreads the points themselves, and farthest-point sampling keeps a
generated point that strays from the rest first. Does dropping the most isolated candidates first
help? Same frames / GT subsets as ``pocoloco bench quality`` (28 frames, 2,048 points), one cloud of
4 N points per frame (seed 0), cut to N by: ``random`` (N of them at random: the layout as drawn),
``fps`` (what ``--even`` does), ``fps_trim{q}`` (FPS after dropping the q % of candidates farthest
from their 8th nearest neighbour).

    python benchmarks/experiments/even_trim_pilot.py --data ~/.cache/pocoloco/data/medium --split test --json OUT.json
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np
import torch
from quality_frames import quality_frames
from scipy.spatial import cKDTree

from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.evaluation.metrics import m2s_cm, s2m_cm
from pocoloco.methods import load_method
from pocoloco.ops.sampling import farthest_point_sampling
from pocoloco.utils.atomic import write_json_atomic


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--ckpt", default="default")
    p.add_argument("--frames", type=int, default=28)
    p.add_argument("--points", type=int, default=2048)
    p.add_argument("--trim", type=float, nargs="+", default=[2, 5, 10], help="percent of candidates dropped before FPS")
    p.add_argument("--json", required=True)
    args = p.parse_args()
    torch.set_num_threads(1)
    method, n = load_method(resolve_ckpt_arg(args.ckpt)), args.points

    def fps(points: np.ndarray) -> np.ndarray:
        return points[farthest_point_sampling(torch.from_numpy(np.ascontiguousarray(points))[None], n)[0].numpy()]

    rows = []
    for i, key, _, gt, pose in quality_frames(method, args.data, args.split, args.frames, n):
        dense = method.predict(pose, 4 * n, (0,)).points[0]
        arms = {"random": dense[np.random.default_rng(i).choice(len(dense), n, replace=False)], "fps": fps(dense)}
        isolation = cKDTree(dense).query(dense, k=9)[0][:, -1]  # distance to the 8th nearest other candidate
        for q in args.trim:
            arms[f"fps_trim{q:g}"] = fps(dense[isolation <= np.quantile(isolation, 1 - q / 100)])
        row = {"key": key}
        for arm, cloud in arms.items():
            m2s, s2m = m2s_cm(cloud.astype(np.float64), gt), s2m_cm(cloud.astype(np.float64), gt)
            row[arm] = {"chamfer_cm": round(m2s + s2m, 4), "m2s_cm": round(m2s, 4), "s2m_cm": round(s2m, 4)}
        rows.append(row)
        print(i, key, {a: v["chamfer_cm"] for a, v in row.items() if a != "key"}, flush=True)
    means = {}
    print("| arm | Chamfer (M2S / S2M) | minus random, paired |\n|---|---|---|")
    for arm in (a for a in rows[0] if a != "key"):
        m = {k: float(np.mean([r[arm][k] for r in rows])) for k in ("chamfer_cm", "m2s_cm", "s2m_cm")}
        d = np.array([r[arm]["chamfer_cm"] - r["random"]["chamfer_cm"] for r in rows])
        m["diff_cm"], m["se_cm"] = float(d.mean()), float(d.std(ddof=1) / math.sqrt(len(d)))
        means[arm] = m
        print(f"| {arm} | {m['chamfer_cm']:.2f} ({m['m2s_cm']:.2f} / {m['s2m_cm']:.2f}) | {m['diff_cm']:+.3f} +- {m['se_cm']:.3f} |")
    write_json_atomic(args.json, {"command": "python " + " ".join(sys.argv), "split": args.split, "means": means,
                                  "frames": rows}, indent=None)  # fmt: skip


if __name__ == "__main__":
    main()
