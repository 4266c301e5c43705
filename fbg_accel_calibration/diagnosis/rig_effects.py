"""Properties of the rig, not of the sensor (role ``RIG``): a constant offset of the table's outer (theta) angle
(``table_theta_offset``) and a change of the sensor's seat on its mount between runs (``mount_change``). Fitted like
every candidate (held out by visit) so that eq. 28 is fitted against the gravity the sensor really felt; reported,
never written to the calibration file (the driver never sees the table or the runs).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..io.table_geometry import outer_angle_offset
from .data import DiagnosisData, Inputs, direction_labels, take_rows, visit_means
from .effects import MIN_SPAN_FRACTION, RIG, Effect
from .run_effects import level_linked_runs

# A two-axis table's zero is set against its index mark or a level to a small fraction of a degree; an offset of
# several degrees is seen by eye on the table (ASSUMPTION: no rig figure is published). The search spans the bound.
MAX_TABLE_OFFSET_DEG = 5.0
TABLE_OFFSET_GRID_DEG = np.linspace(-MAX_TABLE_OFFSET_DEG, MAX_TABLE_OFFSET_DEG, 11)  # 1 deg steps (then refined), 0 included

TELLS_IT_FROM_THE_SENSOR = ("check the table's theta zero against a level, or turn the sensor 90 degrees about the "
                            "table's z axis on its mount and repeat: a table offset stays with the table's axis, an "
                            "effect of the sensor turns with the sensor")


class TableThetaOffsetEffect(Effect):
    """The table's theta encoder reads ``delta`` (deg) less than the table's angle: the reference, computed at the
    reading, is the gravity of theta - delta. The correction turns each sample's reference about the outer axis as it
    lies in the table frame, which the inner angle psi alone places (``table_geometry.outer_angle_offset``): exact,
    whatever theta. Needs the table's angles in the recording (``Recording.table_deg``: the CSV's psi_deg/theta_deg
    columns, the simulator); a reference given as a vector has no axis to turn about, and the candidate is not tried.
    An offset of the outer axis is no fixed rotation of the reference (its axis turns with psi), so eq. 28's matrix
    does not take it; a quadratic in Psi takes part of it (``spectral_nonlinearity``), which this candidate, exact,
    outgains."""

    name = "table_theta_offset"
    role = RIG
    reference_only = True
    stage = 3  # after the chain's corrections of the reference (channel_delay re-reads the table's)
    hyper_name = "delta_theta"
    hyper_unit = "deg"
    hyper_null = 0.0
    title = "offset of the table's outer (theta) angle (a property of the rig)"
    bound = ("|delta_theta| at most MAX_TABLE_OFFSET_DEG (5 deg): a table's zero is set to a fraction of a degree "
             "against its index mark or a level, several degrees are seen by eye (ASSUMPTION)")

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        if data.table_deg is None or not np.all(np.isfinite(data.table_deg[data.use])):
            return False, ("the reference is given as a vector, without the table's angles: an offset of the table's "
                           "theta cannot be tried; " + TELLS_IT_FROM_THE_SENSOR)
        return True, ""

    def void(self, h: float | None) -> bool:
        return not h

    def hyper_limits(self, data: DiagnosisData) -> tuple[float, float]:
        return -MAX_TABLE_OFFSET_DEG, MAX_TABLE_OFFSET_DEG

    def hyper_grid(self, data: DiagnosisData) -> np.ndarray:
        return TABLE_OFFSET_GRID_DEG

    def transform(self, data: DiagnosisData, inp: Inputs, h: float | None) -> None:
        if not h:
            return
        psi = data.table_deg[:, 0] if inp.index is None else data.table_deg[inp.index, 0]
        inp.gref = outer_angle_offset(inp.gref, psi, float(h))
        inp.gref_moved = True

    def reference_at(self, data: DiagnosisData, inp: Inputs, h: float | None,
                     rows: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The turned reference at the samples ``rows`` alone (each sample's turn is its own: the same values as
        those rows of the whole series' turn)."""
        if rows is None or not h:
            return super().reference_at(data, inp, h, rows)
        psi = data.table_deg[:, 0] if inp.index is None else data.table_deg[inp.index, 0]
        return outer_angle_offset(take_rows(inp.gref, rows), psi[rows], float(h)), inp.valid[rows]

    def make_terms(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> list[Any]:
        return []  # the rig's, not the sensor's: nothing for the driver

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        if not h:
            return "no offset of the table's theta"
        return (f"the table's theta reads {abs(float(h)):.2f} deg {'less' if h > 0 else 'more'} than the table's angle "
                f"(delta_theta = {float(h):+.3f} deg): a table-angle offset, a property of the rig, not of the sensor; "
                f"{TELLS_IT_FROM_THE_SENSOR}")


# A sensor taken off its mount and put back (screws, a clamp, no dowel pins) sits again within a fraction of a degree
# to a few degrees of its former pose; beyond 5 degrees the mount is visibly turned (ASSUMPTION: no rig figure is
# published; the paper's sensor sits on a two-axis table, section 4.1, the same bound as the table's zero above).
MAX_REMOUNT_DEG = 5.0
# A re-seat turns the sensor: the change of the output between runs is a rotation of the gravity it feels (an
# antisymmetric map). Its symmetric part (a change of scale or of the cross-axis coupling) is no re-seat: above this
# fraction of the rotation the change is the sensor's response (a connector, a gain), not its mounting.
MAX_REMOUNT_SYMMETRIC_FRACTION = 0.5

TELLS_A_REMOUNT_FROM_THE_SENSOR = (
    "record one temperature level twice in a row, re-seating the sensor between the two and leaving it seated for a "
    "third (or mark its seat with dowel pins and repeat): a change of the mounting comes and goes with the re-seat, a "
    "property of the sensor stays; turning the sensor 90 degrees on its mount between two runs of one level turns a "
    "mounting change with the mount")


class MountChangeEffect(Effect):
    """The sensor was re-seated on its mount between runs: a run holds the sensor turned by a small rotation R_r
    against the seat of the run it is compared with (the first of the runs that shared temperature levels connect to
    it, ``level_linked_runs``). Eq. 28 fitted on that seat then gives R_r g in run r, so the output misses the
    reference g by (R_r - I) g, a linear map C_r of the reference (3 columns per run, the reference in that run: 9
    coefficients). Only a rotation (C_r antisymmetric, up to ``MAX_REMOUNT_DEG``) is a re-seat (:meth:`implausible`); a
    map with a symmetric part as large is a change of the sensor's response.

    A run at a level no other run shares leaves its rotation to eq. 28's M(T) at that level, which a higher degree takes
    without a trace: the campaign cannot reveal the re-seat (``applicable`` says so); a level repeated after re-seating,
    in a run of its own that visits every direction twice, does."""

    name = "mount_change"
    role = RIG
    stage = 80
    title = "the sensor re-seated on its mount between runs (a property of the rig)"
    bound = (f"each run's rotation at most MAX_REMOUNT_DEG ({MAX_REMOUNT_DEG:g} deg) and a rotation (its symmetric part "
             f"at most {MAX_REMOUNT_SYMMETRIC_FRACTION:g} x the rotation): a sensor put back on its mount sits within a "
             "few degrees of its former seat, and a re-seat turns the sensor without changing its response "
             "(ASSUMPTION: no rig figure is published)")

    def _linked_runs(self, data: DiagnosisData) -> list[tuple[int, int]]:
        """(run id, the run it is compared with) for each run whose seat is identified: the first run of each set
        of runs that shared temperature levels connect (``level_linked_runs``) holds the seat the others are compared
        with; a run counts when its visits span the table frame (the weakest direction of its visit-mean reference
        keeps ``MIN_SPAN_FRACTION`` of the whole data's) and visit each of their directions of gravity at least twice
        (a fold that holds out the only visit of a direction leaves the run's map without it)."""
        def find() -> list[tuple[int, int]]:
            rows = data.use & (data.group >= 0) & np.all(np.isfinite(data.gref), axis=1)

            def weakest(sel: np.ndarray) -> float:  # smallest standard deviation of the visit-mean reference, m/s^2
                g = visit_means(data.group, sel, data.gref)
                return float(np.sqrt(max(np.linalg.eigvalsh(np.cov(g.T))[0], 0.0))) if len(g) >= 4 else 0.0

            def seen_twice(sel: np.ndarray) -> bool:
                return bool(np.all(np.bincount(direction_labels(visit_means(data.group, sel, data.gref))) >= 2))

            whole = weakest(rows)
            out = []
            for linked in level_linked_runs(data):
                for r in linked[1:]:
                    sel = rows & (data.run_id == r)
                    if weakest(sel) >= MIN_SPAN_FRACTION * whole and seen_twice(sel):
                        out.append((r, linked[0]))
            return out

        return data.once("mount_change_runs", find)

    def applicable(self, data: DiagnosisData) -> tuple[bool, str]:
        runs = data.run_id[data.use]
        if not len(runs) or bool(np.all(runs == runs[0])):  # fewer than two runs
            return False, ("one run: a re-seat of the sensor between its temperature levels would be taken up by eq. "
                           "28's M(T) without a trace; record each level in a run of its own and repeat a level after "
                           "any re-seat")
        if not self._linked_runs(data):
            return False, ("no run shares a temperature level with an earlier one while visiting every direction of "
                           "the table frame twice: a re-seat of the sensor between runs is taken up by eq. 28's M(T) "
                           "at each run's level, a higher degree without a trace; repeat a temperature level after "
                           "re-seating, in a run of its own that visits each pose twice, to test it")
        return True, ""

    def columns(self, data: DiagnosisData, inp: Inputs, h: float | None) -> np.ndarray:
        runs = self._linked_runs(data)
        out = np.zeros((len(inp.t_s), 3 * len(runs)))
        for j, (r, _) in enumerate(runs):
            at = data.run_id == r
            # the table's reference as recorded (gaps between poses filled): a design's columns do not read the
            # corrections of the reference alone (design.build_design), which move it by far less than a re-seat does
            out[at, 3 * j:3 * j + 3] = data.gref_filled[at]
        return out

    @staticmethod
    def rotations(coeff: np.ndarray) -> list[tuple[np.ndarray, float]]:
        """Per run: (the rotation vector (3,) deg that turns the first run's seat into this run's, the largest
        |eigenvalue| of the symmetric part of its map in rad-equivalent) from ``coeff`` (3, 3k): the output misses
        the reference by C g = -(R - I) g, so C's antisymmetric part is -[w]x for a small rotation w."""
        c = np.asarray(coeff, float)
        out = []
        for j in range(c.shape[1] // 3):
            C = c[:, 3 * j:3 * j + 3]
            A, S = 0.5 * (C - C.T), 0.5 * (C + C.T)
            w = -np.array([A[2, 1], A[0, 2], A[1, 0]])
            out.append((np.degrees(w), float(np.max(np.abs(np.linalg.eigvalsh(S))))))
        return out

    def implausible(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData, M0: np.ndarray) -> str:
        if coeff is None:
            return ""
        for (r, first), (w, sym) in zip(self._linked_runs(data), self.rotations(coeff), strict=True):
            angle = float(np.linalg.norm(w))
            if angle > MAX_REMOUNT_DEG:
                return (f"run {r + 1} would be turned by {angle:.3g} deg against run {first + 1}: beyond the "
                        f"{MAX_REMOUNT_DEG:g} deg a re-seat on the mount can turn the sensor")
            if sym > MAX_REMOUNT_SYMMETRIC_FRACTION * np.radians(angle):
                return (f"the change of run {r + 1} against run {first + 1} is no rotation: its symmetric part ({sym:.3g}, a "
                        f"change of scale or of the cross-axis coupling) exceeds {MAX_REMOUNT_SYMMETRIC_FRACTION:g} x "
                        f"its rotation ({np.radians(angle):.3g} rad, {angle:.3g} deg): a change of the sensor's response "
                        "between runs, not of its mounting")
        return ""

    def describe(self, h: float | None, coeff: np.ndarray | None) -> str:
        return self._text(coeff, None)

    def describe_on(self, h: float | None, coeff: np.ndarray | None, data: DiagnosisData) -> str:
        return self._text(coeff, self._linked_runs(data))

    def _text(self, coeff: np.ndarray | None, runs: list[tuple[int, int]] | None) -> str:
        if coeff is None:
            return "no change of the mounting"
        turns = self.rotations(coeff)
        names = ([f"run {r + 1} against run {first + 1}" for r, first in runs] if runs is not None else
                 [f"compared run {k + 1}" for k in range(len(turns))])
        parts = [f"{n}: turned by {np.linalg.norm(w):.2f} deg (rotation vector x/y/z {w[0]:+.2f} / {w[1]:+.2f} / "
                 f"{w[2]:+.2f} deg)" for n, (w, _) in zip(names, turns, strict=True)]
        return ("the sensor sits on its mount otherwise than in an earlier run at its temperature level: "
                + "; ".join(parts) + ": a property of the rig, not of the sensor (the calibration is of the earlier "
                "seat); "
                + TELLS_A_REMOUNT_FROM_THE_SENSOR)
