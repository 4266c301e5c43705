"""The records of a calibration MCAP file, read through damage: the one path of the reader (``mcap_reader``) through a
file (:func:`_file_records`), the decompressed and CRC-checked chunks and the split of their records (runs of
fixed-layout raw messages as one numpy view), the summary section, and the recovery of damaged files: a chunk whose
CRC or decompression fails is skipped, lost framing is resynchronised at the next intact chunk, a file cut short is
read up to its last complete chunk, a repeated chunk is read once; what was passed over is reported
(:class:`FileReadReport`, :func:`read_warnings`)."""

from __future__ import annotations

import hashlib
import io
import struct
import zlib
from dataclasses import dataclass, field
from itertools import accumulate
from pathlib import Path
from typing import Any

import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Metadata, Schema
from mcap.stream_reader import get_chunk_data_stream

from . import ros2_cdr
from .mcap_format import MCAP_MAGIC, TOPIC_RAW, TYPE_RAW, McapRecordingError, TopicSelection, _topic_list

_RECORD_HEAD = struct.Struct("<BQ")
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")  # message start/end time, uncompressed size, uncompressed CRC
_SKIPPED = frozenset(int(o) for o in (Opcode.MESSAGE_INDEX, Opcode.CHUNK_INDEX, Opcode.ATTACHMENT,
                                      Opcode.ATTACHMENT_INDEX, Opcode.STATISTICS, Opcode.METADATA_INDEX,
                                      Opcode.SUMMARY_OFFSET, Opcode.DATA_END, Opcode.HEADER))
_FOOTER, _MESSAGE_INDEX, _CHUNK, _MESSAGE = (int(o) for o in (Opcode.FOOTER, Opcode.MESSAGE_INDEX, Opcode.CHUNK,
                                                              Opcode.MESSAGE))  # plain ints: compared per record
_PARSED = {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.METADATA: Metadata}


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
        if opcode == _FOOTER:
            return
        if opcode == _MESSAGE_INDEX and last_skip is not None:  # the lost chunk's index: count its messages
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
        if opcode == _CHUNK:
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


def _record_at(data: bytes | memoryview, pos: int, size: int) -> tuple[Any, int]:
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
    return _parse_record(opcode, bytes(data[pos + 9:end])), end


def _parse_record(opcode: int, body: bytes) -> Any:
    """A record, in a chunk or not: a message ``(channel_id, log_time, data)``, a parsed Schema/Channel/Metadata,
    or None for other opcodes."""
    if opcode == _MESSAGE:
        if len(body) < _MESSAGE_HEAD.size:
            raise _PartialRecordError("message record shorter than its header")
        channel_id, _seq, log_time, _pub = _MESSAGE_HEAD.unpack_from(body, 0)
        return channel_id, log_time, body[_MESSAGE_HEAD.size:]
    if opcode in _PARSED:
        return _PARSED[opcode].read(ReadDataStream(io.BytesIO(body)))
    return None


def _set_fast(fast: dict[str, Any], channel_id: int, codec: ros2_cdr.FixedJointStateCodec) -> None:
    """Record layout of one fixed-layout raw message inside a chunk (opcode, length, message header, CDR): ``head``
    its opcode, length and channel id as bytes (what :func:`_split_chunks` looks for), ``size`` its bytes, ``dtype``
    the fields a run's records are read by (``log`` the log time (ns), ``sec``/``nanosec`` the stamp, ``values`` the
    positions; :func:`run_rows`)."""
    if len(codec.middle) % 8 or 12 + len(codec.middle) + 8 * codec.n_values + len(codec.tail) != codec.size:
        return  # not the layout the writer makes (its middle ends 8-aligned): every message decoded one by one
    size = 9 + 22 + codec.size
    values_at = 9 + 22 + 12 + len(codec.middle)  # after the record's and message's heads, the stamp and the middle
    fast["codec"] = codec
    fast["size"] = size
    fast["head"] = _RECORD_HEAD.pack(Opcode.MESSAGE, size - 9) + struct.pack("<H", channel_id)
    fast["dtype"] = np.dtype({"names": ["log", "sec", "nanosec", "values"],
                              "formats": ["<u8", "<i4", "<u4", ("<f8", (codec.n_values,))],
                              "offsets": [15, 35, 39, values_at], "itemsize": size})


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
_FAST_RUN_MIN = 512  # records checked at once first: a recording's run between two events is shorter
_NEAR_ENDS = 4  # later chunk ends looked at one by one for the end of a run (then _first_misaligned_end)
_FAST_RUN_MAX = 16384  # records checked at once for a run of fixed-layout raw messages


def _first_misaligned_end(ends: np.ndarray, pos: int, rec_size: int, size: int, window: int = 64) -> int:
    """The first of the chunk ends ``ends`` (ascending) after ``pos`` that does not fall a whole number of records of
    ``rec_size`` bytes after it; ``size`` when none does. Looked for in windows growing x4 from the next end: a run
    usually stops within a few chunks, so a file's runs do not each read every later end."""
    lo = int(np.searchsorted(ends, pos, side="right"))
    while lo < len(ends):
        later = ends[lo:lo + window]
        misaligned = np.flatnonzero((later - pos) % rec_size)
        if misaligned.size:
            return int(later[misaligned[0]])
        lo, window = lo + window, 4 * window
    return size


def _split_chunks(bodies: list[bytes], fast: dict[str, Any], scratch: bytearray | None = None):
    """Records of decompressed chunks ``bodies``, split together: for each run of consecutive fixed-layout raw
    messages a structured numpy view of its records (``fast["dtype"]``; :func:`run_rows` gives their stamps and
    values), ``(channel_id, log_time, data)`` for other messages, and parsed Schema/Channel/Metadata records. No
    record is read across the end of its chunk (records never span chunks): a run goes on into the next chunk only
    where its chunk ends between two of its records, and a chunk that ends inside a record (an interrupted writer
    that still checksummed it) yields :data:`PARTIAL_RECORD` there and the split goes on at the next chunk's start.

    A run is checked in one window of up to :data:`_FAST_RUN_MIN` records (a recording's runs between two events),
    then in windows growing x4; every record of a run has the raw layout's opcode, length, channel, encapsulation
    and middle (frame id and names).

    ``scratch``: where the chunks are joined, the caller's, reused from one split to the next (a fresh megabyte for
    each split costs more in page faults than the copy); the views of a split must be gone (:func:`run_rows`)
    before the next one, which overwrites it. None: a new buffer."""
    ends = list(accumulate(len(b) for b in bodies))
    size = ends[-1] if ends else 0
    if len(bodies) == 1:
        data: bytes | bytearray = bodies[0]
    elif scratch is None:
        data = b"".join(bodies)
    else:
        if len(scratch) < size:
            scratch.extend(bytes(size - len(scratch)))  # a view of the last split still alive: BufferError
        at = 0
        for body in bodies:
            scratch[at:at + len(body)] = body
            at += len(body)
        data = scratch
    view = memoryview(data)
    ends_array: np.ndarray | None = None  # for the look at many later ends (_first_misaligned_end)
    pos = 0
    ci = 0  # the chunk pos is in: the first with ends[ci] > pos
    while pos < size:
        while ends[ci] <= pos:
            ci += 1
        chunk_end = ends[ci]
        rec_size = fast.get("size")
        if rec_size is not None and view[pos:pos + 11] == fast["head"]:  # a raw record's opcode, length, channel
            limit = chunk_end
            if (chunk_end - pos) % rec_size == 0:  # its chunk ends between two records: the first later end that
                limit = size                       # does not, when it is among the next few; else looked for in windows
                for later in ends[ci + 1:ci + 1 + _NEAR_ENDS]:
                    if (later - pos) % rec_size:
                        limit = later
                        break
                else:
                    if len(ends) > ci + 1 + _NEAR_ENDS:
                        if ends_array is None:
                            ends_array = np.asarray(ends)
                        limit = _first_misaligned_end(ends_array, pos, rec_size, size)
            left = (limit - pos) // rec_size
            window = _FAST_RUN_MIN
            while left:  # windows growing x4 while every record matches the raw layout
                kk = min(left, window)
                n_ok = _run_length(data, pos, kk, fast)
                if n_ok:
                    yield np.frombuffer(data, dtype=fast["dtype"], count=n_ok, offset=pos)
                    pos += n_ok * rec_size
                if n_ok < kk:
                    break
                left -= kk
                window = min(4 * window, _FAST_RUN_MAX)
            if pos >= size:
                break
            while ends[ci] <= pos:
                ci += 1
            chunk_end = ends[ci]
        try:
            item, pos = _record_at(view, pos, chunk_end)
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


def _run_length(data: bytes | bytearray, pos: int, n: int, fast: dict[str, Any]) -> int:
    """How many of the ``n`` records of ``fast["size"]`` bytes from ``pos`` on are, one after the other, raw records of
    the fixed layout: the opcode, length and channel (``fast["head"]``), the encapsulation and the middle (frame id
    and names) of each equal to the layout's. Each field of the ``n`` records is copied out in one piece and compared
    in one piece with the field repeated; where they differ, the first differing byte says which record ends the
    run."""
    rec = fast["size"]
    for offset, part in ((0, fast["head"]), (31, ros2_cdr.ENCAPSULATION), (43, fast["codec"].middle)):
        if n == 0:
            break
        width = len(part)
        got = np.ndarray((n, width), np.uint8, data, pos + offset, (rec, 1)).tobytes()
        want = _repeated(fast, part, n)
        if not want.startswith(got):  # (compared in place: no copy of the first n of the repeats)
            n = _first_difference(got, want[:len(got)]) // width
    return n


def _repeated(fast: dict[str, Any], field: bytes, n: int) -> bytes:
    """``field`` repeated ``n`` times or more (kept in ``fast`` for the largest ``n`` asked so far)."""
    key = ("repeated", field)
    have = fast.get(key, b"")
    if len(have) < n * len(field):
        have = fast[key] = field * max(n, _FAST_RUN_MIN)
    return have


def _first_difference(a: bytes, b: bytes) -> int:
    """The index of the first byte where ``a`` and ``b`` (of one length, not equal) differ."""
    x = int.from_bytes(a, "little") ^ int.from_bytes(b, "little")
    return ((x & -x).bit_length() - 1) // 8


def run_rows(runs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps (k,) int64 ns, values (k, n) float)`` of consecutive runs of fixed-layout raw records (the views
    :func:`_split_chunks` yields), in order, converted at once."""
    if len(runs) == 1:
        recs = runs[0]
    else:  # joined as records of plain bytes: a concatenation of the structured dtype compares its fields run by run
        plain = np.dtype((np.void, runs[0].dtype.itemsize))
        recs = np.concatenate([r.view(plain) for r in runs]).view(runs[0].dtype)
    return recs["sec"].astype(np.int64) * 1_000_000_000 + recs["nanosec"].astype(np.int64), recs["values"].astype(float)
