#!/usr/bin/env python3
"""Run the tests' further seeds: every test case marked ``sweep`` (deselected from the suite, test/conftest.py).

A test over seeds keeps one or two representative cases in the suite (scripts/test.sh), each still failing on the
defect it was written for; its further seeds are marked ``pytest.mark.sweep`` and run here, with the same assertions
(the cases: ``pytest --sweeps --collect-only -m sweep``, and the page this writes).

Usage::

    .venv/bin/python bench/seed_sweeps.py                    # every sweep case of test/, page in the scratch dir
    .venv/bin/python bench/seed_sweeps.py test/test_diagnose_sim.py
    .venv/bin/python bench/seed_sweeps.py --update-results   # docs/results/seed_sweeps.md

Writes a page with each case's outcome and seconds (to the scratch directory of bench/output_paths.py, or with
``--update-results`` to docs/results/seed_sweeps.md); exit status 1 when a case fails. Run it after a change to
what the swept tests guard (the diagnosis's checks); it takes a few minutes on 2 cores (``nice`` it on a shared
machine).
"""

from __future__ import annotations

import argparse
import datetime as dt
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from machine_info import machine
from output_paths import RESULTS_PAGES, add_update_results, scratch_dir

ROOT = Path(__file__).resolve().parents[1]


def run(targets: list[str], junit: Path) -> int:
    """pytest on ``targets`` with only the sweep cases selected; returns its exit status."""
    cmd = [sys.executable, "-m", "pytest", *targets, "--sweeps", "-m", "sweep", "-q", "-p", "no:randomly",
           "-p", "no:cacheprovider", f"--junitxml={junit}"]
    return subprocess.run(cmd, cwd=ROOT, check=False).returncode


def cases(junit: Path) -> list[tuple[str, str, float]]:
    """(test id, outcome, seconds) of every case in the JUnit file."""
    rows = []
    for tc in ET.parse(junit).getroot().iter("testcase"):
        outcome = "passed"
        for kind in ("failure", "error", "skipped"):
            if tc.find(kind) is not None:
                outcome = {"failure": "FAILED", "error": "ERROR", "skipped": "skipped"}[kind]
        rows.append((f"{tc.get('classname', '').replace('.', '/')}.py::{tc.get('name')}", outcome,
                     float(tc.get("time", 0.0))))
    return rows


def page(rows: list[tuple[str, str, float]], targets: list[str], status: int) -> str:
    m = machine()
    lines = [
        "# Further seeds of the tests (sweep cases)",
        "",
        f"Regenerate: `.venv/bin/python bench/seed_sweeps.py {' '.join(targets)} --update-results`".replace("  ", " "),
        "",
        "The cases marked `sweep` in the tests (test/conftest.py `leave_out_sweeps`): further seeds of tests whose "
        "representative cases the suite runs. Same assertions as in the suite.",
        "",
        f"Run {dt.datetime.now(dt.UTC).strftime('%Y-%m-%d %H:%M UTC')} on {m['cpu']} ({m['logical_cpus']} logical CPUs, "
        f"load {m['load_average_1_5_15']}), Python {m['python']}, numpy {m['numpy']}; pytest exit status {status}.",
        "",
        "| case | outcome | s |",
        "|---|---|---:|",
        *(f"| `{name}` | {outcome} | {seconds:.1f} |" for name, outcome, seconds in rows),
        "",
        f"{sum(o == 'passed' for _, o, _ in rows)} of {len(rows)} passed, {sum(s for _, _, s in rows):.0f} s in all.",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("targets", nargs="*", default=["test/"], help="test files or directories (default: test/)")
    add_update_results(ap)
    args = ap.parse_args(argv)
    out_dir = scratch_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    junit = out_dir / "seed_sweeps.xml"
    status = run(args.targets, junit)
    if not junit.is_file() or status == 5:  # pytest's 5: nothing collected (no sweep case under the targets)
        print(f"no sweep case ran (pytest exit {status})", file=sys.stderr)
        return 2
    rows = cases(junit)
    md = RESULTS_PAGES / "seed_sweeps.md" if args.update_results else out_dir / "seed_sweeps.md"
    md.write_text(page(rows, args.targets if args.targets != ["test/"] else [], status))
    print(f"{sum(o == 'passed' for _, o, _ in rows)} of {len(rows)} sweep cases passed; wrote {md}")
    return 0 if status == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
