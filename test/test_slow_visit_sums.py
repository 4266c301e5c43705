"""The slow error of the visit means from sums over the revisits' groups (``structure._Groups``) against the dense
projector P = I - (group means) it stands for: the same estimate and test, for a dense covariance of the visit means
and for a diagonal one given as its diagonal (``slow_wander``: no V x V matrix)."""

from __future__ import annotations

import numpy as np
from held_out_campaign import held_out_campaign
from scipy import stats


def _dense_slow_error(means, cov, unit, pose, run):
    """``slow_visit_error`` written with the dense P: (variance (3,), dof (3,))."""
    key = np.where(pose >= 0, pose * 1_000_003 + run, -1)
    cnt = np.unique(key, return_counts=True)[1][np.unique(key, return_inverse=True)[1]]
    idx = np.flatnonzero((key >= 0) & (cnt >= 2))
    g = np.unique(key[idx], return_inverse=True)[1]
    P = np.eye(len(idx)) - (g[:, None] == g[None, :]) / np.bincount(g)[g][None, :]
    PU = P @ unit[np.ix_(idx, idx)]
    tr_pu = np.trace(PU)
    var, dof = np.zeros(3), np.full(3, np.inf)
    for j in range(3):
        pm = P @ means[idx, j]
        PC = P @ cov[j][np.ix_(idx, idx)]
        var[j] = max((pm @ pm - np.trace(PC)) / tr_pu, 0.0)
        if var[j] > 0:
            PT = PC + var[j] * PU
            dof[j] = 2.0 * var[j] ** 2 / (2.0 * np.sum(PT * PT.T) / tr_pu**2)
    return var, dof


def _campaign(seed: int, dense: bool):
    rng = np.random.default_rng(seed)
    poses, revisits = 13, 5
    V = poses * revisits + 4  # four visits in motion or of a pose seen once
    pose = np.concatenate([rng.permutation(np.repeat(np.arange(poses), revisits)), [-1, -1, 40, 41]])
    run = (np.arange(V) >= V // 2).astype(int)  # two runs: a pose's visits in each run are two groups
    sd = np.array([0.01, 0.02, 0.03])
    if dense:
        B = rng.normal(size=(3, V, V)) / np.sqrt(V)
        cov = np.einsum("jab,jcb->jac", B, B) * sd[:, None, None] ** 2 + np.eye(V) * sd[:, None, None] ** 2
        R = rng.normal(size=(V, V))
        unit = np.eye(V) + 0.1 * (R @ R.T) / V  # symmetric, as every covariance
    else:
        cov = np.stack([np.diag(rng.uniform(0.5, 2.0, V) * s**2) for s in sd])
        unit = np.eye(V)
    means = rng.normal(size=(V, 3)) * sd * 2.0  # beyond the noise: a slow error to estimate
    return means, cov, unit, pose, run


def test_the_slow_error_from_group_sums_is_the_dense_projectors() -> None:
    from fbg_accel_calibration.diagnosis.structure import slow_visit_error

    for seed in range(3):
        for dense in (True, False):
            means, cov, unit, pose, run = _campaign(seed, dense)
            var, dof = _dense_slow_error(means, cov, unit, pose, run)
            assert np.all(var > 0)
            got = slow_visit_error(means, cov, unit, pose, run)
            np.testing.assert_allclose(got.variance, var, rtol=1e-10)
            np.testing.assert_allclose(got.dof, dof, rtol=1e-10)
            if not dense:  # the diagonal alone, U = I: the same figures without a V x V matrix
                diag = slow_visit_error(means, np.diagonal(cov, axis1=1, axis2=2), None, pose, run)
                np.testing.assert_allclose(diag.variance, var, rtol=1e-10)
                np.testing.assert_allclose(diag.dof, dof, rtol=1e-10)
                assert np.array_equal(diag.group, got.group)


def test_the_revisits_test_from_group_sums_is_the_dense_projectors() -> None:
    """``SlowVisitError.beyond`` and the pooled test of ``slow_visit_test`` against their dense forms."""
    from fbg_accel_calibration.diagnosis.structure import SlowVisitError, slow_visit_error, visit_mean_test

    means, cov, unit, pose, run = _campaign(5, True)
    slow = slow_visit_error(means, cov, unit, pose, run)
    bound = np.full(3, 1e-4)
    g = slow.group
    idx = np.flatnonzero(np.bincount(g)[g] >= 2)
    P = np.eye(len(idx)) - (g[idx][:, None] == g[idx][None, :]) / np.bincount(g[idx])[g[idx]][None, :]
    want = np.ones(3)
    for j in range(3):
        pm = P @ means[idx, j]
        PC = P @ (cov[j] + bound[j] * unit)[np.ix_(idx, idx)]
        e, v = np.trace(PC), 2.0 * np.sum(PC * PC.T)
        h = 2.0 * e**2 / v
        want[j] = stats.chi2.sf(pm @ pm * h / e, h)
    np.testing.assert_allclose(slow.beyond(means, cov, unit, bound), want, rtol=1e-8)
    L = (np.arange(g.max() + 1)[:, None] == g[None, :]).astype(float)
    L /= L.sum(axis=1, keepdims=True)
    from fbg_accel_calibration.diagnosis.structure import _Groups

    pool = _Groups(g)
    np.testing.assert_allclose(pool.pooled(cov[1]), L @ cov[1] @ L.T, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(pool.means(means), L @ means, rtol=1e-12, atol=1e-18)
    held = SlowVisitError(slow.variance, slow.dof, slow.revisits, g)
    cov_g = np.stack([L @ c @ L.T for c in cov])
    np.testing.assert_allclose(visit_mean_test(pool.means(means), np.stack([pool.pooled(c) for c in cov]),
                                               held.test_dof(cov_g, L @ unit @ L.T, np.full(3, 50.0)))[1],
                               visit_mean_test(L @ means, cov_g, held.test_dof(cov_g, L @ unit @ L.T,
                                                                                np.full(3, 50.0)))[1], rtol=1e-9)


def test_independent_visit_means_are_tested_from_their_variances_alone() -> None:
    """``slow_visit_test`` of visit means given as their variances (3, V) with the identity for the slow error's unit
    covariance (``residual_structure`` without the held-out null, ``slow_wander``): the figures of the dense diagonal
    matrices, without a V x V matrix."""
    from fbg_accel_calibration.diagnosis.structure import slow_visit_test

    means, cov, unit, pose, run = _campaign(7, False)
    dof = np.full(3, 40.0)
    dense = slow_visit_test(means, cov, unit, pose, run, dof)
    diag = slow_visit_test(means, np.diagonal(cov, axis1=1, axis2=2), None, pose, run, dof)
    assert dense[3].revisits > 0
    for a, b in zip(dense[:3], diag[:3], strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-9)
    np.testing.assert_allclose(diag[4], dense[4], rtol=1e-9)


def test_the_held_out_null_from_its_factors_is_the_exact_covariance_of_white_noise() -> None:
    """``heldout_mean_covariance`` gives each axis' covariance by its factors (``visit_covariance.HeldoutCovariance``):
    its rows (any of them, in any order) and its diagonal are those of sigma^2 L L^T, the covariance of the held-out
    visit means by the refits of cross-validation, which it is exactly for white noise; a visit the null does not hold
    gets the variance it is given, alone (``HeldoutMeanNull.for_visits``)."""
    campaign = held_out_campaign(60, seed=2, visit_samples=(8, 30))
    null, L = campaign.null, campaign.refits()
    exact = campaign.sigma[:, None, None] ** 2 * (L @ L.T)[None]
    np.testing.assert_allclose(null.dense(), exact, rtol=1e-9, atol=1e-12 * np.max(exact))
    for j, c in enumerate(null.cov):
        np.testing.assert_allclose(c.diagonal(), np.diagonal(exact[j]), rtol=1e-9)
        some = np.array([41, 3, 8, 59])  # rows in any order
        np.testing.assert_allclose(c.rows(some), exact[j][some], rtol=1e-9, atol=1e-12 * np.max(exact))
    ug = np.array([2, 3, 100, 7, 200])  # two visits it does not hold
    diag = np.arange(15.0).reshape(5, 3) + 1.0
    cov, slow = null.for_visits(ug, diag)
    for j in range(3):
        got = cov[j].dense()
        known = [0, 1, 3]
        np.testing.assert_allclose(got[np.ix_(known, known)], exact[j][np.ix_([2, 3, 7], [2, 3, 7])], rtol=1e-9)
        assert np.array_equal(got[[2, 4]][:, [2, 4]], np.diag(diag[[2, 4], j]))
        assert not got[[2, 4]][:, known].any()
    assert np.array_equal(slow.dense()[[2, 4]][:, [2, 4]], np.eye(2))


def test_the_residual_test_on_the_held_out_null_makes_no_visit_by_visit_array() -> None:
    """The revisits' test (``slow_visit_test``) on the null of 1500 held-out visits reads its covariances a block of
    rows at a time: the whole of it (the null made, its factors V x 2p, the slow error, its test and the pooled test)
    stays below two V x V arrays (36 MiB; the null as arrays was four and a temporary), and its p-values and slow error
    are those of the dense covariances."""
    import tracemalloc

    from fbg_accel_calibration.diagnosis.structure import heldout_mean_covariance, slow_visit_test

    campaign = held_out_campaign(1500, seed=4, visit_samples=(8, 30))
    null, X, groups, fold = campaign.null, campaign.X, campaign.groups, campaign.fold
    V = len(null.visits)
    rng = np.random.default_rng(5)
    pose = np.where(rng.random(V) < 0.05, -1, rng.integers(0, 40, V))  # revisited poses, some visits in motion
    run = (np.arange(V) >= V // 2).astype(int)
    means = rng.normal(size=(V, 3)) * [0.02, 0.04, 0.08]
    dof = np.full(3, 50.0)
    rows = np.ones(len(groups), bool)
    fold_xtx, XtX = np.stack([X[fold == k].T @ X[fold == k] for k in range(10)]), X.T @ X
    from fbg_accel_calibration.diagnosis.floor import VisitNoise

    noise = VisitNoise(np.array([0.5, 1.0, 2.0]), np.column_stack([np.ones(3), np.zeros(3)]))
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        small = heldout_mean_covariance(X, rows, rows, groups, fold, fold_xtx, XtX, noise)
        got = slow_visit_test(means, small.cov, small.slow, pose, run, dof)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert peak < 2 * 8 * V * V, peak / 2**20
    want = slow_visit_test(means, null.dense(), null.slow.dense(), pose, run, dof)
    assert got[3].revisits > 0
    for a, b in zip(got[:3], want[:3], strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10)
    np.testing.assert_allclose(got[3].variance, want[3].variance, rtol=1e-10)
    np.testing.assert_allclose(got[4], want[4], rtol=1e-10)
