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

    from fbg_accel_calibration.diagnosis.blas_threads import blas_core_names

    np.ones((2, 2)) @ np.ones((2, 2))  # the library is loaded with numpy
    return f"OpenBLAS kernel: {', '.join(blas_core_names()) or 'none found'}"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under mutation testing (``bench/mutation_check.py``: mutmut names the mutant in ``MUTANT_UNDER_TEST`` and runs
    in ``mutants/`` beside its ``mutmut-stats.json``), the tests a mutant reaches run fastest first: pytest stops at the
    first failure (-x), so a mutant is killed by its cheapest killer instead of after the slowest tests; and the slow
    tests the bench script leaves out of the mutation run (``MUTATION_LEAVE_OUT``, node-id prefixes separated by
    ``;``) are deselected, a hypothesis property that fails is not shrunk, and a test that takes 30 times its clean
    duration + 10 s fails (mutmut's own timeout, 15 times the clean duration of all the mutant's tests, stays the
    backstop). What the tests assert is unchanged; outside mutation testing nothing is touched."""
    if os.environ.get("MUTANT_UNDER_TEST", "") in ("", "stats", "list_all_tests", "mutant_generation"):
        return
    leave_out = tuple(t for t in os.environ.get("MUTATION_LEAVE_OUT", "").split(";") if t)  # named by the bench script
    if leave_out:
        left = [item for item in items if item.nodeid.startswith(leave_out)]
        if left:
            config.hook.pytest_deselected(items=left)
            items[:] = [item for item in items if not item.nodeid.startswith(leave_out)]
    from hypothesis import Phase, settings

    for item in items:  # a property that fails is not shrunk: the verdict is the same, minutes sooner
        test = getattr(item, "obj", None)
        if hasattr(test, "_hypothesis_internal_use_settings"):
            test._hypothesis_internal_use_settings = settings(
                test._hypothesis_internal_use_settings, phases=[Phase.explicit, Phase.reuse, Phase.generate])
    stats = Path("mutmut-stats.json")
    if stats.is_file():
        seconds = json.loads(stats.read_text())["duration_by_test"]
        items.sort(key=lambda item: seconds.get(item.nodeid, 0.0))
        for item in items:  # a mutant that hangs (a loop that never advances) fails its first test, not minutes later
            item.add_marker(pytest.mark.timeout(10.0 + 30.0 * seconds.get(item.nodeid, 1.0)))
