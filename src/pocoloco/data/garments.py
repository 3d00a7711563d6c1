"""Procedural loose-garment templates built around a subject's rest body.

A garment is a triangulated tube (an open cylinder, no seams) wrapped around
the rest A-pose body (``AnnyBody.template``, metres, Z up, facing -Y). Its
radius at every height and angle comes from the convex hull of the body's
horizontal cross-section there, plus a clearance and a flare, so it starts
outside the body; a final pass pushes any vertex still inside or too close to
the full body mesh outwards along its ray.

Kinds (``GARMENT_KINDS``):

- ``"skirt"``: an A-line skirt from the waist to between knee and ankle
  (``hem``: 0 = knee, 1 = ankle; default 0.35, about mid-calf). The waistband
  ring is pinned to the body.
- ``"long_shirt"``: a sleeveless loose tunic from the shoulders to mid-thigh.
  The top edge is at shoulder height in front and behind and dips to below
  the armpits at the sides (arm holes); it is pinned to the torso. No sleeves.

``"tight"`` clothing is *not* a garment here: a tight-clothing control subject
is the body surface itself, so there is no cloth mesh to build or simulate.

Pinned garment vertices follow one body vertex each through its skinning
transform: ``posed = v_body + vtransf[v] @ attach_offset`` (see ``pin_positions``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from ..body.anny_body import AnnyBody, PosedBody
from ..body.skeleton import joint_index

GARMENT_KINDS: tuple[str, ...] = ("skirt", "long_shirt")

#: Body parts (skeleton joints) that never shape or hold a garment body tube.
_ARM_AND_HEAD = tuple(
    joint_index(n)
    for n in (
        "head",
        "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
        "left_wrist", "right_wrist", "left_hand", "right_hand",
    )
)  # fmt: skip


@dataclass
class Garment:
    """A garment template around the rest body.

    kind:          one of ``GARMENT_KINDS``.
    rest_vertices: (Vg, 3) float32 vertices around the rest body (metres).
    faces:         (Fg, 3) int64 triangles.
    attach_vertex: (Vg,) int64 body vertex each pinned garment vertex follows,
                   -1 for free (simulated) vertices.
    attach_offset: (Vg, 3) float32 rest-pose offset from that body vertex
                   (zero for free vertices).
    grid_shape:    (rows, columns) of the tube grid, row 0 at the top edge.
    """

    kind: str
    rest_vertices: np.ndarray
    faces: np.ndarray
    attach_vertex: np.ndarray
    attach_offset: np.ndarray
    grid_shape: tuple[int, int] = (0, 0)

    @property
    def pinned(self) -> np.ndarray:
        """(Vg,) bool, True for vertices attached to the body."""
        return self.attach_vertex >= 0


def pin_positions(garment: Garment, posed: PosedBody) -> np.ndarray:
    """Positions of the pinned garment vertices on posed bodies.

    Returns (T, P, 3) float32 for the P pinned vertices (in vertex order):
    ``v_body[t, a] + vtransf[t, a] @ offset``.
    """
    idx = np.flatnonzero(garment.pinned)
    a = garment.attach_vertex[idx]
    off = garment.attach_offset[idx]
    return (posed.vertices[:, a] + np.einsum("tpij,pj->tpi", posed.vtransf[:, a], off)).astype(np.float32)


def _tube_faces(rows: int, cols: int) -> np.ndarray:
    """Triangles of a (rows, cols) grid closed around the columns, outward-facing
    for a tube whose columns go counter-clockwise (seen from +Z) and rows down."""
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols), indexing="ij")
    a = r * cols + c
    b = r * cols + (c + 1) % cols
    d = (r + 1) * cols + c
    e = (r + 1) * cols + (c + 1) % cols
    flip = ((r + c) % 2).astype(bool)  # alternate diagonals: less directional bias
    t1 = np.where(flip[..., None], np.stack([a, d, e], -1), np.stack([a, d, b], -1))
    t2 = np.where(flip[..., None], np.stack([a, e, b], -1), np.stack([b, d, e], -1))
    return np.concatenate([t1.reshape(-1, 3), t2.reshape(-1, 3)]).astype(np.int64)


def _hull_distance(points_xy: np.ndarray, center: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Distance from ``center`` along directions ``theta`` (C,) to the boundary
    of the convex hull of ``points_xy`` (N, 2); 0 if there are too few points."""
    if len(points_xy) < 4:
        return np.zeros_like(theta)
    hull = ConvexHull(points_xy)
    n, b = hull.equations[:, :2], hull.equations[:, 2]  # inside: n.x + b <= 0
    u = np.stack([np.cos(theta), np.sin(theta)], -1)  # (C, 2)
    nu = u @ n.T  # (C, H)
    slack = -(n @ center + b)  # (H,) >= 0 when center is inside
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(nu > 1e-9, slack[None] / nu, np.inf)
    return np.clip(t.min(1), 0.0, None)


def _body_profile(
    body_xyz: np.ndarray, center: np.ndarray, theta: np.ndarray, z: np.ndarray, slab: float
) -> np.ndarray:
    """(R, C) hull distance of the body cross-section at heights z (R,)."""
    out = np.zeros((len(z), len(theta)))
    for i, zi in enumerate(z):
        sel = np.abs(body_xyz[:, 2] - zi) < slab
        out[i] = _hull_distance(body_xyz[sel, :2], center, theta)
    return out


def _smooth_circular(x: np.ndarray, width: int) -> np.ndarray:
    """Moving average over the last (circular) axis."""
    if width <= 1:
        return x
    k = np.ones(width) / width
    pad = width // 2
    xp = np.concatenate([x[..., -pad:], x, x[..., :pad]], -1)
    return np.apply_along_axis(lambda r: np.convolve(r, k, mode="valid"), -1, xp)[..., : x.shape[-1]]


def _push_outside(
    verts: np.ndarray, center: np.ndarray, body: AnnyBody, clearance: float, iters: int = 20
) -> np.ndarray:
    """Move vertices closer than ``clearance`` to the full body mesh (or inside
    it) outwards along their horizontal ray from ``center``."""
    from .sdf import signed_distance_fn  # lazy: open3d

    sdf = signed_distance_fn(body.template, body.faces)
    verts = verts.copy()
    radial = verts[:, :2] - center
    radial /= np.linalg.norm(radial, axis=1, keepdims=True).clip(1e-9)
    for _ in range(iters):
        sd = sdf(verts)
        bad = sd < clearance
        if not bad.any():
            break
        step = np.clip(clearance - sd[bad], 0.002, 0.05)
        verts[bad, :2] += radial[bad] * step[:, None]
    return verts


def anchor_vertices(body: AnnyBody) -> np.ndarray:
    """Indices of the body vertices a garment may follow: torso and legs, not
    arms or head (an A-pose hand next to a skirt must not drag it along)."""
    return np.flatnonzero(~np.isin(body.vertex_joint, _ARM_AND_HEAD))


def _attach(garment_xyz: np.ndarray, pinned: np.ndarray, body: AnnyBody) -> tuple[np.ndarray, np.ndarray]:
    """Nearest torso/leg body vertex and rest offset for each pinned vertex."""
    allowed = anchor_vertices(body)
    tree = cKDTree(body.template[allowed])
    attach = np.full(len(garment_xyz), -1, dtype=np.int64)
    offset = np.zeros_like(garment_xyz, dtype=np.float32)
    idx = np.flatnonzero(pinned)
    _, nn = tree.query(garment_xyz[idx])
    attach[idx] = allowed[nn]
    offset[idx] = garment_xyz[idx] - body.template[attach[idx]]
    return attach, offset


def _grid_counts(resolution: float, base_cols: int, base_rows: int) -> tuple[int, int]:
    cols = max(12, int(round(base_cols * resolution / 2)) * 2)
    rows = max(4, int(round(base_rows * resolution)))
    return rows, cols


def _make_skirt(
    body: AnnyBody,
    resolution: float,
    hem: float = 0.35,
    flare: float = 0.3,
    clearance: float = 0.02,
    waist_clearance: float = 0.008,
) -> Garment:
    j = body.template_joints
    z_waist = j[joint_index("spine1"), 2] + 0.3 * (j[joint_index("spine2"), 2] - j[joint_index("spine1"), 2])
    knee = 0.5 * (j[joint_index("left_knee"), 2] + j[joint_index("right_knee"), 2])
    ankle = 0.5 * (j[joint_index("left_ankle"), 2] + j[joint_index("right_ankle"), 2])
    z_hem = knee + hem * (ankle - knee)
    rows, cols = _grid_counts(resolution, 72, 36)
    theta = np.linspace(0.0, 2 * np.pi, cols, endpoint=False)
    z = np.linspace(z_waist, z_hem, rows)
    center = np.array([0.0, j[0, 1]])
    shape = body.template[~np.isin(body.vertex_joint, _ARM_AND_HEAD)]
    prof = _body_profile(shape, center, theta, z, slab=0.015)  # (R, C)
    prof = np.maximum.accumulate(prof, axis=0)  # a hanging skirt clears everything above
    drop = (z_waist - z)[:, None]
    radius = np.maximum(prof[:1] + waist_clearance + flare * drop, prof + clearance)
    radius = np.maximum(_smooth_circular(radius, 5), prof + clearance)
    radius[0] = prof[0] + waist_clearance
    zz = np.broadcast_to(z[:, None], radius.shape)
    verts = np.stack([center[0] + radius * np.cos(theta), center[1] + radius * np.sin(theta), zz], -1).reshape(-1, 3)
    verts = _push_outside(verts, center, body, clearance=0.004)
    pinned = np.zeros(rows * cols, dtype=bool)
    pinned[:cols] = True  # waistband ring
    attach, offset = _attach(verts, pinned, body)
    return Garment("skirt", verts.astype(np.float32), _tube_faces(rows, cols), attach, offset, (rows, cols))


def _make_long_shirt(
    body: AnnyBody,
    resolution: float,
    hem: float = 0.5,
    flare: float = 0.12,
    clearance: float = 0.03,
    armhole_depth: float = 0.13,
) -> Garment:
    j = body.template_joints
    z_sh = j[joint_index("left_shoulder"), 2] + 0.02
    z_arm = j[joint_index("left_shoulder"), 2] - armhole_depth
    hip = j[joint_index("left_hip"), 2]
    z_hem = hip + hem * (j[joint_index("left_knee"), 2] - hip)
    rows, cols = _grid_counts(resolution, 72, 36)
    theta = np.linspace(0.0, 2 * np.pi, cols, endpoint=False)
    # top edge: shoulder height in front/behind, armpit height at the sides
    s = np.clip((np.abs(np.sin(theta)) - 0.45) / 0.4, 0.0, 1.0)
    z_top = z_arm + (z_sh - z_arm) * s * s * (3 - 2 * s)  # (C,)
    frac = np.linspace(0.0, 1.0, rows)[:, None]
    z = z_top[None] + frac * (z_hem - z_top[None])  # (R, C)
    center = np.array([0.0, j[joint_index("spine3"), 1] * 0.5])
    shape = body.template[~np.isin(body.vertex_joint, _ARM_AND_HEAD)]
    z_levels = np.linspace(z_sh, z_hem, 2 * rows)
    section = _body_profile(shape, center, theta, z_levels, slab=0.015)  # (L, C), top to bottom
    below = np.maximum.accumulate(section[::-1], axis=0)[::-1]  # widest part below: hangs straight
    above = np.maximum.accumulate(section, axis=0)  # widest part above: drapes from the chest
    prof_levels = np.minimum(below, above + 0.05)  # but no huge ledge under the chest
    # interpolate the level profile at each vertex height
    prof = np.empty_like(z)
    for c in range(cols):
        prof[:, c] = np.interp(z[:, c], z_levels[::-1], prof_levels[::-1, c])
    drop = (z - z_top[None]) * -1.0
    radius = prof + clearance + flare * drop
    radius[0] = prof[0] + 0.01
    radius = np.maximum(_smooth_circular(radius, 3), prof + 0.01)
    verts = np.stack([center[0] + radius * np.cos(theta), center[1] + radius * np.sin(theta), z], -1).reshape(-1, 3)
    verts = _push_outside(verts, center, body, clearance=0.006)
    pinned = np.zeros(rows * cols, dtype=bool)
    pinned[:cols] = True  # neckline/shoulder edge and arm holes follow the torso
    attach, offset = _attach(verts, pinned, body)
    return Garment("long_shirt", verts.astype(np.float32), _tube_faces(rows, cols), attach, offset, (rows, cols))


def make_garment(kind: str, body: AnnyBody, resolution: float = 1.0, **params) -> Garment:
    """Build a garment template around ``body``'s rest pose.

    Args:
        kind: ``"skirt"`` or ``"long_shirt"`` (``"tight"`` has no cloth mesh:
            the body surface itself is the tight clothing; asking for it raises).
        body: the subject; its ``template`` (rest A-pose) is dressed.
        resolution: scales the grid in both directions (1.0 gives ~2.6K
            vertices, 72 columns x 36 rows; 0.5 gives ~650).
        **params: kind-specific shape parameters: skirt ``hem`` (0 knee ..
            1 ankle), ``flare`` (radius gain per metre of drop), ``clearance``;
            long_shirt ``hem`` (0 hip .. 1 knee), ``flare``, ``clearance``,
            ``armhole_depth``.
    Returns:
        Garment with vertices outside the body (>= ~4 mm from its surface).
    """
    if kind == "tight":
        raise ValueError("'tight' clothing has no cloth mesh: use the body surface itself")
    if kind not in GARMENT_KINDS:
        raise ValueError(f"unknown garment kind {kind!r}; expected one of {GARMENT_KINDS}")
    if not (0.1 <= resolution <= 4.0):
        raise ValueError(f"resolution must be in [0.1, 4], got {resolution}")
    builder = {"skirt": _make_skirt, "long_shirt": _make_long_shirt}[kind]
    try:
        return builder(body, resolution, **params)
    except TypeError as e:
        raise ValueError(f"bad parameters for garment {kind!r}: {e}") from None
