"""The heap trim that keeps a long run's resident memory flat (fpp_graph.slam.heap)."""

from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.slam import heap

glibc_only = pytest.mark.skipif(heap._MALLOC_TRIM is None, reason="malloc_trim is glibc's; this C library has none")


def _rss_anon_mb() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) / 1024
    pytest.skip("no /proc/self/status RssAnon on this system")


@glibc_only
def test_freed_frame_sized_blocks_go_back_to_the_os(monkeypatch):
    """The pattern of a long run: once a large block was freed, glibc serves frame-sized arrays
    from the heap, and freeing every other one leaves free space the process keeps resident.
    The trim returns it."""
    big = np.ones(16 << 20, np.uint8)
    del big  # glibc's mmap threshold rises to 16 MB: the 2 MB arrays below come from the heap
    arrays = [np.ones(2 << 20, np.uint8) for _ in range(100)]
    kept = arrays[::2]  # holes between live blocks: the heap cannot shrink from its top
    del arrays
    before = _rss_anon_mb()
    monkeypatch.setattr(heap, "_LAST_TRIM_S", 0.0)
    assert heap.trim_heap(period_s=0.0)
    after = _rss_anon_mb()
    assert before - after > 50, (before, after)  # ~100 MB freed; a few pages of each hole stay
    assert sum(int(a[0]) for a in kept) == 50  # the live blocks are untouched


@glibc_only
def test_trims_at_most_once_per_period(monkeypatch):
    calls = []
    clock = [1000.0]
    monkeypatch.setattr(heap, "_MALLOC_TRIM", lambda pad: calls.append(pad) or 1)
    monkeypatch.setattr(heap, "_LAST_TRIM_S", None)
    monkeypatch.setattr(heap.time, "monotonic", lambda: clock[0])
    assert not heap.trim_heap(period_s=10.0)  # the first call starts the clock
    clock[0] += 9.9
    assert not heap.trim_heap(period_s=10.0)
    clock[0] += 0.2
    assert heap.trim_heap(period_s=10.0)
    assert not heap.trim_heap(period_s=10.0)
    assert calls == [0]


def test_without_glibc_nothing_is_done(monkeypatch):
    monkeypatch.setattr(heap, "_MALLOC_TRIM", None)
    monkeypatch.setattr(heap, "_MALLOPT", None)
    assert not heap.trim_heap(period_s=0.0)
    assert not heap.keep_large_blocks_in_heap()


_MAPPED_BYTES_OF_A_FRAME = """
import ctypes, ctypes.util, sys
import numpy as np
from fpp_graph.slam import heap

class Mallinfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

mallinfo2 = ctypes.CDLL(ctypes.util.find_library("c")).mallinfo2
mallinfo2.restype = Mallinfo2
if sys.argv[1] == "heap":
    assert heap.keep_large_blocks_in_heap()
frames = [np.ones((1200, 1920, 3)) for _ in range(2)]  # 1920x1200 float64 maps: 55 MB, above the 32 MB mmap ceiling
print(mallinfo2().hblkhd, mallinfo2().uordblks)
"""


@pytest.mark.skipif(heap._load_glibc("mallinfo2", [], None) is None, reason="mallopt and mallinfo2 are glibc's (2.33+); this C library has none")
def test_large_blocks_stay_in_the_heap():
    """Frame-sized arrays are mapped one by one (the kernel zeroes every page of each afresh),
    unless blocks stay in the heap, where the next frame's arrays reuse freed pages. glibc's
    ``mallinfo2`` tells the bytes in mapped blocks from those in the heap. In a child process:
    the setting is process-wide and not undone."""
    import subprocess
    import sys

    def mapped_and_heap_bytes(mode: str) -> tuple[int, int]:
        out = subprocess.run([sys.executable, "-c", _MAPPED_BYTES_OF_A_FRAME, mode], capture_output=True, text=True, check=True)
        mapped, in_heap = out.stdout.split()[-2:]
        return int(mapped), int(in_heap)

    frames_bytes = 2 * 1200 * 1920 * 3 * 8
    mapped, in_heap = mapped_and_heap_bytes("default")
    assert mapped >= frames_bytes and in_heap < frames_bytes
    mapped, in_heap = mapped_and_heap_bytes("heap")
    assert mapped < frames_bytes and in_heap >= frames_bytes
