"""What remains after the chosen model: is the held-out residual beyond the noise, and what does it depend on
(``residual_structure``)?
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from ..fit.thermal_fit import jacobi_solve
from .data import DiagnosisData, column_rms, direction_labels, finite_rows, group_index

# ============================================================================ data preparation
from .floor import (
    MIN_MEAN_DOF,
    VisitNoise,
)
from .search import (
    _corr,
)
from .visit_covariance import (
    DiagonalCovariance,
    HeldoutCovariance,
    RowCovariance,
    as_covariance,
    squared_correlation_sum,
)

# Bias instability of paper Table 2 (§4.4; ../shared/docs/sensor_facts.md: min Allan deviation / 0.664), x / y / z, mg
TABLE2_BIAS_INSTABILITY_MG = np.array([0.54, 1.10, 1.87])
# The largest slow error of a visit mean the residual test's null hypothesis holds (m/s^2): ten times Table 2's bias
# instability. A flicker wander of Allan floor 0.664 B over 10^4 of its correlation times has a standard deviation of
# about 1.7 B; the rest is margin for what else moves a visit mean slowly on a real sensor (the simulator's clean ramps
# at 10 Hz: up to 4.7x B on x, 2.5x on y, 1.7x on z, median). Revisits that differ by more are evidence, not noise.
SLOW_ERROR_BOUND_MPS2 = 10.0 * TABLE2_BIAS_INSTABILITY_MG * 9.80665e-3
SMALL_RATIO = 1.1  # a significant residual whose held-out RMSE is within this x the per-sample floor is "small"


@dataclass
class ResidualStructure:
    significant: bool  # the test's: chi^2 / F p < alpha on some axis, whatever the size
    verdict: str
    heldout_rmse: np.ndarray
    noise_floor: np.ndarray
    ratio: np.ndarray
    pose_chi2_p: np.ndarray  # (3,)
    excess_rms: np.ndarray  # (3,) sqrt(heldout^2 - floor^2)
    per_pose: list[dict[str, Any]]  # pose id, n, mean residual (3,), z (3,), mean time (s from the first sample)
    pose_mean_rms: np.ndarray  # (3,)
    corr_time: np.ndarray
    corr_temperature: np.ndarray
    orientation_r2: np.ndarray  # (3,) pose-mean residual explained by quadratic in the reference direction
    lag1_autocorr: np.ndarray  # (3,) lag-1 autocorrelation of the noise (the floor's estimate)
    serial_corr_pose_means: np.ndarray  # (3,) correlation of consecutive pose means in time order (slow wander -> ~1)
    noise_corr_samples: np.ndarray  # (3,) integrated correlation time of the noise, samples (VisitNoise)
    noise_mean_dof: np.ndarray  # (3,) degrees of freedom of the variance of a visit mean (VisitNoise.mean_dof)
    small: bool = False  # significant, but on no significant axis is the held-out RMSE above ratio_limit x floor
    # visits of one direction of gravity (``effects.direction_labels``) against their direction's mean: p (3,) of the
    # chi^2 / F test as above; the visits in directions visited more than once; the median time span of those
    # directions' visits (s). Small p: the residual depends on something other than the direction of gravity in the
    # sensor (the table's angles: its geometry, a cable it drags; or time, over that span)
    direction_chi2_p: np.ndarray = field(default_factory=lambda: np.ones(3))
    direction_repeat_visits: int = 0
    direction_span_s: float = 0.0
    # the same split in two: visits of one pose id (the same table angles) against each other, which only time can
    # set apart, and the poses of one direction (other table angles) against each other; p (3,) each, and the median
    # time span (s) of the poses visited more than once
    same_pose_chi2_p: np.ndarray = field(default_factory=lambda: np.ones(3))
    other_pose_chi2_p: np.ndarray = field(default_factory=lambda: np.ones(3))
    same_pose_span_s: float = 0.0
    # noise slower than a visit, in the test's null hypothesis (``slow_visit_error``): standard deviation (3,) m/s^2 of
    # a visit mean's slow error, its degrees of freedom (3,), and the revisits it rests on (0: not identifiable)
    slow_sigma: np.ndarray = field(default_factory=lambda: np.zeros(3))
    slow_dof: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    slow_revisits: int = 0


@dataclass
class HeldoutMeanNull:
    """The covariance of the held-out visit means of the residual under the null hypothesis (the model is right and
    the floor's noise is all there is; ``heldout_mean_covariance``): ``visits`` (V,) the held-out visit ids, ``cov``
    (3,) per axis the (V, V) covariance in (m/s^2)^2; ``slow`` the (V, V) one of a slow error of unit variance, one
    value per visit, independent between visits (``SlowVisitError``), through the same cross-validation: the held-out
    visit's own value less what the coefficients fitted on the other folds took of theirs (dimensionless; None: not
    worked out). Each is given by its factors (``visit_covariance.HeldoutCovariance``: V x p arrays), never as a
    V x V array (48 MiB each at the 2500 visits of 10^6 samples)."""

    visits: np.ndarray
    cov: tuple[HeldoutCovariance, ...]
    slow: HeldoutCovariance | None = None

    def for_visits(self, ug: np.ndarray, diag: np.ndarray) -> tuple[list[RowCovariance], RowCovariance]:
        """The three axes' covariances of the visits ``ug`` (a visit it does not hold gets ``diag`` (len(ug), 3)
        alone), and the slow error's (a visit it does not hold: 1 alone). For its own visits, its own."""
        unit = np.ones(len(ug))
        if np.array_equal(ug, self.visits):
            return list(self.cov), (self.slow if self.slow is not None else DiagonalCovariance(unit))
        pos = np.searchsorted(self.visits, ug)
        known = (pos < len(self.visits)) & (self.visits[np.minimum(pos, len(self.visits) - 1)] == ug)
        pos = np.where(known, pos, 0)
        slow = (self.slow.for_visits(pos, known, unit) if self.slow is not None
                else DiagonalCovariance(unit))
        return [c.for_visits(pos, known, diag[:, j]) for j, c in enumerate(self.cov)], slow

    def dense(self) -> np.ndarray:
        """(3, V, V) the axes' covariances as arrays (for small V: checks and tests)."""
        return np.stack([c.dense() for c in self.cov])


@dataclass
class HeldoutVisitSums:
    """What ``heldout_mean_null`` needs of the final design (N, p): its rows summed by visit, small beside it (the
    design is let go before the (V, V) covariances are made: ``final_model``)."""

    visits: np.ndarray  # (V,) the held-out visit ids
    own: np.ndarray  # (V,) each held-out visit's index among the fitted visits
    counts: np.ndarray  # (Va,) fitted samples of each fitted visit
    fold: np.ndarray  # (Va,) each fitted visit's fold (-2: never held out)
    S: np.ndarray  # (Va, p) each fitted visit's design rows summed
    xbar: np.ndarray  # (V, p) each held-out visit's mean design row


def heldout_visit_sums(X: np.ndarray, fit_rows: np.ndarray, eval_rows: np.ndarray, groups: np.ndarray,
                       fold: np.ndarray) -> HeldoutVisitSums | None:
    """The visit sums of ``X`` (N, p) that ``heldout_mean_null`` works from (arguments as ``heldout_mean_covariance``);
    None when there is nothing to hold out."""
    fa = fit_rows & (groups >= 0)
    ua, inv_a = group_index(groups[fa])
    rb = eval_rows & (groups >= 0) & (fold >= 0)
    ub, inv_b = group_index(groups[rb])
    if not len(ua) or not len(ub):
        return None
    own = np.minimum(np.searchsorted(ua, ub), len(ua) - 1)  # each held-out visit among the fitted ones
    if not np.array_equal(ua[own], ub):
        return None
    fold_a = np.zeros(len(ua), int)
    fold_a[inv_a] = fold[fa]
    cnt_b = np.bincount(inv_b).astype(float)
    return HeldoutVisitSums(ub, own, np.bincount(inv_a).astype(float), fold_a, _visit_sums(X, fa, inv_a, len(ua)),
                            _visit_sums(X, rb, inv_b, len(ub)) / cnt_b[:, None])


def heldout_mean_covariance(X: np.ndarray, fit_rows: np.ndarray, eval_rows: np.ndarray, groups: np.ndarray,
                            fold: np.ndarray, fold_xtx: np.ndarray, XtX: np.ndarray,
                            noise_model: VisitNoise) -> HeldoutMeanNull | None:
    """Covariance of the held-out residual's visit means under the null hypothesis, per axis (V, V) given by its
    factors (``HeldoutMeanNull``), V the visits of ``eval_rows`` (held out, fold >= 0).

    A held-out visit v of fold k is predicted by the coefficients fitted on the other folds' rows, whose error is
    G_k t_k with G_k = (X^T X - X_k^T X_k)^-1 and t_k = sum_{u not in k} X_u^T e_u (e_u the noise of visit u's rows;
    visits never held out, fold -2, are in every training set). Its mean residual is m_v = ebar_v - a_v^T t_k, a_v =
    G_k x_v (x_v its mean design row, ebar_v its mean noise), so
    Cov(m_v, m_w) = var_v [v = w] - (a_v . s_w) var_w [k(w) != k(v)] - (a_w . s_v) var_v [k(v) != k(w)]
    + a_v^T Cov(t_k(v), t_k(w)) a_w, with Cov(t_k, t_l) = sum of B_u over the visits in neither fold, B_u = Cov(X_u^T
    e_u) = var_u s_u s_u^T + n_u var_u (X_u^T X_u - s_u s_u^T / n_u), s_u = X_u^T 1 and var_u the noise model's
    variance of the visit's mean (``VisitNoise.mean_variance``: the null hypothesis, not the residual). B_u is exact
    for white noise and for a design constant within a visit; its within-visit part takes n_u var_u as the median
    over the visits (the fold's X^T X carries that part summed). The diagonal adds to a visit mean's variance what the
    coefficients' error gives it (36 coefficients fitted on 42 visits: ~a third); off the diagonal, the held-out
    visits of one fold share one set of coefficients and so one error, and a visit of another fold was in their
    training set: the sum of squared z over a campaign's visits is more dispersed than chi^2(V) (``visit_mean_test``).
    ``fit_rows``: the fitted samples (X finite there, ``fold`` != -1); ``fold_xtx`` (K, p, p) X^T X of each fold's
    fitted rows, ``XtX`` (p, p) over all of them (as ``cross_validate`` sums them). None when there is nothing to hold
    out or a training set is singular."""
    sums = heldout_visit_sums(X, fit_rows, eval_rows, groups, fold)
    return None if sums is None else heldout_mean_null(sums, fold_xtx, XtX, noise_model)


def heldout_mean_null(sums: HeldoutVisitSums, fold_xtx: np.ndarray, XtX: np.ndarray,
                      noise_model: VisitNoise) -> HeldoutMeanNull | None:
    """``heldout_mean_covariance`` from the design's visit sums (``heldout_visit_sums``)."""
    ub, own, cnt_a, fold_a, S, xbar = sums.visits, sums.own, sums.counts, sums.fold, sums.S, sums.xbar
    p = S.shape[1]
    fold_b = fold_a[own]
    folds = np.unique(fold_a)  # the held-out folds and -2 (never held out)
    at_a = [fold_a == k for k in folds]
    kb = np.searchsorted(folds, fold_b)
    xtx = np.stack([fold_xtx[k] if k >= 0 else XtX - fold_xtx.sum(axis=0) for k in folds])  # (F, p, p)
    a = np.empty((len(ub), p))  # G_k x_v
    for i in range(len(folds)):
        at = kb == i
        if not at.any():
            continue
        Ak = XtX - xtx[i]
        try:  # Jacobi-scaled, as the fit solves it; a regressor the training set lacks: singular, not zero division
            a[at] = jacobi_solve(Ak, xbar[at].T, min_diagonal=1e-300).T
        except np.linalg.LinAlgError:
            return None
    var = noise_model.mean_variance(cnt_a.astype(int))  # (Va, 3)
    Sn = np.stack([(S[at] / cnt_a[at, None]).T @ S[at] for at in at_a])  # (F, p, p) sum of s_u s_u^T / n_u
    s_own, cov = S[own], []  # the three axes' noise, then a slow error of unit variance per visit
    for j in range(4):
        if j < 3:
            phi = float(np.median(cnt_a * var[:, j]))
            vj = var[:, j]
            B = np.stack([(S[at] * vj[at][:, None]).T @ S[at] for at in at_a]) + phi * (xtx - Sn)  # (F, p, p)
        else:  # one value per visit: nothing within a visit
            vj = np.ones(len(cnt_a))
            B = np.stack([S[at].T @ S[at] for at in at_a])
        c = np.empty_like(a)  # B_k(v) a_v
        for i in range(len(folds)):
            c[kb == i] = a[kb == i] @ B[i].T
        cov.append(HeldoutCovariance.of(a, B.sum(axis=0), c, s_own, vj[own], kb, vj[own]))
    return HeldoutMeanNull(ub, tuple(cov[:3]), cov[3])


def residual_structure(data: DiagnosisData, res: np.ndarray, rows: np.ndarray, groups: np.ndarray,
                       noise_model: VisitNoise, alpha: float = 0.01, ratio_limit: float = SMALL_RATIO,
                       null: HeldoutMeanNull | None = None) -> ResidualStructure:
    """Is there a significant residual left, and what does it depend on?

    The statistic, per axis: chi = sum_v z_v^2 over the V held-out visits, z_v = m_v / sd(m_v), m_v the visit's mean
    held-out residual and sd(m_v) its standard deviation under the null hypothesis (the model is right, the floor's
    noise is all there is). ``null`` (``heldout_mean_covariance``) gives the covariance C (V, V) of the m_v: the noise
    of each visit's mean from the floor's own autocorrelation (``VisitNoise.mean_variance``: the same estimate as the
    floor, so that floor and test agree on what the noise is), what the error of the coefficients that predict a
    held-out visit adds to it, and the correlation that error gives the visits of one fold (one set of coefficients)
    and of the others (in its training set). Without it (None) C is the noise's diagonal alone.
    Its distribution: with R = C's correlation matrix, chi = sum_i lambda_i chi^2_1 (lambda the eigenvalues of R, sum V)
    for Gaussian noise; referred to c chi^2(h) of the same mean and variance (Satterthwaite 1946: h = V^2 / tr R^2,
    c = V / h), chi / V is chi^2(h) / h. The variance of a visit mean is itself estimated (nu = ``noise_model.mean_dof``
    degrees of freedom, a common factor for every visit), so chi / V is referred to F(h, nu), taking nu at least
    ``MIN_MEAN_DOF`` (below it the F test could reject nothing at any size). With the diagonal alone and chi^2(V) the
    test fired on 5-6.5 % of clean simulated campaigns at a nominal 1 % (the 36 coefficients of eq. 28 fitted on
    42 visits: h ~ 37; ``bench/residual_false_alarm.py``, ``docs/results/diagnosis_false_alarms.md``).
    Noise slower than a visit (the sensor's bias instability, Table 2: 0.5-1.9 mg) moves the visit means without
    being in the floor. When poses are revisited in a run, its variance is estimated from the revisits' scatter and
    put in the null, and the test is of each pose's mean over its visits (``slow_visit_test``): on clean continuous
    ramps (every pose ~8 times) the noise alone in the null gave "significant" on 7 of 10 seeds. A campaign that
    visits each pose once cannot tell it from an effect of the pose, and it stays out of the null there (on the
    simulator's clean grid it adds about a tenth to the z axis's chi).

    Significant = p < ``alpha`` / 3 on some axis (Bonferroni over the axes): the test's answer, whatever the size.
    The size is reported beside it: a systematic residual does not average out as the per-sample noise does, so
    one well below the per-sample floor (held-out RMSE within ``ratio_limit`` x floor: "small") is still a residual
    the model lacks; the verdict then gives its pose-mean RMS and the visit that shows it most.
    """
    noise = noise_model.sigma
    r, ug, inv, cnt, means, pose_of, run_of = _visit_means(data, res, rows, groups)
    x = res[r]
    noise_var = noise_model.mean_variance(cnt)
    # without ``null``: independent visit means, their covariance given by its diagonal (no V x V matrix)
    cov, slow_unit = null.for_visits(ug, noise_var) if null is not None else (noise_var.T, None)
    noise_dof = np.maximum(noise_model.mean_dof, MIN_MEAN_DOF)
    z, p, dof, slow, p_revisits = slow_visit_test(means, cov, slow_unit, pose_of, run_of, noise_dof)
    ho = column_rms(x)
    ratio = ho / np.maximum(noise, 1e-12)
    excess = np.sqrt(np.maximum(ho**2 - noise**2, 0.0))
    sig_axis = p < alpha / 3.0  # Bonferroni over the axes: a recording of noise alone is called significant at alpha
    significant = bool(np.any(sig_axis))
    small = significant and not np.any(sig_axis & (ratio > ratio_limit))
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
    t0 = float(np.min(data.t_s))  # visits are placed from the first sample: a CSV may be timed in epoch seconds
    per_pose = [{"visit": int(ug[i]), "pose": int(pose_of[i]), "n": int(cnt[i]), "mean_mps2": means[i], "z": z[i],
                 "gref_mps2": g_mean[i], "t_s": float(t_mean[i] - t0), "temp_c": float(temp_mean[i])}
                for i in range(len(ug))]
    per_pose.sort(key=lambda d: -float(np.max(np.abs(d["z"]))))
    pose_rms = column_rms(means)
    if significant:
        axes = [a for j, a in enumerate("xyz") if sig_axis[j]]
        verdict = (f"significant unexplained residual on axis {', '.join(axes)}: held-out RMSE "
                   + ", ".join(f"{a} {ho[j]:.3g} m/s^2 = {ratio[j]:.2f}x floor" for j, a in enumerate("xyz"))
                   + f"; pose means differ beyond noise (chi^2 p = {', '.join(f'{v:.1e}' for v in p)})")
        for j in np.flatnonzero(sig_axis & (ratio <= ratio_limit)):  # significant but small: its size, its place
            top = max(per_pose, key=lambda d, j=j: abs(float(d["z"][j])))
            verdict += (f"; small on {'xyz'[j]}: held-out RMSE within {ratio_limit:g}x the per-sample floor, but "
                        f"systematic (pose-mean RMS {pose_rms[j]:.3g} m/s^2 = {pose_rms[j] / max(noise[j], 1e-12):.2f}x "
                        f"floor, does not average out; largest at visit {top['visit']} (pose {top['pose']}, "
                        f"{top['t_s']:.0f} s from the first sample): {top['mean_mps2'][j]:+.3g} m/s^2, z = {top['z'][j]:+.1f})")
    else:
        verdict = ("no significant unexplained residual: held-out RMSE within "
                   + ", ".join(f"{ratio[j]:.2f}x" for j in range(3)) + " of the noise floor")
    lag1 = noise_model.acf[:, 1] if noise_model.acf.shape[1] > 1 else np.zeros(3)
    split = list(_direction_disagreement(means, noise_model.mean_variance(cnt), g_mean, t_mean, pose_of, noise_dof))
    if slow.revisits:  # visits of one pose against the test's null, the slow wander and the coefficients' error in it
        split[3] = p_revisits
    return ResidualStructure(significant, verdict, ho, noise, ratio, p, excess, per_pose, pose_rms, corr_t, corr_T, r2,
                             lag1, serial, noise_model.correlation_samples, dof, small, *split,
                             slow_sigma=np.sqrt(slow.variance), slow_dof=slow.dof, slow_revisits=slow.revisits)


def _visit_means(data: DiagnosisData, res: np.ndarray, rows: np.ndarray, groups: np.ndarray) -> tuple[np.ndarray, ...]:
    """(rows used (N,), visit ids (V,), each used row's visit index, samples (V,), mean residual (V, 3) m/s^2, pose id
    (V,), run id (V,)) of the finite rows ``rows`` of ``res`` (N, 3) by visit ``groups``."""
    r = rows & finite_rows(res)
    ug, inv = group_index(groups[r])
    cnt = np.bincount(inv)
    x = res[r]
    means = np.stack([np.bincount(inv, weights=x[:, j]) / cnt for j in range(3)], axis=1)
    pose_of = np.zeros(len(ug), int)
    pose_of[inv] = data.pose_id[r]  # orientation of each visit (samples in motion: -1 may overwrite; fixed below)
    static_r = r & (data.pose_id >= 0)
    pose_of[np.searchsorted(ug, groups[static_r])] = data.pose_id[static_r]
    run_of = data.run_id[r][np.unique(inv, return_index=True)[1]]
    return r, ug, inv, cnt, means, pose_of, run_of


def slow_wander(data: DiagnosisData, res: np.ndarray, rows: np.ndarray, groups: np.ndarray,
                noise_model: VisitNoise) -> SlowVisitError:
    """The slow error of a visit mean (``slow_visit_error``) in the held-out residual ``res`` (N, 3) of a model, from
    the revisits of its poses, against the noise of each visit mean alone (the coefficients' error, which no term
    predicts, is left in it: an estimate on the large side); zero without revisits. The noise of the visit means is
    independent between visits: their covariance is given by its diagonal (no V x V matrix)."""
    _, _, _, cnt, means, pose_of, run_of = _visit_means(data, res, rows, groups)
    return slow_visit_error(means, noise_model.mean_variance(cnt).T, None, pose_of, run_of)


def slow_visit_test(means: np.ndarray, cov: np.ndarray, slow_unit: np.ndarray | None, pose: np.ndarray,
                    run: np.ndarray, noise_dof: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, SlowVisitError]:
    """The test of ``residual_structure`` with the slow error in its null hypothesis: visit means ``means`` (V, 3) m/s^2,
    their covariance ``cov`` (3, V, V) under the noise and the coefficients' error (known to ``noise_dof`` (3,) degrees
    of freedom), ``slow_unit`` (V, V) that of a unit slow error, ``pose`` and ``run`` (V,) each visit's (visit means
    independent of each other: ``cov`` (3, V) their variances and ``slow_unit`` None). The slow error's variance comes
    from the revisits of a (pose, run) (``slow_visit_error``); their scatter is then its estimate, not evidence, so the
    test is of the means of each (pose, run)'s visits (a visit not revisited alone) against their covariance, slow error
    included (at most ``SLOW_ERROR_BOUND_MPS2``), referred to F with the degrees of freedom of both estimates
    (``SlowVisitError.test_dof``); and the revisits' scatter is tested against a slow error at that bound
    (``SlowVisitError.beyond``): p is twice the smaller of the two (Bonferroni). Without revisits it is
    ``visit_mean_test`` of the visit means. Returns (z (V, 3) each visit mean over its standard deviation, p (3,),
    degrees of freedom (3,) of a visit mean's variance, the slow error, p (3,) of the revisits of a (pose, run) against
    each other under that null: ``SlowVisitError.beyond`` at the bound; ones without revisits)."""
    cov, slow_unit = _covariances(cov), None if slow_unit is None else as_covariance(slow_unit)
    slow = slow_visit_error(means, cov, slow_unit, pose, run)
    if not slow.revisits:
        return (*visit_mean_test(means, cov, noise_dof), noise_dof, slow, np.ones(3))
    bound = SLOW_ERROR_BOUND_MPS2**2
    p_rev = slow.beyond(means, cov, slow_unit, bound)  # revisits that differ more than the sensor's wander can
    held = SlowVisitError(np.minimum(slow.variance, bound), slow.dof, slow.revisits, slow.group, slow.sums)
    # the null's covariance C + s^2 U, linear in both: its pooled form and its diagonal from theirs; L C L^T by sums
    # over the groups, (G, G) for G groups
    pool = _Groups(held.group)
    var = _variances(cov) + held.variance[:, None] * _unit_diagonal(slow_unit, len(means))[None, :]
    if slow_unit is None:  # diagonal: so are the pooled covariances
        unit_g = pool.pooled_diagonal(np.ones(len(means)))
        cov_g = np.stack([pool.pooled_diagonal(v) for v in var])
    else:
        unit_g, *pooled = held.sums_of(cov, slow_unit).pooled
        cov_g = np.stack([c + s * unit_g for c, s in zip(pooled, held.variance, strict=True)])
    p_pool = visit_mean_test(pool.means(means), cov_g, held.test_dof(cov_g, unit_g, noise_dof))[1]
    z = means / np.sqrt(np.maximum(var.T, 1e-300))
    return z, np.minimum(2.0 * np.minimum(p_pool, p_rev), 1.0), held.test_dof(var, slow_unit, noise_dof), slow, p_rev


def _covariances(cov: np.ndarray | list[RowCovariance]) -> np.ndarray | list[RowCovariance]:
    """The three axes' covariances of the visit means ``cov``: (3, V) their variances (independent means) as they are,
    (3, V, V) arrays or ``RowCovariance``s as a list of ``RowCovariance``."""
    if isinstance(cov, np.ndarray) and cov.ndim == 2:
        return cov
    return cov if isinstance(cov, list) and all(isinstance(c, RowCovariance) for c in cov) else [
        as_covariance(c) for c in cov]


def _variances(cov: np.ndarray | list[RowCovariance]) -> np.ndarray:
    """(3, V) the variances of the visit means in ``cov`` (``_covariances``)."""
    if isinstance(cov, np.ndarray):
        return cov if cov.ndim == 2 else np.diagonal(cov, axis1=1, axis2=2)
    return np.stack([c.diagonal() for c in cov])


def _unit_diagonal(slow_unit: np.ndarray | RowCovariance | None, n: int) -> np.ndarray:
    """(n,) the diagonal of the slow error's unit covariance ``slow_unit`` ((n, n) or a ``RowCovariance``; (n,): a
    diagonal one, given by its diagonal; None: the identity)."""
    if slow_unit is None:
        return np.ones(n)
    if isinstance(slow_unit, RowCovariance):
        return slow_unit.diagonal()
    return slow_unit if slow_unit.ndim == 1 else np.diagonal(slow_unit)


class _Groups:
    """Visits in groups (``labels`` (n,): 0..G-1), and the operators of ``slow_visit_error`` on them without their
    dense n x n matrices: L (G, n), the mean of each group's visits, and P = I - E, E_ij = [same group] / n_g, each
    visit about its group's mean (symmetric, idempotent). A product with a sparse L costs n x (columns) instead of the
    dense products' n^2 x (columns); a covariance (``visit_covariance.RowCovariance``) is read a block of whole groups'
    rows at a time: O(V^2) for a V x V covariance, O(V) for a diagonal one, and never a V x V array."""

    def __init__(self, labels: np.ndarray) -> None:
        from scipy.sparse import csr_array

        self.labels = np.asarray(labels)
        n = len(self.labels)
        self.count = np.bincount(self.labels)
        self.size = self.count.astype(float)  # (G,) visits of each group
        self.L = csr_array((1.0 / self.size[self.labels], (self.labels, np.arange(n))), shape=(len(self.size), n))
        self.order = np.argsort(self.labels, kind="stable")  # the visits group by group
        self.start = np.r_[0, np.cumsum(self.count)]  # (G + 1,) where each group's visits start in ``order``

    def means(self, M: np.ndarray) -> np.ndarray:
        """L M: (G, ...) the mean of each group's rows of ``M`` (n, ...)."""
        return self.L @ M

    def pooled(self, C: np.ndarray | RowCovariance) -> np.ndarray:
        """L C L^T (G, G) of a symmetric ``C`` (n, n)."""
        return self.sums([as_covariance(C)]).pooled[0]

    def pooled_diagonal(self, d: np.ndarray) -> np.ndarray:
        """The diagonal (G,) of L D L^T, D = diag(``d``) (n,) (the whole of it: it is diagonal)."""
        return np.bincount(self.labels, weights=d, minlength=len(self.size)) / self.size**2

    def contrasts(self, m: np.ndarray) -> np.ndarray:
        """P m: each value of ``m`` (n,) less its group's mean."""
        return m - self.means(m)[self.labels]

    def sums(self, mats: list[RowCovariance]) -> _GroupSums:
        """What the tests of the revisits read of the symmetric covariances (n, n) ``mats`` (m of them), in one pass
        over their rows, whole groups at a time: L X L^T (G, G) of each X, and with P the projector of the groups of
        more than one visit (the revisits: their visits alone, each about its group's mean), tr(P X) (m,) and
        tr(P X P Y) (m, m). With E = I - P (E_ij = [same group] / n_g): tr(P X) = tr(X) - sum_i (L X)_{g(i) i},
        tr(P X P Y) = tr(X Y) - 2 tr(E X Y) + tr(E X E Y), tr(E X Y) = sum_g n_g (L X)_g . (L Y)_g and tr(E X E Y) =
        sum_gh n_g n_h (L X L^T)_gh (L Y L^T)_gh, over the revisits' rows and columns."""
        m, G, w = len(mats), len(self.size), self.size
        rep = self.count >= 2
        idx = np.flatnonzero(rep[self.labels])  # the revisits' visits
        every = len(idx) == len(self.labels)  # every visit a revisit: no columns to leave out
        pooled = np.empty((m, G, G))
        trace, product = np.zeros(m), np.zeros((m, m))
        per = min(c.block_rows for c in mats)
        g0 = 0
        while g0 < G:  # whole groups of at most ``per`` visits (one group more if alone)
            g1 = min(G, max(g0 + 1, int(np.searchsorted(self.start, self.start[g0] + per, side="right")) - 1))
            rows = self.order[self.start[g0]:self.start[g1]]  # their visits, group by group
            X = np.empty((m, len(rows), len(self.labels)))  # (m, rows, n)
            for k, c in enumerate(mats):
                X[k] = c.rows(rows)
            LX = np.add.reduceat(X, self.start[g0:g1] - self.start[g0], axis=1) / w[g0:g1, None]  # (m, g1 - g0, n)
            for k in range(m):
                pooled[k, g0:g1] = self.means(LX[k].T).T  # (L X L^T)'s rows: (L X)'s by L^T
            r = np.flatnonzero(rep[self.labels[rows]])
            if len(r):
                vis = rows[r]
                trace += X[:, r, vis].sum(axis=1) - LX[:, self.labels[vis] - g0, vis].sum(axis=1)
                Xr = (X if len(r) == len(rows) else X[:, r]) if every else X[:, r][:, :, idx]
                Xr = Xr.reshape(m, -1)
                product += Xr @ Xr.T
                LXr = LX[:, rep[g0:g1]] if every else LX[:, rep[g0:g1]][:, :, idx]
                product -= 2.0 * (LXr * w[g0:g1][rep[g0:g1], None]).reshape(m, -1) @ LXr.reshape(m, -1).T
            g0 = g1
        Pr = pooled[:, rep][:, :, rep]
        product += (Pr * (w[rep][:, None] * w[rep][None, :])).reshape(m, -1) @ Pr.reshape(m, -1).T
        return _GroupSums(mats, pooled, trace, product)

    def trace_diagonal(self, d: np.ndarray) -> float:
        """tr(P D), D = diag(``d``) (n,)."""
        return float(np.sum(d * (1.0 - 1.0 / self.size[self.labels])))

    def trace_square_diagonal(self, d: np.ndarray) -> float:
        """tr(P D P D), D = diag(``d``) (n,): sum_ij P_ij^2 d_i d_j, P_ij = [i = j] - [same group] / n_g."""
        s = np.bincount(self.labels, weights=d, minlength=len(self.size))
        return float(np.sum(d**2 * (1.0 - 2.0 / self.size[self.labels])) + np.sum(s**2 / self.size**2))


@dataclass
class _GroupSums:
    """``_Groups.sums`` of the covariances ``mats``: ``pooled`` (m, G, G), and of the revisits' projector P ``trace``
    tr(P X) (m,) and ``product`` tr(P X P Y) (m, m)."""

    mats: list[RowCovariance]
    pooled: np.ndarray
    trace: np.ndarray
    product: np.ndarray

    def of(self, mats: list[RowCovariance]) -> bool:
        """Whether these are the sums of ``mats`` (the same objects)."""
        return len(mats) == len(self.mats) and all(a is b for a, b in zip(mats, self.mats, strict=True))


@dataclass
class SlowVisitError:
    """Noise slower than a visit (``slow_visit_error``): ``variance`` (3,) (m/s^2)^2 of a visit mean's slow error,
    its degrees of freedom ``dof`` (3,) as an estimate (inf when 0 by construction), the ``revisits`` it rests on."""

    variance: np.ndarray
    dof: np.ndarray
    revisits: int
    group: np.ndarray | None = None  # (V,) each visit's (pose, run) group, 0..G-1 (a visit not revisited: its own)
    sums: _GroupSums | None = None  # of the covariances it was estimated against, unit's first, by ``group``

    def beyond(self, means: np.ndarray, cov: np.ndarray, slow_unit: np.ndarray | None,
               bound: np.ndarray) -> np.ndarray:
        """p (3,) of the revisits' scatter |P m|^2 (``slow_visit_error``) under a slow error of variance ``bound``
        (3,) (m/s^2)^2: Satterthwaite's chi^2 of its mean tr(P C_b) and variance 2 tr((P C_b)^2),
        C_b = C + bound U. Small: the revisits of a pose differ more than a slow error of that size explains."""
        g = self.group if self.group is not None else np.zeros(0, int)
        rep = np.bincount(g)[g] >= 2
        idx = np.flatnonzero(rep)
        P = _Groups(np.unique(g[idx], return_inverse=True)[1])
        cov = _covariances(cov)
        if slow_unit is not None:
            m = self.sums_of(cov, slow_unit)
        p = np.ones(3)
        for j in range(3):
            pm = P.contrasts(means[idx, j])
            if slow_unit is None:  # independent visit means: C and U diagonal
                d = cov[j][idx] + bound[j]
                e, v = P.trace_diagonal(d), 2.0 * P.trace_square_diagonal(d)
            else:  # C_b = C + bound U: tr(P C_b) and tr((P C_b)^2) from those of C and U
                cc, cu, uu = m.product[j + 1, j + 1], m.product[j + 1, 0], m.product[0, 0]
                e = m.trace[j + 1] + bound[j] * m.trace[0]
                v = 2.0 * (cc + 2.0 * bound[j] * cu + bound[j] ** 2 * uu)
            h = 2.0 * e**2 / max(v, 1e-300)
            p[j] = stats.chi2.sf(float(pm @ pm) * h / max(e, 1e-300), h)
        return p

    def sums_of(self, cov: list[RowCovariance], slow_unit: np.ndarray | RowCovariance) -> _GroupSums:
        """``_Groups.sums`` of ``slow_unit`` and ``cov`` by ``group``: those it was estimated against if they are."""
        mats = [as_covariance(slow_unit), *cov]
        if self.sums is not None and self.sums.of(mats):
            return self.sums
        return _Groups(self.group if self.group is not None else np.zeros(0, int)).sums(mats)

    def test_dof(self, cov: np.ndarray, slow_unit: np.ndarray | None, noise_dof: np.ndarray) -> np.ndarray:
        """Degrees of freedom (3,) of a visit mean's variance in ``cov`` (3, V, V), or (3, V) its diagonal, the
        noise's (known to ``noise_dof``) plus this slow error's (``slow_unit`` (V, V) for a unit variance; None: the
        identity): Satterthwaite's for a sum of two independent estimates, on the visits' mean variance."""
        var = _variances(cov)
        b = self.variance * float(np.mean(_unit_diagonal(slow_unit, var.shape[1])))
        a = np.maximum(np.mean(var, axis=1) - b, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            dof = (a + b) ** 2 / (a**2 / noise_dof + np.where(b > 0, b**2 / self.dof, 0.0))
        return np.where(np.isfinite(dof) & (dof > 0), np.maximum(dof, MIN_MEAN_DOF), noise_dof)


def slow_visit_error(means: np.ndarray, cov: np.ndarray, slow_unit: np.ndarray | None, pose: np.ndarray,
                     run: np.ndarray) -> SlowVisitError:
    """The slow error of a visit mean that the floor cannot see, from the visits of one pose of one run (the same
    table angles) about their pose's mean: a real sensor's bias wanders slowly (flicker-like bias instability,
    correlation times from seconds to hours; paper Table 2: 0.5-1.9 mg), which the floor (a mean and a line removed
    per visit) never sees, and moves the visit means. Model, per axis: the held-out visit means m (V,) are Gaussian
    with covariance C + s^2 U, C (``cov``, (3, V, V)) that of the noise and the coefficients' error
    (``heldout_mean_covariance``) and U (``slow_unit``) that of a slow error of unit variance, one value per visit
    (``HeldoutMeanNull.slow``). With P the projection onto the contrasts of revisits (each visit about its (pose,
    run)'s mean), the method of moments on Q = |P m|^2 (Henderson's method III, as ``fit.slow_error``):
    E[Q] = tr(P C) + s^2 tr(P U), so s^2 = max(0, (Q - tr(P C)) / tr(P U)), with Var(Q) = 2 tr((P (C + s^2 U))^2)
    and dof = 2 s^4 / Var(s^2). What depends on the pose (its table angles, the order of a repeated sequence of poses)
    is the same in every revisit and is not taken into it: the test still sees an effect of the orientation, the
    table or the motion history of a repeated sequence. A campaign whose poses are each visited once cannot tell a
    slow error from an effect of the pose (0, not identifiable; ``means`` (V, 3) m/s^2, ``pose`` (V,) pose ids, -1 in
    motion, ``run`` (V,) run ids). ``cov`` may be (3, V), the variances of visit means independent of each other (a
    diagonal C) with ``slow_unit`` None (U = I): the same figures from O(V) sums. P is never made: its products are
    sums over the groups (``_Groups.sums``), a block of C's rows at a time: O(V^2 p) for the held-out null's
    factored C, which is never made whole (``visit_covariance``)."""
    key = np.where(pose >= 0, pose.astype(np.int64) * 1_000_003 + run.astype(np.int64), -1)
    lab, cnt = np.unique(key, return_inverse=True, return_counts=True)[1:]
    rep = (key >= 0) & (cnt[lab] >= 2)
    revisits = int(rep.sum() - len(np.unique(key[rep])))
    if revisits < 2:
        return SlowVisitError(np.zeros(3), np.full(3, np.inf), 0)
    idx = np.flatnonzero(rep)
    P = _Groups(np.unique(key[idx], return_inverse=True)[1])  # one group's mean: P is never made (n x n)
    group = np.unique(np.where(rep, key, -2 - np.arange(len(key))), return_inverse=True)[1]
    cov, sums = _covariances(cov), None
    diagonal = slow_unit is None
    if diagonal:
        unit = np.ones(len(idx))
        tr_pu = P.trace_diagonal(unit)
    else:  # one pass over the rows of U and C, which the pooled test reads too (``slow_visit_test``)
        sums = _Groups(group).sums([as_covariance(slow_unit), *cov])
        tr_pu, uu = sums.trace[0], sums.product[0, 0]
    var, dof = np.zeros(3), np.full(3, np.inf)
    for j in range(3):
        pm = P.contrasts(means[idx, j])
        if diagonal:
            C = cov[j][idx]
            tr_pc = P.trace_diagonal(C)
        else:
            tr_pc, cc, cu = sums.trace[j + 1], sums.product[j + 1, j + 1], sums.product[j + 1, 0]
        var[j] = max((float(pm @ pm) - tr_pc) / max(tr_pu, 1e-300), 0.0)
        if var[j] > 0:  # tr((P (C + s^2 U))^2)
            sq = (P.trace_square_diagonal(C + var[j] * unit) if diagonal
                  else cc + 2.0 * var[j] * cu + var[j] ** 2 * uu)
            dof[j] = 2.0 * var[j] ** 2 / (2.0 * sq / tr_pu**2)
    return SlowVisitError(var, dof, revisits, group, sums)


def _visit_sums(X: np.ndarray, rows: np.ndarray, inv: np.ndarray, n: int, block: int = 1 << 15) -> np.ndarray:
    """(n, p): the rows ``rows`` of ``X`` (N, p) summed by visit (``inv``: each selected row's visit index), a block of
    rows at a time (no copy of the design's rows)."""
    idx = np.flatnonzero(rows)
    out = np.zeros((n, X.shape[1]))
    for lo in range(0, len(idx), block):
        v = inv[lo:lo + block]
        order = np.argsort(v, kind="stable")
        v = v[order]
        starts = np.flatnonzero(np.r_[True, v[1:] != v[:-1]])
        out[v[starts]] += np.add.reduceat(X[idx[lo:lo + block][order]], starts, axis=0)
    return out


def visit_mean_test(means: np.ndarray, cov: np.ndarray, dof: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The test of ``residual_structure``: visit means ``means`` (V, 3) m/s^2 against their covariance ``cov``
    (3, V, V) under the null hypothesis (or (3, V): independent means, their variances), known to ``dof`` (3,) degrees
    of freedom. Returns (z (V, 3): each mean over
    its standard deviation, p (3,)): chi = sum_v z_v^2 referred to c chi^2(h), h = V^2 / tr R^2 (R the correlation
    matrix of ``cov``: Satterthwaite's two moments of sum_i lambda_i chi^2_1), chi / V to F(h, dof)."""
    V = means.shape[0]
    cov = _covariances(cov)
    var = np.maximum(_variances(cov).T, 1e-300)  # (V, 3)
    z = means / np.sqrt(var)
    chi = np.sum(z**2, axis=0)
    sd = np.sqrt(var.T)  # (3, V)
    h = np.full(3, float(V))  # independent visit means (cov (3, V)): R = I, tr R^2 = V
    if not isinstance(cov, np.ndarray):
        for j in range(3):  # the correlation matrix R squared, a block of its rows at a time
            h[j] = V**2 / max(squared_correlation_sum(cov[j], sd[j]), 1e-300)
    return z, _visit_chi2_p(chi * h / max(V, 1), h, dof)


def _visit_chi2_p(chi: np.ndarray, df: float | np.ndarray, dof: np.ndarray) -> np.ndarray:
    """p (3,) of ``chi`` (3,), a sum of ``df`` squared visit means over their variance under the noise alone: chi / df
    is F(df, ``dof``) when that variance is estimated with ``dof`` (3,) degrees of freedom, chi^2(df) when known (inf)."""
    return np.where(np.isfinite(dof), stats.f.sf(chi / df, df, np.where(np.isfinite(dof), dof, 1.0)),
                    stats.chi2.sf(chi, df=df))


def _direction_disagreement(means: np.ndarray, var: np.ndarray, g_mean: np.ndarray, t_mean: np.ndarray,
                            pose: np.ndarray, dof: np.ndarray) -> tuple[np.ndarray, int, float, np.ndarray, np.ndarray,
                                                                     float]:
    """Do visits of one direction of gravity disagree beyond the noise? ``means`` (V, 3) visit means of the residual
    (m/s^2) with variances ``var`` (V, 3) under the noise alone, ``g_mean`` (V, 3) their mean reference, ``t_mean``
    (V,) their mean time (s), ``pose`` (V,) their pose ids, ``dof`` (3,) degrees of freedom of ``var``. Each
    direction's visits about their weighted mean: chi^2 over the directions visited more than once, df = visits -
    directions, referred to F(df, dof) like the test of the visit means. A model of the sensor maps one direction of
    gravity to one output, so whatever these visits disagree by is not a function of the orientation. The chi^2 splits
    exactly (weighted means) into the visits of one pose id about their pose's mean (the same table angles: only time
    sets them apart) and the poses' means about their direction's (other table angles, or time). Returns (p (3,),
    visits in repeated directions, median time span of those directions (s), p (3,) within poses, p (3,) between the
    poses of a direction, median time span of the poses visited more than once (s))."""
    ones = np.ones(3)

    def f_test(chi: np.ndarray, df: int) -> np.ndarray:
        return _visit_chi2_p(chi, df, dof) if df >= 1 else ones.copy()

    label = direction_labels(g_mean)
    counts = np.bincount(label)
    rep = counts[label] >= 2
    if int(rep.sum() - np.sum(counts >= 2)) < 1:
        return ones.copy(), 0, 0.0, ones.copy(), ones.copy(), 0.0
    w = 1.0 / np.maximum(var[rep], 1e-300)
    m, t = means[rep], t_mean[rep]
    d = np.unique(label[rep], return_inverse=True)[1]
    dp = np.unique(np.column_stack([d, pose[rep]]), axis=0, return_inverse=True)[1].reshape(-1)

    def centre(lab: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(lab, weights=w[:, j] * m[:, j]) / np.bincount(lab, weights=w[:, j])
                         for j in range(3)], axis=1)

    c_d, c_dp = centre(d), centre(dp)
    total = np.sum(w * (m - c_d[d]) ** 2, axis=0)
    within = np.sum(w * (m - c_dp[dp]) ** 2, axis=0)
    n_d, n_dp = np.bincount(d), np.bincount(dp)
    df_total = int(len(m) - len(n_d))
    df_within = int(len(m) - len(n_dp))
    spans = [float(np.ptp(t[d == c])) for c in range(len(n_d))]
    pose_spans = [float(np.ptp(t[dp == c])) for c in np.flatnonzero(n_dp >= 2)]
    return (f_test(total, df_total), int(rep.sum()), float(np.median(spans)), f_test(within, df_within),
            f_test(np.maximum(total - within, 0.0), df_total - df_within),
            float(np.median(pose_spans)) if pose_spans else 0.0)


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return 0.0
    return float(stats.spearmanr(a, b).statistic)
