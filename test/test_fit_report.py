"""``fbg-accel-calib report``: what it shows is the calibration file applied to the inputs it is given, as the
driver applies it (correction terms included), next to what the file says of its own fit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fbg_accel_calibration.commands.cli import main as cli_main
from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_calibration.fit.static_detector import calibration_samples
from fbg_accel_calibration.io.mcap_reader import read_recording
from fbg_accel_calibration.io.mcap_writer import write_recording
from fbg_accel_calibration.reports.fit_report import pose_statistics
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


G = 9.80665


def _multipos(temp: float):
    from fbg_accel_calibration.io.recording import Recording

    rng = np.random.default_rng(0)
    grefs = np.array([[0, 0, G], [0, 0, -G], [G, 0, 0], [-G, 0, 0], [0, G, 0], [0, -G, 0]])
    acc, gr, pid = [], [], []
    for p, gv in enumerate(grefs):
        acc += [gv + rng.standard_normal(3) * 0.5 for _ in range(50)]
        gr += [[np.nan] * 3] * 50
        pid += [-1] * 50
        acc += [gv + rng.standard_normal(3) * 0.01 for _ in range(300)]
        gr += [gv] * 300
        pid += [p] * 300
    acc = np.array(acc)
    n = len(acc)
    # Psi = a / 80 + 1.5 (counts 1000 Psi: 1377 .. 1623, inside the ADC's range), calibrated by M = 80 I, b = -120
    return Recording(np.arange(n) / 100.0, np.full(n, 1000.0), (acc / 80.0 + 1.5) * 1000.0, temp, np.array(gr),
                     np.array(pid))


def _files(tmp_path: Path, rec_sensor: str, temp: float) -> tuple[Path, Path]:
    from fbg_accel_driver.thermal_model import ThermalCalibration

    write_recording(tmp_path / "r.mcap", _multipos(temp), {"sensor_id": rec_sensor}, sensor_id=rec_sensor)
    ThermalCalibration(M=80.0 * np.eye(3)[None], b=np.full((1, 3), -120.0), temperature_range_c=(20.0, 25.0),
                       sensor_id="acc-A").save(tmp_path / "c.yaml")
    return tmp_path / "r.mcap", tmp_path / "c.yaml"


def _argv(cmd: str, rec: Path, cal: Path, tmp_path: Path) -> list[str]:
    out = ["-o", str(tmp_path / "out"), "--max-degree", "0"] if cmd == "report" else ["-o", str(tmp_path / "a.png")]
    return [cmd, str(rec), "--calibration", str(cal), *out]


@pytest.mark.parametrize("cmd", ["report", "allan"])
def test_calibration_of_another_sensor_is_warned(tmp_path: Path, capsys, cmd: str) -> None:
    """The YAML names acc-A, the recording acc-B: both ids on stderr (and the recording's id in report.md)."""
    rec, cal = _files(tmp_path, "acc-B", 23.0)
    assert cli_main(_argv(cmd, rec, cal, tmp_path)) == 0
    err = capsys.readouterr().err
    assert "acc-B" in err and "acc-A" in err and "another sensor" in err, err
    if cmd == "report":
        md = (tmp_path / "out" / "report.md").read_text()
        assert "`acc-B`" in md and "another sensor" in md


def test_matching_sensor_is_not_warned(tmp_path: Path, capsys) -> None:
    rec, cal = _files(tmp_path, "acc-A", 23.0)
    assert cli_main(_argv("report", rec, cal, tmp_path)) == 0
    assert "sensor" not in capsys.readouterr().err


@pytest.mark.parametrize("cmd", ["report", "allan"])
def test_temperature_outside_the_calibrated_range_is_warned(tmp_path: Path, capsys, cmd: str) -> None:
    """Recorded at 45 degC, calibrated over 20..25 degC: count, fraction and range on stderr (and in report.md)."""
    rec, cal = _files(tmp_path, "acc-A", 45.0)
    assert cli_main(_argv(cmd, rec, cal, tmp_path)) == 0
    err = capsys.readouterr().err
    assert "outside the calibrated temperature range 20.00 .. 25.00" in err and "100.0 %" in err, err
    if cmd == "report":
        assert "outside the calibrated temperature range" in (tmp_path / "out" / "report.md").read_text()


def test_temperature_within_the_driver_margin_of_the_calibrated_range_is_not_warned(tmp_path: Path, capsys) -> None:
    """Recorded at 25.2 degC, calibrated over 20..25 degC: within the driver's ``temperature_range_margin_c`` default
    (the AHT10's stated uncertainty), which the driver takes as inside the range, so not warned either (it was)."""
    rec, cal = _files(tmp_path, "acc-A", 25.2)
    assert cli_main(_argv("report", rec, cal, tmp_path)) == 0
    assert "outside the calibrated temperature range" not in capsys.readouterr().err


def test_report_quotes_its_own_command_and_survives_a_yaml_without_fit(tmp_path: Path) -> None:
    """'Produced by' quotes the argv given to cli.main (not the host process's sys.argv, here pytest's); a YAML
    without a fit section shows 'not recorded', not None/nan."""
    rec, cal = _files(tmp_path, "acc-A", 23.0)
    argv = _argv("report", rec, cal, tmp_path)
    assert cli_main(argv) == 0
    md = (tmp_path / "out" / "report.md").read_text()
    assert f"fbg-accel-calib report {rec} --calibration {cal}" in md, md[:300]
    assert "None" not in md and "nan" not in md, md[:1500]
