"""Thermal model fit (eq. 28-30) and degree selection by held-out cross-validation; the fit's building blocks on exact
synthetic data: the refusals and their words, the per-cell sums against sums worked out row by row, the temperature
levels, the normal equations and the sensor a recording names."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from fbg_accel_calibration.fit import thermal_fit as tf
from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_calibration.fit.fit_stream import prepare
from fbg_accel_calibration.fit.model_selection import held_out_predictions, select_degree
from fbg_accel_calibration.fit.thermal_fit import (
    CellAccumulator,
    NotIdentifiedError,
    TemperatureClusters,
    accumulate_cells,
    check_identified,
    check_level_consistency,
    check_level_excitation,
    check_pose_excitation,
    check_recording_excitation,
    coefficients_to_model,
    count_orientations,
    design_matrix,
    model_to_coefficients,
    reference_range,
    reference_reach_warnings,
    residuals,
    sensor_id_of,
    solve_normal_equations,
    solve_normal_equations_each,
    sub_columns,
    temperature_levels,
    temperature_scaling,
)
from fbg_accel_calibration.io.recording import Recording
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
    # into a given buffer, in place (diagnosis fills the first columns of its wider matrix so)
    buffer = np.full((7, 3 * 4 + 2), np.nan)
    design_matrix(psi, tau, 2, out=buffer[:, :12])
    np.testing.assert_allclose(buffer[:5, :12], expected)
    assert np.isnan(buffer[5:]).all() and np.isnan(buffer[:, 12:]).all()
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


def test_the_rss_of_some_cells_is_that_of_every_cell_at_those_cells_bit_for_bit() -> None:
    """The held-out scores take the RSS of a fold's held-out cells alone: each cell's value from its own sums, the same
    bits as among every cell's (the degree's choice compares them at no tolerance)."""
    rng = np.random.default_rng(7)
    M, b = _truth(2, rng)
    rec = _simulate(M, b, (10.0, 20.0, 30.0, 40.0), center=25.0, scale=15.0, psi_noise=1e-4, n=30)
    stats = prepare(rec, 3, usable=np.ones(len(rec), bool)).cell_stats(3)
    for degree in range(4):
        A = tf.solve_normal_equations(*stats.select(np.ones(len(stats.count), bool), degree)[:2])[0]
        every = stats.cell_rss(A, degree)
        for cells in [stats.pose == stats.pose[0], stats.level == stats.level[-1], rng.random(len(every)) < 0.3]:
            assert np.array_equal(stats.cell_rss(A, degree, cells), every[cells])


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

    from fbg_accel_calibration.fit.fit_stream import prepare_stream
    from fbg_accel_calibration.io.mcap_reader import McapSampleStream
    from fbg_accel_calibration.io.mcap_writer import write_recording
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
    from fbg_accel_calibration.fit.thermal_fit import level_excitation

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


def test_the_recording_excitation_check_takes_the_posed_samples_only() -> None:
    """``diagnose``'s cheap check before its long computation: coplanar poses are refused, a recording whose
    samples lack a pose is refused as such, and samples between poses (a reference and a temperature, no pose id) do
    not enter it."""
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


# --- the building blocks on exact synthetic data ---------------------------------------------------------------------
M0 = np.array([[80.0, 1.5, -2.0], [0.5, 78.0, 1.0], [-1.0, 2.5, 107.0]])  # near the paper's linear fit (section 3.6)
B0 = np.array([-101.0, -153.0, -137.0])
SIX = G * np.vstack([np.eye(3), -np.eye(3)])  # the six-position plan's references, m/s^2
REFUSAL_TAIL = ("so the {axis} row of M and b would be fitted to a constant (a dead axis); record poses that tilt that "
                "axis too (at least 4 non-coplanar poses, e.g. the six-position plan)")
NUMBER = r"([-+0-9.e]+)"


def _rows(poses: np.ndarray, counts: list[int] | int, M: np.ndarray = M0, b: np.ndarray = B0
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Psi (N, 3), reference (N, 3) and pose ids (N,) of ``counts`` samples at each reference of ``poses``, with the Psi
    that eq. 28 of degree 0 (M, b) maps exactly onto it."""
    counts = [counts] * len(poses) if isinstance(counts, int) else counts
    gref = np.repeat(poses, counts, axis=0)
    psi = np.linalg.solve(M, (gref - b).T).T
    return psi, gref, np.repeat(np.arange(len(poses)), counts)


def _stats(poses: np.ndarray, counts: list[int] | int = 5, psi: np.ndarray | None = None) -> tf.CellStats:
    exact, gref, pose = _rows(poses, counts)
    n = len(gref)
    return accumulate_cells(exact if psi is None else psi, np.zeros(n), gref, pose, np.zeros(n, np.int64), 0)


def _plane(normal: np.ndarray, n: int = 5) -> np.ndarray:
    """``n`` references of magnitude g in the plane through 0 normal to ``normal``."""
    normal = normal / np.linalg.norm(normal)
    e1 = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    ang = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False) + 0.3
    return G * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)


def _levels(models: list[np.ndarray], poses: list[np.ndarray], noise: float = 0.0, dead: tuple[int, ...] = ()
            ) -> tf.CellStats:
    """Degree-0 sums of one temperature level per model (M of that level, b = B0 at all) with that level's poses (5
    samples each); ``noise`` (Psi units) added to the levels whose poses are not the six positions; at the levels
    ``dead`` the x channel reads the same in every pose."""
    rng = np.random.default_rng(3)
    parts = []
    for lev, (M, pz) in enumerate(zip(models, poses, strict=True)):
        psi, gref, pose = _rows(pz, 5, M)
        if pz is not SIX:
            psi = psi + rng.normal(0.0, noise, psi.shape)
        if lev in dead:
            psi[:, 0] = 0.11
        parts.append((psi, gref, pose, np.full(len(pose), lev)))
    psi, gref, pose, level = (np.concatenate(x) for x in zip(*parts, strict=True))
    return accumulate_cells(psi, np.zeros(len(pose)), gref, pose, level, 0)


# --- what a recording's metadata names -----------------------------------------------------------------------------


def test_the_sensor_a_recording_names_comes_from_its_run_record_then_its_top_level() -> None:
    assert sensor_id_of({"run": {"sensor_id": "acc4"}}) == "acc4"
    assert sensor_id_of({"sensor_id": "acc5"}) == "acc5"
    assert sensor_id_of({"run": {"sensor_id": "acc4"}, "sensor_id": "acc5"}) == "acc4"
    assert sensor_id_of({"run": {"sensor_id": ""}, "sensor_id": "acc5"}) == "acc5"  # an empty id names nothing
    assert sensor_id_of({"run": "acc4"}) is None
    assert sensor_id_of({}) is None
    # several parts: the one sensor they name, 'unknown' (the default of the node and import) naming none
    assert sensor_id_of({"parts": [{"run": {"sensor_id": "unknown"}}, {"run": {"sensor_id": "acc4"}}]}) == "acc4"
    assert sensor_id_of({"parts": [{"run": {"sensor_id": "acc4"}}, "not a part", {"sensor_id": "acc4"}]}) == "acc4"
    assert sensor_id_of({"parts": [{"run": {"sensor_id": "unknown"}}, {}]}) == "unknown"
    assert sensor_id_of({"parts": [{"source": "a.mcap"}], "sensor_id": "acc6"}) == "acc6"
    # parts that are no list of parts: the metadata itself is the one part
    assert sensor_id_of({"parts": [], "sensor_id": "acc6"}) == "acc6"
    assert sensor_id_of({"parts": ({"sensor_id": "a"}, {"sensor_id": "b"}), "sensor_id": "acc6"}) == "acc6"


def test_recordings_of_two_sensors_are_refused_naming_each_sensor_s_inputs() -> None:
    md = {"parts": [{"run": {"sensor_id": "acc4"}, "source": "runs/a.mcap"}, {"run": {"sensor_id": "acc7"}},
                    {"run": {"sensor_id": "unknown"}, "source": "runs/c.mcap"},
                    {"sensor_id": "acc4", "source": "runs/d.mcap"}]}
    with pytest.raises(ValueError) as err:
        sensor_id_of(md)
    assert str(err.value) == ("the recordings are of 2 different sensors (sensor 'acc4': runs/a.mcap, runs/d.mcap; "
                              "sensor 'acc7': input 2); a calibration describes one sensor: give the recordings of one "
                              "sensor only")


# --- the poses and the signal must span the frame ------------------------------------------------------------------


def test_the_pose_spreads_are_the_rms_spreads_of_the_cells_references_weighted_by_their_samples() -> None:
    """Six positions with 10 or 20 samples: the count-weighted mean is -g/9 on every axis, the scatter
    g^2/81 (27 I - 1 1^T), whose principal RMS spreads are g sqrt(24)/9 along (1, 1, 1) and g sqrt(27)/9 twice."""
    spread = check_pose_excitation(_stats(SIX, [10, 10, 10, 20, 20, 20]))
    np.testing.assert_allclose(spread, G * np.sqrt([24.0, 27.0, 27.0]) / 9.0, rtol=1e-12)


def test_poses_that_do_not_span_the_frame_are_refused_naming_their_shape_direction_and_number() -> None:
    empty = accumulate_cells(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64),
                             np.zeros(0, np.int64), 0)
    with pytest.raises(NotIdentifiedError) as err:
        check_pose_excitation(empty)
    assert str(err.value) == "no usable static samples"
    one = _stats(SIX[:1], 1)  # one sample: a cell of one pose
    with pytest.raises(NotIdentifiedError, match=r"^the 1 poses' reference specific forces coincide: "):
        check_pose_excitation(one)
    with pytest.raises(NotIdentifiedError, match=r"^the 2 poses' reference specific forces are collinear: .* the [xy] "
                       r"row of M and b would be fitted to a constant"):
        check_pose_excitation(_stats(SIX[[2, 5]]))
    # five poses in the plane normal to a direction off every axis; its small y component prints as 0.00, not -0.00
    normal = np.array([-0.6, -0.003, 0.8])
    with pytest.raises(NotIdentifiedError) as err:
        check_pose_excitation(_stats(_plane(normal)))
    msg = re.fullmatch(r"the 5 poses' reference specific forces are coplanar: their RMS spread along the table "
                       rf"direction \(-0\.60, 0\.00, 0\.80\) is {NUMBER} m/s\^2 \(< 0\.49\), "
                       + re.escape(REFUSAL_TAIL.format(axis="z")), str(err.value))
    assert msg, str(err.value)
    assert float(msg[1]) < 1e-5  # the spread along the normal, not along the plane


def test_a_dead_or_copied_channel_is_refused_and_a_weak_one_is_not() -> None:
    exact, _, _ = _rows(SIX, 5)
    dead = exact.copy()
    dead[:, 0] = 0.11  # the x channel reads the same in every pose
    with pytest.raises(NotIdentifiedError) as err:
        check_pose_excitation(_stats(SIX, psi=dead))
    msg = re.fullmatch(rf"the sensor's Psi = counts / ref barely changes along \(1\.00, 0\.00, 0\.00\) between poses "
                       rf"\({NUMBER}, vs {NUMBER} along the strongest direction\): a channel is dead, saturated or copied, "
                       r"so M cannot be determined; check the x/y/z_counts columns and the fibre connections",
                       str(err.value))
    assert msg, str(err.value)
    assert float(msg[1]) < 1e-6 and float(msg[2]) > 0.03
    with pytest.raises(NotIdentifiedError) as err:
        check_pose_excitation(_stats(SIX, psi=np.tile([0.1, 0.2, 0.3], (30, 1))))
    assert str(err.value) == ("the counts give the same Psi = counts / ref in every pose (identical samples?): a channel "
                              "is dead, saturated or copied, so M cannot be determined; check the x/y/z_counts columns "
                              "and the fibre connections")
    # an x channel 50 times less sensitive than the others (Psi spread 1.4e-3 against 0.07) is a sensor, not a dead one
    weak, gref, pose = _rows(SIX, 5, M=np.diag([4000.0, 78.0, 107.0]))
    spread = check_pose_excitation(accumulate_cells(weak, np.zeros(30), gref, pose, np.zeros(30, np.int64), 0))
    np.testing.assert_allclose(spread, G / np.sqrt(3.0), rtol=1e-12)


def test_the_recording_check_takes_every_usable_posed_sample_and_only_those() -> None:
    """Pose 0 (the only one tilting z), a sample without a reference, one with NaN counts and one without source
    light: the check keeps pose 0 and leaves the three bad samples out."""
    poses = np.vstack([SIX[2], SIX[[0, 1, 3, 4]]])
    psi, gref, pose = _rows(poses, 6)
    ref = np.full(len(pose), 880.0)
    xyz = psi * ref[:, None]
    gref[7] = np.nan
    xyz[13] = np.nan
    ref[19] = 10.0  # below LOW_REFERENCE_COUNTS: no source light
    rec = Recording(np.arange(len(pose)) * 0.01, ref, xyz, np.full(len(pose), 24.0), gref, pose)
    spread = check_recording_excitation(rec)
    assert spread[0] > 1.0
    only_zero = Recording(rec.t_s, rec.ref, rec.xyz, rec.temp_c, rec.gref_mps2, np.where(pose == 0, 0, -1))
    with pytest.raises(NotIdentifiedError, match=r"^the 1 poses' reference specific forces coincide"):
        check_recording_excitation(only_zero)
    no_temperature = Recording(rec.t_s, rec.ref, rec.xyz, np.full(len(pose), np.nan), rec.gref_mps2, pose)
    with pytest.raises(NotIdentifiedError) as err:
        check_recording_excitation(no_temperature)
    assert str(err.value) == "no sample has a pose, a finite reference, a valid temperature and finite counts"


def test_reference_range_and_orientations_are_those_of_the_cells_means() -> None:
    """A cell of one sample counts; a cell whose mean reference is zero has no direction; a small reference is a
    direction all the same; two cells within the tolerance (0.5 deg apart) are one orientation."""
    tilt = np.radians(0.5)
    poses = np.array([[0.0, 0.0, G], [0.0, G * np.sin(tilt), G * np.cos(tilt)], [0.0, G, 0.0], [0.5, 0.0, 0.0],
                      [0.0, 0.0, 0.0], [-3.0, 4.0, 0.0]])
    psi = np.random.default_rng(1).normal(size=(11, 3))
    gref = np.repeat(poses, [3, 2, 1, 2, 1, 2], axis=0)
    pose = np.repeat(np.arange(6), [3, 2, 1, 2, 1, 2])
    stats = accumulate_cells(psi, np.zeros(11), gref, pose, np.zeros(11, np.int64), 0)
    assert count_orientations(stats) == 4
    np.testing.assert_allclose(reference_range(stats), [[-3.0, 0.5], [0.0, G], [0.0, G]], rtol=1e-12, atol=1e-12)


def test_reference_reach_lines_word_for_word() -> None:
    assert reference_reach_warnings([[-9.8, 9.8], [-9.8, 9.8], [-9.8, 9.8]]) == []
    lines = reference_reach_warnings([[-1.36, 1.36], [-9.8, 9.8], [-9.8, 2.0]])
    assert lines == [
        "the poses never reach 4.90 m/s^2 (half of g) with the table x axis down or up (their reference along it spans "
        "-1.36 .. +1.36 m/s^2): beyond that the calibration extrapolates eq. 28 over a response it never saw, which the "
        "held-out figures cannot show; record poses with x down and up",
        "the poses never reach 4.90 m/s^2 (half of g) with the table z axis up (their reference along it spans -9.80 .. "
        "+2.00 m/s^2): beyond that the calibration extrapolates eq. 28 over a response it never saw, which the held-out "
        "figures cannot show; record poses with z up"]


# --- temperature levels: the degree they identify and their consistency ----------------------------------------------


def test_the_degree_refusal_lists_every_level_whose_poses_do_not_span_the_frame() -> None:
    flat = _plane(np.array([0.0, 0.0, 1.0]))
    stats = _levels([M0] * 4, [SIX, flat, flat, SIX], noise=1e-4)
    check_level_excitation(stats, 1)
    with pytest.raises(NotIdentifiedError) as err:
        check_level_excitation(stats, 2)
    note = (r"temperature level {}: its 5 poses do not tilt the table direction \(0\.00, 0\.00, 1\.00\) "
            rf"\(spread {NUMBER} m/s\^2\)")
    msg = re.fullmatch(r"degree 2 in temperature needs 3 temperature levels whose poses span the table frame, only 2 do "
                       rf"\({note.format(1)}; {note.format(2)}\); use degree <= 1 or repeat the pose plan at that level",
                       str(err.value))
    assert msg, str(err.value)
    assert float(msg[1]) < 1e-5 and float(msg[2]) < 1e-5


def test_a_level_far_from_the_others_is_refused_with_its_own_and_the_others_change() -> None:
    """Exact sums: each level's M is known, so are the relative changes the message gives (b alike at every level)."""
    levels_c = np.array([16.0, 24.0, 45.0])
    with pytest.raises(NotIdentifiedError) as err:
        check_level_consistency(_levels([M0, 1.2448 * M0, -1.5 * M0], [SIX] * 3), levels_c)
    assert str(err.value) == ("the temperature level(s) at 45.0 degC (250 %) give an M that differs from the other "
                              "levels' by more than 30 % (the others: within 24 %), far beyond what temperature changes "
                              "(a few %): gravity in g? a sign or axis convention of that level's reference gravity?")
    check_level_consistency(_levels([M0, 1.02 * M0, 0.99 * M0], [SIX] * 3), levels_c)
    # two levels: each against the other, both beyond the bound
    with pytest.raises(NotIdentifiedError) as err:
        check_level_consistency(_levels([M0, 1.5 * M0], [SIX] * 2), levels_c[:2])
    assert str(err.value) == ("the temperature level(s) at 16.0 degC (33 %), 24.0 degC (50 %) give an M that differs from "
                              "the other level's by more than 30 %, far beyond what temperature changes (a few %): "
                              "gravity in g? a sign or axis convention of that level's reference gravity?")
    check_level_consistency(_levels([M0, 1.1 * M0], [SIX] * 2), levels_c[:2])


def test_levels_whose_poses_cannot_determine_m_are_left_out_of_the_consistency_check() -> None:
    """Level 0's poses are coplanar (their M along the normal is noise), level 1's x channel is dead (singular normal
    equations): both are skipped, and levels 2 and 3, 50 % apart, are still compared and refused."""
    levels_c = np.array([10.0, 20.0, 30.0, 40.0])
    flat = _plane(np.array([0.0, 0.0, 1.0]))
    stats = _levels([M0, M0, M0, 1.5 * M0], [flat, SIX, SIX, SIX], noise=1e-4, dead=(1,))
    with pytest.raises(NotIdentifiedError) as err:
        check_level_consistency(stats, levels_c)
    assert str(err.value).startswith("the temperature level(s) at 30.0 degC (33 %), 40.0 degC (50 %) give an M that "
                                     "differs from the other level's by")


# --- normal equations -----------------------------------------------------------------------------------------------


def test_the_normal_equations_give_their_scaled_condition_and_refuse_a_singular_or_zero_regressor() -> None:
    """Scaled X^T X [[1, .5, 0], [.5, 1, 0], [0, 0, 1]] (eigenvalues 0.5, 1, 1.5): condition 3 whatever the columns'
    scale."""
    s = np.array([[1.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 1.0]])
    d = np.array([2.0, 3.0, 5.0])
    xtg = np.arange(9.0).reshape(3, 3)
    for scale in (1.0, 1e-4):
        xtx = scale * s * np.outer(d, d)
        A, cond = solve_normal_equations(xtx, xtg)
        assert cond == pytest.approx(3.0, rel=1e-12)
        np.testing.assert_allclose(A, np.linalg.solve(xtx, xtg), rtol=1e-12)
    solve_normal_equations(s, xtg, rcond=0.25)  # condition 3 < 4
    with pytest.raises(NotIdentifiedError) as err:
        solve_normal_equations(s, xtg, rcond=0.5)  # condition 3 >= 2
    assert str(err.value) == "normal equations are singular (condition number 3)"
    with pytest.raises(NotIdentifiedError) as err:  # not positive definite: no least-squares problem has it
        solve_normal_equations(np.array([[1.0, 2.0], [2.0, 1.0]]), np.ones((2, 3)))
    assert str(err.value) == "normal equations are singular (condition number inf)"
    with warnings.catch_warnings():  # two equal regressors: refused as such, without a numpy division warning
        warnings.simplefilter("error")
        with pytest.raises(NotIdentifiedError) as err:
            solve_normal_equations(np.array([[1.0, 1.0], [1.0, 1.0]]), np.ones((2, 3)))
    assert str(err.value) == "normal equations are singular (condition number inf)"
    with pytest.raises(NotIdentifiedError) as err:
        solve_normal_equations(np.diag([1.0, 0.0, 1.0]), xtg)
    assert str(err.value) == "a regressor is identically zero on the data"


def test_a_stack_of_normal_equations_is_solved_as_each_alone_bit_for_bit_with_the_same_error() -> None:
    """``solve_normal_equations_each`` (a cross-validation's folds) gives each fold's ``solve_normal_equations``
    coefficients bit for bit, for stacks of 1 to 12 systems of 1 to 30 regressors whose columns differ by orders of
    magnitude; where one fold is singular, lacks a regressor or holds NaN, it raises what solving them one by one
    raises first (that fold's message), without a numpy warning."""
    rng = np.random.default_rng(11)

    def one_by_one(xtx: np.ndarray, xtg: np.ndarray) -> np.ndarray | str:
        try:
            return np.stack([solve_normal_equations(a, b)[0] for a, b in zip(xtx, xtg, strict=True)])
        except (NotIdentifiedError, np.linalg.LinAlgError) as exc:
            return f"{type(exc).__name__}: {exc}"

    kinds = ("fine", "singular", "zero", "nan", "indefinite")
    for trial in range(300):
        K, p = int(rng.integers(1, 13)), int(rng.integers(1, 31))
        scale = 10.0 ** rng.uniform(-6, 6, p)
        X = rng.standard_normal((K, 3 * p + 5, p)) * scale
        xtx, xtg = np.einsum("kni,knj->kij", X, X), np.einsum("kni,knj->kij", X, rng.standard_normal((K, 3 * p + 5, 3)))
        for f in rng.choice(K, size=int(rng.integers(0, min(K, 3) + 1)), replace=False):
            kind = kinds[int(rng.integers(1, len(kinds)))] if p > 1 else "zero"
            if kind == "singular":  # two equal regressors
                xtx[f, :, -1], xtx[f, -1, :] = xtx[f, :, 0], xtx[f, 0, :]
                xtx[f, -1, -1] = xtx[f, 0, 0]
            elif kind == "zero":
                xtx[f, :, -1] = xtx[f, -1, :] = 0.0
            elif kind == "nan":
                xtx[f, 0, 0] = np.nan
            elif kind == "indefinite":  # a correlation beyond 1 between two regressors: no least-squares problem
                xtx[f, 0, -1] = xtx[f, -1, 0] = 2.0 * np.sqrt(xtx[f, 0, 0] * xtx[f, -1, -1])
        want = one_by_one(xtx, xtg)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                got = solve_normal_equations_each(xtx, xtg)
            except (NotIdentifiedError, np.linalg.LinAlgError) as exc:
                got = f"{type(exc).__name__}: {exc}"
        if isinstance(want, str):
            assert got == want, trial
        else:
            assert not isinstance(got, str) and got.shape == want.shape and got.tobytes() == want.tobytes(), trial


def test_the_jacobi_scaled_solve_is_the_fits_and_floors_a_missing_regressor_on_request() -> None:
    """``jacobi_solve`` (the one scaled solve of the fit, its uncertainty, the slow error and the diagnosis' held-out
    null) gives the fit's coefficients bit for bit and solves a system whose columns differ by 12 orders of magnitude;
    a zero column is refused as the fit refuses it, or with ``min_diagonal`` left to the solve as a singular matrix
    (no division by zero)."""
    rng = np.random.default_rng(4)
    X = rng.standard_normal((50, 4)) * np.array([1e-6, 1.0, 1e3, 1e6])
    A_true = rng.standard_normal((4, 3)) / np.array([1e-6, 1.0, 1e3, 1e6])[:, None]
    xtx, xtg = X.T @ X, X.T @ (X @ A_true)
    A = tf.jacobi_solve(xtx, xtg)
    assert np.array_equal(A, solve_normal_equations(xtx, xtg)[0])
    np.testing.assert_allclose(A, A_true, rtol=1e-8)
    d, s = tf.jacobi_scaling(xtx)
    np.testing.assert_allclose(np.diag(s), 1.0, rtol=1e-14)
    np.testing.assert_allclose(d, np.linalg.norm(X, axis=0), rtol=1e-12)
    zero = np.diag([1.0, 0.0, 1.0])
    with pytest.raises(NotIdentifiedError, match="identically zero"):
        tf.jacobi_solve(zero, np.ones((3, 2)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(np.linalg.LinAlgError):
            tf.jacobi_solve(zero, np.ones((3, 2)), min_diagonal=1e-300)


def test_a_negative_degree_and_a_sub_model_above_its_model_are_refused() -> None:
    with pytest.raises(NotIdentifiedError) as err:
        check_identified(-1, 3)
    assert str(err.value) == "degree must be >= 0, got -1"
    with pytest.raises(ValueError) as err:
        sub_columns(3, 2)
    assert str(err.value) == "degree 3 > 2"


# --- temperature levels and scaling ---------------------------------------------------------------------------------


def test_temperature_scaling_maps_the_range_onto_plus_minus_one_and_one_level_onto_scale_one() -> None:
    assert temperature_scaling(np.array([20.0, 22.4, 21.0])) == pytest.approx((21.2, 1.2), rel=1e-12)
    assert temperature_scaling(np.array([24.0, 24.6])) == pytest.approx((24.3, 1.0), rel=1e-12)


def test_temperature_levels_follow_the_gap_and_the_width_asked_for() -> None:
    labels, means = temperature_levels(np.array([np.nan, np.nan]))
    assert labels.tolist() == [-1, -1] and means.shape == (0,)
    labels, means = temperature_levels(np.array([24.0, 16.3, 16.0, 24.4]))
    assert labels.tolist() == [1, 0, 0, 1]
    np.testing.assert_allclose(means, [16.15, 24.2], rtol=1e-12)
    assert len(temperature_levels(np.array([20.0, 20.2, 22.0, 22.1]), gap_c=1.0)[1]) == 2  # 1.8 degC apart
    assert len(temperature_levels(np.array([20.0, 20.2, 22.0, 22.1]), gap_c=2.0)[1]) == 1
    # a sweep wider than the width is split into equal bins: 9 degC into 3 of 3 degC, or 2 of 4.5
    sweep = np.linspace(40.0, 49.0, 50)
    assert len(temperature_levels(sweep)[1]) == 3
    assert len(temperature_levels(sweep, max_width_c=5.0)[1]) == 2
    five = np.linspace(40.0, 45.0, 12)  # 2 bins of 2.5 degC
    assert temperature_levels(five)[0].tolist() == [0] * 6 + [1] * 6
    fine = 20.05 + 0.1 * np.arange(12)  # 1.1 degC at a width of 0.5: 3 bins of 0.367 degC
    assert temperature_levels(fine, max_width_c=0.5)[0].tolist() == [0] * 4 + [1] * 4 + [2] * 4


def test_temperatures_exactly_one_gap_apart_are_one_level_whole_or_in_parts() -> None:
    """The documented rule is "merged wherever the gap is <= gap_c": readings of a 0.5 degC-resolution sensor are
    often exactly one gap apart (20.0 and 21.0 at the default 1 degC), and they are one level, whether they come in
    one array or in two blocks of the streamed fit."""
    assert len(temperature_levels(np.array([21.0, 20.0, 21.0]))[1]) == 1
    assert len(temperature_levels(np.array([20.0, 21.5]))[1]) == 2
    clusters = TemperatureClusters(1.0)
    clusters.add(np.array([20.0]))
    clusters.add(np.array([21.0]))
    np.testing.assert_array_equal(clusters.lo, [20.0])
    np.testing.assert_array_equal(clusters.hi, [21.0])


def test_temperature_clusters_added_in_parts_are_those_of_the_whole() -> None:
    """As the streamed fit adds them, block by block: a block of one sample counts, and a cluster's highest
    temperature decides whether the next block's samples join it."""
    clusters = TemperatureClusters(1.0)
    clusters.add(np.array([24.0, 16.3, 16.0, 24.4]))
    np.testing.assert_array_equal(clusters.lo, [16.0, 24.0])
    np.testing.assert_array_equal(clusters.hi, [16.3, 24.4])
    clusters.add(np.array([25.2]))  # 0.8 degC above 24.4: the same level
    clusters.add(np.array([]))
    clusters.add(np.array([40.0]))
    np.testing.assert_array_equal(clusters.lo, [16.0, 24.0, 40.0])
    np.testing.assert_array_equal(clusters.hi, [16.3, 25.2, 40.0])


# --- the per-cell sums ------------------------------------------------------------------------------------------------


def _campaign(seed: int = 2) -> dict[str, np.ndarray]:
    """640 rows in 8 visits of unequal length over two runs: pose 7 is visited twice in run 0 (one cell, two visits),
    and pose 3 at level 1 goes on from run 0 into run 1 (two cells, two visits)."""
    rng = np.random.default_rng(seed)
    lengths = [90, 50, 120, 70, 100, 60, 80, 70]
    pose_of = [7, 2, 7, 5, 3, 3, 0, 2]
    level_of = [0, 0, 0, 1, 1, 1, 1, 0]
    run_of = [0, 0, 0, 0, 0, 1, 1, 1]
    n = sum(lengths)
    return {"psi": rng.normal(size=(n, 3)), "tau": rng.uniform(-1.0, 1.0, n), "gref": rng.normal(size=(n, 3)),
            "pose": np.repeat(pose_of, lengths), "level": np.repeat(level_of, lengths),
            "run": np.repeat(run_of, lengths), "visit": np.repeat(np.arange(8), lengths)}


def _accumulated(c: dict[str, np.ndarray], chunk: int, degree: int = 1) -> tf.CellStats:
    acc = CellAccumulator(degree, chunk)
    for a in range(0, len(c["tau"]), chunk):
        sl = slice(a, a + chunk)
        acc.add(c["psi"][sl], c["tau"][sl], c["gref"][sl], c["pose"][sl], c["level"][sl], c["run"][sl])
    return acc.finish()


def _check_sums(stats: tf.CellStats, c: dict[str, np.ndarray], degree: int = 1, visits: bool = True) -> None:
    X, G_ = design_matrix(c["psi"], c["tau"], degree), c["gref"]
    cells = sorted({(p, lv, r) for p, lv, r in zip(c["pose"], c["level"], c["run"], strict=True)})
    assert list(zip(stats.pose.tolist(), stats.level.tolist(), strict=True)) == [(p, lv) for p, lv, _ in cells]
    for i, (p, lv, r) in enumerate(cells):
        m = (c["pose"] == p) & (c["level"] == lv) & (c["run"] == r)
        np.testing.assert_allclose(stats.xtx[i], X[m].T @ X[m], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(stats.xtg[i], X[m].T @ G_[m], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(stats.gtg[i], (G_[m] ** 2).sum(axis=0), rtol=1e-10)
        np.testing.assert_allclose(stats.xsum[i], X[m].sum(axis=0), rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(stats.gsum[i], G_[m].sum(axis=0), rtol=1e-10, atol=1e-10)
        assert stats.count[i] == m.sum()
    v = c["visit"]
    lengths = np.bincount(v)
    assert stats.visit_lengths.tolist() == lengths.tolist()
    xsum_v = np.array([X[v == k].sum(axis=0) for k in range(len(lengths))])
    np.testing.assert_allclose(stats.visit_outer, (xsum_v / lengths[:, None]).T @ xsum_v, rtol=1e-10, atol=1e-10)
    if visits:  # each visit's own sums, in the order the visits ended, and its cell
        np.testing.assert_allclose(stats.visit_xtx, [X[v == k].T @ X[v == k] for k in range(len(lengths))],
                                   rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(stats.visit_xtg, [X[v == k].T @ G_[v == k] for k in range(len(lengths))],
                                   rtol=1e-10, atol=1e-10)
        first = [int(np.flatnonzero(v == k)[0]) for k in range(len(lengths))]
        assert stats.visit_cell.tolist() == [cells.index((c["pose"][f], c["level"][f], c["run"][f])) for f in first]


@pytest.mark.parametrize("chunk", [1, 7, 639, 640])
def test_the_cell_sums_are_the_rows_sums_whatever_the_chunks(chunk: int) -> None:
    """Cells ordered by (pose, level, run), every sum equal to the one over its rows; visits joined across chunks and
    ended where the cell or the run changes (one row per chunk, a last chunk of one row, one chunk for all)."""
    c = _campaign()
    _check_sums(_accumulated(c, chunk), c)


def test_interleaved_cells_and_the_one_run_form_give_the_same_sums() -> None:
    c = _campaign()
    one = {k: v[c["run"] == 0] for k, v in c.items()}
    stats = accumulate_cells(one["psi"], one["tau"], one["gref"], one["pose"], one["level"], 1, chunk=7)
    _check_sums(stats, one)
    # every row its own visit, the cells interleaved: grouped by sorting
    rng = np.random.default_rng(5)
    k = rng.permutation(len(one["tau"]))[:200]
    mixed = {key: v[k] for key, v in one.items()}
    mixed["visit"] = np.cumsum(np.r_[0, (np.diff(mixed["pose"]) != 0) | (np.diff(mixed["level"]) != 0)])
    _check_sums(accumulate_cells(mixed["psi"], mixed["tau"], mixed["gref"], mixed["pose"], mixed["level"], 1), mixed)
    # chunks larger than the default one (65536 rows) and than the samples
    n = 70000
    big = accumulate_cells(np.ones((n, 3)), np.zeros(n), np.ones((n, 3)), np.arange(n) // 35000, np.zeros(n, int), 0,
                           chunk=100000)
    assert big.count.tolist() == [35000, 35000]


def test_each_visit_s_sums_are_kept_up_to_the_limit_and_dropped_beyond(monkeypatch: pytest.MonkeyPatch) -> None:
    """Beyond MAX_VISIT_SUMS visits the coefficient covariance clusters by cell; the cells' sums stay exact."""
    c = _campaign()
    monkeypatch.setattr(tf, "MAX_VISIT_SUMS", 8)
    _check_sums(_accumulated(c, 640), c)
    monkeypatch.setattr(tf, "MAX_VISIT_SUMS", 7)
    stats = _accumulated(c, 640)
    _check_sums(stats, c, visits=False)
    p = tf.n_params(1)
    assert stats.visit_xtx.shape == (0, p, p) and stats.visit_xtg.shape == (0, p, 3) and stats.visit_cell.shape == (0,)
    assert stats.visit_cell.dtype.kind == "i"  # indexes the cells (coefficient_uncertainty)


def test_level_labels_are_relabelled_at_the_end_and_refused_outside_their_range() -> None:
    psi, gref = np.ones((4, 3)), np.ones((4, 3))
    acc = CellAccumulator(0, 8)
    acc.add(psi, np.zeros(4), gref, np.array([0, 0, 1, 1]), np.array([-65536, 65535, 1, 0]))
    stats = acc.finish()
    assert list(zip(stats.pose.tolist(), stats.level.tolist(), strict=True)) == [(0, -65536), (0, 65535), (1, 0), (1, 1)]
    acc = CellAccumulator(0, 8)
    acc.add(psi, np.zeros(4), gref, np.array([0, 0, 1, 1]), np.array([0, 1, 1, 0]))
    stats = acc.finish(level_map=np.array([9, 4]))
    assert list(zip(stats.pose.tolist(), stats.level.tolist(), strict=True)) == [(0, 4), (0, 9), (1, 4), (1, 9)]
    for bad in (65536, -65537):
        with pytest.raises(ValueError) as err:
            CellAccumulator(0, 8).add(psi[:1], np.zeros(1), gref[:1], np.zeros(1, np.int64), np.array([bad]))
        assert str(err.value) == "temperature level labels must lie in [-65536, 65536)"
    # nothing added (every sample unusable): empty integer labels, relabelled like any others
    empty = CellAccumulator(0, 8).finish(level_map=np.zeros(1, np.int64))
    assert empty.pose.shape == empty.level.shape == (0,) and empty.level.dtype.kind == "i"


def test_selected_sums_and_the_within_visit_scatter_at_a_lower_degree() -> None:
    c = _campaign()
    stats = _accumulated(c, 640)
    cells = stats.level == 1
    xtx, xtg, gtg, n = stats.select(cells, 0)
    rows = c["level"] == 1
    X0 = design_matrix(c["psi"], c["tau"], 0)
    np.testing.assert_allclose(xtx, X0[rows].T @ X0[rows], rtol=1e-10)
    np.testing.assert_allclose(xtg, X0[rows].T @ c["gref"][rows], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(gtg, (c["gref"][rows] ** 2).sum(axis=0), rtol=1e-10)
    assert n == rows.sum()
    A = np.random.default_rng(0).normal(size=(4, 3))
    out = X0 @ A
    scatter = sum(((out[c["visit"] == k] - out[c["visit"] == k].mean(axis=0)) ** 2).sum(axis=0) for k in range(8))
    np.testing.assert_allclose(stats.visit_scatter(A, 0), scatter, rtol=1e-9)


def test_residuals_are_those_of_the_masked_samples() -> None:
    psi, gref, pose = _rows(SIX, 4)
    rec = Recording(np.arange(24) * 0.01, np.full(24, 880.0), psi * 880.0, np.full(24, 24.0), gref + 0.01, pose)
    cal = ThermalCalibration(M=M0[None], b=B0[None], temperature_range_c=(20.0, 30.0))
    mask = pose == 2
    np.testing.assert_allclose(residuals(cal, rec, mask), np.full((4, 3), -0.01), atol=1e-9)
