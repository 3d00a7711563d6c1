"""What POP and CloSET share: point regressors on the skinned body surface, one outfit code per
dataset subject, trained with the scan as ground truth.

* :class:`SkinnedTrainConfig`: their training config (one dataclass for both, as stored in their
  checkpoints) and the named presets of each (:data:`SKINNED_PRESETS`).
* :class:`SkinnedTask`: the shared part of their :class:`~pocoloco.engine.trainer.TrainingTask`
  (subjects -> outfits, the frames of each step, resume checks, previews, checkpoint metadata).
* :class:`SkinnedMethod`: the shared part of their :class:`~pocoloco.methods.base.Method`
  (outfits, poses with the posed body, one deterministic cloud per pose and outfit).

Data. One outfit per subject of the dataset (ids in sorted subject order; stored in the
checkpoint's ``meta.json`` under ``outfits`` with each subject's anny phenotype). A frame gives
the posed body (``body_vertices`` (V, 3), ``vtransf`` (V, 3, 3)), the joints (root = joints[0]:
both methods work pelvis-centred) and the scan (``points`` / ``normals``, ``num_points`` drawn per
frame). Everything random in a step is a pure function of (seed, step): the frames
(:class:`~pocoloco.data.step_batches.StepBatches` order), the scan-point subsets
(``default_rng([seed, 1, position])``) and CloSET's query points on the template; the model is
initialised from ``torch.manual_seed(seed)``. So ``--resume`` continues exactly.

Schedule. Adam 3e-4 for the networks and 5e-4 for the outfit codes, batch 4, constant lr; the
normal term is switched on at 62.5 % of the run (POP's epoch 250 of 400), ``normal_start``.
Neither paper uses EMA, clipping or bf16: they are off by default (``ema_decay``, ``grad_clip``,
``bf16`` turn them on; POP's fused decoder runs in float32, so ``bf16`` applies to CloSET only).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from abc import abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn

from pocoloco.body.surface import barycentric_interpolate
from pocoloco.data.dataset import Normalisation, OpenedDataset, PointCloudDataset
from pocoloco.data.motion_window import check_motion_training
from pocoloco.data.format import (
    DatasetLayout,
    Frame,
    read_frame,
    read_subject,
)
from pocoloco.data.pack import PackedBodies, is_pack, read_pack_meta, read_pack_subjects
from pocoloco.data.poses import MeanShapeCache, Pose, load_body_pose, motion_path_of, pose_from_frame
from pocoloco.data.step_batches import StepBatches
from pocoloco.engine.checkpoint import Checkpoint, one_line
from pocoloco.engine.trainer import LoopSettings, TrainingTask, check_lr_schedule
from pocoloco.methods.base import Method, SampledClouds, SamplerOptions
from pocoloco.models.closet import CLOSET_PRESETS, CloSETConfig, CloSETLossWeights
from pocoloco.models.pop import LEGACY_LOSS_WEIGHTS, POP_PRESETS, POPConfig, POPLossWeights
from pocoloco.utils.config import Config
from pocoloco.viz.render import render_grid

__all__ = ["NORMAL_START_FRACTION", "SKINNED_PRESETS", "SkinnedMethod", "SkinnedTask", "SkinnedTrainConfig",
           "read_subjects", "skinned_preset"]  # fmt: skip

SKINNED_KINDS = ("pop", "closet")
#: SkinnedTrainConfig fields that may change when resuming (they do not affect the optimisation)
RESUMABLE_CHANGES = frozenset({"steps", "ckpt_every", "sample_every", "log_every", "keep_checkpoints", "num_workers"})
#: the paper switches POP's normal loss on at epoch 250 of 400
NORMAL_START_FRACTION = 250 / 400


# ------------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class SkinnedTrainConfig(Config):
    """A POP or CloSET training run (the data folder and the device excepted).

    model: "pop" or "closet". preset: the preset name. net: the network config as a dict
    (``POPConfig.to_dict()`` / ``CloSETConfig.to_dict()``). steps: optimiser steps. batch_size:
    frames per step. num_points: scan points drawn per frame (the loss's ground truth).
    query_points: CloSET's surface points per training step (POP uses its UV query map).
    lr / lr_codes: Adam rates of the networks and of the auto-decoded outfit codes (POP's
    geometric features, CloSET's garment codes). normal_start: first step with the normal loss.
    pop_weights: ``POPLossWeights`` as a dict (POP only); closet_weights: ``CloSETLossWeights`` as
    a dict (CloSET only). subjects: train on these
    subjects only (one outfit each; None = all), e.g. to hold one out for ``pocoloco fit``.
    seed: everything random.
    ckpt_every / sample_every / log_every: periods in steps (0 disables checkpoints / renders).
    keep_checkpoints: step folders kept. ema_decay: EMA of the weights (None: off, as the papers);
    grad_clip: max gradient L2 norm (None: off); bf16: bf16 autocast (CloSET only).
    num_workers: DataLoader worker processes building the steps' batches (0: the main process).
    lr_schedule: ``constant`` (both papers), ``cosine`` or ``wsd`` (constant, then linear to 0 over the
    last ``decay_steps``: a cool-down, e.g. of a shipped model with ``--init-from``).
    motion_window / history_dropout: POP only: the code of the last this-many seconds of motion joins
    the pose features (issue 41's ablation; :class:`~pocoloco.models.pop.POPConfig`), a
    ``history_dropout`` share of training frames shown at rest, the encoder's learning rate
    ``motion_lr_scale`` x ``lr``.
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
    pop_weights: dict[str, float] = field(default_factory=dict)
    closet_weights: dict[str, float] = field(default_factory=dict)
    subjects: list[str] | None = None
    seed: int = 0
    ckpt_every: int = 250
    sample_every: int = 1000
    log_every: int = 10
    keep_checkpoints: int = 3
    ema_decay: float | None = None
    grad_clip: float | None = None
    bf16: bool = False
    num_workers: int = 0
    lr_schedule: str = "constant"
    decay_steps: int = 0
    motion_window: float = 0.0
    history_dropout: float = 0.15
    motion_lr_scale: float = 1.0

    def __post_init__(self):
        if self.model not in SKINNED_KINDS:
            raise ValueError(f"unknown model {self.model!r} for a SkinnedTrainConfig; choose one of: "
                             f"{', '.join(SKINNED_KINDS)}")  # fmt: skip
        for name in ("steps", "batch_size", "num_points", "query_points", "log_every", "keep_checkpoints"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        for name in ("normal_start", "ckpt_every", "sample_every", "num_workers"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("lr", "lr_codes"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive number, got {v}")
        check_lr_schedule(self.lr_schedule, self.decay_steps, self.steps)
        if self.ema_decay is not None and not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must be in [0, 1) or None, got {self.ema_decay}")
        if self.grad_clip is not None and not self.grad_clip > 0:
            raise ValueError(f"grad_clip must be > 0 or None, got {self.grad_clip}")
        if self.motion_window and self.model != "pop":
            raise ValueError("--motion-window applies to --model pocoloco (latent presets) and pop")
        check_motion_training(self.motion_window, self.history_dropout, self.motion_lr_scale)
        if self.bf16 and self.model == "pop":
            raise ValueError("bf16 is not available for POP: its fused BatchNorm + softplus decoder runs in float32")
        if self.subjects is not None:
            if not self.subjects or len(set(self.subjects)) != len(self.subjects):
                raise ValueError(f"subjects must be distinct names, got {self.subjects!r}")
            object.__setattr__(self, "subjects", sorted(str(x) for x in self.subjects))
        if self.model == "pop":
            net = POPConfig.from_dict(self.net).to_dict() if self.net else POPConfig().to_dict()
            net["motion_window"] = float(self.motion_window)  # the network's input follows the run's
            object.__setattr__(self, "pop_weights", POPLossWeights.from_dict(self.pop_weights).to_dict())
            object.__setattr__(self, "closet_weights", {})
        else:
            net = CloSETConfig.from_dict(self.net).to_dict() if self.net else CLOSET_PRESETS["paper"].to_dict()
            w = dataclasses.asdict(CloSETLossWeights(**self.closet_weights))
            object.__setattr__(self, "closet_weights", w)
            object.__setattr__(self, "pop_weights", {})
        object.__setattr__(self, "net", json.loads(json.dumps(net)))  # plain JSON types (tuples -> lists)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SkinnedTrainConfig:
        """As :meth:`Config.from_dict`; a POP run stored before the network and training configs were
        split kept its loss weights in ``net`` (``w_s2m``, ...): they move to ``pop_weights`` (the
        other training fields there always equalled the run's own)."""
        net = d.get("net") if isinstance(d, dict) else None
        if isinstance(net, dict) and d.get("model", "pop") == "pop":
            legacy = {LEGACY_LOSS_WEIGHTS[k]: v for k, v in net.items() if k in LEGACY_LOSS_WEIGHTS}
            if legacy:
                d = {**d, "pop_weights": {**legacy, **(d.get("pop_weights") or {})}}
        return super().from_dict(d)

    def pop_loss_weights(self) -> POPLossWeights:
        """POP's loss weights (paper Eq. 3)."""
        return POPLossWeights.from_dict(self.pop_weights)

    def loop(self) -> LoopSettings:
        """What the training loop reads (:class:`pocoloco.engine.trainer.LoopSettings`): no warm-up;
        by default a constant learning rate, as in both papers."""
        return LoopSettings(
            preset=self.preset, steps=self.steps, lr=self.lr, seed=self.seed, warmup_steps=0,
            lr_schedule=self.lr_schedule, decay_steps=self.decay_steps, ema_decay=self.ema_decay,
            grad_clip=self.grad_clip, bf16=self.bf16,
            ckpt_every=self.ckpt_every, sample_every=self.sample_every, log_every=self.log_every,
            keep_checkpoints=self.keep_checkpoints, num_workers=self.num_workers,
        )  # fmt: skip

    def net_config(self) -> POPConfig | CloSETConfig:
        """The ``POPConfig`` or ``CloSETConfig``."""
        return POPConfig.from_dict(self.net) if self.model == "pop" else CloSETConfig.from_dict(self.net)


def _pop_net(name: str, **kw) -> dict[str, Any]:
    return dataclasses.replace(POP_PRESETS[name], **kw).to_dict()


SKINNED_PRESETS: dict[tuple[str, str], SkinnedTrainConfig] = {
    # POP paper: 128^2 input, 256^2 query map, batch 4, 40K scan points, Adam 3e-4 / 5e-4
    ("pop", "paper"): SkinnedTrainConfig(model="pop", preset="paper", net=_pop_net("paper"), steps=100_000,
                                         batch_size=4, num_points=40_000, normal_start=62_500, ckpt_every=2000,
                                         sample_every=5000, log_every=50),
    # CPU: POP's small network with a 64^2 query map (~2.5K points per frame at training; any
    # number at test time from finer maps) so a step takes about a second on one core
    ("pop", "small"): SkinnedTrainConfig(model="pop", preset="small", net=_pop_net("small", query_resolution=64),
                                         steps=10_000, batch_size=4, num_points=4096, normal_start=6250),
    # tests: the UNet sees the subject's own body (no anny needed)
    ("pop", "tiny"): SkinnedTrainConfig(model="pop", preset="tiny", net=_pop_net("tiny", pose_input="subject"),
                                        steps=20, batch_size=2, num_points=512, normal_start=10, lr=1e-3,
                                        lr_codes=1e-3, ckpt_every=10, sample_every=0, log_every=1),
    ("closet", "paper"): SkinnedTrainConfig(model="closet", preset="paper", net=CLOSET_PRESETS["paper"].to_dict(),
                                            steps=100_000, batch_size=4, num_points=40_000, query_points=40_000,
                                            normal_start=62_500, ckpt_every=2000, sample_every=5000, log_every=50),
    # CPU: as many query points per frame as POP's small preset
    ("closet", "small"): SkinnedTrainConfig(model="closet", preset="small", net=CLOSET_PRESETS["small"].to_dict(),
                                            steps=10_000, batch_size=4, num_points=4096, query_points=2560,
                                            normal_start=6250),
    ("closet", "tiny"): SkinnedTrainConfig(model="closet", preset="tiny", net=CLOSET_PRESETS["tiny"].to_dict(),
                                           steps=20, batch_size=2, num_points=512, query_points=512, normal_start=10,
                                           lr=1e-3, lr_codes=1e-3, ckpt_every=10, sample_every=0, log_every=1),
}  # fmt: skip


def skinned_preset(model: str, name: str, decomposition: bool | None = None, **overrides) -> SkinnedTrainConfig:
    """The preset ``name`` of ``model`` with field overrides. Changing ``steps`` without giving
    ``normal_start`` moves the normal-loss switch to the same fraction (62.5 %) of the new run.
    ``decomposition=False``: CloSET's single-decoder ablation."""
    if model not in SKINNED_KINDS:
        raise ValueError(f"unknown model {model!r}; choose one of: {', '.join(SKINNED_KINDS)}")
    names = [n for m, n in SKINNED_PRESETS if m == model]
    if (model, name) not in SKINNED_PRESETS:
        raise ValueError(f"unknown training preset {name!r} for {model}; choose one of: {', '.join(names)}")
    base = SKINNED_PRESETS[(model, name)]
    if "steps" in overrides and "normal_start" not in overrides:
        overrides["normal_start"] = int(round(NORMAL_START_FRACTION * overrides["steps"]))
    if decomposition is not None:
        if model != "closet":
            raise ValueError("--no-decomposition applies to --model closet only")
        overrides["net"] = {**base.net, "decomposition": bool(decomposition)}
    return base.replace(**overrides)


# -------------------------------------------------------------------------------- subjects
def read_subjects(data: str | Path, names: Sequence[str]) -> dict[str, Any]:
    """Subject name -> ``SubjectAsset`` of ``names`` (one body topology, else a one-line error)."""
    layout = DatasetLayout(data)
    assets = {s: read_subject(layout.subject_path(s)) for s in names}
    first = assets[names[0]]
    for s, a in assets.items():
        if a.template.shape != first.template.shape or not np.array_equal(a.faces, first.faces):
            raise ValueError(f"{data}: subject {s!r} has another body topology than {names[0]!r}; "
                             "POP / CloSET need one mesh topology")  # fmt: skip
    return assets


def _outfits_meta(assets: dict[str, Any], source: str) -> list[dict[str, Any]]:
    return [{"id": i, "name": s, "phenotype": dict(assets[s].phenotype), "source": source}
            for i, s in enumerate(assets)]  # fmt: skip


# ------------------------------------------------------------------------------------ training
class StepFrame(NamedTuple):
    """One frame of a training step: its subject, where it came from (a frame file, or
    ``PACK[subject/split/sequence/index]``), the :class:`~pocoloco.data.frame.Frame` (points,
    normals, joints, frame_index, body_vertices, vtransf), its global position in the run's frame
    order and, when the method asks for it, the posed mean-shape body (V, 3), centred on its root."""

    subject: str
    path: Path
    frame: Frame
    position: int
    mean_shape: np.ndarray | None = None


class SkinnedBatches(torch.utils.data.Dataset):
    """The frames of each step (``StepBatches`` order over the train split, all subjects) of a
    dataset folder or a ``--bodies`` training pack turned into a method's batch by
    ``make_batch(items, step)``; item ``step`` is a pure function of (seed, step, rank)."""

    def __init__(self, task: SkinnedTask, rank: int = 0, world: int = 1):
        c = task.config
        self.task = task
        if is_pack(task.data):
            self.dataset = PackedBodies(task.data, "train", subjects=list(task.outfits))
        else:
            self.dataset = PointCloudDataset(task.data, "train", num_points=None, subjects=list(task.outfits),
                                             random_subsample=False)  # fmt: skip
        self.order = StepBatches(self.dataset, c.batch_size, c.num_points, c.seed, c.steps, rank, world)

    def __len__(self) -> int:
        return len(self.order)

    def frames(self, step: int) -> list[StepFrame]:
        """The step's frames."""
        g, idx = self.order.frame_indices(step)
        return [self.task.step_frame(self.dataset, int(i), int(gk)) for gk, i in zip(g, idx, strict=True)]

    def __getitem__(self, step: int):
        return self.task.make_batch(self.frames(int(step)), int(step))


class SkinnedTask(TrainingTask):
    """The shared training task of POP and CloSET; subclasses give ``build_model``,
    ``make_optimizer``, ``make_batch`` and ``loss``."""

    resumable_changes = RESUMABLE_CHANGES
    method: type[SkinnedMethod]

    def __init__(self, config: SkinnedTrainConfig, data: str | Path):
        self.config, self.kind = config, config.model
        packed = is_pack(data)
        if packed and config.motion_window:
            raise ValueError(f"{data}: a training pack holds no motion histories yet: train --motion-window on the "
                             "dataset folder")  # fmt: skip
        if packed:  # a --bodies training pack: its rigs give the subjects' assets
            meta = read_pack_meta(data)
            self.normalisation = Normalisation.from_card({"normalisation": meta["normalisation"]})
            pack_assets = read_pack_subjects(data)  # a one-line error for a pack without bodies
            names = sorted(pack_assets)
        else:
            opened = OpenedDataset.open(data, subjects=[])  # the card (read here unless the caller opened it)
            self.normalisation = Normalisation.from_card(opened.card)
            names = opened.layout.subjects()
        if config.subjects is not None:
            unknown = [x for x in config.subjects if x not in names]
            if unknown:
                raise ValueError(f"{data}: unknown subjects {unknown}; the {'pack' if packed else 'dataset'} "
                                 f"has {names}")  # fmt: skip
            names = list(config.subjects)
        if not names:
            raise ValueError(f"{data}: no subjects")
        if packed:
            held = int(meta["points_per_frame"])
            if config.num_points > held:
                raise ValueError(f"{data}: the pack holds {held:,} scan points per frame, fewer than the {config.num_points:,} "
                                 f"{config.model} draws per frame: pass --num-points {held} (or pack more points)")  # fmt: skip
            self.data = os.fspath(data)
            self.assets = {s: pack_assets[s] for s in names}
        else:
            self.data = opened.ensure_checked(names)  # a missing or damaged frame: one line, before training
            self.assets = read_subjects(data, names)
        self.outfits = {s: i for i, s in enumerate(names)}
        self.model: nn.Module | None = None
        self.mean_cache = MeanShapeCache()

    @property
    def needs_mean_shape(self) -> bool:
        """Whether the steps' frames carry the posed mean shape (POP's pose input)."""
        return False

    def step_frame(self, dataset: PointCloudDataset | PackedBodies, index: int, position: int) -> StepFrame:
        """Frame ``index`` of the train split (a dataset folder's or a pack's) as a :class:`StepFrame`."""
        if isinstance(dataset, PackedBodies):
            subject, _, label = dataset.frames[index]
            mean = dataset.mean_shape(index) if self.needs_mean_shape else None
            return StepFrame(subject, Path(label), dataset.frame(index), position, mean)
        subject, _, path = dataset.frames[index]
        fr = read_frame(path, ["points", "normals", "joints", "frame_index", "body_vertices", "vtransf"],
                        allow_missing=True)  # fmt: skip
        mean = self.mean_cache.get(motion_path_of(Path(path)), int(fr.frame_index)) if self.needs_mean_shape else None
        return StepFrame(subject, Path(path), fr, position, mean)

    @abstractmethod
    def make_batch(self, items: list[StepFrame], step: int):
        """The method's batch from the step's frames (:meth:`SkinnedBatches.frames`)."""

    def step_batches(self, model: nn.Module, rank: int, world: int) -> SkinnedBatches:
        self.model = model
        return SkinnedBatches(self, rank, world)

    def check_resume(self, ck: Checkpoint) -> None:
        names = list(self.outfits)
        if [o["name"] for o in ck.meta.get("outfits", [])] != names:
            raise ValueError(f"{self.data}: subjects {names} differ from the checkpoint's outfits ({ck.path})")

    def checkpoint_extra(self, model: nn.Module) -> dict[str, Any]:
        return {"outfits": _outfits_meta(self.assets, "dataset subject"), "num_vertices": int(model.num_vertices)}

    def log_extra(self, step: int) -> dict[str, Any]:
        return {"normal_on": step >= self.config.normal_start}

    def preview(self, model: nn.Module, step: int, out: Path, device: torch.device) -> Path | None:
        """GT next to the model's prediction for two frames (test split if any): ``samples/step_XXXXXX.png``."""
        config = self.config
        if is_pack(self.data):
            split = "test" if "test" in read_pack_meta(self.data)["splits"] else "train"
            dataset: PointCloudDataset | PackedBodies = PackedBodies(self.data, split, subjects=list(self.outfits))
        else:
            split = "test" if DatasetLayout(self.data).iter_frames("test", list(self.outfits)) else "train"
            dataset = PointCloudDataset(self.data, split, num_points=None, subjects=list(self.outfits),
                                        random_subsample=False)  # fmt: skip
        method = self.method(model, config, Normalisation.identity(), out, step,
                             {"outfits": [{"id": i, "name": s} for s, i in self.outfits.items()]})  # fmt: skip
        panels = []
        was_training = model.training
        try:
            for i in sorted({0, len(dataset) // 2}):
                item = self.step_frame(dataset, i, 0)
                subject, seq, fr = item.subject, dataset.frames[i][1], item.frame
                pose = Pose(np.asarray(fr.joints, np.float32), fr.body_vertices, fr.vtransf, item.mean_shape,
                            subject, os.fspath(item.path))  # fmt: skip
                pred = method.predict(pose, 2048, seeds=(0,), outfit=self.outfits[subject])
                sel = np.random.default_rng([config.seed, 3]).choice(len(fr.points), min(2048, len(fr.points)),
                                                                     replace=False)  # fmt: skip
                panels += [(fr.points[sel], None, None, f"data {subject}/{seq}"),
                           (pred.points[0], None, None, f"{config.model}, step {step}")]  # fmt: skip
        finally:
            model.train(was_training)
        if not panels:
            return None
        return Path(render_grid(panels, out / "samples" / f"step_{step:06d}.png", views=("front", "side"), ncols=2))


# ------------------------------------------------------------------------------------- the model
class SkinnedMethod(Method):
    """A trained POP / CloSET: ``outfits`` (list of {"id", "name", "phenotype", "source"} from
    ``meta.json``); predictions are deterministic (a seed only picks the query points)."""

    deterministic = True
    needs_body = True
    train_config = SkinnedTrainConfig

    def __init__(self, model: nn.Module, config: SkinnedTrainConfig, normalisation: Normalisation, path: Path,
                 step: int, meta: dict[str, Any]):  # fmt: skip
        super().__init__(model, config, normalisation, path, step, meta)
        self.outfits = list(meta.get("outfits", []))

    # ------------------------------------------------------------------ loading and training
    @classmethod
    @abstractmethod
    def _model_from_state(cls, config: SkinnedTrainConfig, state: dict[str, torch.Tensor], meta: dict[str, Any]):
        """The network of a checkpoint's config and weights."""

    @classmethod
    def from_checkpoint(cls, ck: Checkpoint, device: str = "cpu", use_ema: bool = True) -> SkinnedMethod:
        state = ck.ema_state if (use_ema and ck.ema_state is not None) else ck.model_state
        try:
            config = SkinnedTrainConfig.from_dict(ck.config)
            outfits = list(ck.meta["outfits"])
            model = cls._model_from_state(config, state, ck.meta)
        except (KeyError, TypeError, RuntimeError) as e:
            raise ValueError(f"{ck.path}: corrupt {cls.kind} checkpoint ({one_line(e)})") from None
        if len(outfits) != int(model.num_outfits):
            raise ValueError(f"{ck.path}: meta lists {len(outfits)} outfits but the weights hold {model.num_outfits}")
        return cls(model.to(device).eval(), config, ck.normalisation, ck.path, ck.step, ck.meta)

    @classmethod
    def presets(cls) -> dict[str, SkinnedTrainConfig]:
        return {n: c for (m, n), c in SKINNED_PRESETS.items() if m == cls.kind}

    @classmethod
    def preset(cls, name: str, decomposition: bool | None = None, **overrides) -> SkinnedTrainConfig:
        return skinned_preset(cls.kind, name, decomposition=decomposition, **overrides)

    @property
    def needs_mean_shape(self) -> bool:
        return False

    # ------------------------------------------------------------------------------ outfits
    def outfit_names(self) -> list[str]:
        return [o["name"] for o in self.outfits]

    # -------------------------------------------------------------------------------- poses
    def load_pose(self, spec: str, outfit: int | None = None, frame_id: int | None = None,
                  any_pose: bool = False) -> Pose:  # fmt: skip
        """``--joints`` for POP / CloSET: a dataset frame ``DATASET:subject/split/sequence/index`` (or
        a frame ``.npz`` of a dataset), or an ``.npz`` with anny ``joint_rotvecs`` (posed with the
        phenotype of ``outfit``'s subject); bare joints are a one-line error (they need the body)."""
        if frame_id is not None:
            raise ValueError(f"{spec}: --frame-id only applies to PocoLoco checkpoints")
        outfit = self.outfit_of_pose_spec(spec, outfit)  # demo:NAME: posed as its outfit
        pheno = self.outfits[outfit].get("phenotype", {}) if outfit is not None else {}
        return load_body_pose(spec, pheno, self.needs_mean_shape)

    def pose_from_frame(self, path: str | Path, subject: str, frame=None, cache: MeanShapeCache | None = None) -> Pose:
        return pose_from_frame(path, subject, self.needs_mean_shape, cache=cache, frame=frame)

    # ---------------------------------------------------------------------------- predicting
    @abstractmethod
    def query_surface(self, num_points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Where on the body the ``num_points`` points of ``predict(..., seeds=(seed,))`` are decoded
        from: face indices (N,) and barycentric coordinates (N, 3) on the model's faces."""

    def even_layout_points(self, pose: Pose, num_points: int, seeds: Sequence[int]) -> np.ndarray:
        """(1, N, 3): the cloud's query points on the posed body (an even cloud is an even set of
        them, not of the decoded points, which would favour points flung off the body)."""
        face_idx, bary = self.query_surface(num_points, int(seeds[0]))
        body = torch.from_numpy(np.asarray(pose.body_vertices, np.float32))[None]
        return barycentric_interpolate(body, self.model.faces.cpu(), torch.as_tensor(face_idx, dtype=torch.long),
                                       torch.as_tensor(bary, dtype=torch.float32)).numpy()  # fmt: skip

    @abstractmethod
    def _predict_one(self, pose: Pose, outfit: int, num_points: int, seed: int, code: torch.Tensor | None = None):
        """The network's output (``points`` (1, N, 3), ``normals`` (1, N, 3), pelvis-centred) in eval mode."""

    @torch.no_grad()
    def predict(self, pose: Pose, num_points: int, seeds: Sequence[int] = (0,), outfit: int | None = None,
                options: SamplerOptions = SamplerOptions(), code: torch.Tensor | None = None) -> SampledClouds:  # fmt: skip
        """One deterministic cloud of ``num_points`` for ``pose`` and ``outfit`` (default: the pose's
        subject), metres, in the frame of ``pose`` (the root joint added back). ``seeds``: one seed,
        which picks the query points. ``code``: outfit features to use instead of ``outfit``'s
        (POP's unseen-outfit fitting: a (1, Cg, Ri, Ri) geometric feature tensor)."""
        if num_points < 1:
            raise ValueError(f"num_points must be >= 1, got {num_points}")
        if len(seeds) != 1:
            raise ValueError(f"{self.title} is deterministic (one cloud per pose and outfit): pass one seed, "
                             f"got {len(seeds)}")  # fmt: skip
        if not pose.has_body:
            raise ValueError(f"{pose.source}: {self.title} needs the posed body (body_vertices / vtransf)")
        outfit = self.default_outfit(pose) if outfit is None else int(outfit)
        model = self.model
        was_training = model.training
        model.eval()
        try:
            out = self._predict_one(pose, outfit, num_points, int(seeds[0]), code=code)
        finally:
            model.train(was_training)
        root = np.asarray(pose.joints[0], np.float32)
        pts = (out.points[0].cpu().numpy() + root).astype(np.float32)
        nrm = out.normals[0].cpu().numpy().astype(np.float32)
        return SampledClouds(pts[None], nrm[None])

    def body_tensors(self, pose: Pose) -> tuple[torch.Tensor, torch.Tensor]:
        """The pose's pelvis-centred body (1, V, 3) and skinning transforms (1, V, 3, 3) on the model's device."""
        dev = self.device
        root = np.asarray(pose.joints[0], np.float32)
        body = torch.from_numpy(np.asarray(pose.body_vertices, np.float32) - root)[None].to(dev)
        vt = torch.from_numpy(np.asarray(pose.vtransf, np.float32))[None].to(dev)
        return body, vt
