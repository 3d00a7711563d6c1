"""Cloth simulation: metrics against references, bad-frame flags, a tiny run."""

import dataclasses

import numpy as np
import pytest
import trimesh

from pocoloco.body.anny_body import AnnyBody
from pocoloco.synth.capsules import fit_capsules
from pocoloco.synth.cloth_sim import (
    ClothSimSettings,
    frame_stats,
    mesh_edges,
    penetration_stats,
    signed_distance,
    simulate_garment,
)
from pocoloco.synth.garments import make_garment


@pytest.fixture(scope="module")
def body():
    return AnnyBody()


@pytest.fixture(scope="module")
def skirt(body):
    return make_garment("skirt", body, resolution=0.3)


def test_signed_distance_matches_a_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    rng = np.random.default_rng(0)
    p = rng.normal(size=(200, 3))
    p *= rng.uniform(0.2, 1.8, size=(200, 1)) / np.linalg.norm(p, axis=1, keepdims=True)
    sd = signed_distance(p, sphere.vertices, sphere.faces)
    np.testing.assert_allclose(sd, np.linalg.norm(p, axis=1) - 1.0, atol=5e-3)  # negative inside


def test_penetration_stats_against_a_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    pts = np.array([[0, 0, 0.9], [0, 0, 1.2], [0.5, 0, 0], [0, 2, 0]], np.float32)  # 2 inside: 0.1, 0.5 deep
    pen = penetration_stats(pts, sphere.vertices, sphere.faces)
    assert pen.fraction == pytest.approx(0.5)
    assert pen.max == pytest.approx(0.5, abs=5e-3)
    assert pen.mean == pytest.approx(0.6 / 4, abs=5e-3)


def test_frame_stats_flags_broken_frames(body, skirt):
    s = ClothSimSettings()
    edges = mesh_edges(skirt.faces)
    rest = skirt.rest_vertices
    rest_len = np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)
    judge = lambda x: frame_stats(x, body.template, body.faces, edges, rest_len, s)  # noqa: E731

    ok = judge(rest)
    assert ok.valid and ok.reason == "" and ok.stretch_max == pytest.approx(1.0, abs=1e-5)
    assert ok.penetration_max == 0.0 and ok.penetration_fraction == 0.0

    nan = rest.copy()
    nan[5] = np.nan
    bad = judge(nan)
    assert not bad.valid and bad.reason == "nan"

    far = rest.copy()
    far[5] += [0.0, 0.0, 5.0]  # one vertex thrown 5 m away
    bad = judge(far)
    assert not bad.valid and "explosion" in bad.reason and bad.stretch_max > 3

    inside = rest.copy()
    inside[: len(rest) // 4] = 0.0  # a quarter of the vertices at the pelvis centre
    bad = judge(inside)
    assert not bad.valid and "penetration" in bad.reason and bad.penetration_fraction >= 0.24

    # lead-in frames (not stored) are checked for hard failures only: penetration is not measured
    lead = lambda x: frame_stats(x, body.template, body.faces, edges, rest_len, s, penetration=False)  # noqa: E731
    sunk = lead(inside)
    assert "penetration" not in sunk.reason and "inside" not in sunk.reason  # (its stretch is judged)
    assert np.isnan(sunk.penetration_max) and np.isnan(sunk.penetration_fraction) and lead(rest).valid
    assert lead(nan).reason == "nan" and "explosion" in lead(far).reason and not lead(far).valid


def test_capsules_follow_the_rest_body(body):
    rig = fit_capsules(body)
    assert (rig.radius > 0.005).all() and (rig.radius < 0.12).all()
    eye = np.tile(np.eye(3, dtype=np.float32), (len(body.template), 1, 1))
    ends = rig.endpoints(body.template, eye)  # (K, 2, 3)
    ref = (body.template[rig.anchors] + rig.offsets).mean(2)
    np.testing.assert_allclose(ends, ref, atol=1e-6)
    # all anchors of one end agree on where it is (offsets are consistent)
    spread = np.linalg.norm(body.template[rig.anchors] + rig.offsets - ends[:, :, None], axis=-1)
    assert spread.max() < 1e-5
    # capsule axes lie inside the body
    assert (signed_distance(ends.reshape(-1, 3), body.template, body.faces) < 0).all()


def test_bad_settings_are_rejected(body, skirt):
    posed = body.pose(np.zeros((1, 24, 3), np.float32))
    with pytest.raises(ValueError, match="collider"):
        simulate_garment(body, skirt, posed, ClothSimSettings(collider="spheres"))


@pytest.mark.slow  # ~40 s of kernel compilation on a fresh warp cache, ~10 s after
@pytest.mark.parametrize("collider", ["mesh", "capsules"])
def test_tiny_simulation_runs_and_stays_outside(body, skirt, collider):
    t = 6
    rot = np.zeros((t, 24, 3), np.float32)
    ramp = np.linspace(0.0, 1.0, t)
    rot[:, 1, 0] = -0.4 * ramp  # left leg forward
    rot[:, 2, 0] = 0.3 * ramp  # right leg back
    rot[:, 0, 2] = 0.3 * ramp  # turning
    posed = body.pose(rot)
    settings = dataclasses.replace(ClothSimSettings(collider=collider), substeps=5, iterations=3, settle_frames=2)
    seq = simulate_garment(body, skirt, posed, settings, progress=(seen := []).append)
    assert seq.vertices.shape == (t, len(skirt.rest_vertices), 3) and seq.vertices.dtype == np.float32
    assert np.isfinite(seq.vertices).all()
    assert seen == list(range(t)) and len(seq.stats) == t
    assert seq.reset_count == 0
    assert max(s.stretch_max for s in seq.stats) < 1.5
    # the cloth fell under gravity a little and the pins moved with the body
    assert seq.vertices[-1, :, 2].min() < skirt.rest_vertices[:, 2].min() + 0.01
    pen = np.array([s.penetration_max for s in seq.stats])
    # the exact mesh keeps cloth within a few mm (contact is a penalty); the
    # capsules only approximate the body, cm-level penetration is expected
    limit = 0.006 if collider == "mesh" else 0.08
    assert pen.max() < limit, pen
    assert seq.seconds_per_frame > 0


@pytest.mark.slow  # a few seconds once the kernels are compiled
def test_a_settled_state_is_reused_with_the_same_result(body, skirt):
    """Sequences that start at the same pose settle the same way: reusing the settled
    cloth skips the settle and gives bit-identical frames (the solver is deterministic)."""
    t = 4
    rot = np.zeros((2, t, 24, 3), np.float32)
    rot[0, :, 1, 0] = -0.4 * np.linspace(0.0, 1.0, t)  # left leg forward
    rot[1, :, 0, 2] = 0.5 * np.linspace(0.0, 1.0, t)  # turn
    a, b = body.pose(rot[0]), body.pose(rot[1])
    settings = dataclasses.replace(ClothSimSettings(), substeps=5, iterations=3, settle_frames=2)
    first = simulate_garment(body, skirt, a, settings)
    full = simulate_garment(body, skirt, b, settings)
    reused = simulate_garment(body, skirt, b, settings, settled=first.settled)
    np.testing.assert_array_equal(full.vertices, reused.vertices)
    with pytest.raises(ValueError, match="settled"):
        other = body.pose(np.full((2, 24, 3), 0.1, np.float32))
        simulate_garment(body, skirt, other, settings, settled=first.settled)


def _walk_and_turn(body, t: int, yaw: float = 0.0, shift=(0.0, 0.0, 0.0)):
    """A short motion that walks forward (the root frame moves) and lifts a leg, the whole of it
    turned by ``yaw`` about the vertical and moved by ``shift``; the (3, 3) turn."""
    from scipy.spatial.transform import Rotation

    rot = np.zeros((t, 24, 3), np.float32)
    rot[:, 1, 0] = -0.5 * np.linspace(0.0, 1.0, t)  # left leg forward
    trans = np.zeros((t, 3), np.float32)
    trans[:, 1] = -0.03 * np.arange(t)  # 0.75 m/s at 25 fps
    turn = Rotation.from_euler("z", yaw)
    rot[:, 0] = (turn * Rotation.from_rotvec(rot[:, 0])).as_rotvec()
    trans = turn.apply(trans) + np.asarray(shift)
    return body.pose(rot, trans.astype(np.float32)), turn.as_matrix()


@pytest.mark.slow  # a few seconds once the kernels are compiled
@pytest.mark.parametrize("kc_gain", [0.0, 4.0])
def test_a_simulation_continues_from_its_final_state_bit_identically(body, skirt, kc_gain):
    """Simulating frames 0..T-1 in one call equals simulating 0..m, then m..T-1 from the first call's
    final state: positions, velocities, the moving root frame's velocity and the air's carry over
    (with the low-KC drag, each vertex's excursion too)."""
    from pocoloco.synth.config import SynthConfig
    from pocoloco.synth.pipeline import cloth_settings

    settings = dataclasses.replace(cloth_settings(SynthConfig(), "skirt"), substeps=3, iterations=3, settle_frames=2,
                                   air_drag_kc_gain=kc_gain)  # fmt: skip
    assert settings.frame == "root" and settings.air_drag_normal > 0  # the state a continuation needs
    posed, _ = _walk_and_turn(body, 7)
    full = simulate_garment(body, skirt, posed, settings)
    m = 3
    head = simulate_garment(body, skirt, _slice(posed, 0, m + 1), settings)
    tail = simulate_garment(body, skirt, _slice(posed, m, 7), settings, settled=head.final)
    np.testing.assert_array_equal(head.vertices, full.vertices[: m + 1])
    np.testing.assert_array_equal(tail.vertices, full.vertices[m:])
    assert np.linalg.norm(head.final.frame_velocity) == pytest.approx(0.75, rel=0.05)
    if kc_gain > 0.0:  # the excursions are part of the state: without them the drag differs
        assert head.final.drag_excursion.shape == (len(skirt.rest_vertices), 4)
        assert np.abs(head.final.drag_excursion[:, 3]).max() > 0.0
        forgot = simulate_garment(body, skirt, _slice(posed, m, 7), settings,
                                  settled=dataclasses.replace(head.final, drag_excursion=None))  # fmt: skip
        assert np.abs(forgot.vertices[-1] - full.vertices[-1]).max() > 1e-6
    else:
        assert head.final.drag_excursion is None
    # without the frame's velocity the continuation goes wrong: the cloth would be thrown back
    lost = dataclasses.replace(head.final, frame_velocity=None)
    wrong = simulate_garment(body, skirt, _slice(posed, m, 7), settings, settled=lost)
    assert np.abs(wrong.vertices[-1] - full.vertices[-1]).max() > 1e-3


@pytest.mark.slow
@pytest.mark.parametrize("kc_gain", [0.0, 4.0])
def test_a_turned_state_continues_as_the_turned_motion_would(body, skirt, kc_gain):
    """The same motion turned about the vertical (and moved): continuing the unturned run's state,
    turned, gives the turned run's cloth to rounding (the physics has no preferred heading; the
    low-KC drag's excursions turn with it)."""
    from pocoloco.synth.config import SynthConfig
    from pocoloco.synth.pipeline import cloth_settings

    settings = dataclasses.replace(cloth_settings(SynthConfig(), "skirt"), substeps=3, iterations=3, settle_frames=2,
                                   air_drag_kc_gain=kc_gain)  # fmt: skip
    straight, _ = _walk_and_turn(body, 6)
    turned, r = _walk_and_turn(body, 6, yaw=0.9, shift=(0.4, -0.2, 0.0))
    m = 3
    head = simulate_garment(body, skirt, _slice(straight, 0, m + 1), settings)
    full = simulate_garment(body, skirt, turned, settings)
    state = head.final.turned(r, turned.vertices[m])
    tail = simulate_garment(body, skirt, _slice(turned, m, 6), settings, settled=state)
    err = np.linalg.norm(tail.vertices - full.vertices[m:], axis=-1)
    assert err.max() < 2e-3, err.max()  # metres: rounding, not another swing
    expected = (head.vertices[-1] - straight.joints[m, 0]) @ r.T + turned.joints[m, 0]
    np.testing.assert_allclose(tail.vertices[0], expected, atol=1e-5)


def _slice(posed, a: int, b: int):
    return type(posed)(posed.vertices[a:b], posed.joints[a:b], posed.vtransf[a:b])


@pytest.mark.slow  # ~30 s of self-contact kernel compilation on a fresh warp cache, ~10 s after
def test_self_contact_keeps_the_cloth_from_crossing_itself(body):
    """A wide maxi skirt folds while it settles; without self-contact its folds pass
    through each other, with it (almost) none do, and the cloth stays off the body."""
    from pocoloco.synth.garments import self_intersections

    g = make_garment("maxi_skirt", body, resolution=0.4, flare=0.5)
    posed = body.pose(np.zeros((2, 24, 3), np.float32))
    base = dataclasses.replace(ClothSimSettings(), substeps=5, iterations=3, settle_frames=8)
    counts = {}
    for sc in (False, True):
        seq = simulate_garment(body, g, posed, dataclasses.replace(base, self_contact=sc))
        assert np.isfinite(seq.vertices).all() and seq.reset_count == 0
        assert max(s.penetration_max for s in seq.stats) < 0.01
        counts[sc] = self_intersections(seq.vertices[-1], g.faces)
    assert counts[False] > 20 and counts[True] <= counts[False] / 4, counts


@pytest.mark.slow  # a few seconds once the kernels are compiled
def test_the_root_frame_simulates_the_same_physics(body, skirt):
    """A body walking forward: simulated in the world or in a frame translating with the
    pelvis (velocities corrected when the frame's changes), the cloth ends up the same.
    (Slowly: the world frame places the body's contacts one substep late, which is
    ~1 mm here but centimetres at running speed; the root frame has no such lag.)"""
    t = 8
    rot = np.zeros((t, 24, 3), np.float32)
    rot[:, 1, 0] = -0.3 * np.linspace(0.0, 1.0, t)
    trans = np.zeros((t, 3), np.float32)
    trans[:, 1] = -0.012 * np.arange(t)  # 0.3 m/s forward (-Y)
    posed = body.pose(rot, trans)
    base = dataclasses.replace(ClothSimSettings(), substeps=10, iterations=3, settle_frames=2)
    world = simulate_garment(body, skirt, posed, base)
    root = simulate_garment(body, skirt, posed, dataclasses.replace(base, frame="root"))
    moved = np.linalg.norm(world.vertices[-1] - world.vertices[0], axis=1).mean()
    assert moved > 0.05  # the skirt travelled with the body
    assert np.abs(world.vertices - root.vertices).max() < 0.005
    with pytest.raises(ValueError, match="frame"):
        simulate_garment(body, skirt, posed, dataclasses.replace(base, frame="pelvis"))


@pytest.mark.slow  # a few seconds once the kernels are compiled
def test_self_contact_that_tears_the_cloth_is_switched_off(body, skirt):
    """Self-contact with a tiny reach cannot follow a fast spin (its divide-and-truncate
    bound caps the cloth's speed): the cloth tears, the last good state is restored and
    the sequence finishes without self-contact."""
    t = 10
    rot = np.zeros((t, 24, 3), np.float32)
    rot[:, 0, 2] = 1.2 * np.maximum(np.arange(t) - 1, 0)  # 30 rad/s about the vertical from frame 2
    posed = body.pose(rot)
    settings = dataclasses.replace(ClothSimSettings(), substeps=5, iterations=3, settle_frames=1, self_contact=True,
                                   self_contact_margin=0.002, self_contact_gap=0.001, frame="root")  # fmt: skip
    seq = simulate_garment(body, skirt, posed, settings)
    assert seq.self_contact_off_from is not None and seq.reset_count >= 1
    assert np.isfinite(seq.vertices).all() and seq.stats[-1].stretch_max < 3.0


@pytest.mark.slow  # a few seconds once the kernels are compiled
@pytest.mark.parametrize("setup", [dict(), dict(collider="capsules"), dict(self_contact=True, frame="root")])
def test_replayed_substep_graphs_give_the_same_bits(body, skirt, setup):
    """Each substep's kernels recorded once as a warp graph and replayed (the default) give
    bit for bit the frames of launching every kernel from Python, whatever the collider and
    with self-contact; every frame moved the cloth (a replay that ran nothing would not)."""
    t = 5
    rot = np.zeros((t, 24, 3), np.float32)
    rot[:, 1, 0] = -0.4 * np.linspace(0.0, 1.0, t)  # left leg forward
    rot[:, 0, 2] = 0.3 * np.linspace(0.0, 1.0, t)  # turning
    posed = body.pose(rot)
    base = dataclasses.replace(ClothSimSettings(**setup), substeps=4, iterations=2, settle_frames=1)
    assert base.replay_graphs
    replayed = simulate_garment(body, skirt, posed, base)
    launched = simulate_garment(body, skirt, posed, dataclasses.replace(base, replay_graphs=False))
    np.testing.assert_array_equal(replayed.vertices, launched.vertices)
    assert (np.abs(np.diff(replayed.vertices, axis=0)).max(axis=(1, 2)) > 1e-5).all()


@pytest.mark.slow  # a few seconds once the kernels are compiled
def test_air_drag_holds_the_skirt_back_the_same_in_either_frame(body, skirt):
    """A body walking forward fast: air drag (relative to still air) pulls the skirt back against
    the motion by the same amount whether simulated in the world or in the root frame, which sees the
    air move (were the air taken to move with the root frame, the root frame would show no lag)."""
    t = 8
    trans = np.zeros((t, 3), np.float32)
    trans[:, 1] = -0.06 * np.arange(t)  # 1.5 m/s forward (-Y)
    posed = body.pose(np.zeros((t, 24, 3), np.float32), trans)
    base = dataclasses.replace(ClothSimSettings(), substeps=10, iterations=3, settle_frames=2)
    drag = dict(air_drag_normal=1.0, air_drag_tangential=0.02)
    lag = {}
    for frame in ("world", "root"):
        for name, extra in (("still air", {}), ("drag", drag)):
            seq = simulate_garment(body, skirt, posed, dataclasses.replace(base, frame=frame, **extra))
            lag[frame, name] = float((seq.vertices[-1, :, 1] - posed.joints[-1, 0, 1]).mean())  # +Y: behind
    held_back = {f: lag[f, "drag"] - lag[f, "still air"] for f in ("world", "root")}
    assert min(held_back.values()) > 0.002, held_back
    assert abs(held_back["world"] - held_back["root"]) < 0.5 * max(held_back.values()), held_back
