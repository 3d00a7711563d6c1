"""Training and sampling throughput of PocoLoco on the CPU and on a GPU, from one script.

Training rows: the real training loop (:func:`pocoloco.engine.trainer.train`: the pack's batches
through the DataLoader, bf16 autocast, AdamW (fused on a GPU), gradient clipping, EMA; TF32 on a
GPU) of a preset at batch B for ``--warmup`` steps, then ``--steps`` timed steps (the time between
the two log records, both taken after a device synchronisation). points/s = steps/s x B x N (N the
preset's points per training cloud, at most the pack's points per frame). Peak GPU memory per row (``max_memory_allocated``).

Sampling rows: clouds per second drawn by :func:`pocoloco.methods.pocoloco.sampling.sample_clouds`
(SDE-DPM-Solver++, 10 steps, bf16 where the device runs it natively) with the ``latent_small``
network (untrained: throughput only), ``--sample-clouds`` clouds per batch, at 2K / 10K / 50K points.

``--compile PRESET:B``: the same training row with ``torch.compile`` (GPU), its warm-up time
(compilation included) reported beside the eager row.

    python benchmarks/bench_gpu_training.py --data medium.pack --device cpu --json cpu.json   # this CPU
    python benchmarks/bench_gpu_training.py --data medium.pack --device cuda --compile latent_small:256 \\
        --json gpu.json
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pocoloco.data.pack import is_pack, read_pack_meta
from pocoloco.engine.trainer import scaled_lr, train
from pocoloco.methods.pocoloco import train_preset
from pocoloco.methods.pocoloco.sampling import sample_clouds
from pocoloco.methods.pocoloco.training import PocoLocoTask


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def train_row(data: str, preset: str, batch: int, device: torch.device, warmup: int, steps: int, workers: int,
              compile_model: bool = False) -> dict:  # fmt: skip
    """Time the training loop of ``preset`` at batch ``batch`` (module docstring)."""
    base = train_preset(preset)
    if is_pack(data):  # a pack holds P points per frame: train at min(N, P) points per cloud
        base = base.replace(num_points=min(base.num_points, int(read_pack_meta(data)["points_per_frame"])))
    config = base.replace(batch_size=batch, lr=scaled_lr(base.lr, batch, base.batch_size), steps=warmup + steps,
                          warmup_steps=0, ckpt_every=0, sample_every=0, log_every=warmup if warmup else steps,
                          outfit_codes=True, body_shape=True, bf16=device.type == "cuda" or _cpu_bf16(),
                          num_workers=workers)  # fmt: skip
    if steps % config.log_every:
        raise ValueError("--steps must be a multiple of --warmup")
    task = PocoLocoTask(config, data)
    times: dict[int, float] = {}

    def log(rec):
        _sync(device)
        times[rec["step"]] = time.perf_counter()

    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        train(task, Path(tmp) / "run", device=device, progress=False, log_fn=log, compile_model=compile_model)
    seconds = times[warmup + steps] - times[warmup] if warmup else times[steps] - t0
    sps = steps / seconds
    n_params = sum(p.numel() for p in task.build_model().parameters())
    return {"kind": "train", "device": str(device), "preset": preset, "batch": batch, "points": config.num_points,
            "params": n_params, "lr": config.lr, "compile": compile_model, "steps_per_s": sps,
            "points_per_s": sps * batch * config.num_points,
            "warmup_s": (times[warmup] - t0) if warmup else None,
            "peak_gib": torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None}  # fmt: skip


def _cpu_bf16() -> bool:
    from pocoloco.utils.hardware import bf16_is_fast

    return bool(bf16_is_fast(torch.device("cpu")))


def sample_row(data: str, device: torch.device, num_points: int, clouds: int, repeats: int) -> dict:
    """Clouds per second at ``num_points`` points (module docstring)."""
    task = PocoLocoTask(train_preset("latent_small", outfit_codes=True, body_shape=True), data)
    torch.manual_seed(0)
    model = task.build_model().to(device).eval()
    item = task.dataset[0]
    joints = task.normalisation.denormalise(item["joints"].numpy(), item["root"].numpy(), item["angle"].numpy())
    bf16 = device.type == "cuda" or _cpu_bf16()
    times = []
    for r in range(repeats + 1):
        _sync(device)
        t = time.perf_counter()
        sample_clouds(model, task.normalisation, task.config, joints, clouds, num_points, steps=10, batch_size=clouds,
                      bf16=bf16, outfit=0, shape=task.shapes[0].tolist(), seeds=list(range(clouds)))  # fmt: skip
        _sync(device)
        if r:  # the first run warms up
            times.append(time.perf_counter() - t)
    sec = statistics.median(times)
    return {"kind": "sample", "device": str(device), "preset": "latent_small", "points": num_points,
            "clouds": clouds, "clouds_per_s": clouds / sec, "seconds_per_batch": sec, "repeats": repeats}  # fmt: skip


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="training pack (or dataset folder)")
    ap.add_argument("--device", nargs="+", default=["cpu"], help="devices, e.g. cpu cuda (default cpu)")
    ap.add_argument("--presets", nargs="+", default=["latent_small", "latent_paper"])
    ap.add_argument("--batches", nargs="+", type=int, default=[16, 64, 256])
    ap.add_argument("--cpu-rows", nargs="*", default=None, metavar="PRESET:B",
                    help="on the CPU only these rows (default: every preset x batch)")  # fmt: skip
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--steps", type=int, default=20, help="timed steps (a multiple of --warmup)")
    ap.add_argument("--cpu-warmup", type=int, default=1)
    ap.add_argument("--cpu-steps", type=int, default=3)
    ap.add_argument("--workers", type=int, default=6, help="DataLoader workers on a GPU (CPU rows: 0)")
    ap.add_argument("--sample-points", nargs="+", type=int, default=[2048, 10_000, 50_000])
    ap.add_argument("--cpu-sample-points", nargs="*", type=int, default=None,
                    help="sampling rows on the CPU (default: as --sample-points; none: skip)")  # fmt: skip
    ap.add_argument("--sample-clouds", type=int, default=16, help="clouds per sampling batch on a GPU (CPU: 1)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--compile", nargs="*", default=[], metavar="PRESET:B", help="also these rows compiled (GPU)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    rows = []

    def show(row):
        rows.append(row)
        if row["kind"] == "train":
            mem = f" {row['peak_gib']:.1f} GiB" if row["peak_gib"] is not None else ""
            print(f"train  {row['device']:6s} {row['preset']:13s} B={row['batch']:4d} N={row['points']:5d} "
                  f"{'compiled ' if row['compile'] else ''}{row['steps_per_s']:8.2f} steps/s "
                  f"{row['points_per_s'] / 1e6:9.3f} M points/s{mem}", flush=True)  # fmt: skip
        else:
            print(f"sample {row['device']:6s} {row['preset']:13s} N={row['points']:6d} x {row['clouds']:3d} "
                  f"{row['clouds_per_s']:8.2f} clouds/s", flush=True)  # fmt: skip

    for dev_name in args.device:
        device = torch.device(dev_name)
        cpu = device.type == "cpu"
        cells = [(p, b) for p in args.presets for b in args.batches]
        if cpu and args.cpu_rows is not None:
            cells = [(c.split(":")[0], int(c.split(":")[1])) for c in args.cpu_rows]
        for preset, batch in cells:
            try:
                show(train_row(args.data, preset, batch, device, args.cpu_warmup if cpu else args.warmup,
                               args.cpu_steps if cpu else args.steps, 0 if cpu else args.workers))  # fmt: skip
            except Exception as e:  # noqa: BLE001 - out of memory, say: report the row and go on
                print(f"train  {dev_name} {preset} B={batch}: failed ({type(e).__name__}: {str(e)[:200]})", flush=True)
                if device.type == "cuda":
                    torch.cuda.empty_cache()
        for n in args.cpu_sample_points if cpu and args.cpu_sample_points is not None else args.sample_points:
            show(sample_row(args.data, device, n, 1 if cpu else args.sample_clouds, 1 if cpu else args.repeats))
        if not cpu:
            for cell in args.compile:
                preset, batch = cell.split(":")
                try:
                    show(train_row(args.data, preset, int(batch), device, args.warmup, args.steps, args.workers,
                                   compile_model=True))  # fmt: skip
                except Exception as e:  # noqa: BLE001 - report and go on: compile is optional
                    print(f"train  {dev_name} {preset} B={batch} compiled: failed ({type(e).__name__}: {e})"[:300])
    result = {"rows": rows, "host": platform.node(), "cpu": platform.processor() or platform.machine(),
              "torch": torch.__version__, "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
              "threads": torch.get_num_threads(), "argv": argv, "time": time.strftime("%Y-%m-%d %H:%M:%S")}  # fmt: skip
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
