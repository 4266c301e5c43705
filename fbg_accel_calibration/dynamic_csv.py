"""CSV interchange of a dynamic run (docs/csv_interchange.md, "Dynamic runs"): the sensor's counts and
the reference transducer's aux counts on one shared time base.

Columns (header row, any order, extra columns ignored): ``t_s`` (s, strictly increasing), ``ref``,
``x``, ``y``, ``z`` (ADC counts), ``aux`` (ADC counts of the reference transducer), and optionally
``temperature_c`` (degC; else give one temperature for the run).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from .recording import Recording

REQUIRED = ("t_s", "ref", "x", "y", "z", "aux")
MAX_BYTES = 2 << 30


class DynamicCsvError(ValueError):
    """The CSV is not a dynamic run in the interchange format."""


def read_dynamic_csv(path: str | Path, temperature_c: float | None = None) -> Recording:
    """A ``Recording`` with ``aux`` from a dynamic-run CSV; one line per malformed row in the error."""
    p = Path(path)
    if not p.is_file():
        raise DynamicCsvError(f"{p}: file not found")
    if p.stat().st_size > MAX_BYTES:
        raise DynamicCsvError(f"{p}: larger than 2 GiB")
    rows: list[list[float]] = []
    errors: list[str] = []
    with p.open(newline="", encoding="utf-8-sig", errors="strict") as fh:
        # (line number in the file, fields): comment and blank lines are skipped but keep their numbers
        reader = ((n, next(csv.reader([line]))) for n, line in enumerate(fh, start=1)
                  if line.strip() and not line.lstrip().startswith("#"))
        try:
            header = [h.strip() for h in next(reader)[1]]
        except StopIteration:
            raise DynamicCsvError(f"{p}: empty file") from None
        except UnicodeDecodeError as exc:
            raise DynamicCsvError(f"{p}: not UTF-8 text ({exc})") from None
        missing = [c for c in REQUIRED if c not in header]
        if missing:
            raise DynamicCsvError(f"{p}: missing column(s) {missing} (a dynamic run needs {list(REQUIRED)}; "
                                  f"found {header})")
        has_temp = "temperature_c" in header
        if not has_temp and temperature_c is None:
            raise DynamicCsvError(f"{p}: no temperature_c column: give the run's temperature (--temperature)")
        cols = [header.index(c) for c in (*REQUIRED, *(("temperature_c",) if has_temp else ()))]
        last_t = -math.inf
        try:
            for line_no, row in reader:
                if len(row) != len(header):
                    errors.append(f"line {line_no}: {len(row)} fields, header has {len(header)}")
                    continue
                try:
                    vals = [_cell(row[i], header[i]) for i in cols]
                except ValueError as exc:
                    errors.append(f"line {line_no}: {exc}")
                    continue
                if not all(math.isfinite(v) for v in vals[:6]):
                    errors.append(f"line {line_no}: t_s, ref, x, y, z and aux must be finite numbers")
                    continue
                if vals[0] <= last_t:
                    errors.append(f"line {line_no}: t_s {vals[0]:g} does not increase (previous {last_t:g})")
                    continue
                last_t = vals[0]
                rows.append(vals if has_temp else [*vals, float(temperature_c)])  # type: ignore[arg-type]
        except UnicodeDecodeError as exc:
            raise DynamicCsvError(f"{p}: not UTF-8 text ({exc})") from None
    if errors:
        shown = "\n".join(f"  {e}" for e in errors[:10])
        more = f"\n  ... and {len(errors) - 10} more" if len(errors) > 10 else ""
        raise DynamicCsvError(f"{p}: {len(errors)} malformed row(s), nothing used:\n{shown}{more}")
    if len(rows) < 10:
        raise DynamicCsvError(f"{p}: {len(rows)} data row(s), a dynamic run needs many periods of every segment")
    a = np.asarray(rows, dtype=float)
    n = len(a)
    return Recording(t_s=a[:, 0], ref=a[:, 1], xyz=a[:, 2:5], temp_c=a[:, 6], gref_mps2=np.full((n, 3), np.nan),
                     pose_id=np.full(n, -1), aux=a[:, 5], metadata={"source": str(p)})


def _cell(text: str, name: str) -> float:
    """A cell's value (NaN for an empty cell); ValueError naming the column and the text."""
    if not text.strip():
        return math.nan
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{name} = {text.strip()!r} is not a number") from None


def write_dynamic_csv(path: str | Path, rec: Recording) -> None:
    """Write ``rec`` (with ``aux``) in the dynamic-run CSV format (the inverse of :func:`read_dynamic_csv`)."""
    if rec.aux is None:
        raise ValueError("the recording has no aux channel")
    data = np.column_stack([rec.t_s, rec.ref, rec.xyz, rec.aux, rec.temp_c])
    np.savetxt(path, data, delimiter=",", header="t_s,ref,x,y,z,aux,temperature_c", comments="", encoding="utf-8",
               fmt=["%.6f", "%.0f", "%.0f", "%.0f", "%.0f", "%.0f", "%.2f"])
