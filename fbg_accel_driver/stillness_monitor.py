"""Live stillness test, with a stated false-alarm rate per run: one implementation for the calibration node and the
driver's gravity check (``gravity_check``), here at the lowest layer both import.

Pure numpy and scipy. The calibration node feeds Psi = counts / reference (paper eq. 24) one board sample at a time
and asks whether the sensor is still; the pose sequencer records a pose only while it is. The driver feeds its
calibrated output (m/s^2) with a floor from the calibration's noise model.

The statistic is the variance (ddof=1) of each component over the trailing ``window`` samples, as in
the static detector of multi-position IMU calibration (Tedaldi, Pretto & Menegatti, ICRA 2014). What
this module adds is the law of that statistic for *this* sensor, whose noise is not white: the
transimpedance stages low-pass it at about 1-1.7 Hz (paper section 3.5, Table 1), so at 100 Hz
consecutive samples correlate at about 0.87 and a 0.25 s window holds the information of about 4.5
independent samples, not 24. A chi-square(w-1) threshold is then wrong by orders of magnitude in the
tail, and a noise floor learnt from 2 s of such data is itself uncertain by tens of per cent.

The law used here:

* For a stationary Gaussian process with per-sample variance s^2 and normalised autocorrelation rho,
  the window variance is the quadratic form x' P x / (w-1) (P the centring projection), i.e.
  s^2 sum_i lambda_i chi2_1 with lambda the eigenvalues of P R P / (w-1), R = Toeplitz(rho)
  (:func:`window_variance_weights`). Its mean is s^2 sum(lambda). A two-moment (Satterthwaite) match
  is too thin in the tail here (a 1e-4 quantile of 5.4 x the mean instead of 6.8), so the tail is
  evaluated exactly enough by a saddlepoint approximation (Lugannani & Rice 1980).
* The floor s^2 is learnt from n still samples; by Bartlett's formula its estimate has
  nu_L = n / (1 + 2 sum_k rho_k^2) effective degrees of freedom (:func:`learn_noise_floor`), and is
  treated as s^2 chi2(nu_L)/nu_L; a configured floor counts as exact (nu_L = inf).
* A threshold c (in units of the expected window variance under the learnt floor) is exceeded by a
  still window with probability P(sum lambda_i chi2_1 - c sum(lambda) chi2(nu_L)/nu_L > 0)
  (:func:`ratio_exceedance`); thresholds are solved from it (:func:`ratio_quantile`).

Hysteresis (a Schmitt trigger with a hold):

* *enter*: from "moving", a window whose variance is below the enter threshold on every component
  starts the hold; a still window exceeds it with probability ``enter_exceedance`` (5 %), so a
  settled sensor enters at once while a settling one does not;
* *hold*: the sensor is still after ``hold`` consecutive samples without a leave-threshold crossing
  (the hold covers the TIA settling after a move: 1 s is about six time constants at 1 Hz) and with the
  window *mean* within ``level_threshold`` of the window mean at the start of the hold (else the hold
  starts again from the current window). The window variance alone is blind to a slow move: the start
  and end of a 10 s raised-cosine turn change Psi by a few noise sigmas per window, well inside the
  variance thresholds, and the hold completed during the move. The level threshold is the two-sided
  quantile, at the leave threshold's per-window exceedance, of the difference of two window means under
  the floor (variance 2 s^2 1'R1 / w^2, Student t with the floor's degrees of freedom);
* *leave*: only a window above the leave threshold ends stillness. Its per-window exceedance is
  ``false_alarm_per_run / (run_samples * components)`` (Bonferroni over every sample of the run and
  every component), so a still sensor is declared moving at most ``false_alarm_per_run`` times per run
  of ``run_samples`` samples in expectation. Real table moves (a 90 deg turn raises the window variance
  about 50-fold) cross it; small moves are the pose-level test's job (``pose_recorder``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

DEFAULT_FALSE_ALARM_PER_RUN = 1e-3
DEFAULT_ENTER_EXCEEDANCE = 0.05
# First-order correlation time of a configured floor: the slowest TIA low-pass, 1 Hz on the reference
# (paper Table 1): tau = 1 / (2 pi 1 Hz) = 0.159 s.
DEFAULT_NOISE_CORR_S = 1.0 / (2.0 * math.pi * 1.0)


@dataclass(frozen=True)
class NoiseFloor:
    """Noise of the still signal, per component (k of them).

    ``variance`` (k,) per-sample variance (signal units^2, Psi is dimensionless); ``acf`` (k, L)
    normalised autocorrelation at lags 0..L-1 (``acf[:, 0] == 1``, zero beyond L); ``dof`` (k,)
    effective degrees of freedom of ``variance`` as an estimate (``inf`` when it is known).
    """

    variance: np.ndarray
    acf: np.ndarray
    dof: np.ndarray

    def __post_init__(self) -> None:
        v, a, d = (np.asarray(self.variance, float), np.atleast_2d(np.asarray(self.acf, float)),
                   np.asarray(self.dof, float))
        if v.ndim != 1 or a.shape[0] != v.size or d.shape != v.shape:
            raise ValueError(f"noise floor shapes disagree: variance {v.shape}, acf {a.shape}, dof {d.shape}")
        if not (np.all(np.isfinite(v)) and np.all(v > 0)):
            raise ValueError(f"noise floor variance must be finite and > 0, got {v}")
        if not (np.all(np.isfinite(a)) and np.allclose(a[:, 0], 1.0)):
            raise ValueError("noise floor autocorrelation must be finite with acf[:, 0] == 1")
        if not np.all(d > 0):
            raise ValueError(f"noise floor degrees of freedom must be > 0, got {d}")
        object.__setattr__(self, "variance", v)
        object.__setattr__(self, "acf", a)
        object.__setattr__(self, "dof", d)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(self.variance)

    def with_minimum_variance(self, floor: np.ndarray | float) -> NoiseFloor:
        """The same floor with each variance raised to at least ``floor`` (e.g. ADC quantisation)."""
        return NoiseFloor(np.maximum(self.variance, floor), self.acf, self.dof)


def learn_noise_floor(signal: np.ndarray, max_lag: int, min_correlation: float = 0.1) -> NoiseFloor:
    """Noise floor of a still stretch ``signal`` (n, k) of consecutive samples.

    The noise of Psi is white noise through the first-order transimpedance low-passes (paper section
    3.5), so its autocorrelation is modelled as rho_l = exp(-l / tau): a parametric fit is far steadier
    than the raw estimate from a few seconds, whose scatter at each lag made the tail of the window
    variance about ten times heavier than predicted (a 3e-5 threshold exceeded 3.5e-4 of the time with
    2 s of learning at 100 Hz; ``bench/stillness_false_alarm.py``). Steps, per component:

    1. the autocovariance up to ``4 * max_lag`` lags, corrected for the two biases of the plain 1/n
       estimator about the sample mean: the (1 - l/n) taper and the variance of the mean, which for
       correlated noise is (1 + 2 sum rho_l) / n of the variance, not 1/n (a fixed-point iteration);
    2. tau by least squares of log rho_l = -l / tau (through the origin) over the lags below
       ``max_lag`` (the lags the window variance depends on) whose corrected rho exceeds
       ``min_correlation`` (white noise: no such lag, rho_l = 0 for l >= 1). Psi is a ratio of
       channels low-passed at different cut-offs (1 to 1.7 Hz), and white ADC read noise may add to
       it: both make the true rho fall faster at the first lags than later, which this fit turns into
       a shorter tau, i.e. a higher, conservative threshold (measured: ``bench/stillness_false_alarm.py``);
    3. degrees of freedom of the variance estimate by Bartlett's n / (1 + 2 sum rho_l^2).

    ``max_lag`` is the number of lags the returned ``acf`` carries (the detector window).
    """
    x = np.asarray(signal, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    n, k = x.shape
    if n < 8 or not np.all(np.isfinite(x)):
        raise ValueError(f"need at least 8 finite still samples to learn the noise floor, got {n}")
    n_lags = int(min(max(4 * max_lag, 8), n // 2))
    z = x - x.mean(axis=0)
    raw = np.array([np.einsum("ij,ij->j", z[: n - lag], z[lag:]) / n for lag in range(n_lags)]).T  # (k, L)
    if np.any(raw[:, 0] <= 0):
        raise ValueError("the still signal is constant on some component: no noise to learn from")
    lags = np.arange(n_lags)
    taper = 1.0 - lags / n
    gamma = raw.copy()
    for _ in range(5):
        rho = cut_at_first_nonpositive(gamma / gamma[:, :1])
        var_of_mean = gamma[:, 0] / n * (1.0 + 2.0 * (rho[:, 1:] * taper[1:]).sum(axis=1))
        gamma = (raw + var_of_mean[:, None]) / taper
    rho = cut_at_first_nonpositive(gamma / gamma[:, :1])
    out_lags = np.arange(max(int(max_lag), 2))
    acf = np.zeros((k, out_lags.size))
    for j in range(k):
        use = (rho[j] > min_correlation) & (lags > 0) & (lags < out_lags.size)
        if np.any(use):  # log rho_l = -l / tau, least squares through the origin
            tau = -float(np.sum(lags[use] ** 2) / np.sum(lags[use] * np.log(rho[j, use])))
            acf[j] = np.exp(-out_lags / tau)
        else:
            acf[j, 0] = 1.0
    dof = n / (1.0 + 2.0 * (rho[:, 1:] ** 2).sum(axis=1))
    return NoiseFloor(gamma[:, 0], acf, dof)


def cut_at_first_nonpositive(rho: np.ndarray) -> np.ndarray:
    """``rho`` (k, L) with each row set to zero from its first non-positive lag on (estimation noise)."""
    out = rho.copy()
    for j in range(out.shape[0]):
        nonpos = np.flatnonzero(out[j] <= 0.0)
        if nonpos.size:
            out[j, nonpos[0]:] = 0.0
    return out


def first_order_noise_floor(std: np.ndarray, corr_samples: float, max_lag: int) -> NoiseFloor:
    """A known floor: per-sample ``std`` (k,) of white noise through a first-order low-pass whose
    correlation time is ``corr_samples`` samples (rho_l = exp(-l / corr_samples)); exact (dof inf)."""
    s = np.asarray(std, dtype=float)
    if not (math.isfinite(corr_samples) and corr_samples >= 0):
        raise ValueError(f"correlation time must be >= 0 samples, got {corr_samples}")
    lags = np.arange(max(int(max_lag), 1))
    row = np.exp(-lags / corr_samples) if corr_samples > 0 else (lags == 0).astype(float)
    return NoiseFloor(s**2, np.tile(row, (s.size, 1)), np.full(s.size, np.inf))


def acf_matrix(acf_row: np.ndarray, window: int) -> np.ndarray:
    """Correlation matrix (window, window) of ``window`` consecutive samples with normalised autocorrelation
    ``acf_row`` (lags 0, 1, ...; zero beyond its length)."""
    r = np.zeros(window)
    m = min(window, len(acf_row))
    r[:m] = np.asarray(acf_row, dtype=float)[:m]
    return r[np.abs(np.subtract.outer(np.arange(window), np.arange(window)))]


def window_variance_weights(acf_row: np.ndarray, window: int) -> np.ndarray:
    """Weights lambda of the window variance (ddof=1) of ``window`` consecutive samples of a stationary
    Gaussian process with normalised autocorrelation ``acf_row``, in units of the per-sample variance:
    the window variance is distributed as sum_i lambda_i chi2_1 (white noise: w-1 weights 1/(w-1))."""
    if window < 2:
        raise ValueError(f"window must be >= 2 samples, got {window}")
    centring = np.eye(window) - 1.0 / window
    lam = np.linalg.eigvalsh(centring @ acf_matrix(acf_row, window) @ centring) / (window - 1)
    lam = lam[lam > 1e-12 * max(float(lam.max()), 1e-300)]  # a truncated estimated acf may be slightly indefinite
    if lam.size == 0:
        raise ValueError("degenerate autocorrelation: the window variance has no spread")
    return lam


def ratio_exceedance(c: float, weights: np.ndarray, nu_floor: float) -> float:
    """P(window variance > c x its expected value under the learnt floor).

    The window variance is Q = sum lambda_i chi2_1 (:func:`window_variance_weights`, mean m = sum lambda);
    the learnt floor is the true one times U = chi2(nu_floor)/nu_floor (exact for ``inf``). The event is
    D = Q - c m U > 0, a sum of chi-squares with weights of both signs, whose upper tail is evaluated by
    the Lugannani-Rice saddlepoint formula (accurate in the far tail, unlike a two-moment match).
    """
    lam = np.asarray(weights, dtype=float)
    m = float(lam.sum())
    b = c * m  # floor weight: -b/nu on nu_floor chi2_1 terms (a constant -b when nu is infinite)
    finite_nu = math.isfinite(nu_floor)

    def k_derivs(s: float) -> tuple[float, float, float]:
        one = 1.0 - 2.0 * s * lam
        k0 = -0.5 * float(np.log(one).sum())
        k1 = float((lam / one).sum())
        k2 = float((2.0 * lam**2 / one**2).sum())
        if finite_nu:
            g = 1.0 + 2.0 * s * b / nu_floor
            k0 += -0.5 * nu_floor * math.log(g)
            k1 += -b / g
            k2 += 2.0 * b * b / nu_floor / g**2
        else:
            k0 -= s * b
            k1 -= b
        return k0, k1, k2

    if k_derivs(0.0)[1] >= 0.0:  # c <= 1 (or not in the tail): the approximation is for the upper tail
        return 0.5
    hi = 1.0 / (2.0 * float(lam.max())) * (1.0 - 1e-12)
    lo, top = 0.0, hi
    for _ in range(80):  # K' is increasing: bisection for K'(s) = 0 on (0, 1/(2 lambda_max))
        mid = 0.5 * (lo + top)
        if k_derivs(mid)[1] < 0.0:
            lo = mid
        else:
            top = mid
    s_hat = 0.5 * (lo + top)
    k0, _, k2 = k_derivs(s_hat)
    w = math.sqrt(max(-2.0 * k0, 0.0))
    u = s_hat * math.sqrt(k2)
    if w < 1e-8 or u < 1e-8:
        return 0.5
    tail = 0.5 * math.erfc(w / math.sqrt(2.0))  # standard normal upper tail and density at w
    density = math.exp(-0.5 * w * w) / math.sqrt(2.0 * math.pi)
    return float(min(max(tail + density * (1.0 / u - 1.0 / w), 0.0), 1.0))


class TooFewDegreesOfFreedomError(ValueError):
    """The learnt floor is too uncertain (too few degrees of freedom) for any finite threshold to reach the
    asked false-alarm rate: learn from a longer still stretch."""


def ratio_quantile(exceedance: float, weights: np.ndarray, nu_floor: float) -> float:
    """The ratio c (window variance / its expected value under the learnt floor) that a still window
    exceeds with probability ``exceedance`` (:func:`ratio_exceedance` solved for c). Raises
    :class:`TooFewDegreesOfFreedomError` when no c below 1e9 does."""
    if not 0.0 < exceedance < 0.5:
        raise ValueError(f"exceedance must be in (0, 0.5), got {exceedance}")
    target = math.log(exceedance)
    lo, hi = 1.0, 2.0
    while math.log(max(ratio_exceedance(hi, weights, nu_floor), 1e-300)) > target:
        lo, hi = hi, hi * 2.0
        if hi > 1e9:
            raise TooFewDegreesOfFreedomError("no finite threshold reaches that exceedance (too few degrees of freedom)")
    for _ in range(60):
        mid = math.sqrt(lo * hi)
        if math.log(max(ratio_exceedance(mid, weights, nu_floor), 1e-300)) > target:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


@functools.lru_cache(maxsize=256)
def _ratio_quantile_cached(exceedance: float, weights: tuple[float, ...], nu_floor: float) -> float:
    return ratio_quantile(exceedance, np.array(weights), nu_floor)


def _ratio_quantile_of(exceedance: float, weights: np.ndarray, nu_floor: float) -> float:
    """:func:`ratio_quantile`, remembered for the same arguments: a monitor of the same floor (every driver core of one
    calibration) does not solve its thresholds again (about 0.1 s each)."""
    return _ratio_quantile_cached(float(exceedance), tuple(np.asarray(weights, float).tolist()), float(nu_floor))


class StillnessMonitor:
    """Streaming stillness test (module docstring): feed samples, ask :attr:`is_still`.

    ``floor`` the noise of the still signal; ``window`` and ``hold`` in samples; ``run_samples`` the
    number of samples one run tests (the plan's nominal duration times the board rate), over which
    ``false_alarm_per_run`` is spent.
    """

    def __init__(self, floor: NoiseFloor, window: int, hold: int, run_samples: int,
                 false_alarm_per_run: float = DEFAULT_FALSE_ALARM_PER_RUN,
                 enter_exceedance: float = DEFAULT_ENTER_EXCEEDANCE) -> None:
        if window < 2:
            raise ValueError(f"window must be >= 2 samples, got {window}")
        if hold < 1:
            raise ValueError(f"hold must be >= 1 sample, got {hold}")
        if run_samples < 1:
            raise ValueError(f"run_samples must be >= 1, got {run_samples}")
        if not 0.0 < false_alarm_per_run < 1.0:
            raise ValueError(f"false_alarm_per_run must be in (0, 1), got {false_alarm_per_run}")
        self.window = int(window)
        self.hold = int(hold)
        k = floor.variance.size
        self.per_window_false_alarm = false_alarm_per_run / (run_samples * k)
        weights = [window_variance_weights(floor.acf[j], self.window) for j in range(k)]
        self.expected_variance = floor.variance * np.array([lam.sum() for lam in weights])
        self.leave_threshold = self.expected_variance * np.array(
            [_ratio_quantile_of(self.per_window_false_alarm, weights[j], floor.dof[j]) for j in range(k)])
        self.enter_threshold = self.expected_variance * np.array(
            [_ratio_quantile_of(enter_exceedance, weights[j], floor.dof[j]) for j in range(k)])
        mean_var = floor.variance * np.array([acf_matrix(floor.acf[j], self.window).sum() for j in range(k)]) / self.window**2
        from scipy.stats import norm  # here, not at import: the node's --help reads this module's defaults
        from scipy.stats import t as student_t

        quantile = np.array([float(student_t.isf(self.per_window_false_alarm / 2.0, d)) if math.isfinite(d)
                             else float(norm.isf(self.per_window_false_alarm / 2.0)) for d in floor.dof])
        # Psi units: a window mean this far from the one at the start of the hold restarts the hold
        self.level_threshold = quantile * np.sqrt(2.0 * mean_var)
        self._hold_mean = np.full(k, np.nan)  # window mean (Psi) when the current hold started
        self._buf = np.zeros((self.window, k))  # ring buffer of the trailing window
        self._filled = 0
        self._armed = False  # below the enter threshold once since the last leave
        self.still_count = 0  # samples since the hold started without a leave-threshold crossing
        self.last_variance = np.full(k, np.nan)

    def reset(self) -> None:
        """Forget the history (the table starts moving to the next pose)."""
        self._filled = 0
        self._armed = False
        self.still_count = 0

    def update(self, sample: np.ndarray) -> bool:
        """Add one sample (k,); returns :attr:`is_still`. A non-finite sample ends stillness."""
        sample = np.asarray(sample, dtype=float).reshape(self.leave_threshold.shape)
        if not np.all(np.isfinite(sample)):
            self.reset()
            return False
        self._buf[self._filled % self.window] = sample
        self._filled += 1
        if self._filled < self.window:
            return False
        self.last_variance = np.var(self._buf, axis=0, ddof=1)
        if np.any(self.last_variance > self.leave_threshold):
            self._armed = False
            self.still_count = 0
        elif self._armed:
            mean = None if self.is_still else self._buf.mean(axis=0)  # the level matters only while holding
            if mean is not None and np.any(np.abs(mean - self._hold_mean) > self.level_threshold):
                self._hold_mean = mean  # the level drifts: a slow move, or still settling; hold again
                self.still_count = 1
            else:
                self.still_count += 1
        elif np.all(self.last_variance <= self.enter_threshold):
            self._armed = True
            self._hold_mean = self._buf.mean(axis=0)
            self.still_count = 1
        return self.is_still

    @property
    def is_still(self) -> bool:
        return self.still_count >= self.hold
