"""Static-interval detector: moving variance, noise-floor threshold, intervals, streaming monitor."""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_calibration.fit.static_detector import (
    calibration_samples,
    estimate_noise_var,
    moving_variance,
    variance_threshold,
)
from fbg_accel_calibration.io.recording import Recording


def _staircase(rng: np.random.Generator, levels: np.ndarray, dwell: int, move: int, sigma: float):
    """Static plateaus of ``dwell`` samples joined by linear ramps of ``move`` samples, plus white noise."""
    parts, truth = [], []
    for i, lvl in enumerate(levels):
        parts.append(np.repeat(lvl[None, :], dwell, axis=0))
        truth.append(np.ones(dwell, bool))
        if i + 1 < len(levels):
            frac = (np.arange(1, move + 1) / (move + 1))[:, None]
            parts.append(lvl + frac * (levels[i + 1] - lvl))
            truth.append(np.zeros(move, bool))
    x = np.vstack(parts)
    return x + rng.normal(0.0, sigma, x.shape), np.concatenate(truth)


def test_moving_variance_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 3)) * [1.0, 10.0, 0.1] + 1000.0
    for window in (2, 3, 5, 8):
        got = moving_variance(x, window)
        lo_half = (window - 1) // 2
        for i in range(50):
            seg = x[max(0, i - lo_half): min(50, i - lo_half + window)]
            expected = seg.var(axis=0, ddof=1) if len(seg) > 1 else np.full(3, np.nan)
            np.testing.assert_allclose(got[i], expected, rtol=1e-6)
    x[20, 1] = np.nan
    v = moving_variance(x, 5)
    assert np.isnan(v[18:23]).all() and np.isfinite(v[:18]).all() and np.isfinite(v[23:]).all()


def test_noise_floor_estimate_and_false_alarm_rate() -> None:
    rng = np.random.default_rng(1)
    sigma = np.array([0.5, 2.0, 0.01])
    x = rng.normal(size=(200_000, 3)) * sigma
    stat = moving_variance(x, 5)
    nv = estimate_noise_var(stat, 5)
    np.testing.assert_allclose(nv, sigma**2, rtol=0.03)
    thr = variance_threshold(nv, 5, false_alarm=1e-2, margin=1.0)
    rate = (stat > thr).mean(axis=0)
    np.testing.assert_allclose(rate, 1e-2, rtol=0.2)


def _signal_static(x: np.ndarray, window: int, min_interval: int, run_id: np.ndarray | None = None) -> np.ndarray:
    """The detector's static samples of a signal ``x`` (N, 1 or 3) taken as Psi (counts over a reference of 1000)."""
    psi = np.repeat(x, 3, axis=1) if x.shape[1] == 1 else x
    n = len(psi)
    rec = Recording(np.arange(n) * 0.01, np.full(n, 1000.0), psi * 1000.0, 23.0, np.full((n, 3), np.nan),
                    np.full(n, -1), run_id)
    return calibration_samples(rec, window=window, min_interval=min_interval)[1]


def _intervals(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist(), strict=True))


def test_detects_plateaus_and_rejects_ramps() -> None:
    rng = np.random.default_rng(2)
    levels = rng.uniform(-1.0, 1.0, (12, 3))
    x, truth = _staircase(rng, levels, dwell=100, move=20, sigma=2e-3)
    static = _signal_static(x, window=5, min_interval=10)
    assert not np.any(static & ~truth), "a sample on a ramp was called static"
    # every plateau is found, losing at most a window's width at its ends
    assert len(_intervals(static)) == len(levels)
    assert static.sum() >= truth.sum() - len(levels) * 2 * 5
    for a, b in _intervals(static):
        assert b - a >= 10 and truth[a:b].all()


def test_min_interval_drops_short_still_runs() -> None:
    rng = np.random.default_rng(3)
    levels = np.array([[0.0], [1.0], [2.0]])
    x, _ = _staircase(rng, levels, dwell=8, move=1, sigma=1e-3)
    x = np.vstack([x, np.full((200, 1), 2.0) + rng.normal(0, 1e-3, (200, 1))])
    long_only = _signal_static(x, window=3, min_interval=20)
    assert all(b - a >= 20 for a, b in _intervals(long_only))
    assert not long_only[:10].any()
    assert _signal_static(x, window=3, min_interval=3)[:10].any()


def test_runs_keep_windows_within_a_run() -> None:
    rng = np.random.default_rng(4)
    a = rng.normal(0.0, 1e-3, (100, 1))
    b = 5.0 + rng.normal(0.0, 1e-3, (100, 1))
    x = np.vstack([a, b])
    plain = _signal_static(x, window=5, min_interval=5)
    assert not plain[98:102].any()  # the jump between files looks like motion
    runs = _signal_static(x, window=5, min_interval=5, run_id=np.repeat([0, 1], 100))
    assert runs.sum() > plain.sum()
    assert (0, 100) in _intervals(runs[:100]) and (0, 100) in _intervals(runs[100:])


def test_calibration_samples_need_a_still_signal_and_a_still_reference() -> None:
    rng = np.random.default_rng(5)
    n = 60
    g = np.repeat(np.array([[0.0, 0.0, 9.8], [0.0, 4.9, 8.5], [0.0, 9.8, 0.0]]), 20, axis=0)
    g[20] = [0.0, 2.5, 9.5]  # intermediate table reading while moving
    psi = np.hstack([g / 80.0, np.ones((n, 1))])[:, :3] + rng.normal(0, 1e-4, (n, 3))
    g[50] += 0.01  # a reading the signal does not show: the reference alone is not still around it
    ref = np.full(n, 900.0)
    pose = np.repeat([0, 1, 2], 20)
    pose[20] = 3
    rec = Recording(np.arange(n) * 0.01, ref, psi * ref[:, None], 23.0, g, pose)
    usable, static = calibration_samples(rec, window=3, min_interval=3)
    assert not usable[[19, 20, 21, 39, 40, 49, 50, 51]].any()
    assert usable[[1, 10, 25, 45, 55]].all()
    assert static[[49, 50, 51]].all() and not static[[20, 40]].any()
    # runs are decided apart (one noise floor each); a run's samples must be together
    two = Recording(np.r_[rec.t_s, rec.t_s + 1.0], np.r_[ref, ref], np.r_[rec.xyz, rec.xyz], 23.0, np.r_[g, g],
                    np.r_[pose, pose], np.repeat([0, 1], n))
    np.testing.assert_array_equal(calibration_samples(two, window=3, min_interval=3)[0], np.r_[usable, usable])
    two.run_id = np.tile(np.repeat([0, 1], n // 2), 2)
    with pytest.raises(ValueError, match="contiguous"):
        calibration_samples(two)


def test_bad_parameters() -> None:
    with pytest.raises(ValueError, match="window"):
        moving_variance(np.zeros((10, 1)), 1)
    with pytest.raises(ValueError, match="false_alarm"):
        variance_threshold(np.ones(1), 5, false_alarm=0.0)
    with pytest.raises(ValueError, match="min_interval"):
        _signal_static(np.zeros((10, 1)), window=3, min_interval=0)


def test_blocked_moving_variance_equals_one_block(monkeypatch: pytest.MonkeyPatch) -> None:
    import fbg_accel_calibration.fit.static_detector as sd

    rng = np.random.default_rng(7)
    x = rng.normal(size=(1000, 3)) + 500.0
    x[333, 0] = np.nan
    whole = moving_variance(x, 5)
    monkeypatch.setattr(sd, "BLOCK_ROWS", 7)
    blocked = moving_variance(x, 5)
    np.testing.assert_allclose(blocked, whole, rtol=1e-9, atol=1e-12)
    assert np.array_equal(np.isnan(blocked), np.isnan(whole))


def test_interval_rules_keep_only_long_enough_runs_of_one_pose() -> None:
    """The interval rule of the detector (static_detector.usable_samples), which it applies block by block."""
    from fbg_accel_calibration.fit.static_detector import long_runs, usable_samples

    still = np.array([1, 1, 1, 0, 1, 1, 1, 1, 0, 1], bool)
    np.testing.assert_array_equal(long_runs(still, 3), [1, 1, 1, 0, 1, 1, 1, 1, 0, 0])
    assert long_runs(np.zeros(0, bool), 3).shape == (0,)
    pose = np.array([0, 0, 0, 0, 0, 1, 1, 1, 1, 1])
    ok = np.ones(10, bool)
    # the pose changes inside the second static run: each part must be long enough on its own
    np.testing.assert_array_equal(usable_samples(long_runs(still, 3), ok, pose, ok, 3), [1, 1, 1, 0, 0, 1, 1, 1, 0, 0])
    ref_moving = ok.copy()
    ref_moving[1] = False
    np.testing.assert_array_equal(usable_samples(long_runs(still, 3), ref_moving, pose, ok, 2)[:3], [0, 0, 0])


@pytest.mark.parametrize("rate_hz", [400.0, 1000.0])
def test_an_oversampled_quantised_signal_keeps_its_still_samples_and_its_noise_floor(rate_hz: float) -> None:
    """At a high sample rate the TIA-filtered channels sit on one ADC code for most 5-sample windows, so the
    median window variance (the noise floor) is near zero; the floor is never taken below the rounding to whole
    counts (``quantisation_var``), so a window in which a code changes is not called moving. Before: 76 % of the
    settled samples rejected at 400 Hz (54 % at 1 kHz), and the fitted noise floor taken from the quietest windows."""
    from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
    from fbg_accel_driver.thermal_model import normalise
    from fbg_accel_sim.board_physics import SimConfig, simulate_recording

    poses = [[0, 0], [0, 90], [90, 90], [180, 90], [270, 90], [0, 180], [45, 45], [135, 60]]
    cfg = SimConfig.load("test/fixtures/sim_diagnosis_baseline.yaml").with_overrides({
        "scenario.rate_hz": rate_hz, "scenario.poses.mode": "list", "scenario.poses.list": poses,
        "scenario.poses.dwell_s": 4.0, "scenario.poses.move_s": 1.0})
    rec = simulate_recording(cfg, seed=3)
    truth = rec.metadata["truth"]
    settled = ~truth["in_motion"] & (truth["time_at_pose_s"] > 1.0)
    usable, static = calibration_samples(rec)
    assert static[settled].mean() > 0.99, f"{100 * (1 - static[settled].mean()):.1f} % of settled samples rejected"
    assert not np.any(usable & truth["in_motion"])  # the moves stay out (the table's reference moves)
    cal = fit_thermal(rec, degree=0)
    # the floor the fit should report: scatter of its residual within each visit, over the settled samples
    resid = cal.base_acceleration(normalise(rec.xyz, rec.ref), rec.temp_c) - rec.gref_mps2
    visit = truth["visit"]
    within = np.vstack([resid[settled & (visit == v)] - resid[settled & (visit == v)].mean(axis=0)
                        for v in np.unique(visit[settled])])
    np.testing.assert_allclose(cal.noise_sigma_mps2, within.std(axis=0), rtol=0.05)


def test_the_chi_square_quantile_is_scipy_stats_own_to_the_bit() -> None:
    """The detector's threshold and noise floor take chi-square quantiles from scipy.special (scipy.stats costs half a
    second of every fit's start-up): the same bits as scipy.stats.chi2 for the windows and levels used."""
    from scipy.stats import chi2

    from fbg_accel_calibration.fit.static_detector import chi2_quantile

    dof = np.arange(1, 200)
    for p in (0.5, 1 - 1e-2, 1 - 1e-3, 1 - 1e-4, 1 - 1e-6, 1 - 1e-9):
        assert np.array_equal(chi2_quantile(p, dof), chi2.ppf(p, dof)), p
    assert np.array_equal(chi2_quantile(0.5, dof), chi2.median(dof))
