"""Procedural motions for the 24-joint skeleton, posed on the anny body.

The LOOSE captures the papers train on are 25 fps recordings of people walking,
turning, dancing and moving their limbs, with separate (different) recordings
for train and test. No motion-capture data ships under a clean licence, so
pocoloco synthesises motions: a :class:`Motion` is a chain of segments of
different kinds (``MOTION_KINDS``), each a smooth periodic or enveloped
function of time with random parameters drawn from a seed, joined by
0.5 s smoothstep cross-fades of the joint angles and heading rates.

Conventions (see ``pocoloco.body.anny_body``): metres, Z up, the body faces -Y
at rest, +X is its left. Rotations are axis-angle vectors in anny's
``local-ref`` axes (world axes at rest, carried along by the parent bone):

=============  ==========================================================
joint          meaning of the rotation-vector components (left side)
=============  ==========================================================
pelvis         global orientation = Rz(heading) Rx(pitch) Ry(roll)
               (intrinsic ZXY Euler; +pitch tips the body forward)
hips           -x flexes the leg forward, -y abducts (left), z twists
knees          +x flexes (shank goes back)
ankles         +x plantar-flexes (toes down), -x dorsi-flexes
spine, neck    +x bends forward, y bends sideways, z twists
shoulders      -x swings the arm forward, -y raises it sideways (left)
elbows         flexion about a fixed axis of the A-pose forearm plane
=============  ==========================================================

Right-side joints mirror the left (the y and z components change sign).

Root translation is not scripted: after posing the body (``AnnyBody.pose``),
the vertical offset keeps the lowest of the four contact joints (ankles and
toe joints) at its rest height, and the horizontal offset keeps that lowest
contact where it was on the previous frame (foot locking). Walking therefore
moves the body forward along its heading with a natural vertical bob, squats
lower the pelvis, feet neither float nor sink (< 5 mm), and a foot that is
clearly planted does not skate (< 1 cm/frame; some slip remains in the brief
double support of a walk, where both feet touch while the legs still move).

Train and test motions differ in content (documented in ``generate_motion``).

Why this module is long: every motion kind is a short closed-form function of time, and they are
kept together with the chaining, cross-fades and foot locking that make them one motion model.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ..body.anny_body import AnnyBody
from ..body.skeleton import JOINT_NAMES, NUM_JOINTS

#: The motion kinds of the first datasets (``tiny``, ``small``): ``generate_motion``'s default.
CLASSIC_KINDS: tuple[str, ...] = ("walk", "turn", "dance", "arm_swing", "squat", "kick", "spin")
#: Every motion kind: the classic ones plus reaching / arms held forward, crouching and sitting-like
#: poses, jumps (with flight), running, bending over, and turning in place on the spot.
MOTION_KINDS: tuple[str, ...] = CLASSIC_KINDS + ("reach", "crouch", "jump", "run", "bend", "turn_in_place")
#: the two motion styles: training motions, and test-style ones (a dataset's test and held-out splits)
MOTION_STYLES: tuple[str, ...] = ("train", "test")

#: Seconds of the smoothstep cross-fade between consecutive segments.
TRANSITION_SECONDS = 0.5
#: Range of segment durations in seconds (the last segment may be cut short).
SEGMENT_SECONDS = (2.0, 4.0)
#: Softmin temperature (metres) that picks the lowest contact joint smoothly.
CONTACT_TEMPERATURE = 0.005

_PI = float(np.pi)


def _mirror(limits: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
    """Left-side limits -> right-side limits (y and z components change sign)."""
    (xl, xh), (yl, yh), (zl, zh) = limits
    return ((xl, xh), (-yh, -yl), (-zh, -zl))


# Per-joint limits (radians) on the rotation-vector components (x, y, z) in
# anny local-ref axes. For the pelvis they bound (pitch, roll, heading) of the
# ZXY Euler decomposition instead; heading is free (wraps to [-pi, pi]).
# Left side given; right side mirrored. Ranges are conservative human ranges
# of motion measured from anny's A-pose (elbow already flexed ~42 deg, arms
# ~42 deg abducted).
_LEFT_LIMITS: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    "hip": ((-2.0, 0.6), (-0.8, 0.35), (-0.6, 0.6)),  # flexion to 115 deg, extension 35
    "knee": ((0.0, 2.4), (-0.1, 0.1), (-0.2, 0.2)),  # flexion only
    "ankle": ((-0.7, 0.8), (-0.3, 0.3), (-0.3, 0.3)),  # dorsi 40 deg / plantar 45 deg
    "foot": ((-0.6, 0.4), (-0.1, 0.1), (-0.1, 0.1)),  # toes
    "collar": ((-0.3, 0.3), (-0.3, 0.3), (-0.3, 0.3)),
    "shoulder": ((-2.6, 1.0), (-1.8, 0.6), (-1.0, 1.0)),  # forward 150 deg, up 100 deg
    "elbow": ((-1.6, 0.6), (-0.2, 0.2), (-1.5, 0.5)),  # box around flexion -0.7..2.1 rad
    "wrist": ((-0.6, 0.6), (-0.6, 0.6), (-0.6, 0.6)),
    "hand": ((-0.3, 0.3), (-0.3, 0.3), (-0.3, 0.3)),
}
_CENTRE_LIMITS = {
    "pelvis": ((-0.35, 0.35), (-0.3, 0.3), (-_PI, _PI)),  # pitch, roll, heading
    "spine1": ((-0.3, 0.5), (-0.3, 0.3), (-0.4, 0.4)),
    "spine2": ((-0.3, 0.5), (-0.3, 0.3), (-0.4, 0.4)),
    "spine3": ((-0.3, 0.5), (-0.3, 0.3), (-0.4, 0.4)),
    "neck": ((-0.5, 0.6), (-0.4, 0.4), (-0.7, 0.7)),
    "head": ((-0.4, 0.5), (-0.3, 0.3), (-0.6, 0.6)),
}

#: Per joint name: ((x_lo, x_hi), (y_lo, y_hi), (z_lo, z_hi)) in radians.
#: Bounds each component of the joint's rotation vector; for the pelvis the
#: three entries bound (pitch, roll, heading) instead (see module docstring).
JOINT_LIMITS: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {}
for _name in JOINT_NAMES:
    if _name in _CENTRE_LIMITS:
        JOINT_LIMITS[_name] = _CENTRE_LIMITS[_name]
    else:
        _side, _base = _name.split("_", 1)
        _lim = _LEFT_LIMITS[_base]
        JOINT_LIMITS[_name] = _lim if _side == "left" else _mirror(_lim)

_LIMITS = np.array([JOINT_LIMITS[n] for n in JOINT_NAMES], dtype=np.float64)  # (J, 3, 2)
_J = {n: i for i, n in enumerate(JOINT_NAMES)}
#: Contact joints that keep the body on the ground.
CONTACT_JOINTS: tuple[str, ...] = ("left_ankle", "right_ankle", "left_foot", "right_foot")
_CONTACT = [_J[n] for n in CONTACT_JOINTS]
#: Joints the test split may take from a second motion kind ("mixed" segments).
UPPER_BODY_JOINTS: tuple[str, ...] = tuple(
    n for n in JOINT_NAMES
    if n.startswith(("spine", "neck", "head")) or n.split("_")[-1] in ("collar", "shoulder", "elbow", "wrist", "hand")
)  # fmt: skip
_UPPER = [_J[n] for n in UPPER_BODY_JOINTS]
#: Elbow flexion axis of the left arm (unit, anny local-ref), normal to the
#: plane of the A-pose upper arm and forearm; the right arm mirrors it.
_ELBOW_AXIS_LEFT = np.array([-0.743, -0.047, -0.667])


@dataclass
class Motion:
    """A joint-angle sequence for the 24-joint skeleton.

    name:             identifier, e.g. ``"train_seed3"``.
    fps:              frames per second.
    joint_rotvecs:    (T, J, 3) float32 axis-angle per joint (anny local-ref
                      axes; joint 0 is the global orientation).
    root_translation: (T, 3) float32 metres added to the posed body.
    segments:         (kind, start_frame, end_frame) per segment, covering
                      [0, T) without overlap; cross-fades are centred on the
                      boundaries. Test motions may have mixed kinds such as
                      ``"walk+dance"`` (lower body + upper body); frames
                      prepended by :func:`rest_to_motion` have kind ``"rest"``.
    """

    name: str
    fps: float
    joint_rotvecs: np.ndarray
    root_translation: np.ndarray
    segments: list[tuple[str, int, int]] = field(default_factory=list)

    def __post_init__(self):
        self.joint_rotvecs = np.asarray(self.joint_rotvecs, dtype=np.float32)
        self.root_translation = np.asarray(self.root_translation, dtype=np.float32)
        t = self.joint_rotvecs.shape[0] if self.joint_rotvecs.ndim == 3 else -1
        if self.joint_rotvecs.shape != (t, NUM_JOINTS, 3):
            raise ValueError(f"joint_rotvecs must have shape (T, {NUM_JOINTS}, 3), got {self.joint_rotvecs.shape}")
        if self.root_translation.shape != (t, 3):
            raise ValueError(f"root_translation must have shape ({t}, 3), got {self.root_translation.shape}")
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        self.segments = [(str(k), int(a), int(b)) for k, a, b in self.segments]

    @property
    def num_frames(self) -> int:
        return int(self.joint_rotvecs.shape[0])

    def save(self, path: str | os.PathLike) -> None:
        """Write an ``.npz`` (numpy adds the suffix if it is missing)."""
        np.savez(
            path,
            name=np.array(self.name),
            fps=np.array(self.fps, dtype=np.float64),
            joint_rotvecs=self.joint_rotvecs,
            root_translation=self.root_translation,
            segment_kinds=np.array([s[0] for s in self.segments], dtype=str),
            segment_frames=np.array([s[1:] for s in self.segments], dtype=np.int64).reshape(-1, 2),
        )

    @classmethod
    def load(cls, path: str | os.PathLike) -> Motion:
        """Read a file written by :meth:`save`; one-line errors name the file."""
        keys = ("name", "fps", "joint_rotvecs", "root_translation", "segment_kinds", "segment_frames")
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [k for k in keys if k not in z.files]
                if missing:
                    raise ValueError(f"{path}: not a motion file, missing keys {missing}")
                d = {k: z[k] for k in keys}
        except (OSError, EOFError) as e:
            raise ValueError(f"{path}: cannot read motion file ({e})") from None
        if d["segment_frames"].shape != (len(d["segment_kinds"]), 2):
            raise ValueError(f"{path}: segment_frames has shape {d['segment_frames'].shape}, expected (S, 2)")
        try:
            return cls(
                name=str(d["name"]),
                fps=float(d["fps"]),
                joint_rotvecs=d["joint_rotvecs"],
                root_translation=d["root_translation"],
                segments=[(str(k), int(a), int(b)) for k, (a, b) in zip(d["segment_kinds"], d["segment_frames"])],
            )
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None


# ----------------------------------------------------------------------------
# Parameter sampling: the train/test split lives here.


class _Params:
    """Draws segment parameters for one split.

    Every range [lo, hi] is cut into 4 equal bands; train draws from bands 0
    and 2, test from bands 1 and 3. Both cover the whole span, but no train
    value equals a test value. Phases and signs are not split.
    """

    def __init__(self, rng: np.random.Generator, split: str):
        self.rng = rng
        self.offset = 0 if split == "train" else 1

    def __call__(self, lo: float, hi: float) -> float:
        band = 2 * int(self.rng.integers(2)) + self.offset
        return lo + (hi - lo) * (band + self.rng.random()) / 4.0

    def sign(self) -> float:
        return float(self.rng.choice((-1.0, 1.0)))

    def phase(self) -> float:
        return float(self.rng.uniform(0.0, 2.0 * _PI))


# ----------------------------------------------------------------------------
# Pose building blocks. ``local`` is (n, J, 3): rotation-vector components per
# joint, except joint 0 which holds (pitch, roll, 0) of the pelvis.


def _side(local: np.ndarray, side: int, base: str, x=0.0, y=0.0, z=0.0) -> None:
    """Add a left-side rotation (side=+1) or its mirror (side=-1) to a joint."""
    j = _J[("left_" if side > 0 else "right_") + base]
    local[:, j, 0] += x
    local[:, j, 1] += side * np.asarray(y)
    local[:, j, 2] += side * np.asarray(z)


def _elbow(local: np.ndarray, side: int, flex) -> None:
    """Elbow flexion (radians beyond the A-pose) about the fixed elbow axis."""
    a = _ELBOW_AXIS_LEFT
    _side(local, side, "elbow", a[0] * np.asarray(flex), a[1] * np.asarray(flex), a[2] * np.asarray(flex))


def _spine(local: np.ndarray, bend=0.0, lateral=0.0, twist=0.0) -> None:
    """Spread a trunk bend/lateral bend/twist over the three spine joints."""
    for name in ("spine1", "spine2", "spine3"):
        local[:, _J[name]] += np.stack(np.broadcast_arrays(bend, lateral, twist), -1) / 3.0


def _flat_feet(local: np.ndarray, weight_left=1.0, weight_right=1.0) -> None:
    """Add ankle flexion that keeps each foot level (sagittal plane) with the
    given weight in [0, 1]: ankle_x = -(pelvis pitch + hip_x + knee_x)."""
    for side, w in ((1, weight_left), (-1, weight_right)):
        s = "left_" if side > 0 else "right_"
        tilt = local[:, 0, 0] + local[:, _J[s + "hip"], 0] + local[:, _J[s + "knee"], 0]
        local[:, _J[s + "ankle"], 0] -= np.asarray(w) * tilt


def _bump(phase: np.ndarray) -> np.ndarray:
    """max(0, cos)^2: a C1 bump over half of each cycle, peak 1 at phase 0."""
    return np.maximum(0.0, np.cos(phase)) ** 2


def _ease(x: np.ndarray) -> np.ndarray:
    """2x - x^2: rises fast from 0 yet keeps a zero slope wherever x has one."""
    return 2 * x - x * x


def _envelope(t: np.ndarray, duration: float) -> np.ndarray:
    """sin^2 envelope over [0, duration] (zero outside); integral duration / 2."""
    return np.sin(_PI * np.clip(t / duration, 0.0, 1.0)) ** 2


# ----------------------------------------------------------------------------
# Motion kinds: each maps local times t (n,) seconds (0 = segment start; may be
# negative / beyond `duration` inside the cross-fades) to local angles (n, J, 3)
# and a heading rate (n,) rad/s; kinds that leave the ground (jump, run) also give a lift (n,)
# metres added to the grounded root height and a forward speed (n,) m/s along the heading.

_Segment = tuple[np.ndarray, ...]


def _gait(t: np.ndarray, p: _Params, heading_rate: np.ndarray) -> _Segment:
    """Walking gait cycle; shared by walk and curved-walk turns."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    cadence = p(0.75, 1.05)  # strides per second (two steps)
    hip_amp, knee_amp = p(0.30, 0.55), p(0.7, 1.1)
    arm_amp, elbow, lean = p(0.2, 0.6), p(0.2, 0.6), p(0.0, 0.12)
    phi = 2 * _PI * cadence * t + p.phase()
    # the knee lifts exactly while the leg swings forward (hip flexion rising), so
    # a foot lands at the hip's most forward point and no planted foot slides
    swings = [_bump(phi), _bump(phi + _PI)]
    for side, ph, swing in ((1, phi, swings[0]), (-1, phi + _PI, swings[1])):
        _side(local, side, "hip", x=-(0.08 + hip_amp * np.sin(ph)))
        _side(local, side, "knee", x=0.08 + knee_amp * swing)
        _side(local, side, "shoulder", x=-(0.1 + arm_amp * np.sin(ph + _PI)), y=0.15)
        _elbow(local, side, elbow + 0.4 * arm_amp * (1 + np.sin(ph + _PI)))
    _flat_feet(local, 1 - swings[0], 1 - swings[1])
    for side, swing in ((1, swings[0]), (-1, swings[1])):
        _side(local, side, "ankle", x=-0.15 * swing)  # toes up for clearance
    _spine(local, bend=lean, twist=0.12 * np.sin(phi))
    local[:, 0, 1] = 0.04 * np.sin(phi)  # pelvis roll with the steps
    local[:, _J["neck"], 0] = -0.5 * lean
    return local, heading_rate


def _walk(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Walk forward along a nearly straight line."""
    return _gait(t, p, np.full(len(t), p(-0.15, 0.15)))


def _turn(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Walk along a curve (0.5-1.2 rad/s), or step around on the spot
    (a 1/4 to 3/4 turn)."""
    if p.rng.random() < 0.5:
        return _gait(t, p, np.full(len(t), p.sign() * p(0.5, 1.2)))
    return _step_around(t, p, duration, lift=(0.25, 0.5), cadence=(0.8, 1.2), arm_swing=0.25, arm_out=0.2, elbow=0.4)


def _step_around(t: np.ndarray, p: _Params, duration: float, *, lift: tuple[float, float],
                 cadence: tuple[float, float], arm_swing: float, arm_out: float, elbow: float) -> _Segment:  # fmt: skip
    """Step around on the spot through a quarter to three quarters of a turn (short segments turn
    less): the feet lift in turn (``lift`` rad of hip flexion, ``cadence`` Hz), the arms swing
    ``arm_swing`` rad with ``arm_out`` rad of abduction and ``elbow`` rad of flexion."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    angle = p.sign() * p(0.5 * _PI, 1.5 * _PI) * min(1.0, duration / 2.5)
    lift_amp, rate = p(*lift), p(*cadence)
    phi = 2 * _PI * rate * t + p.phase()
    swings = []
    for side, ph in ((1, phi), (-1, phi + _PI)):
        lift_t = lift_amp * _bump(ph)
        swings.append(_bump(ph))
        _side(local, side, "hip", x=-lift_t)
        _side(local, side, "knee", x=0.05 + 1.8 * lift_t)
        _side(local, side, "shoulder", x=-arm_swing * np.sin(ph + _PI), y=arm_out)
        _elbow(local, side, elbow)
    _flat_feet(local, 1 - swings[0], 1 - swings[1])
    return local, angle * _envelope(t, duration) / (duration / 2)


def _spin(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Fast spin about Z with the arms out: 0.4-0.8 turns/s on average over
    the segment (peak twice that), i.e. about 1-3 turns."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    angle = p.sign() * 2 * _PI * p(0.4, 0.8) * duration
    arms, elbow, knees = p(0.6, 1.3), p(0.1, 0.5), p(0.05, 0.25)
    env = _envelope(t, duration)
    for side in (1, -1):
        _side(local, side, "shoulder", x=-0.2, y=-arms * _ease(env))
        _elbow(local, side, elbow)
        _side(local, side, "hip", x=-0.5 * knees)
        _side(local, side, "knee", x=knees)
    _flat_feet(local)
    _spine(local, bend=0.05, twist=-0.15 * np.sign(angle) * env)
    return local, angle * env / (duration / 2)


def _dance(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Rhythmic hip sways, knee bounces, arm waves and a twist to a beat."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    beat = p(1.4, 2.2)  # Hz
    sway, roll, bounce = p(0.04, 0.12), p(0.05, 0.15), p(0.15, 0.4)
    arm_up, wave, twist = p(0.4, 1.3), p(0.3, 0.9), p(0.1, 0.5)
    phi = 2 * _PI * beat * t + p.phase()
    half = 0.5 * phi  # sways take two beats
    r = roll * np.sin(half)
    local[:, 0, 1] = r
    knee = 0.1 + bounce * 0.5 * (1 - np.cos(phi))
    for side in (1, -1):
        # legs stay vertical against the pelvis roll, then tilt together (sway)
        local[:, _J[("left_" if side > 0 else "right_") + "hip"], 1] += -r + sway * np.sin(half)
        _side(local, side, "hip", x=-0.5 * knee)
        _side(local, side, "knee", x=knee)
        _side(local, side, "shoulder", x=-0.3, y=-(arm_up + 0.3 * np.sin(half + side * _PI / 2)))
        _elbow(local, side, 0.6 + wave * np.sin(phi + side * _PI / 2))
        _side(local, side, "wrist", z=0.4 * np.sin(phi + side * _PI / 2))
    _flat_feet(local)
    _spine(local, lateral=-1.3 * r, twist=0.5 * twist * np.sin(half))
    local[:, _J["neck"], 0] = 0.08 * np.sin(phi)
    local[:, _J["head"], 1] = 0.1 * np.sin(half)
    return local, twist * (_PI * beat / 2) * np.cos(0.5 * half)


def _arm_swing(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Large alternating forward/back arm swings, or cross-body swings with a
    trunk twist, with a small knee bounce."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    freq, amp = 1.0 / p(0.8, 1.6), p(0.6, 1.3)
    phi = 2 * _PI * freq * t + p.phase()
    if p.rng.random() < 0.5:  # alternating forward / back
        for side in (1, -1):
            _side(local, side, "shoulder", x=-(0.3 + amp * np.sin(phi + (side < 0) * _PI)))
            _elbow(local, side, 0.2)
        _spine(local, twist=0.15 * np.sin(phi))
    else:  # both arms out, swinging across the body; the trunk follows
        for side in (1, -1):
            _side(local, side, "shoulder", x=-0.6, y=-0.6, z=0.5 * side * amp * np.sin(phi))
            _elbow(local, side, 0.3)
        _spine(local, twist=-0.6 * amp * np.sin(phi))
    knee = 0.1 + 0.1 * (1 - np.cos(2 * phi))
    for side in (1, -1):
        _side(local, side, "hip", x=-0.5 * knee)
        _side(local, side, "knee", x=knee)
    _flat_feet(local)
    return local, np.zeros(len(t))


def _squat(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Repeated squats; arms forward for balance, knees slightly out."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    freq, depth, arms = 1.0 / p(1.8, 3.0), p(0.45, 1.0), p(0.6, 1.3)
    s = 0.5 * (1 - np.cos(2 * _PI * freq * t + p.phase()))
    for side in (1, -1):
        _side(local, side, "hip", x=-1.6 * depth * s, y=-0.15 * s)
        _side(local, side, "knee", x=2.2 * depth * s)
        _side(local, side, "shoulder", x=-arms * s)
        _elbow(local, side, 0.2 * s)
    _flat_feet(local)
    _spine(local, bend=0.45 * depth * s)
    local[:, _J["neck"], 0] = -0.3 * depth * s
    return local, np.zeros(len(t))


def _kick(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Front kicks (chamber, extend, retract), alternating legs or one leg."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    period, height, chamber = p(1.4, 2.2), p(0.8, 1.6), p(0.8, 1.4)
    alternate, first = p.rng.random() < 0.5, p.sign()
    u = (t / period) % 1.0
    k = np.floor(t / period)
    active = np.clip(u / 0.75, 0.0, 1.0)  # the kick takes 3/4 of the period
    g = np.sin(_PI * active) ** 2  # hip flexion profile, C1
    knee_k = chamber * np.sin(2 * _PI * active) ** 2  # bent, straight at the top, bent
    kicking_left = (first > 0) ^ (alternate & (k % 2 == 1))
    for side in (1, -1):
        on = np.where(kicking_left == (side > 0), 1.0, 0.0)
        _side(local, side, "hip", x=-(0.05 + on * height * g))
        _side(local, side, "knee", x=0.1 + on * knee_k)
        _side(local, side, "ankle", x=on * 0.3 * g)
        _side(local, side, "shoulder", x=-0.2, y=-0.4 - 0.2 * g)
        _elbow(local, side, 0.6)
    on_l = np.where(kicking_left, 1.0, 0.0)
    _flat_feet(local, 1 - on_l * _ease(g), 1 - (1 - on_l) * _ease(g))
    _spine(local, bend=-0.15 * g)
    return local, np.zeros(len(t))


def _plateau(t: np.ndarray, duration: float, ramp: float) -> np.ndarray:
    """0 -> 1 over the first ``ramp`` share of the segment, 1, then back to 0 over the last (C1)."""
    u = np.clip(t / duration, 0.0, 1.0)
    return _smoothstep(u / ramp) * _smoothstep((1.0 - u) / ramp)


def _reach(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Reach forward and hold: one or both arms raised forward to a height between the waist and
    above the head, elbows more or less straight, the trunk leaning into a low reach; held for
    most of the segment (the pose that made a first model dress tight subjects)."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    s = _plateau(t, duration, p(0.15, 0.35))
    both = p.rng.random() < 0.5
    first = p.sign()
    height = p(0.8, 2.3)  # shoulder flexion (rad): 0.8 = to the waist ... 2.3 = above the head
    for side in (1, -1):
        on = 1.0 if both or side == first else 0.0
        spread = p(-0.35, 0.25)
        _side(local, side, "shoulder", x=-(0.1 + on * height * s), y=on * spread * s)
        _elbow(local, side, 0.3 - on * p(0.0, 0.5) * s)  # straighter when reaching
        _side(local, side, "wrist", x=on * p(-0.3, 0.3) * s)
    lean = p(0.0, 0.5) * max(0.0, 1.6 - height) / 0.8  # low reaches lean the trunk forward
    _spine(local, bend=lean * s, twist=0.0 if both else -first * p(0.0, 0.3) * s)
    for side in (1, -1):
        _side(local, side, "hip", x=-0.3 * lean * s)
        _side(local, side, "knee", x=0.05 + 0.2 * lean * s)
    _flat_feet(local)
    local[:, _J["neck"], 0] = -0.3 * lean * s
    return local, np.zeros(len(t))


def _crouch(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Go down into a deep crouch or a sitting-like pose (thighs near horizontal), hold, come up;
    arms forward for balance or resting on the thighs."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    s = _plateau(t, duration, p(0.2, 0.35))
    hip, knee = p(1.1, 1.9), p(1.3, 2.3)
    pitch, bend = p(0.05, 0.3), p(0.1, 0.45)
    arms_forward = p.rng.random() < 0.5
    for side in (1, -1):
        _side(local, side, "hip", x=-hip * s, y=-p(0.0, 0.3) * s)
        _side(local, side, "knee", x=knee * s)
        if arms_forward:
            _side(local, side, "shoulder", x=-p(0.8, 1.5) * s)
            _elbow(local, side, 0.2 * s)
        else:
            _side(local, side, "shoulder", x=-0.5 * s, y=0.3 * s)
            _elbow(local, side, 0.9 * s)
    local[:, 0, 0] = pitch * s
    _flat_feet(local)
    _spine(local, bend=bend * s)
    local[:, _J["neck"], 0] = -0.4 * (pitch + bend) * s
    return local, np.zeros(len(t))


def _jump(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Repeated jumps on the spot or forward: a counter-movement dip, push-off with the toes, a
    flight of 8-25 cm (the body leaves the ground) with the arms swung up, and a landing dip."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    period, dip, height = p(1.0, 1.6), p(0.5, 1.1), p(0.08, 0.25)
    u = (t / period) % 1.0
    # phases of one jump: dip [0, .35), push [.35, .5), flight [.5, .75), landing [.75, 1)
    down = np.zeros_like(u)
    m = u < 0.35
    down[m] = np.sin(_PI / 2 * u[m] / 0.35) ** 2
    m = (u >= 0.35) & (u < 0.5)
    down[m] = np.cos(_PI / 2 * (u[m] - 0.35) / 0.15) ** 2
    m = u >= 0.75
    down[m] = 0.7 * np.sin(_PI * (u[m] - 0.75) / 0.25) ** 2
    flight = np.where((u >= 0.5) & (u < 0.75), np.sin(_PI * (u - 0.5) / 0.25), 0.0)
    push = np.where((u >= 0.35) & (u < 0.75), np.sin(_PI * (u - 0.35) / 0.4) ** 2, 0.0)
    env = _plateau(t, duration, 0.1)
    for side in (1, -1):
        _side(local, side, "hip", x=-(0.9 * dip * down + 0.1 * flight))
        _side(local, side, "knee", x=1.6 * dip * down + 0.15 * flight)
        _side(local, side, "shoulder", x=0.4 * down - p(1.0, 2.2) * push)
        _elbow(local, side, 0.3 + 0.3 * down)
    _flat_feet(local, 1 - push, 1 - push)
    for side in (1, -1):
        _side(local, side, "ankle", x=0.5 * push)  # toes point at push-off and in the air
    _spine(local, bend=0.4 * dip * down)
    local *= env[:, None, None]
    forward = p(0.0, 0.6) if p.rng.random() < 0.5 else 0.0
    lift = height * flight * env
    return local, np.zeros(len(t)), lift, forward * push * env


def _run(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Running: a faster, higher-stepping gait (1.3-1.7 strides/s) with bent elbows, a forward lean
    and a short flight phase at every step."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    cadence = p(1.3, 1.7)
    hip_amp, knee_amp = p(0.5, 0.8), p(1.2, 1.9)
    arm_amp, elbow, lean = p(0.5, 0.9), p(1.1, 1.5), p(0.1, 0.25)
    phi = 2 * _PI * cadence * t + p.phase()
    swings = [_bump(phi), _bump(phi + _PI)]
    for side, ph, swing in ((1, phi, swings[0]), (-1, phi + _PI, swings[1])):
        _side(local, side, "hip", x=-(0.15 + hip_amp * np.sin(ph)))
        _side(local, side, "knee", x=0.2 + knee_amp * swing)
        _side(local, side, "shoulder", x=-(0.1 + arm_amp * np.sin(ph + _PI)), y=0.2)
        _elbow(local, side, elbow)
    _flat_feet(local, 1 - swings[0], 1 - swings[1])
    for side, swing in ((1, swings[0]), (-1, swings[1])):
        _side(local, side, "ankle", x=-0.2 * swing)
    _spine(local, bend=lean, twist=0.15 * np.sin(phi))
    local[:, 0, 0] = 0.5 * lean
    local[:, 0, 1] = 0.05 * np.sin(phi)
    local[:, _J["neck"], 0] = -0.6 * lean
    env = _plateau(t, duration, 0.1)
    lift = p(0.02, 0.06) * np.abs(np.sin(phi)) ** 4 * env  # a short flight at every step
    return local, np.full(len(t), p(-0.3, 0.3)), lift, np.zeros(len(t))


def _bend(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Bend over and come back: forward to pick something up (hips and spine flexed, arms hanging
    towards the floor) or sideways (lateral trunk bend, one arm sliding down the leg)."""
    local = np.zeros((len(t), NUM_JOINTS, 3))
    s = _plateau(t, duration, p(0.25, 0.4))
    if p.rng.random() < 0.6:
        hip, spine, knees = p(0.5, 1.3), p(0.6, 1.4), p(0.05, 0.6)
        for side in (1, -1):
            _side(local, side, "hip", x=-hip * s)
            _side(local, side, "knee", x=knees * s)
            _side(local, side, "shoulder", x=-(hip + 0.5 * spine) * s * p(0.6, 1.0))
            _elbow(local, side, 0.1 * s)
        local[:, 0, 0] = p(0.0, 0.25) * s
        _spine(local, bend=spine * s)
        local[:, _J["neck"], 0] = -0.3 * spine * s
    else:
        side, amount = p.sign(), p(0.4, 0.85)
        _spine(local, lateral=side * amount * s)
        _side(local, int(side), "shoulder", y=0.3 * s)
        _side(local, int(-side), "shoulder", y=-p(0.3, 1.2) * s)
        local[:, _J["head"], 1] = -0.3 * side * amount * s
    _flat_feet(local)
    return local, np.zeros(len(t))


def _turn_in_place(t: np.ndarray, p: _Params, duration: float) -> _Segment:
    """Step around on the spot through a quarter to three quarters of a turn, or pivot on both feet
    with the trunk leading (a look over the shoulder turning into a turn)."""
    if p.rng.random() < 0.6:
        return _step_around(t, p, duration, lift=(0.2, 0.45), cadence=(0.9, 1.4), arm_swing=0.15, arm_out=0.15,
                            elbow=0.5)  # fmt: skip
    local = np.zeros((len(t), NUM_JOINTS, 3))
    angle = p.sign() * p(0.3 * _PI, 0.7 * _PI)
    env = _envelope(t, duration)
    lead = np.sign(angle) * np.sin(_PI * np.clip(t / duration, 0, 1))  # trunk leads, hips follow
    _spine(local, twist=0.6 * lead)
    local[:, _J["neck"], 2] = 0.5 * lead
    for side in (1, -1):
        _side(local, side, "shoulder", x=-0.2, y=0.2)
        _elbow(local, side, 0.6)
    _flat_feet(local)
    return local, angle * env / (duration / 2)


_KIND_FUNCTIONS: dict[str, Callable[[np.ndarray, _Params, float], _Segment]] = {
    "walk": _walk,
    "turn": _turn,
    "dance": _dance,
    "arm_swing": _arm_swing,
    "squat": _squat,
    "kick": _kick,
    "spin": _spin,
    "reach": _reach,
    "crouch": _crouch,
    "jump": _jump,
    "run": _run,
    "bend": _bend,
    "turn_in_place": _turn_in_place,
}


# ----------------------------------------------------------------------------
# Assembly.


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def clamp_to_limits(local: np.ndarray) -> np.ndarray:
    """Clamp (T, J, 3) local angles to ``JOINT_LIMITS`` (pelvis: pitch, roll)."""
    return np.clip(local, _LIMITS[None, :, :, 0], _LIMITS[None, :, :, 1])


def _compose_root(local: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """Local angles (T, J, 3) + heading (T,) -> joint rotation vectors (T, J, 3)."""
    rot = local.copy()
    euler = np.stack([heading, local[:, 0, 0], local[:, 0, 1]], -1)  # (T, 3) Z, X, Y
    rot[:, 0] = Rotation.from_euler("ZXY", euler).as_rotvec()
    return rot


def pelvis_euler(joint_rotvecs: np.ndarray) -> np.ndarray:
    """(T, J, 3) rotation vectors -> (T, 3) pelvis (pitch, roll, heading) in
    the order of ``JOINT_LIMITS["pelvis"]``; heading in [-pi, pi]."""
    zxy = Rotation.from_rotvec(np.asarray(joint_rotvecs, dtype=np.float64)[:, 0]).as_euler("ZXY")
    return zxy[:, [1, 2, 0]]


def pose_joints(body: AnnyBody, joint_rotvecs: np.ndarray, chunk: int = 64) -> np.ndarray:
    """The 24 joints (T, J, 3) of ``body`` posed with ``joint_rotvecs`` (T, J, 3)
    and zero root translation: ``body.pose(...).joints`` without computing the
    per-vertex skinning transforms (~6x faster; equality is tested)."""
    return body.pose_joints(joint_rotvecs, chunk=chunk)


def ground_translation(body: AnnyBody, joint_rotvecs: np.ndarray, chunk: int = 64) -> np.ndarray:
    """Root translation (T, 3) that keeps the body on the ground without skating.

    Poses the body with zero translation, takes the contact joints
    (``CONTACT_JOINTS``) and their heights c (T, 4) relative to the rest pose
    (all rotations zero, ``body.zero_pose``, whose root translation is 0),
    and weights them with w = softmax(-c / ``CONTACT_TEMPERATURE``) so that the
    lowest contact dominates (smoothly). z = -sum(w c) keeps it at its rest
    height (the lowest joint sinks at most ~0.3 tau when contacts are nearly
    level); x, y integrate -sum(w dp) so the weighted contact stays put in the
    ground plane (starting at 0).
    """
    rest = body.zero_pose.joints[0, _CONTACT, 2].astype(np.float64)  # (4,) all-zero rotations
    pts = pose_joints(body, joint_rotvecs, chunk)[:, _CONTACT].astype(np.float64)  # (T, 4, 3)
    c = pts[..., 2] - rest
    logits = -(c - c.min(1, keepdims=True)) / CONTACT_TEMPERATURE
    w = np.exp(logits)
    w /= w.sum(1, keepdims=True)  # (T, 4)
    trans = np.zeros((len(pts), 3))
    trans[:, 2] = -(w * c).sum(1)
    wm = 0.5 * (w[1:] + w[:-1])
    step = -(wm[..., None] * (pts[1:, :, :2] - pts[:-1, :, :2])).sum(1)  # (T-1, 2)
    trans[1:, :2] = np.cumsum(step, 0)
    return trans


def _plan_segments(rng, num_frames: int, fps: float, kinds: Sequence[str], fade: int) -> list[tuple[str, int, int]]:
    """Chain of (kind, start, end); consecutive kinds differ when possible."""
    segments, start, prev = [], 0, None
    lo, hi = (int(round(s * fps)) for s in SEGMENT_SECONDS)
    while start < num_frames:
        choices = [k for k in kinds if k != prev] or list(kinds)
        kind = choices[int(rng.integers(len(choices)))]
        end = min(start + int(rng.integers(max(lo, 2 * fade), max(hi, 2 * fade) + 1)), num_frames)
        if num_frames - end < 2 * fade:  # no stub segment at the end
            end = num_frames
        segments.append((kind, start, end))
        start, prev = end, kind
    return segments


def generate_motion(
    seed: int,
    num_frames: int,
    split: str = "train",
    fps: float = 25.0,
    kinds: Sequence[str] | None = None,
    body: AnnyBody | None = None,
) -> Motion:
    """A random motion: a chain of 2-4 s segments with 0.5 s cross-fades.

    The output depends only on (seed, split, num_frames, fps, kinds) and the
    body's phenotype (which sets the root translation). It starts at the
    origin facing -Y (heading 0).

    Train and test differ, as in LOOSE where test motions are separate
    recordings:
      * parameters: every random range (speed/cadence, amplitudes, stride,
        tempo, turn angles, ...) is split into 4 bands; train draws from bands
        0 and 2, test from bands 1 and 3, so no parameter value is shared;
      * segment combinations: each test segment is, with probability 1/2,
        "mixed": its upper body (spine, neck, head, arms) comes from a second,
        different kind (e.g. ``"walk+dance"``: walking legs with dancing arms).
        Train segments are never mixed.
      * the random streams differ: the generator is seeded with (seed, split).

    Args:
        seed: non-negative integer.
        num_frames: T > 0.
        split: "train" or "test".
        fps: frames per second (> 0).
        kinds: subset of ``MOTION_KINDS`` to draw from (default: ``CLASSIC_KINDS``, the kinds of
            the ``tiny`` / ``small`` datasets).
        body: the subject used to ground the motion; default ``AnnyBody()``.
    Returns:
        Motion with joint_rotvecs (T, 24, 3) and root_translation (T, 3).
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or num_frames <= 0:
        raise ValueError(f"num_frames must be a positive integer, got {num_frames!r}")
    if split not in MOTION_STYLES:
        raise ValueError(f"unknown motion style {split!r}; expected one of {MOTION_STYLES}")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps!r}")
    kinds = tuple(CLASSIC_KINDS if kinds is None else kinds)
    if not kinds:
        raise ValueError("kinds must not be empty")
    unknown = [k for k in kinds if k not in MOTION_KINDS]
    if unknown:
        raise ValueError(f"unknown motion kinds {unknown}; expected some of {MOTION_KINDS}")

    rng = np.random.default_rng([int(seed), MOTION_STYLES.index(split)])
    params = _Params(rng, split)
    fade = max(2, int(round(TRANSITION_SECONDS * fps)))
    plan = _plan_segments(rng, int(num_frames), float(fps), kinds, fade)

    frames = np.arange(num_frames)
    local = np.zeros((num_frames, NUM_JOINTS, 3))
    rate = np.zeros(num_frames)
    lift = np.zeros(num_frames)  # metres above the grounded height (flight of jumps and runs)
    speed = np.zeros(num_frames)  # m/s along the heading while airborne / pushing off
    segments = []
    for i, (kind, start, end) in enumerate(plan):
        a, b = max(0, start - fade // 2 - 1), min(num_frames, end + fade // 2 + 1)
        f = frames[a:b]
        rise = 1.0 if i == 0 else _smoothstep((f - start + fade / 2 + 0.5) / fade)
        fall = 1.0 if i == len(plan) - 1 else 1.0 - _smoothstep((f - end + fade / 2 + 0.5) / fade)
        w = np.broadcast_to(rise * fall, f.shape)  # (n,); partition of unity across segments
        t = (f - start) / fps
        seg = _KIND_FUNCTIONS[kind](t, params, (end - start) / fps)
        seg_local, seg_rate = seg[0], seg[1]
        name = kind
        if split == "test" and len(kinds) > 1 and rng.random() < 0.5:
            others = [k for k in kinds if k != kind]
            upper = others[int(rng.integers(len(others)))]
            upper_local = _KIND_FUNCTIONS[upper](t, params, (end - start) / fps)[0]
            seg_local[:, _UPPER] = upper_local[:, _UPPER]
            name = f"{kind}+{upper}"
        local[a:b] += w[:, None, None] * seg_local
        rate[a:b] += w * seg_rate
        if len(seg) > 2:
            lift[a:b] += w * seg[2]
            speed[a:b] += w * seg[3]
        segments.append((name, start, end))

    local = clamp_to_limits(local)
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) / fps)])  # trapezoid
    heading = (heading + _PI) % (2 * _PI) - _PI
    rotvecs = _compose_root(local, heading)
    body = body if body is not None else AnnyBody()
    trans = ground_translation(body, rotvecs)
    if lift.any() or speed.any():
        trans[:, 2] += lift
        step = speed / fps  # forward travel of the airborne phases, along the heading (faces -Y at 0)
        trans[:, 0] += np.cumsum(step * np.sin(heading))
        trans[:, 1] += np.cumsum(-step * np.cos(heading))
    return Motion(f"{split}_seed{seed}", float(fps), rotvecs, trans, segments)


def rest_to_motion(motion: Motion, num_frames: int, body: AnnyBody | None = None) -> Motion:
    """Prepend ``num_frames`` frames that move from the rest A-pose (all
    rotations zero, root at the origin) into ``motion``'s first frame.

    The prefix is a cubic Hermite curve per rotation-vector component: zero
    velocity at rest, and at the join the motion's own frame-0 velocity, so
    joint velocities stay continuous (the cloth simulator starts from rest).
    With ``body`` the prefix is grounded like :func:`generate_motion` (feet on
    the ground, no skating) and the original frames are shifted horizontally
    to continue from where the prefix ends; without it the translation is
    blended the same way as the rotations.

    Returns a new Motion of T + num_frames frames; the prefix is segment
    ``("rest", 0, num_frames)``.
    """
    if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or num_frames <= 0:
        raise ValueError(f"num_frames must be a positive integer, got {num_frames!r}")
    n = int(num_frames)
    rot, trans = motion.joint_rotvecs.astype(np.float64), motion.root_translation.astype(np.float64)
    vel_rot = rot[1] - rot[0] if motion.num_frames > 1 else np.zeros_like(rot[0])
    vel_trans = trans[1] - trans[0] if motion.num_frames > 1 else np.zeros(3)
    u = (np.arange(n) / n)[:, None, None]  # (n, 1, 1); u = 1 would be frame 0
    h01, h11 = -2 * u**3 + 3 * u**2, u**3 - u**2  # Hermite basis (start value/slope 0)
    prefix_rot = h01 * rot[0] + h11 * (n * vel_rot)
    # keep the pelvis within its pitch/roll limits and other joints within theirs
    prefix_rot[:, 1:] = clamp_to_limits(prefix_rot)[:, 1:]
    if body is not None:
        both = np.concatenate([prefix_rot, rot[:1]])
        g = ground_translation(body, both)
        prefix_trans = g[:-1]
        shift = g[-1] - trans[0]
        shift[2] = 0.0
        rest_trans = trans + shift
    else:
        prefix_trans = h01[:, 0] * trans[0] + h11[:, 0] * (n * vel_trans)
        rest_trans = trans
    segments = [("rest", 0, n)] + [(k, a + n, b + n) for k, a, b in motion.segments]
    return Motion(
        f"{motion.name}_from_rest",
        motion.fps,
        np.concatenate([prefix_rot, rot]),
        np.concatenate([prefix_trans, rest_trans]),
        segments,
    )
