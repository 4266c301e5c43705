"""The calibration node runs a dynamic plan (issue 9), as real processes over DDS: ``board_sim`` runs a
short excitation plan on a version-2 board, the driver publishes ``imu/raw`` with ``aux_counts``, and two
calibration nodes record it: one to the end (the MCAP holds the plan, every raw sample with the
reference, the reference on its own topic; ``fbg-accel-calib dynamic`` fits it), one SIGKILLed half
way (its file is read up to its last chunk, at most a second before the kill).

No sleeps: every wait is a condition with a deadline (the listener spins, child lines wake waits).
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from process_harness import ChildProcess
from rclpy.context import Context
from test_driver_process import Listener, start_driver, start_sim, stop_all

from fbg_accel_calibration.io.mcap_reader import read_file
from fbg_accel_driver.driver_parameters import default_calibration_path

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

BIN = Path(sys.executable).parent
RATE_HZ = 200
# the fixture's plan with a still start of 1.5 s: the board starts once both nodes subscribed, so the start need only
# hold find_slide_start's 0.5 s envelope window (the table is at rest until the slide: no step for the LDV's AC coupling)
PLAN = {**yaml.safe_load((Path(__file__).parent / "fixtures" / "excitation_plan_three_tone.yaml").read_text()),
        "start_s": 1.5}
LENGTH_S = 1.5 + 6.0 + 4.0 + 3.0 + 2 * 0.5 + 2.0  # start + segments + gaps + the recorder's tail


def _node(tmp: Path, label: str) -> ChildProcess:
    return ChildProcess(label, [BIN / "calibration", "--ros-args", "-p", f"plan_file:={tmp / 'plan.yaml'}",
                                "-p", f"output_dir:={tmp}", "-p", f"run_label:={label}",
                                "-p", "sensor_id:=sim-fbg-accel-001",  # the simulated sensor: its calibration is applied below
                                "-p", "progress:=false"])


def test_dynamic_plan_recorded_to_the_end_and_killed_half_way(ros: Context, tmp_path: Path) -> None:
    (tmp_path / "plan.yaml").write_text(yaml.safe_dump(PLAN, sort_keys=False))
    listener = Listener("test_calibration_dynamic", ros)
    link = tmp_path / "board"
    driver = start_driver({"port": str(link), "calibration_file": "none"}, tmp_path / "driver.log")
    full, killed = _node(tmp_path, "full"), _node(tmp_path, "killed")
    sim = None
    try:
        # both nodes (and the listener) subscribed before the board starts: their first sample is the board's first
        listener.wait_until(lambda: listener.node.count_subscribers("/imu/raw") >= 3, 60,
                            "both calibration nodes subscribed to /imu/raw")
        sim, _ = start_sim(["--link", str(link), "--dynamic-plan", str(tmp_path / "plan.yaml"), "--rate", str(RATE_HZ),
                            "--duration", str(LENGTH_S + 6.0), "--seed", "4"])
        killed.wait_line(r"dynamic run: 10 of \d+ s recorded", timeout=60)
        killed.proc.send_signal(signal.SIGKILL)
        assert killed.wait_exit(timeout=10) == -signal.SIGKILL
        assert full.wait_exit(timeout=60) == 0, full.output()
        assert "dynamic run complete" in full.output()
    finally:
        for p in (full, killed):
            p.kill()
        stop_all(sim, driver, listener)

    rec, report = read_file(tmp_path / "full.mcap")
    assert report.complete and rec.aux is not None and np.all(np.isfinite(rec.aux))
    assert rec.t_s[-1] - rec.t_s[0] >= LENGTH_S - 1.0 / RATE_HZ
    assert report.messages_per_topic["/calibration/reference_velocity"] == len(rec)
    run = report.metadata["run"]
    assert run["kind"] == "dynamic" and "short_process_test" in run["excitation_plan"]

    part, part_report = read_file(tmp_path / "killed.mcap")
    assert not part_report.complete and part.aux is not None
    assert part.t_s[-1] - part.t_s[0] >= 9.0  # killed after 10 s: everything but the chunk in progress (<= 1 s)

    out = tmp_path / "cal.yaml"
    res = subprocess.run([BIN / "fbg-accel-calib", "dynamic", tmp_path / "full.mcap", "--plan", tmp_path / "plan.yaml",
                          "--calibration", default_calibration_path(), "-o", out],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    section = yaml.safe_load(out.read_text())["dynamic"]
    assert section["fit"]["axis_check"]["misfit"] is False
    assert 1.2 < section["cutoff_hz"]["x"] < 2.2 and 0.9 < section["cutoff_hz"]["y"] < 1.7  # 3 frequencies only
