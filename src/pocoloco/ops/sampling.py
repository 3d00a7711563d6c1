"""Point sampling: farthest point sampling and uniform surface sampling of triangle meshes.

Shapes: B batch, N points, S samples, V vertices, F faces.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

FPSBackend = Literal["auto", "torch", "fpsample"]


# ---------------------------------------------------------------------------
# farthest point sampling
# ---------------------------------------------------------------------------


def _check_fps(points: torch.Tensor, num: int, start_index: int) -> None:
    if points.ndim != 3 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (B, N, 3), got {tuple(points.shape)}")
    n = points.shape[1]
    if not 1 <= num <= n:
        raise ValueError(f"num must be in [1, N={n}], got {num}")
    if not 0 <= start_index < n:
        raise ValueError(f"start_index must be in [0, N={n}), got {start_index}")


def fpsample_available() -> bool:
    try:
        import fpsample  # noqa: F401
    except ImportError:
        return False
    return True


def farthest_point_sampling(
    points: torch.Tensor, num: int, start_index: int = 0, *, backend: FPSBackend = "auto"
) -> torch.Tensor:
    """Greedy farthest point sampling (Eldar et al. 1997; PointNet++ Sec. 3.2).

    points: (B, N, 3). Returns idx: (B, S=num) int64. idx[:, 0] = start_index; each next
    index maximises the distance to the already chosen set (ties: the lowest index).

    backend: "torch" = a vectorised loop over the S samples (O(S N) work per cloud, any
    device); "fpsample" = the optional ``fpsample`` package's C++ vanilla FPS (CPU,
    not a dependency of pocoloco: ``pip install fpsample``); "auto" = fpsample for CPU
    tensors when it is installed, else torch. Both give the same indices up to exact ties.
    """
    _check_fps(points, num, start_index)
    if backend not in ("auto", "torch", "fpsample"):
        raise ValueError(f"backend must be 'auto', 'torch' or 'fpsample', got {backend!r}")
    use_lib = backend == "fpsample" or (backend == "auto" and points.device.type == "cpu" and fpsample_available())
    if use_lib:
        import fpsample

        pts = points.detach().cpu().numpy()
        idx = np.stack([fpsample.fps_sampling(p, num, start_idx=start_index) for p in pts])
        return torch.from_numpy(idx.astype(np.int64)).to(points.device)

    B, N, _ = points.shape
    pts = points.detach()
    idx = torch.empty(B, num, dtype=torch.long, device=points.device)
    idx[:, 0] = start_index
    min_d = torch.full((B, N), float("inf"), dtype=pts.dtype, device=pts.device)  # (B, N)
    cur = torch.full((B,), start_index, dtype=torch.long, device=pts.device)
    rows = torch.arange(B, device=pts.device)
    for i in range(1, num):
        d = ((pts - pts[rows, cur][:, None, :]) ** 2).sum(-1)  # (B, N)
        min_d = torch.minimum(min_d, d)
        cur = min_d.argmax(dim=-1)  # first maximal value on ties
        idx[:, i] = cur
    return idx


def farthest_point_sampling_reference(points: torch.Tensor, num: int, start_index: int = 0) -> torch.Tensor:
    """Slow reference for ``farthest_point_sampling``: plain python loops over floats."""
    _check_fps(points, num, start_index)
    out = []
    for cloud in points.detach().cpu().tolist():
        chosen = [start_index]
        min_d = [float("inf")] * len(cloud)
        for _ in range(1, num):
            c = cloud[chosen[-1]]
            best, best_d = 0, -1.0
            for n, p in enumerate(cloud):
                d = (p[0] - c[0]) ** 2 + (p[1] - c[1]) ** 2 + (p[2] - c[2]) ** 2
                min_d[n] = min(min_d[n], d)
                if min_d[n] > best_d:
                    best, best_d = n, min_d[n]
            chosen.append(best)
        out.append(chosen)
    return torch.tensor(out, dtype=torch.long, device=points.device)


# ---------------------------------------------------------------------------
# surface sampling
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SurfaceSample:
    """Points sampled on a triangle mesh (same array type as the input vertices).

    points:      (N, 3) positions.
    face_idx:    (N,) int64 face of each point.
    barycentric: (N, 3) weights of the face's three vertices (non-negative, sum 1).
    normals:     (N, 3) unit normal of the face (right-hand rule on its vertex order).
    """

    points: torch.Tensor | np.ndarray
    face_idx: torch.Tensor | np.ndarray
    barycentric: torch.Tensor | np.ndarray
    normals: torch.Tensor | np.ndarray


def sample_surface(vertices, faces, num: int, seed: int = 0) -> SurfaceSample:
    """Sample ``num`` points uniformly by area on a triangle mesh.

    vertices: (V, 3) float, faces: (F, 3) int; torch tensors or numpy arrays (the
    result uses the same type, dtype and device as ``vertices``). A face is drawn with
    probability area / total area, then a point uniformly inside it by folding the unit
    square: u, v ~ U(0, 1), (u, v) -> (1 - u, 1 - v) if u + v > 1, barycentric
    (1 - u - v, u, v). Deterministic for a given ``seed`` (torch CPU generator).
    """
    as_numpy = isinstance(vertices, np.ndarray)
    v = torch.as_tensor(vertices)
    f = torch.as_tensor(faces, device=v.device)
    if v.ndim != 2 or v.shape[1] != 3 or not v.is_floating_point():
        raise ValueError(f"vertices must be a float (V, 3) array, got {tuple(v.shape)} {v.dtype}")
    if f.ndim != 2 or f.shape[1] != 3 or f.is_floating_point() or f.shape[0] == 0:
        raise ValueError(f"faces must be a non-empty integer (F, 3) array, got {tuple(f.shape)} {f.dtype}")
    if int(f.min()) < 0 or int(f.max()) >= v.shape[0]:
        raise ValueError(f"faces index vertices outside [0, {v.shape[0]})")
    if num < 0:
        raise ValueError(f"num must be >= 0, got {num}")
    f = f.long()
    tri = v[f].double()  # (F, 3, 3)
    cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3)
    area2 = cross.norm(dim=-1)  # (F,) twice the area
    if not float(area2.sum()) > 0:
        raise ValueError("mesh has zero total area")

    g = torch.Generator().manual_seed(int(seed))
    face_idx = torch.multinomial(area2.cpu(), num, replacement=True, generator=g).to(v.device)  # (N,)
    uv = torch.rand(num, 2, generator=g, dtype=torch.float64).to(v.device)  # (N, 2)
    fold = uv.sum(-1) > 1
    uv = torch.where(fold[:, None], 1 - uv, uv)
    bary = torch.cat([1 - uv.sum(-1, keepdim=True), uv], dim=-1)  # (N, 3)
    points = (bary[:, :, None] * tri[face_idx]).sum(1)  # (N, 3)
    normals = cross[face_idx] / area2[face_idx].clamp_min(1e-300)[:, None]

    out = [points.to(v.dtype), face_idx, bary.to(v.dtype), normals.to(v.dtype)]
    if as_numpy:
        out = [t.cpu().numpy() for t in out]
    return SurfaceSample(*out)
