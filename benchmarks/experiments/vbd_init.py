"""Where newton's VBD solver starts its iterations: the VBD paper's adaptive initial guess, tried.

Vertex Block Descent (Chen, Macklin, Yang, Yuksel, Shinar, Jiang, SIGGRAPH 2024) minimises the
backward-Euler energy E(x) = 1 / (2 h^2) ||x - y||_M^2 + E_elastic(x), y = x^t + h v^t + h^2 a_ext,
with a few block Gauss-Seidel sweeps per substep, so where the sweeps start decides much of the
answer. newton 1.8 starts them at the inertial target y. The paper's Sec. 3.6 proposes an
adaptive start, x^t + h v^t + h^2 a~ with a~ = clamp(a^t . a_hat_ext, 0, |a_ext|) a_hat_ext and
a^t = (v^t - v^{t-1}) / h: a vertex held up by the cloth does not start a full step of gravity
below where it was. ``vbd_energy.py --init adaptive velocity inertia`` compares them (the energy
minimised is the same; only the start of the unconverged iterations moves). Not used by the
pipeline: it did not stop the energy gain (docs/lab/synthetic-data.md).
"""

from __future__ import annotations

import warp as wp

import newton
from newton import ParticleFlags


@wp.kernel
def adaptive_forward_step(
    dt: float,
    gravity: wp.array[wp.vec3],
    particle_world: wp.array[wp.int32],
    pos_prev: wp.array[wp.vec3],
    pos: wp.array[wp.vec3],
    vel: wp.array[wp.vec3],
    vel_last: wp.array[wp.vec3],
    inv_mass: wp.array[float],
    external_force: wp.array[wp.vec3],
    particle_flags: wp.array[wp.int32],
    mode: int,
    inertia_out: wp.array[wp.vec3],
    displacements_out: wp.array[wp.vec3],
):
    """newton's ``forward_step`` (the inertial target y, unchanged) with another initial displacement:
    mode 0 the paper's adaptive h v + h^2 a~, 1 h v (a~ = 0), 3 y - x^t (newton's own); keeps v^t
    for the next step's a^t."""
    particle = wp.tid()
    pos_prev[particle] = pos[particle]
    v = vel[particle]
    if not particle_flags[particle] & ParticleFlags.ACTIVE or inv_mass[particle] == 0:
        inertia_out[particle] = pos_prev[particle]
        if displacements_out:
            displacements_out[particle] = wp.vec3(0.0, 0.0, 0.0)
        vel_last[particle] = v
        return
    a_ext = gravity[particle_world[particle]] + external_force[particle] * inv_mass[particle]
    inertia_out[particle] = pos[particle] + (v + a_ext * dt) * dt
    a_ext_norm = wp.length(a_ext)
    a_tilde = wp.vec3(0.0, 0.0, 0.0)
    if a_ext_norm > 0.0:
        direction = a_ext / a_ext_norm
        shown = wp.dot((v - vel_last[particle]) / dt, direction)
        a_tilde = wp.clamp(shown, 0.0, a_ext_norm) * direction
    if mode == 1:
        a_tilde = wp.vec3(0.0, 0.0, 0.0)
    if mode == 3:
        a_tilde = a_ext
    if displacements_out:
        displacements_out[particle] = (v + a_tilde * dt) * dt
    vel_last[particle] = v


INIT_MODES = {"adaptive": 0, "velocity": 1, "inertia": 3}


class SolverVBDInit(newton.solvers.SolverVBD):
    """newton's ``SolverVBD`` whose particle iterations start elsewhere (``INIT_MODES``; the module
    docstring). Same keyword arguments. The previous step's velocities live in the solver (zero at
    first). Recorded into warp graphs like the base solver.
    """

    def __init__(self, model: newton.Model, init_mode: int = 0, **kwargs):
        super().__init__(model, **kwargs)
        self.init_mode = init_mode
        self.particle_qd_last = wp.zeros_like(model.particle_qd, device=self.device)

    def _initialize_particles(self, state_in, state_out, contacts, dt: float):  # noqa: ANN001 (newton's types)
        model = self.model
        if model.particle_count == 0:
            return
        if not self.rigid_soft_enable_dat and not self.particle_enable_self_contact:
            self.pos_prev_collision_detection.assign(state_in.particle_q)
            self.particle_displacements.zero_()
        wp.launch(
            kernel=adaptive_forward_step,
            inputs=[dt, model.gravity, model.particle_world, self.particle_q_prev, state_in.particle_q,
                    state_in.particle_qd, self.particle_qd_last, model.particle_inv_mass, state_in.particle_f,
                    model.particle_flags, self.init_mode],  # fmt: skip
            outputs=[self.inertia, self.particle_displacements],
            dim=model.particle_count,
            device=self.device,
        )
        self._penetration_free_truncation(state_in, contacts)


@wp.kernel
def chebyshev_mix(
    omega: float,
    base: wp.array[wp.vec3],
    displacement: wp.array[wp.vec3],
    older: wp.array[wp.vec3],
    previous: wp.array[wp.vec3],
    pos: wp.array[wp.vec3],
    pos_out: wp.array[wp.vec3],
):
    """x^(k) = omega (x_gs^(k) - x^(k-2)) + x^(k-2) on the displacements (VBD paper Sec. 3.7);
    shifts the history (older <- previous <- x^(k))."""
    i = wp.tid()
    d = omega * (displacement[i] - older[i]) + older[i]
    displacement[i] = d
    pos[i] = base[i] + d
    pos_out[i] = base[i] + d
    older[i] = previous[i]
    previous[i] = d


class SolverVBDChebyshev(SolverVBDInit):
    """``SolverVBDInit`` (newton's inertia start by default) with Chebyshev semi-iterative
    acceleration of the block Gauss-Seidel iterations (Wang 2015, used by the VBD paper, Sec. 3.7):
    omega_1 = 1, omega_2 = 2 / (2 - rho^2), omega_k = 4 / (4 - rho^2 omega_{k-1}); ``rho`` estimates the
    spectral radius of the sweeps. Without self-contact only (the iterate is base + displacement)."""

    def __init__(self, model: newton.Model, rho: float = 0.9, init_mode: int = 3, **kwargs):
        super().__init__(model, init_mode=init_mode, **kwargs)
        self.rho = rho
        self._older = wp.zeros_like(model.particle_q, device=self.device)
        self._previous = wp.zeros_like(model.particle_q, device=self.device)
        self._k = 0
        self._omega = 1.0

    def _initialize_particles(self, state_in, state_out, contacts, dt: float):  # noqa: ANN001
        super()._initialize_particles(state_in, state_out, contacts, dt)
        wp.copy(self._previous, self.particle_displacements)  # x^(0): the initial guess
        wp.copy(self._older, self.particle_displacements)
        self._k = 0

    def _solve_particle_iteration(self, state_in, state_out, contacts, dt: float):  # noqa: ANN001
        super()._solve_particle_iteration(state_in, state_out, contacts, dt)
        self._k += 1
        if self._k == 1:
            self._omega = 1.0
        elif self._k == 2:
            self._omega = 2.0 / (2.0 - self.rho**2)
        else:
            self._omega = 4.0 / (4.0 - self.rho**2 * self._omega)
        wp.launch(chebyshev_mix, dim=self.model.particle_count,
                  inputs=[self._omega, self.pos_prev_collision_detection, self.particle_displacements, self._older,
                          self._previous, state_in.particle_q, state_out.particle_q],
                  device=self.device)  # fmt: skip
