"""PointNet++ building blocks (Qi et al. 2017, "PointNet++: Deep Hierarchical Feature
Learning on Point Sets in a Metric Space"), channels-last, pure torch.

* :class:`SetAbstraction` (Sec. 3.2): farthest-point centroids -> ball-query grouping
  -> shared MLP on [relative xyz, features] -> max pool over each group.
* :class:`FeaturePropagation` (Sec. 3.4): inverse squared distance interpolation over
  the 3 nearest coarse points (Eq. 2, p = 2, k = 3) -> concat skip features -> MLP.
* :class:`TemplateHierarchy`: every index the two modules need (centroids, groups,
  3-NN interpolation weights) for a *fixed* point set, computed once. CloSET (Zhang
  et al. 2023, Sec. 4 "Network Architecture") runs PointNet++ on the T-pose template,
  whose coordinates never change, so FPS and ball query are done once and cached.
* :class:`PointNet2Encoder`: L set abstractions + L feature propagations back to the
  input points; per-point features out. ``forward(xyz, feats, hierarchy=None)``
  recomputes FPS / ball query / 3-NN from ``xyz`` each call (plain PointNet++) and
  with a hierarchy uses the cached indices (identical results for the same xyz).

Deviation (PointNeXt-style, Qian et al. 2022): relative neighbour offsets are divided
by the ball radius (``normalize_xyz``), so every level sees offsets in [-1, 1].

Shapes: B batch, N input points, S centroids, K group size, C channels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from pocoloco.ops import ball_query, farthest_point_sampling, knn
from pocoloco.utils.config import Config

__all__ = [
    "FeaturePropagation",
    "LevelIndex",
    "PointNet2Config",
    "PointNet2Encoder",
    "SetAbstraction",
    "SharedMLP",
    "TemplateHierarchy",
    "gather_points",
    "three_nn_weights",
    "three_interpolate",
    "three_interpolate_reference",
]

#: Added to squared distances before inversion (PointNet++ uses 1e-8).
INTERP_EPS = 1e-8


# ---------------------------------------------------------------------------
# functional helpers
# ---------------------------------------------------------------------------


def gather_points(values: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """values (B, N, C), idx (B, *I) int64 into N -> (B, *I, C) (one flat index_select,
    no (B, *I, C) index tensor)."""
    B, N, C = values.shape
    if idx.shape[0] != B:
        raise ValueError(f"gather_points: idx batch {idx.shape[0]} != values batch {B}")
    offset = torch.arange(B, device=idx.device).mul_(N).reshape(B, *([1] * (idx.ndim - 1)))
    flat = (idx + offset).reshape(-1)
    return values.reshape(B * N, C).index_select(0, flat).reshape(*idx.shape, C)


def three_nn_weights(unknown: torch.Tensor, known: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """PointNet++ Eq. (2) weights: unknown (B, N, 3), known (B, S, 3) ->
    idx (B, N, k) int64 and w (B, N, k), k = min(3, S), w_i = (1/d_i^2) / sum_j (1/d_j^2)
    with d^2 + ``INTERP_EPS``."""
    k = min(3, known.shape[1])
    with torch.no_grad():
        nn_ = knn(unknown, known, k)
        w = 1.0 / (nn_.dists + INTERP_EPS)
        w = w / w.sum(-1, keepdim=True)
    return nn_.idx, w


def three_interpolate(feats: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """feats (B, S, C) at known points; idx, w (B, N, k) -> (B, N, C) = sum_k w_k feats[idx_k]."""
    return (gather_points(feats, idx) * w[..., None]).sum(-2)


def three_interpolate_reference(unknown: torch.Tensor, known: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
    """Slow reference for 3-NN inverse squared distance interpolation: python loops,
    explicit sort of the distances to every known point (ties: lower index)."""
    B, N, _ = unknown.shape
    S = known.shape[1]
    k = min(3, S)
    out = torch.zeros(B, N, feats.shape[-1], dtype=feats.dtype)
    for b in range(B):
        for n in range(N):
            d = [float(((unknown[b, n] - known[b, s]) ** 2).sum()) for s in range(S)]
            order = sorted(range(S), key=lambda s: (d[s], s))[:k]
            inv = [1.0 / (d[s] + INTERP_EPS) for s in order]
            tot = sum(inv)
            for s, wi in zip(order, inv):
                out[b, n] += feats[b, s] * (wi / tot)
    return out


# ---------------------------------------------------------------------------
# cached indices of a fixed point set
# ---------------------------------------------------------------------------


@dataclass
class LevelIndex:
    """Indices of one SA level (and of the FP step that undoes it) for a point set.

    centroid_idx: (B, S) int64 centroids, indices into the previous level's points.
    group_idx:    (B, S, K) int64 ball-query neighbours (previous level's points).
    interp_idx:   (B, N, k) int64 3-NN of each previous-level point among the centroids.
    interp_w:     (B, N, k) float inverse squared distance weights (rows sum to 1).
    xyz:          (B, S, 3) centroid coordinates.
    B is 1 in a cached :class:`TemplateHierarchy` (broadcast over any batch).
    """

    centroid_idx: torch.Tensor
    group_idx: torch.Tensor
    interp_idx: torch.Tensor
    interp_w: torch.Tensor
    xyz: torch.Tensor


def compute_level(xyz: torch.Tensor, npoint: int, radius: float, nsample: int) -> LevelIndex:
    """FPS + ball query + 3-NN for one level: xyz (B, N, 3) -> :class:`LevelIndex`.

    ``npoint`` is clipped to N (a small mesh gets as many centroids as it has points)."""
    S = min(int(npoint), xyz.shape[1])
    cidx = farthest_point_sampling(xyz, S, backend="torch")  # (B, S)
    new_xyz = gather_points(xyz, cidx)  # (B, S, 3)
    gidx = ball_query(new_xyz, xyz, radius, nsample)  # (B, S, K)
    iidx, w = three_nn_weights(xyz, new_xyz)  # (B, N, k)
    return LevelIndex(cidx, gidx, iidx, w, new_xyz)


class TemplateHierarchy(nn.Module):
    """All FPS / ball-query / 3-NN indices of a fixed point set (e.g. a subject's T-pose
    template), computed once (CloSET Sec. 4) and kept as non-persistent buffers so that
    ``.to(device)`` moves them and checkpoints stay free of them.

    xyz: (N, 3) points; npoints, radii, nsamples: one entry per SA level.
    """

    def __init__(
        self, xyz: torch.Tensor, npoints: Sequence[int], radii: Sequence[float], nsamples: Sequence[int],
        *, reuse: TemplateHierarchy | None = None,
    ):  # fmt: skip
        """``reuse``: a hierarchy of the same points whose first levels have the same
        (npoint, radius, nsample); those levels are shared instead of recomputed."""
        super().__init__()
        xyz = torch.as_tensor(xyz)
        if xyz.ndim != 2 or xyz.shape[1] != 3 or not xyz.is_floating_point():
            raise ValueError(f"hierarchy points must be a float (N, 3) tensor, got {tuple(xyz.shape)} {xyz.dtype}")
        if not (len(npoints) == len(radii) == len(nsamples)):
            raise ValueError("npoints, radii and nsamples must have one entry per level")
        self.num_levels = len(npoints)
        self.num_points = int(xyz.shape[0])
        self.register_buffer("xyz0", xyz.detach().clone(), persistent=False)
        self.specs = [(int(n), float(r), int(k)) for n, r, k in zip(npoints, radii, nsamples)]
        shared = 0
        if reuse is not None and reuse.num_points == self.num_points and torch.equal(reuse.xyz0, self.xyz0):
            while shared < min(len(self.specs), len(reuse.specs)) and self.specs[shared] == reuse.specs[shared]:
                shared += 1
        cur = xyz.detach()[None]
        for level, (npt, r, ns) in enumerate(self.specs):
            li = reuse.level(level) if level < shared else compute_level(cur, npt, r, ns)
            for name in ("centroid_idx", "group_idx", "interp_idx", "interp_w", "xyz"):
                self.register_buffer(f"l{level}_{name}", getattr(li, name), persistent=False)
            cur = li.xyz

    def level(self, i: int) -> LevelIndex:
        g = lambda name: getattr(self, f"l{i}_{name}")  # noqa: E731
        return LevelIndex(g("centroid_idx"), g("group_idx"), g("interp_idx"), g("interp_w"), g("xyz"))

    def sizes(self) -> list[int]:
        """Number of points at each level, input first."""
        return [self.num_points] + [int(self.level(i).xyz.shape[1]) for i in range(self.num_levels)]


def _expand(t: torch.Tensor, B: int) -> torch.Tensor:
    return t.expand(B, *t.shape[1:]) if t.shape[0] != B else t


# ---------------------------------------------------------------------------
# modules
# ---------------------------------------------------------------------------


class SharedMLP(nn.Module):
    """Per-point MLP on the last dim: [Linear -> (BatchNorm) -> ReLU] x len(widths).

    PointNet++'s 1x1 convolutions with BatchNorm, channels-last; BatchNorm normalises
    over every leading dim (all points of all groups of the batch)."""

    def __init__(self, in_channels: int, widths: Sequence[int], batchnorm: bool = True):
        super().__init__()
        layers: list[nn.Module] = []
        c = in_channels
        for w in widths:
            layers.append(nn.Linear(c, w, bias=not batchnorm))
            if batchnorm:
                layers.append(_ChannelsLastBN(w))
            layers.append(nn.ReLU(inplace=True))
            c = w
        self.net = nn.Sequential(*layers)
        self.out_channels = c

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class _ChannelsLastBN(nn.BatchNorm1d):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shape = x.shape
        return super().forward(x.reshape(-1, shape[-1])).reshape(shape)


class SetAbstraction(nn.Module):
    """One PointNet++ SA level (single-scale grouping).

    forward(xyz (B, N, 3), feats (B, N, C) or None, index: LevelIndex or None)
    -> new_xyz (B, S, 3), new_feats (B, S, C_out), index used.
    Each group's input is [(x_j - c) / radius (if normalize_xyz), f_j]."""

    def __init__(
        self, npoint: int, radius: float, nsample: int, in_channels: int, widths: Sequence[int],
        batchnorm: bool = True, normalize_xyz: bool = True,
    ):  # fmt: skip
        super().__init__()
        if radius <= 0 or nsample < 1 or npoint < 1:
            raise ValueError(f"SA level needs npoint, nsample >= 1 and radius > 0, got {npoint}, {nsample}, {radius}")
        self.npoint, self.radius, self.nsample = int(npoint), float(radius), int(nsample)
        self.normalize_xyz = normalize_xyz
        self.mlp = SharedMLP(in_channels + 3, widths, batchnorm)
        self.out_channels = self.mlp.out_channels

    def forward(self, xyz: torch.Tensor, feats: torch.Tensor | None, index: LevelIndex | None = None):
        B = xyz.shape[0]
        if index is None:
            index = compute_level(xyz, self.npoint, self.radius, self.nsample)
        new_xyz = _expand(index.xyz, B)
        gidx = _expand(index.group_idx, B)
        rel = gather_points(xyz, gidx) - new_xyz[:, :, None, :]  # (B, S, K, 3)
        if self.normalize_xyz:
            rel = rel / self.radius
        x = rel if feats is None else torch.cat([rel, gather_points(feats, gidx)], dim=-1)
        return new_xyz, self.mlp(x).amax(dim=2), index  # max pool over the group


class FeaturePropagation(nn.Module):
    """One PointNet++ FP level: interpolate coarse features (B, S, C2) to the finer
    points (B, N, ·) with 3-NN inverse squared distance weights, concat the skip
    features (B, N, C1), shared MLP -> (B, N, C_out).

    forward(fine_xyz, coarse_xyz, fine_feats or None, coarse_feats, interp=(idx, w) or None)."""

    def __init__(self, in_channels: int, widths: Sequence[int], batchnorm: bool = True):
        super().__init__()
        self.mlp = SharedMLP(in_channels, widths, batchnorm)
        self.out_channels = self.mlp.out_channels

    def forward(self, fine_xyz, coarse_xyz, fine_feats, coarse_feats, interp=None):
        B = coarse_feats.shape[0]
        if interp is None:
            interp = three_nn_weights(fine_xyz, coarse_xyz)
        idx, w = (_expand(t, B) for t in interp)
        x = three_interpolate(coarse_feats, idx, w)
        if fine_feats is not None:
            x = torch.cat([x, fine_feats], dim=-1)
        return self.mlp(x)


@dataclass(frozen=True)
class PointNet2Config(Config):
    """A PointNet++ encoder with L = len(npoints) SA and L FP levels.

    npoints, radii, nsamples: per SA level (centroids, ball radius in input units,
    group size). sa_widths[l]: shared-MLP widths of SA level l. fp_widths[l]: widths
    of the FP step that brings level l+1 back to level l (fp_widths[0] ends at the
    input points; its last width is the output channels).
    """

    npoints: tuple[int, ...]
    radii: tuple[float, ...]
    nsamples: tuple[int, ...]
    sa_widths: tuple[tuple[int, ...], ...]
    fp_widths: tuple[tuple[int, ...], ...]
    batchnorm: bool = True
    normalize_xyz: bool = True

    def __post_init__(self):
        L = len(self.npoints)
        if L < 1 or not (len(self.radii) == len(self.nsamples) == len(self.sa_widths) == len(self.fp_widths) == L):
            raise ValueError("PointNet2Config: npoints, radii, nsamples, sa_widths, fp_widths need one entry per level")
        if any(len(w) == 0 for w in (*self.sa_widths, *self.fp_widths)):
            raise ValueError("PointNet2Config: every level needs at least one MLP width")

    @property
    def out_channels(self) -> int:
        return self.fp_widths[0][-1]


class PointNet2Encoder(nn.Module):
    """Hierarchical per-point features (PointNet++ segmentation network without head).

    forward(xyz (B, N, 3), feats (B, N, C_in), hierarchy: TemplateHierarchy or None)
    -> (B, N, C_out). With a hierarchy (built from the same xyz), FPS, ball query and
    3-NN come from the cache; otherwise they are computed from ``xyz`` on the fly."""

    def __init__(self, config: PointNet2Config, in_channels: int):
        super().__init__()
        self.config = config
        self.in_channels = in_channels
        self.sa = nn.ModuleList()
        chans = [in_channels]
        c = in_channels
        for npt, r, ns, w in zip(config.npoints, config.radii, config.nsamples, config.sa_widths):
            sa = SetAbstraction(npt, r, ns, c, w, config.batchnorm, config.normalize_xyz)
            self.sa.append(sa)
            c = sa.out_channels
            chans.append(c)
        # FP from the coarsest level down; fp[l] maps level l+1 -> level l
        fps: list[FeaturePropagation | None] = [None] * len(config.npoints)
        up = chans[-1]
        for lvl in reversed(range(len(config.npoints))):
            fp = FeaturePropagation(up + chans[lvl], config.fp_widths[lvl], config.batchnorm)
            fps[lvl] = fp
            up = fp.out_channels
        self.fp = nn.ModuleList(fps)
        self.out_channels = up

    def build_hierarchy(self, xyz: torch.Tensor, reuse: TemplateHierarchy | None = None) -> TemplateHierarchy:
        """Cache FPS / ball query / 3-NN of a fixed (N, 3) point set for this encoder
        (levels matching ``reuse``'s first levels are shared, not recomputed)."""
        c = self.config
        return TemplateHierarchy(xyz, c.npoints, c.radii, c.nsamples, reuse=reuse)

    def forward(self, xyz: torch.Tensor, feats: torch.Tensor, hierarchy: TemplateHierarchy | None = None):
        B, N, _ = feats.shape
        if hierarchy is not None:
            if hierarchy.num_levels != len(self.sa) or hierarchy.num_points != N:
                raise ValueError(
                    f"hierarchy has {hierarchy.num_levels} levels over {hierarchy.num_points} points, "
                    f"encoder expects {len(self.sa)} levels over {N}"
                )
            xyz = hierarchy.xyz0[None].expand(B, -1, -1)
        xyzs, featss, interps = [xyz], [feats], []
        for lvl, sa in enumerate(self.sa):
            index = hierarchy.level(lvl) if hierarchy is not None else None
            new_xyz, new_f, index = sa(xyzs[-1], featss[-1], index)
            xyzs.append(new_xyz)
            featss.append(new_f)
            interps.append((index.interp_idx, index.interp_w))
        up = featss[-1]
        for lvl in reversed(range(len(self.sa))):
            up = self.fp[lvl](xyzs[lvl], xyzs[lvl + 1], featss[lvl], up, interps[lvl])
        return up
