"""False alarms and detection of the driver's live gravity check (``fbg_accel_driver.gravity_check``) on the simulator.

Not a test. Pure core, no ROS, no wire: for each seed the simulator records a still sensor (one orientation per seed,
cycling through the twelve of ``bench/nees_probe.py``) for ``--hours``; the shipped calibration converts its counts (eq.
28, as the driver does) and every sample goes through ``GravityCheck.update`` in order, as ``DriverCore`` feeds it.

* **false alarms**: the sensor has not drifted; every test (one per ``period_s`` of stillness) that fails is a false
  alarm. Reported per test, per hour and per run (the fraction of seeds with at least one), at the default tolerance and
  at the others of ``--tolerances`` (from the same tests: |discrepancy| > tolerance + k sigma);
* **detection**: the same sensor with a bias step of ``--drift`` m/s^2 on z (``effects.bias_step``) before it stands
  still, z up or down (the drift along gravity); detected when a test fails within ``--within`` s of standing still.

    .venv/bin/python bench/gravity_check_false_alarm.py                       # 40 seeds x 1 h, a few minutes
    .venv/bin/python bench/gravity_check_false_alarm.py --update-results      # also bench/results/gravity_check.json

``--effects-off bias_instability`` runs the same without the simulator's flicker floor (the slow bias wander the
calibration's noise model does not contain).
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
from nees_probe import POSES, shipped_calibration
from output_paths import add_update_results, results_dir

from fbg_accel_driver.gravity_check import DEFAULT_TOLERANCE_MPS2, GravityCheck, GravityCheckConfig
from fbg_accel_driver.sensor_constants import STANDARD_GRAVITY
from fbg_accel_sim.board_physics import SimConfig, simulate_recording


def still_run(seed: int, pose: list[float], duration_s: float, extra: dict[str, Any]) -> list[tuple[float, Any]]:
    """(time since the start of the run s, GravityTest) of every test of a still run at ``pose`` (psi, theta deg)."""
    over = {"scenario.poses.mode": "list", "scenario.poses.list": [pose], "scenario.poses.dwell_s": duration_s + 10.0,
            "scenario.poses.move_s": 1.0, "scenario.poses.repeat": 1,
            "scenario.temperature.initial_c": 24.0, **extra}
    rec = simulate_recording(SimConfig.default().with_overrides(over), seed=seed, duration_s=duration_s)
    cal = shipped_calibration()
    acc = cal.apply_counts(rec.ref, rec.xyz, rec.temp_c, rec.t_s)
    psi = rec.xyz / rec.ref[:, None]
    check = GravityCheck(cal, GravityCheckConfig(STANDARD_GRAVITY), float(np.median(np.diff(rec.t_s))))
    out = []
    t0 = float(rec.t_s[0])
    for t, a, p, temp in zip(rec.t_s.tolist(), acc.tolist(), psi.tolist(), rec.temp_c.tolist(), strict=True):
        test = check.update(a, p, temp)
        if test is not None:
            out.append((t - t0, test))
    return out


def failures(tests: list[tuple[float, Any]], tolerance: float) -> np.ndarray:
    """Which tests fail at ``tolerance`` (m/s^2) instead of the one they ran with (the k sigma part is kept)."""
    return np.array([abs(x.discrepancy_mps2) > x.threshold_mps2 - DEFAULT_TOLERANCE_MPS2 + tolerance for _, x in tests],
                    bool)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--hours", type=float, default=1.0, help="still time per seed without drift (h)")
    ap.add_argument("--drift", type=float, default=0.2, help="bias step on z (m/s^2) for the detection runs")
    ap.add_argument("--within", type=float, default=60.0, help="detected when a test fails this soon (s)")
    ap.add_argument("--tolerances", type=float, nargs="+", default=[0.05, 0.1, 0.15, 0.2])
    ap.add_argument("--effects-off", nargs="*", default=[], help="simulator effects switched off (scale 0)")
    ap.add_argument("--output", type=Path, default=None, help="JSON file (default: gravity_check.json in the scratch "
                    "directory, or in bench/results/ with --update-results)")
    add_update_results(ap)
    args = ap.parse_args(argv)
    off = {f"effects.{e}.scale": 0.0 for e in args.effects_off}
    started = time.perf_counter()
    quiet: dict[str, list] = {"tests": [], "seed": []}
    detect: dict[str, list] = {"first_s": [], "discrepancy": []}
    for s in range(args.seeds):
        tests = still_run(1000 + s, POSES[s % len(POSES)], args.hours * 3600.0, off)
        quiet["tests"] += tests
        quiet["seed"] += [s] * len(tests)
        pose = [0.0, 0.0] if s % 2 == 0 else [0.0, 180.0]  # z up / z down: the drift along gravity
        step = {**off, "effects.bias_step.scale": 1.0, "effects.bias_step.at_s": 0.0,
                "effects.bias_step.amplitude_mps2": [0.0, 0.0, args.drift]}
        dtests = still_run(2000 + s, pose, args.within + 5.0, step)
        failed = [t for t, x in dtests if x.failed and t <= args.within]
        detect["first_s"].append(failed[0] if failed else None)
        detect["discrepancy"].append([round(x.discrepancy_mps2, 4) for _, x in dtests])
        verdict = f"flagged at {failed[0]:.0f} s" if failed else "not flagged"
        print(f"seed {s}: {len(tests)} tests, {int(sum(x.failed for _, x in tests))} failed; drift run: {verdict}",
              flush=True)
    seeds = np.array(quiet["seed"])
    hours = args.seeds * args.hours
    per_tol = {}
    disc = np.array([x.discrepancy_mps2 for _, x in quiet["tests"]])
    noise_part = np.array([x.threshold_mps2 - DEFAULT_TOLERANCE_MPS2 for _, x in quiet["tests"]])
    first_two = [x[:2] for x in detect["discrepancy"]]  # the tests within 60 s of standing still (22 and 42 s)
    for tol in sorted({*args.tolerances, DEFAULT_TOLERANCE_MPS2}):
        f = failures(quiet["tests"], tol)
        hit = [any(abs(r) > tol + float(np.median(noise_part)) for r in d) for d in first_two]
        per_tol[f"{tol:g}"] = {"false_alarms": int(f.sum()), "per_test": round(float(f.mean()), 5),
                               "per_hour": round(float(f.sum()) / hours, 4),
                               "runs_with_any": round(len(np.unique(seeds[f])) / args.seeds, 3),
                               "drift_detected_fraction": round(float(np.mean(hit)), 3)}
    f = failures(quiet["tests"], DEFAULT_TOLERANCE_MPS2)
    pose_of = np.array([s % len(POSES) for s in seeds])
    per_pose = {f"psi={POSES[p][0]:g} theta={POSES[p][1]:g}": {
        "discrepancy_rms_mps2": round(float(np.sqrt(np.mean(disc[pose_of == p] ** 2))), 4),
        "discrepancy_abs_max_mps2": round(float(np.abs(disc[pose_of == p]).max()), 4),
        "false_alarms_per_test_at_default": round(float(f[pose_of == p].mean()), 5)}
        for p in np.unique(pose_of)}
    flagged = [t for t in detect["first_s"] if t is not None]
    result = {
        "command": "python bench/gravity_check_false_alarm.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": machine(), "seconds": round(time.perf_counter() - started, 1),
        "seeds": args.seeds, "hours_per_seed": args.hours, "effects_off": args.effects_off,
        "calibration": "config/calibration_sim.yaml (no coefficient_covariance: sigma is the noise only)",
        "tests": len(disc), "default_tolerance_mps2": DEFAULT_TOLERANCE_MPS2,
        "threshold_mps2_median": round(float(np.median([x.threshold_mps2 for _, x in quiet["tests"]])), 4),
        "discrepancy_rms_mps2": round(float(np.sqrt(np.mean(disc**2))), 4),
        "discrepancy_abs_max_mps2": round(float(np.abs(disc).max()), 4),
        "false_alarms_by_tolerance": per_tol,
        "by_orientation": per_pose,
        "drift_mps2": args.drift, "within_s": args.within,
        "detected_fraction": round(len(flagged) / args.seeds, 3),
        "detected_at_s_median": float(np.median(flagged)) if flagged else None,
        "drift_run_discrepancies_mps2": detect["discrepancy"],
    }
    path = args.output or results_dir(args.update_results) / "gravity_check.json"
    path.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    print(json.dumps({k: v for k, v in result.items() if k not in ("drift_run_discrepancies_mps2", "machine")}, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
