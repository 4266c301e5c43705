"""Residual diagnosis of the calibration model: find what eq. 28 lacks, add it, report before/after.

Pure numpy/scipy engine behind ``fbg-accel-calib diagnose``. Steps:

1. Static samples: the static-interval detector of the fit (``static_detector.calibration_samples``,
   signal still AND table reference constant AND in a pose) or, with ``static="table"``, every
   sample the table reports in a pose; never a sample of a reference too low (``Recording.low_reference``: no
   source light), which is taken out of the recording first, as the fit takes it out.
2. Declared model: eq. 28 at the degree chosen by cross-validation over visits (degree
   < number of temperature levels, as in ``thermal_fit``). Noise floor = per-sample standard deviation
   of its residual per axis within visits over settled samples (what no static model can remove),
   corrected for what removing each visit's mean and line takes of correlated noise
   (``within_visit_noise``); the settling transient after a table move is measured and reported on its own. A
   periodic disturbance common to the visits (a table that sways, a fan: ``periodic_disturbance``) is named, and
   the floor is the scatter without it (with it reported beside).
   A visit is one contiguous static interval of one pose id in one run (``effects.visit_ids``); the
   pose id is the orientation. Folds that would lose a direction of the table frame are split or
   their visit kept in training (``check_folds``).
3. Every candidate of ``effects.LIBRARY`` on top of the current model: hyper-parameter by a 1-D
   search (grid; nested inside each training fold for the held-out figures, then refined on all
   data for the final value); held-out residuals by K-fold cross-validation over visits;
   per-visit paired gain in noise-weighted held-out MSE; one-sided Wilcoxon signed-rank test over
   visits (Bonferroni over the candidates of the step); correlation of the candidate's
   contribution with the held-out residual; pairwise confounding among the significant ones (each
   added on top of the other: does it still gain?).
4. Forward selection: add the best significant candidate, repeat; stop when no candidate is
   significant or gains less than ``min_rel_gain`` of the held-out MSE (so nothing is added when
   nothing is significant). Above ``SEARCH_ROWS`` fitted samples, steps 3-4 run on every k-th fitted
   sample (the same visits and folds; ``search_samples``: k no larger than keeps ``MIN_SEARCH_INFORMATION``
   of what a visit's samples tell of its mean) and only the chosen model is fitted on all.
5. Refit with the winners as declared ``corrections`` of a ``ThermalCalibration``; check that the
   driver's ``apply_counts`` reproduces the fit's prediction; before/after held-out RMSE per axis
   next to the noise floor; test and describe what residual remains (per pose, axis, temperature,
   time, orientation).

Significance is tested with visits as the independent units, not samples: the noise of this
sensor is low-pass filtered (TIA ~1 Hz at 100 Hz sampling), so consecutive samples are strongly
correlated and a sample-level F-test would be far too optimistic.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np

from fbg_accel_driver.thermal_model import ThermalCalibration

from .adc_code_candidate import code_width_step
from .adc_code_candidate import describe as describe_code_table
from .adc_codes import HeldCode, held_codes
from .blas_threads import single_blas_thread
from .diagnosis.cv import (
    COLLINEAR_CORR,
    CvResult,
    check_folds,
    cross_validate,
    gram_conditioning,
    make_folds,
)

# ============================================================================ data preparation
from .diagnosis.design import (
    Design,
    ModelSpec,
    build_design,
    fitted_output,
    prepare_data,
)
from .diagnosis.floor import (
    FLOOR_VISIT_ALPHA,
    FLOOR_VISIT_RATIO,
    SettlingTransient,
    VisitNoise,
    _first_kept_age,
    _fmt3,
    settle_window,
    settled_mask,
    settling_transient,
    within_visit_noise,
)
from .diagnosis.search import (
    LANE_SEARCH_ROWS,
    SEARCH_ROWS,
    CandidateResult,
    Evaluator,
    _corr,
    _evaluate_on,
    check_search_rows,
    cross_correlation_delay,
    judge_step,
    paired_gain_test,
    reselect_degree,
    search_samples,
    select_degree,
    time_block_check,
)
from .diagnosis.structure import (
    SMALL_RATIO,
    ResidualStructure,
    coefficient_mean_variance,
    residual_structure,
)
from .effects import (
    LIBRARY,
    DiagnosisData,
    Effect,
    finite_rows,
    separating_measurement,
    visit_means,
)
from .heap_trim import return_free_memory
from .periodic_disturbance import PeriodicDisturbance, find_periodic_disturbance
from .recording import Recording, time_axis_label
from .search_lanes import Lanes, beside, default_lane_count
from .temperature_reading import jump_warning
from .thermal_fit import (
    NotIdentifiedError,
    coefficients_to_model,
    n_params,
    reference_reach_warnings,
    temperature_levels,
    temperature_scaling,
)


# ============================================================================ the diagnosis
@dataclass
class Confounding:
    a: str
    b: str
    corr_contributions: float
    p_b_beyond_a: float
    p_a_beyond_b: float
    verdict: str
    gain_b_beyond_a: float
    gain_a_beyond_b: float  # "confounded", "<a> explains <b>", "both"
    separating_measurement: str


@dataclass
class StepResult:
    step: int
    model: list[str]
    candidates: list[CandidateResult]
    chosen: str | None
    alpha_each: float
    confounding: list[Confounding]
    degree_table: list[dict[str, Any]] = field(default_factory=list)  # degree re-selected after adding ``chosen``
    degree_note: str = ""
    degree_after: int | None = None  # the re-selected degree


@dataclass
class DiagnosisResult:
    data: DiagnosisData
    degree: int
    degree_table: list[dict[str, Any]]
    n_levels: int
    noise_floor: np.ndarray  # (3,) m/s^2
    before_heldout_rmse: np.ndarray  # (3,)
    before_insample_rmse: np.ndarray
    after_heldout_rmse: np.ndarray
    after_insample_rmse: np.ndarray
    steps: list[StepResult]
    added: list[tuple[str, float | None, str]]  # name, hyper, description
    calibration: ThermalCalibration
    base_calibration: ThermalCalibration
    residual_before: np.ndarray  # (N, 3) held-out residual of the declared model
    residual_after: np.ndarray  # (N, 3) held-out residual of the final model
    structure: ResidualStructure
    consistency_max_abs_mps2: float
    n_static: int
    n_groups: int
    moving_residual_rms: np.ndarray | None
    settings: dict[str, Any]
    settling: SettlingTransient | None = None  # the settling transient after table moves (not in the floor)
    fold_notes: list[str] = field(default_factory=list)  # folds split or visits never held out (check_folds)
    n_floor_samples: int = 0  # settled samples the noise floor is computed from
    # filters against noise chosen like effects (e.g. the reference low-pass), not model effects: name, hyper, text
    noise_remedies: list[tuple[str, float | None, str]] = field(default_factory=list)
    noise_floor_after: np.ndarray | None = None  # (3,) floor of the final model (lower once a noise remedy is in)
    warnings: list[str] = field(default_factory=list)  # results a reader must not take at face value
    condition_number: float = float("nan")  # of the final model's scaled normal matrix (gram_conditioning)
    column_correlation: dict[str, float] = field(default_factory=dict)  # added effect -> max |corr| with the others
    final_degree: int = -1  # degree of eq. 28 in the final model (re-selected after each added effect)
    run_terms: list[tuple[str, float | None, str]] = field(default_factory=list)  # per-run terms (not in the YAML)
    held_codes: list[HeldCode] = field(default_factory=list)  # ADC codes that held whole visits (adc_codes)
    # a periodic disturbance found in the visits (periodic_disturbance): when found, the floors above are without it
    disturbance: PeriodicDisturbance = field(default_factory=lambda: PeriodicDisturbance([], (math.nan, math.nan), 0,
                                                                                          0.0, math.inf))

    @property
    def final_floor(self) -> np.ndarray:
        """The floor the final held-out error is judged against (m/s^2, x/y/z)."""
        return self.noise_floor if self.noise_floor_after is None else self.noise_floor_after

    @property
    def ranked(self) -> list[CandidateResult]:
        return self.steps[0].candidates if self.steps else []


@single_blas_thread
def diagnose(rec: Recording | DiagnosisData, *, static: str = "table", max_degree: int = 4, folds: int = 10,
             alpha: float = 0.01, min_rel_gain: float = 0.02, max_effects: int = 3, library: tuple[Effect, ...] = LIBRARY,
             degree: int | None = None, sensor_id: str = "unknown", seed: int = 0,
             progress: Callable[[str], None] | None = None, settle_s: float | None = None,
             search_rows: int | None = SEARCH_ROWS, lanes: int | None = None) -> DiagnosisResult:
    """Run the whole diagnosis on a recording (see the module docstring). ``progress`` (optional) is called
    with the candidate's name after each candidate evaluation (the CLI's progress bar). ``settle_s`` (s):
    samples this close to the start of a visit are left out of the noise floor (``settled_mask``); None: the
    window where the measured settling transient falls below a tenth of the noise (``settle_window``).
    ``search_rows``: above this many fitted samples, the candidates are evaluated and the model chosen on a
    thinned set, and the chosen model fitted on every sample (``search_samples``); None: always on every sample.
    ``lanes``: how many searches run side by side (``search_lanes``; the results are the same with any number);
    None: ``default_lane_count()`` when at least ``LANE_SEARCH_ROWS`` samples are searched, one otherwise. With more
    than one (or, with None, from ``LANE_SEARCH_ROWS`` samples of the recording on, on a machine of two cores or more),
    the work before the first search uses a second thread too. The process's heap policy is its entry point's
    (``heap_trim.set_process_heap_policy``: the command line sets it; the results do not depend on it).

    It runs with one BLAS thread (``blas_threads``): its products of tall, narrow matrices gain nothing from more,
    and lose much when another process holds a core."""
    check_search_rows(search_rows)  # before seconds of work at 10^6 samples, not after
    return_free_memory()  # what the caller dropped (a simulation, an MCAP read), before the diagnosis's arrays are made
    # a large recording's searches run side by side: until they start, the other core takes what it can
    side_by_side = (default_lane_count() > 1 and len(rec.t_s) >= LANE_SEARCH_ROWS) if lanes is None else int(lanes) > 1
    data = rec if isinstance(rec, DiagnosisData) else prepare_data(rec, static, beside_thread=side_by_side)
    groups = data.group

    def folds_and_constants() -> tuple[np.ndarray, list[str]]:
        """The folds and, on a thread of their own, the constants of the recording the first searches ask for
        (``DiagnosisData.once``)."""
        out = check_folds(data, groups, make_folds(groups, data.use, folds, seed))
        if side_by_side:
            for e in library:
                e.applicable(data)
            data.static_psi_map()
            data.run_steps()
        return out

    # beside the degree selection (when the searches will run side by side: the other core idles until then)
    folds_later = beside(folds_and_constants, thread=side_by_side)
    n_levels = data.temperature_level_count()
    try:
        sel_degree, degree_table = select_degree(data, max_degree)
    except Exception:
        folds_later.result()  # a recording the folds cannot be drawn on says so first
        raise
    fold, fold_notes = folds_later.result()
    if degree is not None:
        if degree >= n_levels:
            raise NotIdentifiedError(f"degree {degree} is not identified by {n_levels} temperature level(s)")
        sel_degree = degree
    c, s = temperature_scaling(data.temp_c[data.use])
    spec = ModelSpec(sel_degree, c, s)

    # declared model, noise floor and weights
    des0 = build_design(data, spec)
    cv0 = cross_validate(des0, data.use, fold, np.ones(3))
    rows = data.use & des0.valid & (data.pose_id >= 0)  # the floor: scatter within visits, not during moves
    res0 = des0.G - cv0.fitted_full
    settling_later = beside(settling_transient, res0, data.t_s, groups, rows, thread=side_by_side)
    # the rule of SETTLE_NOISE_FRACTION at either end; the floor it compares with is itself settled. A forced
    # settle_s fixes the start; the end is trimmed only where it is measured disturbed
    auto_start = settle_s is None
    settle_s = 0.0 if settle_s is None else float(settle_s)

    def floor(start_s: float, stop_s: float | None) -> tuple[float, float | None, VisitNoise]:
        return start_s, stop_s, within_visit_noise(res0, groups, settled_mask(data.t_s, groups, rows, start_s, stop_s),
                                                   data.t_s)

    # the last floor worked out, at (settle_s, end_s): meanwhile the transient is measured, the first one with the end
    # kept (as it is unless the end is disturbed)
    floor_at: tuple[float, float | None, VisitNoise] | None = floor(settle_s, None) if side_by_side else None
    settling = settling_later.result()
    end_s = 0.0 if settling.end_detected else None
    for _ in range(4):
        if not auto_start and end_s is None:
            break
        if floor_at is None or floor_at[:2] != (settle_s, end_s):
            floor_at = floor(settle_s, end_s)
        sigma = floor_at[2].sigma
        grew = False
        if auto_start and (nxt := settle_window(settling, sigma)) > settle_s * (1 + 1e-3):
            settle_s, grew = nxt, True
        if end_s is not None and (nxt := settle_window(settling, sigma, end=True)) > end_s * (1 + 1e-3):
            end_s, grew = nxt, True
        if not grew:
            break
    settled = settled_mask(data.t_s, groups, rows, settle_s, end_s)
    # the windows that did not grow are those of the last floor worked out: that floor, not the same one again
    noise_model = (floor_at[2] if floor_at is not None and floor_at[:2] == (settle_s, end_s)
                   else within_visit_noise(res0, groups, settled, data.t_s))
    noise = noise_model.sigma
    if not np.all(np.isfinite(noise)) or np.any(noise <= 0):
        raise ValueError(f"no noise floor: {int(settled.sum())} settled samples (every visit shorter than "
                         f"{settle_s:.3g} s plus one sample?); lower settle_s")
    # a periodic disturbance during the visits (a table that sways, a fan) is no noise of the sensor: named, and the
    # floor is the scatter without it (its floor with it reported beside: PeriodicDisturbance.floor_with_lines)
    disturbance = find_periodic_disturbance(res0, data.t_s, groups, data.run_id, settled)
    if disturbance.found:
        disturbance.floor_with_lines = noise
        noise_model = within_visit_noise(res0 - disturbance.model(data.t_s, data.run_id), groups, settled, data.t_s)
        noise = noise_model.sigma
    settling.settle_s, settling.n_dropped = float(settle_s), int((rows & ~settled).sum())
    settling.end_settle_s = end_s
    settling.end_n_dropped = int((settled_mask(data.t_s, groups, rows, settle_s) & ~settled).sum())
    # what may still reach the floor: the decay at the window's edge, for an unresolved one (window: the first, or
    # last, sample) its bound at the next position, the first kept
    if settling.detected and np.isfinite(settling.tau_s) and settling.tau_s > 0:
        kept = _first_kept_age(settle_s, settling.tau_resolved, settling.age_s)
        settling.residual_after_settle_mps2 = settling.amplitude_mps2 * np.exp(-max(kept, 1e-12) / settling.tau_s)
    if end_s is not None and np.isfinite(settling.end_tau_s) and settling.end_tau_s > 0:
        kept = _first_kept_age(end_s, settling.end_tau_resolved, settling.end_age_s)
        settling.end_residual_after_settle_mps2 = (settling.end_amplitude_mps2
                                                   * np.exp(-max(kept, 1e-12) / settling.end_tau_s))
    weights = 1.0 / np.maximum(noise, 1e-12) ** 2
    fit_rows = data.use & (fold != -1)  # fitted (also the visits never held out, fold -2)
    # a search thinned to fewer rows keeps most of what a visit's samples tell of its mean (the noise is correlated)
    fitted_per_visit = np.bincount(groups[fit_rows & (groups >= 0)], minlength=1)
    fitted_per_visit = fitted_per_visit[fitted_per_visit > 0]
    every, step, kept = search_samples(fit_rows, fold, search_rows, noise_model,
                                       float(np.median(fitted_per_visit)) if fitted_per_visit.size else math.inf)
    thinned = step > 1
    # where the candidates are evaluated and the model chosen; a thinned search's corrected reference is small
    # beside the correction of the whole series it saves: it keeps a search's grid of them for the next model
    sel = Evaluator(data, fold, weights, groups, every, references=24 if thinned else 4)
    n_lanes = (default_lane_count() if len(every) >= LANE_SEARCH_ROWS else 1) if lanes is None else int(lanes)
    # the heap's free pages given back after each batch of searches side by side: what each search made and dropped
    searchers = Lanes([sel] + [sel.lane() for _ in range(n_lanes - 1)], after_map=return_free_memory)
    residual_before = cv0.heldout
    fitted_all = cv0.fitted_full  # the current model's in-sample fit on all samples (the cross-correlation delay)
    base_coefficients: np.ndarray | None = None  # the current model's coefficients when fitted_all is not worked out
    del cv0
    des_s, cv_s = sel.cv(spec)
    base_heldout, base_fitted, base_G = cv_s.heldout, cv_s.fitted_full, des_s.G
    del des_s, cv_s, des0  # the declared model's design matrix (N x p) is not needed again

    steps: list[StepResult] = []
    detection_limit = ""
    time_folds: np.ndarray | None = None  # contiguous blocks of time (time_block_check), made when first needed
    step_confounded: dict[str, str] = {}  # a candidate that a step of the response fits as well: the warning
    reselect_up_to = max_degree if degree is None and n_levels >= 2 else None  # eq. 28's degree is chosen again
    remaining = [e for e in library]
    reading_jumped = bool(data.temperature_jumps) and n_levels >= 2  # eq. 28 reads a reading that jumps
    seconds: dict[str, float] = {}  # what each candidate's evaluation took (the order they start in: Lanes.map)
    while remaining and len(spec.effects) < max_effects:
        # Bonferroni over the candidates the data can show at all (known before any is evaluated)
        alpha_each = alpha / max(sum(e.applicable(data)[0] for e in remaining), 1)
        # the channel delay's cross-check, of the current model alone, worked out beside the searches (its fit (N, 3) is
        # let go once it is done)
        xcorr_later = None
        if any(e.name == "channel_delay" and e.applicable(data)[0] for e in remaining):
            xcorr_later = beside(cross_correlation_delay, data, fitted_output(data, spec, base_coefficients)
                                 if fitted_all is None else fitted_all, thread=n_lanes > 1)
        fitted_all = None
        # the candidates side by side, each on a free lane (their results do not depend on which, or in what order)
        # the longest first (what each took at the step before; one worked out by the confounding check is remembered)
        results = searchers.map(partial(_evaluate_on, spec, base_heldout, base_fitted, base_G, alpha_each, seconds),
                                remaining, None if progress is None else lambda r: progress(r.name),
                                cost=lambda e, model=spec, ev=sel: 0.0 if ev.remembers(model, e) else seconds.get(e.name, 0.0))
        for r in results:
            if r.name == "channel_delay" and r.applicable and xcorr_later is not None:
                r.cross_correlation_delay_s = xcorr_later.result()
        tested = [r for r in results if r.applicable]
        n_vis = max((r.n_groups for r in tested), default=0)
        if not steps and tested and 0.5 ** n_vis >= alpha_each:
            detectable = [r.detectable_gain for r in tested if np.isfinite(r.detectable_gain)]
            detection_limit = (f"this campaign has {n_vis} visits: the one-sided signed-rank test over visits cannot "
                               f"go below p = 2^-{n_vis} = {0.5 ** n_vis:.2g}, above the {alpha_each:.2g} each "
                               f"candidate needs (alpha {alpha:g} over {len(tested)} candidates); at least "
                               f"{math.ceil(-math.log2(alpha_each)) + 1} visits are needed for it (repeat the poses, "
                               "or visit more orientations). "
                               + (f"Candidates are tested with a one-sided paired t-test over the visits instead (df "
                                  f"{n_vis - 1}; it assumes normally distributed per-visit differences): with the "
                                  f"scatter of these visits the smallest held-out gain it detects with 80 % power is "
                                  f"{100 * min(detectable):.3g} % (median over the candidates "
                                  f"{100 * float(np.median(detectable)):.3g} %)" if detectable else
                                  "Too few visits for a paired t-test as well: no effect can be added whatever its size"))
        for r in tested:
            r.significant = r.p_value < alpha_each and r.rel_gain >= min_rel_gain and not r.implausible
            eff_r = next(e for e in remaining if e.name == r.name)
            if r.significant and eff_r.void(r.hyper):
                r.significant = False  # its value on all samples changes nothing: there is nothing to add
                r.detail += "; not added: its value on all samples changes nothing"
            if r.significant and eff_r.follows_a_step and reading_jumped:
                # a jump of the temperature reading moves eq. 28's output once, which this candidate can follow: what it
                # would write is the reading's fault, not the sensor's (test_a_fault_of_the_temperature_reading_...)
                r.significant = False
                r.detail += ("; not added: the AHT10 reading jumps (a sensor re-seated, a spike, a frozen reading), "
                             "and eq. 28 evaluated at it moves the output once, which this candidate can follow")
            if r.significant and eff_r.time_function:
                if time_folds is None:
                    time_folds = check_folds(data, groups, make_folds(groups, data.use, folds, time_blocks=True))[0]
                g, p = r.time_block = time_block_check(data, spec, eff_r, r.hyper, every, time_folds, weights, alpha_each)
                if p < alpha_each and g >= min_rel_gain:
                    r.detail += f"; it also predicts contiguous blocks of time held out (gain {100 * g:+.1f} %, p = {p:.2g})"
                else:
                    r.significant = False
                    r.detail += (f"; not added: it does not predict contiguous blocks of time held out (gain "
                                 f"{100 * g:+.1f} %, p = {p:.2g}): it follows a slow wander of the residual between "
                                 "visits, not a drift it can extrapolate")
            step_confounded.pop(r.name, None)  # the last step's word on it
            if r.significant and eff_r.follows_a_step and eff_r.time_function:
                judge_step(searchers, spec, r, eff_r, alpha_each, min_rel_gain, reselect_up_to, step_confounded)
        results.sort(key=lambda r: (not r.applicable, -r.rel_gain))
        # a function of the temperature's history is set against the step when it is about to be added (the best
        # significant candidate left), not at every step it is significant at: on a cycled run it is significant at
        # most steps, and each check searches the step's time twice. Whatever is added has passed it.
        checked: set[str] = set()
        while (best := next((r for r in results if r.significant), None)) is not None and best.name not in checked:
            checked.add(best.name)
            eff_b = next(e for e in remaining if e.name == best.name)
            if eff_b.follows_a_step and not eff_b.time_function:
                judge_step(searchers, spec, best, eff_b, alpha_each, min_rel_gain, reselect_up_to, step_confounded)
        sig = [r for r in results if r.significant]
        conf = _confounding(searchers, spec, sig, alpha_each, min_rel_gain, library) if len(sig) >= 2 else []
        chosen = sig[0].name if sig else None
        for r in results:  # per-sample arrays (N, 3) are kept only where the report plots them: first step's deltas
            r.delta, r.delta_rows = (None, None) if steps else (r.delta, sel.sub)
        steps.append(StepResult(len(steps) + 1, spec.names, results, chosen, alpha_each, conf))
        if chosen is None:
            break
        eff = next(e for e in remaining if e.name == chosen)
        spec = spec.plus(eff, sig[0].hyper)
        remaining = [e for e in remaining if e.name != chosen]
        if degree is None and n_levels >= 2:  # with one level only degree 0 is identified: nothing to re-select
            was = spec.degree
            spec, steps[-1].degree_table, notes = reselect_degree(searchers, spec, max_degree)
            steps[-1].degree_after = spec.degree
            steps[-1].degree_note = (f"degree of eq. 28 re-selected with {chosen} in the model: "
                                     + (f"{was} -> {spec.degree}" if spec.degree != was else f"{was}, unchanged")
                                     + "".join(f"; {n}" for n in notes))
        des_c, cv_c = sel.cv(spec)
        searchers.each(lambda ev, model=spec: ev.forget(model))
        return_free_memory()  # what the step's searches dropped, before the next step's are made
        base_heldout, base_fitted, base_G = cv_c.heldout, cv_c.fitted_full, des_c.G
        base_coefficients = cv_c.A_full
        del des_c, cv_c  # the design (n x p) is not held beyond the evaluator's own caches

    # final model, built once the caches of the search are let go
    n_search = len(sel.folds) if thinned else None
    del sel, searchers
    data.drop_recent()
    return_free_memory()  # the search's corrected series and designs, before the final design (N x p) is built
    des_f = build_design(data, spec)  # no cache: written straight into its design
    cv_f = cross_validate(des_f, fit_rows, fold, weights)
    codes = code_width_step(data, spec, fold, weights, cv_f.heldout, steps[0].alpha_each if steps else alpha, min_rel_gain)
    steps.append(StepResult(len(steps) + 1, spec.names, [codes.result], codes.result.name if codes.added else None,
                            codes.alpha_each, []))
    if codes.added:  # the final model on the mapped counts (adc_code_candidate)
        des_f, cv_f = codes.design, codes.cv
    rows_f = data.use & des_f.valid & (fold >= 0)
    confounded = {st.chosen: [c.b if c.a == st.chosen else c.a for c in st.confounding
                              if c.verdict == "confounded" and st.chosen in (c.a, c.b)] for st in steps if st.chosen}
    confounded = {k: v for k, v in confounded.items() if v}
    cal, base_cal, added = _calibration_from(spec, des_f, cv_f, data, noise, sensor_id, confounded)
    remedy_names = {e.name for e, _ in spec.effects if e.noise_remedy}
    per_run_names = {e.name for e, _ in spec.effects if e.per_run}
    remedies = [a for a in added if a[0] in remedy_names]
    run_terms = [a for a in added if a[0] in per_run_names]
    added = [a for a in added if a[0] not in remedy_names | per_run_names]
    if codes.added:
        cal.adc_codes, added = codes.table, [*added, (codes.result.name, None, describe_code_table(codes))]
    noise_after, noise_model_after = noise, noise_model
    if remedies:  # the filtered output is less noisy: its own floor, on the same settled samples
        res_f = des_f.G - cv_f.fitted_full
        if disturbance.found:  # the filtered output carries the lines too (refitted on it)
            res_f -= disturbance.refit(res_f, data.t_s, groups, data.run_id, settled & rows_f)
        noise_model_after = within_visit_noise(res_f, groups, settled & rows_f, data.t_s)
        del res_f
        noise_after = noise_model_after.sigma
        cal.noise_sigma_mps2 = noise_after
    # the driver's path over every sample, worked out meanwhile the rest
    calibrated_later = beside(_calibrated, cal, data, thread=n_lanes > 1)  # its result: after the held codes
    fitted_sensor = cv_f.fitted_full.copy()  # what the calibration file reproduces: without the per-run terms
    for name in per_run_names:
        sl = des_f.blocks[name]
        fitted_sensor -= des_f.X[:, sl] @ cv_f.A_full[sl]
    floor_note = _flagged_visits_note(data, groups, [noise_model] + ([noise_model_after] if remedies else []),
                                      des_f, cv_f, fit_rows, rows_f, fold, weights)
    G_f, blocks_f = des_f.G, des_f.blocks
    r_eval = rows_f & finite_rows(residual_before) & finite_rows(cv_f.heldout)
    fit_var = coefficient_mean_variance(des_f.X, fit_rows & des_f.valid, groups, cv_f.sums.XtX, noise_model_after,
                                        int(fold.max()) + 1)
    del des_f  # its design matrix (N x p) is let go once cv_f's held-out residual is worked out
    before_ho = np.sqrt(np.mean(residual_before[r_eval] ** 2, axis=0))
    after_ho = np.sqrt(np.mean(cv_f.heldout[r_eval] ** 2, axis=0))
    before_in = np.sqrt(np.mean(res0[r_eval] ** 2, axis=0))
    after_in = np.sqrt(np.mean((G_f - cv_f.fitted_full)[r_eval] ** 2, axis=0))
    structure = residual_structure(data, cv_f.heldout, r_eval, groups, noise_model_after, alpha, fit_var=fit_var)
    warnings = [detection_limit] if detection_limit else []
    warnings += [w for name, w in step_confounded.items() if name in spec.names]
    # an added function of the orientation with a residual left that is not one (visits of one direction disagree), and
    # not small (the slow part of the noise, bias instability between visits minutes apart, makes a small one common)
    table_axes = [a for j, a in enumerate("xyz") if structure.pose_chi2_p[j] < alpha / 3
                  and structure.other_pose_chi2_p[j] < alpha / 3 and structure.ratio[j] > SMALL_RATIO]
    for e, _ in spec.effects:
        if e.orientation_function and table_axes:
            warnings.append(f"{e.name} is a function of the orientation, but what remains on {'/'.join(table_axes)} "
                            "differs between the poses of one direction of gravity (p "
                            + ", ".join(f"{structure.other_pose_chi2_p['xyz'.index(a)]:.1e}" for a in table_axes)
                            + "): on a plan whose directions and table angles go together it may stand in for an "
                            "effect of the table's angles (a cable the table drags, the table's geometry) that is "
                            "no property of the sensor; turn the sensor by 90 degrees on the table and compare")
    if floor_note:
        warnings.append(floor_note)
    if disturbance.found:
        lines_ho = disturbance.refit(cv_f.heldout, data.t_s, groups, data.run_id, settled & r_eval)
        disturbance.heldout_without_lines = np.sqrt(np.mean((cv_f.heldout - lines_ho)[r_eval] ** 2, axis=0))
        del lines_ho
        warnings.append(disturbance_warning(disturbance, noise, after_ho))
    held = held_codes(np.column_stack([data.ref, data.xyz]), groups, settled & r_eval,
                      _visit_offset(cv_f.heldout, groups, r_eval, noise_after), alpha)
    for h in held:
        means = np.array([cv_f.heldout[r_eval & (groups == v)].mean(axis=0) for v in h.visits])
        h.worst_offset = means[np.argmax(np.abs(means), axis=0), np.arange(3)]
        rest = r_eval & ~np.isin(groups, h.visits)
        h.rmse_without = np.sqrt(np.mean(cv_f.heldout[rest] ** 2, axis=0))
        warnings.append(h.sentence())
    calibrated = calibrated_later.result()  # what needs the calibration file's output, once the rest is done
    consistency = _consistency(calibrated, fitted_sensor, rows_f)
    moving = _moving_residual(data, calibrated)
    del calibrated, fitted_sensor
    if settling.end_detected:
        warnings.append(settling.end_summary() + "; the model is fitted on them too: align the table's readings "
                        "(pose labels, reference) with the signal")
    warnings += reference_reach_warnings(_visit_reference_range(data, groups, r_eval))
    if data.low_reference_note:
        warnings.append(data.low_reference_note)
    if data.temperature_jumps:
        warnings.append(jump_warning(data.temperature_jumps, n_levels >= 2))
    if data.n_clipped_visits:
        warnings.append(f"{data.n_clipped_samples} samples of {data.n_clipped_visits} visit(s) left out: a channel "
                        "clipped at a rail of the ADC (an axis at 0 or 4095 counts, or the reference at 4095) in each; a "
                        "clipped reading bounds the signal instead of measuring it (lower the source power or the "
                        "gain if the signal sits at the rail)")
    cond, column_corr = gram_conditioning(cv_f.sums.XtX, cv_f.sums.xsum, len(cv_f.sums.idx), blocks_f)
    for name, c in column_corr.items():
        if c > COLLINEAR_CORR:
            warnings.append(f"a column of {name} correlates at |r| = {c:.4f} with another column of the model: their "
                            "coefficients are not separately determined (large terms that cancel), whatever the "
                            "held-out gain")
    below = after_ho < 0.9 * noise_after
    if np.any(below):
        warnings.append("held-out error below the noise floor on axis " + ", ".join(a for a, b in zip("xyz", below, strict=True)
                        if b) + f" ({_fmt3(after_ho)} against {_fmt3(noise_after)} m/s^2): a model cannot predict "
                        "held-out data better than the data repeat themselves, so the floor or the model is wrong "
                        "(an added term that removes noise instead of an effect?)")
    time_label = time_axis_label(rec.metadata) if isinstance(rec, Recording) else "time [s]"
    if time_label == "time [s]":  # the report's times start at the first sample (residual_structure)
        time_label = "time from the first sample [s]"
    return DiagnosisResult(
        data=data, degree=sel_degree, degree_table=degree_table, n_levels=n_levels, noise_floor=noise,
        before_heldout_rmse=before_ho, before_insample_rmse=before_in, after_heldout_rmse=after_ho,
        after_insample_rmse=after_in, steps=steps, added=added, calibration=cal, base_calibration=base_cal,
        residual_before=residual_before, residual_after=cv_f.heldout, structure=structure,
        consistency_max_abs_mps2=consistency, n_static=int(r_eval.sum()), n_groups=len(np.unique(groups[r_eval])),
        moving_residual_rms=moving, settling=settling, fold_notes=fold_notes, n_floor_samples=int(settled.sum()),
        noise_remedies=remedies, noise_floor_after=noise_after if remedies else None, warnings=warnings,
        condition_number=cond, column_correlation=column_corr, final_degree=spec.degree, run_terms=run_terms,
        held_codes=held, disturbance=disturbance,
        settings={"static": static if not isinstance(rec, DiagnosisData) else "given", "folds": int(fold.max()) + 1,
                  "alpha": alpha, "min_rel_gain": min_rel_gain, "max_effects": max_effects, "seed": seed,
                  "search_rows": n_search, "search_step": step, "search_information": kept,
                  "degree_forced": degree is not None,
                  "settle_s": settle_s,
                  "time_label": time_label})


def disturbance_warning(d: PeriodicDisturbance, floor: np.ndarray, heldout: np.ndarray) -> str:
    """The warning for a periodic disturbance found in the visits: what, the floor with and without it (m/s^2), what
    the held-out error ``heldout`` (3,) m/s^2 is with and without it, and the basis of the ratios."""
    return (f"{d.summary()}. The noise floor {_fmt3(floor)} m/s^2 is the scatter within visits without the disturbance "
            f"(with it {_fmt3(d.floor_with_lines)}); the held-out error {_fmt3(heldout)} m/s^2 holds it "
            f"({_fmt3(d.heldout_without_lines)} without it), so the ratios to the floor count it as a residual of this "
            "recording, not of the sensor: find what shook the table or chamber, and record again")


def _flagged_visits_note(data: DiagnosisData, groups: np.ndarray, models: list[VisitNoise], des: Design, cv: CvResult,
                         fit_rows: np.ndarray, rows: np.ndarray, fold: np.ndarray, weights: np.ndarray) -> str:
    """The warning for the visits left out of the noise floor (``VisitNoise.flagged``), "" without any.

    They stay in the fit (no data is dropped behind the user's back); the warning says by how much they move it:
    the final model refitted once without them, the largest change of its fitted output on the other visits'
    samples per axis."""
    seen: dict[int, np.ndarray] = {}
    for m in models:
        for g, scatter, _ in m.flagged:
            seen[g] = np.maximum(seen.get(g, scatter), scatter)
    if not seen:
        return ""
    labels = np.array(sorted(seen))
    bad = np.isin(groups, labels)
    names = []
    for g in labels:
        at = np.flatnonzero((groups == g) & (data.pose_id >= 0))
        if not at.size:
            at = np.flatnonzero(groups == g)
        names.append(f"pose {int(data.pose_id[at[0]])} (run {int(data.run_id[at[0]])}, t {data.t_s[at[0]]:.1f}-"
                     f"{data.t_s[at[-1]]:.1f} s) {_fmt3(seen[g])} x floor")
    try:
        with np.errstate(all="ignore"):
            moved = des.X @ (cross_validate(des, fit_rows & ~bad, fold, weights).A_full - cv.A_full)
        other = rows & ~bad & finite_rows(moved)
        shift = (f"leaving them out of the fit as well moves the fitted output on the other visits by up to "
                 f"{_fmt3(np.max(np.abs(moved[other]), axis=0))} m/s^2 (x/y/z)" if other.any() else
                 "no other visit to compare the fit without them on")
    except (np.linalg.LinAlgError, ValueError, IndexError):
        shift = "the model cannot be fitted without them"
    n_v = max(m.n_checked for m in models)
    return (f"{len(labels)} visit(s) left out of the noise floor, their scatter far beyond the other visits' (variance "
            f"over {FLOOR_VISIT_RATIO:g}x the visits' median and p < {FLOOR_VISIT_ALPHA:g} / (3 x {n_v} visits) each): "
            + "; ".join(names) + f". They stay in the fit: {shift}; a burst of outliers or a dead channel there? "
            "Cut that stretch and run again if the change matters")


def _visit_offset(res: np.ndarray, groups: np.ndarray, rows: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """(N,) for every sample of ``rows``: how far its visit's output is off, the squared norm of the visit's mean
    residual ``res`` (N, 3) over the noise ``floor`` (3,) m/s^2; NaN elsewhere."""
    out = np.full(len(groups), np.nan)
    idx = np.flatnonzero(rows)
    labels, inv = np.unique(groups[idx], return_inverse=True)
    n = np.bincount(inv, minlength=len(labels))
    mean = np.stack([np.bincount(inv, res[idx, j], minlength=len(labels)) for j in range(3)], axis=1) / n[:, None]
    out[idx] = np.sum((mean / np.maximum(floor, 1e-12)) ** 2, axis=1)[inv]
    return out


def _confounding(lanes: Lanes[Evaluator], spec: ModelSpec, sig: list[CandidateResult], alpha_each: float,
                 min_rel_gain: float, library: tuple[Effect, ...]) -> list[Confounding]:
    """The candidate about to be added (``sig[0]``, the largest gain) against each of the next three significant
    ones: does each still gain on top of the other? (Pairs among the others are judged at the next step, on top
    of the one added, so they are not worked out here.) The searches of each on top of the other run side by side
    on ``lanes``."""
    lib = {e.name: e for e in library}
    out = []
    a = sig[0]
    ea = lib[a.name]
    ev = lanes.lanes[0]
    a_ho = ev.cv(spec.plus(ea, a.hyper), remember=True)[1].heldout  # the next step's starting model

    # each on top of the other (the added one's hyper-parameter searched again, nested), compared with the other
    # alone at its final hyper-parameter, as the forward selection does
    def on_top(lane: Evaluator, task: tuple[CandidateResult, bool]) -> tuple[np.ndarray, ...]:
        b, b_on_a = task
        eb = lib[b.name]
        if b_on_a:
            b_ho = lane.cv(spec.plus(eb, b.hyper))[1].heldout
            return b_ho, lane.fit_hyper(spec.plus(ea, a.hyper), eb, remember=True)[1]  # evaluated again next step
        return (lane.nested_heldout(spec.plus(eb, b.hyper), ea),)

    done = lanes.map(on_top, [(b, b_on_a) for b in sig[1:4] for b_on_a in (True, False)])
    for i, b in enumerate(sig[1:4]):
        (b_ho, ho_b_on_a), (ho_a_on_b,) = done[2 * i], done[2 * i + 1]
        rows = ev.rows.copy()
        for arr in (a_ho, b_ho, ho_b_on_a, ho_a_on_b):
            rows &= finite_rows(arr)
        g_b, p_b = paired_gain_test(a_ho, ho_b_on_a, ev.groups, rows, ev.weights, alpha_each)[:2]
        g_a, p_a = paired_gain_test(b_ho, ho_a_on_b, ev.groups, rows, ev.weights, alpha_each)[:2]
        r = rows & finite_rows(a.delta) & finite_rows(b.delta)
        cc = _corr((a.delta[r] * np.sqrt(ev.weights)).ravel(), (b.delta[r] * np.sqrt(ev.weights)).ravel())
        b_adds = p_b < alpha_each and g_b >= min_rel_gain
        a_adds = p_a < alpha_each and g_a >= min_rel_gain
        if a_adds and b_adds:
            verdict = "both"
        elif a_adds or b_adds:
            verdict = f"{a.name} explains {b.name}" if a_adds else f"{b.name} explains {a.name}"
        else:
            # neither adds beyond the other: does one fit significantly better head to head?
            g_ab, p_ab = paired_gain_test(b_ho, a_ho, ev.groups, rows, ev.weights, alpha_each)[:2]
            g_ba, p_ba = paired_gain_test(a_ho, b_ho, ev.groups, rows, ev.weights, alpha_each)[:2]
            if p_ab < alpha_each and g_ab >= min_rel_gain:
                verdict = f"{a.name} explains {b.name}"
            elif p_ba < alpha_each and g_ba >= min_rel_gain:
                verdict = f"{b.name} explains {a.name}"
            else:
                verdict = "confounded"
        out.append(Confounding(a.name, b.name, cc, p_b, p_a, verdict, g_b, g_a, separating_measurement(a.name, b.name)))
    return out


def _calibration_from(spec: ModelSpec, des: Design, cv: CvResult, data: DiagnosisData, noise: np.ndarray,
                      sensor_id: str, confounded: dict[str, list[str]] | None = None,
                      ) -> tuple[ThermalCalibration, ThermalCalibration, list[tuple[str, float | None, str]]]:
    n = spec.degree
    A = cv.A_full
    M, b = coefficients_to_model(A[: n_params(n)], n)
    t = data.temp_c[data.use]
    rng = (float(np.min(t)), float(np.max(t)))
    terms, added = [], []
    for eff, h in sorted(spec.effects, key=lambda eh: eh[0].stage):
        coeff = A[des.blocks[eff.name]].T if eff.name in des.blocks else None
        terms.extend(eff.make_terms(h, coeff, data))
        added.append((eff.name, h, eff.describe(h, coeff)))
    per_run = [e.name for e, _ in spec.effects if e.per_run]
    fit = {"tool": "fbg-accel-calib diagnose", "degree": n,
           "added_effects": [a[0] for a in added if a[0] not in per_run],
           "hyper_parameters": {a[0]: a[1] for a in added if a[0] not in per_run}}
    if per_run:  # fitted so that they do not bias eq. 28; the driver cannot apply them (it does not know runs)
        fit["per_run_terms_fitted_not_applied"] = per_run
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


def _visit_reference_range(data: DiagnosisData, groups: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(3, 2): lowest and highest visit-mean reference specific force (m/s^2) along each table axis over the visits of
    ``rows`` (the poses the calibration was fitted on; ``thermal_fit.reference_range`` takes cell means)."""
    g = visit_means(groups, rows & np.all(np.isfinite(data.gref), axis=1), data.gref)
    if not len(g):
        return np.full((3, 2), np.nan)
    return np.column_stack([g.min(axis=0), g.max(axis=0)])


APPLY_BLOCK = 1 << 17  # samples per call of apply_counts in _calibrated (bounds its temporaries)


def _calibrated(cal: ThermalCalibration, data: DiagnosisData) -> np.ndarray:
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


def _consistency(calibrated: np.ndarray, fitted: np.ndarray, rows: np.ndarray) -> float:
    """Max |calibration file's output - fit prediction| (both (N, 3)) over the static ``rows``."""
    return float(np.nanmax(np.abs(calibrated[rows] - fitted[rows]))) if rows.any() else 0.0


def _moving_residual(data: DiagnosisData, calibrated: np.ndarray) -> np.ndarray | None:
    """RMS (3,) of the calibration file's output ``calibrated`` (N, 3) minus the gap-filled reference on samples not
    used (moving, settling)."""
    m = ~data.use & finite_rows(data.gref_filled)
    if m.sum() < 3:
        return None
    d = calibrated[m] - data.gref_filled[m]
    d = d[finite_rows(d)]
    return np.sqrt(np.mean(d**2, axis=0)) if len(d) else None
