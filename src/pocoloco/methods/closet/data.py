"""CloSET training batches, the optimiser and one plain optimisation step; eval-mode prediction
of a batch. Shapes: B frames, V vertices, P query points, N ground-truth points.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from pocoloco.body.surface import SurfacePoints
from pocoloco.methods.closet.losses import CloSETLossWeights, closet_loss
from pocoloco.models.closet import CloSET

__all__ = ["CloSETBatch", "closet_predict", "closet_train_step", "make_closet_batch", "make_closet_optimizer"]


@dataclass
class CloSETBatch:
    """Model inputs and targets for B frames of one subject (pelvis-centred).

    vertices (B, V, 3), vtransf (B, V, 3, 3), outfit (B,) int64, points / normals
    (B, N, 3) GT, face_idx (P,) int64 and barycentric (P, 3) query points,
    pelvis (B, 3) the subtracted joints[0] (add back to place predictions in the world)."""

    vertices: torch.Tensor
    vtransf: torch.Tensor
    outfit: torch.Tensor
    points: torch.Tensor
    normals: torch.Tensor
    face_idx: torch.Tensor
    barycentric: torch.Tensor
    pelvis: torch.Tensor

    def to(self, device) -> CloSETBatch:
        return CloSETBatch(*(getattr(self, f.name).to(device) for f in dataclasses.fields(self)))


def make_closet_batch(frames: Sequence, outfit, query: SurfacePoints, num_gt_points: int | None = None,
                      seed: int = 0) -> CloSETBatch:  # fmt: skip
    """Batch from dataset frames (``pocoloco.data.format.Frame``; need ``points``,
    ``normals``, ``joints``, ``body_vertices``, ``vtransf``). Everything is pelvis-centred
    (joints[0] subtracted). ``num_gt_points``: subsample each frame's GT cloud to this many
    points (without replacement, numpy seed ``seed``); None = all points (then every frame
    needs the same count). ``outfit``: one id or one per frame."""
    if len(frames) == 0:
        raise ValueError("make_closet_batch needs at least one frame")
    rng = np.random.default_rng(seed)
    verts, tf, pts, nrm, pelvis = [], [], [], [], []
    for i, fr in enumerate(frames):
        for k in ("points", "normals", "joints", "body_vertices", "vtransf"):
            if getattr(fr, k, None) is None:
                raise ValueError(f"frame {i} has no {k!r} (CloSET needs the posed body: synthetic or fitted data)")
        p0 = np.asarray(fr.joints[0], np.float32)
        P, N = np.asarray(fr.points, np.float32), np.asarray(fr.normals, np.float32)
        if num_gt_points is not None:
            if num_gt_points > len(P):
                raise ValueError(f"frame {i} has {len(P)} points, fewer than num_gt_points={num_gt_points}")
            sel = rng.choice(len(P), num_gt_points, replace=False)
            P, N = P[sel], N[sel]
        verts.append(np.asarray(fr.body_vertices, np.float32) - p0)
        tf.append(np.asarray(fr.vtransf, np.float32))
        pts.append(P - p0)
        nrm.append(N)
        pelvis.append(p0)
    if len({v.shape for v in verts}) != 1 or len({v.shape for v in tf}) != 1:
        raise ValueError("frames have different body vertex counts; one CloSET batch holds one subject")
    if len({p.shape for p in pts}) != 1:
        raise ValueError("frames have different point counts; pass num_gt_points to subsample them")
    outfit_t = torch.as_tensor(outfit, dtype=torch.long)
    if outfit_t.ndim == 0:
        outfit_t = outfit_t.expand(len(frames)).clone()
    if outfit_t.shape != (len(frames),):
        raise ValueError(f"outfit must be one id or one per frame ({len(frames)}), got shape {tuple(outfit_t.shape)}")
    t = lambda xs: torch.from_numpy(np.stack(xs))  # noqa: E731
    return CloSETBatch(t(verts), t(tf), outfit_t, t(pts), t(nrm), torch.as_tensor(query.face_idx, dtype=torch.long),
                       torch.as_tensor(query.barycentric, dtype=torch.float32), t(pelvis))  # fmt: skip


def make_closet_optimizer(model: CloSET, lr: float = 3e-4, code_lr: float = 5e-4) -> torch.optim.Adam:
    """Adam with POP's rates: networks ``lr``, auto-decoded garment codes ``code_lr``."""
    codes = [model.garment_codes]
    rest = [p for n, p in model.named_parameters() if n != "garment_codes"]
    return torch.optim.Adam([{"params": rest, "lr": lr}, {"params": codes, "lr": code_lr}])


def closet_train_step(model: CloSET, optimizer: torch.optim.Optimizer, batch: CloSETBatch,
                      weights: CloSETLossWeights = CloSETLossWeights()) -> dict[str, float]:  # fmt: skip
    """One optimisation step on ``batch``: forward, Eqs. (4)-(6), backward, step.
    Returns the loss terms as floats. (POP switches the normal term on after the shape
    settles: pass ``weights=dataclasses.replace(w, normal=0.0)`` for the early epochs.)"""
    model.train()
    out = model(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
    losses = closet_loss(out, batch.points, batch.normals, weights)
    optimizer.zero_grad(set_to_none=True)
    losses["total"].backward()
    optimizer.step()
    return {k: float(v.detach()) for k, v in losses.items()}


@torch.no_grad()
def closet_predict(model: CloSET, batch: CloSETBatch) -> tuple[np.ndarray, np.ndarray]:
    """Eval-mode prediction in world coordinates: (B, P, 3) points (pelvis added back)
    and (B, P, 3) unit normals, float32 numpy (e.g. for ``pocoloco sample``/``eval``)."""
    model.eval()
    out = model(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
    pts = out.points + batch.pelvis[:, None, :].to(out.points)
    return pts.cpu().numpy().astype(np.float32), out.normals.cpu().numpy().astype(np.float32)
