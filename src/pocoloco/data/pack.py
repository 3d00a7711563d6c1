"""A training pack: one compact file with what PocoLoco's training reads from a dataset
(``pocoloco data pack DATASET --out FILE``; ``pocoloco train --data FILE``).

A dataset folder holds 40K points with normals, labels and the posed body per frame (``medium``:
11 GB). Training PocoLoco reads a few hundred of those points, the joints, who wears what and
the normalisation. A pack keeps a subset of frames (``every``-th frame of each sequence) and of
points (``points`` per frame, drawn uniformly without replacement, so a random subset of the pack
is a random subset of the scan), quantised, so that a dataset and the code travel to a remote
GPU machine together (the ``medium`` pack: ~20 MB).

File layout (a zip written by ``numpy.savez``, members stored; written atomically)::

    meta                 uint8 JSON: format, version, source, subjects (phenotype, garment kind),
                         subject_names, normalisation, fps, resolution_m, points_per_frame, seed,
                         every, velocity, sequences ("<subject>/<split>/<sequence>"), splits
                         ({split: frames}) and the CRC-32 of every other member
    <split>_index        int32 (F, 3): subject id, sequence id, frame index of each frame
    <split>_root         float32 (F, 3): the root joint, metres
    <split>_joints       LZMA bytes of int16 (F, J, 3): joints - root in ``JOINT_RESOLUTION_M`` units
    <split>_points       LZMA bytes of int16 (F, P, 3): points - root in ``resolution_m`` units, each
                         frame's points sorted along a Morton curve and stored as differences
                         between neighbours, bytes shuffled (low bytes, then high bytes)
    <split>_velocity     LZMA bytes of float16 (F, J, 3) joint velocities, m/s (only if ``velocity``)

Positions read back within half a quantisation step per axis (0.5 mm at the default 1 mm); joints
within 0.05 mm. :class:`PackedDataset` gives the same items as
:class:`~pocoloco.data.dataset.PointCloudDataset` (normalised with the dataset's own statistics,
so a model trained on a pack is interchangeable with one trained on its dataset).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import lzma
import os
import zipfile
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from ..utils.atomic import atomic_open
from . import format as fmt
from .dataset import DEFAULT_FPS, Normalisation, PointCloudDataset, frame_velocity

__all__ = ["PACK_FORMAT", "PACK_VERSION", "PackedDataset", "decode_points", "encode_points", "is_pack",
           "open_point_clouds", "pack_summary", "read_pack_meta", "training_card", "write_pack"]  # fmt: skip

PACK_FORMAT = "pocoloco-pack"
PACK_VERSION = 1
#: quantisation step of the joints (root-relative), metres
JOINT_RESOLUTION_M = 1e-4
_INT16_MAX = 32767


# ------------------------------------------------------------------------------ encoding
def _morton_order(q: np.ndarray) -> np.ndarray:
    """(P, 3) integer coordinates -> (P,) permutation sorting them along a 3D Morton (Z-order) curve."""
    u = (q - q.min(axis=0)).astype(np.uint64)
    code = np.zeros(len(q), np.uint64)
    for bit in range(16):
        for axis in range(3):
            code |= ((u[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def _shuffle_bytes(a: np.ndarray) -> bytes:
    """int16 array -> its low bytes, then its high bytes (compresses better than interleaved)."""
    b = np.ascontiguousarray(a, "<i2").view(np.uint8).reshape(-1, 2)
    return b.T.tobytes()


def _unshuffle_bytes(raw: bytes, shape: tuple[int, ...]) -> np.ndarray:
    b = np.frombuffer(raw, np.uint8)
    if b.size != 2 * int(np.prod(shape)):
        raise ValueError(f"holds {b.size} bytes, expected {2 * int(np.prod(shape))}")
    return np.ascontiguousarray(b.reshape(2, -1).T).view("<i2").reshape(shape)


def encode_points(rel: np.ndarray, resolution: float) -> bytes:
    """(F, P, 3) root-relative points (metres) -> LZMA bytes (module docstring). Raises if a point
    lies farther from the root than int16 codes reach."""
    q = np.round(np.asarray(rel, np.float64) / resolution)
    if q.size and np.abs(q).max() > _INT16_MAX:
        raise ValueError(f"a point lies {np.abs(rel).max():.1f} m from the root, beyond what {resolution * 1e3:g} mm "
                         f"int16 codes hold ({_INT16_MAX * resolution:.1f} m): choose a coarser --resolution-mm")  # fmt: skip
    q = q.astype(np.int32)
    for f in range(len(q)):
        q[f] = q[f][_morton_order(q[f])]
    d = np.diff(q, axis=1, prepend=np.zeros_like(q[:, :1]))  # first point kept, then differences
    return lzma.compress(_shuffle_bytes(d.astype(np.int16)), preset=9 | lzma.PRESET_EXTREME)


def decode_points(blob: bytes, num_frames: int, num_points: int, resolution: float) -> np.ndarray:
    """Inverse of :func:`encode_points` (up to the point order): (F, P, 3) float32 metres."""
    d = _unshuffle_bytes(lzma.decompress(blob), (num_frames, num_points, 3))
    return (np.cumsum(d, axis=1, dtype=np.int32) * resolution).astype(np.float32)


def _encode_int16(a: np.ndarray, resolution: float, what: str) -> bytes:
    q = np.round(np.asarray(a, np.float64) / resolution)
    if q.size and np.abs(q).max() > _INT16_MAX:
        raise ValueError(f"{what} out of the range int16 codes hold at {resolution:g} m")
    return lzma.compress(_shuffle_bytes(q.astype(np.int16)), preset=9)


def _decode_int16(blob: bytes, shape: tuple[int, ...], resolution: float) -> np.ndarray:
    return (_unshuffle_bytes(lzma.decompress(blob), shape).astype(np.float64) * resolution).astype(np.float32)


# ------------------------------------------------------------------------------ writing
def _selected_frames(layout: fmt.DatasetLayout, split: str, subjects: Sequence[str], every: int
                     ) -> list[tuple[str, str, Path]]:  # fmt: skip
    """Every ``every``-th stored frame of each sequence (the first always), in dataset order."""
    out = []
    for s in subjects:
        for seq in layout.sequences(s, split):
            paths = [layout.frame_path(s, split, seq, i) for i in layout.frame_indices(s, split, seq)]
            out += [(s, seq, p) for p in paths[::every]]
    return out


def write_pack(
    data: str | os.PathLike,
    out: str | os.PathLike,
    *,
    splits: Sequence[str] = ("train",),
    every: int = 1,
    eval_every: int = 20,
    points: int = 512,
    resolution_mm: float = 1.0,
    subjects: Sequence[str] | None = None,
    velocity: bool = False,
    seed: int = 0,
    select: Callable[[str, Path], np.ndarray] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Pack the dataset folder ``data`` into the file ``out`` (atomic; module docstring).

    splits: which splits; ``train`` keeps every ``every``-th frame of each sequence, the others
    (previews, validation) every ``eval_every``-th. points: P points per frame, drawn from
    ``default_rng([seed, split id, frame position])`` without replacement. resolution_mm: the
    positions' quantisation step. velocity: also store each frame's joint velocities
    (:func:`~pocoloco.data.dataset.frame_velocity`, from the full dataset). select(subject, frame
    path) -> (N,) bool: draw the points among these only (a region of the body, e.g. the hybrid
    method's free region); frames with fewer than ``points`` selected points are left out (their
    count is the meta's ``skipped``). progress(done, total): called after each frame. Returns the pack's meta (sizes in ``bytes``). One-line ValueErrors for
    a damaged dataset, a frame with fewer than ``points`` points, or bad options.
    """
    for name, value in (("every", every), ("eval_every", eval_every), ("points", points)):
        if not (isinstance(value, int) and value >= 1):
            raise ValueError(f"--{name.replace('_', '-')} must be an integer >= 1, got {value!r}")
    if not (np.isfinite(resolution_mm) and 0.01 <= resolution_mm <= 10):
        raise ValueError(f"--resolution-mm must be in [0.01, 10], got {resolution_mm}")
    bad = [s for s in splits if s not in fmt.SPLITS]
    if bad or not splits:
        raise ValueError(f"unknown split(s) {bad}; choose from {fmt.SPLITS}")
    if "train" not in splits:
        raise ValueError("a pack needs the train split (training reads it)")
    card = fmt.read_card(data)
    norm = Normalisation.from_card(card)  # a one-line error if the dataset is unfinished
    names = sorted(card["subjects"])
    chosen = names if subjects is None else sorted(subjects)
    unknown = [s for s in chosen if s not in card["subjects"]]
    if unknown:
        raise ValueError(f"{data}: unknown subjects {unknown}; the card lists {names}")
    fmt.check_frames(data, subjects=chosen, card=card)
    layout = fmt.DatasetLayout(data)
    fps = float((card.get("generation_config") or {}).get("fps") or DEFAULT_FPS)
    resolution = resolution_mm * 1e-3
    plan = {sp: _selected_frames(layout, sp, chosen, every if sp == "train" else eval_every) for sp in splits}
    plan = {sp: fr for sp, fr in plan.items() if fr}
    if "train" not in plan:
        raise ValueError(f"{data}: no train frames for subjects {chosen}")
    total, done = sum(len(v) for v in plan.values()), 0
    sequences: list[str] = []
    seq_id: dict[str, int] = {}
    members: dict[str, np.ndarray] = {}
    skipped: dict[str, int] = {}
    for split_id, (split, frames) in enumerate(plan.items()):
        F = len(frames)
        index = np.zeros((F, 3), np.int32)
        roots = np.zeros((F, 3), np.float32)
        joints_rel = np.zeros((F, 24, 3), np.float32)
        rel = np.zeros((F, points, 3), np.float32)
        vel = np.zeros((F, 24, 3), np.float32) if velocity else None
        kept = np.ones(F, bool)
        for k, (subject, seq, path) in enumerate(frames):
            fr = fmt.read_frame(path, ["points", "joints", "frame_index"])
            n = fr.points.shape[0]
            if n < points:
                raise ValueError(f"{path}: frame has {n} points, fewer than --points {points}")
            if fr.joints.shape != (24, 3):
                raise ValueError(f"{path}: a pack holds the 24-joint skeleton, this frame has {fr.joints.shape[0]} joints")
            key = f"{subject}/{split}/{seq}"
            if key not in seq_id:
                seq_id[key] = len(sequences)
                sequences.append(key)
            if select is None:
                sel = np.random.default_rng([seed, split_id, k]).choice(n, points, replace=False)
            else:
                pool = np.flatnonzero(np.asarray(select(subject, Path(path)), bool))
                if len(pool) < points:
                    kept[k] = False
                    skipped[split] = skipped.get(split, 0) + 1
                    done += 1
                    if progress is not None:
                        progress(done, total)
                    continue
                sel = np.sort(np.random.default_rng([seed, split_id, k]).choice(pool, points, replace=False))
            root = fr.joints[norm.root_joint]
            index[k] = (names.index(subject), seq_id[key], int(fr.frame_index))
            roots[k] = root
            joints_rel[k] = fr.joints - root
            rel[k] = fr.points[sel] - root
            if vel is not None:
                vel[k] = frame_velocity(path, fr.joints, fps)
            done += 1
            if progress is not None:
                progress(done, total)
        if not kept.any():
            raise ValueError(f"{data}: no {split} frame has {points} selected points")
        index, roots, joints_rel, rel = index[kept], roots[kept], joints_rel[kept], rel[kept]
        vel = None if vel is None else vel[kept]
        plan[split] = [f for f, keep in zip(frames, kept, strict=True) if keep]
        members[f"{split}_index"] = index
        members[f"{split}_root"] = roots
        members[f"{split}_joints"] = _bytes_member(_encode_int16(joints_rel, JOINT_RESOLUTION_M, f"{split} joints"))
        members[f"{split}_points"] = _bytes_member(encode_points(rel, resolution))
        if vel is not None:
            members[f"{split}_velocity"] = _bytes_member(lzma.compress(vel.astype("<f2").tobytes(), preset=9))
    meta = {
        "format": PACK_FORMAT, "version": PACK_VERSION, "source": os.fspath(data),
        "subject_names": names,
        "subjects": {s: {k: card["subjects"][s].get(k) for k in ("phenotype", "garment_kind")} for s in chosen},
        "normalisation": card["normalisation"], "fps": fps, "resolution_m": resolution,
        "joint_resolution_m": JOINT_RESOLUTION_M, "points_per_frame": points, "seed": seed, "every": every,
        "eval_every": eval_every, "velocity": bool(velocity), "sequences": sequences,
        "splits": {sp: len(fr) for sp, fr in plan.items()}, "skipped": skipped,
        "crc32": {k: zlib.crc32(np.ascontiguousarray(v).tobytes()) for k, v in members.items()},
    }  # fmt: skip
    members["meta"] = _bytes_member(json.dumps(meta).encode())
    with atomic_open(out, "wb") as f:
        np.savez(f, **members)
    meta["bytes"] = os.path.getsize(out)
    return meta


def _bytes_member(raw: bytes) -> np.ndarray:
    return np.frombuffer(raw, np.uint8)


# ------------------------------------------------------------------------------ reading
def is_pack(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a file (a pack, or something that claims to be one) rather than a dataset folder."""
    return Path(path).is_file()


def _open_members(path: str | os.PathLike) -> tuple[dict[str, Any], Any]:
    src = os.fspath(path)
    if not os.path.isfile(src):
        raise ValueError(f"{src}: no such pack file")
    try:
        z = np.load(src, allow_pickle=False)
        meta = json.loads(z["meta"].tobytes().decode())
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError, UnicodeDecodeError) as e:
        raise ValueError(f"{src}: not a pocoloco training pack or a damaged one ({type(e).__name__})") from None
    if not isinstance(meta, dict) or meta.get("format") != PACK_FORMAT:
        raise ValueError(f"{src}: not a pocoloco training pack (format {meta.get('format') if isinstance(meta, dict) else None!r})")
    if meta.get("version") != PACK_VERSION:
        raise ValueError(f"{src}: unsupported pack version {meta.get('version')!r} (expected {PACK_VERSION})")
    return meta, z


def read_pack_meta(path: str | os.PathLike) -> dict[str, Any]:
    """The pack's meta (module docstring); a one-line ValueError if it is not a readable pack."""
    meta, z = _open_members(path)
    z.close()
    return meta


def training_card(data: str | os.PathLike) -> dict[str, Any]:
    """What ``pocoloco train`` checks first: the card of a dataset folder, or a pack's meta; one line if neither."""
    return read_pack_meta(data) if is_pack(data) else fmt.read_card(data)


@functools.lru_cache(maxsize=4)
def _load_split(src: str, mtime_ns: int, size: int, split: str, velocity: bool) -> tuple[dict[str, Any], tuple]:
    """Read, check and decode one split of a pack (cached: a search or benchmark building several
    runs on one pack decodes it once; ``mtime_ns`` / ``size`` make a rewritten pack a new key).
    Returns (meta, (index (F, 3), root (F, 3), joints (F, 24, 3), points (F, P, 3), velocity or None))."""
    meta, z = _open_members(src)
    try:
        if split not in meta["splits"]:
            raise ValueError(f"{src}: the pack holds no {split!r} frames (it has {', '.join(meta['splits'])})")
        if velocity and not meta.get("velocity"):
            raise ValueError(f"{src}: the pack holds no joint velocities: make it with `pocoloco data pack --velocity`")
        arrays = {}
        keys = [f"{split}_index", f"{split}_root", f"{split}_joints", f"{split}_points"]
        for key in keys + ([f"{split}_velocity"] if velocity else []):
            try:
                arr = z[key]
            except (KeyError, ValueError, OSError, zipfile.BadZipFile, EOFError) as e:
                raise ValueError(f"{src}: damaged pack ({key}: {type(e).__name__})") from None
            if zlib.crc32(np.ascontiguousarray(arr).tobytes()) != meta["crc32"].get(key):
                raise ValueError(f"{src}: damaged pack ({key} fails its CRC-32 check)")
            arrays[key] = arr
    finally:
        z.close()
    F, P = int(meta["splits"][split]), int(meta["points_per_frame"])
    try:
        index = arrays[f"{split}_index"].reshape(F, 3)
        root = arrays[f"{split}_root"].reshape(F, 3)
        joints = _decode_int16(arrays[f"{split}_joints"].tobytes(), (F, 24, 3), meta["joint_resolution_m"])
        points = decode_points(arrays[f"{split}_points"].tobytes(), F, P, meta["resolution_m"])
        vel = (np.frombuffer(lzma.decompress(arrays[f"{split}_velocity"].tobytes()), "<f2")
               .reshape(F, 24, 3).astype(np.float32) if velocity else None)  # fmt: skip
    except (ValueError, lzma.LZMAError) as e:
        raise ValueError(f"{src}: damaged pack ({e})") from None
    for a in (index, root, joints, points, vel):
        if a is not None:
            a.flags.writeable = False  # shared by every dataset built from the cache
    return meta, (index, root, joints, points, vel)


class PackedDataset(Dataset):
    """The frames of one split of a training pack, as :class:`~pocoloco.data.dataset.PointCloudDataset`
    of a dataset folder holding only the packed subjects gives them (``num_points=None``: every point of the pack's frame; ``points`` (P, 3), ``joints``
    (24, 3) normalised, ``root``, ``angle``, ``velocity`` if asked, ``labels`` unknown, ``subject``,
    ``frame_key``). The pack holds no normals and no posed bodies: asking for them is an error.

    All points are decoded into memory at construction (F x P x 12 bytes: 100 MB for 8K frames of 1K points).
    """

    def __init__(self, path: str | os.PathLike, split: str = "train", *, subjects: Sequence[str] | None = None,
                 with_normals: bool = False, body_point_ids: Sequence[int] | None = None, heading: bool = False,
                 velocity: bool = False):  # fmt: skip
        src = self.root = os.fspath(path)
        if with_normals:
            raise ValueError(f"{src}: a training pack holds no normals (6-channel denoisers train on the dataset folder)")
        if body_point_ids is not None:
            raise ValueError(f"{src}: a training pack holds no posed bodies: train --body-points on the dataset folder")
        if not os.path.isfile(src):
            raise ValueError(f"{src}: no such pack file")
        meta, arrays = _load_split(src, os.stat(src).st_mtime_ns, os.path.getsize(src), split, velocity)
        F = int(meta["splits"][split])
        self._index, self._root, self._joints, self._points, self._velocity = arrays
        self.meta = meta
        self.card = {"subjects": meta["subjects"], "normalisation": meta["normalisation"]}
        # the packed subjects, sorted, as a dataset folder holding only them would list them
        self.subject_names: list[str] = sorted(meta["subjects"])
        remap = np.array([self.subject_names.index(s) if s in meta["subjects"] else -1 for s in meta["subject_names"]])
        self._index = np.concatenate([remap[self._index[:, :1]], self._index[:, 1:]], axis=1)
        if subjects is not None:
            unknown = [s for s in subjects if s not in meta["subjects"]]
            if unknown:
                raise ValueError(f"{src}: unknown subjects {unknown}; the pack holds {sorted(meta['subjects'])}")
        self.split, self.num_points, self.with_normals, self.body_point_ids = split, None, False, None
        self.velocity, self.fps = velocity, float(meta["fps"])
        self.normalisation = Normalisation.from_card(self.card)
        if heading:
            self.normalisation = dataclasses.replace(self.normalisation, heading=True)
        keep = np.arange(F)
        if subjects is not None:
            ids = [self.subject_names.index(s) for s in subjects]
            keep = np.flatnonzero(np.isin(self._index[:, 0], ids))
        self._rows = keep
        if len(keep) == 0:
            raise ValueError(f"{src}: no frames in split {split!r} for subjects {sorted(subjects or [])}")
        seqs = meta["sequences"]
        self.frames = [(self.subject_names[self._index[r, 0]], seqs[self._index[r, 1]].rsplit("/", 1)[1],
                        f"{src}[{seqs[self._index[r, 1]]}/{self._index[r, 2]:06d}]") for r in keep]  # fmt: skip

    def __len__(self) -> int:
        return len(self._rows)

    def frame_key(self, index: int) -> str:
        r = self._rows[index]
        return f"{self.meta['sequences'][self._index[r, 1]]}/{self._index[r, 2]:06d}"

    def __getitem__(self, index: int) -> dict[str, Any]:
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} frames")
        r = self._rows[index]
        root = self._root[r]
        joints_world = self._joints[r] + root
        points, joints = self.normalisation.normalise(self._points[r] + root, joints_world)
        item: dict[str, Any] = {
            "points": torch.from_numpy(np.ascontiguousarray(points, np.float32)),
            "joints": torch.from_numpy(np.ascontiguousarray(joints, np.float32)),
            "root": torch.from_numpy(joints_world[self.normalisation.root_joint].astype(np.float32)),
            "angle": torch.tensor(float(self.normalisation.angle(joints_world)), dtype=torch.float32),
            "labels": torch.full((points.shape[0],), fmt.LABEL_UNKNOWN, dtype=torch.int64),
            "subject": int(self._index[r, 0]),
            "frame_key": self.frame_key(index),
        }
        if self._velocity is not None:
            v = self.normalisation.normalise_velocity(self._velocity[r], joints_world)
            item["velocity"] = torch.from_numpy(np.ascontiguousarray(v, np.float32))
        return item


def open_point_clouds(data: str | os.PathLike, split: str = "train", **kwargs: Any) -> PointCloudDataset | PackedDataset:
    """A split of a dataset folder (:class:`PointCloudDataset`, all of ``kwargs``) or of a training
    pack (:class:`PackedDataset`: ``subjects``, ``with_normals``, ``body_point_ids``, ``heading``,
    ``velocity``; the pack's points are already a subset, so ``num_points`` must be None)."""
    if not is_pack(data):
        return PointCloudDataset(data, split, **kwargs)
    if kwargs.pop("num_points", None) is not None:
        raise ValueError("open_point_clouds: a pack's frames are read whole (num_points=None)")
    kwargs.pop("random_subsample", None)
    kwargs.pop("seed", None)
    return PackedDataset(data, split, **kwargs)


def pack_summary(meta: dict[str, Any]) -> str:
    """One line: frames per split, points per frame, size."""
    splits = ", ".join(f"{n:,} {sp}" for sp, n in meta["splits"].items())
    size = f", {meta['bytes'] / 1e6:.1f} MB" if "bytes" in meta else ""
    return (f"{splits} frames x {meta['points_per_frame']:,} points ({len(meta['subjects'])} subjects, every "
            f"{meta['every']} train frame, {meta['resolution_m'] * 1e3:g} mm){size}")  # fmt: skip

