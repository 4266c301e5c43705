"""The calibration file's ``slow_error`` section: the slow error of a pose mean beyond noise and coefficients (pure numpy).

A pose mean carries, besides the noise model's part and the coefficients' J Sigma J^T (``coefficient_covariance``),
what wanders slowly (bias instability, source-power wander through a dark offset, warm-up drift) and what eq. 28 does
not contain at the poses visited. The fit estimates it from its own campaign, as the visits' mean residuals' scatter
beyond the noise model and, when a level has two runs, the runs' (``fbg_accel_calibration.fit.slow_error``: variance
components by visit and by run, method of moments), and writes its covariance S (3, 3) in (m/s^2)^2, sensor frame,
and, when the run-to-run component R is known (identified by the campaign, or carried from an earlier calibration of the
sensor: ``fit --run-to-run-from``), R itself (3, 3) in (m/s^2)^2, sensor frame, as the optional ``run_to_run_matrix``:
a later one-run recalibration, which cannot identify it, takes it from there. It is the same for every sample of a
still stretch: a bias, correlated in time, added as such (with ``covariance_includes_calibration``, once per
published message) and used by the live gravity check's threshold (docs/topics.md).

A section without R (each temperature level recorded once, nothing carried) states S without the run-to-run part: the
bias instability's slowest components are constant through a run, taken up by b(T), and drawn afresh by the time the
sensor is on the vehicle. No campaign of that design can measure them (its revisits of a pose are minutes apart, the
components hours: docs/calibration_fit.md, *Run to run*), so the published covariance allows
:data:`UNSTATED_RUN_TO_RUN_SIGMA_MPS2` for it, a standard deviation on each axis from the sensor's bias instability
(:attr:`SlowErrorSection.published_matrix`), as the gravity check allows a margin for it
(``gravity_check.unstated_allowance``). The file itself is unchanged: a section without ``run_to_run_matrix`` is what
says that R is not known.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .coefficient_covariance import check_matrix, read_section
from .mapping_fields import number_array, refuse_unknown
from .sensor_constants import STANDARD_GRAVITY

SECTION_VERSION = 1
SECTION_KEYS = ("format_version", "method", "visits", "matrix")  # read_section's order
RUN_KEY = "run_to_run_matrix"  # optional: the run-to-run component R (3, 3) (m/s^2)^2, when known
MAX_SIGMA_MPS2 = 10.0  # a slow error above 1 g is no calibration
# paper Table 2's largest bias instability (z, 1.87 mg; ../shared/docs/sensor_facts.md), m/s^2
TABLE2_BIAS_INSTABILITY_MPS2 = 1.87e-3 * STANDARD_GRAVITY
PLAN_RUN_S = 240.0  # s, one run of the paper's six-position plan (config/pose_plan_six_position.yaml: 6 x (30 + 10) s)
USE_LAG_S = 365.25 * 86400.0  # s, a calibration used for up to a year


def flicker_run_to_run_sigma_mps2(bias_instability_mps2: float, run_s: float, lag_s: float) -> float:
    """Standard deviation (m/s^2) of the difference between a flicker bias' means over two runs of ``run_s`` s,
    ``lag_s`` s apart (lag >> run: the campaign's run, which b(T) took up, and a run on the vehicle), for the bias
    instability B (m/s^2) of an Allan deviation flat at 0.664 B: the integral of the PSD B^2 / (2 pi f) (IEEE Std
    952-1997, annex C) times |1 - e^(2 pi i f lag)|^2 sinc^2(pi f run), (B^2 / pi) (ln(lag / run) + 3/2) (checked
    against the integral done numerically, test/test_slow_error.py)."""
    return math.sqrt(bias_instability_mps2**2 / math.pi * (math.log(lag_s / run_s) + 1.5))


# the run-to-run part (m/s^2, one standard deviation per axis, sensor frame) that a section without R does not state,
# added squared on each axis to the published covariance (isotropic: every axis' bias is drawn afresh, and which axis
# is the sensor's worst is not in the file): Table 2's largest bias instability as a flicker floor, between one run
# of the paper's plan and a use a year later, 0.038 m/s^2 (0.028 a day later, 0.041 ten years later: the logarithm
# makes the lag matter little). A real sensor's is its own: repeat a level, or carry R (``fit --run-to-run-from``),
# and this is not used (docs/calibration_fit.md). Not the gravity check's allowance for the same part
# (``gravity_check.UNSTATED_RUN_TO_RUN_MPS2``, 0.05 m/s^2 added to a threshold, measured against false alarms): that is
# a setting of a decision, this a statement of a standard deviation (docs/topics.md)
UNSTATED_RUN_TO_RUN_SIGMA_MPS2 = flicker_run_to_run_sigma_mps2(TABLE2_BIAS_INSTABILITY_MPS2, PLAN_RUN_S, USE_LAG_S)


@dataclass
class SlowErrorSection:
    """Covariance ``matrix`` (3, 3) (m/s^2)^2 of the slow error of a pose mean, the ``method`` that estimated it and the
    number of ``visits`` it rests on; ``run_to_run`` (3, 3) (m/s^2)^2 the run-to-run component R within ``matrix``
    (sensor frame; None: not known, i.e. not identified by the campaign and not carried from an earlier one)."""

    matrix: np.ndarray
    method: str
    visits: int
    run_to_run: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.matrix = np.asarray(self.matrix, dtype=float)
        problem = check_3x3(self.matrix)
        if problem:
            raise ValueError(f"slow_error.matrix {problem}")
        if self.run_to_run is not None:
            self.run_to_run = np.asarray(self.run_to_run, dtype=float)
            problem = check_3x3(self.run_to_run)
            if problem:
                raise ValueError(f"slow_error.{RUN_KEY} {problem}")
        if not isinstance(self.visits, int) or isinstance(self.visits, bool) or self.visits < 1:
            raise ValueError(f"slow_error.visits must be a positive integer, got {self.visits!r}")

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        same_run = (self.run_to_run is None and other.run_to_run is None) or (
            self.run_to_run is not None and other.run_to_run is not None
            and np.array_equal(self.run_to_run, other.run_to_run))
        return (np.array_equal(self.matrix, other.matrix) and self.method == other.method
                and self.visits == other.visits and same_run)

    __hash__ = None  # type: ignore[assignment]

    @property
    def sigma_mps2(self) -> np.ndarray:
        """Standard deviation (3,) m/s^2 per axis (x, y, z)."""
        return np.sqrt(np.clip(np.diag(self.matrix), 0.0, None))

    @property
    def unstated_run_to_run_sigma_mps2(self) -> float:
        """The allowance (m/s^2, 1 sigma per axis) for the run-to-run part this section does not state:
        :data:`UNSTATED_RUN_TO_RUN_SIGMA_MPS2` without R, 0 with it (identified by the campaign or carried)."""
        return UNSTATED_RUN_TO_RUN_SIGMA_MPS2 if self.run_to_run is None else 0.0

    @property
    def published_matrix(self) -> np.ndarray:
        """What the driver publishes for the slow error (3, 3) (m/s^2)^2: ``matrix`` plus the square of
        :attr:`unstated_run_to_run_sigma_mps2` on each axis."""
        return self.matrix + self.unstated_run_to_run_sigma_mps2**2 * np.eye(3)

    def published_entries(self) -> tuple[float, float, float, float, float, float]:
        """(xx, xy, xz, yy, yz, zz) of :attr:`published_matrix`, (m/s^2)^2, as
        ``coefficient_covariance.output_covariance``."""
        m = self.published_matrix
        return (float(m[0, 0]), float(m[0, 1]), float(m[0, 2]), float(m[1, 1]), float(m[1, 2]), float(m[2, 2]))

    def to_dict(self) -> dict[str, Any]:
        return {"format_version": SECTION_VERSION, "method": self.method, "visits": int(self.visits),
                "matrix": [[float(v) for v in row] for row in self.matrix],
                **({RUN_KEY: [[float(v) for v in row] for row in self.run_to_run]}
                   if self.run_to_run is not None else {})}

    @classmethod
    def from_dict(cls, d: Any, fail: Callable[[str], Exception]) -> SlowErrorSection:
        """The section of a parsed file; ``fail(message)`` makes the error to raise."""
        run = None
        if isinstance(d, dict):  # the optional key among the known ones, so a misspelling of it is named as such
            refuse_unknown(d, (*SECTION_KEYS, RUN_KEY), "slow_error.", fail)
        if isinstance(d, dict) and RUN_KEY in d:  # optional: read here, the other keys exactly by read_section
            run = number_array(d[RUN_KEY], f"slow_error.{RUN_KEY}", fail)
            problem = check_3x3(run)
            if problem:
                raise fail(f"slow_error.{RUN_KEY} {problem}")
            d = {k: v for k, v in d.items() if k != RUN_KEY}
        method, visits, matrix = read_section(d, "slow_error", SECTION_KEYS, SECTION_VERSION, fail)
        problem = check_3x3(matrix)
        if problem:
            raise fail(f"slow_error.matrix {problem}")
        return cls(matrix, method, visits, run)


def check_3x3(m: np.ndarray) -> str:
    """Why ``m`` is not the covariance of a slow error (3 x 3, finite, symmetric, positive semi-definite, each standard
    deviation at most :data:`MAX_SIGMA_MPS2`), or ``""``."""
    if m.shape != (3, 3):
        return f"must be 3 x 3, got shape {m.shape}"
    if not np.all(np.isfinite(m)):
        return "contains NaN or infinite values"
    if np.any(np.diag(m) > MAX_SIGMA_MPS2**2):
        return f"has a standard deviation above {MAX_SIGMA_MPS2:g} m/s^2"
    scale = float(np.max(np.abs(m)))
    if scale == 0.0:
        return ""
    return check_matrix(np.kron(m, np.eye(4)))  # symmetric and positive semi-definite, as the coefficients' (12 x 12)
