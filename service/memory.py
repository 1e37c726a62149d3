"""Giving memory back to the system after sessions end.

CPython frees a session's objects at once, but the C allocator keeps the freed pages of its heap
for reuse, so a replica's RSS stays at its peak after a burst of sessions has ended. `release()`
collects cycles and asks glibc to return its free pages (`malloc_trim`); elsewhere it only collects.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging

log = logging.getLogger(__name__)


def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):  # not glibc (musl, macOS)
        return None


_TRIM = _malloc_trim()


def release() -> bool:
    """Collect garbage and return free heap pages to the system; True when the C allocator could be asked."""
    gc.collect()
    if _TRIM is None:
        return False
    _TRIM(0)  # a ctypes call: the GIL is released while glibc walks its heap
    return True
