"""The driver as a real process on a version-2 board running a dynamic plan, with a calibration that has a
``dynamic`` section (issue 9): ``imu/raw`` carries the reference's ``aux_counts``, ``imu/data_raw`` is
equalised and stamped back by the delay the ``chain compensation`` diagnostic states.

No sleeps: every wait is a condition polled with a deadline while spinning the executor.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rclpy.context import Context
from test_driver_process import REPO, Listener, stamp_ns, start_driver, start_sim, stop, stop_all

from fbg_accel_driver.chain_compensation import ChainDynamics
from fbg_accel_driver.driver_core import RAW_AUX_NAME
from fbg_accel_driver.driver_parameters import default_calibration_path
from fbg_accel_driver.thermal_model import ThermalCalibration

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)


def test_version2_board_aux_on_imu_raw_and_equalised_stamps(ros: Context, tmp_path: Path) -> None:
    cal = ThermalCalibration.load(default_calibration_path())
    cal.dynamic = ChainDynamics(cutoff_hz=(1.0, 1.7, 1.3, 1.3), delay_s=(0.02, 0.02, 0.02))
    cal_file = tmp_path / "cal_dynamic.yaml"
    cal.save(cal_file)
    link = tmp_path / "board"
    listener = Listener("test_driver_dynamic", ros)
    sim, _ = start_sim(["--link", str(link), "--dynamic-plan", str(REPO / "config" / "excitation_plan_stepped_sine.yaml"),
                        "--rate", "100", "--duration", "60", "--seed", "3"])
    driver = start_driver({"port": str(link), "calibration_file": str(cal_file), "chain_compensation": "equalise",
                           "equalise_bandwidth_hz": 10.0}, tmp_path / "driver.log")
    try:
        listener.wait_until(lambda: len(listener.raw) >= 300 and len(listener.imu) >= 300
                            and any("chain compensation" in d for d in listener.diag), 60,
                            lambda: f"300 samples and the chain diagnostic ({len(listener.raw)} raw, {len(listener.imu)} imu)")
        raw = listener.raw[-1]
        assert list(raw.name)[-1] == RAW_AUX_NAME and len(raw.position) == len(raw.name)
        level, message, values = listener.last("chain compensation")
        assert level == 0 and message.startswith("equalise"), message
        expected_ms = cal.dynamic.stamp_delay_s("equalise", 10.0, 0.01) * 1e3
        assert float(values["applied_delay_ms"]) == pytest.approx(expected_ms, abs=0.01)
        assert float(values["bandwidth_hz"]) == 10.0
        # every acceleration stamp is a board sample's stamp moved back by the stated delay (to the 1 us the
        # diagnostic rounds it to)
        raw_stamps = np.array(sorted(stamp_ns(m) for m in listener.raw))
        delay_ns = round(expected_ms * 1e6)
        shifted = np.array([stamp_ns(m) + delay_ns for m in listener.imu])
        shifted = shifted[(shifted >= raw_stamps[0]) & (shifted <= raw_stamps[-1])]
        i = np.clip(np.searchsorted(raw_stamps, shifted), 1, len(raw_stamps) - 1)
        nearest = np.minimum(np.abs(raw_stamps[i] - shifted), np.abs(raw_stamps[i - 1] - shifted))
        assert len(shifted) >= 250 and np.all(nearest <= 2000), (len(shifted), int(nearest.max()))
        assert stop(driver) == 0, (tmp_path / "driver.log").read_text()
    finally:
        stop_all(sim, driver, listener)
