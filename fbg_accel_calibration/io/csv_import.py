"""CSV interchange format for calibration data -> :class:`Recording` (pure Python + numpy).

Format (documented in docs/csv_interchange.md):

* UTF-8 text, comma separated, one header line naming the columns (any order; names matched without
  surrounding spaces and case; empty names are unnamed columns, ignored). Lines starting with ``#``, empty
  lines and lines of only commas are skipped (and counted). Semicolon- or tab-separated files and bare-CR
  line ends are refused with what to do.
* Required: ``ref_counts, x_counts, y_counts, z_counts`` -- ADC counts (reference detector and the
  three axis channels); ``ref_counts`` must be > 0 (Psi = counts / ref, eq. 24), counts >= 0.
* Reference, exactly one of:
  ``gref_x_mps2, gref_y_mps2, gref_z_mps2`` -- reference specific force in the table frame, m/s^2; or
  ``psi_deg, theta_deg`` -- two-axis table angles, degrees, converted with
  :func:`table_specific_force` (convention of ../shared/data/measured/README.md,
  f = Rz(psi)^T Rx(theta)^T (0, 0, g)); ``g`` from ``--g`` (default 9.80665 m/s^2).
* Optional: ``t_s`` (board time, s, strictly increasing; or ``t_ms`` / ``t_us`` in ms / us; a median step
  above ``MAX_MEDIAN_STEP_S`` is refused as not seconds); otherwise the time is the sample index
  (column ``sample`` if present, else the row order) divided by ``--rate`` (Hz).
  ``temperature_c`` (degC; an empty cell or NaN means "no valid reading" and gives NaN); otherwise every
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
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import input_validation as iv
from .recording import Recording, join_blocks
from .table_geometry import STANDARD_GRAVITY, table_specific_force

COUNT_COLUMNS = ("ref_counts", "x_counts", "y_counts", "z_counts")
GREF_COLUMNS = ("gref_x_mps2", "gref_y_mps2", "gref_z_mps2")
ANGLE_COLUMNS = ("psi_deg", "theta_deg")
# time columns and their unit in s: the board's own clock counts us since boot, other software writes ms
TIME_COLUMNS = {"t_s": 1.0, "t_ms": 1e-3, "t_us": 1e-6}
OPTIONAL_COLUMNS = (*TIME_COLUMNS, "temperature_c", "pose", "sample")
MAX_LISTED_ERRORS = 50
# A time column whose median step between the first TIME_CHECK_ROWS rows exceeds this is not in seconds (s). The board
# samples at 100 Hz (paper 3.5); ms or us read as s give steps of 10 s or 10^4 s at that rate. 1 s steps are accepted
# (time counted in samples, as --rate 1 does), so ms from a board at 1 kHz or faster are not caught.
MAX_MEDIAN_STEP_S = 1.0
TIME_CHECK_ROWS = 1000
CR_LINE_ENDS = ("a carriage return (CR) inside the line: the file's lines end in a bare CR (classic Mac OS); "
                "save it with LF or CRLF line ends")


class CsvImportError(ValueError):
    """The CSV cannot be imported; the message lists the problems with line numbers."""


@dataclass
class ImportReport:
    """What the importer read: rows kept, rows rejected (line, reason), skipped lines, ignored columns."""

    path: str
    rows_read: int = 0
    rows_kept: int = 0
    rejected: list[tuple[int, str]] = field(default_factory=list)
    rejected_unlisted: int = 0  # rejected lines beyond MAX_STORED_REJECTS, counted only
    comment_or_blank_lines: int = 0
    ignored_columns: list[str] = field(default_factory=list)
    reference: str = ""
    time_base: str = ""
    temperature: str = ""
    pose_source: str = ""

    def summary(self) -> str:
        n_rejected = len(self.rejected) + self.rejected_unlisted
        lines = [f"{self.path}: {self.rows_read} data rows, {self.rows_kept} kept, {n_rejected} rejected",
                 f"  reference: {self.reference}; time: {self.time_base}; temperature: {self.temperature}; "
                 f"poses: {self.pose_source}"]
        if self.comment_or_blank_lines:
            lines.append(f"  {self.comment_or_blank_lines} comment/blank line(s) skipped")
        if self.ignored_columns:
            lines.append(f"  ignored columns: {', '.join(self.ignored_columns)}")
        lines += [f"  line {ln}: {why}" for ln, why in self.rejected]
        if self.rejected_unlisted:
            lines.append(f"  ... and {self.rejected_unlisted} more rejected line(s) not listed")
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "rejected": [f"line {ln}: {why}" for ln, why in self.rejected]}


def _number(text: str, name: str, allow_empty: bool = False) -> float:
    text = text.strip()
    if text == "" or (allow_empty and text.lower() == "nan"):  # pandas writes no reading as '', MATLAB as NaN
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


MAX_LINE_BYTES = 65536  # a data row of this format is < 200 bytes; a longer line is refused, not parsed
MAX_STORED_REJECTS = 10000  # rejected lines kept with their reason; beyond that only counted
DEFAULT_BLOCK_ROWS = 65536  # rows per parsed block (memory of the importer: a few blocks, not the file)
_BOM = b"\xef\xbb\xbf"


class CsvBlocks:
    """A CSV in the interchange format read block by block (memory: one block, whatever the file size).

    Opening reads and checks the header (:class:`CsvImportError` on a header problem). Iterating
    :meth:`blocks` parses the data rows into :class:`Recording` blocks of at most ``block_rows`` rows;
    rejected rows are recorded in :attr:`report` as they are met (the caller decides after the last
    block whether a rejected row fails the import). The time-order check and the pose numbering from
    reference changes carry over block boundaries, so the blocks concatenated equal a whole-file read.

    Lines, header names, separators, cells, time units and temperatures are read alike for every CSV: another format
    (``dynamic_csv``) overrides :meth:`_columns`, :meth:`_parse_row`, :meth:`_complete`, :meth:`_block`, the constants.
    """

    REQUIRED = COUNT_COLUMNS  # column names the header of this format holds (the delimiter check looks for them)
    WIDTH = 12  # values of a parsed row: t_s (s), ref, x, y, z (counts), temperature (degC), then the format's own
    # (here the reference (3), the pose id and the table angles psi, theta (deg; NaN when the reference is a vector))
    REMEDY = "fbg-accel-calib import --drop-bad-rows imports the others into an MCAP to give here instead"

    def __init__(self, path: str | Path, *, rate_hz: float | None = None, temperature_c: float | None = None,
                 g_mps2: float = STANDARD_GRAVITY, block_rows: int = DEFAULT_BLOCK_ROWS) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise CsvImportError(f"{self.path}: file not found")
        if not (math.isfinite(g_mps2) and g_mps2 > 0):
            raise CsvImportError(f"{self.path}: gravity {g_mps2!r} m/s^2 must be finite and > 0 (--g)")
        if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
            raise CsvImportError(f"{self.path}: --rate {rate_hz!r} Hz must be finite and > 0")
        self.rate_hz, self.temperature_c, self.g_mps2, self.block_rows = rate_hz, temperature_c, g_mps2, block_rows
        self.report = ImportReport(str(self.path))
        self.rejected_total = 0
        self.valid_temperatures = 0
        with open(self.path, "rb") as fh:
            raw_header = None
            for line_no, text in self._lines(fh):
                if text is None:
                    problem = self._line_problem
                    raise CsvImportError(f"{self.path}: line {line_no}: header line"
                                         f"{' is ' if problem.startswith('not UTF-8') else ': '}{problem}")
                # a CR first: with bare-CR line ends a file that opens with a comment is one long comment line
                if "\r" in text.rstrip("\r\n"):
                    raise CsvImportError(f"{self.path}: line {line_no}: {CR_LINE_ENDS}")
                if _blank_or_comment(text):
                    self.report.comment_or_blank_lines += 1
                    continue
                try:
                    raw_header = next(csv.reader([text], skipinitialspace=True))
                except csv.Error as exc:
                    raise CsvImportError(f"{self.path}: line {line_no}: the header is not a line of comma-separated "
                                         f"names ({exc})") from None
                self.header_line = line_no
                break
            self._data_offset = fh.tell()
        if raw_header is None:
            raise CsvImportError(f"{self.path}: no header line (expected column names such as "
                                 f"{', '.join(self.REQUIRED)})")
        # names are matched without surrounding spaces and case (" X_Counts" is x_counts); an empty name (trailing
        # commas, a pandas index) is an unnamed column, ignored like any unknown one
        header = [h.strip().lower() for h in raw_header]
        _check_delimiter(self.path, header, text, self.header_line, self.REQUIRED)
        where = f"{self.path}: line {self.header_line}:"
        dupes = sorted({h for h in header if h and header.count(h) > 1})
        if dupes:
            raise CsvImportError(f"{where} duplicate column(s) {dupes}")
        self.header = header
        self.col = col = self._columns(header, where)
        times = [c for c in TIME_COLUMNS if c in col]
        if len(times) > 1:
            raise CsvImportError(f"{where} {times}: give one time column (t_s in s, t_ms in ms or t_us in us)")
        if not times and not rate_hz:
            raise CsvImportError(f"{self.path}: no t_s column: give the sample rate (--rate, Hz; --rate 1 counts time "
                                 "in samples)")
        if "temperature_c" not in col and (temperature_c is None or not math.isfinite(temperature_c)):
            raise CsvImportError(f"{self.path}: no temperature_c column: give the temperature (--temperature, degC)")
        used = set(col.values())
        self.report.ignored_columns = [h.strip() or f"(unnamed column {i + 1})" for i, h in enumerate(raw_header)
                                       if i not in used]
        self.time_column = next(iter(times), None)
        self.report.time_base = (f"{self.time_column} column" if self.time_column else
                                 f"{'sample column' if 'sample' in col else 'row index'} / {rate_hz} Hz")
        self.report.temperature = "temperature_c column" if "temperature_c" in col else f"constant {temperature_c} degC"

    def _columns(self, header: list[str], where: str) -> dict[str, int]:
        """The format's columns {name: index} in the normalised ``header``; CsvImportError (prefixed ``where``) when
        one is missing. The time columns and the temperature are checked by the caller, alike for every format."""
        col = {h: i for i, h in enumerate(header)
               if h in COUNT_COLUMNS + GREF_COLUMNS + ANGLE_COLUMNS + OPTIONAL_COLUMNS}
        missing = [c for c in COUNT_COLUMNS if c not in col]
        if missing:
            raise CsvImportError(f"{where} missing required column(s) {missing}")
        has_g = [c in col for c in GREF_COLUMNS]
        has_a = [c in col for c in ANGLE_COLUMNS]
        if any(has_g) and any(has_a):
            raise CsvImportError(f"{where} give the reference either as {list(GREF_COLUMNS)} "
                                 f"or as {list(ANGLE_COLUMNS)}, not both")
        if any(has_g) and not all(has_g):
            raise CsvImportError(f"{where} incomplete reference, need all of {list(GREF_COLUMNS)}")
        if any(has_a) and not all(has_a):
            raise CsvImportError(f"{where} incomplete reference, need both {list(ANGLE_COLUMNS)}")
        if not any(has_g) and not any(has_a):
            raise CsvImportError(f"{where} no reference: need {list(GREF_COLUMNS)} or {list(ANGLE_COLUMNS)}")
        self.use_angles = "psi_deg" in col
        self.report.reference = "table angles psi_deg/theta_deg" if self.use_angles else "gref_*_mps2 columns"
        self.report.pose_source = "pose column" if "pose" in col else "a new pose at every change of the reference"
        return col

    def _lines(self, fh, first_line: int = 1):
        """``(line number, text)`` of each line; text None for a line that is not UTF-8 or longer than
        ``MAX_LINE_BYTES`` (its reason in :attr:`_line_problem`). A UTF-8 BOM at the start is dropped."""
        line_no = first_line - 1
        at_start = fh.tell() == 0
        while True:
            raw = fh.readline(MAX_LINE_BYTES + 1)
            if not raw:
                return
            line_no += 1
            if at_start:
                at_start = False
                if raw.startswith(_BOM):
                    raw = raw[len(_BOM):]
            if len(raw) > MAX_LINE_BYTES and not raw.endswith(b"\n"):
                bare_cr = b"\r" in raw[:-1]
                n = len(raw)
                while raw and not raw.endswith(b"\n"):  # skip the rest of the line in bounded pieces
                    raw = fh.readline(MAX_LINE_BYTES)
                    n += len(raw)
                self._line_problem = (CR_LINE_ENDS if bare_cr else
                                      f"line longer than {MAX_LINE_BYTES} bytes ({n} bytes); not a data row")
                yield line_no, None
                continue
            try:
                yield line_no, raw.decode("utf-8")
            except UnicodeDecodeError as exc:
                self._line_problem = (f"not UTF-8 text (byte 0x{raw[exc.start]:02x} at column {exc.start + 1}); "
                                      "save the file as UTF-8")
                yield line_no, None

    def _reject(self, line_no: int, why: str) -> None:
        self.rejected_total += 1
        if len(self.report.rejected) < MAX_STORED_REJECTS:
            self.report.rejected.append((line_no, why))
        else:
            self.report.rejected_unlisted += 1

    def blocks(self) -> Iterator[Recording]:
        """Parse the data rows (one pass; call again for another pass) into Recording blocks."""
        report = self.report
        report.rows_read = report.rows_kept = self.rejected_total = self.valid_temperatures = 0
        report.rejected, report.rejected_unlisted = [], 0
        comments = report.comment_or_blank_lines
        buf = np.empty((self.block_rows, self.WIDTH))
        fill = 0
        last_t = -math.inf
        self._last_g: tuple[float, float, float] | None = None
        self._pose_counter = -1
        first_times: list[float] = []  # s, of the first kept rows (the time-unit check)
        first_lines: list[int] = []
        with open(self.path, "rb") as fh:
            fh.seek(self._data_offset)
            for line_no, text in self._lines(fh, self.header_line + 1):
                if text is not None and _blank_or_comment(text):
                    comments += 1
                    continue
                report.rows_read += 1
                if text is None:
                    self._reject(line_no, self._line_problem)
                    continue
                if "\r" in text.rstrip("\r\n"):
                    self._reject(line_no, CR_LINE_ENDS)
                    continue
                try:
                    fields = next(csv.reader([text], skipinitialspace=True))
                    if len(fields) != len(self.header):
                        raise ValueError(f"{len(fields)} fields, header has {len(self.header)}")
                    row = self._parse_row(fields, report.rows_read - 1)
                except (ValueError, csv.Error) as exc:
                    self._reject(line_no, str(exc))
                    continue
                if row[0] <= last_t:
                    self._reject(line_no, f"time {row[0]:g} s does not increase (previous {last_t:g} s)")
                    continue
                last_t = row[0]
                if len(first_times) <= TIME_CHECK_ROWS:
                    first_times.append(row[0])
                    first_lines.append(line_no)
                    if len(first_times) == TIME_CHECK_ROWS + 1:
                        self._check_time_steps(first_times, first_lines)
                self._complete(row)
                if math.isfinite(row[5]):
                    self.valid_temperatures += 1
                buf[fill] = row
                fill += 1
                report.rows_kept += 1
                if fill == self.block_rows:
                    yield self._block(buf)
                    fill = 0
        if len(first_times) <= TIME_CHECK_ROWS:
            self._check_time_steps(first_times, first_lines)
        if fill:
            yield self._block(buf[:fill])
        report.comment_or_blank_lines = comments
        report.rejected.sort()

    def _parse_row(self, fields: list[str], index: int) -> list[float]:
        """One data row (``index``: 0 first) -> [t_s, ref, x, y, z, temp, gx|psi, gy|theta, gz|nan, pose]; ValueError
        with the reason."""
        col = self.col
        counts = [self._value(fields, c) for c in COUNT_COLUMNS]
        if counts[0] <= 0:
            raise ValueError(f"ref_counts = {fields[col['ref_counts']].strip()} must be > 0")
        for name, value in zip(COUNT_COLUMNS, counts, strict=True):
            problem = iv.count_problem(name, value)  # the words of every input route (iv.SampleCheck)
            if problem:
                raise ValueError(problem)
        t, temp = self._time(fields, index), self._temperature(fields)
        if "psi_deg" in col:
            r = [iv.check_range(c, self._value(fields, c), -iv.ANGLE_LIMIT_DEG, iv.ANGLE_LIMIT_DEG, "deg")
                 for c in ANGLE_COLUMNS] + [math.nan]
        else:
            r = [iv.check_range(c, self._value(fields, c), -iv.FULL_SCALE_MPS2, iv.FULL_SCALE_MPS2, "m/s^2 (+-20 g)")
                 for c in GREF_COLUMNS]
        return [t, *counts, temp, *r, _pose(fields, col), math.nan, math.nan]

    def _value(self, fields: list[str], name: str, allow_empty: bool = False) -> float:
        """The number in column ``name`` (NaN for an empty or NaN cell if ``allow_empty``); ValueError naming it."""
        return _number(fields[self.col[name]], name, allow_empty)

    def _time(self, fields: list[str], index: int) -> float:
        """The row's time (s): its time column converted to s, else ``sample`` (or ``index``) / rate; ValueError
        outside the recordings' stamp range (with the ms / us hint for a t_s column)."""
        if self.time_column is not None:
            t = self._value(fields, self.time_column) * TIME_COLUMNS[self.time_column]
        elif "sample" in self.col:
            t = self._value(fields, "sample") / float(self.rate_hz)  # type: ignore[arg-type]
        else:
            t = index / float(self.rate_hz)  # type: ignore[arg-type]
        lo, hi = iv.TIME_RANGE_S
        if not lo <= t <= hi:
            hint = ("; if the times are ms or us (since 1970?), name the column t_ms or t_us"
                    if t > hi and self.time_column == "t_s" else "")
            raise ValueError(f"time {t:g} s is outside {lo:g} .. {hi:g} s (the recordings' stamp range){hint}")
        return t

    def _temperature(self, fields: list[str]) -> float:
        """The row's temperature (degC): its ``temperature_c`` cell (NaN for no reading; ValueError outside the
        AHT10 range, naming kelvin or Fahrenheit when it looks like them), else the constant given."""
        if "temperature_c" not in self.col:
            return float(self.temperature_c)  # type: ignore[arg-type]
        temp = self._value(fields, "temperature_c", allow_empty=True)
        if math.isfinite(temp):
            try:
                iv.check_range("temperature_c", temp, *iv.TEMPERATURE_RANGE_C, "degC (AHT10 range)")
            except ValueError as exc:
                raise ValueError(f"{exc}{iv.temperature_unit_hint(temp)}") from None
        return temp

    def _complete(self, row: list[float]) -> None:
        """Fill in (in place) what follows from the rows before: the reference from table angles, the pose id
        from changes of the reference."""
        if self.use_angles:
            g = tuple(float(v) for v in table_specific_force(np.array([row[6]]), np.array([row[7]]), self.g_mps2)[0])
            row[10:12] = row[6:8]  # the angles themselves, kept beside the reference (Recording.table_deg)
            row[6:9] = g
        else:
            g = (row[6], row[7], row[8])
        if "pose" not in self.col:
            if g != self._last_g:
                self._pose_counter += 1
            row[9] = self._pose_counter
        self._last_g = g

    def _check_time_steps(self, times: list[float], lines: list[int]) -> None:
        """Refuse a time column that is not in the unit its name says: the median step (s) of the first kept rows
        above ``MAX_MEDIAN_STEP_S`` (ms or us read as s). No check for ``sample`` / ``--rate`` (the user's rate)."""
        if self.time_column is None or len(times) < 2:
            return
        step = float(np.median(np.diff(times)))
        if step > MAX_MEDIAN_STEP_S:
            raise CsvImportError(
                f"{self.path}: {self.time_column}: the median step between the rows of lines {lines[0]}..{lines[-1]} "
                f"is {step:g} s ({1.0 / step:.3g} samples/s), but the board samples at 100 Hz: the times are probably "
                "not in seconds. Milliseconds: name the column t_ms; microseconds (the board's clock): name it t_us; "
                "a recording really slower than 1 sample/s: give a sample column and --rate")

    def _block(self, data: np.ndarray) -> Recording:
        return Recording(data[:, 0].copy(), data[:, 1].copy(), data[:, 2:5].copy(), data[:, 5].copy(),
                         data[:, 6:9].copy(), data[:, 9].astype(int), metadata={"source": str(self.path)},
                         table_deg=data[:, 10:12].copy() if self.use_angles else None)

    def check(self, drop_bad_rows: bool, *, drop_option: bool = False) -> None:
        """After a full pass: fail like :func:`import_csv` on rejected rows (unless ``drop_bad_rows``),
        on a file without data rows and on a temperature column without a single valid reading.
        ``drop_option``: the caller has a ``--drop-bad-rows`` option (``import``); the others are told to import
        the good rows with ``fbg-accel-calib import --drop-bad-rows`` and give the MCAP."""
        report = self.report
        if self.rejected_total and not drop_bad_rows:
            shown = report.rejected[:MAX_LISTED_ERRORS]
            more = self.rejected_total - len(shown)
            msg = "\n".join(f"  line {ln}: {why}" for ln, why in shown)
            remedy = "use --drop-bad-rows to import the others" if drop_option else self.REMEDY
            raise CsvImportError(f"{self.path}: {self.rejected_total} malformed row(s) (nothing imported; "
                                 f"{remedy}):\n{msg}"
                                 + (f"\n  ... and {more} more" if more else ""))
        if report.rows_kept == 0:
            raise CsvImportError(f"{self.path}: no valid data rows")
        if self.valid_temperatures == 0:
            raise CsvImportError(f"{self.path}: temperature_c is empty on every row, so no sample can be fitted; "
                                 "fill the column, or drop it and give the temperature with --temperature")

    def metadata(self) -> dict[str, Any]:
        return {"source": str(self.path), "import": self.report.as_dict(), "g_mps2": self.g_mps2}


class CsvSampleSource:
    """A CSV served as a ``fit_stream.SampleBlockSource`` (one run): every pass re-reads the file block by
    block, so the streamed fit of a CSV holds one block, never the file. After the first complete pass
    the rows are checked as :func:`import_csv` checks them (a malformed row fails the fit)."""

    def __init__(self, path: str | Path, *, rate_hz: float | None = None, temperature_c: float | None = None,
                 g_mps2: float = STANDARD_GRAVITY) -> None:
        self.csv = CsvBlocks(path, rate_hz=rate_hz, temperature_c=temperature_c, g_mps2=g_mps2)
        self._checked = False

    def blocks(self, block_rows: int, with_poses: bool) -> Iterator[Recording]:
        self.csv.block_rows = block_rows
        yield from self.csv.blocks()
        if not self._checked:
            self.csv.check(drop_bad_rows=False)
            self._checked = True

    def metadata(self) -> dict[str, Any]:
        return self.csv.metadata()


def import_csv(path: str | Path, *, rate_hz: float | None = None, temperature_c: float | None = None,
               g_mps2: float = STANDARD_GRAVITY, drop_bad_rows: bool = False) -> tuple[Recording, ImportReport]:
    """Read a CSV in the interchange format into a Recording (run_id 0) and an :class:`ImportReport`.

    Parsed block by block into arrays (:class:`CsvBlocks`): memory is the samples' arrays (80 bytes a
    row) plus one block, not Python objects per cell."""
    src = CsvBlocks(path, rate_hz=rate_hz, temperature_c=temperature_c, g_mps2=g_mps2)
    parts = list(src.blocks())
    src.check(drop_bad_rows)
    rec = join_blocks(parts)
    rec.metadata = src.metadata()
    return rec, src.report


def _pose(fields: list[str], col: dict[str, int]) -> float:
    if "pose" not in col:
        return -2.0
    value = _number(fields[col["pose"]], "pose")
    if value != int(value) or not -1 <= value <= iv.POSE_ID_MAX:
        raise ValueError(f"pose = {fields[col['pose']].strip()!r} must be an integer in -1 .. {iv.POSE_ID_MAX}")
    return value


def write_mcap(src: CsvBlocks, path: str | Path, metadata: dict[str, Any], sensor_id: str = "",
               drop_bad_rows: bool = False, start_ns: int | None = None) -> tuple[int, int, float | None]:
    """Stream a CSV into a calibration MCAP at ``path`` (as :func:`mcap_writer.write_recording` writes a
    Recording: a pose event at every change of pose or of a recorded pose's reference, ``pose_events``).
    Stamps are the file's own ``t_s * 1e9`` ns, or with ``start_ns`` (``import --start-time``) ``start_ns``
    plus the time since the first row;
    ``board_time_s`` in ``imu/raw`` keeps the file's ``t_s`` either way.

    Two passes over the CSV: the first checks every row and counts the poses (nothing is written when
    the import fails), the second writes block by block. Memory: one block. The ``run`` metadata
    record (``metadata`` plus the import report) is written at the end. Returns (messages written, poses,
    the first row's ``t_s`` in s or None for an empty file).
    """
    from .mcap_writer import RecordingWriter, write_samples

    n_poses = max((int(blk.pose_id.max()) + 1 for blk in src.blocks() if len(blk)), default=0)
    src.check(drop_bad_rows, drop_option=True)
    with RecordingWriter(path, None) as w:
        shift, first_t_s = write_samples(w, src.blocks(), n_poses, sensor_id, start_ns=start_ns, where=f"{src.path}: ")
        w.add_metadata("run", {**metadata, "import": src.report.as_dict(), "g_mps2": src.g_mps2,
                               "stamp_offset_ns": shift})
        return w.message_count, n_poses, first_t_s


def _blank_or_comment(text: str) -> bool:
    """A line that holds no data: empty, only commas and spaces (an empty spreadsheet row), or a ``#`` comment."""
    return not text.replace(",", "").strip() or text.lstrip().startswith("#")


def _check_delimiter(path: Path, header: list[str], text: str, line_no: int, required: tuple[str, ...]) -> None:
    """Refuse a header separated by semicolons or tabs (a spreadsheet set to a decimal comma writes ';' and
    '1,5'), naming the separator, instead of reporting every ``required`` column as missing."""
    if any(c in header for c in required):
        return
    for sep, name in ((";", "semicolons"), ("\t", "tabs")):
        names = [h.strip().strip('"').strip().lower() for h in text.split(sep)]
        if any(c in names for c in required):
            decimal = ", decimal=','" if sep == ";" else ""
            raise CsvImportError(
                f"{path}: line {line_no}: the columns are separated by {name}, not commas (a spreadsheet set to a "
                "decimal comma saves CSV this way); save the file as comma-separated values with a decimal point "
                f"(e.g. pandas: pd.read_csv(f, sep={sep!r}{decimal}).to_csv(out, index=False))")
