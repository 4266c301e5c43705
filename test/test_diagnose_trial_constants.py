"""What the diagnosis keeps across a search's trials to spare their CPU (the digest of a search's rows, the thermal
lag's filter coefficient of each run, the powers of the held low-pass's closed forms): the values it would work out
again, bit for bit, and never a value kept for other inputs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fbg_accel_calibration.diagnosis.data import DiagnosisData, Inputs, group_index, rows_digest
from fbg_accel_calibration.diagnosis.effects import ThermalLagEffect
from fbg_accel_calibration.diagnosis.held_lowpass import _powers, held_cascade, held_lowpass, held_rows
from fbg_accel_driver.correction_terms import sample_steps, uniform_coefficient

DT = 0.01


def fresh_digest(rows: np.ndarray) -> str:
    """The digest of ``rows``' values, worked out from a new writable copy (never kept)."""
    return rows_digest(np.array(rows, copy=True))


def test_the_digest_kept_for_read_only_rows_is_theirs_and_never_another_array_s() -> None:
    data = two_rate_lag_data()
    rows = np.arange(0, 3000, 7)
    rows.flags.writeable = False
    key = data.rows_key(rows)
    assert key == fresh_digest(rows) and data.rows_key(rows) == key
    assert data._row_keys[id(rows)] == (rows, key)  # kept with the array, by the recording's cache
    # arrays made and dropped one after the other (numpy reuses their memory, so their address): each its own digest
    for k in range(1, 40):
        other = np.arange(0, 3000, 7) + k
        other.flags.writeable = False
        assert data.rows_key(other) == fresh_digest(other) != key
        del other
    # the same values in another array: the same key (what is kept by the key is shared)
    same = np.arange(0, 3000, 7)
    same.flags.writeable = False
    assert data.rows_key(same) == key


def test_rows_that_can_change_are_digested_on_every_call() -> None:
    data = two_rate_lag_data()
    rows = np.arange(0, 3000, 7)
    key = data.rows_key(rows)
    rows[5] += 1  # written in place: a writable array is digested again
    assert data.rows_key(rows) == fresh_digest(rows) != key
    base = np.arange(0, 3000, 7)
    view = base[:]
    view.flags.writeable = False  # read-only, but its memory is written through ``base``
    key = data.rows_key(view)
    base[0] = 1
    assert data.rows_key(view) == fresh_digest(view) != key


def test_a_read_only_array_made_writable_again_is_digested_again() -> None:
    data = two_rate_lag_data()
    rows = np.arange(0, 3000, 7)
    rows.flags.writeable = False
    key = data.rows_key(rows)
    rows.flags.writeable = True
    rows[0] = 2
    assert data.rows_key(rows) == fresh_digest(rows) != key


def test_the_search_evaluator_keeps_its_rows_read_only_in_its_own_memory() -> None:
    from fbg_accel_calibration.diagnosis.search import Evaluator

    data = two_rate_lag_data()
    sub = np.flatnonzero(data.use)[::5]
    ev = Evaluator(data, np.zeros(len(data.t_s), int), np.ones(3), data.group, sub)
    assert not ev.sub.flags.writeable and ev.sub.base is None and np.array_equal(ev.sub, sub)
    sub[0] = 1  # the caller's array is its own
    assert ev.sub[0] != 1


def two_rate_lag_data() -> DiagnosisData:
    """Two runs of a temperature reading at the AHT10's resolution, the second sampled twice as slowly (another filter
    coefficient for the same time constant), poses held 150-400 samples between moves."""
    rng = np.random.default_rng(3)
    pose, run = [], []
    for r in range(2):
        for p in range(8):
            move, hold = int(rng.integers(20, 60)), int(rng.integers(150, 400))
            pose.append(np.r_[np.full(move, -1), np.full(hold, p)])
            run.append(np.full(move + hold, r))
    pose_id, run_id = np.concatenate(pose), np.concatenate(run)
    n = len(pose_id)
    t = np.empty(n)
    for r, step in ((0, DT), (1, 2 * DT)):
        at = run_id == r
        t[at] = 100.0 * r + step * np.arange(np.count_nonzero(at))
    temp = np.round(25.0 + 2.0 * np.sin(np.arange(n) / 300.0) + rng.normal(0, 0.004, n), 2)
    gref = np.tile([0.0, 0.0, 9.80665], (n, 1))
    ref = 3000.0 + rng.normal(0, 5, n)
    return DiagnosisData(t, ref, gref * ref[:, None] * 1e-3, temp, gref, pose_id, run_id, pose_id >= 0)


def test_the_thermal_lag_s_kept_coefficients_are_those_of_each_run_and_time_constant() -> None:
    """``ThermalLagEffect.transform_rows`` keeps each run's filter coefficient per time constant: trials of several
    time constants on one recording whose runs are sampled differently give, bit for bit, what each gives on a
    recording that has kept nothing, and each run its own coefficient (the filter over every sample)."""
    data = two_rate_lag_data()
    steps = data.run_steps()
    assert uniform_coefficient(2.0, steps[0]) != uniform_coefficient(2.0, steps[1])
    eff = ThermalLagEffect()
    rows = np.flatnonzero(data.use)[::3]
    for h in (2.0, 0.5, -3.0, 2.0, -0.4, 400.0, 0.5):
        part = Inputs.of(data).at(rows)
        assert eff.transform_rows(data, Inputs.of(data), part, h, rows)
        cold_data = replace(data)  # the same arrays, nothing kept
        cold = Inputs.of(cold_data).at(rows)
        assert eff.transform_rows(cold_data, Inputs.of(cold_data), cold, h, rows)
        assert part.temp_c.tobytes() == cold.temp_c.tobytes()
        full = Inputs.of(data)
        eff.transform(data, full, h)
        np.testing.assert_allclose(part.temp_c, full.temp_c[rows], rtol=0, atol=1e-11)
        data.drop_recent()  # the lagged reading itself is kept per time constant: this test is of the coefficients


@pytest.mark.parametrize("c", [0.0, 0.1, 0.5, 0.9, 0.999, 1.0 - 1e-9, 1.0])
def test_the_powers_looked_up_are_those_worked_out(c: float) -> None:
    rng = np.random.default_rng(int(c * 1000))
    for k in (rng.integers(0, 3000, 50_000).astype(float), np.arange(5.0), np.zeros(0), np.zeros(10),
              rng.integers(0, 10**6, 100).astype(float), np.full(1000, 2999.0)):
        assert _powers(c, k).tobytes() == np.power(c, k).tobytes()


def test_the_held_filters_with_looked_up_powers_are_those_with_every_power_worked_out(monkeypatch) -> None:
    """``held_lowpass`` and ``held_cascade`` give the same values bit for bit with every power of the closed forms
    worked out (``np.power``), on rows that fall some thousands into holds of some hundreds of samples."""
    rng = np.random.default_rng(8)
    parts = []
    for _ in range(30):
        parts += [rng.normal(size=int(rng.integers(5, 40))), np.full(int(rng.integers(100, 600)), rng.normal())]
    x = np.concatenate(parts)
    rows = np.arange(len(x))[::2]
    held = held_rows(x, rows)
    assert len(held.in_hold) > 2 * (held.in_hold_steps.max() + 1)  # the lookup is taken
    a = uniform_coefficient(0.05, sample_steps(DT * np.arange(len(x))))
    got = (held_lowpass(held, x[held.samples], a), *held_cascade(held, x[held.samples], a))
    from fbg_accel_calibration.diagnosis import held_lowpass as module

    monkeypatch.setattr(module, "_powers", np.power)
    want = (held_lowpass(held, x[held.samples], a), *held_cascade(held, x[held.samples], a))
    for g, w in zip(got, want, strict=True):
        assert g.tobytes() == w.tobytes()


@pytest.mark.parametrize("high", [3, 400, 10**8])
def test_the_groups_counted_are_those_a_sort_finds(high: int) -> None:
    """The gain tests group the searched rows (fold order, visit ids) by counting each id, not by sorting: the same
    groups and the same row-to-group map as ``np.unique``, whatever the ids (a sparse or a negative one: by the sort)."""
    rng = np.random.default_rng(high)
    for n in (0, 1, 7, 5000):
        for low in (0, -2):
            labels = rng.integers(low, high, n)
            want, got = np.unique(labels, return_inverse=True), group_index(labels)
            assert got[0].dtype == want[0].dtype and got[1].dtype == want[1].dtype
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])


def test_the_paired_gain_test_s_visit_means_are_group_mse_s() -> None:
    """``paired_gain_test`` works out the groups and the weighted squares of both residuals once: its gain and p-value
    are those from ``group_mse`` of each residual on the rows where both are finite, bit for bit."""
    from scipy import stats

    from fbg_accel_calibration.diagnosis.data import finite_rows
    from fbg_accel_calibration.diagnosis.search import group_mse, paired_gain_test

    rng = np.random.default_rng(2)
    n = 4000
    groups = np.repeat(np.arange(40), 100)
    res0 = rng.normal(0, 1.0, (n, 3))
    res1 = res0 * 0.9 + rng.normal(0, 0.2, (n, 3))
    res0[rng.random(n) < 0.05, 1] = np.nan
    res1[rng.random(n) < 0.05, 2] = np.nan
    rows = rng.random(n) < 0.9
    weights = np.array([1.0, 2.0, 0.5])
    r = rows & finite_rows(res0) & finite_rows(res1)
    d = group_mse(res0, groups, r, weights)[1] - group_mse(res1, groups, r, weights)[1]
    tot0 = float(np.sum(res0[r] ** 2 * weights))
    gain = (tot0 - float(np.sum(res1[r] ** 2 * weights))) / tot0
    p = float(stats.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue)
    got = paired_gain_test(res0, res1, groups, rows, weights, 0.01)
    assert got[0] == gain and got[1] == p and got[2] == 40


def test_the_dark_offset_at_the_searched_rows_is_the_one_over_every_sample() -> None:
    """A design whose last correction of the inputs is the reference's dark offset and whose columns read only its
    rows subtracts the offset at those rows alone (``ReferenceDarkOffsetEffect.transform_rows``): the same design,
    valid rows and inputs there bit for bit as the offset subtracted at every sample; after the read-noise filter
    too, and with an offset that leaves some references at or below 0 (those rows not valid)."""
    from fbg_accel_calibration.diagnosis.design import DesignCache, ModelSpec, _corrected_inputs, build_design
    from fbg_accel_calibration.diagnosis.effects import ReferenceDarkOffsetEffect, ReferenceReadNoiseEffect

    data = two_rate_lag_data()
    rows = np.flatnonzero(data.use)[::4]
    dark = ReferenceDarkOffsetEffect()
    low = float(np.sort(data.ref[rows])[10])
    for before in ([], [(ReferenceReadNoiseEffect(), 0.05)]):
        for h in (-200.0, 0.0, 35.5, low, 3000.0):
            spec = ModelSpec(1, 25.0, 2.0, [*before, (dark, h)])
            want = build_design(data, spec, None, rows)
            cache = DesignCache()
            got = build_design(data, spec, cache, rows)
            assert got.X.tobytes() == want.X.tobytes() and np.array_equal(got.valid, want.valid)
            assert got.G.tobytes() == want.G.tobytes()
            inp, part = next(iter(cache.inputs.values()))
            assert inp is None and part.counts_changed  # the rows alone were corrected
            full = _corrected_inputs(data, spec.effects)
            assert np.array_equal(part.valid, full.valid[rows]) and part.ref.tobytes() == full.ref[rows].tobytes()
            if h == 3000.0 or (h == low and not before):
                assert not want.valid.all()


def test_the_read_noise_filter_kept_per_time_constant_is_that_of_the_recorded_counts() -> None:
    """``ReferenceReadNoiseEffect.transform`` keeps the filtered reference counts of the recording per time constant
    (``DiagnosisData.recent``): asked again with a value kept, the same array (read-only) with the values of a
    recording that has kept nothing, bit for bit, and each run filtered from its own start; a time constant not kept
    and counts that are not the recording's (an earlier correction's) are filtered afresh, never served the kept ones."""
    from fbg_accel_calibration.diagnosis.effects import ReferenceReadNoiseEffect
    from fbg_accel_driver.correction_terms import first_order_lowpass

    data = two_rate_lag_data()
    eff = ReferenceReadNoiseEffect()

    def filtered(d: DiagnosisData, h: float, inp: Inputs | None = None) -> Inputs:
        inp = Inputs.of(d) if inp is None else inp
        eff.transform(d, inp, h)
        return inp

    first = filtered(data, 0.05)
    assert not first.ref.flags.writeable and first.counts_changed
    for h in (0.05, 0.2, 0.05, 0.2):
        got = filtered(data, h)
        cold = filtered(replace(data), h)  # the same arrays, nothing kept
        assert got.ref.tobytes() == cold.ref.tobytes() and np.array_equal(got.valid, cold.valid)
        run = data.runs()[1]  # the second run filtered from its own first sample
        want = first_order_lowpass(data.ref[run], data.t_s[run], h, {})
        np.testing.assert_allclose(got.ref[run], want, rtol=1e-13)
    assert filtered(data, 0.05).ref is filtered(data, 0.05).ref  # kept, not filtered again
    assert filtered(data, 0.05).ref.tobytes() != filtered(data, 0.2).ref.tobytes()
    # counts an earlier correction changed (a copy of other values): filtered from those, not the kept ones
    other = Inputs.of(data)
    other.ref = data.ref * 1.5
    got = filtered(data, 0.05, other)
    assert got.ref.tobytes() == filtered(replace(data), 0.05, replace(Inputs.of(data), ref=data.ref * 1.5)).ref.tobytes()
    assert got.ref.tobytes() != filtered(data, 0.05).ref.tobytes()


def test_the_fitted_temperature_levels_are_clustered_once_and_are_those_of_the_fitted_samples() -> None:
    """``DiagnosisData.fitted_temperature_levels`` (what the degree chosen again after each added effect reads):
    ``thermal_fit.temperature_levels`` of the fitted samples' temperatures, the same arrays (read-only) on every call,
    and the level count the candidates read is theirs."""
    from fbg_accel_calibration.fit.thermal_fit import temperature_levels

    data = two_rate_lag_data()
    data.temp_c[~data.use] = 80.0  # a level the samples in motion alone would make: not one of the fitted samples'
    labels, means = data.fitted_temperature_levels()
    want = temperature_levels(data.temp_c[data.use])
    assert labels.dtype == np.int32 and np.array_equal(labels, want[0]) and means.tobytes() == want[1].tobytes()
    assert not labels.flags.writeable and not means.flags.writeable
    again = data.fitted_temperature_levels()
    assert again[0] is labels and again[1] is means
    assert data.temperature_level_count() == max(len(want[1]), 1) >= 2


def test_the_spectral_nonlinearity_s_visit_means_kept_give_its_verdicts_bit_for_bit() -> None:
    """``SpectralNonlinearityEffect``'s non-linear part and bound read the visits' mean Psi and mean reference, kept
    once per recording: for fits of several coefficients, the same parts bit for bit and the same verdicts as
    worked out from every sample on a recording that has kept nothing."""
    import math

    from fbg_accel_calibration.diagnosis.data import visit_means
    from fbg_accel_calibration.diagnosis.effects import SpectralNonlinearityEffect, nonlinearity_bound_mps2
    from fbg_accel_driver.correction_terms import quadratic_features

    rng = np.random.default_rng(11)
    pose, g = [], []
    for p in range(14):
        u = rng.normal(size=3)
        pose.append(np.r_[np.full(15, -1), np.full(120, p)])
        g.append(np.tile(9.80665 * u / np.linalg.norm(u), (135, 1)))
    pose_id, gref = np.concatenate(pose), np.concatenate(g)
    n = len(pose_id)
    ref = 3000.0 + rng.normal(0, 5, n)
    xyz = (gref * 2e-3 + 0.5) * ref[:, None] + rng.normal(0, 0.5, (n, 3))
    data = DiagnosisData(DT * np.arange(n), ref, xyz, np.full(n, 25.0), gref, pose_id, np.zeros(n, int), pose_id >= 0)
    eff = SpectralNonlinearityEffect()

    def by_every_sample(d: DiagnosisData, coeff: np.ndarray) -> tuple[np.ndarray, float]:
        rows = d.use & (d.group >= 0)
        psi = visit_means(d.group, rows, Inputs.normalised(d.xyz, d.ref))
        psi = psi[np.all(np.isfinite(psi), axis=1)]
        contrib = quadratic_features(psi, eff._psi0(d)) @ coeff.T
        A = np.column_stack([np.ones(len(psi)), psi])
        gm = visit_means(d.group, rows & np.all(np.isfinite(d.gref), axis=1), d.gref)
        bound = nonlinearity_bound_mps2(float(np.max(np.linalg.norm(gm, axis=1)))) if len(gm) else math.inf
        return contrib - A @ np.linalg.lstsq(A, contrib, rcond=None)[0], bound

    M0 = np.eye(3)
    verdicts = set()
    for scale in (1e-3, 1.0, 1e3, 1e-3, 30.0):
        coeff = scale * rng.normal(size=(3, 6))
        want, bound = by_every_sample(replace(data), coeff)
        assert eff.nonlinear_part(coeff, data).tobytes() == want.tobytes()
        verdict = eff.implausible(None, coeff, data, M0)
        assert verdict == eff.implausible(None, coeff, replace(data), M0)
        assert bool(verdict) == bool(np.any(np.max(np.abs(want), axis=0) > bound))
        verdicts.add(bool(verdict))
    assert verdicts == {True, False}
    assert {"visit_mean_psi", "nonlinearity_bound_mps2"} <= set(data._memo)  # kept, not worked out on every fit


def test_the_recorded_psi_kept_at_a_search_s_rows_is_theirs_and_only_for_recorded_counts() -> None:
    """``DiagnosisData.psi_at``: the recorded counts' Psi at read-only rows, kept per rows (the same array on the next
    call, another for other rows) and the values of ``Inputs.normalised`` at them bit for bit; writable rows are worked
    out on every call. A design at a search's rows takes it only where its corrections leave the counts as recorded:
    with a dark offset of the reference, or its read-noise filter, its columns are those of the corrected counts (the
    design over every sample at those rows, bit for bit)."""
    from fbg_accel_calibration.diagnosis.design import DesignCache, ModelSpec, build_design
    from fbg_accel_calibration.diagnosis.effects import ReferenceDarkOffsetEffect, ReferenceReadNoiseEffect

    data = two_rate_lag_data()
    rows = np.array(np.flatnonzero(data.use)[::3])  # of their own memory, as a search's (``search.Evaluator``)
    rows.flags.writeable = False
    other = np.array(np.flatnonzero(data.use)[1::3])
    other.flags.writeable = False
    want = Inputs.normalised(data.xyz[rows], data.ref[rows])
    psi = data.psi_at(rows)
    assert psi.tobytes() == want.tobytes() and not psi.flags.writeable and data.psi_at(rows) is psi
    assert data.psi_at(other).tobytes() == Inputs.normalised(data.xyz[other], data.ref[other]).tobytes()
    writable = np.array(rows, copy=True)
    assert data.psi_at(writable).tobytes() == want.tobytes() and data.psi_at(writable) is not psi
    for effects in ([], [(ReferenceDarkOffsetEffect(), 40.0)], [(ReferenceReadNoiseEffect(), 0.05)]):
        spec = ModelSpec(1, 25.0, 2.0, effects)
        got = build_design(data, spec, DesignCache(), rows)
        every = build_design(replace(data), spec, None, None)
        assert np.ascontiguousarray(got.X).tobytes() == np.ascontiguousarray(every.X[rows]).tobytes()
        assert np.array_equal(got.valid, every.valid[rows])
    assert sum(k.startswith("psi_at") for k in data._memo) == 2  # the two read-only rows' (the designs' among them)

def test_a_kept_value_no_longer_fresh_is_let_go_on_the_next_call_for_any_key() -> None:
    """``DiagnosisData.recent``: an entry whose ``fresh`` says it no longer stands for its key (what it was made of is
    gone) is dropped on the next call, whatever key that call asks for, before its value is made; one still fresh
    is served as kept."""
    data = two_rate_lag_data()
    made: list[str] = []

    def make(name: str) -> str:
        made.append(name)
        return name

    alive = {"a": True}
    assert data.recent(("a",), lambda: make("a"), fresh=lambda _: alive["a"]) == "a"
    assert data.recent(("b",), lambda: make("b")) == "b"
    assert data.recent(("a",), lambda: make("a"), fresh=lambda _: alive["a"]) == "a" and made == ["a", "b"]
    alive["a"] = False
    seen_by_b: list[list[tuple]] = []
    data.recent(("c",), lambda: seen_by_b.append(list(data._recent)) or make("c"))
    assert seen_by_b == [[("b",)]]  # gone before "c" was made
    assert list(data._recent) == [("b",), ("c",)]


def test_the_hysteresis_column_at_a_search_s_rows_is_its_column_of_every_sample_there(monkeypatch) -> None:
    """``ThermalHysteresisEffect.columns_at`` carries each run's decisions on to a search's rows alone (no branch of
    every sample made, ``ThermalHysteresis.branch`` not called): bit for bit the column of every sample at those rows,
    rows in any order, of one run or both, and the driver's branch of each run from its own start; so is the block of
    a design built on those rows."""
    from fbg_accel_calibration.diagnosis.design import ModelSpec, build_design
    from fbg_accel_calibration.diagnosis.effects import ThermalHysteresisEffect
    from fbg_accel_driver.correction_terms import ThermalHysteresis

    data = two_rate_lag_data()
    eff = ThermalHysteresisEffect()
    inp = Inputs.of(data)
    rng = np.random.default_rng(4)
    rows = np.flatnonzero(data.use)[::3]
    for h in (0.05, 0.3, 2.0):
        every = eff.columns(data, inp, h)
        driver = np.concatenate([ThermalHysteresis.branch(data.temp_c[run], data.t_s[run], h, eff.deadband(h),
                                                          ThermalHysteresis(np.zeros(3), h, 1.0).new_state())
                                 for run in data.runs()])
        assert every.shape == (len(data.t_s), 1) and every[:, 0].tobytes() == driver.tobytes()
        assert {-1.0, 1.0} <= set(every[rows, 0].tolist())
        with monkeypatch.context() as m:
            m.setattr(ThermalHysteresis, "branch", None)  # the rows' values without the branch of every sample
            for at in (rows, rng.permutation(rows), rows[rows < data.runs()[0].stop], rows[rows >= data.runs()[1].start]):
                got = eff.columns_at(data, inp, h, at)
                assert got.shape == (len(at), 1) and got.tobytes() == every[at].tobytes()
            spec = ModelSpec(0, 25.0, 1.0, [(eff, h)])
            des = build_design(data, spec, sub=rows)
        assert des.X[:, des.blocks[eff.name]].tobytes() == np.ascontiguousarray(every[rows]).tobytes()


def test_the_read_noise_filter_of_one_run_is_the_filter_s_own_output(monkeypatch) -> None:
    """Of a recording of one run, ``ReferenceReadNoiseEffect.transform`` gives the filter's output array itself (no
    copy of every sample into another array); of several runs each run filtered from its own start, every sample
    written (``test_the_read_noise_filter_kept_per_time_constant_is_that_of_the_recorded_counts``)."""
    from fbg_accel_calibration.diagnosis import effects
    from fbg_accel_calibration.diagnosis.effects import ReferenceReadNoiseEffect

    two = two_rate_lag_data()
    one = replace(two, run_id=np.zeros_like(two.run_id), group=None)
    assert len(one.runs()) == 1
    made = []

    def spy(*args, **kwargs) -> np.ndarray:
        made.append(effects.first_order_lowpass.__wrapped__(*args, **kwargs))
        return made[-1]

    spy.__wrapped__ = effects.first_order_lowpass
    monkeypatch.setattr(effects, "first_order_lowpass", spy)
    inp = Inputs.of(one)
    ReferenceReadNoiseEffect().transform(one, inp, 0.05)
    assert len(made) == 1 and inp.ref is made[0]
    want = spy.__wrapped__(one.ref, one.t_s, 0.05, {})
    assert inp.ref.tobytes() == want.tobytes()
    inp = Inputs.of(two)
    ReferenceReadNoiseEffect().transform(two, inp, 0.05)
    assert inp.ref.tobytes() == np.concatenate(made[1:]).tobytes() and len(made) == 3
