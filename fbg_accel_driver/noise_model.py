"""Variance of the mean of consecutive samples of this sensor's noise (pure, no ROS).

The calibrated output's noise is not white: the transimpedance stages low-pass the photodetector
noise at about 1-1.7 Hz (paper section 3.5, Table 1), so at 100 Hz consecutive samples correlate at
about 0.9, and averaging N of them (the driver's ``decimation``) cuts the variance far less than N-fold
(in the simulator 1.35-1.43x for N = 10, 4.3-5.9x for N = 100). The model, per axis:

    noise = white part (variance (1 - f) sigma^2) + first-order (AR(1)) part (variance f sigma^2,
            lag-k correlation rho^k, rho = exp(-dt / tau))

with sigma = ``noise_sigma_mps2``, f = ``noise_correlation.correlated_fraction`` and tau =
``noise_correlation.time_constant_s`` of the calibration file (fitted from the static intervals of the
calibration recording: ``fbg_accel_calibration/fit/noise_correlation.py``), dt the board's sample interval.
For the mean of N consecutive samples

    var(mean) / sigma^2 = (1 - f) / N + f * g(N, rho),   g = (1 + 2 sum_{k=1}^{N-1} (1 - k/N) rho^k) / N

(the variance of a sample mean of a stationary process; e.g. Priestley, Spectral Analysis and Time
Series, 1981, eq. 5.3.6). ``N / factor`` is the effective number of independent samples.

When the driver filters the samples before publishing them (``chain_compensation: equalise``), the
published noise is this model passed through that filter, and so is its correlation:
:func:`filtered_mean_variance_factor` gives the variance of a mean of N published samples from the
filter's impulse response h (the same Priestley eq. 5.3.6, with the autocovariance of the filtered
noise, evaluated as the energy of ``h * boxcar_N`` applied to each part of the model).
"""

from __future__ import annotations

import math

import numpy as np

_TAIL = 1e-12  # impulse responses are cut where they have decayed to this fraction (energy ~1e-24)
_MAX_LEN = 1 << 20  # samples; a longer memory than this is treated as cut there


def mean_variance_factor(n: int, correlated_fraction: float, time_constant_s: float, dt_s: float) -> float:
    """var(mean of ``n`` consecutive samples) / var(one sample) for the white + AR(1) model above; 1 for
    n <= 1, 1/n for white noise (f = 0, tau = 0 or dt unknown)."""
    if n <= 1:
        return 1.0
    f = min(max(correlated_fraction, 0.0), 1.0)
    if f == 0.0 or time_constant_s <= 0.0 or not (dt_s > 0.0 and math.isfinite(dt_s)):
        return 1.0 / n
    rho = math.exp(-dt_s / time_constant_s)
    if rho >= 1.0 - 1e-12:
        g = 1.0
    else:
        # sum_{k=1}^{n-1} (1 - k/n) rho^k in closed form
        s = rho / (1.0 - rho) - rho * (1.0 - rho**n) / (n * (1.0 - rho) ** 2)
        g = (1.0 + 2.0 * s) / n
    return (1.0 - f) / n + f * g


def geometric_length(r: float) -> int:
    """Samples until ``r**k`` (0 <= r < 1) has decayed below ``_TAIL``: the length at which an impulse
    response with pole ``r`` is cut (at least 1, at most ``_MAX_LEN``)."""
    if r <= 0.0:
        return 1
    if r >= 1.0:
        return _MAX_LEN
    return int(min(_MAX_LEN, max(1, math.ceil(math.log(_TAIL) / math.log(r)) + 1)))


def _convolve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Full linear convolution (FFT; the responses here are up to ``_MAX_LEN`` long)."""
    m = len(a) + len(b) - 1
    if min(len(a), len(b)) <= 64:
        return np.convolve(a, b)
    size = 1 << (m - 1).bit_length()
    return np.fft.irfft(np.fft.rfft(a, size) * np.fft.rfft(b, size), size)[:m]


def _mean_energy(g: np.ndarray, n: int) -> float:
    """sum_k ((g * boxcar_n)[k])^2, boxcar_n = ones(n) / n: the variance of the mean of ``n`` consecutive
    outputs of the filter ``g`` driven by unit white noise."""
    if n <= 1:
        return float(np.dot(g, g))
    c = np.concatenate(([0.0], np.cumsum(np.concatenate((np.zeros(n - 1), g, np.zeros(n - 1))))))
    m = (c[n:] - c[:-n]) / n
    return float(np.dot(m, m))


def filtered_mean_variance_factor(n: int, correlated_fraction: float, time_constant_s: float, dt_s: float,
                                  impulse_response: np.ndarray) -> float:
    """var(mean of ``n`` consecutive outputs of a linear filter applied to the noise) / sigma^2.

    The noise is the model of the module docstring (white part ``1 - f``, AR(1) part ``f`` with
    ``rho = exp(-dt / tau)``, total variance sigma^2 before the filter); ``impulse_response`` is the
    filter's, sampled at the samples' interval ``dt_s`` (s) and long enough to have decayed. The AR(1)
    part is unit white noise through ``sqrt(1 - rho^2) rho^k``, so each part is white noise through a
    known filter and the mean of n outputs is that filter followed by a boxcar: its variance is the
    energy of the combined impulse response. With ``impulse_response = [1]`` this equals
    :func:`mean_variance_factor` (to the cut of the AR(1) tail, 1e-24)."""
    h = np.asarray(impulse_response, dtype=float)
    white = _mean_energy(h, max(n, 1))
    f = min(max(correlated_fraction, 0.0), 1.0)
    if f == 0.0 or time_constant_s <= 0.0 or not (dt_s > 0.0 and math.isfinite(dt_s)):
        return white
    rho = math.exp(-dt_s / time_constant_s)
    ar = math.sqrt(max(0.0, 1.0 - rho * rho)) * rho ** np.arange(geometric_length(rho), dtype=float)
    return (1.0 - f) * white + f * _mean_energy(_convolve(ar, h), max(n, 1))
