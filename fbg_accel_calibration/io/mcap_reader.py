"""The reader of a calibration recording (``mcap_format``), an MCAP file or a rosbag2 bag directory:
:class:`McapSampleStream` block by block for the streamed fit, or whole behind :func:`read_file` and
:func:`read_recording`.

Samples get their pose id and reference from the pose events as ``mcap_format``'s docstring says (:func:`assign_poses`);
a truncated file (writer killed) is read up to its last complete chunk (``mcap_records``)."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Channel, Metadata, Schema
from mcap_ros2.decoder import DecoderFactory

from fbg_accel_driver.command_line import first_line
from fbg_accel_driver.driver_core import RAW_AUX_NAME, RAW_NAMES

from . import ros2_cdr
from .mcap_format import (
    MCAP_MAGIC,
    ROLE_TYPES,
    ROLES,
    TOPIC_POSE,
    TOPIC_RAW,
    TOPIC_REFERENCE_GRAVITY,
    TOPIC_TEMPERATURE,
    McapRecordingError,
    TopicSelection,
    _absolute,
)
from .mcap_records import (
    _CHUNK,
    FileReadReport,
    SkippedRange,
    _file_records,
    _parse_record,
    _PartialRecordError,
    _set_fast,
    _split_chunks,
    _summary_topics,
    run_rows,
)
from .mcap_schemas import _check_fields, _decode, _decoder_for, standard_event_schema
from .pass_spill import PassSpill
from .recording import Recording
from .rosbag2_input import BagInputError, bag_files

LOG = logging.getLogger(__name__)

REPLAY_ROWS = 1 << 16  # rows per batch of the samples a later pass takes from the first one (McapSampleStream)
BACKWARDS_TOLERANCE_NS = 1_000_000  # raw stamps going back less than this are jitter, read without a note
_JOIN_BYTES = 1 << 20  # decompressed chunks split together (records never span chunks)


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
    stamps, batches = stream.all_batches()
    rows: np.ndarray | list[np.ndarray] = batches  # the columns are taken from the batches (no joined copy of them)
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
        stamps, rows = stamps[order], np.concatenate(batches)[order]
    rec = stream.block(stamps, rows, with_poses=True, copy=False)
    rec.metadata = stream.metadata()
    return rec, stream.report


def _count_at_or_before(times: np.ndarray, stamps_ns: np.ndarray) -> np.ndarray:
    """For each stamp, how many of the sorted ``times`` are at or before it (``np.searchsorted(times, stamps_ns,
    side="right")``); for stamps in order, by the place of each time among the stamps (a few thousand events
    searched among a million samples, not the other way)."""
    n = len(stamps_ns)
    if n < 2 or not np.all(stamps_ns[1:] >= stamps_ns[:-1]):
        return np.searchsorted(times, stamps_ns, side="right")
    first = np.searchsorted(stamps_ns, times, side="left")  # the first sample at or after each time
    counts = np.bincount(first, minlength=n + 1)[:n]
    return np.cumsum(counts, out=counts)  # in place: no second array of a million


def assign_poses(stamps_ns: np.ndarray, pose_events: list[tuple[int, int, str]],
                 gref_events: list[tuple[int, tuple[float, float, float]]]) -> tuple[np.ndarray, np.ndarray]:
    """Pose id (N,) and reference gravity (N, 3) for samples at ``stamps_ns``.

    A sample belongs to the latest pose event at or before its stamp if that event's state is
    ``recording``; its reference is the latest reference-gravity message at or before its stamp.
    Other samples get pose id -1 and a NaN reference.
    """
    n = len(stamps_ns)
    if not pose_events:
        return np.full(n, -1, dtype=int), np.full((n, 3), np.nan)
    pe = sorted(pose_events, key=lambda e: e[0])
    pt = np.asarray([e[0] for e in pe], dtype=np.int64)
    pid = np.asarray([-1] + [e[1] if e[2] == "recording" else -1 for e in pe], dtype=int)  # [0]: before the first
    pose_id = pid[_count_at_or_before(pt, stamps_ns)]
    if not gref_events:
        return pose_id, np.full((n, 3), np.nan)
    ge = sorted(gref_events, key=lambda e: e[0])
    gt = np.asarray([e[0] for e in ge], dtype=np.int64)
    gv = np.asarray([(np.nan, np.nan, np.nan)] + [e[1] for e in ge], dtype=float)  # [0]: no reference
    j = _count_at_or_before(gt, stamps_ns)  # 1 + the latest reference at or before, 0 for none
    j[pose_id < 0] = 0
    return pose_id, gv[j]


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


class StreamOrderError(McapRecordingError):
    """The ``imu/raw`` stamps of a file go backwards: it cannot be streamed in file order
    (:func:`read_file` sorts such a file in memory)."""


class McapSampleStream:
    """The reader of a calibration MCAP (or rosbag2 bag): block by block for the streaming fit, or every
    sample at once (:meth:`all_batches`, behind :func:`read_file`).

    :meth:`blocks` yields :class:`Recording` blocks of exactly ``block_rows`` samples (the last one
    shorter) in file order: temperature from the ``imu/raw`` field (or the latest ``imu/temperature``
    message at or before the stamp), pose id and reference from :func:`assign_poses`. Pose and reference events are
    collected during the first complete pass (``with_poses=False``); later passes
    (``with_poses=True``) assign them per block. State between passes: the pose, reference and
    (only for raw messages without a temperature field) temperature events, O(poses) values.

    ``imu/raw`` messages in the fixed layout of :class:`ros2_cdr.FixedJointStateCodec` are split out of each
    decompressed chunk with one numpy view per run of equal records (no Python object per message), converted
    to stamps and values once per split; event messages of a topic whose schema is the standard definition are read
    in the layouts ``ros2_cdr`` writes (:func:`_event_reader`), every other message (and an event in another layout)
    through the ``mcap_ros2`` decoder. A truncated file is read up to its last
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
        :data:`REPLAY_ROWS`), with that pass's report. ``keep`` False: a single pass (:meth:`all_batches`), nothing kept."""
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
        readers: dict[int, Any] = {}  # channel id -> the event reader of ros2_cdr's layout (_event_reader), or None
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
                reader = readers.get(channel_id)
                fields = reader(data) if reader is not None else None
                msg = None
                if fields is None:  # not in the layout ros2_cdr reads: the decoder of the channel's schema
                    msg = _decode(path, decoder_of(channel, role), channel, data)
                try:
                    if msg is not None:
                        fields = _event_fields(role, msg)
                        if channel_id not in readers:
                            readers[channel_id] = _event_reader(role, schemas.get(channel.schema_id), msg)
                    if role == TOPIC_TEMPERATURE:
                        self._temp_t.append(fields[0])
                        self._temp_v.append(fields[1])
                    elif role == TOPIC_REFERENCE_GRAVITY:
                        self._gref_events.append(fields)
                    elif role == TOPIC_POSE:
                        values, text = fields
                        event = (int(values.get("pose_id", "-1")), values.get("state", text))
                        self._pose_events.append((log_time - (self._log_offset or 0), *event))
                        self._pose_log.append((log_time, *event))
                except (AttributeError, TypeError, ValueError) as exc:  # e.g. a pose_id that is not a number
                    raise McapRecordingError(f"{path}: a '{channel.topic}' message cannot be read as "
                                             f"{ROLE_TYPES[role]} ({type(exc).__name__}: {first_line(exc)[:200]})"
                                             ) from None
            return None

        def emit(items: Iterable[Any]):
            runs: list[np.ndarray] = []  # runs of fixed-layout raw records not yet converted (at once, run_rows)
            for item in items:
                if isinstance(item, np.ndarray):  # a run of fixed-layout raw records
                    count(report.raw_topic, len(item))
                    if collect_events:
                        last = item[-1]
                        self._raw_clock(int(last["log"]), int(last["sec"]) * 1_000_000_000 + int(last["nanosec"]))
                    runs.append(item)
                elif isinstance(item, tuple):
                    out = message(*item)
                    if out is not None:
                        if runs:
                            yield run_rows(runs)
                            runs = []
                        yield out
                elif isinstance(item, SkippedRange):  # PARTIAL_RECORD, or a chunk of records it cannot hold
                    report.skipped.append(SkippedRange(item.offset, item.end_offset, item.reason))
                else:
                    _note_record(item, schemas, channels, report)
            if runs:
                yield run_rows(runs)

        joined: list[bytes] = []
        joined_bytes = 0
        scratch = bytearray()  # where the joined chunks are split, reused (_split_chunks)
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
                if opcode == _CHUNK:  # records never span chunks: split several chunks at once
                    joined.append(body)
                    joined_bytes += len(body)
                    if joined_bytes < _JOIN_BYTES:
                        continue
                if joined:
                    yield from emit(_split_chunks(joined, fast, scratch))
                    joined, joined_bytes = [], 0
                if opcode != _CHUNK:
                    try:
                        item = _parse_record(opcode, body)
                    except _PartialRecordError as exc:
                        report.stopped_at = str(exc)
                        break
                    yield from emit([item])
        if joined:
            yield from emit(_split_chunks(joined, fast, scratch))

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

    def all_batches(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """Every ``imu/raw`` sample in file order, ``(stamps (N,) int64 ns, [values (n_i, k), ...])``: the values in
        the batches they were read in (:meth:`block` takes its columns from them without a joined copy of every value),
        in one pass that also collects the events (for a reader that holds the whole recording; stamps may go
        backwards)."""
        collect = self._start_pass()
        batches = [(s, v) for s, v in self._batches(collect, keep=False) if len(s)]
        self._end_pass(collect, sum(len(s) for s, _ in batches))  # no samples: raises
        # one width: a message whose name list differs from the first one's already raised in _file_batches
        return np.concatenate([s for s, _ in batches]), [v for _, v in batches]

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

    def block(self, stamps: np.ndarray, rows: np.ndarray | list[np.ndarray], with_poses: bool,
              copy: bool = True) -> Recording:
        """A Recording of copies (the caller reuses ``stamps`` and ``rows``; ``copy`` False: ``stamps`` is the
        caller's to give away). ``rows``: the values (N, k), or the batches of them in order (:meth:`all_batches`)."""
        if copy:
            stamps = stamps.copy()
        col = {n: i for i, n in enumerate(self.names or ())}

        def take(part: Any) -> np.ndarray:
            """``part(rows)``, for batches their parts joined."""
            return part(rows) if isinstance(rows, np.ndarray) else np.concatenate([part(b) for b in rows])

        xyz_cols = [col["x_counts"], col["y_counts"], col["z_counts"]]
        xyz = take(lambda r: r[:, xyz_cols])
        if "temperature_c" in col:
            temp = take(lambda r: r[:, col["temperature_c"]].copy())
            if "temperature_valid" in col:
                temp[take(lambda r: r[:, col["temperature_valid"]] < 0.5)] = np.nan
        elif self._temp_t:
            ts = np.asarray(self._temp_t, dtype=np.int64)
            o = np.argsort(ts, kind="stable")
            idx = np.searchsorted(ts[o], stamps, side="right") - 1
            temp = np.where(idx >= 0, np.asarray(self._temp_v)[o][np.clip(idx, 0, None)], np.nan)
        else:
            temp = np.full(len(stamps), np.nan)
        t_s = take(lambda r: r[:, col["board_time_s"]].copy()) if "board_time_s" in col else stamps * 1e-9
        if with_poses:
            pose_id, gref = assign_poses(stamps, self._pose_events, self._gref_events)
        else:
            pose_id, gref = np.full(len(stamps), -1, dtype=int), np.full((len(stamps), 3), np.nan)
        return Recording(t_s=t_s, ref=take(lambda r: r[:, col["ref_counts"]].copy()), xyz=xyz, temp_c=temp,
                         gref_mps2=gref, pose_id=pose_id,
                         aux=take(lambda r: r[:, col[RAW_AUX_NAME]].copy()) if RAW_AUX_NAME in col else None)

    def metadata(self) -> dict[str, Any]:
        """Run metadata and the read report, as :func:`read_file` puts them in ``Recording.metadata``."""
        md: dict[str, Any] = {name: dict(m) for name, m in self.report.metadata.items()}
        md["source"] = str(self.path)
        md["read_report"] = self.report.as_dict()
        md["pose_events"] = list(self._pose_log)  # at log time, as the chunk ranges read_warnings compares them to
        return md


def _event_fields(role: str, msg: Any) -> tuple[Any, Any]:
    """What the reader takes of an event message decoded by ``mcap_ros2``: ``(stamp ns, temperature degC)``,
    ``(stamp ns, (x, y, z) m/s^2)`` or ``({key: value}, message)`` for a pose event."""
    if role == TOPIC_TEMPERATURE:
        return _stamp_ns(msg.header), float(msg.temperature)
    if role == TOPIC_REFERENCE_GRAVITY:
        return _stamp_ns(msg.header), (msg.vector.x, msg.vector.y, msg.vector.z)
    return {kv.key: kv.value for kv in msg.values}, msg.message


def _event_reader(role: str, schema: Schema | None, msg: Any) -> Any:
    """The reader of an event topic's later messages straight from their bytes, giving :func:`_event_fields`, or
    None when its schema is not the standard definition (``mcap_schemas.standard_event_schema``); it returns None
    for a message not in the layout ``ros2_cdr`` writes (that one goes through the schema's decoder). ``msg``: the
    channel's first message, decoded (its frame id is that of the fixed layouts)."""
    if not standard_event_schema(schema, role):
        return None
    if role == TOPIC_POSE:
        def pose(data: bytes) -> tuple[dict[str, str], str] | None:
            got = ros2_cdr.read_diagnostic_status(data)
            return None if got is None else (dict(got[4]), got[2])
        return pose
    frame_id = msg.header.frame_id
    if not isinstance(frame_id, str):
        return None
    if role == TOPIC_TEMPERATURE:
        codec = ros2_cdr.FixedStampedCodec(frame_id, 2)

        def temperature(data: bytes) -> tuple[int, float] | None:
            got = codec.read(data)
            return None if got is None else (got[0], got[1][0])
        return temperature
    codec = ros2_cdr.FixedStampedCodec(frame_id, 3)
    return codec.read


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
