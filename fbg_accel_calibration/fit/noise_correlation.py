"""Fit of the calibrated output's noise correlation (white + first-order part) from static intervals.

Pure numpy. Within a static interval the specific force is constant, so the calibrated output minus
its interval mean is noise. Its autocorrelation is pooled over the intervals and modelled, for lags
k >= 1, as rho_k = f exp(-k dt / tau) (``fbg_accel_driver.noise_model``: a white part of variance
fraction 1 - f and a first-order part of fraction f, the transimpedance low-pass of paper section 3.5).

Removing each interval's mean biases the sample autocovariance low by about the variance of that
mean, which for correlated noise is (1 + 2 sum rho_k) / n of the variance, not 1/n: with 3 s dwells at
100 Hz and tau near 0.15 s that is 10 % of the variance, enough to halve the fitted f. The bias is
corrected by the same fixed-point iteration as the live stillness detector's noise floor
(``stillness_monitor.learn_noise_floor``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from fbg_accel_driver.stillness_monitor import cut_at_first_nonpositive

if TYPE_CHECKING:
    from fbg_accel_driver.thermal_model import ThermalCalibration

    from ..io.recording import Recording

MIN_SEGMENT = 32  # samples: shorter static intervals carry too little about lags of ~20 samples


@dataclass(frozen=True)
class NoiseCorrelation:
    """Per axis (3,): correlated variance fraction f in [0, 1] and time constant tau in s (0: white)."""

    correlated_fraction: np.ndarray
    time_constant_s: np.ndarray
    segments: int  # static intervals used
    samples: int
    dt_s: float = 0.0  # the sample interval the fit took (s; 0: nothing fitted)

    def as_dict(self) -> dict[str, list[float]]:
        return {"correlated_fraction": [round(float(v), 4) for v in self.correlated_fraction],
                "time_constant_s": [round(float(v), 5) for v in self.time_constant_s]}


def estimate(segments: list[np.ndarray], dt_s: float, max_lag: int = 100, min_correlation: float = 0.05
             ) -> NoiseCorrelation:
    """Fit f and tau per axis from static ``segments`` (each (n_i, 3) in m/s^2, consecutive samples
    ``dt_s`` apart). Lags 1..``max_lag`` whose bias-corrected correlation exceeds ``min_correlation`` enter a
    least-squares fit of log rho_k = log f - k dt / tau; none (white noise) gives f = 0, tau = 0."""
    segs = [np.asarray(s, dtype=float) for s in segments if len(s) >= MIN_SEGMENT and np.all(np.isfinite(s))]
    if not segs or not (dt_s > 0 and np.isfinite(dt_s)):
        return NoiseCorrelation(np.zeros(3), np.zeros(3), 0, 0)
    n_lags = int(min(max_lag, min(len(s) for s in segs) // 2))
    lags = np.arange(n_lags + 1)
    raw = np.zeros((3, n_lags + 1))
    pairs = np.zeros(n_lags + 1)
    total = 0
    for s in segs:
        z = s - s.mean(axis=0)
        n = len(z)
        for lag in lags:
            raw[:, lag] += np.einsum("ij,ij->j", z[: n - lag], z[lag:])
            pairs[lag] += n - lag
        total += n
    raw /= pairs
    gamma = raw.copy()
    for _ in range(8):  # E[raw_k] ~ gamma_k - var(mean); var(mean) from the current rho (fixed point)
        rho = cut_at_first_nonpositive(gamma / gamma[:, :1])
        mean_len = total / len(segs)
        var_of_mean = gamma[:, 0] / mean_len * (1.0 + 2.0 * (rho[:, 1:] * (1.0 - lags[1:] / mean_len)).sum(axis=1))
        gamma = raw + var_of_mean[:, None]
    rho = cut_at_first_nonpositive(gamma / gamma[:, :1])
    f, tau = np.zeros(3), np.zeros(3)
    for j in range(3):
        use = (lags > 0) & (rho[j] > min_correlation)
        if use.sum() >= 2:
            slope, intercept = np.polyfit(lags[use] * dt_s, np.log(rho[j, use]), 1)
            if slope < 0:
                f[j] = float(min(np.exp(intercept), 1.0))
                tau[j] = float(-1.0 / slope)
    return NoiseCorrelation(f, tau, len(segs), total, dt_s)


def within_visit_factor(corr: NoiseCorrelation, dt_s: float, lengths: np.ndarray) -> np.ndarray:
    """(3,) what the pooled within-visit variance (each visit's scatter about its mean, n_v - 1 degrees of freedom
    each) expects of the noise variance under ``corr`` (rho_k = f exp(-k dt / tau) for k >= 1): sum_v (n_v - c_v) /
    sum_v (n_v - 1), c_v = 1 + 2 sum_{k=1}^{n_v - 1} (1 - k / n_v) rho_k the variance of a visit's mean in units of
    sigma^2 / n_v. Below 1 for correlated noise: a visit's mean takes more of it than 1/n_v (short visits, slow
    noise). ``lengths`` (V,) samples of each visit (visits of one sample carry nothing); 1 for white noise."""
    lengths = np.asarray(lengths, dtype=np.int64)
    lengths = lengths[lengths >= 2]
    if lengths.size == 0 or not (dt_s > 0 and np.isfinite(dt_s)):
        return np.ones(3)
    sizes, count = np.unique(lengths, return_counts=True)
    expect = np.zeros(3)
    for j in range(3):
        f, tau = float(corr.correlated_fraction[j]), float(corr.time_constant_s[j])
        for n, m in zip(sizes, count, strict=True):
            k = np.arange(1, n)
            c = 1.0 + (2.0 * float(np.sum((1.0 - k / n) * f * np.exp(-k * dt_s / tau))) if f > 0 and tau > 0 else 0.0)
            expect[j] += m * (n - c)
    return np.clip(expect / float(np.sum(count * (sizes - 1))), 1e-3, 1.0)


def static_segments(acc_mps2: np.ndarray, usable: np.ndarray, pose_id: np.ndarray, run_id: np.ndarray
                    ) -> list[np.ndarray]:
    """Runs of consecutive usable samples of one pose and run, as (n_i, 3) arrays of ``acc_mps2``."""
    if len(usable) == 0:
        return []
    change = np.r_[True, (np.diff(pose_id) != 0) | (np.diff(run_id) != 0) | (np.diff(usable.astype(np.int8)) != 0)]
    seg = np.cumsum(change) - 1
    return [acc_mps2[seg == k] for k in np.unique(seg[usable])]


SAMPLE_ROWS = 65536  # samples of a recording the fit looks at (the first ones): ample for lags of ~20 samples


def from_recording(rec: Recording, cal: ThermalCalibration, window: int = 5, min_interval: int = 5) -> NoiseCorrelation:
    """The noise correlation of ``cal``'s output on the first :data:`SAMPLE_ROWS` samples of ``rec``: static
    intervals, each trimmed by ``window`` samples at both ends (settling), calibrated with eq. 28, the sample
    interval the median step of ``t_s``. The intervals are the samples the fit uses (a pose, a constant reference,
    a still signal: ``calibration_samples``) split by pose; a recording without poses (or without such an interval
    long enough) falls back to the samples whose signal alone is still. The signal alone cannot see a table move
    slower than its noise over the detector's window (a 2 s move at 100 Hz), so with poses it is not used: fitted
    across the moves, the noise model came out f = 1, tau tens of seconds."""
    from fbg_accel_driver.thermal_model import normalise

    from .static_detector import calibration_samples

    if len(rec) > SAMPLE_ROWS:
        rec = rec.select(np.arange(SAMPLE_ROWS))
    psi = normalise(rec.xyz, rec.ref)
    ok = np.all(np.isfinite(psi), axis=1) & np.isfinite(rec.temp_c)
    if ok.sum() < 2 * MIN_SEGMENT:
        return NoiseCorrelation(np.zeros(3), np.zeros(3), 0, 0)
    psi_f = np.where(ok[:, None], psi, 0.0)
    usable, still = calibration_samples(rec, window, min_interval)
    acc = cal.base_acceleration(psi_f, np.where(ok, rec.temp_c, 0.0))
    steps = np.diff(rec.t_s)
    steps = steps[steps > 0]
    dt = float(np.median(steps)) if steps.size else 0.0
    out = NoiseCorrelation(np.zeros(3), np.zeros(3), 0, 0)
    for mask, pose in ((usable & ok, rec.pose_id), (still & ok, np.zeros(len(rec), int))):  # poses first
        out = estimate([s[window:len(s) - window] for s in static_segments(acc, mask, pose, rec.run_id)], dt)
        if out.segments:
            break
    return out
