"""The channel delay's cross-check (``search.cross_correlation_delay``): the delay of the model's output against the
reference from the cross-correlation of their sample-to-sample changes, and the memory it takes at 10^6 samples."""

from __future__ import annotations

import tracemalloc

import numpy as np

from fbg_accel_calibration.diagnosis.data import DiagnosisData
from fbg_accel_calibration.diagnosis.search import cross_correlation_delay, sample_changes

DT = 0.01


def moving_data(n: int, seed: int = 2) -> DiagnosisData:
    """Two runs of a reference (m/s^2) that moves between held poses, with a gap (NaN) in the first run."""
    rng = np.random.default_rng(seed)
    run_id = (np.arange(n) >= n // 2).astype(int)
    t = DT * np.arange(n) + 50.0 * run_id
    steps = np.where(rng.random((n, 3)) < 0.02, rng.normal(0.0, 2.0, (n, 3)), 0.0)
    gref = np.cumsum(steps, axis=0) + np.array([0.0, 0.0, 9.8])
    gref[n // 5:n // 5 + 7] = np.nan
    pose_id = np.zeros(n, int)
    return DiagnosisData(t, np.full(n, 3000.0), gref * 3.0, np.full(n, 25.0), gref, pose_id, run_id, np.ones(n, bool))


def test_the_changes_are_np_diff_of_the_series_with_nan_as_zero_bit_for_bit() -> None:
    data = moving_data(5003)
    x = data.gref.copy()
    x[100, 1], x[4000, 2] = np.inf, -np.inf
    want = np.diff(np.nan_to_num(x), axis=0)
    want[data.run_id[1:] != data.run_id[:-1]] = 0.0
    for block in (1, 97, 65_536):
        assert np.array_equal(sample_changes(data, x, block), want)
    assert sample_changes(moving_data(1), moving_data(1).gref).shape == (0, 3)


def test_the_cross_check_finds_the_output_s_delay() -> None:
    data = moving_data(20_000)
    for lag in (0, 3, 7):
        output = np.roll(data.gref_filled, lag, axis=0) * 1.01  # the output lags the reference by ``lag`` samples
        got = cross_correlation_delay(data, sample_changes(data, output))
        assert abs(got - lag * DT) < 0.3 * DT


def test_the_cross_check_holds_two_series_of_changes_beside_the_output_s() -> None:
    """Beside the output's changes it is given, the cross-check makes the reference's changes and one array for each
    lag's products (two N x 3 arrays at its highest, and a block's copies): not a copy of the reference, nor of each
    lag's products."""
    data = moving_data(1_000_000)
    changes = sample_changes(data, data.gref_filled * 1.01)
    one = changes.nbytes
    assert abs(data.dt_s - DT) < 1e-9  # worked out once per recording, before the searches (not the cross-check's)
    tracemalloc.start()
    try:
        cross_correlation_delay(data, changes)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2.3 * one
