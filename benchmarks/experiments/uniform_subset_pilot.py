"""Paired probe: is a model's Chamfer gap surface noise or uneven point density? Post-processing
only, no training. For each frame and seed of ``pocoloco bench quality`` (same frames, same GT
subsets), one cloud of N points as the model draws it, then:

* ``plane_kK``: every point projected onto the least-squares plane of its K nearest neighbours in
  its own cloud (one step of a moving-least-squares projection, Alexa et al. 2003) -- what a
  denoising filter would buy if the error were a noisy shell around the surface;
* ``dense_random`` / ``dense_fps``: the model draws ``--dense-factor`` x N points (another
  sample of the same pose and seed) and keeps N of them at random or by farthest-point sampling
  (:func:`pocoloco.ops.sampling.farthest_point_sampling`) -- what a more even spread of the same
  surface buys. ``dense_fps`` minus ``dense_random`` is paired on the very same cloud.

    python benchmarks/experiments/uniform_subset_pilot.py --data ~/.cache/pocoloco/data/medium \
        --ckpt default --ckpt default:pop --json benchmarks/results/uniform_subset_medium.json
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
from quality_frames import quality_frames
from scipy.spatial import cKDTree

from pocoloco.engine.shipped import describe_checkpoint, resolve_ckpt_arg
from pocoloco.evaluation.metrics import m2s_cm, s2m_cm
from pocoloco.methods import SamplerOptions, load_method
from pocoloco.ops.sampling import farthest_point_sampling
from pocoloco.utils.atomic import write_json_atomic

PLANE_K = (8, 16)


def plane_project(points: np.ndarray, k: int) -> np.ndarray:
    """(N, 3) -> (N, 3): each point moved onto the PCA plane of its k nearest neighbours (itself
    included) along that plane's normal."""
    _, idx = cKDTree(points).query(points, k)
    nb = points[idx]  # (N, k, 3)
    centre = nb.mean(1)
    d = nb - centre[:, None]
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d))
    normal = vec[:, :, 0]  # smallest eigenvalue's eigenvector
    return points - np.einsum("ni,ni->n", points - centre, normal)[:, None] * normal


def fps_subset(points: np.ndarray, n: int) -> np.ndarray:
    """(M, 3) -> (n, 3) by farthest-point sampling, starting at point 0."""
    idx = farthest_point_sampling(torch.as_tensor(points, dtype=torch.float32)[None], n)[0].numpy()
    return points[idx]


def probe(method, data: str, split: str, frames: int, points: int, factor: int, seeds: list[int]) -> list[dict]:
    options, rows = SamplerOptions(bf16=True), []
    for n_done, key, subject, gt, pose in quality_frames(method, data, split, frames, points):
        outfit = method.outfit_id(subject) if method.outfit_names() else None
        draws = seeds[:1] if method.deterministic else seeds  # a regressor: one cloud per pose
        direct = method.predict(pose, points, draws, outfit, options).points.astype(np.float64)
        dense = method.predict(pose, factor * points, draws, outfit, options).points.astype(np.float64)
        rng = np.random.default_rng([n_done, 7])
        clouds: dict[str, list[np.ndarray]] = {"direct": list(direct)}
        for k in PLANE_K:
            clouds[f"plane_k{k}"] = [plane_project(c, k) for c in direct]
        clouds["dense_random"] = [c[rng.choice(len(c), points, replace=False)] for c in dense]
        clouds["dense_fps"] = [fps_subset(c, points) for c in dense]
        row = {"key": key, "subject": subject}
        for name, cs in clouds.items():
            m2s, s2m = float(np.mean([m2s_cm(c, gt) for c in cs])), float(np.mean([s2m_cm(c, gt) for c in cs]))
            row[name] = {"chamfer_cm": round(m2s + s2m, 4), "m2s_cm": round(m2s, 4), "s2m_cm": round(s2m, 4)}
        rows.append(row)
        print(f"  {n_done + 1}/{frames} {key}: "
              + ", ".join(f"{n} {row[n]['chamfer_cm']:.2f}" for n in clouds), flush=True)  # fmt: skip
    return rows


def paired(rows: list[dict], name: str, base: str) -> dict[str, float]:
    d = np.array([r[name]["chamfer_cm"] - r[base]["chamfer_cm"] for r in rows])
    return {"diff_cm": float(d.mean()), "se_cm": float(d.std(ddof=1) / math.sqrt(len(d)))}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--ckpt", action="append", required=True, help="a model (repeat for several)")
    p.add_argument("--splits", nargs="+", default=["test", "heldout"])
    p.add_argument("--frames", type=int, default=28)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--points", type=int, default=2048)
    p.add_argument("--dense-factor", type=int, default=4)
    p.add_argument("--json", required=True)
    args = p.parse_args()
    torch.set_num_threads(1)
    report: dict = {"command": "python benchmarks/experiments/uniform_subset_pilot.py " + " ".join(
        f"--ckpt {c}" for c in args.ckpt), "points": args.points, "dense_factor": args.dense_factor,
        "frames": args.frames, "seeds": args.seeds, "models": {}}  # fmt: skip
    print("| model | split | direct Chamfer (M2S / S2M) | variant | Chamfer (M2S / S2M) | paired vs direct | paired vs dense_random |")
    print("|---|---|---|---|---|---|---|")
    for ckpt in args.ckpt:
        method = load_method(resolve_ckpt_arg(ckpt))
        name = describe_checkpoint(method.path)
        report["models"][name] = {}
        for split in args.splits:
            t0 = time.perf_counter()
            rows = probe(method, args.data, split, args.frames, args.points, args.dense_factor, args.seeds)
            means = {v: {k: float(np.mean([r[v][k] for r in rows])) for k in ("chamfer_cm", "m2s_cm", "s2m_cm")}
                     for v in rows[0] if v not in ("key", "subject")}  # fmt: skip
            vs = {v: {"direct": paired(rows, v, "direct"), "dense_random": paired(rows, v, "dense_random")}
                  for v in means if v != "direct"}  # fmt: skip
            report["models"][name][split] = {"means": means, "paired": vs, "seconds": time.perf_counter() - t0,
                                             "frames": rows}  # fmt: skip
            m0 = means["direct"]
            for v, m in means.items():
                if v == "direct":
                    continue
                a, b = vs[v]["direct"], vs[v]["dense_random"]
                print(f"| {name} | {split} | {m0['chamfer_cm']:.2f} ({m0['m2s_cm']:.2f} / {m0['s2m_cm']:.2f}) | {v} | "
                      f"{m['chamfer_cm']:.2f} ({m['m2s_cm']:.2f} / {m['s2m_cm']:.2f}) | "
                      f"{a['diff_cm']:+.3f} +- {a['se_cm']:.3f} | {b['diff_cm']:+.3f} +- {b['se_cm']:.3f} |", flush=True)  # fmt: skip
            write_json_atomic(args.json, report, indent=None)  # after every split: a long run keeps what it measured


if __name__ == "__main__":
    main()
