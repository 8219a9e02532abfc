"""Handing freed memory back to the operating system between stages.

glibc's malloc keeps what a process frees in its heap for reuse (only blocks above a
threshold that grows with use are unmapped at once), so after a stage that built large
arrays has dropped them, the process's resident memory stays at that stage's peak, and
the next stage adds its own on top. ``release_memory`` collects Python's garbage and asks
glibc to return the free pages at the heap's top and inside it (``malloc_trim(0)``); it
is a no-op where there is no glibc. The pipeline calls it at the end of every timed stage
(recon.clock.StageClock).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import sys
from functools import lru_cache


@lru_cache(maxsize=1)
def _malloc_trim():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc.malloc_trim
    except (OSError, AttributeError):  # musl and other libcs have no malloc_trim
        return None


def release_memory() -> None:
    """Free unreachable objects and return free heap pages to the OS (module docstring)."""
    gc.collect()
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


__all__ = ["release_memory"]
