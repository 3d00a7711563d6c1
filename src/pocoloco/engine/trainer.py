"""The one training loop every method trains with (``pocoloco train --model pocoloco|pop|closet``).

A method gives the loop a :class:`TrainingTask`: how to build its network and optimiser, the
batch of each step, and the loss of a batch. The loop owns everything else, the same for all:

* the learning rate of every step: linear warm-up, then constant or cosine (:func:`lr_at`);
  an optimiser's parameter groups keep their ratios to the config's ``lr`` (POP's features
  learn at 5e-4 while its network learns at 3e-4);
* gradient-norm clipping (``grad_clip``; the norm is logged either way);
* EMA weights with warm-up, ``decay_s = min(ema_decay, (1 + s) / (10 + s))`` (``ema_decay``
  None: no EMA, the checkpoint's weights are the trained ones);
* bf16 autocast of the loss's forward pass (``bf16``);
* DistributedDataParallel under ``torchrun`` (NCCL on GPUs, gloo on CPU); ``batch_size`` is per
  process; only rank 0 writes logs, previews and checkpoints;
* atomic checkpoints (:mod:`pocoloco.engine.checkpoint`) with optimiser and RNG state, and a
  bit-exact ``resume``: everything random in a step is a pure function of ``(seed, step, rank)``
  (the batch order of :class:`pocoloco.data.step_batches.StepBatches`, and whatever the task
  seeds from :func:`pocoloco.utils.seeding.seed_of`), so a resumed run needs only the weights,
  EMA, optimiser state and step; a damaged newest checkpoint falls back to the newest intact one,
  and temporaries of an interrupted save are removed on start;
* logging: ``metrics.jsonl`` (always), TensorBoard scalars (if installed), ``loss.png``, a rich
  progress bar, and the task's rendered previews.

Run folder::

    RUN_DIR/config.json        the run's config (+ data folder, world size)
    RUN_DIR/metrics.jsonl      one JSON record per logged step
    RUN_DIR/tb/                TensorBoard scalars (only if tensorboard is installed)
    RUN_DIR/loss.png           loss curves (refreshed at every checkpoint / preview)
    RUN_DIR/samples/step_XXXXXX.png   the task's previews next to the data
    RUN_DIR/checkpoints/       see :mod:`pocoloco.engine.checkpoint`

The config a task carries is the method's frozen dataclass (a :class:`pocoloco.utils.config.Config`:
``to_dict()`` / ``from_dict()`` store it in checkpoints); the loop reads only what its ``loop()``
returns, one typed :class:`LoopSettings` (steps, learning-rate curve, EMA, clipping, bf16, periods).

Why this module is long: it is the one loop every method trains with, and the pieces above (the
schedules, EMA, logging, run-folder checks, the task contract) exist only for it; split across
modules they would each need the others' internals.
"""

from __future__ import annotations

import contextlib
import copy
import json
import math
import os
import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from pocoloco.data.dataset import Normalisation
from pocoloco.engine import checkpoint as ckpt_io
from pocoloco.utils.atomic import write_json_atomic
from pocoloco.utils.hardware import available_memory_bytes
from pocoloco.utils.progress import Progress
from pocoloco.viz.render import plot_curves

__all__ = [
    "frozen",
    "EMA",
    "Logger",
    "LoopSettings",
    "TrainResult",
    "TrainingTask",
    "check_run_folder",
    "dist_info",
    "ema_decay_at",
    "export_run",
    "fused_optimizer_options",
    "scaled_lr",
    "init_distributed",
    "lr_at",
    "train",
]


@contextlib.contextmanager
def frozen(model: nn.Module):
    """``model`` in eval mode with every parameter's ``requires_grad`` off for the block (fitting a
    new outfit code or geometric features against a frozen network); both restored after."""
    was_training = model.training
    flags = {n: p.requires_grad for n, p in model.named_parameters()}
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    try:
        yield model
    finally:
        model.train(was_training)
        for n, p in model.named_parameters():
            p.requires_grad_(flags[n])


#: share of the free memory a training step may plan to use
TRAIN_MEMORY_SHARE = 0.8


# ---------------------------------------------------------------------------- the loop's settings
@dataclass(frozen=True)
class LoopSettings:
    """What the loop reads from a method's train config (its ``loop()``): ``lr`` is the rate the
    optimiser's groups scale with; warm-up / schedule / decay: :func:`lr_at`; ``ema_decay`` /
    ``grad_clip`` None: off; ``*_every`` 0: never; ``num_workers``: DataLoader processes."""

    preset: str
    steps: int
    lr: float
    seed: int
    warmup_steps: int
    lr_schedule: str
    decay_steps: int
    ema_decay: float | None
    grad_clip: float | None
    bf16: bool
    ckpt_every: int
    sample_every: int
    log_every: int
    keep_checkpoints: int
    num_workers: int


# ---------------------------------------------------------------------------- pure schedules
def lr_at(config: LoopSettings, step: int, time_share: float | None = None) -> float:
    """Learning rate of optimiser step ``step`` (0-based): linear warm-up over ``warmup_steps``,
    then constant, cosine (to 0 at ``steps``) or ``wsd``: constant, then linear to 0 over the
    last ``decay_steps`` (warm-up / stable / decay, Hu et al. 2024, MiniCPM).

    ``time_share`` (share of a time budget used so far, wsd only): the decay also runs on the
    clock, over the same share of the budget as ``decay_steps`` is of ``steps``, and the lower of
    the two rates is taken, so a run on a machine slower than planned still ends cooled down (in its
    warm-up too)."""
    warmup, schedule = config.warmup_steps, config.lr_schedule
    # the clock's rate (wsd with a time budget): level, then linear to 0 over the last decay share
    clock = (config.lr * min(1.0, max(1.0 - time_share, 0.0) * config.steps / config.decay_steps)
             if schedule == "wsd" and time_share is not None else math.inf)  # fmt: skip
    if warmup and step < warmup:
        return min(config.lr * (step + 1) / warmup, clock)
    if schedule == "cosine":
        span = max(config.steps - warmup, 1)
        progress = min(max(step - warmup, 0) / span, 1.0)
        return config.lr * 0.5 * (1.0 + math.cos(math.pi * progress))
    if schedule == "wsd":
        start = config.steps - config.decay_steps
        by_steps = config.lr * max(config.steps - step, 0) / config.decay_steps if step >= start else config.lr
        return min(by_steps, clock)
    return config.lr


#: the learning-rate curves :func:`lr_at` draws
LR_SCHEDULES = ("constant", "cosine", "wsd")


def check_lr_schedule(lr_schedule: str, decay_steps: int, steps: int) -> None:
    """One-line ValueError unless ``lr_schedule`` is one of :data:`LR_SCHEDULES` and ``decay_steps``
    an integer >= 0 (wsd: 0 < decay_steps <= steps); what every training config checks."""
    if lr_schedule not in LR_SCHEDULES:
        raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got {lr_schedule!r}")
    if isinstance(decay_steps, bool) or not isinstance(decay_steps, int) or decay_steps < 0:
        raise ValueError(f"decay_steps must be an integer >= 0, got {decay_steps!r}")
    if lr_schedule == "wsd" and not 0 < decay_steps <= steps:
        raise ValueError(f"lr_schedule wsd needs 0 < decay_steps <= steps, got decay_steps={decay_steps} "
                         f"and steps={steps} (pass --decay-steps, or another --lr-schedule)")  # fmt: skip


LR_SCALING_RULES = ("sqrt", "linear", "none")


def scaled_lr(lr: float, batch_size: int, base_batch_size: int, rule: str = "sqrt") -> float:
    """The learning rate for ``batch_size`` clouds per step of a recipe tuned at ``base_batch_size``:
    ``sqrt`` (Adam's square-root rule: the gradient noise falls as 1/sqrt(B); Malladi et al.,
    NeurIPS 2022), ``linear`` (SGD's rule; Goyal et al. 2017) or ``none``."""
    if rule not in LR_SCALING_RULES:
        raise ValueError(f"lr scaling rule must be one of {LR_SCALING_RULES}, got {rule!r}")
    ratio = batch_size / base_batch_size
    return lr * (math.sqrt(ratio) if rule == "sqrt" else ratio if rule == "linear" else 1.0)


def fused_optimizer_options(model: nn.Module) -> dict[str, Any]:
    """``{"fused": True}`` for Adam / AdamW when the model's parameters are on a GPU (one kernel for
    all parameters instead of a loop over them); ``{}`` on the CPU, where the loop is kept so that
    resumed runs stay bit-exact with earlier ones."""
    p = next(model.parameters(), None)
    return {"fused": True} if p is not None and p.is_cuda else {}


#: config fields that shape the learning-rate curve: they may change on resume only if the curve
#: of the steps already taken stays the same
LR_FIELDS = ("steps", "lr_schedule", "decay_steps")


def ema_decay_at(ema_decay: float, step: int) -> float:
    """EMA decay after optimiser step ``step`` (0-based): ``min(ema_decay, (1 + step) / (10 + step))``."""
    return min(ema_decay, (1.0 + step) / (10.0 + step))


class EMA:
    """Exponential moving average of a module's parameters (fp32 copy); buffers are copied.

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


# ------------------------------------------------------------------------------------ the task
class TrainingTask(ABC):
    """What a method gives the loop: one training run of one method on one dataset.

    Attributes:
        config: the method's train config (fields: module docstring).
        data: the dataset it trains on (a folder, an opened dataset or a training pack; recorded).
        kind: the checkpoints' ``model_kind`` (``config.model``).
        normalisation: the dataset's, stored in every checkpoint.
        resumable_changes: config fields that may differ on ``--resume``.
        ddp_find_unused: wrap in DDP with ``find_unused_parameters`` (some parameters get no
            gradient in some steps, e.g. POP's normal head before its normal loss is on).
    """

    config: Any
    data: str | os.PathLike
    kind: str
    normalisation: Normalisation
    resumable_changes: frozenset[str] = frozenset({"steps", "ckpt_every", "sample_every", "log_every",
                                                   "keep_checkpoints", "num_workers"})  # fmt: skip
    ddp_find_unused: bool = False

    def step_bytes(self) -> int | None:
        """Working memory of one training step (activations kept for backward), checked against the
        device's free memory before training; None where the method cannot tell."""
        return None

    @abstractmethod
    def build_model(self) -> nn.Module:
        """A fresh network (torch's global RNG was just seeded with ``config.seed``)."""

    @abstractmethod
    def make_optimizer(self, model: nn.Module) -> torch.optim.Optimizer:
        """The optimiser; its groups' ``lr`` are base rates scaled by :func:`lr_at` / ``config.lr``."""

    @abstractmethod
    def step_batches(self, model: nn.Module, rank: int, world: int) -> torch.utils.data.Dataset:
        """A map-style dataset: item ``step`` is this rank's batch of that step (a pure function of
        ``(config.seed, step, rank)``); tensors or objects with ``.to(device)``."""

    @abstractmethod
    def loss(self, net: nn.Module, batch: Any, step: int, rank: int) -> tuple[torch.Tensor, dict[str, float]]:
        """The differentiable loss of ``batch`` (on the device) and floats to log (``"loss"`` first).
        ``net`` is the model, or its DDP wrapper: call it, not the model, for the forward pass."""

    def check_resume(self, ck: ckpt_io.Checkpoint) -> None:
        """Raise a one-line ValueError if ``ck`` cannot continue this run (data differ, ...)."""

    def checkpoint_extra(self, model: nn.Module) -> dict[str, Any]:
        """More JSON metadata for every checkpoint's ``meta.json``."""
        return {}

    def initial_state(self, state: dict[str, torch.Tensor], ck: ckpt_io.Checkpoint) -> dict[str, torch.Tensor]:
        """The weights of ``ck`` as this run starts from them (``--init-from``); e.g. per-outfit rows
        matched by outfit name when the run trains another set of outfits. Default: unchanged."""
        return state

    def fresh_keys(self, missing: list[str]) -> bool:
        """``--init-from``: may these tensors, absent from the source checkpoint, keep this run's own
        initialisation (a new part that starts as a no-op)? Default: no (a one-line error)."""
        return False

    def log_extra(self, step: int) -> dict[str, Any]:
        """More fields for the metrics record of (0-based) ``step``."""
        return {}

    def preview(self, model: nn.Module, step: int, out: Path, device: torch.device) -> Path | None:
        """Render what ``model`` (the EMA model if any) makes of a few frames to ``out/samples``."""
        return None


# ------------------------------------------------------------------------------------- logging
class Logger:
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


# ------------------------------------------------------------------------------ distributed
def dist_info() -> tuple[int, int]:
    """(rank, world size); (0, 1) outside ``torch.distributed``."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def init_distributed(device_arg: str | None) -> tuple[torch.device, bool]:
    """Choose the device and, under torchrun (WORLD_SIZE > 1), initialise the process group
    (NCCL on GPUs, gloo on CPU). Returns (device, whether this call started the group)."""
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
        if device.index is not None:  # "cuda" alone: the current device (set_device wants an index)
            torch.cuda.set_device(device)
    started = False
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        started = True
    return device, started


# ----------------------------------------------------------------------------------- the loop
@dataclass
class TrainResult:
    """What :func:`train` returns.

    model: the trained raw model (unwrapped from DDP). ema: the EMA model (the model itself
    without EMA). step: steps done. last_checkpoint: folder of the last checkpoint written (None
    if none / not rank 0). steps_per_s: over the steps of this call. final_loss: of the last step.
    """

    model: nn.Module
    ema: nn.Module
    step: int
    last_checkpoint: Path | None
    steps_per_s: float
    final_loss: float
    stopped_by_budget: bool = False
    export: Path | None = None


def check_run_folder(out: str | os.PathLike, resume: bool) -> Path | None:
    """One-line errors before any work: ``resume`` without a checkpoint in ``out``, or a fresh run
    into a folder that holds checkpoints. Returns the newest checkpoint (None for a fresh run)."""
    ckpt_root = Path(out) / "checkpoints"
    existing = ckpt_io.latest_checkpoint(ckpt_root)
    if resume and existing is None:
        raise ValueError(f"{out}: --resume but no checkpoint in {ckpt_root}")
    if not resume and existing is not None:
        raise ValueError(f"{out}: already holds checkpoints; pass --resume or choose another --out")
    return existing


def _check_resume_config(task: TrainingTask, ck: ckpt_io.Checkpoint) -> None:
    stored = type(task.config).from_dict(ck.config)
    a, b = stored.to_dict(), task.config.to_dict()
    diff = [k for k in a if k not in task.resumable_changes and k not in LR_FIELDS and a[k] != b.get(k)]
    if diff:
        detail = "; ".join(f"{k}: checkpoint {a[k]!r} vs requested {b.get(k)!r}" for k in diff[:3])
        raise ValueError(f"{ck.path}: cannot resume with a different config ({detail})")
    lr_changes = [k for k in LR_FIELDS if k in a and a[k] != b.get(k)]
    if lr_changes:  # a new LR curve is fine if the steps already taken saw the same one
        old, new = stored.loop(), task.config.loop()
        changed = next((s for s in range(ck.step) if lr_at(old, s) != lr_at(new, s)), None)
        if changed is not None:
            raise ValueError(f"{ck.path}: cannot resume with {', '.join(lr_changes)} changed: the learning rate of "
                             f"step {changed} (already taken) would change from {lr_at(old, changed):.3g} to "
                             f"{lr_at(new, changed):.3g}")  # fmt: skip


def _to_device(batch: Any, device: torch.device) -> Any:
    if isinstance(batch, dict):
        return {k: v.to(device, non_blocking=True) if torch.is_tensor(v) else v for k, v in batch.items()}
    return batch.to(device)


def _grad_norm(model: nn.Module) -> torch.Tensor:
    grads = [p.grad.detach().norm() for p in model.parameters() if p.grad is not None]
    return torch.stack(grads).norm() if grads else torch.zeros(())


def load_initial_weights(model: nn.Module, path: str | os.PathLike, task: TrainingTask) -> str:
    """Load the weights of the checkpoint ``path`` (EMA if it has them, through
    ``task.initial_state``) into ``model`` for fine-tuning; one-line errors for another model kind or
    another network. Returns the checkpoint folder."""
    ck = ckpt_io.load_checkpoint(path, expect_model=task.kind, training_state=False)
    state = task.initial_state(ck.ema_state if ck.ema_state is not None else ck.model_state, ck)
    own = model.state_dict()
    missing, extra = sorted(set(own) - set(state)), sorted(set(state) - set(own))
    fresh = missing and task.fresh_keys(missing)
    if fresh:  # new zero-initialised parts keep this run's initialisation
        state = {**state, **{k: own[k] for k in missing}}
        missing = []
    shapes = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if missing or extra or shapes:
        what = (f"{len(missing)} tensor(s) missing, e.g. {missing[0]}" if missing else
                f"{len(extra)} tensor(s) this network lacks, e.g. {extra[0]}" if extra else
                f"{shapes[0]} is {tuple(state[shapes[0]].shape)}, this run's is {tuple(own[shapes[0]].shape)}")
        raise ValueError(f"--init-from {path}: its network differs from this run's ({what})")
    model.load_state_dict({k: v.to(own[k].dtype) for k, v in state.items()})
    return os.fspath(ck.path)


def train(
    task: TrainingTask,
    out: str | os.PathLike,
    *,
    device: str | torch.device = "cpu",
    resume: bool = False,
    progress: bool = True,
    log_fn=None,
    time_budget_s: float | None = None,
    compile_model: bool = False,
    export_to: str | os.PathLike | None = None,
    init_from: str | os.PathLike | None = None,
) -> TrainResult:
    """Run ``task`` into the run folder ``out`` (its ``data`` is recorded in config.json and checkpoints).

    Args:
        device: where to train (the caller chooses; with DDP the process's device). On CUDA,
            matmuls and convolutions run in TF32 and the logged floats are read from the device
            only at log steps (no host synchronisation per step).
        time_budget_s: stop after the first step that ends this many seconds of training into
            the run (model building and data loading excluded; a resume counts the seconds its
            checkpoint records, ``meta['train_seconds']``), with the usual final checkpoint.
            With the ``wsd`` schedule the decay also runs on this clock (:func:`lr_at`), so the
            run ends cooled down whether the machine is faster or slower than ``steps`` assumed;
            other schedules run to ``config.steps`` (choose ``steps`` to fit).
        compile_model: run the forward pass through ``torch.compile`` (single process only).
        export_to: after training, write a sampling-only copy of the last checkpoint there
            (:func:`pocoloco.engine.checkpoint.export_for_sampling`, replacing an older copy).
        init_from: start a fresh run from the weights of this checkpoint (its EMA weights if it has
            them) instead of a random network: fine-tuning. It must be of the task's model kind with
            the same network; optimiser, step and schedule start afresh. Recorded in config.json and
            in every checkpoint's meta (``init_from``); ignored on ``resume`` (the run's own weights).
        resume: continue from the newest intact checkpoint in ``out``, which must have the same
            config (``task.resumable_changes`` excepted) and pass ``task.check_resume``;
            without it, an existing checkpoint is an error.
        progress: show a rich progress bar (rank 0). log_fn: called with each metrics record.
    If ``torch.distributed`` is initialised, the model is wrapped in DistributedDataParallel and
    every rank trains on its own part of each global batch.
    """
    config, data = task.config.loop(), os.fspath(task.data)
    device = torch.device(device)
    if time_budget_s is not None and not time_budget_s > 0:
        raise ValueError(f"time budget must be > 0 seconds, got {time_budget_s}")
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    rank, world = dist_info()
    out = Path(out)
    ckpt_root = out / "checkpoints"
    if rank == 0:
        ckpt_io.clean_stale_temporaries(ckpt_root)

    # ---- resume or fresh start -------------------------------------------------------------
    start_step, ck = 0, None
    check_run_folder(out, resume)
    if resume:
        ck = ckpt_io.load_checkpoint(ckpt_root, expect_model=task.kind, expect_preset=config.preset)
        _check_resume_config(task, ck)
        task.check_resume(ck)
        start_step = ck.step
        if start_step > config.steps:
            raise ValueError(f"{ck.path}: checkpoint is at step {start_step}, past --steps {config.steps}")
    # seconds this run trained before (a resume): the time budget is the whole run's, so a resumed
    # warm-stable-decay schedule goes on where its clock stopped
    spent_before = float(ck.meta.get("train_seconds", 0.0)) if ck is not None else 0.0
    if time_budget_s is not None and spent_before >= time_budget_s:
        raise ValueError(f"{ck.path}: the run has trained {spent_before / 60:.3g} min, its whole --time-budget of "
                         f"{time_budget_s / 60:g} min; give a larger --time-budget to train on")  # fmt: skip

    def trained_seconds() -> float:
        """This run's training clock: the seconds before a resume and those since the loop began (t0)."""
        return spent_before + time.perf_counter() - t0

    need, free = task.step_bytes(), available_memory_bytes(device)
    if need is not None and free is not None and need > TRAIN_MEMORY_SHARE * free:
        fits = TRAIN_MEMORY_SHARE * free / need
        raise ValueError(f"one training step needs ~{need / 2**30:.1f} GiB and {free / 2**30:.1f} GiB are free on {device}; "
                         f"about {fits:.0%} of it fits: lower --batch-size or --num-points")  # fmt: skip
    torch.manual_seed(config.seed)
    model = task.build_model()
    init_source = None if ck is None else ck.meta.get("init_from")
    if ck is not None:
        model.load_state_dict(ck.model_state)
    elif init_from is not None:
        init_source = load_initial_weights(model, init_from, task)
    model.to(device)
    ema = EMA(model, config.ema_decay) if config.ema_decay is not None else None
    if ema is not None and ck is not None and ck.ema_state is not None:
        ema.load_state_dict(ck.ema_state)
    optimizer = task.make_optimizer(model)
    base_lrs = [float(g["lr"]) for g in optimizer.param_groups]
    if ck is not None and ck.optimizer_state is not None:
        optimizer.load_state_dict(ck.optimizer_state)
    if ck is not None and ck.rng_state is not None:
        ckpt_io.restore_rng_state(ck.rng_state)

    net: nn.Module = model
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel

        net = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None,
                                      find_unused_parameters=task.ddp_find_unused)  # fmt: skip

    if compile_model and world == 1:
        net = torch.compile(model)

    batches = task.step_batches(model, rank, world)
    loader = torch.utils.data.DataLoader(
        batches, batch_size=None, sampler=range(start_step, config.steps),
        num_workers=config.num_workers, pin_memory=device.type == "cuda",
    )  # fmt: skip

    # ---- rank-0 outputs ---------------------------------------------------------------------
    logger = None
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(out / "config.json", {"data": data, "world_size": world,
                                                **({"init_from": init_source} if init_source else {}),
                                                **task.config.to_dict()})  # fmt: skip
        logger = Logger(out, start_step if ck is not None else None)

    def save(step: int) -> Path:
        return ckpt_io.save_checkpoint(
            ckpt_root, step, model_kind=task.kind, preset=config.preset, config=task.config.to_dict(),
            normalisation=task.normalisation, model_state=model.state_dict(),
            ema_state=None if ema is None else ema.state_dict(), optimizer_state=optimizer.state_dict(),
            rng_state=ckpt_io.capture_rng_state(),
            extra={"world_size": world, "data": data, **({"init_from": init_source} if init_source else {}),
                   "train_seconds": round(trained_seconds(), 3), **task.checkpoint_extra(model)},
            keep=config.keep_checkpoints,
        )  # fmt: skip

    bf16, grad_clip = config.bf16, config.grad_clip

    def autocast():
        return torch.autocast(device.type, dtype=torch.bfloat16) if bf16 else contextlib.nullcontext()

    bar = Progress("train", config.steps, loss=True, done=start_step, transient=False, enabled=progress and rank == 0,
                   deadline_s=None if time_budget_s is None else time_budget_s - spent_before)  # fmt: skip
    last_ckpt, saved_step, loss_val, t0, step = None, None, float("nan"), time.perf_counter(), start_step
    stopped_by_budget = False
    clock_decay = time_budget_s is not None and config.lr_schedule == "wsd"
    time_share = spent_before / time_budget_s if clock_decay else None
    model.train()
    try:
        for step, batch in zip(range(start_step, config.steps), loader, strict=True):
            lr = lr_at(config, step, time_share)
            for group, base in zip(optimizer.param_groups, base_lrs, strict=True):
                group["lr"] = lr if base == config.lr else base * (lr / config.lr)
            batch = _to_device(batch, device)
            with autocast():
                loss, logs = task.loss(net, batch, step, rank)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            gnorm = (torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
                     if grad_clip is not None else _grad_norm(model))  # fmt: skip
            optimizer.step()
            decay_now = ema.update(model, step) if ema is not None else None
            done = step + 1
            if time_budget_s is not None and not stopped_by_budget:
                spent = torch.tensor(trained_seconds(), dtype=torch.float64)
                if world > 1:  # every rank stops at the same step, with the same learning rate
                    spent = spent.to(device)
                    dist.all_reduce(spent, op=dist.ReduceOp.MAX)
                spent = float(spent)
                stopped_by_budget = spent >= time_budget_s
                if clock_decay:
                    time_share = spent / time_budget_s
            log_now = done % config.log_every == 0 or done == config.steps or stopped_by_budget
            if log_now or not torch.is_tensor(logs["loss"]):  # tensors (a GPU task): read at log steps only
                logs = {k: float(v) for k, v in logs.items()}
                logs = {k: v for k, v in logs.items() if k == "loss" or not math.isnan(v)}
                loss_val = logs["loss"]
                if not math.isfinite(loss_val):
                    raise FloatingPointError(f"loss is {loss_val} at step {done}; lower --lr or check the data")

            if log_now:
                if world > 1:
                    lt = torch.tensor([loss_val], device=device)
                    dist.all_reduce(lt)
                    loss_val = float(lt) / world
                if rank == 0:
                    elapsed = time.perf_counter() - t0
                    rec = {"step": done, "loss": loss_val, **{k: v for k, v in logs.items() if k != "loss"},
                           "lr": lr, "grad_norm": float(gnorm), **task.log_extra(step)}  # fmt: skip
                    if decay_now is not None:
                        rec["ema_decay"] = decay_now
                    rec.update(steps_per_s=(done - start_step) / max(elapsed, 1e-9), time=elapsed)
                    logger.log(rec)
                    if log_fn is not None:
                        log_fn(rec)
            if rank == 0:
                bar.advance(loss=f"{loss_val:.4f}")
                if config.sample_every and done % config.sample_every == 0:
                    task.preview(model if ema is None else ema.module, done, out, device)
                    logger.plot(out / "loss.png")
                if config.ckpt_every and done % config.ckpt_every == 0:
                    last_ckpt, saved_step = save(done), done
                    logger.plot(out / "loss.png")
            step = done
            if stopped_by_budget:
                break
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
    exported = None
    if export_to is not None and rank == 0:
        exported = export_run(out, export_to, [n for n, b in model.named_buffers() if b.is_floating_point()])
    return TrainResult(model=model, ema=model if ema is None else ema.module, step=step, last_checkpoint=last_ckpt,
                       steps_per_s=(step - start_step) / max(elapsed, 1e-9), final_loss=loss_val,
                       stopped_by_budget=stopped_by_budget, export=exported)  # fmt: skip


def export_run(run: str | os.PathLike, out: str | os.PathLike, keep_float32: Sequence[str] = ()) -> Path:
    """A sampling-only copy of the newest intact checkpoint of ``run`` at ``out`` (EMA weights, fp16;
    the tensors ``keep_float32`` float32, as ``pocoloco export-model`` keeps a model's floating
    buffers: templates, UV queries), replacing an older copy only once the new one is complete."""
    import shutil
    import uuid

    out = Path(out)
    tmp = out.parent / f".{out.name}.export-{uuid.uuid4().hex[:8]}"
    ckpt_io.export_for_sampling(Path(run) / "checkpoints", tmp, dtype="float16", keep_float32=keep_float32)
    old = out.parent / f".{out.name}.old-{uuid.uuid4().hex[:8]}"
    if out.exists():
        os.replace(out, old)
    os.replace(tmp, out)
    shutil.rmtree(old, ignore_errors=True)
    return out
