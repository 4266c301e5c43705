"""The step of the response at one time: not a candidate (not in ``effects.LIBRARY``), the alternative a candidate
that can follow a step (its ``Effect.checks`` hold a step check) must beat (``diagnosis.checks.step_check``).
"""

from __future__ import annotations

import numpy as np

from .data import DiagnosisData, Inputs, finite_rows
from .effects import MIN_SPAN_FRACTION, Effect, SpectralNonlinearityEffect


class ResponseStepEffect(Effect):
    """Not a candidate (not in ``LIBRARY``): the alternative a function of time or of the temperature's history
    (an ``Effect`` whose ``checks`` hold a step check) must beat (``diagnose.step_check``).
    The linear response changes once, for good: from the first sample of one visit on, every axis gets an offset and
    a slope on each Psi (about its mean) of its own (eq. 25 refitted after the step). A connector knocked or re-mated,
    a fibre bent or a knock on the mount does this to the response (a channel's loss changes the counts it reads by a
    factor), and a warm-up with creep follows such a step across contiguous blocks of time as well: it passes
    ``diagnose.time_block_check``. A property of the recording, never a term of the calibration. Its columns carry no
    temperature: a loss step g of channel j changes the output by (g - 1) M(T) e_j Psi_j, whose part that depends on
    the temperature is (g - 1) times eq. 28's (small) temperature coefficient of M; what the step needs of the
    temperature is eq. 28's own degree, chosen again with the step in the model (``diagnose.step_check``). (On a run
    cycled twice, x knocked at 250 s, at degree 1: x held out 0.239 m/s^2 with these columns, 0.241 with them times
    each power of the temperature as well; at degree 0, 0.355, the rest following the temperature.)
    Hyper-parameter: the index of the first sample after the step (the first sample of a visit in recording order,
    at least ``MIN_VISITS_EACH_SIDE`` visits on either side, so that both sides span the orientations)."""

    name = "response_step"
    stage = 90
    hyper_name = "first sample after the step"
    title = "a step of the response at one time (connector, fibre, knock)"
    MIN_VISITS_EACH_SIDE = 4

    def _starts(self, data: DiagnosisData) -> np.ndarray:
        """Index of the first fitted sample of every visit, in recording order."""
        def compute() -> np.ndarray:
            idx = np.flatnonzero(data.use & (data.group >= 0))
            _, first = np.unique(data.group[idx], return_index=True)
            return np.sort(idx[first])

        return data.once("visit_start_samples", compute)

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        if len(self._starts(data)) < 2 * self.MIN_VISITS_EACH_SIDE:
            return False, f"fewer than {2 * self.MIN_VISITS_EACH_SIDE} visits"
        if not len(self.hyper_grid(data)):
            return False, "no time at which the visits before and after each span the table frame"
        return True, ""

    def visit_table(self, data: DiagnosisData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(first fitted sample (V,), visit-mean reference (V, 3) m/s^2 in the table frame, visit id (V,)) of the
        fitted visits with a finite reference, in recording order."""
        def compute() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            idx = np.flatnonzero(data.use & (data.group >= 0) & finite_rows(data.gref))
            ids, first, inv = np.unique(data.group[idx], return_index=True, return_inverse=True)
            cnt = np.bincount(inv, minlength=len(ids)).astype(float)
            g = np.stack([np.bincount(inv, weights=data.gref[idx, j], minlength=len(ids)) / cnt for j in range(3)], axis=1)
            order = np.argsort(idx[first], kind="stable")
            return idx[first][order], g[order], ids[order]

        return data.once("step_visit_table", compute)

    def sides_span(self, data: DiagnosisData, grid: np.ndarray, trained: np.ndarray) -> np.ndarray:
        """(k, m) bool: for each of k training sets (``trained`` (k, V), the visits of :meth:`visit_table` trained on)
        and each step time of ``grid`` (m,) sample indices, whether the visits trained on before the step and those
        after it each span the table frame: the weakest direction of their visit-mean reference keeps
        ``MIN_SPAN_FRACTION`` of the whole data's spread (the identifiability ``diagnose.check_folds`` asks of every
        fold). The step gives the side after it a linear response of its own, so each side alone must identify one:
        on a grid run whose first visits all sit at z up (the inner angle turns, gravity does not), a step after them
        left the side before it one direction, fitted by coefficients that cancel across the step, and a visit held
        out there was predicted wildly (``test_a_step_s_side_that_does_not_span_the_frame_is_not_tried``)."""
        start, g, _ = self.visit_table(data)
        trained = np.atleast_2d(np.asarray(trained, bool))
        before = np.searchsorted(start, np.asarray(grid, float), side="left")  # visits that start before the step

        def weakest_var(n: np.ndarray, s1: np.ndarray, s2: np.ndarray) -> np.ndarray:
            with np.errstate(divide="ignore", invalid="ignore"):
                m = s1 / n[..., None]
                cov = s2 / n[..., None, None] - m[..., :, None] * m[..., None, :]
            cov = np.where((n >= 2)[..., None, None], np.nan_to_num(cov), 0.0)
            return np.where(n >= 2, np.linalg.eigvalsh(cov)[..., 0], 0.0)

        w = trained.astype(float)  # (k, V)
        outer = g[:, :, None] * g[:, None, :]
        pad = [(0, 0), (1, 0)]
        c0 = np.pad(np.cumsum(w, axis=1), pad)  # (k, V + 1) prefix sums over the visits in recording order
        c1 = np.pad(np.cumsum(w[:, :, None] * g[None], axis=1), [*pad, (0, 0)])
        c2 = np.pad(np.cumsum(w[:, :, None, None] * outer[None], axis=1), [*pad, (0, 0), (0, 0)])
        full = weakest_var(np.array(len(g), float), g.sum(axis=0), outer.sum(axis=0))
        limit = (MIN_SPAN_FRACTION ** 2) * max(float(full), 0.0)
        n_b, s1_b, s2_b = c0[:, before], c1[:, before], c2[:, before]
        n_a, s1_a, s2_a = c0[:, -1:] - n_b, c1[:, -1:] - s1_b, c2[:, -1:] - s2_b
        return (weakest_var(n_b, s1_b, s2_b) >= limit) & (weakest_var(n_a, s1_a, s2_a) >= limit) & (limit > 0)

    # the columns are ``switched_columns`` from the first sample ``h`` on, zero before: a search of ``h`` is one pass
    # over the samples (diagnose.switch_profile), not a cross-validation of every value
    switched = True
    pointwise = True

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        """The visit starts with ``MIN_VISITS_EACH_SIDE`` visits on either side, each side's visits spanning the
        table frame (:meth:`sides_span`; every fold is held to it too, ``diagnose.Evaluator``)."""
        def compute() -> np.ndarray:
            m = self.MIN_VISITS_EACH_SIDE
            starts = self._starts(data)
            grid = starts[m:len(starts) - m + 1].astype(float)
            return grid[self.sides_span(data, grid, np.ones(len(self.visit_table(data)[0]), bool))[0]]

        return data.once("step_grid", compute)

    def switched_columns(self, data: DiagnosisData, inp: Inputs) -> np.ndarray:
        """(n, 4) the columns once switched on: 1 and Psi about its mean static value (uncentred, a slope column is
        nearly the offset column times the rest Psi)."""
        psi0 = SpectralNonlinearityEffect()._psi0(data)
        return np.column_stack([np.ones(len(inp.t_s)), inp.psi - psi0[None, :]])

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray:
        after = (inp.sample_index >= float(h)).astype(float)
        return after[:, None] * self.switched_columns(data, inp)
