"""PyTorch dataset over a pocoloco dataset folder, with PocoLoco's normalisation.

Normalisation (as in the PocoLoco paper's public code):
points and joints are centred on the root joint of their frame, then the
dataset-wide per-axis mean is subtracted and the result divided by one scalar
std; both statistics are computed on the training split and stored in
``card.json``::

    x_norm = (x - root - mean) / std            root = joints[root_joint]
    x      = x_norm * std + mean + root         (Normalisation.denormalise)

Samplers return points in the normalised frame; ``denormalise`` with the
frame's root maps them back to metres in the input (world) frame.

``heading=True`` (not in the paper; ``pocoloco train --canonical-heading``) also turns every frame
about the vertical (Z) axis through its root so that the body faces one way (the hips' and
shoulders' left-to-right direction along +X), before the mean and std::

    x_norm = (Rz(-a) (x - root) - mean) / std    a = Normalisation.angle(joints)
    x      = Rz(a) (x_norm * std + mean) + root

A body turned about the vertical then gives the same normalised cloud, so the model need not
learn each garment in every facing direction (POP and CloSET get this from their body-local
frames).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from . import format as fmt
from .frame import FRAME_FILE_NAME
from .motion_window import (
    DEFAULT_HZ,
    MotionHistory,
    MotionWindow,
    augmented_window,
    heading_of,
    motion_feature_dim,
    motion_features,
    read_motion_history,
    window_samples,
)

__all__ = ["Normalisation", "OpenedDataset", "PointCloudDataset", "frame_history", "frame_motion_window", "frame_velocity",
           "rotate_z", "sequence_history", "window_features"]

#: frames per second of a dataset whose card does not record it (the synthetic presets' rate)
DEFAULT_FPS = 25.0
#: the 24-joint skeleton's (left, right) hips and shoulders, whose left-to-right directions give the heading
HEADING_PAIRS = ((1, 2), (16, 17))


def rotate_z(x, angle):
    """Vectors x (..., N, 3) turned by ``angle`` (...,) radians about +Z (numpy or torch, like x)."""
    if isinstance(x, torch.Tensor):
        a = torch.as_tensor(angle, dtype=x.dtype, device=x.device)[..., None]
        c, s = torch.cos(a), torch.sin(a)
        return torch.stack([c * x[..., 0] - s * x[..., 1], s * x[..., 0] + c * x[..., 1], x[..., 2]], dim=-1)
    a = np.asarray(angle, dtype=np.float64)[..., None]
    c, s = np.cos(a), np.sin(a)
    out = np.stack([c * x[..., 0] - s * x[..., 1], s * x[..., 0] + c * x[..., 1], x[..., 2]], axis=-1)
    return out.astype(np.result_type(x.dtype, np.float32), copy=False)


@dataclass(frozen=True)
class Normalisation:
    """Root-centring (and, with ``heading``, turning the body to face one way; module docstring)
    plus one per-axis mean and one scalar std.

    mean: (3,) float, metres. std: float > 0, metres. root_joint: index of the root joint.
    heading: canonicalise the facing direction about +Z (24-joint skeletons only).
    Works on numpy arrays and torch tensors of shape (..., N, 3) / (..., J, 3).
    """

    mean: tuple[float, float, float]
    std: float
    root_joint: int = 0
    heading: bool = False

    def __post_init__(self) -> None:
        if len(self.mean) != 3:
            raise ValueError(f"Normalisation.mean must have 3 values, got {len(self.mean)}")
        if not (np.isfinite(self.std) and self.std > 0):
            raise ValueError(f"Normalisation.std must be finite and > 0, got {self.std}")

    @classmethod
    def from_card(cls, card: dict[str, Any]) -> Normalisation:
        """Read ``card["normalisation"]``; a clear ValueError if the card has none."""
        norm = card.get("normalisation")
        if not norm:
            raise ValueError("dataset card has no 'normalisation' (no complete train split yet): finish the dataset by "
                             "rerunning the same `pocoloco data synth` command, or add train frames with "
                             "`pocoloco data import ... --split train`")  # fmt: skip
        return cls(mean=tuple(float(x) for x in norm["mean"]), std=float(norm["std"]),
                   root_joint=int(norm.get("root_joint", 0)))  # fmt: skip

    @classmethod
    def identity(cls) -> Normalisation:
        """Root-centring only (mean 0, std 1)."""
        return cls(mean=(0.0, 0.0, 0.0), std=1.0)

    def matches(self, other: Normalisation, tol: float = 1e-3) -> bool:
        """Whether ``other`` is this normalisation up to ``tol`` of the std in its mean and ``tol``
        relative in its std, with the same root joint and heading: the same data made again (a
        regenerated dataset's statistics move in their last digits, a different dataset's by mm)."""
        return (self.root_joint == other.root_joint and self.heading == other.heading
                and abs(self.std - other.std) <= tol * self.std
                and max(abs(a - b) for a, b in zip(self.mean, other.mean)) <= tol * self.std)  # fmt: skip

    def _mean_like(self, x):
        if isinstance(x, torch.Tensor):
            return torch.tensor(self.mean, dtype=x.dtype, device=x.device)
        return np.asarray(self.mean, dtype=x.dtype)

    def root(self, joints):
        """(..., J, 3) -> (..., 3) the root joint."""
        return joints[..., self.root_joint, :]

    def angle(self, joints):
        """(..., J, 3) joints -> (...,) the heading angle (radians) that ``normalise`` turns away:
        the angle about +Z of the summed left-to-right hip and shoulder directions; zeros without
        ``heading`` (numpy float64, or torch like ``joints``)."""
        torch_in = isinstance(joints, torch.Tensor)
        if not self.heading:
            return torch.zeros(joints.shape[:-2], dtype=joints.dtype, device=joints.device) if torch_in else \
                np.zeros(joints.shape[:-2])  # fmt: skip
        if joints.shape[-2] <= max(max(p) for p in HEADING_PAIRS):
            raise ValueError(f"heading canonicalisation needs the 24-joint skeleton, got {joints.shape[-2]} joints")
        across = sum(joints[..., left, :] - joints[..., right, :] for left, right in HEADING_PAIRS)
        if torch_in:
            return torch.atan2(across[..., 1], across[..., 0])
        return np.arctan2(np.asarray(across[..., 1], np.float64), np.asarray(across[..., 0], np.float64))

    def normalise(self, points, joints):
        """points (..., N, 3), joints (..., J, 3) in metres -> both normalised (same types)."""
        root = self.root(joints)[..., None, :]
        mean = self._mean_like(points)
        p, j = points - root, joints - root
        if self.heading:
            a = -self.angle(joints)
            p, j = rotate_z(p, a), rotate_z(j, a)
        return (p - mean) / self.std, (j - mean) / self.std

    def denormalise(self, points, root, angle=None):
        """points (..., N, 3) normalised, root (..., 3) in metres -> points (..., N, 3) in metres.
        angle (...,): the frame's :meth:`angle`, required with ``heading``."""
        p = points * self.std + self._mean_like(points)
        if self.heading:
            if angle is None:
                raise ValueError("this normalisation turns bodies to face one way: denormalise needs the frame's angle")
            p = rotate_z(p, angle)
        return p + root[..., None, :]

    def normalise_velocity(self, velocity, joints):
        """(..., J, 3) joint velocities (m/s, world) -> the normalised frame of ``joints``: turned
        like the points (with ``heading``) and divided by the std (no centring: a velocity)."""
        v = rotate_z(velocity, -self.angle(joints)) if self.heading else velocity
        return v / self.std

    def normalise_motion(self, window: MotionWindow, joints) -> np.ndarray:
        """A motion window (heading frame of the pose ``joints`` (J, 3), metres) -> its (J, F) network
        features in the normalised frame of ``joints`` (:func:`~pocoloco.data.motion_window.motion_features`:
        turned out of the heading frame, less the angle this normalisation turns away, lengths / std)."""
        return motion_features(window, heading_of(joints) - float(self.angle(np.asarray(joints))), self.std)


def frame_velocity(path: str | os.PathLike, joints: np.ndarray, fps: float | None = None) -> np.ndarray:
    """(J, 3) float32 joint velocities (m/s) of the frame file ``path`` with ``joints``: the
    difference to the previous stored frame of its sequence (the next one at the sequence's start,
    or across one rejected frame, divided by the frame gap); zeros for a frame with no neighbour
    (a body at rest). fps: frames per second (None: the sequence's ``sequence.json``, else
    ``DEFAULT_FPS``)."""
    folder, name = os.path.split(os.fspath(path))
    if fps is None:
        try:
            fps = float(fmt.read_sequence_meta(os.path.join(os.path.dirname(folder), "sequence.json")).get("fps")
                        or DEFAULT_FPS)  # fmt: skip
        except (OSError, ValueError, TypeError):
            fps = DEFAULT_FPS
    stem, ext = os.path.splitext(name)
    if not stem.isdigit():
        return np.zeros_like(np.asarray(joints, np.float32))
    index = int(stem)
    for other in (index - 1, index + 1, index - 2, index + 2):
        neighbour = os.path.join(folder, f"{other:0{len(stem)}d}{ext}")
        if other >= 0 and os.path.exists(neighbour):
            other_joints = fmt.read_frame(neighbour, ["joints"]).joints
            return ((np.asarray(joints, np.float64) - other_joints) * fps / (index - other)).astype(np.float32)
    return np.zeros_like(np.asarray(joints, np.float32))


def sequence_history(sequence_dir: str | os.PathLike, fps: float | None = None) -> MotionHistory:
    """A dataset sequence's whole motion (issue 41): its ``motion_history.npz`` (``pocoloco data
    motion-history`` writes it for a synthetic dataset: the motion before the first stored frame
    too), else the stored frames' skeletons (``padded``: windows reaching before the first stored
    frame hold it; a rejected frame holds the one before it). fps: None reads ``sequence.json``."""
    folder = Path(sequence_dir)
    if (folder / "motion_history.npz").is_file():
        return read_motion_history(folder / "motion_history.npz")
    if fps is None:
        try:
            fps = float(fmt.read_sequence_meta(folder / "sequence.json").get("fps") or DEFAULT_FPS)
        except (OSError, ValueError, TypeError):
            fps = DEFAULT_FPS
    names = sorted(n for n in os.listdir(folder / "frames") if FRAME_FILE_NAME.match(n)) \
        if (folder / "frames").is_dir() else []  # fmt: skip
    if not names:
        raise ValueError(f"{folder}: no frames to take a motion from")
    stored = {int(FRAME_FILE_NAME.match(n).group(1)): fmt.read_frame(folder / "frames" / n, ["joints"]).joints
              for n in names}  # fmt: skip
    joints, last = [], stored[min(stored)]
    for i in range(max(stored) + 1):
        last = stored.get(i, last)
        joints.append(last)
    return MotionHistory(np.stack(joints).astype(np.float32), float(fps), 0, padded=True)


def window_features(history: MotionHistory, frame: int, seconds: float, normalisation: Normalisation,
                    joints: np.ndarray, rng: np.random.Generator | None = None) -> torch.Tensor:  # fmt: skip
    """(J, F) the motion-window features of stored frame ``frame`` of ``history`` in the frame's
    normalised point frame (``joints`` (J, 3) its skeleton, metres): the last ``seconds`` at 8 Hz
    (:func:`~pocoloco.data.motion_window.motion_features`); ``rng``: training's augmentation
    (:func:`~pocoloco.data.motion_window.augmented_window`)."""
    window = history.window(frame, seconds) if rng is None else augmented_window(history, frame, seconds, rng)
    return torch.from_numpy(normalisation.normalise_motion(window, joints))


_HISTORIES: dict[str, MotionHistory] = {}
#: sequences whose histories :func:`frame_history` keeps (~20 KB each for `medium`'s 60 rows)
_HISTORIES_KEPT = 1024


def frame_history(path: str | os.PathLike) -> tuple[MotionHistory, int]:
    """(its sequence's :func:`sequence_history`, its stored frame index) for the dataset frame file
    ``path`` (``.../<sequence>/frames/000123.npz``); histories cached per sequence folder."""
    path = Path(path)
    folder = str(path.parent.parent)
    if folder not in _HISTORIES:
        if len(_HISTORIES) >= _HISTORIES_KEPT:
            _HISTORIES.clear()
        _HISTORIES[folder] = sequence_history(folder)
    history, frame = _HISTORIES[folder], int(path.stem)
    if history.first + frame >= len(history.joints):
        raise ValueError(f"{path}: frame {frame} is beyond its sequence's motion ({len(history.joints)} frames)")
    return history, frame


def frame_motion_window(path: str | os.PathLike, seconds: float, hz: float = DEFAULT_HZ) -> MotionWindow:
    """The motion window of the dataset frame file ``path``: the last ``seconds`` of its sequence's
    motion (:func:`frame_history`)."""
    history, frame = frame_history(path)
    return history.window(frame, seconds, hz)


@dataclass(frozen=True)
class OpenedDataset:
    """A dataset folder opened once per command and handed down instead of its path: the card (read
    once), the layout, and the subjects whose frame files were already checked against the card
    (:func:`pocoloco.data.format.check_frames`), so that the tasks and datasets built from it read
    and scan nothing again. It is an ``os.PathLike`` of the folder (``os.fspath`` / ``str`` give the
    path), so code that only needs the path takes it unchanged."""

    root: str
    card: dict[str, Any]
    layout: fmt.DatasetLayout
    checked: frozenset[str] = frozenset()

    @classmethod
    def open(cls, root: str | os.PathLike, subjects: Sequence[str] | None = None) -> OpenedDataset:
        """Read the card and check the frame files of ``subjects`` (None: every subject); one-line
        ValueErrors for a missing / malformed card or a damaged frame."""
        if isinstance(root, OpenedDataset):
            return root.ensure_checked(subjects)
        root = os.fspath(root)
        return cls(root, fmt.read_card(root), fmt.DatasetLayout(root)).ensure_checked(subjects)

    def ensure_checked(self, subjects: Sequence[str] | None = None) -> OpenedDataset:
        """This dataset with the frames of ``subjects`` (None: all) checked: itself if they were."""
        names = sorted(self.card["subjects"]) if subjects is None else sorted(subjects)
        todo = [s for s in names if s not in self.checked and s in self.card["subjects"]]
        if not todo:
            return self
        fmt.check_frames(self.root, subjects=todo, card=self.card)
        return dataclasses.replace(self, checked=self.checked | frozenset(todo))

    def __fspath__(self) -> str:
        return self.root

    def __str__(self) -> str:
        return self.root


class PointCloudDataset(Dataset):
    """Frames of one split of a pocoloco dataset, as dicts of tensors.

    Each item::

        points:    (N, 3) float32, normalised (or root-centred only if normalise=False)
        joints:    (24, 3) float32, same transform
        root:      (3,) float32, the root joint in metres (to invert the normalisation)
        angle:     () float32, the heading turned away (``heading=True``; else 0)
        velocity:  (24, 3) float32 joint velocities (:func:`frame_velocity`), normalised
                   (``Normalisation.normalise_velocity``; only if ``velocity``)
        normals:   (N, 3) float32 (only if with_normals), turned like the points
        labels:    (N,) int64 point classes (``format.LABEL_UNKNOWN`` for imported data)
        body:      (K, 3) float32 posed-body vertices ``body_vertices[body_point_ids]``, same
                   transform (only if ``body_point_ids``)
        subject:   int, index into ``dataset.subject_names``
        frame_key: str, "<subject>/<split>/<sequence>/<frame index>"

    N = ``num_points`` points are drawn without replacement from the frame's
    points (None: keep all). ``random_subsample=True`` draws a new subset on
    every access from torch's global RNG (seeded by ``torch.manual_seed`` and
    per worker by ``DataLoader``), so epochs and workers differ;
    ``random_subsample=False`` draws a fixed subset per index from
    ``seed``. ``heading``: turn every frame to face one way (:class:`Normalisation`). ``velocity``: also
    give each frame's joint velocities. A frame with fewer than ``num_points`` points raises.

    A dataset whose frame files (of any split of these subjects) disagree with its card or
    ``sequence.json`` files (a missing, extra, truncated or unreadable frame;
    :func:`pocoloco.data.format.check_frames`) is refused with a one-line ``ValueError``. ``root``
    may be an :class:`OpenedDataset` (its card and checks are reused).
    """

    def __init__(
        self,
        root: str | os.PathLike | OpenedDataset,
        split: str = "train",
        num_points: int | None = 10_000,
        subjects: Sequence[str] | None = None,
        normalise: bool = True,
        with_normals: bool = False,
        seed: int = 0,
        random_subsample: bool = True,
        body_point_ids: Sequence[int] | None = None,
        heading: bool = False,
        velocity: bool = False,
        motion_window: float = 0.0,
    ):
        opened = OpenedDataset.open(root, subjects=[])  # the card (read here unless the caller opened it)
        self.root = opened.root
        self.body_point_ids = None if body_point_ids is None else np.asarray(body_point_ids, np.int64)
        self.card = opened.card
        if split not in fmt.SPLITS:
            raise ValueError(f"unknown split {split!r}; expected one of {fmt.SPLITS}")
        if num_points is not None and num_points < 1:
            raise ValueError(f"num_points must be >= 1 or None, got {num_points}")
        self.subject_names: list[str] = sorted(self.card["subjects"])
        if subjects is not None:
            if isinstance(subjects, str):
                subjects = [subjects]
            unknown = [s for s in subjects if s not in self.card["subjects"]]
            if unknown:
                raise ValueError(f"{self.root}: unknown subjects {unknown}; the card lists {self.subject_names}")
        self.split = split
        self.num_points = num_points
        self.with_normals = with_normals
        self.seed = seed
        self.random_subsample = random_subsample
        self.normalisation = Normalisation.from_card(self.card) if normalise else Normalisation.identity()
        if heading:
            self.normalisation = dataclasses.replace(self.normalisation, heading=True)
        self.velocity = velocity
        if not (np.isfinite(motion_window) and motion_window >= 0):
            raise ValueError(f"motion_window must be >= 0 seconds, got {motion_window}")
        self.motion_window = float(motion_window)
        self._histories: dict[tuple[str, str], MotionHistory] = {}
        self.fps = float((self.card.get("generation_config") or {}).get("fps") or DEFAULT_FPS)
        self.layout = opened.layout
        chosen = self.subject_names if subjects is None else sorted(subjects)
        opened.ensure_checked(chosen)  # every split: one line on a bad frame (once per opened dataset)
        self.frames = self.layout.iter_frames(split, chosen)  # list of (subject, sequence, path)
        if not self.frames:
            raise ValueError(f"{self.root}: no frames in split {split!r} for subjects {chosen}")
        self._subject_id = {s: i for i, s in enumerate(self.subject_names)}

    def __len__(self) -> int:
        return len(self.frames)

    def frame_key(self, index: int) -> str:
        subject, sequence, path = self.frames[index]
        return f"{subject}/{self.split}/{sequence}/{os.path.basename(path)[:-4]}"

    def _choose(self, index: int, n: int, path: str) -> np.ndarray | slice:
        k = self.num_points
        if k is None:
            return slice(None)
        if n < k:
            raise ValueError(f"{path}: frame has {n} points, fewer than num_points={k}")
        if self.random_subsample:
            # one draw from torch's global RNG seeds numpy (faster than torch.randperm at 40K points)
            rng = np.random.default_rng(int(torch.randint(0, 2**62, ())))
            return rng.choice(n, size=k, replace=False)
        rng = np.random.default_rng([self.seed, index])
        return np.sort(rng.choice(n, size=k, replace=False))

    def __getitem__(self, index: int) -> dict[str, Any]:
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} frames")
        subject, _, path = self.frames[index]
        keys = ["points", "joints", "labels"] + (["normals"] if self.with_normals else [])
        if self.body_point_ids is not None:
            keys.append("body_vertices")
        fr = fmt.read_frame(path, keys, allow_missing=True)
        sel = self._choose(index, fr.points.shape[0], path)
        points, joints = self.normalisation.normalise(fr.points[sel], fr.joints)
        angle = self.normalisation.angle(fr.joints)  # the heading turned away (0 without heading)
        labels = fr.labels[sel] if fr.labels is not None else np.full(len(points), fmt.LABEL_UNKNOWN, np.uint8)
        item: dict[str, Any] = {
            "points": torch.from_numpy(np.ascontiguousarray(points, np.float32)),
            "joints": torch.from_numpy(np.ascontiguousarray(joints, np.float32)),
            "root": torch.from_numpy(self.normalisation.root(fr.joints).astype(np.float32)),
            "angle": torch.tensor(float(angle), dtype=torch.float32),
            "labels": torch.from_numpy(labels.astype(np.int64)),
            "subject": self._subject_id[subject],
            "frame_key": self.frame_key(index),
        }
        if self.velocity:
            v = self.normalisation.normalise_velocity(frame_velocity(path, fr.joints, self.fps), fr.joints)
            item["velocity"] = torch.from_numpy(np.ascontiguousarray(v, np.float32))
        if self.motion_window:
            item["motion"] = self.motion_features(index, fr.joints)
        if self.with_normals:
            normals = fr.normals[sel]
            if self.normalisation.heading:  # directions turn with the body
                normals = rotate_z(normals, -angle)
            item["normals"] = torch.from_numpy(np.ascontiguousarray(normals, np.float32))
        if self.body_point_ids is not None:
            if fr.body_vertices is None:
                raise ValueError(f"{path}: frame has no posed body (body_vertices), which --body-points needs")
            if int(self.body_point_ids.max()) >= len(fr.body_vertices):
                raise ValueError(f"{path}: body has {len(fr.body_vertices)} vertices, fewer than the body point ids need")
            body = self.normalisation.normalise(fr.body_vertices[self.body_point_ids], fr.joints)[0]
            item["body"] = torch.from_numpy(np.ascontiguousarray(body, np.float32))
        return item

    # ----------------------------------------------------------------- motion windows (issue 41)
    def history(self, subject: str, sequence: str) -> MotionHistory:
        """The sequence's whole motion: its ``motion_history.npz`` (``pocoloco data motion-history``
        writes it for a synthetic dataset), else the stored frames' skeletons (``padded``: windows
        reaching before the first stored frame hold it). Cached per sequence."""
        key = (subject, sequence)
        if key not in self._histories:
            self._histories[key] = sequence_history(self.layout.sequence_dir(subject, self.split, sequence), self.fps)
        return self._histories[key]

    def motion_features(self, index: int, joints: np.ndarray | None = None,
                        rng: np.random.Generator | None = None) -> torch.Tensor:  # fmt: skip
        """(J, F) the motion-window features of frame ``index`` (``motion_window`` seconds at 8 Hz,
        :func:`~pocoloco.data.motion_window.motion_features`), in the frame's normalised point frame.
        ``rng``: training's augmentation (time-warp +-15 %, past samples jittered by up to one
        frame, 5 mm noise on the past joints). ``joints``: the frame's (J, 3), if already read (else its
        history's row, the same skeleton: no file is read again)."""
        subject, sequence, path = self.frames[index]
        frame = int(os.path.basename(path)[:-4])
        history = self.history(subject, sequence)
        if joints is None:
            joints = history.joints[history.first + frame]
        return window_features(history, frame, self.motion_window, self.normalisation, joints, rng)

    @property
    def motion_feature_dim(self) -> int:
        """F of the frames' motion features (0 without a motion window)."""
        return motion_feature_dim(window_samples(self.motion_window, DEFAULT_HZ)) if self.motion_window else 0
