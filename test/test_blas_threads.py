"""``blas_threads``: the loaded OpenBLAS libraries run a block with the threads asked for, and get their own back."""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_calibration.diagnosis.blas_threads import blas_thread_counts, blas_threads, single_blas_thread


def test_block_runs_with_one_thread_and_the_counts_come_back() -> None:
    np.ones((2, 2)) @ np.ones((2, 2))  # numpy's OpenBLAS is loaded
    before = blas_thread_counts()
    assert before, "numpy's OpenBLAS not found: the diagnosis would run with every core's BLAS threads"
    with blas_threads(1):
        assert blas_thread_counts() == [1] * len(before)
    assert blas_thread_counts() == before


def test_decorated_function_sees_one_thread_and_restores_on_error() -> None:
    before = blas_thread_counts()

    @single_blas_thread
    def inside() -> list[int]:
        seen = blas_thread_counts()
        raise RuntimeError(str(seen))

    with pytest.raises(RuntimeError) as err:
        inside()
    assert err.value.args[0] == str([1] * len(before))
    assert blas_thread_counts() == before
