"""Animation: flicker and accuracy of independent vs. shared-noise vs. chained frames.

For every test sequence (or ``--sequences``), ``--length`` consecutive frames (every
``--stride``-th, from ``--start``) are animated with each method of ``--methods``
(``pocoloco.apps.animation``: independent, shared-noise, chain, and ``chain-world`` = chain with
``anchor="world"``) and scored with :func:`pocoloco.apps.animation.evaluate_animation`:

* flicker: mean PocoLoco Chamfer (cm) between frame k warped by the body motion (each point
  moved like its nearest posed-body vertex) and frame k+1; the ground truth's own flicker
  (N-point subsets of consecutive scans) is the floor;
* accuracy: mean Chamfer (cm) of each frame to its GT scan (N-point subset).

    python benchmarks/bench_animation.py --ckpt default --data data/small
    python benchmarks/bench_animation.py --ckpt runs/small --data data/small --length 4 --points 1024

Prints the table and writes ``--out`` (JSON, default benchmarks/results/animation.json).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from pocoloco.apps.animation import animate, evaluate_animation
from pocoloco.data import format as fmt
from pocoloco.engine.checkpoint import resolve_checkpoint
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.methods import load_method
from pocoloco.utils.atomic import jsonable, write_json_atomic

METHODS = ("independent", "shared-noise", "chain", "chain-world")


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", default="default", help="checkpoint / run folder, or 'default' (the shipped model)")
    p.add_argument("--data", default="data/small", help="dataset folder")
    p.add_argument("--split", default="test")
    p.add_argument("--sequences", nargs="+", help="subject/sequence names (default: every sequence of the split)")
    p.add_argument("--start", type=int, default=0, help="first frame index (default 0)")
    p.add_argument("--length", type=int, default=8, help="frames per sequence (default 8)")
    p.add_argument("--stride", type=int, default=1, help="use every stride-th frame (default 1)")
    p.add_argument("--methods", nargs="+", default=list(METHODS), help=f"from {', '.join(METHODS)}")
    p.add_argument("--t", type=int, default=200, help="chain: renoising step (default 200)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--points", type=int, default=2048, help="N points per frame (default 2048)")
    p.add_argument("--sampler", default="dpm++")
    p.add_argument("--steps", type=int, help="sampler steps (default: the sampler's, at most t for chain steps)")
    p.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    p.add_argument("--out", default="benchmarks/results/animation.json")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    bad = [m for m in args.methods if m not in METHODS]
    if bad or args.length < 2 or args.stride < 1:
        p.error(f"methods from {', '.join(METHODS)}; --length >= 2; --stride >= 1")

    ckpt = resolve_checkpoint(resolve_ckpt_arg(args.ckpt))
    loaded = load_method(ckpt, expect="pocoloco")

    def prior_for(subject: str):  # a model that knows who wears what draws the subject's own outfit
        return loaded.point_prior(loaded.outfit_id(subject) if loaded.outfit_names() else None)

    layout = fmt.DatasetLayout(args.data)
    seqs = [(s, q) for s in layout.subjects() for q in layout.sequences(s, args.split)]
    if args.sequences:
        seqs = [sq for sq in seqs if f"{sq[0]}/{sq[1]}" in args.sequences]
    rows = []
    t0 = time.perf_counter()
    for subject, sequence in seqs:
        idx = layout.frame_indices(subject, args.split, sequence)[args.start :: args.stride][: args.length]
        if len(idx) < 2:
            continue
        paths = [layout.frame_path(subject, args.split, sequence, i) for i in idx]
        joints = np.stack([fmt.read_frame(q, ["joints"]).joints for q in paths])
        gt_row = None
        for method in args.methods:
            ts = time.perf_counter()
            anim = animate(prior_for(subject), joints, args.points, method=method.replace("-world", ""), t=args.t,
                           sampler=args.sampler, steps=args.steps, seed=args.seed,
                           anchor="world" if method == "chain-world" else "root")  # fmt: skip
            sec = (time.perf_counter() - ts) / len(idx)
            m = evaluate_animation(anim.points, paths, args.points, seed=args.seed)
            rows.append({"sequence": f"{subject}/{sequence}", "method": method, "frames": idx,
                         "flicker_cm": m["flicker_mean_cm"], "chamfer_to_gt_cm": m["chamfer_to_gt_mean_cm"],
                         "seconds_per_frame": sec, "per_frame": m})  # fmt: skip
            gt_row = {"sequence": f"{subject}/{sequence}", "method": "ground truth", "frames": idx,
                      "flicker_cm": m["gt_flicker_mean_cm"], "chamfer_to_gt_cm": float("nan")}  # fmt: skip
            print(f"{subject}/{sequence} {method:>12}: flicker {m['flicker_mean_cm']:.2f} cm (GT "
                  f"{m['gt_flicker_mean_cm']:.2f}), Chamfer to GT {m['chamfer_to_gt_mean_cm']:.2f} cm, "
                  f"{sec:.2f} s/frame", flush=True)  # fmt: skip
        if gt_row is not None:
            rows.append(gt_row)
    seconds = time.perf_counter() - t0
    means = {}
    for method in [*args.methods, "ground truth"]:
        sel = [r for r in rows if r["method"] == method]
        if sel:
            means[method] = {"flicker_cm": float(np.mean([r["flicker_cm"] for r in sel])),
                             "chamfer_to_gt_cm": float(np.mean([r["chamfer_to_gt_cm"] for r in sel])),
                             "sequences": len(sel)}  # fmt: skip
    print(f"\n{'method':>13} {'flicker cm':>11} {'Chamfer to GT cm':>17}")
    for method, m in means.items():
        acc = "-" if np.isnan(m["chamfer_to_gt_cm"]) else f"{m['chamfer_to_gt_cm']:.2f}"
        print(f"{method:>13} {m['flicker_cm']:>11.2f} {acc:>17}")
    result = {"checkpoint": str(ckpt), "data": args.data, "split": args.split, "start": args.start,
              "length": args.length, "stride": args.stride, "t": args.t, "seed": args.seed, "points": args.points,
              "sampler": args.sampler, "steps": args.steps, "threads": torch.get_num_threads(),
              "machine": platform.processor() or platform.machine(), "seconds_total": seconds, "means": means,
              "rows": rows}  # fmt: skip
    write_json_atomic(args.out, jsonable(result), indent=None)  # per-frame rows: compact
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
