"""Library of candidate physical effects the declared model (paper eq. 28) may lack (pure numpy).

Each candidate is a physical hypothesis with its own regressors and, where the effect is
non-linear in a parameter, one hyper-parameter found by a 1-D search (grid, then bounded refine):

* ``reference_dark_offset``: offset d on the reference detector and offsets on the axis channels;
  Psi = xyz / (ref - d) plus a regressor 1/(ref - d). Hyper: d (counts).
* ``thermal_lag``: eq. 28 evaluated at a lagged (tau > 0) or leading (tau < 0) temperature. Hyper: tau (s).
* ``spectral_nonlinearity``: quadratic and cross terms of Psi (6 regressors). No hyper.
* ``time_drift``: linear creep t and warm-up exp(-t/tau). Hyper: tau (s).
* ``channel_delay``: the sensor channels lag the table reference by D; the reference is
  re-aligned to t - D. Hyper: D (s), bracketed by the cross-correlation of the calibrated output
  with the reference (D'Emilia et al. 2019, finddelay).
* ``tia_lowpass``: first-order TIA low-pass of the axis channels (Table 1 cut-off ratios); the
  noise-free expected Psi of the reference is passed through the filters and mapped back, i.e. the
  reference is filtered like the signal. Hyper: scale of the Table 1 time constants.
* ``thermal_hysteresis``: bias of opposite sign on heating and cooling branches. Hyper: the time
  constant of the rate filter that decides the branch (s).
* ``run_offset`` / ``run_drift``: each run (file, temperature level) has its own bias offset / its own linear
  drift in time. Properties of the recordings, not of the sensor: fitted so that they do not bias
  eq. 28, reported, never written to the calibration (the driver cannot know runs). No hyper.

The regressors are built with the same code as the run-time terms in
``fbg_accel_driver.correction_terms``, so a fitted candidate becomes declared terms that the
driver evaluates identically. The rationale of every candidate is in ``docs/effects.md``.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fbg_accel_driver.correction_terms import (
    ChainDynamics,
    ChannelOffset,
    ReferenceDarkOffset,
    ReferenceLowpass,
    SampleSteps,
    SpectralNonlinearity,
    ThermalHysteresis,
    ThermalLag,
    TimeDrift,
    first_order_lowpass,
    quadratic_features,
    sample_steps,
)
from fbg_accel_driver.sensor_constants import STANDARD_GRAVITY

# Table 1 of the paper: TIA cut-off frequencies (Hz) of ref, x, y, z (static-test build).
TIA_CUTOFF_HZ = np.array([1.0, 1.7, 1.3, 1.3])
TIA_TAU_S = 1.0 / (2.0 * np.pi * TIA_CUTOFF_HZ)
AHT10_RESOLUTION_C = 0.01  # paper §3.6
# The searches over the chain's times reach at least these, whatever the sample rate (at 100 Hz and below their
# grids in samples reach further): a channel delay of 100 ms, TIA time constants 3 x Table 1.
MIN_DELAY_SEARCH_S = 0.1
MIN_TIA_SCALE_SEARCH = 3.0
# Plausibility bounds of fitted effects: a fit beyond them is refused, never written to the YAML.
# The reference of a training set must span the table frame: the weakest direction of its visit-mean reference
# (smallest standard deviation, m/s^2) must keep this fraction of the whole data's (diagnose.check_folds; each side of
# a step, ResponseStepEffect.sides_span)
MIN_SPAN_FRACTION = 0.1
MAX_CHANNEL_OFFSET_FRACTION = 0.25  # axis-channel offset / the channel's mean counts: dark current + ADC zero
# offset are tens of counts (sim_default.yaml, reference_dark_offset); a quarter of the signal undoes eq. 24
MAX_DRIFT_MPS2 = 0.05 * 20.0 * 9.80665  # warm-up amplitude or creep over the run: 5 % of full scale (1 g)
# A function of board time shared by the runs (time_drift) is told from an effect of the orientation only by visits of
# one orientation at different board times: above this share of the visits' board-time variance explained by their
# orientation it is not testable (``orientation_share_of_visit_times``)
MAX_TIME_ORIENTATION_SHARE = 0.99


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

    _memo: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)
    _recent: OrderedDict[tuple, np.ndarray] = field(default_factory=OrderedDict, init=False, repr=False, compare=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False, compare=False)

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

    def once(self, key: str, compute: Callable[[], Any]) -> Any:
        """``compute()`` the first time ``key`` is asked for, the kept value after (a constant of the recording). Two
        searches that run side by side (``search_lanes``) and ask at once may both compute it; the first kept is the
        one both get."""
        if key not in self._memo:
            return self._memo.setdefault(key, compute())
        return self._memo[key]

    def recent(self, key: tuple, compute: Callable[[], np.ndarray], keep: int = 4) -> np.ndarray:
        """``compute()`` (an array that depends on the recording and ``key`` alone, made read-only), kept for the
        next ``keep`` distinct keys: a correction that a search repeats unchanged on every trial (the thermal lag
        of the model while another effect is searched) is worked out once (by lanes side by side: as ``once``)."""
        with self._lock:
            hit = self._recent.get(key)
            if hit is not None:
                self._recent.move_to_end(key)
                return hit
        value = compute()
        value.flags.writeable = False
        with self._lock:
            hit = self._recent.setdefault(key, value)
            self._recent.move_to_end(key)
            while len(self._recent) > keep:
                self._recent.popitem(last=False)
        return hit

    def drop_recent(self) -> None:
        """Forget what :meth:`recent` keeps (when no search follows)."""
        self._recent.clear()

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
        d = np.diff(self.t_s)
        d = d[d > 0]
        return float(np.median(d)) if d.size else 1.0

    @property
    def duration_s(self) -> float:
        return float(np.ptp(self.t_s)) if self.t_s.size else 0.0

    def temperature_level_count(self) -> int:
        """Temperature levels among the fitted samples (``thermal_fit.temperature_levels``), at least 1: eq. 28's
        degree is below it, so with one level the model has no temperature term."""
        from .thermal_fit import temperature_levels

        # asked by every candidate's ``applicable`` at every step: clustered once per recording
        return self.once("temperature_level_count", lambda: max(len(temperature_levels(self.temp_c[self.use])[1]), 1))

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


def take_rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``a[idx]`` for integer indices ``idx`` (``np.take`` along the first axis, the same values): numpy's fancy
    indexing copies the rows of an (N, 3) array one by one, about three times slower at 10^5 rows of 10^6."""
    return np.take(a, idx, axis=0)


def interp_columns(x: np.ndarray, xp: np.ndarray, fp: np.ndarray, block: int = 1 << 16) -> np.ndarray:
    """``np.interp(x, xp, fp[:, j])`` (len(x), k) for every column j of ``fp`` (len(xp), k) at once, the same values
    bit for bit: ``x`` is looked up in ``xp`` (increasing) once for the k columns, where ``np.interp`` looks it up
    again for each (the channel delay's search interpolates the three reference axes at the same times on every
    trial). As ``np.interp``: below ``xp[0]`` the first row, from ``xp[-1]`` on the last, at a point of ``xp`` its
    row, else the slope of the interval times the distance from its left end plus its left value (from the right
    end where that is NaN); NaN where ``x`` is (but for a single point). Worked out ``block`` values at a time
    (bounded temporaries)."""
    x = np.asarray(x, dtype=float)
    out = np.empty((len(x), fp.shape[1]))
    n = len(xp)
    for lo in range(0, len(x), block):
        xs = x[lo:lo + block]
        j = np.searchsorted(xp, xs, side="right") - 1
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
        at = (j >= n - 1) | (xs == x0)  # from the last point on, or at a point of xp: its row
        part[at] = take_rows(fp, np.minimum(j[at], n - 1))
        part[j < 0] = fp[0]
        if n >= 2:  # (np.interp gives a single point's row even at NaN)
            part[np.isnan(xs)] = np.nan
        out[lo:lo + block] = part
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
        pick = take if take is not None else (lambda a: a[idx])
        return Inputs(pick(self.ref), pick(self.xyz), pick(self.temp_c), pick(self.t_s), pick(self.gref),
                      self.valid[idx], self.gref_moved, self.counts_changed, self.temp_changed,
                      np.asarray(idx) if self.index is None else self.index[idx])

    @property
    def sample_index(self) -> np.ndarray:
        """(n,) the sample index of each row in the recording."""
        return np.arange(len(self.t_s)) if self.index is None else self.index


MODEL_TERM = "model term"  # a term of eq. 28's calibration file, applied by the driver
NOISE_REMEDY = "noise remedy"  # a filter against noise, written to the calibration file, reported apart
PER_RUN = "per-run property"  # a property of each recording: fitted, reported, not in the calibration file
ROLES = (MODEL_TERM, NOISE_REMEDY, PER_RUN)


class Effect:
    """Base class of a candidate effect. Subclasses set the class attributes and override hooks."""

    name: str = ""
    stage: int = 0  # application order: input corrections first, additive terms after
    hyper_name: str | None = None
    hyper_unit: str = ""
    # value of the hyper-parameter that is the simpler variant of the effect (kept unless the data need another),
    # for an effect that is not void there (reference_dark_offset at d_ref = 0 keeps its channel offsets)
    hyper_null: float | None = None
    title: str = ""
    # what adding it means (``ROLES``): a term of the calibration file, a filter against noise reported apart from the
    # added effects, or a property of each recording (run_offset, run_drift) fitted so that it does not bias eq. 28,
    # reported, never written to the YAML (the driver does not know runs)
    role: str = MODEL_TERM
    # its physical bound and the source of that bound: a fit beyond it is refused by :meth:`implausible`; where no
    # refusal is implemented, what bounds the fit (its search grid) and why
    bound: str = ""
    # the checks a candidate must pass beyond its held-out test, by name, in the order they run
    # (``diagnosis.checks.CHECKS``, each saying when it runs: at every step, when the candidate is about to be added,
    # or on the final model):
    # "reading_jump": its contribution can follow a one-time move of eq. 28's output, which a jump of the temperature
    #   reading makes (a function of time or of the temperature's history);
    # "time_blocks": a function of time alone must also predict contiguous blocks of time held out (between visits
    #   interleaved in time any smooth function of time interpolates; ``diagnosis.search.time_block_check``);
    # "step" (at every step) / "step_when_chosen" (when about to be added): its contribution can follow a one-time step
    #   of the response (a connector knocked mid-run): a function of time (time_drift), of the temperature's history,
    #   which a cycled run ties to time (thermal_lag: eq. 28 read at a delayed temperature; thermal_hysteresis: a
    #   branch held between the turns), or of the reference counts, which a step of the reference arm's loss moves
    #   once (reference_dark_offset); it is set against the best step (``diagnosis.search.step_check``). Not the
    #   per-run terms: properties of the recording like the step, never in the calibration file;
    # "table_angles": a function of the direction of gravity in the sensor alone (spectral_nonlinearity) can stand in
    #   for an effect of the table's angles on a plan whose directions and angles go together: the final model's
    #   residual between visits of one direction is looked at.
    checks: tuple[str, ...] = ()
    # for the step checks: what it would be as a property of the sensor, and the measurement that tells it from a step
    sensor_property: str = ""
    tells_it_from_a_step: str = ""
    pointwise: bool = False  # columns() computes each row from that row's inputs alone (may be given some rows only)
    reference_only: bool = False  # transform() changes only the reference (and valid): eq. 28's columns stay the same
    # its columns are switched_columns() from the sample index h on and zero before (h: a grid of sample indices, no
    # values between them): diagnose searches h from sums over the samples (switch_profile), without refinement
    switched: bool = False

    @property
    def noise_remedy(self) -> bool:
        """A filter against noise, not a model effect (``role``)."""
        return self.role == NOISE_REMEDY

    @property
    def per_run(self) -> bool:
        """A property of each recording, not of the sensor (``role``)."""
        return self.role == PER_RUN

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        """Whether the data can show this effect at all (e.g. temperature must vary)."""
        return True, ""

    def void(self, h: float | None) -> bool:
        """At ``h`` the effect changes nothing (a filter of time constant 0): it cannot be added, whatever its test."""
        return False

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray | None:
        """Grid of the hyper-parameter for the 1-D search; ``None`` if the effect has none."""
        return None

    def transform(self, data: DiagnosisData, inp: Inputs, h: float | None) -> None:
        """Input corrections: modify ``inp`` in place (counts, temperature, reference alignment)."""

    def reference_at(self, data: DiagnosisData, inp: Inputs, h: float | None,
                     rows: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(reference (n, 3) m/s^2, valid (n,)) after :meth:`transform` at the samples ``rows`` (None: all) of a
        correction of the reference alone (``reference_only``) that no correction follows: one may work out those
        rows only (the same values); ``inp`` may be left changed."""
        self.transform(data, inp, h)
        return (inp.gref, inp.valid) if rows is None else (inp.gref[rows], inp.valid[rows])

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray | None:
        """Extra regressors (N, k) computed from the corrected inputs, each with 3 coefficients (one per axis);
        None if none."""
        return None

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        """Declared correction terms for the calibration YAML; ``coeff`` (3, k) m/s^2 per unit."""
        return []

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        """One line with the fitted parameter values, for the report."""
        return "" if h is None else f"{self.hyper_name} = {h:.4g} {self.hyper_unit}"

    def implausible(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray) -> str:
        """Why the fitted values are not physical (empty if they are): such a fit is refused, not added.
        ``M0`` (3, 3) is the model's matrix at the mean temperature (m/s^2 per unit Psi)."""
        return ""


class ReferenceReadNoiseEffect(Effect):
    """Read noise of the reference channel, independent of the axis channels (ESP32 ADC): eq. 24 divides
    by it, so it enters Psi. Remedy: a causal first-order low-pass of the reference before eq. 24
    (:class:`~fbg_accel_driver.correction_terms.ReferenceLowpass`), the same in the fit and the driver."""

    name = "reference_read_noise"
    stage = 1
    hyper_name = "tau_ref"
    hyper_unit = "s"
    # No hyper_null: tau = 0 is no filter at all, so whether the data need one is the candidate's own held-out test
    # (each fold's best time constant). A second, stricter rule on the final value (visits as the only units) took
    # tau back to 0 for a read noise that test found worth +11 %: the remedy was added and filtered nothing.
    title = "read noise of the reference channel (low-pass it before eq. 24)"
    role = NOISE_REMEDY
    bound = ("tau_ref within its search grid: up to 50 sample intervals and ReferenceLowpass.MAX_TIME_CONSTANT_S (a "
             "filter, not a property of the sensor: no refusal beyond it)")

    def void(self, h: float | None) -> bool:
        return not h

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        if not data.dt_s > 0:
            return False, "no time base"
        return True, ""

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        hi = min(ReferenceLowpass.MAX_TIME_CONSTANT_S, 50.0 * data.dt_s)
        return np.concatenate([[0.0], np.geomspace(0.5 * data.dt_s, hi, 15)])  # 0: no filter (the null)

    def transform(self, data: DiagnosisData, inp: Inputs, h: float | None) -> None:
        if not h:
            return
        ref = np.array(inp.ref, dtype=float, copy=True)
        for idx, steps in zip(data.runs(), _run_steps(data, inp), strict=True):
            ref[idx] = first_order_lowpass(inp.ref[idx], inp.t_s[idx], float(h), {}, steps)
        inp.ref = ref
        inp.counts_changed = True
        inp.valid &= np.isfinite(ref) & (ref > 0)

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        return [ReferenceLowpass(float(h))] if h else []

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        return f"reference low-pass tau = {h:.3g} s before eq. 24" if h else "no low-pass (tau = 0)"


class ReferenceDarkOffsetEffect(Effect):
    """Offsets of the detectors (dark current, TIA output offset, ADC zero): Psi' = c / (ref - d) and the regressor
    1 / (ref - d) with coefficients k = -M0 c0 (c0 the axis channels' offsets, counts; k in m/s^2 counts).

    It can follow a step (its ``checks`` hold "step_when_chosen"): its column is a function of the reference counts,
    and a one-time change of the reference arm's loss (its connector knocked or re-mated, the fibre to its photodetector bent; the
    paper's reference FBG path, §3.5) is a step of those counts by a factor g, so of 1 / ref by 1 / g. The same step
    multiplies every Psi = axis / ref by 1 / g: the output moves by (1/g - 1) M Psi, mostly the offset (1/g - 1) M Psi_rest,
    and k / ref moves by (1/g - 1) k / ref: with k = -M c0 it follows the offset step exactly for c0 = -c_rest. A
    step of 3 % needs implied axis offsets of 66-132 % of the counts and the plausibility bound refuses it, but a
    step of 0.2-0.5 % fits within the bound, in part, and was added as a dark offset
    (``test_a_small_step_of_the_reference_is_not_written_as_a_dark_offset``). A step of the source's power (all
    four channels) leaves every Psi as it was (eq. 24): nothing for the column to follow, and nothing is added
    (``test_a_step_of_the_source_s_power_adds_nothing``). A real dark offset follows every change of the reference
    counts (the source's wander, its temperature), which no single step does, and passes the check."""

    name = "reference_dark_offset"
    pointwise = True
    checks = ("reading_jump", "step_when_chosen")
    bound = ("the reference offset and the implied axis-channel offsets each at most MAX_CHANNEL_OFFSET_FRACTION (25 %) "
             "of the channel's counts: dark current and ADC zero offset are tens of counts (sim_default.yaml; "
             "../shared/docs/sensor_facts.md), a quarter of the signal undoes eq. 24")
    sensor_property = "a dark offset of the detectors"
    tells_it_from_a_step = ("record the detectors dark (source off) to measure the offsets, or change the source power "
                            "at fixed poses: a dark offset follows every change of the reference counts, a step of "
                            "the reference's connector happens once")
    stage = 10
    hyper_name = "d_ref"
    hyper_unit = "counts"
    hyper_null = 0.0
    title = "reference normalisation offset"

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        lo = float(np.nanmin(data.ref[data.use]))
        return np.linspace(-0.9 * lo, 0.9 * lo, 37)  # includes 0 (the null value)

    def transform(self, data: DiagnosisData, inp: Inputs, h: float | None) -> None:
        inp.ref = inp.ref - float(h)
        inp.counts_changed = True
        inp.valid &= inp.ref > 0

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            return (1.0 / np.where(inp.ref > 0, inp.ref, np.nan))[:, None]

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        return [ReferenceDarkOffset(float(h)), ChannelOffset(np.asarray(coeff)[:, 0])]

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        k = np.asarray(coeff)[:, 0] if coeff is not None else np.zeros(3)
        return (f"reference offset d_ref = {h:.1f} counts; axis-channel offsets via k = [{k[0]:.4g}, {k[1]:.4g}, {k[2]:.4g}] "
                "m/s^2·counts (regressor 1/(ref - d_ref))")

    def implausible(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray) -> str:
        # the reference's own offset: the same bound as the axis channels' (a dark offset is tens of counts)
        ref_counts = data.once("mean_abs_ref", lambda: float(np.nanmean(np.abs(data.ref[data.use]))))
        if h is not None and abs(float(h)) > MAX_CHANNEL_OFFSET_FRACTION * ref_counts:
            return (f"the reference offset d_ref = {float(h):.0f} counts is {100 * abs(float(h)) / ref_counts:.0f} % of "
                    f"the reference's counts (limit {100 * MAX_CHANNEL_OFFSET_FRACTION:.0f} %): not a dark offset")
        # the regressor k/ref is the model's M0 applied to axis-channel offsets c0: k = -M0 c0
        if coeff is None:
            return ""
        c0 = -np.linalg.solve(M0, np.asarray(coeff)[:, 0])
        mean_counts = data.once("mean_abs_counts", lambda: np.nanmean(np.abs(data.xyz[data.use]), axis=0))
        frac = np.abs(c0) / np.maximum(mean_counts, 1e-9)
        if np.any(frac > MAX_CHANNEL_OFFSET_FRACTION):
            return (f"implied axis-channel offsets {', '.join(f'{v:.0f}' for v in c0)} counts are "
                    f"{', '.join(f'{100 * v:.0f}' for v in frac)} % of the channels' counts (limit "
                    f"{100 * MAX_CHANNEL_OFFSET_FRACTION:.0f} %): the term would undo the normalisation by the reference "
                    "(eq. 24) rather than describe an offset; reference read noise does this, and so does a step of the "
                    "reference arm's loss (a connector knocked, its fibre bent)")
        return ""


class ThermalLagEffect(Effect):
    name = "thermal_lag"
    stage = 30
    checks = ("reading_jump", "step_when_chosen")
    bound = ("|tau| within its search grid, up to a third of the recording (not refused beyond it: a lag longer than "
             "the recording is not told from a drift)")
    sensor_property = "a thermal lag"
    tells_it_from_a_step = ("hold each temperature until the housing has settled and change it again: a lag comes back "
                            "with every change of the temperature, a step happens once")
    hyper_name = "tau"
    hyper_unit = "s"
    title = "thermal lag between optics and AHT10"

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        if data.temperature_span_c() < 20 * AHT10_RESOLUTION_C:
            return False, "temperature does not change in this recording"
        if data.temperature_level_count() < 2:  # the lag delays a temperature that eq. 28 of degree 0 does not read
            return False, "one temperature level: eq. 28 has no temperature term for a lag to act on"
        tau = float(np.max(self.hyper_grid(data)))
        reach = float(data.once("thermal_lag_reach", lambda: self.reach_c(data, tau)))
        if reach < 20 * AHT10_RESOLUTION_C:
            return False, (f"the temperature was settled on every fitted sample: a lag of up to {tau:.4g} s would move "
                           f"their temperature by {reach:.2g} degC at most, under what eq. 28 can resolve, so this "
                           "campaign cannot reveal a lag (levels recorded after the chamber settled); record while the "
                           "temperature ramps to test it")
        return True, ""

    @staticmethod
    def reach_c(data: DiagnosisData, tau_s: float) -> float:
        """The largest shift (degC) a lag of ``tau_s`` (s) gives the temperature of a fitted sample: the detection
        limit of the campaign's design (levels recorded once settled give none, whatever the lag)."""
        reach = 0.0
        for idx, steps in zip(data.runs(), data.run_steps(), strict=True):
            temp = data.temp_c[idx]
            use = data.use[idx] & np.isfinite(temp)
            if use.any():
                lagged = ThermalLag(tau_s).effective_temperature(np.where(np.isfinite(temp), temp, np.nanmean(temp)),
                                                                 data.t_s[idx], {}, steps)
                reach = max(reach, float(np.max(np.abs(lagged - temp)[use])))
        return reach

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        lo, hi = max(5 * data.dt_s, data.duration_s / 2000), max(data.duration_s / 3, 10 * data.dt_s)
        pos = np.geomspace(lo, hi, 14)
        return np.concatenate([-pos[::-1], pos])

    def transform(self, data: DiagnosisData, inp: Inputs, h: float | None) -> None:
        def lagged() -> np.ndarray:
            term = ThermalLag(float(h))
            out = np.array(inp.temp_c, copy=True)
            for idx, steps in zip(data.runs(), _run_steps(data, inp), strict=True):
                out[idx] = term.effective_temperature(inp.temp_c[idx], inp.t_s[idx], {}, steps)
            return out

        # of the recorded temperature, the lag depends on tau alone: once per tau (a search over another effect
        # repeats the model's lag on every trial)
        inp.temp_c = lagged() if inp.temp_changed else data.recent((self.name, float(h)), lagged)
        inp.temp_changed = True

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        return [ThermalLag(float(h))]

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        who = "optics lag the AHT10" if h > 0 else "AHT10 lags the optics"
        return f"tau = {h:.4g} s ({who})"


PSI_SPAN_MARGIN = 0.05  # fraction of the fitted Psi range added on each side of a spectral_nonlinearity's psi_span
# How far the spectral overlap can bend the output: the paper's overlap model (eq. 13 and 22, the six gratings'
# spectra of Fig. 7, fitted to the non-linearity of Fig. 12: up to 6.6 % of full scale at 180 m/s^2, section 4.2) is
# curved at rest by at most 1.6 % of the output at 1 g (x; y 0.4 %, z 0.6 %: ``python -m fbg_accel_sim.optics``,
# bench/results/optics_linearity.json, ``nonlinearity_1g_percent_of_1g``). A second-order deviation grows as the
# square of the specific force: at |a| it is NONLINEARITY_AT_1G * |a|^2 / g. NONLINEARITY_MARGIN (2) covers the
# spread between sensors' gratings; a quadratic term that bends the poses' output further is not the spectral overlap
# (an effect of the orientation, of the table's angles or of the pose history stands in for it).
NONLINEARITY_AT_1G = 0.016
NONLINEARITY_MARGIN = 2.0


def nonlinearity_bound_mps2(a_mps2: float) -> float:
    """Largest non-linear deviation (m/s^2) the spectral overlap can give at specific force ``a_mps2`` (m/s^2), with
    its margin (``NONLINEARITY_AT_1G``): 0.31 m/s^2 at 1 g."""
    return NONLINEARITY_MARGIN * NONLINEARITY_AT_1G * a_mps2 ** 2 / STANDARD_GRAVITY


class SpectralNonlinearityEffect(Effect):
    name = "spectral_nonlinearity"
    pointwise = True
    checks = ("table_angles",)
    bound = ("the non-linear part over the poses at most NONLINEARITY_MARGIN x NONLINEARITY_AT_1G of the output at 1 "
             "g, growing as |a|^2 (sensor_facts.md and the paper's Fig. 12: up to 6.6 % of full scale at 180 m/s^2; "
             "the overlap model curved by 1.6 % at 1 g, bench/results/optics_linearity.json)")
    stage = 50
    title = "acceleration non-linearity of the spectral overlap"

    def _psi0(self, data: DiagnosisData) -> np.ndarray:
        return data.once("mean_static_psi",
                         lambda: np.nanmean(Inputs.normalised(data.xyz[data.use], data.ref[data.use]), axis=0))

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray:
        return quadratic_features(inp.psi, self._psi0(data))

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        # The Psi it was fitted on (the static samples), widened by PSI_SPAN_MARGIN of the width on each side: the
        # noise of the edge poses' samples (well under 1 % of the width) does not flag a sensor at rest there.
        psi = Inputs.normalised(data.xyz[data.use], data.ref[data.use])
        lo, hi = np.nanmin(psi, axis=0), np.nanmax(psi, axis=0)
        pad = PSI_SPAN_MARGIN * (hi - lo)
        return [SpectralNonlinearity(self._psi0(data), np.asarray(coeff), np.column_stack([lo - pad, hi + pad]))]

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        c = np.asarray(coeff) if coeff is not None else np.zeros((3, 6))
        return "largest quadratic coefficient per axis = " + ", ".join(f"{v:.3g}" for v in np.max(np.abs(c), axis=1)) + " m/s^2"

    def nonlinear_part(self, coeff: np.ndarray, data: DiagnosisData) -> np.ndarray:
        """(V, 3) m/s^2: what the quadratic terms ``coeff`` (3, 6) add to each static visit's mean output beyond the
        best affine function of Psi over the visits (eq. 28 takes any affine part in Psi)."""
        rows = data.use & (data.group >= 0)
        psi = visit_means(data.group, rows, Inputs.normalised(data.xyz, data.ref))
        ok = np.all(np.isfinite(psi), axis=1)
        psi = psi[ok]
        contrib = quadratic_features(psi, self._psi0(data)) @ np.asarray(coeff, float).T
        A = np.column_stack([np.ones(len(psi)), psi])
        if len(psi) <= A.shape[1]:
            return np.zeros((0, 3))
        return contrib - A @ np.linalg.lstsq(A, contrib, rcond=None)[0]

    def implausible(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray) -> str:
        if coeff is None:
            return ""
        part = self.nonlinear_part(np.asarray(coeff), data)
        if not part.size:
            return ""
        g = visit_means(data.group, data.use & (data.group >= 0) & np.all(np.isfinite(data.gref), axis=1), data.gref)
        bound = nonlinearity_bound_mps2(float(np.max(np.linalg.norm(g, axis=1)))) if len(g) else math.inf
        worst = np.max(np.abs(part), axis=0)
        if np.any(worst > bound):
            return (f"its non-linear part reaches {', '.join(f'{v:.3g}' for v in worst)} m/s^2 (x/y/z) over the poses, "
                    f"beyond the {bound:.3g} m/s^2 the spectral overlap can bend the output at these accelerations "
                    f"(the paper's overlap model is curved by {100 * NONLINEARITY_AT_1G:.1f} % at 1 g, x"
                    f"{NONLINEARITY_MARGIN:.0f}): an effect of the orientation, of the table's angles or of the pose "
                    "history, not the spectral overlap")
        return ""


def visit_means(groups: np.ndarray, rows: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Mean of ``values`` (N, k) over each visit (``groups`` id >= 0) of the samples ``rows`` (N,) bool: (V, k), in
    ascending visit id."""
    sel = rows & (groups >= 0)
    _, inv = np.unique(groups[sel], return_inverse=True)
    n = np.bincount(inv).astype(float)
    return np.column_stack([np.bincount(inv, weights=v, minlength=len(n)) for v in values[sel].T]) / n[:, None]


def direction_labels(g: np.ndarray) -> np.ndarray:
    """Label (V,) of the direction of each reference ``g`` (V, 3) m/s^2: directions closer than
    ``thermal_fit.ORIENTATION_TOLERANCE_DEG`` to the first of a label share it (greedy, in the order given)."""
    from .thermal_fit import ORIENTATION_TOLERANCE_DEG

    u = g / np.maximum(np.linalg.norm(g, axis=1), 1e-300)[:, None]
    cos_tol = math.cos(math.radians(ORIENTATION_TOLERANCE_DEG))
    label, seen = np.empty(len(u), int), []
    for i, v in enumerate(u):
        j = next((k for k, w in enumerate(seen) if float(v @ w) > cos_tol), len(seen))
        if j == len(seen):
            seen.append(v)
        label[i] = j
    return label


def orientation_share_of_visit_times(data: DiagnosisData) -> float:
    """Share (0..1) of the variance of the visits' mean board times (s) that their orientations explain (1 - within /
    total sum of squares; 1 when the times do not vary). An orientation is a direction of the visit-mean reference,
    closer than ``thermal_fit.ORIENTATION_TOLERANCE_DEG`` counting as one (pose ids name orientations within their
    run only). Near 1, every orientation is visited at one board time only (each pose once, or every run from
    power-on through one plan in one order): a function of board time then fits whatever depends on the
    orientation, and no held-out test tells them apart. Computed once per recording."""

    def compute() -> float:
        means = visit_means(data.group, data.use & np.all(np.isfinite(data.gref), axis=1),
                            np.column_stack([data.t_s, data.gref]))
        if len(means) < 2:
            return 1.0
        t = means[:, 0]
        label = direction_labels(means[:, 1:])
        total = float(np.sum((t - t.mean()) ** 2))
        if not total > 0:
            return 1.0
        means = np.bincount(label, weights=t) / np.bincount(label)
        return 1.0 - float(np.sum((t - means[label]) ** 2)) / total

    return float(data.once("orientation_share_of_visit_times", compute))


class TimeDriftEffect(Effect):
    name = "time_drift"
    pointwise = True
    checks = ("reading_jump", "time_blocks", "step")
    bound = ("warm-up amplitude and creep over the run each at most MAX_DRIFT_MPS2, 5 % of full scale (±20 g, paper "
             "§3.4)")
    sensor_property = "a warm-up or creep"
    tells_it_from_a_step = "visit the poses again after a power-on to tell a warm-up from a step"
    stage = 70
    hyper_name = "tau_warmup"
    hyper_unit = "s"
    title = "drift with time (warm-up, creep)"

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        if data.duration_s <= 0:
            return False, "no time base"
        share = orientation_share_of_visit_times(data)
        if share > MAX_TIME_ORIENTATION_SHARE:
            return False, (f"each orientation is visited at the same board time only (the orientation explains "
                           f"{100 * share:.2f} % of the variance of the visits' board times: each pose once per run, "
                           "every run from power-on in the same order), so a drift with time cannot be told from an "
                           "effect of the orientation; visit a pose again later in the run, or change the pose order "
                           "between runs")
        return True, ""

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        d = max(data.duration_s, 1e-9)
        return np.geomspace(d / 100, d * 3, 16)

    def _t0(self, data: DiagnosisData) -> float:
        return float(np.min(data.t_s)) if data.t_s.size else 0.0

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray:
        return TimeDrift.features(inp.t_s, float(h), self._t0(data))

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        c = np.asarray(coeff)
        t = data.t_s[data.use]  # the board times it was fitted on: the driver holds it outside them
        return [TimeDrift(c[:, 0], c[:, 1], float(h), self._t0(data), (float(t.min()), float(t.max())))]

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        c = np.asarray(coeff) if coeff is not None else np.zeros((3, 2))
        return (f"warm-up tau = {h:.4g} s, amplitude [{c[0, 1]:.3g}, {c[1, 1]:.3g}, {c[2, 1]:.3g}] m/s^2; "
                f"creep [{c[0, 0]:.3g}, {c[1, 0]:.3g}, {c[2, 0]:.3g}] m/s^2/s")

    def implausible(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray) -> str:
        if coeff is None:
            return ""
        c = np.asarray(coeff)
        warm, creep = np.abs(c[:, 1]), np.abs(c[:, 0]) * max(data.duration_s, 0.0)
        if np.any(warm > MAX_DRIFT_MPS2) or np.any(creep > MAX_DRIFT_MPS2):
            return (f"warm-up amplitude up to {warm.max():.3g} m/s^2 and creep up to {creep.max():.3g} m/s^2 over the "
                    f"run exceed {MAX_DRIFT_MPS2:.3g} m/s^2 (5 % of full scale): two large terms cancelling, not a drift")
        return ""


class ChannelDelayEffect(Effect):
    name = "channel_delay"
    reference_only = True
    bound = ("D within its search grid, 0 to 12 sample intervals and at least MIN_DELAY_SEARCH_S (a delay of the chain "
             "is tens of ms, sim_default.yaml; not refused beyond it)")
    stage = 1
    hyper_name = "D"
    hyper_unit = "s"
    title = "delay of the sensor channels against the reference angles"

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        # 0 to 12 steps of the grid's unit, a sample or, above 120 Hz, 1/12 of MIN_DELAY_SEARCH_S: a delay of the chain
        # is a time (tens of ms, sim_default.yaml), and 12 samples at 500 Hz (24 ms) stopped short of a 40 ms one
        return np.arange(0.0, 12.5, 0.5) * max(data.dt_s, MIN_DELAY_SEARCH_S / 12)

    def transform(self, data: DiagnosisData, inp: Inputs, h: float | None) -> None:
        if float(h) != 0:
            inp.gref, inp.valid = self._delayed(data, inp, float(h), None, _rows_by_run(data, None))
            inp.gref_moved = True

    def reference_at(self, data: DiagnosisData, inp: Inputs, h: float | None,
                     rows: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        pieces = _rows_by_run(data, rows)
        if pieces is None or float(h) == 0:
            return super().reference_at(data, inp, h, rows)
        return self._delayed(data, inp, float(h), rows, pieces)

    @staticmethod
    def _delayed(data: DiagnosisData, inp: Inputs, D: float, rows: np.ndarray | None,
                 pieces: list[tuple[slice | np.ndarray, Any, Any]]) -> tuple[np.ndarray, np.ndarray]:
        """(reference (n, 3), valid (n,)) at ``rows`` (None: every sample; ``pieces``: ``_rows_by_run``): the
        sample taken at t shows the table at t - D, so it is compared with the reference at t - D (each sample
        interpolated on its own)."""
        g, valid = ((np.array(inp.gref, copy=True), np.array(inp.valid, copy=True)) if rows is None
                    else (take_rows(inp.gref, rows), inp.valid[rows]))  # copies either way
        for run, sel, local in pieces:
            t = data.t_s[run]
            tq = t[local] - D
            g[sel] = interp_columns(tq, t, data.gref_filled[run])
            valid[sel] &= tq >= t[0]
        return g, valid

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        # a pure delay is a time-stamp correction, not an acceleration term (see docs/effects.md)
        return [ChainDynamics(np.zeros(4), float(h))]

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        return f"D = {h:.4g} s (sensor channels late against the reference)"


class TiaLowpassEffect(Effect):
    name = "tia_lowpass"
    reference_only = True
    bound = ("the time constants within the search grid, up to 30 samples and at least MIN_TIA_SCALE_SEARCH x the "
             "paper's Table 1 cut-offs (not refused beyond it)")
    stage = 2
    hyper_name = "tau_scale"
    hyper_unit = "x Table 1"
    title = "TIA first-order low-pass of the axis channels"

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        # axis time constants from 0.05 sample to ~30 samples (Table 1 ratios between channels), and at least to
        # MIN_TIA_SCALE_SEARCH x Table 1: the stages are a time, and 30 samples at 500 Hz stopped at 0.64 x Table 1
        lo = 0.05 * data.dt_s / TIA_TAU_S[1:].min()
        hi = max(30 * data.dt_s, MIN_TIA_SCALE_SEARCH * TIA_TAU_S[1:].min()) / TIA_TAU_S[1:].min()
        return np.geomspace(lo, hi, 22)

    def taus(self, h: float) -> np.ndarray:
        return TIA_TAU_S * float(h)

    def transform(self, data: DiagnosisData, inp: Inputs, h: float | None) -> None:
        inp.gref, inp.valid = self._corrected(data, inp, float(h), None, _rows_by_run(data, None))

    def reference_at(self, data: DiagnosisData, inp: Inputs, h: float | None,
                     rows: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        pieces = _rows_by_run(data, rows)
        if pieces is None:
            return super().reference_at(data, inp, h, rows)
        return self._corrected(data, inp, float(h), rows, pieces)

    def _corrected(self, data: DiagnosisData, inp: Inputs, h: float, rows: np.ndarray | None,
                   pieces: list[tuple[slice | np.ndarray, Any, Any]]) -> tuple[np.ndarray, np.ndarray]:
        """(reference (n, 3), valid (n,)) at ``rows`` (None: every sample; ``pieces``: ``_rows_by_run``). The filters
        run over every sample; the rest only at ``rows`` (a product row by row: the rows of the whole product)."""
        # Filter the noise-free reference, not the noisy signal: the sensor shows LPF(Psi_true), so the
        # reference it must match is the one whose expected Psi went through the same filters. Inverting
        # the filter on the counts instead would amplify the (already filtered) noise by ~1/a.
        # Neither depends on the time constant: reuse the data's own when no earlier stage changed the inputs
        # (the hyper-parameter search calls this for every trial value).
        g = fill_reference_gaps(inp.t_s, inp.gref, data.runs()) if inp.gref_moved else data.gref_filled
        P, q = expected_psi_map(data, inp) if inp.counts_changed else data.static_psi_map()
        if inp.gref_moved or inp.counts_changed:
            psi_hat = g @ P.T
            psi_hat += q  # in place: one array of N x 3, not two
        else:
            psi_hat = data.once("static_psi_hat", lambda: g @ P.T + q)
        d = np.empty((len(g) if rows is None else len(rows), 3))
        tau = self.taus(h)
        for (run, sel, local), steps in zip(pieces, _run_steps(data, inp), strict=True):
            for j in range(3):
                # the column copied first: scipy's filter runs about twice as slow on a strided one
                d[sel, j] = first_order_lowpass(np.ascontiguousarray(psi_hat[run, j]), inp.t_s[run], tau[j + 1], {},
                                                steps)[local]
        d -= psi_hat if rows is None else take_rows(psi_hat, rows)
        # P is 3 x 3: one product, not a solve with N sides (a contiguous right side: numpy's fast product)
        gref = d @ np.ascontiguousarray(np.linalg.inv(P).T)
        gref += g if rows is None else take_rows(g, rows)
        return gref, (inp.valid if rows is None else inp.valid[rows]) & finite_rows(gref)

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        return [ChainDynamics(self.taus(float(h)), 0.0)]

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        t = self.taus(float(h))
        return f"scale = {h:.3g} x Table 1: tau x/y/z = {t[1]:.3g}/{t[2]:.3g}/{t[3]:.3g} s"


def expected_psi_map(data: DiagnosisData, inp: Inputs) -> tuple[np.ndarray, np.ndarray]:
    """Linear map Psi ~ P g + q (P (3, 3), q (3,)) fitted on the static samples (eq. 25 inverted):
    the noise-free Psi the sensor shows for a reference g."""
    # the static samples with a reference, their [g, 1] and its Gram matrix (constants of the recording), then
    # those with a finite Psi (a correction that changed the counts asks again on every trial of a search)
    static = data.once("static_with_reference", lambda: np.flatnonzero(data.use & finite_rows(data.gref)))
    xyz = data.once("static_xyz", lambda: np.asarray(data.xyz, dtype=float)[static]) if _same_memory(inp.xyz, data.xyz) \
        else inp.xyz[static]
    psi = Inputs.normalised(xyz, inp.ref[static])
    ok = finite_rows(psi)
    if ok.all():
        X, XtX = data.once("static_design", lambda: _with_gram(np.column_stack([data.gref[static], np.ones(len(static))])))
        Y = psi
    else:
        X = np.column_stack([data.gref[static[ok]], np.ones(int(ok.sum()))])
        XtX, Y = X.T @ X, psi[ok]
    try:  # 4 x 4 normal equations (well conditioned: |g| ~ 9.8 m/s^2 against 1), not an SVD of the N x 4 matrix
        coef = np.linalg.solve(XtX, X.T @ Y)
    except np.linalg.LinAlgError:  # the reference never changes direction: the minimum-norm solution
        coef = np.linalg.lstsq(X, Y, rcond=None)[0]
    return coef[:3].T, coef[3]


def _rows_by_run(data: DiagnosisData, rows: np.ndarray | None) -> list[tuple[slice | np.ndarray, Any, Any]] | None:
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


def _run_steps(data: DiagnosisData, inp: Inputs) -> list[SampleSteps | None]:
    """The sampling steps of each run for ``first_order_lowpass`` (``DiagnosisData.run_steps``) when the inputs'
    times are the recording's (None per run otherwise)."""
    return data.run_steps() if _same_memory(inp.t_s, data.t_s) else [None] * len(data.runs())


def _with_gram(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return X, X.T @ X


def memory_key(a: np.ndarray) -> tuple:
    """What identifies the values of a read-only array: its memory, shape, strides and type. Views of the same
    memory (``Inputs.of`` makes one of each recorded array per design) have the same key."""
    return a.__array_interface__["data"][0], a.shape, a.strides, a.dtype.str


def _same_memory(a: np.ndarray, b: np.ndarray) -> bool:
    """``a`` is ``b`` or a float64 view of all of it (``Inputs.of``): the recorded array, not a corrected one."""
    return a.dtype == np.float64 and memory_key(a) == memory_key(b)


class ThermalHysteresisEffect(Effect):
    name = "thermal_hysteresis"
    stage = 80
    checks = ("reading_jump", "step_when_chosen")
    bound = "the rate filter within its search grid; no bound on the half gap yet (not refused)"
    sensor_property = "a hysteresis between heating and cooling"
    tells_it_from_a_step = ("cycle the temperature up and down twice: a hysteresis comes back at every turn, a step "
                            "happens once")
    hyper_name = "rate_tau"
    hyper_unit = "s"
    title = "hysteresis: heating versus cooling branch"

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        if data.temperature_span_c() < 50 * AHT10_RESOLUTION_C:
            return False, "temperature does not change in this recording"
        return True, ""

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        return np.geomspace(max(5 * data.dt_s, data.duration_s / 1000), max(data.duration_s / 10, 10 * data.dt_s), 10)

    @staticmethod
    def deadband(h: float) -> float:
        return 2 * AHT10_RESOLUTION_C / float(h)

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray:
        out = np.zeros(len(inp.t_s))
        for idx, steps in zip(data.runs(), _run_steps(data, inp), strict=True):
            st = ThermalHysteresis(np.zeros(3), float(h), self.deadband(float(h))).new_state()
            out[idx] = ThermalHysteresis.branch(inp.temp_c[idx], inp.t_s[idx], float(h), self.deadband(float(h)), st,
                                                steps)
        return out[:, None]

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        return [ThermalHysteresis(np.asarray(coeff)[:, 0], float(h), self.deadband(float(h)))]

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        c = np.asarray(coeff)[:, 0] if coeff is not None else np.zeros(3)
        return f"rate filter {h:.4g} s; half gap heating-cooling [{c[0]:.3g}, {c[1]:.3g}, {c[2]:.3g}] m/s^2"


class _PerRunEffect(Effect):
    """Base of the per-run terms: one column per run (``run_offset``: every run but the first, whose offset is
    eq. 28's b) whose coefficients are m/s^2 per axis. Runs count where ``use`` has samples."""

    role = PER_RUN
    bound = "each run's term at most MAX_DRIFT_MPS2, 5 % of full scale (±20 g, paper §3.4)"
    stage = 80
    skip_first = False
    unit_text = ""

    def _runs(self, data: DiagnosisData) -> list[np.ndarray]:
        return [idx for idx in data.runs() if data.use[idx].any()]

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        if len(self._runs(data)) < 2:
            return False, "one run (file / temperature level) in this recording"
        return True, ""

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray:
        runs = self._runs(data)[1 if self.skip_first else 0:]
        out = np.zeros((len(inp.t_s), len(runs)))
        for j, idx in enumerate(runs):
            out[idx, j] = self._shape(inp.t_s[idx])
        return out

    def _shape(self, t_s: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        c = np.asarray(coeff) if coeff is not None else np.zeros((3, 0))
        first = 2 if self.skip_first else 1
        return f"{self.unit_text}: " + "; ".join(f"run {first + j}: [{c[0, j]:.3g}, {c[1, j]:.3g}, {c[2, j]:.3g}]"
                                                  for j in range(c.shape[1])) + " m/s^2 (not in the calibration file)"

    def implausible(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray) -> str:
        if coeff is not None and np.any(np.abs(coeff) > MAX_DRIFT_MPS2):
            return (f"a per-run term of {np.max(np.abs(coeff)):.3g} m/s^2 exceeds {MAX_DRIFT_MPS2:.3g} m/s^2 (5 % of "
                    "full scale): terms that cancel, not a drift")
        return ""


class RunOffsetEffect(_PerRunEffect):
    name = "run_offset"
    title = "bias offset of each run (file / temperature level) of its own"
    unit_text = "correction added to the output, against run 1, x/y/z"
    skip_first = True

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        ok, why = super().applicable(data)
        apart = data.once("runs_apart_by_level", lambda: runs_apart_by_levels(data)) if ok else []
        if apart:
            first = int(np.min(data.run_id[data.use])) + 1
            who = ("no temperature level is shared by any two runs" if not _any_level_shared(data) else
                   f"run(s) {', '.join(str(r + 1) for r in apart)} share no temperature level with run {first} or "
                   "the runs that share one with it")
            return False, (f"not identified on this data: {who}, so an offset of each run cannot be told from the "
                           "temperature dependence of eq. 28's b (record a temperature level twice, in two runs)")
        return ok, why

    def _shape(self, t_s: np.ndarray) -> np.ndarray:
        return np.ones(len(t_s))


def _run_level_pairs(data: DiagnosisData) -> np.ndarray:
    """(k, 2) the distinct (run id, temperature level label) of the fitted samples (``thermal_fit.temperature_levels``)."""
    from .thermal_fit import temperature_levels

    use = data.use & np.isfinite(data.temp_c)
    labels = temperature_levels(data.temp_c[use])[0]
    return np.unique(np.stack([data.run_id[use], labels], axis=1), axis=0)


def _any_level_shared(data: DiagnosisData) -> bool:
    """Whether two runs have fitted samples at one temperature level."""
    pairs = _run_level_pairs(data)
    return bool(len(np.unique(pairs[:, 1])) < len(pairs))


def runs_apart_by_levels(data: DiagnosisData) -> list[int]:
    """The run ids (ascending) that shared temperature levels do not connect to the first run with fitted samples (two
    runs are linked when both have samples at one level). Only runs all connected let an offset of each run be told
    from a bias that depends on the level: with one level per run (one file per chamber temperature) the offsets
    would take over eq. 28's b(T), and leave the calibration file without it. Empty: all connected."""
    pairs = _run_level_pairs(data)
    runs = np.unique(pairs[:, 0])
    if len(runs) < 2:
        return []
    linked = {int(runs[0])}
    grew = True
    while grew:  # grow the set of runs reachable from the first one through levels they share
        levels = pairs[np.isin(pairs[:, 0], list(linked)), 1]
        reach = {int(r) for r in pairs[np.isin(pairs[:, 1], levels), 0]}
        grew = not reach <= linked
        linked |= reach
    return sorted(int(r) for r in runs if int(r) not in linked)


class RunDriftEffect(_PerRunEffect):
    name = "run_drift"
    title = "linear drift of each run (file / temperature level) of its own"
    unit_text = "correction added to the output over each run (end minus start), x/y/z"

    def _shape(self, t_s: np.ndarray) -> np.ndarray:
        span = float(np.ptp(t_s)) if len(t_s) else 0.0
        return (t_s - 0.5 * (t_s.min() + t_s.max())) / span if span > 0 else np.zeros(len(t_s))


class ResponseStepEffect(Effect):
    """Not a candidate (not in ``LIBRARY``): the alternative a function of time or of the temperature's history
    (an ``Effect`` whose ``checks`` hold a step check) must beat (``diagnose.step_check``).
    The linear response changes once, for good: from the first sample of one visit on, every axis gets an offset and
    a slope on each Psi (about its mean) of its own (eq. 25 refitted after the step). A connector knocked or re-mated,
    a fibre bent or a knock on the mount does this to the response (a channel's loss changes the counts it reads by a
    factor), and a warm-up with creep follows such a step across contiguous blocks of time as well: it passes
    ``diagnose.time_block_check``. A property of the recording, never a term of the calibration. Its columns carry no
    temperature: a loss step g of channel j changes the output by (g - 1) M(T) e_j Psi_j, whose part that depends on
    the temperature is (g - 1) times eq. 28's (small) temperature coefficient of M; what the step needs of the
    temperature is eq. 28's own degree, chosen again with the step in the model (``diagnose.step_check``). (On a run
    cycled twice, x knocked at 250 s, at degree 1: x held out 0.239 m/s^2 with these columns, 0.241 with them times
    each power of the temperature as well; at degree 0, 0.355, the rest following the temperature.)
    Hyper-parameter: the index of the first sample after the step (the first sample of a visit in recording order,
    at least ``MIN_VISITS_EACH_SIDE`` visits on either side, so that both sides span the orientations)."""

    name = "response_step"
    stage = 90
    hyper_name = "first sample after the step"
    title = "a step of the response at one time (connector, fibre, knock)"
    MIN_VISITS_EACH_SIDE = 4

    def _starts(self, data: DiagnosisData) -> np.ndarray:
        """Index of the first fitted sample of every visit, in recording order."""
        def compute() -> np.ndarray:
            idx = np.flatnonzero(data.use & (data.group >= 0))
            _, first = np.unique(data.group[idx], return_index=True)
            return np.sort(idx[first])

        return data.once("visit_start_samples", compute)

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        if len(self._starts(data)) < 2 * self.MIN_VISITS_EACH_SIDE:
            return False, f"fewer than {2 * self.MIN_VISITS_EACH_SIDE} visits"
        if not len(self.hyper_grid(data)):
            return False, "no time at which the visits before and after each span the table frame"
        return True, ""

    def visit_table(self, data: DiagnosisData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(first fitted sample (V,), visit-mean reference (V, 3) m/s^2 in the table frame, visit id (V,)) of the
        fitted visits with a finite reference, in recording order."""
        def compute() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            idx = np.flatnonzero(data.use & (data.group >= 0) & finite_rows(data.gref))
            ids, first, inv = np.unique(data.group[idx], return_index=True, return_inverse=True)
            cnt = np.bincount(inv, minlength=len(ids)).astype(float)
            g = np.stack([np.bincount(inv, weights=data.gref[idx, j], minlength=len(ids)) / cnt for j in range(3)], axis=1)
            order = np.argsort(idx[first], kind="stable")
            return idx[first][order], g[order], ids[order]

        return data.once("step_visit_table", compute)

    def sides_span(self, data: DiagnosisData, grid: np.ndarray, trained: np.ndarray) -> np.ndarray:
        """(k, m) bool: for each of k training sets (``trained`` (k, V), the visits of :meth:`visit_table` trained on)
        and each step time of ``grid`` (m,) sample indices, whether the visits trained on before the step and those
        after it each span the table frame: the weakest direction of their visit-mean reference keeps
        ``MIN_SPAN_FRACTION`` of the whole data's spread (the identifiability ``diagnose.check_folds`` asks of every
        fold). The step gives the side after it a linear response of its own, so each side alone must identify one:
        on a grid run whose first visits all sit at z up (the inner angle turns, gravity does not), a step after them
        left the side before it one direction, fitted by coefficients that cancel across the step, and a visit held
        out there was predicted wildly (``test_a_step_s_side_that_does_not_span_the_frame_is_not_tried``)."""
        start, g, _ = self.visit_table(data)
        trained = np.atleast_2d(np.asarray(trained, bool))
        before = np.searchsorted(start, np.asarray(grid, float), side="left")  # visits that start before the step

        def weakest_var(n: np.ndarray, s1: np.ndarray, s2: np.ndarray) -> np.ndarray:
            with np.errstate(divide="ignore", invalid="ignore"):
                m = s1 / n[..., None]
                cov = s2 / n[..., None, None] - m[..., :, None] * m[..., None, :]
            cov = np.where((n >= 2)[..., None, None], np.nan_to_num(cov), 0.0)
            return np.where(n >= 2, np.linalg.eigvalsh(cov)[..., 0], 0.0)

        w = trained.astype(float)  # (k, V)
        outer = g[:, :, None] * g[:, None, :]
        pad = [(0, 0), (1, 0)]
        c0 = np.pad(np.cumsum(w, axis=1), pad)  # (k, V + 1) prefix sums over the visits in recording order
        c1 = np.pad(np.cumsum(w[:, :, None] * g[None], axis=1), [*pad, (0, 0)])
        c2 = np.pad(np.cumsum(w[:, :, None, None] * outer[None], axis=1), [*pad, (0, 0), (0, 0)])
        full = weakest_var(np.array(len(g), float), g.sum(axis=0), outer.sum(axis=0))
        limit = (MIN_SPAN_FRACTION ** 2) * max(float(full), 0.0)
        n_b, s1_b, s2_b = c0[:, before], c1[:, before], c2[:, before]
        n_a, s1_a, s2_a = c0[:, -1:] - n_b, c1[:, -1:] - s1_b, c2[:, -1:] - s2_b
        return (weakest_var(n_b, s1_b, s2_b) >= limit) & (weakest_var(n_a, s1_a, s2_a) >= limit) & (limit > 0)

    # the columns are ``switched_columns`` from the first sample ``h`` on, zero before: a search of ``h`` is one pass
    # over the samples (diagnose.switch_profile), not a cross-validation of every value
    switched = True
    pointwise = True

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        """The visit starts with ``MIN_VISITS_EACH_SIDE`` visits on either side, each side's visits spanning the
        table frame (:meth:`sides_span`; every fold is held to it too, ``diagnose.Evaluator``)."""
        def compute() -> np.ndarray:
            m = self.MIN_VISITS_EACH_SIDE
            starts = self._starts(data)
            grid = starts[m:len(starts) - m + 1].astype(float)
            return grid[self.sides_span(data, grid, np.ones(len(self.visit_table(data)[0]), bool))[0]]

        return data.once("step_grid", compute)

    def switched_columns(self, data: DiagnosisData, inp: Inputs) -> np.ndarray:
        """(n, 4) the columns once switched on: 1 and Psi about its mean static value (uncentred, a slope column is
        nearly the offset column times the rest Psi)."""
        psi0 = SpectralNonlinearityEffect()._psi0(data)
        return np.column_stack([np.ones(len(inp.t_s)), inp.psi - psi0[None, :]])

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray:
        after = (inp.sample_index >= float(h)).astype(float)
        return after[:, None] * self.switched_columns(data, inp)


LIBRARY: tuple[Effect, ...] = (
    ReferenceReadNoiseEffect(),
    ReferenceDarkOffsetEffect(),
    ThermalLagEffect(),
    SpectralNonlinearityEffect(),
    TimeDriftEffect(),
    ChannelDelayEffect(),
    TiaLowpassEffect(),
    ThermalHysteresisEffect(),
    RunOffsetEffect(),
    RunDriftEffect(),
)


def library_by_name() -> dict[str, Effect]:
    return {e.name: e for e in LIBRARY}


# What measurement separates two candidates that this data cannot tell apart (for the report).
SEPARATING_MEASUREMENT: dict[frozenset[str], str] = {
    frozenset({"reference_dark_offset", "time_drift"}): (
        "change the source power independently of time (step the SLD drive current or insert a calibrated "
        "attenuator after the source at fixed poses, and repeat the pose sequence in reverse order): a dark "
        "offset follows the reference counts, a drift follows the clock; also record the detectors dark "
        "(source off) to measure d directly"),
    frozenset({"channel_delay", "tia_lowpass"}): (
        "record the transitions at a higher sample rate (or a fast tilt step) and compare the step response: "
        "a delay is a shifted step, the TIA low-pass an exponential approach; a sine sweep separates them by "
        "the phase (linear in frequency for a delay, arctan for a first-order low-pass)"),
    frozenset({"thermal_lag", "thermal_hysteresis"}): (
        "hold temperature plateaus long enough (> 5 time constants) after heating and after cooling: a lag "
        "decays on the plateau, hysteresis stays"),
    frozenset({"thermal_lag", "time_drift"}): (
        "repeat the run with a different temperature profile (e.g. a plateau then a ramp): a thermal lag "
        "follows the temperature rate, a drift follows time since power-on"),
    frozenset({"run_drift", "time_drift"}): (
        "record each run after the same warm-up from power-on: a drift shared by all runs follows the time since "
        "power-on, a per-run drift comes back at every run start"),
    frozenset({"run_offset", "thermal_lag"}): (
        "hold each chamber level longer, until the housing temperature has settled: a lag ends, a run offset stays"),
    frozenset({"time_drift", "thermal_hysteresis"}): (
        "cycle the temperature up and down twice: hysteresis repeats with the branch, drift does not"),
}


def separating_measurement(a: str, b: str) -> str:
    return SEPARATING_MEASUREMENT.get(frozenset({a, b}), (
        "repeat the calibration with the two explanatory variables decorrelated (randomised pose order, "
        "temperature and power changes at different times)"))
