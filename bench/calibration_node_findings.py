"""Figures behind docs/calibration_node.md, from the simulator's batch API (no ROS).

1. Static-detector false alarms: fraction of windows of a still sensor whose Psi variance exceeds the
   node's threshold (noise floor learnt from the first 2 s, as the node does), per margin, window and rate.
2. Held-out error of eq. 28 per temperature degree: the six-pose plan at 16/24/45 degC (200 samples =
   2 s per pose, taken 1.2 s after arrival, as in test/test_calibration_e2e.py), validated on three
   oblique poses at the same levels; RMS error over the within-pose noise floor, per axis, with the
   simulator's defaults and with the reference dark offset switched off.

Usage: .venv/bin/python bench/calibration_node_findings.py [--seeds 3]
Writes bench/results/calibration_node_findings.{json,md}.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import platform
import tempfile
from pathlib import Path

import numpy as np
import yaml
from output_paths import add_update_results, results_dir

from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_calibration.fit.static_detector import estimate_noise_var, moving_variance, variance_threshold
from fbg_accel_calibration.io.recording import Recording
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig, simulate_recording

ROOT = Path(__file__).resolve().parents[1]
LEVELS = [16.0, 24.0, 45.0]
HELD_OUT = [[45.0, 45.0], [210.0, 120.0], [300.0, 60.0]]
SIX = [("z_down", 0, 180), ("z_up", 0, 0), ("x_down", 270, 90), ("x_up", 90, 90), ("y_down", 180, 90), ("y_up", 0, 90)]


def false_alarms(rate: float, window_s: float, margin: float, seeds: int) -> list[float]:
    out = []
    for seed in range(seeds):
        cfg = SimConfig.default().with_overrides({"scenario.rate_hz": rate})
        b = BoardSimulator(cfg, seed=seed).step(int(rate * 60))
        c = b.counts.astype(float)
        psi = c[:, 1:] / c[:, :1]
        w = max(3, round(window_s * rate))
        learn = psi[: int(2 * rate)]
        nv = np.maximum(estimate_noise_var(moving_variance(learn, w)[w // 2: -(w // 2)], w), (1 / 870) ** 2 / 12)
        thr = variance_threshold(nv, w, 1e-3, margin)
        out.append(float(np.mean(np.any(moving_variance(psi, w) > thr, axis=1))))
    return out


def held_out_ratios(extra: dict, seeds: int, rate: float = 100.0, rec_s: float = 2.0) -> dict[int, list[list[float]]]:
    plan = {"format": "fbg_accel_pose_plan", "format_version": 1, "dwell_s": 1.2 + rec_s + 0.6, "move_s": 0.8,
            "samples_per_pose": 100, "poses": [{"name": n, "psi_deg": p, "theta_deg": t} for n, p, t in SIX]}
    res: dict[int, list[list[float]]] = {0: [], 1: [], 2: []}
    with tempfile.TemporaryDirectory() as tmp:
        plan_file = Path(tmp) / "plan.yaml"
        plan_file.write_text(yaml.safe_dump(plan))
        for s in range(seeds):
            parts = []
            for i, level in enumerate(LEVELS):
                cfg = SimConfig.default().with_overrides({
                    **extra, "scenario.rate_hz": rate, "scenario.temperature.initial_c": level,
                    "scenario.poses.mode": "plan_file", "scenario.poses.plan_file": str(plan_file)})
                r = simulate_recording(cfg, seed=100 * s + 10 + i)
                tap = np.asarray(r.metadata["truth"]["time_at_pose_s"])
                r.pose_id = np.where((tap >= 1.2) & (tap < 1.2 + rec_s), r.pose_id, -1)
                parts.append(r)
            rec = Recording.concatenate(parts)
            val = []
            for i, level in enumerate(LEVELS):
                cfg = SimConfig.default().with_overrides({
                    **extra, "scenario.rate_hz": rate, "scenario.temperature.initial_c": level,
                    "scenario.poses.mode": "list", "scenario.poses.list": HELD_OUT,
                    "scenario.poses.dwell_s": 4.0, "scenario.poses.move_s": 0.8})
                val.append(BoardSimulator(cfg, seed=100 * s + 20 + i).step(int(rate * 14.0)))
            for degree in res:
                cal = fit_thermal(rec, degree, usable=rec.pose_id >= 0)
                errs, devs = [], []
                for b in val:
                    ok = (b.pose_id >= 0) & (b.time_at_pose_s >= 1.2)
                    c = b.counts.astype(float)
                    e = cal.apply_counts(c[ok, 0], c[ok, 1:], b.temp_sensor_c[ok], b.t_s[ok]) - b.gref_mps2[ok]
                    errs.append(e)
                    pid = b.pose_id[ok]
                    devs += [e[pid == k] - e[pid == k].mean(axis=0) for k in np.unique(pid)]
                floor = np.sqrt(np.mean(np.vstack(devs) ** 2, axis=0))
                rms = np.sqrt(np.mean(np.vstack(errs) ** 2, axis=0))
                res[degree].append((rms / floor).round(3).tolist())
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    add_update_results(ap)
    args = ap.parse_args()
    out_dir = results_dir(args.update_results)
    fa = {f"rate {rate:g} Hz, window {w:g} s, margin {m:g}": false_alarms(rate, w, m, 6)
          for rate in (100.0, 200.0) for w in (0.25,) for m in (3.0, 5.0)}
    ratios = {"simulator defaults": held_out_ratios({}, args.seeds),
              "reference_dark_offset off": held_out_ratios({"effects.reference_dark_offset.scale": 0.0}, args.seeds)}
    result = {"date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"), "machine": platform.platform(),
              "false_alarm_fraction": fa, "held_out_rms_over_floor": ratios}
    (out_dir / "calibration_node_findings.json").write_text(json.dumps(result, indent=1))
    lines = [f"# Calibration node findings ({result['date']}, {result['machine']})", "",
             "Command: `.venv/bin/python bench/calibration_node_findings.py`", "",
             "## Static detector: fraction of still windows above the threshold (6 x 60 s, noise learnt from 2 s)", "",
             "| setting | per seed | max |", "|---|---|---|"]
    lines += [f"| {k} | {' '.join(f'{v:.4f}' for v in vals)} | {max(vals):.4f} |" for k, vals in fa.items()]
    lines += ["", "## Held-out RMS error / within-pose noise floor, x / y / z (three oblique poses, 16/24/45 degC)", "",
              "| simulator | degree | mean over seeds | max over seeds |", "|---|---|---|---|"]
    for name, per_degree in ratios.items():
        for degree, rows in per_degree.items():
            a = np.asarray(rows)
            lines.append(f"| {name} | {degree} | {' / '.join(f'{v:.2f}' for v in a.mean(0))} | "
                         f"{' / '.join(f'{v:.2f}' for v in a.max(0))} |")
    (out_dir / "calibration_node_findings.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
