"""Speed and memory of POP (pocoloco.models.pop): fast decoder vs the public code's layout.

Usage:
    OMP_NUM_THREADS=1 python benchmarks/bench_pop.py [--preset paper] [--batch 4]
        [--scan-points 40000] [--threads 1] [--repeats 3] [--out benchmarks/results/pop.json]

Two decoder implementations with identical weights (tests/test_pop.py checks equal
outputs and gradients):

* ``linear_valid``: features sampled at the P valid query pixels, nn.Linear + BatchNorm1d
  over B*P rows (ours).
* ``conv1d_all_pixels``: feature maps up-sampled to Rq x Rq, 1x1 Conv1d over all Rq^2
  pixels (the public code's structure).

For each implementation: forward time (eval mode, no grad) and training-step time
(train mode: forward, POP losses against a scan of --scan-points points, backward,
Adam step), median of --repeats runs after one warm-up. Peak memory is VmHWM from
/proc/self/status of a fresh subprocess per (implementation, measurement); the parent
poses the anny body once and hands the inputs over in a temporary .npz, so no anny
model is loaded in the measuring process. ``setup_mib`` is VmHWM after building the
model and inputs, before the first measured call.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch

IMPLS = ("linear_valid", "conv1d_all_pixels")
MODES = ("forward", "train_step")


def _vmhwm_mib() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError("VmHWM not found in /proc/self/status")


def _prepare(path: str, batch: int, scan_points: int, seed: int) -> dict:
    """Pose the anny body (batch random poses), write the worker inputs to ``path``."""
    from pocoloco.body import NUM_JOINTS, AnnyBody
    from pocoloco.body.surface import BodySurface, pose_mean_shape

    body = AnnyBody()
    surf = BodySurface.from_body(body)
    rng = np.random.default_rng(seed)
    rot = rng.normal(scale=0.2, size=(batch, NUM_JOINTS, 3)).astype(np.float32)
    posed = body.pose(rot)
    mean = pose_mean_shape(rot)
    root = posed.joints[:, :1]
    verts = posed.vertices - root
    # scan: area-uniform points on each posed body pushed 2 cm out along a random direction
    pts = surf.sample(body.template, scan_points, seed=seed)
    scan = surf.interpolate(torch.from_numpy(verts), pts).numpy()
    nrm = rng.normal(size=scan.shape).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    scan = scan + 0.02 * nrm
    np.savez(path, faces=surf.faces, uv=surf.uv, uv_faces=surf.uv_faces, face_mask=surf.face_mask,
             pose_vertices=(mean.vertices - mean.joints[:, :1]).astype(np.float32), body_vertices=verts,
             vtransf=posed.vtransf, scan_points=scan.astype(np.float32), scan_normals=nrm)  # fmt: skip
    return {"num_vertices": int(verts.shape[1]), "num_faces": int(len(surf.faces))}


def _worker(args) -> None:
    """Measure one (implementation, mode) in this fresh process; print one JSON line."""
    from pocoloco.body.surface import BodySurface
    from pocoloco.methods.pop import make_optimizer, train_step
    from pocoloco.models.pop import POP, POPBatch, pop_preset

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    z = np.load(args.inputs)
    surf = BodySurface(z["faces"], z["uv"], z["uv_faces"], z["face_mask"])
    model = POP(pop_preset(args.preset, decoder_impl=args.impl), surf, num_outfits=1,
                num_vertices=z["body_vertices"].shape[1])  # fmt: skip
    B = z["body_vertices"].shape[0]
    batch = POPBatch(*(torch.from_numpy(z[k]) for k in ("pose_vertices", "body_vertices", "vtransf")),
                     torch.zeros(B, dtype=torch.long), torch.from_numpy(z["scan_points"]),
                     torch.from_numpy(z["scan_normals"]))  # fmt: skip
    if args.mode == "forward":
        model.eval()

        def run():
            with torch.no_grad():
                model(batch)
    else:
        opt = make_optimizer(model)
        step = [0]

        def run():
            train_step(model, opt, batch, step[0])  # normal term on (normal_start 0)
            step[0] += 1

    setup = _vmhwm_mib()
    times = []
    for i in range(args.repeats + 1):
        t0 = time.perf_counter()
        run()
        if i:  # the first call is the warm-up
            times.append(time.perf_counter() - t0)
    print(json.dumps({"impl": args.impl, "mode": args.mode, "median_s": statistics.median(times), "times_s": times,
                      "peak_mib": _vmhwm_mib(), "setup_mib": setup, "query_points": model.num_query_points,
                      "network_parameters": model.num_network_parameters()}))  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--scan-points", type=int, default=40000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--impls", nargs="+", default=list(IMPLS), choices=IMPLS)
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    parser.add_argument("--out", default=os.path.join("benchmarks", "results", "pop.json"))
    parser.add_argument("--_worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--_inputs", dest="inputs", help=argparse.SUPPRESS)
    parser.add_argument("--_impl", dest="impl", help=argparse.SUPPRESS)
    parser.add_argument("--_mode", dest="mode", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args._worker:
        return _worker(args)
    if min(args.batch, args.scan_points, args.threads, args.repeats) < 1:
        raise SystemExit("--batch, --scan-points, --threads and --repeats must be >= 1")

    from pocoloco.models.pop import pop_preset
    from pocoloco.utils.atomic import write_json_atomic

    cfg = pop_preset(args.preset)
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        inputs = os.path.join(tmp, "inputs.npz")
        info = _prepare(inputs, args.batch, args.scan_points, seed=0)
        rows = []
        for mode in args.modes:
            for impl in args.impls:
                cmd = [sys.executable, os.path.abspath(__file__), "--_worker", "--_inputs", inputs, "--_impl", impl,
                       "--_mode", mode, "--preset", args.preset, "--threads", str(args.threads),
                       "--repeats", str(args.repeats)]  # fmt: skip
                env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
                res = subprocess.run(cmd, capture_output=True, text=True, env=env)
                if res.returncode:
                    raise SystemExit(f"worker {impl}/{mode} failed:\n{res.stderr}")
                rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
                print(f"  {mode:<10} {impl:<18} {rows[-1]['median_s']:8.3f} s  peak {rows[-1]['peak_mib']:8.0f} MiB",
                      flush=True)  # fmt: skip

    def get(impl, mode):
        return next((r for r in rows if r["impl"] == impl and r["mode"] == mode), None)

    speedups = {}
    print(f"\nPOP preset {args.preset}: batch {args.batch}, input {cfg.input_resolution}^2, query "
          f"{cfg.query_resolution}^2 ({rows[0]['query_points']} valid of {cfg.query_resolution**2}), "
          f"scan {args.scan_points} points, {args.threads} thread(s)")  # fmt: skip
    print(f"{'mode':<11} {'impl':<18} {'median s':>9} {'peak MiB':>9} {'setup MiB':>9}")
    for r in rows:
        print(f"{r['mode']:<11} {r['impl']:<18} {r['median_s']:>9.3f} {r['peak_mib']:>9.0f} {r['setup_mib']:>9.0f}")
    for mode in args.modes:
        a, b = get("linear_valid", mode), get("conv1d_all_pixels", mode)
        if a and b:
            speedups[mode] = {"time": b["median_s"] / a["median_s"], "peak_memory": b["peak_mib"] / a["peak_mib"]}
            print(f"{mode}: linear_valid is {speedups[mode]['time']:.2f}x faster, "
                  f"{speedups[mode]['peak_memory']:.2f}x less peak memory")  # fmt: skip
    result = {
        "benchmark": "POP decoder implementations (pocoloco.models.pop), anny body, posed mean shape as UNet input",
        "command": "OMP_NUM_THREADS=%d python benchmarks/bench_pop.py %s" % (args.threads, " ".join(sys.argv[1:])),
        "preset": args.preset, "config": cfg.to_dict(), "batch": args.batch, "scan_points": args.scan_points,
        "torch": torch.__version__, "torch_threads": args.threads, "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(), "load_avg_1min": os.getloadavg()[0], "repeats": args.repeats, **info,
        "rows": rows, "speedup_linear_valid_over_conv1d": speedups,
        "wall_s": time.perf_counter() - t_start,
    }  # fmt: skip
    write_json_atomic(args.out, result)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
