"""The slow error of a pose mean beyond noise and coefficients: estimated by visit from the campaign, written to the
calibration file's ``slow_error`` section, added by the driver as a bias and used by the gravity check's threshold."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_driver_core import feed_frames, frame, make_cal, snapshot
from test_gravity_check import DT, feed, still_samples

from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_calibration.fit.fit_stream import prepare
from fbg_accel_calibration.fit.slow_error import attach, visit_component
from fbg_accel_calibration.fit.thermal_fit import model_to_coefficients
from fbg_accel_driver.driver_core import CoreConfig, DriverCore
from fbg_accel_driver.driver_diagnostics import DriverDiagnostics, calibration_uncertainty_values
from fbg_accel_driver.gravity_check import GravityCheck, GravityCheckConfig
from fbg_accel_driver.sensor_constants import STANDARD_GRAVITY
from fbg_accel_driver.slow_error import SlowErrorSection
from fbg_accel_driver.thermal_model import CalibrationFileError, ThermalCalibration
from fbg_accel_sim.eq28_campaign import G, campaign

TILT_DEG = 0.3
NOISE = 0.05
TAU_S = 0.15


def estimated_variance(seed: int, tilt_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The slow error's variance per axis (3,) on an eq. 28 campaign whose visits are each off by a random tilt of the
    table (sigma ``tilt_deg``), with the campaign's true noise model (first-order, 0.15 s); and the true variance (3,)
    of that tilt's error over the campaign's samples: a tilt theta about a random axis a moves the mean by theta
    (a x g), per axis variance theta^2 (G^2 - g_i^2) / 3."""
    rec, _ = campaign(seed, tilt_sigma_deg=tilt_deg, noise_mps2=NOISE, tau_s=TAU_S, visit_s=2.0)
    truth = math.radians(tilt_deg) ** 2 * (G**2 - rec.gref_mps2**2).mean(axis=0) / 3.0
    data = prepare(rec, 1, usable=np.ones(len(rec), bool))
    cal = fit_thermal(data, 1)
    est = visit_component(data.stats, model_to_coefficients(cal.M, cal.b), 1, np.full(3, NOISE), np.ones(3),
                          np.full(3, TAU_S), 0.01)
    assert est.visits == 48 and 38.0 < est.dof < 41.0  # 48 visits, 8 coefficients per axis
    return np.diag(est.matrix), truth


def test_the_visit_component_reads_a_known_visit_error_and_nothing_without_one() -> None:
    """A table tilt of 0.3 deg per visit (about 0.024 m/s^2 per axis) is read back beside the noise of a 2 s visit's
    mean (0.019 m/s^2), which the noise model takes out; without tilt nothing is left."""
    est, truth = (np.array(x) for x in zip(*(estimated_variance(s, TILT_DEG) for s in range(12)), strict=True))
    without = np.array([estimated_variance(s, 0.0)[0] for s in range(12)])
    ratio = est.sum() / truth.sum()
    # 12 campaigns x 3 axes x 40 degrees of freedom (a random tilt's error is heavier-tailed than normal): measured
    # 1.03-1.17 over eight such groups of 12 seeds (this one the first)
    assert 0.7 < ratio < 1.4, ratio
    # without a visit error the estimate is noise about 0, clipped at 0: measured 0.06-0.11 of the tilt case's
    assert without.sum() < 0.25 * truth.sum(), without.sum() / truth.sum()


RUN_OFFSET = 0.04  # m/s^2 per axis: a run's own constant bias (twice the noise of a 2 s visit's mean)


def run_component(seed: int, degree: int, runs_per_level: int):
    """The slow error of an eq. 28 campaign (no table tilt) whose runs each keep a constant bias of sigma
    :data:`RUN_OFFSET` per axis."""
    rec, _ = campaign(seed, degree=degree, tilt_sigma_deg=0.0, noise_mps2=NOISE, tau_s=TAU_S, visit_s=1.0,
                      repeats=1, runs_per_level=runs_per_level, run_offset_mps2=RUN_OFFSET)
    data = prepare(rec, degree, usable=np.ones(len(rec), bool))
    cal = fit_thermal(data, degree)
    return visit_component(data.stats, model_to_coefficients(cal.M, cal.b), degree, np.full(3, NOISE), np.ones(3),
                           np.full(3, TAU_S), 0.01)


def test_a_runs_constant_bias_is_read_as_the_run_to_run_component_when_a_level_is_repeated() -> None:
    """Two runs per level: the runs' constants differ within a level, b(T) cannot take them up, and the second variance
    component reads their variance back; the published slow error holds it for a pose mean in a new run. Before, the
    visits alone were the unit: a run's constant was spread over its visits' scatter (and no run component stated)."""
    ests = [run_component(s, 2, 2) for s in range(12)]
    assert all(e.runs == 6 and e.run_matrix is not None for e in ests)
    ratio = np.mean([np.trace(e.run_matrix) for e in ests]) / (3 * RUN_OFFSET**2)
    # 12 campaigns x 3 axes x 3 between-run degrees of freedom (6 runs less 3 levels' offsets): the mean of 108
    # chi^2(1)-like terms is within 0.6-1.5 of its truth with margin (sd about 0.14; measured 0.92-1.04 over four
    # groups of 12 seeds, this one the first)
    assert 0.6 < ratio < 1.5, ratio
    # a pose mean in a new run misses the calibration by the run's constant and the share of the campaign's runs in
    # b(T) (half of it with two runs): the published total holds 1.5 times the run component (measured 1.43-1.62)
    assert np.mean([np.trace(e.matrix) for e in ests]) > 1.2 * 3 * RUN_OFFSET**2


def test_with_one_run_per_level_the_run_to_run_component_is_said_to_be_unidentified(tmp_path) -> None:
    """One run per level at degree 2: b(T) takes up each run's constant exactly, so the residuals hold nothing of it
    and the fit writes so (method text, figures) instead of a number it cannot have."""
    rec, _ = campaign(4, degree=2, tilt_sigma_deg=0.0, noise_mps2=NOISE, tau_s=TAU_S, visit_s=2.0,
                      run_offset_mps2=RUN_OFFSET)
    data = prepare(rec, 2, usable=np.ones(len(rec), bool))
    cal = fit_thermal(data, 2)
    est = attach(cal, data.stats, 0.01)
    assert est.runs == 3 and est.run_matrix is None
    assert "run-to-run component not identified" in cal.slow_error.method
    assert "not identified" in cal.fit["slow_error"]["run_to_run_sigma_mps2"]
    # what is estimated is the visits' scatter beyond the noise: nothing here, whatever the runs' constants
    assert np.trace(est.matrix) < 0.25 * 3 * RUN_OFFSET**2


def test_fit_writes_the_section_and_it_round_trips(tmp_path) -> None:
    rec, _ = campaign(3)
    data = prepare(rec, 1, usable=np.ones(len(rec), bool))
    cal = fit_thermal(data, 1)
    est = attach(cal, data.stats, 0.01)
    assert est is not None and cal.slow_error.visits == 48 and "by visit" in cal.slow_error.method
    assert cal.fit["slow_error"]["sigma_mps2"] == [round(float(v), 5) for v in est.sigma_mps2]
    cal.save(tmp_path / "cal.yaml")
    back = ThermalCalibration.load(tmp_path / "cal.yaml")
    assert back == cal and back.slow_error == cal.slow_error
    old = cal.to_dict()
    del old["slow_error"]
    assert ThermalCalibration.from_dict(old).slow_error is None  # a file without it loads as before


@pytest.mark.parametrize(("key", "value", "message"), [
    ("format_version", 2, "not supported"), ("format_version", True, "not supported"), ("method", "", "method"),
    ("visits", 0, "visits"), ("visits", 2.5, "integer"), ("extra", 1, "unknown key"),
    ("matrix", [[1.0, 0.0], [0.0, 1.0]], "3 x 3"), ("matrix", [[1e-3, 2e-3, 0], [2e-3, 1e-3, 0], [0, 0, 1e-3]],
                                                  "positive semi-definite"),
    ("matrix", [[1e-3, 1e-4, 0], [0, 1e-3, 0], [0, 0, 1e-3]], "not symmetric"),
    ("matrix", [[200.0, 0, 0], [0, 1e-3, 0], [0, 0, 1e-3]], "above 10"),
    ("matrix", [[math.nan, 0, 0], [0, 1e-3, 0], [0, 0, 1e-3]], "finite"),
])
def test_the_section_is_a_strict_contract(key, value, message) -> None:
    d = make_cal(slow_error=SlowErrorSection(np.diag([1e-3, 2e-3, 3e-3]), "test", 30)).to_dict()
    d["slow_error"][key] = value
    with pytest.raises(CalibrationFileError, match=message):
        ThermalCalibration.from_dict(d)


SLOW = np.array([[4e-3, 1e-3, 0.0], [1e-3, 2e-3, 0.0], [0.0, 0.0, 9e-3]])


def test_the_driver_adds_it_as_a_bias_once_per_message() -> None:
    """With covariance_includes_calibration the slow error is added in full (off-diagonal too), once per published
    message: a decimated message gets it undivided, the noise part 1/N of it; off by default. (A section with its
    run-to-run part: one without it gets an allowance too, next test.)"""
    cal = make_cal(slow_error=SlowErrorSection(SLOW, "test", 40, run_to_run=SLOW / 2))
    frames = [frame(i, xyz=(1100 + 3 * i, 1600, 1100 - 2 * i)) for i in range(40)]
    noise = np.diag(cal.noise_sigma_mps2**2)
    for n in (1, 10):
        plain = feed_frames(DriverCore(cal, CoreConfig(decimation=n)), frames)[1]
        withs = feed_frames(DriverCore(cal, CoreConfig(decimation=n, covariance_includes_calibration=True)), frames)[1]
        assert len(withs) == 40 // n
        for p, w in zip(plain, withs, strict=True):
            np.testing.assert_allclose(np.array(p.covariance).reshape(3, 3), noise / n, rtol=1e-9)
            np.testing.assert_allclose(np.array(w.covariance).reshape(3, 3) - np.array(p.covariance).reshape(3, 3),
                                       SLOW, rtol=1e-9, atol=1e-15)
    snap_values = calibration_uncertainty_values(None, False, True, cal.slow_error.sigma_mps2)
    assert snap_values["slow_sigma_z_mps2"] == round(math.sqrt(9e-3), 6) and snap_values["included_in_covariance"]
    snap = snapshot(1.0)
    snap.calibration_uncertainty = snap_values
    msg = next(e for e in DriverDiagnostics().report(snap) if e.name.endswith("calibration uncertainty")).message
    assert "slow error of a still mean" in msg and "0.0949" in msg


def published_calibration_part(cal) -> np.ndarray:
    """The calibration's part (3, 3) (m/s^2)^2 of the covariance the driver publishes for ``cal`` with
    covariance_includes_calibration: the message's covariance less the one without the parameter."""
    frames = [frame(i, xyz=(1100 + 3 * i, 1600, 1100 - 2 * i)) for i in range(10)]
    plain = feed_frames(DriverCore(cal, CoreConfig()), frames)[1][-1]
    withs = feed_frames(DriverCore(cal, CoreConfig(covariance_includes_calibration=True)), frames)[1][-1]
    return np.array(withs.covariance).reshape(3, 3) - np.array(plain.covariance).reshape(3, 3)


def test_a_slow_error_without_its_run_to_run_part_is_published_with_an_allowance_for_it(monkeypatch) -> None:
    """A one-run-per-level file's slow error lacks the run-to-run part (b(T) took it up): the published covariance adds
    UNSTATED_RUN_TO_RUN_SIGMA_MPS2 squared on each axis (isotropic), the diagnostic names it; a section with R gets
    nothing more. The driver reads the constant from its one place (``fbg_accel_driver.slow_error``); the gravity
    check keeps its own margin for such a file (a threshold setting, not a standard deviation)."""
    import fbg_accel_driver.slow_error as slow_error_module
    from fbg_accel_driver.gravity_check import UNSTATED_RUN_TO_RUN_MPS2, unstated_allowance

    no_r = make_cal(slow_error=SlowErrorSection(SLOW, "test", 40))
    with_r = make_cal(slow_error=SlowErrorSection(SLOW, "test", 40, run_to_run=SLOW / 2))
    a = slow_error_module.UNSTATED_RUN_TO_RUN_SIGMA_MPS2
    assert 0.03 < a < 0.045  # Table 2's z bias instability as a flicker floor, a 240 s run, a year later: 0.038
    np.testing.assert_allclose(published_calibration_part(no_r), SLOW + a**2 * np.eye(3), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(published_calibration_part(with_r), SLOW, rtol=1e-9, atol=1e-15)
    monkeypatch.setattr(slow_error_module, "UNSTATED_RUN_TO_RUN_SIGMA_MPS2", 0.07)
    np.testing.assert_allclose(published_calibration_part(no_r), SLOW + 0.07**2 * np.eye(3), rtol=1e-9, atol=1e-15)
    monkeypatch.undo()
    assert unstated_allowance(no_r) == UNSTATED_RUN_TO_RUN_MPS2 and unstated_allowance(with_r) == 0.0
    values = calibration_uncertainty_values(None, False, True, no_r.slow_error.sigma_mps2,
                                            no_r.slow_error.unstated_run_to_run_sigma_mps2)
    assert values["unstated_run_to_run_sigma_mps2"] == a and values["slow_sigma_z_mps2"] == round(math.sqrt(9e-3), 6)
    assert "unstated_run_to_run_sigma_mps2" not in calibration_uncertainty_values(
        None, False, True, with_r.slow_error.sigma_mps2, with_r.slow_error.unstated_run_to_run_sigma_mps2)
    snap = snapshot(1.0)
    snap.calibration_uncertainty = values
    msg = next(e for e in DriverDiagnostics().report(snap) if e.name.endswith("calibration uncertainty")).message
    assert f"plus {a:.3g} m/s^2 per axis for the run-to-run part the file does not state" in msg


@pytest.mark.parametrize("lag_s", [86400.0, 365.25 * 86400.0])
def test_the_flicker_run_to_run_formula_is_the_integral_of_its_psd(lag_s) -> None:
    """(B^2 / pi)(ln(lag / run) + 3/2) against the integral of B^2 / (2 pi f) |1 - e^(2 pi i f lag)|^2 sinc^2(pi f run),
    done numerically (the fast sine averaged to 2 where f lag > 200): within 0.5 % in variance."""
    from fbg_accel_driver.slow_error import flicker_run_to_run_sigma_mps2

    run_s, b = 240.0, 0.0183
    f = np.logspace(-14, 3, 200_001)
    h = np.where(f * lag_s > 200, 2.0, 4 * np.sin(np.pi * f * lag_s) ** 2) * np.sinc(f * run_s) ** 2
    integral = np.trapezoid(b**2 / (2 * np.pi * f) * h, f)
    assert flicker_run_to_run_sigma_mps2(b, run_s, lag_s) ** 2 == pytest.approx(integral, rel=5e-3)
    assert flicker_run_to_run_sigma_mps2(b, run_s, lag_s) ** 2 != pytest.approx(b**2 / np.pi * np.log(lag_s / run_s),
                                                                                rel=0.05)  # the 3/2 matters


def still_with_and_without_slow_error():
    """A calibration without a slow_error section, the same with SLOW (its run-to-run part known: half of it), the
    gravity direction (m/s^2, sensor frame) and 500 still samples (m/s^2) with their Psi, uncorrelated noise."""
    cal = make_cal(noise_correlated_fraction=np.zeros(3), noise_time_constant_s=np.zeros(3))
    slow = make_cal(noise_correlated_fraction=np.zeros(3), noise_time_constant_s=np.zeros(3),
                    slow_error=SlowErrorSection(SLOW, "test", 40, run_to_run=SLOW / 2))
    a_true = np.array([1.0, -2.0, 9.5])
    a_true *= STANDARD_GRAVITY / np.linalg.norm(a_true)
    return (cal, slow, a_true, *still_samples(cal, 500, a_true))


def test_the_gravity_check_widens_its_threshold_by_the_slow_error_along_gravity() -> None:
    cal, slow, a_true, acc, psi = still_with_and_without_slow_error()
    drift = np.array([0.0, 0.0, 0.2])  # a drift of 0.2 m/s^2 on z, nearly along gravity
    acc = acc + drift
    cfg = GravityCheckConfig(STANDARD_GRAVITY, tolerance_mps2=0.0, period_s=2.0)  # one test: 2.25 s hold, a 2 s block
    plain = feed(GravityCheck(cal, cfg, DT), acc, psi)
    wide = feed(GravityCheck(slow, cfg, DT), acc, psi)
    u = (a_true + drift) / np.linalg.norm(a_true + drift)
    assert wide[0].sigma_slow_mps2 == pytest.approx(math.sqrt(u @ SLOW @ u), rel=1e-3) and plain[0].sigma_slow_mps2 == 0
    assert wide[0].threshold_mps2 == pytest.approx(
        3.89 * math.sqrt(wide[0].sigma_noise_mps2**2 + wide[0].sigma_slow_mps2**2), rel=1e-3)
    # the drift (0.196 along gravity) is 70 noise sigmas but 2 of this slow error (0.095): flagged only without it
    assert len(plain) == len(wide) == 1 and plain[0].failed and not wide[0].failed


def test_the_default_tolerance_is_gravity_s_and_a_file_gets_an_allowance_for_what_its_slow_error_does_not_state() -> None:
    """The default gravity_tolerance_mps2 is standard gravity's error (0.03) alone when the file states its slow error
    with its run-to-run part; a section without that part (one run per level) gets UNSTATED_RUN_TO_RUN_MPS2 (0.05) for
    it, a file without the section UNSTATED_SLOW_ERROR_MPS2 (0.12), each named in the test's figures: a fixed allowance
    added on top of a fully stated slow error would count it twice (threshold about 0.35 m/s^2 with the simulated
    campaigns' slow error: 8 % of the 0.2 m/s^2 drifts flagged)."""
    from fbg_accel_driver.gravity_check import (
        DEFAULT_TOLERANCE_MPS2,
        UNSTATED_RUN_TO_RUN_MPS2,
        UNSTATED_SLOW_ERROR_MPS2,
    )

    assert DEFAULT_TOLERANCE_MPS2 == CoreConfig().gravity_tolerance_mps2 == 0.03 and UNSTATED_SLOW_ERROR_MPS2 == 0.12
    assert UNSTATED_RUN_TO_RUN_MPS2 == 0.05
    cal, slow, _, acc, psi = still_with_and_without_slow_error()
    no_r = make_cal(noise_correlated_fraction=np.zeros(3), noise_time_constant_s=np.zeros(3),
                    slow_error=SlowErrorSection(SLOW, "test", 40))
    cfg = GravityCheckConfig(STANDARD_GRAVITY, period_s=2.0)
    stated, unstated = feed(GravityCheck(slow, cfg, DT), acc, psi)[0], feed(GravityCheck(cal, cfg, DT), acc, psi)[0]
    k_sigma = 3.89 * math.sqrt(stated.sigma_noise_mps2**2 + stated.sigma_slow_mps2**2)
    assert stated.unstated_slow_error_mps2 == 0.0 and stated.threshold_mps2 == pytest.approx(0.03 + k_sigma, rel=1e-3)
    without_r = feed(GravityCheck(no_r, cfg, DT), acc, psi)[0]
    assert without_r.sigma_slow_mps2 == stated.sigma_slow_mps2 and without_r.unstated_slow_error_mps2 == 0.05
    assert without_r.threshold_mps2 == pytest.approx(stated.threshold_mps2 + 0.05, rel=1e-6)
    assert unstated.unstated_slow_error_mps2 == 0.12
    assert unstated.threshold_mps2 == pytest.approx(0.15 + 3.89 * unstated.sigma_noise_mps2, rel=1e-3)
