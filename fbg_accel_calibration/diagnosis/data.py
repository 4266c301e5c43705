"""The data a candidate effect sees (pure numpy): the recording's arrays with their visits and runs
(:class:`DiagnosisData`, with its constants worked out once), the inputs eq. 28 is fed with after the input
corrections (:class:`Inputs`), and the helpers over visits and runs the candidates and the diagnosis share.

Two keys identify where a sample was taken: ``pose_id`` is the *orientation* (the commanded pose), ``group`` the
*visit* (``visit_ids``: one contiguous static interval of one pose id within one run).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from hashlib import blake2b
from typing import Any

import numpy as np

from fbg_accel_driver.correction_terms import SampleSteps, sample_steps, uniform_coefficient

ROW_KEYS_KEPT = 4  # the read-only rows whose digest ``DiagnosisData.rows_key`` keeps (a search's rows, a few tests')


@dataclass
class DiagnosisData:
    """The arrays a candidate needs, all (N,) or (N, 3), time-ordered within each run.

    ``use`` marks the static samples that enter fits and residuals; ``gref_filled`` is the
    reference with the gaps between poses linearly interpolated in time (an approximation of the
    table's motion, used only to re-align the reference in time for ``channel_delay``).

    Two keys identify where a sample was taken: ``pose_id`` is the *orientation* (the commanded
    pose; the same id when the table comes back to it), ``group`` the *visit* (``visit_ids``: one
    contiguous static interval of one pose id within one run). Visits are the unit of the noise
    floor, of the cross-validation folds and of the significance tests; a change between two visits
    of one orientation (repeat, another temperature level or run) is not noise.
    """

    t_s: np.ndarray
    ref: np.ndarray
    xyz: np.ndarray
    temp_c: np.ndarray
    gref: np.ndarray
    pose_id: np.ndarray
    run_id: np.ndarray
    use: np.ndarray
    gref_filled: np.ndarray = field(default=None)  # type: ignore[assignment]
    group: np.ndarray = field(default=None)  # type: ignore[assignment]  # visit label (``visit_ids``)
    n_clipped_samples: int = 0  # samples at a pose left out with their visit for a clipped channel (``prepare_data``)
    n_clipped_visits: int = 0  # those visits
    n_low_reference: int = 0  # samples taken out for a reference too low (``Recording.low_reference``, ``prepare_data``)
    low_reference_note: str = ""  # how many, where (``recording.low_reference_warning``); empty when none
    # jumps of the temperature reading no temperature makes (``temperature_reading.reading_jumps``, ``prepare_data``)
    temperature_jumps: list = field(default_factory=list)
    table_deg: np.ndarray | None = None  # (N, 2) the table's angle readings psi, theta (deg); None: not in the recording

    _memo: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)
    # recent's entries: (value, fresh)
    _recent: OrderedDict[tuple, tuple[Any, Callable[[Any], bool] | None]] = field(default_factory=OrderedDict, init=False,
                                                                                repr=False, compare=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False, compare=False)
    _for_trials: set[str] = field(default_factory=set, init=False, repr=False, compare=False)
    _row_keys: OrderedDict[int, tuple[np.ndarray, str]] = field(default_factory=OrderedDict, init=False, repr=False,
                                                                compare=False)

    def runs(self) -> list[slice | np.ndarray]:
        """The samples of each run, together every sample (computed once; every filter restarts at a run's first
        sample): a slice where the run is contiguous, as runs are (indexing gives views, not copies), else indices."""
        def find() -> list[slice | np.ndarray]:
            out: list[slice | np.ndarray] = []
            for r in np.unique(self.run_id):
                idx = np.flatnonzero(self.run_id == r)
                out.append(slice(int(idx[0]), int(idx[-1]) + 1) if idx[-1] - idx[0] + 1 == len(idx) else idx)
            return out

        return self.once("runs", find)

    def once(self, key: str, compute: Callable[[], Any], for_trials: bool = False) -> Any:
        """``compute()`` the first time ``key`` is asked for, the kept value after (a constant of the recording). Two
        searches that run side by side (``search_lanes``) and ask at once may both compute it; the first kept is the
        one both get. ``for_trials``: a constant kept only to spare the searches' trials its making (an array of up
        to 10^6 samples), forgotten with what ``recent`` keeps (``drop_recent``) and made again if asked for after."""
        if key not in self._memo:
            if for_trials:
                self._for_trials.add(key)
            return self._memo.setdefault(key, compute())
        return self._memo[key]

    def recent(self, key: tuple, compute: Callable[[], Any], keep: int = 4,
               fresh: Callable[[Any], bool] | None = None) -> Any:
        """``compute()`` (a value that depends on the recording and ``key`` alone; an array is made read-only), kept
        for the next ``keep`` distinct keys: a correction that a search repeats unchanged on every trial (the thermal
        lag of the model while another effect is searched) is worked out once (by lanes side by side: as ``once``).
        ``fresh(value)`` false: a kept value no longer stands for ``key`` (what it was made of is gone); it is let go
        on the next call for any key, before anything is made (the holds of a trial's delayed reference once the
        trial's series is dropped: not kept beside the next trial's), and made again if asked for."""
        with self._lock:
            self._drop_stale()
            kept = self._recent.get(key)
            if kept is not None:
                self._recent.move_to_end(key)
                return kept[0]
        value = compute()
        if isinstance(value, np.ndarray):
            value.flags.writeable = False
        with self._lock:
            self._drop_stale()
            kept = self._recent.get(key)
            if kept is None:
                kept = self._recent[key] = (value, fresh)
            self._recent.move_to_end(key)
            while len(self._recent) > keep:
                self._recent.popitem(last=False)
        return kept[0]

    def _drop_stale(self) -> None:
        """Drop the entries of ``recent`` whose ``fresh`` says they no longer stand for their key (under the lock)."""
        for key in [k for k, (value, fresh) in self._recent.items() if fresh is not None and not fresh(value)]:
            del self._recent[key]

    def rows_key(self, rows: np.ndarray) -> str:
        """``rows_digest(rows)``, kept with the array for the last ``ROW_KEYS_KEPT`` read-only arrays that own their
        memory (a search's rows, ``search.Evaluator``: asked on every trial of the TIA and the thermal lag, about 1 ms
        at 10^6 samples). The array itself is the key: its identity, the entry holding it so that no other array takes
        its identity while the entry stands; its values cannot change while it stays read-only. An array that can be
        written, or a view (whose memory another array may write), is digested on every call."""
        if rows.flags.writeable or rows.base is not None:
            return rows_digest(rows)
        with self._lock:
            hit = self._row_keys.get(id(rows))
            if hit is not None and hit[0] is rows and not rows.flags.writeable:
                self._row_keys.move_to_end(id(rows))
                return hit[1]
        key = rows_digest(rows)
        with self._lock:
            self._row_keys[id(rows)] = (rows, key)
            self._row_keys.move_to_end(id(rows))
            while len(self._row_keys) > ROW_KEYS_KEPT:
                self._row_keys.popitem(last=False)
        return key

    def drop_recent(self) -> None:
        """Forget what :meth:`recent` keeps and the constants ``once`` keeps for the trials (when no search follows)."""
        self._recent.clear()
        for key in self._for_trials:
            self._memo.pop(key, None)
        self._for_trials.clear()

    def psi_at(self, rows: np.ndarray) -> np.ndarray:
        """Psi (n, 3) of the recorded counts at the samples ``rows`` (``Inputs.normalised``). Kept (read-only, dropped
        with the searches' constants) for the read-only rows of a search (``rows_key``): every design of a model whose
        corrections leave the counts as recorded reads the same Psi at them (a search over the thermal lag, the TIA
        low-pass, a time function); worked out on every call for other rows."""
        def make() -> np.ndarray:
            psi = Inputs.normalised(take_rows(np.asarray(self.xyz, dtype=float), rows),
                                    np.asarray(self.ref, dtype=float)[rows])
            psi.flags.writeable = False
            return psi

        if rows.flags.writeable or rows.base is not None:
            return make()
        return self.once(f"psi_at {self.rows_key(rows)}", make, for_trials=True)

    def run_steps(self) -> list[SampleSteps]:
        """``sample_steps`` of each run's board times (``runs``), computed once: the low-pass filters of the input
        corrections start afresh at each run, once per trial value of a search."""
        return self.once("run_steps", lambda: [sample_steps(self.t_s[idx]) for idx in self.runs()])

    def static_psi_map(self) -> tuple[np.ndarray, np.ndarray]:
        """``expected_psi_map`` of the recorded counts (computed once)."""
        return self.once("static_psi_map", lambda: expected_psi_map(self, Inputs.of(self)))

    def __post_init__(self) -> None:
        if self.gref_filled is None:
            self.gref_filled = fill_reference_gaps(self.t_s, self.gref, self.runs())
        if self.group is None:
            self.group = visit_ids(self.pose_id, self.run_id)

    @property
    def dt_s(self) -> float:
        """The median step between samples (s; 1 without one), worked out once: every search asks for it."""
        def median_step() -> float:
            d = np.diff(self.t_s)
            d = d[d > 0]
            return float(np.median(d)) if d.size else 1.0

        return self.once("dt_s", median_step)

    @property
    def duration_s(self) -> float:
        return float(np.ptp(self.t_s)) if self.t_s.size else 0.0

    def temperature_level_count(self) -> int:
        """Temperature levels among the fitted samples (``thermal_fit.temperature_levels``), at least 1: eq. 28's
        degree is below it, so with one level the model has no temperature term."""
        # asked by every candidate's ``applicable`` at every step: clustered once per recording
        return self.once("temperature_level_count", lambda: max(len(self.fitted_temperature_levels()[1]), 1))

    def fitted_temperature_levels(self) -> tuple[np.ndarray, np.ndarray]:
        """``thermal_fit.temperature_levels`` of the fitted samples' temperatures (``temp_c[use]``): (the level label of
        each, as int32, the levels' mean temperatures degC), read-only, clustered once for the searches (the degree of
        eq. 28 is chosen again after every effect added, about 50 ms at 10^6 samples each time; dropped with the
        searches' constants)."""
        from ..fit.thermal_fit import temperature_levels

        def cluster() -> tuple[np.ndarray, np.ndarray]:
            labels, means = temperature_levels(self.temp_c[self.use])
            labels, means = np.asarray(labels, dtype=np.int32), np.asarray(means)  # labels: -1 and 0 .. levels - 1
            for a in (labels, means):
                a.flags.writeable = False
            return labels, means

        return self.once("fitted_temperature_levels", cluster, for_trials=True)

    def temperature_span_c(self) -> float:
        t = self.temp_c[self.use]
        t = t[np.isfinite(t)]
        return float(np.ptp(t)) if t.size else 0.0


def motion_groups(pose_id: np.ndarray, run_id: np.ndarray) -> np.ndarray:
    """Orientation key (N,) of every sample: its pose id; a sample taken while the table moves
    belongs to the pose the table moves to (the previous one at the end of a run), -1 if none.
    (The visit, ``visit_ids``, is the grouping unit of the diagnosis; this is the orientation.)"""
    pose_id = np.asarray(pose_id)
    out = np.array(pose_id, copy=True)
    for r in np.unique(run_id):
        idx = np.flatnonzero(run_id == r)
        p = pose_id[idx]
        n = len(p)
        pos = np.where(p >= 0, np.arange(n), n)
        nxt = np.minimum.accumulate(pos[::-1])[::-1]  # index of the next pose sample (n if none)
        prv = np.maximum.accumulate(np.where(p >= 0, np.arange(n), -1))
        fill = np.where(nxt < n, p[np.minimum(nxt, n - 1)], np.where(prv >= 0, p[np.maximum(prv, 0)], -1))
        out[idx] = np.where(p >= 0, p, fill)
    return out


def visit_ids(pose_id: np.ndarray, run_id: np.ndarray) -> np.ndarray:
    """Visit label (N,) of every sample, numbered 0, 1, ... in time order.

    A visit is one contiguous static interval of one pose id (>= 0) within one run: it starts where
    the pose id or the run changes, so a second visit of the same orientation (a repeat, another
    temperature level, another file) is a new visit. A sample taken while the table moves (pose id
    -1) belongs to the visit the table moves to (the previous one at the end of a run), as in
    ``motion_groups``; -1 if the run has no pose at all.
    """
    pose_id = np.asarray(pose_id)
    run_id = np.asarray(run_id)
    n = len(pose_id)
    if n == 0:
        return np.zeros(0, int)
    start = np.r_[True, (np.diff(pose_id) != 0) | (np.diff(run_id) != 0)]
    static_start = start & (pose_id >= 0)
    label = np.cumsum(static_start) - 1
    label = np.where(pose_id >= 0, label, -1)
    return motion_groups(label, run_id)


# a pose the table held for fewer consecutive samples is no static visit (its reference is a passing angle)
MIN_HELD_SAMPLES = 5


def held_poses(pose_id: np.ndarray, run_id: np.ndarray) -> np.ndarray:
    """Mask (N,) of the samples at a pose (id >= 0) that the table held for at least :data:`MIN_HELD_SAMPLES`
    consecutive samples within one run: the samples whose reference is known and constant."""
    pose_id, run_id = np.asarray(pose_id), np.asarray(run_id)
    if len(pose_id) == 0:
        return np.zeros(0, dtype=bool)
    change = np.r_[True, (np.diff(pose_id) != 0) | (np.diff(run_id) != 0)]
    seg = np.cumsum(change) - 1
    return (pose_id >= 0) & (np.bincount(seg)[seg] >= MIN_HELD_SAMPLES)


def take_rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``a[idx]`` for integer indices ``idx`` (``np.take`` along the first axis, the same values): numpy's fancy
    indexing copies the rows of an (N, 3) array one by one, about three times slower at 10^5 rows of 10^6. An (N, k)
    view of a C-ordered (k, N) array (its columns kept contiguous) is taken along the columns: ``np.take`` would first
    copy the whole strided array (the TIA's reference at 5 x 10^4 of 10^6 rows: 10 ms a trial instead of 2)."""
    if a.ndim == 2 and not a.flags.c_contiguous and a.T.flags.c_contiguous:
        return np.ascontiguousarray(np.take(a.T, idx, axis=1).T)  # C-ordered as np.take gives it
    return np.take(a, idx, axis=0)


def rows_at(a: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``a[rows]`` (``rows``: integer indices, or a boolean mask of ``a``'s rows), the same array bit for bit (values,
    shape, C order): for a C-ordered (N, k) array by ``np.take`` / ``np.compress`` along the first axis, which copy
    whole rows (numpy's indexing copies an (N, 3) array's rows value by value, 4-5 times slower); else by indexing
    (an F-ordered design matrix: indexing makes its C-ordered copy faster)."""
    if a.ndim != 2 or not a.flags.c_contiguous:
        return a[rows]
    if rows.dtype == bool:
        if rows.ndim != 1 or len(rows) != len(a):
            return a[rows]  # IndexError as indexing raises it
        return np.compress(rows, a, axis=0)
    return np.take(a, rows, axis=0)


def rows_in_order(a: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``a[rows]`` (``rows``: integer indices, or a boolean mask of ``a``'s rows) laid out as ``a`` is: an (N, p) array
    with its columns contiguous (a design matrix, or a slice of its rows) gives an F-ordered copy, column by column;
    any other array ``rows_at``'s C-ordered copy. The copy's products (X^T X, X^T G) then run the BLAS kernels of the
    array itself: OpenBLAS's AVX-512 kernels (SkylakeX) sum X^T G of an F- and of a C-ordered X in another order."""
    if a.ndim != 2 or a.shape[1] < 2 or a.strides[0] != a.itemsize:
        return rows_at(a, rows)
    if rows.dtype == bool:
        if rows.ndim != 1 or len(rows) != len(a):
            return a[rows]  # IndexError as indexing raises it
        rows = np.flatnonzero(rows)  # then a column's np.take: np.compress of a column is 4 times slower
    out = np.empty((len(rows), a.shape[1]), dtype=a.dtype, order="F")
    for j in range(a.shape[1]):
        np.take(a[:, j], rows, out=out[:, j])
    return out


def set_rows(out: np.ndarray, rows: np.ndarray, values: np.ndarray | float) -> None:
    """``out[rows] = values`` (``rows``: integer indices; ``values``: (len(rows), k) or one value for every element),
    the same bits: for a C-ordered (N, k) float64 ``out`` each row is written whole, as one element of k * 8 bytes
    (numpy's indexed assignment writes an (N, 3) array's rows value by value, about twice as slow); else by
    indexing."""
    if out.ndim != 2 or not out.flags.c_contiguous or out.dtype != np.float64 or not out.flags.writeable:
        out[rows] = values
        return
    k = out.shape[1]
    whole = np.dtype((np.void, 8 * k))
    if np.ndim(values) == 0:
        row = np.ascontiguousarray(np.broadcast_to(np.asarray(values, dtype=np.float64), (1, k)))
        np.asarray(out).view(whole).reshape(len(out))[rows] = row.view(whole)[0, 0]
        return
    values = np.ascontiguousarray(values, dtype=np.float64)
    if values.shape != (len(rows), k):
        out[rows] = values  # broadcasting (or its error) as indexing does it
        return
    np.asarray(out).view(whole).reshape(len(out))[rows] = values.view(whole).reshape(len(rows))


def interval_of(xp: np.ndarray, x: np.ndarray, near: np.ndarray | None = None) -> np.ndarray:
    """``np.searchsorted(xp, x, side="right") - 1`` (``xp`` increasing, without NaN): the index j of the interval
    xp[j] <= x < xp[j + 1] of each ``x`` (-1 below ``xp[0]``, len(xp) - 1 from ``xp[-1]`` on). ``near`` (len(x),
    indices): a guess of each j, taken where it, the index before or the one after it is j by those two comparisons
    (then no other index is: ``xp`` is sorted), searched for elsewhere (a guess off by more, NaN, the ends): the same
    indices, a few comparisons each instead of a bisection of ``xp`` (the channel delay's t - D falls about
    D / step samples before its own, on every trial)."""
    x = np.asarray(x, dtype=float)
    n = len(xp)
    if near is None or n < 3:
        return np.searchsorted(xp, x, side="right") - 1
    j = np.clip(near, 1, n - 3)  # j - 1 .. j + 2 within xp
    below, above = xp[j] <= x, x < xp[j + 1]
    j[~below] -= 1  # x < xp[j]: the interval before, where xp[j - 1] <= x
    low = ~above
    j[low] += 1  # xp[j + 1] <= x: the interval after, where x < xp[j + 2]
    ok = (below & above) | (~below & (xp[j] <= x)) | (low & (x < xp[np.minimum(j + 1, n - 1)]))
    bad = np.flatnonzero(~ok)
    if len(bad):
        j[bad] = np.searchsorted(xp, x[bad], side="right") - 1
    return j


def interp_columns(x: np.ndarray, xp: np.ndarray, fp: np.ndarray, block: int = 1 << 16,
                   near: np.ndarray | None = None) -> np.ndarray:
    """``np.interp(x, xp, fp[:, j])`` (len(x), k) for every column j of ``fp`` (len(xp), k) at once, the same values
    bit for bit: ``x`` is looked up in ``xp`` (increasing) once for the k columns, where ``np.interp`` looks it up
    again for each (the channel delay's search interpolates the three reference axes at the same times on every
    trial). As ``np.interp``: below ``xp[0]`` the first row, from ``xp[-1]`` on the last, at a point of ``xp`` its
    row, else the slope of the interval times the distance from its left end plus its left value (from the right
    end where that is NaN); NaN where ``x`` is (but for a single point). Worked out ``block`` values at a time
    (bounded temporaries). ``near``: a guess of each x's interval (``interval_of``; the same values)."""
    x = np.asarray(x, dtype=float)
    out = np.empty((len(x), fp.shape[1]))
    n = len(xp)
    for lo in range(0, len(x), block):
        xs = x[lo:lo + block]
        j = interval_of(xp, xs, None if near is None else near[lo:lo + block])
        jj = np.clip(j, 0, max(n - 2, 0))
        x0, f0 = xp[jj], take_rows(fp, jj)
        if n >= 2:
            x1, f1 = xp[jj + 1], take_rows(fp, jj + 1)
            with np.errstate(divide="ignore", invalid="ignore"):
                slope = (f1 - f0) / (x1 - x0)[:, None]
                part = slope * (xs - x0)[:, None] + f0
                nan = np.isnan(part)
                if nan.any():  # np.interp's fallbacks: from the right end, then the common value of a flat interval
                    part = np.where(nan, slope * (xs - x1)[:, None] + f1, part)
                    part = np.where(nan & np.isnan(part) & (f0 == f1), f0, part)
        else:
            part = f0.copy()
        at = np.flatnonzero((j >= n - 1) | (xs == x0))  # from the last point on, or at a point of xp: its row
        set_rows(part, at, take_rows(fp, np.minimum(j[at], n - 1)))  # whole rows (a delay of whole steps: most)
        part[j < 0] = fp[0]
        if n >= 2:  # (np.interp gives a single point's row even at NaN)
            part[np.isnan(xs)] = np.nan
        out[lo:lo + block] = part
    return out


def column_rms(a: np.ndarray) -> np.ndarray:
    """``np.sqrt(np.mean(a ** 2, axis=0))`` (k,) of ``a`` (n, k), the same bits: numpy's mean along the first axis
    of a C-ordered array of k >= 2 columns adds the rows one after another into the k sums, as ``einsum`` does at a
    quarter of the cost (numpy's reduction pays its loop's start on every row of 3); other layouts (a contiguous
    column numpy sums pairwise) by ``np.mean`` itself. NaN for no rows, as the mean (without its warning)."""
    sq = a**2
    if sq.ndim != 2 or not sq.flags.c_contiguous or sq.flags.f_contiguous:
        return np.sqrt(np.mean(sq, axis=0))
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.einsum("ij->j", sq) / len(sq))


def row_sums(a: np.ndarray) -> np.ndarray:
    """``np.sum(a, axis=1)`` (n,) of ``a`` (n, k), the same bits: numpy sums a contiguous row of fewer than 8 values
    one after another from 0.0, as the columns added here do at a fraction of the cost (its reduction pays its loop's
    start on every row); other shapes and layouts by ``np.sum`` itself."""
    if a.ndim != 2 or not 1 <= a.shape[1] < 8 or not a.flags.c_contiguous:
        return np.sum(a, axis=1)
    out = a[:, 0] + 0.0
    for j in range(1, a.shape[1]):
        out += a[:, j]
    return out


def finite_rows(a: np.ndarray) -> np.ndarray:
    """Rows (N,) of ``a`` (N, k) whose values are all finite (``np.all(np.isfinite(a), axis=1)``, exactly). Column by
    column where the columns are few or contiguous: numpy's reduction along a short row axis is several times
    slower, and the diagnosis asks this of every design and residual."""
    if a.ndim == 1:
        return np.isfinite(a)
    if a.shape[1] == 0 or (a.shape[1] > 4 and not a.flags.f_contiguous):
        return np.all(np.isfinite(a), axis=1)
    out = np.isfinite(a[:, 0])
    for j in range(1, a.shape[1]):
        out &= np.isfinite(a[:, j])
    return out


def fill_reference_gaps(t_s: np.ndarray, gref: np.ndarray, runs: list[slice | np.ndarray]) -> np.ndarray:
    """Reference (N, 3) with NaN gaps linearly interpolated in time within each run (``runs``: the samples of
    each run, ``DiagnosisData.runs``); a run without gaps is copied as it is. A reference without any gap (the
    simulator's, known in motion too; one the channel delay has interpolated) is returned itself, not a copy
    (24 MB at 10^6 samples): its callers only read it."""
    if finite_rows(gref).all():
        return np.asarray(gref, dtype=float)
    out = np.array(gref, dtype=float, copy=True)
    for idx in runs:
        g = out[idx]
        ok = finite_rows(g)
        if ok.all() or ok.sum() < 2:
            continue
        t = t_s[idx]
        for j in range(3):
            out[idx, j] = np.interp(t, t[ok], g[ok, j])
    return out


@dataclass
class Inputs:
    """What eq. 28 is fed with after the input corrections, plus the reference it is compared to."""

    ref: np.ndarray
    xyz: np.ndarray
    temp_c: np.ndarray
    t_s: np.ndarray
    gref: np.ndarray
    valid: np.ndarray
    gref_moved: bool = False  # an earlier transform changed the reference (else it is data.gref)
    counts_changed: bool = False  # an earlier transform changed ref or xyz (else psi is the data's)
    temp_changed: bool = False  # an earlier transform changed the temperature (else it is data.temp_c)
    index: np.ndarray | None = None  # (n,) the sample index of each row in the recording (None: row i is sample i)
    # (the input corrections that made the counts, as (name, hyper-parameter) in stage order; the ref and xyz arrays
    # they made) where the design cache names them (``design._reference_prefix``): ``psi_map_of`` keeps their expected
    # Psi map under that name while ref and xyz are those arrays (a correction that replaces one makes it void)
    counts_of: tuple[tuple, np.ndarray, np.ndarray] | None = None

    @property
    def psi(self) -> np.ndarray:
        return self.normalised(self.xyz, self.ref)

    @staticmethod
    def normalised(xyz: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Psi (N, 3) of eq. 24: the axis counts over the reference counts (NaN where the reference is not > 0)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return xyz / np.where(ref > 0, ref, np.nan)[:, None]

    @classmethod
    def of(cls, data: DiagnosisData) -> Inputs:
        """Uncorrected inputs of ``data``: read-only views of its arrays (a correction that wrote into one instead
        of replacing it would raise), only ``valid`` is new."""
        def read_only(a: np.ndarray) -> np.ndarray:
            v = np.asarray(a, dtype=float).view()
            v.flags.writeable = False
            return v

        return cls(read_only(data.ref), read_only(data.xyz), read_only(data.temp_c), read_only(data.t_s),
                   read_only(data.gref), np.ones(len(data.t_s), bool))

    def at(self, idx: np.ndarray, take: Callable[[np.ndarray], np.ndarray] | None = None) -> Inputs:
        """These inputs at the samples ``idx`` only (for what is computed sample by sample); ``take(a)``, if
        given, returns ``a[idx]`` for the arrays other than ``valid`` (which the corrections change in place)."""
        pick = take if take is not None else (lambda a: rows_at(a, idx))
        return Inputs(pick(self.ref), pick(self.xyz), pick(self.temp_c), pick(self.t_s), pick(self.gref),
                      self.valid[idx], self.gref_moved, self.counts_changed, self.temp_changed,
                      np.asarray(idx) if self.index is None else self.index[idx])

    @property
    def sample_index(self) -> np.ndarray:
        """(n,) the sample index of each row in the recording."""
        return np.arange(len(self.t_s)) if self.index is None else self.index


def group_index(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(labels, return_inverse=True)``, the same two arrays: for non-negative integer labels no larger than
    a few times their number (visit ids, at most thousands) from a count of each label, O(n), instead of a sort (a
    test and the diagnosis's gain tests ask it of 5 x 10^4 searched rows, in fold order, many times); other labels
    by ``np.unique``."""
    labels = np.asarray(labels)
    if labels.ndim != 1 or labels.dtype.kind not in "iu" or not len(labels) or labels.min() < 0 \
            or labels.max() > 4 * len(labels) + 1024:
        return np.unique(labels, return_inverse=True)
    present = np.bincount(labels) > 0
    position = np.cumsum(present) - 1
    return np.flatnonzero(present).astype(labels.dtype), position[labels]


def visit_means(groups: np.ndarray, rows: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Mean of ``values`` (N, k) over each visit (``groups`` id >= 0) of the samples ``rows`` (N,) bool: (V, k), in
    ascending visit id."""
    sel = rows & (groups >= 0)
    _, inv = group_index(groups[sel])
    n = np.bincount(inv).astype(float)
    return np.column_stack([np.bincount(inv, weights=v, minlength=len(n)) for v in values[sel].T]) / n[:, None]


def direction_labels(g: np.ndarray) -> np.ndarray:
    """Label (V,) of the direction of each reference ``g`` (V, 3) m/s^2: directions closer than
    ``thermal_fit.ORIENTATION_TOLERANCE_DEG`` to the first of a label share it (greedy, in the order given)."""
    from ..fit.thermal_fit import ORIENTATION_TOLERANCE_DEG

    u = g / np.maximum(np.linalg.norm(g, axis=1), 1e-300)[:, None]
    cos_tol = math.cos(math.radians(ORIENTATION_TOLERANCE_DEG))
    label, seen = np.empty(len(u), int), []
    for i, v in enumerate(u):
        j = next((k for k, w in enumerate(seen) if float(v @ w) > cos_tol), len(seen))
        if j == len(seen):
            seen.append(v)
        label[i] = j
    return label


def expected_psi_map(data: DiagnosisData, inp: Inputs) -> tuple[np.ndarray, np.ndarray]:
    """Linear map Psi ~ P g + q (P (3, 3), q (3,)) fitted on the static samples (eq. 25 inverted):
    the noise-free Psi the sensor shows for a reference g."""
    # the static samples with a reference, their [g, 1] and its Gram matrix (constants of the recording), then
    # those with a finite Psi (a correction that changed the counts asks again on every trial of a search)
    static = data.once("static_with_reference", lambda: np.flatnonzero(data.use & finite_rows(data.gref)), True)
    xyz = data.once("static_xyz", lambda: np.asarray(data.xyz, dtype=float)[static], True) if same_memory(inp.xyz, data.xyz) \
        else inp.xyz[static]
    psi = Inputs.normalised(xyz, inp.ref[static])
    ok = finite_rows(psi)
    if ok.all():
        X, XtX = data.once("static_design",
                           lambda: with_gram(np.column_stack([data.gref[static], np.ones(len(static))])), True)
        Y = psi
    else:
        X = np.column_stack([data.gref[static[ok]], np.ones(int(ok.sum()))])
        XtX, Y = X.T @ X, psi[ok]
    try:  # 4 x 4 normal equations (well conditioned: |g| ~ 9.8 m/s^2 against 1), not an SVD of the N x 4 matrix
        coef = np.linalg.solve(XtX, X.T @ Y)
    except np.linalg.LinAlgError:  # the reference never changes direction: the minimum-norm solution
        coef = np.linalg.lstsq(X, Y, rcond=None)[0]
    return coef[:3].T, coef[3]


def psi_map_of(data: DiagnosisData, inp: Inputs) -> tuple[np.ndarray, np.ndarray]:
    """``expected_psi_map`` of the counts of ``inp``: the recording's (``DiagnosisData.static_psi_map``) where no
    correction changed them; where the corrections that made them are named (``Inputs.counts_of``), kept per those
    corrections for the trials (``DiagnosisData.once``, dropped with the searches' constants): the trials of a search
    over the TIA low-pass on top of the read-noise filter, and a search over the filter on top of the TIA searched
    again beside another model, ask for the map of the same filtered counts (a fit over the static samples, about
    18 ms at 10^6 samples); else worked out."""
    if not inp.counts_changed:
        return data.static_psi_map()
    made = inp.counts_of
    if made is None or made[1] is not inp.ref or made[2] is not inp.xyz:
        return expected_psi_map(data, inp)
    return data.once(f"expected_psi_map {made[0]!r}", lambda: expected_psi_map(data, inp), for_trials=True)


def rows_by_run(data: DiagnosisData, rows: np.ndarray | None) -> list[tuple[slice | np.ndarray, Any, Any]] | None:
    """For each run (``DiagnosisData.runs``): (its samples, where its part of ``rows`` goes in an array of ``rows``,
    the positions of that part in the run). ``rows`` None: every sample, (run, run, every position). None when ``rows``
    are given and a run is not contiguous (then every sample is worked out and the rows taken)."""
    runs = data.runs()
    if rows is None:
        return [(run, run, slice(None)) for run in runs]
    if not all(isinstance(r, slice) for r in runs):
        return None
    out = []
    for run in runs:
        sel = np.flatnonzero((rows >= run.start) & (rows < run.stop))
        out.append((run, sel, rows[sel] - run.start))
    return out


def rows_digest(rows: np.ndarray) -> str:
    """A key for a set of rows (sample indices): their number and a cryptographic digest of their bytes, so that two
    sets of rows never share what is kept for one (``DiagnosisData.once``; kept per array: ``DiagnosisData.rows_key``)."""
    return f"{len(rows)} {blake2b(np.ascontiguousarray(rows).tobytes()).hexdigest()}"


def input_run_steps(data: DiagnosisData, inp: Inputs) -> list[SampleSteps | None]:
    """The sampling steps of each run for ``first_order_lowpass`` (``DiagnosisData.run_steps``) when the inputs'
    times are the recording's (None per run otherwise)."""
    return data.run_steps() if same_memory(inp.t_s, data.t_s) else [None] * len(data.runs())


def run_coefficients(data: DiagnosisData, inp: Inputs, tau_s: float) -> list[float | None]:
    """The one coefficient of a first-order low-pass of time constant ``tau_s`` (s) over each run of the inputs
    (``uniform_coefficient`` of ``input_run_steps``; None where the inputs' times are not the recording's or the
    sampling changes it), kept per run and time constant by its bits: working it out is a pass over the run's steps,
    and every trial of a search over another effect asks again for the model's filters, every search of one for its
    grid's."""
    tau_s = float(tau_s)
    return [None if st is None else data.once(f"uniform coefficient {k} {tau_s!r}",
                                              lambda st=st: uniform_coefficient(tau_s, st))
            for k, st in enumerate(input_run_steps(data, inp))]


def with_gram(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return X, X.T @ X


def memory_key(a: np.ndarray) -> tuple:
    """What identifies the values of a read-only array: its memory, shape, strides and type. Views of the same
    memory (``Inputs.of`` makes one of each recorded array per design) have the same key."""
    return a.__array_interface__["data"][0], a.shape, a.strides, a.dtype.str


def same_memory(a: np.ndarray, b: np.ndarray) -> bool:
    """``a`` is ``b`` or a float64 view of all of it (``Inputs.of``): the recorded array, not a corrected one."""
    return a.dtype == np.float64 and memory_key(a) == memory_key(b)
