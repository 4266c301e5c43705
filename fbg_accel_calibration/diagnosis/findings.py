"""What a reader of the diagnosis must not take at face value, as data: each :class:`Finding` says what kind it is,
which effect it is about, the numbers behind it and the measurement that separates its explanations; the report
renders its sentence (``diagnose_report``). ``collect_findings`` gathers them from the final model, in the order the
report lists them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..fit.adc_codes import HeldCode, held_codes
from ..fit.thermal_fit import reference_reach_warnings
from .cv import COLLINEAR_CORR, CvResult, cross_validate
from .data import DiagnosisData, column_rms, finite_rows, visit_means
from .design import Design
from .floor import FLOOR_VISIT_ALPHA, FLOOR_VISIT_RATIO, VisitNoise, _fmt3
from .periodic_disturbance import PeriodicDisturbance
from .search import CandidateResult
from .temperature_reading import jump_warning


@dataclass
class Finding:
    """One result a reader must not take at face value. ``kind`` names the finding (``KINDS``), ``effect`` the
    candidate or effect it is about ("" for the recording), ``numbers`` the measured values it states (m/s^2, s,
    p-values, as named), ``separates`` the measurement that tells its explanations apart ("" when it names none in
    a field of its own), ``text`` the sentence the report renders."""

    kind: str
    text: str
    effect: str = ""
    numbers: dict[str, Any] = field(default_factory=dict)
    separates: str = ""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown kind of finding {self.kind!r}; the kinds: {', '.join(KINDS)}")


KINDS = ("detection_limit", "cannot_reveal", "step_confounded", "table_angles", "approach_direction", "noisy_visits",
         "periodic_disturbance", "held_code", "visit_ends", "reference_reach", "low_reference", "temperature_jumps",
         "clipped", "collinear", "below_floor", "stand_in", "at_bound")


def cannot_reveal(candidates: list[CandidateResult], titles: dict[str, str]) -> list[Finding]:
    """What this campaign cannot reveal, one finding per candidate the data cannot show at all (not testable: its
    ``Effect.applicable`` reason says why and which measurement would show it), so that its absence from the model is
    not read as the sensor's lacking it. ``titles``: candidate name -> what it is (``Effect.title``)."""
    return [Finding("cannot_reveal", f"this campaign cannot reveal {c.name} ({titles.get(c.name, c.name)}): {c.reason}",
                    effect=c.name) for c in candidates if not c.applicable]


def disturbance_warning(d: PeriodicDisturbance, floor: np.ndarray, heldout: np.ndarray) -> str:
    """The warning for a periodic disturbance found in the visits: what, the floor with and without it (m/s^2), what
    the held-out error ``heldout`` (3,) m/s^2 is with and without it, and the basis of the ratios."""
    return (f"{d.summary()}. The noise floor {_fmt3(floor)} m/s^2 is the scatter within visits without the disturbance "
            f"(with it {_fmt3(d.floor_with_lines)}); the held-out error {_fmt3(heldout)} m/s^2 holds it "
            f"({_fmt3(d.heldout_without_lines)} without it), so the ratios to the floor count it as a residual of this "
            "recording, not of the sensor: find what shook the table or chamber, and record again")


def disturbance_finding(data: DiagnosisData, d: PeriodicDisturbance, heldout: np.ndarray, settled: np.ndarray,
                        rows: np.ndarray, floor: np.ndarray, after_ho: np.ndarray) -> Finding:
    """The finding for a periodic disturbance found in the visits: its lines refitted on the final model's held-out
    residual ``heldout`` (N, 3) m/s^2 over the ``settled`` samples, the held-out error without them over ``rows``
    (kept in ``d.heldout_without_lines``), next to the ``floor`` and the held-out error ``after_ho`` (3,) m/s^2."""
    lines_ho = d.refit(heldout, data.t_s, data.group, data.run_id, settled)
    d.heldout_without_lines = column_rms((heldout - lines_ho)[rows])
    return Finding("periodic_disturbance", disturbance_warning(d, floor, after_ho),
                   numbers={"floor_with_lines_mps2": d.floor_with_lines,
                            "heldout_without_lines_mps2": d.heldout_without_lines},
                   separates="find what shook the table or chamber, and record again")


def flagged_visits(data: DiagnosisData, groups: np.ndarray, models: list[VisitNoise], des: Design, cv: CvResult,
                   fit_rows: np.ndarray, rows: np.ndarray, fold: np.ndarray, weights: np.ndarray) -> Finding | None:
    """The finding for the visits left out of the noise floor (``VisitNoise.flagged``), None without any.

    They stay in the fit (no data is dropped behind the user's back); the finding says by how much they move it:
    the final model refitted once without them, the largest change of its fitted output on the other visits'
    samples per axis."""
    seen: dict[int, np.ndarray] = {}
    for m in models:
        for g, scatter, _ in m.flagged:
            seen[g] = np.maximum(seen.get(g, scatter), scatter)
    if not seen:
        return None
    labels = np.array(sorted(seen))
    bad = np.isin(groups, labels)
    names = []
    for g in labels:
        at = np.flatnonzero((groups == g) & (data.pose_id >= 0))
        if not at.size:
            at = np.flatnonzero(groups == g)
        names.append(f"pose {int(data.pose_id[at[0]])} (run {int(data.run_id[at[0]])}, t {data.t_s[at[0]]:.1f}-"
                     f"{data.t_s[at[-1]]:.1f} s) {_fmt3(seen[g])} x floor")
    moved_by = None
    try:
        with np.errstate(all="ignore"):
            moved = des.X @ (cross_validate(des, fit_rows & ~bad, fold, weights).A_full - cv.A_full)
        other = rows & ~bad & finite_rows(moved)
        if other.any():
            moved_by = np.max(np.abs(moved[other]), axis=0)
            shift = (f"leaving them out of the fit as well moves the fitted output on the other visits by up to "
                     f"{_fmt3(moved_by)} m/s^2 (x/y/z)")
        else:
            shift = "no other visit to compare the fit without them on"
    except (np.linalg.LinAlgError, ValueError, IndexError):
        shift = "the model cannot be fitted without them"
    n_v = max(m.n_checked for m in models)
    separates = "cut that stretch and run again"
    return Finding("noisy_visits", f"{len(labels)} visit(s) left out of the noise floor, their scatter far beyond the "
                   f"other visits' (variance over {FLOOR_VISIT_RATIO:g}x what the visits' variances make it, at its "
                   f"reference level and ratios, and p < "
                   f"{FLOOR_VISIT_ALPHA:g} / (3 x {n_v} visits) each): " + "; ".join(names) + f". They stay in the "
                   f"fit: {shift}; a burst of outliers or a dead channel there? Cut that stretch and run again if the "
                   "change matters", numbers={"visits": labels.tolist(), "scatter_x_floor": [seen[g] for g in labels],
                                              "fit_moved_mps2": moved_by}, separates=separates)


def visit_offset(res: np.ndarray, groups: np.ndarray, rows: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """(N,) for every sample of ``rows``: how far its visit's output is off, the squared norm of the visit's mean
    residual ``res`` (N, 3) over the noise ``floor`` (3,) m/s^2; NaN elsewhere."""
    out = np.full(len(groups), np.nan)
    idx = np.flatnonzero(rows)
    labels, inv = np.unique(groups[idx], return_inverse=True)
    n = np.bincount(inv, minlength=len(labels))
    mean = np.stack([np.bincount(inv, res[idx, j], minlength=len(labels)) for j in range(3)], axis=1) / n[:, None]
    out[idx] = np.sum((mean / np.maximum(floor, 1e-12)) ** 2, axis=1)[inv]
    return out


def visit_reference_range(data: DiagnosisData, groups: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(3, 2): lowest and highest visit-mean reference specific force (m/s^2) along each table axis over the visits of
    ``rows`` (the poses the calibration was fitted on; ``thermal_fit.reference_range`` takes cell means)."""
    g = visit_means(groups, rows & np.all(np.isfinite(data.gref), axis=1), data.gref)
    if not len(g):
        return np.full((3, 2), np.nan)
    return np.column_stack([g.min(axis=0), g.max(axis=0)])


def recording_findings(data: DiagnosisData, settling_end: str, groups: np.ndarray, r_eval: np.ndarray,
                       n_levels: int) -> list[Finding]:
    """What the recording itself holds that the reader must know: visit ends disturbed (``settling_end``, the
    settling transient's summary, "" if not), the reference beyond the poses' reach, a low reference, jumps of the
    temperature reading, clipped visits."""
    out = []
    if settling_end:
        out.append(Finding("visit_ends", settling_end + "; the model is fitted on them too: align the table's "
                           "readings (pose labels, reference) with the signal",
                           separates="align the table's readings with the signal"))
    out += [Finding("reference_reach", w) for w in reference_reach_warnings(visit_reference_range(data, groups, r_eval))]
    if data.low_reference_note:
        out.append(Finding("low_reference", data.low_reference_note, numbers={"samples": data.n_low_reference}))
    if data.temperature_jumps:
        out.append(Finding("temperature_jumps", jump_warning(data.temperature_jumps, n_levels >= 2),
                           numbers={"jumps": len(data.temperature_jumps)}))
    if data.n_clipped_visits:
        out.append(Finding("clipped", f"{data.n_clipped_samples} samples of {data.n_clipped_visits} visit(s) left out: "
                           "a channel clipped at a rail of the ADC (an axis at 0 or 4095 counts, or the reference at "
                           "4095) in each; a clipped reading bounds the signal instead of measuring it (lower the "
                           "source power or the gain if the signal sits at the rail)",
                           numbers={"samples": data.n_clipped_samples, "visits": data.n_clipped_visits},
                           separates="lower the source power or the gain"))
    return out


def held_code_findings(data: DiagnosisData, heldout: np.ndarray, groups: np.ndarray, settled: np.ndarray,
                       r_eval: np.ndarray, floor: np.ndarray, alpha: float) -> tuple[list[HeldCode], list[Finding]]:
    """ADC codes that held whole visits (``adc_codes.held_codes``) with what they do to the final model's held-out
    residual ``heldout`` (N, 3) m/s^2: the worst visit offset and the held-out error without their visits."""
    held = held_codes(np.column_stack([data.ref, data.xyz]), groups, settled & r_eval,
                      visit_offset(heldout, groups, r_eval, floor), alpha)
    for h in held:
        means = np.array([heldout[r_eval & (groups == v)].mean(axis=0) for v in h.visits])
        h.worst_offset = means[np.argmax(np.abs(means), axis=0), np.arange(3)]
        rest = r_eval & ~np.isin(groups, h.visits)
        h.rmse_without = column_rms(heldout[rest])
    return held, [Finding("held_code", h.sentence(), numbers={"worst_offset_mps2": h.worst_offset,
                                                              "rmse_without_mps2": h.rmse_without}) for h in held]


def model_findings(column_corr: dict[str, float], after_ho: np.ndarray, floor_after: np.ndarray) -> list[Finding]:
    """What the final model's numbers themselves say: columns not separately determined (``COLLINEAR_CORR``), a
    held-out error below the floor."""
    out = [Finding("collinear", f"a column of {name} correlates at |r| = {c:.4f} with another column of the model: "
                   "their coefficients are not separately determined (large terms that cancel), whatever the held-out "
                   "gain", effect=name, numbers={"abs_r": c}) for name, c in column_corr.items() if c > COLLINEAR_CORR]
    below = after_ho < 0.9 * floor_after
    if np.any(below):
        out.append(Finding("below_floor", "held-out error below the noise floor on axis "
                           + ", ".join(a for a, b in zip("xyz", below, strict=True) if b)
                           + f" ({_fmt3(after_ho)} against {_fmt3(floor_after)} m/s^2): a model cannot predict "
                           "held-out data better than the data repeat themselves, so the floor or the model is wrong "
                           "(an added term that removes noise instead of an effect?)",
                           numbers={"heldout_mps2": after_ho, "floor_mps2": floor_after}))
    return out
