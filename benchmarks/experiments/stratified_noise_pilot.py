"""Paired probe: PocoLoco's initial noise drawn stratified (scrambled Sobol points pushed through the
inverse normal CDF, one scramble per seed) instead of i.i.d. Gaussian, with the SDE and the ODE
solvers. Same frames / GT subsets as ``pocoloco bench quality``; K seeds per frame give Chamfer to
the scan (mean over hypotheses), the mean pairwise Chamfer between hypotheses (their spread) and
the energy score ``mean to-scan - pairwise / 2`` (metrics.energy_score_from_chamfers).

Only the first draw of each sample's generator (the initial noise) is replaced; the SDE's later
draws stay Gaussian. ``sample_clouds`` builds its RNG itself, so the probe swaps the class it uses.

    python benchmarks/experiments/stratified_noise_pilot.py --data ~/.cache/pocoloco/data/medium \
        --arms iid:dpm++sde:25 qmc:dpm++sde:25 iid:dpm++:20 qmc:dpm++:20 qmc:dpm++:30 \
        --json benchmarks/results/stratified_noise_medium.json
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np
import torch
from quality_frames import quality_frames
from scipy.stats import norm, qmc

import pocoloco.methods.pocoloco.sampling as pocoloco_sampling
from pocoloco.diffusion.sampler_base import PerSampleRNG
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.evaluation.metrics import chamfer_cm, m2s_cm, s2m_cm
from pocoloco.methods import SamplerOptions, load_method
from pocoloco.utils.atomic import write_json_atomic


class StratifiedFirstDraw(PerSampleRNG):
    """PerSampleRNG whose first ``randn`` (the initial noise, (N, C) per sample) is a scrambled Sobol
    set seeded by the sample's seed, mapped to N(0, 1) by the inverse CDF."""

    def __init__(self, seeds, device=None) -> None:
        super().__init__(seeds, device)
        self.first = True

    def randn(self, shape_per_sample, dtype=torch.float32, device=None) -> torch.Tensor:
        if not self.first:
            return super().randn(shape_per_sample, dtype, device)
        self.first = False
        n, c = shape_per_sample
        noise = []
        for s in self.seeds:
            u = np.clip(qmc.Sobol(d=c, scramble=True, seed=int(s)).random(n), 1e-6, 1 - 1e-6)
            z = norm.ppf(u)[np.random.default_rng(int(s)).permutation(n)]  # Sobol order is not random
            noise.append(torch.as_tensor(z, dtype=dtype))
        out = torch.stack(noise)
        return out.to(device) if device is not None else out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--ckpt", default="default")
    p.add_argument("--arms", nargs="+", required=True, help="NOISE:SAMPLER:STEPS, NOISE = iid or qmc; the first is the baseline")
    p.add_argument("--splits", nargs="+", default=["test", "heldout"])
    p.add_argument("--frames", type=int, default=28)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    p.add_argument("--points", type=int, default=2048)
    p.add_argument("--json", required=True)
    args = p.parse_args()
    torch.set_num_threads(1)
    method = load_method(resolve_ckpt_arg(args.ckpt))
    report: dict = {"command": "python " + " ".join(sys.argv), "seeds": args.seeds, "points": args.points, "splits": {}}
    for split in args.splits:
        rows = []
        for i, key, subject, gt, pose in quality_frames(method, args.data, split, args.frames, args.points):
            row = {"key": key}
            for arm in args.arms:
                noise, sampler, steps = arm.split(":")
                pocoloco_sampling.PerSampleRNG = StratifiedFirstDraw if noise == "qmc" else PerSampleRNG
                options = SamplerOptions(sampler=sampler, steps=int(steps), bf16=True)
                pts = method.predict(pose, args.points, args.seeds, method.outfit_id(subject), options).points.astype(np.float64)
                K = len(pts)
                row[arm] = {"m2s_cm": round(float(np.mean([m2s_cm(c, gt) for c in pts])), 4),
                            "s2m_cm": round(float(np.mean([s2m_cm(c, gt) for c in pts])), 4),
                            "pairwise_cm": round(float(np.mean([chamfer_cm(pts[a], pts[b]) for a in range(K)
                                                                for b in range(a + 1, K)])), 4)}  # fmt: skip
            pocoloco_sampling.PerSampleRNG = PerSampleRNG
            rows.append(row)
            print(f"  {i + 1}/{args.frames} {key}: "
                  + ", ".join(f"{a} {row[a]['m2s_cm'] + row[a]['s2m_cm']:.2f}" for a in args.arms), flush=True)  # fmt: skip
        summary = {}
        for arm in args.arms:
            ch = np.array([r[arm]["m2s_cm"] + r[arm]["s2m_cm"] for r in rows])
            es = ch - 0.5 * np.array([r[arm]["pairwise_cm"] for r in rows])
            ch0 = np.array([r[args.arms[0]]["m2s_cm"] + r[args.arms[0]]["s2m_cm"] for r in rows])
            es0 = ch0 - 0.5 * np.array([r[args.arms[0]]["pairwise_cm"] for r in rows])
            se = lambda d: float(d.std(ddof=1) / math.sqrt(len(d)))  # noqa: E731
            summary[arm] = {"chamfer_cm": float(ch.mean()), "m2s_cm": float(np.mean([r[arm]["m2s_cm"] for r in rows])),
                            "s2m_cm": float(np.mean([r[arm]["s2m_cm"] for r in rows])),
                            "pairwise_cm": float(np.mean([r[arm]["pairwise_cm"] for r in rows])),
                            "energy_score_cm": float(es.mean()), "chamfer_diff_cm": float((ch - ch0).mean()),
                            "chamfer_diff_se_cm": se(ch - ch0), "energy_score_diff_cm": float((es - es0).mean()),
                            "energy_score_diff_se_cm": se(es - es0)}  # fmt: skip
        report["splits"][split] = {"summary": summary, "frames": rows}
        write_json_atomic(args.json, report, indent=None)
        print(f"| {split} | Chamfer (M2S / S2M) | minus {args.arms[0]} | pairwise | energy score | minus {args.arms[0]} |")
        print("|---|---|---|---|---|---|")
        for arm, m in summary.items():
            print(f"| {arm} | {m['chamfer_cm']:.2f} ({m['m2s_cm']:.2f} / {m['s2m_cm']:.2f}) | "
                  f"{m['chamfer_diff_cm']:+.3f} +- {m['chamfer_diff_se_cm']:.3f} | {m['pairwise_cm']:.2f} | "
                  f"{m['energy_score_cm']:.2f} | {m['energy_score_diff_cm']:+.3f} +- {m['energy_score_diff_se_cm']:.3f} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
