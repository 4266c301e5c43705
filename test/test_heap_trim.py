"""The diagnosis's heap kept near what it holds (``heap_trim``; glibc, the machines this project runs on)."""

from __future__ import annotations

import os
import platform

import numpy as np

from fbg_accel_calibration.heap_trim import return_free_memory, share_one_heap

GLIBC = platform.libc_ver()[0] == "glibc"


def _rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def test_the_pages_of_freed_arrays_are_given_back() -> None:
    """Arrays of a few MiB come from the heap once glibc has raised its mmap threshold (it does when a larger array is
    freed); freed below one that is kept, their pages stay resident until the heap is trimmed."""
    big = np.ones(16 * 2**20 // 8)
    del big  # the mmap threshold is now 16 MiB: the 2 MiB arrays below come from the heap
    arrays = [np.ones(2 * 2**20 // 8) for _ in range(100)]
    kept = arrays[-1]
    del arrays
    before = _rss_mib()
    assert return_free_memory() is GLIBC
    after = _rss_mib()
    assert kept.sum() == kept.size
    assert before - after > 100 if GLIBC else after >= 0, (before, after)


def test_the_threads_can_be_made_to_share_one_heap() -> None:
    assert share_one_heap() is GLIBC
