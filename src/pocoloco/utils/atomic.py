"""Atomic file writes: a reader never sees a half-written file.

Each writer writes to a temporary file in the destination's folder, flushes and
fsyncs it, then ``os.replace``s it over the destination (atomic on POSIX and
Windows when both are on the same filesystem). If writing fails the temporary
file is removed and the destination is left as it was.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

__all__ = ["atomic_write", "atomic_open", "exclusive_lock", "jsonable", "no_file_reason", "output_folder", "save_npz_atomic",
           "write_json_atomic", "write_text_atomic"]


def _fsync_dir(folder: str) -> None:
    """fsync a directory so the rename itself is durable (best effort, POSIX only)."""
    if os.name != "posix":
        return
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb", exclusive: bool = False) -> Iterator[IO[Any]]:
    """Context manager yielding a file object whose content replaces ``path`` on success.

    ``mode`` is ``"wb"`` (default) or ``"w"`` (text, UTF-8). Parent folders are
    created. On an exception inside the block the destination is untouched.

    exclusive: create ``path`` only if it does not exist yet, else raise ``FileExistsError``
    and leave it as it is (several processes racing to create the same file: exactly one
    wins). The temporary file is hard-linked to ``path`` (atomic on POSIX filesystems, NFS
    included); where hard links are not supported it is renamed after a last existence
    check (a narrow race remains there).
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_open: mode must be 'wb' or 'w', got {mode!r}")
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    # like tempfile.mkstemp, but with the usual 0o666 & ~umask permissions (mkstemp makes 0o600 files)
    tmp = os.path.join(folder, f".{os.path.basename(path)}.{uuid.uuid4().hex[:12]}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    try:
        kwargs = {"encoding": "utf-8", "newline": "\n"} if mode == "w" else {}
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        if exclusive:
            _link_or_rename(tmp, path)
        else:
            os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _fsync_dir(folder)


def _link_or_rename(tmp: str, path: str) -> None:
    """Move ``tmp`` to ``path`` if ``path`` does not exist (FileExistsError otherwise)."""
    try:
        os.link(tmp, path)  # fails with FileExistsError if path exists, atomically
    except FileExistsError:
        raise
    except OSError:  # no hard links on this filesystem
        if os.path.exists(path):
            raise FileExistsError(path) from None
        os.replace(tmp, path)
        return
    os.unlink(tmp)


def atomic_write(path: str | os.PathLike, write_fn: Callable[[IO[bytes]], Any]) -> None:
    """Call ``write_fn(binary_file)`` and atomically move the result to ``path``."""
    with atomic_open(path, "wb") as f:
        write_fn(f)


def save_npz_atomic(path: str | os.PathLike, compress: bool = False, **arrays: Any) -> None:
    """``np.savez`` (or ``savez_compressed``) to ``path`` atomically.

    The file name is used as given (numpy's automatic ``.npz`` suffix is not
    added, since we write to an open file object).
    """
    saver = np.savez_compressed if compress else np.savez
    atomic_write(path, lambda f: saver(f, **arrays))


def write_json_atomic(path: str | os.PathLike, obj: Any, indent: int | None = 2, exclusive: bool = False) -> None:
    """Write ``obj`` as JSON (UTF-8, sorted insertion order kept) to ``path`` atomically
    (``exclusive``: only if ``path`` does not exist, see :func:`atomic_open`)."""
    text = json.dumps(obj, indent=indent, ensure_ascii=False, allow_nan=False) + "\n"
    with atomic_open(path, "w", exclusive=exclusive) as f:
        f.write(text)


def output_folder(path: str | os.PathLike) -> Path:
    """``path`` as a Path, after checking it is a folder or does not exist yet (one-line error)."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: exists and is not a folder")
    return out


def no_file_reason(path: str | os.PathLike) -> str:
    """Why ``path`` is not a readable file, in words: a folder, or nothing there."""
    return "is a folder, not a file" if os.path.isdir(path) else "no such file"


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write a UTF-8 text file atomically."""
    with atomic_open(path, "w") as f:
        f.write(text)


def jsonable(x: Any, digits: int | None = None) -> Any:
    """A JSON-ready copy: NaN / inf -> None, numpy scalars / arrays -> Python, dict keys -> str, recursively.
    ``digits``: floats rounded to that many significant digits (a report of many per-pose numbers
    stays small; 6 keeps 1e-6 of each value); None: kept as they are."""
    if isinstance(x, dict):
        return {str(k): jsonable(v, digits) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v, digits) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist(), digits)
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return jsonable(x.item(), digits)
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, float) and digits is not None:
        return float(f"{x:.{digits}g}")
    return x


@contextlib.contextmanager
def exclusive_lock(folder: str | os.PathLike, what: str, name: str = ".lock", shared: bool = False) -> Iterator[Path]:
    """Hold an exclusive lock on ``folder`` (created if missing) for the block: ``folder/NAME``
    (default ``.lock``), locked with ``flock``, so the lock dies with its process (``kill -9``
    included) and a later run never finds a stale one. A second holder gets a one-line ValueError
    naming the holder (``what``: the kind of work, for the message). ``shared``: a shared lock
    instead, which any number of shared holders may hold at once but no exclusive one (the shards
    of one dataset; each also locks its own shard exclusively). Where ``fcntl`` does not exist
    (Windows) the block runs unlocked.

    Nothing is left behind on any way out, a refusal included: a lock file this call created is
    removed (while still locked; a shared holder removes it only when no other holder has it), a
    folder it created is removed when nothing else was written into it; a lock file that was there
    before stays. A holder that finds its lock file unlinked by the previous holder retries on the
    new one, so two holders never lock two different files."""
    folder = Path(folder)
    created = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield path
        return
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
            made = True
        except FileExistsError:
            try:
                fd = os.open(path, os.O_RDWR)
            except FileNotFoundError:  # removed by its last holder in between: try again
                continue
            made = False
        f = os.fdopen(fd, "r+", encoding="utf-8")
        try:
            fcntl.flock(f.fileno(), (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            f.close()
            raise ValueError(f"{folder}: in use by {holder}; wait for it to end or choose another folder") from None
        try:
            same = os.fstat(f.fileno()).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        f.close()  # the file we locked was unlinked by its last holder: lock the current one
    try:
        if not shared:  # the holder, for a refused second writer's message
            f.seek(0)
            f.truncate()
            f.write(f"{what} (pid {os.getpid()} on {os.uname().nodename})\n")
            f.flush()
        yield path
    finally:
        try:
            alone = True
            if shared:  # the last shared holder removes it: none other holds it if we can take it alone
                try:
                    fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    alone = False
            if (made or created) and alone:
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()  # removed while locked: a waiting holder sees the inode change
            if created and alone:
                with contextlib.suppress(OSError):
                    folder.rmdir()  # a run that failed before writing anything leaves no folder behind
        finally:
            f.close()  # releases the lock
