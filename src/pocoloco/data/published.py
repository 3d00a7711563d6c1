"""Readers and writers for the layouts published with the papers' data.

- **PLY** point clouds / meshes (:func:`read_ply`, :func:`write_ply`): a small,
  dependency-free implementation of the PLY format for what scans need —
  ``ascii``, ``binary_little_endian`` and ``binary_big_endian``; a ``vertex``
  element with float ``x y z``, optional ``nx ny nz`` and an optional integer
  ``label``; an optional ``face`` element (polygons are fan-triangulated).
  Other elements and properties are parsed and ignored.
- **LOOSE / DynaCap style** sequences: a folder of one ``.ply`` per frame plus
  a joints text file, one line per frame: a frame id then 3J floats
  (:func:`read_joints_txt`, :func:`write_joints_txt`, :class:`LooseStyleSequence`,
  and :func:`import_loose_style` to convert into the pocoloco format, all or nothing).
- **POP packed npz** files, one per frame (:func:`read_pop_npz`, :func:`write_pop_npz`).

Every reader raises a one-line ``ValueError("<file>: <problem>")`` on malformed input.

Why this module is long: it is the one place that knows the published formats, and each reader
carries the checks that turn a malformed or truncated file into a one-line error (PLY headers of
three encodings, joints text files, POP's packed arrays); its writers are the readers' inverses,
kept next to them so a round trip is tested in one place; and the import stages a sequence in a
temporary folder and puts everything back if any step fails.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..body.skeleton import NUM_JOINTS
from ..utils.atomic import atomic_write, no_file_reason, save_npz_atomic
from . import format as fmt
from .format import read_frame

__all__ = [
    "PlyData", "read_ply", "write_ply", "check_cloud", "CLOUD_CHECK_HELP", "read_joints_txt", "write_joints_txt", "LooseFrame",
    "LooseStyleSequence", "import_loose_style", "POP_KEYS", "read_pop_npz", "write_pop_npz",
]  # fmt: skip

# --------------------------------------------------------------------------- PLY
_PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass
class PlyData:
    """Content of a PLY file.

    points:  (N, 3) float32 vertex positions.
    normals: (N, 3) float32 vertex normals, or None when the file has no nx ny nz.
    labels:  (N,) integer per-vertex ``label`` (dtype as stored: uint8 or int32), or None.
    faces:   (F, 3) int64 triangles (polygons fan-triangulated), or None.
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    labels: np.ndarray | None = None
    faces: np.ndarray | None = None


@dataclass
class _Element:
    name: str
    count: int
    props: list[tuple[str, str, str | None]]  # (name, value dtype, list-count dtype or None)


def _parse_ply_header(path: str, f) -> tuple[str, list[_Element]]:
    first = f.readline()
    if first.strip() != b"ply":
        raise ValueError(f"{path}: not a PLY file (missing 'ply' magic)")
    fmt_name: str | None = None
    elements: list[_Element] = []
    for lineno in range(2, 10_000):
        raw = f.readline()
        if not raw:
            raise ValueError(f"{path}: truncated PLY header (no end_header)")
        try:
            words = raw.decode("ascii").split()
        except UnicodeDecodeError:
            raise ValueError(f"{path}: line {lineno}: non-ASCII PLY header") from None
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        if key == "end_header":
            break
        if key == "format":
            if len(words) != 3 or words[1] not in _PLY_FORMATS:
                raise ValueError(f"{path}: line {lineno}: unsupported PLY format {' '.join(words[1:])!r}")
            fmt_name = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise ValueError(f"{path}: line {lineno}: malformed element line {raw.decode().strip()!r}")
            elements.append(_Element(words[1], int(words[2]), []))
        elif key == "property":
            if not elements:
                raise ValueError(f"{path}: line {lineno}: property before any element")
            if len(words) == 5 and words[1] == "list" and words[2] in _PLY_TYPES and words[3] in _PLY_TYPES:
                elements[-1].props.append((words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]]))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1].props.append((words[2], _PLY_TYPES[words[1]], None))
            else:
                raise ValueError(f"{path}: line {lineno}: malformed property line {raw.decode().strip()!r}")
        else:
            raise ValueError(f"{path}: line {lineno}: unknown PLY header keyword {key!r}")
    else:
        raise ValueError(f"{path}: PLY header too long (no end_header)")
    if fmt_name is None:
        raise ValueError(f"{path}: PLY header has no format line")
    return fmt_name, elements


def _read_binary_element(path: str, buf: memoryview, pos: int, el: _Element, endian: str):
    """Parse one binary element starting at byte ``pos``; returns ({prop: array or list}, new pos)."""
    scalar_only = all(c is None for _, _, c in el.props)
    if scalar_only or el.count == 0:
        dt = np.dtype([(n, endian + t) for n, t, _ in el.props])
        nbytes = dt.itemsize * el.count
        if pos + nbytes > len(buf):
            raise ValueError(f"{path}: truncated PLY (element '{el.name}' needs {nbytes} bytes, {len(buf) - pos} left)")
        arr = np.frombuffer(buf, dtype=dt, count=el.count, offset=pos) if el.count else np.zeros(0, dt)
        return {n: arr[n] for n, _, _ in el.props}, pos + nbytes
    # Fast path for list elements: assume every list has the length of the first one, then verify.
    first_len = None
    off = pos
    for n, t, c in el.props:
        if c is None:
            off += np.dtype(t).itemsize
        else:
            if off + np.dtype(c).itemsize > len(buf):
                raise ValueError(f"{path}: truncated PLY (element '{el.name}')")
            first_len = int(np.frombuffer(buf, dtype=endian + c, count=1, offset=off)[0])
            break
    if first_len is not None and sum(c is not None for _, _, c in el.props) == 1:
        fields = []
        for n, t, c in el.props:
            if c is None:
                fields.append((n, endian + t))
            else:
                fields += [(n + "@count", endian + c), (n, endian + t, (first_len,))]
        dt = np.dtype(fields)
        nbytes = dt.itemsize * el.count
        if pos + nbytes <= len(buf):
            arr = np.frombuffer(buf, dtype=dt, count=el.count, offset=pos)
            lists = [n for n, _, c in el.props if c is not None]
            if all((arr[n + "@count"] == first_len).all() for n in lists):
                return {n: arr[n] for n, _, _ in el.props}, pos + nbytes
    # Slow general path: mixed list lengths.
    out: dict[str, list] = {n: [] for n, _, _ in el.props}
    for _ in range(el.count):
        for n, t, c in el.props:
            try:
                if c is None:
                    v = np.frombuffer(buf, dtype=endian + t, count=1, offset=pos)[0]
                    pos += np.dtype(t).itemsize
                else:
                    k = int(np.frombuffer(buf, dtype=endian + c, count=1, offset=pos)[0])
                    pos += np.dtype(c).itemsize
                    v = np.frombuffer(buf, dtype=endian + t, count=k, offset=pos)
                    pos += k * np.dtype(t).itemsize
            except ValueError:
                raise ValueError(f"{path}: truncated PLY (element '{el.name}')") from None
            out[n].append(v)
    res: dict[str, Any] = {}
    for n, t, c in el.props:
        res[n] = out[n] if c is not None else np.array(out[n], dtype=t)
    return res, pos


def _read_ascii_element(path: str, lines: list[bytes], start: int, el: _Element):
    """Parse ``el.count`` lines from ``lines[start:]``; returns ({prop: array or list}, next line)."""
    rows = lines[start : start + el.count]
    if len(rows) < el.count:
        raise ValueError(f"{path}: truncated PLY (element '{el.name}' has {len(rows)} of {el.count} lines)")
    scalar_only = all(c is None for _, _, c in el.props)
    if scalar_only:
        ncol = len(el.props)
        try:
            flat = np.array(b" ".join(rows).split(), dtype=np.float64)
        except ValueError:
            raise ValueError(f"{path}: non-numeric value in element '{el.name}'") from None
        if flat.size != ncol * el.count:
            for i, r in enumerate(rows):
                if (got := len(r.split())) != ncol:
                    raise ValueError(f"{path}: element '{el.name}' row {i}: expected {ncol} values, got {got}")
        table = flat.reshape(el.count, ncol)
        return {n: table[:, j].astype(t) for j, (n, t, _) in enumerate(el.props)}, start + el.count
    out: dict[str, list] = {n: [] for n, _, _ in el.props}
    for i, r in enumerate(rows):
        words = r.split()
        k = 0
        try:
            for n, t, c in el.props:
                if c is None:
                    out[n].append(float(words[k]))
                    k += 1
                else:
                    m = int(words[k])
                    out[n].append(np.array(words[k + 1 : k + 1 + m], dtype=np.float64).astype(t))
                    if len(out[n][-1]) != m:
                        raise IndexError
                    k += 1 + m
        except (IndexError, ValueError):
            raise ValueError(f"{path}: element '{el.name}' row {i}: malformed ascii values") from None
    res: dict[str, Any] = {}
    for n, t, c in el.props:
        res[n] = out[n] if c is not None else np.array(out[n], dtype=t)
    return res, start + el.count


def _triangulate(path: str, lists: Any, num_vertices: int) -> np.ndarray:
    """(F, k) array or list of polygons -> (F', 3) int64 triangles by fan triangulation."""
    if isinstance(lists, np.ndarray) and lists.ndim == 2:
        polys = lists.astype(np.int64)
        if polys.shape[1] < 3:
            raise ValueError(f"{path}: faces with fewer than 3 vertices")
        tris = np.concatenate([polys[:, [0, i, i + 1]] for i in range(1, polys.shape[1] - 1)], axis=0) \
            if polys.shape[1] > 3 else polys  # fmt: skip
    else:
        out = []
        for poly in lists:
            poly = np.asarray(poly, np.int64)
            if poly.size < 3:
                raise ValueError(f"{path}: a face has fewer than 3 vertices")
            out += [[poly[0], poly[i], poly[i + 1]] for i in range(1, poly.size - 1)]
        tris = np.array(out, np.int64).reshape(-1, 3)
    if tris.size and (tris.min() < 0 or tris.max() >= num_vertices):
        raise ValueError(f"{path}: face index out of range [0, {num_vertices})")
    return tris


#: input clouds (``check_cloud``): fewer distinct points than this (0.1 mm apart) are refused
MIN_DISTINCT_POINTS = 16
#: a cloud whose bounding box is smaller than this along its longest side (metres) is refused
MIN_CLOUD_EXTENT_M = 0.01
#: a cloud whose points lie within this of a line (second-longest box side, metres) is refused
MIN_CLOUD_WIDTH_M = 0.001
#: a cloud whose bounding box is larger than this (metres) is taken to be in the wrong unit
MAX_CLOUD_EXTENT_M = 5.0
#: the thresholds, for the help of every command that reads a cloud
CLOUD_CHECK_HELP = (f"input clouds need >= {MIN_DISTINCT_POINTS} distinct points, finite coordinates in metres, "
                    f"a bounding box {MIN_CLOUD_EXTENT_M * 100:g} cm to {MAX_CLOUD_EXTENT_M:g} m across and not all "
                    f"within {MIN_CLOUD_WIDTH_M * 1000:g} mm of a line")  # fmt: skip


def check_cloud(name: str, points: np.ndarray) -> np.ndarray:
    """(N, 3) float32 points of an input cloud, or a one-line ValueError naming ``name`` and what is
    wrong: not (N, 3), non-finite values, fewer than MIN_DISTINCT_POINTS distinct points (0.1 mm
    grid), a bounding box under MIN_CLOUD_EXTENT_M (a point, a blob) or thinner than
    MIN_CLOUD_WIDTH_M across its second side (a line), or larger than MAX_CLOUD_EXTENT_M (not in
    metres). Every command that reads a cloud a user gives calls it before any model sees it."""
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected points of shape (N, 3), got {p.shape}")
    if not np.isfinite(p).all():
        bad = int((~np.isfinite(p).all(1)).sum())
        raise ValueError(f"{name}: {bad} of {len(p)} points have NaN or inf coordinates")
    if len(p) == 0:
        raise ValueError(f"{name}: the cloud is empty (0 points)")
    p = p.astype(np.float32)
    distinct = len(np.unique(np.round(p.astype(np.float64) * 1e4), axis=0))
    if distinct < MIN_DISTINCT_POINTS:
        raise ValueError(f"{name}: degenerate cloud: {distinct} distinct point(s) of {len(p)} "
                         f"(need at least {MIN_DISTINCT_POINTS})")  # fmt: skip
    extent = np.sort(np.ptp(p.astype(np.float64), axis=0))[::-1]
    if extent[0] < MIN_CLOUD_EXTENT_M:
        raise ValueError(f"{name}: degenerate cloud: all {len(p)} points within {extent[0] * 1000:.3g} mm "
                         f"(need a bounding box at least {MIN_CLOUD_EXTENT_M * 100:g} cm across)")  # fmt: skip
    if extent[1] < MIN_CLOUD_WIDTH_M:
        raise ValueError(f"{name}: degenerate cloud: all points within {extent[1] * 1000:.3g} mm of a line")
    if extent[0] > MAX_CLOUD_EXTENT_M:
        raise ValueError(f"{name}: the cloud is {extent[0]:.3g} units across, more than {MAX_CLOUD_EXTENT_M:g} m "
                         "(not in metres? millimetres must be divided by 1000)")  # fmt: skip
    return p


def read_ply(path: str | os.PathLike, require_normals: bool = False) -> PlyData:
    """Read a PLY point cloud or mesh (see the module docstring for what is supported).

    Raises ``ValueError("<file>: <problem>")`` for a truncated or malformed file,
    a missing ``x y z``, non-finite coordinates, out-of-range face indices, and
    (with ``require_normals``) a file without ``nx ny nz``.
    """
    src = os.fspath(path)
    if not os.path.isfile(src):
        raise FileNotFoundError(f"{src}: {no_file_reason(src)}")
    with open(src, "rb") as f:
        fmt_name, elements = _parse_ply_header(src, f)
        body = f.read()
    data: dict[str, dict[str, Any]] = {}
    if fmt_name == "ascii":
        lines = [ln for ln in body.splitlines() if ln.strip()]
        pos = 0
        for el in elements:
            data[el.name], pos = _read_ascii_element(src, lines, pos, el)
    else:
        endian = _PLY_FORMATS[fmt_name]
        buf = memoryview(body)
        pos = 0
        for el in elements:
            data[el.name], pos = _read_binary_element(src, buf, pos, el, endian)
    if "vertex" not in data:
        raise ValueError(f"{src}: PLY has no 'vertex' element")
    v = data["vertex"]
    for k in ("x", "y", "z"):
        if k not in v:
            raise ValueError(f"{src}: PLY vertex element has no '{k}' property")
    points = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    if not np.isfinite(points).all():
        raise ValueError(f"{src}: non-finite vertex coordinates")
    normals = None
    if all(k in v for k in ("nx", "ny", "nz")):
        normals = np.stack([v["nx"], v["ny"], v["nz"]], axis=1).astype(np.float32)
        if not np.isfinite(normals).all():
            raise ValueError(f"{src}: non-finite normals")
    elif require_normals:
        raise ValueError(f"{src}: has no normals (nx, ny, nz)")
    labels = None
    if "label" in v:
        labels = np.asarray(v["label"])
        if labels.dtype.kind == "f":
            if not np.all(labels == np.round(labels)):
                raise ValueError(f"{src}: 'label' values are not integers")
            labels = labels.astype(np.int32)
        labels = np.ascontiguousarray(labels)
    faces = None
    if "face" in data:
        face = data["face"]
        key = "vertex_indices" if "vertex_indices" in face else "vertex_index" if "vertex_index" in face else None
        if key is None:
            raise ValueError(f"{src}: PLY face element has no 'vertex_indices' list")
        faces = _triangulate(src, face[key], points.shape[0])
    return PlyData(points=points, normals=normals, labels=labels, faces=faces)


def write_ply(
    path: str | os.PathLike,
    points: np.ndarray,
    normals: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    faces: np.ndarray | None = None,
    binary: bool = True,
) -> None:
    """Write a PLY file atomically (binary little endian by default, or ascii).

    points (N, 3) and normals (N, 3) are written as float32; labels (N,) as
    ``uchar`` when their dtype is uint8, otherwise as ``int``; faces (F, 3) as a
    ``uchar``-counted ``int`` list ``vertex_indices``. ASCII floats use 9
    significant digits, so float32 values round-trip exactly.
    """
    src = os.fspath(path)
    pts = np.asarray(points, np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{src}: points must have shape (N, 3), got {pts.shape}")
    n = pts.shape[0]
    cols: list[tuple[str, np.ndarray, str]] = [("x", pts[:, 0], "f4"), ("y", pts[:, 1], "f4"), ("z", pts[:, 2], "f4")]
    if normals is not None:
        nrm = np.asarray(normals, np.float32)
        if nrm.shape != (n, 3):
            raise ValueError(f"{src}: normals must have shape ({n}, 3), got {nrm.shape}")
        cols += [("nx", nrm[:, 0], "f4"), ("ny", nrm[:, 1], "f4"), ("nz", nrm[:, 2], "f4")]
    if labels is not None:
        lab = np.asarray(labels)
        if lab.shape != (n,) or lab.dtype.kind not in "iub":
            raise ValueError(f"{src}: labels must be an integer array of shape ({n},), got {lab.dtype} {lab.shape}")
        cols.append(("label", lab, "u1" if lab.dtype == np.uint8 else "i4"))
    tris = None
    if faces is not None:
        tris = np.asarray(faces)
        if tris.ndim != 2 or tris.shape[1] != 3 or tris.dtype.kind not in "iu":
            raise ValueError(f"{src}: faces must be an integer array of shape (F, 3), got {tris.dtype} {tris.shape}")
        if tris.size and (tris.min() < 0 or tris.max() >= n):
            raise ValueError(f"{src}: face index out of range [0, {n})")
    type_name = {"f4": "float", "u1": "uchar", "i4": "int"}
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", "comment written by pocoloco",
              f"element vertex {n}"]  # fmt: skip
    header += [f"property {type_name[t]} {name}" for name, _, t in cols]
    if tris is not None:
        header += [f"element face {tris.shape[0]}", "property list uchar int vertex_indices"]
    header_bytes = ("\n".join(header) + "\nend_header\n").encode("ascii")

    def write(f) -> None:
        f.write(header_bytes)
        if binary:
            table = np.empty(n, dtype=[(name, "<" + t) for name, _, t in cols])
            for name, values, _ in cols:
                table[name] = values
            f.write(table.tobytes())
            if tris is not None:
                ft = np.empty(tris.shape[0], dtype=[("k", "u1"), ("v", "<i4", (3,))])
                ft["k"] = 3
                ft["v"] = tris
                f.write(ft.tobytes())
        else:
            row = " ".join("%.9g" if t == "f4" else "%d" for _, _, t in cols)
            table = np.stack([values.astype(np.float64) for _, values, _ in cols], axis=1)  # ints exact in f64
            lines = [row % tuple(r) for r in table.tolist()]
            if tris is not None:
                lines += ["3 %d %d %d" % tuple(t) for t in tris.tolist()]
            f.write(("\n".join(lines) + ("\n" if lines else "")).encode("ascii"))

    atomic_write(src, write)


# --------------------------------------------------------------------------- joints text files
def read_joints_txt(path: str | os.PathLike, num_joints: int = NUM_JOINTS) -> tuple[np.ndarray, np.ndarray]:
    """Read a joints text file: per line a frame id then 3*J floats (x y z per joint).

    Blank lines and lines starting with ``#`` are skipped; values may be
    separated by spaces, tabs or commas. Returns frame_ids (T,) int64 and
    joints (T, J, 3) float32. A line with a count other than 1 + 3J, a
    non-numeric or non-integer frame id, NaN/inf, or a repeated frame id raises
    ``ValueError("<file>: line <k>: <problem>")``.
    """
    src = os.fspath(path)
    if not os.path.isfile(src):
        raise FileNotFoundError(f"{src}: {no_file_reason(src)}")
    want = 1 + 3 * num_joints
    ids: list[int] = []
    rows: list[np.ndarray] = []
    seen: set[int] = set()
    with open(src, encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            words = s.replace(",", " ").split()
            if len(words) != want:
                raise ValueError(f"{src}: line {lineno}: expected 1 + 3*{num_joints} = {want} values, got {len(words)}")
            try:
                vals = np.array(words, dtype=np.float64)
            except ValueError:
                raise ValueError(f"{src}: line {lineno}: non-numeric value") from None
            if not np.isfinite(vals).all():
                raise ValueError(f"{src}: line {lineno}: NaN or inf value")
            if vals[0] != np.round(vals[0]) or vals[0] < 0:
                raise ValueError(f"{src}: line {lineno}: frame id {words[0]!r} is not a non-negative integer")
            fid = int(vals[0])
            if fid in seen:
                raise ValueError(f"{src}: line {lineno}: frame id {fid} repeated")
            seen.add(fid)
            ids.append(fid)
            rows.append(vals[1:])
    if not ids:
        raise ValueError(f"{src}: no joint lines")
    joints = np.stack(rows).reshape(len(ids), num_joints, 3).astype(np.float32)
    return np.array(ids, np.int64), joints


def write_joints_txt(path: str | os.PathLike, frame_ids: np.ndarray, joints: np.ndarray) -> None:
    """Write frame_ids (T,) and joints (T, J, 3) as text, one frame per line (float32-exact, 9 digits)."""
    ids = np.asarray(frame_ids)
    j = np.asarray(joints, np.float32)
    if ids.ndim != 1 or j.ndim != 3 or j.shape[0] != ids.shape[0] or j.shape[2] != 3:
        raise ValueError(f"{os.fspath(path)}: need frame_ids (T,) and joints (T, J, 3), got {ids.shape} and {j.shape}")
    lines = [f"{int(i)} " + " ".join("%.9g" % v for v in row.reshape(-1).tolist()) for i, row in zip(ids, j)]
    atomic_write(path, lambda f: f.write(("\n".join(lines) + "\n").encode("ascii")))


# --------------------------------------------------------------------------- LOOSE / DynaCap-style sequences
_LAST_INT = re.compile(r"(\d+)(?!.*\d)")


@dataclass
class LooseFrame:
    """One frame of a LOOSE-style sequence: points (N, 3), normals (N, 3), joints (J, 3) float32."""

    frame_id: int
    points: np.ndarray
    normals: np.ndarray
    joints: np.ndarray
    path: str


class LooseStyleSequence:
    """A folder of one ``.ply`` per frame plus a joints text file.

    Frames are matched by the last integer in each PLY file name
    (``frame_000123.ply`` -> 123) to the frame ids of the joints file. A frame
    id with no PLY always raises; a PLY with no joints line raises unless
    ``strict=False`` (then it is ignored). Frames are ordered as in the joints file.

    PLY handling: vertices with ``nx ny nz`` are used as the point cloud. A
    mesh PLY without normals is sampled uniformly (``mesh_samples`` points,
    seeded by ``seed`` + frame id) with the face normals. A PLY with neither
    normals nor faces raises.
    """

    def __init__(
        self,
        ply_dir: str | os.PathLike,
        joints_txt: str | os.PathLike,
        num_joints: int = NUM_JOINTS,
        mesh_samples: int = 40_000,
        seed: int = 0,
        strict: bool = True,
    ):
        self.ply_dir = os.fspath(ply_dir)
        self.joints_txt = os.fspath(joints_txt)
        self.mesh_samples = mesh_samples
        self.seed = seed
        if not os.path.isdir(self.ply_dir):
            raise ValueError(f"{self.ply_dir}: not a folder")
        self.frame_ids, self.joints = read_joints_txt(self.joints_txt, num_joints)
        by_id: dict[int, str] = {}
        for name in sorted(os.listdir(self.ply_dir)):
            if not name.lower().endswith(".ply"):
                continue
            m = _LAST_INT.search(name[:-4])
            if m is None:
                raise ValueError(f"{os.path.join(self.ply_dir, name)}: no frame number in the file name")
            fid = int(m.group(1))
            if fid in by_id:
                raise ValueError(f"{self.ply_dir}: two PLY files for frame {fid}: {by_id[fid]!r} and {name!r}")
            by_id[fid] = name
        missing = [int(i) for i in self.frame_ids if int(i) not in by_id]
        if missing:
            shown = ", ".join(map(str, missing[:5])) + (" ..." if len(missing) > 5 else "")
            raise ValueError(f"{self.ply_dir}: no .ply for {len(missing)} frame ids of {self.joints_txt} ({shown})")
        extra = sorted(set(by_id) - {int(i) for i in self.frame_ids})
        if extra and strict:
            shown = ", ".join(map(str, extra[:5])) + (" ..." if len(extra) > 5 else "")
            raise ValueError(f"{self.ply_dir}: {len(extra)} PLY files have no line in {self.joints_txt} ({shown})")
        self.ply_paths = [os.path.join(self.ply_dir, by_id[int(i)]) for i in self.frame_ids]

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __getitem__(self, i: int) -> LooseFrame:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range for a sequence of {len(self)} frames")
        path = self.ply_paths[i]
        ply = read_ply(path)
        if ply.normals is not None:
            points, normals = ply.points, ply.normals
        elif ply.faces is not None and len(ply.faces):
            import trimesh

            mesh = trimesh.Trimesh(ply.points, ply.faces, process=False)
            seed = self.seed + int(self.frame_ids[i])
            pts, face_idx = trimesh.sample.sample_surface(mesh, self.mesh_samples, seed=seed)
            points = np.asarray(pts, np.float32)
            normals = np.asarray(mesh.face_normals[face_idx], np.float32)
        else:
            raise ValueError(f"{path}: has no normals (nx, ny, nz) and no faces to compute them from")
        return LooseFrame(int(self.frame_ids[i]), check_cloud(path, points), normals, self.joints[i], path)


def import_loose_style(
    ply_dir: str | os.PathLike,
    joints_txt: str | os.PathLike,
    out_root: str | os.PathLike,
    subject: str,
    split: str,
    sequence: str | None = None,
    fps: float | None = None,
    **sequence_kwargs: Any,
) -> Path:
    """Convert a LOOSE-style sequence into the pocoloco format; returns the sequence folder.

    Writes frames with points, normals, joints and frame_index (0..T-1 in
    joints-file order); labels, parts, body_vertices, vtransf and
    garment_vertices are absent. ``sequence.json`` records the source folder
    and the original ``source_frame_ids``. ``out_root`` is a dataset (the
    sequence is added, or replaces the one of the same name) or a new or
    empty folder (a dataset with a minimal card is made). The subject is added
    to the card (garment_kind "unknown", source "imported") and the card's
    counts, train-split normalisation and frame records are recomputed
    (:func:`format.card_from_disk`). Joints must have 24 joints (the pocoloco
    skeleton order).

    All or nothing: the sequence is written into a temporary folder first and
    moved into place only once every frame is written; the card is written
    last. Any error (a malformed PLY in the middle of the folder, ...) leaves
    ``out_root`` as it was, byte for byte, and raises a one-line ``ValueError``.
    """
    seq = LooseStyleSequence(ply_dir, joints_txt, num_joints=NUM_JOINTS, **sequence_kwargs)
    sequence = sequence or os.path.basename(os.path.normpath(os.fspath(ply_dir)))
    if not re.fullmatch(r"[A-Za-z0-9_.\-]+", subject) or not re.fullmatch(r"[A-Za-z0-9_.\-]+", sequence):
        raise ValueError(f"subject and sequence names must be [A-Za-z0-9_.-]+, got {subject!r}, {sequence!r}")
    if split not in fmt.SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {fmt.SPLITS}")
    out = Path(out_root)
    existing = fmt.DatasetLayout(out).card_path.is_file()
    if existing:
        card = fmt.read_card(out)
    elif out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: exists and is not a pocoloco dataset (no card.json); import into a dataset, "
                         "a new folder or an empty one")  # fmt: skip
    else:
        card = fmt.make_card(subjects={}, generation_config={"source": "import_loose_style"})
    card["subjects"].setdefault(subject, {"garment_kind": "unknown", "phenotype": None, "source": "imported"})
    meta = {
        "num_frames": len(seq), "fps": fps, "rejected_frames": [], "motion": [],
        "source": {"kind": "loose-style", "ply_dir": os.path.abspath(seq.ply_dir),
                   "joints_txt": os.path.abspath(seq.joints_txt),
                   "source_frame_ids": [int(x) for x in seq.frame_ids]},
    }  # fmt: skip
    created: list[Path] = []
    staging, done = None, False
    try:
        if not existing:
            created = _make_folders(out.absolute().parent)
        # the staging folder is on the destination's filesystem: moving it into place is a rename
        staging = Path(tempfile.mkdtemp(prefix=".import-" if existing else f".{out.name}.import-",
                                        dir=out if existing else out.absolute().parent))  # fmt: skip
        stage = fmt.DatasetLayout(staging)
        for i in range(len(seq)):
            fr = seq[i]
            fmt.write_frame(stage.frame_path(subject, split, sequence, i),
                            fmt.Frame(points=fr.points, normals=fr.normals, joints=fr.joints, frame_index=i))  # fmt: skip
        fmt.write_sequence_meta(stage.sequence_meta_path(subject, split, sequence), meta)
        if existing:
            _move_sequence_in(staging, out, card, subject, split, sequence)
        else:
            fmt.write_card(staging, fmt.card_from_disk(staging, card))
            os.replace(staging, out)  # POSIX: also replaces an empty folder
        done = True
    finally:
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
        if not done:
            for folder in reversed(created):
                with contextlib.suppress(OSError):
                    folder.rmdir()
    return fmt.DatasetLayout(out).sequence_dir(subject, split, sequence)


def _make_folders(folder: Path) -> list[Path]:
    """``mkdir -p folder``; returns the folders it created, outermost first."""
    missing = []
    while not folder.exists():
        missing.append(folder)
        folder = folder.parent
    for f in reversed(missing):
        f.mkdir()
    return missing[::-1]


def _move_sequence_in(staging: Path, out: Path, card: dict[str, Any], subject: str, split: str, sequence: str) -> None:
    """Move the staged sequence into the dataset ``out`` (a sequence of the same name is set aside
    in ``staging``), then write the recounted card; on any error put everything back."""
    layout, stage = fmt.DatasetLayout(out), fmt.DatasetLayout(staging)
    target = layout.sequence_dir(subject, split, sequence)
    replaced = staging / "replaced"
    created = _make_folders(target.parent)
    staged = stage.sequence_dir(subject, split, sequence)
    moved_old = moved_new = False
    try:
        if target.exists():
            os.rename(target, replaced)
            moved_old = True
        os.rename(staged, target)
        moved_new = True
        key = layout.sequence_key(subject, split, sequence)
        fmt.write_card(out, fmt.card_from_disk(out, card, rehash=[key]))  # the commit (an atomic rename)
    except BaseException:
        if moved_new:
            os.rename(target, staged)
        if moved_old:
            os.rename(replaced, target)
        for folder in reversed(created):
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise


# --------------------------------------------------------------------------- POP packed npz
#: POP packed-file keys and their expected shapes (letters are free sizes).
POP_KEYS: dict[str, tuple[Any, ...]] = {
    "posmap256": ("H", "W", 3),
    "posmap_canonical128": ("H", "W", 3),
    "body_verts": ("V", 3),
    "scan_pc": ("N", 3),
    "scan_n": ("N", 3),
    "scan_name": (),
    "vtransf": ("V", "3|4", "3|4"),
}


def _check_pop(src: str, out: dict[str, Any]) -> None:
    for k, v in out.items():
        if k == "scan_name":
            continue
        if v.dtype.kind not in "fiu":
            raise ValueError(f"{src}: '{k}' must be numeric, got dtype {v.dtype}")
        shape = POP_KEYS[k]
        if v.ndim != len(shape) or any(isinstance(e, int) and s != e for s, e in zip(v.shape, shape)):
            raise ValueError(f"{src}: '{k}' must have shape ({', '.join(map(str, shape))}), got {v.shape}")
        if k == "vtransf" and not (v.shape[1] == v.shape[2] and v.shape[1] in (3, 4)):
            raise ValueError(f"{src}: 'vtransf' must have shape (V, 3, 3) or (V, 4, 4), got {v.shape}")
        if not np.isfinite(v).all():
            raise ValueError(f"{src}: '{k}' contains NaN or inf")
    if "scan_pc" in out and "scan_n" in out and out["scan_pc"].shape != out["scan_n"].shape:
        raise ValueError(f"{src}: 'scan_pc' {out['scan_pc'].shape} and 'scan_n' {out['scan_n'].shape} disagree")
    if "body_verts" in out and "vtransf" in out and out["body_verts"].shape[0] != out["vtransf"].shape[0]:
        nv, nt = out["body_verts"].shape[0], out["vtransf"].shape[0]
        raise ValueError(f"{src}: 'body_verts' has {nv} vertices but 'vtransf' has {nt}")


def read_pop_npz(
    path: str | os.PathLike, require: Sequence[str] = ("scan_pc", "scan_n", "body_verts", "vtransf")
) -> dict[str, Any]:
    """Read a POP packed npz; returns the POP keys present (``scan_name`` as a str).

    Keys in ``require`` must exist ("<file>: missing key 'scan_n'"); every
    present POP key is shape-checked (see ``POP_KEYS``) and must be finite.
    Other keys in the file are ignored. Pickled object arrays are refused.
    """
    src = os.fspath(path)
    unknown = [k for k in require if k not in POP_KEYS]
    if unknown:
        raise ValueError(f"read_pop_npz: unknown POP keys {unknown}; known: {list(POP_KEYS)}")
    names, raw = fmt.load_npz(src, list(POP_KEYS))
    for k in require:
        if k not in names:
            raise ValueError(f"{src}: missing key '{k}'")
    out: dict[str, Any] = dict(raw)
    if "scan_name" in out:
        name = out["scan_name"]
        if name.dtype.kind not in "US" or name.size != 1:
            raise ValueError(f"{src}: 'scan_name' must be a string, got {name.dtype} {name.shape}")
        name = name.reshape(())[()]
        out["scan_name"] = name.decode() if isinstance(name, bytes) else str(name)
    _check_pop(src, out)
    return out


def write_pop_npz(
    path: str | os.PathLike,
    *,
    scan_pc: np.ndarray,
    scan_n: np.ndarray,
    body_verts: np.ndarray,
    vtransf: np.ndarray,
    scan_name: str,
    posmap256: np.ndarray | None = None,
    posmap_canonical128: np.ndarray | None = None,
) -> None:
    """Write a POP packed npz atomically (float32 arrays, ``scan_name`` as a 0-d unicode array).

    The posmaps are optional here: pocoloco frames can be exported without
    them (they need a UV rasterisation of the body). POP's own loader expects
    both, so add them before feeding POP's original code.
    """
    src = os.fspath(path)
    arrays: dict[str, Any] = {"scan_pc": scan_pc, "scan_n": scan_n, "body_verts": body_verts, "vtransf": vtransf}
    if posmap256 is not None:
        arrays["posmap256"] = posmap256
    if posmap_canonical128 is not None:
        arrays["posmap_canonical128"] = posmap_canonical128
    arrays = {k: np.asarray(v, np.float32) for k, v in arrays.items()}
    _check_pop(src, arrays)
    save_npz_atomic(src, scan_name=np.asarray(str(scan_name)), **arrays)


# --------------------------------------------------------------------------- export
def export_frame(frame_path: str | os.PathLike, out_path: str | os.PathLike, fmt: str = "ply") -> None:
    """Export one frame to a published format.

    fmt="ply": binary PLY with points, normals and (if present) the label per vertex.
    fmt="npz": POP-style packed npz with scan_pc, scan_n, body_verts, vtransf,
    scan_name (no posmaps; see ``published.write_pop_npz``). Needs a frame with
    body_vertices and vtransf (synthetic data). Coordinates are left as stored
    (world frame, not pelvis-centred).
    """
    frame = read_frame(frame_path)
    if fmt == "ply":
        write_ply(out_path, frame.points, normals=frame.normals, labels=frame.labels)
    elif fmt == "npz":
        if frame.body_vertices is None or frame.vtransf is None:
            raise ValueError(f"{os.fspath(frame_path)}: frame has no body_vertices/vtransf; POP export needs them")
        parts = os.path.normpath(os.fspath(frame_path)).split(os.sep)
        scan_name = "_".join(parts[-5:-2] + [parts[-1][:-4]]) if len(parts) >= 5 else parts[-1][:-4]
        write_pop_npz(out_path, scan_pc=frame.points, scan_n=frame.normals, body_verts=frame.body_vertices,
                      vtransf=frame.vtransf, scan_name=scan_name)  # fmt: skip
    else:
        raise ValueError(f"export_frame: fmt must be 'ply' or 'npz', got {fmt!r}")
