"""Which sensor a set of recordings describes (README workflow: ``fbg-accel-calib fit runs/*.mcap``).

A calibration describes one sensor. Recordings name theirs in their ``run`` metadata (the calibration node's
``sensor_id`` parameter, ``fbg-accel-calib import --sensor-id``); the tools that write a calibration from them
must not merge two sensors, nor lose the name. All in process (``cli.main``), on a small synthetic six-pose
series imported to MCAP.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import pytest
import yaml
from test_cli_hostile_inputs import HEADER, base_rows

from fbg_accel_calibration.commands.cli import main
from fbg_accel_driver.driver_parameters import default_calibration_path


def run(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    return code, err.getvalue()


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two runs of sensor acc4 (23.4 and 30 degC) and one of acc5 (30 degC), same six poses."""
    d = tmp_path_factory.mktemp("runs")
    out = {}
    for name, sensor, temp in (("acc4_L0", "acc4", "23.4"), ("acc4_L1", "acc4", "30.0"), ("acc5_L1", "acc5", "30.0")):
        rows = [[*r[:-2], temp, r[-1]] for r in base_rows(per_pose=25 if sensor == "acc4" else 26)]
        csv = d / f"{name}.csv"
        csv.write_text("\n".join(",".join(r) for r in [HEADER, *rows]) + "\n")
        mcap = d / f"{name}.mcap"
        code, err = run(["import", str(csv), "-o", str(mcap), "--sensor-id", sensor, "--no-progress"])
        assert code == 0, err
        out[name] = mcap
    return out


@pytest.mark.parametrize("in_memory", [False, True])
def test_fit_refuses_recordings_of_two_sensors(runs: dict[str, Path], tmp_path: Path, in_memory: bool) -> None:
    """On the code before: exit 0, a calibration named 'acc4' (the first file's id) fitted on acc4's 23.4 degC
    run and acc5's 30 degC run as if they were two temperature levels of one sensor, without a word."""
    out = tmp_path / "cal.yaml"
    code, err = run(["fit", str(runs["acc4_L0"]), str(runs["acc5_L1"]), "-o", str(out), "--no-progress",
                     *(["--in-memory"] if in_memory else [])])
    assert code == 2, err
    assert "acc4" in err and "acc5" in err and "acc5_L1.mcap" in err, err
    assert not out.exists()


def test_fit_of_one_sensor_s_runs_names_that_sensor(runs: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "cal.yaml"
    code, err = run(["fit", str(runs["acc4_L0"]), str(runs["acc4_L1"]), "-o", str(out), "--no-progress"])
    assert code == 0, err
    assert yaml.safe_load(out.read_text())["sensor_id"] == "acc4"


def test_diagnose_refuses_recordings_of_two_sensors(runs: dict[str, Path], tmp_path: Path) -> None:
    """On the code before: exit 0, a diagnosis of acc4 and acc5 together, its YAML named 'unknown'."""
    out = tmp_path / "d" / "report.md"
    code, err = run(["diagnose", str(runs["acc4_L0"]), str(runs["acc5_L1"]), "--out", str(out), "--max-effects", "0",
                     "--no-progress"])
    assert code == 2, err
    assert "acc4" in err and "acc5" in err, err
    assert not out.exists()


def test_diagnose_names_the_recorded_sensor_in_its_calibration(runs: dict[str, Path], tmp_path: Path) -> None:
    """On the code before: ``sensor_id: unknown`` in the YAML although the recording names acc4 (diagnose read a
    top-level ``sensor_id`` key that MCAP recordings do not have; theirs is in the ``run`` record), so the driver's
    diagnostics said hardware_id 'unknown' and no tool could warn of a calibration of another sensor."""
    out, cal = tmp_path / "d" / "report.md", tmp_path / "cal.yaml"
    code, err = run(["diagnose", str(runs["acc4_L0"]), str(runs["acc4_L1"]), "--out", str(out), "--yaml", str(cal),
                     "--max-effects", "0", "--no-progress"])
    assert code == 0, err
    assert yaml.safe_load(cal.read_text())["sensor_id"] == "acc4"


def test_dynamic_refuses_a_static_calibration_of_another_sensor(runs: dict[str, Path], tmp_path: Path) -> None:
    """``dynamic`` writes the static calibration with the run's chain dynamics added: given another sensor's static
    calibration it wrote one file mixing two sensors. Before: no check (the analysis ran; this recording, a static
    run, then failed for a reason unrelated to the sensor). After: refused first, naming both sensors."""
    out = tmp_path / "cal_dyn.yaml"
    repo = Path(__file__).resolve().parents[1]
    code, err = run(["dynamic", str(runs["acc5_L1"]), "--plan", str(repo / "config" / "excitation_plan_stepped_sine.yaml"),
                     "--calibration", str(default_calibration_path()), "-o", str(out)])
    assert code == 2, err
    assert "another sensor" in err and "acc5" in err and "sim-fbg-accel-001" in err, err
    assert not out.exists()


def test_report_and_allan_refuse_recordings_of_two_sensors(runs: dict[str, Path], tmp_path: Path) -> None:
    """On the code before: ``report`` exit 0 (its page named the first file's sensor for both), ``allan`` refused
    for another reason (two runs). Both read through ``load_recording``, which now refuses first."""
    cal = tmp_path / "cal.yaml"
    assert run(["fit", str(runs["acc4_L0"]), "-o", str(cal), "--no-progress"])[0] == 0
    two = [str(runs["acc4_L0"]), str(runs["acc5_L1"])]
    code, err = run(["report", *two, "--calibration", str(cal), "-o", str(tmp_path / "rep")])
    assert code == 2 and "different sensors" in err, err
    code, err = run(["allan", *two, "--calibration", str(cal), "-o", str(tmp_path / "allan.png")])
    assert code == 2 and "different sensors" in err, err


HOSTILE_IDS = ["acc\x1b[31mRED\x1b[0m", "acc4\nwarning: forged line", "acc\r4", "a\x00b"]


@pytest.mark.parametrize("sensor_id", HOSTILE_IDS)
def test_a_sensor_id_with_control_characters_is_refused_never_echoed_raw(tmp_path: Path, sensor_id: str) -> None:
    """Issue 42, item 14: ``--sensor-id`` with an ANSI escape sequence or a line break was stored and echoed raw
    (recolouring the terminal, forging log lines). The tools, the calibration file and the node refuse it, and
    every message shows it escaped."""
    from fbg_accel_calibration.io.input_validation import sensor_id as parse_sensor_id
    from fbg_accel_driver.thermal_model import CalibrationFileError, ThermalCalibration

    csv = tmp_path / "s.csv"
    csv.write_text("\n".join(",".join(r) for r in [HEADER, *base_rows()]) + "\n")
    for argv in (["import", str(csv), "-o", str(tmp_path / "s.mcap")], ["fit", str(csv), "-o", str(tmp_path / "c.yaml")]):
        with pytest.raises(SystemExit) as info, contextlib.redirect_stderr(io.StringIO()) as err:
            main([*argv, "--sensor-id", sensor_id])
        assert info.value.code == 2
        assert "control characters" in err.getvalue() and not any(c in err.getvalue() for c in "\x1b\r\x00")
        assert err.getvalue().count("\n") == 1
    assert list(tmp_path.iterdir()) == [csv]
    with pytest.raises(Exception, match="control characters"):
        parse_sensor_id(sensor_id)
    cal = yaml.safe_load(default_calibration_path().read_text())
    cal["sensor_id"] = sensor_id
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(cal))
    with pytest.raises(CalibrationFileError) as refused:
        ThermalCalibration.load(path)
    assert "control characters" in str(refused.value) and "\n" not in str(refused.value)
    assert not any(c in str(refused.value) for c in "\x1b\r\x00")


def test_a_hostile_sensor_id_inside_a_recording_is_escaped(tmp_path: Path) -> None:
    """A recording written before (or by another tool) that names its sensor with escape sequences: the fit's
    messages and its calibration carry the id escaped, and the calibration loads."""
    from fbg_accel_calibration.fit.thermal_fit import sensor_id_of

    assert sensor_id_of({"run": {"sensor_id": "acc\x1b[31m4\n"}}) == "acc\\x1b[31m4\\n"
    assert sensor_id_of({"run": {"sensor_id": "acc4"}}) == "acc4"
