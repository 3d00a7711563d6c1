"""Chamfer distance between batched point clouds (torch, differentiable).

Shapes: B batch, N points of ``x``, M points of ``y``.

``chamfer_distance`` returns the per-point nearest-neighbour results of both
directions; the reductions (squared and unsquared means, their sums) are properties,
so a loss can also reuse the nearest indices (POP point-to-plane M2S, normal L1).
POP writes the squared form as its Eq. (4):
    CD(X, Y) = 1/N sum_i min_j |x_i - y_j|^2 + 1/M sum_j min_i |x_i - y_j|^2.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .knn import knn, knn_reference


def safe_sqrt(d: torch.Tensor) -> torch.Tensor:
    """sqrt with value 0 and gradient 0 at d == 0 (plain sqrt has an infinite gradient there)."""
    pos = d > 0
    return torch.where(pos, d, torch.ones_like(d)).sqrt() * pos


@dataclass(frozen=True)
class Chamfer:
    """Nearest neighbours both ways between ``x`` (B, N, 3) and ``y`` (B, M, 3).

    dist_xy: (B, N) squared distance from each x_i to its nearest y.
    idx_xy:  (B, N) index into y of that neighbour.
    dist_yx: (B, M) squared distance from each y_j to its nearest x.
    idx_yx:  (B, M) index into x of that neighbour.
    All reductions below are (B,) tensors, one value per cloud pair.
    """

    dist_xy: torch.Tensor
    idx_xy: torch.Tensor
    dist_yx: torch.Tensor
    idx_yx: torch.Tensor

    @property
    def xy_sq(self) -> torch.Tensor:
        """(B,) mean over x of the squared distance to the nearest y."""
        return self.dist_xy.mean(-1)

    @property
    def yx_sq(self) -> torch.Tensor:
        """(B,) mean over y of the squared distance to the nearest x."""
        return self.dist_yx.mean(-1)

    @property
    def xy(self) -> torch.Tensor:
        """(B,) mean over x of the (unsquared) distance to the nearest y."""
        return safe_sqrt(self.dist_xy).mean(-1)

    @property
    def yx(self) -> torch.Tensor:
        """(B,) mean over y of the (unsquared) distance to the nearest x."""
        return safe_sqrt(self.dist_yx).mean(-1)

    @property
    def chamfer_sq(self) -> torch.Tensor:
        """(B,) squared Chamfer distance ``xy_sq + yx_sq`` (POP Eq. 4)."""
        return self.xy_sq + self.yx_sq

    @property
    def chamfer(self) -> torch.Tensor:
        """(B,) unsquared Chamfer distance ``xy + yx`` (PocoLoco Table 2 convention)."""
        return self.xy + self.yx


def _check(x: torch.Tensor, y: torch.Tensor) -> None:
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"x must have shape (B, N, 3), got {tuple(x.shape)}")
    if y.ndim != 3 or y.shape[-1] != 3:
        raise ValueError(f"y must have shape (B, M, 3), got {tuple(y.shape)}")
    if x.shape[1] == 0 or y.shape[1] == 0:
        raise ValueError("x and y must each have at least one point")


def chamfer_distance(x: torch.Tensor, y: torch.Tensor, *, chunk: int | None = None) -> Chamfer:
    """Chamfer distance between x (B, N, 3) and y (B, M, 3), both directions.

    Uses the chunked ``knn`` (memory bounded, differentiable in the distances).
    chunk: queries per chunk (see ``knn``). Returns a ``Chamfer``; e.g.
    ``chamfer_distance(x, y).chamfer_sq.mean()`` is a batch-mean POP Eq. (4) loss.
    """
    _check(x, y)
    a = knn(x, y, 1, chunk=chunk)
    b = knn(y, x, 1, chunk=chunk)
    return Chamfer(a.dists[..., 0], a.idx[..., 0], b.dists[..., 0], b.idx[..., 0])


def chamfer_distance_reference(x: torch.Tensor, y: torch.Tensor) -> Chamfer:
    """Slow reference for ``chamfer_distance`` (``knn_reference`` both ways)."""
    _check(x, y)
    a = knn_reference(x, y, 1)
    b = knn_reference(y, x, 1)
    return Chamfer(a.dists[..., 0], a.idx[..., 0], b.dists[..., 0], b.idx[..., 0])
