"""Tests for procedural motions (pocoloco.synth.motion)."""

from __future__ import annotations

import numpy as np
import pytest

from pocoloco.body.skeleton import JOINT_NAMES, MIRROR_PAIRS
from pocoloco.synth import motion as M
from pocoloco.synth.motion import (
    JOINT_LIMITS,
    MOTION_KINDS,
    Motion,
    generate_motion,
    pelvis_euler,
    pose_joints,
    rest_to_motion,
)

CONTACT = [JOINT_NAMES.index(n) for n in M.CONTACT_JOINTS]


@pytest.fixture(scope="module")
def body():
    from pocoloco.body.anny_body import AnnyBody

    return AnnyBody()


@pytest.fixture(scope="module")
def mixed(body):
    """A few motions over all kinds, both splits (about 1 s each)."""
    return [generate_motion(s, 125, split=sp, body=body) for s in (0, 1) for sp in ("train", "test")]


def _limits_array():
    return np.array([JOINT_LIMITS[n] for n in JOINT_NAMES])  # (J, 3, 2)


def test_limits_table_is_complete_and_mirrored():
    assert M.CLASSIC_KINDS == ("walk", "turn", "dance", "arm_swing", "squat", "kick", "spin")
    assert MOTION_KINDS == M.CLASSIC_KINDS + ("reach", "crouch", "jump", "run", "bend", "turn_in_place")
    assert set(JOINT_LIMITS) == set(JOINT_NAMES)
    lim = _limits_array()
    assert (lim[..., 0] < lim[..., 1]).all()
    assert (lim[..., 0] <= 0).all() and (lim[..., 1] >= 0).all()  # the rest pose is allowed
    for l, r in MIRROR_PAIRS:
        np.testing.assert_allclose(lim[r, 0], lim[l, 0])  # x unchanged
        np.testing.assert_allclose(lim[r, 1:], -lim[l, 1:, ::-1])  # y, z negated


def test_params_train_and_test_bands_are_disjoint():
    tr = M._Params(np.random.default_rng(0), "train")
    te = M._Params(np.random.default_rng(0), "test")
    a = np.array([tr(0.0, 1.0) for _ in range(2000)])
    b = np.array([te(0.0, 1.0) for _ in range(2000)])
    assert ((a // 0.25) % 2 == 0).all() and ((b // 0.25) % 2 == 1).all()
    assert a.min() < 0.1 and a.max() > 0.65 and b.min() < 0.35 and b.max() > 0.9  # span the range


def test_all_frames_within_joint_limits(mixed):
    lim = _limits_array()
    for m in mixed:
        rv = m.joint_rotvecs[:, 1:].astype(np.float64)
        assert (rv >= lim[None, 1:, :, 0] - 1e-5).all() and (rv <= lim[None, 1:, :, 1] + 1e-5).all(), m.name
        pe = pelvis_euler(m.joint_rotvecs)  # (T, 3) pitch, roll, heading
        assert (pe >= lim[0, :, 0] - 1e-5).all() and (pe <= lim[0, :, 1] + 1e-5).all(), m.name


def test_clamp_enforces_limits():
    x = np.random.default_rng(0).normal(scale=3.0, size=(50, 24, 3))
    c = M.clamp_to_limits(x)
    lim = _limits_array()
    assert (c >= lim[..., 0]).all() and (c <= lim[..., 1]).all()
    inside = (x >= lim[..., 0]) & (x <= lim[..., 1])
    np.testing.assert_array_equal(c[inside], x[inside])


def test_shapes_segments_and_smoothness(mixed):
    for m in mixed:
        assert m.joint_rotvecs.shape == (125, 24, 3) and m.joint_rotvecs.dtype == np.float32
        assert m.root_translation.shape == (125, 3) and m.fps == 25.0
        assert m.segments[0][1] == 0 and m.segments[-1][2] == 125
        assert all(a[2] == b[1] for a, b in zip(m.segments, m.segments[1:]))
        assert all(k in MOTION_KINDS for name, _, _ in m.segments for k in name.split("+"))
        # joint angles (not the pelvis, which spins) change smoothly
        d1 = np.diff(m.joint_rotvecs[:, 1:], axis=0)
        d2 = np.diff(m.joint_rotvecs[:, 1:], 2, axis=0)
        assert np.abs(d1).max() < 0.4 and np.abs(d2).max() < 0.3, m.name
        # pelvis turns at most ~1.6 turns/s, root moves < 6 cm per frame
        from scipy.spatial.transform import Rotation

        r = Rotation.from_rotvec(m.joint_rotvecs[:, 0].astype(np.float64))
        assert (r[1:] * r[:-1].inv()).magnitude().max() < 0.45, m.name
        assert np.linalg.norm(np.diff(m.root_translation, axis=0), axis=1).max() < 0.06, m.name


def test_deterministic_and_splits_differ(body, mixed):
    again = generate_motion(0, 125, split="train", body=body)
    np.testing.assert_array_equal(again.joint_rotvecs, mixed[0].joint_rotvecs)
    np.testing.assert_array_equal(again.root_translation, mixed[0].root_translation)
    assert again.segments == mixed[0].segments
    train, test = mixed[0], mixed[1]
    assert test.name == "test_seed0" and train.name == "train_seed0"
    assert np.abs(train.joint_rotvecs - test.joint_rotvecs).max() > 0.3
    # test segments may mix an upper body from another kind; train never does
    names = [s[0] for m in mixed for s in m.segments]
    assert any("+" in n for n in names)
    assert not any("+" in s[0] for m in mixed if m.name.startswith("train") for s in m.segments)


def test_feet_on_the_ground(body, mixed):
    rest = body.zero_pose.joints[0, CONTACT, 2]
    ground = body.zero_pose.vertices[0, :, 2].min()
    for m in mixed[:2]:
        p = body.pose(m.joint_rotvecs[::6], m.root_translation[::6])
        lowest = (p.joints[:, CONTACT, 2] - rest).min(1)  # lowest contact vs its rest height
        assert np.abs(lowest).max() < 0.005, m.name
        # the sole neither floats nor sinks much (toes may point down a little)
        sole = p.vertices[..., 2].min(1) - ground
        assert sole.max() < 0.02 and sole.min() > -0.04, (m.name, sole.min(), sole.max())


def test_pose_joints_matches_body_pose(body, mixed):
    rv = mixed[1].joint_rotvecs[::15]
    np.testing.assert_allclose(pose_joints(body, rv, chunk=4), body.pose(rv).joints, atol=1e-5)


def test_walk_moves_forward_without_skating(body):
    m = generate_motion(3, 100, kinds=("walk",), body=body)
    heading = pelvis_euler(m.joint_rotvecs)[:, 2]
    forward = np.stack([np.sin(heading), -np.cos(heading)], -1)  # body faces -Y at heading 0
    step = np.diff(m.root_translation[:, :2], axis=0)
    assert (step * forward[1:]).sum() > 1.5  # metres in 4 s
    assert np.ptp(m.root_translation[:, 2]) > 0.01  # vertical bob
    # the lowest contact joint, while clearly lowest, stays put on the ground
    j = pose_joints(body, m.joint_rotvecs) + m.root_translation[:, None]
    c = j[:, CONTACT, 2] - body.zero_pose.joints[0, CONTACT, 2]
    low = c.argmin(1)  # contacts: left ankle, right ankle, left toes, right toes
    other_foot = np.where((low % 2 == 0)[:, None], c[:, [1, 3]], c[:, [0, 2]]).min(1)
    planted = (other_foot - c.min(1) > 0.03)[:-1] & (low[1:] == low[:-1])
    jc = j[:, CONTACT, :2]
    slide = np.linalg.norm(jc[1:][np.arange(99), low[:-1]] - jc[:-1][np.arange(99), low[:-1]], axis=1)
    assert planted.sum() > 10 and slide[planted].max() < 0.01


def test_squat_lowers_pelvis_and_spin_turns(body):
    sq = generate_motion(4, 75, kinds=("squat",), body=body)
    assert sq.root_translation[:, 2].min() < -0.15
    sp = generate_motion(5, 75, kinds=("spin",), body=body)
    pe = pelvis_euler(sp.joint_rotvecs)
    assert np.abs(np.unwrap(pe[:, 2])[-1]) > np.pi  # more than half a turn about Z
    assert np.abs(pe[:, :2]).max() < 0.1  # upright while spinning


def test_kinds_restrict_segments(body):
    m = generate_motion(6, 80, kinds=("kick", "dance"), body=body)
    assert {s[0] for s in m.segments} <= {"kick", "dance"}


def test_rest_to_motion(body, mixed):
    m = mixed[0]
    r = rest_to_motion(m, 20, body=body)
    assert r.num_frames == 145 and r.segments[0] == ("rest", 0, 20)
    assert r.segments[1:] == [(k, a + 20, b + 20) for k, a, b in m.segments]
    np.testing.assert_array_equal(r.joint_rotvecs[0], 0)
    np.testing.assert_allclose(r.root_translation[0], 0, atol=1e-6)
    np.testing.assert_array_equal(r.joint_rotvecs[20:], m.joint_rotvecs)
    # continuous positions and velocities across the join
    v_in = r.joint_rotvecs[20] - r.joint_rotvecs[19]
    v_out = r.joint_rotvecs[21] - r.joint_rotvecs[20]
    assert np.abs(v_in - v_out).max() < 0.05
    assert np.abs(np.diff(r.root_translation, axis=0)).max() < 0.06
    plain = rest_to_motion(m, 10)  # without a body: blended translation
    np.testing.assert_array_equal(plain.root_translation[10:], m.root_translation)
    np.testing.assert_array_equal(plain.root_translation[0], 0)
    with pytest.raises(ValueError, match="num_frames"):
        rest_to_motion(m, 0)


def test_save_load_roundtrip_and_errors(tmp_path, mixed):
    m = mixed[1]
    m.save(tmp_path / "m.npz")
    back = Motion.load(tmp_path / "m.npz")
    assert back.name == m.name and back.fps == m.fps and back.segments == m.segments
    np.testing.assert_array_equal(back.joint_rotvecs, m.joint_rotvecs)
    np.testing.assert_array_equal(back.root_translation, m.root_translation)
    np.savez(tmp_path / "bad.npz", joint_rotvecs=m.joint_rotvecs)
    with pytest.raises(ValueError, match="bad.npz.*missing keys"):
        Motion.load(tmp_path / "bad.npz")
    d = dict(np.load(tmp_path / "m.npz"))
    d["joint_rotvecs"] = d["joint_rotvecs"][:, :10]
    np.savez(tmp_path / "shape.npz", **d)
    with pytest.raises(ValueError, match="shape.npz.*joint_rotvecs"):
        Motion.load(tmp_path / "shape.npz")
    with pytest.raises(ValueError, match="nope.npz"):
        Motion.load(tmp_path / "nope.npz")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(kinds=("walk", "moonwalk")), "unknown motion kinds"),
        (dict(kinds=()), "kinds must not be empty"),
        (dict(split="val"), "unknown motion style"),
        (dict(num_frames=0), "num_frames"),
        (dict(num_frames=-5), "num_frames"),
        (dict(seed=-1), "seed"),
        (dict(fps=0.0), "fps"),
    ],
)
def test_generate_motion_errors(kwargs, match):
    args = dict(seed=0, num_frames=10) | kwargs
    with pytest.raises(ValueError, match=match):
        generate_motion(**args)


@pytest.mark.parametrize("kind", ["reach", "crouch", "jump", "run", "bend", "turn_in_place"])
def test_new_kinds_stay_in_limits_grounded_and_do_what_they_say(body, kind):
    """The data-v2 kinds: within joint limits, feet never below the ground (<= 5 mm), and each one's
    signature: arms held forward, a deep crouch, real flight, fast travel, a deep bend, a turn."""
    lim = _limits_array()
    rest = body.zero_pose.joints[0, CONTACT, 2]
    for split in ("train", "test"):
        m = generate_motion(5, 150, split=split, kinds=(kind,), body=body)
        assert np.isfinite(m.joint_rotvecs).all() and np.isfinite(m.root_translation).all()
        local = m.joint_rotvecs[:, 1:]
        assert (local >= lim[1:, :, 0] - 1e-5).all() and (local <= lim[1:, :, 1] + 1e-5).all()
        j = pose_joints(body, m.joint_rotvecs) + m.root_translation[:, None]
        low = (j[:, CONTACT, 2] - rest).min(1)  # lowest contact above its rest height (m)
        assert low.min() > -0.005, (kind, split, low.min())
        r = m.joint_rotvecs
        left_shoulder, left_hip = JOINT_NAMES.index("left_shoulder"), JOINT_NAMES.index("left_hip")
        pelvis_drop = j[0, 0, 2] - j[:, 0, 2].min()
        if kind == "reach":  # an arm held forward (shoulder flexion) for a third of the segment or more
            forward = -np.minimum(r[:, left_shoulder, 0], r[:, JOINT_NAMES.index("right_shoulder"), 0])
            assert (forward > 0.7).mean() > 0.3, forward.max()
        elif kind == "crouch":
            assert pelvis_drop > 0.2 and -r[:, left_hip, 0].min() > 1.0
        elif kind == "jump":
            assert low.max() > 0.05  # both feet off the ground
        elif kind == "run":
            assert np.linalg.norm(m.root_translation[-1, :2] - m.root_translation[0, :2]) > 2.0
        elif kind == "bend":
            spine = JOINT_NAMES.index("spine1")
            assert np.abs(r[:, spine, :2]).max() > 0.1
        else:
            heading = np.unwrap(pelvis_euler(r)[:, 2])
            assert np.abs(heading - heading[0]).max() > 0.6 * np.pi / 2
