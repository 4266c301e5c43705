"""Field check from gravity: normal gravity (WGS-84) and bias/scale from still periods at unknown orientations."""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_calibration.fit.field_check import (
    PARAMETERS,
    StillPeriods,
    estimate,
    normal_gravity,
    updated_calibration,
)
from fbg_accel_driver.slow_error import UNSTATED_RUN_TO_RUN_SIGMA_MPS2, SlowErrorSection
from fbg_accel_driver.thermal_model import ThermalCalibration

G = 9.80665


def test_normal_gravity_matches_wgs84_at_equator_pole_and_height() -> None:
    assert normal_gravity(0.0) == pytest.approx(9.7803253359, abs=1e-10)
    assert normal_gravity(90.0) == pytest.approx(9.8321849379, abs=1e-9)  # NIMA TR8350.2 table 3.4, at the poles
    assert normal_gravity(45.0) == pytest.approx(9.806199, abs=2e-6)
    # free-air gradient about -3.086e-6 s^-2 at mid latitudes
    assert (normal_gravity(45.0, 1000.0) - normal_gravity(45.0)) / 1000.0 == pytest.approx(-3.086e-6, rel=2e-3)
    with pytest.raises(ValueError):
        normal_gravity(91.0)


def periods(orientations: np.ndarray, bias: np.ndarray, seed: int, sigma: float = 0.01) -> StillPeriods:
    """Still-period means of a sensor whose output is off by ``bias`` (m/s^2) at unit ``orientations`` of gravity,
    with the noise of each mean (sigma m/s^2 per axis)."""
    rng = np.random.default_rng(seed)
    u = orientations / np.linalg.norm(orientations, axis=1)[:, None]
    mean = G * u + bias + rng.normal(0.0, sigma, u.shape)
    k = len(u)
    return StillPeriods(mean, np.full((k, 3), sigma**2), np.full(k, 24.0), np.full(k, 2000), np.zeros((k, 2)))


SIX_PLUS = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [1, 1, 1], [-1, 1, -1.0]])


def test_an_injected_bias_drift_is_estimated_within_its_uncertainty_over_seeds() -> None:
    z = []
    for seed in range(20):
        fc = estimate(periods(SIX_PLUS, np.array([0.2, 0.0, 0.0]), seed), G)
        assert fc.identified.all() and not fc.not_identified()
        z.append((np.r_[fc.bias, fc.scale] - np.r_[0.2, 0, 0, 0, 0, 0]) / fc.sigma)
        assert fc.bias[0] > 0.15 and abs(fc.residual_mps2).max() < abs(fc.residual_before_mps2).max()
    z = np.array(z)
    assert 0.4 < float(np.sqrt(np.mean(z**2))) < 1.6  # normalised errors of unit size
    assert float((np.abs(z) < 3.0).mean()) > 0.95


def test_no_drift_gives_nothing_significant_and_z_up_identifies_only_z() -> None:
    fc = estimate(periods(SIX_PLUS, np.zeros(3), 3), G)
    assert np.all(np.abs(np.r_[fc.bias, fc.scale]) < 4 * fc.sigma)
    tilted = np.array([[0.005, 0.0, 1.0], [0.0, 0.005, 1.0], [-0.005, 0.0, 1.0], [0.0, -0.005, 1.0]])  # 0.3 deg
    fc = estimate(periods(tilted, np.array([0.0, 0.0, 0.2]), 4), G)
    assert "bias_x" in fc.not_identified() and "scale_y" in fc.not_identified()
    assert any("do not identify" in n for n in fc.notes)
    assert np.all(fc.bias[:2] == 0.0) and np.all(fc.scale[:2] == 0.0)


def test_the_updated_calibration_removes_the_estimated_drift() -> None:
    cal = ThermalCalibration(M=np.array([np.diag([80.0, 78.0, 107.0])]), b=np.array([[-100.0, -150.0, -137.0]]),
                             temperature_range_c=(15.0, 35.0))
    fc = estimate(periods(SIX_PLUS, np.array([0.2, -0.1, 0.05]), 5, sigma=1e-4), G)
    new = updated_calibration(cal, fc)
    psi = np.linalg.solve(cal.M[0], (G * np.array([0.6, 0.0, 0.8]) + np.array([0.2, -0.1, 0.05]) - cal.b[0]))
    out = new.base_acceleration(psi[None], 24.0)[0]
    assert np.linalg.norm(out) == pytest.approx(G, abs=2e-3)
    assert new.fit["field_check"]["not_identified"] == [] and len(PARAMETERS) == 6


def test_no_still_period_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="no still period"):
        estimate(StillPeriods(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, int), np.zeros((0, 2))), G)


def test_field_check_command_on_a_simulated_recording(tmp_path, capsys) -> None:
    """A calibration whose output has drifted by +0.2 m/s^2 on x, checked on a simulated recording of eight still
    orientations (no table reference used): the drift is found, the updated calibration is written only when asked,
    never over an input."""
    import dataclasses
    import re

    from fbg_accel_calibration.commands.cli import main as cli_main
    from fbg_accel_calibration.io.mcap_writer import write_recording
    from fbg_accel_sim.board_physics import SimConfig, simulate_recording
    from fbg_accel_sim.sim_config import config_dir

    poses = [[0.0, 0.0], [0.0, 180.0], [0.0, 90.0], [90.0, 90.0], [180.0, 90.0], [270.0, 90.0], [45.0, 45.0],
             [200.0, 120.0]]
    cfg = SimConfig.default().with_overrides({"scenario.poses.mode": "list", "scenario.poses.list": poses,
                                              "scenario.poses.dwell_s": 12.0, "scenario.poses.move_s": 4.0,
                                              "scenario.poses.repeat": 1, "scenario.temperature.initial_c": 24.0})
    write_recording(tmp_path / "run.mcap", simulate_recording(cfg, seed=11))
    cal = ThermalCalibration.load(config_dir() / "calibration_sim.yaml")
    drifted = cal.b.copy()
    drifted[0, 0] += 0.2
    dataclasses.replace(cal, b=drifted).save(tmp_path / "cal.yaml")
    args = ["field-check", str(tmp_path / "run.mcap"), "--calibration", str(tmp_path / "cal.yaml")]
    assert cli_main(args) == 0
    out = capsys.readouterr().out
    assert "8 still period(s)" in out and not (tmp_path / "new.yaml").exists()
    found = re.search(r"bias_x\s+([+-][0-9.]+) \+- ([0-9.]+)", out)
    bias_x, sigma_x = float(found.group(1)), float(found.group(2))
    # 0.2 injected, plus the shipped calibration's own error at 24 degC (0.03-0.08 rms), which the residuals' scatter
    # puts into the uncertainty (measured: +0.28 +- 0.06)
    assert abs(bias_x - 0.2) < 3 * sigma_x and sigma_x < 0.1
    warning = next(line for line in out.splitlines() if line.startswith(("WARNING", "no drift")))
    assert warning.startswith("WARNING: the calibration has moved: ") and "bias_x" in warning  # +0.28: 4.7 sigma
    assert cli_main([*args, "-o", str(tmp_path / "new.yaml")]) == 0
    new = ThermalCalibration.load(tmp_path / "new.yaml")
    psi = np.array([[1.27, 1.88, 1.45], [1.18, 1.93, 1.27]])  # about z up and z down (ref 870 counts)
    moved = dataclasses.replace(cal, b=drifted).base_acceleration(psi, 24.0) - cal.base_acceleration(psi, 24.0)
    back = new.base_acceleration(psi, 24.0) - cal.base_acceleration(psi, 24.0)
    assert np.all(np.abs(back[:, 0]) < 0.5 * np.abs(moved[:, 0]))  # most of the drift on x taken out
    assert new.fit["field_check"]["not_identified"] == []
    assert cli_main([*args, "-o", str(tmp_path / "cal.yaml"), "--force"]) == 2  # never over an input
    assert "input" in capsys.readouterr().err
    # the calibration's slow error as the driver publishes it: a section without its run-to-run part (one run per
    # level) carries the allowance for that part, one with R (here 0) none
    sigma = {}
    for label, run in (("without R", None), ("with R", np.zeros((3, 3)))):
        slow = SlowErrorSection(np.diag([0.02, 0.01, 0.015]) ** 2, "test", 18, run)
        dataclasses.replace(cal, b=drifted, slow_error=slow).save(tmp_path / f"{label}.yaml")
        assert cli_main(["field-check", str(tmp_path / "run.mcap"), "--calibration", str(tmp_path / f"{label}.yaml")]) == 0
        found = re.search(r"bias_x\s+[+-][0-9.]+ \+- ([0-9.]+)", capsys.readouterr().out)
        sigma[label] = float(found.group(1))
    added = sigma["without R"] ** 2 - sigma["with R"] ** 2
    assert 0.5 * UNSTATED_RUN_TO_RUN_SIGMA_MPS2**2 < added < 1.5 * UNSTATED_RUN_TO_RUN_SIGMA_MPS2**2


@pytest.mark.parametrize(("option", "value"), [("--min-period", "nan"), ("--min-period", "0"), ("--gravity", "9.95")])
def test_a_bad_period_or_gravity_is_refused_in_one_line(option: str, value: str, tmp_path, capsys) -> None:
    """``--min-period nan`` used to select no period without a word; ``--gravity`` is bounded by the input-validation
    layer's local-gravity range (the one bound of the tools and the driver's check), before any file is read."""
    from fbg_accel_calibration.commands.cli import main as cli_main

    with pytest.raises(SystemExit) as exc:
        cli_main(["field-check", str(tmp_path / "absent.mcap"), "--calibration", str(tmp_path / "absent.yaml"),
                  option, value])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and option in err and value in err and "Traceback" not in err


def test_the_calibration_s_slow_error_widens_the_bias_and_decides_the_warning() -> None:
    """The slow error (the calibration's ``slow_error`` section) is a bias the sensor wanders by without drifting: it
    is added to the identified biases' covariance, and a drift is named only beyond DRIFT_SIGMAS of the total."""
    from fbg_accel_calibration.fit.field_check import DRIFT_SIGMAS, drifted

    p = periods(SIX_PLUS, np.array([0.2, 0.0, 0.0]), 7)
    plain = estimate(p, G)
    slow = np.diag([0.08, 0.03, 0.04]) ** 2
    wide = estimate(p, G, slow_error=slow)
    np.testing.assert_allclose(wide.cov[:3, :3], plain.cov[:3, :3] + slow, rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(wide.cov[3:, 3:], plain.cov[3:, 3:])
    np.testing.assert_array_equal(np.r_[wide.bias, wide.scale], np.r_[plain.bias, plain.scale])
    # 0.2 on x: about 20 sigma of the noise, 2.5 sigma of a slow error of 0.08: named only without it
    assert drifted(plain) == ["bias_x"] and drifted(wide) == [] and 0.2 / 0.08 < DRIFT_SIGMAS
    z_up = np.array([[0.0, 0.0, 1.0]] * 3 + [[0.01, 0.0, 1.0]])
    assert "bias_x" not in drifted(estimate(periods(z_up, np.array([0.5, 0.0, 0.0]), 8), G, slow_error=slow))
