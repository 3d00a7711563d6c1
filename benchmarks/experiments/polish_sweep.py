"""Which of a distilled student's grid times, and which finishing step of its teacher (issue 42).

For each student sub-grid (``--grids``, e.g. ``999,749,249``) the student samples on exactly those
timesteps (the few-step sampler with fresh noise), and each ``--ts`` step t > 0 adds the teacher's
finishing call: the student's answer re-noised to 1-based step t and the teacher's x0 there
(:func:`pocoloco.diffusion.few_step.polish`; t = 0: the student alone). Every setting is scored by
Chamfer to the scan on the frames ``pocoloco bench quality`` picks (``--frames``, 2 seeds, the
same scan subset), paired with the teacher's own 25-call SDE answer on the same frames and seeds.
No x0 clamp (the quality bench clamps at 5 normalised units, which these clouds never reach).

    python benchmarks/experiments/polish_sweep.py --data DATA --split test \\
        --grids 999,749,249 999,749,499,249 --ts 0 10 20 30 50 --json polish_test.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import torch


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--student", default="default:fast")
    ap.add_argument("--teacher", default="default")
    ap.add_argument("--grids", nargs="+", required=True, help="student timesteps, comma-separated, one list per grid")
    ap.add_argument("--ts", type=int, nargs="+", default=[0, 20], help="teacher's finishing step (0: none)")
    ap.add_argument("--frames", type=int, default=28)
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--json", required=True)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    from pocoloco.data import format as fmt
    from pocoloco.data.poses import MeanShapeCache
    from pocoloco.diffusion.few_step import polish
    from pocoloco.diffusion.sampler_base import PerSampleRNG
    from pocoloco.diffusion.samplers import sample_ddim
    from pocoloco.diffusion.schedules import NoiseSchedule
    from pocoloco.engine.shipped import resolve_ckpt_arg
    from pocoloco.evaluation.baselines import select_frames, subset
    from pocoloco.evaluation.metrics import chamfer_cm
    from pocoloco.methods import load_method
    from pocoloco.methods.pocoloco.sampling import condition_for

    student, teacher = load_method(resolve_ckpt_arg(args.student)), load_method(resolve_ckpt_arg(args.teacher))
    if not student.config.student_calls:
        raise SystemExit(f"{args.student}: not a distilled model")
    grids = [[int(t) for t in g.split(",")] for g in args.grids]
    schedule = NoiseSchedule.from_kind(student.config.schedule, student.config.num_timesteps)
    norm, ptype = student.normalisation, student.config.prediction_type
    layout = fmt.DatasetLayout(args.data)
    frames = layout.iter_frames(args.split, layout.subjects())
    chosen = [frames[i] for i in select_frames(frames, args.frames)]
    labels = [f"{g}+T{t}" if t else g for g in args.grids for t in args.ts]
    chamfer: dict[str, list[float]] = {k: [] for k in ["teacher25", *labels]}
    seconds = {k: 0.0 for k in chamfer}
    cache = MeanShapeCache()
    for n, (subject, _, path) in enumerate(chosen):
        fr = fmt.read_frame(path, ["points", "normals", "labels", "joints", "frame_index", "body_vertices", "vtransf"],
                            allow_missing=True)  # fmt: skip
        gt = fr.points[subset(fr.num_points, args.points, (0, n))].astype(np.float64)
        pose = student.pose_from_frame(path, subject, frame=fr, cache=cache)
        outfit = student.outfit_id(subject)
        joints = np.asarray(pose.joints)
        t0 = time.perf_counter()
        ref = teacher.predict(pose, args.points, seeds=args.seeds, outfit=outfit).points
        seconds["teacher25"] += time.perf_counter() - t0
        chamfer["teacher25"] += [chamfer_cm(c, gt) for c in ref]
        kw = student.condition(outfit)
        joints_n = norm.normalise(np.zeros((1, 3), np.float32), joints)[1]
        cond = condition_for(torch.as_tensor(joints_n, dtype=torch.float32).expand(len(args.seeds), -1, -1), kw.get("outfit"), kw.get("shape"))
        root, angle = norm.root(joints).astype(np.float32), norm.angle(joints)
        for g, grid in zip(args.grids, grids, strict=True):
            t0 = time.perf_counter()
            rng = PerSampleRNG(args.seeds)
            x0 = sample_ddim(student.model, schedule, rng.randn((args.points, 3)), cond, timesteps=grid, renoise=1.0,
                             rng=rng, prediction_type=ptype)  # fmt: skip
            base = time.perf_counter() - t0
            for t in args.ts:
                t0 = time.perf_counter()
                x = polish(teacher.model, schedule, x0, cond, t, PerSampleRNG([s + 7919 for s in args.seeds]),
                           prediction_type=ptype) if t else x0  # fmt: skip
                label = f"{g}+T{t}" if t else g
                seconds[label] += base + time.perf_counter() - t0
                pts = norm.denormalise(x.numpy(), root, angle)
                chamfer[label] += [chamfer_cm(c, gt) for c in pts]
        print(f"frame {n + 1}/{len(chosen)}", flush=True)

    ref = np.asarray(chamfer["teacher25"])
    rows = {}
    print(f"{'setting':28s} calls  Chamfer cm  ratio  paired diff")
    for k, v in chamfer.items():
        d = np.asarray(v) - ref
        calls = 25 if k == "teacher25" else len(k.split("+")[0].split(",")) + ("+T" in k)
        rows[k] = {"calls": calls, "chamfer_cm": float(np.mean(v)), "ratio": float(np.mean(v) / ref.mean()),
                   "diff": float(d.mean()), "se": float(d.std(ddof=1) / np.sqrt(len(d))),
                   "seconds_per_cloud": seconds[k] / len(ref)}  # fmt: skip
        r = rows[k]
        print(f"{k:28s} {calls:5d}  {r['chamfer_cm']:10.3f}  {r['ratio']:.3f}  {r['diff']:+.3f} +- {r['se']:.3f}")
    with open(args.json, "w") as f:
        json.dump({"argv": ["python", "benchmarks/experiments/polish_sweep.py", *(argv or sys.argv[1:])],
                   "rows": rows, "per_cloud": chamfer}, f, indent=1)  # fmt: skip
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
