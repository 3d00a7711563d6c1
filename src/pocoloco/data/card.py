"""The dataset folder's layout and its card (``card.json``): what the dataset is, its counts,
normalisation, pose coverage, and the size + CRC-32 record of every frame file (written by
:func:`refresh_card`, read by the checks of :mod:`pocoloco.data.verify`; the record format lives
here, with the card that holds it)."""

from __future__ import annotations

import datetime
import os
import zipfile
import zlib
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..body.skeleton import JOINT_NAMES, JOINT_PARENTS
from ..utils.atomic import write_json_atomic
from .frame import FRAME_FILE_NAME, read_frame, read_json, read_sequence_meta


FORMAT_NAME = "pocoloco-dataset"
FORMAT_VERSION = 1
#: ``heldout``: test-style motions from other seeds than ``test`` (``SynthConfig.heldout_sequences``);
#: absent from most datasets (its folders are simply missing)
SPLITS: tuple[str, ...] = ("train", "test", "heldout")

# --------------------------------------------------------------------------- layout and card
class DatasetLayout:
    """Paths (``pathlib.Path``) inside a dataset folder. Pure path arithmetic plus directory listing."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    @property
    def card_path(self) -> Path:
        return self.root / "card.json"

    def subject_dir(self, subject: str) -> Path:
        return self.root / "subjects" / subject

    def subject_path(self, subject: str) -> Path:
        return self.subject_dir(subject) / "subject.npz"

    def split_dir(self, subject: str, split: str) -> Path:
        check_split(split)
        return self.subject_dir(subject) / split

    def sequence_dir(self, subject: str, split: str, sequence: str) -> Path:
        return self.split_dir(subject, split) / sequence

    def sequence_meta_path(self, subject: str, split: str, sequence: str) -> Path:
        return self.sequence_dir(subject, split, sequence) / "sequence.json"

    def motion_path(self, subject: str, split: str, sequence: str) -> Path:
        return self.sequence_dir(subject, split, sequence) / "motion.npz"

    def motion_history_path(self, subject: str, split: str, sequence: str) -> Path:
        """The sequence's whole motion, before its first stored frame too (issue 41's windows)."""
        return self.sequence_dir(subject, split, sequence) / "motion_history.npz"

    def frames_dir(self, subject: str, split: str, sequence: str) -> Path:
        return self.sequence_dir(subject, split, sequence) / "frames"

    def frame_path(self, subject: str, split: str, sequence: str, index: int) -> Path:
        if index < 0:
            raise ValueError(f"frame index must be >= 0, got {index}")
        return self.frames_dir(subject, split, sequence) / f"{index:06d}.npz"

    def subjects(self) -> list[str]:
        """Subject folders present on disk, sorted."""
        d = self.root / "subjects"
        return sorted(p.name for p in d.iterdir() if p.is_dir()) if d.is_dir() else []

    def sequences(self, subject: str, split: str) -> list[str]:
        """Sequence folders of a subject's split present on disk, sorted."""
        d = self.split_dir(subject, split)
        return sorted(p.name for p in d.iterdir() if p.is_dir()) if d.is_dir() else []

    @staticmethod
    def sequence_key(subject: str, split: str, sequence: str) -> str:
        """``"<subject>/<split>/<sequence>"``: how the card's ``frame_files`` names a sequence."""
        check_split(split)
        return f"{subject}/{split}/{sequence}"

    def frame_indices(self, subject: str, split: str, sequence: str) -> list[int]:
        """Indices of the frame files present, sorted (temporary files are ignored)."""
        d = self.frames_dir(subject, split, sequence)
        if not d.is_dir():
            return []
        return sorted(int(m.group(1)) for n in os.listdir(d) if (m := FRAME_FILE_NAME.match(n)))

    def iter_frames(self, split: str, subjects: Sequence[str] | None = None) -> list[tuple[str, str, Path]]:
        """All frames of a split as (subject, sequence, frame_path), sorted by subject, sequence, index."""
        check_split(split)
        out = []
        for s in self.subjects() if subjects is None else subjects:
            for seq in self.sequences(s, split):
                for i in self.frame_indices(s, split, seq):
                    out.append((s, seq, self.frame_path(s, split, seq, i)))
        return out


def check_split(split: str) -> None:
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")


def _pocoloco_version() -> str:
    return __version__


def make_card(
    *,
    subjects: Mapping[str, Mapping[str, Any]],
    generation_config: Mapping[str, Any] | None = None,
    counts: Mapping[str, Any] | None = None,
    normalisation: Mapping[str, Any] | None = None,
    loose_share: Mapping[str, float] | None = None,
    label_names: Sequence[str] | None = None,
) -> dict[str, Any]:
    """A new card dict with the format header, skeleton, creation time and version filled in.

    subjects: {name: {"garment_kind": str, "phenotype": {...}, ...}}.
    counts:   {subject: {split: {"sequences": int, "frames": int, "rejected_frames": int}}}.
    normalisation: {"root_joint": 0, "mean": [3], "std": float, "computed_on": "train"}.
    loose_share: {subject: fraction of points labelled loose garment}.
    label_names: name of each point label value (index = value), e.g. ["body", "tight", "loose"].
    """
    return {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "pocoloco_version": _pocoloco_version(),
        "generation_config": dict(generation_config or {}),
        "skeleton": {"joint_names": list(JOINT_NAMES), "parents": list(JOINT_PARENTS)},
        "subjects": {k: dict(v) for k, v in subjects.items()},
        "counts": {k: dict(v) for k, v in (counts or {}).items()},
        "normalisation": dict(normalisation) if normalisation is not None else None,
        "loose_share": dict(loose_share or {}),
        "label_names": list(label_names or []),
    }


def validate_card(src: str, card: Any) -> None:
    if not isinstance(card, dict):
        raise ValueError(f"{src}: card must be a JSON object")
    if card.get("format") != FORMAT_NAME:
        found = card.get("format")
        raise ValueError(f"{src}: not a pocoloco dataset card (format is {found!r}, expected {FORMAT_NAME!r})")
    if card.get("version") != FORMAT_VERSION:
        found = card.get("version")
        raise ValueError(f"{src}: unsupported dataset format version {found!r} (this code reads {FORMAT_VERSION})")
    if not isinstance(card.get("subjects"), dict):
        raise ValueError(f"{src}: card has no 'subjects' object")
    norm = card.get("normalisation")
    if norm is not None:
        ok = (
            isinstance(norm, dict)
            and isinstance(norm.get("mean"), list) and len(norm["mean"]) == 3
            and isinstance(norm.get("std"), (int, float)) and norm["std"] > 0
        )  # fmt: skip
        if not ok:
            want = "{'mean': [3 floats], 'std': float > 0, ...}"
            raise ValueError(f"{src}: 'normalisation' must be {want}, got {norm!r}")
    files = card.get("frame_files")
    if files is not None and not (isinstance(files, dict) and all(isinstance(v, dict) for v in files.values())):
        raise ValueError(f"{src}: 'frame_files' must be {{'<subject>/<split>/<sequence>': {{'<frame>.npz': "
                         f"[bytes, crc32]}}}}")  # fmt: skip


def read_card(root: str | os.PathLike) -> dict[str, Any]:
    """Read and validate ``<root>/card.json``.

    Raises ``ValueError`` naming the path when the folder is not a pocoloco
    dataset (no card), the JSON is malformed, the format name or version differ.
    """
    root = os.fspath(root)
    path = os.path.join(root, "card.json")
    if not os.path.isdir(root):
        raise ValueError(f"{root}: not a pocoloco dataset (no such folder)")
    if not os.path.isfile(path):
        raise ValueError(f"{root}: not a pocoloco dataset (no card.json)")
    card = read_json(path, "card.json")
    validate_card(path, card)
    return card


def write_card(root: str | os.PathLike, card: Mapping[str, Any], exclusive: bool = False) -> bool:
    """Validate ``card`` (format name, version, subjects, normalisation) and write it atomically.

    exclusive: only create the card: if ``card.json`` exists (another process wrote it first)
    leave it and return False. Returns True when the card was written."""
    path = os.path.join(os.fspath(root), "card.json")
    card = dict(card)
    validate_card(path, card)
    try:
        write_json_atomic(path, card, exclusive=exclusive)
    except FileExistsError:
        if not exclusive:
            raise
        return False
    return True


# --------------------------------------------------------------------------- statistics
def compute_normalisation(frame_paths: Iterable[str | os.PathLike], root_joint: int = 0) -> dict[str, Any]:
    """Dataset normalisation: per-axis mean and one scalar std of root-centred points.

    For every frame, c = points - joints[root_joint] (N, 3). Over all points of
    all frames (each point weighs the same): mean = (3,) per-axis mean of c,
    std = sqrt(mean over all points and all 3 axes of (c - mean)^2).

    Streaming: one frame in memory at a time (only ``points`` and ``joints``
    are read); per-frame moments are merged with Chan et al.'s parallel
    variance update in float64.

    Returns {"root_joint", "mean": [3 floats], "std": float, "num_frames", "num_points"}.
    """
    count = 0
    mean = np.zeros(3)
    m2 = np.zeros(3)  # per-axis sum of squared deviations from the running mean
    num_frames = 0
    for p in frame_paths:
        fr = read_frame(p, ("points", "joints"))
        c = fr.points.astype(np.float64) - fr.joints[root_joint].astype(np.float64)
        n_b = c.shape[0]
        mean_b = c.mean(axis=0)
        m2_b = ((c - mean_b) ** 2).sum(axis=0)
        total = count + n_b
        delta = mean_b - mean
        mean = mean + delta * (n_b / total)
        m2 = m2 + m2_b + delta**2 * (count * n_b / total)
        count = total
        num_frames += 1
    if count == 0:
        raise ValueError("compute_normalisation: no frames given")
    std = float(np.sqrt(m2.sum() / (3 * count)))
    if not std > 0:
        raise ValueError("compute_normalisation: zero spread (all points identical)")
    return {"root_joint": root_joint, "mean": [float(x) for x in mean], "std": std,
            "num_frames": num_frames, "num_points": int(count)}  # fmt: skip


def refresh_card(
    root: str | os.PathLike, normalise_on: str = "train", *, rehash: Iterable[str] = ()
) -> dict[str, Any]:
    """Recount the card from disk (:func:`card_from_disk`), write it and return it."""
    card = card_from_disk(root, read_card(root), normalise_on=normalise_on, rehash=rehash)
    write_card(root, card)
    return card


def card_from_disk(
    root: str | os.PathLike, card: Mapping[str, Any], normalise_on: str = "train", *, rehash: Iterable[str] = ()
) -> dict[str, Any]:
    """A copy of ``card`` with what it says about the files recomputed from the folder ``root``
    (nothing is written): ``counts`` (sequences, frames, rejected frames per subject and split),
    ``normalisation`` on the ``normalise_on`` split, and ``frame_files``, the size and CRC-32 of
    every frame file.

    Rejected-frame counts come from each ``sequence.json``'s ``rejected_frames`` list. A frame
    file the card already records with the same size keeps its record (not read again) unless its
    sequence is in ``rehash`` (``"<subject>/<split>/<sequence>"`` keys: sequences just rewritten);
    any other frame file is checked to be a readable npz (a truncated one raises a one-line
    ``ValueError``) and hashed.
    """
    layout = DatasetLayout(root)
    card = dict(card)
    validate_card(os.fspath(layout.card_path), card)
    rehash = set(rehash)
    old_files = card.get("frame_files") or {}
    counts: dict[str, Any] = {}
    files: dict[str, dict[str, list]] = {}
    for s in card["subjects"]:
        counts[s] = {}
        for split in SPLITS:
            seqs = layout.sequences(s, split)
            frames = rejected = 0
            for seq in seqs:
                indices = layout.frame_indices(s, split, seq)
                frames += len(indices)
                meta_path = layout.sequence_meta_path(s, split, seq)
                if os.path.isfile(meta_path):
                    rejected += len(read_sequence_meta(meta_path).get("rejected_frames", []))
                key = layout.sequence_key(s, split, seq)
                before = {} if key in rehash else old_files.get(key, {})
                records = {}
                for i in indices:
                    path = layout.frame_path(s, split, seq, i)
                    rec = before.get(path.name)
                    keep = is_frame_record(rec) and rec[0] == path.stat().st_size
                    records[path.name] = list(rec) if keep else frame_record(path)
                files[key] = records
            if seqs or split != "heldout":  # the optional split is counted only where it exists
                counts[s][split] = {"sequences": len(seqs), "frames": frames, "rejected_frames": rejected}
    card["counts"] = counts
    card["frame_files"] = files
    paths = [p for _, _, p in layout.iter_frames(normalise_on, list(card["subjects"]))]
    if paths:
        stats = compute_normalisation(paths)
        card["normalisation"] = {"root_joint": stats["root_joint"], "mean": stats["mean"],
                                 "std": stats["std"], "computed_on": normalise_on}  # fmt: skip
    card["pose_coverage"] = pose_coverage(root, list(card["subjects"]))
    heldout = pose_coverage(root, list(card["subjects"]), split="heldout")
    if heldout:
        card["pose_coverage_heldout"] = heldout
    else:
        card.pop("pose_coverage_heldout", None)
    return card


def pose_coverage(
    root: str | os.PathLike, subjects: Sequence[str], root_joint: int = 0, split: str = "test"
) -> dict[str, Any]:
    """How far the poses of ``split`` (test or heldout) are from the training poses, per subject: for
    every frame, the RMS distance (cm) between its root-aligned joints and those of the nearest
    training frame of the same subject; the distribution as ``{"test_frames", "median_cm", "p90_cm",
    "max_cm"}`` (subjects without train or ``split`` frames are left out). Small values mean the
    split only re-samples training poses; tens of centimetres mean poses no training frame covers."""
    layout = DatasetLayout(root)
    out: dict[str, Any] = {}
    for s in subjects:
        joints = {}
        for part in ("train", split):
            frames = layout.iter_frames(part, [s])
            if not frames:
                break
            j = np.stack([read_frame(p, ["joints"]).joints for _, _, p in frames]).astype(np.float64)  # (F, J, 3)
            joints[part] = j - j[:, root_joint : root_joint + 1]
        if len(joints) < 2:
            continue
        train, test = joints["train"], joints[split]
        nearest = np.empty(len(test))
        for a in range(0, len(test), 256):  # (t, F) squared RMS over joints, 256 test frames at a time
            d2 = ((test[a : a + 256, None] - train[None]) ** 2).sum(-1).mean(-1)
            nearest[a : a + 256] = np.sqrt(d2.min(1))
        cm = 100.0 * nearest
        out[s] = {"test_frames": int(len(cm)), "median_cm": float(np.median(cm)),
                  "p90_cm": float(np.quantile(cm, 0.9)), "max_cm": float(cm.max())}  # fmt: skip
    return out


def file_crc32(path: str | os.PathLike) -> str:
    """CRC-32 (``zlib.crc32``) of a whole file as 8 lowercase hex digits, read in 1 MiB blocks."""
    crc = 0
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            crc = zlib.crc32(block, crc)
    return f"{crc:08x}"


def npz_directory_error(path: Path) -> str | None:
    """Why ``path`` is not a readable zip (npz) archive, from its central directory only; None if it is."""
    try:
        with zipfile.ZipFile(path) as z:
            if not z.namelist():
                return "corrupt npz (empty archive)"
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
        return f"corrupt or truncated npz ({type(e).__name__}: {' '.join(str(e).split())})"
    return None


def frame_record(path: str | os.PathLike) -> list:
    """``[bytes, crc32]``: the card's record of a frame file, after checking the file is a readable
    npz archive (a truncated or corrupt one raises ``ValueError("<path>: ...")``)."""
    path = Path(path)
    error = npz_directory_error(path)
    if error:
        raise ValueError(f"{path}: {error}")
    return [path.stat().st_size, file_crc32(path)]


def is_frame_record(rec: Any) -> bool:
    return (isinstance(rec, list) and len(rec) == 2 and isinstance(rec[0], int) and not isinstance(rec[0], bool)
            and isinstance(rec[1], str))  # fmt: skip
