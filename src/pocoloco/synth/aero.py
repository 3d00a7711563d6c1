"""Air drag on a cloth mesh: the force that lets a skirt come to rest.

A thin sheet moving through still air feels a pressure drag along its normal and a
(much weaker) skin-friction drag along its plane. Per triangle of area ``A`` and unit
normal ``n``, with ``u = v_mid - v_air`` its velocity relative to the air::

    f = -1/2 rho_air A ( C_n |u.n| (u.n) n  +  C_t |u_t| u_t ),    u_t = u - (u.n) n

the quadratic drag law of a flat plate (the form newton's semi-implicit solver and
Baraff & Witkin's cloth use, with Bhat et al.'s (SCA 2003) split into a normal and a
tangential part; no lift: a garment is no wing). Each triangle hands a third of its
force to each of its vertices.

newton's VBD solver has no aerodynamic force, so it is applied here as an **implicit
velocity update** before each substep: the drag coefficients are frozen at the current
velocity (``f = -C (v - v_air)`` with C a symmetric 3x3 per vertex, positive
semi-definite) and the update solves ``(m I + dt C) v' = m v + dt C v_air``, which is
unconditionally stable and never reverses a velocity (a linearisation of quadratic
drag: exact in the limit of small dt). ``drag_velocity_update_reference`` is the
plain NumPy reference the warp kernels are tested against.

**Small oscillations** (optional, ``kc_gain`` > 0): a plate oscillating at an amplitude A
small against its width D sheds vortices from its edges every half cycle and meets far
more drag than in a steady stream: its drag coefficient grows as KC^(-1/3) with the
Keulegan-Carpenter number KC = 2 pi A / D (Graham, *J. Fluid Mech.* 97, 1980, the theory of
sharp-edged bodies at low KC, against Keulegan & Carpenter's 1958 plate measurements; the
reason offshore heave plates damp). The coefficient, C_d ~ 8 KC^(-1/3) against a steady ~2 (a
gain of 4 at KC = 1), is the order of that plate data as recalled, not re-checked here: a
gain 1.26x larger changes the settle benchmark by less than its noise
(docs/lab/synthetic-data.md). A hanging hem that flaps by a centimetre is such a plate. Here
each vertex keeps its *excursion* relative to the air, e (a leaky integral of its velocity
relative to the air over ``kc_time``: the displacement about its recent mean position;
steady motion at speed U gives U * kc_time, a large KC), and the running mean of |e|^2; a
triangle's amplitude is A = sqrt(2 <|e|^2>) over its vertices, and its normal coefficient
is ``c_normal * clip(kc_gain * KC^(-1/3), 1, kc_gain * KC_MIN^(-1/3))``: the steady value
for large excursions, more for small ones, held below KC_MIN (0.1, where viscous terms take
over and the law has no data). ``excursion_update_reference`` and the ``mean_square`` argument
of ``drag_velocity_update_reference`` are the NumPy references.
"""

from __future__ import annotations

import numpy as np
import warp as wp

#: density of air at 20 C and sea level [kg/m^3]
AIR_DENSITY = 1.204

#: below this Keulegan-Carpenter number the low-KC drag factor is held constant
KC_MIN = 0.1


def kc_drag_factor(amplitude: np.ndarray, width: float, gain: float) -> np.ndarray:
    """The low-KC multiplier of the normal drag: clip(gain * KC^(-1/3), 1, gain * KC_MIN^(-1/3)),
    KC = 2 pi amplitude / width (amplitude [m], any shape; width [m]); gain 0 gives 1."""
    if gain <= 0.0:
        return np.ones_like(np.asarray(amplitude, np.float64))
    kc = np.maximum(2.0 * np.pi * np.asarray(amplitude, np.float64) / width, KC_MIN)
    return np.maximum(gain * kc ** (-1.0 / 3.0), 1.0)


def excursion_update_reference(
    excursion: np.ndarray, mean_square: np.ndarray, v: np.ndarray, mass: np.ndarray, v_air: np.ndarray,
    dt: float, time: float,
) -> tuple[np.ndarray, np.ndarray]:
    """One step of each vertex's excursion relative to the air, plain NumPy (the kernels' reference).

    excursion: (V, 3) [m]; mean_square: (V,) running mean of |excursion|^2 [m^2]; v: (V, 3)
    velocities [m/s]; mass: (V,) (0 = kinematic: its excursion stays 0); v_air: (3,); dt: the
    step [s]; time: the averaging time [s]. ``e <- (e + dt (v - v_air)) exp(-dt / time)``,
    ``<|e|^2> <- <|e|^2> + (1 - exp(-dt / time)) (|e|^2 - <|e|^2>)``. Returns both, float64.
    """
    decay = np.exp(-dt / time)
    free = (np.asarray(mass) > 0.0)[:, None]
    e = np.where(free, (np.asarray(excursion, np.float64) + dt * (np.asarray(v, np.float64) - v_air)) * decay, 0.0)
    ms = np.asarray(mean_square, np.float64)
    ms = ms + (1.0 - decay) * ((e**2).sum(1) - ms)
    return e, ms


def drag_velocity_update_reference(
    x: np.ndarray, v: np.ndarray, faces: np.ndarray, mass: np.ndarray, v_air: np.ndarray,
    dt: float, c_normal: float, c_tangential: float, rho: float = AIR_DENSITY,
    mean_square: np.ndarray | None = None, kc_gain: float = 0.0, kc_width: float = 0.3,
) -> np.ndarray:
    """One implicit drag update, plain NumPy (the reference for the warp kernels).

    x, v: (V, 3) positions [m] and velocities [m/s]; faces: (F, 3); mass: (V,) [kg]
    (0 = kinematic: left alone); v_air: (3,) air velocity in the simulation frame;
    mean_square: (V,) the vertices' running mean |excursion|^2 (``excursion_update_reference``),
    used with ``kc_gain`` > 0 for the low-KC factor of each triangle (width ``kc_width`` [m]).
    Returns the new velocities (V, 3) float64.
    """
    x = np.asarray(x, np.float64)
    v = np.asarray(v, np.float64)
    V = len(x)
    C = np.zeros((V, 3, 3))
    for f in faces:
        a, b, c = x[f]
        cr = np.cross(b - a, c - a)
        area2 = np.linalg.norm(cr)
        if area2 <= 0.0:
            continue
        n = cr / area2
        area = 0.5 * area2
        u = v[f].mean(0) - v_air
        un = float(u @ n)
        ut = u - un * n
        nn = np.outer(n, n)
        k = 0.5 * rho * area / 3.0
        cn = c_normal
        if kc_gain > 0.0:
            cn = c_normal * float(kc_drag_factor(np.sqrt(2.0 * np.mean(mean_square[f])), kc_width, kc_gain))
        Cf = k * (cn * abs(un) * nn + c_tangential * np.linalg.norm(ut) * (np.eye(3) - nn))
        for i in f:
            C[i] += Cf
    out = v.copy()
    for i in range(V):
        if mass[i] <= 0.0:
            continue
        A = mass[i] * np.eye(3) + dt * C[i]
        out[i] = np.linalg.solve(A, mass[i] * v[i] + dt * C[i] @ v_air)
    return out


class AirDrag:
    """Warp kernels applying the drag update to a newton state, recordable in a graph.

    faces: (F, 3) cloth triangles; mass: (V,) particle masses (0 = pinned / kinematic);
    c_normal, c_tangential: drag coefficients (dimensionless); device: a warp device;
    kc_gain, kc_width [m], kc_time [s]: the low-KC drag of small oscillations (module docstring;
    gain 0 = off). ``set_air_velocity`` changes the air's velocity in the simulation frame (a
    frame translating with the pelvis sees the still air move at minus its own velocity) without
    invalidating a recorded graph (the array is written in place). ``excursion_state`` /
    ``set_excursion_state`` read and restore the per-vertex excursions, (V, 4): e and <|e|^2>.
    """

    def __init__(self, faces: np.ndarray, mass: np.ndarray, c_normal: float, c_tangential: float, dt: float,
                 device, rho: float = AIR_DENSITY, kc_gain: float = 0.0, kc_width: float = 0.3,
                 kc_time: float = 1.0):  # fmt: skip
        if kc_gain < 0.0 or (kc_gain > 0.0 and (kc_width <= 0.0 or kc_time <= 0.0)):
            raise ValueError(f"low-KC drag: gain {kc_gain} must be >= 0, width {kc_width} m and time {kc_time} s > 0")
        self.device = device
        self.faces = wp.array(np.ascontiguousarray(faces, dtype=np.int32), dtype=wp.int32, ndim=2, device=device)
        self.mass = wp.array(np.asarray(mass, np.float32), dtype=wp.float32, device=device)
        self.coeff = wp.zeros(len(mass), dtype=wp.mat33, device=device)
        self.v_air = wp.zeros(1, dtype=wp.vec3, device=device)
        self.k_normal = float(0.5 * rho * c_normal / 3.0)
        self.k_tangential = float(0.5 * rho * c_tangential / 3.0)
        self.dt = float(dt)
        self.num_faces = len(faces)
        self.num_particles = len(mass)
        self.kc_gain = float(kc_gain)
        self.kc_width = float(kc_width)
        self.kc_decay = float(np.exp(-dt / kc_time)) if kc_gain > 0.0 else 1.0
        self.excursion = wp.zeros(len(mass), dtype=wp.vec3, device=device)
        self.mean_square = wp.zeros(len(mass), dtype=wp.float32, device=device)
        wp.load_module(__name__, device=device)  # compiled now, not while a graph records its launches

    def set_air_velocity(self, v_air: np.ndarray) -> None:
        self.v_air.assign(np.asarray(v_air, np.float32).reshape(1, 3))

    def excursion_state(self) -> np.ndarray:
        """(V, 4) float32: each vertex's excursion e (3) and running mean |e|^2 (all 0 when off)."""
        return np.concatenate([self.excursion.numpy(), self.mean_square.numpy()[:, None]], 1)

    def set_excursion_state(self, state: np.ndarray) -> None:
        """Restore ``excursion_state()`` (in place: recorded graphs stay valid)."""
        state = np.asarray(state, np.float32)
        if state.shape != (self.num_particles, 4):
            raise ValueError(f"drag excursion state has shape {state.shape}, expected ({self.num_particles}, 4)")
        self.excursion.assign(np.ascontiguousarray(state[:, :3]))
        self.mean_square.assign(np.ascontiguousarray(state[:, 3]))

    def apply(self, particle_q, particle_qd) -> None:
        """Update ``particle_qd`` (warp vec3 array) in place; launches only (graph-safe)."""
        wp.launch(_zero_mat33, dim=self.num_particles, device=self.device, inputs=[self.coeff])
        if self.kc_gain > 0.0:
            wp.launch(_update_excursion, dim=self.num_particles, device=self.device,
                      inputs=[self.mass, particle_qd, self.v_air, self.dt, self.kc_decay, self.excursion,
                              self.mean_square])  # fmt: skip
        wp.launch(_accumulate_drag, dim=self.num_faces, device=self.device,
                  inputs=[self.faces, particle_q, particle_qd, self.v_air, self.k_normal, self.k_tangential,
                          self.mean_square, self.kc_gain, self.kc_width, self.coeff])  # fmt: skip
        wp.launch(_implicit_drag_update, dim=self.num_particles, device=self.device,
                  inputs=[self.mass, self.coeff, self.v_air, self.dt, particle_qd])  # fmt: skip


KC_MIN_WP = wp.constant(KC_MIN)


@wp.kernel
def _update_excursion(
    mass: wp.array(dtype=float),
    qd: wp.array(dtype=wp.vec3),
    v_air: wp.array(dtype=wp.vec3),
    dt: float,
    decay: float,
    excursion: wp.array(dtype=wp.vec3),
    mean_square: wp.array(dtype=wp.float32),
):
    """Per particle: the excursion relative to the air and its running mean square
    (``excursion_update_reference``)."""
    p = wp.tid()
    if mass[p] <= 0.0:
        return
    e = (excursion[p] + dt * (qd[p] - v_air[0])) * decay
    excursion[p] = e
    mean_square[p] = mean_square[p] + (1.0 - decay) * (wp.dot(e, e) - mean_square[p])


@wp.kernel
def _zero_mat33(a: wp.array(dtype=wp.mat33)):
    a[wp.tid()] = wp.mat33(0.0)


@wp.kernel
def _accumulate_drag(
    faces: wp.array2d(dtype=wp.int32),
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    v_air: wp.array(dtype=wp.vec3),
    k_normal: float,
    k_tangential: float,
    mean_square: wp.array(dtype=wp.float32),
    kc_gain: float,
    kc_width: float,
    coeff: wp.array(dtype=wp.mat33),
):
    """Per triangle: its frozen drag coefficient matrix, a third to each vertex (``coeff``)."""
    f = wp.tid()
    i = faces[f, 0]
    j = faces[f, 1]
    k = faces[f, 2]
    cr = wp.cross(q[j] - q[i], q[k] - q[i])
    area2 = wp.length(cr)
    if area2 <= 0.0:
        return
    n = cr / area2
    area = 0.5 * area2
    u = (qd[i] + qd[j] + qd[k]) / 3.0 - v_air[0]
    un = wp.dot(u, n)
    ut = u - un * n
    nn = wp.outer(n, n)
    kn = k_normal
    if kc_gain > 0.0:  # low-KC factor from the triangle's oscillation amplitude (kc_drag_factor)
        amp = wp.sqrt(2.0 * (mean_square[i] + mean_square[j] + mean_square[k]) / 3.0)
        kc = wp.max(2.0 * wp.pi * amp / kc_width, KC_MIN_WP)
        kn = k_normal * wp.max(kc_gain * wp.pow(kc, -1.0 / 3.0), 1.0)
    c = area * (kn * wp.abs(un) * nn + k_tangential * wp.length(ut) * (wp.identity(n=3, dtype=float) - nn))
    wp.atomic_add(coeff, i, c)
    wp.atomic_add(coeff, j, c)
    wp.atomic_add(coeff, k, c)


@wp.kernel
def _implicit_drag_update(
    mass: wp.array(dtype=float),
    coeff: wp.array(dtype=wp.mat33),
    v_air: wp.array(dtype=wp.vec3),
    dt: float,
    qd: wp.array(dtype=wp.vec3),
):
    """Per particle: solve (m I + dt C) v' = m v + dt C v_air."""
    p = wp.tid()
    m = mass[p]
    if m <= 0.0:
        return
    c = coeff[p]
    a = m * wp.identity(n=3, dtype=float) + dt * c
    qd[p] = wp.inverse(a) * (m * qd[p] + dt * (c * v_air[0]))
