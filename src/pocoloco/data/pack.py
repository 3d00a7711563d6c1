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

With ``motion`` (``pocoloco data pack --motion``: what ``train --motion-window`` reads) also the
whole motion of every packed sequence (:func:`~pocoloco.data.dataset.sequence_history`, the rows
before its first stored frame included)::

    history_joints       LZMA bytes of int16 (sum T_s, 24, 3): each row's joints minus its root, in
                         ``JOINT_RESOLUTION_M`` units, sequences one after another
    history_root         float32 (sum T_s, 3): each row's root, metres
    history_rows         int64 (S, 3): each sequence's first row there, its row count T_s, and the
                         row of its stored frame 0

With ``bodies`` (``pocoloco data pack --bodies``: what POP and CloSET train on) also::

    <split>_normals      LZMA bytes of int8 (F, P, 2): the points' unit normals, octahedral code, in
                         the points' stored order
    <split>_transforms   LZMA bytes of int16 (F, 2, 24, 3, 4): the frame's 24 skinning transforms of
                         the subject's body and of the mean-shape body in the same pose, in
                         ``TRANSFORM_RESOLUTION`` units (:mod:`pocoloco.body.rig`)
    body_*               LZMA bytes of the rigs (one per subject, then the mean shape: rest vertices
                         in ``REST_RESOLUTION_M`` units, bind-pose pelvis, bone offsets) and of what
                         they share (weights, bones, each bone's joint, faces, UVs, body parts)

A posed body is rebuilt exactly as anny poses it (:class:`~pocoloco.body.rig.SkeletonRig`), within
~0.1 mm of the dataset's; the pack checks that against every frame's stored body when it is made.

Positions read back within half a quantisation step per axis (0.5 mm at the default 1 mm); joints
within 0.05 mm. :class:`PackedDataset` gives the same items as
:class:`~pocoloco.data.dataset.PointCloudDataset` (normalised with the dataset's own statistics,
so a model trained on a pack is interchangeable with one trained on its dataset);
:class:`PackedBodies` gives the frames (points, normals, posed body, ``vtransf``) and posed mean
shapes POP and CloSET train on.

Why this module is long: it is one file format, its writer and its readers (frames, posed bodies,
motion histories) with the integrity checks they share; the byte codecs live in ``pack_codec``.
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

from ..body.anny_body import AnnyBody
from ..body.rig import SkeletonRig
from ..utils.atomic import atomic_open
from . import format as fmt
from .dataset import DEFAULT_FPS, Normalisation, PointCloudDataset, frame_velocity, sequence_history, window_features
from .motion_window import DEFAULT_HZ, MotionHistory, motion_feature_dim, window_samples
from .frame import Frame, SubjectAsset
from .pack_codec import (
    bytes_member,
    decode_int16,
    decode_normals,
    decode_points,
    encode_int16,
    encode_normals,
    encode_points,
    lzma_array,
    morton_order,
    unlzma_array,
)

__all__ = ["PACK_FORMAT", "PACK_VERSION", "PackedBodies", "PackedDataset", "decode_normals", "decode_points",
           "encode_normals", "encode_points", "is_pack", "open_point_clouds", "pack_summary", "read_pack_meta",
           "read_pack_subjects", "training_card", "write_pack"]  # fmt: skip

PACK_FORMAT = "pocoloco-pack"
PACK_VERSION = 1
#: quantisation step of the joints (root-relative), metres
JOINT_RESOLUTION_M = 1e-4
#: quantisation step of the skinning transforms (rotation entries and metres alike)
TRANSFORM_RESOLUTION = 1e-4
#: quantisation step of the rigs' rest vertices, metres
REST_RESOLUTION_M = 5e-5
#: the most a rebuilt body may differ from the dataset's stored one, metres (compact frames hold
#: bodies to 0.5 mm)
BODY_TOLERANCE_M = 2e-3


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
    bodies: bool = False,
    motion: bool = False,
    seed: int = 0,
    select: Callable[[str, Path], np.ndarray] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Pack the dataset folder ``data`` into the file ``out`` (atomic; module docstring).

    splits: which splits; ``train`` keeps every ``every``-th frame of each sequence, the others
    (previews, validation) every ``eval_every``-th. points: P points per frame, drawn from
    ``default_rng([seed, split id, frame position])`` without replacement. resolution_mm: the
    positions' quantisation step. velocity: also store each frame's joint velocities
    (:func:`~pocoloco.data.dataset.frame_velocity`, from the full dataset). bodies: also the
    points' normals and each frame's posed body and posed mean shape as skinning transforms, with
    the rigs that turn them back into vertices (needs anny; every rebuilt body is checked against
    the frame's stored one, ``BODY_TOLERANCE_M``). motion: also every packed sequence's whole
    motion, for motion-window training (module docstring). select(subject, frame
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
    rigs = _PackRigs(data, layout, card, chosen, plan) if bodies else None
    if rigs is not None:
        members.update(rigs.members())
    for split_id, (split, frames) in enumerate(plan.items()):
        F = len(frames)
        index = np.zeros((F, 3), np.int32)
        roots = np.zeros((F, 3), np.float32)
        joints_rel = np.zeros((F, 24, 3), np.float32)
        rel = np.zeros((F, points, 3), np.float32)
        vel = np.zeros((F, 24, 3), np.float32) if velocity else None
        normals = np.zeros((F, points, 3), np.float32) if bodies else None
        transforms = np.zeros((F, 2, 24, 3, 4), np.float64) if bodies else None
        kept = np.ones(F, bool)
        for k, (subject, seq, path) in enumerate(frames):
            keys = ["points", "joints", "frame_index"] + (["normals", "body_vertices"] if bodies else [])
            fr = fmt.read_frame(path, keys, allow_missing=bodies)
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
            if rigs is not None:
                transforms[k] = rigs.transforms(subject, split, seq, fr, Path(path))
                order = morton_order(np.round(rel[k].astype(np.float64) / resolution).astype(np.int64))
                rel[k], normals[k] = rel[k][order], fr.normals[sel][order]
            if vel is not None:
                vel[k] = frame_velocity(path, fr.joints, fps)
            done += 1
            if progress is not None:
                progress(done, total)
        if not kept.any():
            raise ValueError(f"{data}: no {split} frame has {points} selected points")
        index, roots, joints_rel, rel = index[kept], roots[kept], joints_rel[kept], rel[kept]
        vel = None if vel is None else vel[kept]
        if rigs is not None:
            members[f"{split}_normals"] = lzma_array(encode_normals(normals[kept]))
            members[f"{split}_transforms"] = bytes_member(
                encode_int16(transforms[kept], TRANSFORM_RESOLUTION, f"{split} skinning transforms"))
        plan[split] = [f for f, keep in zip(frames, kept, strict=True) if keep]
        members[f"{split}_index"] = index
        members[f"{split}_root"] = roots
        members[f"{split}_joints"] = bytes_member(encode_int16(joints_rel, JOINT_RESOLUTION_M, f"{split} joints"))
        members[f"{split}_points"] = bytes_member(encode_points(rel, resolution))
        if vel is not None:
            members[f"{split}_velocity"] = lzma_array(vel.astype("<f2"))
    if motion:
        members.update(_history_members(layout, sequences, fps))
    meta = {
        "format": PACK_FORMAT, "version": PACK_VERSION, "source": os.fspath(data),
        "subject_names": names,
        "subjects": {s: {k: card["subjects"][s].get(k) for k in ("phenotype", "garment_kind")} for s in chosen},
        "normalisation": card["normalisation"], "fps": fps, "resolution_m": resolution,
        "joint_resolution_m": JOINT_RESOLUTION_M, "points_per_frame": points, "seed": seed, "every": every,
        "eval_every": eval_every, "velocity": bool(velocity), "motion": bool(motion), "bodies": None if rigs is None else rigs.meta(),
        "sequences": sequences,
        "splits": {sp: len(fr) for sp, fr in plan.items()}, "skipped": skipped,
        "crc32": {k: zlib.crc32(np.ascontiguousarray(v).tobytes()) for k, v in members.items()},
    }  # fmt: skip
    members["meta"] = bytes_member(json.dumps(meta).encode())
    with atomic_open(out, "wb") as f:
        np.savez(f, **members)
    meta["bytes"] = os.path.getsize(out)
    return meta


def _history_members(layout, sequences: Sequence[str], fps: float) -> dict[str, np.ndarray]:
    """The ``history_*`` members of the packed sequences ``["<subject>/<split>/<sequence>"]``."""
    rows, roots, parts, start = [], [], [], 0
    for key in sequences:
        subject, split, sequence = key.split("/")
        h = sequence_history(layout.sequence_dir(subject, split, sequence), fps)
        rows.append((start, len(h.joints), h.first))
        roots.append(h.joints[:, 0].astype(np.float32))
        parts.append(h.joints - h.joints[:, :1])
        start += len(h.joints)
    return {"history_joints": bytes_member(encode_int16(np.concatenate(parts), JOINT_RESOLUTION_M, "motion histories")),
            "history_root": np.concatenate(roots), "history_rows": np.asarray(rows, np.int64).reshape(-1, 3)}


@functools.lru_cache(maxsize=2)
def _load_histories(src: str, mtime_ns: int, size: int) -> list[MotionHistory]:
    """The packed sequences' motion histories (``meta["sequences"]`` order)."""
    meta, z = _open_members(src)
    try:
        if not meta.get("motion"):
            raise ValueError(f"{src}: the pack holds no motion histories: make it with `pocoloco data pack --motion`")
        m = _checked_members(src, meta, z, ["history_joints", "history_root", "history_rows"])
    finally:
        z.close()
    try:
        rows = m["history_rows"].reshape(-1, 3)
        root = m["history_root"].reshape(-1, 3)
        joints = decode_int16(m["history_joints"].tobytes(), (len(root), 24, 3), JOINT_RESOLUTION_M) + root[:, None]
    except (ValueError, lzma.LZMAError) as e:
        raise ValueError(f"{src}: damaged pack ({e})") from None
    return [MotionHistory(joints[a:a + n], float(meta["fps"]), int(first)) for a, n, first in rows]


class _PackRigs:
    """What ``write_pack(bodies=True)`` adds: the rigs of the packed subjects and of the mean shape
    (anny), the mesh they share, and each frame's skinning transforms, checked against the frame's
    stored body."""

    def __init__(self, data, layout: fmt.DatasetLayout, card: dict[str, Any], subjects: Sequence[str],
                 plan: dict[str, list[tuple[str, str, Path]]]):  # fmt: skip
        self.data, self.layout, self.subjects = os.fspath(data), layout, list(subjects)
        self.needed: dict[tuple[str, str, str], list[int]] = {}  # the frame indices packed of each sequence
        for split, frames in plan.items():
            for subject, seq, path in frames:
                self.needed.setdefault((subject, split, seq), []).append(int(Path(path).stem))
        self.assets = {s: fmt.read_subject(layout.subject_path(s)) for s in self.subjects}
        first = self.assets[self.subjects[0]]
        for s, a in self.assets.items():
            if a.template.shape != first.template.shape or not np.array_equal(a.faces, first.faces):
                raise ValueError(f"{self.data}: subject {s!r} has another body topology than {self.subjects[0]!r}")
        self.bodies = {s: AnnyBody((card["subjects"][s].get("phenotype") or {})) for s in self.subjects}
        self.bodies["mean"] = AnnyBody()
        self.rigs = {s: b.skeleton_rig() for s, b in self.bodies.items()}
        # the bind-pose pelvis: anny's rest frame minus the subject.npz template's (pelvis at the origin)
        self.origins = {s: self.rigs[s].rest_vertices[0] - b.template[0] for s, b in self.bodies.items()}
        for s in self.subjects:
            err = np.abs(self.rigs[s].rest_vertices - self.origins[s] - self.assets[s].template).max()
            if first.template.shape[0] != self.rigs[s].num_vertices or err > BODY_TOLERANCE_M:
                raise ValueError(f"{self.data}: subject {s!r}: its stored template is not anny's body for its phenotype "
                                 "(another anny version?): it cannot be packed with --bodies")  # fmt: skip
        self._sequence: tuple[tuple[str, str, str], dict[int, np.ndarray]] | None = None

    def meta(self) -> dict[str, Any]:
        rig = self.rigs["mean"]
        first = self.assets[self.subjects[0]]
        return {"rigs": self.subjects + ["mean"], "num_vertices": rig.num_vertices,
                "num_weights": int(rig.weights.shape[1]), "num_bones": int(rig.bone_offsets.shape[0]),
                "num_faces": int(first.faces.shape[0]), "num_uv": int(first.uv.shape[0]),
                "rest_resolution_m": REST_RESOLUTION_M, "transform_resolution": TRANSFORM_RESOLUTION}  # fmt: skip

    def members(self) -> dict[str, np.ndarray]:
        names = self.subjects + ["mean"]
        rigs = [self.rigs[n] for n in names]
        first = self.assets[self.subjects[0]]
        rest = np.stack([r.rest_vertices for r in rigs])
        return {
            "body_rest": bytes_member(encode_int16(rest, REST_RESOLUTION_M, "rest vertices")),
            "body_origin": lzma_array(np.stack([self.origins[n] for n in names]).astype(np.float64)),
            "body_offsets": lzma_array(np.stack([r.bone_offsets for r in rigs]).astype(np.float64)),
            "body_weights": lzma_array(rigs[0].weights.astype(np.float32)),
            "body_bones": lzma_array(rigs[0].bones.astype(np.uint8)),
            "body_bone_joint": lzma_array(rigs[0].bone_joint.astype(np.uint8)),
            "body_faces": lzma_array(first.faces.astype(np.int32)),
            "body_uv": lzma_array(first.uv.astype(np.float32)),
            "body_uv_faces": lzma_array(first.uv_faces.astype(np.int32)),
            "body_vertex_joint": lzma_array(np.stack([self.assets[s].vertex_joint for s in self.subjects]).astype(np.int8)),
        }  # fmt: skip

    def transforms(self, subject: str, split: str, sequence: str, frame, path: Path) -> np.ndarray:
        """(2, 24, 3, 4) the frame's transforms (subject, mean shape), after checking the subject's
        rebuilt body against the frame's stored one."""
        key = (subject, split, sequence)
        if self._sequence is None or self._sequence[0] != key:  # the sequence's packed frames, posed at once
            rot = fmt.read_motion(self.layout.motion_path(subject, split, sequence)).joint_rotvecs
            idx = [i for i in self.needed.get(key, []) if 0 <= i < len(rot)]
            both = np.stack([self.bodies[subject].joint_transforms(rot[idx]),
                             self.bodies["mean"].joint_transforms(rot[idx])], 1) if idx else []  # fmt: skip
            self._sequence = key, dict(zip(idx, both, strict=True))
        i = int(frame.frame_index)
        if i not in self._sequence[1]:
            raise ValueError(f"{path}: frame {i} is not in its motion.npz")
        if frame.body_vertices is None or frame.normals is None:
            raise ValueError(f"{path}: --bodies needs each frame's normals and posed body; this frame has none")
        seq = self._sequence[1]
        body, _ = self.rigs[subject].pose(seq[i][:1])
        err = float(np.abs(body[0] - (frame.body_vertices - frame.joints[0])).max())
        if err > BODY_TOLERANCE_M:
            raise ValueError(f"{path}: the stored body differs from anny's by {err * 1e3:.1f} mm (another anny "
                             "version?): it cannot be packed with --bodies")  # fmt: skip
        return seq[i]


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


def _checked_members(src: str, meta: dict[str, Any], z, keys: Sequence[str]) -> dict[str, np.ndarray]:
    """The members ``keys``, each checked against its CRC-32 (one line if missing or damaged)."""
    arrays = {}
    for key in keys:
        try:
            arr = z[key]
        except (KeyError, ValueError, OSError, zipfile.BadZipFile, EOFError) as e:
            raise ValueError(f"{src}: damaged pack ({key}: {type(e).__name__})") from None
        if zlib.crc32(np.ascontiguousarray(arr).tobytes()) != meta["crc32"].get(key):
            raise ValueError(f"{src}: damaged pack ({key} fails its CRC-32 check)")
        arrays[key] = arr
    return arrays


def _no_bodies(src: str) -> ValueError:
    return ValueError(f"{src}: the pack holds no posed bodies or normals (POP and CloSET train on them): make it "
                      "with `pocoloco data pack --bodies`")  # fmt: skip


@functools.lru_cache(maxsize=4)
def _load_split(src: str, mtime_ns: int, size: int, split: str, velocity: bool, bodies: bool = False
                ) -> tuple[dict[str, Any], tuple]:  # fmt: skip
    """Read, check and decode one split of a pack (cached: a search or benchmark building several
    runs on one pack decodes it once; ``mtime_ns`` / ``size`` make a rewritten pack a new key).
    Returns (meta, (index (F, 3), root (F, 3), joints (F, 24, 3), points (F, P, 3), velocity or None,
    normals (F, P, 3) or None, transforms (F, 2, 24, 3, 4) or None)); the last two with ``bodies``."""
    meta, z = _open_members(src)
    try:
        if split not in meta["splits"]:
            raise ValueError(f"{src}: the pack holds no {split!r} frames (it has {', '.join(meta['splits'])})")
        if velocity and not meta.get("velocity"):
            raise ValueError(f"{src}: the pack holds no joint velocities: make it with `pocoloco data pack --velocity`")
        if bodies and not meta.get("bodies"):
            raise _no_bodies(src)
        keys = [f"{split}_index", f"{split}_root", f"{split}_joints", f"{split}_points"]
        keys += [f"{split}_velocity"] if velocity else []
        keys += [f"{split}_normals", f"{split}_transforms"] if bodies else []
        arrays = _checked_members(src, meta, z, keys)
    finally:
        z.close()
    F, P = int(meta["splits"][split]), int(meta["points_per_frame"])
    try:
        index = arrays[f"{split}_index"].reshape(F, 3)
        root = arrays[f"{split}_root"].reshape(F, 3)
        joints = decode_int16(arrays[f"{split}_joints"].tobytes(), (F, 24, 3), meta["joint_resolution_m"])
        points = decode_points(arrays[f"{split}_points"].tobytes(), F, P, meta["resolution_m"])
        vel = unlzma_array(arrays[f"{split}_velocity"], "<f2", (F, 24, 3)).astype(np.float32) if velocity else None
        normals = transforms = None
        if bodies:
            normals = decode_normals(unlzma_array(arrays[f"{split}_normals"], "<i1", (F, P, 2)))
            transforms = decode_int16(arrays[f"{split}_transforms"].tobytes(), (F, 2, 24, 3, 4),
                                       meta["bodies"]["transform_resolution"])  # fmt: skip
    except (ValueError, lzma.LZMAError) as e:
        raise ValueError(f"{src}: damaged pack ({e})") from None
    for a in (index, root, joints, points, vel, normals, transforms):
        if a is not None:
            a.flags.writeable = False  # shared by every dataset built from the cache
    return meta, (index, root, joints, points, vel, normals, transforms)


@functools.lru_cache(maxsize=2)
def _load_rigs(src: str, mtime_ns: int, size: int) -> tuple[dict[str, SkeletonRig], dict[str, SubjectAsset]]:
    """The rigs of a ``--bodies`` pack ({subject or "mean": SkeletonRig}) and the packed subjects'
    ``SubjectAsset`` (mesh, template, body parts, phenotype) as their ``subject.npz`` holds them."""
    meta, z = _open_members(src)
    try:
        b = meta.get("bodies")
        if not b:
            raise _no_bodies(src)
        keys = ["body_rest", "body_origin", "body_offsets", "body_weights", "body_bones", "body_bone_joint",
                "body_faces", "body_uv", "body_uv_faces", "body_vertex_joint"]  # fmt: skip
        m = _checked_members(src, meta, z, keys)
    finally:
        z.close()
    names = list(b["rigs"])
    R, V, K, B = len(names), int(b["num_vertices"]), int(b["num_weights"]), int(b["num_bones"])
    Fc, U = int(b["num_faces"]), int(b["num_uv"])
    try:
        rest = decode_int16(m["body_rest"].tobytes(), (R, V, 3), b["rest_resolution_m"])
        origin = unlzma_array(m["body_origin"], "<f8", (R, 3))
        offsets = unlzma_array(m["body_offsets"], "<f8", (R, B, 3, 4))
        weights = unlzma_array(m["body_weights"], "<f4", (V, K))
        bones = unlzma_array(m["body_bones"], "u1", (V, K)).astype(np.int64)
        bone_joint = unlzma_array(m["body_bone_joint"], "u1", (B,)).astype(np.int64)
        faces = unlzma_array(m["body_faces"], "<i4", (Fc, 3))
        uv = unlzma_array(m["body_uv"], "<f4", (U, 2))
        uv_faces = unlzma_array(m["body_uv_faces"], "<i4", (Fc, 3))
        parts = unlzma_array(m["body_vertex_joint"], "i1", (R - 1, V))
        rigs = {n: SkeletonRig(rest[i], weights, bones, bone_joint, offsets[i]) for i, n in enumerate(names)}
    except (ValueError, lzma.LZMAError) as e:
        raise ValueError(f"{src}: damaged pack ({e})") from None
    assets = {n: SubjectAsset(template=(rest[i] - origin[i]).astype(np.float32), faces=faces, uv=uv, uv_faces=uv_faces,
                              vertex_joint=parts[i], phenotype=dict(meta["subjects"][n].get("phenotype") or {}))
              for i, n in enumerate(names[:-1])}  # fmt: skip
    return rigs, assets


def read_pack_subjects(path: str | os.PathLike) -> dict[str, SubjectAsset]:
    """Subject name -> ``SubjectAsset`` of a ``--bodies`` pack (the subject.npz POP / CloSET read)."""
    src = os.fspath(path)
    if not os.path.isfile(src):
        raise ValueError(f"{src}: no such pack file")
    return dict(_load_rigs(src, os.stat(src).st_mtime_ns, os.path.getsize(src))[1])


class PackedDataset(Dataset):
    """The frames of one split of a training pack, as :class:`~pocoloco.data.dataset.PointCloudDataset`
    of a dataset folder holding only the packed subjects gives them (``num_points=None``: every point of the pack's frame; ``points`` (P, 3), ``joints``
    (24, 3) normalised, ``root``, ``angle``, ``velocity`` if asked, ``labels`` unknown, ``subject``,
    ``frame_key``). The pack holds no normals and no posed bodies: asking for them is an error.

    All points are decoded into memory at construction (F x P x 12 bytes: 100 MB for 8K frames of 1K points).
    """

    def __init__(self, path: str | os.PathLike, split: str = "train", *, subjects: Sequence[str] | None = None,
                 with_normals: bool = False, body_point_ids: Sequence[int] | None = None, heading: bool = False,
                 velocity: bool = False, motion_window: float = 0.0, _bodies: bool = False):  # fmt: skip
        src = self.root = os.fspath(path)
        if with_normals:
            raise ValueError(f"{src}: PocoLoco reads no normals from a training pack (6-channel denoisers train on "
                             "the dataset folder)")  # fmt: skip
        if body_point_ids is not None:
            raise ValueError(f"{src}: PocoLoco reads no posed bodies from a training pack: train --body-points on "
                             "the dataset folder")  # fmt: skip
        if not os.path.isfile(src):
            raise ValueError(f"{src}: no such pack file")
        meta, arrays = _load_split(src, os.stat(src).st_mtime_ns, os.path.getsize(src), split, velocity, _bodies)
        F = int(meta["splits"][split])
        self._index, self._root, self._joints, self._points, self._velocity, self._normals, self._transforms = arrays
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
        self.motion_window = float(motion_window)
        self._histories = (_load_histories(src, os.stat(src).st_mtime_ns, os.path.getsize(src)) if motion_window
                           else None)  # fmt: skip
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
        if self._histories is not None:
            item["motion"] = self.motion_features(index)
        return item

    def motion_features(self, index: int, joints: np.ndarray | None = None,
                        rng: np.random.Generator | None = None) -> torch.Tensor:  # fmt: skip
        """(J, F) frame ``index``'s motion-window features, as
        :meth:`~pocoloco.data.dataset.PointCloudDataset.motion_features` gives them."""
        r = self._rows[index]
        joints = self._joints[r] + self._root[r] if joints is None else joints
        return window_features(self._histories[self._index[r, 1]], int(self._index[r, 2]), self.motion_window,
                               self.normalisation, joints, rng)  # fmt: skip

    @property
    def motion_feature_dim(self) -> int:
        """F of the frames' motion features (0 without a motion window)."""
        return motion_feature_dim(window_samples(self.motion_window, DEFAULT_HZ)) if self.motion_window else 0


class PackedBodies(PackedDataset):
    """The frames of one split of a ``--bodies`` pack as POP and CloSET read them from a dataset
    folder: :meth:`frame` gives a :class:`~pocoloco.data.frame.Frame` (world frame: ``points``
    (P, 3), ``normals`` (P, 3), ``joints`` (24, 3), ``frame_index``, ``body_vertices`` (V, 3),
    ``vtransf`` (V, 3, 3)) and :meth:`mean_shape` the mean-shape body in the frame's pose (V, 3),
    centred on its root (POP's pose input), both rebuilt from the pack's rigs
    (:class:`~pocoloco.body.rig.SkeletonRig`). ``subjects``: as :class:`PackedDataset`."""

    def __init__(self, path: str | os.PathLike, split: str = "train", *, subjects: Sequence[str] | None = None):
        super().__init__(path, split, subjects=subjects, _bodies=True)
        self.rigs, self.assets = _load_rigs(self.root, os.stat(self.root).st_mtime_ns, os.path.getsize(self.root))

    def frame(self, index: int) -> Frame:
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} frames")
        r = self._rows[index]
        root = self._root[r]
        body, vtransf = self.rigs[self.subject_names[self._index[r, 0]]].pose(self._transforms[r, :1])
        return Frame(points=self._points[r] + root, normals=np.array(self._normals[r]), joints=self._joints[r] + root,
                     frame_index=int(self._index[r, 2]), body_vertices=body[0] + root, vtransf=vtransf[0])  # fmt: skip

    def mean_shape(self, index: int) -> np.ndarray:
        """(V, 3) float32 the mean-shape body in frame ``index``'s pose, centred on its root joint."""
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} frames")
        return self.rigs["mean"].pose(self._transforms[self._rows[index], 1:])[0][0]


def open_point_clouds(data: str | os.PathLike, split: str = "train", **kwargs: Any) -> PointCloudDataset | PackedDataset:
    """A split of a dataset folder (:class:`PointCloudDataset`, all of ``kwargs``) or of a training
    pack (:class:`PackedDataset`: ``subjects``, ``with_normals``, ``body_point_ids``, ``heading``,
    ``velocity``, ``motion_window``; the pack's points are already a subset, so ``num_points`` must be None)."""
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
    extra = ", with normals and posed bodies" if meta.get("bodies") else ""
    extra += ", with motion histories" if meta.get("motion") else ""
    return (f"{splits} frames x {meta['points_per_frame']:,} points ({len(meta['subjects'])} subjects, every "
            f"{meta['every']} train frame, {meta['resolution_m'] * 1e3:g} mm{extra}){size}")  # fmt: skip

