"""How much of the TIA settling after a table move the offline fit keeps, against the dwell and move times.

The fit keeps a sample when its signal and the table's reference are still over a 5-sample window
(``static_detector``). A first-order TIA low-pass (paper Table 1, 1-1.7 Hz: time constants 0.09-0.16 s) makes
the signal approach its new value exponentially after the table stops; the window variance of that slow tail is
small, so the detector keeps most of it, and the tail enters the fit and its noise floor (``noise_sigma_mps2``,
which the driver publishes as the covariance). The calibration node records a pose only once it is still
(``stillness_monitor``), so its recordings hold no settling; a CSV of a table that moves on a fixed schedule does.

For each (dwell, move) the simulator (``test/fixtures/sim_diagnosis_baseline.yaml`` with the TIA low-pass on)
records a six-position run (4 repeats), ``fit_thermal`` fits it at degree 0, and two figures compare it with the
truth on the settled samples (at least 2 s at the pose):
- the fit's ``noise_sigma_mps2`` over the within-visit standard deviation of its output on those samples;
- the RMS over the visits of the mean error of the output against the true specific force (m/s^2).

Usage: .venv/bin/python bench/fit_settling_check.py
Writes bench/results/fit_settling.{json,md}.
"""

from __future__ import annotations

import datetime as _dt
import json
import platform
from pathlib import Path

import numpy as np
from output_paths import output_dir_from_command_line

from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_driver.thermal_model import normalise
from fbg_accel_sim.board_physics import SimConfig, simulate_recording

ROOT = Path(__file__).resolve().parents[1]
SIX = [[0, 0], [0, 180], [0, 90], [0, -90], [90, 90], [-90, 90]]
CASES = [(2.0, 1.0), (4.0, 1.0), (4.0, 2.0), (10.0, 2.0), (30.0, 2.0)]  # (dwell s, move s)
SETTLED_S = 2.0  # s at the pose after which the truth takes a sample as settled
SEED = 20


def case(dwell_s: float, move_s: float) -> dict[str, object]:
    cfg = SimConfig.load(ROOT / "test" / "fixtures" / "sim_diagnosis_baseline.yaml").with_overrides({
        "effects.tia_lowpass.scale": 1.0, "scenario.poses.mode": "list", "scenario.poses.list": SIX,
        "scenario.poses.repeat": 4, "scenario.poses.dwell_s": dwell_s, "scenario.poses.move_s": move_s})
    rec = simulate_recording(cfg, seed=SEED)
    cal = fit_thermal(rec, 0)
    truth = rec.metadata["truth"]
    err = cal.base_acceleration(normalise(rec.xyz, rec.ref), rec.temp_c) - truth["accel_true_mps2"]
    settled = ~truth["in_motion"] & (truth["time_at_pose_s"] >= min(SETTLED_S, 0.5 * dwell_s))
    visits = [settled & (truth["visit"] == v) for v in np.unique(truth["visit"][settled])]
    means = np.array([err[m].mean(axis=0) for m in visits])
    within = np.sqrt(np.mean([np.mean((err[m] - err[m].mean(axis=0)) ** 2, axis=0) for m in visits], axis=0))
    return {"dwell_s": dwell_s, "move_s": move_s, "noise_sigma_mps2": cal.noise_sigma_mps2.tolist(),
            "settled_within_sd_mps2": within.tolist(),
            "ratio": (cal.noise_sigma_mps2 / within).tolist(),
            "visit_mean_error_rms_mps2": np.sqrt(np.mean(means**2, axis=0)).tolist(),
            "samples_used": cal.fit["samples_used"], "samples_total": cal.fit["samples_total"]}


def main() -> int:
    out_dir = output_dir_from_command_line(__doc__.splitlines()[0])
    rows = [case(d, m) for d, m in CASES]
    doc = {"benchmark": "fit_settling", "command": ".venv/bin/python bench/fit_settling_check.py",
           "date_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
           "machine": {"cpu": platform.processor() or platform.machine(), "python": platform.python_version()},
           "seed": SEED, "settled_s": SETTLED_S, "cases": rows}
    (out_dir / "fit_settling.json").write_text(json.dumps(doc, indent=1) + "\n")

    def fmt(v: list[float], digits: int = 3) -> str:
        return " / ".join(f"{x:.{digits}f}" for x in v)

    lines = [f"Written by `{doc['command']}` on {doc['date_utc']}.", "",
             "| dwell [s] | move [s] | fit noise_sigma / settled sd (x / y / z) | visit-mean error RMS [m/s²] | samples used |",
             "|---:|---:|---|---|---:|"]
    lines += [f"| {r['dwell_s']:g} | {r['move_s']:g} | {fmt(r['ratio'], 2)} | {fmt(r['visit_mean_error_rms_mps2'])} | "
              f"{r['samples_used']} / {r['samples_total']} |" for r in rows]
    (out_dir / "fit_settling.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
