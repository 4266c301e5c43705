"""The package builds with colcon into a temporary directory and its installed `driver` runs."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

REPO = Path(__file__).resolve().parents[1]
COLCON = Path(sys.executable).parent / "colcon"


def test_colcon_build_and_installed_driver_help(tmp_path: Path) -> None:
    assert COLCON.is_file(), f"colcon not found at {COLCON}; run scripts/bootstrap.sh dev"
    env = {**os.environ, "COLCON_HOME": str(tmp_path / "colcon_home")}
    build = subprocess.run(
        [str(COLCON), "--log-base", str(tmp_path / "log"), "build", "--base-paths", str(REPO),
         "--build-base", str(tmp_path / "build"), "--install-base", str(tmp_path / "install"),
         "--packages-select", "fbg_accel_driver"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240,
    )
    assert build.returncode == 0, build.stdout + build.stderr
    prefix = tmp_path / "install" / "fbg_accel_driver"
    exe = prefix / "lib" / "fbg_accel_driver" / "driver"
    assert exe.is_file() and os.access(exe, os.X_OK), f"{exe} not installed"
    assert (prefix / "lib" / "fbg_accel_driver" / "board_sim").is_file()
    share = prefix / "share" / "fbg_accel_driver"
    assert (share / "package.xml").is_file() and (share / "config" / "driver.yaml").is_file()
    # What `ros2 run fbg_accel_driver driver` does after sourcing install/setup.bash.
    site = next((prefix / "lib").glob("python3*/site-packages"))
    run_env = {**os.environ, "PYTHONPATH": f"{site}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
               "AMENT_PREFIX_PATH": str(prefix)}
    res = subprocess.run([str(exe), "--help"], env=run_env, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("usage: driver")
    for topic in ("imu/data_raw", "imu/temperature", "imu/raw", "/diagnostics"):
        assert topic in res.stdout
    # The installed copy is the one that ran, and it finds the calibration in its own share directory.
    default_cal = res.stdout.strip().splitlines()[-1].split(": ", 1)[1]
    assert Path(default_cal) == share / "config" / "calibration_sim.yaml", default_cal
    assert Path(default_cal).is_file()
    # Bring-up files (issue 10): params and launch files in share/, version from the installed metadata.
    for f in ("driver.yaml", "calibration.yaml"):
        assert (share / "config" / f).is_file(), f"config/{f} not installed"
    launch_files = sorted(p.name for p in (share / "launch").glob("*.launch.py"))
    assert launch_files == ["calibration.launch.py", "driver.launch.py", "sim.launch.py"], launch_files
    # what `ros2 launch fbg_accel_driver driver.launch.py` resolves: the params file in the share directory
    probe = ("import importlib.util, sys; s = importlib.util.spec_from_file_location('l', sys.argv[1]); "
             "m = importlib.util.module_from_spec(s); s.loader.exec_module(m); "
             "a = {n: d for n, (d, _) in m.launch_arguments(sys.argv[2]).items()}; "
             "print(m.node_descriptions(sys.argv[2], a)[0]['parameters'][0])")
    res = subprocess.run([sys.executable, "-c", probe, str(share / "launch" / "driver.launch.py"), str(share)],
                         env=run_env, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert res.returncode == 0 and Path(res.stdout.strip()) == share / "config" / "driver.yaml", res.stdout + res.stderr
    version = subprocess.run([str(exe), "--version"], env=run_env, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    expected = ET.parse(REPO / "package.xml").getroot().findtext("version")
    assert (version.returncode, version.stdout) == (0, f"driver {expected}\n"), version.stdout + version.stderr
    where = subprocess.run([sys.executable, "-c", "import fbg_accel_driver; print(fbg_accel_driver.__file__)"],
                           env=run_env, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert where.stdout.strip().startswith(str(site)), where.stdout + where.stderr
