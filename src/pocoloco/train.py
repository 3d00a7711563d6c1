"""Training loop of the PocoLoco diffusion model (``pocoloco train --model pocoloco``).

The model learns p(X | K) with the DDPM objective (PocoLoco paper, Eq. 7; Ho et al. 2020,
Eq. 14): each step draws a batch of B clouds X (B, N, 3) with their joints K (B, J, 3), one
timestep t (B,) and noise per sample, and regresses the denoiser's output on the target of the
chosen parametrisation (:func:`pocoloco.diffusion.diffusion_loss`).

What this loop adds to the paper's recipe (Adam 2e-4, batch 16, fp32, constant lr):

* AdamW (weight decay only on matrices; 0 in the ``paper`` preset, i.e. Adam), linear LR
  warm-up then constant or cosine LR, gradient-norm clipping;
* EMA weights with warm-up, ``decay_s = min(ema_decay, (1 + s) / (10 + s))``; samples and
  :func:`pocoloco.checkpoint.load_denoiser` use them;
* optional bf16 autocast, min-SNR-gamma weighting, epsilon / x0 / v prediction;
* exact resume. Everything random in a step is a pure function of ``(seed, step, rank)``:
  the frames of step s are positions ``s*G + r*B + i`` (G = B x world size) of an endless
  sequence of seeded per-epoch permutations, their point subsets are drawn from
  ``default_rng([seed, 1, position])``, and t / noise from a generator seeded by
  ``(seed, 2, step, rank)``. A resumed run therefore needs only the weights, EMA, optimiser
  state and step (the python / numpy / torch RNG states are saved and restored too).
* DistributedDataParallel under ``torchrun`` (NCCL on GPUs, gloo on CPU); ``--batch-size`` is
  per process. Only rank 0 writes logs, samples and checkpoints.

Run folder::

    RUN_DIR/config.json        the TrainConfig of the run
    RUN_DIR/metrics.jsonl      one JSON record per logged step (always written)
    RUN_DIR/tb/                TensorBoard scalars (only if tensorboard is installed)
    RUN_DIR/loss.png           loss curves (refreshed at every checkpoint / sample)
    RUN_DIR/samples/step_XXXXXX.png   DDIM samples from the EMA weights next to the data
    RUN_DIR/checkpoints/       see :mod:`pocoloco.checkpoint`

Entry points: :func:`train` (library), :func:`add_train_arguments` + :func:`cmd_train`
(``pocoloco train``) and ``python -m pocoloco.train`` (for ``torchrun``).
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from pocoloco import checkpoint as ckpt_io
from pocoloco.data.dataset import Normalisation, PointCloudDataset
from pocoloco.diffusion import NoiseSchedule, PerSampleRNG, diffusion_loss, sample_ddim
from pocoloco.diffusion.schedules import PREDICTION_TYPES
from pocoloco.models.pocoloco import DENOISER_PRESETS, PocoLocoDenoiser, PocoLocoDenoiserConfig, denoiser_preset

__all__ = [
    "EMA",
    "MODEL_KINDS",
    "StepBatches",
    "TRAIN_PRESETS",
    "TrainConfig",
    "TrainResult",
    "add_train_arguments",
    "cmd_train",
    "ema_decay_at",
    "lr_at",
    "train",
    "train_preset",
]

MODEL_KINDS = ("pocoloco",)
#: what ``pocoloco train --model`` accepts: PocoLoco here, the peers in :mod:`pocoloco.peers`
ALL_MODEL_KINDS = ("pocoloco", "pop", "closet")
SCHEDULE_KINDS = ("four", "linear", "cosine")
LR_SCHEDULES = ("constant", "cosine")
#: TrainConfig fields that may change when resuming (they do not affect the optimisation).
RESUMABLE_CHANGES = frozenset({"steps", "ckpt_every", "sample_every", "log_every", "sample_steps", "keep_checkpoints",
                               "num_workers"})  # fmt: skip


# ------------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (the data folder and the device excepted).

    preset: name of the denoiser preset (``tiny`` / ``small`` / ``paper``); denoiser: its config
    (with any overrides). steps: total optimiser steps. batch_size: clouds per step *per process*.
    num_points: N points per cloud. lr / weight_decay / adam_betas / adam_eps: AdamW.
    warmup_steps: linear LR warm-up; lr_schedule: ``constant`` or ``cosine`` (to 0 at ``steps``).
    grad_clip: max gradient L2 norm (None: no clipping). ema_decay: EMA decay (warm-up applied).
    schedule / num_timesteps: the beta schedule ("four" = PocoLoco's quartic). prediction_type:
    what the network predicts. min_snr_gamma: min-SNR-gamma weighting (None: plain L_simple).
    bf16: bf16 autocast for the forward pass. seed: everything random derives from it.
    ckpt_every / sample_every / log_every: periods in steps (0 disables checkpoints / samples).
    sample_steps: DDIM steps of the periodic samples. keep_checkpoints: how many step folders to
    keep. num_workers: DataLoader worker processes (0 = load in the main process).
    """

    preset: str = "small"
    denoiser: PocoLocoDenoiserConfig = dataclasses.field(default_factory=lambda: DENOISER_PRESETS["small"])
    model: str = "pocoloco"
    steps: int = 20_000
    batch_size: int = 16
    num_points: int = 1024
    lr: float = 2e-4
    weight_decay: float = 0.0
    adam_betas: tuple[float, float] = (0.9, 0.999)
    adam_eps: float = 1e-8
    warmup_steps: int = 500
    lr_schedule: str = "constant"
    grad_clip: float | None = 1.0
    ema_decay: float = 0.999
    schedule: str = "four"
    num_timesteps: int = 1000
    prediction_type: str = "epsilon"
    min_snr_gamma: float | None = None
    bf16: bool = False
    seed: int = 0
    ckpt_every: int = 1000
    sample_every: int = 1000
    log_every: int = 10
    sample_steps: int = 25
    keep_checkpoints: int = 3
    num_workers: int = 0

    def __post_init__(self):
        if self.model not in MODEL_KINDS:
            raise ValueError(f"unknown model {self.model!r}; choose one of: {', '.join(MODEL_KINDS)}")
        if not isinstance(self.denoiser, PocoLocoDenoiserConfig):
            raise ValueError(f"denoiser must be a PocoLocoDenoiserConfig, got {type(self.denoiser).__name__}")
        positive = ("steps", "batch_size", "num_points", "num_timesteps", "log_every", "sample_steps",
                    "keep_checkpoints")
        for name in positive:
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("warmup_steps", "ckpt_every", "sample_every", "num_workers"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"lr must be a positive number, got {self.lr}")
        if self.weight_decay < 0:
            raise ValueError(f"weight_decay must be >= 0, got {self.weight_decay}")
        if len(self.adam_betas) != 2 or not all(0 <= b < 1 for b in self.adam_betas):
            raise ValueError(f"adam_betas must be two numbers in [0, 1), got {self.adam_betas}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got {self.lr_schedule!r}")
        if self.grad_clip is not None and not self.grad_clip > 0:
            raise ValueError(f"grad_clip must be > 0 or None, got {self.grad_clip}")
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must be in [0, 1), got {self.ema_decay}")
        if self.schedule not in SCHEDULE_KINDS:
            raise ValueError(f"schedule must be one of {SCHEDULE_KINDS}, got {self.schedule!r}")
        if self.prediction_type not in PREDICTION_TYPES:
            raise ValueError(f"prediction_type must be one of {PREDICTION_TYPES}, got {self.prediction_type!r}")
        if self.min_snr_gamma is not None and not self.min_snr_gamma > 0:
            raise ValueError(f"min_snr_gamma must be > 0 or None, got {self.min_snr_gamma}")
        if self.sample_steps > self.num_timesteps:
            raise ValueError(f"sample_steps ({self.sample_steps}) must be <= num_timesteps ({self.num_timesteps})")
        if self.denoiser.prediction_type != self.prediction_type:  # keep the two in sync
            object.__setattr__(self, "denoiser", self.denoiser.replace(prediction_type=self.prediction_type))
        object.__setattr__(self, "adam_betas", tuple(float(b) for b in self.adam_betas))

    def replace(self, **changes) -> TrainConfig:
        """A copy with fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["adam_betas"] = list(self.adam_betas)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise."""
        d = dict(d)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown TrainConfig fields {unknown}")
        if "denoiser" in d:
            d["denoiser"] = PocoLocoDenoiserConfig(**d["denoiser"])
        if "adam_betas" in d:
            d["adam_betas"] = tuple(d["adam_betas"])
        return cls(**d)


TRAIN_PRESETS: dict[str, TrainConfig] = {
    # the paper's settings (Sec. 5.1 + the authors' code): width 512, 8 layers, Adam 2e-4,
    # batch 16, 10K points, constant lr, no clipping; EMA is ours (it does not change training)
    "paper": TrainConfig(
        preset="paper", denoiser=DENOISER_PRESETS["paper"], steps=1_000_000, batch_size=16, num_points=10_000,
        lr=2e-4, weight_decay=0.0, warmup_steps=0, grad_clip=None, ema_decay=0.9999, ckpt_every=5000,
        sample_every=5000, log_every=50, sample_steps=50,
    ),
    # what this 2-core CPU can train in hours
    "small": TrainConfig(
        preset="small", denoiser=DENOISER_PRESETS["small"], steps=20_000, batch_size=16, num_points=512,
        lr=5e-4, weight_decay=0.01, warmup_steps=200, lr_schedule="constant", grad_clip=1.0, ema_decay=0.999,
        ckpt_every=250, sample_every=1000, log_every=10, sample_steps=25,
    ),
    # tests and smoke runs: seconds
    "tiny": TrainConfig(
        preset="tiny", denoiser=DENOISER_PRESETS["tiny"], steps=20, batch_size=2, num_points=256,
        lr=1e-3, weight_decay=0.0, warmup_steps=2, grad_clip=1.0, ema_decay=0.99, ckpt_every=10,
        sample_every=10, log_every=1, sample_steps=3,
    ),
}  # fmt: skip


def train_preset(name: str, **overrides) -> TrainConfig:
    """A named training preset with field overrides; a one-line error for unknown names."""
    if name not in TRAIN_PRESETS:
        raise ValueError(f"unknown training preset {name!r}; choose one of: {', '.join(TRAIN_PRESETS)}")
    return TRAIN_PRESETS[name].replace(**overrides)


# ---------------------------------------------------------------------------- pure schedules
def lr_at(config: TrainConfig, step: int) -> float:
    """Learning rate of optimiser step ``step`` (0-based): linear warm-up, then constant or cosine."""
    if config.warmup_steps and step < config.warmup_steps:
        return config.lr * (step + 1) / config.warmup_steps
    if config.lr_schedule == "cosine":
        span = max(config.steps - config.warmup_steps, 1)
        progress = min(max(step - config.warmup_steps, 0) / span, 1.0)
        return config.lr * 0.5 * (1.0 + math.cos(math.pi * progress))
    return config.lr


def ema_decay_at(ema_decay: float, step: int) -> float:
    """EMA decay after optimiser step ``step`` (0-based): ``min(ema_decay, (1 + step) / (10 + step))``."""
    return min(ema_decay, (1.0 + step) / (10.0 + step))


def _seed_of(*words: int) -> int:
    """A 63-bit seed from integers (numpy SeedSequence hashing)."""
    return int(np.random.SeedSequence([int(w) for w in words]).generate_state(2, np.uint32).astype(np.uint64)
               .dot(np.array([1, 2**32], np.uint64)) >> np.uint64(1))  # fmt: skip


class EMA:
    """Exponential moving average of a module's parameters and buffers (fp32 copy).

    ``update(model, step)``: ema <- d ema + (1 - d) param with d = :func:`ema_decay_at`.
    """

    def __init__(self, model: nn.Module, decay: float):
        self.decay = float(decay)
        self.module = copy.deepcopy(model).eval()
        for p in self.module.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def update(self, model: nn.Module, step: int) -> float:
        d = ema_decay_at(self.decay, step)
        ema_p = list(self.module.parameters())
        src_p = [p.detach() for p in model.parameters()]
        torch._foreach_lerp_(ema_p, src_p, 1.0 - d)
        for e, b in zip(self.module.buffers(), model.buffers(), strict=True):
            e.copy_(b)
        return d

    def state_dict(self) -> dict[str, torch.Tensor]:
        return self.module.state_dict()

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.module.load_state_dict(state)


# ----------------------------------------------------------------------------------------- data
class StepBatches(torch.utils.data.Dataset):
    """The batches of a run, indexed by step: ``batches[step]`` is rank ``rank``'s batch of that step.

    Frame order: global position ``g = step * B * world + rank * B + i`` (i < B) reads frame
    ``perm_e[g mod L]`` of epoch ``e = g // L`` with ``perm_e = default_rng([seed, 0, e]).permutation(L)``
    (every frame once per epoch, across all ranks). Points: N of the frame's points without
    replacement from ``default_rng([seed, 1, g])``. So a batch depends only on (seed, step, rank)
    and is the same with any number of DataLoader workers, and after a resume.

    Items: ``points`` (B, N, C) normalised (C = 3, or 6 with unit normals), ``joints`` (B, J, 3)
    normalised, ``root`` (B, 3) metres, ``index`` (B,) frame indices.
    """

    def __init__(self, dataset: PointCloudDataset, batch_size: int, num_points: int, seed: int, steps: int,
                 rank: int = 0, world_size: int = 1):  # fmt: skip
        if dataset.num_points is not None:
            raise ValueError("StepBatches subsamples points itself: build the dataset with num_points=None")
        self.dataset, self.B, self.N, self.seed = dataset, batch_size, num_points, seed
        self.steps, self.rank, self.world = steps, rank, world_size
        self._perms: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return self.steps

    def frame_indices(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """(B,) global positions and (B,) frame indices of this rank's batch at ``step``."""
        L = len(self.dataset)
        g = step * self.B * self.world + self.rank * self.B + np.arange(self.B, dtype=np.int64)
        idx = np.empty(self.B, dtype=np.int64)
        for k, gk in enumerate(g):
            e = int(gk // L)
            if e not in self._perms:
                if len(self._perms) > 4:
                    self._perms.clear()
                self._perms[e] = np.random.default_rng([self.seed, 0, e]).permutation(L)
            idx[k] = self._perms[e][gk % L]
        return g, idx

    def __getitem__(self, step: int) -> dict[str, torch.Tensor]:
        g, idx = self.frame_indices(int(step))
        pts, jts, roots = [], [], []
        for gk, i in zip(g, idx, strict=True):
            item = self.dataset[int(i)]
            n = item["points"].shape[0]
            if n < self.N:
                path = self.dataset.frames[int(i)][2]
                raise ValueError(f"{path}: frame has {n} points, fewer than num_points={self.N}")
            sel = torch.from_numpy(np.random.default_rng([self.seed, 1, int(gk)]).choice(n, self.N, replace=False))
            p = item["points"][sel]
            if self.dataset.with_normals:
                p = torch.cat([p, item["normals"][sel]], dim=-1)
            pts.append(p)
            jts.append(item["joints"])
            roots.append(item["root"])
        return {"points": torch.stack(pts), "joints": torch.stack(jts), "root": torch.stack(roots),
                "index": torch.from_numpy(idx)}  # fmt: skip


# ------------------------------------------------------------------------------------- logging
class _Logger:
    """metrics.jsonl (always) + TensorBoard (if importable); rank 0 only."""

    def __init__(self, run_dir: Path, resume_step: int | None):
        self.path = run_dir / "metrics.jsonl"
        self.records: list[dict[str, Any]] = []
        if resume_step is not None and self.path.is_file():  # drop records past the checkpoint
            for line in self.path.read_text(encoding="utf-8").splitlines():
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if isinstance(rec, dict) and rec.get("step", math.inf) <= resume_step:
                    self.records.append(rec)
        self.file = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 - closed in close()
        for rec in self.records:
            self.file.write(json.dumps(rec) + "\n")
        self.file.flush()
        self.tb = None
        try:
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(str(run_dir / "tb"), purge_step=resume_step)
        except Exception:  # tensorboard is an optional extra
            self.tb = None

    def log(self, rec: dict[str, Any]) -> None:
        self.records.append(rec)
        self.file.write(json.dumps(rec) + "\n")
        self.file.flush()
        if self.tb is not None:
            for k, v in rec.items():
                if k != "step" and isinstance(v, (int, float)):
                    self.tb.add_scalar(f"train/{k}", v, rec["step"])

    def plot(self, path: Path) -> None:
        from pocoloco.render import plot_curves

        recs = [r for r in self.records if "loss" in r]
        if len(recs) < 1:
            return
        steps = [r["step"] for r in recs]
        curves = {"loss": (steps, [r["loss"] for r in recs])}
        if len(recs) >= 10:  # a running mean reads better than the noisy per-step loss
            k = max(len(recs) // 20, 5)
            ys = np.convolve([r["loss"] for r in recs], np.ones(k) / k, mode="valid")
            curves[f"loss (mean of {k})"] = (steps[k - 1:], ys.tolist())
            # the loss per quarter of [0, T): the low-noise quarter q0 is near 1 for a long time
            # and hides the progress of the others
            for q in range(4):
                sel = [(r["step"], r[f"mse_q{q}"]) for r in recs if f"mse_q{q}" in r]
                if len(sel) >= k:
                    ys = np.convolve([v for _, v in sel], np.ones(k) / k, mode="valid")
                    curves[f"mse, t in quarter {q} (mean of {k})"] = ([s_ for s_, _ in sel][k - 1:], ys.tolist())
        plot_curves(curves, path, logy=True, title="training loss")

    def close(self) -> None:
        self.file.close()
        if self.tb is not None:
            self.tb.close()


# ----------------------------------------------------------------------------------- the loop
@dataclass
class TrainResult:
    """What :func:`train` returns.

    model: the trained raw model (unwrapped from DDP). ema: the EMA model. step: steps done.
    last_checkpoint: folder of the last checkpoint written (None if none / not rank 0).
    steps_per_s: measured over the steps of this call. final_loss: loss of the last step.
    """

    model: PocoLocoDenoiser
    ema: PocoLocoDenoiser
    step: int
    last_checkpoint: Path | None
    steps_per_s: float
    final_loss: float


def _dist_info() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _check_resume_config(stored: TrainConfig, requested: TrainConfig, where: Path) -> None:
    a, b = stored.to_dict(), requested.to_dict()
    diff = [k for k in a if k not in RESUMABLE_CHANGES and a[k] != b.get(k)]
    if diff:
        detail = "; ".join(f"{k}: checkpoint {a[k]!r} vs requested {b.get(k)!r}" for k in diff[:3])
        raise ValueError(f"{where}: cannot resume with a different config ({detail})")


def train(
    config: TrainConfig,
    data: str | os.PathLike,
    out: str | os.PathLike,
    *,
    device: str | torch.device = "cpu",
    resume: bool = False,
    progress: bool = True,
    log_fn=None,
) -> TrainResult:
    """Train the PocoLoco denoiser on the ``train`` split of the dataset at ``data``.

    Args:
        config: the run's :class:`TrainConfig`.
        data: a pocoloco dataset folder (``card.json`` with normalisation stats).
        out: the run folder (created). With ``resume``, training continues from its newest
            checkpoint, which must have the same config (fields in ``RESUMABLE_CHANGES`` excepted)
            and the same dataset normalisation; without it, an existing checkpoint is an error.
        device: where to train (the caller chooses; with DDP the process's device).
        progress: show a rich progress bar (rank 0).
        log_fn: optional callable receiving each metrics record (rank 0).
    If ``torch.distributed`` is initialised, the model is wrapped in DistributedDataParallel and
    every rank trains on its own part of each global batch.
    """
    device = torch.device(device)
    rank, world = _dist_info()
    out = Path(out)
    ckpt_root = out / "checkpoints"
    dataset = PointCloudDataset(data, "train", num_points=None, with_normals=config.denoiser.point_channels == 6,
                                random_subsample=False)  # fmt: skip
    norm = dataset.normalisation

    # ---- resume or fresh start -------------------------------------------------------------
    start_step, ck = 0, None
    existing = ckpt_io.latest_checkpoint(ckpt_root)
    if resume:
        if existing is None:
            raise ValueError(f"{out}: --resume but no checkpoint in {ckpt_root}")
        ck = ckpt_io.load_checkpoint(existing, expect_model=config.model, expect_preset=config.preset)
        _check_resume_config(TrainConfig.from_dict(ck.config), config, ck.path)
        if ck.normalisation != norm:
            raise ValueError(f"{data}: dataset normalisation differs from the checkpoint's ({ck.path})")
        start_step = ck.step
        if start_step > config.steps:
            raise ValueError(f"{ck.path}: checkpoint is at step {start_step}, past --steps {config.steps}")
    elif existing is not None:
        raise ValueError(f"{out}: already holds checkpoints; pass --resume or choose another --out")

    torch.manual_seed(config.seed)
    model = PocoLocoDenoiser(config.denoiser)
    if ck is not None:
        model.load_state_dict(ck.model_state)
    model.to(device)
    ema = EMA(model, config.ema_decay)
    if ck is not None and ck.ema_state is not None:
        ema.load_state_dict(ck.ema_state)
    decay, no_decay = [], []
    for p in model.parameters():
        (decay if p.ndim >= 2 else no_decay).append(p)
    optimizer = torch.optim.AdamW(
        [{"params": decay, "weight_decay": config.weight_decay}, {"params": no_decay, "weight_decay": 0.0}],
        lr=lr_at(config, start_step), betas=config.adam_betas, eps=config.adam_eps,
    )  # fmt: skip
    if ck is not None and ck.optimizer_state is not None:
        optimizer.load_state_dict(ck.optimizer_state)
    if ck is not None and ck.rng_state is not None:
        ckpt_io.restore_rng_state(ck.rng_state)

    net: nn.Module = model
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel

        net = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)

    schedule = NoiseSchedule.from_kind(config.schedule, config.num_timesteps)
    batches = StepBatches(dataset, config.batch_size, config.num_points, config.seed, config.steps, rank, world)
    loader = torch.utils.data.DataLoader(
        batches, batch_size=None, sampler=range(start_step, config.steps), num_workers=config.num_workers,
        pin_memory=device.type == "cuda",
    )  # fmt: skip

    # ---- rank-0 outputs ---------------------------------------------------------------------
    logger = None
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        from pocoloco.utils.atomic import write_json_atomic

        write_json_atomic(out / "config.json", {"data": os.fspath(data), "world_size": world, **config.to_dict()})
        logger = _Logger(out, start_step if ck is not None else None)
    sample_frames = _sample_frames(data, config, dataset) if rank == 0 and config.sample_every else None

    def save(step: int) -> Path:
        return ckpt_io.save_checkpoint(
            ckpt_root, step, model_kind=config.model, preset=config.preset, config=config.to_dict(),
            normalisation=norm, model_state=model.state_dict(), ema_state=ema.state_dict(),
            optimizer_state=optimizer.state_dict(), rng_state=ckpt_io.capture_rng_state(),
            extra={"world_size": world, "data": os.fspath(data)}, keep=config.keep_checkpoints,
        )  # fmt: skip

    def autocast():
        return torch.autocast(device.type, dtype=torch.bfloat16) if config.bf16 else contextlib.nullcontext()

    weighting = "min_snr" if config.min_snr_gamma is not None else "none"
    gen = torch.Generator(device)
    bar = _progress_bar(progress and rank == 0, start_step, config.steps)
    last_ckpt, saved_step, loss_val, t0, step = None, None, float("nan"), time.perf_counter(), start_step
    model.train()
    try:
        for step, batch in zip(range(start_step, config.steps), loader, strict=True):
            lr = lr_at(config, step)
            for group in optimizer.param_groups:
                group["lr"] = lr
            x0 = batch["points"].to(device, non_blocking=True)  # (B, N, C)
            joints = batch["joints"].to(device, non_blocking=True)  # (B, J, 3)
            gen.manual_seed(_seed_of(config.seed, 2, step, rank))
            with autocast():
                loss, logs = diffusion_loss(net, x0, joints, schedule, config.prediction_type, weighting,
                                            config.min_snr_gamma or 5.0, generator=gen)  # fmt: skip
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            gnorm = (torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
                     if config.grad_clip is not None else _grad_norm(model))  # fmt: skip
            optimizer.step()
            decay_now = ema.update(model, step)
            done = step + 1
            loss_val = logs["loss"]
            if not math.isfinite(loss_val):
                raise FloatingPointError(f"loss is {loss_val} at step {done}; lower --lr or check the data")

            if done % config.log_every == 0 or done == config.steps:
                if world > 1:
                    lt = torch.tensor([loss_val], device=device)
                    dist.all_reduce(lt)
                    loss_val = float(lt) / world
                if rank == 0:
                    elapsed = time.perf_counter() - t0
                    rec = {"step": done, "loss": loss_val, **{k: v for k, v in logs.items() if k.startswith("mse")},
                           "lr": lr, "grad_norm": float(gnorm), "ema_decay": decay_now,
                           "steps_per_s": (done - start_step) / max(elapsed, 1e-9), "time": elapsed}  # fmt: skip
                    logger.log(rec)
                    if log_fn is not None:
                        log_fn(rec)
            if rank == 0:
                bar.advance(loss_val)
                if config.sample_every and done % config.sample_every == 0:
                    _render_samples(ema.module, schedule, config, norm, sample_frames, out, done, device)
                    logger.plot(out / "loss.png")
                if config.ckpt_every and done % config.ckpt_every == 0:
                    last_ckpt, saved_step = save(done), done
                    logger.plot(out / "loss.png")
            step = done
        if rank == 0 and step > start_step and saved_step != step:
            last_ckpt = save(step)
            logger.plot(out / "loss.png")
    finally:
        bar.close()
        if logger is not None:
            logger.close()
    if world > 1:
        dist.barrier()
    elapsed = time.perf_counter() - t0
    return TrainResult(model=model, ema=ema.module, step=step, last_checkpoint=last_ckpt,
                       steps_per_s=(step - start_step) / max(elapsed, 1e-9), final_loss=loss_val)  # fmt: skip


def _grad_norm(model: nn.Module) -> torch.Tensor:
    grads = [p.grad.detach().norm() for p in model.parameters() if p.grad is not None]
    return torch.stack(grads).norm() if grads else torch.zeros(())


class _progress_bar:
    """A rich progress bar (or nothing)."""

    def __init__(self, enabled: bool, start: int, total: int):
        self.bar = None
        if not enabled:
            return
        from rich import progress as rp

        self.bar = rp.Progress(rp.TextColumn("train"), rp.BarColumn(), rp.MofNCompleteColumn(),
                               rp.TextColumn("loss {task.fields[loss]}"), rp.TimeElapsedColumn(),
                               rp.TimeRemainingColumn())  # fmt: skip
        self.bar.start()
        self.task = self.bar.add_task("train", total=total, completed=start, loss="-")

    def advance(self, loss: float) -> None:
        if self.bar is not None:
            self.bar.update(self.task, advance=1, loss=f"{loss:.4f}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def _sample_frames(data, config: TrainConfig, train_set: PointCloudDataset) -> list[dict[str, Any]]:
    """Two frames (test split if it has any, else train) with fixed point subsets, for the periodic samples."""
    try:
        ds = PointCloudDataset(data, "test", num_points=None, random_subsample=False)
    except ValueError:
        ds = train_set
    picks = sorted({0, len(ds) // 2})
    frames = []
    for i in picks:
        item = ds[i]
        n = item["points"].shape[0]
        sel = np.random.default_rng([config.seed, 3, i]).choice(n, min(n, config.num_points), replace=False)
        frames.append({"points": item["points"][sel], "joints": item["joints"], "root": item["root"],
                       "key": item["frame_key"]})  # fmt: skip
    return frames


@torch.no_grad()
def _render_samples(model: PocoLocoDenoiser, schedule: NoiseSchedule, config: TrainConfig, norm: Normalisation,
                    frames: list[dict[str, Any]], out: Path, step: int, device: torch.device) -> Path:  # fmt: skip
    """DDIM samples (``config.sample_steps`` steps, fixed seeds) from ``model`` for ``frames``; a PNG grid."""
    from pocoloco.render import render_grid

    C = config.denoiser.point_channels
    joints = torch.stack([f["joints"] for f in frames]).to(device)  # (B, J, 3)
    rng = PerSampleRNG([config.seed * 1000 + k for k in range(len(frames))], device=device)
    noise = rng.randn((config.num_points, C), device=device)  # (B, N, C)
    was_training = model.training
    model.eval()
    x = sample_ddim(model, schedule, noise, joints, prediction_type=config.prediction_type,
                    steps=config.sample_steps, rng=rng)  # fmt: skip
    model.train(was_training)
    clouds = []
    for k, f in enumerate(frames):
        root = f["root"].numpy()
        gt = norm.denormalise(f["points"].numpy(), root)
        pred = norm.denormalise(x[k, :, :3].float().cpu().numpy(), root)
        clouds += [(gt, None, None, f"data {f['key']}"), (pred, None, None, f"sample, step {step}")]
    return Path(render_grid(clouds, out / "samples" / f"step_{step:06d}.png", views=("front", "side"), ncols=2))


# -------------------------------------------------------------------------------- entry points
def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``pocoloco train`` options to ``parser`` (its handler is :func:`cmd_train`)."""
    parser.add_argument("--model", default="pocoloco", choices=ALL_MODEL_KINDS,
                        help="model to train: pocoloco (diffusion) or the peers pop / closet (pocoloco.peers)")  # fmt: skip
    parser.add_argument("--data", required=True, help="pocoloco dataset folder (trains on its train split)")
    parser.add_argument("--preset", default=None, help=f"training preset: {', '.join(TRAIN_PRESETS)} "
                        "(default: small; with --resume, the checkpoint's)")  # fmt: skip
    parser.add_argument("--out", required=True, help="run folder (checkpoints, logs, samples)")
    parser.add_argument("--steps", type=int, help="total optimiser steps")
    parser.add_argument("--batch-size", type=int, help="clouds per step per process")
    parser.add_argument("--lr", type=float, help="peak learning rate")
    parser.add_argument("--num-points", type=int, help="points per cloud")
    parser.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in --out")
    parser.add_argument("--bf16", action="store_true", default=None, help="bf16 autocast")
    parser.add_argument("--seed", type=int)
    parser.add_argument("--ckpt-every", type=int, help="checkpoint period in steps (0: only at the end)")
    parser.add_argument("--sample-every", type=int, help="rendered-sample period in steps (0: never)")
    parser.add_argument("--log-every", type=int, help="metrics period in steps")
    parser.add_argument("--schedule", choices=SCHEDULE_KINDS, help="beta schedule (four = PocoLoco's quartic)")
    parser.add_argument("--prediction-type", choices=PREDICTION_TYPES, help="network target")
    parser.add_argument("--min-snr", type=float, metavar="GAMMA", help="min-SNR-gamma loss weighting (e.g. 5)")
    parser.add_argument("--workers", type=int, help="DataLoader worker processes")
    parser.add_argument("--device", default=None, help="cuda, cuda:1, cpu (default: cuda if available)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch CPU threads per process (default: cores / processes)")  # fmt: skip
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    from pocoloco.peers import add_peer_train_arguments

    add_peer_train_arguments(parser)


def _config_from_args(args: argparse.Namespace) -> TrainConfig:
    overrides = {
        "steps": args.steps, "batch_size": args.batch_size, "lr": args.lr, "num_points": args.num_points,
        "bf16": args.bf16, "seed": args.seed, "ckpt_every": args.ckpt_every, "sample_every": args.sample_every,
        "log_every": args.log_every, "schedule": args.schedule, "prediction_type": args.prediction_type,
        "min_snr_gamma": args.min_snr, "num_workers": args.workers,
    }  # fmt: skip
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if args.preset is None and args.resume:
        found = ckpt_io.latest_checkpoint(Path(args.out) / "checkpoints")
        if found is None:
            raise ValueError(f"{args.out}: --resume but no checkpoint in {Path(args.out) / 'checkpoints'}")
        meta = ckpt_io.load_checkpoint(found, expect_model=args.model, training_state=False)
        return TrainConfig.from_dict(meta.config).replace(**overrides)
    return train_preset(args.preset or "small", model=args.model, **overrides)


def _init_distributed(device_arg: str | None) -> tuple[torch.device, bool]:
    """Choose the device and, under torchrun (WORLD_SIZE > 1), initialise the process group."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if device_arg is None:
        device = torch.device(f"cuda:{local_rank}" if torch.cuda.is_available() and world > 1 else
                              "cuda" if torch.cuda.is_available() else "cpu")  # fmt: skip
    else:
        device = torch.device(device_arg)
        if device.type == "cuda" and world > 1 and device.index is None:
            device = torch.device(f"cuda:{local_rank}")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"--device {device_arg}: CUDA is not available")
        torch.cuda.set_device(device)
    started = False
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        started = True
    return device, started


def cmd_train(args: argparse.Namespace) -> None:
    """``pocoloco train``: build the config from the preset and options, choose the device, train.
    ``--model pop|closet`` trains the peers (:func:`pocoloco.peers.cmd_train_peer`)."""
    from pocoloco.peers import PEER_KINDS, cmd_train_peer

    if args.model in PEER_KINDS:
        return cmd_train_peer(args)
    for flag, value in (("--no-decomposition", getattr(args, "no_decomposition", False)),
                        ("--normal-start", getattr(args, "normal_start", None)),
                        ("--query-points", getattr(args, "query_points", None)),
                        ("--subjects", getattr(args, "subjects", None))):  # fmt: skip
        if value not in (None, False):
            raise ValueError(f"{flag} applies to --model pop / closet only")
    if args.model not in MODEL_KINDS:
        raise ValueError(f"unknown model {args.model!r}; choose one of: {', '.join(MODEL_KINDS)}")
    from pocoloco.data.format import read_card

    read_card(args.data)  # fail early (one line) if --data is not a dataset
    config = _config_from_args(args)
    device, started = _init_distributed(args.device)
    rank, world = _dist_info()
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", str(world)))
    if args.threads is not None:
        torch.set_num_threads(max(1, args.threads))
    elif device.type == "cpu" and "OMP_NUM_THREADS" not in os.environ:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // max(local_world, 1)))
    try:
        if rank == 0:
            from rich.console import Console

            n_params = sum(p.numel() for p in PocoLocoDenoiser(config.denoiser).parameters())
            Console(stderr=True).print(
                f"[bold]pocoloco train[/] model={config.model} preset={config.preset} params={n_params:,} "
                f"device={device} world={world} threads={torch.get_num_threads()} steps={config.steps} "
                f"batch={config.batch_size}x{world} N={config.num_points} -> {args.out}"
            )  # fmt: skip
        result = train(config, args.data, args.out, device=device, resume=args.resume,
                       progress=not args.no_progress)  # fmt: skip
        if rank == 0:
            print(f"trained to step {result.step} ({result.steps_per_s:.2f} steps/s), loss {result.final_loss:.4f}; "
                  f"checkpoint {result.last_checkpoint}")  # fmt: skip
    finally:
        if started:
            dist.destroy_process_group()


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m pocoloco.train`` (what ``torchrun`` launches); same options as ``pocoloco train``."""
    parser = argparse.ArgumentParser(prog="python -m pocoloco.train", description=__doc__.splitlines()[0])
    add_train_arguments(parser)
    args = parser.parse_args(argv)
    from .cli import run_command

    return run_command(cmd_train, args, prog="pocoloco train")


if __name__ == "__main__":
    sys.exit(main())
