"""False alarms and detection of the driver's live gravity check (``fbg_accel_driver.gravity_check``) on the simulator.

Not a test. Pure core, no ROS, no wire: for each seed the simulator records a still sensor (one orientation per seed,
cycling through the twelve of ``bench/nees_probe.py``) for ``--hours``; a calibration (the shipped simulated one, or
with ``--fitted-calibrations N`` N calibrations fitted on simulated campaigns as ``fbg-accel-calib fit`` does, with their
coefficient covariance and slow error, used in turn) converts its counts (eq. 28, as the driver does) and every sample
goes through ``GravityCheck.update`` in order, as ``DriverCore`` feeds it.

* **false alarms**: the sensor has not drifted; every test (one per ``period_s`` of stillness) that fails is a false
  alarm. Reported per test, per 24 h of stillness and per run (the fraction of seeds with at least one);
* **detection**: the same sensor with a bias step of ``--drift`` m/s^2 (``effects.bias_step``) before it stands still,
  detected when a test fails within ``--within`` s of standing still. ``--drift-direction along`` (default): on z, z up
  or down, the drift along gravity; ``random``: in a direction drawn uniformly on the sphere at the seed's orientation,
  tabulated against its projection on gravity b cos(phi) (what |a| sees of it to first order). Several ``--drift``
  values: detection for each (the trade-off and the per-run discrepancies for the first);
* **budget**: the parts of each test's sigma (noise, J Sigma J^T, stated slow error; medians), the undrifted
  discrepancy's rms where the drifts are drawn, the drift runs' first test less the drift's projection (the sensor's own
  |a| - g there), and the simulator's truth of what no term states: the stationary
  standard deviation of its bias instability per axis (a bias with correlation times up to 10^4 s, drawn afresh each run,
  as a sensor's is long after its calibration);
* **trade-off**: both again for each tolerance of ``--tolerances`` and multiple of sigma of ``--k-sigmas`` (from the same
  tests: |discrepancy| > tolerance + allowance + k sigma, sigma each test's own, the allowance 0.12 m/s^2 for a file
  without ``slow_error``, ``gravity_check.UNSTATED_SLOW_ERROR_MPS2``, else 0).

    .venv/bin/python bench/gravity_check_false_alarm.py                       # 40 seeds x 1 h, a few minutes
    .venv/bin/python bench/gravity_check_false_alarm.py --update-results      # also bench/results/gravity_check.json
    .venv/bin/python bench/gravity_check_false_alarm.py --fitted-calibrations 6 --tolerance 0 --k-sigmas 2 3 3.89 5
    .venv/bin/python bench/gravity_check_false_alarm.py --fitted-calibrations 6 --hours 0.05 --drift 0.2 0.5 \
        --drift-direction random

``--effects-off bias_instability`` runs the same without the simulator's flicker floor, ``--bias-instability-scale``
with it scaled (campaigns and runs).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path
from statistics import NormalDist
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine_info import machine
from nees_probe import POSES, fitted_calibration, shipped_calibration
from output_paths import add_update_results, results_dir

from fbg_accel_driver.gravity_check import (
    DEFAULT_FALSE_ALARM_PER_TEST,
    DEFAULT_TOLERANCE_MPS2,
    GravityCheck,
    GravityCheckConfig,
)
from fbg_accel_driver.sensor_constants import STANDARD_GRAVITY
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig, simulate_recording


def still_run(seed: int, pose: list[float], duration_s: float, extra: dict[str, Any], cal: Any = None,
              tolerance: float = DEFAULT_TOLERANCE_MPS2, mean_out: list | None = None) -> list[tuple[float, Any]]:
    """(time since the start of the run s, GravityTest) of every test of a still run at ``pose`` (psi, theta deg),
    converted by ``cal`` (default: the shipped simulated calibration) and tested at ``tolerance`` (m/s^2); the mean
    calibrated specific force (3,) m/s^2, sensor frame, appended to ``mean_out`` when given."""
    over = {"scenario.poses.mode": "list", "scenario.poses.list": [pose], "scenario.poses.dwell_s": duration_s + 10.0,
            "scenario.poses.move_s": 1.0, "scenario.poses.repeat": 1,
            "scenario.temperature.initial_c": 24.0, **extra}
    rec = simulate_recording(SimConfig.default().with_overrides(over), seed=seed, duration_s=duration_s)
    cal = cal if cal is not None else shipped_calibration()
    acc = cal.apply_counts(rec.ref, rec.xyz, rec.temp_c, rec.t_s)
    if mean_out is not None:
        mean_out.append(acc.mean(axis=0))
    psi = rec.xyz / rec.ref[:, None]
    check = GravityCheck(cal, GravityCheckConfig(STANDARD_GRAVITY, tolerance), float(np.median(np.diff(rec.t_s))))
    out = []
    t0 = float(rec.t_s[0])
    for t, a, p, temp in zip(rec.t_s.tolist(), acc.tolist(), psi.tolist(), rec.temp_c.tolist(), strict=True):
        test = check.update(a, p, temp)
        if test is not None:
            out.append((t - t0, test))
    return out


def sigma_of(test: Any, tolerance: float, k: float) -> float:
    """The standard deviation (m/s^2) a test's threshold was made of: (threshold - tolerance - the allowance for a slow
    error the file does not state) / k."""
    return (test.threshold_mps2 - tolerance - test.unstated_slow_error_mps2) / k


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--first-seed", type=int, default=0,
                    help="seed index of the first run (runs s use simulator seeds 1000 + s, 2000 + s, 3000 + s): a "
                    "later batch of independent hours")
    ap.add_argument("--hours", type=float, default=1.0, help="still time per seed without drift (h)")
    ap.add_argument("--drift", type=float, nargs="+", default=[0.2],
                    help="bias step(s) (m/s^2) for the detection runs, one run per seed and value")
    ap.add_argument("--drift-direction", choices=("along", "random"), default="along",
                    help="along: on z with z up or down (along gravity); random: uniform on the sphere at the seed's "
                    "orientation, tabulated against its projection on gravity")
    ap.add_argument("--within", type=float, default=60.0, help="detected when a test fails this soon (s)")
    ap.add_argument("--tolerance", type=float, default=DEFAULT_TOLERANCE_MPS2,
                    help="gravity_tolerance_mps2 the check runs with (m/s^2)")
    ap.add_argument("--tolerances", type=float, nargs="+", default=[0.0, 0.05, 0.1, 0.15, 0.2],
                    help="tolerances of the trade-off table (from the same tests)")
    ap.add_argument("--k-sigmas", type=float, nargs="+", default=None,
                    help="multiples of each test's sigma of the trade-off table (default: the check's own k only)")
    ap.add_argument("--fitted-calibrations", type=int, default=0,
                    help="fit this many calibrations (bench/nees_probe.py fitted_calibration, seeds 100.., with their "
                    "coefficient covariance and slow error) and use them in turn instead of the shipped one")
    ap.add_argument("--campaign-repeat-levels", type=float, nargs="*", default=[],
                    help="with --fitted-calibrations: campaign levels (degC) given a second run, so that the slow error "
                    "holds its run-to-run part (bench/nees_probe.py --calibration-repeat-levels)")
    ap.add_argument("--bias-instability-scale", type=float, default=None,
                    help="effects.bias_instability.scale of the simulator (campaigns and runs); default the config's")
    ap.add_argument("--effects-off", nargs="*", default=[], help="simulator effects switched off (scale 0)")
    ap.add_argument("--output", type=Path, default=None, help="JSON file (default: gravity_check.json in the scratch "
                    "directory, or in bench/results/ with --update-results)")
    add_update_results(ap)
    args = ap.parse_args(argv)
    off: dict[str, Any] = {f"effects.{e}.scale": 0.0 for e in args.effects_off}
    if args.bias_instability_scale is not None:
        off["effects.bias_instability.scale"] = args.bias_instability_scale
    started = time.perf_counter()
    cals = [fitted_calibration(100 + i, overrides=off, repeat_levels=args.campaign_repeat_levels)
            for i in range(args.fitted_calibrations)] or [None]
    quiet: dict[str, list] = {"tests": [], "seed": []}
    detect: dict[float, dict[str, list]] = {b: {"first_s": [], "tests": [], "projection": []} for b in args.drift}
    for s in range(args.first_seed, args.first_seed + args.seeds):
        cal = cals[s % len(cals)]
        tests = still_run(1000 + s, POSES[s % len(POSES)], args.hours * 3600.0, off, cal, args.tolerance)
        quiet["tests"] += tests
        quiet["seed"] += [s] * len(tests)
        if args.drift_direction == "along":
            pose = [0.0, 0.0] if s % 2 == 0 else [0.0, 180.0]  # z up / z down: the drift along gravity
            unit = np.array([0.0, 0.0, 1.0])
        else:
            pose = POSES[s % len(POSES)]
            unit = np.random.default_rng(3000 + s).standard_normal(3)
            unit /= np.linalg.norm(unit)  # uniform on the sphere, sensor frame
        verdicts = []
        for b in args.drift:
            step = {**off, "effects.bias_step.scale": 1.0, "effects.bias_step.at_s": 0.0,
                    "effects.bias_step.amplitude_mps2": (b * unit).tolist()}
            mean: list = []
            dtests = [(t, x) for t, x in still_run(2000 + s, pose, args.within + 5.0, step, cal, args.tolerance, mean)
                      if t <= args.within]
            up = mean[0] - b * unit  # the specific force's direction without the drift (calibration error: ~0.01 rad)
            failed = [t for t, x in dtests if x.failed]
            detect[b]["first_s"].append(failed[0] if failed else None)
            detect[b]["tests"].append([x for _, x in dtests])
            detect[b]["projection"].append(float(b * unit @ up / np.linalg.norm(up)))
            verdicts.append(f"{b:g}: " + (f"flagged at {failed[0]:.0f} s" if failed else "not flagged"))
        print(f"seed {s}: {len(tests)} tests, {int(sum(x.failed for _, x in tests))} failed; drift runs "
              + ", ".join(verdicts), flush=True)
    seeds = np.array(quiet["seed"])
    hours = args.seeds * args.hours
    k_run = NormalDist().inv_cdf(1.0 - DEFAULT_FALSE_ALARM_PER_TEST / 2.0)
    disc = np.array([x.discrepancy_mps2 for _, x in quiet["tests"]])
    sig = np.array([sigma_of(x, args.tolerance, k_run) for _, x in quiet["tests"]])
    unstated = np.array([x.unstated_slow_error_mps2 for _, x in quiet["tests"]])
    trade = {}
    for tol in sorted({*args.tolerances, args.tolerance}):
        for k in sorted({*(args.k_sigmas or []), round(k_run, 2)}):
            f = np.abs(disc) > tol + unstated + k * sig
            hit = [any(abs(x.discrepancy_mps2) > tol + x.unstated_slow_error_mps2 + k * sigma_of(x, args.tolerance, k_run)
                       for x in d) for d in detect[args.drift[0]]["tests"]]
            trade[f"tolerance {tol:g}, k {k:g}"] = {
                "tolerance_mps2": tol, "k_sigma": k, "false_alarms": int(f.sum()), "per_test": round(float(f.mean()), 5),
                "per_24h": round(float(f.sum()) / hours * 24.0, 3),
                "hours_with_any": round(len(np.unique(seeds[f])) / args.seeds, 3),
                "drift_detected_fraction": round(float(np.mean(hit)), 3)}
    f = np.abs(disc) > np.array([x.threshold_mps2 for _, x in quiet["tests"]])
    pose_of = np.array([s % len(POSES) for s in seeds])
    per_pose = {f"psi={POSES[p][0]:g} theta={POSES[p][1]:g}": {
        "discrepancy_rms_mps2": round(float(np.sqrt(np.mean(disc[pose_of == p] ** 2))), 4),
        "discrepancy_abs_max_mps2": round(float(np.abs(disc[pose_of == p]).max()), 4),
        "false_alarms_per_test": round(float(f[pose_of == p].mean()), 5)}
        for p in np.unique(pose_of)}
    flagged = [t for t in detect[args.drift[0]]["first_s"] if t is not None]
    by_drift, by_projection = {}, {}
    edges = [0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, np.inf]
    for b, d in detect.items():
        hit = np.array([t is not None for t in d["first_s"]])
        proj = np.abs(np.array(d["projection"]))
        by_drift[f"{b:g}"] = {"flagged": int(hit.sum()), "runs": len(hit),
                              "projection_abs_min_mps2": round(float(proj.min()), 4),
                              "largest_projection_not_flagged_mps2": round(float(proj[~hit].max()), 4)
                              if not hit.all() else 0.0}
        for lo, hi in itertools.pairwise(edges):
            m = (proj >= lo) & (proj < hi)
            if m.any():
                row = by_projection.setdefault(f"{lo:g}..{hi:g}", {"flagged": 0, "runs": 0})
                row["flagged"] += int(hit[m].sum())
                row["runs"] += int(m.sum())
    drift_tests = [x for d in detect[args.drift[0]]["tests"] for x in d]
    # the first test of each drift run less the drift's projection: what the sensor itself shows there, undrifted
    own = np.array([d[0].discrepancy_mps2 - p for d, p in zip(detect[args.drift[0]]["tests"],
                                                               detect[args.drift[0]]["projection"], strict=True) if d])
    at_drift_pose = np.isin(pose_of, [1, 0] if args.drift_direction == "along" else list(range(len(POSES))))
    bi = BoardSimulator(SimConfig.default().with_overrides(off), seed=0)
    budget = {
        "sigma_noise_mps2_median": round(float(np.median([x.sigma_noise_mps2 for x in drift_tests])), 4),
        "sigma_calibration_mps2_median": round(float(np.median([x.sigma_calibration_mps2 for x in drift_tests])), 4),
        "sigma_slow_mps2_median": round(float(np.median([x.sigma_slow_mps2 for x in drift_tests])), 4),
        "threshold_mps2_median": round(float(np.median([x.threshold_mps2 for x in drift_tests])), 4),
        "tolerance_mps2": args.tolerance,
        "undrifted_discrepancy_rms_mps2_at_the_drift_orientations": round(float(np.sqrt(np.mean(disc[at_drift_pose]**2))), 4)
        if at_drift_pose.any() else None,
        "drift_runs_first_test_less_projection_mps2": {"rms": round(float(np.sqrt(np.mean(own**2))), 4),
                                                        "min": round(float(own.min()), 4), "max": round(float(own.max()), 4)},
        "simulator_bias_instability_stationary_sigma_mps2": [round(float(np.sqrt(ax.bi_q.sum())) * bi.bi_scale, 4)
                                                             for ax in bi.noise_model.axes],
    }
    slow = [c.slow_error.sigma_mps2.round(4).tolist() for c in cals if c is not None and c.slow_error is not None]
    result = {
        "command": "python bench/gravity_check_false_alarm.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": machine(), "seconds": round(time.perf_counter() - started, 1),
        "seeds": args.seeds, "first_seed": args.first_seed, "hours_per_seed": args.hours, "effects_off": args.effects_off,
        "bias_instability_scale": args.bias_instability_scale,
        "calibration": (f"{len(cals)} fitted (bench/nees_probe.py fitted_calibration, seeds 100..)" if cals[0] is not None
                        else "config/calibration_sim.yaml (no coefficient_covariance, no slow_error: sigma is the noise "
                        "only)"),
        "slow_error_sigma_mps2": slow, "campaign_repeat_levels_c": args.campaign_repeat_levels,
        "tests": len(disc), "tolerance_mps2": args.tolerance, "k_sigma": round(k_run, 3),
        "threshold_mps2_median": round(float(np.median([x.threshold_mps2 for _, x in quiet["tests"]])), 4),
        "sigma_mps2_median": round(float(np.median(sig)), 4),
        "discrepancy_rms_mps2": round(float(np.sqrt(np.mean(disc**2))), 4),
        "discrepancy_abs_max_mps2": round(float(np.abs(disc).max()), 4),
        "false_alarms": int(f.sum()), "false_alarms_per_24h": round(float(f.sum()) / hours * 24.0, 3),
        "trade_off": trade,
        "by_orientation": per_pose,
        "drift_mps2": args.drift, "drift_direction": args.drift_direction, "within_s": args.within,
        "budget": budget, "by_drift": by_drift, "by_projection_abs_mps2": by_projection,
        "detected_fraction": round(len(flagged) / args.seeds, 3),
        "detected_at_s_median": float(np.median(flagged)) if flagged else None,
        "drift_run_discrepancies_mps2": [[round(x.discrepancy_mps2, 4) for x in d] for d in detect[args.drift[0]]["tests"]],
        "drift_run_projections_mps2": {f"{b:g}": [round(v, 4) for v in d["projection"]] for b, d in detect.items()},
    }
    path = args.output or results_dir(args.update_results) / "gravity_check.json"
    path.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    print(json.dumps({k: v for k, v in result.items()
                      if k not in ("drift_run_discrepancies_mps2", "drift_run_projections_mps2", "machine")}, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
