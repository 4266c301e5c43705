"""Benchmark: fit eq. 28 at n = 3 to 1,000,000 samples (issue 3: < 2 s on the 2-core machine).

Not a test. Generates a recording that looks like a multi-temperature calibration (24 poses at
4 chamber temperatures, Psi noise like the sensor's, moves between poses with a leading table
reading) with numpy, then times

* ``full``: ``fit_thermal(rec, 3)`` -- static detector, temperature levels, streamed normal
  equations, solve, RMSE and noise floor: what ``fbg-accel-calib fit --degree 3`` does after reading;
* ``core``: the same with the static mask given (the streamed least squares alone);
* ``select``: ``select_degree(rec, 6)`` -- cross-validation over degrees 0..6 by pose and level;
* ``mcap_read`` (``--mcap-samples``, default 200,000): ``read_recording`` of an MCAP written by
  ``RecordingWriter`` -- the Python ``mcap`` stream reader is the bottleneck of a fit from files, so
  its throughput is reported per sample.

Peak memory is measured with ``tracemalloc`` (numpy allocations are traced) in a separate run of
each step, so tracing does not slow the timed run. Writes bench/results/fit.json.

    .venv/bin/python bench/bench_fit.py [--samples 1000000]
"""

from __future__ import annotations

import argparse
import json
import time
import tracemalloc
from pathlib import Path

import numpy as np
from machine_info import machine
from output_paths import add_update_results, results_dir

from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_calibration.fit.model_selection import select_degree
from fbg_accel_calibration.fit.thermal_fit import n_params
from fbg_accel_calibration.io.mcap_reader import read_recording
from fbg_accel_calibration.io.mcap_writer import write_recording
from fbg_accel_calibration.io.recording import Recording

G = 9.80665


def make_recording(n_samples: int, degree: int = 3, seed: int = 0) -> tuple[Recording, np.ndarray]:
    """Synthetic calibration data: (recording, boolean mask of the static samples)."""
    rng = np.random.default_rng(seed)
    levels = np.array([10.0, 20.0, 30.0, 45.0])
    poses = rng.normal(size=(24, 3))
    poses = G * poses / np.linalg.norm(poses, axis=1)[:, None]
    M = np.array([np.diag([80.0, 78.0, 107.0])] + [rng.normal(0, 1.0, (3, 3)) / (k + 1) for k in range(degree)])
    b = np.array([[-101.0, 153.0, -137.0]] + [rng.normal(0, 1.0, 3) / (k + 1) for k in range(degree)])
    n_cells = len(levels) * len(poses)
    per = n_samples // n_cells
    move = 20
    pose = np.tile(np.repeat(np.arange(len(poses)), per), len(levels))[:n_samples]
    level = np.repeat(np.arange(len(levels)), per * len(poses))[:n_samples]
    pad = n_samples - len(pose)
    pose = np.r_[pose, np.full(pad, pose[-1])]
    level = np.r_[level, np.full(pad, level[-1])]
    temp = levels[level] + rng.normal(0.0, 0.05, n_samples)
    tau = (temp - 27.5) / 17.5
    Mt = np.einsum("nk,kij->nij", tau[:, None] ** np.arange(degree + 1), M)
    bt = (tau[:, None] ** np.arange(degree + 1)) @ b
    gref = poses[pose]
    psi = np.linalg.solve(Mt, (gref - bt)[:, :, None])[:, :, 0]
    # the first `move` samples of each pose: the sensor still ramps from the previous pose
    start = np.flatnonzero(np.r_[True, (np.diff(pose) != 0) | (np.diff(level) != 0)])
    moving = np.zeros(n_samples, bool)
    for s in start[1:]:
        frac = (np.arange(1, move + 1) / (move + 1))[:, None]
        psi[s:s + move] = psi[s - 1] + frac * (psi[s + move] - psi[s - 1])
        moving[s:s + move] = True
    psi += rng.normal(0.0, 3e-4, psi.shape)
    ref = np.full(n_samples, 880.0) + rng.normal(0.0, 1.0, n_samples)
    rec = Recording(np.arange(n_samples) * 0.01, ref, psi * ref[:, None], temp, gref, pose, level)
    return rec, ~moving


def timed(fn, repeat: int = 3) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def peak_mb(fn) -> float:
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--mcap-samples", type=int, default=200_000, help="samples for the MCAP read step (0: skip)")
    ap.add_argument("--out", type=Path, help="output file (default: fit.json in the scratch or results directory)")
    add_update_results(ap)
    args = ap.parse_args()
    args.out = args.out or results_dir(args.update_results) / "fit.json"
    rec, static = make_recording(args.samples)
    data_mb = sum(a.nbytes for a in (rec.t_s, rec.ref, rec.xyz, rec.temp_c, rec.gref_mps2, rec.pose_id, rec.run_id)) / 1e6
    full_design_mb = args.samples * n_params(3) * 8 / 1e6
    steps = {
        "full": lambda: fit_thermal(rec, 3),
        "core": lambda: fit_thermal(rec, 3, usable=static),
        "select": lambda: select_degree(rec, 6),
    }
    results = {}
    for name, fn in steps.items():
        results[name] = {"seconds_best_of_3": round(timed(fn), 3), "peak_traced_mb": round(peak_mb(fn), 1)}
    mcap_info = None
    if args.mcap_samples:
        import tempfile

        small = rec.select(np.arange(len(rec)) < args.mcap_samples)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "bench.mcap"
            t0 = time.perf_counter()
            write_recording(path, small)
            t_write = time.perf_counter() - t0
            t_read = timed(lambda: read_recording(path), repeat=2)
            mcap_info = {"samples": len(small), "file_mb": round(path.stat().st_size / 1e6, 1),
                         "write_s": round(t_write, 2), "read_s": round(t_read, 2),
                         "read_us_per_sample": round(1e6 * t_read / len(small), 2)}
    cal = fit_thermal(rec, 3)
    out = {
        "samples": args.samples, "degree": 3, "regressors_per_axis": n_params(3),
        "recording_arrays_mb": round(data_mb, 1), "full_design_matrix_would_be_mb": round(full_design_mb, 1),
        "chunk_rows": 65536, "steps": results, "mcap_read": mcap_info,
        "fit_check": {"samples_used": cal.fit["samples_used"], "excluded_in_motion": cal.fit["samples_excluded_in_motion"],
                      "rmse_mps2": [round(v, 5) for v in cal.fit["rmse_mps2"]]},
        "target": "full < 2 s (issue 3)", "machine": machine(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
