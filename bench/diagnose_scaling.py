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

``--trials N [N ...]``: instead, where the diagnosis of the same run spends its CPU time, on one lane, per size: each
hyper-parameter search (``Evaluator._grid_search`` and ``final_value``) by the phase it runs in (a candidate on top
of the model, one judged again at the degree chosen with it in, the confounding pairs, the backward step, the step check) and by
candidate, with its grid's size, the designs it built (its trials: grid values visited, the refinement's values, the
parsimony check) and their CPU time; and the
diagnosis's CPU outside the searches. It says how the cost grows with N, with the number of candidates (each step
searches every candidate left, the confounding check the best against up to three others) and with each grid
(``search_batches`` visits every 4th value then the neighbours of the folds' bests; the refinement up to 25 more):

    .venv/bin/python bench/diagnose_scaling.py --trials 100000 1000000
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


# innermost first; judged_at_its_degree: a refused candidate judged again at the degree chosen with it in
SEARCH_PHASES = ("step_check", "confounding", "drop_explained", "judged_at_its_degree", "_evaluate_on")


def trial_costs(n: int) -> dict:
    """CPU seconds of the diagnosis of the benchmark run of ``n`` samples on one lane, split by hyper-parameter search
    (phase, candidate): searches, grid size, designs built, CPU (see the module docstring). In this process."""
    import traceback

    from fbg_accel_calibration.diagnosis import search
    from fbg_accel_calibration.diagnosis.diagnose import diagnose
    from fbg_accel_sim.board_physics import simulate_recording

    cfg, duration = scenario(n)
    rec = simulate_recording(cfg, seed=0, duration_s=duration)
    rows: dict[tuple[str, str], dict] = {}
    running: list[tuple[str, str]] = []
    designs = {"outside searches": 0}
    grid_search, final_value, build_design = (search.Evaluator._grid_search, search.Evaluator.final_value,
                                              search.build_design)

    def timed(searches: int, method):
        """``method`` (the grid search, or the final value worked out of it) timed under its phase and candidate."""
        def run(self, spec, eff, *a, **kw):
            names = [f.name for f in traceback.extract_stack()]
            phase = next((p for p in SEARCH_PHASES if p in names), "other")
            key = (phase.lstrip("_").replace("evaluate_on", "candidate on top of the model"), eff.name)
            grid = eff.hyper_grid(self.data)
            row = rows.setdefault(key, {"searches": 0, "grid": 0 if grid is None else len(grid), "designs": 0,
                                        "cpu_s": 0.0})
            running.append(key)
            t0 = time.process_time()
            try:
                return method(self, spec, eff, *a, **kw)
            finally:
                running.pop()
                row["searches"] += searches
                row["cpu_s"] += time.process_time() - t0
        return run

    def counted_build_design(*a, **kw):
        if running:
            rows[running[-1]]["designs"] += 1
        else:
            designs["outside searches"] += 1
        return build_design(*a, **kw)

    search.Evaluator._grid_search, search.Evaluator.final_value = timed(1, grid_search), timed(0, final_value)
    search.build_design = counted_build_design
    try:
        t0 = time.process_time()
        diagnose(rec, sensor_id="bench", lanes=1)
        total = time.process_time() - t0
    finally:
        search.Evaluator._grid_search, search.Evaluator.final_value = grid_search, final_value
        search.build_design = build_design
    searches = sorted(({"phase": k[0], "candidate": k[1], **{f: round(v, 3) if isinstance(v, float) else v
                                                            for f, v in r.items()}} for k, r in rows.items()),
                      key=lambda r: -r["cpu_s"])
    in_searches = sum(r["cpu_s"] for r in searches)
    by_phase: dict[str, float] = {}
    for r in searches:
        by_phase[r["phase"]] = round(by_phase.get(r["phase"], 0.0) + r["cpu_s"], 3)
    return {"diagnose_cpu_s": round(total, 3), "in_searches_cpu_s": round(in_searches, 3),
            "designs_in_searches": sum(r["designs"] for r in searches),
            "designs_outside_searches": designs["outside searches"], "by_phase_cpu_s": by_phase, "searches": searches}


def print_trials(n: int, res: dict) -> None:
    print(f"{n} samples: diagnose {res['diagnose_cpu_s']:.2f} s CPU, {res['in_searches_cpu_s']:.2f} s in "
          f"{sum(r['searches'] for r in res['searches'])} searches ({res['designs_in_searches']} designs; "
          f"{res['designs_outside_searches']} outside them); by phase {res['by_phase_cpu_s']}")
    print("| phase | candidate | searches | grid | designs | CPU s | per design ms |")
    print("|---|---|---|---|---|---|---|")
    for r in res["searches"]:
        print(f"| {r['phase']} | {r['candidate']} | {r['searches']} | {r['grid']} | {r['designs']} | {r['cpu_s']:.2f} | "
              f"{1e3 * r['cpu_s'] / max(r['designs'], 1):.0f} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--trials", type=int, nargs="+", default=None,
                    help="sizes at which to split the diagnosis's CPU by search (module docstring)")
    ap.add_argument("--output", type=Path, help="output file (default: diagnose_scaling.json in the scratch/results directory)")
    add_update_results(ap)
    args = ap.parse_args(argv)
    if args.trials:
        args.output = args.output or results_dir(args.update_results) / "diagnose_trials.json"
        runs = {}
        for n in args.trials:
            runs[str(n)] = trial_costs(n)
            print_trials(n, runs[str(n)])
        write_results(args.output, results_doc(
            "diagnose_scaling.py", argv,
            what="CPU time of diagnose() on one lane (lanes=1) of bench_calibration.scenario(N), seed 0, in this "
                 "process, split by hyper-parameter search (Evaluator._grid_search and final_value: phase, "
                 "candidate) with the designs each built (build_design calls: its trials)", runs=runs), indent=1)
        return 0
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
