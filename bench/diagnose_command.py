#!/usr/bin/env python3
"""``fbg-accel-calib diagnose``, the command a user runs, against the diagnosis alone on the same recording (issue 36).

Goal: the command's CPU time <= 1.5x that of the diagnosis alone. Both are child processes run alternately (diagnosis,
command, diagnosis, ...; ``floors.interleaved``): their CPU times (user + system, all threads, ``os.wait4``) and the
median of the per-pair ratios. The diagnosis alone (``--diagnosis-alone``) imports the engine, reads the recording
and calls ``diagnose()`` with the command's defaults; the command adds its argument parsing, the report text on
stdout, the markdown report with its PNG figures (``--out``; by default those the report shows, ``--figures report``)
and the refitted calibration (``--yaml``). The command freezes what is alive at its end out of the interpreter's last
garbage collections (``cli_main._freeze_at_exit``), a plain script does not: so the command is also set against the
diagnosis alone exiting the same way (``--exit-frozen``, interleaved with the command in pairs of their own), the
ratio of what the command adds to the diagnosis alone, its exit aside.

Then one more child (``--breakdown``) says where the command's time goes, in CPU seconds of one process: importing
the engine, reading, the diagnosis, the report text and markdown, importing matplotlib, each figure, the YAML.

The data: the simulator's benchmark run (``bench_calibration.scenario``, every effect at its default) of N samples,
written as a calibration MCAP into ``--dir`` (a temporary directory by default).

    .venv/bin/python bench/diagnose_command.py                        # 10^4 and 10^5 samples, scratch results
    .venv/bin/python bench/diagnose_command.py --sizes 10000 --pairs 3
    .venv/bin/python bench/diagnose_command.py --sizes 10000 --figures none   # the command without its figures
    .venv/bin/python bench/diagnose_command.py --update-results       # bench/results/, a section of performance.md
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from floors import interleaved, run_child
from machine_info import machine, results_doc, write_results
from output_paths import RESULTS_PAGES, add_update_results, results_dir

HERE = Path(__file__).resolve()
GOAL = 1.5
SECTION = "## `fbg-accel-calib diagnose` against the diagnosis alone"


def recording(n: int, folder: Path) -> Path:
    """The benchmark run of ``n`` samples as a calibration MCAP in ``folder`` (written once)."""
    path = folder / f"diagnose_{n}.mcap"
    if not path.exists():
        from bench_calibration import scenario

        from fbg_accel_calibration.io.mcap_writer import write_recording
        from fbg_accel_sim.board_physics import simulate_recording

        cfg, duration = scenario(n)
        write_recording(path, simulate_recording(cfg, seed=0, duration_s=duration), metadata={"sensor_id": "bench"})
    return path


def command_argv(path: Path, out: Path, figures: str = "report") -> list[str]:
    return [sys.executable, "-c", "import sys; from fbg_accel_calibration.commands.cli_main import main; sys.exit(main())",
            "diagnose", str(path), "--out", str(out / "report.md"), "--yaml", str(out / "cal.yaml"), "--force",
            "--no-progress", "--figures", figures]


def diagnosis_alone(path: str, exit_frozen: bool = False, lanes: int | None = None,
                    numpy_huge_pages: bool = False) -> None:
    """The floor (in its own process): read the recording and diagnose it as the command does, nothing written; with
    ``exit_frozen`` what is alive at the end frozen out of the interpreter's last collections, as the command does
    (``cli_main._freeze_at_exit``); ``lanes``: the searches side by side (None: the command's default);
    ``numpy_huge_pages``: numpy's huge-page advice left on (``bench/huge_pages.py``), the rest of the heap policy set."""
    from fbg_accel_calibration.diagnosis.diagnose import diagnose
    from fbg_accel_calibration.diagnosis.heap_policy import set_process_heap_policy, small_pages_for_arrays
    from fbg_accel_calibration.io.input_files import load_recording

    set_process_heap_policy()
    if numpy_huge_pages:
        small_pages_for_arrays(False)
    rec = load_recording([path], rate=None, temperature=None, g=None, namespace=None, topic=None)
    diagnose(rec, sensor_id="bench", lanes=lanes)
    if exit_frozen:
        import gc

        gc.freeze()


def breakdown(path: str, out: str, figures: str = "report") -> None:
    """CPU seconds of each stage of the command in this process, as JSON on stdout."""
    stages: dict[str, float] = {}
    t = time.process_time()

    def lap(name: str) -> None:
        nonlocal t
        now = time.process_time()
        stages[name] = round(now - t, 3)
        t = now

    from fbg_accel_calibration.diagnosis.diagnose import diagnose
    from fbg_accel_calibration.diagnosis.heap_policy import set_process_heap_policy
    from fbg_accel_calibration.io.input_files import load_recording

    set_process_heap_policy()
    lap("import the engine")
    rec = load_recording([path], rate=None, temperature=None, g=None, namespace=None, topic=None)
    lap("read the recording")
    res = diagnose(rec, sensor_id="bench")
    lap("diagnosis")
    from fbg_accel_calibration.reports import diagnose_report as report

    report.text(res)
    report.markdown(res)
    lap("report text and markdown")
    if figures != "none":  # as the command: matplotlib only for figures
        import matplotlib.backends.backend_agg
        import matplotlib.figure

        lap("import matplotlib")
        real = matplotlib.figure.Figure.savefig

        def timed(fig, name, *a, **kw):  # each figure: from the end of the previous one to its file written
            real(fig, name, *a, **kw)
            lap(f"figure {Path(name).name}")

        matplotlib.figure.Figure.savefig = timed
        report.write_plots(res, out, figures)
        lap("(between figures)")
    res.calibration.save(Path(out) / "cal.yaml")
    lap("YAML")
    print(json.dumps(stages))


def measure(n: int, pairs: int, folder: Path, figures: str = "report") -> dict:
    path = recording(n, folder)
    out = folder / f"out_{n}"
    out.mkdir(exist_ok=True)
    for old in out.glob("img/*.png"):  # a --dir kept from a run with other --figures
        old.unlink()
    floor = [sys.executable, str(HERE), "--diagnosis-alone", str(path)]
    project = command_argv(path, out, figures)
    run_child(project)  # page cache and .pyc files
    res = interleaved(floor, project, pairs)
    frozen = interleaved([*floor, "--exit-frozen"], project, pairs)  # the floor exiting as the command does
    res.update(floor_exit_frozen=frozen["floor"], cpu_ratio_exit_frozen=frozen["cpu_ratio"],
               cpu_ratio_exit_frozen_range=frozen["cpu_ratio_range"])
    proc = subprocess.run([sys.executable, str(HERE), "--breakdown", str(path), str(out), "--figures", figures],
                          capture_output=True, text=True, check=True)
    stages = json.loads(proc.stdout.strip().splitlines()[-1])
    res.update(samples=n, goal=GOAL, goal_met=res["cpu_ratio"] <= GOAL, breakdown_cpu_s=stages,
               figures=sorted(p.name for p in out.glob("img/*.png")))
    print(f"diagnose {n} samples: command CPU {res['project']['cpu_s']:.2f} s, diagnosis alone "
          f"{res['floor']['cpu_s']:.2f} s: {res['cpu_ratio']:.2f}x (range {res['cpu_ratio_range']}; goal <= {GOAL}x: "
          f"{'met' if res['goal_met'] else 'NOT met'}); against the diagnosis alone exiting as the command does "
          f"{res['floor_exit_frozen']['cpu_s']:.2f} s: {res['cpu_ratio_exit_frozen']:.2f}x", flush=True)
    print("  breakdown (CPU s): " + ", ".join(f"{k} {v}" for k, v in stages.items()), flush=True)
    return res


def section(doc: dict) -> str:
    m = doc["machine"]
    lines = [SECTION, "",
             f"Generated by `{doc['command']}` on {doc['date_utc']}. Machine: {m['cpu']}, {m['logical_cpus']} logical "
             f"CPUs; load average before {doc['load_average_before']}, after {m['load_average_1_5_15']}. Method: the "
             "docstring of `bench/diagnose_command.py` (the simulator's benchmark run as MCAP; CPU times of child "
             "processes, interleaved pairs, median of the per-pair ratios).", "",
             "| samples | command CPU | diagnosis alone CPU | ratio (range) | goal | diagnosis alone, exiting as the "
             "command (frozen) | ratio (range) |", "|---|---|---|---|---|---|---|"]
    for r in doc["sizes"]:
        lines.append(f"| {r['samples']:.0e} | {r['project']['cpu_s']:.2f} s | {r['floor']['cpu_s']:.2f} s | "
                     f"{r['cpu_ratio']:.2f}x ({r['cpu_ratio_range'][0]:.2f}-{r['cpu_ratio_range'][1]:.2f}) | "
                     f"<= {GOAL}x: {'met' if r['goal_met'] else 'not met'} | {r['floor_exit_frozen']['cpu_s']:.2f} s | "
                     f"{r['cpu_ratio_exit_frozen']:.2f}x ({r['cpu_ratio_exit_frozen_range'][0]:.2f}-"
                     f"{r['cpu_ratio_exit_frozen_range'][1]:.2f}) |")
    lines += ["", "Where the command's time goes (CPU seconds of one process, `--breakdown`):", "",
              "| stage | " + " | ".join(f"{r['samples']:.0e}" for r in doc["sizes"]) + " |",
              "|---|" + "---|" * len(doc["sizes"])]
    stages = list(dict.fromkeys(k for r in doc["sizes"] for k in r["breakdown_cpu_s"]))
    for k in stages:
        lines.append(f"| {k} | " + " | ".join(str(r["breakdown_cpu_s"].get(k, "-")) for r in doc["sizes"]) + " |")
    return "\n".join(lines) + "\n"


def with_section(page: str, text: str) -> str:
    """``page`` with its section ``SECTION`` replaced by ``text`` (up to the next heading of its level), or added."""
    pattern = re.compile(re.escape(SECTION) + r"\n.*?(?=^## |\Z)", re.S | re.M)
    if pattern.search(page):
        return pattern.sub(lambda _: text + "\n", page, count=1).rstrip("\n") + "\n"
    return page.rstrip("\n") + "\n\n" + text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000], help="samples (default %(default)s)")
    ap.add_argument("--pairs", type=int, default=5, help="interleaved pairs per size (default %(default)s)")
    ap.add_argument("--dir", type=Path, default=None, help="keep the recordings here (default: a temporary directory)")
    ap.add_argument("--output", type=Path, default=None, help="results JSON (default: scratch diagnose_command.json)")
    ap.add_argument("--figures", choices=("report", "all", "none"), default="report",
                    help="the command's --figures (default %(default)s, the command's own)")
    ap.add_argument("--diagnosis-alone", metavar="MCAP", help=argparse.SUPPRESS)
    ap.add_argument("--exit-frozen", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--numpy-huge-pages", action="store_true", help=argparse.SUPPRESS)  # of --diagnosis-alone
    ap.add_argument("--lanes", type=int, default=None, help=argparse.SUPPRESS)  # of --diagnosis-alone
    ap.add_argument("--breakdown", nargs=2, metavar=("MCAP", "DIR"), help=argparse.SUPPRESS)
    add_update_results(ap)
    args = ap.parse_args(argv)
    if args.diagnosis_alone:
        diagnosis_alone(args.diagnosis_alone, args.exit_frozen, args.lanes, args.numpy_huge_pages)
        return 0
    if args.breakdown:
        breakdown(*args.breakdown, args.figures)
        return 0
    load_before = [round(v, 2) for v in os.getloadavg()]
    doc = results_doc("diagnose_command.py", argv, benchmark="diagnose_command", load_average_before=load_before)
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.dir or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        doc["sizes"] = [measure(n, args.pairs, folder, args.figures) for n in args.sizes]
    doc["machine"] = machine()  # the load average after
    out = args.output or results_dir(args.update_results) / "diagnose_command.json"
    write_results(out, doc)
    md = RESULTS_PAGES / "performance.md" if args.update_results else out.with_suffix(".md")
    md.write_text(with_section(md.read_text(encoding="utf-8") if md.exists() else "", section(doc)), encoding="utf-8")
    print(f"page written to {md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
