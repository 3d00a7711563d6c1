"""The compression-free membrane: the warp kernel against the NumPy reference, and what the relaxed
rest shapes do to the membrane's strain."""

import numpy as np
from conftest import grid_faces, newton_cloth

from pocoloco.synth.tension_field import TensionField, relaxed_rest_shapes_reference


def _sheet_model(n=6, size=0.2):
    """A flat sheet in the xy plane."""
    xs = np.linspace(0.0, size, n)
    return newton_cloth([(x, y, 0.0) for y in xs for x in xs], grid_faces(n, n), color=False)


def _metric(x, tris, poses):
    """(T, 2, 2) F^T F of positions x against rest-shape inverses poses."""
    ds = np.stack([x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]]], axis=2)
    f = ds @ poses
    return np.swapaxes(f, 1, 2) @ f


def test_kernel_matches_the_reference_and_drops_only_compression():
    import warp as wp

    model = _sheet_model()
    tris = model.tri_indices.numpy()
    original = model.tri_poses.numpy().copy()
    x0 = model.particle_q.numpy().astype(np.float64)
    # squeeze x by 20 %, stretch y by 10 %, and jitter: compressed, stretched and mixed triangles
    rng = np.random.default_rng(0)
    x = x0 * np.array([0.8, 1.1, 1.0]) + rng.normal(scale=0.001, size=x0.shape)
    field = TensionField(model, wp.get_device("cpu"), min_stretch=0.5)
    field.apply(wp.array(x.astype(np.float32), dtype=wp.vec3, device="cpu"))
    got = model.tri_poses.numpy()
    ref = relaxed_rest_shapes_reference(x.astype(np.float32), tris, original, min_stretch=0.5)
    np.testing.assert_allclose(got, ref, atol=2e-3 * np.abs(original).max())
    before = np.linalg.eigvalsh(_metric(x, tris, original))
    after = np.linalg.eigvalsh(_metric(x, tris, got.astype(np.float64)))
    assert (before[:, 0] < 0.95).all()  # every triangle was compressed along x
    np.testing.assert_allclose(after[:, 0], 1.0, atol=2e-3)  # ... and no longer is
    np.testing.assert_allclose(after[:, 1], before[:, 1], rtol=2e-3)  # the stretch is kept
    # a pure stretch leaves the rest shapes as they were; the original is kept for the next step
    field.apply(wp.array((x0 * np.array([1.1, 1.05, 1.0])).astype(np.float32), dtype=wp.vec3, device="cpu"))
    np.testing.assert_allclose(model.tri_poses.numpy(), original, rtol=1e-5, atol=1e-6)


def test_a_collapsing_triangle_keeps_resisting():
    import warp as wp

    model = _sheet_model()
    tris = model.tri_indices.numpy()
    original = model.tri_poses.numpy().copy()
    x = model.particle_q.numpy().astype(np.float64) * np.array([0.3, 1.0, 1.0])  # squeezed to 30 %
    field = TensionField(model, wp.get_device("cpu"), min_stretch=0.7)
    field.apply(wp.array(x.astype(np.float32), dtype=wp.vec3, device="cpu"))
    after = np.linalg.eigvalsh(_metric(x, tris, model.tri_poses.numpy().astype(np.float64)))
    np.testing.assert_allclose(after[:, 0], (0.3 / 0.7) ** 2, rtol=0.05)  # compressed, but only past 0.7
    np.testing.assert_allclose(model.tri_poses.numpy(), relaxed_rest_shapes_reference(x, tris, original, 0.7),
                               atol=1e-3 * np.abs(original).max())  # fmt: skip


def test_a_softened_membrane_keeps_a_share_of_the_compressive_strain():
    import warp as wp

    model = _sheet_model()
    tris = model.tri_indices.numpy()
    original = model.tri_poses.numpy().copy()
    x = model.particle_q.numpy().astype(np.float64) * np.array([0.9, 1.1, 1.0])  # 10 % shorter along x
    field = TensionField(model, wp.get_device("cpu"), min_stretch=0.7, compression=0.09)
    field.apply(wp.array(x.astype(np.float32), dtype=wp.vec3, device="cpu"))
    got = model.tri_poses.numpy()
    np.testing.assert_allclose(got, relaxed_rest_shapes_reference(x, tris, original, 0.7, compression=0.09),
                               atol=1e-3 * np.abs(original).max())  # fmt: skip
    after = np.sqrt(np.linalg.eigvalsh(_metric(x, tris, got.astype(np.float64))))
    np.testing.assert_allclose(after[:, 0], 1.0 - 0.3 * 0.1, rtol=2e-3)  # the strain scaled by sqrt(0.09)
    np.testing.assert_allclose(after[:, 1], 1.1, rtol=2e-3)  # the stretch untouched
    # compression=1 is newton's membrane: the rest shapes stay as they were
    fresh = _sheet_model()
    TensionField(fresh, wp.get_device("cpu"), compression=1.0).apply(
        wp.array(x.astype(np.float32), dtype=wp.vec3, device="cpu"))
    np.testing.assert_allclose(fresh.tri_poses.numpy(), original, rtol=1e-5, atol=1e-6)
