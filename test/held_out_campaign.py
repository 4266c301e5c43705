"""A synthetic cross-validated design of visits, with its held-out null and the exact refits behind it (shared by the
residual test's tests)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FOLDS = 10
COLUMNS = 30  # the diagnosis' 36 coefficients, about
SIGMA = np.array([0.5, 1.0, 2.0])  # white noise of each axis (m/s^2)


@dataclass
class HeldOutCampaign:
    """V visits (``n_v`` samples each, ``groups`` by sample), a design ``X`` (N, 30) of columns that vary a little within
    a visit, folds by visit (``fold_v``; ``fold`` by sample), white noise of standard deviations ``sigma`` (3,), the
    null of ``heldout_mean_covariance`` for it, and ``rng`` where the campaign's draws left it."""

    X: np.ndarray
    groups: np.ndarray
    n_v: np.ndarray
    fold_v: np.ndarray
    fold: np.ndarray
    sigma: np.ndarray
    null: object
    rng: np.random.Generator

    def refits(self) -> np.ndarray:
        """L (V, N): the held-out visit means as a map of the noise by the refits of cross-validation (each visit's
        mean, less the mean of its fold's fit on the other folds), so that their covariance under white noise is
        sigma^2 L L^T exactly."""
        V, N = len(self.n_v), len(self.groups)
        L = np.zeros((V, N))
        for k in range(FOLDS):
            train = self.fold != k
            H = self.X[self.fold == k] @ np.linalg.solve(self.X[train].T @ self.X[train], self.X[train].T)
            for v in np.flatnonzero(self.fold_v == k):
                L[v, self.groups == v] += 1.0 / self.n_v[v]
                L[v, train] -= H[self.groups[self.fold == k] == v].mean(axis=0)
        return L


def held_out_campaign(V: int, seed: int, visit_samples: tuple[int, int]) -> HeldOutCampaign:
    """:class:`HeldOutCampaign` of ``V`` visits of ``visit_samples`` (lowest, highest) samples each, drawn from
    ``seed``."""
    from fbg_accel_calibration.diagnosis.floor import VisitNoise
    from fbg_accel_calibration.diagnosis.structure import heldout_mean_covariance

    rng = np.random.default_rng(seed)
    n_v = rng.integers(visit_samples[0], visit_samples[1] + 1, size=V)
    groups = np.repeat(np.arange(V), n_v)
    N = len(groups)
    X = np.column_stack([np.ones(N), rng.normal(size=(V, COLUMNS - 1))[groups]
                         + 0.1 * rng.normal(size=(N, COLUMNS - 1))])
    fold_v = rng.permutation(V) % FOLDS
    fold = fold_v[groups]
    rows = np.ones(N, bool)
    null = heldout_mean_covariance(X, rows, rows, groups, fold,
                                   np.stack([X[fold == k].T @ X[fold == k] for k in range(FOLDS)]), X.T @ X,
                                   VisitNoise(SIGMA, np.column_stack([np.ones(3), np.zeros(3)])))
    return HeldOutCampaign(X, groups, n_v, fold_v, fold, SIGMA, null, rng)
