"""Few-step sampling: Chamfer vs. number of sampler steps, against the 1000-step ancestral DDPM.

For a trained checkpoint, ``--frames`` test frames (evenly spaced) and ``--seeds`` seeds per
frame, every sampler configuration draws the same clouds (same per-sample seeds, so the same
initial noise) and each cloud is scored against the frame's scan (an N-point subset, as in
``pocoloco eval``): PocoLoco Chamfer = S2M + M2S in cm. Reported per configuration: mean
Chamfer, its ratio to DDPM-1000 (the paper's sampler), wall time per sample and the speed-up
over DDPM-1000, all measured in this run.

    python benchmarks/bench_sampler_steps.py --ckpt default --data data/small
    python benchmarks/bench_sampler_steps.py --ckpt RUN --data data/small --frames 4 --seeds 0 1 --points 1024

Writes ``--out`` (JSON, default benchmarks/results/sampler_steps.json) and a plot of Chamfer vs.
steps next to it (``.png``).
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch

from pocoloco.data import format as fmt
from pocoloco.engine.checkpoint import resolve_checkpoint
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.evaluation.baselines import select_frames
from pocoloco.evaluation.baselines import subset as _subset
from pocoloco.evaluation.metrics import chamfer_cm
from pocoloco.methods.pocoloco import load_denoiser, sample_clouds
from pocoloco.utils.atomic import write_json_atomic
from pocoloco.viz.render import plot_curves

DEFAULT_CONFIGS = ("ddpm:1000", "ddpm:25", "ddpm:50", "ddpm:100", "ddim:10", "ddim:25", "ddim:50", "ddim:100", "dpm++:5", "dpm++:10", "dpm++:20",
                   "dpm++:50")  # fmt: skip


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", default="default", help="checkpoint / run folder, or 'default' (the shipped model)")
    p.add_argument("--data", default="data/small", help="dataset folder")
    p.add_argument("--split", default="test")
    p.add_argument("--frames", type=int, default=8, help="test frames, evenly spaced (default 8)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3], help="samples per frame (default 4 seeds)")
    p.add_argument("--points", type=int, default=2048, help="points per cloud (default 2048)")
    p.add_argument("--configs", nargs="+", default=list(DEFAULT_CONFIGS), help="sampler:steps to compare")
    p.add_argument("--baseline", default="ddpm:1000", help="the reference configuration (must be in --configs)")
    p.add_argument("--clip", type=float, default=5.0, help="sampler x0 clamp (0 = off), as pocoloco eval")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--out", default="benchmarks/results/sampler_steps.json")
    args = p.parse_args(argv)
    if args.baseline not in args.configs:
        p.error(f"--baseline {args.baseline} is not one of --configs")
    if args.threads:
        torch.set_num_threads(args.threads)

    ckpt = resolve_checkpoint(resolve_ckpt_arg(args.ckpt))
    model, norm, config = load_denoiser(ckpt)
    layout = fmt.DatasetLayout(args.data)
    frames = layout.iter_frames(args.split, layout.subjects())
    chosen = [frames[i] for i in select_frames(frames, args.frames)]
    gts = []
    for n, (_, _, path) in enumerate(chosen):
        fr = fmt.read_frame(path, ["points", "joints"])
        gts.append((fr.joints, fr.points[_subset(fr.num_points, args.points, (0, n))]))

    rows = []
    for spec in args.configs:
        kind, steps = spec.split(":")
        steps = int(steps)
        t0 = time.perf_counter()
        cds = []
        for joints, gt in gts:
            clouds = sample_clouds(model, norm, config, joints, len(args.seeds), args.points, sampler=kind,
                                   steps=steps, seeds=args.seeds, batch_size=len(args.seeds),
                                   clip=args.clip or None)  # fmt: skip
            cds += [chamfer_cm(c, gt) for c in clouds.points]
        sec = (time.perf_counter() - t0) / (len(gts) * len(args.seeds))
        rows.append({"sampler": kind, "steps": steps, "chamfer_cm": float(np.mean(cds)),
                     "chamfer_sem_cm": float(np.std(cds) / np.sqrt(len(cds))), "seconds_per_sample": sec,
                     "chamfer_per_cloud_cm": [float(c) for c in cds]})  # fmt: skip
        print(f"{spec:>10}: Chamfer {rows[-1]['chamfer_cm']:.3f} cm  {sec:.2f} s/sample", flush=True)
    base = next(r for r in rows if f"{r['sampler']}:{r['steps']}" == args.baseline)
    for r in rows:
        r["chamfer_ratio"] = r["chamfer_cm"] / base["chamfer_cm"]
        # paired: the same frames, seeds and initial noise as the baseline, so the standard error
        # of the mean per-cloud difference is much smaller than either row's own spread
        diff = np.asarray(r["chamfer_per_cloud_cm"]) - np.asarray(base["chamfer_per_cloud_cm"])
        r["diff_vs_baseline_cm"] = float(diff.mean())
        r["diff_sem_cm"] = float(diff.std() / np.sqrt(len(diff)))
        r["speedup"] = base["seconds_per_sample"] / r["seconds_per_sample"]

    print(f"\n{'sampler':>8} {'steps':>6} {'Chamfer cm':>11} {'vs ' + args.baseline:>14} {'paired diff cm':>16} "
          f"{'s/sample':>9} {'speed-up':>9}")  # fmt: skip
    for r in rows:
        print(f"{r['sampler']:>8} {r['steps']:>6} {r['chamfer_cm']:>11.3f} {r['chamfer_ratio']:>14.3f} "
              f"{r['diff_vs_baseline_cm']:>+9.3f} ± {r['diff_sem_cm']:.3f} "
              f"{r['seconds_per_sample']:>9.2f} {r['speedup']:>8.1f}x")  # fmt: skip
    result = {"checkpoint": str(ckpt), "data": args.data, "split": args.split, "frames": len(gts), "seeds": args.seeds,
              "points": args.points, "clip": args.clip or None, "threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
              "rows": rows}  # fmt: skip
    out = Path(args.out)
    write_json_atomic(out, result)
    curves = {}
    for kind in dict.fromkeys(r["sampler"] for r in rows):
        sel = [r for r in rows if r["sampler"] == kind]
        curves[kind] = ([r["steps"] for r in sel], [r["chamfer_cm"] for r in sel])
    curves[f"{base['sampler']}-{base['steps']} level"] = ([1, base["steps"]], [base["chamfer_cm"]] * 2)
    plot_curves(curves, out.with_suffix(".png"), xlabel="sampler steps (log)", ylabel="Chamfer cm",
                title="Chamfer vs. sampler steps", logx=True)  # fmt: skip
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return result


if __name__ == "__main__":
    main()
