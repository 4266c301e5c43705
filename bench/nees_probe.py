"""Is the published ``linear_acceleration_covariance`` consistent with the actual error? (NEES per axis)

Not a test. Drives the pure ``DriverCore`` with the simulator's byte stream (host receive time = true sample
time + 2 ms for the last frame of each 0.1 s chunk) and compares each published ``imu/data_raw`` sample with
the simulator's truth, ``accel_true_mps2`` (specific force, sensor frame) at the sample's stamp (true time =
stamp - 2 ms, linearly interpolated). Per axis and case it reports

* mean NEES = mean(e^2 / sigma^2), sigma^2 the published variance (consistent: about 1; >> 1 overconfident);
* for the static samples (table at rest >= ``--settle`` s): the bias part (the error's mean per visit, squared,
  over sigma^2) and the noise part (the within-visit variance over sigma^2), which add up to the static NEES;
* the fraction of samples flagged (``temperature_out_of_range`` etc.): a large NEES without a flag is silent.

    .venv/bin/python bench/nees_probe.py --json bench/results/nees_probe.json      # all cases, about 1.5 min
    .venv/bin/python bench/nees_probe.py --case static_temps                     # one case; --list names them

``--calibration-seeds N`` checks the calibration's own uncertainty instead (``calibration_consistency``): for each of
N seeds a calibration campaign is simulated and fitted (six poses at 16 / 24 / 45 degC, ``fit_thermal`` with its
coefficient covariance), the driver core runs it on the twelve poses above at ``--calibration-temps``, and the mean
error of each static pose against the simulator's truth is normalised by the covariance of that mean, with and without
the calibration's terms as the driver publishes them with ``covariance_includes_calibration`` (J Sigma J^T and the slow
error, and for a slow error without its run-to-run part the allowance ``slow_error.UNSTATED_RUN_TO_RUN_SIGMA_MPS2``; NEES,
3 degrees of freedom; the mean of S seeds' NEES of one pose lies in [chi2_0.025(3S), chi2_0.975(3S)] / S when the
covariance is right; the result also gives the NEES with the file's stated terms only, without that allowance).
``--calibration-runs-per-level 2`` fits campaigns of two separate runs per level,
``--calibration-repeat-levels 24`` gives one level a second run, ``--calibration-levels 24`` makes a single-level
campaign (degree 0 in temperature). ``--calibration-carry-runs-per-level 2`` fits, for each seed, first an earlier
calibration of the same simulated sensor with two runs per level (on seed + 1000) and carries its run-to-run component
into the seed's campaign (``fit --run-to-run-from``), which then cannot identify its own. The result goes to the
scratch directory (``nees_<design>.json``), ``--json`` or, with ``--update-results``, to bench/results/ and the
design's table on docs/results/calibration_consistency.md.

    .venv/bin/python bench/nees_probe.py --calibration-seeds 20 --json /tmp/nees_calibration.json   # about 4 min

``bench/results/nees_probe_before.json`` is the same command run on the code before the reference-level check
(commit 2b70689 with this script and its calibration file, which has no ``reference_level``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine_info import machine
from output_paths import RESULTS_PAGES, add_update_results, results_dir

from fbg_accel_driver.chain_compensation import ChainDynamics
from fbg_accel_driver.driver_core import CoreConfig, DriverCore
from fbg_accel_driver.thermal_model import ThermalCalibration
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig

REPO = Path(__file__).resolve().parents[1]
HOST_DELAY_S = 0.002
CHUNK_S = 0.1
# the simulated chain's truth (config/sim_default.yaml: electronics.tia_cutoff_hz, effects.channel_delay)
SIM_DYNAMICS = ChainDynamics(cutoff_hz=(1.0, 1.7, 1.3, 1.3), delay_s=(0.02, 0.02, 0.02))
# six calibration poses and six oblique ones (psi, theta) in degrees
POSES = [[0.0, 180.0], [0.0, 0.0], [270.0, 90.0], [90.0, 90.0], [180.0, 90.0], [0.0, 90.0],
         [30.0, 45.0], [120.0, 135.0], [210.0, 60.0], [300.0, 120.0], [45.0, 30.0], [160.0, 250.0]]


def pose_plan(temp_c: float, dwell_s: float = 20.0, move_s: float = 5.0, poses: list | None = None) -> dict[str, Any]:
    """Simulator overrides: ``poses`` (default POSES) once at a constant chamber temperature ``temp_c`` (degC)."""
    return {"scenario.poses.mode": "list", "scenario.poses.list": poses or POSES, "scenario.poses.dwell_s": dwell_s,
            "scenario.poses.move_s": move_s, "scenario.poses.repeat": 1, "scenario.temperature.initial_c": temp_c}


def run_case(overrides: dict[str, Any], cal: ThermalCalibration, core_cfg: CoreConfig, seed: int = 5,
             duration_s: float | None = None) -> dict[str, np.ndarray]:
    """Simulate, feed the driver core, return published samples with their truth (arrays over samples)."""
    cfg = SimConfig.default().with_overrides(overrides)
    sim = BoardSimulator(cfg, seed=seed)
    n = sim.samples_for(duration_s if duration_s is not None else sim.duration_s)
    blk = sim.step(n)
    pieces = blk.wire_pieces()
    t_true = blk.t_s
    core = DriverCore(cal, core_cfg)
    step = max(1, round(CHUNK_S * sim.rate_hz))
    recs = []
    for k in range(0, n, step):
        last = min(k + step, n) - 1
        out = core.feed(b"".join(pieces[k:last + 1]), round(float(t_true[last] + HOST_DELAY_S) * 1e9))
        recs += out.imu
    recs += core.flush().imu
    stamp_s = np.array([r.stamp_ns for r in recs]) * 1e-9 - HOST_DELAY_S
    acc = np.array([r.accel_mps2 for r in recs])
    var = np.array([(r.covariance[0], r.covariance[4], r.covariance[8]) for r in recs])
    truth = np.stack([np.interp(stamp_s, t_true, blk.accel_true_mps2[:, j]) for j in range(3)], axis=1)
    idx = np.clip(np.searchsorted(t_true, stamp_s), 0, n - 1)
    # static: the table has been at rest for `settle` s at the stamp (and the whole decimation window)
    cov = np.array([r.covariance for r in recs]).reshape(-1, 3, 3)
    return {"t": stamp_s, "acc": acc, "var": var, "cov": cov, "truth": truth, "err": acc - truth,
            "time_at_pose": blk.time_at_pose_s[idx], "visit": np.where(blk.pose_id[idx] >= 0, blk.visit[idx], -1),
            "moving": blk.in_motion[idx], "temp": np.array([r.temperature_c for r in recs]),
            "flagged": np.array([bool(r.flags) for r in recs]),
            "flags": [sorted(r.flags) for r in recs]}


def summarise(res: dict[str, np.ndarray], settle_s: float, window_s: float = 0.0) -> dict[str, Any]:
    """NEES per axis: all samples, static ones (bias and noise parts), moving ones; flags."""
    e, v = res["err"], res["var"]
    ok = np.all(v > 0, axis=1)
    nees = np.where(ok[:, None], e**2 / np.where(v > 0, v, 1.0), np.nan)
    static = ok & (res["time_at_pose"] >= settle_s + window_s) & (res["visit"] >= 0)
    moving = ok & ~static
    out: dict[str, Any] = {"samples": len(e), "flagged_fraction": round(float(res["flagged"].mean()), 4)
                           if len(e) else math.nan,
                           "sigma_published_mps2": np.round(np.sqrt(np.median(v, axis=0)), 4).tolist(),
                           "mean_nees_all": np.round(np.nanmean(nees, axis=0), 2).tolist()}
    if static.any():
        bias2 = np.zeros(3)
        within = np.zeros(3)
        vis = res["visit"][static]
        es, vs = e[static], v[static]
        biases = []
        for u in np.unique(vis):
            sel = vis == u
            m = es[sel].mean(axis=0)
            biases.append(m)
            bias2 += (m**2 / vs[sel].mean(axis=0)) * sel.sum()
            within += (((es[sel] - m) ** 2) / vs[sel]).sum(axis=0)
        ns = static.sum()
        out.update({"static_samples": int(ns), "static_flagged_fraction": round(float(res["flagged"][static].mean()), 4),
                    "mean_nees_static": np.round(np.nanmean(nees[static], axis=0), 2).tolist(),
                    "static_bias_part": np.round(bias2 / ns, 2).tolist(),
                    "static_noise_part": np.round(within / ns, 2).tolist(),
                    "rms_bias_mps2": np.round(np.sqrt(np.mean(np.square(biases), axis=0)), 4).tolist(),
                    "max_abs_bias_mps2": np.round(np.max(np.abs(biases), axis=0), 4).tolist()})
    if moving.any():
        nm = nees[moving]
        out.update({"moving_samples": int(moving.sum()),
                    "moving_flagged_fraction": round(float(res["flagged"][moving].mean()), 4),
                    "mean_nees_moving": np.round(np.nanmean(nm, axis=0), 2).tolist(),
                    "p99_nees_moving": np.round(np.nanpercentile(nm, 99, axis=0), 1).tolist(),
                    "max_abs_err_moving_mps2": np.round(np.nanmax(np.abs(e[moving]), axis=0), 3).tolist()})
    return out


def shipped_calibration(dynamic: bool = False) -> ThermalCalibration:
    cal = ThermalCalibration.load(REPO / "config" / "calibration_sim.yaml")
    return dataclasses.replace(cal, dynamic=SIM_DYNAMICS) if dynamic else cal


def fitted_calibration(seed: int, degree: int = 2, settle_s: float = 2.0, repeat: int = 3,
                       overrides: dict[str, Any] | None = None, runs_per_level: int = 1,
                      repeat_levels: list[float] | None = None, levels: list[float] | None = None,
                       carried: Any = None) -> ThermalCalibration:
    """A calibration fitted as ``fbg-accel-calib fit`` does (eq. 28 with its coefficient covariance, the noise model and
    its within-visit correction, the slow error) on the simulator's six-pose campaign at 16 / 24 / 45 degC of ``seed``, with the
    static samples (at rest ``settle_s``) given by the simulator's truth; the six poses visited ``repeat`` times per
    level, so that the covariance rests on 18 ``repeat`` visits (with one, 18 visits for 12 coefficients per axis leave
    6 degrees of freedom: the estimate is then so uncertain itself that a normalised error's mean is 3 x 6 / (6 - 4) =
    9, not 3, although unbiased, Hotelling's T^2). ``runs_per_level`` > 1: that many separate runs (sessions, each with
    its own state of the slow processes) at each level, so that a wander constant over a run is not absorbed by b(T);
    ``repeat_levels``: levels (degC, of 16 / 24 / 45) given one more run each (the cheapest design that identifies
    the run-to-run part of the slow error); ``levels``: the campaign's levels (degC, default 16 / 24 / 45; the degree is
    then at most one less than their number); ``carried`` (``slow_error.CarriedRunToRun``): the run-to-run component of
    an earlier calibration, used when this campaign does not identify its own."""
    from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
    from fbg_accel_calibration.fit.fit_stream import prepare
    from fbg_accel_calibration.fit.noise_correlation import from_recording, within_visit_factor
    from fbg_accel_calibration.fit.slow_error import attach as attach_slow_error
    from fbg_accel_calibration.io.recording import Recording
    from fbg_accel_sim.make_default_calibration import LEVELS_C, calibration_runs, static_mask

    cfg = SimConfig.default().with_overrides(overrides or {})
    lv = tuple(levels) if levels else LEVELS_C
    degree = min(degree, len(lv) - 1)
    parts = [calibration_runs(cfg, seed + 500 * k, levels_c=lv, repeat=repeat) for k in range(runs_per_level)]
    if repeat_levels:
        parts.append(calibration_runs(cfg, seed + 500 * runs_per_level, levels_c=tuple(repeat_levels), repeat=repeat))
    rec = parts[0] if len(parts) == 1 else Recording.concatenate(parts)
    if len(parts) > 1:
        rec.metadata["truth"] = {k: np.concatenate([p.metadata["truth"][k] for p in parts]) for k in parts[0].metadata["truth"]}
        rec.metadata["sensor_id"] = parts[0].metadata["sensor_id"]
    data = prepare(rec, degree, usable=static_mask(rec, settle_s))
    cal = fit_thermal(data, degree)
    corr = from_recording(rec.select(rec.run_id == rec.run_id[0]), cal)
    cal.noise_correlated_fraction, cal.noise_time_constant_s = corr.correlated_fraction, corr.time_constant_s
    cal.noise_sigma_mps2 = cal.noise_sigma_mps2 / np.sqrt(within_visit_factor(corr, corr.dt_s, data.stats.visit_lengths))
    attach_slow_error(cal, data.stats, corr.dt_s, carried)  # the slow error, as fit_pipeline.fit_files writes it
    return cal


def pose_means(res: dict[str, np.ndarray], settle_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per static visit (at rest >= ``settle_s``): mean error (V, 3) m/s^2, the covariance of that mean from the noise
    (V, 3, 3; the published variance times the noise model's factor for a mean of n samples) and the calibration's
    part (V, 3, 3; the covariance published with it, ``cov_with``, less the one without, averaged over the visit: the
    same bias for every sample)."""
    from fbg_accel_driver.noise_model import mean_variance_factor

    cal = res["cal"]
    static = (res["time_at_pose"] >= settle_s) & (res["visit"] >= 0)
    dt = float(np.median(np.diff(res["t"])))
    errs, noise, calib = [], [], []
    for v in np.unique(res["visit"][static]):
        sel = static & (res["visit"] == v)
        n = int(sel.sum())
        errs.append(res["err"][sel].mean(axis=0))
        f = [mean_variance_factor(n, float(cal.noise_correlated_fraction[a]), float(cal.noise_time_constant_s[a]), dt)
             for a in range(3)]
        noise.append(np.diag(res["var"][sel].mean(axis=0) * np.array(f)))
        calib.append((res["cov_with"][sel] - res["cov"][sel]).mean(axis=0))
    return np.array(errs), np.array(noise), np.array(calib)


def calibration_consistency(seeds: int, temps: list[float], settle_s: float, first_seed: int = 100,
                            effects_off: list[str] | None = None, runs_per_level: int = 1,
                            repeat_levels: list[float] | None = None, levels: list[float] | None = None,
                            carry_runs_per_level: int = 0, allowance_scan: tuple[float, ...] = ()) -> dict[str, Any]:
    """NEES of the static pose means with and without the calibration's uncertainty over ``seeds`` fitted
    calibrations (module docstring); ``effects_off``: simulator effects switched off (``effects.<name>.scale`` 0) in the
    campaign and in the check; ``carry_runs_per_level`` > 0: each seed's calibration carries the run-to-run component
    of an earlier one with that many runs per level (seed + 1000); ``allowance_scan``: allowances (m/s^2, 1 sigma per
    axis) for the unstated run-to-run part in place of ``slow_error.UNSTATED_RUN_TO_RUN_SIGMA_MPS2``, each giving the mean
    NEES of the same pose means (where the calibrations lack R; a sensitivity, not a choice)."""
    from scipy.stats import chi2

    from fbg_accel_calibration.fit.slow_error import CarriedRunToRun

    over = {f"effects.{e}.scale": 0.0 for e in effects_off or []}
    nees_with: dict[str, list[np.ndarray]] = {f"{t:g}": [] for t in temps}
    # with the file's stated terms only: without the allowance for a run-to-run part the file does not state
    nees_stated: dict[str, list[np.ndarray]] = {f"{t:g}": [] for t in temps}
    allowances: list[float] = []
    # per axis, e_i^2 / C_ii with the published terms (1 when the axis' variance is right)
    per_axis: dict[str, list[np.ndarray]] = {f"{t:g}": [] for t in temps}
    # the same pose means normalised with other (isotropic) allowances in place of the one applied: a sensitivity
    scan: dict[str, dict[float, list[np.ndarray]]] = {f"{t:g}": {a: [] for a in allowance_scan} for t in temps}
    nees_without: dict[str, list[np.ndarray]] = {f"{t:g}": [] for t in temps}
    sigma_cal: dict[str, list[np.ndarray]] = {f"{t:g}": [] for t in temps}
    for s in range(first_seed, first_seed + seeds):
        carried = None
        if carry_runs_per_level:
            earlier = fitted_calibration(s + 1000, overrides=over, runs_per_level=carry_runs_per_level, levels=levels)
            if earlier.slow_error is None or earlier.slow_error.run_to_run is None:
                raise SystemExit(f"seed {s + 1000}: the earlier campaign did not identify its run-to-run component")
            carried = CarriedRunToRun(earlier.slow_error.run_to_run, earlier.sensor_id, f"seed {s + 1000}")
        cal = fitted_calibration(s, overrides=over, runs_per_level=runs_per_level, repeat_levels=repeat_levels,
                                 levels=levels, carried=carried)
        allow = 0.0 if cal.slow_error is None else cal.slow_error.unstated_run_to_run_sigma_mps2
        allowances.append(allow)
        for t in temps:
            res = run_case({**pose_plan(t), **over}, cal, CoreConfig(), seed=s + 7919)
            res["cov_with"] = run_case({**pose_plan(t), **over}, cal, CoreConfig(covariance_includes_calibration=True),
                                       seed=s + 7919)["cov"]
            res["cal"] = cal
            e, cn, cc = pose_means(res, settle_s)
            nees_with[f"{t:g}"].append(np.einsum("vi,vij,vj->v", e, np.linalg.inv(cn + cc), e))
            per_axis[f"{t:g}"].append(e**2 / np.einsum("vii->vi", cn + cc))
            nees_stated[f"{t:g}"].append(np.einsum("vi,vij,vj->v", e, np.linalg.inv(cn + cc - allow**2 * np.eye(3)), e))
            for a in allowance_scan:
                c = cn + cc + (a**2 - allow**2) * np.eye(3) if allow else cn + cc
                scan[f"{t:g}"][a].append(np.einsum("vi,vij,vj->v", e, np.linalg.inv(c), e))
            nees_without[f"{t:g}"].append(np.einsum("vi,vij,vj->v", e, np.linalg.inv(cn), e))
            sigma_cal[f"{t:g}"].append(np.sqrt(np.einsum("vii->vi", cc)))
            print(f"seed {s} T={t:g}: mean NEES with {nees_with[f'{t:g}'][-1].mean():.2f}, without "
                  f"{nees_without[f'{t:g}'][-1].mean():.1f}", flush=True)
    lo, hi = chi2.ppf(0.025, 3 * seeds) / seeds, chi2.ppf(0.975, 3 * seeds) / seeds
    out: dict[str, Any] = {"seeds": seeds, "first_seed": first_seed, "settle_s": settle_s, "dof": 3,
                           "effects_off": effects_off or [], "campaign_runs_per_level": runs_per_level,
                           "campaign_repeated_levels_c": repeat_levels or [],
                           "run_to_run_carried_from_runs_per_level": carry_runs_per_level,
                           "campaign_levels_c": levels or [16.0, 24.0, 45.0],
                           "band_95_of_mean_over_seeds": [round(lo, 3), round(hi, 3)],
                           # slow_error.UNSTATED_RUN_TO_RUN_SIGMA_MPS2 where a calibration's slow error lacks R, else 0
                           "unstated_run_to_run_allowance_mps2": sorted(set(allowances)),
                           "poses": [f"psi={p[0]:g} theta={p[1]:g}" for p in POSES], "temperatures": {}}
    for key in nees_with:
        w, wo = np.array(nees_with[key]), np.array(nees_without[key])  # (seeds, poses)
        mw, mwo = w.mean(axis=0), wo.mean(axis=0)
        out["temperatures"][key] = {
            "mean_nees_per_pose_with": np.round(mw, 2).tolist(),
            "mean_nees_per_pose_without": np.round(mwo, 1).tolist(),
            "poses_in_band_with": int(((mw >= lo) & (mw <= hi)).sum()),
            "poses_in_band_without": int(((mwo >= lo) & (mwo <= hi)).sum()),
            "poses_above_band_with": int((mw > hi).sum()),
            "mean_nees_all_with": round(float(w.mean()), 3), "mean_nees_all_without": round(float(wo.mean()), 2),
            "fraction_below_chi2_95_with": round(float((w < chi2.ppf(0.95, 3)).mean()), 3),
            "fraction_below_chi2_95_without": round(float((wo < chi2.ppf(0.95, 3)).mean()), 3),
            "mean_nees_all_with_stated_only": round(float(np.mean(nees_stated[key])), 3),
            "mean_normalised_square_per_axis_with": np.round(np.concatenate(per_axis[key]).mean(axis=0), 3).tolist(),
            "fraction_below_chi2_95_with_stated_only": round(float((np.array(nees_stated[key]) < chi2.ppf(0.95, 3)).mean()), 3),
            "median_sigma_calibration_mps2": np.round(np.median(np.concatenate(sigma_cal[key]), axis=0), 4).tolist()}
        if allowance_scan and any(allowances):
            out["temperatures"][key]["allowance_scan"] = {
                f"{a:g}": {"mean_nees": round(float(np.mean(scan[key][a])), 3),
                           "fraction_below_chi2_95": round(float((np.array(scan[key][a]) < chi2.ppf(0.95, 3)).mean()), 3)}
                for a in allowance_scan}
    return out


def design_tag(out: dict[str, Any]) -> str:
    """A name for the campaign design and simulator of a ``calibration_consistency`` result (file and page marker)."""
    levels = out["campaign_levels_c"]
    tag = "levels_" + "_".join(f"{v:g}" for v in levels) if levels != [16.0, 24.0, 45.0] else "paper_levels"
    tag += f"_runs{out['campaign_runs_per_level']}"
    if out["campaign_repeated_levels_c"]:
        tag += "_repeat_" + "_".join(f"{v:g}" for v in out["campaign_repeated_levels_c"])
    if out.get("run_to_run_carried_from_runs_per_level"):
        tag += f"_carried_from_runs{out['run_to_run_carried_from_runs_per_level']}"
    return tag + ("_effects_off" if out["effects_off"] else "")


def table_markdown(out: dict[str, Any]) -> str:
    """The results page's table of a ``calibration_consistency`` result."""
    lo, hi = out["band_95_of_mean_over_seeds"]
    allow = [a for a in out.get("unstated_run_to_run_allowance_mps2", []) if a]
    note = ""
    if allow:
        stated = "; ".join(f"{t} °C {r['mean_nees_all_with_stated_only']:.2f}, "
                           f"{r['fraction_below_chi2_95_with_stated_only']:.0%} below χ²₀.₉₅(3)"
                           for t, r in out["temperatures"].items())
        note = (f"; *with* includes the allowance for the run-to-run part the files do not state, "
                f"{', '.join(f'{a:g}' for a in allow)} m/s² per axis (with the stated terms only: {stated})")
    rows = [f"{out['seeds']} seeds; band of a right covariance for the mean over seeds [{lo:.2f}, {hi:.2f}]{note}", "",
            "| chamber °C | mean NEES with / without | poses in band with / without (of 12) | within χ²₀.₉₅(3) with / "
            "without | median σ of the calibration terms x / y / z [m/s²] |", "|---|---|---|---|---|"]
    for t, r in out["temperatures"].items():
        sig = " / ".join(f"{v:.4f}" for v in r["median_sigma_calibration_mps2"])
        rows.append(f"| {t} | {r['mean_nees_all_with']:.2f} / {r['mean_nees_all_without']:.2f} | "
                    f"{r['poses_in_band_with']} / {r['poses_in_band_without']} | "
                    f"{r['fraction_below_chi2_95_with']:.0%} / {r['fraction_below_chi2_95_without']:.0%} | {sig} |")
    return "\n".join(rows)


def update_page(out: dict[str, Any], page: Path) -> bool:
    """Replace the table between ``<!-- nees TAG -->`` and ``<!-- /nees TAG -->`` on the results page; False when the
    page has no such markers (the table is then only printed)."""
    tag = design_tag(out)
    text = page.read_text(encoding="utf-8")
    start, end = f"<!-- nees {tag} -->", f"<!-- /nees {tag} -->"
    if start not in text or end not in text:
        return False
    head, rest = text.split(start, 1)
    page.write_text(head + start + "\n" + table_markdown(out) + "\n" + end + rest.split(end, 1)[1], encoding="utf-8")
    return True


def cases() -> dict[str, list[tuple[str, dict[str, Any], dict[str, Any], float | None]]]:
    """name -> [(label, sim overrides, CoreConfig fields, duration)]."""
    temps = [10.0, 13.0, 15.0, 16.0, 20.0, 24.0, 30.0, 38.0, 45.0, 45.3, 47.0, 50.0]
    return {
        "static_temps": [(f"T={t}", pose_plan(t), {}, None) for t in temps],
        "chain": [(f"{m} N={n}", pose_plan(24.0), {"chain_compensation": m, "decimation": n}, None)
                  for m in ("none", "delay", "equalise") for n in (1, 10)],
        "decimation": [(f"T={t} N={n}", pose_plan(t, dwell_s=60.0), {"decimation": n}, None)
                       for t in (24.0, 45.0) for n in (1, 10, 100)],
        "rates": [(f"{r} Hz", {**pose_plan(24.0), "scenario.rate_hz": r}, {}, None) for r in (10.0, 100.0, 1000.0)],
        "source_power": [(f"source x{lv}", {**pose_plan(24.0), "faults.source_dropout.windows": [
            {"start_s": 0.0, "duration_s": 1e6, "level": lv}]}, {}, None) for lv in (1.0, 0.97, 0.9, 0.8, 0.7, 0.5, 0.3)],
        "ramp": [("16->45 degC in 30 min", {**pose_plan(16.0, dwell_s=60.0, poses=POSES * 3),
                                           "scenario.temperature.profile": [{"ramp_to_c": 45.0, "duration_s": 1800.0}]},
                  {}, None)],
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--case", action="append", help="case name (repeatable); default all")
    p.add_argument("--settle", type=float, default=2.0, help="s at rest before a sample counts as static")
    p.add_argument("--seed", type=int, default=5)
    p.add_argument("--json", help="write the results here")
    p.add_argument("--list", action="store_true")
    p.add_argument("--calibration-seeds", type=int, default=0,
                   help="check the calibration's uncertainty on this many fitted calibrations instead (>= 20)")
    p.add_argument("--calibration-effects-off", nargs="*", default=[],
                   help="simulator effects switched off for the check (config/sim_default.yaml effects), e.g. bias_instability")
    p.add_argument("--calibration-runs-per-level", type=int, default=1,
                   help="separate campaign runs (sessions) per temperature level; default 1")
    p.add_argument("--calibration-repeat-levels", type=float, nargs="*", default=[],
                   help="campaign levels (degC, of 16 24 45) given one more run each, e.g. 24")
    p.add_argument("--calibration-carry-runs-per-level", type=int, default=0,
                   help="carry the run-to-run component of an earlier calibration (seed + 1000) with this many runs per "
                        "level into each seed's (fit --run-to-run-from); default 0: none")
    p.add_argument("--calibration-levels", type=float, nargs="+", default=None,
                   help="the campaign's levels (degC; default 16 24 45; one level: degree 0 in temperature)")
    p.add_argument("--calibration-allowance-scan", type=float, nargs="*", default=[],
                   help="allowances (m/s^2 per axis) for a run-to-run part the files do not state, in place of "
                        "slow_error.UNSTATED_RUN_TO_RUN_SIGMA_MPS2: the same pose means' NEES with each (a sensitivity)")
    p.add_argument("--calibration-temps", type=float, nargs="+", default=[24.0, 45.0, 52.0],
                   help="chamber temperatures (degC) of the check; the campaign's are 16, 24, 45")
    add_update_results(p)
    args = p.parse_args(argv)
    if args.calibration_seeds:
        out = calibration_consistency(args.calibration_seeds, args.calibration_temps, args.settle,
                                      effects_off=args.calibration_effects_off,
                                      runs_per_level=args.calibration_runs_per_level,
                                      repeat_levels=args.calibration_repeat_levels,
                                      levels=args.calibration_levels,
                                      carry_runs_per_level=args.calibration_carry_runs_per_level,
                                      allowance_scan=tuple(args.calibration_allowance_scan))
        out["command"] = "python bench/nees_probe.py " + " ".join(argv if argv is not None else sys.argv[1:])
        out["machine"] = machine()
        print(json.dumps(out, indent=1))
        path = Path(args.json) if args.json else results_dir(args.update_results) / f"nees_{design_tag(out)}.json"
        path.write_text(json.dumps(out, indent=1) + "\n")
        print(table_markdown(out))
        if args.update_results:
            page = RESULTS_PAGES / "calibration_consistency.md"
            print(f"{page}: {'table updated' if update_page(out, page) else 'no markers for ' + design_tag(out)}")
        print(f"wrote {path}")
        return 0
    all_cases = cases()
    if args.list:
        print("\n".join(all_cases))
        return 0
    results: dict[str, Any] = {}
    for name in args.case or list(all_cases):
        results[name] = {}
        for label, over, core_fields, dur in all_cases[name]:
            mode = core_fields.get("chain_compensation", "none")
            cal = shipped_calibration(dynamic=mode != "none")
            res = run_case(over, cal, CoreConfig(**core_fields), seed=args.seed, duration_s=dur)
            rate = float(over.get("scenario.rate_hz", 100.0))
            window = core_fields.get("decimation", 1) / rate
            s = summarise(res, args.settle, window)
            results[name][label] = s
            print(f"{name:13s} {label:24s} {json.dumps(s)}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
