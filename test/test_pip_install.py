"""``pip install .`` gives working executables: the driver finds the shipped calibration in the install's
``share/fbg_accel_driver/config`` (``calibration_file:=sim``), ``driver --help`` names that file, and without the
ROS 2 Python packages ``driver`` and ``calibration`` say in one line what to install (exit 2, no traceback).

The install is a real ``pip install --no-deps .`` of a copy of the source tree into a fresh virtual environment
whose interpreter sees the test venv's packages through a ``.pth`` line (so nothing is downloaded; the copy
keeps build files out of the repository). A missing rclpy is an ``rclpy`` module on PYTHONPATH whose import
raises ModuleNotFoundError, as the interpreter does when the package is absent.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from collections.abc import Iterator
from pathlib import Path

import pytest
from process_harness import ChildProcess

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

REPO = Path(__file__).resolve().parents[1]
SOURCE_ITEMS = ("setup.py", "setup.cfg", "package.xml", "resource", "config", "launch",
                "fbg_accel_driver", "fbg_accel_calibration", "fbg_accel_sim")


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The prefix (a fresh venv) into which ``pip install .`` put the package."""
    tmp = tmp_path_factory.mktemp("pip_install")
    src = tmp / "src"
    src.mkdir()
    for item in SOURCE_ITEMS:
        p = REPO / item
        if p.is_dir():
            shutil.copytree(p, src / item, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(p, src / item)
    prefix = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(prefix)], check=True, timeout=120)
    py = prefix / "bin" / "python"
    site = Path(subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    # the test venv's packages (numpy, the ROS 2 wheels, pip, setuptools) after the fresh venv's own
    (site / "test_venv.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    res = subprocess.run([py, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index", str(src)],
                         cwd=tmp, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    yield prefix


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("AMENT_PREFIX_PATH", "PYTHONPATH", "VIRTUAL_ENV")}
    return env | extra


def test_installed_driver_help_names_the_shipped_calibration(installed: Path, tmp_path: Path) -> None:
    res = subprocess.run([installed / "bin" / "driver", "--help"], env=_env(), cwd=tmp_path,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    last = res.stdout.strip().splitlines()[-1]
    assert last.startswith("calibration_file 'sim': "), last
    path = Path(last.split(": ", 1)[1])
    assert path == installed / "share" / "fbg_accel_driver" / "config" / "calibration_sim.yaml", path
    assert path.is_file()


def test_installed_driver_starts_with_the_simulated_calibration(installed: Path, tmp_path: Path) -> None:
    port = tmp_path / "no_board_here"
    proc = ChildProcess("driver", [installed / "bin" / "driver", "--ros-args", "-p", f"port:={port}",
                                   "-p", "calibration_file:=sim"])
    try:
        line = proc.wait_line(r"reading \S+ at \d+ baud", timeout=60)
    finally:
        rc = proc.stop()
    cal = installed / "share" / "fbg_accel_driver" / "config" / "calibration_sim.yaml"
    assert f"calibration {cal}" in line, line
    assert rc == 0, proc.output()


@pytest.mark.parametrize("exe", ["driver", "calibration"])
def test_without_rclpy_one_line_names_what_to_install(installed: Path, tmp_path: Path, exe: str) -> None:
    shim = tmp_path / "no_ros"
    shim.mkdir()
    (shim / "rclpy.py").write_text("raise ModuleNotFoundError(\"No module named 'rclpy'\", name='rclpy')\n")
    res = subprocess.run([installed / "bin" / exe, "--ros-args", "-p", "plan_file:=x.yaml"],
                         env=_env(PYTHONPATH=str(shim)), cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert lines[0].startswith(f"{exe}: error: ") and "'rclpy'" in lines[0], lines[0]
    assert "/opt/ros/jazzy/setup.bash" in lines[0] and "pip install" in lines[0], lines[0]
    # --help and --version still answer without ROS
    res = subprocess.run([installed / "bin" / exe, "--version"], env=_env(PYTHONPATH=str(shim)), cwd=tmp_path,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and res.stdout.startswith(f"{exe} "), res.stdout + res.stderr
