"""The heap policy of a process that diagnoses (glibc): its threads share one heap (``M_ARENA_MAX``), and that heap
serves a freed array's pages to the next one instead of giving them back to be faulted in again (``M_MMAP_THRESHOLD``,
``M_TRIM_THRESHOLD``). Set once by the entry point (the ``diagnose`` command; ``bench/``'s scripts that time or weigh
the diagnosis as it runs there): a library call does not change its caller's allocator, and the diagnosis's results do
not depend on it.

A search makes and drops arrays of 10^5 to 10^6 samples by the thousand (designs of up to 40 MiB, corrected series of
24 MiB). An array glibc maps on its own (above its mmap threshold, which it raises to 32 MiB at most) and every page
the heap gives back are new pages the next array faults in, zeroed by the kernel: system time, a few microseconds a
page (``bench_calibration.py`` reports the diagnosis's page faults and system time). ``keep_freed_pages`` takes arrays
of up to 64 MiB from the heap and lets it keep up to ``HEAP_TOP_BYTES`` free at its top, so that what a search drops
serves its next trial. The peak resident memory is the peak of what the diagnosis holds, plus the heap's
fragmentation: the heap grows only when what is alive outgrows it, and a search takes its arrays from the pages the
one before freed (``bench/floors.py --only diagnose``: the peak at 10^6 samples against the 600 MiB goal). One
exception: ``diagnose`` gives the heap's free pages back once (``return_free_memory``), after its searches, before its
final phase maps its designs of every sample on their own (N x p, above ``HEAP_ARRAY_BYTES``): kept, the searches'
free pages would stand beside them at the peak (``bench/diagnose_memory.py``: 617 MiB without it, 545 MiB with). A thread
that allocates while another does gets a heap (arena) of its own, whose free pages sit beside the first one's: the
searches that run side by side (``search_lanes``) share one instead. Elsewhere than on glibc these do nothing.

The pages themselves are the kernel's small ones (``small_pages_for_arrays``): numpy advises every array of 4 MiB or
more for transparent huge pages (``madvise(MADV_HUGEPAGE)``, its default on Linux), and where the kernel honours that
advice (``/sys/kernel/mm/transparent_hugepage/enabled`` set to ``madvise``, the usual default) a fault in such an array
zeroes a 2 MiB page, compacting memory to find one (``defrag`` set to ``madvise``). On a heap whose freed pages serve
the next arrays, few faults are left for huge pages to save and each costs more: without the advice the diagnosis's
system time is about halved and its CPU time a few per cent lower, though its own work takes a little longer on small
pages (more misses of the processor's page-table cache) (``bench/huge_pages.py``: docs/diagnose_speed.md). Where the
kernel backs every mapping with huge pages (``always``) or none (``never``) the advice changes nothing.
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
HEAP_TOP_BYTES = 256 << 20  # free memory the heap keeps at its top: a phase after a larger one takes its pages from it


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


def small_pages_for_arrays(small: bool = True) -> bool:
    """From now on (for all of the process), numpy does not advise its large arrays for transparent huge pages (its
    documented ``NUMPY_MADVISE_HUGEPAGE=0``, which it reads at import only, set at run time through the call numpy's own
    import makes; ``small`` false: its advice again, as ``bench/huge_pages.py`` compares); whether it could (a numpy
    that has the call)."""
    import importlib

    for module in ("numpy._core.multiarray", "numpy.core.multiarray"):  # numpy 2, numpy 1
        try:
            advise = getattr(importlib.import_module(module), "_set_madvise_hugepage", None)
        except ImportError:
            continue
        if advise is not None:
            advise(not small)
            return True
    return False


def set_process_heap_policy() -> bool:
    """The heap policy of a process that diagnoses (``share_one_heap``, ``keep_freed_pages`` and
    ``small_pages_for_arrays``), for its entry point to set once: a library call does not change its caller's
    allocator. Whether it could (glibc, and a numpy that has the call)."""
    done = [share_one_heap(), keep_freed_pages(), small_pages_for_arrays()]  # each whether or not another could
    return all(done)
