"""Paired per-frame comparison of two models scored by ``pocoloco bench quality`` / ``pocoloco eval``.

Each argument names a JSON file and a row in it (``FILE:ROW``, e.g. ``quality.json:pocoloco``); the
frames both rows scored (same frame keys) are paired, and for each metric the table gives both
means over those frames and the mean of the per-frame differences (second minus first) with its
standard error (std / sqrt(n)). The frames and the GT subsets of two ``bench quality`` runs with the
same ``--frames`` / ``--points`` / dataset are identical, so the pairing removes the frame-to-frame
spread that dominates an unpaired comparison.

    python benchmarks/compare_quality.py benchmarks/results/quality_medium/test/quality.json:pocoloco \\
        out/gpu_test/quality.json:pocoloco --also benchmarks/results/quality_medium/test/quality.json:pop --json cmp.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

METRICS = ("chamfer_cm", "s2m_cm", "m2s_cm", "best_of_k_chamfer_cm", "energy_score_cm", "energy_score_adj_cm", "s2m_garment_cm",
           "m2s_garment_cm", "fscore_2cm_pct", "loose_pred_pct", "loose_gt_pct", "outlier_10cm_pct")


def frame_rows(spec: str) -> dict[str, dict[str, float]]:
    """``FILE:ROW`` -> {frame key: metrics} (a one-line error naming what is missing)."""
    path, _, row = spec.rpartition(":")
    data = json.loads(Path(path).read_text())
    frames = data.get("frames")
    if isinstance(frames, dict):
        if row not in frames:
            raise SystemExit(f"{path}: no row {row!r} (it has {', '.join(frames)})")
        rows = frames[row]
    else:  # eval.json: a list of per-frame rows of one model
        rows = frames or data.get("rows") or []
    return {r["key"]: r.get("model", r) for r in rows}


def paired(a: dict, b: dict, metric: str) -> dict[str, float] | None:
    # a metric is null (NaN) on some frames, e.g. the garment columns of a tight subject: those frames are left out
    keys = [k for k in a if k in b and a[k].get(metric) is not None and b[k].get(metric) is not None]
    if not keys:
        return None
    xa = [float(a[k][metric]) for k in keys]
    xb = [float(b[k][metric]) for k in keys]
    d = [y - x for x, y in zip(xa, xb, strict=True)]
    n = len(d)
    mean = sum(d) / n
    se = math.sqrt(sum((v - mean) ** 2 for v in d) / (n - 1) / n) if n > 1 else float("nan")
    return {"n": n, "first": sum(xa) / n, "second": sum(xb) / n, "diff": mean, "se": se}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("first", help="FILE:ROW, the reference")
    ap.add_argument("second", help="FILE:ROW, the model compared with it")
    ap.add_argument("--also", nargs="*", default=[], help="more references FILE:ROW, each paired with the second")
    ap.add_argument("--metrics", nargs="+", default=list(METRICS))
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    second = frame_rows(args.second)
    out = {}
    for ref in [args.first, *args.also]:
        first = frame_rows(ref)
        out[ref] = {}
        print(f"{args.second}  vs  {ref}")
        for m in args.metrics:
            r = paired(first, second, m)
            if r is None:
                continue
            out[ref][m] = r
            print(f"  {m:22s} n={r['n']:3d}  {r['first']:8.3f} -> {r['second']:8.3f}   diff {r['diff']:+.3f} +- {r['se']:.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"second": args.second, "comparisons": out}, indent=1))
    return out


if __name__ == "__main__":
    main()
