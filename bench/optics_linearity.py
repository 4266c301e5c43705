"""Spectral-overlap non-linearity of the simulated sensor: where the numbers in docs/simulator.md come from.

Not a test (test/test_sim_physics.py asserts the per-axis figures). Writes
bench/results/optics_linearity.json and .md with

* ``report``: ``fbg_accel_sim.optics.linearity_report`` of config/sim_default.yaml (paper 3.4 metric
  over +-180 m/s^2 and +-20 g, slope and curvature at rest, monotonicity, crossing);
* ``report_gaussian``: the same for the former all-Gaussian gratings (order 1, FWHM 2.896 / 3.412 / 3.326 nm);
* ``curvature_1g``: the curvature of the response at rest within +-1 g, as the quadratic share of the 1 g
  response (%), estimated the same way from (a) the measured multi-position run
  (../shared/data/measured/fig13_multiposition_23C.csv; skipped with a message when absent) with a
  pose-bootstrap standard error, and (b) noise-free simulated runs of the same 30-degree grid with each
  grating set (a check that the estimator recovers the model's own value);
* ``calibrated_static_error``: mean error (m/s^2) of config/calibration_sim.yaml on 30 s static runs of the
  default config (23.4 degC, seed 3) at a few poses: what the linear-in-Psi calibration leaves of the
  spectral non-linearity (plus the run-to-run bias of the noise).

    .venv/bin/python bench/optics_linearity.py
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from output_paths import output_dir_from_command_line

from fbg_accel_calibration.io.table_geometry import table_specific_force
from fbg_accel_driver.thermal_model import ThermalCalibration
from fbg_accel_sim import optics
from fbg_accel_sim.board_physics import SimConfig, simulate_recording
from fbg_accel_sim.sim_config import config_dir

ROOT = Path(__file__).resolve().parents[1]
MEASURED = ROOT.parent / "shared" / "data" / "measured" / "fig13_multiposition_23C.csv"
GAUSSIAN = {"optics.grating_super_gaussian_order": [1.0, 1.0, 1.0], "optics.grating_fwhm_nm": [2.896, 3.412, 3.326]}
G = optics.STANDARD_G


def curvature_share_1g(f: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """Quadratic share (%) of the 1 g response of each channel, from static samples on a sphere of |f| = g.

    Fits Psi_i = c0 + g.f + f^T Q f; on a sphere only the anisotropic part of Q is identifiable, so the
    curvature along the channel's sensing direction n = g/|g| is n^T Q n minus the mean of Q across n.
    Returned: 100 * curvature * g^2 / (|g| g), i.e. the quadratic term at 1 g over the linear one.
    """
    x1 = np.c_[np.ones(len(f)), f]
    fx, fy, fz = f.T
    quad = np.c_[fx**2 - fz**2, fy**2 - fz**2, fx * fy, fx * fz, fy * fz]
    x2 = np.c_[x1, quad]
    out = []
    for j in range(psi.shape[1]):
        b1 = np.linalg.lstsq(x1, psi[:, j], rcond=None)[0]
        b2 = np.linalg.lstsq(x2, psi[:, j], rcond=None)[0]
        n = b1[1:] / np.linalg.norm(b1[1:])
        q = np.array([[b2[4], b2[6] / 2, b2[7] / 2], [b2[6] / 2, b2[5], b2[8] / 2], [b2[7] / 2, b2[8] / 2, -b2[4] - b2[5]]])
        c2 = n @ q @ n - (np.trace(q) - n @ q @ n) / 2.0
        out.append(100.0 * c2 * G * G / (np.linalg.norm(b1[1:]) * G))
    return np.array(out)


def measured_curvature() -> dict:
    if not MEASURED.is_file():
        msg = f"measured data not found: {MEASURED} (the shared directory ../shared is not next to the repository)"
        print(msg, file=sys.stderr)
        return {"error": msg}
    d = np.genfromtxt(MEASURED, delimiter=",", names=True)
    psi_deg, th_deg = d["psi_deg"], d["theta_deg"]
    static = (np.abs(psi_deg / 30 - np.round(psi_deg / 30)) < 1e-6) & (np.abs(th_deg / 30 - np.round(th_deg / 30)) < 1e-6)
    f = table_specific_force(psi_deg[static], th_deg[static], G)
    psi = np.c_[d["x_counts"], d["y_counts"], d["z_counts"]][static] / d["ref_counts"][static][:, None]
    est = curvature_share_1g(f, psi)
    # pose bootstrap: resample whole pose visits (runs of consecutive static samples at one pose)
    idx = np.flatnonzero(static)
    starts = np.flatnonzero(np.r_[True, (np.diff(idx) != 1) | (np.diff(psi_deg[idx]) != 0) | (np.diff(th_deg[idx]) != 0)])
    blocks = np.split(np.arange(len(idx)), starts[1:])
    rng = np.random.default_rng(0)
    boots = []
    for _ in range(300):
        pick = np.concatenate([blocks[i] for i in rng.integers(0, len(blocks), len(blocks))])
        boots.append(curvature_share_1g(f[pick], psi[pick]))
    return {"csv": str(MEASURED), "static_samples": int(static.sum()), "pose_visits": len(blocks),
            "curvature_share_1g_pct": est.tolist(), "bootstrap_se_pct": np.std(boots, axis=0).tolist()}


def simulated_curvature(overrides: dict) -> list[float]:
    quiet = {"scenario.poses.mode": "grid", "scenario.poses.dwell_s": 3.0, "scenario.poses.move_s": 1.0,
             "effects.white_noise.scale": 0.0, "effects.bias_instability.scale": 0.0, "effects.source_power_wander.scale": 0.0,
             "effects.time_drift.scale": 0.0, "effects.adc_quantisation.scale": 0.0}
    rec = simulate_recording(SimConfig.default().with_overrides({**quiet, **overrides}), seed=0)
    m = (rec.pose_id >= 0) & (rec.metadata["truth"]["time_at_pose_s"] > 2.0)
    return curvature_share_1g(rec.gref_mps2[m], rec.xyz[m] / rec.ref[m][:, None]).tolist()


POSES = {"z up": (0.0, 0.0), "x horizontal, theta 90": (0.0, 90.0), "oblique psi 45 theta 45": (45.0, 45.0),
         "oblique psi 135 theta 125": (135.0, 125.0)}


def calibrated_static_error() -> dict:
    cal = ThermalCalibration.load(config_dir() / "calibration_sim.yaml")
    out = {}
    for name, (psi, theta) in POSES.items():
        cfg = SimConfig.default().with_overrides({"scenario.poses.static": {"psi_deg": psi, "theta_deg": theta}})
        rec = simulate_recording(cfg, seed=3, duration_s=30.0)
        keep = rec.t_s > 2.0
        a = cal.apply_counts(rec.ref, rec.xyz, rec.temp_c, rec.t_s)[keep]
        out[name] = (a.mean(axis=0) - rec.gref_mps2[keep].mean(axis=0)).tolist()
    return out


def main() -> int:
    res = output_dir_from_command_line(__doc__.splitlines()[0])
    cfg = SimConfig.default()
    out = {
        "report": optics.linearity_report(cfg),
        "report_gaussian": optics.linearity_report(cfg.with_overrides(GAUSSIAN)),
        "curvature_1g": {"measured": measured_curvature(), "simulated": simulated_curvature({}),
                         "simulated_gaussian": simulated_curvature(GAUSSIAN)},
        "calibrated_static_error": calibrated_static_error(),
    }
    (res / "optics_linearity.json").write_text(json.dumps(out, indent=2))
    lines = ["# Spectral-overlap non-linearity (bench/optics_linearity.py)", "",
             f"Metric: {out['report']['metric']}.", "",
             "| axis | gratings | order | FWHM nm | r(d0/2)/R | NL % FS +-180 m/s^2 | NL % FS +-20 g "
             "| quadratic share at 1 g % | paper % FS |",
             "|---|---|---|---|---|---|---|---|---|"]
    meas = out["curvature_1g"]["measured"]
    for name in "xyz":
        for label, key, ckey in (("Gaussian (before)", "report_gaussian", "simulated_gaussian"),
                                 ("current", "report", "simulated")):
            a = out[key]["axes"][name]
            curv = out["curvature_1g"][ckey]["xyz".index(name)]
            paper = a["paper_nonlinearity_pct_fs_180"]
            lines.append(f"| {name} | {label} | {a['super_gaussian_order']:.2f} | {a['grating_fwhm_nm']:.3f} | "
                         f"{a['reflectivity_at_crossing_rel_peak']:.2f} | {a['nonlinearity_pct_fs_pm180']:.2f} | "
                         f"{a['nonlinearity_pct_fs_pm20g']:.2f} | {curv:.2f} | {paper if paper else 'lowest'} |")
        if "curvature_share_1g_pct" in meas:
            j = "xyz".index(name)
            lines.append(f"| {name} | measured run | | | | | | {meas['curvature_share_1g_pct'][j]:.2f} "
                         f"+- {meas['bootstrap_se_pct'][j]:.2f} | |")
    lines += ["", "Mean error (m/s^2, x/y/z) of config/calibration_sim.yaml, 30 s static at 23.4 degC, seed 3:", ""]
    lines += [f"* {k}: " + " / ".join(f"{v:+.3f}" for v in e) for k, e in out["calibrated_static_error"].items()]
    (res / "optics_linearity.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
