"""Produce ``config/calibration_sim.yaml``: the shipped calibration of the simulated sensor.

    python -m fbg_accel_sim.make_default_calibration [--output PATH] [--seed N] [--degree N]

It does what the paper's thermal calibration does (section 3.6.2 and 4.5), on the simulator:
the six-pose plan (z down/up, x down/up, y down/up) at the three chamber temperatures 16, 24 and
45 degC, each level starting in thermal equilibrium, then eq. 28 fitted by plain linear least
squares on the static samples (table at rest for at least ``--settle`` seconds, so the TIA
low-pass has settled), with the AHT10 reading as temperature, centred and scaled
(tau = (T - t_center_c) / t_scale_c) for conditioning. ``noise_sigma_mps2`` is the within-pose
standard deviation of the calibrated output (white noise at the board rate) and
``temperature_range_c`` the span of the temperatures the fit saw; ``noise_correlation`` the white +
first-order model of that noise fitted to the same visits (``fbg_accel_calibration.fit.noise_correlation``);
``reference_level`` the mean reference counts and temperature of those samples per chamber level (as ``fit``).
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
from pathlib import Path

import numpy as np

from fbg_accel_calibration.fit.thermal_fit import coefficients_to_model, design_matrix, solve_normal_equations
from fbg_accel_calibration.io.atomic_output import OutputError, atomic_path, check_outputs
from fbg_accel_calibration.io.recording import Recording
from fbg_accel_driver.thermal_model import ThermalCalibration, normalise

from .board_physics import simulate_recording
from .sim_config import SimConfig, config_dir

LEVELS_C = (16.0, 24.0, 45.0)  # paper 3.6.2 / 4.5


def calibration_runs(cfg: SimConfig, seed: int, levels_c=LEVELS_C, dwell_s: float = 30.0, move_s: float = 10.0,
                     repeat: int = 1) -> Recording:
    """Six-pose runs at each chamber level (dwell and move as config/pose_plan_six_position.yaml; the plan ``repeat``
    times in a run), concatenated."""
    parts = []
    for i, level in enumerate(levels_c):
        run_cfg = cfg.with_overrides({
            "scenario.poses.mode": "six_position", "scenario.poses.dwell_s": dwell_s, "scenario.poses.move_s": move_s,
            "scenario.poses.repeat": repeat, "scenario.temperature.initial_c": float(level),
            "scenario.temperature.profile": [], "scenario.duration_s": None, "thermal.initial_optics_c": None,
        })
        parts.append(simulate_recording(run_cfg, seed=seed + 1000 * i))
    rec = Recording.concatenate(parts)
    rec.metadata["truth"] = {k: np.concatenate([p.metadata["truth"][k] for p in parts]) for k in parts[0].metadata["truth"]}
    rec.metadata["sensor_id"] = parts[0].metadata["sensor_id"]
    return rec


def static_mask(rec: Recording, settle_s: float) -> np.ndarray:
    """Samples at rest on a pose for at least ``settle_s`` with a valid temperature."""
    tr = rec.metadata["truth"]
    return (rec.pose_id >= 0) & (tr["time_at_pose_s"] >= settle_s) & np.isfinite(rec.temp_c)


def fit_eq28(psi: np.ndarray, temp_c: np.ndarray, gref: np.ndarray, degree: int, t_center_c: float,
             t_scale_c: float) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of eq. 28 (G = A X) by the fit's own design and solver; returns M (n+1, 3, 3), b (n+1, 3)."""
    X = design_matrix(psi, (temp_c - t_center_c) / t_scale_c, degree)
    A, _ = solve_normal_equations(X.T @ X, X.T @ gref)
    return coefficients_to_model(A, degree)


def make_calibration(cfg: SimConfig | None = None, seed: int = 0, degree: int = 2, settle_s: float = 2.0) -> ThermalCalibration:
    cfg = cfg if cfg is not None else SimConfig.default()
    rec = calibration_runs(cfg, seed)
    m = static_mask(rec, settle_s)
    psi = normalise(rec.xyz[m], rec.ref[m])
    temp = rec.temp_c[m]
    lo, hi = float(np.min(temp)), float(np.max(temp))
    center, scale = 0.5 * (lo + hi), max(0.5 * (hi - lo), 1.0)
    M, b = fit_eq28(psi, temp, rec.gref_mps2[m], degree, center, scale)
    cal = ThermalCalibration(M=M, b=b, temperature_range_c=(np.floor(lo * 10) / 10, np.ceil(hi * 10) / 10),
                             sensor_id=str(rec.metadata.get("sensor_id", "sim")), t_center_c=center, t_scale_c=scale)
    resid = cal.base_acceleration(psi, temp) - rec.gref_mps2[m]
    visit = rec.metadata["truth"]["visit"][m] + 1000 * rec.run_id[m]
    within = resid.copy()
    for v in np.unique(visit):
        sel = visit == v
        within[sel] -= within[sel].mean(axis=0)
    cal.noise_sigma_mps2 = within.std(axis=0)
    from fbg_accel_calibration.fit.noise_correlation import estimate

    segments = [within[visit == v] for v in np.unique(visit)]
    corr = estimate(segments, float(np.median(np.diff(rec.t_s))))
    cal.noise_correlated_fraction, cal.noise_time_constant_s = corr.correlated_fraction, corr.time_constant_s
    runs = rec.run_id[m]
    cal.reference_level_temperature_c = np.array([temp[runs == r].mean() for r in np.unique(runs)])
    cal.reference_level_counts = np.array([rec.ref[m][runs == r].mean() for r in np.unique(runs)])
    cal.created = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    cal.fit = {
        "method": "plain least squares of paper eq. 28 on simulated six-pose data "
                  "(python -m fbg_accel_sim.make_default_calibration)",
        "source": f"board simulator, config {Path(cfg.source).name}, seed {seed}, chamber levels {list(LEVELS_C)} degC",
        "degree": degree, "samples": int(m.sum()), "settle_s": settle_s,
        "rmse_mps2": [float(v) for v in np.sqrt(np.mean(resid**2, axis=0))],
        "pose_mean_rmse_mps2": [float(v) for v in np.sqrt(np.mean((resid - within) ** 2, axis=0))],
    }
    return cal


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Fit the shipped calibration of the simulated sensor (paper eq. 28).")
    p.add_argument("--output", default=str(config_dir() / "calibration_sim.yaml"))
    p.add_argument("--config", help="simulator config (default config/sim_default.yaml)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--degree", type=int, default=2)
    p.add_argument("--settle", type=float, default=2.0, help="s at rest on a pose before samples are used")
    p.add_argument("--force", action="store_true", help="replace an existing --output (the shipped file included)")
    args = p.parse_args(argv)
    try:
        check_outputs([Path(args.output)], [args.config] if args.config else [], args.force)
    except OutputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    cfg = SimConfig.load(args.config) if args.config else SimConfig.default()
    cal = make_calibration(cfg, seed=args.seed, degree=args.degree, settle_s=args.settle)
    with atomic_path(args.output) as tmp:
        cal.save(tmp)
    print(f"wrote {args.output}: degree {cal.degree}, {cal.fit['samples']} samples, range {cal.temperature_range_c} degC, "
          f"rmse {np.round(cal.fit['rmse_mps2'], 4).tolist()} m/s^2, "
          f"noise sigma {np.round(cal.noise_sigma_mps2, 4).tolist()} m/s^2")
    return 0


if __name__ == "__main__":
    sys.exit(main())
