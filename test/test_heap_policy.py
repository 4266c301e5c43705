"""The heap policy of a process that diagnoses (``heap_policy``; glibc, the machines this project runs on): one heap for
its threads, the pages of freed arrays kept for the next ones, and no huge-page advice for numpy's arrays."""

from __future__ import annotations

import os
import platform
import resource

import numpy as np

from fbg_accel_calibration.diagnosis.heap_policy import keep_freed_pages, share_one_heap, small_pages_for_arrays

GLIBC = platform.libc_ver()[0] == "glibc"


def test_the_threads_can_be_made_to_share_one_heap() -> None:
    assert share_one_heap() is GLIBC


def test_a_freed_array_above_glibcs_own_threshold_lends_its_pages_to_the_next() -> None:
    """glibc maps an array above 32 MiB on its own and unmaps it when freed, so each new one faults in fresh zeroed
    pages; after keep_freed_pages it comes from the heap, and the next one reuses the freed one's pages (the first
    array's pages: fewer faults than a tenth of one array's pages for ten more)."""
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


def test_the_pages_of_many_arrays_freed_at_once_serve_the_next_ones() -> None:
    """A phase that drops 160 MiB of arrays at once (a search's trials, a step's designs) leaves them at the heap's top;
    glibc gives a top beyond its trim threshold back to the system (its default: twice its mmap threshold; 64 MiB here
    before), and the next phase faults the pages in again. Kept (``HEAP_TOP_BYTES``), they serve the next phase's
    arrays: fewer faults than a tenth of their pages."""
    assert keep_freed_pages() is GLIBC
    size = 2 * 2**20 // 8  # 2 MiB arrays: from the heap, not madvised for huge pages by numpy (from 4 MiB)
    count = 80
    pages = count * 2 * 2**20 // os.sysconf("SC_PAGE_SIZE")
    arrays = [np.ones(size) for _ in range(count)]
    del arrays
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    arrays = [np.ones(size) for _ in range(count)]
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    assert sum(float(a[0]) for a in arrays) == count
    assert faults < pages // 10 if GLIBC else faults >= 0, (faults, pages)


def test_numpy_can_be_told_not_to_advise_its_arrays_for_huge_pages() -> None:
    """``small_pages_for_arrays`` reaches numpy's own switch (the one ``NUMPY_MADVISE_HUGEPAGE`` sets at import): off
    after it, and this test process's setting put back after."""
    from numpy._core import multiarray

    before = multiarray._get_madvise_hugepage()
    try:
        multiarray._set_madvise_hugepage(True)
        assert small_pages_for_arrays()
        assert multiarray._get_madvise_hugepage() is False
    finally:
        multiarray._set_madvise_hugepage(before)
