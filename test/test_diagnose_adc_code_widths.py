"""The ADC's code widths as a candidate of the diagnosis (``fbg_accel_calibration.diagnosis.adc_code_candidate``): the simulator's
injected width pattern is named by its own held-out test, a campaign without it claims nothing, each fold's table never
sees the visits it predicts, and a pattern beyond the ESP32's datasheet is refused. The 10-seed check through the whole
diagnosis is ``bench/diagnose_adc_codes_check.py``."""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_calibration.diagnosis import adc_code_candidate as cand
from fbg_accel_calibration.diagnosis.adc_code_candidate import code_width_step, implausible
from fbg_accel_calibration.diagnosis.cv import check_folds, cross_validate, make_folds
from fbg_accel_calibration.diagnosis.design import ModelSpec, build_design, prepare_data
from fbg_accel_calibration.fit.thermal_fit import temperature_scaling
from fbg_accel_driver.adc_code_table import ADC_CODES, AdcCodeTable, pattern_edges
from fbg_accel_sim.board_physics import simulate_recording
from fbg_accel_sim.sim_config import SimConfig

OFF = ("reference_dark_offset", "thermal_lag", "spectral_nonlinearity", "time_drift", "channel_delay", "tia_lowpass",
       "thermal_hysteresis", "unmodelled_cable_torque")
FOLDS = 5  # the diagnosis draws 10; 5 decide as clearly here at half the width fits
LEVEL = 0.01 / 9  # the first step's level of the measured series' diagnosis (alpha 0.01 over its 9 candidates)


def campaign(seed: int, pattern: bool):
    """The measured run's 156-pose grid (theta, psi in 30 degree steps), 2 s at each pose at 10 Hz, the named effects
    off, the Table 2 noise and 1 count of reference read noise; the measured width pattern on or off."""
    cfg = SimConfig.default().with_overrides({
        **{f"effects.{k}.scale": 0.0 for k in OFF}, "scenario.poses.mode": "grid", "scenario.poses.dwell_s": 2.0,
        "scenario.poses.move_s": 1.0, "scenario.rate_hz": 10.0, "noise.reference_noise_counts": 1.0,
        "effects.adc_code_widths.scale": 1.0 if pattern else 0.0})
    return simulate_recording(cfg, seed=seed)


def evaluate(rec):
    """The candidate on top of the declared model (eq. 25), with the diagnosis' folds over visits and noise weights."""
    data = prepare_data(rec)
    fold = check_folds(data, data.group, make_folds(data.group, data.use, FOLDS, 0))[0]
    spec = ModelSpec(0, *temperature_scaling(data.temp_c[data.use]))
    des = build_design(data, spec)
    fit = data.use & (fold != -1)
    res = cross_validate(des, fit, fold, np.ones(3)).heldout
    weights = 1.0 / np.nanvar(res[data.use & (fold >= 0)], axis=0)
    return data, spec, fold, weights, code_width_step(data, spec, fold, weights, res, LEVEL, 0.02)


def test_an_injected_width_pattern_is_named_with_each_fold_s_table_blind_to_the_visits_it_predicts(monkeypatch) -> None:
    """Seed 1: gain +18.1 %, p 2e-13 against the rule's p < 1.1e-3 and 2 %, asserted with margin (seeds 2 and 3: +10.0 %,
    p 3e-6 and +3.8 %, p 0.16: the pattern's bias depends on where the visits' inputs fall between codes, so the test's
    power on 156 visits is not 1; the rate over 10 seeds through the whole diagnosis: bench/diagnose_adc_codes_check.py).
    The table each fold is predicted through is estimated from samples none of which is in that fold (no leak into
    the visits held out)."""
    seen: list[tuple[str, np.ndarray]] = []
    real = cand.fold_table

    def spy(data, train, source):
        seen.append((source, train.copy()))
        return real(data, train, source)

    monkeypatch.setattr(cand, "fold_table", spy)
    _, _, fold, _, step = evaluate(campaign(1, True))
    r = step.result
    assert r.significant and r.p_value < LEVEL / 100 and r.rel_gain > 0.06, (r.rel_gain, r.p_value, r.detail)
    assert step.table is not None and step.cv is not None and not r.implausible
    # the table the calibration would carry holds the pattern: code 16k wide, 16k + 8 narrow (injected 2.2 / 0.35)
    w = np.diff(step.table.edges[1, 1600:1617])
    assert w[0] > 1.6 and w[8] < 0.6, w.round(2)
    left_out = []  # the folds' tables: each trained on every fold but a pair (2k, 2k + 1), none of that pair's samples
    for _, train in seen[:-1]:
        missing = [f for f in range(FOLDS) if not np.any(train & (fold == f))]
        assert train.any() and missing == [f for f in range(FOLDS) if f // 2 == missing[0] // 2], missing
        left_out += missing
    assert sorted(left_out) == list(range(FOLDS))  # every fold is predicted through a table blind to it
    assert "diagnosed recording" in seen[-1][0] and all(np.any(seen[-1][1] & (fold == f)) for f in range(FOLDS))


@pytest.mark.parametrize("seed", [1, 2])
def test_without_a_pattern_nothing_is_claimed(seed: int) -> None:
    step = evaluate(campaign(seed, False))[-1]
    r = step.result
    assert r.applicable and not r.significant and step.table is None, r.detail
    assert "no width pattern" in r.detail


def test_a_pattern_beyond_the_datasheet_s_dnl_or_inl_is_refused() -> None:
    codes = np.arange(ADC_CODES + 1)
    ok = np.array([2.2, 1.1, 1, 1, 0.7, 1, 1, 1.1, 0.35, 0.8, 1.05, 1.2, 0.75, 1.05, 0.95, 0.75])
    ok *= 16 / ok.sum()
    assert implausible(AdcCodeTable(np.tile(pattern_edges(ok, codes), (4, 1))), ok) == ""
    wide = np.full(16, 7.0 / 15)
    wide[0] = 9.0  # a code 9 LSB wide: DNL +8, beyond the datasheet's 7
    assert "beyond the ESP32's DNL of 7 LSB" in implausible(AdcCodeTable(np.tile(pattern_edges(wide, codes), (4, 1))),
                                                           wide)
    edges = np.tile(codes - 0.5, (4, 1)).astype(float)
    edges[1, 2000:2040] += np.linspace(0.0, 30.0, 40)  # interval edges 30 counts off: INL far beyond 12 LSB
    edges[1, 2040:] += 30.0
    msg = implausible(AdcCodeTable(edges), np.ones(16))
    assert "INL" in msg and "beyond the ESP32's 12 LSB" in msg, msg


def test_the_pooled_widths_read_the_chosen_samples_alone_and_equal_the_estimate_over_every_sample() -> None:
    """``pooled_widths`` takes its samples out before it estimates (its arrays are of those rows, not of the whole
    recording): the same pattern, test and pieces, bit for bit, as ``recording_code_widths`` over every sample with
    the rows as a mask, and a sample outside the rows, however wild, changes nothing."""
    from fbg_accel_calibration.fit.adc_codes import recording_code_widths

    data = prepare_data(campaign(1, True))
    rows = cand._thinned(cand.width_rows(data), cand.GATE_SAMPLES)
    assert 0 < rows.sum() < cand.width_rows(data).sum()  # thinned: samples of the visits left out
    whole = recording_code_widths(np.column_stack([data.ref, data.xyz]), data.group, rows, per_channel=False).pooled
    got = cand.pooled_widths(data, rows).pooled
    assert got is not None and whole is not None and got.pattern_found
    for field in ("pattern", "pattern_sd", "expected", "codes", "hits"):
        np.testing.assert_array_equal(getattr(got, field), getattr(whole, field))
    assert (got.chi2, got.p_value, got.sigma_counts, got.n_visits) == (whole.chi2, whole.p_value, whole.sigma_counts,
                                                                         whole.n_visits)
    wild = replace_counts(data, ~rows)
    again = cand.pooled_widths(wild, rows).pooled
    np.testing.assert_array_equal(again.pattern, got.pattern)
    assert again.p_value == got.p_value


def replace_counts(data, where: np.ndarray):
    """``data`` with the counts of the samples ``where`` set to codes no visit reads."""
    from dataclasses import replace

    ref, xyz = data.ref.copy(), data.xyz.copy()
    ref[where], xyz[where] = 7.0, 4000.0
    return replace(data, ref=ref, xyz=xyz)
