"""False alarms of the calibration node's live stillness detector (fbg_accel_driver.stillness_monitor).

Long static recordings of the board simulator (no ROS), cut into runs as the node sees them: the noise
floor is learnt from the first ``learn_s`` seconds of each run, then the next 60 s are tested. Two figures:

1. per window: the fraction of still windows whose Psi variance exceeds the leave threshold on any axis,
   against the nominal exceedance (split over the three axes), at 3e-2 .. 3e-5: shows whether the law
   (saddlepoint of the correlated window variance over a learnt floor) holds in the tail;
2. per run: still -> moving transitions of the full detector (hysteresis, 1 s hold) with a budget of 0.1
   false alarms per run, against that budget.

Usage: .venv/bin/python bench/stillness_false_alarm.py [--hours 1]
Writes bench/results/stillness_false_alarm.{json,md}.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import platform

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from output_paths import add_update_results, results_dir

from fbg_accel_driver.stillness_monitor import (
    StillnessMonitor,
    learn_noise_floor,
    ratio_quantile,
    window_variance_weights,
)
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig

NOMINAL = [3e-2, 3e-3, 3e-4, 3e-5]
PER_RUN = 0.1
TEST_S = 60.0


def measure(rate: float, learn_s: float, seconds: float, overrides: dict, seed: int = 2) -> dict:
    cfg = SimConfig.default().with_overrides({**overrides, "scenario.rate_hz": rate})
    counts = BoardSimulator(cfg, seed=seed).step(int(seconds * rate)).counts.astype(float)
    psi = counts[:, 1:] / counts[:, :1]
    w, n_learn = round(0.25 * rate), round(learn_s * rate)
    run = n_learn + round(TEST_S * rate)
    exceed = np.zeros(len(NOMINAL))
    windows = transitions = runs = 0
    for s0 in range(0, len(psi) - run + 1, run):
        x = psi[s0:s0 + run]
        quant = (1.0 / np.median(counts[s0:s0 + n_learn, 0])) ** 2 / 12.0
        floor = learn_noise_floor(x[:n_learn], max_lag=w).with_minimum_variance(quant)
        weights = [window_variance_weights(floor.acf[j], w) for j in range(3)]
        expected = floor.variance * np.array([lam.sum() for lam in weights])
        v = sliding_window_view(x[n_learn:], w, axis=0).var(axis=-1, ddof=1)
        windows += len(v)
        for i, a in enumerate(NOMINAL):
            thr = expected * np.array([ratio_quantile(a / 3, weights[j], floor.dof[j]) for j in range(3)])
            exceed[i] += np.count_nonzero(np.any(v > thr, axis=1))
        mon = StillnessMonitor(floor, window=w, hold=round(rate), run_samples=run - n_learn, false_alarm_per_run=PER_RUN)
        was = False
        for sample in x[n_learn:]:
            now = mon.update(sample)
            transitions += was and not now
            was = now
        runs += 1
    return {"rate_hz": rate, "learn_s": learn_s, "overrides": overrides, "windows": windows, "runs": runs,
            "nominal": NOMINAL, "observed": (exceed / windows).tolist(), "transitions": transitions,
            "transition_budget": PER_RUN * runs}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0, help="simulated hours at 100 Hz (1 kHz: a sixth of it)")
    add_update_results(ap)
    args = ap.parse_args()
    out_dir = results_dir(args.update_results)
    sec = args.hours * 3600.0
    cases = [(100.0, 2.0, sec, {}), (100.0, 5.0, sec, {}), (1000.0, 5.0, sec / 6, {}),
             (100.0, 5.0, sec, {"noise.reference_noise_counts": 1.0})]
    rows = [measure(*c) for c in cases]
    result = {"date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"), "machine": platform.platform(),
              "cases": rows}
    (out_dir / "stillness_false_alarm.json").write_text(json.dumps(result, indent=1))
    lines = [f"# Stillness detector false alarms ({result['date']}, {result['machine']})", "",
             "Command: `.venv/bin/python bench/stillness_false_alarm.py`", "",
             "| rate | learn | simulator | windows | observed at nominal " + " / ".join(f"{a:.0e}" for a in NOMINAL)
             + f" | still->moving per run (budget {PER_RUN:g}) |", "|---|---|---|---|---|---|"]
    for r in rows:
        sim = ", ".join(f"{k}={v}" for k, v in r["overrides"].items()) or "defaults"
        lines.append(f"| {r['rate_hz']:g} Hz | {r['learn_s']:g} s | {sim} | {r['windows']} | "
                     + " / ".join(f"{o:.1e}" for o in r["observed"])
                     + f" | {r['transitions']} in {r['runs']} runs ({r['transitions'] / r['runs']:.3f}) |")
    (out_dir / "stillness_false_alarm.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
