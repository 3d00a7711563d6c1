"""Air drag and fabrics: the warp kernels against the NumPy reference, the physics of the update,
and a damped skirt that comes to rest."""

import dataclasses

import numpy as np
import pytest

from pocoloco.synth.aero import (
    AIR_DENSITY,
    KC_MIN,
    AirDrag,
    drag_velocity_update_reference,
    excursion_update_reference,
    kc_drag_factor,
)
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


def test_warp_low_kc_drag_matches_the_reference():
    """The excursion kernel and the low-KC factor of each triangle, three substeps in a row,
    against ``excursion_update_reference`` + ``drag_velocity_update_reference``."""
    import warp as wp

    x, faces = _sheet()
    rng = np.random.default_rng(2)
    v = rng.normal(size=x.shape) * 0.3
    mass = np.full(len(x), 0.15 * 0.09 / len(x))
    mass[:3] = 0.0
    v_air, dt, time = np.array([0.05, 0.0, -0.1]), 0.005, 0.8
    e = rng.normal(size=x.shape) * 0.01
    e[:3] = 0.0
    ms = (e**2).sum(1) * rng.uniform(0.5, 2.0, len(x))
    dev = wp.get_device("cpu")
    drag = AirDrag(faces, mass, 1.0, 0.02, dt, dev, kc_gain=4.0, kc_width=0.3, kc_time=time)
    drag.set_air_velocity(v_air)
    drag.set_excursion_state(np.concatenate([e, ms[:, None]], 1))
    q = wp.array(x.astype(np.float32), dtype=wp.vec3, device=dev)
    qd = wp.array(v.astype(np.float32), dtype=wp.vec3, device=dev)
    plain = drag_velocity_update_reference(x, v, faces, mass, v_air, dt, 1.0, 0.02)
    ref_v = v
    for _ in range(3):
        drag.apply(q, qd)
        e, ms = excursion_update_reference(e, ms, ref_v, mass, v_air, dt, time)
        ref_v = drag_velocity_update_reference(x, ref_v, faces, mass, v_air, dt, 1.0, 0.02, mean_square=ms,
                                               kc_gain=4.0, kc_width=0.3)  # fmt: skip
        if _ == 0:
            first = ref_v
    state = drag.excursion_state()
    np.testing.assert_allclose(state[:, :3], e, atol=1e-6)
    np.testing.assert_allclose(state[:, 3], ms, rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(qd.numpy(), ref_v, atol=1e-5)
    # centimetre excursions on a 0.3 m panel: KC ~ 0.2, more than the steady drag takes out
    assert np.abs(v - first).sum() > 2.0 * np.abs(v - plain).sum()
    with pytest.raises(ValueError, match="excursion state"):
        drag.set_excursion_state(np.zeros((4, 4)))


def test_low_kc_factor_follows_the_plate_law_between_its_limits():
    import warp as wp

    width, gain = 0.3, 4.0
    amp = lambda kc: kc * width / (2 * np.pi)  # noqa: E731
    np.testing.assert_allclose(kc_drag_factor(amp(1.0), width, gain), gain)  # KC = 1: the gain itself
    np.testing.assert_allclose(kc_drag_factor(amp(0.5), width, gain) / kc_drag_factor(amp(1.0), width, gain),
                               0.5 ** (-1 / 3))  # fmt: skip
    assert kc_drag_factor(amp(1000.0), width, gain) == 1.0  # large excursions: the steady drag
    cap = gain * KC_MIN ** (-1 / 3)
    np.testing.assert_allclose(kc_drag_factor(np.array([0.0, amp(KC_MIN / 10)]), width, gain), [cap, cap])
    np.testing.assert_array_equal(kc_drag_factor(np.array([0.0, 1.0]), width, 0.0), [1.0, 1.0])  # off
    with pytest.raises(ValueError, match="low-KC"):
        AirDrag(np.zeros((1, 3), int), np.ones(3), 1.0, 0.0, 0.01, wp.get_device("cpu"), kc_gain=4.0, kc_width=0.0)


def test_excursion_of_steady_motion_grows_to_speed_times_time_and_of_an_oscillation_to_its_amplitude():
    dt, time, mass = 0.002, 0.5, np.ones(1)
    e, ms = np.zeros((1, 3)), np.zeros(1)
    for _ in range(int(6 * time / dt)):  # steady 1 m/s through still air
        e, ms = excursion_update_reference(e, ms, np.array([[1.0, 0.0, 0.0]]), mass, np.zeros(3), dt, time)
    np.testing.assert_allclose(e[0, 0], 1.0 * time, rtol=0.02)
    e, ms = np.zeros((1, 3)), np.zeros(1)
    a, w = 0.01, 2 * np.pi * 4.0  # 1 cm at 4 Hz, well above 1 / time
    for k in range(int(10 * time / dt)):
        vel = np.array([[0.0, 0.0, a * w * np.cos(w * k * dt)]])
        e, ms = excursion_update_reference(e, ms, vel, mass, np.zeros(3), dt, time)
    np.testing.assert_allclose(np.sqrt(2 * ms[0]), a, rtol=0.1)
    kinematic = excursion_update_reference(np.ones((1, 3)), np.zeros(1), np.ones((1, 3)), np.zeros(1), np.zeros(3),
                                           dt, time)  # fmt: skip
    np.testing.assert_array_equal(kinematic[0], 0.0)


def test_fabrics_cover_every_garment_and_undamped_is_v2():
    assert set(GARMENT_FABRIC) == set(GARMENT_KINDS)
    assert all(GARMENT_FABRIC[k] in FABRICS for k in GARMENT_KINDS)
    for kind in GARMENT_KINDS:
        assert fabric_for(kind, "none") is UNDAMPED
        f = fabric_for(kind, "physical")
        assert f.drag_normal > 0 and f.bend_damping > 0 and f.friction > UNDAMPED.friction
        assert f.drag_kc_gain == 0.0  # data v3: the steady drag alone
        u = fabric_for(kind, "unsteady")
        assert u.drag_kc_gain > 1.0 and dataclasses.replace(u, drag_kc_gain=0.0) == f  # v4: that and nothing else
    with pytest.raises(ValueError, match="damping model"):
        fabric_for("skirt", "syrup")
    assert DAMPING_MODELS == ("physical", "none", "unsteady")


def test_old_cards_read_as_undamped():
    from pocoloco.synth.config import SynthConfig, config_of_card

    card = SynthConfig().to_dict()
    del card["cloth_damping"]  # a card written before data v3
    card["cloth_damping"] = "physical"
    assert config_of_card(card).cloth_damping == "physical"
    del card["cloth_damping"]  # a card written before the field existed
    assert config_of_card(card).cloth_damping == "none"
    assert SynthConfig().cloth_damping == "unsteady"  # data v4


def test_cloth_versions_name_the_data_each_reproduces():
    import dataclasses

    from pocoloco.synth.config import CLOTH_VERSIONS, SYNTH_PRESETS, SynthConfig, cloth_version, config_of_card
    from pocoloco.synth.pipeline import cloth_settings

    assert cloth_version(SynthConfig()) == "v4"
    assert all(cloth_version(c) == "v4" for c in SYNTH_PRESETS.values())
    settings = cloth_settings(SynthConfig(), "skirt")
    assert settings.air_drag_kc_gain > 1.0 and settings.chebyshev_rho == 0.9
    v3_config = dataclasses.replace(SynthConfig(), **CLOTH_VERSIONS["v3"])
    assert (v3_config.cloth_damping, v3_config.cloth_chebyshev_rho) == ("physical", 0.0)
    v3 = cloth_settings(v3_config, "skirt")
    assert v3.air_drag_kc_gain == 0.0 and v3.chebyshev_rho == 0.0  # data v3 reproduced
    assert dataclasses.replace(settings, air_drag_kc_gain=0.0, chebyshev_rho=0.0) == v3  # v4 = v3 + these two
    card = v3_config.to_dict()
    del card["cloth_chebyshev_rho"]  # a v3 card, written before the field existed
    assert cloth_version(config_of_card(card)) == "v3"
    for name, overrides in CLOTH_VERSIONS.items():
        assert cloth_version(dataclasses.replace(SynthConfig(), **overrides)) == name
    v2 = dataclasses.replace(SynthConfig(), **CLOTH_VERSIONS["v2"])
    assert (v2.garment_tessellation, v2.cloth_damping) == ("isotropic", "none")
    card = v2.to_dict()
    del card["cloth_damping"], card["cloth_chebyshev_rho"]  # a v2 card, written before the fields existed
    assert cloth_version(config_of_card(card)) == "v2"
    assert cloth_version(dataclasses.replace(SynthConfig(), cloth_substeps=9)) == "custom"
