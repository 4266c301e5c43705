"""Fit of the paper's measured multi-position series with the linear model, and its report.

``fbg-accel-calib report-measured`` (run from the repository root) reads
``../shared/data/measured/fig13_multiposition_23C.csv`` (override with ``--csv``), imports it with
the CSV interchange importer (table angles -> reference, ``g = 9.81 m/s^2`` as in the data README,
constant 23.4 degC, time = sample index because no time base was published), keeps the samples the
static detector calls still, fits the paper's linear model (eq. 25 = eq. 28 with n = 0: one
temperature level identifies nothing more), and writes ``docs/results/measured_fit.md`` and
``docs/img/measured_fit.png``:

* in-sample and held-out (leave-one-pose-out) RMSE per axis against the within-pose noise floor
  (pooled standard deviation of the calibrated output within each pose);
* the fitted M and b next to the paper's published values. The sensor's mounting on the table was
  not published, so the fitted rows (table axes) are shown as fitted and re-ordered by the signed
  permutation that makes the diagonal largest and positive (a fixed mounting rotation/reflection,
  absorbed by M); the paper lost the signs of b and of some M entries, so magnitudes are compared.

Static detector settings for this series: a pose holds only about 9 samples, so the window is 3
samples and the minimum interval 3 samples (the node's defaults, 5 and 5, are for 100 Hz streams).
"""

from __future__ import annotations

import csv
import itertools
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2
from fbg_accel_driver.thermal_model import normalise

from ..fit.fit_pipeline import fit_thermal
from ..fit.fit_stream import fit_valid, prepare
from ..fit.model_selection import SelectionResult, held_out_predictions, select_degree
from ..fit.static_detector import calibration_samples
from ..io.atomic_output import OutputError, check_outputs, committed_outputs
from ..io.csv_import import import_csv
from ..io.recording import Recording
from .fit_report import AXES, PoseStats, plot_calibrated_vs_reference, pose_statistics
from .measured_paths import FIT_MD as DEFAULT_MD
from .measured_paths import FIT_PNG as DEFAULT_PNG
from .measured_paths import MEASURED_CSV as DEFAULT_CSV

TEMPERATURE_C = 23.4  # data README: held at about 23.4 degC, not in the series
G_MPS2 = 9.81  # data README: g ~ 9.81 m/s^2
WINDOW = 3
MIN_INTERVAL = 3
PAPER_M = np.array([[81.60, 2.89, 0.71], [1.59, 77.66, 3.75], [0.24, 1.23, 107.66]])
PAPER_B_ABS = np.array([101.08, 153.59, 137.16])


class MeasuredDataMissingError(FileNotFoundError):
    """The measured series (../shared) is not available."""


@dataclass
class MeasuredFit:
    """Everything the report shows (m/s^2 unless stated)."""

    rec: Recording
    usable: np.ndarray
    selection: SelectionResult
    M: np.ndarray
    b: np.ndarray
    perm: np.ndarray  # (3, 3) signed permutation applied to the rows for the comparison
    rmse_in: np.ndarray
    rmse_held_out: np.ndarray
    noise_floor: np.ndarray
    stats: PoseStats
    held_out_stats: PoseStats
    n_intermediate: int
    n_intermediate_kept: int
    n_intermediate_kept_same_reference: int
    n_intermediate_signal_still: int  # intermediate samples the signal criterion alone calls still
    trend_mps2: np.ndarray  # (3,) change of the per-pose residual over the run, linear fit
    csv_path: Path
    coefficient_covariance: np.ndarray | None = None  # (12, 12) of (M, b), coefficient_uncertainty's order
    visit_stats: Any = None  # the fit's CellStats (thermal_fit), for other clusterings and the bootstrap


def signed_permutation(M: np.ndarray) -> np.ndarray:
    """The 3x3 signed permutation P maximising trace(P M) (rows of M re-ordered and sign-flipped)."""
    best, best_val = np.eye(3), -np.inf
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            P = np.zeros((3, 3))
            for i, (p, s) in enumerate(zip(perm, signs, strict=True)):
                P[i, p] = s
            val = np.trace(P @ M)
            if val > best_val:
                best, best_val = P, val
    return best


def fit_measured(csv_path: Path = DEFAULT_CSV) -> MeasuredFit:
    """Import and fit the measured series; raises :class:`MeasuredDataMissingError` if the CSV is absent."""
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        raise MeasuredDataMissingError(
            f"measured data not found: {csv_path} (expected the team's shared directory next to the repository, "
            "../shared/data/measured/; give another path with --csv)")
    rec, _ = import_csv(csv_path, rate_hz=1.0, temperature_c=TEMPERATURE_C, g_mps2=G_MPS2)
    rec.metadata["sensor_id"] = "paper-fig13"
    usable, signal_static = calibration_samples(rec, window=WINDOW, min_interval=MIN_INTERVAL)
    data = prepare(rec, 2, usable=usable)
    selection = select_degree(data, max_degree=2)
    cal = fit_thermal(data, 0, sensor_id="paper-fig13")
    M, b = cal.M[0], cal.b[0]
    fitted = np.flatnonzero(usable & fit_valid(rec, normalise(rec.xyz, rec.ref)))  # the samples data holds
    res_held = held_out_predictions(data, rec, usable, 0, by="pose")[fitted] - rec.gref_mps2[fitted]
    rmse_held = np.sqrt(np.nanmean(res_held**2, axis=0))
    stats = pose_statistics(cal, rec, usable)
    # held-out residual per pose, in the order of pose_statistics (run 0 only here)
    held_mean = np.stack([np.bincount(np.searchsorted(stats.pose, rec.pose_id[fitted]), weights=res_held[:, j],
                                      minlength=len(stats.pose)) for j in range(3)], axis=1) / stats.count[:, None]
    held_stats = PoseStats(stats.pose, stats.run, stats.temp_c, stats.count, stats.gref, stats.mean_cal + 0.0,
                           held_mean, stats.residual_std)
    try:
        with open(csv_path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
        psi_deg = np.array([[float(r["psi_deg"]), float(r["theta_deg"])] for r in rows])
    except (OSError, KeyError, ValueError):
        psi_deg = None
    inter = (np.zeros(len(rec), bool) if psi_deg is None
             else (np.mod(psi_deg[:, 0], 30.0) != 0) | (np.mod(psi_deg[:, 1], 30.0) != 0))
    kept = np.flatnonzero(inter & usable)
    signal_only = int((inter & signal_static).sum())
    g = rec.gref_mps2
    same_ref = sum(1 for i in kept if 0 < i < len(rec) - 1
                   and np.array_equal(g[i - 1], g[i]) and np.array_equal(g[i + 1], g[i]))
    # linear trend of the per-pose mean residual against the pose's mean sample index
    idx = np.flatnonzero(usable)
    order = np.searchsorted(stats.pose, rec.pose_id[idx])
    pose_pos = np.bincount(order, weights=idx.astype(float), minlength=len(stats.pose)) / stats.count
    slope = np.polyfit(pose_pos, stats.residual_mean, 1)[0]
    trend = slope * (pose_pos.max() - pose_pos.min())
    return MeasuredFit(rec, usable, selection, M, b, signed_permutation(M), np.asarray(cal.fit["rmse_mps2"]),
                       rmse_held, stats.pooled_within_pose_std(), stats, held_stats, int(inter.sum()),
                       len(kept), int(same_ref), signal_only, trend, csv_path, cal.coefficient_covariance.matrix,
                       data.stats)


def _matrix_md(M: np.ndarray, fmt: str = "{:.2f}") -> str:
    return "<br>".join("[" + ", ".join(fmt.format(v) for v in row) + "]" for row in M)


def _perm_md(P: np.ndarray) -> str:
    sign = {1: "+1", -1: "−1", 0: "0"}
    return "<br>".join("[" + ", ".join(sign[round(float(v))] for v in row) + "]" for row in P)


def report_markdown(fit: MeasuredFit, png_rel: str, command: str) -> str:
    P = fit.perm
    Ma, ba = P @ fit.M, P @ fit.b
    n_total = len(fit.rec)
    lines = [
        "# Measured series: linear calibration fit (paper Figure 13 data)", "",
        "Reproduce (from the repository root, with `../shared` present):", "", "```", command, "```", "",
        f"Data: `{fit.csv_path}` — {n_total} samples at 23.4 °C, multi-position test θ 0..360° × ψ 0..330° "
        "(step 30°), no time base (time = sample index). Reference: f = Rz(ψ)ᵀ Rx(θ)ᵀ (0, 0, 9.81 m/s²) "
        "(data README). Ψ = counts / ref_counts (eq. 24).", "",
        "## Samples used",
        "",
        f"- static detector (moving variance of Ψ over {WINDOW} samples against the noise-floor threshold, "
        f"plus a constant table reference over the same window, runs of ≥ {MIN_INTERVAL} samples; "
        "`fbg_accel_calibration/fit/static_detector.py`): "
        f"**{int(fit.usable.sum())} of {n_total}** samples kept, {len(fit.stats.pose)} poses.",
        f"- samples whose table angle is not a multiple of 30° (taken while the table moved): {fit.n_intermediate}; "
        f"kept by the detector: **{fit.n_intermediate_kept}** (the detector is not told about the angles; "
        "this count is a check, not an input), of which "
        f"{fit.n_intermediate_kept_same_reference} have the same reference as both neighbours (θ = 0: ψ turns "
        "about the vertical, the specific force does not change, the sample is static in the sense the fit needs). "
        f"The signal criterion alone (Ψ variance) calls {fit.n_intermediate_signal_still} of the {fit.n_intermediate} "
        "still: a one-sample move whose step is within the noise, or whose first sample still lags (TIA "
        "low-pass); the reference criterion (the table's own readings, constant over the window) removes those "
        "whose reference changes.",
        "",
        "## Model and degree",
        "",
        "One temperature level: only the paper's linear model (eq. 25, = eq. 28 with n = 0, 12 parameters) is "
        "identified; degrees ≥ 1 are refused, as the table shows.", "",
        fit.selection.table_markdown(), "",
        "## Accuracy against the noise floor", "",
        "| axis | in-sample RMSE [m/s²] | held-out RMSE (leave one pose out) [m/s²] | within-pose noise floor [m/s²] "
        "| held-out / noise floor | in-sample RMSE / 20 g FS |",
        "|---|---|---|---|---|---|",
    ]
    for j in range(3):
        lines.append(f"| {AXES[j]} | {fit.rmse_in[j]:.3f} | {fit.rmse_held_out[j]:.3f} | {fit.noise_floor[j]:.3f} | "
                     f"{fit.rmse_held_out[j] / fit.noise_floor[j]:.2f} | {fit.rmse_in[j] / FULL_SCALE_MPS2:.1e} |")
    lines += [
        "",
        "The within-pose noise floor is the pooled standard deviation of the calibrated output around each "
        "pose's mean (static samples only). Held-out RMSE: every pose predicted by the model fitted without it.",
        "",
        "The residual is above the noise floor (most on x). It is not random from pose to pose: the per-pose "
        "mean residual changes along the run by " + " / ".join(f"{v:+.2f}" for v in fit.trend_mps2)
        + " m/s² (x / y / z, linear trend from the first to the last pose, bottom row of the plot), i.e. a "
        "drift during the run that the paper's linear model does not contain; the residual diagnosis "
        "(`fbg-accel-calib diagnose`, issue 4) tests such effects.",
        "",
        "## Fitted M and b next to the paper", "",
        "Rows of the fit are table axes; the sensor's mounting on the table was not published, so the rows are "
        "also shown re-ordered by the signed permutation P that makes the diagonal largest and positive "
        f"(P = {_perm_md(P)}). The paper lost the signs of b and of some M entries, so magnitudes "
        "are compared. M maps Ψ (dimensionless) to m/s², so its unit is m/s² per unit Ψ (the data README calls "
        "the published M dimensionless; the agreement below shows it is on the same m/s² scale).", "",
        "| | fitted (table axes) | fitted, P·M / P·b | paper (published) | abs(fitted) − paper |",
        "|---|---|---|---|---|",
        f"| M [m/s² per unit Ψ] | {_matrix_md(fit.M)} | {_matrix_md(Ma)} | {_matrix_md(PAPER_M)} | "
        f"{_matrix_md(np.abs(Ma) - PAPER_M)} |",
        f"| b [m/s²] | {_matrix_md(fit.b[None, :])} | {_matrix_md(ba[None, :])} | "
        f"{_matrix_md(PAPER_B_ABS[None, :])} (magnitudes) | {_matrix_md((np.abs(ba) - PAPER_B_ABS)[None, :])} |",
        "",
        f"![calibrated vs reference, residual per pose]({png_rel})", "",
        "Top: calibrated output (colour: static samples used by the fit; grey: excluded) and the reference. "
        "Bottom: per-pose residual, mean ± within-pose std, and the held-out residual (×).", "",
    ]
    return "\n".join(lines)


def run_report(csv_path: Path = DEFAULT_CSV, md_path: Path = DEFAULT_MD, png_path: Path = DEFAULT_PNG,
               command: str = "") -> MeasuredFit:
    fit = fit_measured(csv_path)
    cal_title = "measured series (paper Fig. 13), linear model, static samples"
    from fbg_accel_driver.thermal_model import ThermalCalibration

    cal = ThermalCalibration(M=fit.M[None], b=fit.b[None], temperature_range_c=(TEMPERATURE_C, TEMPERATURE_C))
    md_path, png_path = Path(md_path), Path(png_path)
    try:  # resolved as paths (the directories are made with the outputs)
        png_rel = str(png_path.resolve().relative_to(md_path.parent.resolve()))
    except ValueError:
        png_rel = str(png_path)
    # the report and its plot are replaced together or not at all (an interrupted run keeps the previous pair)
    with committed_outputs() as outs:
        plot_calibrated_vs_reference(cal, fit.rec, fit.usable, outs.path(png_path), title=cal_title,
                                     held_out_residual=fit.held_out_stats)
        outs.path(md_path).write_text(report_markdown(fit, png_rel, command or ".venv/bin/fbg-accel-calib "
                                                      "report-measured --force"), encoding="utf-8")
    return fit


def main_args(csv_path: Path, md_path: Path, png_path: Path, argv: list[str] | None = None,
              force: bool = False) -> int:
    """CLI body of ``report-measured``; exit code 2 with a clear message when the data is absent. ``argv``: the
    command line given to ``cli.main`` (default: sys.argv, the console script's)."""
    argv = sys.argv[1:] if argv is None else argv
    command = "fbg-accel-calib report-measured" + ("".join(" " + shlex.quote(str(a)) for a in argv[1:]))
    try:  # existing pages (the committed results included) are replaced only with --force
        check_outputs([md_path, png_path], [csv_path], force=force)
        fit = run_report(csv_path, md_path, png_path, command=".venv/bin/" + command)
    except (OutputError, MeasuredDataMissingError) as exc:
        print(f"fbg-accel-calib report-measured: {exc}", file=sys.stderr)
        return 2
    print(f"static samples kept: {int(fit.usable.sum())} of {len(fit.rec)}")
    for j in range(3):
        print(f"{AXES[j]}: in-sample RMSE {fit.rmse_in[j]:.3f} m/s^2, held-out {fit.rmse_held_out[j]:.3f} m/s^2, "
              f"within-pose noise floor {fit.noise_floor[j]:.3f} m/s^2")
    print(f"wrote {md_path} and {png_path}")
    return 0
