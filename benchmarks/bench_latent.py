"""Speed and memory of the latent read / compute / write denoiser against PocoLoco's.

Three parts, all on the CPU, every figure a median of ``--repeats`` runs after one warm-up run;
the models of one comparison are run in turns (round-robin), so a load change on this shared
machine hits them alike, and every speed-up is a ratio of two medians measured in this run:

1. ``paper``: ``LatentDenoiser`` ``paper`` (latent width 512, 8 blocks, 4 heads x 128, M = 256
   latents, 128-wide point stream; optionally also ``--ablation``: the same with a 256-wide point
   stream) against ``PocoLocoDenoiser`` ``paper`` (width 512, depth 8, fused SDPA attention), on
   ``--threads`` (default 1) threads: a training step (forward + backward + AdamW step on the epsilon
   MSE, as ``bench_denoiser.py``) and a no-grad forward, at batch x points 4 x 2,048, 4 x 10,000 and
   1 x 10,000. PocoLoco's 4 x 10,000 training step is not run (>10 GB of activations and minutes per
   step on this machine): its 10K comparison is at batch 1, where both networks are measured.
2. peak memory: one training step (or one no-grad forward) per fresh subprocess, peak resident set
   size (``VmHWM``) of that process, which includes the runtime, the weights and AdamW's state; the
   RSS before the step is reported too, so the step's own share is the difference.
3. ``small`` (the CPU-sized preset): seconds per network call (B = 1, no grad) at 2K, 10K and 50K
   points on 1 and 2 threads, against PocoLoco's ``small``; and a whole 10-call sampler run
   (DPM-Solver++ 2M, 10 steps) of 10K and 50K points on 1 and 2 threads. On a machine whose other
   jobs keep both cores busy, 2 threads can be slower than 1 (each OpenMP barrier waits for a
   descheduled thread): compare the two rows.

``--pilot`` instead runs a short training pilot (not a benchmark of quality): ``latent small``
and PocoLoco ``small`` trained side by side for ``--pilot-steps`` AdamW steps on the same batches
of the ``tiny`` synthetic dataset (generated into a temporary folder), with the epsilon loss of
``diffusion_loss``; the held-out loss on the test split (fixed frames, timesteps and noise) is
reported before and after training, at the training resolution (512 points) and at ~8x it
(4,000: every point of a tiny-dataset frame). Both models use AdamW (lr 5e-4, weight decay 0.01,
linear warm-up over the first 1/15 of the steps, gradient clipping at 1), as the ``small`` recipe.

    python benchmarks/bench_latent.py --ablation  # full run (~60 min on a loaded 2-core CPU)
    python benchmarks/bench_latent.py --quick     # smoke run with small sizes (~1 min)
    python benchmarks/bench_latent.py --pilot     # training pilot (~11 min)
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

import torch

from pocoloco.diffusion import NoiseSchedule, PerSampleRNG, diffusion_loss, sample
from pocoloco.models import (
    LatentDenoiser,
    PocoLocoDenoiser,
    denoiser_preset,
    latent_preset,
)

#: model name -> (constructor, preset, overrides)
MODELS = {
    "pocoloco paper": (PocoLocoDenoiser, denoiser_preset, "paper", {}),
    "latent paper": (LatentDenoiser, latent_preset, "paper", {}),
    "latent paper P=256": (LatentDenoiser, latent_preset, "paper", {"point_width": 256}),
    "pocoloco small": (PocoLocoDenoiser, denoiser_preset, "small", {}),
    "latent small": (LatentDenoiser, latent_preset, "small", {}),
    "pocoloco tiny": (PocoLocoDenoiser, denoiser_preset, "tiny", {}),
    "latent tiny": (LatentDenoiser, latent_preset, "tiny", {}),
}


def build(name: str, seed: int = 0) -> torch.nn.Module:
    cls, preset_fn, preset, overrides = MODELS[name]
    torch.manual_seed(seed)
    return cls(preset_fn(preset, **overrides))


def make_inputs(batch: int, points: int, cfg, seed: int = 0):
    """Random (x, t, joints) of the right shapes; joints ~ a body-sized cloud."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, points, cfg.point_channels, generator=g)
    t = torch.randint(0, 1000, (batch,), generator=g)
    joints = torch.randn(batch, cfg.num_joints, 3, generator=g) * 0.5
    return x, t, joints


class Runner:
    """One model with its AdamW optimiser; ``train_step`` / ``forward`` return seconds."""

    def __init__(self, name: str):
        self.name = name
        self.model = build(name)
        self.opt = torch.optim.AdamW(self.model.parameters(), lr=2e-4)

    def train_step(self, inputs) -> float:
        x, t, joints = inputs
        noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(1))
        self.model.train()
        t0 = time.perf_counter()
        loss = ((self.model(x, t, joints) - noise) ** 2).mean()
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return time.perf_counter() - t0

    def forward(self, inputs) -> float:
        self.model.eval()
        with torch.no_grad():
            t0 = time.perf_counter()
            self.model(*inputs)
            return time.perf_counter() - t0


def round_robin(runners: list[Runner], what: str, batch: int, points: int, repeats: int) -> dict[str, dict]:
    """Time ``what`` ("train_step" / "forward") of every runner, in turns; one warm-up round."""
    runs: dict[str, list[float]] = {r.name: [] for r in runners}
    inputs = {r.name: make_inputs(batch, points, r.model.config) for r in runners}
    for i in range(repeats + 1):
        for r in runners:
            dt = getattr(r, what)(inputs[r.name])
            if i:
                runs[r.name].append(dt)
            print(f"    {what} {r.name} {batch} x {points}: {dt:.3f} s{'' if i else ' (warm-up)'}", flush=True)
    return {name: {"median": statistics.median(ts), "runs": ts} for name, ts in runs.items()}


# -- peak memory in a fresh subprocess ---------------------------------------------------------


def _vm_hwm_gib() -> float:
    """Peak resident set size of this process (``VmHWM``, not inherited across exec), GiB."""
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024**2
    raise RuntimeError("no VmHWM in /proc/self/status (not Linux?)")


def _child(args) -> None:
    """In a fresh process: one training step or no-grad forward; print a JSON line."""
    r = Runner(args.model)
    inputs = make_inputs(args.batch, args.points, r.model.config)
    before = _vm_hwm_gib()
    dt = r.train_step(inputs) if args.mode == "train_step" else r.forward(inputs)
    print(json.dumps({"seconds": dt, "peak_rss_gib": _vm_hwm_gib(), "rss_before_gib": before}))


def measure_memory(model: str, mode: str, batch: int, points: int, threads: int, timeout: float) -> dict:
    cmd = [sys.executable, __file__, "--_child", "--model", model, "--mode", mode, "--batch", str(batch),
           "--points", str(points), "--threads", str(threads)]  # fmt: skip
    entry = {"model": model, "mode": mode, "batch": batch, "points": points}
    try:
        res = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {**entry, "error": f"timeout after {timeout:.0f} s"}
    if res.returncode != 0:
        tail = (res.stderr.strip().splitlines() or [f"exit code {res.returncode}"])[-1]
        return {**entry, "error": f"exit code {res.returncode}: {tail}"}
    out = {**entry, **json.loads(res.stdout.strip().splitlines()[-1])}
    print(f"    memory {model} {mode} {batch} x {points}: peak {out['peak_rss_gib']:.2f} GiB "
          f"(before {out['rss_before_gib']:.2f})", flush=True)  # fmt: skip
    return out


# -- sampling ----------------------------------------------------------------------------------


def time_sampling(model: torch.nn.Module, points: int, steps: int) -> float:
    """Seconds for one DPM-Solver++(2M) run of ``steps`` network calls, batch 1."""
    model.eval()
    schedule = NoiseSchedule.from_kind("four", 1000)
    rng = PerSampleRNG([0])
    noise = rng.randn((points, model.config.point_channels))
    _, _, joints = make_inputs(1, 1, model.config)
    t0 = time.perf_counter()
    out = sample("dpm++", model, schedule, noise, joints, rng=rng, steps=steps)
    dt = time.perf_counter() - t0
    assert out.shape == (1, points, model.config.point_channels)
    return dt


# -- training pilot ------------------------------------------------------------------------------


def _pilot_eval(model, frames, schedule, points: int) -> float:
    """Mean epsilon-MSE over fixed (frame, t, noise) triples; the first ``points`` of each frame."""
    model.eval()
    losses = []
    with torch.no_grad():
        for k, (x0, joints) in enumerate(frames):
            g = torch.Generator().manual_seed(1000 + k)
            x = x0[None, :points]
            t = torch.randint(0, schedule.num_timesteps, (1,), generator=g)
            noise = torch.randn(x.shape, generator=g)
            loss, _ = diffusion_loss(model, x, joints[None], schedule, t=t, noise=noise)
            losses.append(float(loss))
    model.train()
    return statistics.fmean(losses)


def pilot(args) -> dict:
    """Train ``latent small`` and PocoLoco ``small`` on the same batches; see the module docstring."""
    import tempfile

    from pocoloco.synth.config import synth_preset
    from pocoloco.data.dataset import PointCloudDataset
    from pocoloco.synth.pipeline import synthesize

    names = ("pocoloco tiny", "latent tiny") if args.quick else ("pocoloco small", "latent small")
    steps, batch, points, eval_points = (10, 2, 128, 512) if args.quick else (args.pilot_steps, 8, 512, 4000)
    schedule = NoiseSchedule.from_kind("four", 1000)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        synthesize(synth_preset("tiny"), Path(tmp) / "data")
        print(f"  synthesised the tiny dataset in {time.perf_counter() - t0:.0f} s", flush=True)
        train = PointCloudDataset(Path(tmp) / "data", "train", num_points=points, random_subsample=True)
        test = PointCloudDataset(Path(tmp) / "data", "test", num_points=eval_points, random_subsample=False)
        frames = [(test[i]["points"], test[i]["joints"]) for i in range(len(test))] * 4  # 4 (t, noise) per frame
        torch.manual_seed(0)
        batches = []
        for _ in range(steps):
            idx = torch.randint(0, len(train), (batch,))
            items = [train[int(i)] for i in idx]
            batches.append((torch.stack([it["points"] for it in items]), torch.stack([it["joints"] for it in items])))
        out: dict = {"steps": steps, "batch": batch, "points": points, "train_frames": len(train),
                     "test_frames": len(test), "eval_pairs": len(frames), "models": {}}  # fmt: skip
        warm = max(1, steps // 15)  # linear warm-up steps
        for name in names:
            model = build(name).train()
            opt = torch.optim.AdamW(model.parameters(), lr=5e-4, weight_decay=0.01)
            sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: min(1.0, (i + 1) / warm))
            before = {n: _pilot_eval(model, frames, schedule, n) for n in (points, eval_points)}
            g = torch.Generator().manual_seed(0)  # same t and noise draws for both models
            curve, t0 = [], time.perf_counter()
            for i, (x0, joints) in enumerate(batches):
                loss, _ = diffusion_loss(model, x0, joints, schedule, generator=g)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
                opt.step()
                sched.step()
                curve.append(float(loss))
                if (i + 1) % max(1, steps // 10) == 0:
                    print(f"    {name} step {i + 1}: train loss (mean of last 10) {statistics.fmean(curve[-10:]):.4f}",
                          flush=True)  # fmt: skip
            seconds = time.perf_counter() - t0
            after = {n: _pilot_eval(model, frames, schedule, n) for n in (points, eval_points)}
            out["models"][name] = {
                "parameters": model.num_parameters(), "train_seconds": seconds,
                "train_loss_first10": statistics.fmean(curve[:10]), "train_loss_last10": statistics.fmean(curve[-10:]),
                "test_loss_before": before, "test_loss_after": after, "curve": curve,
            }  # fmt: skip
    print(f"\ntraining pilot: {steps} steps, batch {batch} x {points} points, tiny synthetic dataset "
          f"({out['train_frames']} train / {out['test_frames']} test frames)")  # fmt: skip
    for name, m in out["models"].items():
        b, a = m["test_loss_before"], m["test_loss_after"]
        print(f"  {name:<15} {m['parameters']:>9,} params  {m['train_seconds']:6.0f} s  train loss "
              f"{m['train_loss_first10']:.3f} -> {m['train_loss_last10']:.3f}  test loss at {points}: "
              f"{b[points]:.3f} -> {a[points]:.3f}, "
              f"at {eval_points}: {b[eval_points]:.3f} -> {a[eval_points]:.3f}")  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=1, help="torch threads of the paper comparison (default 1)")
    p.add_argument("--ablation", action="store_true", help="also time the paper preset with a 256-wide point stream")
    p.add_argument("--no-memory", action="store_true", help="skip the peak-memory subprocesses")
    p.add_argument("--no-paper", action="store_true", help="skip part 1 (paper-size comparison)")
    p.add_argument("--no-small", action="store_true", help="skip part 3 (small preset per-call and sampling)")
    p.add_argument("--sampler-steps", type=int, default=10)
    p.add_argument("--timeout", type=float, default=3600.0, help="per memory subprocess, seconds")
    p.add_argument("--quick", action="store_true", help="tiny models and sizes for a smoke run")
    p.add_argument("--pilot", action="store_true", help="run the training pilot instead of the benchmark")
    p.add_argument("--pilot-steps", type=int, default=300)
    p.add_argument("--out", type=Path, default=None,
                   help="JSON output (default benchmarks/results/latent.json, latent_quick.json with --quick)")
    p.add_argument("--_child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--model", help=argparse.SUPPRESS)
    p.add_argument("--mode", help=argparse.SUPPRESS)
    p.add_argument("--batch", type=int, help=argparse.SUPPRESS)
    p.add_argument("--points", type=int, help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    torch.set_num_threads(args.threads)
    if args._child:
        _child(args)
        return {}
    if args.out is None:
        stem = "latent_pilot" if args.pilot else "latent"
        args.out = Path(__file__).parent / "results" / f"{stem}{'_quick' if args.quick else ''}.json"
    if args.pilot:
        res = pilot(args)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=2))
        print(f"wrote {args.out}")
        return res
    size = "tiny" if args.quick else "paper"
    small = "tiny" if args.quick else "small"
    big = (4, 10_000) if not args.quick else (2, 2_000)
    paper_sizes = [(4, 2048), big, (1, big[1])] if not args.quick else [(2, 256), big, (1, big[1])]
    small_points = [2_000, 10_000, 50_000] if not args.quick else [500, 2_000]

    results: dict = {
        "machine": {
            "torch": torch.__version__,
            "threads": args.threads,
            "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "loadavg_at_start": os.getloadavg(),
        },
        "repeats": args.repeats,
        "models": {},
    }
    rows: list[tuple[str, str, str, str, str]] = []  # what, size, baseline, latent, ratio

    def describe(name: str) -> None:
        m = build(name)
        results["models"][name] = {"config": m.config.to_dict(), "parameters": m.num_parameters()}

    # -- 1. paper-size comparison ----------------------------------------------------------------
    if not args.no_paper:
        base, lat = f"pocoloco {size}", f"latent {size}"
        latents = [lat] + ([f"latent {size} P=256"] if args.ablation and not args.quick else [])
        for name in (base, *latents):
            describe(name)
        runners = {name: Runner(name) for name in (base, *latents)}
        results["paper"] = {}
        for batch, points in paper_sizes:
            key = f"{batch}x{points}"
            entry = results["paper"][key] = {}
            for what in ("train_step", "forward"):
                who = [runners[n] for n in latents] if (batch, points) == big and what == "train_step" else [
                    runners[n] for n in (base, *latents)]  # fmt: skip
                print(f"  {what} {key} ...", flush=True)
                entry[what] = round_robin(who, what, batch, points, args.repeats)
                for n in latents:
                    b = entry[what].get(base, {}).get("median")
                    ln = entry[what][n]["median"]
                    ratio = f"{b / ln:.1f}x" if b else "-"
                    if b:
                        entry[what][f"speedup {n}"] = b / ln
                    rows.append((f"{what} ({n})", f"{batch} x {points:,}", f"{b:.2f} s" if b else "not run",
                                 f"{ln:.2f} s", ratio))  # fmt: skip
        del runners
        if not args.no_memory:
            mem = []
            for batch, points in paper_sizes:
                for name in (base, *latents):
                    if (batch, points) == big and name == base:
                        continue
                    mem.append(measure_memory(name, "train_step", batch, points, args.threads, args.timeout))
            results["paper_memory"] = mem

    # -- 3. the CPU-sized preset -------------------------------------------------------------------
    if not args.no_small:
        base, lat = f"pocoloco {small}", f"latent {small}"
        for name in (base, lat):
            describe(name)
        runners = [Runner(base), Runner(lat)]
        results["small_per_call"] = {}
        for threads in (1, 2):
            torch.set_num_threads(threads)
            for points in small_points:
                key = f"{threads}thr 1x{points}"
                print(f"  forward {key} ...", flush=True)
                res = results["small_per_call"][key] = round_robin(runners, "forward", 1, points, args.repeats)
                b, ln = res[base]["median"], res[lat]["median"]
                res["speedup"] = b / ln
                rows.append((f"call, {threads} thread{'s' if threads > 1 else ''} ({lat})", f"1 x {points:,}",
                             f"{b:.2f} s", f"{ln:.3f} s", f"{b / ln:.1f}x"))  # fmt: skip
        # a whole sampler run, latent model only (the baseline's per-call figures are above)
        results["small_sampling"] = {}
        model = runners[1].model
        for threads in (1, 2):
            torch.set_num_threads(threads)
            for points in small_points[1:]:
                ts = [time_sampling(model, points, args.sampler_steps) for _ in range(args.repeats)]
                med = statistics.median(ts)
                results["small_sampling"][f"{threads}thr 1x{points}"] = {"steps": args.sampler_steps, "median": med,
                                                                          "runs": ts}  # fmt: skip
                thr = f"{threads} thread{'s' if threads > 1 else ''}"
                print(f"    sampling {lat} 1 x {points}, {args.sampler_steps} calls, {thr}: {med:.2f} s", flush=True)
                rows.append((f"sample, {args.sampler_steps} calls, {thr} ({lat})", f"1 x {points:,}", "-",
                             f"{med:.2f} s", "-"))  # fmt: skip
        torch.set_num_threads(args.threads)
        if not args.no_memory:
            results["small_memory"] = [
                measure_memory(name, "forward", 1, small_points[-1], 1, args.timeout) for name in (lat, base)
            ]

    results["loadavg_at_end"] = os.getloadavg()
    print(f"\ntorch {torch.__version__}, paper comparison on {args.threads} thread(s), median of {args.repeats}")
    for name, info in results["models"].items():
        print(f"  {name}: {info['parameters']:,} parameters")
    header = ("what", "batch x points", "PocoLoco", "latent", "speed-up")
    w = [max(len(r[i]) for r in [header, *rows]) for i in range(5)]
    for r in [header, *rows]:
        print("  " + "  ".join(f"{c:<{w[i]}}" if i < 2 else f"{c:>{w[i]}}" for i, c in enumerate(r)))
    for m in [*results.get("paper_memory", []), *results.get("small_memory", [])]:
        size_s = f"{m['batch']} x {m['points']:,}"
        val = m.get("error") or f"peak RSS {m['peak_rss_gib']:.2f} GiB (before the step {m['rss_before_gib']:.2f})"
        print(f"  memory {m['mode']:<10} {m['model']:<20} {size_s:>10}  {val}")
    results["table"] = [dict(zip(header, r)) for r in rows]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2))
    print(f"wrote {args.out}")
    return results


if __name__ == "__main__":
    main()
