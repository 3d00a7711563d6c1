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
"""

from __future__ import annotations

import numpy as np
import warp as wp

#: density of air at 20 C and sea level [kg/m^3]
AIR_DENSITY = 1.204


def drag_velocity_update_reference(
    x: np.ndarray, v: np.ndarray, faces: np.ndarray, mass: np.ndarray, v_air: np.ndarray,
    dt: float, c_normal: float, c_tangential: float, rho: float = AIR_DENSITY,
) -> np.ndarray:
    """One implicit drag update, plain NumPy (the reference for the warp kernels).

    x, v: (V, 3) positions [m] and velocities [m/s]; faces: (F, 3); mass: (V,) [kg]
    (0 = kinematic: left alone); v_air: (3,) air velocity in the simulation frame.
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
        Cf = k * (c_normal * abs(un) * nn + c_tangential * np.linalg.norm(ut) * (np.eye(3) - nn))
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
    c_normal, c_tangential: drag coefficients (dimensionless); device: a warp device.
    ``set_air_velocity`` changes the air's velocity in the simulation frame (a frame
    translating with the pelvis sees the still air move at minus its own velocity) without
    invalidating a recorded graph (the array is written in place).
    """

    def __init__(self, faces: np.ndarray, mass: np.ndarray, c_normal: float, c_tangential: float, dt: float,
                 device, rho: float = AIR_DENSITY):  # fmt: skip
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
        wp.load_module(__name__, device=device)  # compiled now, not while a graph records its launches

    def set_air_velocity(self, v_air: np.ndarray) -> None:
        self.v_air.assign(np.asarray(v_air, np.float32).reshape(1, 3))

    def apply(self, particle_q, particle_qd) -> None:
        """Update ``particle_qd`` (warp vec3 array) in place; launches only (graph-safe)."""
        wp.launch(_zero_mat33, dim=self.num_particles, device=self.device, inputs=[self.coeff])
        wp.launch(_accumulate_drag, dim=self.num_faces, device=self.device,
                  inputs=[self.faces, particle_q, particle_qd, self.v_air, self.k_normal, self.k_tangential,
                          self.coeff])  # fmt: skip
        wp.launch(_implicit_drag_update, dim=self.num_particles, device=self.device,
                  inputs=[self.mass, self.coeff, self.v_air, self.dt, particle_qd])  # fmt: skip


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
    c = area * (k_normal * wp.abs(un) * nn + k_tangential * wp.length(ut) * (wp.identity(n=3, dtype=float) - nn))
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
