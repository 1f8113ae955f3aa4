"""Keeping a long run's resident memory flat: freed heap pages go back to the OS now and then.

A run allocates and frees frame-sized arrays (a 640x480 xyz map in float64 is 7.4 MB) thousands
of times. glibc serves such a block by ``mmap`` at first, but each time one is freed it raises its
threshold to that size (up to 32 MB), so from then on they come from the heap, and the heap's free
space fragments: a 300-frame RGB-D run's tracking process held 290-320 MB of live blocks
throughout (``mallinfo2``; ``tracemalloc`` saw no growth), while the free space inside its heap
grew from 42 to 158 MB and the resident memory with it (374 -> 605 MB). Fixing the threshold
keeps the heap clean but maps and faults in every large temporary afresh: the same run took 1.5x
(1 MB threshold) to 1.9x (glibc's 128 kB) as long. ``malloc_trim`` instead hands the heap's free
pages back (``MADV_DONTNEED``) and leaves its layout alone; a page is faulted in again only when
it is used again.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import time

log = logging.getLogger(__name__)

HEAP_TRIM_PERIOD_S = 1.0
"""At most one ``malloc_trim`` per second per process: a trim and the page faults that follow it
cost a few milliseconds against a second of frames (30 at 30 Hz), and the free pages a second of
work can touch again is what the resident memory then varies by."""


def _load_malloc_trim():
    """glibc's ``malloc_trim``, or ``None`` (other C libraries: musl, macOS)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


_MALLOC_TRIM = _load_malloc_trim()
_LAST_TRIM_S = 0.0


def trim_heap(period_s: float = HEAP_TRIM_PERIOD_S) -> bool:
    """Return this process's free heap pages to the OS unless that was done within ``period_s``;
    whether it was done now (never without glibc)."""
    global _LAST_TRIM_S
    if _MALLOC_TRIM is None:
        return False
    now = time.monotonic()
    if now - _LAST_TRIM_S < period_s:
        return False
    _MALLOC_TRIM(0)
    _LAST_TRIM_S = time.monotonic()
    return True
