"""Few-step sampling: Chamfer vs. number of denoiser calls (NFE), against the 1000-step ancestral DDPM.

For a trained checkpoint, ``--frames`` test frames (evenly spaced) and ``--seeds`` seeds per
frame, every sampler configuration draws the same clouds (same per-sample seeds, so the same
initial noise) and each cloud is scored against the frame's scan (an N-point subset, as in
``pocoloco eval``): PocoLoco Chamfer = S2M + M2S in cm. Reported per configuration: mean
Chamfer, its ratio to DDPM-1000 (the paper's sampler), the paired per-cloud difference to it with
its standard error, the denoiser calls per cloud (counted), wall time per sample and the speed-up
over DDPM-1000.

A configuration is ``SAMPLER:STEPS`` or ``SAMPLER:STEPS:KEY=VALUE,...`` with keyword arguments of the
sampler (``pocoloco.diffusion.sample``), e.g. ``dpm++sde:10:spacing=karras``,
``unipc:8:order=3,variant=bh1``, ``dpm++3m:10:d2=half``, ``dpm++sde:10:clip=0`` (0 = no x0 clip;
otherwise ``--clip``). Clouds are drawn as ``pocoloco.methods.pocoloco.sample_clouds`` draws them
(same normalisation, per-sample seeds and batches), with the keywords passed through.

    python benchmarks/bench_sampler_steps.py --ckpt default --data data/small
    python benchmarks/bench_sampler_steps.py --ckpt RUN --data data/small --frames 4 --seeds 0 1 --points 1024

``--reuse JSON ...`` takes the row of any configuration already in earlier results of this script
with the same checkpoint, frames, seeds, points, clip and threads (e.g. the expensive DDPM-1000) instead
of recomputing it: the samples are seeded, so its Chamfer values are the same; its time was
measured in the other run (the row says ``reused_from``), so compare times within one run.

``--combine JSON ...`` samples nothing: it pools the rows of runs on other seeds (same checkpoint,
frames, points and clip), configuration by configuration, into one table over all their clouds.

Writes ``--out`` (JSON, default benchmarks/results/sampler_steps.json) and a plot of Chamfer vs.
NFE next to it (``.png``; not with ``--combine``).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pocoloco.data import format as fmt
from pocoloco.diffusion import NoiseSchedule, PerSampleRNG, sample
from pocoloco.engine.checkpoint import resolve_checkpoint
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.evaluation.baselines import select_frames
from pocoloco.evaluation.baselines import subset as _subset
from pocoloco.evaluation.metrics import chamfer_cm
from pocoloco.methods import load_method
from pocoloco.utils.atomic import write_json_atomic
from pocoloco.viz.render import plot_curves

DEFAULT_CONFIGS = ("ddpm:1000", "dpm++sde:5", "dpm++sde:10", "dpm++sde:25", "dpm++sde:5:spacing=karras",
                   "dpm++sde:10:spacing=karras", "dpm++3msde:10:spacing=karras", "unipc:10:spacing=karras",
                   "dpm++:20")  # fmt: skip


def parse_config(spec: str) -> tuple[str, int, dict[str, Any]]:
    """``"kind:steps[:k=v,...]"`` -> (kind, steps, kwargs); values become int, float or str."""
    parts = spec.split(":")
    if len(parts) not in (2, 3):
        raise ValueError(f"config {spec!r} is not SAMPLER:STEPS[:KEY=VALUE,...]")
    extra: dict[str, Any] = {}
    for item in filter(None, (parts[2] if len(parts) == 3 else "").split(",")):
        key, _, value = item.partition("=")
        for cast in (int, float):
            try:
                extra[key] = cast(value)
                break
            except ValueError:
                pass
        else:
            extra[key] = value
    return parts[0], int(parts[1]), extra


class CountingDenoiser:
    """The model, counting its calls (NFE) and keeping its ``prediction_type``."""

    def __init__(self, model: torch.nn.Module, prediction_type: str) -> None:
        self.model, self.prediction_type, self.calls = model, prediction_type, 0

    def __call__(self, x: torch.Tensor, t: torch.Tensor, cond: Any) -> torch.Tensor:
        self.calls += 1
        return self.model(x, t, cond)


@torch.no_grad()
def draw(model, norm, config, joints: np.ndarray, seeds: list[int], num_points: int, kind: str,
         steps: int, clip: float | None, extra: dict[str, Any]) -> tuple[np.ndarray, int]:  # fmt: skip
    """(K, N, 3) clouds in metres for one pose, one batch of ``seeds``, and the denoiser calls per
    batch: ``sample_clouds`` with extra sampler keywords."""
    den = config.denoiser
    C, J = int(den.point_channels), int(den.num_joints)
    _, joints_n = norm.normalise(np.zeros((1, 3), np.float32), joints)  # (J, 3) normalised
    root = norm.root(joints)
    schedule = NoiseSchedule.from_kind(config.schedule, config.num_timesteps)
    rng = PerSampleRNG(seeds)
    noise = rng.randn((num_points, C))  # (B, N, C)
    cond = torch.as_tensor(joints_n, dtype=torch.float32).expand(len(seeds), J, 3)  # (B, J, 3)
    counted = CountingDenoiser(model, config.prediction_type)
    kwargs = {"steps": steps, "clip": clip, **extra}
    if kwargs["clip"] == 0:
        kwargs["clip"] = None
    model.eval()
    x = sample(kind, counted, schedule, noise, cond, rng=rng, **kwargs)  # (B, N, C)
    pts = norm.denormalise(x.float().numpy()[..., :3], root.astype(np.float32), norm.angle(joints)).astype(np.float32)
    return pts, counted.calls


def _paired(r: dict, base: dict) -> None:
    r["chamfer_ratio"] = r["chamfer_cm"] / base["chamfer_cm"]
    # paired: the same frames, seeds and initial noise as the baseline, so the standard error of the
    # mean per-cloud difference is much smaller than either row's own spread
    diff = np.asarray(r["chamfer_per_cloud_cm"]) - np.asarray(base["chamfer_per_cloud_cm"])
    r["diff_vs_baseline_cm"] = float(diff.mean())
    r["diff_sem_cm"] = float(diff.std(ddof=1) / np.sqrt(len(diff))) if len(diff) > 1 else 0.0
    r["speedup"] = base["seconds_per_sample"] / r["seconds_per_sample"]


def combine(paths: list[str], baseline: str) -> dict:
    """Pool results of runs on disjoint seeds (same checkpoint, frames, points, clip) into one."""
    runs = [json.loads(Path(path).read_text()) for path in paths]
    keys = ("checkpoint", "data", "split", "frames", "points", "clip")
    for path, r in zip(paths[1:], runs[1:], strict=True):
        if any(r.get(k) != runs[0].get(k) for k in keys):
            raise ValueError(f"{path} differs from {paths[0]} in {[k for k in keys if r.get(k) != runs[0].get(k)]}")
    seeds = [s for r in runs for s in r["seeds"]]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"--combine needs runs on disjoint seeds, got {[r['seeds'] for r in runs]}")
    by_spec = [{row.get("config", f"{row['sampler']}:{row['steps']}"): row for row in r["rows"]} for r in runs]
    rows = []
    for spec, first in by_spec[0].items():
        if not all(spec in b for b in by_spec):
            continue
        parts = [b[spec] for b in by_spec]
        cds = [c for part in parts for c in part["chamfer_per_cloud_cm"]]
        rows.append({**{k: v for k, v in first.items() if k != "reused_from"}, "config": spec,
                     "chamfer_cm": float(np.mean(cds)), "chamfer_sem_cm": float(np.std(cds) / np.sqrt(len(cds))),
                     "seconds_per_sample": float(np.mean([part["seconds_per_sample"] for part in parts])),
                     "chamfer_per_cloud_cm": cds, "combined_from": paths})  # fmt: skip
    base = next((r for r in rows if r["config"] == baseline), None)
    if base is None:
        raise ValueError(f"the baseline {baseline} is not in every file of --combine")
    for r in rows:
        _paired(r, base)
    return {**{k: runs[0].get(k) for k in keys}, "seeds": seeds, "threads": runs[0].get("threads"),
            "machine": runs[0].get("machine"), "baseline": baseline, "rows": rows}  # fmt: skip


def print_table(rows: list[dict], baseline: str) -> None:
    print(f"\n{'config':>32} {'NFE':>5} {'Chamfer cm':>11} {'vs ' + baseline:>14} {'paired diff cm':>16} "
          f"{'s/sample':>9} {'speed-up':>9}")  # fmt: skip
    for r in rows:
        print(f"{r['config']:>32} {r.get('nfe', r['steps']):>5} {r['chamfer_cm']:>11.3f} {r['chamfer_ratio']:>14.3f} "
              f"{r['diff_vs_baseline_cm']:>+9.3f} ± {r['diff_sem_cm']:.3f} "
              f"{r['seconds_per_sample']:>9.2f} {r['speedup']:>8.1f}x")  # fmt: skip


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", default="default", help="checkpoint / run folder, or 'default' (the shipped model)")
    p.add_argument("--data", default="data/small", help="dataset folder")
    p.add_argument("--split", default="test")
    p.add_argument("--frames", type=int, default=8, help="test frames, evenly spaced (default 8)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3], help="samples per frame (default 4 seeds)")
    p.add_argument("--points", type=int, default=2048, help="points per cloud (default 2048)")
    p.add_argument("--configs", nargs="+", default=list(DEFAULT_CONFIGS), help="SAMPLER:STEPS[:KEY=VALUE,...] to compare")
    p.add_argument("--baseline", default="ddpm:1000", help="the reference configuration (must be in --configs)")
    p.add_argument("--reuse", nargs="+", default=[], help="results JSON of earlier runs whose rows are reused")
    p.add_argument("--combine", nargs="+", default=None, help="pool these results JSON (disjoint seeds); no sampling")
    p.add_argument("--clip", type=float, default=5.0, help="sampler x0 clamp (0 = off), as pocoloco eval")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--out", default="benchmarks/results/sampler_steps.json")
    args = p.parse_args(argv)
    if args.combine:
        result = combine(args.combine, args.baseline)
        print_table(result["rows"], args.baseline)
        write_json_atomic(Path(args.out), result)
        print(f"wrote {args.out}")
        return result
    if args.baseline not in args.configs:
        p.error(f"--baseline {args.baseline} is not one of --configs")
    configs = [(spec, *parse_config(spec)) for spec in args.configs]
    if args.threads:
        torch.set_num_threads(args.threads)

    ckpt = resolve_checkpoint(resolve_ckpt_arg(args.ckpt))
    loaded = load_method(ckpt, expect="pocoloco")
    norm, config = loaded.normalisation, loaded.config
    layout = fmt.DatasetLayout(args.data)
    frames = layout.iter_frames(args.split, layout.subjects())
    chosen = [frames[i] for i in select_frames(frames, args.frames)]
    gts = []
    for n, (subject, _, path) in enumerate(chosen):
        fr = fmt.read_frame(path, ["points", "joints"])
        # a model that knows who wears what draws the frame's own outfit
        model = loaded.denoiser_for(loaded.outfit_id(subject) if loaded.outfit_names() else None)
        gts.append((fr.joints, fr.points[_subset(fr.num_points, args.points, (0, n))], model))

    cache: dict[str, dict] = {}
    want = {"frames": len(gts), "seeds": args.seeds, "points": args.points, "clip": args.clip or None,
            "threads": torch.get_num_threads()}  # fmt: skip
    for path in args.reuse:
        prev = json.loads(Path(path).read_text())
        got = {k: prev.get(k) for k in want}
        if got != want or Path(prev["checkpoint"]).resolve() != Path(ckpt).resolve():
            p.error(f"--reuse {path} was run with {got} on {prev['checkpoint']}, not {want} on {ckpt}")
        for r in prev["rows"]:
            spec = r.get("config", f"{r['sampler']}:{r['steps']}")
            cache.setdefault(spec, {**r, "config": spec, "reused_from": r.get("reused_from", path)})

    rows = []
    for spec, kind, steps, extra in configs:
        if spec in cache:
            rows.append(cache[spec])
            print(f"{spec:>32}: Chamfer {cache[spec]['chamfer_cm']:.3f} cm (from {cache[spec]['reused_from']})", flush=True)
            continue
        t0 = time.perf_counter()
        cds, nfe = [], 0
        for joints, gt, model in gts:
            clouds, nfe = draw(model, norm, config, joints, args.seeds, args.points, kind, steps, args.clip or None, extra)
            cds += [chamfer_cm(c, gt) for c in clouds]
        sec = (time.perf_counter() - t0) / (len(gts) * len(args.seeds))
        rows.append({"config": spec, "sampler": kind, "steps": steps, "options": extra, "nfe": nfe,
                     "chamfer_cm": float(np.mean(cds)), "chamfer_sem_cm": float(np.std(cds) / np.sqrt(len(cds))),
                     "seconds_per_sample": sec, "chamfer_per_cloud_cm": [float(c) for c in cds]})  # fmt: skip
        print(f"{spec:>32}: Chamfer {rows[-1]['chamfer_cm']:.3f} cm  {sec:.2f} s/sample  NFE {nfe}", flush=True)
    base = next(r for r in rows if r["config"] == args.baseline)
    for r in rows:
        _paired(r, base)

    print_table(rows, args.baseline)
    result = {"checkpoint": str(ckpt), "data": args.data, "split": args.split, "frames": len(gts), "seeds": args.seeds,
              "points": args.points, "clip": args.clip or None, "threads": torch.get_num_threads(),
              "machine": platform.processor() or platform.machine(), "baseline": args.baseline, "rows": rows}  # fmt: skip
    out = Path(args.out)
    write_json_atomic(out, result)
    curves = {}
    for r in rows:
        if r["config"] == args.baseline:
            continue
        opts = ",".join(f"{k}={v}" for k, v in sorted(r.get("options", {}).items()))
        label = r["sampler"] + (f" {opts}" if opts else "")
        xs, ys = curves.setdefault(label, ([], []))
        xs.append(r.get("nfe", r["steps"]))
        ys.append(r["chamfer_cm"])
    curves[f"{args.baseline} level"] = ([1, 1000], [base["chamfer_cm"]] * 2)
    plot_curves(curves, out.with_suffix(".png"), xlabel="denoiser calls (NFE, log)", ylabel="Chamfer cm",
                title="Chamfer vs. NFE", logx=True)  # fmt: skip
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return result


if __name__ == "__main__":
    main()
