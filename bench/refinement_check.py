#!/usr/bin/env python3
"""Does refining only the candidates that pass their step's test change what the diagnosis decides? (not a test)

Each search ends by refining the best grid value of its hyper-parameter between its grid neighbours (a bounded
scalar minimisation of the in-sample RSS, about ten designs: ``Evaluator.final_value``). The held-out gain and its
test come from the values nested in the folds (``GridSearch.heldout``), not from that refinement, so by default a
candidate is refined only when it passes its step's test (p below the step's level, gain at least the least gain:
``Evaluator.evaluate``); the others report their grid's best value. Compared with every candidate refined
(``diagnose(..., refine_every_candidate=True)``), on one lane, on the recordings of ``diagnosis_variants`` (the
benchmark run at each of ``--samples``, seeds ``--seeds``; each one-effect scenario of ``test/test_diagnose_sim.py``,
seeds ``--scenario-seeds``).

A row: whether the two add the same effects with the same hyper-parameters (bit for bit), every candidate's verdict
the same, the calibration's largest difference, the largest relative differences of the candidates' held-out gains
and p-values, the candidates left at their grid value and the largest relative difference of their values from the
refined ones, and each diagnosis's CPU time. Writes
refinement_check.md (``--update-results``: in bench/results).

    .venv/bin/python bench/refinement_check.py [--samples 100000 1000000] [--seeds 0 1] [--scenario-seeds 2 3]
"""

from __future__ import annotations

import time

from diagnosis_variants import decided_alike, relative_difference, run

from fbg_accel_calibration.diagnosis.diagnose import DiagnosisResult, diagnose
from fbg_accel_calibration.io.recording import Recording

HEAD = ("| recording | samples | added (every candidate refined) | same added, same values | same verdicts | "
        "calibration's largest difference | gains' largest relative difference | p-values' | candidates left at a grid "
        "value | their values' largest relative difference | CPU: every one refined | CPU: default |")


def compare(every: DiagnosisResult, default: DiagnosisResult) -> dict:
    """What differs between the diagnosis with every candidate refined and the default."""
    d = decided_alike(every, default)
    a, b, tested = d["a"], d["b"], d["tested"]
    left = [k for k in tested if not b[k].hyper_refined and b[k].hyper is not None]
    return {**d, "left": len(left), "of": len(tested),
            "hyper": max((relative_difference(a[k].hyper, b[k].hyper) for k in left), default=0.0)}


def check(name: str, rec: Recording, static: str) -> tuple[str, bool]:
    """One row of the table (Markdown) and whether the default decided and fitted what refining every candidate did."""
    t0 = time.process_time()  # the default first: what a process's first diagnosis pays more is not its saving
    default = diagnose(rec, static=static, lanes=1)
    t1 = time.process_time()
    every = diagnose(rec, static=static, lanes=1, refine_every_candidate=True)
    t2 = time.process_time()
    d = compare(every, default)
    row = (f"| {name} | {len(rec)} | {', '.join(a[0] for a in every.added) or '-'} | "
           f"{'yes' if d['same_added'] else 'NO'} | {'yes' if d['same_verdicts'] else 'NO'} | {d['calibration']:.3g} | "
           f"{d['gain']:.2g} | {d['p']:.2g} | {d['left']} of {d['of']} | {100 * d['hyper']:.3g} % | {t2 - t1:.1f} s | "
           f"{t1 - t0:.1f} s |")
    print(row, flush=True)
    return row, d["ok"]


if __name__ == "__main__":
    raise SystemExit(run(__doc__, "refinement_check", "Refining the candidates that pass their test against refining "
                         "every one", "A candidate's gain and p-value can move where its value's design leaves other "
                         "rows valid (the rows its test compares); a value relative to 0 differs by 100 % where one of "
                         "the two is the null value the parsimony check keeps.", HEAD, check))
