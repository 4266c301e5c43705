"""CSV interchange of a dynamic run (docs/csv_interchange.md, "Dynamic runs"): the sensor's counts and
the reference transducer's aux counts on one shared time base.

Columns (header row, any order, extra columns ignored): ``t_s`` (s, strictly increasing; or ``t_ms`` / ``t_us``),
``ref``, ``x``, ``y``, ``z`` (ADC counts), ``aux`` (ADC counts of the reference transducer), and optionally
``temperature_c`` (degC; else give one temperature for the run). Read by :class:`csv_import.CsvBlocks`, so lines,
header, separators, cells, time units and temperatures follow the calibration CSV's rules.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .csv_import import TIME_COLUMNS, CsvBlocks, CsvImportError
from .recording import Recording, join_blocks

COUNTS = ("ref", "x", "y", "z", "aux")
MIN_ROWS = 10
DynamicCsvError = CsvImportError  # one reader, one error


class DynamicCsvBlocks(CsvBlocks):
    """A dynamic-run CSV read block by block; rows are [t_s, ref, x, y, z, temperature_c, aux]."""

    REQUIRED = COUNTS
    WIDTH = 7
    REMEDY = "a dynamic run uses every row: correct or delete those lines"

    def _columns(self, header: list[str], where: str) -> dict[str, int]:
        col = {h: i for i, h in enumerate(header) if h in (*TIME_COLUMNS, *COUNTS, "temperature_c")}
        missing = ([] if TIME_COLUMNS.keys() & col.keys() else ["t_s"]) + [c for c in COUNTS if c not in col]
        if missing:
            raise CsvImportError(f"{where} missing column(s) {missing} (a dynamic run needs t_s (or t_ms, t_us), "
                                 f"{', '.join(COUNTS)}; found {header})")
        return col

    def _parse_row(self, fields: list[str], index: int) -> list[float]:
        ref, x, y, z, aux = (self._value(fields, c) for c in COUNTS)
        return [self._time(fields, index), ref, x, y, z, self._temperature(fields), aux]

    def _complete(self, row: list[float]) -> None:
        pass

    def _block(self, data: np.ndarray) -> Recording:
        n = len(data)
        return Recording(data[:, 0].copy(), data[:, 1].copy(), data[:, 2:5].copy(), data[:, 5].copy(),
                         np.full((n, 3), np.nan), np.full(n, -1), aux=data[:, 6].copy(),
                         metadata={"source": str(self.path)})


def read_dynamic_csv(path: str | Path, temperature_c: float | None = None) -> Recording:
    """A ``Recording`` with ``aux`` from a dynamic-run CSV (``temperature_c``: degC of a file without the column);
    :class:`DynamicCsvError` lists the malformed rows by their line in the file, and nothing is used."""
    src = DynamicCsvBlocks(path, temperature_c=temperature_c)
    parts = list(src.blocks())
    src.check(drop_bad_rows=False)
    if src.report.rows_kept < MIN_ROWS:
        raise DynamicCsvError(f"{src.path}: {src.report.rows_kept} data row(s), a dynamic run needs many periods "
                              "of every segment")
    return join_blocks(parts)


def write_dynamic_csv(path: str | Path, rec: Recording) -> None:
    """Write ``rec`` (with ``aux``) in the dynamic-run CSV format (the inverse of :func:`read_dynamic_csv`)."""
    if rec.aux is None:
        raise ValueError("the recording has no aux channel")
    data = np.column_stack([rec.t_s, rec.ref, rec.xyz, rec.aux, rec.temp_c])
    np.savetxt(path, data, delimiter=",", header="t_s,ref,x,y,z,aux,temperature_c", comments="", encoding="utf-8",
               fmt=["%.6f", "%.0f", "%.0f", "%.0f", "%.0f", "%.0f", "%.2f"])
