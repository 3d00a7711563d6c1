"""CloSET (Zhang et al. 2023) behind the :class:`~pocoloco.methods.base.Method` interface, and its
training task for the shared loop.

Prediction: N points drawn area-uniformly on the template surface (body faces; seeded): its
features live on the continuous surface, so any N is queried directly. The pose encoder runs
over one T-pose template: with several subjects of one topology, the mean of their bind-pose
templates (the paper has one subject per model; this is our multi-subject choice).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pocoloco.data.poses import Pose
from pocoloco.methods.closet.data import (
    CloSETBatch,
    make_closet_batch,
    make_closet_optimizer,
)
from pocoloco.methods.closet.losses import CloSETLossWeights, closet_loss
from pocoloco.methods.skinned import SkinnedMethod, SkinnedTask, SkinnedTrainConfig
from pocoloco.models.closet import CloSET
from pocoloco.utils.seeding import seed_of

__all__ = ["CloSETMethod", "CloSETTask"]


class CloSETMethod(SkinnedMethod):
    """A trained CloSET: PointNet++ pose and garment encoders on the template, barycentric surface
    features, garment-template + pose-wrinkle decoders (or one decoder without decomposition)."""

    kind = "closet"
    train_options = frozenset({"decomposition"})

    @classmethod
    def _model_from_state(cls, config: SkinnedTrainConfig, state: dict[str, torch.Tensor],
                          meta: dict[str, Any]) -> CloSET:  # fmt: skip
        return CloSET.from_state(config.net_config(), state)

    @classmethod
    def training_task(cls, config: SkinnedTrainConfig, data: str | Path) -> CloSETTask:
        return CloSETTask(config, data)

    @property
    def title(self) -> str:
        return "CloSET" if self.config.net.get("decomposition", True) else "CloSET (no decomposition)"

    def query_surface(self, num_points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        q = self.model.sample_query_points(num_points, seed=int(seed))
        return q.face_idx, q.barycentric

    def _predict_one(self, pose: Pose, outfit: int, num_points: int, seed: int, code: torch.Tensor | None = None):
        if code is not None:
            raise ValueError("CloSET cannot take an outfit code from outside (it does not fit new outfits)")
        body, vt = self.body_tensors(pose)
        outfit_t = torch.tensor([int(outfit)], dtype=torch.long, device=body.device)
        face_idx, bary = self.query_surface(num_points, seed)
        return self.model(body, vt, outfit_t, torch.as_tensor(face_idx, dtype=torch.long, device=body.device),
                          torch.as_tensor(bary, dtype=torch.float32, device=body.device))  # fmt: skip

    def sample_settings(self, options, num_points: int) -> dict[str, Any]:
        if options.even:
            return {"query_points": f"{self.even_candidates(num_points):,} area-uniform points on the template surface, "
                                    "N of them kept by farthest-point sampling of their spots on the posed body"}  # fmt: skip
        return {"query_points": "N area-uniform points on the template surface"}


class CloSETTask(SkinnedTask):
    """CloSET's training: Eqs. 4-6 (:func:`~pocoloco.methods.closet.losses.closet_loss`) with POP's
    rates and normal schedule; the query points of step s are drawn with seed ``(seed, 4, s)``."""

    method = CloSETMethod

    def build_model(self) -> nn.Module:
        names = list(self.assets)
        first = self.assets[names[0]]
        template = np.mean([np.asarray(self.assets[s].template, np.float64) for s in names], axis=0).astype(np.float32)
        return CloSET(template, np.asarray(first.faces, np.int64), len(names), self.config.net_config())

    def make_optimizer(self, model: nn.Module) -> torch.optim.Optimizer:
        return make_closet_optimizer(model, lr=self.config.lr, code_lr=self.config.lr_codes)

    def make_batch(self, items, step: int) -> CloSETBatch:
        c = self.config
        q = self.model.sample_query_points(c.query_points, seed=seed_of(c.seed, 4, step) % (2**31))
        for it in items:
            if it.frame.body_vertices is None or it.frame.vtransf is None:
                raise ValueError(f"{it.path}: frame has no posed body (body_vertices / vtransf); CloSET needs it")
        return make_closet_batch([it.frame for it in items], [self.outfits[it.subject] for it in items], q,
                                 c.num_points, seed=seed_of(c.seed, 1, step) % (2**31))  # fmt: skip

    def loss(self, net: nn.Module, batch: CloSETBatch, step: int, rank: int):
        w = CloSETLossWeights(**self.config.closet_weights)
        if step < self.config.normal_start:
            w = dataclasses.replace(w, normal=0.0)
        out = net(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
        losses = closet_loss(out, batch.points, batch.normals, w)
        logs = {k: float(v.detach()) for k, v in losses.items()}
        return losses["total"], {"loss": logs.pop("total"), **logs}
