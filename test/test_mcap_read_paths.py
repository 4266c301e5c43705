"""The MCAP reader's shortcuts give what the generic path gives: runs of fixed-layout raw records cut where a record
of another layout starts, event messages read from ``ros2_cdr``'s layouts equal to the ``mcap_ros2`` decoder's
reading of the same bytes, and an event schema of another layout read by its decoder."""

from __future__ import annotations

import bisect
import random
import struct
from pathlib import Path

import numpy as np
import pytest
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from ros2_mcap import ros2_messages

from fbg_accel_calibration.io import mcap_records, ros2_cdr
from fbg_accel_calibration.io.mcap_format import (
    ROLE_TYPES,
    TOPIC_POSE,
    TOPIC_RAW,
    TOPIC_REFERENCE_GRAVITY,
    TOPIC_TEMPERATURE,
    TYPE_RAW,
)
from fbg_accel_calibration.io.mcap_reader import _event_fields, _event_reader, read_recording
from fbg_accel_calibration.io.mcap_schemas import message_definition, standard_event_schema
from fbg_accel_calibration.io.mcap_writer import RecordingWriter
from fbg_accel_driver.driver_core import RAW_NAMES

T0 = 1_700_000_000_000_000_000  # ns
EVENT_ROLES = (TOPIC_TEMPERATURE, TOPIC_REFERENCE_GRAVITY, TOPIC_POSE)


def _schema(role: str, text: str | None = None) -> Schema:
    name = ROLE_TYPES[role]
    return Schema(id=1, name=name, encoding="ros2msg", data=(text or message_definition(name)).encode())


def _messages(role: str, rng: random.Random) -> list[bytes]:
    """Messages of ``role`` as the recorder writes them: frame ids and strings of several lengths (empty, odd,
    non-ASCII), stamps around the epoch, values of every sign."""
    out = []
    for i in range(40):
        stamp = rng.choice((0, 1, 999_999_999, T0 + i * 10_000_000, -1_500_000_000))
        frame = rng.choice(("", "a", "calibration_table", "imu_lïnk", "x" * 13))
        if role == TOPIC_TEMPERATURE:
            out.append(ros2_cdr.temperature(stamp, frame, rng.uniform(-40, 85), rng.choice((0.0, 0.09, -0.0))))
        elif role == TOPIC_REFERENCE_GRAVITY:
            out.append(ros2_cdr.vector3_stamped(stamp, frame, [rng.uniform(-10, 10) for _ in range(3)]))
        else:
            pairs = [(rng.choice(("pose_id", "state", "index", "", "ψ")), rng.choice(("0", "-1", "recording", "")))
                     for _ in range(rng.randint(0, 5))]
            out.append(ros2_cdr.diagnostic_status(rng.randint(0, 3), frame, rng.choice(("moving", "", "é")), frame,
                                                  pairs))
    return out


def _mutants(data: bytes, rng: random.Random) -> list[bytes]:
    """``data`` with bytes changed (lengths, paddings, NULs, values), cut short, or with bytes appended."""
    out = [data[:-1], data + b"\0", data + b"\0" * 4, data[:len(data) // 2]]
    for _ in range(60):
        b = bytearray(data)
        for _ in range(rng.randint(1, 2)):
            b[rng.randrange(len(b))] = rng.choice((0, 1, 2, 4, 8, 0x80, 0xFF, rng.randrange(256)))
        out.append(bytes(b))
    return out


def _bits(value: object) -> object:
    """``value`` with every float as its 8 bytes (NaN equal to the same NaN)."""
    if isinstance(value, float):
        return struct.pack("<d", value)
    if isinstance(value, tuple | list):
        return type(value)(_bits(v) for v in value)
    if isinstance(value, dict):
        return {k: _bits(v) for k, v in value.items()}
    return value


@pytest.mark.parametrize("role", EVENT_ROLES)
def test_an_event_read_from_its_bytes_is_what_the_ros2_decoder_reads(role: str) -> None:
    """Every message the recorder writes is read by the shortcut (not the decoder), and whatever bytes the shortcut
    takes -- changed lengths, paddings, frame ids, strings without their NUL -- it reads as ``mcap_ros2`` does."""
    rng = random.Random(7)
    schema = _schema(role)
    decode = DecoderFactory().decoder_for("cdr", schema)
    taken = 0
    for data in _messages(role, rng):
        first = decode(data)
        reader = _event_reader(role, schema, first)
        assert reader is not None
        assert reader(data) == _event_fields(role, first)  # the recorder's own bytes: taken
        for other in _messages(role, rng)[:5] + _mutants(data, rng):
            got = reader(other)
            if got is None:
                continue
            taken += 1
            assert _bits(got) == _bits(_event_fields(role, decode(other))), other
    assert taken > 0


@pytest.mark.parametrize("role", EVENT_ROLES)
def test_an_event_schema_is_standard_only_field_for_field(role: str) -> None:
    """The shortcut needs the standard definition: the same fields in the same order, comments and constants aside."""
    text = message_definition(ROLE_TYPES[role])
    assert standard_event_schema(_schema(role, text), role)
    assert standard_event_schema(_schema(role, "# a comment\n" + text.replace("\n", "  # note\n", 1)), role)
    assert not standard_event_schema(None, role)
    lines = text.splitlines()
    fields = [i for i, line in enumerate(lines) if line.split("#")[0].strip() and "=" not in line
              and not line.startswith("MSG:")][:2]
    swapped = list(lines)
    swapped[fields[0]], swapped[fields[1]] = lines[fields[1]], lines[fields[0]]
    assert not standard_event_schema(_schema(role, "\n".join(swapped)), role)
    assert not standard_event_schema(_schema(role, text.replace("\n", "\nfloat64 extra\n", 1)), role)


def test_a_temperature_schema_of_another_order_is_read_by_its_decoder(tmp_path: Path) -> None:
    """A ``sensor_msgs/msg/Temperature`` whose definition puts the variance first: its messages are read as that
    definition says (the decoder), not in the standard layout; the raw messages, without a temperature field, take
    their temperature from these messages."""
    from mcap_ros2.writer import Writer

    swapped = message_definition(ROLE_TYPES[TOPIC_TEMPERATURE]).replace("float64 temperature", "float64 TEMP_SLOT")
    swapped = swapped.replace("float64 variance", "float64 temperature").replace("float64 TEMP_SLOT", "float64 variance")
    path = tmp_path / "swapped.mcap"
    names = list(RAW_NAMES[:4])
    with open(path, "wb") as fh:
        w = Writer(fh)
        raw = w.register_msgdef(TYPE_RAW, message_definition(TYPE_RAW))
        temp = w.register_msgdef(ROLE_TYPES[TOPIC_TEMPERATURE], swapped)
        for i in range(30):
            stamp = T0 + i * 10_000_000
            header = {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "imu"}
            w.write_message(TOPIC_TEMPERATURE, temp, {"header": header, "temperature": 20.0 + i, "variance": 0.5},
                            log_time=stamp)
            w.write_message(TOPIC_RAW, raw, {"header": header, "name": names, "position": [900.0, 1.0, 2.0, 3.0],
                                             "velocity": [], "effort": []}, log_time=stamp)
        w.finish()
    rec = read_recording(path)
    np.testing.assert_array_equal(rec.temp_c, 20.0 + np.arange(30))


def _raw_records(codec: ros2_cdr.FixedJointStateCodec, n: int, channel: int = 1) -> list[bytes]:
    """``n`` raw message records (opcode, length, message header, CDR) of ``codec`` on ``channel``."""
    out = []
    for i in range(n):
        data = codec.encode(T0 + i, [float(i)] * codec.n_values)
        body = mcap_records._MESSAGE_HEAD.pack(channel, i, T0 + i, T0 + i) + data
        out.append(mcap_records._RECORD_HEAD.pack(5, len(body)) + body)
    return out


@pytest.mark.parametrize("where", ["head", "channel", "encapsulation", "middle", "last middle byte"])
def test_a_run_of_raw_records_ends_at_the_first_record_of_another_layout(where: str) -> None:
    """Runs longer and shorter than a window, cut by one record whose opcode/length, channel, encapsulation or frame
    id and names differ from the layout's by one byte: the runs hold exactly the records before and after it, and
    that record goes to the decoder (as a message)."""
    codec = ros2_cdr.FixedJointStateCodec("imu", tuple(RAW_NAMES))
    fast: dict = {}
    mcap_records._set_fast(fast, 1, codec)
    byte = {"head": 3, "channel": 9, "encapsulation": 32, "middle": 50, "last middle byte": 43 + len(codec.middle) - 1}
    for n, odd in ((1, 0), (3, 2), (700, 1), (700, 512), (3000, 2047), (3000, 2999)):
        records = _raw_records(codec, n)
        bad = bytearray(records[odd])
        bad[byte[where]] ^= 0x01
        records[odd] = bytes(bad)
        items = list(mcap_records._split_chunks([b"".join(records)], fast, bytearray()))
        runs = [item for item in items if isinstance(item, np.ndarray)]
        messages = [item for item in items if isinstance(item, tuple)]
        if where == "head":  # another length: a message record that takes in what follows, or overruns the chunk
            first_other = next(item for item in items if not isinstance(item, np.ndarray))
            assert first_other is mcap_records.PARTIAL_RECORD or first_other[1] == T0 + odd
        else:  # the odd record alone, as a message (on channel 0 when its channel byte changed)
            assert [m[2] for m in messages] == [bytes(bad[31:])]
        got = [int(v) for r in runs for v in r["values"][:, 0]]
        if where == "head":
            assert got[:odd] == list(range(odd))
        else:
            assert got == [i for i in range(n) if i != odd], (n, odd)
        assert sum(len(r) for r in runs) == len(got)


def test_a_recording_of_many_splits_reads_as_the_ros2_decoder_reads_it(tmp_path: Path) -> None:
    """A file of several megabytes of chunks (several splits through one reused buffer), events between the raw
    messages: every sample and event as ``mcap_ros2`` decodes them, in order."""
    path = tmp_path / "long.mcap"
    rng = np.random.default_rng(3)
    n = 12_000
    with RecordingWriter(path, chunk_bytes=32 * 1024) as w:
        for i in range(n):
            stamp = T0 + i * 1_000_000
            if i % 97 == 0:
                w.write_pose(stamp, i // 97, "recording" if i % 2 else "settling", index=i // 97, count=n // 97)
                w.write_reference_gravity(stamp, rng.normal(0, 5, 3))
            counts = rng.integers(0, 4096, 4).astype(float)
            w.write_raw(stamp, counts[0], counts[1:], temperature_c=20.0 + i * 1e-4, status=3, seq=i,
                        board_time_s=i * 1e-3)
    rec = read_recording(path)
    raws = [m for topic, _, _, m in ros2_messages(path) if topic.endswith(TOPIC_RAW)]
    assert len(rec) == len(raws) == n
    values = np.array([m.position for m in raws])
    names = list(raws[0].name)
    np.testing.assert_array_equal(rec.ref, values[:, names.index("ref_counts")])
    np.testing.assert_array_equal(rec.xyz, values[:, [names.index(c) for c in ("x_counts", "y_counts", "z_counts")]])
    np.testing.assert_array_equal(rec.t_s, values[:, names.index("board_time_s")])
    stamps = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in raws])
    np.testing.assert_array_equal(stamps, T0 + np.arange(n) * 1_000_000)
    messages = ros2_messages(path)
    poses = [(t, int({kv.key: kv.value for kv in m.values}["pose_id"]), m.message) for topic, t, _, m in messages
             if topic.endswith(TOPIC_POSE)]
    assert poses == rec.metadata["pose_events"]
    refs = [(t, (m.vector.x, m.vector.y, m.vector.z)) for topic, t, _, m in messages
            if topic.endswith(TOPIC_REFERENCE_GRAVITY)]
    want_pose, want_gref = np.full(n, -1), np.full((n, 3), np.nan)
    for i, stamp in enumerate(stamps):  # the latest event at or before each sample (log time = stamp here)
        k = bisect.bisect_right([e[0] for e in poses], stamp)
        if k and poses[k - 1][2] == "recording":
            want_pose[i] = poses[k - 1][1]
            want_gref[i] = refs[bisect.bisect_right([t for t, _ in refs], stamp) - 1][1]
    assert (want_pose >= 0).any() and (want_pose < 0).any()
    np.testing.assert_array_equal(rec.pose_id, want_pose)
    np.testing.assert_array_equal(rec.gref_mps2, want_gref)
