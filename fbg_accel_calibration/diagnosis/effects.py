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
  (These two, the measuring chain's, are in ``diagnosis.chain_effects``.)
* ``thermal_hysteresis``: bias of opposite sign on heating and cooling branches. Hyper: the time
  constant of the rate filter that decides the branch (s).
* ``run_offset`` / ``run_drift``: each run (file, temperature level) has its own bias offset / its own linear
  drift in time. Properties of the recordings, not of the sensor: fitted so that they do not bias
  eq. 28, reported, never written to the calibration (the driver cannot know runs). No hyper.
  (``diagnosis/run_effects.py``.)

Every effect declares what the diagnosis asks of it (``Effect``): its role (model term, noise remedy, per-run
property), its physical bound with the bound's source, and the checks it must pass beyond its held-out test
(``diagnosis.checks``). The candidates are registered in one place, ``diagnosis.library.LIBRARY``.

The regressors are built with the same code as the run-time terms in
``fbg_accel_driver.correction_terms``, so a fitted candidate becomes declared terms that the
driver evaluates identically. The rationale of every candidate is in ``docs/effects.md``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy import stats

from fbg_accel_driver.correction_terms import (
    ChannelOffset,
    ReferenceDarkOffset,
    ReferenceLowpass,
    SpectralNonlinearity,
    ThermalHysteresis,
    ThermalLag,
    TimeDrift,
    first_order_lowpass,
    quadratic_features,
)
from fbg_accel_driver.sensor_constants import STANDARD_GRAVITY

from .data import (
    DiagnosisData,
    Inputs,
    direction_labels,
    input_run_steps,
    rows_at,
    rows_by_run,
    run_coefficients,
    same_memory,
    visit_means,
)
from .held_lowpass import HeldRows, held_cascade, held_lowpass, held_rows

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
# The whole assembly settled from 45 to 23.4 degC in about 7 h, some 5 time constants of the housing (paper 4.4;
# sim_default.yaml thermal.optics_time_constant_s 5000 s): the AHT10 and the optics both sit inside that sealed housing
# (paper 3.5), so neither can lag the other by more than the housing's own time constant.
MAX_THERMAL_LAG_S = 7.0 * 3600.0 / 5.0
# A pure delay of the sensor channels behind the table's angles: the board converts the four channels one after the
# other within a sample interval and stamps the sample on its clock (ESP32 one-shot conversion, sim_default.yaml
# electronics), and the analogue delay of the chain is the TIA low-pass (tia_lowpass); the simulator's 20 ms is an
# ASSUMPTION of tens of ms. Beyond one sample interval plus this, the table's and the board's clocks disagree: a
# misalignment of the rig's records, no property of the sensor.
MAX_CHANNEL_DELAY_S = 0.1
# The TIA's time constants are R_tr C_tr of the parts of the paper's Table 1 (the values used give its cut-offs):
# common tolerances (a capacitor +-20 %, a resistor +-5 %; ASSUMPTION, the paper gives the values, not the
# tolerances) move them by at most about 26 %; twice Table 1 is slower than any such part. (The flight build's
# ~50 Hz, paper 3.5, is faster: within.)
MAX_TIA_SCALE = 2.0
# A function of board time shared by the runs (time_drift) is told from an effect of the orientation only by visits of
# one orientation at different board times: above this share of the visits' board-time variance explained by their
# orientation it is not testable (``orientation_share_of_visit_times``)
MAX_TIME_ORIENTATION_SHARE = 0.99
# A fitted value is refused as beyond its bound only when the data show it beyond, at the diagnosis' own level: the
# one-sided test of "within the bound" over the folds' estimates (``Effect.refusal``) rejects at this level. Between,
# the bound is not decided by this fit (the value is beyond it by less than its uncertainty).
BOUND_LEVEL = 0.01


MODEL_TERM = "model term"  # a term of eq. 28's calibration file, applied by the driver
NOISE_REMEDY = "noise remedy"  # a filter against noise, written to the calibration file, reported apart
PER_RUN = "per-run property"  # a property of each recording: fitted, reported, not in the calibration file
RIG = "rig property"  # a property of the rig (the table's angles): fitted, reported, not in the calibration file
ROLES = (MODEL_TERM, NOISE_REMEDY, PER_RUN, RIG)


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
    # added effects, a property of each recording (run_offset, run_drift) or of the rig (table_theta_offset) fitted so
    # that it does not bias eq. 28, reported, never written to the YAML (the driver knows neither runs nor the table)
    role: str = MODEL_TERM
    # its physical bound and the source of that bound: a fit beyond it is refused as not physical (:meth:`refusal`:
    # its hyper-parameter outside :meth:`hyper_limits`, its fitted values beyond :meth:`implausible`)
    bound: str = ""
    # the checks a candidate must pass beyond its held-out test, by name, in the order they run
    # (``diagnosis.checks.CHECKS``, each saying when it runs: at every step, when the candidate is about to be added,
    # or on the final model):
    # "reading_jump": its contribution can follow a one-time move of eq. 28's output, which a jump of the temperature
    #   reading makes (a function of time or of the temperature's history);
    # "slow_wander": such a function predicts the slow wander of the bias between visits from the visits around them in
    #   time: its gain must be beyond what that wander, measured on the revisits, could give
    #   (``diagnosis.checks.wander_gain``);
    # "time_blocks": a function of time alone must also predict contiguous blocks of time held out (between visits
    #   interleaved in time any smooth function of time interpolates; ``diagnosis.checks.time_block_check``);
    # "step" (at every step) / "step_when_chosen" (when about to be added): its contribution can follow a one-time step
    #   of the response (a connector knocked mid-run): a function of time (time_drift), of the temperature's history,
    #   which a cycled run ties to time (thermal_lag: eq. 28 read at a delayed temperature; thermal_hysteresis: a
    #   branch held between the turns), or of the reference counts, which a step of the reference arm's loss moves
    #   once (reference_dark_offset); it is set against the best step (``diagnosis.checks.step_check``). Not the
    #   per-run terms: properties of the recording like the step, never in the calibration file;
    # "table_angles": a function of the direction of gravity in the sensor alone (spectral_nonlinearity) can stand in
    #   for an effect of the table's angles on a plan whose directions and angles go together: the final model's
    #   residual between visits of one direction is looked at.
    checks: tuple[str, ...] = ()
    # for the step checks: what it would be as a property of the sensor, and the measurement that tells it from a step
    sensor_property: str = ""
    tells_it_from_a_step: str = ""
    # with :meth:`bound_ratios`: the measurement that gives its value directly rather than by a fit (for a fit its
    # bound does not decide, :meth:`at_bound`)
    measures_its_value: str = ""
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

    @property
    def rig(self) -> bool:
        """A property of the rig (the table), not of the sensor (``role``)."""
        return self.role == RIG

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

    def transform_rows(self, data: DiagnosisData, inp: Inputs, part: Inputs, h: float | None, rows: np.ndarray) -> bool:
        """:meth:`transform` at the samples ``rows`` alone, ``part`` (``inp`` at ``rows``) changed in place, for the last
        input correction of a design that reads no other sample of the corrected inputs (``build_design``): the
        values of ``transform`` there up to rounding. Whether it could (False: nothing changed, ``transform`` is
        used)."""
        return False

    def reference_at(self, data: DiagnosisData, inp: Inputs, h: float | None,
                     rows: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """(reference (n, 3) m/s^2, valid (n,)) after :meth:`transform` at the samples ``rows`` (None: all) of a
        correction of the reference alone (``reference_only``) that no correction follows: one may work out those
        rows only (the same values); ``inp`` may be left changed."""
        self.transform(data, inp, h)
        return (inp.gref, inp.valid) if rows is None else (rows_at(inp.gref, rows), inp.valid[rows])

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray | None:
        """Extra regressors (N, k) computed from the corrected inputs, each with 3 coefficients (one per axis);
        None if none."""
        return None

    def columns_at(self, data: DiagnosisData, inp: Inputs, h: float | None, rows: np.ndarray | None) -> np.ndarray | None:
        """:meth:`columns` at the samples ``rows`` (None: every sample) of the corrected inputs ``inp`` of every
        sample, for an effect that is not ``pointwise`` (its rows read other samples): the same values; an effect may
        work out what it needs at those rows alone."""
        c = self.columns(data, inp, h)
        return c if c is None or rows is None else c[rows]

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        """Declared correction terms for the calibration YAML; ``coeff`` (3, k) m/s^2 per unit."""
        return []

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        """One line with the fitted parameter values, for the report."""
        return "" if h is None else f"{self.hyper_name} = {h:.4g} {self.hyper_unit}"

    def describe_on(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> str:
        """The line of :meth:`describe` for a fit on ``data``: the same, unless the line needs the data (which runs a
        term of some runs only is of)."""
        return self.describe(h, coeff)

    def hyper_limits(self, data: DiagnosisData) -> tuple[float, float] | None:
        """The physical range (lowest, highest; ``hyper_unit``) of the hyper-parameter that ``bound`` states; None:
        the hyper-parameter itself is not bounded (its fitted values may be, :meth:`implausible`)."""
        return None

    def implausible(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray) -> str:
        """Why the fitted values are not physical (empty if they are): such a fit is refused, not added.
        ``M0`` (3, 3) is the model's matrix at the mean temperature (m/s^2 per unit Psi)."""
        return ""

    def bound_ratios(self, h: float | None, coeff: np.ndarray, data: DiagnosisData, M0: np.ndarray) -> np.ndarray | None:
        """Every value :meth:`implausible` bounds, each as its magnitude over its limit (1 at the bound; any shape),
        for the coefficients ``coeff``: the bound is then judged with the fit's uncertainty (:meth:`refusal`). None:
        its bound is judged on the fit alone."""
        return None

    def bound_margin(self, h: float | None, coeff: np.ndarray, coeff_folds: np.ndarray, data: DiagnosisData,
                     M0: np.ndarray) -> tuple[float, float, float] | None:
        """(ratio, its standard error, the ratio the one-sided test at ``BOUND_LEVEL`` cannot exclude below) of the
        bounded value (:meth:`bound_ratios`) that is furthest beyond its bound by that lower limit; None when the
        effect bounds no fitted value this way. The standard error is the delete-a-group jackknife over the folds'
        training fits (``coeff_folds`` (K, 3, k): each fold's coefficients without its visits): folds are groups of
        visits, so it holds under the noise's correlation within a visit and the slow noise between visits, which a
        sample-level standard error does not; the limit is the one-sided t quantile with K - 1 degrees of freedom."""
        full = self.bound_ratios(h, coeff, data, M0)
        if full is None or len(coeff_folds) < 3:
            return None
        folds = np.array([self.bound_ratios(h, c, data, M0) for c in coeff_folds])
        k = len(folds)
        se = np.sqrt((k - 1) / k * np.sum((folds - folds.mean(axis=0)) ** 2, axis=0))
        lower = full - stats.t.ppf(1.0 - BOUND_LEVEL, k - 1) * se
        i = int(np.argmax(lower))
        return float(full.flat[i]), float(se.flat[i]), float(lower.flat[i])

    def refusal(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray,
                coeff_folds: np.ndarray | None = None) -> str:
        """Why the fit at ``h`` with ``coeff`` is not physical, "" when it is: the one question the search asks of
        every effect. A hyper-parameter outside :meth:`hyper_limits`, then :meth:`implausible`; with ``coeff_folds``
        (the folds' training coefficients, (K, 3, k)) a fitted value that :meth:`bound_ratios` gives is refused only when
        it is beyond its bound by more than its uncertainty (:meth:`bound_margin`): a value beyond it by less is no
        decision of this fit, and :meth:`at_bound` says so."""
        limits = None if h is None else self.hyper_limits(data)
        if limits is not None and not limits[0] <= float(h) <= limits[1]:
            return (f"not physical: {self.hyper_name} = {float(h):.4g} {self.hyper_unit} is outside "
                    f"[{limits[0]:.4g}, {limits[1]:.4g}] {self.hyper_unit}, the bound of {self.name} ({self.bound})")
        why = self.implausible(h, coeff, data, M0)
        if why and coeff is not None and coeff_folds is not None:
            margin = self.bound_margin(h, coeff, coeff_folds, data, M0)
            if margin is not None and margin[2] <= 1.0:
                return ""
        return why

    def at_bound(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray,
                 coeff_folds: np.ndarray | None) -> str:
        """For a fit :meth:`refusal` does not refuse: why its bound is not decided ("" when it is), a value beyond
        its bound by less than its uncertainty (:meth:`bound_margin`)."""
        if coeff is None or coeff_folds is None or not self.implausible(h, coeff, data, M0):
            return ""
        margin = self.bound_margin(h, coeff, coeff_folds, data, M0)
        if margin is None or margin[2] > 1.0:  # none, or refused
            return ""
        ratio, se, lower = margin
        return (f"its fitted value is {100 * ratio:.0f} % of its bound (standard error {100 * se:.1f} % over the "
                f"folds): beyond it by less than its uncertainty (the one-sided {100 * (1 - BOUND_LEVEL):g} % "
                f"limit is {100 * lower:.0f} %), so the bound does not decide: a large {self.title} and a term that "
                "stands in for another effect both fit")


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
    bound = ("tau_ref at most ReferenceLowpass.MAX_TIME_CONSTANT_S (100 s): the source's power (the SLD, paper 3.5) "
             "wanders over minutes (ReferenceLowpass), which the reference must follow for eq. 24 to cancel it; the "
             "driver refuses a slower filter in the calibration file")

    def void(self, h: float | None) -> bool:
        return not h

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        if not data.dt_s > 0:
            return False, "no time base"
        return True, ""

    def hyper_limits(self, data: DiagnosisData) -> tuple[float, float]:
        return 0.0, ReferenceLowpass.MAX_TIME_CONSTANT_S

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        hi = min(ReferenceLowpass.MAX_TIME_CONSTANT_S, 50.0 * data.dt_s)
        return np.concatenate([[0.0], np.geomspace(0.5 * data.dt_s, hi, 15)])  # 0: no filter (the null)

    def transform(self, data: DiagnosisData, inp: Inputs, h: float | None) -> None:
        if not h:
            return

        def filtered() -> np.ndarray:
            runs, run_steps = data.runs(), input_run_steps(data, inp)
            if len(runs) == 1:  # one run holds every sample: the filter's own output, not copied into another array
                return first_order_lowpass(inp.ref[runs[0]], inp.t_s[runs[0]], float(h), {}, run_steps[0])
            ref = np.empty(len(inp.ref))  # every sample is in one run: each written below
            for idx, steps in zip(runs, run_steps, strict=True):
                ref[idx] = first_order_lowpass(inp.ref[idx], inp.t_s[idx], float(h), {}, steps)
            return ref

        # of the recorded reference counts and times, the filtered counts depend on tau alone: once per tau while
        # kept (``DiagnosisData.recent``, read-only), where a search's trial corrects the inputs of its design and of
        # the reference before the TIA low-pass with the same value, and a search on top of the model repeats it
        recorded = same_memory(inp.ref, data.ref) and same_memory(inp.t_s, data.t_s)
        ref = data.recent((self.name, float(h)), filtered) if recorded else filtered()
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
    checks = ("reading_jump", "slow_wander", "step_when_chosen")
    bound = ("the reference offset and the implied axis-channel offsets each at most MAX_CHANNEL_OFFSET_FRACTION (25 %) "
             "of the channel's counts: dark current and ADC zero offset are tens of counts (sim_default.yaml; "
             "../shared/docs/sensor_facts.md), a quarter of the signal undoes eq. 24")
    sensor_property = "a dark offset of the detectors"
    measures_its_value = "record the detectors dark (source off): the offsets are then measured, not fitted"
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

    def transform_rows(self, data: DiagnosisData, inp: Inputs, part: Inputs, h: float | None, rows: np.ndarray) -> bool:
        """:meth:`transform` at ``rows`` alone: each sample's offset is its own, so these are its values bit for bit,
        and a trial of the search subtracts the offset at the searched rows, not at every sample."""
        part.ref = part.ref - float(h)
        part.counts_changed = True
        part.valid &= part.ref > 0
        return True

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            return (1.0 / np.where(inp.ref > 0, inp.ref, np.nan))[:, None]

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        return [ReferenceDarkOffset(float(h)), ChannelOffset(np.asarray(coeff)[:, 0])]

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        k = np.asarray(coeff)[:, 0] if coeff is not None else np.zeros(3)
        return (f"reference offset d_ref = {h:.1f} counts; axis-channel offsets via k = [{k[0]:.4g}, {k[1]:.4g}, {k[2]:.4g}] "
                "m/s^2·counts (regressor 1/(ref - d_ref))")

    def _channel_offsets(self, coeff: np.ndarray, data: DiagnosisData, M0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the implied axis-channel offsets c0 (3,) counts, each as a fraction of its channel's mean counts): the
        regressor k/ref is the model's M0 applied to them, k = -M0 c0."""
        c0 = -np.linalg.solve(M0, np.asarray(coeff)[:, 0])
        mean_counts = data.once("mean_abs_counts", lambda: np.nanmean(np.abs(data.xyz[data.use]), axis=0))
        return c0, np.abs(c0) / np.maximum(mean_counts, 1e-9)

    def bound_ratios(self, h: float | None, coeff: np.ndarray, data: DiagnosisData, M0: np.ndarray) -> np.ndarray:
        ref = abs(float(h or 0.0)) / self._ref_counts(data)  # the same in every fold: it is not fitted there
        return np.concatenate([[ref], self._channel_offsets(coeff, data, M0)[1]]) / MAX_CHANNEL_OFFSET_FRACTION

    @staticmethod
    def _ref_counts(data: DiagnosisData) -> float:
        return data.once("mean_abs_ref", lambda: float(np.nanmean(np.abs(data.ref[data.use]))))

    def implausible(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray) -> str:
        # the reference's own offset: the same bound as the axis channels' (a dark offset is tens of counts)
        ref_counts = self._ref_counts(data)
        if h is not None and abs(float(h)) > MAX_CHANNEL_OFFSET_FRACTION * ref_counts:
            return (f"the reference offset d_ref = {float(h):.0f} counts is {100 * abs(float(h)) / ref_counts:.0f} % of "
                    f"the reference's counts (limit {100 * MAX_CHANNEL_OFFSET_FRACTION:.0f} %): not a dark offset")
        if coeff is None:
            return ""
        c0, frac = self._channel_offsets(coeff, data, M0)
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
    checks = ("reading_jump", "slow_wander", "step_when_chosen")
    bound = ("|tau| at most MAX_THERMAL_LAG_S (5040 s): the housing's time constant, the assembly settled in about 7 h "
             "(5 time constants, paper 4.4) with the AHT10 and the optics inside it (paper 3.5)")
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

    def hyper_limits(self, data: DiagnosisData) -> tuple[float, float]:
        return -MAX_THERMAL_LAG_S, MAX_THERMAL_LAG_S

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        lo, hi = max(5 * data.dt_s, data.duration_s / 2000), max(data.duration_s / 3, 10 * data.dt_s)
        pos = np.geomspace(lo, hi, 14)
        return np.concatenate([-pos[::-1], pos])

    def transform(self, data: DiagnosisData, inp: Inputs, h: float | None) -> None:
        def lagged() -> np.ndarray:
            term = ThermalLag(float(h))
            out = np.array(inp.temp_c, copy=True)
            for idx, steps in zip(data.runs(), input_run_steps(data, inp), strict=True):
                out[idx] = term.effective_temperature(inp.temp_c[idx], inp.t_s[idx], {}, steps)
            return out

        # of the recorded temperature, the lag depends on tau alone: once per tau (a search over another effect
        # repeats the model's lag on every trial)
        inp.temp_c = lagged() if inp.temp_changed else data.recent((self.name, float(h)), lagged)
        inp.temp_changed = True

    def transform_rows(self, data: DiagnosisData, inp: Inputs, part: Inputs, h: float | None, rows: np.ndarray) -> bool:
        """The lagged temperature at ``rows`` alone, its filters worked out over the holds of the reading in closed form
        (``held_lowpass``: the AHT10's reading changes on a few percent of the samples), so a trial costs the changes
        and the rows, not the series. Where the recorded temperature is what is lagged, every run's sampling keeps one
        filter coefficient and the reading is finite (else False: ``transform`` over every sample)."""
        if inp.temp_changed or not data.once("temp_c_finite", lambda: bool(np.isfinite(data.temp_c).all())):
            return False
        pieces = rows_by_run(data, rows)
        if pieces is None:
            return False
        term = ThermalLag(float(h))
        tau = term.tau_s if term.tau_s > 0 else term.rate_smoothing_s
        coeff = run_coefficients(data, inp, tau)
        if any(a is None for a in coeff):
            return False
        key = data.rows_key(rows)

        def lagged() -> np.ndarray:
            out = np.empty(len(rows))
            for (run, sel, local), a in zip(pieces, coeff, strict=True):
                held, x_at = data.once(f"temperature holds {run.start} {run.stop} {key}",
                                       lambda run=run, local=local: self._holds(data.temp_c[run], local), True)
                if term.tau_s > 0:
                    out[sel] = held_lowpass(held, x_at, a)
                    continue
                # ThermalLag.effective_temperature's rate estimate, term by term in its order
                temp, r = part.temp_c[sel], abs(term.tau_s) / term.rate_smoothing_s
                if term.rate_order == 1:
                    out[sel] = temp + r * (temp - held_lowpass(held, x_at, a))
                else:
                    lp, lp2 = held_cascade(held, x_at, a)
                    out[sel] = temp + r * (2.0 * (temp - lp) - (lp - lp2))
            return out

        # once per tau and rows, as ``transform`` (a search over another effect repeats the model's lag on every trial)
        part.temp_c = data.recent((self.name, float(h), key), lagged)
        part.temp_changed = True
        return True

    @staticmethod
    def _holds(temp: np.ndarray, rows: np.ndarray) -> tuple[HeldRows, np.ndarray]:
        """(the holds of a run's temperature reading ``temp`` and where ``rows`` (local) fall, the reading where the
        filters read it): what every trial shares."""
        held = held_rows(temp, rows)
        x_at = temp[held.samples]
        for arr in (x_at, *vars(held).values()):
            arr.flags.writeable = False
        return held, x_at

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

    @staticmethod
    def _visit_psi(data: DiagnosisData) -> np.ndarray:
        """(V', 3) the mean recorded Psi of each static visit where it is finite, in ascending visit id (read-only):
        worked out once per recording (a pass over every sample, asked of every fit the search checks)."""
        def means() -> np.ndarray:
            psi = visit_means(data.group, data.use & (data.group >= 0), Inputs.normalised(data.xyz, data.ref))
            psi = psi[np.all(np.isfinite(psi), axis=1)]
            psi.flags.writeable = False
            return psi

        return data.once("visit_mean_psi", means)

    def nonlinear_part(self, coeff: np.ndarray, data: DiagnosisData) -> np.ndarray:
        """(V, 3) m/s^2: what the quadratic terms ``coeff`` (3, 6) add to each static visit's mean output beyond the
        best affine function of Psi over the visits (eq. 28 takes any affine part in Psi)."""
        psi = self._visit_psi(data)
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

        def largest_bound() -> float:
            g = visit_means(data.group, data.use & (data.group >= 0) & np.all(np.isfinite(data.gref), axis=1),
                            data.gref)
            return nonlinearity_bound_mps2(float(np.max(np.linalg.norm(g, axis=1)))) if len(g) else math.inf

        # of the visits' mean reference alone: once per recording (asked of every fit the search checks)
        bound = data.once("nonlinearity_bound_mps2", largest_bound)
        worst = np.max(np.abs(part), axis=0)
        if np.any(worst > bound):
            return (f"its non-linear part reaches {', '.join(f'{v:.3g}' for v in worst)} m/s^2 (x/y/z) over the poses, "
                    f"beyond the {bound:.3g} m/s^2 the spectral overlap can bend the output at these accelerations "
                    f"(the paper's overlap model is curved by {100 * NONLINEARITY_AT_1G:.1f} % at 1 g, x"
                    f"{NONLINEARITY_MARGIN:.0f}): an effect of the orientation, of the table's angles or of the pose "
                    "history, not the spectral overlap")
        return ""


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
    checks = ("reading_jump", "time_blocks", "slow_wander", "step")
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


class ThermalHysteresisEffect(Effect):
    name = "thermal_hysteresis"
    stage = 80
    checks = ("reading_jump", "slow_wander", "step_when_chosen")
    bound = ("the half gap between heating and cooling at most MAX_DRIFT_MPS2 (5 % of full scale, paper 3.4) on each "
             "axis: the stress of the same bonds (cyanoacrylate, epoxy, paper 3.1) as a warm-up or creep, bounded alike")
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
        return self.columns_at(data, inp, h, None)

    def columns_at(self, data: DiagnosisData, inp: Inputs, h: float | None, rows: np.ndarray | None) -> np.ndarray:
        """The branch of each run (``ThermalHysteresis.branch``) at ``rows`` (None: every sample): its decisions over
        every sample of the run, carried on to those rows alone (a search's rows: no series of every sample made)."""
        pieces = None if rows is None else rows_by_run(data, rows)
        if rows is not None and pieces is None:  # rows not in runs of their own: every sample's branch, then theirs
            return self.columns_at(data, inp, h, None)[rows]
        out = np.zeros(len(inp.t_s) if rows is None else len(rows))
        for k, (idx, steps) in enumerate(zip(data.runs(), input_run_steps(data, inp), strict=True)):
            st = ThermalHysteresis(np.zeros(3), float(h), self.deadband(float(h))).new_state()
            decision = ThermalHysteresis.decisions(inp.temp_c[idx], inp.t_s[idx], float(h), self.deadband(float(h)),
                                                   st, steps)
            if rows is None:
                out[idx] = ThermalHysteresis.held(decision, st["branch"])
            else:
                _, sel, local = pieces[k]
                out[sel] = ThermalHysteresis.held(decision, st["branch"], local)
        return out[:, None]

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        return [ThermalHysteresis(np.asarray(coeff)[:, 0], float(h), self.deadband(float(h)))]

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        c = np.asarray(coeff)[:, 0] if coeff is not None else np.zeros(3)
        return f"rate filter {h:.4g} s; half gap heating-cooling [{c[0]:.3g}, {c[1]:.3g}, {c[2]:.3g}] m/s^2"

    def implausible(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray) -> str:
        if coeff is None:
            return ""
        half = np.abs(np.asarray(coeff)[:, 0])
        if np.any(half > MAX_DRIFT_MPS2):
            return (f"not physical: half gap heating-cooling up to {half.max():.3g} m/s^2, beyond {MAX_DRIFT_MPS2:.3g} "
                    "m/s^2 (5 % of full scale) that the bonds' stress can move the bias by")
        return ""
