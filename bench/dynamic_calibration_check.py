#!/usr/bin/env python3
"""Dynamic calibration on the simulated board, end to end (issue 9). Not a test: it writes the README's
figures and numbers.

1. The stepped-sine plan (config/excitation_plan_stepped_sine.yaml: 0.5-20 Hz, LDV reference on the aux
   channel, protocol version 2) is simulated at 500 Hz for ``--seeds`` seeds and decoded through the
   driver's own ``StreamDecoder``; ``run_dynamic`` recovers each axis's TIA cut-off and pure delay,
   compared with the simulator's configured truth (electronics.tia_cutoff_hz, effects.channel_delay).
2. The first seed's points and fits: Bode plot (docs/img/dynamic_bode.png), table (docs/results_dynamic.md).
3. Seed Fig. 12's check: a 3 Hz run (a frequency the fit did not use) at the ESP32's 100 Hz goes through
   ``DriverCore`` with chain_compensation none / delay / equalise (10 Hz); RMS difference to the
   reference over whole periods.
4. A step on the reference's time line, through each axis's continuous TIA stage, at 100 Hz.

Usage: ``.venv/bin/python bench/dynamic_calibration_check.py [--seeds 5]`` (about 10 s).
Results: bench/results/dynamic_calibration.json, docs/results_dynamic.md, docs/img/dynamic_bode.png.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from machine_info import results_doc, write_results  # noqa: E402

from fbg_accel_calibration.bode_plot import plot_bode  # noqa: E402
from fbg_accel_calibration.dynamic_analysis import budget_table_markdown  # noqa: E402
from fbg_accel_calibration.dynamic_calibration import run_dynamic  # noqa: E402
from fbg_accel_calibration.dynamic_check import step_check  # noqa: E402
from fbg_accel_calibration.excitation_plan import ExcitationPlan  # noqa: E402
from fbg_accel_driver.driver_main import default_calibration_path  # noqa: E402
from fbg_accel_driver.thermal_model import ThermalCalibration  # noqa: E402
from fbg_accel_sim.dynamic_run import simulate_dynamic_run, simulated_tone_check  # noqa: E402
from fbg_accel_sim.sim_config import SimConfig  # noqa: E402

PLAN_FILE = ROOT / "config" / "excitation_plan_stepped_sine.yaml"
REFERENCE_CUTOFF_HZ = 1.0  # paper Table 1 (design value of the reference TIA; a slide run cannot see it)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--rate", type=float, default=500.0, help="board rate of the calibration runs (Hz)")
    ap.add_argument("--output", type=Path, default=ROOT / "bench" / "results" / "dynamic_calibration.json")
    ap.add_argument("--md", type=Path, default=ROOT / "docs" / "results_dynamic.md")
    ap.add_argument("--png", type=Path, default=ROOT / "docs" / "img" / "dynamic_bode.png")
    args = ap.parse_args(argv)

    plan = ExcitationPlan.load(PLAN_FILE)
    static = ThermalCalibration.load(default_calibration_path())
    cfg = SimConfig.default()
    fc_true = [float(v) * cfg.scale("tia_lowpass") ** -1 if cfg.scale("tia_lowpass") else float("inf")
               for v in cfg.get("electronics.tia_cutoff_hz")]
    delay_true = cfg.scale("channel_delay") * float(cfg.get("effects.channel_delay.delay_s"))

    recoveries, first = [], None
    for seed in range(args.seeds):
        rec, _, _ = simulate_dynamic_run(plan, rate_hz=args.rate, seed=seed)
        res = run_dynamic(rec, plan, static, reference_cutoff_hz=REFERENCE_CUTOFF_HZ)
        first = first or res
        row = {"seed": seed}
        for a, ax in enumerate("xyz"):
            m = res.models[ax]
            row[ax] = {"cutoff_hz": m.cutoff_hz, "u_cutoff_hz": m.u_cutoff_hz,
                       "cutoff_error_pct": 100.0 * (m.cutoff_hz / fc_true[a + 1] - 1.0),
                       "delay_ms": 1e3 * m.delay_s, "u_delay_ms": 1e3 * m.u_delay_s,
                       "delay_error_ms": 1e3 * (m.delay_s - delay_true), "gain": m.gain}
        recoveries.append(row)
        print(f"seed {seed}: " + "  ".join(f"{ax} fc {row[ax]['cutoff_hz']:.3f} Hz ({row[ax]['cutoff_error_pct']:+.1f} %), "
                                           f"delay {row[ax]['delay_ms']:.2f} ms" for ax in "xyz"), flush=True)
    assert first is not None
    args.png.parent.mkdir(parents=True, exist_ok=True)
    plot_bode(first.points, first.models, args.png, title=f"Dynamic calibration (simulated, seed 0, {args.rate:g} Hz)")

    cal = ThermalCalibration.from_dict({**static.to_dict(), "dynamic": first.dynamics.to_dict()})
    tone = simulated_tone_check(plan.with_tone(3.0, 8.0, 14.0), cal, rate_hz=100.0, seed=100)
    steps = [step_check(cal, "delay", 100.0), step_check(cal, "equalise", 100.0, 10.0),
             step_check(cal, "equalise", 100.0, 20.0)]

    cut = {ax: [r[ax]["cutoff_error_pct"] for r in recoveries] for ax in "xyz"}
    dly = {ax: [r[ax]["delay_error_ms"] for r in recoveries] for ax in "xyz"}
    doc = results_doc("dynamic_calibration_check.py", argv, "dynamic calibration on the simulated board") | {
           "truth": {"cutoff_hz": fc_true, "delay_s": delay_true}, "rate_hz": args.rate, "recoveries": recoveries,
           "max_abs_cutoff_error_pct": {ax: float(np.max(np.abs(v))) for ax, v in cut.items()},
           "max_abs_delay_error_ms": {ax: float(np.max(np.abs(v))) for ax, v in dly.items()},
           "first_seed": first.as_dict(), "tone_check": tone.as_dict(), "step_check": steps}
    write_results(args.output, doc, indent=1)
    x2 = next(p for p in first.points if p.axis == "x" and p.f_hz == 2.0)
    args.md.write_text(markdown(doc, first.report(), budget_table_markdown(x2)))
    print(f"wrote {args.output}, {args.md}, {args.png}")
    return 0


def markdown(doc: dict, report: str, budget: str) -> str:
    t = doc["truth"]
    lines = ["# Dynamic calibration on the simulated board",
             "",
             f"Written by `{doc['command'].strip()}` on {doc['date_utc']} ({doc['machine'].get('cpu', '?')}). "
             "Data: the simulator (`config/sim_default.yaml`) running `config/excitation_plan_stepped_sine.yaml` "
             f"at {doc['rate_hz']:g} Hz, decoded by the driver's stream decoder; truth: TIA cut-offs "
             f"{', '.join(f'{v:g}' for v in t['cutoff_hz'])} Hz (reference, x, y, z), pure delay "
             f"{1e3 * t['delay_s']:g} ms (`effects.channel_delay`).",
             "",
             "## Recovered chain, every seed",
             "",
             "| seed | x fc [Hz] (error) | y fc [Hz] (error) | z fc [Hz] (error) | x / y / z delay [ms] |",
             "|---:|---:|---:|---:|---:|"]
    for r in doc["recoveries"]:
        lines.append(f"| {r['seed']} | " + " | ".join(
            f"{r[ax]['cutoff_hz']:.3f} +- {r[ax]['u_cutoff_hz']:.3f} ({r[ax]['cutoff_error_pct']:+.1f} %)" for ax in "xyz")
            + " | " + " / ".join(f"{r[ax]['delay_ms']:.2f}" for ax in "xyz") + " |")
    lines += ["", "Largest cut-off error: " + ", ".join(f"{ax} {v:.1f} %" for ax, v in doc["max_abs_cutoff_error_pct"].items())
              + "; largest delay error: " + ", ".join(f"{ax} {v:.2f} ms" for ax, v in doc["max_abs_delay_error_ms"].items())
              + ".", "", "## Points and fit of seed 0", "", "![Bode plot](img/dynamic_bode.png)", "", report, "",
              "Uncertainty budget of one point (seed Tables 2-3):", "", budget, "",
              "## Seed Fig. 12: a frequency the fit did not use", ""]
    tone = doc["tone_check"]
    lines += [f"{tone['f_hz']:g} Hz, {tone['periods']} whole periods at 100 Hz through `DriverCore`; RMS difference between "
              "the published acceleration (at its stamps) and the reference, mean removed:", "",
              "| chain_compensation | x [m/s^2] | y [m/s^2] | z [m/s^2] | reduction x / y / z |", "|---|---:|---:|---:|---:|"]
    for mode, vals in tone["rms_mps2"].items():
        red = tone["reduction_pct"].get(mode)
        lines.append(f"| {mode} | " + " | ".join(f"{v:.3f}" for v in vals) + " | "
                     + (" / ".join(f"{v:.0f} %" for v in red) if red else "-") + " |")
    lines += ["", "## A step on the reference's time line (100 Hz)", "",
              "When the published output crosses half of an acceleration step, relative to the step (negative = early):", "",
              "| chain_compensation | bandwidth [Hz] | x [ms] | y [ms] | z [ms] |", "|---|---:|---:|---:|---:|"]
    for s in doc["step_check"]:
        bw = f"{s['bandwidth_hz']:g}" if s["mode"] == "equalise" else "-"
        lines.append(f"| {s['mode']} | {bw} | " + " | ".join(f"{1e3 * s[f'{ax}_half_step_s']:+.1f}" for ax in "xyz") + " |")
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
