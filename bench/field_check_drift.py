"""Does ``fbg-accel-calib field-check`` find a drift within its uncertainty, and stay quiet without one? (simulator)

Not a test. For each seed a calibration is fitted on a simulated campaign as ``fbg-accel-calib fit`` does
(``bench/nees_probe.py`` fitted_calibration: coefficient covariance and slow error), then the simulator records the
sensor still at ``--orientations`` orientations (the first of: z up, z down, x and y both ways, two oblique; 20 s each,
at 24 degC, a new seed), once undrifted and once with a bias step of ``--drift`` m/s^2 on one axis (x, y, z in turn;
``effects.bias_step``, before the recording starts). The still periods are found by the signal alone and the drift
estimated as the command does (``field_check.still_periods``, ``estimate``, ``drifted``), with the calibration's slow
error and, for comparison, without it (noise and the Birge ratio only). Per case: the normalised error z of the six
parameters against the truth (the injected bias on its axis, 0 elsewhere), the fraction within 2 sigma, and the
fraction of recordings with a warning (beyond ``DRIFT_SIGMAS``).

    .venv/bin/python bench/field_check_drift.py --seeds 24 --output /tmp/field_check.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine_info import machine
from nees_probe import fitted_calibration
from output_paths import add_update_results, results_dir

from fbg_accel_calibration.fit.field_check import DRIFT_SIGMAS, drifted, estimate, still_periods
from fbg_accel_calibration.fit.static_detector import DEFAULT_MIN_INTERVAL, DEFAULT_WINDOW, calibration_samples
from fbg_accel_sim.board_physics import SimConfig, simulate_recording

ORIENTATIONS = [[0.0, 0.0], [0.0, 180.0], [0.0, 90.0], [180.0, 90.0], [90.0, 90.0], [270.0, 90.0], [45.0, 45.0],
                [200.0, 120.0]]
G_SIM = 9.80665  # the simulator's scenario.gravity_mps2


def check(cal: Any, seed: int, n_orient: int, drift: np.ndarray) -> dict[str, Any]:
    """z of the six parameters and the warning, with and without the calibration's slow error."""
    over = {"scenario.poses.mode": "list", "scenario.poses.list": ORIENTATIONS[:n_orient], "scenario.poses.dwell_s": 20.0,
            "scenario.poses.move_s": 4.0, "scenario.poses.repeat": 1, "scenario.temperature.initial_c": 24.0}
    if np.any(drift):
        over.update({"effects.bias_step.scale": 1.0, "effects.bias_step.at_s": 0.0,
                     "effects.bias_step.amplitude_mps2": drift.tolist()})
    rec = simulate_recording(SimConfig.default().with_overrides(over), seed=seed)
    periods = still_periods(rec, cal, calibration_samples(rec, DEFAULT_WINDOW, DEFAULT_MIN_INTERVAL)[1])
    truth = np.r_[drift, np.zeros(3)]
    out: dict[str, Any] = {"periods": len(periods.mean)}
    for label, slow in (("with", cal.slow_error.published_matrix), ("without", None)):
        fc = estimate(periods, G_SIM, slow_error=slow)
        values = np.r_[fc.bias, fc.scale]
        out[label] = {"z": np.where(fc.identified, (values - truth) / np.where(fc.sigma > 0, fc.sigma, np.inf),
                                    np.nan).tolist(),
                      "sigma": fc.sigma.tolist(), "warning": drifted(fc), "identified": fc.identified.tolist()}
    return out


def summary(runs: list[dict[str, Any]], label: str) -> dict[str, Any]:
    z = np.array([r[label]["z"] for r in runs], float)
    ok = np.isfinite(z)
    return {"z_rms_per_parameter": np.round(np.sqrt(np.nanmean(z**2, axis=0)), 2).tolist(),
            "within_2_sigma": round(float((np.abs(z[ok]) < 2.0).mean()), 3),
            "within_3_sigma": round(float((np.abs(z[ok]) < 3.0).mean()), 3),
            "warned_fraction": round(float(np.mean([bool(r[label]["warning"]) for r in runs])), 3),
            "median_sigma_bias_mps2": np.round(np.median([r[label]["sigma"][:3] for r in runs], axis=0), 4).tolist()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=24)
    ap.add_argument("--orientations", type=int, default=8, help="still orientations per recording (6..8)")
    ap.add_argument("--drift", type=float, default=0.2, help="bias step (m/s^2) on x, y, z in turn")
    ap.add_argument("--output", type=Path, default=None, help="JSON file (default: field_check.json in the scratch "
                    "directory, or in bench/results/ with --update-results)")
    add_update_results(ap)
    args = ap.parse_args(argv)
    if not 6 <= args.orientations <= len(ORIENTATIONS):
        ap.error(f"--orientations must be in 6..{len(ORIENTATIONS)}")
    started = time.perf_counter()
    quiet, moved = [], []
    for s in range(args.seeds):
        cal = fitted_calibration(100 + s)
        drift = np.zeros(3)
        drift[s % 3] = args.drift
        quiet.append(check(cal, 3000 + s, args.orientations, np.zeros(3)))
        moved.append(check(cal, 4000 + s, args.orientations, drift))
        print(f"seed {s}: undrifted warns {quiet[-1]['with']['warning']}; drift on {'xyz'[s % 3]}: z "
              f"{moved[-1]['with']['z'][s % 3]:+.2f}, warns {moved[-1]['with']['warning']}", flush=True)
    result = {
        "command": "python bench/field_check_drift.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": machine(), "seconds": round(time.perf_counter() - started, 1), "seeds": args.seeds,
        "orientations": ORIENTATIONS[:args.orientations], "drift_mps2": args.drift, "drift_sigmas": DRIFT_SIGMAS,
        "undrifted": {label: summary(quiet, label) for label in ("with", "without")},
        "drifted": {label: summary(moved, label) for label in ("with", "without")},
        "drifted_axis_z_with": [round(r["with"]["z"][s % 3], 2) for s, r in enumerate(moved)],
    }
    path = args.output or results_dir(args.update_results) / "field_check.json"
    path.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    print(json.dumps({k: v for k, v in result.items() if k != "machine"}, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
