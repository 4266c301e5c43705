#!/usr/bin/env python3
"""Does walking a candidate's grid from where its last search ended change what the diagnosis decides? (not a test)

A hyper-parameter search visits some of its grid's values and walks from the best ones until each fold's best and the
best mean have both neighbours visited (``cv.search_batches``). The first step's searches start from every 4th
value; after it, by default, a candidate's searches start where its search of the step before ended
(``GridSearch.walked_to``). Both find what visiting every value finds wherever each fold's training RSS has one
minimum over the grid; where one has two, they can end at different ones. Compared with every search started from
every 4th value (``diagnose(..., walk_from_last_step=False)``), on one lane, on the recordings of
``diagnosis_variants`` (the benchmark run at each of ``--samples``, seeds ``--seeds``; each one-effect scenario of
``test/test_diagnose_sim.py``, seeds ``--scenario-seeds``).

A row: whether the two add the same effects with the same hyper-parameters (bit for bit), every candidate's verdict
the same, the calibration's largest difference, the candidates whose held-out gain, p-value or value differ and
the largest relative differences, the designs each built and each diagnosis's CPU time. Writes walk_start_check.md
(``--update-results``: in bench/results).

    .venv/bin/python bench/walk_start_check.py [--samples 100000 1000000] [--seeds 0 1] [--scenario-seeds 2 3]
"""

from __future__ import annotations

import time

from diagnosis_variants import decided_alike, relative_difference, run

from fbg_accel_calibration.diagnosis import search
from fbg_accel_calibration.diagnosis.diagnose import DiagnosisResult, diagnose
from fbg_accel_calibration.io.recording import Recording

HEAD = ("| recording | samples | added (every search from every 4th value) | same added, same values | same verdicts | "
        "calibration's largest difference | candidates whose gain differs | gains' largest relative difference | "
        "p-values' | values' | designs: from every 4th | designs: default | CPU: from every 4th | CPU: default |")


def compare(cold: DiagnosisResult, warm: DiagnosisResult) -> dict:
    """What differs between the diagnosis with every search from every 4th value (``cold``) and the default."""
    d = decided_alike(cold, warm)
    a, b, tested = d["a"], d["b"], d["tested"]
    valued = [k for k in tested if a[k].hyper is not None and b[k].hyper is not None]
    return {**d, "of": len(tested), "moved": sum(a[k].rel_gain != b[k].rel_gain for k in tested),
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
    row = (f"| {name} | {len(rec)} | {', '.join(a[0] for a in cold.added) or '-'} | "
           f"{'yes' if d['same_added'] else 'NO'} | {'yes' if d['same_verdicts'] else 'NO'} | {d['calibration']:.3g} | "
           f"{d['moved']} of {d['of']} | {d['gain']:.2g} | {d['p']:.2g} | {d['hyper']:.2g} | {n_cold} | {n_warm} | "
           f"{t_cold:.1f} s | {t_warm:.1f} s |")
    print(row, flush=True)
    return row, d["ok"]


if __name__ == "__main__":
    raise SystemExit(run(__doc__, "walk_start_check", "Searches from where the last step's ended against searches from "
                         "every 4th value", "A candidate's held-out gain and p-value move where a fold's training RSS "
                         "has more than one minimum over the grid and the two walks end at different ones; its value "
                         "where the mean training RSS has.", HEAD, check))
