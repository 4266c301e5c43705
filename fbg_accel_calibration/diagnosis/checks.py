"""The checks a candidate declares beyond its held-out test (``Effect.checks``), by name, each with when it runs.

The forward selection (``diagnosis.selection``) asks each candidate for its checks and runs them; no check is tied to
an effect's name. A check that runs during the search takes the candidate's result (``CandidateResult``) and may
refuse it (``CandidateResult.refuse``: why as data); a check on the final model returns a :class:`Finding`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from ..fit.thermal_fit import NotIdentifiedError
from .cv import check_folds, cross_validate, make_folds
from .data import DiagnosisData, finite_rows
from .design import ModelSpec, build_design
from .effects import MODEL_TERM, Effect
from .findings import Finding
from .floor import VisitNoise
from .response_step import ResponseStepEffect
from .search import CandidateResult, Evaluator, Refusal, StepCheck, group_mse, paired_gain_test, reselect_degree
from .search_lanes import Lanes
from .structure import SLOW_ERROR_BOUND_MPS2, SMALL_RATIO, ResidualStructure, residual_structure, slow_wander

EACH_STEP = "each step"  # on every significant result of every step, in the order the effect declares them
WHEN_CHOSEN = "when chosen"  # on the best significant candidate, when it is about to be added
ON_FINAL_MODEL = "on the final model"  # on the residual of the final model, for an effect in it: a Finding


@dataclass
class SearchChecks:
    """What the checks during the search need: the data, the lanes the searches run on, the model the candidates are
    tried on top of and the step's level."""

    data: DiagnosisData
    lanes: Lanes[Evaluator]
    folds: int  # folds over visits (the contiguous blocks of time are as many)
    every: np.ndarray  # the samples searched (indices)
    weights: np.ndarray  # (3,) 1 / floor^2
    min_rel_gain: float
    reselect_up_to: int | None  # largest degree of eq. 28 chosen again beside a step; None: not chosen again
    reading_jumped: bool  # the temperature reading jumps and eq. 28 reads it
    spec: ModelSpec | None = None  # the current model (set at each step)
    alpha_each: float = 0.0  # the step's level per candidate (set at each step)
    step_confounded: dict[str, str] = field(default_factory=dict)  # a candidate that a step fits as well: why
    noise_model: VisitNoise | None = None  # the floor's noise (the slow wander is measured against it)
    _time_folds: np.ndarray | None = None  # contiguous blocks of time, made when first needed

    def time_folds(self) -> np.ndarray:
        if self._time_folds is None:
            d = self.data
            self._time_folds = check_folds(d, d.group, make_folds(d.group, d.use, self.folds, time_blocks=True))[0]
        return self._time_folds


def reading_jump(ctx: SearchChecks, r: CandidateResult, eff: Effect) -> None:
    """A jump of the temperature reading moves eq. 28's output once, which this candidate can follow: what it would
    write is the reading's fault, not the sensor's (test_a_fault_of_the_temperature_reading_...)."""
    if ctx.reading_jumped:
        r.refuse(Refusal.READING_JUMP, "the AHT10 reading jumps (a sensor re-seated, a spike, a frozen reading), and "
                 "eq. 28 evaluated at it moves the output once, which this candidate can follow")


def wander_gain(ctx: SearchChecks, r: CandidateResult, eff: Effect) -> None:
    """Does the candidate gain more than the sensor's slow bias wander left beside it? A function of time, of the
    temperature's history (tied to time on a cycled run) or of the reference counts (the source wanders in time)
    predicts a held-out visit from the visits around it in time, and so predicts part of the wander of the bias
    between visits (Table 2's bias instability: flicker-like, correlation times up to hours), which the floor (a mean
    and a line removed per visit) never sees: on the simulator's clean ramps such a term was added on 4 of 100
    campaigns (``bench/residual_false_alarm.py``). The wander's variance is measured on the revisits of a pose in the
    candidate model's held-out residual (``structure.slow_wander``; 0 without revisits): a term that explains an
    effect of time leaves the revisits agreeing to within the wander, one that follows the wander takes part of it and
    leaves the rest there. That rest is the sensor's wander up to its bound (``SLOW_ERROR_BOUND_MPS2``, as in the
    residual test's null): revisits that differ by more hold another effect still outside the model (two effects of
    time at once: a lag and dark offsets under a source drift), which no wander of the sensor is. Its gain on a
    held-out visit must be beyond that rest, s^2 per axis (at most the bound's square): the paired test over
    visits is of the per-visit gains less sum_j w_j s_j^2 (the search's weights), one-sided Wilcoxon signed-rank at
    the step's level. Refused (``significant`` False) when the gain is not beyond it."""
    ev = ctx.lanes.lanes[0]
    data = ev.data
    if ctx.noise_model is None:
        return
    ho1 = ev.cv(ctx.spec.plus(eff, r.hyper))[1].heldout
    full = np.full((len(data.t_s), 3), np.nan)
    full[ev.sub] = ho1
    rows = np.zeros(len(data.t_s), bool)
    rows[ev.sub] = ev.rows
    slow = slow_wander(data, full, rows, data.group, ctx.noise_model)
    shift = float(np.sum(np.minimum(slow.variance, SLOW_ERROR_BOUND_MPS2**2) * ev.weights)) if slow.revisits else 0.0
    if shift <= 0.0:
        return
    ho0 = ev.cv(ctx.spec)[1].heldout
    ok = ev.rows & finite_rows(ho0) & finite_rows(ho1)
    d = group_mse(ho0, ev.groups, ok, ev.weights)[1] - group_mse(ho1, ev.groups, ok, ev.weights)[1] - shift
    p = float(stats.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue) if len(d) >= 5 else 1.0
    if p < ctx.alpha_each:
        r.detail += f"; it gains beyond the slow wander of the bias its revisits keep (p = {p:.2g})"
    else:
        r.refuse(Refusal.SLOW_WANDER, f"its gain is not beyond the slow wander of the bias that the revisits of a "
                 f"pose keep with it in the model (that wander's variance taken off every visit's gain, p = {p:.2g}): "
                 "it may follow the sensor's bias instability, not an effect it can extrapolate")


def time_blocks(ctx: SearchChecks, r: CandidateResult, eff: Effect) -> None:
    """A function of time must also predict contiguous blocks of time held out (``time_block_check``)."""
    g, p = r.time_block = time_block_check(ctx.data, ctx.spec, eff, r.hyper, ctx.every, ctx.time_folds(), ctx.weights,
                                           ctx.alpha_each)
    if p < ctx.alpha_each and g >= ctx.min_rel_gain:
        r.detail += f"; it also predicts contiguous blocks of time held out (gain {100 * g:+.1f} %, p = {p:.2g})"
    else:
        r.refuse(Refusal.TIME_BLOCKS, f"it does not predict contiguous blocks of time held out (gain {100 * g:+.1f} "
                 f"%, p = {p:.2g}): it follows a slow wander of the residual between visits, not a drift it can "
                 "extrapolate")


def step(ctx: SearchChecks, r: CandidateResult, eff: Effect) -> None:
    """Set against the best step of the response at one time (``judge_step``)."""
    judge_step(ctx.lanes, ctx.spec, r, eff, ctx.alpha_each, ctx.min_rel_gain, ctx.reselect_up_to,
               ctx.step_confounded)


def table_angles(eff: Effect, structure: ResidualStructure, alpha: float) -> Finding | None:
    """An added function of the orientation with a residual left that is not one (visits of one direction disagree),
    and not small (the slow part of the noise, bias instability between visits minutes apart, makes a small one
    common)."""
    axes = [a for j, a in enumerate("xyz") if structure.pose_chi2_p[j] < alpha / 3
            and structure.other_pose_chi2_p[j] < alpha / 3 and structure.ratio[j] > SMALL_RATIO]
    if not axes:
        return None
    p = [structure.other_pose_chi2_p["xyz".index(a)] for a in axes]
    separates = "turn the sensor by 90 degrees on the table and compare"
    return Finding("table_angles", f"{eff.name} is a function of the orientation, but what remains on {'/'.join(axes)} "
                   "differs between the poses of one direction of gravity (p " + ", ".join(f"{v:.1e}" for v in p)
                   + "): on a plan whose directions and table angles go together it may stand in for an effect of the "
                   "table's angles (a cable the table drags, the table's geometry) that is no property of the sensor; "
                   + separates, effect=eff.name, numbers={"axes": axes, "p_other_poses": p}, separates=separates)


@dataclass(frozen=True)
class Check:
    when: str  # EACH_STEP, WHEN_CHOSEN or ON_FINAL_MODEL
    run: Callable  # (SearchChecks, CandidateResult, Effect) -> None; on the final model (Effect, structure, alpha)


CHECKS: dict[str, Check] = {
    "reading_jump": Check(EACH_STEP, reading_jump),
    "slow_wander": Check(EACH_STEP, wander_gain),
    "time_blocks": Check(EACH_STEP, time_blocks),
    "step": Check(EACH_STEP, step),
    "step_when_chosen": Check(WHEN_CHOSEN, step),
    "table_angles": Check(ON_FINAL_MODEL, table_angles),
}


def run_checks(when: str, ctx: SearchChecks, r: CandidateResult, eff: Effect) -> None:
    """The checks ``eff`` declares that run ``when``, in its order, while ``r`` is still significant."""
    for name in eff.checks:
        check = CHECKS[name]
        if check.when == when and r.significant:
            check.run(ctx, r, eff)


def final_model_findings(spec: ModelSpec, structure: ResidualStructure, alpha: float) -> list[Finding]:
    """The findings of the checks the effects of the final model declare on it."""
    out = []
    for eff, _ in spec.effects:
        for name in eff.checks:
            if CHECKS[name].when == ON_FINAL_MODEL and (f := CHECKS[name].run(eff, structure, alpha)) is not None:
                out.append(f)
    return out


# A residual whose visits of one direction of gravity still disagree at a p below this, on an axis whose held-out RMSE
# is above SMALL_RATIO x the floor, holds an effect that no term of the model represents. Set far from both sides of
# the simulator's campaigns (bench/diagnose_robustness.py): with each library effect named (alone or two together) and
# on clean data the slow noise outside the test's null (the bias instability between visits minutes apart) takes this
# p down to 7e-4 at the lowest, at 1.04x the floor at most; a cable the table drags or a motion-history hysteresis
# leave it at 9e-9 or below, at 1.15-1.5x the floor.
STAND_IN_LEVEL = 1e-6
TELLS_A_STAND_IN = ("visit each direction of gravity at other table angles and from both sides (the plan in shuffled "
                    "orders), and turn the sensor 90 degrees on the table and repeat: an effect of the sensor's "
                    "orientation turns with the sensor and gives one output per direction, a table's effect (a cable "
                    "it drags) stays with the table's angles, a motion-history hysteresis comes back with the side of "
                    "approach")


def stand_ins(lanes: Lanes[Evaluator], spec: ModelSpec, noise_model: VisitNoise,
              alpha: float) -> tuple[ModelSpec, list[Finding]]:
    """The terms of the selected model ``spec`` that cannot be claimed: a term claims that its physical effect explains
    the structure it removes, so the residual it leaves must not keep structure of the kind no term of the model has.
    When the held-out residual of ``spec`` (on the searched samples) still differs between the visits of one direction
    of gravity (``structure.other_pose_chi2_p`` below ``STAND_IN_LEVEL`` on an axis whose held-out RMSE is above
    ``SMALL_RATIO`` x the floor), the data hold an effect that is not a function of the sensor's orientation and that
    none of the added terms of time, temperature or the reference explains either: each model term (``MODEL_TERM``)
    may take part of it (a quadratic of Psi takes what a cable the table drags does over the directions, a warm-up or a
    dark offset what a motion-history hysteresis does over the pose order), so none is claimed. Returns the model
    without them and one Finding each; ``spec`` and [] when the residual keeps no such structure. Noise remedies,
    per-run and rig properties stay: they claim nothing about the sensor."""
    terms = [e for e, _ in spec.effects if e.role == MODEL_TERM]
    if not terms:
        return spec, []
    ev = lanes.lanes[0]
    data = ev.data
    heldout = np.full((len(data.t_s), 3), np.nan)
    heldout[ev.sub] = ev.cv(spec)[1].heldout
    rows = np.zeros(len(data.t_s), dtype=bool)
    rows[ev.sub] = ev.rows
    s = residual_structure(data, heldout, rows, data.group, noise_model, alpha)
    axes = [j for j in range(3) if s.other_pose_chi2_p[j] < STAND_IN_LEVEL and s.ratio[j] > SMALL_RATIO]
    if not axes:
        return spec, []
    where = ", ".join(f"{'xyz'[j]} (p {s.other_pose_chi2_p[j]:.1e}, held-out {s.ratio[j]:.2f}x the floor)" for j in axes)
    out = []
    for eff in terms:
        out.append(Finding(
            "stand_in", f"{eff.name} ({eff.title}) is not claimed: it would take part of the residual, but with it in "
            f"the model the visits of one direction of gravity still disagree on {where}, which no term of the model "
            f"represents and {eff.name} does not share: an effect outside the library (of the table's angles, of "
            "the pose history) that it would stand in for, so the residual is left unexplained; " + TELLS_A_STAND_IN,
            effect=eff.name, numbers={"axes": ["xyz"[j] for j in axes], "p_other_poses": s.other_pose_chi2_p,
                                      "ratio": s.ratio}, separates=TELLS_A_STAND_IN))
    kept = [(e, h) for e, h in spec.effects if e.role != MODEL_TERM]
    return ModelSpec(spec.degree, spec.t_center_c, spec.t_scale_c, kept), out


def time_block_check(data: DiagnosisData, spec: ModelSpec, eff: Effect, h: float | None, sub: np.ndarray,
                     folds: np.ndarray, weights: np.ndarray, alpha: float) -> tuple[float, float]:
    """(held-out gain, one-sided p over visits: ``paired_gain_test``) of ``eff`` at ``h`` on top of ``spec`` when the
    folds are contiguous blocks of time (``folds``: ``make_folds``' time blocks made identifiable by ``check_folds``), on
    the samples ``sub`` (indices; the search's). A function of time (``Effect.time_function``) that only gains
    between visits interleaved in time follows a slow wander of the residual, which it cannot extrapolate: the
    driver would apply it after every power-on. A model not identified on these folds has gain -inf, p 1."""
    f = folds[sub]
    fit, judged = data.use[sub] & (f != -1), data.use[sub] & (f >= 0)
    try:
        ho = [cross_validate(build_design(data, s, sub=sub), fit, f, weights).heldout for s in (spec, spec.plus(eff, h))]
    except NotIdentifiedError:
        return -math.inf, 1.0
    r = judged & finite_rows(ho[0]) & finite_rows(ho[1])
    gain, p = paired_gain_test(ho[0], ho[1], data.group[sub], r, weights, alpha)[:2]
    return gain, p


def step_check(lanes: Lanes[Evaluator], spec: ModelSpec, eff: Effect, h: float | None, alpha: float,
               min_rel_gain: float, max_degree: int | None = None) -> StepCheck | None:
    """Does a step of the response at one time explain what ``eff`` (at ``h``; ``Effect.follows_a_step``) fits on top
    of ``spec``? A warm-up with creep follows a step (a connector knocked mid-run) across contiguous blocks of time too,
    so ``time_block_check`` passes it; on a temperature-cycled run a hysteresis branch or a thermal lag follows it as
    well, since the temperature's history is tied to time; written to the calibration, the driver applies it for good.
    The step (its time found like any hyper-parameter, nested in the folds) and ``eff`` are each added on top of the
    other, as in the confounding check: if the step gains beyond ``eff`` (``alpha``, ``min_rel_gain``) and ``eff`` not
    beyond the step, ``eff`` is a stand-in. ``max_degree`` (None: the degree is forced, or one temperature level): eq.
    28's degree is first chosen again with both in the model (``reselect_degree``), as it is after any effect is added,
    and both are compared at it: a degree chosen with the step in the residual can be too low for the step's model, and
    the temperature dependence it leaves then passes for a drift or a hysteresis. None when the recording has too few
    visits for a step. The two candidates on top of each other run side by side on ``lanes``."""
    step = ResponseStepEffect()
    ev = lanes.lanes[0]
    if not step.applicable(ev.data)[0]:
        return None

    def on_top(lane: Evaluator, base_eff: tuple[ModelSpec, Effect]) -> CandidateResult:
        base, e = base_eff
        des, cvr = lane.cv(base)
        return lane.evaluate(base, e, cvr.heldout, cvr.fitted_full, des.G, alpha, min_rel_gain)

    def gains(r: CandidateResult) -> bool:
        return r.applicable and r.p_value < alpha and r.rel_gain >= min_rel_gain and not r.implausible

    try:
        # the step that fits best in place of the candidate, not beside it; kept: every candidate checked at this
        # step (a drift, a dark offset, a temperature history) is set against the same best step
        with lanes.lending():  # ev (the first lane) searches it, the other lanes work its trials out beside it
            h_step = ev.fit_hyper(spec, step, remember=True)[0]
        if max_degree is not None:
            degree = reselect_degree(lanes, spec.plus(eff, h).plus(step, h_step), max_degree)[0].degree
            # the step's time, set by the jump rather than by the temperature terms, is kept (a search of it is
            # most of the check's cost)
            spec = ModelSpec(degree, spec.t_center_c, spec.t_scale_c, spec.effects)
    except NotIdentifiedError:
        return None
    beyond_time, beyond_step = lanes.map(on_top, [(spec.plus(eff, h), step), (spec.plus(step, h_step), eff)])
    if not beyond_time.applicable:
        return None
    i = min(math.ceil(float(h_step)), len(ev.data.t_s) - 1)
    fitted = np.flatnonzero(ev.data.use[:i] & (ev.data.group[:i] >= 0))
    t_before = float(ev.data.t_s[fitted[-1]]) if fitted.size else math.nan
    return StepCheck(float(ev.data.t_s[i]), t_before, int(ev.data.run_id[i]), beyond_time.rel_gain, beyond_time.p_value,
                     beyond_step.rel_gain if beyond_step.applicable else -math.inf,
                     beyond_step.p_value if beyond_step.applicable else 1.0,
                     gains(beyond_time) and not gains(beyond_step), spec.degree)


def judge_step(lanes: Lanes[Evaluator], spec: ModelSpec, r: CandidateResult, eff_r: Effect, alpha_each: float,
               min_rel_gain: float, max_degree: int | None, step_confounded: dict[str, str]) -> None:
    """Set the significant candidate ``r`` (of ``eff_r``, ``Effect.follows_a_step``) on top of ``spec`` against the best
    step of the response (``step_check``; ``max_degree`` None: eq. 28's degree is not chosen again): refused (``r``
    no longer significant, ``Refusal.STEP``) if the step explains it; if the step fits as well, the warning for the
    report is put in ``step_confounded`` under its name."""
    sc = r.step_check = step_check(lanes, spec, eff_r, r.hyper, alpha_each, min_rel_gain, max_degree)
    at_degree = f", eq. 28 of degree {sc.degree}" if sc is not None and sc.degree != spec.degree else ""
    if sc is not None and sc.explained:
        r.refuse(Refusal.STEP, f"a step of the response {sc.when} explains "
                 f"it: the step gains {100 * sc.gain_step_beyond:+.1f} % beyond it (p = "
                 f"{sc.p_step_beyond:.2g}), it gains {100 * sc.gain_time_beyond:+.1f} % beyond the step "
                 f"(p = {sc.p_time_beyond:.2g}{at_degree}): the response changed once (a connector "
                 f"knocked or re-mated, a fibre bent, a knock), not {eff_r.sensor_property} the driver "
                 "could apply")
    elif sc is not None and sc.p_time_beyond < alpha_each and sc.gain_time_beyond >= min_rel_gain:
        r.detail += (f"; it gains {100 * sc.gain_time_beyond:+.1f} % beyond the best step of the response "
                     f"at one time ({sc.when}, p = {sc.p_time_beyond:.2g}{at_degree})")
    elif sc is not None:  # neither beyond the other: the data do not tell a step from this candidate
        r.detail += (f"; a step of the response {sc.when} fits as well: it "
                     f"gains {100 * sc.gain_time_beyond:+.1f} % beyond the step (p = {sc.p_time_beyond:.2g}), "
                     f"the step {100 * sc.gain_step_beyond:+.1f} % beyond it (p = {sc.p_step_beyond:.2g}"
                     f"{at_degree})")
        step_confounded[r.name] = (f"{r.name} is in the calibration, but a step of the response {sc.when} (a "
                                   "connector, a fibre, a knock) fits this "
                                   "data as well, and a step is no property of the sensor: "
                                   f"{eff_r.tells_it_from_a_step}")
