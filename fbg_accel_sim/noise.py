"""Sensor noise matching the paper's Allan figures (Table 2), with its exact expected Allan deviation.

Pure numpy. The noise is defined on the calibrated output (m/s^2, per axis) and injected
into the axis channels through the small-signal slope, so the calibrated output of the simulator
carries exactly this noise (see ``board_physics``), plus what other effects add (the default source-power
wander does: docs/simulator.md "Noise", bench/sim_noise_vs_table2.py).

Two parts, each a sum of discrete first-order Gauss-Markov (GM) processes
``x[k] = rho x[k-1] + sqrt(q (1 - rho^2)) e[k]`` (stationary variance q, rho = exp(-dt/T)):

* **velocity random walk**: white detector/TIA noise shaped by the channel's nominal TIA
  low-pass (paper 3.5, Table 1). A first-order low-pass of white noise *is* a GM process with
  T = 1/(2 pi fc). Its level is solved so that ADEV(1 s) of the total = VRW/60 (paper eq. 26).
* **bias instability**: GM processes with log-spaced correlation times
  (``noise.bias_instability_time_constants_s``) and variances growing as sqrt(T), so that the
  Allan deviation has a shallow floor that rises slowly up to the longest T. A common scale is
  solved so that the minimum of the total ADEV over tau in [1 s, max T] equals 0.664 * BI
  (paper eq. 27: BI = min ADEV / 0.66 in mg_E, g_E = 9.81 m/s^2; see ``BI_ADEV_FACTOR``).

The expected Allan variance of a discrete GM process at cluster size m (tau = m dt) is exact::

    AVAR(m) = (V_m - C_m) / m^2,  V_m = q [m (1+rho)/(1-rho) - 2 rho (1-rho^m)/(1-rho)^2],
                                  C_m = q rho ((1-rho^m)/(1-rho))^2

(variance of an m-sample mean minus the covariance of adjacent means), and variances add, so
``NoiseModel.expected_adev(tau)`` is what an Allan tool must find on a long enough record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# mg -> m/s^2 with standard gravity. Paper eq. 27 converts with g_E = 9.81 m/s^2 (its section 1): 0.03 % apart.
MG_TO_MPS2 = 9.80665e-3
# min ADEV / BI of a bias-instability (flicker) floor, sqrt(2 ln 2 / pi) = 0.6643 (IEEE Std 952, PSD B^2/(2 pi f)).
# Paper eq. 27 prints it rounded to 0.66: 0.6 % apart, inside Table 2's own rounding (0.54 mg is +-0.9 %). The
# Allan tool (fbg_accel_calibration.fit.allan) uses 0.664 and 9.80665 too, so it reads Table 2 back from the simulator.
BI_ADEV_FACTOR = 0.664
VRW_TAU_S = 1.0  # paper eq. 26: VRW = 60 * ADEV(1 s)
BI_VARIANCE_EXPONENT = 0.5  # q_j ~ T_j ** 0.5: slowly rising floor, so min ADEV is a true minimum


def gm_avar(q: float, rho: float, m: np.ndarray) -> np.ndarray:
    """Exact Allan variance of a stationary discrete GM process (variance q, lag-1 correlation rho)."""
    m = np.asarray(m, dtype=float)
    if rho <= 0.0:
        return q / m
    one = 1.0 - rho
    rm = rho**m
    v = q * (m * (1.0 + rho) / one - 2.0 * rho * (1.0 - rm) / one**2)
    c = q * rho * ((1.0 - rm) / one) ** 2
    return (v - c) / (m * m)


def first_order_filter(x: np.ndarray, a: float, b: float, y0: np.ndarray | float) -> np.ndarray:
    """y[k] = a y[k-1] + b x[k] along axis 0 with y[-1] = y0 (vectorised; scipy.signal costs 1 s to import).

    Closed form per sub-block: y[k] = a^(k+1) (y0 + b sum_{j<=k} a^(-j-1) x[j]); sub-blocks are short
    enough that a^(-L) stays far from overflow.
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[0]
    y = np.empty_like(x)
    prev = np.broadcast_to(np.asarray(y0, dtype=float), x.shape[1:]).astype(float)
    if a <= 0.0:
        y[:] = b * x
        return y
    block = n if a >= 1.0 else max(1, min(n, int(100.0 / -math.log10(a))))
    p = a ** np.arange(1, block + 1, dtype=float)
    shape = (-1,) + (1,) * (x.ndim - 1)
    for s in range(0, n, block):
        e = min(n, s + block)
        pk = p[: e - s].reshape(shape)
        y[s:e] = pk * (prev + b * np.cumsum(x[s:e] / pk, axis=0))
        prev = y[e - 1]
    return y


@dataclass
class AxisNoise:
    """Noise parameters of one axis at one sample rate (all in m/s^2)."""

    white_q: float  # stationary variance of the TIA-filtered white noise
    white_rho: float
    bi_q: np.ndarray  # (J,) variances of the bias-instability GM processes
    bi_rho: np.ndarray  # (J,)

    def avar(self, m: np.ndarray, white_scale: float = 1.0, bi_scale: float = 1.0) -> np.ndarray:
        total = white_scale**2 * gm_avar(self.white_q, self.white_rho, m)
        for q, rho in zip(self.bi_q, self.bi_rho, strict=True):
            total = total + bi_scale**2 * gm_avar(q, rho, m)
        return total


class NoiseModel:
    """Per-axis noise of the calibrated output, solved from VRW and bias instability (paper Table 2).

    ``vrw_mps_per_sqrt_h`` (3,), ``bias_instability_mg`` (3,), ``tia_cutoff_hz`` (3,) of the x, y, z
    channels, ``time_constants_s`` (J,), ``rate_hz`` the board rate.
    """

    def __init__(self, vrw_mps_per_sqrt_h: np.ndarray, bias_instability_mg: np.ndarray, tia_cutoff_hz: np.ndarray,
                 time_constants_s: np.ndarray, rate_hz: float) -> None:
        self.vrw = np.asarray(vrw_mps_per_sqrt_h, dtype=float)
        self.bi_mg = np.asarray(bias_instability_mg, dtype=float)
        self.rate_hz = float(rate_hz)
        self.dt = 1.0 / self.rate_hz
        self.time_constants_s = np.asarray(time_constants_s, dtype=float)
        self.max_tau_s = float(self.time_constants_s.max())
        self.target_adev_1s = self.vrw / 60.0
        self.target_min_adev = BI_ADEV_FACTOR * self.bi_mg * MG_TO_MPS2
        self.axes = [self._solve(i, float(fc)) for i, fc in enumerate(np.asarray(tia_cutoff_hz, float))]
        taus = self._tau_grid()
        adev = self.expected_adev(taus)
        self.min_adev_tau_s = taus[np.argmin(adev, axis=0)]

    def _tau_grid(self) -> np.ndarray:
        m = np.unique(np.round(np.geomspace(VRW_TAU_S * self.rate_hz, self.max_tau_s * self.rate_hz, 400)))
        return m * self.dt

    def _solve(self, axis: int, cutoff_hz: float) -> AxisNoise:
        a2 = self.target_adev_1s[axis] ** 2
        f2 = self.target_min_adev[axis] ** 2
        m1 = np.array([round(VRW_TAU_S * self.rate_hz)], float)
        m_grid = self._tau_grid() / self.dt
        white_rho = math.exp(-2.0 * math.pi * cutoff_hz * self.dt) if cutoff_hz > 0 else 0.0
        bi_rho = np.exp(-self.dt / self.time_constants_s)
        shape = (self.time_constants_s / self.time_constants_s.min()) ** BI_VARIANCE_EXPONENT
        unit_w = float(gm_avar(1.0, white_rho, m1)[0])
        unit_bi_grid = sum(s * gm_avar(1.0, r, m_grid) for s, r in zip(shape, bi_rho, strict=True))
        unit_bi_1s = float(sum(s * gm_avar(1.0, r, m1)[0] for s, r in zip(shape, bi_rho, strict=True)))
        unit_w_grid = gm_avar(1.0, white_rho, m_grid)
        c = 0.0
        for _ in range(50):
            qw = (a2 - c * unit_bi_1s) / unit_w
            if qw <= 0:
                raise ValueError(f"axis {axis}: bias instability too large for the VRW (ADEV(1 s) would exceed VRW/60)")
            lo, hi = 0.0, f2 / float(unit_bi_grid.min()) * 4.0 + 1e-30
            for _ in range(100):
                mid = 0.5 * (lo + hi)
                if float(np.min(qw * unit_w_grid + mid * unit_bi_grid)) > f2:
                    hi = mid
                else:
                    lo = mid
            c_new = 0.5 * (lo + hi)
            if abs(c_new - c) <= 1e-12 * max(c_new, 1e-300):
                c = c_new
                break
            c = c_new
        qw = (a2 - c * unit_bi_1s) / unit_w
        return AxisNoise(white_q=qw, white_rho=white_rho, bi_q=c * shape, bi_rho=bi_rho)

    def expected_adev(self, tau_s: np.ndarray, white_scale: float = 1.0, bi_scale: float = 1.0) -> np.ndarray:
        """Expected Allan deviation (len(tau), 3) in m/s^2 of the calibrated output; tau multiple of dt."""
        m = np.maximum(np.round(np.atleast_1d(np.asarray(tau_s, float)) * self.rate_hz), 1.0)
        return np.sqrt(np.stack([ax.avar(m, white_scale, bi_scale) for ax in self.axes], axis=-1))

    def sample_sigma(self, white_scale: float = 1.0, bi_scale: float = 1.0) -> np.ndarray:
        """Per-sample standard deviation (3,) of the noise in m/s^2."""
        return np.sqrt(np.array([white_scale**2 * ax.white_q + bi_scale**2 * float(ax.bi_q.sum()) for ax in self.axes]))


class GaussMarkovBank:
    """Streaming generator of independent stationary GM processes (columns), exact discretisation."""

    def __init__(self, q: np.ndarray, rho: np.ndarray, rng: np.random.Generator) -> None:
        self.q = np.asarray(q, dtype=float).ravel()
        self.rho = np.asarray(rho, dtype=float).ravel()
        self.drive = np.sqrt(self.q * (1.0 - self.rho**2))
        self.state = rng.standard_normal(self.q.shape) * np.sqrt(self.q)  # stationary start

    def step(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """Next n samples, shape (n, K)."""
        e = rng.standard_normal((n, self.q.size)) * self.drive
        out = np.empty_like(e)
        for j in range(self.q.size):
            out[:, j] = first_order_filter(e[:, j], float(self.rho[j]), 1.0, self.state[j])
            if n:
                self.state[j] = out[-1, j]
        return out


def flicker_noise(n: int, rate_hz: float, b_mps2: float, rng: np.random.Generator) -> np.ndarray:
    """``n`` samples of pure bias-instability (flicker) noise, m/s^2, FFT-shaped Gaussian.

    One-sided PSD B^2/(pi f), i.e. IEEE 952's two-sided B^2/(2 pi f), whose Allan deviation floor is
    sqrt(2 ln 2 / pi) B = 0.664 B. A reference series with a known B for checking the Allan tool (the
    simulator itself uses the Gauss-Markov bank above).
    """
    f = np.fft.rfftfreq(n, 1.0 / rate_hz)
    psd = np.zeros_like(f)
    psd[1:] = b_mps2**2 / (np.pi * f[1:])
    spec = np.sqrt(n * psd * rate_hz / 2.0) * (rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f))) / np.sqrt(2.0)
    spec[0] = 0.0
    return np.fft.irfft(spec, n)
