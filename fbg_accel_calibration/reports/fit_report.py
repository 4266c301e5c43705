"""Tables and plots of a calibration fit (numpy + matplotlib Agg; no ROS).

* :func:`pose_statistics` -- per pose: reference, mean calibrated output, residual mean and
  within-pose standard deviation (m/s^2).
* :func:`plot_calibrated_vs_reference` -- PNG: calibrated output and reference over the samples
  (samples used by the fit highlighted) and the residual of every pose with its within-pose scatter.
* :func:`plot_residuals_per_degree` -- PNG: RMSE / full scale per degree, in sample and held out
  (the picture of paper Table 4 with the held-out columns added).
* :func:`fit_report_markdown` -- the text report combining them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2
from fbg_accel_driver.thermal_model import ThermalCalibration, normalise

from ..fit.model_selection import SelectionResult
from ..io.recording import Recording

AXES = ("x", "y", "z")
COLORS = ("tab:red", "tab:green", "tab:blue")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


@dataclass
class PoseStats:
    """Per-pose figures (P poses): ``pose`` (P,), ``run`` (P,), ``temp_c`` (P,), ``count`` (P,),
    ``gref`` (P, 3), ``mean_cal`` (P, 3), ``residual_mean`` (P, 3), ``residual_std`` (P, 3), all m/s^2."""

    pose: np.ndarray
    run: np.ndarray
    temp_c: np.ndarray
    count: np.ndarray
    gref: np.ndarray
    mean_cal: np.ndarray
    residual_mean: np.ndarray
    residual_std: np.ndarray

    def rmse(self) -> np.ndarray:
        """Root-mean-square residual (3,) of every sample of the poses, m/s^2."""
        dof = np.maximum(self.count - 1, 0)
        sq = self.count[:, None] * self.residual_mean**2 + dof[:, None] * self.residual_std**2
        return np.sqrt(sq.sum(axis=0) / max(float(self.count.sum()), 1.0))

    def pooled_within_pose_std(self) -> np.ndarray:
        """Pooled within-pose standard deviation (3,) of the calibrated output: the noise floor, m/s^2."""
        dof = np.maximum(self.count - 1, 0)
        return np.sqrt((dof[:, None] * self.residual_std**2).sum(axis=0) / max(dof.sum(), 1))


def calibrated(cal: ThermalCalibration, rec: Recording) -> np.ndarray:
    """The calibration file's output (N, 3) m/s^2 for every sample, as the driver computes it: eq. 28 and the
    file's correction terms, each run streamed from its start (the terms may be filters with state)."""
    if not cal.corrections:
        return cal.base_acceleration(normalise(rec.xyz, rec.ref), rec.temp_c)
    out = np.empty((len(rec), 3))
    for run in np.unique(rec.run_id):
        idx = np.flatnonzero(rec.run_id == run)
        out[idx] = cal.apply_counts(rec.ref[idx], rec.xyz[idx], rec.temp_c[idx], rec.t_s[idx], cal.new_state())
    return out


def pose_statistics(cal: ThermalCalibration, rec: Recording, mask: np.ndarray) -> PoseStats:
    """Statistics per (run, pose) of the samples in ``mask``."""
    out = calibrated(cal, rec)
    res = out - rec.gref_mps2
    idx = np.flatnonzero(mask)
    keys = np.stack([rec.run_id[idx], rec.pose_id[idx]], axis=1)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    cnt = np.bincount(inv).astype(float)

    def mean(a: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(inv, weights=a[idx, j]) for j in range(a.shape[1])], axis=1) / cnt[:, None]

    r_mean = mean(res)
    sq = np.stack([np.bincount(inv, weights=(res[idx, j] - r_mean[inv, j]) ** 2) for j in range(3)], axis=1)
    r_std = np.sqrt(sq / np.maximum(cnt - 1, 1)[:, None])
    temp = np.bincount(inv, weights=np.nan_to_num(rec.temp_c[idx])) / cnt
    return PoseStats(uniq[:, 1], uniq[:, 0], temp, cnt, mean(rec.gref_mps2), mean(out), r_mean, r_std)


def plot_calibrated_vs_reference(cal: ThermalCalibration, rec: Recording, mask: np.ndarray, path: str | Path,
                                 title: str = "", held_out_residual: PoseStats | None = None) -> Path:
    """Two rows x three axes: (top) calibrated output (grey: all samples, colour: used by the fit) and
    reference over the sample index; (bottom) per-pose residual mean +- within-pose std, with held-out
    residuals (model fitted without that pose) if given."""
    plt = _plt()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    out = calibrated(cal, rec)
    stats = pose_statistics(cal, rec, mask)
    n = np.arange(len(rec))
    fig, axs = plt.subplots(2, 3, figsize=(14, 7.5))
    for j in range(3):
        ax = axs[0, j]
        ax.plot(n, out[:, j], ".", ms=2, color="0.7", label="calibrated, excluded (moving)")
        ax.plot(n[mask], out[mask, j], ".", ms=2.5, color=COLORS[j], label="calibrated, static (fit)")
        ax.plot(n, rec.gref_mps2[:, j], "-", lw=0.8, color="k", label="reference")
        ax.set_title(f"{AXES[j]} axis")
        ax.set_xlabel("sample")
        ax.set_ylabel("specific force [m/s²]")
        ax.grid(alpha=0.3)
        if j == 0:
            ax.legend(fontsize=7, loc="lower left")
        ax = axs[1, j]
        k = np.arange(len(stats.pose))
        ax.errorbar(k, stats.residual_mean[:, j], yerr=stats.residual_std[:, j], fmt="o", ms=2.5, lw=0.6,
                    color=COLORS[j], label="in sample: mean ± within-pose std")
        if held_out_residual is not None:
            ax.plot(k, held_out_residual.residual_mean[:, j], "x", ms=3, color="k", label="held out (pose left out)")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_xlabel("pose (in order of the run)")
        ax.set_ylabel("calibrated − reference [m/s²]")
        ax.grid(alpha=0.3)
        if j == 0:
            ax.legend(fontsize=7)
    fig.suptitle(title or f"calibration fit, degree {cal.degree}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_residuals_per_degree(selection: SelectionResult, path: str | Path, title: str = "") -> Path:
    """RMSE / full scale per degree and axis: in sample, held out by pose, held out by temperature level."""
    plt = _plt()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    deg = np.array([s.degree for s in selection.scores])
    series = {"in sample": np.array([s.in_sample for s in selection.scores]),
              "held out by pose": np.array([s.held_out_pose for s in selection.scores]),
              "held out by temperature level": np.array([s.held_out_level for s in selection.scores])}
    fig, axs = plt.subplots(1, 3, figsize=(13, 4), sharey=True)
    for j in range(3):
        ax = axs[j]
        for (name, arr), marker in zip(series.items(), ("o-", "s--", "^:"), strict=True):
            ok = np.isfinite(arr[:, j])
            if ok.any():
                ax.semilogy(deg[ok], arr[ok, j] / FULL_SCALE_MPS2, marker, label=name)
        for s in selection.scores:
            if not s.identified:
                ax.axvspan(s.degree - 0.5, s.degree + 0.5, color="0.9")
        if selection.chosen_degree is not None:
            ax.axvline(selection.chosen_degree, color="k", lw=0.8, ls="--")
        ax.set_title(f"{AXES[j]} axis")
        ax.set_xlabel("degree n in temperature (grey: not identified)")
        ax.set_xticks(deg)
        ax.grid(alpha=0.3, which="both")
        if j == 0:
            ax.set_ylabel("RMSE / 20 g full scale")
            ax.legend(fontsize=8)
    fig.suptitle(title or f"residuals per degree ({selection.n_levels} temperature level(s), chosen n = "
                 f"{selection.chosen_degree})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def pose_table_markdown(stats: PoseStats, max_rows: int = 40) -> str:
    lines = ["| run | pose | T [°C] | n | reference x / y / z [m/s²] | residual mean x / y / z | within-pose std x / y / z |",
             "|---|---|---|---|---|---|---|"]
    for i in range(min(len(stats.pose), max_rows)):
        lines.append(
            f"| {stats.run[i]} | {stats.pose[i]} | {stats.temp_c[i]:.2f} | {int(stats.count[i])} | "
            + " / ".join(f"{v:.3f}" for v in stats.gref[i]) + " | "
            + " / ".join(f"{v:+.3f}" for v in stats.residual_mean[i]) + " | "
            + " / ".join(f"{v:.3f}" for v in stats.residual_std[i]) + " |")
    if len(stats.pose) > max_rows:
        lines.append(f"| ... | {len(stats.pose) - max_rows} more poses | | | | | |")
    return "\n".join(lines)


def _or_not_recorded(v: object) -> str:
    return "not recorded" if v is None else str(v)


def fit_report_markdown(cal: ThermalCalibration, selection: SelectionResult | None, stats: PoseStats,
                        images: dict[str, str], command: str = "", recording_sensor_id: str | None = None,
                        warnings: list[str] | None = None) -> str:
    """Markdown report of a fit: degree table, RMSE vs noise floor, per-pose table, images. ``warnings`` (another
    sensor, temperatures outside the calibrated range) are listed under the header."""
    fit = cal.fit or {}
    rmse = stats.rmse()  # the file on these inputs; the YAML's own figure is that of the data it was fitted on
    noise = stats.pooled_within_pose_std()
    lines = ["# Calibration fit report", ""]
    if command:
        lines += ["Produced by:", "", "```", command, "```", ""]
    lines += [f"- **warning:** {w}" for w in warnings or []]
    if fit.get("rmse_mps2") is not None:
        fit_line = (f"- at fit time (the YAML): samples used {_or_not_recorded(fit.get('samples_used'))} of "
                    f"{_or_not_recorded(fit.get('samples_total'))} "
                    f"({_or_not_recorded(fit.get('samples_excluded_in_motion'))} excluded by the static detector, "
                    f"{_or_not_recorded(fit.get('samples_excluded_invalid'))} outside poses or without valid "
                    f"reference/temperature), poses {_or_not_recorded(fit.get('poses'))}, in-sample RMSE x/y/z "
                    + " / ".join(f"{v:.4f}" for v in np.asarray(fit["rmse_mps2"], dtype=float)) + " m/s²")
    else:
        fit_line = "- at fit time (the YAML): not recorded (the file has no fit section)"
    lines += [f"- sensor: `{cal.sensor_id}` (calibration), `{recording_sensor_id or 'not recorded'}` (recording), "
              f"degree n = {cal.degree}, temperature range "
              f"{cal.temperature_range_c[0]:.2f} .. {cal.temperature_range_c[1]:.2f} °C, levels "
              f"{_or_not_recorded(fit.get('temperature_levels_c'))}",
              fit_line,
              f"- on these inputs: {int(stats.count.sum())} static samples in {len(stats.count)} poses, the file's "
              "output (eq. 28 and its correction terms) against the reference",
              "", "| axis | RMSE on these inputs [m/s²] | RMSE / FS | within-pose noise floor [m/s²] |", "|---|---|---|---|"]
    for j in range(3):
        lines.append(f"| {AXES[j]} | {rmse[j]:.4f} | {rmse[j] / FULL_SCALE_MPS2:.2e} | {noise[j]:.4f} |")
    if selection is not None:
        lines += ["", f"## Degree selection ({selection.criterion})", "", selection.table_markdown(), ""]
        lines += [f"- {n}" for n in selection.notes]
    for name, rel in images.items():
        lines += ["", f"![{name}]({rel})"]
    lines += ["", "## Poses", "", pose_table_markdown(stats), ""]
    return "\n".join(lines)
