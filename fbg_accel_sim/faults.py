"""Fault injection on the board's byte stream, and the decoder counts it must produce (pure numpy).

Wire faults (one per frame at most, drawn at fixed sample indices from the seed):

* ``dropped``: the frame never reaches the host (sequence gap).
* ``duplicated``: the frame is sent twice in a row (the decoder drops the copy).
* ``bit_flips``: one bit flipped in the body/CRC region, bytes 4..26 (never sync/version/length:
  a flip there makes the decoder skip a header instead of failing a CRC). CRC-16 detects every
  single-bit error, so each flip is exactly one CRC error and one lost frame.
* ``truncated``: only the first 4..26 bytes of the frame are sent (header intact), then the next
  frame. The decoder tries the candidate, fails its CRC once, and resynchronises on the next
  frame: exactly one CRC error and one lost frame.
* ``garbage``: a burst of random bytes between frames; the bytes 0xA5 and 0x5A never occur in a
  burst, so garbage can never form or complete a sync pattern and costs no CRC error.

Exactness guards: a corrupted frame whose remaining bytes happen to contain the sync pattern
(the decoder would try it as a candidate) gets another bit/length, and a truncated candidate
window that happens to pass the CRC (p = 2^-16) gets another length; both checks run on the final
bytes. So the truth counters equal what ``StreamDecoder`` reports, exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fbg_accel_driver.frame_codec import (
    BODY_LEN_V1,
    BODY_LEN_V2,
    FRAME_SIZE_V1,
    FRAME_SIZE_V2,
    PROTOCOL_VERSION,
    PROTOCOL_VERSION_V2,
    SEQ_MODULO,
    SYNC,
    Status,
    crc16,
)

DROP, DUPLICATE, BIT_FLIP, TRUNCATE = 1, 2, 3, 4  # wire fault codes (0 = none)
FLIP_FIRST_BYTE = 4  # first byte a bit flip may touch (after sync, version, body_len)
TRUNC_MIN = 4  # fewest bytes kept of a truncated frame (at most its size - 1)
_GARBAGE_ALPHABET = np.array([b for b in range(256) if b not in (SYNC[0], SYNC[1])], dtype=np.uint8)

_FIELDS = [("sync", "u1", (2,)), ("version", "u1"), ("body_len", "u1"), ("seq", "<u2"), ("t_us", "<u8"),
           ("ref", "<u2"), ("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("temp_cc", "<i2"), ("status", "u1")]
FRAME_DTYPE = np.dtype([*_FIELDS, ("crc", "<u2")])
FRAME_DTYPE_V2 = np.dtype([*_FIELDS, ("aux", "<u2"), ("crc", "<u2")])
assert (FRAME_DTYPE.itemsize, FRAME_DTYPE_V2.itemsize) == (FRAME_SIZE_V1, FRAME_SIZE_V2)


def encode_frames(seq: np.ndarray, t_us: np.ndarray, counts: np.ndarray, temp_cc: np.ndarray, status: np.ndarray,
                  aux: np.ndarray | None = None) -> np.ndarray:
    """Vectorised ``frame_codec.encode_frame``: (N,) records with valid CRCs, version 1 (FRAME_DTYPE) or,
    when ``aux`` (N,) counts are given, version 2 (FRAME_DTYPE_V2)."""
    n = len(seq)
    v2 = aux is not None
    rec = np.zeros(n, dtype=FRAME_DTYPE_V2 if v2 else FRAME_DTYPE)
    size = rec.dtype.itemsize
    rec["sync"] = np.frombuffer(SYNC, dtype=np.uint8)
    rec["version"] = PROTOCOL_VERSION_V2 if v2 else PROTOCOL_VERSION
    rec["body_len"] = BODY_LEN_V2 if v2 else BODY_LEN_V1
    if v2:
        rec["aux"] = aux
    rec["seq"] = np.asarray(seq) % SEQ_MODULO
    rec["t_us"] = t_us
    rec["ref"], rec["x"], rec["y"], rec["z"] = (counts[:, i] for i in range(4))
    rec["temp_cc"] = temp_cc
    rec["status"] = status
    raw = memoryview(rec.tobytes())
    rec["crc"] = np.fromiter((crc16(raw[i * size + 2: (i + 1) * size - 2]) for i in range(n)), dtype=np.uint16, count=n)
    return rec


def corrupt_flip(frame: bytes, bit_index: int) -> bytes:
    """Flip bit ``bit_index`` (0-based over bytes FLIP_FIRST_BYTE..end of the CRC) of a frame."""
    b = bytearray(frame)
    byte = FLIP_FIRST_BYTE + bit_index // 8
    b[byte] ^= 1 << (bit_index % 8)
    return bytes(b)


def hides_sync(corrupted: bytes) -> bool:
    """True if the decoder, rescanning a rejected candidate from its second byte, would meet a sync."""
    return corrupted.find(SYNC, 1) >= 0


def garbage_bytes(rng: np.random.Generator, n: int) -> bytes:
    return _GARBAGE_ALPHABET[rng.integers(0, _GARBAGE_ALPHABET.size, n)].tobytes()


@dataclass
class FaultSchedule:
    """Sample indices of the wire faults and garbage bursts (``wire[k]``, ``garbage[k]`` = bytes before k)."""

    wire: dict[int, int] = field(default_factory=dict)
    garbage: dict[int, int] = field(default_factory=dict)


def schedule_faults(fcfg: dict, rate_true_hz: float, end_s: float, rng: np.random.Generator,
                    unsent: callable, chunk: int) -> FaultSchedule:
    """Place the configured wire faults on sample indices (explicit ``at_s`` plus ``count`` random ones).

    ``unsent(k)`` tells whether sample k is never sent (boot gap, disconnect); faults move forward to
    the next free, sent sample. A truncated frame is never the last of a generation chunk (its
    guard needs the next frame's bytes) and is followed by a sent frame without a wire fault.
    """
    sched = FaultSchedule()
    start = float(fcfg.get("start_s", 0.0))

    def times(kind: str) -> list[float]:
        spec = fcfg.get(kind) or {}
        ts = [float(t) for t in spec.get("at_s") or []]
        count = int(spec.get("count", 0) or 0)
        if count:
            if not math.isfinite(end_s) or end_s <= start:
                raise ValueError(f"faults.{kind}.count needs a finite window: set faults.end_s or scenario.duration_s")
            ts += list(np.sort(rng.uniform(start, end_s, count)))
        return ts

    used: set[int] = set()

    # Faults stay off the last two samples of a finite run (a truncated final frame would wait forever
    # for the rest of its candidate window); a collision moves forward, or backward near the end.
    k_max = math.floor(end_s * rate_true_hz) - 3 if math.isfinite(end_s) else None

    def free(k: int, need_next: bool) -> bool:
        ok = k not in used and not unsent(k)
        if ok and need_next:  # the next frame goes on the wire unchanged, in the same chunk
            ok = (k + 1) % chunk != 0 and not unsent(k + 1) and k + 1 not in used
        return ok

    def place(t: float, need_next: bool) -> int:
        k0 = max(0, math.ceil(t * rate_true_hz - 1e-9))
        if k_max is not None:
            k0 = min(k0, k_max)
        k = k0
        while k_max is None or k <= k_max:
            if free(k, need_next):
                return k
            k += 1
        for k in range(k0 - 1, -1, -1):
            if free(k, need_next):
                return k
        raise ValueError("too many faults for the run: no free sample left")

    for code, kind in ((DROP, "dropped"), (DUPLICATE, "duplicated"), (BIT_FLIP, "bit_flips"), (TRUNCATE, "truncated")):
        for t in times(kind):
            k = place(t, need_next=code == TRUNCATE)
            used.add(k)
            if code == TRUNCATE:
                used.add(k + 1)  # reserved: its bytes are the ones the truncation guard checked
            sched.wire[k] = code
    gspec = fcfg.get("garbage") or {}
    lo, hi = int(gspec.get("min_bytes", 5)), int(gspec.get("max_bytes", 60))
    for t in times("garbage"):
        k = max(0, math.ceil(t * rate_true_hz - 1e-9))
        while k in sched.garbage or unsent(k):
            k += 1
        if k_max is not None:
            k = min(k, k_max + 2)  # a burst before the last sample still arrives and is discarded
        sched.garbage[k] = sched.garbage.get(k, 0) + int(rng.integers(lo, hi + 1))
    return sched


class ExpectedDecoder:
    """Mirror of ``StreamDecoder``'s sequence bookkeeping on the frames the wire delivers intact."""

    def __init__(self) -> None:
        self.last_seq: int | None = None
        self.last_t: int | None = None
        self.frames = 0
        self.lost_frames = 0
        self.duplicates = 0
        self.resets = 0

    def feed(self, seq: np.ndarray, t_us: np.ndarray, status: np.ndarray) -> None:
        """Delivered intact frames in wire order (duplicates included)."""
        if len(seq) == 0:
            return
        seq = np.asarray(seq, np.int64)
        t = np.asarray(t_us, np.int64)
        boot = (np.asarray(status) & int(Status.BOOT)) != 0
        prev_seq = np.concatenate([[self.last_seq if self.last_seq is not None else -1], seq[:-1]])
        prev_t = np.concatenate([[self.last_t if self.last_t is not None else -1], t[:-1]])
        has_prev = np.ones(len(seq), bool)
        if self.last_seq is None:
            has_prev[0] = False
        dup = has_prev & (seq == prev_seq) & (t == prev_t)
        # Duplicates do not update the decoder's last seq/t, but a duplicate equals its predecessor,
        # so comparing every frame with its wire predecessor gives the same answer.
        acc = ~dup
        reset = has_prev & acc & ((t < prev_t) | boot)
        gap = has_prev & acc & ~reset
        self.duplicates += int(dup.sum())
        self.frames += int(acc.sum())
        self.resets += int(reset.sum())
        self.lost_frames += int(((seq[gap] - prev_seq[gap] - 1) % SEQ_MODULO).sum())
        self.last_seq, self.last_t = int(seq[-1]), int(t[-1])
