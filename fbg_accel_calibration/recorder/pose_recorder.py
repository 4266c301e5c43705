"""One calibration run from raw samples to an MCAP file (pure core of the ``calibration`` node, no ROS).

The node hands every ``imu/raw`` message to :meth:`RunRecorder.on_raw` and every
``imu/temperature`` message to :meth:`RunRecorder.on_temperature`. The recorder

1. writes each message to the run's MCAP at once (:class:`~fbg_accel_calibration.io.mcap_writer.RecordingWriter`,
   incremental, so a killed run leaves a readable file; the chunk is also ended after every pose);
2. computes Psi = counts / reference (paper eq. 24) and feeds it to the static-interval detector
   (:class:`~fbg_accel_driver.stillness_monitor.StillnessMonitor`), whose verdict drives the
   :class:`~fbg_accel_calibration.recorder.pose_sequencer.PoseSequencer`;
3. tells the sequencer whether the signal has *left the pose*: the mean Psi of the detector's trailing
   window further from the pose's mean Psi than the detector's level threshold, on ``DEPART_CONFIRM_WINDOWS``
   windows of consecutive samples, so a detector false alarm or a knock at the pose pauses the recording
   instead of being taken for the table's move to the next pose. The departure is dated to the first sample
   of the first window off the level; the pose's samples from then on are taken back (a ``moving`` pose
   event at that stamp, written after them, and the sequencer's count): they were taken in motion; a fast change
   of the source power (the reference ``SOURCE_SIGMAS`` noise sigmas off its slow baseline: no table move
   changes the reference channel, but Psi is distorted while the differently low-passed channels follow
   the change) is neither stillness nor motion: the pose pauses, the detector restarts after it;
4. writes a ``calibration/pose`` event whenever the sequencer's state changes and the pose's
   reference gravity when its recording starts, so the file carries the pose of every sample;
5. counts lost and repeated messages from the driver's ``seq`` field, never across a board reset
   (:class:`~fbg_accel_calibration.recorder.board_stream.BoardStream`, the driver decoder's reset rule), and checks
   the sensor temperature against the chamber set-point of the run.

Detector settings (:class:`DetectorSettings`). The window and the hold time are given in seconds
and turned into samples with the board rate measured at the start of the run. The noise floor of
Psi (per-sample variance and autocorrelation, :class:`~fbg_accel_driver.stillness_monitor.NoiseFloor`)
is either given (``noise_std`` per axis, low-passed with correlation time ``noise_corr_s``) or learnt
during the first ``learn_s`` seconds of the run (:func:`~fbg_accel_driver.stillness_monitor.learn_noise_floor`;
the sensor must be still then: the table at the first pose, whose dwell the plan can lengthen; if
the means of the four quarters of that period differ by more than ``LEARN_SHIFT_LIMIT`` noise
sigmas the table moved: service mode learns again, auto mode aborts the run because the pose
sequence is out of step). It never goes below the ADC quantisation floor of Psi,
(1 / ref)^2 / 12 per axis. The detector (:class:`~fbg_accel_driver.stillness_monitor.StillnessMonitor`)
spends ``false_alarm_per_run`` over the plan's nominal duration: a still sensor is declared moving
at most that many times per run in expectation.
"""

from __future__ import annotations

import datetime as _dt
import errno
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fbg_accel_driver.frame_codec import ADC_MAX, clipped_reading
from fbg_accel_driver.stillness_monitor import (
    DEFAULT_FALSE_ALARM_PER_RUN,
    DEFAULT_NOISE_CORR_S,
    NoiseFloor,
    StillnessMonitor,
    TooFewDegreesOfFreedomError,
    first_order_noise_floor,
    learn_noise_floor,
)

from ..fit.static_detector import estimate_noise_var, moving_variance, quantisation_var
from ..io.mcap_writer import RecordingLostError, RecordingWriter
from .board_stream import BoardStream, StreamStep
from .pose_plan import PosePlan
from .pose_sequencer import Mode, Phase, PoseSequencer, SequencerEvent

LEARN_BLOCKS = 4  # the learning period is cut into this many blocks whose means must agree
LEARN_SHIFT_LIMIT = 8.0  # largest block-mean difference (in noise sigmas) accepted as "still" while learning
DEPART_CONFIRM_WINDOWS = 2  # windows of consecutive samples whose window mean is off the pose's level: the table
# has left the pose (a knock shorter than a window shifts the window mean for less than two windows)
SOURCE_SIGMAS = 10.0  # a reference this many reference-noise sigmas off its baseline is a source-power event
SOURCE_BASELINE_S = 2.0  # s; time constant of the reference baseline (follows the slow wander of the source)
SOURCE_REBASE_S = 5.0  # s; a reference off its baseline this long is the source's new level (warned)
RECENT_SAMPLES = 20  # still samples before a pose's first recorded one that seed its mean Psi
MIN_RATE_SAMPLES = 20  # samples needed to measure the board rate
MAX_LEARN_FACTOR = 8  # a floor with too few degrees of freedom is learnt over 2, 4, then 8 x learn_s, then anew


@dataclass(frozen=True)
class DetectorSettings:
    """Static detector of the node: ``window_s`` (s) moving window, ``hold_s`` (s) of continuous
    stillness before a pose is recorded, ``noise_std`` Psi noise floor per axis (per-sample standard
    deviation; None: learn it during ``learn_s`` s), ``noise_corr_s`` (s) correlation time of a given
    floor (the TIA low-pass, paper Table 1), ``false_alarm_per_run`` the expected number of false
    still-to-moving transitions per run (``stillness_monitor``)."""

    window_s: float = 0.25
    hold_s: float = 1.0
    noise_std: tuple[float, float, float] | None = None
    # 5 s: with 2 s at 100 Hz the learnt autocorrelation is too uncertain and a 3e-5 threshold was exceeded
    # 5.8e-5 of the time; with 5 s, 1.8e-5 (test_stillness_monitor, bench numbers in docs/calibration_node.md)
    learn_s: float = 5.0
    false_alarm_per_run: float = DEFAULT_FALSE_ALARM_PER_RUN
    noise_corr_s: float = DEFAULT_NOISE_CORR_S

    def validate(self) -> None:
        for name in ("window_s", "hold_s", "learn_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"detector {name} must be > 0, got {v}")
        if not (math.isfinite(self.noise_corr_s) and self.noise_corr_s >= 0):
            raise ValueError(f"detector noise_corr_s must be >= 0 s, got {self.noise_corr_s}")
        if not 0 < self.false_alarm_per_run < 1:
            raise ValueError(f"detector false_alarm_per_run must be in (0, 1), got {self.false_alarm_per_run}")
        if self.noise_std is not None and (len(self.noise_std) != 3 or not all(math.isfinite(s) and s > 0
                                                                              for s in self.noise_std)):
            raise ValueError(f"detector noise_std must be 3 positive numbers (Psi units), got {self.noise_std}")


def describe_write_error(exc: OSError) -> str:
    """An OSError of the recording in words, with its errno name (``ENOSPC``, ...)."""
    name = errno.errorcode.get(exc.errno, "") if exc.errno is not None else ""
    text = exc.strerror or str(exc)
    return f"{name} ({text})" if name else text


def learning_shift(psi: np.ndarray, noise_var: np.ndarray, blocks: int = LEARN_BLOCKS) -> float:
    """Largest difference between the means of ``blocks`` consecutive blocks of ``psi`` (N, 3), in units
    of the per-sample noise sigma of the axis. A still sensor gives a few sigma at most (the block means
    of even strongly low-pass-filtered noise scatter less than one sample sigma); a table move of
    0.1 g or more gives tens to hundreds."""
    parts = np.array_split(np.asarray(psi, dtype=float), blocks)
    means = np.array([p.mean(axis=0) for p in parts if len(p)])
    spread = means.max(axis=0) - means.min(axis=0)
    return float(np.max(spread / np.sqrt(noise_var)))


@dataclass(frozen=True)
class RawSample:
    """One ``imu/raw`` message: ROS stamp (ns), counts, AHT10 temperature (degC), flags, board time (s)."""

    stamp_ns: int
    ref: float
    x: float
    y: float
    z: float
    temperature_c: float = math.nan
    temperature_valid: bool = True
    status: int = 0
    seq: int = 0
    board_time_s: float | None = None
    frame_id: str = ""
    aux: float = math.nan  # aux_counts of a version-2 board (the reference of a dynamic run)


@dataclass
class RunCounters:
    messages_raw: int = 0
    messages_temperature: int = 0
    lost: int = 0  # gaps in the driver's seq (frames the driver did not publish or DDS dropped), not across a reset
    repeated: int = 0  # seq equal to or just behind the previous one, within one board run
    board_resets: int = 0  # board time went back or a BOOT status after the first message
    invalid_reference: int = 0  # ref < 1 count: Psi undefined, the sample is written but not judged still
    stamps_not_increasing: int = 0
    clipped: int = 0  # samples of a pose with a channel at a rail of the ADC: the fit leaves their visit out


class GuardedRecording:
    """What a run recorder (:class:`RunRecorder`, ``DynamicRunRecorder``) does with its recording's ``OSError`` (disk
    full, the file removed): never raised to the node. The sample or reading that failed aborts the run with a
    warning (``_write_failed``, which sets ``write_error``), later inputs are ignored (``_stopped``, True when inputs
    are no longer taken), and ``close`` finishes the file as it is (it reads up to its last complete chunk). A
    subclass gives ``_stopped``, ``_on_raw`` (one sample -> its pose id), ``_write_failed`` and ``summary``."""

    writer: RecordingWriter
    counters: RunCounters
    messages: list[tuple[str, str]]  # (level, text) for the node's log
    write_error: str

    def pop_messages(self) -> list[tuple[str, str]]:
        out, self.messages = self.messages, []
        return out

    def on_raw(self, s: RawSample) -> int:
        """Record one raw sample; returns its pose id (-1 when not one of a pose's recorded samples)."""
        if self._stopped:
            return -1
        try:
            return self._on_raw(s)
        except OSError as exc:
            self._write_failed(exc)
            return -1

    def on_temperature(self, stamp_ns: int, temperature_c: float, variance_c2: float, frame_id: str = "") -> None:
        """One ``imu/temperature`` message (degC, variance degC^2, ROS time in ns), recorded in its own ``frame_id``
        (empty: the frame of the raw messages)."""
        if self._stopped:
            return
        self.counters.messages_temperature += 1
        try:
            self.writer.write_temperature(stamp_ns, temperature_c, variance_c2, frame_id=frame_id or None)
        except OSError as exc:
            self._write_failed(exc)

    def _close_recording(self, last_records: Callable[[], None] | None = None) -> dict[str, Any]:
        """``last_records()`` (the records before ``run_end``), the ``run_end`` record, the file finished; returns
        the summary. After a failed write, or on one here, the file is closed as it is."""
        if self.write_error:
            self.writer.abandon()
            return self.summary()
        try:
            if last_records is not None:
                last_records()
            self.writer.add_metadata("run_end", self.summary())
            self.writer.close()
        except OSError as exc:
            self._write_failed(exc, closing=True)
            self.writer.abandon()
        return self.summary()

    def _say_write_failed(self, exc: OSError, closing: bool, on_disk: str) -> None:
        """Set ``write_error`` and warn at once: what failed and what is safely on disk (``on_disk``: what the file
        reads up to its last complete chunk)."""
        self.write_error = describe_write_error(exc)
        path = self.writer.path
        kept = ("the recording is lost (nothing of this run remains on disk)" if isinstance(exc, RecordingLostError)
                else f"{path} reads up to its last complete chunk: {on_disk}")
        self.messages.append(("warn", f"writing {path} failed: {self.write_error}; "
                                      f"{'while closing the recording' if closing else 'run aborted'}; {kept}"))


@dataclass
class RunRecorder(GuardedRecording):
    """See the module docstring. ``metadata`` goes into the MCAP ``run`` record."""

    plan: PosePlan
    writer: RecordingWriter
    mode: Mode = Mode.SERVICE
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    sensor_id: str = "unknown"
    setpoint_c: float | None = None
    motion_expect_g: float = 0.1

    def __post_init__(self) -> None:
        self.detector.validate()
        self.sequencer = PoseSequencer(self.plan, Mode(self.mode), self.motion_expect_g)
        self.counters = RunCounters()
        self.messages: list[tuple[str, str]] = []
        self.monitor: StillnessMonitor | None = None
        self.rate_hz = math.nan
        self.noise_std = np.full(3, math.nan)
        self._startup_t: list[float] = []
        self._learn_factor = 1  # the noise is learnt over this many learn_s (raised while its floor is too uncertain)
        self._startup_psi: list[np.ndarray] = []
        self._startup_ref: list[float] = []
        self._stream = BoardStream()
        self._last_stamp: int | None = None
        self._event_key: tuple[str, int] | None = None
        self._frame_id: str | None = None
        self.temperature_c = math.nan  # degC, the latest valid AHT10 reading
        self._temp_warned = False
        self.temperature_seen_c = [math.inf, -math.inf]
        self.last_pose_id = -1
        self.finished_reason = ""
        self.write_error = ""  # why writing the recording failed (the run was aborted then), "" if it did not
        self.poses_on_disk: list[int] = []  # poses completed and ended in a chunk (safe after a crash)
        self._pending_label = -1
        self._recent: deque[np.ndarray] = deque(maxlen=RECENT_SAMPLES)
        self._pose_level_index = -1
        self._pose_sum = np.zeros(3)
        self._pose_n = 0
        self._depart_run = 0
        self._depart_window: deque[np.ndarray] = deque()  # Psi of the trailing window (departure test)
        self._depart_start_ns = 0  # stamp of the first sample of the first window off the pose's level
        self._pending: deque[np.ndarray] = deque()  # labelled Psi not yet in the pose's level (still in the window)
        self._trail: deque[tuple[int, int]] = deque()  # (stamp, label) of the last samples, to take labels back
        self._recording_events: deque[tuple[int, int]] = deque(maxlen=8)  # (stamp, pose) of recording events
        self._clipped_pose = -1  # the last pose warned of a clipped reading
        self._ref_base = math.nan  # counts; slow baseline of the reference (source power)
        self._ref_std = math.nan  # counts; noise of the reference, learnt at start-up
        self._source_off_s = 0.0  # s of board time the reference has been off its baseline
        self._ref_last_s: float | None = None  # elapsed board time (s) of the last reference judged

    # ------------------------------------------------------------------ inputs
    @property
    def _stopped(self) -> bool:
        return bool(self.write_error)

    def _on_raw(self, s: RawSample) -> int:
        c = self.counters
        c.messages_raw += 1
        step = self._check_seq(s)
        if step.reset and self.monitor is None and self._startup_t:
            # the board restarted during start-up: its clock restarts, so a span measured across the reset
            # means nothing (the detector waited for the board's whole previous uptime); learn from its new run
            self._clear_startup()
            self._say("info", "board reset during start-up: measuring the board rate / learning the noise floor again")
        if self._last_stamp is not None and s.stamp_ns <= self._last_stamp:
            c.stamps_not_increasing += 1
        self._last_stamp = s.stamp_ns
        if self._frame_id is None:
            self._frame_id = s.frame_id or self.writer.frame_id
        elif s.frame_id and s.frame_id != self._frame_id:  # recorded as received (write_raw below), and said
            self._say("warn", f"imu/raw frame_id changed from {self._frame_id!r} to {s.frame_id!r}")
            self._frame_id = s.frame_id
        temp = float(s.temperature_c)
        if s.temperature_valid and math.isfinite(temp):
            self.temperature_c = temp
            self.temperature_seen_c = [min(self.temperature_seen_c[0], temp), max(self.temperature_seen_c[1], temp)]
            self._check_setpoint(temp)
        t_s = float(s.board_time_s) if s.board_time_s is not None and math.isfinite(s.board_time_s) else s.stamp_ns * 1e-9
        if s.ref >= 1:
            psi = np.array([s.x, s.y, s.z], dtype=float) / float(s.ref)
        else:
            c.invalid_reference += 1
            psi = np.full(3, np.nan)

        pose_id = -1
        if self.monitor is None:
            self._startup(t_s, psi, s.ref)
        if self.monitor is not None and not self.sequencer.finished:
            if self._source_event(float(s.ref), step.elapsed_s):
                # Psi is distorted while the source power changes: not still (the detector restarts, a fresh
                # hold covers the channels' settling) and not a departure (the table did not move)
                self.monitor.reset()
                self._depart_run = 0
                self._depart_window.clear()
                still, departed = False, False
            else:
                still = self.monitor.update(psi)
                departed = self._departed(psi, s.stamp_ns)
                seq = self.sequencer
                if departed and seq.phase is Phase.RECORDING and seq.index == self._pose_level_index:
                    still = False  # the signal has left the pose being recorded, whatever the window variance says
            pose_id = self.sequencer.step(t_s, still, departed)
            self._trail.append((s.stamp_ns, pose_id))
            while len(self._trail) > (DEPART_CONFIRM_WINDOWS + 1) * self.monitor.window + 1:
                self._trail.popleft()
            if departed and self._depart_run == DEPART_CONFIRM_WINDOWS * self.monitor.window:
                self._retract_departure()
            if self.sequencer.stillness_stale:
                # the table left the pose while the detector still holds the pose's stillness: restart it,
                # so stillness at the next pose comes from a fresh window and hold after the motion
                self.monitor.reset()
            self._track_pose_level(pose_id, psi)
        if pose_id >= 0 and clipped_reading(s.ref, s.x, s.y, s.z):
            c.clipped += 1
            if self._clipped_pose != pose_id:  # said at once, while the pose can still be repeated
                self._clipped_pose = pose_id
                self._say("warn", f"pose {pose_id}: a channel clipped at a rail of the ADC (an axis at 0 or {ADC_MAX} "
                                  f"counts, or the reference at {ADC_MAX}): the fit leaves this visit out; lower the "
                                  "source power or the gain and repeat the pose")
        self._pending_label = pose_id  # counted by the sequencer, not yet written
        self._write_pose_event(s.stamp_ns, pose_id)
        self.writer.write_raw(s.stamp_ns, s.ref, (s.x, s.y, s.z), temperature_c=temp,
                              temperature_valid=bool(s.temperature_valid), status=int(s.status), seq=int(s.seq),
                              board_time_s=t_s, frame_id=s.frame_id)
        self._pending_label = -1
        seq = self.sequencer
        completed = pose_id >= 0 and (seq.phase is not Phase.RECORDING or seq.index != pose_id)
        interrupted = self.last_pose_id >= 0 and pose_id != self.last_pose_id
        if completed or interrupted:
            # end the chunk so a crash keeps the pose's samples: on its last sample (the one that
            # reports "recorded") when it is complete, on the first unlabelled one when it pauses
            self.writer.flush()
            if completed:
                self.poses_on_disk.append(pose_id)
        self.last_pose_id = -1 if completed else pose_id
        return pose_id

    def request_next(self) -> tuple[bool, str]:
        if self.monitor is None:
            return False, "still measuring the board rate / learning the noise floor; try again in a moment"
        ok, message = self.sequencer.request_next()
        if ok and self.sequencer.phase is Phase.WAIT_MOTION and self._recent:
            # an auto-mode skip with the table still: the motion awaited is away from where the table is now
            # (the skipped pose may never have been recorded, so its level is not known otherwise)
            self._seed_level(-1, list(self._recent))
        return ok, message

    def abort(self, reason: str) -> None:
        self.sequencer.abort(reason)

    # ------------------------------------------------------------------ state
    @property
    def done(self) -> bool:
        return self.sequencer.phase is Phase.DONE

    @property
    def finished(self) -> bool:
        return self.sequencer.finished

    def pop_events(self) -> list[SequencerEvent]:
        return self.sequencer.pop_events()

    def summary(self) -> dict[str, Any]:
        """Run summary for the ``run_end`` metadata record and the final log."""
        c = self.counters
        lo, hi = self.temperature_seen_c
        return {
            "ended": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "result": self.sequencer.phase.value,
            "reason": self.finished_reason,
            "poses": self.sequencer.summary(),
            "messages_raw": c.messages_raw,
            "messages_temperature": c.messages_temperature,
            "lost_messages": c.lost,
            "repeated_messages": c.repeated,
            "board_resets": c.board_resets,
            "invalid_reference": c.invalid_reference,
            "stamps_not_increasing": c.stamps_not_increasing,
            "clipped_samples": c.clipped,
            "board_rate_hz": self.rate_hz,
            "detector_noise_std_psi": [float(v) for v in self.noise_std],
            "temperature_range_c": [lo, hi] if math.isfinite(lo) else [],
            "write_error": self.write_error,
        }

    def close(self, reason: str) -> dict[str, Any]:
        """Write the closing pose event and the ``run_end`` record, finish the MCAP; returns the summary.

        Never raises an ``OSError`` of the recording: after a failed write the file is closed as it is (it
        reads up to its last complete chunk); a failure here is reported in the summary's ``write_error``."""
        self.finished_reason = reason

        def closing_pose_event() -> None:
            if self._last_stamp is not None and self._event_key != ("done", self.sequencer.index):
                # 1 ns after the last sample: an event applies to samples at or after its stamp
                self.writer.write_pose(self._last_stamp + 1, -1, "done", index=self.sequencer.index,
                                       count=len(self.plan), extra={"phase": self.sequencer.phase.value},
                                       sensor_id=self.sensor_id)

        return self._close_recording(closing_pose_event)

    def _write_failed(self, exc: OSError, closing: bool = False) -> None:
        """Writing the recording failed: abort the run (what follows cannot be recorded) and say at once what
        is safely on disk."""
        if self._pending_label >= 0:  # the sequencer counted a sample that was not written
            self.sequencer.retract(self._pending_label, 1, "not written")
            self._pending_label = -1
        self._say_write_failed(exc, closing, f"pose(s) {', '.join(str(k) for k in self.poses_on_disk)} complete on "
                                             "disk" if self.poses_on_disk else "no complete pose")
        self.sequencer.abort(f"recording failed: {self.write_error}", even_if_done=not closing)

    # ------------------------------------------------------------------ internals
    def _say(self, level: str, text: str) -> None:
        self.messages.append((level, text))

    def _check_seq(self, s: RawSample) -> StreamStep:
        """Lost / repeated messages and board resets from the sample's ``seq``, board time and status."""
        step = self._stream.update(s.seq, s.board_time_s, s.status)
        c = self.counters
        c.lost, c.repeated, c.board_resets = self._stream.lost, self._stream.repeated, self._stream.resets
        if step.reset:
            self._say("warn", f"board reset (board time went back or BOOT status) after {c.messages_raw - 1} messages: "
                      "no message counted lost across it")
        return step

    def _check_setpoint(self, temp: float) -> None:
        if self.setpoint_c is None or self._temp_warned or self.plan.chamber is None:
            return
        if abs(temp - self.setpoint_c) > self.plan.chamber.tolerance_c:
            self._temp_warned = True
            self._say("warn", f"sensor temperature {temp:.2f} degC is {temp - self.setpoint_c:+.2f} degC from the chamber "
                      f"set-point {self.setpoint_c:g} degC (tolerance {self.plan.chamber.tolerance_c:g}); still soaking?")

    def _startup(self, t_s: float, psi: np.ndarray, ref: float) -> None:
        """Collect the first samples: board rate, then (if not configured) the Psi noise floor."""
        if np.all(np.isfinite(psi)):
            self._startup_t.append(t_s)
            self._startup_psi.append(psi)
            self._startup_ref.append(float(ref))
        n = len(self._startup_t)
        if n < MIN_RATE_SAMPLES:
            return
        span = self._startup_t[-1] - self._startup_t[0]
        need = self.detector.learn_s * self._learn_factor if self.detector.noise_std is None else 0.0
        if span < need:
            return
        dt = np.diff(np.asarray(self._startup_t))
        dt = dt[dt > 0]
        if dt.size == 0:
            return
        self.rate_hz = float(1.0 / np.median(dt))
        window = max(3, round(self.detector.window_s * self.rate_hz))
        hold = max(1, round(self.detector.hold_s * self.rate_hz))
        psi_arr, refs = np.asarray(self._startup_psi), np.asarray(self._startup_ref)
        quant_var = quantisation_var(refs, psi_arr)  # rounding to whole counts, in Psi^2
        floor: NoiseFloor
        if self.detector.noise_std is None:
            # was the table still? Block means against the robust (median window variance) noise scale, which a
            # move inside the period does not inflate as it does the floor's plain variance
            stat = moving_variance(psi_arr, window)[window // 2: len(psi_arr) - window // 2]
            shift = learning_shift(psi_arr, np.maximum(estimate_noise_var(stat, window), quant_var))
            if shift > LEARN_SHIFT_LIMIT:
                self._motion_while_learning(shift)
                return
            floor = learn_noise_floor(psi_arr, max_lag=window).with_minimum_variance(quant_var)
            source = f"learnt from the first {span:.2f} s"
        else:
            floor = first_order_noise_floor(np.asarray(self.detector.noise_std, float),
                                            self.detector.noise_corr_s * self.rate_hz, window
                                            ).with_minimum_variance(quant_var)
            source = "configured"
        self.noise_std = floor.std
        self._ref_base = float(np.mean(refs))
        self._ref_std = max(float(np.std(refs)), 0.5)  # counts; not below the rounding to whole counts
        run_samples = max(1, round(self.plan.nominal_duration_s() * self.rate_hz))
        try:
            self.monitor = StillnessMonitor(floor, window=window, hold=hold, run_samples=run_samples,
                                            false_alarm_per_run=self.detector.false_alarm_per_run)
        except TooFewDegreesOfFreedomError:
            self._too_few_degrees_of_freedom(floor, span)
            return
        self._say("info", f"board rate {self.rate_hz:.1f} Hz; static detector: window {window} samples, hold {hold} samples, "
                  f"Psi noise floor {', '.join(f'{v:.2e}' for v in self.noise_std)} ({source}), "
                  f"leave threshold (std) {', '.join(f'{v:.2e}' for v in np.sqrt(self.monitor.leave_threshold))} "
                  f"(false alarms <= {self.detector.false_alarm_per_run:g} per run of {run_samples} samples)")
        shortest = min(p.dwell_s for p in self.plan.poses)
        needed = self.detector.hold_s + self.detector.window_s + max(p.samples for p in self.plan.poses) / self.rate_hz
        if needed > shortest:
            self._say("warn", f"the shortest dwell ({shortest:g} s) is shorter than window + hold + samples/rate "
                      f"({needed:.2f} s) at {self.rate_hz:.0f} Hz: poses may be closed short")
        self._clear_startup()

    def _clear_startup(self) -> None:
        """Forget the start-up samples (board rate / noise learning starts again, over learn_s)."""
        self._learn_factor = 1
        self._startup_t.clear()
        self._startup_psi.clear()
        self._startup_ref.clear()

    def _source_event(self, ref: float, elapsed_s: float) -> bool:
        """Is the reference (source power) off its slow baseline by more than ``SOURCE_SIGMAS`` noise sigmas?

        The baseline follows the reference with time constant ``SOURCE_BASELINE_S`` outside such events; a
        reference off it for ``SOURCE_REBASE_S`` of board time is taken as the source's new level (warned).
        """
        dt = 0.0 if self._ref_last_s is None else max(0.0, elapsed_s - self._ref_last_s)
        self._ref_last_s = elapsed_s
        if not math.isfinite(ref):
            return True
        if abs(ref - self._ref_base) <= SOURCE_SIGMAS * self._ref_std:
            self._source_off_s = 0.0
            self._ref_base += (ref - self._ref_base) * min(1.0, dt / SOURCE_BASELINE_S)
            return False
        if self._source_off_s == 0.0:
            self._say("warn", f"source power changed: reference {ref:.0f} counts against {self._ref_base:.0f}; "
                      "not taken for table motion, the pose pauses until it is steady again")
        self._source_off_s += max(dt, 1e-9)
        if self._source_off_s >= SOURCE_REBASE_S:
            self._say("warn", f"reference has stayed at {ref:.0f} counts for {SOURCE_REBASE_S:g} s: taken as the "
                      "source's new level")
            self._ref_base = ref
            self._source_off_s = 0.0
            return False
        return True

    def _departed(self, psi: np.ndarray, stamp_ns: int) -> bool | None:
        """Has the signal left the level of the current / last recorded pose (the table really moved)?

        The mean of the trailing window (the detector's) against the pose's mean Psi, with the detector's
        level threshold (``StillnessMonitor.level_threshold``: the difference of two window means of the still
        signal exceeds it with the leave threshold's per-window probability): True after
        ``DEPART_CONFIRM_WINDOWS`` windows of consecutive samples off the level on some axis; None while no
        pose level is known yet. A per-sample test (10 sigmas on 5 samples) noticed a slow departure only
        when it was nearly over: a third of a pose's samples were taken in motion.
        """
        assert self.monitor is not None
        w = self.monitor.window
        if np.all(np.isfinite(psi)):
            self._depart_window.append((stamp_ns, psi))
            while len(self._depart_window) > w:
                self._depart_window.popleft()
        if self._pose_n < 1:
            return None
        if len(self._depart_window) < w:
            return self._depart_run >= DEPART_CONFIRM_WINDOWS * w
        level = self._pose_sum / self._pose_n
        mean = np.mean([p for _, p in self._depart_window], axis=0)
        if np.any(np.abs(mean - level) > self.monitor.level_threshold):
            if self._depart_run == 0:
                self._depart_start_ns = self._depart_window[0][0]
            self._depart_run += 1
        else:
            self._depart_run = 0
        return self._depart_run >= DEPART_CONFIRM_WINDOWS * w

    def _retract_departure(self) -> None:
        """The table has left pose k: its samples from the first window off the level on were taken in
        motion. They are taken back from the sequencer's count, and a ``moving`` pose event at the departure
        start (written after them: an event applies to the samples at or after its stamp) takes them out of
        the pose in the file; a pose resumed after that stamp gets the same at its ``recording`` event."""
        k = self._pose_level_index
        if k < 0:
            return
        start = self._depart_start_ns
        n = sum(1 for stamp, label in self._trail if label == k and stamp >= start)
        if n == 0:
            return
        self.sequencer.retract(k, n, "taken after the table began to leave the pose")
        pose = self.plan.poses[k]
        extra = {"phase": self.sequencer.phase.value, "name": pose.name, "retracted": n}
        for stamp in [start] + [t for t, j in self._recording_events if j == k and t > start]:
            self.writer.write_pose(stamp, -1, "moving", index=k, count=len(self.plan), extra=extra,
                                   sensor_id=self.sensor_id)
        self._event_key = None  # the next sample's state is written again
        self.writer.flush()

    def _track_pose_level(self, pose_id: int, psi: np.ndarray) -> None:
        """Mean Psi of the pose being recorded, seeded with the still window that preceded its first sample."""
        if pose_id >= 0 and np.all(np.isfinite(psi)):
            if pose_id != self._pose_level_index:
                self._seed_level(pose_id, list(self._recent))
            # a sample joins the level once it has left the trailing window: the window is compared with
            # samples before it, so the level does not follow a departure as it begins
            self._pending.append(psi)
            if self.monitor is not None and len(self._pending) > self.monitor.window:
                self._pose_sum = self._pose_sum + self._pending.popleft()
                self._pose_n += 1
        if np.all(np.isfinite(psi)):
            self._recent.append(psi)

    def _seed_level(self, index: int, prior: list[np.ndarray]) -> None:
        """Start the level of pose ``index`` (-1: where the table is now) from the still samples ``prior``."""
        self._pose_level_index = index
        self._pose_sum = np.sum(prior, axis=0) if prior else np.zeros(3)
        self._pose_n = len(prior)
        self._pending.clear()
        self._depart_run = 0

    def _too_few_degrees_of_freedom(self, floor: NoiseFloor, span: float) -> None:
        """The floor learnt over ``span`` s is too uncertain for the false-alarm rate (a slow wander of the still
        signal leaves few independent samples): keep the samples and learn over twice the stretch, up to
        MAX_LEARN_FACTOR x learn_s; beyond, start again (as after a board reset)."""
        dof = ", ".join(f"{v:.1f}" for v in floor.dof)
        if self._learn_factor < MAX_LEARN_FACTOR:
            self._learn_factor *= 2
            self._say("warn", f"the noise floor learnt from the first {span:.2f} s has too few degrees of freedom "
                      f"({dof}) for a threshold at {self.detector.false_alarm_per_run:g} false alarms per run (a slow "
                      f"wander of the still signal?): learning over {self._learn_factor * self.detector.learn_s:g} s")
            return
        self._clear_startup()
        self._say("warn", f"no usable noise floor in {MAX_LEARN_FACTOR * self.detector.learn_s:g} s (degrees of freedom "
                  f"{dof}): keep the sensor still or set still_noise_std; learning again")

    def _motion_while_learning(self, shift: float) -> None:
        """The table moved while the noise floor was being learnt (the sensor must be still then)."""
        self._clear_startup()
        if self.sequencer.mode is Mode.AUTO:
            # the table is following the plan without us: which pose it is at is unknown now
            self._say("warn", f"the table moved while the noise floor was being learnt (mean shift {shift:.0f} sigma): "
                      "in auto mode the pose sequence is out of step. Give the plan's first pose a dwell covering the "
                      "node's start-up (learn_s + hold + samples/rate) or set still_noise_std; run aborted")
            self.sequencer.abort("table moved during start-up (auto mode)")
        else:
            self._say("warn", f"the table moved while the noise floor was being learnt (mean shift {shift:.0f} sigma); "
                      "keep it still at pose 0; learning again")

    def _write_pose_event(self, stamp_ns: int, pose_id: int) -> None:
        """Pose event before the sample at ``stamp_ns`` when its state differs from the previous sample's.

        The state follows the sample's label (a pose's last recorded sample is still ``recording``
        although the sequencer has moved on), else the sequencer phase.
        """
        seq = self.sequencer
        if pose_id >= 0:
            key = ("recording", pose_id)
        elif self.monitor is None:
            key = ("settling", -1)
        else:
            state = {Phase.WAIT_STILL: "settling", Phase.WAIT_MOTION: "moving"}.get(seq.phase, "done")
            key = (state, seq.index)
        if key == self._event_key:
            return
        self._event_key = key
        state, index = key
        extra: dict[str, Any] = {"phase": "startup" if self.monitor is None else seq.phase.value}
        if index >= 0:
            pose = self.plan.poses[index]
            extra["name"] = pose.name
            if pose.psi_deg is not None:
                extra["psi_deg"] = pose.psi_deg
                extra["theta_deg"] = pose.theta_deg
            if state == "recording":
                self.writer.write_reference_gravity(stamp_ns, pose.gref_mps2)
                self._recording_events.append((stamp_ns, index))
        if self.setpoint_c is not None:
            extra["setpoint_c"] = self.setpoint_c
        self.writer.write_pose(stamp_ns, pose_id, state, index=index, count=len(self.plan), extra=extra,
                               sensor_id=self.sensor_id)
