"""The calibration file's ``coefficient_covariance`` section and what it gives at the output (pure numpy, no ROS).

The fit (``fbg_accel_calibration.fit.coefficient_uncertainty``) writes the covariance Sigma (3p, 3p) of eq. 28's
coefficients, p = 4(n+1), ordered row-major over A (p, 3): index ``3 k + i`` is regressor k of eq. 29 for output axis
i, where regressor ``3 m + j`` (m = 0..n, j = 0..2) is tau^m Psi_j (so A[3m + j, i] = M_m[i, j]) and regressor
``3(n+1) + m`` is tau^m (A[3(n+1) + m, i] = b_m[i]). The output is a_i = x . A[:, i] with x the regressor row, so
the calibration's contribution to the output's error covariance (GUM, JCGM 100:2008 eq. 13) at (Psi, T) is::

    C_ij(Psi, T) = x^T Sigma[i::3, j::3] x,     x = T(tau) z,  z = (Psi_x, Psi_y, Psi_z, 1)

with T(tau) (p, 4) the powers of tau. Per temperature the six distinct C_ij are quadratic forms in z: their ten
monomial weights are cached per temperature reading, as the coefficients are (``ThermalCalibration.coefficients_at``),
and a sample costs ten products and six sums of ten. Outside the calibrated range tau^m grows and with it C: the
extrapolation inflates the term through the model itself.

The term is the uncertainty of a bias: the coefficients' error is the same for every sample the calibration
converts, so it does not average out over samples (docs/topics.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .mapping_fields import format_version, number, number_array, refuse_unknown

SECTION_VERSION = 1
SECTION_KEYS = ("format_version", "method", "clusters", "matrix")  # read_section's order
MAX_METHOD_CHARS = 512
# eigenvalues down to -tol * largest are rounding (a covariance written to 17 digits and read back)
PSD_TOLERANCE = 1e-9
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # the distinct entries of the symmetric 3 x 3


@dataclass
class CoefficientCovariance:
    """Covariance ``matrix`` (3p, 3p) of eq. 28's coefficients (module docstring for its order and units), the
    ``method`` that estimated it and the number of independent ``clusters`` (visits) it rests on."""

    matrix: np.ndarray
    method: str
    clusters: int
    # per (temperature reading, centre, scale): the ten monomial weights of each of the six C_ij (6 x 10 floats)
    _cache: dict[tuple[float, float, float], tuple[tuple[float, ...], ...]] = field(default_factory=dict, init=False, repr=False,
                                                               compare=False)

    def __post_init__(self) -> None:
        self.matrix = np.asarray(self.matrix, dtype=float)
        problem = check_matrix(self.matrix)
        if problem:
            raise ValueError(f"coefficient_covariance.matrix {problem}")
        if not isinstance(self.clusters, int) or isinstance(self.clusters, bool) or self.clusters < 1:
            raise ValueError(f"coefficient_covariance.clusters must be a positive integer, got {self.clusters!r}")

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return (np.array_equal(self.matrix, other.matrix) and self.method == other.method
                and self.clusters == other.clusters)

    __hash__ = None  # type: ignore[assignment]

    @property
    def degree(self) -> int:
        return self.matrix.shape[0] // 12 - 1

    def weights(self, tau: float) -> tuple[tuple[float, ...], ...]:
        """The ten weights, per distinct output pair (xx, xy, xz, yy, yz, zz), of the monomials of z = (Psi, 1)
        ``(x x, x y, x z, x, y y, y z, y, z z, z, 1)`` at scaled temperature ``tau``."""
        n = self.degree
        p = 4 * (n + 1)
        powers = tau ** np.arange(n + 1)
        T = np.zeros((p, 4))
        for m in range(n + 1):
            T[3 * m:3 * m + 3, 0:3] = powers[m] * np.eye(3)
            T[3 * (n + 1) + m, 3] = powers[m]
        blocks = self.matrix.reshape(p, 3, p, 3)
        out = []
        for i, j in _PAIRS:
            c = T.T @ blocks[:, i, :, j] @ T
            c = c + c.T - np.diag(np.diag(c))  # z^T c z summed over a <= b
            out.append(tuple(float(c[a, b]) for a in range(4) for b in range(a, 4)))
        return tuple(out)

    def weights_at(self, temp_c: float, center_c: float, scale_c: float) -> tuple[tuple[float, ...], ...]:
        """:meth:`weights` at the temperature reading ``temp_c`` (degC) of a model scaled tau = (T - ``center_c``) /
        ``scale_c``, cached per reading (emptied at 256 entries, as ``ThermalCalibration.coefficients_at``)."""
        key = (temp_c, center_c, scale_c)
        w = self._cache.get(key)
        if w is None:
            if len(self._cache) >= 256:
                self._cache.clear()
            w = self._cache[key] = self.weights((temp_c - center_c) / scale_c)
        return w

    def to_dict(self) -> dict[str, Any]:
        return {"format_version": SECTION_VERSION, "method": self.method, "clusters": int(self.clusters),
                "matrix": [[float(v) for v in row] for row in self.matrix]}

    @classmethod
    def from_dict(cls, d: Any, degree: int, fail: Callable[[str], Exception]) -> CoefficientCovariance:
        """The section of a file whose model has ``degree``; ``fail(message)`` makes the error to raise."""
        method, clusters, matrix = read_section(d, "coefficient_covariance", SECTION_KEYS, SECTION_VERSION, fail)
        size = 12 * (degree + 1)
        if matrix.shape != (size, size):
            raise fail(f"coefficient_covariance.matrix has shape {matrix.shape}, expected {(size, size)} for degree "
                       f"{degree} (3 axes x {size // 3} coefficients)")
        problem = check_matrix(matrix)
        if problem:
            raise fail(f"coefficient_covariance.matrix {problem}")
        return cls(matrix, method, int(clusters))


def read_section(d: Any, section: str, keys: tuple[str, str, str, str], version: int,
                 fail: Callable[[str], Exception]) -> tuple[str, int, np.ndarray]:
    """``(method, count, matrix)`` of a covariance section of a calibration file (this module's and the slow
    error's): a mapping of exactly ``keys`` -- format_version (``version``), method (a text of 1..
    :data:`MAX_METHOD_CHARS` characters), a count (an integer >= 1: the clusters or visits it rests on) and matrix
    (numbers) -- each refusal through ``fail(message)`` naming ``section``. The matrix's shape and values are the
    section's own check."""
    if not isinstance(d, dict):
        raise fail(f"'{section}' must be a mapping, got {type(d).__name__}")
    refuse_unknown(d, keys, f"{section}.", fail)
    for key in keys:
        if key not in d:
            raise fail(f"missing key '{section}.{key}'")
    version_key, method_key, count_key, matrix_key = keys
    format_version(d[version_key], f"{section}.{version_key}", fail, reads=version)
    method = d[method_key]
    if not isinstance(method, str) or not method or len(method) > MAX_METHOD_CHARS:
        raise fail(f"{section}.{method_key} must be a text of 1..{MAX_METHOD_CHARS} characters")
    count = number(d[count_key], f"{section}.{count_key}", fail, minimum=1)
    if count != int(count):
        raise fail(f"{section}.{count_key} must be an integer, got {d[count_key]!r}")
    return method, int(count), number_array(d[matrix_key], f"{section}.{matrix_key}", fail)


def check_matrix(m: np.ndarray) -> str:
    """Why ``m`` is not a covariance of eq. 28's coefficients (square of 12(n+1), finite, symmetric, positive
    semi-definite), or ``""``."""
    if m.ndim != 2 or m.shape[0] != m.shape[1] or m.shape[0] < 12 or m.shape[0] % 12:
        return f"must be square of size 12(n+1), got shape {m.shape}"
    if not np.all(np.isfinite(m)):
        return "contains NaN or infinite values"
    scale = float(np.max(np.abs(m)))
    if not np.allclose(m, m.T, rtol=1e-9, atol=1e-12 * scale):
        return "is not symmetric"
    lowest = float(np.linalg.eigvalsh(m)[0]) if scale > 0 else 0.0
    if lowest < -PSD_TOLERANCE * scale:
        return f"is not positive semi-definite (eigenvalue {lowest:.3g})"
    return ""


def output_covariance(w: tuple[tuple[float, ...], ...], px: float, py: float,
                      pz: float) -> tuple[float, float, float, float, float, float]:
    """(xx, xy, xz, yy, yz, zz) of C(Psi, T), (m/s^2)^2, from the :meth:`CoefficientCovariance.weights` ``w`` of T."""
    z = (px * px, px * py, px * pz, px, py * py, py * pz, py, pz * pz, pz, 1.0)
    return tuple(c[0] * z[0] + c[1] * z[1] + c[2] * z[2] + c[3] * z[3] + c[4] * z[4] + c[5] * z[5] + c[6] * z[6]
                 + c[7] * z[7] + c[8] * z[8] + c[9] for c in w)  # type: ignore[return-value]
