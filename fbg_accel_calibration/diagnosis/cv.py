"""Cross-validation by visit: the folds (``make_folds``, ``check_folds``), K-fold fits from per-fold normal equations
(``cross_validate``), the training RSS of a switched effect at every value from one pass (``switch_profile``), ties
up to rounding (``first_min``) and the conditioning checks of a fit (``cancelling_terms``, ``gram_conditioning``).
"""

from __future__ import annotations

import weakref
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..fit.thermal_fit import (
    NotIdentifiedError,
    scaled_condition,
    solve_normal_equations,
    solve_normal_equations_each,
    temperature_levels,
)
from .data import DiagnosisData, finite_rows, rows_at, rows_in_order, set_rows

# ============================================================================ data preparation
from .design import (
    Design,
)
from .effects import MIN_SPAN_FRACTION


# ============================================================================ cross-validation
def make_folds(groups: np.ndarray, rows: np.ndarray, k: int = 10, seed: int = 0, time_blocks: bool = False) -> np.ndarray:
    """Fold index (N,) per sample (-1 outside ``rows``): whole visits are assigned to folds at random (``seed``) or, with
    ``time_blocks``, the visits in recording order (the order of their first samples) cut into ``k`` contiguous blocks,
    so a held-out visit has no training neighbour in time on one side at least (``time_block_check``)."""
    ug, inv = np.unique(groups[rows], return_inverse=True)
    k = int(min(k, len(ug)))
    if k < 2:
        raise ValueError("need at least two visits for cross-validation")
    fold_of_group = np.empty(len(ug), int)
    if time_blocks:
        first = np.full(len(ug), len(groups))
        np.minimum.at(first, inv, np.flatnonzero(rows))
        fold_of_group[np.argsort(first)] = np.arange(len(ug)) * k // len(ug)
    else:
        fold_of_group[np.random.default_rng(seed).permutation(len(ug))] = np.arange(len(ug)) % k
    out = np.full(len(groups), -1)
    out[rows] = fold_of_group[inv]
    return out


# The reference of a training set must span the table frame: its weakest direction (smallest
# standard deviation of the visit-mean reference) must keep this fraction of the whole data's
# (effects.MIN_SPAN_FRACTION: each side of a step is held to it too).


def _reference_spread(gmean: np.ndarray) -> tuple[float, np.ndarray]:
    """(standard deviation m/s^2, unit direction (3,)) of the weakest direction of visit-mean references
    (V, 3), table frame. An affine model (eq. 25: M Psi + b) is identified along a direction only if
    the reference varies along it."""
    if len(gmean) < 2:
        return 0.0, np.array([0.0, 0.0, 1.0])
    c = gmean - gmean.mean(axis=0)
    w, v = np.linalg.eigh(c.T @ c / len(gmean))
    return float(np.sqrt(max(w[0], 0.0))), v[:, 0]


def _visit_levels(temp_c: np.ndarray, inv: np.ndarray, n_visits: int) -> np.ndarray:
    """Temperature level (``thermal_fit.temperature_levels`` of the samples ``temp_c``) of each of ``n_visits``
    visits (``inv``: the visit of each sample): the level most of its samples are at, -1 if none has a valid
    temperature."""
    labels, means = temperature_levels(temp_c)
    counts = np.bincount(inv * (len(means) + 1) + labels + 1, minlength=n_visits * (len(means) + 1))
    counts = counts.reshape(n_visits, len(means) + 1)[:, 1:]
    return np.where(counts.sum(axis=1) > 0, np.argmax(counts, axis=1), -1) if len(means) else np.full(n_visits, -1)


def check_folds(data: DiagnosisData, groups: np.ndarray, folds: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Make every fold identifiable; returns (new folds (N,), notes for the report).

    A fold is identifiable when the visits left for training still span the table frame: the
    weakest direction of their visit-mean reference (m/s^2, table frame) keeps at least
    ``MIN_SPAN_FRACTION`` of the whole data's spread. A fold that holds out every visit exciting one
    direction (e.g. both +z and -z of a six-position plan) would otherwise predict a constant along
    it (held-out residuals of exactly +-g). Such a fold is split into one fold per visit; a visit
    whose own removal still loses a direction (the only one exciting it) is never held out: its fold
    index becomes -2 (kept in every training set and the final fit, excluded from the held-out
    figures), with a note.

    With several temperature levels the same holds for each level whose own visits span the frame: a
    temperature term of eq. 28 along a direction is determined only by the levels that tilt it
    (``thermal_fit.level_excitation``), so a fold holding out both +y and -y of one level would leave
    the degree-2 term along y to two levels and predict that level's y by extrapolation (held-out
    errors of metres per second squared on a clean campaign of three chamber levels).
    """
    rows = data.use & (folds >= 0) & finite_rows(data.gref)
    ug, inv = np.unique(groups[rows], return_inverse=True)
    if len(ug) == 0:
        return folds, []
    cnt = np.bincount(inv).astype(float)
    gmean = np.stack([np.bincount(inv, weights=data.gref[rows, j]) / cnt for j in range(3)], axis=1)
    fold_of = np.zeros(len(ug), int)
    fold_of[inv] = folds[rows]
    pose_of = np.zeros(len(ug), int)
    pose_of[inv] = data.pose_id[rows]
    full_sd, _ = _reference_spread(gmean)
    limit = MIN_SPAN_FRACTION * full_sd
    level_of = _visit_levels(data.temp_c[rows], inv, len(ug))
    spanning = [lev for lev in np.unique(level_of[level_of >= 0])  # levels that identify a temperature term alone
                if _reference_spread(gmean[level_of == lev])[0] >= limit] if len(np.unique(level_of)) > 1 else []
    new_fold = fold_of.copy()
    notes: list[str] = []
    next_fold = int(fold_of.max()) + 1

    def loses(held: np.ndarray) -> tuple[bool, float, np.ndarray, str]:
        sd, direction = _reference_spread(gmean[~held])
        if sd < limit or sd <= 1e-9:
            return True, sd, direction, ""
        for lev in spanning:
            at = level_of == lev
            if held[at].any():
                sd, direction = _reference_spread(gmean[at & ~held])
                if sd < limit or sd <= 1e-9:
                    return True, sd, direction, f" of temperature level {int(lev)}"
        return False, sd, direction, ""

    for f in np.unique(fold_of):
        held = fold_of == f
        bad, sd, direction, where = loses(held)
        if not bad:
            continue
        members = np.flatnonzero(held)
        split, skipped = [], []
        for v in members:
            one = np.zeros(len(ug), bool)
            one[v] = True
            if loses(one)[0]:
                new_fold[v] = -2
                skipped.append(v)
            else:
                new_fold[v] = next_fold
                next_fold += 1
                split.append(v)
        dir_txt = "(" + ", ".join(f"{c:+.2f}" for c in direction) + ")"
        whole = "at that level" if where else f"whole data {full_sd:.3g} m/s^2"
        note = (f"fold {f} held out every visit{where} exciting the table direction {dir_txt} (training reference "
                f"spread {sd:.3g} m/s^2 along it, {whole}): the fit could not predict that direction")
        if split:
            note += f"; split into {len(split)} fold(s) of one visit each"
        if skipped:
            note += ("; visit(s) " + ", ".join(f"{int(ug[v])} (pose {int(pose_of[v])})" for v in skipped)
                     + " alone excite a direction and are never held out (kept in training; not in the held-out figures)")
        notes.append(note)
    if not notes:
        return folds, []
    # renumber the folds in use to 0..K-1 (-2: training only; -1: outside the rows)
    used = np.unique(new_fold[new_fold >= 0])
    remap = {int(u): i for i, u in enumerate(used)}
    out = np.array(folds, copy=True)
    vf = np.array([remap.get(int(x), int(x)) if x >= 0 else int(x) for x in new_fold])
    out[rows] = vf[inv]
    # samples of a visit that are outside ``rows`` only because their reference is not finite keep -1
    if len(used) < 2:
        raise NotIdentifiedError("cross-validation is not possible: no fold can be held out without losing a "
                                 "direction of the table frame (" + "; ".join(notes) + ")")
    return out, notes


@dataclass
class FoldSums:
    """The sums of one design matrix that ``cross_validate`` works out per fold (they do not depend on the
    reference): kept while a search changes the reference alone (``DesignCache``: the same matrix)."""

    X: weakref.ref  # the design matrix (N, p) they are of, and the fold index (N,): compared by identity, not
    folds: weakref.ref  # kept alive by the sums (the final model's matrix is let go once it is fitted)
    idx: np.ndarray  # the fitted rows, in fold order
    xtx: np.ndarray  # (K, p, p) X^T X per fold
    XtX: np.ndarray  # (p, p) over every fitted row
    xsum: np.ndarray  # (p,) column sums over every fitted row

    def of(self, X: np.ndarray, folds: np.ndarray, idx: np.ndarray) -> bool:
        return self.X() is X and self.folds() is folds and np.array_equal(self.idx, idx)


class CvResult:
    """What ``cross_validate`` found. The held-out residual and the in-sample fit (each (N, 3), a pass over the design
    matrix) are worked out when first asked for, by the same products as at once: a search reads its trials' training
    RSS and, of the held-out residual, only the folds a trial fits best (``fold_heldout``). The design's X and G are
    held until both are worked out."""

    def __init__(self, train_rss: np.ndarray, A_full: np.ndarray, sums: FoldSums, X: np.ndarray, G: np.ndarray,
                 start: np.ndarray, A_folds: np.ndarray) -> None:
        self.train_rss = train_rss  # (K,) weighted training RSS per fold
        self.A_full = A_full  # (p, 3) coefficients on all rows
        self.sums = sums  # X^T X per fold and over the fitted rows (all folds), column sums: the conditioning checks
        # (X, G) until both arrays below are worked out: one attribute, read once by each caller, so that a lane that
        # shares the result sees the pair or None (then both arrays are there), never half of it
        self._design: tuple[np.ndarray, np.ndarray] | None = (X, G)
        self._start = start  # fold f's rows are sums.idx[start[f + 2]:start[f + 3]]
        self._A_folds = A_folds  # (K, p, 3) each fold's training coefficients
        self._heldout: np.ndarray | None = None
        self._fitted: np.ndarray | None = None

    def fold_heldout(self, f: int) -> tuple[np.ndarray, np.ndarray]:
        """(the rows of fold ``f`` that were fitted, their held-out residual (n_f, 3) m/s^2)."""
        lo, hi = self._start[f + 2], self._start[f + 3]
        rows = self.sums.idx[lo:hi]
        design = self._design
        if design is None:
            return rows, rows_at(self.heldout, rows)
        X, G = design
        return rows, _fold_part(self.sums.idx, lo, hi, G) - _fold_part(self.sums.idx, lo, hi, X) @ self._A_folds[f]

    @property
    def heldout(self) -> np.ndarray:
        """(N, 3) held-out residual (NaN outside the evaluated rows)."""
        design = self._design
        if self._heldout is None and design is not None:
            out = np.full(design[1].shape, np.nan)
            for f in range(len(self._A_folds)):
                rows, res = self.fold_heldout(f)
                block = _block(rows)
                if block is not None:  # a design in fold order: one block
                    out[block] = res
                else:
                    set_rows(out, rows, res)
            self._heldout = out  # assigned once whole: lanes that share the result read it whole or work it out too
            self._release()
        return self._heldout

    @property
    def fold_coefficients(self) -> np.ndarray:
        """(K, p, 3) each fold's training coefficients (the fit without that fold's visits)."""
        return self._A_folds

    @property
    def fitted_full(self) -> np.ndarray:
        """(N, 3) in-sample prediction with ``A_full``."""
        design = self._design
        if self._fitted is None and design is not None:
            self._fitted = design[0] @ self.A_full
            self._release()
        return self._fitted

    def _release(self) -> None:
        if self._heldout is not None and self._fitted is not None:
            self._design = None

    def let_go(self) -> None:
        """Drop the design and what was worked out of it (the held-out residual, the fit); the coefficients, training
        RSS and sums stay (``on``)."""
        self._design = self._heldout = self._fitted = None

    def on(self, des: Design) -> CvResult:
        """This cross-validation read from ``des``, the design it was of built again (the same matrix, bit for bit):
        its held-out residual and fit worked out from it as they would have been from the first, once the first was let
        go (``let_go``: the declared model's, while the searches run)."""
        return CvResult(self.train_rss, self.A_full, self.sums, des.X, des.G, self._start, self._A_folds)


def _block(rows: np.ndarray) -> slice | None:
    """The slice of ``rows`` (ascending, each once: a fold's rows in ``cross_validate``'s order) when they are
    consecutive (a design in fold order), else None."""
    if len(rows) and rows[-1] - rows[0] == len(rows) - 1:
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return None


def _fold_part(idx: np.ndarray, lo: int, hi: int, of: np.ndarray) -> np.ndarray:
    """``of`` at the rows ``idx[lo:hi]`` (``cross_validate``'s rows in fold order): a view when they are consecutive
    (``_block``), else a copy in the same layout (``rows_in_order``: the products of either, the same bits)."""
    rows = idx[lo:hi]
    block = _block(rows)
    return of[block] if block is not None else rows_in_order(of, rows)


SEARCH_STRIDE = 4  # a search with no start visits every 4th grid value first, then walks from the best (search_batches)


# training RSS that differ by less than this fraction are equal up to rounding: the same fit computed in another
# order (another BLAS kernel, another sum of the same rows). Far above the rounding of a weighted RSS of normal
# equations (~1e-12 relative at 10^6 rows), far below any difference a test over visits can see.
RSS_TIE_RTOL = 1e-9


def first_min(values: np.ndarray) -> int:
    """Index of the first value within ``RSS_TIE_RTOL`` of the smallest (finite; 0 when none is): ``np.argmin``
    with ties up to rounding broken by order, so that the machine's rounding does not choose among equal fits."""
    v = np.asarray(values, float)
    finite = np.isfinite(v)
    if not finite.any():
        return 0
    lo = float(v[finite].min())
    return int(np.flatnonzero(finite & (v <= lo + RSS_TIE_RTOL * abs(lo)))[0])


def search_batches(n: int, seen: dict[int, tuple[bool | None, float]], best_at: np.ndarray,
                   start: tuple[int, ...] = ()) -> Iterator[list[int]]:
    """Indices of a grid of ``n`` hyper-parameter values for a search to visit, chosen from what it has found so far,
    a batch at a time (the values of a batch do not depend on each other's results: ``Evaluator.cv_each``).

    The caller updates, after each index of a batch, ``seen`` (index -> (plausible, mean training RSS over the folds); plausible
    is None for a value that does not identify the model) and ``best_at`` ((K,) the index of the plausible value each
    training fold fits best, ``n`` while none). First the values ``start`` (where a search of the same effect on
    another model ended: ``GridSearch.walked_to``), or, with none, every ``SEARCH_STRIDE``-th value and the last one;
    then, batch by batch, the nearest plausible value not yet visited on each side of each fold's best and of the
    best mean (values not plausible or not identified are stepped over), until those are all visited. With no
    plausible value among the ``start`` values, every ``SEARCH_STRIDE``-th value next; with none among those either,
    every value (the search then falls back on the implausible ones, which need the whole grid). A walk from
    ``start`` whose bests have moved two values from it visits every ``SEARCH_STRIDE``-th value with its next batch.
    Each fold's best value, the best mean and its plausible neighbours are then those of a visit of every value, from
    any start, whenever each training RSS, over the plausible values in grid order, falls and then rises (one minimum;
    ``test_the_search_walk_finds_what_visiting_every_value_finds``): from the stride in about half the visits on the
    diagnosis's grids, from where the last search ended in 3-4 where its minimum has not moved (a trial is a design
    and its cross-validation)."""
    stride = list(range(0, n, SEARCH_STRIDE)) + ([n - 1] if (n - 1) % SEARCH_STRIDE else [])
    first = sorted({int(i) for i in start if 0 <= i < n})
    yield first or stride
    strided = not first
    if not strided and not any(ok for ok, _ in seen.values()):
        yield [i for i in stride if i not in seen]
        strided = True
    if not any(ok for ok, _ in seen.values()):
        yield [i for i in range(n) if i not in seen]
        return
    while True:
        plausible = [i for i, (ok, _) in seen.items() if ok]
        starts = {int(b) for b in best_at if b < n} | {min(plausible, key=lambda i: (seen[i][1], i))}
        todo = set()
        for b in starts:
            for step in (-1, 1):
                i = b + step
                while 0 <= i < n and i in seen and not seen[i][0]:
                    i += step
                if 0 <= i < n and i not in seen:
                    todo.add(i)
        if not strided and any(min(abs(b - f) for f in first) >= 2 for b in starts):
            # a minimum moved on the new model: the stride finds its neighbourhood in one batch, not a value a batch
            todo |= {i for i in stride if i not in seen}
            strided = True
        if not todo:
            return
        yield sorted(todo)


def cross_validate(des: Design, rows: np.ndarray, folds: np.ndarray, weights: np.ndarray,
                   sums: FoldSums | None = None) -> CvResult:
    """K-fold CV by normal equations (per-fold sums subtracted from the total). Rows of ``rows`` with a
    negative fold index (``check_folds``: -2, a visit that cannot be held out) are in every training
    set and in the full fit, never held out (their held-out residual stays NaN). ``sums``: those of an
    earlier call, used again when they are of the same matrix, folds and fitted rows.

    The fitted rows are put in fold order (a stable counting sort of the small fold numbers) and gathered
    one fold at a time for the sums, and again by the result when it is asked for a fold's held-out residual
    (``CvResult``): a fold's rows, not a copy of every fitted row (N x p), are what the cross-validation holds
    beside the design.
    """
    X, G = des.X, des.G
    idx = np.flatnonzero(rows & des.valid)
    f_idx = folds[idx].astype(np.int16)  # a few folds: numpy's stable sort of int16 is a radix sort
    if np.any(f_idx[1:] < f_idx[:-1]):  # a search's rows come in fold order (``search_samples``): nothing to move
        order = np.argsort(f_idx, kind="stable")
        idx, f_idx = idx[order], f_idx[order]
    K = int(f_idx[-1]) + 1
    start = np.searchsorted(f_idx, np.arange(-2, K + 1))  # [-2, -1, 0, .., K]: fold f is start[f+2]:start[f+3]

    p = X.shape[1]
    fresh = sums is None or not sums.of(X, folds, idx)
    xtx = np.zeros((K, p, p)) if fresh else sums.xtx
    xsum = np.zeros(p)
    xtg = np.zeros((K, p, 3))
    gtg = np.zeros((K, 3))
    for f in range(K):
        Xf, Gf = _fold_part(idx, start[f + 2], start[f + 3], X), _fold_part(idx, start[f + 2], start[f + 3], G)
        if fresh:
            xtx[f] = Xf.T @ Xf
            xsum += Xf.sum(axis=0)
        xtg[f], gtg[f] = Xf.T @ Gf, np.einsum("ij,ij->j", Gf, Gf)
    XtG, GtG = xtg.sum(0), gtg.sum(0)
    Xa, Ga = _fold_part(idx, 0, start[2], X), _fold_part(idx, 0, start[2], G)  # fold < 0: always trained on
    if len(Xa):
        XtG, GtG = XtG + Xa.T @ Ga, GtG + np.einsum("ij,ij->j", Ga, Ga)
    if fresh:
        XtX = xtx.sum(0)
        if len(Xa):
            XtX = XtX + Xa.T @ Xa
            xsum += Xa.sum(axis=0)
        sums = FoldSums(weakref.ref(X), weakref.ref(folds), idx, xtx, XtX, xsum)
    XtX = sums.XtX
    Xt, Gt = XtX - xtx, XtG - xtg  # each fold's training sums (K, p, p), (K, p, 3)
    A_folds = solve_normal_equations_each(Xt, Gt)
    train_rss = np.zeros(K)
    for f in range(K):
        A = A_folds[f]
        rss = GtG - gtg[f] - 2 * np.einsum("pi,pi->i", A, Gt[f]) + np.einsum("pi,pq,qi->i", A, Xt[f], A)
        train_rss[f] = float(np.sum(rss * weights))
    A_full = solve_normal_equations(XtX, XtG)[0]
    return CvResult(train_rss, A_full, sums, X, G, start, A_folds)


@dataclass
class RssSums:
    """The fitted rows of one design matrix and their X^T X (``weighted_rss``), kept while a search changes the
    reference alone (the same matrix, ``DesignCache``)."""

    X: weakref.ref  # the design matrix (N, p), compared by identity
    rows: np.ndarray  # (N,) the fitted rows
    Xr: np.ndarray  # (n, p) the matrix at those rows (the matrix itself when they are every row: then kept alive)
    XtX: np.ndarray  # (p, p)


def weighted_rss(des: Design, rows: np.ndarray, weights: np.ndarray,
                 sums: RssSums | None = None) -> tuple[float, RssSums]:
    """Weighted in-sample RSS of the least-squares fit of ``des`` on ``rows`` (noise ``weights`` (3,) per axis),
    and the sums it used (``sums``: an earlier call's, used again when they are of the same matrix and rows)."""
    r = rows & des.valid
    every = bool(r.all())  # every row (a search's fitted rows, mostly): the arrays themselves, no copy
    if sums is None or sums.X() is not des.X or not np.array_equal(sums.rows, r):
        Xr = des.X if every else rows_in_order(des.X, r)  # a copy in the matrix's layout: the same products
        sums = RssSums(weakref.ref(des.X), r, Xr, Xr.T @ Xr)
    X, G = sums.Xr, des.G if every else rows_at(des.G, r)
    A = solve_normal_equations(sums.XtX, X.T @ G)[0]
    res = G - X @ A
    return float(np.sum(res**2 * weights)), sums



def switch_profile(X: np.ndarray, G: np.ndarray, Z: np.ndarray, index: np.ndarray, folds: np.ndarray,
                   rows: np.ndarray, weights: np.ndarray, grid: np.ndarray, chunk: int = 16_384) -> np.ndarray:
    """Weighted training RSS (K, m) of each fold's least-squares fit of ``G`` (n, 3) by ``[X, 1{index >= h} Z]``
    for every value h of ``grid`` (m,): ``cross_validate``'s ``train_rss`` of the design with switched columns
    (``Effect.switched``) at each value, from one pass over the rows instead of a cross-validation per value.

    ``X`` (n, p) the model's design, ``Z`` (n, q) the switched columns, ``index`` (n,) each row's sample index,
    ``grid`` ascending sample indices, ``folds``/``rows`` as ``cross_validate`` (fold -2: always trained on).
    The sums of Z^T [X, Z, G] of the rows between two grid values are taken per fold and added up from the end
    (the rows a value switches on); the fit with the switched columns is the fit of X alone updated by them
    (Frisch-Waugh: the RSS falls by v^T M^-1 v per axis, M = S_ZZ - S_ZX (X^T X)^-1 S_XZ, v = S_ZG - S_ZX A).
    Equal to the cross-validation up to rounding (``test_the_switch_profile_is_the_cross_validation_of_each_value``);
    inf where the switched columns are not identified on a fold's training rows (scaled M singular to 1e-12)."""
    idx = np.flatnonzero(rows)
    f = folds[idx].astype(np.int64)
    K = int(f.max()) + 1
    slot = np.where(f >= 0, f + 1, 0)  # 0: the rows always trained on
    m, p, q = len(grid), X.shape[1], Z.shape[1]
    seg = np.searchsorted(grid, index[idx], side="right")  # a row is switched on at grid[j] when seg > j
    key = slot * (m + 1) + seg
    order = np.argsort(key, kind="stable")
    idx, key, slot = idx[order], key[order], slot[order]
    width = p + q + 3
    T = np.zeros(((K + 1) * (m + 1), q, width))
    xtx, xtg, gtg = np.zeros((K + 1, p, p)), np.zeros((K + 1, p, 3)), np.zeros((K + 1, 3))
    for lo in range(0, len(idx), chunk):
        r = idx[lo:lo + chunk]
        W = np.concatenate([X[r], Z[r], rows_at(G, r)], axis=1)
        k = key[lo:lo + chunk]
        starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
        T[k[starts]] += np.add.reduceat(Z[r][:, :, None] * W[:, None, :], starts, axis=0)
        sl = slot[lo:lo + chunk]
        for s_ in np.unique(sl):
            w = W[sl == s_]
            xtx[s_] += w[:, :p].T @ w[:, :p]
            xtg[s_] += w[:, :p].T @ w[:, p + q:]
            gtg[s_] += np.einsum("ij,ij->j", w[:, p + q:], w[:, p + q:])
    T = T.reshape(K + 1, m + 1, q, width)
    # rows per (slot, segment): values between which a fold trains on no row give that fold the same fit
    counts = np.bincount(key, minlength=(K + 1) * (m + 1)).reshape(K + 1, m + 1)
    S = np.cumsum(T[:, ::-1], axis=1)[:, ::-1][:, 1:]  # (K + 1, m, q, width): the rows after each grid value
    S_tot, XtX, XtG, GtG = S.sum(0), xtx.sum(0), xtg.sum(0), gtg.sum(0)
    out = np.full((K, m), np.inf)
    for fo in range(K):
        St = S_tot - S[fo + 1]
        Xt, Gt = XtX - xtx[fo + 1], XtG - xtg[fo + 1]
        A = solve_normal_equations(Xt, Gt)[0]
        base = GtG - gtg[fo + 1] - 2 * np.einsum("pi,pi->i", A, Gt) + np.einsum("pi,pq,qi->i", A, Xt, A)
        S_zx, S_zz, S_zg = St[:, :, :p], St[:, :, p:p + q], St[:, :, p + q:]
        C = np.linalg.solve(Xt, S_zx.reshape(m * q, p).T).T.reshape(m, q, p)  # S_ZX (X^T X)^-1
        M = S_zz - np.einsum("jap,jbp->jab", C, S_zx)
        v = S_zg - S_zx @ A
        d = np.sqrt(np.maximum(np.einsum("jaa->ja", M), 0.0))
        ok = np.all(d > 0, axis=1)
        Ms = np.where(ok[:, None, None], M / np.where(ok[:, None], d, 1.0)[:, :, None]
                      / np.where(ok[:, None], d, 1.0)[:, None, :], np.eye(q))
        eig = np.linalg.eigvalsh(Ms)
        ok &= eig[:, 0] > 1e-12 * eig[:, -1]
        red = np.zeros((m, 3))
        red[ok] = np.einsum("jai,jai->ji", v[ok], np.linalg.solve(M[ok], v[ok]))
        out[fo, ok] = (base[None, :] - red[ok]) @ weights
        out[fo] = _share_equal_fits(out[fo], counts.sum(0)[1:m] - counts[fo + 1, 1:m])
    return out


def _share_equal_fits(rss: np.ndarray, trained_between: np.ndarray) -> np.ndarray:
    """``rss`` (m,) of one fold over a grid of switch values, where values with no training row between them
    (``trained_between`` (m - 1,): the fold's training rows between value j and j + 1) take the first one's RSS. Such
    values fit the fold's training rows with the same design, so their RSS are equal but for rounding, and the
    rounding (which the BLAS kernel decides) must not choose among them: each keeps the first value's RSS, so that
    a search's choice falls on the first of them on every machine."""
    out = rss.copy()
    for j in np.flatnonzero(trained_between == 0):
        out[j + 1] = out[j]
    return out


COLLINEAR_CORR = 0.99  # |correlation| of an added column with the model's others above which it is not separable
CANCEL_RATIO = 10.0  # a collinear column whose own contribution exceeds the net change it makes this many times


def cancelling_terms(des: Design, cv: CvResult, name: str) -> str:
    """Why the effect ``name`` fits as large terms that cancel, or "" if it does not: one of its columns
    correlates above ``COLLINEAR_CORR`` with another column of the model (its own included) AND that column's
    contribution (coefficient x column, RMS over the fitted rows) is more than ``CANCEL_RATIO`` times the RMS of
    the effect's net contribution (all its columns), on some axis (e.g. a warm-up of 13 m/s^2 against a creep that
    takes it back). Correlated columns whose contributions stay modest are not refused. From the fit's sums."""
    sl = des.blocks.get(name)
    if sl is None:
        return ""
    xtx, n = cv.sums.XtX, len(cv.sums.idx)
    corr = gram_conditioning(xtx, cv.sums.xsum, n, des.blocks)[1].get(name, 0.0)
    if corr <= COLLINEAR_CORR:
        return ""
    A = cv.A_full[sl]
    net = np.sqrt(np.maximum(np.einsum("kj,kl,lj->j", A, xtx[sl, sl], A), 0.0) / n)
    own = np.abs(A) * np.sqrt(np.diag(xtx)[sl] / n)[:, None]  # (k, 3) RMS of each column's contribution
    ratio = float(np.max(own / np.maximum(net, 1e-300)))
    if ratio <= CANCEL_RATIO:
        return ""
    return (f"a column correlates at |r| = {corr:.4f} (limit {COLLINEAR_CORR}) with another column of the model and "
            f"contributes {ratio:.3g} times the effect's net contribution (limit {CANCEL_RATIO:g}): large terms that "
            "cancel, not separately determined")


def gram_conditioning(xtx: np.ndarray, xsum: np.ndarray, n: int, blocks: dict[str, slice]) -> tuple[float, dict[str, float]]:
    """How well a model's coefficients are determined, from its sums over the fitted rows (X^T X, column sums,
    row count): the condition number of the scaled normal matrix (the fit's solver), and per effect block the
    largest |correlation| of one of its columns with any other column of the model, its own included (centred:
    the constant column, b's, is left out)."""
    cond = scaled_condition(xtx)[2]
    cov = xtx - np.outer(xsum, xsum) / max(n, 1)
    var = np.diag(cov)
    live = var > 1e-10 * np.maximum(np.diag(xtx), 1e-300)
    sd = np.sqrt(var[live])
    corr = cov[np.ix_(live, live)] / np.outer(sd, sd)
    np.fill_diagonal(corr, 0.0)
    col = np.flatnonzero(live)
    out = {}
    for name, sl in blocks.items():
        own = np.isin(col, np.arange(sl.start, sl.stop))
        out[name] = float(np.max(np.abs(corr[own]))) if own.any() else 0.0
    return cond, out
