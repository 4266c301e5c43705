"""Fixtures shared by the test modules (pytest loads this file before them)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
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


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under mutation testing (``bench/mutation_check.py``: mutmut names the mutant in ``MUTANT_UNDER_TEST`` and runs
    in ``mutants/`` beside its ``mutmut-stats.json``), the tests a mutant reaches run fastest first: pytest stops at the
    first failure (-x), so a mutant is killed by its cheapest killer instead of after the slowest tests. Which tests
    run, and what they assert, is unchanged; outside mutation testing nothing is reordered."""
    if os.environ.get("MUTANT_UNDER_TEST", "") in ("", "stats", "list_all_tests", "mutant_generation"):
        return
    stats = Path("mutmut-stats.json")
    if stats.is_file():
        seconds = json.loads(stats.read_text())["duration_by_test"]
        items.sort(key=lambda item: seconds.get(item.nodeid, 0.0))
