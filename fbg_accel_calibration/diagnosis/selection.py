"""Forward selection over the candidate effects by nested cross-validation over visits (the diagnosis' search).

``declared_model``: eq. 28 at the degree cross-validation over visits chooses, and the folds. ``forward_selection``:
every candidate on top of the current model (``search.Evaluator``: hyper-parameter nested in each training fold,
held-out gain per visit, one-sided test over visits, Bonferroni over the candidates the data can show), the checks
each candidate declares (``checks``), confounding among the significant ones; the best is added, eq. 28's degree
chosen again, and an effect added earlier that no longer gains on top of the others taken out again
(``drop_explained``), until none is significant or gains less than ``min_rel_gain``. A candidate that gains but is
refused or fails a check at the model's degree is judged again at the higher degree chosen with it in
(``judged_at_its_degree``); a term let in while its bound was not decided must be within it in the selected model
(``beyond_bound_at_the_end``). A model whose residual still
keeps a structure no term of it represents claims none of its terms (``checks.stand_ins``: they would stand in for an
effect outside the library). The searches run on ``Lanes`` (its
``map`` is the one seam of the parallel execution: serial with one lane, the same results with any number).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np

from ..fit.thermal_fit import NotIdentifiedError, temperature_scaling
from . import checks
from .cv import check_folds, make_folds
from .data import DiagnosisData, finite_rows
from .design import ModelSpec, fitted_output
from .effects import Effect
from .findings import Finding
from .floor import FloorMeasurement
from .library import separating_measurement
from .search import (
    LANE_SEARCH_ROWS,
    CandidateResult,
    Evaluator,
    Refusal,
    _corr,
    _evaluate_on,
    cross_correlation_delay,
    paired_gain_test,
    reselect_degree,
    sample_changes,
    search_samples,
    select_degree,
)
from .search_lanes import Lanes, beside, default_lane_count

# the corrected references a thinned search keeps (``DesignCache``, shared by its lanes; 1.2 MiB each at
# ``SEARCH_ROWS``, small beside the correction of the whole series each saves; an unthinned search keeps 4): a step's
# searches, its confounding check and the next step ask again for the grids of the reference's corrections on top of
# one model (the channel delay's on the TIA's, the TIA's again when an earlier effect is refitted), up to some 80 trials
# apart at 10^6 samples. With one lane 48 keep most of them; with more, the lanes' own caches take that room under the
# 600 MiB the diagnosis of 10^6 samples is held to (``bench/floors.py``: docs/diagnose_speed.md)
REFERENCES_KEPT_ONE_LANE, REFERENCES_KEPT = 48, 24


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
    removed_note: str = ""  # an effect added earlier taken out again after ``chosen`` was added (``drop_explained``)


@dataclass
class Rules:
    """The selection's rules: family-wise level per step, least held-out gain, most effects added, largest degree of
    eq. 28 and whether it is chosen again after each added effect, folds over visits."""

    alpha: float
    min_rel_gain: float
    max_effects: int
    max_degree: int
    reselect_degree: bool
    folds: int


@dataclass
class Selection:
    """What the forward selection found: the final model, its steps, what the design cannot show (a Finding or
    None), the candidates a step of the response fits as well (name -> why), how far the search was thinned and the
    terms taken out again as stand-ins for an effect outside the library."""

    spec: ModelSpec
    steps: list[StepResult]
    detection_limit: Finding | None
    step_confounded: dict[str, str]
    n_search: int | None  # samples searched when thinned, else None
    step: int  # every step-th fitted sample searched
    kept: float  # information of a visit mean the thinned search keeps
    n_lanes: int  # searches that ran side by side
    stand_ins: list[Finding] = field(default_factory=list)  # terms not claimed: stand-ins (``checks.stand_ins``)
    beyond_bound: list[Finding] = field(default_factory=list)  # terms not claimed (``beyond_bound_at_the_end``)

    def confounded(self) -> dict[str, list[str]]:
        """Added effect -> the candidates it was confounded with when added (only those with any)."""
        out = {st.chosen: [c.b if c.a == st.chosen else c.a for c in st.confounding
                           if c.verdict == "confounded" and st.chosen in (c.a, c.b)] for st in self.steps
               if st.chosen in self.spec.names}  # not one taken out again (drop_explained)
        return {k: v for k, v in out.items() if v}


def declared_model(data: DiagnosisData, library: tuple[Effect, ...], max_degree: int, degree: int | None, folds: int,
                   seed: int, side_by_side: bool) -> tuple[ModelSpec, list[dict[str, Any]], np.ndarray, list[str]]:
    """Eq. 28 at the degree held-out cross-validation over visits chooses (or ``degree``), its degree table, the folds
    over visits and their notes (``check_folds``). With ``side_by_side`` the folds, and the constants of the recording
    the first searches ask for (``DiagnosisData.once``), are worked out on a thread beside the degree selection."""
    def folds_and_constants() -> tuple[np.ndarray, list[str]]:
        out = check_folds(data, data.group, make_folds(data.group, data.use, folds, seed))
        if side_by_side:
            for e in library:
                e.applicable(data)
            data.static_psi_map()
            data.run_steps()
        return out

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
    return ModelSpec(sel_degree, c, s), degree_table, fold, fold_notes


def _detection_limit(tested: list[CandidateResult], alpha: float, alpha_each: float) -> Finding | None:
    """When the campaign has too few visits for the signed-rank test to reach the level each candidate needs."""
    n_vis = max((r.n_groups for r in tested), default=0)
    if not tested or 0.5 ** n_vis < alpha_each:
        return None
    detectable = [r.detectable_gain for r in tested if np.isfinite(r.detectable_gain)]
    need = math.ceil(-math.log2(alpha_each)) + 1
    return Finding("detection_limit", f"this campaign has {n_vis} visits: the one-sided signed-rank test over visits "
                   f"cannot go below p = 2^-{n_vis} = {0.5 ** n_vis:.2g}, above the {alpha_each:.2g} each candidate "
                   f"needs (alpha {alpha:g} over {len(tested)} candidates); at least {need} visits are needed for it "
                   "(repeat the poses, or visit more orientations). "
                   + (f"Candidates are tested with a one-sided paired t-test over the visits instead (df "
                      f"{n_vis - 1}; it assumes normally distributed per-visit differences): with the "
                      f"scatter of these visits the smallest held-out gain it detects with 80 % power is "
                      f"{100 * min(detectable):.3g} % (median over the candidates "
                      f"{100 * float(np.median(detectable)):.3g} %)" if detectable else
                      "Too few visits for a paired t-test as well: no effect can be added whatever its size"),
                   numbers={"visits": n_vis, "visits_needed": need, "alpha_each": alpha_each},
                   separates="repeat the poses, or visit more orientations")


def delay_cross_check(data: DiagnosisData, candidates: list[Effect] | tuple[Effect, ...],
                      output: Callable[[], np.ndarray], thread: bool) -> Future[float] | None:
    """The channel delay's cross-check of a model (``cross_correlation_delay``) whose output on every sample (N, 3)
    m/s^2 ``output()`` gives, on a thread of its own beside the caller's work (``thread``) or now; the output's
    changes are what the check holds, not the output. None when the channel delay is not among the ``candidates``
    the data can show."""
    if not any(e.name == "channel_delay" and e.applicable(data)[0] for e in candidates):
        return None
    return beside(cross_correlation_delay, data, sample_changes(data, output()), thread=thread)


def forward_selection(data: DiagnosisData, spec: ModelSpec, fold: np.ndarray, floor: FloorMeasurement,
                      library: tuple[Effect, ...], rules: Rules, search_rows: int | None, lanes: int | None,
                      first_delay_check: Future[float] | None, progress: Callable[[str], None] | None,
                      refine_every_candidate: bool = False, walk_from_last_step: bool = True) -> Selection:
    """Add the best significant candidate on top of ``spec`` and repeat (see the module docstring).
    ``first_delay_check``: the channel delay's cross-check of ``spec`` (``delay_cross_check`` of the declared model's
    in-sample fit on every sample), None when the channel delay is not a candidate. Above
    ``search_rows`` fitted samples the candidates are evaluated on every k-th one (``search_samples``); ``lanes``:
    searches side by side (None: ``default_lane_count()`` from ``LANE_SEARCH_ROWS`` searched samples on);
    ``refine_every_candidate``: ``Evaluator.refine_every``. ``walk_from_last_step``: a candidate's searches after the
    first step start their walk over the grid where its search of the step before ended (``Evaluator.walk_starts``);
    False: every search starts from every 4th grid value."""
    groups, weights = data.group, 1.0 / np.maximum(floor.noise, 1e-12) ** 2
    fit_rows = data.use & (fold != -1)  # fitted (also the visits never held out, fold -2)
    # a search thinned to fewer rows keeps most of what a visit's samples tell of its mean (the noise is correlated)
    per_visit = np.bincount(groups[fit_rows & (groups >= 0)], minlength=1)
    per_visit = per_visit[per_visit > 0]
    every, step, kept = search_samples(fit_rows, fold, search_rows, floor.noise_model,
                                       float(np.median(per_visit)) if per_visit.size else math.inf)
    n_lanes = (default_lane_count() if len(every) >= LANE_SEARCH_ROWS else 1) if lanes is None else int(lanes)
    references = (REFERENCES_KEPT_ONE_LANE if n_lanes == 1 else REFERENCES_KEPT) if step > 1 else 4
    sel = Evaluator(data, fold, weights, groups, every, references=references, refine_every=refine_every_candidate)
    searchers = Lanes([sel] + [sel.lane() for _ in range(n_lanes - 1)])
    des_s, cv_s = sel.cv(spec)
    base = (cv_s.heldout, cv_s.fitted_full, des_s.G)
    del des_s, cv_s
    base_coefficients: np.ndarray | None = None  # the current model's coefficients (after the first step)
    n_levels = data.temperature_level_count()
    ctx = checks.SearchChecks(data, searchers, rules.folds, every, weights, rules.min_rel_gain,
                              rules.max_degree if rules.reselect_degree else None,
                              bool(data.temperature_jumps) and n_levels >= 2, noise_model=floor.noise_model)
    steps: list[StepResult] = []
    detection_limit = None
    remaining = list(library)
    seconds: dict[str, float] = {}  # what each candidate's evaluation took (the order they start in: Lanes.map)
    while remaining and len(spec.effects) < rules.max_effects:
        # Bonferroni over the candidates the data can show at all (known before any is evaluated)
        ctx.spec, ctx.alpha_each = spec, rules.alpha / max(sum(e.applicable(data)[0] for e in remaining), 1)
        # the channel delay's cross-check, of the current model alone, beside the searches
        xcorr_later = first_delay_check if not steps else delay_cross_check(
            data, remaining, lambda model=spec, coeff=base_coefficients: fitted_output(data, model, coeff), n_lanes > 1)
        # the candidates side by side, the longest first (what each took at the step before)
        results = searchers.map(partial(_evaluate_on, spec, *base, ctx.alpha_each, rules.min_rel_gain, seconds), remaining,
                                None if progress is None else lambda r: progress(r.name),
                                cost=lambda e, model=spec: 0.0 if sel.remembers(model, e) else seconds.get(e.name, 0.0))
        if walk_from_last_step:  # each candidate's next searches start where this one ended (the lanes share them)
            sel.walk_starts.update({r.name: r.walked_to for r in results if r.walked_to})
        if xcorr_later is not None:
            for r in results:
                if r.name == "channel_delay" and r.applicable:
                    r.cross_correlation_delay_s = xcorr_later.result()
        tested = [r for r in results if r.applicable]
        if not steps:
            detection_limit = _detection_limit(tested, rules.alpha, ctx.alpha_each)
        effect_of = {e.name: e for e in remaining}
        up_to = rules.max_degree if rules.reselect_degree else None
        for r in tested:
            ctx.step_confounded.pop(r.name, None)  # the last step's word on it
            _judge(ctx, spec, r, effect_of[r.name])
        # one that gains but is refused or fails a check at the model's degree: judged at the degree chosen with it in
        retry = [r for r in tested if not r.significant and _gains(ctx, r)] if up_to is not None else []
        for r, again in zip(retry, searchers.map(partial(judged_at_its_degree, spec, ctx.alpha_each, ctx.min_rel_gain, up_to),
                                                 [(r, effect_of[r.name]) for r in retry]), strict=True):
            if again is not None:
                _in_place_of(results, r, again)
                _judge(ctx, spec, again, effect_of[r.name])
        results.sort(key=lambda r: (not r.applicable, -r.rel_gain))
        # the checks of a candidate about to be added (the best significant one left), not of every significant one
        checked: set[tuple[str, int | None]] = set()
        while ((best := next((r for r in results if r.significant), None)) is not None
               and (best.name, best.degree) not in checked):
            checked.add((best.name, best.degree))
            ctx.spec = at_its_degree(spec, best)
            checks.run_checks(checks.WHEN_CHOSEN, ctx, best, effect_of[best.name])
            if not best.significant and up_to is not None and best.degree is None:
                again = judged_at_its_degree(spec, ctx.alpha_each, ctx.min_rel_gain, up_to, sel,
                                             (best, effect_of[best.name]))
                if again is not None:
                    _in_place_of(results, best, again)
                    _judge(ctx, spec, again, effect_of[best.name])
                    results.sort(key=lambda r: (not r.applicable, -r.rel_gain))
        sig = [r for r in results if r.significant]
        conf = confounding(searchers, spec, sig, ctx.alpha_each, rules.min_rel_gain, library) if len(sig) >= 2 else []
        chosen = sig[0].name if sig else None
        for r in results:  # per-sample arrays (N, 3) are kept only where the report plots them: first step's deltas
            r.delta, r.delta_rows = (None, None) if steps else (r.delta, sel.sub)
        steps.append(StepResult(len(steps) + 1, spec.names, results, chosen, ctx.alpha_each, conf))
        if chosen is None:
            break
        was = spec.degree
        spec = at_its_degree(spec, sig[0]).plus(effect_of[chosen], sig[0].hyper)
        remaining = [e for e in remaining if e.name != chosen]
        if rules.reselect_degree:  # with one level only degree 0 is identified: nothing to re-select
            spec, steps[-1].degree_table, notes = reselect_degree(searchers, spec, rules.max_degree)
            steps[-1].degree_after = spec.degree
            steps[-1].degree_note = (f"degree of eq. 28 re-selected with {chosen} in the model: "
                                     + (f"{was} -> {spec.degree}" if spec.degree != was else f"{was}, unchanged")
                                     + "".join(f"; {n}" for n in notes))
        if len(spec.effects) >= 2:  # the terms added before it searched again beside it (and eq. 28's degree)
            spec, refit_note = refit_earlier(searchers, spec, rules.max_degree if rules.reselect_degree else None)
            steps[-1].degree_note += refit_note
        if len(spec.effects) >= 2:  # a term added earlier that those after it explain is taken out again
            spec, steps[-1].removed_note = drop_explained(searchers, spec, chosen, ctx.alpha_each, rules.min_rel_gain)
            if steps[-1].removed_note and rules.reselect_degree:
                was = spec.degree
                spec, _, notes = reselect_degree(searchers, spec, rules.max_degree)
                steps[-1].removed_note += (f"; degree of eq. 28 re-selected without it: {was} -> {spec.degree}"
                                           if spec.degree != was else "") + "".join(f"; {n}" for n in notes)
        des_c, cv_c = sel.cv(spec)
        searchers.each(lambda ev, model=spec: ev.forget(model))
        base, base_coefficients = (cv_c.heldout, cv_c.fitted_full, des_c.G), cv_c.A_full
        del des_c, cv_c  # the design (n x p) is not held beyond the evaluator's own caches
    # a term whose residual keeps structure no term has is a stand-in for an effect outside the library: not claimed
    spec, refused = checks.stand_ins(searchers, spec, floor.noise_model, rules.alpha)
    spec = _not_claimed(searchers, spec, refused, rules, steps, "the residual keeps a structure no term represents "
                        "(stand-ins for an effect outside the library); degree of eq. 28 without them")
    # a term let in while its bound was not decided must be within it in the selected model
    spec, beyond = beyond_bound_at_the_end(sel, spec)
    spec = _not_claimed(searchers, spec, beyond, rules, steps,
                        "beyond its bound in the selected model; degree of eq. 28 without it")
    n_search = len(sel.folds) if step > 1 else None
    return Selection(spec, steps, detection_limit, ctx.step_confounded, n_search, step, kept, n_lanes, refused, beyond)


def _not_claimed(lanes: Lanes[Evaluator], spec: ModelSpec, left_out: list[Finding], rules: Rules, steps: list[StepResult],
                 why: str) -> ModelSpec:
    """``spec`` (the terms of ``left_out`` already taken out) with eq. 28's degree chosen again when the rules
    re-select it, the last of ``steps``' note saying which terms are not claimed, ``why``, and the degree."""
    if not left_out:
        return spec
    if rules.reselect_degree:
        spec = reselect_degree(lanes, spec, rules.max_degree)[0]
    step = steps[-1]  # there is one: a term left out was added at a step
    step.removed_note += ("; " if step.removed_note else "") + (
        f"{', '.join(f.effect for f in left_out)} not claimed: {why} {spec.degree}")
    return spec


def beyond_bound_at_the_end(ev: Evaluator, spec: ModelSpec) -> tuple[ModelSpec, list[Finding]]:
    """The selected model ``spec`` without the terms whose bound is judged with the fit's uncertainty
    (``Effect.bound_ratios``) and that are beyond it on the fit in ``spec`` (on the search's samples), and a Finding
    each. Such a term may have entered while its bound was not decided (beyond it by less than its uncertainty,
    ``Effect.refusal``: beside an effect not yet in the model, the dark offsets' implied x offset was 103 % of its
    bound, and 3 % of the counts once the lag was in); in the model that explains the rest its value must be within
    the bound, or it is not claimed: the data never showed it physical."""
    des, cvr = ev.cv(spec)
    kept, out = [], []
    for eff, h in spec.effects:
        coeff, folds = ev.coefficients(eff, des, cvr)
        bounded = coeff is not None and eff.bound_ratios(h, coeff, ev.data, ev.model_matrix) is not None
        why = eff.implausible(h, coeff, ev.data, ev.model_matrix) if bounded else ""
        if not why:
            kept.append((eff, h))
            continue
        undecided = eff.at_bound(h, coeff, ev.data, ev.model_matrix, folds)
        out.append(Finding("at_bound", f"{eff.name} ({eff.title}) is not claimed: in the selected model {why}"
                           + (f"; {undecided}" if undecided else "") + f"; {eff.measures_its_value}",
                           effect=eff.name, separates=eff.measures_its_value))
    return ModelSpec(spec.degree, spec.t_center_c, spec.t_scale_c, kept), out


def _gains(ctx: checks.SearchChecks, r: CandidateResult) -> bool:
    """``r`` passes the step's test and least gain."""
    return r.p_value < ctx.alpha_each and r.rel_gain >= ctx.min_rel_gain


def _judge(ctx: checks.SearchChecks, spec: ModelSpec, r: CandidateResult, eff: Effect) -> None:
    """Whether ``r`` (of ``eff`` on top of ``spec``) is significant: its test and bound, then the checks ``eff``
    declares for every step, on the model it was judged on."""
    r.significant = _gains(ctx, r) and not r.implausible
    if r.significant and eff.void(r.hyper):  # there is nothing to add
        r.refuse(Refusal.VOID, "its value on all samples changes nothing")
    ctx.spec = at_its_degree(spec, r)
    checks.run_checks(checks.EACH_STEP, ctx, r, eff)


def _in_place_of(results: list[CandidateResult], r: CandidateResult, again: CandidateResult) -> None:
    results[next(i for i, x in enumerate(results) if x is r)] = again


def at_its_degree(spec: ModelSpec, r: CandidateResult) -> ModelSpec:
    """``spec`` at eq. 28's degree the candidate ``r`` was judged at (``judged_at_its_degree``)."""
    return spec if r.degree is None else ModelSpec(r.degree, spec.t_center_c, spec.t_scale_c, spec.effects)


def judged_at_its_degree(spec: ModelSpec, alpha: float, min_rel_gain: float, max_degree: int, ev: Evaluator,
                         item: tuple[CandidateResult, Effect]) -> CandidateResult | None:
    """The candidate ``item`` (its result on top of ``spec`` and its effect), refused or failing a check at the
    model's degree although it gains, judged again at eq. 28's degree chosen with it in the model (``reselect_degree``,
    the rule used once an effect is added): its hyper-parameter searched again, its gain, test and bound
    (``Evaluator.evaluate``) on top of the model at that degree (``CandidateResult.degree``); the caller runs its checks
    there. None when that degree is not above the model's. The model's degree was chosen with what the candidate
    explains still in the residual, and an effect missing from the model makes a higher degree overfit: on 15 -> 45 ->
    15 degC ramps with a thermal lag and dark offsets under a source drift eq. 28 comes out of degree 1 where the
    sensor needs 2. Not below: at a lower degree the candidate is judged on a model with less of eq. 28's temperature
    dependence, which a function of time or of the temperature's history on ramps can take (a time drift that fails
    the contiguous blocks of time at degree 2 passed them at degree 1, and on another seed, judged there, it was added
    first and a wrong lag followed). A candidate that passes at the model's degree is judged there: at another degree
    its gain is over another model, and the candidates of a step are ranked by their gains. A task of ``Lanes.map``
    once the arguments before ``ev`` are bound."""
    first, eff = item
    try:
        degree = reselect_degree(Lanes([ev]), spec.plus(eff, first.hyper), max_degree)[0].degree
        if degree <= spec.degree:
            return None
        at = ModelSpec(degree, spec.t_center_c, spec.t_scale_c, spec.effects)
        des, cvr = ev.cv(at)
        again = ev.evaluate(at, eff, cvr.heldout, cvr.fitted_full, des.G, alpha, min_rel_gain)
    except NotIdentifiedError:  # not identified at that degree: judged at the model's
        return None
    if not again.applicable:
        return None
    why = first.implausible or first.refusal_why
    again.degree = degree
    again.detail += (f"; judged on eq. 28 of degree {degree}, chosen again with it in (at the model's degree "
                     f"{spec.degree} it gained {100 * first.rel_gain:+.1f} %, p = {first.p_value:.2g}, but "
                     f"{why or 'was not added'})")
    return again


def refit_earlier(lanes: Lanes[Evaluator], spec: ModelSpec, max_degree: int | None) -> tuple[ModelSpec, str]:
    """After a term entered (the last of ``spec.effects``): the hyper-parameter of each term added before it searched
    again on top of all the others (``Evaluator.fit_hyper``, nested, then refined on all rows), then, with ``max_degree``
    (None: not re-selected), eq. 28's degree chosen again with the new values. Each value was chosen beside another
    model: on ramps with a thermal lag and dark offsets under a source drift, the lag entered first at the degree
    its missing partner held eq. 28 to (1) with tau 35 % long, stayed so once the dark offset took the degree to 2,
    and a drift took what the wrong tau left. Returns the model and a note ("" when nothing moved). The searches run
    side by side on ``lanes``."""
    data = lanes.lanes[0].data
    todo = [i for i, (e, h) in enumerate(spec.effects[:-1]) if h is not None and e.hyper_grid(data) is not None]
    if not todo:
        return spec, ""

    def again(lane: Evaluator, i: int) -> float | None:
        rest = ModelSpec(spec.degree, spec.t_center_c, spec.t_scale_c, [x for j, x in enumerate(spec.effects) if j != i])
        try:
            return lane.fit_hyper(rest, spec.effects[i][0])[0]
        except NotIdentifiedError:  # the model without it is not identified on this data: it keeps its value
            return None
        finally:
            lane.forget_trials(spec.effects[i][0])

    effects, notes = list(spec.effects), []
    for i, h in zip(todo, lanes.map(again, todo), strict=True):
        eff, was = effects[i]
        if h is None or float(h) == float(was):
            continue
        effects[i] = (eff, float(h))
        notes.append(f"{eff.name} {eff.hyper_name} searched again beside it: {float(was):.4g} -> {float(h):.4g} "
                     f"{eff.hyper_unit}")
    if not notes:
        return spec, ""
    out = ModelSpec(spec.degree, spec.t_center_c, spec.t_scale_c, effects)
    if max_degree is not None:
        was_degree = out.degree
        out = reselect_degree(lanes, out, max_degree)[0]
        if out.degree != was_degree:
            notes.append(f"degree of eq. 28 chosen again with it: {was_degree} -> {out.degree}")
    return out, "".join(f"; {n}" for n in notes)


def drop_explained(lanes: Lanes[Evaluator], spec: ModelSpec, chosen: str, alpha_each: float,
                   min_rel_gain: float) -> tuple[ModelSpec, str]:
    """The backward step after ``chosen`` (the last of ``spec.effects``) was added: does each effect added before it
    still gain on top of all the others? Without it, ``chosen``'s hyper-parameter is searched again (it was chosen
    beside the one now in question: a thermal lag's tau came out 10 % long beside a time drift that took part of its
    residual), then the effect in question is tried on top, nested, with the forward step's test, level and least gain.
    The one that gains least of those that no longer do is taken out: the model without it and a note for the report;
    ``spec`` and "" when every one still earns its place. Forward selection alone keeps a term chosen first for a
    residual that effects added after it share out between them (on ramps with a thermal lag and reference dark
    offsets under a source drift, a time drift fits more of the declared model's residual than either, and stayed
    beside both). The searches for each effect in question run side by side on ``lanes``."""
    *before, (last, _) = spec.effects

    def without(i: int) -> ModelSpec:
        return ModelSpec(spec.degree, spec.t_center_c, spec.t_scale_c, [x for j, x in enumerate(before) if j != i])

    def beyond(lane: Evaluator, i: int) -> tuple[ModelSpec, np.ndarray, np.ndarray, np.ndarray] | None:
        try:
            rest = without(i)
            rest = rest.plus(last, lane.hyper_value(rest, last))
            des, cvr = lane.cv(rest)
            return rest, des.valid, cvr.heldout, lane.nested_heldout(rest, before[i][0])
        except NotIdentifiedError:  # the model without it is not identified on this data: it stays
            return None

    ev = lanes.lanes[0]
    weakest: tuple[float, float, int, ModelSpec] | None = None  # (p, -gain, index, model without it): least gain
    for i, done in enumerate(lanes.map(beyond, range(len(before)))):
        if done is None:
            continue
        rest, valid, ho_rest, ho_with = done
        gain, p = paired_gain_test(ho_rest, ho_with, ev.groups, ev.rows & valid, ev.weights, alpha_each)[:2]
        if not (p < alpha_each and gain >= min_rel_gain) and (weakest is None or (p, -gain) > weakest[:2]):
            weakest = (p, -gain, i, rest)
    if weakest is None:
        return spec, ""
    p, gain, i, rest = weakest[0], -weakest[1], weakest[2], weakest[3]
    return rest, (f"{before[i][0].name} taken out again: with {chosen} in the model it gains {100 * gain:+.1f} % on "
                  f"top of the others (p {p:.2g}; it needs p < {alpha_each:.2g} and {100 * min_rel_gain:g} %): the "
                  f"effects added after it explain what it took")


def confounding(lanes: Lanes[Evaluator], spec: ModelSpec, sig: list[CandidateResult], alpha_each: float,
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
    a_ho = ev.cv(at_its_degree(spec, a).plus(ea, a.hyper), remember=True)[1].heldout  # the next step's starting model

    # each on top of the other (the added one's hyper-parameter searched again, nested), compared with the other
    # alone at its final hyper-parameter, as the forward selection does
    def on_top(lane: Evaluator, task: tuple[CandidateResult, bool]) -> tuple[np.ndarray, ...]:
        b, b_on_a = task
        eb = lib[b.name]
        if b_on_a:
            b_ho = lane.cv(at_its_degree(spec, b).plus(eb, b.hyper))[1].heldout
            # evaluated again next step
            b_on_a = lane.grid_search(at_its_degree(spec, a).plus(ea, a.hyper), eb, remember=True).heldout
            lane.forget_trials(eb)
            return b_ho, b_on_a
        return (lane.nested_heldout(at_its_degree(spec, b).plus(eb, b.hyper), ea),)

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
