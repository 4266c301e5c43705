"""Covariances of visit means given by blocks of their rows, never made whole (``RowCovariance``).

The residual test's null hypothesis (``structure.heldout_mean_null``) holds, per axis, the covariance of the V held-out
visit means (2500 visits at 10^6 samples: a V x V array is 48 MiB, and the null has four). Its tests read only
diagonals, traces and sums over rows: the traces with the revisits' projector, the pooled covariance of groups of
visits, the squared correlations. So a covariance here is what makes any block of its rows on demand
(``RowCovariance.rows``), and those sums are taken a block of ``ROW_BLOCK`` rows at a time: the held-out null's
(``HeldoutCovariance``) from its factors (V x 2p each, p the design's columns), a dense array's (``DenseCovariance``)
from the array itself.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

ROW_BLOCK = 64  # rows of a factored covariance made at a time: 64 x V values (1.2 MiB at 2500 visits)


class RowCovariance:
    """A symmetric (n, n) covariance given by blocks of its rows."""

    n: int
    block_rows: int = ROW_BLOCK  # rows worth making at a time

    def diagonal(self) -> np.ndarray:
        """(n,) its diagonal."""
        raise NotImplementedError

    def rows(self, i: np.ndarray | slice) -> np.ndarray:
        """(len(i), n) its rows ``i``."""
        raise NotImplementedError

    def blocks(self) -> Iterator[slice]:
        """Its rows, ``block_rows`` at a time."""
        for lo in range(0, self.n, self.block_rows):
            yield slice(lo, min(lo + self.block_rows, self.n))

    def dense(self) -> np.ndarray:
        """(n, n) the whole of it (for small n: checks and tests)."""
        return np.array(self.rows(slice(0, self.n)))


class DenseCovariance(RowCovariance):
    """A covariance held as its (n, n) array: its rows are the array's (one block: no copy)."""

    def __init__(self, matrix: np.ndarray) -> None:
        self.matrix = matrix
        self.n = len(matrix)
        self.block_rows = max(self.n, 1)

    def diagonal(self) -> np.ndarray:
        return np.diagonal(self.matrix)

    def rows(self, i: np.ndarray | slice) -> np.ndarray:
        return self.matrix[i]


class HeldoutCovariance(RowCovariance):
    """The covariance of held-out visit means under the null hypothesis (``structure.heldout_mean_null``), from its
    factors: for visits v, w of folds k(v), k(w),

    C_vw = a_v^T B a_w - c_v . a_w - a_v . c_w + [k(v) = k(w)] c_v . a_w
           - [k(v) != k(w)] (a_v . s_w var_w + s_v . a_w var_v) + [v = w] d_v
         = l_v . r_w - [k(v) != k(w)] (l'_v . r'_w) + [v = w] d_v,

    l = (a B, a), r = (a, -c), l' = (c + var s, a), r' = (a, var s): ``a`` (n, p) each visit's G_k x_v, ``B`` (p, p)
    the sum of the folds' B_u, ``c`` (n, p) B_k(v) a_v, ``s`` (n, p) its design rows summed, ``var`` (n,) its mean's
    noise variance, ``fold`` (n,), ``d`` (n,) what its own mean adds on the diagonal. A block of b rows is two
    products of (b, 2p) by (2p, n). A visit whose factors are all zero has ``d`` alone (``for_visits``)."""

    def __init__(self, left: np.ndarray, right: np.ndarray, left_other: np.ndarray, right_other: np.ndarray,
                 fold: np.ndarray, d: np.ndarray) -> None:
        self.left, self.right, self.left_other, self.right_other, self.fold, self.d = (
            left, right, left_other, right_other, fold, d)
        self.n = len(d)

    @classmethod
    def of(cls, a: np.ndarray, B: np.ndarray, c: np.ndarray, s: np.ndarray, var: np.ndarray, fold: np.ndarray,
           d: np.ndarray) -> HeldoutCovariance:
        """From the factors of the formula above."""
        vs = s * var[:, None]
        return cls(np.hstack([a @ B, a]), np.hstack([a, -c]), np.hstack([c + vs, a]), np.hstack([a, vs]), fold, d)

    def diagonal(self) -> np.ndarray:
        return np.einsum("vp,vp->v", self.left, self.right) + self.d

    def rows(self, i: np.ndarray | slice) -> np.ndarray:
        out = self.left[i] @ self.right.T
        other = np.matmul(self.left_other[i], self.right_other.T)
        other[self.fold[i][:, None] == self.fold[None, :]] = 0.0
        out -= other
        r = np.arange(self.n)[i]
        out[np.arange(len(r)), r] += self.d[r]
        return out

    def for_visits(self, pos: np.ndarray, known: np.ndarray, d: np.ndarray) -> HeldoutCovariance:
        """The covariance of other visits: visit i is this one's ``pos[i]`` where ``known[i]``, else a visit of
        variance ``d[i]`` independent of the others."""
        def put(x: np.ndarray) -> np.ndarray:
            out = np.zeros((len(pos), *x.shape[1:]), x.dtype)
            out[known] = x[pos[known]]
            return out

        dd = np.array(d, dtype=float)
        dd[known] = self.d[pos[known]]
        return HeldoutCovariance(put(self.left), put(self.right), put(self.left_other), put(self.right_other),
                                 np.where(known, put(self.fold), -1), dd)


class DiagonalCovariance(RowCovariance):
    """A diagonal covariance ``d`` (n,): independent visit means."""

    def __init__(self, d: np.ndarray) -> None:
        self.d = np.asarray(d, dtype=float)
        self.n = len(self.d)

    def diagonal(self) -> np.ndarray:
        return self.d

    def rows(self, i: np.ndarray | slice) -> np.ndarray:
        r = np.arange(self.n)[i]
        out = np.zeros((len(r), self.n))
        out[np.arange(len(r)), r] = self.d[r]
        return out


def as_covariance(m: np.ndarray | RowCovariance) -> RowCovariance:
    """``m`` as a ``RowCovariance``: an (n, n) array is held as it is."""
    return m if isinstance(m, RowCovariance) else DenseCovariance(np.asarray(m))


def squared_correlation_sum(c: RowCovariance, sd: np.ndarray) -> float:
    """tr(R^2) = sum_vw (C_vw / (sd_v sd_w))^2 of the correlation matrix R of ``c``, ``sd`` (n,) its standard
    deviations, a block of rows at a time."""
    total = 0.0
    for b in c.blocks():
        r = c.rows(b) / sd[b][:, None]
        r /= sd[None, :]
        np.square(r, out=r)
        total += float(np.sum(r))
    return total
