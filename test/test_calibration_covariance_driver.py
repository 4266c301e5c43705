"""The driver carries the calibration's own uncertainty (J Sigma J^T of the file's coefficient_covariance) to the
published covariance when asked, once per published sample (a bias does not average), and to the diagnostics."""

from __future__ import annotations

import numpy as np
from test_driver_core import feed_frames, frame, make_cal, values

from fbg_accel_driver.coefficient_covariance import CoefficientCovariance
from fbg_accel_driver.driver_core import CoreConfig, DriverCore
from fbg_accel_driver.driver_diagnostics import OK, DriverDiagnostics, calibration_uncertainty_values
from fbg_accel_driver.thermal_model import ThermalCalibration


def covariance(seed: int = 0) -> CoefficientCovariance:
    """A dense, positive definite covariance of the 24 degree-1 coefficients (correlated axes)."""
    rng = np.random.default_rng(seed)
    L = rng.normal(0.0, 1.0, (24, 24)) * np.r_[[0.5] * 18, [0.01] * 6][:, None]
    return CoefficientCovariance(L @ L.T * 1e-3, "test", 30)


def j_sigma_jt(cal: ThermalCalibration, psi: np.ndarray, temp_c: float) -> np.ndarray:
    """J Sigma J^T written out from the model's regressor row: a_i = x . A[:, i]."""
    tau = (temp_c - cal.t_center_c) / cal.t_scale_c
    x = np.r_[psi, tau * psi, 1.0, tau]
    S = cal.coefficient_covariance.matrix.reshape(8, 3, 8, 3)
    return np.einsum("k,kilj,l->ij", x, S, x)


def test_off_by_default_and_added_in_full_when_asked() -> None:
    cal = make_cal(coefficient_covariance=covariance())
    frames = [frame(i, xyz=(1100 + i, 1600 - i, 1100), temp_cc=2340) for i in range(20)]
    _, plain, _ = feed_frames(DriverCore(cal), frames)
    _, withc, _ = feed_frames(DriverCore(cal, CoreConfig(covariance_includes_calibration=True)), frames)
    noise = np.diag(cal.noise_sigma_mps2**2)
    for r in plain:
        np.testing.assert_array_equal(np.array(r.covariance).reshape(3, 3), noise)
    for r, f in zip(withc, frames, strict=True):
        expected = noise + j_sigma_jt(cal, np.array([f.x, f.y, f.z]) / f.ref, 23.4)
        np.testing.assert_allclose(np.array(r.covariance).reshape(3, 3), expected, rtol=1e-9)
    assert [r.accel_mps2 for r in withc] == [r.accel_mps2 for r in plain]


def test_a_decimated_sample_gets_the_bias_once_not_divided_by_the_block() -> None:
    cal = make_cal(coefficient_covariance=covariance(1))
    frames = [frame(i, xyz=(1100 + 3 * i, 1600, 1100 - 2 * i)) for i in range(40)]
    core = DriverCore(cal, CoreConfig(decimation=10, covariance_includes_calibration=True))
    _, imu, _ = feed_frames(core, frames)
    _, noise_only, _ = feed_frames(DriverCore(cal, CoreConfig(decimation=10)), frames)
    assert len(imu) == 4
    for k, (r, q) in enumerate(zip(imu, noise_only, strict=True)):
        block = frames[10 * k:10 * k + 10]
        psi = np.mean([np.array([f.x, f.y, f.z]) / f.ref for f in block], axis=0)
        added = np.array(r.covariance).reshape(3, 3) - np.array(q.covariance).reshape(3, 3)
        np.testing.assert_allclose(added, j_sigma_jt(cal, psi, 23.4), rtol=1e-9)
        # the noise part is divided by the block (white noise: 1/10), the calibration's part is not
        assert added[0, 0] > 5 * q.covariance[0]


def test_outside_the_range_the_model_s_own_powers_inflate_it() -> None:
    cal = make_cal(coefficient_covariance=covariance(2))
    inside = feed_frames(DriverCore(cal, CoreConfig(covariance_includes_calibration=True)), [frame(0, temp_cc=2500)])[1]
    hot = feed_frames(DriverCore(cal, CoreConfig(covariance_includes_calibration=True)), [frame(0, temp_cc=7000)])[1]
    hot_plain = feed_frames(DriverCore(cal), [frame(0, temp_cc=7000)])[1]
    f = frame(0)
    psi = np.array([f.x, f.y, f.z]) / f.ref
    added = np.array(hot[0].covariance).reshape(3, 3) - np.array(hot_plain[0].covariance).reshape(3, 3)
    np.testing.assert_allclose(added, j_sigma_jt(cal, psi, 70.0), rtol=1e-9)
    assert np.all(np.diag(added) > 2 * np.diag(j_sigma_jt(cal, psi, 25.0)))
    assert inside[0].covariance[0] < hot[0].covariance[0]


def test_unknown_covariance_stays_unknown() -> None:
    cal = make_cal(coefficient_covariance=covariance())
    core = DriverCore(cal, CoreConfig(covariance_source="unknown", covariance_includes_calibration=True))
    _, imu, _ = feed_frames(core, [frame(i) for i in range(5)])
    assert all(r.covariance == (0.0,) * 9 for r in imu)


def test_the_diagnostics_state_it_at_the_last_sample() -> None:
    cal = make_cal(coefficient_covariance=covariance())
    core = DriverCore(cal)
    assert core.calibration_uncertainty() is None
    frames = [frame(i, temp_cc=2000 + i) for i in range(6)]
    feed_frames(core, frames)
    sx, sy, sz, temp = core.calibration_uncertainty()
    f = frames[-1]
    expected = np.sqrt(np.diag(j_sigma_jt(cal, np.array([f.x, f.y, f.z]) / f.ref, 20.05)))
    np.testing.assert_allclose([sx, sy, sz], expected, rtol=1e-9)
    assert temp == 20.05
    diag = DriverDiagnostics()
    from test_driver_core import snapshot

    snap = snapshot(1.0)
    snap.calibration_uncertainty = calibration_uncertainty_values(core.calibration_uncertainty(), True, False)
    entries = diag.report(snap)
    entry = next(e for e in entries if e.name.endswith("calibration uncertainty"))
    assert entry.level == OK and "not included" in entry.message
    assert float(values(entries, "calibration uncertainty")["sigma_x_mps2"]) == round(sx, 6)
    snap2 = snapshot(2.0)
    snap2.calibration_uncertainty = calibration_uncertainty_values(None, False, False)
    assert "no coefficient_covariance" in next(e for e in diag.report(snap2)
                                               if e.name.endswith("calibration uncertainty")).message
