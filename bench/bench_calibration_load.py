#!/usr/bin/env python3
"""Calibration file loading: time of a normal load (with the plausibility evaluation) and of refusing a
100 000-term file (issue 11: it took 21.7 s and 658 MB before the size bound). Not a test.

Each case runs in a fresh interpreter so its peak RSS (``ru_maxrss``) is its own.

    .venv/bin/python bench/bench_calibration_load.py     # -> bench/results/calibration_load.json
"""

from __future__ import annotations

import datetime as dt
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine_info import machine  # noqa: E402
from output_paths import output_dir_from_command_line  # noqa: E402

CHILD = """
import resource, sys, time
from fbg_accel_driver.thermal_model import CalibrationFileError, ThermalCalibration
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
for _ in range(int(sys.argv[2])):
    try:
        ThermalCalibration.load(sys.argv[1]); outcome = "loaded"
    except CalibrationFileError as exc:
        outcome = "refused: " + str(exc).split(": ", 1)[1][:90]
dt = (time.perf_counter() - t) / int(sys.argv[2])
print(dt, (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024, outcome, sep="|")
"""


def run(path: Path, repeat: int) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, str(path), str(repeat)], capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout.strip().split("|")
    return {"seconds_per_load": float(out[0]), "peak_rss_growth_mib": float(out[1]), "outcome": out[2]}


def main() -> int:
    out_dir = output_dir_from_command_line(__doc__.splitlines()[0])
    good = yaml.safe_load((ROOT / "config" / "calibration_sim.yaml").read_text())
    results = {"when": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), "machine": machine(), "cases": {}}
    with tempfile.TemporaryDirectory() as tmp:
        cases = {
            "shipped calibration_sim.yaml (degree 2, no terms)": (ROOT / "config" / "calibration_sim.yaml", 20),
            "measured diagnosis (degree 0, 2 terms)": (ROOT / "docs" / "results" / "measured_diagnosis.yaml", 20),
        }
        big = Path(tmp) / "big.yaml"
        term = {"kind": "reference_dark_offset", "ref_offset_counts": 1.0}
        big.write_text(yaml.safe_dump(dict(good, corrections=[dict(term) for _ in range(100_000)])))
        cases[f"100 000 correction terms ({big.stat().st_size / 1e6:.1f} MB)"] = (big, 3)
        for name, (path, repeat) in cases.items():
            results["cases"][name] = run(path, repeat)
            r = results["cases"][name]
            print(f"{name}: {r['seconds_per_load'] * 1e3:.1f} ms, peak RSS +{r['peak_rss_growth_mib']:.1f} MiB, "
                  f"{r['outcome']}")
    out = out_dir / "calibration_load.json"
    out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
