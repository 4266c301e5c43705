#!/usr/bin/env python3
"""Dynamic calibration per channel on the simulated board, end to end (issues 9, 37). Not a test: it measures the
figures of docs/results/dynamic.md.

1. The paper's chain (Table 1: x 1.7, y/z 1.3 Hz, 20 ms) for ``--default-seeds`` seeds, then a sweep of
   ``--seeds`` chains whose x, y, z channels have random TIA cut-offs in 0.5-5 Hz and random pure delays in
   0-50 ms (``fbg_accel_sim.dynamic_run.random_channel_chain``, chain seed 1000 + seed; reference channel at
   1 Hz): the stepped-sine plan (config/excitation_plan_stepped_sine.yaml, 0.5-20 Hz, LDV on aux, protocol
   version 2) simulated at 500 Hz, decoded by the driver's ``StreamDecoder``; ``run_dynamic`` identifies
   each channel (cut-off, delay, standard uncertainties) and checks the axes it predicts.
2. Coverage: the share of (chain, channel) cases whose error is inside k = 2 stated standard uncertainties
   (the level the report states, about 95 %), for the cut-offs and the delays apart; required >= 90 %.
3. Seed Fig. 12 for every swept chain: a 3 Hz run (a frequency the fit did not use) at the ESP32's 100 Hz
   through ``DriverCore`` with chain_compensation none / delay / equalise (10 Hz); RMS difference to the
   reference over whole periods, and its cut against none.
4. Second-order stages added to the y channel's counts of one run (the paper's chain): the axis check's
   largest |z|, or the plausibility refusal.
5. The Bode plot (channels and axes) of the first swept chain.

Usage: ``.venv/bin/python bench/dynamic_calibration_check.py [--seeds 12] [--output DIR]`` (about 1 min on
2 cores); it writes to ``--output`` (default: a scratch folder under the system's temporary directory).
``--update-results`` writes the committed bench/results/dynamic_calibration.json, docs/results/dynamic.md and
docs/img/dynamic_bode_per_channel.png instead. Exit status 1 when a criterion of the summary fails.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import signal

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import output_paths  # noqa: E402
from machine_info import results_doc, write_results  # noqa: E402

from fbg_accel_calibration.bode_plot import plot_bode  # noqa: E402
from fbg_accel_calibration.chain_model import axis_response_along  # noqa: E402
from fbg_accel_calibration.dynamic_calibration import MISFIT_Z, DynamicCalibrationError, run_dynamic  # noqa: E402
from fbg_accel_calibration.dynamic_check import step_check  # noqa: E402
from fbg_accel_calibration.excitation_plan import ExcitationPlan  # noqa: E402
from fbg_accel_driver.driver_parameters import default_calibration_path  # noqa: E402
from fbg_accel_driver.thermal_model import ThermalCalibration  # noqa: E402
from fbg_accel_sim.dynamic_run import random_channel_chain, simulate_dynamic_run, simulated_tone_check  # noqa: E402
from fbg_accel_sim.sim_config import SimConfig  # noqa: E402

PLAN_FILE = ROOT / "config" / "excitation_plan_stepped_sine.yaml"
REFERENCE_CUTOFF_HZ = 1.0  # paper Table 1 (design value of the reference TIA; a slide run cannot see it)
COVERAGE_K = 2.0  # the stated level: k = 2 standard uncertainties
STAGES = ((25.0, 0.7), (30.0, 0.7), (40.0, 1.5), (50.0, 0.7), (8.0, 0.7))  # (f0 Hz, Q) added to the y channel
COMMITTED = (output_paths.COMMITTED / "dynamic_calibration.json", output_paths.RESULTS_PAGES / "dynamic.md",
             output_paths.RESULTS_PAGES.parent / "img" / "dynamic_bode_per_channel.png")


def identify(plan: ExcitationPlan, static: ThermalCalibration, seed: int, rate: float, fc: np.ndarray,
             delay: np.ndarray, overrides: dict | None) -> tuple[dict, object]:
    """One simulated run's per-channel identification against the truth ``fc`` (Hz), ``delay`` (s)."""
    rec, _, _ = simulate_dynamic_run(plan, rate_hz=rate, seed=seed, overrides=overrides)
    res = run_dynamic(rec, plan, static, reference_cutoff_hz=REFERENCE_CUTOFF_HZ)
    row: dict = {"seed": seed, "axis_check_max_abs_z": res.check.max_abs_z, "misfit": res.check.misfit}
    for j, ax in enumerate("xyz"):
        m = res.models[ax]
        row[ax] = {"cutoff_true_hz": float(fc[j]), "cutoff_hz": m.cutoff_hz, "u_cutoff_hz": m.u_cutoff_hz,
                   "cutoff_error_pct": 100.0 * (m.cutoff_hz / fc[j] - 1.0),
                   "cutoff_z": (m.cutoff_hz - fc[j]) / m.u_cutoff_hz,
                   "delay_true_ms": 1e3 * float(delay[j]), "delay_ms": 1e3 * m.delay_s, "u_delay_ms": 1e3 * m.u_delay_s,
                   "delay_error_ms": 1e3 * (m.delay_s - delay[j]), "delay_z": (m.delay_s - delay[j]) / m.u_delay_s,
                   "gain": m.gain}
    return row, res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=12, help="random per-channel chains in the sweep (>= 10)")
    ap.add_argument("--default-seeds", type=int, default=3, help="runs of the paper's chain")
    ap.add_argument("--rate", type=float, default=500.0, help="board rate of the calibration runs (Hz)")
    ap.add_argument("--output", type=Path, default=output_paths.scratch_dir() / "dynamic",
                    help="folder for the JSON, markdown and PNG (default: a scratch folder)")
    ap.add_argument("--update-results", action="store_true",
                    help="write the committed results (bench/results, docs/results/dynamic.md, docs/img) instead")
    args = ap.parse_args(argv)
    if args.update_results:
        out_json, out_md, out_png = COMMITTED
    else:
        out_json, out_md, out_png = (args.output / p.name for p in COMMITTED)

    plan = ExcitationPlan.load(PLAN_FILE)
    static = ThermalCalibration.load(default_calibration_path())
    cfg = SimConfig.default()
    fc_paper = np.asarray(cfg.get("electronics.tia_cutoff_hz"), float)[1:]
    delay_paper = np.full(3, cfg.scale("channel_delay") * float(cfg.get("effects.channel_delay.delay_s")))

    paper_rows, paper_first = [], None
    for seed in range(args.default_seeds):
        row, res = identify(plan, static, seed, args.rate, fc_paper, delay_paper, None)
        paper_rows.append(row)
        paper_first = paper_first or res
        print(f"paper chain, seed {seed}: " + _line(row), flush=True)
    assert paper_first is not None
    cal = ThermalCalibration.from_dict({**static.to_dict(), "dynamic": paper_first.dynamics.to_dict()})
    paper_tone = simulated_tone_check(plan.with_tone(3.0, 8.0, 14.0), cal, rate_hz=100.0, seed=100).as_dict()
    paper_steps = [step_check(cal, "delay", 100.0), step_check(cal, "equalise", 100.0, 10.0),
                   step_check(cal, "equalise", 100.0, 20.0)]

    sweep, first = [], None
    for seed in range(args.seeds):
        fc, delay, overrides = random_channel_chain(1000 + seed)
        row, res = identify(plan, static, seed, args.rate, fc, delay, overrides)
        cal = ThermalCalibration.from_dict({**static.to_dict(), "dynamic": res.dynamics.to_dict()})
        tone = simulated_tone_check(plan.with_tone(3.0, 8.0, 14.0), cal, rate_hz=100.0, seed=100 + seed,
                                    overrides=overrides)
        row["tone_check"] = tone.as_dict()
        sweep.append(row)
        first = first or (res, fc, delay)
        print(f"chain {1000 + seed}: " + _line(row) + "; equalise cut " +
              " / ".join(f"{v:.0f} %" for v in tone.reduction_pct["equalise"]), flush=True)

    stages = []
    rec, _, _ = simulate_dynamic_run(plan, rate_hz=args.rate, seed=3)
    for f0, q in STAGES:
        w0 = 2 * np.pi * f0
        b, a = signal.bilinear([w0**2], [1.0, w0 / q, w0**2], fs=args.rate)
        bad = rec.select(np.ones(len(rec), dtype=bool))
        y = bad.xyz[:, 1].copy()
        bad.xyz[:, 1] = signal.lfilter(b, a, y, zi=signal.lfilter_zi(b, a) * y[0])[0]
        try:
            r = run_dynamic(bad, plan, static, reference_cutoff_hz=REFERENCE_CUTOFF_HZ)
            stages.append({"f0_hz": f0, "q": q, "outcome": "misfit" if r.check.misfit else "not flagged",
                           "axis_check_max_abs_z": r.check.max_abs_z, "y_cutoff_hz": r.models["y"].cutoff_hz,
                           "y_delay_ms": 1e3 * r.models["y"].delay_s})
        except DynamicCalibrationError as exc:
            stages.append({"f0_hz": f0, "q": q, "outcome": "refused", "reason": str(exc).split(":")[1].strip()})
        print(f"second-order stage {f0:g} Hz Q {q:g} on y: {stages[-1]['outcome']}", flush=True)

    assert first is not None
    res, fc, delay = first
    chain = [res.models[ax] for ax in "xyz"]
    predicted = {ax: (lambda f, i=i: axis_response_along(res.m_static, chain, plan.direction, f)[..., i])
                 for i, ax in enumerate("xyz")}
    out_png.parent.mkdir(parents=True, exist_ok=True)
    plot_bode(res.channel_points, res.models, out_png, axis_points=res.points, axis_responses=predicted,
              title=f"Simulated chain 1000 ({', '.join(f'{v:.2f}' for v in fc)} Hz)")

    cases = [r[ax] for r in sweep for ax in "xyz"]
    summary = {
        "cases": len(cases),
        "max_abs_cutoff_error_pct": max(abs(c["cutoff_error_pct"]) for c in cases),
        "max_abs_delay_error_ms": max(abs(c["delay_error_ms"]) for c in cases),
        "coverage_k": COVERAGE_K,
        "cutoff_coverage": float(np.mean([abs(c["cutoff_z"]) <= COVERAGE_K for c in cases])),
        "delay_coverage": float(np.mean([abs(c["delay_z"]) <= COVERAGE_K for c in cases])),
        "cutoff_coverage_k1": float(np.mean([abs(c["cutoff_z"]) <= 1.0 for c in cases])),
        "delay_coverage_k1": float(np.mean([abs(c["delay_z"]) <= 1.0 for c in cases])),
        "max_axis_check_z": max(r["axis_check_max_abs_z"] for r in sweep),
        "misfits": sum(r["misfit"] for r in sweep),
        "min_equalise_cut_pct": min(min(r["tone_check"]["reduction_pct"]["equalise"]) for r in sweep),
    }
    # issue 37's "done when", measured here
    summary["criteria"] = {
        "every cut-off within 5 %": summary["max_abs_cutoff_error_pct"] < 5.0,
        "every delay within 1 ms": summary["max_abs_delay_error_ms"] < 1.0,
        f"coverage at k = {COVERAGE_K:g} >= 90 % (cut-offs and delays)":
            min(summary["cutoff_coverage"], summary["delay_coverage"]) >= 0.9,
        "no misfit on the swept chains": summary["misfits"] == 0,
        "second-order stages at 25-40 Hz flagged": all(st["outcome"] == "misfit" for st in stages
                                                       if 25.0 <= st["f0_hz"] <= 40.0),
        "equalise cuts the 3 Hz RMS error >= 80 % on every axis": summary["min_equalise_cut_pct"] >= 80.0,
    }
    doc = results_doc("dynamic_calibration_check.py", argv, "dynamic calibration per channel on the simulated board") | {
        "rate_hz": args.rate, "misfit_z": MISFIT_Z, "paper_chain": {"cutoff_hz": fc_paper, "delay_s": delay_paper},
        "paper_runs": paper_rows, "paper_tone_check": paper_tone, "paper_step_check": paper_steps,
        "sweep": sweep, "summary": summary, "second_order_stages": stages,
        "first_chain": res.as_dict()}
    write_results(out_json, doc, indent=1)
    out_md.parent.mkdir(parents=True, exist_ok=True)
    out_md.write_text(markdown(doc, res.report(), out_png.name))
    print(f"wrote {out_json}, {out_md}, {out_png}")
    print(f"summary: {summary}")
    return 0 if all(summary["criteria"].values()) else 1


def _line(row: dict) -> str:
    return "  ".join(f"{ax} fc {row[ax]['cutoff_hz']:.3f} Hz ({row[ax]['cutoff_error_pct']:+.1f} %), "
                     f"delay {row[ax]['delay_ms']:.2f} ms ({row[ax]['delay_error_ms']:+.2f})" for ax in "xyz") \
        + f"; axis check |z| {row['axis_check_max_abs_z']:.2f}"


def markdown(doc: dict, report: str, png: str) -> str:
    s = doc["summary"]
    lines = ["# Dynamic calibration per channel on the simulated board",
             "",
             f"Written by `{doc['command'].strip()}` on {doc['date_utc']} "
             f"({doc['machine'].get('cpu', '?')}, {doc['machine'].get('logical_cpus', '?')} cores). Data: the simulator "
             "(`config/sim_default.yaml`) running `config/excitation_plan_stepped_sine.yaml` at "
             f"{doc['rate_hz']:g} Hz, decoded by the driver's stream decoder, with the chain set per channel "
             "(`electronics.tia_cutoff_hz`, `effects.channel_delay.axis_channel_extra_s`). Method: "
             "[dynamic_calibration.md](../dynamic_calibration.md).",
             "",
             "## Summary",
             "",
             f"* {s['cases']} channels of {len(doc['sweep'])} random chains (cut-offs 0.5-5 Hz, delays 0-50 ms per "
             f"channel): largest cut-off error {s['max_abs_cutoff_error_pct']:.1f} %, largest delay error "
             f"{s['max_abs_delay_error_ms']:.2f} ms.",
             f"* Coverage at k = {s['coverage_k']:g}: the stated uncertainty covers the cut-off's error in "
             f"{100 * s['cutoff_coverage']:.0f} % and the delay's in {100 * s['delay_coverage']:.0f} % of the cases "
             f"(at k = 1: {100 * s['cutoff_coverage_k1']:.0f} % and {100 * s['delay_coverage_k1']:.0f} %: the "
             "uncertainties are conservative).",
             f"* Axis check: largest |z| {s['max_axis_check_z']:.2f} over the sweep (misfit beyond {doc['misfit_z']:g}); "
             f"{s['misfits']} false alarm(s).",
             f"* Seed Fig. 12 (3 Hz, not in the fit, 100 Hz through `DriverCore`): equalise cuts the RMS error by at "
             f"least {s['min_equalise_cut_pct']:.0f} % on every axis of every swept chain.",
             "",
             "Criteria (issue 37): " + "; ".join(f"{k}: {'yes' if v else 'NO'}" for k, v in s["criteria"].items()) + ".",
             "",
             "## The paper's chain (x 1.7, y/z 1.3 Hz, 20 ms)",
             "",
             "| seed | x fc [Hz] (error) | y fc [Hz] (error) | z fc [Hz] (error) | x / y / z delay [ms] | "
             "axis check max \\|z\\| |",
             "|---:|---:|---:|---:|---:|---:|"]
    for r in doc["paper_runs"]:
        lines.append(_row(r, str(r["seed"])))
    tone = doc["paper_tone_check"]
    lines += ["", f"Seed Fig. 12 with seed 0's calibration: {tone['f_hz']:g} Hz (not in the fit), {tone['periods']} whole "
              "periods at 100 Hz through `DriverCore`; RMS difference between the published acceleration (at its "
              "stamps) and the reference, mean removed:", "",
              "| chain_compensation | x [m/s^2] | y [m/s^2] | z [m/s^2] | cut x / y / z |", "|---|---:|---:|---:|---:|"]
    for mode, vals in tone["rms_mps2"].items():
        red = tone["reduction_pct"].get(mode)
        lines.append(f"| {mode} | " + " | ".join(f"{v:.3f}" for v in vals) + " | "
                     + (" / ".join(f"{v:.0f} %" for v in red) if red else "-") + " |")
    lines += ["", "A step on the reference's time line (100 Hz), through each channel's TIA stage and delay: when the "
              "published output crosses half of it, relative to the step (negative = early):", "",
              "| chain_compensation | bandwidth [Hz] | x [ms] | y [ms] | z [ms] |", "|---|---:|---:|---:|---:|"]
    for st in doc["paper_step_check"]:
        bw = f"{st['bandwidth_hz']:g}" if st["mode"] == "equalise" else "-"
        lines.append(f"| {st['mode']} | {bw} | " + " | ".join(f"{1e3 * st[f'{ax}_half_step_s']:+.1f}" for ax in "xyz")
                     + " |")
    lines += ["", "## Random per-channel chains", "",
              "Truth and result per channel (error, and in brackets in units of its stated standard uncertainty); "
              "the last columns are Seed Fig. 12's check: RMS error at 3 Hz (m/s^2) with none -> equalise, its cut, "
              "and the part of the equalised error at 3 Hz itself (the rest is noise, amplified by the equaliser's "
              "high-frequency gain bandwidth / fc: largest on the slowest channels).", "",
              "| chain | truth fc x / y / z [Hz] | truth delay x / y / z [ms] | fc error x / y / z [%] (z) | "
              "delay error x / y / z [ms] (z) | axis check max \\|z\\| | RMS none -> equalise x / y / z | cut | "
              "of it at 3 Hz |",
              "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in doc["sweep"]:
        t = r["tone_check"]
        lines.append(
            f"| {1000 + r['seed']} | " + " / ".join(f"{r[ax]['cutoff_true_hz']:.2f}" for ax in "xyz") + " | "
            + " / ".join(f"{r[ax]['delay_true_ms']:.1f}" for ax in "xyz") + " | "
            + " / ".join(f"{r[ax]['cutoff_error_pct']:+.1f} ({r[ax]['cutoff_z']:+.1f})" for ax in "xyz") + " | "
            + " / ".join(f"{r[ax]['delay_error_ms']:+.2f} ({r[ax]['delay_z']:+.1f})" for ax in "xyz") + " | "
            + f"{r['axis_check_max_abs_z']:.2f} | "
            + " / ".join(f"{a:.2f} -> {b:.2f}" for a, b in zip(t["rms_mps2"]["none"], t["rms_mps2"]["equalise"],
                                                                 strict=True)) + " | "
            + " / ".join(f"{v:.0f} %" for v in t["reduction_pct"]["equalise"]) + " | "
            + " / ".join(f"{v:.2f}" for v in t["tone_rms_mps2"]["equalise"]) + " |")
    lines += ["", "The `delay` mode (stamps only) on the same tones: cut "
              + ", ".join(f"{min(r['tone_check']['reduction_pct']['delay']):.0f}" for r in doc["sweep"])
              + " % (the smallest axis of each chain): one stamp shift cannot undo channels of different dynamics, "
              "and over-corrects tones above its limit (`ChainDynamics.delay_helps_below_hz`).",
              "", "## A stage the model cannot represent", "",
              "A second-order low-pass added to the y channel's counts of the paper's chain (seed 3):", "",
              "| f0 [Hz] | Q | outcome | axis check max \\|z\\| or reason |", "|---:|---:|---|---|"]
    for st in doc["second_order_stages"]:
        what = f"{st['axis_check_max_abs_z']:.1f}" if "axis_check_max_abs_z" in st else st["reason"]
        lines.append(f"| {st['f0_hz']:g} | {st['q']:g} | {st['outcome']} | {what} |")
    lines += ["", "A stage far above the plan's band (20 Hz) acts on it as a pure delay and is identified as one; "
              "one inside it is refused by the fit's plausibility limit (the model misses its points by more than "
              "10 standard uncertainties rms); between them the axis check flags it.",
              "", "## Chain 1000: channels and axes", "", f"![Bode plot](../img/{png})", "", "```", report, "```", ""]
    return "\n".join(lines)


def _row(r: dict, label: str) -> str:
    return (f"| {label} | " + " | ".join(
        f"{r[ax]['cutoff_hz']:.3f} +- {r[ax]['u_cutoff_hz']:.3f} ({r[ax]['cutoff_error_pct']:+.1f} %)" for ax in "xyz")
        + " | " + " / ".join(f"{r[ax]['delay_ms']:.2f}" for ax in "xyz") + f" | {r['axis_check_max_abs_z']:.2f} |")


if __name__ == "__main__":
    raise SystemExit(main())
