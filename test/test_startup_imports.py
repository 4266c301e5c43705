"""``--help`` of every command loads none of the heavy libraries: the argument parsers import only what they need to
describe the options, and numpy, scipy, matplotlib, mcap, rclpy are imported by the code that computes, reads or
publishes (at its use site or at the command's dispatch). Checked in a fresh interpreter, as a user's command starts."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

HEAVY = ("numpy", "scipy", "scipy.stats", "matplotlib", "mcap", "rclpy", "tqdm")

# each command's --help as its console script runs it; the modules it must not load
HELP_RUNS = {
    "fbg-accel-calib": ("fbg_accel_calibration.commands.cli_main", [["--help"], ["fit", "--help"], ["diagnose", "--help"],
                                                           ["report-measured", "--help"], ["adc-codes", "--help"],
                                                           ["import", "--help"], ["dynamic", "--help"]], HEAVY),
    "driver": ("fbg_accel_driver.driver_main", [["--help"]], HEAVY),
    # its parameter table shows the stillness monitor's defaults, kept in their owner (a numpy module): numpy, no scipy
    "calibration": ("fbg_accel_calibration.recorder.calibration_main", [["--help"]], tuple(m for m in HEAVY if m != "numpy")),
    "board_sim": ("fbg_accel_sim.board_sim_main", [["--help"]], HEAVY),
}

_PROBE = """
import contextlib, importlib, io, json, sys
module, runs = sys.argv[1], json.loads(sys.argv[2])
loaded, results = importlib.import_module(module), []
for argv in runs:  # every --help of one command in one interpreter: what any of them loads stays in sys.modules
    with contextlib.redirect_stdout(io.StringIO()) as out:
        try:
            code = loaded.main(argv)
        except SystemExit as exc:
            code = exc.code
    results.append({"code": code, "help": out.getvalue()})
print(json.dumps({"runs": results, "modules": sorted(sys.modules)}))
"""


def _loaded(module: str, runs: list[list[str]]) -> dict:
    """Exit code and stdout of each ``module.main(argv)`` of ``runs``, and the modules loaded by the import and all
    of them (``runs`` empty: the import alone)."""
    run = subprocess.run([sys.executable, "-c", _PROBE, module, json.dumps(runs)], capture_output=True, text=True,
                         timeout=120, check=True)
    return json.loads(run.stdout)


@pytest.mark.parametrize("command", sorted(HELP_RUNS))
def test_help_loads_no_heavy_library(command: str) -> None:
    module, runs, heavy = HELP_RUNS[command]
    got = _loaded(module, runs)
    for argv, res in zip(runs, got["runs"], strict=True):
        assert res["code"] in (0, None) and "usage" in res["help"], (command, argv, res["code"])
    assert not set(heavy) & set(got["modules"]), (command, sorted(set(heavy) & set(got["modules"])))


def test_parser_module_alone_loads_no_heavy_library() -> None:
    """Importing the parser modules and building the parser (what the README's check and the docs tests do)."""
    probe = ("import json, sys\nfrom fbg_accel_calibration.commands.cli import build_parser\nbuild_parser()\n"
             "import fbg_accel_calibration.commands.diagnose_cli, fbg_accel_calibration.commands.adc_codes_cli\n"
             "print(json.dumps(sorted(sys.modules)))")
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert not set(HEAVY) & set(json.loads(run.stdout))


def test_the_probe_sees_a_heavy_import() -> None:
    """The check is able to fail: a module that does load numpy is seen loading it."""
    assert "numpy" in _loaded("fbg_accel_calibration.io.table_geometry", [])["modules"]
