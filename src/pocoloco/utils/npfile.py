"""What kind of NumPy file a path holds, read from its first bytes.

``np.load`` takes any file that is neither ``.npy`` nor ``.npz`` for a pickle and, with
``allow_pickle=False``, answers a text file or an image with "This file contains pickled (object)
data". The readers call :func:`numpy_file_problem` when a load fails (never on the fast path) to
give the user the real reason in one line.
"""

from __future__ import annotations

import os

__all__ = ["NPY_MAGIC", "ZIP_MAGIC", "numpy_file_kind", "numpy_file_problem"]

#: first bytes of a .npy file (numpy.lib.format) and of a zip archive (.npz; the second: an empty one)
NPY_MAGIC = b"\x93NUMPY"
ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")
_NOUN = {"npy": "array", "npz": "archive"}


def numpy_file_kind(path: str | os.PathLike) -> str | None:
    """``"npy"``, ``"npz"`` or None (neither, an empty file, or unreadable) from the first bytes."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(NPY_MAGIC))
    except OSError:
        return None
    if head == NPY_MAGIC:
        return "npy"
    if head[:4] in ZIP_MAGIC:
        return "npz"
    return None


def numpy_file_problem(path: str | os.PathLike, expect: str | None = None) -> str | None:
    """Why ``path`` is not a NumPy file (of the ``expect``-ed kind, ``"npy"`` / ``"npz"``), in
    words; None when its first bytes are right (the problem, if any, lies further in)."""
    kind = numpy_file_kind(path)
    if kind is None:
        try:
            empty = os.path.getsize(path) == 0
        except OSError:
            return "cannot be read"
        return "empty file" if empty else "not a NumPy file (neither a .npy array nor a .npz archive)"
    if expect is not None and kind != expect:
        return f"a NumPy .{kind} {_NOUN[kind]}, not a .{expect} {_NOUN[expect]}"
    return None
