"""Keeping a long run's resident memory flat: the heap's free pages go back to the OS now and then.

A run allocates and frees frame-sized arrays (a 640x480 xyz map in float64 is 7.4 MB) thousands
of times. glibc serves such a block by ``mmap`` at first, but each time one is freed it raises its
threshold to that size (up to 32 MB), so from then on they come from the heap, and the heap's free
space fragments: a 300-frame RGB-D run's tracking process held 290-320 MB of live blocks
throughout (``mallinfo2``; ``tracemalloc`` saw no growth), while the free space inside its heap
grew from 42 to 158 MB and the resident memory with it (374 -> 605 MB).

``malloc_trim`` hands the heap's free pages back (``MADV_DONTNEED``) without moving anything. The
pages the next frames' temporaries reuse are then faulted in again, which is the cost: trimming
once a second made the 2000-frame walk's tracking 12 % slower (8.1 M page faults instead of
1.9 M), and trimming whenever the free space passed a quarter of the live blocks 21 % slower
(20.9 M). The slow growth is in pages nothing touches again, and those stay returned however
rarely the trim runs, so it runs every :data:`HEAP_TRIM_PERIOD_S` seconds. Two remedies that keep the heap
clean cost more: a fixed mmap threshold maps and faults in every large temporary afresh (the 300
frames took 1.5x as long at 1 MB, 1.9x at glibc's 128 kB).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import time

HEAP_TRIM_PERIOD_S = 5.0
"""At most one trim per five seconds per process: a trim costs about a tenth of a second of page
faults afterwards (the once-a-second trim's 12 %), so about 2 % of the run. The free space grows
with the frames processed, not with time: on the 2000-frame walk the peak RSS of the second half
grew 10 % over the first at 5 s, 15 % at 10 s (as without trimming)."""


def _load_glibc(function: str, argtypes: list, restype):
    """A glibc malloc function (``malloc_trim``, ``mallopt``), or ``None`` (other C libraries: musl, macOS)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        loaded = getattr(ctypes.CDLL(name), function)
    except (OSError, AttributeError):
        return None
    loaded.argtypes, loaded.restype = argtypes, restype
    return loaded


_MALLOC_TRIM = _load_glibc("malloc_trim", [ctypes.c_size_t], ctypes.c_int)
_MALLOPT = _load_glibc("mallopt", [ctypes.c_int, ctypes.c_int], ctypes.c_int)
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4  # <malloc.h>


def keep_large_blocks_in_heap() -> bool:
    """Serve every block from the heap, none from a mapping of its own (glibc; whether it was set).

    glibc maps a block above its mmap threshold (at most 32 MB) afresh and unmaps it when freed,
    so the kernel zeroes every page of each such array on first use; a 1920x1200 FPP frame's
    float64 map is 55 MB, and on 1920x1200 sequences zeroing pages took ~15 % of the cycles
    (``perf``: ``clear_page_erms``). From the heap the next frame's arrays reuse the freed pages
    (ten such arrays in a row: 713 page faults instead of 7260); the heap is not shrunk on every
    free either (the top's trim threshold is raised), and :func:`trim_heap` still hands the free
    pages back every :data:`HEAP_TRIM_PERIOD_S`. Results are the same; system time falls by a
    quarter to a third on 1920x1200 FPP runs, and RGB-D frames are far below the threshold.
    ``fpp-slam run`` and the benchmark scripts set it in their own processes (the pipeline trims
    the heap between its stages, not while fusing, where a trim refaults the map's pages).
    Process-wide and not undone, so only for processes the project owns: the library never sets
    it in a caller's process."""
    if _MALLOPT is None:
        return False
    return bool(_MALLOPT(_M_MMAP_MAX, 0)) and bool(_MALLOPT(_M_TRIM_THRESHOLD, 2**31 - 1))


_LAST_TRIM_S: float | None = None


def trim_heap(period_s: float = HEAP_TRIM_PERIOD_S) -> bool:
    """Return this process's free heap pages to the OS unless that was done within ``period_s``
    (the first call only starts the clock); whether it was done now (never without glibc)."""
    global _LAST_TRIM_S
    if _MALLOC_TRIM is None:
        return False
    now = time.monotonic()
    if _LAST_TRIM_S is None:
        _LAST_TRIM_S = now
    if now - _LAST_TRIM_S < period_s:
        return False
    _MALLOC_TRIM(0)
    _LAST_TRIM_S = time.monotonic()
    return True
