"""Code widths of the simulated ESP32 ADC: is an injected width pattern recovered, and does the table remove its bias?

Not a test (test/test_adc_code_widths.py asserts the same with fewer seeds and margin). For each seed, a campaign on
the measured run's table grid (theta and psi in 30 degree steps, 156 poses, 1 s each) with the board's measured
noise (white noise x ``NOISE_SCALE``, 1 count on the reference), once with ``effects.adc_code_widths`` on (the
measured pattern of config/sim_default.yaml) and once off, same seed (same noise draws):

* ``covered``: the share of the 16 pooled pattern widths whose stated 95 % interval holds the injected width;
* ``bias_before`` / ``bias_after``: rms over visits and channels of the visit mean code with the pattern minus the
  one without it (counts), read raw and through the estimated code table (``AdcCodeTable.map_counts``);
* ``claimed_without``: the pattern found (p < 0.01) in the campaign without it (it should not be).

    .venv/bin/python bench/adc_code_widths_check.py [--seeds 10] [--output PATH] [--update-results]

Writes adc_code_widths_check.json to the scratch directory (bench/output_paths.py) by default;
``--update-results``: bench/results/adc_code_widths_check.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import output_paths

from fbg_accel_calibration.diagnosis.data import visit_ids
from fbg_accel_calibration.fit.adc_codes import code_table, recording_code_widths
from fbg_accel_sim.board_physics import simulate_recording
from fbg_accel_sim.sim_config import SimConfig

NAMED = ("reference_dark_offset", "thermal_lag", "spectral_nonlinearity", "time_drift", "channel_delay", "tia_lowpass",
         "thermal_hysteresis", "unmodelled_cable_torque")
NOISE_SCALE = 3.0  # the measured series' axes read 1-3 counts rms within a visit; the simulator's Table 2 noise 0.4-0.9
CAMPAIGN = {**{f"effects.{k}.scale": 0.0 for k in NAMED}, "scenario.poses.mode": "grid", "scenario.poses.dwell_s": 1.0,
            "scenario.poses.move_s": 1.0, "scenario.poses.grid.theta_step_deg": 30.0,
            "scenario.poses.grid.psi_step_deg": 30.0, "noise.reference_noise_counts": 1.0,
            "effects.white_noise.scale": NOISE_SCALE}
RESULTS = output_paths.COMMITTED / "adc_code_widths_check.json"


def campaign(seed: int, pattern: bool):
    """A simulated campaign (``Recording``) with the measured width pattern on or off."""
    cfg = SimConfig.default().with_overrides({**CAMPAIGN, "effects.adc_code_widths.scale": 1.0 if pattern else 0.0})
    return simulate_recording(cfg, seed=seed)


def _visit_means(counts: np.ndarray, groups: np.ndarray, rows: np.ndarray) -> np.ndarray:
    _, inv = np.unique(groups[rows], return_inverse=True)
    n = np.bincount(inv)
    return np.stack([np.bincount(inv, counts[rows, j]) / n for j in range(counts.shape[1])], axis=1)


def check(seed: int) -> dict:
    """One seed's figures (module docstring)."""
    on, off = campaign(seed, True), campaign(seed, False)
    injected = np.asarray(SimConfig.default().get("effects.adc_code_widths.widths"), float)
    groups, rows = visit_ids(on.pose_id, on.run_id), on.pose_id >= 0
    counts_on = np.column_stack([on.ref, on.xyz])
    counts_off = np.column_stack([off.ref, off.xyz])
    est = recording_code_widths(counts_on, groups, rows, per_channel=False)
    table = code_table(est, {"source": f"simulated seed {seed}"})
    ref_c, xyz_c = table.map_counts(on.ref, on.xyz)
    truth = _visit_means(counts_off, groups, rows)
    before = _visit_means(counts_on, groups, rows) - truth
    after = _visit_means(np.column_stack([ref_c, xyz_c]), groups, rows) - truth
    without = recording_code_widths(counts_off, groups, rows, per_channel=False)
    p = est.pooled
    return {"seed": seed, "covered": float(np.mean(np.abs(p.pattern - injected) <= p.pattern_u95)),
            "pattern": p.pattern.round(3).tolist(), "u95": p.pattern_u95.round(3).tolist(), "p_value": p.p_value,
            "bias_before": float(np.sqrt(np.mean(before ** 2))), "bias_after": float(np.sqrt(np.mean(after ** 2))),
            "claimed_without": bool(without.pooled.pattern_found), "p_without": without.pooled.p_value}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--output", type=Path, default=output_paths.scratch_dir() / "adc_code_widths_check.json")
    ap.add_argument("--update-results", action="store_true", help=f"write {RESULTS}")
    args = ap.parse_args(argv)
    runs = []
    for seed in range(1, args.seeds + 1):
        runs.append(r := check(seed))
        print(f"seed {r['seed']}: covered {r['covered']:.3f}, bias {r['bias_before']:.3f} -> {r['bias_after']:.3f} "
              f"counts, pattern p {r['p_value']:.2g}; without the pattern p {r['p_without']:.2g}", flush=True)
    out = {"noise_scale": NOISE_SCALE, "runs": runs,
           "covered_all": float(np.mean([r["covered"] for r in runs])),
           "claimed_without": sum(r["claimed_without"] for r in runs)}
    print(f"widths within their 95 % interval: {out['covered_all']:.3f} of {16 * len(runs)}; pattern claimed without "
          f"it in {out['claimed_without']} of {len(runs)} seeds")
    path = RESULTS if args.update_results else args.output
    path.write_text(json.dumps(out, indent=1), encoding="utf-8")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
