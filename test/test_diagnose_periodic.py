"""A periodic disturbance during the static visits is named, and kept out of the noise floor (issue 8 §2).

A table or chamber that sways, or a fan, adds a sine of a few 0.01-0.1 m/s^2 at 0.2-2 Hz to every visit. It was
absorbed into the within-visit noise floor and never named: on the simulator's grid run with a 0.37 Hz sine of
0.1 / 0.06 m/s^2 on x / y the floor came out 1.13 / 1.17x the sensor's noise (seed 1), every ratio "held-out / floor"
was flattered by as much, and nothing told the reader that the table shook. The simulator's sines
(``scenario.vibration.sines``, ``fbg_accel_sim.scenario.vibration``) are the disturbance; the truth of the noise is the
same seed simulated without noise and rounding (as ``test_diagnose_sim``'s floor test), the truth of the disturbance
the same seed simulated without noise, with and without the sine, both through the diagnosis's calibration.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_diagnose import measured_diagnosis
from test_diagnose_sim import _config, _diagnosed, _output

from fbg_accel_calibration.diagnosis.diagnose import diagnose
from fbg_accel_calibration.diagnosis.periodic_disturbance import PERIODIC_ALPHA, find_periodic_disturbance
from fbg_accel_calibration.reports.diagnose_report import markdown
from fbg_accel_sim.board_physics import simulate_recording

QUIET = {"effects.white_noise.scale": 0.0, "effects.adc_quantisation.scale": 0.0}
SWAY = [  # (sine, extra config): a slow table sway on x / y; a faster one on y / z with the TIA low-passes on
    ({"freq_hz": 0.37, "amplitude_mps2": [0.1, 0.06, 0.0], "phase_deg": 20.0}, {}),
    ({"freq_hz": 1.3, "amplitude_mps2": [0.0, 0.08, 0.12], "phase_deg": -70.0}, {"effects.tia_lowpass.scale": 1.0}),
]


def _sine_amplitude(x: np.ndarray, t: np.ndarray, freq: float) -> np.ndarray:
    """Least-squares amplitude (3,) of a sine at ``freq`` Hz (with a constant) in x (n, 3) at times t (n,) s."""
    A = np.column_stack([np.cos(2 * np.pi * freq * t), np.sin(2 * np.pi * freq * t), np.ones_like(t)])
    c = np.linalg.lstsq(A, x, rcond=None)[0]
    return np.hypot(c[0], c[1])


@pytest.mark.parametrize("seed", [1, pytest.param(2, marks=pytest.mark.sweep)])  # seed 2: bench/seed_sweeps.py
@pytest.mark.parametrize("case", range(len(SWAY)))
def test_a_table_sway_is_named_and_kept_out_of_the_noise_floor(case: int, seed: int) -> None:
    """On the code before (e6af7cc): no ``disturbance`` on the result, no warning, and the floor x / y / z against the
    noise 1.13 / 1.17 / 1.01 and 1.15 / 1.16 / 1.01 (0.37 Hz, seeds 1 / 2), 1.03 / 1.17 / 1.18 and 1.01 / 1.15 / 1.11
    (1.3 Hz): held-out / floor 0.96-1.01, "no significant unexplained residual"."""
    sine, extra = SWAY[case]
    cfg = {**extra, "scenario.vibration.sines": [sine]}
    rec = simulate_recording(_config(cfg), seed=seed)
    quiet = simulate_recording(_config({**cfg, **QUIET}), seed=seed)
    still = simulate_recording(_config({**extra, **QUIET}), seed=seed)
    res = diagnose(rec)
    cal = res.calibration
    used = res.data.use & (rec.pose_id >= 0)
    noise = _output(cal, rec) - _output(cal, quiet)
    truth_floor = np.sqrt(np.mean(noise[used] ** 2, axis=0))
    sway = _output(cal, quiet) - _output(cal, still)  # the disturbance as the calibrated output carries it
    truth_amp = _sine_amplitude(sway[used], rec.t_s[used], sine["freq_hz"])

    d = res.disturbance
    assert len(d.lines) == 1, d.summary()
    line = d.lines[0]
    assert abs(line.freq_hz / sine["freq_hz"] - 1.0) < 0.02, line.freq_hz
    # amplitude per axis: within 15 % where there is a sine, within 0.015 m/s^2 of nothing where there is none
    np.testing.assert_allclose(line.amplitude_mps2, truth_amp, rtol=0.15, atol=0.015)
    assert line.p_value < PERIODIC_ALPHA
    # the floor the ratios use is the noise without it, within 10 % of the truth; the floor with it is reported
    assert np.all(np.abs(res.final_floor / truth_floor - 1.0) < 0.10), (res.final_floor / truth_floor).round(3)
    assert d.floor_with_lines is not None and np.all(d.floor_with_lines >= res.noise_floor)
    axes = np.flatnonzero(truth_amp > 0.03)
    assert np.all(d.floor_with_lines[axes] > 1.04 * res.noise_floor[axes]), (d.floor_with_lines, res.noise_floor)
    # the held-out error holds the disturbance: reported without it too
    assert np.all(d.heldout_without_lines[axes] < res.after_heldout_rmse[axes])
    # named in the warnings and in the report, with its frequency and the basis of the ratios
    named = [w for w in res.warnings if "periodic disturbance" in w]
    assert len(named) == 1 and f"{line.freq_hz:.4g} Hz" in named[0], res.warnings
    md = markdown(res)
    assert "## Periodic disturbance" in md and f"{line.freq_hz:.4g} Hz" in md
    assert "without the disturbance" in md


@pytest.mark.parametrize("seed", [1, 2, 3, 11, 12, 13])
def test_clean_recordings_name_no_disturbance_and_keep_their_floor(seed: int) -> None:
    """No sine: nothing is named, no warning, the floor is the within-visit scatter as before. The search's
    family-wise level is PERIODIC_ALPHA = 1e-3 per recording, so the six seeds together false-alarm with probability
    below 0.6 % (the level itself is measured in the next test). On the code before: no ``disturbance``. The clean
    grids are those the other diagnosis tests check other things of (``_diagnosed``: each diagnosed once per run)."""
    res = _diagnosed({}, seed)
    assert not res.disturbance.found, res.disturbance.summary()
    assert res.disturbance.floor_with_lines is None
    assert not [w for w in res.warnings if "periodic disturbance" in w]
    assert "## Periodic disturbance" not in markdown(res)


def _gapped_noise(rng: np.random.Generator, n_visits: int = 40, n: int = 300, gap: int = 100, tau: float = 12.0,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """White plus first-order noise (3 axes, unit variance each part) in visits of ``n`` samples at 100 Hz separated by
    ``gap`` unsampled ones, each visit with its own offset and slope: (residual (N, 3), t (N,) s, visit (N,))."""
    total = n_visits * (n + gap)
    e = rng.normal(size=(total, 3))
    a = np.exp(-1.0 / tau)
    ar = np.empty_like(e)
    ar[0] = e[0]
    for k in range(1, total):  # loop over ~16 000 samples: cheap
        ar[k] = a * ar[k - 1] + np.sqrt(1 - a * a) * e[k]
    x = ar + rng.normal(size=(total, 3))
    keep = (np.arange(total) % (n + gap)) < n
    visit = np.arange(total) // (n + gap)
    t = np.arange(total) / 100.0
    x = x + rng.normal(size=(n_visits, 3))[visit] + rng.normal(size=(n_visits, 3))[visit] * t[:, None]
    return x[keep], t[keep], visit[keep]


def test_false_alarm_rate_of_the_line_search_stays_at_its_level() -> None:
    """The search run at a loose level (alpha 0.2, so that false alarms are frequent enough to count) on 60 gapped
    series of coloured noise without any line: its false alarms stay within the binomial 99.9 % bound of that level
    (Bonferroni makes the search conservative, so fewer is fine). A level that did not hold (an ordinate against a
    level it is not distributed about) would fire on most series. On the code before: no search."""
    rng = np.random.default_rng(7)
    trials, alpha = 60, 0.2
    alarms = 0
    for _ in range(trials):
        x, t, visit = _gapped_noise(rng)
        d = find_periodic_disturbance(x, t, visit, np.zeros(len(t), int), np.ones(len(t), bool), alpha=alpha,
                                      max_lines=1)
        alarms += d.found
    from scipy import stats
    assert alarms <= stats.binom.ppf(0.999, trials, alpha), alarms


def test_a_line_in_gapped_noise_is_found_at_its_frequency_and_amplitude() -> None:
    """The same series with a sine of 0.3 x the noise's standard deviation at 0.83 Hz on y: found, within 1 % of its
    frequency and 15 % of its amplitude, nothing of it on x / z beyond the noise."""
    rng = np.random.default_rng(8)
    x, t, visit = _gapped_noise(rng)
    amp = 0.3 * np.sqrt(2.0)
    x[:, 1] += amp * np.sin(2 * np.pi * 0.83 * t + 0.4)
    d = find_periodic_disturbance(x, t, visit, np.zeros(len(t), int), np.ones(len(t), bool))
    assert len(d.lines) == 1, d.summary()
    assert abs(d.lines[0].freq_hz / 0.83 - 1) < 0.01
    np.testing.assert_allclose(d.lines[0].amplitude_mps2, [0.0, amp, 0.0], rtol=0.15, atol=0.1)


def test_measured_series_names_no_disturbance_and_keeps_its_figures(tmp_path: Path) -> None:
    """The measured multi-position series (1 Hz, 1560 samples): no line is found, so every figure stays what it was
    (the floor and held-out errors are those of ``test_diagnose``'s measured test, unchanged by the search)."""
    res = measured_diagnosis()  # diagnose(import_csv(MEASURED, ...)), shared with test_diagnose's measured test
    assert not res.disturbance.found, res.disturbance.summary()
    assert res.disturbance.floor_with_lines is None and res.disturbance.heldout_without_lines is None
    assert not [w for w in res.warnings if "periodic disturbance" in w]
