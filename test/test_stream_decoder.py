"""Tests of the streaming decoder (fbg_accel_driver.stream_decoder): unit cases and hypothesis properties.

Properties (docs/protocol.md, "Decoder rules"):

* every intact frame fed in is returned, once, in order, whatever garbage, truncated or bit-flipped
  frames surround it and however the bytes are cut into chunks;
* nothing raises; the decoder's memory stays bounded (arbitrary bytes: test_fuzz_inputs);
* counters are exact: ``crc_errors`` when only body/CRC bytes were corrupted, ``lost_frames`` from
  the sequence gaps (with wrap-around at 65535), ``duplicates``, ``resets`` (BOOT flag or clock going
  backwards), and a byte balance ``received = discarded + 27 * (frames + duplicates) + buffered``.

The one thing a sync/CRC protocol cannot do is tell a garbage candidate whose CRC happens to be
valid (probability 2^-16) from a real frame; generated streams containing one are discarded with
``assume`` (``has_foreign_valid_candidate``), everything else must hold exactly.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from fbg_accel_driver.frame_codec import (
    ADC_MAX,
    CRC_SIZE,
    FRAME_SIZE_V1,
    HEADER_SIZE,
    SEQ_MODULO,
    SYNC,
    Frame,
    Status,
    crc16,
    encode_frame,
)
from fbg_accel_driver.stream_decoder import MAX_BODY_LEN, StreamDecoder

MAX_CANDIDATE = HEADER_SIZE + MAX_BODY_LEN + CRC_SIZE  # longest candidate the decoder may wait for (206 bytes)
# Zero bytes appended after a test stream: "the line carries on", so a false header in garbage that
# announced a long body is completed, rejected, and the frames held behind it come out.
LINE_CONTINUES = bytes(MAX_CANDIDATE)
OK_STATUS = int(Status.TEMP_VALID | Status.TEMP_PRESENT)

PROPERTY = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ----------------------------------------------------------------------------- helpers
def make_frames(n: int, seq0: int = 0, t0: int = 1_000_000, dt: int = 10_000, status: int = OK_STATUS) -> list[Frame]:
    """``n`` consecutive frames of one boot session (seq +1 mod 65536, clock +dt us)."""
    return [
        Frame(
            seq=(seq0 + i) % SEQ_MODULO,
            t_us=t0 + i * dt,
            ref=3000 + i % 5,
            x=1000 + i % 7,
            y=2000,
            z=(i * 37) % (ADC_MAX + 1),
            temp_cc=2345,
            status=status,
        )
        for i in range(n)
    ]


def wire(frames: list[Frame]) -> bytes:
    return b"".join(encode_frame(f) for f in frames)


def future_frame(body: bytes, version: int = 3) -> bytes:
    """A CRC-valid frame of a hypothetical protocol version (3: unknown to this decoder) with a longer body."""
    covered = bytes([version, len(body)]) + body
    return SYNC + covered + crc16(covered).to_bytes(2, "little")


def split(stream: bytes, sizes: list[int]) -> list[bytes]:
    """Cut ``stream`` into chunks of the given sizes (cycled), the last chunk takes the rest."""
    chunks, pos, i = [], 0, 0
    while pos < len(stream):
        size = sizes[i % len(sizes)] if sizes else len(stream)
        chunks.append(stream[pos : pos + size])
        pos += size
        i += 1
    return chunks


def run(chunks: list[bytes], dec: StreamDecoder | None = None) -> tuple[StreamDecoder, list[Frame]]:
    """Feed ``chunks``; also check that ``resets_at`` marks exactly the frames that start a new board run."""
    dec = dec or StreamDecoder()
    out: list[Frame] = []
    marked: list[int] = []
    resets_before = dec.stats.resets
    for chunk in chunks:
        frames = dec.feed(chunk)
        marked += [len(out) + i for i in dec.resets_at]
        out.extend(frames)
        assert dec.buffered < MAX_CANDIDATE
    check_byte_balance(dec)
    assert len(marked) == dec.stats.resets - resets_before
    assert all(out[i].t_us < out[i - 1].t_us or out[i].status & Status.BOOT for i in marked)
    return dec, out


def check_byte_balance(dec: StreamDecoder) -> None:
    s = dec.stats
    assert s.bytes_received == s.bytes_discarded + FRAME_SIZE_V1 * (s.frames + s.duplicates) + dec.buffered
    assert min(s.as_dict().values()) >= 0


def has_foreign_valid_candidate(stream: bytes, intact_starts: set[int]) -> bool:
    """True if a sync at a position other than an intact frame starts a CRC-valid candidate.

    Conservative (ignores the decoder's header rules): any body length byte > 0 whose CRC checks.
    """
    i = stream.find(SYNC)
    while i >= 0:
        if i not in intact_starts and i + HEADER_SIZE <= len(stream):
            end = i + HEADER_SIZE + stream[i + 3] + CRC_SIZE
            if stream[i + 3] and end <= len(stream):
                if crc16(stream[i + 2 : end - 2]) == int.from_bytes(stream[end - 2 : end], "little"):
                    return True
        i = stream.find(SYNC, i + 1)
    return False


# ----------------------------------------------------------------------------- strategies
adc = st.integers(0, ADC_MAX)
status_no_boot = st.integers(0, 255).map(lambda s: s & ~int(Status.BOOT))


@st.composite
def sessions(draw: st.DrawFn, max_frames: int = 40, boot_first: bool = False) -> list[Frame]:
    """Consecutive frames of one boot session, often starting near the sequence wrap-around."""
    n = draw(st.integers(1, max_frames))
    seq0 = draw(st.one_of(st.integers(SEQ_MODULO - max_frames, SEQ_MODULO - 1), st.integers(0, SEQ_MODULO - 1)))
    t = draw(st.integers(0, 2**40)) if not boot_first else draw(st.integers(0, 5_000))
    # The board's clock advances by about one sample interval per sequence number (the firmware's scheduler): the
    # decoder reads whole wraps of seq in a t_us step far longer than that (a long outage), so the clock steps vary
    # around a nominal interval, not arbitrarily.
    dt0 = draw(st.integers(1, 100_000))
    out = []
    for i in range(n):
        status = draw(status_no_boot)
        if boot_first and i == 0:
            status |= int(Status.BOOT)
        out.append(
            Frame(
                seq=(seq0 + i) % SEQ_MODULO,
                t_us=t,
                ref=draw(adc),
                x=draw(adc),
                y=draw(adc),
                z=draw(adc),
                temp_cc=draw(st.integers(-(2**15), 2**15 - 1)),
                status=status,
            )
        )
        t += dt0 + draw(st.integers(0, dt0 // 2))
    return out


garbage = st.one_of(
    st.binary(max_size=40),
    # sync-rich garbage: false headers of every kind
    st.lists(
        st.sampled_from([b"\xa5", b"\x5a", SYNC, SYNC + b"\x01\x15", b"\x01", b"\x15", b"\x00", b"\xc8", b"\xff"]), max_size=12
    ).map(b"".join),
)


@dataclass
class Built:
    """A generated byte stream and what an ideal decoder must report for it."""

    stream: bytes = b""
    intact_starts: set[int] = field(default_factory=set)
    expected: list[Frame] = field(default_factory=list)  # intact frames, in order, once
    duplicates: int = 0
    body_corrupted: int = 0  # frames with only body/CRC bytes altered
    lost: int = 0
    resets: int = 0


ACTIONS_EXACT = ["keep", "keep", "keep", "drop", "corrupt_body", "duplicate"]
ACTIONS_ALL = [*ACTIONS_EXACT, "corrupt_header", "truncate"]


@st.composite
def built_streams(draw: st.DrawFn, actions: list[str], with_garbage: bool, n_sessions: int = 1) -> Built:
    """Sessions of frames, each frame kept, dropped, duplicated, corrupted or truncated, with garbage between."""
    b = Built()
    parts: list[bytes] = []
    pos = 0
    last_received: Frame | None = None
    sessions_seen = 0
    for k in range(n_sessions):
        frames = draw(sessions(boot_first=n_sessions > 1))
        acts = draw(st.lists(st.sampled_from(actions), min_size=len(frames), max_size=len(frames)))
        received_idx: list[int] = []
        for i, (f, act) in enumerate(zip(frames, acts, strict=True)):
            if with_garbage:
                g = draw(garbage)
                parts.append(g)
                pos += len(g)
            enc = encode_frame(f)
            if act in ("keep", "duplicate"):
                copies = 2 if act == "duplicate" else 1
                for c in range(copies):
                    if c and with_garbage:
                        g = draw(garbage)
                        parts.append(g)
                        pos += len(g)
                    b.intact_starts.add(pos)
                    parts.append(enc)
                    pos += len(enc)
                if not received_idx and k > 0 and sessions_seen:
                    # first frame received of a new session: the decoder must be able to see the reset
                    # (BOOT frame received or clock behind), and it must not look like a repeat of the last frame
                    assert last_received is not None
                    assume((f.seq, f.t_us) != (last_received.seq, last_received.t_us))
                    assume(bool(f.status & Status.BOOT) or f.t_us < last_received.t_us)
                    b.resets += 1
                b.expected.append(f)
                b.duplicates += copies - 1
                received_idx.append(i)
                last_received = f
            elif act == "corrupt_body":
                off = draw(st.integers(HEADER_SIZE, FRAME_SIZE_V1 - 1))
                mask = draw(st.integers(1, 255))
                bad = bytearray(enc)
                bad[off] ^= mask
                parts.append(bytes(bad))
                pos += len(bad)
                b.body_corrupted += 1
            elif act == "corrupt_header":
                off = draw(st.integers(0, HEADER_SIZE - 1))
                bad = bytearray(enc)
                bad[off] ^= 1 << draw(st.integers(0, 7))
                parts.append(bytes(bad))
                pos += len(bad)
            elif act == "truncate":
                cut = enc[: draw(st.integers(1, FRAME_SIZE_V1 - 1))]
                parts.append(cut)
                pos += len(cut)
            # "drop": nothing on the wire
        b.lost += sum(j - i - 1 for i, j in itertools.pairwise(received_idx))
        if received_idx:
            sessions_seen += 1
    if with_garbage:
        parts.append(draw(garbage))
    b.stream = b"".join(parts) + LINE_CONTINUES
    assume(not has_foreign_valid_candidate(b.stream, b.intact_starts))
    return b


chunk_sizes = st.lists(st.integers(1, 64), min_size=1, max_size=8)


# ----------------------------------------------------------------------------- unit tests
def test_clean_stream_in_one_chunk() -> None:
    frames = make_frames(50)
    dec, out = run([wire(frames)])
    assert out == frames
    s = dec.stats
    assert (s.frames, s.crc_errors, s.lost_frames, s.duplicates, s.resets, s.bytes_discarded) == (50, 0, 0, 0, 0, 0)
    assert dec.buffered == 0


def test_byte_by_byte_feeding() -> None:
    frames = make_frames(5)
    data = wire(frames)
    dec = StreamDecoder()
    out = []
    for i in range(len(data)):
        got = dec.feed(data[i : i + 1])
        # a frame comes out exactly when its last byte arrives
        assert len(got) == (1 if (i + 1) % FRAME_SIZE_V1 == 0 else 0)
        out += got
    assert out == frames


def test_accepts_bytes_like_inputs() -> None:
    frames = make_frames(3)
    data = wire(frames)
    dec = StreamDecoder()
    out = dec.feed(bytearray(data[:30])) + dec.feed(memoryview(data)[30:60]) + dec.feed(np.frombuffer(data[60:], np.uint8))
    assert out == frames


@pytest.mark.parametrize("bad", [None, "a5 5a", 5, 10**12, -(2**70), 3.5, float("nan"), object(), [0xA5, 0x5A],
                                 {"a": 1}])
def test_non_bytes_input_is_ignored_without_raising(bad: object) -> None:
    dec = StreamDecoder()
    assert dec.feed(bad) == []  # type: ignore[arg-type]
    assert dec.stats.bytes_received == 0
    assert dec.buffered == 0
    assert dec.feed(wire(make_frames(1))) == make_frames(1)


def test_no_reset_is_marked_before_the_first_chunk() -> None:
    assert StreamDecoder().resets_at == []


def test_empty_chunk() -> None:
    dec = StreamDecoder()
    assert dec.feed(b"") == []
    assert dec.stats.bytes_received == 0


def test_garbage_around_frames_is_discarded_and_counted() -> None:
    frames = make_frames(3)
    junk = b"\x00\x11\x22\xa5\x33"
    dec, out = run([junk + encode_frame(frames[0]) + junk + encode_frame(frames[1]) + encode_frame(frames[2]) + junk])
    assert out == frames
    assert dec.stats.bytes_discarded == 3 * len(junk)
    assert dec.stats.crc_errors == 0


def test_trailing_first_sync_byte_is_kept_for_the_next_chunk() -> None:
    f = make_frames(1)[0]
    enc = encode_frame(f)
    dec = StreamDecoder()
    assert dec.feed(b"\x00\x00\xa5") == []
    assert dec.buffered == 1
    assert dec.feed(enc[1:]) == [f]
    assert dec.stats.bytes_discarded == 2


def test_truncated_frame_then_intact_frame() -> None:
    a, b = make_frames(2)
    dec, out = run([encode_frame(a)[:15] + encode_frame(b)])
    assert out == [b]
    # the truncated candidate swallowed the start of b, failed its CRC, and the search resumed
    assert dec.stats.crc_errors == 1
    assert dec.stats.bytes_discarded == 15


def test_body_bit_flip_counts_one_crc_error_and_one_lost_frame() -> None:
    frames = make_frames(3)
    bad = bytearray(encode_frame(frames[1]))
    bad[10] ^= 0x10
    dec, out = run([encode_frame(frames[0]) + bytes(bad) + encode_frame(frames[2])])
    assert out == [frames[0], frames[2]]
    assert (dec.stats.crc_errors, dec.stats.lost_frames) == (1, 1)


def test_false_header_with_long_body_only_delays_frames() -> None:
    frames = make_frames(8)
    false_header = SYNC + bytes([7, MAX_BODY_LEN])  # unknown version, longest body: waits for 206 bytes
    dec = StreamDecoder()
    assert dec.feed(false_header + wire(frames[:3])) == []  # 85 bytes: the candidate is not complete yet
    assert dec.feed(wire(frames[3:])) == frames  # 220 bytes: candidate rejected, all frames behind it recovered
    assert dec.stats.crc_errors == 1
    assert dec.stats.lost_frames == 0


@pytest.mark.parametrize(
    "header",
    [SYNC + b"\x00\x15", SYNC + b"\x01\x00", SYNC + bytes([3, MAX_BODY_LEN + 1]), SYNC + b"\x01\x16", SYNC + b"\x01\x14",
     SYNC + b"\x02\x15", SYNC + b"\x02\x18"],
    ids=["version0", "body_len0", "body_len_too_long", "v1_long", "v1_short", "v2_with_v1_length", "v2_long"],
)
def test_impossible_headers_are_rejected_without_waiting(header: bytes) -> None:
    f = make_frames(1)[0]
    dec = StreamDecoder()
    assert dec.feed(header + encode_frame(f)) == [f]
    assert dec.stats.crc_errors == 0
    assert dec.stats.bytes_discarded == len(header)


def test_unknown_version_frame_is_skipped_whole() -> None:
    frames = make_frames(4)
    v3 = future_frame(bytes(range(30)) + SYNC + bytes(10))  # body with a sync inside: none of its bytes is a frame
    dec, out = run([encode_frame(frames[0]) + encode_frame(frames[1]) + v3 + encode_frame(frames[2]) + encode_frame(frames[3])])
    assert out == frames
    s = dec.stats
    assert (s.unsupported_version, s.crc_errors, s.lost_frames) == (1, 0, 0)
    assert s.bytes_discarded == len(v3)


def test_adc_counts_above_12_bits_are_invalid_and_lost() -> None:
    a, b, c = make_frames(3)
    b_bad = Frame(b.seq, b.t_us, ADC_MAX + 1, b.x, b.y, b.z, b.temp_cc, b.status)
    dec, out = run([wire([a, b_bad, c])])
    assert out == [a, c]
    assert (dec.stats.invalid_frames, dec.stats.crc_errors, dec.stats.lost_frames) == (1, 0, 1)


@pytest.mark.parametrize(("channel", "aux"), [(c, None) for c in ("ref", "x", "y", "z")]
                         + [(c, 100) for c in ("ref", "x", "y", "z", "aux")])
def test_every_adc_channel_is_range_checked(channel: str, aux: int | None) -> None:
    """Each 12-bit count on its own above 4095 (a CRC-valid frame from a board whose firmware packs a wider value)
    makes the frame invalid, in both versions (aux None: version 1): a check that forgot one axis would publish it."""
    a, b, c = (replace(f, aux=aux) for f in make_frames(3))
    for value in (ADC_MAX, ADC_MAX + 1, 0xFFFF):
        bad = replace(b, **{channel: value})
        dec, out = run_any([wire([a, bad, c])])
        invalid = value > ADC_MAX
        assert out == ([a, c] if invalid else [a, bad, c]), (channel, value)
        assert (dec.stats.invalid_frames, dec.stats.lost_frames) == ((1, 1) if invalid else (0, 0))


def run_any(chunks: list[bytes]) -> tuple[StreamDecoder, list[Frame]]:
    """``chunks`` fed to a new decoder (frames of any version: no version-1 byte balance)."""
    dec = StreamDecoder()
    out = [f for chunk in chunks for f in dec.feed(chunk)]
    return dec, out


def test_several_unknown_version_frames_and_garbage_stretches_are_each_counted() -> None:
    """Counters add up over several events: three CRC-valid frames of unknown versions (3, 7, 200) of different
    lengths, and garbage of 5, 1 and 11 bytes, each counted once and in full."""
    frames = make_frames(6)
    unknown = [future_frame(bytes(12), 3), future_frame(bytes(range(40)), 7), future_frame(bytes(3), 200)]
    garbage = [b"\x00\x11\x22\x33\x44", b"\x99", bytes(range(100, 111))]
    stream = (encode_frame(frames[0]) + unknown[0] + encode_frame(frames[1]) + garbage[0] + unknown[1]
              + encode_frame(frames[2]) + garbage[1] + encode_frame(frames[3]) + unknown[2] + garbage[2]
              + encode_frame(frames[4]) + encode_frame(frames[5]))
    dec, out = run([stream])
    assert out == frames
    s = dec.stats
    assert (s.unsupported_version, s.crc_errors, s.lost_frames, s.frames) == (3, 0, 0, 6)
    assert s.bytes_discarded == sum(map(len, unknown)) + sum(map(len, garbage))


def test_intact_frames_inside_a_frame_of_unknown_version_are_recovered() -> None:
    """A CRC-valid frame of a version this decoder does not know, whose body holds intact version-1 frames (a CRC that
    came out right by chance over a stretch of the stream, or a forged one): the decoder looks inside it as it does
    inside a candidate whose CRC failed, so the inner frames come out instead of being skipped with their container."""
    frames = make_frames(10)
    inner = wire(frames[1:8])  # 7 frames, 189 bytes: a body of at most 200 bytes
    container = future_frame(b"\x01" + inner + b"\x02", 9)
    dec, out = run([encode_frame(frames[0]) + container + encode_frame(frames[8]) + encode_frame(frames[9])])
    assert out == frames
    s = dec.stats
    assert (s.unsupported_version, s.lost_frames, s.crc_errors) == (1, 0, 0)
    assert s.bytes_discarded == len(container) - len(inner)


def test_a_frame_whose_board_clock_did_not_advance_is_invalid() -> None:
    """``t_us`` increases strictly from one sample to the next within a boot (docs/protocol.md section 4); a frame
    with another ``seq`` but the previous frame's ``t_us`` (a board whose clock is stuck: a firmware that never
    fills it in) has no time of its own: invalid, dropped and counted, and lost to the sequence count like any
    rejected frame. Before, every such frame was accepted and the driver stamped them all at one instant (the
    monotonic guard adding 1 ns per frame), with no diagnostic."""
    a, _, _, c = make_frames(4)
    stuck = [Frame(seq, a.t_us, 870, 1100, 1600, 1100, 2340, OK_STATUS) for seq in (a.seq + 1, a.seq + 2)]
    dec, out = run([wire([a, *stuck, c])])
    assert out == [a, c]
    s = dec.stats
    assert (s.frames, s.invalid_frames, s.lost_frames, s.duplicates, s.resets) == (2, 2, 2, 0, 0)
    assert s.bytes_discarded == 2 * FRAME_SIZE_V1 and dec.frame_bytes == 2 * FRAME_SIZE_V1
    # a BOOT frame at the same board time is a reboot, not a stuck clock; the same seq is a duplicate
    boot = Frame(0, c.t_us, 870, 1100, 1600, 1100, 2340, OK_STATUS | int(Status.BOOT))
    dec, out = run([wire([c, c, boot])])
    assert out == [c, boot] and (dec.stats.duplicates, dec.stats.resets, dec.stats.invalid_frames) == (1, 1, 0)


def _sequence_cases() -> dict[str, tuple[list[Frame], list[Frame] | None, tuple[int, int, int]]]:
    """Frames sent, frames out (None: those sent) and (lost_frames, duplicates, resets), per sequence or reset rule."""
    a, b = make_frames(2)
    wrap = make_frames(6, seq0=65533)
    assert [f.seq for f in wrap] == [65533, 65534, 65535, 0, 1, 2]
    before, after = make_frames(5, seq0=1000, t0=50_000_000), make_frames(5, seq0=0, t0=60_000_000)
    after[0] = replace(after[0], status=OK_STATUS | int(Status.BOOT))  # the clock even moves forward: BOOT alone decides
    late, early = make_frames(5, seq0=40_000, t0=900_000_000), make_frames(5, seq0=0, t0=200_000)
    first_boot = [Frame(0, 0, 1, 1, 1, 1, 0, OK_STATUS | Status.BOOT), *make_frames(3, seq0=0, t0=0)[1:]]
    boot, two = Frame(0, 100, 1, 1, 1, 1, 0, OK_STATUS | Status.BOOT), make_frames(2, seq0=7, t0=10_000_000)

    def at(seq: int, t0: int) -> Frame:
        return make_frames(1, seq0=seq, t0=t0)[0]

    return {
        "immediate_duplicate_is_dropped": ([a, a, b, b, b], [a, b], (0, 3, 0)),
        "sequence_wrap_is_not_a_loss": (wrap, None, (0, 0, 0)),
        "loss_across_wrap": (wrap[:2] + wrap[4:], None, (2, 0, 0)),  # 65535 and 0 missing
        # seq 9 after seq 10, clock forward: 65534 frames missed
        "large_gap_counts_all_missing_frames": ([at(10, 1_000_000), at(9, 5_000_000)], None, (SEQ_MODULO - 2, 0, 0)),
        "boot_flag_is_a_reset_and_no_loss_is_counted_across_it": (before + after, None, (0, 0, 1)),
        # the BOOT frame and the next one lost
        "clock_going_backwards_is_a_reset_even_without_boot_frame": (late + early[2:], None, (0, 0, 1)),
        "clock_one_microsecond_backwards_is_a_reset": ([at(5, 10_000), at(6, 9_999)], None, (0, 0, 1)),
        # 65536 frames later (or a re-sent number): a new sample
        "same_sequence_number_with_another_clock_is_not_a_duplicate": ([at(5, 10_000), at(5, 20_000)], None,
                                                                       (SEQ_MODULO - 1, 0, 0)),
        "first_frame_with_boot_flag_is_not_a_reset": (first_boot, None, (0, 0, 0)),
        "duplicate_of_boot_frame_is_a_duplicate_not_a_second_reset": ([*two, boot, boot], [*two, boot], (0, 1, 1)),
    }


@pytest.mark.parametrize("case", list(_sequence_cases()))
def test_sequence_and_reset_rules(case: str) -> None:
    """seq + 1 (mod 65536) within a boot session, a reset on a BOOT flag or a board clock going back, a repeat of
    the previous frame a duplicate: the frames out and the counts of each case."""
    sent, expected, counts = _sequence_cases()[case]
    dec, out = run([wire(sent)])
    assert out == (sent if expected is None else expected)
    assert (dec.stats.lost_frames, dec.stats.duplicates, dec.stats.resets) == counts


def test_endless_garbage_keeps_memory_bounded() -> None:
    rng = np.random.default_rng(1)
    dec = StreamDecoder()
    adversarial = (SYNC + bytes([9, MAX_BODY_LEN])) * 64  # false headers that each announce the longest body
    for i in range(300):
        chunk = adversarial if i % 3 == 0 else rng.integers(0, 256, 4096, dtype=np.uint8).tobytes()
        dec.feed(chunk)
        assert dec.buffered < MAX_CANDIDATE
    check_byte_balance(dec)
    # still decodes after all that
    tail = make_frames(3, seq0=5)
    assert dec.feed(LINE_CONTINUES + wire(tail))[-3:] == tail


# ----------------------------------------------------------------------------- properties
@PROPERTY
@given(b=built_streams(ACTIONS_EXACT, with_garbage=False), sizes=chunk_sizes)
def test_property_body_corruption_counts_are_exact(b: Built, sizes: list[int]) -> None:
    """Only body/CRC bytes corrupted, no garbage: crc_errors == corrupted frames, exactly."""
    assume(b.stream.count(SYNC) == len(b.intact_starts) + b.body_corrupted)  # no sync inside any frame body
    dec, out = run(split(b.stream, sizes))
    assert out == b.expected
    s = dec.stats
    assert s.crc_errors == b.body_corrupted
    assert s.frames == len(b.expected)
    assert s.duplicates == b.duplicates
    assert s.lost_frames == b.lost
    assert s.resets == 0
    assert s.invalid_frames == s.unsupported_version == 0


@PROPERTY
@given(b=built_streams(ACTIONS_ALL, with_garbage=True), sizes=chunk_sizes)
def test_property_garbage_truncation_bit_flips(b: Built, sizes: list[int]) -> None:
    """Interleaved garbage, truncated and bit-flipped frames, random chunking: every intact frame, in order."""
    dec, out = run(split(b.stream, sizes))
    assert out == b.expected
    s = dec.stats
    assert s.frames == len(b.expected)
    assert s.duplicates == b.duplicates
    assert s.lost_frames == b.lost
    assert s.resets == 0
    # every body-corrupted frame is seen as a CRC error; nothing but sync positions can be one
    assert b.body_corrupted <= s.crc_errors <= b.stream.count(SYNC) - len(b.intact_starts)


@settings(PROPERTY, max_examples=100)
@given(b=built_streams(ACTIONS_ALL, with_garbage=True, n_sessions=3), sizes=chunk_sizes)
def test_property_resets_across_boot_sessions(b: Built, sizes: list[int]) -> None:
    """Three boot sessions (BOOT flag on the first frame, clock restarting near 0): resets and losses exact."""
    dec, out = run(split(b.stream, sizes))
    assert out == b.expected
    s = dec.stats
    assert s.resets == b.resets
    assert s.lost_frames == b.lost
    assert s.duplicates == b.duplicates


@PROPERTY
@given(b=built_streams(ACTIONS_ALL, with_garbage=True), sizes=chunk_sizes)
def test_property_chunking_does_not_change_anything(b: Built, sizes: list[int]) -> None:
    whole, out_whole = run([b.stream])
    chunked, out_chunked = run(split(b.stream, sizes))
    assert out_chunked == out_whole
    assert chunked.stats == whole.stats
    assert chunked.buffered == whole.buffered


def catch_up_frames(n: int, late_k: int | tuple[int, ...], late_us: int, dt: int = 1_000, read_us: int = 40,
                    t0: int = 1_000_000, seq0: int = 0) -> list[Frame]:
    """``n`` frames of a board whose read ``late_k`` (or each of them) is taken ``late_us`` late, then the reads already
    due back to back,
    ``read_us`` apart, with ADC_OVERRUN on each read taken at or after the next read's time: the firmware's catch-up
    (firmware/core/fbg_scheduler.c fbg_sched_take, firmware/host/fbg_board_host.c). Nothing is skipped or lost."""
    frames = make_frames(n, seq0=seq0, t0=t0, dt=dt)
    late_ks = {late_k} if isinstance(late_k, int) else set(late_k)
    read = -read_us
    for k, f in enumerate(frames):
        due = t0 + k * dt + (late_us if k in late_ks else 0)
        read = max(due, read + read_us)
        late = read >= t0 + (k + 1) * dt
        frames[k] = replace(f, t_us=read, status=f.status | (int(Status.ADC_OVERRUN) if late else 0))
    return frames


@pytest.mark.parametrize("catch_up_before", [False, True])
@pytest.mark.parametrize("gap", [1_000, 65_535, 65_536, 70_000, 100_000, 200_000])
def test_an_outage_of_a_sequence_period_or_more_is_counted_in_full(gap: int, catch_up_before: bool) -> None:
    """A link outage of ``gap`` samples at 1 kHz (the board keeps sampling and counting seq; docs/firmware.md: the
    missing samples are counted as lost_frames after a reconnect). The u16 seq alone counted 65536 lost samples as 0 and
    70000 as 4464; the 64-bit t_us step over the nominal sample interval tells how many times seq wrapped. Also right
    after a late read's catch-up (4 reads 40 us apart just before the outage): the nominal interval must not be the
    40 us catch-up step, or a 1000-sample outage would count 65536 x 4 + 999."""
    frames = catch_up_frames(50 + gap + 5, late_k=45 if catch_up_before else -1, late_us=3_500)
    if catch_up_before:
        assert [f.t_us - 1_000_000 for f in frames[44:50]] == [44_000, 48_500, 48_540, 48_580, 48_620, 49_000]
    kept = frames[:50] + frames[50 + gap:]
    dec, out = run([wire(kept)])
    assert out == kept
    assert (dec.stats.lost_frames, dec.stats.resets, dec.stats.duplicates) == (gap, 0, 0)


def test_two_catch_ups_just_before_an_outage_leave_the_nominal_interval() -> None:
    """Two late reads 6 samples apart, each followed by its catch-up, and an outage of 100 000 samples just after: every
    step that starts or ends at an ADC_OVERRUN frame (into a late read, out of its catch-up) is left out of the
    nominal interval, so the window holds one irregular step per late read and the outage is counted in full. A
    decoder that left out only the steps between two ADC_OVERRUN frames would take 4500 us into a late read and 40 us
    out of its catch-up as sample intervals (4 of the last 7 steps irregular), take 380 us for the interval and count
    231 072 lost samples (2 x 65536 too many)."""
    gap = 100_000
    frames = catch_up_frames(56 + gap + 5, late_k=(45, 51), late_us=3_500)
    assert [f.t_us - 1_000_000 for f in frames[50:56]] == [50_000, 54_500, 54_540, 54_580, 54_620, 55_000]
    assert sum(bool(f.status & Status.ADC_OVERRUN) for f in frames[:56]) == 6
    kept = frames[:56] + frames[56 + gap:]
    dec, out = run([wire(kept)])
    assert out == kept
    assert (dec.stats.lost_frames, dec.stats.resets) == (gap, 0)

def test_an_outage_after_the_first_two_frames_is_counted_in_full() -> None:
    """The link drops for 70 000 samples right after the first two frames of a session: their one step is the nominal
    interval already (the first frame is on time), so the outage is counted in full, not as 70 000 mod 65536."""
    frames = make_frames(2 + 70_000 + 3, dt=1_000)
    kept = frames[:2] + frames[2 + 70_000:]
    dec, out = run([wire(kept)])
    assert out == kept
    assert dec.stats.lost_frames == 70_000

def test_the_sample_interval_forgets_its_oldest_step_first() -> None:
    """The ring of the last INTERVAL_WINDOW steps is first in, first out: after 7 steps (five of 1000 us, two of
    3000 us) and three of 2000 us, the window holds 2000 x3, 1000 x2, 3000 x2 (median 2000); a ring that overwrote
    its newest steps first would hold 1000 x4 and read 1000."""
    from fbg_accel_driver.stream_decoder import INTERVAL_WINDOW, SampleInterval

    assert INTERVAL_WINDOW == 7
    interval = SampleInterval()
    for step in (1000, 1000, 1000, 1000, 1000, 3000, 3000):
        interval.add(step, 0)
    assert interval.us == 1000
    for _ in range(3):
        interval.add(2000, 0)
    assert interval.us == 2000


def test_a_header_that_cannot_start_a_frame_is_dropped_once_complete_and_an_empty_body_is_no_candidate() -> None:
    """A complete 4-byte header that cannot start a frame (version 0) is discarded as soon as it has arrived, not
    held waiting for more bytes (the diagnostics' discarded-byte count is up to date); a header announcing an empty
    body is no candidate, even of an unknown version with a valid CRC (counted neither as an unsupported version nor
    as a CRC error), while a one-byte body of an unknown version is one: its wrong CRC is counted."""
    dec = StreamDecoder()
    assert dec.feed(SYNC + bytes([0, 10])) == []
    assert (dec.stats.bytes_discarded, dec.buffered) == (HEADER_SIZE, 0)
    empty = bytes([9, 0])
    dec = StreamDecoder()
    assert dec.feed(SYNC + empty + crc16(empty).to_bytes(CRC_SIZE, "little")) == []
    assert (dec.stats.unsupported_version, dec.stats.crc_errors) == (0, 0)
    one = bytes([9, 1, 0x33])
    dec = StreamDecoder()
    assert dec.feed(SYNC + one + (crc16(one) ^ 1).to_bytes(CRC_SIZE, "little")) == []
    assert (dec.stats.unsupported_version, dec.stats.crc_errors) == (0, 1)

def test_the_sample_interval_is_the_upper_median_of_the_last_window_of_on_time_steps() -> None:
    """Against the definition, step by step over 400 random steps (the nominal 1000 us, its neighbours, a catch-up's
    40 us, an outage's long step; one in eight at an ADC_OVERRUN frame, ignored): after each step :attr:`us` is the
    upper median of the last INTERVAL_WINDOW steps taken. A window one step too long, a ring overwritten out of order
    or a lower quantile read as the median each differ within the first few dozen steps."""
    from fbg_accel_driver.stream_decoder import INTERVAL_WINDOW, SampleInterval

    rng = np.random.default_rng(7)
    interval, taken = SampleInterval(), []
    for step, overrun in zip(rng.choice([40, 990, 1000, 1010, 2000, 50_000], 400).tolist(),
                             (rng.random(400) < 0.125).tolist(), strict=True):
        interval.add(step, int(overrun))
        if not overrun:
            taken.append(step)
        window = sorted(taken[-INTERVAL_WINDOW:])
        assert interval.us == (window[len(window) // 2] if window else 0), (taken[-INTERVAL_WINDOW:], interval.us)
