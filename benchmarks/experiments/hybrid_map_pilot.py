"""Paired pilot of the hybrid's free-region rule (issue 26): for each map variant, the hybrid of the
shipped POP and a PocoLoco (``--free``) on the same test frames and seeds, against POP; Chamfer,
loose share, garment S2M and far points, with the paired difference to POP (mean +- standard
error). Rows "mix a": the first map, with the generator drawing a share a of the free region's
points and POP the rest (its own points in that region). Row "oracle": the first map's split with the scan's own free-region points in place of the
generator's (what a perfect generator would score).

    python benchmarks/experiments/hybrid_map_pilot.py --data ~/.cache/pocoloco/data/medium \
        --split test --out benchmarks/results/hybrid_map_pilot_test.json
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import torch

from pocoloco.data.format import DatasetLayout, read_frame
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.evaluation.metrics import evaluate_frame
from pocoloco.methods import load_method
from pocoloco.methods.base import SamplerOptions
from pocoloco.methods.hybrid import learn_free_maps, point_regions

#: generator shares of the free region (POP draws the rest of it)
MIX = (0.25, 0.5, 0.75)
KEYS = ("chamfer_cm", "loose_pred_pct", "loose_gt_pct", "s2m_garment_cm", "outlier_10cm_pct")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--free", default="default", help="PocoLoco checkpoint of the free region")
    p.add_argument("--points", type=int, default=2048)
    p.add_argument("--steps", type=int, default=10, help="SDE steps of the free region")
    p.add_argument("--per-subject", type=int, default=2, help="frames per subject")
    p.add_argument("--out", required=True)
    args = p.parse_args()
    torch.set_num_threads(1)
    pop = load_method(resolve_ckpt_arg("default:pop"))
    gen = load_method(resolve_ckpt_arg(args.free))
    variants = {"labels or 3 cm": dict(margin=0.03, labels=True), "3 cm": dict(margin=0.03, labels=False),
                "2 cm": dict(margin=0.02, labels=False), "5 cm": dict(margin=0.05, labels=False)}  # fmt: skip
    maps = {name: learn_free_maps(args.data, pop.outfit_names(), **kw) for name, kw in variants.items()}
    opt = SamplerOptions(steps=args.steps)
    N, rows = args.points, []
    for s, path in pilot_frames(args.data, args.split, args.per_subject):
        fr = read_frame(path, allow_missing=True)
        pose = pop.pose_from_frame(path, s, frame=fr)
        o = pop.outfit_id(s)
        pop_pts = pop.predict(pose, N, seeds=(0,), outfit=o).points[0]
        pop_all = pop.predict(pose, len(pop.model.query_points()), seeds=(0,), outfit=o).points[0]
        for seed in (0, 1):
            if s in gen.outfit_names() or not gen.outfit_names():
                go = gen.outfit_id(s) if gen.outfit_names() else None
                gen_pts = gen.predict(pose, 3 * N, seeds=(seed,), outfit=go, options=opt).points[0]
            else:  # a generator trained on free regions only never saw a wholly attached outfit
                gen_pts = np.zeros((0, 3), np.float32)
            row = {"subject": s, "frame": str(path), "seed": seed}
            row.update({f"pop:{k}": v for k, v in _metrics(pop_pts, fr).items()})
            rng = np.random.default_rng(seed)
            for name, m in maps.items():
                free = m.free(o)
                nf = int(round(m.free_share_of(o) * N))
                att = pop_all[~point_regions(pop_all, fr.body_vertices, free)]
                fre = gen_pts[point_regions(gen_pts, fr.body_vertices, free)]
                parts = [att[rng.choice(len(att), N - nf, replace=len(att) < N - nf)]]
                if nf:
                    parts.append(fre[rng.choice(len(fre), nf, replace=len(fre) < nf)])
                row.update({f"{name}:{k}": v for k, v in _metrics(np.concatenate(parts), fr).items()})
                if name == "labels or 3 cm":
                    # generator share: the generator draws a * nf of the free region's points, POP the rest
                    pop_free = pop_all[point_regions(pop_all, fr.body_vertices, free)]
                    for a in MIX:
                        ng = int(round(a * nf))
                        mix = [parts[0]]
                        if ng:
                            mix.append(fre[rng.choice(len(fre), ng, replace=len(fre) < ng)])
                        if nf - ng:
                            mix.append(pop_free[rng.choice(len(pop_free), nf - ng, replace=len(pop_free) < nf - ng)])
                        row.update({f"mix {a:g}:{k}": v for k, v in _metrics(np.concatenate(mix), fr).items()})
                    # the same split with the scan's own free-region points
                    scan = fr.points[point_regions(fr.points, fr.body_vertices, free)]
                    if nf:
                        parts[1] = scan[rng.choice(len(scan), nf, replace=len(scan) < nf)]
                    row.update({f"oracle:{k}": v for k, v in _metrics(np.concatenate(parts), fr).items()})
            rows.append(row)
            print(s, seed, {n: round(row[f"{n}:chamfer_cm"], 2) for n in ("pop", *maps)}, flush=True)
    summary = {}
    for name in ("pop", *maps, *(f"mix {a:g}" for a in MIX), "oracle"):
        summary[name] = {k: float(np.nanmean([r[f"{name}:{k}"] for r in rows])) for k in KEYS}
        d = np.array([r[f"{name}:chamfer_cm"] - r["pop:chamfer_cm"] for r in rows])
        summary[name]["chamfer_minus_pop"] = float(d.mean())
        summary[name]["chamfer_minus_pop_se"] = float(d.std(ddof=1) / math.sqrt(len(d)))
        if name in maps:
            summary[name]["free_share"] = {o: float(x) for o, x in zip(maps[name].outfits, maps[name].point_share, strict=True)}
    print(f"| map | Chamfer cm | minus POP | loose % (scan {summary['pop']['loose_gt_pct']:.1f}) | garment S2M cm | >10 cm % |")
    print("|---|---|---|---|---|---|")
    for name, m in summary.items():
        print(f"| {name} | {m['chamfer_cm']:.2f} | {m['chamfer_minus_pop']:+.2f} +- {m['chamfer_minus_pop_se']:.2f} | "
              f"{m['loose_pred_pct']:.1f} | {m['s2m_garment_cm']:.2f} | {m['outlier_10cm_pct']:.2f} |")
    for r in rows:
        r["frame"] = r["frame"].split("/subjects/")[-1]
    with open(args.out, "w") as f:
        json.dump(_rounded({"settings": vars(args), "summary": summary, "rows": rows}), f, separators=(",", ":"))


def pilot_frames(data, split: str, per_subject: int) -> list[tuple[str, object]]:
    """(subject, frame path) of the pilots: per subject, the frames a quarter and three quarters
    into its ``split`` frames (the first ``per_subject`` of those two)."""
    frames: dict[str, list] = {}
    for s, _, path in DatasetLayout(data).iter_frames(split):
        frames.setdefault(s, []).append(path)
    return [(s, path) for s in sorted(frames)
            for path in (frames[s][len(frames[s]) // 4], frames[s][3 * len(frames[s]) // 4])[:per_subject]]  # fmt: skip


def _rounded(x):
    if isinstance(x, float):
        return round(x, 4)
    if isinstance(x, dict):
        return {k: _rounded(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_rounded(v) for v in x]
    return x


def _metrics(points: np.ndarray, fr) -> dict[str, float]:
    m = evaluate_frame(points, None, fr.points, fr.normals, fr.labels)
    return {k: m[k] for k in KEYS}


if __name__ == "__main__":
    main()
