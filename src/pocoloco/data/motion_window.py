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

from dataclasses import dataclass

import numpy as np

PELVIS, LEFT_HIP, RIGHT_HIP = 0, 1, 2


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


def motion_window(joints: np.ndarray, t: int, fps: float, seconds: float = 2.0, hz: float = 8.0) -> MotionWindow:
    """The window of frame ``t`` of ``joints`` (T, J, 3) world positions (z up) at ``fps``: samples at
    ``t / fps - k / hz`` for k = 0 .. round(seconds * hz) (17 for the default 2 s at 8 Hz)."""
    j = _check(joints, fps, seconds, hz)
    if not (0 <= t < len(j)):
        raise ValueError(f"motion: frame {t} is outside the sequence of {len(j)} frames")
    times = t / fps - np.arange(int(round(seconds * hz)) + 1) / hz
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
