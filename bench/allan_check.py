"""Allan tool against known noise: where the numbers in docs/calibration_fit.md come from.

Not a test (test/test_allan.py asserts tolerances). Writes bench/results/allan_check.json with

* ``flicker_hours``: 8 independent hours (10 Hz) of white + flicker noise with known bias instability
  B = 0.5 / 1.0 / 2.0 mg: ratio read / configured per hour and axis, their mean, min and max;
* ``simulated_hour``: the board simulator (Table 2 noise model; non-noise effects off), calibrated on a
  short multi-position run, static hour, seed 2: VRW and BI read vs configured, once with x VRW 1.2
  (floor within reach of one hour) and once with Table 2's x VRW 3.96 (floor at ~1614 s).

    .venv/bin/python bench/allan_check.py
"""

from __future__ import annotations

import json

import numpy as np
from output_paths import output_dir_from_command_line

from fbg_accel_calibration.fit.allan import BI_FACTOR, MG_TO_MPS2, allan_deviation
from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig, simulate_recording
from fbg_accel_sim.noise import flicker_noise


def flicker_hours() -> dict:
    rate, n = 10.0, 36000
    b = np.array([0.5, 1.0, 2.0]) * MG_TO_MPS2
    sigma = np.array([0.006, 0.01, 0.006])
    ratios = []
    for seed in range(8):
        rng = np.random.default_rng(seed)
        x = np.stack([flicker_noise(n, rate, b[j], rng) for j in range(3)], axis=1) + rng.standard_normal((n, 3)) * sigma
        ratios.append(allan_deviation(x, rate).bias_instability_mg * MG_TO_MPS2 / b)
    r = np.array(ratios)
    return {"configured_bi_mg": (b / MG_TO_MPS2).tolist(), "floor_adev_mps2": (BI_FACTOR * b).tolist(),
            "ratio_read_over_configured": r.round(3).tolist(), "mean": r.mean(axis=0).round(3).tolist(),
            "min": float(r.min().round(3)), "max": float(r.max().round(3))}


def simulated_hour(vrw: list[float]) -> dict:
    off = {f"effects.{k}.scale": 0.0 for k in ("time_drift", "reference_dark_offset", "source_power_wander",
                                               "thermal_hysteresis", "thermal_lag")}
    base = SimConfig.default().with_overrides({**off, "noise.vrw_mps_per_sqrt_h": vrw})
    poses = [[0, 0], [0, 180], [270, 90], [90, 90], [180, 90], [0, 90], [45, 45], [135, 60]]
    cal_cfg = base.with_overrides({"scenario.poses.mode": "list", "scenario.poses.list": poses,
                                   "scenario.poses.dwell_s": 20.0, "scenario.poses.move_s": 2.0})
    cal = fit_thermal(simulate_recording(cal_cfg, seed=1), 0)
    static = simulate_recording(base, seed=2, duration_s=3600.0)
    cn = BoardSimulator(base, seed=2).configured_noise()
    res = allan_deviation(cal.apply_counts(static.ref, static.xyz, static.temp_c, static.t_s), 100.0)
    return {"configured_vrw": np.round(cn["vrw_mps_per_sqrt_h"], 3).tolist(),
            "read_vrw": res.vrw_mps_per_sqrt_h.round(3).tolist(),
            "read_white_noise_vrw": [None if np.isnan(v) else round(float(v), 3) for v in res.white_noise_vrw_mps_per_sqrt_h],
            "white_tau_range_s": [None if np.isnan(r[0]) else np.round(r, 2).tolist() for r in res.white_tau_range_s],
            "configured_bi_mg": np.round(cn["bias_instability_mg"], 3).tolist(),
            "read_bi_mg": res.bias_instability_mg.round(3).tolist(),
            "configured_min_adev_tau_s": np.round(cn["min_adev_tau_s"], 1).tolist(),
            "read_min_tau_s": res.bi_tau_s.round(1).tolist(),
            "bi_is_upper_bound": res.bi_is_upper_bound.tolist()}


def main() -> None:
    out_dir = output_dir_from_command_line(__doc__.splitlines()[0])
    out = {"flicker_hours": flicker_hours(),
           "simulated_hour": {"x_vrw_1.2": simulated_hour([1.2, 1.94, 2.87]), "table2": simulated_hour([3.96, 1.94, 2.87])}}
    path = out_dir / "allan_check.json"
    path.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
