"""Scan completion scored on the hole: generated points vs. the removed surface, against a fresh sample.

For ``--frames`` held-out frames (evenly spaced over the split, so spread over the subjects),
every region of ``--regions`` (:data:`pocoloco.apps.completion.REGIONS`: below the knees, one
knee, one hand) and every seed, the region's points are removed from the full scan (with its
normals, as a scan file would carry them) and the rest is completed into ``--points`` points.
Each method's *generated* points are scored on the hole with
:func:`pocoloco.apps.completion.score_hole` (cm):

* hole S2M: removed scan points -> nearest generated point (is the hole covered?);
* hole M2S: generated points -> nearest point of the full scan (are they on the surface?);
* far: share of generated points more than 5 cm off the full scan; s: seconds per completion.

Methods (``--methods``, :data:`METHODS`):

* ``fresh``: a fresh full sample of the pose (the output's seed); its "generated points" are
  those whose nearest full-scan point lies in the removed region (an oracle selection);
* ``repaint``: plain RePaint from pure noise (``init="noise"``, probe coverage);
* ``old``: the previous default: init "sample", one candidate, distance-only hole test with a
  6 cm radius, no resampling;
* ``new``: ``complete``'s defaults (best-of-K candidates, normal-cone hole test);
* ``k1``, ``resample``, ``t0``, ``est_normals``: the new default with one candidate / RePaint
  resampling in the chain (4 passes, jumps of 5 steps) / no chain / the scan's normals estimated
  from its points (a scan file without normals), to see what each piece does.

The K candidate samples are drawn once per (frame, seed) and shared by the sample-init methods
(candidate 0 is the fresh sample); each method's seconds include its share (K x one sample).
Paired differences (method - fresh, per frame, region and seed) are printed with their standard
errors.

    nice -n 15 python benchmarks/bench_completion.py --frames 9 --seeds 0 1
    nice -n 15 python benchmarks/bench_completion.py --frames 1 --regions right_knee --out /tmp/c.json

Writes ``--out`` (JSON, default benchmarks/results/completion.json).
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch

from pocoloco.apps.completion import (
    DEFAULT_CANDIDATES,
    REGIONS,
    complete,
    draw_candidates,
    region_mask,
    score_hole,
)
from pocoloco.data import format as fmt
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.evaluation.baselines import select_frames
from pocoloco.evaluation.metrics import nearest
from pocoloco.methods import load_method
from pocoloco.utils.atomic import jsonable, write_json_atomic

#: method name -> keyword arguments of ``complete`` (None: the fresh sample itself)
METHODS: dict[str, dict | None] = {
    "fresh": None,
    "repaint": {"init": "noise"},
    "old": {"candidates": 1, "radius": 0.06, "max_cos": None},
    "new": {},
    "k1": {"candidates": 1},
    "resample": {"resample": 4, "jump": 5},
    "t0": {"t": 0},
    "est_normals": {"partial_normals": None},
}
KEYS = ("s2m_cm", "m2s_cm", "far_share", "num", "seconds")


def _mean_se(v: list[float]) -> tuple[float, float]:
    a = np.asarray(v, np.float64)
    a = a[np.isfinite(a)]
    if len(a) == 0:
        return float("nan"), float("nan")
    return float(a.mean()), float(a.std(ddof=1) / np.sqrt(len(a))) if len(a) > 1 else float("nan")


def summarise(rows: list[dict], regions: list[str], methods: list[str]) -> dict[str, dict]:
    """Per region (and "all"): each method's mean scores and, paired by row, its mean difference to
    fresh (+- standard error) and the share of rows where it is <= fresh."""
    summary: dict[str, dict] = {}
    for region in [*regions, "all"]:
        sel = [r for r in rows if region in ("all", r["region"])]
        if not sel:
            continue
        summary[region] = {"n": len(sel)}
        for name in methods:
            s = {k: _mean_se([r[name][k] for r in sel])[0] for k in KEYS}
            if name != "fresh" and "fresh" in methods:
                for k in ("s2m_cm", "m2s_cm"):
                    diff = [r[name][k] - r["fresh"][k] for r in sel]
                    s[f"{k}_minus_fresh"], s[f"{k}_minus_fresh_se"] = _mean_se(diff)
                    s[f"{k}_le_fresh_share"] = float(np.mean([d <= 0 for d in diff if np.isfinite(d)] or [np.nan]))
            summary[region][name] = s
    return summary


def markdown_table(summary: dict[str, dict], methods: list[str]) -> str:
    """The summary as a markdown table (one row per region and method; differences to fresh paired)."""
    lines = ["| region (n) | method | hole S2M cm | hole M2S cm | > 5 cm off | #gen | s | S2M - fresh | M2S - fresh |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for region, s in summary.items():
        for name in methods:
            m = s[name]
            d = ["", ""] if "s2m_cm_minus_fresh" not in m else [
                f"{m[k + '_minus_fresh']:+.2f} +- {m[k + '_minus_fresh_se']:.2f} ({100 * m[k + '_le_fresh_share']:.0f} % <=)"
                for k in ("s2m_cm", "m2s_cm")]  # fmt: skip
            lines.append(f"| {region} ({s['n']}) | {name} | {m['s2m_cm']:.2f} | {m['m2s_cm']:.2f} | "
                         f"{100 * m['far_share']:.1f} % | {m['num']:.0f} | {m['seconds']:.1f} | {d[0]} | {d[1]} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", default="default", help="checkpoint / run folder, or 'default' (the shipped model)")
    p.add_argument("--data", default="data/small", help="dataset folder")
    p.add_argument("--split", default="test")
    p.add_argument("--frames", type=int, default=9, help="frames, evenly spaced over the split (default 9)")
    p.add_argument("--regions", nargs="+", default=["below_knees", "right_knee", "left_hand"],
                   help=f"from {', '.join(REGIONS)} (default below_knees right_knee left_hand)")  # fmt: skip
    p.add_argument("--methods", nargs="+", default=["fresh", "repaint", "old", "new"],
                   help=f"from {', '.join(METHODS)} (default fresh repaint old new)")  # fmt: skip
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="one completion per seed (default 0 1)")
    p.add_argument("--points", type=int, default=2048, help="N points per cloud (default 2048)")
    p.add_argument("--candidates", type=int, default=DEFAULT_CANDIDATES,
                   help=f"K candidates drawn per (frame, seed) (default {DEFAULT_CANDIDATES})")  # fmt: skip
    p.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    p.add_argument("--out", default="benchmarks/results/completion.json")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    for name, known in (("regions", REGIONS), ("methods", METHODS)):
        unknown = [r for r in getattr(args, name) if r not in known]
        if unknown:
            p.error(f"unknown {name} {unknown}; choose from {', '.join(known)}")

    method = load_method(resolve_ckpt_arg(args.ckpt), expect="pocoloco")
    layout = fmt.DatasetLayout(args.data)
    frames = layout.iter_frames(args.split, layout.subjects())
    chosen = [frames[i] for i in select_frames(frames, args.frames)]
    K = max([args.candidates] + [int(METHODS[m].get("candidates", args.candidates)) for m in args.methods
                                 if METHODS[m] is not None])  # fmt: skip
    rows = []
    t_start = time.perf_counter()
    for subject, sequence, path in chosen:
        fr = fmt.read_frame(path, ["points", "normals", "joints"])
        # a model that knows who wears what completes the frame's own outfit
        prior = method.point_prior(method.outfit_id(subject) if method.outfit_names() else None)
        for seed in args.seeds:
            t0 = time.perf_counter()
            cands = draw_candidates(prior, fr.joints, args.points, [seed], K)
            per_sample = (time.perf_counter() - t0) / K
            fresh = cands.points[0, 0]  # candidate 0 has the output's seed: the fresh sample
            fresh_in = None
            for region in args.regions:
                inside = region_mask(fr.points, fr.joints, region)
                if not inside.any() or inside.all():
                    continue
                partial, partial_n = fr.points[~inside], fr.normals[~inside]
                row = {"frame": f"{subject}/{sequence}/{path.stem}", "subject": subject, "region": region,
                       "seed": seed, "removed_share": float(inside.mean())}  # fmt: skip
                for name in args.methods:
                    kw = METHODS[name]
                    if kw is None:
                        fresh_in = inside[nearest(fresh, fr.points)[1]]
                        m = score_hole(fresh[fresh_in], fr.points, inside) | {"seconds": per_sample}
                    else:
                        kw = {"candidates": args.candidates, "partial_normals": partial_n} | kw
                        t0 = time.perf_counter()
                        comp = complete(prior, partial, fr.joints, args.points, seeds=[seed],
                                        samples=None if kw.get("init") == "noise" else cands, **kw)  # fmt: skip
                        sec = time.perf_counter() - t0
                        if kw.get("init") != "noise":
                            sec += kw["candidates"] * per_sample
                        m = score_hole(comp.points[0][~comp.known[0]], fr.points, inside) | {"seconds": sec}
                    row[name] = m
                rows.append(row)
                print(f"{row['frame']} {region:>11} seed {seed} (removed {100 * row['removed_share']:.0f} %): "
                      + ", ".join(f"{n} {row[n]['s2m_cm']:.2f}/{row[n]['m2s_cm']:.2f}/{100 * row[n]['far_share']:.0f}%"
                                  f" ({row[n]['num']:.0f})" for n in args.methods), flush=True)  # fmt: skip
        write_json_atomic(f"{args.out}.partial", jsonable({"rows": rows}))  # survives an interrupted run
    seconds = time.perf_counter() - t_start

    summary = summarise(rows, args.regions, args.methods)
    print(f"\nhole S2M / M2S cm (mean), far = generated points > 5 cm off, #gen, s per completion; "
          f"d = paired mean difference to fresh +- s.e. ({len(chosen)} frames x {len(args.seeds)} seeds)")
    print(f"{'region':>11} {'n':>3} {'method':>9} {'S2M':>6} {'M2S':>6} {'far %':>6} {'#gen':>5} {'s':>6} "
          f"{'d S2M':>13} {'d M2S':>13}")  # fmt: skip
    for region, s in summary.items():
        for name in args.methods:
            m = s[name]
            d = ("" if name == "fresh" or "fresh" not in args.methods else
                 f"{m['s2m_cm_minus_fresh']:>+6.2f}+-{m['s2m_cm_minus_fresh_se']:<5.2f} "
                 f"{m['m2s_cm_minus_fresh']:>+6.2f}+-{m['m2s_cm_minus_fresh_se']:<5.2f}")  # fmt: skip
            print(f"{region:>11} {s['n']:>3} {name:>9} {m['s2m_cm']:>6.2f} {m['m2s_cm']:>6.2f} "
                  f"{100 * m['far_share']:>6.1f} {m['num']:>5.0f} {m['seconds']:>6.1f} {d}")  # fmt: skip
    print("\n" + markdown_table(summary, args.methods))
    result = {"checkpoint": str(method.path), "data": args.data, "split": args.split, "frames": len(chosen),
              "regions": {r: vars(REGIONS[r]) for r in args.regions}, "seeds": args.seeds, "points": args.points,
              "candidates": args.candidates, "methods": {m: METHODS[m] for m in args.methods},
              "settings": "complete's defaults unless the method says otherwise; the scan's normals are passed",
              "threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
              "seconds_total": seconds, "summary": summary, "rows": rows}  # fmt: skip
    write_json_atomic(args.out, jsonable(result), indent=None)  # per-frame rows: compact
    Path(f"{args.out}.partial").unlink(missing_ok=True)  # the finished run replaces it
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
