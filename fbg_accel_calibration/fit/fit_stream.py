"""The fit's preparation: runs read block by block into the sums of eq. 28, never held whole (pure numpy).

:func:`prepare_stream` selects the fit's samples (static detector), finds the temperature levels and scaling and
accumulates the per-cell sums of eq. 28 and the sample counts, for runs served by a :class:`SampleBlockSource`
(``mcap_reader.McapSampleStream``, ``csv_import.CsvSampleSource``, or a ``Recording`` in memory: :func:`prepare`), in
a few passes with memory independent of their length. ``thermal_fit.fit_thermal`` and
``model_selection.select_degree`` take the result (:class:`FitData`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from fbg_accel_driver.thermal_model import normalise

from ..io.input_validation import SampleCheck
from ..io.pass_spill import PassSpill
from ..io.recording import LowReference, Recording, without_low_reference, without_samples
from .static_detector import (
    BLOCK_ROWS,
    DEFAULT_FALSE_ALARM,
    DEFAULT_MARGIN,
    DEFAULT_MIN_INTERVAL,
    DEFAULT_REFERENCE_TOLERANCE_MPS2,
    DEFAULT_WINDOW,
    clipped_visits,
    streamed_noise_floor,
    usable_blocks,
)
from .thermal_fit import (
    DEFAULT_CHUNK,
    DEFAULT_LEVEL_GAP_C,
    CellAccumulator,
    CellStats,
    TemperatureClusters,
    count_orientations,
    temperature_scaling,
)


class SampleBlockSource(Protocol):
    """One run (one file) served block by block; see :class:`fbg_accel_calibration.io.mcap_reader.McapSampleStream`."""

    def blocks(self, block_rows: int, with_poses: bool) -> Iterator[Recording]:
        """Consecutive blocks of ``block_rows`` samples (the last one shorter) of the run, in time order.
        With ``with_poses=False`` pose id and reference may be missing (the first pass)."""
        ...


@dataclass
class FitData:
    """Everything the fit and the degree selection need, accumulated without holding the samples.

    ``stats`` are the per-cell sums at degree ``stats.degree`` (lower degrees are sub-blocks); ``level_means_c``
    the temperature levels (degC, ascending), ``t_center_c``/``t_scale_c`` the scaling tau = (T - centre)/scale;
    the counts are of samples fitted, seen, excluded as moving, excluded as invalid and excluded with their visit
    for a clipped sample (and of those visits), and of those left out for a reference too low (``low_reference``:
    how many and where, ``Recording.low_reference``); ``detector`` the static detector's settings and noise floor
    (variances of Psi). ``levels`` and ``level_map`` label a fitted sample's level (:meth:`level_of`).
    """

    stats: CellStats
    level_means_c: np.ndarray
    temperature_range_c: tuple[float, float]
    t_center_c: float
    t_scale_c: float
    n_used: int
    n_total: int
    n_excluded_motion: int
    n_excluded_other: int
    n_poses: int  # distinct orientations (thermal_fit.count_orientations), not pose ids
    levels: TemperatureClusters
    level_map: np.ndarray
    detector: dict[str, Any] = field(default_factory=dict)
    n_excluded_clipped: int = 0  # samples at a pose of the visits left out for a clipped sample (clipped_visits)
    n_clipped_visits: int = 0  # those visits
    low_reference: LowReference = field(default_factory=LowReference)  # samples left out: no source light
    # mean reference counts of the fitted samples per level (ADC counts, as level_means_c): the source power the
    # model holds at (ThermalCalibration.reference_level_counts)
    level_reference_counts: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # per source: the samples dropped for values no sensor gives (input_validation.SampleCheck: counts, temperature,
    # its junk readings, the reference's magnitude) and the samples without a temperature reading
    checks: list[SampleCheck] = field(default_factory=list)

    @property
    def n_rejected(self) -> int:
        """Samples the input check (:attr:`checks`) dropped or kept from the fit, all sources and reasons."""
        return sum(c.flagged for c in self.checks)

    def rejected_warnings(self, names: list[str]) -> list[str]:
        """The input check's lines (``SampleCheck.warnings``), ``names[i]`` naming source i."""
        return [line for c, name in zip(self.checks, names, strict=True) for line in c.warnings(name)]

    @property
    def n_excluded_low_reference(self) -> int:
        """Samples left out for a reference too low (``Recording.low_reference``), whatever else they were."""
        return self.low_reference.count

    def __len__(self) -> int:
        return self.n_used

    def level_of(self, temp_c: np.ndarray) -> np.ndarray:
        """Temperature level (N,) of fitted samples at ``temp_c`` degC: the ``level`` of their cells."""
        return self.level_map[self.levels.labels(temp_c)]

    def cell_stats(self, degree: int, chunk: int = DEFAULT_CHUNK) -> CellStats:
        """The sums for a fit of ``degree`` (<= ``stats.degree``): ``stats`` itself, no copy -- every
        ``CellStats`` method takes the degree and picks its columns (``sub_columns``), and the excitation
        checks read only columns that do not depend on the degree. ``chunk`` is not used: the sums are
        already accumulated."""
        if degree > self.stats.degree:
            raise ValueError(f"degree {degree} > the degree {self.stats.degree} the streamed sums were accumulated for")
        return self.stats


def fit_valid(rec: Recording, psi: np.ndarray) -> np.ndarray:
    """Samples (N,) the fit can use at all, static or not: in a pose with a finite reference, a valid temperature
    and a finite Psi (``psi`` (N, 3), the normalised counts of ``rec``)."""
    valid = (rec.pose_id >= 0) & np.all(np.isfinite(rec.gref_mps2), axis=1) & np.isfinite(rec.temp_c)
    return valid & np.all(np.isfinite(psi), axis=1)


def prepare(rec: Recording, degree: int, window: int = DEFAULT_WINDOW, min_interval: int = DEFAULT_MIN_INTERVAL,
            level_gap_c: float = DEFAULT_LEVEL_GAP_C, usable: np.ndarray | None = None,
            chunk: int = DEFAULT_CHUNK) -> FitData:
    """:func:`prepare_stream` of a recording in memory, each run (``Recording.runs``) read block by block as a file
    is. ``usable`` (N,) bool replaces the static detector (tests, the diagnosis, a report of given samples)."""
    runs = rec.runs()
    masks = None
    if usable is not None:
        usable = np.asarray(usable, dtype=bool)
        if usable.shape != (len(rec),):
            raise ValueError(f"usable must be one flag per sample ({len(rec)}), got shape {usable.shape}")
        ends = np.cumsum([len(r) for r in runs])
        masks = [usable[e - len(r):e] for r, e in zip(runs, ends, strict=True)]
    return prepare_stream(runs, degree, window, min_interval, level_gap_c, chunk, usable=masks)


def prepare_stream(sources: list[SampleBlockSource], degree: int, window: int = DEFAULT_WINDOW,
                   min_interval: int = DEFAULT_MIN_INTERVAL, level_gap_c: float = DEFAULT_LEVEL_GAP_C,
                   chunk: int = DEFAULT_CHUNK, false_alarm: float = DEFAULT_FALSE_ALARM, margin: float = DEFAULT_MARGIN,
                   tolerance_mps2: float = DEFAULT_REFERENCE_TOLERANCE_MPS2,
                   usable: list[np.ndarray] | None = None) -> FitData:
    """The fit's samples of runs read block by block and their sums of eq. 28 at ``degree`` (:class:`FitData`).

    Exact scheme, in passes over each run (``sources[i]`` is run i, as ``Recording.concatenate``):

    1. noise floor: moving variance of Psi per block (window carried between blocks) into an exact
       streaming median (:class:`static_detector.ExactMedian`, radix selection on the float bits): one pass to
       histogram (it also collects the pose/reference events), usually one more to collect the
       median's bin; the robust noise-floor estimate of the static detector (``static_detector``'s docstring);
       a run with a sample at an ADC rail (``Recording.clipped``) gets one pass more, with the poses, to find
       the visits left out whole (:func:`static_detector.clipped_visits`);
    2. temperatures: the static detector and the interval rules (:func:`static_detector.usable_blocks`, context of
       ``2 min_interval`` samples carried between blocks) select the fit samples; their temperatures
       go into the exact gap clustering (``thermal_fit.TemperatureClusters``) and the min/max that give the
       temperature levels and the scaling tau = (T - centre)/scale;
    3. sums: the same selection again (the detector's decisions of step 2 kept per block, ``pass_spill.PassSpill``),
       now with tau and the level of each sample, into :class:`CellAccumulator`, in chunks of ``chunk`` selected
       rows across blocks and runs.

    ``usable`` (one (N_i,) bool mask per source): the fit's samples given, no static detection (step 1 skipped).

    Before every step, the samples whose values no sensor gives are dropped from each run and counted
    (``input_validation.SampleCheck``, :attr:`FitData.checks`: every input route, CSV, MCAP or bag, gets this one
    check); then the samples of a reference too low (``Recording.low_reference``: no source light, Psi = counts
    / ref no measurement) are taken out of each run (``recording.without_low_reference``, also out of a given
    ``usable``): the result is that of the runs without them, and they are counted (``FitData.low_reference``).

    Memory: a few blocks of ``static_detector.BLOCK_ROWS`` samples, one chunk of the design matrix
    and O(cells + levels) state, independent of the number of samples. The sums do not depend on the block size
    (chunks of ``chunk`` selected rows across blocks and runs).
    """
    raw_sources, low_tally = sources, LowReference()
    checks = [SampleCheck() for _ in raw_sources]  # of the pass that counts (count=True)

    def checked(blocks: Iterator[Recording], check: SampleCheck, block_rows: int) -> Iterator[Recording]:
        """``blocks`` without the samples ``check`` drops (``input_validation.SampleCheck``)."""
        return without_samples(blocks, block_rows, check.apply)

    class Lit:
        """A source without the samples the input check drops, counted in ``checks`` when ``count`` is set, and
        without its samples of a reference too low, counted in ``low_tally`` then."""

        def __init__(self, src: SampleBlockSource, i: int) -> None:
            self.src, self.i, self.count = src, i, False

        def blocks(self, block_rows: int, with_poses: bool) -> Iterator[Recording]:
            check = SampleCheck()
            if self.count:
                checks[self.i] = check
            return without_low_reference(checked(self.src.blocks(block_rows, with_poses), check, block_rows),
                                         block_rows, low_tally if self.count else None, self.i)

    sources = [Lit(src, i) for i, src in enumerate(raw_sources)]
    thresholds: list[np.ndarray] = []
    left_out: list[np.ndarray | None] = []  # per source: the visits with a clipped sample (clipped_visits), or None
    noise_out, thr_out = np.zeros(3), np.zeros(3)
    for src in sources if usable is None else []:
        clipped = [False]

        def first_pass(src: SampleBlockSource = src, clipped: list[bool] = clipped) -> Iterator[Recording]:
            for blk in src.blocks(BLOCK_ROWS, False):
                clipped[0] = clipped[0] or bool(blk.clipped().any())
                yield blk

        nv, thr = streamed_noise_floor(first_pass, window, false_alarm, margin)
        thresholds.append(thr)
        noise_out, thr_out = np.maximum(noise_out, nv), np.maximum(thr_out, thr)
        # a pass more, with the poses, only for a file that has a clipped sample at all
        left_out.append(clipped_visits(src.blocks(BLOCK_ROWS, True)) if clipped[0] else None)

    def detected(src: SampleBlockSource, i: int) -> Iterator[tuple[Recording, np.ndarray, np.ndarray, np.ndarray]]:
        """(block, its Psi, its usable samples, its samples left out as clipped) of the run ``src``, the ``i``-th
        source."""
        if usable is None:
            for blk, psi, use, _static, clipped in usable_blocks(src.blocks(BLOCK_ROWS, True), window, min_interval,
                                                                 thresholds[i], tolerance_mps2, left_out[i]):
                yield blk, psi, use, clipped
            return
        start = 0
        check = SampleCheck()
        if src.count:
            checks[i] = check
        for blk in raw_sources[i].blocks(BLOCK_ROWS, True):  # the given mask is of every sample
            use = usable[i][start:start + len(blk)]
            start += len(blk)
            blk, bad, _ = check.apply(blk, last=True)  # block by block: no reading is held back
            if bad.any():
                blk, use = blk.select(~bad), use[~bad]
            low = blk.low_reference()
            if src.count:
                low_tally.add(i, blk.t_s, low)
            if low.any():
                blk, use = blk.select(~low), use[~low]
            yield blk, normalise(blk.xyz, blk.ref), use, np.zeros(len(blk), bool)

    # per source: each block's (usable, clipped) as the detector decided them in the first pass over it (steps 2, 3)
    selections: list[PassSpill | None] = [None] * len(sources)

    def kept_blocks(count: bool = False):
        for i, src in enumerate(sources):
            src.count = count
            kept = selections[i]
            if kept is not None:  # the same blocks again: the detector's decisions kept, not made again
                for blk, (use, clipped) in zip(src.blocks(BLOCK_ROWS, True), kept.pieces(), strict=True):
                    psi = normalise(blk.xyz, blk.ref)
                    valid = fit_valid(blk, psi)
                    yield i, blk, psi, use, valid, use & valid, clipped
                continue
            spill = PassSpill((bool, bool), keep_lengths=True) if usable is None else None
            for blk, psi, use, clipped in detected(src, i):
                if spill is not None:
                    spill.add(use, clipped)
                valid = fit_valid(blk, psi)
                yield i, blk, psi, use, valid, use & valid, clipped
            selections[i] = spill

    clusters = TemperatureClusters(level_gap_c)
    n_total = n_motion = n_other = n_clipped = 0
    t_min, t_max = np.inf, -np.inf
    for _i, blk, _psi, use, valid, keep, clipped in kept_blocks(count=True):  # the pass that counts the dark samples
        n_total += len(blk)
        n_clipped += int(clipped.sum())
        n_motion += int((valid & ~use & ~clipped).sum())
        n_other += int((~valid & ~clipped).sum())
        t = blk.temp_c[keep]
        clusters.add(t)
        if len(t):
            t_min, t_max = min(t_min, float(t.min())), max(t_max, float(t.max()))
    clusters.finish()
    n_total += low_tally.count + sum(c.count for c in checks)
    center, scale = temperature_scaling(np.array([t_min, t_max])) if np.isfinite(t_min) else (0.0, 1.0)

    acc = CellAccumulator(degree, chunk)
    # the rows of CellAccumulator.add: Psi, tau, reference, pose, level, run
    buffers = [np.empty((chunk, 3)), np.empty(chunk), np.empty((chunk, 3)), *(np.empty(chunk, np.int64) for _ in range(3))]
    fill = 0
    level_sum = np.zeros(clusters.n_labels)
    level_count = np.zeros(clusters.n_labels, np.int64)
    level_ref_sum = np.zeros(clusters.n_labels)
    for i, blk, psi, _use, _valid, keep, _clipped in kept_blocks():
        rows = np.flatnonzero(keep)
        t = blk.temp_c[rows]
        lab = clusters.labels(t)
        level_sum += np.bincount(lab, weights=t, minlength=clusters.n_labels)
        level_count += np.bincount(lab, minlength=clusters.n_labels)
        level_ref_sum += np.bincount(lab, weights=blk.ref[rows].astype(float), minlength=clusters.n_labels)
        columns = (psi[rows], (t - center) / scale, blk.gref_mps2[rows], blk.pose_id[rows], lab,
                   np.broadcast_to(i, len(rows)))  # a cell is one run's (CellStats)
        start = 0
        while start < len(rows):
            take = min(chunk - fill, len(rows) - start)
            for buf, col in zip(buffers, columns, strict=True):
                buf[fill:fill + take] = col[start:start + take]
            fill += take
            start += take
            if fill == chunk:
                acc.add(*buffers)
                fill = 0
    if fill:
        acc.add(*(buf[:fill] for buf in buffers))
    present = np.flatnonzero(level_count)
    level_map = np.full(max(clusters.n_labels, 1), -1, np.int64)
    level_map[present] = np.arange(len(present))
    stats = acc.finish(level_map)
    n_used = int(level_count.sum())
    detector = ({"window_samples": window, "min_interval_samples": min_interval, "noise_var_psi": noise_out.tolist(),
                 "threshold_var_psi": thr_out.tolist()} if usable is None else {"mask": "given by caller"})
    return FitData(stats, level_sum[present] / level_count[present], (t_min, t_max), center, scale, n_used, n_total,
                   n_motion, n_other, count_orientations(stats), clusters, level_map, detector, n_clipped,
                   sum(len(v) for v in left_out if v is not None), low_tally,
                   level_ref_sum[present] / level_count[present], checks)
