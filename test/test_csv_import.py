"""CSV interchange import: columns, references, time base, malformed rows with line numbers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fbg_accel_calibration.commands.cli import main as cli_main
from fbg_accel_calibration.io.csv_import import CsvImportError, import_csv
from fbg_accel_calibration.io.mcap_reader import read_recording
from fbg_accel_calibration.io.table_geometry import table_specific_force


def _write(tmp_path: Path, text: str, name: str = "in.csv") -> Path:
    p = tmp_path / name
    p.write_bytes(text.encode("utf-8"))  # the bytes as given: line ends are what some tests are about
    return p


GOOD = """# calibration export
t_s,ref_counts,x_counts,y_counts,z_counts,gref_x_mps2,gref_y_mps2,gref_z_mps2,temperature_c,pose,comment
0.00,880,1138,1649,1216,0,0,9.8,23.4,0,a

0.01,881,1137,1650,1215,0,0,9.8,,0,b
0.02,879,1200,1600,1100,9.8,0,0,23.5,1,c
"""


def test_full_format(tmp_path: Path) -> None:
    rec, report = import_csv(_write(tmp_path, GOOD))
    assert len(rec) == 3 and report.rows_kept == 3 and not report.rejected
    np.testing.assert_array_equal(rec.t_s, [0.0, 0.01, 0.02])
    np.testing.assert_array_equal(rec.ref, [880, 881, 879])
    np.testing.assert_array_equal(rec.xyz[2], [1200, 1600, 1100])
    np.testing.assert_array_equal(rec.gref_mps2[2], [9.8, 0.0, 0.0])
    assert np.isnan(rec.temp_c[1]) and rec.temp_c[2] == 23.5  # empty cell: no valid reading
    np.testing.assert_array_equal(rec.pose_id, [0, 0, 1])
    assert report.ignored_columns == ["comment"]
    assert rec.table_deg is None  # a reference given as a vector: no table angles
    assert report.comment_or_blank_lines == 2


def test_angles_rate_and_constant_temperature(tmp_path: Path) -> None:
    text = "sample,ref_counts,x_counts,y_counts,z_counts,psi_deg,theta_deg\n"
    rows = [(0, 0, 0), (1, 0, 0), (2, 15, 30), (3, 30, 30), (4, 30, 30)]
    text += "".join(f"{s},880,1100,1600,1200,{p},{t}\n" for s, p, t in rows)
    path = _write(tmp_path, text)
    with pytest.raises(CsvImportError, match="--rate"):
        import_csv(path, temperature_c=23.4)
    with pytest.raises(CsvImportError, match="--temperature"):
        import_csv(path, rate_hz=100.0)
    rec, report = import_csv(path, rate_hz=100.0, temperature_c=23.4, g_mps2=9.81)
    np.testing.assert_allclose(rec.t_s, np.arange(5) / 100.0)
    np.testing.assert_array_equal(rec.temp_c, 23.4)
    expected = table_specific_force(np.array([0, 0, 15, 30, 30.0]), np.array([0, 0, 30, 30, 30.0]), 9.81)
    np.testing.assert_allclose(rec.gref_mps2, expected)
    np.testing.assert_array_equal(rec.pose_id, [0, 0, 1, 2, 2])  # a new pose at every change of the reference
    assert "sample column / 100.0 Hz" in report.time_base
    # the angles themselves are kept for the diagnosis (a table offset is a suspect: table_theta_offset)
    np.testing.assert_array_equal(rec.table_deg, [[0, 0], [0, 0], [15, 30], [30, 30], [30, 30]])


def test_malformed_rows_are_reported_with_line_numbers(tmp_path: Path) -> None:
    text = (
        "t_s,ref_counts,x_counts,y_counts,z_counts,gref_x_mps2,gref_y_mps2,gref_z_mps2,temperature_c\n"  # line 1
        "0.00,880,1,2,3,0,0,9.8,20\n"  # 2 ok
        "0.01,880,1,2,3,0,0,9.8\n"  # 3 too few fields
        "# a comment\n"  # 4
        "0.02,880,abc,2,3,0,0,9.8,20\n"  # 5 not a number
        "0.03,0,1,2,3,0,0,9.8,20\n"  # 6 ref 0
        "0.04,880,1,-2,3,0,0,9.8,20\n"  # 7 negative count
        "0.05,880,1,2,3,0,inf,9.8,20\n"  # 8 not finite
        "0.06,880,1,2,3,0,0,9.8,20\n"  # 9 ok
        "0.06,880,1,2,3,0,0,9.8,20\n"  # 10 time does not increase
        "0.07,880,1,2,,0,0,9.8,20\n"  # 11 empty required value
        "0.08,880,1,2,3,0,0,9.8,20\n"  # 12 ok
    )
    path = _write(tmp_path, text)
    with pytest.raises(CsvImportError) as err:
        import_csv(path)
    msg = str(err.value)
    assert "7 malformed row(s)" in msg and "nothing imported" in msg
    for line, why in ((3, "8 fields, header has 9"), (5, "x_counts = 'abc' is not a number"), (6, "ref_counts = 0 must be > 0"),
                      (7, "y_counts = -2 is negative"), (8, "not finite"), (10, "does not increase"), (11, "z_counts is empty")):
        assert f"line {line}: " in msg and why in msg, (line, why)
    assert "line 2:" not in msg and "line 9:" not in msg and "line 12:" not in msg
    rec, report = import_csv(path, drop_bad_rows=True)
    np.testing.assert_array_equal(rec.t_s, [0.0, 0.06, 0.08])
    assert [ln for ln, _ in report.rejected] == [3, 5, 6, 7, 8, 10, 11]
    assert report.rows_read == 10 and report.rows_kept == 3
    assert "line 10: time 0.06 s does not increase" in report.summary()
    assert len(rec.metadata["import"]["rejected"]) == 7


@pytest.mark.parametrize(("header", "match"), [
    ("t_s,ref_counts,x_counts,y_counts,gref_x_mps2,gref_y_mps2,gref_z_mps2,temperature_c",
     r"missing required column\(s\) \['z_counts'\]"),
    ("t_s,ref_counts,x_counts,y_counts,z_counts,temperature_c", "no reference"),
    ("t_s,ref_counts,x_counts,y_counts,z_counts,gref_x_mps2,gref_y_mps2,temperature_c", "incomplete reference"),
    ("t_s,ref_counts,x_counts,y_counts,z_counts,psi_deg,temperature_c", "incomplete reference"),
    ("t_s,ref_counts,x_counts,y_counts,z_counts,psi_deg,theta_deg,gref_x_mps2,gref_y_mps2,gref_z_mps2,temperature_c",
     "not both"),
    ("t_s,ref_counts,ref_counts,x_counts,y_counts,z_counts,psi_deg,theta_deg,temperature_c", "duplicate column"),
])
def test_header_errors(tmp_path: Path, header: str, match: str) -> None:
    with pytest.raises(CsvImportError, match=match):
        import_csv(_write(tmp_path, header + "\n"))


def test_bad_pose_and_missing_file(tmp_path: Path) -> None:
    text = "t_s,ref_counts,x_counts,y_counts,z_counts,psi_deg,theta_deg,temperature_c,pose\n0,880,1,2,3,0,0,20,1.5\n"
    with pytest.raises(CsvImportError, match=r"line 2: pose = '1\.5' must be an integer"):
        import_csv(_write(tmp_path, text))
    with pytest.raises(CsvImportError, match="file not found"):
        import_csv(tmp_path / "absent.csv")


def test_cli_import_round_trip_to_mcap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out.mcap"
    assert cli_main(["import", str(_write(tmp_path, GOOD)), "-o", str(out), "--sensor-id", "s-1", "--notes", "bench A"]) == 0
    rec = read_recording(out)
    np.testing.assert_array_equal(rec.xyz[:, 0], [1138, 1137, 1200])
    np.testing.assert_array_equal(rec.pose_id, [0, 0, 1])
    assert rec.metadata["run"]["sensor_id"] == "s-1" and rec.metadata["run"]["operator_notes"] == "bench A"
    header = "t_s,ref_counts,x_counts,y_counts,z_counts,psi_deg,theta_deg,temperature_c\n"
    bad = _write(tmp_path, header + "0,880,x,2,3,0,0,20\n", "bad.csv")
    assert cli_main(["import", str(bad), "-o", str(tmp_path / "bad.mcap")]) == 2
    assert "line 2: x_counts = 'x' is not a number" in capsys.readouterr().err
    assert not (tmp_path / "bad.mcap").exists()


def test_times_that_collide_at_nanosecond_resolution_are_refused(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """Strictly increasing in the file, the same stamp once rounded to ns: the writer refuses, nothing is left."""
    collide = _write(tmp_path, GOOD.replace("0.01,881", "0.0000000001,881"), "ns.csv")
    assert cli_main(["import", str(collide), "-o", str(tmp_path / "ns.mcap")]) == 2
    assert "ns.csv: times 0 ns and 0 ns are not strictly increasing at nanosecond resolution" in capsys.readouterr().err
    assert not (tmp_path / "ns.mcap").exists()


def _raw_log_times(path: Path) -> list[int]:
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        return [m.log_time for _, _, m in make_reader(fh).iter_messages(topics=["/imu/raw"])]


def test_import_start_time_places_the_recording_in_real_time(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """issue 10: import wrote every recording on 1970-01-01; --start-time gives the first row's ROS time."""
    csv = _write(tmp_path, GOOD)
    rec, _ = import_csv(csv)
    out = tmp_path / "a.mcap"
    assert cli_main(["import", str(csv), "-o", str(out), "--start-time", "2026-11-20T09:30:00Z"]) == 0
    start = 1_795_167_000 * 10**9  # 2026-11-20T09:30:00Z
    stamps = np.array(_raw_log_times(out))
    np.testing.assert_array_equal(stamps - start, np.round((rec.t_s - rec.t_s[0]) * 1e9).astype(np.int64))
    back = read_recording(out)
    np.testing.assert_allclose(back.t_s, rec.t_s)  # board time keeps the file's own t_s
    assert "1970" not in capsys.readouterr().err
    # without --start-time: the file's own times, and a note that they are relative
    assert cli_main(["import", str(csv), "-o", str(tmp_path / "b.mcap")]) == 0
    assert _raw_log_times(tmp_path / "b.mcap")[0] == round(rec.t_s[0] * 1e9)
    assert "give --start-time" in capsys.readouterr().err
    for bad in ("2026-11-20T09:30:00", "yesterday", "-5", "3e9"):
        with pytest.raises(SystemExit) as info:
            cli_main(["import", str(csv), "-o", str(tmp_path / "c.mcap"), "--start-time", bad])
        assert info.value.code == 2
        assert "--start-time" in capsys.readouterr().err
    assert not (tmp_path / "c.mcap").exists()


def test_import_and_diagnose_have_the_same_rate_rule(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """issue 10: a CSV without t_s needs --rate in every subcommand (diagnose silently assumed 1 Hz)."""
    from fbg_accel_calibration.commands.diagnose_cli import main as diagnose_main

    lines = [ln for ln in GOOD.splitlines() if ln and not ln.startswith("#")]
    keep = [i for i, c in enumerate(lines[0].split(",")) if c != "t_s"]
    no_time = _write(tmp_path, "\n".join(",".join(ln.split(",")[i] for i in keep) for ln in lines) + "\n", "nt.csv")
    assert cli_main(["import", str(no_time), "-o", str(tmp_path / "x.mcap")]) == 2
    assert "give the sample rate (--rate" in capsys.readouterr().err
    assert diagnose_main(["diagnose", str(no_time)]) == 2
    assert "give the sample rate (--rate" in capsys.readouterr().err


# ---------------------------------------------------------------------------- files from other software


def _data_lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]


def _requote(text: str, cell) -> str:
    """Every non-comment line of ``text`` with each field (header included) rewritten by ``cell(i_line, field)``."""
    out = []
    for ln in text.splitlines():
        out.append(ln if not ln.strip() or ln.startswith("#") else
                   ",".join(cell(i, f) for i, f in enumerate(ln.split(","))))
    return "\n".join(out) + "\n"


def _with_index(text: str) -> str:
    """pandas ``to_csv()``: the index as a first column with an empty name."""
    out, k = [], -1
    for ln in text.splitlines():
        if ln.strip() and not ln.startswith("#"):
            out.append(("" if k < 0 else str(k)) + "," + ln)
            k += 1
        else:
            out.append(ln)
    return "\n".join(out) + "\n"


def _sci(field: str) -> str:
    try:
        v = float(field)
    except ValueError:
        return field
    return f"{v:.6e}" if "." in field else f"{v:.1f}"  # 1.380000e+03 and integers written as 1138.0


SPREADSHEET_EXPORTS = {
    # Excel "CSV UTF-8" on Windows: a byte-order mark and CRLF line ends
    "bom_crlf": lambda t: "\ufeff" + t.replace("\n", "\r\n"),
    # Excel with formatted but empty columns to the right: every line, header included, ends in commas,
    # and an empty row of the sheet is a line of commas
    "trailing_empty_columns": lambda t: "\n".join(ln + ",," if ln.strip() else ",,,,,,,,,,,," for ln in t.splitlines())
    + "\n",
    # pandas to_csv() with its index: a first column with an empty name
    "pandas_index": lambda t: _with_index(t),
    # every field quoted, header included (MATLAB writetable with QuoteStrings, LibreOffice "quote all")
    "quoted": lambda t: _requote(t, lambda i, f: f'"{f}"'),
    # a hand-edited header: spaces after the commas, upper-case names
    "padded_upper_header": lambda t: t.replace(_data_lines(t)[0], ", ".join(
        f" {h.upper()} " for h in _data_lines(t)[0].split(","))),
    # numbers written by other tools: scientific notation, integers as 1138.0
    "scientific_and_float_integers": lambda t: _requote(t, lambda i, f: _sci(f)),
}


@pytest.mark.parametrize("variant", sorted(SPREADSHEET_EXPORTS))
def test_spreadsheet_and_dataframe_exports_import_like_the_plain_file(tmp_path: Path, variant: str) -> None:
    """The same data as written by Excel, pandas, MATLAB or by hand gives the same recording.

    On the unchanged code two of these were refused: two or more empty trailing columns gave "duplicate column(s)
    ['']" (an empty header cell is no column name), and an upper-case header gave "missing required column(s)
    ['ref_counts', 'x_counts', 'y_counts', 'z_counts']" with those columns in the file."""
    want, _ = import_csv(_write(tmp_path, GOOD, "plain.csv"))
    text = SPREADSHEET_EXPORTS[variant](GOOD)
    got, report = import_csv(_write(tmp_path, text, "v.csv"))
    for k in ("t_s", "ref", "xyz", "temp_c", "gref_mps2", "pose_id"):
        np.testing.assert_allclose(getattr(got, k), getattr(want, k), rtol=1e-12, err_msg=k)
    assert report.rows_kept == 3 and not report.rejected
    assert "" not in report.ignored_columns  # an unnamed column is shown by its position
    if variant in ("trailing_empty_columns", "pandas_index"):
        assert any("unnamed column" in c for c in report.ignored_columns), report.ignored_columns


@pytest.mark.parametrize(("sep", "decimal"), [(";", "."), (";", ","), ("\t", ".")])
def test_semicolon_or_tab_separated_files_are_refused_with_what_to_do(tmp_path: Path, sep: str, decimal: str) -> None:
    """European Excel writes 'a;b' with decimal commas. On the unchanged code the header read as one column and the
    message was "missing required column(s) ['ref_counts', 'x_counts', 'y_counts', 'z_counts']"."""
    text = "\n".join(ln.replace(".", decimal).replace(",", sep) if decimal == "," else ln.replace(",", sep)
                     for ln in GOOD.splitlines()) + "\n"
    with pytest.raises(CsvImportError, match=r"line 2: the columns are separated by (semicolons|tabs), not commas") as err:
        import_csv(_write(tmp_path, text))
    assert "decimal point" in str(err.value)


@pytest.mark.parametrize("size", ["small", "large"])
def test_bare_carriage_return_line_ends_are_named(tmp_path: Path, size: str) -> None:
    """Old Mac OS line ends (CR only). On the unchanged code a small file raised _csv.Error with a traceback
    ("new-line character seen in unquoted field") and a file over 64 KiB said "header line is not UTF-8 text or too
    long". A file that starts with a comment line was one long comment line to the header search: "no header line
    (expected column names such as ref_counts, x_counts, y_counts, z_counts)", with the columns in the file."""
    with pytest.raises(CsvImportError, match=r"line 1: .*carriage return"):
        import_csv(_write(tmp_path, GOOD.replace("\n", "\r"), "commented_cr.csv"))
    lines = _data_lines(GOOD)
    if size == "large":
        lines += [f"{0.03 + 0.01 * k:.2f},880,1138,1649,1216,0,0,9.8,23.4,0,a" for k in range(3000)]
    path = tmp_path / "cr.csv"
    path.write_bytes("\r".join(lines).encode() + b"\r")
    with pytest.raises(CsvImportError, match=r"line 1: .*carriage return"):
        import_csv(path)
    # one CR inside an otherwise LF file: that line is a malformed row with the same reason, not a csv module message
    text = GOOD.replace("0.02,879", "0.015,879,1200,1600,1100,9.8,0,0,23.5,1,c\r0.02,879")
    with pytest.raises(CsvImportError, match=r"line 6: .*carriage return"):
        import_csv(_write(tmp_path, text))


def _timed(times: list[str], column: str = "t_s") -> str:
    rows = "".join(f"{t},880,1138,1649,1216,0,0,9.8,23.4,0\n" for t in times)
    return f"{column},ref_counts,x_counts,y_counts,z_counts,gref_x_mps2,gref_y_mps2,gref_z_mps2,temperature_c,pose\n" + rows


def test_times_that_are_not_seconds_are_refused_or_read_by_their_column_name(tmp_path: Path) -> None:
    """A 100 Hz run with t_s in ms or us (the board's own clock is us since boot). On the unchanged code it was read
    as seconds without a word: steps of 10 s (10000 s), and `fit` wrote a noise correlation time constant of
    107.27 / 127.02 / 191.49 s instead of 0.107 / 0.127 / 0.191 s into the calibration (the three-level simulated
    campaign), `allan` gave its ADEV at 0.1 Hz. Named t_ms / t_us the column is converted."""
    k = np.arange(300)
    want, _ = import_csv(_write(tmp_path, _timed([f"{0.01 * i:.2f}" for i in k]), "s.csv"))
    for scale, unit in ((1e3, "t_ms"), (1e6, "t_us")):
        values = [f"{0.01 * i * scale:.0f}" for i in k]
        with pytest.raises(CsvImportError, match=rf"t_s: the median step .* is {0.01 * scale:g} s.*name the column "
                                                 r"t_ms.*t_us"):
            import_csv(_write(tmp_path, _timed(values), f"{unit}_as_s.csv"))
        got, report = import_csv(_write(tmp_path, _timed(values, unit), f"{unit}.csv"))
        np.testing.assert_allclose(got.t_s, want.t_s, rtol=0, atol=1e-12)
        assert unit in report.time_base and unit not in report.ignored_columns
    # seconds since 1970 stay what they are; so do 1 s steps (time counted in samples, as --rate 1)
    epoch, _ = import_csv(_write(tmp_path, _timed([f"{1.7e9 + 0.01 * i:.2f}" for i in k]), "epoch.csv"))
    np.testing.assert_allclose(epoch.t_s - 1.7e9, want.t_s, atol=1e-6)
    ones, _ = import_csv(_write(tmp_path, _timed([str(i) for i in k]), "ones.csv"))
    np.testing.assert_array_equal(ones.t_s, k)
    # milliseconds since 1970 are beyond any time in seconds: the message says which column to use
    with pytest.raises(CsvImportError, match=r"line 2: time 1\.7e\+12 s is outside .* t_ms"):
        import_csv(_write(tmp_path, _timed([f"{1.7e12 + 10 * i:.0f}" for i in k]), "epoch_ms.csv"))
    with pytest.raises(CsvImportError, match="one time column"):
        import_csv(_write(tmp_path, _timed(["0"]).replace("t_s,", "t_s,t_ms,").replace("0,880", "0,0,880"), "two.csv"))


def test_temperature_no_reading_and_other_units(tmp_path: Path) -> None:
    """MATLAB and numpy write a missing reading as NaN, pandas as an empty cell: both mean "no valid reading". A
    temperature in kelvin or Fahrenheit above the AHT10 range is refused with the unit it looks like. On the unchanged
    code 'NaN' was a malformed row ("temperature_c = 'NaN' is not finite") and 297.34 K was "outside -40 .. 85 degC
    (AHT10 range)" with no hint. (Fahrenheit readings within -40 .. 85, i.e. below 29.4 degC, cannot be told apart
    from Celsius: docs/csv_interchange.md.)"""
    rec, report = import_csv(_write(tmp_path, GOOD.replace("0.01,881,1137,1650,1215,0,0,9.8,,0",
                                                           "0.01,881,1137,1650,1215,0,0,9.8,NaN,0")))
    assert np.isnan(rec.temp_c[1]) and not report.rejected
    with pytest.raises(CsvImportError, match=r"line 3: temperature_c = 296\.55 is outside .*kelvin"):
        import_csv(_write(tmp_path, GOOD.replace(",23.4,", ",296.55,"), "k.csv"))
    with pytest.raises(CsvImportError, match=r"line 6: temperature_c = 113 is outside .*Fahrenheit"):
        import_csv(_write(tmp_path, GOOD.replace(",23.5,", ",113,"), "f.csv"))
