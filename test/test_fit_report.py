"""``fbg-accel-calib report``: what it shows is the calibration file applied to the inputs it is given, as the
driver applies it (correction terms included), next to what the file says of its own fit."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fbg_accel_calibration.cli import main as cli_main
from fbg_accel_calibration.fit_report import pose_statistics
from fbg_accel_calibration.mcap_io import read_recording, write_recording
from fbg_accel_calibration.static_detector import calibration_samples
from fbg_accel_calibration.thermal_fit import fit_thermal
from fbg_accel_driver.correction_terms import TimeDrift
from fbg_accel_sim.board_physics import SimConfig, simulate_recording

SIX = {"scenario.poses.mode": "six_position", "scenario.poses.dwell_s": 4.0, "scenario.poses.move_s": 1.0}


def test_the_report_shows_the_file_applied_to_the_given_inputs_corrections_included(tmp_path: Path) -> None:
    """A calibration checked on a second run was reported with the RMSE of its own fit (from the YAML) beside a
    floor of the new run, and its residuals were eq. 28 without the file's correction terms: a file whose drift
    term is wrong by 0.5 m/s^2 read as good as the fit. The report's RMSE is now that of the file's output on
    these inputs, streamed per run as the driver runs it, and the fit's own RMSE is labelled as such."""
    fitted = simulate_recording(SimConfig.default().with_overrides(SIX), seed=1)
    cal = fit_thermal(fitted, 0)
    cal.corrections = [TimeDrift(np.zeros(3), np.array([0.5, -0.5, 0.5]), 1e6, 0.0)]  # ~constant 0.5 m/s^2 bias
    cal.save(tmp_path / "cal.yaml")
    write_recording(tmp_path / "other.mcap", simulate_recording(SimConfig.default().with_overrides(SIX), seed=2))
    other = read_recording(tmp_path / "other.mcap")  # what the command reads
    assert cli_main(["report", str(tmp_path / "other.mcap"), "--calibration", str(tmp_path / "cal.yaml"),
                     "-o", str(tmp_path / "rep")]) == 0
    text = (tmp_path / "rep" / "report.md").read_text()
    usable, _ = calibration_samples(other)
    stats = pose_statistics(cal, other, usable & np.isfinite(other.temp_c))
    truth = cal.apply_counts(other.ref, other.xyz, other.temp_c, other.t_s, cal.new_state()) - other.gref_mps2
    keep = usable & np.isfinite(other.temp_c)
    rmse = np.sqrt(np.mean(truth[keep] ** 2, axis=0))
    np.testing.assert_allclose(stats.rmse(), rmse, rtol=1e-9)
    assert np.all(rmse > 0.45)  # the drift term's 0.5 m/s^2 is in it
    for j in range(3):
        assert f"{rmse[j]:.4f}" in text
    assert "at fit time" in text and f"{cal.fit['rmse_mps2'][0]:.4f}" in text
