"""Calibration recordings as MCAP files with the ROS 2 profile (ros2msg schemas, CDR messages).

Pure Python + numpy + ``mcap``/``mcap_ros2`` (no rclpy): the calibration node, the CSV importer and
the tests all write through :class:`RecordingWriter`; the fit and the diagnosis read through
:func:`read_recording`. Files open in ``ros2 bag info``/``ros2 bag play`` (rosbag2 MCAP storage)
and Foxglove because every schema is the full concatenated ``.msg`` text of the type and its
dependencies, exactly as rosbag2 writes it.

Topics (stamps are ROS time in ns; the MCAP log time of every message equals its stamp):

* ``imu/raw`` -- ``sensor_msgs/msg/JointState``, the driver's raw topic (see docs/topics.md):
  ``name`` = :data:`RAW_NAMES`, ``position`` = the values as float64 (temperature_c NaN if never valid).
* ``imu/temperature`` -- ``sensor_msgs/msg/Temperature`` (degC, variance in degC^2).
* ``calibration/reference_gravity`` -- ``geometry_msgs/msg/Vector3Stamped``: reference specific force
  of a pose in the table frame, m/s^2, written when the pose's reference becomes known (frame_id
  ``calibration_table``).
* ``calibration/pose`` -- ``diagnostic_msgs/msg/DiagnosticStatus`` (chosen over std_msgs/String+JSON
  because it is a standard message whose key/value list Foxglove and ``ros2 topic echo`` show
  readably): ``name`` = ``calibration/pose``, ``message`` = the pose state, ``hardware_id`` = sensor
  id, ``values`` = key/value pairs ``pose_id``, ``state``, ``index``, ``count`` and optionally
  ``psi_deg``, ``theta_deg``, ``setpoint_c``. ``level`` is OK while recording, WARN while moving or
  settling.

Pose states (:data:`POSE_STATES`): ``moving`` (table moving, no reference), ``settling`` (table at the
pose, waiting for the static detector), ``recording`` (static, samples belong to the pose), ``done``.
:func:`read_recording` gives a sample the pose id and reference gravity of the latest pose event at
or before its stamp when that event's state is ``recording``; otherwise pose_id -1 and NaN reference. A pose
event has no header stamp: it is put on the samples' clock with the (log time - stamp) offset of the raw
message before it in the file, so a recorder whose clock is not the driver's (``ros2 bag record`` on another
machine) places it where it was published; in the files written here that offset is 0.

Run metadata (sensor id, plan, operator notes, ...) are MCAP Metadata records named ``run``
(string -> string; non-string values are stored as JSON).

Crash safety: the file is written through an unbuffered OS file with small chunks (default 32 KiB
uncompressed); every finished chunk goes to the OS at once, so a writer killed with SIGKILL leaves
a file whose complete chunks read back (:func:`read_recording` stops at the first incomplete
record and reports how many messages it recovered).
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import logging
import math
import os
import re
import struct
import sys
import zlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Metadata, Schema
from mcap.stream_reader import get_chunk_data_stream
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory

from fbg_accel_driver.command_line import first_line
from fbg_accel_driver.driver_core import RAW_AUX_NAME, RAW_NAMES

from . import ros2_cdr
from .atomic_output import create_exclusive
from .pass_spill import PassSpill
from .recording import Recording
from .rosbag2_input import BagInputError, bag_files, offered_qos_yaml

MCAP_MAGIC = b"\x89MCAP0\r\n"  # first bytes of an MCAP file (mcap.dev specification)

LOG = logging.getLogger(__name__)

TOPIC_RAW = "imu/raw"
TOPIC_TEMPERATURE = "imu/temperature"
TOPIC_REFERENCE_GRAVITY = "calibration/reference_gravity"
TOPIC_POSE = "calibration/pose"

TYPE_RAW = "sensor_msgs/msg/JointState"
TYPE_TEMPERATURE = "sensor_msgs/msg/Temperature"
TYPE_REFERENCE_GRAVITY = "geometry_msgs/msg/Vector3Stamped"
TYPE_POSE = "diagnostic_msgs/msg/DiagnosticStatus"
ROLES = (TOPIC_RAW, TOPIC_TEMPERATURE, TOPIC_REFERENCE_GRAVITY, TOPIC_POSE)  # topic names relative to the namespace
ROLE_TYPES = dict(zip(ROLES, (TYPE_RAW, TYPE_TEMPERATURE, TYPE_REFERENCE_GRAVITY, TYPE_POSE), strict=True))

POSE_STATES = ("moving", "settling", "recording", "done")
TABLE_FRAME = "calibration_table"
DEFAULT_CHUNK_BYTES = 32 * 1024
REPLAY_ROWS = 1 << 16  # rows per batch of the samples a later pass takes from the first one (McapSampleStream)
BACKWARDS_TOLERANCE_NS = 1_000_000  # raw stamps going back less than this are jitter, read without a note

_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
               "uint32", "int64", "uint64", "string", "wstring"}
_SEPARATOR = "=" * 80
_CONSTANT = re.compile(r"^\S+\s+[A-Z][A-Z0-9_]*\s*=")


class McapRecordingError(ValueError):
    """An MCAP file cannot be written or read as a calibration recording."""


class RecordingLostError(OSError):
    """The path of a :class:`RecordingWriter` no longer names the file it writes (the file or its directory
    was deleted, or replaced, while recording): Linux keeps writing into the unlinked file, which is lost."""


# ---------------------------------------------------------------------------- topic names
def normalize_namespace(namespace: str | None) -> str:
    """ROS namespace with one leading slash and none trailing: ``""``/``"/"`` -> ``"/"``, ``"ns/"`` -> ``"/ns"``."""
    return "/" + (namespace or "").strip().strip("/")


def full_topic_name(namespace: str, relative: str) -> str:
    """``/ns/relative`` (``/relative`` in the root namespace)."""
    ns = normalize_namespace(namespace)
    return ("" if ns == "/" else ns) + "/" + relative.strip("/")


def _absolute(topic: str) -> str:
    return topic if topic.startswith("/") else "/" + topic


def _namespace_of(topic: str, relative: str = TOPIC_RAW) -> str:
    """Namespace of a full ``.../<relative>`` name (``/`` for ``/imu/raw`` or a name of another form)."""
    t = _absolute(topic)
    suffix = "/" + relative
    return normalize_namespace(t[: -len(suffix)]) if t.endswith(suffix) else "/"


def _topic_list(topics: dict[str, str]) -> str:
    return ", ".join(f"{t} ({ty})" for t, ty in sorted(topics.items())) or "none"


class TopicSelection:
    """Which channels of a recording are its ``imu/raw``, ``imu/temperature``, ``calibration/*`` topics.

    Channel topics are compared as full names: a relative name (old recordings: ``imu/raw``) means the
    root namespace (``/imu/raw``). ``namespace`` (e.g. ``/veh1``) selects ``/veh1/imu/raw`` and its
    siblings; ``raw_topic`` names the raw topic itself (its namespace, unless given, is the part before
    ``/imu/raw``). With neither, the first ``.../imu/raw`` channel of type ``sensor_msgs/msg/JointState``
    fixes the namespace, and another namespace with such a channel is refused (give ``namespace``);
    :meth:`resolve` makes that choice up front from a topic list (bag metadata or MCAP summary). Without a
    topic list (a file cut short before its summary) the first message on any of the four topics, with its
    type, fixes the namespace (a recorder writes pose events before the first sample).
    """

    def __init__(self, namespace: str | None = None, raw_topic: str | None = None) -> None:
        self.namespace = normalize_namespace(namespace) if namespace is not None else None
        self.raw_topic = _absolute(raw_topic) if raw_topic else None
        if self.namespace is None and self.raw_topic is not None:
            self.namespace = _namespace_of(self.raw_topic)
        self._cache: dict[str, str | None] = {}
        self.mismatched: dict[str, str | None] = {}  # topic with a role's name but another type -> its type

    @property
    def fixed(self) -> bool:
        return self.namespace is not None

    def expected_raw(self) -> str:
        """The raw topic looked for, for messages (``.../imu/raw`` before the namespace is known)."""
        if self.raw_topic is not None:
            return self.raw_topic
        return full_topic_name(self.namespace, TOPIC_RAW) if self.namespace is not None else f".../{TOPIC_RAW}"

    def _names(self) -> dict[str, str]:
        names = {full_topic_name(self.namespace or "/", rel): rel for rel in ROLES}
        if self.raw_topic is not None:
            names = {t: r for t, r in names.items() if r != TOPIC_RAW}
            names[self.raw_topic] = TOPIC_RAW
        return names

    def role(self, topic: str, type_name: str | None, where: str | Path = "") -> str | None:
        """The relative role name (:data:`ROLES`) of a channel, or None for a topic this reader ignores: another
        name, or a sibling's name with a type other than :data:`ROLE_TYPES` (noted in :attr:`mismatched`; the raw
        topic of another type keeps its role, so that reading it gives its one-line error)."""
        if topic in self._cache and self.fixed:
            return self._cache[topic]
        full = _absolute(topic)
        if not self.fixed:
            rel = next((r for r in ROLES if full.endswith("/" + r) and type_name == ROLE_TYPES[r]), None)
            if rel is None:
                return None
            self.namespace = _namespace_of(full, rel)
            self._cache.clear()
            self.mismatched.clear()
        elif (full.endswith("/" + TOPIC_RAW) and type_name == TYPE_RAW and self.raw_topic is None
              and self._auto and _namespace_of(full) != self.namespace):
            raise McapRecordingError(f"{where}: several namespaces have a {TYPE_RAW} {TOPIC_RAW} topic "
                                     f"({full_topic_name(self.namespace, TOPIC_RAW)}, {full}); choose one with "
                                     "--namespace")
        role = self._names().get(full)
        if role is not None and role != TOPIC_RAW and type_name != ROLE_TYPES[role]:
            self.mismatched[topic] = type_name  # another node's topic of that name: ignored, never decoded
            role = None
        self._cache[topic] = role
        return role

    _auto = False  # True when the namespace was chosen by the reader (then a second one is an error)

    @classmethod
    def resolve(cls, topics: dict[str, str], namespace: str | None, raw_topic: str | None,
                where: str | Path) -> TopicSelection:
        """Choose the topics from ``topics`` (full or relative name -> type) before reading: with
        ``namespace``/``raw_topic`` the expected raw topic must be there with type JointState; without,
        exactly one namespace may have a JointState ``.../imu/raw``. One-line :class:`McapRecordingError`
        listing the topics found (with types) otherwise."""
        sel = cls(namespace, raw_topic)
        absolute = {_absolute(t): ty for t, ty in topics.items()}
        if sel.fixed:
            raw = sel.expected_raw()
            if raw not in absolute:
                raise McapRecordingError(f"{where}: no topic {raw}; topics found: {_topic_list(topics)}; give "
                                         "--namespace or --topic")
            if absolute[raw] != TYPE_RAW:
                raise McapRecordingError(f"{where}: topic '{raw}' has type '{absolute[raw]}', expected '{TYPE_RAW}'")
            return sel
        raws = sorted(t for t, ty in absolute.items() if t.endswith("/" + TOPIC_RAW) and ty == TYPE_RAW)
        if not raws:
            named = sorted(t for t in topics if _absolute(t).endswith("/" + TOPIC_RAW))
            if named:
                raise McapRecordingError(f"{where}: topic '{named[0]}' has type '{topics[named[0]]}', expected "
                                         f"'{TYPE_RAW}'; topics found: {_topic_list(topics)}")
            raise McapRecordingError(f"{where}: no {TYPE_RAW} topic named .../{TOPIC_RAW}; topics found: "
                                     f"{_topic_list(topics)}; give --topic")
        if len(raws) > 1:
            raise McapRecordingError(f"{where}: several namespaces have a {TYPE_RAW} {TOPIC_RAW} topic ("
                                     + ", ".join(raws) + "); choose one with --namespace")
        sel.namespace = _namespace_of(raws[0])
        return sel


def _summary_topics(path: Path) -> dict[str, str] | None:
    """Topic -> type from an MCAP file's summary section (None when it has none, e.g. a truncated file)."""
    try:
        with open(path, "rb") as fh:
            records = _summary_records(fh)
    except Exception:  # no or damaged summary: the readers find the topics while reading
        return None
    if not records:
        return None
    schemas = {r.id: r.name for r in records if isinstance(r, Schema)}
    channels = {r.id: r for r in records if isinstance(r, Channel)}
    if not channels:
        return None
    return {c.topic: schemas.get(c.schema_id, "no schema") for c in channels.values()}


_SUMMARY_OPCODES = frozenset((Opcode.SCHEMA, Opcode.CHANNEL, Opcode.CHUNK_INDEX, Opcode.ATTACHMENT_INDEX,
                              Opcode.METADATA_INDEX, Opcode.STATISTICS, Opcode.SUMMARY_OFFSET))


def _summary_records(fh: Any) -> list[Any] | None:
    """The schema and channel records of the summary section (MCAP spec), or None unless the records from the
    footer's ``summary_start`` to the footer are summary records that tile that stretch exactly, walked by their
    framing alone (a footer pointing at a chunk of zeros is no summary: it must not start a walk over millions of
    9-byte records); the other summary records (chunk indexes, statistics, ...) are passed over unparsed."""
    size = fh.seek(0, io.SEEK_END)
    footer_at = size - len(MCAP_MAGIC) - 9 - 20
    if footer_at < len(MCAP_MAGIC):
        return None
    fh.seek(footer_at)
    head = fh.read(9 + 8)
    if head[0] != Opcode.FOOTER:
        return None
    (pos,) = struct.unpack_from("<Q", head, 9)
    if pos == 0 or pos > footer_at:
        return None  # no summary
    fh.seek(pos)
    data = fh.read(footer_at - pos)
    at, end, records = 0, len(data), []
    while at < end:
        if at + 9 > end or data[at] not in _SUMMARY_OPCODES:
            return None
        opcode, length = _RECORD_HEAD.unpack_from(data, at)
        if at + 9 + length > end:
            return None
        if opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            records.append(_PARSED[opcode].read(ReadDataStream(io.BytesIO(data[at + 9:at + 9 + length]))))
        at += 9 + length
    return records


def recording_files(path: str | Path, namespace: str | None = None, raw_topic: str | None = None
                    ) -> tuple[list[Path], TopicSelection, list[str]]:
    """The MCAP files of one recording, its topic selection and warning lines about it: a rosbag2 bag directory
    (its ``metadata.yaml`` files in order, topics chosen from its topic list; a note names the .mcap files it does
    not list) or one MCAP file (topics chosen from its summary, or while reading when it has none)."""
    path = Path(path)
    if path.is_dir():
        try:
            info = bag_files(path)
        except BagInputError as exc:
            raise McapRecordingError(str(exc)) from None
        files, topics, notes = info.files, info.topics, info.notes()
    elif path.is_file():
        files, topics, notes = [path], _summary_topics(path), []
    else:
        raise McapRecordingError(f"{path}: file not found")
    if not topics:  # a metadata.yaml without its topic list, a file cut before its summary: choose while reading
        sel = TopicSelection(namespace, raw_topic)
        sel._auto = not sel.fixed
        return files, sel, notes
    return files, TopicSelection.resolve(topics, namespace, raw_topic, path), notes


# ---------------------------------------------------------------------------- message definitions
def _find_msg_file(package: str, name: str) -> Path:
    tried = []
    prefixes = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    for prefix in [*prefixes, Path(sys.prefix)]:
        candidate = prefix / "share" / package / "msg" / f"{name}.msg"
        tried.append(str(candidate))
        if candidate.is_file():
            return candidate
    raise McapRecordingError(f"message definition {package}/msg/{name} not found; looked in: {', '.join(tried)}")


def _dependencies(package: str, text: str) -> list[tuple[str, str]]:
    """Non-primitive field types (package, name) referenced by a .msg text, in order of appearance."""
    deps: list[tuple[str, str]] = []
    for raw_line in text.splitlines():
        line = raw_line.split("#", 1)[0].strip()
        if not line or _CONSTANT.match(line):  # a constant definition: "type NAME=value"
            continue
        field_type = line.split()[0]
        base = re.sub(r"\[.*?\]$", "", field_type)
        base = re.sub(r"<=\d+$", "", base)
        if base in _PRIMITIVES:
            continue
        parts = base.split("/")
        dep = (package, parts[0]) if len(parts) == 1 else (parts[0], parts[-1])
        if dep not in deps:
            deps.append(dep)
    return deps


def message_definition(datatype: str) -> str:
    """Full ros2msg schema text of ``datatype`` (``pkg/msg/Name``): its .msg text followed by every
    dependency as ``====...`` / ``MSG: pkg/Name`` / text, the format rosbag2 writes into MCAP."""
    package, _, name = datatype.split("/")
    main_text = _find_msg_file(package, name).read_text(encoding="utf-8")
    out = [main_text.rstrip("\n")]
    seen = {(package, name)}
    queue = _dependencies(package, main_text)
    while queue:
        dep = queue.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        text = _find_msg_file(*dep).read_text(encoding="utf-8")
        out.append(f"{_SEPARATOR}\nMSG: {dep[0]}/{dep[1]}\n{text.rstrip(chr(10))}")
        queue.extend(d for d in _dependencies(dep[0], text) if d not in seen)
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------- writer
class _UnbufferedSink:
    """Write-through file wrapper: every ``write`` reaches the OS before returning (SIGKILL-safe)."""

    def __init__(self, path: Path, exclusive: bool = False) -> None:
        self._raw = io.FileIO(create_exclusive(path) if exclusive else str(path), "wb")  # exclusive: no overwrite, no link
        self._pos = 0
        st = os.fstat(self._raw.fileno())
        self.identity = (st.st_dev, st.st_ino)  # the file written, to check that its path still names it

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            written = self._raw.write(view)
            if written is None:  # pragma: no cover - only for non-blocking files
                continue
            view = view[written:]
        self._pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        """Nothing is buffered in this process; ``os.fsync`` is left to :meth:`sync`."""

    def sync(self) -> None:
        os.fsync(self._raw.fileno())

    def close(self) -> None:
        self._raw.close()


class RecordingWriter:
    """Incremental MCAP writer of one calibration run (ROS 2 profile, CDR, zstd chunks).

    ``metadata`` is written at once as the MCAP metadata record ``run`` (e.g. ``sensor_id``, ``plan``,
    ``operator_notes``); :meth:`add_metadata` adds more records later. ``exclusive=True`` creates the
    file with ``O_CREAT|O_EXCL|O_NOFOLLOW`` (``FileExistsError`` if a file or any symbolic link is there).
    All ``stamp_ns`` arguments are ROS time in nanoseconds. Use as a context manager or call :meth:`close`.
    """

    def __init__(self, path: str | Path, metadata: dict[str, Any] | None = None, *,
                 chunk_bytes: int = DEFAULT_CHUNK_BYTES, compression: str = "zstd",
                 frame_id: str = "fbg_accel_link", exclusive: bool = False, namespace: str = "/") -> None:
        self.path = Path(path)
        self.namespace = normalize_namespace(namespace)
        self.topics = {rel: full_topic_name(self.namespace, rel) for rel in ROLES}  # relative -> full name
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in comp:
            raise McapRecordingError(f"compression must be one of {sorted(comp)}, got {compression!r}")
        self._sink = _UnbufferedSink(self.path, exclusive)
        self._writer = McapWriter(self._sink, chunk_size=chunk_bytes, compression=comp[compression])
        self._writer.start(profile="ros2", library="fbg_accel_calibration.io.mcap_io")
        self._channels: dict[str, int] = {}
        self._closed = False
        self.message_count = 0
        for topic, datatype in ROLE_TYPES.items():
            self._register(topic, datatype)
        self._raw_codec: ros2_cdr.FixedJointStateCodec
        self._aux_codec: ros2_cdr.FixedJointStateCodec | None = None  # imu/raw with aux_counts (created when first needed)
        self.frame_id = frame_id  # builds the raw encoder
        if metadata:
            self.add_metadata("run", metadata)

    @property
    def frame_id(self) -> str:
        """The sensor frame written into ``imu/raw``, ``imu/temperature`` and a dynamic run's reference: the
        frame of the latest raw message (``write_raw(frame_id=...)``), else the constructor's."""
        return self._frame_id

    @frame_id.setter
    def frame_id(self, value: str) -> None:
        # the raw encoders hold the frame in their precomputed bytes: a new frame needs new encoders
        self._frame_id = value
        self._raw_codec = ros2_cdr.FixedJointStateCodec(value, RAW_NAMES)
        self._aux_codec = None

    def _register(self, topic: str, datatype: str) -> None:
        """Channel of the relative ``topic`` under the full name ``/<namespace>/<topic>``, with the
        ``offered_qos_profiles`` metadata of the ROS 2 profile (reliable, volatile, keep_last 10)."""
        schema_id = self._writer.register_schema(datatype, SchemaEncoding.ROS2, message_definition(datatype).encode())
        qos = offered_qos_yaml(reliable=True, depth=10)
        self._channels[topic] = self._writer.register_channel(self.topics[topic], MessageEncoding.CDR, schema_id,
                                                              metadata={"offered_qos_profiles": qos})

    def _write(self, topic: str, stamp_ns: int, data: bytes) -> None:
        """One CDR-encoded message (:mod:`ros2_cdr`) whose log and publish time are its stamp."""
        if self._closed:
            raise McapRecordingError(f"{self.path}: writer is closed")
        self._writer.add_message(self._channels[topic], log_time=int(stamp_ns), data=data,
                                 publish_time=int(stamp_ns), sequence=self.message_count)
        self.message_count += 1

    # -- message kinds
    def write_raw(self, stamp_ns: int, ref_counts: float, xyz_counts: Any, temperature_c: float = math.nan,
                  temperature_valid: bool = True, status: int = 0, seq: int = 0,
                  board_time_s: float | None = None, aux_counts: float | None = None,
                  frame_id: str | None = None) -> None:
        """One ``imu/raw`` JointState: counts, AHT10 temperature (degC), status flags, sequence, board time (s),
        and the aux channel's counts of a version-2 board (``aux_counts``, appended as the driver does).
        ``frame_id``: the frame the message was received in (a driver's ``frame_id`` parameter); it becomes
        :attr:`frame_id`, so later temperature and reference messages say the same sensor frame. None or empty:
        :attr:`frame_id` as it is."""
        if frame_id and frame_id != self._frame_id:
            self.frame_id = frame_id
        x, y, z = (float(v) for v in xyz_counts)
        values = [float(ref_counts), x, y, z, float(temperature_c), 1.0 if temperature_valid else 0.0,
                  float(status), float(seq), float(stamp_ns) * 1e-9 if board_time_s is None else float(board_time_s)]
        if aux_counts is not None:
            if self._aux_codec is None:
                self._aux_codec = ros2_cdr.FixedJointStateCodec(self.frame_id, (*RAW_NAMES, RAW_AUX_NAME))
            self._write(TOPIC_RAW, stamp_ns, self._aux_codec.encode(stamp_ns, [*values, float(aux_counts)]))
            return
        self._write(TOPIC_RAW, stamp_ns, self._raw_codec.encode(stamp_ns, values))

    def write_reference_motion(self, stamp_ns: int, kind: str, vector: Any) -> None:
        """The reference transducer of a dynamic run on its own topic, ``calibration/reference_velocity``
        (``kind`` 'velocity', m/s) or ``calibration/reference_acceleration`` ('acceleration', m/s^2):
        ``geometry_msgs/Vector3Stamped``, the value along the slide direction as a vector in the sensor
        frame. The channel is registered on first use."""
        if kind not in ("velocity", "acceleration"):
            raise McapRecordingError(f"reference kind must be 'velocity' or 'acceleration', got {kind!r}")
        topic = f"calibration/reference_{kind}"
        if topic not in self._channels:
            self.topics[topic] = full_topic_name(self.namespace, topic)
            self._register(topic, TYPE_REFERENCE_GRAVITY)
        self._write(topic, stamp_ns, ros2_cdr.vector3_stamped(stamp_ns, self.frame_id, vector))

    def write_temperature(self, stamp_ns: int, temperature_c: float, variance_c2: float = 0.0,
                          frame_id: str | None = None) -> None:
        """One ``imu/temperature`` message (degC, variance degC^2) in ``frame_id``, the frame it was received in
        (None: :attr:`frame_id`, that of the raw messages)."""
        self._write(TOPIC_TEMPERATURE, stamp_ns,
                    ros2_cdr.temperature(stamp_ns, frame_id or self.frame_id, float(temperature_c), float(variance_c2)))

    def write_reference_gravity(self, stamp_ns: int, gref_mps2: Any) -> None:
        """Reference specific force (3,) of the current pose in the table frame, m/s^2."""
        self._write(TOPIC_REFERENCE_GRAVITY, stamp_ns, ros2_cdr.vector3_stamped(stamp_ns, TABLE_FRAME, gref_mps2))

    def write_pose(self, stamp_ns: int, pose_id: int, state: str, index: int = -1, count: int = -1,
                   extra: dict[str, Any] | None = None, sensor_id: str = "") -> None:
        """Pose event: ``state`` in :data:`POSE_STATES`; ``index``/``count`` = pose k of N (0-based k)."""
        if state not in POSE_STATES:
            raise McapRecordingError(f"pose state must be one of {POSE_STATES}, got {state!r}")
        values = {"pose_id": int(pose_id), "state": state, "index": int(index), "count": int(count)}
        values.update(extra or {})
        self._write(TOPIC_POSE, stamp_ns, ros2_cdr.diagnostic_status(
            0 if state == "recording" else 1, TOPIC_POSE, state, sensor_id,
            [(str(k), _to_text(v)) for k, v in values.items()]))

    def add_metadata(self, name: str, metadata: dict[str, Any]) -> None:
        """An MCAP metadata record (values that are not strings are stored as JSON)."""
        self._writer.add_metadata(name, {str(k): _to_text(v) for k, v in metadata.items()})

    def flush(self) -> None:
        """End the chunk in progress now (e.g. at the end of a pose) so it survives a crash.

        Raises :class:`RecordingLostError` if the path no longer names the file written (:meth:`check_path`);
        an ``OSError`` of the write itself (e.g. ``ENOSPC``) propagates."""
        if not self._closed:
            self._writer.flush()
            self.check_path()

    def check_path(self) -> None:
        """Raise :class:`RecordingLostError` unless ``path`` still names the file being written (same device
        and inode as the open file): a deleted file or output directory is otherwise noticed only when the
        run is over, since writes into an unlinked file succeed."""
        try:
            st = os.stat(self.path)
        except OSError as exc:
            raise RecordingLostError(errno.ENOENT, f"{self.path} no longer exists ({exc.strerror}): deleted while "
                                     "recording, the data written goes to an unlinked file", str(self.path)) from None
        if (st.st_dev, st.st_ino) != self._sink.identity:
            raise RecordingLostError(errno.ENOENT, f"{self.path} was replaced by another file while recording: the "
                                     "data written goes to the unlinked original", str(self.path))

    def close(self) -> None:
        """Finish the file (summary, index, footer) and close it. Idempotent. Raises
        :class:`RecordingLostError` (after closing) if the path no longer names the file written."""
        if self._closed:
            return
        try:
            self._writer.finish()
            self._sink.sync()
        finally:
            self._sink.close()
            self._closed = True
        self.check_path()

    def abandon(self) -> None:
        """Close the file as it is, without summary or footer (after a failed write: the file then reads up to
        its last complete chunk, as after a crash). Idempotent; never raises."""
        if self._closed:
            return
        self._closed = True
        try:
            self._sink.close()
        except OSError:
            pass

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _to_text(value: Any) -> str:
    if isinstance(value, str):
        return value
    return json.dumps(value, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))


# ---------------------------------------------------------------------------- reader
@dataclass
class SkippedRange:
    """A damaged stretch of an MCAP file that was passed over: a chunk whose CRC or decompression failed,
    or bytes whose record framing was lost until the next intact chunk."""

    offset: int  # byte offset of the damaged record in the file
    end_offset: int  # where reading resumed
    reason: str
    start_ns: int | None = None  # log-time range of the chunk's messages (from its header), if known
    end_ns: int | None = None
    messages: dict[str, int] | None = None  # per topic, from the chunk's message index records; None = unknown
    by_channel: dict[int, int] = field(default_factory=dict)  # the index counts per channel id, while reading

    def resolve(self, topics: dict[int, str]) -> None:
        """Name the channels of the index counts (channels may be defined after the damaged chunk was met)."""
        if self.by_channel:
            self.messages = {}
            for cid, n in self.by_channel.items():
                name = topics.get(cid, f"channel {cid}")
                self.messages[name] = self.messages.get(name, 0) + n

    def describe(self) -> str:
        if self.offset < 0:
            return self.reason
        what = (f"{sum(self.messages.values())} messages ("
                + ", ".join(f"{t} {n}" for t, n in sorted(self.messages.items())) + ")") if self.messages else \
            "an unknown number of messages"
        span = f", log time {self.start_ns * 1e-9:.3f}..{self.end_ns * 1e-9:.3f} s" \
            if self.start_ns is not None and self.end_ns is not None else ""
        return f"bytes {self.offset}..{self.end_offset}: {what}{span} ({self.reason})"

    def as_dict(self) -> dict[str, Any]:
        return {"offset": self.offset, "end_offset": self.end_offset, "reason": self.reason,
                "start_ns": self.start_ns, "end_ns": self.end_ns, "messages": self.messages}


@dataclass
class FileReadReport:
    """What :func:`read_recording` got out of one file."""

    path: str
    messages: int = 0
    messages_per_topic: dict[str, int] = field(default_factory=dict)
    complete: bool = False  # the footer was reached
    stopped_at: str = ""  # why reading stopped early (truncation, corruption)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    skipped: list[SkippedRange] = field(default_factory=list)  # damaged chunks passed over
    channel_topics: dict[int, str] = field(default_factory=dict)  # channel id -> topic, as read
    channel_types: dict[str, str] = field(default_factory=dict)  # topic -> type, as read
    raw_topic: str = TOPIC_RAW  # full name of the raw topic read (for messages)
    notes: list[str] = field(default_factory=list)  # one line each: what was read differently from the file's word

    def note(self, line: str) -> None:
        """Add a warning line once (a pass over a bag meets the same topic in every file)."""
        if line not in self.notes:
            self.notes.append(line)

    def finish(self) -> None:
        """Resolve the skipped chunks' per-channel counts to topics (call when reading ended)."""
        for r in self.skipped:
            r.resolve(self.channel_topics)

    def summary(self) -> str:
        self.finish()
        state = "complete" if self.complete else f"TRUNCATED ({self.stopped_at}); recovered up to the last complete chunk"
        text = f"{self.path}: {self.messages} messages, {state}"
        if self.skipped:
            text += f"; {len(self.skipped)} damaged stretch(es) SKIPPED: " + "; ".join(r.describe() for r in self.skipped)
        return text

    def as_dict(self) -> dict[str, Any]:
        """The form kept in ``Recording.metadata["read_report"]``."""
        self.finish()
        return {"messages": self.messages, "complete": self.complete, "stopped_at": self.stopped_at,
                "per_topic": dict(self.messages_per_topic), "skipped": [r.as_dict() for r in self.skipped],
                "raw_topic": self.raw_topic, "notes": list(self.notes)}

    def no_raw_error(self, where: str | Path, selection: TopicSelection) -> McapRecordingError:
        """The error of a recording without readable raw messages, listing the topics found with types."""
        return McapRecordingError(f"{where}: no readable {TOPIC_RAW} messages (expected topic "
                                  f"{selection.expected_raw()} of type {TYPE_RAW}); topics found: "
                                  f"{_topic_list(self.channel_types)} ({self.summary()})")


def read_warnings(path: str | Path, report: dict[str, Any], pose_events: list[tuple[int, int, str]] | None = None
                  ) -> list[str]:
    """Lines for stderr about a recording that was not read whole (``report`` = ``FileReadReport.as_dict()``):
    truncation, and every skipped damaged stretch with the poses whose recording it overlapped. Lines that
    mean data of the fit are missing start with ``WARNING:``; then the reader's notes (a sibling topic of another
    type ignored, stamps going backwards, a bag file metadata.yaml does not list), ``warning:`` each."""
    out = []
    if report and not report.get("complete", True):
        out.append(f"warning: {path} is truncated ({report.get('stopped_at')}); recovered {report.get('messages')} "
                   "messages up to the last complete chunk")
    for r in report.get("skipped", []) if report else []:
        rng = SkippedRange(**{k: v for k, v in r.items() if k != "by_channel"})
        lost = ""
        if pose_events and rng.start_ns is not None and rng.end_ns is not None:
            hit = sorted({pid for t, pid, _ in pose_events if rng.start_ns <= t <= rng.end_ns and pid >= 0})
            lost = f"; poses with events in that time: {hit}" if hit else ""
        raw_topic = report.get("raw_topic", TOPIC_RAW)
        raw = (rng.messages or {}).get(raw_topic)
        n_raw = f"{raw} {raw_topic} samples" if raw is not None else f"an unknown number of {TOPIC_RAW} samples"
        out.append(f"WARNING: {path}: damaged data skipped, {n_raw} lost: {rng.describe()}{lost}; the fit uses the "
                   "rest of the file (check that every pose and temperature level it needs is still there)")
    out.extend(f"warning: {line}" for line in (report or {}).get("notes", []))
    return out


_RECORD_HEAD = struct.Struct("<BQ")
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")  # message start/end time, uncompressed size, uncompressed CRC
_SKIPPED = {Opcode.MESSAGE_INDEX, Opcode.CHUNK_INDEX, Opcode.ATTACHMENT, Opcode.ATTACHMENT_INDEX, Opcode.STATISTICS,
            Opcode.METADATA_INDEX, Opcode.SUMMARY_OFFSET, Opcode.DATA_END, Opcode.HEADER}
_PARSED = {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.METADATA: Metadata}


class _TruncatedError(McapRecordingError):
    """The file ends inside a record."""


def _read_exact(fh: Any, n: int) -> bytes:
    data = fh.read(n)
    if len(data) != n:
        raise _TruncatedError(f"file ends {n - len(data)} bytes inside a record")
    return data


_OPCODES = frozenset(int(o) for o in Opcode)
_RESYNC_WINDOW = 64 << 20  # bytes searched for the next intact chunk after the framing is lost


def _file_records(fh: Any, report: FileReadReport, seen: dict[bytes, str] | None = None, where: str | Path = ""):
    """``(opcode, payload)`` of each top-level record of an MCAP file (``fh`` just past its magic) up to its
    footer, the index and summary records passed over; for a chunk the payload is its decompressed,
    CRC-checked records. The one path of the reader (:class:`McapSampleStream`) through a file.

    Damage is survived where the data allow it, and noted in ``report.skipped``:

    * a chunk whose CRC or decompression fails is skipped; the message index records that follow it
      give the number of messages lost per topic, its header their log-time range;
    * a record whose framing is impossible (unknown opcode, or a length past the end of a file that
      still ends in the MCAP magic, i.e. is not truncated) starts a search for the next chunk that
      decompresses with a valid CRC; reading resumes there.

    A chunk record equal byte for byte to one met before (``seen``: digest -> where, shared by the files of a
    recording) is read once: one note counts the copies.

    Raises ``_TruncatedError`` when the file ends inside a record or without a footer (the caller keeps
    what was read), ``McapRecordingError`` when no intact chunk follows a framing error.
    """
    seen = {} if seen is None else seen
    copies: list[tuple[int, str]] = []  # (offset, where the original is) of the copies in this file
    try:
        yield from _file_records_walk(fh, report, seen, copies, str(where or report.path))
    finally:
        if copies:
            report.note(f"{where or report.path}: {len(copies)} chunk{'s' if len(copies) > 1 else ''} (the first at byte "
                        f"{copies[0][0]}) {'are exact copies' if len(copies) > 1 else 'is an exact copy'} of chunks "
                        f"read before (the first: {copies[0][1]}), each read once; a copy tool or a writer that "
                        "repeated a block, not a second measurement")


def _file_records_walk(fh: Any, report: FileReadReport, seen: dict[bytes, str], copies: list[tuple[int, str]],
                       where: str):
    """:func:`_file_records` without the note of the copies."""
    pos = fh.tell()
    file_size = fh.seek(0, io.SEEK_END)
    fh.seek(max(0, file_size - len(MCAP_MAGIC)))
    ends_with_magic = file_size >= 2 * len(MCAP_MAGIC) and fh.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    fh.seek(pos)
    last_skip: SkippedRange | None = None
    while True:
        start = fh.tell()
        head = fh.read(9)
        if not head:
            raise _TruncatedError("file ends without a footer")
        if len(head) < 9:
            raise _TruncatedError("file ends inside a record header")
        opcode, length = _RECORD_HEAD.unpack(head)
        if opcode not in _OPCODES or start + 9 + length > file_size:
            if opcode in _OPCODES and not ends_with_magic:
                raise _TruncatedError("file ends inside a record")
            resume = _resync(fh, start + 1, file_size)
            if resume is None:
                raise McapRecordingError(f"record framing lost at byte {start} (opcode {opcode}, length {length}) "
                                         "and no intact chunk follows")
            report.skipped.append(SkippedRange(start, resume, f"record framing lost at byte {start}"))
            last_skip = None
            fh.seek(resume)
            continue
        if opcode == Opcode.FOOTER:
            return
        if opcode == Opcode.MESSAGE_INDEX and last_skip is not None:  # the lost chunk's index: count its messages
            body = _read_exact(fh, length)
            if len(body) >= 6:
                channel_id, nbytes = struct.unpack_from("<HI", body, 0)  # the index's records: 16 bytes a message
                last_skip.by_channel[channel_id] = last_skip.by_channel.get(channel_id, 0) + nbytes // 16
            continue
        last_skip = None
        if opcode in _SKIPPED:
            fh.seek(length, io.SEEK_CUR)
            continue
        body = _read_exact(fh, length)
        if opcode == Opcode.CHUNK:
            digest = hashlib.blake2b(body, digest_size=16).digest()
            if digest in seen:
                copies.append((start, seen[digest]))
                continue
            seen[digest] = f"byte {start} of {where}"
            try:
                data = _chunk_bytes(body)
            except Exception as exc:  # CRC mismatch, zstd error, bad header: skip this chunk only
                start_ns = end_ns = None
                if len(body) >= _CHUNK_HEAD.size:
                    start_ns, end_ns = (int(v) for v in _CHUNK_HEAD.unpack_from(body, 0)[:2])
                last_skip = SkippedRange(start, start + 9 + length, f"chunk unreadable: {type(exc).__name__} {exc}".strip(),
                                         start_ns, end_ns)
                report.skipped.append(last_skip)
                continue
            yield opcode, data
            continue
        yield opcode, body


def _resync(fh: Any, start: int, file_size: int) -> int | None:
    """Offset of the first chunk record at or after ``start`` whose body decompresses with a valid CRC
    (searched over at most :data:`_RESYNC_WINDOW` bytes), or None."""
    fh.seek(start)
    window = fh.read(min(_RESYNC_WINDOW, file_size - start))
    at = window.find(bytes([Opcode.CHUNK]))
    while at >= 0:
        if at + 9 <= len(window):
            (length,) = struct.unpack_from("<Q", window, at + 1)
            end = at + 9 + length
            if _CHUNK_HEAD.size + 12 <= length and end <= len(window):
                try:
                    _chunk_bytes(window[at + 9:end])
                    return start + at
                except Exception:
                    pass
        at = window.find(bytes([Opcode.CHUNK]), at + 1)
    return None


class _PartialRecordError(McapRecordingError):
    """A record inside a chunk is cut short: an interrupted writer still wrote (and checksummed) its last
    chunk. The records before it are good; the split yields :data:`PARTIAL_RECORD` and goes on at the next chunk."""


class _ForeignRecordError(McapRecordingError):
    """A record a chunk cannot hold (opcode 0 of a chunk of zeros, a footer...): the chunk's data are not records, the
    split yields a :class:`SkippedRange` with the reason and goes on at the next chunk (one check per record, so a
    chunk of 9-byte records of nothing costs no loop over them)."""


PARTIAL_RECORD = SkippedRange(-1, -1, "a record cut short at the end of a chunk (interrupted writer); "
                                      "the records after it in that chunk are lost")


def _record_at(data: bytes, pos: int, size: int) -> tuple[Any, int]:
    """The record at ``pos`` of decompressed chunk data (:func:`_parse_record`) and the next position."""
    if pos + 9 > size:
        raise _PartialRecordError("record header overruns its chunk")
    opcode, length = _RECORD_HEAD.unpack_from(data, pos)
    if opcode not in _CHUNK_OPCODES:
        raise _ForeignRecordError(f"a record of opcode {opcode} inside a chunk, which holds schema, channel and message "
                                  "records only: the rest of that chunk is skipped")
    end = pos + 9 + length
    if end > size:
        raise _PartialRecordError("record overruns its chunk")
    return _parse_record(opcode, data[pos + 9:end]), end


def _parse_record(opcode: int, body: bytes) -> Any:
    """A record, in a chunk or not: a message ``(channel_id, log_time, data)``, a parsed Schema/Channel/Metadata,
    or None for other opcodes."""
    if opcode == Opcode.MESSAGE:
        if len(body) < _MESSAGE_HEAD.size:
            raise _PartialRecordError("message record shorter than its header")
        channel_id, _seq, log_time, _pub = _MESSAGE_HEAD.unpack_from(body, 0)
        return channel_id, log_time, body[_MESSAGE_HEAD.size:]
    if opcode in _PARSED:
        return _PARSED[opcode].read(ReadDataStream(io.BytesIO(body)))
    return None


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _role_of(path: str | Path, selection: TopicSelection, channel: Channel, schemas: dict[int, Schema],
             report: FileReadReport) -> str | None:
    """Role (relative topic name) of a channel under ``selection``; notes the raw topic's full name."""
    schema = schemas.get(channel.schema_id)
    type_name = schema.name if schema is not None else None
    role = selection.role(channel.topic, type_name, path)
    if role == TOPIC_RAW:
        report.raw_topic = channel.topic
    elif role is None and channel.topic in selection.mismatched:
        named = next(r for r in ROLES if _absolute(channel.topic).endswith("/" + r))
        report.note(f"{path}: topic {channel.topic} has type {type_name or 'no schema'}, not {ROLE_TYPES[named]}; "
                    "ignored (never decoded), as the other topics")
    return role


def read_file(path: str | Path, namespace: str | None = None, topic: str | None = None
              ) -> tuple[Recording, FileReadReport]:
    """One recording -- an MCAP file or a rosbag2 bag directory (its files in order) -- to a
    :class:`Recording` (run_id 0) and the report of what was read. ``namespace``/``topic`` choose the
    raw topic and its siblings (:class:`TopicSelection`; default: the single ``.../imu/raw``).

    The same reader as the streaming fit (:class:`McapSampleStream`), in one pass holding every sample;
    samples are put in stamp order, so a file whose stamps go backwards is read too (a note in the report when
    they go back by more than :data:`BACKWARDS_TOLERANCE_NS`, naming the first sample where they do)."""
    stream = McapSampleStream(path, namespace, topic)
    stamps, rows = stream.all_rows()
    if np.any(stamps[1:] < stamps[:-1]):  # only then reorder (a stable sort of sorted stamps changes nothing)
        step = np.diff(stamps)
        back = np.flatnonzero(step < -BACKWARDS_TOLERANCE_NS)
        if len(back):  # more than jitter: a driver restart or a clock step, whose stretches the sort interleaves
            i = int(back[0])
            stream.report.note(f"{path}: {stream.report.raw_topic} stamps go back {-step[i] * 1e-9:.3f} s at sample "
                               f"{i + 1} (in file order; {len(back)} such place(s)); the samples are read in stamp "
                               "order, so the stretches before and after are interleaved (a driver restart or a "
                               "clock step?)")
        order = np.argsort(stamps, kind="stable")
        stamps, rows = stamps[order], rows[order]
    rec = stream.block(stamps, rows, with_poses=True)
    rec.metadata = stream.metadata()
    return rec, stream.report


def assign_poses(stamps_ns: np.ndarray, pose_events: list[tuple[int, int, str]],
                 gref_events: list[tuple[int, tuple[float, float, float]]]) -> tuple[np.ndarray, np.ndarray]:
    """Pose id (N,) and reference gravity (N, 3) for samples at ``stamps_ns``.

    A sample belongs to the latest pose event at or before its stamp if that event's state is
    ``recording``; its reference is the latest reference-gravity message at or before its stamp.
    Other samples get pose id -1 and a NaN reference.
    """
    n = len(stamps_ns)
    pose_id = np.full(n, -1, dtype=int)
    gref = np.full((n, 3), np.nan)
    if not pose_events:
        return pose_id, gref
    pe = sorted(pose_events, key=lambda e: e[0])
    pt = np.asarray([e[0] for e in pe], dtype=np.int64)
    pid = np.asarray([e[1] if e[2] == "recording" else -1 for e in pe], dtype=int)
    k = np.searchsorted(pt, stamps_ns, side="right") - 1
    has = k >= 0
    pose_id[has] = pid[k[has]]
    if gref_events:
        ge = sorted(gref_events, key=lambda e: e[0])
        gt = np.asarray([e[0] for e in ge], dtype=np.int64)
        gv = np.asarray([e[1] for e in ge], dtype=float)
        j = np.searchsorted(gt, stamps_ns, side="right") - 1
        ok = (j >= 0) & (pose_id >= 0)
        gref[ok] = gv[j[ok]]
    return pose_id, gref


def read_recording(paths: str | Path | list[str | Path], namespace: str | None = None,
                   topic: str | None = None) -> Recording:
    """Read one or more calibration MCAPs or rosbag2 bag directories (e.g. one per chamber temperature)
    into one Recording; ``namespace``/``topic`` as :func:`read_file`.

    Each file (or bag) becomes its own ``run_id``. A truncated file (writer killed) is read up to its last
    complete chunk; ``metadata['parts'][i]['read_report']`` says how many messages were recovered and
    why reading stopped, and a warning is logged.
    """
    if isinstance(paths, str | Path):
        paths = [paths]
    if not paths:
        raise McapRecordingError("no MCAP files given")
    parts = [read_file(p, namespace, topic)[0] for p in paths]
    if len(parts) == 1:
        parts[0].metadata = {"parts": [parts[0].metadata], **parts[0].metadata}
        return parts[0]
    return Recording.concatenate(parts)


def pose_events(pose_id: np.ndarray, gref_mps2: np.ndarray,
                before: tuple[int, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(pose (n,): the pose id, -1 where moving or the reference (n, 3) m/s^2 is unknown; the samples (n,) at
    which a writer puts a pose event): where the pose changes, or the reference of a recorded pose does. A
    moving sample's reference is not written, so its changes are no event (a table that reports its angles
    while it moves would otherwise give an event per sample). ``before``: (pose, reference) of the sample
    before these (a writer that goes block by block); None: the first sample is an event."""
    known = np.all(np.isfinite(gref_mps2), axis=1)
    pose = np.where((pose_id >= 0) & known, pose_id, -1)
    prev_pose = np.empty_like(pose)
    prev_g = np.empty_like(gref_mps2, dtype=float)
    prev_pose[:1], prev_g[:1] = (before[0], before[1]) if before is not None else (-2, np.nan)
    prev_pose[1:], prev_g[1:] = pose[:-1], gref_mps2[:-1]
    return pose, (pose != prev_pose) | ((pose >= 0) & np.any(gref_mps2 != prev_g, axis=1))


def write_recording(path: str | Path, rec: Recording, metadata: dict[str, Any] | None = None,
                    t0_ns: int = 0, sensor_id: str = "") -> int:
    """Write a :class:`Recording` (e.g. from the CSV importer) as a calibration MCAP (:func:`write_samples`, stamps
    ``t0_ns + t_s * 1e9``); returns messages written. Times that do not increase are refused before anything is
    written."""
    stamps = t0_ns + np.round(rec.t_s * 1e9).astype(np.int64)
    if len(stamps) > 1 and np.any(np.diff(stamps) <= 0):
        raise McapRecordingError("sample times must be strictly increasing")
    with RecordingWriter(path, metadata) as w:
        write_samples(w, [rec], int(rec.pose_id.max()) + 1 if len(rec) else 0, sensor_id, t0_ns)
        return w.message_count


def write_samples(w: RecordingWriter, blocks: Iterable[Recording], n_poses: int, sensor_id: str = "", t0_ns: int = 0,
                  start_ns: int | None = None, where: str = "") -> tuple[int, float | None]:
    """Write the samples of one run, served in ``blocks``, as ``imu/raw`` messages with their pose events: a pose
    event (``recording`` with its reference gravity, or ``moving`` for pose id -1 or an unknown reference)
    wherever the pose id or the reference of a recorded pose changes (``pose_events``), so a sample with a pose id
    but no reference reads back as pose -1. Stamps are ``t0_ns + t_s * 1e9`` ns, or with ``start_ns``
    ``start_ns`` plus the time since the first sample; ``board_time_s`` keeps ``t_s`` either way; ``seq`` counts
    the samples. Stamps that do not increase raise :class:`McapRecordingError` (``where``: what to name).
    Returns (the stamps' offset from ``t_s * 1e9`` in ns, the first sample's ``t_s`` or None if there is none)."""
    before: tuple[int, np.ndarray] | None = None  # the last sample's pose and reference
    prev_stamp, seq = -1, 0
    shift: int | None = None if start_ns is not None else t0_ns
    first_t_s: float | None = None
    for blk in blocks:
        stamps = np.round(blk.t_s * 1e9).astype(np.int64)
        if not len(stamps):
            continue
        if shift is None:
            shift = int(start_ns) - int(stamps[0])
        first_t_s = float(blk.t_s[0]) if first_t_s is None else first_t_s
        stamps += shift
        step = np.diff(np.r_[prev_stamp, stamps])
        if np.any(step <= 0):
            i = int(np.argmax(step <= 0))
            raise McapRecordingError(f"{where}times {int(stamps[i] - step[i])} ns and {int(stamps[i])} ns are not "
                                     "strictly increasing at nanosecond resolution")
        pose, change = pose_events(blk.pose_id, blk.gref_mps2, before)
        before = int(pose[-1]), blk.gref_mps2[-1].copy()
        rows = zip(stamps.tolist(), pose.tolist(), change.tolist(), blk.ref.tolist(), blk.xyz.tolist(),
                   blk.temp_c.tolist(), blk.t_s.tolist(), strict=True)
        for i, (stamp, p, event, ref, xyz, temp, t) in enumerate(rows):
            if event:
                if p >= 0:
                    w.write_reference_gravity(stamp, blk.gref_mps2[i])
                    w.write_pose(stamp, p, "recording", index=p, count=n_poses, sensor_id=sensor_id)
                else:
                    w.write_pose(stamp, -1, "moving", sensor_id=sensor_id)
            w.write_raw(stamp, ref, xyz, temperature_c=temp, temperature_valid=math.isfinite(temp), seq=seq,
                        board_time_s=t)
            seq += 1
        prev_stamp = int(stamps[-1])
    return shift or 0, first_t_s


# ---------------------------------------------------------------------------- streaming reader
class StreamOrderError(McapRecordingError):
    """The ``imu/raw`` stamps of a file go backwards: it cannot be streamed in file order
    (:func:`read_file` sorts such a file in memory)."""


class McapSampleStream:
    """The reader of a calibration MCAP (or rosbag2 bag): block by block for the streaming fit, or every
    sample at once (:meth:`all_rows`, behind :func:`read_file`).

    :meth:`blocks` yields :class:`Recording` blocks of exactly ``block_rows`` samples (the last one
    shorter) in file order: temperature from the ``imu/raw`` field (or the latest ``imu/temperature``
    message at or before the stamp), pose id and reference from :func:`assign_poses`. Pose and reference events are
    collected during the first complete pass (``with_poses=False``); later passes
    (``with_poses=True``) assign them per block. State between passes: the pose, reference and
    (only for raw messages without a temperature field) temperature events, O(poses) values.

    ``imu/raw`` messages in the fixed layout of :class:`ros2_cdr.FixedJointStateCodec` are split out of each
    decompressed chunk with one numpy view per run of equal records (no Python object per message);
    other messages go through the ``mcap_ros2`` decoder. A truncated file is read up to its last
    complete chunk; ``report`` tells what the last pass that read to its end read.
    """

    def __init__(self, path: str | Path, namespace: str | None = None, topic: str | None = None) -> None:
        self.path = Path(path)
        self.files, self.selection, self._notes = recording_files(self.path, namespace, topic)
        self.report = FileReadReport(str(self.path))
        self.names: tuple[str, ...] | None = None
        self.samples: int | None = None  # raw samples of the file, known after the first pass
        self._events_complete = False
        self._pose_events: list[tuple[int, int, str]] = []
        self._gref_events: list[tuple[int, tuple[float, float, float]]] = []
        self._temp_t: list[int] = []
        self._temp_v: list[float] = []
        self._pose_log: list[tuple[int, int, str]] = []  # the pose events at their log time (read_warnings)
        self._log_offset: int | None = None  # log time - stamp of the last raw message read (first pass)
        self._spill: PassSpill | None = None  # the samples of the first pass that read the files to their end
        self._spill_report = self.report

    def _raw_clock(self, log_time: int, stamp: int) -> None:
        """Note the raw messages' log-time-minus-stamp offset (the recorder's clock against the driver's): a
        pose event, which has no header stamp, is put on the samples' clock with the offset of the raw message
        before it in the file (events before the first sample: the first sample's offset)."""
        offset = int(log_time) - int(stamp)
        if self._log_offset is None and offset:
            self._pose_events = [(t - offset, p, st) for t, p, st in self._pose_events]
        self._log_offset = offset

    # -- record level
    def _batches(self, collect_events: bool, keep: bool = True):
        """Yield ``(stamps (k,) int64 ns, values (k, n))`` batches of ``imu/raw`` in file order, the files of
        a bag one after the other (``report.complete`` only when every file was read to its footer). The pass's
        report becomes ``self.report`` when the pass ends: a pass its consumer closes early (the fit's second look at
        a run's first samples) read only part of the file and must not stand for it.

        The files are read once: the first pass that reaches the end keeps its samples (``pass_spill.PassSpill``), and
        every later pass gives them back from there, the same values in the same order (in batches of
        :data:`REPLAY_ROWS`), with that pass's report. ``keep`` False: a single pass (:meth:`all_rows`), nothing kept."""
        if self._spill is not None:
            yield from self._spill.pieces(REPLAY_ROWS)
            self.report = self._spill_report
            return
        report = FileReadReport(str(self.path), notes=list(self._notes))
        complete = True
        seen: dict[bytes, str] = {}  # chunk digests of the pass: a chunk repeated in a file or across files is read once
        spill = PassSpill((np.int64, float)) if keep else None
        try:
            for path in self.files:
                report.complete = False
                for stamps, values in self._file_batches(path, report, collect_events, seen):
                    if spill is not None:
                        spill.add(stamps, values)
                    yield stamps, values
                complete &= report.complete
        except BaseException:  # an error, or a pass closed early: what was kept is not the whole file
            if spill is not None:
                spill.close()
            raise
        report.complete = complete
        self.report = self._spill_report = report
        self._spill = spill

    def _file_batches(self, path: Path, report: FileReadReport, collect_events: bool, seen: dict[bytes, str]):
        """:meth:`_batches` of one MCAP file (channel and schema ids are per file)."""
        sel = self.selection
        factory = DecoderFactory()
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        decoders: dict[int, Any] = {}
        fast: dict[str, Any] = {}

        def count(topic: str, n: int) -> None:
            report.messages += n
            report.messages_per_topic[topic] = report.messages_per_topic.get(topic, 0) + n

        def decoder_of(channel: Channel, role: str) -> Any:
            dec = decoders.get(channel.id)
            if dec is None:
                dec = _decoder_for(path, factory, channel, schemas, role == TOPIC_RAW)
                _check_fields(path, channel, schemas.get(channel.schema_id), role)
                decoders[channel.id] = dec
            return dec

        def message(channel_id: int, log_time: int, data: bytes):
            channel = channels.get(channel_id)
            if channel is None:
                raise McapRecordingError(f"{path}: message on unknown channel {channel_id}")
            count(channel.topic, 1)
            role = _role_of(path, sel, channel, schemas, report)
            if role == TOPIC_RAW:
                msg = _decode(path, decoder_of(channel, role), channel, data)
                names = tuple(msg.name)
                if self.names is None:
                    missing = [n for n in RAW_NAMES[:4] if n not in names]
                    if missing:
                        raise McapRecordingError(f"{path}: {channel.topic} lacks joint names {missing}")
                    self.names = names
                elif names != self.names:
                    raise McapRecordingError(f"{path}: {channel.topic} changes its name list")
                if len(msg.position) != len(names):
                    raise McapRecordingError(f"{path}: {channel.topic} message has {len(msg.position)} values "
                                             f"for {len(names)} names")
                if "codec" not in fast:
                    _set_fast(fast, channel_id, ros2_cdr.FixedJointStateCodec(msg.header.frame_id, names))
                stamp = _stamp_ns(msg.header)
                if collect_events:
                    self._raw_clock(log_time, stamp)
                return np.asarray([stamp], dtype=np.int64), np.asarray(msg.position, dtype=float).reshape(1, -1)
            if collect_events and role is not None:
                msg = _decode(path, decoder_of(channel, role), channel, data)
                try:
                    if role == TOPIC_TEMPERATURE:
                        self._temp_t.append(_stamp_ns(msg.header))
                        self._temp_v.append(float(msg.temperature))
                    elif role == TOPIC_REFERENCE_GRAVITY:
                        self._gref_events.append((_stamp_ns(msg.header), (msg.vector.x, msg.vector.y, msg.vector.z)))
                    elif role == TOPIC_POSE:
                        values = {kv.key: kv.value for kv in msg.values}
                        event = (int(values.get("pose_id", "-1")), values.get("state", msg.message))
                        self._pose_events.append((log_time - (self._log_offset or 0), *event))
                        self._pose_log.append((log_time, *event))
                except (AttributeError, TypeError, ValueError) as exc:  # e.g. a pose_id that is not a number
                    raise McapRecordingError(f"{path}: a '{channel.topic}' message cannot be read as "
                                             f"{ROLE_TYPES[role]} ({type(exc).__name__}: {first_line(exc)[:200]})"
                                             ) from None
            return None

        def emit(items: Iterable[Any]):
            for item in items:
                if isinstance(item, tuple) and len(item) == 2:  # a run of fixed-layout raw records
                    count(report.raw_topic, len(item[0]))
                    if collect_events:
                        self._raw_clock(fast["last_log"], item[0][-1])
                    yield item
                elif isinstance(item, tuple):
                    out = message(*item)
                    if out is not None:
                        yield out
                elif isinstance(item, SkippedRange):  # PARTIAL_RECORD, or a chunk of records it cannot hold
                    report.skipped.append(SkippedRange(item.offset, item.end_offset, item.reason))
                else:
                    _note_record(item, schemas, channels, report)

        joined: list[bytes] = []
        joined_bytes = 0
        with open(path, "rb", buffering=1 << 20) as fh:
            if fh.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise McapRecordingError(f"{path}: not an MCAP file (bad magic)")
            records = _file_records(fh, report, seen, path)
            while True:
                try:
                    opcode, body = next(records)
                except StopIteration:  # the footer
                    report.complete = True
                    break
                except Exception as exc:  # truncated or corrupt tail: keep what was read
                    report.stopped_at = f"{type(exc).__name__} {exc}".strip()
                    break
                if opcode == Opcode.CHUNK:  # records never span chunks: split several chunks at once
                    joined.append(body)
                    joined_bytes += len(body)
                    if joined_bytes < _JOIN_BYTES:
                        continue
                if joined:
                    yield from emit(_split_chunks(joined, fast))
                    joined, joined_bytes = [], 0
                if opcode != Opcode.CHUNK:
                    try:
                        item = _parse_record(opcode, body)
                    except _PartialRecordError as exc:
                        report.stopped_at = str(exc)
                        break
                    yield from emit([item])
        if joined:
            yield from emit(_split_chunks(joined, fast))

    def blocks(self, block_rows: int, with_poses: bool) -> Any:
        """Yield :class:`Recording` blocks of ``block_rows`` samples (run_id 0) in file order.

        ``with_poses=False`` (the first pass) leaves pose id -1 and NaN reference and collects the
        events; ``with_poses=True`` needs a complete earlier pass. Raises :class:`StreamOrderError`
        when the stamps go backwards.
        """
        if with_poses and not self._events_complete:
            raise McapRecordingError(f"{self.path}: pose events are known only after a first pass")
        collect = self._start_pass()
        buf_s: np.ndarray | None = None  # one block of stamps and values, filled batch by batch
        buf_v: np.ndarray | None = None
        fill = 0
        last_stamp = np.iinfo(np.int64).min
        total = 0
        for stamps, values in self._batches(collect):
            if len(stamps) == 0:
                continue
            if stamps[0] < last_stamp or np.any(np.diff(stamps) < 0):
                raise StreamOrderError(f"{self.path}: {TOPIC_RAW} stamps go backwards; the file cannot be streamed "
                                       "in file order")
            last_stamp = int(stamps[-1])
            if buf_v is None or buf_v.shape[1] != values.shape[1]:
                buf_s, buf_v = np.empty(block_rows, np.int64), np.empty((block_rows, values.shape[1]))
            start = 0
            while start < len(stamps):
                take = min(block_rows - fill, len(stamps) - start)
                buf_s[fill:fill + take] = stamps[start:start + take]
                buf_v[fill:fill + take] = values[start:start + take]
                fill += take
                start += take
                if fill == block_rows:
                    yield self.block(buf_s, buf_v, with_poses)
                    total += fill
                    fill = 0
        if fill:
            yield self.block(buf_s[:fill], buf_v[:fill], with_poses)
            total += fill
        self._end_pass(collect, total)

    def all_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """Every ``imu/raw`` sample in file order, ``(stamps (N,) int64 ns, values (N, k))``, in one pass that
        also collects the events (for a reader that holds the whole recording; stamps may go backwards)."""
        collect = self._start_pass()
        batches = [(s, v) for s, v in self._batches(collect, keep=False) if len(s)]
        self._end_pass(collect, sum(len(s) for s, _ in batches))  # no samples: raises
        # one width: a message whose name list differs from the first one's already raised in _file_batches
        return np.concatenate([s for s, _ in batches]), np.concatenate([v for _, v in batches])

    def _start_pass(self) -> bool:
        """Whether this pass collects the events (the first complete one); resets them if so."""
        collect = not self._events_complete
        if collect:
            self._pose_events, self._gref_events, self._temp_t, self._temp_v = [], [], [], []
            self._pose_log, self._log_offset = [], None
        return collect

    def _end_pass(self, collect: bool, total: int) -> None:
        if collect:
            self._events_complete = True
            self.samples = total
        if collect and (not self.report.complete or self.report.skipped):
            LOG.warning("%s", self.report.summary())
        if total == 0:
            raise self.report.no_raw_error(self.path, self.selection)

    def block(self, stamps: np.ndarray, rows: np.ndarray, with_poses: bool) -> Recording:
        """A Recording of copies (the caller reuses ``stamps`` and ``rows``)."""
        stamps = stamps.copy()
        col = {n: i for i, n in enumerate(self.names or ())}
        xyz = rows[:, [col["x_counts"], col["y_counts"], col["z_counts"]]]
        if "temperature_c" in col:
            temp = rows[:, col["temperature_c"]].copy()
            if "temperature_valid" in col:
                temp[rows[:, col["temperature_valid"]] < 0.5] = np.nan
        elif self._temp_t:
            ts = np.asarray(self._temp_t, dtype=np.int64)
            o = np.argsort(ts, kind="stable")
            idx = np.searchsorted(ts[o], stamps, side="right") - 1
            temp = np.where(idx >= 0, np.asarray(self._temp_v)[o][np.clip(idx, 0, None)], np.nan)
        else:
            temp = np.full(len(stamps), np.nan)
        t_s = rows[:, col["board_time_s"]].copy() if "board_time_s" in col else stamps * 1e-9
        if with_poses:
            pose_id, gref = assign_poses(stamps, self._pose_events, self._gref_events)
        else:
            pose_id, gref = np.full(len(stamps), -1, dtype=int), np.full((len(stamps), 3), np.nan)
        return Recording(t_s=t_s, ref=rows[:, col["ref_counts"]].copy(), xyz=xyz, temp_c=temp, gref_mps2=gref,
                         pose_id=pose_id, aux=rows[:, col[RAW_AUX_NAME]].copy() if RAW_AUX_NAME in col else None)

    def metadata(self) -> dict[str, Any]:
        """Run metadata and the read report, as :func:`read_file` puts them in ``Recording.metadata``."""
        md: dict[str, Any] = {name: dict(m) for name, m in self.report.metadata.items()}
        md["source"] = str(self.path)
        md["read_report"] = self.report.as_dict()
        md["pose_events"] = list(self._pose_log)  # at log time, as the chunk ranges read_warnings compares them to
        return md


def _decoder_for(path: Path | str, factory: DecoderFactory, channel: Channel, schemas: dict[int, Schema],
                 is_raw: bool) -> Any:
    """The ``mcap_ros2`` decoder of a channel, or one line saying why there is none: the raw topic of another
    type, a schema that does not parse (instead of an AttributeError or InvalidResourceName traceback)."""
    schema = schemas.get(channel.schema_id)
    if is_raw and (schema is None or schema.name != TYPE_RAW):
        found = schema.name if schema is not None else "no schema"
        raise McapRecordingError(f"{path}: topic '{channel.topic}' has type '{found}', expected '{TYPE_RAW}'")
    try:
        decoder = factory.decoder_for(channel.message_encoding, schema)
    except Exception as exc:  # the ROS 2 msg parser raises many types on a malformed definition
        name = schema.name if schema is not None else "?"
        raise McapRecordingError(f"{path}: schema '{name}' of topic '{channel.topic}' cannot be parsed "
                                 f"({type(exc).__name__}: {first_line(exc)[:200]})") from None
    if decoder is None:
        raise McapRecordingError(f"{path}: no ROS 2 decoder for topic {channel.topic} "
                                 f"(encoding '{channel.message_encoding}')")
    return decoder


_HEADER = ("std_msgs/Header", "stamp"), ("std_msgs/Header", "frame_id")
_ROLE_FIELDS = {  # (type, field) that the reader uses of each role; "" = the channel's own type
    TOPIC_RAW: (("", "header"), ("", "name"), ("", "position"), *_HEADER),
    TOPIC_TEMPERATURE: (("", "header"), ("", "temperature"), *_HEADER),
    TOPIC_REFERENCE_GRAVITY: (("", "header"), ("", "vector"), *_HEADER, *(("geometry_msgs/Vector3", c) for c in "xyz")),
    TOPIC_POSE: (("", "message"), ("", "values"), ("diagnostic_msgs/KeyValue", "key"),
                 ("diagnostic_msgs/KeyValue", "value")),
}


def _short_type(name: str) -> str:
    """``pkg/msg/Name`` -> ``pkg/Name`` (the spelling of a schema's ``MSG:`` lines)."""
    parts = name.strip().split("/")
    return f"{parts[0]}/{parts[-1]}" if len(parts) > 1 else name.strip()


def _schema_fields(name: str, text: str) -> dict[str, set[str]]:
    """Field names of each type in a ros2msg schema text (its own type under ``name``, then every ``MSG:``
    section), constants left out."""
    out: dict[str, set[str]] = {}
    current = _short_type(name)
    for section in re.split(r"^={3,}\s*$", text, flags=re.MULTILINE):
        lines = section.strip().splitlines()
        if lines and lines[0].startswith("MSG:"):
            current = _short_type(lines[0][4:])
            lines = lines[1:]
        fields = out.setdefault(current, set())
        for raw_line in lines:
            line = raw_line.split("#", 1)[0].strip()
            parts = line.split()
            if len(parts) >= 2 and not _CONSTANT.match(line):
                fields.add(parts[1])
    return out


def _check_fields(path: Path | str, channel: Channel, schema: Schema | None, role: str) -> None:
    """One line when a role's schema has the type name this reader expects but not the fields it reads (another
    definition under that name, e.g. a renamed field): the messages would decode into objects without them."""
    if schema is None:
        return
    fields = _schema_fields(schema.name, schema.data.decode("utf-8", "replace"))
    own = _short_type(schema.name)
    for type_name, name in _ROLE_FIELDS[role]:
        have = fields.get(type_name or own)
        if have is not None and name not in have:
            where = name if not type_name else f"{type_name}.{name}"
            raise McapRecordingError(f"{path}: topic {channel.topic}'s schema {schema.name} lacks field {where} "
                                     "(a different definition)")


def _decode(path: Path | str, decoder: Any, channel: Channel, data: bytes) -> Any:
    """One message decoded, or one line naming the topic when its bytes do not match its schema."""
    try:
        return decoder(data)
    except Exception as exc:
        raise McapRecordingError(f"{path}: a '{channel.topic}' message does not decode with its schema "
                                 f"({type(exc).__name__}: {first_line(exc)[:200]})") from None


def _note_record(rec: Any, schemas: dict[int, Schema], channels: dict[int, Channel], report: FileReadReport) -> None:
    if isinstance(rec, Schema):
        schemas[rec.id] = rec
    elif isinstance(rec, Channel):
        channels[rec.id] = rec
        report.channel_topics[rec.id] = rec.topic
        schema = schemas.get(rec.schema_id)
        report.channel_types[rec.topic] = schema.name if schema is not None else "no schema"
    elif isinstance(rec, Metadata):
        report.metadata[rec.name] = dict(rec.metadata)


def _set_fast(fast: dict[str, Any], channel_id: int, codec: ros2_cdr.FixedJointStateCodec) -> None:
    """Record layout of one fixed-layout raw message inside a chunk (opcode, length, message header, CDR)."""
    words = len(codec.middle) // 8  # the middle (frame_id, names) ends 8-aligned: compare it as uint64 words
    msg = np.dtype([("enc", "<u4"), ("sec", "<i4"), ("nanosec", "<u4"), ("mid", "<u8", (words,)),
                    ("values", "<f8", (codec.n_values,)), ("tail", f"V{len(codec.tail)}")])
    if len(codec.middle) % 8 or msg.itemsize != codec.size:
        return  # unexpected layout: no fast path, every message decoded one by one
    fast["codec"] = codec
    fast["channel"] = channel_id
    fast["dtype"] = np.dtype([("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"), ("log", "<u8"),
                              ("pub", "<u8"), ("msg", msg)])
    fast["size"] = 9 + 22 + codec.size
    fast["enc"] = np.frombuffer(ros2_cdr.ENCAPSULATION, dtype="<u4")[0]
    fast["mid"] = np.frombuffer(codec.middle, dtype="<u8")


def _chunk_bytes(body: bytes) -> bytes:
    """Decompressed, CRC-checked records of a chunk record body."""
    start_t, end_t, size, crc = _CHUNK_HEAD.unpack_from(body, 0)
    (clen,) = struct.unpack_from("<I", body, 28)
    compression = body[32:32 + clen].decode()
    (rlen,) = struct.unpack_from("<Q", body, 32 + clen)
    chunk = Chunk(compression=compression, data=body[40 + clen:40 + clen + rlen], message_start_time=start_t,
                  message_end_time=end_t, uncompressed_crc=crc, uncompressed_size=size)
    if compression and size > MAX_CHUNK_RATIO * max(len(chunk.data), 1):
        raise McapRecordingError(f"a chunk of {len(chunk.data)} compressed bytes claims {size}: a decompression ratio "
                                 f"above {MAX_CHUNK_RATIO} (a recording's chunks: below 20), not recorded data")
    if compression == "zstd" and size:
        declared = zstandard.frame_content_size(chunk.data) if len(chunk.data) >= 18 else -1
        if declared not in (-1, size):  # decompress() allocates what the frame declares, whatever the bound
            raise McapRecordingError(f"the chunk's zstd frame declares {declared} bytes, its header {size}")
        data = _ZSTD.decompress(chunk.data, max_output_size=size)
        if len(data) != size:
            raise McapRecordingError(f"chunk decompressed to {len(data)} bytes, expected {size}")
        if crc != 0 and zlib.crc32(data) != crc:
            raise McapRecordingError("chunk CRC mismatch")
        return data
    stream, size = get_chunk_data_stream(chunk, validate_crc=True)
    return stream.read(size) if size else b""


_ZSTD = zstandard.ZstdDecompressor()
# Largest uncompressed / compressed size of a chunk that is read: a recording's chunks compress 4-15x (our writer's
# chunks of a constant signal: 15x), 10 MB of zeros fits in 338 bytes (31000x). Above it the chunk is skipped as
# damaged, before it is decompressed: the work and memory of a file stay within 200x its size.
MAX_CHUNK_RATIO = 200
_CHUNK_OPCODES = frozenset((Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE))  # what a chunk holds (MCAP spec)
_JOIN_BYTES = 1 << 20  # decompressed chunks split together (records never span chunks)
_FAST_RUN_MIN = 64
_FAST_RUN_MAX = 16384  # records checked at once for a run of fixed-layout raw messages


def _split_chunks(bodies: list[bytes], fast: dict[str, Any]):
    """Records of decompressed chunks ``bodies``, split together: ``(stamps, values)`` for each run of consecutive
    fixed-layout raw messages (one numpy view), ``(channel_id, log_time, data)`` for other messages, and parsed
    Schema/Channel/Metadata records. No record is read across the end of its chunk (records never span chunks): a
    run goes on into the next chunk only where its chunk ends between two of its records, and a chunk that ends
    inside a record (an interrupted writer that still checksummed it) yields :data:`PARTIAL_RECORD` there and the
    split goes on at the next chunk's start."""
    data = b"".join(bodies)
    ends = np.cumsum([len(b) for b in bodies])
    size = len(data)
    pos = 0
    while pos < size:
        chunk_end = int(ends[np.searchsorted(ends, pos, side="right")])  # the end of the chunk pos is in
        rec_size = fast.get("size")
        if rec_size is not None:  # a run stops at the first chunk end that does not fall between two of its records
            limit = chunk_end
            if (chunk_end - pos) % rec_size == 0:  # its chunk ends between two records: look at the later ends
                later = ends[ends > pos]
                misaligned = np.flatnonzero((later - pos) % rec_size)
                limit = int(later[misaligned[0]]) if misaligned.size else size
        start = pos
        k = _FAST_RUN_MIN
        while rec_size is not None:  # windows growing x4 while every record matches the raw layout
            kk = min((limit - pos) // rec_size, k)
            if kk == 0:
                break
            arr = np.frombuffer(data, dtype=fast["dtype"], count=kk, offset=pos)
            ok = (arr["op"] == Opcode.MESSAGE) & (arr["len"] == rec_size - 9) & (arr["ch"] == fast["channel"])
            ok &= (arr["msg"]["enc"] == fast["enc"]) & np.all(arr["msg"]["mid"] == fast["mid"], axis=1)
            n_ok = kk if ok.all() else int(np.argmin(ok))
            if n_ok:
                msg = arr["msg"][:n_ok]
                fast["last_log"] = int(arr["log"][n_ok - 1])  # the run's last log time (the recorder's clock)
                yield msg["sec"].astype(np.int64) * 1_000_000_000 + msg["nanosec"].astype(np.int64), msg["values"].astype(float)
                pos += n_ok * rec_size
            if n_ok < kk:
                break
            k = min(4 * k, _FAST_RUN_MAX)
        if pos >= size:
            break
        if pos != start:  # a run moved it
            chunk_end = int(ends[np.searchsorted(ends, pos, side="right")])
        try:
            item, pos = _record_at(data, pos, chunk_end)
        except _PartialRecordError:
            yield PARTIAL_RECORD
            pos = chunk_end
            continue
        except _ForeignRecordError as exc:
            yield SkippedRange(-1, -1, str(exc))
            pos = chunk_end
            continue
        if item is not None:
            yield item
