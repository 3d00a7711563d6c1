"""Is a model resolution-free? Chamfer against the *full* scan as the number of sampled points grows.

For each checkpoint and each N of ``--points``, samples ``--frames`` test frames (spread over every
subject, ``evaluation.baselines.select_frames``) with ``--seeds`` and scores every cloud against the
frame's whole scan (all its points, 40K for the synthetic presets), not an N-point subset of it, so
the target is the same for every N:

- M2S (model to scan): mean distance of a generated point to the scan, cm. Independent of N for a
  resolution-free model (each point should lie on the surface whatever N); it grows if points drift
  off the body at large N (the "tail" failure of a network trained at a few hundred points).
- S2M (scan to model): mean distance of a scan point to the generated cloud, cm. Shrinks as N grows
  (a denser cloud covers the surface better) unless the model leaves parts of the body out.
- Chamfer = S2M + M2S (the PocoLoco convention, evaluation/metrics.py), and the share of generated
  points more than 5 cm / 10 cm from the scan (outliers).

"Must not get worse as N grows" (issue 14) means M2S and the outlier shares stay flat and Chamfer
does not rise. Prints a table per checkpoint, writes JSON, and with ``--figure`` a plot of Chamfer,
S2M and M2S against N.

    python benchmarks/bench_resolution.py --ckpt default RUN_FOLDER --data data/small \\
        --points 2048 10000 50000 --frames 6 --seeds 0 1 --steps 10 --threads 2 \\
        --out benchmarks/results/resolution.json --figure docs/images/chamfer_vs_points.png
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np


def score(pred: np.ndarray, scan: np.ndarray) -> dict[str, float]:
    """M2S / S2M / Chamfer (cm) and outlier shares (%) of one cloud (N, 3) against a scan (M, 3)."""
    from pocoloco.evaluation.metrics import nearest

    d_pred = nearest(pred, scan)[0]  # metres, per generated point
    d_scan = nearest(scan, pred)[0]
    m2s, s2m = 100.0 * float(d_pred.mean()), 100.0 * float(d_scan.mean())
    return dict(m2s_cm=m2s, s2m_cm=s2m, chamfer_cm=m2s + s2m, over_5cm_percent=100.0 * float((d_pred > 0.05).mean()),
                over_10cm_percent=100.0 * float((d_pred > 0.10).mean()))  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", nargs="+", required=True, help="checkpoints or run folders (or default)")
    ap.add_argument("--data", required=True, help="dataset folder (its test frames are scored)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--points", type=int, nargs="+", default=[2048, 10000, 50000])
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--steps", type=int, default=10, help="sampler steps (network calls)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="benchmarks/results/resolution.json")
    ap.add_argument("--figure", default=None, help="PNG of Chamfer / S2M / M2S against N")
    ap.add_argument("--pop-decoded", action="store_true",
                    help="for each POP checkpoint, a second row that decodes points off its training UV map at their "
                         "own UVs (the behaviour before interpolation, POPMethod.finer_map = 'decode')")  # fmt: skip
    ap.add_argument("--even", action="store_true",
                    help="for each checkpoint, a second row with its points spread evenly (SamplerOptions.even, "
                         "``sample --even``: more points drawn, N kept by farthest-point sampling)")  # fmt: skip
    ap.add_argument("--means-only", action="store_true", help="write the means only, not every cloud's row (small JSON)")
    args = ap.parse_args()

    import torch

    from pocoloco.data import format as fmt
    from pocoloco.engine.shipped import resolve_ckpt_arg
    from pocoloco.evaluation.baselines import select_frames
    from pocoloco.methods import SamplerOptions, load_method, predict_clouds

    torch.set_num_threads(args.threads)
    layout = fmt.DatasetLayout(args.data)
    frames = layout.iter_frames(args.split)
    if not frames:
        raise SystemExit(f"{args.data}: no {args.split} frames")
    chosen = [frames[i] for i in select_frames(frames, args.frames)]
    results: dict = {"data": args.data, "split": args.split, "frames": [str(p) for _, _, p in chosen],
                     "seeds": args.seeds, "steps": args.steps, "threads": args.threads, "models": {}}  # fmt: skip
    arms = [(c, None, False) for c in args.ckpt]
    if args.pop_decoded:
        arms += [(c, "decode", False) for c in args.ckpt if load_method(resolve_ckpt_arg(c)).kind == "pop"]
    if args.even:
        arms += [(c, None, True) for c in args.ckpt]
    for ckpt, finer_map, even in arms:
        method = load_method(resolve_ckpt_arg(ckpt))
        if finer_map is not None:
            method.finer_map = finer_map
            ckpt = f"{ckpt} (decoded off its UV map)"
        if even:
            ckpt = f"{ckpt} (even)"
        seeds = args.seeds[:1] if method.deterministic else args.seeds  # a regressor: one cloud per pose
        options = SamplerOptions(steps=args.steps, even=even)
        per_n: dict = {}
        for n in args.points:
            rows, seconds = [], []
            for subject, _, path in chosen:
                fr = fmt.read_frame(path, ["points", "joints", "frame_index", "body_vertices", "vtransf"],
                                    allow_missing=True)  # fmt: skip
                pose = method.pose_from_frame(path, subject, frame=fr)
                outfit = method.outfit_id(subject) if method.outfit_names() else None
                t0 = time.perf_counter()
                pred = predict_clouds(method, pose, n, seeds, outfit, options)
                seconds.append((time.perf_counter() - t0) / len(seeds))
                scan = fr.points.astype(np.float64)
                rows += [score(pred.points[k].astype(np.float64), scan) for k in range(len(seeds))]
            mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
            mean["worst_over_10cm_percent"] = max(r["over_10cm_percent"] for r in rows)
            mean["seconds_per_sample"] = statistics.median(seconds)
            per_n[str(n)] = {"mean": mean} if args.means_only else {"mean": mean, "clouds": rows}
            print(f"{ckpt} N={n}: Chamfer {mean['chamfer_cm']:.2f} cm (S2M {mean['s2m_cm']:.2f}, M2S "
                  f"{mean['m2s_cm']:.2f}), > 10 cm {mean['over_10cm_percent']:.2f} % (worst cloud "
                  f"{mean['worst_over_10cm_percent']:.1f} %), {mean['seconds_per_sample']:.3f} s/sample", flush=True)  # fmt: skip
        results["models"][ckpt] = {"info": method.info(), "by_points": per_n}

    print(f"\n{len(chosen)} {args.split} frames x {len(args.seeds)} seeds, {args.steps} network calls, against the "
          f"full scan ({args.threads} threads)")  # fmt: skip
    print("| model | N | Chamfer cm | S2M cm | M2S cm | > 5 cm % | > 10 cm % (worst cloud) | s / sample |")
    print("|---|---|---|---|---|---|---|---|")
    for ckpt, res in results["models"].items():
        for n, r in res["by_points"].items():
            m = r["mean"]
            print(f"| {ckpt} | {int(n):,} | {m['chamfer_cm']:.2f} | {m['s2m_cm']:.2f} | {m['m2s_cm']:.2f} | "
                  f"{m['over_5cm_percent']:.2f} | {m['over_10cm_percent']:.2f} ({m['worst_over_10cm_percent']:.1f}) | "
                  f"{m['seconds_per_sample']:.3f} |")  # fmt: skip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out}")
    if args.figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
        for ckpt, res in results["models"].items():
            ns = [int(n) for n in res["by_points"]]
            for ax, key in zip(axes, ("chamfer_cm", "s2m_cm", "m2s_cm"), strict=True):
                ax.plot(ns, [res["by_points"][str(n)]["mean"][key] for n in ns], "o-", label=ckpt)
                ax.set_xscale("log")
                ax.set_xlabel("points sampled (N)")
                ax.set_title(key.replace("_cm", " (cm, vs full scan)").replace("_", " "))
        axes[0].legend(fontsize=8)
        fig.tight_layout()
        Path(args.figure).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.figure, dpi=110)
        print(f"wrote {args.figure}")


if __name__ == "__main__":
    main()
