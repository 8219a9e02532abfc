"""Handing freed memory back to the operating system between stages.

glibc's malloc keeps freed memory in its heap, so a stage's peak would stay resident and
the next stage's would stack on it: ``release_memory`` (called at the end of every timed
stage, recon.core.clock.StageClock) collects Python's garbage and asks glibc to return
the free pages (``malloc_trim(0)``; a no-op without glibc). ``freeze_imported`` takes the
libraries' own objects (torch, Open3D, OpenCV, SciPy: about a quarter of a million, alive
until exit) out of the collector's reach (``gc.freeze``), so that a collection walks only
what the run itself made.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import sys
import time
from functools import lru_cache

# A full collection and trim take a fraction of a second on a large heap, and the streamed
# pipeline ends a stage every few frames (a test's streamed run took 47 s instead of 9 with
# a release at each): at most one release in this many seconds, which still follows every
# long stage, where the large arrays were.
MIN_INTERVAL_S = 5.0
_last_release = [float("-inf")]


@lru_cache(maxsize=1)
def _malloc_trim():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc.malloc_trim
    except (OSError, AttributeError):  # musl and other libcs have no malloc_trim
        return None


def release_memory(force: bool = False) -> None:
    """Free unreachable objects and return free heap pages to the OS (module docstring), at
    most once every MIN_INTERVAL_S seconds unless `force`."""
    if not force and time.monotonic() - _last_release[0] < MIN_INTERVAL_S:
        return
    gc.collect()
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
    _last_release[0] = time.monotonic()


def freeze_imported() -> None:
    """Exempt every object alive now from the collector's passes (``gc.freeze``; module
    docstring).

    For a process that runs the pipeline, called once its libraries are imported and before
    it makes its own objects: what is frozen is never collected, so a reference cycle frozen
    now and dropped later would stay in memory.
    """
    gc.collect()
    gc.freeze()


__all__ = ["freeze_imported", "release_memory"]
