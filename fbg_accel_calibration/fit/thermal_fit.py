"""Least-squares fit of the thermal calibration model (paper eq. 28-30) for any degree n.

Pure numpy. Per sample i, with tau_i = (T_i - t_center_c) / t_scale_c::

    a_i = sum_{k=0..n} M_k tau_i^k Psi_i + sum_{k=0..n} b_k tau_i^k          (eq. 28, m/s^2)

which is linear in the 12(n+1) coefficients. The regressor row (eq. 29) is::

    x_i = [Psi_i, Psi_i tau_i, ..., Psi_i tau_i^n, 1, tau_i, ..., tau_i^n]  (4(n+1) values)

and the three output axes share it: A = (X^T X)^-1 X^T G (eq. 30, written here for row-wise
samples; the paper's Â = G X^T (X X^T)^-1 is the same with column-wise samples). M_k[i, j] =
A[3k + j, i], b_k[i] = A[3(n+1) + k, i].

Sums: X^T X, X^T G, G^T G and sum(X) are accumulated chunk by chunk and per *cell* (one pose
at one temperature level), so memory is bounded by one chunk of the design matrix whatever the
number of samples, and cross-validation (``model_selection``) can remove whole poses or whole
temperature levels from the sums without touching the samples again. Residual sums of squares
follow from the same sums: RSS = G^T G - 2 diag(A^T X^T G) + diag(A^T X^T X A). Choosing the samples
(static detector, temperature levels) and reading runs into these sums block by block, from files or from
memory, is :mod:`fit_stream`'s job.

Temperature is centred and scaled (tau in [-1, 1] over the data) so that high degrees stay well
conditioned; ``ThermalCalibration`` stores centre and scale, and with centre 0 and scale 1 the
coefficients are exactly the paper's.

Identifiability: with L distinct temperature levels the columns tau^k, k >= L, are linear
combinations of lower powers on the data (a polynomial of degree >= L through L points is not
unique), so a degree n >= L is refused with :class:`NotIdentifiedError`.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from fbg_accel_driver.command_line import printable
from fbg_accel_driver.sensor_constants import STANDARD_GRAVITY
from fbg_accel_driver.thermal_model import ThermalCalibration, normalise

from ..io.recording import Recording

DEFAULT_LEVEL_GAP_C = 1.0  # degC: sorted temperatures further apart than this belong to different levels
DEFAULT_LEVEL_WIDTH_C = 3.0  # degC: a wider cluster (a sweep, not a set-point) is split into bins this wide
DEFAULT_CHUNK = 65536
# Smallest RMS spread (m/s^2) of the poses' reference specific force along any direction of the table
# frame. Along a direction the poses do not span, eq. 28 fits the output to a constant: that row of M
# comes out zero and the noise figure zero, a dead axis that looks perfect. The six-position plan spreads
# g/sqrt(3) = 5.7 m/s^2 along every axis; coplanar poses (one tilt axis only, or a run stopped after its
# 4th pose) spread exactly 0 along the normal of their plane. 0.05 g is a tilt of about +-4 deg.
MIN_POSE_SPREAD_MPS2 = 0.05 * STANDARD_GRAVITY
# Reach the poses should have both ways along each table axis (m/s^2): beyond the reference the poses reached, eq. 28
# is extrapolated over a response the fit never saw (the spectral non-linearity: on the simulator, 0.42 m/s^2 at x down
# after poses tilting x by 8 degrees at most, 0.12 with the six positions), and no hold-out figure can show it
MIN_REFERENCE_REACH_MPS2 = 0.5 * STANDARD_GRAVITY
# Smallest spread of the poses' mean Psi along any direction, relative to the largest. A working sensor
# spreads about equally along all three (each channel follows its own axis, paper eq. 25: ratios near 1
# on the measured series); a dead or saturated channel, or copied samples, leave one direction flat.
MIN_SIGNAL_SPREAD_RATIO = 1e-3
_LEVEL_OFFSET = 1 << 16  # cell key = pose << 32 | (level + offset)
# Visits whose own sums (X^T X, X^T G: p(p+3) floats each, 2.4 kB at degree 3) are kept for the coefficient covariance;
# a campaign has tens to hundreds. Beyond this (rows of interleaved cells: every sample its own visit) they are dropped
# and the covariance is clustered by cell instead (coefficient_uncertainty), which is coarser and still valid.
MAX_VISIT_SUMS = 20000


class NotIdentifiedError(ValueError):
    """The requested model cannot be determined from the data (degree >= levels, too few poses)."""


def n_params(degree: int) -> int:
    """Regressors per output axis: 3(n+1) for M, (n+1) for b."""
    return 4 * (degree + 1)


def design_matrix(psi: np.ndarray, tau: np.ndarray, degree: int, out: np.ndarray | None = None) -> np.ndarray:
    """Eq. 29 regressor rows (N, 4(n+1)) from Psi (N, 3) and scaled temperature tau (N,).

    ``out`` (N, 4(n+1)) may be given to reuse a buffer. A new matrix is column-major: it is filled a
    column at a time, and the products that use it (X^T X, X A) take either layout.
    """
    psi = np.asarray(psi, dtype=float)
    tau = np.asarray(tau, dtype=float)
    n, q = len(tau), 3 * (degree + 1)
    X = np.empty((n_params(degree), n)).T if out is None else out[:n]
    X[:, q] = 1.0
    X[:, 0:3] = psi
    for k in range(1, degree + 1):
        np.multiply(X[:, q + k - 1], tau, out=X[:, q + k])
        np.multiply(X[:, 3 * (k - 1):3 * k], tau[:, None], out=X[:, 3 * k:3 * (k + 1)])
    return X


def sub_columns(degree: int, of_degree: int) -> np.ndarray:
    """Column indices of the degree-``degree`` regressors inside a degree-``of_degree`` design matrix."""
    if degree > of_degree:
        raise ValueError(f"degree {degree} > {of_degree}")
    return np.concatenate([np.arange(3 * (degree + 1)), 3 * (of_degree + 1) + np.arange(degree + 1)])  # Psi, constant


def coefficients_to_model(A: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Split A (4(n+1), 3) into M (n+1, 3, 3) and b (n+1, 3)."""
    m_part = A[: 3 * (degree + 1)].reshape(degree + 1, 3, 3)  # [k, j, i]
    return np.transpose(m_part, (0, 2, 1)), A[3 * (degree + 1):]


def model_to_coefficients(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Inverse of :func:`coefficients_to_model`."""
    degree = M.shape[0] - 1
    return np.vstack([np.transpose(M, (0, 2, 1)).reshape(3 * (degree + 1), 3), b])


class TemperatureClusters:
    """The temperature levels (chamber set-points) of samples added in any number of parts.

    Sorted temperatures further apart than ``gap_c`` separate clusters, so a cluster is fully
    described by its lowest and highest temperature: the clusters of a union of samples are the
    clusters of the parts merged wherever the gap between neighbours is <= ``gap_c``. State: two
    floats per cluster, so the streamed fit (``fit_stream.prepare_stream``) adds a file block by
    block and :func:`temperature_levels` adds an array at once, with the same result. A cluster wider
    than ``max_width_c`` (a slow sweep rather than a set-point) is split into equal-width bins no
    wider than ``max_width_c``, so a continuous sweep counts as several levels for identifiability
    and for hold-out by temperature (:meth:`labels`; empty bins are dropped by the caller).
    """

    def __init__(self, gap_c: float, max_width_c: float = DEFAULT_LEVEL_WIDTH_C) -> None:
        self.gap_c, self.max_width_c = gap_c, max_width_c
        self.lo = np.zeros(0)
        self.hi = np.zeros(0)

    def add(self, temp_c: np.ndarray) -> None:
        """Add finite temperatures (degC)."""
        t = np.sort(np.asarray(temp_c, dtype=float))
        if len(t) == 0:
            return
        brk = np.flatnonzero(np.diff(t) > self.gap_c)
        lo = np.r_[self.lo, t[np.r_[0, brk + 1]]]
        hi = np.r_[self.hi, t[np.r_[brk, len(t) - 1]]]
        order = np.argsort(lo, kind="stable")
        out_lo, out_hi = [lo[order[0]]], [hi[order[0]]]
        for a, b in zip(lo[order[1:]], hi[order[1:]], strict=True):
            if a - out_hi[-1] > self.gap_c:
                out_lo.append(a)
                out_hi.append(b)
            else:
                out_hi[-1] = max(out_hi[-1], b)
        self.lo, self.hi = np.asarray(out_lo), np.asarray(out_hi)

    def finish(self) -> None:
        """Fix the bins of each cluster (after all samples were added)."""
        self.bins = np.array([max(1, int(np.ceil((h - lo) / self.max_width_c - 1e-9))) for lo, h in zip(self.lo, self.hi,
                                                                                                    strict=True)], int)
        self.offset = np.r_[0, np.cumsum(self.bins)[:-1]].astype(np.int64)
        self.n_labels = int(self.bins.sum())

    def labels(self, temp_c: np.ndarray) -> np.ndarray:
        """Provisional level labels (N,), ordered by temperature, of temperatures that were added."""
        t = np.asarray(temp_c, dtype=float)
        c = np.searchsorted(self.lo, t, side="right") - 1
        out = self.offset[c].copy()
        for ci in np.flatnonzero(self.bins > 1):
            sel = c == ci
            lo, hi, bins = self.lo[ci], self.hi[ci], int(self.bins[ci])
            out[sel] += np.minimum(((t[sel] - lo) / max((hi - lo) / bins, 1e-12)).astype(int), bins - 1)
        return out


def temperature_levels(temp_c: np.ndarray, gap_c: float = DEFAULT_LEVEL_GAP_C,
                       max_width_c: float = DEFAULT_LEVEL_WIDTH_C) -> tuple[np.ndarray, np.ndarray]:
    """Cluster temperatures into levels (:class:`TemperatureClusters`). Returns ``(labels (N,), level_means_c
    (L,))`` with levels ordered by temperature and numbered without gaps; NaN temperatures get label -1."""
    t = np.asarray(temp_c, dtype=float)
    labels = np.full(t.shape, -1, dtype=int)
    ok = np.isfinite(t)
    if not ok.any():
        return labels, np.zeros(0)
    clusters = TemperatureClusters(gap_c, max_width_c)
    clusters.add(t[ok])
    clusters.finish()
    provisional = clusters.labels(t[ok])
    present = np.flatnonzero(np.bincount(provisional))  # drop empty bins
    relabel = np.zeros(clusters.n_labels, dtype=np.int64)
    relabel[present] = np.arange(len(present))
    lab = relabel[provisional]
    labels[ok] = lab
    return labels, np.bincount(lab, weights=t[ok]) / np.bincount(lab)


@dataclass
class CellStats:
    """Normal-equation sums per cell (pose x temperature level x run) for the maximum degree.

    ``xtx`` (C, p, p), ``xtg`` (C, p, 3), ``gtg`` (C, 3), ``xsum`` (C, p), ``gsum`` (C, 3),
    ``count`` (C,), with ``p = 4(degree+1)``; ``pose`` (C,) and ``level`` (C,) label the cells. A pose id
    names an orientation within its run only (two runs of other plans may give one id to two orientations),
    so a cell is one run's (cells of one pose and level in two runs are ordered by run). ``visit_outer``
    (p, p) is the sum over the visits (contiguous stays at one pose) of xsum_v xsum_v^T / n_v and
    ``visit_lengths`` their n_v (``n_visits`` their number): the noise floor is the scatter within a visit
    (:meth:`visit_scatter`), not the difference between two visits of one cell.

    ``visit_xtx`` (V, p, p), ``visit_xtg`` (V, p, 3), ``visit_cell`` (V,) and ``visit_run`` (V,) are each visit's own
    X^T X, X^T G, cell (index into the cells above) and run id, in the order the visits ended: the clusters of the
    coefficient covariance (``coefficient_uncertainty``) and the runs of the slow error (``slow_error``).
    Empty (V = 0) when the visits were more than :data:`MAX_VISIT_SUMS`.
    """

    degree: int
    pose: np.ndarray
    level: np.ndarray
    xtx: np.ndarray
    xtg: np.ndarray
    gtg: np.ndarray
    xsum: np.ndarray
    gsum: np.ndarray
    count: np.ndarray
    visit_outer: np.ndarray
    visit_lengths: np.ndarray  # (n_visits,) samples of each visit
    visit_xtx: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))
    visit_xtg: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))
    visit_cell: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    visit_run: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (V,) the run of each visit

    @property
    def n_visits(self) -> int:
        return len(self.visit_lengths)

    def select(self, cells: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Summed (XtX, XtG, GtG, n) over boolean ``cells`` for a degree <= self.degree."""
        cols = sub_columns(degree, self.degree)
        xtx = self.xtx[cells].sum(axis=0)[np.ix_(cols, cols)]
        xtg = self.xtg[cells].sum(axis=0)[cols]
        return xtx, xtg, self.gtg[cells].sum(axis=0), float(self.count[cells].sum())

    def cell_rss(self, A: np.ndarray, degree: int, cells: np.ndarray | None = None) -> np.ndarray:
        """Residual sum of squares (C, 3) of coefficients A (degree ``degree``) on each cell; of the boolean ``cells``
        alone (their values the same bit for bit: each cell's is its own sums'), None: of every cell."""
        cols = sub_columns(degree, self.degree)
        xtx, xtg, gtg = (self.xtx, self.xtg, self.gtg) if cells is None else (
            self.xtx[cells], self.xtg[cells], self.gtg[cells])
        xtx = xtx[:, cols][:, :, cols]
        xtg = xtg[:, cols]
        quad = np.einsum("pi,cpq,qi->ci", A, xtx, A)
        lin = np.einsum("pi,cpi->ci", A, xtg)
        return np.maximum(gtg - 2.0 * lin + quad, 0.0)

    def visit_scatter(self, A: np.ndarray, degree: int) -> np.ndarray:
        """Sum of squared deviations (3,) of the calibrated output x A from the mean of its visit:
        sum_v [A^T X_v^T X_v A - (xsum_v A)^2 / n_v] = A^T (X^T X - visit_outer) A."""
        cols = sub_columns(degree, self.degree)
        within = self.xtx.sum(axis=0)[np.ix_(cols, cols)] - self.visit_outer[np.ix_(cols, cols)]
        return np.maximum(np.einsum("pi,pq,qi->i", A, within, A), 0.0)


class CellAccumulator:
    """Per-cell normal-equation sums built chunk by chunk (cells appear as they come).

    The fit's preparation (``fit_stream.prepare_stream``) feeds it chunks of ``chunk`` selected rows across
    blocks and runs, so the sums do not depend on how the runs were read. Memory: one chunk's design matrix
    plus O(cells).
    """

    def __init__(self, degree: int, chunk: int = DEFAULT_CHUNK) -> None:
        self.degree = degree
        self.p = n_params(degree)
        self._buffer = np.empty((chunk, self.p))
        self._index: dict[tuple[int, int], int] = {}  # (run, pose and level key) -> cell
        self._keys: list[tuple[int, int, int]] = []  # (pose, level, run) of each cell
        # per-cell sums, in CellStats' field order, with the shape of one cell's
        self._shapes = {"xtx": (self.p, self.p), "xtg": (self.p, 3), "gtg": (3,), "xsum": (self.p,), "gsum": (3,),
                        "count": ()}
        self._sums: dict[str, list[np.ndarray]] = {name: [] for name in self._shapes}
        # visits (contiguous rows of one cell): sum of xsum xsum^T / n over the closed ones, and the open one
        self._visit_outer = np.zeros((self.p, self.p))
        self._visit_n: list[int] = []
        self._open: tuple[int, int] | None = None  # (run, cell key) of the visit the last chunk ended in
        self._open_sum = np.zeros(self.p)
        self._open_n = 0
        # each visit's own X^T X and X^T G (the open one last), and its (run, cell key); None once too many
        self._visit_sums: list[tuple[np.ndarray, np.ndarray]] | None = []
        self._visit_keys: list[tuple[int, int]] = []

    def _cell(self, run: int, key: int) -> int:
        c = self._index.get((run, key))
        if c is None:
            c = self._index[(run, key)] = len(self._keys)
            self._keys.append((key >> 32, (key & 0xFFFFFFFF) - _LEVEL_OFFSET, run))
            for name, shape in self._shapes.items():
                self._sums[name].append(np.zeros(shape))
        return c

    def add(self, psi: np.ndarray, tau: np.ndarray, gref: np.ndarray, pose: np.ndarray, level: np.ndarray,
            run: np.ndarray | None = None) -> None:
        """Add one chunk (at most ``chunk`` rows): Psi (n, 3), tau (n,), reference (n, 3) m/s^2, pose, level and
        run (None: one run) of each row; a run's rows are together."""
        if len(tau) == 0:
            return
        X = design_matrix(psi, tau, self.degree, out=self._buffer)
        G = np.asarray(gref, dtype=float)
        pose = np.asarray(pose, np.int64)
        level = np.asarray(level, np.int64)
        if level.min() < -_LEVEL_OFFSET or level.max() >= _LEVEL_OFFSET:
            raise ValueError(f"temperature level labels must lie in [-{_LEVEL_OFFSET}, {_LEVEL_OFFSET})")
        key = (pose << 32) + (level + _LEVEL_OFFSET)
        runs = [(0, 0, len(key))] if run is None else _runs_of(np.asarray(run, np.int64))
        # (cell, rows, their X^T X and X^T G when the visit sums worked them out already, else None)
        segments: list[tuple[int, slice | np.ndarray, tuple[np.ndarray, np.ndarray] | None]] = []
        for r, lo, hi in runs:
            k = key[lo:hi]
            change = np.flatnonzero(k[1:] != k[:-1]) + 1
            pieces = self._add_visits(X[lo:hi], G[lo:hi], r, k, change)
            if len(change) < len(k) // 64:  # samples come pose by pose: contiguous slices, no copy
                bounds = np.r_[0, change, len(k)] + lo
                segments += [(self._cell(r, int(key[a])), slice(a, b), pieces[j] if pieces else None)
                             for j, (a, b) in enumerate(itertools.pairwise(bounds))]
            else:  # interleaved cells: group by sorting
                order = np.argsort(k, kind="stable") + lo
                ks = key[order]
                bounds = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1], True])
                segments += [(self._cell(r, int(ks[a])), order[a:b], None) for a, b in itertools.pairwise(bounds)]
        sums = self._sums
        for c, rows, done in segments:
            Xc, Gc = X[rows], G[rows]
            xtx, xtg = done if done is not None else (Xc.T @ Xc, Xc.T @ Gc)
            sums["xtx"][c] += xtx
            sums["xtg"][c] += xtg
            sums["gtg"][c] += np.einsum("ni,ni->i", Gc, Gc)
            sums["xsum"][c] += Xc.sum(axis=0)
            sums["gsum"][c] += Gc.sum(axis=0)
            sums["count"][c] += len(Gc)

    def _add_visits(self, X: np.ndarray, G: np.ndarray, run: int, key: np.ndarray,
                    change: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]] | None:
        """Column sums of each visit in rows ``X`` of one run (time order; ``key`` their cells, ``change`` where
        it changes; ``G`` the rows' reference): a visit ends where the cell or the run changes; the last one stays
        open, for the next chunk to continue. Returns each piece's X^T X and X^T G (:meth:`_add_visit_sums`)."""
        starts = np.r_[0, change]
        sums = np.add.reduceat(X, starts, axis=0)
        counts = np.diff(np.r_[starts, len(key)])
        goes_on = self._open == (run, int(key[0]))  # the visit the previous chunk ended in goes on
        if goes_on:
            sums[0] += self._open_sum
            counts[0] += self._open_n
        else:
            self._close_visit()
        pieces = self._add_visit_sums(X, G, run, key, starts, goes_on)
        if len(starts) > 1:
            closed = sums[:-1] / np.sqrt(counts[:-1, None])
            self._visit_outer += closed.T @ closed
            self._visit_n.extend(counts[:-1].tolist())
        self._open, self._open_sum, self._open_n = (run, int(key[-1])), sums[-1].copy(), int(counts[-1])
        return pieces

    def _add_visit_sums(self, X: np.ndarray, G: np.ndarray, run: int, key: np.ndarray, starts: np.ndarray,
                        goes_on: bool) -> list[tuple[np.ndarray, np.ndarray]] | None:
        """Each visit's own X^T X and X^T G (the first continues the open visit when ``goes_on``); returns those of
        the pieces of this chunk (the cells' sums reuse them), None when the visits are not kept."""
        kept = self._visit_sums
        if kept is None:
            return None
        if len(kept) + len(starts) > MAX_VISIT_SUMS:
            self._visit_sums, self._visit_keys = None, []
            return None
        ends = np.r_[starts[1:], len(key)]
        pieces = []
        for i, (a, b) in enumerate(zip(starts.tolist(), ends.tolist(), strict=True)):
            xtx, xtg = X[a:b].T @ X[a:b], X[a:b].T @ G[a:b]
            pieces.append((xtx, xtg))
            if i == 0 and goes_on:
                kept[-1][0][...] += xtx
                kept[-1][1][...] += xtg
            else:
                kept.append((xtx.copy(), xtg.copy()))  # its own: the open visit's grows in place
                self._visit_keys.append((run, int(key[a])))
        return pieces

    def _close_visit(self) -> None:
        if self._open is not None:
            self._visit_outer += np.outer(self._open_sum, self._open_sum) / self._open_n
            self._visit_n.append(self._open_n)
            self._open = None

    def finish(self, level_map: np.ndarray | None = None) -> CellStats:
        """The sums as :class:`CellStats`, cells ordered by (pose, level, run); ``level_map`` relabels levels."""
        self._close_visit()
        keys = np.asarray(self._keys, dtype=np.int64).reshape(-1, 3)
        if level_map is not None:
            keys[:, 1] = level_map[keys[:, 1]]
        order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))
        sums = [np.asarray(self._sums[name], dtype=float).reshape(-1, *shape)[order]
                for name, shape in self._shapes.items()]
        p = self.p
        if self._visit_sums:  # visits in the order they ended, each with its cell's index in the ordered cells
            rank = np.empty(len(order), np.int64)
            rank[order] = np.arange(len(order))
            visit_xtx = np.array([v[0] for v in self._visit_sums])
            visit_xtg = np.array([v[1] for v in self._visit_sums])
            visit_cell = rank[[self._index[k] for k in self._visit_keys]]
            visit_run = np.array([k[0] for k in self._visit_keys], np.int64)
        else:
            visit_xtx, visit_xtg, visit_cell = np.zeros((0, p, p)), np.zeros((0, p, 3)), np.zeros(0, np.int64)
            visit_run = np.zeros(0, np.int64)
        return CellStats(self.degree, keys[order, 0], keys[order, 1], *sums, self._visit_outer.copy(),
                         np.asarray(self._visit_n, dtype=np.int64), visit_xtx, visit_xtg, visit_cell, visit_run)


def _runs_of(run: np.ndarray) -> list[tuple[int, int, int]]:
    """(run, first row, end row) of each stretch of one run in ``run`` (n,)."""
    cuts = np.r_[0, np.flatnonzero(run[1:] != run[:-1]) + 1, len(run)]
    return [(int(run[a]), int(a), int(b)) for a, b in itertools.pairwise(cuts)]


def accumulate_cells(psi: np.ndarray, tau: np.ndarray, gref: np.ndarray, pose: np.ndarray, level: np.ndarray,
                     degree: int, chunk: int = DEFAULT_CHUNK) -> CellStats:
    """Stream the samples in chunks of ``chunk`` rows into per-cell normal-equation sums."""
    acc = CellAccumulator(degree, min(chunk, max(len(tau), 1)))
    for start in range(0, len(tau), chunk):
        sl = slice(start, start + chunk)
        acc.add(psi[sl], tau[sl], gref[sl], pose[sl], level[sl])
    return acc.finish()


def _cell_mean_spread(gsum: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RMS spreads (3,), ascending, and principal directions (3, 3 columns) of the cells' means ``gsum / count``
    (the reference specific force, m/s^2, or Psi), weighted by sample count."""
    means = gsum / count[:, None]
    d = means - (count[:, None] * means).sum(axis=0) / count.sum()
    eig, vec = np.linalg.eigh((count[:, None, None] * d[:, :, None] * d[:, None, :]).sum(axis=0) / count.sum())
    return np.sqrt(np.maximum(eig, 0.0)), vec


def _direction_text(v: np.ndarray) -> str:
    """"(x, y, z)" of the unit vector ``v`` signed so that its largest component is positive (0.00, not -0.00)."""
    u = v * np.sign(v[np.argmax(np.abs(v))])
    u = np.where(np.abs(u) < 5e-3, 0.0, u)
    return f"({u[0]:.2f}, {u[1]:.2f}, {u[2]:.2f})"


ORIENTATION_TOLERANCE_DEG = 1.0  # cells whose mean reference directions are closer are one orientation


def count_orientations(stats: CellStats, tolerance_deg: float = ORIENTATION_TOLERANCE_DEG) -> int:
    """Distinct table orientations among the cells: directions of their mean reference specific force that
    differ by more than ``tolerance_deg``. Not the distinct pose ids: an id names an orientation within its
    run only (two runs of other plans may give one id to two orientations, and one plan's runs repeat them)."""
    count = np.asarray(stats.count, dtype=float)
    g = stats.gsum[count > 0] / count[count > 0, None]
    norm = np.linalg.norm(g, axis=1)
    u = g[norm > 0] / norm[norm > 0, None]
    cos_tol = math.cos(math.radians(tolerance_deg))
    seen: list[np.ndarray] = []
    for v in u:
        if not any(float(v @ w) > cos_tol for w in seen):
            seen.append(v)
    return len(seen)


def level_excitation(stats: CellStats, min_spread_mps2: float = MIN_POSE_SPREAD_MPS2) -> tuple[int, list[str]]:
    """Temperature levels whose own poses span the table frame: ``(count, notes on the others)``.

    A temperature term M_k, b_k (k >= 1) along a direction is determined only by levels that excite that
    direction: with coplanar poses at one level (e.g. that level's run stopped after its 4th pose) the
    degree-n polynomial along the plane's normal passes through n levels only. Degree n >= 1 therefore
    needs n + 1 fully excited levels (:func:`fit_thermal` refuses it, ``model_selection`` marks it not
    identified)."""
    ok, notes = 0, []
    for lev in np.unique(stats.level):
        sel = stats.level == lev
        spread, vec = _cell_mean_spread(stats.gsum[sel], np.asarray(stats.count[sel], dtype=float))
        if spread[0] >= min_spread_mps2:
            ok += 1
        else:
            notes.append(f"temperature level {int(lev)}: its {len(np.unique(stats.pose[sel]))} poses do not tilt "
                         f"the table direction {_direction_text(vec[:, 0])} (spread {spread[0]:.3g} m/s^2)")
    return ok, notes


def check_level_excitation(stats: CellStats, degree: int) -> None:
    """Refuse a temperature degree that the fully excited levels cannot determine (:func:`level_excitation`)."""
    if degree < 1:
        return
    ok, notes = level_excitation(stats)
    if degree >= ok:
        raise NotIdentifiedError(
            f"degree {degree} in temperature needs {degree + 1} temperature levels whose poses span the table "
            f"frame, only {ok} do ({'; '.join(notes)}); use degree <= {max(ok - 1, 0)} or repeat the pose plan "
            "at that level")


# Largest change of M between two temperature levels, relative (Frobenius): the sensitivity of the optical pairs
# moves by a few % over the calibrated range (the shipped simulated sensor's M: 5 % over 16-45 degC, the thermal
# terms of the paper's eq. 28); a level whose M differs by more is a different convention, not a temperature effect.
LEVEL_M_CHANGE_MAX = 0.3


def check_level_consistency(stats: CellStats, level_means_c: np.ndarray) -> None:
    """Refuse temperature levels whose own fit (eq. 25 at that level, M and b from its poses alone) disagrees with the
    other levels' far beyond what temperature does (:data:`LEVEL_M_CHANGE_MAX`): one level's reference gravity with
    its sign flipped, its x and y swapped, or in another unit gives a small in-sample RMSE (a polynomial of degree
    L - 1 in temperature passes through any L levels) and a calibration metres per second squared off the truth. With
    three levels or more, each is compared with the median of all; with two, with each other."""
    fits: dict[int, np.ndarray] = {}
    for lev in np.unique(stats.level):
        sel = stats.level == lev
        spread, _ = _cell_mean_spread(stats.gsum[sel], np.asarray(stats.count[sel], dtype=float))
        if spread[0] < MIN_POSE_SPREAD_MPS2:
            continue  # its poses do not determine M (level_excitation)
        xtx, xtg, _, _ = stats.select(sel, 0)
        try:
            A, _ = solve_normal_equations(xtx, xtg)
        except NotIdentifiedError:
            continue
        fits[int(lev)] = coefficients_to_model(A, 0)[0][0]
    if len(fits) < 2:
        return
    levels = sorted(fits)
    ms = np.array([fits[lev] for lev in levels])
    centre = np.median(ms, axis=0) if len(ms) >= 3 else None
    change = [float(np.linalg.norm(m - (centre if centre is not None else ms[1 - i])) /
                    np.linalg.norm(centre if centre is not None else ms[1 - i])) for i, m in enumerate(ms)]
    bad = [i for i, c in enumerate(change) if not c <= LEVEL_M_CHANGE_MAX]
    if not bad or (centre is None and len(bad) < 2):
        return
    good = [c for i, c in enumerate(change) if i not in bad]
    what = ", ".join(f"{level_means_c[levels[i]]:.1f} degC ({100 * change[i]:.0f} %)" for i in bad)
    raise NotIdentifiedError(
        f"the temperature level(s) at {what} give an M that differs from the "
        + ("other levels'" if centre is not None else "other level's")
        + f" by more than {100 * LEVEL_M_CHANGE_MAX:.0f} %"
        + (f" (the others: within {100 * max(good):.0f} %)" if good else "")
        + ", far beyond what temperature changes (a few %): gravity in g? a sign or axis convention of that "
          "level's reference gravity?")


def check_pose_excitation(stats: CellStats, min_spread_mps2: float = MIN_POSE_SPREAD_MPS2) -> np.ndarray:
    """Refuse a pose set that does not excite every direction of the table frame.

    The reference specific force of each cell (its mean, m/s^2, table frame) is weighted by the cell's
    sample count; the square roots of the eigenvalues of their centred scatter are the RMS spreads of
    the poses along the principal directions. Returns the spreads (3,) sorted ascending; raises
    :class:`NotIdentifiedError` naming the weakest direction (and the output axis it is closest to)
    when its spread is below ``min_spread_mps2``.
    """
    count = np.asarray(stats.count, dtype=float)
    if len(count) == 0 or count.sum() <= 0:
        raise NotIdentifiedError("no usable static samples")
    spread, vec = _cell_mean_spread(stats.gsum, count)
    if not spread[0] >= min_spread_mps2:
        axis = "xyz"[int(np.argmax(np.abs(vec[:, 0])))]
        n_poses = count_orientations(stats)
        shape = "coincide" if spread[2] < min_spread_mps2 else ("are collinear" if spread[1] < min_spread_mps2
                                                               else "are coplanar")
        raise NotIdentifiedError(
            f"the {n_poses} poses' reference specific forces {shape}: their RMS spread along the table direction "
            f"{_direction_text(vec[:, 0])} is {spread[0]:.3g} m/s^2 (< {min_spread_mps2:.3g}), so the {axis} row "
            "of M and b would be fitted to a constant (a dead axis); record poses that tilt that axis too "
            "(at least 4 non-coplanar poses, e.g. the six-position plan)")
    psi_spread, vec_p = _cell_mean_spread(stats.xsum[:, 0:3], count)  # columns 0..2 of eq. 29: Psi at k = 0
    if not psi_spread[0] > MIN_SIGNAL_SPREAD_RATIO * psi_spread[2]:
        if not psi_spread[2] > 1e-9:
            why = "the counts give the same Psi = counts / ref in every pose (identical samples?)"
        else:
            why = (f"the sensor's Psi = counts / ref barely changes along {_direction_text(vec_p[:, 0])} "
                   f"between poses ({psi_spread[0]:.3g}, vs {psi_spread[2]:.3g} along the strongest direction)")
        raise NotIdentifiedError(f"{why}: a channel is dead, saturated or copied, so M cannot be determined; "
                                 "check the x/y/z_counts columns and the fibre connections")
    return spread


def reference_range(stats: CellStats) -> np.ndarray:
    """(3, 2): the lowest and highest reference specific force (m/s^2) of the cells' means along each table axis
    x, y, z: the range of accelerations the calibration was fitted on."""
    count = np.asarray(stats.count, dtype=float)
    g = stats.gsum[count > 0] / count[count > 0, None]
    return np.column_stack([g.min(axis=0), g.max(axis=0)])


def reference_reach_warnings(rng: np.ndarray | list, reach_mps2: float = MIN_REFERENCE_REACH_MPS2) -> list[str]:
    """One line per table axis along which the poses (``reference_range``, (3, 2) m/s^2, the YAML's
    ``fit.reference_range_mps2``) do not reach ``reach_mps2`` both ways: a calibration accepted by the excitation check
    whose output there is an extrapolation of eq. 28 (the pose hold-out tests only the orientations recorded)."""
    out = []
    for k, (lo, hi) in enumerate(np.asarray(rng, dtype=float).reshape(3, 2)):
        ways = [w for w, short in (("down", lo > -reach_mps2), ("up", hi < reach_mps2)) if short]
        if ways:
            axis = "xyz"[k]
            out.append(f"the poses never reach {reach_mps2:.2f} m/s^2 (half of g) with the table {axis} axis "
                       f"{' or '.join(ways)} (their reference along it spans {lo:+.2f} .. {hi:+.2f} m/s^2): beyond that "
                       "the calibration extrapolates eq. 28 over a response it never saw, which the held-out figures "
                       f"cannot show; record poses with {axis} {' and '.join(ways)}")
    return out


def check_recording_excitation(rec: Recording) -> np.ndarray:
    """:func:`check_pose_excitation` on every sample of a recording that has a pose, a finite reference,
    a valid temperature, finite Psi and source light (``Recording.low_reference``) (no static detection: a cheap
    check before a long computation)."""
    psi = normalise(rec.xyz, rec.ref)
    ok = (rec.pose_id >= 0) & np.all(np.isfinite(rec.gref_mps2), axis=1) & np.isfinite(rec.temp_c)
    ok &= np.all(np.isfinite(psi), axis=1) & ~rec.low_reference()
    if not np.any(rec.pose_id >= 0):
        raise NotIdentifiedError(f"no pose was held: every one of the {len(rec.pose_id)} samples was taken while the "
                                 "table moved, so nothing static can be fitted; record with the table stopped at each pose")
    if not ok.any():
        raise NotIdentifiedError("no sample has a pose, a finite reference, a valid temperature and finite counts")
    stats = accumulate_cells(psi[ok], np.zeros(int(ok.sum())), rec.gref_mps2[ok], rec.pose_id[ok],
                             np.zeros(int(ok.sum()), np.int64), 0)
    return check_pose_excitation(stats)


def jacobi_scaling(xtx: np.ndarray, min_diagonal: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Jacobi (column) scaling of a normal matrix X^T X (p, p): the column norms d = sqrt(diag(X^T X)) (p,) and the
    scaled matrix X^T X / (d d^T), whose diagonal is 1. Why: eq. 28's regressors differ by orders of magnitude (counts
    ratios near 1 against their products with powers of the scaled temperature, an effect's column in m/s^2 or
    seconds), so X^T X itself is ill-conditioned by its units alone; scaled, its condition number measures only how
    nearly collinear the regressors are, and the solve loses no digits to the units. ``min_diagonal`` > 0: the
    diagonal is floored there first (a held-out training set may lack a regressor; the solve then fails on the
    singular matrix, not on a division by zero). Raises :class:`NotIdentifiedError` when a column is zero."""
    diag = np.diagonal(xtx, axis1=-2, axis2=-1)  # (a stack of them: each one's, ``solve_normal_equations_each``)
    d = np.sqrt(np.maximum(diag, min_diagonal) if min_diagonal > 0.0 else diag)
    if np.any(d <= 0.0):
        raise NotIdentifiedError("a regressor is identically zero on the data")
    return d, xtx / (d[..., :, None] * d[..., None, :])


def jacobi_solve(xtx: np.ndarray, rhs: np.ndarray, min_diagonal: float = 0.0) -> np.ndarray:
    """Z with X^T X Z = ``rhs`` (p, k), solved on the Jacobi-scaled matrix (:func:`jacobi_scaling`, the reason and
    ``min_diagonal`` there): Z = D^-1 S^-1 D^-1 rhs with S = D^-1 X^T X D^-1, D = diag(d). ``rhs`` = X^T G gives the
    least-squares coefficients of eq. 28 (:func:`solve_normal_equations`); other right-hand sides give B^-1 applied
    to a design's column sums (the slow error, the held-out residual's null covariance). No check of the condition
    number (``solve_normal_equations`` does it); ``np.linalg.LinAlgError`` when S is exactly singular."""
    return _scaled_solve(*jacobi_scaling(xtx, min_diagonal), rhs)


def _scaled_solve(d: np.ndarray, s: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """:func:`jacobi_solve` given the scaling (d, S) of X^T X (:func:`jacobi_scaling`)."""
    return np.linalg.solve(s, rhs / d[..., None]) / d[..., None]


def scaled_condition(xtx: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Jacobi scaling of X^T X: (column norms d, scaled matrix, its condition number; inf if singular)."""
    d, s = jacobi_scaling(xtx)
    eig = np.linalg.eigvalsh(s)
    return d, s, float(eig[-1] / eig[0]) if eig[0] > 0 else float("inf")


def solve_normal_equations(xtx: np.ndarray, xtg: np.ndarray, rcond: float = 1e-12) -> tuple[np.ndarray, float]:
    """Solve (X^T X) A = X^T G with Jacobi scaling (:func:`jacobi_solve`); returns (A, condition number of the scaled
    X^T X).

    Raises :class:`NotIdentifiedError` when the scaled matrix is (numerically) singular.
    """
    d, s, cond = scaled_condition(xtx)
    if not cond < 1.0 / rcond:
        raise NotIdentifiedError(f"normal equations are singular (condition number {cond:.3g})")
    return _scaled_solve(d, s, xtg), cond  # jacobi_solve on the scaling the condition number was taken of


def solve_normal_equations_each(xtx: np.ndarray, xtg: np.ndarray, rcond: float = 1e-12) -> np.ndarray:
    """``solve_normal_equations(xtx[k], xtg[k])[0]`` of each of a stack of normal equations (``xtx`` (K, p, p),
    ``xtg`` (K, p, q)): (K, p, q), the same bits, and the error of the first of them that raises. numpy's linear
    algebra works each matrix of a stack by the same LAPACK call as it does one alone, so the K folds of a
    cross-validation cost one call of each step, not K (the solve of a dozen coefficients is mostly numpy's own
    overhead). A stack of which one would raise is solved one by one, so that the same one raises."""
    with np.errstate(divide="ignore", invalid="ignore"):
        try:
            d, s = jacobi_scaling(xtx)
            eig = np.linalg.eigvalsh(s)
            if np.all(eig[:, 0] > 0) and np.all(eig[:, -1] / eig[:, 0] < 1.0 / rcond):  # scaled_condition's test
                return _scaled_solve(d, s, xtg)
        except (NotIdentifiedError, np.linalg.LinAlgError):
            pass
    return np.stack([solve_normal_equations(a, b, rcond)[0] for a, b in zip(xtx, xtg, strict=True)])


def temperature_scaling(temp_c: np.ndarray) -> tuple[float, float]:
    """Centre and half-range (degC) mapping the data's temperatures onto [-1, 1] (scale 1 for one level)."""
    lo, hi = float(np.min(temp_c)), float(np.max(temp_c))
    half = (hi - lo) / 2.0
    return (lo + hi) / 2.0, half if half > 0.5 else 1.0


def check_identified(degree: int, n_levels: int) -> None:
    """Refuse a degree that L temperature levels cannot determine."""
    if degree < 0:
        raise NotIdentifiedError(f"degree must be >= 0, got {degree}")
    if degree >= n_levels:
        raise NotIdentifiedError(
            f"degree {degree} in temperature is not identified by {n_levels} temperature level(s): "
            f"a polynomial of degree >= L through L levels is not unique; use degree <= {n_levels - 1} "
            "or record more temperature levels")


UNNAMED_SENSOR_IDS = frozenset({"", "unknown"})  # the calibration node's and import's default: names no sensor


def _recorded_sensor_id(md: object) -> str | None:
    """The sensor id one recording's metadata holds (its ``run`` record, else a top-level ``sensor_id``), if any."""
    if not isinstance(md, dict):
        return None
    for candidate in (md.get("run"), md):
        if isinstance(candidate, dict) and candidate.get("sensor_id"):
            return printable(str(candidate["sensor_id"]))  # escaped: echoed in messages, stored in the calibration
    return None


def sensor_id_of(md: dict) -> str | None:
    """The sensor id a recording's metadata names (one recording's, or every part's of several), if any.

    Raises ``ValueError`` when the parts name different sensors: a calibration describes one sensor, and the
    recordings of two cannot be fitted, diagnosed or reported as one (``fit runs/*.mcap`` over a directory that
    holds two sensors' runs used to write a calibration named after the first file's sensor, silently).
    Parts that name no sensor (``unknown``) do not count."""
    parts = md.get("parts")
    parts = parts if isinstance(parts, list) and parts else [md]
    named: dict[str, list[str]] = {}
    recorded = None
    for i, part in enumerate(parts):
        sid = _recorded_sensor_id(part)
        recorded = recorded or sid
        if sid is not None and sid not in UNNAMED_SENSOR_IDS:
            source = part.get("source") if isinstance(part, dict) else None
            named.setdefault(sid, []).append(str(source) if source else f"input {i + 1}")
    if len(named) > 1:
        listing = "; ".join(f"sensor '{sid}': {', '.join(srcs)}" for sid, srcs in named.items())
        raise ValueError(f"the recordings are of {len(named)} different sensors ({listing}); a calibration describes "
                         "one sensor: give the recordings of one sensor only")
    if named:
        return next(iter(named))
    return recorded or _recorded_sensor_id(md)  # 'unknown' as recorded, or None


def residuals(cal: ThermalCalibration, rec: Recording, mask: np.ndarray | None = None) -> np.ndarray:
    """Calibrated output minus reference (N, 3) m/s^2 (eq. 28 without corrections) on ``mask``."""
    sel = rec if mask is None else rec.select(mask)
    psi = normalise(sel.xyz, sel.ref)
    return cal.base_acceleration(psi, sel.temp_c) - sel.gref_mps2
