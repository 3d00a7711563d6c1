"""Coulomb bending friction: the hinge angles against newton's own, the warp update against the NumPy
reference, the stiffness it adds, and one-line errors."""

import numpy as np
import pytest
from conftest import grid_faces, newton_cloth

from pocoloco.synth.bend_friction import BendFriction, bend_friction_update_reference, dihedral_angles_reference


def _curved_sheet_model(n=7, size=0.2):
    """A sheet rolled into a quarter cylinder (its rest hinges bent), 1e-3 bending stiffness."""
    verts = [(0.15 * np.cos(0.5 * np.pi * j / (n - 1)), 0.15 * np.sin(0.5 * np.pi * j / (n - 1)), -size * i / (n - 1))
             for i in range(n) for j in range(n)]  # fmt: skip
    return newton_cloth(verts, grid_faces(n, n))


def test_hinge_angles_are_newtons():
    model = _curved_sheet_model()
    edges = model.edge_indices.numpy()
    ours = dihedral_angles_reference(model.particle_q.numpy(), edges)
    inner = ~np.isnan(ours)
    assert inner.sum() > 20 and np.abs(ours[inner]).max() > 0.1  # bent hinges, not a flat sheet
    np.testing.assert_allclose(ours[inner], model.edge_rest_angle.numpy()[inner], atol=1e-5)


def test_warp_update_matches_the_reference():
    import warp as wp

    model = _curved_sheet_model()
    edges = model.edge_indices.numpy()
    rest0 = model.edge_rest_angle.numpy().copy()
    friction = BendFriction(model, moment=1.5e-4, stick_angle=0.02, device=wp.get_device("cpu"))
    rng = np.random.default_rng(0)
    x = model.particle_q.numpy() + rng.normal(scale=0.004, size=(model.particle_count, 3))
    slip0 = rest0 + rng.normal(scale=0.03, size=len(rest0))  # some within the stick angle, some beyond
    friction.slip_angle.assign(slip0.astype(np.float32))
    friction.apply(wp.array(x.astype(np.float32), dtype=wp.vec3, device="cpu"))
    slip_ref, rest_ref = bend_friction_update_reference(x.astype(np.float32), edges, rest0, slip0, 0.02, friction.share)
    inner = ~np.isnan(rest_ref)
    slip = friction.slip_angle.numpy()
    moved = np.abs(slip_ref - slip0) > 1e-6
    assert moved[inner].any() and (~moved[inner]).any()  # both regimes happen
    np.testing.assert_allclose(slip, slip_ref, atol=2e-5)
    np.testing.assert_allclose(model.edge_rest_angle.numpy()[inner], rest_ref[inner], atol=2e-5)
    np.testing.assert_array_equal(model.edge_rest_angle.numpy()[~inner], rest0[~inner])  # boundary: untouched


def test_the_friction_spring_is_added_once():
    import warp as wp

    model = _curved_sheet_model()
    k_e = model.edge_bending_properties.numpy()[:, 0].copy()
    friction = BendFriction(model, moment=1e-4, stick_angle=0.01, device=wp.get_device("cpu"))
    k_f = 1e-4 / 0.01
    np.testing.assert_allclose(model.edge_bending_properties.numpy()[:, 0], k_e + k_f, rtol=1e-6)
    assert friction.share == pytest.approx(k_f / (1e-3 + k_f))
    for moment, angle in ((0.0, 0.02), (1e-4, 0.0), (-1.0, 0.02)):
        with pytest.raises(ValueError, match="bend friction"):
            BendFriction(_curved_sheet_model(), moment=moment, stick_angle=angle, device=wp.get_device("cpu"))


def test_a_hinge_within_its_stick_angle_holds():
    # the reference on one hinge: inside the stick angle nothing slips, beyond it the element trails
    x = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.3], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    edges = np.array([[0, 1, 2, 3]])
    theta = dihedral_angles_reference(x, edges)[0]
    slip, rest = bend_friction_update_reference(x, edges, np.array([0.0]), np.array([theta - 0.01]), 0.02, 0.8)
    assert slip[0] == pytest.approx(theta - 0.01)
    slip, rest = bend_friction_update_reference(x, edges, np.array([0.0]), np.array([theta - 0.5]), 0.02, 0.8)
    assert slip[0] == pytest.approx(theta - 0.02) and rest[0] == pytest.approx(0.8 * (theta - 0.02))
