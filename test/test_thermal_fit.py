"""Thermal model fit (eq. 28-30) and degree selection by held-out cross-validation."""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_calibration.fit_pipeline import fit_thermal
from fbg_accel_calibration.fit_stream import prepare
from fbg_accel_calibration.model_selection import held_out_predictions, select_degree
from fbg_accel_calibration.recording import Recording
from fbg_accel_calibration.thermal_fit import (
    NotIdentifiedError,
    accumulate_cells,
    coefficients_to_model,
    design_matrix,
    model_to_coefficients,
    residuals,
    temperature_levels,
)
from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2
from fbg_accel_driver.thermal_model import ThermalCalibration, normalise

G = 9.80665


def _truth(degree: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 28 coefficients near the paper's linear fit (section 3.6; b negative: Psi at rest is positive, as counts are)."""
    M = [np.diag([80.0, 78.0, 107.0]) + rng.normal(0.0, 2.0, (3, 3))]
    M += [rng.normal(0.0, 1.0, (3, 3)) / k for k in range(1, degree + 1)]
    b = [np.array([-101.0, -153.0, -137.0])] + [rng.normal(0.0, 1.0, 3) / k for k in range(1, degree + 1)]
    return np.array(M), np.array(b)


def _simulate(M: np.ndarray, b: np.ndarray, levels: tuple[float, ...], *, n_poses: int = 10, n: int = 60,
              psi_noise: float = 1e-5, center: float, scale: float, seed: int = 0, moves: int = 0) -> Recording:
    """Counts that eq. 28 with (M, b) maps exactly onto random gravity poses, plus Psi noise.

    ``moves`` > 0 inserts that many samples between poses whose signal ramps to the next pose while
    the reference already shows the next pose (the table's angle reading leads the sensor)."""
    rng = np.random.default_rng(seed)
    poses = rng.normal(size=(n_poses, 3))
    poses = G * poses / np.linalg.norm(poses, axis=1)[:, None]
    parts = []
    t0 = 0.0
    for li, temp_c in enumerate(levels):
        tau = (temp_c - center) / scale
        Mt = sum(M[k] * tau**k for k in range(len(M)))
        bt = sum(b[k] * tau**k for k in range(len(b)))
        psi_of = np.linalg.solve(Mt, (poses - bt).T).T  # (P, 3)
        for p in range(n_poses):
            psi = psi_of[p] + rng.normal(0.0, psi_noise, (n, 3))
            parts.append((psi, np.full(n, temp_c), np.repeat(poses[p][None], n, 0), np.full(n, p), np.full(n, li)))
            if moves and p + 1 < n_poses:
                frac = (np.arange(1, moves + 1) / (moves + 1))[:, None]
                ramp = psi_of[p] + frac * (psi_of[p + 1] - psi_of[p]) + rng.normal(0.0, psi_noise, (moves, 3))
                parts.append((ramp, np.full(moves, temp_c), np.repeat(poses[p + 1][None], moves, 0),
                              np.full(moves, p + 1), np.full(moves, li)))
    psi, temp, gref, pose, run = (np.concatenate(x) for x in zip(*parts, strict=True))
    ref = np.full(len(temp), 880.0)
    t = t0 + np.arange(len(temp)) * 0.01
    return Recording(t, ref, psi * ref[:, None], temp, gref, pose, run)


def test_design_matrix_matches_eq_29_and_coefficients_round_trip() -> None:
    rng = np.random.default_rng(0)
    psi, tau = rng.normal(size=(5, 3)), rng.normal(size=5)
    X = design_matrix(psi, tau, 2)
    expected = np.hstack([psi, psi * tau[:, None], psi * tau[:, None] ** 2, np.ones((5, 1)), tau[:, None], tau[:, None] ** 2])
    np.testing.assert_allclose(X, expected)
    M, b = _truth(2, rng)
    A = model_to_coefficients(M, b)
    M2, b2 = coefficients_to_model(A, 2)
    np.testing.assert_array_equal(M2, M)
    np.testing.assert_array_equal(b2, b)
    cal = ThermalCalibration(M=M, b=b, temperature_range_c=(0, 1))
    np.testing.assert_allclose(X @ A, cal.base_acceleration(psi, tau), rtol=1e-12)


def test_recovers_known_coefficients() -> None:
    rng = np.random.default_rng(1)
    M, b = _truth(2, rng)
    rec = _simulate(M, b, (16.0, 24.0, 45.0), center=30.5, scale=14.5, psi_noise=2e-6)
    cal = fit_thermal(rec, 2, usable=np.ones(len(rec), bool))
    assert (cal.t_center_c, cal.t_scale_c) == (30.5, 14.5)
    np.testing.assert_allclose(cal.M, M, atol=2e-3)
    np.testing.assert_allclose(cal.b, b, atol=2e-3)
    assert cal.temperature_range_c == (16.0, 45.0)
    assert cal.fit["temperature_levels_c"] == [16.0, 24.0, 45.0]
    # RMSE from the streamed sums equals the RMSE of the explicit residuals
    res = residuals(cal, rec)
    np.testing.assert_allclose(cal.fit["rmse_mps2"], np.sqrt((res**2).mean(axis=0)), rtol=1e-4)
    # the within-pose noise floor is the injected Psi noise through M
    expected_noise = 2e-6 * np.sqrt((M[0] ** 2).sum(axis=1))
    np.testing.assert_allclose(cal.noise_sigma_mps2, expected_noise, rtol=0.15)


def test_streaming_equals_one_shot_least_squares() -> None:
    rng = np.random.default_rng(2)
    M, b = _truth(1, rng)
    rec = _simulate(M, b, (10.0, 30.0), center=20.0, scale=10.0, psi_noise=1e-3)
    psi, tau, level = normalise(rec.xyz, rec.ref), (rec.temp_c - 20.0) / 10.0, temperature_levels(rec.temp_c)[0]
    small = accumulate_cells(psi, tau, rec.gref_mps2, rec.pose_id, level, 1, chunk=7)
    big = accumulate_cells(psi, tau, rec.gref_mps2, rec.pose_id, level, 1, chunk=10**6)
    np.testing.assert_allclose(small.xtx, big.xtx, rtol=1e-10)
    np.testing.assert_allclose(small.xtg, big.xtg, rtol=1e-10)
    # visits that chunks cut are joined again (60 samples a pose, chunks of 7)
    assert small.n_visits == big.n_visits == 2 * 10
    np.testing.assert_allclose(small.visit_outer, big.visit_outer, rtol=1e-10, atol=1e-12 * np.abs(big.visit_outer).max())
    cal = fit_thermal(rec, 1, chunk=7, usable=np.ones(len(rec), bool))
    X = design_matrix(psi, tau, 1)
    A_ref, *_ = np.linalg.lstsq(X, rec.gref_mps2, rcond=None)
    np.testing.assert_allclose(model_to_coefficients(cal.M, cal.b), A_ref, rtol=1e-7, atol=1e-9)


def test_a_usable_mask_of_another_length_is_refused() -> None:
    rec = _simulate(*_truth(0, np.random.default_rng(8)), (20.0,), center=20.0, scale=1.0)
    with pytest.raises(ValueError, match=rf"usable must be one flag per sample \({len(rec)}\), got shape \(3,\)"):
        prepare(rec, 0, usable=np.ones(3, bool))


def test_degree_not_identified_by_levels_is_refused() -> None:
    rng = np.random.default_rng(3)
    M, b = _truth(1, rng)
    rec = _simulate(M, b, (16.0, 24.0, 45.0), center=30.5, scale=14.5)
    fit_thermal(rec, 2, usable=np.ones(len(rec), bool))  # degree 2 < 3 levels: fine
    with pytest.raises(NotIdentifiedError, match=r"degree 3 in temperature is not identified by 3 temperature level.*"
                       r"use degree <= 2 or record more temperature levels$"):
        fit_thermal(rec, 3, usable=np.ones(len(rec), bool))
    one = rec.select(rec.run_id == 0)
    with pytest.raises(NotIdentifiedError, match="not identified by 1 temperature level"):
        fit_thermal(one, 1, usable=np.ones(len(one), bool))
    few = rec.select((rec.run_id == 0) & (rec.pose_id < 3))
    with pytest.raises(NotIdentifiedError, match="poses"):
        fit_thermal(few, 0, usable=np.ones(len(few), bool))


def test_temperature_levels() -> None:
    t = np.r_[np.full(5, 16.0) + np.linspace(0, 0.3, 5), np.nan, np.full(4, 24.2), np.linspace(40.0, 49.0, 50)]
    labels, means = temperature_levels(t, gap_c=1.0, max_width_c=3.0)
    assert labels[5] == -1
    assert len(means) == 2 + 3  # two set-points, the 9 degC sweep split into 3 bins
    assert np.all(np.diff(means) > 0)
    assert len(set(labels[:5])) == 1 and len(set(labels[6:10])) == 1


def test_cross_validation_chooses_the_true_degree_and_matches_explicit_refits() -> None:
    rng = np.random.default_rng(4)
    M, b = _truth(1, rng)
    M[1] *= 3.0
    levels = (10.0, 20.0, 30.0, 40.0)
    rec = _simulate(M, b, levels, center=25.0, scale=15.0, psi_noise=1e-4, n=30)
    usable = np.ones(len(rec), bool)
    sel = select_degree(rec, max_degree=4, usable=usable)
    assert sel.n_levels == 4
    assert sel.chosen_degree == 1
    by_degree = {s.degree: s for s in sel.scores}
    assert not by_degree[4].identified and "not identified" in by_degree[4].note
    assert by_degree[3].identified and np.isnan(by_degree[3].held_out_level).all()  # needs 4 levels per fold
    assert np.isfinite(by_degree[2].held_out_level).all()
    # held out by level, degree 1: explicit refits without each level
    rss, n = np.zeros(3), 0
    for lv in range(4):
        train = rec.select(rec.run_id != lv)
        test = rec.select(rec.run_id == lv)
        cal = fit_thermal(train, 1, usable=np.ones(len(train), bool))
        # same temperature scaling as the CV (centre/scale of all data) does not change predictions
        r = residuals(cal, test)
        rss += (r**2).sum(axis=0)
        n += len(test)
    np.testing.assert_allclose(by_degree[1].held_out_level, np.sqrt(rss / n), rtol=1e-5)
    # held out by pose, degree 0: explicit refits
    rss, n = np.zeros(3), 0
    for p in range(10):
        cal = fit_thermal(rec.select(rec.pose_id != p), 0, usable=np.ones(int((rec.pose_id != p).sum()), bool))
        r = residuals(cal, rec.select(rec.pose_id == p))
        rss += (r**2).sum(axis=0)
        n += int((rec.pose_id == p).sum())
    np.testing.assert_allclose(by_degree[0].held_out_pose, np.sqrt(rss / n), rtol=1e-5)
    assert by_degree[1].held_out_pose.mean() < by_degree[0].held_out_pose.mean()
    table = sel.table_markdown()
    assert "| 1 **(chosen)** |" in table and "NO" in table
    # per-sample held-out predictions agree with the scores
    pred = held_out_predictions(prepare(rec, 1, usable=usable), rec, usable, 1, by="level")[usable]
    np.testing.assert_allclose(np.sqrt(((pred - rec.gref_mps2[usable]) ** 2).mean(axis=0)), by_degree[1].held_out_level,
                               rtol=1e-6)


def test_three_levels_like_the_paper_never_pick_degree_three() -> None:
    rng = np.random.default_rng(5)
    M, b = _truth(3, rng)
    rec = _simulate(M, b, (16.0, 24.0, 45.0), center=30.5, scale=14.5, psi_noise=1e-4, n=30)
    sel = select_degree(rec, max_degree=6, usable=np.ones(len(rec), bool))
    # the truth is cubic in temperature; three levels identify at most n = 2, and n = 2 fits them exactly
    assert sel.chosen_degree == 2
    assert any("not validated by a level hold-out" in note for note in sel.notes)
    assert all(not s.identified for s in sel.scores if s.degree >= 3)
    assert any("not identified" in note for note in sel.notes)
    # in-sample RMSE keeps falling with the degree, which is why the paper's in-sample choice misleads
    ins = [s.in_sample.mean() for s in sel.scores if s.identified]
    assert ins == sorted(ins, reverse=True)
    assert sel.as_dict()["full_scale_mps2"] == pytest.approx(FULL_SCALE_MPS2)


def test_temperature_guard_stops_at_a_degree_that_predicts_unseen_levels_worse() -> None:
    """Pure noise in temperature: a linear term predicts held-out levels worse and is not chosen."""
    rng = np.random.default_rng(6)
    M, b = _truth(0, rng)
    rec = _simulate(M, b, (10.0, 20.0, 30.0, 40.0), center=25.0, scale=15.0, psi_noise=3e-3, n=30)
    sel = select_degree(rec, max_degree=3, usable=np.ones(len(rec), bool))
    assert sel.chosen_degree == 0
    assert any(note.startswith("degree 1 predicts held-out temperature levels worse") for note in sel.notes)
    by_degree = {s.degree: s for s in sel.scores}
    # the in-sample error still falls with the degree: only held-out data protect the choice
    assert by_degree[2].in_sample.mean() < by_degree[0].in_sample.mean()


def test_temperature_guard_walks_past_a_worse_degree_to_a_quadratic_truth() -> None:
    """A bias even in temperature: the linear term extrapolates the outer levels worse than the constant,
    but the quadratic predicts every held-out level far better than both and must stay a candidate (the guard
    used to stop at the first worse degree and chose n = 0, leaving errors of 30x the noise)."""
    rng = np.random.default_rng(7)
    M, b = _truth(2, rng)
    M[1:], b[1], b[2] = 0.0, 0.0, np.array([1.5, -1.0, 0.8])
    rec = _simulate(M, b, (20.0, 25.0, 30.0, 35.0), center=27.5, scale=7.5, psi_noise=1e-4, n=30)
    sel = select_degree(rec, max_degree=3, usable=np.ones(len(rec), bool))
    by_degree = {s.degree: s for s in sel.scores}
    assert by_degree[1].held_out_level.mean() > by_degree[0].held_out_level.mean()  # the case itself
    assert by_degree[2].held_out_level.mean() < 0.1 * by_degree[0].held_out_level.mean()
    assert sel.chosen_degree == 2, sel.notes
    assert any(note.startswith("degree 1 predicts held-out temperature levels worse") for note in sel.notes)


def test_static_detector_keeps_motion_out_of_the_fit() -> None:
    rng = np.random.default_rng(6)
    M, b = _truth(0, rng)
    rec = _simulate(M, b, (23.4,), center=23.4, scale=1.0, psi_noise=2e-5, n=80, moves=6, n_poses=12)
    good = fit_thermal(rec, 0)  # static detector decides
    naive = fit_thermal(rec, 0, usable=np.ones(len(rec), bool))  # every sample with its table reading
    assert good.fit["samples_excluded_in_motion"] >= 6 * 11
    assert np.abs(good.M - M).max() < 0.05 and np.abs(good.b - b).max() < 0.05
    assert np.max(good.fit["rmse_mps2"]) < 0.3 * np.min(naive.fit["rmse_mps2"])


def test_runs_whose_pose_ids_name_other_orientations_keep_the_noise_floor(tmp_path) -> None:
    """A pose id names an orientation within its run (its plan) only: two runs of different plans at one
    temperature share ids for other orientations. A cell is one pose at one level *of one run*, so the
    within-pose floor that the driver publishes as the noise covariance stays that of each run (pooling
    the two orientations behind one id inflated it about 25-fold); fit and model agree with each run's."""
    from test_diagnose_sim import _config

    from fbg_accel_calibration.fit_stream import prepare_stream
    from fbg_accel_calibration.mcap_io import McapSampleStream, write_recording
    from fbg_accel_sim.board_physics import simulate_recording

    a = simulate_recording(_config({}), seed=11)  # 60-degree grid
    b = simulate_recording(_config({"scenario.poses.grid.theta_step_deg": 45.0,
                                    "scenario.poses.grid.psi_step_deg": 45.0}), seed=12)
    assert not np.allclose(a.gref_mps2[a.pose_id == 10][0], b.gref_mps2[b.pose_id == 10][0])  # id 10: two orientations
    floor_a, floor_b = fit_thermal(a, 0).noise_sigma_mps2, fit_thermal(b, 0).noise_sigma_mps2
    both = fit_thermal(Recording.concatenate([a, b]), 0)
    assert np.all(both.noise_sigma_mps2 <= 1.05 * np.maximum(floor_a, floor_b)), both.noise_sigma_mps2
    assert np.all(both.noise_sigma_mps2 >= 0.95 * np.minimum(floor_a, floor_b)), both.noise_sigma_mps2
    # the same cells when the runs are two files, streamed
    write_recording(tmp_path / "a.mcap", a)
    write_recording(tmp_path / "b.mcap", b)
    streamed = prepare_stream([McapSampleStream(tmp_path / "a.mcap"), McapSampleStream(tmp_path / "b.mcap")], 0)
    assert len(streamed.stats.count) == len(np.unique(a.pose_id[a.pose_id >= 0])) + len(np.unique(b.pose_id[b.pose_id >= 0]))


def test_poses_are_counted_as_orientations_not_as_pose_ids() -> None:
    """Two runs whose ids 0-2 name six orientations between them are fitted (before: refused as "3 pose(s)"),
    and two runs of one plan count its orientations once: the YAML's ``poses`` is the number of orientations."""
    rng = np.random.default_rng(7)
    M, b = _truth(0, rng)
    rec = _simulate(M, b, (24.0,), center=24.0, scale=1.0, n_poses=6, n=50)
    first, second = rec.select(rec.pose_id < 3), rec.select(rec.pose_id >= 3)
    second.pose_id, second.run_id = second.pose_id - 3, np.ones(len(second), rec.run_id.dtype)
    both = Recording.concatenate([first, second])
    assert len(np.unique(both.pose_id)) == 3
    cal = fit_thermal(both, 0)
    assert cal.fit["poses"] == 6
    # as one run of six ids (each run has its own detector floor)
    np.testing.assert_allclose(cal.M, fit_thermal(rec, 0).M, rtol=1e-4, atol=1e-3)
    again = rec.select(np.ones(len(rec), bool))
    again.run_id = np.ones(len(again), rec.run_id.dtype)
    assert fit_thermal(Recording.concatenate([rec, again]), 0).fit["poses"] == 6


def test_repeated_visits_of_a_pose_keep_the_noise_floor_of_one_visit() -> None:
    """The floor is the scatter within a visit (one contiguous stay at one pose), as diagnose's is: a pose
    visited again in the same run and at the same level (a looped plan) may read a little differently each
    time (table repeatability, slow drift), and that difference is not the sample noise the driver publishes
    as the covariance."""
    rng = np.random.default_rng(4)
    M, b = _truth(0, rng)
    once = _simulate(M, b, (24.0,), center=24.0, scale=1.0, psi_noise=1e-4, n=200, n_poses=8)
    visits = [once.select(once.pose_id == p) for p in range(8)]
    second = [v.select(np.ones(len(v), bool)) for v in visits]  # every pose again, shifted by 20 noise sigmas
    for v in second:
        v.xyz = v.xyz + 20 * 1e-4 * v.ref[:, None]
    rec = Recording.concatenate(visits + second)
    rec.run_id[:] = 0
    rec.t_s = np.arange(len(rec)) * 0.01
    floor_once = fit_thermal(once, 0, usable=np.ones(len(once), bool)).noise_sigma_mps2
    floor = fit_thermal(rec, 0, usable=np.ones(len(rec), bool)).noise_sigma_mps2
    expected = 1e-4 * np.sqrt((M[0] ** 2).sum(axis=1))
    np.testing.assert_allclose(floor_once, expected, rtol=0.15)
    np.testing.assert_allclose(floor, floor_once, rtol=0.1)


def test_four_orientations_are_enough_and_three_are_not() -> None:
    """At the ``n_poses < 4`` boundary: each axis' row of M and its b are 4 unknowns, one equation per orientation, so 4
    non-coplanar orientations determine a degree-0 model and 3 do not; a check that wanted 5 refused a valid campaign."""
    M, b = _truth(0, np.random.default_rng(4))
    rec = _simulate(M, b, (24.0,), center=24.0, scale=1.0, n_poses=4, n=80, psi_noise=1e-6, seed=5)
    cal = fit_thermal(rec, 0, usable=np.ones(len(rec), bool))
    assert cal.fit["poses"] == 4 and cal.fit["samples_used"] == len(rec)
    np.testing.assert_allclose(cal.M[0], M[0], rtol=1e-3, atol=1e-2)
    three = rec.select(rec.pose_id < 3)
    with pytest.raises(NotIdentifiedError, match="3 orientation"):
        fit_thermal(three, 0, usable=np.ones(len(three), bool))


@pytest.mark.parametrize("convention", ["sign flipped", "x and y swapped"])
def test_a_level_whose_reference_follows_another_convention_is_refused(convention: str) -> None:
    """One level of three with its reference gravity sign-flipped, or x and y swapped (a node of another convention
    publishing ``calibration/reference_gravity``): a degree-2 polynomial passes through any 3 levels, so the fit gave a
    small in-sample RMSE and exit 0 with 2.9 - 6.5 m/s^2 of error against the truth. That level's own M differs from
    the others' by 100-200 %, where temperature moves it by a few %."""
    M, b = _truth(2, np.random.default_rng(6))
    rec = _simulate(M, b, (16.0, 24.0, 45.0), center=30.5, scale=14.5)
    fit_thermal(rec, 2, usable=np.ones(len(rec), bool))  # as recorded: fitted
    mid = rec.run_id == 1
    rec.gref_mps2[mid] = -rec.gref_mps2[mid] if convention == "sign flipped" else rec.gref_mps2[mid][:, [1, 0, 2]]
    with pytest.raises(NotIdentifiedError, match=r"level\(s\) at 24.0 degC \(\d+ %\) give an M that differs from the "
                       r"other levels' by more than 30 % \(the others: within \d %\), far beyond what temperature "
                       r"changes \(a few %\): gravity in g\? a sign or axis convention of that level's reference gravity\?$"):
        fit_thermal(rec, 2, usable=np.ones(len(rec), bool))


def _planar(rec: Recording) -> Recording:
    """``rec`` with only the poses whose reference lies within 25 deg of the table's x-y plane, projected onto it: a
    run whose poses never tilt z (coplanar), with the signal the simulation gave them."""
    g = rec.gref_mps2
    keep = (rec.pose_id >= 0) & (np.abs(g[:, 2]) < 0.42 * np.linalg.norm(g, axis=1))
    out = rec.select(keep)
    out.gref_mps2[:, 2] = 0.0
    return out


def test_a_level_whose_poses_are_coplanar_does_not_count_for_the_temperature_degree() -> None:
    """Degree 1 needs two levels whose own poses span the frame: with the second level's poses all in the x-y plane,
    the z rows of the temperature terms are not determined, and degree 1 is refused naming that level."""
    from fbg_accel_calibration.thermal_fit import check_level_excitation, level_excitation

    M, b = _truth(1, np.random.default_rng(9))
    full = _simulate(M, b, (16.0, 45.0), center=30.5, scale=14.5, n_poses=40, seed=9)
    flat = Recording.concatenate([full.select(full.run_id == 0), _planar(full.select(full.run_id == 1))])
    stats = prepare(flat, 1, usable=np.ones(len(flat), bool)).stats
    ok, notes = level_excitation(stats)
    assert ok == 1 and len(notes) == 1 and notes[0].startswith("temperature level 1:"), notes
    check_level_excitation(stats, 0)
    with pytest.raises(NotIdentifiedError, match=r"degree 1 in temperature needs 2 temperature levels whose poses span "
                       r"the table frame, only 1 do \(temperature level 1: its \d+ poses do not tilt the table direction "
                       r".*\); use degree <= 0 or repeat the pose plan at that level$"):
        check_level_excitation(stats, 1)
    assert level_excitation(prepare(full, 1, usable=np.ones(len(full), bool)).stats)[0] == 2


def test_reference_reach_names_each_axis_and_way_the_poses_never_reached() -> None:
    from fbg_accel_calibration.thermal_fit import reference_reach_warnings

    assert reference_reach_warnings([[-9.8, 9.8], [-9.8, 9.8], [-9.8, 9.8]]) == []
    lines = reference_reach_warnings([[-1.36, 1.36], [-9.8, 9.8], [-9.8, 2.0]])
    assert len(lines) == 2
    assert "table x axis down or up (their reference along it spans -1.36 .. +1.36" in lines[0]
    assert "table z axis up (" in lines[1] and lines[1].endswith("record poses with z up")


def test_the_recording_excitation_check_takes_the_posed_samples_only() -> None:
    """``diagnose``'s cheap check before its long computation: coplanar poses are refused, a recording whose
    samples lack a pose is refused as such, and samples between poses (a reference and a temperature, no pose id) do
    not enter it."""
    from fbg_accel_calibration.thermal_fit import check_recording_excitation

    M, b = _truth(0, np.random.default_rng(10))
    rec = _simulate(M, b, (24.0,), center=24.0, scale=1.0, n_poses=30, seed=10)
    assert np.all(check_recording_excitation(rec) > 1.0)
    with pytest.raises(NotIdentifiedError, match=r"so the z row of M and b would be fitted to a constant \(a dead axis\); "
                       "record poses that tilt that axis too"):
        check_recording_excitation(_planar(rec))
    # between poses: no pose id, and a reference that is not one (a CSV row between poses carries any)
    moving = Recording(rec.t_s, rec.ref, rec.xyz, rec.temp_c, np.tile([0.0, 0.0, 9.80665], (len(rec), 1)),
                       np.full(len(rec), -1))
    with pytest.raises(NotIdentifiedError,
                       match=r"no pose was held: every one of the \d+ samples was taken while the table moved"):
        check_recording_excitation(moving)
    flat_and_moving = Recording.concatenate([_planar(rec), moving])
    with pytest.raises(NotIdentifiedError, match="coplanar"):
        check_recording_excitation(flat_and_moving)
