"""POP and CloSET in the shared harness: training, checkpoints, prediction, unseen-outfit fitting.

The peers (:mod:`pocoloco.models.pop`, :mod:`pocoloco.models.closet`) are trained, checkpointed,
sampled and evaluated through the same commands as PocoLoco (``pocoloco train|sample|eval
--model pop|closet``); this module holds their per-model pieces and reuses the harness's:
run folder, :class:`pocoloco.train._Logger` (``metrics.jsonl`` + ``loss.png``), the rich progress
bar, the batch order of :class:`pocoloco.train.StepBatches` and the atomic checkpoints of
:mod:`pocoloco.checkpoint` (``model_kind`` "pop" / "closet").

Data. One outfit per subject of the dataset (ids in sorted subject order; stored in the
checkpoint's ``meta.json`` under ``outfits`` with each subject's anny phenotype). A frame gives
the posed body (``body_vertices`` (V, 3), ``vtransf`` (V, 3, 3)), the joints (root = joints[0]:
both peers work pelvis-centred) and the scan (``points`` / ``normals``, ``num_points`` drawn per
frame). POP's pose encoder sees the posed *mean-shape* anny body (paper Sec. 3.2), posed with
the sequence's ``motion.npz`` (presets ``small`` / ``paper``; ``tiny`` feeds the subject's own
body so tests need no anny). CloSET's pose encoder runs over one T-pose template: with several
subjects of one topology, the mean of their bind-pose templates (the paper has one subject per
model; this is our multi-subject choice).

Everything random in a step is a pure function of (seed, step): the frames (``StepBatches``
order), the scan-point subsets (``default_rng([seed, 1, position])``) and CloSET's query points
on the template (seed ``(seed, 4, step)``); the model is initialised from ``torch.manual_seed(seed)``.
So ``--resume`` (weights incl. BatchNorm statistics, Adam state, RNG states) continues exactly.

Losses and schedule. POP: paper Eq. 3 (:func:`pocoloco.models.pop.pop_losses`), Adam 3e-4 for the
network and 5e-4 for the geometric features, batch 4, constant lr; the normal term is switched on
at 62.5 % of the run (the paper's epoch 250 of 400), ``normal_start``. CloSET: Eqs. 4-6
(:func:`pocoloco.models.closet.closet_loss`) with the same rates and the same normal schedule.
No EMA (neither paper uses one); the checkpoint's weights are the trained ones.

Prediction (``pocoloco sample`` / ``eval``; one deterministic cloud per pose and outfit):

* POP: its query points are the valid pixels of the UV query map; to give N points it uses the
  training map (resolution Rq) if it has >= N valid pixels, else the smallest finer map that does
  (POP's decoder takes any UV), and keeps N of them drawn without replacement (seeded).
* CloSET: N points drawn area-uniformly on the template surface (body faces; seeded): its
  features live on the continuous surface, so any N is queried directly.

Unseen outfit (POP, paper Sec. 3.3 / Eq. 7): :func:`fit_outfit` optimises only a new geometric
feature tensor against one scan and writes a new checkpoint with the outfit added.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pocoloco import checkpoint as ckpt_io
from pocoloco.data.dataset import Normalisation
from pocoloco.utils.atomic import output_folder

__all__ = [
    "PEER_KINDS",
    "PEER_PRESETS",
    "LoadedPeer",
    "PeerPose",
    "PeerTrainConfig",
    "add_fit_arguments",
    "checkpoint_kind",
    "cmd_fit",
    "cmd_sample_peer",
    "cmd_train_peer",
    "fit_outfit",
    "load_peer",
    "peer_pose_from_frame",
    "peer_preset",
    "predict_peer",
    "train_peer",
]

PEER_KINDS = ("pop", "closet")
#: PeerTrainConfig fields that may change when resuming (they do not affect the optimisation)
RESUMABLE_CHANGES = frozenset({"steps", "ckpt_every", "sample_every", "log_every", "keep_checkpoints"})
#: the paper switches POP's normal loss on at epoch 250 of 400
NORMAL_START_FRACTION = 250 / 400
#: fewest scan points ``pocoloco fit`` accepts
MIN_SCAN_POINTS = 256


# ------------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class PeerTrainConfig:
    """A POP or CloSET training run (the data folder and the device excepted).

    model: "pop" or "closet". preset: the preset name. net: the network config as a dict
    (``POPConfig.to_dict()`` / ``CloSETConfig.to_dict()``). steps: optimiser steps. batch_size:
    frames per step. num_points: scan points drawn per frame (the loss's ground truth).
    query_points: CloSET's surface points per training step (POP uses its UV query map).
    lr / lr_codes: Adam rates of the networks and of the auto-decoded outfit codes (POP's
    geometric features, CloSET's garment codes). normal_start: first step with the normal loss.
    closet_weights: ``CloSETLossWeights`` as a dict (CloSET only). subjects: train on these
    subjects only (one outfit each; None = all), e.g. to hold one out for ``pocoloco fit``.
    seed: everything random.
    ckpt_every / sample_every / log_every: periods in steps (0 disables checkpoints / renders).
    keep_checkpoints: step folders kept.
    """

    model: str = "pop"
    preset: str = "small"
    net: dict[str, Any] = field(default_factory=dict)
    steps: int = 10_000
    batch_size: int = 4
    num_points: int = 8192
    query_points: int = 8192
    lr: float = 3e-4
    lr_codes: float = 5e-4
    normal_start: int = 6250
    closet_weights: dict[str, float] = field(default_factory=dict)
    subjects: list[str] | None = None
    seed: int = 0
    ckpt_every: int = 250
    sample_every: int = 1000
    log_every: int = 10
    keep_checkpoints: int = 3

    def __post_init__(self):
        if self.model not in PEER_KINDS:
            raise ValueError(f"unknown peer model {self.model!r}; choose one of: {', '.join(PEER_KINDS)}")
        for name in ("steps", "batch_size", "num_points", "query_points", "log_every", "keep_checkpoints"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        for name in ("normal_start", "ckpt_every", "sample_every"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("lr", "lr_codes"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive number, got {v}")
        if self.subjects is not None:
            if not self.subjects or len(set(self.subjects)) != len(self.subjects):
                raise ValueError(f"subjects must be distinct names, got {self.subjects!r}")
            object.__setattr__(self, "subjects", sorted(str(x) for x in self.subjects))
        if self.model == "pop":
            from pocoloco.models.pop import POPConfig

            net = POPConfig.from_dict(self.net).to_dict() if self.net else POPConfig().to_dict()
            # the POP config's own training fields follow the run's (one source of truth)
            net.update(lr=self.lr, lr_features=self.lr_codes, batch_size=self.batch_size,
                       num_scan_points=self.num_points, normal_start=self.normal_start)  # fmt: skip
            POPConfig.from_dict(net)  # validate
            object.__setattr__(self, "closet_weights", {})
        else:
            from pocoloco.models.closet import CloSETConfig, CloSETLossWeights, closet_preset

            net = CloSETConfig.from_dict(self.net).to_dict() if self.net else closet_preset("paper").to_dict()
            w = dataclasses.asdict(CloSETLossWeights(**self.closet_weights))
            object.__setattr__(self, "closet_weights", w)
        object.__setattr__(self, "net", json.loads(json.dumps(net)))  # plain JSON types (tuples -> lists)

    def net_config(self):
        """The ``POPConfig`` or ``CloSETConfig``."""
        if self.model == "pop":
            from pocoloco.models.pop import POPConfig

            return POPConfig.from_dict(self.net)
        from pocoloco.models.closet import CloSETConfig

        return CloSETConfig.from_dict(self.net)

    def replace(self, **changes) -> PeerTrainConfig:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PeerTrainConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown PeerTrainConfig fields {unknown}")
        return cls(**d)


def _presets() -> dict[tuple[str, str], PeerTrainConfig]:
    from pocoloco.models.closet import CLOSET_PRESETS
    from pocoloco.models.pop import POP_PRESETS

    def pop(name: str, **kw) -> dict[str, Any]:
        return dataclasses.replace(POP_PRESETS[name], **kw).to_dict()

    return {
        # POP paper: 128^2 input, 256^2 query map, batch 4, 40K scan points, Adam 3e-4 / 5e-4
        ("pop", "paper"): PeerTrainConfig(model="pop", preset="paper", net=pop("paper"), steps=100_000, batch_size=4,
                                          num_points=40_000, normal_start=62_500, ckpt_every=2000, sample_every=5000,
                                          log_every=50),
        # CPU: POP's small network with a 64^2 query map (~2.5K points per frame at training; any
        # number at test time from finer maps) so a step takes about a second on one core
        ("pop", "small"): PeerTrainConfig(model="pop", preset="small", net=pop("small", query_resolution=64),
                                          steps=10_000, batch_size=4, num_points=4096, normal_start=6250),
        # tests: the UNet sees the subject's own body (no anny needed)
        ("pop", "tiny"): PeerTrainConfig(model="pop", preset="tiny", net=pop("tiny", pose_input="subject"), steps=20,
                                         batch_size=2, num_points=512, normal_start=10, lr=1e-3, lr_codes=1e-3,
                                         ckpt_every=10, sample_every=0, log_every=1),
        ("closet", "paper"): PeerTrainConfig(model="closet", preset="paper", net=CLOSET_PRESETS["paper"].to_dict(),
                                             steps=100_000, batch_size=4, num_points=40_000, query_points=40_000,
                                             normal_start=62_500, ckpt_every=2000, sample_every=5000, log_every=50),
        # CPU: as many query points per frame as POP's small preset
        ("closet", "small"): PeerTrainConfig(model="closet", preset="small", net=CLOSET_PRESETS["small"].to_dict(),
                                             steps=10_000, batch_size=4, num_points=4096, query_points=2560,
                                             normal_start=6250),
        ("closet", "tiny"): PeerTrainConfig(model="closet", preset="tiny", net=CLOSET_PRESETS["tiny"].to_dict(),
                                            steps=20, batch_size=2, num_points=512, query_points=512, normal_start=10,
                                            lr=1e-3, lr_codes=1e-3, ckpt_every=10, sample_every=0, log_every=1),
    }  # fmt: skip


PEER_PRESETS: dict[tuple[str, str], PeerTrainConfig] = _presets()


def peer_preset(model: str, name: str, decomposition: bool | None = None, **overrides) -> PeerTrainConfig:
    """The preset ``name`` of ``model`` with field overrides. Changing ``steps`` without giving
    ``normal_start`` moves the normal-loss switch to the same fraction (62.5 %) of the new run.
    ``decomposition=False``: CloSET's single-decoder ablation."""
    if model not in PEER_KINDS:
        raise ValueError(f"unknown peer model {model!r}; choose one of: {', '.join(PEER_KINDS)}")
    names = sorted({n for m, n in PEER_PRESETS if m == model})
    if (model, name) not in PEER_PRESETS:
        raise ValueError(f"unknown training preset {name!r} for {model}; choose one of: {', '.join(names)}")
    base = PEER_PRESETS[(model, name)]
    if "steps" in overrides and "normal_start" not in overrides:
        overrides["normal_start"] = int(round(NORMAL_START_FRACTION * overrides["steps"]))
    if decomposition is not None:
        if model != "closet":
            raise ValueError("--no-decomposition applies to --model closet only")
        overrides["net"] = {**base.net, "decomposition": bool(decomposition)}
    return base.replace(**overrides)


def model_title(kind: str, config: dict[str, Any] | None = None) -> str:
    """Display name: PocoLoco, POP, CloSET or CloSET (no decomposition)."""
    if kind == "closet" and config is not None and not config.get("net", {}).get("decomposition", True):
        return "CloSET (no decomposition)"
    return {"pocoloco": "PocoLoco", "pop": "POP", "closet": "CloSET"}.get(kind, kind)


# ------------------------------------------------------------------------------------ bodies
@dataclass
class PeerPose:
    """One posed body (numpy float32, metres, world frame).

    body_vertices (V, 3) the subject's posed body; vtransf (V, 3, 3) per-vertex skinning
    transforms; joints (24, 3) (joints[0] = the root both peers centre on); mean_shape (V, 3)
    the posed mean-shape body centred on its own root (POP's pose input) or None; subject: the
    dataset subject the body belongs to (None for an anny pose file); source: where it came from.
    """

    body_vertices: np.ndarray
    vtransf: np.ndarray
    joints: np.ndarray
    mean_shape: np.ndarray | None = None
    subject: str | None = None
    source: str = ""


class _MeanShapeCache:
    """Posed mean-shape bodies (T, V, 3), centred on their root, per ``motion.npz`` (anny, cached)."""

    def __init__(self):
        self._cache: dict[str, np.ndarray] = {}

    def get(self, motion_path: Path, frame_index: int, whole_sequence: bool = True) -> np.ndarray:
        from pocoloco.body.surface import pose_mean_shape_vertices
        from pocoloco.data.format import read_motion

        key = os.fspath(motion_path)
        if key not in self._cache:
            m = read_motion(motion_path)
            if frame_index >= len(m.joint_rotvecs):
                raise ValueError(f"{motion_path}: frame {frame_index} is beyond the motion ({len(m.joint_rotvecs)} frames)")
            if not whole_sequence:
                return pose_mean_shape_vertices(m.joint_rotvecs[frame_index : frame_index + 1])[0]
            self._cache[key] = pose_mean_shape_vertices(m.joint_rotvecs)
        verts = self._cache[key]
        if frame_index >= len(verts):
            raise ValueError(f"{motion_path}: frame {frame_index} is beyond the motion ({len(verts)} frames)")
        return verts[frame_index]


def _motion_path_of(frame_path: Path) -> Path:
    """``.../<sequence>/frames/000123.npz`` -> ``.../<sequence>/motion.npz``."""
    return Path(frame_path).parent.parent / "motion.npz"


def peer_pose_from_frame(frame_path: str | os.PathLike, subject: str | None, need_mean_shape: bool,
                         cache: _MeanShapeCache | None = None, frame=None) -> PeerPose:  # fmt: skip
    """The posed body of a dataset frame file (and, if needed, the mean shape in its pose)."""
    from pocoloco.data.format import read_frame

    path = Path(frame_path)
    fr = frame if frame is not None else read_frame(path, ["joints", "frame_index", "body_vertices", "vtransf"],
                                                    allow_missing=True)  # fmt: skip
    if fr.body_vertices is None or fr.vtransf is None:
        raise ValueError(f"{path}: frame has no posed body (body_vertices / vtransf); POP and CloSET need it")
    mean = None
    if need_mean_shape:
        mean = (cache or _MeanShapeCache()).get(_motion_path_of(path), int(fr.frame_index), whole_sequence=cache is not None)
    return PeerPose(np.asarray(fr.body_vertices, np.float32), np.asarray(fr.vtransf, np.float32),
                    np.asarray(fr.joints, np.float32), mean, subject, os.fspath(path))  # fmt: skip


def peer_pose_from_anny_file(path: str | os.PathLike, phenotype: dict[str, float], need_mean_shape: bool) -> PeerPose:
    """An ``.npz`` with ``joint_rotvecs`` (24, 3) anny axis-angle rotations (as in ``motion.npz``;
    optional ``root_translation`` (3,)) -> the body of ``phenotype`` in that pose."""
    from pocoloco.body.anny_body import AnnyBody
    from pocoloco.body.skeleton import NUM_JOINTS
    from pocoloco.body.surface import pose_mean_shape_vertices

    src = os.fspath(path)
    try:
        with np.load(src, allow_pickle=False) as z:
            rot = np.asarray(z["joint_rotvecs"], np.float32)
            trans = np.asarray(z["root_translation"], np.float32) if "root_translation" in z.files else None
    except Exception as e:
        raise ValueError(f"{src}: cannot read anny pose parameters ({type(e).__name__}: {e})") from None
    if rot.ndim == 3 and rot.shape[0] == 1:
        rot = rot[0]
    if rot.shape != (NUM_JOINTS, 3) or not np.isfinite(rot).all():
        raise ValueError(f"{src}: joint_rotvecs must be a finite ({NUM_JOINTS}, 3) array, got {rot.shape}")
    if trans is not None:
        trans = trans.reshape(-1)[:3] if trans.size >= 3 else None
    posed = AnnyBody(phenotype).pose(rot[None], None if trans is None else trans[None])
    mean = None
    if need_mean_shape:
        mean = pose_mean_shape_vertices(rot[None])[0]
    return PeerPose(posed.vertices[0], posed.vtransf[0], posed.joints[0], mean, None, src)


def is_anny_pose_file(spec: str) -> bool:
    """True for an existing ``.npz`` holding ``joint_rotvecs``."""
    p = Path(spec)
    if p.suffix != ".npz" or not p.is_file():
        return False
    try:
        with np.load(p, allow_pickle=False) as z:
            return "joint_rotvecs" in z.files
    except Exception:
        return False


# -------------------------------------------------------------------------------- models
def _read_subjects(data, names: Sequence[str]):
    from pocoloco.data.format import DatasetLayout, read_subject

    layout = DatasetLayout(data)
    assets = {s: read_subject(layout.subject_path(s)) for s in names}
    first = assets[names[0]]
    for s, a in assets.items():
        if a.template.shape != first.template.shape or not np.array_equal(a.faces, first.faces):
            raise ValueError(f"{data}: subject {s!r} has another body topology than {names[0]!r}; "
                             "POP / CloSET need one mesh topology")  # fmt: skip
    return assets


def build_peer_model(config: PeerTrainConfig, assets: dict[str, Any]) -> nn.Module:
    """A fresh POP / CloSET for the subjects ``assets`` (name -> ``SubjectAsset``; outfit ids in
    this order). Initialised from torch's global RNG (seed it first)."""
    names = list(assets)
    first = assets[names[0]]
    if config.model == "pop":
        from pocoloco.body.surface import BodySurface, largest_component_faces
        from pocoloco.models.pop import POP

        faces = np.asarray(first.faces, np.int64)
        surface = BodySurface(faces, first.uv, np.asarray(first.uv_faces, np.int64), largest_component_faces(faces))
        return POP(config.net_config(), surface, len(names), int(first.template.shape[0]))
    from pocoloco.models.closet import CloSET

    template = np.mean([np.asarray(assets[s].template, np.float64) for s in names], axis=0).astype(np.float32)
    return CloSET(template, np.asarray(first.faces, np.int64), len(names), config.net_config())


def _num_vertices(model: nn.Module) -> int:
    return int(model.num_vertices)


def _outfits_meta(assets: dict[str, Any], source: str) -> list[dict[str, Any]]:
    return [{"id": i, "name": s, "phenotype": dict(assets[s].phenotype), "source": source}
            for i, s in enumerate(assets)]


# ---------------------------------------------------------------------------------- batches
class PeerBatches:
    """The frames of each step (``StepBatches`` order over the train split, all subjects) as
    POP / CloSET batches. ``batch(step)`` is a pure function of (seed, step)."""

    def __init__(self, data, config: PeerTrainConfig, outfits: dict[str, int], model: nn.Module):
        from pocoloco.data.dataset import PointCloudDataset
        from pocoloco.train import StepBatches

        self.config, self.outfits, self.model = config, outfits, model
        self.dataset = PointCloudDataset(data, "train", num_points=None, subjects=list(outfits), random_subsample=False)
        self.order = StepBatches(self.dataset, config.batch_size, config.num_points, config.seed, config.steps)
        self.need_mean = config.model == "pop" and config.net.get("pose_input") == "mean_shape"
        self.mean_cache = _MeanShapeCache()

    def frames(self, step: int):
        """[(subject, frame path, Frame, global position)] of the step."""
        from pocoloco.data.format import read_frame

        g, idx = self.order.frame_indices(step)
        out = []
        for gk, i in zip(g, idx, strict=True):
            subject, _, path = self.dataset.frames[int(i)]
            fr = read_frame(path, ["points", "normals", "joints", "frame_index", "body_vertices", "vtransf"],
                            allow_missing=True)  # fmt: skip
            out.append((subject, Path(path), fr, int(gk)))
        return out

    def batch(self, step: int):
        from pocoloco.train import _seed_of

        c = self.config
        items = self.frames(step)
        if c.model == "pop":
            from pocoloco.models.pop import collate_pop, pop_sample_from_frame

            samples = []
            for subject, path, fr, g in items:
                mean = self.mean_cache.get(_motion_path_of(path), int(fr.frame_index)) if self.need_mean else None
                rng = np.random.default_rng([c.seed, 1, g])
                samples.append(pop_sample_from_frame(fr, self.outfits[subject], c.num_points, rng, mean,
                                                     num_vertices=_num_vertices(self.model), src=os.fspath(path)))  # fmt: skip
            return collate_pop(samples)
        from pocoloco.models.closet import make_closet_batch

        q = self.model.sample_query_points(c.query_points, seed=_seed_of(c.seed, 4, step) % (2**31))
        frames = [fr for _, _, fr, _ in items]
        for _, path, fr, _ in items:
            if fr.body_vertices is None or fr.vtransf is None:
                raise ValueError(f"{path}: frame has no posed body (body_vertices / vtransf); CloSET needs it")
        return make_closet_batch(frames, [self.outfits[s] for s, _, _, _ in items], q, c.num_points,
                                 seed=_seed_of(c.seed, 1, step) % (2**31))  # fmt: skip


def _make_optimizer(model: nn.Module, config: PeerTrainConfig) -> torch.optim.Optimizer:
    if config.model == "pop":
        from pocoloco.models.pop import make_optimizer

        return make_optimizer(model)
    from pocoloco.models.closet import make_closet_optimizer

    return make_closet_optimizer(model, lr=config.lr, code_lr=config.lr_codes)


def _train_step(model, optimizer, batch, step: int, config: PeerTrainConfig) -> dict[str, float]:
    """One step; POP's normal weight follows ``normal_start`` (in its config), CloSET's too."""
    if config.model == "pop":
        from pocoloco.models.pop import train_step

        return train_step(model, optimizer, batch, step)
    from pocoloco.models.closet import CloSETLossWeights, closet_train_step

    w = CloSETLossWeights(**config.closet_weights)
    if step < config.normal_start:
        w = dataclasses.replace(w, normal=0.0)
    return closet_train_step(model, optimizer, batch, w)


# ------------------------------------------------------------------------------------ training
def train_peer(
    config: PeerTrainConfig,
    data: str | os.PathLike,
    out: str | os.PathLike,
    *,
    device: str | torch.device = "cpu",
    resume: bool = False,
    progress: bool = True,
    log_fn=None,
):
    """Train POP or CloSET on the ``train`` split of ``data`` into the run folder ``out``
    (same layout as ``pocoloco train``: config.json, metrics.jsonl, loss.png, samples/,
    checkpoints/). Returns a :class:`pocoloco.train.TrainResult` (``ema`` is the model itself)."""
    from pocoloco.data.format import DatasetLayout, read_card
    from pocoloco.train import TrainResult, _Logger, _progress_bar
    from pocoloco.utils.atomic import write_json_atomic

    device = torch.device(device)
    out = Path(out)
    ckpt_root = out / "checkpoints"
    card = read_card(data)
    norm = Normalisation.from_card(card)
    names = DatasetLayout(data).subjects()
    if config.subjects is not None:
        unknown = [x for x in config.subjects if x not in names]
        if unknown:
            raise ValueError(f"{data}: unknown subjects {unknown}; the dataset has {names}")
        names = list(config.subjects)
    if not names:
        raise ValueError(f"{data}: no subjects")
    assets = _read_subjects(data, names)

    start_step, ck = 0, None
    existing = ckpt_io.latest_checkpoint(ckpt_root)
    if resume:
        if existing is None:
            raise ValueError(f"{out}: --resume but no checkpoint in {ckpt_root}")
        ck = ckpt_io.load_checkpoint(existing, expect_model=config.model, expect_preset=config.preset)
        stored = PeerTrainConfig.from_dict(ck.config)
        a, b = stored.to_dict(), config.to_dict()
        diff = [k for k in a if k not in RESUMABLE_CHANGES and a[k] != b.get(k)]
        if diff:
            detail = "; ".join(f"{k}: checkpoint {a[k]!r} vs requested {b.get(k)!r}" for k in diff[:3])
            raise ValueError(f"{ck.path}: cannot resume with a different config ({detail})")
        if [o["name"] for o in ck.meta.get("outfits", [])] != names:
            raise ValueError(f"{data}: subjects {names} differ from the checkpoint's outfits ({ck.path})")
        start_step = ck.step
        if start_step > config.steps:
            raise ValueError(f"{ck.path}: checkpoint is at step {start_step}, past --steps {config.steps}")
    elif existing is not None:
        raise ValueError(f"{out}: already holds checkpoints; pass --resume or choose another --out")

    torch.manual_seed(config.seed)
    model = build_peer_model(config, assets)
    if ck is not None:
        model.load_state_dict(ck.model_state)
    model.to(device)
    optimizer = _make_optimizer(model, config)
    if ck is not None and ck.optimizer_state is not None:
        optimizer.load_state_dict(ck.optimizer_state)
    if ck is not None and ck.rng_state is not None:
        ckpt_io.restore_rng_state(ck.rng_state)
    outfits = {s: i for i, s in enumerate(names)}
    batches = PeerBatches(data, config, outfits, model)

    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "config.json", {"data": os.fspath(data), "world_size": 1, **config.to_dict()})
    logger = _Logger(out, start_step if ck is not None else None)
    outfits_meta = _outfits_meta(assets, "dataset subject")

    def save(step: int) -> Path:
        return ckpt_io.save_checkpoint(
            ckpt_root, step, model_kind=config.model, preset=config.preset, config=config.to_dict(),
            normalisation=norm, model_state=model.state_dict(), ema_state=None,
            optimizer_state=optimizer.state_dict(), rng_state=ckpt_io.capture_rng_state(),
            extra={"world_size": 1, "data": os.fspath(data), "outfits": outfits_meta,
                   "num_vertices": _num_vertices(model)}, keep=config.keep_checkpoints,
        )  # fmt: skip

    bar = _progress_bar(progress, start_step, config.steps)
    last_ckpt, saved_step, loss_val, t0, step = None, None, float("nan"), time.perf_counter(), start_step
    try:
        for step in range(start_step, config.steps):
            batch = batches.batch(step).to(device)
            logs = _train_step(model, optimizer, batch, step, config)
            done = step + 1
            loss_val = logs["total"]
            if not math.isfinite(loss_val):
                raise FloatingPointError(f"loss is {loss_val} at step {done}; lower --lr or check the data")
            if done % config.log_every == 0 or done == config.steps:
                elapsed = time.perf_counter() - t0
                rec = {"step": done, "loss": loss_val, **{k: v for k, v in logs.items() if k != "total"},
                       "lr": config.lr, "normal_on": step >= config.normal_start,
                       "steps_per_s": (done - start_step) / max(elapsed, 1e-9), "time": elapsed}  # fmt: skip
                logger.log(rec)
                if log_fn is not None:
                    log_fn(rec)
            bar.advance(loss_val)
            if config.sample_every and done % config.sample_every == 0:
                _render_predictions(model, config, data, outfits, out, done, device)
                logger.plot(out / "loss.png")
            if config.ckpt_every and done % config.ckpt_every == 0:
                last_ckpt, saved_step = save(done), done
                logger.plot(out / "loss.png")
            step = done
        if step > start_step and saved_step != step:
            last_ckpt = save(step)
            logger.plot(out / "loss.png")
    finally:
        bar.close()
        logger.close()
    elapsed = time.perf_counter() - t0
    return TrainResult(model=model, ema=model, step=step, last_checkpoint=last_ckpt,
                       steps_per_s=(step - start_step) / max(elapsed, 1e-9), final_loss=loss_val)  # fmt: skip


def _render_predictions(model, config: PeerTrainConfig, data, outfits: dict[str, int], out: Path, step: int,
                        device) -> Path | None:  # fmt: skip
    """GT next to the model's prediction for two frames (test split if any): ``samples/step_XXXXXX.png``."""
    from pocoloco.data.format import DatasetLayout, read_frame
    from pocoloco.render import render_grid

    layout = DatasetLayout(data)
    frames = layout.iter_frames("test") or layout.iter_frames("train")
    frames = [frames[i] for i in sorted({0, len(frames) // 2})]
    loaded = LoadedPeer(model, config.model, config, [{"id": i, "name": s} for s, i in outfits.items()],
                        Normalisation.identity(), out, step, {})  # fmt: skip
    panels = []
    was_training = model.training
    try:
        for subject, seq, path in frames:
            if subject not in outfits:
                continue
            fr = read_frame(path, ["points", "joints", "frame_index", "body_vertices", "vtransf"], allow_missing=True)
            pose = peer_pose_from_frame(path, subject, config.net.get("pose_input") == "mean_shape" and config.model == "pop",
                                        frame=fr)  # fmt: skip
            pred = predict_peer(loaded, pose, outfits[subject], 2048, seed=0)
            sel = np.random.default_rng([config.seed, 3]).choice(len(fr.points), min(2048, len(fr.points)), replace=False)
            panels += [(fr.points[sel], None, None, f"data {subject}/{seq}"),
                       (pred.points[0], None, None, f"{config.model}, step {step}")]  # fmt: skip
    finally:
        model.train(was_training)
    if not panels:
        return None
    return Path(render_grid(panels, out / "samples" / f"step_{step:06d}.png", views=("front", "side"), ncols=2))


# ------------------------------------------------------------------------------------- loading
@dataclass
class LoadedPeer:
    """A POP / CloSET checkpoint ready to predict.

    model (eval mode), kind ("pop" / "closet"), config (:class:`PeerTrainConfig`), outfits
    (list of {"id", "name", "phenotype", "source"}), normalisation (the dataset's, stored for
    reference), path, step, meta (``meta.json``).
    """

    model: nn.Module
    kind: str
    config: PeerTrainConfig
    outfits: list[dict[str, Any]]
    normalisation: Normalisation
    path: Path
    step: int
    meta: dict[str, Any]

    @property
    def title(self) -> str:
        return model_title(self.kind, self.config.to_dict())

    @property
    def num_parameters(self) -> int:
        return int(sum(p.numel() for p in self.model.parameters()))

    @property
    def needs_mean_shape(self) -> bool:
        return self.kind == "pop" and self.config.net.get("pose_input") == "mean_shape"

    def outfit_names(self) -> list[str]:
        return [o["name"] for o in self.outfits]

    def outfit_id(self, outfit: str | int) -> int:
        """An outfit name or id (as given on the command line) -> its id; one-line error if never trained."""
        names = self.outfit_names()
        s = str(outfit)
        if s in names:
            return names.index(s)
        if s.lstrip("-").isdigit() and 0 <= int(s) < len(names):
            return int(s)
        raise ValueError(f"{self.path}: outfit {s!r} was never trained (this {self.kind} checkpoint has "
                         f"{', '.join(f'{i}={n}' for i, n in enumerate(names))})")  # fmt: skip


def checkpoint_kind(path: str | os.PathLike) -> str:
    """The ``model_kind`` of a checkpoint (folder, checkpoints folder or run folder)."""
    ck = ckpt_io.resolve_checkpoint(path)
    return ckpt_io._read_meta(ck)["model_kind"]


def load_peer(path: str | os.PathLike, expect_model: str | None = None, device: str | torch.device = "cpu") -> LoadedPeer:
    """Load a POP / CloSET checkpoint. ``expect_model``: "pop" or "closet" (None: either); a
    checkpoint of another kind is a one-line error naming both kinds."""
    ck_path = ckpt_io.resolve_checkpoint(path)
    kind = ckpt_io._read_meta(ck_path)["model_kind"]
    want = expect_model if expect_model is not None else "pop' or 'closet"
    if (expect_model is not None and kind != expect_model) or kind not in PEER_KINDS:
        raise ValueError(f"{ck_path / ckpt_io.META_FILE}: checkpoint is of model {kind!r}, expected '{want}'")
    ck = ckpt_io.load_checkpoint(ck_path, expect_model=kind, training_state=False)
    try:
        config = PeerTrainConfig.from_dict(ck.config)
        outfits = list(ck.meta["outfits"])
        if kind == "pop":
            from pocoloco.models.pop import POP

            model = POP.from_state(config.net_config(), ck.model_state, int(ck.meta["num_vertices"]))
        else:
            from pocoloco.models.closet import CloSET

            model = CloSET.from_state(config.net_config(), ck.model_state)
    except (KeyError, TypeError, RuntimeError) as e:
        raise ValueError(f"{ck.path}: corrupt {kind} checkpoint ({ckpt_io._one_line(e)})") from None
    if len(outfits) != int(getattr(model, "num_outfits")):
        raise ValueError(f"{ck.path}: meta lists {len(outfits)} outfits but the weights hold {model.num_outfits}")
    return LoadedPeer(model.to(device).eval(), kind, config, outfits, ck.normalisation, ck.path, ck.step, ck.meta)


# ---------------------------------------------------------------------------------- prediction
def pop_query_for(model, num_points: int, seed: int):
    """N POP query points: the valid pixels of the training UV query map, or of the smallest
    finer map with >= N valid pixels, of which N are drawn without replacement (seeded)."""
    q = model.query_points()
    R = model.config.query_resolution
    while len(q) < num_points:
        if R >= 4096:
            raise ValueError(f"--points {num_points}: POP's UV map gives at most {len(q)} points")
        R = int(math.ceil(R * math.sqrt(num_points / max(len(q), 1)) * 1.02))
        q = model.query_points(R)
    idx = np.sort(np.random.default_rng([int(seed), 5]).choice(len(q), num_points, replace=False))
    return q.subset(idx), R


@torch.no_grad()
def predict_peer(loaded: LoadedPeer, pose: PeerPose, outfit: int, num_points: int, seed: int = 0,
                 geom: torch.Tensor | None = None):  # fmt: skip
    """One deterministic cloud of ``num_points`` for ``pose`` and ``outfit`` (eval mode):
    :class:`pocoloco.sample.SampledClouds` with points (1, N, 3) and normals (1, N, 3), metres,
    in the frame of ``pose`` (the root joint added back). ``seed`` picks the query points only."""
    from pocoloco.sample import SampledClouds

    if num_points < 1:
        raise ValueError(f"num_points must be >= 1, got {num_points}")
    model = loaded.model
    dev = next(model.parameters()).device
    root = np.asarray(pose.joints[0], np.float32)
    body = torch.from_numpy(np.asarray(pose.body_vertices, np.float32) - root)[None].to(dev)  # (1, V, 3)
    vt = torch.from_numpy(np.asarray(pose.vtransf, np.float32))[None].to(dev)  # (1, V, 3, 3)
    outfit_t = torch.tensor([int(outfit)], dtype=torch.long, device=dev)
    was_training = model.training
    model.eval()
    try:
        if loaded.kind == "pop":
            from pocoloco.models.pop import POPBatch

            if loaded.needs_mean_shape:
                if pose.mean_shape is None:
                    raise ValueError(f"{pose.source}: POP needs the posed mean-shape body for its pose input")
                pv = torch.from_numpy(np.asarray(pose.mean_shape, np.float32))[None].to(dev)
            else:
                pv = body
            query, _ = pop_query_for(model, num_points, seed)
            out = model(POPBatch(pv, body, vt, outfit_t), geom=geom, query=query)
        else:
            q = model.sample_query_points(num_points, seed=int(seed))
            out = model(body, vt, outfit_t, torch.as_tensor(q.face_idx, dtype=torch.long, device=dev),
                        torch.as_tensor(q.barycentric, dtype=torch.float32, device=dev))  # fmt: skip
    finally:
        model.train(was_training)
    pts = (out.points[0].cpu().numpy() + root).astype(np.float32)
    nrm = out.normals[0].cpu().numpy().astype(np.float32)
    return SampledClouds(pts[None], nrm[None])


def load_peer_pose(spec: str, loaded: LoadedPeer, outfit: int | None, frame_id: int | None = None) -> PeerPose:
    """``--joints`` for a peer: a dataset frame ``DATASET:subject/split/sequence/index`` (or a frame
    ``.npz`` of a dataset), or an ``.npz`` with anny ``joint_rotvecs`` (posed with the phenotype of
    ``outfit``'s subject); bare joints are a one-line error (the peers need the posed body)."""
    from pocoloco.sample import _dataset_frame_path

    if frame_id is not None:
        raise ValueError(f"{spec}: --frame-id only applies to PocoLoco checkpoints")
    spec = os.fspath(spec)
    path = Path(spec)
    kind = pose_spec_kind(spec)
    if kind == "dataset":
        fpath = _dataset_frame_path(spec)
        subject = spec.rpartition(":")[2].strip("/").split("/")[0]
        return peer_pose_from_frame(fpath, subject, loaded.needs_mean_shape)
    if kind == "anny":
        pheno = loaded.outfits[outfit].get("phenotype", {}) if outfit is not None else {}
        return peer_pose_from_anny_file(path, pheno, loaded.needs_mean_shape)
    subject = path.parent.parent.parent.parent.name
    return peer_pose_from_frame(path, subject, loaded.needs_mean_shape)


def pose_spec_kind(spec: str) -> str:
    """"dataset" (DATASET:subject/split/sequence/index), "anny" (.npz with joint_rotvecs) or "frame"
    (a frame .npz inside a dataset); anything else (bare joints) is a one-line error."""
    path = Path(spec)
    if not path.exists() and ":" in spec and not spec.startswith("demo:"):
        return "dataset"
    if is_anny_pose_file(spec):
        return "anny"
    if path.suffix == ".npz" and path.is_file() and path.parent.name == "frames" and \
            (path.parent.parent / "motion.npz").is_file():  # fmt: skip
        return "frame"
    raise ValueError(f"{spec}: POP and CloSET need the posed body, not only joints: pass a dataset frame "
                     "DATASET:subject/split/sequence/index or an .npz with anny pose parameters 'joint_rotvecs' (24, 3)")


# ----------------------------------------------------------------------------- pocoloco sample
def cmd_sample_peer(args: argparse.Namespace) -> None:
    """``pocoloco sample`` for a POP / CloSET checkpoint: one deterministic cloud (``--num`` > 1
    is an error: the peers have no sampling noise), written like PocoLoco's samples."""
    from pocoloco.sample import write_samples

    if args.num is not None and args.num != 1:
        raise ValueError(f"--num {args.num}: POP and CloSET are deterministic (one cloud per pose and outfit); use --num 1")
    if args.points is not None and args.points < 1:
        raise ValueError(f"--points must be >= 1, got {args.points}")
    out = output_folder(args.out)
    device = torch.device(args.device or "cpu")
    loaded = load_peer(args.ckpt, device=device)
    outfit_arg = getattr(args, "outfit", None)
    joints_spec = os.fspath(args.joints)
    pose_spec_kind(joints_spec)  # bare joints: the one-line error first
    if outfit_arg is None:  # default: the frame's subject
        subject = joints_spec.rpartition(":")[2].strip("/").split("/")[0] if ":" in joints_spec else None
        if subject is None or subject not in loaded.outfit_names():
            raise ValueError(f"--outfit is required (this {loaded.kind} checkpoint has outfits "
                             f"{', '.join(loaded.outfit_names())})")  # fmt: skip
        outfit_arg = subject
    outfit = loaded.outfit_id(outfit_arg)
    pose = load_peer_pose(joints_spec, loaded, outfit, args.frame_id)
    num_points = args.points if args.points is not None else 2048
    t0 = time.perf_counter()
    clouds = predict_peer(loaded, pose, outfit, num_points, seed=args.seed)
    seconds = time.perf_counter() - t0
    how = ("N of the valid pixels of the UV query map (finer than the training map if needed), without replacement"
           if loaded.kind == "pop" else "N area-uniform points on the template surface")  # fmt: skip
    settings = {
        "checkpoint": str(loaded.path), "model_kind": loaded.kind, "model": loaded.title, "step": loaded.step,
        "preset": loaded.config.preset, "outfit": loaded.outfit_names()[outfit], "outfit_id": outfit,
        "joints": joints_spec, "body_source": pose.source, "joints_m": pose.joints.tolist(), "num": 1,
        "points": num_points, "query_points": how, "seed": args.seed, "deterministic": True, "normals": True,
        "device": str(device), "threads": torch.get_num_threads(), "seconds_total": seconds,
        "seconds_per_sample": seconds,
    }  # fmt: skip
    write_samples(out, clouds, settings, render=not args.no_render)
    print(f"wrote 1 {loaded.title} cloud of {num_points} points (outfit {loaded.outfit_names()[outfit]}) to {out} "
          f"({seconds:.3f} s)")  # fmt: skip


# ------------------------------------------------------------------------------ pocoloco train
def add_peer_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pocoloco train`` that only the peers use."""
    parser.add_argument("--no-decomposition", action="store_true",
                        help="CloSET: one decoder instead of garment template + pose wrinkles (the paper's ablation)")  # fmt: skip
    parser.add_argument("--normal-start", type=int,
                        help="POP / CloSET: first step with the normal loss (default: 62.5%% of --steps, as POP)")  # fmt: skip
    parser.add_argument("--query-points", type=int, help="CloSET: surface points per training frame")
    parser.add_argument("--subjects", nargs="+",
                        help="POP / CloSET: train on these subjects only (e.g. hold one out for `pocoloco fit`)")  # fmt: skip


def _peer_config_from_args(args: argparse.Namespace) -> PeerTrainConfig:
    overrides = {"steps": args.steps, "batch_size": args.batch_size, "lr": args.lr, "num_points": args.num_points,
                 "seed": args.seed, "ckpt_every": args.ckpt_every, "sample_every": args.sample_every,
                 "log_every": args.log_every, "normal_start": getattr(args, "normal_start", None),
                 "query_points": getattr(args, "query_points", None), "subjects": getattr(args, "subjects", None)}  # fmt: skip
    overrides = {k: v for k, v in overrides.items() if v is not None}
    for name in ("schedule", "prediction_type", "min_snr", "bf16", "workers"):
        if getattr(args, name, None) not in (None, False):
            raise ValueError(f"--{name.replace('_', '-')} applies to --model pocoloco only")
    decomposition = False if getattr(args, "no_decomposition", False) else None
    if args.preset is None and args.resume:
        found = ckpt_io.latest_checkpoint(Path(args.out) / "checkpoints")
        if found is None:
            raise ValueError(f"{args.out}: --resume but no checkpoint in {Path(args.out) / 'checkpoints'}")
        meta = ckpt_io.load_checkpoint(found, expect_model=args.model, training_state=False)
        if decomposition is not None:
            raise ValueError("--no-decomposition cannot change on --resume (it comes from the checkpoint)")
        return PeerTrainConfig.from_dict(meta.config).replace(**overrides)
    return peer_preset(args.model, args.preset or "small", decomposition=decomposition, **overrides)


def cmd_train_peer(args: argparse.Namespace) -> None:
    """``pocoloco train --model pop|closet``."""
    from rich.console import Console

    from pocoloco.data.format import read_card

    read_card(args.data)
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise ValueError("POP / CloSET train in one process (no torchrun / DDP); run `pocoloco train` directly")
    config = _peer_config_from_args(args)
    device = torch.device(args.device or "cpu")
    if args.threads is not None:
        torch.set_num_threads(max(1, args.threads))
    Console(stderr=True).print(
        f"[bold]pocoloco train[/] model={model_title(config.model, config.to_dict())} preset={config.preset} "
        f"device={device} threads={torch.get_num_threads()} steps={config.steps} batch={config.batch_size} "
        f"scan N={config.num_points} normal loss from step {config.normal_start} -> {args.out}"
    )  # fmt: skip
    result = train_peer(config, args.data, args.out, device=device, resume=args.resume, progress=not args.no_progress)
    n_params = sum(p.numel() for p in result.model.parameters())
    print(f"trained to step {result.step} ({result.steps_per_s:.3f} steps/s, {n_params:,} parameters), "
          f"loss {result.final_loss:.4f}; checkpoint {result.last_checkpoint}")  # fmt: skip


# ---------------------------------------------------------------------------------- pocoloco fit
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
    from pocoloco.metrics import evaluate_frame

    m = evaluate_frame(pred_points, pred_normals, scan, scan_n, None)
    return {k: float(m[k]) for k in ("chamfer_cm", "s2m_cm", "m2s_cm", "pop_chamfer_e-4m2", "normal_l1_e-1") if k in m}


def fit_outfit(ckpt: str | os.PathLike, scan_path: str | os.PathLike, frame_spec: str, out: str | os.PathLike,
               name: str | None = None, steps: int = 400, lr: float | None = None, num_points: int | None = None,
               seed: int = 0, progress=None) -> FitReport:  # fmt: skip
    """Fit a new POP outfit to one scan (paper Eq. 7) and write ``out`` = a new checkpoint folder
    with the outfit appended (atomic), plus ``out/fit.json``.

    The scan (PLY with normals, world frame of ``frame_spec``'s body) is subsampled to
    ``num_points`` (default: the model's ``num_scan_points``). Only the new (1, Cg, Ri, Ri)
    geometric feature tensor is optimised, from the mean of the trained outfits (the paper's
    init); the network is frozen. Chamfer is reported before (the mean outfit = the start point;
    and the best trained outfit) and after fitting, on the scan, with the model's query points.
    """
    from pocoloco.data.published import read_ply
    from pocoloco.models.pop import fit_unseen_outfit
    from pocoloco.sample import _dataset_frame_path
    from pocoloco.utils.atomic import write_json_atomic

    loaded = load_peer(ckpt, expect_model="pop")
    if isinstance(steps, bool) or steps < 1:
        raise ValueError(f"--steps must be >= 1, got {steps}")
    out = Path(out)
    if ckpt_io.latest_checkpoint(out / "checkpoints") is not None or (out / ckpt_io.META_FILE).exists():
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
    pose = peer_pose_from_frame(_dataset_frame_path(frame_spec), subject, loaded.needs_mean_shape)
    root = pose.joints[0]
    model = loaded.model
    pv = pose.mean_shape if loaded.needs_mean_shape else pose.body_vertices - root
    t0 = time.perf_counter()
    fit = fit_unseen_outfit(model, scan[sel] - root, scan_n[sel], pv, pose.body_vertices - root, pose.vtransf,
                            steps=steps, lr=lr, progress=progress)  # fmt: skip
    seconds = time.perf_counter() - t0

    n_eval = min(len(scan), 10_000)
    esel = np.sort(np.random.default_rng([seed, 7]).choice(len(scan), n_eval, replace=False))
    gt, gt_n = scan[esel].astype(np.float64), scan_n[esel].astype(np.float64)

    def score(geom=None, outfit=0):
        c = predict_peer(loaded, pose, outfit, n_eval, seed=seed, geom=geom)
        return _score(c.points[0], c.normals[0], gt, gt_n)

    before_mean = score(geom=model.geom.detach().mean(0, keepdim=True))
    per_outfit = [score(outfit=i) for i in range(model.num_outfits)]
    best = int(np.argmin([m["chamfer_cm"] for m in per_outfit]))
    after = score(geom=fit.features)

    new_id = model.add_outfit(fit.features)
    outfits = [*loaded.outfits, {"id": new_id, "name": name, "phenotype": loaded.outfits[0].get("phenotype", {}),
                                 "source": f"fitted to {os.fspath(scan_path)} (body of {frame_spec})"}]  # fmt: skip
    if subject in loaded.outfit_names():  # the body the scan was fitted on
        outfits[-1]["phenotype"] = loaded.outfits[loaded.outfit_id(subject)].get("phenotype", {})
    meta = dict(loaded.meta)
    extra = {k: v for k, v in meta.items() if k not in ("format", "version", "model_kind", "preset", "step", "config",
                                                         "normalisation", "has_ema", "has_training_state",
                                                         "torch_version")}  # fmt: skip
    extra.update(outfits=outfits, fitted_from=str(loaded.path))
    path = ckpt_io.save_checkpoint(out / "checkpoints", loaded.step, model_kind="pop", preset=loaded.config.preset,
                                   config=loaded.config.to_dict(), normalisation=loaded.normalisation,
                                   model_state=model.state_dict(), extra=extra)  # fmt: skip
    report = FitReport(path, name, new_id, before_mean, per_outfit[best], loaded.outfit_names()[best], after,
                       fit.losses, seconds)  # fmt: skip
    write_json_atomic(out / "fit.json", {
        "checkpoint": str(path), "from": str(loaded.path), "scan": os.fspath(scan_path), "frame": frame_spec,
        "outfit": name, "outfit_id": new_id, "steps": steps, "scan_points_fit": n_fit, "eval_points": n_eval,
        "before_mean_outfit": before_mean, "before_nearest_outfit": {"outfit": report.nearest_outfit, **per_outfit[best]},
        "after": after, "loss_first": fit.losses[0], "loss_last": fit.losses[-1], "seconds": seconds,
        "note": "Chamfer on the scan (10K points at most) with the same number of model points; 'before' = the mean of "
                "the trained outfits' features (where fitting starts) and the best single trained outfit",
    })  # fmt: skip
    return report


def add_fit_arguments(parser: argparse.ArgumentParser) -> None:
    """``pocoloco fit`` options (handler :func:`cmd_fit`)."""
    parser.add_argument("--model", default="pop", choices=("pop",), help="only POP fits unseen outfits (paper Sec. 3.3)")
    parser.add_argument("--ckpt", required=True, help="trained POP checkpoint / run folder")
    parser.add_argument("--scan", required=True, help="PLY of the unseen outfit with normals (world frame of --frame)")
    parser.add_argument("--frame", required=True,
                        help="DATASET:subject/split/sequence/index: the body and pose the scan was taken in")  # fmt: skip
    parser.add_argument("--name", help="name of the new outfit (default: the scan file's stem)")
    parser.add_argument("--steps", type=int, default=400, help="Adam steps (default 400, as the paper)")
    parser.add_argument("--lr", type=float, help="learning rate (default: the model's feature lr)")
    parser.add_argument("--points", type=int, help="scan points used by the loss (default: the model's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--out", required=True, help="new folder: the checkpoint with the added outfit + fit.json")


def cmd_fit(args: argparse.Namespace) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    if args.threads is not None:
        torch.set_num_threads(max(1, args.threads))
    with Progress(TextColumn("fit"), BarColumn(), MofNCompleteColumn(), TextColumn("loss {task.fields[loss]}"),
                  TimeRemainingColumn(), transient=True) as bar:  # fmt: skip
        task = bar.add_task("fit", total=args.steps, loss="-")
        rep = fit_outfit(args.ckpt, args.scan, args.frame, args.out, name=args.name, steps=args.steps, lr=args.lr,
                         num_points=args.points, seed=args.seed,
                         progress=lambda d, n, loss: bar.update(task, completed=d, loss=f"{loss:.3f}"))  # fmt: skip
    b, nb, a = rep.before_mean, rep.before_nearest, rep.after
    print(f"outfit {rep.outfit!r} (id {rep.outfit_id}) fitted in {rep.seconds:.1f} s: Chamfer {b['chamfer_cm']:.2f} cm "
          f"(mean outfit) / {nb['chamfer_cm']:.2f} cm (nearest trained outfit {rep.nearest_outfit!r}) -> "
          f"{a['chamfer_cm']:.2f} cm; CD {b['pop_chamfer_e-4m2']:.2f} -> {a['pop_chamfer_e-4m2']:.2f} 1e-4 m^2")  # fmt: skip
    print(f"wrote {rep.checkpoint} and {Path(args.out) / 'fit.json'}; animate it with "
          f"`pocoloco sample --ckpt {args.out} --outfit {rep.outfit} --joints DATASET:subject/split/sequence/index`")
