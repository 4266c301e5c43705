"""Evaluating a candidate effect on top of a model: eq. 28's degree (``select_degree``), the hyper-parameter search
nested in the folds and the held-out gain over visits (``Evaluator``, ``paired_gain_test``). The checks a candidate
must pass beyond its gain are in ``checks``.
"""

from __future__ import annotations

import copy
import enum
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize, stats

from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2

from ..dynamic.tone_delay import peak_offset
from ..fit.model_selection import DegreeScores, choose_degree
from ..fit.model_selection import select_degree as calibration_select_degree
from ..fit.thermal_fit import NotIdentifiedError
from ..io.recording import Recording
from .cv import (
    RSS_TIE_RTOL,
    CvResult,
    FoldSums,
    RssSums,
    cancelling_terms,
    cross_validate,
    first_min,
    search_batches,
    switch_profile,
    weighted_rss,
)
from .data import DiagnosisData, column_rms, finite_rows, group_index, row_sums, rows_at, set_rows

# ============================================================================ data preparation
from .design import (
    Design,
    DesignCache,
    ModelSpec,
    build_design,
)
from .effects import Effect
from .floor import (
    VisitNoise,
)
from .search_lanes import Lanes, idle_lanes

# searched samples from which the searches run side by side by default (``search_lanes``): bench_calibration --lanes 1/2
# at 3e4 samples (2.2e4 searched): 2.5 / 2.3 s, at 1e4: 0.6 / 0.7 s (threads cost more than they save on small designs)
LANE_SEARCH_ROWS = 20_000


def _degree_rows(scores: list[DegreeScores], held_out: Callable[[DegreeScores], np.ndarray],
                 note: str, chosen: int | None) -> list[dict[str, Any]]:
    """The report's degree table (one dict per degree) from the selection's scores; the rule's ``note`` stands
    on the degree it chose (``chosen``), not on every row."""
    table: list[dict[str, Any]] = []
    for sc in scores:
        if not sc.identified:
            table.append({"degree": sc.degree, "identified": False, "note": sc.note})
            continue
        ho = held_out(sc)
        table.append({"degree": sc.degree, "identified": True, "heldout_rmse_mps2": ho, "insample_rmse_mps2": sc.in_sample,
                      "heldout_rmse_fs": ho / FULL_SCALE_MPS2, "insample_rmse_fs": sc.in_sample / FULL_SCALE_MPS2,
                      "note": sc.note or (note if sc.degree == chosen else ""), "rule_choice": sc.degree == chosen})
    return table


def select_degree(data: DiagnosisData, max_degree: int) -> tuple[int, list[dict[str, Any]]]:
    """Degree of the declared model, chosen exactly as the calibration does (``model_selection.select_degree``:
    held out by temperature level with several levels, by pose with one) on the diagnosis samples."""
    rec = Recording(data.t_s, data.ref, data.xyz, data.temp_c, data.gref, data.pose_id, data.run_id)
    sel = calibration_select_degree(rec, max_degree, usable=data.use & (data.pose_id >= 0))
    by_level = sel.n_levels >= 2
    table = _degree_rows(sel.scores, lambda sc: sc.held_out_level if by_level else sc.held_out_pose, sel.criterion,
                         sel.chosen_degree)
    if sel.chosen_degree is None:
        raise NotIdentifiedError("no degree of eq. 28 could be validated on held-out data: " + "; ".join(sel.notes))
    return sel.chosen_degree, table


def reselect_degree(lanes: Lanes[Evaluator], spec: ModelSpec,
                    max_degree: int) -> tuple[ModelSpec, list[dict[str, Any]], list[str]]:
    """Degree and effects chosen jointly: once an effect is in the model, choose the degree of eq. 28
    again with the effect in every candidate model, by the calibration's rule (``model_selection.choose_degree``:
    temperature-level hold-out guard with two or more levels, then the lowest degree within one standard error
    of the best held-out error), the held-out unit being the visit. A term that stood in for a missing effect
    (a higher degree absorbing a drift) is dropped again; a degree an effect hid is taken up.
    Returns (the spec at the chosen degree, the degree table, notes). The degrees are cross-validated side by side
    on ``lanes``."""
    ev = lanes.lanes[0]
    data = ev.data
    labels = np.full(len(data.t_s), -1)
    labels[data.use], means = data.fitted_temperature_levels()
    n_levels = max(len(means), 1)
    by_level = n_levels >= 2
    labels = ev.at(labels)
    level_rows = ev.at(data.use) & (labels >= 0)
    nan3 = np.full(3, np.nan)

    def score(lane: Evaluator, n: int) -> tuple[DegreeScores, np.ndarray | None]:
        if n >= n_levels:
            return DegreeScores(n, False, nan3, nan3, nan3, f"not identified by {n_levels} temperature level(s)"), None
        try:
            des, cv = lane.cv(ModelSpec(n, spec.t_center_c, spec.t_scale_c, spec.effects))
        except NotIdentifiedError as exc:
            return DegreeScores(n, False, nan3, nan3, nan3, f"not identified: {exc}"), None
        r = lane.rows & des.valid & finite_rows(cv.heldout)
        ho = column_rms(rows_at(cv.heldout, r))
        ins = column_rms(rows_at(des.G - cv.fitted_full, r))
        level_ho = nan3
        if by_level and n < n_levels - 1:  # a fold trains on the other levels: degree n needs n + 1 of them
            try:
                lv = cross_validate(des, level_rows, labels, lane.weights).heldout
                rl = level_rows & des.valid & finite_rows(lv)
                level_ho = column_rms(lv[rl])
            except NotIdentifiedError:  # a fold without one level cannot fit this degree
                pass
        return DegreeScores(n, True, ins, ho, level_ho), group_mse(cv.heldout, lane.groups, r, np.full(3, 1.0 / 3))[1]

    done = lanes.map(score, range(max_degree + 1))
    scores = [sc for sc, _ in done]
    mse_by_degree = {sc.degree: m for sc, m in done if m is not None}
    chosen, criterion, notes = choose_degree(scores, mse_by_degree, by_level, unit="visit")
    table = _degree_rows(scores, lambda sc: sc.held_out_pose, criterion, chosen)
    if chosen is None:
        return spec, table, ["no degree could be validated with the added effects: degree kept", *notes]
    return ModelSpec(chosen, spec.t_center_c, spec.t_scale_c, spec.effects), table, notes


# ============================================================================ candidate evaluation
class Refusal(enum.Enum):
    """Why a candidate is not added although its test was reached or passed (``CandidateResult.refuse``): the
    check that refused it, by the name it is declared under (``checks.CHECKS``), or what else stopped it."""

    VOID = "void"  # its value on all samples changes nothing (``Effect.void``)
    READING_JUMP = "reading_jump"  # the temperature reading jumps and the candidate can follow it
    SLOW_WANDER = "slow_wander"  # its gain is not beyond the bias wander its revisits keep
    TIME_BLOCKS = "time_blocks"  # it does not predict contiguous blocks of time held out
    STEP = "step"  # a step of the response at one time explains it
    NO_GAIN = "no_gain"  # its held-out gain does not reach the level (the ADC code table, tested on its own)


@dataclass
class CandidateResult:
    name: str
    title: str
    applicable: bool
    reason: str = ""
    hyper: float | None = None
    # hyper refined between its grid neighbours (``Evaluator.final_value``); False: the best value of its grid, for a
    # candidate that does not pass its step's test (``Evaluator.evaluate``)
    hyper_refined: bool = True
    hyper_profile: list[tuple[float, float]] = field(default_factory=list)  # (h, weighted RSS)
    walked_to: tuple[int, ...] = ()  # where its search's walk over the grid ended (``GridSearch.walked_to``)
    heldout_rmse: np.ndarray | None = None  # (3,)
    rel_gain: float = 0.0  # fraction of the weighted held-out MSE removed
    p_value: float = 1.0
    n_groups: int = 0
    corr_with_residual: np.ndarray | None = None  # (3,)
    significant: bool = False
    detail: str = ""
    delta: np.ndarray | None = None  # (n, 3) change of the in-sample prediction vs the current model (float32)
    delta_rows: np.ndarray | None = None  # the samples of delta's rows (None: every sample, n = N)
    cross_correlation_delay_s: float | None = None
    implausible: str = ""  # why the fitted values are not physical (then never significant, never added)
    detectable_gain: float = math.nan  # small campaigns: gain the paired t-test finds with 80 % power
    time_block: tuple[float, float] | None = None  # a time function's (gain, p) over contiguous blocks of time held out
    step_check: StepCheck | None = None  # a candidate that can follow a step, against the best step (``step_check``)
    # eq. 28's degree it was judged at, chosen again with it in, where that is above the model's (None: the model's;
    # ``selection.judged_at_its_degree``)
    degree: int | None = None
    refusal: Refusal | None = None  # why it is not added although it gains (``refuse``); None: not refused so
    refusal_why: str = ""  # that reason in words (what its ``detail`` says after "not added: ")

    def refuse(self, refusal: Refusal, why: str) -> None:
        """Not added, for ``refusal`` (``why``: its reason in words, from the check's numbers): not significant, the
        reason kept as data, and said in ``detail`` (the report's words come from it, nothing reads them back)."""
        self.significant = False
        self.refusal, self.refusal_why = refusal, why
        self.detail += f"; not added: {why}"

    def delta_of_every_sample(self, n: int) -> np.ndarray | None:
        """``delta`` (N, 3) on every one of the recording's ``n`` samples, NaN where it was not evaluated (for the
        report's plots), or None."""
        if self.delta is None or self.delta_rows is None:
            return self.delta
        out = np.full((n, 3), np.nan, np.float32)
        out[self.delta_rows] = self.delta
        return out


def group_mse(res: np.ndarray, groups: np.ndarray, rows: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The groups (visits) of ``rows`` with a finite residual ``res`` (N, 3) m/s^2, and each group's mean of the
    per-sample squared residual weighted over the axes by ``weights`` (3,): (groups, (groups,) (m/s^2)^2)."""
    r = rows & finite_rows(res)
    ug, inv = group_index(groups[r])
    return ug, _group_means(inv, np.bincount(inv), rows_at(res, r) ** 2 * weights)


def _group_means(inv: np.ndarray, count: np.ndarray, squares: np.ndarray) -> np.ndarray:
    """Each group's mean of its rows' ``squares`` (n, 3) summed over the axes: ``inv`` (n,) the row's group, ``count``
    the rows of each group."""
    return np.bincount(inv, weights=row_sums(squares)) / count


def paired_gain_test(res0: np.ndarray, res1: np.ndarray, groups: np.ndarray, rows: np.ndarray,
                     weights: np.ndarray, alpha: float | None = None) -> tuple[float, float, int, float]:
    """(relative gain, one-sided p-value, groups, detectable gain) of held-out residual res1 over res0, paired by
    visit group.

    The test is the one-sided Wilcoxon signed-rank test of the per-group MSE differences. With so few groups
    that it cannot reach ``alpha`` at all (2^-n >= alpha: six visits against 0.01 / 8) it is a one-sided paired
    t-test over the groups instead (df n - 1; it has power on small designs but assumes normally distributed
    per-group differences), and the detectable gain is the relative gain it finds with 80 % power at ``alpha``
    given the scatter of these differences (NaN where the signed-rank test is used)."""
    r = rows & finite_rows(res0) & finite_rows(res1)
    # group_mse of each residual on the rows where both are finite: the groups and each residual's weighted squares
    # worked out once for the means and the totals (the same values)
    _, inv = group_index(groups[r])
    count = np.bincount(inv)
    e0, e1 = rows_at(res0, r) ** 2 * weights, rows_at(res1, r) ** 2 * weights
    m0, m1 = _group_means(inv, count, e0), _group_means(inv, count, e1)
    d = m0 - m1
    n = len(d)
    tot0 = float(np.sum(e0))
    gain = (tot0 - float(np.sum(e1))) / tot0 if tot0 > 0 else 0.0
    if alpha is not None and 0.5**n >= alpha:  # small campaign: the rank test cannot reach alpha
        sd = float(np.std(d, ddof=1)) if n >= 3 else 0.0
        if sd <= 0:
            return gain, 1.0, n, math.inf
        p = float(stats.ttest_1samp(d, 0.0, alternative="greater").pvalue)
        detectable = (stats.t.ppf(1 - alpha, n - 1) + stats.t.ppf(0.8, n - 1)) * sd / math.sqrt(n) / float(np.mean(m0))
        return gain, p, n, float(detectable)
    if n < 5 or np.all(d == 0):
        return gain, 1.0, n, math.nan
    p = float(stats.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue)
    return gain, p, n, math.nan


def sample_changes(data: DiagnosisData, x: np.ndarray, block: int = 65_536) -> np.ndarray:
    """First differences (N - 1, k) of ``x`` (N, k) over the samples, NaN read as 0 (``np.nan_to_num``), 0 across a
    change of run: ``np.diff(np.nan_to_num(x), axis=0)`` bit for bit, made ``block`` rows at a time into the one
    result (no copy of ``x``)."""
    out = np.empty((max(len(x) - 1, 0), *x.shape[1:]))
    for lo in range(0, len(out), block):
        hi = min(lo + block, len(out))
        np.subtract(np.nan_to_num(x[lo + 1:hi + 1]), np.nan_to_num(x[lo:hi]), out=out[lo:hi])
    out[data.run_id[1:] != data.run_id[:-1]] = 0.0
    return out


def cross_correlation_delay(data: DiagnosisData, fitted_changes: np.ndarray, max_lag: int = 12) -> float:
    """Delay (s) of the model output against the (gap-filled) reference by cross-correlation of their
    first differences (finddelay of D'Emilia et al. 2019), with parabolic sub-sample interpolation.
    ``fitted_changes``: ``sample_changes`` of the model's output (N, 3) m/s^2, taken by the caller so that the output
    itself need not be held beside the reference's changes and their products (three arrays of N x 3 here)."""
    best_lag, best_val, vals = 0, -np.inf, {}
    a, g = fitted_changes, sample_changes(data, data.gref_filled)
    product = np.empty_like(g)  # each lag's products, in one array
    for lag in range(0, max_lag + 1):
        n = len(g) - lag
        v = float(np.sum(np.multiply(a[lag:], g[:n], out=product[:n])))
        vals[lag] = v
        if v > best_val:
            best_lag, best_val = lag, v
    frac = peak_offset(vals[best_lag - 1], vals[best_lag], vals[best_lag + 1]) if 0 < best_lag < max_lag else 0.0
    return (best_lag + frac) * data.dt_s


SEARCH_ROWS = 50_000  # fitted samples above which the candidates are evaluated on every k-th one
MIN_SEARCH_INFORMATION = 0.8  # but a thinned search keeps at least this much of what a visit's samples tell of its mean


def thinned_information(noise: VisitNoise, k: int, visit_samples: float) -> float:
    """What every ``k``-th sample of a visit of ``visit_samples`` consecutive samples tells of the visit's mean, as a
    fraction of what all of them tell: var(mean of all) / var(mean of every k-th) under the noise's autocorrelation
    (``VisitNoise.mean_variance``; ``visit_samples`` / k of them, as many as the thinning leaves on average over the
    visits' phases: a little less than the ceiling, so on the safe side), on the axis that loses most. 1 / k for white
    noise; near 1 while k is well within the noise's correlation time (the TIA's filtered noise at 100 Hz:
    ``VisitNoise.correlation_samples``)."""
    if k <= 1:
        return 1.0
    every = noise.mean_variance(np.array([float(visit_samples)]))[0]
    thinned = VisitNoise(noise.sigma, noise.acf[:, ::k]).mean_variance(np.array([float(visit_samples) / k]))[0]
    return float(np.min(every / thinned))


def check_search_rows(search_rows: int | None) -> None:
    """Refuse a ``search_rows`` below 1 (None: every sample) with a clear error."""
    if search_rows is not None and search_rows < 1:
        raise ValueError(f"search_rows must be at least 1 (None: every sample), got {search_rows}")


def search_samples(fit_rows: np.ndarray, folds: np.ndarray, search_rows: int | None, noise: VisitNoise | None = None,
                   visit_samples: float = math.inf) -> tuple[np.ndarray, int, float]:
    """(the samples the candidates are searched on, in fold order: each fold a slice of the search's designs, no
    gathers; the step k of the thinning (1: not thinned); ``thinned_information`` at k). Those are the fitted
    samples ``fit_rows`` (N,); with more than ``search_rows`` of them, every k-th one (about ``search_rows``), k
    lowered until the thinned samples keep ``MIN_SEARCH_INFORMATION`` of what the visits' samples tell of their means
    (``noise``: the floor's model of the noise; ``visit_samples``: a visit's typical number of fitted samples).
    Consecutive samples of a visit are strongly correlated (TIA-filtered noise): the thinned set carries most of
    the information that decides a choice, at a fraction of the cost; a recording sampled so slowly that its noise
    is nearly white is thinned less."""
    check_search_rows(search_rows)
    n_fit = int(fit_rows.sum())
    k = math.ceil(n_fit / search_rows) if search_rows is not None and n_fit > search_rows else 1
    kept = 1.0 if noise is None or not math.isfinite(visit_samples) else thinned_information(noise, k, visit_samples)
    if kept < MIN_SEARCH_INFORMATION:  # the largest k below that keeps it (bisection: the information falls with k)
        lo, hi, kept = 1, k, 1.0
        while hi - lo > 1:
            mid = (lo + hi) // 2
            info = thinned_information(noise, mid, visit_samples)
            lo, hi, kept = (mid, hi, info) if info >= MIN_SEARCH_INFORMATION else (lo, mid, kept)
        k = lo
    every = np.flatnonzero(fit_rows)[::k]
    return every[np.argsort(folds[every], kind="stable")], k, kept


@dataclass
class GridSearch:
    """One hyper-parameter's search on top of a model over its grid, nested in the folds (``Evaluator.grid_search``).

    ``heldout`` (N, 3): each fold's held-out residual at the value that fits the other folds best; ``profile``: (value,
    mean training RSS over the folds) of every value visited that is identified; ``values`` (ascending) and ``rss``:
    those the final value is chosen among (the plausible ones, or every one when none is: ``plausible``); empty for an
    effect without a hyper-parameter. ``final`` (refined or not -> value) and ``rss_at`` (value -> in-sample RSS on all
    rows): what ``Evaluator.final_value`` worked out of it. ``walked_to``: the grid indices the walk ended at (each
    fold's best plausible value and the best mean), where a search of the same effect on the next step's model starts
    (``search_batches``)."""

    heldout: np.ndarray
    profile: list[tuple[float, float]]
    values: np.ndarray
    rss: np.ndarray
    plausible: bool
    walked_to: tuple[int, ...] = ()
    final: dict[bool, float] = field(default_factory=dict)
    rss_at: dict[float, float] = field(default_factory=dict)


class Evaluator:
    """Evaluates specs on the samples ``sub`` (indices, ``search_samples``) of one recording with fixed folds,
    rows and noise weights (cached designs): ``diagnose`` evaluates the candidates and chooses the model on it
    (hyper-parameters, held-out gains, tests over the visits), then fits the chosen model on every sample.
    Designs, folds, groups and held-out arrays are of ``sub``'s length; the input corrections still run on the
    whole time series. ``references``: the corrected references a search keeps (``DesignCache``); ``refine_every``:
    :meth:`evaluate` refines every candidate's hyper-parameter, not only those of the candidates that pass the test.
    """

    def __init__(self, data: DiagnosisData, folds: np.ndarray, weights: np.ndarray, groups: np.ndarray,
                 sub: np.ndarray, references: int = 4, refine_every: bool = False) -> None:
        # the rows read-only, of their own memory: their digest is worked out once (``DiagnosisData.rows_key``)
        sub = np.array(sub, copy=True)
        sub.flags.writeable = False
        self.data, self.weights, self.sub, self.refine_every = data, weights, sub, refine_every
        self.folds, self.groups = self.at(folds), self.at(groups)
        self.rows = self.at(data.use) & (self.folds >= 0)  # held out and judged
        self.fit_rows = self.at(data.use) & (self.folds != -1)  # fitted (also the visits never held out, fold -2)
        self.designs = DesignCache(references=references)
        # results worked out by the confounding check that the next step needs again (see ``forget``)
        self._cv_memo: dict[tuple, tuple[Design, CvResult]] = {}
        self._hyper_memo: dict[tuple, GridSearch] = {}
        # the refined value of every search made (``final_value``), by model and effect, for the diagnosis: the backward
        # step asks again for a search the step before made (``hyper_value``); a float each, the lanes share them
        self._final_values: dict[tuple, float] = {}
        self._last_cv: tuple[tuple, tuple[Design, CvResult]] | None = None
        # the trials a search's evaluation asks for again (``_keep``): the chosen grid value's design and fit, the
        # refinement's best value's design, the null value's; by slot ("walk", "refine", "null"): (model key,
        # design, fit or None)
        self._kept: dict[str, tuple[tuple, Design, CvResult | None]] = {}
        # by effect name, the grid indices a search of it starts its walk from (``search_batches``): where its last
        # step's search ended (``GridSearch.walked_to``), set between steps by ``forward_selection``; the lanes share it
        self.walk_starts: dict[str, tuple[int, ...]] = {}
        self._sums: FoldSums | None = None
        self._rss_sums: RssSums | None = None

    def at(self, a: np.ndarray) -> np.ndarray:
        """``a`` (per sample of the recording) at this evaluator's samples."""
        return a[self.sub]

    @property
    def model_matrix(self) -> np.ndarray:
        """(3, 3) model matrix at the mean temperature (m/s^2 per unit Psi), for the plausibility bounds."""
        return np.linalg.inv(self.data.static_psi_map()[0])

    def design(self, spec: ModelSpec) -> Design:
        kept = self._kept_trial(spec)
        return kept[0] if kept is not None else build_design(self.data, spec, self.designs, self.sub)

    def _keep(self, slot: str, spec: ModelSpec, des: Design, cvr: CvResult | None) -> None:
        """Keep a search's trial (``des`` and its cross-validation ``cvr``, None: not worked out) in ``slot`` until the
        next search starts or its evaluation ends (``forget_trials``): the value a search chose is asked for again by
        its final value's in-sample fit and by the candidate's evaluation, the refinement's best by its plausibility
        check, the null value by the evaluation when the parsimony check keeps it. The same arrays, so the same
        results, bit for bit; one design a slot."""
        self._kept[slot] = (spec.key, des, cvr)

    def _kept_trial(self, spec: ModelSpec) -> tuple[Design, CvResult | None] | None:
        """The kept trial (``_keep``) of the model ``spec``, if any."""
        for key, des, cvr in self._kept.values():
            if key == spec.key:
                return des, cvr
        return None

    def cv(self, spec: ModelSpec, remember: bool = False) -> tuple[Design, CvResult]:
        """Design and cross-validation of ``spec``; ``remember``: keep them for a later call (``forget``). The
        last one is kept too: a search's final value is checked for plausibility, then evaluated."""
        hit = self._cv_memo.get(spec.key)
        if hit is None and self._last_cv is not None and self._last_cv[0] == spec.key:
            hit = self._last_cv[1]
        if hit is not None:
            return hit
        self._last_cv = None  # not held while the next design is built
        kept = self._kept_trial(spec)
        if kept is not None and kept[1] is not None:
            out = kept
        else:
            des = kept[0] if kept is not None else build_design(self.data, spec, self.designs, self.sub)
            out = des, cross_validate(des, self.fit_rows, self.folds, self.weights, self._sums)
            self._sums = out[1].sums  # a search over the reference alone asks again with the same matrix
        if remember:
            self._cv_memo[spec.key] = out
        self._last_cv = (spec.key, out)
        return out

    def cv_each(self, specs: list[ModelSpec],
                use: Callable[[int, tuple[Design, CvResult] | NotIdentifiedError], None]) -> None:
        """``use(k, self.cv(specs[k]))`` (or the NotIdentifiedError it raised) for each spec in order, the designs and
        cross-validations worked out on this lane and on the lanes of the map left idle meanwhile
        (``search_lanes.idle_lanes``): one spec a lane at a time, each result used before the next round (the lanes'
        results are the same, bit for bit; a lent lane keeps its last design until its next trial, as any lane)."""
        def one(lane: Evaluator, spec: ModelSpec) -> tuple[Design, CvResult] | NotIdentifiedError:
            try:
                return lane.cv(spec)
            except NotIdentifiedError as exc:
                return exc

        with idle_lanes(len(specs) - 1) as extra:
            if not extra:
                for k, spec in enumerate(specs):
                    use(k, one(self, spec))
                return
            lanes = [self, *extra]
            with ThreadPoolExecutor(len(extra), thread_name_prefix="search-lane-lent") as pool:
                for lo in range(0, len(specs), len(lanes)):
                    part = specs[lo:lo + len(lanes)]
                    later = [pool.submit(one, lane, spec) for lane, spec in zip(lanes[1:], part[1:], strict=False)]
                    use(lo, one(self, part[0]))
                    for k, f in enumerate(later, start=lo + 1):
                        use(k, f.result())

    def forget(self, spec: ModelSpec) -> None:
        """Drop remembered results except those on top of ``spec``, the model the next step starts from: the
        confounding check has already worked out each candidate on top of the one that is then added."""
        for k in [k for k in self._cv_memo if k != spec.key]:  # in place: the lanes share them (``lane``)
            del self._cv_memo[k]
        for k in [k for k in self._hyper_memo if k[0] != spec.key]:
            del self._hyper_memo[k]
        self._rss_sums = None  # its copy of the matrix's fitted rows (n x p)

    def lane(self) -> Evaluator:
        """Another evaluator of the same samples, folds and weights, for searches run beside this one's
        (``search_lanes``): its own caches of inputs and designs, this one's remembered results and corrected
        references (values that depend on their key alone, whichever lane works them out)."""
        other = copy.copy(self)
        other.designs = self.designs.for_another_lane()
        other._last_cv = other._sums = other._rss_sums = None
        other._kept = {}
        return other

    def fit_hyper(self, spec: ModelSpec, eff: Effect,
                  remember: bool = False) -> tuple[float | None, np.ndarray, list[tuple[float, float]]]:
        """Hyper-parameter of ``eff`` added to ``spec``: nested grid choice per fold for the held-out
        residual (:meth:`grid_search`), and grid + bounded refinement on all rows for the final value
        (:meth:`final_value`). Returns (value, held-out residual (N, 3), profile of (value, mean training RSS)).
        ``remember``: keep the search (``forget``)."""
        search = self.grid_search(spec, eff, remember)
        return self.final_value(spec, eff, search), search.heldout, search.profile

    def grid_search(self, spec: ModelSpec, eff: Effect, remember: bool = False) -> GridSearch:
        """The search of ``eff``'s hyper-parameter on top of ``spec`` over its grid, nested in the folds
        (``GridSearch``); ``remember``: keep it for a later call (``forget``), with the final values worked out of it."""
        key = (spec.key, eff.name)
        if key in self._hyper_memo:
            return self._hyper_memo[key]
        out = self._grid_search(spec, eff)
        if remember:
            self._hyper_memo[key] = out
        return out

    def remembers(self, spec: ModelSpec, eff: Effect) -> bool:
        """Whether :meth:`grid_search` of ``eff`` on top of ``spec`` is remembered (costs nothing)."""
        return (spec.key, eff.name) in self._hyper_memo

    def nested_heldout(self, spec: ModelSpec, eff: Effect) -> np.ndarray:
        """The held-out residual (N, 3) of :meth:`grid_search` alone: the final value is not worked out (the held-out
        residual does not depend on it); what the lane's cache kept of the trials is let go after it
        (:meth:`forget_trials`)."""
        try:
            return self.grid_search(spec, eff).heldout
        finally:
            self.forget_trials(eff)

    def forget_trials(self, eff: Effect) -> None:
        """Let go of what this lane's cache keeps of models with ``eff`` (``DesignCache.forget``): called once a search
        over ``eff`` is judged, when the searches after it ask for other models (the series of 10^6 samples of its
        trial values would stay beside theirs until pushed out)."""
        self.designs.forget(eff.name)
        self._kept.clear()

    def _grid_search(self, spec: ModelSpec, eff: Effect) -> GridSearch:
        """:meth:`grid_search`."""
        self._kept.clear()  # another search's trials
        if eff.hyper_grid(self.data) is None:
            _, cvr = self.cv(spec.plus(eff, None))
            return GridSearch(cvr.heldout, [], np.empty(0), np.empty(0), True)
        grid = eff.hyper_grid(self.data)
        K = int(self.folds[self.rows].max()) + 1
        fold_rows = [np.flatnonzero(self.rows & (self.folds == f)) for f in range(K)]  # indices: a fold is taken often
        # nested choice: each fold's held-out residual is the one of the grid value that fits the other folds
        # best (the first such value on a tie), kept as the grid is walked: one (N, 3) array, not one per value.
        # Values whose fit on all rows is not physical (Effect.implausible: e.g. a warm-up of 13 m/s^2 cancelled
        # by a creep) are searched apart and used only when no value is plausible: the hypothesis is a
        # physical effect, and the best implausible value must not hide a plausible one. Each kind's (N, 3) array
        # is made when a value of that kind first fits a fold best: a search with no implausible value holds one.
        heldout: dict[bool, np.ndarray] = {}

        def heldout_of(ok: bool) -> np.ndarray:
            if ok not in heldout:
                heldout[ok] = np.full((len(self.folds), 3), np.nan)
            return heldout[ok]

        best_train = {ok: np.full(K, np.inf) for ok in (True, False)}
        best_at = {ok: np.full(K, len(grid)) for ok in (True, False)}  # grid index of each fold's best value
        seen: dict[int, tuple[bool | None, float]] = {}  # grid index -> (plausible, mean training RSS); None: not identified
        lowest: dict[bool, tuple[float, int, Design, CvResult]] = {}  # of each kind, the visited value of least mean
        unidentified: list[str] = []
        # a step's time is a fold's choice only where that fold's training visits on each side span the frame
        fold_ok = self._step_sides(eff, grid, K) if eff.switched else None

        def visit(i: int, done: tuple[Design, CvResult] | NotIdentifiedError) -> None:
            h = float(grid[i])
            if isinstance(done, NotIdentifiedError):  # this value makes the design singular: not a candidate
                unidentified.append(f"{eff.hyper_name} = {h:.4g}: {done}")
                seen[i] = (None, math.inf)
                return
            des, cvr = done
            ok = not self.implausible(eff, h, des, cvr)
            # the first value in grid order wins a tie (equal up to rounding: ``RSS_TIE_RTOL``), whatever the order
            # the values are visited in
            tie = np.abs(cvr.train_rss - best_train[ok]) <= RSS_TIE_RTOL * np.minimum(cvr.train_rss, best_train[ok])
            better = np.where(tie, i < best_at[ok], cvr.train_rss < best_train[ok])
            if fold_ok is not None:
                better &= fold_ok[:, i]
            for f in np.flatnonzero(better):
                best_train[ok][f], best_at[ok][f] = cvr.train_rss[f], i
                out = heldout_of(ok)
                set_rows(out, fold_rows[f], np.nan)  # those of the fold not fitted at this value
                at, res = cvr.fold_heldout(f)
                set_rows(out, at, res)
            seen[i] = (ok, float(np.sum(cvr.train_rss) / max(K - 1, 1)))
            if ok not in lowest or seen[i][1] < lowest[ok][0]:
                lowest[ok] = (seen[i][1], i, des, cvr)

        def visit_all(batch: list[int]) -> None:
            todo = [i for i in batch if i not in seen]
            self.cv_each([spec.plus(eff, float(grid[i])) for i in todo], lambda k, done: visit(todo[k], done))

        picks = self._switch_picks(spec, eff, grid, fold_ok) if eff.switched else None
        visit_all(picks or [])
        if picks is None or not all(ok for ok, _ in seen.values()):  # an implausible or unidentified pick: the walk
            for batch in search_batches(len(grid), seen, best_at[True], self.walk_starts.get(eff.name, ())):
                visit_all(batch)
        order = sorted(i for i in seen if seen[i][0] is not None)
        if not order:
            raise NotIdentifiedError("no value of the grid is identified (" + unidentified[0] + ")")
        use_ok = any(seen[i][0] for i in order)
        chosen = [i for i in order if seen[i][0] == use_ok]
        best = chosen[first_min(np.asarray([seen[i][1] for i in chosen]))]  # the value ``final_value`` starts from
        if lowest[use_ok][1] == best:
            self._keep("walk", spec.plus(eff, float(grid[best])), *lowest[use_ok][2:])
        walked_to = tuple(sorted({int(b) for b in best_at[True] if b < len(grid)} | {best}))
        return GridSearch(heldout_of(use_ok), [(float(grid[i]), seen[i][1]) for i in order],
                          np.asarray([float(grid[i]) for i in chosen]), np.asarray([seen[i][1] for i in chosen]), use_ok,
                          walked_to)

    def final_value(self, spec: ModelSpec, eff: Effect, search: GridSearch, refine: bool = True) -> float | None:
        """The value of ``eff``'s hyper-parameter on top of ``spec`` (None: it has none): the best of ``search``'s
        values (of the kind it chose: plausible ones when any), with ``refine`` the bounded scalar refinement of the
        in-sample RSS on all rows between that value's neighbours (a plausible one when the search chose among
        plausible ones), then the parsimony check against the effect's null value. Kept in ``search``: a remembered
        search works each out once."""
        if not len(search.values):
            return None
        if refine in search.final:
            return search.final[refine]
        grid = search.values
        j = first_min(search.rss)
        lo = grid[max(j - 1, 0)]
        hi = grid[min(j + 1, len(grid) - 1)]
        h_best = float(grid[j])
        rss_at = search.rss_at  # the refinement and the parsimony check ask for some values again
        least = math.inf  # the least in-sample RSS of a design worked out here, kept (``_keep``)

        def obj(h: float) -> float:
            nonlocal least
            h = float(h)
            if h not in rss_at:
                at = spec.plus(eff, h)
                try:
                    des = self.design(at)
                    rss_at[h], self._rss_sums = weighted_rss(des, self.fit_rows, self.weights, self._rss_sums)
                except NotIdentifiedError:
                    rss_at[h] = math.inf
                else:
                    if eff.hyper_null is not None and h == float(eff.hyper_null):
                        self._keep("null", at, des, None)  # the value the parsimony check may keep
                    elif rss_at[h] < least:
                        least = rss_at[h]
                        self._keep("refine", at, des, None)
            return rss_at[h]

        if refine and hi > lo and not eff.switched:  # a switched effect's values are sample indices: none between them
            res = optimize.minimize_scalar(obj, bounds=(float(lo), float(hi)), method="bounded",
                                           options={"xatol": 1e-3 * (hi - lo), "maxiter": 25})
            if res.success and res.fun <= obj(h_best):
                h_ref = float(res.x)
                if not (search.plausible and self.implausible(eff, h_ref, *self.cv(spec.plus(eff, h_ref)))):
                    h_best = h_ref
        if eff.hyper_null is not None:
            # parsimony: keep the null value unless moving away from it is a significant improvement,
            # judged with visits as the independent units (likelihood ratio ~ chi^2(1), 1 %)
            rss_best, rss_null = obj(h_best), obj(eff.hyper_null)  # a null value not identified is not kept
            n_groups = len(np.unique(self.groups[self.rows]))
            if (rss_null - rss_best) / max(rss_best / n_groups, 1e-300) < stats.chi2.ppf(0.99, 1):
                h_best = float(eff.hyper_null)
        search.final[refine] = h_best
        if refine:
            self._final_values[(spec.key, eff.name)] = h_best
        return h_best

    def hyper_value(self, spec: ModelSpec, eff: Effect) -> float | None:
        """``fit_hyper(spec, eff)[0]``: the refined value of ``eff``'s hyper-parameter on top of ``spec``, that of the
        search made before where there was one (``final_value`` keeps it), else searched now. A search asked again
        would walk its grid from where the effect's last search ended, not from where this one started: the same
        value wherever each fold's training RSS has one minimum over the grid (``bench/walk_start_check.py``)."""
        key = (spec.key, eff.name)
        return self._final_values[key] if key in self._final_values else self.fit_hyper(spec, eff)[0]

    def _step_sides(self, eff: Effect, grid: np.ndarray, K: int) -> np.ndarray:
        """(K, m) bool: whether fold f's training visits before and after the step at each value of ``grid`` each
        span the table frame (``ResponseStepEffect.sides_span``; the visits a fold holds out are those of its
        judged rows)."""
        _, _, ids = eff.visit_table(self.data)
        order = np.argsort(ids)
        r = np.flatnonzero(self.rows)
        pos = np.minimum(np.searchsorted(ids[order], self.groups[r]), len(ids) - 1)
        known = ids[order][pos] == self.groups[r]
        held = np.zeros((K, len(ids)), bool)
        held[self.folds[r][known], order[pos[known]]] = True
        return eff.sides_span(self.data, grid, ~held)

    def _switch_picks(self, spec: ModelSpec, eff: Effect, grid: np.ndarray,
                      fold_ok: np.ndarray | None = None) -> list[int] | None:
        """The grid indices a search of a switched effect (``Effect.switched``) visits: each fold's best (among the
        values ``fold_ok`` (K, m) allows it) and the best mean training RSS from ``switch_profile``; None when the
        model alone is not identified (the walk says why)."""
        des = self.design(spec.plus(eff, -math.inf))  # switched on everywhere: its block is the switched columns
        blk = des.blocks[eff.name]
        X = des.X[:, :blk.start] if blk.stop == des.X.shape[1] else np.delete(des.X, np.r_[blk], axis=1)
        try:
            prof = switch_profile(X, des.G, des.X[:, blk], self.sub, self.folds,
                                  self.fit_rows & des.valid, self.weights, grid)
        except NotIdentifiedError:
            return None
        best_mean = first_min(prof.sum(axis=0))
        if fold_ok is not None:
            prof = np.where(fold_ok, prof, np.inf)
        return sorted({first_min(p) for p in prof if np.isfinite(p).any()} | {best_mean})

    def implausible(self, eff: Effect, h: float | None, des: Design, cvr: CvResult) -> str:
        """Why the fit of ``eff`` at ``h`` (design ``des``, fit ``cvr`` on all rows) is not physical, or "": the
        effect's own bound (``Effect.refusal``: its hyper-parameter's range, its fitted values) or columns that cancel
        (``cancelling_terms``)."""
        coeff, folds = self.coefficients(eff, des, cvr)
        return (eff.refusal(h, coeff, self.data, self.model_matrix, folds)
                or cancelling_terms(des, cvr, eff.name))

    @staticmethod
    def coefficients(eff: Effect, des: Design, cvr: CvResult) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``eff``'s coefficients (3, k) on all rows and in each fold's training fit (K, 3, k); None, None when it
        has no columns."""
        if eff.name not in des.blocks:
            return None, None
        blk = des.blocks[eff.name]
        return cvr.A_full[blk].T, np.swapaxes(cvr.fold_coefficients[:, blk, :], 1, 2)

    def evaluate(self, spec: ModelSpec, eff: Effect, base_heldout: np.ndarray, base_fitted: np.ndarray,
                 base_G: np.ndarray, alpha: float | None = None, min_rel_gain: float = 0.0) -> CandidateResult:
        """Held-out gain and significance of ``eff`` on top of ``spec``, whose held-out residual, in-sample fit and
        reference (each (n, 3), this evaluator's samples) are the ``base_*`` (``alpha``: the candidate's level,
        which decides the test on small campaigns, ``paired_gain_test``); what the lane's cache kept of the search's
        trials is let go after it (:meth:`forget_trials`). The hyper-parameter is refined between its grid neighbours
        (:meth:`final_value`) for a candidate that passes the test (p below ``alpha``, gain at least ``min_rel_gain``;
        ``alpha`` None or ``refine_every``: always): the held-out gain and its test do not depend on it
        (``GridSearch.heldout``), and a candidate that does not pass them is never added, so its value is the best of
        its grid (``CandidateResult.hyper_refined`` False)."""
        try:
            return self._evaluate(spec, eff, base_heldout, base_fitted, base_G, alpha, min_rel_gain)
        finally:
            self.forget_trials(eff)

    def _evaluate(self, spec: ModelSpec, eff: Effect, base_heldout: np.ndarray, base_fitted: np.ndarray,
                  base_G: np.ndarray, alpha: float | None, min_rel_gain: float) -> CandidateResult:
        """:meth:`evaluate`."""
        ok, why = eff.applicable(self.data)
        out = CandidateResult(eff.name, eff.title, ok, why)
        if not ok:
            return out
        try:
            search = self.grid_search(spec, eff)
            # nothing to refine without a hyper-parameter; a remembered search may hold its refined value already
            refined = alpha is None or self.refine_every or True in search.final or not len(search.values)
            h = self.final_value(spec, eff, search, refine=refined)
            des, cvr = self.cv(spec.plus(eff, h))
            r, (gain, p, ng, out.detectable_gain) = self._gain_test(des, search.heldout, base_heldout, alpha)
            if not refined and p < alpha and gain >= min_rel_gain:  # it passes: its value refined, judged there
                refined, h = True, self.final_value(spec, eff, search)
                des, cvr = self.cv(spec.plus(eff, h))
                r, (gain, p, ng, out.detectable_gain) = self._gain_test(des, search.heldout, base_heldout, alpha)
        except NotIdentifiedError as exc:  # the data cannot tell its columns from the model's: say so
            out.applicable, out.reason = False, f"not identified on this data: {exc}"
            return out
        heldout, profile = search.heldout, search.profile
        out.hyper_refined = refined
        # what the candidate explains of the current residual (reference changes count too: delay, TIA)
        delta = (base_G - des.G) + (cvr.fitted_full - base_fitted)
        corr = np.array([_corr(base_heldout[r, j], delta[r, j]) for j in range(3)])
        out.hyper, out.hyper_profile, out.walked_to = h, profile, search.walked_to
        out.heldout_rmse = column_rms(rows_at(heldout, r))
        out.rel_gain, out.p_value, out.n_groups = gain, p, ng
        out.corr_with_residual = corr
        coeff = cvr.A_full[des.blocks[eff.name]].T if eff.name in des.blocks else None
        out.detail = eff.describe_on(h, coeff, self.data)
        if not refined and h is not None and h != eff.hyper_null:
            out.detail += " (its grid's best value: refined only for a candidate that passes the test)"
        out.implausible = self.implausible(eff, h, des, cvr)
        if out.implausible:
            out.detail += f"; REFUSED: {out.implausible}"
        else:
            at_bound = eff.at_bound(h, coeff, self.data, self.model_matrix, self.coefficients(eff, des, cvr)[1])
            out.detail += f"; not refused: {at_bound}" if at_bound else ""
        out.delta = delta.astype(np.float32)  # for the plots and a correlation only
        return out

    def _gain_test(self, des: Design, heldout: np.ndarray, base_heldout: np.ndarray,
                   alpha: float | None) -> tuple[np.ndarray, tuple[float, float, int, float]]:
        """(the rows (n,) compared, ``paired_gain_test`` of ``heldout`` against ``base_heldout`` on them): the rows
        judged that ``des`` leaves valid and both residuals have."""
        r = self.rows & des.valid & finite_rows(heldout) & finite_rows(base_heldout)
        return r, paired_gain_test(base_heldout, heldout, self.groups, r, self.weights, alpha)


def _evaluate_on(spec: ModelSpec, base_heldout: np.ndarray, base_fitted: np.ndarray, base_G: np.ndarray, alpha: float,
                 min_rel_gain: float, seconds: dict[str, float], ev: Evaluator, eff: Effect) -> CandidateResult:
    """``ev.evaluate(spec, eff, ...)``: a task of ``Lanes.map`` (lane, item) once the step's arguments are bound; the
    time it took goes into ``seconds`` (by the candidate's name: the order the next step's candidates start in)."""
    t0 = time.perf_counter()
    out = ev.evaluate(spec, eff, base_heldout, base_fitted, base_G, alpha, min_rel_gain)
    seconds[eff.name] = time.perf_counter() - t0
    return out


@dataclass
class StepCheck:
    """A candidate that can follow a step (``Effect.follows_a_step``: a function of time, of the temperature's history
    or of the reference counts) against the best step of the response at one time (``effects.ResponseStepEffect``),
    each added on top of the other (held-out gain, one-sided p over visits) with eq. 28 at ``degree``."""

    t_s: float  # board time of the first fitted sample after the step (s)
    t_before_s: float  # board time of the last fitted sample before it (s): the step happened in between
    run: int  # the run it is in
    gain_step_beyond: float  # the step on top of the candidate
    p_step_beyond: float
    gain_time_beyond: float  # the candidate on top of the step
    p_time_beyond: float
    explained: bool  # the step gains beyond the candidate, the candidate not beyond the step
    degree: int = 0  # degree of eq. 28 in both models (chosen again with the candidate and the step in it)

    @property
    def when(self) -> str:
        """Where the step is, for the report: between two fitted samples (a table move, a settling or a gap in between)."""
        return f"between t = {self.t_before_s:.4g} and {self.t_s:.4g} s (run {self.run})"


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    if a.size < 3 or np.std(a) == 0 or np.std(b) == 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])
