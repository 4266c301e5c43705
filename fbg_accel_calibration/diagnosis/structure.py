"""What remains after the chosen model: is the held-out residual beyond the noise, and what does it depend on
(``residual_structure``)?
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from .data import DiagnosisData, direction_labels, finite_rows

# ============================================================================ data preparation
from .floor import (
    MIN_MEAN_DOF,
    VisitNoise,
)
from .search import (
    _corr,
)

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


def coefficient_mean_variance(X: np.ndarray, rows: np.ndarray, groups: np.ndarray, XtX: np.ndarray,
                              noise_model: VisitNoise, n_folds: int) -> dict[int, np.ndarray]:
    """Variance (3,) in (m/s^2)^2, by visit id, that the error of the fitted coefficients adds to a visit's mean
    held-out residual: x_v^T Cov(A) x_v per axis, x_v the visit's mean design row. A held-out visit is predicted by
    coefficients fitted on the other folds, whose own error the noise alone does not contain (36 coefficients fitted
    on ~100 visits add ~a third to a visit mean's variance). Cov(A) is the sandwich (X^T X)^-1 B (X^T X)^-1 with
    visits as the independent units, B = sum_v n_v^2 var(mean_v) x_v x_v^T (the noise model's variance of each
    visit's mean: the null hypothesis of the test, not the residual), scaled by K / (K - 1) for the fold held out.
    ``rows``: the fitted samples (X finite there)."""
    sel = rows & (groups >= 0)
    ug, inv = np.unique(groups[sel], return_inverse=True)
    if not len(ug):
        return {}
    cnt = np.bincount(inv).astype(float)
    Xs = X[sel]
    sums = np.stack([np.bincount(inv, weights=Xs[:, c], minlength=len(ug)) for c in range(X.shape[1])], axis=1)
    xbar = sums / cnt[:, None]
    d = np.sqrt(np.maximum(np.diag(XtX), 1e-300))
    try:
        # (X^T X)^-1 x_v for every visit, Jacobi-scaled as the fit solves it
        Wx = (np.linalg.solve(XtX / d[:, None] / d[None, :], (xbar / d).T) / d[:, None]).T
    except np.linalg.LinAlgError:
        return {}
    var = noise_model.mean_variance(cnt.astype(int))  # (V, 3)
    P = Wx @ sums.T  # (V, V): x_v^T (X^T X)^-1 (n_u x_u)
    out = (P ** 2) @ var * (n_folds / max(n_folds - 1, 1))  # (V, 3): sum_u P_vu^2 var_u
    return {int(g): out[i] for i, g in enumerate(ug)}


def residual_structure(data: DiagnosisData, res: np.ndarray, rows: np.ndarray, groups: np.ndarray,
                       noise_model: VisitNoise, alpha: float = 0.01, ratio_limit: float = SMALL_RATIO,
                       fit_var: dict[int, np.ndarray] | None = None) -> ResidualStructure:
    """Is there a significant residual left, and what does it depend on?

    Test: visit means of the held-out residual against what the noise alone gives, chi^2 with the variance of
    each visit's mean from the floor's own autocorrelation (``VisitNoise.mean_variance``: the same estimate as
    the floor, so that floor and test agree on what the noise is; a first-order count of effective samples from
    the lag-1 correlation counted 2-4 times too many for this noise and flagged clean data), plus what the error of
    the coefficients that predict a held-out visit adds to its mean (``fit_var``: ``coefficient_mean_variance``, by
    visit id; without it the test flagged a fifth of clean campaigns at a nominal 1 %).
    Significant = p < ``alpha`` / 3 on some axis (Bonferroni over the axes): the test's answer, whatever the size.
    The size is reported beside it: a systematic residual does not average out as the per-sample noise does, so
    one well below the per-sample floor (held-out RMSE within ``ratio_limit`` x floor: "small") is still a residual
    the model lacks; the verdict then gives its pose-mean RMS and the visit that shows it most. The degrees of
    freedom nu of the floor's mean variance are taken as at least ``MIN_MEAN_DOF``: below it the F test could
    reject nothing at any size.
    """
    noise = noise_model.sigma
    r = rows & finite_rows(res)
    ug, inv = np.unique(groups[r], return_inverse=True)
    cnt = np.bincount(inv)
    x = res[r]
    means = np.stack([np.bincount(inv, weights=x[:, j]) / cnt for j in range(3)], axis=1)
    mean_var = noise_model.mean_variance(cnt)
    if fit_var:
        mean_var = mean_var + np.stack([fit_var.get(int(g), np.zeros(3)) for g in ug])
    z = means / np.sqrt(np.maximum(mean_var, 1e-300))
    chi = np.sum(z**2, axis=0)
    # the variance of a visit mean is itself estimated (nu = noise_model.mean_dof degrees of freedom, a common factor
    # for every visit): chi / df is then F(df, nu) under the noise alone, the chi^2 law when it is known (nu = inf)
    dof = np.maximum(noise_model.mean_dof, MIN_MEAN_DOF)
    p = _visit_chi2_p(chi, len(ug), dof)
    ho = np.sqrt(np.mean(x**2, axis=0))
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
    pose_of = np.zeros(len(ug), int)
    pose_of[inv] = data.pose_id[r]  # orientation of each visit (samples in motion: -1 may overwrite; fixed below)
    static_r = r & (data.pose_id >= 0)
    pose_of[np.searchsorted(ug, groups[static_r])] = data.pose_id[static_r]
    t0 = float(np.min(data.t_s))  # visits are placed from the first sample: a CSV may be timed in epoch seconds
    per_pose = [{"visit": int(ug[i]), "pose": int(pose_of[i]), "n": int(cnt[i]), "mean_mps2": means[i], "z": z[i],
                 "gref_mps2": g_mean[i], "t_s": float(t_mean[i] - t0), "temp_c": float(temp_mean[i])}
                for i in range(len(ug))]
    per_pose.sort(key=lambda d: -float(np.max(np.abs(d["z"]))))
    pose_rms = np.sqrt(np.mean(means**2, axis=0))
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
    split = _direction_disagreement(means, noise_model.mean_variance(cnt), g_mean, t_mean, pose_of, dof)
    return ResidualStructure(significant, verdict, ho, noise, ratio, p, excess, per_pose, pose_rms, corr_t, corr_T, r2,
                             lag1, serial, noise_model.correlation_samples, dof, small, *split)


def _visit_chi2_p(chi: np.ndarray, df: int, dof: np.ndarray) -> np.ndarray:
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
