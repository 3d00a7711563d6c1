"""Chebyshev-accelerated VBD sweeps: the weights, each sweep's extrapolation against the formula
written out in NumPy, rho = 0 as newton's own solver, and the energy a hanging sheet gains."""

import numpy as np
import pytest
from conftest import grid_faces, newton_cloth

from pocoloco.synth.vbd_chebyshev import chebyshev_weights


def test_weights_follow_the_recurrence():
    w = chebyshev_weights(5, 0.9)
    assert w[0] == 1.0
    assert w[1] == pytest.approx(2 / (2 - 0.81))
    for k in range(2, 5):
        assert w[k] == pytest.approx(4 / (4 - 0.81 * w[k - 1]))
    assert all(1.0 <= x < 2.0 for x in w)  # over-relaxation, below the divergence bound
    assert chebyshev_weights(4, 0.0) == [1.0, 1.0, 1.0, 1.0]
    for bad in (-0.1, 1.0, 1.5):
        with pytest.raises(ValueError, match="rho"):
            chebyshev_weights(3, bad)


def _sheet_model(n=8, size=0.2, kick=0.3):
    """A vertical sheet, its top edge pinned, kicked along its normal."""
    xs = np.linspace(0.0, size, n)
    model = newton_cloth([(x, 0.0, -z) for z in xs for x in xs], grid_faces(n, n), pinned=range(n))
    state = model.state()
    qd = state.particle_qd.numpy()
    qd[n:, 1] = kick
    state.particle_qd.assign(qd)
    return model, state


def _run(solver, model, state, steps, dt=1 / 175):
    s0, s1, control = state, model.state(), model.control()
    for _ in range(steps):
        solver.step(s0, s1, control, None, dt)
        s0, s1 = s1, s0
    return s0.particle_q.numpy(), s0.particle_qd.numpy()


def test_each_sweep_is_extrapolated_as_written():
    import warp as wp

    from pocoloco.synth.vbd_chebyshev import SolverVBDChebyshev

    model, state = _sheet_model()
    seen = []

    class Recording(SolverVBDChebyshev):
        """Records, per sweep, the Gauss-Seidel answer and the extrapolated iterate."""

        def _initialize_particles(self, *a):
            super()._initialize_particles(*a)
            seen.append(("init", self.particle_displacements.numpy().copy()))

        def _solve_particle_iteration(self, state_in, state_out, contacts, dt):
            omega = self.weights[self._sweep]
            real_launch = wp.launch

            def spy(kernel, *args, **kwargs):
                if kernel is not None and getattr(kernel, "key", "").startswith("chebyshev_step"):
                    seen.append(("gs", self.particle_displacements.numpy().copy(), omega))
                return real_launch(kernel, *args, **kwargs)

            import pocoloco.synth.vbd_chebyshev as mod

            mod.wp.launch = spy
            try:
                super()._solve_particle_iteration(state_in, state_out, contacts, dt)
            finally:
                mod.wp.launch = real_launch
            seen.append(("x", self.particle_displacements.numpy().copy(),
                         state_in.particle_q.numpy().copy(), self.pos_prev_collision_detection.numpy().copy()))  # fmt: skip

    solver = Recording(model, rho=0.9, iterations=4)
    _run(solver, model, state, 2)
    checked = 0
    history = []
    for entry in seen:
        if entry[0] == "init":
            history = [entry[1], entry[1]]  # x^(-1) = x^(0): the first weight is 1 anyway
        elif entry[0] == "gs":
            gs, omega = entry[1], entry[2]
        else:
            expected = omega * (gs - history[-2]) + history[-2]
            np.testing.assert_allclose(entry[1], expected, atol=1e-7)
            np.testing.assert_allclose(entry[2], entry[3] + entry[1], atol=1e-6)  # the iterate follows
            history.append(entry[1])
            checked += 1
    assert checked == 8  # 2 substeps x 4 sweeps
    assert any(e[2] > 1.0 for e in seen if e[0] == "gs")


def test_rho_zero_is_newtons_solver():
    import newton

    from pocoloco.synth.vbd_chebyshev import SolverVBDChebyshev

    model, state = _sheet_model()
    q_ref, v_ref = _run(newton.solvers.SolverVBD(model, iterations=5), model, state, 10)
    model, state = _sheet_model()
    q, v = _run(SolverVBDChebyshev(model, rho=0.0, iterations=5), model, state, 10)
    np.testing.assert_allclose(q, q_ref, atol=1e-6)
    np.testing.assert_allclose(v, v_ref, atol=1e-4)
    model, state = _sheet_model()
    q9, _ = _run(SolverVBDChebyshev(model, rho=0.9, iterations=5), model, state, 10)
    assert np.abs(q9 - q_ref).max() > 1e-5  # the acceleration changes the answer


def test_self_contact_is_refused():
    from pocoloco.synth.vbd_chebyshev import SolverVBDChebyshev

    model, _ = _sheet_model()
    with pytest.raises(ValueError, match="self-contact"):
        SolverVBDChebyshev(model, rho=0.9, iterations=5, particle_enable_self_contact=True)
