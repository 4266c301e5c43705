"""Fixtures shared by the test modules (pytest loads this file before them)."""

from __future__ import annotations

import ast
import functools
import json
import os
import sys
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
    config.addinivalue_line("markers", f"{REAL_TIME_MARK}: a file whose tests wait on the wall clock for processes, ptys "
                                       "or DDS; run one after another on one worker (test/conftest.py)")
    _watch_real_time_starts()
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


# Real-time tests wait on the wall clock for other processes and threads: simulated boards streaming over a pty to
# driver and calibration processes over DDS, command-line tools run as processes. A file whose tests start a child
# process, open a pseudo-terminal or use the ``ros`` fixture declares ``pytestmark = pytest.mark.real_time``; a test of
# a file that does not fails naming what it did (``pytest_runtest_call``), so a new real-time file cannot go unnoticed.
# On pytest-xdist workers (scripts/test.sh) the real-time files are one work unit, run on one worker one after another
# as in a serial run: they see at most the other worker's computation as load, never each other.
REAL_TIME_MARK = "real_time"
_PROCESS_EVENTS = frozenset({"subprocess.Popen", "os.fork", "os.forkpty", "os.posix_spawn", "os.spawn", "os.system",
                             "os.exec"})  # the audit events (sys.addaudithook) of starting a process
_real_time_seen: set[str] = set()  # what the running test did that makes it real-time (cleared at each setup)


# What libraries run to look something up, not part of what a test waits on: ``ctypes.util.find_library`` runs
# ``ldconfig -p`` (the diagnosis finds the C library to return freed memory with it); matplotlib's font manager runs
# ``fc-list`` once, to build its font cache on a machine that has none (a fresh CI machine's first test that draws).
_LOOKUP_PROGRAMS = frozenset({"ldconfig", "fc-list"})


def _audit(event: str, args: tuple) -> None:
    if event in _PROCESS_EVENTS:
        program = args[0] if event == "subprocess.Popen" and args else None
        if program is None or Path(os.fsdecode(program)).name not in _LOOKUP_PROGRAMS:
            _real_time_seen.add("starts a child process")


def _watch_real_time_starts() -> None:
    """Record, for the test that runs, each child process it starts (Python's audit events) and each pseudo-terminal
    it opens (``os.openpty``, which ``pty.openpty`` and the simulator's pty server call, has no audit event: it is
    wrapped). Process-wide and not removable (an audit hook), so installed once per process."""
    if getattr(os.openpty, "_records_real_time", False):
        return
    sys.addaudithook(_audit)
    openpty = os.openpty

    @functools.wraps(openpty)
    def recorded_openpty() -> tuple[int, int]:
        _real_time_seen.add("opens a pseudo-terminal")
        return openpty()

    recorded_openpty._records_real_time = True  # type: ignore[attr-defined]
    os.openpty = recorded_openpty


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    _real_time_seen.clear()  # before the fixtures of this test (also its module's) are set up


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Iterator[None]:
    """A test that passed but started a process, opened a pty or used the ``ros`` fixture (in its setup or its body)
    while its file does not declare ``real_time`` fails, naming what it did."""
    result = yield
    if item.get_closest_marker(REAL_TIME_MARK) is None:
        did = sorted(_real_time_seen) + (["uses the `ros` fixture"] if "ros" in getattr(item, "fixturenames", ()) else [])
        if did:
            pytest.fail(f"{item.path.name} {' and '.join(did)} but does not declare "
                        f"`pytestmark = pytest.mark.{REAL_TIME_MARK}` (test/conftest.py)", pytrace=False)
    return result


def declares_real_time(path: Path) -> bool:
    """The test file ``path`` declares ``pytestmark = pytest.mark.real_time`` (alone or in a list) at module level.
    Read from the source, so pytest-xdist's controller, which collects nothing, groups by it too; each worker checks it
    against the marks its tests carry (``run_real_time_first``), so the two cannot disagree silently."""
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets):
            return f"pytest.mark.{REAL_TIME_MARK}" in ast.unparse(node.value)
    return False


def run_real_time_first(items: list[pytest.Item]) -> None:
    """Order ``items`` (in place, stably): the real-time files' tests first, each file's in its order. On workers they
    are one work unit (``pytest_xdist_make_scheduler``), the first: it starts at once and the other files fill the
    other worker meanwhile, instead of a long real-time file starting last and running alone at the end of the run.
    A test marked ``real_time`` in a file that does not declare it at module level is a usage error (its file would run
    beside the real-time group)."""
    declared: dict[Path, bool] = {}
    for item in items:
        if item.path not in declared:
            declared[item.path] = declares_real_time(item.path)
        if item.get_closest_marker(REAL_TIME_MARK) is not None and not declared[item.path]:
            raise pytest.UsageError(f"{item.nodeid} is marked {REAL_TIME_MARK} but its file does not declare "
                                    f"`pytestmark = pytest.mark.{REAL_TIME_MARK}` at module level (test/conftest.py)")
    items.sort(key=lambda item: not declared[item.path])


@pytest.hookimpl(optionalhook=True)  # an xdist hook: without the plugin pytest must not refuse it
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """Under ``--dist loadfile`` (scripts/test.sh, scripts/test_blas_kernels.sh) each test file is one work unit, so its
    module fixtures (one simulated board, one diagnosis shared by several tests) are built once, in one worker; and all
    real-time files (``declares_real_time``) are one unit, run one after another on one worker. Units go out in
    collection order when given ``--no-loadscope-reorder``. (pytest-xdist's own ``--dist loadgroup`` cannot do this
    with pytest 9.2: the group it writes into a test's node id no longer reaches the node id, so it groups nothing.)"""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    real_time: dict[str, bool] = {}

    class FileOrRealTimeScheduling(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            file = super()._split_scope(nodeid)
            if file not in real_time:
                real_time[file] = declares_real_time(config.rootpath / file)
            return REAL_TIME_MARK if real_time[file] else file

    return FileOrRealTimeScheduling(config, log)


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
    """The real-time tests first (``run_real_time_first``), the sweeps' further seeds left out
    (``leave_out_sweeps``). Under mutation testing (``bench/mutation_check.py``: mutmut names the mutant in
    ``MUTANT_UNDER_TEST`` and runs in ``mutants/`` beside its ``mutmut-stats.json``), the tests a mutant reaches run
    fastest first: pytest stops at the first failure (-x), so a mutant is killed by its cheapest killer instead of after
    the slowest tests; and the slow tests the bench script leaves out of the mutation run (``MUTATION_LEAVE_OUT``,
    node-id prefixes separated by ``;``) are deselected, a hypothesis property that fails is not shrunk, and a test that
    takes 30 times its clean duration + 10 s fails (mutmut's own timeout, 15 times the clean duration of all the
    mutant's tests, stays the backstop). What the tests assert is unchanged; outside mutation testing nothing else is
    touched."""
    run_real_time_first(items)
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
