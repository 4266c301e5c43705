"""Streaming decoder for the board's byte stream (pure Python, no ROS).

Feed it arbitrary chunks as they arrive from the serial port; it returns the intact frames and
keeps counters of everything it rejected. It never raises on any input and never blocks.

Rules (see docs/protocol.md):

* Versions 1 (27 bytes) and 2 (29 bytes: version 1 + ``aux``) are decoded; a version-2 frame
  comes out as a ``Frame`` with ``aux`` set, a version-1 frame with ``aux`` None.
* A frame candidate starts at ``SYNC`` with a known ``version`` and its ``body_len``. If its
  CRC fails, the candidate is counted in ``crc_errors`` and the search resumes one byte after
  the sync, so a frame hidden behind a truncated one or behind garbage is still recovered.
* Bytes that are not part of an accepted frame are counted in ``bytes_discarded``.
* A CRC-valid frame with an ADC count above 12 bits, or with another ``seq`` but the same ``t_us`` as the
  last accepted frame (a board clock that did not advance), is ``invalid_frames``: dropped, and lost.
* A CRC-valid frame with the sync of a version this decoder does not know is counted in
  ``unsupported_version`` and its bytes are searched for frames like those of a failed candidate, so intact
  frames inside it (a CRC right by chance over a stretch of the stream) are still recovered.
* Sequence tracking, for frames whose board clock moves forward: a gap of ``g`` sequence
  numbers adds ``g - 1`` to ``lost_frames``. Frames rejected for CRC are
  therefore also counted as lost: ``lost_frames`` is what the host did not receive intact.
  ``g`` is the step of the 16-bit ``seq`` (1..65536), plus the whole number of 65536 wraps the
  64-bit ``t_us`` step shows: ``g + 65536 round((dt_step / dt - g) / 65536)`` (never fewer), with
  ``dt`` the nominal sample interval (:class:`SampleInterval`); so a link outage of 65536 samples
  or more is counted in full. Until a first interval is known, the modulo-2**16 step alone.
* A frame identical in ``seq`` and ``t_us`` to the previous one is a ``duplicate`` and dropped.
* A board clock that goes backwards, or a frame with the BOOT status bit after the first
  frame, is a board ``reset``: tracking restarts and no loss is counted across it.
"""

from __future__ import annotations

from bisect import bisect_left, insort
from dataclasses import asdict, dataclass

from .frame_codec import (
    ADC_MAX,
    BODY_LEN_BY_VERSION,
    CRC_SIZE,
    HEADER_SIZE,
    PROTOCOL_VERSION,
    SEQ_MODULO,
    SYNC,
    Frame,
    Status,
    crc16,
    decode_body_v1,
    decode_body_v2,
)

# Longest body any future version may declare; a larger body_len means "not a frame".
MAX_BODY_LEN = 200
# Steps (between frames of consecutive seq) the nominal sample interval is the median of: a late read's catch-up
# leaves one irregular step the ADC_OVERRUN rule does not exclude (``SampleInterval``), a median of 7 outvotes 3.
INTERVAL_WINDOW = 7
_OVERRUN = int(Status.ADC_OVERRUN)
HALF_WRAP = SEQ_MODULO // 2


class SampleInterval:
    """The board's nominal sample interval (us), robust to a late read and its catch-up.

    When the sampler misses a deadline the firmware takes that read late (ADC_OVERRUN) and then the reads
    already due back to back, an ADC conversion (~40 us) apart (firmware/core/fbg_scheduler.c,
    ``fbg_sched_take``): one step between consecutive ``seq`` is long, the next ones are ~40 us, and the
    step into the next on-time read is short. None of them is the sample interval. :meth:`add` takes the
    ``t_us`` step between two frames of consecutive ``seq``; a step that starts or ends at an ADC_OVERRUN
    frame is ignored, and :attr:`us` is the median of the last :data:`INTERVAL_WINDOW` others (0 until
    the first). O(1) a frame: a fixed ring, and a sorted copy of it updated by one removal and one
    insertion, skipped when the step equals the one it replaces (a steady board).
    """

    __slots__ = ("_next", "_ring", "_sorted", "us")

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget every step (board reset)."""
        self._ring: list[int] = []
        self._sorted: list[int] = []
        self._next = 0
        self.us = 0

    def add(self, step_us: int, overrun: int) -> None:
        """A ``t_us`` step (> 0) between frames of consecutive ``seq``; ``overrun``: either frame has ADC_OVERRUN."""
        if overrun:
            return
        ring, srt = self._ring, self._sorted
        if len(ring) < INTERVAL_WINDOW:
            ring.append(step_us)
            insort(srt, step_us)
        else:
            i = self._next
            self._next = (i + 1) % INTERVAL_WINDOW
            old = ring[i]
            if old == step_us:
                return
            ring[i] = step_us
            del srt[bisect_left(srt, old)]
            insort(srt, step_us)
        self.us = srt[len(srt) // 2]


@dataclass
class DecoderStats:
    """Cumulative counters since the decoder was created (all counts, never reset)."""

    frames: int = 0
    bytes_received: int = 0
    bytes_discarded: int = 0
    crc_errors: int = 0
    invalid_frames: int = 0  # CRC fine but absurd: an ADC count (aux included) above 12 bits, or a stuck board clock
    unsupported_version: int = 0  # CRC-valid frames of a version other than 1 and 2
    lost_frames: int = 0
    duplicates: int = 0
    resets: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class StreamDecoder:
    """Incremental decoder: ``feed(chunk) -> list[Frame]``.

    ``resets_at`` lists, after each ``feed``, the indices in its returned list of the frames that
    start a new board run (the reset rule of the module docstring), so a consumer can split there.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.stats = DecoderStats()
        self._last_seq: int | None = None
        self._last_t_us: int | None = None
        self._last_overrun = 0
        self.interval = SampleInterval()  # nominal sample interval of the current board run (unwraps long outages)
        # Bytes of accepted and duplicate frames (27 per version-1 frame, 29 per version-2 frame):
        # bytes_received = bytes_discarded + frame_bytes + buffered, whatever the mix of versions.
        self.frame_bytes = 0
        self.resets_at: list[int] = []

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[Frame]:
        """Consume ``chunk`` and return the intact, non-duplicate frames it completed."""
        out: list[Frame] = []
        self.resets_at = []
        try:
            data = bytes(memoryview(chunk))  # bytes-like only: bytes(int) would allocate int zero bytes
        except (TypeError, ValueError):
            return out
        if not data:
            return out
        self.stats.bytes_received += len(data)
        buf = self._buf
        buf += data
        pos = 0
        n = len(buf)
        while True:
            start = buf.find(SYNC, pos)
            if start < 0:
                # Keep a trailing first sync byte that may pair with the next chunk.
                keep_from = n - 1 if n > pos and buf[n - 1] == SYNC[0] else n
                self.stats.bytes_discarded += keep_from - pos
                pos = keep_from
                break
            if start > pos:
                self.stats.bytes_discarded += start - pos
                pos = start
            if n - pos < HEADER_SIZE:
                break  # wait for the header
            version = buf[pos + 2]
            body_len = buf[pos + 3]
            known_len = BODY_LEN_BY_VERSION.get(version)
            if version == 0 or body_len == 0 or body_len > MAX_BODY_LEN or (
                known_len is not None and body_len != known_len
            ):
                self.stats.bytes_discarded += 1
                pos += 1
                continue
            total = HEADER_SIZE + body_len + CRC_SIZE
            if n - pos < total:
                break  # wait for the rest of the candidate
            crc_rx = buf[pos + total - 2] | (buf[pos + total - 1] << 8)
            if crc16(memoryview(buf)[pos + 2 : pos + total - 2]) != crc_rx:
                self.stats.crc_errors += 1
                self.stats.bytes_discarded += 1
                pos += 1
                continue
            if known_len is None:  # looked into like a failed candidate: it may hold intact frames
                self.stats.unsupported_version += 1
                self.stats.bytes_discarded += 1
                pos += 1
                continue
            if version == PROTOCOL_VERSION:
                frame = decode_body_v1(buf, pos + HEADER_SIZE)
                top = max(frame.ref, frame.x, frame.y, frame.z)
            else:  # version 2: the version-1 fields + aux
                frame = decode_body_v2(buf, pos + HEADER_SIZE)
                top = max(frame.ref, frame.x, frame.y, frame.z, frame.aux)
            pos += total
            if top > ADC_MAX or self._clock_stuck(frame):
                self.stats.invalid_frames += 1
                self.stats.bytes_discarded += total
                continue
            self.frame_bytes += total  # accepted or duplicate
            accepted = self._accept(frame)
            if accepted is not None:
                if accepted:
                    self.resets_at.append(len(out))
                out.append(frame)
        if pos:
            del buf[:pos]
        return out

    def _clock_stuck(self, frame: Frame) -> bool:
        """Another sample at the last accepted frame's board time (not a duplicate, not a reboot): the board clock did
        not advance, so the frame has no time of its own to be stamped with."""
        return (frame.t_us == self._last_t_us and frame.seq != self._last_seq
                and not frame.status & Status.BOOT)

    def _accept(self, frame: Frame) -> bool | None:
        """Sequence and clock bookkeeping: None for a duplicate, else whether the frame follows a reset."""
        last_seq, last_t = self._last_seq, self._last_t_us
        reset = False
        if last_seq is not None and last_t is not None:
            if frame.seq == last_seq and frame.t_us == last_t:
                self.stats.duplicates += 1
                return None
            reset = frame.t_us < last_t or bool(frame.status & Status.BOOT)
            overrun = frame.status & _OVERRUN
            if reset:
                self.stats.resets += 1
                self.interval.reset()
            else:
                step = (frame.seq - last_seq - 1) % SEQ_MODULO + 1  # 1..65536 (the same seq: a whole wrap)
                dt_step = frame.t_us - last_t
                dt = self.interval.us
                if dt > 0 and dt_step > (step + HALF_WRAP) * dt:  # the board clock shows whole wraps of seq
                    step += max(0, round((dt_step / dt - step) / SEQ_MODULO)) * SEQ_MODULO
                if step == 1:
                    self.interval.add(dt_step, overrun | self._last_overrun)
                else:
                    self.stats.lost_frames += step - 1
            self._last_overrun = overrun
        else:
            self._last_overrun = frame.status & _OVERRUN
        self._last_seq, self._last_t_us = frame.seq, frame.t_us
        self.stats.frames += 1
        return reset

    @property
    def buffered(self) -> int:
        """Bytes held while waiting for the rest of a frame."""
        return len(self._buf)
