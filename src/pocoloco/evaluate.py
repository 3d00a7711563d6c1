"""``pocoloco eval``: a trained model and two baselines scored on the test frames of a dataset.

For every evaluated test frame (joints K, ground-truth scan G with normals and labels):

* **model**: S clouds of N points sampled for K (one per seed, ``pocoloco.sample.sample_clouds``);
  each is scored against G (:func:`pocoloco.metrics.evaluate_frame`) and the S scores are
  averaged, as the PocoLoco paper averages its metrics over several samples. Diversity is the
  mean pairwise Chamfer (cm) among the S clouds, over the whole cloud and separately over the
  points in the garment / body region (each point takes the label of its nearest GT point).
* **nearest-frame** baseline: the training frame of the same subject whose root-aligned joints
  are nearest to K (sum of squared joint distances), its scan translated by the root offset.
* **posed-body** baseline: N points sampled uniformly on the frame's posed minimally-clothed
  body (the body the garment was simulated on), with face normals.
* **GT resample** (reference row, the metric's own noise floor): another N-point subset of
  the same scan.

G is an N-point subset of the scan (fixed seed), so every row compares N points with N points.
Metric definitions and units: :mod:`pocoloco.metrics` (Chamfer = S2M + M2S in cm, unsquared;
POP CD = squared, point-to-plane M2S, in 1e-4 m^2).

Output folder: ``eval.json`` (settings, per-frame rows, means per method and per subject),
``eval.md`` (the same tables in markdown), ``chamfer_per_frame.png`` (per-frame Chamfer of
every method), ``examples.png`` (GT, baselines and samples for a few frames, coloured by label;
a generated point takes the label of its nearest GT point).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pocoloco.metrics import diversity_cm, evaluate_frame, nearest, summarise
from pocoloco.utils.atomic import output_folder

__all__ = ["EvalSettings", "METHODS", "add_eval_arguments", "cmd_eval", "evaluate", "markdown_tables",
           "select_frames", "NearestFrameBaseline"]  # fmt: skip

#: methods in the order of the tables; "model" is the checkpoint being evaluated
METHODS = ("model", "nearest_frame", "posed_body", "gt_resample")
METHOD_TITLES = {
    "model": "PocoLoco (this checkpoint)",
    "nearest_frame": "nearest training frame (pose)",
    "posed_body": "posed body (no clothes)",
    "gt_resample": "GT resample (noise floor)",
}
#: columns of the markdown table: (key, header, format)
TABLE_COLUMNS = (
    ("chamfer_cm", "Chamfer cm", "{:.2f}"),
    ("s2m_cm", "S2M cm", "{:.2f}"),
    ("m2s_cm", "M2S cm", "{:.2f}"),
    ("pop_chamfer_e-4m2", "CD 1e-4 m^2", "{:.2f}"),
    ("normal_l1_e-1", "normal 1e-1", "{:.2f}"),
    ("fscore_pct", "F@1cm %", "{:.1f}"),
    ("loose_pred_pct", "loose %", "{:.1f}"),
    ("loose_gt_pct", "loose GT %", "{:.1f}"),
    ("diversity_cm", "div. cm", "{:.2f}"),
    ("diversity_garment_cm", "div. garment", "{:.2f}"),
    ("diversity_body_cm", "div. body", "{:.2f}"),
    ("seconds_per_sample", "s/sample", "{:.2f}"),
)


@dataclass(frozen=True)
class EvalSettings:
    """What ``pocoloco eval`` evaluates.

    split: dataset split. num_frames: frames evaluated, evenly spaced over the split's frames in
    order (0 or >= the split size: all). num_points: N points per cloud (model, baselines and
    the GT subset). seeds: one model sample per seed and frame. sampler / steps: see
    ``pocoloco sample``. baselines: which of ``nearest_frame``, ``posed_body``, ``gt_resample``.
    subjects: restrict to these subjects (None: all). batch_size: clouds sampled together.
    use_ema: EMA (default) or raw weights. clip: x0 clamp of the sampler (``sample_clouds``).
    bf16: the denoiser under bf16 autocast (``sample_clouds``). nearest_align: ``root`` or ``yaw``
    (``NearestFrameBaseline``).
    """

    split: str = "test"
    num_frames: int = 24
    num_points: int = 10_000
    seeds: tuple[int, ...] = (0, 1, 2)
    sampler: str = "dpm++sde"
    steps: int | None = None
    baselines: tuple[str, ...] = ("nearest_frame", "posed_body", "gt_resample")
    subjects: tuple[str, ...] | None = None
    batch_size: int = 4
    use_ema: bool = True
    clip: float | None = None
    bf16: bool = False
    nearest_align: str = "root"

    def __post_init__(self):
        if self.num_frames < 0:
            raise ValueError(f"num_frames must be >= 0, got {self.num_frames}")
        if self.num_points < 1:
            raise ValueError(f"num_points must be >= 1, got {self.num_points}")
        if len(self.seeds) < 1:
            raise ValueError("at least one seed is needed")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds must be distinct, got {list(self.seeds)}")
        unknown = [b for b in self.baselines if b not in METHODS[1:]]
        if unknown:
            raise ValueError(f"unknown baselines {unknown}; choose from {', '.join(METHODS[1:])}")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.clip is not None and not self.clip > 0:
            raise ValueError(f"clip must be > 0, got {self.clip}")
        if self.nearest_align not in NEAREST_ALIGNS:
            raise ValueError(f"nearest_align must be one of {', '.join(NEAREST_ALIGNS)}, got {self.nearest_align!r}")


# ------------------------------------------------------------------------------------- frames
def select_frames(frames: Sequence[Any], num: int) -> list[int]:
    """Indices of ``num`` frames evenly spaced over ``frames`` (all of them if num is 0 or too large)."""
    n = len(frames)
    if num <= 0 or num >= n:
        return list(range(n))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, num)})


def _subset(n: int, k: int, seed: Sequence[int]) -> np.ndarray:
    """Sorted indices of min(k, n) of n items drawn without replacement from ``default_rng(seed)``."""
    return np.sort(np.random.default_rng(list(seed)).choice(n, size=min(k, n), replace=False))


#: how ``NearestFrameBaseline`` aligns a training pose to the query before comparing
NEAREST_ALIGNS = ("root", "yaw")


def _yaw_to_match(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Angles theta (F,) of the rotations R_y(theta) about the vertical (y) axis minimising
    sum_j |R_y(theta) src_fj - dst_j|^2 (2-D Procrustes in the x-z plane; closed form).

    src: (F, J, 3) root-aligned joints; dst: (J, 3). R_y(theta) maps (x, z) to
    (cos x + sin z, -sin x + cos z)."""
    a = (dst[None, :, 0] * src[..., 0] + dst[None, :, 2] * src[..., 2]).sum(-1)
    b = (dst[None, :, 0] * src[..., 2] - dst[None, :, 2] * src[..., 0]).sum(-1)
    return np.arctan2(b, a)


def _rotate_y(x: np.ndarray, theta: float | np.ndarray) -> np.ndarray:
    """x: (..., 3) rotated by R_y(theta) (see ``_yaw_to_match``); theta broadcasts over x[..., 0]."""
    c, s = np.cos(theta), np.sin(theta)
    out = np.array(x, dtype=np.float64, copy=True)
    out[..., 0] = c * x[..., 0] + s * x[..., 2]
    out[..., 2] = -s * x[..., 0] + c * x[..., 2]
    return out


class NearestFrameBaseline:
    """The training frame nearest in pose: argmin_f sum_j |(k_j - k_root) - A_f(k'_fj - k'_f,root)|^2,
    over the frames of one subject (``subject=``) or of all.

    ``align="root"`` (default): A_f = identity, the poses compared after moving the roots together.
    ``align="yaw"``: A_f = the rotation about the vertical axis that best fits frame f to the query
    (closed form), so a query facing a direction no training frame faces still finds its pose.
    Reads only the joints of every training frame at construction (fast); the chosen frame's
    points are read on demand and moved by the same rigid motion onto the query pose.
    """

    def __init__(self, root: str | os.PathLike, subjects: Sequence[str] | None = None, root_joint: int = 0,
                 align: str = "root"):  # fmt: skip
        from pocoloco.data import format as fmt

        if align not in NEAREST_ALIGNS:
            raise ValueError(f"nearest-frame alignment must be one of {', '.join(NEAREST_ALIGNS)}, got {align!r}")
        self.align = align

        layout = fmt.DatasetLayout(root)
        chosen = sorted(subjects) if subjects else layout.subjects()
        self.frames = layout.iter_frames("train", chosen)
        if not self.frames:
            raise ValueError(f"{root}: no training frames for the nearest-frame baseline")
        self.root_joint = root_joint
        joints = np.stack([fmt.read_frame(p, ["joints"]).joints for _, _, p in self.frames]).astype(np.float64)
        self.joints = joints  # (F, J, 3)
        self.aligned = joints - joints[:, root_joint : root_joint + 1]  # (F, J, 3)
        self.subject_of = np.array([s for s, _, _ in self.frames])  # (F,)

    def nearest(self, joints: np.ndarray, subject: str | None = None) -> tuple[int, float, float]:
        """(index into ``frames``, RMS joint distance in metres, yaw angle in radians applied to
        that frame: 0 unless ``align="yaw"``) of the nearest training pose (among ``subject``'s
        frames if given)."""
        q = np.asarray(joints, np.float64)
        q = q - q[self.root_joint]
        if self.align == "yaw":
            theta = _yaw_to_match(self.aligned, q)  # (F,)
            cand = _rotate_y(self.aligned, theta[:, None])
        else:
            theta, cand = np.zeros(len(self.aligned)), self.aligned
        d2 = ((cand - q[None]) ** 2).sum(-1).mean(-1)  # (F,)
        if subject is not None:
            if not (self.subject_of == subject).any():
                raise ValueError(f"no training frames of subject {subject!r} for the nearest-frame baseline")
            d2 = np.where(self.subject_of == subject, d2, np.inf)
        i = int(np.argmin(d2))
        return i, float(math.sqrt(d2[i])), float(theta[i])

    def predict(self, joints: np.ndarray, num_points: int, seed: Sequence[int],
                subject: str | None = None) -> dict[str, Any]:  # fmt: skip
        """N points (+ normals, labels) of the nearest training frame, moved onto the query root."""
        from pocoloco.data import format as fmt

        i, rms, theta = self.nearest(joints, subject)
        fr = fmt.read_frame(self.frames[i][2], ["points", "normals", "joints", "labels"], allow_missing=True)
        sel = _subset(fr.points.shape[0], num_points, seed)
        src_root = fr.joints[self.root_joint].astype(np.float64)
        dst_root = np.asarray(joints, np.float64)[self.root_joint]
        points = _rotate_y(fr.points[sel] - src_root, theta) + dst_root
        normals = _rotate_y(fr.normals[sel], theta)
        return {"points": points, "normals": normals.astype(fr.normals.dtype),
                "source": str(self.frames[i][2]), "labels": None if fr.labels is None else fr.labels[sel],
                "pose_rms_m": rms, "yaw_deg": math.degrees(theta)}  # fmt: skip


def _posed_body(frame, faces: np.ndarray, num_points: int, seed: int) -> dict[str, Any]:
    from pocoloco.ops.sampling import sample_surface

    s = sample_surface(frame.body_vertices.astype(np.float64), faces, num_points, seed=seed)
    return {"points": s.points, "normals": s.normals}


# ---------------------------------------------------------------------------------- evaluation
@dataclass
class EvalResult:
    """settings: the EvalSettings as a dict plus checkpoint facts. frames: one dict per frame with
    ``key``, ``subject`` and a metrics dict per method. means: method -> mean metrics;
    per_subject: subject -> method -> mean metrics."""

    settings: dict[str, Any]
    frames: list[dict[str, Any]] = field(default_factory=list)
    means: dict[str, dict[str, float]] = field(default_factory=dict)
    per_subject: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"settings": self.settings, "means": self.means, "per_subject": self.per_subject,
                "frames": self.frames}  # fmt: skip


def evaluate(
    ckpt: str | os.PathLike | None,
    data: str | os.PathLike,
    settings: EvalSettings = EvalSettings(),
    *,
    device: str = "cpu",
    progress: Callable[[int, int], None] | None = None,
    keep_examples: int = 3,
) -> tuple[EvalResult, list[dict[str, Any]]]:
    """Score ``ckpt`` (None: baselines only) on ``settings.split`` of the dataset at ``data``.

    Returns the :class:`EvalResult` and, for up to ``keep_examples`` frames, the clouds (GT,
    baselines, model samples) to render.
    """
    from pocoloco.data import format as fmt

    card = fmt.read_card(data)
    layout = fmt.DatasetLayout(data)
    subjects = list(settings.subjects) if settings.subjects else None
    if subjects:
        unknown = [s for s in subjects if s not in card["subjects"]]
        if unknown:
            raise ValueError(f"{data}: unknown subjects {unknown}; the card lists {sorted(card['subjects'])}")
    all_frames = layout.iter_frames(settings.split, subjects or layout.subjects())
    if not all_frames:
        raise ValueError(f"{data}: no frames in split {settings.split!r}")
    chosen = [all_frames[i] for i in select_frames(all_frames, settings.num_frames)]

    info: dict[str, Any] = {"data": os.fspath(data), **_settings_dict(settings)}
    model = peer = None
    if ckpt is not None:
        from pocoloco.checkpoint import load_denoiser, resolve_checkpoint
        from pocoloco.peers import PEER_KINDS, checkpoint_kind, load_peer

        path = resolve_checkpoint(ckpt)
    if ckpt is not None and checkpoint_kind(path) in PEER_KINDS:
        # POP / CloSET: one deterministic cloud per frame (outfit = the frame's subject)
        peer = load_peer(path, device=device)
        info.update(checkpoint=str(path), step=peer.step, preset=peer.config.preset, model_kind=peer.kind,
                    model_title=peer.title, num_parameters=peer.num_parameters, deterministic=True)  # fmt: skip
        for subject in sorted({s for s, _, _ in chosen}):
            peer.outfit_id(subject)  # one-line error before any work if a subject was never trained
        _check_normalisation(peer.normalisation, card, path, data)
    elif ckpt is not None:
        model, normalisation, config = load_denoiser(path, use_ema=settings.use_ema, device=device)
        from pocoloco.sample import _check_sampler

        _check_sampler(settings.sampler, settings.steps, config.num_timesteps)
        meta = json.loads((path / "meta.json").read_text(encoding="utf-8"))
        info.update(checkpoint=str(path), step=int(meta["step"]), preset=config.preset, model_kind="pocoloco",
                    model_title="PocoLoco", num_parameters=int(sum(p.numel() for p in model.parameters())),
                    deterministic=False)  # fmt: skip
        _check_normalisation(normalisation, card, path, data)
    nearest_frame = (NearestFrameBaseline(data, subjects, align=settings.nearest_align)
                     if "nearest_frame" in settings.baselines else None)  # fmt: skip
    faces: dict[str, np.ndarray] = {}
    mean_cache = None
    if peer is not None:
        from pocoloco.peers import _MeanShapeCache, peer_pose_from_frame, predict_peer

        mean_cache = _MeanShapeCache()

    result = EvalResult(info)
    examples: list[dict[str, Any]] = []
    example_ids = set(select_frames(chosen, keep_examples)) if keep_examples > 0 else set()
    for n_done, (subject, sequence, path) in enumerate(chosen):
        fr = fmt.read_frame(path, ["points", "normals", "labels", "joints", "frame_index", "body_vertices", "vtransf"],
                            allow_missing=True)  # fmt: skip
        key = f"{subject}/{settings.split}/{sequence}/{fr.frame_index:06d}"
        gsel = _subset(fr.num_points, settings.num_points, (0, n_done))
        gt, gt_n = fr.points[gsel].astype(np.float64), fr.normals[gsel].astype(np.float64)
        gt_lab = None if fr.labels is None else fr.labels[gsel]
        row: dict[str, Any] = {"key": key, "subject": subject}
        clouds: dict[str, Any] = {"gt": (gt, gt_lab)}

        def score(points, normals):
            return evaluate_frame(points, normals, gt, gt_n, gt_lab)

        if model is not None:
            from pocoloco.sample import sample_clouds

            t0 = time.perf_counter()
            sampled = sample_clouds(model, normalisation, config, fr.joints, len(settings.seeds), settings.num_points,
                                    sampler=settings.sampler, steps=settings.steps, seeds=list(settings.seeds),
                                    batch_size=settings.batch_size, clip=settings.clip, bf16=settings.bf16)  # fmt: skip
            per_sample = (time.perf_counter() - t0) / len(settings.seeds)
            scores = [score(sampled.points[k], None if sampled.normals is None else sampled.normals[k])
                      for k in range(len(settings.seeds))]  # fmt: skip
            m = summarise(scores)
            m.pop("num_frames", None)
            m["seconds_per_sample"] = per_sample
            if len(settings.seeds) >= 2:
                m["diversity_cm"] = diversity_cm(sampled.points)
                if gt_lab is not None:
                    m["diversity_garment_cm"] = diversity_cm(sampled.points, gt, gt_lab, region="garment")
                    m["diversity_body_cm"] = diversity_cm(sampled.points, gt, gt_lab, region="body")
            row["model"] = m
            clouds["model"] = sampled.points
        if peer is not None:
            pose = peer_pose_from_frame(path, subject, peer.needs_mean_shape, cache=mean_cache, frame=fr)
            t0 = time.perf_counter()
            pred = predict_peer(peer, pose, peer.outfit_id(subject), settings.num_points, seed=settings.seeds[0])
            m = score(pred.points[0], pred.normals[0])
            m["seconds_per_sample"] = time.perf_counter() - t0
            # deterministic: every seed gives the same cloud, so the diversity is exactly 0
            m["diversity_cm"] = 0.0
            if gt_lab is not None:
                m["diversity_garment_cm"] = m["diversity_body_cm"] = 0.0
            row["model"] = m
            clouds["model"] = pred.points
        if nearest_frame is not None:
            pred = nearest_frame.predict(fr.joints, settings.num_points, (1, n_done), subject=subject)
            row["nearest_frame"] = {**score(pred["points"], pred["normals"]), "pose_rms_cm": 100 * pred["pose_rms_m"],
                                    "yaw_deg": pred["yaw_deg"]}  # fmt: skip
            row["nearest_frame_source"] = pred["source"]
            clouds["nearest_frame"] = (pred["points"], pred["labels"])
        if "posed_body" in settings.baselines:
            if fr.body_vertices is None:
                raise ValueError(f"{path}: no body_vertices (imported data?): drop the posed_body baseline")
            if subject not in faces:
                faces[subject] = fmt.read_subject(layout.subject_path(subject)).faces
            pred = _posed_body(fr, faces[subject], settings.num_points, seed=n_done)
            row["posed_body"] = score(pred["points"], pred["normals"])
            clouds["posed_body"] = (pred["points"], np.zeros(settings.num_points, np.uint8))
        if "gt_resample" in settings.baselines:
            other = _subset(fr.num_points, settings.num_points, (2, n_done))
            row["gt_resample"] = score(fr.points[other], fr.normals[other])
        result.frames.append(row)
        if n_done in example_ids:
            examples.append({"key": key, **clouds})
        if progress is not None:
            progress(n_done + 1, len(chosen))

    methods = [m for m in METHODS if any(m in r for r in result.frames)]
    result.means = {m: _mean(result.frames, m) for m in methods}
    for subject in sorted({r["subject"] for r in result.frames}):
        rows = [r for r in result.frames if r["subject"] == subject]
        result.per_subject[subject] = {m: _mean(rows, m) for m in methods}
    return result, examples


def _mean(rows: list[dict[str, Any]], method: str) -> dict[str, float]:
    out = summarise([r[method] for r in rows if method in r])
    return out


def _settings_dict(s: EvalSettings) -> dict[str, Any]:
    return {"split": s.split, "num_frames": s.num_frames, "num_points": s.num_points, "seeds": list(s.seeds),
            "sampler": s.sampler, "steps": s.steps, "baselines": list(s.baselines),
            "subjects": None if s.subjects is None else list(s.subjects), "weights": "ema" if s.use_ema else "raw",
            "clip": s.clip}  # fmt: skip


def _check_normalisation(normalisation, card: dict[str, Any], ckpt: Path, data) -> None:
    """Warn-free check that the model was trained in the same units as this dataset (metres, similar scale)."""
    from pocoloco.data.dataset import Normalisation

    here = Normalisation.from_card(card)
    ratio = float(np.max(np.atleast_1d(normalisation.std))) / float(np.max(np.atleast_1d(here.std)))
    if not 0.2 < ratio < 5.0:
        raise ValueError(f"{ckpt}: trained on data with scale {normalisation.std} but {data} has {here.std} "
                         "(another unit?)")  # fmt: skip


# -------------------------------------------------------------------------------------- output
def _fmt(value: Any, pattern: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return pattern.format(value)


def method_titles(settings: dict[str, Any]) -> dict[str, str]:
    """``METHOD_TITLES`` with the "model" row named after the evaluated checkpoint's kind."""
    titles = dict(METHOD_TITLES)
    if settings.get("model_title"):
        titles["model"] = f"{settings['model_title']} (this checkpoint)"
    return titles


def markdown_table(means: dict[str, dict[str, float]], titles: dict[str, str] | None = None,
                   columns: Sequence[tuple[str, str, str]] = TABLE_COLUMNS, first: str = "method") -> str:
    """One markdown table: a row per method, the ``columns`` (key, header, format) present in any
    row; ``first`` heads the column of row titles."""
    titles = METHOD_TITLES if titles is None else titles
    cols = [c for c in columns if any(c[0] in m for m in means.values())]
    lines = [f"| {first} | " + " | ".join(h for _, h, _ in cols) + " |", "|---|" + "---|" * len(cols)]
    for method, m in means.items():
        cells = [_fmt(m.get(k), f) for k, _, f in cols]
        lines.append(f"| {titles.get(method, method)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def markdown_tables(result: EvalResult) -> str:
    """The whole ``eval.md``: settings, the mean table, one table per subject."""
    s = result.settings
    titles = method_titles(s)
    head = [f"# pocoloco eval — {s.get('checkpoint', 'baselines only')}", ""]
    if "step" in s:
        head.append(f"{s.get('model_title', 'PocoLoco')} checkpoint step {s['step']}, preset `{s['preset']}`, "
                    f"{s['num_parameters']:,} parameters" + (", deterministic: one cloud per frame (its seeds only "
                    "pick the query points), diversity 0." if s.get("deterministic") else f", {s['weights']} weights."))  # fmt: skip
    n = len(result.frames)
    head.append(f"Data `{s['data']}`, split `{s['split']}`: {n} frames, {s['num_points']} points per cloud "
                f"(GT subsampled to the same N), model samples: {len(s['seeds'])} seeds {s['seeds']} with "
                f"{s['sampler']} ({s['steps'] or 'default'} steps), metrics averaged over seeds and frames.")  # fmt: skip
    head += ["", "Chamfer = S2M + M2S (unsquared, cm; PocoLoco Table 2). CD 1e-4 m^2 = POP convention (squared, "
             "point-to-plane M2S). normal = L1 of unit normals x10. loose % = share of points whose nearest GT point is "
             "garment. div. = mean pairwise Chamfer among the seeds' samples (whole / garment region / body region).",
             "", "## All frames", "", markdown_table(result.means, titles)]  # fmt: skip
    for subject, means in result.per_subject.items():
        head += ["", f"## {subject}", "", markdown_table(means, titles)]
    return "\n".join(head) + "\n"


def write_outputs(out: str | os.PathLike, result: EvalResult, examples: list[dict[str, Any]]) -> Path:
    """eval.json, eval.md, chamfer_per_frame.png, examples.png in ``out`` (each written atomically)."""
    from pocoloco.render import plot_curves, render_grid
    from pocoloco.utils.atomic import jsonable, write_json_atomic, write_text_atomic

    out = output_folder(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "eval.json", jsonable(result.to_dict()))
    write_text_atomic(out / "eval.md", markdown_tables(result))
    curves = {}
    for method in result.means:
        ys = [r[method]["chamfer_cm"] for r in result.frames if method in r]
        curves[method_titles(result.settings).get(method, method)] = (list(range(len(ys))), ys)
    plot_curves(curves, out / "chamfer_per_frame.png", logy=False, title="Chamfer (cm) per test frame",
                xlabel="evaluated frame", ylabel="Chamfer cm")  # fmt: skip
    panels = []
    for ex in examples:
        gt, lab = ex["gt"]
        panels.append((gt, lab, None, f"GT {ex['key'].split('/')[0]}"))
        for method in ("nearest_frame", "posed_body"):
            if method in ex:
                panels.append((*ex[method], None, method.replace("_", " ")))
        if "model" in ex:
            for k, pts in enumerate(ex["model"][:3]):  # coloured by the label of the nearest GT point
                plab = None if lab is None else lab[nearest(pts, gt)[1]]
                panels.append((pts, plab, None, f"sample {k}"))
    if panels:
        per_row = len(panels) // max(len(examples), 1)
        render_grid(panels, out / "examples.png", views=("front",), ncols=max(per_row, 1))
    return out


# -------------------------------------------------------------------------------------- the CLI
def add_nearest_align_argument(parser: argparse.ArgumentParser) -> None:
    """``--nearest-align root|yaw`` (shared by ``eval`` and ``bench quality``)."""
    parser.add_argument("--nearest-align", choices=NEAREST_ALIGNS, default="root",
                        help="nearest-frame baseline: compare poses after moving the roots together (root, default) "
                             "or also turning about the vertical axis (yaw)")  # fmt: skip


def add_eval_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``pocoloco eval`` options (handler: :func:`cmd_eval`)."""
    parser.add_argument("--ckpt", help="checkpoint / run folder; 'default' = the model shipped with pocoloco; "
                                       "omit with --baselines-only")  # fmt: skip
    parser.add_argument("--data", required=True, help="pocoloco dataset folder")
    parser.add_argument("--split", default="test", help="split to evaluate (default test)")
    parser.add_argument("--frames", type=int, default=24, help="frames evenly spaced over the split (0 = all; default 24)")
    parser.add_argument("--points", type=int, default=10_000, help="points per cloud (default 10000, as the paper)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="one sample per seed (default 0 1 2)")
    parser.add_argument("--sampler", default="dpm++sde", help="dpm++sde, ddpm, dpm++ or ddim (default dpm++sde, 25 steps)")
    parser.add_argument("--steps", type=int, help="sampler steps (default: dpm++sde 25, ddpm 100, dpm++ 20, ddim 50)")
    parser.add_argument("--subjects", nargs="+", help="only these subjects")
    parser.add_argument("--no-baselines", action="store_true", help="skip the nearest-frame / posed-body / GT rows")
    parser.add_argument("--baselines-only", action="store_true", help="no model: only the baselines")
    add_nearest_align_argument(parser)
    parser.add_argument("--batch-size", type=int, default=4, help="clouds sampled together (default 4)")
    parser.add_argument("--raw-weights", action="store_true", help="use the raw weights instead of the EMA")
    parser.add_argument("--clip", type=float, default=5.0,
                        help="clamp the sampler's x0 estimates, normalised units (default 5; 0 = off; see pocoloco sample)")  # fmt: skip
    parser.add_argument("--bf16", action="store_true", help="denoiser under bf16 autocast (see pocoloco sample --bf16)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1 (default cpu)")
    parser.add_argument("--out", required=True, help="output folder (eval.json, eval.md, plots)")


def cmd_eval(args: argparse.Namespace) -> None:
    """``pocoloco eval``: everything is validated (one-line errors) before the first sample."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from pocoloco.data import format as fmt

    if args.ckpt is None and not args.baselines_only:
        raise ValueError("--ckpt is required (or --baselines-only)")
    if args.ckpt is not None and args.baselines_only:
        raise ValueError("--ckpt and --baselines-only exclude each other")
    if args.no_baselines and args.baselines_only:
        raise ValueError("--no-baselines and --baselines-only exclude each other")
    if args.steps is not None and args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    settings = EvalSettings(split=args.split, num_frames=args.frames, num_points=args.points, seeds=tuple(args.seeds),
                            sampler=args.sampler, steps=args.steps,
                            baselines=() if args.no_baselines else EvalSettings.baselines,
                            subjects=tuple(args.subjects) if args.subjects else None, batch_size=args.batch_size,
                            use_ema=not args.raw_weights, clip=args.clip or None, bf16=args.bf16,
                            nearest_align=args.nearest_align)  # fmt: skip
    from pocoloco.sample import SAMPLERS

    if settings.sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {settings.sampler!r}; choose one of: {', '.join(SAMPLERS)}")
    if settings.split not in fmt.SPLITS:
        raise ValueError(f"unknown split {settings.split!r}; expected one of {fmt.SPLITS}")
    fmt.read_card(args.data)
    out = output_folder(args.out)
    ckpt = args.ckpt
    if ckpt == "default":
        from pocoloco.pretrained import default_checkpoint

        ckpt = default_checkpoint()

    with Progress(TextColumn("eval"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  transient=True) as bar:  # fmt: skip
        task = bar.add_task("frames", total=None)
        result, examples = evaluate(ckpt, args.data, settings, device=args.device,
                                    progress=lambda d, n: bar.update(task, completed=d, total=n))  # fmt: skip
    write_outputs(out, result, examples)
    print(markdown_table(result.means, method_titles(result.settings)))
    print(f"wrote {out / 'eval.json'}, {out / 'eval.md'}, {out / 'chamfer_per_frame.png'}, {out / 'examples.png'}")
