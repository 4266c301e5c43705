"""The writer of a calibration recording (``mcap_format``): :class:`RecordingWriter`, incremental and crash-safe,
and :func:`write_recording`/:func:`write_samples` for samples held or streamed (the CSV importer, the simulator, tests).

Crash safety: the file is written through an unbuffered OS file with small chunks (default 32 KiB
uncompressed); every finished chunk goes to the OS at once, so a writer killed with SIGKILL leaves
a file whose complete chunks read back (``mcap_reader.read_recording`` stops at the first incomplete
record and reports how many messages it recovered)."""

from __future__ import annotations

import errno
import io
import json
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from fbg_accel_driver.driver_core import RAW_AUX_NAME, RAW_NAMES

from . import ros2_cdr
from .atomic_output import create_exclusive
from .mcap_format import (
    POSE_STATES,
    ROLE_TYPES,
    ROLES,
    TABLE_FRAME,
    TOPIC_POSE,
    TOPIC_RAW,
    TOPIC_REFERENCE_GRAVITY,
    TOPIC_TEMPERATURE,
    TYPE_REFERENCE_GRAVITY,
    McapRecordingError,
    full_topic_name,
    normalize_namespace,
)
from .mcap_schemas import message_definition
from .recording import Recording
from .rosbag2_input import offered_qos_yaml

DEFAULT_CHUNK_BYTES = 32 * 1024


class RecordingLostError(OSError):
    """The path of a :class:`RecordingWriter` no longer names the file it writes (the file or its directory
    was deleted, or replaced, while recording): Linux keeps writing into the unlinked file, which is lost."""


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
        self._writer.start(profile="ros2", library="fbg_accel_calibration")
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
