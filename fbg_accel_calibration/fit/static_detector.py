"""Static-interval detection from the sensor signal itself (multi-position calibration practice).

Pure numpy/scipy. Used offline by the fit to exclude samples taken while the table moves
(:func:`calibration_samples` on a recording in memory, ``fit_stream.prepare_stream`` on files: each run
read block by block either way), and by the noise model of the calibrated output to find still
intervals. The calibration node's live test, which must hold a false-alarm rate per run on correlated
noise, is :mod:`fbg_accel_driver.stillness_monitor`.

Method (the static detector of multi-position IMU calibration, e.g. Tedaldi, Pretto & Menegatti,
"A robust and easy to implement method for IMU calibration without external equipments", ICRA
2014): for every sample the variance of each component of the signal (normally
Psi = counts / ref, eq. 24) over a centred moving window of ``window`` samples is compared with a
threshold derived from the noise floor; a sample is static when every component is below its
threshold, and only runs of at least ``min_interval`` consecutive static samples are kept.

Threshold. For white noise of variance s^2 the window variance v (``window`` samples, ddof=1)
follows s^2 * chi2(w-1)/(w-1). The threshold per component is therefore
``s^2 * chi2.ppf(1 - false_alarm, w-1) / (w-1) * margin``: a still sample is flagged as moving with
probability ``false_alarm`` (for independent samples; low-pass-filtered noise has fewer degrees of
freedom, which ``margin`` (default 2) absorbs). The noise floor s^2 is estimated robustly from each run
itself as ``median(v) / (median(chi2(w-1))/(w-1))`` (:func:`estimate_noise_var`; the node's recorder
learns it from a still period first), valid when most samples are static -- true for any calibration
run, where dwell times are much longer than moves.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from scipy.special import gammaincinv

from fbg_accel_driver.thermal_model import normalise

from ..io.recording import Recording

DEFAULT_WINDOW = 5
DEFAULT_FALSE_ALARM = 1e-3
DEFAULT_MARGIN = 2.0
DEFAULT_MIN_INTERVAL = 5


BLOCK_ROWS = 65536  # moving variances are computed in blocks of this many rows (bounded memory)


def moving_variance(signal: np.ndarray, window: int) -> np.ndarray:
    """Variance (ddof=1) of each column over a centred window of ``window`` samples, (N, k).

    Near the ends the window is truncated to the available samples (NaN if only one is left).
    NaN anywhere in a window gives NaN for that window. Computed in blocks of ``BLOCK_ROWS`` rows
    (with the window's overlap), so the temporaries do not grow with N.
    """
    x = np.asarray(signal, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    if window < 2:
        raise ValueError(f"window must be >= 2 samples, got {window}")
    n = x.shape[0]
    out = np.empty(x.shape)
    half_lo = (window - 1) // 2
    half_hi = window - 1 - half_lo
    for start in range(0, n, BLOCK_ROWS):
        stop = min(n, start + BLOCK_ROWS)
        lo, hi = max(0, start - half_lo), min(n, stop + half_hi)
        out[start:stop] = _moving_variance_block(x[lo:hi], window)[start - lo:stop - lo]
    return out


def _moving_variance_block(x: np.ndarray, window: int) -> np.ndarray:
    n, k = x.shape
    half_lo = (window - 1) // 2
    half_hi = window - 1 - half_lo
    finite = np.isfinite(x)
    every = bool(finite.all())
    if every:  # the usual block: no NaN to skip (x.mean is nanmean's value then)
        z = x - x.mean(axis=0)
    else:
        centre = np.nanmean(x, axis=0) if finite.any() else np.zeros(k)
        z = np.where(finite, x - np.nan_to_num(centre), 0.0)
    c1, c2 = np.zeros((n + 1, k)), np.zeros((n + 1, k))
    np.cumsum(z, axis=0, out=c1[1:])
    np.cumsum(z * z, axis=0, out=c2[1:])
    cn = None if every else np.concatenate([[0], np.cumsum(~np.all(finite, axis=1))])

    def windows(rows: np.ndarray) -> np.ndarray:
        """The variance at ``rows`` over their windows, truncated at the block's ends."""
        lo = np.clip(rows - half_lo, 0, n)
        hi = np.clip(rows + half_hi + 1, 0, n)
        m = (hi - lo).astype(float)[:, None]
        s1 = c1[hi] - c1[lo]
        var = np.maximum((c2[hi] - c2[lo] - s1 * s1 / m) / np.maximum(m - 1.0, 1.0), 0.0)
        if cn is not None:
            var[(cn[hi] - cn[lo]) > 0] = np.nan
        var[m[:, 0] < 2] = np.nan  # a single sample has no variance
        return var

    if not every or n < window:
        return windows(np.arange(n))
    # rows whose window is whole: the same sums by slices, not gathers (the same values, bit for bit)
    var = np.empty((n, k))
    s1 = c1[window:] - c1[: n + 1 - window]
    var[half_lo: n - half_hi] = np.maximum((c2[window:] - c2[: n + 1 - window] - s1 * s1 / float(window))
                                           / float(window - 1), 0.0)
    edges = np.r_[np.arange(half_lo), np.arange(n - half_hi, n)]
    var[edges] = windows(edges)
    return var


def chi2_quantile(p: float, dof: int) -> float:
    """Quantile ``p`` of the chi-square distribution of ``dof`` degrees of freedom: ``scipy.stats.chi2.ppf``'s own
    formula, the same bits, without importing ``scipy.stats`` (half a second of every fit's start-up)."""
    return 2.0 * gammaincinv(dof / 2.0, p)


def variance_threshold(noise_var: np.ndarray, window: int, false_alarm: float = DEFAULT_FALSE_ALARM,
                       margin: float = DEFAULT_MARGIN) -> np.ndarray:
    """Window-variance threshold for a noise floor ``noise_var`` (see module docstring)."""
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f"false_alarm must be in (0, 1), got {false_alarm}")
    dof = window - 1
    return np.asarray(noise_var, dtype=float) * chi2_quantile(1.0 - false_alarm, dof) / dof * margin


def estimate_noise_var(statistic: np.ndarray, window: int) -> np.ndarray:
    """Robust noise-floor variance per column from moving-window variances (mostly static data)."""
    dof = window - 1
    med = np.nanmedian(statistic, axis=0)
    return med / (chi2_quantile(0.5, dof) / dof)


def quantisation_var(ref_counts: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """Mean variance (Psi^2, per axis) of the rounding of the readings to whole ADC counts, over samples with
    references ``ref_counts`` (n,) and Psi ``psi`` (n, 3): the axis count and the reference count each carry a
    uniform error of one count, so Psi = x / ref varies by (1 + Psi^2) / (12 ref^2). No still signal reads
    quieter than its quantisation, so a noise floor is never taken below it: a signal that sits on one code for
    most windows (an oversampled, low-pass-filtered channel, e.g. at 400 Hz) would otherwise give a floor near
    zero and call every window in which a code changes moving."""
    ref = np.asarray(ref_counts, dtype=float)[:, None]
    return np.mean((1.0 + np.asarray(psi, dtype=float) ** 2) / (12.0 * ref**2), axis=0)


def _run_lengths(change: np.ndarray) -> np.ndarray:
    """Length of the run each sample belongs to; a run starts where ``change`` is True (``change[0]`` is)."""
    segment = np.cumsum(change) - 1
    return np.bincount(segment)[segment]


def long_runs(mask: np.ndarray, min_interval: int) -> np.ndarray:
    """``mask`` (N,) bool kept only in runs of at least ``min_interval`` consecutive True samples."""
    mask = np.asarray(mask, dtype=bool)
    if len(mask) == 0:
        return mask.copy()
    return mask & (_run_lengths(np.r_[True, np.diff(mask.astype(np.int8)) != 0]) >= min_interval)


def usable_samples(static: np.ndarray, ref_still: np.ndarray, pose: np.ndarray, gref_ok: np.ndarray,
                   min_interval: int) -> np.ndarray:
    """The fit's interval rule on one run: static signal (``long_runs`` of the detector) AND still reference
    AND in a pose with a finite reference, kept only in stretches of at least ``min_interval`` such samples
    of one pose."""
    usable = static & ref_still & (np.asarray(pose) >= 0) & gref_ok
    if len(usable) == 0:
        return usable
    change = np.r_[True, (np.diff(pose) != 0) | (np.diff(usable.astype(np.int8)) != 0)]
    return usable & (_run_lengths(change) >= min_interval)


DEFAULT_REFERENCE_TOLERANCE_MPS2 = 1e-3  # m/s^2, standard deviation of the reference over the window when still


class VisitNumbers:
    """The number (within one run, from 0) of the visit each sample belongs to, block after block: a visit is one
    contiguous stay at one pose id, and a new one starts where the pose id changes (the stretches between poses,
    id -1, are numbered too)."""

    def __init__(self) -> None:
        self.last: int | None = None
        self.count = 0  # visits numbered so far

    def of(self, pose_id: np.ndarray) -> np.ndarray:
        """Visit numbers (n,) of the next ``pose_id`` (n,) of the run."""
        pose = np.asarray(pose_id)
        if len(pose) == 0:
            return np.zeros(0, np.int64)
        change = np.empty(len(pose), bool)
        change[0] = self.last is None or pose[0] != self.last
        np.not_equal(pose[1:], pose[:-1], out=change[1:])
        out = self.count - 1 + np.cumsum(change)
        self.count, self.last = int(out[-1]) + 1, int(pose[-1])
        return out


def clipped_visits(blocks: Iterator[Recording]) -> np.ndarray:
    """Numbers (``VisitNumbers``) of the visits at a pose of one run, served block by block, that hold a sample with a
    channel at a rail of the ADC (``Recording.clipped``). Such a visit is left out whole by the detector: where the
    signal sits at the rail, the samples of the visit that are not clipped are a censored, biased subset."""
    numbers, hit = VisitNumbers(), []
    for blk in blocks:
        visit = numbers.of(blk.pose_id)
        hit.append(visit[blk.clipped() & (blk.pose_id >= 0)])
    return np.unique(np.concatenate(hit)) if hit else np.zeros(0, np.int64)


def calibration_samples(rec: Recording, window: int = DEFAULT_WINDOW, min_interval: int = DEFAULT_MIN_INTERVAL,
                        false_alarm: float = DEFAULT_FALSE_ALARM, margin: float = DEFAULT_MARGIN,
                        tolerance_mps2: float = DEFAULT_REFERENCE_TOLERANCE_MPS2) -> tuple[np.ndarray, np.ndarray]:
    """Samples of a :class:`Recording` usable for a static calibration fit (N,) bool, and those whose sensor signal
    alone is static (N,) bool (the detector's kept runs, whatever the reference).

    Usable = belongs to a pose (``pose_id >= 0``, finite reference) AND the sensor signal Psi is still (the
    detector of the module docstring, noise floor estimated per run) AND the reference is constant over the
    window (to ``tolerance_mps2``, standard deviation: the table stands still; a window that includes a reference
    change or a NaN reference is not, e.g. right after a move, when the TIA low-pass (Table 1, ~1 Hz) has not
    settled) AND, after those, the sample lies in a run of at least ``min_interval`` usable samples of one pose,
    in a visit without a clipped sample (:func:`clipped_visits`). Each run goes through the streamed detector
    block by block, as a file does (:func:`usable_blocks`). The samples of a reference too low
    (``Recording.low_reference``: no source light) are neither: they are taken out before the detector, which decides
    on the run without them, as ``fit_stream.prepare_stream`` does (``recording.without_low_reference``).
    """
    usable, static = [np.zeros(0, bool)], [np.zeros(0, bool)]
    for run in rec.runs():
        low = run.low_reference()
        lit = run.select(~low) if low.any() else run  # the blocks of without_low_reference, in memory
        threshold = streamed_noise_floor(lambda lit=lit: lit.blocks(BLOCK_ROWS, False), window, false_alarm, margin)[1]
        left_out = clipped_visits(lit.blocks(BLOCK_ROWS))  # in memory: as cheap as finding whether any is clipped
        run_usable, run_static = [np.zeros(0, bool)], [np.zeros(0, bool)]
        for _blk, _psi, blk_usable, blk_static, _ in usable_blocks(lit.blocks(BLOCK_ROWS), window, min_interval,
                                                                   threshold, tolerance_mps2, left_out):
            run_usable.append(blk_usable)
            run_static.append(blk_static)
        for out, kept in ((usable, run_usable), (static, run_static)):
            flags = np.zeros(len(run), bool)
            flags[~low] = np.concatenate(kept)
            out.append(flags)
    return np.concatenate(usable), np.concatenate(static)


# ----------------------------------------------------------------------------- streamed
# A run is read block by block (a file larger than memory, or a recording in memory: ``Recording.blocks``) and
# goes through the kernels above: moving variances on the ``BLOCK_ROWS`` grid of :func:`moving_variance`, the
# rules with the context they need carried between blocks, and an exact streaming median for the noise floor.
class ExactMedian:
    """Exact ``np.nanmedian`` per column of a stream of (k)-column non-negative values, in passes.

    Radix selection on the IEEE-754 bit pattern, which orders non-negative doubles: the first pass
    histograms the top 16 bits; every further pass either narrows the bin holding each wanted rank
    by 16 more bits or, once that bin holds at most ``cap`` values, collects and sorts them. Memory:
    2^16 counts per column and rank plus ``cap`` values per column, whatever the number of samples.
    Passes: one when the first pass's speculative collection (the values of the bins around the
    first block's median, at most ``cap`` of them) holds the final median's bin -- the usual case
    for a calibration run whose noise floor does not drift by 1/8 octave --, else two for up to
    about ``cap`` / (fraction of the data in the median's 1/16-octave bin) samples, more beyond.
    """

    RADIX = 16
    SPEC_BINS = 2  # bins either side of the first block's median bin kept during the first pass

    def __init__(self, k: int, cap: int = 1 << 18) -> None:
        self.k, self.cap = k, cap
        self.count = np.zeros(k, np.int64)
        self.hist0 = np.zeros((k, 1 << self.RADIX), np.int64)
        self.targets: list[list[dict[str, Any]]] | None = None
        self.result = np.full(k, np.nan)
        self.done = False
        # speculation: during the first pass, keep the values of the bins around the first block's
        # median (at most ``cap`` values); if the final median falls in them, no second pass is needed
        self.spec_bins: list[tuple[int, int] | None] = [None] * k
        self.spec_values: list[list[np.ndarray] | None] = [[] for _ in range(k)]
        self.spec_count = np.zeros(k, np.int64)

    def add(self, values: np.ndarray) -> None:
        v = np.asarray(values, dtype=float).reshape(-1, self.k) + 0.0  # -0.0 -> +0.0
        for j in range(self.k):
            col = v[:, j]
            col = col[~np.isnan(col)]
            bits = col.view(np.uint64)
            if self.targets is None:
                self.count[j] += len(col)
                top = (bits >> np.uint64(64 - self.RADIX)).astype(np.int64)
                self.hist0[j] += np.bincount(top, minlength=1 << self.RADIX)
                if self.spec_bins[j] is None and self.count[j]:
                    cum = np.cumsum(self.hist0[j])
                    b = int(np.searchsorted(cum, (self.count[j] - 1) // 2, side="right"))
                    self.spec_bins[j] = (b - self.SPEC_BINS, b + self.SPEC_BINS)
                if self.spec_values[j] is not None and self.spec_bins[j] is not None:
                    lo, hi = self.spec_bins[j]
                    kept = col[(top >= lo) & (top <= hi)]
                    self.spec_count[j] += len(kept)
                    if self.spec_count[j] > self.cap:
                        self.spec_values[j] = None  # too many: give up, a second pass collects exactly
                    else:
                        self.spec_values[j].append(kept)
                continue
            for t in self.targets[j]:
                if t["value"] is not None:
                    continue
                sel = (bits >> np.uint64(t["shift"])) == np.uint64(t["prefix"])
                if t["collect"]:
                    t["values"].append(col[sel])
                else:
                    sub = (bits[sel] >> np.uint64(t["shift"] - self.RADIX)) & np.uint64((1 << self.RADIX) - 1)
                    t["hist"] += np.bincount(sub.astype(np.int64), minlength=1 << self.RADIX)

    def _narrow(self, t: dict[str, Any], hist: np.ndarray, prefix: int, shift: int) -> None:
        cum = np.cumsum(hist)
        b = int(np.searchsorted(cum, t["rank"], side="right"))
        t["rank"] -= int(cum[b - 1]) if b else 0
        t["prefix"], t["shift"] = (prefix << self.RADIX) | b, shift - self.RADIX
        if t["shift"] == 0:
            t["value"] = float(np.array([t["prefix"]], dtype=np.uint64).view(float)[0])
        t["collect"] = int(hist[b]) <= self.cap
        t["hist"] = np.zeros(1 << self.RADIX, np.int64)
        t["values"] = []

    def end_pass(self) -> None:
        """Close a pass over the whole stream; :attr:`done` tells whether another pass is needed."""
        if self.targets is None:
            self.targets = []
            for j in range(self.k):
                m = int(self.count[j])
                ranks = sorted({(m - 1) // 2, m // 2}) if m else []
                ts = [{"rank": r, "value": None} for r in ranks]
                spec = self.spec_values[j]
                spec_sorted = np.sort(np.concatenate(spec)) if spec else None
                for t in ts:
                    self._narrow(t, self.hist0[j], 0, 64)
                    lo, hi = self.spec_bins[j] or (1, 0)
                    if t["value"] is None and spec_sorted is not None and lo <= t["prefix"] <= hi:
                        in_bin = spec_sorted[(spec_sorted.view(np.uint64) >> np.uint64(t["shift"])) == np.uint64(t["prefix"])]
                        t["value"] = float(in_bin[t["rank"]])
                self.targets.append(ts)
            self.hist0 = np.zeros((0, 0), np.int64)
            self.spec_values = [None] * self.k
        else:
            for ts in self.targets:
                for t in ts:
                    if t["value"] is not None:
                        continue
                    if t["collect"]:
                        t["value"] = float(np.sort(np.concatenate(t["values"]))[t["rank"]])
                    else:
                        self._narrow(t, t["hist"], t["prefix"], t["shift"])
        self.done = all(t["value"] is not None for ts in self.targets for t in ts)
        if self.done:
            for j, ts in enumerate(self.targets):
                if len(ts) == 1:
                    self.result[j] = ts[0]["value"]
                elif ts:  # even count: mean of the two middle values, as np.median
                    self.result[j] = np.median(np.array([ts[0]["value"], ts[1]["value"]]))


def signal_blocks(blocks: Iterator[Recording], window: int, with_reference: bool):
    """Yield ``(block, psi, var_psi, var_gref)`` with the centred moving variances of each block computed
    exactly as :func:`moving_variance` computes them for the whole run (same
    ``BLOCK_ROWS`` grid and window overlap: one block of lookahead, ``window`` rows carried)."""
    half_lo = (window - 1) // 2
    half_hi = window - 1 - half_lo
    it = iter(blocks)
    cur = next(it, None)
    if cur is None:
        return
    cur_psi = normalise(cur.xyz, cur.ref)
    tail_psi, tail_g = np.zeros((0, 3)), np.zeros((0, 3))
    while cur is not None:
        nxt = next(it, None)
        nxt_psi = normalise(nxt.xyz, nxt.ref) if nxt is not None else np.zeros((0, 3))
        head_g = nxt.gref_mps2[:half_hi] if nxt is not None else np.zeros((0, 3))
        n, off = len(cur), len(tail_psi)
        var = _moving_variance_block(np.vstack([tail_psi, cur_psi, nxt_psi[:half_hi]]), window)[off:off + n]
        var_g = (_moving_variance_block(np.vstack([tail_g, cur.gref_mps2, head_g]), window)[off:off + n]
                 if with_reference else None)
        yield cur, cur_psi, var, var_g
        tail_psi = np.vstack([tail_psi, cur_psi[-half_lo:]])[-half_lo:] if half_lo else np.zeros((0, 3))
        tail_g = np.vstack([tail_g, cur.gref_mps2[-half_lo:]])[-half_lo:] if half_lo else np.zeros((0, 3))
        cur, cur_psi = nxt, nxt_psi


def usable_blocks(blocks: Iterator[Recording], window: int, min_interval: int, threshold: np.ndarray,
                   tolerance_mps2: float, left_out: np.ndarray | None = None):
    """Yield ``(block, psi, usable, static, clipped)`` of each block of one run: ``usable`` the fit's samples and
    ``static`` those whose signal is static (:func:`calibration_samples`), as if decided on the whole run at once;
    ``clipped`` the samples at a pose of the visits ``left_out`` (numbers of :class:`VisitNumbers`, from
    :func:`clipped_visits`; None: none), which are not usable.

    The run-length rules (static runs and pose segments of >= ``min_interval`` samples) only look
    ``2 * min_interval`` samples either way, so each block is decided with that much context carried
    from the previous block and taken from the next one (one block of lookahead).
    """
    if min_interval < 1:
        raise ValueError(f"min_interval must be >= 1 sample, got {min_interval}")
    ctx = 2 * min_interval + 2

    def flags(item):
        blk, psi, var, var_g = item
        still = np.all(var <= threshold, axis=1)
        ref_still = np.all(var_g <= tolerance_mps2**2, axis=1)
        gref_ok = np.all(np.isfinite(blk.gref_mps2), axis=1)
        return blk, psi, np.stack([still, ref_still, gref_ok], axis=1), blk.pose_id

    it = signal_blocks(blocks, window, with_reference=True)
    first = next(it, None)
    if first is None:
        return
    cur = flags(first)
    tail_f, tail_p = np.zeros((0, 3), bool), np.zeros(0, int)
    visits = VisitNumbers()
    while cur is not None:
        nxt_item = next(it, None)
        nxt = flags(nxt_item) if nxt_item is not None else None
        head_f = nxt[2][:ctx] if nxt is not None else np.zeros((0, 3), bool)
        head_p = nxt[3][:ctx] if nxt is not None else np.zeros(0, int)
        blk, psi, f, p = cur
        ff, pp = np.vstack([tail_f, f, head_f]), np.r_[tail_p, p, head_p]
        off = len(tail_f)
        static = long_runs(ff[:, 0], min_interval)
        usable = usable_samples(static, ff[:, 1], pp, ff[:, 2], min_interval)[off:off + len(p)]
        clipped = np.zeros(len(p), bool)
        if left_out is not None and len(left_out):
            clipped = np.isin(visits.of(p), left_out) & (p >= 0)
            usable &= ~clipped
        yield blk, psi, usable, static[off:off + len(p)], clipped
        tail_f, tail_p = np.vstack([tail_f, f[-ctx:]])[-ctx:], np.r_[tail_p, p[-ctx:]][-ctx:]
        cur = nxt


def streamed_noise_floor(blocks: Callable[[], Iterator[Recording]], window: int,
                         false_alarm: float = DEFAULT_FALSE_ALARM,
                         margin: float = DEFAULT_MARGIN) -> tuple[np.ndarray, np.ndarray]:
    """Noise floor and threshold (:func:`estimate_noise_var`, :func:`variance_threshold`) of one run whose
    blocks ``blocks()`` yields (called once per pass); returns ``(noise_var, threshold)``."""
    dof = window - 1
    med = ExactMedian(3)
    quant, n_ok = np.zeros(3), 0  # the run's quantisation floor (quantisation_var), summed over its samples
    while not med.done:
        for blk, psi, var, _ in signal_blocks(blocks(), window, with_reference=False):
            med.add(var)
            if med.targets is None:  # first pass
                ok = np.isfinite(blk.ref) & (blk.ref > 0) & np.all(np.isfinite(psi), axis=1)
                if ok.any():
                    quant += quantisation_var(blk.ref[ok], psi[ok]) * ok.sum()
                    n_ok += int(ok.sum())
        med.end_pass()
    nv = med.result / (chi2_quantile(0.5, dof) / dof)
    if n_ok:
        nv = np.maximum(nv, quant / n_ok)
    return nv, variance_threshold(nv, window, false_alarm, margin)
