"""Simulate a loose garment on a moving anny body with newton's VBD cloth solver (CPU).

The body is a *kinematic collider*: it drives the cloth, the cloth never
pushes back. Two collider set-ups are available (``ClothSimSettings.collider``):

- ``"capsules"``: 16 capsules fitted to body parts in the rest pose (pelvis,
  2 torso columns x 2 levels, thighs, shins, upper arms, forearms, hips). Each
  capsule end is skinned like a garment pin (mean of its nearest body
  vertices' ``v + vtransf @ offset``), so the capsules follow the posed body.
  Capsules are analytic: cheap, but they can only approximate the body
  (concave/flat regions), so some cloth ends up a few mm inside the true skin.
- ``"mesh"``: the full anny body mesh as one deforming mesh shape (its points
  and velocities are rewritten and its BVH refit every substep), attached to a
  kinematic body that follows the pelvis. Exact surface; contact is found
  only within ``contact_margin`` of the surface, so particles pushed deeper
  than that in one substep are lost (keep substeps high enough).

``benchmarks/bench_cloth.py`` measures the speed/penetration trade-off.

Per output frame (fps 25) the simulator records penetration of the garment
into the *full* body mesh (signed distance via open3d ray casting), the
maximum edge stretch and a validity flag. Frames with NaN, stretch above
``max_stretch``, vertices farther than ``max_distance`` from the body, or
penetration above thresholds are marked invalid with a reason. After a
*hard* failure (NaN, explosion) the state is garbage: the simulator restores
the last valid cloth state (zero velocity) and continues, so later frames may
recover; each frame is still judged on its own. ``reset_count`` in the
result says how often this happened.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..body.anny_body import AnnyBody, PosedBody
from ..body.skeleton import joint_index
from .garments import Garment, pin_positions

COLLIDERS: tuple[str, ...] = ("capsules", "mesh")


@dataclass
class ClothSimSettings:
    """Cloth simulation settings (SI units: metres, seconds, kg).

    fps: output frame rate; the body sequence is given at this rate.
    substeps, iterations: VBD substeps per frame and solver iterations per substep.
    collider: ``"capsules"`` or ``"mesh"`` (see module docstring).
    density: cloth area density [kg/m^2]. tri_ke/tri_ka/tri_kd: membrane
    stretch/area stiffness and damping; edge_ke/edge_kd: bending.
    particle_radius, contact_margin: collision thickness and detection gap [m].
    contact_ke/kd/mu: cloth-body contact stiffness, damping, friction.
    settle_frames: frames simulated at the first pose before recording.
    capsule_percentile: percentile of the part vertices' distance to a capsule
        axis used as its radius (100 = enclose every vertex).
    max_stretch, max_distance, max_penetration, max_penetration_fraction:
        validity thresholds (ratio, m, m, fraction).
    """

    fps: float = 25.0
    substeps: int = 10
    iterations: int = 5
    collider: str = "capsules"
    density: float = 0.15
    tri_ke: float = 1.0e4
    tri_ka: float = 1.0e4
    tri_kd: float = 1.0e-5
    edge_ke: float = 1.0e-3
    edge_kd: float = 0.0
    particle_radius: float = 0.004
    contact_margin: float = 0.01
    contact_ke: float = 1.0e4
    contact_kd: float = 1.0e-2
    contact_mu: float = 0.2
    settle_frames: int = 10
    capsule_percentile: float = 90.0
    max_stretch: float = 3.0
    max_distance: float = 0.6
    max_penetration: float = 0.03
    max_penetration_fraction: float = 0.1


@dataclass
class ClothFrameStats:
    """Quality of one simulated frame (distances in metres)."""

    penetration_max: float
    penetration_mean: float
    penetration_fraction: float
    stretch_max: float
    valid: bool
    reason: str = ""


@dataclass
class ClothSequence:
    """Simulated garment over T frames.

    vertices: (T, Vg, 3) float32; faces: (Fg, 3) int64; stats: T frame stats;
    seconds_per_frame: wall-clock simulation time per output frame (excludes
    settling, kernel compilation and the stats); reset_count: how often the
    state was restored after a hard failure.
    """

    vertices: np.ndarray
    faces: np.ndarray
    stats: list[ClothFrameStats]
    seconds_per_frame: float
    reset_count: int = 0
    settings: ClothSimSettings = field(default_factory=ClothSimSettings)

    @property
    def valid(self) -> np.ndarray:
        """(T,) bool per-frame validity."""
        return np.array([s.valid for s in self.stats], dtype=bool)


# ----------------------------------------------------------------------------- metrics


def signed_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed distance (N,) of points (N, 3) to a closed triangle mesh, negative
    inside (open3d RaycastingScene: closest point + ray-parity inside test)."""
    import open3d as o3d  # lazy: heavy import

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
    )
    q = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
    return scene.compute_signed_distance(q).numpy()


@dataclass
class PenetrationStats:
    """Penetration of points into a body mesh: depths in metres."""

    max: float
    mean: float
    fraction: float


def penetration_stats(
    garment_vertices: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray
) -> PenetrationStats:
    """Depth of garment vertices (Vg, 3) inside the body mesh (V, 3)/(F, 3).

    max/mean are over all garment vertices of max(0, -signed distance); fraction
    is the share of vertices strictly inside. NaN vertices count as inside.
    """
    sd = signed_distance(np.nan_to_num(garment_vertices, nan=0.0), body_vertices, body_faces)
    sd[~np.isfinite(garment_vertices).all(1)] = -np.inf
    depth = np.clip(-sd, 0.0, None)
    return PenetrationStats(float(depth.max()), float(depth.mean()), float((sd < 0).mean()))


def edge_stretch(vertices: np.ndarray, edges: np.ndarray, rest_length: np.ndarray) -> float:
    """Max ratio of current to rest length over edges (E, 2)."""
    cur = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    return float(np.max(cur / rest_length))


def frame_stats(
    vertices: np.ndarray,
    body_vertices: np.ndarray,
    body_faces: np.ndarray,
    edges: np.ndarray,
    rest_length: np.ndarray,
    settings: ClothSimSettings,
) -> ClothFrameStats:
    """Judge one frame: garment (Vg, 3) against the posed full body (V, 3)."""
    if not np.isfinite(vertices).all():
        return ClothFrameStats(np.inf, np.inf, 1.0, np.inf, False, "nan")
    stretch = edge_stretch(vertices, edges, rest_length)
    pen = penetration_stats(vertices, body_vertices, body_faces)
    reasons = []
    if stretch > settings.max_stretch:
        reasons.append(f"explosion: stretch {stretch:.2f}")
    far = np.linalg.norm(vertices - body_vertices.mean(0), axis=1).max()
    lo, hi = body_vertices.min(0) - settings.max_distance, body_vertices.max(0) + settings.max_distance
    if (vertices < lo).any() or (vertices > hi).any():
        reasons.append(f"explosion: vertex {far:.2f} m from the body centre")
    if pen.max > settings.max_penetration:
        reasons.append(f"penetration {pen.max * 100:.1f} cm")
    if pen.fraction > settings.max_penetration_fraction:
        reasons.append(f"{pen.fraction * 100:.0f}% vertices inside")
    return ClothFrameStats(pen.max, pen.mean, pen.fraction, stretch, not reasons, "; ".join(reasons))


def _is_hard_failure(s: ClothFrameStats) -> bool:
    return s.reason.startswith("nan") or "explosion" in s.reason


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2) of triangles (F, 3)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


# ----------------------------------------------------------------------------- capsules

#: (start joint, end joint, body parts (joints) whose vertices fit the radius, lateral side)
_CAPSULE_SPECS: tuple[tuple[str, str, tuple[str, ...], int], ...] = (
    ("left_hip", "left_knee", ("left_hip",), 0),
    ("right_hip", "right_knee", ("right_hip",), 0),
    ("left_knee", "left_ankle", ("left_knee",), 0),
    ("right_knee", "right_ankle", ("right_knee",), 0),
    ("left_shoulder", "left_elbow", ("left_shoulder",), 0),
    ("right_shoulder", "right_elbow", ("right_shoulder",), 0),
    ("left_elbow", "left_wrist", ("left_elbow",), 0),
    ("right_elbow", "right_wrist", ("right_elbow",), 0),
    ("pelvis", "spine2", ("pelvis", "spine1", "left_hip", "right_hip"), +1),
    ("pelvis", "spine2", ("pelvis", "spine1", "left_hip", "right_hip"), -1),
    ("spine2", "neck", ("spine2", "spine3", "left_collar", "right_collar"), +1),
    ("spine2", "neck", ("spine2", "spine3", "left_collar", "right_collar"), -1),
    ("spine1", "spine2", ("pelvis", "spine1", "spine2"), 0),
    ("spine3", "neck", ("spine3", "neck", "left_collar", "right_collar"), 0),
)


@dataclass
class CapsuleRig:
    """Capsules skinned to the body.

    anchors: (K, 2, A) body vertex indices per capsule end; offsets (K, 2, A, 3)
    rest offsets from those vertices to the end point; radius (K,).
    """

    anchors: np.ndarray
    offsets: np.ndarray
    radius: np.ndarray

    def endpoints(self, vertices: np.ndarray, vtransf: np.ndarray) -> np.ndarray:
        """(K, 2, 3) capsule end points on one posed body (V, 3)/(V, 3, 3)."""
        p = vertices[self.anchors] + np.einsum("keaij,keaj->keai", vtransf[self.anchors], self.offsets)
        return p.mean(2)


def fit_capsules(body: AnnyBody, percentile: float = 90.0, num_anchors: int = 8) -> CapsuleRig:
    """Fit the capsule rig to ``body``'s rest pose (see ``_CAPSULE_SPECS``)."""
    tv, tj, vj = body.template, body.template_joints, body.vertex_joint
    anchors, offsets, radii = [], [], []
    for a_name, b_name, parts, side in _CAPSULE_SPECS:
        part = np.isin(vj, [joint_index(p) for p in parts])
        if side:
            part &= np.sign(tv[:, 0]) == side
        pts = tv[part]
        a, b = tj[joint_index(a_name)].copy(), tj[joint_index(b_name)].copy()
        if side:  # a torso column: axis through the middle of that half
            off = np.array([np.median(pts[:, 0]) * 0.9, np.median(pts[:, 1]) - a[1], 0.0])
            a, b = a + off, b + off
        elif a_name.startswith("spine") or a_name == "pelvis":
            a[1] = b[1] = np.median(pts[:, 1])
        d = b - a
        t = np.clip((pts - a) @ d / (d @ d), 0.0, 1.0)
        dist = np.linalg.norm(pts - (a + t[:, None] * d), axis=1)
        radii.append(float(np.percentile(dist, percentile)))
        idx = np.flatnonzero(part)
        ends_a, ends_o = [], []
        for e in (a, b):
            nn = idx[np.argsort(np.linalg.norm(tv[idx] - e, axis=1))[:num_anchors]]
            ends_a.append(nn)
            ends_o.append(e - tv[nn])
        anchors.append(ends_a)
        offsets.append(ends_o)
    return CapsuleRig(np.array(anchors), np.array(offsets, dtype=np.float32), np.array(radii, dtype=np.float32))


def _quat_z_to(d: np.ndarray) -> np.ndarray:
    """(K, 4) xyzw quaternions rotating +Z onto directions d (K, 3)."""
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d)
    w = 1.0 + d[:, 2]
    q = np.concatenate([axis, w[:, None]], 1)
    flip = w < 1e-6
    q[flip] = [1.0, 0.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ----------------------------------------------------------------------------- simulation


def simulate_garment(
    body: AnnyBody,
    garment: Garment,
    posed: PosedBody,
    settings: ClothSimSettings | None = None,
    progress: Callable[[int], None] | None = None,
) -> ClothSequence:
    """Simulate ``garment`` on the body sequence ``posed`` (T frames at ``settings.fps``).

    The cloth starts at the garment's rest shape placed on frame 0 (pins at
    their skinned positions), settles ``settle_frames`` under gravity with the
    body held at frame 0, then follows the motion. Give a sequence that starts
    at (or blends from) the rest pose.

    Returns a ClothSequence with (T, Vg, 3) vertices and per-frame stats.
    """
    import warp as wp

    import newton

    s = settings or ClothSimSettings()
    if s.collider not in COLLIDERS:
        raise ValueError(f"unknown collider {s.collider!r}; expected one of {COLLIDERS}")
    if s.substeps < 1 or s.iterations < 1 or s.fps <= 0:
        raise ValueError("substeps, iterations and fps must be positive")
    T = posed.vertices.shape[0]
    if posed.vertices.shape[1] != body.num_vertices:
        raise ValueError(f"posed body has {posed.vertices.shape[1]} vertices, body has {body.num_vertices}")
    if T < 1:
        raise ValueError("posed sequence is empty")

    device = wp.get_device("cpu")
    pins = pin_positions(garment, posed)  # (T, P, 3)
    pin_idx = np.flatnonzero(garment.pinned)
    x0 = garment.rest_vertices.astype(np.float32).copy()
    x0[pin_idx] = pins[0]

    builder = newton.ModelBuilder()  # Z up, gravity -9.81
    builder.add_cloth_mesh(
        pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
        vertices=[wp.vec3(*p) for p in x0], indices=garment.faces.reshape(-1).tolist(),
        density=s.density, tri_ke=s.tri_ke, tri_ka=s.tri_ka, tri_kd=s.tri_kd,
        edge_ke=s.edge_ke, edge_kd=s.edge_kd, particle_radius=s.particle_radius,
    )  # fmt: skip
    for i in pin_idx:
        builder.particle_mass[i] = 0.0
    cfg = newton.ModelBuilder.ShapeConfig(ke=s.contact_ke, kd=s.contact_kd, mu=s.contact_mu, has_shape_collision=False)

    rig = None
    body_mesh = None
    if s.collider == "capsules":
        rig = fit_capsules(body, s.capsule_percentile)
        ends = rig.endpoints(posed.vertices[0], posed.vtransf[0])
        for k in range(len(rig.radius)):
            a, b = ends[k]
            bid = builder.add_body(
                xform=wp.transform(wp.vec3(*((a + b) / 2)), wp.quat_identity()), mass=0.0, is_kinematic=True
            )
            builder.add_shape_capsule(
                bid, radius=float(rig.radius[k]), half_height=float(np.linalg.norm(b - a) / 2), cfg=cfg
            )
    else:
        root0 = posed.joints[0, 0]
        body_mesh = newton.Mesh(posed.vertices[0] - root0, body.faces.reshape(-1), compute_inertia=False)
        bid = builder.add_body(xform=wp.transform(wp.vec3(*root0), wp.quat_identity()), mass=0.0, is_kinematic=True)
        builder.add_shape_mesh(bid, mesh=body_mesh, cfg=cfg)
    builder.color()
    model = builder.finalize(device=device)
    model.soft_contact_ke = s.contact_ke
    model.soft_contact_kd = s.contact_kd
    model.soft_contact_mu = s.contact_mu
    if body_mesh is not None:  # the mesh deforms: widen its culling box
        lo = model.shape_collision_aabb_lower.numpy() - 0.5
        hi = model.shape_collision_aabb_upper.numpy() + 0.5
        model.shape_collision_aabb_lower.assign(lo)
        model.shape_collision_aabb_upper.assign(hi)
        model.shape_collision_radius.assign(model.shape_collision_radius.numpy() + 0.5)

    solver = newton.solvers.SolverVBD(model, iterations=s.iterations, integrate_with_external_rigid_solver=True)
    pipeline = newton.CollisionPipeline(model, soft_contact_gap=s.contact_margin)
    contacts = pipeline.contacts()
    control = model.control()
    state0, state1 = model.state(), model.state()

    frame_dt = 1.0 / s.fps
    dt = frame_dt / s.substeps
    edges = mesh_edges(garment.faces)
    rest_len = np.linalg.norm(garment.rest_vertices[edges[:, 0]] - garment.rest_vertices[edges[:, 1]], axis=1)

    def set_collider(verts: np.ndarray, vtransf: np.ndarray, vel_verts: np.ndarray | None, st) -> None:
        if rig is not None:
            ends = rig.endpoints(verts, vtransf)
            mid = (ends[:, 0] + ends[:, 1]) / 2
            q = _quat_z_to(ends[:, 1] - ends[:, 0])
            st.body_q.assign(np.concatenate([mid, q], 1).astype(np.float32))
        else:
            root = verts_root[0]
            local = verts - root
            body_mesh.mesh.points.assign(local.astype(np.float32))
            vel = np.zeros_like(local) if vel_verts is None else vel_verts
            body_mesh.mesh.velocities.assign(vel.astype(np.float32))
            body_mesh.mesh.refit()
            st.body_q.assign(np.array([[*root, 0.0, 0.0, 0.0, 1.0]], dtype=np.float32))

    verts_root = [posed.joints[0, 0]]

    def substep(t_frame: int, alpha: float, vel_verts) -> None:
        nonlocal state0, state1
        t1 = min(t_frame + 1, T - 1)
        if t_frame < 0:
            v, vt, p = posed.vertices[0], posed.vtransf[0], pins[0]
            verts_root[0] = posed.joints[0, 0]
        else:
            v = (1 - alpha) * posed.vertices[t_frame] + alpha * posed.vertices[t1]
            vt = (1 - alpha) * posed.vtransf[t_frame] + alpha * posed.vtransf[t1]
            p = (1 - alpha) * pins[t_frame] + alpha * pins[t1]
            verts_root[0] = (1 - alpha) * posed.joints[t_frame, 0] + alpha * posed.joints[t1, 0]
        q = state0.particle_q.numpy()
        q[pin_idx] = p
        state0.particle_q.assign(q)
        set_collider(v, vt, vel_verts, state0)
        pipeline.collide(state0, contacts)
        solver.step(state0, state1, control, contacts, dt)
        state1.body_q.assign(state0.body_q)
        state0, state1 = state1, state0

    # settle at the first pose
    for _ in range(s.settle_frames):
        for _ in range(s.substeps):
            substep(-1, 0.0, None)

    out = np.zeros((T, len(x0), 3), dtype=np.float32)
    stats: list[ClothFrameStats] = []
    sim_time = 0.0
    resets = 0
    last_good = state0.particle_q.numpy().copy()
    for t in range(T):
        if t > 0:
            t_start = time.perf_counter()
            vel = (posed.vertices[t] - posed.vertices[t - 1]) / frame_dt if body_mesh is not None else None
            for k in range(s.substeps):
                substep(t - 1, (k + 1) / s.substeps, vel)
            sim_time += time.perf_counter() - t_start
        x = state0.particle_q.numpy().copy()
        st = frame_stats(x, posed.vertices[t], body.faces, edges, rest_len, s)
        out[t] = x
        stats.append(st)
        if _is_hard_failure(st):  # restore the last good cloth, at rest
            resets += 1
            state0.particle_q.assign(last_good)
            state0.particle_qd.zero_()
        elif st.valid:
            last_good = x
        if progress is not None:
            progress(t)
    return ClothSequence(out, garment.faces.copy(), stats, sim_time / max(T - 1, 1), resets, s)
