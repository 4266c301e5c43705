"""Disturbed samples at the END of a visit are measured, reported and kept out of the noise floor (issue 8).

When the table's readings (pose label and reference) lag the signal, or the chain is delayed against them, the last
samples of every visit were taken while the table already moved to the next pose. The settling measurement compared
the k-th sample from a visit's start with the k-th from its end but only looked for a positive excess (the start), and
the floor trimmed only the start: with the readings 0.3 s late in the simulator the y floor rose from 0.094 to
0.41 m/s^2 and the verdict was "no significant unexplained residual"; on the measured series with the angle labels
shifted by one sample the x floor went from 0.125 to 0.61 m/s^2. The end is now measured like the start (amplitude,
extent, 3 standard errors, either sign of the excess), reported, and trimmed with the start's rule.

Synthetic recordings from ``test_diagnose_visits.campaign`` (known white noise ``sigma``, a first-order chain that
leaves a transient at every visit's start) and the simulator's grid (as in ``test_diagnose_sim``).
"""

from __future__ import annotations

import numpy as np
import pytest
from test_diagnose_sim import _config, _diagnosed
from test_diagnose_visits import M_TRUE, campaign

from fbg_accel_calibration.diagnosis.diagnose import diagnose
from fbg_accel_calibration.diagnosis.floor import settle_window, settled_mask, settling_transient
from fbg_accel_calibration.io.recording import Recording
from fbg_accel_calibration.reports.diagnose_report import markdown, text
from fbg_accel_sim.board_physics import simulate_recording

END_WORDS = "ends of visits disturbed"


def _sim(seed: int) -> Recording:
    return simulate_recording(_config({}), seed=seed)


def _readings_late(rec: Recording, k: int) -> Recording:
    """The recording with the table's readings (pose label, reference) ``k`` samples late against the signal."""
    out = rec.select(slice(None))
    out.pose_id = np.r_[np.full(k, rec.pose_id[0]), rec.pose_id[:-k]]
    out.gref_mps2 = np.r_[np.repeat(rec.gref_mps2[:1], k, 0), rec.gref_mps2[:-k]]
    return out


def _end_disturbed(rec: Recording, axis: int, amp: float, m: int) -> Recording:
    """``campaign``'s recording with ``amp`` m/s^2 on ``axis`` growing as (j / m)^2 over the last ``m`` samples of every
    visit (the table starting to move before its reading changes), put into the counts through the true matrix."""
    pid = rec.pose_id
    last = np.flatnonzero((pid >= 0) & np.r_[(pid[1:] != pid[:-1]) | (rec.run_id[1:] != rec.run_id[:-1]), True])
    da = np.zeros((len(pid), 3))
    for e in last:
        j = np.arange(m)
        da[e - j, axis] = amp * ((m - j) / m) ** 2
    out = rec.select(slice(None))
    out.xyz = rec.xyz + rec.ref[:, None] * np.linalg.solve(M_TRUE, da.T).T
    return out


def test_settled_mask_drops_the_end_of_a_visit_when_asked() -> None:
    t = np.arange(10) * 0.25
    groups = np.array([0] * 5 + [1] * 5)
    every = np.ones(10, bool)
    # no end window (the default): the end of a visit is kept
    np.testing.assert_array_equal(settled_mask(t, groups, every, 0.25), settled_mask(t, groups, every, 0.25, None))
    # an end window of 0: the last sample goes; 0.3 s: the last two (0 and 0.25 s before the last)
    np.testing.assert_array_equal(settled_mask(t, groups, every, 0.0, 0.0),
                                  [False, True, True, True, False, False, True, True, True, False])
    np.testing.assert_array_equal(settled_mask(t, groups, every, 0.5, 0.3),
                                  [False, False, True, False, False, False, False, True, False, False])


# seeds 2 and 3: bench/seed_sweeps.py (further synthetic campaigns of the same design)
@pytest.mark.parametrize("seed", [1, pytest.param(2, marks=pytest.mark.sweep), pytest.param(3, marks=pytest.mark.sweep)])
@pytest.mark.parametrize("lag", [4, 8])
def test_readings_late_against_the_signal_are_trimmed_and_reported(seed: int, lag: int) -> None:
    """Readings 80 or 160 ms late (moves of 200 ms): the end of every visit holds part of the next move. The floor
    stays the per-sample noise, the end is detected with a positive amplitude, and the report says so."""
    rec, sigma, _ = campaign(seed)
    res = diagnose(_readings_late(rec, lag), static="table", max_effects=1)
    st = res.settling
    assert st.end_detected and np.max(st.end_amplitude_mps2) > 3 * sigma, st.summary()
    assert st.end_n_dropped >= res.n_groups  # at least the last sample of every visit
    assert np.all(np.abs(res.noise_floor / sigma - 1) < 0.15), (res.noise_floor, st.summary())
    assert np.all(st.end_residual_after_settle_mps2 <= 0.101 * np.max(res.noise_floor)), st.summary()
    assert END_WORDS in markdown(res) and END_WORDS in text(res)
    assert any(END_WORDS in w for w in res.warnings), res.warnings


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_an_end_disturbance_on_any_axis_of_either_sign_is_measured(axis: int, sign: float) -> None:
    """0.8 m/s^2 (8 sigma) over the last 10 samples (0.2 s) of every visit, on one axis: detected on that axis
    (amplitude within a factor 2 of the true one at the last sample, the others small), trimmed, floor unharmed; the
    start transient of the chain is still measured."""
    rec, sigma, _ = campaign(axis + 1)
    res = diagnose(_end_disturbed(rec, axis, sign * 0.8, 10), static="table", max_effects=1)
    st = res.settling
    assert st.end_detected, st.summary()
    assert 0.4 < st.end_amplitude_mps2[axis] < 1.6, st.end_amplitude_mps2
    assert np.argmax(st.end_amplitude_mps2) == axis, st.end_amplitude_mps2
    assert st.detected  # the start transient (tau 0.12 s) is still there and measured
    assert np.all(np.abs(res.noise_floor / sigma - 1) < 0.15), (res.noise_floor, st.summary())


# seeds 2..8: bench/seed_sweeps.py (each a clean campaign of the same design; a check that calls a clean end
# disturbed calls it so on most of them)
@pytest.mark.parametrize("seed", [1, *(pytest.param(s, marks=pytest.mark.sweep) for s in range(2, 9))])
def test_clean_synthetic_recordings_trim_no_end(seed: int) -> None:
    """No end disturbance (the chain's start transient only): no end is reported or trimmed (false alarm about 1 % per
    recording: 3 standard errors, two-sided, three axes)."""
    rec, _, _ = campaign(seed)
    res = diagnose(rec, static="table", max_effects=1)
    st = res.settling
    assert not st.end_detected and st.end_n_dropped == 0 and st.end_settle_s is None, (seed, st.summary())
    assert st.detected, (seed, st.summary())
    assert END_WORDS not in markdown(res)


# seeds 1, 3 and 4: bench/seed_sweeps.py. Seed 2's diagnosis is the clean one that
# test_simulated_table_readings_late_do_not_raise_the_floor compares with (``_diagnosed``: computed once)
@pytest.mark.parametrize("seed", [pytest.param(1, marks=pytest.mark.sweep), 2,
                                  *(pytest.param(s, marks=pytest.mark.sweep) for s in (3, 4))])
def test_clean_simulated_recordings_trim_no_end(seed: int) -> None:
    """The simulator with every named effect off: no end reported or trimmed, the summary says so."""
    res = _diagnosed({}, seed)
    st = res.settling
    assert not st.end_detected and st.end_n_dropped == 0, (seed, st.summary())
    assert "first or the last sample" in st.summary(), st.summary()
    assert not any(END_WORDS in w for w in res.warnings), res.warnings


# seed 1: bench/seed_sweeps.py. The two seeds tell the same (largest floor / clean floor 1.038 / 1.029 at 0.1 s late,
# 1.011 / 1.015 at 0.3 s, ends detected at 0.3 s on both); seed 1's 0.1 s case also fits the reference low-pass, which
# costs 5 s of its 7 and plays no part in the floor
@pytest.mark.parametrize("seed", [pytest.param(1, marks=pytest.mark.sweep), 2])
@pytest.mark.parametrize("lag", [10, 30])
def test_simulated_table_readings_late_do_not_raise_the_floor(seed: int, lag: int) -> None:
    """The simulator's grid with the readings 0.1 or 0.3 s late: the floor stays within 15 % of the clean recording's
    (it went from 0.094 to 0.41 m/s^2 on y at 0.3 s) and, where the end holds more than the noise, it is reported."""
    clean = _diagnosed({}, seed)  # the clean recording's diagnosis, shared with the test above
    res = diagnose(_readings_late(_sim(seed), lag))
    assert np.all(res.noise_floor < 1.15 * clean.noise_floor), (res.noise_floor, clean.noise_floor,
                                                                res.settling.summary())
    if lag == 30:
        assert res.settling.end_detected, res.settling.summary()
        assert any(END_WORDS in w for w in res.warnings), res.warnings
        # and the ends are out of the floor: the reason the floor stays within the 15 % above
        assert res.settling.end_n_dropped >= res.settling.n_visits, res.settling.summary()


@pytest.mark.parametrize("end", [False, True])
def test_a_marginal_unresolved_transient_trims_only_the_sample_where_it_is_significant(end: bool) -> None:
    """A synthetic residual: white noise (sigma 0.1 m/s^2, 60 visits of 100 samples at 100 Hz) and, on y, the first
    (or the last) sample of every visit raised by the smallest step that makes it significant; the next position is
    pure noise. The transient is detected but not resolved, and the upper bound of its time constant from the
    detection limit at the next position grows without limit as the excess nears that limit (0.49 s at the start,
    1e7 s at the end here): extrapolated, it trimmed 1.2 s (the start) and 1.6 s (the end, MAX_SETTLE_S), more than
    whole visits of 1 s (the simulator's clean 1 s visits at 100 Hz lost all but one sample). It must trim only the
    position where it is significant: the first (or last) sample of each visit."""
    rng = np.random.default_rng(0)
    n_visits, n, dt, sigma = 60, 100, 0.01, 0.1
    groups = np.repeat(np.arange(n_visits), n)
    t = np.arange(n_visits * n) * dt + groups * 1.0  # a second's move between visits
    rows = np.ones(len(t), bool)
    noise = rng.normal(0.0, sigma, (len(t), 3))
    at = np.arange(n_visits) * n + (n - 1 if end else 0)
    for step in np.arange(0.0, 0.3, 0.002):  # the smallest step detected: barely significant
        res = noise.copy()
        res[at, 1] += step
        st = settling_transient(res, t, groups, rows)
        if st.end_detected if end else st.detected:
            break
    detected, resolved, tau = ((st.end_detected, st.end_tau_resolved, st.end_tau_s) if end
                               else (st.detected, st.tau_resolved, st.tau_s))
    assert detected and not resolved, st.summary()
    amp = st.end_amplitude_mps2 if end else st.amplitude_mps2
    assert tau * np.log(np.max(amp) / (0.1 * sigma)) > 20 * dt, (tau, amp)  # what the loose bound would trim
    assert not (st.detected if end else st.end_detected), st.summary()  # the other end: noise only
    window = settle_window(st, np.full(3, sigma), end=end)
    assert window == 0.0, window
    kept = settled_mask(t, groups, rows, 0.0 if end else window, window if end else None)
    assert np.sum(~kept) == (2 if end else 1) * n_visits  # the first sample (and, the end disturbed, the last) of each visit


@pytest.mark.parametrize("disturbed", [False, True], ids=["ends-kept", "ends-disturbed"])
def test_the_floor_worked_out_beside_the_settling_measurement_is_the_one_worked_out_after_it(disturbed: bool) -> None:
    """With a second thread (two lanes) the first noise floor is worked out, with the visits' ends kept, while the
    settling transient is measured, and used only when the ends prove undisturbed; otherwise it is worked out again
    with them trimmed. Either way the floor, the windows and the result are those of one thread, bit for bit."""
    rec, _, _ = campaign(2)
    if disturbed:
        rec = _end_disturbed(rec, 1, 0.8, 10)
    one, two = (diagnose(rec, static="table", max_effects=1, lanes=n) for n in (1, 2))
    assert two.settling.end_detected == disturbed
    assert np.array_equal(one.noise_floor, two.noise_floor)
    assert (one.settling.settle_s, one.settling.end_settle_s, one.n_floor_samples) == \
        (two.settling.settle_s, two.settling.end_settle_s, two.n_floor_samples)
    assert [a[:2] for a in one.added] == [a[:2] for a in two.added]
    assert np.array_equal(one.residual_after, two.residual_after, equal_nan=True)
