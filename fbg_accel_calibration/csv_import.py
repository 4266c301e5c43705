"""CSV interchange format for calibration data -> :class:`Recording` (pure Python + numpy).

Format (documented in docs/csv_interchange.md):

* UTF-8 text, comma separated, one header line naming the columns (any order). Lines starting
  with ``#`` and empty lines are skipped (and counted).
* Required: ``ref_counts, x_counts, y_counts, z_counts`` -- ADC counts (reference detector and the
  three axis channels); ``ref_counts`` must be > 0 (Psi = counts / ref, eq. 24), counts >= 0.
* Reference, exactly one of:
  ``gref_x_mps2, gref_y_mps2, gref_z_mps2`` -- reference specific force in the table frame, m/s^2; or
  ``psi_deg, theta_deg`` -- two-axis table angles, degrees, converted with
  :func:`table_specific_force` (convention of ../shared/data/measured/README.md,
  f = Rz(psi)^T Rx(theta)^T (0, 0, g)); ``g`` from ``--g`` (default 9.80665 m/s^2).
* Optional: ``t_s`` (board time, s, strictly increasing); otherwise the time is the sample index
  (column ``sample`` if present, else the row order) divided by ``--rate`` (Hz).
  ``temperature_c`` (degC; an empty cell means "no valid reading" and gives NaN); otherwise every
  sample gets ``--temperature``. ``pose`` (integer >= 0, or -1 for "moving"); otherwise a new pose
  id starts at every change of the reference (so a sample with an intermediate table angle is a
  pose of its own, which the static detector then excludes).
* Other columns are ignored and listed in the import report.

Malformed rows (wrong field count, non-numeric or non-finite values, ref <= 0, negative counts,
time not increasing) are never dropped silently: by default the import fails with every bad line
number and reason (:class:`CsvImportError`); with ``drop_bad_rows=True`` the good rows are kept
and every dropped line is listed in the report and in the recording's metadata.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .recording import Recording
from .table_geometry import STANDARD_GRAVITY, table_specific_force

COUNT_COLUMNS = ("ref_counts", "x_counts", "y_counts", "z_counts")
GREF_COLUMNS = ("gref_x_mps2", "gref_y_mps2", "gref_z_mps2")
ANGLE_COLUMNS = ("psi_deg", "theta_deg")
OPTIONAL_COLUMNS = ("t_s", "temperature_c", "pose", "sample")
MAX_LISTED_ERRORS = 50


class CsvImportError(ValueError):
    """The CSV cannot be imported; the message lists the problems with line numbers."""


@dataclass
class ImportReport:
    """What the importer read: rows kept, rows rejected (line, reason), skipped lines, ignored columns."""

    path: str
    rows_read: int = 0
    rows_kept: int = 0
    rejected: list[tuple[int, str]] = field(default_factory=list)
    comment_or_blank_lines: int = 0
    ignored_columns: list[str] = field(default_factory=list)
    reference: str = ""
    time_base: str = ""
    temperature: str = ""
    pose_source: str = ""

    def summary(self) -> str:
        lines = [f"{self.path}: {self.rows_read} data rows, {self.rows_kept} kept, {len(self.rejected)} rejected",
                 f"  reference: {self.reference}; time: {self.time_base}; temperature: {self.temperature}; "
                 f"poses: {self.pose_source}"]
        if self.comment_or_blank_lines:
            lines.append(f"  {self.comment_or_blank_lines} comment/blank line(s) skipped")
        if self.ignored_columns:
            lines.append(f"  ignored columns: {', '.join(self.ignored_columns)}")
        lines += [f"  line {ln}: {why}" for ln, why in self.rejected]
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        return {"path": self.path, "rows_read": self.rows_read, "rows_kept": self.rows_kept,
                "rejected": [f"line {ln}: {why}" for ln, why in self.rejected],
                "comment_or_blank_lines": self.comment_or_blank_lines, "ignored_columns": self.ignored_columns,
                "reference": self.reference, "time_base": self.time_base, "temperature": self.temperature,
                "pose_source": self.pose_source}


def _number(text: str, name: str, allow_empty: bool = False) -> float:
    text = text.strip()
    if text == "":
        if allow_empty:
            return math.nan
        raise ValueError(f"{name} is empty")
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{name} = {text!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{name} = {text!r} is not finite")
    return value


def import_csv(path: str | Path, *, rate_hz: float | None = None, temperature_c: float | None = None,
               g_mps2: float = STANDARD_GRAVITY, drop_bad_rows: bool = False) -> tuple[Recording, ImportReport]:
    """Read a CSV in the interchange format into a Recording (run_id 0) and an :class:`ImportReport`."""
    path = Path(path)
    if not path.is_file():
        raise CsvImportError(f"{path}: file not found")
    report = ImportReport(str(path))
    with open(path, newline="", encoding="utf-8") as fh:
        lines = enumerate(fh, start=1)
        header: list[str] | None = None
        header_line = 0
        for line_no, line in lines:
            if not line.strip() or line.lstrip().startswith("#"):
                report.comment_or_blank_lines += 1
                continue
            header = [h.strip() for h in next(csv.reader([line]))]
            header_line = line_no
            break
        if header is None:
            raise CsvImportError(f"{path}: no header line")
        col = _check_header(path, header, header_line, rate_hz, temperature_c)
        report.ignored_columns = [h for h in header if h not in col]
        use_angles = "psi_deg" in col
        report.reference = "table angles psi_deg/theta_deg" if use_angles else "gref_*_mps2 columns"
        report.time_base = ("t_s column" if "t_s" in col else
                            f"{'sample column' if 'sample' in col else 'row index'} / {rate_hz} Hz")
        report.temperature = "temperature_c column" if "temperature_c" in col else f"constant {temperature_c} degC"
        report.pose_source = "pose column" if "pose" in col else "a new pose at every change of the reference"
        rows: list[list[float]] = []
        row_lines: list[int] = []
        for line_no, line in lines:
            if not line.strip() or line.lstrip().startswith("#"):
                report.comment_or_blank_lines += 1
                continue
            report.rows_read += 1
            fields = next(csv.reader([line]))
            try:
                rows.append(_parse_row(fields, header, col, rate_hz, temperature_c, report.rows_read - 1))
                row_lines.append(line_no)
            except ValueError as exc:
                report.rejected.append((line_no, str(exc)))
    data = np.asarray(rows, dtype=float).reshape(-1, 10)
    # time must increase strictly (checked on the parsed rows, so the line numbers are exact)
    if len(data) > 1:
        bad = np.flatnonzero(np.diff(data[:, 0]) <= 0) + 1
        if len(bad):
            for i in bad:
                report.rejected.append((row_lines[i], f"time {data[i, 0]:g} s does not increase (previous {data[i - 1, 0]:g} s)"))
            keep = np.ones(len(data), bool)
            keep[bad] = False
            data = data[keep]
            row_lines = [ln for ln, k in zip(row_lines, keep, strict=True) if k]
    report.rejected.sort()
    if report.rejected and not drop_bad_rows:
        shown = report.rejected[:MAX_LISTED_ERRORS]
        more = len(report.rejected) - len(shown)
        msg = "\n".join(f"  line {ln}: {why}" for ln, why in shown)
        raise CsvImportError(f"{path}: {len(report.rejected)} malformed row(s) (nothing imported; "
                             f"use --drop-bad-rows to import the others):\n{msg}"
                             + (f"\n  ... and {more} more" if more else ""))
    if len(data) == 0:
        raise CsvImportError(f"{path}: no valid data rows")
    report.rows_kept = len(data)
    t_s, ref, xyz, temp = data[:, 0], data[:, 1], data[:, 2:5], data[:, 5]
    if use_angles:
        gref = table_specific_force(data[:, 6], data[:, 7], g_mps2)
    else:
        gref = data[:, 6:9]
    if "pose" in col:
        pose = data[:, 9].astype(int)
    else:
        changed = np.r_[True, np.any(np.diff(gref, axis=0) != 0.0, axis=1)]
        pose = np.cumsum(changed) - 1
    meta = {"source": str(path), "import": report.as_dict(), "g_mps2": g_mps2}
    return Recording(t_s, ref, xyz, temp, gref, pose, metadata=meta), report


def _check_header(path: Path, header: list[str], line_no: int, rate_hz: float | None,
                  temperature_c: float | None) -> dict[str, int]:
    dupes = sorted({h for h in header if header.count(h) > 1})
    if dupes:
        raise CsvImportError(f"{path}: line {line_no}: duplicate column(s) {dupes}")
    col = {h: i for i, h in enumerate(header)
           if h in COUNT_COLUMNS + GREF_COLUMNS + ANGLE_COLUMNS + OPTIONAL_COLUMNS}
    missing = [c for c in COUNT_COLUMNS if c not in col]
    if missing:
        raise CsvImportError(f"{path}: line {line_no}: missing required column(s) {missing}")
    has_g = [c in col for c in GREF_COLUMNS]
    has_a = [c in col for c in ANGLE_COLUMNS]
    if any(has_g) and any(has_a):
        raise CsvImportError(f"{path}: line {line_no}: give the reference either as {list(GREF_COLUMNS)} "
                             f"or as {list(ANGLE_COLUMNS)}, not both")
    if any(has_g) and not all(has_g):
        raise CsvImportError(f"{path}: line {line_no}: incomplete reference, need all of {list(GREF_COLUMNS)}")
    if any(has_a) and not all(has_a):
        raise CsvImportError(f"{path}: line {line_no}: incomplete reference, need both {list(ANGLE_COLUMNS)}")
    if not any(has_g) and not any(has_a):
        raise CsvImportError(f"{path}: line {line_no}: no reference: need {list(GREF_COLUMNS)} or {list(ANGLE_COLUMNS)}")
    if "t_s" not in col and not (rate_hz and rate_hz > 0):
        raise CsvImportError(f"{path}: no t_s column: give the sample rate (--rate, Hz)")
    if "temperature_c" not in col and (temperature_c is None or not math.isfinite(temperature_c)):
        raise CsvImportError(f"{path}: no temperature_c column: give the temperature (--temperature, degC)")
    return col


def _parse_row(fields: list[str], header: list[str], col: dict[str, int], rate_hz: float | None,
               temperature_c: float | None, index: int) -> list[float]:
    """One data row -> [t_s, ref, x, y, z, temp, gx|psi, gy|theta, gz|nan, pose]; ValueError with the reason."""
    if len(fields) != len(header):
        raise ValueError(f"{len(fields)} fields, header has {len(header)}")
    counts = [_number(fields[col[c]], c) for c in COUNT_COLUMNS]
    if counts[0] <= 0:
        raise ValueError(f"ref_counts = {fields[col['ref_counts']].strip()} must be > 0")
    for name, value in zip(COUNT_COLUMNS[1:], counts[1:], strict=True):
        if value < 0:
            raise ValueError(f"{name} = {value:g} is negative")
    if "t_s" in col:
        t = _number(fields[col["t_s"]], "t_s")
    elif "sample" in col:
        t = _number(fields[col["sample"]], "sample") / float(rate_hz)
    else:
        t = index / float(rate_hz)
    temp = _number(fields[col["temperature_c"]], "temperature_c", allow_empty=True) if "temperature_c" in col \
        else float(temperature_c)
    if "psi_deg" in col:
        r = [_number(fields[col["psi_deg"]], "psi_deg"), _number(fields[col["theta_deg"]], "theta_deg"), math.nan]
    else:
        r = [_number(fields[col[c]], c) for c in GREF_COLUMNS]
    return [t, *counts, temp, *r, _pose(fields, col)]


def _pose(fields: list[str], col: dict[str, int]) -> float:
    if "pose" not in col:
        return -2.0
    value = _number(fields[col["pose"]], "pose")
    if value != int(value) or value < -1:
        raise ValueError(f"pose = {fields[col['pose']].strip()!r} must be an integer >= -1")
    return value
