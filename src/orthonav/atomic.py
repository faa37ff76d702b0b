"""Atomic file writes: a reader sees the old file or the new one, never half of one; the
checksum that tells a file written whole from one changed or cut short; and a failed write told
in one line naming the file (:func:`file_error`).

Every long-running write of orthonav (map packages, logs, plots, benchmark results, terrain)
goes through :func:`atomic_path`, so a crash or Ctrl-C loses nothing already written.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import stat
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

import numpy as np


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary sibling of ``path`` to write to, renamed over ``path`` when the block succeeds.

    The temporary name keeps the suffix, so writers that choose a format by suffix (matplotlib,
    OpenCV) write the right one. On any error it is removed and ``path`` is left as it was. A
    file system error of the write names ``path``, not the temporary.

    A device or pipe (``/dev/null``, ``/dev/full``) is written to directly: renaming over it
    would replace the device with a file, and it has no old content to keep.
    """
    path = Path(path)
    if is_special(path):
        with _naming(path):
            yield path
        return
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}")
    try:
        with _naming(path, tmp):
            yield tmp
            os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):  # under a file or in a folder gone: nothing was made
            tmp.unlink(missing_ok=True)


# Errors of a write itself, which Python raises without a file name: the disk or the quota is
# full, or the process's file size limit (``ulimit -f``) is reached.
WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
# What each file system error means, in a user's words.
_FILE_ERRORS = {
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "the disk quota is used up",
    errno.EFBIG: "larger than the file size limit (ulimit -f) or the file system allows",
    errno.EACCES: "permission denied",
    errno.EPERM: "not permitted",
    errno.EROFS: "on a read-only file system",
    errno.ENOTDIR: "a part of the path is a file, not a folder",
    errno.EISDIR: "is a folder, expected a file",
    errno.EEXIST: "already exists (and is not a folder)",
    errno.ENOENT: "no such file or folder",
}


def file_error(exc: OSError, show_path: bool = True) -> str:
    """One line for a file system error: the file, what is wrong, and the error's symbolic name
    (``ENOSPC``); without ``show_path`` the file is left out (a server's folders stay private)."""
    what = _FILE_ERRORS.get(exc.errno or 0, exc.strerror or str(exc))
    code = errno.errorcode.get(exc.errno or 0)
    line = f"{what} ({code})" if code else what
    if show_path and exc.filename is not None:
        return f"{exc.filename}: {line}"
    return f"writing a file: {line}" if exc.errno in WRITE_ERRNOS else line


@contextmanager
def _naming(path: Path, tmp: Path | None = None) -> Iterator[None]:
    """OSErrors of writing ``path`` (through ``tmp``) name ``path``, as the user gave it."""
    try:
        yield
    except OSError as exc:
        named = exc.filename is not None and str(exc.filename) == str(tmp)
        if named or (exc.filename is None and exc.errno in WRITE_ERRNOS):
            exc.filename, exc.filename2 = str(path), None
        raise


@contextmanager
def open_output(path: str | Path, mode: str = "w") -> Iterator[IO]:
    """``open(path, mode)`` for a log or a results file written as it goes; a write that fails
    (a full disk, the file size limit) raises an OSError naming ``path``, which Python's own
    writes and closes do not."""
    path = Path(path)
    with _naming(path), open(path, mode) as fh:
        yield fh


def is_special(path: str | Path) -> bool:
    """Whether ``path`` is a device or a pipe (``/dev/null``): written to, never replaced, and
    no place to put files beside (``/dev/null.html``)."""
    try:
        mode = Path(path).stat().st_mode
    except OSError:  # absent (the usual case), or unreachable: the write says why
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def write_text_atomic(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_npz_atomic(path: str | Path, **arrays: np.ndarray) -> None:
    """Compressed numpy arrays (``np.load`` reads them back by name), written atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)


def write_json_atomic(path: str | Path, data: object) -> None:
    """Indented JSON, written atomically; the parent folder is created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(data, indent=2))


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """The file's sha256 as hex, read in chunks (map arrays and models are hundreds of MB)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            digest.update(block)
    return digest.hexdigest()
