"""Dynamic calibration core: amplitude and phase of a measuring chain at low frequency (plain numpy/scipy).

Method of the second seed (D'Emilia, Gaspari, Natale, "Amplitude-phase calibration of tri-axial
accelerometers in the low-frequency range by a LDV", JSSS 8, 223, 2019; cited below as "seed"):
a linear slide moves sinusoidally along one direction, exciting all three axes at once (seed 2); the
reference acceleration is projected on every axis (seed 2.1 eq. 1-3); the sensitivity is the ratio of
amplitudes (seed 2.1 eq. 4); the phase / delay comes from a cross-correlation ("finddelay", seed 2.2)
checked by the cross-spectrum (seed 2.3, 3.3); sensitivities are reported as a difference from the value
at 2 Hz (seed 3.2 eq. 5); uncertainties by a budget (seed 2.4, Tables 2-3).

Units and frames (REP 103): accelerations in m/s^2 in the sensor frame (x, y, z), time in s, frequency
in Hz, phases in rad unless the name says ``_deg``. ``direction`` is the unit vector of the slide motion
in the sensor frame: the reference acceleration along axis i is ``reference * direction[i]``.

Conventions (used throughout, also by :mod:`chain_model`):

* a tone is written ``y(t) = A cos(2 pi f t + phi) + offset`` with ``t`` the given time base (phase
  referred to t = 0 of that time base; only differences between channels on one time base matter);
* the measured response at f is ``H(f) = (A_s e^{j phi_s}) / (A_r d_i e^{j phi_r})``: sensitivity
  ``|H|`` (unitless, m/s^2 per m/s^2), phase ``arg H``; a sensor that *lags* the reference has a
  **negative phase**;
* delays are **positive when the sensor lags the reference**: ``sig(t) = ref(t - delay)``, so
  ``delay = -phase / (2 pi f)`` for a tone (the phase delay).

A tone fixes a delay only modulo its period: both delay estimators return the value in
(-T/2, T/2] (xcorr: the correlation peak nearest zero lag, as MATLAB finddelay).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np

from .tone_delay import delay_by_cross_correlation, delay_by_cross_spectrum, whole_period_length, wrap_phase

LOG = logging.getLogger(__name__)
AXES = ("x", "y", "z")
SENSITIVITY_REFERENCE_F_HZ = 2.0  # seed 3.2 eq. 5: differences from the value at 2 Hz
MIN_DIRECTION_COMPONENT = 0.1  # |direction[i]| below this: the axis sees < 10 % of the slide's acceleration
STEP_TOL = 0.05  # a time step more than 5 % from the median one is a gap (a lost frame is 100 %)
MAX_SUB_BLOCKS = 8  # repeatability from at most this many whole-period sub-blocks of one segment


# ---------------------------------------------------------------------------------------------------
# Tone estimators (seed 2.1: amplitudes for eq. 4; ISO 16063-21 comparison method)
# ---------------------------------------------------------------------------------------------------


@dataclass
class SineFit:
    """Least-squares sine approximation ``y = amplitude cos(2 pi f_hz t + phase_rad) + offset``.

    ``amplitude`` and ``offset`` in the unit of y (m/s^2 for accelerations), ``phase_rad`` in
    (-pi, pi] referred to t = 0, ``f_hz`` the fitted (or given) frequency. ``residual_rms`` is the
    rms of y minus the fit; ``u_amplitude``, ``u_phase_rad`` are standard uncertainties from the
    least-squares covariance scaled by the residual variance (white-noise assumption); ``u_f_hz`` is 0
    for a 3-parameter fit.
    """

    amplitude: float
    phase_rad: float
    offset: float
    f_hz: float
    residual_rms: float
    u_amplitude: float
    u_phase_rad: float
    u_f_hz: float
    n_samples: int

    def complex_amplitude(self) -> complex:
        """``amplitude * exp(j phase_rad)``."""
        return complex(self.amplitude * np.exp(1j * self.phase_rad))


def sine_approximation(t_s: np.ndarray, y: np.ndarray, f_hz: float, fit_frequency: bool = False,
                       max_iterations: int = 20) -> SineFit:
    """Sine approximation of ``y(t_s)`` at ``f_hz`` (3-parameter), or with frequency refinement (4-parameter).

    3 parameters: linear least squares on ``[cos wt, sin wt, 1]`` (ISO 16063-21 / IEEE 1057 three-parameter
    fit). 4 parameters (``fit_frequency``): Gauss-Newton on the same model plus the frequency, started at
    ``f_hz`` (IEEE 1057 four-parameter fit); ``f_hz`` must be within ~1/(record length) of the true tone.
    Sampling need not be uniform. Raises ``ValueError`` for fewer than 4 samples or a non-positive f.
    """
    t = np.asarray(t_s, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.shape != y.shape or t.ndim != 1:
        raise ValueError("t_s and y must be 1-D of equal length")
    if t.size < 5:
        raise ValueError("sine approximation needs at least 5 samples")
    if not f_hz > 0:
        raise ValueError(f"frequency must be positive, got {f_hz}")
    # Work on a centred time axis for conditioning; the phase is moved back to t = 0 at the end.
    tc = float(np.mean(t))
    tau = t - tc
    w = 2.0 * np.pi * float(f_hz)
    for _ in range(max_iterations if fit_frequency else 0):
        c, s = np.cos(w * tau), np.sin(w * tau)
        X = np.column_stack([c, s, np.ones_like(tau)])
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        a, b, _ = coef
        # d/dw [a cos(w tau) + b sin(w tau)] = tau (-a sin + b cos)
        step, *_ = np.linalg.lstsq(np.column_stack([X, tau * (-a * s + b * c)]), y - X @ coef, rcond=None)
        w += step[3]
        if abs(step[3]) < 1e-12 * w:
            break
    c, s = np.cos(w * tau), np.sin(w * tau)
    X = np.column_stack([c, s, np.ones_like(tau)])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    a, b, off = (float(v) for v in coef)
    resid = y - X @ coef
    if fit_frequency:  # the covariance of the 4-parameter model
        X = np.column_stack([X, tau * (-a * s + b * c)])
    var = float(resid @ resid) / max(t.size - X.shape[1], 1)
    cov = var * np.linalg.pinv(X.T @ X)
    amp = math.hypot(a, b)
    # a cos + b sin = amp cos(w tau + phi) with amp cos phi = a, amp sin phi = -b
    phi_c = math.atan2(-b, a)
    # gradients of amp and phi with respect to (a, b)
    g_amp = np.array([a, b]) / amp if amp > 0 else np.zeros(2)
    g_phi = np.array([b, -a]) / amp**2 if amp > 0 else np.zeros(2)
    cab = cov[:2, :2]
    u_amp = math.sqrt(max(float(g_amp @ cab @ g_amp), 0.0))
    u_phi = math.sqrt(max(float(g_phi @ cab @ g_phi), 0.0))
    u_w = math.sqrt(max(float(cov[3, 3]), 0.0)) if fit_frequency else 0.0
    phase0 = wrap_phase(phi_c - w * tc)  # cos(w (t - tc) + phi_c) = cos(w t + phi_c - w tc)
    if fit_frequency:  # the phase at t = 0 also carries the frequency's uncertainty times tc
        g = np.array([g_phi[0], g_phi[1], 0.0, -tc])
        u_phi = math.sqrt(max(float(g @ cov @ g), 0.0))
    return SineFit(amp, phase0, off, float(w / (2 * np.pi)), math.sqrt(float(resid @ resid) / t.size), u_amp, u_phi,
                   u_w / (2 * np.pi), int(t.size))


@dataclass
class FftTone:
    """Tone read from one DFT bin over whole periods: ``amplitude`` (unit of y), ``phase_rad`` (cosine
    convention, referred to t = 0), ``n_periods`` and ``n_samples`` actually used."""

    amplitude: float
    phase_rad: float
    n_periods: int
    n_samples: int

    def complex_amplitude(self) -> complex:
        return complex(self.amplitude * np.exp(1j * self.phase_rad))


def fft_amplitude_phase(y: np.ndarray, fs_hz: float, f_hz: float, t0_s: float = 0.0) -> FftTone:
    """Amplitude and phase of the tone ``f_hz`` by a DFT over the largest whole number of periods (seed 2.1).

    Uniform sampling at ``fs_hz`` starting at time ``t0_s`` (s). The record is cut to whole periods and the
    DFT is evaluated exactly at ``f_hz`` (one bin of a rectangular-window DFT, i.e. the FFT bin when fs/f
    is an integer). Window choice: **rectangular** -- over whole periods the tone sits on a bin, so the
    rectangular window has no scalloping loss, no leakage from the tone into itself and the narrowest
    noise bandwidth; a Hann window would only help for non-coherent records, which cutting to whole periods
    avoids. The mean is removed first (a DC offset leaks into the bin when fs/f is not an integer).
    """
    y = np.asarray(y, dtype=float)
    k, n = whole_period_length(y.size, fs_hz, f_hz)
    yy = y[:n] - np.mean(y[:n])
    t = t0_s + np.arange(n) / fs_hz
    X = np.sum(yy * np.exp(-2j * np.pi * f_hz * t))
    return FftTone(float(2 * abs(X) / n), float(np.angle(X)), k, n)


# ---------------------------------------------------------------------------------------------------
# Uncertainty budget (seed 2.4, Tables 2-3)
# ---------------------------------------------------------------------------------------------------


@dataclass
class BudgetComponent:
    """One line of an uncertainty budget (seed Tables 2-3).

    ``value`` is the quantity as evaluated (a standard deviation, a resolution, a half-width) in ``unit``;
    ``divisor`` turns it into the standard uncertainty ``standard_uncertainty = value / divisor`` (1 for a
    standard deviation, sqrt(3) for a rectangular half-width); ``kind`` is ``"A"`` (statistics of the data)
    or ``"B"`` (other information).
    """

    name: str
    value: float
    unit: str
    divisor: float
    standard_uncertainty: float
    kind: str
    note: str = ""

    @classmethod
    def standard(cls, name: str, value: float, unit: str, kind: str, note: str) -> BudgetComponent:
        """A component whose value is already a standard uncertainty (divisor 1)."""
        return cls(name, value, unit, 1.0, value, kind, note)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def combined_standard_uncertainty(components: Sequence[BudgetComponent]) -> float:
    """Root sum of squares of the components' standard uncertainties (uncorrelated inputs, GUM)."""
    return float(math.sqrt(sum(c.standard_uncertainty**2 for c in components)))


def effective_degrees_of_freedom(components: Sequence[BudgetComponent], type_a_dof: float) -> float:
    """Welch-Satterthwaite effective degrees of freedom of the combined uncertainty (GUM, JCGM 100:2008 G.4.1):
    ``u_c^4 / sum(u_i^4 / nu_i)``, with ``type_a_dof`` for the type-A components (a repeatability over k repeats:
    :meth:`DynamicPoint.degrees_of_freedom`) and infinitely many for type B (the budget's B components are taken as
    known). A budget with no type-A part, or ``type_a_dof`` infinite, has infinitely many."""
    denom = sum(c.standard_uncertainty**4 / type_a_dof for c in components if c.kind == "A" and c.standard_uncertainty > 0)
    if not denom > 0:
        return math.inf
    return combined_standard_uncertainty(components) ** 4 / denom


def resolution_components(fs_hz: float, f_hz: float) -> tuple[BudgetComponent, BudgetComponent]:
    """Resolution of the delay and phase from the sampling rate (seed 2.4, Table 3).

    The delay is resolved to one sample, ``1/fs`` (s); its phase equivalent at f is ``360 f / fs``
    (degrees). Both are taken as the half-width of a rectangular distribution (divisor sqrt(3)):
    conservative, since the sub-sample refinement of :func:`delay_by_cross_correlation` resolves better
    than one sample, and the same as the seed's budget where the resolution is the sample interval.
    """
    r3 = math.sqrt(3.0)
    d = 1.0 / fs_hz
    p = 360.0 * f_hz / fs_hz
    return (BudgetComponent("resolution", d, "s", r3, d / r3, "B", "1/fs, rectangular"),
            BudgetComponent("resolution", p, "deg", r3, p / r3, "B", "360 f/fs, rectangular"))


@dataclass
class ReferenceUncertainty:
    """What is known about the reference (seed 2.4: "reference uncertainty", from its data sheet / calibration).

    ``sensitivity_rel``: relative standard uncertainty of the reference amplitude (e.g. 0.01 = 1 %);
    ``phase_deg``: standard uncertainty of the reference phase (degrees), also converted to delay at each f;
    ``direction_rad``: standard uncertainty of the mounting angle (rad), giving the projection's relative
    uncertainty ``sqrt(1 - d_i^2) / |d_i| * direction_rad`` per axis (seed Table 2 "positioning angles");
    ``transverse_rel``: relative standard uncertainty from neglected transverse sensitivity (seed 2.1:
    ~2 % if the transverse sensitivity is below 5 %).
    """

    sensitivity_rel: float = 0.0
    phase_deg: float = 0.0
    direction_rad: float = 0.0
    transverse_rel: float = 0.0


# ---------------------------------------------------------------------------------------------------
# Points per (frequency, axis) and the run analysis (seed 2, 3.2, 3.3)
# ---------------------------------------------------------------------------------------------------


@dataclass
class DynamicPoint:
    """Amplitude and phase of one axis at one excitation frequency (sensor vs projected reference).

    * ``f_hz``: excitation frequency (Hz; the reference's fitted frequency when refined);
      ``axis`` ('x', 'y', 'z'), ``axis_index``; ``direction_component`` = direction[axis] (signed).
    * ``measurable``: False when |direction_component| is below the threshold; then all figures are NaN
      and ``note`` says why.
    * ``reference_amplitude_mps2`` = |reference amplitude * direction_component| (m/s^2);
      ``sensor_amplitude_mps2`` (m/s^2).
    * ``sensitivity`` = sensor amplitude / projected reference amplitude (unitless ratio, seed eq. 4);
      ``sensitivity_diff_pct`` = 100 (S(f) - S(f2)) / S(f2) with f2 = ``sensitivity_reference_f_hz``, the
      axis' frequency nearest 2 Hz (seed eq. 5).
    * ``phase_deg`` = arg H in degrees, (-180, 180], negative when the sensor lags; from the sine fits.
    * ``delay_xcorr_s``, ``delay_cross_spectrum_s``: delay (s) of the sensor behind the projected reference,
      positive = sensor lags (seed 2.2, 2.3).
    * ``u_sensitivity`` (absolute, unitless), ``u_phase_deg``, ``u_delay_s``: combined standard
      uncertainties; ``budget_sensitivity``, ``budget_phase``, ``budget_delay``: their components.
    * ``n_repeats``: repeats (segments at this frequency, or whole-period sub-blocks of one segment) used
      for the repeatability; ``residual_rms_mps2``: rms residual of the sensor's sine fit; ``fs_hz``.
    """

    f_hz: float
    axis: str
    axis_index: int
    direction_component: float
    measurable: bool = True
    note: str = ""
    reference_amplitude_mps2: float = math.nan
    sensor_amplitude_mps2: float = math.nan
    sensitivity: float = math.nan
    sensitivity_diff_pct: float = math.nan
    sensitivity_reference_f_hz: float = math.nan
    phase_deg: float = math.nan
    delay_xcorr_s: float = math.nan
    delay_cross_spectrum_s: float = math.nan
    u_sensitivity: float = math.nan
    u_phase_deg: float = math.nan
    u_delay_s: float = math.nan
    budget_sensitivity: list[BudgetComponent] = field(default_factory=list)
    budget_phase: list[BudgetComponent] = field(default_factory=list)
    budget_delay: list[BudgetComponent] = field(default_factory=list)
    n_repeats: int = 0
    residual_rms_mps2: float = math.nan
    fs_hz: float = math.nan

    @property
    def response(self) -> complex:
        """Measured complex response ``sensitivity * exp(j phase)`` (unitless)."""
        return complex(self.sensitivity * np.exp(1j * np.deg2rad(self.phase_deg)))

    def degrees_of_freedom(self, quantity: Literal["sensitivity", "phase", "delay"]) -> float:
        """Effective degrees of freedom of ``u_<quantity>`` (:func:`effective_degrees_of_freedom`). The repeatability
        rests on ``n_repeats`` = k estimates: the sensitivity's and the phase's are one pooled scatter of amplitude and
        phase, 2(k - 1) degrees of freedom (4 to 14 for 3 to 8 sub-blocks of one segment), the delay's k - 1; the sine
        fits' covariance of a single estimate rests on its many samples (infinite here). The ratio of a standard
        deviation to the true one spreads by about 1/sqrt(2 nu): 50 % for nu = 2, 35 % for 4."""
        budget = {"sensitivity": self.budget_sensitivity, "phase": self.budget_phase, "delay": self.budget_delay}[quantity]
        k = self.n_repeats
        return effective_degrees_of_freedom(budget, math.inf if k < 2 else (k - 1) * (1 if quantity == "delay" else 2))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)  # the budgets as lists of dicts


@dataclass
class _Estimate:
    """Figures of one block (a segment or a sub-block) for one axis."""

    h: complex
    delay_xcorr_s: float
    delay_cs_s: float
    ref_amp: float
    sens_amp: float
    resid_rms: float
    u_h_rel: float  # relative statistical uncertainty of |H| from the two sine fits
    u_phase_rad: float


def sampling_rate(t: np.ndarray) -> float:
    """Sampling rate (Hz) of the time base ``t`` (s) from its median step, so a lost frame (a step of two)
    or a repeated stamp somewhere does not move it; :func:`uniformly_sampled` checks a span."""
    dt = np.diff(np.asarray(t, dtype=float))
    dt = dt[np.isfinite(dt)]
    if dt.size == 0:
        raise ValueError("time base needs at least 2 finite samples")
    med = float(np.median(dt))
    if not med > 0:
        raise ValueError("time base does not increase (median step <= 0)")
    return 1.0 / med


def uniformly_sampled(t: np.ndarray, fs_hz: float, tol: float = STEP_TOL) -> bool:
    """True when every step of ``t`` (s) is within ``tol`` (relative) of ``1 / fs_hz``: no lost frame, no
    repeated or out-of-order stamp. The whole-period cuts, the DFT and the circular cross-correlation
    count samples, so a span they use must pass."""
    dt = np.diff(np.asarray(t, dtype=float))
    return bool(np.all(np.abs(dt * fs_hz - 1.0) <= tol))


def _estimate_block(t: np.ndarray, ref: np.ndarray, sens: np.ndarray, d_i: float, f_hz: float, fs_hz: float,
                    method: str) -> _Estimate:
    ref_proj = ref * d_i  # seed 2.1 eq. 1-3: reference along the axis
    if method == "sine":
        fr = sine_approximation(t, ref_proj, f_hz)
        fsn = sine_approximation(t, sens, f_hz)
        zr, zs = fr.complex_amplitude(), fsn.complex_amplitude()
        u_rel = math.hypot(fr.u_amplitude / fr.amplitude, fsn.u_amplitude / fsn.amplitude)
        u_ph = math.hypot(fr.u_phase_rad, fsn.u_phase_rad)
        resid = fsn.residual_rms
    elif method == "fft":
        tr = fft_amplitude_phase(ref_proj, fs_hz, f_hz, t[0])
        ts = fft_amplitude_phase(sens, fs_hz, f_hz, t[0])
        zr, zs = tr.complex_amplitude(), ts.complex_amplitude()
        u_rel = u_ph = 0.0
        resid = math.nan
    else:
        raise ValueError(f"unknown amplitude method {method!r} (sine or fft)")
    H = zs / zr
    half_period = 0.5 / f_hz
    dx = delay_by_cross_correlation(ref_proj, sens, fs_hz, max_lag_s=half_period, circular=True)  # whole periods
    dc = delay_by_cross_spectrum(ref_proj, sens, fs_hz, f_hz)
    return _Estimate(H, dx, dc, abs(zr), abs(zs), resid, u_rel, u_ph)


def _sub_blocks(n: int, k: int, fs_hz: float, f_hz: float, max_blocks: int) -> list[slice]:
    """Up to ``max_blocks`` consecutive sub-blocks of whole periods of a block of ``n`` samples that spans
    ``k`` whole periods (as cut by :func:`whole_period_length`; not cut again, which could keep fewer).

    Every sub-block has the same length ``round(p fs / f)`` samples (``p`` periods, ``fs`` and ``f`` in Hz),
    the whole-period span of :func:`whole_period_length`, and starts at ``round(j p fs / f)``: a span cut
    between two rounded boundaries can be a sample short of one period when fs / f is not an integer.
    Neighbours may share one sample; the last sub-block ends at or before ``n``.
    """
    m = min(k, max_blocks)
    per_block = k // m
    length = min(round(per_block * fs_hz / f_hz), n)  # f refined by a 4-parameter fit may move it
    out = []
    for j in range(m):
        a = min(round(j * per_block * fs_hz / f_hz), n - length)
        out.append(slice(a, a + length))
    return out


def analyse_run(t_s: np.ndarray, reference_accel: np.ndarray, sensor_accel: np.ndarray, direction: Sequence[float],
                segments: Sequence[tuple[float, float, float]], reference_uncertainty: ReferenceUncertainty | None = None,
                method: Literal["sine", "fft"] = "sine", refine_frequency: bool = False,
                min_direction_component: float = MIN_DIRECTION_COMPONENT, max_sub_blocks: int = MAX_SUB_BLOCKS
                ) -> list[DynamicPoint]:
    """Amplitude/phase points per (frequency, axis) of one slide run (seed 2, 2.1-2.4, 3.2-3.3).

    ``t_s`` (N,) time (s), sampled at the rate of its median step; each segment's samples must be
    uniformly sampled (:func:`uniformly_sampled`, else ``ValueError``), a gap outside them does not matter;
    ``reference_accel`` (N,) slide acceleration along ``direction``
    (m/s^2, e.g. the differentiated LDV velocity); ``sensor_accel`` (N, 3) sensor output (m/s^2, sensor
    frame); ``direction`` (3,) unit vector of the slide motion in the sensor frame (normalised here);
    ``segments``: ``(f_hz, t_start_s, t_end_s)`` of steady sinusoidal excitation (settling excluded by the
    caller). Segments sharing a frequency (within 1e-6 relative) are repeats: the point is their mean and
    the repeatability their standard deviation of the mean; a frequency with one segment is split into up
    to ``max_sub_blocks`` whole-period sub-blocks for the repeatability (seed 2.4). Each segment is cut to
    whole periods; a frequency with one segment of one whole period is refused (``ValueError``): it has no
    measured repeatability.

    ``method``: amplitudes/phases by the sine approximation (default) or a whole-period DFT.
    ``refine_frequency``: fit the frequency on the reference (4-parameter) and use it for the sensor.
    An axis with ``|direction[i]| < min_direction_component`` is not measurable: it gets a point with
    ``measurable=False`` and a note (also logged) per frequency.

    Returns points ordered by frequency, then axis.
    """
    t = np.asarray(t_s, dtype=float)
    ref = np.asarray(reference_accel, dtype=float)
    sens = np.asarray(sensor_accel, dtype=float)
    if ref.shape != t.shape or sens.shape != (t.size, 3):
        raise ValueError("shapes: t_s (N,), reference_accel (N,), sensor_accel (N, 3)")
    d = np.asarray(direction, dtype=float)
    if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
        raise ValueError("direction must be a finite non-zero 3-vector")
    d = d / np.linalg.norm(d)
    fs = sampling_rate(t)
    ru = reference_uncertainty or ReferenceUncertainty()

    groups: dict[float, list[tuple[float, float]]] = {}
    for f, a, b in segments:
        if not f > 0 or not b > a:
            raise ValueError(f"bad segment {(f, a, b)}")
        key = next((k for k in groups if abs(k - f) <= 1e-6 * f), float(f))
        groups.setdefault(key, []).append((float(a), float(b)))

    points: list[DynamicPoint] = []
    for f_nom in sorted(groups):
        blocks: list[np.ndarray] = []
        periods: list[int] = []
        f_use = f_nom
        for a, b in groups[f_nom]:
            idx = np.flatnonzero((t >= a) & (t < b))
            if idx.size < 5:
                raise ValueError(f"segment {f_nom} Hz [{a}, {b}) s has fewer than 5 samples")
            if not uniformly_sampled(t[idx], fs):
                raise ValueError(f"segment {f_nom:g} Hz [{a}, {b}) s is not uniformly sampled (a lost frame or a "
                                 f"step more than {STEP_TOL:.0%} from 1/{fs:g} Hz): leave it out or resample it")
            k, n = whole_period_length(idx.size, fs, f_nom)
            blocks.append(idx[:n])
            periods.append(k)
        if len(blocks) == 1 and periods[0] < 2:
            a, b = groups[f_nom][0]
            raise ValueError(f"segment {f_nom:g} Hz [{a}, {b}) s holds one whole period only: no measured "
                             "repeatability (the sine fits' white-noise covariance understates the scatter of "
                             "coloured noise several times); record at least 2 periods or repeat the segment")
        if refine_frequency:
            f_use = float(np.mean([sine_approximation(t[i], ref[i], f_nom, fit_frequency=True).f_hz for i in blocks]))
        for ax in range(3):
            p = DynamicPoint(f_hz=f_use, axis=AXES[ax], axis_index=ax, direction_component=float(d[ax]), fs_hz=fs)
            if abs(d[ax]) < min_direction_component:
                p.measurable = False
                p.note = (f"not measurable: |direction[{AXES[ax]}]| = {abs(d[ax]):.3f} < {min_direction_component} "
                          "(the slide barely moves along this axis)")
                LOG.warning("%s at %.4g Hz: %s", AXES[ax], f_use, p.note)
                points.append(p)
                continue
            whole = [_estimate_block(t[i], ref[i], sens[i, ax], d[ax], f_use, fs, method) for i in blocks]
            if len(blocks) >= 2:
                reps = whole
            else:
                i0 = blocks[0]
                reps = [_estimate_block(t[i0[s]], ref[i0[s]], sens[i0[s], ax], d[ax], f_use, fs, method)
                        for s in _sub_blocks(i0.size, periods[0], fs, f_use, max_sub_blocks)]
            _fill_point(p, whole, reps, fs, ru)
            points.append(p)
    _fill_sensitivity_differences(points)
    return points


def _fill_point(p: DynamicPoint, whole: list[_Estimate], reps: list[_Estimate], fs: float,
                ru: ReferenceUncertainty) -> None:
    f = p.f_hz
    Hm = complex(np.mean([e.h for e in whole]))
    p.sensitivity = abs(Hm)
    p.phase_deg = math.degrees(wrap_phase(float(np.angle(Hm))))
    p.delay_xcorr_s = float(np.mean([e.delay_xcorr_s for e in whole]))
    p.delay_cross_spectrum_s = float(np.mean([e.delay_cs_s for e in whole]))
    p.reference_amplitude_mps2 = float(np.mean([e.ref_amp for e in whole]))
    p.sensor_amplitude_mps2 = float(np.mean([e.sens_amp for e in whole]))
    p.residual_rms_mps2 = float(np.mean([e.resid_rms for e in whole]))
    p.n_repeats = k = len(reps)

    # Repeatability (type A): standard deviation of the mean over k repeats (seed 2.4).
    if k >= 2:
        # Additive stationary noise on a tone is circular: over whole periods its in-phase and quadrature parts have one
        # variance, so the relative scatter of |H| and the scatter of arg H (rad) estimate one quantity (the slide's own
        # amplitude and phase wander cancel in the ratio H). Pooled, k repeats give 2(k - 1) degrees of freedom instead
        # of k - 1 each: from 3 sub-blocks either alone can read the scatter several times low (see
        # DynamicPoint.degrees_of_freedom).
        s_amp = float(np.std([abs(e.h) for e in reps], ddof=1)) / p.sensitivity / math.sqrt(k)
        s_arg = float(np.std([wrap_phase(float(np.angle(e.h / Hm))) for e in reps], ddof=1)) / math.sqrt(k)
        s_rel = math.sqrt(0.5 * (s_amp**2 + s_arg**2))
        s_ph = math.degrees(s_rel)
        s_d = float(np.std([e.delay_xcorr_s for e in reps], ddof=1)) / math.sqrt(k)
        note = f"std of the mean over {k} repeats, amplitude and phase pooled"
    else:  # analyse_run refuses a single period; kept for a caller passing one estimate
        e = whole[0]
        s_rel = e.u_h_rel
        s_ph = math.degrees(e.u_phase_rad)
        s_d = e.u_phase_rad / (2 * np.pi * f)
        note = "single period: sine-fit covariance (white noise assumed: an underestimate for coloured noise)"
    res_d, res_p = resolution_components(fs, f)

    d_abs = abs(p.direction_component)
    ang_rel = math.sqrt(max(1.0 - d_abs**2, 0.0)) / d_abs * ru.direction_rad
    S = p.sensitivity
    std = BudgetComponent.standard
    p.budget_sensitivity = [
        std("repeatability", s_rel * S, "1", "A", note),
        std("reference", ru.sensitivity_rel * S, "1", "B", f"{ru.sensitivity_rel:.3g} relative"),
        std("positioning angle", ang_rel * S, "1", "B", f"{ru.direction_rad:.3g} rad on the projection"),
        std("transverse sensitivity", ru.transverse_rel * S, "1", "B", f"{ru.transverse_rel:.3g} relative"),
    ]
    p.budget_phase = [std("repeatability", s_ph, "deg", "A", note), res_p,
                      std("reference", ru.phase_deg, "deg", "B", "reference phase")]
    p.budget_delay = [std("repeatability", s_d, "s", "A", note), res_d,
                      std("reference", ru.phase_deg / (360.0 * f), "s", "B", "reference phase / (360 f)")]
    p.u_sensitivity = combined_standard_uncertainty(p.budget_sensitivity)
    p.u_phase_deg = combined_standard_uncertainty(p.budget_phase)
    p.u_delay_s = combined_standard_uncertainty(p.budget_delay)


def _fill_sensitivity_differences(points: list[DynamicPoint], f_ref_hz: float = SENSITIVITY_REFERENCE_F_HZ) -> None:
    """Seed 3.2 eq. 5: 100 (S(f) - S(2 Hz)) / S(2 Hz) per axis, 2 Hz or the nearest measured frequency."""
    for ax in AXES:
        pts = [p for p in points if p.axis == ax and p.measurable]
        if not pts:
            continue
        p2 = min(pts, key=lambda p: abs(p.f_hz - f_ref_hz))
        for p in pts:
            p.sensitivity_reference_f_hz = p2.f_hz
            p.sensitivity_diff_pct = 100.0 * (p.sensitivity - p2.sensitivity) / p2.sensitivity


def points_table_markdown(points: Sequence[DynamicPoint]) -> str:
    """Markdown table of the points (one row per frequency and axis) with combined standard uncertainties."""
    lines = ["| f [Hz] | axis | S [1] | u(S) | ΔS vs 2 Hz [%] | phase [deg] | u [deg] | delay xcorr [ms] | "
             "delay cross-spectrum [ms] | u [ms] | repeats |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for p in points:
        if not p.measurable:
            lines.append(f"| {p.f_hz:.4g} | {p.axis} | {p.note} |||||||||")
            continue
        lines.append(f"| {p.f_hz:.4g} | {p.axis} | {p.sensitivity:.4f} | {p.u_sensitivity:.2g} | "
                     f"{p.sensitivity_diff_pct:+.2f} | {p.phase_deg:.2f} | {p.u_phase_deg:.2g} | "
                     f"{1e3 * p.delay_xcorr_s:.3f} | {1e3 * p.delay_cross_spectrum_s:.3f} | {1e3 * p.u_delay_s:.2g} | "
                     f"{p.n_repeats} |")
    return "\n".join(lines)


def budget_table_markdown(point: DynamicPoint) -> str:
    """Markdown uncertainty budget of one point (seed Tables 2-3): every component and the combination."""
    lines = [f"Budget at {point.f_hz:.4g} Hz, axis {point.axis}", "",
             "| quantity | component | value | unit | divisor | standard uncertainty | type | note |",
             "|---|---|---|---|---|---|---|---|"]
    for qty, comps, total in (("sensitivity", point.budget_sensitivity, point.u_sensitivity),
                              ("phase", point.budget_phase, point.u_phase_deg),
                              ("delay", point.budget_delay, point.u_delay_s)):
        for c in comps:
            lines.append(f"| {qty} | {c.name} | {c.value:.3g} | {c.unit} | {c.divisor:.3g} | "
                         f"{c.standard_uncertainty:.3g} | {c.kind} | {c.note} |")
        lines.append(f"| {qty} | **combined** | | | | {total:.3g} | | |")
    return "\n".join(lines)
