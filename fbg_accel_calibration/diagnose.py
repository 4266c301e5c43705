"""Residual diagnosis of the calibration model: find what eq. 28 lacks, add it, report before/after.

Pure numpy/scipy engine behind ``fbg-accel-calib diagnose`` (issue 4). Steps:

1. Static samples: the static-interval detector of the fit (``static_detector.calibration_samples``,
   signal still AND table reference constant AND in a pose) or, with ``static="table"``, every
   sample the table reports in a pose.
2. Declared model: eq. 28 at the degree chosen by cross-validation over pose groups (degree
   < number of temperature levels, as in ``thermal_fit``). Noise floor = pooled within-pose
   standard deviation of its residual per axis (what no static model can remove).
3. Every candidate of ``effects.LIBRARY`` on top of the current model: hyper-parameter by a 1-D
   search (grid; nested inside each training fold for the held-out figures, then refined on all
   data for the final value); held-out residuals by K-fold cross-validation over pose groups;
   per-pose paired gain in noise-weighted held-out MSE; one-sided Wilcoxon signed-rank test over
   pose groups (Bonferroni over the candidates of the step); correlation of the candidate's
   contribution with the held-out residual; pairwise confounding among the significant ones (each
   added on top of the other: does it still gain?).
4. Forward selection: add the best significant candidate, repeat; stop when no candidate is
   significant or gains less than ``min_rel_gain`` of the held-out MSE (so nothing is added when
   nothing is significant).
5. Refit with the winners as declared ``corrections`` of a ``ThermalCalibration``; check that the
   driver's ``apply_counts`` reproduces the fit's prediction; before/after held-out RMSE per axis
   next to the noise floor; test and describe what residual remains (per pose, axis, temperature,
   time, orientation).

Significance is tested with pose groups as the independent units, not samples: the noise of this
sensor is low-pass filtered (TIA ~1 Hz at 100 Hz sampling), so consecutive samples are strongly
correlated and a sample-level F-test would be far too optimistic.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize, stats

from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2
from fbg_accel_driver.thermal_model import ThermalCalibration

from .effects import LIBRARY, DiagnosisData, Effect, Inputs, motion_groups, separating_measurement
from .recording import Recording, time_axis_label
from .static_detector import calibration_samples
from .thermal_fit import NotIdentifiedError, design_matrix, n_params, temperature_levels, temperature_scaling

# ============================================================================ data preparation
SAMPLE_SELECTIONS = ("table", "detector", "all")


def prepare_data(rec: Recording, static: str = "table") -> DiagnosisData:
    """Diagnosis arrays from a recording. ``static`` selects the samples that are fitted and judged:

    * ``"table"`` (default): every sample of a pose the table held for at least 5 samples (the
      reference is known and constant). Chain dynamics that outlast the stop stay visible.
    * ``"detector"``: the fit's static-interval detector (signal still AND reference constant); it
      removes settling samples, so it hides most of the chain dynamics.
    * ``"all"``: every sample with a finite reference, including those taken while the table moves
      (only for recordings whose reference is the table's angle reading during motion, e.g. the
      simulator; samples in motion are cross-validated with the pose the table moves to).
    """
    if static not in SAMPLE_SELECTIONS:
        raise ValueError(f"static must be one of {SAMPLE_SELECTIONS}, got {static!r}")
    finite = np.all(np.isfinite(rec.gref_mps2), axis=1) & np.isfinite(rec.ref) & (rec.ref > 0)
    finite &= np.all(np.isfinite(rec.xyz), axis=1) & np.isfinite(rec.temp_c)
    if static == "all":
        use = finite & (motion_groups(rec.pose_id, rec.run_id) >= 0)
    elif static == "detector":
        usable, _ = calibration_samples(rec)
        use = usable & finite & (rec.pose_id >= 0)
    else:
        finite &= rec.pose_id >= 0
        # every sample of a pose the table held for at least 5 consecutive samples
        change = np.r_[True, (np.diff(rec.pose_id) != 0) | (np.diff(rec.run_id) != 0)]
        seg = np.cumsum(change) - 1
        use = finite & (np.bincount(seg)[seg] >= 5)
    if use.sum() < 20:
        raise ValueError(f"only {int(use.sum())} static samples with a reference: nothing to diagnose")
    return DiagnosisData(rec.t_s, rec.ref, rec.xyz, rec.temp_c, rec.gref_mps2, rec.pose_id, rec.run_id, use)


# ============================================================================ model specification
@dataclass
class ModelSpec:
    """Declared degree + temperature scaling + the effects added so far, each with its hyper-parameter."""

    degree: int
    t_center_c: float
    t_scale_c: float
    effects: list[tuple[Effect, float | None]] = field(default_factory=list)

    def plus(self, effect: Effect, h: float | None) -> ModelSpec:
        return ModelSpec(self.degree, self.t_center_c, self.t_scale_c, [*self.effects, (effect, h)])

    @property
    def names(self) -> list[str]:
        return [e.name for e, _ in self.effects]


@dataclass
class Design:
    X: np.ndarray  # (N, p)
    G: np.ndarray  # (N, 3) reference (possibly re-aligned)
    valid: np.ndarray  # (N,) rows where X and G are finite and the effects are defined
    blocks: dict[str, slice]  # extra-column block of each effect
    n_base: int


def build_design(data: DiagnosisData, spec: ModelSpec) -> Design:
    """Regressors of eq. 28 on the corrected inputs, then the extra columns of the additive effects."""
    inp = Inputs(np.array(data.ref, float), np.array(data.xyz, float), np.array(data.temp_c, float),
                 np.array(data.t_s, float), np.array(data.gref, float), np.ones(len(data.t_s), bool))
    ordered = sorted(spec.effects, key=lambda eh: eh[0].stage)
    for eff, h in ordered:
        eff.transform(data, inp, h)
    tau = (inp.temp_c - spec.t_center_c) / spec.t_scale_c
    n_base = n_params(spec.degree)
    extra, blocks, p = [], {}, n_base
    for eff, h in ordered:
        c = eff.columns(data, inp, h)
        if c is not None:
            blocks[eff.name] = slice(p, p + c.shape[1])
            extra.append(c)
            p += c.shape[1]
    X = np.empty((len(tau), p))  # filled in place: no per-trial concatenation copy
    design_matrix(inp.psi, tau, spec.degree, out=X)  # writes the first n_base columns
    for c, sl in zip(extra, blocks.values(), strict=True):
        X[:, sl] = c
    valid = inp.valid & np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(inp.gref), axis=1)
    return Design(X, inp.gref, valid, blocks, n_base)


# ============================================================================ cross-validation
def pose_groups(data: DiagnosisData) -> np.ndarray:
    """Group label (N,) of each sample: one group per pose id (the same commanded orientation in
    several runs is held out together, as in ``thermal_fit``); samples in motion go with the pose the
    table moves to (``effects.motion_groups``)."""
    return data.group


def make_folds(groups: np.ndarray, rows: np.ndarray, k: int = 10, seed: int = 0) -> np.ndarray:
    """Fold index (N,) per sample (-1 outside ``rows``): whole pose groups are assigned to folds."""
    ug = np.unique(groups[rows])
    k = int(min(k, len(ug)))
    if k < 2:
        raise ValueError("need at least two pose groups for cross-validation")
    perm = np.random.default_rng(seed).permutation(len(ug))
    fold_of_group = np.empty(len(ug), int)
    fold_of_group[perm] = np.arange(len(ug)) % k
    out = np.full(len(groups), -1)
    idx = np.searchsorted(ug, groups[rows])
    out[rows] = fold_of_group[idx]
    return out


def _solve(xtx: np.ndarray, xtg: np.ndarray) -> np.ndarray:
    d = np.sqrt(np.clip(np.diag(xtx), 1e-300, None))
    s = xtx / np.outer(d, d)
    try:
        a = np.linalg.solve(s + 1e-13 * np.eye(len(d)), xtg / d[:, None])
    except np.linalg.LinAlgError:
        a = np.linalg.lstsq(s, xtg / d[:, None], rcond=1e-12)[0]
    return a / d[:, None]


@dataclass
class CvResult:
    heldout: np.ndarray  # (N, 3) held-out residual (NaN outside the evaluated rows)
    train_rss: np.ndarray  # (K,) weighted training RSS per fold
    A_full: np.ndarray  # (p, 3) coefficients on all rows
    fitted_full: np.ndarray  # (N, 3) in-sample prediction with A_full


def cross_validate(des: Design, rows: np.ndarray, folds: np.ndarray, weights: np.ndarray) -> CvResult:
    """K-fold CV by normal equations (per-fold sums subtracted from the total)."""
    X, G = des.X, des.G
    r = rows & des.valid
    K = int(folds[r].max()) + 1
    xtx = np.zeros((K, X.shape[1], X.shape[1]))
    xtg = np.zeros((K, X.shape[1], 3))
    gtg = np.zeros((K, 3))
    for f in range(K):
        m = r & (folds == f)
        Xf, Gf = X[m], G[m]
        xtx[f], xtg[f], gtg[f] = Xf.T @ Xf, Xf.T @ Gf, np.sum(Gf**2, axis=0)
    XtX, XtG = xtx.sum(0), xtg.sum(0)
    heldout = np.full(G.shape, np.nan)
    train_rss = np.zeros(K)
    for f in range(K):
        A = _solve(XtX - xtx[f], XtG - xtg[f])
        m = r & (folds == f)
        heldout[m] = G[m] - X[m] @ A
        Xt, Gt = XtX - xtx[f], XtG - xtg[f]
        gt = gtg.sum(0) - gtg[f]
        rss = gt - 2 * np.einsum("pi,pi->i", A, Gt) + np.einsum("pi,pq,qi->i", A, Xt, A)
        train_rss[f] = float(np.sum(rss * weights))
    A_full = _solve(XtX, XtG)
    fitted = X @ A_full
    return CvResult(heldout, train_rss, A_full, fitted)


def weighted_rss(des: Design, rows: np.ndarray, weights: np.ndarray) -> float:
    r = rows & des.valid
    X, G = des.X[r], des.G[r]  # one copy each, not three
    A = _solve(X.T @ X, X.T @ G)
    res = G - X @ A
    return float(np.sum(res**2 * weights))


# ============================================================================ noise floor, degree
def within_pose_sigma(res: np.ndarray, groups: np.ndarray, rows: np.ndarray, t_s: np.ndarray | None = None) -> np.ndarray:
    """Pooled within-pose standard deviation (3,) of a residual, m/s^2: the noise floor.

    With ``t_s`` a straight line in time is removed inside every pose first (dof n - 2 per pose), so
    that slow changes within a pose (temperature ramps, drift) do not count as noise.
    """
    r = rows & np.all(np.isfinite(res), axis=1)
    g = groups[r]
    x = res[r]
    ug, inv = np.unique(g, return_inverse=True)
    cnt = np.bincount(inv).astype(float)
    means = np.stack([np.bincount(inv, weights=x[:, j]) / cnt for j in range(3)], axis=1)
    dev = x - means[inv]
    n_par = 1
    if t_s is not None:
        t = t_s[r]
        tc = t - (np.bincount(inv, weights=t) / cnt)[inv]
        stt = np.bincount(inv, weights=tc * tc)[inv]
        ok = stt > 0
        for j in range(3):
            slope = np.bincount(inv, weights=tc * dev[:, j])[inv]
            dev[ok, j] -= (slope[ok] / stt[ok]) * tc[ok]
        n_par = 2
    dof = max(len(x) - n_par * len(ug), 1)
    return np.sqrt(np.sum(dev**2, axis=0) / dof)


def temperature_level_count(data: DiagnosisData) -> int:
    _, means = temperature_levels(data.temp_c[data.use])
    return max(len(means), 1)


def select_degree(data: DiagnosisData, folds: np.ndarray, max_degree: int = 4) -> tuple[int, list[dict[str, Any]]]:
    """Degree of eq. 28 with the lowest held-out RMSE (CV over pose groups), never >= the number of levels.

    Used with one or two temperature clusters (``thermal_fit.temperature_levels``): with one level it
    is the calibration's rule (held out by pose, degree 0); with a temperature *ramp* (which clusters
    into one or two levels) holding out whole levels cannot validate any temperature term, whereas
    poses recorded at many temperatures along the ramp can. With three or more discrete levels the
    calibration's own selection (held out by level, ``model_selection``) is used instead.
    """
    L = temperature_level_count(data)
    t = data.temp_c[data.use]
    c, s = temperature_scaling(t)
    table, best, best_score = [], 0, np.inf
    for n in range(0, max_degree + 1):
        if n >= L:
            table.append({"degree": n, "identified": False,
                          "note": f"not identified by {L} temperature level(s): not considered"})
            continue
        spec = ModelSpec(n, c, s)
        des = build_design(data, spec)
        try:
            cv = cross_validate(des, data.use, folds, np.ones(3))
        except NotIdentifiedError:
            continue
        r = data.use & des.valid
        ho = np.sqrt(np.nanmean(cv.heldout[r] ** 2, axis=0))
        ins = np.sqrt(np.mean((des.G[r] - cv.fitted_full[r]) ** 2, axis=0))
        score = float(np.sum(ho**2))
        table.append({"degree": n, "identified": True, "heldout_rmse_mps2": ho, "insample_rmse_mps2": ins,
                      "heldout_rmse_fs": ho / FULL_SCALE_MPS2, "insample_rmse_fs": ins / FULL_SCALE_MPS2})
        if score < best_score * (1 - 1e-3):
            best, best_score = n, score
    return best, table


def _degree_as_calibration(rec: Recording, data: DiagnosisData, max_degree: int) -> tuple[int, list[dict[str, Any]]]:
    """Degree chosen exactly as the calibration does (``model_selection.select_degree``: held out by
    temperature level with several levels, by pose with one), on the diagnosis samples."""
    from .model_selection import select_degree as calibration_select_degree

    sel = calibration_select_degree(rec, max_degree, usable=data.use & (data.pose_id >= 0))
    by_level = sel.n_levels >= 2
    table = []
    for sc in sel.scores:
        if not sc.identified:
            table.append({"degree": sc.degree, "identified": False, "note": sc.note})
            continue
        ho = sc.held_out_level if by_level else sc.held_out_pose
        table.append({"degree": sc.degree, "identified": True, "heldout_rmse_mps2": ho, "insample_rmse_mps2": sc.in_sample,
                      "heldout_rmse_fs": ho / FULL_SCALE_MPS2, "insample_rmse_fs": sc.in_sample / FULL_SCALE_MPS2,
                      "note": sc.note or sel.criterion})
    if sel.chosen_degree is None:
        raise NotIdentifiedError("no degree of eq. 28 could be validated on held-out data: " + "; ".join(sel.notes))
    return sel.chosen_degree, table


# ============================================================================ candidate evaluation
@dataclass
class CandidateResult:
    name: str
    title: str
    applicable: bool
    reason: str = ""
    hyper: float | None = None
    hyper_profile: list[tuple[float, float]] = field(default_factory=list)  # (h, weighted RSS)
    heldout_rmse: np.ndarray | None = None  # (3,)
    base_heldout_rmse: np.ndarray | None = None  # (3,)
    rel_gain: float = 0.0  # fraction of the weighted held-out MSE removed
    p_value: float = 1.0
    n_groups: int = 0
    corr_with_residual: np.ndarray | None = None  # (3,)
    n_params: int = 0
    significant: bool = False
    detail: str = ""
    delta: np.ndarray | None = None  # (N, 3) change of the in-sample prediction vs the current model
    heldout: np.ndarray | None = None  # (N, 3)
    cross_correlation_delay_s: float | None = None


def _group_mse(res: np.ndarray, groups: np.ndarray, rows: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r = rows & np.all(np.isfinite(res), axis=1)
    ug, inv = np.unique(groups[r], return_inverse=True)
    e = np.sum(res[r] ** 2 * weights, axis=1)
    return ug, np.bincount(inv, weights=e) / np.bincount(inv)


def paired_gain_test(res0: np.ndarray, res1: np.ndarray, groups: np.ndarray, rows: np.ndarray,
                     weights: np.ndarray) -> tuple[float, float, int]:
    """(relative gain, one-sided p-value, groups) of held-out residual res1 over res0, paired by pose group."""
    r = rows & np.all(np.isfinite(res0), axis=1) & np.all(np.isfinite(res1), axis=1)
    _, m0 = _group_mse(res0, groups, r, weights)
    _, m1 = _group_mse(res1, groups, r, weights)
    d = m0 - m1
    tot0 = float(np.sum(res0[r] ** 2 * weights))
    gain = (tot0 - float(np.sum(res1[r] ** 2 * weights))) / tot0 if tot0 > 0 else 0.0
    if len(d) < 5 or np.all(d == 0):
        return gain, 1.0, len(d)
    p = float(stats.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue)
    return gain, p, len(d)


def cross_correlation_delay(data: DiagnosisData, fitted: np.ndarray, max_lag: int = 12) -> float:
    """Delay (s) of the model output against the (gap-filled) reference by cross-correlation of their
    first differences (finddelay of D'Emilia et al. 2019), with parabolic sub-sample interpolation."""
    best_lag, best_val, vals = 0, -np.inf, {}
    a = np.diff(np.nan_to_num(fitted), axis=0)
    g = np.diff(np.nan_to_num(data.gref_filled), axis=0)
    same_run = data.run_id[1:] == data.run_id[:-1]
    a[~same_run], g[~same_run] = 0.0, 0.0
    for lag in range(0, max_lag + 1):
        v = float(np.sum(a[lag:] * g[: len(g) - lag]))
        vals[lag] = v
        if v > best_val:
            best_lag, best_val = lag, v
    frac = 0.0
    if 0 < best_lag < max_lag:
        y0, y1, y2 = vals[best_lag - 1], vals[best_lag], vals[best_lag + 1]
        den = y0 - 2 * y1 + y2
        frac = 0.5 * (y0 - y2) / den if den != 0 else 0.0
    return (best_lag + frac) * data.dt_s


class Evaluator:
    """Evaluates specs on one recording with fixed folds, rows and noise weights (cached designs)."""

    def __init__(self, data: DiagnosisData, folds: np.ndarray, weights: np.ndarray, groups: np.ndarray) -> None:
        self.data, self.folds, self.weights, self.groups = data, folds, weights, groups
        self.rows = data.use & (folds >= 0)

    def cv(self, spec: ModelSpec) -> tuple[Design, CvResult]:
        des = build_design(self.data, spec)
        return des, cross_validate(des, self.rows, self.folds, self.weights)

    def fit_hyper(self, spec: ModelSpec, eff: Effect) -> tuple[float | None, np.ndarray, list[tuple[float, float]]]:
        """Hyper-parameter of ``eff`` added to ``spec``: nested grid choice per fold for the held-out
        residual, and grid + bounded refinement on all rows for the final value."""
        grid = eff.hyper_grid(self.data)
        if grid is None:
            _, cvr = self.cv(spec.plus(eff, None))
            return None, cvr.heldout, []
        K = int(self.folds[self.rows].max()) + 1
        per_h, profile = [], []
        for h in grid:
            des, cvr = self.cv(spec.plus(eff, float(h)))
            per_h.append((cvr.train_rss, cvr.heldout, des.valid))
            profile.append((float(h), float(np.sum(cvr.train_rss) / max(K - 1, 1))))
        heldout = np.full((len(self.data.t_s), 3), np.nan)
        for f in range(K):
            j = int(np.argmin([p[0][f] for p in per_h]))
            m = self.rows & (self.folds == f)
            heldout[m] = per_h[j][1][m]
        # final value on all rows: best grid point then bounded scalar refinement between its neighbours
        j = int(np.argmin([p[1] for p in profile]))
        lo = grid[max(j - 1, 0)]
        hi = grid[min(j + 1, len(grid) - 1)]
        h_best = float(grid[j])
        if hi > lo:
            def obj(h: float) -> float:
                return weighted_rss(build_design(self.data, spec.plus(eff, float(h))), self.rows, self.weights)

            res = optimize.minimize_scalar(obj, bounds=(float(lo), float(hi)), method="bounded",
                                           options={"xatol": 1e-3 * (hi - lo), "maxiter": 25})
            if res.success and res.fun <= obj(h_best):
                h_best = float(res.x)
        if eff.hyper_null is not None:
            # parsimony: keep the null value unless moving away from it is a significant improvement,
            # judged with pose groups as the independent units (likelihood ratio ~ chi^2(1), 1 %)
            rss_best = weighted_rss(build_design(self.data, spec.plus(eff, h_best)), self.rows, self.weights)
            rss_null = weighted_rss(build_design(self.data, spec.plus(eff, eff.hyper_null)), self.rows, self.weights)
            n_groups = len(np.unique(self.groups[self.rows]))
            if (rss_null - rss_best) / max(rss_best / n_groups, 1e-300) < stats.chi2.ppf(0.99, 1):
                h_best = float(eff.hyper_null)
        return h_best, heldout, profile

    def evaluate(self, spec: ModelSpec, eff: Effect, base_heldout: np.ndarray, base_fitted: np.ndarray,
                 base_G: np.ndarray | None = None) -> CandidateResult:
        ok, why = eff.applicable(self.data)
        out = CandidateResult(eff.name, eff.title, ok, why)
        self.base_G = self.data.gref if base_G is None else base_G
        if not ok:
            return out
        h, heldout, profile = self.fit_hyper(spec, eff)
        des, cvr = self.cv(spec.plus(eff, h))
        r = self.rows & des.valid & np.all(np.isfinite(heldout), axis=1) & np.all(np.isfinite(base_heldout), axis=1)
        gain, p, ng = paired_gain_test(base_heldout, heldout, self.groups, r, self.weights)
        # what the candidate explains of the current residual (reference changes count too: delay, TIA)
        delta = (self.base_G - des.G) + (cvr.fitted_full - base_fitted)
        corr = np.array([_corr(base_heldout[r, j], delta[r, j]) for j in range(3)])
        out.hyper, out.hyper_profile = h, profile
        out.heldout_rmse = np.sqrt(np.mean(heldout[r] ** 2, axis=0))
        out.base_heldout_rmse = np.sqrt(np.mean(base_heldout[r] ** 2, axis=0))
        out.rel_gain, out.p_value, out.n_groups = gain, p, ng
        out.corr_with_residual = corr
        out.n_params = 3 * eff.n_columns + (0 if h is None else 1)
        coeff = cvr.A_full[des.blocks[eff.name]].T if eff.name in des.blocks else None
        out.detail = eff.describe(h, coeff)
        out.delta, out.heldout = delta, heldout
        if eff.name == "channel_delay":
            out.cross_correlation_delay_s = cross_correlation_delay(self.data, base_fitted)
        return out


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    if a.size < 3 or np.std(a) == 0 or np.std(b) == 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


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


@dataclass
class ResidualStructure:
    significant: bool
    verdict: str
    heldout_rmse: np.ndarray
    noise_floor: np.ndarray
    ratio: np.ndarray
    pose_chi2_p: np.ndarray  # (3,)
    excess_rms: np.ndarray  # (3,) sqrt(heldout^2 - floor^2)
    per_pose: list[dict[str, Any]]  # pose id, n, mean residual (3,), z (3,)
    pose_mean_rms: np.ndarray  # (3,)
    corr_time: np.ndarray
    corr_temperature: np.ndarray
    orientation_r2: np.ndarray  # (3,) pose-mean residual explained by quadratic in the reference direction
    lag1_autocorr: np.ndarray
    serial_corr_pose_means: np.ndarray  # (3,) correlation of consecutive pose means in time order (slow wander -> ~1)


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

    @property
    def ranked(self) -> list[CandidateResult]:
        return self.steps[0].candidates if self.steps else []


def diagnose(rec: Recording | DiagnosisData, *, static: str = "table", max_degree: int = 4, folds: int = 10,
             alpha: float = 0.01, min_rel_gain: float = 0.02, max_effects: int = 3, library: tuple[Effect, ...] = LIBRARY,
             degree: int | None = None, sensor_id: str = "unknown", seed: int = 0,
             progress: Callable[[str], None] | None = None) -> DiagnosisResult:
    """Run the whole diagnosis on a recording (see the module docstring). ``progress`` (optional) is called
    with the candidate's name after each candidate evaluation (the CLI's progress bar)."""
    data = rec if isinstance(rec, DiagnosisData) else prepare_data(rec, static)
    groups = pose_groups(data)
    fold = make_folds(groups, data.use, folds, seed)
    n_levels = temperature_level_count(data)
    if isinstance(rec, Recording) and n_levels >= 3:
        # discrete chamber levels: exactly the calibration's choice (held out by temperature level)
        sel_degree, degree_table = _degree_as_calibration(rec, data, max_degree)
    else:
        sel_degree, degree_table = select_degree(data, fold, max_degree)
    if degree is not None:
        if degree >= n_levels:
            raise NotIdentifiedError(f"degree {degree} is not identified by {n_levels} temperature level(s)")
        sel_degree = degree
    c, s = temperature_scaling(data.temp_c[data.use])
    spec = ModelSpec(sel_degree, c, s)

    # declared model, noise floor and weights
    des0 = build_design(data, spec)
    cv0 = cross_validate(des0, data.use, fold, np.ones(3))
    rows = data.use & des0.valid & (data.pose_id >= 0)  # the floor: scatter within poses, not during moves
    noise = within_pose_sigma(des0.G - cv0.fitted_full, groups, rows, data.t_s)
    weights = 1.0 / np.maximum(noise, 1e-12) ** 2
    ev = Evaluator(data, fold, weights, groups)
    base_heldout, base_fitted, base_G = cv0.heldout, cv0.fitted_full, des0.G
    residual_before = base_heldout.copy()

    steps: list[StepResult] = []
    remaining = [e for e in library]
    while remaining and len(spec.effects) < max_effects:
        results = []
        for e in remaining:
            results.append(ev.evaluate(spec, e, base_heldout, base_fitted, base_G))
            if progress is not None:
                progress(e.name)
        tested = [r for r in results if r.applicable]
        alpha_each = alpha / max(len(tested), 1)
        for r in tested:
            r.significant = r.p_value < alpha_each and r.rel_gain >= min_rel_gain
        results.sort(key=lambda r: (not r.applicable, -r.rel_gain))
        sig = [r for r in results if r.significant]
        conf = _confounding(ev, spec, sig, alpha_each, min_rel_gain) if len(sig) >= 2 else []
        chosen = sig[0].name if sig else None
        steps.append(StepResult(len(steps) + 1, spec.names, results, chosen, alpha_each, conf))
        if chosen is None:
            break
        eff = next(e for e in remaining if e.name == chosen)
        spec = spec.plus(eff, sig[0].hyper)
        remaining = [e for e in remaining if e.name != chosen]
        des_c, cv_c = ev.cv(spec)
        base_heldout, base_fitted, base_G = cv_c.heldout, cv_c.fitted_full, des_c.G

    # final model
    des_f, cv_f = ev.cv(spec)
    rows_f = data.use & des_f.valid & (fold >= 0)
    confounded = {st.chosen: [c.b if c.a == st.chosen else c.a for c in st.confounding
                              if c.verdict == "confounded" and st.chosen in (c.a, c.b)] for st in steps if st.chosen}
    confounded = {k: v for k, v in confounded.items() if v}
    cal, base_cal, added = _calibration_from(spec, des_f, cv_f, data, noise, sensor_id, confounded)
    consistency = _consistency(cal, data, des_f, cv_f, rows_f)
    r_eval = rows_f & np.all(np.isfinite(residual_before), axis=1) & np.all(np.isfinite(cv_f.heldout), axis=1)
    before_ho = np.sqrt(np.mean(residual_before[r_eval] ** 2, axis=0))
    after_ho = np.sqrt(np.mean(cv_f.heldout[r_eval] ** 2, axis=0))
    before_in = np.sqrt(np.mean((des0.G - cv0.fitted_full)[r_eval] ** 2, axis=0))
    after_in = np.sqrt(np.mean((des_f.G - cv_f.fitted_full)[r_eval] ** 2, axis=0))
    structure = residual_structure(data, cv_f.heldout, r_eval, groups, noise, alpha)
    moving = _moving_residual(data, cal)
    return DiagnosisResult(
        data=data, degree=sel_degree, degree_table=degree_table, n_levels=n_levels, noise_floor=noise,
        before_heldout_rmse=before_ho, before_insample_rmse=before_in, after_heldout_rmse=after_ho,
        after_insample_rmse=after_in, steps=steps, added=added, calibration=cal, base_calibration=base_cal,
        residual_before=residual_before, residual_after=cv_f.heldout, structure=structure,
        consistency_max_abs_mps2=consistency, n_static=int(r_eval.sum()), n_groups=len(np.unique(groups[r_eval])),
        moving_residual_rms=moving,
        settings={"static": static if not isinstance(rec, DiagnosisData) else "given", "folds": int(fold.max()) + 1,
                  "alpha": alpha, "min_rel_gain": min_rel_gain, "max_effects": max_effects, "seed": seed,
                  "time_label": time_axis_label(rec.metadata) if isinstance(rec, Recording) else "time [s]"})


def _confounding(ev: Evaluator, spec: ModelSpec, sig: list[CandidateResult], alpha_each: float,
                 min_rel_gain: float) -> list[Confounding]:
    """Pairwise: does each significant candidate still gain on top of the other one?"""
    lib = {e.name: e for e in LIBRARY}
    out = []
    top = sig[:4]
    for i in range(len(top)):
        for j in range(i + 1, len(top)):
            a, b = top[i], top[j]
            ea, eb = lib[a.name], lib[b.name]
            # each on top of the other (the added one's hyper-parameter searched again, nested), compared
            # with the other alone at its final hyper-parameter, as the forward selection does
            a_ho = ev.cv(spec.plus(ea, a.hyper))[1].heldout
            b_ho = ev.cv(spec.plus(eb, b.hyper))[1].heldout
            _, ho_b_on_a, _ = ev.fit_hyper(spec.plus(ea, a.hyper), eb)
            _, ho_a_on_b, _ = ev.fit_hyper(spec.plus(eb, b.hyper), ea)
            rows = ev.rows.copy()
            for arr in (a_ho, b_ho, ho_b_on_a, ho_a_on_b):
                rows &= np.all(np.isfinite(arr), axis=1)
            g_b, p_b = paired_gain_test(a_ho, ho_b_on_a, ev.groups, rows, ev.weights)[:2]
            g_a, p_a = paired_gain_test(b_ho, ho_a_on_b, ev.groups, rows, ev.weights)[:2]
            r = rows & np.all(np.isfinite(a.delta), axis=1) & np.all(np.isfinite(b.delta), axis=1)
            cc = _corr((a.delta[r] * np.sqrt(ev.weights)).ravel(), (b.delta[r] * np.sqrt(ev.weights)).ravel())
            b_adds = p_b < alpha_each and g_b >= min_rel_gain
            a_adds = p_a < alpha_each and g_a >= min_rel_gain
            if a_adds and b_adds:
                verdict = "both"
            elif a_adds or b_adds:
                verdict = f"{a.name} explains {b.name}" if a_adds else f"{b.name} explains {a.name}"
            else:
                # neither adds beyond the other: does one fit significantly better head to head?
                g_ab, p_ab = paired_gain_test(b_ho, a_ho, ev.groups, rows, ev.weights)[:2]
                g_ba, p_ba = paired_gain_test(a_ho, b_ho, ev.groups, rows, ev.weights)[:2]
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
    M = np.transpose(A[: 3 * (n + 1)].reshape(n + 1, 3, 3), (0, 2, 1))
    b = A[3 * (n + 1): 4 * (n + 1)]
    t = data.temp_c[data.use]
    rng = (float(np.min(t)), float(np.max(t)))
    terms, added = [], []
    for eff, h in sorted(spec.effects, key=lambda eh: eh[0].stage):
        coeff = A[des.blocks[eff.name]].T if eff.name in des.blocks else None
        terms.extend(eff.make_terms(h, coeff, data))
        added.append((eff.name, h, eff.describe(h, coeff)))
    fit = {"tool": "fbg-accel-calib diagnose", "degree": n, "added_effects": [a[0] for a in added],
           "hyper_parameters": {a[0]: a[1] for a in added}}
    if confounded:
        fit["confounded_with"] = confounded
    delay = [h for e, h in spec.effects if e.name == "channel_delay"]
    if delay:
        fit["channel_delay_s"] = float(delay[0])  # applied to time stamps, not to accelerations
    cal = ThermalCalibration(M=M, b=b, temperature_range_c=rng, sensor_id=sensor_id, t_center_c=spec.t_center_c,
                             t_scale_c=spec.t_scale_c, noise_sigma_mps2=noise, fit=fit, corrections=terms)
    base = ThermalCalibration(M=M, b=b, temperature_range_c=rng, sensor_id=sensor_id, t_center_c=spec.t_center_c,
                              t_scale_c=spec.t_scale_c, noise_sigma_mps2=noise)
    return cal, base, added


def _consistency(cal: ThermalCalibration, data: DiagnosisData, des: Design, cv: CvResult, rows: np.ndarray) -> float:
    """Max |apply_counts - fit prediction| over the static rows, per run streamed with one state."""
    worst = 0.0
    for r in np.unique(data.run_id):
        idx = data.run_id == r
        out = cal.apply_counts(data.ref[idx], data.xyz[idx], data.temp_c[idx], data.t_s[idx], cal.new_state())
        m = rows[idx]
        if m.any():
            worst = max(worst, float(np.nanmax(np.abs(out[m] - cv.fitted_full[idx][m]))))
    return worst


def _moving_residual(data: DiagnosisData, cal: ThermalCalibration) -> np.ndarray | None:
    """RMS (3,) of calibrated output minus the gap-filled reference on samples not used (moving, settling)."""
    m = ~data.use & np.all(np.isfinite(data.gref_filled), axis=1)
    if m.sum() < 3:
        return None
    out = np.full((len(data.t_s), 3), np.nan)
    for r in np.unique(data.run_id):
        idx = data.run_id == r
        out[idx] = cal.apply_counts(data.ref[idx], data.xyz[idx], data.temp_c[idx], data.t_s[idx], cal.new_state())
    d = out[m] - data.gref_filled[m]
    d = d[np.all(np.isfinite(d), axis=1)]
    return np.sqrt(np.mean(d**2, axis=0)) if len(d) else None


def _lag1(res: np.ndarray, groups: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Pooled lag-1 autocorrelation (3,) of within-pose deviations (consecutive samples of one pose)."""
    idx = np.flatnonzero(rows)
    g = groups[idx]
    x = res[idx]
    _, inv = np.unique(g, return_inverse=True)
    cnt = np.bincount(inv)
    means = np.stack([np.bincount(inv, weights=x[:, j]) / cnt for j in range(3)], axis=1)
    dev = x - means[inv]
    same = (g[1:] == g[:-1]) & (np.diff(idx) == 1)
    if same.sum() < 3:
        return np.zeros(3)
    num = np.sum(dev[1:][same] * dev[:-1][same], axis=0)
    den = np.sum(dev**2, axis=0)
    return np.clip(num / np.maximum(den, 1e-300), -0.99, 0.99)


def residual_structure(data: DiagnosisData, res: np.ndarray, rows: np.ndarray, groups: np.ndarray, noise: np.ndarray,
                       alpha: float = 0.01, ratio_limit: float = 1.1) -> ResidualStructure:
    """Is there a significant residual left, and what does it depend on?

    Test: pose means of the held-out residual against what the noise alone gives, chi^2 with the
    effective sample count of each pose (lag-1 autocorrelation of the within-pose residual).
    Significant = p < ``alpha`` on some axis AND the held-out RMSE exceeds ``ratio_limit`` x floor.
    """
    r = rows & np.all(np.isfinite(res), axis=1)
    rho = _lag1(res, groups, r)
    ug, inv = np.unique(groups[r], return_inverse=True)
    cnt = np.bincount(inv)
    x = res[r]
    means = np.stack([np.bincount(inv, weights=x[:, j]) / cnt for j in range(3)], axis=1)
    neff = np.clip(cnt[:, None] * (1 - rho[None, :]) / (1 + rho[None, :]), 1.0, cnt[:, None])
    z = means * np.sqrt(neff) / np.maximum(noise, 1e-12)
    chi = np.sum(z**2, axis=0)
    p = stats.chi2.sf(chi, df=len(ug))
    ho = np.sqrt(np.mean(x**2, axis=0))
    ratio = ho / np.maximum(noise, 1e-12)
    excess = np.sqrt(np.maximum(ho**2 - noise**2, 0.0))
    significant = bool(np.any((p < alpha) & (ratio > ratio_limit)))
    t_mean = np.bincount(inv, weights=data.t_s[r]) / cnt
    temp_mean = np.bincount(inv, weights=data.temp_c[r]) / cnt
    g_mean = np.stack([np.bincount(inv, weights=data.gref[r][:, j]) / cnt for j in range(3)], axis=1)
    corr_t = np.array([_spearman(t_mean, means[:, j]) for j in range(3)])
    corr_T = (np.array([_spearman(temp_mean, means[:, j]) for j in range(3)]) if np.ptp(temp_mean) > 0.05
              else np.full(3, np.nan))  # isothermal: no temperature dependence can be seen
    order = np.argsort(t_mean)
    serial = np.array([_corr(means[order[1:], j], means[order[:-1], j]) for j in range(3)])
    u = g_mean / np.maximum(np.linalg.norm(g_mean, axis=1, keepdims=True), 1e-12)
    Q = np.column_stack([np.ones(len(u)), u, u[:, 0] * u[:, 1], u[:, 0] * u[:, 2], u[:, 1] * u[:, 2],
                         u[:, 0] ** 2 - u[:, 1] ** 2, 3 * u[:, 2] ** 2 - 1])
    r2 = np.zeros(3)
    if len(u) > Q.shape[1] + 2:
        for j in range(3):
            coef = np.linalg.lstsq(Q, means[:, j], rcond=None)[0]
            tot = np.sum((means[:, j] - means[:, j].mean()) ** 2)
            r2[j] = 1 - np.sum((means[:, j] - Q @ coef) ** 2) / tot if tot > 0 else 0.0
    per_pose = [{"pose": int(ug[i]), "n": int(cnt[i]), "mean_mps2": means[i], "z": z[i],
                 "gref_mps2": g_mean[i], "t_s": float(t_mean[i]), "temp_c": float(temp_mean[i])} for i in range(len(ug))]
    per_pose.sort(key=lambda d: -float(np.max(np.abs(d["z"]))))
    if significant:
        axes = [a for j, a in enumerate("xyz") if p[j] < alpha and ratio[j] > ratio_limit]
        verdict = (f"significant unexplained residual on axis {', '.join(axes)}: held-out RMSE "
                   + ", ".join(f"{a} {ho[j]:.3g} m/s^2 = {ratio[j]:.2f}x floor" for j, a in enumerate("xyz"))
                   + f"; pose means differ beyond noise (chi^2 p = {', '.join(f'{v:.1e}' for v in p)})")
    else:
        verdict = ("no significant unexplained residual: held-out RMSE within "
                   + ", ".join(f"{ratio[j]:.2f}x" for j in range(3)) + " of the noise floor")
    return ResidualStructure(significant, verdict, ho, noise, ratio, p, excess, per_pose,
                             np.sqrt(np.mean(means**2, axis=0)), corr_t, corr_T, r2, rho, serial)


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return 0.0
    return float(stats.spearmanr(a, b).statistic)
