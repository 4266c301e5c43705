"""CDR encoding (XCDR1, little endian: the ROS 2 default) of the four message types a calibration
recording holds, written by :class:`mcap_writer.RecordingWriter`.

Pure Python. The layouts are those of the ROS 2 middleware (and of the ``mcap_ros2`` encoder,
byte for byte: ``test_mcap_io`` compares each with messages written through ``mcap_ros2``'s public
writer): a 4-byte encapsulation header, then the fields in order, each primitive aligned to its own
size counted from the end of that header; a string is a uint32 length (with its NUL) and the bytes
with the NUL; a sequence is a uint32 count and its elements.

The reader reads the event messages back in exactly these layouts (:class:`FixedStampedCodec`,
:func:`read_diagnostic_status`), bytes of any other layout being left to the ``mcap_ros2`` decoder.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable

ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR_LE


class CdrWriter:
    """One message body under construction (alignment counted from the start of the body)."""

    def __init__(self) -> None:
        self.body = bytearray()

    def align(self, n: int) -> None:
        self.body += b"\x00" * (-len(self.body) % n)

    def put(self, fmt: str, *values: float | int) -> None:
        """Primitives of one struct format character each (``b``/``B``, ``i``/``I``, ``d``), aligned to it."""
        self.align(struct.calcsize("<" + fmt[0]))
        self.body += struct.pack("<" + fmt, *values)

    def string(self, text: str) -> None:
        raw = text.encode() + b"\x00"
        self.put("I", len(raw))
        self.body += raw

    def header(self, stamp_ns: int, frame_id: str) -> None:
        """``std_msgs/Header``: stamp (int32 s, uint32 ns of ROS time) and frame_id."""
        self.put("iI", *divmod(int(stamp_ns), 1_000_000_000))
        self.string(frame_id)

    def message(self) -> bytes:
        return ENCAPSULATION + bytes(self.body)


def _stamped(stamp_ns: int, frame_id: str, *values: float) -> bytes:
    """A ``std_msgs/Header`` followed by float64 fields."""
    w = CdrWriter()
    w.header(stamp_ns, frame_id)
    w.put("d" * len(values), *values)
    return w.message()


def temperature(stamp_ns: int, frame_id: str, temperature_c: float, variance_c2: float) -> bytes:
    """``sensor_msgs/msg/Temperature`` (degC, degC^2)."""
    return _stamped(stamp_ns, frame_id, temperature_c, variance_c2)


def vector3_stamped(stamp_ns: int, frame_id: str, vector: Iterable[float]) -> bytes:
    """``geometry_msgs/msg/Vector3Stamped``."""
    return _stamped(stamp_ns, frame_id, *(float(v) for v in vector))


def diagnostic_status(level: int, name: str, message: str, hardware_id: str,
                      values: Iterable[tuple[str, str]]) -> bytes:
    """``diagnostic_msgs/msg/DiagnosticStatus`` with its ``KeyValue`` list."""
    w = CdrWriter()
    w.put("B", level)
    for text in (name, message, hardware_id):
        w.string(text)
    pairs = list(values)
    w.put("I", len(pairs))
    for key, value in pairs:
        w.string(key)
        w.string(value)
    return w.message()


class FixedJointStateCodec:
    """``sensor_msgs/msg/JointState`` messages whose frame_id and name list are fixed and whose
    velocity/effort are empty -- the ``imu/raw`` layout: encoded by filling the stamp and positions into
    precomputed bytes (``mcap_records`` reads runs of them as one numpy record array)."""

    def __init__(self, frame_id: str, names: tuple[str, ...]) -> None:
        w = CdrWriter()
        w.header(0, frame_id)
        w.put("I", len(names))
        for name in names:
            w.string(name)
        w.put("I", len(names))
        w.align(8)
        self.middle = bytes(w.body[8:])  # after the stamp, up to the first position
        start = len(w.body) + 8 * len(names)
        w.body += b"\x00" * (8 * len(names))
        w.put("II", 0, 0)  # velocity[], effort[] empty
        self.tail = bytes(w.body[start:])
        self.size = len(ENCAPSULATION) + len(w.body)
        self.n_values = len(names)
        self._values = struct.Struct(f"<{self.n_values}d")

    def encode(self, stamp_ns: int, values: list[float]) -> bytes:
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        return b"".join((ENCAPSULATION, struct.pack("<iI", sec, nsec), self.middle, self._values.pack(*values), self.tail))

    def matches(self, data: bytes) -> bool:
        return len(data) == self.size and data[:4] == ENCAPSULATION and data[12:12 + len(self.middle)] == self.middle


_STAMP = struct.Struct("<iI")
_COUNT = struct.Struct("<I")
_ZEROS = (b"", b"\0", b"\0\0", b"\0\0\0")


class FixedStampedCodec:
    """Messages of a ``std_msgs/Header`` of one frame id followed by ``k`` float64 fields (``sensor_msgs/Temperature``:
    2, ``geometry_msgs/Vector3Stamped``: 3), as :func:`temperature` and :func:`vector3_stamped` write them: every byte
    but the stamp and the values is that of the frame id, so a message is read back by comparing those bytes and
    unpacking the rest (the reader's path for the event topics, beside the decoder of their schema)."""

    def __init__(self, frame_id: str, k: int) -> None:
        sample = _stamped(0, frame_id, *([0.0] * k))
        self.size = len(sample)
        self.at = self.size - 8 * k  # the first value's offset
        self.middle = sample[12:self.at]  # after the stamp: the frame id and its padding
        self._values = struct.Struct(f"<{k}d")

    def read(self, data: bytes) -> tuple[int, tuple[float, ...]] | None:
        """``(stamp ns, values)`` of one message of this layout, None for bytes of any other."""
        if len(data) != self.size or data[12:self.at] != self.middle or data[:4] != ENCAPSULATION:
            return None
        sec, nanosec = _STAMP.unpack_from(data, 4)
        return int(sec) * 1_000_000_000 + int(nanosec), self._values.unpack_from(data, self.at)


def read_diagnostic_status(data: bytes) -> tuple[int, str, str, str, list[tuple[str, str]]] | None:
    """``(level, name, message, hardware_id, [(key, value), ...])`` of a ``diagnostic_msgs/DiagnosticStatus`` message
    exactly as :func:`diagnostic_status` writes it, None for any other bytes: each string's length counts its NUL
    (at least that), each padding is zeros, and the pairs end the message, so that :func:`diagnostic_status` of the
    values read gives ``data`` back."""
    size = len(data)
    if size < 5 or data[:4] != ENCAPSULATION:
        return None
    unpack = _COUNT.unpack_from
    texts: list[str] = []
    wanted = 3  # name, message, hardware_id; then the pair count, and two strings a pair
    counted = False
    at = 5
    try:
        while True:
            pad = -at % 4  # a uint32 (a count, a string's length) aligned to 4 from the body (offset 4)
            if pad and data[at:at + pad] != _ZEROS[pad]:
                return None
            (n,) = unpack(data, at + pad)
            at += pad + 4
            if len(texts) == wanted:  # the pair count
                if 8 * n > size - at:  # each pair takes 8 bytes at least
                    return None
                wanted += 2 * n
                counted = True
            else:
                end = at + n
                if n == 0 or end > size or data[end - 1] != 0:
                    return None
                texts.append(data[at:end - 1].decode())
                at = end
            if counted and len(texts) == wanted:
                break
    except (struct.error, UnicodeDecodeError):
        return None
    if at != size:
        return None
    return data[4], texts[0], texts[1], texts[2], list(zip(texts[3::2], texts[4::2], strict=True))
