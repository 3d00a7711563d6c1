"""Paired probe: POP's N points drawn uniformly among its UV pixels (as shipped) vs by the body area
each pixel stands for (the hybrid's ``area_weighted`` draw), on the same frames and GT subsets.

    python benchmarks/experiments/pop_area_weighting.py --data ~/.cache/pocoloco/data/medium \
        --hybrid RUN --out ~/.cache/pocoloco/runs/pop_area_weighting.json

``--hybrid``: any hybrid checkpoint; its POP part is the model probed (the shipped POP when it was
assembled with ``--attached default:pop``) and its ``_pixel_areas`` gives the weights.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import torch
from hybrid_map_pilot import pilot_frames

from pocoloco.data.format import read_frame
from pocoloco.evaluation.baselines import subset
from pocoloco.evaluation.metrics import evaluate_frame
from pocoloco.methods import load_method


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--hybrid", required=True)
    p.add_argument("--points", type=int, default=2048)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    torch.set_num_threads(1)
    hy = load_method(args.hybrid)
    pop = hy.attached
    P = len(pop.model.query_points())
    report = {}
    for split in ("test", "heldout"):
        rows = []
        for k, (s, path) in enumerate(pilot_frames(args.data, split, 2)):
            fr = read_frame(path, allow_missing=True)
            o = pop.outfit_id(s)
            pose = pop.pose_from_frame(path, s, frame=fr)
            pixels = pop.predict(pose, P, seeds=(0,), outfit=o).points[0]
            w = hy._pixel_areas(pose, P)
            gsel = subset(len(fr.points), args.points, (0, k))
            uniform = pop.predict(pose, args.points, seeds=(0,), outfit=o).points[0]
            weighted = pixels[np.sort(np.random.default_rng(0).choice(P, args.points, replace=False, p=w / w.sum()))]
            m = [evaluate_frame(c, None, fr.points[gsel], fr.normals[gsel], fr.labels[gsel]) for c in (uniform, weighted)]
            rows.append({"subject": s, **{f"{n}:{key}": float(x[key]) for n, x in zip(("uniform", "area"), m, strict=True)
                                          for key in ("chamfer_cm", "loose_pred_pct")}})  # fmt: skip
        d = np.array([r["area:chamfer_cm"] - r["uniform:chamfer_cm"] for r in rows])
        report[split] = {"uniform_chamfer_cm": float(np.mean([r["uniform:chamfer_cm"] for r in rows])),
                         "area_chamfer_cm": float(np.mean([r["area:chamfer_cm"] for r in rows])),
                         "diff_cm": float(d.mean()), "se_cm": float(d.std(ddof=1) / math.sqrt(len(d))),
                         "uniform_loose_pct": float(np.mean([r["uniform:loose_pred_pct"] for r in rows])),
                         "area_loose_pct": float(np.mean([r["area:loose_pred_pct"] for r in rows])), "rows": rows}  # fmt: skip
        r = report[split]
        print(f"{split}: POP uniform {r['uniform_chamfer_cm']:.3f} cm, area-weighted {r['area_chamfer_cm']:.3f} cm, "
              f"paired {r['diff_cm']:+.3f} +- {r['se_cm']:.3f}; loose {r['uniform_loose_pct']:.1f} -> {r['area_loose_pct']:.1f} %")  # fmt: skip
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
