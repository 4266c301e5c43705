"""The search of a step of the response (``effects.ResponseStepEffect``, ``Effect.switched``) from sums over the
samples (``diagnose.switch_profile``) instead of a cross-validation of every candidate time.

On a run of 10^6 samples with ~2500 visits, the step check cross-validated a quarter of the visit starts (the search
walk) three times over: it took ``diagnose`` from 16.3 s to 59.4 s (``bench/bench_calibration.py --samples 1000000
--mcap-samples 0 --repeats 1``) once a thermal lag was set against a step."""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_calibration.diagnosis.cv import cross_validate, switch_profile
from fbg_accel_calibration.diagnosis.design import Design
from fbg_accel_calibration.fit.thermal_fit import NotIdentifiedError


def _case(seed: int, n: int = 3000, p: int = 7, q: int = 4, k: int = 6):
    rng = np.random.default_rng(seed)
    X = np.column_stack([np.ones(n), rng.normal(size=(n, p - 1))])
    Z = np.column_stack([np.ones(n), rng.normal(size=(n, q - 1))])
    index = np.sort(rng.choice(10 * n, size=n, replace=False))  # thinned samples of a longer run
    step = index[n // 3]
    G = X @ rng.normal(size=(p, 3)) + (index >= step)[:, None] * (Z @ rng.normal(size=(q, 3))) \
        + rng.normal(scale=0.3, size=(n, 3))
    folds = rng.integers(0, k, size=n)
    folds[rng.random(n) < 0.05] = -2  # always trained on
    folds[rng.random(n) < 0.05] = -1  # not fitted
    rows = rng.random(n) > 0.02
    grid = np.sort(rng.choice(index[50:-50], size=40, replace=False)).astype(float)
    weights = np.array([1.0, 2.5, 0.4])
    return X, G, Z, index, folds, rows, weights, grid


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_switch_profile_is_the_cross_validation_of_each_value(seed):
    """Every fold's training RSS at every grid value equals ``cross_validate``'s for the design with the switched
    columns at that value, to rounding."""
    X, G, Z, index, folds, rows, weights, grid = _case(seed)
    fit_rows = rows & (folds != -1)
    prof = switch_profile(X, G, Z, index, folds, fit_rows, weights, grid)
    for j, h in enumerate(grid):
        Xa = np.column_stack([X, (index >= h)[:, None] * Z])
        des = Design(Xa, G, np.ones(len(G), bool), {"step": slice(X.shape[1], Xa.shape[1])}, X.shape[1])
        ref = cross_validate(des, fit_rows, folds, weights).train_rss
        np.testing.assert_allclose(prof[:, j], ref, rtol=1e-9)
    assert np.argmin(prof.sum(axis=0)) == np.argmin(np.abs(grid - index[len(index) // 3]))


def test_a_switch_value_that_leaves_a_fold_no_switched_rows_is_not_identified():
    """A value after every training row of a fold switches nothing on there: inf for that fold, as the
    cross-validation's singular normal equations make it not identified."""
    X, G, Z, index, folds, rows, weights, grid = _case(3)
    grid = np.r_[grid, float(index.max() + 1)]
    prof = switch_profile(X, G, Z, index, folds, rows & (folds != -1), weights, grid)
    assert np.all(np.isinf(prof[:, -1])) and np.all(np.isfinite(prof[:, :-1]))
    Xa = np.column_stack([X, np.zeros_like(Z)])
    with pytest.raises(NotIdentifiedError):
        cross_validate(Design(Xa, G, np.ones(len(G), bool), {}, X.shape[1]), rows & (folds != -1), folds, weights)


def test_switch_values_between_which_a_fold_trains_on_no_row_fit_it_the_same_to_the_bit():
    """Visits held out by a fold leave gaps in its training rows; every step time within one gap gives that fold the
    same design on its training rows, so the same RSS. Computed from different partial sums, the RSS of such values
    differed in their last bits, and the BLAS kernel's rounding chose the fold's step time among them (a held-out
    visit then fell on either side of the step by chance). They are now equal to the bit, and the first wins."""
    X, G, Z, index, folds, rows, weights, _ = _case(4)
    fit_rows = rows & (folds != -1)
    held = np.flatnonzero(fit_rows & (folds == 0))
    inside = index[held[len(held) // 2]:held[len(held) // 2] + 1]  # one held-out row of fold 0
    # three step times in the gap of fold 0's training rows around that held-out row, and two well apart
    trained0 = np.flatnonzero(fit_rows & (folds != 0))
    before = index[trained0[trained0 < held[len(held) // 2]][-1]]
    after = index[trained0[trained0 > held[len(held) // 2]][0]]
    grid = np.array([index[200], before + 1, inside[0], after, index[-200]], float)
    assert before + 1 < inside[0] < after  # a gap with a held-out row in it
    prof = switch_profile(X, G, Z, index, folds, fit_rows, weights, grid)
    assert prof[0, 1] == prof[0, 2] == prof[0, 3]  # fold 0: the same fit, the same bits
    assert all(prof[f, 1] != prof[f, 3] for f in range(1, prof.shape[0]))  # the other folds train on that row


def test_the_first_of_equal_fits_is_chosen_whatever_their_last_bits():
    """``first_min``: values equal up to rounding (``RSS_TIE_RTOL``) go to the first; a real difference still wins."""
    from fbg_accel_calibration.diagnosis.cv import RSS_TIE_RTOL, first_min

    v = np.array([5.0, 2.0 * (1 + RSS_TIE_RTOL / 10), 2.0, np.inf, 2.0 * (1 - RSS_TIE_RTOL / 10)])
    assert first_min(v) == 1
    assert first_min(np.array([5.0, 2.0 * (1 + 10 * RSS_TIE_RTOL), 2.0])) == 2
    assert first_min(np.array([np.inf, np.nan])) == 0
