#!/usr/bin/env python3
"""Diagnose time and peak memory at 10^4, 10^5 and 10^6 samples (issue 8 §7), and the growth exponent.

Not a test. Runs ``bench_calibration.py --samples N --mcap-samples 0 --repeats 1`` once per
size, each in its own process (so each peak RSS is that run's own), and collects the diagnose step of each
into bench/results/diagnose_scaling.json. Below 10^6 samples the timed fit uses degree 0: the short runs see
fewer than the three temperature levels a degree-2 fit needs (the diagnosis selects its own degree).
Then the command a user runs, ``fbg-accel-calib diagnose`` on the same simulated run written as a calibration
MCAP, in its own process: its wall time (reading, diagnosis, report, YAML and plots) and its peak RSS
(``os.wait4``), which the in-process figure overstates by the simulation's own peak.
Run on an idle machine:

    .venv/bin/python bench/diagnose_scaling.py [--sizes 10000 100000 1000000]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from bench_calibration import scenario  # noqa: E402
from machine_info import results_doc, write_results  # noqa: E402
from output_paths import add_update_results, results_dir  # noqa: E402


def run_command(n: int, tmp: Path) -> dict:
    """``fbg-accel-calib diagnose`` on the benchmark's simulated run of ``n`` samples written as MCAP:
    {wall seconds, peak RSS MiB} of that one process."""
    from fbg_accel_calibration.io.mcap_writer import write_recording
    from fbg_accel_sim.board_physics import simulate_recording

    cfg, duration = scenario(n)
    path = tmp / f"{n}.mcap"
    write_recording(path, simulate_recording(cfg, seed=0, duration_s=duration), metadata={"sensor_id": "bench"})
    cmd = [sys.executable, "-m", "fbg_accel_calibration.commands.cli", "diagnose", str(path), "--out", str(tmp / f"{n}.md"),
           "--yaml", str(tmp / f"{n}.yaml"), "--force", "--no-progress"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} exited with {proc.returncode}")
    path.unlink()
    return {"command_seconds": round(wall, 1), "command_peak_rss_mib": round(usage.ru_maxrss / 1024)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--output", type=Path, help="output file (default: diagnose_scaling.json in the scratch/results directory)")
    add_update_results(ap)
    args = ap.parse_args(argv)
    args.output = args.output or results_dir(args.update_results) / "diagnose_scaling.json"
    runs: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="diagnose_scaling_") as tmp:
        for n in args.sizes:
            out = Path(tmp) / f"{n}.json"
            cmd = [sys.executable, str(ROOT / "bench" / "bench_calibration.py"), "--samples", str(n),
                   "--mcap-samples", "0", "--repeats", "1", "--output", str(out)]
            if n < 1_000_000:
                cmd += ["--degree", "0"]
            subprocess.run(cmd, check=True)
            step = json.loads(out.read_text())["steps"]["diagnose"]
            runs[str(n)] = {"diagnose_seconds": round(step["seconds"], 2), "peak_rss_mib": round(step["peak_rss_mib"]),
                            "added": step["added"], "report_seconds": round(step["report_seconds"], 2),
                            **run_command(n, Path(tmp))}
            print(f"{n}: {runs[str(n)]}", flush=True)
    sizes = sorted(int(k) for k in runs)
    pairs = [*itertools.pairwise(sizes), *([(sizes[0], sizes[-1])] if len(sizes) > 2 else [])]
    growth = {f"{a:.0e}_to_{b:.0e}".replace("+0", ""): round(
        math.log(runs[str(b)]["diagnose_seconds"] / runs[str(a)]["diagnose_seconds"]) / math.log(b / a), 2)
        for a, b in pairs}
    write_results(args.output, results_doc(
        "diagnose_scaling.py", argv,
        what="bench_calibration.py --samples N --mcap-samples 0 --repeats 1 (--degree 0 below 10^6), one process per "
             "size; diagnose step only (simulation and fit not counted in the time, counted in the peak RSS); "
             "report_seconds: the Markdown report and its plots written after it; command_seconds, command_peak_rss_mib: "
             "fbg-accel-calib diagnose on the same run written as MCAP, in its own process (read, diagnose, report, "
             "YAML, plots)",
        runs=runs, growth_exponent=growth), indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
