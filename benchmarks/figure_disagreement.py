"""GT, PocoLoco (2 hypotheses), POP and CloSET side by side on the loose-garment frames where the
models disagree most: the frames of a ``bench quality`` run whose Chamfer differs most between
PocoLoco and POP, one per subject, points coloured by label (a generated point takes the label of
its nearest scan point); each panel's title gives Chamfer to the scan and the share of loose-garment points.

    python benchmarks/figure_disagreement.py --data ~/.cache/pocoloco/data/medium \\
        --quality benchmarks/results/quality_medium/test/quality.json --ckpt-pocoloco default --ckpt-pop default:pop \\
        --ckpt-closet default:closet --out docs/images/models_disagree.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from pocoloco.data.format import read_frame
from pocoloco.data.poses import dataset_frame_path
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.evaluation.metrics import LABEL_GARMENT, chamfer_cm
from pocoloco.methods import load_method
from pocoloco.viz.render import render_grid


def pick_frames(quality: dict, num: int, rows: tuple[str, str] = ("pocoloco", "pop")) -> list[str]:
    """Keys of the ``num`` loose-garment frames (scan >= 20 % loose) with the largest |Chamfer
    difference| between the two rows, at most one per subject."""
    a = {r["key"]: r["model"] for r in quality["frames"][rows[0]]}
    b = {r["key"]: r["model"] for r in quality["frames"][rows[1]]}
    keys = [k for k in a if k in b and a[k].get("loose_gt_pct", 0) >= 20]
    keys.sort(key=lambda k: -abs(a[k]["chamfer_cm"] - b[k]["chamfer_cm"]))
    chosen, subjects = [], set()
    for k in keys:
        if k.split("/")[0] not in subjects:
            chosen.append(k)
            subjects.add(k.split("/")[0])
        if len(chosen) == num:
            break
    return chosen


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--quality", required=True, type=Path, help="quality.json of `pocoloco bench quality` on --data")
    ap.add_argument("--ckpt-pocoloco", default="default")
    ap.add_argument("--ckpt-pop", default="default:pop")
    ap.add_argument("--ckpt-closet", default=None)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", required=True, type=Path)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    quality = json.loads(args.quality.read_text())
    split = quality["settings"]["split"]
    models = [("PocoLoco", load_method(resolve_ckpt_arg(args.ckpt_pocoloco)), (0, 1)),
              ("POP", load_method(resolve_ckpt_arg(args.ckpt_pop)), (0,))]  # fmt: skip
    if args.ckpt_closet:
        models.append(("CloSET", load_method(resolve_ckpt_arg(args.ckpt_closet)), (0,)))
    panels, poses = [], []  # poses: each panel's joints (the shading's normals face away from its bones)
    for key in pick_frames(quality, args.frames):
        subject, _, seq, index = key.split("/")
        path = dataset_frame_path(f"{args.data}:{subject}/{split}/{seq}/{int(index)}")
        frame = read_frame(path)
        sel = np.random.default_rng(0).choice(len(frame.points), min(args.points, len(frame.points)), replace=False)
        gt, gt_labels = frame.points[sel], frame.labels[sel]
        tree = cKDTree(gt)
        row = [(gt, gt_labels, None, f"scan {subject} {seq[-2:]}/{int(index)}")]
        for title, method, seeds in models:
            outfit = method.outfit_id(subject)
            pose = method.pose_from_frame(path, subject, frame=frame)
            clouds = method.predict(pose, args.points, seeds, outfit)
            for k, pts in enumerate(clouds.points):
                label = gt_labels[tree.query(pts)[1]]
                name = f"{title} #{k + 1}" if len(seeds) > 1 else title
                row.append((pts, label, None, f"{name} {chamfer_cm(pts, gt):.1f}cm {100 * np.mean(label == LABEL_GARMENT):.0f}%"))
        panels += row
        poses += [frame.joints] * len(row)
    ncols = 1 + sum(len(s) for _, _, s in models)
    print(render_grid(panels, args.out, views=("front", "side"), ncols=ncols, panel_size=2.2, joints=poses))


if __name__ == "__main__":
    main()
