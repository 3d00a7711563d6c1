"""Point-cloud and curve rendering to PNG with matplotlib's Agg backend (no system deps).

Point clouds are drawn as orthographic splats in painter's order (far points
first), Z up, equal aspect, no axes; every figure of the package that shows
clouds goes through :func:`render_points`. Colours come from :func:`colors_for`
(by label, by normal, or by height). Each point's brightness follows how much
its normal faces a light beside the viewer (Lambert, :data:`KEY_LIGHT`), which
makes the surface shape and the folds readable; points facing away from the
viewer are culled; a cloud without normals gets them estimated (:func:`estimate_normals`:
PCA of its nearest neighbours, oriented outward from the skeleton when the
joints are known). An unlabeled cloud whose pose is known gets its loose
garment tinted (:func:`garment_weights`: points off the posed body, or outside
a calibrated body envelope around the skeleton's bones).

Views (body convention: Z up, the subject faces -Y, +X is its left):
``front`` looks from -Y, ``back`` from +Y, ``side`` from +X (the subject's
left; it faces left in the image), ``top`` from +Z (front at the bottom).

Why this module is long: it is the one renderer of every picture of clouds (grids,
turntables, GIFs) with the shading they share (estimated normals, garment tint), plus
the mesh and curve plots; split, the figures would drift apart again.
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence

import numpy as np

from pocoloco.body.skeleton import JOINT_PARENTS, NUM_JOINTS
from pocoloco.utils.atomic import atomic_open

#: Per-view (right, up, towards-viewer) unit axes in world coordinates.
VIEWS: dict[str, tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]] = {
    "front": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "back": ((-1, 0, 0), (0, 0, 1), (0, 1, 0)),
    "side": ((0, 1, 0), (0, 0, 1), (1, 0, 0)),
    "top": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
}

#: The light of the clouds' Lambert shading, moving with the viewer: (right, up) components of its
#: direction beside the line of sight (1), ~35 deg from it at the upper left; off the line of sight
#: the two flanks of a fold differ, which a headlight would light alike.
KEY_LIGHT = (-0.6, 0.35)

#: RGB per label: body (skin), garment (blue), anything else (orange).
LABEL_COLORS = np.array([[0.87, 0.72, 0.62], [0.25, 0.47, 0.82], [0.95, 0.6, 0.2]], dtype=np.float32)


def new_figure(width: float, height: float, dpi: int):
    """A matplotlib Figure on the Agg canvas, independent of pyplot's global state."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def _save_atomic(fig, path: str | os.PathLike) -> str:
    """Write ``fig`` as a PNG to ``path`` atomically (temporary file + os.replace), flattened on the
    figure's face colour and stored with a 256-colour palette (a third of the RGBA file's size; the
    figures are flat-shaded points and text, which a palette keeps without visible banding)."""
    import io

    from PIL import Image

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", facecolor=fig.get_facecolor())
    buffer.seek(0)
    with Image.open(buffer) as image:
        rgba = image.convert("RGBA")
    flat = Image.new("RGBA", rgba.size, (255, 255, 255, 255))
    flat.alpha_composite(rgba)
    palette = flat.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    with atomic_open(path, "wb") as fh:
        palette.save(fh, format="PNG", optimize=True)
    return os.fspath(path)


def _check_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {points.shape}")
    return points


def colors_for(
    points: np.ndarray, normals: np.ndarray | None = None, labels: np.ndarray | None = None,
    mode: str = "label", *, joints: np.ndarray | None = None, body: np.ndarray | None = None,
) -> np.ndarray:
    """Base colour per point.

    Args:
        points: (N, 3). normals: (N, 3) unit or None. labels: (N,) int or None.
        mode: ``label`` (body skin / garment blue; without labels: skin, with the loose garment
            tinted garment blue where :func:`garment_weights` finds it from ``joints`` / ``body``),
            ``normal`` (RGB = (n + 1) / 2; needs normals), ``height`` (viridis on z).
        joints: (J, 3) the cloud's pose, or None. body: (V, 3) its posed body's vertices, or None.
    Returns:
        (N, 3) float32 RGB in [0, 1].
    """
    points = _check_points(points)
    n = len(points)
    if mode == "label":
        if labels is None:
            skin = np.broadcast_to(LABEL_COLORS[0], (n, 3)).astype(np.float32)
            known = joints is not None or body is not None
            w = garment_weights(points, joints, body) if known and n and np.isfinite(points).all() else None
            if w is None:
                return skin.copy()
            return (skin + w[:, None] * (LABEL_COLORS[1] - LABEL_COLORS[0])).astype(np.float32)
        labels = np.asarray(labels).reshape(-1)
        if labels.shape != (n,):
            raise ValueError(f"labels must have shape ({n},), got {labels.shape}")
        return LABEL_COLORS[np.clip(labels.astype(np.int64), 0, len(LABEL_COLORS) - 1)]
    if mode == "normal":
        if normals is None:
            raise ValueError("mode='normal' needs normals")
        normals = _check_points(normals, "normals")
        return np.clip((normals + 1.0) / 2.0, 0.0, 1.0).astype(np.float32)
    if mode == "height":
        from matplotlib import colormaps

        z = points[:, 2]
        t = (z - z.min()) / max(float(np.ptp(z)), 1e-9) if n else z
        return colormaps["viridis"](t)[:, :3].astype(np.float32)
    raise ValueError(f"mode must be 'label', 'normal' or 'height', got {mode!r}")


# ------------------------------------------------------------------ normals and garment tint
#: neighbours of the PCA normal estimate (:func:`estimate_normals`): on 2,048 points of a body
#: (~3 cm apart) they span ~5 cm, less than a forearm's girth
NORMAL_NEIGHBOURS = 12
#: garment tint ramps (metres; no tint below the first, full tint above the second, linear between)
#: of the distance from the posed body's nearest vertex (~0.3 cm apart), and of the distance
#: beyond the body envelope of the skeleton (:data:`BONE_RADII_M`)
TINT_BODY_M = (0.015, 0.025)
TINT_JOINTS_M = (0.01, 0.03)
#: Radius (metres) of the body around each bone of the 24-joint skeleton (bone k joins joint k + 1
#: to its parent; the head's runs on past the head joint by 0.6 of its length, to the crown) at
#: the bone's start, middle and end (linear between), for a skeleton whose pelvis-head + thigh +
#: shin length is ``BONE_RADII_SCALE_M`` (anny's mean body); scaled with it. Fitted to the anny
#: bodies of the 14 ``medium`` subjects, in the rest pose and in their demo poses: each vertex
#: belongs to the bone whose capsule it exceeds least, a radius is the 80th percentile of its
#: vertices' distances (median over the bodies), iterated to a fixed point. Torso and collar radii
#: are large: the torso is wide, not round.
BONE_RADII_M = np.array([
    (0.102, 0.112, 0.100), (0.102, 0.112, 0.100), (0.117, 0.099, 0.102),  # hips, spine1
    (0.096, 0.095, 0.065), (0.096, 0.095, 0.065), (0.079, 0.093, 0.144),  # knees, spine2
    (0.063, 0.062, 0.046), (0.063, 0.062, 0.046), (0.149, 0.153, 0.126),  # ankles, spine3
    (0.068, 0.049, 0.046), (0.068, 0.049, 0.046), (0.056, 0.055, 0.053),  # feet, neck
    (0.153, 0.181, 0.092), (0.153, 0.181, 0.092), (0.058, 0.104, 0.090),  # collars, head
    (0.067, 0.076, 0.065), (0.067, 0.076, 0.065), (0.047, 0.046, 0.041),  # shoulders, elbows
    (0.047, 0.046, 0.041), (0.040, 0.032, 0.026), (0.040, 0.032, 0.026),  # elbow, wrists
    (0.028, 0.067, 0.071), (0.028, 0.067, 0.071),  # hands
])  # fmt: skip
BONE_RADII_SCALE_M = 1.404
_BONES = np.array([(p, c) for c, p in enumerate(JOINT_PARENTS) if p >= 0])  # (23, 2) parent, child
#: bones whose envelope holds a skirt, dress or trousers: pelvis-hips, pelvis-spine1, the legs, feet
_LEG_BONES = np.isin(_BONES[:, 1], (1, 2, 3, 4, 5, 7, 8, 10, 11))


def _finite_points(points, name: str, min_rows: int = 0) -> np.ndarray:
    arr = np.asarray(points)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    arr = _check_points(arr, name)
    if len(arr) < min_rows:
        raise ValueError(f"{name} needs at least {min_rows} points, got {len(arr)}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contain NaN or inf")
    return arr


def _skeleton_capsules(points: np.ndarray, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point, how far (metres) it lies beyond the body envelope of a 24-joint skeleton
    (:data:`BONE_RADII_M`, scaled to the skeleton), the bone whose capsule it exceeds least (the
    index of its child joint minus 1) and that bone's nearest point: (N,), (N,) int, (N, 3)."""
    j = np.asarray(joints, np.float64)
    length = np.linalg.norm(j[15] - j[0]) + np.linalg.norm(j[4] - j[1]) + np.linalg.norm(j[7] - j[4])  # pelvis-head, leg
    scale = length / BONE_RADII_SCALE_M
    a, ab = j[_BONES[:, 0]], j[_BONES[:, 1]] - j[_BONES[:, 0]]  # (B, 3)
    ab[14] *= 1.6  # neck -> head, on to the crown
    t = np.clip(np.einsum("nbk,bk->nb", points[:, None] - a, ab) / np.maximum((ab * ab).sum(1), 1e-12), 0.0, 1.0)
    foot = a + t[..., None] * ab  # (N, B, 3)
    dist = np.linalg.norm(points[:, None] - foot, axis=2)  # (N, B)
    r = BONE_RADII_M * scale
    radius = np.where(t < 0.5, r[:, 0] + (r[:, 1] - r[:, 0]) * 2 * t, r[:, 1] + (r[:, 2] - r[:, 1]) * (2 * t - 1))
    excess = dist - radius
    k = excess.argmin(1)
    rows = np.arange(len(points))
    return excess[rows, k], k, foot[rows, k]


def _neighbours(points: np.ndarray, k: int) -> np.ndarray:
    """(N, min(k, N)) indices of each point's nearest points (itself first)."""
    from scipy.spatial import cKDTree

    return cKDTree(points).query(points, k=min(k, len(points)))[1].reshape(len(points), -1)


def estimate_normals(points: np.ndarray, joints: np.ndarray | None = None, k: int = NORMAL_NEIGHBOURS) -> np.ndarray:
    """Unit normals of a cloud without them: the least-variance axis of each point's ``k`` nearest
    neighbours (PCA; Hoppe et al. 1992, Sec. 3.2), turned outward.

    Outward: with the 24 ``joints``, away from the nearest point of the bone the point belongs to
    (the one whose body envelope it exceeds least, :data:`BONE_RADII_M`; 98-99 % right on clouds
    with known normals); other joints: away from the nearest joint; without joints, away from the
    centroid of its 32 nearest points plus half the direction away from the vertical axis through
    the centroid of the points at its height (~93 % right: flat and concave parts are ambiguous).
    Each normal is then averaged with those of its neighbours that agree with it (weights
    max(0, n_i . n_j)^2), which calms the noise of a sparse cloud without blurring thin parts.
    points: (N, 3), N >= 3, finite; joints: (J, 3) or None. Returns (N, 3) float64.
    """
    points = _finite_points(points, "points", 3)
    if not isinstance(k, (int, np.integer)) or k < 3:
        raise ValueError(f"k must be an integer >= 3, got {k!r}")
    idx = _neighbours(points, k)
    local = points[idx] - points[idx].mean(1, keepdims=True)  # (N, k, 3)
    normals = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))[1][:, :, 0]  # smallest eigenvalue
    if joints is not None:
        joints = _finite_points(joints, "joints", 1)
        if len(joints) == NUM_JOINTS:
            out = points - _skeleton_capsules(points, joints)[2]
        else:
            from scipy.spatial import cKDTree

            out = points - joints[cKDTree(joints).query(points)[1]]
    else:
        wide = points[_neighbours(points, 32)].mean(1)
        z = points[:, 2]
        slab = np.clip(((z - z.min()) / max(float(np.ptp(z)), 1e-9) * 30).astype(np.int64), 0, 29)
        count = np.maximum(np.bincount(slab, minlength=30), 1)
        axis = np.stack([np.bincount(slab, points[:, i], minlength=30) / count for i in (0, 1)], 1)
        radial = np.concatenate([points[:, :2] - axis[slab], np.zeros((len(points), 1))], 1)
        out = _unit(points - wide) + 0.5 * _unit(radial)
    flip = np.einsum("ni,ni->n", normals, out) < 0
    normals[flip] *= -1
    agree = np.clip(np.einsum("nki,ni->nk", normals[idx], normals), 0.0, None) ** 2  # (N, k)
    return _unit(np.einsum("nk,nki->ni", agree, normals[idx]))  # averaged with the neighbours that agree


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def garment_weights(
    points: np.ndarray, joints: np.ndarray | None = None, body: np.ndarray | None = None
) -> np.ndarray | None:
    """How much each point of an unlabeled cloud is loose garment, in [0, 1] (1: garment).

    Where the cloth hangs free: with the posed ``body`` (V, 3) vertices, by the distance to the
    nearest vertex, ramped over :data:`TINT_BODY_M` (1.5-2.5 cm: skin lies within ~1 cm); with
    the 24 ``joints`` only, by how far the point lies beyond the body envelope of the skeleton
    (:data:`BONE_RADII_M`), ramped over :data:`TINT_JOINTS_M` (1-3 cm). Either distance is the
    median over the point's 12 nearest points (no speckles). Where it clings: a skirt, dress or
    trousers hugs the hips and thighs, closer than any distance tells from skin; with the 24
    joints, the tint climbs from the points found hanging free (weight >= 0.5) up the graph of
    12 nearest points, from each point to its higher neighbours, over the points of the legs and
    pelvis (those whose envelope is a hip, leg, foot or lower-spine bone's): up to the waist, never
    down to a bare leg below the hem, nor onto the torso or arms. On the 14 shipped demo poses
    (POP's clouds of 2,048 points, posed body known) the joints rule agrees with the body rule on
    87-100 % of the points (at most 6 % tinted that it leaves skin; 3 % on ``tight_a``); it tints
    46-51 % of the default model's three ``demo:skirt`` hypotheses, whose scan has 50 % of its
    points on the skirt. Neither known, or joints of another skeleton: None (no tint).
    points: (N, 3) finite; joints: (J, 3); body: (V, 3).
    """
    points = _finite_points(points, "points")
    skeleton = None
    if joints is not None:
        joints = _finite_points(joints, "joints", 1)
        skeleton = _skeleton_capsules(points, joints) if len(joints) == NUM_JOINTS and len(points) else None
    if body is not None:
        from scipy.spatial import cKDTree

        dist, ramp = cKDTree(_finite_points(body, "body", 1)).query(points)[0], TINT_BODY_M
    elif skeleton is not None:
        dist, ramp = skeleton[0], TINT_JOINTS_M
    else:
        return None
    idx = _neighbours(points, 12) if len(points) > 1 else np.zeros((len(points), 1), np.int64)
    weights = np.clip((np.median(dist[idx], axis=1) - ramp[0]) / (ramp[1] - ramp[0]), 0.0, 1.0)
    if skeleton is not None:  # up from where it hangs free, over the legs and pelvis
        legs = _LEG_BONES[skeleton[1]]
        z = points[:, 2]
        climbs = (z[idx] < z[:, None] - 1e-4) & legs[idx] & legs[:, None]  # (N, k): neighbour j lies below i
        tinted = (weights >= 0.5) & legs
        for _ in range(len(points)):
            new = ~tinted & (tinted[idx] & climbs).any(1)
            if not new.any():
                break
            tinted |= new
        weights[tinted] = 1.0
    return weights


def project(points: np.ndarray, view: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3) -> screen u (N,), v (N,), depth towards the viewer (N,)."""
    if view not in VIEWS:
        raise ValueError(f"view must be one of {sorted(VIEWS)}, got {view!r}")
    right, up, toward = (np.asarray(a, dtype=np.float64) for a in VIEWS[view])
    return points @ right, points @ up, points @ toward


def _auto_point_size(ax, u: np.ndarray, v: np.ndarray, extent, front_share: float = 0.5) -> float:
    """Marker area (points^2) so splats close the gaps between neighbouring points.

    The silhouette area is estimated on a 64x64 occupancy grid, covered by the
    front layer of ``front_share * N`` points (about half of an unculled cloud).
    """
    n = len(u)
    if n == 0 or extent is None:
        return 4.0
    du, dv = extent[1] - extent[0], extent[3] - extent[2]
    bbox = ax.get_window_extent()
    px_per_m = min(bbox.width / max(du, 1e-9), bbox.height / max(dv, 1e-9))
    cell = max(du, dv) / 64
    occ = np.unique(np.stack([np.floor(u / cell), np.floor(v / cell)], 1).astype(np.int64), axis=0)
    spacing_m = np.sqrt(len(occ) * cell * cell / max(front_share * n, 1))
    diameter_px = np.clip(4.0 * spacing_m * px_per_m, 2.2, 20.0)  # >= 2 px: smaller splats alias to grey
    return float((diameter_px * 72.0 / ax.figure.dpi) ** 2)


def render_points(
    ax, points: np.ndarray, colors: np.ndarray | None = None, labels: np.ndarray | None = None,
    normals: np.ndarray | None = None, view: str = "front", point_size: float | None = None,
    extent: tuple[float, float, float, float] | None = None, shade: bool = True, cull: bool = True,
    *, joints: np.ndarray | None = None, body: np.ndarray | None = None, estimate: bool = True,
    two_sided: bool = False,
) -> None:
    """Draw a point cloud on a matplotlib Axes, orthographic, painter's order.

    Args:
        ax: matplotlib Axes (cleared of ticks/spines; equal aspect).
        points: (N, 3). colors: (N, 3) RGB or None (then from ``labels``, or from ``joints`` /
            ``body``: the loose garment tinted, :func:`colors_for`).
        labels: (N,) point labels, used when ``colors`` is None.
        normals: (N, 3) unit normals or None; with ``shade`` they darken points
            facing away from the light (Lambert, :data:`KEY_LIGHT`, 0.42 ambient).
        view: one of ``VIEWS`` (front, side, back, top).
        point_size: marker area in points^2; None = chosen from N.
        extent: (u_min, u_max, v_min, v_max) screen window; None = fit the cloud.
        shade: modulate brightness by the normal's facing (without normals and
            fewer than 8 points or any NaN: by depth, farther points darker).
        cull: drop points whose normal faces away from the viewer (needs
            normals): they are hidden in a solid surface and would otherwise
            show through the gaps between splats.
        joints: (J, 3) the cloud's pose or None; body: (V, 3) its posed body's vertices or None.
        estimate: without ``normals``, estimate them (:func:`estimate_normals`, oriented by
            ``joints``). Without joints their orientation is a guess (~93 % right): the shading
            is then two-sided and nothing is culled.
        two_sided: the normals' orientation is unknown: shade by the absolute facing, cull nothing.
    """
    points = _check_points(points)
    n = len(points)
    if colors is None:
        colors = colors_for(points, labels=labels, mode="label", joints=joints, body=body)
    colors = np.asarray(colors, dtype=np.float32)
    if colors.shape != (n, 3):
        raise ValueError(f"colors must have shape ({n}, 3), got {colors.shape}")
    u, v, depth = project(points, view)
    if extent is None and n:
        pad = 0.03 * max(float(np.ptp(u)), float(np.ptp(v)), 1e-6)
        extent = (u.min() - pad, u.max() + pad, v.min() - pad, v.max() + pad)
    culled = False
    if normals is None and estimate and (shade or cull):
        normals, two_sided = _shading_normals(points, joints)
    cull = cull and not two_sided
    if normals is not None and (shade or cull):
        normals = _check_points(normals, "normals")
        if normals.shape != points.shape:
            raise ValueError(f"normals must have shape {points.shape}, got {normals.shape}")
        facing = normals @ np.asarray(VIEWS[view][2], dtype=np.float64)
        if two_sided:
            facing = np.abs(facing)
        if shade:
            right, up, toward = (np.asarray(a, dtype=np.float64) for a in VIEWS[view])
            lit = normals @ _unit(toward + KEY_LIGHT[0] * right + KEY_LIGHT[1] * up)
            light = 0.42 + 0.58 * np.clip(np.abs(lit) if two_sided else lit, 0.0, 1.0) ** 1.2
            colors = np.clip(colors * light[:, None], 0.0, 1.0)
        if cull:
            keep = facing > -0.15
            u, v, depth, colors = u[keep], v[keep], depth[keep], colors[keep]
            culled = True
    elif shade and n:  # no normals: depth cue, farther points darker
        near = (depth - depth.min()) / max(float(np.ptp(depth)), 1e-9)
        colors = np.clip(colors * (0.55 + 0.45 * near)[:, None], 0.0, 1.0)
    if point_size is None:
        point_size = _auto_point_size(ax, u, v, extent, front_share=1.0 if culled else 0.5)
    order = np.argsort(depth, kind="stable")  # far (small depth) first
    ax.scatter(u[order], v[order], c=colors[order], s=point_size, marker="o", linewidths=0,
               edgecolors="none", rasterized=True)
    if extent is not None:
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal", adjustable="box")
    ax.set_axis_off()


def _shading_normals(points: np.ndarray, joints: np.ndarray | None) -> tuple[np.ndarray | None, bool]:
    """Estimated normals to shade a cloud without them, and whether their orientation is a guess
    (no joints); None for fewer than 8 points or any NaN (then a depth cue shades it)."""
    if len(points) < 8 or not np.isfinite(points).all():
        return None, False
    return estimate_normals(points, joints), joints is None


def _per_cloud(value, count: int, name: str) -> list[np.ndarray | None]:
    """``value`` for each of ``count`` clouds: None, one (J, 3) array for all, or one entry each."""
    if value is None:
        return [None] * count
    if isinstance(value, np.ndarray) and value.ndim == 2:
        return [value] * count
    if len(value) != count:
        raise ValueError(f"{name} must be one (K, 3) array or one entry per cloud ({count}), got {len(value)}")
    return [None if x is None else np.asarray(x) for x in value]


def render_grid(
    clouds: Sequence[tuple], path: str | os.PathLike, views: Sequence[str] = ("front", "side"),
    ncols: int | None = None, mode: str = "label", panel_size: float = 3.0, dpi: int = 100,
    point_size: float | None = None, colors: Sequence[np.ndarray | None] | None = None,
    *, joints: np.ndarray | Sequence[np.ndarray | None] | None = None,
    body: np.ndarray | Sequence[np.ndarray | None] | None = None, fit: bool = False,
) -> str:
    """Render several clouds, each from several views, into one PNG (atomic write).

    Args:
        clouds: list of ``(points (N, 3), labels (N,) | None, normals (N, 3) | None, title)``.
        path: output PNG path.
        views: views per cloud, drawn side by side.
        ncols: clouds per row (default: all in one row, at most 4).
        mode: colour mode, see :func:`colors_for` (``normal`` without normals: estimated ones).
        panel_size: inches per panel; dpi: pixels per inch.
        colors: per cloud, (N, 3) RGB in [0, 1] used instead of ``mode`` (None entries keep it).
        joints: the clouds' pose, (J, 3) for all of them or one (J, 3) | None per cloud: orients
            the estimated normals of clouds without them and, for unlabeled clouds, finds the
            loose garment to tint (:func:`garment_weights`). body: the posed body's (V, 3)
            vertices, shared or per cloud likewise (a sharper garment tint).
        fit: panel widths fitted to each view's widest cloud (``panel_size`` is then the
            panels' height), instead of square panels: less white space around a body.
    All panels share one scale (metres per pixel) so sizes are comparable; clouds without normals
    are shaded by estimated ones (:func:`render_points`).
    Returns: ``path`` as a string.
    """
    if len(clouds) == 0:
        raise ValueError("clouds is empty: nothing to render")
    if not views:
        raise ValueError("views is empty")
    for v in views:
        if v not in VIEWS:
            raise ValueError(f"view must be one of {sorted(VIEWS)}, got {v!r}")
    items = []
    for k, c in enumerate(clouds):
        if len(c) != 4:
            raise ValueError(f"clouds[{k}] must be (points, labels, normals, title), got {len(c)} items")
        pts, lab, nrm, title = c
        items.append((_check_points(pts, f"clouds[{k}] points"), lab, nrm, str(title)))
    if colors is not None and len(colors) != len(items):
        raise ValueError(f"colors must have one entry per cloud ({len(items)}), got {len(colors)}")
    poses, bodies = _per_cloud(joints, len(items), "joints"), _per_cloud(body, len(items), "body")
    ncols = ncols or min(len(items), 4)
    nrows = -(-len(items) // ncols)
    half_u = dict.fromkeys(views, 1e-6)  # shared half-extents of the panel windows, per view
    half_v = 1e-6
    for pts, *_ in items:
        for v in views:
            if len(pts):
                u, w, _ = project(pts, v)
                half_u[v], half_v = max(half_u[v], float(np.ptp(u)) / 2), max(half_v, float(np.ptp(w)) / 2)
    if not fit:  # square panels
        half_v = max(half_v, *half_u.values())
        half_u = dict.fromkeys(views, half_v)
    half_u, half_v = {v: 1.04 * h for v, h in half_u.items()}, 1.04 * half_v
    cols = ncols * len(views)
    widths = [panel_size * half_u[v] / half_v for v in views] * ncols
    title_h = 0.35
    fig = new_figure(sum(widths), panel_size * nrows + title_h * nrows, dpi)
    fig.patch.set_facecolor("white")
    grid = fig.add_gridspec(nrows, cols, width_ratios=widths, left=0.01, right=0.99, bottom=0.01,
                            top=1 - 0.3 / (panel_size * nrows + title_h * nrows), wspace=0.02, hspace=0.08)
    for k, (pts, lab, nrm, title) in enumerate(items):
        given = None if colors is None else colors[k]
        if given is not None and np.shape(given) != (len(pts), 3):
            raise ValueError(f"colors[{k}] must have shape ({len(pts)}, 3), got {np.shape(given)}")
        two_sided = False
        if nrm is None:  # estimated once, for every view
            nrm, two_sided = _shading_normals(pts, poses[k])
        rgb = (colors_for(pts, normals=nrm, labels=lab, mode=mode, joints=poses[k], body=bodies[k])
               if given is None else np.asarray(given, np.float32))  # fmt: skip
        r, c0 = divmod(k, ncols)
        for j, v in enumerate(views):
            ax = fig.add_subplot(grid[r, c0 * len(views) + j])
            if len(pts):
                u, w, _ = project(pts, v)
                cu, cw = (u.min() + u.max()) / 2, (w.min() + w.max()) / 2
            else:
                cu = cw = 0.0
            render_points(ax, pts, colors=rgb, normals=nrm, view=v, point_size=point_size,
                          extent=(cu - half_u[v], cu + half_u[v], cw - half_v, cw + half_v), estimate=False,
                          two_sided=two_sided)  # fmt: skip
            ax.set_title(f"{title} ({v})" if title else v, fontsize=9)
    return _save_atomic(fig, path)


def render_turntable_frames(
    points: np.ndarray, labels: np.ndarray | None, normals: np.ndarray | None, folder: str | os.PathLike,
    num_frames: int = 12, size: float = 4.0, dpi: int = 100, mode: str = "label",
    *, joints: np.ndarray | None = None, body: np.ndarray | None = None,
) -> list[str]:
    """Render ``num_frames`` PNGs of a cloud rotating about the vertical axis (front view).

    The cloud is rotated about its own vertical centre line by 360/num_frames
    degrees per frame. joints / body: the cloud's pose, as in :func:`render_points`.
    Returns the written paths ``folder/frame_0000.png`` ...
    """
    points = _check_points(points)
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    colors = colors_for(points, normals=normals, labels=labels, mode=mode, joints=joints, body=body)
    two_sided = False
    if normals is None:  # estimated once, turned with the cloud
        normals, two_sided = _shading_normals(points, None if joints is None else np.asarray(joints, np.float64))
    centre = (points.min(0) + points.max(0)) / 2 if len(points) else np.zeros(3)
    half = 1.04 * max(float(np.linalg.norm((points - centre)[:, :2], axis=1).max()) if len(points) else 1e-6,
                      float(np.ptp(points[:, 2])) / 2 if len(points) else 1e-6)
    paths = []
    for i in range(num_frames):
        a = 2 * np.pi * i / num_frames
        rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        p = (points - centre) @ rot.T
        nrm = None if normals is None else np.asarray(normals, dtype=np.float64) @ rot.T
        fig = new_figure(size, size, dpi)
        ax = fig.add_axes((0, 0, 1, 1))
        render_points(ax, p, colors=colors, normals=nrm, view="front", extent=(-half, half, -half, half),
                      two_sided=two_sided)  # fmt: skip
        paths.append(_save_atomic(fig, os.path.join(os.fspath(folder), f"frame_{i:04d}.png")))
    return paths


def plot_curves(
    curves: dict[str, tuple[Sequence[float], Sequence[float]]], path: str | os.PathLike,
    xlabel: str = "step", ylabel: str = "loss", logy: bool = False, title: str | None = None,
    logx: bool = False,
) -> str:
    """Line plot of named (x, y) curves (loss curves etc.) to a PNG (atomic write).

    Args:
        curves: name -> (x (K,), y (K,)).
        logy / logx: log-scale axes (non-positive values are dropped by matplotlib).
    Returns: ``path`` as a string.
    """
    if not curves:
        raise ValueError("curves is empty: nothing to plot")
    fig = new_figure(6.0, 4.0, 100)
    ax = fig.add_subplot(1, 1, 1)
    for name, (x, y) in curves.items():
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        if x.shape != y.shape or x.ndim != 1:
            raise ValueError(f"curve {name!r}: x and y must be 1-D of equal length, got {x.shape} and {y.shape}")
        ax.plot(x, y, label=name, linewidth=1.5, marker="o" if len(x) <= 12 else None, markersize=3)
    if logy:
        ax.set_yscale("log")
    if logx:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(True, alpha=0.3, which="both")
    ax.legend(frameon=False, fontsize=7 if len(curves) > 3 else 9)
    fig.tight_layout()
    return _save_atomic(fig, path)


def _face_colors(tri: np.ndarray, fn: np.ndarray, mode: str, color: Sequence[float]) -> np.ndarray:
    """(F, 3) base RGB per face: ``label`` one colour, ``normal`` (n + 1) / 2, ``height`` viridis on z."""
    if mode == "normal":
        return ((fn + 1.0) / 2.0).astype(np.float64)
    if mode == "height":
        return colors_for(tri.mean(1), mode="height").astype(np.float64)
    if mode == "label":
        return np.broadcast_to(np.asarray(color, np.float64), (len(tri), 3))
    raise ValueError(f"mode must be 'label', 'normal' or 'height', got {mode!r}")


def draw_mesh(
    ax, vertices: np.ndarray, faces: np.ndarray, view: str = "front", color: Sequence[float] = (0.75, 0.78, 0.85),
    mode: str = "label", extent: tuple[float, float, float, float] | None = None,
) -> None:
    """Draw a triangle mesh on a matplotlib Axes (orthographic, painter's order, headlight Lambert
    shading with 0.25 ambient, back faces culled). vertices: (V, 3); faces: (F, 3) int.
    mode: face colours, see :func:`_face_colors` (``label`` = ``color``). extent: as in
    :func:`render_points` (None: fit the mesh)."""
    from matplotlib.collections import PolyCollection

    vertices = _check_points(vertices, "vertices")
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
        raise ValueError(f"faces must be an integer array of shape (F, 3), got {faces.dtype} {faces.shape}")
    if len(faces) == 0:
        raise ValueError("faces is empty: nothing to render")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"face index out of range [0, {len(vertices)})")
    tri = vertices[faces]  # (F, 3, 3)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-20)
    base = _face_colors(tri, fn, mode, color)
    u, v, depth = project(tri.reshape(-1, 3), view)
    u, v, depth = u.reshape(-1, 3), v.reshape(-1, 3), depth.reshape(-1, 3).mean(1)
    facing = fn @ np.asarray(VIEWS[view][2], dtype=np.float64)
    keep = facing > 0
    order = np.argsort(depth[keep], kind="stable")
    shade = 0.25 + 0.75 * facing[keep][order]
    colors = np.clip(base[keep][order] * shade[:, None], 0, 1)
    polys = np.stack([u[keep][order], v[keep][order]], axis=-1)  # (F', 3, 2)
    ax.add_collection(PolyCollection(polys, facecolors=colors, edgecolors="face", linewidths=0.1,
                                     rasterized=True))  # fmt: skip
    if extent is None:
        uu, vv, _ = project(vertices, view)
        pad = 0.03 * max(float(np.ptp(uu)), float(np.ptp(vv)), 1e-6)
        extent = (uu.min() - pad, uu.max() + pad, vv.min() - pad, vv.max() + pad)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal", adjustable="box")
    ax.set_axis_off()


def render_mesh(
    vertices: np.ndarray, faces: np.ndarray, path: str | os.PathLike, views: Sequence[str] = ("front", "side"),
    color: Sequence[float] = (0.75, 0.78, 0.85), panel_size: float = 4.0, dpi: int = 100,
) -> str:
    """Render a triangle mesh to a PNG, one panel per view (orthographic, atomic write).

    Faces are drawn in painter's order (far first) with headlight Lambert shading
    (0.25 ambient); back faces are culled (:func:`draw_mesh`). vertices: (V, 3); faces: (F, 3) int.
    Returns ``path`` as a string.
    """
    return render_meshes([(vertices, faces, "")], path, views=views, color=color, panel_size=panel_size, dpi=dpi,
                         titles=False)  # fmt: skip


def render_meshes(
    meshes: Sequence[tuple], path: str | os.PathLike, views: Sequence[str] = ("front", "side"),
    mode: str = "label", color: Sequence[float] = (0.75, 0.78, 0.85), panel_size: float = 4.0, dpi: int = 100,
    titles: bool = True,
) -> str:
    """Render meshes ``[(vertices (V, 3), faces (F, 3), title), ...]`` to one PNG: a row per
    mesh, a panel per view, each panel fitted to its mesh (atomic write). Returns ``path``."""
    if len(meshes) == 0:
        raise ValueError("meshes is empty: nothing to render")
    for v in views:
        if v not in VIEWS:
            raise ValueError(f"view must be one of {sorted(VIEWS)}, got {v!r}")
    rows, cols = len(meshes), len(views)
    fig = new_figure(panel_size * cols, panel_size * rows, dpi)
    fig.patch.set_facecolor("white")
    for r, (verts, faces, title) in enumerate(meshes):
        for j, view in enumerate(views):
            ax = fig.add_subplot(rows, cols, r * cols + j + 1)
            draw_mesh(ax, verts, faces, view=view, color=color, mode=mode)
            ax.set_title(f"{title} ({view})" if titles and title else view, fontsize=9)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=1 - 0.07 / rows, wspace=0.02, hspace=0.08)
    return _save_atomic(fig, path)


# ------------------------------------------------------------------------------ turntable GIFs
def frames_to_gif(images: Sequence[np.ndarray], path: str | os.PathLike, fps: float = 10.0) -> str:
    """Write RGB frames (each (H, W, 3) uint8) as a looping animated GIF, atomically."""
    import io

    from PIL import Image

    if len(images) == 0:
        raise ValueError("no frames to write")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    pal = [Image.fromarray(np.asarray(im, np.uint8)[..., :3]).convert("P", palette=Image.ADAPTIVE) for im in images]
    buf = io.BytesIO()
    pal[0].save(buf, format="GIF", save_all=True, append_images=pal[1:], duration=int(1000 / fps), loop=0)
    with atomic_open(path, "wb") as f:
        f.write(buf.getvalue())
    return os.fspath(path)


def _fig_rgb(fig) -> np.ndarray:
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()  # (H, W, 3) uint8


def turntable_gif(
    path: str | os.PathLike, points: np.ndarray, labels: np.ndarray | None = None, normals: np.ndarray | None = None,
    faces: np.ndarray | None = None, num_frames: int = 24, mode: str = "label", size: float = 4.0, dpi: int = 80,
    fps: float = 12.0, *, joints: np.ndarray | None = None, body: np.ndarray | None = None,
) -> str:
    """An animated GIF of a cloud (``faces`` None) or a mesh (``points`` = vertices) rotating
    360 degrees about its vertical centre line, seen from the front; one fixed window for all
    frames (as :func:`render_turntable_frames`). joints / body: the cloud's pose, as in
    :func:`render_points`. Returns ``path``."""
    points = _check_points(points)
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    if len(points) == 0:
        raise ValueError("nothing to render: no points")
    colors = None if faces is not None else colors_for(points, normals=normals, labels=labels, mode=mode,
                                                       joints=joints, body=body)  # fmt: skip
    two_sided = False
    if faces is None and normals is None:  # estimated once, turned with the cloud
        normals, two_sided = _shading_normals(points, None if joints is None else np.asarray(joints, np.float64))
    centre = (points.min(0) + points.max(0)) / 2
    half = 1.04 * max(float(np.linalg.norm((points - centre)[:, :2], axis=1).max()), float(np.ptp(points[:, 2])) / 2,
                      1e-6)  # fmt: skip
    images = []
    for i in range(num_frames):
        a = 2 * np.pi * i / num_frames
        rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        p = (points - centre) @ rot.T
        fig = new_figure(size, size, dpi)
        fig.patch.set_facecolor("white")
        ax = fig.add_axes((0, 0, 1, 1))
        if faces is None:
            nrm = None if normals is None else np.asarray(normals, dtype=np.float64) @ rot.T
            render_points(ax, p, colors=colors, normals=nrm, view="front", extent=(-half, half, -half, half),
                          two_sided=two_sided)  # fmt: skip
        else:
            draw_mesh(ax, p, faces, view="front", mode=mode, extent=(-half, half, -half, half))
        images.append(_fig_rgb(fig))
    return frames_to_gif(images, path, fps)


# ----------------------------------------------------------------------------- animation GIF
def render_gif(clouds: np.ndarray, path: str | os.PathLike, fps: float = 10.0, view: str = "front",
               size: float = 3.0, dpi: int = 80, colors: np.ndarray | None = None, *,
               joints: np.ndarray | None = None) -> str:  # fmt: skip
    """Render clouds (T, N, 3) as an animated GIF (one shared window, so motion is visible);
    written atomically. colors: (T, N, 3) RGB or None (skin colour, the loose garment tinted when
    ``joints`` are given). Shaded by estimated normals (:func:`render_points`). joints: (T, J, 3)
    each frame's pose, or None."""
    from PIL import Image

    clouds = np.asarray(clouds, np.float64)
    if clouds.ndim != 3 or clouds.shape[-1] != 3 or len(clouds) == 0:
        raise ValueError(f"clouds must have shape (T, N, 3), got {clouds.shape}")
    if joints is not None and (np.ndim(joints) != 3 or len(joints) != len(clouds)):
        raise ValueError(f"joints must have shape ({len(clouds)}, J, 3), got {np.shape(joints)}")
    u, v, _ = project(clouds.reshape(-1, 3), view)
    half = 0.52 * max(float(np.ptp(u)), float(np.ptp(v)), 1e-6)
    cu, cv = (u.min() + u.max()) / 2, (v.min() + v.max()) / 2
    images = []
    for k, pts in enumerate(clouds):
        fig = new_figure(size, size, dpi)
        fig.patch.set_facecolor("white")
        ax = fig.add_axes((0, 0, 1, 1))
        render_points(ax, pts, colors=None if colors is None else colors[k], view=view,
                      extent=(cu - half, cu + half, cv - half, cv + half),
                      joints=None if joints is None else joints[k])  # fmt: skip
        ax.text(0.02, 0.97, f"{k}", transform=ax.transAxes, fontsize=8, va="top")
        fig.canvas.draw()
        rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3]  # (H, W, 3) uint8
        images.append(Image.fromarray(rgb).convert("P", palette=Image.ADAPTIVE))
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    with atomic_open(path, "wb") as f:
        f.write(buf.getvalue())
    return os.fspath(path)
