"""Static-interval detector: moving variance, noise-floor threshold, intervals, streaming monitor."""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_calibration.recording import Recording
from fbg_accel_calibration.static_detector import (
    calibration_samples,
    detect_static,
    estimate_noise_var,
    intervals_from_mask,
    moving_variance,
    variance_threshold,
)


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


def test_detects_plateaus_and_rejects_ramps() -> None:
    rng = np.random.default_rng(2)
    levels = rng.uniform(-1.0, 1.0, (12, 3))
    x, truth = _staircase(rng, levels, dwell=100, move=20, sigma=2e-3)
    det = detect_static(x, window=5, min_interval=10)
    assert not np.any(det.mask & ~truth), "a sample on a ramp was called static"
    # every plateau is found, losing at most a window's width at its ends
    assert len(det.intervals) == len(levels)
    assert det.mask.sum() >= truth.sum() - len(levels) * 2 * 5
    for a, b in det.intervals:
        assert b - a >= 10 and truth[a:b].all()


def test_min_interval_drops_short_still_runs() -> None:
    rng = np.random.default_rng(3)
    levels = np.array([[0.0], [1.0], [2.0]])
    x, _ = _staircase(rng, levels, dwell=8, move=1, sigma=1e-3)
    x = np.vstack([x, np.full((200, 1), 2.0) + rng.normal(0, 1e-3, (200, 1))])
    long_only = detect_static(x, window=3, min_interval=20, noise_var=np.array([1e-6]))
    assert all(b - a >= 20 for a, b in long_only.intervals)
    assert not long_only.mask[:10].any()
    short_ok = detect_static(x, window=3, min_interval=3, noise_var=np.array([1e-6]))
    assert short_ok.mask[:10].any()


def test_groups_keep_windows_within_a_run() -> None:
    rng = np.random.default_rng(4)
    a = rng.normal(0.0, 1e-3, (100, 1))
    b = 5.0 + rng.normal(0.0, 1e-3, (100, 1))
    x = np.vstack([a, b])
    plain = detect_static(x, window=5, min_interval=5)
    assert not plain.mask[98:102].any()  # the jump between files looks like motion
    grouped = detect_static(x, window=5, min_interval=5, groups=np.repeat([0, 1], 100))
    assert grouped.mask.sum() > plain.mask.sum()
    assert (0, 100) in grouped.intervals and (100, 200) in grouped.intervals


def test_intervals_from_mask() -> None:
    assert intervals_from_mask(np.array([1, 1, 0, 0, 1, 0, 1, 1, 1], bool)) == [(0, 2), (4, 5), (6, 9)]
    assert intervals_from_mask(np.zeros(3, bool)) == []


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
        detect_static(np.zeros((10, 1)), min_interval=0)


def test_blocked_moving_variance_equals_one_block(monkeypatch: pytest.MonkeyPatch) -> None:
    import fbg_accel_calibration.static_detector as sd

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
    from fbg_accel_calibration.static_detector import long_runs, usable_samples

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
