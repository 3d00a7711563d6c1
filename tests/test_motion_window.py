"""The motion window: the last seconds of a skeleton sequence seen from its current frame."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pocoloco.data.motion_window import motion_window


def _walk(t: int = 60, fps: float = 25.0, speed=(0.8, 0.3), turn_rate: float = 0.7, seed: int = 0):
    """A skeleton that walks at ``speed`` (m/s on the ground) while turning at ``turn_rate`` rad/s,
    its limbs jittering: (T, 24, 3)."""
    rng = np.random.default_rng(seed)
    rest = rng.normal(scale=0.3, size=(24, 3))
    rest[0] = 0.0
    rest[1], rest[2] = (0.1, 0.0, -0.05), (-0.1, 0.0, -0.05)  # hips along x at rest
    out = np.zeros((t, 24, 3))
    for i in range(t):
        yaw = turn_rate * i / fps
        jitter = rng.normal(scale=0.01, size=rest.shape)
        jitter[:3] = 0.0  # the pelvis and hips move rigidly; the limbs jitter
        out[i] = Rotation.from_euler("z", yaw).apply(rest + jitter)
        out[i] += (speed[0] * i / fps, speed[1] * i / fps, 0.9)
    return out


def _slow_window(joints, t, fps, seconds, hz):
    """The window by loops: for each sample, interpolate the frames, express in the current frame."""
    n = int(round(seconds * hz)) + 1

    def at(time):
        f = min(max(time * fps, 0.0), len(joints) - 1)
        lo = int(math.floor(f))
        hi = min(lo + 1, len(joints) - 1)
        return (1 - (f - lo)) * joints[lo] + (f - lo) * joints[hi]

    def heading(j):
        axis = j[1] - j[2]
        return math.atan2(axis[1], axis[0])

    now = joints[t]
    inv = Rotation.from_euler("z", -heading(now))
    out_j, out_v, out_w = [], [], []
    for k in range(n):
        time = t / fps - k / hz
        a, b = at(time), at(time - 1 / hz)
        out_j.append(inv.apply(a - now[0]))
        out_v.append(inv.apply((a[0] - b[0]) * hz))
        d = heading(a) - heading(b)
        out_w.append(((d + math.pi) % (2 * math.pi) - math.pi) * hz)
    return np.array(out_j), np.array(out_v), np.array(out_w)


@pytest.mark.parametrize("t", [0, 7, 30, 59])
def test_the_window_matches_a_loop_reference(t):
    joints = _walk()
    w = motion_window(joints, t, 25.0, seconds=2.0, hz=8.0)
    ref_j, ref_v, ref_w = _slow_window(joints, t, 25.0, 2.0, 8.0)
    assert w.joints.shape == (17, 24, 3) and w.root_velocity.shape == (17, 3) and w.yaw_rate.shape == (17,)
    np.testing.assert_allclose(w.joints, ref_j, atol=1e-5)
    np.testing.assert_allclose(w.root_velocity, ref_v, atol=1e-4)
    np.testing.assert_allclose(w.yaw_rate, ref_w, atol=1e-4)


def test_turning_or_moving_the_whole_motion_changes_nothing():
    joints = _walk()
    moved = Rotation.from_euler("z", 2.3).apply(joints.reshape(-1, 3)).reshape(joints.shape) + (4.0, -1.0, 0.0)
    a, b = motion_window(joints, 45, 25.0), motion_window(moved, 45, 25.0)
    for x, y in zip((a.joints, a.root_velocity, a.yaw_rate), (b.joints, b.root_velocity, b.yaw_rate)):
        np.testing.assert_allclose(x, y, atol=1e-4)


def test_the_root_velocity_and_turn_rate_are_the_motions():
    w = motion_window(_walk(speed=(1.0, 0.0), turn_rate=0.5), 50, 25.0)
    # samples fully inside the motion: speed 1 m/s, turning at 0.5 rad/s
    assert np.linalg.norm(w.root_velocity[:10, :2], axis=1) == pytest.approx(np.ones(10), abs=1e-3)
    assert w.yaw_rate[:10] == pytest.approx(np.full(10, 0.5), abs=1e-3)
    assert np.abs(w.joints[0, 0]).max() < 1e-6  # now: the pelvis at the origin


def test_before_the_first_frame_the_window_holds_it():
    joints = _walk()
    w = motion_window(joints, 0, 25.0)
    assert np.abs(w.root_velocity).max() < 1e-6 and np.abs(w.yaw_rate).max() < 1e-6
    np.testing.assert_allclose(w.joints, np.repeat(w.joints[:1], 17, 0), atol=1e-6)


@pytest.mark.parametrize("bad, msg", [
    (dict(joints=np.zeros((10, 24))), "shape"),
    (dict(joints=np.full((10, 24, 3), np.nan)), "NaN"),
    (dict(fps=0.0), "fps"),
    (dict(seconds=-1.0), "seconds"),
    (dict(t=10), "outside"),
])  # fmt: skip
def test_bad_input_gives_one_line(bad, msg):
    args = dict(joints=_walk(10), t=3, fps=25.0, seconds=2.0)
    args.update(bad)
    with pytest.raises(ValueError, match=msg) as e:
        motion_window(**args)
    assert "\n" not in str(e.value)


def test_a_dataset_frames_window_ends_on_its_stored_skeleton(tiny_dataset):
    """The window of a stored frame, redrawn from the sequence's seed: its current sample is the
    frame's own skeleton (in its heading frame), and the first frame's reaches into the blend from rest."""
    from pocoloco.data.format import DatasetLayout, read_frame
    from pocoloco.synth.motion_windows import sequence_windows

    layout = DatasetLayout(tiny_dataset)
    seq = sorted(p.name for p in (tiny_dataset / "subjects" / "skirt" / "test").iterdir() if p.is_dir())[0]
    windows = sequence_windows(tiny_dataset, "skirt", "test", seq)
    frame = read_frame(layout.frame_path("skirt", "test", seq, 3))
    joints = frame.joints.astype(np.float64)
    axis = joints[1] - joints[2]
    expected = Rotation.from_euler("z", -math.atan2(axis[1], axis[0])).apply(joints - joints[0])
    np.testing.assert_allclose(windows[3].joints[0], expected, atol=2e-4)
    assert len({w.joints.shape for w in windows}) == 1
    # two seconds back from the first stored frame lie in the blend from rest and before it
    assert np.abs(windows[0].joints[-1] - windows[0].joints[0]).max() > 1e-3
