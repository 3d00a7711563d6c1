"""Speed and memory of the PocoLoco denoiser: fused SDPA attention vs the dense-einsum baseline.

Measures, on the current device (CPU):

1. forward time (``torch.no_grad``) at ``--preset`` (default ``paper``), ``--batch`` x ``--points``
   (default 4 x 2048), SDPA vs dense, median of ``--repeats`` runs after one warm-up run;
   optionally also SDPA under bf16 autocast (``--bf16``);
2. training step time (forward + backward + AdamW step on the epsilon MSE loss), same sizes;
3. peak memory of one no-grad forward at ``--mem-batch`` x ``--mem-points`` (default 4 x 10,000),
   SDPA and (unless ``--no-dense-memory``) dense. Each memory figure comes from a fresh
   subprocess: peak resident set size (``VmHWM``) of that process, which includes the
   Python/torch runtime and the weights; the RSS just before the forward is reported too;
4. one SDPA forward of ``--big-points`` (default 50,000) points at batch 1: time and peak RSS
   (subprocess).

The dense baseline is the same network with the same weights, its attention computed as the
original PocoLoco code does (materialised N x N softmax with einsum, softmax in float32).

Where the time goes (FLOPs per block, B x N tokens, width D): the linear layers cost ~28 N D^2
(QKV/out of self-attention, Q/out of cross-attention, MLP 4x), self-attention ~4 N^2 D. At
N = 2048, D = 512 attention is only ~36% of the FLOPs, so a faster attention kernel alone cannot
make the whole forward 4x faster on a CPU (Amdahl); the gap grows with N (N = 10K: ~73%), and the
dense baseline's N x N softmax is what blows up memory (4 x 4 x 10K^2 floats = 6.4 GB per copy).
bf16 autocast pays off on CPUs with native bf16 (this machine's AMD EPYC has avx512_bf16, no
AMX: bf16 matmuls on the denoiser's linear shapes run ~2-3x the float32 rate, while PyTorch's
CPU flash-attention kernel is no faster in bf16 than in float32); without it the linear layers
get slower. ``--bf16`` reports the speed-ups at equal precision and SDPA-bf16 against the
dense original in float32 (the precision the original code trains and samples in).

    python benchmarks/bench_denoiser.py            # full run (slow on a 2-core CPU: ~30+ min)
    python benchmarks/bench_denoiser.py --quick    # smoke run with small sizes (~1 min)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from pocoloco.models import PocoLocoDenoiser, denoiser_preset


def make_inputs(batch: int, points: int, cfg, seed: int = 0):
    """Random (x, t, joints) of the right shapes; joints ~ a body-sized cloud."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, points, cfg.point_channels, generator=g)
    t = torch.randint(0, 1000, (batch,), generator=g)
    joints = torch.randn(batch, cfg.num_joints, 3, generator=g) * 0.5
    return x, t, joints


def build(preset: str, impl: str, seed: int = 0) -> PocoLocoDenoiser:
    torch.manual_seed(seed)
    return PocoLocoDenoiser(denoiser_preset(preset, attention=impl))


def time_forward(model, inputs, repeats: int, bf16: bool = False) -> list[float]:
    model.eval()
    times = []
    for i in range(repeats + 1):  # first run is a warm-up
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            t0 = time.perf_counter()
            model(*inputs)
            dt = time.perf_counter() - t0
        if i:
            times.append(dt)
    return times


def time_train_step(model, inputs, repeats: int, bf16: bool = False) -> list[float]:
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=2e-4)
    x, t, joints = inputs
    noise = torch.randn_like(x)
    times = []
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):  # as `pocoloco train --bf16`
            pred = model(x, t, joints)
        loss = ((pred.float() - noise) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        dt = time.perf_counter() - t0
        if i:
            times.append(dt)
    return times


def _vm_hwm_gib() -> float:
    """Peak resident set size of this process's address space (``VmHWM``), GiB.

    Not ``getrusage().ru_maxrss``: Linux carries that over ``execve`` from the parent that forked
    us, so a child of a benchmark that had run big dense steps reported the parent's peak.
    """
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024**2  # kB -> GiB
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2  # not Linux: best effort


def _child_memory(args) -> None:
    """Run in a fresh process: one no-grad forward, print a JSON line with time and peak RSS."""
    model = build(args.preset, args.impl).eval()
    inputs = make_inputs(args.batch, args.points, model.config)
    rss_before = _vm_hwm_gib()
    with torch.no_grad():
        t0 = time.perf_counter()
        model(*inputs)
        dt = time.perf_counter() - t0
    peak = _vm_hwm_gib()
    print(json.dumps({"seconds": dt, "peak_rss_gib": peak, "rss_before_forward_gib": rss_before}))


def measure_memory(preset: str, impl: str, batch: int, points: int, timeout: float) -> dict:
    """Spawn ``_child_memory`` in a subprocess (same torch thread count); returns its JSON or an ``error`` entry."""
    cmd = [sys.executable, __file__, "--_child", "--preset", preset, "--impl", impl,
           "--batch", str(batch), "--points", str(points), "--threads", str(torch.get_num_threads())]  # fmt: skip
    entry = {"impl": impl, "batch": batch, "points": points}
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {**entry, "error": f"timeout after {timeout:.0f} s"}
    if res.returncode != 0:
        tail = (res.stderr.strip().splitlines() or [f"exit code {res.returncode}"])[-1]
        return {**entry, "error": f"exit code {res.returncode}: {tail}"}
    return {**entry, **json.loads(res.stdout.strip().splitlines()[-1])}


def median(xs: list[float]) -> float:
    return statistics.median(xs)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--points", type=int, default=2048)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--mem-batch", type=int, default=4)
    p.add_argument("--mem-points", type=int, default=10_000)
    p.add_argument("--big-points", type=int, default=50_000)
    p.add_argument("--no-dense-memory", action="store_true", help="skip the dense memory run (needs ~13 GB at 4 x 10K)")
    p.add_argument("--no-train", action="store_true", help="skip the training-step timings")
    p.add_argument("--no-memory", action="store_true", help="skip the memory / big-forward subprocesses")
    p.add_argument("--memory-only", action="store_true", help="only the memory / big-forward subprocesses")
    p.add_argument("--bf16", action="store_true",
                   help="also time both implementations under bf16 autocast (pays off with AMX / avx512_bf16)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--timeout", type=float, default=3600.0, help="per memory subprocess, seconds")
    p.add_argument("--quick", action="store_true", help="small sizes for a smoke run")
    p.add_argument("--out", type=Path, default=None,
                   help="JSON output (default benchmarks/results/denoiser.json, denoiser_quick.json with --quick)")
    p.add_argument("--_child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--impl", default="sdpa", help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args.threads:
        torch.set_num_threads(args.threads)
    if args._child:
        _child_memory(args)
        return {}
    if args.quick:
        args.preset, args.batch, args.points, args.repeats = "small", 2, 512, 1
        args.mem_batch, args.mem_points, args.big_points = 2, 2000, 5000
    if args.out is None:
        name = "denoiser_quick.json" if args.quick else "denoiser_memory.json" if args.memory_only else "denoiser.json"
        args.out = Path(__file__).parent / "results" / name

    cfg = denoiser_preset(args.preset)
    n_params = PocoLocoDenoiser(cfg).num_parameters()
    inputs = make_inputs(args.batch, args.points, cfg)
    results: dict = {
        "preset": args.preset,
        "config": cfg.to_dict(),
        "parameters": n_params,
        "sizes": {"batch": args.batch, "points": args.points, "repeats": args.repeats},
        "machine": {
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
            "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "platform": platform.platform(),
            "loadavg_at_start": os.getloadavg(),
        },
        "forward_s": {},
        "train_step_s": {},
    }
    rows = []

    for impl in () if args.memory_only else ("sdpa", "dense"):
        model = build(args.preset, impl)
        for bf16 in (False, True) if args.bf16 else (False,):
            key = f"{impl}_bf16" if bf16 else impl
            ts = time_forward(model, inputs, args.repeats, bf16=bf16)
            results["forward_s"][key] = {"median": median(ts), "runs": ts}
            rows.append((f"forward {key}", f"{args.batch} x {args.points}", f"{median(ts):.3f} s"))
            if not args.no_train:
                ts = time_train_step(model, inputs, args.repeats, bf16=bf16)
                results["train_step_s"][key] = {"median": median(ts), "runs": ts}
                rows.append((f"train step {key}", f"{args.batch} x {args.points}", f"{median(ts):.3f} s"))
        del model

    speedups = {}  # dense / sdpa, same precision; and sdpa bf16 against the dense original in fp32
    for what in ("forward_s", "train_step_s"):
        tab = results[what]
        for name, (num, den) in {"fp32": ("dense", "sdpa"), "bf16": ("dense_bf16", "sdpa_bf16"),
                                 "sdpa_bf16_vs_dense_fp32": ("dense", "sdpa_bf16")}.items():  # fmt: skip
            if num in tab and den in tab:
                speedups[f"{what[:-2]} {name}"] = tab[num]["median"] / tab[den]["median"]
    results["speedups"] = speedups
    if "forward fp32" in speedups:
        results["forward_speedup"] = speedups["forward fp32"]
    if "train_step fp32" in speedups:
        results["train_step_speedup"] = speedups["train_step fp32"]

    mem_impls = () if args.no_memory else ("sdpa",) if args.no_dense_memory else ("sdpa", "dense")
    results["memory"] = [
        measure_memory(args.preset, impl, args.mem_batch, args.mem_points, args.timeout) for impl in mem_impls
    ]
    if not args.no_memory:
        results["big_forward"] = measure_memory(args.preset, "sdpa", 1, args.big_points, args.timeout)
    for m in [*results["memory"], *([results["big_forward"]] if "big_forward" in results else [])]:
        size = f"{m['batch']} x {m['points']}"
        if "error" in m:
            rows.append((f"memory {m['impl']}", size, m["error"]))
        else:
            rows.append((f"no-grad forward {m['impl']} (subprocess)", size,
                         f"{m['seconds']:.2f} s, peak RSS {m['peak_rss_gib']:.2f} GiB "
                         f"(before forward {m['rss_before_forward_gib']:.2f})"))  # fmt: skip

    print(f"PocoLoco denoiser, preset {args.preset!r} ({n_params:,} parameters), "
          f"torch {torch.__version__}, {torch.get_num_threads()} threads")  # fmt: skip
    w = max(len(r[0]) for r in rows)
    for name, size, val in rows:
        print(f"  {name:<{w}}  {size:>12}  {val}")
    for name, v in speedups.items():
        print(f"  speed-up (dense / sdpa) {name}: {v:.2f}x")

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2))
    print(f"wrote {args.out}")
    return results


if __name__ == "__main__":
    main()
