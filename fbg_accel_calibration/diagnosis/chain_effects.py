"""Candidates of the measuring chain's dynamics: the axis channels late against the reference (``channel_delay``) and
the TIA first-order low-pass of paper Table 1 (``tia_lowpass``), each applied to the counts before eq. 24 as the
driver's ``ChainDynamics`` term does. Their bounds (``MAX_CHANNEL_DELAY_S``, ``MAX_TIA_SCALE``) and Table 1's time
constants are with the other effects' in ``diagnosis.effects``; the candidates are registered in
``diagnosis.library.LIBRARY``."""

from __future__ import annotations

import weakref
from typing import Any

import numpy as np

from fbg_accel_driver.correction_terms import ChainDynamics, first_order_lowpass

from .data import (
    DiagnosisData,
    Inputs,
    fill_reference_gaps,
    finite_rows,
    input_run_steps,
    interp_columns,
    psi_map_of,
    rows_at,
    rows_by_run,
    run_coefficients,
    set_rows,
    take_rows,
)
from .effects import (
    MAX_CHANNEL_DELAY_S,
    MAX_TIA_SCALE,
    MIN_DELAY_SEARCH_S,
    MIN_TIA_SCALE_SEARCH,
    TIA_TAU_S,
    Effect,
)
from .held_lowpass import HeldRows, held_lowpass, held_rows, lowpass_at, lowpass_states, moves, stretch_indices

# rows of the TIA's reference worked out at a time over every sample (``TiaLowpassEffect._held_every_sample``): the
# arrays of one block (a dozen of its length) stay a few MiB, not hundreds at 10^6 samples
ROW_BLOCK = 1 << 16


class ChannelDelayEffect(Effect):
    name = "channel_delay"
    reference_only = True
    bound = ("D from 0 to one sample interval plus MAX_CHANNEL_DELAY_S (100 ms): the board converts and stamps the "
             "four channels within a sample, the chain's analogue delay is the TIA's (a delay of the chain is tens of "
             "ms, sim_default.yaml); a longer one is the table's and the board's clocks disagreeing")
    stage = 1
    hyper_name = "D"
    hyper_unit = "s"
    title = "delay of the sensor channels against the reference angles"

    def hyper_limits(self, data: DiagnosisData) -> tuple[float, float]:
        return 0.0, MAX_CHANNEL_DELAY_S + max(data.dt_s, 0.0)

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        # 0 to 12 steps of the grid's unit, a sample or, above 120 Hz, 1/12 of MIN_DELAY_SEARCH_S: a delay of the chain
        # is a time (tens of ms, sim_default.yaml), and 12 samples at 500 Hz (24 ms) stopped short of a 40 ms one
        return np.arange(0.0, 12.5, 0.5) * max(data.dt_s, MIN_DELAY_SEARCH_S / 12)

    def transform(self, data: DiagnosisData, inp: Inputs, h: float | None) -> None:
        if float(h) != 0:
            inp.gref, inp.valid = self._delayed(data, inp, float(h), None, rows_by_run(data, None))
            # never written after (a correction after it replaces it): the TIA low-pass keeps the holds it finds in it
            # by the array itself (``TiaLowpassEffect._moved_held_reference``)
            inp.gref.flags.writeable = False
            inp.gref_moved = True

    def reference_at(self, data: DiagnosisData, inp: Inputs, h: float | None,
                     rows: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        pieces = rows_by_run(data, rows)
        if pieces is None or float(h) == 0:
            return super().reference_at(data, inp, h, rows)
        return self._delayed(data, inp, float(h), rows, pieces)

    @staticmethod
    def _delayed(data: DiagnosisData, inp: Inputs, D: float, rows: np.ndarray | None,
                 pieces: list[tuple[slice | np.ndarray, Any, Any]]) -> tuple[np.ndarray, np.ndarray]:
        """(reference (n, 3), valid (n,)) at ``rows`` (None: every sample; ``pieces``: ``rows_by_run``, whose runs
        hold every sample): the sample taken at t shows the table at t - D, so it is compared with the reference at
        t - D (each sample interpolated on its own), valid where t - D is not before its run's first sample."""
        f_all = data.gref_filled
        g, valid = ((np.array(f_all, dtype=float, copy=True), np.array(inp.valid, copy=True)) if rows is None
                    else (take_rows(f_all, rows), inp.valid[rows]))  # copies either way
        for run, sel, local in pieces:
            t = data.t_s[run]
            near = ChannelDelayEffect._near_a_move(data, run, D)
            if near is None:
                tq = t[local] - D
                g[sel] = interp_columns(tq, t, f_all[run])
                valid[sel] &= tq >= t[0]
                continue
            # the reference's own value where it held still over the delay (already in g), interpolated where it moved
            start, stop = near
            if rows is None:
                part = stretch_indices(start, stop)
                at = run.start + part
            else:
                k = np.searchsorted(stop, local, side="right")
                inside = k < len(stop)
                inside[inside] = start[k[inside]] <= local[inside]
                part = local[inside]
                at = sel[inside]
            # where t - D falls (times increasing, ``_near_a_move``): about D / step samples before each sample's own,
            # a guess that ``interval_of`` checks
            lag = round(float(D * (len(t) - 1) / (t[-1] - t[0]))) if len(t) > 1 else 0
            set_rows(g, at, interp_columns(t[part] - D, t, f_all[run], near=part - lag))  # whole rows: g[at] = ...
            first = _delay_start(t, D)
            if rows is None:
                valid[run.start:run.start + first] = False
            else:
                valid[sel] &= local >= first
        return g, valid

    @staticmethod
    def _near_a_move(data: DiagnosisData, run: slice | np.ndarray, D: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(start, stop) of the stretches [start, stop) of a run's samples (local, ascending, disjoint) whose reference
        delayed by ``D`` (s) is not their own: where the filled reference (``gref_filled``) moved within the delay
        before them. Elsewhere ``interp_columns`` at t - D reads two samples of one held value and gives that value,
        bit for bit (a zero slope): the table holds every pose for seconds and moves a quarter of the time, so a trial
        interpolates that quarter only. Each move from sample c to c + 1 reaches the samples after it up to
        t[c + 1] + D, and one more (a margin of a sample for the rounding of t - D); the moves of one motion, from
        sample to sample, reach as far as their last one does, so each motion is one stretch, worked out once (not
        per move, nor per sample). None where this does not apply (a run that is not contiguous, times not
        increasing)."""
        if not isinstance(run, slice):
            return None
        t = data.t_s[run]
        ok = data.once(f"times_increasing {run.start} {run.stop}", lambda: bool(np.all(np.diff(t) > 0)))
        if not ok:
            return None

        def motions() -> tuple[np.ndarray, np.ndarray]:
            # a motion: moves of the reference back to back
            c = np.flatnonzero(moves(data.gref_filled[run]))
            if not len(c):
                return c, c
            cut = np.flatnonzero(np.diff(c) > 1)
            return c[np.r_[0, cut + 1]] + 1, c[np.r_[cut, len(c) - 1]] + 1  # (c + 1 of its first move, of its last)

        first, last = data.once(f"reference_motions {run.start} {run.stop}", motions)
        n = len(t)
        reach = np.minimum(np.searchsorted(t, t[last] + D, side="right") + 1, n)
        # a motion's stretch can reach into the next one's: start each where the one before ends (reach increases)
        start = np.maximum(first, np.r_[0, reach[:-1]]) if len(first) else first
        keep = start < reach
        return start[keep], reach[keep]

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        # a pure delay is a time-stamp correction, not an acceleration term (see docs/effects.md)
        return [ChainDynamics(np.zeros(4), float(h))]

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        return f"D = {h:.4g} s (sensor channels late against the reference)"


def _delay_start(t: np.ndarray, D: float) -> int:
    """The first sample i of a run whose times ``t`` increase where t[i] - D (s; rounded as an array's difference) is
    not before t[0]: by bisection, about log2(n) samples, not n (t - D increases with t, rounded too)."""
    lo, hi = 0, len(t)
    while lo < hi:
        mid = (lo + hi) // 2
        if t[mid] - D >= t[0]:
            hi = mid
        else:
            lo = mid + 1
    return lo


def _expected_psi(kept: dict | None, P: np.ndarray, q: np.ndarray, g_at: np.ndarray,
                  g_rows: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The expected Psi = P g + q (eq. 25 inverted) of each axis where the TIA's filter reads a run's reference
    (``g_at``) and at the rows (``g_rows``, each (3, k) by column), a 3 x 3 map written out (no matrix product of a
    few hundred thousand rows by 3: BLAS's start costs more than the arithmetic). Kept in ``kept`` (the entry of the
    recorded reference's holds; None: not kept) for the map ``P``, ``q`` alone, by their bits: the trials of a search
    over the time constant read the same; a search over a correction of the counts before it changes the map on every
    trial (then each is worked out and replaces the last)."""
    key = P.tobytes() + q.tobytes()
    hit = None if kept is None else kept.get(key)
    if hit is None:
        hit = ([_affine(P[j], q[j], g_at) for j in range(3)], [_affine(P[j], q[j], g_rows) for j in range(3)])
        if kept is not None:
            for a in (*hit[0], *hit[1]):  # shared by the trials, of either lane
                a.flags.writeable = False
            kept.clear()
            kept[key] = hit
    return hit


def _affine(row: np.ndarray, offset: float, cols: np.ndarray | list[np.ndarray]) -> np.ndarray:
    """``row @ cols + offset`` for a row of 3 and 3 columns (3, n), written out term by term."""
    out = row[0] * cols[0]
    out += row[1] * cols[1]
    out += row[2] * cols[2]
    out += offset
    return out


class TiaLowpassEffect(Effect):
    name = "tia_lowpass"
    reference_only = True
    bound = ("the time constants at most MAX_TIA_SCALE (2) x those of the paper's Table 1: R_tr C_tr of its parts, "
             "which common tolerances move by about 26 % at most")
    stage = 2
    hyper_name = "tau_scale"
    hyper_unit = "x Table 1"
    title = "TIA first-order low-pass of the axis channels"

    def hyper_limits(self, data: DiagnosisData) -> tuple[float, float]:
        return 0.0, MAX_TIA_SCALE

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        # axis time constants from 0.05 sample to ~30 samples (Table 1 ratios between channels), and at least to
        # MIN_TIA_SCALE_SEARCH x Table 1: the stages are a time, and 30 samples at 500 Hz stopped at 0.64 x Table 1
        lo = 0.05 * data.dt_s / TIA_TAU_S[1:].min()
        hi = max(30 * data.dt_s, MIN_TIA_SCALE_SEARCH * TIA_TAU_S[1:].min()) / TIA_TAU_S[1:].min()
        return np.geomspace(lo, hi, 22)

    def taus(self, h: float) -> np.ndarray:
        return TIA_TAU_S * float(h)

    def transform(self, data: DiagnosisData, inp: Inputs, h: float | None) -> None:
        inp.gref, inp.valid = self._corrected(data, inp, float(h), None, rows_by_run(data, None))

    def reference_at(self, data: DiagnosisData, inp: Inputs, h: float | None,
                     rows: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        pieces = rows_by_run(data, rows)
        if pieces is None:
            return super().reference_at(data, inp, h, rows)
        return self._corrected(data, inp, float(h), rows, pieces)

    def _corrected(self, data: DiagnosisData, inp: Inputs, h: float, rows: np.ndarray | None,
                   pieces: list[tuple[slice | np.ndarray, Any, Any]]) -> tuple[np.ndarray, np.ndarray]:
        """(reference (n, 3), valid (n,)) at ``rows`` (None: every sample; ``pieces``: ``rows_by_run``). Of a
        reference without gaps (the recorded one or the channel delay's), the filters run over the samples in motion
        only (``_held_at_rows``: at a search's rows the cost of a trial is the motion's and the rows', not the
        series'); else over every sample, and the rest only at ``rows`` (a product row by row: the rows of the whole
        product)."""
        held = self._held_at_rows(data, inp, h, rows, pieces)
        if held is not None:
            return held
        # Filter the noise-free reference, not the noisy signal: the sensor shows LPF(Psi_true), so the
        # reference it must match is the one whose expected Psi went through the same filters. Inverting
        # the filter on the counts instead would amplify the (already filtered) noise by ~1/a.
        # Neither depends on the time constant: reuse the data's own when no earlier stage changed the inputs
        # (the hyper-parameter search calls this for every trial value).
        g = fill_reference_gaps(inp.t_s, inp.gref, data.runs()) if inp.gref_moved else data.gref_filled
        P, q = psi_map_of(data, inp)
        if inp.gref_moved or inp.counts_changed:
            psi_hat = g @ P.T
            psi_hat += q  # in place: one array of N x 3, not two
        else:
            # kept column by column (an (N, 3) view of a C-ordered (3, N)): each run's column is filtered in place of
            # a copy on every trial
            psi_hat = data.once("static_psi_hat_columns", lambda: np.ascontiguousarray((g @ P.T + q).T), True).T
        d = np.empty((len(g) if rows is None else len(rows), 3))
        tau = self.taus(h)
        for (run, sel, local), steps in zip(pieces, input_run_steps(data, inp), strict=True):
            for j in range(3):
                # a strided column copied first: scipy's filter runs about twice as slow on one
                d[sel, j] = first_order_lowpass(np.ascontiguousarray(psi_hat[run, j]), inp.t_s[run], tau[j + 1], {},
                                                steps)[local]
        d -= psi_hat if rows is None else take_rows(psi_hat, rows)
        # P is 3 x 3: one product, not a solve with N sides (a contiguous right side: numpy's fast product)
        gref = d @ np.ascontiguousarray(np.linalg.inv(P).T)
        gref += g if rows is None else take_rows(g, rows)
        return gref, (inp.valid if rows is None else inp.valid[rows]) & finite_rows(gref)

    def _held_at_rows(self, data: DiagnosisData, inp: Inputs, h: float, rows: np.ndarray | None,
                      pieces: list[tuple[slice | np.ndarray, Any, Any]]) -> tuple[np.ndarray, np.ndarray] | None:
        """``_corrected`` at ``rows`` (None: every sample) with the filters worked out by ``held_lowpass``: the
        expected Psi holds its value wherever the reference does (every pose; the channel delay's reference too, its
        holds shifted by the delay, the run's last cut short at its end), so each trial filters the samples in motion
        and works out the holds and the rows in closed form: the values of the recursion over every sample up to rounding
        (``test/test_held_lowpass.py``), and each row's value the same bit for bit whichever rows are asked for (a
        search's, or every sample's when the reference is corrected again after it). None where that does not apply:
        a gap in the reference, a run whose sampling changes the filter's coefficient."""
        moved = inp.gref_moved
        g = inp.gref if moved else data.gref_filled
        if not all(isinstance(run, slice) for run, _, _ in pieces) \
                or not (moved or data.once("gref_filled_finite", lambda: bool(finite_rows(g).all()))):
            return None
        tau = self.taus(h)
        coeff = [list(per) for per in zip(*(run_coefficients(data, inp, t) for t in tau[1:]), strict=True)]
        if any(a is None for per in coeff for a in per):
            return None
        if rows is None:  # every sample (a correction of the reference after it, the final model): not kept
            runs = [run for run, _, _ in pieces]
            holds = [self._held_reference(g[run], np.zeros(0, dtype=np.intp))[:2] for run in runs]
            # a moved reference with a gap (never in a hold: NaN is not the sample before it): over every sample
            if moved and not all(finite_rows(g_at.T).all() for _, g_at in holds):
                return None
            P, q = psi_map_of(data, inp)
            gref = self._held_every_sample(g, runs, holds, coeff, P, q)
            return gref, inp.valid & finite_rows(gref)
        rows_key = data.rows_key(rows)
        found = []
        for run, _, local in pieces:
            if moved:
                found.append((*self._moved_held_reference(data, g, run, local, rows_key), None))  # Psi not kept
            else:
                # the recorded reference's holds, and where the Psi they expect is kept (``_expected_psi``)
                found.append(data.once(f"held_reference {run.start} {run.stop} {rows_key}",
                                       lambda run=run, local=local: (*self._held_reference(g[run], local), {}), True))
            # a moved reference with a gap (never in a hold: NaN is not the sample before it): over every sample
            if moved and not finite_rows(found[-1][1].T).all():
                return None
        P, q = psi_map_of(data, inp)
        P_inv = np.linalg.inv(P)
        gref = np.empty((len(rows), 3))
        for (_, sel, _), per, (held, g_at, g_rows, kept) in zip(pieces, coeff, found, strict=True):
            psi_at, psi_rows = _expected_psi(kept, P, q, g_at, g_rows)
            d = [held_lowpass(held, psi_at[j], per[j]) - psi_rows[j] for j in range(3)]
            for k in range(3):
                gref[sel, k] = _affine(P_inv[k], 0.0, d) + g_rows[k]
        return gref, inp.valid[rows] & finite_rows(gref)

    @staticmethod
    def _held_every_sample(g: np.ndarray, runs: list[slice], holds: list[tuple[HeldRows, np.ndarray]],
                           coeff: list[list[float]], P: np.ndarray, q: np.ndarray) -> np.ndarray:
        """``_held_at_rows``'s reference (N, 3) at every sample of the reference ``g`` (N, 3), from each run's holds
        and the reference where the filter reads it (``holds``, of ``_held_reference`` with no rows), ``ROW_BLOCK``
        rows at a time: each filter's states at the holds are worked out once per run (``lowpass_states``) and each
        block's rows from them, so no array of the run's length is made but the result. The values are those of the
        rows asked for all at once, bit for bit: a row's value depends on the holds and on it alone."""
        P_inv = np.linalg.inv(P)
        gref = np.empty((len(g), 3))
        for run, (held, g_at), per in zip(runs, holds, coeff, strict=True):
            x, out = g[run], gref[run]
            states = [lowpass_states(held, _affine(P[j], q[j], g_at), per[j]) for j in range(3)]
            for lo in range(0, len(x), ROW_BLOCK):
                block = held.at(np.arange(lo, min(lo + ROW_BLOCK, len(x))))
                g_rows = np.ascontiguousarray(x[lo:lo + ROW_BLOCK].T)
                d = [lowpass_at(block, states[j], per[j]) - _affine(P[j], q[j], g_rows) for j in range(3)]
                for k in range(3):
                    out[lo:lo + ROW_BLOCK, k] = _affine(P_inv[k], 0.0, d) + g_rows[k]
        return gref

    @staticmethod
    def _held_reference(g: np.ndarray, rows: np.ndarray) -> tuple[HeldRows, np.ndarray, np.ndarray]:
        """(the holds of a run's reference ``g`` (n, 3) and where ``rows`` (local) fall, the reference where the filter
        reads it and at ``rows``, each (3, k) by column): what every trial of ``_held_at_rows`` shares."""
        held = held_rows(g, rows)
        return held, np.ascontiguousarray(rows_at(g, held.samples).T), np.ascontiguousarray(rows_at(g, rows).T)

    def _moved_held_reference(self, data: DiagnosisData, g: np.ndarray, run: slice, rows: np.ndarray,
                              rows_key: str) -> tuple[HeldRows, np.ndarray, np.ndarray]:
        """``_held_reference`` of a run of the reference ``g`` (N, 3) an earlier correction moved (the channel delay),
        at ``rows`` (local; ``rows_key`` their digest). Kept for the next searches' trials (``DiagnosisData.recent``:
        a search of the TIA on top of a delay asks on every trial) by the array itself, read-only: ``g``'s identity
        and a weak reference to it: the kept holds do not keep the array alive, are let go once it is gone (before the
        next trial's are made) and are never served for another (a new array at its address is not it). A writable
        array is worked out on each call."""
        if g.flags.writeable or g.base is not None:
            return self._held_reference(g[run], rows)

        def find() -> tuple[Any, ...]:
            held, g_at, g_rows = self._held_reference(g[run], rows)
            for a in (g_at, g_rows, *vars(held).values()):  # shared by the trials, of either lane
                a.flags.writeable = False
            return weakref.ref(g), held, g_at, g_rows

        # the predicate holds no reference to g: the entry stands while g lives, and g alone has its identity then
        return data.recent(("held_reference", id(g), run.start, run.stop, rows_key), find,
                           fresh=lambda hit: hit[0]() is not None)[1:]

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        return [ChainDynamics(self.taus(float(h)), 0.0)]

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        t = self.taus(float(h))
        return f"scale = {h:.3g} x Table 1: tau x/y/z = {t[1]:.3g}/{t[2]:.3g}/{t[3]:.3g} s"
