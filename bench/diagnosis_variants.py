"""What the checks of a diagnosis's shortcut against its full computation share (not a test, not a bench of its own).

A shortcut of the diagnosis (refining only the candidates that pass, a later step's walk from where the last one
ended) is checked by diagnosing the same recordings with it (the default) and without it, on one lane: the benchmark
run (``bench_calibration.scenario``) at each of ``--samples``, seeds ``--seeds``, and each one-effect scenario of
``test/test_diagnose_sim.py``, seeds ``--scenario-seeds``. ``bench/refinement_check.py`` and
``bench/walk_start_check.py`` each give their own row of a recording (``check``) and call :func:`run`.
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "test"))

from machine_info import machine  # noqa: E402
from output_paths import add_update_results, results_dir  # noqa: E402
from search_thinning_check import benchmark_runs, one_effect_runs  # noqa: E402

from fbg_accel_calibration.diagnosis.diagnose import DiagnosisResult  # noqa: E402
from fbg_accel_calibration.io.recording import Recording  # noqa: E402


def candidates_by_step(res: DiagnosisResult) -> dict[tuple[int, str], object]:
    """Every candidate of every step, by (step, name)."""
    return {(st.step, c.name): c for st in res.steps for c in st.candidates}


def relative_difference(a: float, b: float) -> float:
    """|a - b| relative to the larger of the two (0 when equal)."""
    return 0.0 if a == b else abs(a - b) / max(abs(a), abs(b))


def decided_alike(full: DiagnosisResult, default: DiagnosisResult) -> dict:
    """What both checks compare: the same effects added with the same values (``same_added``), every candidate's
    verdict the same (``same_verdicts``), the calibration's largest difference (``calibration``), the candidates of
    both (``a``, ``b``: :func:`candidates_by_step`), those tested in both (``tested``) and the largest relative
    differences of their held-out gains (``gain``) and p-values (``p``); ``ok``: the first two and the calibration bit
    for bit."""
    a, b = candidates_by_step(full), candidates_by_step(default)
    same_verdicts = a.keys() == b.keys() and all(
        (x.applicable, x.significant, bool(x.implausible), x.refusal)
        == (b[k].applicable, b[k].significant, bool(b[k].implausible), b[k].refusal) for k, x in a.items())
    tested = [k for k in a.keys() & b.keys() if a[k].applicable and b[k].applicable]
    cal = max(float(np.max(np.abs(np.asarray(full.calibration.M) - np.asarray(default.calibration.M)))),
              float(np.max(np.abs(np.asarray(full.calibration.b) - np.asarray(default.calibration.b)))))
    same_added = [tuple(x[:2]) for x in full.added] == [tuple(x[:2]) for x in default.added]
    return {"same_added": same_added, "same_verdicts": same_verdicts, "calibration": cal, "a": a, "b": b,
            "tested": tested, "ok": same_added and same_verdicts and cal == 0.0,
            "gain": max((relative_difference(a[k].rel_gain, b[k].rel_gain) for k in tested), default=0.0),
            "p": max((relative_difference(a[k].p_value, b[k].p_value) for k in tested), default=0.0)}


def run(doc: str, script: str, title: str, remark: str, head: str,
        check: Callable[[str, Recording, str], tuple[str, bool]]) -> int:
    """The command line of a check (``doc``: its module docstring; ``script``: its file name): each recording's row
    (``check(name, recording, static detection)`` -> (Markdown row, decided alike)) printed, then the page
    ``<script>.md`` with ``title``, how many decided alike, ``remark`` and the table under ``head``. Exit status 0
    when every recording decided alike, else 1."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--samples", type=int, nargs="+", default=[100_000, 1_000_000], help="samples of the benchmark runs")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="seeds of the benchmark runs")
    ap.add_argument("--scenario-seeds", type=int, nargs="*", default=[2, 3], help="seeds of the one-effect scenarios")
    ap.add_argument("--output", type=Path, help=f"output (default: {script}.md in the scratch/results directory)")
    add_update_results(ap)
    args = ap.parse_args()
    args.output = args.output or results_dir(args.update_results) / f"{script}.md"
    rows = [check(name, rec, "table") for name, rec in benchmark_runs(args.samples, args.seeds)]
    rows += [check(name, rec, static) for name, rec, static in one_effect_runs(args.scenario_seeds)]
    command = f"python bench/{script}.py " + " ".join(sys.argv[1:])
    m = machine()
    text = (f"# {title}\n\nProduced by `{command.strip()}` ({dt.datetime.now(dt.UTC).isoformat(timespec='seconds')}; "
            f"{m['cpu']}, {m['logical_cpus']} logical CPUs, load {m['load_average_1_5_15']}).\n\n"
            f"The same effects added with the same values, every candidate's verdict the same and the same calibration "
            f"bit for bit: {sum(ok for _, ok in rows)} of {len(rows)}. {remark}\n\n"
            + "\n".join([head, "|" + "---|" * (head.count("|") - 1), *(r for r, _ in rows)]) + "\n")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text)
    print(f"wrote {args.output}")
    return 0 if all(ok for _, ok in rows) else 1
