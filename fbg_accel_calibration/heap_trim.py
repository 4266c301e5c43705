"""Hand the heap's free pages back to the system (glibc ``malloc_trim``), where a diagnosis lets go of much at once.

numpy's arrays of up to 32 MiB come from the C heap once glibc has raised its mmap threshold (it does after the
first large array is freed), and the heap keeps their pages when they are freed: after a search has made and dropped
many corrected series of 10^6 samples, the process holds hundreds of MiB it no longer uses, and the next phase's
arrays add to them (the peak resident memory). ``malloc_trim(0)`` gives back every free page of every arena, in
about 10 ms. Elsewhere than on glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to trim
        return None


def return_free_memory() -> bool:
    """Give the heap's free pages back to the system; whether it could (glibc)."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
