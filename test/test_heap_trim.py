"""The diagnosis's heap kept near what it holds (``heap_trim``; glibc, the machines this project runs on)."""

from __future__ import annotations

import os
import platform

import numpy as np

from fbg_accel_calibration.diagnosis.heap_trim import keep_freed_pages, return_free_memory, share_one_heap

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


def test_a_freed_array_above_glibcs_own_threshold_lends_its_pages_to_the_next() -> None:
    """glibc maps an array above 32 MiB on its own and unmaps it when freed, so each new one faults in fresh zeroed
    pages; after keep_freed_pages it comes from the heap, and the next one reuses the freed one's pages (the first
    array's pages: fewer faults than a tenth of one array's pages for ten more)."""
    import resource

    assert keep_freed_pages() is GLIBC
    pages = 40 * 2**20 // os.sysconf("SC_PAGE_SIZE")
    np.ones(40 * 2**20 // 8).sum()  # the first one may grow the heap
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        assert np.ones(40 * 2**20 // 8).sum() == 40 * 2**20 // 8
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    # without it: about one fault per page, or one per huge page where the kernel backs the mapping with them (here
    # 5320 for the ten arrays' 102400 pages); with it none
    assert faults < pages // 10 if GLIBC else faults >= 0, (faults, pages)
