"""Watertight meshes from point clouds: screened Poisson surface reconstruction (``pocoloco mesh``).
 The surface is the level set of an indicator
function chi whose gradient best matches the oriented normal field V of the
samples, with a screening term pulling chi's level set through the samples
(Kazhdan & Hoppe, "Screened Poisson Surface Reconstruction", ToG 2013, eq. 3
minimised over an adaptive octree of depth ``depth``). We use open3d's
implementation (``TriangleMesh.create_from_point_cloud_poisson``).

Normals, when the cloud has none, are estimated by PCA over the k nearest
neighbours and made consistent by propagation over a Riemannian graph
(Hoppe et al., "Surface reconstruction from unorganized points", SIGGRAPH 1992,
sec. 3.3; open3d ``orient_normals_consistent_tangent_plane``). Propagation
fixes the orientation only up to one global sign, which is chosen so that the
most extreme points along +-x, +-y, +-z point outwards (a closed surface's
outward normal at its extreme point along an axis points along that axis).
Propagation fails on thin parts seen from both sides (hands, feet, arms held
close to the body): a flipped patch becomes a Poisson "balloon". When the cloud's
pose is known (``joints``), each PCA normal is instead turned away from the
nearest bone segment of the skeleton (a human surface faces away from its
bones), which needs no propagation (:func:`skeleton_outward`).

Body refinement (``--refine-body``, the PocoLoco paper's appendix A.2): generated clouds are
weakest on the head and hands. The anny body is fitted to the cloud
(:func:`pocoloco.body.anny_body.fit_body_to_cloud`: pose from the joints, then pose and shape
refined to the cloud's head and hands), the cloud points nearest to the fitted body's head and
hands are removed and replaced by points sampled area-uniformly on those parts of the fitted
body (with its face normals), and the result is meshed as usual (:func:`replace_parts`).

Density trimming: Poisson returns, per vertex, the octree depth at which the
samples supporting it were splatted (about one unit per factor 4 of sample
density on a surface). Where the input has holes, the reconstruction bridges
them with surface supported by few samples. A vertex is removed when its
density is in the lowest ``density_quantile`` fraction AND it is farther than
``far_factor`` times the typical sample spacing (median nearest-neighbour
distance r_m) from every input point. For uniform random samples a surface
point has no sample within c * r_m with probability exp(-ln 2 * c^2) (2^-16 for
c = 4), so on a densely sampled closed surface nothing is removed (the mesh stays
watertight), while where Poisson filled a real opening the filling is cut away
(the mesh is then honestly not watertight).
"""

from __future__ import annotations

import os
import time
from typing import NamedTuple

import numpy as np

from pocoloco.apps.common import check_scan
from pocoloco.body.anny_body import fit_body_to_cloud
from pocoloco.body.skeleton import JOINT_PARENTS
from pocoloco.body.surface import vertex_normals
from pocoloco.data.published import check_cloud, read_ply, write_ply
from pocoloco.viz.render import render_mesh, render_meshes

__all__ = ["PoissonMesh", "MeshReport", "RefineReport", "estimate_normals", "skeleton_outward", "mesh_from_points",
           "mesh_report",
           "is_watertight", "mesh_ply", "replace_parts", "refine_body_ply"]  # fmt: skip

#: Fewer points than this cannot describe a surface worth reconstructing.
MIN_POINTS = 100
# Open3D's multi-threaded Poisson solver crashes the process now and then (a data race, Open3D
# issues #6828 / #7229; it segfaulted our CI once in ~100 runs). One thread costs ~10 % on 2 cores.
POISSON_THREADS = 1


class PoissonMesh(NamedTuple):
    """A triangle mesh. vertices: (V, 3) float32; faces: (F, 3) int64 indices into vertices."""

    vertices: np.ndarray
    faces: np.ndarray


class MeshReport(NamedTuple):
    """Summary of a mesh for the user: sizes, trimesh watertightness, seconds spent."""

    num_vertices: int
    num_faces: int
    watertight: bool
    seconds: float


def _check_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {pts.shape}")
    if not np.isfinite(pts).all():
        bad = int((~np.isfinite(pts)).any(axis=1).sum())
        raise ValueError(f"{name} has {bad} row(s) with NaN or infinite values")
    return pts


def _open3d():
    try:
        import open3d as o3d
    except ImportError:  # pragma: no cover - open3d is in the synth extra
        raise ValueError("pocoloco mesh needs open3d: pip install 'pocoloco[synth]'") from None
    return o3d


def _extreme_vote(points: np.ndarray, normals: np.ndarray, k: int = 10) -> float:
    """Sum over the k most extreme points along each of +-x, +-y, +-z of sign(n . axis direction).

    Positive when the normals point outwards. points, normals: (N, 3).
    """
    votes = 0.0
    k = max(1, min(k, len(points) // 6))
    for axis in range(3):
        for sign in (1.0, -1.0):
            idx = np.argpartition(-sign * points[:, axis], k - 1)[:k]
            votes += float(np.sign(sign * normals[idx, axis]).sum())
    return votes


def skeleton_outward(points: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Direction from the nearest bone segment of the skeleton to each point.

    points: (N, 3); joints: (J, 3) in the same frame, bones = (joint, parent) pairs of
    ``JOINT_PARENTS``. Returns (N, 3) float64 vectors p - c(p), c(p) the closest point on the
    nearest segment (not normalised; zero for a point on a bone).
    """
    pts = np.asarray(points, np.float64)
    J = np.asarray(joints, np.float64)
    if J.shape != (len(JOINT_PARENTS), 3):
        raise ValueError(f"joints must have shape ({len(JOINT_PARENTS)}, 3), got {J.shape}")
    best = np.full(len(pts), np.inf)
    out = np.zeros_like(pts)
    for child, parent in enumerate(JOINT_PARENTS):
        if parent < 0:
            continue
        a, ab = J[parent], J[child] - J[parent]
        t = np.clip((pts - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        d = pts - (a + t[:, None] * ab)  # (N, 3)
        dist = np.einsum("ij,ij->i", d, d)
        closer = dist < best
        best[closer], out[closer] = dist[closer], d[closer]
    return out


def estimate_normals(points: np.ndarray, knn: int = 30, joints: np.ndarray | None = None) -> np.ndarray:
    """Unit normals for a cloud that has none, oriented outwards.

    PCA normals over ``knn`` neighbours. Without ``joints``: orientation propagated over the
    k-NN graph (Hoppe et al. 1992), global sign by :func:`_extreme_vote`. With ``joints`` ((24, 3),
    the cloud's pose): each normal turned away from its nearest bone (:func:`skeleton_outward`).
    points: (N, 3) -> (N, 3) float32.
    """
    o3d = _open3d()
    pts = _check_points(points)
    if knn < 3:
        raise ValueError(f"knn must be >= 3, got {knn}")
    k = min(knn, len(pts) - 1)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    if joints is not None:
        n = np.asarray(pc.normals).copy()
        flip = np.einsum("ij,ij->i", n, skeleton_outward(pts, joints)) < 0
        n[flip] *= -1
        return n.astype(np.float32)
    pc.orient_normals_consistent_tangent_plane(k)
    n = np.asarray(pc.normals).copy()
    if _extreme_vote(pts, n) < 0:
        n = -n
    return n.astype(np.float32)


def mesh_from_points(
    points: np.ndarray,
    normals: np.ndarray | None = None,
    depth: int = 8,
    density_quantile: float = 0.0,
    far_factor: float = 4.0,
    scale: float = 1.5,
    knn: int = 30,
    min_component_share: float = 0.01,
    joints: np.ndarray | None = None,
) -> PoissonMesh:
    """Screened Poisson reconstruction (Kazhdan & Hoppe 2013) of an oriented cloud.

    Args:
        points: (N, 3) positions, N >= ``MIN_POINTS``, finite.
        normals: (N, 3) outward normals (need not be unit), or None to estimate them
            (:func:`estimate_normals` with ``knn`` neighbours).
        depth: octree depth (resolution ~ bounding-box size * scale / 2**depth), 1..12.
        density_quantile: at most this fraction of vertices (the lowest-density ones) is trimmed;
            0 disables trimming. Only those also farther than ``far_factor`` x the typical sample
            spacing from every input point are removed (see the module docstring).
        far_factor: see above.
        scale: reconstruction cube / bounding-box ratio; > 1 leaves room to close open regions.
            Doubled (up to twice, with depth + 1) when the surface reaches the cube's faces.
        knn: neighbours for normal estimation (only when ``normals`` is None).
        min_component_share: connected components with fewer faces than this fraction of the
            largest one are removed (stray bubbles); 0 keeps all.
        joints: (24, 3) the cloud's pose, to orient estimated normals away from the bones
            (only when ``normals`` is None; see :func:`estimate_normals`).
    Returns:
        :class:`PoissonMesh` (vertices (V, 3) float32, faces (F, 3) int64).
    Raises:
        ValueError (one line) on empty, too sparse, non-finite or degenerate input.
    """
    pts = _check_points(points)
    if len(pts) == 0:
        raise ValueError("point cloud is empty")
    if len(pts) < MIN_POINTS:
        raise ValueError(f"point cloud too sparse to mesh: {len(pts)} points (need at least {MIN_POINTS})")
    if not 1 <= int(depth) <= 12:
        raise ValueError(f"depth must be in 1..12, got {depth}")
    if not 0.0 <= density_quantile < 1.0:
        raise ValueError(f"density quantile must be in [0, 1), got {density_quantile}")
    if far_factor < 0:
        raise ValueError(f"far factor must be >= 0, got {far_factor}")
    if scale < 1.0:
        raise ValueError(f"scale must be >= 1, got {scale}")
    if not 0.0 <= min_component_share <= 1.0:
        raise ValueError(f"min component share must be in [0, 1], got {min_component_share}")
    extent = np.ptp(pts, axis=0)
    if np.sort(extent)[1] <= 1e-9 * max(float(extent.max()), 1e-30):
        raise ValueError("point cloud is degenerate (all points on a line or a single point)")
    if normals is None:
        nrm = estimate_normals(pts, knn=knn, joints=joints).astype(np.float64)
    else:
        nrm = _check_points(normals, "normals")
        if nrm.shape != pts.shape:
            raise ValueError(f"normals must have shape {pts.shape}, got {nrm.shape}")
        length = np.linalg.norm(nrm, axis=1, keepdims=True)
        if (length < 1e-12).any():
            raise ValueError(f"normals has {int((length < 1e-12).sum())} zero-length row(s)")
        nrm = nrm / length
    o3d = _open3d()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.normals = o3d.utility.Vector3dVector(nrm)
    lo, hi = pts.min(0), pts.max(0)
    for attempt in range(3):
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
                pc, depth=int(depth), scale=float(scale), linear_fit=False, n_threads=POISSON_THREADS
            )
        # Where the cloud is open the surface may extrapolate out of the reconstruction cube
        # (centre of the bounding box, side scale * its longest extent) and get cut there:
        # retry in a cube twice as large, one octree level deeper (same cells), so it closes inside.
        side = scale * float((hi - lo).max())
        gap = np.abs(np.asarray(mesh.vertices) - (lo + hi) / 2).max() if len(mesh.vertices) else 0.0
        if side / 2 - gap > 2 * side / 2 ** int(depth) or attempt == 2 or depth >= 12:
            break
        scale, depth = scale * 2, depth + 1  # same cell size
    densities = np.asarray(densities)
    if density_quantile > 0 and len(densities):
        from scipy.spatial import cKDTree

        tree = cKDTree(pts)
        spacing = float(np.median(tree.query(pts, k=2)[0][:, 1]))  # typical sample spacing
        far = tree.query(np.asarray(mesh.vertices))[0] > far_factor * spacing
        mesh.remove_vertices_by_mask(far & (densities <= np.quantile(densities, density_quantile)))
    faces = _cancel_face_pairs(np.asarray(mesh.triangles, dtype=np.int64))
    if len(faces) == 0:
        raise ValueError("Poisson reconstruction produced no surface (are the normals consistent?)")
    faces = _drop_small_components(faces, len(mesh.vertices), min_component_share)
    all_vertices, faces = _split_nonmanifold_edges(np.asarray(mesh.vertices, dtype=np.float32), faces)
    used = np.unique(faces)
    remap = np.full(len(all_vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    vertices = all_vertices[used]
    return PoissonMesh(vertices, remap[faces])


def _split_nonmanifold_edges(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Make edges shared by more than two faces manifold by giving each sheet its own vertices.

    Marching cubes emits an edge used by four faces where two sheets of the surface touch along
    one cube edge (the surface is closed, but not a 2-manifold there, so ``is_watertight`` fails).
    At every endpoint v of such an edge, v's faces are grouped by adjacency across edges of v
    used by exactly two faces; each group after the first gets a copy of v (same position).
    (V, 3), (F, 3) -> (V', 3), (F, 3) with V' >= V.
    """
    if len(faces) == 0:
        return vertices, faces
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)  # (3F, 2)
    uniq, inv, counts = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    bad = np.flatnonzero(counts > 2)
    if len(bad) == 0:
        return vertices, faces
    inv = inv.reshape(-1)
    face_of_edge = np.tile(np.arange(len(faces)), 3)
    faces = faces.copy()
    new_vertices = [vertices]
    next_id = len(vertices)
    for v in np.unique(uniq[bad].reshape(-1)):
        fv = np.flatnonzero((faces == v).any(1))  # faces at v (indices may have been renumbered: none yet for v)
        parent = {int(f): int(f) for f in fv}

        def find(f: int) -> int:
            while parent[f] != f:
                parent[f] = parent[parent[f]]
                f = parent[f]
            return f

        rows = np.flatnonzero(np.isin(face_of_edge, fv) & (e == v).any(1) & (counts[inv] == 2))
        by_edge: dict[int, list[int]] = {}
        for r in rows:
            by_edge.setdefault(int(inv[r]), []).append(int(face_of_edge[r]))
        for pair in by_edge.values():
            if len(pair) == 2:
                parent[find(pair[0])] = find(pair[1])
        groups: dict[int, list[int]] = {}
        for f in fv:
            groups.setdefault(find(int(f)), []).append(int(f))
        for members in list(groups.values())[1:]:
            for f in members:
                faces[f][faces[f] == v] = next_id
            new_vertices.append(vertices[v][None])
            next_id += 1
    return np.concatenate(new_vertices).astype(vertices.dtype), faces


def _cancel_face_pairs(faces: np.ndarray) -> np.ndarray:
    """Drop coincident triangles of opposite winding in pairs (zero-volume fins that Poisson's
    marching cubes occasionally emits) and same-winding duplicates. (F, 3) -> (F', 3)."""
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    dup = np.flatnonzero(counts > 1)
    if len(dup) == 0:
        return faces
    keep = np.ones(len(faces), dtype=bool)
    for g in dup:
        members = np.flatnonzero(inv == g)
        # winding parity: rotate so the smallest index comes first; even if the rest ascends
        parity = []
        for f in faces[members]:
            r = np.roll(f, -int(np.argmin(f)))
            parity.append(1 if r[1] < r[2] else -1)
        net = int(np.sum(parity))
        keep[members] = False
        if net != 0:  # one copy of the surviving orientation
            keep[members[parity.index(1 if net > 0 else -1)]] = True
    return faces[keep]


def _drop_small_components(faces: np.ndarray, num_vertices: int, min_share: float) -> np.ndarray:
    """Remove edge-connected components with fewer than ``min_share`` x (faces of the largest
    component) faces: the tiny closed bubbles Poisson leaves around stray samples. (F, 3) -> (F', 3)."""
    if min_share <= 0 or len(faces) == 0:
        return faces
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    # vertices joined by an edge share a component; faces inherit their first vertex's component
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(num_vertices, num_vertices))
    _, comp = connected_components(graph, directed=False)
    face_comp = comp[faces[:, 0]]
    sizes = np.bincount(face_comp)
    return faces[sizes[face_comp] >= min_share * sizes.max()]


def is_watertight(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """trimesh's watertightness: every edge shared by exactly two faces, consistently wound."""
    import trimesh

    return bool(trimesh.Trimesh(vertices, faces, process=False).is_watertight)


def mesh_report(mesh: PoissonMesh, seconds: float = 0.0) -> MeshReport:
    """Sizes and watertightness of ``mesh``."""
    return MeshReport(len(mesh.vertices), len(mesh.faces), is_watertight(mesh.vertices, mesh.faces), seconds)


def mesh_ply(
    src: str | os.PathLike, out: str | os.PathLike, depth: int = 8, density_quantile: float = 0.0,
    render: str | os.PathLike | None = None, **kwargs,
) -> MeshReport:
    """Read a PLY cloud, reconstruct, write the mesh PLY (vertices, vertex normals, faces) atomically.

    With ``render`` also write a PNG (front and side views, Lambert-shaded). ``kwargs`` go to
    :func:`mesh_from_points`. Nothing is written when anything fails.
    """

    src = os.fspath(src)
    if os.path.isdir(src):
        raise ValueError(f"{src}: is a folder, expected a .ply file")
    cloud = read_ply(src)
    check_cloud(src, cloud.points)
    try:
        t0 = time.perf_counter()
        mesh = mesh_from_points(cloud.points, cloud.normals, depth=depth, density_quantile=density_quantile, **kwargs)
        seconds = time.perf_counter() - t0
    except ValueError as e:
        raise ValueError(f"{src}: {e}") from None
    report = mesh_report(mesh, seconds)
    if render is not None:

        render_mesh(mesh.vertices, mesh.faces, render)
    write_ply(out, mesh.vertices, normals=vertex_normals(mesh.vertices, mesh.faces), faces=mesh.faces)
    return report


# ------------------------------------------------------------------------------ body refinement
def sample_faces(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points area-uniformly on triangles ``faces`` (F, 3) of ``vertices`` (V, 3):
    (points (count, 3) float32, unit face normals (count, 3) float32)."""
    v = np.asarray(vertices, np.float64)
    tri = v[np.asarray(faces)]  # (F, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(cross, axis=1)
    if count < 1 or len(tri) == 0 or area.sum() <= 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    rng = np.random.default_rng(seed)
    f = rng.choice(len(tri), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], 1)  # uniform on a triangle
    pts = (bary[:, :, None] * tri[f]).sum(1)
    nrm = cross[f] / np.maximum(area[f], 1e-20)[:, None]
    return pts.astype(np.float32), nrm.astype(np.float32)


def replace_parts(points: np.ndarray, normals: np.ndarray | None, body_vertices: np.ndarray, body_faces: np.ndarray,
                  part_vertices: np.ndarray, margin: float = 0.06,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:  # fmt: skip
    """Replace a cloud's points on some body parts by points sampled on the body's parts.

    A cloud point (N, 3) is removed when its nearest body vertex (V, 3) is a part vertex
    (``part_vertices`` (V,) bool) and lies within ``margin`` m. As many points as were removed,
    but at least the parts' share of the body's area times N, are sampled area-uniformly on the
    faces whose three vertices are all part vertices (:func:`sample_faces`).

    Returns ``(points (N', 3), normals (N', 3) or None (when ``normals`` is None), from_body
    (N',) bool, body_normals (K, 3))``: the kept cloud points first, then the K body points
    (``from_body`` True), whose unit face normals are ``body_normals``.
    """
    from scipy.spatial import cKDTree

    pts = _check_points(points)
    verts = np.asarray(body_vertices, np.float64)
    part = np.asarray(part_vertices, bool)
    if part.shape != (len(verts),):
        raise ValueError(f"part_vertices must have shape ({len(verts)},), got {part.shape}")
    d, i = cKDTree(verts).query(pts)
    remove = part[i] & (d < margin)
    faces = np.asarray(body_faces)
    part_faces = faces[part[faces].all(1)]
    tri = verts[faces]
    areas = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    share = float(areas[part[faces].all(1)].sum() / max(areas.sum(), 1e-20))
    count = max(int(remove.sum()), int(round(share * len(pts))))
    new_pts, new_nrm = sample_faces(verts, part_faces, count, seed)
    out_pts = np.concatenate([pts[~remove], new_pts]).astype(np.float32)
    from_body = np.concatenate([np.zeros(int((~remove).sum()), bool), np.ones(len(new_pts), bool)])
    out_nrm = None
    if normals is not None:
        out_nrm = np.concatenate([np.asarray(normals, np.float32)[~remove], new_nrm]).astype(np.float32)
    return out_pts, out_nrm, from_body, new_nrm


class RefineReport(NamedTuple):
    """What :func:`refine_body_ply` did: the mesh report, the body fit (``BodyFit``), the
    number of cloud points replaced and of body points added."""

    mesh: MeshReport
    fit: object
    removed: int
    added: int


def refine_body_ply(src: str | os.PathLike, out: str | os.PathLike, joints: np.ndarray,
                    body_out: str | os.PathLike, depth: int = 8, density_quantile: float = 0.0,
                    render: str | os.PathLike | None = None, fit_steps: int = 150, knn: int = 30,
                    progress=None) -> RefineReport:  # fmt: skip
    """``pocoloco mesh --refine-body``: fit anny to the cloud ``src``, replace its head and
    hands by the fitted body's, Poisson-mesh the result to ``out`` and write the fitted body
    mesh to ``body_out`` (both PLYs with vertex normals; written only when everything
    succeeded). joints: (24, 3) metres, the cloud's pose. fit_steps: Adam steps per stage."""

    src = os.fspath(src)
    if os.path.isdir(src):
        raise ValueError(f"{src}: is a folder, expected a .ply file")
    cloud = read_ply(src)
    check_cloud(src, cloud.points)
    try:
        pts = check_scan("cloud", cloud.points, joints)
        if len(pts) < MIN_POINTS:
            raise ValueError(f"point cloud too sparse to mesh: {len(pts)} points (need at least {MIN_POINTS})")
        t0 = time.perf_counter()
        fit = fit_body_to_cloud(pts, joints, joint_steps=fit_steps, surface_steps=fit_steps, progress=progress)
        new_pts, new_nrm, from_body, body_nrm = replace_parts(pts, cloud.normals, fit.vertices, fit.faces,
                                                              fit.part_vertices)  # fmt: skip
        if new_nrm is None:  # the cloud had none: estimate for all, keep the body's exact normals
            new_nrm = estimate_normals(new_pts, knn=knn)
            new_nrm[from_body] = body_nrm
        mesh = mesh_from_points(new_pts, new_nrm, depth=depth, density_quantile=density_quantile, knn=knn)
        seconds = time.perf_counter() - t0
    except ValueError as e:
        raise ValueError(f"{src}: {e}") from None
    report = mesh_report(mesh, seconds)
    if render is not None:

        render_meshes([(mesh.vertices, mesh.faces, "refined mesh"), (fit.vertices, fit.faces, "fitted body")], render)
    body_faces = np.asarray(fit.faces, np.int64)
    write_ply(body_out, fit.vertices, normals=vertex_normals(fit.vertices, body_faces), faces=body_faces)
    write_ply(out, mesh.vertices, normals=vertex_normals(mesh.vertices, mesh.faces), faces=mesh.faces)
    return RefineReport(report, fit, int(len(pts) - (~from_body).sum()), int(from_body.sum()))
