"""Virtual multi-view capture: what a camera rig reconstructs of one frame.

A real capture dome (e.g. DynaCap, LOOSE) reconstructs only the *outer* surface
of the subject: body parts hidden under a skirt are seen by no camera and are
absent from the scan, while the inside of a skirt seen from below is real
surface. :func:`capture_frame` reproduces that for a set of triangle meshes
(the body and optionally loose garments) and returns a dense, uniformly dense
point cloud with unit outward normals, a label per point (body / garment) and
the body part (skeleton joint) of each body point.

Method (visibility by ray casting with open3d's ``RaycastingScene``, CPU):

1. Cameras: ``num_cameras`` pinhole centres spread evenly (a Fibonacci lattice)
   over a band of a sphere around the frame's bounding box, from
   ``min_elevation_deg`` (below, looking up) to ``max_elevation_deg`` (above,
   looking down). The rig is re-centred on the bounding box every frame.
2. Candidates: points sampled uniformly by area over all triangles
   (barycentric ``sqrt`` trick). A single-sided mesh (closed body) gets one
   candidate per area element; a two-sided mesh (cloth) gets each side as its
   own surface, i.e. twice the area, each candidate carrying the side it
   belongs to.
3. Visibility: candidate ``p`` is seen by camera ``c`` if the ray from ``c``
   towards ``p`` hits nothing before ``p`` (first-hit distance >=
   ``|p - c| - hit_tolerance``) and the surface faces the camera at more than
   a grazing angle (``|cos| > min_cos``). For a two-sided candidate the camera
   must be on the candidate's side. Each candidate tries its cameras from the
   best-facing one down (an any-hit occlusion query per try) and stops at the
   first that sees it, so most visible candidates cost one ray; hidden ones
   cost one per camera facing them. This is visibility *per surface point*,
   i.e. a rig of unlimited image resolution: no pixel grid, hence no density
   that grows near cameras.
4. Uniform density: candidates are i.i.d. uniform over the (doubled-for-cloth)
   surface, so the visible ones are i.i.d. uniform over the visible surface.
   Rounds of candidates are drawn until ``num_points`` are visible; the first
   ``num_points`` visible ones (in draw order) are kept.
5. Normals: the face normal, flipped towards the camera that saw the point. On
   a closed mesh any seeing camera is outside, so normals point outward
   whatever the triangle winding; on cloth the normal is the side's normal.
6. Optional scanner noise: Gaussian offsets along the normal (``noise_std``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..data.format import LABEL_BODY, LABEL_GARMENT, LABEL_NAMES  # noqa: F401  (re-exported)


@dataclass
class CaptureMesh:
    """One triangle mesh of a frame.

    vertices:  (V, 3) float vertex positions, metres.
    faces:     (F, 3) int vertex indices.
    label:     ``LABEL_BODY`` or ``LABEL_GARMENT``.
    face_part: (F,) int body part (skeleton joint index) per face, or None
               (parts of its points are then -1).
    two_sided: whether both sides of each face are real surface (cloth).
               None = ``label == LABEL_GARMENT``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    label: int
    face_part: np.ndarray | None = None
    two_sided: bool | None = None


@dataclass
class CaptureSettings:
    """Rig and sampling parameters.

    num_points:        points stored per frame (N).
    num_cameras:       camera centres on the dome.
    min_elevation_deg: lowest camera elevation seen from the subject's centre
                       (negative = below, looking up, e.g. under a skirt). -30
                       is about a camera at floor level at the default distance.
    max_elevation_deg: highest camera elevation (90 = straight above).
    distance_factor:   camera distance from the centre, in bounding-sphere radii.
    min_cos:           a camera sees a surface point only if the cosine between
                       the surface normal and the direction to the camera
                       exceeds this (rejects grazing views beyond ~75 deg, which
                       multi-view stereo does not reconstruct).
    hit_tolerance:     metres; a ray's first hit this close before the point
                       still counts as hitting the point.
    oversample:        first-round candidates = ``oversample * num_points``.
    max_rounds:        candidate rounds before giving up on ``num_points``.
    noise_std:         metres; std of Gaussian scanner noise along the normal.
    seed:              seed of all randomness (candidates, noise).
    cull_hidden_faces: first test the mesh vertices and draw candidates only on
                       faces that may be visible (``possibly_visible_faces``):
                       fewer rays (1.3-1.5x faster frames with a skirt or a
                       shirt), the visible surface minus 0.03-0.3 %. Applied
                       only to frames with cloth (a bare body hides too little
                       to pay for the probes) and when ``num_points`` is at
                       least the number of vertex probes.
    """

    num_points: int = 40000
    num_cameras: int = 32
    min_elevation_deg: float = -30.0
    max_elevation_deg: float = 90.0
    distance_factor: float = 2.5
    min_cos: float = 0.25
    hit_tolerance: float = 1e-4
    oversample: float = 1.6
    max_rounds: int = 8
    noise_std: float = 0.0
    seed: int = 0
    cull_hidden_faces: bool = False


@dataclass
class ScanFrame:
    """A captured frame (N points).

    points:  (N, 3) float32 metres.
    normals: (N, 3) float32 unit outward normals.
    labels:  (N,) uint8 ``LABEL_BODY`` / ``LABEL_GARMENT``.
    parts:   (N,) int8 body part (skeleton joint) of body points, -1 otherwise.
    """

    points: np.ndarray
    normals: np.ndarray
    labels: np.ndarray
    parts: np.ndarray


def loose_share(labels: np.ndarray) -> float:
    """Percent of points labelled ``LABEL_GARMENT``. labels: (N,) -> float in [0, 100]."""
    labels = np.asarray(labels)
    if labels.ndim != 1 or labels.size == 0:
        raise ValueError(f"labels must be a non-empty 1-D array, got shape {labels.shape}")
    return float(100.0 * np.mean(labels == LABEL_GARMENT))


def camera_centres(
    center: np.ndarray, distance: float, num_cameras: int, min_elevation_deg: float, max_elevation_deg: float
) -> np.ndarray:
    """Camera centres spread evenly over a band of a sphere.

    A Fibonacci lattice restricted to elevations [min, max] (equal-area in z),
    so cameras form interleaved rings at several heights, with the top one(s)
    looking down and the low ones looking up.

    Returns: (C, 3) float64.
    """
    if num_cameras < 1:
        raise ValueError(f"num_cameras must be >= 1, got {num_cameras}")
    if not -90.0 <= min_elevation_deg < max_elevation_deg <= 90.0:
        raise ValueError(f"need -90 <= min_elevation_deg < max_elevation_deg <= 90, got "
                         f"{min_elevation_deg}, {max_elevation_deg}")
    z_lo, z_hi = math.sin(math.radians(min_elevation_deg)), math.sin(math.radians(max_elevation_deg))
    i = np.arange(num_cameras, dtype=np.float64)
    z = z_hi - (i + 0.5) / num_cameras * (z_hi - z_lo)  # top to bottom, equal area per camera
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    azimuth = i * math.pi * (3.0 - math.sqrt(5.0))  # golden angle
    dirs = np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=1)
    return np.asarray(center, dtype=np.float64) + distance * dirs


def _validate(meshes: Sequence[CaptureMesh], settings: CaptureSettings) -> None:
    if len(meshes) == 0:
        raise ValueError("meshes is empty: capture_frame needs at least one mesh")
    if settings.num_points < 1:
        raise ValueError(f"num_points must be >= 1, got {settings.num_points}")
    if settings.noise_std < 0:
        raise ValueError(f"noise_std must be >= 0, got {settings.noise_std}")
    if settings.oversample <= 0 or settings.max_rounds < 1:
        raise ValueError("oversample must be > 0 and max_rounds >= 1")
    for k, m in enumerate(meshes):
        v, f = np.asarray(m.vertices), np.asarray(m.faces)
        if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
            raise ValueError(f"mesh {k}: vertices must have shape (V, 3) with V > 0, got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
            raise ValueError(f"mesh {k}: faces must have shape (F, 3) with F > 0, got {f.shape}")
        if not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"mesh {k}: faces must be integers, got {f.dtype}")
        if f.min() < 0 or f.max() >= v.shape[0]:
            raise ValueError(f"mesh {k}: face indices out of range [0, {v.shape[0]})")
        if not np.isfinite(v).all():
            raise ValueError(f"mesh {k}: vertices contain NaN or inf")
        if m.label not in (LABEL_BODY, LABEL_GARMENT):
            raise ValueError(f"mesh {k}: label must be {LABEL_BODY} (body) or {LABEL_GARMENT} (garment), got {m.label}")
        if m.face_part is not None and np.asarray(m.face_part).shape != (f.shape[0],):
            raise ValueError(f"mesh {k}: face_part must have shape ({f.shape[0]},), got {np.asarray(m.face_part).shape}")


class _Surface:
    """All meshes of a frame flattened into one triangle soup for sampling.

    Sides: a two-sided face appears twice (side +1 and -1), so sampling by
    "side area" gives each cloth side its own uniform density.
    """

    def __init__(self, meshes: Sequence[CaptureMesh]):
        tri, normal, side, label, part = [], [], [], [], []
        self.sheets: list[tuple[np.ndarray, np.ndarray, float]] = []  # (vertices, faces, side) in soup order
        for m in meshes:
            v = np.asarray(m.vertices, dtype=np.float64)
            f = np.asarray(m.faces, dtype=np.int64)
            t = v[f]  # (F, 3, 3)
            n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
            fp = np.full(len(f), -1, np.int64) if m.face_part is None else np.asarray(m.face_part, np.int64)
            two = (m.label == LABEL_GARMENT) if m.two_sided is None else bool(m.two_sided)
            for s in ((1.0, -1.0) if two else (0.0,)):  # 0 = one-sided: either side, flipped to the camera
                tri.append(t)
                normal.append(n if s == 0.0 else s * n)
                side.append(np.full(len(f), s))
                label.append(np.full(len(f), m.label, np.uint8))
                part.append(fp)
                self.sheets.append((v, f, s))
        self.tri = np.concatenate(tri)  # (S, 3, 3)
        normal = np.concatenate(normal)
        area2 = np.linalg.norm(normal, axis=1)
        self.normal = normal / np.maximum(area2, 1e-30)[:, None]  # (S, 3) unit
        self.side = np.concatenate(side)  # (S,) +1 / -1 two-sided, 0 one-sided
        self.label = np.concatenate(label)
        self.part = np.concatenate(part)
        self.area2 = area2
        self.cdf = np.cumsum(area2)
        if not self.cdf[-1] > 0:
            raise ValueError("meshes have zero total area")

    def restrict(self, keep: np.ndarray) -> None:
        """Sample only from the soup faces where ``keep`` (S,) is True (area-uniform over them)."""
        cdf = np.cumsum(np.where(keep, self.area2, 0.0))
        if cdf[-1] > 0:
            self.cdf = cdf

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """n i.i.d. points uniform by area. Returns (face index (n,), points (n, 3))."""
        face = np.searchsorted(self.cdf, rng.random(n) * self.cdf[-1], side="right")
        face = np.minimum(face, len(self.cdf) - 1)
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        t = self.tri[face]
        p = (1 - s)[:, None] * t[:, 0] + (s * (1 - r2))[:, None] * t[:, 1] + (s * r2)[:, None] * t[:, 2]
        return face, p


_VIS_CHUNK = 65536  # points per visibility batch


def visibility(
    scene, points: np.ndarray, normals: np.ndarray, sides: np.ndarray, cameras: np.ndarray,
    min_cos: float, hit_tolerance: float, max_tries: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Which points some camera sees first, and the normals facing that camera.

    Each point tries the cameras that face it (``cos > min_cos``) best-facing
    first, one any-hit occlusion ray per try, and stops at the first that sees
    it. The cosines are accumulated axis by axis in float32 (no (N, C, 3)
    temporaries); :func:`_visibility_reference` is the original.

    Args:
        scene: an open3d ``RaycastingScene`` holding all triangles.
        points: (N, 3) surface points; normals: (N, 3) unit face normals.
        sides: (N,) nonzero = only cameras on the side the normal points to
            may see the point (one side of cloth; its normal is that side's);
            0 = either side (the normal is flipped towards the camera).
        cameras: (C, 3) camera centres.
        max_tries: try at most this many cameras per point (best-facing first);
            None = every camera that faces it (exact).
    Returns:
        seen (N,) bool, oriented normals (N, 3) (unchanged where not seen).
    """
    import open3d as o3d  # deferred: heavy import, optional dependency

    n = len(points)
    if n > _VIS_CHUNK:  # bound the (N, C) temporaries
        parts = [visibility(scene, points[i : i + _VIS_CHUNK], normals[i : i + _VIS_CHUNK], sides[i : i + _VIS_CHUNK],
                            cameras, min_cos, hit_tolerance, max_tries) for i in range(0, n, _VIS_CHUNK)]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    seen = np.zeros(n, dtype=bool)
    oriented = np.array(normals, copy=True)
    if n == 0:
        return seen, oriented
    p = np.ascontiguousarray(points, dtype=np.float32)
    nrm = np.ascontiguousarray(normals, dtype=np.float32)
    cam = np.ascontiguousarray(cameras, dtype=np.float32)
    # |c - p|^2 and (c - p) . n accumulated one axis at a time: (N, C), no (N, C, 3) temporaries
    dist2 = np.zeros((n, cam.shape[0]), dtype=np.float32)
    dot = np.zeros_like(dist2)
    for a in range(3):
        d = cam[None, :, a] - p[:, a : a + 1]
        dist2 += d * d
        dot += d * nrm[:, a : a + 1]
    cos = dot / np.sqrt(np.maximum(dist2, 1e-24))
    score = np.where(np.asarray(sides)[:, None] == 0, np.abs(cos), cos)
    score[score <= min_cos] = -np.inf  # cameras that cannot see the point
    facing = np.isfinite(score).sum(1)
    active = np.flatnonzero(facing > 0)  # points not yet seen that may still be seen
    # best-facing first: most visible points cost one ray, so the first try takes each row's
    # best camera (argmax) and only the rows still unseen after it are sorted (rank k of
    # ``order`` belongs to row ``rows[k]``); the same cameras in the same order as a full sort
    # (but for a tie of two best cosines, where argmax takes the lower camera index)
    first = np.argmax(score, axis=1)
    order = rows = None
    for k in range(cam.shape[0] if max_tries is None else min(max_tries, cam.shape[0])):
        active = active[facing[active] > k]
        if active.size == 0:
            break
        if k == 0:
            cam_k = first[active]
        else:
            if order is None:  # the still-unseen rows' cameras, best-facing first
                rows = np.full(n, -1, dtype=np.int64)
                rows[active] = np.arange(active.size)
                order = np.argsort(-score[active], axis=1)
            cam_k = order[rows[active], k]
        origin = cam[cam_k]  # (M, 3)
        d = p[active] - origin
        length = np.sqrt(np.einsum("ij,ij->i", d, d))
        # direction scaled so that t = 1 is `hit_tolerance` before the point:
        # any hit in (0, 1) occludes it.
        d *= (np.maximum(length - hit_tolerance, 1e-9) / np.maximum(length, 1e-12))[:, None]
        rays = np.concatenate([origin, d], axis=1)
        occluded = scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0).numpy()
        idx = active[~occluded]
        seen[idx] = True
        flip = idx[cos[idx, cam_k[~occluded]] < 0]
        oriented[flip] *= -1.0
        active = active[occluded]
    return seen, oriented


def _visibility_reference(
    scene, points: np.ndarray, normals: np.ndarray, sides: np.ndarray, cameras: np.ndarray,
    min_cos: float, hit_tolerance: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Slow, obviously-correct version of :func:`visibility` (the original
    implementation: (N, C, 3) temporaries and a full per-point camera sort), kept
    for the test that compares them.

    Args:
        scene: an open3d ``RaycastingScene`` holding all triangles.
        points: (N, 3) surface points; normals: (N, 3) unit face normals.
        sides: (N,) nonzero = only cameras on the side the normal points to
            may see the point (one side of cloth; its normal is that side's);
            0 = either side (the normal is flipped towards the camera).
        cameras: (C, 3) camera centres.
    Returns:
        seen (N,) bool, oriented normals (N, 3) (unchanged where not seen).
    """
    import open3d as o3d  # deferred: heavy import, optional dependency

    n = len(points)
    if n > _VIS_CHUNK:  # bound the (N, C, 3) temporaries
        parts = [_visibility_reference(scene, points[i : i + _VIS_CHUNK], normals[i : i + _VIS_CHUNK], sides[i : i + _VIS_CHUNK],
                            cameras, min_cos, hit_tolerance) for i in range(0, n, _VIS_CHUNK)]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    seen = np.zeros(n, dtype=bool)
    oriented = normals.copy()
    if n == 0:
        return seen, oriented
    # cosine between each normal and the direction to each camera: (N, C)
    to_cam = (cameras[None, :, :] - points[:, None, :]).astype(np.float32)
    dist = np.sqrt(np.einsum("ncj,ncj->nc", to_cam, to_cam))
    cos = np.einsum("ncj,nj->nc", to_cam, normals.astype(np.float32)) / np.maximum(dist, 1e-12)
    score = np.where(sides[:, None] == 0, np.abs(cos), cos)
    score[score <= min_cos] = -np.inf  # cameras that cannot see the point
    # try each point's cameras best-facing first: most visible points cost one ray
    order = np.argsort(-score, axis=1)
    active = np.arange(n)  # points not yet seen that may still be seen
    for k in range(cameras.shape[0]):
        cam_k = order[active, k]
        ok = np.isfinite(score[active, cam_k])
        active, cam_k = active[ok], cam_k[ok]
        if active.size == 0:
            break
        cam = cameras[cam_k]  # (M, 3)
        d = np.linalg.norm(points[active] - cam, axis=1)
        # direction scaled so that t = 1 is `hit_tolerance` before the point:
        # any hit in (0, 1) occludes it.
        direction = (points[active] - cam) * (np.maximum(d - hit_tolerance, 1e-9) / d)[:, None]
        rays = np.concatenate([cam, direction], axis=1).astype(np.float32)
        occluded = scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0).numpy()
        idx = active[~occluded]
        seen[idx] = True
        flip = np.where(cos[idx, cam_k[~occluded]] < 0, -1.0, 1.0)
        oriented[idx] = normals[idx] * flip[:, None]
        active = active[occluded]
    return seen, oriented


def possibly_visible_faces(
    surface: _Surface, scene, cameras: np.ndarray, min_cos: float, margin_cos: float = 0.25,
    offset: float = 1e-3, max_tries: int | None = 16,
) -> np.ndarray:
    """Soup faces (S,) bool that may hold a visible point: a face is kept if one of
    its vertices, or of the faces sharing a vertex with it (one ring of dilation),
    is seen by some camera. Vertices are tested like candidates (``visibility``)
    with their area-weighted normal, a cosine threshold ``margin_cos`` lower than
    the candidates', on cloth ``offset`` m off the surface on their side, and at most
    ``max_tries`` cameras each (a hidden vertex costs one ray per camera tried).
    Conservative, not exact: a face whose probes are all hidden but which shows a
    sliver through a gap is dropped (measured on the pipeline's frames: 0.03-0.3 % of
    the visible surface, benchmarks/bench_capture_speed.py)."""
    pts, nrm, sides, spans = [], [], [], []
    start = 0
    for v, f, side in surface.sheets:
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        vn = np.zeros_like(v)
        for k in range(3):
            np.add.at(vn, f[:, k], fn)
        vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-30)
        if side != 0.0:
            vn = side * vn
        pts.append(v + (offset if side != 0.0 else 0.0) * vn)
        nrm.append(vn)
        sides.append(np.full(len(v), side))
        spans.append((start, len(v), f))
        start += len(v)
    seen, _ = visibility(scene, np.concatenate(pts), np.concatenate(nrm), np.concatenate(sides), cameras,
                         min_cos - margin_cos, max(offset, 1e-4), max_tries=max_tries)  # fmt: skip
    keep = []
    for begin, nv, f in spans:
        vs = seen[begin : begin + nv]
        near = np.zeros(nv, dtype=bool)
        near[f[vs[f].any(1)].ravel()] = True  # dilate by one ring
        keep.append(near[f].any(1))
    return np.concatenate(keep)


_CAPTURE_CHUNK = 16384  # candidates per visibility call; stop as soon as enough are seen


def capture_frame(meshes: Sequence[CaptureMesh], settings: CaptureSettings | None = None) -> ScanFrame:
    """Capture one frame: the outer, camera-visible surface as a uniform point cloud.

    Args:
        meshes: the frame's meshes (body, garments), see :class:`CaptureMesh`.
        settings: rig and sampling parameters (defaults: 40,000 points, 32 cameras).
    Returns:
        ScanFrame with N = ``settings.num_points`` points (fewer only if the
        visible area is tiny and ``max_rounds`` rounds could not find them).
    """
    import open3d as o3d  # deferred: heavy import, optional dependency

    settings = settings or CaptureSettings()
    _validate(meshes, settings)
    rng = np.random.default_rng(settings.seed)
    surface = _Surface(meshes)

    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(
            o3d.core.Tensor(np.asarray(m.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.asarray(m.faces, dtype=np.uint32)),
        )
    all_v = np.concatenate([np.asarray(m.vertices, dtype=np.float64) for m in meshes])
    lo, hi = all_v.min(0), all_v.max(0)
    center, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)
    cameras = camera_centres(center, settings.distance_factor * radius, settings.num_cameras,
                             settings.min_elevation_deg, settings.max_elevation_deg)

    probes = sum(len(v) for v, _, _ in surface.sheets)
    cloth = any(side != 0.0 for _, _, side in surface.sheets)
    if settings.cull_hidden_faces and cloth and settings.num_points >= probes:  # the probe pass pays off
        surface.restrict(possibly_visible_faces(surface, scene, cameras, settings.min_cos))

    faces, points, normals = [], [], []
    found, drawn, want = 0, 0, settings.num_points
    batch = int(math.ceil(settings.oversample * want))
    for _ in range(settings.max_rounds):
        face, p = surface.sample(batch, rng)
        # test in draw order and stop once `want` are seen: the kept points (the first
        # `want` visible in draw order) are the same as testing the whole batch
        for i in range(0, batch, _CAPTURE_CHUNK):
            sl = slice(i, i + _CAPTURE_CHUNK)
            seen, nrm = visibility(scene, p[sl], surface.normal[face[sl]], surface.side[face[sl]], cameras,
                                   settings.min_cos, settings.hit_tolerance)  # fmt: skip
            faces.append(face[sl][seen])
            points.append(p[sl][seen])
            normals.append(nrm[seen])
            found += int(seen.sum())
            if found >= want:
                break
        drawn += batch
        if found >= want:
            break
        rate = max(found / drawn, 1e-3)  # visible fraction of the (two-sided) area so far
        batch = int(math.ceil(1.2 * (want - found) / rate)) + 64
    face = np.concatenate(faces)[:want]
    points = np.concatenate(points)[:want]
    normals = np.concatenate(normals)[:want]
    if settings.noise_std > 0:
        points = points + rng.normal(0.0, settings.noise_std, size=(len(points), 1)) * normals
    return ScanFrame(
        points=points.astype(np.float32),
        normals=normals.astype(np.float32),
        labels=surface.label[face].astype(np.uint8),
        parts=surface.part[face].astype(np.int8),
    )


def open_tube(
    z_top: float, z_bottom: float, radii_top: tuple[float, float], radii_bottom: tuple[float, float],
    center_xy: tuple[float, float] = (0.0, 0.0), n_around: int = 64, n_down: int = 16,
) -> tuple[np.ndarray, np.ndarray]:
    """A synthetic skirt: an open elliptic frustum (no caps), for tests and benchmarks.

    Args:
        z_top, z_bottom: heights of the waist and hem rings (metres).
        radii_top, radii_bottom: (x, y) half-axes of the waist and hem ellipses.
        center_xy: axis position.
        n_around, n_down: vertices around a ring, rings from waist to hem.
    Returns:
        vertices (n_down * n_around, 3) float32, faces (2 * (n_down - 1) * n_around, 3) int64.
    """
    if n_around < 3 or n_down < 2:
        raise ValueError(f"need n_around >= 3 and n_down >= 2, got {n_around}, {n_down}")
    a = np.linspace(0.0, 2 * np.pi, n_around, endpoint=False)
    w = np.linspace(0.0, 1.0, n_down)[:, None]  # 0 at the waist, 1 at the hem
    rx = (1 - w) * radii_top[0] + w * radii_bottom[0]
    ry = (1 - w) * radii_top[1] + w * radii_bottom[1]
    z = np.broadcast_to((1 - w) * z_top + w * z_bottom, (n_down, n_around))
    verts = np.stack([center_xy[0] + rx * np.cos(a), center_xy[1] + ry * np.sin(a), z], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_down - 1), np.arange(n_around), indexing="ij")
    v00, v01 = i * n_around + j, i * n_around + (j + 1) % n_around
    v10, v11 = v00 + n_around, v01 + n_around
    faces = np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3), np.stack([v00, v11, v01], -1).reshape(-1, 3)])
    return verts.astype(np.float32), faces.astype(np.int64)
