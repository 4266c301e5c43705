"""Calibration recordings as MCAP files with the ROS 2 profile (ros2msg schemas, CDR messages): the format.

Pure Python + numpy + ``mcap``/``mcap_ros2`` (no rclpy): the calibration node, the CSV importer and
the tests all write through :class:`~fbg_accel_calibration.io.mcap_writer.RecordingWriter`; the fit and the
diagnosis read through :func:`~fbg_accel_calibration.io.mcap_reader.read_recording`. This module holds what both
sides share: the topics, their types, the pose states, the MCAP magic bytes, the error, and the choice of a
recording's topics (:class:`TopicSelection`). The jobs around it: ``mcap_schemas`` (the ros2msg definitions written
and the checks of those read), ``mcap_writer``, ``mcap_records`` (the file's records, read through damage) and
``mcap_reader`` (one reader, :class:`~fbg_accel_calibration.io.mcap_reader.McapSampleStream`, streamed or whole).
Files open in ``ros2 bag info``/``ros2 bag play`` (rosbag2 MCAP storage) and Foxglove because every schema is the
full concatenated ``.msg`` text of the type and its dependencies, exactly as rosbag2 writes it.

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
``mcap_reader.read_recording`` gives a sample the pose id and reference gravity of the latest pose event at
or before its stamp when that event's state is ``recording``; otherwise pose_id -1 and NaN reference. A pose
event has no header stamp: it is put on the samples' clock with the (log time - stamp) offset of the raw
message before it in the file, so a recorder whose clock is not the driver's (``ros2 bag record`` on another
machine) places it where it was published; in the files written here that offset is 0.

Run metadata (sensor id, plan, operator notes, ...) are MCAP Metadata records named ``run``
(string -> string; non-string values are stored as JSON).
"""

from __future__ import annotations

from pathlib import Path

MCAP_MAGIC = b"\x89MCAP0\r\n"  # first bytes of an MCAP file (mcap.dev specification)

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


class McapRecordingError(ValueError):
    """An MCAP file cannot be written or read as a calibration recording."""


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
