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
3. Every candidate of ``diagnosis.library.LIBRARY`` on top of the current model: hyper-parameter by a 1-D
   search (grid; nested inside each training fold for the held-out figures, then refined on all
   data for the final value); held-out residuals by K-fold cross-validation over visits;
   per-visit paired gain in noise-weighted held-out MSE; one-sided Wilcoxon signed-rank test over
   visits (Bonferroni over the candidates of the step); correlation of the candidate's
   contribution with the held-out residual; pairwise confounding among the significant ones (each
   added on top of the other: does it still gain?).
4. Forward selection: add the best significant candidate, then take out again an effect added before it that no
   longer gains on top of the others (``selection.drop_explained``), repeat; stop when no candidate is
   significant or gains less than ``min_rel_gain`` of the held-out MSE (so nothing is added when
   nothing is significant). When the selected model's residual still differs between visits of one direction of
   gravity far beyond the noise, its terms are not claimed: they would stand in for an effect outside the library
   (``checks.stand_ins``), and the report says "unexplained". Above ``SEARCH_ROWS`` fitted samples, steps 3-4 run
   on every k-th fitted sample (the same visits and folds; ``search_samples``: k no larger than keeps ``MIN_SEARCH_INFORMATION``
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
from typing import Any

import numpy as np

from fbg_accel_driver.thermal_model import ThermalCalibration

from ..fit.adc_codes import HeldCode
from ..io.recording import Recording, time_axis_label
from .approach import approach_findings, approach_signature
from .blas_threads import single_blas_thread
from .checks import final_model_findings
from .cv import cross_validate
from .data import DiagnosisData
from .design import build_design, prepare_data
from .effects import Effect
from .final_model import fit_final
from .findings import (
    Finding,
    cannot_reveal,
    disturbance_finding,
    held_code_findings,
    model_findings,
    recording_findings,
)
from .floor import SettlingTransient, measure_floor
from .heap_policy import return_free_memory
from .library import LIBRARY
from .periodic_disturbance import PeriodicDisturbance
from .search import LANE_SEARCH_ROWS, SEARCH_ROWS, CandidateResult, check_search_rows
from .search_lanes import default_lane_count
from .selection import Rules, StepResult, declared_model, delay_cross_check, forward_selection
from .structure import ResidualStructure


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
    findings: list[Finding] = field(default_factory=list)  # results a reader must not take at face value
    condition_number: float = float("nan")  # of the final model's scaled normal matrix (gram_conditioning)
    column_correlation: dict[str, float] = field(default_factory=dict)  # added effect -> max |corr| with the others
    final_degree: int = -1  # degree of eq. 28 in the final model (re-selected after each added effect)
    run_terms: list[tuple[str, float | None, str]] = field(default_factory=list)  # per-run terms (not in the YAML)
    rig_terms: list[tuple[str, float | None, str]] = field(default_factory=list)  # the rig's (not in the YAML)
    held_codes: list[HeldCode] = field(default_factory=list)  # ADC codes that held whole visits (adc_codes)
    # a periodic disturbance found in the visits (periodic_disturbance): when found, the floors above are without it
    disturbance: PeriodicDisturbance = field(default_factory=lambda: PeriodicDisturbance([], (math.nan, math.nan), 0,
                                                                                          0.0, math.inf))

    @property
    def final_floor(self) -> np.ndarray:
        """The floor the final held-out error is judged against (m/s^2, x/y/z)."""
        return self.noise_floor if self.noise_floor_after is None else self.noise_floor_after

    @property
    def warnings(self) -> list[str]:
        """The sentences of the findings, in the report's order, but those of what the campaign cannot reveal
        (``cannot_reveal``: no warning about this data, a limit of its design)."""
        return [f.text for f in self.findings if f.kind != "cannot_reveal"]

    @property
    def ranked(self) -> list[CandidateResult]:
        return self.steps[0].candidates if self.steps else []


@single_blas_thread
def diagnose(rec: Recording | DiagnosisData, *, static: str = "table", max_degree: int = 4, folds: int = 10,
             alpha: float = 0.01, min_rel_gain: float = 0.02, max_effects: int = 3, library: tuple[Effect, ...] = LIBRARY,
             degree: int | None = None, sensor_id: str = "unknown", seed: int = 0,
             progress: Callable[[str], None] | None = None, settle_s: float | None = None,
             search_rows: int | None = SEARCH_ROWS, lanes: int | None = None,
             refine_every_candidate: bool = False, walk_from_last_step: bool = True) -> DiagnosisResult:
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
    (``heap_policy.set_process_heap_policy``: the command line sets it; the results do not depend on it).
    ``refine_every_candidate``: every candidate's hyper-parameter refined between its grid neighbours, not only those
    of the candidates that pass their step's test (``Evaluator.evaluate``; the others then report their grid's best
    value: nothing the diagnosis decides or fits depends on it, ``bench/refinement_check.py``).
    ``walk_from_last_step``: a candidate's searches after the first step walk its grid from where its search of the
    step before ended, not from every 4th value (the same values wherever each fold's training RSS has one minimum
    over the grid; ``bench/walk_start_check.py`` compares the two).

    The algorithm: measure the floor; forward selection over the candidates by nested cross-validation over visits,
    with the checks each candidate declares; the final model on every sample; findings; the result the report
    renders. It runs with one BLAS thread (``blas_threads``): its products of tall, narrow matrices gain nothing from more,
    and lose much when another process holds a core."""
    check_search_rows(search_rows)  # before seconds of work at 10^6 samples, not after
    # a large recording's searches run side by side: until they start, the other core takes what it can
    side_by_side = (default_lane_count() > 1 and len(rec.t_s) >= LANE_SEARCH_ROWS) if lanes is None else int(lanes) > 1
    data = rec if isinstance(rec, DiagnosisData) else prepare_data(rec, static, beside_thread=side_by_side)
    n_levels = data.temperature_level_count()
    # 1. the declared model (eq. 28, degree by held-out CV over visits) and its floor: the scatter within visits
    spec, degree_table, fold, fold_notes = declared_model(data, library, max_degree, degree, folds, seed, side_by_side)
    des0 = build_design(data, spec)
    cv0 = cross_validate(des0, data.use, fold, np.ones(3))
    res0 = des0.G - cv0.fitted_full
    # neither the declared model's design (N x p, 92 MiB at 10^6 samples) nor its fit nor its held-out residual
    # (N x 3 each) is held through the floor and the searches: they are worked out again after them from the design
    # built anew. The first step's channel delay cross-check of the fit is worked out now, once the design is let go
    # (beside the floor its arrays would add to the floor's)
    floor_rows = data.use & des0.valid & (data.pose_id >= 0)
    fitted0 = cv0.fitted_full
    cv0.let_go()
    del des0
    first_delay_check = delay_cross_check(data, library, lambda: fitted0, thread=False)
    fitted0 = None
    floor = measure_floor(data, res0, floor_rows, settle_s, side_by_side)
    del res0, floor_rows
    # 2. forward selection over the candidates by nested cross-validation over visits, with their checks
    rules = Rules(alpha, min_rel_gain, max_effects, max_degree, degree is None and n_levels >= 2, folds)
    sel = forward_selection(data, spec, fold, floor, library, rules, search_rows, lanes, first_delay_check, progress,
                            refine_every_candidate, walk_from_last_step)
    data.drop_recent()
    return_free_memory()  # the searches' free pages, before the final phase's designs of every sample (N x p) are mapped
    des0 = build_design(data, spec)  # the same matrix, bit for bit
    cv0 = cv0.on(des0)  # lets go of the design once both are worked out
    residual_before, fit_before = cv0.heldout, (des0.G, cv0.fitted_full)  # (the reference: a view of the recording's)
    del des0  # before the final design (N x p) is built
    # 3. the final model on every sample, judged against the floor
    code_rule = (sel.steps[0].alpha_each if sel.steps else alpha, min_rel_gain)
    final = fit_final(data, sel.spec, fold, floor, sensor_id, sel.confounded(), residual_before, fit_before, alpha,
                      code_rule, thread=sel.n_lanes > 1)
    code = final.code_step  # its row in the step table, after the library's steps
    sel.steps.append(StepResult(len(sel.steps) + 1, sel.spec.names, [code.result],
                                code.result.name if code.added else None, code.alpha_each, []))
    # 4. findings: what the reader must not take at face value, in the report's order
    findings = [sel.detection_limit] if sel.detection_limit else []
    findings += cannot_reveal(sel.steps[0].candidates if sel.steps else [], {e.name: e.title for e in library})
    findings += [Finding("step_confounded", why, effect=e.name, separates=e.tells_it_from_a_step)
                 for e, _ in sel.spec.effects if (why := sel.step_confounded.get(e.name))]
    findings += sel.stand_ins + sel.beyond_bound + final_model_findings(sel.spec, final.structure, alpha)
    findings += approach_findings(approach_signature(data, final.heldout, final.r_eval), alpha, sel.spec.names)
    findings += [final.flagged] if final.flagged else []
    if floor.disturbance.found:
        findings.append(disturbance_finding(data, floor.disturbance, final.heldout, floor.settled & final.r_eval,
                                            final.r_eval, floor.noise, final.after_ho))
    held, held_found = held_code_findings(data, final.heldout, data.group, floor.settled, final.r_eval,
                                          final.noise_after, alpha)
    findings += held_found
    findings += recording_findings(data, floor.settling.end_summary() if floor.settling.end_detected else "",
                                   data.group, final.r_eval, n_levels)
    findings += model_findings(final.column_correlation, final.after_ho, final.noise_after)
    consistency, moving = final.consistency_and_moving(data)
    # 5. the result the report renders
    return DiagnosisResult(
        data=data, degree=spec.degree, degree_table=degree_table, n_levels=n_levels, noise_floor=floor.noise,
        before_heldout_rmse=final.before_ho, before_insample_rmse=final.before_in, after_heldout_rmse=final.after_ho,
        after_insample_rmse=final.after_in, steps=sel.steps, added=final.added, calibration=final.cal,
        base_calibration=final.base_cal, residual_before=residual_before, residual_after=final.heldout,
        structure=final.structure, consistency_max_abs_mps2=consistency, n_static=final.n_static,
        n_groups=len(np.unique(data.group[final.r_eval])), moving_residual_rms=moving, settling=floor.settling,
        fold_notes=fold_notes, n_floor_samples=int(floor.settled.sum()), noise_remedies=final.remedies,
        noise_floor_after=final.noise_after if final.remedies else None, findings=findings,
        condition_number=final.condition_number, column_correlation=final.column_correlation,
        final_degree=sel.spec.degree, run_terms=final.run_terms, rig_terms=final.rig_terms, held_codes=held,
        disturbance=floor.disturbance,
        settings={"static": static if not isinstance(rec, DiagnosisData) else "given", "folds": int(fold.max()) + 1,
                  "alpha": alpha, "min_rel_gain": min_rel_gain, "max_effects": max_effects, "seed": seed,
                  "search_rows": sel.n_search, "search_step": sel.step, "search_information": sel.kept,
                  "degree_forced": degree is not None, "settle_s": floor.settle_s,
                  "time_label": _time_label(rec)})


def _time_label(rec: Recording | DiagnosisData) -> str:
    """The label of the report's time axis: the recording's, from its first sample (``residual_structure``)."""
    label = time_axis_label(rec.metadata) if isinstance(rec, Recording) else "time [s]"
    return "time from the first sample [s]" if label == "time [s]" else label
