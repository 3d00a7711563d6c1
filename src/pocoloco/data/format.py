"""The pocoloco on-disk dataset format (``"pocoloco-dataset"``, version 1).

One folder per dataset; the full specification is ``docs/dataset_format.md``.
In short::

    DATASET/
      card.json                                     # what the dataset is (see make_card)
      subjects/<subject>/subject.npz                # body template, faces, UVs, garment rest mesh
      subjects/<subject>/<split>/<sequence>/sequence.json
      subjects/<subject>/<split>/<sequence>/motion.npz
      subjects/<subject>/<split>/<sequence>/frames/000123.npz

Every file is written atomically (temp file + ``os.replace``), so an
interrupted generator never leaves a half-written frame behind.

A frame (:class:`Frame`) holds one captured point cloud with its skeleton and,
for synthetic data, the posed body. Shapes use N points, V body vertices,
Vg garment vertices, J = 24 joints. Required keys: ``points``, ``normals``,
``joints``, ``frame_index``; optional keys (absent for tight subjects or for
data imported from published scans): ``labels``, ``parts``,
``body_vertices``, ``vtransf``, ``garment_vertices``.

Every reader validates at the boundary and raises a one-line
``ValueError("<path>: <problem>")``.

Frame storage (:data:`FRAME_STORAGES`, chosen per file by :func:`write_frame`; :func:`read_frame`
tells them apart from the file itself, so a dataset may mix them): ``"float32"`` (the default: the
arrays as listed, uncompressed) or ``"compact"`` (deflated, ~37 % of the bytes, reads back within
:data:`COMPACT_MAX_ERROR`; see :func:`encode_compact`).

Integrity: the card records the size and CRC-32 of every frame file (``frame_files``, written by
:func:`refresh_card`). :func:`check_frames` (what training and evaluation call) compares the frame
files present with the card's records and each ``sequence.json`` using only directory listings and
file sizes; :func:`verify_dataset` (``pocoloco data verify``) also reads every byte. Cards written
before ``frame_files`` existed stay valid: their frames are "not recorded", checked against
``sequence.json`` and by reading them, never reported as corrupt for lacking a record.

Why this module is long: it is the one place that knows the on-disk format: the writers, the
validating readers, the card, and the checks that compare the card with the files. The card's
per-frame records are written by :func:`refresh_card` and read by the checks, so the record format
lives in one module rather than two that must agree.
"""

from __future__ import annotations

import datetime
import json
import os
import re
import zipfile
import zlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..body.skeleton import JOINT_NAMES, JOINT_PARENTS, NUM_JOINTS
from ..utils.atomic import no_file_reason, save_npz_atomic, write_json_atomic

__all__ = [
    "FORMAT_NAME", "FORMAT_VERSION", "SPLITS", "LABEL_BODY", "LABEL_GARMENT", "LABEL_NAMES", "LABEL_UNKNOWN", "FRAME_KEYS", "REQUIRED_FRAME_KEYS",
    "OPTIONAL_FRAME_KEYS", "FRAME_STORAGES", "COMPACT_MAX_ERROR", "Frame", "write_frame", "read_frame",
    "encode_compact", "frame_storage", "DatasetLayout", "make_card",
    "read_card", "write_card", "compute_normalisation", "refresh_card", "card_from_disk", "pose_coverage",
    "SubjectAsset", "write_subject", "read_subject", "StoredMotion", "write_motion", "read_motion",
    "write_sequence_meta", "read_sequence_meta",
    "PROBLEM_KINDS", "FrameProblem", "FrameReport", "file_crc32", "frame_record", "scan_frames", "check_frames",
    "verify_dataset",
]  # fmt: skip

FORMAT_NAME = "pocoloco-dataset"
FORMAT_VERSION = 1
#: ``heldout``: test-style motions from other seeds than ``test`` (``SynthConfig.heldout_sequences``);
#: absent from most datasets (its folders are simply missing)
SPLITS: tuple[str, ...] = ("train", "test", "heldout")

#: Point labels: body, loose garment; unknown for points whose class is unknown (imported data
#: has no labels).
LABEL_BODY: int = 0
LABEL_GARMENT: int = 1
LABEL_NAMES: tuple[str, ...] = ("body", "garment")
LABEL_UNKNOWN = 255

#: Frame npz keys and their on-disk dtypes.
FRAME_KEYS: dict[str, np.dtype] = {
    "points": np.dtype(np.float32),
    "normals": np.dtype(np.float32),
    "labels": np.dtype(np.uint8),
    "parts": np.dtype(np.int8),
    "joints": np.dtype(np.float32),
    "body_vertices": np.dtype(np.float32),
    "vtransf": np.dtype(np.float32),
    "garment_vertices": np.dtype(np.float32),
    "frame_index": np.dtype(np.int64),
}
REQUIRED_FRAME_KEYS: tuple[str, ...] = ("points", "normals", "joints", "frame_index")
OPTIONAL_FRAME_KEYS: tuple[str, ...] = tuple(k for k in FRAME_KEYS if k not in REQUIRED_FRAME_KEYS)

_FRAME_NAME = re.compile(r"^(\d+)\.npz$")

#: How a frame file stores its arrays (:func:`write_frame`'s ``storage``).
FRAME_STORAGES: tuple[str, ...] = ("float32", "compact")

#: Largest absolute error of each key read back from a ``"compact"`` frame (metres for positions),
#: guaranteed by :func:`encode_compact` (an array it cannot store within it stays float32):
#: ``normals`` and ``vtransf`` are float16 when within +-1 (half the float16 spacing below 1 is
#: 2^-12), positions int16 fixed point. ``joints``, ``labels``, ``parts``, ``frame_index`` are exact.
COMPACT_MAX_ERROR: dict[str, float] = {
    "points": 1e-4, "body_vertices": 1e-4, "garment_vertices": 1e-4, "normals": 2.0**-12, "vtransf": 2.0**-12,
}  # fmt: skip

_STORAGE_MEMBER = "frame_storage"  # 0-d str array naming the storage; absent in float32 frames
_HALF_KEYS: tuple[str, ...] = ("normals", "vtransf")
_FIXED_POINT_KEYS: tuple[str, ...] = ("points", "body_vertices", "garment_vertices")
_Q16_MAX = 32767  # int16 codes used: -_Q16_MAX..._Q16_MAX
_HALF_MAX = 1.0 + 2.0**-12  # float16 only for arrays within +-1 (float32 unit vectors may pass 1 a little)


# --------------------------------------------------------------------------- frames
@dataclass(kw_only=True)
class Frame:
    """One captured frame (or the subset of its fields that was read).

    points:           (N, 3) float32, metres, world frame (Z up).
    normals:          (N, 3) float32 unit outward normals.
    joints:           (J=24, 3) float32 skeleton joints (``skeleton.JOINT_NAMES``).
    frame_index:      int, index of the frame in its sequence (``motion.npz`` row).
    labels:           (N,) uint8 point class, or None (imported data). Synthetic
                      data: 0 body, 1 garment (``LABEL_NAMES``); 255 = unknown.
    parts:            (N,) int8 body part (skeleton joint index) per point, -1 = none; or None.
    body_vertices:    (V, 3) float32 posed body, or None (imported data).
    vtransf:          (V, 3, 3) float32 per-vertex skinning transform, or None.
    garment_vertices: (Vg, 3) float32 simulated garment, or None (tight subjects, imported data).

    ``points``, ``normals``, ``joints`` and ``frame_index`` are required on
    disk; they are None only in a frame read with ``read_frame(path, keys)``
    that did not ask for them.
    """

    points: np.ndarray | None = None
    normals: np.ndarray | None = None
    joints: np.ndarray | None = None
    frame_index: int | None = None
    labels: np.ndarray | None = None
    parts: np.ndarray | None = None
    body_vertices: np.ndarray | None = None
    vtransf: np.ndarray | None = None
    garment_vertices: np.ndarray | None = None

    @property
    def num_points(self) -> int:
        if self.points is None:
            raise ValueError("frame was read without 'points'")
        return int(self.points.shape[0])

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The frame as a dict of on-disk arrays (None fields omitted)."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is not None:
                out[f.name] = np.asarray(value)
        return out


def _check_array(src: str, key: str, arr: np.ndarray) -> np.ndarray:
    """Validate dtype kind, finiteness and per-key shape; return it in the on-disk dtype."""
    arr = np.asarray(arr)
    target = FRAME_KEYS[key]
    if target.kind == "f":
        if arr.dtype.kind not in "fiu":
            raise ValueError(f"{src}: '{key}' must be numeric, got dtype {arr.dtype}")
    elif arr.dtype.kind not in "iub":
        raise ValueError(f"{src}: '{key}' must be integer, got dtype {arr.dtype}")
    if key == "frame_index":
        if arr.shape != ():
            raise ValueError(f"{src}: 'frame_index' must be a scalar, got shape {arr.shape}")
        if int(arr) < 0:
            raise ValueError(f"{src}: 'frame_index' must be >= 0, got {int(arr)}")
        return arr.astype(target)
    expected: tuple[Any, ...] = {
        "points": ("N", 3), "normals": ("N", 3), "labels": ("N",), "parts": ("N",),
        "joints": (NUM_JOINTS, 3), "body_vertices": ("V", 3), "vtransf": ("V", 3, 3),
        "garment_vertices": ("Vg", 3),
    }[key]  # fmt: skip
    ok = arr.ndim == len(expected) and all(
        isinstance(e, str) or s == e for s, e in zip(arr.shape, expected)
    )
    if not ok:
        want = "(" + ", ".join(str(e) for e in expected) + ("," if len(expected) == 1 else "") + ")"
        raise ValueError(f"{src}: '{key}' must have shape {want}, got {arr.shape}")
    if target.kind == "f" and not np.isfinite(arr).all():
        raise ValueError(f"{src}: '{key}' contains NaN or inf")
    if key == "labels" and arr.size and (arr.min() < 0 or arr.max() > 255):
        raise ValueError(f"{src}: 'labels' must be in [0, 255]")
    if key == "parts" and arr.size and (arr.min() < -1 or arr.max() >= NUM_JOINTS):
        raise ValueError(f"{src}: 'parts' must be in [-1, {NUM_JOINTS - 1}]")
    return arr.astype(target, copy=False)


def _check_consistency(src: str, arrays: Mapping[str, np.ndarray]) -> None:
    """Cross-key checks: all per-point arrays share N, body arrays share V."""
    per_point = [k for k in ("points", "normals", "labels", "parts") if k in arrays]
    sizes = {k: arrays[k].shape[0] for k in per_point}
    if len(set(sizes.values())) > 1:
        desc = ", ".join(f"{k}={n}" for k, n in sizes.items())
        raise ValueError(f"{src}: per-point arrays disagree on N ({desc})")
    if "points" in arrays and arrays["points"].shape[0] == 0:
        raise ValueError(f"{src}: 'points' is empty")
    if "body_vertices" in arrays and "vtransf" in arrays:
        if arrays["body_vertices"].shape[0] != arrays["vtransf"].shape[0]:
            raise ValueError(
                f"{src}: 'body_vertices' has {arrays['body_vertices'].shape[0]} vertices but "
                f"'vtransf' has {arrays['vtransf'].shape[0]}"
            )


def _validate_frame_arrays(src: str, raw: Mapping[str, Any]) -> dict[str, np.ndarray]:
    out = {k: _check_array(src, k, v) for k, v in raw.items()}
    _check_consistency(src, out)
    return out


def write_frame(path: str | os.PathLike, frame: Frame, compress: bool = False, *, storage: str = "float32") -> None:
    """Validate ``frame`` and write it atomically as an npz.

    storage: ``"float32"`` (the arrays in their ``FRAME_KEYS`` dtypes, uncompressed unless
    ``compress``; the bytes are what this function always wrote) or ``"compact"``
    (:func:`encode_compact`, always deflated).
    """
    if storage not in FRAME_STORAGES:
        raise ValueError(f"write_frame: storage must be one of {FRAME_STORAGES}, got {storage!r}")
    missing = [k for k in REQUIRED_FRAME_KEYS if getattr(frame, k) is None]
    if missing:
        raise ValueError(f"{os.fspath(path)}: frame lacks required fields {missing}")
    arrays = _validate_frame_arrays(os.fspath(path), frame.to_arrays())
    if storage == "compact":
        save_npz_atomic(path, compress=True, **encode_compact(arrays))
    else:
        save_npz_atomic(path, compress=compress, **arrays)


def encode_compact(arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The npz members of a ``"compact"`` frame holding the validated frame ``arrays``.

    - ``frame_storage``: ``"compact"`` (how :func:`read_frame` recognises the file);
    - ``normals``, ``vtransf``: float16 (unit directions and blended skinning rotations, entries
      in [-1, 1]: error <= 2^-12 per entry, ~0.02 degrees; an array with an entry beyond +-1 stays
      float32);
    - ``points``, ``body_vertices``, ``garment_vertices``: int16 fixed point per axis,
      ``<key>_q16`` (n, 3) int16 codes q and ``<key>_q16_scale`` (2, 3) float64 rows origin o and
      step s, read back as ``o + q * s`` with o the middle of the array's bounding box and
      s = half its extent / 32767: error <= s / 2, 0.015 mm for a 2 m tall frame; a key whose
      error would exceed ``COMPACT_MAX_ERROR`` (an extent over ~13 m) stays float32;
    - ``joints``, ``labels``, ``parts``, ``frame_index``: unchanged (exact).

    Positions are not stored as float16: its spacing is ~1 mm between 1 and 2 m and ~2 mm
    between 2 and 4 m, and root translations reach several metres (float16 offsets from the pelvis
    joint err up to 0.5 mm within 2 m of it, more beyond). Fixed point costs the same 2 bytes.
    Renamed members (``points_q16``) make a reader that does not know this storage fail with
    "missing key 'points'" instead of reading codes as coordinates.
    """
    out: dict[str, np.ndarray] = {_STORAGE_MEMBER: np.asarray("compact")}
    for key, arr in arrays.items():
        if key in _HALF_KEYS and arr.size and np.abs(arr).max() <= _HALF_MAX:
            out[key] = arr.astype(np.float16)
        elif key in _FIXED_POINT_KEYS and arr.size:
            x = arr.astype(np.float64)
            lo, hi = x.min(axis=0), x.max(axis=0)
            step = (hi - lo) / (2 * _Q16_MAX)
            rounding = np.abs(x).max() * 2.0**-24  # of the float32 result
            if step.max() / 2 + rounding > COMPACT_MAX_ERROR[key]:
                out[key] = arr
                continue
            origin = (lo + hi) / 2
            step = np.where(step > 0, step, 1.0)  # a flat axis: every code is 0
            codes = np.clip(np.rint((x - origin) / step), -_Q16_MAX, _Q16_MAX).astype(np.int16)
            out[f"{key}_q16"] = codes
            out[f"{key}_q16_scale"] = np.stack([origin, step])
        else:
            out[key] = arr
    return out


def _decode_compact(src: str, names: set[str], raw: dict[str, np.ndarray]) -> None:
    """Turn the fixed-point members of a compact frame (in ``raw``) back into float32 positions,
    in place; ``names`` (the archive's members) gains the decoded keys."""
    for key in _FIXED_POINT_KEYS:
        q_name, scale_name = f"{key}_q16", f"{key}_q16_scale"
        if q_name not in names:
            continue
        names.add(key)
        if q_name not in raw:  # not asked for
            continue
        if scale_name not in raw:
            raise ValueError(f"{src}: missing key '{scale_name}'")
        codes, scale = raw.pop(q_name), raw.pop(scale_name)
        if codes.dtype != np.int16 or codes.ndim != 2 or codes.shape[1] != 3:
            raise ValueError(f"{src}: '{q_name}' must be int16 of shape (n, 3), got {codes.dtype} {codes.shape}")
        if scale.dtype.kind != "f" or scale.shape != (2, 3) or not np.isfinite(scale).all():
            raise ValueError(f"{src}: '{scale_name}' must be a finite (2, 3) float array, got {scale.dtype} "
                             f"{scale.shape}")  # fmt: skip
        raw[key] = (scale[0] + codes * scale[1]).astype(np.float32)


def _storage_of(src: str, raw: Mapping[str, np.ndarray]) -> str:
    """The storage a frame archive declares (its ``frame_storage`` member; float32 without one)."""
    if _STORAGE_MEMBER not in raw:
        return "float32"
    marker = raw[_STORAGE_MEMBER]
    value = str(marker.reshape(())[()]) if marker.dtype.kind == "U" and marker.size == 1 else repr(marker)
    if value not in FRAME_STORAGES:
        raise ValueError(f"{src}: unknown frame storage {value} (this code reads {', '.join(FRAME_STORAGES)})")
    return value


def frame_storage(path: str | os.PathLike) -> str:
    """``"float32"`` or ``"compact"``: how the frame file at ``path`` stores its arrays."""
    src = os.fspath(path)
    return _storage_of(src, load_npz(src, [_STORAGE_MEMBER])[1])


def load_npz(path: str, keys: Iterable[str] | None) -> tuple[set[str], dict[str, np.ndarray]]:
    """Read ``keys`` (all if None; missing ones skipped) from an npz; errors become one-line ValueErrors."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: {no_file_reason(path)}")
    try:
        with np.load(path, allow_pickle=False) as z:
            if not hasattr(z, "files"):
                raise ValueError("not an npz archive")
            names = set(z.files)
            wanted = names if keys is None else [k for k in keys if k in names]
            return names, {k: z[k] for k in wanted}
    except Exception as e:  # zipfile.BadZipFile, EOFError, OSError, ValueError, zlib.error ...
        msg = " ".join(str(e).split()) or type(e).__name__
        raise ValueError(f"{path}: corrupt or truncated npz ({type(e).__name__}: {msg})") from None


def read_frame(path: str | os.PathLike, keys: Sequence[str] | None = None, *, allow_missing: bool = False) -> Frame:
    """Read and validate one frame npz.

    keys=None: read every key (required keys must exist, absent optional ones
    are None). With ``keys``: read only those members (fast: npz members are
    loaded lazily); the other fields of the returned :class:`Frame` are None.
    A requested key that is absent raises, unless ``allow_missing`` and the
    key is optional (then it is None).

    Either storage (:data:`FRAME_STORAGES`) is read, recognised from the file; arrays come back
    in their ``FRAME_KEYS`` dtypes (float32 positions, normals and ``vtransf``) either way.

    Raises ``ValueError("<path>: <problem>")`` for a truncated/corrupt archive,
    a missing key, a wrong shape, or NaN/inf values.
    """
    src = os.fspath(path)
    if keys is not None:
        if isinstance(keys, str):
            keys = [keys]
        unknown = [k for k in keys if k not in FRAME_KEYS]
        if unknown:
            raise ValueError(f"read_frame: unknown frame keys {unknown}; known: {list(FRAME_KEYS)}")
    members = None if keys is None else [_STORAGE_MEMBER] + [
        m for k in keys for m in ((k, f"{k}_q16", f"{k}_q16_scale") if k in _FIXED_POINT_KEYS else (k,))
    ]  # fmt: skip
    names, raw = load_npz(src, members)
    if _storage_of(src, raw) == "compact":
        _decode_compact(src, names, raw)
    needed = REQUIRED_FRAME_KEYS if keys is None else [
        k for k in keys if not (allow_missing and k in OPTIONAL_FRAME_KEYS)
    ]  # fmt: skip
    for k in needed:
        if k not in names:
            raise ValueError(f"{src}: missing key '{k}'")
    raw = {k: v for k, v in raw.items() if k in FRAME_KEYS}  # ignore foreign extras
    kwargs: dict[str, Any] = _validate_frame_arrays(src, raw)
    if "frame_index" in kwargs:
        kwargs["frame_index"] = int(kwargs["frame_index"])
    return Frame(**kwargs)


# --------------------------------------------------------------------------- subject / sequence files
@dataclass(kw_only=True)
class SubjectAsset:
    """``subjects/<subject>/subject.npz``: everything constant for a subject.

    template:     (V, 3) float32 rest-pose body vertices.
    faces:        (F, 3) int32 body triangles.
    uv:           (U, 2) float32 texture coordinates.
    uv_faces:     (F, 3) int32 per-face indices into ``uv``.
    vertex_joint: (V,) int8 skeleton joint (body part) of each vertex.
    phenotype:    dict of anny phenotype values (stored as a JSON string).
    garment_rest_vertices: (Vg, 3) float32 or None (tight subjects).
    garment_faces:         (Fg, 3) int32 or None.
    """

    template: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    vertex_joint: np.ndarray
    phenotype: dict[str, Any] = field(default_factory=dict)
    garment_rest_vertices: np.ndarray | None = None
    garment_faces: np.ndarray | None = None


def write_subject(path: str | os.PathLike, subject: SubjectAsset) -> None:
    """Write ``subject.npz`` atomically (garment arrays omitted when None)."""
    src = os.fspath(path)
    t = np.asarray(subject.template, np.float32)
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"{src}: template must have shape (V, 3), got {t.shape}")
    arrays: dict[str, np.ndarray] = {
        "template": t,
        "faces": np.asarray(subject.faces, np.int32),
        "uv": np.asarray(subject.uv, np.float32),
        "uv_faces": np.asarray(subject.uv_faces, np.int32),
        "vertex_joint": np.asarray(subject.vertex_joint, np.int8),
        "phenotype": np.asarray(json.dumps(subject.phenotype, sort_keys=True)),
    }
    if arrays["vertex_joint"].shape != (t.shape[0],):
        raise ValueError(f"{src}: vertex_joint must have shape ({t.shape[0]},), got {arrays['vertex_joint'].shape}")
    if (subject.garment_rest_vertices is None) != (subject.garment_faces is None):
        raise ValueError(f"{src}: garment_rest_vertices and garment_faces must both be given or both None")
    if subject.garment_rest_vertices is not None:
        arrays["garment_rest_vertices"] = np.asarray(subject.garment_rest_vertices, np.float32)
        arrays["garment_faces"] = np.asarray(subject.garment_faces, np.int32)
    save_npz_atomic(path, **arrays)


def read_subject(path: str | os.PathLike) -> SubjectAsset:
    """Read ``subject.npz``; a missing key or bad phenotype JSON raises ``ValueError`` naming the file."""
    src = os.fspath(path)
    names, raw = load_npz(src, None)
    for k in ("template", "faces", "uv", "uv_faces", "vertex_joint", "phenotype"):
        if k not in names:
            raise ValueError(f"{src}: missing key '{k}'")
    try:
        phenotype = json.loads(str(raw["phenotype"]))
    except json.JSONDecodeError as e:
        raise ValueError(f"{src}: 'phenotype' is not valid JSON ({e})") from None
    return SubjectAsset(
        template=raw["template"], faces=raw["faces"], uv=raw["uv"], uv_faces=raw["uv_faces"],
        vertex_joint=raw["vertex_joint"], phenotype=phenotype,
        garment_rest_vertices=raw.get("garment_rest_vertices"), garment_faces=raw.get("garment_faces"),
    )  # fmt: skip


@dataclass
class StoredMotion:
    """``motion.npz``: joint_rotvecs (T, 24, 3) axis-angle (anny local-ref axes), root_translation (T, 3) metres."""

    joint_rotvecs: np.ndarray
    root_translation: np.ndarray


def write_motion(path: str | os.PathLike, motion: StoredMotion) -> None:
    """Write ``motion.npz`` atomically after checking shapes."""
    src = os.fspath(path)
    r = np.asarray(motion.joint_rotvecs, np.float32)
    t = np.asarray(motion.root_translation, np.float32)
    if r.ndim != 3 or r.shape[1:] != (NUM_JOINTS, 3):
        raise ValueError(f"{src}: joint_rotvecs must have shape (T, {NUM_JOINTS}, 3), got {r.shape}")
    if t.shape != (r.shape[0], 3):
        raise ValueError(f"{src}: root_translation must have shape ({r.shape[0]}, 3), got {t.shape}")
    save_npz_atomic(path, joint_rotvecs=r, root_translation=t)


def read_motion(path: str | os.PathLike) -> StoredMotion:
    """Read ``motion.npz`` with the same checks as :func:`write_motion`."""
    src = os.fspath(path)
    names, raw = load_npz(src, ("joint_rotvecs", "root_translation"))
    for k in ("joint_rotvecs", "root_translation"):
        if k not in names:
            raise ValueError(f"{src}: missing key '{k}'")
    r, t = raw["joint_rotvecs"], raw["root_translation"]
    if r.ndim != 3 or r.shape[1:] != (NUM_JOINTS, 3) or t.shape != (r.shape[0], 3):
        raise ValueError(f"{src}: bad shapes joint_rotvecs {r.shape}, root_translation {t.shape}")
    return StoredMotion(r, t)


def _read_json(path: str, what: str) -> Any:
    if not os.path.isfile(path):
        raise ValueError(f"{path}: missing ({what})")
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: malformed JSON ({' '.join(str(e).split())})") from None


def write_sequence_meta(path: str | os.PathLike, meta: Mapping[str, Any]) -> None:
    """Write ``sequence.json`` atomically; ``num_frames`` (int) is required.

    Conventional keys: ``motion`` (list of segments {name, seed, kind, start, stop}),
    ``fps``, ``num_frames``, ``rejected_frames`` (list of {frame, reason}),
    ``source`` (for imported data: original folder and ``source_frame_ids``).
    """
    if not isinstance(meta.get("num_frames"), int):
        raise ValueError(f"{os.fspath(path)}: sequence meta needs an integer 'num_frames'")
    write_json_atomic(path, dict(meta))


def read_sequence_meta(path: str | os.PathLike) -> dict[str, Any]:
    """Read ``sequence.json``; malformed JSON or a missing ``num_frames`` raises ``ValueError``."""
    src = os.fspath(path)
    meta = _read_json(src, "sequence.json")
    if not isinstance(meta, dict) or not isinstance(meta.get("num_frames"), int):
        raise ValueError(f"{src}: sequence.json must be an object with an integer 'num_frames'")
    return meta


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
        _check_split(split)
        return self.subject_dir(subject) / split

    def sequence_dir(self, subject: str, split: str, sequence: str) -> Path:
        return self.split_dir(subject, split) / sequence

    def sequence_meta_path(self, subject: str, split: str, sequence: str) -> Path:
        return self.sequence_dir(subject, split, sequence) / "sequence.json"

    def motion_path(self, subject: str, split: str, sequence: str) -> Path:
        return self.sequence_dir(subject, split, sequence) / "motion.npz"

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
        _check_split(split)
        return f"{subject}/{split}/{sequence}"

    def frame_indices(self, subject: str, split: str, sequence: str) -> list[int]:
        """Indices of the frame files present, sorted (temporary files are ignored)."""
        d = self.frames_dir(subject, split, sequence)
        if not d.is_dir():
            return []
        return sorted(int(m.group(1)) for n in os.listdir(d) if (m := _FRAME_NAME.match(n)))

    def iter_frames(self, split: str, subjects: Sequence[str] | None = None) -> list[tuple[str, str, Path]]:
        """All frames of a split as (subject, sequence, frame_path), sorted by subject, sequence, index."""
        _check_split(split)
        out = []
        for s in self.subjects() if subjects is None else subjects:
            for seq in self.sequences(s, split):
                for i in self.frame_indices(s, split, seq):
                    out.append((s, seq, self.frame_path(s, split, seq, i)))
        return out


def _check_split(split: str) -> None:
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


def _validate_card(src: str, card: Any) -> None:
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
    card = _read_json(path, "card.json")
    _validate_card(path, card)
    return card


def write_card(root: str | os.PathLike, card: Mapping[str, Any], exclusive: bool = False) -> bool:
    """Validate ``card`` (format name, version, subjects, normalisation) and write it atomically.

    exclusive: only create the card: if ``card.json`` exists (another process wrote it first)
    leave it and return False. Returns True when the card was written."""
    path = os.path.join(os.fspath(root), "card.json")
    card = dict(card)
    _validate_card(path, card)
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
    _validate_card(os.fspath(layout.card_path), card)
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
                    keep = _is_record(rec) and rec[0] == path.stat().st_size
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


# --------------------------------------------------------------------------- integrity
#: What can be wrong with a frame file, in the order reports list them.
PROBLEM_KINDS: tuple[str, ...] = ("missing", "extra", "size", "checksum", "unreadable")


@dataclass(frozen=True)
class FrameProblem:
    """One frame file (or ``sequence.json``) that disagrees with what the dataset says about it.

    kind: ``missing`` (the card's records or ``sequence.json`` expect it, it is not on disk),
    ``extra`` (on disk, expected by neither), ``size`` (its size differs from the card's record:
    truncated or overwritten), ``checksum`` (same size, different CRC-32: corrupt),
    ``unreadable`` (not a readable frame npz, or a malformed ``sequence.json``).
    path: the file. detail: one line.
    """

    kind: str
    path: Path
    detail: str

    def __str__(self) -> str:
        return f"{self.path}: {self.detail}"


@dataclass
class FrameReport:
    """What :func:`scan_frames` found.

    frames: frame files examined (present on disk). recorded: those the card records (size and
    CRC-32); the others were checked against ``sequence.json`` and by reading them only.
    card_records: whether the card has ``frame_files`` at all (False: a dataset written before
    them). contents: whether file contents were checked (checksums, full reads) or only sizes.
    problems: sorted by path. records: with ``contents``, ``frame_files`` as computed from disk.
    """

    root: Path
    card_records: bool
    contents: bool
    frames: int = 0
    recorded: int = 0
    problems: list[FrameProblem] = field(default_factory=list)
    records: dict[str, dict[str, list]] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.problems

    def kinds(self) -> dict[str, int]:
        """Number of problems of each kind (kinds with none left out), in ``PROBLEM_KINDS`` order."""
        out = {k: sum(p.kind == k for p in self.problems) for k in PROBLEM_KINDS}
        return {k: n for k, n in out.items() if n}

    def summary(self) -> str:
        """One line: ``2 bad frame files (1 missing, 1 size); first: <problem>`` or ``960 frame files OK``."""
        if self.ok:
            return f"{self.frames} frame files OK"
        kinds = ", ".join(f"{n} {k}" for k, n in self.kinds().items())
        n = len(self.problems)
        return f"{n} bad frame file{'s' if n != 1 else ''} ({kinds}); first: {self.problems[0]}"


def file_crc32(path: str | os.PathLike) -> str:
    """CRC-32 (``zlib.crc32``) of a whole file as 8 lowercase hex digits, read in 1 MiB blocks."""
    crc = 0
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            crc = zlib.crc32(block, crc)
    return f"{crc:08x}"


def _npz_directory_error(path: Path) -> str | None:
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
    error = _npz_directory_error(path)
    if error:
        raise ValueError(f"{path}: {error}")
    return [path.stat().st_size, file_crc32(path)]


def _is_record(rec: Any) -> bool:
    return (isinstance(rec, list) and len(rec) == 2 and isinstance(rec[0], int) and not isinstance(rec[0], bool)
            and isinstance(rec[1], str))  # fmt: skip


def _expected_by_meta(layout: DatasetLayout, subject: str, split: str, seq: str,
                      problems: list[FrameProblem]) -> set[int] | None:  # fmt: skip
    """Frame indices ``sequence.json`` promises (``range(num_frames)`` minus rejected frames); None
    without a ``sequence.json`` (a sequence being generated); a malformed one is a problem."""
    meta_path = layout.sequence_meta_path(subject, split, seq)
    if not meta_path.is_file():
        return None
    try:
        meta = read_sequence_meta(meta_path)
    except ValueError as e:
        problems.append(FrameProblem("unreadable", meta_path, str(e).split(": ", 1)[-1]))
        return None
    rejected = {r.get("frame") for r in meta.get("rejected_frames", []) if isinstance(r, dict)}
    return set(range(meta["num_frames"])) - rejected


def _sequences_to_scan(layout: DatasetLayout, card: Mapping[str, Any], splits: Sequence[str],
                       subjects: Sequence[str] | None) -> list[tuple[str, str, str]]:  # fmt: skip
    """(subject, split, sequence) on disk or in the card's records, sorted."""
    files = card.get("frame_files") or {}
    chosen = sorted(set(card["subjects"]) | set(layout.subjects())) if subjects is None else sorted(subjects)
    out = set()
    for s in chosen:
        for split in splits:
            out |= {(s, split, q) for q in layout.sequences(s, split)}
            out |= {(s, split, k.split("/", 2)[2]) for k in files if k.startswith(f"{s}/{split}/")}
    return sorted(out)


def scan_frames(
    root: str | os.PathLike,
    *,
    splits: Sequence[str] = SPLITS,
    subjects: Sequence[str] | None = None,
    contents: bool = False,
    card: Mapping[str, Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> FrameReport:
    """Compare the frame files of ``splits`` (of ``subjects``; None: every subject of the card or
    on disk) with the card's ``frame_files`` records and each ``sequence.json``.

    Always: a frame file the card records, or ``sequence.json`` promises (``range(num_frames)``
    minus its rejected frames), but absent is ``missing``; one present that either of them does
    not list is ``extra``; a recorded one of another size is ``size``. Without ``contents``
    (cheap: listings and sizes) a frame the card does not record is checked to open as a zip
    archive (its central directory, at the end: truncation shows). With ``contents`` every byte
    is read: recorded frames must match their CRC-32, the others must pass :func:`read_frame`,
    and ``report.records`` holds the ``frame_files`` of what is on disk.
    ``progress(done, total)`` is called after each frame file.
    """
    root = Path(root)
    card = read_card(root) if card is None else card
    for split in splits:
        _check_split(split)
    layout = DatasetLayout(root)
    files = card.get("frame_files")
    report = FrameReport(root, card_records=files is not None, contents=contents)
    plan = []
    for s, split, seq in _sequences_to_scan(layout, card, splits, subjects):
        key = layout.sequence_key(s, split, seq)
        recorded = None
        if files is not None:
            recorded = {}
            for name, rec in files.get(key, {}).items():
                m = _FRAME_NAME.match(name)
                if m is None or not _is_record(rec):
                    raise ValueError(f"{layout.card_path}: malformed frame_files record {key}/{name}: {rec!r}")
                recorded[int(m.group(1))] = rec
        plan.append((s, split, seq, key, recorded, layout.frame_indices(s, split, seq)))
    total = sum(len(present) for *_, present in plan)
    done = 0
    for s, split, seq, key, recorded, present_list in plan:
        problems: list[FrameProblem] = []
        present = set(present_list)
        by_meta = _expected_by_meta(layout, s, split, seq, problems)
        for i in sorted((by_meta or set()) | set(recorded or {})):
            if i not in present:
                why = "card.json records it" if recorded and i in recorded else "sequence.json lists it"
                problems.append(FrameProblem("missing", layout.frame_path(s, split, seq, i), f"missing ({why})"))
        records = {}
        for i in present_list:
            p = layout.frame_path(s, split, seq, i)
            done += 1
            report.frames += 1
            if recorded is not None and i not in recorded:
                problems.append(FrameProblem("extra", p, "not recorded in card.json"))
            elif by_meta is not None and i not in by_meta:
                problems.append(FrameProblem("extra", p, "not one of sequence.json's frames (rejected or beyond "
                                                         "num_frames)"))  # fmt: skip
            else:
                problem, record = _check_frame_file(p, recorded.get(i) if recorded else None, contents)
                report.recorded += bool(recorded and i in recorded)
                if problem is not None:
                    problems.append(problem)
                elif record is not None:
                    records[p.name] = record
            if progress is not None:
                progress(done, total)
        if contents:
            report.records[key] = records
        report.problems += sorted(problems, key=lambda q: str(q.path))
    return report


def _check_frame_file(path: Path, rec: list | None, contents: bool) -> tuple[FrameProblem | None, list | None]:
    """(problem or None, the file's [bytes, crc32] when ``contents``) for one present frame file."""
    size = path.stat().st_size
    if rec is not None and size != rec[0]:
        what = "truncated" if size < rec[0] else "overwritten"
        return FrameProblem("size", path, f"{size} bytes, card.json records {rec[0]} ({what})"), None
    if not contents:
        error = None if rec is not None else _npz_directory_error(path)
        return (FrameProblem("unreadable", path, error) if error else None), None
    crc = file_crc32(path)
    if rec is not None:
        if crc != rec[1]:
            return FrameProblem("checksum", path, f"CRC-32 {crc}, card.json records {rec[1]} (corrupt)"), None
        return None, [size, crc]
    try:
        read_frame(path)
    except ValueError as e:
        return FrameProblem("unreadable", path, str(e).split(": ", 1)[-1]), None
    return None, [size, crc]


def check_frames(
    root: str | os.PathLike,
    *,
    splits: Sequence[str] = SPLITS,
    subjects: Sequence[str] | None = None,
    card: Mapping[str, Any] | None = None,
) -> FrameReport:
    """The cheap :func:`scan_frames` (listings and sizes) training and evaluation run first; any
    missing, extra, truncated or unreadable frame raises one line naming the first one."""
    report = scan_frames(root, splits=splits, subjects=subjects, card=card)
    if not report.ok:
        raise ValueError(f"{report.summary()}; run `pocoloco data verify {os.fspath(root)}` for the full list")
    return report


def verify_dataset(
    root: str | os.PathLike, *, record: bool = False, progress: Callable[[int, int], None] | None = None
) -> FrameReport:
    """Every frame file of the dataset at ``root`` checked, reading every byte (:func:`scan_frames`
    with ``contents``): recorded frames against their CRC-32, unrecorded ones by :func:`read_frame`.

    ``record``: when nothing is wrong and the card has no ``frame_files`` (a dataset written before
    them), write the sizes and checksums just computed into the card (nothing else changes).
    """
    card = read_card(root)
    report = scan_frames(root, contents=True, card=card, progress=progress)
    if record and report.ok and not report.card_records:
        write_card(root, {**card, "frame_files": report.records})
    return report
