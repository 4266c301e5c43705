"""Keep a diagnosis's resident memory near what it holds (glibc): hand the heap's free pages back to the system where
it lets go of much at once (``malloc_trim``), let its threads share one heap (``M_ARENA_MAX``), and let that heap
use the pages of freed arrays again instead of faulting in fresh ones (``M_MMAP_THRESHOLD``, ``M_TRIM_THRESHOLD``).

numpy's arrays of up to 32 MiB come from the C heap once glibc has raised its mmap threshold (it does after the
first large array is freed), and the heap keeps their pages when they are freed: after a search has made and dropped
many corrected series of 10^6 samples, the process holds hundreds of MiB it no longer uses, and the next phase's
arrays add to them (the peak resident memory). ``malloc_trim(0)`` gives back every free page of every arena, in
about 10 ms. A thread that allocates while another does gets a heap (arena) of its own, whose free pages sit beside
the first one's: the searches that run side by side (``search_lanes``) share one instead (bench_calibration at 10^6
samples, three runs each: peak RSS 981-1044 MiB with an arena per thread, 951-973 MiB with one; the same time, the
arrays being few and large).

A search makes and drops arrays of 10^5 to 10^6 samples by the thousand (designs of up to 40 MiB, corrected series of
24 MiB). An array glibc maps on its own (above its mmap threshold, which it raises to 32 MiB at most) and every page
a trim gave back are new pages the next array faults in, zeroed by the kernel (``bench_calibration.py`` reports the
diagnosis's page faults and system time). ``keep_freed_pages`` sets the threshold to 64 MiB and lets the heap keep up
to 64 MiB free at its top: the pages of what a search drops serve its next trial, and the trims after each batch of
searches keep what the heap holds between batches from adding to the peak. Elsewhere than on glibc these do nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable

_M_ARENA_MAX = -8  # glibc's mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3
_M_TRIM_THRESHOLD = -1
HEAP_ARRAY_BYTES = 64 << 20  # arrays up to this size come from the heap (keep_freed_pages)
HEAP_TOP_BYTES = 64 << 20  # free memory the heap keeps at its top (more would fault less but hold more at the peak)


@functools.cache
def _glibc(symbol: str) -> Callable[..., int] | None:
    name = ctypes.util.find_library("c")
    try:
        return getattr(ctypes.CDLL(name), symbol) if name else None
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to do
        return None


def return_free_memory() -> bool:
    """Give the heap's free pages back to the system; whether it could (glibc)."""
    trim = _glibc("malloc_trim")
    if trim is None:
        return False
    trim(0)
    return True


def share_one_heap() -> bool:
    """Let every thread made from now on allocate from the heap the process has (for all of the process: threads that
    allocate large arrays now and then gain nothing from heaps of their own); whether it could (glibc)."""
    mallopt = _glibc("mallopt")
    return mallopt is not None and bool(mallopt(_M_ARENA_MAX, 1))


def keep_freed_pages() -> bool:
    """From now on (for all of the process), take arrays of up to ``HEAP_ARRAY_BYTES`` from the heap and let it keep up
    to ``HEAP_TOP_BYTES`` free at its top: a freed array's pages serve the next one instead of being given back and
    faulted in again; whether it could (glibc)."""
    mallopt = _glibc("mallopt")
    return mallopt is not None and bool(mallopt(_M_MMAP_THRESHOLD, HEAP_ARRAY_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, HEAP_TOP_BYTES))


def set_process_heap_policy() -> bool:
    """The heap policy of a process that diagnoses (``share_one_heap`` and ``keep_freed_pages``), for its entry point
    to set once: a library call does not change its caller's allocator. Whether it could (glibc)."""
    return share_one_heap() and keep_freed_pages()
