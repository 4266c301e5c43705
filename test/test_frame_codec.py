"""Tests of the board frame format v1 (fbg_accel_driver.frame_codec), checked against docs/protocol.md.

The expected bytes are built here independently of ``struct`` (``int.to_bytes``) and the CRC is
checked against a bit-by-bit reference implementation and the published CRC-16/CCITT-FALSE check
value, so a change of layout, byte order or CRC variant in the codec fails these tests.
"""

from __future__ import annotations

import struct

import pytest
from frame_strategies import frames
from hypothesis import given, settings
from hypothesis import strategies as st

from fbg_accel_driver.frame_codec import (
    ADC_MAX,
    BODY_LEN_V1,
    CRC_SIZE,
    FRAME_SIZE_V1,
    HEADER_SIZE,
    PROTOCOL_VERSION,
    SEQ_MODULO,
    SYNC,
    Frame,
    Status,
    crc16,
    decode_body_v1,
    encode_frame,
    link_frame_rate_limit,
)

# Golden frame from docs/protocol.md ("Test vector").
GOLDEN_FRAME = Frame(seq=0x1234, t_us=0x0102030405060708, ref=4095, x=2048, y=1, z=0, temp_cc=-1234, status=0x03)
GOLDEN_HEX = "a5 5a 01 15 34 12 08 07 06 05 04 03 02 01 ff 0f 00 08 01 00 00 00 2e fb 03 17 ae"


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
    covered = bytes([1, 21]) + body
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
