"""The slow error of a pose mean beyond the noise model: variance components by visit and by run (pure numpy).

A pose mean (the mean of a still stretch) carries more than the noise model's white + first-order part and the
coefficients' own uncertainty (``coefficient_uncertainty``): what wanders slowly -- bias instability (flicker-like,
correlation times from seconds to hours), the source power's wander where a dark offset keeps eq. 24 from cancelling
it, warm-up drift -- and what eq. 28 does not contain at the poses visited. The calibration's own campaign shows it:
the visits' mean residuals scatter more than the noise model says they should. Model, per output axis i, for the mean
residual r_v of visit v (m/s^2)::

    r = (I - H) (u + eta),    u_v ~ (0, S) the visit's slow error,  eta_v ~ (0, sigma_i^2 c_v) the noise of its mean

with H the fit's hat matrix at the visit level, H_vw = xbar_v^T B^-1 s_w (s_w the visit's sum of regressor rows,
xbar_v = s_v / n_v, B = X^T X), and c_v the noise model's variance factor of a mean of n_v samples
(``noise_model.mean_variance_factor``). The method of moments (Henderson's method III; Searle, Casella & McCulloch,
"Variance Components", Wiley 1992, ch. 5) equates sum_v r_v r_v^T with its expectation::

    E[sum_v r_v r_v^T] = S tr((I - H)(I - H)^T) + diag_i(sigma_i^2 sum_{v,w} (I - H)_vw^2 c_w)

and solves for S (3, 3), projected onto the positive semi-definite matrices. It is written to the calibration file's
``slow_error`` section; the driver adds it to the published covariance as a bias with the calibration's J Sigma J^T
(``covariance_includes_calibration``) and the live gravity check widens its threshold by it.

Run to run (turn-on to turn-on, the bias repeatability of IEEE Std 1293 beside the in-run stability): what a run keeps
constant -- the bias instability's parts of 10^3-10^4 s correlation time, which a run of some minutes does not see
wander -- differs between runs, so a later run's pose means miss the calibration by it although no visit of the
campaign scatters by it. With the runs as a second random effect w_r ~ (0, R), Z (V, runs) the visits' run indicators::

    r = (I - H)(u + Z w + eta)

two quadratic forms of the residuals, the total sum r^T r and the between-run sum r^T P r (P = Z (Z^T Z)^-1 Z^T),
give two moment equations for S and R (Henderson III with two components). R is identified only when the fit leaves
part of a run's constant in the residuals, i.e. when some temperature level has two or more runs: with one run per
level, b(T) (degree 2 through three levels: one offset per level) absorbs each run's constant exactly, and no
campaign of that design can tell its run-to-run part from its b(T) (``run_matrix`` None; the file's method says
so). The published slow error is that of a pose mean in a *new* run, S + R (1 + h), h = |H Z|_F^2 / V the share of a
run's constant that the coefficients took up (their cluster-by-visit covariance does not hold it).

R is a property of the sensor (its bias repeatability), not of the campaign: a later recalibration of one run per level
takes it from an earlier calibration of the same sensor that identified it (``fit --run-to-run-from``,
:func:`carried_run_to_run`), with its own S and h (1 there: b(T) took up each run's constant). A campaign that
identifies R itself keeps its own (the sensor now, from this data) and says that the earlier one was not used.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fbg_accel_driver.noise_model import mean_variance_factor

from .thermal_fit import CellStats, jacobi_solve, model_to_coefficients, sub_columns

if TYPE_CHECKING:
    from fbg_accel_driver.thermal_model import ThermalCalibration

METHOD = ("variance component by visit beyond the noise model (method of moments on the visits' mean residuals, "
          "Henderson III; fbg_accel_calibration/fit/slow_error.py)")
MIN_DOF = 3.0  # visits left over the coefficients: fewer leave no scatter to estimate from
# fraction of the runs' constants the fit leaves in the residuals, |(I - H) Z|_F^2 / V, below which the run-to-run
# component is not identified (one run per level: 0 up to the temperature's slight wander within a run)
MIN_RUN_RESIDUAL = 0.01
RUN_NOT_IDENTIFIED = ("run-to-run component not identified (one run per temperature level: b(T) absorbs each run's "
                      "constant); repeat a level in a second run")


@dataclass(frozen=True)
class SlowError:
    """Covariance ``matrix`` (3, 3) (m/s^2)^2 of the slow error of a pose mean, the ``visits`` it rests on and the
    degrees of freedom left by the fit (tr((I - H)(I - H)^T)); ``excess`` (3,) the visits' residual scatter over what
    the noise model expects of it (1: none beyond the noise). ``matrix`` is the published total, visit and run parts
    (module docstring); ``run_matrix`` (3, 3) the run-to-run component R (None: not identified) over ``runs`` runs."""

    matrix: np.ndarray
    visits: int
    dof: float
    excess: np.ndarray
    runs: int = 1
    run_matrix: np.ndarray | None = None
    carried_from: str | None = None  # where ``run_matrix`` came from when this campaign did not identify it

    @property
    def method(self) -> str:
        """The file's method text: :data:`METHOD` and how the run-to-run component was treated."""
        if self.run_matrix is None:
            return f"{METHOD}; {RUN_NOT_IDENTIFIED}"
        if self.carried_from is not None:
            return (f"{METHOD}; plus the run-to-run component carried from {self.carried_from} (not identified by "
                    f"this campaign: one run per temperature level)")
        return (f"{METHOD}; plus the run-to-run component (a second variance component, the runs as its random "
                f"effect; {self.runs} runs)")

    @property
    def sigma_mps2(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.matrix), 0.0, None))


@dataclass(frozen=True)
class CarriedRunToRun:
    """The run-to-run component ``matrix`` R (3, 3) (m/s^2)^2, sensor frame, of an earlier calibration of sensor
    ``sensor_id``, and ``source``: that file's name, its ``created`` time and the start of its SHA-256."""

    matrix: np.ndarray
    sensor_id: str
    source: str
    option: str = "--run-to-run-from"  # how the user gave it (the CLI option, the node's parameter): named in messages


def carried_run_to_run(path: Path | str, option: str = "--run-to-run-from") -> CarriedRunToRun:
    """R of the calibration file ``path`` (its ``slow_error.run_to_run_matrix``), given as ``option`` (``fit``'s
    option, the calibration node's ``run_to_run_from`` parameter). Raises ``ValueError`` (one line, naming
    ``option``) when the file does not load or holds no run-to-run component."""
    from fbg_accel_driver.thermal_model import ThermalCalibration

    try:
        earlier = ThermalCalibration.load(path)
        digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12]
    except OSError as exc:  # a name too long for the file system; the file gone between load and hash
        raise ValueError(f"{option}: {path}: calibration file cannot be read ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise ValueError(f"{option}: {exc}") from None
    if earlier.slow_error is None or earlier.slow_error.run_to_run is None:
        has = "no slow_error section" if earlier.slow_error is None else "no run-to-run component in its slow_error"
        raise ValueError(f"{option} {path}: {has} (its campaign did not identify it); give the calibration "
                         "of a campaign with a temperature level run twice")
    created = f"created {earlier.created[:40]}, " if earlier.created else ""
    name = "".join(c if c.isprintable() else "?" for c in Path(path).name[:120])  # the method text stays one line
    return CarriedRunToRun(earlier.slow_error.run_to_run, earlier.sensor_id, f"{name} ({created}sha256 {digest})",
                           option)


def check_same_sensor(carried: CarriedRunToRun, sensor_id: str) -> str:
    """Refuses (``ValueError``, one line) an R carried from another sensor than ``sensor_id`` (this campaign's);
    returns a note (or ``""``) when either id is ``unknown`` and the match cannot be checked."""
    if "unknown" in (carried.sensor_id, sensor_id):
        return (f"note: {carried.option} {carried.source}: the sensor ids ('{carried.sensor_id}', this campaign "
                f"'{sensor_id}') do not tell whether it is the same sensor; its run-to-run component is used")
    if carried.sensor_id != sensor_id:
        raise ValueError(f"{carried.option}: {carried.source} is a calibration of sensor '{carried.sensor_id}', this "
                         f"campaign is of sensor '{sensor_id}': the run-to-run component belongs to one sensor")
    return ""


def visit_component(stats: CellStats, A: np.ndarray, degree: int, noise_sigma_mps2: np.ndarray,
                    correlated_fraction: np.ndarray, time_constant_s: np.ndarray, dt_s: float,
                    carried: CarriedRunToRun | None = None) -> SlowError | None:
    """The slow error (module docstring) of coefficients ``A`` (p, 3) fitted at ``degree`` on ``stats``, with the
    noise model (per-sample sigma m/s^2, correlated fraction, time constant s; samples ``dt_s`` s apart). None when
    the visits' own sums were not kept (``thermal_fit.MAX_VISIT_SUMS``) or too few visits are left over the
    coefficients (:data:`MIN_DOF`). ``carried``: the run-to-run component of an earlier calibration, used when this
    campaign does not identify its own."""
    if len(stats.visit_cell) == 0:
        return None
    cols = sub_columns(degree, stats.degree)
    xtx = stats.visit_xtx[:, cols][:, :, cols]
    xtg = stats.visit_xtg[:, cols]
    q = 3 * (degree + 1)  # the constant regressor: its row of a visit's X^T X is the visit's sum of regressor rows
    s = xtx[:, :, q]  # (V, p)
    n = s[:, q]  # (V,) samples
    keep = n >= 1
    s, n, xtg = s[keep], n[keep], xtg[keep]
    V = len(n)
    B = xtx.sum(axis=0)
    Binv_s = jacobi_solve(B, s.T)  # B^-1 s_w, (p, V)
    H = (s / n[:, None]) @ Binv_s  # H_vw = xbar_v^T B^-1 s_w
    Mres = np.eye(V) - H
    r = (xtg[:, q] - s @ A) / n[:, None]  # (V, 3) mean residual of each visit
    m2 = Mres**2
    dof = float(m2.sum())
    if dof < MIN_DOF:
        return None
    sigma2 = np.asarray(noise_sigma_mps2, float) ** 2
    c = np.array([[mean_variance_factor(int(nv), float(correlated_fraction[i]), float(time_constant_s[i]), dt_s)
                   for i in range(3)] for nv in n])  # (V, 3)
    noise_part = sigma2 * (m2 @ c).sum(axis=0)  # (3,)
    Q = r.T @ r
    excess = np.diag(Q) / np.maximum(noise_part, 1e-300)
    run = stats.visit_run[keep] if len(stats.visit_run) == len(keep) else np.zeros(V, np.int64)
    labels, inverse = np.unique(run, return_inverse=True)
    Z = np.zeros((V, len(labels)))
    Z[np.arange(V), inverse] = 1.0
    MZ = Mres @ Z
    b1 = float((MZ**2).sum())
    h = float(((Z - MZ) ** 2).sum()) / V  # |H Z|_F^2 / V
    if len(labels) < 2 or b1 < MIN_RUN_RESIDUAL * V:
        S = _psd((Q - np.diag(noise_part)) / dof)
        if carried is None:
            return SlowError(S, V, dof, excess, len(labels))
        R = np.asarray(carried.matrix, float)
        return SlowError(S + (1.0 + h) * R, V, dof, excess, len(labels), R, carried.source)
    # the between-run sum r^T P r and its expectation's coefficients (module docstring)
    nr = Z.sum(axis=0)
    ZtM = Z.T @ Mres  # (R, V)
    a2 = float(((ZtM**2) / nr[:, None]).sum())
    b2 = float((((ZtM @ Z) ** 2) / nr[:, None]).sum())
    noise2 = sigma2 * (((ZtM**2) / nr[:, None]).sum(axis=0) @ c)
    Q2 = (Z.T @ r).T @ ((Z.T @ r) / nr[:, None])
    lhs1, lhs2 = Q - np.diag(noise_part), Q2 - np.diag(noise2)
    det = dof * b2 - a2 * b1
    S = _psd((b2 * lhs1 - b1 * lhs2) / det)
    R = _psd((dof * lhs2 - a2 * lhs1) / det)
    return SlowError(S + (1.0 + h) * R, V, dof, excess, len(labels), R)


def _psd(m: np.ndarray) -> np.ndarray:
    """The nearest positive semi-definite matrix (eigenvalues clipped at 0) of the symmetric part of ``m``."""
    w, v = np.linalg.eigh(0.5 * (m + m.T))
    return (v * np.clip(w, 0.0, None)) @ v.T


def attach(cal: ThermalCalibration, stats: CellStats, dt_s: float,
           carried: CarriedRunToRun | None = None) -> SlowError | None:
    """Estimate the slow error of ``cal`` (its coefficients, degree and final noise model) on the fit's ``stats`` and
    set ``cal.slow_error`` (the file's ``slow_error`` section) and ``cal.fit["slow_error"]`` (figures for people);
    ``dt_s`` the sample interval (s) of the noise model; ``carried`` the run-to-run component of an earlier
    calibration of the sensor (used when this campaign does not identify it). Returns the estimate (None: nothing
    set)."""
    from fbg_accel_driver.slow_error import SlowErrorSection

    est = visit_component(stats, model_to_coefficients(cal.M, cal.b), cal.degree, cal.noise_sigma_mps2,
                          cal.noise_correlated_fraction, cal.noise_time_constant_s, dt_s, carried)
    if est is None:
        cal.fit["slow_error"] = {"not_estimated": "the visits' own sums were not kept, or fewer than "
                                 f"{MIN_DOF:g} visits are left over the coefficients: repeat the poses"}
        if carried is not None:
            cal.fit["slow_error"]["run_to_run_not_carried"] = (
                f"{carried.option} {carried.source} not used: this campaign's slow error is not estimated ("
                + cal.fit["slow_error"]["not_estimated"] + ")")
        return None
    cal.slow_error = SlowErrorSection(est.matrix, est.method, est.visits, est.run_matrix)
    cal.fit["slow_error"] = {"sigma_mps2": [round(float(v), 5) for v in est.sigma_mps2],
                             "scatter_over_noise": [round(float(v), 3) for v in est.excess],
                             "dof": round(est.dof, 2), "runs": est.runs,
                             "run_to_run_sigma_mps2": RUN_NOT_IDENTIFIED if est.run_matrix is None else
                             [round(float(v), 5) for v in np.sqrt(np.clip(np.diag(est.run_matrix), 0.0, None))]}
    if est.carried_from is not None:
        cal.fit["slow_error"]["run_to_run_carried_from"] = est.carried_from
    elif carried is not None:
        cal.fit["slow_error"]["run_to_run_not_carried"] = _carried_ignored(carried)
    return est


def _carried_ignored(carried: CarriedRunToRun) -> str:
    """Why an earlier calibration's run-to-run component was not used: this campaign identified its own."""
    return (f"{carried.option} {carried.source} not used: this campaign identifies its own run-to-run component "
            "(a temperature level with two or more runs), which is the sensor's now")


def summary_line(figures: dict) -> str | None:
    """The printed "slow error" line of the fit's figures (``cal.fit["slow_error"]``, set by :func:`attach`): the
    published sigma per axis and the run-to-run part, with where it was carried from, or why it is not a number.
    None when the slow error was not estimated."""
    if "sigma_mps2" not in figures:
        return None
    run = figures["run_to_run_sigma_mps2"]
    carried = f" (carried from {figures['run_to_run_carried_from']})" if "run_to_run_carried_from" in figures else ""
    return ("slow error of a pose mean x/y/z " + " / ".join(f"{v:.4f}" for v in figures["sigma_mps2"]) + " m/s^2; "
            + ("run to run " + " / ".join(f"{v:.4f}" for v in run) + f" m/s^2{carried}" if isinstance(run, list)
               else run))
