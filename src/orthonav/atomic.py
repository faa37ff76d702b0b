"""Atomic file writes: a reader sees the old file or the new one, never half of one; and the
checksum that tells a file written whole from one changed or cut short.

Every long-running write of orthonav (map packages, logs, plots, benchmark results, terrain)
goes through :func:`atomic_path`, so a crash or Ctrl-C loses nothing already written.
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary sibling of ``path`` to write to, renamed over ``path`` when the block succeeds.

    The temporary name keeps the suffix, so writers that choose a format by suffix (matplotlib,
    OpenCV) write the right one. On any error it is removed and ``path`` is left as it was.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


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
