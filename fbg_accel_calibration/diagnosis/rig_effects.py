"""Properties of the rig, not of the sensor (role ``RIG``): a constant offset of the table's outer (theta) angle
(``table_theta_offset``). Fitted like every candidate (held out by visit) so that eq. 28 is fitted against the gravity
the table really gave; reported, never written to the calibration file (the driver never sees the table).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..effects import RIG, Effect
from ..table_geometry import outer_angle_offset
from .data import DiagnosisData, Inputs, take_rows

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
