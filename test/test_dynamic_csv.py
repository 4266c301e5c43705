"""The dynamic-run CSV is read by the static importer's rules (issue 12, "one path for each job"): the exports of
spreadsheets and dataframes that ``csv_import`` reads or refuses with what to do are read or refused the same way
when they hold a dynamic run (docs/csv_interchange.md, "Dynamic runs")."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_csv_import import SPREADSHEET_EXPORTS, _write

from fbg_accel_calibration.io.dynamic_csv import DynamicCsvError, read_dynamic_csv, write_dynamic_csv

# a slide run at 500 Hz: 40 rows, one comment line, one blank line, the temperature column last
ROWS = [f"{0.002 * i:.3f},2000,{1500 + i},{1600 - i},1700,{2048 + 3 * i},{24.0 + 0.01 * i:.2f}" for i in range(40)]
GOOD = "# slide run\nt_s,ref,x,y,z,aux,temperature_c\n" + "\n".join(ROWS[:20]) + "\n\n" + "\n".join(ROWS[20:]) + "\n"


@pytest.mark.parametrize("variant", sorted(SPREADSHEET_EXPORTS))
def test_spreadsheet_exports_of_a_dynamic_run_read_like_the_plain_file(tmp_path: Path, variant: str) -> None:
    """On the unchanged reader (its own csv.reader per line, case-sensitive names): the upper-case header was
    "missing column(s) ['t_s', 'ref', 'x', 'y', 'z', 'aux']", a line of commas was "line 13: t_s, ref, x, y, z and
    aux must be finite numbers"; BOM + CRLF, the pandas index and the quoted header were read. The exports are
    test_csv_import's, which the calibration CSV reads alike."""
    want = read_dynamic_csv(_write(tmp_path, GOOD, "plain.csv"))
    got = read_dynamic_csv(_write(tmp_path, SPREADSHEET_EXPORTS[variant](GOOD)))
    for k in ("t_s", "ref", "xyz", "aux", "temp_c"):
        np.testing.assert_array_equal(getattr(got, k), getattr(want, k), err_msg=k)
    assert len(got) == len(ROWS)


def test_bare_carriage_return_line_ends_are_refused_naming_the_line(tmp_path: Path) -> None:
    """On the unchanged reader (the file opened with newline='', which splits lines at a bare CR) the file was read
    as if its lines ended in LF; one CR inside line 8 split that row in two, reported as "line 8: 2 fields, header has
    7" and "line 9: 6 fields, header has 7" (a line 9 that holds the next row), instead of naming the line end."""
    with pytest.raises(DynamicCsvError, match=r"line 1: .*carriage return"):
        read_dynamic_csv(_write(tmp_path, GOOD.replace("\n", "\r")))
    text = GOOD.replace(ROWS[5], ROWS[5][:9] + "\r" + ROWS[5][9:])
    with pytest.raises(DynamicCsvError, match=r"line 8: .*carriage return"):
        read_dynamic_csv(_write(tmp_path, text))


@pytest.mark.parametrize("sep", [";", "\t"])
def test_semicolon_or_tab_separated_dynamic_runs_are_refused_with_what_to_do(tmp_path: Path, sep: str) -> None:
    """On the unchanged reader: "missing column(s) ['t_s', 'ref', 'x', 'y', 'z', 'aux'] ... found
    ['t_s;ref;x;y;z;aux;temperature_c']", with no word about the separator."""
    with pytest.raises(DynamicCsvError, match=r"line 2: the columns are separated by (semicolons|tabs), not commas"):
        read_dynamic_csv(_write(tmp_path, GOOD.replace(",", sep)))


def test_dynamic_run_times_that_are_not_seconds_are_refused_or_read_by_their_column_name(tmp_path: Path) -> None:
    """t_s written in ms (steps of 2 for a 500 Hz run). On the unchanged reader it was read as seconds without a word
    (a run 1000x longer: every excitation segment missed), and a t_ms or t_us column was "missing column(s)
    ['t_s']"."""
    want = read_dynamic_csv(_write(tmp_path, GOOD, "plain.csv"))
    for scale, unit in ((1e3, "t_ms"), (1e6, "t_us")):
        text = "t_s,ref,x,y,z,aux,temperature_c\n" + "".join(
            f"{0.002 * i * scale:.0f}{r[r.index(','):]}\n" for i, r in enumerate(ROWS))
        with pytest.raises(DynamicCsvError, match=rf"t_s: the median step .* is {0.002 * scale:g} s.*t_ms.*t_us"):
            read_dynamic_csv(_write(tmp_path, text, f"{unit}_as_s.csv"))
        got = read_dynamic_csv(_write(tmp_path, text.replace("t_s,", f"{unit},", 1), f"{unit}.csv"))
        np.testing.assert_allclose(got.t_s, want.t_s, rtol=0, atol=1e-12)


def test_dynamic_run_temperatures_no_reading_and_other_units(tmp_path: Path) -> None:
    """NaN and an empty cell are "no valid reading" (both were read as NaN before, too). On the unchanged reader a
    temperature in kelvin was read as degC without a word (temp_c[0] = 297.15: no range check at all), and a column
    empty on every row was read as 40 NaN temperatures, refused only later by the fit ("no valid temperature in the
    recording") with no word about the file's column or --temperature."""
    rec = read_dynamic_csv(_write(tmp_path, GOOD.replace(ROWS[3][-5:] + "\n", "NaN\n").replace(
        ROWS[4][-5:] + "\n", "\n")))
    assert np.isnan(rec.temp_c[3:5]).all() and np.isfinite(rec.temp_c[5:]).all()
    with pytest.raises(DynamicCsvError, match=r"line 3: temperature_c = 297\.15 is outside .*kelvin"):
        read_dynamic_csv(_write(tmp_path, GOOD.replace(",24.00\n", ",297.15\n")))
    with pytest.raises(DynamicCsvError, match="temperature_c is empty on every row"):
        read_dynamic_csv(_write(tmp_path, GOOD.splitlines()[1] + "\n" + "".join(r[:r.rindex(",") + 1] + "\n" for r in ROWS)))


def test_written_dynamic_csv_reads_back(tmp_path: Path) -> None:
    """write_dynamic_csv's output is read back to the same samples (the format's round trip)."""
    rec = read_dynamic_csv(_write(tmp_path, GOOD))
    out = tmp_path / "again.csv"
    write_dynamic_csv(out, rec)
    again = read_dynamic_csv(out)
    for k in ("t_s", "ref", "xyz", "aux", "temp_c"):
        np.testing.assert_allclose(getattr(again, k), getattr(rec, k), rtol=0, atol=1e-9, err_msg=k)
