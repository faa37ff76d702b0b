"""Memory handed back to the system after a large request or a mission.

glibc keeps the heap a request grew for its next allocations, so without it the server's footprint
would stay at its largest request's (a large upload validated, a mission flown) for good.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from functools import cache


def release_memory() -> None:
    """Hand the heap memory freed since back to the system (where the C library can)."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


@cache
def _malloc_trim() -> ctypes._CFuncPtr | None:
    """glibc's ``malloc_trim``, or None where the C library has none (musl, macOS)."""
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None
