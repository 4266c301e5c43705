"""Driver core: board bytes -> stamped, calibrated, flagged samples (pure Python + numpy, no ROS).

``DriverCore.feed(chunk, host_ns)`` decodes the bytes (``StreamDecoder``), maps board time to
host/ROS time (``ClockSync``), normalises and calibrates (paper eq. 24, and eq. 28 by the calibration
object itself: ``ThermalCalibration.acceleration_at`` per sample, plus ``correction_sum`` with persistent
state for the stateful correction terms), applies the sample
policies below and decimates. The ROS node only turns the returned records into messages.

Sample policies (documented in docs/topics.md; each has a counter and a diagnostic):

* **Reference too low** (``ref < min_reference_counts``, including 0): Psi = counts/ref is
  meaningless (eq. 24 divides by the source power), so no acceleration is published for that
  sample (counted in ``reference_low``). The raw record is still published: nothing is lost for
  calibration, and no division by zero ever happens.
* **ADC saturation** (any of ref/x/y/z at 4095, or an axis at 0): the sample is published but the variance
  of the affected axes (all axes if the reference saturated) is raised to ``full_scale_mps2**2``: the
  value is clipped and only bounded by the full scale (counted in ``adc_saturated``). (A reference at 0 is
  no light: *reference too low* above.)
* **Temperature invalid** (TEMP_VALID clear, or a reading outside the AHT10's -40..85 degC): the
  last good temperature is used for at most ``temperature_hold_s`` seconds of stamped time
  (diagnostic WARN). After that, or when no good temperature was ever seen, the thermal model
  cannot be evaluated honestly: acceleration samples are dropped (``temperature_stale_dropped``)
  and diagnostics report ERROR until a valid reading returns.
* **Outside the calibrated temperature range** (by more than ``temperature_range_margin_c``, default the AHT10's
  stated uncertainty: the range is the span of the calibration's own readings): the model is extrapolating. The sample is
  published with each axis variance raised to ``out_of_range_variance_factor * sigma**2`` plus
  the square of the difference between the extrapolated output and the output at the nearest
  edge of the range (a measure of how far the polynomial has wandered); diagnostics WARN.
* **Reference power off its calibrated level** (the reference counts more than ``reference_level_tolerance``,
  relative, from the level the calibration's fit saw at this temperature, ``ThermalCalibration.expected_reference_counts``;
  only with a calibration that records it): eq. 24 cancels the source power only if the counts carry no offset
  (detector dark current, ADC zero), and the detector noise, in counts, does not scale with the power, so the
  output is biased and noisier than ``noise_sigma_mps2`` says. The sample is published with each axis variance
  raised to ``out_of_range_variance_factor * (expected / reference)**2 * sigma**2`` (the noise growth, with the
  extrapolation margin; the bias an unknown offset causes is not bounded by it); flagged, counted
  (``reference_level_changed``), diagnostics WARN.
* **A correction term outside its fitted span** (a ``time_drift`` after the board times of the calibration run,
  a ``spectral_nonlinearity`` beyond the Psi it was fitted on; ``correction_terms``): the term is held at the
  span's edge, not extrapolated; the sample is published with each axis variance raised to
  ``out_of_range_variance_factor * sigma**2`` plus the square of what the term's formula would have added
  beyond the edge (at most the full scale squared); flagged, counted (``correction_out_of_span``),
  diagnostics WARN.
* **The calibration's own uncertainty** (a calibration with a ``coefficient_covariance`` section): J Sigma J^T, the
  coefficients' covariance carried to the output at the sample's Psi and temperature
  (``coefficient_covariance.output_covariance``; outside the calibrated range the powers of tau make it grow), is
  added to the covariance, all nine entries, when ``covariance_includes_calibration`` is set. It is a bias, the same
  error for every sample: a decimated sample gets it once, at the block's mean Psi and temperature, not divided by
  the block's size. Always reported in the diagnostics (:meth:`DriverCore.calibration_uncertainty`). The file's
  ``slow_error`` section (the slow error of a pose mean beyond noise and coefficients, ``slow_error``) is added with it,
  in the same way: a bias, once per published message; a section without its run-to-run part (one run per level) with
  ``slow_error.UNSTATED_RUN_TO_RUN_SIGMA_MPS2`` squared on each axis for that part (``SlowErrorSection.published_matrix``).
* With ``covariance_source`` ``unknown`` the covariance is all zeros (REP 145 "unknown") for every sample: the
  policies above still flag and count, but there is no variance to inflate, and a single inflated entry would state
  the other axes exactly known.
* **Gravity check** (``gravity_mps2`` set to the local gravity; 0, the default, is off; ``gravity_check``): every
  published, unflagged sample is fed to the live check, which tests each ``gravity_check_period_s`` of stillness: |mean
  a| against ``gravity_mps2``, within ``gravity_tolerance_mps2`` (plus ``gravity_check.unstated_allowance`` for the slow
  error the file does not state) plus k sigma of the noise, J Sigma J^T and the slow error (:meth:`DriverCore.gravity_status`,
  the ``gravity check`` diagnostic). A flagged or dropped sample, or a board reset, ends the still stretch.
* **Non-finite output** (cannot happen with a validated calibration, kept as a last guard): the
  sample is dropped (``non_finite_dropped``). Nothing non-finite ever reaches a topic, except the
  documented NaN temperature in the raw record before the first valid reading.

Start-up: the frames of the first ``ClockSyncConfig.prime_s`` (0.2 s) after a start or board
reset are held until the clock estimate has seen that much data, then released together (a
one-off latency, so that no stamp has to be stepped back later); a board clock that crawls ends the
hold after 0.2 s of arrivals instead (``ClockSync.primed``), so it never holds the stream.

Raw only: with ``calibration=None`` (the node's ``calibration_file: none``) every board sample gives
its raw and temperature records and no acceleration is computed (a sensor not calibrated yet, e.g.
while recording its first calibration run).

Decimation: ``decimation`` consecutive published samples are averaged (boxcar); the stamp is
their mean stamp (the group-delay centre). The variance is the mean of the samples' variances times
the variance factor of a mean of N samples of the noise *as published* (``_mean_variance_factors``):
without equalisation the noise is low-passed by the transimpedance stages, so N correlated samples
carry the information of fewer than N independent ones (``noise_model.mean_variance_factor``: white
noise 1/N; with the calibration's ``noise_correlation``, from the block's own sample interval); with
``equalise`` the TIA poles are cancelled and the factor is that of the model through the equaliser.
A block never spans a board reset nor a gap in board time: a sample more than
``MAX_BLOCK_SPAN_WINDOWS`` x N board sample intervals (the median of recent steps between frames of consecutive seq,
``SampleInterval``: a late read's catch-up, reads ~40 us apart, is no gap) after the block's first sample (lost frames, a link
outage, a run of samples the policies dropped) ends the block; the partial block is discarded in both
cases and its samples counted in ``decimation_discarded`` (``decimation_gaps`` counts the gaps).
Raw records are always produced for every board sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .chain_compensation import MODES as CHAIN_MODES
from .chain_compensation import ChannelEqualiser
from .clock_sync import ClockSync, ClockSyncConfig
from .coefficient_covariance import output_covariance
from .correction_terms import TiaInverseFilter
from .frame_codec import ADC_MAX, SEQ_MODULO, Frame, Status, at_adc_rail
from .gravity_check import DEFAULT_PERIOD_S, DEFAULT_TOLERANCE_MPS2, GravityCheck, GravityCheckConfig
from .noise_model import mean_variance_factor
from .sensor_constants import AHT10_SIGMA_C, LOW_REFERENCE_COUNTS, STANDARD_GRAVITY
from .stream_decoder import SampleInterval, StreamDecoder
from .thermal_model import MIN_REFERENCE_COUNTS, ThermalCalibration, widened_range

AHT10_MIN_C = -40.0  # AHT10 datasheet operating range
AHT10_MAX_C = 85.0
COVARIANCE_SOURCES = ("calibration", "parameter", "unknown")
# A decimation block of N samples (N = decimation, or the block's own size if ``reconfigure`` lowered it) must lie
# within this many times N board sample intervals (at least half of its window received); a larger hole in
# board time (lost frames, an outage) ends it like a board reset.
MAX_BLOCK_SPAN_WINDOWS = 2.0
_OVERRUN = int(Status.ADC_OVERRUN)
# board sample intervals (us) the gravity check runs at: 2 kHz .. 1 Hz (a board clock that crawls, or one sample a
# minute, gives no stillness window of a quarter second of sensible size)
GRAVITY_CHECK_INTERVAL_US = (500, 1_000_000)
# ``imu/raw`` (sensor_msgs/JointState): ``name`` of each ``position`` entry of a RawRecord, in order.
RAW_NAMES = ("ref_counts", "x_counts", "y_counts", "z_counts", "temperature_c", "temperature_valid",
             "status", "seq", "board_time_s")
RAW_AUX_NAME = "aux_counts"  # appended by version-2 frames: the auxiliary ADC channel (reference transducer)


@dataclass(frozen=True)
class CoreConfig:
    """Policy settings of the driver core (SI units)."""

    decimation: int = 1
    min_reference_counts: int = LOW_REFERENCE_COUNTS  # ADC counts (sensor_constants: the offline tools' limit too)
    temperature_hold_s: float = 5.0  # board seconds a stale temperature may be used
    covariance_source: str = "calibration"  # "calibration" | "parameter" | "unknown"
    accel_stddev_mps2: float = 0.0  # per-axis sigma when covariance_source == "parameter"
    out_of_range_variance_factor: float = 10.0
    # a reading this close to the calibrated range (degC) is inside it: the range is the span of the calibration's own
    # readings, and a reading is uncertain by the AHT10's stated accuracy (the temperature variance published)
    temperature_range_margin_c: float = AHT10_SIGMA_C
    full_scale_mps2: float = 20.0 * STANDARD_GRAVITY  # paper: +-20 g full scale
    # relative departure of the reference counts from the calibration's level at this temperature beyond which a
    # sample is flagged and its variance inflated (none flagged on the simulator at 16-45 degC: bench/nees_probe.py)
    reference_level_tolerance: float = 0.03
    chain_compensation: str = "none"  # "none" | "delay" | "equalise" (chain_compensation module)
    equalise_bandwidth_hz: float = 10.0  # common low-pass the equaliser leaves in place of the TIA stages
    # add the calibration's J Sigma J^T (a bias, correlated in time: docs/topics.md) to the published covariance
    covariance_includes_calibration: bool = False
    # the live gravity check (gravity_check): local gravity (m/s^2; 0, the default, = off: the check needs the site's
    # gravity and costs about as much per sample as the rest of the core), the discrepancy allowed beyond the noise and
    # J Sigma J^T (m/s^2), the still stretch each test averages (s)
    gravity_mps2: float = 0.0
    gravity_tolerance_mps2: float = DEFAULT_TOLERANCE_MPS2
    gravity_check_period_s: float = DEFAULT_PERIOD_S

    @property
    def gravity_check(self) -> GravityCheckConfig:
        return GravityCheckConfig(self.gravity_mps2, self.gravity_tolerance_mps2, self.gravity_check_period_s)

    def validate(self) -> None:
        """Raise ValueError with a message naming the bad setting."""
        if not 1 <= self.decimation <= 10000:
            raise ValueError(f"decimation must be in 1..10000, got {self.decimation}")
        if not 0 <= self.min_reference_counts <= ADC_MAX:
            raise ValueError(f"min_reference_counts must be in 0..{ADC_MAX}, got {self.min_reference_counts}")
        if not (math.isfinite(self.temperature_hold_s) and self.temperature_hold_s >= 0):
            raise ValueError(f"temperature_hold_s must be a finite value >= 0, got {self.temperature_hold_s}")
        if self.covariance_source not in COVARIANCE_SOURCES:
            raise ValueError(f"covariance_source must be one of {COVARIANCE_SOURCES}, got '{self.covariance_source}'")
        if not (math.isfinite(self.accel_stddev_mps2) and self.accel_stddev_mps2 >= 0):
            raise ValueError(f"accel_stddev_mps2 must be a finite value >= 0, got {self.accel_stddev_mps2}")
        if self.covariance_source == "parameter" and self.accel_stddev_mps2 <= 0:
            raise ValueError("covariance_source 'parameter' needs accel_stddev_mps2 > 0")
        if not (math.isfinite(self.out_of_range_variance_factor) and self.out_of_range_variance_factor >= 1):
            raise ValueError(f"out_of_range_variance_factor must be >= 1, got {self.out_of_range_variance_factor}")
        if not (math.isfinite(self.temperature_range_margin_c) and self.temperature_range_margin_c >= 0):
            raise ValueError(f"temperature_range_margin_c must be a finite value >= 0, got {self.temperature_range_margin_c}")
        if not (math.isfinite(self.reference_level_tolerance) and 0 < self.reference_level_tolerance <= 1):
            raise ValueError(f"reference_level_tolerance must be in (0, 1], got {self.reference_level_tolerance}")
        if self.chain_compensation not in CHAIN_MODES:
            raise ValueError(f"chain_compensation must be one of {CHAIN_MODES}, got '{self.chain_compensation}'")
        if not (math.isfinite(self.equalise_bandwidth_hz) and self.equalise_bandwidth_hz > 0):
            raise ValueError(f"equalise_bandwidth_hz must be > 0, got {self.equalise_bandwidth_hz}")
        self.gravity_check.validate()


@dataclass(frozen=True, slots=True)
class RawRecord:
    """One board sample as received (for ``imu/raw``); ``stamp_ns`` is ROS time in ns."""

    stamp_ns: int
    frame: Frame
    temperature_c: float  # the valid reading, else the last good one, NaN if never valid
    temperature_valid: bool


@dataclass(frozen=True, slots=True)
class ImuRecord:
    """One calibrated (possibly decimated) specific-force sample in the sensor frame."""

    stamp_ns: int
    accel_mps2: tuple[float, float, float]
    covariance: tuple[float, ...]  # 9 entries, row-major 3x3, (m/s^2)^2; all 0 = unknown (REP 145)
    temperature_c: float  # temperature used by the thermal model
    flags: frozenset[str]  # subset of {"adc_saturated", "temperature_held", "temperature_out_of_range",
    #                        "correction_out_of_span", "reference_level_changed"}


@dataclass(frozen=True, slots=True)
class TemperatureRecord:
    """A fresh valid AHT10 reading (degC) with its variance (degC^2)."""

    stamp_ns: int
    temperature_c: float
    variance: float


@dataclass
class CoreOutput:
    raw: list[RawRecord] = field(default_factory=list)
    imu: list[ImuRecord] = field(default_factory=list)
    temperature: list[TemperatureRecord] = field(default_factory=list)


@dataclass
class CoreCounters:
    """Cumulative sample counters (all since start)."""

    samples: int = 0  # frames accepted by the decoder
    imu_published: int = 0  # ImuRecords emitted (after decimation)
    samples_calibrated: int = 0  # board samples that went into an ImuRecord (counted when it is emitted)
    decimation_discarded: int = 0  # calibrated samples of a partial decimation block a reset or gap ended: unpublished
    decimation_gaps: int = 0  # pending decimation blocks ended by a gap in board time (lost frames, link outage)
    reference_low: int = 0
    adc_saturated: int = 0
    temperature_invalid: int = 0  # frames without a valid temperature reading
    temperature_held: int = 0  # of those, calibrated with a held temperature
    temperature_stale_dropped: int = 0
    temperature_out_of_range: int = 0
    reference_level_changed: int = 0  # reference counts off the calibration's level by more than the tolerance
    correction_out_of_span: int = 0  # samples a correction term was held at the edge of its fitted span for
    non_finite_dropped: int = 0
    board_resets: int = 0
    chain_priming: int = 0  # first sample after a (re)start with chain_compensation 'equalise': not published

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


class DriverCore:
    """Stateful pipeline for one board stream (see module docstring)."""

    def __init__(
        self,
        calibration: ThermalCalibration | None,
        config: CoreConfig | None = None,
        clock_config: ClockSyncConfig | None = None,
    ) -> None:
        self.cal = calibration
        self.config = config or CoreConfig()
        self.config.validate()
        self.decoder = StreamDecoder()
        self.clock = ClockSync(clock_config)
        self.counters = CoreCounters()
        self._cal_state = calibration.new_state() if calibration is not None else []
        self._last_good_temp_c: float | None = None
        self._last_good_stamp_ns: int | None = None
        self._last_stamp_ns: int | None = None
        self._last_raw_temp_valid: bool | None = None
        # decimation block: (stamp ns, accel m/s^2, variance (m/s^2)^2, temperature degC, flags, board time us, Psi or
        # None when the calibration's uncertainty is not added)
        self._pending: list[tuple[int, tuple[float, float, float], list[float], float, frozenset[str], int,
                                  tuple[float, float, float] | None]] = []
        # the calibration's uncertainty: at each emitted sample (covariance_includes_calibration), and at the last
        # calibrated sample's (Psi, temperature) for the diagnostics
        self._with_cal_cov = (calibration is not None and self.config.covariance_includes_calibration
                              and (calibration.coefficient_covariance is not None or calibration.slow_error is not None)
                              and self.config.covariance_source != "unknown")
        self._last_cal_point: tuple[float, float, float, float] | None = None
        # the slow error's (xx, xy, xz, yy, yz, zz) as published (with the allowance for an unstated run-to-run part),
        # the same for every message
        self._slow_entries = (calibration.slow_error.published_entries()
                              if calibration is not None and calibration.slow_error is not None else None)
        self._prev_frame: tuple[int, int, int] | None = None  # (seq, t_us, ADC_OVERRUN) of the previous frame of this run
        # the board's nominal sample interval (us): median of recent t_us steps between frames of consecutive seq, a late
        # read's catch-up left out (SampleInterval); one step is no estimate (catch-up reads are ~40 us apart)
        self._interval = SampleInterval()
        self._unstamped: list[Frame] = []  # frames waiting for the clock estimate to be primed
        self._base_var = tuple(float(v) ** 2 for v in self._base_sigma())
        if calibration is not None and self.config.covariance_source != "unknown":
            self._noise_corr = tuple(zip(calibration.noise_correlated_fraction.tolist(),
                                         calibration.noise_time_constant_s.tolist(), strict=True))
        else:
            self._noise_corr = ((0.0, 0.0),) * 3
        # chain compensation: stamps moved back by the chain's delay, optionally equalised counts
        mode = self.config.chain_compensation
        self._dyn = calibration.dynamic if calibration is not None else None
        if mode != "none" and self._dyn is None:
            raise ValueError(f"chain_compensation '{mode}' needs a calibration with a 'dynamic' section "
                             "(fbg-accel-calib dynamic; docs/dynamic_calibration.md)")
        if mode == "equalise" and any(t.kind == TiaInverseFilter.kind for t in calibration.corrections):
            raise ValueError("chain_compensation 'equalise' inverts the TIA stages, and the calibration's "
                             "'tia_inverse_filter' term does too: the two would invert them twice; use 'delay' "
                             "(or a calibration without that term)")
        self._equaliser = ChannelEqualiser(self._dyn, self.config.equalise_bandwidth_hz) if mode == "equalise" else None
        self._eq_prev_t_us: int | None = None
        self._delay_ns = round(self._dyn.stamp_delay_s(mode) * 1e9) if mode == "delay" else 0
        # where the shift stops being a correction (ChainDynamics.delay_helps_below_hz), for the diagnostics
        self._delay_helps_hz = self._dyn.delay_helps_below_hz() if mode == "delay" else None
        self._eq_cache: dict[int, tuple[int, tuple[float, float, float]]] = {}  # dt_us -> (delay ns, var factors)
        self._eq_mean_cache: dict[tuple[int, int], tuple[float, float, float]] = {}  # (dt_us, n) -> mean factors
        self._has_ref_level = calibration is not None and len(calibration.reference_level_counts) > 0
        # the live gravity check, built at the first calibrated sample after the board's sample interval is known
        self._gravity: GravityCheck | None = None
        self._gravity_on = calibration is not None and self.config.gravity_check.enabled

    def _base_sigma(self) -> np.ndarray:
        src = self.config.covariance_source
        if src == "calibration" and self.cal is not None:
            return np.asarray(self.cal.noise_sigma_mps2, dtype=float)
        if src == "parameter":
            return np.full(3, self.config.accel_stddev_mps2)
        return np.zeros(3)

    RUNTIME_SETTABLE = frozenset({"decimation", "min_reference_counts", "temperature_hold_s",
                                  "out_of_range_variance_factor"})

    def reconfigure(self, **changes: object) -> None:
        """Change the :data:`RUNTIME_SETTABLE` fields of the configuration while streaming (``ros2 param
        set``). Validated as a whole first (``ValueError``, nothing changed); the new configuration is
        swapped in by one assignment, which the data path picks up at its next chunk. A decimation block
        in progress is emitted once it holds the new number of samples (its variance uses its own size)."""
        unknown = set(changes) - self.RUNTIME_SETTABLE
        if unknown:
            raise ValueError(f"not settable at run time: {', '.join(sorted(unknown))}")
        new = replace(self.config, **changes)
        new.validate()
        self.config = new

    # ------------------------------------------------------------------ state for diagnostics
    @property
    def last_good_temperature_c(self) -> float | None:
        return self._last_good_temp_c

    @property
    def temperature_age_s(self) -> float | None:
        """Seconds (of stamped time, continuous across board resets) since the last valid reading.

        None if no valid reading was ever received.
        """
        if self._last_good_stamp_ns is None or self._last_stamp_ns is None:
            return None
        return max(0.0, (self._last_stamp_ns - self._last_good_stamp_ns) * 1e-9)

    @property
    def last_temperature_valid(self) -> bool | None:
        return self._last_raw_temp_valid

    # ------------------------------------------------------------------ pipeline
    def feed(self, chunk: bytes, host_ns: int, steady_ns: int | None = None) -> CoreOutput:
        """Consume bytes that had arrived by ``host_ns`` (ROS time, ns), read when a steady clock showed ``steady_ns``
        (ns; None: ROS time does not step, ``ClockSync.observe``); return the records."""
        out = CoreOutput()
        frames = self.decoder.feed(chunk)
        if not frames:
            return out
        # Split at board resets (found by the decoder) so each part is stamped with its own clock estimate.
        start = 0
        for i in self.decoder.resets_at:
            self._process(frames[start:i], host_ns, steady_ns, out, flush=True)
            self._on_reset()
            start = i
        self._process(frames[start:], host_ns, steady_ns, out)
        return out

    def flush(self) -> CoreOutput:
        """End of stream: stamp and release frames still held for clock priming (partial decimation blocks stay)."""
        out = CoreOutput()
        self._process([], 0, None, out, flush=True)
        return out

    def _on_reset(self) -> None:
        self.counters.board_resets += 1
        self._gravity_interrupt()
        self.clock.reset()
        self._discard_pending()  # never average across a reboot
        self._prev_frame = None
        self._interval.reset()
        if self._equaliser is not None:  # nor filter across one
            self._equaliser.reset()
            self._eq_prev_t_us = None

    def _discard_pending(self) -> None:
        """Drop a partial decimation block that may not be completed (board reset, gap): its samples go into no
        record, so they are counted in ``decimation_discarded``, not in ``samples_calibrated``."""
        self.counters.decimation_discarded += len(self._pending)
        self._pending = []

    def _gravity_interrupt(self) -> None:
        if self._gravity is not None:
            self._gravity.interrupt()

    def gravity_status(self) -> dict[str, float | int | bool | str]:
        """The live gravity check (``gravity_check``) for the diagnostics: its settings, whether the sensor is still,
        the tests and failures so far, the last test's figures (m/s^2, degC) and, per sensor axis, the fraction of a bias
        on it that the orientations tested so far see (``seen_x/y/z``; ``unseen_axes`` those below
        ``gravity_check.SEEN_FRACTION``); empty without a calibration."""
        if self.cal is None:
            return {}
        cfg = self.config.gravity_check
        if not cfg.enabled:
            return {"state": "off"}
        g = self._gravity
        out: dict[str, float | int | bool | str] = {
            "state": "on", "gravity_mps2": cfg.gravity_mps2, "tolerance_mps2": cfg.tolerance_mps2,
            "period_s": cfg.period_s, "still": bool(g is not None and g.still),
            "tests": g.tests if g is not None else 0, "failures": g.failures if g is not None else 0}
        last = g.last if g is not None else None
        if last is not None:
            out.update({"discrepancy_mps2": round(last.discrepancy_mps2, 4), "threshold_mps2": round(last.threshold_mps2, 4),
                        "sigma_noise_mps2": round(last.sigma_noise_mps2, 4),
                        "sigma_calibration_mps2": round(last.sigma_calibration_mps2, 4),
                        "sigma_slow_mps2": round(last.sigma_slow_mps2, 4),
                        "unstated_slow_error_mps2": last.unstated_slow_error_mps2,
                        "last_failed": last.failed, "temperature_c": round(last.temperature_c, 2),
                        "k_sigma": round(g.k, 2), "seen_x": round(float(g.seen[0]), 2),
                        "seen_y": round(float(g.seen[1]), 2), "seen_z": round(float(g.seen[2]), 2),
                        "unseen_axes": ", ".join(g.unseen_axes())})
        return out

    def clock_status(self) -> dict[str, float | int | bool]:
        """The board clock's mapping onto host time (``ClockSync.status``), for the diagnostics."""
        return self.clock.status()

    def calibration_uncertainty(self) -> tuple[float, float, float, float] | None:
        """Standard uncertainty (m/s^2, x, y, z) the calibration's coefficients give the output at the last calibrated
        sample's Psi, and that sample's temperature (degC): the diagonal of J Sigma J^T
        (``coefficient_covariance.output_covariance``). None without a ``coefficient_covariance`` section or before
        the first calibrated sample."""
        point = self._last_cal_point
        if point is None or self.cal is None or self.cal.coefficient_covariance is None:
            return None
        px, py, pz, temp = point
        c = output_covariance(self.cal.calibration_weights_at(round(temp, 2)), px, py, pz)
        return math.sqrt(max(c[0], 0.0)), math.sqrt(max(c[3], 0.0)), math.sqrt(max(c[5], 0.0)), temp

    def chain_status(self) -> dict[str, float | str]:
        """Chain compensation for diagnostics: mode, bandwidth of the published acceleration (Hz; the
        slowest axis's -3 dB point unless equalised) and the delay taken off the stamps (ms); in ``delay`` mode also,
        per axis, the frequency (Hz) below which the shift is a correction (``delay_helps_below_hz_x/y/z``,
        :meth:`ChainDynamics.delay_helps_below_hz`) and the top of the calibrated band (``calibrated_band_max_hz``,
        NaN when the section does not say); ``identified_per``: ``channel``, or ``axis`` for a format-1 section a
        dynamic calibration fitted per output axis (:attr:`ChainDynamics.identified_per_axis`). A calibration
        without a ``dynamic`` section gives mode ``none`` with ``dynamic_section`` ``absent``: the stamps are
        not moved and the chain's lag is unknown (about 0.1 s on the static-test build's 1-1.7 Hz TIA stages).
        Raw only (no calibration): empty."""
        dyn = self._dyn
        if dyn is None:
            return {} if self.cal is None else {"mode": "none", "dynamic_section": "absent"}
        mode = self.config.chain_compensation
        if self._equaliser is not None:  # the delay depends on the sample interval: the latest sample's
            bandwidth = self._equaliser.bandwidth_hz
            delay_ms = self._delay_ns * 1e-6 if self._eq_cache else math.nan
        else:
            bandwidth = min(dyn.cutoff_hz[1:])
            delay_ms = self._delay_ns * 1e-6
        out: dict[str, float | str] = {
            "mode": mode, "bandwidth_hz": round(bandwidth, 4), "applied_delay_ms": round(delay_ms, 3),
            **{f"group_delay_dc_ms_{n}": round(dyn.group_delay_s(a) * 1e3, 3) for a, n in enumerate("xyz")},
            "identified_per": "axis" if dyn.identified_per_axis else "channel"}
        if self._delay_helps_hz is not None:
            out.update({f"delay_helps_below_hz_{n}": round(v, 3) for n, v in zip("xyz", self._delay_helps_hz, strict=True)})
            band = dyn.calibrated_band_hz()
            out["calibrated_band_max_hz"] = band[1] if band is not None else math.nan
        return out

    def _equalised(self, f: Frame, read: tuple[float, float, float, float],
                   ) -> tuple[tuple[float, float, float, float], int, tuple[float, float, float]] | None:
        """Equalised (ref, x, y, z) counts ``read`` of ``f``, the stamp delay (ns) and the variance factors; None for
        the first sample after a (re)start: the inverse filter needs the previous sample and the stamp delay
        the sample interval, so that sample is not published (its stamp could not be moved consistently)."""
        eq = self._equaliser
        prev = self._eq_prev_t_us
        self._eq_prev_t_us = f.t_us
        dt_us = f.t_us - prev if prev is not None else 0
        if dt_us <= 0:  # first sample (or a repeated time): start the filters from it
            eq.reset()
            eq.step(0.0, read)
            self.counters.chain_priming += 1
            return None
        counts = eq.step(dt_us * 1e-6, read)  # this sample's own step
        # the stamp delay (and the noise factors) at the board's nominal interval, not at this one step: a late read's
        # catch-up (reads ~40 us apart) would move its stamps by ms off the board spacing; one step until it is known
        nominal_us = self._interval.us or dt_us
        cached = self._eq_cache.get(nominal_us)
        if cached is None:
            if len(self._eq_cache) >= 64:
                self._eq_cache.clear()
            dt_s = nominal_us * 1e-6
            cached = self._eq_cache[nominal_us] = (
                round(self._dyn.stamp_delay_s("equalise", eq.bandwidth_hz, dt_s) * 1e9),
                tuple(eq.variance_factor(a, dt_s, *self._noise_corr[a]) for a in range(3)))
        self._delay_ns = cached[0]
        return counts, cached[0], cached[1]

    def _process(self, frames: list[Frame], host_ns: int, steady_ns: int | None, out: CoreOutput,
                 flush: bool = False) -> None:
        clock = self.clock
        for f in frames:
            clock.observe(f.t_us, host_ns, steady_ns)
        if self._unstamped or not clock.primed:
            # Hold the first frames after a (re)start until the clock estimate is primed (ClockSync.primed).
            self._unstamped.extend(frames)
            if not (clock.primed or flush):
                return
            frames, self._unstamped = self._unstamped, []
        if not frames:
            return
        # One sample at a time in plain floats: at the driver's batch sizes (one frame per serial read
        # at 100 Hz, tens at the link limit) numpy's per-call overhead costs more than it saves.
        cfg = self.config
        counters = self.counters
        cal = self.cal
        lo, hi = cal.temperature_range_c if cal is not None else (-math.inf, math.inf)
        inside_lo, inside_hi = widened_range((lo, hi), cfg.temperature_range_margin_c)
        base_var = self._base_var
        full_var = cfg.full_scale_mps2**2
        check_ref = self._has_ref_level
        ref_tol = cfg.reference_level_tolerance
        # (stamp, frame, temperature, eq. 28 value, temperature held, variance factors, counts used: ref, x, y, z,
        #  reference off its calibrated level)
        used: list[tuple[int, Frame, float, tuple[float, float, float], bool, tuple[float, float, float],
                         tuple[float, float, float, float], bool]] = []
        equaliser = self._equaliser
        unit = (1.0, 1.0, 1.0)
        unknown = cfg.covariance_source == "unknown"
        table = cal.adc_codes if cal is not None else None
        for f in frames:
            stamp_ns = clock.stamp(f.t_us)
            counters.samples += 1
            prev = self._prev_frame
            overrun = f.status & _OVERRUN
            if prev is not None and (f.seq - prev[0]) % SEQ_MODULO == 1 and f.t_us > prev[1]:
                self._interval.add(f.t_us - prev[1], overrun | prev[2])
            self._prev_frame = (f.seq, f.t_us, overrun)
            t_c = f.temp_cc / 100.0
            valid = f.temp_valid and AHT10_MIN_C <= t_c <= AHT10_MAX_C
            if valid:
                self._last_good_temp_c, self._last_good_stamp_ns = t_c, stamp_ns
                out.temperature.append(TemperatureRecord(stamp_ns, t_c, AHT10_SIGMA_C**2))
            else:
                counters.temperature_invalid += 1
            self._last_stamp_ns = stamp_ns
            self._last_raw_temp_valid = valid
            temp = self._last_good_temp_c
            out.raw.append(RawRecord(stamp_ns, f, math.nan if temp is None else temp, valid))
            if cal is None:  # raw only
                continue
            # the centres of the codes' intervals when the calibration has a code table (adc_code_table), else as read
            read = (f.ref, f.x, f.y, f.z) if table is None else table.values(f.ref, f.x, f.y, f.z)
            if equaliser is not None:  # every sample passes the filters, in order, whatever happens next
                eq_out = self._equalised(f, read)
                if eq_out is None:
                    continue
                (ref, cx, cy, cz), delay_ns, vfac = eq_out
            else:
                (ref, cx, cy, cz), delay_ns, vfac = read, self._delay_ns, unit
            if f.ref < cfg.min_reference_counts or ref < MIN_REFERENCE_COUNTS:
                counters.reference_low += 1
                self._gravity_interrupt()
                continue
            if not valid:
                age = self.temperature_age_s
                if temp is None or age is None or age > cfg.temperature_hold_s:
                    counters.temperature_stale_dropped += 1
                    self._gravity_interrupt()
                    continue
                counters.temperature_held += 1
            base = cal.acceleration_at(cx / ref, cy / ref, cz / ref, temp)
            ref_off = False
            if check_ref:  # the measured reference against the level the fit saw at this temperature (raw counts)
                expected = cal.expected_reference_counts(temp)
                if abs(f.ref - expected) > ref_tol * expected:
                    vfac = tuple(v * (expected / f.ref) ** 2 for v in vfac)  # noise in counts over a smaller reference
                    ref_off = True
            used.append((stamp_ns - delay_ns, f, temp, base, not valid, vfac, (ref, cx, cy, cz), ref_off))  # equalised
        if not used:
            return
        last = used[-1]
        self._last_cal_point = (last[6][1] / last[6][0], last[6][2] / last[6][0], last[6][3] / last[6][0], last[2])
        with_cal_cov = self._with_cal_cov
        gravity = self._gravity
        lo_us, hi_us = GRAVITY_CHECK_INTERVAL_US
        if gravity is None and self._gravity_on and lo_us <= self._interval.us <= hi_us:
            gravity = self._gravity = GravityCheck(cal, cfg.gravity_check, self._interval.us * 1e-6)
        extra = beyond = None
        if cal.corrections:  # declared correction terms (diagnose): vectorised, with their stream state, fed the
            counts = np.array([u[6] for u in used], dtype=float)  # same counts as eq. 28 (equalised or not)
            temp_a = np.fromiter((u[2] for u in used), dtype=float, count=len(used))
            t_a = np.fromiter((u[1].t_us * 1e-6 for u in used), dtype=float, count=len(used))
            span = np.zeros((len(used), 3))
            extra = cal.correction_sum(counts[:, 0], counts[:, 1:], counts[:, 1:] / counts[:, :1], temp_a, t_a,
                                       self._cal_state, span).tolist()
            beyond = span.tolist() if span.any() else None
        for i, (stamp_ns, f, temp, base, held, vfac, (ref, cx, cy, cz), ref_off) in enumerate(used):
            accel = base if extra is None else (base[0] + extra[i][0], base[1] + extra[i][1], base[2] + extra[i][2])
            var = [base_var[0] * vfac[0], base_var[1] * vfac[1], base_var[2] * vfac[2]]
            flags = []
            if held:
                flags.append("temperature_held")
            if ref_off:
                # The source power away from the calibration's level: eq. 24 is extrapolating (vfac carries the noise
                # growth); inflate as outside the temperature range.
                counters.reference_level_changed += 1
                flags.append("reference_level_changed")
                var = [v * cfg.out_of_range_variance_factor for v in var]
            if beyond is not None and any(beyond[i]):
                # A correction term outside the span it was fitted on, held at the edge: inflate as outside the
                # temperature range, with what its formula would have added beyond the edge (capped at full scale).
                counters.correction_out_of_span += 1
                flags.append("correction_out_of_span")
                for a in range(3):
                    var[a] = var[a] * cfg.out_of_range_variance_factor + min(beyond[i][a] ** 2, full_var)
            if not inside_lo <= temp <= inside_hi:
                # Extrapolating: inflate, and add how far the polynomial has moved from the range edge.
                counters.temperature_out_of_range += 1
                flags.append("temperature_out_of_range")
                edge = cal.acceleration_at(cx / ref, cy / ref, cz / ref, min(max(temp, lo), hi))
                for a in range(3):
                    d = base[a] - edge[a]
                    var[a] = var[a] * cfg.out_of_range_variance_factor + d * d
            if f.ref >= ADC_MAX or at_adc_rail(f.x) or at_adc_rail(f.y) or at_adc_rail(f.z):
                # Clipped: the value is only bounded by the full scale (all axes if the reference clipped).
                counters.adc_saturated += 1
                flags.append("adc_saturated")
                ref_sat = f.ref >= ADC_MAX
                for a, c in enumerate((f.x, f.y, f.z)):
                    if ref_sat or at_adc_rail(c):
                        var[a] = max(var[a], full_var)
            if unknown:  # REP 145 "covariance unknown" is the all-zero matrix: nothing to inflate, and one inflated
                var = [0.0, 0.0, 0.0]  # entry would state the other axes exactly known (the flags still count)
            if not all(math.isfinite(v) for v in (*accel, *var)):
                counters.non_finite_dropped += 1
                self._gravity_interrupt()
                continue
            if gravity is not None:  # a flagged sample is no clean still sample: it ends the still stretch
                if flags:
                    gravity.interrupt()
                else:
                    gravity.update(accel, (cx / ref, cy / ref, cz / ref), temp)
            pending = self._pending
            board_dt_us = self._interval.us
            if pending and board_dt_us > 0 and (
                    f.t_us - pending[0][5]
                    > (MAX_BLOCK_SPAN_WINDOWS * max(cfg.decimation, len(pending) + 1) - 0.5) * board_dt_us):
                # a gap in board time (lost frames, a link outage, samples the policies dropped): never average
                # across it, as across a reboot; the partial block is discarded (counted)
                counters.decimation_gaps += 1
                self._discard_pending()
            self._pending.append((stamp_ns, accel, var, temp, frozenset(flags), f.t_us,
                                  (cx / ref, cy / ref, cz / ref) if with_cal_cov else None))
            if len(self._pending) >= cfg.decimation:
                out.imu.append(self._emit())

    def _calibration_bias(self, psi: tuple[float, float, float],
                          temp: float) -> tuple[float, float, float, float, float, float]:
        """(xx, xy, xz, yy, yz, zz), (m/s^2)^2, of the calibration's bias at ``psi`` and ``temp`` (degC): J Sigma J^T of
        the ``coefficient_covariance`` section plus the ``slow_error`` section's published matrix (each 0 when absent)."""
        cal = self.cal
        c = (output_covariance(cal.calibration_weights_at(round(temp, 2)), *psi)
             if cal.coefficient_covariance is not None else (0.0,) * 6)
        if self._slow_entries is not None:
            c = tuple(a + b for a, b in zip(c, self._slow_entries, strict=True))
        return c  # type: ignore[return-value]

    def _mean_variance_factors(self, n: int, dt_s: float) -> tuple[float, float, float]:
        """var(mean of ``n`` consecutive published samples) / var(one published sample) per axis (x, y, z of
        the sensor frame), for samples ``dt_s`` (s) apart, from the correlation of the noise *as published*:
        the calibration's white + first-order model (``noise_model.mean_variance_factor``), or, with
        ``equalise``, that model through the axis channel's equaliser (``ChannelEqualiser.variance_factor``:
        the TIA pole the model's correlation comes from is cancelled, the noise is left nearly white and
        low-passed at the equaliser's bandwidth; Priestley 1981 eq. 5.3.6 with the filtered autocovariance)."""
        eq = self._equaliser
        if eq is None:
            return tuple(mean_variance_factor(n, *self._noise_corr[a], dt_s) for a in range(3))  # type: ignore[return-value]
        dt_us = round(dt_s * 1e6) if math.isfinite(dt_s) else 0
        if dt_us <= 0:
            return (1.0 / n,) * 3
        key = (dt_us, n)
        factors = self._eq_mean_cache.get(key)
        if factors is None:
            if len(self._eq_mean_cache) >= 64:
                self._eq_mean_cache.clear()
            dt = dt_us * 1e-6
            one = self._eq_cache[dt_us][1] if dt_us in self._eq_cache else tuple(  # the per-sample factors
                eq.variance_factor(a, dt, *self._noise_corr[a]) for a in range(3))
            factors = self._eq_mean_cache[key] = tuple(  # type: ignore[assignment]
                eq.variance_factor(a, dt, *self._noise_corr[a], n) / one[a] for a in range(3))
        return factors

    def _emit(self) -> ImuRecord:
        block = self._pending
        n = len(block)
        if n == 1:
            stamp, acc, var, temp, flags, _, psi = block[0]
        else:
            stamp = sum(b[0] for b in block) // n
            acc = tuple(math.fsum(b[1][a] for b in block) / n for a in range(3))
            # the board's sample interval: the board clock's (the span would be stretched by missing samples)
            board_dt_us = self._interval.us
            dt_s = board_dt_us * 1e-6 if board_dt_us > 0 else (block[-1][0] - block[0][0]) * 1e-9 / (n - 1)
            mean_factor = self._mean_variance_factors(n, dt_s)
            var = [math.fsum(b[2][a] for b in block) / n * mean_factor[a] for a in range(3)]
            temp = math.fsum(b[3] for b in block) / n
            flags = frozenset().union(*(b[4] for b in block))
            psi = None if block[0][6] is None else tuple(math.fsum(b[6][a] for b in block) / n for a in range(3))
        self._pending = []
        if psi is None:
            cov = (float(var[0]), 0.0, 0.0, 0.0, float(var[1]), 0.0, 0.0, 0.0, float(var[2]))
        else:  # the calibration's bias, once for the block: J at its mean Psi and temperature (AHT10 steps: 0.01 degC),
            xx, xy, xz, yy, yz, zz = self._calibration_bias(psi, temp)  # and the slow error
            cov = (float(var[0] + xx), xy, xz, xy, float(var[1] + yy), yz, xz, yz, float(var[2] + zz))
        self.counters.imu_published += 1
        self.counters.samples_calibrated += n
        return ImuRecord(stamp, (float(acc[0]), float(acc[1]), float(acc[2])), cov, float(temp), flags)
