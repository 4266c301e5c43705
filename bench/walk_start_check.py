#!/usr/bin/env python3
"""Does walking a candidate's grid from where its last search ended change what the diagnosis decides? (not a test)

A hyper-parameter search visits some of its grid's values and walks from the best ones until each fold's best and the
best mean have both neighbours visited (``cv.search_batches``). The first step's searches start from every 4th
value; after it, by default, a candidate's searches start where its search of the step before ended
(``GridSearch.walked_to``). Both find what visiting every value finds wherever each fold's training RSS has one
minimum over the grid; where one has two, they can end at different ones. Compared with every search started from
every 4th value (``diagnose(..., walk_from_last_step=False)``), on one lane, on

* the benchmark run (``bench_calibration.scenario``: every nominal effect, four chamber levels) at each of
  ``--samples``, seeds ``--seeds``;
* each one-effect scenario of ``test/test_diagnose_sim.py``, seeds ``--scenario-seeds``.

A row: whether the two add the same effects with the same hyper-parameters (bit for bit), every candidate's verdict
the same, the calibration's largest difference, the candidates whose held-out gain, p-value or value differ and
the largest relative differences, the designs each built and each diagnosis's CPU time. Writes walk_start_check.md
(``--update-results``: in bench/results).

    .venv/bin/python bench/walk_start_check.py [--samples 100000 1000000] [--seeds 0 1] [--scenario-seeds 2 3]
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "test"))

from machine_info import machine  # noqa: E402
from output_paths import add_update_results, results_dir  # noqa: E402
from refinement_check import candidates_by_step, relative_difference  # noqa: E402
from search_thinning_check import benchmark_runs, one_effect_runs  # noqa: E402

from fbg_accel_calibration.diagnosis import search  # noqa: E402
from fbg_accel_calibration.diagnosis.diagnose import DiagnosisResult, diagnose  # noqa: E402
from fbg_accel_calibration.io.recording import Recording  # noqa: E402

HEAD = ("| recording | samples | added (every search from every 4th value) | same added, same values | same verdicts | "
        "calibration's largest difference | candidates whose gain differs | gains' largest relative difference | "
        "p-values' | values' | designs: from every 4th | designs: default | CPU: from every 4th | CPU: default |")


def compare(cold: DiagnosisResult, warm: DiagnosisResult) -> dict:
    """What differs between the diagnosis with every search from every 4th value (``cold``) and the default."""
    a, b = candidates_by_step(cold), candidates_by_step(warm)
    same_verdicts = a.keys() == b.keys() and all(
        (x.applicable, x.significant, bool(x.implausible), x.refusal)
        == (b[k].applicable, b[k].significant, bool(b[k].implausible), b[k].refusal) for k, x in a.items())
    tested = [k for k in a.keys() & b.keys() if a[k].applicable and b[k].applicable]
    valued = [k for k in tested if a[k].hyper is not None and b[k].hyper is not None]
    cal = max(float(np.max(np.abs(np.asarray(cold.calibration.M) - np.asarray(warm.calibration.M)))),
              float(np.max(np.abs(np.asarray(cold.calibration.b) - np.asarray(warm.calibration.b)))))
    return {"same_added": [tuple(x[:2]) for x in cold.added] == [tuple(x[:2]) for x in warm.added],
            "same_verdicts": same_verdicts, "calibration": cal, "of": len(tested),
            "moved": sum(a[k].rel_gain != b[k].rel_gain for k in tested),
            "gain": max((relative_difference(a[k].rel_gain, b[k].rel_gain) for k in tested), default=0.0),
            "p": max((relative_difference(a[k].p_value, b[k].p_value) for k in tested), default=0.0),
            "hyper": max((relative_difference(a[k].hyper, b[k].hyper) for k in valued), default=0.0)}


def counted(rec: Recording, static: str, **kwargs) -> tuple[DiagnosisResult, int, float]:
    """``diagnose(rec, static=static, lanes=1, **kwargs)``, the designs its searches built and its CPU time (s)."""
    build, built = search.build_design, [0]

    def counting(*args, **kw):
        built[0] += 1
        return build(*args, **kw)

    search.build_design = counting
    try:
        t0 = time.process_time()
        res = diagnose(rec, static=static, lanes=1, **kwargs)
        return res, built[0], time.process_time() - t0
    finally:
        search.build_design = build


def check(name: str, rec: Recording, static: str) -> tuple[str, bool]:
    """One row of the table (Markdown) and whether the default decided and fitted what the searches from every 4th
    value did."""
    warm, n_warm, t_warm = counted(rec, static)  # the default first: a process's first diagnosis pays more
    cold, n_cold, t_cold = counted(rec, static, walk_from_last_step=False)
    d = compare(cold, warm)
    ok = d["same_added"] and d["same_verdicts"] and d["calibration"] == 0.0
    row = (f"| {name} | {len(rec)} | {', '.join(a[0] for a in cold.added) or '-'} | "
           f"{'yes' if d['same_added'] else 'NO'} | {'yes' if d['same_verdicts'] else 'NO'} | {d['calibration']:.3g} | "
           f"{d['moved']} of {d['of']} | {d['gain']:.2g} | {d['p']:.2g} | {d['hyper']:.2g} | {n_cold} | {n_warm} | "
           f"{t_cold:.1f} s | {t_warm:.1f} s |")
    print(row, flush=True)
    return row, ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, nargs="+", default=[100_000, 1_000_000], help="samples of the benchmark runs")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="seeds of the benchmark runs")
    ap.add_argument("--scenario-seeds", type=int, nargs="*", default=[2, 3], help="seeds of the one-effect scenarios")
    ap.add_argument("--output", type=Path, help="output (default: walk_start_check.md in the scratch/results directory)")
    add_update_results(ap)
    args = ap.parse_args()
    args.output = args.output or results_dir(args.update_results) / "walk_start_check.md"
    rows = [check(name, rec, "table") for name, rec in benchmark_runs(args.samples, args.seeds)]
    rows += [check(name, rec, static) for name, rec, static in one_effect_runs(args.scenario_seeds)]
    command = "python bench/walk_start_check.py " + " ".join(sys.argv[1:])
    m = machine()
    text = (f"# Searches from where the last step's ended against searches from every 4th value\n\nProduced by "
            f"`{command.strip()}` ({dt.datetime.now(dt.UTC).isoformat(timespec='seconds')}; {m['cpu']}, "
            f"{m['logical_cpus']} logical CPUs, load {m['load_average_1_5_15']}).\n\n"
            f"The same effects added with the same values, every candidate's verdict the same and the same calibration "
            f"bit for bit: {sum(ok for _, ok in rows)} of {len(rows)}. A candidate's held-out gain and p-value move "
            f"where a fold's training RSS has more than one minimum over the grid and the two walks end at different "
            f"ones; its value where the mean training RSS has.\n\n"
            + "\n".join([HEAD, "|" + "---|" * 14, *(r for r, _ in rows)]) + "\n")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text)
    print(f"wrote {args.output}")
    return 0 if all(ok for _, ok in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
