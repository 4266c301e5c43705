"""The covariance of eq. 28's coefficients: cluster-robust by visit (CR2), checked against a bootstrap over visits
and against the truth of a small simulated campaign, written to and read from the calibration file."""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_calibration.fit.coefficient_uncertainty import (
    bootstrap_covariance,
    cluster_covariance,
)
from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_calibration.fit.fit_stream import prepare
from fbg_accel_calibration.fit.thermal_fit import CellStats, model_to_coefficients
from fbg_accel_calibration.io.recording import Recording
from fbg_accel_driver.coefficient_covariance import CoefficientCovariance, output_covariance
from fbg_accel_driver.thermal_model import CalibrationFileError, ThermalCalibration
from fbg_accel_sim.eq28_campaign import campaign


def _fit(rec: Recording, degree: int = 1):
    data = prepare(rec, degree, usable=np.ones(len(rec), bool))
    return fit_thermal(data, degree), data


def naive_covariance(stats: CellStats, A: np.ndarray, degree: int) -> np.ndarray:
    """The textbook covariance sigma^2 (X^T X)^-1 per axis (independent samples; no correlation between axes): what
    the cluster-robust estimate replaces, the baseline these tests compare with (it ignores what a visit shares)."""
    xtx, _, _, n = stats.select(np.ones(len(stats.count), bool), degree)
    rss = stats.cell_rss(A, degree).sum(axis=0)
    p = xtx.shape[0]
    inv = np.linalg.inv(xtx)
    cov = np.zeros((3 * p, 3 * p))
    for i in range(3):
        cov[i::3, i::3] = inv * rss[i] / max(n - p, 1.0)
    return cov


def test_visit_sums_add_up_to_the_cell_sums_and_count_every_visit() -> None:
    rec, _ = campaign(0)
    _, data = _fit(rec)
    st = data.stats
    assert len(st.visit_cell) == st.n_visits == 3 * 2 * 8
    tol = {"rtol": 1e-12, "atol": 1e-12 * np.abs(st.xtg).max()}  # a level's tau sums to 0: rounding only
    np.testing.assert_allclose(st.visit_xtx.sum(axis=0), st.xtx.sum(axis=0), **tol)
    np.testing.assert_allclose(st.visit_xtg.sum(axis=0), st.xtg.sum(axis=0), **tol)
    for c in range(len(st.count)):  # each visit's sums belong to its own cell
        np.testing.assert_allclose(st.visit_xtg[st.visit_cell == c].sum(axis=0), st.xtg[c], **tol)


def test_cr2_from_the_sums_equals_its_definition_on_the_samples() -> None:
    """The p x p push-through form against (I - H_vv)^(-1/2) e_v worked out on the samples of each visit."""
    rec, _ = campaign(1, n_poses=5, repeats=1, visit_s=0.3)
    cal, data = _fit(rec)
    A = model_to_coefficients(cal.M, cal.b)
    cov, _, clusters = cluster_covariance(data.stats, A, 1)
    from fbg_accel_calibration.fit.thermal_fit import design_matrix
    from fbg_accel_driver.thermal_model import normalise

    X = design_matrix(normalise(rec.xyz, rec.ref), (rec.temp_c - 25.0) / 10.0, 1)
    e = rec.gref_mps2 - X @ A
    Binv = np.linalg.inv(X.T @ X)
    visit = np.cumsum(np.r_[True, (np.diff(rec.pose_id) != 0) | (np.diff(rec.run_id) != 0)]) - 1
    direct = np.zeros_like(cov)
    for v in np.unique(visit):
        Xv, ev = X[visit == v], e[visit == v]
        w, q = np.linalg.eigh(np.eye(len(Xv)) - Xv @ Binv @ Xv.T)
        u = (Binv @ Xv.T @ (q / np.sqrt(w)) @ q.T @ ev).ravel()
        direct += np.outer(u, u)
    assert clusters == len(np.unique(visit))
    np.testing.assert_allclose(cov, direct, rtol=1e-5, atol=1e-8 * np.abs(direct).max())


def test_sandwich_agrees_with_the_bootstrap_over_visits() -> None:
    rec, _ = campaign(2, repeats=3)
    cal, data = _fit(rec)
    A = model_to_coefficients(cal.M, cal.b)
    cov, _, _ = cluster_covariance(data.stats, A, 1)
    boot, used = bootstrap_covariance(data.stats, 1, n_boot=300, seed=1)
    assert used >= 290
    ratio = np.sqrt(np.diag(boot) / np.diag(cov))
    # 300 draws: a standard deviation to ~4 % (measured: median ratio 1.00-1.01, all within 0.92..1.13 for three
    # bootstrap seeds); the bootstrap leaves out the leverage correction, ~1 - p/V = 11 % in variance here
    assert 0.8 < np.median(ratio) < 1.25
    assert np.all((ratio > 0.6) & (ratio < 1.6))
    # the naive covariance of independent samples is far too small: the visit's tilt does not average out
    naive = naive_covariance(data.stats, A, 1)
    assert np.median(np.sqrt(np.diag(naive) / np.diag(cov))) < 0.5


def test_coverage_of_the_truth_over_seeds() -> None:
    """Over 24 campaigns, the true coefficients fall within 1.96 standard deviations of the fit for about 95 % of
    (coefficient, campaign) pairs with the cluster covariance; with the naive one, for far fewer."""
    inside, inside_naive, total = 0, 0, 0
    for seed in range(24):
        rec, A_true = campaign(100 + seed, n_poses=6, repeats=2, visit_s=2.0)
        cal, data = _fit(rec)
        A = model_to_coefficients(cal.M, cal.b)
        z = np.abs(A - A_true).ravel() / np.sqrt(np.diag(cal.coefficient_covariance.matrix))
        z_naive = np.abs(A - A_true).ravel() / np.sqrt(np.diag(naive_covariance(data.stats, A, 1)))
        inside += int((z < 1.96).sum())
        inside_naive += int((z_naive < 1.96).sum())
        total += z.size
    coverage, coverage_naive = inside / total, inside_naive / total
    # 24 x 24 coefficients, correlated within a campaign: measured 0.91 (0.19 naive); a sandwich from 36 visits is
    # itself uncertain, which lowers the coverage of a normal quantile a little
    assert 0.85 < coverage < 0.995, coverage
    assert coverage_naive < 0.6, coverage_naive


def test_output_covariance_is_j_sigma_jt() -> None:
    """The cached quadratic form equals J Sigma J^T with J worked out by finite differences of the model."""
    rec, _ = campaign(3)
    cal, _ = _fit(rec)
    cov = cal.coefficient_covariance.matrix
    psi, temp = np.array([0.12, -0.05, 0.09]), 41.0  # outside the 15..35 degC range: extrapolating
    A = model_to_coefficients(cal.M, cal.b)
    J = np.zeros((3, A.size))
    for idx in range(A.size):
        d = np.zeros(A.size)
        d[idx] = 1e-3
        from fbg_accel_calibration.fit.thermal_fit import coefficients_to_model
        M2, b2 = coefficients_to_model(A + d.reshape(A.shape), 1)
        moved = ThermalCalibration(M=M2, b=b2, temperature_range_c=cal.temperature_range_c,
                                   t_center_c=cal.t_center_c, t_scale_c=cal.t_scale_c)
        J[:, idx] = (moved.base_acceleration(psi[None], temp)[0] - cal.base_acceleration(psi[None], temp)[0]) / 1e-3
    expected = J @ cov @ J.T
    got = output_covariance(cal.calibration_weights_at(temp), *psi)
    full = np.array([[got[0], got[1], got[2]], [got[1], got[3], got[4]], [got[2], got[4], got[5]]])
    np.testing.assert_allclose(full, expected, rtol=1e-6, atol=1e-12)
    inside = output_covariance(cal.calibration_weights_at(25.0), *psi)
    assert got[0] > 2 * inside[0]  # beyond the range the model's own powers of tau inflate it


def test_file_round_trip_and_old_files(tmp_path) -> None:
    rec, _ = campaign(4)
    cal, _ = _fit(rec)
    cal.save(tmp_path / "cal.yaml")
    back = ThermalCalibration.load(tmp_path / "cal.yaml")
    assert back == cal and back.coefficient_covariance.clusters == 48
    assert "CR2" in back.coefficient_covariance.method
    old = cal.to_dict()
    del old["coefficient_covariance"]
    assert ThermalCalibration.from_dict(old).coefficient_covariance is None  # a file without it loads as before


@pytest.mark.parametrize(("change", "message"), [
    (lambda m: m[:-1], "shape"),
    (lambda m: m + np.triu(np.full_like(m, 1e-3), 1), "not symmetric"),
    (lambda m: m - 2 * np.abs(np.linalg.eigvalsh(m)).max() * np.eye(len(m)), "positive semi-definite"),
    (lambda m: np.where(np.eye(len(m)) > 0, np.nan, m), "finite"),
])
def test_loader_refuses_a_matrix_that_is_no_covariance(change, message) -> None:
    rec, _ = campaign(5)
    cal, _ = _fit(rec)
    d = cal.to_dict()
    d["coefficient_covariance"]["matrix"] = change(np.array(d["coefficient_covariance"]["matrix"])).tolist()
    with pytest.raises(CalibrationFileError, match=message):
        ThermalCalibration.from_dict(d)


def test_section_keys_and_version_are_checked() -> None:
    rec, _ = campaign(6)
    cal, _ = _fit(rec)
    for key, value, message in (("format_version", 2, "not supported"), ("method", "", "method"),
                                 ("clusters", 0, "clusters"), ("extra", 1, "unknown key")):
        d = cal.to_dict()
        d["coefficient_covariance"][key] = value
        with pytest.raises(CalibrationFileError, match=message):
            ThermalCalibration.from_dict(d)
    with pytest.raises(ValueError, match="degree"):
        ThermalCalibration(M=cal.M[:1], b=cal.b[:1], temperature_range_c=(15, 35),
                           coefficient_covariance=CoefficientCovariance(np.eye(24), "m", 3))  # degree 1 for degree 0


def _frames_at(M: np.ndarray, b: np.ndarray, g: np.ndarray, temp_c: float, n: int, start: int):
    """``n`` frames whose counts eq. 28 with the true (M, b) maps onto ``g`` (m/s^2) at ``temp_c`` (no noise: what is
    left of the driver's error is the calibration's), and the true output of their (rounded) counts."""
    from fbg_accel_driver.frame_codec import Frame, Status

    tau = (temp_c - 25.0) / 10.0
    Mt = sum(M[k] * tau**k for k in range(len(M)))
    bt = sum(b[k] * tau**k for k in range(len(b)))
    counts = np.round(np.linalg.solve(Mt, g - bt) * 880.0).astype(int)
    truth = Mt @ (counts / 880.0) + bt
    good = int(Status.TEMP_VALID | Status.TEMP_PRESENT)
    return [Frame(seq=(start + i) % 65536, t_us=(start + i) * 10_000, ref=880, x=int(counts[0]), y=int(counts[1]),
                  z=int(counts[2]), temp_cc=round(temp_c * 100), status=good) for i in range(n)], truth


def test_the_driver_s_calibration_term_is_consistent_with_its_error_over_seeds() -> None:
    """NEES per axis of the driver's output against the truth of 24 simulated campaigns, at four orientations the
    campaign did not visit, inside (25 degC) and beyond (40 degC) the 15..35 degC range, normalised by the calibration
    term the driver publishes: about 1 (consistent), where the naive coefficient covariance gives far more."""
    from dataclasses import replace

    from test_driver_core import feed_frames

    from fbg_accel_driver.driver_core import CoreConfig, DriverCore
    from fbg_accel_sim.eq28_campaign import G, _truth

    rng = np.random.default_rng(7)
    checks = rng.normal(size=(4, 3))
    checks = G * checks / np.linalg.norm(checks, axis=1)[:, None]
    M, b = _truth(1)
    nees, nees_naive = [], []
    for seed in range(24):
        rec, _ = campaign(300 + seed, n_poses=6, repeats=2, visit_s=2.0)
        cal, data = _fit(rec)
        naive = replace(cal, coefficient_covariance=CoefficientCovariance(
            naive_covariance(data.stats, model_to_coefficients(cal.M, cal.b), 1), "naive", 1))
        for temp_c in (25.0, 40.0):
            for g in checks:
                frames, truth = _frames_at(M, b, g, temp_c, 10, 0)
                for c, out in ((cal, nees), (naive, nees_naive)):
                    with_term = feed_frames(DriverCore(c, CoreConfig(decimation=10, covariance_includes_calibration=True)),
                                            frames)[1][0]
                    # less the noise of a mean of 10 samples (white: the campaign's fit has no noise_correlation)
                    term = np.diag(np.array(with_term.covariance).reshape(3, 3)) - c.noise_sigma_mps2**2 / 10
                    out.append((np.array(with_term.accel_mps2) - truth) ** 2 / term)
    nees_a, naive_a = np.array(nees), np.array(nees_naive)
    # per axis chi2(1) if the term were exact; it is estimated from 36 visits, which fattens the tail (measured: mean
    # 0.82, 93 % of the errors within 1.96 sigma; with the naive covariance: mean 41, 59 %)
    assert 0.5 < float(nees_a.mean()) < 2.0, nees_a.mean()
    assert 0.85 < float((nees_a < 1.96**2).mean()) < 0.99
    assert naive_a.mean() > 10.0 and float((naive_a < 1.96**2).mean()) < 0.75


def test_too_many_visits_fall_back_to_the_cells_as_clusters(monkeypatch) -> None:
    """Beyond MAX_VISIT_SUMS visits their sums are not kept (memory): the covariance is clustered by cell, and says so;
    with one visit per cell it is then the same covariance."""
    from fbg_accel_calibration.fit import thermal_fit

    rec, _ = campaign(8, repeats=1)
    by_visit, _ = _fit(rec)
    monkeypatch.setattr(thermal_fit, "MAX_VISIT_SUMS", 10)
    by_cell, data = _fit(rec)
    assert len(data.stats.visit_cell) == 0 and data.stats.n_visits == 24
    assert "cells" in by_cell.coefficient_covariance.method and "visits as clusters" in by_visit.coefficient_covariance.method
    np.testing.assert_allclose(by_cell.coefficient_covariance.matrix, by_visit.coefficient_covariance.matrix,
                               rtol=1e-9, atol=1e-12 * np.abs(by_visit.coefficient_covariance.matrix).max())
