"""Fitting an outfit a model never saw to one scan (``pocoloco fit``), and its before / after report.

The method does the fitting (POP: only a new geometric feature tensor is optimised against one
scan, paper Sec. 3.3 / Eq. 7; PocoLoco: only a new outfit code, with the diffusion loss, on one or
a few scans; both start from the trained outfit nearest to the first scan, or from the mean of the
trained outfits, the network frozen); this module checks the inputs, scores the model on the scan
before (every trained outfit; the start) and after fitting, and writes a new checkpoint with the outfit added (then
``pocoloco sample --outfit NAME`` puts it in new poses) and ``fit.json``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pocoloco.apps.common import check_scan
from pocoloco.data.format import read_card, read_frame
from pocoloco.data.poses import dataset_frame_path
from pocoloco.data.published import check_cloud, read_ply
from pocoloco.engine.checkpoint import META_FILE, latest_checkpoint
from pocoloco.evaluation.metrics import evaluate_frame
from pocoloco.methods import load_method
from pocoloco.models.conditioning import phenotype_vector
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
    start: str
    before_start: dict[str, float]
    before_nearest: dict[str, float]
    nearest_outfit: str
    after: dict[str, float]
    losses: list[float]
    seconds: float


def _score(pred_points, pred_normals, scan, scan_n) -> dict[str, float]:
    m = evaluate_frame(pred_points, pred_normals, scan, scan_n, None)
    return {k: float(m[k]) for k in ("chamfer_cm", "s2m_cm", "m2s_cm", "pop_chamfer_e-4m2", "normal_l1_e-1") if k in m}


def _read_scan(path: str | os.PathLike, need_normals: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(points, unit normals or None, per-point labels or None) of a scan PLY."""
    ply = read_ply(path, require_normals=need_normals)
    scan, scan_n = check_cloud(os.fspath(path), ply.points), ply.normals
    labels = None if ply.labels is None else np.asarray(ply.labels, np.int64)
    if len(scan) < MIN_SCAN_POINTS:
        raise ValueError(f"{path}: scan has {len(scan)} points; fitting needs at least {MIN_SCAN_POINTS}")
    if scan_n is None:
        return scan, None, labels
    lens = np.linalg.norm(scan_n, axis=1)
    if not (lens > 1e-6).all():
        if need_normals:
            raise ValueError(f"{path}: {int((lens <= 1e-6).sum())} normals are zero; the point-to-plane loss needs normals")
        return scan, None, labels
    return scan, (scan_n / lens[:, None]).astype(np.float32), labels


def fit_outfit(ckpt: str | os.PathLike, scans: Sequence[tuple[str | os.PathLike, str]], out: str | os.PathLike,
               name: str | None = None, steps: int = 400, lr: float | None = None, num_points: int | None = None,
               seed: int = 0, start: str = "nearest", anchor: float = 0.0, progress=None) -> FitReport:  # fmt: skip
    """Fit a new outfit to scans of a garment the model never saw and write ``out`` = a new checkpoint
    folder with the outfit appended (atomic), plus ``out/fit.json``.

    scans: [(PLY path, ``DATASET:subject/split/sequence/index`` of the body and pose it was captured
    in)], world frame of that frame's body; POP takes one scan (paper Eq. 7; its loss needs the
    normals), PocoLoco one or a few. Each scan is subsampled to ``num_points`` (default: the model's
    own). Only the new outfit code is optimised (POP: its geometric feature tensor; PocoLoco: its
    outfit embedding, with the diffusion loss); the network is frozen. ``start``: ``nearest`` = the
    trained outfit whose samples are closest (Chamfer) to the first scan, ``mean`` = the mean of the
    trained outfits (POP Sec. 3.3). ``anchor`` (PocoLoco): weight of an L2 pull of the code to its
    start. Chamfer is reported on the first scan before (the start; the best trained outfit) and
    after fitting, with the same seeds for every row.
    """
    loaded = load_method(ckpt)
    if not loaded.fits_outfits:
        raise ValueError(f"{loaded.path}: this {loaded.title} checkpoint cannot fit a new outfit (POP can, and PocoLoco "
                         "trained with --outfit-codes; a distilled model cannot: fit with its teacher)")  # fmt: skip
    if isinstance(steps, bool) or steps < 1:
        raise ValueError(f"--steps must be >= 1, got {steps}")
    if not scans:
        raise ValueError("fitting needs at least one --scan")
    if start not in ("nearest", "mean"):
        raise ValueError(f"--start must be 'nearest' or 'mean', got {start!r}")
    if not (np.isfinite(anchor) and anchor >= 0):
        raise ValueError(f"--anchor must be a finite number >= 0, got {anchor}")
    out = Path(out)
    if latest_checkpoint(out / "checkpoints") is not None or (out / META_FILE).exists():
        raise ValueError(f"{out}: already holds a checkpoint; choose another --out")
    if name is None:
        name = Path(scans[0][0]).stem
    if name in loaded.outfit_names():
        raise ValueError(f"outfit name {name!r} already exists in {loaded.path}; pass another --name")
    if name.lstrip("-").isdigit():
        raise ValueError(f"--name {name!r}: outfit names must not be plain integers (they would read as ids)")
    read = [_read_scan(path, loaded.fit_needs_normals) for path, _ in scans]
    n_fit = num_points or loaded.fit_points()
    fit_scans, poses, fit_labels = [], [], []
    for k, ((path, frame_spec), (scan, scan_n, labels)) in enumerate(zip(scans, read, strict=True)):
        sel = np.sort(np.random.default_rng([seed, 6, k]).choice(len(scan), min(len(scan), n_fit), replace=False))
        subject = frame_spec.rpartition(":")[2].strip("/").split("/")[0]
        pose = loaded.pose_from_frame(dataset_frame_path(frame_spec), subject,
                                      frame=read_frame(dataset_frame_path(frame_spec)))  # fmt: skip
        check_scan(os.fspath(path), scan, pose.joints)  # units and frame, as completion checks them
        fit_scans.append((scan[sel], None if scan_n is None else scan_n[sel], pose))
        fit_labels.append(None if labels is None else labels[sel])
        poses.append(pose)
    trained_names = loaded.outfit_names()
    subject = poses[0].subject
    # the body the scans were taken on: a trained subject's, else the one its dataset card records
    if subject in trained_names:
        phenotype = loaded.outfits[loaded.outfit_id(subject)].get("phenotype", {})
    else:
        card_subject = read_card(scans[0][1].rpartition(":")[0]).get("subjects", {}).get(subject) or {}
        phenotype = dict(card_subject.get("phenotype") or loaded.outfits[0].get("phenotype", {}))
    scan, scan_n, _ = read[0]
    n_eval = min(len(scan), 10_000)
    esel = np.sort(np.random.default_rng([seed, 7]).choice(len(scan), n_eval, replace=False))
    gt, gt_n = scan[esel].astype(np.float64), None if scan_n is None else scan_n[esel].astype(np.float64)

    def score(code=None, outfit=0):
        c = loaded.predict(poses[0], n_eval, (seed,), outfit=outfit, code=code)
        return _score(c.points[0], None if c.normals is None else c.normals[0], gt, gt_n)

    per_outfit = [score(outfit=i) for i in range(len(trained_names))]
    best = int(np.argmin([m["chamfer_cm"] for m in per_outfit]))
    start_code = loaded.outfit_code(best) if start == "nearest" else loaded.mean_outfit_code()
    t0 = time.perf_counter()
    fit = loaded.fit_outfit(fit_scans, steps=steps, lr=lr, progress=progress, shape=phenotype_vector(phenotype),
                            seed=seed, init=start_code, anchor=anchor, labels=fit_labels)  # fmt: skip
    seconds = time.perf_counter() - t0

    sources = "; ".join(f"{os.fspath(p)} (body of {f})" for p, f in scans)
    new_id = loaded.add_outfit(fit.features, {"name": name, "phenotype": phenotype, "source": f"fitted to {sources}"})
    before_start = score(code=start_code, outfit=new_id)  # the scans' body, the start code
    after = score(outfit=new_id)  # exactly what the saved checkpoint samples
    from_path = str(loaded.path)
    path = loaded.save(out / "checkpoints", extra={"fitted_from": from_path})
    report = FitReport(path, name, new_id, start, before_start, per_outfit[best], trained_names[best], after,
                       fit.losses, seconds)  # fmt: skip
    write_json_atomic(out / "fit.json", {
        "checkpoint": str(path), "from": from_path, "model_kind": loaded.kind,
        "scans": [{"scan": os.fspath(p), "frame": f} for p, f in scans], "scan": os.fspath(scans[0][0]),
        "frame": scans[0][1], "outfit": name, "outfit_id": new_id, "steps": steps, "scan_points_fit": n_fit,
        "start": start, "anchor": anchor, "eval_points": n_eval, "before_start": before_start,
        "before_nearest_outfit": {"outfit": report.nearest_outfit, **per_outfit[best]}, "after": after,
        "loss_first": fit.losses[0], "loss_last": fit.losses[-1], "seconds": seconds,
        "note": "Chamfer on the first scan (10K points at most) with the same number of model points and the same "
                "seed for every row; 'before_start' = the start code ('nearest': the best trained outfit's code on "
                "the scans' body; 'mean': the mean of the trained outfits' codes), 'before_nearest_outfit' = the "
                "best trained outfit as trained (its own body shape)",
    })  # fmt: skip
    return report
