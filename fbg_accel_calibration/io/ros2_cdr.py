"""CDR encoding (XCDR1, little endian: the ROS 2 default) of the four message types a calibration
recording holds, written by :class:`mcap_writer.RecordingWriter`.

Pure Python. The layouts are those of the ROS 2 middleware (and of the ``mcap_ros2`` encoder,
byte for byte: ``test_mcap_io`` compares each with messages written through ``mcap_ros2``'s public
writer): a 4-byte encapsulation header, then the fields in order, each primitive aligned to its own
size counted from the end of that header; a string is a uint32 length (with its NUL) and the bytes
with the NUL; a sequence is a uint32 count and its elements.
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
