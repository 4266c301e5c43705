"""Issue 11, "wrong calibrations written with exit 0" and "inputs that give tracebacks": every hostile
input is refused with exit 2 and one line naming the file/option, the field and what to do."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from fbg_accel_calibration.commands.cli import main
from fbg_accel_calibration.io.csv_import import import_csv
from fbg_accel_calibration.io.mcap_writer import write_recording
from fbg_accel_sim.board_physics import simulate_recording
from fbg_accel_sim.sim_config import SimConfig

MEASURED = Path(__file__).resolve().parents[2] / "shared" / "data" / "measured" / "fig13_multiposition_23C.csv"
MEASURED_OPTS = ["--rate", "1", "--temperature", "23.4", "--g", "9.81"]
HEADER = "t_s,ref_counts,x_counts,y_counts,z_counts,gref_x_mps2,gref_y_mps2,gref_z_mps2,temperature_c,pose\n"
SIX = ["0,0,9.8", "0,0,-9.8", "9.8,0,0", "-9.8,0,0", "0,9.8,0", "0,-9.8,0"]


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """``main(argv)`` in process: (exit code, stderr); argparse usage errors give SystemExit(2)."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:
        rc = exc.code
    err = capsys.readouterr().err
    return rc, err


def one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def six_pose_csv(path: Path, row: str | None = None, at: int = 7) -> Path:
    """A six-pose CSV (50 samples a pose, sensor-like counts); ``row`` replaces data row ``at``."""
    rng = np.random.default_rng(0)
    rows, i = [], 0
    for p, g in enumerate(SIX):
        gx, gy, gz = (float(v) for v in g.split(","))
        for _ in range(50):
            c = np.array([1000 + 80 * gx, 1500 + 80 * gy, 1200 + 80 * gz]) + rng.normal(0, 0.5, 3)
            rows.append(f"{i * 0.01:.2f},880,{c[0]:.2f},{c[1]:.2f},{c[2]:.2f},{g},23.4,{p}\n")
            i += 1
    if row is not None:
        rows[at] = row + "\n"
    path.write_text(HEADER + "".join(rows))
    return path


# ---------------------------------------------------------------------------- rank / conditioning


def test_coplanar_measured_poses_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The measured series restricted to psi = 0 (one tilt axis): every pose has f_x = 0. The old code wrote
    an x row of M, b and noise of zero with exit 0."""
    assert MEASURED.is_file(), f"measured data not found: {MEASURED}"
    lines = MEASURED.read_text().splitlines()
    kept = [lines[0]] + [ln for ln in lines[1:] if ln.split(",")[5] == "0.0"]
    csv = tmp_path / "theta_only.csv"
    csv.write_text("\n".join(kept) + "\n")
    out = tmp_path / "cal.yaml"
    rc, err = run(["fit", csv, "-o", out, *MEASURED_OPTS], capsys)
    line = one_line(err)
    assert rc == 2 and "coplanar" in line and "the x row of M" in line and "theta_only.csv" in line
    assert not out.exists()
    rc, err = run(["diagnose", csv, *MEASURED_OPTS, "--yaml", tmp_path / "d.yaml"], capsys)
    assert rc == 2 and "coplanar" in one_line(err) and not (tmp_path / "d.yaml").exists()
    # the whole series spans the frame and still fits
    rc, _ = run(["fit", MEASURED, "-o", out, *MEASURED_OPTS], capsys)
    assert rc == 0 and out.is_file()


def test_a_plan_that_never_points_an_axis_down_is_fitted_with_a_warning(tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """Poses that tilt x by 8 degrees at most (z and y up and down, x at +-1.36 m/s^2): enough spread to identify the
    x row (0.96 m/s^2 RMS > 0.49), so the fit is accepted, and its pose hold-out is at the noise floor (x 0.18 m/s^2),
    but the calibration extrapolates eq. 28 to x = +-g over a response it never saw. Measured against the simulator's
    truth (three levels 16 / 24 / 45 degC, probe of 2026-11-26) its error at x down was 0.42 m/s^2 (0.12 with the
    six-position plan); a plan that never points x down (a 30-degree grid with f_x >= 0) gave 0.36. The unchanged
    code said nothing (no warning, no field). The YAML now records each table axis' range of reference and the fit
    warns, naming the axis and the direction, when the poses do not reach half of g both ways."""
    poses = [[0.0, 0.0], [0.0, 180.0], [0.0, 90.0], [180.0, 90.0], [90.0, 8.0], [270.0, 8.0], [90.0, 172.0],
             [270.0, 172.0]]
    cfg = SimConfig.default().with_overrides({
        "scenario.rate_hz": 25.0, "scenario.poses.mode": "list", "scenario.poses.list": poses,
        "scenario.poses.dwell_s": 10.0, "scenario.poses.move_s": 3.0, "scenario.poses.repeat": 1})
    mcap = tmp_path / "x_flat.mcap"
    write_recording(mcap, simulate_recording(cfg, seed=1), {"sensor_id": "sim"})
    out = tmp_path / "cal.yaml"
    rc, err = run(["fit", mcap, "-o", out], capsys)
    assert rc == 0 and out.is_file()
    warned = [ln for ln in err.splitlines() if "never reach" in ln]
    assert len(warned) == 1 and "table x axis" in warned[0] and "-1.36 .. +1.36 m/s^2" in warned[0], err
    fit = yaml.safe_load(out.read_text())["fit"]
    np.testing.assert_allclose(fit["reference_range_mps2"][0], [-1.365, 1.365], atol=0.01)
    np.testing.assert_allclose(fit["reference_range_mps2"][1:], [[-9.807, 9.807]] * 2, atol=0.01)
    # diagnose writes a calibration from the same poses and says so too (before: nothing; on a 30-degree grid without
    # x down it added a spectral non-linearity fitted on x >= 0 only, 6.9 m/s^2 off the truth at x down and 45 degC)
    report = tmp_path / "diag.md"
    rc, err = run(["diagnose", mcap, "--out", report, "--yaml", tmp_path / "diag.yaml"], capsys)
    assert rc == 0
    said = err.splitlines() + (report.read_text().splitlines() if report.is_file() else [])
    assert any("never reach" in ln and "table x axis" in ln for ln in said), err
    # the six positions reach +-g on every axis: no such warning
    rc, err = run(["fit", six_pose_csv(tmp_path / "six.csv"), "-o", tmp_path / "six.yaml"], capsys)
    assert rc == 0 and "never reach" not in err, err


def test_six_position_run_cut_after_its_fourth_pose_is_refused(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    """z down, z up, x down, x up: the y axis was never tilted (the old fit gave a y row of zeros, exit 0)."""
    cfg = SimConfig.default().with_overrides({
        "scenario.poses.mode": "six_position", "scenario.poses.dwell_s": 30.0, "scenario.poses.move_s": 10.0,
        "scenario.poses.repeat": 1, "scenario.duration_s": 150.0})  # 4 dwells + 3 moves
    rec = simulate_recording(cfg, seed=1)
    assert set(np.unique(rec.pose_id)) == {-1, 0, 1, 2, 3}
    mcap = tmp_path / "cut.mcap"
    write_recording(mcap, rec, {"sensor_id": "sim"})
    rc, err = run(["fit", mcap, "-o", tmp_path / "cal.yaml"], capsys)
    line = one_line(err)
    assert rc == 2 and "the y row of M" in line and "(0.00, 1.00, 0.00)" in line
    assert not (tmp_path / "cal.yaml").exists()


def test_a_level_cut_after_its_fourth_pose_limits_the_temperature_degree(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """Three chamber levels, the 45 degC run stopped after x up: y is tilted at two levels only, so a
    quadratic temperature term along y is not determined; the global span check alone would accept it."""
    files = []
    for i, (level, duration) in enumerate([(16.0, None), (24.0, None), (45.0, 150.0)]):
        cfg = SimConfig.default().with_overrides({
            "scenario.poses.mode": "six_position", "scenario.poses.dwell_s": 30.0, "scenario.poses.move_s": 10.0,
            "scenario.poses.repeat": 1, "scenario.duration_s": duration, "scenario.temperature.initial_c": level,
            "scenario.temperature.profile": [], "thermal.initial_optics_c": None})
        files.append(tmp_path / f"run{i}.mcap")
        write_recording(files[-1], simulate_recording(cfg, seed=10 + i), {"sensor_id": "sim"})
    rc, err = run(["fit", *files, "-o", tmp_path / "q.yaml", "--degree", "2"], capsys)
    line = one_line(err)
    assert rc == 2 and "needs 3 temperature levels whose poses span the table frame, 2 do" in line
    assert not (tmp_path / "q.yaml").exists()
    rc = main(["fit", *map(str, files), "-o", str(tmp_path / "c.yaml")])
    text = capsys.readouterr().out
    assert rc == 0 and "degree n = 1" in text
    assert "temperature level 2: its 4 poses do not tilt the table direction (0.00, 1.00, 0.00)" in text


def test_identical_samples_are_refused_by_fit_and_diagnose(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Six poses, the same counts in each: diagnose raised 'Singular matrix' before."""
    rows = [f"{i},880,1000,1000,1000,{SIX[i // 50]},23,{i // 50}\n" for i in range(300)]
    csv = tmp_path / "same.csv"
    csv.write_text(HEADER + "".join(rows))
    for argv in (["fit", csv, "-o", tmp_path / "a.yaml"], ["diagnose", csv]):
        rc, err = run(argv, capsys)
        line = one_line(err)
        assert rc == 2 and "same Psi" in line and "same.csv" in line, line


# ---------------------------------------------------------------------------- options


@pytest.mark.parametrize(("argv", "needle"), [
    (["fit", "{csv}", "-o", "{out}", "--g", "nan"], "argument --g: nan is outside"),
    (["fit", "{csv}", "-o", "{out}", "--g", "-9.81"], "argument --g: -9.81 is outside"),
    (["fit", "{csv}", "-o", "{out}", "--level-gap", "-1"], "argument --level-gap: -1 is outside"),
    (["fit", "{csv}", "-o", "{out}", "--level-gap", "inf"], "argument --level-gap"),
    (["fit", "{csv}", "-o", "{out}", "--window", "1"], "argument --window"),
    (["fit", "{csv}", "-o", "{out}", "--min-interval", "0"], "argument --min-interval"),
    (["fit", "{csv}", "-o", "{out}", "--degree", "-1"], "argument --degree"),
    (["fit", "{csv}", "-o", "{out}", "--max-degree", "1000"], "argument --max-degree"),
    (["fit", "{csv}", "-o", "{out}", "--temperature", "1e300"], "argument --temperature"),
    (["import", "{csv}", "-o", "{out}", "--rate", "0"], "argument --rate: 0 is outside"),
    (["import", "{csv}", "-o", "{out}", "--rate", "nan"], "argument --rate: nan is outside"),
    (["import", "{csv}", "-o", "{out}", "--rate", "abc"], "argument --rate: 'abc' is not a number"),
    (["allan", "{csv}", "--calibration", "{csv}", "--skip", "-5"], "argument --skip"),
    (["diagnose", "{csv}", "--alpha", "nan"], "argument --alpha: nan is outside (0, 1)"),
    (["diagnose", "{csv}", "--alpha", "1"], "argument --alpha"),
    (["diagnose", "{csv}", "--min-gain", "-0.1"], "argument --min-gain"),
    (["diagnose", "{csv}", "--folds", "1"], "argument --folds"),
    (["diagnose", "{csv}", "--seed", "-1"], "argument --seed"),
    (["diagnose", "{csv}", "--lanes", "0"], "argument --lanes: 0 is outside [1, 64]"),
    (["diagnose", "{csv}", "--lanes", "two"], "argument --lanes: 'two' is not an integer"),
    (["diagnose", "{csv}", "--search-rows", "-1"], "argument --search-rows: -1 is outside [0, 1000000000]"),
    (["diagnose", "{csv}", "--max-effects", "-2"], "argument --max-effects"),
    (["diagnose", "{csv}", "--g", "0"], "argument --g"),
])
def test_implausible_options_give_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                      argv: list[str], needle: str) -> None:
    csv = six_pose_csv(tmp_path / "in.csv")
    out = tmp_path / "out.yaml"
    rc, err = run([a.format(csv=csv, out=out) for a in argv], capsys)
    assert rc == 2 and needle in one_line(err), err
    assert not out.exists()


# ---------------------------------------------------------------------------- CSV cells


@pytest.mark.parametrize(("row", "needle"), [
    ("0.07,60880,1000,1500,1200,0,0,9.8,23.4,0", "ref_counts = 60880 is beyond the 12-bit ADC range"),
    ("0.07,880,1e300,1500,1200,0,0,9.8,23.4,0", "x_counts = 1e+300 is beyond the 12-bit ADC range"),
    ("0.07,880,1000,1500,1200,0,0,9.8,23.4,1e300", "pose = '1e300' must be an integer in -1 .."),
    ("0.07,880,1000,1500,1200,0,0,1e300,23.4,0", "gref_z_mps2 = 1e+300 is outside"),
    ("0.07,880,1000,1500,1200,0,0,9.8,1e300,0", "temperature_c = 1e+300 is outside -40 .. 85"),
    ("-0.07,880,1000,1500,1200,0,0,9.8,23.4,0", "time -0.07 s is outside 0 .."),
    ("1e10,880,1000,1500,1200,0,0,9.8,23.4,0", "time 1e+10 s is outside 0 .."),
    ("0.07,880,1000,1500,1200,0,0,9.8,23.4,0," + "x" * 200_000, "line longer than 65536 bytes"),
])
def test_implausible_csv_cells_are_named_with_their_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                         row: str, needle: str) -> None:
    csv = six_pose_csv(tmp_path / "in.csv", row, at=7)
    out = tmp_path / "out.mcap"
    rc, err = run(["import", csv, "-o", out], capsys)
    assert rc == 2 and "line 9: " + needle in err and "Traceback" not in err, err
    assert not out.exists() and not list(tmp_path.glob(".*part*"))
    rc, _ = run(["import", csv, "-o", out, "--drop-bad-rows"], capsys)  # the other rows import
    assert rc == 0 and out.is_file()


@pytest.mark.parametrize("command", ["import", "fit", "allan", "report", "diagnose"])
def test_the_remedy_a_malformed_row_message_gives_works_in_that_subcommand(tmp_path: Path, command: str,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """The message of a CSV with a malformed row names a remedy, and following it works. On the unchanged code every
    subcommand said "use --drop-bad-rows to import the others", an option only `import` has: `fit ... --drop-bad-rows`
    stopped with "unrecognized arguments"."""
    csv = six_pose_csv(tmp_path / "in.csv", "0.07,880,abc,1500,1200,0,0,9.8,23.4,0", at=7)
    cal = tmp_path / "cal.yaml"
    assert main(["fit", str(six_pose_csv(tmp_path / "good.csv")), "-o", str(cal)]) == 0
    capsys.readouterr()
    extra = {"import": ["-o", tmp_path / "o.mcap"], "fit": ["-o", tmp_path / "c.yaml"],
             "allan": ["--calibration", cal, "-o", tmp_path / "a.png"],
             "report": ["--calibration", cal, "-o", tmp_path / "rep"], "diagnose": []}[command]
    rc, err = run([command, csv, *extra], capsys)
    assert rc == 2 and "line 9: x_counts = 'abc' is not a number" in err, err
    if command == "import":
        assert "use --drop-bad-rows" in err
        rc, _ = run([command, csv, *extra, "--drop-bad-rows"], capsys)
        assert rc == 0
        return
    assert "fbg-accel-calib import --drop-bad-rows" in err, err  # the remedy: import the good rows, give the MCAP
    mcap = tmp_path / "good_rows.mcap"
    rc, _ = run(["import", csv, "-o", mcap, "--drop-bad-rows"], capsys)
    assert rc == 0
    if command == "allan":  # allan wants one static pose: the remedy is shown to work on fit instead
        rc, err = run(["fit", mcap, "-o", tmp_path / "c2.yaml"], capsys)
    else:
        rc, err = run([command, mcap, *extra], capsys)
    assert rc == 0, err


def test_utf8_bom_keeps_the_first_column(tmp_path: Path) -> None:
    """A BOM hid 't_s' (the time became the sample index / --rate)."""
    plain = six_pose_csv(tmp_path / "plain.csv")
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    rec, report = import_csv(bom, rate_hz=1000.0)
    assert report.time_base == "t_s column"
    np.testing.assert_array_equal(rec.t_s, import_csv(plain)[0].t_s)


def test_bad_utf8_names_file_and_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv = six_pose_csv(tmp_path / "in.csv")
    data = csv.read_bytes().split(b"\n")
    data[4] = data[4].replace(b"880", b"8\xff0", 1)
    csv.write_bytes(b"\n".join(data))
    rc, err = run(["import", csv, "-o", tmp_path / "o.mcap"], capsys)
    assert rc == 2 and f"{csv}: 1 malformed row(s)" in err and "line 5: not UTF-8 text (byte 0xff at column" in err
    bad_header = tmp_path / "h.csv"
    bad_header.write_bytes(b"t_s,r\xe9f_counts\n")
    rc, err = run(["import", bad_header, "-o", tmp_path / "o.mcap"], capsys)
    assert rc == 2 and "h.csv: line 1: header line is not UTF-8" in one_line(err)


def test_all_temperatures_missing_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """It said 'no usable static samples'."""
    csv = six_pose_csv(tmp_path / "in.csv")
    lines = csv.read_text().splitlines()
    lines = [lines[0]] + [",".join([*ln.split(",")[:8], "", ln.split(",")[9]]) for ln in lines[1:]]
    csv.write_text("\n".join(lines) + "\n")
    rc, err = run(["fit", csv, "-o", tmp_path / "c.yaml"], capsys)
    line = one_line(err)
    assert rc == 2 and "temperature_c is empty on every row" in line and "--temperature" in line


def test_non_mcap_file_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """It said 'TRUNCATED ... bad magic'."""
    fake = tmp_path / "notes.mcap"
    fake.write_text("hello\n")
    for argv in (["fit", fake, "-o", tmp_path / "c.yaml"], ["diagnose", fake]):
        rc, err = run(argv, capsys)
        assert rc == 2 and "notes.mcap: not an MCAP recording" in one_line(err)


def test_streamed_import_equals_the_in_memory_import(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`import` now streams the CSV into the MCAP; the file reads back as the whole-file import wrote it."""
    from fbg_accel_calibration.io.csv_import import CsvBlocks
    from fbg_accel_calibration.io.mcap_reader import read_recording

    csv = six_pose_csv(tmp_path / "in.csv")
    rec, _ = import_csv(csv)
    write_recording(tmp_path / "ref.mcap", rec)
    rc, _ = run(["import", csv, "-o", tmp_path / "new.mcap"], capsys)
    assert rc == 0
    a, b = read_recording(tmp_path / "ref.mcap"), read_recording(tmp_path / "new.mcap")
    for k in ("t_s", "ref", "xyz", "temp_c", "pose_id"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    np.testing.assert_array_equal(a.gref_mps2, b.gref_mps2)
    assert b.metadata["run"]["import"]
    # small blocks: the block boundaries change nothing
    src = CsvBlocks(csv, block_rows=7)
    blocks = list(src.blocks())
    assert len(blocks) == 43
    np.testing.assert_array_equal(np.concatenate([x.pose_id for x in blocks]), rec.pose_id)
    np.testing.assert_array_equal(np.concatenate([x.t_s for x in blocks]), rec.t_s)


def test_streamed_fit_of_a_csv_equals_the_in_memory_fit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`fit CSV` re-reads the CSV block by block on every pass instead of importing it whole."""
    from fbg_accel_driver.thermal_model import ThermalCalibration

    csv = six_pose_csv(tmp_path / "in.csv")
    assert run(["fit", csv, "-o", tmp_path / "s.yaml"], capsys)[0] == 0
    assert run(["fit", csv, "-o", tmp_path / "m.yaml", "--in-memory"], capsys)[0] == 0
    a, b = ThermalCalibration.load(tmp_path / "s.yaml"), ThermalCalibration.load(tmp_path / "m.yaml")
    np.testing.assert_allclose(a.M, b.M, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(a.b, b.b, rtol=1e-9, atol=1e-12)
    bad = six_pose_csv(tmp_path / "bad.csv", "0.07,880,abc,1500,1200,0,0,9.8,23.4,0")
    rc, err = run(["fit", bad, "-o", tmp_path / "b.yaml"], capsys)
    assert rc == 2 and "line 9: x_counts = 'abc' is not a number" in err and not (tmp_path / "b.yaml").exists()


def _six_pose_rows() -> list[str]:
    """300 CSV rows of six poses, counts varying a little (no noise)."""
    return [f"{i * 0.01:.2f},880,{1000 + i % 7},{1100 + i % 5},{1200 + i % 3},{SIX[i // 50]},23,{i // 50}\n"
            for i in range(300)]


def test_a_recording_given_twice_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run given twice (the same path, a link to it, or a copy of the file: ``runs/*.mcap runs/run16.mcap``)
    was read as two runs: its samples counted twice in the YAML (14319 of 18400 used, from 13800), its level
    weighted double, and in ``diagnose`` its visits were repeats of themselves, pseudo-replicates for the
    significance tests. Every subcommand that reads several recordings refuses it before any work."""
    rows = _six_pose_rows()
    csv = tmp_path / "run.csv"
    csv.write_text(HEADER + "".join(rows))
    mcap = tmp_path / "run.mcap"
    assert main(["import", str(csv), "-o", str(mcap)]) == 0
    capsys.readouterr()
    copy = tmp_path / "copy.mcap"
    copy.write_bytes(mcap.read_bytes())
    link = tmp_path / "link.mcap"
    link.symlink_to(mcap)
    other = tmp_path / "other.csv"
    other.write_text(HEADER + "".join(rows[:299]))  # not the same file: accepted
    cal = tmp_path / "cal.yaml"
    rc, err = run(["fit", csv, other, "-o", cal], capsys)
    assert rc == 0 and cal.is_file(), err
    for second in (mcap, link, copy):
        for argv in (["fit", mcap, second, "-o", tmp_path / "twice.yaml"], ["diagnose", mcap, second],
                     ["report", mcap, second, "--calibration", cal, "-o", tmp_path / "rep"]):
            rc, err = run(argv, capsys)
            line = one_line(err)
            assert rc == 2 and "the same recording as" in line and str(second) in line, line
            assert not (tmp_path / "twice.yaml").exists() and not (tmp_path / "rep").exists()


def test_a_bag_directory_and_its_own_file_are_one_recording_given_twice(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """A rosbag2 directory given with one of its own .mcap files (or a copy of it) was accepted: the files were
    compared, not what the directory holds, and that file's samples were counted twice. Every input is now
    expanded to its files; two inputs sharing one (the same file or the same bytes) are refused, both named."""
    import shutil

    import yaml

    from fbg_accel_calibration.io.input_files import check_inputs

    rows = _six_pose_rows()
    csv = tmp_path / "run.csv"
    csv.write_text(HEADER + "".join(rows))
    bag = tmp_path / "run_24C"
    bag.mkdir()
    member = bag / "run_24C_0.mcap"
    assert main(["import", str(csv), "-o", str(member)]) == 0
    (bag / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": {
        "version": 9, "storage_identifier": "mcap", "relative_file_paths": [member.name]}}))
    copy = tmp_path / "copy.mcap"
    shutil.copy(member, copy)
    other_bag = tmp_path / "other_bag"
    shutil.copytree(bag, other_bag)
    capsys.readouterr()
    for first, second in ((bag, member), (bag, copy), (copy, bag), (bag, other_bag)):
        with pytest.raises(ValueError, match="same recording as"):
            check_inputs([first, second])
        rc, err = run(["fit", first, second, "-o", tmp_path / "twice.yaml"], capsys)
        line = one_line(err)
        assert rc == 2 and str(first) in line and str(second) in line, line
        assert not (tmp_path / "twice.yaml").exists()


# ---------------------------------------------------------------------------- one check of the samples, every route
LEVELS_C = (16.0, 24.0, 45.0)


def _campaign(tmp_path: Path, kind: str, damage=None) -> list[Path]:
    """Three temperature levels of six poses (test_fit_streaming.make_run), one file each, as MCAP or CSV; ``damage``
    changes the runs first."""
    from test_fit_streaming import make_run

    runs = [make_run(i, t, n_poses=6, t0_s=i * 100.0) for i, t in enumerate(LEVELS_C)]
    if damage is not None:
        damage(runs)
    paths = []
    for i, r in enumerate(runs):
        path = tmp_path / f"run_{i}.{kind}"
        if kind == "mcap":
            write_recording(path, r, {"sensor_id": "fbg-test"})
        else:
            g = np.where(np.isfinite(r.gref_mps2), r.gref_mps2, 0.0)  # a CSV row between poses: pose -1, any reference
            t = ["" if not np.isfinite(v) else f"{v:.3f}" for v in r.temp_c]
            path.write_text(HEADER + "".join(
                f"{r.t_s[k]:.3f},{r.ref[k]:.4f},{r.xyz[k, 0]:.4f},{r.xyz[k, 1]:.4f},{r.xyz[k, 2]:.4f},"
                f"{g[k, 0]:.6f},{g[k, 1]:.6f},{g[k, 2]:.6f},{t[k]},{r.pose_id[k]}\n" for k in range(len(r))))
        paths.append(path)
    return paths


def _fit(paths: list[Path], capsys: pytest.CaptureFixture[str]) -> tuple[object, list[str]]:
    """fit_files in process, numpy warnings as errors: (calibration, the WARNING lines of stderr without file names)."""
    import warnings

    from fbg_accel_calibration.fit.fit_pipeline import fit_files

    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        cal = fit_files(paths).calibration
    err = capsys.readouterr().err
    lines = [ln.split(": ", 2)[2] for ln in err.splitlines() if ln.startswith("WARNING: ") and "samples" in ln]
    return cal, lines


@pytest.fixture(scope="module")
def clean_fit(tmp_path_factory: pytest.TempPathFactory) -> object:
    from fbg_accel_calibration.fit.fit_pipeline import fit_files

    return fit_files(_campaign(tmp_path_factory.mktemp("clean"), "mcap")).calibration


def test_one_absurd_count_drops_its_sample_not_its_file(tmp_path: Path, clean_fit, capsys) -> None:
    """One count of 1e308 in a static pose of the middle level: before, the whole file (every sample of that level)
    left the fit, the degree dropped from 2 to 1, the warning spoke of 3000 samples of one visit, and numpy printed
    13 RuntimeWarnings. Now that sample alone is dropped, and the line says so."""
    def damage(runs):
        k = int(np.flatnonzero(runs[1].pose_id == 3)[20])
        runs[1].xyz[k, 0] = 1e308

    cal, lines = _fit(_campaign(tmp_path, "mcap", damage), capsys)
    assert any(ln.startswith("1 of ") and "samples dropped: ADC counts outside the 12-bit range" in ln
               and "x_counts = 1e+308 is beyond the 12-bit ADC range 0 .. 4095 counts" in ln for ln in lines), lines
    assert cal.degree == clean_fit.degree and cal.fit["temperature_levels_c"] == clean_fit.fit["temperature_levels_c"]
    assert clean_fit.fit["samples_used"] - cal.fit["samples_used"] < 50, (cal.fit["samples_used"],
                                                                            clean_fit.fit["samples_used"])


@pytest.mark.parametrize("kind", ["mcap", "csv"])
def test_a_level_s_reference_in_g_is_named_the_same_way_on_every_route(tmp_path: Path, kind: str, capsys) -> None:
    """The middle level's reference gravity in g (another node publishing ``calibration/reference_gravity`` in g):
    before, the MCAP route fitted it (exit 0, m/s^2 off the truth). CSV or MCAP, the same check and the same line."""
    def damage(runs):
        runs[1].gref_mps2 /= 9.80665

    cal, lines = _fit(_campaign(tmp_path, kind, damage), capsys)
    assert [round(t) for t in cal.fit["temperature_levels_c"]] == [16, 45]  # the level without a usable reference
    hits = [ln for ln in lines if "not fitted: a reference gravity |g_ref| outside 9.7 .. 9.9 m/s^2 (gravity in g?" in ln]
    assert len(hits) == 1 and "(first: 1)" in hits[0], lines


def _junk_readings(runs) -> None:
    """30 single readings and a burst of 5 of 85 degC (the AHT10's top) in the first level's run."""
    t = runs[0].temp_c
    idx = np.flatnonzero(np.isfinite(t))
    t[idx[10:610:20]] = 85.0
    t[idx[700:705]] = 85.0


def _all_nan(runs) -> None:
    runs[2].temp_c[:] = np.nan


@pytest.mark.parametrize(("case", "damage", "line", "levels"), [
    ("kelvin", lambda runs: runs[1].temp_c.__iadd__(273.15), "not fitted: a temperature outside the AHT10 range "
     "-40 .. 85 degC (first: 297", [16, 45]),
    ("1e300", lambda runs: runs[2].temp_c.__setitem__(slice(None), 1e300), "not fitted: a temperature outside the "
     "AHT10 range -40 .. 85 degC (first: 1e+300)", [16, 24]),
    ("junk 85 degC", _junk_readings, "35 of", [16, 24, 45]),
    ("all NaN", _all_nan, "none of its", [16, 24]),
    ("x = -500", lambda runs: runs[0].xyz.__setitem__((int(np.flatnonzero(runs[0].pose_id == 2)[10]), 0), -500.0),
     "1 of", [16, 24, 45]),
], ids=["kelvin", "1e300", "junk 85 degC", "all NaN", "x = -500"])
def test_temperatures_and_counts_no_sensor_gives_are_named_not_fitted(tmp_path: Path, capsys, case: str, damage,
                                                                      line: str, levels: list[int]) -> None:
    """Before, each of these went into the fit with exit 0: a level in kelvin or at 1e300 degC gave a YAML its own
    loader refused; 85 degC junk readings gave a claimed range of 16-85 degC and degree 3; a file without a single
    temperature contributed nothing, silently; x = -500 counts on one pose moved the calibration by m/s^2."""
    cal, lines = _fit(_campaign(tmp_path, "mcap", damage), capsys)
    assert any(line in ln for ln in lines), lines
    assert [round(t) for t in cal.fit["temperature_levels_c"]] == levels
    assert cal.temperature_range_c[1] < 46.0
    if case == "kelvin":
        assert any("it looks like kelvin" in ln for ln in lines), lines


def test_a_junk_reading_at_a_block_end_is_judged_with_the_next_block() -> None:
    """The last readings of a block wait for the next one (``SampleCheck.apply`` holds them back): cut anywhere, the
    samples blanked are those of the run in one block."""
    from fbg_accel_calibration.io.input_validation import SampleCheck
    from fbg_accel_calibration.io.recording import Recording, join_blocks, without_samples

    n = 400
    temp = 24.0 + 0.01 * np.round(np.sin(np.arange(n) / 50.0) * 10)
    temp[[99, 100, 101, 250]] = 85.0  # a burst across the cut at 100, and a single reading
    temp[300:] += 3.0  # a real step that stays: not a spike
    rec = Recording(np.arange(n) * 0.01, np.full(n, 870.0), np.full((n, 3), 1000.0), temp, np.full((n, 3), np.nan),
                    np.full(n, -1))

    def blanked(block_rows: int) -> np.ndarray:
        check = SampleCheck()
        blocks = [rec.select(slice(i, i + block_rows)) for i in range(0, n, block_rows)]
        out = join_blocks(list(without_samples(iter(blocks), block_rows, check.apply)))
        assert len(out) == n and check.dropped["temperature_spike"] == 4
        return np.isnan(out.temp_c)

    whole = blanked(n)
    assert np.flatnonzero(whole).tolist() == [99, 100, 101, 250]
    for rows in (100, 101, 37):
        assert np.array_equal(blanked(rows), whole), rows
