"""Pose inputs: the 24 joints of one pose, and (for the body-driven methods) the posed body.

Every method is conditioned on a :class:`Pose`. PocoLoco needs only its ``joints``; POP and CloSET
also need the subject's posed body (``body_vertices``, the skinning transforms ``vtransf``) and
POP the mean-shape body in the same pose (``mean_shape``, its pose encoder's input, paper Sec. 3.2).

Where poses come from (``--joints`` on the command line, :func:`load_joints` / :func:`pose_from_spec`):

- a ``.npy`` (J, 3) array, or a ``.npz`` with a ``joints`` array (this covers dataset frame files);
- a LOOSE-style joints text file (per line a frame id and 3J floats);
- a dataset frame ``DATASET:subject/split/sequence/index`` (joints, and the posed body);
- ``demo:NAME``, a pose shipped with the package, one per outfit of the ``medium`` dataset
  (``demo:skirt_a`` ... ``demo:trousers_b``: the last frame of that subject's first test sequence,
  its joints and anny pose parameters, so every method can take it); ``demo:KIND`` (``demo:skirt``)
  is the first outfit of that kind (``skirt_a``);
- an ``.npz`` with anny pose parameters ``joint_rotvecs`` (24, 3) (+ optional ``root_translation``),
  posed with a subject's phenotype (the body-driven methods).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pocoloco.body.anny_body import AnnyBody
from pocoloco.body.skeleton import BONE_LENGTH_RANGE_M, JOINT_NAMES, JOINT_PARENTS, MIRROR_PAIRS, NUM_JOINTS
from pocoloco.body.surface import pose_mean_shape_vertices
from pocoloco.data.format import (
    SPLITS,
    DatasetLayout,
    read_card,
    read_frame,
    read_motion,
)
from pocoloco.data.motion_window import MotionWindow, motion_window
from pocoloco.data.published import read_joints_txt
from pocoloco.utils.npfile import numpy_file_problem

__all__ = [
    "DEMO_POSES_DIR",
    "MeanShapeCache",
    "Pose",
    "check_joints",
    "dataset_frame_path",
    "demo_motion",
    "demo_pose_names",
    "demo_pose_outfit",
    "demo_pose_path",
    "is_anny_pose_file",
    "load_body_pose",
    "load_joints",
    "load_motion",
    "motion_pose",
    "motion_path_of",
    "outfit_of_spec",
    "pose_from_anny_file",
    "pose_from_anny_params",
    "pose_from_frame",
    "pose_spec_kind",
    "subject_of_spec",
]

#: one ``NAME.npz`` per outfit of the ``medium`` dataset: ``joints`` (24, 3) metres, anny
#: ``joint_rotvecs`` (24, 3) and ``root_translation`` (3,), ``outfit`` (the subject wearing it),
#: ``source`` (the dataset frame) and ``loose_pct`` (the scan's share of loose-garment points);
#: written by ``benchmarks/make_demo_poses.py``, usable as ``--joints demo:NAME``
DEMO_POSES_DIR = Path(__file__).resolve().parent.parent / "assets" / "poses"


def demo_pose_names() -> list[str]:
    """Names of the shipped demo poses (one per outfit: ``dress_a`` ... ``trousers_b``)."""
    return sorted(p.stem for p in DEMO_POSES_DIR.glob("*.npz"))


def demo_pose_path(name: str) -> Path:
    """The .npz of demo pose ``name``, or of the first outfit ``name_*`` (``skirt`` -> ``skirt_a``);
    a one-line error naming the known ones otherwise."""
    names = demo_pose_names()
    if name and "/" not in name:
        if name in names:
            return DEMO_POSES_DIR / f"{name}.npz"
        kinds = [n for n in names if n.startswith(f"{name}_")]
        if kinds:
            return DEMO_POSES_DIR / f"{kinds[0]}.npz"
    aliases = sorted({n.rsplit("_", 1)[0] for n in names if "_" in n})
    raise ValueError(f"demo:{name}: no such demo pose; choose one of: {', '.join(aliases + names)}")


def demo_pose_outfit(name: str) -> str:
    """The outfit demo pose ``name`` was captured on (``skirt`` -> ``skirt_a``)."""
    path = demo_pose_path(name)
    with np.load(path, allow_pickle=False) as z:
        return str(z["outfit"]) if "outfit" in z.files else path.stem


def demo_motion(spec: str, seconds: float) -> MotionWindow | None:
    """The motion window a ``demo:NAME`` pose ships with (the 2 s at 8 Hz before its frame), for a
    model whose window is ``seconds`` long; None for another spec, another window length, or 0."""
    if not seconds or not str(spec).startswith("demo:") or Path(spec).exists():
        return None
    with np.load(demo_pose_path(str(spec)[5:]), allow_pickle=False) as z:
        if "motion_window_joints" not in z.files or abs(float(z["motion_seconds"]) - seconds) > 1e-6:
            return None
        return MotionWindow(z["motion_window_joints"].astype(np.float32), z["motion_root_velocity"].astype(np.float32),
                            z["motion_yaw_rate"].astype(np.float32))  # fmt: skip


# ------------------------------------------------------------------------------------ joints
def check_joints(src: str, joints: Any, num_joints: int) -> np.ndarray:
    """(J, 3) finite float array or a one-line ValueError naming ``src``."""
    arr = np.asarray(joints)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{src}: joints must be numeric, got dtype {arr.dtype}")
    if arr.shape != (num_joints, 3):
        raise ValueError(f"{src}: expected joints of shape ({num_joints}, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{src}: joints contain NaN or inf")
    return arr.astype(np.float32)


#: a joint this far from the root (metres) is not a human body in metres
MAX_JOINT_REACH_M = 2.5
#: all joints within this distance (metres) of the root: not a body
MIN_JOINT_SPREAD_M = 0.1
#: the pelvis-to-head direction may lean this far from +z (the up axis); the training motions of
#: ``medium`` lean at most ~54 deg (400 random frames), a body lying down or upside down is refused
MAX_SPINE_TILT_DEG = 75.0
ANY_POSE_HINT = "pass --any-pose (library: any_pose=True) to use it anyway"


def check_skeleton(src: str, joints: np.ndarray) -> np.ndarray:
    """A one-line ValueError naming the problem unless ``joints`` (24, 3) look like a human skeleton
    in metres: every joint within ``MAX_JOINT_REACH_M`` of the root and not all of them on one spot,
    every bone no shorter than half and no longer than twice the range of anny's bodies (a young child
    to a tall adult, ``BONE_LENGTH_RANGE_M``), left and right bones within a factor 1.5 of each other,
    and upright: the pelvis-to-head direction within ``MAX_SPINE_TILT_DEG`` of +z (swapped axes fail here).
    A model trained on human poses turns anything else into a cloud that is meaningless (or hundreds
    of km wide); returns the joints."""
    j = np.asarray(joints, np.float64)
    if j.shape != (NUM_JOINTS, 3):  # only the 24-joint skeleton has known bones
        return joints
    reach = np.linalg.norm(j - j[0], axis=1)
    if reach.max() > MAX_JOINT_REACH_M:
        k = int(reach.argmax())
        raise ValueError(f"{src}: joint {JOINT_NAMES[k]} is {reach.max():.3g} m from the root (a body spans ~1 m): "
                         f"not metres, or not a body; {ANY_POSE_HINT}")  # fmt: skip
    if reach.max() < MIN_JOINT_SPREAD_M:
        raise ValueError(f"{src}: all joints lie within {100 * reach.max():.1f} cm of the root: not a body; {ANY_POSE_HINT}")
    lengths = np.array([np.linalg.norm(j[c] - j[p]) for c, p in enumerate(JOINT_PARENTS) if p >= 0])
    lo, hi = 0.5 * np.array(BONE_LENGTH_RANGE_M[0]), 2.0 * np.array(BONE_LENGTH_RANGE_M[1])
    bad = np.flatnonzero((lengths < lo) | (lengths > hi))
    if len(bad):
        k = int(bad[np.argmax(np.maximum(lengths[bad] / hi[bad], lo[bad] / np.maximum(lengths[bad], 1e-12)))])
        raise ValueError(f"{src}: impossible bone length: {JOINT_NAMES[k + 1]} is {100 * lengths[k]:.1f} cm from its "
                         f"parent (human bodies: {100 * lo[k]:.1f}-{100 * hi[k]:.1f} cm); {ANY_POSE_HINT}")  # fmt: skip
    for left, right in MIRROR_PAIRS:
        if left == 0 or JOINT_PARENTS[left] < 0:
            continue
        a, b = lengths[left - 1], lengths[right - 1]
        if max(a, b) > 1.5 * min(a, b):
            raise ValueError(f"{src}: left and right differ: {JOINT_NAMES[left]} {100 * a:.1f} cm vs "
                             f"{JOINT_NAMES[right]} {100 * b:.1f} cm from their parents; {ANY_POSE_HINT}")  # fmt: skip
    spine = j[JOINT_NAMES.index("head")] - j[0]
    tilt = float(np.degrees(np.arccos(np.clip(spine[2] / max(np.linalg.norm(spine), 1e-12), -1.0, 1.0))))
    if tilt > MAX_SPINE_TILT_DEG:
        axis = "xyz"[int(np.argmax(np.abs(spine)))]
        raise ValueError(f"{src}: the head is not above the pelvis: the pelvis-to-head direction is {tilt:.0f} deg from +z "
                         f"(it runs along {'-' if spine['xyz'.index(axis)] < 0 else '+'}{axis}): pocoloco's joints are z-up "
                         f"(axes swapped or flipped?); {ANY_POSE_HINT}")  # fmt: skip
    return joints


def _load_array_file(path: Path) -> np.ndarray:
    """The joints array of a .npy, or of a .npz (key ``joints``, else its only array)."""
    try:
        loaded = np.load(path, allow_pickle=False)
        if not hasattr(loaded, "files"):  # a .npy array
            return np.asarray(loaded)
        with loaded as z:
            if "joints" in z.files:
                return z["joints"]
            if len(z.files) == 1:
                return z[z.files[0]]
            raise ValueError(f"{path}: npz has no 'joints' array (arrays: {', '.join(sorted(z.files))})")
    except Exception as e:  # zipfile.BadZipFile, EOFError, OSError, ValueError ...
        if isinstance(e, ValueError) and str(e).startswith(str(path)):
            raise
        problem = numpy_file_problem(path)
        if problem is not None:
            raise ValueError(f"{path}: cannot read joints: {problem}") from None
        raise ValueError(f"{path}: cannot read joints ({type(e).__name__}: {' '.join(str(e).split())})") from None


#: fastest a body's root may travel in a motion file (m/s; a sprinter's top speed is ~12) and the
#: fastest it may turn (rad/s; a pirouette is ~4 turns a second): beyond them a file is refused
MAX_ROOT_SPEED, MAX_YAW_RATE = 15.0, 30.0
#: frames per second a motion file may have
FPS_RANGE = (1.0, 1000.0)


def load_motion(path: str | os.PathLike, fps: float, seconds: float = 2.0,
                any_pose: bool = False) -> tuple[Pose, str | None]:  # fmt: skip
    """A joints sequence file (``.npy`` / ``.npz`` (T, 24, 3), metres, z up, at ``fps``) -> the Pose
    of its **last** frame carrying the ``seconds`` of motion before it
    (:func:`~pocoloco.data.motion_window.motion_window`), and a note for the user (a sequence shorter
    than the window is padded with its first frame, as a body at rest before it) or None. One-line
    errors for a wrong shape, NaN, an fps out of range, a last frame that is not a human skeleton
    (unless ``any_pose``), and implausible speeds (``MAX_ROOT_SPEED``, ``MAX_YAW_RATE``)."""
    src = os.fspath(path)
    if not Path(src).is_file():
        raise ValueError(f"{src}: no such motion file")
    return motion_pose(_load_array_file(Path(src)), fps, seconds, any_pose=any_pose, src=src)


def motion_pose(joints: Any, fps: float, seconds: float = 2.0, any_pose: bool = False,
                src: str = "motion") -> tuple[Pose, str | None]:  # fmt: skip
    """A joints sequence (T, 24, 3) in metres, z up, at ``fps`` -> the Pose of its last frame with the
    ``seconds`` of motion before it, and a note or None (:func:`load_motion`, which reads a file)."""
    if not (np.isfinite(fps) and FPS_RANGE[0] <= fps <= FPS_RANGE[1]):
        raise ValueError(f"--fps {fps}: expected frames per second between {FPS_RANGE[0]:g} and {FPS_RANGE[1]:g}")
    seq = np.asarray(joints)
    if seq.dtype.kind not in "fiu" or seq.ndim != 3 or seq.shape[1:] != (NUM_JOINTS, 3) or len(seq) < 1:
        raise ValueError(f"{src}: a motion is a (T, {NUM_JOINTS}, 3) joints array, got shape {seq.shape}")
    if not np.isfinite(seq).all():
        raise ValueError(f"{src}: the motion contains NaN or infinite values")
    seq = seq.astype(np.float32)
    last = seq[-1] if any_pose else check_skeleton(f"{src} (last frame)", seq[-1])
    if len(seq) > 1:
        speed = np.linalg.norm(np.diff(seq[:, 0], axis=0), axis=-1).max() * fps
        if speed > MAX_ROOT_SPEED:
            raise ValueError(f"{src}: the root moves at up to {speed:.1f} m/s at --fps {fps:g} (more than "
                             f"{MAX_ROOT_SPEED:g}): wrong fps, or not metres?")  # fmt: skip
        across = seq[:, 1] - seq[:, 2]
        yaw = np.unwrap(np.arctan2(across[:, 1], across[:, 0]))
        turn = np.abs(np.diff(yaw)).max() * fps
        if turn > MAX_YAW_RATE:
            raise ValueError(f"{src}: the body turns at up to {turn:.1f} rad/s at --fps {fps:g} (more than "
                             f"{MAX_YAW_RATE:g}): wrong fps, or not z up?")  # fmt: skip
    window = motion_window(seq, len(seq) - 1, fps, seconds)
    covered = (len(seq) - 1) / fps
    note = (f"{src}: {len(seq)} frames cover {covered:.2f} s of the {seconds:g} s window; the earlier part holds "
            "its first frame (a body at rest before it)") if covered + 1e-9 < seconds else None  # fmt: skip
    return Pose(last, source="motion" if src == "motion" else f"motion:{src}", motion=window), note


def dataset_frame_path(spec: str) -> Path:
    """``DATASET:subject/split/sequence/index`` -> the frame file (the dataset is validated)."""
    root, _, key = spec.rpartition(":")
    parts = key.strip("/").split("/")
    if len(parts) != 4:
        raise ValueError(f"{spec}: expected DATASET:subject/split/sequence/index, got frame key {key!r}")
    subject, split, sequence, index = parts
    read_card(root)  # one-line error when root is not a dataset
    if split not in SPLITS:
        raise ValueError(f"{spec}: unknown split {split!r}; expected one of {SPLITS}")
    try:
        idx = int(index)
    except ValueError:
        raise ValueError(f"{spec}: frame index {index!r} is not an integer") from None
    layout = DatasetLayout(root)
    if subject not in layout.subjects():
        raise ValueError(f"{spec}: no subject {subject!r} in {root} (has {', '.join(layout.subjects()) or 'none'})")
    path = layout.frame_path(subject, split, sequence, idx)
    if not path.is_file():
        raise ValueError(f"{spec}: no such frame ({path})")
    return path


def load_joints(spec: str | os.PathLike, frame_id: int | None = None, num_joints: int = NUM_JOINTS,
                any_pose: bool = False) -> np.ndarray:
    """Read one pose's joints (J, 3) float32, in metres, from ``spec``.

    ``spec`` is one of:

    - a ``.npy`` holding a (J, 3) array, or a ``.npz`` with a ``joints`` array (this covers our
      dataset frame files) or a single (J, 3) array;
    - a LOOSE-style joints text file (per line a frame id and 3J floats,
      :func:`pocoloco.data.published.read_joints_txt`): ``frame_id`` picks the line with that
      frame id (None: the first line);
    - a dataset frame ``DATASET:subject/split/sequence/index`` (e.g. ``data/tiny:s0/test/seq_000/3``);
    - ``demo:NAME``, a pose shipped with the package (``demo:skirt``, ``demo:dress_b``, ...).

    Raises:
        ValueError: one line, naming the file: unreadable file, not a dataset, no such frame,
            wrong joint count or shape, NaN / inf; and, unless ``any_pose``, a skeleton that is not
            a human body in metres (:func:`check_skeleton`).
    """
    joints = _read_joints(spec, frame_id, num_joints)
    return joints if any_pose else check_skeleton(os.fspath(spec), joints)


def _read_joints(spec: str | os.PathLike, frame_id: int | None, num_joints: int) -> np.ndarray:
    spec = os.fspath(spec)
    path = Path(spec)
    if spec.startswith("demo:") and not path.exists():
        if frame_id is not None:
            raise ValueError(f"{spec}: --frame-id only applies to joints text files")
        return check_joints(spec, _load_array_file(demo_pose_path(spec[5:])), num_joints)
    if not path.exists() and ":" in spec:
        if frame_id is not None:
            raise ValueError(f"{spec}: --frame-id only applies to joints text files")
        return check_joints(spec, read_frame(dataset_frame_path(spec), ["joints"]).joints, num_joints)
    if not path.is_file():
        raise ValueError(f"{spec}: no such joints file (or DATASET:subject/split/sequence/index frame)")
    if path.suffix in (".npy", ".npz"):
        if frame_id is not None:
            raise ValueError(f"{spec}: --frame-id only applies to joints text files")
        return check_joints(spec, _load_array_file(path), num_joints)
    ids, joints = read_joints_txt(path, num_joints)  # (T,), (T, J, 3); validates counts and NaNs
    if frame_id is None:
        return joints[0]
    hit = np.flatnonzero(ids == frame_id)
    if len(hit) == 0:
        raise ValueError(f"{spec}: no line with frame id {frame_id} (ids {ids.min()}..{ids.max()})")
    return joints[hit[0]]


# ---------------------------------------------------------------------------------- posed body
@dataclass
class Pose:
    """One pose (numpy float32, metres, world frame).

    joints (J, 3) (joints[0] = the root the methods centre on); body_vertices (V, 3) the subject's
    posed body and vtransf (V, 3, 3) its per-vertex skinning transforms, or None (joints only);
    mean_shape (V, 3) the posed mean-shape body centred on its own root (POP's pose input) or
    None; subject: the dataset subject the body belongs to (None for joints / an anny pose file);
    source: where it came from; velocity (J, 3) joint velocities in m/s (a dataset frame's, for
    models conditioned on them) or None (at rest); joint_rotvecs (24, 3) / root_translation (3,):
    the anny pose parameters it was posed from (an anny pose file, a motion frame), or None;
    motion: the last seconds of the body's motion before it
    (:class:`~pocoloco.data.motion_window.MotionWindow`, for models conditioned on them) or None
    (the body at rest).
    """

    joints: np.ndarray
    body_vertices: np.ndarray | None = None
    vtransf: np.ndarray | None = None
    mean_shape: np.ndarray | None = None
    subject: str | None = None
    source: str = ""
    velocity: np.ndarray | None = None
    joint_rotvecs: np.ndarray | None = None
    root_translation: np.ndarray | None = None
    motion: MotionWindow | None = None

    @property
    def has_body(self) -> bool:
        return self.body_vertices is not None and self.vtransf is not None

    @classmethod
    def from_joints(cls, joints: Any, any_pose: bool = False) -> Pose:
        """A pose from joints (24, 3) in metres (any array-like); a one-line error for a wrong shape,
        NaN / inf, or (unless ``any_pose``) a skeleton that is not a human body in metres."""
        arr = check_joints("joints", np.asarray(joints, dtype=np.float32), NUM_JOINTS)
        return cls(arr if any_pose else check_skeleton("joints", arr), source="joints")

    @classmethod
    def from_motion(cls, joints: Any, fps: float, seconds: float = 2.0, any_pose: bool = False) -> Pose:
        """The last frame of a joints sequence (T, 24, 3), metres, z up, at ``fps``, carrying the
        ``seconds`` of motion before it (what a ``--motion-window`` model reads; a sequence shorter
        than that holds its first frame before it); one-line errors as ``sample --motion``."""
        return motion_pose(joints, fps, seconds, any_pose=any_pose)[0]

    @classmethod
    def load(cls, spec: str | os.PathLike, frame_id: int | None = None, any_pose: bool = False) -> Pose:
        """A pose from anything ``--joints`` takes (:func:`load_joints`): ``demo:NAME``, a dataset
        frame ``DATASET:subject/split/sequence/index``, a ``.npy`` / ``.npz`` of joints, a joints text
        file (``frame_id``: its line), an anny pose ``.npz``; or a sequence's ``motion.npz``
        (``frame_id``: its frame, posed on the mean body). The joints only: a method that needs the
        posed body (POP, CloSET) poses it from ``source`` with its outfit's shape
        (:meth:`pocoloco.methods.Method.sample`)."""
        spec = os.fspath(spec)
        if Path(spec).name == "motion.npz" and Path(spec).is_file():
            motion = read_motion(spec)
            t = 0 if frame_id is None else int(frame_id)
            if not 0 <= t < len(motion.joint_rotvecs):
                raise ValueError(f"{spec}: frame {t} out of range (the motion has {len(motion.joint_rotvecs)} frames)")
            pose = pose_from_anny_params(motion.joint_rotvecs[t], motion.root_translation[t], {}, False, f"{spec}@{t}")
        elif is_anny_pose_file(spec) and frame_id is None:
            pose = pose_from_anny_file(spec, {}, False)
        else:
            joints = load_joints(spec, frame_id, NUM_JOINTS, any_pose=any_pose)
            return cls(joints, subject=outfit_of_spec(spec), source=spec)
        joints = pose.joints if any_pose else check_skeleton(spec, pose.joints)
        return cls(joints, source=pose.source, joint_rotvecs=pose.joint_rotvecs, root_translation=pose.root_translation)
        joints = load_joints(spec, frame_id, NUM_JOINTS, any_pose=any_pose)
        return cls(joints, subject=outfit_of_spec(spec), source=spec)


def subject_of_spec(spec: str) -> str | None:
    """The subject of a ``DATASET:subject/split/sequence/index`` spec, else None."""
    spec = os.fspath(spec)
    if ":" not in spec or spec.startswith("demo:") or Path(spec).exists():
        return None
    return spec.rpartition(":")[2].strip("/").split("/")[0] or None


def outfit_of_spec(spec: str) -> str | None:
    """The outfit a pose spec belongs to: the subject of a ``DATASET:...`` frame, the outfit a
    ``demo:NAME`` pose was captured on; None otherwise (and for an unknown demo name)."""
    spec = os.fspath(spec)
    if spec.startswith("demo:") and not Path(spec).exists():
        try:
            return demo_pose_outfit(spec[len("demo:"):])
        except ValueError:
            return None
    return subject_of_spec(spec)


class MeanShapeCache:
    """Posed mean-shape bodies (T, V, 3), centred on their root, per ``motion.npz`` (anny, cached)."""

    def __init__(self):
        self._cache: dict[str, np.ndarray] = {}

    def get(self, motion_path: Path, frame_index: int, whole_sequence: bool = True) -> np.ndarray:
        key = os.fspath(motion_path)
        if key not in self._cache:
            m = read_motion(motion_path)
            if frame_index >= len(m.joint_rotvecs):
                raise ValueError(f"{motion_path}: frame {frame_index} is beyond the motion ({len(m.joint_rotvecs)} frames)")
            if not whole_sequence:
                return pose_mean_shape_vertices(m.joint_rotvecs[frame_index : frame_index + 1])[0]
            self._cache[key] = pose_mean_shape_vertices(m.joint_rotvecs)
        verts = self._cache[key]
        if frame_index >= len(verts):
            raise ValueError(f"{motion_path}: frame {frame_index} is beyond the motion ({len(verts)} frames)")
        return verts[frame_index]


def motion_path_of(frame_path: Path) -> Path:
    """``.../<sequence>/frames/000123.npz`` -> ``.../<sequence>/motion.npz``."""
    return Path(frame_path).parent.parent / "motion.npz"


def pose_from_frame(frame_path: str | os.PathLike, subject: str | None, need_mean_shape: bool,
                    cache: MeanShapeCache | None = None, frame=None) -> Pose:  # fmt: skip
    """The posed body of a dataset frame file (and, if needed, the mean shape in its pose)."""
    path = Path(frame_path)
    fr = frame if frame is not None else read_frame(path, ["joints", "frame_index", "body_vertices", "vtransf"],
                                                    allow_missing=True)  # fmt: skip
    if fr.body_vertices is None or fr.vtransf is None:
        raise ValueError(f"{path}: frame has no posed body (body_vertices / vtransf); POP, CloSET and PocoLoco "
                         "with --body-points need it")  # fmt: skip
    mean = None
    if need_mean_shape:
        mean = (cache or MeanShapeCache()).get(motion_path_of(path), int(fr.frame_index), whole_sequence=cache is not None)
    return Pose(np.asarray(fr.joints, np.float32), np.asarray(fr.body_vertices, np.float32),
                np.asarray(fr.vtransf, np.float32), mean, subject, os.fspath(path))  # fmt: skip


def pose_from_anny_file(path: str | os.PathLike, phenotype: dict[str, float], need_mean_shape: bool) -> Pose:
    """An ``.npz`` with ``joint_rotvecs`` (24, 3) anny axis-angle rotations (as in ``motion.npz``;
    optional ``root_translation`` (3,)) -> the body of ``phenotype`` in that pose."""
    src = os.fspath(path)
    try:
        with np.load(src, allow_pickle=False) as z:
            rot = np.asarray(z["joint_rotvecs"], np.float32)
            trans = np.asarray(z["root_translation"], np.float32) if "root_translation" in z.files else None
    except Exception as e:  # KeyError, ValueError, OSError, zipfile.BadZipFile ...
        why = numpy_file_problem(src, "npz") or f"{type(e).__name__}: {e}"
        raise ValueError(f"{src}: cannot read anny pose parameters ({why})") from None
    if rot.ndim == 3 and rot.shape[0] == 1:
        rot = rot[0]
    if rot.shape != (NUM_JOINTS, 3) or not np.isfinite(rot).all():
        raise ValueError(f"{src}: joint_rotvecs must be a finite ({NUM_JOINTS}, 3) array, got {rot.shape}")
    if trans is not None:
        trans = trans.reshape(-1)[:3] if trans.size >= 3 else None
    return pose_from_anny_params(rot, trans, phenotype, need_mean_shape, src)


def pose_from_anny_params(joint_rotvecs: np.ndarray, root_translation: np.ndarray | None,
                          phenotype: dict[str, float], need_mean_shape: bool, source: str) -> Pose:  # fmt: skip
    """The body of ``phenotype`` posed with anny pose parameters ``joint_rotvecs`` (24, 3) and
    ``root_translation`` (3,) or None (the parameters are kept on the pose)."""
    rot = np.asarray(joint_rotvecs, np.float32)
    trans = None if root_translation is None else np.asarray(root_translation, np.float32)
    posed = AnnyBody(phenotype).pose(rot[None], None if trans is None else trans[None])
    mean = None
    if need_mean_shape:
        mean = pose_mean_shape_vertices(rot[None])[0]
    return Pose(posed.joints[0], posed.vertices[0], posed.vtransf[0], mean, None, source, joint_rotvecs=rot,
                root_translation=trans)  # fmt: skip


def is_anny_pose_file(spec: str) -> bool:
    """True for an existing ``.npz`` holding ``joint_rotvecs``."""
    p = Path(spec)
    if p.suffix != ".npz" or not p.is_file():
        return False
    try:
        with np.load(p, allow_pickle=False) as z:
            return "joint_rotvecs" in z.files
    except Exception:
        return False


def pose_spec_kind(spec: str) -> str:
    """"dataset" (DATASET:subject/split/sequence/index), "anny" (.npz with joint_rotvecs, or demo:NAME) or "frame"
    (a frame .npz inside a dataset); anything else (bare joints) is a one-line error."""
    path = Path(spec)
    if spec.startswith("demo:") and not path.exists():
        demo_pose_path(spec[len("demo:"):])  # an unknown name: the one-line error
        return "anny"
    if not path.exists() and ":" in spec and not spec.startswith("demo:"):
        return "dataset"
    if is_anny_pose_file(spec):
        return "anny"
    if path.suffix == ".npz" and path.is_file() and path.parent.name == "frames" and \
            (path.parent.parent / "motion.npz").is_file():  # fmt: skip
        return "frame"
    raise ValueError(f"{spec}: POP, CloSET and PocoLoco with --body-points need the posed body, not only joints: pass a dataset frame "
                     "DATASET:subject/split/sequence/index, demo:NAME or an .npz with anny pose parameters 'joint_rotvecs' (24, 3)")


def load_body_pose(spec: str, phenotype: dict[str, float] | None, need_mean_shape: bool) -> Pose:
    """A pose with its posed body (what POP, CloSET and PocoLoco with ``--body-points`` take): a
    dataset frame ``DATASET:subject/split/sequence/index``, a frame ``.npz`` inside a dataset, or an
    ``.npz`` of anny pose parameters posed with ``phenotype``; bare joints are a one-line error."""
    spec = str(spec)
    if spec.startswith("demo:") and not Path(spec).exists():
        pose = pose_from_anny_file(demo_pose_path(spec[len("demo:"):]), phenotype or {}, need_mean_shape)
        pose.subject, pose.source = outfit_of_spec(spec), spec
        return pose
    kind = pose_spec_kind(spec)
    if kind == "dataset":
        return pose_from_frame(dataset_frame_path(spec), subject_of_spec(spec), need_mean_shape)
    if kind == "anny":
        return pose_from_anny_file(spec, phenotype or {}, need_mean_shape)
    path = Path(spec)
    return pose_from_frame(path, path.parent.parent.parent.parent.name, need_mean_shape)
