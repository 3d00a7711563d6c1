"""Paired probe: the regressors' N query points chosen evenly spread instead of at random. POP and
CloSET decode any query point on the body, so the layout of their N output points is theirs to
choose (PocoLoco's is not: its points are samples). Same frames / GT subsets as ``pocoloco bench
quality`` (28 frames, 2,048 points), one cloud per frame:

* ``random``: as shipped (POP: N of its training map's pixels at random; CloSET: N area-uniform
  random template points);
* ``even``: N of ``--factor`` x N such candidates by farthest-point sampling of their base points
  (POP: on the posed body, the candidates its pixels, or a finer map's when factor x N exceeds them;
  CloSET: on the template).

    python benchmarks/experiments/even_query_pilot.py --data ~/.cache/pocoloco/data/medium \
        --json benchmarks/results/even_query_medium.json
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np
import torch
from quality_frames import quality_frames

from pocoloco.body.surface import SurfacePoints, barycentric_interpolate
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.evaluation.metrics import m2s_cm, s2m_cm
from pocoloco.methods import load_method
from pocoloco.methods.pop import method as pop_method
from pocoloco.ops.sampling import farthest_point_sampling
from pocoloco.utils.atomic import write_json_atomic


def _fps(points: np.ndarray | torch.Tensor, n: int) -> np.ndarray:
    return farthest_point_sampling(torch.as_tensor(points, dtype=torch.float32)[None], n)[0].numpy()


def even_closet(method, factor: int):
    """CloSET's ``sample_query_points`` replaced by FPS (on the template) over factor x N random ones."""
    model, random_points = method.model, method.model.sample_query_points
    template, faces = model.template.cpu().numpy(), model.faces.cpu().numpy()

    def even(num: int, seed: int = 0) -> SurfacePoints:
        q = random_points(factor * num, seed)
        idx = _fps((template[faces[q.face_idx]] * q.barycentric[:, :, None]).sum(1), num)
        return SurfacePoints(q.face_idx[idx], q.barycentric[idx])

    return even


def even_pop(method, factor: int, body: np.ndarray):
    """``pop_query_for`` replaced by FPS (on this pose's body) over factor x N candidate pixels."""
    query_for = pop_method.pop_query_for

    def even(model, num_points: int, seed: int):
        q, R = query_for(model, max(factor * num_points, 1), seed) if factor * num_points > len(model.query_points()) \
            else (model.query_points(), model.config.query_resolution)  # fmt: skip
        base = barycentric_interpolate(torch.as_tensor(body)[None], model.faces, q.face_idx, q.barycentric)[0]
        return q.subset(np.sort(_fps(base, num_points))), R

    return even


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--splits", nargs="+", default=["test", "heldout"])
    p.add_argument("--frames", type=int, default=28)
    p.add_argument("--points", type=int, default=2048)
    p.add_argument("--factors", type=int, nargs="+", default=[1, 4], help="candidates per kept point (POP: 1 = its pixels)")
    p.add_argument("--json", required=True)
    args = p.parse_args()
    torch.set_num_threads(1)
    report: dict = {"command": "python " + " ".join(sys.argv), "points": args.points, "models": {}}
    print("| model | split | random: Chamfer (M2S / S2M) | arm | Chamfer (M2S / S2M) | minus random, paired |")
    print("|---|---|---|---|---|---|")
    for name in ("default:pop", "default:closet"):
        method = load_method(resolve_ckpt_arg(name))
        report["models"][name] = {}
        factors = [f for f in args.factors if name == "default:pop" or f > 1]
        for split in args.splits:
            rows = []
            for _, key, subject, gt, pose in quality_frames(method, args.data, split, args.frames, args.points):
                o = method.outfit_id(subject)
                clouds = {"random": method.predict(pose, args.points, (0,), o).points[0]}
                for f in factors:
                    if name == "default:pop":  # POP's body is pelvis-centred, as its predict poses it
                        body = np.asarray(pose.body_vertices, np.float32) - np.asarray(pose.joints[0], np.float32)
                        pop_method.pop_query_for, saved = even_pop(method, f, body), pop_method.pop_query_for
                        try:
                            clouds[f"even_x{f}"] = method.predict(pose, args.points, (0,), o).points[0]
                        finally:
                            pop_method.pop_query_for = saved
                    else:
                        method.model.sample_query_points, saved = even_closet(method, f), method.model.sample_query_points
                        try:
                            clouds[f"even_x{f}"] = method.predict(pose, args.points, (0,), o).points[0]
                        finally:
                            method.model.sample_query_points = saved
                row = {"key": key}
                for arm, c in clouds.items():
                    c = c.astype(np.float64)
                    m2s, s2m = m2s_cm(c, gt), s2m_cm(c, gt)
                    row[arm] = {"chamfer_cm": round(m2s + s2m, 4), "m2s_cm": round(m2s, 4), "s2m_cm": round(s2m, 4)}
                rows.append(row)
            means = {a: {k: float(np.mean([r[a][k] for r in rows])) for k in ("chamfer_cm", "m2s_cm", "s2m_cm")}
                     for a in rows[0] if a != "key"}  # fmt: skip
            report["models"][name][split] = {"means": means, "frames": rows}
            m0 = means["random"]
            for arm, m in means.items():
                if arm == "random":
                    continue
                d = np.array([r[arm]["chamfer_cm"] - r["random"]["chamfer_cm"] for r in rows])
                m["diff_cm"], m["se_cm"] = float(d.mean()), float(d.std(ddof=1) / math.sqrt(len(d)))
                print(f"| {name} | {split} | {m0['chamfer_cm']:.2f} ({m0['m2s_cm']:.2f} / {m0['s2m_cm']:.2f}) | {arm} | "
                      f"{m['chamfer_cm']:.2f} ({m['m2s_cm']:.2f} / {m['s2m_cm']:.2f}) | {m['diff_cm']:+.3f} +- {m['se_cm']:.3f} |",
                      flush=True)  # fmt: skip
            write_json_atomic(args.json, report, indent=None)


if __name__ == "__main__":
    main()
