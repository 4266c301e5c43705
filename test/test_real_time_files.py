"""test/conftest.py's real-time files: a test that starts a process or opens a pty in a file that does not declare
``real_time`` fails naming what it did, and on two workers the declared files run first, on one worker, one after
another. Each case runs pytest as a child process on a few small test files beside a copy of test/conftest.py."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

HEADER = "import os\nimport subprocess\nimport sys\n\nimport pytest\n\n"
DECLARED = "pytestmark = pytest.mark.real_time\n\n\n"
STARTS_A_PROCESS = "def test_runs():\n    subprocess.run([sys.executable, '-c', ''], check=True)\n"
OPENS_A_PTY = "def test_opens():\n    for fd in os.openpty():\n        os.close(fd)\n"
PLAIN = "def test_a():\n    pass\n\n\ndef test_b():\n    pass\n"


def _pytest(where: Path, files: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    (where / "conftest.py").write_text(Path(__file__).with_name("conftest.py").read_text())
    for name, text in files.items():
        (where / name).write_text(HEADER + text)
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-v", *args], cwd=where,
                          capture_output=True, text=True, timeout=240)


def test_a_file_that_starts_a_process_or_opens_a_pty_without_declaring_it_fails_saying_so(tmp_path: Path) -> None:
    run = _pytest(tmp_path, {"test_process.py": STARTS_A_PROCESS, "test_pty.py": OPENS_A_PTY,
                             "test_declared.py": DECLARED + STARTS_A_PROCESS + "\n\n" + OPENS_A_PTY})
    assert run.returncode == 1, run.stdout + run.stderr
    assert "test_process.py starts a child process but does not declare" in run.stdout
    assert "test_pty.py opens a pseudo-terminal but does not declare" in run.stdout
    assert "test_declared.py::test_runs PASSED" in run.stdout and "test_declared.py::test_opens PASSED" in run.stdout


def test_a_library_s_lookups_are_not_processes_a_test_waits_on(tmp_path: Path) -> None:
    """Programs a library runs once to look something up do not make a file real-time: matplotlib's font manager runs
    ``fc-list`` to build its font cache on a machine that has none (a fresh CI machine: its first test that draws),
    ``ctypes.util.find_library`` runs ``ldconfig -p``."""
    cache = tmp_path / "mplconfig"  # empty: matplotlib builds its font cache there, asking fontconfig
    lookups = (f"def test_fonts():\n    os.environ['MPLCONFIGDIR'] = {str(cache)!r}\n"
               "    import matplotlib.font_manager\n    assert matplotlib.font_manager.fontManager.ttflist\n\n\n"
               "def test_library():\n    import ctypes.util\n    ctypes.util.find_library('c')\n")
    run = _pytest(tmp_path, {"test_lookups.py": lookups})
    assert run.returncode == 0, run.stdout + run.stderr
    assert any(cache.glob("fontlist-*.json"))  # the cache was built here


def test_a_mark_on_one_test_is_refused_as_it_would_not_group_its_file(tmp_path: Path) -> None:
    run = _pytest(tmp_path, {"test_one.py": "@pytest.mark.real_time\ndef test_one():\n    pass\n"})
    assert run.returncode == pytest.ExitCode.USAGE_ERROR, run.stdout + run.stderr
    assert "test_one.py::test_one is marked real_time but its file does not declare" in run.stderr + run.stdout


def test_on_two_workers_the_declared_files_run_first_on_one_worker_one_after_another(tmp_path: Path) -> None:
    # by name the real-time files come last: in file order on two workers they would go to different workers
    run = _pytest(tmp_path, {"test_a_plain.py": PLAIN, "test_b_plain.py": PLAIN,
                             "test_y_real.py": DECLARED + STARTS_A_PROCESS, "test_z_real.py": DECLARED + OPENS_A_PTY},
                  "-n", "2", "--dist", "loadfile", "--no-loadscope-reorder")
    assert run.returncode == 0, run.stdout + run.stderr
    ran = re.findall(r"^\[(gw\d)\] \[\s*\d+%\] PASSED (test_\w+)\.py", run.stdout, re.M)
    worker = next(w for w, file in ran if file.endswith("_real"))
    assert [file for w, file in ran if w == worker][:2] == ["test_y_real", "test_z_real"], run.stdout
    assert {w for w, _ in ran} == {"gw0", "gw1"}, run.stdout  # the plain files fill the other worker meanwhile
