"""Evaluation (``pocoloco eval``): a trained model of any method and two baselines scored on the test
frames of a dataset.

For every evaluated test frame (joints K, ground-truth scan G with normals and labels):

* **model**: S clouds of N points for K (one per seed, :meth:`pocoloco.methods.Method.predict`; a
  deterministic method gives one cloud);
  each is scored against G (:func:`pocoloco.evaluation.metrics.evaluate_frame`) and the S scores are
  averaged, as the PocoLoco paper averages its metrics over several samples. Diversity is the
  mean pairwise Chamfer (cm) among the S clouds, over the whole cloud and separately over the
  points in the garment / body region (each point takes the label of its nearest GT point).
  Best of K (min Chamfer over the S = K clouds) and the energy score (mean Chamfer to G minus half
  the mean pairwise Chamfer; :func:`pocoloco.evaluation.metrics.energy_score_cm`) score the set of
  samples as a whole, with K in ``num_samples``; a deterministic model and every baseline have
  K = 1 and best of K = energy score = Chamfer.
* **nearest-frame** baseline: the training frame of the same subject whose root-aligned joints
  are nearest to K (sum of squared joint distances), its scan translated by the root offset.
* **posed-body** baseline: N points sampled uniformly on the frame's posed minimally-clothed
  body (the body the garment was simulated on), with face normals.
* **GT resample** (reference row, the metric's own noise floor): another N-point subset of
  the same scan.

G is an N-point subset of the scan (fixed seed), so every row compares N points with N points.
Metric definitions and units: :mod:`pocoloco.evaluation.metrics` (Chamfer = S2M + M2S in cm, unsquared;
POP CD = squared, point-to-plane M2S, in 1e-4 m^2).

Output folder: ``eval.json`` (settings, per-frame rows, means per method and per subject),
``eval.md`` (the same tables in markdown), ``chamfer_per_frame.png`` (per-frame Chamfer of
every method), ``examples.png`` (GT, baselines and samples for a few frames, coloured by label;
a generated point takes the label of its nearest GT point).
"""

from __future__ import annotations

import math
import os
import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pocoloco.data import format as fmt
from pocoloco.data.dataset import Normalisation
from pocoloco.data.poses import MeanShapeCache
from pocoloco.evaluation.baselines import (
    NEAREST_ALIGNS,
    NearestFrameBaseline,
    posed_body_baseline,
    select_frames,
    subset,
)
from pocoloco.evaluation.metrics import (chamfer_cm, diversity_cm, evaluate_frame, nearest, partly_shared_floor_cm,
                                         shared_fraction, summarise, summarise_samples)
from pocoloco.methods import SamplerOptions, fit_to_memory, load_method, predict_clouds
from pocoloco.utils.atomic import (
    jsonable,
    output_folder,
    write_json_atomic,
    write_text_atomic,
)
from pocoloco.viz.render import plot_curves, render_grid

__all__ = ["EvalResult", "EvalSettings", "GARMENT_COLUMNS", "METHODS", "TABLE_COLUMNS", "evaluate", "markdown_table",
           "markdown_tables", "method_titles", "write_outputs"]  # fmt: skip

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
    ("best_of_k_chamfer_cm", "best-of-K Chamfer", "{:.2f}"),
    ("energy_score_cm", "Chamfer ES (not proper) cm", "{:.2f}"),
    ("energy_score_adj_cm", "Chamfer ES adj. (not proper) cm", "{:.2f}"),
    ("num_samples", "K", "{:.0f}"),
    ("pop_chamfer_e-4m2", "CD 1e-4 m^2", "{:.2f}"),
    ("normal_l1_e-1", "normal 1e-1", "{:.2f}"),
    ("outlier_5cm_pct", ">5cm %", "{:.1f}"),
    ("outlier_10cm_pct", ">10cm %", "{:.1f}"),
    ("outlier_10cm_pct_max", "max >10cm %", "{:.1f}"),
    ("loose_pred_pct", "loose %", "{:.1f}"),
    ("loose_gt_pct", "loose GT %", "{:.1f}"),
    ("diversity_cm", "div. cm", "{:.2f}"),
    ("diversity_garment_cm", "div. garment", "{:.2f}"),
    ("diversity_body_cm", "div. body", "{:.2f}"),
    ("seconds_per_sample", "s/sample", "{:.2f}"),
)
#: columns of the second table (scan split by its labels, F-scores): (key, header, format); the
#: garment columns average over the frames with garment points only (``num_frames_garment``)
GARMENT_COLUMNS = (
    ("s2m_garment_cm", "S2M garment cm", "{:.2f}"),
    ("m2s_garment_cm", "M2S garment cm", "{:.2f}"),
    ("s2m_rest_cm", "S2M rest cm", "{:.2f}"),
    ("m2s_rest_cm", "M2S rest cm", "{:.2f}"),
    ("num_frames_garment", "garment frames", "{:.0f}"),
    ("fscore_1cm_pct", "F@1cm %", "{:.1f}"),
    ("fscore_2cm_pct", "F@2cm %", "{:.1f}"),
    ("precision_2cm_pct", "P@2cm %", "{:.1f}"),
    ("recall_2cm_pct", "R@2cm %", "{:.1f}"),
    ("fscore_garment_1cm_pct", "F garment@1cm %", "{:.1f}"),
    ("fscore_garment_2cm_pct", "F garment@2cm %", "{:.1f}"),
    ("precision_garment_2cm_pct", "P garment@2cm %", "{:.1f}"),
    ("recall_garment_2cm_pct", "R garment@2cm %", "{:.1f}"),
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
    (``NearestFrameBaseline``). outfit: draw every frame in this trained outfit (models with outfit
    codes, e.g. a fitted outfit or the nearest trained one for an unseen subject; None: each
    frame's subject). even: the models' points spread evenly (``SamplerOptions.even``; the GT
    subsets and the baselines stay random). history: the motion window a motion-aware model is
    given (issue 41; pose-only models ignore it): ``dataset`` the frame's own, ``rest`` none (the
    body at rest: the pose-only use of the same model), ``shuffled`` the window of another frame of
    the same subject and split (in another sequence where there is one; fixed per frame), which
    tells the motion's information from the extra capacity. finish_t: the generative models' own
    finishing call (``SamplerOptions.finish_t``; None: off).
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
    outfit: str | None = None
    even: bool = False
    history: str = "dataset"
    finish_t: int | None = None

    def __post_init__(self):
        if self.split not in fmt.SPLITS:
            raise ValueError(f"unknown split {self.split!r}; expected one of {fmt.SPLITS}")
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
        if self.history not in HISTORY_MODES:
            raise ValueError(f"history must be one of {', '.join(HISTORY_MODES)}, got {self.history!r}")
        if self.nearest_align not in NEAREST_ALIGNS:
            raise ValueError(f"nearest_align must be one of {', '.join(NEAREST_ALIGNS)}, got {self.nearest_align!r}")


#: what a motion-aware model is given as the motion before each frame (``EvalSettings.history``)
HISTORY_MODES = ("dataset", "rest", "shuffled")


def shuffled_frame(frames: Sequence[tuple[str, str, Any]], subject: str, sequence: str, key: str):
    """The frame file whose motion window ``--history shuffled`` gives the frame ``key``: a frame of
    the same subject among ``frames`` [(subject, sequence, path)], in another sequence where there is
    one, drawn from a generator seeded by the key (the same on every run)."""
    same = [p for s, q, p in frames if s == subject and q != sequence] or [p for s, _, p in frames if s == subject]
    return same[int(np.random.default_rng(zlib.crc32(key.encode())).integers(len(same)))]


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
    ckpt: str | os.PathLike | Mapping[str, str | os.PathLike] | None,
    data: str | os.PathLike,
    settings: EvalSettings = EvalSettings(),
    *,
    device: str = "cpu",
    progress: Callable[[int, int], None] | None = None,
    keep_examples: int = 3,
) -> tuple[EvalResult, list[dict[str, Any]]]:
    """Score the checkpoint ``ckpt`` (any method; None: baselines only) on ``settings.split`` of the
    dataset at ``data``. ``ckpt`` may also map subject -> checkpoint (one model per subject, as the
    PocoLoco paper trains them): each frame is then sampled by its subject's model, on the same frames
    a single model would see; every evaluated subject needs a model.

    Returns the :class:`EvalResult` and, for up to ``keep_examples`` frames, the clouds (GT,
    baselines, model samples) to render.
    """
    card = fmt.read_card(data)
    layout = fmt.DatasetLayout(data)
    subjects = list(settings.subjects) if settings.subjects else None
    if subjects:
        unknown = [s for s in subjects if s not in card["subjects"]]
        if unknown:
            raise ValueError(f"{data}: unknown subjects {unknown}; the card lists {sorted(card['subjects'])}")
    fmt.check_frames(data, subjects=subjects, card=card)  # a missing or damaged frame: one line, before any work
    all_frames = layout.iter_frames(settings.split, subjects or layout.subjects())
    if not all_frames:
        raise ValueError(f"{data}: no frames in split {settings.split!r}")
    chosen = [all_frames[i] for i in select_frames(all_frames, settings.num_frames)]

    info: dict[str, Any] = {"data": os.fspath(data), **_settings_dict(settings)}
    options = SamplerOptions(sampler=settings.sampler, steps=settings.steps, clip=settings.clip, bf16=settings.bf16,
                             batch_size=settings.batch_size, even=settings.even, finish_t=settings.finish_t)  # fmt: skip
    methods = _load_methods(ckpt, data, card, sorted({s for s, _, _ in chosen}), settings, options, device, info)
    if methods:  # a request larger than free memory: fewer clouds at a time, or one line
        options = fit_to_memory(next(iter(methods.values())), settings.num_points, len(settings.seeds), options)
    method = next(iter(methods.values()), None)  # the one model (or the first of the per-subject ones)
    seeds = list(settings.seeds[:1]) if method is not None and method.deterministic else list(settings.seeds)
    nearest_frame = (NearestFrameBaseline(data, subjects, align=settings.nearest_align)
                     if "nearest_frame" in settings.baselines else None)  # fmt: skip
    faces: dict[str, np.ndarray] = {}
    mean_cache = MeanShapeCache()

    result = EvalResult(info)
    examples: list[dict[str, Any]] = []
    example_ids = set(select_frames(chosen, keep_examples)) if keep_examples > 0 else set()
    for n_done, (subject, sequence, path) in enumerate(chosen):
        fr = fmt.read_frame(path, ["points", "normals", "labels", "joints", "frame_index", "body_vertices", "vtransf"],
                            allow_missing=True)  # fmt: skip
        key = f"{subject}/{settings.split}/{sequence}/{fr.frame_index:06d}"
        gsel = subset(fr.num_points, settings.num_points, (0, n_done))
        gt, gt_n = fr.points[gsel].astype(np.float64), fr.normals[gsel].astype(np.float64)
        gt_lab = None if fr.labels is None else fr.labels[gsel]
        row: dict[str, Any] = {"key": key, "subject": subject}
        clouds: dict[str, Any] = {"gt": (gt, gt_lab)}
        resample = subset(fr.num_points, settings.num_points, (2, n_done))  # the noise floor's second GT subset

        def score(points, normals):
            return evaluate_frame(points, normals, gt, gt_n, gt_lab)

        def single(points, normals):  # one cloud: K = 1, best of K = energy score = Chamfer
            return summarise_samples([score(points, normals)])

        if method is not None:
            method = methods.get(subject, methods.get(None))
            pose = method.pose_from_frame(path, subject, frame=fr, cache=mean_cache)
            if method.motion_window and settings.history != "dataset":
                pose.motion = (None if settings.history == "rest" else
                               method.motion_of_frame(shuffled_frame(all_frames, subject, sequence, key)))  # fmt: skip
            outfit = method.outfit_id(settings.outfit or subject) if method.outfit_names() else None
            t0 = time.perf_counter()
            pred = predict_clouds(method, pose, settings.num_points, seeds, outfit, options)
            per_sample = (time.perf_counter() - t0) / len(seeds)
            normals = [None if pred.normals is None else pred.normals[k] for k in range(len(seeds))]
            if method.deterministic:
                m = single(pred.points[0], normals[0])
                # deterministic: every seed gives the same cloud, so the diversity is exactly 0
                m["seconds_per_sample"] = per_sample
                m["diversity_cm"] = 0.0
                if gt_lab is not None:
                    m["diversity_garment_cm"] = m["diversity_body_cm"] = 0.0
            else:
                div = diversity_cm(pred.points) if len(seeds) >= 2 else None
                # the resampling floor of hypotheses sharing as many points as these do (0: all resampled)
                shared = shared_fraction(pred.points) if len(seeds) >= 2 else 0.0
                floor = partly_shared_floor_cm(gt, fr.points[resample].astype(np.float64), shared, (3, n_done))
                m = summarise_samples([score(pred.points[k], normals[k]) for k in range(len(seeds))], div, floor)
                m["seconds_per_sample"] = per_sample
                m["shared_points_pct"] = 100.0 * shared
                if div is not None:
                    m["diversity_cm"] = div
                    if gt_lab is not None:
                        m["diversity_garment_cm"] = diversity_cm(pred.points, gt, gt_lab, region="garment")
                        m["diversity_body_cm"] = diversity_cm(pred.points, gt, gt_lab, region="body")
            row["model"] = m
            clouds["model"] = pred.points
        if nearest_frame is not None:
            pred = nearest_frame.predict(fr.joints, settings.num_points, (1, n_done), subject=subject)
            row["nearest_frame"] = {**single(pred["points"], pred["normals"]), "pose_rms_cm": 100 * pred["pose_rms_m"],
                                    "yaw_deg": pred["yaw_deg"]}  # fmt: skip
            row["nearest_frame_source"] = pred["source"]
            clouds["nearest_frame"] = (pred["points"], pred["labels"])
        if "posed_body" in settings.baselines:
            if fr.body_vertices is None:
                raise ValueError(f"{path}: no body_vertices (imported data?): drop the posed_body baseline")
            if subject not in faces:
                faces[subject] = fmt.read_subject(layout.subject_path(subject)).faces
            pred = posed_body_baseline(fr, faces[subject], settings.num_points, seed=n_done)
            row["posed_body"] = single(pred["points"], pred["normals"])
            clouds["posed_body"] = (pred["points"], np.zeros(settings.num_points, np.uint8))
        if "gt_resample" in settings.baselines:
            row["gt_resample"] = single(fr.points[resample], fr.normals[resample])
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


def _load_methods(ckpt, data, card: dict[str, Any], subjects: list[str], settings: EvalSettings,
                  options: SamplerOptions, device: str, info: dict[str, Any]) -> dict[str | None, Any]:  # fmt: skip
    """{None: the method} for one checkpoint, {subject: its method} for per-subject checkpoints, {}
    for none; every check (sampler options, trained outfits / subjects, normalisation) before any
    work, and the checkpoint facts added to ``info``."""
    if ckpt is None:
        return {}
    per_subject = isinstance(ckpt, Mapping)
    given = dict(ckpt) if per_subject else {None: ckpt}
    if per_subject:
        missing = [s for s in subjects if s not in given]
        if missing:
            raise ValueError(f"no per-subject model for subjects {missing}: give one for each, or evaluate only "
                             f"{sorted(given)} (--subjects)")  # fmt: skip
    methods: dict[str | None, Any] = {}
    for subject, path in given.items():
        if per_subject and subject not in subjects:
            continue
        method = load_method(path, device=device, use_ema=settings.use_ema)
        method.check_options(options)
        trained = getattr(method.config, "subjects", None)
        if per_subject and trained and subject not in trained:
            raise ValueError(f"{method.path}: the model for {subject!r} was trained on {list(trained)} only")
        if method.outfit_names():  # one-line error before any work if a subject was never trained
            for s in [settings.outfit] if settings.outfit else ([subject] if per_subject else subjects):
                method.outfit_id(s)
        elif settings.outfit:
            raise ValueError(f"--outfit {settings.outfit}: {method.path} has no outfits (a joints-only model)")
        _check_normalisation(method.normalisation, card, method.path, data)
        methods[subject] = method
    first = next(iter(methods.values()))
    info.update(first.info())
    if per_subject:
        info["checkpoint"] = {s: str(m.path) for s, m in methods.items()}
        info["step"] = {s: m.step for s, m in methods.items()}
        info["num_parameters"] = sum(m.num_parameters for m in methods.values())
        info["per_subject_models"] = True
    return methods


def _mean(rows: list[dict[str, Any]], method: str) -> dict[str, float]:
    out = summarise([r[method] for r in rows if method in r])
    return out


def _settings_dict(s: EvalSettings) -> dict[str, Any]:
    return {"split": s.split, "num_frames": s.num_frames, "num_points": s.num_points, "seeds": list(s.seeds),
            "sampler": s.sampler, "steps": s.steps, "baselines": list(s.baselines),
            "subjects": None if s.subjects is None else list(s.subjects), "weights": "ema" if s.use_ema else "raw",
            "clip": s.clip, "outfit": s.outfit, "even": s.even, "history": s.history}  # fmt: skip


def _check_normalisation(normalisation, card: dict[str, Any], ckpt: Path, data) -> None:
    """Warn-free check that the model was trained in the same units as this dataset (metres, similar scale)."""
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
    """The whole ``eval.md``: settings, the mean tables, the same per subject."""
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
                f"{s['sampler']} ({s['steps'] or 'default'} steps), metrics averaged over seeds and frames."
                + (" Model points evenly spread (`--even`)." if s.get("even") else ""))  # fmt: skip
    head += ["", "Chamfer = S2M + M2S (unsquared, cm; PocoLoco Table 2). CD 1e-4 m^2 = POP convention (squared, "
             "point-to-plane M2S). normal = L1 of unit normals x10. >5cm / >10cm % = share of generated points farther "
             "than that from every GT point (mean; max = the worst cloud). loose % = share of points whose nearest GT point is "
             "garment. div. = mean pairwise Chamfer among the seeds' samples (whole / garment region / body region).",
             "", FAIR_NOTE, "", "## All frames", "", *_tables(result.means, titles)]  # fmt: skip
    for subject, means in result.per_subject.items():
        head += ["", f"## {subject}", "", *_tables(means, titles)]
    return "\n".join(head) + "\n"


#: what the columns fair to a generative model mean (eval.md and quality.md)
FAIR_NOTE = ("best-of-K Chamfer = the smallest Chamfer among the K samples of a frame (K = samples per frame: one per "
             "seed for a generative model, 1 for a deterministic model and the baselines). ES = energy score (Gneiting & "
             "Raftery 2007) with d = Chamfer, which is NOT a proper score (Chamfer is not conditionally negative definite: "
             "two 1-D forecasts beat the truth itself, pocoloco.evaluation.distribution.chamfer_energy_counterexamples; "
             "the proper one is the energy score of a fixed embedding, pocoloco.evaluation.distribution): mean Chamfer of the K samples to the scan minus half their mean pairwise "
             "Chamfer, = Chamfer for K = 1. Mean Chamfer over samples charges a calibrated sampler an extra spread term that "
             "a regressor's conditional mean does not pay; ES subtracts it; lower is better. Between finite point sets the "
             "pairwise term also holds the point-resampling noise (the GT-resample Chamfer), which flatters a sampler: "
             "ES adj. adds half of that per-frame floor back (= ES for K = 1; for hypotheses that share points, as the "
             "hybrid's do, the floor of two resamples sharing as many) and is the column that ranks both kinds. "
             "Second table: the scan split by its labels, S2M over the GT garment (rest) points, M2S over the predicted "
             "points whose nearest GT point is garment (rest); garment columns average over the garment frames only "
             "(tight subjects have none). F / P / R = F-score / precision / recall (%) at 1 and 2 cm, overall and on "
             "the garment (precision over the predicted points labelled garment, recall over the GT garment points).")  # fmt: skip


def _tables(means: dict[str, dict[str, float]], titles: dict[str, str], columns=TABLE_COLUMNS,
            first: str = "method") -> list[str]:  # fmt: skip
    """The main table and, when any row has its keys (not in old JSONs), the garment / F-score table."""
    out = [markdown_table(means, titles, columns, first)]
    if any(k in m for k, _, _ in GARMENT_COLUMNS for m in means.values()):
        out += ["", markdown_table(means, titles, GARMENT_COLUMNS, first)]
    return out


def write_outputs(out: str | os.PathLike, result: EvalResult, examples: list[dict[str, Any]]) -> Path:
    """eval.json, eval.md, chamfer_per_frame.png, examples.png in ``out`` (each written atomically)."""
    out = output_folder(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "eval.json", jsonable(result.to_dict()), indent=None)  # per-frame rows: compact
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
