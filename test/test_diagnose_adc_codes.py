"""ADC codes that hold whole visits and carry the residual (``fbg_accel_calibration.fit.adc_codes``; no open issue: found on
the measured series, where the y channel reads 1535 through the five visits the model fits worst and the codes
1536-1543 never occur: a wide code of the ESP32's ADC). The measured case is asserted in ``test_diagnose.py``."""

from __future__ import annotations

import numpy as np
import pytest
from test_diagnose_sim import _config, _diagnosed

from fbg_accel_calibration.diagnosis.diagnose import diagnose
from fbg_accel_calibration.fit.adc_codes import held_codes
from fbg_accel_sim.board_physics import simulate_recording

V, N = 80, 12  # visits, samples each
HELD = (5, 23, 41, 66)  # the visits a wide code at 1535 holds on y


def campaign(seed: int, held_score: float, wide: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(counts (V N, 4), visit labels, rows, score): channels with 1.5 counts of noise around visit means spread over
    their range; the ``HELD`` visits sit at y = 1535 on a wide code (or, ``wide`` False, with y's noise like the rest)
    and carry a score of ``held_score`` (the others: chi^2(3), the score of a visit that is off by noise alone)."""
    rng = np.random.default_rng(seed)
    means = np.column_stack([rng.uniform(850, 880, V), rng.uniform(1000, 1250, V), rng.uniform(1560, 1760, V),
                             rng.uniform(1040, 1220, V)])
    means[list(HELD), 2] = 1537.0
    counts = np.round(np.repeat(means, N, axis=0) + rng.normal(0.0, 1.5, (V * N, 4)))
    groups = np.repeat(np.arange(V), N)
    if wide:
        counts[np.isin(groups, HELD), 2] = 1535.0
    score = np.repeat(rng.chisquare(3, V), N)
    score[np.isin(groups, HELD)] = held_score
    return counts, groups, np.ones(V * N, bool), score


def test_a_wide_code_whose_visits_carry_the_residual_is_found_with_its_missing_codes() -> None:
    counts, groups, rows, score = campaign(1, held_score=40.0)
    found = held_codes(counts, groups, rows, score)
    assert len(found) == 1
    h = found[0]
    assert (h.channel, h.code, sorted(h.visits.tolist())) == ("y", 1535, sorted(HELD))
    assert h.n_at_code == h.n_samples == len(HELD) * N and h.p_value < 0.01
    # the y channel reads nothing between the held visits (1535) and the lowest other visit (>= 1560 - noise)
    assert h.missing_above is not None and h.missing_above[0] == 1536 and h.missing_above[1] >= 1545
    assert "ADC code 1535 of channel y holds 4 visit(s)" in h.sentence()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_held_visits_that_fit_as_well_as_the_others_are_no_finding(seed: int) -> None:
    """Holding alone proves little (a quiet channel holds visits by chance): only visits that carry the residual count."""
    counts, groups, rows, score = campaign(seed, held_score=3.0)
    assert held_codes(counts, groups, rows, score) == []


def test_one_held_visit_is_never_enough_and_averaged_counts_are_not_judged() -> None:
    counts, groups, rows, score = campaign(4, held_score=1e3)
    one = ~np.isin(groups, HELD[1:])  # only the first held visit is left
    assert held_codes(counts[one], groups[one], rows[one], score[one]) == []  # p >= 1/visits, above alpha/codes
    assert held_codes(counts + 0.25, groups, rows, score) == []  # not integers: no ADC codes to judge


@pytest.mark.parametrize("seed", [2, 3])
def test_a_clean_simulated_campaign_reports_no_held_code(seed: int) -> None:
    """The board simulator without wide codes (every named effect off, the measured run's grid): nothing reported."""
    assert _diagnosed({}, seed).held_codes == []  # diagnose(simulate_recording(_config({}), seed=seed))


def test_the_simulator_wide_code_is_found_where_it_holds_the_extreme_visits() -> None:
    """The simulator's ``adc_wide_codes`` over the y channel's lowest visits of a repeated grid (156 visits): those
    visits read one code, the model cannot follow them, and diagnose names the code."""
    extra = {"scenario.poses.repeat": 2, "scenario.poses.grid.theta_step_deg": 30.0, "scenario.poses.dwell_s": 2.0}
    clean = simulate_recording(_config(extra), seed=4)
    low = clean.xyz[clean.pose_id >= 0, 1].min()
    res = diagnose(simulate_recording(_config({**extra, "effects.adc_wide_codes.scale": 1.0,
                                                "effects.adc_wide_codes.codes": [[int(low), 14]]}), seed=4))
    assert [(h.channel, h.code) for h in res.held_codes] == [("y", int(low))]
    h = res.held_codes[0]
    assert len(h.visits) >= 3 and h.rmse_without[1] < 0.9 * res.after_heldout_rmse[1]  # y carries it (sim y axis)
    assert any(w.startswith(f"ADC code {int(low)} of channel y") for w in res.warnings)


def test_the_modal_code_of_every_visit_at_once_is_np_unique_s_of_each() -> None:
    """``adc_codes.modal_codes`` (every visit's most read code and its count, from one sort) against ``np.unique`` of
    each visit's counts, its first most counted code: ties to the smallest code, visits of one sample, gaps between
    the visits, codes far apart, zeros of both signs."""
    from fbg_accel_calibration.fit.adc_codes import modal_codes

    rng = np.random.default_rng(0)
    for trial in range(200):
        m = int(rng.integers(1, 40))
        n = rng.integers(1, 30, m)
        starts = np.cumsum(np.r_[0, (n + rng.integers(0, 5, m))[:-1]]) + int(rng.integers(0, 3))
        v = rng.integers(-3, 4, int(starts[-1] + n[-1] + 5)).astype(float) * float(rng.choice([1.0, 1000.0]))
        if trial % 3 == 0:
            v[rng.random(len(v)) < 0.2] = -0.0
        each = [np.unique(v[s:s + k], return_counts=True) for s, k in zip(starts, n, strict=True)]
        codes, at_code = modal_codes(v, starts, n)
        assert codes.tolist() == [int(u[np.argmax(c)]) for u, c in each]
        assert at_code.tolist() == [int(c.max()) for _, c in each]
    assert [len(a) for a in modal_codes(np.zeros(3), np.zeros(0, int), np.zeros(0, int))] == [0, 0]



def test_a_held_code_s_noise_is_the_median_of_every_visit_s_scatter_on_its_channel(monkeypatch) -> None:
    """The noise a held code reports (``HeldCode.sigma_counts``) is the median standard deviation of every visit's
    counts on its channel (the held visits and the others), worked out only for a channel where a code held a visit:
    the channels without one cost no pass over their visits."""
    from fbg_accel_calibration.fit import adc_codes

    counts, groups, rows, score = campaign(1, held_score=40.0)
    passes = []  # the loops over a channel's visits (each zips their starts and lengths)

    def counted(starts: np.ndarray, n: np.ndarray, strict: bool) -> zip:
        passes.append(len(starts))
        return zip(starts, n, strict=strict)

    monkeypatch.setattr(adc_codes, "zip", counted, raising=False)
    found = held_codes(counts, groups, rows, score)
    monkeypatch.undo()
    assert [h.channel for h in found] == ["y"]
    y = counts[:, 2]
    assert found[0].sigma_counts == float(np.median([y[groups == g].std() for g in range(V)]))
    assert passes == [V]  # over the one channel where a code held visits
