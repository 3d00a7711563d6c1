"""A short measured search for the network and batch to train PocoLoco with on one GPU.

Each candidate ``PRESET:B`` trains for the same wall-clock time (``--seconds``) on the pack's train
frames, from the same seed, with the full recipe of the final run (outfit codes + body shape, bf16,
the preset's warm-up, the sqrt learning-rate rule for its batch); then its EMA network is scored by
the **validation loss**: the epsilon MSE on the pack's test and held-out frames at 8 fixed timesteps
spread over [0, T) with fixed noise and fixed 512-point subsets (the same for every candidate).
Lowest wins. Equal wall-clock favours small networks early; the final run is ~10x longer, so the
table also reports each candidate's steps/s, from which the final run's step count is set.

    python benchmarks/search_gpu_recipe.py --data medium.pack --seconds 30 --json search.json \\
        --candidates latent_small:64 latent_small:256 latent_base:64 latent_base:256
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pocoloco.data.pack import open_point_clouds
from pocoloco.diffusion import NoiseSchedule, diffusion_loss
from pocoloco.engine.trainer import scaled_lr, train
from pocoloco.methods.pocoloco import train_preset
from pocoloco.methods.pocoloco.training import PocoLocoTask


@torch.no_grad()
def validation_loss(task: PocoLocoTask, model: torch.nn.Module, data: str, device: torch.device,
                    num_points: int = 512, timesteps: int = 8, max_frames: int = 256, batch: int = 32) -> dict:  # fmt: skip
    """Epsilon MSE of ``model`` on the pack's test / heldout frames (module docstring): mean and
    the per-split means. Deterministic: the frames, point subsets, timesteps and noise are fixed."""
    c = task.config
    schedule = NoiseSchedule.from_kind(c.schedule, c.num_timesteps)
    out = {}
    model.eval()
    for split in ("test", "heldout"):
        try:
            ds = open_point_clouds(data, split, num_points=None, subjects=task.dataset.subject_names)
        except ValueError:
            continue
        frames = np.linspace(0, len(ds) - 1, min(len(ds), max_frames)).round().astype(int)
        ts = np.linspace(0, c.num_timesteps - 1, timesteps).round().astype(int)
        total, count = 0.0, 0
        for lo in range(0, len(frames), batch):
            items = [ds[int(i)] for i in frames[lo:lo + batch]]
            pts = []
            for k, it in zip(frames[lo:lo + batch], items, strict=True):
                sel = np.random.default_rng([7, int(k)]).choice(it["points"].shape[0], num_points, replace=False)
                pts.append(it["points"][sel])
            x0 = torch.stack(pts).to(device)
            joints = torch.stack([it["joints"] for it in items]).to(device)
            subject = torch.tensor([it["subject"] for it in items])
            cond = task.condition(joints, subject)
            for t_val in ts:
                g = torch.Generator(device).manual_seed(int(1000 * lo + t_val))
                noise = torch.randn(x0.shape, generator=g, device=device)
                t = torch.full((len(items),), int(t_val), device=device, dtype=torch.long)
                with torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"):
                    loss, _ = diffusion_loss(model, x0, cond, schedule, c.prediction_type, t=t, noise=noise)
                total += float(loss) * len(items)
                count += len(items)
        out[split] = total / count
    out["mean"] = float(np.mean([out[s] for s in ("test", "heldout") if s in out]))
    return out


def run_candidate(data: str, preset: str, batch: int, seconds: float, device: torch.device, workers: int) -> dict:
    base = train_preset(preset)
    config = base.replace(batch_size=batch, lr=scaled_lr(base.lr, batch, base.batch_size), steps=1_000_000,
                          ckpt_every=0, sample_every=0, log_every=50, outfit_codes=True, body_shape=True,
                          bf16=device.type == "cuda", num_workers=workers)  # fmt: skip
    task = PocoLocoTask(config, data)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        result = train(task, Path(tmp) / "run", device=device, progress=False, time_budget_s=seconds)
    wall = time.perf_counter() - t0
    val = validation_loss(task, result.ema, data, device)
    return {"preset": preset, "batch": batch, "points": config.num_points, "lr": config.lr, "steps": result.step,
            "steps_per_s": result.steps_per_s, "train_loss": result.final_loss, "val": val, "wall_s": wall,
            "params": sum(p.numel() for p in result.model.parameters())}  # fmt: skip


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="training pack with test / heldout frames")
    ap.add_argument("--candidates", nargs="+", default=["latent_small:64", "latent_small:256", "latent_base:64",
                                                         "latent_base:256"], metavar="PRESET:B")  # fmt: skip
    ap.add_argument("--seconds", type=float, default=30.0, help="training wall-clock per candidate")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--workers", type=int, default=6)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    rows = []
    for cand in args.candidates:
        preset, batch = cand.split(":")
        try:
            row = run_candidate(args.data, preset, int(batch), args.seconds, device, args.workers)
        except Exception as e:  # noqa: BLE001 - out of memory, say: report the candidate and go on
            print(f"{cand}: failed ({type(e).__name__}: {str(e)[:200]})", flush=True)
            if device.type == "cuda":
                torch.cuda.empty_cache()
            continue
        rows.append(row)
        print(f"{preset:13s} B={row['batch']:4d} lr={row['lr']:.2e} {row['steps']:6d} steps ({row['steps_per_s']:.2f}/s) "
              f"train loss {row['train_loss']:.4f} val {row['val']['mean']:.4f} "
              f"({', '.join(f'{k} {v:.4f}' for k, v in row['val'].items() if k != 'mean')})", flush=True)  # fmt: skip
    best = min(rows, key=lambda r: r["val"]["mean"])
    print(f"best: {best['preset']}:{best['batch']} (val {best['val']['mean']:.4f})", flush=True)
    result = {"rows": rows, "best": {"preset": best["preset"], "batch": best["batch"], "steps_per_s": best["steps_per_s"]},
              "seconds": args.seconds, "device": str(device),
              "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
