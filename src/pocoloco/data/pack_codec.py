"""The codecs of a training pack (:mod:`pocoloco.data.pack`): points quantised and sorted along a
Morton curve with neighbour differences, octahedral unit normals, int16 fixed-point arrays, all
LZMA-compressed with their bytes shuffled (low bytes, then high bytes).
"""

from __future__ import annotations

import lzma

import numpy as np

__all__ = ["bytes_member", "decode_int16", "decode_normals", "decode_points", "encode_int16", "encode_normals",
           "encode_points", "lzma_array", "morton_order", "unlzma_array"]  # fmt: skip

_INT16_MAX = 32767


def morton_order(q: np.ndarray) -> np.ndarray:
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
        q[f] = q[f][morton_order(q[f])]
    d = np.diff(q, axis=1, prepend=np.zeros_like(q[:, :1]))  # first point kept, then differences
    return lzma.compress(_shuffle_bytes(d.astype(np.int16)), preset=9 | lzma.PRESET_EXTREME)


def decode_points(blob: bytes, num_frames: int, num_points: int, resolution: float) -> np.ndarray:
    """Inverse of :func:`encode_points` (up to the point order): (F, P, 3) float32 metres."""
    d = _unshuffle_bytes(lzma.decompress(blob), (num_frames, num_points, 3))
    return (np.cumsum(d, axis=1, dtype=np.int32) * resolution).astype(np.float32)


def _sign(x: np.ndarray) -> np.ndarray:
    return np.where(x >= 0, 1.0, -1.0)


def encode_normals(normals: np.ndarray) -> np.ndarray:
    """(..., 3) unit vectors -> (..., 2) int8 octahedral codes (Meyer et al. 2010: the sphere
    folded onto the octahedron |x| + |y| + |z| = 1, its lower half unfolded onto the square's
    corners); within ~1 degree."""
    n = np.asarray(normals, np.float64)
    n = n / np.maximum(np.abs(n).sum(-1, keepdims=True), 1e-12)
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    fx, fy = (1 - np.abs(y)) * _sign(x), (1 - np.abs(x)) * _sign(y)
    uv = np.stack([np.where(z < 0, fx, x), np.where(z < 0, fy, y)], -1)
    return np.clip(np.round(uv * 127), -127, 127).astype(np.int8)


def decode_normals(codes: np.ndarray) -> np.ndarray:
    """Inverse of :func:`encode_normals`: (..., 2) int8 -> (..., 3) float32 unit vectors."""
    uv = np.asarray(codes, np.float64) / 127
    x, y = uv[..., 0], uv[..., 1]
    z = 1 - np.abs(x) - np.abs(y)
    fx, fy = (1 - np.abs(y)) * _sign(x), (1 - np.abs(x)) * _sign(y)
    n = np.stack([np.where(z < 0, fx, x), np.where(z < 0, fy, y), z], -1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def lzma_array(a: np.ndarray) -> np.ndarray:
    """An array's raw little-endian bytes, LZMA-compressed, as a uint8 member."""
    a = np.ascontiguousarray(a)
    return bytes_member(lzma.compress(a.astype(a.dtype.newbyteorder("<")).tobytes(), preset=9))


def unlzma_array(member: np.ndarray, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
    a = np.frombuffer(lzma.decompress(member.tobytes()), dtype)
    if a.size != int(np.prod(shape)):
        raise ValueError(f"holds {a.size} values, expected {int(np.prod(shape))}")
    return a.reshape(shape)


def encode_int16(a: np.ndarray, resolution: float, what: str) -> bytes:
    """Values -> LZMA bytes of their int16 codes in ``resolution`` units (bytes shuffled); one line if out of range."""
    q = np.round(np.asarray(a, np.float64) / resolution)
    if q.size and np.abs(q).max() > _INT16_MAX:
        raise ValueError(f"{what} out of the range int16 codes hold at {resolution:g} m")
    return lzma.compress(_shuffle_bytes(q.astype(np.int16)), preset=9)


def decode_int16(blob: bytes, shape: tuple[int, ...], resolution: float) -> np.ndarray:
    """Inverse of :func:`encode_int16`: float32 values of ``shape``."""
    return (_unshuffle_bytes(lzma.decompress(blob), shape).astype(np.float64) * resolution).astype(np.float32)


def bytes_member(raw: bytes) -> np.ndarray:
    """Bytes as a uint8 array (a member of the pack's zip)."""
    return np.frombuffer(raw, np.uint8)
