"""Live stillness detector (fbg_accel_driver.stillness_monitor): its law, its learnt floor, its
hysteresis, and its false-alarm rate per run on long simulated static recordings (issue 11).

The simulator is the physics-based board model (TIA low-pass of paper Table 1, Table 2 noise, ADC), so
the Psi noise here is the correlated noise the calibration node sees; no numbers are hard-coded from a
previous run of the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from fbg_accel_driver.stillness_monitor import (
    NoiseFloor,
    StillnessMonitor,
    first_order_noise_floor,
    learn_noise_floor,
    ratio_exceedance,
    ratio_quantile,
    window_variance_weights,
)
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig

RATE_HZ = 100.0
WINDOW = 25  # 0.25 s at 100 Hz, the node's default
LEARN = 500  # 5 s at 100 Hz, the node's default


def _ar1(n: int, rho: float, k: int, rng: np.random.Generator) -> np.ndarray:
    """Unit-variance first-order (AR(1)) noise, (n, k): a white source through a first-order low-pass."""
    e = rng.standard_normal((n, k)) * math.sqrt(1.0 - rho * rho)
    x = np.empty((n, k))
    x[0] = rng.standard_normal(k)
    for i in range(1, n):
        x[i] = rho * x[i - 1] + e[i]
    return x


@pytest.mark.parametrize("exceedance", [1e-2, 1e-4, 1e-7])
def test_white_noise_known_floor_gives_the_chi_square_quantile(exceedance: float) -> None:
    lam = window_variance_weights(np.array([1.0]), WINDOW)
    assert np.allclose(lam, 1.0 / (WINDOW - 1))
    exact = stats.chi2.isf(exceedance, WINDOW - 1) / (WINDOW - 1)
    assert ratio_quantile(exceedance, lam, math.inf) == pytest.approx(exact, rel=5e-3)


@pytest.mark.parametrize("nu_floor", [10.0, 60.0])
def test_white_noise_learnt_floor_gives_the_f_quantile(nu_floor: float) -> None:
    lam = window_variance_weights(np.array([1.0]), WINDOW)
    for exceedance in (1e-3, 1e-6):
        exact = stats.f.isf(exceedance, WINDOW - 1, nu_floor)
        assert ratio_quantile(exceedance, lam, nu_floor) == pytest.approx(exact, rel=5e-3)


def test_correlated_noise_quantile_matches_monte_carlo() -> None:
    # lag-1 correlation 0.87, as Psi at 100 Hz (TIA ~1 Hz): the window holds ~4.5 independent samples
    rho = 0.87
    lam = window_variance_weights(rho ** np.arange(WINDOW), WINDOW)
    rng = np.random.default_rng(5)
    x = np.empty((200_000, WINDOW))  # independent windows of a stationary AR(1)
    x[:, 0] = rng.standard_normal(200_000)
    for i in range(1, WINDOW):
        x[:, i] = rho * x[:, i - 1] + math.sqrt(1 - rho * rho) * rng.standard_normal(200_000)
    ratio = x.var(axis=1, ddof=1) / lam.sum()
    for exceedance in (1e-2, 1e-3):
        mc = np.quantile(ratio, 1.0 - exceedance)
        assert ratio_quantile(exceedance, lam, math.inf) == pytest.approx(mc, rel=0.05)
    # and the white-noise law would be badly wrong there (this is why the old chi-square bound needed a margin)
    white = stats.chi2.isf(1e-3, WINDOW - 1) / (WINDOW - 1)
    assert np.mean(ratio > white) > 10 * 1e-3
    assert ratio_exceedance(1.0, lam, math.inf) == 0.5  # at or below the mean: not a tail


def test_learnt_floor_recovers_a_first_order_process() -> None:
    rng = np.random.default_rng(11)
    tau = 7.0  # samples
    x = 3e-3 * _ar1(20_000, math.exp(-1.0 / tau), 3, rng)
    floor = learn_noise_floor(x, max_lag=WINDOW)
    assert floor.variance == pytest.approx(np.full(3, 9e-6), rel=0.1)
    lag5 = floor.acf[:, 5]
    assert lag5 == pytest.approx(np.full(3, math.exp(-5.0 / tau)), abs=0.04)
    assert np.all(floor.dof > 1000) and np.all(floor.dof < 20_000)
    white = learn_noise_floor(rng.standard_normal((2000, 2)), max_lag=WINDOW)
    assert np.all(white.acf[:, 1:] == 0.0)
    assert white.dof == pytest.approx(np.full(2, 2000.0), rel=0.01)
    with pytest.raises(ValueError, match="constant"):
        learn_noise_floor(np.ones((100, 3)), max_lag=WINDOW)
    with pytest.raises(ValueError, match="finite"):
        learn_noise_floor(np.full((100, 3), np.nan), max_lag=WINDOW)


def test_hysteresis_enter_hold_leave_and_no_reentry_while_settling() -> None:
    rng = np.random.default_rng(3)
    sigma = 1e-3
    floor = first_order_noise_floor(np.full(3, sigma), corr_samples=0.0, max_lag=WINDOW)
    mon = StillnessMonitor(floor, window=WINDOW, hold=50, run_samples=10_000, false_alarm_per_run=1e-3)
    # white, known floor: the enter threshold is the 5 % point of chi2(w-1)/(w-1), the leave one far out
    assert mon.enter_threshold == pytest.approx(sigma**2 * stats.chi2.isf(0.05, WINDOW - 1) / (WINDOW - 1), rel=5e-3)
    assert np.all(mon.leave_threshold > mon.enter_threshold)
    # still from the start: the window fills, a window below the enter threshold on all axes (each 95 %)
    # starts the 50-sample hold
    first = next(i for i in range(1000) if mon.update(sigma * rng.standard_normal(3)))
    assert WINDOW - 1 + 50 - 1 <= first <= WINDOW - 1 + 50 + 20
    # a table move: variance 50x the floor -> moving at once
    assert not mon.update(np.array([0.05, 0.0, 0.0]))
    # settling: variance between the enter and the leave thresholds keeps it from re-entering
    mid = math.sqrt(float(np.sqrt(mon.enter_threshold[0] * mon.leave_threshold[0])))
    for _ in range(5 * WINDOW):
        assert not mon.update(np.array([mid * rng.choice([-1.0, 1.0]), 0.0, 0.0]))
    # quiet again: enters and is still after the hold
    out = [mon.update(sigma * rng.standard_normal(3)) for _ in range(WINDOW + 60)]
    assert out[-1] and not out[WINDOW]
    # a non-finite sample ends stillness and restarts the window
    assert not mon.update(np.array([np.nan, 0.0, 0.0]))
    assert mon.still_count == 0


def test_monitor_arguments_are_checked() -> None:
    floor = first_order_noise_floor(np.full(3, 1e-3), 5.0, WINDOW)
    for kw in ({"window": 1}, {"hold": 0}, {"run_samples": 0}, {"false_alarm_per_run": 0.0},
               {"false_alarm_per_run": float("nan")}):
        args = {"window": WINDOW, "hold": 10, "run_samples": 100} | kw
        with pytest.raises(ValueError):
            StillnessMonitor(floor, **args)
    with pytest.raises(ValueError):
        NoiseFloor(np.array([1.0, -1.0]), np.ones((2, 1)), np.ones(2))


def _static_psi(seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    cfg = SimConfig.default().with_overrides({"scenario.rate_hz": RATE_HZ})
    counts = BoardSimulator(cfg, seed=seed).step(n).counts.astype(float)
    return counts[:, 1:] / counts[:, [0]], counts[:, 0]


def test_false_alarms_per_run_on_long_simulated_static_recordings() -> None:
    """Runs of a still sensor (5 s learning, then 60 s of testing each), as the node sees them: the number
    of still -> moving transitions must stay within the per-run budget. With a budget of 0.1 per run the
    expected total over 20 runs is at most 2; the detector this replaced (chi-square bound x 5 margin,
    floor from 2 s) had about 1.9 such transitions per 400 s, i.e. about 6 here. This one has none in these
    20 runs (1 in 60 with seeds 21-23); the rate over hours of runs is bench/stillness_false_alarm.py's."""
    per_run = 0.1
    run_len = LEARN + round(60 * RATE_HZ)
    runs, transitions, still_samples = 0, 0, 0
    for seed in (21,):
        psi, ref = _static_psi(seed, 20 * run_len)
        for r in range(20):
            x = psi[r * run_len:(r + 1) * run_len]
            quant = (1.0 / np.median(ref[r * run_len:r * run_len + LEARN])) ** 2 / 12.0
            floor = learn_noise_floor(x[:LEARN], max_lag=WINDOW).with_minimum_variance(quant)
            mon = StillnessMonitor(floor, window=WINDOW, hold=100, run_samples=run_len - LEARN,
                                   false_alarm_per_run=per_run)
            was = False
            for sample in x[LEARN:]:
                now = mon.update(sample)
                transitions += was and not now
                still_samples += now
                was = now
            runs += 1
    budget = per_run * runs
    assert transitions <= budget, f"{transitions} false still->moving transitions in {runs} runs (budget {budget:g})"
    # and the detector is not trivially silent: the sensor is judged still almost all the time
    assert still_samples > 0.95 * runs * (run_len - LEARN - WINDOW - 100)


def test_a_slow_drift_of_the_level_never_completes_the_hold():
    """A slow move (the start or end of a raised-cosine turn) shifts Psi by a few sigma per window: the
    window variance stays under the enter threshold, and the hold used to complete during the move. The
    hold must also see a steady level: a drift of 5 sigma per second (100 samples) keeps restarting it."""
    rng = np.random.default_rng(3)
    floor = first_order_noise_floor(np.ones(3), 0.0, WINDOW)
    mon = StillnessMonitor(floor, window=WINDOW, hold=100, run_samples=30_000)
    ramp = 0.05 * np.arange(600)[:, None] * np.array([1.0, 0.0, 0.0])  # 5 sigma per second on x, 6 s
    verdicts = [mon.update(row) for row in ramp + rng.standard_normal((600, 3))]
    assert max(mon.last_variance) < mon.enter_threshold.max() * 2, "the ramp must be slow (variance-blind)"
    assert not any(verdicts), "still during a steady drift of the level"
    after = [mon.update(row) for row in ramp[-1] + rng.standard_normal((300, 3))]
    assert any(after) and after.index(True) < WINDOW + 100 + 50, "still again soon after the drift stops"
