"""Speed and memory of CloSET (pocoloco.models.closet) on the anny template (13,718 vertices).

For each ``--presets`` entry (default: ``small`` then ``paper``) two fresh subprocesses run:

1. ``forward``: build the model (FPS / ball-query hierarchy included; timed separately),
   then a no-grad eval forward at ``--batch`` x ``--points`` query points, median of
   ``--repeats`` runs after one warm-up run;
2. ``train``: ``closet_train_step`` (forward + CloSET Eqs. 4-6 loss against ``--gt-points``
   ground-truth points + backward + Adam step), median of ``--train-repeats`` steps after
   one warm-up step.

Each subprocess reports its peak resident set size (``VmHWM`` from /proc/self/status; not
``ru_maxrss``, which Linux carries over from the forking parent) and the RSS before the
timed work (model + inputs). Inputs: anny's default body posed by random joint rotations
(std 0.2 rad, seed 0) with its real ``vtransf``; GT = the posed surface pushed out 2 cm
along the normals (area-uniform samples). Defaults are the paper's evaluation size:
batch 4 (POP's batch), 50,000 query points (CloSET Sec. 4 "Metrics"), 40,000 GT points.

    OMP_NUM_THREADS=1 python benchmarks/bench_closet.py --threads 1                # small + paper
    OMP_NUM_THREADS=1 python benchmarks/bench_closet.py --threads 1 --skip-train paper  # what was run here
    python benchmarks/bench_closet.py --quick     # smoke run: tiny preset, batch 1, 2,000 points

Writes ``benchmarks/results/closet.json`` (``closet_quick.json`` with --quick) and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch


def _vm_hwm_gib() -> float:
    """Peak resident set size of this process (``VmHWM``), GiB."""
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024**2
    raise RuntimeError("no VmHWM in /proc/self/status (Linux only)")


def _vm_rss_gib() -> float:
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024**2
    raise RuntimeError("no VmRSS in /proc/self/status (Linux only)")


def _inputs(batch: int, points: int, gt_points: int, seed: int = 0):
    """anny posed bodies -> (template, faces, CloSETBatch)."""
    from pocoloco.body import NUM_JOINTS, AnnyBody
    from pocoloco.data.format import Frame
    from pocoloco.methods.closet import make_closet_batch
    from pocoloco.ops import sample_surface

    body = AnnyBody()
    rng = np.random.default_rng(seed)
    rot = rng.normal(scale=0.2, size=(batch, NUM_JOINTS, 3)).astype(np.float32)
    posed = body.pose(rot)
    frames = []
    for b in range(batch):
        s = sample_surface(posed.vertices[b].astype(np.float64), body.faces, gt_points, seed=seed + b)
        frames.append(Frame(points=(s.points + 0.02 * s.normals).astype(np.float32), normals=s.normals.astype(np.float32),
                            joints=posed.joints[b], frame_index=b, body_vertices=posed.vertices[b],
                            vtransf=posed.vtransf[b]))  # fmt: skip
    return body.template, body.faces, frames


def _child(args) -> None:
    """Fresh process: build, time forward or train steps, print one JSON line."""
    from pocoloco.methods.closet import (
        closet_train_step,
        make_closet_batch,
        make_closet_optimizer,
    )
    from pocoloco.models.closet import CloSET, closet_preset

    template, faces, frames = _inputs(args.batch, args.points, args.gt_points)
    torch.manual_seed(0)
    t0 = time.perf_counter()
    model = CloSET(template, faces, 1, closet_preset(args.preset))
    build_s = time.perf_counter() - t0
    query = model.sample_query_points(args.points, seed=0)
    batch = make_closet_batch(frames, 0, query)
    del frames
    rss_before = _vm_rss_gib()
    times = []
    if args.mode == "forward":
        model.eval()
        with torch.no_grad():
            for i in range(args.repeats + 1):
                t0 = time.perf_counter()
                model(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
                times.append(time.perf_counter() - t0)
    else:
        opt = make_closet_optimizer(model)
        for i in range(args.repeats + 1):
            t0 = time.perf_counter()
            losses = closet_train_step(model, opt, batch)
            times.append(time.perf_counter() - t0)
        if not np.isfinite(losses["total"]):
            raise SystemExit("non-finite loss")
    print(json.dumps({
        "build_s": build_s, "warmup_s": times[0], "runs_s": times[1:], "median_s": statistics.median(times[1:]),
        "peak_rss_gib": _vm_hwm_gib(), "rss_before_gib": rss_before, "parameters": model.parameter_breakdown(),
    }))  # fmt: skip


def _run(preset: str, mode: str, args) -> dict:
    repeats = args.repeats if mode == "forward" else args.train_repeats
    cmd = [sys.executable, __file__, "--_child", mode, "--presets", preset, "--batch", str(args.batch),
           "--points", str(args.points), "--gt-points", str(args.gt_points), "--repeats", str(repeats),
           "--threads", str(args.threads)]  # fmt: skip
    entry = {"preset": preset, "mode": mode, "batch": args.batch, "points": args.points, "gt_points": args.gt_points}
    t0 = time.perf_counter()
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
    except subprocess.TimeoutExpired:
        return {**entry, "error": f"timeout after {args.timeout:.0f} s"}
    if res.returncode != 0:
        tail = (res.stderr.strip().splitlines() or [f"exit code {res.returncode}"])[-1]
        return {**entry, "error": f"exit code {res.returncode}: {tail}"}
    return {**entry, **json.loads(res.stdout.strip().splitlines()[-1]), "wall_s": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--presets", nargs="+", default=["small", "paper"])
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--points", type=int, default=50_000, help="query points per frame (paper: 50K)")
    p.add_argument("--gt-points", type=int, default=40_000, help="ground-truth points per frame (training loss)")
    p.add_argument("--repeats", type=int, default=2, help="timed forwards after one warm-up")
    p.add_argument("--train-repeats", type=int, default=1, help="timed training steps after one warm-up")
    p.add_argument("--threads", type=int, default=1, help="torch threads in the subprocesses (default 1)")
    p.add_argument("--timeout", type=float, default=1800.0, help="per subprocess, seconds")
    p.add_argument("--no-train", action="store_true", help="skip the training-step runs")
    p.add_argument("--skip-train", nargs="*", default=[], metavar="PRESET",
                   help="presets whose training step is not run (e.g. paper: minutes per step and ~10+ GB)")  # fmt: skip
    p.add_argument("--quick", action="store_true", help="smoke run: tiny preset, batch 1, 2,000 points")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--_child", choices=["forward", "train"], default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if min(args.batch, args.points, args.gt_points, args.repeats, args.train_repeats, args.threads) < 1:
        raise SystemExit("--batch, --points, --gt-points, --repeats, --train-repeats and --threads must be >= 1")
    torch.set_num_threads(args.threads)
    if args._child:
        args.preset, args.mode = args.presets[0], args._child
        _child(args)
        return {}
    if args.quick:
        args.presets, args.batch, args.points, args.gt_points = ["tiny"], 1, 2000, 2000
    if args.out is None:
        args.out = Path(__file__).parent / "results" / ("closet_quick.json" if args.quick else "closet.json")

    results: dict = {
        "command": " ".join([os.path.basename(sys.executable), *sys.argv]),
        "machine": {"torch": torch.__version__, "threads": args.threads, "platform": platform.platform(),
                    "cpu_count": os.cpu_count(), "loadavg_at_start": os.getloadavg()},  # fmt: skip
        "runs": [],
    }
    rows = []
    for preset in args.presets:
        for mode in ("forward",) if args.no_train or preset in args.skip_train else ("forward", "train"):
            r = _run(preset, mode, args)
            results["runs"].append(r)
            if "error" in r:
                rows.append((preset, mode, f"{args.batch} x {args.points}", "-", "-", "-", "-", r["error"]))
            else:
                rows.append((preset, mode, f"{args.batch} x {args.points}", f"{r['parameters']['total'] / 1e6:.2f}M",
                             f"{r['build_s']:.1f} s", f"{r['median_s']:.2f} s", f"{r['peak_rss_gib']:.2f} GiB", ""))  # fmt: skip
            print(f"  {preset} {mode}: " + (r.get("error") or f"{r['median_s']:.2f} s, {r['peak_rss_gib']:.2f} GiB"),
                  file=sys.stderr, flush=True)  # fmt: skip
    results["loadavg_at_end"] = os.getloadavg()
    from pocoloco.utils.atomic import write_json_atomic

    write_json_atomic(args.out, results)
    head = ("preset", "mode", "batch x points", "params", "build", "median", "peak RSS", "note")
    widths = [max(len(str(r[i])) for r in (head, *rows)) for i in range(len(head))]
    for r in (head, *rows):
        print("  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip())
    print(f"-> {args.out}")
    return results


if __name__ == "__main__":
    main()
