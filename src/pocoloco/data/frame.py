"""Frames and the per-subject / per-sequence files of a pocoloco dataset (the format is
:mod:`pocoloco.data.format`; the specification ``docs/reference/formats.md``).

A frame (:class:`Frame`) holds one captured point cloud with its skeleton and, for synthetic data,
the posed body. Shapes use N points, V body vertices, Vg garment vertices, J = 24 joints. Required
keys: ``points``, ``normals``, ``joints``, ``frame_index``; optional keys (absent for tight subjects
or for data imported from published scans): ``labels``, ``parts``, ``body_vertices``, ``vtransf``,
``garment_vertices``. Every reader validates at the boundary and raises a one-line
``ValueError("<path>: <problem>")``; every writer is atomic.

Frame storage (:data:`FRAME_STORAGES`, chosen per file by :func:`write_frame`; :func:`read_frame`
tells them apart from the file itself, so a dataset may mix them): ``"float32"`` (the default: the
arrays as listed, uncompressed) or ``"compact"`` (deflated, ~37 % of the bytes, reads back within
:data:`COMPACT_MAX_ERROR`; see :func:`encode_compact`).
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from ..body.skeleton import NUM_JOINTS
from ..utils.atomic import no_file_reason, save_npz_atomic, write_json_atomic
from ..utils.npfile import numpy_file_problem


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

FRAME_FILE_NAME = re.compile(r"^(\d+)\.npz$")

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
        problem = numpy_file_problem(path, "npz")
        if problem is not None:
            raise ValueError(f"{path}: {problem}") from None
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


def read_json(path: str, what: str) -> Any:
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
    meta = read_json(src, "sequence.json")
    if not isinstance(meta, dict) or not isinstance(meta.get("num_frames"), int):
        raise ValueError(f"{src}: sequence.json must be an object with an integer 'num_frames'")
    return meta
