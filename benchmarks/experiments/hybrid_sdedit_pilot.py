"""Paired pilot (issue 26): the hybrid's free region drawn by SDEdit from POP's own points there.

POP's points in the free region are close to the body and miss part of the garment; the free
generator's samples cover the garment but pay for their spread. This pilot renoises POP's
free-region points to step t and denoises them with the hybrid's generator under the pose (SDEdit,
Meng et al. 2022), so each hypothesis starts from POP's shape; rows for several t against the
hybrid as it is (``--ckpt``, e.g. generator share 0.5) and POP, on the same frames and seeds.

    python benchmarks/experiments/hybrid_sdedit_pilot.py --data ~/.cache/pocoloco/data/medium \
        --ckpt RUN --split test --out benchmarks/results/hybrid_sdedit_pilot_test.json
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import torch

from pocoloco.apps.common import denoise_from, to_metres, to_normalised
from hybrid_map_pilot import pilot_frames

from pocoloco.data.format import read_frame
from pocoloco.evaluation.metrics import evaluate_frame
from pocoloco.methods import load_method
from pocoloco.methods.base import SamplerOptions
from pocoloco.methods.hybrid import point_regions

KEYS = ("chamfer_cm", "s2m_cm", "m2s_cm", "loose_pred_pct", "loose_gt_pct", "s2m_garment_cm", "outlier_10cm_pct")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--ckpt", required=True, help="hybrid checkpoint")
    p.add_argument("--split", default="test")
    p.add_argument("--points", type=int, default=2048)
    p.add_argument("--t", type=int, nargs="+", default=[200, 400, 600])
    p.add_argument("--per-subject", type=int, default=2)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    torch.set_num_threads(1)
    hy = load_method(args.ckpt)
    N, rows = args.points, []
    for s, path in pilot_frames(args.data, args.split, args.per_subject):
        fr = read_frame(path, allow_missing=True)
        pose = hy.pose_from_frame(path, s, frame=fr)
        o = hy.outfit_id(s)
        free = hy.maps.free(o)
        n_att, n_free = hy.split(o, N)
        pop = hy.attached.predict(pose, N, seeds=(0,), outfit=o).points[0]
        att = hy._skinned_points(pose, o, free, n_att, 0)
        pop_free = hy._skinned_points(pose, o, free, 0, n_free) if n_free else np.zeros((0, 3), np.float32)
        base = hy.predict(pose, N, seeds=(0, 1), outfit=o).points
        for seed in (0, 1):
            row = {"subject": s, "frame": str(path).split("/subjects/")[-1], "seed": seed}
            row.update({f"pop:{k}": v for k, v in _metrics(pop, fr).items()})
            row.update({f"hybrid:{k}": v for k, v in _metrics(base[seed], fr).items()})
            for t in args.t:
                if n_free:
                    prior = hy.free.point_prior(hy._free_outfit(o))
                    x0 = to_normalised(prior.normalisation, pop_free, None, pose.joints, prior.point_channels)[None]
                    x = denoise_from(prior, pose.joints, x0, t, seeds=[seed])
                    gen = to_metres(prior.normalisation, x, pose.joints)[0][0]
                    keep = gen[point_regions(gen, pose.body_vertices, free)]
                    keep = keep if len(keep) else gen
                    rng = np.random.default_rng([seed, t])
                    cloud = np.concatenate([att, keep[rng.choice(len(keep), n_free, replace=len(keep) < n_free)]])
                else:
                    cloud = att
                row.update({f"sdedit {t}:{k}": v for k, v in _metrics(cloud, fr).items()})
            rows.append(row)
            print(s, seed, {n: round(row[f"{n}:chamfer_cm"], 2) for n in ("pop", "hybrid", *(f"sdedit {t}" for t in args.t))},
                  flush=True)  # fmt: skip
    names = ("pop", "hybrid", *(f"sdedit {t}" for t in args.t))
    summary = {}
    for name in names:
        summary[name] = {k: float(np.nanmean([r[f"{name}:{k}"] for r in rows])) for k in KEYS}
        for ref in ("pop", "hybrid"):
            d = np.array([r[f"{name}:chamfer_cm"] - r[f"{ref}:chamfer_cm"] for r in rows])
            summary[name][f"chamfer_minus_{ref}"] = float(d.mean())
            summary[name][f"chamfer_minus_{ref}_se"] = float(d.std(ddof=1) / math.sqrt(len(d)))
    print(f"| free region | Chamfer cm | minus POP | minus hybrid | loose % (scan {summary['pop']['loose_gt_pct']:.1f}) "
          "| garment S2M cm | M2S cm | >10 cm % |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for name, m in summary.items():
        print(f"| {name} | {m['chamfer_cm']:.2f} | {m['chamfer_minus_pop']:+.2f} +- {m['chamfer_minus_pop_se']:.2f} | "
              f"{m['chamfer_minus_hybrid']:+.2f} +- {m['chamfer_minus_hybrid_se']:.2f} | {m['loose_pred_pct']:.1f} | "
              f"{m['s2m_garment_cm']:.2f} | {m['m2s_cm']:.2f} | {m['outlier_10cm_pct']:.2f} |")  # fmt: skip
    with open(args.out, "w") as f:
        json.dump({"settings": vars(args), "summary": summary, "rows": rows}, f, separators=(",", ":"))


def _metrics(points: np.ndarray, fr) -> dict[str, float]:
    m = evaluate_frame(points, None, fr.points, fr.normals, fr.labels)
    return {k: round(float(m[k]), 4) for k in KEYS}


if __name__ == "__main__":
    main()
