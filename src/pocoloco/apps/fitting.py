"""Fitting an outfit a model never saw to one scan (``pocoloco fit``), and its before / after report.

The method does the fitting (POP: only a new geometric feature tensor is optimised against the
scan, paper Sec. 3.3 / Eq. 7, from the mean of the trained outfits; the network is frozen); this
module checks the inputs, scores the model on the scan before (the mean outfit, where fitting
starts, and the best trained outfit) and after fitting, and writes a new checkpoint with the outfit
added (then ``pocoloco sample --outfit NAME`` animates it in new poses) and ``fit.json``.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pocoloco.data.poses import dataset_frame_path
from pocoloco.data.published import read_ply
from pocoloco.engine.checkpoint import META_FILE, latest_checkpoint
from pocoloco.evaluation.metrics import evaluate_frame
from pocoloco.methods import METHODS, load_method
from pocoloco.utils.atomic import write_json_atomic

__all__ = ["MIN_SCAN_POINTS", "FitReport", "fit_outfit"]

#: fewest scan points ``pocoloco fit`` accepts
MIN_SCAN_POINTS = 256


@dataclass
class FitReport:
    """Chamfer of the fitted outfit before / after (metrics on the scan), and the new checkpoint."""

    checkpoint: Path
    outfit: str
    outfit_id: int
    before_mean: dict[str, float]
    before_nearest: dict[str, float]
    nearest_outfit: str
    after: dict[str, float]
    losses: list[float]
    seconds: float


def _score(pred_points, pred_normals, scan, scan_n) -> dict[str, float]:
    m = evaluate_frame(pred_points, pred_normals, scan, scan_n, None)
    return {k: float(m[k]) for k in ("chamfer_cm", "s2m_cm", "m2s_cm", "pop_chamfer_e-4m2", "normal_l1_e-1") if k in m}


def fit_outfit(ckpt: str | os.PathLike, scan_path: str | os.PathLike, frame_spec: str, out: str | os.PathLike,
               name: str | None = None, steps: int = 400, lr: float | None = None, num_points: int | None = None,
               seed: int = 0, progress=None) -> FitReport:  # fmt: skip
    """Fit a new outfit to one scan with a method that can (POP: paper Eq. 7) and write ``out`` = a
    new checkpoint folder with the outfit appended (atomic), plus ``out/fit.json``.

    The scan (PLY with normals, world frame of ``frame_spec``'s body) is subsampled to
    ``num_points`` (default: the model's ``num_scan_points``). Only the new (1, Cg, Ri, Ri)
    geometric feature tensor is optimised, from the mean of the trained outfits (the paper's
    init); the network is frozen. Chamfer is reported before (the mean outfit = the start point;
    and the best trained outfit) and after fitting, on the scan, with the model's query points.
    """
    loaded = load_method(ckpt, expect=tuple(k for k, c in METHODS.items() if c.fits_outfits))
    if not loaded.fits_outfits:
        raise ValueError(f"{loaded.path}: {loaded.title} cannot fit a new outfit to a scan; POP can "
                         "(e.g. --ckpt default:pop)")  # fmt: skip
    if isinstance(steps, bool) or steps < 1:
        raise ValueError(f"--steps must be >= 1, got {steps}")
    out = Path(out)
    if latest_checkpoint(out / "checkpoints") is not None or (out / META_FILE).exists():
        raise ValueError(f"{out}: already holds a checkpoint; choose another --out")
    if name is None:
        name = Path(scan_path).stem
    if name in loaded.outfit_names():
        raise ValueError(f"outfit name {name!r} already exists in {loaded.path}; pass another --name")
    if name.lstrip("-").isdigit():
        raise ValueError(f"--name {name!r}: outfit names must not be plain integers (they would read as ids)")
    ply = read_ply(scan_path, require_normals=True)
    scan, scan_n = ply.points, ply.normals
    if len(scan) < MIN_SCAN_POINTS:
        raise ValueError(f"{scan_path}: scan has {len(scan)} points; fitting needs at least {MIN_SCAN_POINTS}")
    lens = np.linalg.norm(scan_n, axis=1)
    if not (lens > 1e-6).all():
        raise ValueError(f"{scan_path}: {int((lens <= 1e-6).sum())} normals are zero; the point-to-plane loss needs normals")
    scan_n = (scan_n / lens[:, None]).astype(np.float32)
    n_fit = min(len(scan), num_points or loaded.model.config.num_scan_points)
    sel = np.sort(np.random.default_rng([seed, 6]).choice(len(scan), n_fit, replace=False))
    subject = frame_spec.rpartition(":")[2].strip("/").split("/")[0]
    pose = loaded.pose_from_frame(dataset_frame_path(frame_spec), subject)
    t0 = time.perf_counter()
    fit = loaded.fit_outfit(scan[sel], scan_n[sel], pose, steps=steps, lr=lr, progress=progress)
    seconds = time.perf_counter() - t0

    n_eval = min(len(scan), 10_000)
    esel = np.sort(np.random.default_rng([seed, 7]).choice(len(scan), n_eval, replace=False))
    gt, gt_n = scan[esel].astype(np.float64), scan_n[esel].astype(np.float64)

    def score(geom=None, outfit=0):
        c = loaded.predict(pose, n_eval, (seed,), outfit=outfit, geom=geom)
        return _score(c.points[0], c.normals[0], gt, gt_n)

    before_mean = score(geom=loaded.mean_outfit_code())
    trained_names = loaded.outfit_names()
    per_outfit = [score(outfit=i) for i in range(len(trained_names))]
    best = int(np.argmin([m["chamfer_cm"] for m in per_outfit]))
    after = score(geom=fit.features)

    phenotype = loaded.outfits[0].get("phenotype", {})
    if subject in trained_names:  # the body the scan was fitted on
        phenotype = loaded.outfits[loaded.outfit_id(subject)].get("phenotype", {})
    new_id = loaded.add_outfit(fit.features, {"name": name, "phenotype": phenotype,
                                              "source": f"fitted to {os.fspath(scan_path)} (body of {frame_spec})"})  # fmt: skip
    from_path = str(loaded.path)
    path = loaded.save(out / "checkpoints", extra={"fitted_from": from_path})
    report = FitReport(path, name, new_id, before_mean, per_outfit[best], trained_names[best], after,
                       fit.losses, seconds)  # fmt: skip
    write_json_atomic(out / "fit.json", {
        "checkpoint": str(path), "from": from_path, "scan": os.fspath(scan_path), "frame": frame_spec,
        "outfit": name, "outfit_id": new_id, "steps": steps, "scan_points_fit": n_fit, "eval_points": n_eval,
        "before_mean_outfit": before_mean, "before_nearest_outfit": {"outfit": report.nearest_outfit, **per_outfit[best]},
        "after": after, "loss_first": fit.losses[0], "loss_last": fit.losses[-1], "seconds": seconds,
        "note": "Chamfer on the scan (10K points at most) with the same number of model points; 'before' = the mean of "
                "the trained outfits' features (where fitting starts) and the best single trained outfit",
    })  # fmt: skip
    return report
