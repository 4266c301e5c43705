"""Benchmark: ``fbg-accel-calib fit`` of 1,000,000 samples streamed from MCAP files (issue 3).

Not a test (never run by pytest). Writes the synthetic campaign of ``bench_fit.make_recording``
(24 poses x 4 chamber temperatures, moves between poses) as four MCAP files, one per temperature,
through ``write_recording`` (``RecordingWriter``: ROS 2 profile, 32 KiB zstd chunks, as the node), then
runs each mode in a fresh Python process, so that its resident-memory figure is its own:
``rss_peak_delta_mb`` = peak of the current resident set (``/proc/self/statm``, sampled every 5 ms
while the fit runs) minus the resident set after imports (``ru_maxrss`` is reported too, but it
includes the transient peak of the imports):

* ``stream_n3``: ``fbg-accel-calib fit FILES --degree 3 --max-degree 3`` (streaming, the default);
* ``memory_n3``: the same with ``--in-memory`` (``read_recording`` of every sample, then the fit);
* ``stream_default``: ``fbg-accel-calib fit FILES`` (streaming, degree chosen by cross-validation 0..6).

For ``stream_n3`` and ``memory_n3`` a second process measures the peak of ``tracemalloc`` (numpy
arrays are traced; tracing slows the run, so it is not timed). The YAMLs of ``stream_n3`` and
``memory_n3`` are compared, and a second, larger campaign (``--check-samples``, default 2,000,000) is
fitted by streaming to show that the traced peak does not depend on the number of samples. Writes
bench/results/fit_stream.json.

    .venv/bin/python bench/bench_fit_stream.py [--samples 1000000] [--dir DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from machine_info import machine
from output_paths import add_update_results, results_dir

HERE = Path(__file__).resolve().parent
MODES = {
    "stream_n3": ["--degree", "3", "--max-degree", "3"],
    "memory_n3": ["--degree", "3", "--max-degree", "3", "--in-memory"],
    "stream_default": [],
}


def child(mode: str, files: list[str], out: str, trace: bool) -> None:
    """Run one mode in this (fresh) process and print its figures as JSON on the last stdout line."""
    import contextlib
    import io
    import tracemalloc

    import fbg_accel_calibration.fit.model_selection
    import fbg_accel_calibration.fit.thermal_fit
    import fbg_accel_calibration.io.csv_import
    import fbg_accel_calibration.io.mcap_reader
    import fbg_accel_calibration.io.mcap_writer  # noqa: F401  (imports outside the measured region)
    from fbg_accel_calibration.commands.cli import main as cli_main

    page = os.sysconf("SC_PAGE_SIZE")

    def rss_bytes() -> int:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * page

    base = rss_bytes()
    peak_rss = [base]
    stop = threading.Event()

    def sample() -> None:  # current resident set every 5 ms (ru_maxrss also holds the import-time peak)
        while not stop.wait(0.005):
            peak_rss[0] = max(peak_rss[0], rss_bytes())

    argv = ["fit", *files, "-o", out, *MODES[mode]]
    if trace:
        tracemalloc.start()
    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        rc = cli_main(argv)
    seconds = time.perf_counter() - t0
    stop.set()
    sampler.join()
    peak = tracemalloc.get_traced_memory()[1] if trace else None
    print(json.dumps({"rc": rc, "seconds": seconds, "rss_peak_delta_mb": (peak_rss[0] - base) / 1e6,
                      "rss_before_mb": base / 1e6,
                      "ru_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                      "peak_traced_mb": None if peak is None else peak / 1e6}))


def run_child(mode: str, files: list[str], out: Path, trace: bool) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", mode, "--out", str(out), *(["--trace"] if trace else []),
           *files]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{mode} failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--check-samples", type=int, default=2_000_000,
                    help="second campaign (2x larger) fitted by streaming: its peak memory must be the same (0: skip)")
    ap.add_argument("--dir", type=Path, default=None, help="keep the MCAP files here (default: a temporary directory)")
    ap.add_argument("--out", type=Path, help="output file (default: fit_stream.json in the scratch or results directory)")
    add_update_results(ap)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--trace", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("files", nargs="*", help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.out = args.out or results_dir(args.update_results) / "fit_stream.json"
    if args.child:
        child(args.child, args.files, str(args.out), args.trace)
        return

    sys.path.insert(0, str(HERE))
    from bench_fit import make_recording

    from fbg_accel_calibration.fit.static_detector import BLOCK_ROWS
    from fbg_accel_calibration.fit.thermal_fit import DEFAULT_CHUNK, n_params
    from fbg_accel_calibration.io.mcap_writer import write_recording
    from fbg_accel_driver.thermal_model import ThermalCalibration

    tmp = tempfile.TemporaryDirectory() if args.dir is None else None
    folder = Path(tmp.name) if tmp else args.dir
    folder.mkdir(parents=True, exist_ok=True)

    def write_campaign(n: int, prefix: str) -> list[str]:
        rec, _ = make_recording(n)
        files = []
        for level in range(int(rec.run_id.max()) + 1):
            part = rec.select(rec.run_id == level)
            part.run_id[:] = 0
            path = folder / f"{prefix}_level{level}.mcap"
            write_recording(path, part, {"sensor_id": "bench"})
            files.append(str(path))
        return files

    t0 = time.perf_counter()
    files = write_campaign(args.samples, "bench")
    write_s = time.perf_counter() - t0
    results = {}
    for mode in MODES:
        results[mode] = run_child(mode, files, folder / f"{mode}.yaml", trace=False)
        print(mode, results[mode], flush=True)
    for mode in ("stream_n3", "memory_n3"):
        results[mode]["peak_traced_mb"] = run_child(mode, files, folder / f"{mode}_traced.yaml", trace=True)["peak_traced_mb"]
    memory_check = None
    if args.check_samples:
        small = write_campaign(args.check_samples, "check")
        r = run_child("stream_n3", small, folder / "check_traced.yaml", trace=True)
        memory_check = {"samples": args.check_samples, "stream_n3_peak_traced_mb": round(r["peak_traced_mb"], 2),
                        "same_at_samples": args.samples, "stream_n3_peak_traced_mb_there": round(
                            results["stream_n3"]["peak_traced_mb"], 2)}
    streamed = ThermalCalibration.load(folder / "stream_n3.yaml")
    in_memory = ThermalCalibration.load(folder / "memory_n3.yaml")
    equality = {
        "max_abs_diff_M": float(np.abs(streamed.M - in_memory.M).max()),
        "max_abs_M": float(np.abs(in_memory.M).max()),
        "max_abs_diff_b_mps2": float(np.abs(streamed.b - in_memory.b).max()),
        "max_rel_diff_noise": float(np.abs(streamed.noise_sigma_mps2 / in_memory.noise_sigma_mps2 - 1.0).max()),
        "same_samples_used": streamed.fit["samples_used"] == in_memory.fit["samples_used"],
        "same_temperature_range": streamed.temperature_range_c == in_memory.temperature_range_c,
    }
    p3, p6 = n_params(3), n_params(6)
    out = {
        "samples": args.samples, "files": len(files),
        "file_mb": round(sum(os.path.getsize(f) for f in files) / 1e6, 1), "write_s": round(write_s, 1),
        "block_rows": BLOCK_ROWS, "chunk_rows": DEFAULT_CHUNK,
        "design_matrix_chunk_mb": {"n3": round(DEFAULT_CHUNK * p3 * 8 / 1e6, 1), "n6": round(DEFAULT_CHUNK * p6 * 8 / 1e6, 1)},
        "full_design_matrix_would_be_mb": {"n3": round(args.samples * p3 * 8 / 1e6, 1),
                                           "n6": round(args.samples * p6 * 8 / 1e6, 1)},
        "commands": {m: "fbg-accel-calib fit bench_level{0..3}.mcap -o cal.yaml " + " ".join(a) for m, a in MODES.items()},
        "modes": {m: {k: (round(v, 2) if isinstance(v, float) else v) for k, v in r.items()} for m, r in results.items()},
        "stream_vs_memory_n3": equality,
        "stream_memory_independent_of_samples": memory_check,
        "fit_check": {"samples_used": streamed.fit["samples_used"],
                      "rmse_mps2": [round(v, 5) for v in streamed.fit["rmse_mps2"]]},
        "machine": machine(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))
    if tmp:
        tmp.cleanup()


if __name__ == "__main__":
    main()
