"""The diagnosis' final model on every sample: its design, held-out residual, the calibration file it writes (terms by
the role each effect declares: model terms, noise remedies, per-run properties), the floor after a noise remedy, the
residual's structure, and the check that the driver's ``apply_counts`` reproduces the fit.
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from fbg_accel_driver.thermal_model import ThermalCalibration

from ..fit.thermal_fit import coefficients_to_model, n_params, temperature_levels
from .adc_code_candidate import CodeWidthStep, code_width_step
from .adc_code_candidate import describe as describe_code_table
from .cv import CvResult, cross_validate, gram_conditioning
from .data import DiagnosisData, column_rms, finite_rows
from .design import Design, ModelSpec, build_design
from .findings import Finding, flagged_visits
from .floor import FloorMeasurement, VisitNoise, within_visit_noise
from .search_lanes import beside
from .structure import ResidualStructure, heldout_mean_null, heldout_visit_sums, residual_structure

Added = tuple[str, float | None, str]  # effect name, hyper-parameter, description


@dataclass
class FinalModel:
    """The final model's results (see ``fit_final``); the calibration file's output on every sample is worked out on a
    thread meanwhile (``consistency_and_moving``)."""

    cal: ThermalCalibration
    base_cal: ThermalCalibration
    added: list[Added]  # model terms
    remedies: list[Added]  # noise remedies
    run_terms: list[Added]  # per-run properties
    rig_terms: list[Added]  # properties of the rig (the table's angles)
    heldout: np.ndarray  # (N, 3) held-out residual, m/s^2
    r_eval: np.ndarray  # (N,) the samples the held-out errors are judged on
    n_static: int  # samples of r_eval
    noise_after: np.ndarray  # (3,) the floor of the final model (lower once a noise remedy is in)
    noise_model_after: VisitNoise
    before_ho: np.ndarray
    before_in: np.ndarray
    after_ho: np.ndarray
    after_in: np.ndarray
    structure: ResidualStructure
    condition_number: float
    column_correlation: dict[str, float]
    flagged: Finding | None  # visits left out of the noise floor
    code_step: CodeWidthStep  # the ADC code-width candidate, tested on top of this model (``adc_code_candidate``)
    _calibrated: Future
    _fitted_sensor: np.ndarray
    _rows_f: np.ndarray

    def consistency_and_moving(self, data: DiagnosisData) -> tuple[float, np.ndarray | None]:
        """Max |calibration file's output - fit prediction| over the static samples (m/s^2) and the RMS (3,) of the
        file's output minus the reference on the samples not used (``moving_residual``)."""
        calibrated = self._calibrated.result()
        out = consistency(calibrated, self._fitted_sensor, self._rows_f), moving_residual(data, calibrated)
        self._fitted_sensor = np.zeros((0, 3))  # (N, 3): let go once used
        return out


def fit_final(data: DiagnosisData, spec: ModelSpec, fold: np.ndarray, floor: FloorMeasurement, sensor_id: str,
              confounded: dict[str, list[str]], residual_before: np.ndarray,
              fit_before: tuple[np.ndarray, np.ndarray], alpha: float,
              code_rule: tuple[float, float], thread: bool) -> FinalModel:
    """Fit ``spec`` on every sample (folds ``fold``, weights from ``floor``), write its calibration, and judge it:
    before (``residual_before``: the declared model's held-out residual; ``fit_before``: (the reference, its fit) (N, 3)
    each, whose difference is its in-sample residual, taken at the evaluated rows only) and after, the
    floor after a noise remedy, the residual's structure at level ``alpha``. ``code_rule``: (level, least relative gain)
    the ADC code-width candidate is tested at on top of ``spec`` (when added, the model is fitted on the mapped
    counts and the file carries the table). ``thread``: the driver's path over every
    sample runs beside the rest."""
    groups, noise, settled = data.group, floor.noise, floor.settled
    weights = 1.0 / np.maximum(noise, 1e-12) ** 2
    fit_rows = data.use & (fold != -1)
    des_f = build_design(data, spec)  # no cache: written straight into its design
    cv_f = cross_validate(des_f, fit_rows, fold, weights)
    code_step = code_width_step(data, spec, fold, weights, cv_f.heldout, *code_rule)
    if code_step.added:  # the final model on the mapped counts
        des_f, cv_f = code_step.design, code_step.cv
    rows_f = data.use & des_f.valid & (fold >= 0)
    cal, base_cal, added = calibration_from(spec, des_f, cv_f, data, noise, sensor_id, confounded)
    role = {e.name: e for e, _ in spec.effects}
    remedies = [a for a in added if role[a[0]].noise_remedy]
    run_terms = [a for a in added if role[a[0]].per_run]
    rig_terms = [a for a in added if role[a[0]].rig]
    added = [a for a in added if not (role[a[0]].noise_remedy or role[a[0]].per_run or role[a[0]].rig)]
    if code_step.added:
        cal.adc_codes = code_step.table
        added.append((code_step.result.name, None, describe_code_table(code_step)))
    noise_after, noise_model_after = noise, floor.noise_model
    if remedies:  # the filtered output is less noisy: its own floor, on the same settled samples
        res_f = des_f.G - cv_f.fitted_full
        if floor.disturbance.found:  # the filtered output carries the lines too (refitted on it)
            res_f -= floor.disturbance.refit(res_f, data.t_s, groups, data.run_id, settled & rows_f)
        noise_model_after = within_visit_noise(res_f, groups, settled & rows_f, data.t_s, reference=data.ref,
                                               axis_counts=data.xyz)
        del res_f
        noise_after = noise_model_after.sigma
        cal.noise_sigma_mps2 = noise_after
    # what the calibration file reproduces: the fit without the runs' and the rig's columns (not the sensor's); the
    # fit itself when there are none (only read: no copy of N x 3)
    not_sensor = [des_f.blocks[e.name] for e, _ in spec.effects if (e.per_run or e.rig) and e.name in des_f.blocks]
    fitted_sensor = cv_f.fitted_full.copy() if not_sensor else cv_f.fitted_full
    for sl in not_sensor:
        fitted_sensor -= des_f.X[:, sl] @ cv_f.A_full[sl]
    flagged = flagged_visits(data, groups, [floor.noise_model] + ([noise_model_after] if remedies else []),
                             des_f, cv_f, fit_rows, rows_f, fold, weights)
    G_f, blocks_f = des_f.G, des_f.blocks
    r_eval = rows_f & finite_rows(residual_before) & finite_rows(cv_f.heldout)
    visit_sums = heldout_visit_sums(des_f.X, fit_rows & des_f.valid, r_eval, groups, fold)
    del des_f  # its design matrix (N x p) is let go before the residual's test
    # the driver's path over every sample (N x 3), meanwhile the rest: not beside the design
    calibrated_later = beside(calibrated_output, cal, data, thread=thread)
    null = None if visit_sums is None else heldout_mean_null(visit_sums, cv_f.sums.xtx, cv_f.sums.XtX,
                                                             noise_model_after)

    def rms(r: np.ndarray) -> np.ndarray:
        return column_rms(r[r_eval])

    def rms_of_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # rms(a - b), a - b made at r_eval alone
        return column_rms(a[r_eval] - b[r_eval])

    structure = residual_structure(data, cv_f.heldout, r_eval, groups, noise_model_after, alpha, null=null)
    cond, column_corr = gram_conditioning(cv_f.sums.XtX, cv_f.sums.xsum, len(cv_f.sums.idx), blocks_f)
    return FinalModel(cal, base_cal, added, remedies, run_terms, rig_terms, cv_f.heldout, r_eval, int(r_eval.sum()), noise_after,
                      noise_model_after, rms(residual_before), rms_of_difference(*fit_before), rms(cv_f.heldout),
                      rms(G_f - cv_f.fitted_full), structure, cond, column_corr, flagged, code_step, calibrated_later,
                      fitted_sensor, rows_f)


def calibration_from(spec: ModelSpec, des: Design, cv: CvResult, data: DiagnosisData, noise: np.ndarray,
                     sensor_id: str, confounded: dict[str, list[str]] | None = None,
                     ) -> tuple[ThermalCalibration, ThermalCalibration, list[Added]]:
    """The calibration of ``spec`` with its declared terms, the one without them (eq. 28 alone) and each effect's
    (name, hyper-parameter, description); per-run terms are fitted, not applied (the driver does not know runs)."""
    n = spec.degree
    A = cv.A_full
    M, b = coefficients_to_model(A[: n_params(n)], n)
    t = data.temp_c[data.use]
    rng = (float(np.min(t)), float(np.max(t)))
    terms, added = [], []
    for eff, h in sorted(spec.effects, key=lambda eh: eh[0].stage):
        coeff = A[des.blocks[eff.name]].T if eff.name in des.blocks else None
        terms.extend(eff.make_terms(h, coeff, data))
        added.append((eff.name, h, eff.describe_on(h, coeff, data)))
    per_run = [e.name for e, _ in spec.effects if e.per_run]
    rig = {e.name: h for e, h in spec.effects if e.rig}
    fit = {"tool": "fbg-accel-calib diagnose", "degree": n,
           "added_effects": [a[0] for a in added if a[0] not in per_run and a[0] not in rig],
           "hyper_parameters": {a[0]: a[1] for a in added if a[0] not in per_run and a[0] not in rig}}
    if per_run:  # fitted so that they do not bias eq. 28; the driver cannot apply them (it does not know runs)
        fit["per_run_terms_fitted_not_applied"] = per_run
    if rig:  # the reference was corrected for them: the rig's, never the sensor's
        fit["rig_properties_fitted_not_applied"] = rig
    if confounded:
        fit["confounded_with"] = confounded
    delay = [h for e, h in spec.effects if e.name == "channel_delay"]
    if delay:
        fit["channel_delay_s"] = float(delay[0])  # applied to time stamps, not to accelerations
    # the reference counts the model holds at, per temperature level (the driver flags a reference far off them)
    labels, level_t = temperature_levels(t)
    ref_used = np.asarray(data.ref, dtype=float)[data.use]
    level_ref = np.array([ref_used[labels == k].mean() for k in range(len(level_t))])
    model = {"M": M, "b": b, "temperature_range_c": rng, "sensor_id": sensor_id, "t_center_c": spec.t_center_c,
             "t_scale_c": spec.t_scale_c, "noise_sigma_mps2": noise, "reference_level_temperature_c": level_t,
             "reference_level_counts": level_ref}
    return ThermalCalibration(**model, fit=fit, corrections=terms), ThermalCalibration(**model), added


APPLY_BLOCK = 1 << 17  # samples per call of apply_counts in calibrated_output (bounds its temporaries)


def calibrated_output(cal: ThermalCalibration, data: DiagnosisData) -> np.ndarray:
    """The calibration file's output (N, 3) m/s^2, table frame, on every sample: ``apply_counts`` streamed per run
    in blocks of ``APPLY_BLOCK`` samples with one state, as the driver runs it."""
    out = np.full((len(data.t_s), 3), np.nan)
    for idx in data.runs():
        run = np.arange(len(data.t_s))[idx]
        state = cal.new_state()
        for lo in range(0, len(run), APPLY_BLOCK):
            b = run[lo:lo + APPLY_BLOCK]
            out[b] = cal.apply_counts(data.ref[b], data.xyz[b], data.temp_c[b], data.t_s[b], state)
    return out


def consistency(calibrated: np.ndarray, fitted: np.ndarray, rows: np.ndarray) -> float:
    """Max |calibration file's output - fit prediction| (both (N, 3)) over the static ``rows``."""
    return float(np.nanmax(np.abs(calibrated[rows] - fitted[rows]))) if rows.any() else 0.0


def moving_residual(data: DiagnosisData, calibrated: np.ndarray) -> np.ndarray | None:
    """RMS (3,) of the calibration file's output ``calibrated`` (N, 3) minus the gap-filled reference on samples not
    used (moving, settling)."""
    m = ~data.use & finite_rows(data.gref_filled)
    if m.sum() < 3:
        return None
    d = calibrated[m] - data.gref_filled[m]
    d = d[finite_rows(d)]
    return column_rms(d) if len(d) else None
