"""Tests of the board frame formats v1 and v2 (fbg_accel_driver.frame_codec), checked against docs/protocol.md.

The expected bytes are built here independently of ``struct`` (``int.to_bytes``) and the CRC is
checked against a bit-by-bit reference implementation and the published CRC-16/CCITT-FALSE check
value, so a change of layout, byte order or CRC variant in the codec fails these tests.
"""

from __future__ import annotations

import math
import struct

import pytest
from frame_strategies import frames, frames_v2
from hypothesis import given, settings
from hypothesis import strategies as st

from fbg_accel_driver.frame_codec import (
    ADC_MAX,
    BODY_LEN_V1,
    BODY_LEN_V2,
    CRC_SIZE,
    FRAME_SIZE_V1,
    FRAME_SIZE_V2,
    HEADER_SIZE,
    PROTOCOL_VERSION,
    PROTOCOL_VERSION_V2,
    SEQ_MODULO,
    SYNC,
    Frame,
    Status,
    crc16,
    decode_body_v1,
    decode_body_v2,
    encode_frame,
    frame_size,
    link_frame_rate_limit,
)
from fbg_accel_driver.stream_decoder import StreamDecoder

# Golden frame from docs/protocol.md ("Test vector").
GOLDEN_FRAME = Frame(seq=0x1234, t_us=0x0102030405060708, ref=4095, x=2048, y=1, z=0, temp_cc=-1234, status=0x03)
GOLDEN_HEX = "a5 5a 01 15 34 12 08 07 06 05 04 03 02 01 ff 0f 00 08 01 00 00 00 2e fb 03 17 ae"
# Version-2 golden frame from docs/protocol.md: the same fields + aux = 0x0ABC (2748 counts).
GOLDEN_FRAME_V2 = Frame(seq=0x1234, t_us=0x0102030405060708, ref=4095, x=2048, y=1, z=0, temp_cc=-1234, status=0x03,
                        aux=0x0ABC)
GOLDEN_HEX_V2 = "a5 5a 02 17 34 12 08 07 06 05 04 03 02 01 ff 0f 00 08 01 00 00 00 2e fb 03 bc 0a 57 06"


def crc16_bitwise(data: bytes) -> int:
    """Reference CRC-16/CCITT-FALSE, one bit at a time: poly 0x1021, init 0xFFFF, MSB first, no xor-out."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def manual_encode(f: Frame) -> bytes:
    """The v1 layout of docs/protocol.md written out field by field (little-endian)."""
    body = (
        (f.seq % SEQ_MODULO).to_bytes(2, "little")
        + f.t_us.to_bytes(8, "little")
        + f.ref.to_bytes(2, "little")
        + f.x.to_bytes(2, "little")
        + f.y.to_bytes(2, "little")
        + f.z.to_bytes(2, "little")
        + f.temp_cc.to_bytes(2, "little", signed=True)
        + f.status.to_bytes(1, "little")
    )
    if f.aux is None:
        covered = bytes([1, 21]) + body
    else:  # version 2: aux appended after status, body_len 23
        covered = bytes([2, 23]) + body + f.aux.to_bytes(2, "little")
    return b"\xa5\x5a" + covered + crc16_bitwise(covered).to_bytes(2, "little")




def test_sizes_and_constants() -> None:
    assert SYNC == b"\xa5\x5a"
    assert PROTOCOL_VERSION == 1
    assert (HEADER_SIZE, BODY_LEN_V1, CRC_SIZE, FRAME_SIZE_V1) == (4, 21, 2, 27)
    assert ADC_MAX == 2**12 - 1
    assert SEQ_MODULO == 65536


def test_status_bits_match_protocol_doc() -> None:
    assert (Status.TEMP_VALID, Status.TEMP_PRESENT, Status.ADC_OVERRUN, Status.BOOT) == (0x01, 0x02, 0x04, 0x08)


def test_crc_check_value() -> None:
    # The catalogue check value of CRC-16/CCITT-FALSE over ASCII "123456789".
    assert crc16(b"123456789") == 0x29B1
    assert crc16_bitwise(b"123456789") == 0x29B1
    assert crc16(b"") == 0xFFFF


@given(st.binary(max_size=300))
@settings(max_examples=200, deadline=None)
def test_crc_matches_bitwise_reference(data: bytes) -> None:
    assert crc16(data) == crc16_bitwise(data)
    assert crc16(bytearray(data)) == crc16(memoryview(data)) == crc16(data)


def test_golden_vector() -> None:
    wire = encode_frame(GOLDEN_FRAME)
    assert wire == bytes.fromhex(GOLDEN_HEX)
    assert crc16(wire[2:25]) == 0xAE17
    assert wire[25:27] == b"\x17\xae"  # CRC little-endian on the wire


@given(frames)
@settings(max_examples=200, deadline=None)
def test_encode_matches_documented_layout(f: Frame) -> None:
    wire = encode_frame(f)
    assert len(wire) == FRAME_SIZE_V1
    assert wire == manual_encode(f)


@given(frames)
@settings(max_examples=200, deadline=None)
def test_body_round_trip(f: Frame) -> None:
    wire = encode_frame(f)
    assert decode_body_v1(wire, HEADER_SIZE) == f
    # Offset is honoured when the frame sits inside a larger buffer.
    assert decode_body_v1(b"junk" + wire, 4 + HEADER_SIZE) == f


def test_sequence_wraps_modulo_65536_on_encode() -> None:
    f = Frame(seq=SEQ_MODULO + 5, t_us=1, ref=1, x=2, y=3, z=4, temp_cc=0, status=0)
    assert decode_body_v1(encode_frame(f), HEADER_SIZE).seq == 5


@pytest.mark.parametrize(
    "field,value",
    [("t_us", -1), ("t_us", 2**64), ("temp_cc", 2**15), ("temp_cc", -(2**15) - 1), ("status", 256), ("ref", 2**16)],
)
def test_encoder_refuses_values_that_do_not_fit(field: str, value: int) -> None:
    kwargs = {"seq": 1, "t_us": 1, "ref": 1, "x": 1, "y": 1, "z": 1, "temp_cc": 0, "status": 0, field: value}
    with pytest.raises(struct.error):
        encode_frame(Frame(**kwargs))


def test_temperature_properties() -> None:
    f = Frame(seq=0, t_us=0, ref=0, x=0, y=0, z=0, temp_cc=-1234, status=int(Status.TEMP_PRESENT))
    assert f.temperature_c == pytest.approx(-12.34)
    assert not f.temp_valid
    g = Frame(seq=0, t_us=0, ref=0, x=0, y=0, z=0, temp_cc=2501, status=int(Status.TEMP_VALID | Status.TEMP_PRESENT))
    assert g.temperature_c == pytest.approx(25.01)
    assert g.temp_valid


def test_link_frame_rate_limit() -> None:
    # 8N1: 10 bit times per byte, 27 bytes per frame -> 270 bit times per frame.
    assert link_frame_rate_limit(921600) == pytest.approx(921600 / 270)
    assert link_frame_rate_limit(115200) == pytest.approx(115200 / 270)
    assert link_frame_rate_limit(921600, frame_size=30, bits_per_byte=11) == pytest.approx(921600 / 330)


# ----------------------------------------------------------------------------- version 2 (aux channel)
def test_v2_sizes_and_constants() -> None:
    assert (PROTOCOL_VERSION_V2, BODY_LEN_V2, FRAME_SIZE_V2) == (2, 23, 29)
    assert (frame_size(1), frame_size(2)) == (27, 29)
    # 8N1: 290 bit times per version-2 frame.
    assert link_frame_rate_limit(921600, frame_size=FRAME_SIZE_V2) == pytest.approx(3177.93, abs=0.01)


def test_v2_golden_vector() -> None:
    wire = encode_frame(GOLDEN_FRAME_V2)
    assert wire == bytes.fromhex(GOLDEN_HEX_V2)
    assert crc16(wire[2:27]) == 0x0657  # CRC covers version .. aux
    assert wire[4:25] == bytes.fromhex(GOLDEN_HEX)[4:25]  # the version-1 fields in place
    assert StreamDecoder().feed(wire) == [GOLDEN_FRAME_V2]


@given(frames_v2)
@settings(max_examples=200, deadline=None)
def test_v2_round_trip_and_layout(f: Frame) -> None:
    wire = encode_frame(f)
    assert len(wire) == FRAME_SIZE_V2 and wire[2:4] == bytes([2, 23])
    assert wire == manual_encode(f)
    assert decode_body_v2(wire, HEADER_SIZE) == f
    dec = StreamDecoder()
    assert dec.feed(wire) == [f]
    assert dec.stats.frames == 1 and dec.frame_bytes == FRAME_SIZE_V2


def test_v1_frames_still_decode_without_aux() -> None:
    dec = StreamDecoder()
    out = dec.feed(bytes.fromhex(GOLDEN_HEX))
    assert out == [GOLDEN_FRAME] and out[0].aux is None and out[0].version == 1
    assert math.isnan(out[0].aux_counts)
    assert decode_body_v1(encode_frame(GOLDEN_FRAME), HEADER_SIZE) == GOLDEN_FRAME


def test_encoder_version_choice() -> None:
    assert encode_frame(GOLDEN_FRAME, version=1) == bytes.fromhex(GOLDEN_HEX)
    assert encode_frame(GOLDEN_FRAME_V2, version=2) == bytes.fromhex(GOLDEN_HEX_V2)
    with pytest.raises(ValueError, match="no aux"):
        encode_frame(GOLDEN_FRAME_V2, version=1)
    with pytest.raises(ValueError, match="needs aux"):
        encode_frame(GOLDEN_FRAME, version=2)
    with pytest.raises(ValueError, match="unknown"):
        encode_frame(GOLDEN_FRAME, version=3)
    with pytest.raises(struct.error):
        encode_frame(Frame(1, 1, 1, 1, 1, 1, 0, 0, aux=2**16))


@given(st.lists(st.one_of(frames, frames_v2), min_size=1, max_size=30), st.integers(1, 40))
@settings(max_examples=100, deadline=None)
def test_mixed_v1_v2_stream(fs: list[Frame], chunk: int) -> None:
    # Consecutive samples (distinct seq and t_us) so none is a duplicate or a reset.
    fs = [Frame(i, 1000 + i, f.ref, f.x, f.y, f.z, f.temp_cc, f.status & ~int(Status.BOOT), f.aux) for i, f in enumerate(fs)]
    data = b"".join(encode_frame(f) for f in fs)
    dec = StreamDecoder()
    out: list[Frame] = []
    for i in range(0, len(data), chunk):
        out += dec.feed(data[i:i + chunk])
    assert out == fs
    s = dec.stats
    assert (s.crc_errors, s.lost_frames, s.unsupported_version, s.bytes_discarded) == (0, 0, 0, 0)
    assert s.bytes_received == dec.frame_bytes == sum(frame_size(f.version) for f in fs)


@pytest.mark.parametrize("byte", [25, 26])
def test_v2_corrupted_aux_byte_fails_crc(byte: int) -> None:
    a = Frame(1, 1000, 870, 1130, 1650, 1130, 2340, 3, aux=2000)
    b = Frame(2, 2000, 870, 1130, 1650, 1130, 2340, 3, aux=2001)
    c = Frame(3, 3000, 870, 1130, 1650, 1130, 2340, 3, aux=2002)
    bad = bytearray(encode_frame(b))
    bad[byte] ^= 0x10
    dec = StreamDecoder()
    assert dec.feed(encode_frame(a) + bytes(bad) + encode_frame(c)) == [a, c]
    s = dec.stats
    assert (s.crc_errors, s.lost_frames, s.bytes_discarded) == (1, 1, FRAME_SIZE_V2)


def test_v2_aux_above_12_bits_is_invalid() -> None:
    a = Frame(1, 1000, 870, 1130, 1650, 1130, 2340, 3, aux=2000)
    b = Frame(2, 2000, 870, 1130, 1650, 1130, 2340, 3, aux=ADC_MAX + 1)
    c = Frame(3, 3000, 870, 1130, 1650, 1130, 2340, 3, aux=0)
    dec = StreamDecoder()
    assert dec.feed(encode_frame(a) + encode_frame(b) + encode_frame(c)) == [a, c]
    assert (dec.stats.invalid_frames, dec.stats.lost_frames) == (1, 1)


def test_adc_rails_and_clipped_readings_at_their_edges() -> None:
    """A channel sits at a rail at exactly 0 or from ADC_MAX up (not at 1 or ADC_MAX - 1); a reading is clipped when the
    reference is at least LOW_REFERENCE_COUNTS (a dark reference is another matter) and the reference is at its top or
    any one axis at a rail, each on its own."""
    import numpy as np

    from fbg_accel_driver.frame_codec import at_adc_rail, clipped_reading
    from fbg_accel_driver.sensor_constants import LOW_REFERENCE_COUNTS

    counts = np.array([0, 1, ADC_MAX - 1, ADC_MAX, ADC_MAX + 1])
    assert at_adc_rail(counts).tolist() == [True, False, False, True, True]
    mid, lo = 2000, LOW_REFERENCE_COUNTS
    cases = {  # (ref, x, y, z): clipped
        (lo, 0, mid, mid): True, (lo - 1, 0, mid, mid): False, (mid, mid, mid, mid): False,
        (ADC_MAX, mid, mid, mid): True, (ADC_MAX - 1, mid, mid, mid): False,
        (mid, ADC_MAX, mid, mid): True, (mid, mid, 0, mid): True, (mid, mid, mid, ADC_MAX): True,
    }
    ref, x, y, z = (np.array(v) for v in zip(*cases, strict=True))
    assert clipped_reading(ref, x, y, z).tolist() == list(cases.values())


def test_a_frame_whose_aux_does_not_fit_its_version_is_refused_with_the_reason() -> None:
    with_aux = Frame(1, 10, 900, 1000, 1500, 1100, 2300, 0, aux=5)
    without = Frame(1, 10, 900, 1000, 1500, 1100, 2300, 0)
    with pytest.raises(ValueError, match=r"^a version-1 frame has no aux field: encode with version=2 or clear aux$"):
        encode_frame(with_aux, version=PROTOCOL_VERSION)
    with pytest.raises(ValueError, match=r"^a version-2 frame needs aux counts$"):
        encode_frame(without, version=PROTOCOL_VERSION_V2)
