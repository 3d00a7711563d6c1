"""Air drag and fabrics: the warp kernels against the NumPy reference, the physics of the update,
and a damped skirt that comes to rest."""

import numpy as np
import pytest

from pocoloco.synth.aero import AIR_DENSITY, AirDrag, drag_velocity_update_reference
from pocoloco.synth.fabric import DAMPING_MODELS, FABRICS, GARMENT_FABRIC, UNDAMPED, fabric_for
from pocoloco.synth.garments import GARMENT_KINDS


def _sheet(n=10, size=0.3, seed=0):
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n))
    x = np.stack([u.ravel(), v.ravel(), 0.02 * rng.normal(size=n * n)], 1)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            faces += [[a, a + 1, a + n], [a + 1, a + n + 1, a + n]]
    return x, np.array(faces)


def _warp_update(x, v, faces, mass, v_air, dt, cn, ct):
    import warp as wp

    dev = wp.get_device("cpu")
    drag = AirDrag(faces, mass, cn, ct, dt, dev)
    drag.set_air_velocity(v_air)
    q = wp.array(x.astype(np.float32), dtype=wp.vec3, device=dev)
    qd = wp.array(v.astype(np.float32), dtype=wp.vec3, device=dev)
    drag.apply(q, qd)
    return qd.numpy()


def test_warp_drag_matches_the_reference():
    x, faces = _sheet()
    rng = np.random.default_rng(1)
    v = rng.normal(size=x.shape) * 0.5
    mass = np.full(len(x), 0.15 * 0.09 / len(x))
    mass[:3] = 0.0  # pinned: untouched
    v_air = np.array([0.1, -0.2, 0.05])
    ref = drag_velocity_update_reference(x, v, faces, mass, v_air, 0.005, 1.0, 0.02)
    got = _warp_update(x, v, faces, mass, v_air, 0.005, 1.0, 0.02)
    assert np.abs(ref - v).max() > 1e-2  # the update does something
    np.testing.assert_allclose(got, ref, atol=1e-5)
    np.testing.assert_array_equal(got[:3], v[:3].astype(np.float32))


def test_drag_on_a_falling_flat_sheet_is_the_plate_law():
    # a flat sheet moving along its normal: dv = -dt rho C A v|v| / (2 m), to first order in dt
    x, faces = _sheet()
    x[:, 2] = 0.0
    area, density, cn = 0.09, 0.15, 1.0
    mass = np.full(len(x), density * area / len(x))
    v = np.tile([0.0, 0.0, -0.5], (len(x), 1))
    dt = 1e-4
    new = drag_velocity_update_reference(x, v, faces, mass, np.zeros(3), dt, cn, 0.0)
    expected = -0.5 + dt * 0.5 * AIR_DENSITY * cn * 0.5**2 / density  # per unit area: m = density
    np.testing.assert_allclose(new[:, 2].mean(), expected, rtol=1e-3)
    # moving in its own plane, only the (much weaker) tangential drag acts
    v = np.tile([0.5, 0.0, 0.0], (len(x), 1))
    new_n = drag_velocity_update_reference(x, v, faces, mass, np.zeros(3), dt, cn, 0.0)
    new_t = drag_velocity_update_reference(x, v, faces, mass, np.zeros(3), dt, cn, 0.02)
    np.testing.assert_allclose(new_n, v)
    assert 0.0 < (v - new_t)[:, 0].mean() < 0.05 * (0.5 - (-expected))


def test_drag_is_relative_to_the_air_and_never_reverses():
    x, faces = _sheet()
    mass = np.full(len(x), 1e-4)
    v = np.tile([0.0, 0.0, 2.0], (len(x), 1))
    same = drag_velocity_update_reference(x, v, faces, mass, np.array([0.0, 0.0, 2.0]), 0.01, 1.0, 0.02)
    np.testing.assert_allclose(same, v)  # moving with the air: no force
    huge = drag_velocity_update_reference(x, v, faces, mass, np.zeros(3), 10.0, 1.0, 0.02)
    assert (huge[:, 2] >= 0).all() and (huge[:, 2] < 2.0).all()  # implicit: slows, never flips


def test_fabrics_cover_every_garment_and_undamped_is_v2():
    assert set(GARMENT_FABRIC) == set(GARMENT_KINDS)
    assert all(GARMENT_FABRIC[k] in FABRICS for k in GARMENT_KINDS)
    for kind in GARMENT_KINDS:
        assert fabric_for(kind, "none") is UNDAMPED
        f = fabric_for(kind, "physical")
        assert f.drag_normal > 0 and f.bend_damping > 0 and f.friction > UNDAMPED.friction
    with pytest.raises(ValueError, match="damping model"):
        fabric_for("skirt", "syrup")
    assert DAMPING_MODELS == ("physical", "none")


def test_old_cards_read_as_undamped():
    from pocoloco.synth.config import SynthConfig, config_of_card

    card = SynthConfig().to_dict()
    del card["cloth_damping"]  # a card written before data v3
    card["cloth_damping"] = "physical"
    assert config_of_card(card).cloth_damping == "physical"
    del card["cloth_damping"]  # a card written before the field existed
    assert config_of_card(card).cloth_damping == "none"
    assert SynthConfig().cloth_damping == "physical"  # data v3


def test_cloth_versions_name_the_data_each_reproduces():
    import dataclasses

    from pocoloco.synth.config import CLOTH_VERSIONS, SYNTH_PRESETS, SynthConfig, cloth_version, config_of_card

    assert cloth_version(SynthConfig()) == "v3"
    assert all(cloth_version(c) == "v3" for c in SYNTH_PRESETS.values())
    for name, overrides in CLOTH_VERSIONS.items():
        assert cloth_version(dataclasses.replace(SynthConfig(), **overrides)) == name
    v2 = dataclasses.replace(SynthConfig(), **CLOTH_VERSIONS["v2"])
    assert (v2.garment_tessellation, v2.cloth_damping) == ("isotropic", "none")
    card = v2.to_dict()
    del card["cloth_damping"]  # a v2 card, written before the field existed
    assert cloth_version(config_of_card(card)) == "v2"
    assert cloth_version(dataclasses.replace(SynthConfig(), cloth_substeps=9)) == "custom"
