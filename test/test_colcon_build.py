"""The package builds with colcon into a temporary directory and its installed `driver` runs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

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
    where = subprocess.run([sys.executable, "-c", "import fbg_accel_driver; print(fbg_accel_driver.__file__)"],
                           env=run_env, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert where.stdout.strip().startswith(str(site)), where.stdout + where.stderr
