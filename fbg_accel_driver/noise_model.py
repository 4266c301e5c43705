"""Variance of the mean of consecutive samples of this sensor's noise (pure, no ROS).

The calibrated output's noise is not white: the transimpedance stages low-pass the photodetector
noise at about 1-1.7 Hz (paper section 3.5, Table 1), so at 100 Hz consecutive samples correlate at
about 0.9, and averaging N of them (the driver's ``decimation``) cuts the variance far less than N-fold
(in the simulator 1.35-1.43x for N = 10, 4.3-5.9x for N = 100). The model, per axis:

    noise = white part (variance (1 - f) sigma^2) + first-order (AR(1)) part (variance f sigma^2,
            lag-k correlation rho^k, rho = exp(-dt / tau))

with sigma = ``noise_sigma_mps2``, f = ``noise_correlation.correlated_fraction`` and tau =
``noise_correlation.time_constant_s`` of the calibration file (fitted from the static intervals of the
calibration recording: ``fbg_accel_calibration/noise_correlation.py``), dt the board's sample interval.
For the mean of N consecutive samples

    var(mean) / sigma^2 = (1 - f) / N + f * g(N, rho),   g = (1 + 2 sum_{k=1}^{N-1} (1 - k/N) rho^k) / N

(the variance of a sample mean of a stationary process; e.g. Priestley, Spectral Analysis and Time
Series, 1981, eq. 5.3.6). ``N / factor`` is the effective number of independent samples.
"""

from __future__ import annotations

import math


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
