"""Training the hybrid's free-region generator: a pack of free-region points and a fine-tune of a
PocoLoco denoiser on it, in the shared training loop (:func:`pocoloco.engine.trainer.train`).

The hybrid's attached part is a POP trained on the whole body (``pocoloco train --model pop``),
whose points the hybrid also uses for a share of the free region; its free part is a PocoLoco
denoiser fine-tuned on the points where the cloth hangs free. ``pocoloco hybrid --fine-tune
MINUTES`` runs the stages below into one run folder, each resumable after a kill:

1. ``maps.npz``: the free-region maps (:func:`~pocoloco.methods.hybrid.regions.learn_free_maps`);
2. ``free.pack``: every ``every``-th train frame of the outfits with a free region, ``points``
   free-region points each (:func:`write_free_pack`, atomic);
3. ``free_generator/``: a PocoLoco run fine-tuned from ``init`` on that pack for a time budget
   (:func:`train_free_generator`; resumed when it has checkpoints);
4. ``checkpoints/``: the assembled hybrid (:func:`~pocoloco.methods.hybrid.assemble.assemble_hybrid`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from pocoloco.data.format import read_frame
from pocoloco.data.pack import write_pack
from pocoloco.engine.checkpoint import latest_checkpoint, load_checkpoint
from pocoloco.engine.trainer import train as run_training
from pocoloco.methods.hybrid.regions import FreeRegionMaps, point_regions
from pocoloco.methods.pocoloco.config import PocoLocoTrainConfig
from pocoloco.methods.pocoloco.method import PocoLocoMethod

__all__ = ["FREE_RECIPE", "train_free_generator", "write_free_pack"]

#: the fine-tuning recipe measured for the free-region generator (BENCHMARKS "The hybrid method"):
#: batch 32 x 512 points, peak lr 3e-4, wsd with the cool-down on the time budget's clock, fp32
FREE_RECIPE: dict[str, Any] = {"batch_size": 32, "num_points": 512, "lr": 3e-4, "lr_schedule": "wsd",
                               "steps": 20_000, "decay_steps": 4_000, "warmup_steps": 200, "bf16": False,
                               "num_workers": 0, "ckpt_every": 250, "sample_every": 0}  # fmt: skip


def write_free_pack(data: str | os.PathLike, maps: FreeRegionMaps, out: str | os.PathLike, *, every: int = 3,
                    points: int = 512, min_share: float = 0.05,
                    progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:  # fmt: skip
    """Write ``out``: a training pack of ``data``'s train split holding only free-region points
    (each point's nearest posed body vertex is free in its outfit's map, or it lies farther than
    the maps' ``far`` from the body: :func:`point_regions`), every ``every``-th frame
    of the outfits whose free point share is at least ``min_share``. Returns the pack's meta
    (:func:`~pocoloco.data.pack.write_pack`) with ``packed`` (those outfits)."""
    chosen = [n for i, n in enumerate(maps.outfits) if maps.point_share[i] >= min_share]
    if not chosen:
        raise ValueError(f"no outfit has a free point share >= {min_share}: there is no free region to train on")
    free = {name: maps.free(i) for i, name in enumerate(maps.outfits)}

    def select(subject: str, path: Path):
        fr = read_frame(path, ("points", "body_vertices"))
        return point_regions(fr.points, fr.body_vertices, free[subject], maps.far)

    meta = write_pack(data, out, every=every, points=points, subjects=chosen, select=select, splits=("train",),
                      progress=progress)  # fmt: skip
    return {**meta, "packed": chosen}


def train_free_generator(pack: str | os.PathLike, init: str | os.PathLike, out: str | os.PathLike, *,
                         minutes: float, device: str | torch.device = "cpu", progress: bool = True,
                         **recipe: Any) -> Path:  # fmt: skip
    """Fine-tune the PocoLoco checkpoint ``init`` (its network and config) on the free-region
    ``pack`` into the run folder ``out`` for ``minutes`` of wall clock (:data:`FREE_RECIPE`, fields
    overridden by ``recipe``); resumes a run that has checkpoints. Returns the exported model."""
    if not minutes > 0:
        raise ValueError(f"the fine-tune's time budget must be > 0 minutes, got {minutes}")
    out = Path(out)
    resume = latest_checkpoint(out / "checkpoints") is not None
    source = out if resume else init
    ck = load_checkpoint(source, expect_model="pocoloco", training_state=False)
    config = PocoLocoTrainConfig.from_dict(ck.config)
    if not resume:
        config = config.replace(**{**FREE_RECIPE, **recipe})
    task = PocoLocoMethod.training_task(config, pack)
    run_training(task, out, device=device, resume=resume, progress=progress, time_budget_s=60.0 * minutes,
                 export_to=out / "model", init_from=None if resume else init)  # fmt: skip
    return out / "model"
