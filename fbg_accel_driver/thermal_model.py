"""Thermal calibration model of the accelerometer (paper eq. 24, 28-30) and its YAML file.

Pure numpy, no ROS. One dataclass, ``ThermalCalibration``, holds the coefficients and metadata,
applies itself to raw counts, and round-trips to a YAML file that carries its format name,
format version and units. The loader refuses a format, version, unit, shape or value it does
not understand, with one message naming the problem (``CalibrationFileError``).

Model, per sample i (sensor frame, REP 103 SI units)::

    Psi_i   = (c_x, c_y, c_z) / c_ref                      (eq. 24, dimensionless)
    tau_i   = (T_i - t_center_c) / t_scale_c               (scaled temperature)
    a_i     = sum_k M_k tau_i^k Psi_i + sum_k b_k tau_i^k  (eq. 28, m/s^2)
            + sum_j correction_j(...)                      (declared extra terms, m/s^2)

With ``t_center_c = 0`` and ``t_scale_c = 1`` this is exactly the paper's eq. 28; centring and
scaling only re-parametrise the same polynomial so that high degrees stay well conditioned.
``corrections`` holds extra physical terms added by ``fbg-accel-calib diagnose`` (see
``fbg_accel_driver.correction_terms``); each is stateless or carries its own streaming state,
so the driver and the offline tools evaluate the same model on the same frames.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

FORMAT_NAME = "fbg_accel_calibration"
FORMAT_VERSION = 1
UNITS = {"psi": "1", "temperature": "degC", "acceleration": "m/s^2", "time": "s"}
MIN_REFERENCE_COUNTS = 1  # a reference of 0 counts would divide by zero; see normalise()


class CalibrationFileError(ValueError):
    """A calibration file is missing, malformed or not understood."""


@dataclass
class ThermalCalibration:
    """Polynomial thermal calibration: ``M`` (n+1, 3, 3) dimensionless, ``b`` (n+1, 3) m/s^2.

    ``temperature_range_c`` is the range the calibration data covered; outside it the model is
    extrapolating. ``noise_sigma_mps2`` is the per-axis white-noise standard deviation of the
    calibrated output at the board's sample rate (m/s^2), used for the IMU covariance.
    ``fit`` holds fit figures (RMSE, held-out RMSE, sample counts, sources) for people to read.
    """

    M: np.ndarray
    b: np.ndarray
    temperature_range_c: tuple[float, float]
    sensor_id: str = "unknown"
    t_center_c: float = 0.0
    t_scale_c: float = 1.0
    noise_sigma_mps2: np.ndarray = field(default_factory=lambda: np.full(3, 0.01))
    created: str = ""
    fit: dict[str, Any] = field(default_factory=dict)
    corrections: list[Any] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.M = np.asarray(self.M, dtype=float)
        self.b = np.asarray(self.b, dtype=float)
        self.noise_sigma_mps2 = np.asarray(self.noise_sigma_mps2, dtype=float)
        lo, hi = self.temperature_range_c
        self.temperature_range_c = (float(lo), float(hi))
        _validate(self)

    # ------------------------------------------------------------------ evaluation
    @property
    def degree(self) -> int:
        """Polynomial degree n in temperature."""
        return self.M.shape[0] - 1

    def scaled_temperature(self, temp_c: np.ndarray | float) -> np.ndarray:
        return (np.asarray(temp_c, dtype=float) - self.t_center_c) / self.t_scale_c

    def base_acceleration(self, psi: np.ndarray, temp_c: np.ndarray | float) -> np.ndarray:
        """Eq. 28 without corrections: ``psi`` (N, 3), ``temp_c`` (N,) or scalar -> (N, 3) m/s^2."""
        psi = np.atleast_2d(np.asarray(psi, dtype=float))
        tau = np.broadcast_to(self.scaled_temperature(temp_c), (psi.shape[0],))
        powers = tau[:, None] ** np.arange(self.degree + 1)[None, :]  # (N, n+1)
        m_t = np.einsum("nk,kij->nij", powers, self.M)  # (N, 3, 3)
        b_t = powers @ self.b  # (N, 3)
        return np.einsum("nij,nj->ni", m_t, psi) + b_t

    def coefficients_at(self, temp_c: float) -> tuple[tuple[float, ...], tuple[float, float, float]]:
        """M(T) row-major (9 floats) and b(T) (3 floats, m/s^2) of eq. 28 at one temperature (degC).

        Plain floats, for a caller that evaluates ``M(T) @ psi + b(T)`` one sample at a time without
        numpy (the driver, whose temperature changes in 0.01 degC steps, caches them per reading).
        """
        tau = float(self.scaled_temperature(temp_c))
        powers = tau ** np.arange(self.degree + 1)
        m_t = np.tensordot(powers, self.M, axes=1)
        b_t = powers @ self.b
        return tuple(float(v) for v in m_t.ravel()), (float(b_t[0]), float(b_t[1]), float(b_t[2]))

    def correction_sum(self, ref: np.ndarray, xyz: np.ndarray, psi: np.ndarray, temp_c: np.ndarray, t_s: np.ndarray,
                       state: list[Any]) -> np.ndarray:
        """Sum of the correction terms' contributions (N, 3) in m/s^2 (zeros without terms); ``state`` as in apply_counts."""
        out = np.zeros_like(psi)
        inputs = {"ref": ref, "xyz": xyz, "psi": psi, "temp_c": temp_c, "t_s": np.asarray(t_s, float)}
        for term, term_state in zip(self.corrections, state, strict=True):
            out = out + term.contribution(self, inputs, term_state)
        return out

    def in_range(self, temp_c: float) -> bool:
        lo, hi = self.temperature_range_c
        return lo <= temp_c <= hi

    def new_state(self) -> list[Any]:
        """Fresh streaming state for the stateful correction terms (one entry per term)."""
        return [term.new_state() for term in self.corrections]

    def apply_counts(
        self,
        ref: np.ndarray,
        xyz: np.ndarray,
        temp_c: np.ndarray,
        t_s: np.ndarray,
        state: list[Any] | None = None,
    ) -> np.ndarray:
        """Calibrated specific force (N, 3) in m/s^2 from raw counts.

        ``ref`` (N,) and ``xyz`` (N, 3) are ADC counts, ``temp_c`` (N,) degC, ``t_s`` (N,) board
        time in seconds. ``state`` (from ``new_state``) carries stateful correction terms across
        consecutive calls; pass the same list for consecutive batches of one stream. Samples
        whose reference is below ``MIN_REFERENCE_COUNTS`` give NaN rows (the caller drops them).
        """
        ref = np.asarray(ref, dtype=float)
        xyz = np.atleast_2d(np.asarray(xyz, dtype=float))
        temp_c = np.asarray(temp_c, dtype=float)
        psi = normalise(xyz, ref)
        out = self.base_acceleration(psi, temp_c)
        if self.corrections:
            out = out + self.correction_sum(ref, xyz, psi, temp_c, t_s, self.new_state() if state is None else state)
        return out

    # ------------------------------------------------------------------ file I/O
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "units": dict(UNITS),
            "model": "thermal_polynomial",
            "sensor_id": self.sensor_id,
            "created": self.created or _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "degree": self.degree,
            "temperature_center_c": float(self.t_center_c),
            "temperature_scale_c": float(self.t_scale_c),
            "temperature_range_c": [float(v) for v in self.temperature_range_c],
            "M": [[[float(v) for v in row] for row in mk] for mk in self.M],
            "b": [[float(v) for v in bk] for bk in self.b],
            "noise_sigma_mps2": [float(v) for v in self.noise_sigma_mps2],
            "fit": _plain(self.fit),
            "corrections": [term.to_dict() for term in self.corrections],
        }

    def save(self, path: str | Path) -> None:
        text = "# FBG triaxial accelerometer calibration (paper eq. 28); see docs/calibration_file.md\n"
        text += yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None, width=100)
        Path(path).write_text(text)

    @classmethod
    def from_dict(cls, d: Any, source: str = "<dict>") -> ThermalCalibration:
        def need(key: str) -> Any:
            if key not in d:
                raise CalibrationFileError(f"{source}: missing key '{key}'")
            return d[key]

        if not isinstance(d, dict):
            raise CalibrationFileError(f"{source}: top level is not a mapping")
        if need("format") != FORMAT_NAME:
            raise CalibrationFileError(f"{source}: format is '{d['format']}', expected '{FORMAT_NAME}'")
        version = need("format_version")
        if not isinstance(version, int) or isinstance(version, bool) or version != FORMAT_VERSION:
            raise CalibrationFileError(
                f"{source}: format_version {d['format_version']!r} is not supported (this driver reads {FORMAT_VERSION})"
            )
        units = need("units")
        if not isinstance(units, dict):
            raise CalibrationFileError(f"{source}: 'units' is not a mapping")
        for key, unit in UNITS.items():
            if units.get(key) != unit:
                raise CalibrationFileError(f"{source}: unit of '{key}' is {units.get(key)!r}, expected '{unit}'")
        if need("model") != "thermal_polynomial":
            raise CalibrationFileError(f"{source}: model '{d['model']}' is not supported")
        M_raw, b_raw, rng = need("M"), need("b"), need("temperature_range_c")  # outside the try: keep their message
        try:
            M = np.asarray(M_raw, dtype=float)
            b = np.asarray(b_raw, dtype=float)
            noise = np.asarray(d.get("noise_sigma_mps2", [0.01, 0.01, 0.01]), dtype=float)
        except (TypeError, ValueError, OverflowError) as exc:
            raise CalibrationFileError(f"{source}: coefficients are not numeric arrays ({exc})") from None
        degree = need("degree")
        if not isinstance(degree, int) or isinstance(degree, bool) or degree < 0:
            raise CalibrationFileError(f"{source}: degree must be a non-negative integer, got {degree!r}")
        if M.shape != (degree + 1, 3, 3):
            raise CalibrationFileError(f"{source}: M has shape {M.shape}, expected {(degree + 1, 3, 3)} for degree {degree}")
        if b.shape != (degree + 1, 3):
            raise CalibrationFileError(f"{source}: b has shape {b.shape}, expected {(degree + 1, 3)} for degree {degree}")
        if not (isinstance(rng, list | tuple) and len(rng) == 2):
            raise CalibrationFileError(f"{source}: temperature_range_c must be [min, max]")
        from .correction_terms import correction_from_dict  # local: keeps the import graph flat

        corrections_raw = d.get("corrections") or []
        if not isinstance(corrections_raw, list):
            raise CalibrationFileError(f"{source}: 'corrections' must be a list")
        try:
            corrections = [correction_from_dict(c) for c in corrections_raw]
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise CalibrationFileError(f"{source}: bad correction term: {exc}") from None
        try:
            return cls(
                M=M,
                b=b,
                temperature_range_c=(float(rng[0]), float(rng[1])),
                sensor_id=str(d.get("sensor_id", "unknown")),
                t_center_c=float(d.get("temperature_center_c", 0.0)),
                t_scale_c=float(d.get("temperature_scale_c", 1.0)),
                noise_sigma_mps2=noise,
                created=str(d.get("created", "")),
                fit=dict(d.get("fit") or {}),
                corrections=corrections,
            )
        except (TypeError, ValueError, OverflowError) as exc:
            raise CalibrationFileError(f"{source}: {exc}") from None

    @classmethod
    def load(cls, path: str | Path) -> ThermalCalibration:
        p = Path(path)
        if not p.is_file():
            raise CalibrationFileError(f"{p}: calibration file not found")
        try:
            text = p.read_text()
        except OSError as exc:
            raise CalibrationFileError(f"{p}: calibration file cannot be read ({exc.strerror or exc})") from None
        except UnicodeDecodeError as exc:
            raise CalibrationFileError(f"{p}: not valid YAML ({exc})") from None
        try:
            data = yaml.load(text, Loader=_NoAliasSafeLoader)  # a SafeLoader subclass: no arbitrary objects
        except (yaml.YAMLError, ValueError, TypeError) as exc:  # ValueError: e.g. a date like 2024-13-45
            raise CalibrationFileError(f"{p}: not valid YAML ({exc})") from None
        except RecursionError:
            raise CalibrationFileError(f"{p}: not valid YAML (nested too deeply)") from None
        return cls.from_dict(data, source=str(p))


class _NoAliasSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses aliases (``*name``).

    A few aliased lines can expand into a structure that refers to itself or holds billions of
    elements, which numpy would then try to convert (memory exhaustion); a calibration file never
    needs aliases (``save`` does not write any).
    """

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            raise yaml.composer.ComposerError(
                None, None, "aliases (*name) are not allowed in a calibration file", self.peek_event().start_mark
            )
        return super().compose_node(parent, index)


def normalise(xyz: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Eq. 24: Psi = counts / reference counts, (N, 3). NaN where ref < MIN_REFERENCE_COUNTS."""
    ref = np.asarray(ref, dtype=float)
    safe = np.where(ref >= MIN_REFERENCE_COUNTS, ref, np.nan)
    return np.asarray(xyz, dtype=float) / safe[:, None]


def _validate(cal: ThermalCalibration) -> None:
    if cal.M.ndim != 3 or cal.M.shape[1:] != (3, 3) or cal.M.shape[0] < 1:
        raise ValueError(f"M must have shape (n+1, 3, 3), got {cal.M.shape}")
    if cal.b.shape != (cal.M.shape[0], 3):
        raise ValueError(f"b must have shape {(cal.M.shape[0], 3)}, got {cal.b.shape}")
    if cal.noise_sigma_mps2.shape != (3,):
        raise ValueError(f"noise_sigma_mps2 must have 3 entries, got shape {cal.noise_sigma_mps2.shape}")
    for name, arr in (("M", cal.M), ("b", cal.b), ("noise_sigma_mps2", cal.noise_sigma_mps2)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains NaN or infinite values")
    if np.any(cal.noise_sigma_mps2 < 0):
        raise ValueError("noise_sigma_mps2 must be non-negative")
    lo, hi = cal.temperature_range_c
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"temperature_range_c must be finite [min, max], got {[lo, hi]}")
    if not (math.isfinite(cal.t_scale_c) and cal.t_scale_c > 0 and math.isfinite(cal.t_center_c)):
        raise ValueError("temperature_scale_c must be positive and temperature_center_c finite")


def _plain(obj: Any) -> Any:
    """Convert numpy scalars/arrays inside nested dicts to plain YAML-safe Python types."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
