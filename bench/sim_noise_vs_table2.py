"""Calibrated-output noise of the simulator with its default chain effects, against paper Table 2.

Not a test. ``bench/allan_check.py`` checks the noise model with every non-noise effect off; this script
runs the default configuration (``config/sim_default.yaml``; only ``time_drift`` off, since the paper's
Allan data start after the warm-up) and switches off one mechanism at a time, to show which effect
moves the calibrated output away from Table 2:

* ``default``: all chain effects on, ``noise.reference_noise_counts`` 0;
* ``wander_off``: ``source_power_wander`` off (the noise parts alone, as allan_check);
* ``quantisation_off``: ``adc_quantisation`` off: the noiseless reference is no longer rounded, so the
  slowly wandering reference stops stepping across ADC codes;
* ``dark_offset_off``: ``reference_dark_offset`` off: the source wander cancels again in Psi = c/c_ref;
* ``reference_noise_1``: ``noise.reference_noise_counts`` 1.0 (the measured board's read noise).

Each: calibrated on a short multi-position run (seed 1), static run at 23.4 degC (seed 2) of ``--hours``,
``fbg_accel_calibration.fit.allan``: VRW and bias instability read against the configured Table 2 values,
and the ratio read / expected (``NoiseModel.expected_adev``) at a few cluster times. Writes
bench/results/sim_noise_vs_table2.json::

    .venv/bin/python bench/sim_noise_vs_table2.py            # 6 h per case, about 2 min
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from output_paths import add_update_results, results_dir

from fbg_accel_calibration.fit.allan import allan_deviation
from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig, simulate_recording

CASES = {
    "default": {},
    "wander_off": {"effects.source_power_wander.scale": 0.0},
    "quantisation_off": {"effects.adc_quantisation.scale": 0.0},
    "dark_offset_off": {"effects.reference_dark_offset.scale": 0.0},
    "reference_noise_1": {"noise.reference_noise_counts": 1.0},
}
TAUS_S = (1.0, 10.0, 30.0, 100.0, 300.0)
CAL_POSES = [[0, 0], [0, 180], [270, 90], [90, 90], [180, 90], [0, 90], [45, 45], [135, 60]]


def cluster_adev(a: np.ndarray, rate_hz: float, tau_s: float) -> np.ndarray:
    """Non-overlapping Allan deviation (3,) of ``a`` (N, 3) at cluster time ``tau_s``."""
    m = round(tau_s * rate_hz)
    n = len(a) // m
    means = a[: n * m].reshape(n, m, -1).mean(axis=1)
    return np.sqrt(0.5 * np.mean(np.diff(means, axis=0) ** 2, axis=0))


def case(overrides: dict, hours: float) -> dict:
    base = SimConfig.default().with_overrides({"effects.time_drift.scale": 0.0, **overrides})
    cal_cfg = base.with_overrides({"scenario.poses.mode": "list", "scenario.poses.list": CAL_POSES,
                                   "scenario.poses.dwell_s": 20.0, "scenario.poses.move_s": 2.0})
    cal = fit_thermal(simulate_recording(cal_cfg, seed=1), 0)
    static = simulate_recording(base, seed=2, duration_s=3600.0 * hours)
    accel = cal.apply_counts(static.ref, static.xyz, static.temp_c, static.t_s)
    res = allan_deviation(accel, static.metadata["rate_hz"])
    noise = BoardSimulator(base, seed=2).configured_noise()
    expected = noise["model"].expected_adev(np.array(TAUS_S))
    ratio = {f"{t:g}": (cluster_adev(accel, static.metadata["rate_hz"], t) / expected[i]).round(2).tolist()
             for i, t in enumerate(TAUS_S)}
    return {"overrides": overrides, "configured_vrw": np.round(noise["vrw_mps_per_sqrt_h"], 2).tolist(),
            "read_vrw": res.vrw_mps_per_sqrt_h.round(2).tolist(),
            "read_white_noise_vrw": [None if np.isnan(v) else round(float(v), 2) for v in res.white_noise_vrw_mps_per_sqrt_h],
            "white_tau_range_s": [None if np.isnan(r[0]) else np.round(r, 1).tolist() for r in res.white_tau_range_s],
            "bi_is_upper_bound": res.bi_is_upper_bound.tolist(),
            "configured_bi_mg": np.round(noise["bias_instability_mg"], 2).tolist(),
            "read_bi_mg": res.bias_instability_mg.round(2).tolist(), "read_bi_tau_s": res.bi_tau_s.round(0).tolist(),
            "adev_read_over_expected": ratio}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hours", type=float, default=6.0, help="static run per case (h; the paper's Allan data: 6 h)")
    p.add_argument("--output", help="output file (default: sim_noise_vs_table2.json in the scratch or results directory)")
    add_update_results(p)
    args = p.parse_args()
    args.output = args.output or str(results_dir(args.update_results) / "sim_noise_vs_table2.json")
    out = {"hours": args.hours, "time_drift": "off in every case", "cases": {}}
    for name, over in CASES.items():
        out["cases"][name] = case(over, args.hours)
        r = out["cases"][name]
        print(f"{name:18s} VRW {r['read_vrw']} (Table 2 {r['configured_vrw']})  BI mg {r['read_bi_mg']} "
              f"(Table 2 {r['configured_bi_mg']})  ADEV read/expected at 1 s {r['adev_read_over_expected']['1']}, "
              f"300 s {r['adev_read_over_expected']['300']}", flush=True)
    path = Path(args.output)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
