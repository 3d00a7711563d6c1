"""Scan completion: Chamfer of inpainted regions vs. the same region of a fresh full sample.

For ``--frames`` test frames (evenly spaced, as ``pocoloco eval``) and every region of
``--regions`` (``pocoloco.apps.completion.REGIONS``: all scan points within a radius of a joint,
e.g. the left hand, the right knee, or between the knees = the hem), the region is removed from
the full scan, the rest is completed and scored with
:func:`pocoloco.apps.completion.evaluate_completion` (PocoLoco Chamfer, cm, vs. an N-point
subset of the scan, so densities match):

* inpaint: ``complete`` (init "sample": a full sample's hole points renoised to ``--t`` and
  inpainted with the scan points kept): its generated points vs. the GT points of the region;
  "full": the whole completed cloud vs. the GT;
* noise: plain RePaint (generated points from pure noise, probe coverage), the same;
* fresh: a fresh full sample of the pose (same seed), restricted to its points whose nearest GT
  point lies in the region (oracle selection); "full": the whole fresh sample vs. the GT;
* fresh-hole: the same fresh sample's points farthest from the partial scan (no GT used: the
  completion's starting points, before harmonising).

    python benchmarks/bench_completion.py --ckpt default --data data/small
    python benchmarks/bench_completion.py --ckpt runs/small --data data/small --frames 2 --points 1024

Prints a table per region and writes ``--out`` (JSON, default benchmarks/results/completion.json).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from pocoloco.apps.completion import DEFAULT_RADIUS_M, REGIONS, evaluate_completion
from pocoloco.data import format as fmt
from pocoloco.engine.checkpoint import resolve_checkpoint
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.evaluation.baselines import select_frames
from pocoloco.methods.pocoloco import load_denoiser
from pocoloco.utils.atomic import jsonable, write_json_atomic

KEYS = ("inpaint_chamfer_cm", "noise_chamfer_cm", "fresh_hole_chamfer_cm", "fresh_chamfer_cm",
        "inpaint_full_chamfer_cm", "noise_full_chamfer_cm", "fresh_full_chamfer_cm", "coverage_estimated",
        "coverage_true", "num_generated", "num_gt_region", "num_fresh_region")  # fmt: skip


def _nanstat(fn, values: list[float]) -> float:
    """fn (np.nanmean / np.nanmedian) of values; NaN (no warning) if all are NaN."""
    v = np.asarray(values, np.float64)
    return float(fn(v)) if np.isfinite(v).any() else float("nan")


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", default="default", help="checkpoint / run folder, or 'default' (the shipped model)")
    p.add_argument("--data", default="data/small", help="dataset folder")
    p.add_argument("--split", default="test")
    p.add_argument("--frames", type=int, default=6, help="frames, evenly spaced over the split (default 6)")
    p.add_argument("--regions", nargs="+", default=list(REGIONS), help=f"from {', '.join(REGIONS)}")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="one completion per seed (default 0)")
    p.add_argument("--points", type=int, default=2048, help="N points per cloud (default 2048)")
    p.add_argument("--sampler", default="dpm++")
    p.add_argument("--steps", type=int, help="sampler steps (default: the sampler's)")
    p.add_argument("--coverage-radius", type=float, default=DEFAULT_RADIUS_M,
                   help=f"coverage radius, m (default {DEFAULT_RADIUS_M})")  # fmt: skip
    p.add_argument("--t", type=int, help="start step of the harmonising chain (default: complete's, 100)")
    p.add_argument("--no-noise", action="store_true", help="skip the plain-RePaint (init noise) comparison")
    p.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    p.add_argument("--out", default="benchmarks/results/completion.json")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    unknown = [r for r in args.regions if r not in REGIONS]
    if unknown:
        p.error(f"unknown regions {unknown}; choose from {', '.join(REGIONS)}")

    ckpt = resolve_checkpoint(resolve_ckpt_arg(args.ckpt))
    model, norm, config = load_denoiser(ckpt)
    layout = fmt.DatasetLayout(args.data)
    frames = layout.iter_frames(args.split, layout.subjects())
    chosen = [frames[i] for i in select_frames(frames, args.frames)]
    rows = []
    t0 = time.perf_counter()
    for subject, sequence, path in chosen:
        fr = fmt.read_frame(path, ["points", "joints"])
        for region in args.regions:
            for seed in args.seeds:
                m = evaluate_completion(model, norm, config, fr.points, fr.joints, region, args.points,
                                        seed=seed, sampler=args.sampler, steps=args.steps,
                                        radius=args.coverage_radius, t=args.t, noise=not args.no_noise)  # fmt: skip
                if m is None:
                    continue
                rows.append({"frame": f"{subject}/{sequence}/{path.stem}", "subject": subject, "region": region,
                             "seed": seed, **m})  # fmt: skip
                print(f"{rows[-1]['frame']} {region:>10} seed {seed}: region: inpaint {m['inpaint_chamfer_cm']:.2f} "
                      f"cm, noise {m['noise_chamfer_cm']:.2f}, fresh-hole {m['fresh_hole_chamfer_cm']:.2f}, fresh "
                      f"{m['fresh_chamfer_cm']:.2f}; whole cloud: "
                      f"inpaint {m['inpaint_full_chamfer_cm']:.2f}, fresh {m['fresh_full_chamfer_cm']:.2f} "
                      f"(coverage {m['coverage_estimated']:.2f} est. / {m['coverage_true']:.2f} true)",
                      flush=True)  # fmt: skip
    seconds = time.perf_counter() - t0
    means, medians = {}, {}
    for region in args.regions:
        sel = [r for r in rows if r["region"] == region]
        if sel:
            means[region] = {k: _nanstat(np.nanmean, [r[k] for r in sel]) for k in KEYS} | {"n": len(sel)}
            medians[region] = {k: _nanstat(np.nanmedian, [r[k] for r in sel]) for k in KEYS} | {"n": len(sel)}
    for label, table in (("median", medians), ("mean", means)):
        print(f"\n{label:>6}: Chamfer cm of the removed region (inpaint / noise = plain RePaint / fresh) and of the "
              f"whole cloud")  # fmt: skip
        print(f"{'region':>10} {'n':>3} {'inpaint':>8} {'noise':>7} {'fr-hole':>8} {'fresh':>7} {'full inp':>9} "
              f"{'full noi':>9} "
              f"{'full fr':>8} {'cov est':>8} {'cov true':>9} {'#gen':>5} {'#gt':>5}")  # fmt: skip
        for region, m in table.items():
            print(f"{region:>10} {m['n']:>3} {m['inpaint_chamfer_cm']:>8.2f} {m['noise_chamfer_cm']:>7.2f} "
                  f"{m['fresh_hole_chamfer_cm']:>8.2f} "
                  f"{m['fresh_chamfer_cm']:>7.2f} {m['inpaint_full_chamfer_cm']:>9.2f} "
                  f"{m['noise_full_chamfer_cm']:>9.2f} {m['fresh_full_chamfer_cm']:>8.2f} "
                  f"{m['coverage_estimated']:>8.2f} {m['coverage_true']:>9.2f} {m['num_generated']:>5.0f} "
                  f"{m['num_gt_region']:>5.0f}")  # fmt: skip
    result = {"checkpoint": str(ckpt), "data": args.data, "split": args.split, "frames": len(chosen),
              "regions": {r: {"joints": list(REGIONS[r][0]), "radius_m": REGIONS[r][1]} for r in args.regions},
              "seeds": args.seeds, "points": args.points, "sampler": args.sampler, "steps": args.steps,
              "coverage_radius_m": args.coverage_radius, "t": args.t, "threads": torch.get_num_threads(),
              "machine": platform.processor() or platform.machine(), "seconds_total": seconds,
              "means": means, "medians": medians, "rows": rows}  # fmt: skip
    write_json_atomic(args.out, jsonable(result))
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
