"""Fixtures shared by the test modules (pytest loads this file before them)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

# Fast DDS derives its UDP ports from the domain: 0..232 fit below 65536 (scripts/test.sh picks 1..101).
MAX_DOMAIN_ID = 232


def worker_domain_id(base: str, worker: str) -> str:
    """The DDS domain of pytest-xdist worker ``worker`` ("gw0", "gw1", ...) in a run whose domain is ``base``: base + the
    worker's number (wrapped into 0..MAX_DOMAIN_ID), so the workers' nodes and processes never see each other's."""
    return str((int(base) + int(worker.removeprefix("gw"))) % (MAX_DOMAIN_ID + 1))


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--sweeps", action="store_true",
                     help="also run the cases marked 'sweep' (further seeds of a test; bench/seed_sweeps.py runs them)")


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist each worker gets its own ROS_DOMAIN_ID (the run's + its number) before any test module is
    collected, so before any rclpy context or child process starts; without workers nothing changes."""
    config.addinivalue_line("markers", "sweep: a further seed of a test whose representative cases the suite runs; "
                                       "deselected unless --sweeps (bench/seed_sweeps.py)")
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker and "ROS_DOMAIN_ID" in os.environ:
        os.environ["ROS_DOMAIN_ID"] = worker_domain_id(os.environ["ROS_DOMAIN_ID"], worker)
    if hasattr(config, "workeroutput"):  # read back by the controller (pytest_testnodedown)
        config.workeroutput["blas_kernel"] = _blas_kernel()
        config.workeroutput["ros_domain_id"] = os.environ.get("ROS_DOMAIN_ID", "unset")


_WORKERS: dict[str, dict[str, str]] = {}


@pytest.hookimpl(optionalhook=True)  # an xdist hook: without the plugin pytest must not refuse it
def pytest_testnodedown(node: Any, error: Any) -> None:
    """Under pytest-xdist (controller side): what each worker computed with and which DDS domain it used."""
    out = getattr(node, "workeroutput", None) or {}
    if "blas_kernel" in out:
        _WORKERS[node.gateway.id] = out


def _workers_on_another_kernel() -> list[str]:
    mine = _blas_kernel()
    return sorted(w for w, o in _WORKERS.items() if o["blas_kernel"] != mine)


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """A worker computing with another OpenBLAS kernel than this process (so than OPENBLAS_CORETYPE asks for,
    ``scripts/test_blas_kernels.sh``) fails the run even when its tests passed."""
    if _workers_on_another_kernel() and exitstatus == 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: pytest.Config) -> None:
    """Under pytest-xdist, one line per worker: its OpenBLAS kernel and DDS domain."""
    for w, o in sorted(_WORKERS.items()):
        terminalreporter.write_line(f"worker {w}: OpenBLAS kernel {o['blas_kernel']}, ROS_DOMAIN_ID {o['ros_domain_id']}")
    wrong = _workers_on_another_kernel()
    if wrong:
        terminalreporter.write_line(f"ERROR: workers {', '.join(wrong)} did not compute with this run's OpenBLAS kernel "
                                    f"({_blas_kernel()})", red=True)


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
    return f"OpenBLAS kernel: {_blas_kernel()}"


def _blas_kernel() -> str:
    """The OpenBLAS kernel(s) this process computes with (after one product: the library is loaded with numpy)."""
    import numpy as np

    from fbg_accel_calibration.diagnosis.blas_threads import blas_core_names

    np.ones((2, 2)) @ np.ones((2, 2))
    return ", ".join(blas_core_names()) or "none found"


# The test files that wait longest on the wall clock (real-time process tests: simulated boards streaming to driver and
# calibration processes over DDS), longest first, from `scripts/test.sh --durations=40`. They run first, so that on
# pytest-xdist workers (`--dist loadfile --no-loadscope-reorder`, scripts/test.sh) the short tests fill the other
# worker meanwhile instead of one of these starting last and running alone at the end of the run.
LONG_FIRST = (
    "test_calibration_e2e.py",
    "test_two_sensors_process.py",
    "test_calibration_dynamic_process.py",
)


def run_long_tests_first(items: list[pytest.Item]) -> None:
    """Order ``items`` (in place, stably): the files of LONG_FIRST first, in its order; a name there that is no file of
    this directory is a usage error (a renamed file would silently go back to its place)."""
    missing = [name for name in LONG_FIRST if not (Path(__file__).parent / name).is_file()]
    if missing:
        raise pytest.UsageError(f"test/conftest.py LONG_FIRST names no test file: {', '.join(missing)}")
    rank = {name: i for i, name in enumerate(LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FIRST)))


def leave_out_sweeps(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Deselect the cases marked ``sweep`` unless ``--sweeps``: a test over seeds keeps one or two representative cases
    in the suite (each still fails on the defect it was written for); its other seeds run in bench/seed_sweeps.py."""
    if config.getoption("--sweeps"):
        return
    named = {a for a in config.args if "::" in a}  # a case asked for by its node id runs, sweep or not
    swept = [item for item in items if item.get_closest_marker("sweep") and item.nodeid not in named]
    if swept:
        config.hook.pytest_deselected(items=swept)
        items[:] = [item for item in items if item not in swept]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The long tests first (``run_long_tests_first``), the sweeps' further seeds left out (``leave_out_sweeps``). Under
    mutation testing (``bench/mutation_check.py``: mutmut names the mutant in ``MUTANT_UNDER_TEST`` and runs in
    ``mutants/`` beside its ``mutmut-stats.json``), the tests a mutant reaches run fastest first: pytest stops at the
    first failure (-x), so a mutant is killed by its cheapest killer instead of after the slowest tests; and the slow
    tests the bench script leaves out of the mutation run (``MUTATION_LEAVE_OUT``, node-id prefixes separated by ``;``)
    are deselected, a hypothesis property that fails is not shrunk, and a test that takes 30 times its clean duration +
    10 s fails (mutmut's own timeout, 15 times the clean duration of all the mutant's tests, stays the backstop). What
    the tests assert is unchanged; outside mutation testing nothing else is touched."""
    run_long_tests_first(items)
    leave_out_sweeps(config, items)
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
