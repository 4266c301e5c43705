"""One dynamic calibration run from raw samples to an MCAP file (pure core of the ``calibration`` node
when its ``plan_file`` is an excitation plan; issue 9; docs/dynamic_calibration.md). No ROS.

The slide follows the plan by itself (its controller, or the simulator's ``--dynamic-plan``); the
recorder writes every ``imu/raw`` message with the board's ``aux_counts`` as it arrives, the reference
transducer's reading on its own topic (``calibration/reference_velocity`` for an LDV,
``calibration/reference_acceleration`` for a reference accelerometer: the value along the slide
direction as a vector in the sensor frame, converted with the plan's sensitivity and offset), ends
the MCAP chunk every ``chunk_period_s`` of board time so a killed run keeps all but the last second,
and is done ``start_s + duration + tail_s`` of board time after its first sample. Board time is counted
continuously across a board reset (its clock restarts at 0; ``board_stream.BoardStream``). The plan is in the
file's metadata; ``fbg-accel-calib dynamic`` finds the slide's start in the aux channel itself.
"""

from __future__ import annotations

import datetime as _dt
import math
from typing import Any

import numpy as np

from ..dynamic.excitation_plan import ExcitationPlan
from ..io.mcap_writer import RecordingWriter
from .board_stream import BoardStream
from .pose_recorder import GuardedRecording, RawSample, RunCounters
from .pose_sequencer import SequencerEvent

PROGRESS_EVERY_S = 10.0
RATE_SAMPLES = 20  # samples to measure the board rate
NYQUIST_FRACTION = 0.45  # a segment at this fraction of the board rate or above is refused by the offline fit


class DynamicRunRecorder(GuardedRecording):
    """Recorder of a dynamic run with the interface the node drives (``on_raw``, ``on_temperature``,
    ``done``, ``finished``, ``pop_events``, ``pop_messages``, ``request_next``, ``abort``, ``close``)."""

    monitor = None  # no stillness detector: the node shows no pose progress line

    def __init__(self, plan: ExcitationPlan, writer: RecordingWriter, sensor_id: str = "", tail_s: float = 2.0,
                 chunk_period_s: float = 1.0) -> None:
        self.plan = plan
        self.writer = writer
        self.sensor_id = sensor_id
        self.length_s = plan.start_s + plan.duration_s + tail_s
        self.chunk_period_s = chunk_period_s
        self.counters = RunCounters()
        self.messages: list[tuple[str, str]] = []
        self.events: list[SequencerEvent] = []
        self.finished_reason = ""
        self._last_chunk_s = 0.0  # elapsed board time (s) of the last chunk end
        self._next_progress = PROGRESS_EVERY_S
        self._elapsed = 0.0
        self._stream = BoardStream()
        self._aux_missing_warned = False
        self._aborted = False
        self._direction = np.asarray(plan.direction, dtype=float)
        self._kind = "velocity" if plan.reference.type == "ldv" else "acceleration"
        self.temperature_c = math.nan  # degC, the latest valid AHT10 reading
        self.aux_samples = 0
        self.rate_hz = math.nan  # board rate, measured from the first RATE_SAMPLES samples
        self._rate_t: list[float] = []
        self.write_error = ""  # why writing the recording failed (the run was aborted then), "" if it did not
        self._on_disk_s = 0.0  # elapsed board time (s) up to which the recording is in ended chunks

    # ------------------------------------------------------------------ inputs
    @property
    def _stopped(self) -> bool:
        return self.finished

    def _on_raw(self, s: RawSample) -> int:
        c = self.counters
        c.messages_raw += 1
        # no loss counted across a board reset; elapsed board time continuous across it (the clock restarts at 0)
        step = self._stream.update(s.seq, s.board_time_s, s.status, host_time_s=s.stamp_ns * 1e-9)
        c.lost, c.repeated, c.board_resets = self._stream.lost, self._stream.repeated, self._stream.resets
        if step.reset:
            self.messages.append(("warn", f"board reset after {c.messages_raw - 1} messages: the board clock "
                                          "restarted; recording goes on (the slide keeps following the plan)"))
        t = float(s.board_time_s) if s.board_time_s is not None and math.isfinite(s.board_time_s) else s.stamp_ns * 1e-9
        if s.temperature_valid and math.isfinite(s.temperature_c):
            self.temperature_c = float(s.temperature_c)
        aux = s.aux if math.isfinite(s.aux) else None
        self.writer.write_raw(s.stamp_ns, s.ref, (s.x, s.y, s.z), temperature_c=float(s.temperature_c),
                              temperature_valid=bool(s.temperature_valid), status=int(s.status), seq=int(s.seq),
                              board_time_s=t, aux_counts=aux, frame_id=s.frame_id)
        if aux is not None:
            self.aux_samples += 1
            ref = self.plan.reference
            value = (aux - ref.offset_counts) / ref.sensitivity
            self.writer.write_reference_motion(s.stamp_ns, self._kind, value * self._direction)
        elif not self._aux_missing_warned:
            self._aux_missing_warned = True
            self.messages.append(("warn", "imu/raw has no aux_counts: the board sends protocol version 1, so the "
                                          "reference transducer is not recorded (docs/protocol.md, version 2)"))
        self._elapsed = step.elapsed_s
        if not math.isfinite(self.rate_hz):
            self._measure_rate(step.elapsed_s)
        if self._elapsed - self._last_chunk_s >= self.chunk_period_s:
            self.writer.flush()  # a killed run keeps everything up to here
            self._last_chunk_s = self._elapsed
            self._on_disk_s = self._elapsed
        if self._elapsed >= self._next_progress:
            self._next_progress += PROGRESS_EVERY_S
            self._event("progress", f"dynamic run: {self._elapsed:.0f} of {self.length_s:.0f} s recorded")
        if self._elapsed >= self.length_s:
            self.finished_reason = "complete"
            self._event("done", f"dynamic run complete: {self.length_s:.0f} s, {c.messages_raw} samples")
        return -1

    def request_next(self) -> tuple[bool, str]:
        return False, "a dynamic run has no poses: the slide follows the plan by itself"

    def abort(self, reason: str) -> None:
        self._aborted = True
        self.finished_reason = reason
        self._event("aborted", f"dynamic run aborted: {reason}", warning=True)

    # ------------------------------------------------------------------ state
    @property
    def done(self) -> bool:
        return not self._aborted and self._elapsed >= self.length_s

    @property
    def finished(self) -> bool:
        return self._aborted or self._elapsed >= self.length_s

    def pop_events(self) -> list[SequencerEvent]:
        out, self.events = self.events, []
        return out

    def summary(self) -> dict[str, Any]:
        c = self.counters
        return {"ended": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"), "result": "done" if self.done else
                "incomplete", "reason": self.finished_reason, "poses": [], "kind": "dynamic",
                "recorded_s": self._elapsed, "planned_s": self.length_s, "messages_raw": c.messages_raw,
                "messages_temperature": c.messages_temperature, "lost_messages": c.lost,
                "repeated_messages": c.repeated, "board_resets": c.board_resets, "aux_samples": self.aux_samples,
                "write_error": self.write_error}

    def close(self, reason: str) -> dict[str, Any]:
        """Write the ``run_end`` record and finish the MCAP; returns the summary. Never raises an ``OSError`` of
        the recording (reported in the summary's ``write_error``; the file then reads up to its last chunk)."""
        self.finished_reason = self.finished_reason or reason
        return self._close_recording()

    def _measure_rate(self, elapsed_s: float) -> None:
        """Board rate from the first samples; warns at once of segments the offline fit will refuse
        (``fbg-accel-calib dynamic``: a segment at >= ``NYQUIST_FRACTION`` x the board rate)."""
        self._rate_t.append(elapsed_s)
        if len(self._rate_t) < RATE_SAMPLES:
            return
        dt = np.diff(np.asarray(self._rate_t))
        dt = dt[dt > 0]
        if dt.size == 0:
            return
        self.rate_hz = float(1.0 / np.median(dt))
        self._rate_t.clear()
        near = [seg.freq_hz for seg in self.plan.segments if seg.freq_hz >= NYQUIST_FRACTION * self.rate_hz]
        if near:
            self.messages.append(("warn", f"segment(s) at {', '.join(f'{f:g}' for f in near)} Hz are at or above "
                                  f"{NYQUIST_FRACTION:g} x the board rate of {self.rate_hz:.1f} Hz (Nyquist "
                                  f"{self.rate_hz / 2:.1f} Hz): fbg-accel-calib dynamic will refuse them; record at a "
                                  "higher board rate or drop them from the plan"))

    def _write_failed(self, exc: OSError, closing: bool = False) -> None:
        """Writing the recording failed: abort the run and say at once what is safely on disk."""
        self._say_write_failed(exc, closing, f"about {self._on_disk_s:.0f} s of the run")
        if not closing:
            self._aborted = True
            self.finished_reason = f"recording failed: {self.write_error}"
            self._event("aborted", f"dynamic run aborted: recording failed ({self.write_error})", warning=True)

    def _event(self, kind: str, message: str, warning: bool = False) -> None:
        self.events.append(SequencerEvent(self._elapsed, kind, -1, message, warning))
