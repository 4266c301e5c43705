"""Keep a diagnosis's resident memory near what it holds (glibc): hand the heap's free pages back to the system where
it lets go of much at once (``malloc_trim``), and let its threads share one heap (``M_ARENA_MAX``).

numpy's arrays of up to 32 MiB come from the C heap once glibc has raised its mmap threshold (it does after the
first large array is freed), and the heap keeps their pages when they are freed: after a search has made and dropped
many corrected series of 10^6 samples, the process holds hundreds of MiB it no longer uses, and the next phase's
arrays add to them (the peak resident memory). ``malloc_trim(0)`` gives back every free page of every arena, in
about 10 ms. A thread that allocates while another does gets a heap (arena) of its own, whose free pages sit beside
the first one's: the searches that run side by side (``search_lanes``) share one instead (bench_calibration at 10^6
samples, three runs each: peak RSS 981-1044 MiB with an arena per thread, 951-973 MiB with one; the same time, the
arrays being few and large). Elsewhere than on glibc both do nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable

_M_ARENA_MAX = -8  # glibc's mallopt parameter (malloc.h)


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
