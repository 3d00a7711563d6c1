"""POP's training loss (paper Eq. 3-6; the weights are those of POP's public training configuration): scan-to-model and point-to-plane
model-to-scan Chamfer terms, the normal term (switched on after the shape settles), and the
displacement and feature regularisers; with a slow reference implementation.

Shapes: B batch, P predicted points, N scan points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pocoloco.models.pop import POPLossWeights, POPOutput
from pocoloco.ops import knn, knn_numpy

__all__ = ["POPLossWeights", "POPLosses", "check_scan", "normal_weight_at", "pop_losses", "pop_losses_reference"]


@dataclass
class POPLosses:
    """Weighted total and the unweighted terms (each a scalar tensor, batch-mean).

    s2m: mean over scan points of the squared distance to the nearest predicted point.
    m2s: mean over predicted points of ((x - y_nn) . n_y)^2 (point-to-plane).
    normal: mean over predicted points of |n_x - n_y_nn|_1 (0 when switched off).
    displacement: mean |s r_i|^2 (L_rd); feature: mean squared entry of G (L_rg).
    """

    total: torch.Tensor
    s2m: torch.Tensor
    m2s: torch.Tensor
    normal: torch.Tensor
    displacement: torch.Tensor
    feature: torch.Tensor

    def as_floats(self) -> dict[str, float]:
        return {k: float(getattr(self, k).detach()) for k in ("total", "s2m", "m2s", "normal", "displacement", "feature")}


def check_scan(scan_points, scan_normals, B: int, need_normals: bool):
    if scan_points is None:
        raise ValueError("the batch has no scan_points (needed for the loss)")
    if scan_points.ndim != 3 or scan_points.shape[0] != B or scan_points.shape[2] != 3:
        raise ValueError(f"scan_points must have shape (B={B}, N, 3), got {tuple(scan_points.shape)}")
    if scan_points.shape[1] < 1:
        raise ValueError("scan_points is empty")
    if need_normals or scan_normals is not None:
        if scan_normals is None:
            raise ValueError("the loss needs scan_normals (point-to-plane / normal term) but the batch has none")
        if scan_normals.shape != scan_points.shape:
            raise ValueError(f"scan_normals {tuple(scan_normals.shape)} must match scan_points {tuple(scan_points.shape)}")


def _nearest(query: torch.Tensor, ref: torch.Tensor, backend: str) -> torch.Tensor:
    """(B, N, 3), (B, M, 3) -> (B, N) int64 index of the nearest ``ref`` point (no gradient).

    backend "kdtree": scipy cKDTree per frame (``pocoloco.ops.knn_numpy``; O(N log M), far
    faster than brute force on CPU); "brute": ``pocoloco.ops.knn`` (chunked matmul, any
    device); "auto": kdtree for CPU tensors, brute otherwise."""
    if backend == "auto":
        backend = "kdtree" if query.device.type == "cpu" else "brute"
    if backend == "brute":
        return knn(query.detach(), ref.detach(), 1).idx[..., 0]
    if backend != "kdtree":
        raise ValueError(f"nn_backend must be 'auto', 'kdtree' or 'brute', got {backend!r}")
    q, r = query.detach().cpu().double().numpy(), ref.detach().cpu().double().numpy()
    idx = np.stack([knn_numpy(q[b], r[b], 1).idx[:, 0] for b in range(q.shape[0])])
    return torch.from_numpy(idx).to(query.device)


def pop_losses(out: POPOutput, scan_points, scan_normals, weights: POPLossWeights = POPLossWeights(),
               normal_weight: float | None = None, nn_backend: str = "auto") -> POPLosses:  # fmt: skip
    """POP training loss (Eq. 3): w_s2m L_s2m + w_m2s L_m2s + w_n L_n + w_rd L_rd + w_rg L_rg.

    out: model output (points (B, P, 3)); scan_points, scan_normals: (B, N, 3).
    weights: the w of Eq. 3. normal_weight: w_n (None = ``weights.normal``; 0 switches the normal term off).
    Nearest neighbours (``_nearest``: cKDTree on CPU, ``pocoloco.ops.knn`` otherwise) are
    chosen without gradient; distances are recomputed in torch for the chosen pairs, so
    gradients flow through them and the predicted normals, not the neighbour choice.
    """
    x, n = out.points, out.normals
    B = x.shape[0]
    wn = weights.normal if normal_weight is None else float(normal_weight)
    check_scan(scan_points, scan_normals, B, need_normals=True)
    y, ny = scan_points.to(x.dtype), scan_normals.to(x.dtype)
    idx_s = _nearest(y, x, nn_backend)  # (B, N) nearest predicted point of each scan point
    s2m = ((y - torch.gather(x, 1, idx_s[..., None].expand(-1, -1, 3))) ** 2).sum(-1).mean()
    idx = _nearest(x, y, nn_backend)  # (B, P) nearest scan point of each predicted point
    gather = idx[..., None].expand(-1, -1, 3)
    y_nn, n_nn = torch.gather(y, 1, gather), torch.gather(ny, 1, gather)
    m2s = (((x - y_nn) * n_nn).sum(-1) ** 2).mean()
    normal = (n - n_nn).abs().sum(-1).mean() if wn > 0 else x.new_zeros(())
    disp = (out.displacement**2).sum(-1).mean()
    feat = (out.geom**2).mean()
    w = weights
    total = w.s2m * s2m + w.m2s * m2s + wn * normal + w.displacement * disp + w.feature * feat
    return POPLosses(total, s2m, m2s, normal, disp, feat)


def pop_losses_reference(out: POPOutput, scan_points, scan_normals, weights: POPLossWeights = POPLossWeights(),
                         normal_weight: float | None = None) -> POPLosses:  # fmt: skip
    """Slow reference for ``pop_losses``: explicit loops over frames and points."""
    x, n = out.points, out.normals
    B, P, _ = x.shape
    wn = weights.normal if normal_weight is None else float(normal_weight)
    s2m, m2s, normal = [], [], []
    for b in range(B):
        y, ny = scan_points[b].to(x.dtype), scan_normals[b].to(x.dtype)
        s2m += [((x[b] - y[j]) ** 2).sum(-1).min() for j in range(y.shape[0])]
        for i in range(P):
            j = int(((y - x[b, i].detach()) ** 2).sum(-1).argmin())
            m2s.append(((x[b, i] - y[j]) @ ny[j]) ** 2)
            normal.append((n[b, i] - ny[j]).abs().sum())
    s2m_t, m2s_t = torch.stack(s2m).mean(), torch.stack(m2s).mean()
    normal_t = torch.stack(normal).mean() if wn > 0 else x.new_zeros(())
    disp = torch.stack([(out.displacement[b, i] ** 2).sum() for b in range(B) for i in range(P)]).mean()
    feat = torch.stack([(g**2).sum() / g.numel() for g in out.geom]).mean()
    w = weights
    total = w.s2m * s2m_t + w.m2s * m2s_t + wn * normal_t + w.displacement * disp + w.feature * feat
    return POPLosses(total, s2m_t, m2s_t, normal_t, disp, feat)


def normal_weight_at(weights: POPLossWeights, normal_start: int, step: int) -> float:
    """w_n at a training step: 0 before ``normal_start``, ``weights.normal`` from it on."""
    return weights.normal if step >= normal_start else 0.0
