"""Input files of the offline tools: which files are accepted, and one loader for all of them.

A recording is a ``.csv`` in the interchange format (docs/csv_interchange.md), an MCAP file written by
the calibration node or ``fbg-accel-calib import``, or a rosbag2 bag directory (metadata.yaml + .mcap
files); anything else is refused in one line before any work is done, and so is a recording given twice
(the same path, a link to it, or a copy of the file; a bag directory and one of its own files or a copy of one).
"""

from __future__ import annotations

import filecmp
import os
import sys
from pathlib import Path

from fbg_accel_driver.yaml_input import file_kind

from .table_geometry import STANDARD_GRAVITY


def check_mcap(path: Path) -> None:
    """Refuse a file that is not an MCAP (by its magic bytes) with a message saying what to give instead."""
    from .mcap_format import MCAP_MAGIC  # the format's own module, imported here: a CSV input loads no MCAP reader

    with open(path, "rb") as fh:
        head = fh.read(len(MCAP_MAGIC))
    if head != MCAP_MAGIC:
        raise ValueError(f"{path}: not an MCAP recording (it does not start with the MCAP magic bytes); give a .mcap "
                         "file written by the calibration node or `fbg-accel-calib import`, or a .csv in the "
                         "interchange format (docs/csv_interchange.md)")


def check_input(path: Path) -> list[Path]:
    """An input is a .csv file, an MCAP file or a rosbag2 bag directory (metadata.yaml + .mcap files);
    anything else is refused in one line. Returns the files the input reads (a bag's members, in order)."""
    if path.is_dir():
        from .rosbag2_input import bag_files

        files = bag_files(path).files
        for part in files:
            check_mcap(part)
        return files
    kind = file_kind(path)
    if kind is not None:  # a FIFO or /dev/zero is said as what it is, and never read
        raise ValueError(f"{path}: file not found" if kind == "not found" else f"{path}: {kind}, not a recording")
    if path.suffix.lower() != ".csv":
        check_mcap(path)
    return [path]


def _same_file(a: Path, b: Path) -> bool:
    """Whether two files are one: the same file (a path, a link to it), or the same bytes (a copy; compared only
    when their sizes are equal)."""
    try:
        if os.path.samefile(a, b):
            return True
        return a.stat().st_size == b.stat().st_size and filecmp.cmp(a, b, shallow=False)
    except OSError:
        return False


def _shared_file(a: list[Path], b: list[Path]) -> tuple[Path, Path] | None:
    """The first pair of files of two inputs that are one file (:func:`_same_file`), or None."""
    return next(((x, y) for x in a for y in b if _same_file(x, y)), None)


def check_inputs(paths: list[Path] | list[str]) -> None:
    """:func:`check_input` for each, and refuse a recording given twice (or with a copy of it): it would be read as
    two runs, its samples counted twice and its visits taken for repeats. Inputs are compared by the files they
    read, so a bag directory and one of its own .mcap files (or a copy of one, or a copy of the bag) are one
    recording given twice."""
    paths = [Path(p) for p in paths]
    files: list[list[Path]] = []
    for i, path in enumerate(paths):
        mine = check_input(path)
        for earlier, theirs in zip(paths[:i], files, strict=True):
            shared = _shared_file(mine, theirs)
            if shared is None:
                continue
            inner = "" if (shared[0], shared[1]) == (path, earlier) else \
                f"; {shared[0]} is {'' if os.path.samefile(*shared) else 'a copy of '}{shared[1]}"
            raise ValueError(f"{path}: the same recording as {earlier} (given twice, or a copy of it{inner}); give "
                             "each run once")
        files.append(mine)


def load_recording(paths: list[Path] | list[str], *, rate: float | None = None, temperature: float | None = None,
                   g: float | None = None, namespace: str | None = None, topic: str | None = None):
    """Recording from CSV and/or MCAP files and/or rosbag2 bag directories (one run per input); ``rate``,
    ``temperature`` and ``g`` (m/s^2, default standard gravity) complete a CSV, ``namespace``/``topic``
    choose the raw topic of MCAP inputs (``mcap_format.TopicSelection``). Damaged-file warnings go to stderr."""
    from ..fit.thermal_fit import sensor_id_of
    from .csv_import import import_csv
    from .mcap_reader import read_recording
    from .mcap_records import read_warnings
    from .recording import Recording

    check_inputs(paths)
    parts = []
    for path in map(Path, paths):
        if path.suffix.lower() == ".csv" and path.is_file():
            parts.append(import_csv(path, rate_hz=rate, temperature_c=temperature,
                                    g_mps2=STANDARD_GRAVITY if g is None else g)[0])
        else:
            rec = read_recording(path, namespace, topic)
            for line in read_warnings(path, rec.metadata.get("read_report", {}), rec.metadata.get("pose_events")):
                print(line, file=sys.stderr)
            parts.append(rec)
    rec = parts[0] if len(parts) == 1 else Recording.concatenate(parts)
    sensor_id_of(rec.metadata)  # recordings of two sensors are refused (ValueError naming them)
    return rec
