"""Issue 42, items 8 and 14: every YAML file the project reads goes through one loader
(``fbg_accel_driver.yaml_input``) with one error contract: a ``ValueError`` whose message is one line and starts
with the file's path -- for deep nesting (RecursionError before), impossible dates (a bare ValueError), wrong types,
a FIFO, a device or a directory (each said as what it is); and YAML 1.1 sexagesimal/hex/octal never become numbers."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from fbg_accel_calibration.dynamic.excitation_plan import ExcitationPlan
from fbg_accel_calibration.io.rosbag2_input import bag_files
from fbg_accel_calibration.recorder.calibration_node import plan_format
from fbg_accel_calibration.recorder.pose_plan import PosePlan
from fbg_accel_driver.thermal_model import ThermalCalibration
from fbg_accel_driver.yaml_input import MAX_DEPTH, load_yaml, read_yaml_file
from fbg_accel_sim.sim_config import SimConfig, parse_set_argument

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

REPO = Path(__file__).resolve().parents[1]
DEEP = "[" * 3000 + "]" * 3000
DEEP_MAPPING = "".join(f"{' ' * i}k{i}:\n" for i in range(300)) + " " * 300 + "x: 1\n"


def _bag(path: Path) -> Any:
    """bag_files reads ``<dir>/metadata.yaml``: the file given is that metadata file."""
    return bag_files(path.parent)


# name -> reader of a file at a path: every YAML file the project reads
READERS: dict[str, Callable[[Path], Any]] = {
    "calibration file": ThermalCalibration.load,
    "pose plan": PosePlan.load,
    "excitation plan": ExcitationPlan.load,
    "simulator config": SimConfig.load,
    "rosbag2 metadata": _bag,
}
HOSTILE_TEXTS = {
    "3000 deep": DEEP,
    "300 deep mapping": DEEP_MAPPING,
    "impossible date": "format: x\nwhen: !!timestamp 2026-13-45\n",
    "bad int tag": "a: !!int x\n",
    "not utf-8": b"a: \xff\xfe\n",
    "python object": "a: !!python/object/apply:os.system ['true']\n",
    "alias": "a: &x [1]\nb: *x\n",
    "tab": "a:\n\t- 1\n",
}


def check_one_line(exc: BaseException, path: Path) -> str:
    assert isinstance(exc, ValueError), repr(exc)
    msg = str(exc)
    assert "\n" not in msg and msg.startswith(str(path)), msg
    return msg


def write(path: Path, text: str | bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    return path


@pytest.mark.parametrize("reader", READERS)
@pytest.mark.parametrize("hostile", HOSTILE_TEXTS)
def test_every_reader_refuses_hostile_yaml_in_one_line_naming_the_file(tmp_path: Path, reader: str,
                                                                        hostile: str) -> None:
    path = write(tmp_path / "d" / "metadata.yaml", HOSTILE_TEXTS[hostile])
    with pytest.raises(Exception) as info:
        READERS[reader](path)
    check_one_line(info.value, path)


@pytest.mark.parametrize("reader", READERS)
def test_a_fifo_a_device_and_a_directory_are_named_as_what_they_are(tmp_path: Path, reader: str) -> None:
    """Before: "file not found" for all three (and a FIFO would block a reader that opened it)."""
    fifo = tmp_path / "f" / "metadata.yaml"
    fifo.parent.mkdir()
    os.mkfifo(fifo)
    directory = tmp_path / "g" / "metadata.yaml"
    directory.mkdir(parents=True)
    for path, kind in ((fifo, "FIFO"), (Path("/dev/zero"), "character device"), (directory, "directory")):
        if reader == "rosbag2 metadata" and path == Path("/dev/zero"):
            continue  # bag_files takes the directory; /dev has no metadata.yaml
        with pytest.raises(Exception) as info:
            READERS[reader](path)
        msg = check_one_line(info.value, path)
        assert kind in msg and "not found" not in msg, msg


def test_the_node_plan_format_probe_survives_what_the_plan_loader_refuses(tmp_path: Path) -> None:
    """``plan_file`` with ``x: 2026-13-45`` (ValueError out of plan_format) or 3000-deep nesting (RecursionError)
    stopped the calibration node with a traceback; the probe now leaves the message to the plan's loader."""
    for i, text in enumerate(("x: 2026-13-45\nformat: 3\n", DEEP, "a: !!int x\n")):
        path = write(tmp_path / f"p{i}.yaml", text)
        assert plan_format(str(path)) in (None, 3)
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    assert plan_format(str(fifo)) is None


def test_dates_load_as_text_and_numbers_only_in_decimal() -> None:
    doc = load_yaml("d: 2026-13-45\nt: 2026-11-20T09:30:00Z\ns: 1:22\nh: 0x52\no: 012\nb: 0b11\nsf: 1:22.5\n"
                    "i: -12\nf: 2.5e-3\ng: 1_000\nn: .nan\n")
    assert doc["d"] == "2026-13-45" and doc["t"] == "2026-11-20T09:30:00Z"
    assert [doc[k] for k in ("s", "h", "o", "b", "sf")] == ["1:22", "0x52", "012", "0b11", "1:22.5"]
    assert doc["i"] == -12 and doc["f"] == 2.5e-3 and doc["g"] == 1000 and doc["n"] != doc["n"]


@pytest.mark.parametrize("value", ["1:22", "0x52", "012"])
def test_sexagesimal_hex_and_octal_are_not_numbers_in_the_calibration_file(tmp_path: Path, value: str) -> None:
    """YAML 1.1 read ``temperature_center_c: 1:22`` as 82 and ``0x52`` as 82: a calibration quietly centred at
    82 degC. Now the text is refused where a number belongs."""
    text = (REPO / "config" / "calibration_sim.yaml").read_text()
    key = "temperature_center_c:"
    assert key in text
    lines = [f"{key} {value}" if ln.startswith(key) else ln for ln in text.splitlines()]
    path = write(tmp_path / "c.yaml", "\n".join(lines) + "\n")
    with pytest.raises(ValueError) as info:
        ThermalCalibration.load(path)
    assert "temperature_center_c" in check_one_line(info.value, path)


def test_nesting_is_bounded_below_the_stack() -> None:
    ok = "[" * (MAX_DEPTH - 1) + "]" * (MAX_DEPTH - 1)
    assert load_yaml(ok) is not None
    with pytest.raises(yaml.YAMLError, match="nested more than"):
        load_yaml("[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1))


def test_bag_metadata_with_wrong_types_is_refused_in_one_line(tmp_path: Path) -> None:
    """``topics_with_message_count: 5`` gave a TypeError traceback (rosbag2_input.py:91)."""
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "run_0.mcap").write_bytes(b"\x89MCAP0\r\n")
    for topics in ("5", "'abc'", "{a: 1}"):
        meta = write(bag / "metadata.yaml", "rosbag2_bagfile_information:\n  storage_identifier: mcap\n"
                     f"  relative_file_paths: [run_0.mcap]\n  topics_with_message_count: {topics}\n")
        with pytest.raises(ValueError) as info:
            bag_files(bag)
        assert "topics_with_message_count" in check_one_line(info.value, meta)


def test_set_values_follow_the_same_contract() -> None:
    for raw in (DEEP, "!!int x", "[1, 2", "!!timestamp 2026-13-45"):
        with pytest.raises(ValueError) as info:
            parse_set_argument(f"scenario.rate_hz={raw}")
        msg = str(info.value)
        assert "\n" not in msg and msg.startswith("--set scenario.rate_hz"), msg


def test_read_yaml_file_bounds_the_size_before_parsing(tmp_path: Path) -> None:
    big = write(tmp_path / "big.yaml", "a: 1\n" * 1000)
    with pytest.raises(ValueError, match="larger than 100 bytes"):
        read_yaml_file(big, "plan", max_bytes=100)


@pytest.mark.parametrize("argv", [
    ["board_sim", "--config", "{deep}"],
    ["board_sim", "--set", "scenario.rate_hz=" + DEEP],
    ["fbg-accel-calib", "dynamic", "rec.mcap", "--plan", "{date}", "--calibration", "c.yaml", "-o", "out.yaml"],
])
def test_tools_answer_a_hostile_yaml_with_one_line_and_exit_2(tmp_path: Path, argv: list[str]) -> None:
    deep = write(tmp_path / "deep.yaml", DEEP)
    date = write(tmp_path / "date.yaml", "format: fbg_accel_excitation_plan\nx: 2026-13-45\nformat_version: [\n")
    args = [a.format(deep=deep, date=date) for a in argv]
    module = {"board_sim": "fbg_accel_sim.board_sim", "fbg-accel-calib": "fbg_accel_calibration.commands.cli"}[args[0]]
    proc = subprocess.run([sys.executable, "-m", module, *args[1:]], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert str(deep if "{deep}" in " ".join(argv) else date) in lines[0] or "--set" in lines[0], lines[0]


def test_a_recording_input_that_is_a_fifo_or_a_device_is_named_as_such(tmp_path: Path) -> None:
    """``fit FIFO`` and ``fit /dev/zero`` said "file not found"."""
    from fbg_accel_calibration.io.input_files import check_input

    fifo = tmp_path / "run.mcap"
    os.mkfifo(fifo)
    for path, kind in ((fifo, "a FIFO (named pipe), not a recording"), (Path("/dev/zero"), "a character device")):
        with pytest.raises(ValueError) as info:
            check_input(path)
        assert kind in check_one_line(info.value, path)
