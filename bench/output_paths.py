"""Where the bench scripts write: a scratch directory by default, the committed results only when asked.

A benchmark or check run for a look, or on another machine, must not silently replace the committed figures that
README and docs/results/ quote. So each script writes to :func:`scratch_dir` (``$FBG_ACCEL_BENCH_DIR``, else
``<tmp>/fbg_accel_bench_<uid>``) unless given ``--output`` (an explicit file) or ``--update-results`` (the committed
``bench/results/``; ``bench/run_all.py --update-results`` also rewrites ``docs/results/benchmarks.md``).
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "bench" / "results"
RESULTS_PAGES = ROOT / "docs" / "results"
SCRATCH_ENV = "FBG_ACCEL_BENCH_DIR"


def scratch_dir() -> Path:
    """The directory a run writes to unless told otherwise."""
    return Path(os.environ.get(SCRATCH_ENV) or Path(tempfile.gettempdir()) / f"fbg_accel_bench_{os.getuid()}")


def add_update_results(ap: argparse.ArgumentParser) -> None:
    """The ``--update-results`` flag of a bench script."""
    ap.add_argument("--update-results", action="store_true",
                    help=f"write into the committed {COMMITTED.relative_to(ROOT)}/ (default: {scratch_dir()}, "
                         f"or ${SCRATCH_ENV})")


def results_dir(update_results: bool) -> Path:
    """The committed results directory with ``update_results``, else the scratch directory (created)."""
    d = COMMITTED if update_results else scratch_dir()
    d.mkdir(parents=True, exist_ok=True)
    return d


def output_dir_from_command_line(description: str, argv: list[str] | None = None) -> Path:
    """For a script without options of its own: parse ``--update-results`` and return where to write."""
    ap = argparse.ArgumentParser(description=description)
    add_update_results(ap)
    return results_dir(ap.parse_args(argv).update_results)
