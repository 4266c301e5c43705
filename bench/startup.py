#!/usr/bin/env python3
"""Start-up of every command's ``--help`` against the interpreter's own start-up (``python -c pass``), interleaved.

Each command is run as its console script runs it (``python -c 'from <entry module> import main; main()' --help``),
alternating with ``python -c pass`` in pairs, so that the other load of a shared machine falls on both alike. The CPU
time (user + system) of each child comes from ``os.wait4``; the ratio is the median of the per-pair ratios, the goal
``--help`` <= 0.2 s of CPU. The load average before and after is in the results.

    .venv/bin/python bench/startup.py                    # scratch results (bench/output_paths.py)
    .venv/bin/python bench/startup.py --update-results   # bench/results/startup.json
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from machine_info import results_doc, write_results
from output_paths import add_update_results, results_dir

ENTRY = {"fbg-accel-calib": "fbg_accel_calibration.commands.cli_main", "driver": "fbg_accel_driver.driver_main",
         "calibration": "fbg_accel_calibration.recorder.calibration_main", "board_sim": "fbg_accel_sim.board_sim_main"}
COMMANDS = [("fbg-accel-calib", ["--help"]), ("fbg-accel-calib", ["fit", "--help"]),
            ("fbg-accel-calib", ["diagnose", "--help"]), ("fbg-accel-calib", ["report-measured", "--help"]),
            ("driver", ["--help"]), ("calibration", ["--help"]), ("board_sim", ["--help"])]
GOAL_CPU_S = 0.2


def run_child(argv: list[str]) -> tuple[float, float]:
    """(CPU s, wall s) of one child process, its output discarded. (Its peak RSS is not reported: ``ru_maxrss`` of a
    child includes the parent's resident set at the fork, larger than an interpreter that prints its help.)"""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{argv} exited with {proc.returncode}")
    return usage.ru_utime + usage.ru_stime, wall


def command_argv(command: str, args: list[str]) -> list[str]:
    return [sys.executable, "-c", f"import sys; from {ENTRY[command]} import main; sys.exit(main())", *args]


def measure(pairs: int) -> list[dict]:
    floor_argv = [sys.executable, "-c", "pass"]
    rows = []
    for command, args in COMMANDS:
        argv = command_argv(command, args)
        run_child(argv)  # the first run fills the page cache and writes the .pyc files
        floor, own = [], []
        for _ in range(pairs):
            floor.append(run_child(floor_argv))
            own.append(run_child(argv))
        cpu_ratio = statistics.median(o[0] / max(f[0], 1e-3) for o, f in zip(own, floor, strict=True))
        row = {"command": " ".join([command, *args]),
               "cpu_s": statistics.median(o[0] for o in own), "wall_s": statistics.median(o[1] for o in own),
               "floor_cpu_s": statistics.median(f[0] for f in floor),
               "floor_wall_s": statistics.median(f[1] for f in floor), "cpu_ratio": cpu_ratio}
        row["goal_met"] = row["cpu_s"] <= GOAL_CPU_S
        rows.append(row)
        print(f"{row['command']:40s} CPU {row['cpu_s']:.3f} s  wall {row['wall_s']:.3f} s"
              f"  | python -c pass CPU {row['floor_cpu_s']:.3f} s  ratio {cpu_ratio:.1f}x  goal <= {GOAL_CPU_S} s: "
              f"{'met' if row['goal_met'] else 'NOT met'}", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=15, help="interleaved (floor, command) pairs per command")
    ap.add_argument("--output", type=Path, default=None, help="results JSON (default: startup.json in the results dir)")
    add_update_results(ap)
    args = ap.parse_args(argv)
    load_before = [round(v, 2) for v in os.getloadavg()]
    rows = measure(args.pairs)
    out = args.output or results_dir(args.update_results) / "startup.json"
    write_results(out, results_doc("startup.py", argv, benchmark="startup", pairs=args.pairs, goal_cpu_s=GOAL_CPU_S,
                                   load_average_before=load_before, commands=rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
