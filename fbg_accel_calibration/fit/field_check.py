"""Field check of a calibration from gravity alone: still periods at unknown orientations (pure numpy).

While the sensor stands still its calibrated specific force has the magnitude of local gravity g, whatever its
orientation. With K still periods at different orientations, a per-axis bias d and scale error s of the calibrated
output, c = (1 + s) * (a - d) (element-wise), are estimated by requiring |c_k| = g: the multi-position calibration
without a rotation table of Tedaldi, Pretto & Menegatti (ICRA 2014, "A robust and easy to implement method for IMU
calibration without external equipments"), here with the calibration's own output a and only the six parameters a
drift can move (their misalignment terms are in eq. 28's M and are not re-estimated). Gauss-Newton on
r_k = |c_k| - g with weights from the noise of each period's mean (the calibration's noise model); the covariance is
scaled up by the Birge ratio chi2/dof when the residuals scatter more than that noise.

Orientations identify only some parameters: all periods with z up see s_z g - d_z and nothing of x or y. A parameter
is *identified* when its unit vector lies in the row space of the Jacobian (null-space component below
:data:`NULL_TOLERANCE`, directions seen less than :data:`SEEN_RATIO` of the best counted as null); the others
are held at 0, named, and never changed in an updated calibration.

Local gravity: given, or the normal gravity of the WGS-84 ellipsoid at a latitude (Somigliana's closed formula) with
the second-order height correction, NIMA TR8350.2 (2000), "Department of Defense World Geodetic System 1984", 3rd
ed., eq. 4-1 and 4-3. It ignores the local anomaly (tens of mGal, about 1e-4 m/s^2 on plains, up to ~3e-3 m/s^2 in
mountains), far below what this check resolves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fbg_accel_driver.noise_model import mean_variance_factor
from fbg_accel_driver.thermal_model import ThermalCalibration

# WGS-84 (NIMA TR8350.2, tables 3.1 and 3.4)
WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_GAMMA_E = 9.7803253359  # normal gravity at the equator, m/s^2
WGS84_K = 0.00193185265241  # Somigliana's constant
WGS84_E2 = 0.00669437999013  # first eccentricity squared
WGS84_M = 0.00344978650684  # omega^2 a^2 b / GM
PARAMETERS = ("bias_x", "bias_y", "bias_z", "scale_x", "scale_y", "scale_z")
NULL_TOLERANCE = 0.1  # a parameter whose unit vector has more than this in the null space is not identified
# a direction of the (noise-weighted, column-scaled) Jacobian whose singular value is below this fraction of the largest
# is not seen: orientations within ~0.5 deg of one axis see the other axes' bias only through that tilt
SEEN_RATIO = 1e-2
MIN_PERIOD_S = 2.0  # still periods shorter than this are not used (the TIA settling is ~1 s)
BLOCK_S = 1.0  # a still period is cut into blocks this long; neighbours whose means differ are not one period
BLOCK_SIGMAS = 6.0  # ... by more than this many standard deviations of a difference of two block means
BLOCK_FLOOR_MPS2 = 0.03  # ... and by more than this (a slow turn the variance test cannot see moves |a| by ~g/10)
# a parameter further than this many standard deviations from 0 has drifted (six parameters tested: a false warning
# in about 0.3 % of checks of an undrifted sensor if the uncertainties are right: 6 x 4.7e-4)
DRIFT_SIGMAS = 3.5
GROSS_FRACTION = 0.2  # a period whose |a| is further than this from g is no still period (a move, a shock)


def normal_gravity(latitude_deg: float, height_m: float = 0.0) -> float:
    """Normal gravity (m/s^2) of the WGS-84 ellipsoid at geodetic latitude ``latitude_deg`` and ellipsoidal height
    ``height_m`` (NIMA TR8350.2 eq. 4-1, Somigliana, and eq. 4-3, the height correction to second order)."""
    if not (-90.0 <= latitude_deg <= 90.0 and math.isfinite(height_m) and -1e4 < height_m < 1e5):
        raise ValueError(f"latitude must be in -90..90 deg and height in -10..100 km, got {latitude_deg}, {height_m}")
    s2 = math.sin(math.radians(latitude_deg)) ** 2
    gamma = WGS84_GAMMA_E * (1.0 + WGS84_K * s2) / math.sqrt(1.0 - WGS84_E2 * s2)
    return gamma * (1.0 - 2.0 / WGS84_A_M * (1.0 + WGS84_F + WGS84_M - 2.0 * WGS84_F * s2) * height_m
                    + 3.0 / WGS84_A_M**2 * height_m**2)


@dataclass
class StillPeriods:
    """Mean calibrated specific force (K, 3) m/s^2 of each still period, the variance of that mean from the noise
    (K, 3), the mean temperature (K,) degC, the samples (K,) and the start and end times (K, 2) s."""

    mean: np.ndarray
    var: np.ndarray
    temp_c: np.ndarray
    samples: np.ndarray
    span_s: np.ndarray


@dataclass
class FieldCheck:
    """Estimated bias d (3,) m/s^2 and scale error s (3,) of the calibrated output (c = (1 + s)(a - d)), their
    covariance (6, 6) in :data:`PARAMETERS` order, which are identified (6,), the residuals |c_k| - g (K,) after the
    estimate and before it, the gravity used and the Birge ratio applied."""

    bias: np.ndarray
    scale: np.ndarray
    cov: np.ndarray
    identified: np.ndarray
    residual_mps2: np.ndarray
    residual_before_mps2: np.ndarray
    g_mps2: float
    birge_ratio: float
    notes: list[str] = field(default_factory=list)

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def not_identified(self) -> list[str]:
        return [p for p, ok in zip(PARAMETERS, self.identified, strict=True) if not ok]


def still_periods(rec, cal: ThermalCalibration, still: np.ndarray, min_period_s: float = MIN_PERIOD_S) -> StillPeriods:
    """The still periods of a recording (runs of ``still`` samples at least ``min_period_s`` long, within one run),
    calibrated with ``cal``; the variance of each mean is the calibration's noise of one sample times the noise
    model's factor for a mean of n samples (``noise_model.mean_variance_factor``).

    The variance test behind ``still`` cannot see a slow turn (its window is a fraction of a second), so each run of
    still samples is cut into :data:`BLOCK_S` blocks and split where the means of neighbouring blocks differ by more
    than :data:`BLOCK_SIGMAS` standard deviations (and :data:`BLOCK_FLOOR_MPS2`); the first block of each period is
    dropped (the TIA stages settle for about a second after a move)."""
    acc = cal.apply_counts(rec.ref, rec.xyz, rec.temp_c, rec.t_s)
    ok = np.asarray(still, bool) & np.all(np.isfinite(acc), axis=1) & np.isfinite(rec.temp_c)
    run = rec.run_id if rec.run_id is not None else np.zeros(len(rec), np.int64)
    edges = np.flatnonzero(np.diff(np.r_[0, ok.astype(np.int8), 0]) != 0)
    means, var, temps, counts, spans = [], [], [], [], []
    sigma2 = np.asarray(cal.noise_sigma_mps2, float) ** 2
    pieces = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        for r in np.unique(run[a:b]):  # a period never spans two runs
            idx = a + np.flatnonzero(run[a:b] == r)
            if len(idx) < 4:
                continue
            dt = float(np.median(np.diff(rec.t_s[idx])))
            n_blk = max(round(BLOCK_S / dt), 2) if dt > 0 else len(idx)
            blocks = [idx[i:i + n_blk] for i in range(0, len(idx) - n_blk + 1, n_blk)]
            if not blocks:
                continue
            f = np.array([mean_variance_factor(n_blk, float(cal.noise_correlated_fraction[i]),
                                               float(cal.noise_time_constant_s[i]), dt) for i in range(3)])
            tol = np.maximum(BLOCK_SIGMAS * np.sqrt(2.0 * sigma2 * f), BLOCK_FLOOR_MPS2)
            m = np.array([acc[blk].mean(axis=0) for blk in blocks])
            cut = np.flatnonzero(np.any(np.abs(np.diff(m, axis=0)) > tol, axis=1)) + 1
            for part in np.split(np.arange(len(blocks)), cut):
                if len(part) > 1:  # the first block settles
                    pieces.append(np.concatenate([blocks[j] for j in part[1:]]))
    for idx in pieces:
        if rec.t_s[idx[-1]] - rec.t_s[idx[0]] < min_period_s:
            continue
        dt = float(np.median(np.diff(rec.t_s[idx])))
        f = [mean_variance_factor(len(idx), float(cal.noise_correlated_fraction[i]),
                                  float(cal.noise_time_constant_s[i]), dt) for i in range(3)]
        means.append(acc[idx].mean(axis=0))
        var.append(sigma2 * np.array(f))
        temps.append(float(rec.temp_c[idx].mean()))
        counts.append(len(idx))
        spans.append((float(rec.t_s[idx[0]]), float(rec.t_s[idx[-1]])))
    return StillPeriods(np.array(means).reshape(-1, 3), np.array(var).reshape(-1, 3), np.array(temps),
                        np.array(counts, int), np.array(spans).reshape(-1, 2))


def _residual_and_jacobian(p: np.ndarray, a: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray]:
    d, s = p[:3], p[3:]
    c = (1.0 + s) * (a - d)
    norm = np.linalg.norm(c, axis=1)
    u = c / norm[:, None]
    J = np.hstack([-u * (1.0 + s), u * (a - d)])
    return norm - g, J


def estimate(periods: StillPeriods, g_mps2: float, iterations: int = 10, slow_error: np.ndarray | None = None) -> FieldCheck:
    """Bias and scale per axis from the still periods (module docstring); raises ``ValueError`` without any period.

    ``slow_error`` (3, 3) (m/s^2)^2, optional: the calibration's slow error of a pose mean (its ``slow_error`` section):
    a bias the sensor wanders by without having drifted, shared by the periods of one recording, so it is added to the
    identified biases' covariance: the estimate is of the drift, and the drift is known no better than that."""
    notes: list[str] = []
    gross = np.abs(np.linalg.norm(periods.mean, axis=1) - g_mps2) > GROSS_FRACTION * g_mps2
    if gross.any():
        notes.append(f"{int(gross.sum())} period(s) left out: |a| further than {GROSS_FRACTION:.0%} from g (not still)")
    a = periods.mean[~gross]
    var_a = periods.var[~gross]
    if len(a) == 0:
        raise ValueError("no still period of at least "
                         f"{MIN_PERIOD_S:g} s: the sensor must stand still, at several orientations")
    r0, J0 = _residual_and_jacobian(np.zeros(6), a, g_mps2)
    u0 = a / np.linalg.norm(a, axis=1)[:, None]
    w = 1.0 / np.maximum(np.einsum("ki,ki->k", u0**2, var_a), 1e-30)  # variance of |a_k| from the noise
    # identifiability from the Jacobian at the start, columns scaled (a scale multiplies g, a bias m/s^2)
    scale = np.r_[np.ones(3), np.full(3, g_mps2)]
    Js = J0 * np.sqrt(w)[:, None] / scale
    _, sv, vt = np.linalg.svd(Js, full_matrices=True)
    rank = int((sv > SEEN_RATIO * sv.max()).sum()) if len(sv) else 0
    null = vt[rank:].T  # (6, 6 - rank)
    identified = np.linalg.norm(null, axis=1) < NULL_TOLERANCE if null.size else np.ones(6, bool)
    p = np.zeros(6)
    cols = np.flatnonzero(identified)
    cov = np.zeros((6, 6))
    if len(cols):
        for _ in range(iterations):
            r, J = _residual_and_jacobian(p, a, g_mps2)
            Jw = J[:, cols] * np.sqrt(w)[:, None]
            step = np.linalg.lstsq(Jw, -r * np.sqrt(w), rcond=None)[0]
            for _halving in range(30):  # never a step that makes the fit worse
                trial = p.copy()
                trial[cols] += step
                if np.sum(w * _residual_and_jacobian(trial, a, g_mps2)[0] ** 2) <= np.sum(w * r**2):
                    break
                step = step / 2.0
            p = trial
            if np.all(np.abs(step) < 1e-12 * np.maximum(1.0, np.abs(p[cols]))):
                break
        r, J = _residual_and_jacobian(p, a, g_mps2)
        Jw = J[:, cols] * np.sqrt(w)[:, None]
        dof = len(a) - len(cols)
        chi2 = float(np.sum(w * r**2))
        birge = math.sqrt(chi2 / dof) if dof > 0 else math.nan
        inflate = max(1.0, birge**2) if dof > 0 else 1.0
        cov[np.ix_(cols, cols)] = np.linalg.inv(Jw.T @ Jw) * inflate
        if slow_error is not None:
            seen = np.flatnonzero(identified[:3])
            cov[np.ix_(seen, seen)] += np.asarray(slow_error, float)[np.ix_(seen, seen)]
        if dof <= 0:
            notes.append(f"{len(a)} still period(s) for {len(cols)} parameter(s): no residual left to check the fit "
                         "(its uncertainty is the noise's only)")
    else:
        r, birge = r0, math.nan
    missing = [PARAMETERS[j] for j in range(6) if not identified[j]]
    if missing:
        notes.append(f"the orientations seen do not identify {', '.join(missing)} (held at 0): record still periods "
                     "with each axis up and down, or tilted well away from the others")
    return FieldCheck(p[:3], p[3:], cov, identified, r, r0, g_mps2, birge, notes)


def drifted(fc: FieldCheck, k_sigma: float = DRIFT_SIGMAS) -> list[str]:
    """The identified parameters estimated further from 0 than ``k_sigma`` of their uncertainty: the calibration has
    moved (``[]``: no drift shown)."""
    values = np.r_[fc.bias, fc.scale]
    return [p for p, v, sd, ok in zip(PARAMETERS, values, fc.sigma, fc.identified, strict=True)
            if ok and abs(v) > k_sigma * sd]


def updated_calibration(cal: ThermalCalibration, fc: FieldCheck) -> ThermalCalibration:
    """``cal`` with the identified bias and scale folded into eq. 28: c = (1 + s)(M Psi + b - d), i.e. every M_k and
    b_k times (1 + s) and d taken off b_0. Unidentified parameters stay 0 (unchanged); corrections are kept as they
    are (they add after eq. 28, uncorrected)."""
    import dataclasses

    s = np.where(fc.identified[3:], fc.scale, 0.0)
    d = np.where(fc.identified[:3], fc.bias, 0.0)
    M = cal.M * (1.0 + s)[None, :, None]
    b = cal.b * (1.0 + s)[None, :]
    b[0] -= (1.0 + s) * d
    fit = dict(cal.fit)
    fit["field_check"] = {"bias_mps2": d.tolist(), "scale": s.tolist(), "sigma": fc.sigma.tolist(),
                          "not_identified": fc.not_identified(), "g_mps2": fc.g_mps2}
    return dataclasses.replace(cal, M=M, b=b, fit=fit, coefficient_covariance=None)
