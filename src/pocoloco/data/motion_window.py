"""The last seconds of a body's motion, seen from the current frame (issue 41's motion window).

What decides a garment's swing is the motion before the frame: where the root travelled and turned
over the last second or two, how the legs moved. ``motion_window`` cuts that out of a skeleton
sequence: ``samples`` instants going back ``seconds`` from frame ``t`` (``hz`` per second, the
current frame included), each as the 24 joints in the **current frame's heading frame** (origin at
the current pelvis, x along the current hip axis projected on the ground, z up), with the root's
linear velocity in that frame and its yaw rate. Turning or moving the whole motion about the
vertical leaves the window unchanged; a window reaching before the sequence holds its first frame
(a synthetic motion starts at rest).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..utils.atomic import save_npz_atomic
from .frame import load_npz

PELVIS, LEFT_HIP, RIGHT_HIP = 0, 1, 2
#: the default window: 2 s of motion at 8 samples per second (issue 41; Dyco uses 1.5 s at 4 Hz)
DEFAULT_SECONDS, DEFAULT_HZ = 2.0, 8.0


@dataclass(frozen=True)
class MotionWindow:
    """joints: (S, J, 3) float32, metres, in the current heading frame, S = samples (index 0 = now,
    then back in time); root_velocity: (S, 3) the pelvis' velocity there (m/s, over the previous
    sample interval); yaw_rate: (S,) the heading's turn rate (rad/s, same interval)."""

    joints: np.ndarray
    root_velocity: np.ndarray
    yaw_rate: np.ndarray


def _check(joints: np.ndarray, fps: float, seconds: float, hz: float) -> np.ndarray:
    j = np.asarray(joints)
    if j.ndim != 3 or j.shape[2] != 3 or j.shape[1] <= RIGHT_HIP or j.shape[0] < 1:
        raise ValueError(f"motion: expected joints of shape (T, J, 3) with T >= 1 and J >= 3, got {j.shape}")
    if not np.isfinite(j).all():
        raise ValueError("motion: the joints contain NaN or inf")
    for name, v in (("fps", fps), ("seconds", seconds), ("hz", hz)):
        if not np.isfinite(v) or v <= 0:
            raise ValueError(f"motion: {name} must be a positive number, got {v}")
    return j.astype(np.float64)


def _heading(joints: np.ndarray) -> np.ndarray:
    """(...,) yaw of the hip axis (left minus right hip) on the ground plane, radians."""
    axis = joints[..., LEFT_HIP, :] - joints[..., RIGHT_HIP, :]
    return np.arctan2(axis[..., 1], axis[..., 0])


def _at(joints: np.ndarray, times: np.ndarray, fps: float) -> np.ndarray:
    """(len(times), J, 3): the sequence linearly interpolated at ``times`` seconds (clamped to it)."""
    f = np.clip(np.asarray(times) * fps, 0.0, len(joints) - 1)
    lo = np.floor(f).astype(int)
    hi = np.minimum(lo + 1, len(joints) - 1)
    a = (f - lo)[:, None, None]
    return (1.0 - a) * joints[lo] + a * joints[hi]


def window_samples(seconds: float = DEFAULT_SECONDS, hz: float = DEFAULT_HZ) -> int:
    """S: the samples of a window (the current one included), 17 for 2 s at 8 Hz."""
    return int(round(seconds * hz)) + 1


def motion_window(joints: np.ndarray, t: int, fps: float, seconds: float = DEFAULT_SECONDS, hz: float = DEFAULT_HZ,
                  lag: float = 0.0) -> MotionWindow:  # fmt: skip
    """The window of frame ``t`` of ``joints`` (T, J, 3) world positions (z up) at ``fps``: samples at
    ``t / fps - k / hz`` for k = 0 .. round(seconds * hz) (17 for the default 2 s at 8 Hz); ``lag``
    seconds shift every past sample (k >= 1) further back (training's jitter)."""
    j = _check(joints, fps, seconds, hz)
    if not (0 <= t < len(j)):
        raise ValueError(f"motion: frame {t} is outside the sequence of {len(j)} frames")
    times = t / fps - np.arange(window_samples(seconds, hz)) / hz
    times[1:] -= lag
    now = j[t]
    psi = _heading(now)
    c, s = np.cos(-psi), np.sin(-psi)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> heading frame
    here = _at(j, times, fps)
    before = _at(j, times - 1.0 / hz, fps)
    local = (here - now[PELVIS]) @ turn.T
    velocity = (here[:, PELVIS] - before[:, PELVIS]) * hz @ turn.T
    yaw = np.angle(np.exp(1j * (_heading(here) - _heading(before)))) * hz  # wrapped to (-pi, pi]
    return MotionWindow(local.astype(np.float32), velocity.astype(np.float32), yaw.astype(np.float32))


def check_motion_training(motion_window: float, history_dropout: float, motion_lr_scale: float) -> None:
    """One-line ValueErrors for a training run's motion options (PocoLoco's and POP's configs)."""
    if not (np.isfinite(motion_window) and 0 <= motion_window <= 10):
        raise ValueError(f"motion_window must be between 0 and 10 seconds, got {motion_window}")
    if not 0 <= history_dropout < 1:
        raise ValueError(f"history_dropout must be in [0, 1), got {history_dropout}")
    if not (np.isfinite(motion_lr_scale) and motion_lr_scale > 0):
        raise ValueError(f"motion_lr_scale must be > 0, got {motion_lr_scale}")


def motion_features(window: MotionWindow, turn: float, scale: float) -> np.ndarray:
    """(J, F) float32 per-joint features of a window for a network (F = 7 S - 3, 116 for 17 samples):
    joint j's past positions relative to its current one (S - 1 samples x 3), then the root's
    velocity (S x 3) and yaw rate (S), the same for every joint. Directions are turned by ``turn``
    radians about +Z out of the heading frame (into the network's point frame: the current heading
    minus the angle the normalisation turns away), lengths divided by ``scale`` (its std). A body at
    rest has all-zero features."""
    S, J = window.joints.shape[:2]
    c, s = np.cos(turn), np.sin(turn)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    joints = window.joints.astype(np.float64) @ rot.T / scale  # (S, J, 3)
    deltas = (joints[1:] - joints[:1]).transpose(1, 0, 2).reshape(J, -1)  # (J, 3 (S - 1))
    root = np.concatenate([(window.root_velocity.astype(np.float64) @ rot.T / scale).reshape(-1),
                           window.yaw_rate.astype(np.float64)])  # (4 S,); fmt: skip
    return np.concatenate([deltas, np.broadcast_to(root, (J, root.size))], axis=1).astype(np.float32)


def motion_feature_dim(samples: int) -> int:
    """F of :func:`motion_features` for windows of ``samples`` samples."""
    return 7 * samples - 3


def heading_of(joints: np.ndarray) -> float:
    """The yaw (radians) of a (J, 3) pose's hip axis: the heading frame :func:`motion_window` uses."""
    return float(_heading(np.asarray(joints, np.float64)))


@dataclass(frozen=True)
class MotionHistory:
    """A sequence's whole body motion: joints (T, J, 3) float32 world positions (metres, z up) at
    ``fps``; the sequence's stored frame i is row ``first + i`` (the rows before it are the motion
    the simulation ran before the first stored frame: warm-up, blend from rest). ``padded``: the
    history only starts at the first stored frame (a dataset without a ``motion_history.npz``), so
    windows reaching earlier hold that frame."""

    joints: np.ndarray
    fps: float
    first: int
    padded: bool = False

    def window(self, frame: int, seconds: float = DEFAULT_SECONDS, hz: float = DEFAULT_HZ,
               lag: float = 0.0) -> MotionWindow:  # fmt: skip
        """The window of stored frame ``frame``."""
        return motion_window(self.joints, self.first + int(frame), self.fps, seconds, hz, lag)


def augmented_window(history: MotionHistory, frame: int, seconds: float, rng: np.random.Generator) -> MotionWindow:
    """Training's augmentation of stored frame ``frame``'s window (issue 41): the window's time
    warped by a factor in [0.85, 1.15] (the same number of samples over 0.85-1.15 x ``seconds``),
    its past samples shifted by -1, 0 or +1 frame, and 5 mm of noise on their joints."""
    warp = rng.uniform(0.85, 1.15)
    lag = int(rng.integers(-1, 2)) / history.fps
    window = history.window(frame, seconds * warp, DEFAULT_HZ / warp, lag)
    noisy = window.joints.copy()
    noisy[1:] += rng.normal(0.0, 0.005, noisy[1:].shape).astype(np.float32)
    return MotionWindow(noisy, window.root_velocity, window.yaw_rate)


def write_motion_history(path: str | os.PathLike, history: MotionHistory) -> None:
    """Write ``motion_history.npz`` atomically after checking it."""
    j = _check(history.joints, history.fps, 1.0, 1.0).astype(np.float32)
    if not 0 <= history.first < len(j):
        raise ValueError(f"{os.fspath(path)}: first stored frame {history.first} outside the {len(j)}-frame history")
    save_npz_atomic(path, joints=j, fps=np.float64(history.fps), first=np.int64(history.first))


def read_motion_history(path: str | os.PathLike) -> MotionHistory:
    """Read ``motion_history.npz``; one-line ValueErrors for missing keys or bad values."""
    src = os.fspath(path)
    names, raw = load_npz(src, ("joints", "fps", "first"))
    for k in ("joints", "fps", "first"):
        if k not in names:
            raise ValueError(f"{src}: missing key '{k}'")
    try:
        j = _check(raw["joints"], float(raw["fps"]), 1.0, 1.0).astype(np.float32)
    except ValueError as e:
        raise ValueError(f"{src}: {e}") from None
    first = int(raw["first"])
    if not 0 <= first < len(j):
        raise ValueError(f"{src}: first stored frame {first} outside the {len(j)}-frame history")
    return MotionHistory(j, float(raw["fps"]), first)
