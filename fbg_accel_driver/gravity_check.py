"""The driver's live gravity check: while the sensor stands still, |a| must equal local gravity (pure numpy, no ROS).

A calibration made in the chamber can stop holding on the vehicle (a knock, a re-mated connector, ageing of the
bonds). Standing still, the calibrated specific force has the magnitude of local gravity g whatever the orientation,
so the mean of a still stretch tests the calibration without any reference (the idea of multi-position calibration
without a table, Tedaldi, Pretto & Menegatti, ICRA 2014; ``fbg-accel-calib field-check`` does the offline estimate of
bias and scale from several orientations).

Stillness: :class:`~fbg_accel_driver.stillness_monitor.StillnessMonitor` (the calibration node's live detector) on
the calibrated output, its floor the calibration's own noise model (``noise_sigma_mps2`` and ``noise_correlation``:
white plus first order, exact, no learning). Samples the driver flags (a clipped channel, a held or out-of-range
temperature, a correction beyond its span, the reference off its level) end a still stretch.

Test: every ``period_s`` of uninterrupted stillness the block's mean a_bar (m/s^2, sensor frame) gives the
discrepancy r = |a_bar| - g. Its standard deviation under "the calibration holds" is

    sigma^2 = u^T (C_noise + C_cal + S) u,    u = a_bar / |a_bar|

with C_noise the variance of the mean of n samples of the calibration's noise model
(``noise_model.mean_variance_factor``, diagonal), C_cal the calibration's own uncertainty J Sigma J^T at the block's
mean Psi and temperature (``coefficient_covariance``; 0 when the file has no such section) and S the slow error of a
pose mean (``slow_error``: bias wander and eq. 28's misfit, which make a fresh calibration's pose means miss the truth
by 0.06-0.07 m/s^2 rms on the full simulator). The calibration no longer holds when

    |r| > tolerance_mps2 + k sigma                       (``slow_error`` with its run-to-run part R)
    |r| > tolerance_mps2 + UNSTATED_RUN_TO_RUN_MPS2 + k sigma (``slow_error`` without R: one run per level)
    |r| > tolerance_mps2 + UNSTATED_SLOW_ERROR_MPS2 + k sigma (no ``slow_error``: S = 0 above)

k the two-sided normal quantile of ``false_alarm_per_test``. The tolerance is what no term contains: a
``gravity_mps2`` left at standard gravity is off local gravity by up to 0.03 m/s^2 (9.780 at the equator .. 9.832 at
the poles), its default, which also covers, measured, the slow bias wander a campaign's ``slow_error`` cannot state
(docs/topics.md: keep it with a measured local gravity too). A file without ``slow_error`` does not say how far its pose
means miss the truth, so the check allows :data:`UNSTATED_SLOW_ERROR_MPS2` for it, what the simulated sensor's shipped
calibration needs (its |a| - g has 0.081 m/s^2 rms; the threshold is then 0.15 + k sigma_noise). A file whose
``slow_error`` has no run-to-run part (each temperature level recorded once: the slowest components of the bias wander
are constant through a run, taken up by b(T), and drawn afresh by the time the sensor is on the vehicle) states S
without them, so the check allows :data:`UNSTATED_RUN_TO_RUN_MPS2` for what it does not state.

What one orientation sees: a drift d changes |a| by u.d + |d|^2 sin^2(phi) / (2 g) (phi its angle to u), so a drift
perpendicular to gravity is seen only to second order (0.2 m/s^2: 0.002 m/s^2, far below any threshold), whatever the
test. The check therefore keeps, per sensor axis, the largest |u_j| of the orientations it has tested (:attr:`seen`:
the fraction of a bias on that axis that reaches |a| in the best of them) and names the axes below
:data:`SEEN_FRACTION` (:meth:`unseen_axes`): a vehicle that only ever stands level checks z, not x and y, until it
stands still with x or y tilted towards gravity. Three floats: no memory of the orientations themselves.
False alarms and detection on the simulator: ``bench/gravity_check_false_alarm.py`` (docs/topics.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from .coefficient_covariance import output_covariance
from .noise_model import mean_variance_factor
from .sensor_constants import GRAVITY_RANGE_MPS2
from .stillness_monitor import NoiseFloor, StillnessMonitor
from .thermal_model import ThermalCalibration

# still stretches of this many seconds (s) per test: long enough that the noise of the mean (~0.01 m/s^2 on the
# simulated sensor) is well below the tolerance, short enough that a drift is flagged within a minute of standing still
DEFAULT_PERIOD_S = 20.0
DEFAULT_TOLERANCE_MPS2 = 0.03  # standard gravity's error against local gravity (9.780..9.832 m/s^2)
# allowance (m/s^2) for the slow error of a file without a ``slow_error`` section: 0.15 - 0.03, the tolerance measured
# for the shipped simulated calibration (bench/gravity_check_false_alarm.py; docs/topics.md, gravity check)
UNSTATED_SLOW_ERROR_MPS2 = 0.12
# allowance (m/s^2) for the run-to-run part of the slow error that a one-run-per-level file does not state: measured,
# the undrifted simulated sensor's |a| - g has 0.079 m/s^2 rms where such a file states 0.051 (noise, J Sigma J^T and
# S): at 0.05 beyond the tolerance no still hour of 72 had a false alarm, at 0 three had (bench/gravity_check_false_alarm.py
# --fitted-calibrations 6; docs/topics.md, gravity check). A margin of this decision, not a standard deviation: the
# published covariance states that part as one, slow_error.UNSTATED_RUN_TO_RUN_SIGMA_MPS2, from the bias instability
UNSTATED_RUN_TO_RUN_MPS2 = 0.05
DEFAULT_FALSE_ALARM_PER_TEST = 1e-4  # of the noise and J Sigma J^T part alone (k = 3.89)
WINDOW_S = 0.25  # the stillness monitor's window (s): the calibration node's
MAX_WINDOW = 128  # samples (the window's law is an eigenproblem of its size: 0.25 s up to 512 Hz, shorter above)
HOLD_S = 2.0  # still this long (s) before the samples count: the TIA stages settle after a move (~1 s)
RUN_S = 3600.0  # the stillness monitor spends its false alarm (leave while still) per hour of samples
# an axis is named as not seen while a bias on it reaches |a| at less than this fraction in every orientation tested
# (|u_j| < 0.5: the axis never within 60 deg of the vertical): seen at half its size, a drift must be twice the one the
# check flags along gravity
SEEN_FRACTION = 0.5
AXES = ("x", "y", "z")


@dataclass(frozen=True)
class GravityCheckConfig:
    """Settings (SI units). ``gravity_mps2`` 0 switches the check off."""

    gravity_mps2: float
    tolerance_mps2: float = DEFAULT_TOLERANCE_MPS2
    period_s: float = DEFAULT_PERIOD_S
    false_alarm_per_test: float = DEFAULT_FALSE_ALARM_PER_TEST

    @property
    def enabled(self) -> bool:
        return self.gravity_mps2 != 0.0

    def validate(self) -> None:
        """Raise ValueError naming the bad setting."""
        lo, hi = GRAVITY_RANGE_MPS2
        if self.gravity_mps2 != 0.0 and not (math.isfinite(self.gravity_mps2) and lo <= self.gravity_mps2 <= hi):
            raise ValueError(f"gravity_mps2 must be 0 (check off) or a local gravity in {lo:g}..{hi:g} m/s^2, got "
                             f"{self.gravity_mps2}")
        if not (math.isfinite(self.tolerance_mps2) and 0.0 <= self.tolerance_mps2 <= 10.0):
            raise ValueError(f"gravity_tolerance_mps2 must be in 0..10 m/s^2, got {self.tolerance_mps2}")
        if not (math.isfinite(self.period_s) and 1.0 <= self.period_s <= 3600.0):
            raise ValueError(f"gravity_check_period_s must be in 1..3600 s, got {self.period_s}")
        if not 0.0 < self.false_alarm_per_test < 0.5:
            raise ValueError(f"false_alarm_per_test must be in (0, 0.5), got {self.false_alarm_per_test}")


@dataclass(frozen=True)
class GravityTest:
    """One test of a still block: its discrepancy |a_bar| - g (m/s^2), the standard deviations of that discrepancy
    from the noise and from the calibration's coefficients (m/s^2), the threshold on |discrepancy| (m/s^2), whether
    it failed, the block's samples and mean temperature (degC), the standard deviation from the calibration's slow
    error (m/s^2), the allowance for a slow error the file does not state (m/s^2: :data:`UNSTATED_SLOW_ERROR_MPS2`
    without a ``slow_error`` section, else 0) and the unit vector along which the test sees a drift (sensor frame)."""

    discrepancy_mps2: float
    sigma_noise_mps2: float
    sigma_calibration_mps2: float
    threshold_mps2: float
    failed: bool
    samples: int
    temperature_c: float
    sigma_slow_mps2: float = 0.0
    unstated_slow_error_mps2: float = 0.0
    direction: tuple[float, float, float] = (0.0, 0.0, 0.0)  # u = a_bar / |a_bar| (sensor frame): what it sees of a drift


class GravityCheck:
    """Feed every calibrated board sample (:meth:`update`); read :attr:`last`, :attr:`tests` and :attr:`failures`.

    ``dt_s`` is the board's sample interval (s): the stillness window, hold and block are counted in samples."""

    def __init__(self, calibration: ThermalCalibration, config: GravityCheckConfig, dt_s: float) -> None:
        config.validate()
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"sample interval must be > 0 s, got {dt_s}")
        self.cal = calibration
        self.config = config
        self.dt_s = float(dt_s)
        self.k = NormalDist().inv_cdf(1.0 - config.false_alarm_per_test / 2.0)  # the driver loads no scipy
        sigma = np.asarray(calibration.noise_sigma_mps2, float)
        frac = np.asarray(calibration.noise_correlated_fraction, float)
        tau = np.asarray(calibration.noise_time_constant_s, float)
        window = min(max(round(WINDOW_S / dt_s), 3), MAX_WINDOW)
        lags = np.arange(window)
        acf = np.array([(1.0 - f) * (lags == 0) + (f * np.exp(-lags * dt_s / t) if t > 0 else f * (lags == 0))
                        for f, t in zip(frac, tau, strict=True)])
        self.monitor = StillnessMonitor(NoiseFloor(sigma**2, acf, np.full(3, np.inf)), window,
                                        max(round(HOLD_S / dt_s), 1), max(round(RUN_S / dt_s), 1))
        self.block = max(round(config.period_s / dt_s), 2)
        self._noise = (sigma**2, frac, tau)
        self._sums = [0.0] * 7  # a_x, a_y, a_z, Psi_x, Psi_y, Psi_z, temperature
        self._n = 0
        self.last: GravityTest | None = None
        self.tests = 0
        self.failures = 0
        self.seen = np.zeros(3)  # per axis, the largest |u_j| of the tests so far (module docstring)

    @property
    def still(self) -> bool:
        return self.monitor.is_still

    def unseen_axes(self) -> list[str]:
        """The sensor axes a bias on which no orientation tested so far sees at :data:`SEEN_FRACTION` of its size
        (all three before the first test)."""
        return [a for a, f in zip(AXES, self.seen.tolist(), strict=True) if f < SEEN_FRACTION]

    def interrupt(self) -> None:
        """A sample that may not count (flagged, dropped): the still stretch ends here."""
        self.monitor.reset()
        self._n = 0

    def update(self, accel: tuple[float, float, float], psi: tuple[float, float, float],
               temperature_c: float) -> GravityTest | None:
        """Add one calibrated sample (m/s^2, sensor frame), its Psi and temperature (degC); the test of a block when
        this sample completes one, else None."""
        if not self.monitor.update(np.asarray(accel, float)):
            self._n = 0
            return None
        s = self._sums
        if self._n == 0:
            s[:] = [0.0] * 7
        for i, v in enumerate((*accel, *psi, temperature_c)):
            s[i] += v
        self._n += 1
        if self._n < self.block:
            return None
        result = self._test()
        self._n = 0
        return result

    def _test(self) -> GravityTest:
        n = self._n
        mean = np.array(self._sums[:3]) / n
        psi = np.array(self._sums[3:6]) / n
        temp = self._sums[6] / n
        norm_a = float(np.linalg.norm(mean))
        u = mean / norm_a
        var0, frac, tau = self._noise
        factors = np.array([mean_variance_factor(n, float(frac[a]), float(tau[a]), self.dt_s) for a in range(3)])
        var_noise = float(np.sum(u**2 * var0 * factors))
        var_cal = var_slow = 0.0
        cc = self.cal.coefficient_covariance
        if cc is not None:
            xx, xy, xz, yy, yz, zz = output_covariance(self.cal.calibration_weights_at(round(temp, 2)), *psi.tolist())
            c = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
            var_cal = max(float(u @ c @ u), 0.0)
        if self.cal.slow_error is not None:
            var_slow = max(float(u @ self.cal.slow_error.matrix @ u), 0.0)
        unstated = unstated_allowance(self.cal)
        r = norm_a - self.config.gravity_mps2
        threshold = self.config.tolerance_mps2 + unstated + self.k * math.sqrt(var_noise + var_cal + var_slow)
        failed = abs(r) > threshold
        self.tests += 1
        self.failures += int(failed)
        self.seen = np.maximum(self.seen, np.abs(u))
        self.last = GravityTest(r, math.sqrt(var_noise), math.sqrt(var_cal), threshold, failed, n, temp,
                                math.sqrt(var_slow), unstated, tuple(u.tolist()))
        return self.last


def unstated_allowance(cal: ThermalCalibration) -> float:
    """The allowance (m/s^2) for the part of the slow error ``cal`` does not state: all of it without ``slow_error``
    (:data:`UNSTATED_SLOW_ERROR_MPS2`), its run-to-run part when the section has no R
    (:data:`UNSTATED_RUN_TO_RUN_MPS2`), none when it has R (measured by the campaign or carried from an earlier one)."""
    if cal.slow_error is None:
        return UNSTATED_SLOW_ERROR_MPS2
    return UNSTATED_RUN_TO_RUN_MPS2 if cal.slow_error.run_to_run is None else 0.0
