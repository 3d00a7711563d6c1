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

``"mesh"`` is the default: the solver's elasticity sweeps dominate the cost,
so the exact mesh costs the same as capsules (~0.8 s per frame for a 2.6K
vertex skirt at 10 substeps x 5 iterations, 2-core CPU) and keeps the cloth
out of the body (median per-frame max penetration ~2 mm, vs ~7.5 cm for the
capsules, which are inscribed in the body and so let the cloth sink in).
``benchmarks/bench_cloth.py`` measures the trade-off. Fewer substeps (5)
lose contacts (cloth ends up cm deep inside the legs); 3 iterations halve the
cost with ~4 mm median penetration.

Simulation frame (``ClothSimSettings.frame``): ``"world"`` (the first pipeline) or
``"root"``, a frame translating with the pelvis. The physics is the same (the cloth's
velocity is corrected whenever the frame's velocity changes between frames; tested),
but two things improve: the kinematic pelvis body no longer moves, so the body's
contacts are not evaluated with the previous substep's pelvis transform (in the world
frame they are: a walking body then sinks into its skirt by ~1 cm, 3 % of the skirt's
vertices inside on a walk vs 0.02 % in the root frame), and self-contact's
divide-and-truncate bound (a particle moves at most a fraction of the detection reach
per substep) only has to cover motion relative to the pelvis.

Self-contact (``self_contact``): newton VBD's vertex-triangle and edge-edge cloth
self-contact, detected once per substep, 1.6 cm reach. It removes 85-98 % of the
crossing triangle pairs, at 2.4-3.2x the simulation time, and its speed cap still
tears the cloth on fast spins (``benchmarks/experiments/bench_cloth_settings.py``).

Sequences that start on the same pose settle the same way: ``ClothSequence.settled``
can be passed back (``settled=``) to skip the settle (bit-identical results).

Per output frame (fps 25) the simulator records penetration of the garment
into the *full* body mesh (signed distance via open3d ray casting), the
maximum edge stretch and a validity flag. Frames with NaN, stretch above
``max_stretch``, vertices farther than ``max_distance`` from the body, or
penetration above thresholds are marked invalid with a reason. After a
*hard* failure (NaN, explosion) the state is garbage: the simulator restores
the last valid cloth state (zero velocity) and continues, so later frames may
recover; each frame is still judged on its own. ``reset_count`` in the
result says how often this happened.

Why this module is long: it is the one simulation loop every dataset is made with, and the
settings it reads, each documented with the measurement that chose its value; the optional
forces and solver changes live in their own modules (``aero``, ``bend_friction``,
``tension_field``, ``vbd_chebyshev``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..body.anny_body import AnnyBody, PosedBody
from .capsules import fit_capsules, quat_z_to
from .garments import Garment, anchor_vertices, pin_positions
from .sdf import signed_distance, signed_distance_fn  # noqa: F401  (re-exported)

COLLIDERS: tuple[str, ...] = ("capsules", "mesh")


@dataclass
class ClothSimSettings:
    """Cloth simulation settings (SI units: metres, seconds, kg).

    fps: output frame rate; the body sequence is given at this rate.
    substeps, iterations: VBD substeps per frame and solver iterations per substep.
    collider: ``"capsules"`` or ``"mesh"`` (see module docstring).
    frame: ``"world"``, or ``"root"``: simulate in a frame translating with the
        pelvis (the same physics: the cloth's velocity is corrected whenever the
        frame's changes). Self-contact needs it: its divide-and-truncate bound
        lets two touching layers move at most about half their gap per substep,
        so in the world frame the layers of a walking subject's skirt lag behind.
    density: cloth area density [kg/m^2]. tri_ke/tri_ka/tri_kd: membrane
    stretch/area stiffness and damping; edge_ke/edge_kd: bending.
    particle_radius, contact_margin: collision thickness and detection gap [m].
    contact_ke/kd/mu: cloth-body contact stiffness, damping, friction.
    air_drag_normal, air_drag_tangential: drag coefficients (dimensionless) of the cloth's
        motion through still air along its normal and along its plane (``synth.aero``);
        0 = no air (data v1 / v2). ``synth.fabric`` gives physical values per fabric.
    air_drag_kc_gain, air_drag_kc_width, air_drag_kc_time: the extra pressure drag of small
        oscillations (``synth.aero``: the drag coefficient grows as KC^(-1/3) below KC ~ 64 /
        gain^3; the gain [1], a flapping panel's width [m], the excursion's averaging time [s]);
        gain 0 = the steady drag alone (data v3).
    color_bending: colour the VBD graph with the bending neighbours too (newton's
        ``ModelBuilder.color(include_bending=True)``); without it (data v1 / v2) vertices that share
        a bending element are updated in the same parallel pass, which feeds energy into hanging
        cloth (benchmarks/experiments/vbd_energy.py --tube).
    bend_friction: Coulomb friction moment per unit length in bending, HB [N] (``synth.bend_friction``:
        half the hysteresis width of Kawabata's bending test); 0 = none (data v1 - v3).
    bend_friction_stick_angle: the hinge angle [rad] over which that friction builds up (Dahl's
        stick region; the friction element's stiffness is HB / this).
    tension_field: the membrane carries no compression (``synth.tension_field``: each triangle's
        rest shape relaxed along its compressed directions before each step); False = newton's
        membrane, which resists compression like stretch (data v1 - v3).
    tension_field_compression: with ``tension_field``, the share of the membrane's stiffness a
        compressed direction keeps (0: none; a softened post-buckling response between 0 and 1).
    tension_field_min_stretch: with ``tension_field``, the length ratio below which a compressed
        direction resists again (so that no triangle collapses to a line).
    chebyshev_rho: Chebyshev acceleration of the VBD sweeps with this spectral radius estimate
        (``synth.vbd_chebyshev``; 0 = newton's plain sweeps, data v1 - v3). Not with self-contact.
    self_contact: newton VBD cloth self-contact (vertex-triangle and edge-edge).
    self_contact_margin: distance [m] at which two cloth layers start to repel.
    self_contact_gap: extra detection reach [m]. VBD's divide-and-truncate bound
        lets a particle move at most ~0.43 x (margin + gap) per substep, and two
        touching layers about half their gap: this caps the cloth's speed relative
        to the simulation frame (1.6 cm at 10 substeps of 4 ms: 1.7 m/s), so use
        ``frame="root"`` (a walking body's skirt layers otherwise lag and tangle).
        Measured on a walk (benchmarks/experiments/bench_cloth_settings.py): a 1 cm reach lets
        legs through the cloth (8 of 110 frames > 3 cm), 1.6 cm none; cost 2.1x /
        2.7x / 3.6x the simulation without self-contact at 1.0 / 1.6 / 2.4 cm.
    self_contact_fallback: after the first hard failure (explosion) of a sequence
        with self-contact, restore the last good state and finish without it.
    self_contact_detection: "pre_init" (detect once per substep) or
        "pre_post_init" (twice, newton's default; ~10 % slower, same result here).
    settle_frames: frames simulated at the first pose before recording.
    replay_graphs: record each substep's kernel launches (collision detection and the
        solver step) once as a warp graph and replay it (warp >= 1.10 records CPU graphs):
        the same bits, 1.27x less simulation CPU time on a skirt sequence (Python launch overhead gone;
        benchmarks/experiments/bench_synth_v2.py). False launches every kernel from Python.
    capsule_percentile: percentile of the part vertices' distance to a capsule
        axis used as its radius (100 = enclose every vertex).
    max_stretch, max_distance, max_penetration, max_penetration_fraction:
        validity thresholds (ratio, m, m, fraction).
    """

    fps: float = 25.0
    substeps: int = 10
    iterations: int = 5
    collider: str = "mesh"
    frame: str = "world"
    density: float = 0.15
    tri_ke: float = 1.0e4
    tri_ka: float = 1.0e4
    tri_kd: float = 1.0e-5
    edge_ke: float = 1.0e-3
    edge_kd: float = 0.0
    particle_radius: float = 0.004
    contact_margin: float = 0.04
    contact_ke: float = 3.0e4
    contact_kd: float = 1.0e-2
    contact_mu: float = 0.05
    air_drag_normal: float = 0.0
    air_drag_tangential: float = 0.0
    air_drag_kc_gain: float = 0.0
    air_drag_kc_width: float = 0.3
    air_drag_kc_time: float = 1.0
    color_bending: bool = False
    chebyshev_rho: float = 0.0
    bend_friction: float = 0.0
    bend_friction_stick_angle: float = 0.02
    tension_field: bool = False
    tension_field_compression: float = 0.0
    tension_field_min_stretch: float = 0.7
    self_contact: bool = False
    self_contact_margin: float = 0.004
    self_contact_gap: float = 0.012
    self_contact_detection: str = "pre_init"
    self_contact_fallback: bool = True
    settle_frames: int = 10
    replay_graphs: bool = True
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
    settling, kernel compilation and the stats); cpu_seconds_per_frame: the
    same in process CPU time (robust to other load on the machine);
    reset_count: how often the state was restored after a hard failure;
    settled: the cloth state after settling (reusable, see ``simulate_garment``);
    final: the cloth state at the last frame (a later call continues from it: ``settled=final``
    with a sequence whose frame 0 is this one's last);
    self_contact_off_from: the frame from which self-contact was switched off
    after a hard failure (``ClothSimSettings.self_contact_fallback``), or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    stats: list[ClothFrameStats]
    seconds_per_frame: float
    cpu_seconds_per_frame: float = 0.0
    reset_count: int = 0
    settings: ClothSimSettings = field(default_factory=ClothSimSettings)
    settled: SettledCloth | None = None
    self_contact_off_from: int | None = None
    final: SettledCloth | None = None

    @property
    def valid(self) -> np.ndarray:
        """(T,) bool per-frame validity."""
        return np.array([s.valid for s in self.stats], dtype=bool)


# ----------------------------------------------------------------------------- metrics


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
    penetration: bool = True,
) -> ClothFrameStats:
    """Judge one frame: garment (Vg, 3) against the posed full body (V, 3). ``penetration=False``
    checks only for hard failures (NaN, explosion; penetration is then reported as NaN)."""
    if not np.isfinite(vertices).all():
        return ClothFrameStats(np.inf, np.inf, 1.0, np.inf, False, "nan")
    stretch = edge_stretch(vertices, edges, rest_length)
    pen = (penetration_stats(vertices, body_vertices, body_faces) if penetration
           else PenetrationStats(np.nan, np.nan, np.nan))  # fmt: skip
    reasons = []
    if stretch > settings.max_stretch:
        reasons.append(f"explosion: stretch {stretch:.2f}")
    far = np.linalg.norm(vertices - body_vertices.mean(0), axis=1).max()
    lo, hi = body_vertices.min(0) - settings.max_distance, body_vertices.max(0) + settings.max_distance
    if (vertices < lo).any() or (vertices > hi).any():
        reasons.append(f"explosion: vertex {far:.2f} m from the body centre")
    if penetration and pen.max > settings.max_penetration:
        reasons.append(f"penetration {pen.max * 100:.1f} cm")
    if penetration and pen.fraction > settings.max_penetration_fraction:
        reasons.append(f"{pen.fraction * 100:.0f}% vertices inside")
    return ClothFrameStats(pen.max, pen.mean, pen.fraction, stretch, not reasons, "; ".join(reasons))


def _is_hard_failure(s: ClothFrameStats) -> bool:
    return s.reason.startswith("nan") or "explosion" in s.reason


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2) of triangles (F, 3)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


# ----------------------------------------------------------------------------- simulation


#: rest distance over which a sleeve's placement blends from the torso's motion to its arm's
SLEEVE_BLEND_M = 0.12


def skin_garment(
    garment: Garment, body: AnnyBody, vertices: np.ndarray, vtransf: np.ndarray, k: int = 16
) -> np.ndarray:
    """Carry the whole garment onto one posed body by smooth skinning.

    Each garment vertex x follows its ``k`` nearest template vertices u of its
    skin region (torso and legs; for sleeves, a blend from the torso's at the arm hole to
    their arm's ``SLEEVE_BLEND_M`` further out: ``Garment.skin_region``)
    like a pin does (``v_u + vtransf_u @ (x - u)``), blended with inverse square
    distance weights so neighbouring garment vertices move alike (a hem between
    the legs does not tear). Used to place the cloth on the first frame, which
    differs from the bind pose ``AnnyBody.template`` (anny's zero pose tilts the
    upper spine and shoulders). Returns (Vg, 3) float32.
    """
    from scipy.spatial import cKDTree

    from .garments import REGION_LEFT_ARM, REGION_RIGHT_ARM, arm_vertices

    region = garment.skin_region
    rest = garment.rest_vertices

    def skin(sel: np.ndarray, allowed: np.ndarray) -> np.ndarray:
        x = rest[sel]
        dist, nn = cKDTree(body.template[allowed]).query(x, k=k)  # (n, k)
        nn = allowed[nn]
        w = 1.0 / (dist + 1e-3) ** 2
        w /= w.sum(1, keepdims=True)
        off = x[:, None] - body.template[nn]  # (n, k, 3)
        moved = vertices[nn] + np.einsum("nkij,nkj->nki", vtransf[nn], off)  # (n, k, 3)
        return (w[..., None] * moved).sum(1)

    out = np.empty(rest.shape, dtype=np.float32)
    torso = anchor_vertices(body)
    if region is None:
        out[:] = skin(np.ones(len(out), dtype=bool), torso)
        return out
    body_part = region == 0
    out[body_part] = skin(body_part, torso)
    # a sleeve blends from the torso's motion at the arm hole to its arm's over SLEEVE_BLEND_M
    # of rest distance from the body part (no seam opens at the arm hole, the cuff follows the arm)
    for side, code in (("left", REGION_LEFT_ARM), ("right", REGION_RIGHT_ARM)):
        sel = region == code
        if not sel.any():
            continue
        d, _ = cKDTree(rest[body_part]).query(rest[sel]) if body_part.any() else (np.full(sel.sum(), np.inf), None)
        t = np.clip(d / SLEEVE_BLEND_M, 0.0, 1.0)[:, None]
        out[sel] = (1.0 - t) * skin(sel, torso) + t * skin(sel, arm_vertices(body, side))
    return out


def _record_substep(wp, device, kernels: Callable[[], None]):
    """Record ``kernels`` (launches only, no host work) as a warp graph for replay, or None
    where this warp cannot record CPU graphs (the caller then launches them one by one).
    Recording runs nothing: the caller launches the graph, also the first time."""
    try:
        wp.capture_begin(device)
    except Exception:  # noqa: BLE001  (older warp: graphs are CUDA only)
        return None
    try:
        kernels()
    finally:
        graph = wp.capture_end(device)
    return graph


@dataclass
class SettledCloth:
    """Cloth state at a frame (after settling on a sequence's first frame, or at its last frame):
    particle positions and velocities (Vg, 3) float32 in the simulation frame, that frame's body
    vertices (V, 3) in the world (a state is only reused on the same body frame), the
    simulation frame's world velocity (3,) there (zeros: at rest, or the world frame), the
    cloth's rest shape (Vg, 3): the garment skinned to the first frame of the simulation that
    made the state (its triangles' rest shapes, bending rest angles and masses come from it),
    and the low-KC air drag's excursions (Vg, 4) (``aero.AirDrag.excursion_state``; None: off)."""

    positions: np.ndarray
    velocities: np.ndarray
    first_frame: np.ndarray
    frame_velocity: np.ndarray | None = None
    rest_positions: np.ndarray | None = None
    drag_excursion: np.ndarray | None = None

    def turned(self, rotation: np.ndarray, first_frame: np.ndarray) -> SettledCloth:
        """The same state with the body turned by ``rotation`` (3, 3) about the vertical (and moved):
        positions, velocities and the frame's velocity rotated, on the body frame ``first_frame``.
        Cloth physics here is invariant to a turn about gravity, so the turned state continues as
        the original would have on the turned body (to rounding). Positions are relative to the
        pelvis in the ``root`` frame; a turned ``world``-frame state needs the pelvis at the origin."""
        r = np.asarray(rotation, dtype=np.float64)
        fv = np.zeros(3) if self.frame_velocity is None else self.frame_velocity
        rest = None if self.rest_positions is None else (self.rest_positions @ r.T).astype(np.float32)
        exc = None
        if self.drag_excursion is not None:
            exc = np.concatenate([self.drag_excursion[:, :3] @ r.T, self.drag_excursion[:, 3:]], 1).astype(np.float32)
        return SettledCloth((self.positions @ r.T).astype(np.float32), (self.velocities @ r.T).astype(np.float32),
                            first_frame, (r @ fv).astype(np.float64), rest, exc)  # fmt: skip


def _vbd_solver(model, s: ClothSimSettings, extra: dict):  # noqa: ANN001, ANN202 (newton's types)
    """newton's VBD solver for ``s`` (``extra``: self-contact keyword arguments), Chebyshev-accelerated
    when ``s.chebyshev_rho`` > 0 and the cloth has no self-contact."""
    import newton

    if s.chebyshev_rho > 0.0 and not extra.get("particle_enable_self_contact"):
        from .vbd_chebyshev import SolverVBDChebyshev

        return SolverVBDChebyshev(model, rho=s.chebyshev_rho, iterations=s.iterations,
                                  integrate_with_external_rigid_solver=True, **extra)  # fmt: skip
    return newton.solvers.SolverVBD(model, iterations=s.iterations, integrate_with_external_rigid_solver=True, **extra)


def simulate_garment(
    body: AnnyBody,
    garment: Garment,
    posed: PosedBody,
    settings: ClothSimSettings | None = None,
    progress: Callable[[int], None] | None = None,
    settled: SettledCloth | None = None,
    judge_from: int = 0,
) -> ClothSequence:
    """Simulate ``garment`` on the body sequence ``posed`` (T frames at ``settings.fps``).

    The cloth starts at the garment's rest shape placed on frame 0 (pins at
    their skinned positions), settles ``settle_frames`` under gravity with the
    body held at frame 0, then follows the motion. Give a sequence that starts
    at (or blends from) the rest pose.

    settled: the state a previous call with the same garment, settings and
        frame 0 reached after settling (``ClothSequence.settled``): the settle
        is skipped and the result is the same (the simulation is deterministic);
        or the state a previous call ended in (``ClothSequence.final``, whose
        last frame is this call's frame 0): the simulation continues it.
    judge_from: frames before it (lead-in frames the caller does not keep) are checked for
        hard failures only (NaN, explosion: the state is then restored), not for penetration,
        whose signed distances cost ~15 ms a frame; their stats report penetration as NaN.

    Returns a ClothSequence with (T, Vg, 3) vertices and per-frame stats.
    """
    s = settings or ClothSimSettings()
    if s.collider not in COLLIDERS:
        raise ValueError(f"unknown collider {s.collider!r}; expected one of {COLLIDERS}")
    if s.frame not in ("world", "root"):
        raise ValueError(f"frame must be 'world' or 'root', got {s.frame!r}")
    if s.bend_friction < 0.0 or not s.bend_friction_stick_angle > 0.0:
        raise ValueError(f"bend_friction must be >= 0 and bend_friction_stick_angle > 0, got {s.bend_friction} "
                         f"and {s.bend_friction_stick_angle}")  # fmt: skip
    if not 0.0 <= s.chebyshev_rho < 1.0:
        raise ValueError(f"chebyshev_rho must be in [0, 1), got {s.chebyshev_rho}")
    if s.substeps < 1 or s.iterations < 1 or s.fps <= 0:
        raise ValueError("substeps, iterations and fps must be positive")
    T = posed.vertices.shape[0]
    if posed.vertices.shape[1] != body.num_vertices:
        raise ValueError(f"posed body has {posed.vertices.shape[1]} vertices, body has {body.num_vertices}")
    if T < 1:
        raise ValueError("posed sequence is empty")

    from ..body.anny_body import quiet_warp

    quiet_warp()
    import warp as wp  # lazy: warp/newton are only needed to simulate

    import newton

    device = wp.get_device("cpu")
    world = posed
    # the simulation frame: the world, or a frame translating with the pelvis ("root")
    origin = posed.joints[:, 0].astype(np.float64) if s.frame == "root" else np.zeros((T, 3))
    posed = PosedBody((world.vertices - origin[:, None]).astype(np.float32),
                      (world.joints - origin[:, None]).astype(np.float32), world.vtransf)  # fmt: skip
    # the frame's velocity, constant within a frame (body data is interpolated linearly)
    frame_velocity = np.diff(origin, axis=0, prepend=origin[:1]) * s.fps  # (T, 3), 0 for frame 0
    pins = pin_positions(garment, posed)  # (T, P, 3)
    pin_idx = np.flatnonzero(garment.pinned)
    x0 = skin_garment(garment, body, posed.vertices[0], posed.vtransf[0])
    x0[pin_idx] = pins[0]
    # the cloth's rest shape: the garment skinned to frame 0 (a continued state brings its own)
    rest = x0 if settled is None or settled.rest_positions is None else settled.rest_positions
    if rest.shape != x0.shape:
        raise ValueError("settled: the state was settled for another garment or first frame")

    builder = newton.ModelBuilder()  # Z up, gravity -9.81
    builder.add_cloth_mesh(
        pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
        vertices=[wp.vec3(*p) for p in rest], indices=garment.faces.reshape(-1).tolist(),
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
    builder.color(include_bending=s.color_bending)
    model = builder.finalize(device=device)
    drag = None
    if s.air_drag_normal > 0.0 or s.air_drag_tangential > 0.0:
        from .aero import AirDrag

        drag = AirDrag(garment.faces, model.particle_mass.numpy(), s.air_drag_normal, s.air_drag_tangential,
                       1.0 / (s.fps * s.substeps), device, kc_gain=s.air_drag_kc_gain,
                       kc_width=s.air_drag_kc_width, kc_time=s.air_drag_kc_time)  # fmt: skip
    friction = None
    if s.bend_friction > 0.0:
        from .bend_friction import BendFriction

        friction = BendFriction(model, s.bend_friction, s.bend_friction_stick_angle, device)
    tension = None
    if s.tension_field:
        from .tension_field import TensionField

        tension = TensionField(model, device, min_stretch=s.tension_field_min_stretch,
                               compression=s.tension_field_compression)  # fmt: skip
    model.soft_contact_ke = s.contact_ke
    model.soft_contact_kd = s.contact_kd
    model.soft_contact_mu = s.contact_mu
    if body_mesh is not None:  # the mesh deforms: widen its culling box
        lo = model.shape_collision_aabb_lower.numpy() - 0.5
        hi = model.shape_collision_aabb_upper.numpy() + 0.5
        model.shape_collision_aabb_lower.assign(lo)
        model.shape_collision_aabb_upper.assign(hi)
        model.shape_collision_radius.assign(model.shape_collision_radius.numpy() + 0.5)

    extra = {}
    if s.self_contact:
        freq = newton.solvers.SolverBase.CollisionFrequencyType
        when = {"pre_init": freq.PRE_INIT, "pre_post_init": freq.PRE_POST_INIT}[s.self_contact_detection]
        extra = {
            "particle_enable_self_contact": True,
            "particle_self_contact_margin": s.self_contact_margin,
            "particle_self_contact_gap": s.self_contact_gap,
            "collision_frequency_type": {newton.solvers.SolverBase.CollisionSlot.SOFT_SELF_CONTACT: when},
        }
    solvers = [_vbd_solver(model, s, extra)]
    self_contact_off_from = None
    pipeline = newton.CollisionPipeline(model, soft_contact_gap=s.contact_margin)
    contacts = pipeline.contacts()
    control = model.control()
    state0, state1 = model.state(), model.state()

    frame_dt = 1.0 / s.fps
    dt = frame_dt / s.substeps
    edges = mesh_edges(garment.faces)
    # stretch is judged on cloth edges only: an edge between two pins has the
    # length the body gives it (e.g. the shirt's neckline when the arms rise)
    edges = edges[~(garment.pinned[edges[:, 0]] & garment.pinned[edges[:, 1]])]
    rest_len = np.linalg.norm(garment.rest_vertices[edges[:, 0]] - garment.rest_vertices[edges[:, 1]], axis=1)

    def lerp(x: np.ndarray, t: int, alpha: float) -> np.ndarray:
        """Linear interpolation of per-frame data between frames t and t+1."""
        return x[t] if alpha == 0.0 or t + 1 >= T else (1 - alpha) * x[t] + alpha * x[t + 1]

    graphs: dict = {}  # state parity -> recorded warp graph (None: cannot record); cleared with a new solver

    def collide_and_step(a, b) -> None:
        """The substep's kernels: contacts of state a, then one solver step a -> b."""
        if drag is not None:  # air drag first: an implicit velocity update (synth.aero)
            drag.apply(a.particle_q, a.particle_qd)
        if tension is not None:  # the membrane's rest shapes give way where the step starts compressed
            tension.apply(a.particle_q)
        pipeline.collide(a, contacts)
        solvers[0].step(a, b, control, contacts, dt)
        if friction is not None:  # the bending friction elements slip to the step's result
            friction.apply(b.particle_q)

    def substep(t: int, alpha: float, body_velocity: np.ndarray | None) -> None:
        """One VBD substep with the body at frame t + alpha (velocity (V, 3) or None)."""
        nonlocal state0, state1
        q = state0.particle_q.numpy()
        q[pin_idx] = lerp(pins, t, alpha)
        state0.particle_q.assign(q)
        verts = lerp(posed.vertices, t, alpha)
        if rig is not None:
            ends = rig.endpoints(verts, lerp(posed.vtransf, t, alpha))  # (K, 2, 3)
            mid, quat = (ends[:, 0] + ends[:, 1]) / 2, quat_z_to(ends[:, 1] - ends[:, 0])
            state0.body_q.assign(np.concatenate([mid, quat], 1).astype(np.float32))
        else:  # mesh points are stored relative to the pelvis body
            root = lerp(posed.joints[:, 0], t, alpha)
            body_mesh.mesh.points.assign((verts - root).astype(np.float32))
            vel = np.zeros_like(verts) if body_velocity is None else body_velocity
            body_mesh.mesh.velocities.assign(vel.astype(np.float32))
            body_mesh.mesh.refit()
            state0.body_q.assign(np.array([[*root, 0.0, 0.0, 0.0, 1.0]], dtype=np.float32))
        key = id(state0)  # a graph per state parity (state0 and state1 live as long as this call)
        if s.replay_graphs and key not in graphs:
            graphs[key] = _record_substep(wp, device, lambda: collide_and_step(state0, state1))
        if graphs.get(key) is not None:
            wp.capture_launch(graphs[key])
        else:
            collide_and_step(state0, state1)
        state1.body_q.assign(state0.body_q)
        state0, state1 = state1, state0

    # settle at the first pose (or restore a settled state of the same first frame)
    if settled is not None:
        if settled.positions.shape != x0.shape or not np.array_equal(settled.first_frame, world.vertices[0]):
            raise ValueError("settled: the state was settled for another garment or first frame")
        state0.particle_q.assign(settled.positions)
        state0.particle_qd.assign(settled.velocities)
        if settled.frame_velocity is not None and np.any(settled.frame_velocity):  # continued mid-motion
            frame_velocity[0] = settled.frame_velocity
            if drag is not None:
                drag.set_air_velocity(-frame_velocity[0])
        if drag is not None and settled.drag_excursion is not None:
            drag.set_excursion_state(settled.drag_excursion)
    else:
        for _ in range(s.settle_frames):
            for _ in range(s.substeps):
                substep(0, 0.0, None)
    def snapshot(t: int) -> SettledCloth:
        """The cloth's state now, on body frame t (the low-KC drag's excursions with it, if on)."""
        kc = drag.excursion_state() if drag is not None and s.air_drag_kc_gain > 0.0 else None
        return SettledCloth(state0.particle_q.numpy().copy(), state0.particle_qd.numpy().copy(),
                            world.vertices[t].copy(), frame_velocity[t].copy(), np.array(rest, np.float32), kc)  # fmt: skip

    settled_out = snapshot(0)

    out = np.zeros((T, len(x0), 3), dtype=np.float32)
    stats: list[ClothFrameStats] = []
    sim_time = cpu_time = 0.0
    resets = 0
    last_good = state0.particle_q.numpy().copy()
    for t in range(T):
        if t > 0:
            t_start, c_start = time.perf_counter(), time.process_time()
            dv = frame_velocity[t] - frame_velocity[t - 1]
            if dv.any():  # the frame changes velocity: the cloth keeps its world velocity
                state0.particle_qd.assign(state0.particle_qd.numpy() - dv.astype(np.float32))
                if drag is not None:  # the still air moves at minus the frame's velocity
                    drag.set_air_velocity(-frame_velocity[t])
            vel = (posed.vertices[t] - posed.vertices[t - 1]) / frame_dt if body_mesh is not None else None
            for k in range(s.substeps):
                substep(t - 1, (k + 1) / s.substeps, vel)
            sim_time += time.perf_counter() - t_start
            cpu_time += time.process_time() - c_start
        x = state0.particle_q.numpy().copy()  # in the simulation frame
        st = frame_stats(x, posed.vertices[t], body.faces, edges, rest_len, s, penetration=t >= judge_from)
        out[t] = x + origin[t]
        stats.append(st)
        if _is_hard_failure(st):  # restore the last good cloth, at rest
            resets += 1
            state0.particle_q.assign(last_good)
            state0.particle_qd.zero_()
            if s.self_contact and s.self_contact_fallback and self_contact_off_from is None:
                # self-contact's speed bound let the cloth tear: go on without it
                self_contact_off_from = t
                solvers[0] = _vbd_solver(model, s, {})
                graphs.clear()  # they replay the old solver's kernels
        elif st.valid:
            last_good = x
        if progress is not None:
            progress(t)
    n = max(T - 1, 1)
    final = snapshot(T - 1)
    return ClothSequence(out, garment.faces.copy(), stats, sim_time / n, cpu_time / n, resets, s, settled_out,
                         self_contact_off_from, final)  # fmt: skip
