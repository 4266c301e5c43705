"""rosbag2 round trip (issue 10): recordings carry full topic names and the QoS metadata of the MCAP ROS 2
profile, and the offline tools read what ``ros2 bag record -s mcap`` writes -- a bag directory of one or more
.mcap files with namespaced topics -- checked against an independent writer and reader, ``rosbags`` (a test
dependency, requirements-dev.txt: imported, so without it these tests fail instead of being skipped).
"""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import McapReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from test_fit_streaming import make_run

from fbg_accel_calibration.io import mcap_format, mcap_reader, mcap_records, mcap_schemas
from fbg_accel_calibration.io.mcap_format import McapRecordingError
from fbg_accel_calibration.io.mcap_reader import McapSampleStream, read_recording
from fbg_accel_calibration.io.mcap_writer import RecordingWriter, write_recording
from fbg_accel_calibration.io.recording import Recording
from fbg_accel_driver.driver_core import RAW_NAMES

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

BIN = Path(sys.executable).parent
TYPES = mcap_format.ROLE_TYPES  # relative topic -> type (docs/topics.md)
TOPICS = tuple(TYPES)
TS = get_typestore(Stores.ROS2_JAZZY)
RELIABLE = Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE, QosTime(0, 0),
               QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "fbg-accel-calib"), *args], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def samples() -> Recording:
    """Twelve poses over a 20 degC temperature sweep: enough for a thermal fit of degree >= 1."""
    return make_run(3, 15.0, n_poses=12, sweep_c=20.0, t0_s=1_700_000_000.0)


def stamps_of(rec: Recording) -> list[int]:
    """The sample stamps (ns) ``write_recording`` uses (t0 0): round(t_s * 1e9)."""
    return np.round(rec.t_s * 1e9).astype(np.int64).tolist()


def events(rec: Recording):
    """``(relative topic, stamp_ns, kind, payload)`` of a calibration run in this project's layout, written
    here from docs/topics.md and mcap_format's module docstring, not with RecordingWriter: a reference and a
    ``recording`` pose event when the pose starts, a ``moving`` event when the table leaves it, then the
    sample (imu/raw JointState, names RAW_NAMES)."""
    known = np.all(np.isfinite(rec.gref_mps2), axis=1)
    pose = np.where((rec.pose_id >= 0) & known, rec.pose_id, -1)
    n_poses = int(rec.pose_id.max()) + 1
    prev = None
    for i, stamp in enumerate(stamps_of(rec)):
        if pose[i] != prev:
            if pose[i] >= 0:
                yield "calibration/reference_gravity", stamp, "gref", rec.gref_mps2[i]
                yield "calibration/pose", stamp, "pose", (int(pose[i]), "recording", n_poses)
            else:
                yield "calibration/pose", stamp, "pose", (-1, "moving", -1)
            prev = pose[i]
        temp = float(rec.temp_c[i])
        values = [float(rec.ref[i]), *map(float, rec.xyz[i]), temp, 1.0 if np.isfinite(temp) else 0.0, 0.0,
                  float(i), float(rec.t_s[i])]
        yield "imu/raw", stamp, "raw", values


def rosbags_message(kind: str, stamp: int, payload):
    """A rosbags message object of the event (the typestore's own classes and CDR serializer)."""
    t = TS.types
    header = t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9),
                                      "fbg_accel_link")
    if kind == "raw":
        empty = np.array([], dtype=np.float64)
        return "sensor_msgs/msg/JointState", t["sensor_msgs/msg/JointState"](
            header, list(RAW_NAMES), np.asarray(payload, dtype=np.float64), empty, empty)
    if kind == "gref":
        header = t["std_msgs/msg/Header"](header.stamp, "calibration_table")
        return "geometry_msgs/msg/Vector3Stamped", t["geometry_msgs/msg/Vector3Stamped"](
            header, t["geometry_msgs/msg/Vector3"](*map(float, payload)))
    pid, state, count = payload
    kv = t["diagnostic_msgs/msg/KeyValue"]
    values = [kv("pose_id", str(pid)), kv("state", state), kv("index", str(pid)), kv("count", str(count))]
    return "diagnostic_msgs/msg/DiagnosticStatus", t["diagnostic_msgs/msg/DiagnosticStatus"](
        0 if state == "recording" else 1, "calibration/pose", state, "sensor-1", values)


def write_bag(path: Path, rec: Recording, namespaces: tuple[str, ...] = ("/veh1",), files: int = 2) -> Path:
    """A rosbag2 (format 9, MCAP) bag directory written by rosbags, split into ``files`` .mcap files at
    sample boundaries inside poses (as ``ros2 bag record --max-bag-size`` splits), plus an unrelated
    ``sensor_msgs/msg/Imu`` topic the tools must ignore."""
    evs = list(events(rec))
    cuts = np.linspace(0, len(evs), files + 1).astype(int)
    parts = []
    for k in range(files):
        part = path.parent / f"{path.name}_part{k}"
        with Writer(part, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            conns = {}
            for ns in namespaces:
                for rel, kind in TYPES.items():
                    conns[ns, rel] = w.add_connection(f"{ns}/{rel}", kind, typestore=TS, offered_qos_profiles=[RELIABLE])
            imu = w.add_connection(f"{namespaces[0]}/imu/data", "sensor_msgs/msg/Imu", typestore=TS)
            for rel, stamp, kind, payload in evs[cuts[k]:cuts[k + 1]]:
                msgtype, msg = rosbags_message(kind, stamp, payload)
                data = TS.serialize_cdr(msg, msgtype)
                for ns in namespaces:
                    w.write(conns[ns, rel], stamp, data)
            t = TS.types
            vec, cov = t["geometry_msgs/msg/Vector3"](0.0, 0.0, 9.8), np.zeros(9)
            imu_msg = t["sensor_msgs/msg/Imu"](rosbags_message("raw", evs[cuts[k]][1], [0.0] * 9)[1].header,
                                               t["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0), cov, vec, cov,
                                               vec, cov)
            w.write(imu, evs[cuts[k]][1], TS.serialize_cdr(imu_msg, "sensor_msgs/msg/Imu"))
        parts.append(part)
    # one bag of several files: move the parts' .mcap files together, one metadata.yaml listing them in order
    path.mkdir()
    meta = yaml.safe_load((parts[0] / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    names = []
    for k, part in enumerate(parts):
        (mcap,) = part.glob("*.mcap")
        name = f"{path.name}_{k}.mcap"
        mcap.rename(path / name)
        names.append(name)
    info["relative_file_paths"] = names
    info["files"] = [{"path": n} for n in names]
    (path / "metadata.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    return path


def qos_of(channel) -> list[dict]:
    return yaml.safe_load(channel.metadata["offered_qos_profiles"])


# ---------------------------------------------------------------------------- 1. names and QoS
@pytest.mark.parametrize("namespace,prefix", [("/", ""), ("", ""), ("/ns", "/ns"), ("veh1/", "/veh1"),
                                              ("/a/b", "/a/b")])
def test_recordings_store_full_topic_names_with_offered_qos(tmp_path: Path, namespace: str, prefix: str) -> None:
    path = tmp_path / "run.mcap"
    with RecordingWriter(path, {"sensor_id": "s"}, namespace=namespace) as w:
        w.write_raw(10, 900.0, [1.0, 2.0, 3.0], temperature_c=20.0)
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert sorted(c.topic for c in summary.channels.values()) == sorted(f"{prefix}/{t}" for t in TOPICS)
    for channel in summary.channels.values():
        (profile,) = qos_of(channel)
        assert profile["reliability"] == "reliable" and profile["history"] == "keep_last" and profile["depth"] == 10
        assert set(profile) == {"history", "depth", "reliability", "durability", "deadline", "lifespan",
                                "liveliness", "liveliness_lease_duration", "avoid_ros_namespace_conventions"}


def test_a_namespaced_file_cut_before_its_summary_still_reads(tmp_path: Path, samples: Recording) -> None:
    """Without a summary (writer killed) the topics are found while reading: the first message on one
    of the four topics fixes the namespace; another namespace given is refused listing what was found."""
    whole = tmp_path / "whole.mcap"
    with RecordingWriter(whole, namespace="/veh1", chunk_bytes=4096) as w:
        for _rel, stamp, kind, payload in events(samples):
            if kind == "raw":
                w.write_raw(stamp, payload[0], payload[1:4], temperature_c=payload[4], seq=int(payload[7]),
                            board_time_s=payload[8])
            elif kind == "gref":
                w.write_reference_gravity(stamp, payload)
            else:
                w.write_pose(stamp, payload[0], payload[1], payload[0], payload[2])
    data = whole.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    rec = read_recording(cut)
    assert 0 < len(rec) < len(samples) and not rec.metadata["read_report"]["complete"]
    np.testing.assert_array_equal(rec.pose_id, samples.pose_id[: len(rec)])
    src = McapSampleStream(cut, namespace="/veh1")
    assert sum(len(b) for b in src.blocks(500, with_poses=False)) == len(rec)
    with pytest.raises(McapRecordingError, match=r"no readable imu/raw messages \(expected topic /veh2/imu/raw"
                       r".*topics found: .*/veh1/imu/raw \(sensor_msgs/msg/JointState\)"):
        read_recording(cut, namespace="/veh2")


def _write_relative_names(path: Path, rec: Recording) -> None:
    """An old-style recording (topics ``imu/raw`` ... without a leading slash), with mcap_ros2's writer."""
    from mcap_ros2.writer import Writer as Ros2Writer

    with open(path, "wb") as fh:
        w = Ros2Writer(fh)
        schemas = {}
        for rel, stamp, kind, payload in events(rec):
            msgtype, msg = rosbags_message(kind, stamp, payload)
            if msgtype not in schemas:
                schemas[msgtype] = w.register_msgdef(msgtype, mcap_schemas.message_definition(msgtype))
            w.write_message(rel, schemas[msgtype], _as_dict(msg), log_time=stamp, publish_time=stamp)
        w.finish()


def _as_dict(msg):
    """A rosbags message as nested dicts/lists for mcap_ros2's dynamic serializer."""
    if hasattr(msg, "__dataclass_fields__"):
        return {k: _as_dict(getattr(msg, k)) for k in msg.__dataclass_fields__ if k != "__msgtype__"}
    if isinstance(msg, np.ndarray):
        return msg.tolist()
    if isinstance(msg, list):
        return [_as_dict(m) for m in msg]
    return msg


def _same_samples(a: Recording, b: Recording) -> None:
    for name in ("t_s", "xyz", "ref", "pose_id", "gref_mps2"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_readers_accept_relative_and_full_names(tmp_path: Path, samples: Recording) -> None:
    ours = tmp_path / "ours.mcap"
    write_recording(ours, samples)
    old = tmp_path / "old.mcap"
    _write_relative_names(old, samples)
    ref = read_recording(ours)
    assert ref.metadata["read_report"]["per_topic"]["/imu/raw"] == len(samples)
    assert int((ref.pose_id >= 0).sum()) > 0
    _same_samples(read_recording(old), ref)
    _same_samples(read_recording(old, namespace="/"), ref)
    _same_samples(read_recording(ours, topic="/imu/raw"), ref)
    for path in (old, ours):
        src = McapSampleStream(path)
        n = sum(len(b) for b in src.blocks(500, with_poses=False))
        got = Recording.concatenate(list(src.blocks(500, with_poses=True)))
        assert n == len(samples)
        np.testing.assert_array_equal(got.pose_id, ref.pose_id)


# ---------------------------------------------------------------------------- 2./3. bag directories
@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory, samples: Recording) -> tuple[Path, Path, Path]:
    """Our MCAP of the samples, the rosbags bag of the same samples, and the fit of our MCAP."""
    tmp = tmp_path_factory.mktemp("bag")
    ours = tmp / "ours.mcap"
    write_recording(ours, samples, {"sensor_id": "sensor-1"})
    bag = write_bag(tmp / "bag", samples)
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap" and len(info["relative_file_paths"]) == 2
    assert {"/veh1/imu/raw", "/veh1/imu/data"} <= {t["topic_metadata"]["name"] for t in info["topics_with_message_count"]}
    cal = tmp / "ours.yaml"
    res = run_cli("fit", str(ours), "-o", str(cal), "--sensor-id", "sensor-1")
    assert res.returncode == 0, res.stderr
    return ours, bag, cal


def coefficients(path: Path) -> dict:
    doc = yaml.safe_load(path.read_text())
    return {k: v for k, v in doc.items() if k not in ("fit", "created")}


@pytest.mark.parametrize("options", [["--namespace", "/veh1"], ["--namespace", "veh1"], ["--topic", "/veh1/imu/raw"],
                                     [], ["--namespace", "/veh1", "--in-memory"]])
def test_fit_of_the_bag_directory_equals_the_fit_of_our_mcap(fitted: tuple[Path, Path, Path], tmp_path: Path,
                                                            options: list[str]) -> None:
    _, bag, cal = fitted
    out = tmp_path / "bag.yaml"
    res = run_cli("fit", str(bag), "-o", str(out), "--sensor-id", "sensor-1", *options)
    assert res.returncode == 0, res.stderr
    got, want = coefficients(out), coefficients(cal)
    assert got.keys() == want.keys()
    for key in want:
        if isinstance(want[key], (list, float)):
            np.testing.assert_allclose(np.asarray(got[key], dtype=float), np.asarray(want[key], dtype=float),
                                       rtol=1e-12, atol=1e-12, err_msg=key)
        else:
            assert got[key] == want[key], key
    fit_got, fit_want = yaml.safe_load(out.read_text())["fit"], yaml.safe_load(cal.read_text())["fit"]
    assert fit_got["samples_used"] == fit_want["samples_used"] and fit_got["samples_total"] == fit_want["samples_total"]


def test_allan_report_and_diagnose_read_the_bag(fitted: tuple[Path, Path, Path], tmp_path: Path) -> None:
    ours, bag, cal = fitted
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    for src, js, options in ((ours, a, []), (bag, b, ["--namespace", "/veh1"])):
        res = run_cli("allan", str(src), "--calibration", str(cal), "-o", str(js.with_suffix(".png")), "--json", str(js),
                      *options)
        assert res.returncode == 0, res.stderr
    assert yaml.safe_load(a.read_text()) == yaml.safe_load(b.read_text())
    res = run_cli("report", str(bag), "--calibration", str(cal), "-o", str(tmp_path / "rep"), "--max-degree", "2")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "rep" / "report.md").is_file()
    from fbg_accel_calibration.io.input_files import load_recording

    _same_samples(load_recording([bag], namespace="/veh1"), read_recording(ours))


def test_several_namespaces_are_refused_and_a_missing_topic_lists_the_topics(tmp_path: Path, samples: Recording
                                                                            ) -> None:
    short = samples.select(np.arange(len(samples)) < 400)
    bag = write_bag(tmp_path / "two", short, namespaces=("/left", "/right"), files=1)
    out = tmp_path / "cal.yaml"
    res = run_cli("fit", str(bag), "-o", str(out))
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert "/left/imu/raw" in res.stderr and "/right/imu/raw" in res.stderr and "--namespace" in res.stderr
    res = run_cli("fit", str(bag), "-o", str(out), "--namespace", "/middle")
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert "no topic /middle/imu/raw" in res.stderr
    assert "/left/imu/raw (sensor_msgs/msg/JointState)" in res.stderr and "/left/imu/data (sensor_msgs/msg/Imu)" in res.stderr
    res = run_cli("diagnose", str(bag), "--namespace", "/middle")
    assert res.returncode == 2 and "no topic /middle/imu/raw" in res.stderr and "Traceback" not in res.stderr
    assert not out.exists()
    one = tmp_path / "one.mcap"  # a single MCAP file: the same message, from its summary
    with RecordingWriter(one, namespace="/veh1") as w:
        w.write_raw(10, 900.0, [1.0, 2.0, 3.0], temperature_c=20.0)
    res = run_cli("fit", str(one), "-o", str(out), "--namespace", "/veh2")
    assert res.returncode == 2 and "no topic /veh2/imu/raw" in res.stderr and "/veh1/imu/raw (sensor_msgs/msg/JointState)" \
        in res.stderr, res.stderr
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    meta["rosbag2_bagfile_information"]["relative_file_paths"] = ["../one.mcap"]
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    res = run_cli("fit", str(bag), "-o", str(out))
    assert res.returncode == 2 and "leaves the bag directory" in res.stderr, res.stderr
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {storage_identifier: sqlite3}\n")
    res = run_cli("fit", str(bag), "-o", str(out))
    assert res.returncode == 2 and "storage_identifier" in res.stderr and "-s mcap" in res.stderr, res.stderr


# ---------------------------------------------------------------------------- 3. an independent reader
def test_rosbags_decodes_every_message_of_our_recording(tmp_path: Path, samples: Recording) -> None:
    path = tmp_path / "ours.mcap"
    n = write_recording(path, samples.select(np.arange(len(samples)) < 1500))
    path_ns = tmp_path / "ns.mcap"
    with RecordingWriter(path_ns, namespace="/veh1") as w:
        w.write_raw(10, 900.0, [1.0, 2.0, 3.0], temperature_c=20.0)
        w.write_temperature(11, 20.5, 0.01)
        w.write_reference_gravity(12, [0.0, 0.0, 9.8])
        w.write_pose(13, 0, "recording", 0, 1)
    for file, prefix, count in ((path, "", n), (path_ns, "/veh1", 4)):
        reader = McapReader(file)
        reader.open()
        try:
            store = get_typestore(Stores.EMPTY)
            for conn in reader.connections:
                store.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
            assert {c.topic for c in reader.connections} == {f"{prefix}/{t}" for t in TOPICS}
            for conn in reader.connections:
                (qos,) = conn.ext.offered_qos_profiles
                assert qos.reliability == QosReliability.RELIABLE and qos.history == QosHistory.KEEP_LAST
                assert qos.depth == 10 and qos.durability == QosDurability.VOLATILE
            decoded = 0
            for conn, stamp, data in reader.messages(reader.connections):
                msg = store.deserialize_cdr(data, conn.msgtype)
                if conn.topic.endswith("imu/raw"):
                    assert list(msg.name) == list(RAW_NAMES)
                    assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp
                decoded += 1
            assert decoded == count
        finally:
            reader.close()


def test_a_bag_whose_metadata_lists_no_topics_is_read_choosing_while_reading(fitted: tuple[Path, Path, Path],
                                                                           tmp_path: Path) -> None:
    import shutil

    ours, bag, _ = fitted
    copy = tmp_path / "bare"
    shutil.copytree(bag, copy)
    meta = yaml.safe_load((copy / "metadata.yaml").read_text())
    meta["rosbag2_bagfile_information"]["topics_with_message_count"] = []
    (copy / "metadata.yaml").write_text(yaml.safe_dump(meta))
    ref = read_recording(ours)
    _same_samples(read_recording(copy), ref)
    _same_samples(read_recording(copy, namespace="/veh1"), ref)
    with pytest.raises(McapRecordingError, match=r"expected topic /veh2/imu/raw.*/veh1/imu/data \(sensor_msgs/msg/Imu\)"):
        read_recording(copy, namespace="/veh2")


# ---------------------------------------------------------------------------- what other recorders write
# Recordings written as rosbag2 writes them (plain mcap writer, ros2msg schemas, log time = the recorder's
# receive clock), with what a user's setup may put on the topic names this reader looks for.
T0 = 1_700_000_000_000_000_000
DT = 10_000_000


def driver_events(n: int, pose_len: int = 500, move_len: int = 100, t0: int = T0,
                  shift: dict[int, int] | None = None) -> list[tuple[str, int, bytes]]:
    """``(relative topic, stamp, CDR)`` of a driver + table run: a ``moving`` event, then after ``move_len``
    samples a reference and a ``recording`` event of the next pose; raw sample i has ref_counts 1e6 + i (and its
    stamp moved by ``shift[i]`` ns)."""
    from fbg_accel_calibration.io import ros2_cdr

    codec = ros2_cdr.FixedJointStateCodec("fbg_accel_link", RAW_NAMES)
    out = []
    for i in range(n):
        st, ph = t0 + i * DT, i % (pose_len + move_len)
        if ph == 0:
            out.append(("calibration/pose", st, ros2_cdr.diagnostic_status(
                1, "calibration/pose", "moving", "s", [("pose_id", "-1"), ("state", "moving")])))
        if ph == move_len:
            pid = i // (pose_len + move_len)
            g = [0.0, 0.0, 9.81] if pid % 2 == 0 else [9.81, 0.0, 0.0]
            out.append(("calibration/reference_gravity", st, ros2_cdr.vector3_stamped(st, "calibration_table", g)))
            out.append(("calibration/pose", st, ros2_cdr.diagnostic_status(
                0, "calibration/pose", "recording", "s", [("pose_id", str(pid)), ("state", "recording")])))
        if i % 10 == 0:
            out.append(("imu/temperature", st, ros2_cdr.temperature(st, "fbg_accel_link", 20.0, 0.01)))
        st += (shift or {}).get(i, 0)
        out.append(("imu/raw", st, codec.encode(st, [1e6 + i, 1.0, 2.0, 3.0, 20.0, 1.0, 0.0, float(i), i * 0.01])))
    return out


def write_foreign(path: Path, evs: list[tuple[str, int, bytes]], types: dict[str, str] | None = None,
                  defs: dict[str, str] | None = None, log_offset_ns: int = 0) -> Path:
    """An MCAP as ``ros2 bag record`` writes it: topics ``/fbg/<relative>`` of ``types`` (default the project's),
    schemas ``defs`` (default the installed definitions), log time = stamp + ``log_offset_ns``."""
    from mcap.writer import CompressionType

    from fbg_accel_calibration.io.rosbag2_input import offered_qos_yaml

    types = {**TYPES, **(types or {})}
    with open(path, "wb") as fh:
        w = McapWriter(fh, chunk_size=32 * 1024, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="rosbag2-like")
        chans = {}
        for rel, ty in types.items():
            sid = w.register_schema(ty, "ros2msg", (defs or {}).get(rel, mcap_schemas.message_definition(ty)).encode())
            chans[rel] = w.register_channel(f"/fbg/{rel}", "cdr", sid, metadata={"offered_qos_profiles": offered_qos_yaml()})
        for rel, st, data in evs:
            w.add_message(chans[rel], log_time=st + log_offset_ns, publish_time=st + log_offset_ns, data=data)
        w.finish()
    return path


def _cdr_string(text: str) -> bytes:
    b = text.encode() + b"\0"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(b)) + b


@pytest.mark.parametrize(("rel", "other_type", "payload"), [
    ("imu/temperature", "std_msgs/msg/Float64", b"\x00\x01\x00\x00" + struct.pack("<d", 21.5)),
    ("calibration/pose", "std_msgs/msg/String", _cdr_string('{"pose_id": 1}')),
])
def test_a_sibling_topic_of_another_type_is_ignored_with_a_warning(tmp_path: Path, rel: str, other_type: str,
                                                                   payload: bytes) -> None:
    """A user's own node publishes std_msgs on /fbg/imu/temperature or /fbg/calibration/pose: it was decoded as
    the project's type (AttributeError: 'Float64' object has no attribute 'header'); now it is one of the
    other topics, never decoded, with one warning line naming the file, the topic and its type."""
    evs = [(r, st, payload if r == rel else d) for r, st, d in driver_events(1000)]
    path = write_foreign(tmp_path / "other_type.mcap", evs, types={rel: other_type})
    for rec in (read_recording(path), mcap_reader.read_file(path)[0]):
        assert np.array_equal(rec.ref, 1e6 + np.arange(1000))
        lines = mcap_records.read_warnings(path, rec.metadata["read_report"], rec.metadata["pose_events"])
        hits = [ln for ln in lines if f"/fbg/{rel}" in ln]
        assert len(hits) == 1 and str(path) in hits[0] and other_type in hits[0] and "ignored" in hits[0], lines
    stream = McapSampleStream(path)
    assert sum(len(b) for b in stream.blocks(256, False)) == 1000
    assert len(list(stream.blocks(256, True))) == 4


@pytest.mark.parametrize(("rel", "old", "new"), [
    ("imu/raw", "string[] name", "string[] joint_names"),
    ("imu/temperature", "float64 temperature", "float64 temp"),
    ("calibration/reference_gravity", "Vector3 vector", "Vector3 direction"),
    ("calibration/pose", "KeyValue[] values", "KeyValue[] items"),
    ("calibration/pose", "string key", "string name_of_key"),
])
def test_a_type_of_the_same_name_with_another_definition_is_one_line(tmp_path: Path, rel: str, old: str, new: str,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Same type name, another definition (a renamed field, same CDR layout): was an AttributeError, and a
    traceback from ``fbg-accel-calib``; now one line naming the file, the topic, the type and the field."""
    from fbg_accel_calibration.commands.cli import main

    definition = mcap_schemas.message_definition(TYPES[rel])
    assert old in definition
    path = write_foreign(tmp_path / "other_definition.mcap", driver_events(1000), defs={rel: definition.replace(old, new)})
    field = old.split()[1]
    pattern = rf"other_definition\.mcap: topic /fbg/{rel}'s schema {TYPES[rel]} lacks field \S*{field} \(a different definition\)"
    with pytest.raises(McapRecordingError, match=pattern):
        mcap_reader.read_file(path)
    with pytest.raises(McapRecordingError, match=pattern):
        list(McapSampleStream(path).blocks(256, False))
    assert main(["fit", str(path), "-o", str(tmp_path / "cal.yaml")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and "lacks field" in err, err


@pytest.mark.parametrize("offset_s", [0.003, 0.5, 2.0])
def test_pose_events_follow_the_samples_when_the_recorder_clock_is_offset(tmp_path: Path, offset_s: float) -> None:
    """``ros2 bag record`` on another machine logs every message at its own receive clock: pose events (no
    header) were placed at that log time, the samples at the driver's stamps, and with a 0.5 s offset 450 of
    3000 samples got another pose. Pose events now go on the samples' clock; a file whose log time is the stamp
    (the calibration node's) reads as before."""
    evs = driver_events(3000)
    same, _ = mcap_reader.read_file(write_foreign(tmp_path / "same_clock.mcap", evs))
    assert sorted(set(same.pose_id.tolist())) == [-1, 0, 1, 2, 3, 4] and np.sum(same.pose_id == -1) == 500
    offset = write_foreign(tmp_path / "recorder_ahead.mcap", evs, log_offset_ns=int(offset_s * 1e9))
    rec, _ = mcap_reader.read_file(offset)
    assert np.array_equal(rec.pose_id, same.pose_id)
    assert np.array_equal(rec.gref_mps2, same.gref_mps2, equal_nan=True)
    stream = McapSampleStream(offset)
    for _ in stream.blocks(700, False):
        pass
    streamed = Recording.concatenate(list(stream.blocks(700, True)))
    assert np.array_equal(streamed.pose_id, same.pose_id)


def _bag(path: Path, names: list[str], **info) -> Path:
    path.joinpath("metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": {
        "version": 9, "storage_identifier": "mcap", "relative_file_paths": names, **info,
        "topics_with_message_count": [{"topic_metadata": {"name": f"/fbg/{rel}", "type": ty}, "message_count": 1}
                                      for rel, ty in TYPES.items()]}}))
    return path


def test_stamps_going_backwards_are_named_in_a_warning(tmp_path: Path) -> None:
    """The driver restarted with a clock 5 s behind: the in-memory reader sorted the samples and merged the two
    stretches without a word. It still sorts, and now says where the stamps went back."""
    evs = driver_events(1000) + driver_events(1000, t0=T0 + 5_000_000_000)
    path = write_foreign(tmp_path / "restarted.mcap", evs)
    rec, _ = mcap_reader.read_file(path)
    assert len(rec) == 2000
    lines = mcap_records.read_warnings(path, rec.metadata["read_report"], rec.metadata["pose_events"])
    hits = [ln for ln in lines if "go back" in ln]
    assert len(hits) == 1 and str(path) in hits[0] and "sample 1000" in hits[0] and "go back 4.990 s" in hits[0], lines
    jitter = write_foreign(tmp_path / "jitter.mcap", driver_events(1000, shift={501: -10_500_000}))  # 0.5 ms back
    rec, _ = mcap_reader.read_file(jitter)
    lines = mcap_records.read_warnings(jitter, rec.metadata["read_report"])
    assert len(rec) == 1000 and not [ln for ln in lines if "go back" in ln]


def test_an_mcap_file_the_bag_metadata_does_not_list_is_named(tmp_path: Path) -> None:
    """A bag whose recorder was killed lists only the files it had finished: the others were passed over
    silently. They are still not read (metadata.yaml says what the bag is), with a warning naming them."""
    bag = tmp_path / "killed"
    bag.mkdir()
    write_foreign(bag / "killed_0.mcap", driver_events(1000))
    write_foreign(bag / "killed_1.mcap", driver_events(1000, t0=T0 + 20_000_000_000))
    _bag(bag, ["killed_0.mcap"])
    rec = read_recording(bag)
    assert len(rec) == 1000
    lines = mcap_records.read_warnings(bag, rec.metadata["read_report"])
    hits = [ln for ln in lines if "killed_1.mcap" in ln]
    assert len(hits) == 1 and "ros2 bag reindex" in hits[0] and "not listed" in hits[0], lines


def test_a_file_compressed_bag_is_refused_for_its_compression(tmp_path: Path) -> None:
    """``ros2 bag record --compression-mode file`` writes ``*.mcap.zstd``: it was refused as 'not an MCAP
    recording (magic bytes)', which sends the user looking for a damaged file."""
    import zstandard

    from fbg_accel_calibration.io.input_files import check_inputs

    bag = tmp_path / "compressed"
    bag.mkdir()
    plain = write_foreign(tmp_path / "plain.mcap", driver_events(100))
    (bag / "compressed_0.mcap.zstd").write_bytes(zstandard.ZstdCompressor().compress(plain.read_bytes()))
    _bag(bag, ["compressed_0.mcap.zstd"], compression_mode="FILE", compression_format="zstd")
    for call in (lambda: check_inputs([bag]), lambda: read_recording(bag)):
        with pytest.raises(ValueError, match=r"compression_mode 'FILE' \(zstd\).*not read.*ros2 bag"):
            call()


def test_a_bag_that_lists_a_file_twice_reads_it_once_with_a_note(tmp_path: Path) -> None:
    """``relative_file_paths`` naming ``run_0.mcap`` twice (a hand-edited or merged metadata.yaml): every sample was
    fitted twice (1651 + 1651) and the warning guessed a driver restart. The file is read once, and a note says so."""
    bag = tmp_path / "twice"
    bag.mkdir()
    write_foreign(bag / "run_0.mcap", driver_events(1000))
    write_foreign(bag / "run_1.mcap", driver_events(1000, t0=T0 + 20_000_000_000))
    _bag(bag, ["run_0.mcap", "run_1.mcap", "./run_0.mcap"])
    rec = read_recording(bag)
    assert len(rec) == 2000
    lines = mcap_records.read_warnings(bag, rec.metadata["read_report"])
    hits = [ln for ln in lines if "run_0.mcap" in ln]
    assert len(hits) == 1 and "twice" in hits[0] and "read once" in hits[0], lines
    assert not [ln for ln in lines if "go back" in ln], lines
