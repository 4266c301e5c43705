"""How many threads the loaded OpenBLAS libraries use, changed for a block of code (ctypes, no dependency).

numpy's and scipy's wheels bundle OpenBLAS, which starts one thread per core for every matrix product it deems
large enough. The diagnosis makes thousands of products of tall, narrow matrices (10^5 rows x ~25 columns, one per
fold and trial value): split over the 2 cores of the benchmark machine they took ~2x the CPU time of one thread for
no wall-clock gain when the machine was idle, and while another process used a core the waiting BLAS threads made a
diagnosis of 10^5 samples 6x slower (71.7 s against 11.4 s wall, ``bench/bench_calibration.py``). This is what
``threadpoolctl`` does for OpenBLAS, for the library names numpy and scipy ship: the libraries mapped into the process
(``/proc/self/maps``) whose file name contains "openblas", through their ``*set_num_threads*`` entry points.
Elsewhere (no ``/proc``, another BLAS) nothing is changed.
"""

from __future__ import annotations

import ctypes
import functools
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

# (get, set) entry points of OpenBLAS builds: plain, scipy-openblas 64-bit integer builds (numpy >= 2), 32-bit ones
_ENTRY_POINTS = (("openblas_get_num_threads", "openblas_set_num_threads"),
                 ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                 ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
                 ("openblas_get_num_threads64_", "openblas_set_num_threads64_"))

F = TypeVar("F", bound=Callable[..., Any])


def _openblas_libraries() -> list[Any]:
    """Every OpenBLAS library mapped into this process, once per file (``/proc/self/maps``; empty elsewhere)."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as f:
            paths = {line.split(None, 5)[5].strip() for line in f if len(line.split(None, 5)) == 6}
    except OSError:
        return []
    out = []
    for path in sorted(p for p in paths if "openblas" in os.path.basename(p).lower() and os.path.isfile(p)):
        try:
            out.append(ctypes.CDLL(path, mode=getattr(os, "RTLD_NOLOAD", 0) | ctypes.RTLD_GLOBAL))
        except OSError:
            continue
    return out


def _loaded_openblas() -> list[tuple[Any, Any]]:
    """(get, set) thread-count functions of every OpenBLAS library mapped into this process, once per file."""
    out = []
    for lib in _openblas_libraries():
        for get_name, set_name in _ENTRY_POINTS:
            get, set_ = getattr(lib, get_name, None), getattr(lib, set_name, None)
            if get is not None and set_ is not None:
                get.restype, set_.restype = ctypes.c_int, None
                out.append((get, set_))
                break
    return out


def blas_core_names() -> list[str]:
    """The kernel family each loaded OpenBLAS library runs (``openblas_get_corename``: e.g. "Haswell", "SkylakeX"; set
    by the CPU, or by ``OPENBLAS_CORETYPE``). Their rounding differs, so a result that changes with it is at a
    threshold."""
    names = []
    for lib in _openblas_libraries():
        for entry in ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename", "openblas_get_corename64_",
                      "openblas_get_corename"):
            get = getattr(lib, entry, None)
            if get is not None:
                get.restype = ctypes.c_char_p
                names.append(get().decode("ascii", "replace"))
                break
    return names


def blas_thread_counts() -> list[int]:
    """The thread count of each OpenBLAS library loaded (empty if none is found)."""
    return [int(get()) for get, _ in _loaded_openblas()]


@contextmanager
def blas_threads(n: int) -> Iterator[None]:
    """Run the block with every loaded OpenBLAS limited to ``n`` threads; their counts are restored after."""
    libs = _loaded_openblas()
    before = [int(get()) for get, _ in libs]
    for _, set_ in libs:
        set_(ctypes.c_int(int(n)))
    try:
        yield
    finally:
        for (_, set_), k in zip(libs, before, strict=True):
            set_(ctypes.c_int(k))


def single_blas_thread(fn: F) -> F:
    """Decorator: ``fn`` runs with one BLAS thread (:func:`blas_threads`)."""
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with blas_threads(1):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
