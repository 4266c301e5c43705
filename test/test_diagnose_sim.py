"""Diagnosis on simulator recordings with an undeclared effect (issue 4).

The simulator (``fbg_accel_sim.board_physics.simulate_recording``, batch API, no ROS)
injects one named effect that the declared model (eq. 28) does not have. ``diagnose`` must rank it
first, add it, and bring the held-out error within 1.5x the noise floor. With every named effect off
the declared model is exact up to noise and nothing may be added (several seeds). With the
``unmodelled_cable_torque`` (not in the library) a significant unexplained residual must be reported.

Each scenario is a short experiment designed so that the effect can show at all, as one would design
the calibration run: the source power must change for a dark offset to matter, the temperature must
go up and down for thermal lag and hysteresis, the table must move briskly (and the samples taken
while it moves must be used) to see a 20-40 ms channel delay. Effect sizes above nominal (``scale``)
keep the test short; nominal sizes need hours of data.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from fbg_accel_calibration.diagnosis.diagnose import diagnose
from fbg_accel_calibration.diagnosis.floor import VisitNoise
from fbg_accel_calibration.diagnosis.search import MIN_SEARCH_INFORMATION, SEARCH_ROWS, Refusal, search_samples
from fbg_accel_calibration.io.recording import Recording
from fbg_accel_calibration.io.table_geometry import table_specific_force
from fbg_accel_calibration.reports.diagnose_report import markdown, ordinal, settling_measurements, write_plots
from fbg_accel_driver.correction_terms import ReferenceLowpass
from fbg_accel_driver.thermal_model import ThermalCalibration
from fbg_accel_sim.board_physics import simulate_recording
from fbg_accel_sim.scenario import grid_poses
from fbg_accel_sim.sim_config import SimConfig

NAMED = ("reference_dark_offset", "thermal_lag", "spectral_nonlinearity", "time_drift", "channel_delay", "tia_lowpass",
         "thermal_hysteresis", "unmodelled_cable_torque")
# Every named effect off: the declared model is exact up to noise (white + bias instability of Table 2).
BASELINE = {f"effects.{k}.scale": 0.0 for k in NAMED}
# 7 x 6 poses of the measured run's table (theta and psi in 60 degree steps), 3 s dwell, 1 s moves.
GRID = {"scenario.poses.mode": "grid", "scenario.poses.dwell_s": 3.0, "scenario.poses.move_s": 1.0,
        "scenario.poses.grid.theta_step_deg": 60.0, "scenario.poses.grid.psi_step_deg": 60.0}
# Chamber cycled twice 20 <-> 30 degC with a fast housing (60 s instead of 5000 s) so 8 minutes suffice.
THERMAL = {"scenario.rate_hz": 25.0, "scenario.poses.repeat": 3, "thermal.optics_time_constant_s": 60.0,
           "scenario.temperature.profile": [{"ramp_to_c": 30.0, "duration_s": 120.0}, {"ramp_to_c": 20.0, "duration_s": 120.0},
                                            {"ramp_to_c": 30.0, "duration_s": 120.0}, {"ramp_to_c": 20.0, "duration_s": 120.0}]}

SCENARIOS = {
    # name: (effect scale, extra config, sample selection of diagnose)
    "reference_dark_offset": (4.0, {"effects.source_power_wander.relative_sigma": 0.02}, "table"),
    "thermal_lag": (0.25, THERMAL, "table"),
    "spectral_nonlinearity": (2.0, {}, "table"),
    "time_drift": (30.0, {"effects.time_drift.warmup_time_constant_s": 60.0}, "table"),
    "channel_delay": (2.0, {"scenario.poses.move_s": 0.3}, "all"),
    "tia_lowpass": (1.0, {}, "table"),
    "thermal_hysteresis": (10.0, THERMAL, "table"),
}
# Continuous ramps with a turning point: 15 -> 45 -> 15 degC, 600 s each way through a fast 60 s housing, 10 Hz, the
# GRID repeated through the whole run; a first-order thermal lag of 120 s (the simulator's nominal) of the AHT10
# reading behind the optics (LAG) or of the optics behind the reading (LEAD); reference dark offsets of 80 counts
# under a source drift of 4 % rms (about +-8 %). bench/diagnose_robustness.py runs them over 10 seeds each.
RAMP_S, LAG_S = 600.0, 120.0
RAMPS = {"scenario.rate_hz": 10.0, "scenario.poses.repeat": int(2 * RAMP_S / 168.0) + 1,
         "thermal.optics_time_constant_s": 60.0, "scenario.temperature.initial_c": 15.0,
         "thermal.initial_optics_c": 15.0, "scenario.duration_s": 2 * RAMP_S,
         "scenario.temperature.profile": [{"ramp_to_c": 45.0, "duration_s": RAMP_S},
                                          {"ramp_to_c": 15.0, "duration_s": RAMP_S}]}
LAG = {"effects.thermal_lag.scale": 1.0, "effects.thermal_lag.time_constant_s": LAG_S}
LEAD = {**LAG, "effects.thermal_lag.reading_leads": True}
DARK_UNDER_DRIFT = {"effects.reference_dark_offset.scale": 4.0, "effects.source_power_wander.relative_sigma": 0.04}


# Further seeds of a test whose first seed(s) the suite runs (test/conftest.py ``leave_out_sweeps``): each test keeps a
# representative case that fails on the defect it was written for; bench/seed_sweeps.py runs every seed.
SWEEP = pytest.mark.sweep


def _config(extra: dict) -> SimConfig:
    return SimConfig.default().with_overrides({**BASELINE, **GRID, **extra})


_DIAGNOSED: dict[str, object] = {}


def _diagnosed(extra: dict, seed: int, **kwargs):
    """``diagnose(simulate_recording(_config(extra), seed=seed), **kwargs)``, computed once per test run: several tests
    check different things of the same simulated campaign's diagnosis (each only reads the result)."""
    key = json.dumps([extra, seed, kwargs], sort_keys=True)
    if key not in _DIAGNOSED:
        _DIAGNOSED[key] = diagnose(simulate_recording(_config(extra), seed=seed), **kwargs)
    return _DIAGNOSED[key]


@pytest.fixture(scope="module")
def settled_levels_campaign():
    """Three six-position runs (16 / 24 / 45 degC, 10 s dwells), each from power-on, and their diagnosis."""
    from fbg_accel_sim.make_default_calibration import calibration_runs

    rec = calibration_runs(SimConfig.default(), seed=1, dwell_s=10.0, move_s=3.0)
    return rec, diagnose(rec)


@pytest.mark.parametrize("effect", list(SCENARIOS))
def test_injected_effect_is_ranked_first_added_and_brings_error_to_the_floor(effect: str) -> None:
    scale, extra, static = SCENARIOS[effect]
    # diagnose(simulate_recording(_config(...), seed=1), static=static); the hysteresis's is also the first case of
    # test_a_real_thermal_hysteresis_passes_the_step_check
    res = _diagnosed({**extra, f"effects.{effect}.scale": scale}, 1, **({} if static == "table" else {"static": static}))
    first = res.ranked[0]
    assert first.name == effect, [(c.name, round(c.rel_gain, 3), c.p_value) for c in res.ranked]
    assert first.significant
    assert res.added[0][0] == effect
    # the effect was visible on the declared model, and is gone after adding it (held out)
    assert np.max(res.before_heldout_rmse / res.noise_floor) > 1.05
    ratio = res.after_heldout_rmse / res.noise_floor
    assert np.all(ratio <= 1.5), ratio
    assert res.consistency_max_abs_mps2 < 1e-6  # the YAML terms reproduce the fit (driver = offline)


@pytest.mark.parametrize("seed", [11, pytest.param(12, marks=SWEEP), pytest.param(13, marks=SWEEP)])
def test_nothing_injected_nothing_added(seed: int) -> None:
    """No model effect is added. The reference's own ADC rounding (0.29 count rms on ~870 counts, about 0.05 m/s^2
    through eq. 24) is noise in every recording: its remedy, the reference low-pass, may be (+5-6 % held out)."""
    res = _diagnosed({}, seed)
    assert res.added == [], [(c.name, round(c.rel_gain, 3), c.p_value) for c in res.ranked]
    assert all(isinstance(t, ReferenceLowpass) for t in res.calibration.corrections), res.calibration.corrections
    assert not res.structure.significant, res.structure.verdict
    assert np.all(res.after_heldout_rmse <= 1.1 * res.noise_floor)
    assert not any("cannot go below" in w for w in res.warnings)  # 42 visits: a campaign that can add effects


def test_a_clean_ramp_campaign_is_not_called_an_unexplained_residual() -> None:
    """Continuous ramps, every pose revisited ~8 times, nothing injected: the sensor's bias instability (paper Table 2,
    a slow random wander) moves the visit means, which the floor (a mean and a line removed per visit) never sees.
    With the noise alone in the residual test's null hypothesis this seed was "significant unexplained residual" at
    p 8e-5 / 1e-2 on y / z (7 of 10 seeds of bench/diagnose_robustness.py); the slow error, estimated from the
    revisits of each pose, is in it now (``structure.slow_visit_test``)."""
    res = diagnose(simulate_recording(_config(RAMPS), seed=45))
    s = res.structure
    assert not s.significant and np.all(s.pose_chi2_p > 0.05), s.verdict  # threshold: 0.01 / 3
    assert s.slow_revisits > 200 and s.slow_sigma[2] > 0.0  # the slow error is identified


def test_the_bias_wander_between_revisits_is_not_written_as_a_drift_but_a_hysteresis_is() -> None:
    """Clean continuous ramps with the measured board's reference read noise: the sensor's bias instability (paper
    Table 2, flicker-like) wanders between the ~8 revisits of each pose, and a function of time or of the
    temperature's history fitted on the visits around a held-out one predicts part of that wander: on this seed
    time_drift was added (p 8e-8 against a step level of 1.3e-3; 4 of 100 such campaigns had a term added,
    bench/residual_false_alarm.py). Its gain must now be beyond the wander its revisits keep (``checks.wander_gain``):
    here far from it (p ~1). A real thermal hysteresis (0.2 m/s^2 between the branches) on the same ramps is still
    added, far beyond its wander (p ~1e-45), on the ramps sampled at 5 Hz: the check compares visits' held-out gains,
    which the rate barely moves (its p 4.8e-46 at 5 Hz, 8.5e-46 at 10 Hz; with the wander taken off 10 times, 5.4e-33
    and 4.4e-30), and the diagnosis takes 3 s instead of 15."""
    clean = diagnose(simulate_recording(_config({**RAMPS, "noise.reference_noise_counts": 1.0}), seed=69), lanes=1)
    assert [a[0] for a in clean.added] == [], clean.added
    followed = [c for st in clean.steps for c in st.candidates if "not beyond the slow wander" in c.detail]
    assert {c.name for c in followed} >= {"time_drift"}, [(c.name, c.detail) for c in clean.ranked]
    hyst = diagnose(simulate_recording(_config({**RAMPS, "scenario.rate_hz": 5.0, "effects.thermal_hysteresis.scale": 10.0}),
                                       seed=2), lanes=1)
    assert "thermal_hysteresis" in [a[0] for a in hyst.added], hyst.added
    assert np.all(hyst.after_heldout_rmse < 1.1 * hyst.final_floor)


def test_effect_outside_the_library_is_reported_as_unexplained() -> None:
    rec = simulate_recording(_config({"effects.unmodelled_cable_torque.scale": 3.0}), seed=2)
    res = diagnose(rec)
    s = res.structure
    assert s.significant, s.verdict
    assert "significant unexplained residual" in s.verdict
    assert res.rig_terms == [], res.rig_terms  # a function of the table's angles, but no offset of theta
    # its structure: x and y carry it (amplitudes 0.05/0.04/0 m/s^2 x 3), z does not
    assert s.ratio[0] > 1.1 and s.ratio[1] > 1.1
    assert s.pose_chi2_p[0] < 1e-6 and s.pose_chi2_p[1] < 1e-6
    assert s.pose_mean_rms[0] > 2 * s.pose_mean_rms[2]
    assert len(s.per_pose) == res.n_groups and abs(s.per_pose[0]["mean_mps2"][0]) > 0.05
    assert np.all(np.isfinite(s.corr_time)) and np.all(np.isfinite(s.orientation_r2))
    # the report says what would settle it, for the axes that carry it (x and y), not for z
    settle = settling_measurements(res)
    on_axes = [m.split(":")[0].split(" on ")[-1].split(" (")[0] for m in settle]
    assert settle and all("z" not in a for a in on_axes) and any("x" in a for a in on_axes), settle
    assert "Measurements that would settle it" in markdown(res)


@pytest.mark.parametrize(("extra", "seed"), [({"effects.unmodelled_cable_torque.scale": 3.0}, 4),
                                             ({"effects.motion_hysteresis.scale": 0.75}, 12)],
                         ids=["cable-torque", "motion-hysteresis"])
def test_an_effect_outside_the_library_claims_no_term_that_would_stand_in_for_it(extra: dict, seed: int) -> None:
    """Issue 41: a cable the table drags (sin 2 psi, x3) or a motion-history hysteresis (0.3 m/s^2) on the grid. On
    the unchanged code a library term took part of each and was written to the calibration (spectral_nonlinearity
    +18-22 % for the cable; time_drift tau ~20 s or a dark offset for the hysteresis) while the residual stayed
    significant (1.1-1.3x the floor). With the term in, the visits of one direction of gravity still disagree (p
    1e-13 .. 1e-26 on these seeds, against the refusal's 1e-6; the library effects alone leave 7e-4 at the lowest):
    no term is claimed, each refused one is a finding naming what separates them, and the residual is "unexplained"."""
    res = diagnose(simulate_recording(_config(extra), seed=seed))
    assert res.added == [] and res.rig_terms == [], res.added
    refused = [f for f in res.findings if f.kind == "stand_in"]
    assert refused and all("turn the sensor 90 degrees" in f.separates for f in refused), res.findings
    assert res.structure.significant and "significant unexplained residual" in res.structure.verdict
    assert "not claimed" in markdown(res)


def test_an_implausible_best_hyper_value_does_not_hide_a_plausible_one() -> None:
    """Issue 8: the warm-up time constant that fits best on this seed gives a warm-up of 13 m/s^2 cancelled by a
    creep, refused by the plausibility bound; the whole drift was then refused and a dark offset added in its
    place. The hyper-parameter search now keeps to plausible values when there are any."""
    scale, extra, static = SCENARIOS["time_drift"]
    res = _diagnosed({**extra, "effects.time_drift.scale": scale}, 3, static=static)
    first = res.ranked[0]
    assert first.name == "time_drift" and not first.implausible, first.detail
    assert res.added[0][0] == "time_drift"


def test_the_empirical_terms_carry_the_span_they_were_fitted_on() -> None:
    """A time drift and a spectral non-linearity found by the diagnosis are written with the board times and the
    Psi of the samples they were fitted on, so the driver holds them at the edge instead of extrapolating a creep
    to hours after power-on or a quadratic to many g; on the calibration data itself nothing is held."""
    for eff in ("time_drift", "spectral_nonlinearity"):
        scale, extra, static = SCENARIOS[eff]
        res = _diagnosed({**extra, f"effects.{eff}.scale": scale}, 3, static=static)
        term = next(t for t in res.calibration.corrections if t.kind == eff)
        used = res.data.use
        if eff == "time_drift":
            assert term.span_s == (float(res.data.t_s[used].min()), float(res.data.t_s[used].max()))
        else:
            psi = res.data.xyz[used] / res.data.ref[used, None]
            lo, hi = term.psi_span[:, 0], term.psi_span[:, 1]
            assert np.all(lo < psi.min(axis=0)) and np.all(hi > psi.max(axis=0))
            assert np.all(hi - lo < 1.2 * np.ptp(psi, axis=0))
        span = np.zeros((int(used.sum()), 3))
        res.calibration.correction_sum(res.data.ref[used], res.data.xyz[used], res.data.xyz[used] / res.data.ref[used, None],
                                       res.data.temp_c[used], res.data.t_s[used], res.calibration.new_state(), span)
        assert not span.any()


def test_the_chain_s_searches_reach_its_times_at_a_high_sample_rate() -> None:
    """At 500 Hz the TIA grid, bounded at 30 samples, stopped at 0.64 x Table 1 and the channel delay's, at 12
    samples, at 24 ms: the TIA stages were fitted at the edge and a delay that was not injected was added at
    its edge to make up for them. Both searches now reach the chain's times whatever the rate."""
    rec = simulate_recording(_config({"effects.tia_lowpass.scale": 1.0, "scenario.rate_hz": 500.0,
                                      "scenario.poses.grid.theta_step_deg": 90.0,
                                      "scenario.poses.grid.psi_step_deg": 90.0}), seed=5)
    res = diagnose(rec)
    added = dict((name, h) for name, h, _ in res.added)
    assert set(added) == {"tia_lowpass"} and abs(added["tia_lowpass"] - 1.0) < 0.1, res.added


def test_a_thermal_lag_is_not_tried_on_one_temperature_level() -> None:
    """One temperature level: eq. 28 is of degree 0 and has no temperature term, so a lag of the temperature
    cannot act: the candidate is not applicable (it was listed as tested, gain 0, p 1)."""
    thermal = {**THERMAL, "scenario.temperature.profile": [{"ramp_to_c": 22.0, "duration_s": 240.0},
                                                           {"ramp_to_c": 20.0, "duration_s": 240.0}]}
    res = diagnose(simulate_recording(_config({**thermal, "effects.thermal_lag.scale": 0.75}), seed=7))
    assert res.n_levels == 1
    lag = next(c for c in res.ranked if c.name == "thermal_lag")
    assert not lag.applicable and "one temperature level" in lag.reason, (lag.applicable, lag.reason)


@pytest.mark.parametrize("effect", ["thermal_lag", "tia_lowpass"])
def test_a_search_on_thinned_samples_chooses_what_the_full_search_chooses(effect: str, tmp_path: Path) -> None:
    """Issue 8 §7: above ``search_rows`` fitted samples the candidates are evaluated and the model chosen on every
    k-th one, and only the chosen model is fitted on all samples. Forced here at 1/8 of the samples (fewer at 25 Hz,
    where that would keep too little: ``search_samples``): the same effect is added, its hyper-parameter agrees
    within 5 %, the held-out error within 1 %; the contributions the report plots are of every sample, NaN where none
    was evaluated, and the plots are drawn."""
    scale, extra, static = SCENARIOS[effect]
    rec = simulate_recording(_config({**extra, f"effects.{effect}.scale": scale}), seed=1)
    # the full search: below SEARCH_ROWS fitted samples the default searches on every one, so it is the diagnosis of
    # test_injected_effect_is_ranked_first_added_and_brings_error_to_the_floor (computed once, ``_diagnosed``)
    assert len(rec) < SEARCH_ROWS
    full = _diagnosed({**extra, f"effects.{effect}.scale": scale}, 1, **({} if static == "table" else {"static": static}))
    thin = diagnose(rec, static=static, search_rows=2000)
    assert full.settings["search_rows"] is None and full.settings["search_step"] == 1
    assert thin.settings["search_step"] >= 2 and thin.settings["search_rows"] <= len(rec) / 2, thin.settings
    assert [a[0] for a in thin.added] == [a[0] for a in full.added] == [effect]
    assert thin.added[0][1] == pytest.approx(full.added[0][1], rel=0.05)
    np.testing.assert_allclose(thin.after_heldout_rmse, full.after_heldout_rmse, rtol=0.01)
    plotted = [c.delta_of_every_sample(len(rec)) for c in thin.steps[0].candidates if c.delta is not None]
    assert plotted and all(d.shape == (len(rec), 3) for d in plotted)
    assert all(0 < np.isfinite(d[:, 0]).sum() <= thin.settings["search_rows"] for d in plotted)
    drawn = {p.name for p in write_plots(thin, tmp_path, "all")}
    assert {f"candidate_{c.name}.png" for c in thin.steps[0].candidates if c.delta is not None} <= drawn, drawn



@pytest.mark.parametrize("tau", [0.0, 3.0, 20.0, 400.0], ids=["white", "tau-3", "tau-20", "tau-400"])
def test_a_search_is_thinned_only_as_far_as_the_visit_means_keep_their_information(tau: float) -> None:
    """Issue 8 §7: thinning the search to ``search_rows`` must not throw away what decides a choice. Every k-th sample
    of a visit tells less of its mean than all of them, little less while k is within the noise's correlation time,
    1/k for white noise: k is lowered until the thinned samples keep ``MIN_SEARCH_INFORMATION``. Checked against the
    variance of a visit mean worked out from the noise's whole covariance matrix."""
    n_visits, n = 200, 300
    fit_rows = np.ones(n_visits * n, bool)
    folds = np.repeat(np.arange(n_visits) % 10, n)
    lags = np.arange(251)
    acf = np.exp(-lags / tau) if tau else (lags == 0).astype(float)
    every, k, kept = search_samples(fit_rows, folds, 600, VisitNoise(np.ones(3), np.tile(acf, (3, 1))), n)
    cap = math.ceil(n_visits * n / 600)
    R = np.r_[acf, np.zeros(n)][np.abs(np.arange(n)[:, None] - np.arange(n)[None, :])]

    def brute(step: int) -> float:
        idx = np.arange(0, n, step)
        return float((R.sum() / n**2) / (R[np.ix_(idx, idx)].sum() / len(idx) ** 2))

    assert 1 <= k <= cap and kept >= MIN_SEARCH_INFORMATION
    assert brute(k) >= MIN_SEARCH_INFORMATION - 0.02, (k, brute(k))
    assert k == cap or brute(k + 1) < MIN_SEARCH_INFORMATION + 0.02, (k, brute(k + 1))
    assert (k == 1) == (tau == 0.0) and (k == cap) == (tau == 400.0)
    assert len(every) == len(range(0, n_visits * n, k)) and np.all(np.diff(folds[every]) >= 0)
    with pytest.raises(ValueError, match="search_rows must be at least 1"):
        search_samples(fit_rows, folds, 0)


def test_a_slowly_sampled_recording_is_thinned_less_and_the_report_says_how_much_it_keeps() -> None:
    """At 25 Hz the TIA's filtered noise is nearly white from sample to sample: thinning to ``search_rows`` would keep
    a fraction of what the visits' samples tell. The search is thinned less, and the report says what it keeps."""
    scale, extra, static = SCENARIOS["thermal_lag"]
    rec = simulate_recording(_config({**extra, "effects.thermal_lag.scale": scale}), seed=1)
    res = diagnose(rec, static=static, search_rows=1500)
    n_fit = len(res.steps[0].candidates[0].delta_rows) * res.settings["search_step"]
    assert 1 < res.settings["search_step"] < math.ceil(n_fit / 1500) - 1, res.settings
    assert res.settings["search_information"] >= MIN_SEARCH_INFORMATION
    assert f"every {ordinal(res.settings['search_step'])}: they keep {100 * res.settings['search_information']:.0f} %" \
        in markdown(res)
    assert [ordinal(k) for k in (1, 2, 3, 4, 11, 12, 13, 15, 21, 22, 101, 111)] == \
        ["1st", "2nd", "3rd", "4th", "11th", "12th", "13th", "15th", "21st", "22nd", "101st", "111th"]
    assert res.added and res.added[0][0] == "thermal_lag"


def test_the_command_s_search_rows_option_thins_the_search_or_searches_every_sample(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--search-rows N`` thins the search above N fitted samples, ``--search-rows 0`` searches on every one (an
    effect seen only in the first tenths of a second of each visit keeps all its samples), and the help names the
    default and the guard the diagnosis uses."""
    from fbg_accel_calibration.commands.cli import main
    from fbg_accel_calibration.io.mcap_writer import write_recording

    mcap = tmp_path / "run.mcap"
    scale, extra, _ = SCENARIOS["tia_lowpass"]
    write_recording(mcap, simulate_recording(_config({**extra, "effects.tia_lowpass.scale": scale}), seed=1))
    reports = {}
    for n in ("0", "3000"):
        assert main(["diagnose", str(mcap), "--search-rows", n, "--out", str(tmp_path / n / "r.md")]) == 0
        reports[n] = (tmp_path / n / "r.md").read_text()
    assert "evenly spread fitted samples" not in reports["0"]
    step = re.search(r"evenly spread fitted samples, every (\d+)(?:st|nd|rd|th): they keep (\d+) %", reports["3000"])
    assert step and int(step.group(1)) >= 2 and int(step.group(2)) >= 100 * MIN_SEARCH_INFORMATION
    with pytest.raises(SystemExit):
        main(["diagnose", "--help"])
    usage = " ".join(capsys.readouterr().out.split())
    assert f"default {SEARCH_ROWS}" in usage and f"keeps {100 * MIN_SEARCH_INFORMATION:.0f} %" in usage


@pytest.fixture(scope="module")
def chamber_levels():
    """The usual campaign: one six-position run (one file) per chamber level, 16, 24 and 45 degC, nothing injected."""
    from fbg_accel_calibration.io.recording import Recording

    runs = []
    for i, level in enumerate((16.0, 24.0, 45.0)):
        cfg = SimConfig.default().with_overrides({
            **BASELINE, "scenario.poses.mode": "six_position", "scenario.poses.dwell_s": 6.0,
            "scenario.poses.move_s": 2.0, "scenario.poses.repeat": 1, "scenario.temperature.initial_c": level,
            "scenario.temperature.profile": [], "thermal.initial_optics_c": None})
        runs.append(simulate_recording(cfg, seed=10 + i))
    rec = Recording.concatenate(runs)
    return rec, diagnose(rec)


def test_a_run_offset_is_not_fitted_when_each_run_is_its_own_chamber_level(chamber_levels) -> None:
    """Issue 8: with one temperature per run, an offset of each run cannot be told from the temperature dependence
    of eq. 28's b. It was fitted anyway (offsets up to 8.6 m/s^2, told apart only by the AHT10's scatter within a
    run), chosen, and left out of the YAML together with the b(T) it had replaced: the written calibration missed
    its own data by 2.7 / 0.34 / 5.1 m/s^2 while the report said 0.17 / 0.10 / 0.13."""
    rec, res = chamber_levels
    offset = next(c for c in res.ranked if c.name == "run_offset")
    assert not offset.applicable and "not identified on this data" in offset.reason, offset.reason
    assert res.run_terms == []
    # the file as the driver runs it: each run (file) streamed from its start (its terms may be filters)
    output = np.concatenate([_output(res.calibration, rec.select(rec.run_id == r)) for r in np.unique(rec.run_id)])
    u = res.data.use
    rmse = np.sqrt(np.mean((output[u] - rec.gref_mps2[u]) ** 2, axis=0))
    assert np.all(rmse <= 1.2 * res.final_floor), (rmse, res.final_floor)


def test_the_cross_validation_of_a_chamber_campaign_trains_only_models_it_identifies(chamber_levels) -> None:
    """Issue 8: a degree-2 temperature term along a direction is determined only by levels whose poses tilt it.
    One fold held out both +y and -y of the 24 degC run: its training data left the y term to two levels, the
    held-out error of the declared model came out 0.90 / 2.67 / 1.05 m/s^2 (floor 0.17 / 0.09 / 0.12). Then the
    level hold-out re-scored degree 2 on two training levels (28 m/s^2), dropped it for degree 1, and a
    reference dark offset was added to stand in for the missing curvature, on a campaign with nothing injected."""
    _, res = chamber_levels
    assert any("of temperature level 1" in n for n in res.fold_notes), res.fold_notes
    assert np.all(res.before_heldout_rmse <= 1.2 * res.noise_floor), (res.before_heldout_rmse, res.noise_floor)
    assert res.final_degree == 2 and res.calibration.degree == 2
    assert res.added == [], [(c.name, round(c.rel_gain, 3), c.p_value) for c in res.ranked]


def _output(cal: ThermalCalibration, rec: Recording) -> np.ndarray:
    """The calibration file's output (N, 3) m/s^2 of a one-run recording, streamed with state as the driver runs it."""
    return cal.apply_counts(rec.ref, rec.xyz, rec.temp_c, rec.t_s, cal.new_state())


# Every named effect and the bias instability off, 1 s visits: the noise is the TIA-shaped white noise (plus the ADC's
# rounding) alone, correlated over ~0.1 s, i.e. over a good part of a visit.
SHORT_VISITS = {"effects.bias_instability.scale": 0.0, "scenario.poses.dwell_s": 1.0}


@pytest.mark.parametrize("rate_hz", [100.0, 400.0])
def test_the_floor_of_short_visits_is_the_per_sample_noise_and_clean_data_stays_clean(rate_hz: float) -> None:
    """Issue 8: removing a visit's mean and line removes more than two samples' worth of correlated noise (about two
    correlation times' worth), so the pooled within-visit scatter over n - 2 was ~15 % low on 1 s visits, the held-out
    error stood 1.15-1.3x above it, and the AR(1) count of effective samples from the lag-1 correlation put the visit
    means far beyond the noise: a clean recording got a "significant unexplained residual". The truth here is the noise
    itself: the same seed simulated without noise and rounding, both through the diagnosis's calibration."""
    ratios = []
    for seed in (21, 22, 23):
        cfg = {**SHORT_VISITS, "scenario.rate_hz": rate_hz}
        rec = simulate_recording(_config(cfg), seed=seed)
        quiet = simulate_recording(_config({**cfg, "effects.white_noise.scale": 0.0,
                                            "effects.adc_quantisation.scale": 0.0}), seed=seed)
        assert len(quiet) == len(rec)
        res = diagnose(rec)
        assert not res.structure.significant, res.structure.verdict
        assert res.added == [], res.added
        noise = _output(res.calibration, rec) - _output(res.calibration, quiet)
        used = res.data.use & (rec.pose_id >= 0)
        ratios.append(res.final_floor / np.sqrt(np.mean(noise[used] ** 2, axis=0)))  # the floor of what the file outputs
    assert np.all(np.abs(np.mean(ratios, axis=0) - 1.0) < 0.08), np.round(ratios, 3)


def test_the_settling_measurement_keeps_visits_one_sample_shorter_than_the_median(tmp_path: Path) -> None:
    """Issue 8: the settling transient is measured at K sample positions from each end of a visit, K at most a third
    of the median visit, and visits needed 3 K samples: with the grid's dwell one sample (10 ms) shorter at every third
    pose, the 14 visits shorter than the median were all left out (28 of 42 used). A visit needs 2 K + 1 samples (a
    middle to refer to), so every visit counts."""
    poses = [{"name": f"p{i}", "psi_deg": psi, "theta_deg": theta, "dwell_s": 2.99 if i % 3 == 2 else 3.0}
             for i, (psi, theta) in enumerate(grid_poses(60.0, 60.0))]
    plan = tmp_path / "jittered.yaml"
    plan.write_text(yaml.safe_dump({"format": "fbg_accel_pose_plan", "format_version": 1, "move_s": 1.0,
                                    "poses": poses}))
    rec = simulate_recording(_config({"scenario.poses.mode": "plan_file", "scenario.poses.plan_file": str(plan)}),
                             seed=1)
    res = diagnose(rec)
    lengths = np.bincount(res.data.group[res.data.use & (rec.pose_id >= 0)])
    lengths = lengths[lengths > 0]
    assert len(lengths) == 42 and np.sum(lengths < np.median(lengths)) >= 10, np.unique(lengths, return_counts=True)
    assert len(res.settling.age_s) == int(np.median(lengths)) // 3  # K at its bound: a third of the median visit
    assert res.settling.n_visits == 42


def _with_acceleration_error(rec: Recording, da: np.ndarray) -> Recording:
    """``rec`` with an acceleration error ``da`` (N, 3) m/s^2, table frame, put into the axis counts through the
    recording's own small-signal sensitivity (Psi ~ P g + q fitted on the posed samples): an effect the
    simulator does not have, injected with a known truth."""
    m = rec.pose_id >= 0
    A = np.column_stack([rec.gref_mps2[m], np.ones(int(m.sum()))])
    P = np.linalg.lstsq(A, rec.xyz[m] / rec.ref[m, None], rcond=None)[0][:3].T
    out = rec.select(slice(None))
    out.xyz = rec.xyz + rec.ref[:, None] * (da @ P.T)
    return out


def test_a_drift_is_not_tested_when_every_run_visits_each_orientation_at_the_same_board_time(
        settled_levels_campaign) -> None:
    """Three six-position runs (16 / 24 / 45 degC), each from power-on (board time 0), with one plan: every run
    visits x down at the same board time, so a function of board time shared by the runs fits whatever depends on
    the orientation there (here the spectral non-linearity: +0.1 m/s^2 on x at x up and x down). On the unchanged
    code time_drift was added at +32.5 %, p 3.8e-6, passing the check over contiguous blocks of time too (the other
    runs hold the same board times), with a warm-up of several m/s^2 (the simulated one: 0.01 m/s^2); on the
    offline campaign of the shipped plan (30 s dwells, seed 0) it was 6.07 m/s^2 and the YAML with it was 3x
    further from the simulator's truth on x (0.15 against 0.046 m/s^2 RMS over a 30-degree grid of poses).
    The candidate is not testable on such data, and says why; the same runs recorded one after the other on one
    board clock do test it."""
    rec, res = settled_levels_campaign
    assert "time_drift" not in [a[0] for a in res.added], res.added
    drift = next(c for c in res.ranked if c.name == "time_drift")
    assert not drift.applicable and "same board time" in drift.reason, drift.reason
    assert not any(t.kind == "time_drift" for t in res.calibration.corrections)
    # one board clock across the runs (a board powered through the campaign): each orientation at three times
    shifted = rec.select(slice(None))
    shifted.t_s = rec.t_s + 1000.0 * rec.run_id
    drift = next(c for c in diagnose(shifted).ranked if c.name == "time_drift")
    assert drift.applicable, drift.reason


# seed 3: bench/seed_sweeps.py (the same case: time_drift p 1.6e-5 / 5.9e-6 over random visits, refused over time
# blocks, x/y 1.6x / 2.0x the floor on seeds 2 / 3)
@pytest.mark.parametrize("seed", [2, pytest.param(3, marks=SWEEP)])
def test_a_slow_wander_that_is_no_drift_is_not_written_as_time_drift(seed: int) -> None:
    """A 20-minute oscillation of the x/y bias (a chamber's air-conditioning cycle; not in the library) is not a
    warm-up or creep. With visits held out at random, their neighbours in time on both sides let any smooth
    function of time "predict" them, so time_drift used to be added (p 1e-5 .. 2e-6) and written to the YAML the
    driver applies after every power-on. It must also predict contiguous blocks of time held out."""
    rec = simulate_recording(_config({"scenario.rate_hz": 25.0, "scenario.poses.dwell_s": 10.0,
                                      "scenario.poses.move_s": 2.0, "scenario.poses.repeat": 5}), seed=seed)
    da = np.zeros_like(rec.gref_mps2)
    da[:, 0] = 0.3 * np.sin(2 * np.pi * rec.t_s / 1200.0)
    da[:, 1] = 0.2 * np.sin(2 * np.pi * rec.t_s / 1200.0 + 1.0)
    res = diagnose(_with_acceleration_error(rec, da))
    assert "time_drift" not in [a[0] for a in res.added], res.added
    drift = next(c for c in res.ranked if c.name == "time_drift")
    assert drift.time_block is not None and "contiguous blocks of time" in drift.detail, drift.detail
    assert res.structure.significant  # the oscillation stays unexplained, and is reported so
    # and the report names its signature and the measurement that tells a drift from an orientation effect
    assert any(m.startswith("a slow change along the run on x/y") for m in settling_measurements(res)), \
        settling_measurements(res)




def _near(t_before: float, t_after: float, at_s: float) -> bool:
    """A step placed between two fitted samples under 4 s apart (a table move and a settling) is at the true time
    ``at_s`` (s), or, when that fell within a visit, at one of its ends (visits of the grid run: under 4 s)."""
    return t_after - t_before < 4.0 and t_before - 4.0 <= at_s <= t_after + 4.0


def _brackets(sc, at_s: float) -> bool:
    return _near(sc.t_before_s, sc.t_s, at_s)


def _said_at(text: str, at_s: float, start: str) -> bool:
    """``text`` starts with ``start`` and puts the step between two times ``_near`` the true time ``at_s`` (s)."""
    m = re.match(re.escape(start) + r" between t = ([0-9.]+) and ([0-9.]+) s", text)
    return m is not None and _near(float(m.group(1)), float(m.group(2)), at_s)


@pytest.mark.parametrize("seed", [1, 4])
def test_a_step_of_a_channel_s_loss_is_not_written_as_a_warm_up_and_creep(seed: int) -> None:
    """A connector of the x channel knocked mid-run (its loss up 0.13 dB, 3 % of the power, at 83 s of a 167 s grid
    run; ``effects.connector_loss_step``, not in the library). On the unchanged code time_drift was added at +71 %,
    p 7.3e-10, passing the check over contiguous blocks of time too (+44 %, p 2.2e-6): a warm-up of 3.47 m/s^2 on x with
    tau 25 s and a creep of 0.041 m/s^2/s (6.8 m/s^2 over the run), written to the YAML the driver applies after every
    power-on, while x stayed 5.55x the floor. A warm-up with creep follows a step across time blocks as well; a step
    of the response at one time explains what it fits and gains beyond it, so the drift is not added, the candidate
    says where the step is, and the residual is reported as what the model lacks.

    Seed 4 once wrote the drift with a warning that a step fits as well, on some machines only: the fold holding out
    the visit next to the step trains on the same rows for every step time within that visit, and which of those
    equal fits won was left to the BLAS kernel's rounding (step gain beyond the drift -3 % with Haswell's kernels,
    +28 % with Prescott's, +59 % with SkylakeX's). Equal fits now go to the first step time on every machine."""
    rec = simulate_recording(_config({"effects.connector_loss_step.scale": 1.0,
                                      "effects.connector_loss_step.at_s": 83.0}), seed=seed)
    res = diagnose(rec)
    assert "time_drift" not in [a[0] for a in res.added], res.added
    assert not any(t.kind == "time_drift" for t in res.calibration.corrections)
    drift = next(c for c in res.ranked if c.name == "time_drift")
    assert drift.step_check is not None and not drift.significant, drift.detail
    assert _brackets(drift.step_check, 83.0), drift.step_check  # the two visits the step falls between
    assert "step" in drift.detail and "not added" in drift.detail, drift.detail
    assert res.structure.significant and res.structure.ratio[0] > 3.0, res.structure.verdict
    assert any(_said_at(m, 83.0, "a step of the response") for m in settling_measurements(res)), \
        settling_measurements(res)


# The chamber ramped up and down once (20 -> 30 -> 20 degC over the run, the fast housing of THERMAL), and held at
# levels (20 / 30 / 20 / 30 degC, 90 s each after a 30 s ramp): the other ways to cycle the temperature of a calibration.
UP_DOWN = [{"ramp_to_c": 30.0, "duration_s": 240.0}, {"ramp_to_c": 20.0, "duration_s": 240.0}]
LEVELS = [seg for level in (30.0, 20.0, 30.0, 20.0) for seg in ({"ramp_to_c": level, "duration_s": 30.0}, {"hold_s": 90.0})]
HISTORY_TERMS = ("time_drift", "thermal_lag", "thermal_hysteresis")


@pytest.mark.parametrize(("profile", "at_s"), [(None, 250.0), (None, 120.0), (UP_DOWN, 250.0)],
                         ids=["cycled-twice-step-after-a-turn", "cycled-twice-step-at-a-turn", "up-and-down"])
def test_a_step_in_a_temperature_cycled_run_is_not_written_as_a_drift_lag_or_hysteresis(profile, at_s: float) -> None:
    """The x connector knocked (0.13 dB, ``effects.connector_loss_step``) during a temperature-cycled run (THERMAL: 126
    visits, 503 s; nothing else injected). On the unchanged code the step was written to the calibration as properties
    of the sensor (seed 1):

    * cycled twice, step at 250 s: eq. 28 of degree 0 (chosen with the step in the residual), so the best step fitted
      at degree 0 left a residual that follows the temperature (r = 0.68 on x) and time_drift gained +14.0 % beyond it
      (p 6.1e-4): added (+73.7 %; creep 0.0099 m/s^2/s on x, 5 m/s^2 over the run), then thermal_hysteresis (+33.3 %,
      p 1e-4, a half gap of 0.48 m/s^2 on x); x 3.80x the floor. At degree 1 the step leaves nothing that follows the
      temperature or time (x 0.24 m/s^2 held out, time_drift +0.0 % beyond it).
    * cycled twice, step at 120 s (a turn of the ramp): the step check refused time_drift, but thermal_lag (+73.0 %, p
      8.8e-11) was added unchecked (thermal_hysteresis +31.7 %, p 7e-4, stood next); x 3.99x the floor.
    * up and down once, step at 250 s (just after the turn): thermal_lag (+78.2 %) and thermal_hysteresis added, x
      3.72x the floor.

    A function of the temperature's history follows a step as well as a function of time does: the branch of a
    hysteresis switches at the turns, a lag's correction changes sign with the rate. Each is now set against the best
    step, with eq. 28's degree chosen again with both in the model."""
    extra = {**THERMAL, "effects.connector_loss_step.scale": 1.0, "effects.connector_loss_step.at_s": at_s}
    if profile is not None:
        extra["scenario.temperature.profile"] = profile
    res = diagnose(simulate_recording(_config(extra), seed=1))
    assert not set(HISTORY_TERMS) & {a[0] for a in res.added}, res.added
    assert not set(HISTORY_TERMS) & {t.kind for t in res.calibration.corrections}, res.calibration.corrections
    refused = [c for st in res.steps for c in st.candidates if c.step_check is not None and c.step_check.explained]
    assert refused and all(_brackets(c.step_check, at_s) for c in refused), [(c.name, c.step_check) for c in refused]
    assert all("not added" in c.detail and c.name in HISTORY_TERMS for c in refused), [c.detail for c in refused]
    assert res.structure.significant and res.structure.ratio[0] > 3.0, res.structure.verdict
    assert any(_said_at(m, at_s, "a step of the response") for m in settling_measurements(res)), \
        settling_measurements(res)


@pytest.mark.parametrize(("profile", "seed"), [(None, 1), pytest.param(None, 2, marks=SWEEP), pytest.param(None, 3, marks=SWEEP),
                                               (LEVELS, 1), pytest.param(LEVELS, 2, marks=SWEEP)])
def test_a_real_thermal_hysteresis_passes_the_step_check(profile, seed: int) -> None:
    """The simulator's hysteresis (x10: half gaps 0.1 / 0.075 / 0.125 m/s^2, play 1 degC) on a run cycled twice or held
    at four levels, no step: the hysteresis is set against the best step (on the unchanged code it was never checked:
    ``step_check`` None) and still added first, with nothing else of the temperature's history or of time."""
    extra = {**THERMAL, "effects.thermal_hysteresis.scale": 10.0}
    if profile is not None:
        extra["scenario.temperature.profile"] = profile
    res = _diagnosed(extra, seed)
    hyst = next(c for c in res.steps[0].candidates if c.name == "thermal_hysteresis")
    assert hyst.step_check is not None and not hyst.step_check.explained, hyst.detail
    assert res.added and res.added[0][0] == "thermal_hysteresis", res.added
    assert [a[0] for a in res.added if a[0] in HISTORY_TERMS] == ["thermal_hysteresis"], res.added
    assert np.all(res.after_heldout_rmse / res.noise_floor <= 1.1), res.after_heldout_rmse / res.noise_floor


def test_a_residual_that_differs_at_one_direction_of_gravity_is_named_a_table_angle_effect() -> None:
    """The table's outer-axis encoder reads 1 degree low (the reference is computed at theta - 1 degree while the sensor
    sits at theta; not in the library, not a property of the sensor). The error is a function of the table's angles,
    not of the direction of gravity in the sensor: at theta = 0 (z up) it rotates with the inner angle psi. On the
    unchanged code the report said "a slow change along the run on z" (consecutive visit means correlated +0.83: the
    grid turns theta in time order) and an orientation share of 0.02 / 0.00 / 0.01, naming neither the table nor the
    pose. Visits of one direction of gravity, a few seconds apart, disagree far beyond the noise: that is the signature."""
    rec = simulate_recording(_config({}), seed=1)
    truth = rec.metadata["truth"]
    bad = rec.select(slice(None))
    bad.gref_mps2 = np.where(np.isnan(rec.gref_mps2), np.nan,
                             table_specific_force(truth["psi_deg"], truth["theta_deg"] - 1.0))
    # the reference given as a vector, without the table's angles: the offset cannot be tried as a property of the
    # rig (``table_theta_offset``, test_diagnose.py), and this signature is what says it
    bad.table_deg = None
    res = diagnose(bad)
    s = res.structure
    assert res.added == [], res.added
    assert s.significant and np.all(s.pose_chi2_p < 1e-6), s.verdict
    assert s.direction_repeat_visits >= 12  # z up at 6 psi angles, z down at 6
    # at z up and z down the error rotates with psi in the x-y plane; on z it changes sign between theta and -theta,
    # directions that the wrong reference no longer puts together
    assert np.all(s.direction_chi2_p[:2] < 1e-5), s.direction_chi2_p
    assert np.all(s.other_pose_chi2_p[:2] < 1e-5) and np.all(s.same_pose_chi2_p == 1.0)  # each pose visited once
    settle = settling_measurements(res)
    assert any(m.startswith("at one direction of gravity the visits disagree on x/y (") for m in settle), settle
    assert "disagree" in markdown(res)


def test_clean_data_shows_no_disagreement_at_one_direction_of_gravity() -> None:
    """The signature of the test above on a recording with nothing injected: no axis below the per-axis level."""
    res = _diagnosed({}, 11)
    assert np.all(res.structure.direction_chi2_p > 0.01 / 3), res.structure.direction_chi2_p


def test_an_orientation_term_that_stands_in_for_a_table_angle_effect_is_said_to_be_one() -> None:
    """The cable torque ~ sin(2 psi) (not in the library) is 2 u_x u_y / sin^2 theta in the direction of gravity u: on
    this grid a quadratic in Psi predicts it wherever theta is not 0 or 180 degrees, and spectral_nonlinearity was added
    (+17.7 %, p 1.7e-3) and written to the YAML as a property of the sensor, with no word that it may stand in for
    something else. What remains differs between the visits at z up and z down (the inner angle turns, the direction
    does not), far beyond the noise: the orientation term is not claimed (issue 41, ``checks.stand_ins``) and the
    finding says it would stand in for an effect of the table's angles. A genuine second-order sensitivity (K2 =
    0.004 per m/s^2 on x) is added with nothing left over, and no such warning."""
    # the reference given as a vector (no table angles, so no table_theta_offset). What is tested is the warning once
    # the term is in, not the selection's threshold: this small grid's signed-rank test gives p 6e-4 .. 4e-3 over
    # seeds 1-4, around the default level (0.01 / 6 candidates), so the level is 0.05 / 6 = 8.3e-3, 13x the p of
    # seed 1 (6.3e-4)
    rec = simulate_recording(_config({"effects.unmodelled_cable_torque.scale": 3.0}), seed=1)
    rec.table_deg = None
    res = diagnose(rec, alpha=0.05)
    assert res.steps[0].chosen == "spectral_nonlinearity", res.steps[0].chosen  # the case at all
    assert "spectral_nonlinearity" not in [a[0] for a in res.added], res.added
    assert [f.effect for f in res.findings if f.kind == "stand_in"] == ["spectral_nonlinearity"], res.findings
    rec = simulate_recording(_config({}), seed=1)
    da = np.zeros_like(rec.gref_mps2)
    da[:, 0] = 0.004 * np.nan_to_num(rec.gref_mps2[:, 0]) ** 2
    res = diagnose(_with_acceleration_error(rec, da))
    assert [a[0] for a in res.added] == ["spectral_nonlinearity"] and not res.structure.significant, res.added
    assert not any("function of the orientation" in w for w in res.warnings), res.warnings
    # the simulator's own non-linearity on a seed that leaves a small residual (1.03x the floor, visits of one
    # direction apart at p 4e-4: the bias instability between visits minutes apart): small, so no warning
    scale, extra, static = SCENARIOS["spectral_nonlinearity"]
    res = _diagnosed({**extra, "effects.spectral_nonlinearity.scale": scale}, 3, static=static)
    assert res.added[0][0] == "spectral_nonlinearity" and np.all(res.structure.ratio < 1.1), res.structure.ratio
    assert not any("function of the orientation" in w for w in res.warnings), res.warnings


def test_a_pose_visited_again_that_reads_differently_is_named_a_change_with_time() -> None:
    """A six-position plan run three times (18 visits, each pose at three times) with the x connector knocked at 60 s.
    Each direction is one pose, so what its visits disagree by is time alone, not the table's angles. The first form
    of the direction signature named the table's angles first for it; now the report says the same pose reads
    differently when visited again, and names no table-angle effect."""
    cfg = SimConfig.default().with_overrides({
        **BASELINE, "scenario.poses.mode": "six_position", "scenario.poses.dwell_s": 6.0, "scenario.poses.move_s": 2.0,
        "scenario.poses.repeat": 3, "effects.connector_loss_step.scale": 1.0, "effects.connector_loss_step.at_s": 60.0})
    res = diagnose(simulate_recording(cfg, seed=3))
    s = res.structure
    assert s.significant and s.same_pose_chi2_p[0] < 1e-6 and np.all(s.other_pose_chi2_p == 1.0), s.same_pose_chi2_p
    settle = settling_measurements(res)
    assert any(m.startswith("the same pose visited again reads differently on x") for m in settle), settle
    assert not any(m.startswith("at one direction of gravity") for m in settle), settle


def _reference_step(extra: dict, loss_db: float, at_s: float) -> dict:
    """``extra`` with the reference channel's connector knocked at ``at_s`` (s): its loss up ``loss_db`` (dB), the
    axis channels untouched (``effects.connector_loss_step``), so every Psi = axis / reference rises by the same factor."""
    return {**extra, "effects.connector_loss_step.scale": 1.0, "effects.connector_loss_step.at_s": at_s,
            "effects.connector_loss_step.loss_db": [loss_db, 0.0, 0.0, 0.0]}


@pytest.mark.parametrize(("extra", "loss_db", "at_s", "seed"),
                         [({}, 0.01, 83.0, 3), (THERMAL, 0.01, 250.0, 3), (THERMAL, 0.02, 250.0, 1)],
                         ids=["grid-0.01dB", "cycled-0.01dB", "cycled-0.02dB"])
def test_a_small_step_of_the_reference_is_not_written_as_a_dark_offset(extra: dict, loss_db: float, at_s: float,
                                                                       seed: int) -> None:
    """The reference's connector knocked by 0.01-0.02 dB (0.23-0.46 % of its power): every Psi rises by as much, the
    output by (1/g - 1) M Psi, mostly an offset (M Psi at rest). The regressor 1/ref of the dark offset steps with the
    reference, so k / ref follows that offset step; a 3 % step needs implied axis-channel offsets of 66-132 % of the
    counts and is refused by the plausibility bound, a small one fits within it. On the unchanged code it was added
    and written to the YAML as a property of the sensor (``reference_dark_offset`` + ``channel_offset``), never set
    against a step: grid run 0.01 dB seed 3 +36.4 % (p 5.8e-7, k = 2.0e4 / 2.9e4 / 2.8e4 m/s^2 counts); run cycled
    twice 0.01 dB seed 3 +33.5 % (p 1.1e-9); 0.02 dB seed 1 +20.0 % (p 1.7e-5). Now it is set against the best step;
    on the cycled runs, whose poses are revisited, it is first set against the slow wander of the bias between the
    revisits: the step moves the output by 0.02-0.05 m/s^2, inside the wander the sensor may have (its bound is 10x
    Table 2's bias instability), so either answer is right and neither claims a sensor property."""
    res = diagnose(simulate_recording(_config(_reference_step(extra, loss_db, at_s)), seed=seed))
    assert "reference_dark_offset" not in [a[0] for a in res.added], res.added
    assert not {"reference_dark_offset", "channel_offset"} & {t.kind for t in res.calibration.corrections}, \
        res.calibration.corrections
    tried = [c for st in res.steps for c in st.candidates if c.name == "reference_dark_offset"]
    if extra and not any(c.step_check for c in tried):
        assert any("slow wander of the bias" in c.detail for c in tried), [c.detail for c in tried]
        return
    offset = next(c for c in tried if c.step_check)
    assert offset.step_check.explained and _brackets(offset.step_check, at_s), offset.detail
    assert "not a dark offset of the detectors" in offset.detail, offset.detail
    assert any(_said_at(m, at_s, "a step of the response") for m in settling_measurements(res)), \
        settling_measurements(res)


@pytest.mark.parametrize("seed", [pytest.param(4, marks=SWEEP), pytest.param(7, marks=SWEEP), 8])
def test_a_step_s_side_that_does_not_span_the_frame_is_not_tried(seed: int) -> None:
    """The real dark offset (``SCENARIOS``, no step) set against the best step: the grid run's first visits are all at
    z up (psi turns, gravity does not), so a step placed after them leaves the side before it one direction of gravity;
    it is fitted there by coefficients that cancel across the step and a visit held out there is predicted wildly (seed
    8: one visit's weighted MSE 8320 against 3.1). On the code before, the step's gain beyond the offset came out
    -6503 / -6613 / -6467 % (seeds 4 / 7 / 8), and on seed 8 the offset's gain beyond the step +0.9 % (p 2e-10: the
    wild visit inflated the denominator), so a real offset was written with the warning that a step fits as well. A
    step's time is now tried only where the visits trained on either side span the table frame, as ``check_folds``
    asks of every fold."""
    scale, extra, static = SCENARIOS["reference_dark_offset"]
    rec = simulate_recording(_config({**extra, "effects.reference_dark_offset.scale": scale}), seed=seed)
    res = diagnose(rec, static=static)
    assert [a[0] for a in res.added] == ["reference_dark_offset"], res.added
    sc = next(c for c in res.steps[0].candidates if c.name == "reference_dark_offset").step_check
    assert sc is not None and not sc.explained, sc
    assert sc.gain_step_beyond > -0.5, sc  # the step on top of the offset: no visit predicted wildly
    assert sc.gain_time_beyond > 0.02 and sc.p_time_beyond < 1e-3, sc
    assert not any("a step of the response" in w for w in res.warnings), res.warnings


@pytest.mark.parametrize(("extra", "at_s", "seed"), [({}, 83.0, 1), pytest.param({}, 83.0, 2, marks=SWEEP),
                                                     pytest.param({}, 83.0, 3, marks=SWEEP), (THERMAL, 120.0, 1)],
                         ids=["grid-1", "grid-2", "grid-3", "cycled-1"])
def test_a_3_percent_step_of_the_reference_is_reported_not_written(extra: dict, at_s: float, seed: int) -> None:
    """The reference's connector knocked by 0.13 dB (3 %): every Psi rises 3 %, the output moves 1.5-2 m/s^2 on each
    axis. The dark offset's column 1/ref follows the step (+98 % held out on grid seed 1) but only with implied
    axis-channel offsets of 66-132 % of the counts: refused by the plausibility bound; the warm-up and creep is
    refused by the step; neither read noise nor the non-linearity gains. Nothing is written to the YAML as a
    property of the sensor, and the residual is reported with where the step is. (Pins what the code did when
    issue 8 asked whether anything absorbs such a step: nothing did.)"""
    res = diagnose(simulate_recording(_config(_reference_step(extra, 0.13, at_s)), seed=seed))
    assert res.added == [], res.added
    assert all(isinstance(t, ReferenceLowpass) for t in res.calibration.corrections), res.calibration.corrections
    offset = next(c for c in res.ranked if c.name == "reference_dark_offset")
    assert offset.rel_gain > 0.3 and offset.implausible and not offset.significant, offset.detail
    drift = next(c for c in res.ranked if c.name == "time_drift")
    assert drift.step_check is not None and drift.step_check.explained and _brackets(drift.step_check, at_s), drift.detail
    assert res.structure.significant and np.all(res.structure.ratio > 3.0), res.structure.verdict
    assert any(_said_at(m, at_s, "a step of the response") for m in settling_measurements(res)), \
        settling_measurements(res)


@pytest.mark.parametrize(("extra", "at_s", "seed"), [({}, 83.0, 1), pytest.param({}, 83.0, 2, marks=SWEEP),
                                                     (THERMAL, 250.0, 1), pytest.param(THERMAL, 250.0, 3, marks=SWEEP)],
                         ids=["grid-1", "grid-2", "cycled-1", "cycled-3"])
def test_a_step_of_the_source_s_power_adds_nothing(extra: dict, at_s: float, seed: int) -> None:
    """All four channels lose 0.13 dB at once (a connector between the source and the coupler): eq. 24 divides the
    step out of every Psi (paper §3.5), so nothing may be added and nothing is left: the output within 1.1x the noise
    floor, no significant residual. (The reference's 12-bit rounding, 3 % coarser, is the only trace.)"""
    extra = {**extra, "effects.connector_loss_step.scale": 1.0, "effects.connector_loss_step.at_s": at_s,
             "effects.connector_loss_step.loss_db": [0.13, 0.13, 0.13, 0.13]}
    res = diagnose(simulate_recording(_config(extra), seed=seed))
    assert res.added == [], [(c.name, round(c.rel_gain, 3), c.p_value) for c in res.ranked]
    assert all(isinstance(t, ReferenceLowpass) for t in res.calibration.corrections), res.calibration.corrections
    assert not res.structure.significant, res.structure.verdict
    assert np.all(res.after_heldout_rmse <= 1.1 * res.noise_floor), res.after_heldout_rmse / res.noise_floor


# Faults of the AHT10 reading the firmware does not flag (``faults.temperature_reading``; the sensor itself is fine)
READING_STEP = {"steps": [{"at_s": 250.0, "step_c": 0.5}], "frozen": [], "spikes": {"at_s": [], "size_c": 50.0}}
READING_FROZEN = {"steps": [], "frozen": [{"start_s": 60.0, "duration_s": 180.0}], "spikes": {"at_s": [], "size_c": 50.0}}
READING_SPIKES = {"steps": [], "frozen": [], "spikes": {"at_s": [40.5, 140.5, 300.5, 380.5, 460.5], "size_c": 50.0}}
# what a fault of the temperature reading must never be written as: a function of time or of the temperature's history
READING_ABSORBERS = {"time_drift", "thermal_lag", "thermal_hysteresis", "reference_dark_offset", "channel_offset"}


def _jumps_named(warnings: list[str]) -> list[float]:
    """The times (s) at which a warning says the AHT10 reading jumps."""
    text = next((w for w in warnings if w.startswith("the AHT10 reading jumps")), "")
    return [float(m) for m in re.findall(r"at t = ([0-9.]+) s", text)]


@pytest.mark.parametrize(("fault", "seed", "at_s"),
                         [(READING_STEP, 1, [250.0]), pytest.param(READING_STEP, 2, [250.0], marks=SWEEP),
                          (READING_FROZEN, 1, [240.0]), pytest.param(READING_FROZEN, 2, [240.0], marks=SWEEP),
                          (READING_SPIKES, 1, [40.5, 140.5, 300.5, 380.5, 460.5])],
                         ids=["step-1", "step-2", "frozen-1", "frozen-2", "spikes-1"])
def test_a_fault_of_the_temperature_reading_is_not_written_as_a_property_of_the_sensor(fault, seed: int,
                                                                                        at_s: list[float]) -> None:
    """The sensor is fine, its AHT10 reading is not (the firmware flags nothing): on the temperature-cycled run (THERMAL,
    eq. 28 of degree 1) the reading steps by +0.5 degC at 250 s (re-seated), repeats one value from 60 to 240 s (frozen
    over a turn of the ramp) or reads 50 degC too high for one read (0.5 s) five times (a flipped bit of the 20-bit
    word). On the code before, what each did to eq. 28 was written to the calibration YAML as a property of the sensor:
    step seed 1 time_drift (+3.4 %, p 7.6e-9: a warm-up of 3.4 m/s^2 on x cancelled by a creep), seed 2 time_drift
    (+2.2 %, p 1.7e-7); frozen seed 1 time_drift (+20.7 %) and thermal_hysteresis, seed 2 reference_dark_offset (+23.7 %)
    and thermal_lag; spikes seed 1 reference_dark_offset (+31.8 %), thermal_lag and thermal_hysteresis, eq. 28 down to
    degree 0 (a lag's low-pass of the temperature smooths the
    spikes away). The reading is now checked first: where it departs from its own recent course by more than two
    reads of one temperature can differ (2 x the datasheet's +-0.1 degC repeatability) the warning names the time, and
    nothing that reads time or the temperature's history is added on a run of two temperature levels or more."""
    res = diagnose(simulate_recording(_config({**THERMAL, "faults.temperature_reading": fault}), seed=seed))
    assert not READING_ABSORBERS & {a[0] for a in res.added}, res.added
    # and it is the reading that keeps them out: each absorber refused is refused for the jump (the check runs first;
    # the checks after it refuse some of them too, so the outcome alone would not show the jump's check at work)
    refused = [(c.name, c.refusal) for st in res.steps for c in st.candidates
               if c.name in READING_ABSORBERS and c.refusal is not None]
    assert refused and all(why is Refusal.READING_JUMP for _, why in refused), refused
    assert not READING_ABSORBERS & {t.kind for t in res.calibration.corrections}, res.calibration.corrections
    named = _jumps_named(res.warnings)
    assert named and all(any(abs(n - t) < 1.0 for n in named) for t in at_s), (named, res.warnings)
    assert all(any(abs(n - t) < 1.0 for t in at_s) for n in named), (named, at_s)


@pytest.mark.parametrize("seed", [1, pytest.param(2, marks=SWEEP), pytest.param(3, marks=SWEEP)])
def test_a_clean_temperature_reading_is_not_called_a_fault(seed: int) -> None:
    """The cycled run's own reading (ramps of 5 degC/min through a 60 s housing, AHT10 noise 0.03 degC, 0.01 degC
    resolution, held at 2 Hz) and the run held at four levels (10 degC in 30 s) never depart from their recent course
    by 0.2 degC: no warning, and the simulator's hysteresis x10 on the levels is still added."""
    for extra in (THERMAL, {**THERMAL, "scenario.temperature.profile": LEVELS, "effects.thermal_hysteresis.scale": 10.0}):
        res = _diagnosed(extra, seed)
        assert _jumps_named(res.warnings) == [], res.warnings


def test_a_quadratic_of_the_orientation_beyond_what_the_spectral_overlap_can_bend_is_refused() -> None:
    """An error that is a quadratic function of the orientation (1.5 m/s^2 x (g_x / g)^2 on x, a cross term on z): a
    quadratic in Psi fits it (+83 % held out on seed 1), and on the unchanged code spectral_nonlinearity was written to
    the calibration with no bound at all. Its non-linear part over the poses (0.64 m/s^2 on x) is twice what the
    paper's overlap model can bend the output by at 1 g (``effects.nonlinearity_bound_mps2``: 0.31 m/s^2), so it is
    refused as not physical and the residual stays unexplained."""
    rec = simulate_recording(_config({}), seed=1)
    g = rec.gref_mps2 / 9.80665
    da = np.zeros_like(g)
    da[:, 0], da[:, 2] = 1.5 * g[:, 0] ** 2, -1.5 * g[:, 0] * g[:, 1]
    res = diagnose(_with_acceleration_error(rec, da))
    assert "spectral_nonlinearity" not in [a[0] for a in res.added], res.added
    nl = next(c for c in res.steps[0].candidates if c.name == "spectral_nonlinearity")
    assert nl.rel_gain > 0.3 and "REFUSED" in nl.detail and "spectral overlap can bend" in nl.detail, nl.detail
    assert res.structure.significant, res.structure.verdict


def test_a_campaign_of_settled_levels_is_said_to_be_unable_to_reveal_a_lag(settled_levels_campaign) -> None:
    """The paper's campaign design (six poses at each of three levels, 16 / 24 / 45 degC, each level recorded once the
    chamber had settled): no fitted sample sees the temperature change, so no lag between the optics and the AHT10
    can show, whatever its time constant. On the unchanged code thermal_lag was searched and ranked like any
    candidate, and the report said nothing of what the design cannot see; now it is not testable, and says why and
    what measurement would test it. A campaign recorded during ramps (THERMAL) still tests it."""
    lag = next(c for c in settled_levels_campaign[1].ranked if c.name == "thermal_lag")
    assert not lag.applicable and "cannot reveal a lag" in lag.reason and "ramps" in lag.reason, lag.reason
    ramped = next(c for c in _diagnosed(THERMAL, 1).ranked if c.name == "thermal_lag")
    assert ramped.applicable, ramped.reason


def test_run_offset_names_the_runs_no_shared_level_connects() -> None:
    """Six-position runs at 20, 20 and 35 degC: runs 1 and 2 share a level, run 3 shares none. run_offset is not
    identified (run 3's offset would take over eq. 28's b(T)); on the unchanged code it said "no temperature level
    is shared by the runs", which two of them do. It now names the run that no shared level connects."""
    from fbg_accel_sim.make_default_calibration import calibration_runs

    rec = calibration_runs(SimConfig.default(), seed=2, levels_c=(20.0, 20.0, 35.0), dwell_s=10.0, move_s=3.0)
    off = next(c for c in diagnose(rec).ranked if c.name == "run_offset")
    assert not off.applicable and "run(s) 3 share no temperature level with run 1" in off.reason, off.reason


def test_an_effect_chosen_first_that_two_later_ones_explain_is_taken_out_again() -> None:
    """Issue 41, defect 2: on ramps with a thermal lag and reference dark offsets under a source drift, a time drift
    fits more of the declared model's residual than either (+53 % against +39-41 %) and is chosen first; the two are
    added after it, and forward selection kept it beside them (with the lag's tau 11 % long). The backward step asks
    each earlier effect whether it still gains on top of the others (the later ones' hyper-parameters searched again
    without it): the time drift gains +0.2 % (it needs 2 %) and is taken out. The library is the three candidates
    in question, to keep the test short."""
    from fbg_accel_calibration.diagnosis.effects import ReferenceDarkOffsetEffect, ThermalLagEffect, TimeDriftEffect

    rec = simulate_recording(_config({**RAMPS, **LAG, **DARK_UNDER_DRIFT}), seed=40)
    res = diagnose(rec, library=(ReferenceDarkOffsetEffect(), ThermalLagEffect(), TimeDriftEffect()))
    assert res.steps[0].chosen == "time_drift", [(c.name, round(c.rel_gain, 3)) for c in res.ranked]  # the case at all
    assert sorted(a[0] for a in res.added) == ["reference_dark_offset", "thermal_lag"], res.added
    assert any(st.removed_note.startswith("time_drift taken out again") for st in res.steps)
    tau = next(a[1] for a in res.added if a[0] == "thermal_lag")
    assert abs(tau / -LAG_S - 1.0) < 0.05, tau  # the reading lags the optics by 120 s


def test_a_term_added_before_another_has_its_hyper_parameter_searched_again_beside_it() -> None:
    """Issue 41, defect 2: the same ramps on another seed. With their bound judged on the fit alone (judged with its
    uncertainty, 108 % of the bound is not decided and the dark offsets enter first), the dark offsets are refused at
    step 1 (eq. 28 of degree 1 makes their implied x offset 27 % of the counts; at degree 2, chosen with them in, 30 %),
    so the thermal lag enters first, with tau 161.5 s (35 % long); the dark offset follows and takes eq. 28 to degree
    2, and on the unchanged code the lag kept its tau and a time drift was added third for what it left. After each
    term enters, those before it are searched again beside it: tau comes back to 118.7 s (1 % of the 120 s
    injected, asserted within 5 %), and nothing else is added."""
    from fbg_accel_calibration.diagnosis.effects import ReferenceDarkOffsetEffect, ThermalLagEffect, TimeDriftEffect

    class DarkOffsetBoundOnTheFit(ReferenceDarkOffsetEffect):  # its bound judged on the fit alone, as it was
        def bound_ratios(self, h, coeff, data, M0):
            return None

    rec = simulate_recording(_config({**RAMPS, **LAG, **DARK_UNDER_DRIFT}), seed=43)
    res = diagnose(rec, library=(DarkOffsetBoundOnTheFit(), ThermalLagEffect(), TimeDriftEffect()))
    assert res.steps[0].chosen == "thermal_lag", [(c.name, round(c.rel_gain, 3)) for c in res.ranked]  # the case at all
    assert sorted(a[0] for a in res.added) == ["reference_dark_offset", "thermal_lag"], res.added
    tau = next(a[1] for a in res.added if a[0] == "thermal_lag")
    assert abs(tau / -LAG_S - 1.0) < 0.05, tau
    assert res.final_degree == 2 and any("searched again beside it" in st.degree_note for st in res.steps)


def test_two_effects_that_hold_eq_28_s_degree_down_are_named_with_it() -> None:
    """Issue 41, defect 2: the same ramps on a third seed, where nothing was added. Both missing effects made a higher
    degree of eq. 28 overfit, so it came out of degree 1 (2 without the effects); there the dark offsets' implied x
    offset is 103 % of its bound (standard error 3 % over the folds), which refused it, and the lag, judged at degree
    1, a step fitted as well. Now a bound beyond which a fit lies by less than its uncertainty does not refuse it
    (the one-sided 99 % limit is 94 % of the bound), and a candidate is judged at the degree chosen with it in: the
    lag at degree 2 (held out y 0.095 against 0.146 m/s^2 at degree 1). Both are named, eq. 28 ends at degree 2 and
    the lag's tau within 5 % of the 120 s injected; nothing else is added."""
    from fbg_accel_calibration.diagnosis.effects import ReferenceDarkOffsetEffect, ThermalLagEffect, TimeDriftEffect

    rec = simulate_recording(_config({**RAMPS, **LAG, **DARK_UNDER_DRIFT}), seed=48)
    res = diagnose(rec, library=(ReferenceDarkOffsetEffect(), ThermalLagEffect(), TimeDriftEffect()))
    assert sorted(a[0] for a in res.added) == ["reference_dark_offset", "thermal_lag"], res.added
    assert res.final_degree == 2
    tau = next(a[1] for a in res.added if a[0] == "thermal_lag")
    assert abs(tau / -LAG_S - 1.0) < 0.05, tau
    dark = next(c for c in res.steps[0].candidates if c.name == "reference_dark_offset")
    assert dark.significant and "the bound does not decide" in dark.detail, dark.detail
    # beside the lag at degree 2 the implied offsets are 3-10 % of the counts: the bound is decided, nothing to say
    assert not [f for f in res.findings if f.kind == "at_bound"], res.findings


def test_a_candidate_refused_at_the_model_s_degree_is_judged_again_at_the_degree_chosen_with_it() -> None:
    """Issue 41: a candidate is judged at eq. 28's degree chosen with it in, not only at the degree chosen without it.
    On the ramps with a thermal lag alone the declared model is of degree 1 (2 without the lag); the dark offsets,
    refused there, are judged again at degree 2, chosen with them in, and refused there too: their implied x offset
    is 41-45 % of the counts, a stand-in for the lag, beyond the 25 % bound by far more than its uncertainty. The
    lag is named (tau within 5 %) at degree 2."""
    from fbg_accel_calibration.diagnosis.effects import ReferenceDarkOffsetEffect, ThermalLagEffect

    res = diagnose(simulate_recording(_config({**RAMPS, **LAG}), seed=40),
                   library=(ReferenceDarkOffsetEffect(), ThermalLagEffect()))
    dark = next(c for c in res.steps[0].candidates if c.name == "reference_dark_offset")
    assert res.degree == 1 and dark.degree == 2, (res.degree, dark.degree)
    assert "judged on eq. 28 of degree 2, chosen again with it in" in dark.detail and "REFUSED" in dark.detail
    assert not dark.significant
    assert [a[0] for a in res.added] == ["thermal_lag"] and res.final_degree == 2
    assert abs(res.added[0][1] / -LAG_S - 1.0) < 0.05
