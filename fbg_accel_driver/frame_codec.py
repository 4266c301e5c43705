"""Binary frame format of the acquisition board, protocol versions 1 and 2 (see docs/protocol.md).

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

Version 2 (29 bytes) is version 1 with one field appended after ``status``::

    25     2    aux          u16, 12-bit ADC counts of the auxiliary channel (reference transducer of a
                             dynamic calibration, sampled by the same board on the same clock)
    27     2    crc          CRC-16/CCITT-FALSE over bytes 2..26 (version..aux)

``body_len`` lets a version append fields: a decoder skips frames of a version it does not know,
using ``body_len``, instead of losing sync. The CRC always covers ``version`` .. end of body and
is always the last two bytes.
"""

from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass
from enum import IntFlag
from typing import Any

from .sensor_constants import LOW_REFERENCE_COUNTS

SYNC = b"\xa5\x5a"
PROTOCOL_VERSION = 1  # version of the boards in the field, and what ``encode_frame`` writes for a frame without aux
PROTOCOL_VERSION_V2 = 2  # version 1 + ``aux`` (auxiliary ADC channel: reference transducer)
_HEADER = struct.Struct("<2sBB")  # sync, version, body_len
_BODY_V1 = struct.Struct("<HQHHHHhB")  # seq, t_us, ref, x, y, z, temp_cc, status
_BODY_V2 = struct.Struct("<HQHHHHhBH")  # version-1 body + aux
_CRC = struct.Struct("<H")
HEADER_SIZE = _HEADER.size  # 4
BODY_LEN_V1 = _BODY_V1.size  # 21
BODY_LEN_V2 = _BODY_V2.size  # 23
CRC_SIZE = _CRC.size  # 2
FRAME_SIZE_V1 = HEADER_SIZE + BODY_LEN_V1 + CRC_SIZE  # 27
FRAME_SIZE_V2 = HEADER_SIZE + BODY_LEN_V2 + CRC_SIZE  # 29
# Versions this codec knows, with their (frozen) body length.
BODY_LEN_BY_VERSION = {PROTOCOL_VERSION: BODY_LEN_V1, PROTOCOL_VERSION_V2: BODY_LEN_V2}
ADC_MAX = 4095  # 12-bit full scale
SEQ_MODULO = 1 << 16


def at_adc_rail(counts: Any) -> Any:
    """True where a channel reads a rail of the 12-bit ADC, 0 or ``ADC_MAX`` counts (a number or an array): the
    reading is clipped, a bound of the signal and not a measurement of it. (The reference at 0 is no light, not a
    clipped signal: for it only ``>= ADC_MAX`` counts.)"""
    return (counts == 0) | (counts >= ADC_MAX)


def clipped_reading(ref: Any, x: Any, y: Any, z: Any) -> Any:
    """True where a sample (counts: numbers or arrays) has a clipped channel: an axis at a rail
    (:func:`at_adc_rail`) or the reference at ``ADC_MAX``, with light on the reference. A sample without light
    (reference below ``LOW_REFERENCE_COUNTS``: a source dropout, every channel at its dark level, an axis maybe at 0)
    is not one: it is no data at all (the driver publishes nothing for it, the offline tools leave it out)."""
    return (ref >= LOW_REFERENCE_COUNTS) & ((ref >= ADC_MAX) | at_adc_rail(x) | at_adc_rail(y) | at_adc_rail(z))


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
    ``temp_cc`` is the AHT10 temperature in hundredths of a degree Celsius. ``aux`` holds the
    12-bit counts of the auxiliary channel of a version-2 frame (the reference transducer of a
    dynamic calibration, same board clock) and is ``None`` for a version-1 frame.
    """

    seq: int
    t_us: int
    ref: int
    x: int
    y: int
    z: int
    temp_cc: int
    status: int
    aux: int | None = None

    @property
    def version(self) -> int:
        """Protocol version this frame is encoded with: 2 if it carries ``aux``, else 1."""
        return PROTOCOL_VERSION if self.aux is None else PROTOCOL_VERSION_V2

    @property
    def aux_counts(self) -> float:
        """``aux`` as a float, NaN for a version-1 frame (convenient for numeric arrays)."""
        return math.nan if self.aux is None else float(self.aux)

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


def encode_frame(frame: Frame, version: int | None = None) -> bytes:
    """Serialise one frame exactly as the board firmware does.

    ``version`` None: version 2 if ``frame.aux`` is set, else version 1. Asking for version 1 with
    ``aux`` set (the value would be lost) or version 2 without it raises ``ValueError``.
    """
    if version is None:
        version = frame.version
    fields = (frame.seq % SEQ_MODULO, frame.t_us, frame.ref, frame.x, frame.y, frame.z, frame.temp_cc, frame.status)
    if version == PROTOCOL_VERSION:
        if frame.aux is not None:
            raise ValueError("a version-1 frame has no aux field: encode with version=2 or clear aux")
        body = _BODY_V1.pack(*fields)
    elif version == PROTOCOL_VERSION_V2:
        if frame.aux is None:
            raise ValueError("a version-2 frame needs aux counts")
        body = _BODY_V2.pack(*fields, frame.aux)
    else:
        raise ValueError(f"protocol version {version} unknown (this codec writes 1 and 2)")
    head = _HEADER.pack(SYNC, version, len(body))
    crc = crc16(head[2:] + body)
    return head + body + _CRC.pack(crc)


def decode_body_v1(buf: bytes | bytearray | memoryview, offset: int) -> Frame:
    """Unpack a version-1 body starting at ``offset`` (caller has checked length and CRC)."""
    return Frame(*_BODY_V1.unpack_from(buf, offset))


def decode_body_v2(buf: bytes | bytearray | memoryview, offset: int) -> Frame:
    """Unpack a version-2 body (version-1 fields + ``aux``) starting at ``offset`` (length and CRC checked)."""
    return Frame(*_BODY_V2.unpack_from(buf, offset))


def frame_size(version: int) -> int:
    """Bytes on the wire of one frame of a known ``version`` (27 for 1, 29 for 2)."""
    return HEADER_SIZE + BODY_LEN_BY_VERSION[version] + CRC_SIZE


def link_frame_rate_limit(baud: int, frame_size: int = FRAME_SIZE_V1, bits_per_byte: int = 10) -> float:
    """Highest frame rate a UART link can carry, in frames/s (8N1: 10 bits per byte).

    ``frame_size`` 27 for version 1 (3413.3 frames/s at 921600 baud), ``FRAME_SIZE_V2`` = 29 for
    version 2 (3177.9 frames/s at 921600 baud).
    """
    return baud / (bits_per_byte * frame_size)
