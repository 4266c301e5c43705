"""``--help`` of every command loads none of the heavy libraries: the argument parsers import only what they need to
describe the options, and numpy, scipy, matplotlib, mcap, rclpy are imported by the code that computes, reads or
publishes (at its use site or at the command's dispatch). Checked in a fresh interpreter, as a user's command starts."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("numpy", "scipy", "scipy.stats", "matplotlib", "mcap", "rclpy", "tqdm")

# each command's --help as its console script runs it; the modules it must not load
HELP_RUNS = {
    "fbg-accel-calib": ("fbg_accel_calibration.cli_main", [["--help"], ["fit", "--help"], ["diagnose", "--help"],
                                                           ["report-measured", "--help"], ["adc-codes", "--help"],
                                                           ["import", "--help"], ["dynamic", "--help"]], HEAVY),
    "driver": ("fbg_accel_driver.driver_main", [["--help"]], HEAVY),
    # its parameter table shows the stillness monitor's defaults, kept in their owner (a numpy module): numpy, no scipy
    "calibration": ("fbg_accel_calibration.calibration_main", [["--help"]], tuple(m for m in HEAVY if m != "numpy")),
    "board_sim": ("fbg_accel_sim.board_sim_main", [["--help"]], HEAVY),
}

_PROBE = """
import contextlib, importlib, io, json, sys
module, argv = sys.argv[1], json.loads(sys.argv[2])
with contextlib.redirect_stdout(io.StringIO()) as out:
    try:
        loaded = importlib.import_module(module)
        code = loaded.main(argv) if argv is not None else 0
    except SystemExit as exc:
        code = exc.code
print(json.dumps({"code": code, "help": out.getvalue(), "modules": sorted(sys.modules)}))
"""


def _loaded(module: str, argv: list[str] | None) -> dict:
    """Exit code, stdout and loaded modules of ``module.main(argv)`` (``argv`` None: the import alone)."""
    run = subprocess.run([sys.executable, "-c", _PROBE, module, json.dumps(argv)], capture_output=True, text=True,
                         timeout=120, check=True)
    return json.loads(run.stdout)


@pytest.mark.parametrize("command", sorted(HELP_RUNS))
def test_help_loads_no_heavy_library(command: str) -> None:
    module, runs, heavy = HELP_RUNS[command]
    for argv in runs:
        got = _loaded(module, argv)
        assert got["code"] in (0, None) and "usage" in got["help"], (command, argv, got["code"])
        assert not set(heavy) & set(got["modules"]), (command, argv, sorted(set(heavy) & set(got["modules"])))


def test_parser_module_alone_loads_no_heavy_library() -> None:
    """Importing the parser modules and building the parser (what the README's check and the docs tests do)."""
    probe = ("import json, sys\nfrom fbg_accel_calibration.cli import build_parser\nbuild_parser()\n"
             "import fbg_accel_calibration.diagnose_cli, fbg_accel_calibration.adc_codes_cli\n"
             "print(json.dumps(sorted(sys.modules)))")
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert not set(HEAVY) & set(json.loads(run.stdout))


def test_the_probe_sees_a_heavy_import() -> None:
    """The check is able to fail: a module that does load numpy is seen loading it."""
    assert "numpy" in _loaded("fbg_accel_calibration.table_geometry", None)["modules"]
