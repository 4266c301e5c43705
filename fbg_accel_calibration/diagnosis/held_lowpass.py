"""A first-order low-pass of a signal that holds its value for long stretches, worked out at chosen rows only.

The filter is ``correction_terms.first_order_lowpass``'s: y[0] = x[0], then y[n] = a x[n] + c y[n-1] with c = 1 - a
(a run of uniform sampling: one coefficient a). A search tries many time constants on one recording and needs the
output at its searched rows only (every k-th fitted sample), while the input (the table's reference, so the Psi it
expects) holds its value through every pose. Over a hold of L samples of value v the recursion is, exactly,
y_end = v + c^L (y_before - v), and at its m-th sample v + c^m (y_before - v): the filter needs every sample only where
the input moves. So:

1. the samples outside the holds (the motion between poses, short stretches; ``HeldRows.busy``) are filtered as one
   series by ``lfilter``, each stretch starting from the state the stretch before it left, as if the holds between
   them were not there;
2. the state entering each hold follows from the one entering the hold before it by an affine map (the hold's c^L,
   then the stretch after it, whose own start the map corrects by c^k times the difference of the true state and the
   one ``lfilter`` carried in); the maps are composed by a prefix scan (log2 of the number of holds numpy passes);
3. each row is then the closed form of its hold, or ``lfilter``'s value plus the decayed correction of its stretch.

The cost of a trial is that of the samples in motion plus the holds and rows, not of the whole series. The values are
those of the recursion over every sample up to rounding (the powers c^L for L multiplications, the scan's order of
products): ``test/test_held_lowpass.py`` sets them against ``first_order_lowpass``; ``bench/fingerprint_compare.py``
says how far the diagnosis' numbers move (docs/diagnose_speed.md). A row's value does not depend on which other rows
are asked for: the holds are the input's, the rows only read them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from fbg_accel_driver.correction_terms import lowpass_after_first

# holds shorter than this are filtered with the samples in motion: an lfilter step costs a few ns, a hold in the scan
# and the closed forms some tens
MIN_HOLD = 16


@dataclass(frozen=True)
class HeldRows:
    """A run's samples (local indices 0..n-1) split into the holds of its input and the rest, and where the rows fall
    (``held_rows``): what a search's trials share, whatever the time constant."""

    busy: np.ndarray  # (b,) the samples outside the holds, ascending; 0 (where the filter starts) first
    start: np.ndarray  # (m,) each hold's first sample (>= 1)
    stop: np.ndarray  # (m,) the sample after its last
    length: np.ndarray  # (m,) its samples (float: an exponent)
    before: np.ndarray  # (m,) position in ``busy`` of the last sample before the hold
    n_after: np.ndarray  # (m,) samples of ``busy`` between the hold and the next one or the run's end (float)
    rows: np.ndarray  # (q,) the rows asked for (local)
    busy_at: np.ndarray  # (q,) each row's position in ``busy`` (used for the rows outside the holds)
    in_hold: np.ndarray  # (i,) the positions in ``rows`` of the rows in a hold
    in_hold_of: np.ndarray  # (i,) their hold
    in_hold_steps: np.ndarray  # (i,) filter steps from their hold's start (float)
    after: np.ndarray  # (j,) the positions of the rows outside the holds with a hold before them
    after_of: np.ndarray  # (j,) that hold (the last before them)
    after_steps: np.ndarray  # (j,) filter steps from the start of the stretch after it (float)

    @property
    def samples(self) -> np.ndarray:
        """(b + m,) the samples where the input is read: ``busy`` then each hold's first sample (its value)."""
        return np.concatenate([self.busy, self.start])

    def at(self, rows: np.ndarray) -> HeldRows:
        """The same holds, for the rows ``rows`` (local indices, ascending) instead: a row's entries depend on the
        holds and on it alone, so the rows of a long run can be asked for a block at a time."""
        rows = np.asarray(rows, dtype=np.intp)
        hold = np.searchsorted(self.start, rows, side="right") - 1
        h = np.maximum(hold, 0)
        first, last = (self.start[h], self.stop[h]) if len(self.start) else (np.zeros_like(rows), np.zeros_like(rows))
        in_hold = (hold >= 0) & (rows < last)
        busy_at = np.minimum(np.searchsorted(self.busy, rows), len(self.busy) - 1)
        inside, after = np.flatnonzero(in_hold), np.flatnonzero(~in_hold & (hold >= 0))
        return replace(self, rows=rows, busy_at=busy_at, in_hold=inside, in_hold_of=hold[inside],
                       in_hold_steps=(rows[inside] - first[inside] + 1).astype(float), after=after,
                       after_of=hold[after], after_steps=(rows[after] - last[after] + 1).astype(float))


def held_rows(x: np.ndarray, rows: np.ndarray, min_hold: int = MIN_HOLD) -> HeldRows:
    """:class:`HeldRows` of the input ``x`` (n,) or (n, k) (a hold: at least ``min_hold`` consecutive samples, from
    the second on, where every column keeps its value) for the rows ``rows`` (local indices, ascending)."""
    x = np.asarray(x)
    n = len(x)
    s = np.concatenate([[0], np.flatnonzero(moves(x)) + 1])  # the constant stretches
    e = np.append(s[1:], n)
    s = np.maximum(s, 1)  # sample 0 starts the filter: never in a hold
    keep = e - s >= min_hold
    start, stop = s[keep], e[keep]
    busy = stretch_indices(np.r_[0, stop], np.r_[start, n])  # between the holds (before the first, after the last)
    before = np.searchsorted(busy, start) - 1
    n_after = np.searchsorted(busy, np.append(start[1:], n)) - (before + 1)
    none = np.zeros(0, dtype=np.intp)
    holds = HeldRows(busy, start, stop, (stop - start).astype(float), before, n_after.astype(float), none, none, none,
                     none, none.astype(float), none, none, none.astype(float))
    return holds.at(rows)


def moves(x: np.ndarray) -> np.ndarray:
    """(n - 1,) bool: where the input ``x`` (n,) or (n, k) moves from one sample to the next (a column differs, or is
    NaN: never the same). Column by column: numpy's reduction along a row of 3 costs more than the comparisons."""
    if x.ndim == 1:
        return x[1:] != x[:-1]
    out = x[1:, 0] != x[:-1, 0]
    for j in range(1, x.shape[1]):
        out |= x[1:, j] != x[:-1, j]
    return out


def stretch_indices(start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """The indices of the stretches [start, stop) (ascending, disjoint; an empty one, start = stop, adds none), in
    order: ``np.r_`` of their ranges, at the cost of the indices it gives, not of the span they cover."""
    keep = stop > start
    start, stop = start[keep], stop[keep]
    length = stop - start
    out = np.ones(int(length.sum()), dtype=np.intp)
    if len(out):
        out[0] = start[0]
        out[np.cumsum(length)[:-1]] = start[1:] - stop[:-1] + 1  # from the last of one stretch to the first of the next
    return np.cumsum(out)


def _scan(alpha: np.ndarray, beta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Prefix compositions of the affine maps s -> alpha_i s + beta_i: (A_i, B_i) with f_i o ... o f_0 = A_i s + B_i,
    by doubling (log2(m) passes)."""
    a, b = alpha.copy(), beta.copy()
    d = 1
    while d < len(a):
        b[d:] = a[d:] * b[:-d] + b[d:]  # right side first: both use the maps composed so far
        a[d:] = a[d:] * a[:-d]
        d *= 2
    return a, b


def held_lowpass(held: HeldRows, x_at: np.ndarray, a: float) -> np.ndarray:
    """y (q,) at ``held.rows`` of the low-pass y[0] = x[0], y[n] = a x[n] + (1 - a) y[n-1], from the input at
    ``held.samples`` only (``x_at``: the values there, (b + m,)): see the module docstring."""
    return _first_stage(held, x_at, a)[0]


def held_cascade(held: HeldRows, x_at: np.ndarray, a: float) -> tuple[np.ndarray, np.ndarray]:
    """(y, z) (q,) each at ``held.rows``: y the low-pass of ``held_lowpass``, z the same low-pass of y (z[0] = y[0],
    z[n] = a y[n] + c z[n-1], c = 1 - a: two filters of one time constant in cascade), from the input at
    ``held.samples`` only.

    Over a hold of value v entered with the states (y0, z0), m steps in: y = v + c^m (y0 - v) and, the cascade's
    double pole, z = v + c^m (z0 - v) + m a c^m (y0 - v). The samples outside the holds go through both filters as
    one series; where a stretch of them starts after a hold, the states ``lfilter`` carried in differ from the true
    ones by (d, e), and that difference decays through the stretch as the filters' own response, k steps on
    (c^k d, c^k e + k a c^k d). So z's state entering each hold follows from the one before by an affine map of the
    same factor as y's, and one more prefix scan gives it once y's states are known."""
    y, st = _first_stage(held, x_at, a)
    c = 1.0 - a
    zb = lowpass_after_first(st.yb, a, float(st.yb[0]))  # z[0] = y[0], then lfilter from c y[0]
    z = zb[held.busy_at]
    if st.v is None:
        return y, z
    v, y_in, d = st.v, st.s_in, st.delta
    L, n = held.length, held.n_after
    end = held.before + n.astype(np.intp)
    # z's state entering hold i + 1 from the one entering hold i (y's known): the hold, then the stretch after it
    into = v * (1.0 - st.c_hold) + L * a * st.c_hold * (y_in - v)
    beta = np.where(n > 0, zb[end] + st.c_after * (into - zb[held.before]) + n * a * st.c_after * d, into)
    A, B = _scan(st.c_after * st.c_hold, beta)
    z_in = np.empty(len(v))
    z_in[0] = zb[held.before[0]]
    z_in[1:] = A[:-1] * z_in[0] + B[:-1]
    e = v + st.c_hold * (z_in - v) + L * a * st.c_hold * (y_in - v) - zb[held.before]
    h, m = held.in_hold_of, held.in_hold_steps
    c_m = _powers(c, m)
    z[held.in_hold] = v[h] + c_m * (z_in[h] - v[h]) + m * a * c_m * (y_in[h] - v[h])
    j, k = held.after_of, held.after_steps
    c_k = _powers(c, k)
    z[held.after] += c_k * e[j] + k * a * c_k * d[j]
    return y, z


def _powers(c: float, k: np.ndarray) -> np.ndarray:
    """``np.power(c, k)`` for the whole numbers ``k`` (float; the rows' steps into a hold or a stretch), the same values
    bit for bit: where there are more of them than their largest value, the powers c^0..c^max are worked out once and
    looked up (the rows of a search fall some tens of thousands into holds of at most a few thousand samples: a power
    costs some tens of ns, a lookup a few)."""
    top = int(k.max()) if len(k) else 0
    if len(k) <= 2 * (top + 1):
        return np.power(c, k)
    return np.power(c, np.arange(top + 1, dtype=float))[k.astype(np.intp)]


@dataclass(frozen=True)
class FilterStates:
    """What the low-pass leaves at a run's holds (``lowpass_states``), which ``lowpass_at`` and ``held_cascade`` read:
    its values at ``busy`` (b,), and per hold (m,; None: no hold) the hold's value, its c^L, the c^n of the stretch
    after it, the true state entering it and the difference of the true and the carried state where the stretch after
    it starts."""

    yb: np.ndarray
    v: np.ndarray | None = None
    c_hold: np.ndarray | None = None
    c_after: np.ndarray | None = None
    s_in: np.ndarray | None = None
    delta: np.ndarray | None = None


def _first_stage(held: HeldRows, x_at: np.ndarray, a: float) -> tuple[np.ndarray, FilterStates]:
    """(y (q,) at ``held.rows``, what the filter left at ``held``'s samples and holds) of ``held_lowpass``."""
    st = lowpass_states(held, x_at, a)
    return lowpass_at(held, st, a), st


def lowpass_states(held: HeldRows, x_at: np.ndarray, a: float) -> FilterStates:
    """What ``held_lowpass``'s filter leaves at ``held``'s samples and holds (whatever rows ``held`` is for): with it,
    ``lowpass_at`` gives the output at the rows of any ``held.at(rows)``."""
    b = len(held.busy)
    xb, v = x_at[:b], x_at[b:]
    c = 1.0 - a
    yb = lowpass_after_first(xb, a, float(xb[0]))  # y[0] = x[0], then lfilter from c x[0]
    m = len(v)
    if not m:
        return FilterStates(yb)
    c_hold = np.power(c, held.length)
    c_after = np.power(c, held.n_after)
    end = held.before + held.n_after.astype(np.intp)  # the last sample of the stretch after each hold (else ``before``)
    into = v * (1.0 - c_hold)  # what the hold's value brings in
    # state entering hold i + 1 from the one entering hold i: c_after (c_hold s + into - yb[before]) + yb[end]
    alpha = c_after * c_hold
    beta = np.where(held.n_after > 0, yb[end] + c_after * (into - yb[held.before]), into)
    A, B = _scan(alpha, beta)
    s_in = np.empty(m)  # the true state entering each hold
    s_in[0] = yb[held.before[0]]
    s_in[1:] = A[:-1] * s_in[0] + B[:-1]
    delta = v + c_hold * (s_in - v) - yb[held.before]  # true minus carried state where the stretch after a hold starts
    return FilterStates(yb, v, c_hold, c_after, s_in, delta)


def lowpass_at(held: HeldRows, st: FilterStates, a: float) -> np.ndarray:
    """y (q,) at ``held.rows`` of the filter whose states at the holds are ``st`` (``lowpass_states`` of the same
    holds): each row's value from its hold's closed form or its stretch's, alone."""
    out = st.yb[held.busy_at]
    if st.v is None:
        return out
    c = 1.0 - a
    h = held.in_hold_of
    out[held.in_hold] = st.v[h] + _powers(c, held.in_hold_steps) * (st.s_in[h] - st.v[h])
    out[held.after] += _powers(c, held.after_steps) * st.delta[held.after_of]
    return out
