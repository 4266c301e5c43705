"""CSV interchange import: columns, references, time base, malformed rows with line numbers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fbg_accel_calibration.cli import main as cli_main
from fbg_accel_calibration.csv_import import CsvImportError, import_csv
from fbg_accel_calibration.mcap_io import read_recording
from fbg_accel_calibration.table_geometry import table_specific_force


def _write(tmp_path: Path, text: str, name: str = "in.csv") -> Path:
    p = tmp_path / name
    p.write_text(text)
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
    from fbg_accel_calibration.diagnose_cli import main as diagnose_main

    lines = [ln for ln in GOOD.splitlines() if ln and not ln.startswith("#")]
    keep = [i for i, c in enumerate(lines[0].split(",")) if c != "t_s"]
    no_time = _write(tmp_path, "\n".join(",".join(ln.split(",")[i] for i in keep) for ln in lines) + "\n", "nt.csv")
    assert cli_main(["import", str(no_time), "-o", str(tmp_path / "x.mcap")]) == 2
    assert "give the sample rate (--rate" in capsys.readouterr().err
    assert diagnose_main(["diagnose", str(no_time)]) == 2
    assert "give the sample rate (--rate" in capsys.readouterr().err
