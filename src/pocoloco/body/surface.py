"""Body-surface machinery shared by the POP and CloSET baselines: UV rasterisation,
position maps, barycentric sampling of per-vertex data, local frames.

A point on the body surface is a (face id, barycentric) pair; its position on any
posed body of the same mesh is the barycentric blend of the face's posed vertices.
Query points therefore come either from the pixels of a UV map (POP, Ma et al. 2021,
Sec. 3.1-3.2) or from area-uniform samples on the template (CloSET, Zhang et al. 2023,
Sec. 3.1), and can be reused across all frames of a subject.

Conventions (ours; POP's public maps follow the same): for a UV map of resolution R, pixel (i, j) (row i,
column j) samples UV (u, v) = ((j + 0.5) / R, 1 - (i + 0.5) / R), so row 0 is the top
of the texture (v close to 1). Valid pixels are listed in row-major order.

Shapes: B batch (frames), V vertices, F faces, U texture coordinates, P query points,
C channels, R map resolution. Rasterisation is numpy (done once per resolution);
everything applied per frame is torch and differentiable.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from pocoloco.body.anny_body import AnnyBody
from pocoloco.ops import sample_surface
from pocoloco.utils.atomic import atomic_open, save_npz_atomic

__all__ = [
    "BodySurface",
    "PositionMap",
    "UVMapReport",
    "SurfacePoints",
    "UVRaster",
    "barycentric_interpolate",
    "blend_transforms",
    "mean_shape_body",
    "largest_component_faces",
    "pixel_uv",
    "pose_mean_shape",
    "position_map",
    "vertex_normals",
    "rasterize_uv",
    "rasterize_uv_reference",
    "sample_surface_points",
    "uv_island_labels",
    "uv_to_grid",
    "write_uv_map",
]

#: Barycentric tolerance of the inside test: a pixel centre on a shared edge is inside
#: both faces (no cracks from rounding); the lowest face index then wins.
INSIDE_EPS = 1e-9


# ---------------------------------------------------------------------------
# data classes
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SurfacePoints:
    """P points on a triangle mesh, independent of its pose (numpy).

    face_idx:    (P,) int64 face of each point.
    barycentric: (P, 3) float32 weights of the face's three corners (>= 0, sum 1).
    """

    face_idx: np.ndarray
    barycentric: np.ndarray

    def __len__(self) -> int:
        return int(self.face_idx.shape[0])


@dataclass(frozen=True)
class UVRaster:
    """Which face covers each pixel of an R x R UV map, and where (numpy).

    face_idx:    (R, R) int64 covering face, -1 where no face covers the pixel centre.
    barycentric: (R, R, 3) float32 barycentric coordinates of the pixel centre in that
                 face (in the UV triangle, which are also the weights on the 3D face);
                 zero where uncovered.
    coverage:    (R, R) int32 number of faces whose closed UV triangle contains the pixel
                 centre (> 1 only where UV triangles overlap, or for a centre exactly on
                 a shared edge); the lowest face index is kept.
    """

    resolution: int
    face_idx: np.ndarray
    barycentric: np.ndarray
    coverage: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """(R, R) bool: pixels covered by a face."""
        return self.face_idx >= 0

    @property
    def num_valid(self) -> int:
        return int(self.mask.sum())

    @property
    def num_overlapping(self) -> int:
        """Pixels whose centre lies in more than one face."""
        return int((self.coverage > 1).sum())

    def pixels(self) -> np.ndarray:
        """(P, 2) int64 (i, j) of the valid pixels, row-major order."""
        return np.argwhere(self.mask).astype(np.int64)

    def uv(self) -> np.ndarray:
        """(P, 2) float32 UV coordinates of the valid pixel centres, row-major order."""
        return pixel_uv(self.pixels(), self.resolution)

    def points(self) -> SurfacePoints:
        """The valid pixels as surface points (row-major order)."""
        m = self.mask
        return SurfacePoints(self.face_idx[m], self.barycentric[m])


@dataclass(frozen=True)
class PositionMap:
    """UV position map of a batch of posed bodies (torch, dtype/device of the vertices).

    maps: (B, 3, R, R) 3D position of the surface point of each valid pixel, 0 elsewhere.
    mask: (R, R) bool valid pixels.
    """

    maps: torch.Tensor
    mask: torch.Tensor


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 unit vertex normals of a mesh (V, 3) / (F, 3): the area-weighted sum of its
    faces' normals (outward for counter-clockwise faces; zero for a vertex no face uses)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    face_normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length = 2 x area
    n = np.zeros_like(v)
    for corner in range(3):
        np.add.at(n, f[:, corner], face_normals)
    return (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)).astype(np.float32)


# ---------------------------------------------------------------------------
# UV rasterisation
# ---------------------------------------------------------------------------


def pixel_uv(pixels: np.ndarray, resolution: int) -> np.ndarray:
    """(P, 2) integer (i, j) -> (P, 2) float32 (u, v) = ((j + .5) / R, 1 - (i + .5) / R)."""
    p = np.asarray(pixels, dtype=np.float64)
    r = float(resolution)
    return np.stack([(p[:, 1] + 0.5) / r, 1.0 - (p[:, 0] + 0.5) / r], axis=-1).astype(np.float32)


def uv_to_grid(uv: torch.Tensor) -> torch.Tensor:
    """(..., 2) UV in [0, 1] -> (..., 2) ``grid_sample`` coordinates for an (H, W) map
    whose row i holds v = 1 - (i + .5) / H (``align_corners=False``): x = 2u - 1,
    y = 1 - 2v. Sampling a map at a pixel centre's UV returns that pixel exactly."""
    return torch.stack([2 * uv[..., 0] - 1, 1 - 2 * uv[..., 1]], dim=-1)


def _check_uv(uv: np.ndarray, uv_faces: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    uv = np.asarray(uv)
    uv_faces = np.asarray(uv_faces)
    if uv.ndim != 2 or uv.shape[1] != 2 or not np.issubdtype(uv.dtype, np.floating):
        raise ValueError(f"uv must be a float (U, 2) array, got {uv.shape} {uv.dtype}")
    if uv_faces.ndim != 2 or uv_faces.shape[1] != 3 or not np.issubdtype(uv_faces.dtype, np.integer):
        raise ValueError(f"uv_faces must be an integer (F, 3) array, got {uv_faces.shape} {uv_faces.dtype}")
    if uv_faces.size and (uv_faces.min() < 0 or uv_faces.max() >= uv.shape[0]):
        raise ValueError(f"uv_faces index texture coordinates outside [0, {uv.shape[0]})")
    if not np.isfinite(uv).all():
        raise ValueError("uv contains NaN or inf")
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 1:
        raise ValueError(f"resolution must be a positive integer, got {resolution!r}")
    return uv.astype(np.float64), uv_faces.astype(np.int64)


def _check_face_mask(face_mask, num_faces: int) -> np.ndarray:
    if face_mask is None:
        return np.ones(num_faces, dtype=bool)
    m = np.asarray(face_mask)
    if m.shape != (num_faces,) or m.dtype != bool:
        raise ValueError(f"face_mask must be a bool array of shape ({num_faces},), got {m.shape} {m.dtype}")
    return m


def largest_component_faces(faces: np.ndarray) -> np.ndarray:
    """(F,) bool: faces of the largest vertex-connected component of the mesh.

    anny's mesh has four closed components: the body (26,692 faces) plus two eyeballs
    and the mouth interior (teeth/tongue) inside the head; garment models want only
    the body."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, dtype=np.int64)
    F, V = len(faces), int(faces.max()) + 1
    # faces -- vertices incidence; face components = components of the bipartite graph
    n = F + V
    rows = np.repeat(np.arange(F), 3)
    g = sp.coo_matrix((np.ones(3 * F), (rows, F + faces.ravel())), shape=(n, n))
    _, label = connected_components(g, directed=False)
    face_label = label[:F]
    return face_label == np.bincount(face_label).argmax()


def uv_island_labels(uv_faces: np.ndarray) -> np.ndarray:
    """(F,) int64 UV island of each face: faces sharing a texture-coordinate index are
    in the same island. anny 0.6 has 14: head, mouth cavity, torso+limbs, 2 eye sockets,
    2 hands, 2 feet, 4 eyeball halves, mouth interior."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    uv_faces = np.asarray(uv_faces, dtype=np.int64)
    F, U = len(uv_faces), int(uv_faces.max()) + 1
    rows = np.repeat(np.arange(F), 3)
    g = sp.coo_matrix((np.ones(3 * F), (rows, F + uv_faces.ravel())), shape=(F + U, F + U))
    _, label = connected_components(g, directed=False)
    _, label = np.unique(label[:F], return_inverse=True)  # 0..n-1 in order of first face
    return label.astype(np.int64)


def _edge_barycentrics(tri: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Edge functions of points in their triangles, normalised to barycentrics.

    tri: (N, 3, 2) UV corners (a, b, c) of each point's face; px, py: (N,) point.
    Returns (N, 3) float64 (w_a, w_b, w_c); w_a is the edge function of edge b->c over
    twice the signed area, so the weights are right for both windings.
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]

    def edge(p, q):  # cross(q - p, x - p)
        return (q[:, 0] - p[:, 0]) * (py - p[:, 1]) - (q[:, 1] - p[:, 1]) * (px - p[:, 0])

    e = np.stack([edge(b, c), edge(c, a), edge(a, b)], axis=-1)  # (N, 3)
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    return e / area2[:, None]


def _finish(resolution: int, face: np.ndarray, bary: np.ndarray, coverage: np.ndarray) -> UVRaster:
    """Clamp the tolerance-sized negative weights, renormalise, pack as float32."""
    bary = np.clip(bary, 0.0, None)
    s = bary.sum(-1, keepdims=True)
    bary = np.where(s > 0, bary / np.where(s > 0, s, 1), 0.0)
    return UVRaster(int(resolution), face, bary.astype(np.float32), coverage.astype(np.int32))


def rasterize_uv(
    uv: np.ndarray, uv_faces: np.ndarray, resolution: int, *, face_mask: np.ndarray | None = None, chunk: int = 4096
) -> UVRaster:
    """Rasterise a UV layout at R x R with the pixel-centre convention of ``pixel_uv``.

    uv: (U, 2) texture coordinates, uv_faces: (F, 3) their indices per face corner.
    Vectorised over faces: each face's pixel bounding box is expanded into candidate
    pixels (``chunk`` faces at a time to bound memory), and a pixel is inside when the
    three edge functions, normalised to barycentrics, are >= -``INSIDE_EPS`` (either
    winding). Degenerate (zero-area) UV faces cover nothing. Where several faces cover
    a pixel the lowest face index is kept (deterministic) and ``coverage`` counts them.
    ``face_mask`` (F,) bool restricts the faces drawn (face ids still index all F).
    Cost ~ F + (UV area + perimeter terms) x R^2 candidates.
    """
    uv, uv_faces = _check_uv(uv, uv_faces, resolution)
    keep = _check_face_mask(face_mask, len(uv_faces))
    R = int(resolution)
    face_out = np.full(R * R, -1, dtype=np.int64)
    bary_out = np.zeros((R * R, 3), dtype=np.float64)
    coverage = np.zeros(R * R, dtype=np.int64)
    tri_all = uv[uv_faces]  # (F, 3, 2)
    e1, e2 = tri_all[:, 1] - tri_all[:, 0], tri_all[:, 2] - tri_all[:, 0]
    area2 = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])  # (F,) twice the UV area
    for f0 in range(0, len(uv_faces), chunk):
        fid = np.arange(f0, min(f0 + chunk, len(uv_faces)))
        fid = fid[(area2[fid] > 0) & keep[fid]]
        tri = tri_all[fid]  # (f, 3, 2)
        # pixel-index bounding boxes (one pixel of margin; the exact test follows)
        j0 = np.floor(tri[:, :, 0].min(1) * R - 0.5).astype(np.int64)
        j1 = np.ceil(tri[:, :, 0].max(1) * R - 0.5).astype(np.int64)
        i0 = np.floor((1 - tri[:, :, 1].max(1)) * R - 0.5).astype(np.int64)
        i1 = np.ceil((1 - tri[:, :, 1].min(1)) * R - 0.5).astype(np.int64)
        j0, i0 = np.maximum(j0, 0), np.maximum(i0, 0)
        j1, i1 = np.minimum(j1, R - 1), np.minimum(i1, R - 1)
        nj = np.maximum(j1 - j0 + 1, 0)
        ni = np.maximum(i1 - i0 + 1, 0)
        count = ni * nj  # (f,)
        if count.sum() == 0:
            continue
        owner = np.repeat(np.arange(len(fid)), count)  # (N,) candidate -> face in chunk
        k = np.arange(owner.shape[0]) - np.repeat(np.cumsum(count) - count, count)
        nj_o = nj[owner]
        ii = i0[owner] + k // nj_o
        jj = j0[owner] + k % nj_o
        px = (jj + 0.5) / R
        py = 1.0 - (ii + 0.5) / R
        w = _edge_barycentrics(tri[owner], px, py)  # (N, 3)
        inside = (w >= -INSIDE_EPS).all(-1)
        lin = (ii * R + jj)[inside]
        face = fid[owner[inside]]
        w = w[inside]
        coverage += np.bincount(lin, minlength=R * R)
        # candidates are in ascending face order: the first per pixel has the lowest index
        _, first = np.unique(lin, return_index=True)
        lin, face, w = lin[first], face[first], w[first]
        free = face_out[lin] < 0  # earlier chunks hold lower face indices
        face_out[lin[free]] = face[free]
        bary_out[lin[free]] = w[free]
    return _finish(R, face_out.reshape(R, R), bary_out.reshape(R, R, 3), coverage.reshape(R, R))


def rasterize_uv_reference(
    uv: np.ndarray, uv_faces: np.ndarray, resolution: int, *, face_mask: np.ndarray | None = None
) -> UVRaster:
    """Slow reference for ``rasterize_uv``: a python loop over pixels; for each pixel
    centre the barycentrics in every face from sub-triangle areas (Cramer's rule) and
    a point-in-triangle test; the first (lowest-index) containing face is kept."""
    uv, uv_faces = _check_uv(uv, uv_faces, resolution)
    R = int(resolution)
    keep = _check_face_mask(face_mask, len(uv_faces))
    a, b, c = (uv[uv_faces[:, k]] for k in range(3))  # (F, 2) each

    def cross(p, q, x):  # signed doubled area of the triangle (p, q, x)
        return (q[:, 0] - p[:, 0]) * (x[1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (x[0] - p[:, 0])

    total = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])  # (F,)
    ok = (total != 0) & keep
    face = np.full((R, R), -1, dtype=np.int64)
    bary = np.zeros((R, R, 3))
    coverage = np.zeros((R, R), dtype=np.int64)
    for i in range(R):
        for j in range(R):
            x = ((j + 0.5) / R, 1.0 - (i + 0.5) / R)
            with np.errstate(divide="ignore", invalid="ignore"):
                w = np.stack([cross(x_b, x_c, x) for x_b, x_c in ((b, c), (c, a), (a, b))], -1) / total[:, None]
            hit = np.flatnonzero(ok & (w >= -INSIDE_EPS).all(-1))
            coverage[i, j] = hit.size
            if hit.size:
                face[i, j] = hit[0]
                bary[i, j] = w[hit[0]]
    return _finish(R, face, bary, coverage)


# ---------------------------------------------------------------------------
# per-frame ops (torch, differentiable)
# ---------------------------------------------------------------------------


def _as_index(x, name: str, device) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(x) if isinstance(x, np.ndarray) else x, device=device)
    if t.is_floating_point():
        raise ValueError(f"{name} must be an integer array, got {t.dtype}")
    return t.long()


def _gather_corners(values: torch.Tensor, faces, face_idx, bary, name: str):
    """values (B, V, *D) -> corner values (B, P, 3, *D) and weights (P, 3) or (B, P, 3)."""
    if values.ndim < 3:
        raise ValueError(f"{name} must have shape (B, V, ...), got {tuple(values.shape)}")
    device = values.device
    faces = _as_index(faces, "faces", device)
    face_idx = _as_index(face_idx, "face_idx", device)
    bary = torch.as_tensor(bary, device=device).to(values.dtype)
    B, V = values.shape[:2]
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {tuple(faces.shape)}")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= V):
        raise ValueError(f"faces index vertices outside [0, V={V}) of {name}")
    if face_idx.ndim not in (1, 2) or (face_idx.ndim == 2 and face_idx.shape[0] != B):
        raise ValueError(f"face_idx must have shape (P,) or (B={B}, P), got {tuple(face_idx.shape)}")
    if bary.shape != (*face_idx.shape, 3):
        raise ValueError(f"barycentric must have shape {(*face_idx.shape, 3)}, got {tuple(bary.shape)}")
    if face_idx.numel() and (int(face_idx.min()) < 0 or int(face_idx.max()) >= faces.shape[0]):
        raise ValueError(f"face_idx outside [0, F={faces.shape[0]})")
    corner = faces[face_idx]  # (P, 3) or (B, P, 3)
    if corner.ndim == 2:
        out = values[:, corner]  # (B, P, 3, *D)
    else:
        rows = torch.arange(B, device=device)[:, None, None]
        out = values[rows, corner]  # (B, P, 3, *D)
    return out, bary


def barycentric_interpolate(values, faces, face_idx, barycentric) -> torch.Tensor:
    """Per-vertex values at surface points (CloSET Sec. 3.1: the feature of a surface
    point is the barycentric blend of its face's three vertex features).

    values: (B, V, C) (or (B, V, *D)); faces: (F, 3); face_idx: (P,) shared by the
    batch, or (B, P); barycentric: matching (P, 3) / (B, P, 3).
    Returns (B, P, C) in the dtype/device of ``values``; differentiable w.r.t. values
    and barycentric.
    """
    values = torch.as_tensor(values)
    corners, w = _gather_corners(values, faces, face_idx, barycentric, "values")
    if w.ndim == 2:
        w = w.expand(values.shape[0], *w.shape)  # (B, P, 3)
    w = w.reshape(*w.shape, *([1] * (values.ndim - 2)))
    return (corners * w).sum(2)


def position_map(vertices, faces, raster: UVRaster) -> PositionMap:
    """POP's UV positional map (Ma et al. 2021, Sec. 3.2): (B, V, 3) posed vertices ->
    (B, 3, R, R) positions of each valid pixel's surface point, zeros elsewhere.

    Transpose to (B, R, R, 3) for POP's packed ``posmap*`` (H, W, 3) layout."""
    vertices = torch.as_tensor(vertices)
    if vertices.ndim != 3 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices must have shape (B, V, 3), got {tuple(vertices.shape)}")
    R = raster.resolution
    mask = torch.from_numpy(raster.mask).to(vertices.device)
    pts = raster.points()
    p = barycentric_interpolate(vertices, faces, pts.face_idx, pts.barycentric)  # (B, P, 3)
    flat = vertices.new_zeros(vertices.shape[0], R * R, 3)
    idx = torch.from_numpy(np.flatnonzero(raster.mask)).to(vertices.device)
    flat = flat.index_copy(1, idx, p)  # row-major, like raster.points()
    return PositionMap(flat.reshape(-1, R, R, 3).permute(0, 3, 1, 2), mask)


def blend_transforms(
    vtransf, faces, face_idx, barycentric, mode: Literal["blend", "polar"] = "blend"
) -> torch.Tensor:
    """Local frames T_i of surface points from per-vertex skinning transforms.

    POP Eq. (2), x_i = T_i r_i + p_i, with T_i the barycentric blend of the face's three
    ``vtransf`` (LoopReg-style, POP Sec. 3.1). vtransf: (B, V, 3, 3); face_idx (P,) or
    (B, P); barycentric (P, 3) or (B, P, 3). Returns (B, P, 3, 3).

    mode: "blend" (default, as POP) = the plain blend (not exactly a rotation: LBS
    blends of rotations shrink); "polar" = its orthogonal polar factor U V^T from the
    SVD (the closest rotation; the sign of the last singular vector is flipped if
    needed so that det = +1).
    """
    vtransf = torch.as_tensor(vtransf)
    if vtransf.ndim != 4 or vtransf.shape[-2:] != (3, 3):
        raise ValueError(f"vtransf must have shape (B, V, 3, 3), got {tuple(vtransf.shape)}")
    if mode not in ("blend", "polar"):
        raise ValueError(f"mode must be 'blend' or 'polar', got {mode!r}")
    t = barycentric_interpolate(vtransf, faces, face_idx, barycentric)  # (B, P, 3, 3)
    if mode == "blend":
        return t
    u, _, vh = torch.linalg.svd(t)
    d = torch.sign(torch.linalg.det(u @ vh))  # (B, P)
    d = torch.where(d == 0, torch.ones_like(d), d)
    u = torch.cat([u[..., :2], u[..., 2:] * d[..., None, None]], dim=-1)
    return u @ vh


# ---------------------------------------------------------------------------
# surface samples, mean-shape body, a per-subject bundle
# ---------------------------------------------------------------------------


def sample_surface_points(
    vertices, faces, num: int, seed: int = 0, *, face_mask: np.ndarray | None = None
) -> SurfacePoints:
    """``num`` points uniform by area on the mesh (``pocoloco.ops.sample_surface``),
    kept as (face id, barycentric) so one draw on a subject's template can be placed
    on every posed frame with ``barycentric_interpolate``. Note the density is uniform
    on the mesh given (use the template, not a posed frame, for a pose-free draw).
    ``face_mask`` (F,) bool: sample only those faces (returned ids index all F)."""
    faces = np.asarray(faces)
    keep = np.flatnonzero(_check_face_mask(face_mask, len(faces)))
    s = sample_surface(np.asarray(vertices, dtype=np.float64), faces[keep], num, seed=seed)
    return SurfacePoints(keep[np.asarray(s.face_idx)].astype(np.int64), np.asarray(s.barycentric, np.float32))


@functools.lru_cache(maxsize=1)
def mean_shape_body():
    """The anny body with default phenotype (every parameter 0.5), built once per
    process. POP feeds the posed mean shape to its pose encoder (Sec. 3.2)."""
    return AnnyBody()


def pose_mean_shape(joint_rotvecs, root_translation=None):
    """``mean_shape_body().pose(...)``: (T, 24, 3) rotations (anny local-ref axis-angle)
    -> PosedBody of the mean-shape body in the same poses."""
    return mean_shape_body().pose(joint_rotvecs, root_translation)


def pose_mean_shape_vertices(joint_rotvecs, chunk: int = 32) -> np.ndarray:
    """(T, 24, 3) rotations -> (T, V, 3) float32 vertices of the posed mean-shape body, centred
    on its root joint (POP's pose-encoder input, Sec. 3.2). Same vertices as
    :func:`pose_mean_shape` without the per-vertex skinning transforms (~8x faster)."""
    body = mean_shape_body()
    rot = torch.as_tensor(np.asarray(joint_rotvecs, dtype=np.float32))
    if rot.ndim != 3 or rot.shape[1:] != (24, 3):
        raise ValueError(f"joint_rotvecs must have shape (T, 24, 3), got {tuple(rot.shape)}")
    out = []
    for i in range(0, rot.shape[0], chunk):
        r = body.run_anny(rot[i : i + chunk])
        root = r["bone_poses"][:, body.bone_of_joint[0], :3, 3]  # (t, 3)
        out.append((r["vertices"] - root[:, None]).numpy().astype(np.float32))
    return np.concatenate(out)


class BodySurface:
    """One mesh's surface helpers with rasters cached per resolution.

    faces (F, 3), uv (U, 2), uv_faces (F, 3) as on ``AnnyBody``; face_mask (F,) bool
    the faces that carry query points (None = all). ``BodySurface.from_body(body)``
    keeps only the body component (drops anny's eyeballs and mouth interior).
    """

    def __init__(self, faces: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray, face_mask: np.ndarray | None = None):
        self.faces = np.asarray(faces, dtype=np.int64)
        self.uv, self.uv_faces = _check_uv(uv, uv_faces, 1)
        if self.uv_faces.shape != self.faces.shape:
            raise ValueError(f"uv_faces {self.uv_faces.shape} and faces {self.faces.shape} must match")
        self.face_mask = _check_face_mask(face_mask, len(self.faces))
        self._rasters: dict[int, UVRaster] = {}

    @classmethod
    def from_body(cls, body, body_only: bool = True) -> BodySurface:
        mask = largest_component_faces(body.faces) if body_only else None
        return cls(body.faces, body.uv, body.uv_faces, mask)

    def raster(self, resolution: int) -> UVRaster:
        if resolution not in self._rasters:
            self._rasters[resolution] = rasterize_uv(self.uv, self.uv_faces, resolution, face_mask=self.face_mask)
        return self._rasters[resolution]

    def sample(self, vertices, num: int, seed: int = 0) -> SurfacePoints:
        """``num`` area-uniform points on ``vertices`` (V, 3) (e.g. the template)."""
        return sample_surface_points(vertices, self.faces, num, seed, face_mask=self.face_mask)

    def position_map(self, vertices, resolution: int) -> PositionMap:
        return position_map(vertices, self.faces, self.raster(resolution))

    def points_uv(self, points: SurfacePoints) -> np.ndarray:
        """(P, 2) float32 UV coordinates of surface points (exact pixel centres for
        points from ``raster(R).points()``)."""
        w = points.barycentric.astype(np.float64)
        uv = barycentric_interpolate(self.uv[None], self.uv_faces, points.face_idx, w)  # (1, P, 2)
        return uv[0].numpy().astype(np.float32)

    def interpolate(self, values, points: SurfacePoints) -> torch.Tensor:
        """(B, V, ...) per-vertex values -> (B, P, ...) at ``points``."""
        return barycentric_interpolate(values, self.faces, points.face_idx, points.barycentric)

    def frames(self, vtransf, points: SurfacePoints, mode: Literal["blend", "polar"] = "blend") -> torch.Tensor:
        """(B, V, 3, 3) skinning transforms -> (B, P, 3, 3) local frames at ``points``."""
        return blend_transforms(vtransf, self.faces, points.face_idx, points.barycentric, mode)


# ---------------------------------------------------------------------------
# UV map files (``pocoloco uvmap``)
# ---------------------------------------------------------------------------


@dataclass
class UVMapReport:
    """What :func:`write_uv_map` wrote: resolution R, valid pixels, pixels covered by > 1 face."""

    resolution: int
    num_valid: int
    num_overlapping: int


def write_uv_map(out: str, resolution: int = 256, phenotype: dict[str, float] | None = None, all_faces: bool = False,
                 png: str | None = None) -> UVMapReport:  # fmt: skip
    """Rasterise anny's UV layout at R x R and write the pixel -> (face, barycentric) tables and the
    template's position map (R, R, 3) to ``out`` (.npz: face_idx, barycentric, mask, uv, posmap,
    resolution); ``png``: also the position map as an image. ``all_faces``: also the eyeballs and
    the mouth interior (default: body only)."""
    if resolution < 1 or resolution > 4096:
        raise ValueError(f"--resolution must be in [1, 4096], got {resolution}")
    if not str(out).endswith(".npz"):
        raise ValueError(f"--out must end with .npz, got {str(out)!r}")
    if png and not str(png).endswith(".png"):
        raise ValueError(f"--png must end with .png, got {str(png)!r}")
    body = AnnyBody(phenotype or {})
    surface = BodySurface.from_body(body, body_only=not all_faces)
    r = surface.raster(resolution)
    pm = surface.position_map(torch.from_numpy(body.template[None]), resolution).maps[0]
    posmap = pm.permute(1, 2, 0).numpy()  # (R, R, 3) like POP's posmap* arrays
    save_npz_atomic(out, face_idx=r.face_idx, barycentric=r.barycentric, mask=r.mask, uv=r.uv(),
                    posmap=posmap, resolution=np.int64(resolution))  # fmt: skip
    if png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        lo, hi = posmap[r.mask].min(0), posmap[r.mask].max(0)
        img = np.where(r.mask[..., None], (posmap - lo) / np.maximum(hi - lo, 1e-9), 1.0)
        with atomic_open(png) as f:
            plt.imsave(f, np.clip(img, 0, 1), format="png")
    return UVMapReport(resolution, int(r.num_valid), int(r.num_overlapping))
