"""DynamicRunRecorder (pure core of a dynamic calibration run): board time, chunks and counters, no ROS."""

from __future__ import annotations

from pathlib import Path

from ros2_mcap import frames_by_topic

from fbg_accel_calibration.dynamic.excitation_plan import ExcitationPlan
from fbg_accel_calibration.io.mcap_writer import RecordingWriter
from fbg_accel_calibration.recorder.dynamic_recorder import DynamicRunRecorder
from fbg_accel_calibration.recorder.pose_recorder import RawSample
from fbg_accel_driver.frame_codec import Status

RATE = 100.0
PLAN = Path(__file__).resolve().parents[1] / "config" / "excitation_plan_stepped_sine.yaml"


def test_a_board_reset_neither_stalls_the_run_nor_its_chunks_nor_counts_as_lost(tmp_path):
    """A v2 board that had been up 60 s when the run started reboots 20 s into it: its clock restarts at 0
    and seq at 0 (BOOT on the first frame). The recorder measured the run as board time minus the first
    sample's, which went negative: the run ran 188 s instead of 108 (80 s of the slide's rest recorded as
    part of the run, the node exits that much late), no chunk was ended for 81 s (a SIGKILL then loses
    them), and the seq jump counted as lost messages. Board time must run on across the reset."""
    plan = ExcitationPlan.load(PLAN)
    writer = RecordingWriter(tmp_path / "dyn.mcap", {"kind": "dynamic"})
    flushed: list[int] = []
    flush = writer.flush

    def counting_flush() -> None:
        flushed.append(n)
        flush()

    writer.flush = counting_flush  # type: ignore[method-assign]
    rec = DynamicRunRecorder(plan, writer, sensor_id="t")
    reset_at = round(20 * RATE)
    n = 0
    while not rec.finished and n < round(3 * rec.length_s * RATE):
        j = n - reset_at
        board_t, seq = (60.0 + n / RATE, (6000 + n) % 65536) if j < 0 else (j / RATE, j)
        status = Status.TEMP_VALID | (Status.BOOT if j == 0 else 0)
        rec.on_raw(RawSample(stamp_ns=10**18 + n * 10_000_000, ref=2000.0, x=1000.0, y=1000.0, z=1500.0,
                             temperature_c=24.0, status=int(status), seq=seq, board_time_s=board_t, aux=2048.0))
        n += 1
    summary = rec.close("complete" if rec.done else "aborted")
    assert rec.done
    recorded_s = n / RATE
    assert abs(recorded_s - rec.length_s) <= 5 / RATE, f"run lasted {recorded_s:.1f} s for {rec.length_s:.1f} s planned"
    gaps = [b - a for a, b in zip([0, *flushed], flushed, strict=False)]
    assert max(gaps) <= RATE * 1.0 + 3, f"longest stretch without a chunk end: {max(gaps) / RATE:.1f} s"
    assert (summary["lost_messages"], summary["repeated_messages"], summary["board_resets"]) == (0, 0, 1)


def test_disk_full_aborts_a_dynamic_run_without_raising(tmp_path, monkeypatch):
    """ENOSPC at a chunk end: the OSError escaped on_raw (the node died with a traceback) and close() raised
    again. The run ends aborted with a warning naming the error; close() returns the summary."""
    import errno

    from fbg_accel_calibration.io import mcap_writer

    orig = mcap_writer._UnbufferedSink.write

    def full(self, data):
        if self._pos + len(data) > 20_000:
            raise OSError(errno.ENOSPC, "No space left on device")
        return orig(self, data)

    monkeypatch.setattr(mcap_writer._UnbufferedSink, "write", full)
    rec = DynamicRunRecorder(ExcitationPlan.load(PLAN), RecordingWriter(tmp_path / "dyn.mcap", {}), sensor_id="t")
    n = 0
    while not rec.finished and n < 20_000:
        rec.on_raw(RawSample(stamp_ns=10**18 + n * 10_000_000, ref=2000.0, x=1000.0, y=1000.0, z=1500.0, seq=n,
                             board_time_s=n / RATE, aux=2048.0 + n % 7))  # must not raise
        n += 1
    assert rec.finished and not rec.done
    assert any(level == "warn" and "ENOSPC" in text for level, text in rec.pop_messages())
    summary = rec.close("test")  # must not raise
    assert summary["result"] == "incomplete" and "ENOSPC" in summary["write_error"]


def test_segments_near_the_nyquist_frequency_of_the_board_are_warned_at_once(tmp_path):
    """A 60 Hz segment on a 100 Hz board: fbg-accel-calib dynamic refuses it after the run (>= 0.45 fs), but the
    recorder, which knows the board rate after a few samples, recorded the whole plan without a word."""
    plan = ExcitationPlan.from_dict({
        "format": "fbg_accel_excitation_plan", "format_version": 1, "direction": [0.5, -0.5, 0.70710678],
        "reference": {"type": "ldv", "sensitivity_counts_per_mps": 2500.0},
        "segments": [{"freq_hz": 2.0, "amplitude_mps2": 2.0, "duration_s": 6.0},
                     {"freq_hz": 60.0, "amplitude_mps2": 2.0, "duration_s": 6.0}]})
    rec = DynamicRunRecorder(plan, RecordingWriter(tmp_path / "dyn.mcap", {}))
    msgs = []
    for i in range(50):  # 0.5 s
        rec.on_raw(RawSample(stamp_ns=10**18 + i * 10**7, ref=870, x=2000, y=2000, z=2000, seq=i, board_time_s=i / RATE,
                             aux=2048.0))
        msgs += rec.pop_messages()
    rec.close("test")
    warned = [text for level, text in msgs if level == "warn" and "Nyquist" in text]
    assert len(warned) == 1 and "segment(s) at 60 Hz are" in warned[0], warned


def test_a_dynamic_run_is_recorded_in_the_frame_the_driver_published_it_in(tmp_path):
    """``imu/raw`` of a driver with ``frame_id: acc_b_link``: the raw messages and the reference (a vector in the
    sensor frame) must say ``acc_b_link``. On the unchanged code the dynamic recorder never looked at the
    messages' frame: everything was written in the writer's default 'fbg_accel_link'."""
    plan = ExcitationPlan.load(PLAN)
    writer = RecordingWriter(tmp_path / "dyn.mcap", {"kind": "dynamic"})
    rec = DynamicRunRecorder(plan, writer, sensor_id="t")
    for n in range(200):
        rec.on_raw(RawSample(stamp_ns=10**18 + n * 10_000_000, ref=2000.0, x=1000.0, y=1000.0, z=1500.0,
                             temperature_c=24.0, status=int(Status.TEMP_VALID), seq=n, board_time_s=n / RATE,
                             aux=2048.0, frame_id="acc_b_link"))
    rec.close("aborted")
    frames = frames_by_topic(tmp_path / "dyn.mcap")
    assert frames["/imu/raw"] == {"acc_b_link"}, frames
    assert frames["/calibration/reference_velocity"] == {"acc_b_link"}, frames
