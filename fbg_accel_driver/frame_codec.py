"""Binary frame format of the acquisition board, protocol version 1 (see docs/protocol.md).

Pure Python, no ROS. All multi-byte fields are little-endian (the ESP32's native order).

Layout of a version-1 frame (27 bytes)::

    offset size field
    0      2    sync         0xA5 0x5A
    2      1    version      1
    3      1    body_len     21 (bytes from ``seq`` to ``status`` inclusive)
    4      2    seq          u16, +1 per frame, wraps 65535 -> 0
    6      8    t_us         u64, board clock in microseconds since boot
    14     2    ref          u16, 12-bit ADC counts of the source-reference photodetector
    16     2    x            u16, 12-bit ADC counts, x channel
    18     2    y            u16, 12-bit ADC counts, y channel
    20     2    z            u16, 12-bit ADC counts, z channel
    22     2    temp_cc      i16, AHT10 temperature in 0.01 degC
    24     1    status       bit flags, see ``Status``
    25     2    crc          CRC-16/CCITT-FALSE over bytes 2..24 (version..status)

``body_len`` lets a future version append fields: a decoder skips frames of a version it does
not know, using ``body_len``, instead of losing sync.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass
from enum import IntFlag

SYNC = b"\xa5\x5a"
PROTOCOL_VERSION = 1
_HEADER = struct.Struct("<2sBB")  # sync, version, body_len
_BODY_V1 = struct.Struct("<HQHHHHhB")  # seq, t_us, ref, x, y, z, temp_cc, status
_CRC = struct.Struct("<H")
HEADER_SIZE = _HEADER.size  # 4
BODY_LEN_V1 = _BODY_V1.size  # 21
CRC_SIZE = _CRC.size  # 2
FRAME_SIZE_V1 = HEADER_SIZE + BODY_LEN_V1 + CRC_SIZE  # 27
ADC_MAX = 4095  # 12-bit full scale
SEQ_MODULO = 1 << 16


class Status(IntFlag):
    """Status bits set by the board firmware."""

    TEMP_VALID = 0x01  # AHT10 reading is fresh and its CRC/busy bit were fine
    TEMP_PRESENT = 0x02  # AHT10 answered on I2C at boot
    ADC_OVERRUN = 0x04  # the sampler missed its deadline; this sample is late
    BOOT = 0x08  # first frame after a (re)boot


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded board sample.

    ``t_us`` is the board clock (microseconds since boot), counts are raw 12-bit ADC values,
    ``temp_cc`` is the AHT10 temperature in hundredths of a degree Celsius.
    """

    seq: int
    t_us: int
    ref: int
    x: int
    y: int
    z: int
    temp_cc: int
    status: int

    @property
    def temperature_c(self) -> float:
        """AHT10 temperature in degC (meaningful only when ``temp_valid``)."""
        return self.temp_cc / 100.0

    @property
    def temp_valid(self) -> bool:
        return bool(self.status & Status.TEMP_VALID)


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no xor-out)."""
    return binascii.crc_hqx(data, 0xFFFF)


def encode_frame(frame: Frame) -> bytes:
    """Serialise one frame exactly as the board firmware does (version 1)."""
    body = _BODY_V1.pack(
        frame.seq % SEQ_MODULO,
        frame.t_us,
        frame.ref,
        frame.x,
        frame.y,
        frame.z,
        frame.temp_cc,
        frame.status,
    )
    head = _HEADER.pack(SYNC, PROTOCOL_VERSION, BODY_LEN_V1)
    crc = crc16(head[2:] + body)
    return head + body + _CRC.pack(crc)


def decode_body_v1(buf: bytes | bytearray | memoryview, offset: int) -> Frame:
    """Unpack a version-1 body starting at ``offset`` (caller has checked length and CRC)."""
    return Frame(*_BODY_V1.unpack_from(buf, offset))


def link_frame_rate_limit(baud: int, frame_size: int = FRAME_SIZE_V1, bits_per_byte: int = 10) -> float:
    """Highest frame rate a UART link can carry, in frames/s (8N1: 10 bits per byte)."""
    return baud / (bits_per_byte * frame_size)
