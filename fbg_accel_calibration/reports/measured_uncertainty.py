"""The coefficient uncertainty of the paper's linear model on its measured series, next to the published matrix.

``fbg-accel-calib uncertainty-measured`` (run from the repository root) fits the measured series exactly as
``report-measured`` does (``measured_report.fit_measured``: static samples, eq. 25 = eq. 28 with n = 0) and writes
``docs/results/calibration_uncertainty.md`` (``--md``):

* the standard uncertainty of each entry of M and b, cluster-robust with the visits (stays at one pose) as clusters,
  CR2 (``coefficient_uncertainty``, the covariance the fit writes into a calibration file), next to a bootstrap over
  the visits and next to the same estimate with groups of 12 consecutive visits (about one psi sweep of the table) as
  clusters: the series drifts during the run (its reference falls 1.6 %, ``report-measured``'s residual trend), so
  neighbouring visits share an error and the visits are not quite independent;
* the fitted entries (rows re-ordered and signed as in ``report-measured``: the mounting was not published) against
  the paper's published values (``measured_report.PAPER_M``, ``PAPER_B_ABS``; magnitudes, the paper lost signs), the
  difference in units of the combined standard uncertainty u = sqrt(u_fit^2 + u_round^2), u_round = 0.005 / sqrt(3)
  for the paper's two decimals (GUM 4.3.7, a rectangular distribution), and whether it is within k = 2 (about 95 %).
"""

from __future__ import annotations

import math
import shlex
import sys
from pathlib import Path

import numpy as np

from fbg_accel_driver.coefficient_covariance import CoefficientCovariance, output_covariance
from fbg_accel_driver.thermal_model import normalise

from ..fit.coefficient_uncertainty import bootstrap_covariance, cluster_covariance
from ..fit.thermal_fit import model_to_coefficients
from ..io.atomic_output import OutputError, atomic_path, check_outputs
from .measured_report import PAPER_B_ABS, PAPER_M, MeasuredDataMissingError, MeasuredFit, fit_measured

SWEEP_VISITS = 12  # psi steps 0..330 deg by 30: one sweep of the inner table axis at one theta (data README)
U_ROUND = 0.005 / math.sqrt(3.0)  # two decimals published: rectangular +-0.005
COVERAGE_K = 2.0
BOOTSTRAP_DRAWS = 1000


def entry_uncertainties(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Standard uncertainties of M (3, 3) and b (3,) of a degree-0 fit from its (12, 12) coefficient covariance
    (``coefficient_covariance``'s order: index 3 k + i, regressor k = Psi_j for k = j < 3 and the constant for k = 3,
    output axis i)."""
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None)).reshape(4, 3)  # [k, i]
    return sd[:3].T, sd[3]


def compare(fit: MeasuredFit) -> dict[str, np.ndarray | int]:
    """Everything the page shows: uncertainties by the three estimates, the permuted fit and its differences."""
    A = model_to_coefficients(fit.M[None], fit.b[None])
    stats = fit.visit_stats
    by_visit = fit.coefficient_covariance
    groups = np.arange(len(stats.visit_cell)) // SWEEP_VISITS
    by_sweep, _, n_sweeps = cluster_covariance(stats, A, 0, groups=groups)
    boot, used = bootstrap_covariance(stats, 0, n_boot=BOOTSTRAP_DRAWS, seed=0)
    P = fit.perm
    absP = np.abs(P)  # the signed permutation moves rows (output axes); a sign does not change an uncertainty
    out: dict[str, np.ndarray | int] = {"visits": len(stats.visit_cell), "sweeps": n_sweeps, "bootstrap_draws": used}
    for name, cov in (("visit", by_visit), ("sweep", by_sweep), ("bootstrap", boot)):
        uM, ub = entry_uncertainties(cov)
        out[f"uM_{name}"], out[f"ub_{name}"] = absP @ uM, absP @ ub
    # at the output: sqrt(diag(J Sigma J^T)) at every static sample's Psi (one temperature: tau = 0), median per axis
    psi = normalise(fit.rec.xyz, fit.rec.ref)[fit.usable]
    psi = psi[np.all(np.isfinite(psi), axis=1)]
    w = CoefficientCovariance(by_visit, "by visit", len(stats.visit_cell)).weights(0.0)
    var = np.array([output_covariance(w, *p) for p in psi])[:, [0, 3, 5]]
    out["u_output"] = absP @ np.median(np.sqrt(np.clip(var, 0.0, None)), axis=0)
    Ma, ba = P @ fit.M, P @ fit.b
    out["M"], out["b"] = Ma, ba
    out["dM"], out["db"] = np.abs(Ma) - PAPER_M, np.abs(ba) - PAPER_B_ABS
    for name in ("visit", "sweep"):
        out[f"zM_{name}"] = out["dM"] / np.hypot(out[f"uM_{name}"], U_ROUND)
        out[f"zb_{name}"] = out["db"] / np.hypot(out[f"ub_{name}"], U_ROUND)
    return out


def _rows(values: np.ndarray, fmt: str) -> str:
    return "<br>".join("[" + ", ".join(fmt.format(v) for v in row) + "]" for row in np.atleast_2d(values))


def report_markdown(fit: MeasuredFit, c: dict, command: str) -> str:
    within = {name: int((np.abs(c[f"zM_{name}"]) <= COVERAGE_K).sum() + (np.abs(c[f"zb_{name}"]) <= COVERAGE_K).sum())
              for name in ("visit", "sweep")}
    lines = [
        "# Calibration uncertainty on the measured series (paper Figure 13 data)", "",
        "Reproduce (from the repository root, with `../shared` present):", "", "```", command, "```", "",
        f"Data: `{fit.csv_path}` (1560 samples at 23.4 °C, no time base); the fit of `report-measured` "
        f"(docs/results/measured_fit.md): {int(fit.usable.sum())} static samples, the paper's linear model (eq. 25 = "
        "eq. 28 with n = 0, 12 coefficients). Rows re-ordered and signed by the same P as there (the mounting was not "
        "published); the paper's values are magnitudes (it lost signs).", "",
        "## Method", "",
        f"- **by visit** (what `fbg-accel-calib fit` writes to the calibration file): cluster-robust (sandwich) "
        f"covariance with the {c['visits']} visits (stays at one pose) as the independent clusters, CR2 small-sample "
        "correction (Bell & McCaffrey 2002; `fbg_accel_calibration/fit/coefficient_uncertainty.py`);",
        f"- **bootstrap**: {c['bootstrap_draws']} refits on visits drawn with replacement (a check of the above);",
        f"- **by sweep**: the same sandwich with groups of {SWEEP_VISITS} consecutive visits (about one ψ sweep) as the "
        f"{c['sweeps']} clusters: the run drifts (its reference falls 1.6 %), so neighbouring visits share an error "
        "that the by-visit estimate takes as independent.",
        f"- The comparison with the paper uses u = sqrt(u_fit² + u_round²), u_round = 0.005/√3 = {U_ROUND:.4f} for its "
        f"two published decimals (GUM 4.3.7); an entry agrees when |fitted| − paper is within {COVERAGE_K:g} u "
        "(about 95 %).", "",
        "## M [m/s² per unit Ψ] and b [m/s²]", "",
        "| | fitted P·M, P·b | u by visit | u bootstrap | u by sweep | paper (magnitudes) | abs(fitted) − paper "
        "| in u by visit | in u by sweep |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| M | {_rows(c['M'], '{:.3f}')} | {_rows(c['uM_visit'], '{:.3f}')} | {_rows(c['uM_bootstrap'], '{:.3f}')} | "
        f"{_rows(c['uM_sweep'], '{:.3f}')} | {_rows(PAPER_M, '{:.2f}')} | {_rows(c['dM'], '{:+.3f}')} | "
        f"{_rows(c['zM_visit'], '{:+.1f}')} | {_rows(c['zM_sweep'], '{:+.1f}')} |",
        f"| b | {_rows(c['b'], '{:.3f}')} | {_rows(c['ub_visit'], '{:.3f}')} | {_rows(c['ub_bootstrap'], '{:.3f}')} | "
        f"{_rows(c['ub_sweep'], '{:.3f}')} | {_rows(PAPER_B_ABS, '{:.2f}')} | {_rows(c['db'], '{:+.3f}')} | "
        f"{_rows(c['zb_visit'], '{:+.1f}')} | {_rows(c['zb_sweep'], '{:+.1f}')} |", "",
        "The entries are strongly correlated (M's column of an axis with its b: Ψ sits near 1.2-1.9, far from 0), so "
        "the calibrated output is far better known than the entries: sqrt(diag(J Σ Jᵀ)) at the fit's own static "
        "samples, by visit, median: " + " / ".join(f"{v:.3f}" for v in c["u_output"]) + " m/s² (x / y / z, after P). "
        "That is what the driver adds to the covariance (docs/topics.md, calibration uncertainty).", "",
        "## Verdict", "",
        f"- Within {COVERAGE_K:g} u by visit: **{within['visit']} of 12** entries; by sweep: **{within['sweep']} of 12**.",
        ("- The paper's published matrix and vector agree with this fit within the fit's own uncertainty: the "
         "differences are what the scatter of the visits explains." if min(within.values()) == 12 else
         "- An entry outside says that the paper's value and this fit differ by more than the visits' scatter "
         "explains: the two fits did not use the same samples (the paper's selection of static samples, its value of g "
         "and the table-axis pairing are not published; here the static detector's samples, g = 9.81 m/s²), so the "
         "difference is one of method, not only of noise."), "",
    ]
    return "\n".join(lines)


def main_args(csv_path: Path, md_path: Path, argv: list[str] | None = None, force: bool = False) -> int:
    """CLI body of ``uncertainty-measured``: exit 2 with one line when the data is absent or the output refused (an
    existing page is replaced only with ``force``)."""
    argv = sys.argv[1:] if argv is None else argv
    command = ".venv/bin/fbg-accel-calib uncertainty-measured" + "".join(" " + shlex.quote(str(a)) for a in argv[1:])
    try:
        check_outputs([md_path], [csv_path], force=force)
        fit = fit_measured(csv_path)
        c = compare(fit)
        with atomic_path(md_path) as tmp:
            tmp.write_text(report_markdown(fit, c, command), encoding="utf-8")
    except (OutputError, MeasuredDataMissingError) as exc:
        print(f"fbg-accel-calib uncertainty-measured: {exc}", file=sys.stderr)
        return 2
    uM, ub = c["uM_visit"], c["ub_visit"]
    print("u(M) by visit [m/s^2 per unit Psi]: " + "; ".join(", ".join(f"{v:.3f}" for v in row) for row in uM))
    print("u(b) by visit [m/s^2]: " + ", ".join(f"{v:.3f}" for v in ub))
    print(f"wrote {md_path}")
    return 0

