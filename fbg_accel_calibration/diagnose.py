"""Residual diagnosis of the calibration model: find what eq. 28 lacks, add it, report before/after.

Pure numpy/scipy engine behind ``fbg-accel-calib diagnose``. Steps:

1. Static samples: the static-interval detector of the fit (``static_detector.calibration_samples``,
   signal still AND table reference constant AND in a pose) or, with ``static="table"``, every
   sample the table reports in a pose; never a sample of a reference too low (``Recording.low_reference``: no
   source light), which is taken out of the recording first, as the fit takes it out.
2. Declared model: eq. 28 at the degree chosen by cross-validation over visits (degree
   < number of temperature levels, as in ``thermal_fit``). Noise floor = per-sample standard deviation
   of its residual per axis within visits over settled samples (what no static model can remove),
   corrected for what removing each visit's mean and line takes of correlated noise
   (``within_visit_noise``); the settling transient after a table move is measured and reported on its own. A
   periodic disturbance common to the visits (a table that sways, a fan: ``periodic_disturbance``) is named, and
   the floor is the scatter without it (with it reported beside).
   A visit is one contiguous static interval of one pose id in one run (``effects.visit_ids``); the
   pose id is the orientation. Folds that would lose a direction of the table frame are split or
   their visit kept in training (``check_folds``).
3. Every candidate of ``effects.LIBRARY`` on top of the current model: hyper-parameter by a 1-D
   search (grid; nested inside each training fold for the held-out figures, then refined on all
   data for the final value); held-out residuals by K-fold cross-validation over visits;
   per-visit paired gain in noise-weighted held-out MSE; one-sided Wilcoxon signed-rank test over
   visits (Bonferroni over the candidates of the step); correlation of the candidate's
   contribution with the held-out residual; pairwise confounding among the significant ones (each
   added on top of the other: does it still gain?).
4. Forward selection: add the best significant candidate, repeat; stop when no candidate is
   significant or gains less than ``min_rel_gain`` of the held-out MSE (so nothing is added when
   nothing is significant). Above ``SEARCH_ROWS`` fitted samples, steps 3-4 run on every k-th fitted
   sample (the same visits and folds; ``search_samples``: k no larger than keeps ``MIN_SEARCH_INFORMATION``
   of what a visit's samples tell of its mean) and only the chosen model is fitted on all.
5. Refit with the winners as declared ``corrections`` of a ``ThermalCalibration``; check that the
   driver's ``apply_counts`` reproduces the fit's prediction; before/after held-out RMSE per axis
   next to the noise floor; test and describe what residual remains (per pose, axis, temperature,
   time, orientation).

Significance is tested with visits as the independent units, not samples: the noise of this
sensor is low-pass filtered (TIA ~1 Hz at 100 Hz sampling), so consecutive samples are strongly
correlated and a sample-level F-test would be far too optimistic.
"""

from __future__ import annotations

import copy
import math
import threading
import time
import weakref
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np
from scipy import fft as scipy_fft
from scipy import optimize, stats

from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2
from fbg_accel_driver.thermal_model import ThermalCalibration

from .adc_codes import HeldCode, held_codes
from .blas_threads import single_blas_thread
from .dynamic_analysis import peak_offset
from .effects import (
    LIBRARY,
    MIN_SPAN_FRACTION,
    TIA_TAU_S,
    DiagnosisData,
    Effect,
    Inputs,
    ResponseStepEffect,
    direction_labels,
    finite_rows,
    memory_key,
    motion_groups,
    separating_measurement,
    take_rows,
    visit_ids,
    visit_means,
)
from .heap_trim import keep_freed_pages, return_free_memory, share_one_heap
from .model_selection import DegreeScores, choose_degree
from .model_selection import select_degree as calibration_select_degree
from .periodic_disturbance import PeriodicDisturbance, find_periodic_disturbance
from .recording import LowReference, Recording, time_axis_label
from .search_lanes import Lanes, beside, default_lane_count, idle_lanes
from .static_detector import calibration_samples
from .temperature_reading import jump_warning, reading_jumps
from .thermal_fit import (
    NotIdentifiedError,
    coefficients_to_model,
    design_matrix,
    n_params,
    reference_reach_warnings,
    scaled_condition,
    solve_normal_equations,
    temperature_levels,
    temperature_scaling,
)

# ============================================================================ data preparation
SAMPLE_SELECTIONS = ("table", "detector", "all")


def prepare_data(rec: Recording, static: str = "table", beside_thread: bool = False) -> DiagnosisData:
    """Diagnosis arrays from a recording. ``static`` selects the samples that are fitted and judged:

    * ``"table"`` (default): every sample of a pose the table held for at least 5 samples (the
      reference is known and constant). Chain dynamics that outlast the stop stay visible.
    * ``"detector"``: the fit's static-interval detector (signal still AND reference constant); it
      removes settling samples, so it hides most of the chain dynamics.
    * ``"all"``: every sample with a finite reference, including those taken while the table moves
      (only for recordings whose reference is the table's angle reading during motion, e.g. the
      simulator; samples in motion are cross-validated with the pose the table moves to).

    Whichever the selection, the samples of a reference too low (``Recording.low_reference``: no source light) are
    not in the result at all (counted in ``n_low_reference``, named in ``low_reference_note``), and a visit with a
    clipped channel is left out whole. ``beside_thread``: the temperature reading's jumps (a scan of every reading) are
    looked for on a thread of their own meanwhile the rest (``search_lanes.beside``).
    """
    if static not in SAMPLE_SELECTIONS:
        raise ValueError(f"static must be one of {SAMPLE_SELECTIONS}, got {static!r}")
    # the samples of a reference too low (no source light: Psi = counts/ref is no measurement) are taken out of the
    # recording first, as the fit takes them out (fit_stream.prepare_stream): the diagnosis of the recording without
    # them, whichever the selection, with a visit partly dark keeping its other samples
    dark = LowReference()
    dark.add_recording(rec)
    if dark.count:
        rec = rec.select(~rec.low_reference())
    jumps = beside(reading_jumps, rec.t_s, rec.temp_c, rec.run_id, thread=beside_thread)
    finite = finite_rows(rec.gref_mps2) & np.isfinite(rec.ref) & (rec.ref > 0)
    finite &= finite_rows(rec.xyz) & np.isfinite(rec.temp_c)
    # the visits with a channel at an ADC rail are left out whole, as the fit's detector leaves them out
    # (static_detector.clipped_visits), whichever the selection; and so is a clipped sample taken in motion
    visit, posed, at_rail = visit_ids(rec.pose_id, rec.run_id), rec.pose_id >= 0, rec.clipped()
    clipped = np.unique(visit[at_rail & posed])
    left_out = np.isin(visit, clipped) & posed
    finite &= ~(left_out | at_rail)
    if static == "all":
        use = finite & (motion_groups(rec.pose_id, rec.run_id) >= 0)
    elif static == "detector":
        usable, _ = calibration_samples(rec)
        use = usable & finite & (rec.pose_id >= 0)
    else:
        finite &= rec.pose_id >= 0
        # every sample of a pose the table held for at least 5 consecutive samples
        change = np.r_[True, (np.diff(rec.pose_id) != 0) | (np.diff(rec.run_id) != 0)]
        seg = np.cumsum(change) - 1
        use = finite & (np.bincount(seg)[seg] >= 5)
    if use.sum() < 20:
        raise ValueError(f"only {int(use.sum())} static samples with a reference: nothing to diagnose")
    return DiagnosisData(rec.t_s, rec.ref, rec.xyz, rec.temp_c, rec.gref_mps2, rec.pose_id, rec.run_id, use,
                         group=visit, n_clipped_samples=int(left_out.sum()), n_clipped_visits=len(clipped),
                         n_low_reference=dark.count, low_reference_note=dark.warning(),
                         temperature_jumps=jumps.result())


# ============================================================================ model specification
@dataclass
class ModelSpec:
    """Declared degree + temperature scaling + the effects added so far, each with its hyper-parameter."""

    degree: int
    t_center_c: float
    t_scale_c: float
    effects: list[tuple[Effect, float | None]] = field(default_factory=list)

    def plus(self, effect: Effect, h: float | None) -> ModelSpec:
        return ModelSpec(self.degree, self.t_center_c, self.t_scale_c, [*self.effects, (effect, h)])

    @property
    def key(self) -> tuple:
        """What identifies the model: degree, temperature scaling, effects with their hyper-parameters."""
        return (self.degree, self.t_center_c, self.t_scale_c, tuple((e.name, h) for e, h in self.effects))

    @property
    def names(self) -> list[str]:
        return [e.name for e, _ in self.effects]


@dataclass
class Design:
    X: np.ndarray  # (N, p)
    G: np.ndarray  # (N, 3) reference (possibly re-aligned)
    valid: np.ndarray  # (N,) rows where X and G are finite and the effects are defined
    blocks: dict[str, slice]  # extra-column block of each effect
    n_base: int


def _transforms_inputs(eff: Effect) -> bool:
    return type(eff).transform is not Effect.transform


class _Recent(OrderedDict):
    """At most ``size`` entries once trimmed, the least recently used dropped first. Its methods hold a lock: the
    corrected references are shared by the lanes of a search (``DesignCache.for_another_lane``)."""

    def __init__(self, size: int) -> None:
        super().__init__()
        self.size = size
        self._lock = threading.Lock()

    def hit(self, key: tuple) -> Any:
        """The entry under ``key`` (made the most recent), or None."""
        with self._lock:
            value = self.get(key)
            if value is not None:
                self.move_to_end(key)
        return value

    def put(self, key: tuple, value: Any) -> None:
        with self._lock:
            self[key] = value

    def trim(self, room: int = 0) -> None:
        """Drop the oldest entries until ``room`` more fit: called with 1 before a new entry is computed, so that the
        arrays it replaces are not held beside the new ones while they are built."""
        with self._lock:
            while len(self) > self.size - room:
                self.popitem(last=False)


class DesignCache:
    """The corrected inputs of the last few sets of input corrections, the inputs part-way through the
    corrections (``prefix``) and the last few design matrices (bounded).

    A hyper-parameter search over an additive effect, and every candidate tried on top of the same model,
    feed eq. 28 the same corrected inputs: they are corrected once. A search over an input correction that
    runs after the model's own (a later stage) starts from the inputs the model's corrections left, instead
    of re-running them (the TIA correction filters the whole series on every trial). A correction of the
    reference alone (``Effect.reference_only``: the channel delay, the TIA low-pass) leaves the design matrix
    as it was: a search over one reuses the matrix, and ``cross_validate`` its sums. Only for one recording.
    """

    def __init__(self, size: int = 1, prefixes: int = 2, matrices: int = 2, references: int = 4) -> None:
        self.inputs = _Recent(size)  # (the inputs after a set of corrections, those at the design's rows)
        self.prefixes = _Recent(prefixes)  # the inputs after the first corrections of a set (``prefix``)
        self.matrices = _Recent(matrices)  # (X (n, p) read-only, its finite rows (n,), effect blocks) (``build_design``)
        self.references = _Recent(references)  # (reference (n, 3), valid rows (n,)) (``_corrected_reference``)
        self._taken = _Recent(8)

    def for_another_lane(self) -> DesignCache:
        """An empty cache of the same sizes for another lane (``search_lanes``) that shares this one's corrected
        references: each depends on its corrections and the design's rows alone, and a search over a correction of
        the reference tries the same grid whatever lane it runs on."""
        other = DesignCache(self.inputs.size, self.prefixes.size, self.matrices.size, 0)
        other.references = self.references
        return other

    def prefix(self, names: tuple) -> tuple[int, Inputs | None]:
        """(number of corrections done, a private copy of the inputs after them) for the longest cached prefix
        of ``names`` (the (name, hyper-parameter) of each correction in stage order); (0, None) if none."""
        for n in range(len(names) - 1, 0, -1):
            hit = self.prefixes.hit(names[:n])
            if hit is not None:
                return n, _private(hit)
        return 0, None

    def take(self, a: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """``a[idx]`` (``idx``: the rows of the cache's designs, the same on every call), kept for a read-only ``a``
        (the recorded inputs, a correction a search repeats unchanged, ``DiagnosisData.recent``) while it is among
        the last few such arrays asked for: most trials of a search change one input array and share the rest."""
        if a.flags.writeable:
            return a[idx]
        key = memory_key(a)  # the same memory, read-only
        hit = self._taken.hit(key)
        if hit is None:
            hit = self._taken[key] = (a, a[idx])  # a is kept: its memory cannot be reused for another array
            self._taken.trim()
        return hit[1]


def _private(inp: Inputs) -> Inputs:
    """A copy of ``inp`` that the corrections can work on without changing ``inp``: they replace its arrays
    and change only ``valid`` in place, so the other arrays are shared (read-only, ``Inputs.of``)."""
    return replace(inp, valid=inp.valid.copy())


def build_design(data: DiagnosisData, spec: ModelSpec, cache: DesignCache | None = None,
                 sub: np.ndarray | None = None) -> Design:
    """Regressors of eq. 28 on the corrected inputs, then the extra columns of the additive effects.

    The input corrections (``Effect.transform``) run first in stage order, on the whole time series; every
    effect's columns are then computed from the fully corrected inputs. ``sub`` (sample indices): the design
    of those rows only (the corrections still see every sample; eq. 28's columns and the columns of a
    ``pointwise`` effect are computed on those rows alone). ``cache`` keeps the corrected inputs of a set of
    corrections, and the design matrix of a model but for its corrections of the reference alone, for the
    next design that has the same (the arrays it holds are never written).
    """
    ordered = sorted(spec.effects, key=lambda eh: eh[0].stage)
    corrections = [(eff, h) for eff, h in ordered if _transforms_inputs(eff)]
    if cache is None:
        inp = _corrected_inputs(data, corrections)
        part = inp if sub is None else inp.at(sub)
        gref, valid = part.gref, part.valid
    else:
        # The corrections of the reference alone (Effect.reference_only) are worked out apart, with the corrections
        # before them: no other correction reads the reference, and they read only what comes before them.
        inp, part = _corrected(data, [c for c in corrections if not c[0].reference_only], cache, sub)
        gref, valid = part.gref, part.valid
        last = max((i + 1 for i, (e, _) in enumerate(corrections) if e.reference_only), default=0)
        if last:
            gref, ref_valid = _corrected_reference(data, corrections[:last], cache, sub)
            valid = valid & ref_valid
    # eq. 28's columns and the extra ones depend on every effect but the corrections of the reference alone
    x_key = (spec.degree, spec.t_center_c, spec.t_scale_c, tuple((e.name, h) for e, h in ordered if not e.reference_only))
    x_hit = cache.matrices.hit(x_key) if cache is not None else None
    if x_hit is None:
        if cache is not None:
            cache.matrices.trim(room=1)
        x_hit = _design_matrix(data, spec, ordered, inp, part, sub)
        if cache is not None:
            x_hit[0].flags.writeable = False  # shared by the designs of every trial value of a search over the reference
            cache.matrices[x_key] = x_hit
    X, x_ok, blocks = x_hit
    return Design(X, gref, valid & x_ok & finite_rows(gref), blocks, n_params(spec.degree))


def fitted_output(data: DiagnosisData, spec: ModelSpec, coeff: np.ndarray, block: int = 100_000) -> np.ndarray:
    """``build_design(data, spec).X @ coeff`` (N, k): the model's output on every sample, its design made ``block``
    rows at a time (the same rows' values) after the input corrections of the whole series: the design of every
    sample (N x p, 92 MiB at 10^6 samples) was the diagnosis's peak of memory, held beside the search's caches."""
    ordered = sorted(spec.effects, key=lambda eh: eh[0].stage)
    inp = _corrected_inputs(data, [(eff, h) for eff, h in ordered if _transforms_inputs(eff)])
    n = len(data.t_s)
    out = np.empty((n, coeff.shape[1]))
    for lo in range(0, n, block):
        rows = np.arange(lo, min(lo + block, n))
        out[rows[0]:rows[-1] + 1] = _design_matrix(data, spec, ordered, inp, inp.at(rows), rows)[0] @ coeff
    return out


def _corrected_inputs(data: DiagnosisData, corrections: list[tuple[Effect, float | None]]) -> Inputs:
    """The recording's inputs after ``corrections`` (input corrections in stage order), on every sample, uncached."""
    inp = Inputs.of(data)
    for eff, h in corrections:
        eff.transform(data, inp, h)
    return inp


def _corrected(data: DiagnosisData, corrections: list[tuple[Effect, float | None]], cache: DesignCache,
               sub: np.ndarray | None) -> tuple[Inputs, Inputs]:
    """(the inputs after ``corrections``, those at the design's rows ``sub``), from ``cache`` when it has them."""
    names = tuple((eff.name, h) for eff, h in corrections)
    hit = cache.inputs.hit(names)
    if hit is not None:
        return hit
    cache.inputs.trim(room=1)
    done, inp = cache.prefix(names)
    if inp is None:
        inp = Inputs.of(data)
    for i in range(done, len(corrections)):
        if i == len(corrections) - 1 and i > done:
            cache.prefixes[names[:i]] = _private(inp)  # all but the last: what a search over the last one repeats
            cache.prefixes.trim()
        eff, h = corrections[i]
        eff.transform(data, inp, h)
    part = inp if sub is None else inp.at(sub, lambda a: cache.take(a, sub))  # the design's rows
    cache.inputs[names] = (inp, part)
    return inp, part


def _corrected_reference(data: DiagnosisData, corrections: list[tuple[Effect, float | None]], cache: DesignCache,
                         sub: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(the reference (n, 3) m/s^2 after ``corrections``, the rows (n,) they leave valid) at the design's rows
    ``sub``, from ``cache`` when it has them: a search over a correction of the reference tries the same grid
    for every model it is tried on top of."""
    names = tuple((eff.name, h) for eff, h in corrections)
    hit = cache.references.hit(names)
    if hit is None:
        inp = _corrected_inputs(data, corrections[:-1])
        last, h = corrections[-1]  # a correction of the reference alone (build_design): at the rows only
        hit = last.reference_at(data, inp, h, sub)
        for a in hit:
            a.flags.writeable = False
        cache.references.put(names, hit)
        cache.references.trim()
    return hit


def _design_matrix(data: DiagnosisData, spec: ModelSpec, ordered: list[tuple[Effect, float | None]], inp: Inputs,
                   part: Inputs, sub: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, dict[str, slice]]:
    """(X (n, p): eq. 28's columns then each effect's, its finite rows (n,), each effect's block of columns) of
    ``build_design``: ``inp`` the corrected inputs, ``part`` those at the design's rows."""
    n_base = n_params(spec.degree)
    extra, blocks, p = [], {}, n_base
    for eff, h in ordered:
        c = eff.columns(data, part if eff.pointwise else inp, h)
        if c is not None:
            c = c if eff.pointwise or sub is None else c[sub]
            blocks[eff.name] = slice(p, p + c.shape[1])
            extra.append(c)
            p += c.shape[1]
    X = np.empty((p, len(part.valid))).T  # column-major, filled in place: no concatenation copy
    tau = (part.temp_c - spec.t_center_c) / spec.t_scale_c
    design_matrix(part.psi, tau, spec.degree, out=X[:, :n_base])
    ok = finite_rows(X[:, :n_base])
    for c, sl in zip(extra, blocks.values(), strict=True):
        X[:, sl] = c
        ok &= finite_rows(c)
    return X, ok, blocks


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
            return rows, self.heldout[rows]
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
                out[rows] = res
            self._heldout = out  # assigned once whole: lanes that share the result read it whole or work it out too
            self._release()
        return self._heldout

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


def _fold_part(idx: np.ndarray, lo: int, hi: int, of: np.ndarray) -> np.ndarray:
    """``of`` at the rows ``idx[lo:hi]`` (``cross_validate``'s rows in fold order): a view when they are consecutive
    (a design in fold order), else a copy."""
    rows = idx[lo:hi]
    if hi > lo and rows[-1] - rows[0] == hi - lo - 1:
        return of[rows[0]:rows[-1] + 1]
    return of[rows]


# searched samples from which the searches run side by side by default (``search_lanes``): bench_calibration --lanes 1/2
# at 3e4 samples (2.2e4 searched): 2.5 / 2.3 s, at 1e4: 0.6 / 0.7 s (threads cost more than they save on small designs)
LANE_SEARCH_ROWS = 20_000
SEARCH_STRIDE = 4  # a hyper-parameter search visits every 4th grid value first, then walks from the best (search_batches)


def search_batches(n: int, seen: dict[int, tuple[bool | None, float]], best_at: np.ndarray) -> Iterator[list[int]]:
    """Indices of a grid of ``n`` hyper-parameter values for a search to visit, chosen from what it has found so far,
    a batch at a time (the values of a batch do not depend on each other's results: ``Evaluator.cv_each``).

    The caller updates, after each index of a batch, ``seen`` (index -> (plausible, mean training RSS over the folds); plausible
    is None for a value that does not identify the model) and ``best_at`` ((K,) the index of the plausible value each
    training fold fits best, ``n`` while none). First every ``SEARCH_STRIDE``-th value and the last one; then, batch
    by batch, the nearest plausible value not yet visited on each side of each fold's best and of the best mean
    (values not plausible or not identified are stepped over), until those are all visited. With no plausible value
    among the first ones, every value is visited (the search then falls back on the implausible ones, which need the
    whole grid). Each fold's best value, the best mean and its plausible neighbours are then those of a visit of
    every value whenever each training RSS, over the plausible values in grid order, falls and then rises (one
    minimum; ``test_the_search_walk_finds_what_visiting_every_value_finds``) with about half the visits on the
    diagnosis's grids (a trial is a design and its cross-validation)."""
    yield list(range(0, n, SEARCH_STRIDE)) + ([n - 1] if (n - 1) % SEARCH_STRIDE else [])
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
    train_rss = np.zeros(K)
    A_folds = np.empty((K, p, 3))
    for f in range(K):
        Xt, Gt = XtX - xtx[f], XtG - xtg[f]
        A = A_folds[f] = solve_normal_equations(Xt, Gt)[0]
        rss = GtG - gtg[f] - 2 * np.einsum("pi,pi->i", A, Gt) + np.einsum("pi,pq,qi->i", A, Xt, A)
        train_rss[f] = float(np.sum(rss * weights))
    A_full = solve_normal_equations(XtX, XtG)[0]
    return CvResult(train_rss, A_full, sums, X, G, start, A_folds)


@dataclass
class RssSums:
    """The fitted rows of one design matrix and their X^T X (``weighted_rss``), kept while a search changes the
    reference alone (the same matrix, ``DesignCache``)."""

    X: weakref.ref  # the design matrix (N, p), compared by identity (not kept alive)
    rows: np.ndarray  # (N,) the fitted rows
    Xr: np.ndarray  # (n, p) the matrix at those rows
    XtX: np.ndarray  # (p, p)


def weighted_rss(des: Design, rows: np.ndarray, weights: np.ndarray,
                 sums: RssSums | None = None) -> tuple[float, RssSums]:
    """Weighted in-sample RSS of the least-squares fit of ``des`` on ``rows`` (noise ``weights`` (3,) per axis),
    and the sums it used (``sums``: an earlier call's, used again when they are of the same matrix and rows)."""
    r = rows & des.valid
    if sums is None or sums.X() is not des.X or not np.array_equal(sums.rows, r):
        Xr = des.X[r]  # one copy, not three
        sums = RssSums(weakref.ref(des.X), r, Xr, Xr.T @ Xr)
    X, G = sums.Xr, des.G[r]
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
        W = np.concatenate([X[r], Z[r], G[r]], axis=1)
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
    return out

# ============================================================================ noise floor, settling, degree
# Settling window after a table move, from the measuring chain's physics: every TIA is a first-order
# low-pass (paper Table 1: 1 / 1.7 / 1.3 / 1.3 Hz for ref / x / y / z, time constants 0.09-0.16 s), so a
# transient left at the end of a move decays as A exp(-t/tau). The floor leaves out the first sample of
# every visit and every sample before the measured transient has fallen below a tenth of the noise
# (t < tau ln(10 A / sigma): under 0.5 % on the floor in quadrature). Without a measurable transient only
# the first sample goes. The window never exceeds 10 x the slowest TIA time constant (1.6 s): a slower
# "transient" is not the chain's and is reported, not hidden.
SETTLE_NOISE_FRACTION = 0.1
MAX_SETTLE_S = float(10.0 * np.max(TIA_TAU_S))


def visit_index(g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``np.unique(g, return_inverse=True)`` and, when ``g`` never decreases (visits numbered in time order,
    ``visit_ids``, at rows in time order), where each value's samples start (else None): then found from where ``g``
    changes instead of by sorting it, the same arrays in a tenth of the time at 10^6 samples."""
    if g.size and bool(np.all(g[1:] >= g[:-1])):
        change = np.empty(g.size, bool)
        change[0] = True
        np.not_equal(g[1:], g[:-1], out=change[1:])
        return g[change], np.cumsum(change) - 1, np.flatnonzero(change)
    ug, inv = np.unique(g, return_inverse=True)
    return ug, inv, None


def per_visit(extreme: np.ufunc, t: np.ndarray, inv: np.ndarray, starts: np.ndarray | None, n: int) -> np.ndarray:
    """``extreme`` (``np.minimum`` or ``np.maximum``) of ``t`` over each of the ``n`` visits (``visit_index``'s
    ``inv`` and ``starts``): over each visit's side-by-side samples when ``starts`` is known, else gathered by index."""
    if starts is not None:
        return extreme.reduceat(t, starts)
    out = np.full(n, np.inf if extreme is np.minimum else -np.inf)
    extreme.at(out, inv, t)
    return out


def settled_mask(t_s: np.ndarray, groups: np.ndarray, rows: np.ndarray, settle_s: float = 0.0,
                 end_s: float | None = None) -> np.ndarray:
    """Settled samples (N,) among ``rows``: the first sample of every visit and every sample less than
    ``settle_s`` (s, board time) after it are dropped (the settling transient after a table move).
    At least the first sample of a visit is always dropped, whatever the sample rate. ``end_s`` (s): the same at
    the other end, for a visit whose end is disturbed (``SettlingTransient.end_detected``): the last sample and
    every sample less than ``end_s`` before it are dropped; None (the default): the end is kept."""
    idx = np.flatnonzero(rows)
    out = np.zeros(len(t_s), bool)
    if idx.size == 0:
        return out
    g = groups[idx]
    t = t_s[idx]
    ug, inv, starts = visit_index(g)
    age = t - per_visit(np.minimum, t, inv, starts, len(ug))[inv]
    first = np.zeros(len(idx), bool)  # idx is time-ordered within a run
    first[np.unique(inv, return_index=True)[1] if starts is None else starts] = True
    keep = (age >= settle_s) & ~first
    if end_s is not None:
        last = np.zeros(len(idx), bool)
        last[len(idx) - 1 - np.unique(inv[::-1], return_index=True)[1] if starts is None
             else np.r_[starts[1:], len(idx)] - 1] = True
        keep &= (per_visit(np.maximum, t, inv, starts, len(ug))[inv] - t >= end_s) & ~last
    out[idx] = keep
    return out


# Noise floor of correlated noise. The noise of this sensor is white noise through the first-order TIA
# low-passes (time constants up to 0.16 s: 16 samples at 100 Hz, 64 at 400 Hz) plus the ADC's white rounding. Removing
# a visit's mean and line removes about two integrated correlation times' worth of it, not two samples' worth: the
# expected sum of squares is sigma^2 tr((I - H) R) (H the hat matrix of the mean and line over the visit, R the noise's
# correlation matrix), about sigma^2 (n - 2 kappa) with kappa = 1 + 2 sum_l rho_l samples (~70 at 400 Hz). Divided by
# n - 2, the floor of 1 s visits came out 13-19 % low (clean simulated recordings, 100 and 400 Hz), and the held-out
# error stood 1.15-1.26x above it: a clean recording was judged to hold an unexplained residual. So the pooled lag
# products of the detrended residual, lags 0..K, are fitted with their exact expectation (``detrended_lag_matrix``:
# E[sum_i d_i d_{i+k}] = sum_m A_km gamma_m) under white noise plus a first-order process, gamma_l = a delta_l +
# b exp(-l / tau), which is the chain (as ``stillness_monitor`` models it, plus the white part). The floor is
# sqrt(a + b); the variance of a visit mean that the chi^2 of ``residual_structure`` needs follows from the same fit
# (``VisitNoise``), so floor and test agree on what the noise is. A free gamma_0..gamma_K solved from the same equations
# is unbiased but, from 1 s visits at 400 Hz, so uncertain at long lags (they make the variance of a visit mean) that it
# came out negative on some seeds (integrated correlation < 0, floor 0.82x the truth); it is used only where the model
# has too few lags (``MODEL_MIN_LAGS``). K covers NOISE_CORR_S, five of the slowest TIA time constants (a first-order
# correlation is e^-5 = 0.7 % there), and at most half the median visit. Slower noise (bias instability, drift) is
# removed with the line within a visit, and is not in the floor.
NOISE_CORR_S = 5.0 * float(np.max(TIA_TAU_S))


@dataclass
class VisitNoise:
    """Noise floor of a residual (``within_visit_noise``): what no static model can remove, and how it correlates."""

    sigma: np.ndarray  # (3,) per-sample standard deviation, m/s^2 (table frame)
    acf: np.ndarray  # (3, L + 1) normalised autocorrelation at lags 0..L samples (acf[:, 0] = 1), zero beyond L
    # (3,) degrees of freedom of the variance of a visit mean as an estimate (inf: known exactly)
    mean_dof: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    # visits left out of the floor, their scatter far beyond the others' (``noisy_visits``): label, (3,) scatter /
    # floor, (3,) p-value of the check
    flagged: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)
    n_checked: int = 0  # visits the check ran over (its Bonferroni count)

    def mean_variance(self, n: np.ndarray) -> np.ndarray:
        """Variance (len(n), 3) in (m/s^2)^2 of the mean of ``n`` (V,) consecutive samples of the noise:
        sigma^2 (n + 2 sum_l (n - l) rho_l) / n^2, kept within [sigma^2 / n^2, sigma^2] (estimated rho may be noisy)."""
        cnt = np.asarray(n, dtype=float)[:, None]
        lag = np.arange(1, self.acf.shape[1], dtype=float)
        pairs = np.clip(cnt - lag[None, :], 0.0, None)  # (V, L) pairs of samples at each lag
        var = self.sigma**2 * (cnt + 2.0 * pairs @ self.acf[:, 1:].T) / cnt**2
        return np.clip(var, self.sigma**2 / cnt**2, self.sigma**2)

    @property
    def correlation_samples(self) -> np.ndarray:
        """(3,) integrated correlation time 1 + 2 sum_l rho_l, samples (1 for white noise): a visit of n samples
        holds about n / this many independent ones."""
        return 1.0 + 2.0 * self.acf[:, 1:].sum(axis=1)


def _range_products(qa: tuple[float, float], qb: tuple[float, float], n: int, lo: np.ndarray, hi: np.ndarray,
                    alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """sum_{i=lo}^{hi} q_a[i + alpha] q_b[i + beta] (0 for an empty range) for q(i) = A + B (i - (n - 1) / 2), ``qa``
    and ``qb`` their (A, B); arrays broadcast. Centred on the range's mean, so that nothing large cancels."""
    (aa, ba), (ab, bb) = qa, qb
    cnt = np.maximum(hi - lo + 1.0, 0.0)
    mu = (lo + hi) / 2.0 - (n - 1) / 2.0  # mean of i - (n - 1) / 2 over the range
    spread = (cnt**2 - 1.0) / 12.0  # variance of consecutive integers
    a0, b0 = aa + ba * alpha, ab + bb * beta
    return cnt * (a0 * b0 + (a0 * bb + b0 * ba) * mu + ba * bb * (mu * mu + spread))


def detrended_lag_matrix(n: int, lags: int, model_lags: int, line: bool = True) -> np.ndarray:
    """A (lags + 1, model_lags + 1): E[sum_i d_i d_{i+k}] = sum_m A[k, m] gamma_m for d the residual of
    ``n`` consecutive samples of a stationary process (autocovariance gamma_m at lag m samples, zero beyond
    ``model_lags``) after removing their least-squares mean and, with ``line`` (and n >= 2), a straight line in the
    sample index.

    d = (I - P) x with P = sum_a q_a q_a' (q_a orthonormal: the constant, the centred index), so
    E[d d'] = (I - P) S (I - P) with S = sum_m gamma_m T_m (T_0 = I, T_m ones where |i - j| = m). Expanded, every
    entry is a sum over an index range of products of two linear functions of the index (``_range_products``), so A
    is exact and costs O(lags model_lags), not O(n lags model_lags)."""
    k = np.arange(lags + 1, dtype=float)[:, None]
    m = np.arange(model_lags + 1, dtype=float)[None, :]
    basis = [(1.0 / math.sqrt(n), 0.0)]
    if line and n >= 2:
        basis.append((0.0, 1.0 / math.sqrt(n * (n * n - 1.0) / 12.0)))
    zero = np.zeros(1)

    def cross(a: tuple[float, float], b: tuple[float, float], lag: np.ndarray) -> np.ndarray:
        """sum_{i=0}^{n-1-lag} q_a[i] q_b[i + lag]."""
        return _range_products(a, b, n, zero, n - 1.0 - lag, zero, lag)

    out = np.where((k == m) & (k <= n - 1), n - k, 0.0)  # sum_i (S)_{i, i+k}
    for q in basis:  # - sum_i (P S + S P)_{i, i+k}: (T_m q)[j] = q[j - m] (j >= m) + q[j + m] (j + m <= n - 1)
        ps = (_range_products(q, q, n, np.maximum(0.0, m - k), n - 1.0 - k, zero, k - m)
              + _range_products(q, q, n, zero, n - 1.0 - k - m, zero, k + m))
        sp = (_range_products(q, q, n, m, n - 1.0 - k, -m, k)
              + _range_products(q, q, n, zero, np.minimum(n - 1.0 - k, n - 1.0 - m), m, k))
        out = out - np.where(m == 0, 2.0 * cross(q, q, k), ps + sp)
    for ia, qa in enumerate(basis):  # + sum_i (P S P)_{i, i+k} = sum_ab (q_a' S q_b) sum_i q_a[i] q_b[i + k]
        for ib, qb in enumerate(basis):
            g = np.where(m == 0, float(ia == ib), cross(qa, qb, m) + cross(qb, qa, m))
            out = out + g * cross(qa, qb, k)
    return out


def _noise_lags(t_s: np.ndarray | None, groups: np.ndarray, r: np.ndarray, cnt: np.ndarray) -> int:
    """Lags (samples) of the lag products the floor is fitted to: NOISE_CORR_S at the median sample interval within
    visits (s), at most half the median visit; 0 (white noise) without times."""
    if t_s is None or cnt.size == 0:
        return 0
    t, g = t_s[r], groups[r]
    step = np.diff(t)[(g[1:] == g[:-1]) & (np.diff(t) > 0)]
    if step.size == 0:
        return 0
    return int(max(min(math.ceil(NOISE_CORR_S / float(np.median(step))), int(np.median(cnt)) // 2), 0))


MIN_MEAN_DOF = 2.0  # least degrees of freedom of the floor's mean variance in the F test (F(df, nu) tails ~ x^(-nu/2))
FLOOR_VISIT_ALPHA = 0.01  # level of the check for a visit noisier than the others (Bonferroni over visits and axes)
FLOOR_VISIT_RATIO = 2.0  # and its variance at least this many times the others' (scatter 1.41x): one that matters
MODEL_MIN_LAGS = 3  # with fewer lag products than the white + first-order model's 3 parameters: a free autocovariance
JACKKNIFE_GROUPS = 20  # groups of visits left out in turn to measure how well the variance of a visit mean is known
TAU_GRID = 48  # correlation times tried by the fit (log-spaced)


@dataclass
class _LagMoments:
    """The lag products of the detrended visits and the expectations they are fitted to (``within_visit_noise``)."""

    prods: np.ndarray  # (V, K + 1, 3) lag-k products of every visit
    kind: np.ndarray  # (V,) index of the visit's (length, line) among ``expect``'s
    expect: np.ndarray  # (kinds, T, K + 1, 2) expected lag products per unit white / first-order variance
    tau: np.ndarray  # (T,) correlation times, samples
    model_lags: int  # M: lags of the model autocovariance

    def fit(self, visits: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(a, b, tau) per axis (3,) of the autocovariance a delta_l + b exp(-l / tau) (a, b >= 0, tau in samples)
        that fits the lag products of ``visits`` best (least squares over the lags, for each tau of the grid)."""
        w = np.bincount(self.kind[visits], minlength=self.expect.shape[0]).astype(float)
        D = np.tensordot(w, self.expect, axes=1)  # (T, K + 1, 2)
        c = self.prods[visits].sum(axis=0)  # (K + 1, 3)
        G = np.einsum("tki,tkj->tij", D, D)
        h = np.einsum("tki,kj->tij", D, c)  # (T, 2, 3)
        det = G[:, 0, 0] * G[:, 1, 1] - G[:, 0, 1] ** 2
        both = np.stack([G[:, 1, 1, None] * h[:, 0] - G[:, 0, 1, None] * h[:, 1],
                         G[:, 0, 0, None] * h[:, 1] - G[:, 0, 1, None] * h[:, 0]], axis=1)
        both /= np.where(np.abs(det) > 1e-300, det, np.inf)[:, None, None]
        # with a negative part, the better of the white part alone and the first-order part alone
        alone = np.clip(h / np.maximum(np.diagonal(G, axis1=1, axis2=2), 1e-300)[:, :, None], 0.0, None)
        cands = np.zeros((3, *both.shape))  # (white alone, first-order alone, both; T, 2, 3)
        cands[0, :, 0], cands[1, :, 1], cands[2] = alone[:, 0], alone[:, 1], both
        # residual sum of squares less the constant c'c: coef' G coef - 2 coef' h
        score = np.einsum("ctik,tij,ctjk->ctk", cands, G, cands) - 2.0 * np.einsum("ctik,tik->ctk", cands, h)
        score[2][np.any(both < 0.0, axis=1)] = np.inf
        ci, ti = np.unravel_index(np.argmin(score.reshape(-1, 3), axis=0), score.shape[:2])
        axis = np.arange(3)
        return cands[ci, ti, 0, axis], cands[ci, ti, 1, axis], self.tau[ti]

    def noise(self, visits: np.ndarray) -> VisitNoise | None:
        a, b, tau = self.fit(visits)
        var = a + b
        if not np.all(var > 0):
            return None
        lag = np.arange(self.model_lags + 1)
        acf = (a[:, None] * (lag == 0) + b[:, None] * np.exp(-lag[None, :] / tau[:, None])) / var[:, None]
        return VisitNoise(np.sqrt(var), acf)


def _lag_products(dev: np.ndarray, n_v: np.ndarray, lags: int, batch: int = 256) -> np.ndarray:
    """(V, K + 1, 3): sum_i d_i d_{i+k} of every visit for k = 0..K (``lags``), ``dev`` (N, 3) the visits one after the
    other (``n_v`` (V,) samples each). By FFT, zero-padded against wrap-around up to lag K; the visits of one length
    are transformed together, ``batch`` at a time (the same transform of each: its values are those of one at a time)."""
    bounds = np.r_[0, np.cumsum(n_v)]
    prods = np.zeros((len(n_v), lags + 1, 3))
    for n in np.unique(n_v):
        size = scipy_fft.next_fast_len(int(n) + lags + 1, real=True)
        keep = min(lags + 1, int(n))
        same = np.flatnonzero(n_v == n)
        for lo in range(0, len(same), batch):
            vs = same[lo:lo + batch]
            x = take_rows(dev, (bounds[vs][:, None] + np.arange(n)[None, :]).ravel()).reshape(len(vs), int(n), 3)
            spec = scipy_fft.rfft(x, size, axis=1)
            prods[vs, :keep] = scipy_fft.irfft(spec.real**2 + spec.imag**2, size, axis=1)[:, :keep]
    return prods


def within_visit_noise(res: np.ndarray, groups: np.ndarray, rows: np.ndarray, t_s: np.ndarray | None = None,
                       jackknife: bool = True) -> VisitNoise:
    """The noise floor (3,) m/s^2 of a residual (N, 3) m/s^2, table frame, and its autocorrelation (see above).

    ``groups`` are visits (``DiagnosisData.group``), ``rows`` the samples that count (settled ones: see ``settled_mask``).
    The mean of every visit is removed and, with ``t_s`` (s), a straight line in time (so that slow changes within
    a visit, temperature ramps, drift, do not count as noise). What is left is the noise seen through I - H; its
    pooled lag products over 0..K lags (``_noise_lags``) are fitted with their exact expectation
    (``detrended_lag_matrix``) under white noise plus a first-order process, a delta_l + b exp(-l / tau): the chain's
    white noise through the TIA low-pass plus the ADC's white rounding and read noise (as ``stillness_monitor``). The
    floor is sqrt(a + b). A free autocovariance fitted the same way is unbiased but, from short visits, far too
    uncertain at long lags (they matter for the variance of a visit mean and the floor); with fewer than
    ``MODEL_MIN_LAGS`` lags it is what is used (white noise with none: the pooled standard deviation over the
    degrees of freedom left). Lags count the samples of a visit in ``rows`` in order (evenly spaced; a lost sample
    shifts the lags across it by one).

    How well the variance of a visit mean is known (``VisitNoise.mean_dof``) is measured by a grouped jackknife over
    the visits (``JACKKNIFE_GROUPS``): short visits tell little about the correlation at long lags, on which it rests.
    ``jackknife`` False: not measured (``mean_dof`` stays inf), for a caller that needs the floor alone.
    """
    r = rows & finite_rows(res)
    if not r.any():
        return VisitNoise(np.full(3, np.nan), np.ones((3, 1)))
    idx = np.flatnonzero(r)
    ug, inv, starts = visit_index(groups[idx])
    cnt = np.bincount(inv).astype(float)
    dev = take_rows(res, idx)
    dev -= take_rows(np.stack([np.bincount(inv, weights=dev[:, j]) / cnt for j in range(3)], axis=1), inv)
    stt = np.zeros(len(ug))  # sum of squared centred times of each visit (s^2), 0 where no line is fitted
    if t_s is not None:
        # times from each visit's first sample: the line does not depend on the time origin (a CSV with seconds since
        # 1970, ~1.7e9 s, gives what the same run from 0 s gives); no line where a visit's samples share one time
        t = t_s[idx]
        t_first = per_visit(np.minimum, t, inv, starts, len(ug))
        t_rel = t - t_first[inv]
        tmean_rel = np.bincount(inv, weights=t_rel) / cnt
        tc = t_rel - tmean_rel[inv]
        stt = np.bincount(inv, weights=tc * tc)
        ok = stt > 1e-12 * np.maximum(tmean_rel**2, 1.0)
        slope = np.zeros((len(ug), 3))
        for j in range(3):
            slope[ok, j] = np.bincount(inv, weights=tc * dev[:, j])[ok] / stt[ok]
        stt = np.where(ok, stt, 0.0)
        dev -= take_rows(slope, inv) * (t - (t_first + tmean_rel)[inv])[:, None]
    lags = _noise_lags(t_s, groups, r, cnt)
    n_v = cnt.astype(int)
    if starts is None:
        dev = dev[np.argsort(inv, kind="stable")]  # by visit, in time order within a visit
    prods = _lag_products(dev, n_v, lags)
    kinds, kind = np.unique(np.column_stack([n_v, stt > 0]), axis=0, return_inverse=True)
    kind = kind.ravel()
    if lags >= MODEL_MIN_LAGS:
        tau = np.geomspace(0.25, lags / 2.0, TAU_GRID)
        model_lags = int(min(math.ceil(10.0 * tau[-1]), n_v.max() - 1))
        lag = np.arange(model_lags + 1)
        basis = np.stack([np.broadcast_to((lag == 0).astype(float)[:, None], (len(lag), len(tau))),
                          np.exp(-lag[:, None] / tau[None, :])], axis=-1)  # (M + 1, T, 2)
        expect = np.stack([np.einsum("km,mtj->tkj", detrended_lag_matrix(int(n), lags, model_lags, bool(h)), basis)
                           for n, h in kinds])
        moments = _LagMoments(prods, kind, expect, tau, model_lags)
        estimate: Callable[[np.ndarray], VisitNoise | None] = moments.noise
    else:
        A_k = np.array([detrended_lag_matrix(int(n), lags, lags, bool(h)) for n, h in kinds])

        def estimate(visits: np.ndarray) -> VisitNoise | None:
            A = np.tensordot(np.bincount(kind[visits], minlength=len(kinds)).astype(float), A_k, axes=1)
            try:
                gamma = np.linalg.solve(A, prods[visits].sum(axis=0))
            except np.linalg.LinAlgError:
                return None
            if not (np.all(np.isfinite(gamma)) and np.all(gamma[0] > 0)):
                return None
            return VisitNoise(np.sqrt(gamma[0]), (gamma / gamma[0]).T)

    every = np.arange(len(n_v))
    noise = estimate(every)
    if noise is None:
        return VisitNoise(np.full(3, np.nan), np.ones((3, 1)))
    flagged = np.zeros(len(n_v), bool)
    for _ in range(3):  # the autocorrelation the check uses is refitted without the visits it flags
        ratio, p = noisy_visits(prods[:, 0], n_v, stt > 0, noise.acf)
        now = np.any((p < FLOOR_VISIT_ALPHA / (3 * len(n_v))) & (ratio > FLOOR_VISIT_RATIO), axis=1)
        if np.array_equal(now, flagged) or now.all():
            break
        flagged = now
        refit = estimate(every[~flagged])
        if refit is None:
            flagged[:] = False
            break
        noise = refit
    every = every[~flagged]
    # grouped jackknife of log(variance of the mean of a median-length visit): its spread gives the degrees of freedom
    # of that variance as an estimate, nu = 2 / var(log), as for a scaled chi^2(nu) / nu
    n_groups = min(JACKKNIFE_GROUPS, len(every))
    if jackknife and n_groups >= 3:
        ref = np.array([np.median(cnt)])
        member = np.arange(len(every)) % n_groups
        parts = [estimate(every[member != gi]) for gi in range(n_groups)]
        logs = np.array([np.log(part.mean_variance(ref)[0]) for part in parts if part is not None])
        if len(logs) >= 3:  # a group without a fit of its own (too few visits left) does not count
            spread = (len(logs) - 1) / len(logs) * np.sum((logs - logs.mean(axis=0)) ** 2, axis=0)
            noise.mean_dof = 2.0 / np.maximum(spread, 1e-12)
    noise.flagged = [(int(ug[v]), np.sqrt(ratio[v]), p[v]) for v in np.flatnonzero(flagged)]
    noise.n_checked = len(n_v)
    return noise


def noisy_visits(lag0: np.ndarray, n: np.ndarray, line: np.ndarray, acf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Is a visit's scatter far beyond the others'? For every visit (``lag0`` (V, 3) its sum of squared detrended
    residuals, ``n`` (V,) samples, ``line`` (V,) a line in time removed too) and axis: the ratio (V, 3) of its
    variance to the robust centre of the visits' variances, and the p-value (V, 3) of that ratio under the noise.

    A visit's variance is its sum of squares over E = the sum expected per unit variance after the detrending under
    the floor's autocorrelation ``acf`` (3, L + 1) (``detrended_lag_matrix``); the centre is their median (over the
    median of chi^2(nu) / nu, so that it is unbiased for a visit of median length). Under the noise the sum is
    about sigma^2 chi^2(nu) / nu E with the effective degrees of freedom of a variance from correlated samples,
    nu = E / (1 + 2 sum_l rho_l^2) (Bartlett); one-sided: a quieter visit does not dominate the pooled floor."""
    lag = acf.shape[1] - 1
    kinds, kind = np.unique(np.column_stack([n, line]), axis=0, return_inverse=True)
    expect = np.array([detrended_lag_matrix(int(k), 0, lag, bool(h))[0] @ acf.T for k, h in kinds])  # (kinds, 3)
    E = np.maximum(expect[kind.ravel()], 1e-12)
    nu = np.maximum(E / (1.0 + 2.0 * np.sum(acf[:, 1:] ** 2, axis=1)), 1.0)
    var = lag0 / E
    centre = np.median(var, axis=0) / (stats.chi2.median(np.median(nu, axis=0)) / np.median(nu, axis=0))
    ratio = var / np.maximum(centre, 1e-300)
    return ratio, stats.chi2.sf(nu * ratio, nu)


@dataclass
class SettlingTransient:
    """Settling transient after the table stops, and disturbance before it moves on, measured on the declared
    model's residual (m/s^2).

    The k-th sample after the start of a visit is compared with its mirror about a window of the visit's samples:
    the window [K, n - 2K) for the start (mirror: the (K + k)-th sample before the end), [2K, n - K) for the end
    (mirror: the (K + k)-th after the start), each sample referred to the window's mean. A sample and its mirror lie
    at the same distance from the window, so noise of any colour and a linear drift cancel, and the mirror is clear
    of both ends, so a start and an end disturbed alike do not cancel. The excess power, averaged over visits, is
    modelled as A^2 exp(-2 age/tau) (first-order chain), one tau for all axes, at the start (the transient after a
    table move) and, with the time counted back from the last sample, at the end (samples taken while the table
    already moves to the next pose: its reading changes late, or the chain is delayed against the reference). Each
    is detected at 3 standard errors on some axis (a disturbance of either sign adds power).
    """

    settle_s: float  # samples within this time (s) of a visit's first sample are not in the floor
    n_visits: int  # visits long enough to measure it
    n_dropped: int  # static samples left out of the floor (both ends)
    age_s: np.ndarray  # (K,) median time since the visit's first sample, s
    excess_rms: np.ndarray  # (K, 3) signed sqrt of the excess power (start over its mirror), m/s^2
    amplitude_mps2: np.ndarray  # (3,) A per axis at the first sample, m/s^2 (0 where none)
    tau_s: float  # time constant, s (an upper bound if not resolved; NaN if not detected)
    tau_resolved: bool  # the decay shows in at least two sample positions
    detected: bool  # the excess at the first sample is > 3 standard errors on some axis
    residual_after_settle_mps2: np.ndarray  # (3,) A exp(-settle_s/tau): what may still reach the floor
    # the end of a visit, as above with the sign of the excess reversed and the time counted back from the last sample
    end_age_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (K,) median time before the last sample, s
    end_excess_rms: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (K, 3) m/s^2
    end_amplitude_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) at the last sample, m/s^2
    end_tau_s: float = np.nan
    end_tau_resolved: bool = False
    end_detected: bool = False  # the excess of the last sample over the first is > 3 standard errors on some axis
    end_settle_s: float | None = None  # samples within this time (s) of a visit's last sample are not in the floor
    end_n_dropped: int = 0  # of n_dropped, those left out at the end of a visit
    end_residual_after_settle_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def _end_first(self) -> np.ndarray:
        return self.end_excess_rms[0] if len(self.end_excess_rms) else np.zeros(3)

    @staticmethod
    def _decay(tau_s: float, resolved: bool, when: str) -> str:
        return (f"time constant {tau_s:.3g} s" if resolved else
                f"gone by the {when} sample (time constant <= {tau_s:.3g} s, not resolved by the sample rate)")

    def end_summary(self) -> str:
        """The end-of-visit disturbance in one sentence (empty without one)."""
        if not self.end_detected:
            return ""
        return f"{self._end_sentence()}; {self.end_n_dropped} samples at the ends of visits are left out of the noise floor"

    def _end_sentence(self) -> str:
        return (f"ends of visits disturbed: the table moves before its reading changes, or the chain is delayed against "
                f"the reference: amplitude {_fmt3(self.end_amplitude_mps2)} m/s^2 (x/y/z, at the last sample of a visit, "
                f"above the noise), {self._decay(self.end_tau_s, self.end_tau_resolved, 'previous')} before the end")

    def summary(self) -> str:
        cut = ["the first of each visit" + (f" and those within {self.settle_s:.3g} s of it" if self.settle_s > 0 else "")]
        if self.end_settle_s is not None:
            cut.append("the last of each visit" + (f" and those within {self.end_settle_s:.3g} s of it"
                                                   if self.end_settle_s > 0 else ""))
        drop = f"{self.n_dropped} samples ({', '.join(cut)}) are left out of the noise floor"
        if not self.detected:
            first = self.excess_rms[0] if len(self.excess_rms) else np.zeros(3)
            where = "first sample" if self.end_detected else "first or the last sample"
            out = (f"no settling transient above the noise at the {where} of a visit (excess "
                   f"{_fmt3(first)} m/s^2" + ("" if self.end_detected else
                                             f" at the first, {_fmt3(self._end_first())} m/s^2 at the last")
                   + f", {self.n_visits} visits)")
        else:
            out = (f"settling transient after a table move: amplitude {_fmt3(self.amplitude_mps2)} m/s^2 (x/y/z, at the "
                   f"first sample of a visit, above the noise), {self._decay(self.tau_s, self.tau_resolved, 'next')}, "
                   f"{self.n_visits} visits")
        if self.end_detected:
            out += "; " + self._end_sentence()
        return f"{out}; {drop}"


def _decay_fit(P: np.ndarray, SE: np.ndarray, age: np.ndarray, dt: float) -> tuple[np.ndarray, float, bool, bool]:
    """A first-order decay A^2 exp(-2 age/tau) fitted to an excess power ``P`` (K, 3) (m/s^2)^2 with standard errors
    ``SE`` at ages ``age`` (K,) s: (A (3,) m/s^2, tau s, tau resolved, detected). Detected: P > 3 SE at age 0 on
    some axis; resolved: also at the next position (else tau is bounded by the detection limit there)."""
    signif = P > 3 * SE
    detected = bool(np.any(signif[0]))
    amp, tau, resolved = np.zeros(3), np.nan, False
    if not detected:
        return amp, tau, resolved, detected
    resolved = bool(len(P) > 1 and np.any(signif[1]))
    if resolved:
        best = (np.inf, np.nan, np.zeros(3))
        for tau_try in np.geomspace(dt / 20, max(age[-1], dt) * 5, 300):
            f = np.exp(-2 * age / tau_try)
            w = 1.0 / SE**2
            a2 = np.clip(np.sum(w * f[:, None] * P, axis=0) / np.sum(w * f[:, None] ** 2, axis=0), 0, None)
            sse = float(np.sum(w * (P - f[:, None] * a2[None, :]) ** 2))
            if sse < best[0]:
                best = (sse, tau_try, a2)
        tau, amp = float(best[1]), np.sqrt(best[2])
    else:
        amp = np.sqrt(np.clip(P[0], 0, None))
        if len(P) > 1:  # below the detection limit one sample later: bound tau
            ratio = float(np.max(np.clip(P[0], 0, None) / (3 * SE[1])))
            tau = float((age[1] - age[0]) / max(0.5 * np.log(max(ratio, 1.0 + 1e-9)), 1e-9))
        else:
            tau = dt
    return amp, tau, resolved, detected


def settling_transient(res: np.ndarray, t_s: np.ndarray, groups: np.ndarray, rows: np.ndarray,
                       max_window_s: float = MAX_SETTLE_S) -> SettlingTransient:
    """Measure the settling transient and the end-of-visit disturbance (see ``SettlingTransient``) from a residual
    (N, 3) m/s^2.

    ``rows``: static samples of the visits (time-ordered, visits contiguous). Sample positions
    k = 0 .. K-1 with K covering ``max_window_s`` (s) plus one sample, at most a third of the median visit;
    visits shorter than 2 K + 1 samples (no middle sample left to refer to) are not used. The k-th sample from
    the start and the k-th from the end lie at the same distance from the middle whatever its length, so a
    visit one sample shorter than 3 K counts as well (it was left out: with jittered visit lengths, every
    visit shorter than the median). The start is fitted to the positive excess, the end to the negative one
    (``_decay_fit``). ``settle_s``, ``end_settle_s`` and the counts dropped are left unset (set by the caller once
    the windows are chosen).
    """
    r = rows & finite_rows(res)
    idx = np.flatnonzero(r)
    empty = SettlingTransient(0.0, 0, 0, np.zeros(0), np.zeros((0, 3)), np.zeros(3), np.nan, False, False, np.zeros(3))
    if idx.size < 9:
        return empty
    g = groups[idx]
    first = np.r_[True, g[1:] != g[:-1]]
    vid = np.cumsum(first) - 1  # contiguous block number
    length = np.bincount(vid)
    start = np.flatnonzero(first)
    pos = np.arange(len(idx)) - start[vid]
    rpos = length[vid] - 1 - pos
    dts = np.diff(t_s[idx])[~first[1:]]
    dt = float(np.median(dts)) if dts.size else 1.0
    K = int(min(np.ceil(max_window_s / max(dt, 1e-12)) + 1, np.median(length) // 3))
    if K < 1:
        return empty
    ok_v = length >= 2 * K + 1
    if ok_v.sum() < 3:
        return empty
    Kv = np.minimum(K, (length - 1) // 3)  # positions used at each end of a visit: a middle is left between mirrors
    x = res[idx]
    t = t_s[idx]
    last = start + length - 1
    nv = len(length)

    def window_mean(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:  # per visit, positions lo <= pos < length - hi
        w = ok_v[vid] & (pos >= lo[vid]) & (rpos >= hi[vid])
        c = np.maximum(np.bincount(vid[w], minlength=nv), 1).astype(float)
        return np.stack([np.bincount(vid[w], weights=x[w, j], minlength=nv) for j in range(3)], axis=1) / c[:, None]

    # each end is compared with the samples mirrored about a window that ends K_v samples before the other end: the
    # same distance from the window (noise of any colour and a linear drift cancel), away from both ends' disturbances
    d_s = x - window_mean(Kv, 2 * Kv)[vid]  # the start against [K_v, n - 2 K_v)
    d_e = x - window_mean(2 * Kv, Kv)[vid]  # the end against [2 K_v, n - K_v)
    ages, end_ages, start_excess, end_excess = [], [], [], []

    def excess(near: np.ndarray, far: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        diff = d[near] ** 2 - d[far] ** 2  # visits in the same order in both
        if len(diff) == 0:
            return np.zeros(3), np.full(3, np.inf)
        return diff.mean(axis=0), (diff.std(axis=0, ddof=1) / np.sqrt(len(diff)) if len(diff) > 1 else np.full(3, np.inf))

    vs = np.flatnonzero(ok_v)  # the visits used, in order: one sample of each at every position k
    for k in range(K):
        v = vs[Kv[vs] > k]
        near_s, far_s = start[v] + k, last[v] - (Kv[v] + k)  # pos == k and rpos == K_v + k
        near_e, far_e = last[v] - k, start[v] + (Kv[v] + k)  # rpos == k and pos == K_v + k
        start_excess.append(excess(near_s, far_s, d_s))
        end_excess.append(excess(near_e, far_e, d_e))
        ages.append(float(np.median(t[near_s] - t[start[v]])) if v.size else np.nan)
        end_ages.append(float(np.median(t[last[v]] - t[near_e])) if v.size else np.nan)
    (P, SE), (Pe, SEe) = (np.array(e).transpose(1, 0, 2) for e in (start_excess, end_excess))
    age, end_age = np.array(ages), np.array(end_ages)
    amp, tau, resolved, detected = _decay_fit(P, np.maximum(SE, 1e-300), age, dt)
    e_amp, e_tau, e_resolved, e_detected = _decay_fit(Pe, np.maximum(SEe, 1e-300), end_age, dt)
    return SettlingTransient(0.0, int(ok_v.sum()), 0, age, np.sign(P) * np.sqrt(np.abs(P)), amp, tau, resolved, detected,
                             np.zeros(3), end_age, np.sign(Pe) * np.sqrt(np.abs(Pe)), e_amp, e_tau, e_resolved, e_detected)


def settle_window(st: SettlingTransient, sigma: np.ndarray, end: bool = False) -> float:
    """Time (s) after a visit's first sample (``end``: before its last) that the floor leaves out: where the
    measured transient A exp(-t/tau) falls below ``SETTLE_NOISE_FRACTION`` x the noise ``sigma`` (3,) m/s^2, capped
    at ``MAX_SETTLE_S``; 0 (only the first, or last, sample) without a detected transient.

    Only a resolved decay (significant at two positions or more) is extrapolated with its fitted tau: the fit is then
    what says how far below the detection limit the transient still reaches (with tau 0.12 s at 50 Hz it is
    significant for 0.42 s but above a tenth of the noise for 0.72 s). An unresolved one (significant at the first
    position only) has just an upper bound on tau, which grows without limit as the excess at the first position
    nears its detection limit (a chance 3-standard-error excess on a clean recording trimmed ~1 s, nearly whole 1 s
    visits): its window is the positions where it is significant, the first (or last) sample, always dropped."""
    detected, tau, amp, resolved = ((st.end_detected, st.end_tau_s, st.end_amplitude_mps2, st.end_tau_resolved) if end
                                    else (st.detected, st.tau_s, st.amplitude_mps2, st.tau_resolved))
    if not detected or not resolved or not np.isfinite(tau) or tau <= 0:
        return 0.0
    ratio = float(np.max(amp / np.maximum(sigma, 1e-12)))
    if ratio <= SETTLE_NOISE_FRACTION:
        return 0.0
    return float(min(tau * np.log(ratio / SETTLE_NOISE_FRACTION), MAX_SETTLE_S))


def _first_kept_age(window_s: float, resolved: bool, age_s: np.ndarray) -> float:
    """Age (s, from the visit's first or last sample) of the first sample a settle window keeps, as far as the
    transient's measurement says: the window itself, or for an unresolved transient (window 0: the first, or last,
    sample dropped) the next position, where its time constant was bounded."""
    if resolved or len(age_s) < 2 or not np.isfinite(age_s[1] - age_s[0]):
        return float(window_s)
    return float(max(window_s, age_s[1] - age_s[0]))


def _degree_rows(scores: list[DegreeScores], held_out: Callable[[DegreeScores], np.ndarray],
                 note: str, chosen: int | None) -> list[dict[str, Any]]:
    """The report's degree table (one dict per degree) from the selection's scores; the rule's ``note`` stands
    on the degree it chose (``chosen``), not on every row."""
    table: list[dict[str, Any]] = []
    for sc in scores:
        if not sc.identified:
            table.append({"degree": sc.degree, "identified": False, "note": sc.note})
            continue
        ho = held_out(sc)
        table.append({"degree": sc.degree, "identified": True, "heldout_rmse_mps2": ho, "insample_rmse_mps2": sc.in_sample,
                      "heldout_rmse_fs": ho / FULL_SCALE_MPS2, "insample_rmse_fs": sc.in_sample / FULL_SCALE_MPS2,
                      "note": sc.note or (note if sc.degree == chosen else ""), "rule_choice": sc.degree == chosen})
    return table


def select_degree(data: DiagnosisData, max_degree: int) -> tuple[int, list[dict[str, Any]]]:
    """Degree of the declared model, chosen exactly as the calibration does (``model_selection.select_degree``:
    held out by temperature level with several levels, by pose with one) on the diagnosis samples."""
    rec = Recording(data.t_s, data.ref, data.xyz, data.temp_c, data.gref, data.pose_id, data.run_id)
    sel = calibration_select_degree(rec, max_degree, usable=data.use & (data.pose_id >= 0))
    by_level = sel.n_levels >= 2
    table = _degree_rows(sel.scores, lambda sc: sc.held_out_level if by_level else sc.held_out_pose, sel.criterion,
                         sel.chosen_degree)
    if sel.chosen_degree is None:
        raise NotIdentifiedError("no degree of eq. 28 could be validated on held-out data: " + "; ".join(sel.notes))
    return sel.chosen_degree, table


def reselect_degree(lanes: Lanes[Evaluator], spec: ModelSpec,
                    max_degree: int) -> tuple[ModelSpec, list[dict[str, Any]], list[str]]:
    """Degree and effects chosen jointly: once an effect is in the model, choose the degree of eq. 28
    again with the effect in every candidate model, by the calibration's rule (``model_selection.choose_degree``:
    temperature-level hold-out guard with two or more levels, then the lowest degree within one standard error
    of the best held-out error), the held-out unit being the visit. A term that stood in for a missing effect
    (a higher degree absorbing a drift) is dropped again; a degree an effect hid is taken up.
    Returns (the spec at the chosen degree, the degree table, notes). The degrees are cross-validated side by side
    on ``lanes``."""
    ev = lanes.lanes[0]
    data = ev.data
    labels = np.full(len(data.t_s), -1)
    labels[data.use], means = temperature_levels(data.temp_c[data.use])
    n_levels = max(len(means), 1)
    by_level = n_levels >= 2
    labels = ev.at(labels)
    level_rows = ev.at(data.use) & (labels >= 0)
    nan3 = np.full(3, np.nan)

    def score(lane: Evaluator, n: int) -> tuple[DegreeScores, np.ndarray | None]:
        if n >= n_levels:
            return DegreeScores(n, False, nan3, nan3, nan3, f"not identified by {n_levels} temperature level(s)"), None
        try:
            des, cv = lane.cv(ModelSpec(n, spec.t_center_c, spec.t_scale_c, spec.effects))
        except NotIdentifiedError as exc:
            return DegreeScores(n, False, nan3, nan3, nan3, f"not identified: {exc}"), None
        r = lane.rows & des.valid & finite_rows(cv.heldout)
        ho = np.sqrt(np.mean(cv.heldout[r] ** 2, axis=0))
        ins = np.sqrt(np.mean((des.G - cv.fitted_full)[r] ** 2, axis=0))
        level_ho = nan3
        if by_level and n < n_levels - 1:  # a fold trains on the other levels: degree n needs n + 1 of them
            try:
                lv = cross_validate(des, level_rows, labels, lane.weights).heldout
                rl = level_rows & des.valid & finite_rows(lv)
                level_ho = np.sqrt(np.mean(lv[rl] ** 2, axis=0))
            except NotIdentifiedError:  # a fold without one level cannot fit this degree
                pass
        return DegreeScores(n, True, ins, ho, level_ho), _group_mse(cv.heldout, lane.groups, r, np.full(3, 1.0 / 3))[1]

    done = lanes.map(score, range(max_degree + 1))
    scores = [sc for sc, _ in done]
    group_mse = {sc.degree: m for sc, m in done if m is not None}
    chosen, criterion, notes = choose_degree(scores, group_mse, by_level, unit="visit")
    table = _degree_rows(scores, lambda sc: sc.held_out_pose, criterion, chosen)
    if chosen is None:
        return spec, table, ["no degree could be validated with the added effects: degree kept", *notes]
    return ModelSpec(chosen, spec.t_center_c, spec.t_scale_c, spec.effects), table, notes


# ============================================================================ candidate evaluation
@dataclass
class CandidateResult:
    name: str
    title: str
    applicable: bool
    reason: str = ""
    hyper: float | None = None
    hyper_profile: list[tuple[float, float]] = field(default_factory=list)  # (h, weighted RSS)
    heldout_rmse: np.ndarray | None = None  # (3,)
    rel_gain: float = 0.0  # fraction of the weighted held-out MSE removed
    p_value: float = 1.0
    n_groups: int = 0
    corr_with_residual: np.ndarray | None = None  # (3,)
    significant: bool = False
    detail: str = ""
    delta: np.ndarray | None = None  # (n, 3) change of the in-sample prediction vs the current model (float32)
    delta_rows: np.ndarray | None = None  # the samples of delta's rows (None: every sample, n = N)
    cross_correlation_delay_s: float | None = None
    implausible: str = ""  # why the fitted values are not physical (then never significant, never added)
    detectable_gain: float = math.nan  # small campaigns: gain the paired t-test finds with 80 % power
    time_block: tuple[float, float] | None = None  # a time function's (gain, p) over contiguous blocks of time held out
    step_check: StepCheck | None = None  # a candidate that can follow a step, against the best step (``step_check``)

    def delta_of_every_sample(self, n: int) -> np.ndarray | None:
        """``delta`` (N, 3) on every one of the recording's ``n`` samples, NaN where it was not evaluated (for the
        report's plots), or None."""
        if self.delta is None or self.delta_rows is None:
            return self.delta
        out = np.full((n, 3), np.nan, np.float32)
        out[self.delta_rows] = self.delta
        return out


def _group_mse(res: np.ndarray, groups: np.ndarray, rows: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r = rows & finite_rows(res)
    ug, inv = np.unique(groups[r], return_inverse=True)
    e = np.sum(res[r] ** 2 * weights, axis=1)
    return ug, np.bincount(inv, weights=e) / np.bincount(inv)


def paired_gain_test(res0: np.ndarray, res1: np.ndarray, groups: np.ndarray, rows: np.ndarray,
                     weights: np.ndarray, alpha: float | None = None) -> tuple[float, float, int, float]:
    """(relative gain, one-sided p-value, groups, detectable gain) of held-out residual res1 over res0, paired by
    visit group.

    The test is the one-sided Wilcoxon signed-rank test of the per-group MSE differences. With so few groups
    that it cannot reach ``alpha`` at all (2^-n >= alpha: six visits against 0.01 / 8) it is a one-sided paired
    t-test over the groups instead (df n - 1; it has power on small designs but assumes normally distributed
    per-group differences), and the detectable gain is the relative gain it finds with 80 % power at ``alpha``
    given the scatter of these differences (NaN where the signed-rank test is used)."""
    r = rows & finite_rows(res0) & finite_rows(res1)
    _, m0 = _group_mse(res0, groups, r, weights)
    _, m1 = _group_mse(res1, groups, r, weights)
    d = m0 - m1
    n = len(d)
    tot0 = float(np.sum(res0[r] ** 2 * weights))
    gain = (tot0 - float(np.sum(res1[r] ** 2 * weights))) / tot0 if tot0 > 0 else 0.0
    if alpha is not None and 0.5**n >= alpha:  # small campaign: the rank test cannot reach alpha
        sd = float(np.std(d, ddof=1)) if n >= 3 else 0.0
        if sd <= 0:
            return gain, 1.0, n, math.inf
        p = float(stats.ttest_1samp(d, 0.0, alternative="greater").pvalue)
        detectable = (stats.t.ppf(1 - alpha, n - 1) + stats.t.ppf(0.8, n - 1)) * sd / math.sqrt(n) / float(np.mean(m0))
        return gain, p, n, float(detectable)
    if n < 5 or np.all(d == 0):
        return gain, 1.0, n, math.nan
    p = float(stats.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue)
    return gain, p, n, math.nan


def cross_correlation_delay(data: DiagnosisData, fitted: np.ndarray, max_lag: int = 12) -> float:
    """Delay (s) of the model output against the (gap-filled) reference by cross-correlation of their
    first differences (finddelay of D'Emilia et al. 2019), with parabolic sub-sample interpolation."""
    best_lag, best_val, vals = 0, -np.inf, {}
    a = np.diff(np.nan_to_num(fitted), axis=0)
    g = np.diff(np.nan_to_num(data.gref_filled), axis=0)
    same_run = data.run_id[1:] == data.run_id[:-1]
    a[~same_run], g[~same_run] = 0.0, 0.0
    for lag in range(0, max_lag + 1):
        v = float(np.sum(a[lag:] * g[: len(g) - lag]))
        vals[lag] = v
        if v > best_val:
            best_lag, best_val = lag, v
    frac = peak_offset(vals[best_lag - 1], vals[best_lag], vals[best_lag + 1]) if 0 < best_lag < max_lag else 0.0
    return (best_lag + frac) * data.dt_s


SEARCH_ROWS = 50_000  # fitted samples above which the candidates are evaluated on every k-th one
MIN_SEARCH_INFORMATION = 0.8  # but a thinned search keeps at least this much of what a visit's samples tell of its mean


def thinned_information(noise: VisitNoise, k: int, visit_samples: float) -> float:
    """What every ``k``-th sample of a visit of ``visit_samples`` consecutive samples tells of the visit's mean, as a
    fraction of what all of them tell: var(mean of all) / var(mean of every k-th) under the noise's autocorrelation
    (``VisitNoise.mean_variance``; ``visit_samples`` / k of them, as many as the thinning leaves on average over the
    visits' phases: a little less than the ceiling, so on the safe side), on the axis that loses most. 1 / k for white
    noise; near 1 while k is well within the noise's correlation time (the TIA's filtered noise at 100 Hz:
    ``VisitNoise.correlation_samples``)."""
    if k <= 1:
        return 1.0
    every = noise.mean_variance(np.array([float(visit_samples)]))[0]
    thinned = VisitNoise(noise.sigma, noise.acf[:, ::k]).mean_variance(np.array([float(visit_samples) / k]))[0]
    return float(np.min(every / thinned))


def check_search_rows(search_rows: int | None) -> None:
    """Refuse a ``search_rows`` below 1 (None: every sample) with a clear error."""
    if search_rows is not None and search_rows < 1:
        raise ValueError(f"search_rows must be at least 1 (None: every sample), got {search_rows}")


def search_samples(fit_rows: np.ndarray, folds: np.ndarray, search_rows: int | None, noise: VisitNoise | None = None,
                   visit_samples: float = math.inf) -> tuple[np.ndarray, int, float]:
    """(the samples the candidates are searched on, in fold order: each fold a slice of the search's designs, no
    gathers; the step k of the thinning (1: not thinned); ``thinned_information`` at k). Those are the fitted
    samples ``fit_rows`` (N,); with more than ``search_rows`` of them, every k-th one (about ``search_rows``), k
    lowered until the thinned samples keep ``MIN_SEARCH_INFORMATION`` of what the visits' samples tell of their means
    (``noise``: the floor's model of the noise; ``visit_samples``: a visit's typical number of fitted samples).
    Consecutive samples of a visit are strongly correlated (TIA-filtered noise): the thinned set carries most of
    the information that decides a choice, at a fraction of the cost; a recording sampled so slowly that its noise
    is nearly white is thinned less."""
    check_search_rows(search_rows)
    n_fit = int(fit_rows.sum())
    k = math.ceil(n_fit / search_rows) if search_rows is not None and n_fit > search_rows else 1
    kept = 1.0 if noise is None or not math.isfinite(visit_samples) else thinned_information(noise, k, visit_samples)
    if kept < MIN_SEARCH_INFORMATION:  # the largest k below that keeps it (bisection: the information falls with k)
        lo, hi, kept = 1, k, 1.0
        while hi - lo > 1:
            mid = (lo + hi) // 2
            info = thinned_information(noise, mid, visit_samples)
            lo, hi, kept = (mid, hi, info) if info >= MIN_SEARCH_INFORMATION else (lo, mid, kept)
        k = lo
    every = np.flatnonzero(fit_rows)[::k]
    return every[np.argsort(folds[every], kind="stable")], k, kept


class Evaluator:
    """Evaluates specs on the samples ``sub`` (indices, ``search_samples``) of one recording with fixed folds,
    rows and noise weights (cached designs): ``diagnose`` evaluates the candidates and chooses the model on it
    (hyper-parameters, held-out gains, tests over the visits), then fits the chosen model on every sample.
    Designs, folds, groups and held-out arrays are of ``sub``'s length; the input corrections still run on the
    whole time series. ``references``: the corrected references a search keeps (``DesignCache``).
    """

    def __init__(self, data: DiagnosisData, folds: np.ndarray, weights: np.ndarray, groups: np.ndarray,
                 sub: np.ndarray, references: int = 4) -> None:
        self.data, self.weights, self.sub = data, weights, sub
        self.folds, self.groups = self.at(folds), self.at(groups)
        self.rows = self.at(data.use) & (self.folds >= 0)  # held out and judged
        self.fit_rows = self.at(data.use) & (self.folds != -1)  # fitted (also the visits never held out, fold -2)
        self.designs = DesignCache(references=references)
        # results worked out by the confounding check that the next step needs again (see ``forget``)
        self._cv_memo: dict[tuple, tuple[Design, CvResult]] = {}
        self._hyper_memo: dict[tuple, tuple[float | None, np.ndarray, list[tuple[float, float]]]] = {}
        self._last_cv: tuple[tuple, tuple[Design, CvResult]] | None = None
        self._sums: FoldSums | None = None
        self._rss_sums: RssSums | None = None

    def at(self, a: np.ndarray) -> np.ndarray:
        """``a`` (per sample of the recording) at this evaluator's samples."""
        return a[self.sub]

    @property
    def model_matrix(self) -> np.ndarray:
        """(3, 3) model matrix at the mean temperature (m/s^2 per unit Psi), for the plausibility bounds."""
        return np.linalg.inv(self.data.static_psi_map()[0])

    def design(self, spec: ModelSpec) -> Design:
        return build_design(self.data, spec, self.designs, self.sub)

    def cv(self, spec: ModelSpec, remember: bool = False) -> tuple[Design, CvResult]:
        """Design and cross-validation of ``spec``; ``remember``: keep them for a later call (``forget``). The
        last one is kept too: a search's final value is checked for plausibility, then evaluated."""
        hit = self._cv_memo.get(spec.key)
        if hit is None and self._last_cv is not None and self._last_cv[0] == spec.key:
            hit = self._last_cv[1]
        if hit is not None:
            return hit
        self._last_cv = None  # not held while the next design is built
        des = self.design(spec)
        out = des, cross_validate(des, self.fit_rows, self.folds, self.weights, self._sums)
        self._sums = out[1].sums  # a search over the reference alone asks again with the same matrix
        if remember:
            self._cv_memo[spec.key] = out
        self._last_cv = (spec.key, out)
        return out

    def cv_each(self, specs: list[ModelSpec],
                use: Callable[[int, tuple[Design, CvResult] | NotIdentifiedError], None]) -> None:
        """``use(k, self.cv(specs[k]))`` (or the NotIdentifiedError it raised) for each spec in order, the designs and
        cross-validations worked out on this lane and on the lanes of the map left idle meanwhile
        (``search_lanes.idle_lanes``): one spec a lane at a time, each result used before the next round (the lanes'
        results are the same, bit for bit; a lent lane keeps its last design until its next trial, as any lane)."""
        def one(lane: Evaluator, spec: ModelSpec) -> tuple[Design, CvResult] | NotIdentifiedError:
            try:
                return lane.cv(spec)
            except NotIdentifiedError as exc:
                return exc

        with idle_lanes(len(specs) - 1) as extra:
            if not extra:
                for k, spec in enumerate(specs):
                    use(k, one(self, spec))
                return
            lanes = [self, *extra]
            with ThreadPoolExecutor(len(extra), thread_name_prefix="search-lane-lent") as pool:
                for lo in range(0, len(specs), len(lanes)):
                    part = specs[lo:lo + len(lanes)]
                    later = [pool.submit(one, lane, spec) for lane, spec in zip(lanes[1:], part[1:], strict=False)]
                    use(lo, one(self, part[0]))
                    for k, f in enumerate(later, start=lo + 1):
                        use(k, f.result())

    def forget(self, spec: ModelSpec) -> None:
        """Drop remembered results except those on top of ``spec``, the model the next step starts from: the
        confounding check has already worked out each candidate on top of the one that is then added."""
        for k in [k for k in self._cv_memo if k != spec.key]:  # in place: the lanes share them (``lane``)
            del self._cv_memo[k]
        for k in [k for k in self._hyper_memo if k[0] != spec.key]:
            del self._hyper_memo[k]
        self._rss_sums = None  # its copy of the matrix's fitted rows (n x p)

    def lane(self) -> Evaluator:
        """Another evaluator of the same samples, folds and weights, for searches run beside this one's
        (``search_lanes``): its own caches of inputs and designs, this one's remembered results and corrected
        references (values that depend on their key alone, whichever lane works them out)."""
        other = copy.copy(self)
        other.designs = self.designs.for_another_lane()
        other._last_cv = other._sums = other._rss_sums = None
        return other

    def fit_hyper(self, spec: ModelSpec, eff: Effect,
                  remember: bool = False) -> tuple[float | None, np.ndarray, list[tuple[float, float]]]:
        """Hyper-parameter of ``eff`` added to ``spec``: nested grid choice per fold for the held-out
        residual, and grid + bounded refinement on all rows for the final value. Returns (value, held-out
        residual (N, 3), profile of (value, mean training RSS)). ``remember``: keep the result (``forget``)."""
        key = (spec.key, eff.name)
        if key in self._hyper_memo:
            return self._hyper_memo[key]
        out = self._fit_hyper(spec, eff)
        if remember:
            self._hyper_memo[key] = out
        return out

    def remembers(self, spec: ModelSpec, eff: Effect) -> bool:
        """Whether :meth:`fit_hyper` of ``eff`` on top of ``spec`` is remembered (costs nothing)."""
        return (spec.key, eff.name) in self._hyper_memo

    def nested_heldout(self, spec: ModelSpec, eff: Effect) -> np.ndarray:
        """The held-out residual (N, 3) of :meth:`fit_hyper` alone: the final value is not worked out (its
        refinement on all rows, which the held-out residual does not depend on, is skipped)."""
        return self._fit_hyper(spec, eff, final=False)[1]

    def _fit_hyper(self, spec: ModelSpec, eff: Effect,
                   final: bool = True) -> tuple[float | None, np.ndarray, list[tuple[float, float]]]:
        """:meth:`fit_hyper`; ``final`` False: the value returned is the best grid value, not refined (see
        :meth:`nested_heldout`)."""
        if eff.hyper_grid(self.data) is None:
            _, cvr = self.cv(spec.plus(eff, None))
            return None, cvr.heldout, []
        grid = eff.hyper_grid(self.data)
        K = int(self.folds[self.rows].max()) + 1
        fold_rows = [np.flatnonzero(self.rows & (self.folds == f)) for f in range(K)]  # indices: a fold is taken often
        # nested choice: each fold's held-out residual is the one of the grid value that fits the other folds
        # best (the first such value on a tie), kept as the grid is walked: one (N, 3) array, not one per value.
        # Values whose fit on all rows is not physical (Effect.implausible: e.g. a warm-up of 13 m/s^2 cancelled
        # by a creep) are searched apart and used only when no value is plausible: the hypothesis is a
        # physical effect, and the best implausible value must not hide a plausible one.
        heldout = {ok: np.full((len(self.folds), 3), np.nan) for ok in (True, False)}
        best_train = {ok: np.full(K, np.inf) for ok in (True, False)}
        best_at = {ok: np.full(K, len(grid)) for ok in (True, False)}  # grid index of each fold's best value
        seen: dict[int, tuple[bool | None, float]] = {}  # grid index -> (plausible, mean training RSS); None: not identified
        unidentified: list[str] = []
        # a step's time is a fold's choice only where that fold's training visits on each side span the frame
        fold_ok = self._step_sides(eff, grid, K) if eff.switched else None

        def visit(i: int, done: tuple[Design, CvResult] | NotIdentifiedError) -> None:
            h = float(grid[i])
            if isinstance(done, NotIdentifiedError):  # this value makes the design singular: not a candidate
                unidentified.append(f"{eff.hyper_name} = {h:.4g}: {done}")
                seen[i] = (None, math.inf)
                return
            des, cvr = done
            ok = not self.implausible(eff, h, des, cvr)
            # the first value in grid order wins a tie, whatever the order the values are visited in
            better = (cvr.train_rss < best_train[ok]) | ((cvr.train_rss == best_train[ok]) & (i < best_at[ok]))
            if fold_ok is not None:
                better &= fold_ok[:, i]
            for f in np.flatnonzero(better):
                best_train[ok][f], best_at[ok][f] = cvr.train_rss[f], i
                heldout[ok][fold_rows[f]] = np.nan  # those of the fold not fitted at this value
                at, res = cvr.fold_heldout(f)
                heldout[ok][at] = res
            seen[i] = (ok, float(np.sum(cvr.train_rss) / max(K - 1, 1)))

        def visit_all(batch: list[int]) -> None:
            todo = [i for i in batch if i not in seen]
            self.cv_each([spec.plus(eff, float(grid[i])) for i in todo], lambda k, done: visit(todo[k], done))

        picks = self._switch_picks(spec, eff, grid, fold_ok) if eff.switched else None
        visit_all(picks or [])
        if picks is None or not all(ok for ok, _ in seen.values()):  # an implausible or unidentified pick: the walk
            for batch in search_batches(len(grid), seen, best_at[True]):
                visit_all(batch)
        order = sorted(i for i in seen if seen[i][0] is not None)
        if not order:
            raise NotIdentifiedError("no value of the grid is identified (" + unidentified[0] + ")")
        kept = [float(grid[i]) for i in order]
        plausible = [bool(seen[i][0]) for i in order]
        profile = [(float(grid[i]), seen[i][1]) for i in order]
        use_ok = any(plausible)
        grid = np.asarray([h for h, ok in zip(kept, plausible, strict=True) if ok == use_ok])
        rss_grid = [p[1] for p, ok in zip(profile, plausible, strict=True) if ok == use_ok]
        # final value on all rows: best grid point then bounded scalar refinement between its neighbours
        j = int(np.argmin(rss_grid))
        lo = grid[max(j - 1, 0)]
        hi = grid[min(j + 1, len(grid) - 1)]
        h_best = float(grid[j])
        if not final:
            return h_best, heldout[use_ok], profile

        rss_at: dict[float, float] = {}  # the refinement and the parsimony check ask for some values again

        def obj(h: float) -> float:
            if float(h) not in rss_at:
                try:
                    rss_at[float(h)], self._rss_sums = weighted_rss(self.design(spec.plus(eff, float(h))), self.fit_rows,
                                                                    self.weights, self._rss_sums)
                except NotIdentifiedError:
                    rss_at[float(h)] = math.inf
            return rss_at[float(h)]

        if hi > lo and not eff.switched:  # a switched effect's values are sample indices: none between them
            res = optimize.minimize_scalar(obj, bounds=(float(lo), float(hi)), method="bounded",
                                           options={"xatol": 1e-3 * (hi - lo), "maxiter": 25})
            if res.success and res.fun <= obj(h_best):
                h_ref = float(res.x)
                if not (use_ok and self.implausible(eff, h_ref, *self.cv(spec.plus(eff, h_ref)))):
                    h_best = h_ref
        if eff.hyper_null is not None:
            # parsimony: keep the null value unless moving away from it is a significant improvement,
            # judged with visits as the independent units (likelihood ratio ~ chi^2(1), 1 %)
            rss_best, rss_null = obj(h_best), obj(eff.hyper_null)  # a null value not identified is not kept
            n_groups = len(np.unique(self.groups[self.rows]))
            if (rss_null - rss_best) / max(rss_best / n_groups, 1e-300) < stats.chi2.ppf(0.99, 1):
                h_best = float(eff.hyper_null)
        return h_best, heldout[use_ok], profile

    def _step_sides(self, eff: Effect, grid: np.ndarray, K: int) -> np.ndarray:
        """(K, m) bool: whether fold f's training visits before and after the step at each value of ``grid`` each
        span the table frame (``ResponseStepEffect.sides_span``; the visits a fold holds out are those of its
        judged rows)."""
        _, _, ids = eff.visit_table(self.data)
        order = np.argsort(ids)
        r = np.flatnonzero(self.rows)
        pos = np.minimum(np.searchsorted(ids[order], self.groups[r]), len(ids) - 1)
        known = ids[order][pos] == self.groups[r]
        held = np.zeros((K, len(ids)), bool)
        held[self.folds[r][known], order[pos[known]]] = True
        return eff.sides_span(self.data, grid, ~held)

    def _switch_picks(self, spec: ModelSpec, eff: Effect, grid: np.ndarray,
                      fold_ok: np.ndarray | None = None) -> list[int] | None:
        """The grid indices a search of a switched effect (``Effect.switched``) visits: each fold's best (among the
        values ``fold_ok`` (K, m) allows it) and the best mean training RSS from ``switch_profile``; None when the
        model alone is not identified (the walk says why)."""
        des = self.design(spec.plus(eff, -math.inf))  # switched on everywhere: its block is the switched columns
        blk = des.blocks[eff.name]
        X = des.X[:, :blk.start] if blk.stop == des.X.shape[1] else np.delete(des.X, np.r_[blk], axis=1)
        try:
            prof = switch_profile(X, des.G, des.X[:, blk], self.sub, self.folds,
                                  self.fit_rows & des.valid, self.weights, grid)
        except NotIdentifiedError:
            return None
        best_mean = int(np.argmin(prof.sum(axis=0)))
        if fold_ok is not None:
            prof = np.where(fold_ok, prof, np.inf)
        return sorted({int(np.argmin(p)) for p in prof if np.isfinite(p).any()} | {best_mean})

    def implausible(self, eff: Effect, h: float | None, des: Design, cvr: CvResult) -> str:
        """Why the fit of ``eff`` at ``h`` (design ``des``, fit ``cvr`` on all rows) is not physical, or "": the
        effect's own bounds (``Effect.implausible``) or columns that cancel (``cancelling_terms``)."""
        coeff = cvr.A_full[des.blocks[eff.name]].T if eff.name in des.blocks else None
        return (eff.implausible(h, coeff, self.data, self.model_matrix)
                or cancelling_terms(des, cvr, eff.name))

    def evaluate(self, spec: ModelSpec, eff: Effect, base_heldout: np.ndarray, base_fitted: np.ndarray,
                 base_G: np.ndarray, alpha: float | None = None) -> CandidateResult:
        """Held-out gain and significance of ``eff`` on top of ``spec``, whose held-out residual, in-sample fit and
        reference (each (n, 3), this evaluator's samples) are the ``base_*`` (``alpha``: the candidate's level,
        which decides the test on small campaigns, ``paired_gain_test``)."""
        ok, why = eff.applicable(self.data)
        out = CandidateResult(eff.name, eff.title, ok, why)
        if not ok:
            return out
        try:
            h, heldout, profile = self.fit_hyper(spec, eff)
            des, cvr = self.cv(spec.plus(eff, h))
        except NotIdentifiedError as exc:  # the data cannot tell its columns from the model's: say so
            out.applicable, out.reason = False, f"not identified on this data: {exc}"
            return out
        r = self.rows & des.valid & finite_rows(heldout) & finite_rows(base_heldout)
        gain, p, ng, out.detectable_gain = paired_gain_test(base_heldout, heldout, self.groups, r, self.weights, alpha)
        # what the candidate explains of the current residual (reference changes count too: delay, TIA)
        delta = (base_G - des.G) + (cvr.fitted_full - base_fitted)
        corr = np.array([_corr(base_heldout[r, j], delta[r, j]) for j in range(3)])
        out.hyper, out.hyper_profile = h, profile
        out.heldout_rmse = np.sqrt(np.mean(heldout[r] ** 2, axis=0))
        out.rel_gain, out.p_value, out.n_groups = gain, p, ng
        out.corr_with_residual = corr
        coeff = cvr.A_full[des.blocks[eff.name]].T if eff.name in des.blocks else None
        out.detail = eff.describe(h, coeff)
        out.implausible = self.implausible(eff, h, des, cvr)
        if out.implausible:
            out.detail += f"; REFUSED: {out.implausible}"
        out.delta = delta.astype(np.float32)  # for the plots and a correlation only
        return out


def _evaluate_on(spec: ModelSpec, base_heldout: np.ndarray, base_fitted: np.ndarray, base_G: np.ndarray, alpha: float,
                 seconds: dict[str, float], ev: Evaluator, eff: Effect) -> CandidateResult:
    """``ev.evaluate(spec, eff, ...)``: a task of ``Lanes.map`` (lane, item) once the step's arguments are bound; the
    time it took goes into ``seconds`` (by the candidate's name: the order the next step's candidates start in)."""
    t0 = time.perf_counter()
    out = ev.evaluate(spec, eff, base_heldout, base_fitted, base_G, alpha)
    seconds[eff.name] = time.perf_counter() - t0
    return out


def time_block_check(data: DiagnosisData, spec: ModelSpec, eff: Effect, h: float | None, sub: np.ndarray,
                     folds: np.ndarray, weights: np.ndarray, alpha: float) -> tuple[float, float]:
    """(held-out gain, one-sided p over visits: ``paired_gain_test``) of ``eff`` at ``h`` on top of ``spec`` when the
    folds are contiguous blocks of time (``folds``: ``make_folds``' time blocks made identifiable by ``check_folds``), on
    the samples ``sub`` (indices; the search's). A function of time (``Effect.time_function``) that only gains
    between visits interleaved in time follows a slow wander of the residual, which it cannot extrapolate: the
    driver would apply it after every power-on. A model not identified on these folds has gain -inf, p 1."""
    f = folds[sub]
    fit, judged = data.use[sub] & (f != -1), data.use[sub] & (f >= 0)
    try:
        ho = [cross_validate(build_design(data, s, sub=sub), fit, f, weights).heldout for s in (spec, spec.plus(eff, h))]
    except NotIdentifiedError:
        return -math.inf, 1.0
    r = judged & finite_rows(ho[0]) & finite_rows(ho[1])
    gain, p = paired_gain_test(ho[0], ho[1], data.group[sub], r, weights, alpha)[:2]
    return gain, p


@dataclass
class StepCheck:
    """A candidate that can follow a step (``Effect.follows_a_step``: a function of time, of the temperature's history
    or of the reference counts) against the best step of the response at one time (``effects.ResponseStepEffect``),
    each added on top of the other (held-out gain, one-sided p over visits) with eq. 28 at ``degree``."""

    t_s: float  # board time of the first fitted sample after the step (s)
    t_before_s: float  # board time of the last fitted sample before it (s): the step happened in between
    run: int  # the run it is in
    gain_step_beyond: float  # the step on top of the candidate
    p_step_beyond: float
    gain_time_beyond: float  # the candidate on top of the step
    p_time_beyond: float
    explained: bool  # the step gains beyond the candidate, the candidate not beyond the step
    degree: int = 0  # degree of eq. 28 in both models (chosen again with the candidate and the step in it)

    @property
    def when(self) -> str:
        """Where the step is, for the report: between two fitted samples (a table move, a settling or a gap in between)."""
        return f"between t = {self.t_before_s:.4g} and {self.t_s:.4g} s (run {self.run})"


def step_check(lanes: Lanes[Evaluator], spec: ModelSpec, eff: Effect, h: float | None, alpha: float,
               min_rel_gain: float, max_degree: int | None = None) -> StepCheck | None:
    """Does a step of the response at one time explain what ``eff`` (at ``h``; ``Effect.follows_a_step``) fits on top
    of ``spec``? A warm-up with creep follows a step (a connector knocked mid-run) across contiguous blocks of time too,
    so ``time_block_check`` passes it; on a temperature-cycled run a hysteresis branch or a thermal lag follows it as
    well, since the temperature's history is tied to time; written to the calibration, the driver applies it for good.
    The step (its time found like any hyper-parameter, nested in the folds) and ``eff`` are each added on top of the
    other, as in the confounding check: if the step gains beyond ``eff`` (``alpha``, ``min_rel_gain``) and ``eff`` not
    beyond the step, ``eff`` is a stand-in. ``max_degree`` (None: the degree is forced, or one temperature level): eq.
    28's degree is first chosen again with both in the model (``reselect_degree``), as it is after any effect is added,
    and both are compared at it: a degree chosen with the step in the residual can be too low for the step's model, and
    the temperature dependence it leaves then passes for a drift or a hysteresis. None when the recording has too few
    visits for a step. The two candidates on top of each other run side by side on ``lanes``."""
    step = ResponseStepEffect()
    ev = lanes.lanes[0]
    if not step.applicable(ev.data)[0]:
        return None

    def on_top(lane: Evaluator, base_eff: tuple[ModelSpec, Effect]) -> CandidateResult:
        base, e = base_eff
        des, cvr = lane.cv(base)
        return lane.evaluate(base, e, cvr.heldout, cvr.fitted_full, des.G, alpha)

    def gains(r: CandidateResult) -> bool:
        return r.applicable and r.p_value < alpha and r.rel_gain >= min_rel_gain and not r.implausible

    try:
        # the step that fits best in place of the candidate, not beside it; kept: every candidate checked at this
        # step (a drift, a dark offset, a temperature history) is set against the same best step
        with lanes.lending():  # ev (the first lane) searches it, the other lanes work its trials out beside it
            h_step = ev.fit_hyper(spec, step, remember=True)[0]
        if max_degree is not None:
            degree = reselect_degree(lanes, spec.plus(eff, h).plus(step, h_step), max_degree)[0].degree
            # the step's time, set by the jump rather than by the temperature terms, is kept (a search of it is
            # most of the check's cost)
            spec = ModelSpec(degree, spec.t_center_c, spec.t_scale_c, spec.effects)
    except NotIdentifiedError:
        return None
    beyond_time, beyond_step = lanes.map(on_top, [(spec.plus(eff, h), step), (spec.plus(step, h_step), eff)])
    if not beyond_time.applicable:
        return None
    i = min(math.ceil(float(h_step)), len(ev.data.t_s) - 1)
    fitted = np.flatnonzero(ev.data.use[:i] & (ev.data.group[:i] >= 0))
    t_before = float(ev.data.t_s[fitted[-1]]) if fitted.size else math.nan
    return StepCheck(float(ev.data.t_s[i]), t_before, int(ev.data.run_id[i]), beyond_time.rel_gain, beyond_time.p_value,
                     beyond_step.rel_gain if beyond_step.applicable else -math.inf,
                     beyond_step.p_value if beyond_step.applicable else 1.0,
                     gains(beyond_time) and not gains(beyond_step), spec.degree)


def judge_step(lanes: Lanes[Evaluator], spec: ModelSpec, r: CandidateResult, eff_r: Effect, alpha_each: float,
               min_rel_gain: float, max_degree: int | None, step_confounded: dict[str, str]) -> None:
    """Set the significant candidate ``r`` (of ``eff_r``, ``Effect.follows_a_step``) on top of ``spec`` against the best
    step of the response (``step_check``; ``max_degree`` None: eq. 28's degree is not chosen again): refused (``r``
    no longer significant, why in its detail) if the step explains it; if the step fits as well, the warning for the
    report is put in ``step_confounded`` under its name."""
    sc = r.step_check = step_check(lanes, spec, eff_r, r.hyper, alpha_each, min_rel_gain, max_degree)
    at_degree = f", eq. 28 of degree {sc.degree}" if sc is not None and sc.degree != spec.degree else ""
    if sc is not None and sc.explained:
        r.significant = False
        r.detail += (f"; not added: a step of the response {sc.when} explains "
                     f"it: the step gains {100 * sc.gain_step_beyond:+.1f} % beyond it (p = "
                     f"{sc.p_step_beyond:.2g}), it gains {100 * sc.gain_time_beyond:+.1f} % beyond the step "
                     f"(p = {sc.p_time_beyond:.2g}{at_degree}): the response changed once (a connector "
                     f"knocked or re-mated, a fibre bent, a knock), not {eff_r.sensor_property} the driver "
                     "could apply")
    elif sc is not None and sc.p_time_beyond < alpha_each and sc.gain_time_beyond >= min_rel_gain:
        r.detail += (f"; it gains {100 * sc.gain_time_beyond:+.1f} % beyond the best step of the response "
                     f"at one time ({sc.when}, p = {sc.p_time_beyond:.2g}{at_degree})")
    elif sc is not None:  # neither beyond the other: the data do not tell a step from this candidate
        r.detail += (f"; a step of the response {sc.when} fits as well: it "
                     f"gains {100 * sc.gain_time_beyond:+.1f} % beyond the step (p = {sc.p_time_beyond:.2g}), "
                     f"the step {100 * sc.gain_step_beyond:+.1f} % beyond it (p = {sc.p_step_beyond:.2g}"
                     f"{at_degree})")
        step_confounded[r.name] = (f"{r.name} is in the calibration, but a step of the response {sc.when} (a "
                                   "connector, a fibre, a knock) fits this "
                                   "data as well, and a step is no property of the sensor: "
                                   f"{eff_r.tells_it_from_a_step}")


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    if a.size < 3 or np.std(a) == 0 or np.std(b) == 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


# ============================================================================ the diagnosis
@dataclass
class Confounding:
    a: str
    b: str
    corr_contributions: float
    p_b_beyond_a: float
    p_a_beyond_b: float
    verdict: str
    gain_b_beyond_a: float
    gain_a_beyond_b: float  # "confounded", "<a> explains <b>", "both"
    separating_measurement: str


@dataclass
class StepResult:
    step: int
    model: list[str]
    candidates: list[CandidateResult]
    chosen: str | None
    alpha_each: float
    confounding: list[Confounding]
    degree_table: list[dict[str, Any]] = field(default_factory=list)  # degree re-selected after adding ``chosen``
    degree_note: str = ""
    degree_after: int | None = None  # the re-selected degree


SMALL_RATIO = 1.1  # a significant residual whose held-out RMSE is within this x the per-sample floor is "small"


@dataclass
class ResidualStructure:
    significant: bool  # the test's: chi^2 / F p < alpha on some axis, whatever the size
    verdict: str
    heldout_rmse: np.ndarray
    noise_floor: np.ndarray
    ratio: np.ndarray
    pose_chi2_p: np.ndarray  # (3,)
    excess_rms: np.ndarray  # (3,) sqrt(heldout^2 - floor^2)
    per_pose: list[dict[str, Any]]  # pose id, n, mean residual (3,), z (3,), mean time (s from the first sample)
    pose_mean_rms: np.ndarray  # (3,)
    corr_time: np.ndarray
    corr_temperature: np.ndarray
    orientation_r2: np.ndarray  # (3,) pose-mean residual explained by quadratic in the reference direction
    lag1_autocorr: np.ndarray  # (3,) lag-1 autocorrelation of the noise (the floor's estimate)
    serial_corr_pose_means: np.ndarray  # (3,) correlation of consecutive pose means in time order (slow wander -> ~1)
    noise_corr_samples: np.ndarray  # (3,) integrated correlation time of the noise, samples (VisitNoise)
    noise_mean_dof: np.ndarray  # (3,) degrees of freedom of the variance of a visit mean (VisitNoise.mean_dof)
    small: bool = False  # significant, but on no significant axis is the held-out RMSE above ratio_limit x floor
    # visits of one direction of gravity (``effects.direction_labels``) against their direction's mean: p (3,) of the
    # chi^2 / F test as above; the visits in directions visited more than once; the median time span of those
    # directions' visits (s). Small p: the residual depends on something other than the direction of gravity in the
    # sensor (the table's angles: its geometry, a cable it drags; or time, over that span)
    direction_chi2_p: np.ndarray = field(default_factory=lambda: np.ones(3))
    direction_repeat_visits: int = 0
    direction_span_s: float = 0.0
    # the same split in two: visits of one pose id (the same table angles) against each other, which only time can
    # set apart, and the poses of one direction (other table angles) against each other; p (3,) each, and the median
    # time span (s) of the poses visited more than once
    same_pose_chi2_p: np.ndarray = field(default_factory=lambda: np.ones(3))
    other_pose_chi2_p: np.ndarray = field(default_factory=lambda: np.ones(3))
    same_pose_span_s: float = 0.0


@dataclass
class DiagnosisResult:
    data: DiagnosisData
    degree: int
    degree_table: list[dict[str, Any]]
    n_levels: int
    noise_floor: np.ndarray  # (3,) m/s^2
    before_heldout_rmse: np.ndarray  # (3,)
    before_insample_rmse: np.ndarray
    after_heldout_rmse: np.ndarray
    after_insample_rmse: np.ndarray
    steps: list[StepResult]
    added: list[tuple[str, float | None, str]]  # name, hyper, description
    calibration: ThermalCalibration
    base_calibration: ThermalCalibration
    residual_before: np.ndarray  # (N, 3) held-out residual of the declared model
    residual_after: np.ndarray  # (N, 3) held-out residual of the final model
    structure: ResidualStructure
    consistency_max_abs_mps2: float
    n_static: int
    n_groups: int
    moving_residual_rms: np.ndarray | None
    settings: dict[str, Any]
    settling: SettlingTransient | None = None  # the settling transient after table moves (not in the floor)
    fold_notes: list[str] = field(default_factory=list)  # folds split or visits never held out (check_folds)
    n_floor_samples: int = 0  # settled samples the noise floor is computed from
    # filters against noise chosen like effects (e.g. the reference low-pass), not model effects: name, hyper, text
    noise_remedies: list[tuple[str, float | None, str]] = field(default_factory=list)
    noise_floor_after: np.ndarray | None = None  # (3,) floor of the final model (lower once a noise remedy is in)
    warnings: list[str] = field(default_factory=list)  # results a reader must not take at face value
    condition_number: float = float("nan")  # of the final model's scaled normal matrix (gram_conditioning)
    column_correlation: dict[str, float] = field(default_factory=dict)  # added effect -> max |corr| with the others
    final_degree: int = -1  # degree of eq. 28 in the final model (re-selected after each added effect)
    run_terms: list[tuple[str, float | None, str]] = field(default_factory=list)  # per-run terms (not in the YAML)
    held_codes: list[HeldCode] = field(default_factory=list)  # ADC codes that held whole visits (adc_codes)
    # a periodic disturbance found in the visits (periodic_disturbance): when found, the floors above are without it
    disturbance: PeriodicDisturbance = field(default_factory=lambda: PeriodicDisturbance([], (math.nan, math.nan), 0,
                                                                                          0.0, math.inf))

    @property
    def final_floor(self) -> np.ndarray:
        """The floor the final held-out error is judged against (m/s^2, x/y/z)."""
        return self.noise_floor if self.noise_floor_after is None else self.noise_floor_after

    @property
    def ranked(self) -> list[CandidateResult]:
        return self.steps[0].candidates if self.steps else []


@single_blas_thread
def diagnose(rec: Recording | DiagnosisData, *, static: str = "table", max_degree: int = 4, folds: int = 10,
             alpha: float = 0.01, min_rel_gain: float = 0.02, max_effects: int = 3, library: tuple[Effect, ...] = LIBRARY,
             degree: int | None = None, sensor_id: str = "unknown", seed: int = 0,
             progress: Callable[[str], None] | None = None, settle_s: float | None = None,
             search_rows: int | None = SEARCH_ROWS, lanes: int | None = None) -> DiagnosisResult:
    """Run the whole diagnosis on a recording (see the module docstring). ``progress`` (optional) is called
    with the candidate's name after each candidate evaluation (the CLI's progress bar). ``settle_s`` (s):
    samples this close to the start of a visit are left out of the noise floor (``settled_mask``); None: the
    window where the measured settling transient falls below a tenth of the noise (``settle_window``).
    ``search_rows``: above this many fitted samples, the candidates are evaluated and the model chosen on a
    thinned set, and the chosen model fitted on every sample (``search_samples``); None: always on every sample.
    ``lanes``: how many searches run side by side (``search_lanes``; the results are the same with any number);
    None: ``default_lane_count()`` when at least ``LANE_SEARCH_ROWS`` samples are searched, one otherwise. With more
    than one (or, with None, from ``LANE_SEARCH_ROWS`` samples of the recording on, on a machine of two cores or more),
    the work before the first search uses a second thread too, and the process's threads allocate from one heap from
    then on (``heap_trim.share_one_heap``); with any, the heap takes arrays of up to 64 MiB and keeps their pages when
    they are freed (``heap_trim.keep_freed_pages``).

    It runs with one BLAS thread (``blas_threads``): its products of tall, narrow matrices gain nothing from more,
    and lose much when another process holds a core."""
    check_search_rows(search_rows)  # before seconds of work at 10^6 samples, not after
    return_free_memory()  # what the caller dropped (a simulation, an MCAP read), before the diagnosis's arrays are made
    keep_freed_pages()  # the searches' arrays reuse the pages of those they dropped (heap_trim)
    # a large recording's searches run side by side: until they start, the other core takes what it can
    side_by_side = (default_lane_count() > 1 and len(rec.t_s) >= LANE_SEARCH_ROWS) if lanes is None else int(lanes) > 1
    if side_by_side:
        share_one_heap()  # the threads allocate from the one heap (heap_trim)
    data = rec if isinstance(rec, DiagnosisData) else prepare_data(rec, static, beside_thread=side_by_side)
    groups = data.group

    def folds_and_constants() -> tuple[np.ndarray, list[str]]:
        """The folds and, on a thread of their own, the constants of the recording the first searches ask for
        (``DiagnosisData.once``)."""
        out = check_folds(data, groups, make_folds(groups, data.use, folds, seed))
        if side_by_side:
            for e in library:
                e.applicable(data)
            data.static_psi_map()
            data.run_steps()
        return out

    # beside the degree selection (when the searches will run side by side: the other core idles until then)
    folds_later = beside(folds_and_constants, thread=side_by_side)
    n_levels = data.temperature_level_count()
    try:
        sel_degree, degree_table = select_degree(data, max_degree)
    except Exception:
        folds_later.result()  # a recording the folds cannot be drawn on says so first
        raise
    fold, fold_notes = folds_later.result()
    if degree is not None:
        if degree >= n_levels:
            raise NotIdentifiedError(f"degree {degree} is not identified by {n_levels} temperature level(s)")
        sel_degree = degree
    c, s = temperature_scaling(data.temp_c[data.use])
    spec = ModelSpec(sel_degree, c, s)

    # declared model, noise floor and weights
    des0 = build_design(data, spec)
    cv0 = cross_validate(des0, data.use, fold, np.ones(3))
    rows = data.use & des0.valid & (data.pose_id >= 0)  # the floor: scatter within visits, not during moves
    res0 = des0.G - cv0.fitted_full
    settling_later = beside(settling_transient, res0, data.t_s, groups, rows, thread=side_by_side)
    # the rule of SETTLE_NOISE_FRACTION at either end; the floor it compares with is itself settled. A forced
    # settle_s fixes the start; the end is trimmed only where it is measured disturbed
    auto_start = settle_s is None
    settle_s = 0.0 if settle_s is None else float(settle_s)

    def floor(start_s: float, stop_s: float | None) -> tuple[float, float | None, VisitNoise]:
        return start_s, stop_s, within_visit_noise(res0, groups, settled_mask(data.t_s, groups, rows, start_s, stop_s),
                                                   data.t_s)

    # the last floor worked out, at (settle_s, end_s): meanwhile the transient is measured, the first one with the end
    # kept (as it is unless the end is disturbed)
    floor_at: tuple[float, float | None, VisitNoise] | None = floor(settle_s, None) if side_by_side else None
    settling = settling_later.result()
    end_s = 0.0 if settling.end_detected else None
    for _ in range(4):
        if not auto_start and end_s is None:
            break
        if floor_at is None or floor_at[:2] != (settle_s, end_s):
            floor_at = floor(settle_s, end_s)
        sigma = floor_at[2].sigma
        grew = False
        if auto_start and (nxt := settle_window(settling, sigma)) > settle_s * (1 + 1e-3):
            settle_s, grew = nxt, True
        if end_s is not None and (nxt := settle_window(settling, sigma, end=True)) > end_s * (1 + 1e-3):
            end_s, grew = nxt, True
        if not grew:
            break
    settled = settled_mask(data.t_s, groups, rows, settle_s, end_s)
    # the windows that did not grow are those of the last floor worked out: that floor, not the same one again
    noise_model = (floor_at[2] if floor_at is not None and floor_at[:2] == (settle_s, end_s)
                   else within_visit_noise(res0, groups, settled, data.t_s))
    noise = noise_model.sigma
    if not np.all(np.isfinite(noise)) or np.any(noise <= 0):
        raise ValueError(f"no noise floor: {int(settled.sum())} settled samples (every visit shorter than "
                         f"{settle_s:.3g} s plus one sample?); lower settle_s")
    # a periodic disturbance during the visits (a table that sways, a fan) is no noise of the sensor: named, and the
    # floor is the scatter without it (its floor with it reported beside: PeriodicDisturbance.floor_with_lines)
    disturbance = find_periodic_disturbance(res0, data.t_s, groups, data.run_id, settled)
    if disturbance.found:
        disturbance.floor_with_lines = noise
        noise_model = within_visit_noise(res0 - disturbance.model(data.t_s, data.run_id), groups, settled, data.t_s)
        noise = noise_model.sigma
    settling.settle_s, settling.n_dropped = float(settle_s), int((rows & ~settled).sum())
    settling.end_settle_s = end_s
    settling.end_n_dropped = int((settled_mask(data.t_s, groups, rows, settle_s) & ~settled).sum())
    # what may still reach the floor: the decay at the window's edge, for an unresolved one (window: the first, or
    # last, sample) its bound at the next position, the first kept
    if settling.detected and np.isfinite(settling.tau_s) and settling.tau_s > 0:
        kept = _first_kept_age(settle_s, settling.tau_resolved, settling.age_s)
        settling.residual_after_settle_mps2 = settling.amplitude_mps2 * np.exp(-max(kept, 1e-12) / settling.tau_s)
    if end_s is not None and np.isfinite(settling.end_tau_s) and settling.end_tau_s > 0:
        kept = _first_kept_age(end_s, settling.end_tau_resolved, settling.end_age_s)
        settling.end_residual_after_settle_mps2 = (settling.end_amplitude_mps2
                                                   * np.exp(-max(kept, 1e-12) / settling.end_tau_s))
    weights = 1.0 / np.maximum(noise, 1e-12) ** 2
    fit_rows = data.use & (fold != -1)  # fitted (also the visits never held out, fold -2)
    # a search thinned to fewer rows keeps most of what a visit's samples tell of its mean (the noise is correlated)
    fitted_per_visit = np.bincount(groups[fit_rows & (groups >= 0)], minlength=1)
    fitted_per_visit = fitted_per_visit[fitted_per_visit > 0]
    every, step, kept = search_samples(fit_rows, fold, search_rows, noise_model,
                                       float(np.median(fitted_per_visit)) if fitted_per_visit.size else math.inf)
    thinned = step > 1
    # where the candidates are evaluated and the model chosen; a thinned search's corrected reference is small
    # beside the correction of the whole series it saves: it keeps a search's grid of them for the next model
    sel = Evaluator(data, fold, weights, groups, every, references=24 if thinned else 4)
    n_lanes = (default_lane_count() if len(every) >= LANE_SEARCH_ROWS else 1) if lanes is None else int(lanes)
    # the heap's free pages given back after each batch of searches side by side: what each search made and dropped
    searchers = Lanes([sel] + [sel.lane() for _ in range(n_lanes - 1)], after_map=return_free_memory)
    residual_before = cv0.heldout
    fitted_all = cv0.fitted_full  # the current model's in-sample fit on all samples (the cross-correlation delay)
    base_coefficients: np.ndarray | None = None  # the current model's coefficients when fitted_all is not worked out
    del cv0
    des_s, cv_s = sel.cv(spec)
    base_heldout, base_fitted, base_G = cv_s.heldout, cv_s.fitted_full, des_s.G
    del des_s, cv_s, des0  # the declared model's design matrix (N x p) is not needed again

    steps: list[StepResult] = []
    detection_limit = ""
    time_folds: np.ndarray | None = None  # contiguous blocks of time (time_block_check), made when first needed
    step_confounded: dict[str, str] = {}  # a candidate that a step of the response fits as well: the warning
    reselect_up_to = max_degree if degree is None and n_levels >= 2 else None  # eq. 28's degree is chosen again
    remaining = [e for e in library]
    reading_jumped = bool(data.temperature_jumps) and n_levels >= 2  # eq. 28 reads a reading that jumps
    seconds: dict[str, float] = {}  # what each candidate's evaluation took (the order they start in: Lanes.map)
    while remaining and len(spec.effects) < max_effects:
        # Bonferroni over the candidates the data can show at all (known before any is evaluated)
        alpha_each = alpha / max(sum(e.applicable(data)[0] for e in remaining), 1)
        # the channel delay's cross-check, of the current model alone, worked out beside the searches (its fit (N, 3) is
        # let go once it is done)
        xcorr_later = None
        if any(e.name == "channel_delay" and e.applicable(data)[0] for e in remaining):
            xcorr_later = beside(cross_correlation_delay, data, fitted_output(data, spec, base_coefficients)
                                 if fitted_all is None else fitted_all, thread=n_lanes > 1)
        fitted_all = None
        # the candidates side by side, each on a free lane (their results do not depend on which, or in what order)
        # the longest first (what each took at the step before; one worked out by the confounding check is remembered)
        results = searchers.map(partial(_evaluate_on, spec, base_heldout, base_fitted, base_G, alpha_each, seconds),
                                remaining, None if progress is None else lambda r: progress(r.name),
                                cost=lambda e, model=spec, ev=sel: 0.0 if ev.remembers(model, e) else seconds.get(e.name, 0.0))
        for r in results:
            if r.name == "channel_delay" and r.applicable and xcorr_later is not None:
                r.cross_correlation_delay_s = xcorr_later.result()
        tested = [r for r in results if r.applicable]
        n_vis = max((r.n_groups for r in tested), default=0)
        if not steps and tested and 0.5 ** n_vis >= alpha_each:
            detectable = [r.detectable_gain for r in tested if np.isfinite(r.detectable_gain)]
            detection_limit = (f"this campaign has {n_vis} visits: the one-sided signed-rank test over visits cannot "
                               f"go below p = 2^-{n_vis} = {0.5 ** n_vis:.2g}, above the {alpha_each:.2g} each "
                               f"candidate needs (alpha {alpha:g} over {len(tested)} candidates); at least "
                               f"{math.ceil(-math.log2(alpha_each)) + 1} visits are needed for it (repeat the poses, "
                               "or visit more orientations). "
                               + (f"Candidates are tested with a one-sided paired t-test over the visits instead (df "
                                  f"{n_vis - 1}; it assumes normally distributed per-visit differences): with the "
                                  f"scatter of these visits the smallest held-out gain it detects with 80 % power is "
                                  f"{100 * min(detectable):.3g} % (median over the candidates "
                                  f"{100 * float(np.median(detectable)):.3g} %)" if detectable else
                                  "Too few visits for a paired t-test as well: no effect can be added whatever its size"))
        for r in tested:
            r.significant = r.p_value < alpha_each and r.rel_gain >= min_rel_gain and not r.implausible
            eff_r = next(e for e in remaining if e.name == r.name)
            if r.significant and eff_r.void(r.hyper):
                r.significant = False  # its value on all samples changes nothing: there is nothing to add
                r.detail += "; not added: its value on all samples changes nothing"
            if r.significant and eff_r.follows_a_step and reading_jumped:
                # a jump of the temperature reading moves eq. 28's output once, which this candidate can follow: what it
                # would write is the reading's fault, not the sensor's (test_a_fault_of_the_temperature_reading_...)
                r.significant = False
                r.detail += ("; not added: the AHT10 reading jumps (a sensor re-seated, a spike, a frozen reading), "
                             "and eq. 28 evaluated at it moves the output once, which this candidate can follow")
            if r.significant and eff_r.time_function:
                if time_folds is None:
                    time_folds = check_folds(data, groups, make_folds(groups, data.use, folds, time_blocks=True))[0]
                g, p = r.time_block = time_block_check(data, spec, eff_r, r.hyper, every, time_folds, weights, alpha_each)
                if p < alpha_each and g >= min_rel_gain:
                    r.detail += f"; it also predicts contiguous blocks of time held out (gain {100 * g:+.1f} %, p = {p:.2g})"
                else:
                    r.significant = False
                    r.detail += (f"; not added: it does not predict contiguous blocks of time held out (gain "
                                 f"{100 * g:+.1f} %, p = {p:.2g}): it follows a slow wander of the residual between "
                                 "visits, not a drift it can extrapolate")
            step_confounded.pop(r.name, None)  # the last step's word on it
            if r.significant and eff_r.follows_a_step and eff_r.time_function:
                judge_step(searchers, spec, r, eff_r, alpha_each, min_rel_gain, reselect_up_to, step_confounded)
        results.sort(key=lambda r: (not r.applicable, -r.rel_gain))
        # a function of the temperature's history is set against the step when it is about to be added (the best
        # significant candidate left), not at every step it is significant at: on a cycled run it is significant at
        # most steps, and each check searches the step's time twice. Whatever is added has passed it.
        checked: set[str] = set()
        while (best := next((r for r in results if r.significant), None)) is not None and best.name not in checked:
            checked.add(best.name)
            eff_b = next(e for e in remaining if e.name == best.name)
            if eff_b.follows_a_step and not eff_b.time_function:
                judge_step(searchers, spec, best, eff_b, alpha_each, min_rel_gain, reselect_up_to, step_confounded)
        sig = [r for r in results if r.significant]
        conf = _confounding(searchers, spec, sig, alpha_each, min_rel_gain, library) if len(sig) >= 2 else []
        chosen = sig[0].name if sig else None
        for r in results:  # per-sample arrays (N, 3) are kept only where the report plots them: first step's deltas
            r.delta, r.delta_rows = (None, None) if steps else (r.delta, sel.sub)
        steps.append(StepResult(len(steps) + 1, spec.names, results, chosen, alpha_each, conf))
        if chosen is None:
            break
        eff = next(e for e in remaining if e.name == chosen)
        spec = spec.plus(eff, sig[0].hyper)
        remaining = [e for e in remaining if e.name != chosen]
        if degree is None and n_levels >= 2:  # with one level only degree 0 is identified: nothing to re-select
            was = spec.degree
            spec, steps[-1].degree_table, notes = reselect_degree(searchers, spec, max_degree)
            steps[-1].degree_after = spec.degree
            steps[-1].degree_note = (f"degree of eq. 28 re-selected with {chosen} in the model: "
                                     + (f"{was} -> {spec.degree}" if spec.degree != was else f"{was}, unchanged")
                                     + "".join(f"; {n}" for n in notes))
        des_c, cv_c = sel.cv(spec)
        searchers.each(lambda ev, model=spec: ev.forget(model))
        return_free_memory()  # what the step's searches dropped, before the next step's are made
        base_heldout, base_fitted, base_G = cv_c.heldout, cv_c.fitted_full, des_c.G
        base_coefficients = cv_c.A_full
        del des_c, cv_c  # the design (n x p) is not held beyond the evaluator's own caches

    # final model, built once the caches of the search are let go
    n_search = len(sel.folds) if thinned else None
    del sel, searchers
    data.drop_recent()
    return_free_memory()  # the search's corrected series and designs, before the final design (N x p) is built
    des_f = build_design(data, spec)  # no cache: written straight into its design
    cv_f = cross_validate(des_f, fit_rows, fold, weights)
    rows_f = data.use & des_f.valid & (fold >= 0)
    confounded = {st.chosen: [c.b if c.a == st.chosen else c.a for c in st.confounding
                              if c.verdict == "confounded" and st.chosen in (c.a, c.b)] for st in steps if st.chosen}
    confounded = {k: v for k, v in confounded.items() if v}
    cal, base_cal, added = _calibration_from(spec, des_f, cv_f, data, noise, sensor_id, confounded)
    remedy_names = {e.name for e, _ in spec.effects if e.noise_remedy}
    per_run_names = {e.name for e, _ in spec.effects if e.per_run}
    remedies = [a for a in added if a[0] in remedy_names]
    run_terms = [a for a in added if a[0] in per_run_names]
    added = [a for a in added if a[0] not in remedy_names | per_run_names]
    noise_after, noise_model_after = noise, noise_model
    if remedies:  # the filtered output is less noisy: its own floor, on the same settled samples
        res_f = des_f.G - cv_f.fitted_full
        if disturbance.found:  # the filtered output carries the lines too (refitted on it)
            res_f -= disturbance.refit(res_f, data.t_s, groups, data.run_id, settled & rows_f)
        noise_model_after = within_visit_noise(res_f, groups, settled & rows_f, data.t_s)
        del res_f
        noise_after = noise_model_after.sigma
        cal.noise_sigma_mps2 = noise_after
    # the driver's path over every sample, worked out meanwhile the rest
    calibrated_later = beside(_calibrated, cal, data, thread=n_lanes > 1)  # its result: after the held codes
    fitted_sensor = cv_f.fitted_full.copy()  # what the calibration file reproduces: without the per-run terms
    for name in per_run_names:
        sl = des_f.blocks[name]
        fitted_sensor -= des_f.X[:, sl] @ cv_f.A_full[sl]
    floor_note = _flagged_visits_note(data, groups, [noise_model] + ([noise_model_after] if remedies else []),
                                      des_f, cv_f, fit_rows, rows_f, fold, weights)
    G_f, blocks_f = des_f.G, des_f.blocks
    del des_f  # its design matrix (N x p) is let go once cv_f's held-out residual is worked out (r_eval below)
    r_eval = rows_f & finite_rows(residual_before) & finite_rows(cv_f.heldout)
    before_ho = np.sqrt(np.mean(residual_before[r_eval] ** 2, axis=0))
    after_ho = np.sqrt(np.mean(cv_f.heldout[r_eval] ** 2, axis=0))
    before_in = np.sqrt(np.mean(res0[r_eval] ** 2, axis=0))
    after_in = np.sqrt(np.mean((G_f - cv_f.fitted_full)[r_eval] ** 2, axis=0))
    structure = residual_structure(data, cv_f.heldout, r_eval, groups, noise_model_after, alpha)
    warnings = [detection_limit] if detection_limit else []
    warnings += [w for name, w in step_confounded.items() if name in spec.names]
    # an added function of the orientation with a residual left that is not one (visits of one direction disagree), and
    # not small (the slow part of the noise, bias instability between visits minutes apart, makes a small one common)
    table_axes = [a for j, a in enumerate("xyz") if structure.pose_chi2_p[j] < alpha / 3
                  and structure.other_pose_chi2_p[j] < alpha / 3 and structure.ratio[j] > SMALL_RATIO]
    for e, _ in spec.effects:
        if e.orientation_function and table_axes:
            warnings.append(f"{e.name} is a function of the orientation, but what remains on {'/'.join(table_axes)} "
                            "differs between the poses of one direction of gravity (p "
                            + ", ".join(f"{structure.other_pose_chi2_p['xyz'.index(a)]:.1e}" for a in table_axes)
                            + "): on a plan whose directions and table angles go together it may stand in for an "
                            "effect of the table's angles (a cable the table drags, the table's geometry) that is "
                            "no property of the sensor; turn the sensor by 90 degrees on the table and compare")
    if floor_note:
        warnings.append(floor_note)
    if disturbance.found:
        lines_ho = disturbance.refit(cv_f.heldout, data.t_s, groups, data.run_id, settled & r_eval)
        disturbance.heldout_without_lines = np.sqrt(np.mean((cv_f.heldout - lines_ho)[r_eval] ** 2, axis=0))
        del lines_ho
        warnings.append(disturbance_warning(disturbance, noise, after_ho))
    held = held_codes(np.column_stack([data.ref, data.xyz]), groups, settled & r_eval,
                      _visit_offset(cv_f.heldout, groups, r_eval, noise_after), alpha)
    for h in held:
        means = np.array([cv_f.heldout[r_eval & (groups == v)].mean(axis=0) for v in h.visits])
        h.worst_offset = means[np.argmax(np.abs(means), axis=0), np.arange(3)]
        rest = r_eval & ~np.isin(groups, h.visits)
        h.rmse_without = np.sqrt(np.mean(cv_f.heldout[rest] ** 2, axis=0))
        warnings.append(h.sentence())
    calibrated = calibrated_later.result()  # what needs the calibration file's output, once the rest is done
    consistency = _consistency(calibrated, fitted_sensor, rows_f)
    moving = _moving_residual(data, calibrated)
    del calibrated, fitted_sensor
    if settling.end_detected:
        warnings.append(settling.end_summary() + "; the model is fitted on them too: align the table's readings "
                        "(pose labels, reference) with the signal")
    warnings += reference_reach_warnings(_visit_reference_range(data, groups, r_eval))
    if data.low_reference_note:
        warnings.append(data.low_reference_note)
    if data.temperature_jumps:
        warnings.append(jump_warning(data.temperature_jumps, n_levels >= 2))
    if data.n_clipped_visits:
        warnings.append(f"{data.n_clipped_samples} samples of {data.n_clipped_visits} visit(s) left out: a channel "
                        "clipped at a rail of the ADC (an axis at 0 or 4095 counts, or the reference at 4095) in each; a "
                        "clipped reading bounds the signal instead of measuring it (lower the source power or the "
                        "gain if the signal sits at the rail)")
    cond, column_corr = gram_conditioning(cv_f.sums.XtX, cv_f.sums.xsum, len(cv_f.sums.idx), blocks_f)
    for name, c in column_corr.items():
        if c > COLLINEAR_CORR:
            warnings.append(f"a column of {name} correlates at |r| = {c:.4f} with another column of the model: their "
                            "coefficients are not separately determined (large terms that cancel), whatever the "
                            "held-out gain")
    below = after_ho < 0.9 * noise_after
    if np.any(below):
        warnings.append("held-out error below the noise floor on axis " + ", ".join(a for a, b in zip("xyz", below, strict=True)
                        if b) + f" ({_fmt3(after_ho)} against {_fmt3(noise_after)} m/s^2): a model cannot predict "
                        "held-out data better than the data repeat themselves, so the floor or the model is wrong "
                        "(an added term that removes noise instead of an effect?)")
    time_label = time_axis_label(rec.metadata) if isinstance(rec, Recording) else "time [s]"
    if time_label == "time [s]":  # the report's times start at the first sample (residual_structure)
        time_label = "time from the first sample [s]"
    return DiagnosisResult(
        data=data, degree=sel_degree, degree_table=degree_table, n_levels=n_levels, noise_floor=noise,
        before_heldout_rmse=before_ho, before_insample_rmse=before_in, after_heldout_rmse=after_ho,
        after_insample_rmse=after_in, steps=steps, added=added, calibration=cal, base_calibration=base_cal,
        residual_before=residual_before, residual_after=cv_f.heldout, structure=structure,
        consistency_max_abs_mps2=consistency, n_static=int(r_eval.sum()), n_groups=len(np.unique(groups[r_eval])),
        moving_residual_rms=moving, settling=settling, fold_notes=fold_notes, n_floor_samples=int(settled.sum()),
        noise_remedies=remedies, noise_floor_after=noise_after if remedies else None, warnings=warnings,
        condition_number=cond, column_correlation=column_corr, final_degree=spec.degree, run_terms=run_terms,
        held_codes=held, disturbance=disturbance,
        settings={"static": static if not isinstance(rec, DiagnosisData) else "given", "folds": int(fold.max()) + 1,
                  "alpha": alpha, "min_rel_gain": min_rel_gain, "max_effects": max_effects, "seed": seed,
                  "search_rows": n_search, "search_step": step, "search_information": kept,
                  "degree_forced": degree is not None,
                  "settle_s": settle_s,
                  "time_label": time_label})


def disturbance_warning(d: PeriodicDisturbance, floor: np.ndarray, heldout: np.ndarray) -> str:
    """The warning for a periodic disturbance found in the visits: what, the floor with and without it (m/s^2), what
    the held-out error ``heldout`` (3,) m/s^2 is with and without it, and the basis of the ratios."""
    return (f"{d.summary()}. The noise floor {_fmt3(floor)} m/s^2 is the scatter within visits without the disturbance "
            f"(with it {_fmt3(d.floor_with_lines)}); the held-out error {_fmt3(heldout)} m/s^2 holds it "
            f"({_fmt3(d.heldout_without_lines)} without it), so the ratios to the floor count it as a residual of this "
            "recording, not of the sensor: find what shook the table or chamber, and record again")


def _flagged_visits_note(data: DiagnosisData, groups: np.ndarray, models: list[VisitNoise], des: Design, cv: CvResult,
                         fit_rows: np.ndarray, rows: np.ndarray, fold: np.ndarray, weights: np.ndarray) -> str:
    """The warning for the visits left out of the noise floor (``VisitNoise.flagged``), "" without any.

    They stay in the fit (no data is dropped behind the user's back); the warning says by how much they move it:
    the final model refitted once without them, the largest change of its fitted output on the other visits'
    samples per axis."""
    seen: dict[int, np.ndarray] = {}
    for m in models:
        for g, scatter, _ in m.flagged:
            seen[g] = np.maximum(seen.get(g, scatter), scatter)
    if not seen:
        return ""
    labels = np.array(sorted(seen))
    bad = np.isin(groups, labels)
    names = []
    for g in labels:
        at = np.flatnonzero((groups == g) & (data.pose_id >= 0))
        if not at.size:
            at = np.flatnonzero(groups == g)
        names.append(f"pose {int(data.pose_id[at[0]])} (run {int(data.run_id[at[0]])}, t {data.t_s[at[0]]:.1f}-"
                     f"{data.t_s[at[-1]]:.1f} s) {_fmt3(seen[g])} x floor")
    try:
        with np.errstate(all="ignore"):
            moved = des.X @ (cross_validate(des, fit_rows & ~bad, fold, weights).A_full - cv.A_full)
        other = rows & ~bad & finite_rows(moved)
        shift = (f"leaving them out of the fit as well moves the fitted output on the other visits by up to "
                 f"{_fmt3(np.max(np.abs(moved[other]), axis=0))} m/s^2 (x/y/z)" if other.any() else
                 "no other visit to compare the fit without them on")
    except (np.linalg.LinAlgError, ValueError, IndexError):
        shift = "the model cannot be fitted without them"
    n_v = max(m.n_checked for m in models)
    return (f"{len(labels)} visit(s) left out of the noise floor, their scatter far beyond the other visits' (variance "
            f"over {FLOOR_VISIT_RATIO:g}x the visits' median and p < {FLOOR_VISIT_ALPHA:g} / (3 x {n_v} visits) each): "
            + "; ".join(names) + f". They stay in the fit: {shift}; a burst of outliers or a dead channel there? "
            "Cut that stretch and run again if the change matters")


def _visit_offset(res: np.ndarray, groups: np.ndarray, rows: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """(N,) for every sample of ``rows``: how far its visit's output is off, the squared norm of the visit's mean
    residual ``res`` (N, 3) over the noise ``floor`` (3,) m/s^2; NaN elsewhere."""
    out = np.full(len(groups), np.nan)
    idx = np.flatnonzero(rows)
    labels, inv = np.unique(groups[idx], return_inverse=True)
    n = np.bincount(inv, minlength=len(labels))
    mean = np.stack([np.bincount(inv, res[idx, j], minlength=len(labels)) for j in range(3)], axis=1) / n[:, None]
    out[idx] = np.sum((mean / np.maximum(floor, 1e-12)) ** 2, axis=1)[inv]
    return out


def _fmt3(v: np.ndarray) -> str:
    return " / ".join(f"{x:.3f}" for x in v)


def _confounding(lanes: Lanes[Evaluator], spec: ModelSpec, sig: list[CandidateResult], alpha_each: float,
                 min_rel_gain: float, library: tuple[Effect, ...]) -> list[Confounding]:
    """The candidate about to be added (``sig[0]``, the largest gain) against each of the next three significant
    ones: does each still gain on top of the other? (Pairs among the others are judged at the next step, on top
    of the one added, so they are not worked out here.) The searches of each on top of the other run side by side
    on ``lanes``."""
    lib = {e.name: e for e in library}
    out = []
    a = sig[0]
    ea = lib[a.name]
    ev = lanes.lanes[0]
    a_ho = ev.cv(spec.plus(ea, a.hyper), remember=True)[1].heldout  # the next step's starting model

    # each on top of the other (the added one's hyper-parameter searched again, nested), compared with the other
    # alone at its final hyper-parameter, as the forward selection does
    def on_top(lane: Evaluator, task: tuple[CandidateResult, bool]) -> tuple[np.ndarray, ...]:
        b, b_on_a = task
        eb = lib[b.name]
        if b_on_a:
            b_ho = lane.cv(spec.plus(eb, b.hyper))[1].heldout
            return b_ho, lane.fit_hyper(spec.plus(ea, a.hyper), eb, remember=True)[1]  # evaluated again next step
        return (lane.nested_heldout(spec.plus(eb, b.hyper), ea),)

    done = lanes.map(on_top, [(b, b_on_a) for b in sig[1:4] for b_on_a in (True, False)])
    for i, b in enumerate(sig[1:4]):
        (b_ho, ho_b_on_a), (ho_a_on_b,) = done[2 * i], done[2 * i + 1]
        rows = ev.rows.copy()
        for arr in (a_ho, b_ho, ho_b_on_a, ho_a_on_b):
            rows &= finite_rows(arr)
        g_b, p_b = paired_gain_test(a_ho, ho_b_on_a, ev.groups, rows, ev.weights, alpha_each)[:2]
        g_a, p_a = paired_gain_test(b_ho, ho_a_on_b, ev.groups, rows, ev.weights, alpha_each)[:2]
        r = rows & finite_rows(a.delta) & finite_rows(b.delta)
        cc = _corr((a.delta[r] * np.sqrt(ev.weights)).ravel(), (b.delta[r] * np.sqrt(ev.weights)).ravel())
        b_adds = p_b < alpha_each and g_b >= min_rel_gain
        a_adds = p_a < alpha_each and g_a >= min_rel_gain
        if a_adds and b_adds:
            verdict = "both"
        elif a_adds or b_adds:
            verdict = f"{a.name} explains {b.name}" if a_adds else f"{b.name} explains {a.name}"
        else:
            # neither adds beyond the other: does one fit significantly better head to head?
            g_ab, p_ab = paired_gain_test(b_ho, a_ho, ev.groups, rows, ev.weights, alpha_each)[:2]
            g_ba, p_ba = paired_gain_test(a_ho, b_ho, ev.groups, rows, ev.weights, alpha_each)[:2]
            if p_ab < alpha_each and g_ab >= min_rel_gain:
                verdict = f"{a.name} explains {b.name}"
            elif p_ba < alpha_each and g_ba >= min_rel_gain:
                verdict = f"{b.name} explains {a.name}"
            else:
                verdict = "confounded"
        out.append(Confounding(a.name, b.name, cc, p_b, p_a, verdict, g_b, g_a, separating_measurement(a.name, b.name)))
    return out


def _calibration_from(spec: ModelSpec, des: Design, cv: CvResult, data: DiagnosisData, noise: np.ndarray,
                      sensor_id: str, confounded: dict[str, list[str]] | None = None,
                      ) -> tuple[ThermalCalibration, ThermalCalibration, list[tuple[str, float | None, str]]]:
    n = spec.degree
    A = cv.A_full
    M, b = coefficients_to_model(A[: n_params(n)], n)
    t = data.temp_c[data.use]
    rng = (float(np.min(t)), float(np.max(t)))
    terms, added = [], []
    for eff, h in sorted(spec.effects, key=lambda eh: eh[0].stage):
        coeff = A[des.blocks[eff.name]].T if eff.name in des.blocks else None
        terms.extend(eff.make_terms(h, coeff, data))
        added.append((eff.name, h, eff.describe(h, coeff)))
    per_run = [e.name for e, _ in spec.effects if e.per_run]
    fit = {"tool": "fbg-accel-calib diagnose", "degree": n,
           "added_effects": [a[0] for a in added if a[0] not in per_run],
           "hyper_parameters": {a[0]: a[1] for a in added if a[0] not in per_run}}
    if per_run:  # fitted so that they do not bias eq. 28; the driver cannot apply them (it does not know runs)
        fit["per_run_terms_fitted_not_applied"] = per_run
    if confounded:
        fit["confounded_with"] = confounded
    delay = [h for e, h in spec.effects if e.name == "channel_delay"]
    if delay:
        fit["channel_delay_s"] = float(delay[0])  # applied to time stamps, not to accelerations
    # the reference counts the model holds at, per temperature level (the driver flags a reference far off them)
    labels, level_t = temperature_levels(t)
    ref_used = np.asarray(data.ref, dtype=float)[data.use]
    level_ref = np.array([ref_used[labels == k].mean() for k in range(len(level_t))])
    model = {"M": M, "b": b, "temperature_range_c": rng, "sensor_id": sensor_id, "t_center_c": spec.t_center_c,
             "t_scale_c": spec.t_scale_c, "noise_sigma_mps2": noise, "reference_level_temperature_c": level_t,
             "reference_level_counts": level_ref}
    return ThermalCalibration(**model, fit=fit, corrections=terms), ThermalCalibration(**model), added


def _visit_reference_range(data: DiagnosisData, groups: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(3, 2): lowest and highest visit-mean reference specific force (m/s^2) along each table axis over the visits of
    ``rows`` (the poses the calibration was fitted on; ``thermal_fit.reference_range`` takes cell means)."""
    g = visit_means(groups, rows & np.all(np.isfinite(data.gref), axis=1), data.gref)
    if not len(g):
        return np.full((3, 2), np.nan)
    return np.column_stack([g.min(axis=0), g.max(axis=0)])


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


APPLY_BLOCK = 1 << 17  # samples per call of apply_counts in _calibrated (bounds its temporaries)


def _calibrated(cal: ThermalCalibration, data: DiagnosisData) -> np.ndarray:
    """The calibration file's output (N, 3) m/s^2, table frame, on every sample: ``apply_counts`` streamed per run
    in blocks of ``APPLY_BLOCK`` samples with one state, as the driver runs it."""
    out = np.full((len(data.t_s), 3), np.nan)
    for idx in data.runs():
        run = np.arange(len(data.t_s))[idx]
        state = cal.new_state()
        for lo in range(0, len(run), APPLY_BLOCK):
            b = run[lo:lo + APPLY_BLOCK]
            out[b] = cal.apply_counts(data.ref[b], data.xyz[b], data.temp_c[b], data.t_s[b], state)
    return out


def _consistency(calibrated: np.ndarray, fitted: np.ndarray, rows: np.ndarray) -> float:
    """Max |calibration file's output - fit prediction| (both (N, 3)) over the static ``rows``."""
    return float(np.nanmax(np.abs(calibrated[rows] - fitted[rows]))) if rows.any() else 0.0


def _moving_residual(data: DiagnosisData, calibrated: np.ndarray) -> np.ndarray | None:
    """RMS (3,) of the calibration file's output ``calibrated`` (N, 3) minus the gap-filled reference on samples not
    used (moving, settling)."""
    m = ~data.use & finite_rows(data.gref_filled)
    if m.sum() < 3:
        return None
    d = calibrated[m] - data.gref_filled[m]
    d = d[finite_rows(d)]
    return np.sqrt(np.mean(d**2, axis=0)) if len(d) else None


def residual_structure(data: DiagnosisData, res: np.ndarray, rows: np.ndarray, groups: np.ndarray,
                       noise_model: VisitNoise, alpha: float = 0.01, ratio_limit: float = SMALL_RATIO) -> ResidualStructure:
    """Is there a significant residual left, and what does it depend on?

    Test: visit means of the held-out residual against what the noise alone gives, chi^2 with the variance of
    each visit's mean from the floor's own autocorrelation (``VisitNoise.mean_variance``: the same estimate as
    the floor, so that floor and test agree on what the noise is; a first-order count of effective samples from
    the lag-1 correlation counted 2-4 times too many for this noise and flagged clean data).
    Significant = p < ``alpha`` / 3 on some axis (Bonferroni over the axes): the test's answer, whatever the size.
    The size is reported beside it: a systematic residual does not average out as the per-sample noise does, so
    one well below the per-sample floor (held-out RMSE within ``ratio_limit`` x floor: "small") is still a residual
    the model lacks; the verdict then gives its pose-mean RMS and the visit that shows it most. The degrees of
    freedom nu of the floor's mean variance are taken as at least ``MIN_MEAN_DOF``: below it the F test could
    reject nothing at any size.
    """
    noise = noise_model.sigma
    r = rows & finite_rows(res)
    ug, inv = np.unique(groups[r], return_inverse=True)
    cnt = np.bincount(inv)
    x = res[r]
    means = np.stack([np.bincount(inv, weights=x[:, j]) / cnt for j in range(3)], axis=1)
    z = means / np.sqrt(np.maximum(noise_model.mean_variance(cnt), 1e-300))
    chi = np.sum(z**2, axis=0)
    # the variance of a visit mean is itself estimated (nu = noise_model.mean_dof degrees of freedom, a common factor
    # for every visit): chi / df is then F(df, nu) under the noise alone, the chi^2 law when it is known (nu = inf)
    dof = np.maximum(noise_model.mean_dof, MIN_MEAN_DOF)
    p = _visit_chi2_p(chi, len(ug), dof)
    ho = np.sqrt(np.mean(x**2, axis=0))
    ratio = ho / np.maximum(noise, 1e-12)
    excess = np.sqrt(np.maximum(ho**2 - noise**2, 0.0))
    sig_axis = p < alpha / 3.0  # Bonferroni over the axes: a recording of noise alone is called significant at alpha
    significant = bool(np.any(sig_axis))
    small = significant and not np.any(sig_axis & (ratio > ratio_limit))
    t_mean = np.bincount(inv, weights=data.t_s[r]) / cnt
    temp_mean = np.bincount(inv, weights=data.temp_c[r]) / cnt
    g_mean = np.stack([np.bincount(inv, weights=data.gref[r][:, j]) / cnt for j in range(3)], axis=1)
    corr_t = np.array([_spearman(t_mean, means[:, j]) for j in range(3)])
    corr_T = (np.array([_spearman(temp_mean, means[:, j]) for j in range(3)]) if np.ptp(temp_mean) > 0.05
              else np.full(3, np.nan))  # isothermal: no temperature dependence can be seen
    order = np.argsort(t_mean)
    serial = np.array([_corr(means[order[1:], j], means[order[:-1], j]) for j in range(3)])
    u = g_mean / np.maximum(np.linalg.norm(g_mean, axis=1, keepdims=True), 1e-12)
    Q = np.column_stack([np.ones(len(u)), u, u[:, 0] * u[:, 1], u[:, 0] * u[:, 2], u[:, 1] * u[:, 2],
                         u[:, 0] ** 2 - u[:, 1] ** 2, 3 * u[:, 2] ** 2 - 1])
    r2 = np.zeros(3)
    if len(u) > Q.shape[1] + 2:
        for j in range(3):
            coef = np.linalg.lstsq(Q, means[:, j], rcond=None)[0]
            tot = np.sum((means[:, j] - means[:, j].mean()) ** 2)
            r2[j] = 1 - np.sum((means[:, j] - Q @ coef) ** 2) / tot if tot > 0 else 0.0
    pose_of = np.zeros(len(ug), int)
    pose_of[inv] = data.pose_id[r]  # orientation of each visit (samples in motion: -1 may overwrite; fixed below)
    static_r = r & (data.pose_id >= 0)
    pose_of[np.searchsorted(ug, groups[static_r])] = data.pose_id[static_r]
    t0 = float(np.min(data.t_s))  # visits are placed from the first sample: a CSV may be timed in epoch seconds
    per_pose = [{"visit": int(ug[i]), "pose": int(pose_of[i]), "n": int(cnt[i]), "mean_mps2": means[i], "z": z[i],
                 "gref_mps2": g_mean[i], "t_s": float(t_mean[i] - t0), "temp_c": float(temp_mean[i])}
                for i in range(len(ug))]
    per_pose.sort(key=lambda d: -float(np.max(np.abs(d["z"]))))
    pose_rms = np.sqrt(np.mean(means**2, axis=0))
    if significant:
        axes = [a for j, a in enumerate("xyz") if sig_axis[j]]
        verdict = (f"significant unexplained residual on axis {', '.join(axes)}: held-out RMSE "
                   + ", ".join(f"{a} {ho[j]:.3g} m/s^2 = {ratio[j]:.2f}x floor" for j, a in enumerate("xyz"))
                   + f"; pose means differ beyond noise (chi^2 p = {', '.join(f'{v:.1e}' for v in p)})")
        for j in np.flatnonzero(sig_axis & (ratio <= ratio_limit)):  # significant but small: its size, its place
            top = max(per_pose, key=lambda d, j=j: abs(float(d["z"][j])))
            verdict += (f"; small on {'xyz'[j]}: held-out RMSE within {ratio_limit:g}x the per-sample floor, but "
                        f"systematic (pose-mean RMS {pose_rms[j]:.3g} m/s^2 = {pose_rms[j] / max(noise[j], 1e-12):.2f}x "
                        f"floor, does not average out; largest at visit {top['visit']} (pose {top['pose']}, "
                        f"{top['t_s']:.0f} s from the first sample): {top['mean_mps2'][j]:+.3g} m/s^2, z = {top['z'][j]:+.1f})")
    else:
        verdict = ("no significant unexplained residual: held-out RMSE within "
                   + ", ".join(f"{ratio[j]:.2f}x" for j in range(3)) + " of the noise floor")
    lag1 = noise_model.acf[:, 1] if noise_model.acf.shape[1] > 1 else np.zeros(3)
    split = _direction_disagreement(means, noise_model.mean_variance(cnt), g_mean, t_mean, pose_of, dof)
    return ResidualStructure(significant, verdict, ho, noise, ratio, p, excess, per_pose, pose_rms, corr_t, corr_T, r2,
                             lag1, serial, noise_model.correlation_samples, dof, small, *split)


def _visit_chi2_p(chi: np.ndarray, df: int, dof: np.ndarray) -> np.ndarray:
    """p (3,) of ``chi`` (3,), a sum of ``df`` squared visit means over their variance under the noise alone: chi / df
    is F(df, ``dof``) when that variance is estimated with ``dof`` (3,) degrees of freedom, chi^2(df) when known (inf)."""
    return np.where(np.isfinite(dof), stats.f.sf(chi / df, df, np.where(np.isfinite(dof), dof, 1.0)),
                    stats.chi2.sf(chi, df=df))


def _direction_disagreement(means: np.ndarray, var: np.ndarray, g_mean: np.ndarray, t_mean: np.ndarray,
                            pose: np.ndarray, dof: np.ndarray) -> tuple[np.ndarray, int, float, np.ndarray, np.ndarray,
                                                                     float]:
    """Do visits of one direction of gravity disagree beyond the noise? ``means`` (V, 3) visit means of the residual
    (m/s^2) with variances ``var`` (V, 3) under the noise alone, ``g_mean`` (V, 3) their mean reference, ``t_mean``
    (V,) their mean time (s), ``pose`` (V,) their pose ids, ``dof`` (3,) degrees of freedom of ``var``. Each
    direction's visits about their weighted mean: chi^2 over the directions visited more than once, df = visits -
    directions, referred to F(df, dof) like the test of the visit means. A model of the sensor maps one direction of
    gravity to one output, so whatever these visits disagree by is not a function of the orientation. The chi^2 splits
    exactly (weighted means) into the visits of one pose id about their pose's mean (the same table angles: only time
    sets them apart) and the poses' means about their direction's (other table angles, or time). Returns (p (3,),
    visits in repeated directions, median time span of those directions (s), p (3,) within poses, p (3,) between the
    poses of a direction, median time span of the poses visited more than once (s))."""
    ones = np.ones(3)

    def f_test(chi: np.ndarray, df: int) -> np.ndarray:
        return _visit_chi2_p(chi, df, dof) if df >= 1 else ones.copy()

    label = direction_labels(g_mean)
    counts = np.bincount(label)
    rep = counts[label] >= 2
    if int(rep.sum() - np.sum(counts >= 2)) < 1:
        return ones.copy(), 0, 0.0, ones.copy(), ones.copy(), 0.0
    w = 1.0 / np.maximum(var[rep], 1e-300)
    m, t = means[rep], t_mean[rep]
    d = np.unique(label[rep], return_inverse=True)[1]
    dp = np.unique(np.column_stack([d, pose[rep]]), axis=0, return_inverse=True)[1].reshape(-1)

    def centre(lab: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(lab, weights=w[:, j] * m[:, j]) / np.bincount(lab, weights=w[:, j])
                         for j in range(3)], axis=1)

    c_d, c_dp = centre(d), centre(dp)
    total = np.sum(w * (m - c_d[d]) ** 2, axis=0)
    within = np.sum(w * (m - c_dp[dp]) ** 2, axis=0)
    n_d, n_dp = np.bincount(d), np.bincount(dp)
    df_total = int(len(m) - len(n_d))
    df_within = int(len(m) - len(n_dp))
    spans = [float(np.ptp(t[d == c])) for c in range(len(n_d))]
    pose_spans = [float(np.ptp(t[dp == c])) for c in np.flatnonzero(n_dp >= 2)]
    return (f_test(total, df_total), int(rep.sum()), float(np.median(spans)), f_test(within, df_within),
            f_test(np.maximum(total - within, 0.0), df_total - df_within),
            float(np.median(pose_spans)) if pose_spans else 0.0)


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return 0.0
    return float(stats.spearmanr(a, b).statistic)
