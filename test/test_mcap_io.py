"""MCAP recordings: ROS 2 profile round trip through the ``mcap`` reader + ``mcap_ros2`` decoder,
pose assignment, truncated files and a writer killed with SIGKILL."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from fbg_accel_calibration.io.mcap_format import (
    TOPIC_POSE,
    TOPIC_RAW,
    TOPIC_REFERENCE_GRAVITY,
    TOPIC_TEMPERATURE,
    McapRecordingError,
)
from fbg_accel_calibration.io.mcap_reader import read_recording
from fbg_accel_calibration.io.mcap_schemas import message_definition
from fbg_accel_calibration.io.mcap_writer import RecordingWriter, write_recording
from fbg_accel_calibration.io.recording import Recording
from fbg_accel_driver.driver_core import RAW_NAMES

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

T0 = 1_700_000_000_000_000_000  # ns


def _write_run(path: Path, n_per_pose: int = 40, poses: int = 3) -> list[tuple[str, int, dict]]:
    """Write a small run; returns what was written as (topic, stamp_ns, fields) in order."""
    written: list[tuple[str, int, dict]] = []
    rng = np.random.default_rng(1)
    t = T0
    with RecordingWriter(path, {"sensor_id": "fbg-7", "plan": {"poses": poses}, "operator_notes": "unit test"},
                         chunk_bytes=2048) as w:
        seq = 0
        for p in range(poses):
            t += 1  # the move starts after the last sample of the previous pose
            w.write_pose(t, -1, "moving", index=p, count=poses)
            written.append((TOPIC_POSE, t, {"pose_id": -1, "state": "moving"}))
            t += 10_000_000
            g = rng.normal(0.0, 5.0, 3)
            w.write_reference_gravity(t, g)
            written.append((TOPIC_REFERENCE_GRAVITY, t, {"g": g}))
            w.write_pose(t, p, "recording", index=p, count=poses, extra={"psi_deg": 30.0 * p})
            written.append((TOPIC_POSE, t, {"pose_id": p, "state": "recording"}))
            for _ in range(n_per_pose):
                t += 10_000_000
                counts = rng.integers(0, 4096, 4).astype(float)
                temp = 20.0 + 0.01 * seq
                w.write_raw(t, counts[0], counts[1:], temperature_c=temp, status=3, seq=seq, board_time_s=seq * 0.01)
                written.append((TOPIC_RAW, t, {"counts": counts, "temp": temp, "seq": seq}))
                w.write_temperature(t, temp, 0.09)
                written.append((TOPIC_TEMPERATURE, t, {"temp": temp}))
                seq += 1
        w.write_pose(t + 1, -1, "done", index=poses, count=poses)
        written.append((TOPIC_POSE, t + 1, {"pose_id": -1, "state": "done"}))
    return written


def test_round_trip_message_for_message_with_ros2_decoder(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    written = _write_run(path)
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        got = list(reader.iter_decoded_messages(log_time_order=False))
        summary = reader.get_summary()
        metadata = list(reader.iter_metadata())
    assert summary is not None and summary.statistics.chunk_count > 3  # small chunks
    for schema in summary.schemas.values():
        assert schema.encoding == "ros2msg"
    for channel in summary.channels.values():
        assert channel.message_encoding == "cdr"
    raw_schema = next(s for s in summary.schemas.values() if s.name == "sensor_msgs/msg/JointState")
    assert b"MSG: std_msgs/Header" in raw_schema.data and b"MSG: builtin_interfaces/Time" in raw_schema.data
    assert len(got) == len(written)
    for (topic, stamp, fields), item in zip(written, got, strict=True):
        assert item.channel.topic == "/" + topic  # full names (root namespace)
        assert item.message.log_time == stamp
        msg = item.decoded_message
        if topic == TOPIC_RAW:
            assert tuple(msg.name) == RAW_NAMES
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp
            assert list(msg.position[:4]) == list(fields["counts"])
            assert msg.position[4] == fields["temp"] and msg.position[5] == 1.0 and msg.position[6] == 3.0
            assert msg.position[7] == fields["seq"]
            assert msg.position[8] == pytest.approx(fields["seq"] * 0.01)
        elif topic == TOPIC_TEMPERATURE:
            assert msg.temperature == fields["temp"] and msg.variance == 0.09
        elif topic == TOPIC_REFERENCE_GRAVITY:
            assert [msg.vector.x, msg.vector.y, msg.vector.z] == list(fields["g"])
            assert msg.header.frame_id == "calibration_table"
        else:
            values = {kv.key: kv.value for kv in msg.values}
            assert int(values["pose_id"]) == fields["pose_id"] and values["state"] == fields["state"]
            assert msg.message == fields["state"]
    assert [m.name for m in metadata] == ["run"]
    assert metadata[0].metadata["sensor_id"] == "fbg-7"
    assert metadata[0].metadata["operator_notes"] == "unit test"
    assert metadata[0].metadata["plan"] == '{"poses": 3}'


def test_read_recording_assigns_pose_and_reference(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    written = _write_run(path)
    rec = read_recording(path)
    raws = [f for topic, _, f in written if topic == TOPIC_RAW]
    grefs = [f["g"] for topic, _, f in written if topic == TOPIC_REFERENCE_GRAVITY]
    assert len(rec) == len(raws)
    np.testing.assert_array_equal(rec.xyz, np.array([f["counts"][1:] for f in raws]))
    np.testing.assert_array_equal(rec.ref, np.array([f["counts"][0] for f in raws]))
    np.testing.assert_allclose(rec.t_s, np.arange(len(raws)) * 0.01)
    np.testing.assert_array_equal(rec.pose_id, np.repeat(np.arange(3), 40))
    np.testing.assert_array_equal(rec.gref_mps2, np.repeat(np.array(grefs), 40, axis=0))
    assert rec.metadata["run"]["sensor_id"] == "fbg-7"
    assert rec.metadata["read_report"]["complete"] is True


def test_samples_outside_recording_state_have_no_pose(tmp_path: Path) -> None:
    path = tmp_path / "moving.mcap"
    with RecordingWriter(path) as w:
        w.write_raw(T0, 900, (1, 2, 3))  # before any pose event
        w.write_reference_gravity(T0 + 1, (0.0, 0.0, 9.8))
        w.write_pose(T0 + 1, 0, "settling")
        w.write_raw(T0 + 2, 900, (1, 2, 3))
        w.write_pose(T0 + 3, 0, "recording")
        w.write_raw(T0 + 4, 900, (1, 2, 3), temperature_c=math.nan, temperature_valid=False)
        w.write_pose(T0 + 5, -1, "moving")
        w.write_raw(T0 + 6, 900, (1, 2, 3))
    rec = read_recording(path)
    np.testing.assert_array_equal(rec.pose_id, [-1, -1, 0, -1])
    assert np.isnan(rec.gref_mps2[[0, 1, 3]]).all()
    np.testing.assert_array_equal(rec.gref_mps2[2], [0.0, 0.0, 9.8])
    assert np.isnan(rec.temp_c[2])


def test_truncated_file_reads_up_to_last_complete_chunk(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    written = _write_run(path, n_per_pose=200)
    raw_stamps = np.array([s for topic, s, _ in written if topic == TOPIC_RAW])
    data = path.read_bytes()
    with open(path, "rb") as fh:
        chunks = sorted(make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    previous = 0
    last_end = chunks[-1].chunk_start_offset + chunks[-1].chunk_length
    for cut in np.linspace(chunks[1].chunk_start_offset + chunks[1].chunk_length, last_end - 1, 7).astype(int):
        cut_path = tmp_path / f"cut_{cut}.mcap"
        cut_path.write_bytes(data[:cut])
        complete = [c for c in chunks if c.chunk_start_offset + c.chunk_length <= cut]
        assert complete, "cut before the first chunk ends: choose larger cuts"
        expected = int(np.sum(raw_stamps <= complete[-1].message_end_time))
        rec = read_recording(cut_path)
        report = rec.metadata["read_report"]
        assert report["complete"] is False and report["stopped_at"]
        assert len(rec) == expected
        assert len(rec) >= previous
        previous = len(rec)
        # what was recovered is exactly the head of the written series
        np.testing.assert_allclose(rec.t_s, np.arange(expected) * 0.01)
    assert previous < len(raw_stamps)


_KILL_CHILD = r"""
import sys
from fbg_accel_calibration.io.mcap_writer import RecordingWriter
w = RecordingWriter(sys.argv[1], {"sensor_id": "killed"}, chunk_bytes=4096)
w.write_reference_gravity(0, (0.0, 0.0, 9.80665))
w.write_pose(0, 0, "recording")
i = 0
while True:
    i += 1
    w.write_raw(i * 10_000_000, 1000 + i % 7, (i % 4096, 2, 3), temperature_c=25.0, seq=i, board_time_s=i * 0.01)
    if i == 3000:
        w.flush()
        print("FLUSHED", i, flush=True)
"""


def test_sigkilled_writer_leaves_a_readable_file(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen([sys.executable, "-c", _KILL_CHILD, str(path)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()  # blocks until the child has flushed 3000 messages (pytest-timeout bounds it)
        assert line.startswith("FLUSHED"), line
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    rec = read_recording(path)
    assert rec.metadata["read_report"]["complete"] is False
    assert rec.metadata["run"]["sensor_id"] == "killed"
    assert len(rec) >= 3000
    np.testing.assert_array_equal(rec.xyz[:, 0], np.arange(1, len(rec) + 1) % 4096)
    assert (rec.pose_id == 0).all()


def test_a_moving_reference_is_no_pose_event_and_reads_back_as_moving(tmp_path: Path) -> None:
    """A table that reports its angles while it moves (the simulator's does) must not give a pose event per moving
    sample: the moving samples' reference is not written. A recorded pose whose reference changes is an event.
    Written in one go or block by block (the CSV importer), the events are the same. write_recording's round trip:
    counts, temperatures (a NaN among them) and times read back as written."""
    from fbg_accel_calibration.io.mcap_writer import pose_events

    n = 60
    rng = np.random.default_rng(4)
    pose = np.repeat([0, -1, 1, -1, 2], [15, 10, 15, 5, 15])
    gref = np.where(pose[:, None] >= 0, rng.normal(size=(4, 3))[pose + 1], rng.normal(size=(n, 3)))  # moving: known
    gref[52:] += 0.5  # the reference of pose 2 changes while it is recorded
    temp = np.full(n, 23.4)
    temp[7] = np.nan
    rec = Recording(np.arange(n) * 0.1, rng.integers(800, 900, n), rng.integers(0, 4096, (n, 3)), temp, gref, pose)
    write_recording(tmp_path / "m.mcap", rec, {"sensor_id": "sim"})
    with open(tmp_path / "m.mcap", "rb") as f:
        events = sum(1 for _, ch, _ in make_reader(f).iter_messages() if ch.topic.endswith("calibration/pose"))
    assert events == 6  # 0, moving, 1, moving, 2, 2 with its new reference
    back = read_recording(tmp_path / "m.mcap")  # and the samples read back as written
    np.testing.assert_array_equal(back.pose_id, pose)
    np.testing.assert_array_equal(back.gref_mps2, np.where(pose[:, None] >= 0, gref, np.nan))
    np.testing.assert_array_equal(back.xyz, rec.xyz)
    np.testing.assert_array_equal(back.ref, rec.ref)
    np.testing.assert_array_equal(back.temp_c, rec.temp_c)  # NaN (no valid reading) included
    np.testing.assert_allclose(back.t_s, rec.t_s)
    whole = pose_events(rec.pose_id, rec.gref_mps2)[1]
    for cut in range(1, n):
        first = pose_events(rec.pose_id[:cut], rec.gref_mps2[:cut])
        rest = pose_events(rec.pose_id[cut:], rec.gref_mps2[cut:], (int(first[0][-1]), rec.gref_mps2[cut - 1]))
        np.testing.assert_array_equal(np.concatenate([first[1], rest[1]]), whole)


def test_several_files_become_runs(tmp_path: Path) -> None:
    _write_run(tmp_path / "a.mcap", n_per_pose=5)
    _write_run(tmp_path / "b.mcap", n_per_pose=7)
    rec = read_recording([tmp_path / "a.mcap", tmp_path / "b.mcap"])
    np.testing.assert_array_equal(np.bincount(rec.run_id), [15, 21])


def test_bad_inputs_give_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(McapRecordingError, match="not found"):
        read_recording(tmp_path / "nope.mcap")
    with RecordingWriter(tmp_path / "empty.mcap") as w:
        w.write_temperature(T0, 20.0)
    with pytest.raises(McapRecordingError, match="no readable imu/raw"):
        read_recording(tmp_path / "empty.mcap")
    with pytest.raises(McapRecordingError, match="pose state"):
        with RecordingWriter(tmp_path / "bad.mcap") as w:
            w.write_pose(T0, 0, "wobbling")
    with pytest.raises(McapRecordingError, match="not found"):
        message_definition("no_such_pkg/msg/Thing")


def test_each_message_is_byte_identical_to_the_ros2_encoder(tmp_path: Path) -> None:
    """Every message kind the writer encodes itself (ros2_cdr) against the same message written through
    mcap_ros2's public writer and read back as bytes: the layouts, alignment and padding agree."""
    from mcap_ros2.writer import Writer

    from fbg_accel_calibration.io import ros2_cdr
    from fbg_accel_calibration.io.mcap_format import TYPE_POSE, TYPE_RAW, TYPE_REFERENCE_GRAVITY, TYPE_TEMPERATURE

    rng = np.random.default_rng(7)
    cases = []  # (datatype, dict for mcap_ros2, our bytes)
    for frame_id in ("fbg_accel_link", "", "abc"):
        stamp = int(rng.integers(0, 2**31 * 10**9))
        header = {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": frame_id}
        for names in (RAW_NAMES, (*RAW_NAMES, "aux_counts")):
            values = [float(v) for v in rng.normal(size=len(names))]
            values[4] = math.nan
            cases.append((TYPE_RAW, {"header": header, "name": list(names), "position": values, "velocity": [],
                                     "effort": []}, ros2_cdr.FixedJointStateCodec(frame_id, names).encode(stamp, values)))
        t, var = (float(v) for v in rng.normal(size=2))
        cases.append((TYPE_TEMPERATURE, {"header": header, "temperature": t, "variance": var},
                      ros2_cdr.temperature(stamp, frame_id, t, var)))
        v = rng.normal(size=3)
        cases.append((TYPE_REFERENCE_GRAVITY, {"header": header, "vector": dict(zip("xyz", map(float, v), strict=True))},
                      ros2_cdr.vector3_stamped(stamp, frame_id, v)))
        pairs = [("pose_id", "3"), ("state", frame_id), ("psi_deg", "-90.5")][: len(frame_id) % 4]
        cases.append((TYPE_POSE, {"level": len(frame_id) % 3, "name": "calibration/pose", "message": frame_id,
                                  "hardware_id": frame_id[:1], "values": [{"key": k, "value": x} for k, x in pairs]},
                      ros2_cdr.diagnostic_status(len(frame_id) % 3, "calibration/pose", frame_id, frame_id[:1], pairs)))
    path = tmp_path / "reference.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        schemas = {t: w.register_msgdef(t, message_definition(t)) for t in {c[0] for c in cases}}
        for i, (datatype, msg, _) in enumerate(cases):
            w.write_message(f"/t{i}", schemas[datatype], msg, log_time=i)
        w.finish()
    with open(path, "rb") as fh:
        theirs = [m.data for _, _, m in make_reader(fh).iter_messages(log_time_order=True)]
    assert len(theirs) == len(cases)
    for (datatype, _, ours), data in zip(cases, theirs, strict=True):
        assert ours == data, datatype
    for frame_id in ("fbg_accel_link", ""):  # the reader's fast path recognises the layout
        codec = ros2_cdr.FixedJointStateCodec(frame_id, RAW_NAMES)
        assert codec.matches(codec.encode(T0, [0.0] * len(RAW_NAMES)))


def test_reads_raw_messages_written_by_another_ros2_writer(tmp_path: Path) -> None:
    """A file written with the generic mcap_ros2 writer (as a bag recorder would), with two frame ids:
    the reader's fast path and its generic fallback give the same values."""
    from mcap_ros2.writer import Writer

    from fbg_accel_calibration.io.mcap_format import TYPE_RAW

    path = tmp_path / "other.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        schema = w.register_msgdef(TYPE_RAW, message_definition(TYPE_RAW))
        for i in range(50):
            stamp = T0 + i * 10_000_000
            w.write_message(TOPIC_RAW, schema, {
                "header": {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "a" if i < 30 else "bbb"},
                "name": list(RAW_NAMES), "position": [900.0 + i, 1.0 * i, 2.0, 3.0, 21.5, 1.0, 0.0, float(i), i * 0.01],
                "velocity": [], "effort": []}, log_time=stamp)
        w.finish()
    rec = read_recording(path)
    np.testing.assert_array_equal(rec.ref, 900.0 + np.arange(50))
    np.testing.assert_array_equal(rec.xyz[:, 0], np.arange(50.0))
    np.testing.assert_allclose(rec.t_s, np.arange(50) * 0.01)
    assert (rec.pose_id == -1).all() and np.isnan(rec.gref_mps2).all()


def test_writer_notices_that_its_path_no_longer_names_the_file_it_writes(tmp_path: Path) -> None:
    """Writes into a deleted (unlinked) file succeed on Linux: a removed output directory went unnoticed
    until the run was over. flush() and close() check the path against the open file (device, inode)."""
    from fbg_accel_calibration.io.mcap_writer import RecordingLostError

    w = RecordingWriter(tmp_path / "a.mcap", {"sensor_id": "t"})
    w.write_temperature(1, 24.0)
    w.flush()  # the path names the file: no error
    (tmp_path / "a.mcap").unlink()
    (tmp_path / "a.mcap").write_bytes(b"someone else's file")
    with pytest.raises(RecordingLostError, match="replaced"):
        w.flush()
    (tmp_path / "a.mcap").unlink()
    with pytest.raises(RecordingLostError, match="no longer exists"):
        w.close()
    w.close()  # closed: idempotent
