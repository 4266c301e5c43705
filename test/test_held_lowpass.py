"""The low-pass of a held signal at chosen rows (``diagnosis.held_lowpass``) against the filter over every sample
(``correction_terms.first_order_lowpass``), and the TIA candidate's reference worked out with it against the same
reference worked out over every sample."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fbg_accel_calibration.diagnosis import chain_effects
from fbg_accel_calibration.diagnosis.chain_effects import TiaLowpassEffect
from fbg_accel_calibration.diagnosis.data import DiagnosisData, Inputs, expected_psi_map
from fbg_accel_calibration.diagnosis.effects import ReferenceReadNoiseEffect
from fbg_accel_calibration.diagnosis.held_lowpass import held_cascade, held_lowpass, held_rows
from fbg_accel_driver.correction_terms import first_order_lowpass, sample_steps, uniform_coefficient

DT = 0.01


def held_signal(rng: np.random.Generator, n: int, first_held: bool, last_held: bool) -> np.ndarray:
    """(n,) holds of 1-300 samples (some back to back) between stretches that move every sample, as the table's
    reference between poses; starting and ending with a hold or with motion."""
    parts: list[np.ndarray] = []
    held = first_held
    while sum(len(p) for p in parts) < n:
        if held:
            parts.append(np.full(int(rng.integers(1, 300)), rng.normal()))
            held = rng.random() < 0.3  # two holds of other values back to back
        else:
            parts.append(rng.normal(size=int(rng.integers(1, 40))))
            held = True
    x = 5.0 + 3.0 * np.concatenate(parts)[:n]
    if last_held:
        x[-40:] = x[-40]
    return x


@pytest.mark.parametrize("first_held,last_held", [(True, True), (False, False), (True, False), (False, True)])
@pytest.mark.parametrize("min_hold", [1, 2, 16, 1000])
def test_the_rows_of_a_held_signal_are_those_of_the_filter_over_every_sample(first_held: bool, last_held: bool,
                                                                             min_hold: int) -> None:
    rng = np.random.default_rng(min_hold + 10 * first_held + 20 * last_held)
    n = 3000
    x = held_signal(rng, n, first_held, last_held)
    t = 100.0 + DT * np.arange(n)
    steps = sample_steps(t)
    every = np.arange(n)
    # the edge rows (the first and last sample, each hold's first and last sample, the sample after a hold), a thinned
    # set (every k-th) and every sample
    edges = np.flatnonzero(np.diff(x) != 0)
    for rows in (np.unique(np.concatenate([[0, 1, n - 1], edges, edges + 1, edges[edges > 0] - 1])), every[::15],
                 every[7::4], every):
        held = held_rows(x, rows, min_hold)
        assert held.busy[0] == 0 and (min_hold > 300 or len(held.start) > 0)  # holds are at most 300 long
        for tau in (1e-4, 0.003, DT, 0.05, 0.3, 3.0, 100.0):  # from 1e-2 to 1e4 samples
            a = uniform_coefficient(tau, steps)
            assert a is not None
            want = first_order_lowpass(x, t, tau, {}, steps)[rows]
            got = held_lowpass(held, x[held.samples], a)
            # the same recursion but for rounding: c^L for L multiplications, the scan's order of products
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * np.max(np.abs(x)))


@pytest.mark.parametrize("first_held,last_held", [(True, True), (False, False)])
@pytest.mark.parametrize("min_hold", [1, 16])
def test_two_low_passes_in_cascade_at_the_rows_are_those_over_every_sample(first_held: bool, last_held: bool,
                                                                           min_hold: int) -> None:
    """``held_cascade``: the low-pass and the same low-pass of it (the thermal lag's rate estimate) at a search's rows,
    from the holds in closed form, against both filters over every sample; its first output is ``held_lowpass``'s."""
    rng = np.random.default_rng(7 + min_hold + 10 * first_held)
    n = 3000
    x = held_signal(rng, n, first_held, last_held)
    t = DT * np.arange(n)
    steps = sample_steps(t)
    edges = np.flatnonzero(np.diff(x) != 0)
    for rows in (np.unique(np.concatenate([[0, 1, n - 1], edges, edges + 1])), np.arange(n)[5::11], np.arange(n)):
        held = held_rows(x, rows, min_hold)
        for tau in (1e-4, DT, 0.3, 100.0):
            a = uniform_coefficient(tau, steps)
            y = first_order_lowpass(x, t, tau, {}, steps)
            z = first_order_lowpass(y, t, tau, {}, steps)
            got_y, got_z = held_cascade(held, x[held.samples], a)
            assert np.array_equal(got_y, held_lowpass(held, x[held.samples], a))
            np.testing.assert_allclose(got_z, z[rows], rtol=0, atol=1e-13 * np.max(np.abs(x)))
            if DT <= tau <= 1.0:  # the second filter changes something to get right
                assert np.max(np.abs(z - y)) > 1e-3


def test_a_signal_without_a_hold_and_a_signal_that_is_one_hold() -> None:
    t = DT * np.arange(500)
    steps = sample_steps(t)
    rows = np.arange(0, 500, 7)
    for x in (np.random.default_rng(3).normal(size=500), np.full(500, 2.5), np.r_[1.0, np.full(499, 2.5)]):
        held = held_rows(x, rows)
        for tau in (0.02, 1.0):
            got = held_lowpass(held, x[held.samples], uniform_coefficient(tau, steps))
            np.testing.assert_allclose(got, first_order_lowpass(x, t, tau, {}, steps)[rows], rtol=0, atol=1e-13 * 2.5)


def test_a_sampling_that_changes_the_coefficient_has_none() -> None:
    t = np.r_[DT * np.arange(100), 1.0 + 0.02 * np.arange(1, 100)]
    assert uniform_coefficient(0.1, sample_steps(t)) is None
    assert uniform_coefficient(0.1, sample_steps(DT * np.arange(100))) == pytest.approx(1 - np.exp(-DT / 0.1), rel=1e-12)


def tia_data() -> DiagnosisData:
    """Two runs of poses held 150-400 samples with the table's motion between them (the reference moves every
    sample), a reference of counts with read noise."""
    rng = np.random.default_rng(5)
    g, pose, run = [], [], []
    for r in range(2):
        for p in range(12):
            u = rng.normal(size=3)
            u *= 9.80665 / np.linalg.norm(u)
            move = int(rng.integers(20, 60))
            start = g[-1][-1] if g else u
            g.append(start + np.linspace(0, 1, move)[:, None] * (u - start))
            pose.append(np.full(move, -1))
            hold = int(rng.integers(150, 400))
            g.append(np.tile(u, (hold, 1)))
            pose.append(np.full(hold, p))
            run.append(np.full(move + hold, r))
    gref = np.concatenate(g)
    pose_id, run_id = np.concatenate(pose), np.concatenate(run)
    n = len(gref)
    M = np.array([[2e-3, 1e-4, 0.0], [0.0, 2.1e-3, 2e-4], [1e-4, 0.0, 1.9e-3]])
    ref = 3000.0 + rng.normal(0, 5, n)
    xyz = (gref @ M.T + 0.5) * ref[:, None] + rng.normal(0, 0.5, (n, 3))
    t = DT * np.arange(n)
    t[run_id == 1] += 50.0  # the second run later on the board's clock
    use = pose_id >= 0
    return DiagnosisData(t, ref, xyz, np.full(n, 25.0), np.where(use[:, None], gref, np.nan), pose_id, run_id, use,
                         gref_filled=gref)


def tia_reference_over_every_sample(data: DiagnosisData, inp: Inputs, h: float) -> np.ndarray:
    """The TIA candidate's reference (N, 3) by its definition: the expected Psi of the reference (the recorded one, or
    the one an earlier correction moved), each column through its low-pass over every sample of each run, mapped
    back."""
    P, q = expected_psi_map(data, inp) if inp.counts_changed else data.static_psi_map()
    g = inp.gref if inp.gref_moved else data.gref_filled
    psi = g @ P.T + q
    lp = np.empty_like(psi)
    tau = TiaLowpassEffect().taus(h)
    for run in data.runs():
        for j in range(3):
            lp[run, j] = first_order_lowpass(np.ascontiguousarray(psi[run, j]), data.t_s[run], tau[j + 1], {})
    return g + (lp - psi) @ np.linalg.inv(P).T


@pytest.fixture(params=[97, None], ids=["blocks", "one_block"])
def row_block(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """The rows the TIA's reference over every sample is worked out at a time: blocks that split its runs (and their
    holds) anywhere, and the default (None: a block longer than these runs)."""
    if request.param is not None:
        monkeypatch.setattr(chain_effects, "ROW_BLOCK", request.param)


@pytest.mark.parametrize("read_noise", [None, 0.05])
def test_the_tia_reference_at_the_searched_rows_is_the_one_over_every_sample(read_noise: float | None,
                                                                             row_block: None) -> None:
    """The TIA candidate filters the samples in motion only (the holds in closed form): the reference of filtering
    every sample, up to rounding, with the recorded counts and with the counts an earlier correction changed (the
    reference's read-noise filter: another expected Psi); and a row's value is the same bit for bit at a search's
    rows and when every sample is asked for (a correction of the reference after it reads every sample), whatever
    blocks of rows the latter is worked out in."""
    data = tia_data()
    eff = TiaLowpassEffect()
    rows = np.flatnonzero(data.use)[::9]
    largest = 0.0
    for h in (*eff.hyper_grid(data)[::4], 1.0):
        inp = [Inputs.of(data), Inputs.of(data)]
        if read_noise is not None:
            for i in inp:
                ReferenceReadNoiseEffect().transform(data, i, read_noise)
        got = eff.reference_at(data, inp[0], h, rows)
        assert any(k.startswith("held_reference") for k in data._memo)  # the held path was taken
        np.testing.assert_allclose(got[0], tia_reference_over_every_sample(data, inp[0], float(h))[rows], rtol=0,
                                   atol=1e-12)
        eff.transform(data, inp[1], h)
        np.testing.assert_array_equal(got[0], inp[1].gref[rows])
        np.testing.assert_array_equal(got[1], inp[1].valid[rows])
        largest = max(largest, float(np.max(np.abs(got[0] - data.gref_filled[rows]))))
    assert largest > 0.1  # m/s^2: the filter corrects the reference (a test of the filter, not of the reference alone)


def test_the_tia_reference_over_every_sample_makes_no_array_of_its_length_but_the_result(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Over every sample (the final model's design, a correction of the reference after the TIA's) the reference is
    worked out a block of rows at a time: the memory it takes beyond its result (N, 3) is a block's and the holds',
    not arrays of the series' length (at 10^6 samples each is 8-24 MiB, and a dozen of them were the searches' peak)."""
    import tracemalloc

    monkeypatch.setattr(chain_effects, "ROW_BLOCK", 256, raising=False)
    data = replace(tia_data(), temp_c=np.full(len(tia_data().t_s), 25.0))
    eff = TiaLowpassEffect()
    eff.transform(data, Inputs.of(data), 0.5)  # the recording's constants it keeps (the expected Psi's map, ...)
    inp = Inputs.of(data)
    tracemalloc.start()
    try:
        eff.transform(data, inp, 1.0)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # beyond the result: a block's arrays, and the holds and the filter's states there, in proportion to the samples
    # in motion (an eighth of these); arrays of every sample (the rows' places in the holds, the reference at them,
    # each column filtered) took about 5x the result
    result = inp.gref.nbytes + inp.valid.nbytes
    assert peak < 2.5 * result, (peak, result)


def test_the_delayed_reference_is_interpolated_where_it_moved_only_and_is_the_same_bit_for_bit() -> None:
    """The channel delay's reference (``ChannelDelayEffect``) interpolated near the table's moves only, elsewhere the
    held value itself: the values of ``interp_columns`` at t - D over every sample, bit for bit, for delays of a
    fraction of a sample to many samples, at a search's rows and at every sample (both runs)."""
    from fbg_accel_calibration.diagnosis.chain_effects import ChannelDelayEffect
    from fbg_accel_calibration.diagnosis.data import interp_columns

    data = tia_data()
    eff = ChannelDelayEffect()
    rows = np.flatnonzero(data.use)[::9]
    for D in (1e-9, 0.3 * DT, DT, 2.5 * DT, 0.1, 1.7):
        want, want_valid = np.empty((len(data.t_s), 3)), np.ones(len(data.t_s), bool)
        for run in data.runs():
            t = data.t_s[run]
            want[run] = interp_columns(t - D, t, data.gref_filled[run])
            want_valid[run] = t - D >= t[0]
        every, valid = eff.reference_at(data, Inputs.of(data), D, None)
        assert np.array_equal(every, want) and np.array_equal(valid, want_valid & Inputs.of(data).valid)
        at_rows, valid_rows = eff.reference_at(data, Inputs.of(data), D, rows)
        assert np.array_equal(at_rows, want[rows]) and np.array_equal(valid_rows, (want_valid & Inputs.of(data).valid)[rows])
        inp = Inputs.of(data)
        eff.transform(data, inp, D)
        assert np.array_equal(inp.gref, want)
        for run in data.runs():  # a stretch per motion: the samples each move reaches, and those only
            t, f = data.t_s[run], data.gref_filled[run]
            c = np.flatnonzero(np.any(f[1:] != f[:-1], axis=1))
            reach = np.minimum(np.searchsorted(t, t[c + 1] + D, side="right") + 1, len(t))
            by_move = np.zeros(len(t), bool)
            for a, b in zip(c + 1, reach, strict=True):
                by_move[a:b] = True
            start, stop = ChannelDelayEffect._near_a_move(data, run, D)
            near = np.zeros(len(t), bool)
            for a, b in zip(start, stop, strict=True):
                assert not near[a:b].any()  # disjoint
                near[a:b] = True
            assert np.array_equal(near, by_move) and np.all(np.diff(start) > 0)
            if D == DT:
                assert 0 < near.mean() < 0.5  # the held samples are not interpolated


def test_the_delayed_reference_looks_its_times_up_from_the_delay_s_steps_not_by_search(monkeypatch) -> None:
    """A trial of the channel delay finds where each t - D falls from the samples D is (``interval_of``'s guess),
    checked by comparisons: the points ``np.searchsorted`` bisects for are the motions' few (their reach), not the
    samples interpolated near the moves (the same values: the test above)."""
    from fbg_accel_calibration.diagnosis.chain_effects import ChannelDelayEffect

    data = tia_data()
    eff = ChannelDelayEffect()
    rows = np.flatnonzero(data.use)[::9]
    real = np.searchsorted
    searched: list[int] = []

    def spy(a, v, *args, **kwargs):
        searched.append(np.size(v))
        return real(a, v, *args, **kwargs)

    for D in (0.3 * DT, DT, 2.5 * DT, 0.1):
        data = replace(data)  # nothing kept of another delay
        searched.clear()
        with monkeypatch.context() as m:
            m.setattr(np, "searchsorted", spy)
            eff.reference_at(data, Inputs.of(data), D, None)
            eff.reference_at(data, Inputs.of(data), D, rows)
        interpolated = sum(int(np.sum(b - a)) for run in data.runs()
                           for a, b in zip(*ChannelDelayEffect._near_a_move(data, run, D), strict=True))
        motions = sum(len(ChannelDelayEffect._near_a_move(data, run, D)[0]) for run in data.runs())
        assert interpolated > 20 * motions and sum(searched) <= 4 * motions + len(rows), (sum(searched), motions)


@pytest.mark.parametrize("D", [0.3 * DT, 2.5 * DT, 0.1])
def test_the_tia_reference_on_a_delayed_reference_is_the_one_over_every_sample(D: float, row_block: None) -> None:
    """On the channel delay's reference (its holds shortened by the delay after each move) the TIA candidate filters
    the samples in motion only too: the reference of filtering every sample of the delayed reference, up to rounding,
    at a search's rows and at every sample, a row the same bit for bit both ways; the holds found once for a delayed
    reference and kept while it lives (a TIA search on top of a delay asks on every trial), not for another."""
    from fbg_accel_calibration.diagnosis.chain_effects import ChannelDelayEffect

    data = tia_data()
    eff, delay = TiaLowpassEffect(), ChannelDelayEffect()
    rows = np.flatnonzero(data.use)[::9]
    delayed = Inputs.of(data)
    delay.transform(data, delayed, D)
    assert delayed.gref_moved and not np.array_equal(delayed.gref, data.gref_filled)
    largest = 0.0
    for h in (*eff.hyper_grid(data)[::5], 1.0):
        inp = replace(delayed, valid=delayed.valid.copy())  # as a search's trials: the same delayed reference
        got = eff.reference_at(data, inp, h, rows)
        kept = [k for k in data._recent if k[0] == "held_reference"]
        assert [k[1] for k in kept] == [id(delayed.gref)] * len(data.runs())  # the held path, its holds kept
        want = tia_reference_over_every_sample(data, delayed, float(h))
        np.testing.assert_allclose(got[0], want[rows], rtol=0, atol=1e-12)
        every = replace(delayed, valid=delayed.valid.copy())
        eff.transform(data, every, h)
        np.testing.assert_allclose(every.gref, want, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(got[0], every.gref[rows])
        np.testing.assert_array_equal(got[1], every.valid[rows])
        np.testing.assert_array_equal(got[1], delayed.valid[rows])
        largest = max(largest, float(np.max(np.abs(got[0] - delayed.gref[rows]))))
    assert largest > 0.1  # m/s^2: the filter corrects the delayed reference
    # another delay: its own holds, not those kept for the first
    other = Inputs.of(data)
    delay.transform(data, other, 2 * D)
    got = eff.reference_at(data, other, 1.0, rows)
    np.testing.assert_allclose(got[0], tia_reference_over_every_sample(data, other, 1.0)[rows], rtol=0, atol=1e-12)



def test_the_holds_kept_for_a_delayed_reference_go_with_it() -> None:
    """The holds a TIA trial keeps for a delayed reference (``DiagnosisData.recent``) are let go once that reference
    is gone, before the next trial's are made: a search over the delay under the TIA (a new delayed series on each
    trial) holds the holds of the series it works on, not those of the trials before it beside them."""
    from fbg_accel_calibration.diagnosis.chain_effects import ChannelDelayEffect

    data = tia_data()
    eff, delay = TiaLowpassEffect(), ChannelDelayEffect()
    rows = np.flatnonzero(data.use)[::9]
    for D in (0.3 * DT, 2.5 * DT, 0.1, 0.2):
        delayed = Inputs.of(data)  # the trial before's series is dropped here, as a search's cache drops it
        delay.transform(data, delayed, D)
        got = eff.reference_at(data, delayed, 1.0, rows)
        kept = [k for k in data._recent if k[0] == "held_reference"]
        assert [k[1] for k in kept] == [id(delayed.gref)] * len(data.runs())
        want = tia_reference_over_every_sample(data, delayed, 1.0)
        np.testing.assert_allclose(got[0], want[rows], rtol=0, atol=1e-12)

def lag_data() -> DiagnosisData:
    """Two runs of a temperature reading at the AHT10's resolution (0.01 degC) ramping up and down through 4 degC, with
    its reading noise (holds of a few samples to hundreds between its changes)."""
    rng = np.random.default_rng(11)
    data = tia_data()
    n = len(data.t_s)
    temp = np.round(25.0 + 2.0 * np.sin(np.arange(n) / 900.0) + rng.normal(0, 0.004, n), 2)
    return replace(data, temp_c=temp)


def test_the_thermal_lag_at_the_searched_rows_is_the_one_over_every_sample() -> None:
    """The thermal lag of the temperature reading at a search's rows alone (``ThermalLagEffect.transform_rows``: its
    filters over the reading's holds in closed form) against ``transform`` over every sample, for the optics lagging
    (one low-pass) and the AHT10 lagging (the rate through two in cascade), in both runs; and a design whose
    columns read only its rows takes it (the same design up to rounding), one with the hysteresis's branch (which
    reads every sample) does not."""
    from fbg_accel_calibration.diagnosis.design import DesignCache, ModelSpec, build_design
    from fbg_accel_calibration.diagnosis.effects import ThermalHysteresisEffect, ThermalLagEffect

    data = lag_data()
    eff = ThermalLagEffect()
    rows = np.flatnonzero(data.use)[::9]
    assert np.count_nonzero(np.diff(data.temp_c)) > 0.05 * len(data.t_s)  # the reading moves, the holds are short
    for h in (-40.0, -3.0, -0.2, 0.05, 2.0, 60.0):
        full, part = Inputs.of(data), Inputs.of(data).at(rows)
        eff.transform(data, full, h)
        assert eff.transform_rows(data, Inputs.of(data), part, h, rows)
        np.testing.assert_allclose(part.temp_c, full.temp_c[rows], rtol=0, atol=1e-11)
        assert part.temp_changed and np.max(np.abs(full.temp_c - data.temp_c)) > 0.01  # the lag moves the reading
        spec = ModelSpec(2, 25.0, 5.0).plus(eff, h)
        want = build_design(data, spec, None, rows).X
        cache = DesignCache()
        np.testing.assert_allclose(build_design(data, spec, cache, rows).X, want, rtol=1e-9, atol=1e-12)
        assert next(iter(cache.inputs.values()))[0] is None  # the rows alone were corrected
        both = spec.plus(ThermalHysteresisEffect(), 10.0)
        cache = DesignCache()
        np.testing.assert_array_equal(build_design(data, both, cache, rows).X, build_design(data, both, None, rows).X)
        assert next(iter(cache.inputs.values()))[0] is not None  # the whole series was corrected


def test_the_holds_at_the_searched_rows_are_let_go_when_the_searches_end() -> None:
    """The holds the TIA's reference and the thermal lag keep for a search's rows (read by every trial of the search)
    are constants for the trials alone (``DiagnosisData.once(..., for_trials=True)``): ``drop_recent``, when the
    searches end, forgets them; asked for again they are made again, the values the same."""
    from fbg_accel_calibration.diagnosis.effects import ThermalLagEffect

    data = lag_data()
    rows = np.flatnonzero(data.use)[::9]
    tia, lag = TiaLowpassEffect(), ThermalLagEffect()
    ref = tia.reference_at(data, Inputs.of(data), 1.0, rows)[0]
    part = Inputs.of(data).at(rows)
    assert lag.transform_rows(data, Inputs.of(data), part, 2.0, rows)
    kinds = ("held_reference", "temperature holds")
    assert all(any(k.startswith(kind) for k in data._memo) for kind in kinds)
    runs = data.runs()
    data.drop_recent()
    assert not any(k.startswith(kinds) for k in data._memo)
    assert data.runs() is runs  # a constant of the recording, not of the trials alone, is kept
    again = Inputs.of(data).at(rows)
    assert lag.transform_rows(data, Inputs.of(data), again, 2.0, rows)
    assert np.array_equal(tia.reference_at(data, Inputs.of(data), 1.0, rows)[0], ref)
    assert np.array_equal(again.temp_c, part.temp_c)


def test_the_expected_psi_map_kept_per_correction_is_that_of_those_counts() -> None:
    """The TIA's reference on top of the read-noise filter in a cached design (``design._corrected_reference``) takes
    the expected Psi map of the filtered counts kept under the filter's (name, tau) (``data.psi_map_of``): the same
    designs bit for bit as on a recording that has kept nothing, for several filters asked in turn and again, each
    its own map; inputs whose counts were replaced after they were named are never served the named map."""
    from fbg_accel_calibration.diagnosis.data import psi_map_of
    from fbg_accel_calibration.diagnosis.design import DesignCache, ModelSpec, build_design

    data = tia_data()
    rows = np.flatnonzero(data.use)[::7]
    rows.flags.writeable = False
    noise, tia = ReferenceReadNoiseEffect(), TiaLowpassEffect()
    cache = DesignCache(references=1)  # every reference worked out again from the kept maps
    for tau_ref, h in ((0.05, 1.0), (0.2, 1.0), (0.05, 0.5), (0.2, 2.0), (0.05, 1.0)):
        spec = ModelSpec(1, 25.0, 2.0, [(noise, tau_ref), (tia, h)])
        got = build_design(data, spec, cache, rows)
        cold_data = replace(data)  # the same arrays, nothing kept
        want = build_design(cold_data, spec, None, rows)  # every sample filtered, no cache
        assert got.G.tobytes() == want.G.tobytes() and np.array_equal(got.valid, want.valid)
        assert not any(k.startswith("expected_psi_map") for k in cold_data._memo)
    kept = sorted(k for k in data._memo if k.startswith("expected_psi_map"))
    assert len(kept) == 2  # one map per filter, worked out once
    # counts named, then replaced: the map of the new counts
    inp = Inputs.of(data)
    noise.transform(data, inp, 0.05)
    inp.counts_of = ((("reference_read_noise", 0.05),), inp.ref, inp.xyz)
    assert psi_map_of(data, inp)[0].tobytes() == expected_psi_map(data, inp)[0].tobytes()
    inp.ref = inp.ref * 1.01 + 3.0
    want = expected_psi_map(data, inp)
    got = psi_map_of(data, inp)
    assert got[0].tobytes() == want[0].tobytes() and got[1].tobytes() == want[1].tobytes()
    assert got[1].tobytes() != psi_map_of(data, replace(Inputs.of(data), ref=data.ref))[1].tobytes()
