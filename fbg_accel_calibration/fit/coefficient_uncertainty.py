"""Covariance of the eq. 28 coefficients (GUM, JCGM 100:2008 section 5: the uncertainty of a least-squares estimate).

Pure numpy. The fit's errors are not independent samples: the noise is low-passed by the transimpedance stages (the
samples of one visit are correlated over ~0.1-0.2 s), and what one visit shares -- the table's pose error, the
reference's error at that orientation, the misfit of eq. 28 there -- does not average out over its samples at all.
What can be taken as independent are the *visits* (contiguous stays at one pose). So the covariance is the
cluster-robust (sandwich) estimate with the visits as clusters (Liang & Zeger 1986; Cameron & Miller 2015, "A
Practitioner's Guide to Cluster-Robust Inference", J. Human Resources 50(2)), for coefficients A (p, 3) with
B = X^T X and each visit's score s_v = X_v^T e_v (p, 3), e_v the visit's residuals::

    Cov(vec A) = sum_v vec(B^-1 s~_v) vec(B^-1 s~_v)^T,      s~_v = (I - X_v^T X_v B^-1)^(-1/2) s_v

with the small-sample correction CR2 of Bell & McCaffrey (2002, "Bias reduction in standard errors for linear
regression with multi-stage samples", Survey Methodology 28(2) 169-181): a visit's residuals are shrunk by the fit
by its leverage (I - H_vv), and with few visits per coefficient (18 visits for the 12 coefficients per axis of the
paper's degree-2 campaign) the uncorrected sandwich reads the variance about three times low. The matrix power is
taken on p x p matrices by the push-through identity X_v^T f(X_v B^-1 X_v^T) = f(X_v^T X_v B^-1) X_v^T, so only the
visits' sums (``thermal_fit.CellStats.visit_xtx``, ``visit_xtg``) are needed, never the samples.

``vec`` is row-major over A (p, 3): index ``3 k + i`` is regressor k of eq. 29 (``thermal_fit.design_matrix``) for
output axis i. :func:`bootstrap_covariance` checks it by resampling whole visits (stratified by temperature level).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .thermal_fit import CellStats, jacobi_scaling, solve_normal_equations, sub_columns

METHOD = ("cluster-robust sandwich, visits as clusters, CR2 small-sample correction (Bell & McCaffrey 2002); "
          "vec row-major over A (p, 3) of eq. 29 regressors x output axes")
METHOD_BY_CELL = METHOD.replace("visits as clusters", "cells (pose x temperature level x run) as clusters")
MAX_LEVERAGE = 0.99  # a visit the fit reproduces exactly carries no residual to scale up: its factor is capped at 10


@dataclass
class Clusters:
    """Per-cluster sums at one degree: X^T X (V, p, p), X^T G (V, p, 3) and temperature level (V,)."""

    xtx: np.ndarray
    xtg: np.ndarray
    level: np.ndarray
    by_visit: bool


def clusters_of(stats: CellStats, degree: int) -> Clusters:
    """The visits' sums at ``degree`` (the cells' when the visits were not kept: ``thermal_fit.MAX_VISIT_SUMS``)."""
    cols = sub_columns(degree, stats.degree)
    by_visit = len(stats.visit_cell) > 0
    if by_visit:
        xtx, xtg, level = stats.visit_xtx, stats.visit_xtg, stats.level[stats.visit_cell]
    else:
        xtx, xtg, level = stats.xtx, stats.xtg, stats.level
    return Clusters(xtx[:, cols][:, :, cols], xtg[:, cols], np.asarray(level), by_visit)


def _inverse_sqrt(sym: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh(sym)
    return (v / np.sqrt(w)) @ v.T


def cluster_covariance(stats: CellStats, A: np.ndarray, degree: int,
                       groups: np.ndarray | None = None) -> tuple[np.ndarray, str, int]:
    """CR2 cluster-robust covariance (3p, 3p) of the coefficients ``A`` (p, 3) fitted at ``degree`` on ``stats``;
    returns ``(covariance, method, clusters)``. Units: those of A's entries squared (m/s^2 per unit regressor).
    ``groups`` (V,) int, optional: coarser clusters, a label per visit (e.g. runs of consecutive visits that share a
    slow drift); visits of one label are one cluster."""
    cl = clusters_of(stats, degree)
    method = METHOD if cl.by_visit else METHOD_BY_CELL
    if groups is not None:
        labels, inverse = np.unique(np.asarray(groups), return_inverse=True)
        xtx, xtg = np.zeros((len(labels), *cl.xtx.shape[1:])), np.zeros((len(labels), *cl.xtg.shape[1:]))
        np.add.at(xtx, inverse, cl.xtx)
        np.add.at(xtg, inverse, cl.xtg)
        cl = Clusters(xtx, xtg, np.zeros(len(labels), int), False)
        method = METHOD.replace("visits as clusters", "groups of visits as clusters")
    B = cl.xtx.sum(axis=0)
    d, Bs = jacobi_scaling(B)  # as the fit solves it: the regressors differ by orders of magnitude
    W = _inverse_sqrt(Bs)  # Bs^(-1/2)
    scores = (cl.xtg - cl.xtx @ A) / d[None, :, None]  # scaled s_v (V, p, 3)
    S = W @ (cl.xtx / np.outer(d, d)) @ W  # W Ms_v W: the visit's leverage, eigenvalues in [0, 1]
    w, v = np.linalg.eigh(S)
    factor = (v / np.sqrt(1.0 - np.clip(w, 0.0, MAX_LEVERAGE))[:, None, :]) @ np.swapaxes(v, 1, 2)
    u = (W @ factor @ W @ scores) / d[None, :, None]  # B^-1 s~_v, (V, p, 3)
    flat = u.reshape(len(u), -1)
    cov = flat.T @ flat
    return 0.5 * (cov + cov.T), method, len(u)


def bootstrap_covariance(stats: CellStats, degree: int, n_boot: int = 400, seed: int = 0) -> tuple[np.ndarray, int]:
    """Covariance (3p, 3p) of the coefficients over ``n_boot`` refits on visits drawn with replacement within each
    temperature level (a level keeps its number of visits); returns ``(covariance, refits that were identified)``.
    A draw whose normal equations are singular (a pose missing at a level that needs it) is skipped."""
    from .thermal_fit import NotIdentifiedError

    cl = clusters_of(stats, degree)
    rng = np.random.default_rng(seed)
    groups = [np.flatnonzero(cl.level == lev) for lev in np.unique(cl.level)]
    draws = []
    for _ in range(n_boot):
        pick = np.concatenate([g[rng.integers(0, len(g), len(g))] for g in groups])
        try:
            A, _ = solve_normal_equations(cl.xtx[pick].sum(axis=0), cl.xtg[pick].sum(axis=0), rcond=1e-10)
        except NotIdentifiedError:
            continue
        draws.append(A.ravel())
    draws_a = np.asarray(draws)
    return np.cov(draws_a, rowvar=False), len(draws_a)
