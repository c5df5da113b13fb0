"""Atomic file writes (a temporary file beside the target, then a rename) and lock files (one home).

An interrupted write (a killed process, a full disk) leaves the previous file or none, never a
truncated one. Every writer of the package goes through here (checkpoints, stores, shards,
extended XYZ, JSON, NPZ, plots):

* :func:`atomic_path` yields a temporary *path* for writers that want a file name
  (``torch.save``, ``np.savez``, h5py, ``shutil.copyfile``);
* :func:`atomic_write` calls ``write(handle)`` on an open text or binary handle;
* :func:`try_lock` takes an exclusive lock on a lock file without waiting (one writer of a
  store, one training of a run folder at a time);
* :func:`write_bytes_atomic`, :func:`write_text_atomic`, :func:`write_json_atomic`,
  :func:`write_npz_atomic` and :func:`write_figure_atomic` (a matplotlib figure) write one
  value.

The file keeps the permissions of the file it replaces (a new one gets the umask's default),
and a temporary file is never left behind.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "atomic_path",
    "atomic_write",
    "try_lock",
    "write_bytes_atomic",
    "write_figure_atomic",
    "write_json_atomic",
    "write_npz_atomic",
    "write_text_atomic",
]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``.

    For writers that want a file name (``torch.save``, ``np.savez``, h5py, ASE). ``suffix``
    keeps an extension that a writer needs (e.g. ``".npz"``). The parent folder is created; the
    temporary path does not exist yet (the writer creates it: h5py refuses an empty file). On an
    exception the temporary file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    os.unlink(tmp)  # a unique name; the writer creates the file
    try:
        yield Path(tmp)
        os.chmod(tmp, _file_mode(path))
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write(
    path: str | os.PathLike, write: Callable[[IO], Any], binary: bool = False
) -> None:
    """Call ``write(handle)`` on a temporary file beside ``path`` (text, UTF-8, unless
    ``binary``), flush it to disk, then rename it onto ``path``."""
    with atomic_path(path) as tmp:
        text = {} if binary else {"encoding": "utf-8", "newline": ""}  # no newline translation
        with open(tmp, "xb" if binary else "x", **text) as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())


def try_lock(path: str | os.PathLike) -> int | None:
    """An exclusive advisory lock (``flock``) on the file ``path`` (created when missing),
    taken without waiting: its file descriptor, held until closed (``os.close``) or until the
    process ends (a killed holder leaves no stale lock), or None when another process holds
    it."""
    import fcntl

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(str(path), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (flushed to disk before the rename)."""
    atomic_write(path, lambda fh: fh.write(data), binary=True)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes_atomic(path, text.encode())


def write_json_atomic(
    path: str | os.PathLike, data: Any, default: Callable[[Any], Any] | None = None
) -> None:
    """JSON (indent 1, trailing newline) written atomically; ``default`` as in
    :func:`json.dumps` (for values JSON does not know)."""
    write_text_atomic(path, json.dumps(data, indent=1, default=default) + "\n")


def write_npz_atomic(path: str | os.PathLike, compressed: bool = False, **arrays) -> None:
    """Write ``arrays`` as an ``.npz`` archive atomically (``np.savez``, or
    ``np.savez_compressed`` when ``compressed``), flushed to disk before the rename."""
    save = np.savez_compressed if compressed else np.savez
    atomic_write(path, lambda fh: save(fh, **arrays), binary=True)


def write_figure_atomic(path: str | os.PathLike, figure: Figure, dpi: int = 120) -> None:
    """Save a matplotlib ``figure`` to ``path`` atomically, in the format of its suffix
    (``.png`` when it has none)."""
    fmt = Path(path).suffix.lstrip(".").lower() or "png"
    atomic_write(path, lambda fh: figure.savefig(fh, format=fmt, dpi=dpi), binary=True)


def _file_mode(path: Path) -> int:
    """The permissions of the file being replaced, or a new file's default under the umask."""
    if path.exists():
        return path.stat().st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask
