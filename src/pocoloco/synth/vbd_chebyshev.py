"""newton's VBD cloth solver with Chebyshev-accelerated iterations.

Vertex Block Descent (Chen, Macklin, Yang, Yuksel, Shinar, Jiang, SIGGRAPH 2024) minimises each
substep's backward-Euler energy with a few block Gauss-Seidel sweeps over the vertex colours. The
data pipeline stops after 5; a hanging garment's tension cannot cross its 20-40 rows of vertices in
5 sweeps, the unconverged answer feeds energy into the cloth, and the garment never comes to rest
(``benchmarks/experiments/vbd_energy.py``, docs/lab/synthetic-data.md). More sweeps shrink that
gain but cost as much again each.

The VBD paper (Sec. 3.7) accelerates the sweeps with Chebyshev semi-iterative extrapolation
(Wang, "A Chebyshev semi-iterative approach for accelerating projective and position-based
dynamics", SIGGRAPH Asia 2015): after sweep k,

    x^(k) = omega_k (x_gs^(k) - x^(k-2)) + x^(k-2),
    omega_1 = 1,  omega_2 = 2 / (2 - rho^2),  omega_k = 4 / (4 - rho^2 omega_{k-1}),

with ``rho`` an estimate of the sweeps' spectral radius (too high diverges). It costs one vector
update per sweep. The energy minimised and the physical parameters are unchanged: only how close
5 sweeps get to its minimum.
"""

from __future__ import annotations

import warp as wp

import newton


@wp.kernel
def chebyshev_step(
    omega: float,
    base: wp.array[wp.vec3],
    displacement: wp.array[wp.vec3],
    older: wp.array[wp.vec3],
    previous: wp.array[wp.vec3],
    pos: wp.array[wp.vec3],
    pos_out: wp.array[wp.vec3],
):
    """Extrapolate one sweep's displacements (base + displacement = the iterate) and shift the
    history: older <- previous <- x^(k)."""
    i = wp.tid()
    d = omega * (displacement[i] - older[i]) + older[i]
    displacement[i] = d
    pos[i] = base[i] + d
    pos_out[i] = base[i] + d
    older[i] = previous[i]
    previous[i] = d


def chebyshev_weights(iterations: int, rho: float) -> list[float]:
    """omega_1 ... omega_n of Wang 2015 for spectral radius estimate ``rho`` in [0, 1)."""
    if not 0.0 <= rho < 1.0:
        raise ValueError(f"chebyshev rho must be in [0, 1), got {rho}")
    out: list[float] = []
    for k in range(1, iterations + 1):
        out.append(1.0 if k == 1 else 2.0 / (2.0 - rho**2) if k == 2 else 4.0 / (4.0 - rho**2 * out[-1]))
    return out


class SolverVBDChebyshev(newton.solvers.SolverVBD):
    """newton's ``SolverVBD`` (same keyword arguments) whose particle sweeps are Chebyshev-accelerated
    (module docstring). ``rho`` = 0 is newton's solver. Cloth without self-contact only (its iterate
    is the step's start plus a displacement; self-contact truncates displacements in between).
    Records into warp graphs like the base solver (the weights are fixed per sweep index)."""

    def __init__(self, model: newton.Model, rho: float = 0.9, **kwargs):
        super().__init__(model, **kwargs)
        if self.particle_enable_self_contact:
            raise ValueError("Chebyshev acceleration: cloth self-contact is not supported")
        self.weights = chebyshev_weights(self.iterations, rho)
        self._older = wp.zeros_like(model.particle_q, device=self.device)
        self._previous = wp.zeros_like(model.particle_q, device=self.device)
        self._sweep = 0

    def _initialize_particles(self, state_in, state_out, contacts, dt: float):  # noqa: ANN001 (newton's types)
        super()._initialize_particles(state_in, state_out, contacts, dt)
        wp.copy(self._previous, self.particle_displacements)  # x^(0), the initial guess
        wp.copy(self._older, self.particle_displacements)
        self._sweep = 0

    def _solve_particle_iteration(self, state_in, state_out, contacts, dt: float):  # noqa: ANN001
        super()._solve_particle_iteration(state_in, state_out, contacts, dt)
        omega = self.weights[min(self._sweep, len(self.weights) - 1)]
        self._sweep += 1
        if self.model.particle_count == 0:
            return
        wp.launch(chebyshev_step, dim=self.model.particle_count,
                  inputs=[omega, self.pos_prev_collision_detection, self.particle_displacements, self._older,
                          self._previous, state_in.particle_q, state_out.particle_q],
                  device=self.device)  # fmt: skip
