"""The methods registry: checkpoint kind -> method class, read once, here.

Adding a method = a folder under ``methods/`` with a :class:`~pocoloco.methods.base.Method`
subclass, and one line in :data:`METHODS`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from pocoloco.engine import trainer
from pocoloco.engine.checkpoint import (
    META_FILE,
    load_checkpoint,
    read_meta,
    resolve_checkpoint,
)
from pocoloco.engine.trainer import TrainResult
from pocoloco.methods.base import Method
from pocoloco.methods.closet.method import CloSETMethod
from pocoloco.methods.hybrid.method import HybridMethod
from pocoloco.methods.pocoloco.method import PocoLocoMethod
from pocoloco.methods.pop.method import POPMethod

__all__ = ["METHODS", "checkpoint_kind", "load_method", "method_class", "train", "train_preset"]

#: ``model_kind`` of a checkpoint (and ``pocoloco train --model``) -> its method
METHODS: dict[str, type[Method]] = {
    "pocoloco": PocoLocoMethod,
    "pop": POPMethod,
    "closet": CloSETMethod,
    "hybrid": HybridMethod,
}


def method_class(kind: str) -> type[Method]:
    """The method of ``kind``; a one-line error naming the known ones otherwise."""
    if kind not in METHODS:
        raise ValueError(f"unknown model {kind!r}; choose one of: {', '.join(METHODS)}")
    return METHODS[kind]


def checkpoint_kind(path: str | os.PathLike) -> str:
    """The ``model_kind`` of a checkpoint (checkpoint folder, checkpoints folder or run folder)."""
    return read_meta(resolve_checkpoint(path))["model_kind"]


def load_method(path: str | os.PathLike, device: str | torch.device = "cpu", use_ema: bool = True,
                expect: str | tuple[str, ...] | None = None) -> Method:  # fmt: skip
    """Load any checkpoint (a checkpoint, checkpoints or run folder; a damaged newest checkpoint of a
    run falls back to the newest intact one) as its :class:`Method`, in eval mode on ``device``.

    expect: the kind(s) the caller needs; a checkpoint of another kind is a one-line error naming both.
    """
    p = Path(path)
    meta_path = resolve_checkpoint(p)
    kind = read_meta(meta_path)["model_kind"]
    wanted = (expect,) if isinstance(expect, str) else expect
    if wanted is None and kind not in METHODS:
        wanted = tuple(METHODS)
    if wanted is not None and kind not in wanted:
        raise ValueError(f"{meta_path / META_FILE}: checkpoint is of model {kind!r}, expected "
                         f"{' or '.join(repr(w) for w in wanted)}")  # fmt: skip
    cls = method_class(kind)
    ck = load_checkpoint(p, expect_model=kind, map_location="cpu", training_state=False)
    return cls.from_checkpoint(ck, device=str(torch.device(device)), use_ema=use_ema)


def train_preset(kind: str, preset: str, **overrides) -> Any:
    """The training config of method ``kind``'s preset with field overrides."""
    return method_class(kind).preset(preset, **overrides)


def config_from_checkpoint(path: str | os.PathLike, kind: str, **overrides) -> Any:
    """The training config stored in a run's newest checkpoint, with field overrides (``--resume``
    without ``--preset``)."""
    ck = load_checkpoint(path, expect_model=kind, training_state=False)
    return method_class(kind).train_config.from_dict(ck.config).replace(**overrides)


def train(config: Any, data: str | os.PathLike, out: str | os.PathLike, **kwargs) -> TrainResult:
    """Train ``config`` (any method's train config) on ``data`` into the run folder ``out`` with the
    shared loop (:func:`pocoloco.engine.trainer.train`; ``kwargs``: device, resume, progress, log_fn)."""
    task = method_class(config.model).training_task(config, data)
    return trainer.train(task, out, **kwargs)
