"""Properties of each recording, not of the sensor (role ``PER_RUN``): each run (file, temperature level) has its own
bias offset (``run_offset``) or its own linear drift in time (``run_drift``). Fitted so that they do not bias eq. 28,
reported, never written to the calibration (the driver cannot know runs). No hyper-parameter.
"""

from __future__ import annotations

import numpy as np

from .data import DiagnosisData, Inputs
from .effects import MAX_DRIFT_MPS2, PER_RUN, Effect


class _PerRunEffect(Effect):
    """Base of the per-run terms: one column per run (``run_offset``: every run but the first, whose offset is
    eq. 28's b) whose coefficients are m/s^2 per axis. Runs count where ``use`` has samples."""

    role = PER_RUN
    bound = "each run's term at most MAX_DRIFT_MPS2, 5 % of full scale (±20 g, paper §3.4)"
    stage = 80
    skip_first = False
    unit_text = ""

    def _runs(self, data: DiagnosisData) -> list[np.ndarray]:
        return [idx for idx in data.runs() if data.use[idx].any()]

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        if len(self._runs(data)) < 2:
            return False, "one run (file / temperature level) in this recording"
        return True, ""

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray:
        runs = self._runs(data)[1 if self.skip_first else 0:]
        out = np.zeros((len(inp.t_s), len(runs)))
        for j, idx in enumerate(runs):
            out[idx, j] = self._shape(inp.t_s[idx])
        return out

    def _shape(self, t_s: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        c = np.asarray(coeff) if coeff is not None else np.zeros((3, 0))
        first = 2 if self.skip_first else 1
        return f"{self.unit_text}: " + "; ".join(f"run {first + j}: [{c[0, j]:.3g}, {c[1, j]:.3g}, {c[2, j]:.3g}]"
                                                  for j in range(c.shape[1])) + " m/s^2 (not in the calibration file)"

    def implausible(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray) -> str:
        if coeff is not None and np.any(np.abs(coeff) > MAX_DRIFT_MPS2):
            return (f"a per-run term of {np.max(np.abs(coeff)):.3g} m/s^2 exceeds {MAX_DRIFT_MPS2:.3g} m/s^2 (5 % of "
                    "full scale): terms that cancel, not a drift")
        return ""


class RunOffsetEffect(_PerRunEffect):
    name = "run_offset"
    title = "bias offset of each run (file / temperature level) of its own"
    unit_text = "correction added to the output, against run 1, x/y/z"
    skip_first = True

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        ok, why = super().applicable(data)
        apart = data.once("runs_apart_by_level", lambda: runs_apart_by_levels(data)) if ok else []
        if apart:
            first = int(np.min(data.run_id[data.use])) + 1
            who = ("no temperature level is shared by any two runs" if not _any_level_shared(data) else
                   f"run(s) {', '.join(str(r + 1) for r in apart)} share no temperature level with run {first} or "
                   "the runs that share one with it")
            return False, (f"not identified on this data: {who}, so an offset of each run cannot be told from the "
                           "temperature dependence of eq. 28's b (record a temperature level twice, in two runs)")
        return ok, why

    def _shape(self, t_s: np.ndarray) -> np.ndarray:
        return np.ones(len(t_s))


def _run_level_pairs(data: DiagnosisData) -> np.ndarray:
    """(k, 2) the distinct (run id, temperature level label) of the fitted samples (``thermal_fit.temperature_levels``)."""
    from ..fit.thermal_fit import temperature_levels

    use = data.use & np.isfinite(data.temp_c)
    labels = temperature_levels(data.temp_c[use])[0]
    return np.unique(np.stack([data.run_id[use], labels], axis=1), axis=0)


def _any_level_shared(data: DiagnosisData) -> bool:
    """Whether two runs have fitted samples at one temperature level."""
    pairs = _run_level_pairs(data)
    return bool(len(np.unique(pairs[:, 1])) < len(pairs))


def level_linked_runs(data: DiagnosisData) -> list[list[int]]:
    """The run ids with fitted samples in sets that shared temperature levels connect (two runs are linked when both
    have samples at one level), each set ascending, the sets in the order of their first run."""
    pairs = _run_level_pairs(data)
    left = [int(r) for r in np.unique(pairs[:, 0])]
    out = []
    while left:
        linked, grew = {left[0]}, True
        while grew:  # grow the set of runs reachable from its first one through levels they share
            levels = pairs[np.isin(pairs[:, 0], list(linked)), 1]
            reach = {int(r) for r in pairs[np.isin(pairs[:, 1], levels), 0]}
            grew = not reach <= linked
            linked |= reach
        out.append(sorted(linked))
        left = [r for r in left if r not in linked]
    return out


def runs_apart_by_levels(data: DiagnosisData) -> list[int]:
    """The run ids (ascending) that shared temperature levels do not connect to the first run with fitted samples (two
    runs are linked when both have samples at one level). Only runs all connected let an offset of each run be told
    from a bias that depends on the level: with one level per run (one file per chamber temperature) the offsets
    would take over eq. 28's b(T), and leave the calibration file without it. Empty: all connected."""
    sets = level_linked_runs(data)
    return sorted(r for linked in sets[1:] for r in linked)


class RunDriftEffect(_PerRunEffect):
    name = "run_drift"
    title = "linear drift of each run (file / temperature level) of its own"
    unit_text = "correction added to the output over each run (end minus start), x/y/z"

    def _shape(self, t_s: np.ndarray) -> np.ndarray:
        span = float(np.ptp(t_s)) if len(t_s) else 0.0
        return (t_s - 0.5 * (t_s.min() + t_s.max())) / span if span > 0 else np.zeros(len(t_s))
