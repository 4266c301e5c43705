"""Fixtures shared by the test modules (pytest loads this file before them)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest


@pytest.fixture(scope="module")
def ros() -> Iterator[Any]:
    """A private rclpy context per test module (independent of any other module's rclpy.init)."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(args=[], context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def pytest_report_header(config: pytest.Config) -> str:
    """Which OpenBLAS kernel this run computes with (``scripts/test_blas_kernels.sh`` runs the numerical tests under
    each one the CPU has): a failure that only one kernel shows is a result decided by rounding."""
    import numpy as np

    from fbg_accel_calibration.blas_threads import blas_core_names

    np.ones((2, 2)) @ np.ones((2, 2))  # the library is loaded with numpy
    return f"OpenBLAS kernel: {', '.join(blas_core_names()) or 'none found'}"
