#!/usr/bin/env python3
"""Calibration benchmark: fit and diagnose on 10^6 simulated samples, MCAP write rate of the recorder.

Not a test. Steps (wall clock, one process, numpy may use both cores for its BLAS calls):

* ``simulate``: ``simulate_recording`` of the board simulator (default physics: every nominal effect
  on) over a multi-temperature calibration run: the measured run's table grid (theta 0..360 and psi
  0..330 degrees in 60-degree steps, 3 s dwell, 1 s moves, looped) at 100 Hz while the chamber holds
  four levels 16 / 25 / 35 / 45 degC (``thermal.optics_time_constant_s`` shortened to 60 s so the
  levels settle within the run), ``--samples`` samples (default 10^6 = 2.8 h of board time);
* ``fit``: ``fit_thermal(rec, degree)`` (static detector, temperature levels, streamed least
  squares, RMSE, noise floor): what ``fbg-accel-calib fit`` does after reading; best of ``--repeats``;
* ``diagnose``: ``diagnose(rec)`` (degree selection, cross-validated effect library, residual
  structure): what the diagnosis command does after reading; once; then, timed apart
  (``report_seconds``), the Markdown report with its plots that the command writes;
* ``mcap_write``: the recorder's ``RecordingWriter`` (via ``write_recording``: one ``write_raw`` per
  sample plus pose and reference-gravity events at pose changes, zstd chunks, as the calibration node
  writes them) for ``--mcap-samples`` samples (default 10^6); messages/s and MB/s of file written,
  and the ratio to the 3413 messages/s the driver publishes on ``imu/raw`` at the 921600-baud link
  limit; the file is read back with ``read_recording`` and the sample count checked.

Peak resident memory (ru_maxrss) after each step is reported. ``--profile-diagnose [TOP]`` runs the
diagnosis under cProfile and stores its top functions (15 unless TOP; where the diagnosis spends its time). cProfile sees the
calling thread only: with the searches side by side (two lanes, the default at 10^6 samples) their own time is not
in it, only the wait for them (``Lanes.map``); ``--lanes 1`` profiles them too.
``--memory-diagnose`` runs it under tracemalloc and stores, for the moment its traced memory peaked,
the allocation sites holding the most (what the diagnosis holds at its peak; slower, time not comparable).
Writes bench/results/calibration.json.

    .venv/bin/python bench/bench_calibration.py [--samples 1000000] [--mcap-samples 1000000]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import resource
import sys
import tempfile
import threading
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from machine_info import results_doc, write_results  # noqa: E402
from output_paths import add_update_results, results_dir  # noqa: E402

from fbg_accel_calibration.diagnosis.diagnose import diagnose  # noqa: E402
from fbg_accel_calibration.diagnosis.search import SEARCH_ROWS  # noqa: E402
from fbg_accel_calibration.fit.fit_pipeline import fit_thermal  # noqa: E402
from fbg_accel_calibration.io.mcap_reader import read_recording  # noqa: E402
from fbg_accel_calibration.io.mcap_writer import write_recording  # noqa: E402
from fbg_accel_calibration.reports.diagnose_report import write_report  # noqa: E402
from fbg_accel_driver.frame_codec import link_frame_rate_limit  # noqa: E402
from fbg_accel_sim.board_physics import simulate_recording  # noqa: E402
from fbg_accel_sim.sim_config import SimConfig  # noqa: E402

RATE_HZ = 100.0
LEVELS_C = (16.0, 25.0, 35.0, 45.0)


def scenario(n_samples: int) -> tuple[SimConfig, float]:
    """Simulator config of the benchmark run and its duration (s) for ``n_samples`` samples."""
    cfg = SimConfig.default()
    ppm = float(cfg.get("board.clock_ppm"))
    duration = n_samples / (RATE_HZ * (1.0 + ppm * 1e-6))
    hold = duration / len(LEVELS_C)
    profile: list[dict] = []
    for i, level in enumerate(LEVELS_C):
        if i:
            profile.append({"ramp_to_c": level, "duration_s": 60.0})
        profile.append({"hold_s": hold - (60.0 if i else 0.0)})
    cfg = cfg.with_overrides({
        "scenario.rate_hz": RATE_HZ,
        "scenario.poses.mode": "grid", "scenario.poses.dwell_s": 3.0, "scenario.poses.move_s": 1.0,
        "scenario.poses.grid.theta_step_deg": 60.0, "scenario.poses.grid.psi_step_deg": 60.0,
        "scenario.poses.repeat": 0,
        "scenario.temperature.initial_c": LEVELS_C[0], "scenario.temperature.profile": profile,
        "thermal.optics_time_constant_s": 60.0,
    })
    return cfg, duration


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def profile_top(profiler: cProfile.Profile, n: int = 15) -> dict[str, list[dict]]:
    """The ``n`` functions with the most cumulative and the most own time (s, calls), as plain rows."""
    st = pstats.Stats(profiler)
    rows = [{"function": f"{Path(file).name}:{line}({name})", "calls": nc, "own_s": round(tt, 2), "cumulative_s": round(ct, 2)}
            for (file, line, name), (_, nc, tt, ct, _) in st.stats.items()]
    return {"by_cumulative": sorted(rows, key=lambda r: -r["cumulative_s"])[:n],
            "by_own": sorted(rows, key=lambda r: -r["own_s"])[:n]}


def memory_at_peak(run: Callable[[], Any], n: int = 12) -> tuple[Any, dict[str, Any]]:
    """``run()`` under tracemalloc; (its result, {peak MiB, the ``n`` allocation sites holding the most at the
    peak, each with the innermost project frames}). The peak is caught by a snapshot whenever the traced total
    has grown by 2 % (sampled every 0.2 s), so it is the peak to within that."""
    best: list[Any] = [0, None]
    done = threading.Event()

    def watch() -> None:
        while not done.wait(0.2):
            cur, _ = tracemalloc.get_traced_memory()
            if cur > best[0] * 1.02:
                best[0], best[1] = cur, tracemalloc.take_snapshot()

    tracemalloc.start(10)
    th = threading.Thread(target=watch, daemon=True)
    th.start()
    try:
        out = run()
    finally:
        done.set()
        th.join()
        tracemalloc.stop()
    sites = []
    for st in (best[1].statistics("traceback") if best[1] is not None else [])[:n]:
        frames = [f"{Path(f.filename).name}:{f.lineno}" for f in st.traceback if "fbg_accel" in f.filename]
        sites.append({"mib": round(st.size / 2**20, 1), "blocks": st.count, "frames": frames[-4:]})
    return out, {"traced_peak_mib": round(best[0] / 2**20, 1), "top_sites": sites}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=1_000_000, help="samples of the fit/diagnose recording (default 10^6)")
    ap.add_argument("--mcap-samples", type=int, default=1_000_000, help="samples written to MCAP (default 10^6; 0: skip)")
    ap.add_argument("--degree", type=int, default=2, help="polynomial degree of the timed fit (default 2, as calibration_sim)")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats of the fit (best is reported)")
    ap.add_argument("--skip-diagnose", action="store_true", help="do not run the diagnosis step")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--search-rows", type=int, default=SEARCH_ROWS,
                    help=f"fitted samples above which diagnose searches on every k-th one (default {SEARCH_ROWS}, the "
                         "library's): to measure what a smaller search set saves and what it changes")
    ap.add_argument("--lanes", type=int, default=None,
                    help="searches of the diagnosis side by side (default: diagnose's own choice, one per core up to two)")
    ap.add_argument("--profile-diagnose", type=int, nargs="?", const=15, default=None, metavar="TOP",
                    help="run the diagnosis under cProfile; its TOP (default 15) functions by cumulative and by own "
                         "time go into the JSON")
    ap.add_argument("--memory-diagnose", action="store_true",
                    help="run the diagnosis under tracemalloc; what it holds at its peak goes into the JSON")
    ap.add_argument("--output", type=Path, help="output file (default: calibration.json in the scratch or results directory)")
    add_update_results(ap)
    args = ap.parse_args(argv)
    args.output = args.output or results_dir(args.update_results) / "calibration.json"
    from fbg_accel_calibration.diagnosis.heap_policy import set_process_heap_policy

    set_process_heap_policy()  # as the diagnose command sets it (its entry point's policy)

    steps: dict[str, dict] = {}
    cfg, duration = scenario(args.samples)
    t0 = time.perf_counter()
    rec = simulate_recording(cfg, seed=args.seed, duration_s=duration)
    steps["simulate"] = {"seconds": time.perf_counter() - t0, "samples": len(rec), "board_hours": duration / 3600,
                         "peak_rss_mib": peak_rss_mib()}
    print(f"simulate: {len(rec)} samples in {steps['simulate']['seconds']:.1f} s", flush=True)

    times = []
    cal = None
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        cal = fit_thermal(rec, args.degree)
        times.append(time.perf_counter() - t0)
    assert cal is not None
    steps["fit"] = {"degree": args.degree, "seconds_best": min(times), "seconds_all": times,
                    "samples_per_s": len(rec) / min(times), "samples_used": cal.fit.get("samples_used"),
                    "rmse_mps2": [float(v) for v in cal.fit.get("rmse_mps2", [])], "peak_rss_mib": peak_rss_mib()}
    print(f"fit (degree {args.degree}): best {min(times):.2f} s of {args.repeats}", flush=True)

    if not args.skip_diagnose:
        profiler = cProfile.Profile() if args.profile_diagnose else None
        t0, use0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
        if profiler is not None:
            profiler.enable()
        memory = None
        if args.memory_diagnose:
            res, memory = memory_at_peak(lambda: diagnose(rec, search_rows=args.search_rows, lanes=args.lanes))
        else:
            res = diagnose(rec, search_rows=args.search_rows, lanes=args.lanes)
        if profiler is not None:
            profiler.disable()
        sec, use1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF)
        steps["diagnose"] = {"seconds": sec, "samples_per_s": len(rec) / sec, "search_rows": args.search_rows,
                             "lanes": args.lanes, "user_seconds": use1.ru_utime - use0.ru_utime,
                             "system_seconds": use1.ru_stime - use0.ru_stime,  # mostly page faults (heap_policy)
                             "page_faults": use1.ru_minflt - use0.ru_minflt,
                             "degree": res.degree,
                             "ranked": [c.name for c in res.ranked][:5], "added": [a[0] for a in res.added],
                             "noise_floor_mps2": [float(v) for v in res.noise_floor], "peak_rss_mib": peak_rss_mib()}
        if profiler is not None:
            steps["diagnose"]["profile_top"] = profile_top(profiler, args.profile_diagnose)
        if memory is not None:
            steps["diagnose"]["memory_at_peak"] = memory
        with tempfile.TemporaryDirectory(prefix="bench_report_") as tmp:
            t0 = time.perf_counter()
            write_report(res, Path(tmp) / "diagnosis.md")  # what the command writes after the diagnosis
            steps["diagnose"]["report_seconds"] = time.perf_counter() - t0
        print(f"diagnose: {sec:.1f} s, added {steps['diagnose']['added']}; report and plots "
              f"{steps['diagnose']['report_seconds']:.1f} s", flush=True)

    link_msgs = link_frame_rate_limit(921600)
    if args.mcap_samples:
        part = rec.select(np.arange(len(rec)) < args.mcap_samples)
        with tempfile.TemporaryDirectory(prefix="bench_mcap_") as tmp:
            path = Path(tmp) / "bench.mcap"
            t0 = time.perf_counter()
            n_msgs = write_recording(path, part, metadata={"sensor_id": "bench"})
            sec = time.perf_counter() - t0
            size = path.stat().st_size
            t0 = time.perf_counter()
            back = read_recording(path)
            read_s = time.perf_counter() - t0
            if len(back) != len(part):
                raise RuntimeError(f"MCAP read back {len(back)} samples, wrote {len(part)}")
        steps["mcap_write"] = {"samples": len(part), "messages": n_msgs, "seconds": sec, "messages_per_s": n_msgs / sec,
                               "file_mb": size / 1e6, "mb_per_s": size / 1e6 / sec, "bytes_per_message": size / n_msgs,
                               "compression": "zstd (RecordingWriter default)",
                               "ratio_to_imu_raw_rate_at_link_limit": (n_msgs / sec) / link_msgs,
                               "read_back_seconds": read_s, "read_back_samples": len(back), "peak_rss_mib": peak_rss_mib()}
        print(f"mcap write: {n_msgs} messages in {sec:.1f} s = {n_msgs / sec:.0f} msg/s, {size / 1e6 / sec:.2f} MB/s", flush=True)

    write_results(args.output, results_doc(
        "bench_calibration.py", argv, "calibration: fit and diagnose on simulated samples, MCAP write rate of RecordingWriter",
        scenario={"rate_hz": RATE_HZ, "levels_c": list(LEVELS_C), "poses": "grid 60 deg, dwell 3 s, move 1 s, looped",
                  "seed": args.seed},
        imu_raw_messages_per_s_at_link_limit=link_msgs, steps=steps))
    return 0


if __name__ == "__main__":
    sys.exit(main())
