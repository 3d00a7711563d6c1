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

