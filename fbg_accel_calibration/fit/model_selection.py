"""Choose the temperature degree n of eq. 28 by cross-validation (pure numpy).

Paper Table 4 reports, per degree, the *in-sample* RMSE normalised by the 20 g full scale and
picks n = 3 from three temperature levels (16, 24, 45 degC). In-sample RMSE can only fall with
the degree, and with L levels a degree >= L is not even identified. This module therefore reports
for every degree 0..max:

* ``in_sample``: RMSE of the fit on its own samples;
* ``held_out_pose``: leave-one-pose-out -- each pose (all its samples, at every temperature level)
  is predicted by the model fitted without it;
* ``held_out_level`` (only with L >= 2 levels): leave-one-temperature-level-out -- each level is
  predicted by the model fitted on the other L - 1 levels (interpolation for inner levels,
  extrapolation for the outer ones). A degree >= L - 1 cannot be fitted without one level, so it
  has no value there.

All figures are RMSE per axis over the predicted samples, m/s^2 and divided by the 20 g full
scale (196.1 m/s^2). Folds remove cells from the streamed normal-equation sums of
:mod:`thermal_fit`, so cross-validation costs one pass over the data.

Choice (three steps; every step is reported in ``criterion`` and ``notes``):

1. Only identified degrees (n < L) with a pose hold-out score are candidates.
2. Temperature guard (only with L >= 2 levels): the level hold-out tests interpolation between
   temperature levels. A degree whose level hold-out RMSE is worse than that of every lower degree's
   best is not a candidate: a temperature term that predicts unseen levels worse is over-fitting
   temperature. The walk goes on above it: a bias even in temperature makes the linear term
   extrapolate the outer levels worse than the constant while the quadratic predicts them far better,
   so stopping at the first worse degree would keep the wrong model. Degrees without a level score
   (n = L - 1 passes exactly through the L level means) cannot be checked this way; the notes say so
   when one is chosen.
3. One-standard-error rule (Breiman et al. 1984, CART §3.4) on the pose hold-out: take the
   candidate with the smallest mean squared held-out error, estimate that mean's standard error
   from the per-pose fold errors, and choose the lowest candidate degree within one standard
   error of it. A higher degree must beat a lower one by more than the pose-to-pose scatter of the
   validation itself.

In-sample RMSE never enters the choice (it can only fall with the degree).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2
from fbg_accel_driver.thermal_model import normalise

from ..io.recording import Recording
from .fit_stream import FitData, fit_valid, prepare
from .static_detector import DEFAULT_MIN_INTERVAL, DEFAULT_WINDOW
from .thermal_fit import (
    DEFAULT_CHUNK,
    DEFAULT_LEVEL_GAP_C,
    CellStats,
    NotIdentifiedError,
    check_pose_excitation,
    design_matrix,
    level_excitation,
    solve_normal_equations,
)


@dataclass
class DegreeScores:
    """Scores of one degree; RMSE arrays are (3,) in m/s^2, NaN where not computable."""

    degree: int
    identified: bool
    in_sample: np.ndarray
    held_out_pose: np.ndarray
    held_out_level: np.ndarray
    note: str = ""


@dataclass
class SelectionResult:
    """Cross-validation over degrees, like paper Table 4 plus held-out columns."""

    scores: list[DegreeScores]
    n_levels: int
    level_means_c: list[float]
    n_poses: int
    n_samples: int
    chosen_degree: int | None
    criterion: str
    notes: list[str] = field(default_factory=list)

    def table_markdown(self) -> str:
        """Markdown table: RMSE / full scale per axis, in sample and held out, per degree."""
        def fmt(v: np.ndarray) -> str:
            return " / ".join("n/a" if not np.isfinite(x) else f"{x / FULL_SCALE_MPS2:.2e}" for x in v)

        lines = ["| n | identified | in-sample RMSE/FS x / y / z | held out by pose x / y / z | "
                 "held out by temperature level x / y / z | note |", "|---|---|---|---|---|---|"]
        for s in self.scores:
            mark = " **(chosen)**" if s.degree == self.chosen_degree else ""
            lines.append(f"| {s.degree}{mark} | {'yes' if s.identified else 'NO'} | {fmt(s.in_sample)} | "
                         f"{fmt(s.held_out_pose)} | {fmt(s.held_out_level)} | {s.note} |")
        return "\n".join(lines)

    def as_dict(self) -> dict:
        return {
            "n_levels": self.n_levels, "level_means_c": self.level_means_c, "n_poses": self.n_poses,
            "n_samples": self.n_samples, "chosen_degree": self.chosen_degree, "criterion": self.criterion,
            "notes": list(self.notes), "full_scale_mps2": FULL_SCALE_MPS2,
            "degrees": [{"degree": s.degree, "identified": s.identified, "note": s.note,
                         "in_sample_rmse_mps2": s.in_sample.tolist(),
                         "held_out_pose_rmse_mps2": s.held_out_pose.tolist(),
                         "held_out_level_rmse_mps2": s.held_out_level.tolist()} for s in self.scores],
        }


def _fit_cells(stats: CellStats, cells: np.ndarray, degree: int) -> np.ndarray:
    xtx, xtg, _, _ = stats.select(cells, degree)
    return solve_normal_equations(xtx, xtg)[0]


def _held_out(stats: CellStats, groups: np.ndarray, degree: int, min_levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Predict each group's cells from a fit on all other cells.

    Returns the RMSE (3,) over all predicted samples and the per-group mean squared error
    (G,), averaged over axes, for the standard error of the score; NaN if any fold fails.
    """
    rss = np.zeros(3)
    n = 0.0
    group_mse = []
    for g in np.unique(groups):
        test = groups == g
        train = ~test
        if len(np.unique(stats.level[train])) < min_levels:
            return np.full(3, np.nan), np.full(1, np.nan)
        try:
            A = _fit_cells(stats, train, degree)
        except NotIdentifiedError:
            return np.full(3, np.nan), np.full(1, np.nan)
        g_rss = stats.cell_rss(A, degree, test).sum(axis=0)  # the held-out cells' alone
        g_n = stats.count[test].sum()
        rss += g_rss
        n += g_n
        group_mse.append(float(g_rss.mean() / max(g_n, 1)))
    return np.sqrt(rss / n), np.asarray(group_mse)


def select_degree(rec: Recording | FitData, max_degree: int = 6, *, window: int = DEFAULT_WINDOW,
                  min_interval: int = DEFAULT_MIN_INTERVAL, level_gap_c: float = DEFAULT_LEVEL_GAP_C,
                  chunk: int = DEFAULT_CHUNK, usable: np.ndarray | None = None) -> SelectionResult:
    """Score degrees 0..``max_degree`` and choose one (see module docstring)."""
    data = prepare(rec, max_degree, window, min_interval, level_gap_c, usable, chunk) if isinstance(rec, Recording) else rec
    if len(data) == 0:
        raise NotIdentifiedError("no usable static samples")
    n_levels = len(data.level_means_c)
    stats = data.cell_stats(max_degree, chunk)  # streamed data: the sums already read from the files
    check_pose_excitation(stats)
    n_excited, excitation_notes = level_excitation(stats)
    all_cells = np.ones(len(stats.count), dtype=bool)
    n_total = stats.count.sum()
    by_level = n_levels >= 2
    notes: list[str] = []
    scores: list[DegreeScores] = []
    pose_mse_by_degree: dict[int, np.ndarray] = {}
    for degree in range(max_degree + 1):
        nan3 = np.full(3, np.nan)
        if degree >= n_levels:
            scores.append(DegreeScores(degree, False, nan3, nan3, nan3,
                                       f"not identified: degree >= {n_levels} temperature level(s)"))
            continue
        if degree >= 1 and degree >= n_excited:
            scores.append(DegreeScores(degree, False, nan3, nan3, nan3,
                                       f"not identified: needs {degree + 1} temperature levels whose poses span the "
                                       f"table frame, {n_excited} do"))
            continue
        try:
            A = _fit_cells(stats, all_cells, degree)
        except NotIdentifiedError as exc:
            scores.append(DegreeScores(degree, False, nan3, nan3, nan3, f"not identified: {exc}"))
            continue
        in_sample = np.sqrt(stats.cell_rss(A, degree).sum(axis=0) / n_total)
        pose_cv, pose_group_mse = _held_out(stats, stats.pose, degree, min_levels=degree + 1)
        level_cv = _held_out(stats, stats.level, degree, min_levels=degree + 1)[0] if by_level else nan3
        pose_mse_by_degree[degree] = pose_group_mse
        note = ""
        if by_level and not np.all(np.isfinite(level_cv)):
            note = f"no level hold-out: degree {degree} needs {degree + 1} levels in each fold"
        elif not np.all(np.isfinite(pose_cv)):
            note = "no pose hold-out: too few poses without one"
        scores.append(DegreeScores(degree, True, in_sample, pose_cv, level_cv, note))
    chosen, criterion, guard_notes = choose_degree(scores, pose_mse_by_degree, by_level)
    notes += guard_notes
    if excitation_notes and n_levels > 1:
        notes += [f"{n} (its poses do not constrain the temperature terms along that direction)"
                  for n in excitation_notes]
    if n_levels == 1:
        notes.append("one temperature level: only degree 0 (the paper's linear model, eq. 25) is identified")
    if max_degree >= n_levels:
        notes.append(f"degrees >= {n_levels} are not identified by {n_levels} temperature level(s) and are never chosen")
    if chosen is None:
        notes.append("no degree could be validated on held-out data")
    return SelectionResult(scores, n_levels, [float(v) for v in data.level_means_c], data.n_poses,
                           int(n_total), chosen, criterion, notes)


def choose_degree(scores: list[DegreeScores], group_mse: dict[int, np.ndarray], by_level: bool,
                  unit: str = "pose") -> tuple[int | None, str, list[str]]:
    """Steps 1-3 of the module docstring: (chosen degree or None, criterion, notes).

    ``scores[i].held_out_pose`` is the RMSE (m/s^2, x/y/z) held out by ``unit`` (the calibration holds out
    poses; ``diagnose`` re-selects the degree of a model with added effects holding out visits) and
    ``group_mse[degree]`` the mean squared held-out error of each held-out group, whose scatter sets the
    one-standard-error margin."""
    notes: list[str] = []
    candidates: list[DegreeScores] = []
    best_level = np.inf
    for s in scores:
        if not (s.identified and np.all(np.isfinite(s.held_out_pose))):
            continue
        level = float(np.mean(s.held_out_level)) if by_level else np.nan
        if np.isfinite(level):
            if level > best_level:
                notes.append(f"degree {s.degree} predicts held-out temperature levels worse than a lower degree "
                             f"({level:.4g} > {best_level:.4g} m/s^2): not chosen")
                continue
            best_level = level
        candidates.append(s)
    criterion = (f"lowest degree within one standard error of the best {unit} hold-out"
                 + (", after the temperature-level hold-out guard" if by_level else " (one temperature level)"))
    if not candidates:
        return None, criterion, notes
    mse = {s.degree: group_mse[s.degree] for s in candidates}
    best = min(candidates, key=lambda s: float(mse[s.degree].mean()))
    groups = mse[best.degree]
    se = float(groups.std(ddof=1) / np.sqrt(len(groups))) if len(groups) > 1 else 0.0
    limit = float(groups.mean()) + se
    chosen = min(s.degree for s in candidates if float(mse[s.degree].mean()) <= limit)
    if chosen != best.degree:
        notes.append(f"degree {best.degree} has the lowest {unit} hold-out error, but degree {chosen} is within one "
                     f"standard error of it ({limit:.4g} (m/s^2)^2) and is simpler")
    chosen_scores = next(s for s in candidates if s.degree == chosen)
    if by_level and not np.all(np.isfinite(chosen_scores.held_out_level)):
        notes.append(f"degree {chosen} passes exactly through the temperature levels: its interpolation between "
                     "levels is not validated by a level hold-out (that needs one more level)")
    return chosen, criterion, notes


def held_out_predictions(data: FitData, rec: Recording, usable: np.ndarray, degree: int, by: str = "pose") -> np.ndarray:
    """Calibrated output (N, 3) m/s^2 of the samples of ``rec`` that ``data`` fitted (``fit_stream.prepare`` of
    ``rec`` with ``usable``), each predicted by the model fitted without its pose (``by='pose'``) or without its
    temperature level (``by='level'``); NaN for the other samples and where that fold cannot be fitted."""
    if by not in ("pose", "level"):
        raise ValueError(f"by must be 'pose' or 'level', got {by!r}")
    psi = normalise(rec.xyz, rec.ref)
    fitted = np.flatnonzero(np.asarray(usable, dtype=bool) & fit_valid(rec, psi))
    tau = (rec.temp_c[fitted] - data.t_center_c) / data.t_scale_c
    stats = data.cell_stats(degree)
    cell_group = stats.pose if by == "pose" else stats.level
    sample_group = rec.pose_id[fitted] if by == "pose" else data.level_of(rec.temp_c[fitted])
    out = np.full((len(rec), 3), np.nan)
    for g in np.unique(cell_group):
        train = cell_group != g
        if len(np.unique(stats.level[train])) <= degree:
            continue
        try:
            A = _fit_cells(stats, train, degree)
        except NotIdentifiedError:
            continue
        rows = np.flatnonzero(sample_group == g)
        out[fitted[rows]] = design_matrix(psi[fitted[rows]], tau[rows], degree) @ A
    return out
