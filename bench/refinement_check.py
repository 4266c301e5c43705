#!/usr/bin/env python3
"""Does refining only the candidates that pass their step's test change what the diagnosis decides? (not a test)

Each search ends by refining the best grid value of its hyper-parameter between its grid neighbours (a bounded
scalar minimisation of the in-sample RSS, about ten designs: ``Evaluator.final_value``). The held-out gain and its
test come from the values nested in the folds (``GridSearch.heldout``), not from that refinement, so by default a
candidate is refined only when it passes its step's test (p below the step's level, gain at least the least gain:
``Evaluator.evaluate``); the others report their grid's best value. Compared with every candidate refined
(``diagnose(..., refine_every_candidate=True)``), on one lane, on

* the benchmark run (``bench_calibration.scenario``: every nominal effect, four chamber levels) at each of
  ``--samples``, seeds ``--seeds``;
* each one-effect scenario of ``test/test_diagnose_sim.py``, seeds ``--scenario-seeds``.

A row: whether the two add the same effects with the same hyper-parameters (bit for bit), every candidate's verdict
the same, the calibration's largest difference, the largest relative differences of the candidates' held-out gains
and p-values, the candidates left at their grid value and the largest relative difference of their values from the
refined ones, and each diagnosis's CPU time. Writes
refinement_check.md (``--update-results``: in bench/results).

    .venv/bin/python bench/refinement_check.py [--samples 100000 1000000] [--seeds 0 1] [--scenario-seeds 2 3]
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
from search_thinning_check import benchmark_runs, one_effect_runs  # noqa: E402

from fbg_accel_calibration.diagnosis.diagnose import DiagnosisResult, diagnose  # noqa: E402
from fbg_accel_calibration.io.recording import Recording  # noqa: E402

HEAD = ("| recording | samples | added (every candidate refined) | same added, same values | same verdicts | "
        "calibration's largest difference | gains' largest relative difference | p-values' | candidates left at a grid "
        "value | their values' largest relative difference | CPU: every one refined | CPU: default |")


def candidates_by_step(res: DiagnosisResult) -> dict[tuple[int, str], object]:
    """Every candidate of every step, by (step, name)."""
    return {(st.step, c.name): c for st in res.steps for c in st.candidates}


def relative_difference(a: float, b: float) -> float:
    """|a - b| relative to the larger of the two (0 when equal)."""
    return 0.0 if a == b else abs(a - b) / max(abs(a), abs(b))


def compare(every: DiagnosisResult, default: DiagnosisResult) -> dict:
    """What differs between the diagnosis with every candidate refined and the default."""
    a, b = candidates_by_step(every), candidates_by_step(default)
    same_verdicts = a.keys() == b.keys() and all(
        (x.applicable, x.significant, bool(x.implausible), x.refusal)
        == (b[k].applicable, b[k].significant, bool(b[k].implausible), b[k].refusal) for k, x in a.items())
    tested = [k for k in a.keys() & b.keys() if a[k].applicable and b[k].applicable]
    left = [k for k in tested if not b[k].hyper_refined and b[k].hyper is not None]
    cal = max(float(np.max(np.abs(np.asarray(every.calibration.M) - np.asarray(default.calibration.M)))),
              float(np.max(np.abs(np.asarray(every.calibration.b) - np.asarray(default.calibration.b)))))
    return {"same_added": [tuple(x[:2]) for x in every.added] == [tuple(x[:2]) for x in default.added],
            "same_verdicts": same_verdicts, "calibration": cal, "left": len(left), "of": len(tested),
            "gain": max((relative_difference(a[k].rel_gain, b[k].rel_gain) for k in tested), default=0.0),
            "p": max((relative_difference(a[k].p_value, b[k].p_value) for k in tested), default=0.0),
            "hyper": max((relative_difference(a[k].hyper, b[k].hyper) for k in left), default=0.0)}


def check(name: str, rec: Recording, static: str) -> tuple[str, bool]:
    """One row of the table (Markdown) and whether the default decided and fitted what refining every candidate did."""
    t0 = time.process_time()  # the default first: what a process's first diagnosis pays more is not its saving
    default = diagnose(rec, static=static, lanes=1)
    t1 = time.process_time()
    every = diagnose(rec, static=static, lanes=1, refine_every_candidate=True)
    t2 = time.process_time()
    d = compare(every, default)
    ok = d["same_added"] and d["same_verdicts"] and d["calibration"] == 0.0
    row = (f"| {name} | {len(rec)} | {', '.join(a[0] for a in every.added) or '-'} | "
           f"{'yes' if d['same_added'] else 'NO'} | {'yes' if d['same_verdicts'] else 'NO'} | {d['calibration']:.3g} | "
           f"{d['gain']:.2g} | {d['p']:.2g} | {d['left']} of {d['of']} | {100 * d['hyper']:.3g} % | {t2 - t1:.1f} s | "
           f"{t1 - t0:.1f} s |")
    print(row, flush=True)
    return row, ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, nargs="+", default=[100_000, 1_000_000], help="samples of the benchmark runs")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="seeds of the benchmark runs")
    ap.add_argument("--scenario-seeds", type=int, nargs="*", default=[2, 3], help="seeds of the one-effect scenarios")
    ap.add_argument("--output", type=Path, help="output (default: refinement_check.md in the scratch/results directory)")
    add_update_results(ap)
    args = ap.parse_args()
    args.output = args.output or results_dir(args.update_results) / "refinement_check.md"
    rows = [check(name, rec, "table") for name, rec in benchmark_runs(args.samples, args.seeds)]
    rows += [check(name, rec, static) for name, rec, static in one_effect_runs(args.scenario_seeds)]
    command = "python bench/refinement_check.py " + " ".join(sys.argv[1:])
    m = machine()
    text = (f"# Refining the candidates that pass their test against refining every one\n\nProduced by "
            f"`{command.strip()}` ({dt.datetime.now(dt.UTC).isoformat(timespec='seconds')}; {m['cpu']}, "
            f"{m['logical_cpus']} logical CPUs, load {m['load_average_1_5_15']}).\n\n"
            f"The same effects added with the same values, every candidate's verdict the same and the same calibration "
            f"bit for bit: {sum(ok for _, ok in rows)} of {len(rows)}. A candidate's gain and p-value can move where "
            f"its value's design leaves other rows valid (the rows its test compares); a value relative to 0 differs "
            f"by 100 % where one of the two is the null value the parsimony check keeps.\n\n"
            + "\n".join([HEAD, "|" + "---|" * 12, *(r for r, _ in rows)]) + "\n")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text)
    print(f"wrote {args.output}")
    return 0 if all(ok for _, ok in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
