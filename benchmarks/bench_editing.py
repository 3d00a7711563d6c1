"""Pose editing: detail kept in unchanged regions vs. the target pose met, per edit mode.

Pairs of test frames of the same sequence, source = frame i, target = frame i + ``--k``
(``--pairs`` sources evenly spaced over the frames that have a partner). For each pair,
:func:`pocoloco.apps.editing.evaluate_edit` edits the source scan to the target pose with
``renoise`` at each ``--ts`` (SDEdit), ``region`` (moving bones inpainted from noise), and
compares with ``scratch`` (a fresh sample of the target pose) and ``copy`` (the source moved with
the root). Metrics (PocoLoco Chamfer, cm):

* unchanged: output points whose nearest target bone is static vs. the source's points whose
  nearest source bone is static (how much of the source survives where nothing moved);
* target: the whole output vs. the GT target frame (how well the target pose is met).

    python benchmarks/bench_editing.py --ckpt default --data data/small
    python benchmarks/bench_editing.py --ckpt runs/small --data data/small --pairs 2 --points 1024

Prints the table and writes ``--out`` (JSON, default benchmarks/results/editing.json).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from pocoloco.apps.editing import DEFAULT_THRESHOLD_M, evaluate_edit
from pocoloco.data import format as fmt
from pocoloco.engine.checkpoint import resolve_checkpoint
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.evaluation.baselines import select_frames
from pocoloco.methods import load_method
from pocoloco.utils.atomic import jsonable, write_json_atomic

KEYS = ("unchanged_chamfer_cm", "target_chamfer_cm", "moved_joints", "static_share")


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", default="default", help="checkpoint / run folder, or 'default' (the shipped model)")
    p.add_argument("--data", default="data/small", help="dataset folder")
    p.add_argument("--split", default="test")
    p.add_argument("--k", type=int, default=10, help="target = source frame + k (default 10)")
    p.add_argument("--pairs", type=int, default=6, help="source frames, evenly spaced (default 6)")
    p.add_argument("--ts", type=int, nargs="+", default=[100, 300], help="renoise start steps (default 100 300)")
    p.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD_M, help="region: joint moved threshold, m")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="one edit per seed and method (default 0)")
    p.add_argument("--points", type=int, default=2048, help="N points per cloud (default 2048)")
    p.add_argument("--sampler", default="dpm++")
    p.add_argument("--steps", type=int, help="sampler steps (default: the sampler's, at most t)")
    p.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    p.add_argument("--out", default="benchmarks/results/editing.json")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.k < 1:
        p.error("--k must be >= 1")

    ckpt = resolve_checkpoint(resolve_ckpt_arg(args.ckpt))
    loaded = load_method(ckpt, expect="pocoloco")

    def prior_for(subject: str):  # a model that knows who wears what draws the subject's own outfit
        return loaded.point_prior(loaded.outfit_id(subject) if loaded.outfit_names() else None)

    layout = fmt.DatasetLayout(args.data)
    candidates = []  # (subject, sequence, source index, target index)
    for subject in layout.subjects():
        for sequence in layout.sequences(subject, args.split):
            idx = set(layout.frame_indices(subject, args.split, sequence))
            candidates += [(subject, sequence, i, i + args.k) for i in sorted(idx) if i + args.k in idx]
    if not candidates:
        p.error(f"no frame pairs {args.k} apart in split {args.split!r} of {args.data}")
    chosen = [candidates[i] for i in select_frames(candidates, args.pairs)]
    rows = []
    t0 = time.perf_counter()
    for subject, sequence, i, j in chosen:
        src = fmt.read_frame(layout.frame_path(subject, args.split, sequence, i), ["points", "joints"])
        tgt = fmt.read_frame(layout.frame_path(subject, args.split, sequence, j), ["points", "joints"])
        for seed in args.seeds:
            res = evaluate_edit(prior_for(subject), src.points, src.joints, tgt.points, tgt.joints, args.points,
                                seed=seed, sampler=args.sampler, steps=args.steps, renoise_ts=args.ts,
                                threshold=args.threshold)  # fmt: skip
            for method, m in res.items():
                rows.append({"pair": f"{subject}/{sequence}/{i}->{j}", "subject": subject, "seed": seed,
                             "method": method, **m})  # fmt: skip
            parts = [f"{k} {m['unchanged_chamfer_cm']:.2f}/{m['target_chamfer_cm']:.2f}" for k, m in res.items()]
            print(f"{subject}/{sequence} {i}->{j} seed {seed}: " + ", ".join(parts), flush=True)
    seconds = time.perf_counter() - t0
    methods = list(dict.fromkeys(r["method"] for r in rows))
    means = {m: {k: float(np.nanmean([r[k] for r in rows if r["method"] == m])) for k in KEYS} for m in methods}
    print(f"\n{'method':>13} {'unchanged cm':>13} {'target cm':>10}   (Chamfer to the source's static region / "
          f"to the GT target frame)")  # fmt: skip
    for m, v in means.items():
        print(f"{m:>13} {v['unchanged_chamfer_cm']:>13.2f} {v['target_chamfer_cm']:>10.2f}")
    first = next(iter(means.values()))
    print(f"pairs {len(chosen)}, k = {args.k}: {first['moved_joints']:.1f} joints moved on average, "
          f"{100 * first['static_share']:.0f}% of the source static")  # fmt: skip
    result = {"checkpoint": str(ckpt), "data": args.data, "split": args.split, "k": args.k, "pairs": len(chosen),
              "ts": args.ts, "threshold_m": args.threshold, "seeds": args.seeds, "points": args.points,
              "sampler": args.sampler, "steps": args.steps, "threads": torch.get_num_threads(),
              "machine": platform.processor() or platform.machine(), "seconds_total": seconds, "means": means,
              "rows": rows}  # fmt: skip
    write_json_atomic(args.out, jsonable(result), indent=None)  # per-frame rows: compact
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
