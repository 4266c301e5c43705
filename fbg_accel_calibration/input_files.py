"""Input files of the offline tools: which files are accepted, and one loader for all of them.

A recording is a ``.csv`` in the interchange format (docs/csv_interchange.md), an MCAP file written by
the calibration node or ``fbg-accel-calib import``, or a rosbag2 bag directory (metadata.yaml + .mcap
files); anything else is refused in one line before any work is done.
"""

from __future__ import annotations

import sys
from pathlib import Path

from .table_geometry import STANDARD_GRAVITY

MCAP_MAGIC = b"\x89MCAP0\r\n"


def check_mcap(path: Path) -> None:
    """Refuse a file that is not an MCAP (by its magic bytes) with a message saying what to give instead."""
    with open(path, "rb") as fh:
        head = fh.read(len(MCAP_MAGIC))
    if head != MCAP_MAGIC:
        raise ValueError(f"{path}: not an MCAP recording (it does not start with the MCAP magic bytes); give a .mcap "
                         "file written by the calibration node or `fbg-accel-calib import`, or a .csv in the "
                         "interchange format (docs/csv_interchange.md)")


def check_input(path: Path) -> None:
    """An input is a .csv file, an MCAP file or a rosbag2 bag directory (metadata.yaml + .mcap files);
    anything else is refused in one line."""
    if path.is_dir():
        from .rosbag2_input import bag_files

        for part in bag_files(path).files:
            check_mcap(part)
        return
    if not path.is_file():
        raise ValueError(f"{path}: file not found")
    if path.suffix.lower() != ".csv":
        check_mcap(path)


def load_recording(paths: list[Path] | list[str], *, rate: float | None = None, temperature: float | None = None,
                   g: float | None = None, namespace: str | None = None, topic: str | None = None):
    """Recording from CSV and/or MCAP files and/or rosbag2 bag directories (one run per input); ``rate``,
    ``temperature`` and ``g`` (m/s^2, default standard gravity) complete a CSV, ``namespace``/``topic``
    choose the raw topic of MCAP inputs (``mcap_io.TopicSelection``). Damaged-file warnings go to stderr."""
    from .csv_import import import_csv
    from .mcap_io import read_recording, read_warnings
    from .recording import Recording

    parts = []
    for path in map(Path, paths):
        check_input(path)
        if path.suffix.lower() == ".csv" and path.is_file():
            parts.append(import_csv(path, rate_hz=rate, temperature_c=temperature,
                                    g_mps2=STANDARD_GRAVITY if g is None else g)[0])
        else:
            rec = read_recording(path, namespace, topic)
            for line in read_warnings(path, rec.metadata.get("read_report", {}), rec.metadata.get("pose_events")):
                print(line, file=sys.stderr)
            parts.append(rec)
    return parts[0] if len(parts) == 1 else Recording.concatenate(parts)
