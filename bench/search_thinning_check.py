"""Does a search thinned as the default thins it choose what the full search chooses? (not a test)

Above ``SEARCH_ROWS`` fitted samples the diagnosis evaluates its candidates on every k-th one (``search_samples``; k
lowered until the thinned samples keep ``MIN_SEARCH_INFORMATION`` of what a visit's samples tell of its mean). With
``SEARCH_ROWS`` = 5 * 10^4 (10^5 before) k is 15 or 16 at 10^6 samples of the benchmark run (8 before). Compared with the
full search (``search_rows=None``):

* the benchmark run (``bench_calibration.scenario``: every nominal effect, four chamber levels, 100 Hz, 3 s visits) at
  each of ``--samples``, seeds ``--seeds``, thinned with ``SEARCH_ROWS`` = 10^5 and with the default;
* a stress test the default never makes: each one-effect scenario of ``test/test_diagnose_sim.py`` (42 visits at
  100 Hz, 126 at 25 Hz; 12 575 to 16 700 samples: never thinned by default), seeds 2..4, with k = 8 and k = 15 forced
  (through ``search_rows``; the guard lowers k where the noise is nearly white from sample to sample): the same steps
  on 20 to 60 times fewer visits than the benchmark run's 2500 at 10^6 samples.

A row: the effects added by the full search, whether each thinned search adds the same in the same order, the largest
relative difference of their hyper-parameters and of the held-out RMSE after, the step and information each thinned
search used, and the times. Writes bench/results/search_thinning_check.md.

    .venv/bin/python bench/search_thinning_check.py [--samples 200000 1000000] [--seeds 1 2]
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "test"))

from bench_calibration import scenario  # noqa: E402
from machine_info import machine  # noqa: E402
from output_paths import add_update_results, results_dir  # noqa: E402
from test_diagnose_sim import SCENARIOS, _config  # noqa: E402

from fbg_accel_calibration.diagnosis.diagnose import DiagnosisResult, diagnose  # noqa: E402
from fbg_accel_calibration.diagnosis.search import SEARCH_ROWS  # noqa: E402
from fbg_accel_calibration.io.recording import Recording  # noqa: E402
from fbg_accel_sim.board_physics import simulate_recording  # noqa: E402

OLD_SEARCH_ROWS = 100_000  # SEARCH_ROWS before 2026-11-27
FORCED_STEPS = (8, 15)  # the default's step at 10^6 samples of the benchmark run before and since then


def _differences(full: DiagnosisResult, thin: DiagnosisResult) -> tuple[bool, float, float]:
    """(same effects added in the same order, largest relative difference of their hyper-parameters, of the held-out
    RMSE after per axis)."""
    same = [a[0] for a in thin.added] == [a[0] for a in full.added]
    hyper = [abs(t[1] - f[1]) / max(abs(f[1]), 1e-12) for f, t in zip(full.added, thin.added, strict=False)
             if f[0] == t[0] and f[1] is not None and t[1] is not None]
    rmse = np.abs(thin.after_heldout_rmse - full.after_heldout_rmse) / full.after_heldout_rmse
    return same, max(hyper, default=0.0), float(rmse.max())


def benchmark_runs(samples: list[int], seeds: list[int]) -> Iterator[tuple[str, Recording]]:
    """(name, recording) of the benchmark run (``bench_calibration.scenario``) at each of ``samples``, each seed."""
    for n in samples:
        cfg, duration = scenario(n)
        for seed in seeds:
            yield f"benchmark run, seed {seed}", simulate_recording(cfg, seed=seed, duration_s=duration)


def one_effect_runs(seeds: Iterable[int]) -> Iterator[tuple[str, Recording, str]]:
    """(name, recording, its static detection) of each one-effect scenario of ``test/test_diagnose_sim.py``, each
    seed."""
    for eff, (scale, extra, static) in SCENARIOS.items():
        for seed in seeds:
            yield (f"{eff} x{scale:g}, seed {seed}",
                   simulate_recording(_config({**extra, f"effects.{eff}.scale": scale}), seed=seed), static)


def check(name: str, rec: Recording, static: str, thinned: Callable[[int], list[int]]) -> tuple[str, list[bool]]:
    """One row of the table (Markdown) and, for each thinned search, whether it added what the full one added.
    ``thinned``: the ``search_rows`` of each thinned search, of the number of fitted samples."""
    t0 = time.perf_counter()
    full = diagnose(rec, static=static, search_rows=None)
    seconds = time.perf_counter() - t0
    n_fit = len(full.steps[0].candidates[0].delta_rows)
    cells, same_each = [], []
    for rows in thinned(n_fit):
        t0 = time.perf_counter()
        thin = diagnose(rec, static=static, search_rows=rows)
        same, hyper, rmse = _differences(full, thin)
        same_each.append(same)
        cells.append(f"{'same' if same else 'DIFFERENT: ' + (', '.join(a[0] for a in thin.added) or 'none')} | "
                     f"{100 * hyper:.2g} % | {100 * rmse:.2g} % | {thin.settings['search_step']}, "
                     f"{100 * thin.settings['search_information']:.0f} % | {time.perf_counter() - t0:.1f} s")
    row = (f"| {name} | {len(rec)} ({n_fit} fitted) | {', '.join(a[0] for a in full.added) or '-'} | {seconds:.1f} s | "
           + " | ".join(cells) + " |")
    print(row, flush=True)
    return row, same_each


def table(results: list[tuple[str, list[bool]]], labels: list[str]) -> str:
    """How many of the thinned searches of each label added what the full one added, then the table."""
    counts = "; ".join(f"{label}: {sum(same[i] for _, same in results)} of {len(results)}" for i, label in enumerate(labels))
    head = ("| recording | samples | added by the full search | its time | "
            + " | ".join(f"{label}: added | hyper-parameter diff. | held-out RMSE diff. | step, information kept | "
                         "its time" for label in labels) + " |")
    return (f"The thinned search adds what the full search adds, in the same order: {counts}.\n\n"
            + "\n".join([head, "|" + "---|" * (4 + 5 * len(labels)), *(r for r, _ in results)]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, nargs="+", default=[200_000, 1_000_000], help="samples of the benchmark runs")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2], help="seeds of the benchmark runs")
    ap.add_argument("--output", type=Path, help="output (default: search_thinning_check.md in the scratch/results directory)")
    add_update_results(ap)
    args = ap.parse_args()
    args.output = args.output or results_dir(args.update_results) / "search_thinning_check.md"
    runs = [check(name, rec, "table", lambda _: [OLD_SEARCH_ROWS, SEARCH_ROWS])
            for name, rec in benchmark_runs(args.samples, args.seeds)]
    stress = [check(name, rec, static, lambda n_fit: [n_fit // k for k in FORCED_STEPS])
              for name, rec, static in one_effect_runs(range(2, 5))]
    command = "python bench/search_thinning_check.py " + " ".join(sys.argv[1:])
    m = machine()
    text = (f"# Thinned search against the full search\n\nProduced by `{command.strip()}` "
            f"({dt.datetime.now(dt.UTC).isoformat(timespec='seconds')}; {m['cpu']}, {m['logical_cpus']} logical CPUs, "
            f"load {m['load_average_1_5_15']}).\n\n"
            "## The benchmark run, thinned as the default thins it\n\n"
            + table(runs, [f"SEARCH_ROWS = {OLD_SEARCH_ROWS}", f"SEARCH_ROWS = {SEARCH_ROWS} (default)"])
            + "\n\n## Stress test: the one-effect scenarios (never thinned by default) with forced steps\n\n"
            + table(stress, [f"k = {k} forced" for k in FORCED_STEPS]) + "\n")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
