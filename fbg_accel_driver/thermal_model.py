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
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .adc_code_table import AdcCodeTable
from .chain_compensation import ChainDynamics
from .coefficient_covariance import CoefficientCovariance
from .command_line import check_name_text
from .correction_terms import CorrectionTerm, TermInputs, correction_from_dict
from .mapping_fields import format_version, number, number_array, refuse_unknown, same_values
from .sensor_constants import AHT10_SIGMA_C, FULL_SCALE_MPS2
from .slow_error import SlowErrorSection
from .yaml_input import StrictSafeLoader, YamlFileError, file_kind, load_yaml

FORMAT_NAME = "fbg_accel_calibration"
FORMAT_VERSION = 1
UNITS = {"psi": "1", "temperature": "degC", "acceleration": "m/s^2", "time": "s"}
MIN_REFERENCE_COUNTS = 1  # a reference of 0 counts would divide by zero; see normalise()

# The file contract (docs/calibration_file.md, sections 2 and 5): bounds a real calibration is far inside.
TOP_LEVEL_KEYS = ("format", "format_version", "units", "model", "sensor_id", "created", "degree",
                  "temperature_center_c", "temperature_scale_c", "temperature_range_c", "M", "b",
                  "noise_sigma_mps2", "noise_correlation", "reference_level", "dynamic", "fit", "corrections", "notes",
                  "coefficient_covariance", "slow_error", "adc_codes")
NOISE_CORRELATION_KEYS = ("correlated_fraction", "time_constant_s")
REFERENCE_LEVEL_KEYS = ("temperature_c", "counts")
MAX_REFERENCE_LEVELS = 64  # one entry per temperature level of the fit (the paper's campaign has three)
MAX_NOISE_TIME_CONSTANT_S = 100.0  # the TIA low-passes are ~0.1-0.16 s (paper Table 1)
MAX_FILE_BYTES = 1 << 20  # a real file is a few kB; refused before parsing
MCAP_MAGIC = b"\x89MCAP0\r\n"  # first bytes of an MCAP file (mcap.dev spec): a recording, not a calibration
MAX_DEGREE = 6  # the fit tools choose <= 3; beyond 6 the polynomial is noise
MAX_CORRECTIONS = 32
MAX_TEXT_CHARS = 256  # sensor_id, created
MAX_NOTES_CHARS = 65536
TEMPERATURE_LIMITS_C = (-100.0, 200.0)  # range and centre: beyond any climatic chamber and the AHT10 (-40..85)
SCALE_LIMITS_C = (1e-3, 1e3)  # temperature_scale_c
NOISE_MAX_MPS2 = 0.1 * FULL_SCALE_MPS2  # a white noise of a tenth of the full scale: not an accelerometer
OUTPUT_MAX_MPS2 = 100.0 * FULL_SCALE_MPS2  # |a| bound of the plausibility evaluation (section 5)
AHT10_RANGE_C = (-40.0, 85.0)  # the temperatures the driver can ever evaluate the model at
PLAUSIBILITY_REF_COUNTS = (256.0, 1024.0, 2048.0, 4095.0)  # reference counts of the evaluation grid
# least change of the output along any direction over the whole count range (check_plausible): a quarter of the full
# scale (5 g), with a reference of 256 counts (each Psi from 0 to 16, where the sensor's runs give ~4.7); a model
# below it cannot read an eighth of the sensor's +-20 g span whatever the counts
MIN_OUTPUT_SPAN_MPS2 = 0.25 * FULL_SCALE_MPS2
_ARRAY_FIELDS = ("M", "b", "noise_sigma_mps2", "noise_correlated_fraction", "noise_time_constant_s",
                 "reference_level_temperature_c", "reference_level_counts")  # ThermalCalibration's float arrays


class CalibrationFileError(ValueError):
    """A calibration file is missing, malformed or not understood."""


def widened_range(range_c: tuple[float, float], margin_c: float) -> tuple[float, float]:
    """The calibrated temperature range (lo, hi) degC widened by ``margin_c`` degC on each side: what the driver, its
    diagnostics and the offline reports count as inside. The range is the span of the calibration run's own
    readings, each uncertain by the sensor's accuracy, so the same chamber level read later may fall just beyond it."""
    return range_c[0] - margin_c, range_c[1] + margin_c


@dataclass
class ThermalCalibration:
    """Polynomial thermal calibration: ``M`` (n+1, 3, 3) dimensionless, ``b`` (n+1, 3) m/s^2.

    ``temperature_range_c`` is the range the calibration data covered; outside it the model is
    extrapolating. ``noise_sigma_mps2`` is the per-axis white-noise standard deviation of the
    calibrated output at the board's sample rate (m/s^2), used for the IMU covariance.
    ``fit`` holds fit figures (RMSE, held-out RMSE, sample counts, sources) for people to read.
    ``reference_level_temperature_c`` (L,) ascending, degC, and ``reference_level_counts`` (L,) ADC counts: the mean
    reference counts of the fit's samples at each of its temperature levels (optional ``reference_level``; empty
    when absent): eq. 24 cancels the source power only without offsets in the counts, and the detector noise does
    not scale with the power, so the model holds near this level (:meth:`expected_reference_counts`).
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
    corrections: list[CorrectionTerm] = field(default_factory=list)
    notes: str = ""  # free text for people; the only place a file may carry prose
    # noise model (fbg_accel_driver.noise_model): variance fraction of the first-order part and its time
    # constant in s, per axis; zeros = white noise
    noise_correlated_fraction: np.ndarray = field(default_factory=lambda: np.zeros(3))
    noise_time_constant_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    # dynamics of the measuring chain (optional ``dynamic`` section; fbg_accel_driver.chain_compensation)
    dynamic: ChainDynamics | None = None
    # covariance of eq. 28's coefficients (optional ``coefficient_covariance`` section; coefficient_covariance module)
    coefficient_covariance: CoefficientCovariance | None = None
    # the slow error of a pose mean beyond noise and coefficients (optional ``slow_error`` section; slow_error module)
    slow_error: SlowErrorSection | None = None
    # reference counts of the fit's samples per temperature level (optional ``reference_level`` section)
    reference_level_temperature_c: np.ndarray = field(default_factory=lambda: np.zeros(0))
    reference_level_counts: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # the ADC's code-to-value table (optional ``adc_codes`` section; fbg_accel_driver.adc_code_table): counts are
    # mapped to the centres of their codes' intervals before eq. 24; None: counts are used as read
    adc_codes: AdcCodeTable | None = None
    # M(T), b(T) as plain floats per temperature reading (coefficients_at); the coefficients are not
    # changed after construction (a new calibration is a new object, with an empty cache)
    _coef_cache: dict[float, tuple[tuple[float, ...], tuple[float, float, float]]] = field(
        default_factory=dict, init=False, repr=False, compare=False)
    # expected_reference_counts per temperature reading, as _coef_cache
    _ref_level_cache: dict[float, float] = field(default_factory=dict, init=False, repr=False, compare=False)
    # within apply_counts: (temperatures, M(T), b(T)) of the last batch base_acceleration evaluated, () before the
    # first (_coefficients_of); None outside it: nothing is kept between calls
    _last_coefficients: tuple[np.ndarray, np.ndarray, np.ndarray] | tuple[()] | None = field(
        default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in _ARRAY_FIELDS:
            setattr(self, name, np.asarray(getattr(self, name), dtype=float))
        lo, hi = self.temperature_range_c
        self.temperature_range_c = (float(lo), float(hi))
        _validate(self)

    def __eq__(self, other: object) -> bool:
        """Same coefficients and metadata (arrays equal with NaN equal to NaN), same terms (by their file form)."""
        if type(other) is not type(self):
            return NotImplemented
        return (all(np.array_equal(getattr(self, name), getattr(other, name), equal_nan=True)
                    for name in _ARRAY_FIELDS)
                and same_values((self.temperature_range_c, self.sensor_id, self.t_center_c, self.t_scale_c, self.created,
                           self.notes, self.fit, [t.to_dict() for t in self.corrections]),
                          (other.temperature_range_c, other.sensor_id, other.t_center_c, other.t_scale_c, other.created,
                           other.notes, other.fit, [t.to_dict() for t in other.corrections]))
                and self.dynamic == other.dynamic and self.coefficient_covariance == other.coefficient_covariance
                and self.slow_error == other.slow_error
                and self.adc_codes == other.adc_codes)

    __hash__ = None  # type: ignore[assignment]  # mutable, as the dataclass-generated __eq__ made it

    # ------------------------------------------------------------------ evaluation
    @property
    def degree(self) -> int:
        """Polynomial degree n in temperature."""
        return self.M.shape[0] - 1

    def scaled_temperature(self, temp_c: np.ndarray | float) -> np.ndarray:
        return (np.asarray(temp_c, dtype=float) - self.t_center_c) / self.t_scale_c

    def coefficients(self, temp_c: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """M(T) (N, 3, 3) and b(T) (N, 3) m/s^2 of eq. 28 at temperatures ``temp_c`` (N,) or scalar, degC."""
        tau = np.atleast_1d(self.scaled_temperature(temp_c))
        powers = tau[:, None] ** np.arange(self.degree + 1)[None, :]  # (N, n+1)
        return np.einsum("nk,kij->nij", powers, self.M), powers @ self.b

    def base_acceleration(self, psi: np.ndarray, temp_c: np.ndarray | float) -> np.ndarray:
        """Eq. 28 without corrections: ``psi`` (N, 3), ``temp_c`` (N,) or scalar -> (N, 3) m/s^2."""
        psi = np.atleast_2d(np.asarray(psi, dtype=float))
        m_t, b_t = self._coefficients_of(np.broadcast_to(np.asarray(temp_c, dtype=float), (psi.shape[0],)))
        return np.einsum("nij,nj->ni", m_t, psi) + b_t

    def _coefficients_of(self, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``coefficients(temp_c)``; within ``apply_counts``, those of the last array again when it holds the same
        temperatures: the correction terms evaluate the model at one batch's temperatures two or three times (a thermal
        lag before and after, a change of Psi at the lagged temperature). Nothing is kept after ``apply_counts``
        returns (one stream at a time per calibration object, as the driver runs it)."""
        last = self._last_coefficients
        if last is None:  # not within apply_counts
            return self.coefficients(temp_c)
        if last and last[0].shape == temp_c.shape and np.array_equal(last[0], temp_c, equal_nan=True):
            return last[1], last[2]
        self._last_coefficients = ()  # the last batch's let go before this one's are made
        m_t, b_t = self.coefficients(temp_c)
        self._last_coefficients = (np.array(temp_c, copy=True), m_t, b_t)  # a copy: the caller may change its array
        return m_t, b_t

    def coefficients_at(self, temp_c: float) -> tuple[tuple[float, ...], tuple[float, float, float]]:
        """M(T) row-major (9 floats) and b(T) (3 floats, m/s^2) of eq. 28 at one temperature (degC).

        Cached per temperature: the AHT10 reports 0.01 degC steps, so a stream has few distinct values
        (the cache is emptied when it reaches 256 entries).
        """
        coef = self._coef_cache.get(temp_c)
        if coef is None:
            if len(self._coef_cache) >= 256:
                self._coef_cache.clear()
            m_t, b_t = self.coefficients(temp_c)
            coef = self._coef_cache[temp_c] = (tuple(float(v) for v in m_t[0].ravel()),
                                               (float(b_t[0, 0]), float(b_t[0, 1]), float(b_t[0, 2])))
        return coef

    def acceleration_at(self, px: float, py: float, pz: float, temp_c: float) -> tuple[float, float, float]:
        """Eq. 28 without corrections for one sample, in plain floats: ``M(T) Psi + b(T)`` in m/s^2.

        The driver's per-sample path (at its batch sizes numpy's per-call overhead costs more than it
        saves); ``base_acceleration`` is the same model for arrays.
        """
        m, b = self.coefficients_at(temp_c)
        return (m[0] * px + m[1] * py + m[2] * pz + b[0],
                m[3] * px + m[4] * py + m[5] * pz + b[1],
                m[6] * px + m[7] * py + m[8] * pz + b[2])

    def calibration_weights_at(self, temp_c: float) -> tuple[tuple[float, ...], ...] | None:
        """The weights of the calibration's output covariance at ``temp_c`` (degC; cached per reading), for
        ``coefficient_covariance.output_covariance``; None without a ``coefficient_covariance`` section."""
        cov = self.coefficient_covariance
        return None if cov is None else cov.weights_at(temp_c, self.t_center_c, self.t_scale_c)

    def correction_sum(self, ref: np.ndarray, xyz: np.ndarray, psi: np.ndarray, temp_c: np.ndarray, t_s: np.ndarray,
                       state: list[Any], extrapolation: np.ndarray | None = None) -> np.ndarray:
        """Sum of the correction terms' contributions (N, 3) in m/s^2 (zeros without terms); ``state`` as in apply_counts.

        ``extrapolation`` (N, 3), optional: gets added, per sample and axis, the size of what the terms evaluated outside
        their fitted span would have added beyond its edge (``CorrectionTerm.extrapolation``; m/s^2, 0 inside every span)."""
        out = np.zeros_like(psi)
        inputs = TermInputs(ref, xyz, psi, temp_c, np.asarray(t_s, float))
        for term, term_state in zip(self.corrections, state, strict=True):
            if extrapolation is not None:  # on the inputs this term sees (earlier input corrections replace them)
                beyond = term.extrapolation(inputs)
                if beyond is not None:
                    extrapolation += np.abs(beyond)
            out = out + term.contribution(self, inputs, term_state)
        return out

    def expected_reference_counts(self, temp_c: float) -> float:
        """Reference counts (ADC counts) the fit saw at ``temp_c`` (degC): its per-level means, linear in
        temperature between levels, the outer level's beyond them; NaN if the file has none. Cached per temperature
        (the driver asks for every sample, :meth:`coefficients_at`)."""
        level = self._ref_level_cache.get(temp_c)
        if level is None:
            t, c = self.reference_level_temperature_c, self.reference_level_counts
            level = float(np.interp(temp_c, t, c)) if len(t) and math.isfinite(temp_c) else math.nan
            if len(self._ref_level_cache) >= 256:
                self._ref_level_cache.clear()
            self._ref_level_cache[temp_c] = level
        return level

    def in_range(self, temp_c: float | np.ndarray, margin_c: float = AHT10_SIGMA_C) -> bool | np.ndarray:
        """Whether ``temp_c`` (degC; a value or an array, NaN is outside) lies in the calibrated range widened by
        ``margin_c`` (degC, the driver's ``temperature_range_margin_c``; default the AHT10's uncertainty)."""
        lo, hi = widened_range(self.temperature_range_c, margin_c)
        return (temp_c >= lo) & (temp_c <= hi)

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
        if self.adc_codes is not None:
            ref, xyz = self.adc_codes.map_counts(ref, xyz)
        temp_c = np.asarray(temp_c, dtype=float)
        psi = normalise(xyz, ref)
        if not self.corrections:
            return self.base_acceleration(psi, temp_c)
        self._last_coefficients = ()  # the terms evaluate the model at these temperatures again (_coefficients_of)
        try:
            out = self.base_acceleration(psi, temp_c)
            return out + self.correction_sum(ref, xyz, psi, temp_c, t_s, self.new_state() if state is None else state)
        finally:
            self._last_coefficients = None

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
            **({"noise_correlation": {"correlated_fraction": [float(v) for v in self.noise_correlated_fraction],
                                      "time_constant_s": [float(v) for v in self.noise_time_constant_s]}}
               if np.any(self.noise_correlated_fraction > 0) else {}),
            **({"reference_level": {"temperature_c": [float(v) for v in self.reference_level_temperature_c],
                                    "counts": [float(v) for v in self.reference_level_counts]}}
               if len(self.reference_level_counts) else {}),
            **({"dynamic": _plain(self.dynamic.to_dict())} if self.dynamic is not None else {}),
            **({"coefficient_covariance": self.coefficient_covariance.to_dict()}
               if self.coefficient_covariance is not None else {}),
            **({"slow_error": self.slow_error.to_dict()} if self.slow_error is not None else {}),
            "fit": _plain(self.fit),
            "corrections": [term.to_dict() for term in self.corrections],
            **({"notes": self.notes} if self.notes else {}),
            **({"adc_codes": self.adc_codes.to_dict()} if self.adc_codes is not None else {}),
        }

    def save(self, path: str | Path) -> None:
        text = "# FBG triaxial accelerometer calibration (paper eq. 28); see docs/calibration_file.md\n"
        text += yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None, width=100)
        Path(path).write_text(text, encoding="utf-8")

    @classmethod
    def from_dict(cls, d: Any, source: str = "<dict>") -> ThermalCalibration:
        """The calibration of a parsed file (``load``): migrated to the current format version, every key
        known and typed, sizes bounded, and the model evaluated for plausibility (``check_plausible``)."""

        def fail(msg: str) -> CalibrationFileError:
            return CalibrationFileError(f"{source}: {msg}")

        def fail_key(msg: str) -> CalibrationFileError:  # an unknown key is often a note put in the wrong place
            return fail(f"{msg}; free text goes under 'notes'")

        def num(v: Any, key: str) -> float:  # _validate names a non-finite one better
            return number(v, f"'{key}'", fail, finite=False)

        def need(key: str) -> Any:
            if key not in d:
                raise fail(f"missing key '{key}'")
            return d[key]

        if not isinstance(d, dict):
            raise fail("top level is not a mapping")
        if need("format") != FORMAT_NAME:
            raise fail(f"format is '{d['format']}', expected '{FORMAT_NAME}'")
        d = migrate(d, source)
        refuse_unknown(d, TOP_LEVEL_KEYS, "", fail_key)
        units = need("units")
        if not isinstance(units, dict):
            raise fail("'units' is not a mapping")
        for key, unit in UNITS.items():
            if units.get(key) != unit:
                raise fail(f"unit of '{key}' is {units.get(key)!r}, expected '{unit}'")
        if need("model") != "thermal_polynomial":
            raise fail(f"model '{d['model']}' is not supported")
        M_raw, b_raw, rng = need("M"), need("b"), need("temperature_range_c")  # outside the try: keep their message
        noise_raw = need("noise_sigma_mps2")
        degree = need("degree")
        if not isinstance(degree, int) or isinstance(degree, bool) or degree < 0:
            raise fail(f"degree must be a non-negative integer, got {degree!r}")
        if degree > MAX_DEGREE:
            raise fail(f"degree {degree} is above {MAX_DEGREE} (docs/calibration_file.md, section 5)")

        def coefficients_fail(msg: str) -> CalibrationFileError:
            return fail(f"coefficients are not numeric arrays ({msg})")

        M = number_array(M_raw, "M", coefficients_fail, finite=False)  # _validate names a non-finite one
        b = number_array(b_raw, "b", coefficients_fail, finite=False)
        noise = number_array(noise_raw, "noise_sigma_mps2", coefficients_fail, finite=False)
        if M.shape != (degree + 1, 3, 3):
            raise fail(f"M has shape {M.shape}, expected {(degree + 1, 3, 3)} for degree {degree}")
        if b.shape != (degree + 1, 3):
            raise fail(f"b has shape {b.shape}, expected {(degree + 1, 3)} for degree {degree}")
        if not (isinstance(rng, list | tuple) and len(rng) == 2):
            raise fail("temperature_range_c must be [min, max]")
        texts = {key: _text(d, key, MAX_NOTES_CHARS if key == "notes" else MAX_TEXT_CHARS, fail)
                 for key in ("sensor_id", "created", "notes")}
        corr_f, corr_tau = _section(d, "noise_correlation", NOISE_CORRELATION_KEYS, 3, " for white noise", fail, fail_key)
        ref_t, ref_c = _section(d, "reference_level", REFERENCE_LEVEL_KEYS, 0, "", fail, fail_key)
        fit = _optional(d, "fit", {})
        if not isinstance(fit, dict):
            raise fail(f"'fit' must be a mapping of figures, got {type(fit).__name__}")
        dynamic = ChainDynamics.from_dict(d["dynamic"], fail) if "dynamic" in d else None
        coef_cov = (CoefficientCovariance.from_dict(d["coefficient_covariance"], degree, fail)
                    if d.get("coefficient_covariance") is not None else None)
        slow = SlowErrorSection.from_dict(d["slow_error"], fail) if d.get("slow_error") is not None else None
        adc_codes = AdcCodeTable.from_dict(d["adc_codes"], fail) if d.get("adc_codes") is not None else None

        corrections_raw = _optional(d, "corrections", [])
        if not isinstance(corrections_raw, list):
            raise fail("'corrections' must be a list")
        if len(corrections_raw) > MAX_CORRECTIONS:
            raise fail(f"{len(corrections_raw)} correction terms, at most {MAX_CORRECTIONS} are accepted")
        corrections = []
        for i, c in enumerate(corrections_raw):
            where = f"corrections[{i}]"
            if not isinstance(c, dict):
                raise fail(f"{where} must be a mapping with a 'kind', got {type(c).__name__}")
            if not isinstance(c.get("kind"), str):
                raise fail(f"{where}.kind must be a string, got {type(c.get('kind')).__name__}")
            try:
                term = correction_from_dict(c)
            except (KeyError, TypeError, ValueError, OverflowError) as exc:
                raise fail(f"bad correction term: {where}: {exc}") from None
            written = term.to_dict()
            refuse_unknown(c, (*written, "notes"), f"{where}.", fail_key)
            for key, value in c.items():  # the descriptive keys (channels, features, ...) too: they must agree
                if key != "notes" and not _agrees(value, written[key]):
                    raise fail(f"{where}.{key} is {value!r:.80}, but this {term.kind} term is "
                               f"{written[key]!r:.80}: give the value it writes, or leave the key out")
            corrections.append(term)
        try:
            cal = cls(M=M, b=b, temperature_range_c=(num(rng[0], "temperature_range_c"), num(rng[1], "temperature_range_c")),
                      sensor_id=texts["sensor_id"] if "sensor_id" in d else "unknown",
                      t_center_c=num(d.get("temperature_center_c", 0.0), "temperature_center_c"),
                      t_scale_c=num(d.get("temperature_scale_c", 1.0), "temperature_scale_c"),
                      noise_sigma_mps2=noise, created=texts["created"], fit=dict(fit), corrections=corrections,
                      notes=texts["notes"], noise_correlated_fraction=corr_f, noise_time_constant_s=corr_tau,
                      dynamic=dynamic, reference_level_temperature_c=ref_t, reference_level_counts=ref_c,
                      coefficient_covariance=coef_cov, slow_error=slow, adc_codes=adc_codes)
        except (TypeError, ValueError, OverflowError) as exc:
            if isinstance(exc, CalibrationFileError):
                raise
            raise fail(str(exc)) from None
        problem = check_plausible(cal)
        if problem:
            raise fail(problem)
        return cal

    @classmethod
    def load(cls, path: str | Path) -> ThermalCalibration:
        p = Path(path)
        if p.is_dir():  # e.g. the run directory the calibration node writes its YAML into
            found = sorted(str(f) for f in p.glob("*.yaml"))[:3]
            raise CalibrationFileError(f"{p}: a directory, not a calibration file"
                                       + (f"; the YAML in it: {', '.join(found)}" if found else " (no .yaml in it)"))
        kind = file_kind(p)
        if kind is not None:  # also a FIFO or /dev/zero: said, never read
            raise CalibrationFileError(f"{p}: calibration file not found" if kind == "not found"
                                       else f"{p}: {kind}, not a calibration file")
        try:
            size = p.stat().st_size
            if size > MAX_FILE_BYTES:  # before parsing: 100 000 terms took 21.7 s and 658 MB
                raise CalibrationFileError(f"{p}: file of {size} bytes is above the {MAX_FILE_BYTES}-byte bound of a "
                                           "calibration file (docs/calibration_file.md, section 5)")
            text = p.read_text(encoding="utf-8")
        except OSError as exc:
            raise CalibrationFileError(f"{p}: calibration file cannot be read ({exc.strerror or exc})") from None
        except UnicodeDecodeError as exc:
            if exc.object[:len(MCAP_MAGIC)] == MCAP_MAGIC:  # the node writes the run's MCAP beside its YAML: a likely slip
                raise CalibrationFileError(f"{p}: an MCAP recording, not a calibration YAML; a calibration is made from "
                                           f"recordings by `fbg-accel-calib fit {p} ... -o cal.yaml` (or the calibration "
                                           "node's end-of-run fit)") from None
            raise CalibrationFileError(f"{p}: not valid YAML ({exc})") from None
        try:
            data = load_yaml(text, _CalibrationLoader, source=str(p))  # a SafeLoader subclass: no arbitrary objects
        except YamlFileError as exc:
            raise CalibrationFileError(str(exc)) from None
        return cls.from_dict(data, source=str(p))


class _CalibrationLoader(StrictSafeLoader):
    """The project's YAML loader (``fbg_accel_driver.yaml_input``: no arbitrary objects, no aliases, no duplicate
    keys, YAML 1.2 floats). A few aliased lines can expand into a structure that refers to itself or holds billions
    of elements, which numpy would then try to convert (memory exhaustion); a calibration file never needs aliases
    (``save`` does not write any)."""

    document_kind = "a calibration file"


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
    f, tau = cal.noise_correlated_fraction, cal.noise_time_constant_s
    if f.shape != (3,) or tau.shape != (3,):
        raise ValueError("noise_correlation.correlated_fraction and .time_constant_s must have 3 entries each")
    if not (np.all(np.isfinite(f)) and np.all((f >= 0) & (f <= 1))):
        raise ValueError(f"noise_correlation.correlated_fraction must be in 0..1, got {f.tolist()}")
    if not (np.all(np.isfinite(tau)) and np.all((tau >= 0) & (tau <= MAX_NOISE_TIME_CONSTANT_S))):
        raise ValueError(f"noise_correlation.time_constant_s must be in 0..{MAX_NOISE_TIME_CONSTANT_S:g} s, "
                         f"got {tau.tolist()}")
    if np.any((f > 0) & (tau == 0)):
        raise ValueError(f"noise_correlation: a correlated_fraction above 0 needs a time_constant_s above 0 "
                         f"(correlated_fraction {f.tolist()}, time_constant_s {tau.tolist()})")
    rt, rc = cal.reference_level_temperature_c, cal.reference_level_counts
    if rt.ndim != 1 or rc.shape != rt.shape or len(rt) > MAX_REFERENCE_LEVELS:
        raise ValueError(f"reference_level.temperature_c and .counts must be lists of equal length (at most "
                         f"{MAX_REFERENCE_LEVELS}), got shapes {rt.shape} and {rc.shape}")
    if not (np.all(np.isfinite(rt)) and np.all(np.diff(rt) > 0)):
        raise ValueError(f"reference_level.temperature_c must be finite and strictly ascending, got {rt.tolist()}")
    if not (np.all(np.isfinite(rc)) and np.all((rc >= MIN_REFERENCE_COUNTS) & (rc <= 4095))):
        raise ValueError(f"reference_level.counts must be ADC counts in {MIN_REFERENCE_COUNTS}..4095, got {rc.tolist()}")
    if cal.coefficient_covariance is not None and cal.coefficient_covariance.degree != cal.degree:
        raise ValueError(f"coefficient_covariance is of degree {cal.coefficient_covariance.degree}, the model of "
                         f"degree {cal.degree}")
    lo, hi = cal.temperature_range_c
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"temperature_range_c must be finite [min, max], got {[lo, hi]}")
    if not (math.isfinite(cal.t_scale_c) and cal.t_scale_c > 0 and math.isfinite(cal.t_center_c)):
        raise ValueError("temperature_scale_c must be positive and temperature_center_c finite")


# ---------------------------------------------------------------------------- format versions
# MIGRATIONS[v] turns a parsed file of format_version v into one of version v + 1 (a dict -> dict
# function that also sets format_version). Version 1 is the first, so the table is empty; when version
# 2 comes, its step is added here and ``migrate`` reads every older file (docs/calibration_file.md, 3).
MIGRATIONS: dict[int, Callable[[dict[str, Any]], dict[str, Any]]] = {}


def migrate(d: dict[str, Any], source: str = "<dict>") -> dict[str, Any]:
    """A parsed calibration file brought to :data:`FORMAT_VERSION` through :data:`MIGRATIONS`, one version
    at a time. Refuses a version that is not an integer, newer than this reader, or older without a path."""
    def fail(msg: str) -> CalibrationFileError:
        return CalibrationFileError(f"{source}: {msg}")

    def unsupported(version: int) -> str:
        return f"format_version {version} is not supported (this driver reads {FORMAT_VERSION})"

    if "format_version" not in d:
        raise fail("missing key 'format_version'")
    version = format_version(d["format_version"], "format_version", fail, reads=FORMAT_VERSION, exact=False)
    if version < 1:
        raise fail(unsupported(version))
    if version > FORMAT_VERSION:
        raise fail(f"{unsupported(version)}; the file is newer than this driver: update fbg_accel_driver")
    while version < FORMAT_VERSION:
        step = MIGRATIONS.get(version)
        if step is None:
            raise fail(unsupported(version))
        d = step(dict(d))
        version += 1
        if d.get("format_version") != version:
            raise fail(f"migration to format_version {version} failed")
    return d


def check_plausible(cal: ThermalCalibration) -> str:
    """Why ``cal`` cannot describe this sensor, or ``""``. Bounds (docs/calibration_file.md, section 5):

    * temperature range and centre within :data:`TEMPERATURE_LIMITS_C`, scale within :data:`SCALE_LIMITS_C`;
    * every ``noise_sigma_mps2`` at most :data:`NOISE_MAX_MPS2` (its square must be a usable variance);
    * the model (eq. 28 and every correction term) evaluated on a grid of inputs: reference counts
      :data:`PLAUSIBILITY_REF_COUNTS`, axis counts at 0, 2048 and 4095 (27 combinations), temperatures
      across the calibrated range and across the AHT10 range :data:`AHT10_RANGE_C`. The output must be
      finite everywhere the driver can evaluate it (AHT10 range), and at most :data:`OUTPUT_MAX_MPS2` in
      magnitude inside the calibrated range. Each grid point is held for 0.5 s of samples at 100 Hz so
      that stateful terms (filters) are judged on their settled output, not on the steps between points;
    * at 5 temperatures across the calibrated range, the output's change along ``M(T)``'s least sensitive direction
      over the whole 12-bit range of the counts (each Psi from 0 to 4095 / 256, the lowest reference of the grid:
      its smallest singular value times 16) at least :data:`MIN_OUTPUT_SPAN_MPS2`. A zero row or column, dependent
      rows, or M = 1e-6 I cannot read the sensor's range; a real sensor's is 25x above the bound (``M`` of paper
      section 3.6: smallest singular value 77 m/s^2 per unit Psi, 1230 m/s^2 over the range).
    """
    lo_lim, hi_lim = TEMPERATURE_LIMITS_C
    lo, hi = cal.temperature_range_c
    if not (lo_lim <= lo <= hi <= hi_lim):
        return f"temperature_range_c {[lo, hi]} is outside {list(TEMPERATURE_LIMITS_C)} degC"
    if not lo_lim <= cal.t_center_c <= hi_lim:
        return f"temperature_center_c {cal.t_center_c} is outside {list(TEMPERATURE_LIMITS_C)} degC"
    if not SCALE_LIMITS_C[0] <= cal.t_scale_c <= SCALE_LIMITS_C[1]:
        return f"temperature_scale_c {cal.t_scale_c} is outside {list(SCALE_LIMITS_C)} degC"
    if np.any(cal.noise_sigma_mps2 > NOISE_MAX_MPS2):
        return f"noise_sigma_mps2 {cal.noise_sigma_mps2.tolist()} is above {NOISE_MAX_MPS2:.3g} m/s^2 (a tenth of full scale)"
    levels = np.array([0.0, 2048.0, 4095.0])
    xyz = np.stack(np.meshgrid(levels, levels, levels, indexing="ij"), axis=-1).reshape(-1, 3)
    ref = np.repeat(np.asarray(PLAUSIBILITY_REF_COUNTS), len(xyz))
    xyz = np.tile(xyz, (len(PLAUSIBILITY_REF_COUNTS), 1))
    inside = np.unique(np.linspace(lo, hi, 5))
    wide = np.array([AHT10_RANGE_C[0], AHT10_RANGE_C[1], *np.linspace(*AHT10_RANGE_C, 6)])
    with np.errstate(all="ignore"):
        for temps, bounded in ((inside, True), (wide, False)):
            out = _evaluate_grid(cal, ref, xyz, temps)
            if not np.all(np.isfinite(out)):
                return ("the model gives a non-finite acceleration at temperatures the driver can read "
                        f"({AHT10_RANGE_C[0]:g}..{AHT10_RANGE_C[1]:g} degC) and 12-bit counts: every such sample would "
                        "be dropped (coefficients, temperature scaling or a correction term out of range)")
            if bounded and np.max(np.abs(out)) > OUTPUT_MAX_MPS2:
                return (f"the model gives |a| up to {np.max(np.abs(out)):.3g} m/s^2 inside its calibrated range, above "
                        f"{OUTPUT_MAX_MPS2:.3g} (100x the +-20 g full scale): coefficients are absurd")
    return _insensitive(cal, inside)


def _insensitive(cal: ThermalCalibration, temps: np.ndarray) -> str:
    """Why M(T) cannot read the sensor's range at some temperature of ``temps`` (degC), or ``""``: the output's
    change over the whole 12-bit count range, along its least sensitive direction, below :data:`MIN_OUTPUT_SPAN_MPS2`
    (see :func:`check_plausible`). Judged by size, not by a scale-free rank: 1e-6 I has rank 3."""
    psi_span = 4095.0 / PLAUSIBILITY_REF_COUNTS[0]  # each Psi over its whole range at the lowest reference of the grid
    with np.errstate(all="ignore"):
        m_t = cal.coefficients(temps)[0]
        for t, m in zip(temps, m_t, strict=True):
            if not np.all(np.isfinite(m)):
                return f"M at {t:g} degC is not finite"
            u, s, _ = np.linalg.svd(m)
            span = float(s[-1]) * psi_span
            if not span >= MIN_OUTPUT_SPAN_MPS2:
                weak = u[:, -1] * np.sign(u[np.argmax(np.abs(u[:, -1])), -1])
                axis = int(np.argmax(np.abs(weak)))
                where = "xyz"[axis] if abs(weak[axis]) > 0.99 else "(" + ", ".join(f"{v:.2f}" for v in weak) + ")"
                return (f"M at {t:g} degC: along its least sensitive direction {where} the output changes by at most "
                        f"{span:.3g} m/s^2 over the whole 12-bit range of the counts (reference "
                        f"{PLAUSIBILITY_REF_COUNTS[0]:g} counts), below {MIN_OUTPUT_SPAN_MPS2:.3g} m/s^2 (5 g, an eighth "
                        "of the sensor's +-20 g span): a zero row or column, dependent rows, or coefficients in the wrong unit "
                        f"(M(T) = {np.array2string(m, precision=4, max_line_width=1000).replace(chr(10), '')})")
    return ""


def _evaluate_grid(cal: ThermalCalibration, ref: np.ndarray, xyz: np.ndarray, temps: np.ndarray) -> np.ndarray:
    """Settled outputs (P*len(temps), 3) of ``cal`` for every (count point, temperature), see check_plausible."""
    hold = 50 if cal.corrections else 1  # 0.5 s at 100 Hz settles the filters of the terms
    n = len(ref) * len(temps)
    ref_s = np.repeat(np.tile(ref, len(temps)), hold)
    xyz_s = np.repeat(np.tile(xyz, (len(temps), 1)), hold, axis=0)
    t_s = np.repeat(np.repeat(temps, len(ref)), hold)
    time_s = np.arange(n * hold) * 0.01
    return cal.apply_counts(ref_s, xyz_s, t_s, time_s)[hold - 1::hold]


def _optional(d: dict[str, Any], key: str, default: Any) -> Any:
    """``d[key]``, or ``default`` when it is absent or null (an empty ``key:`` line); any other value, also an empty
    container of the wrong type, is returned for the caller's type check."""
    v = d.get(key)
    return default if v is None else v


def _section(d: dict[str, Any], name: str, keys: tuple[str, str], absent_len: int, none_means: str,
             fail: Callable[[str], CalibrationFileError], fail_key: Callable[[str], CalibrationFileError],
             ) -> tuple[np.ndarray, np.ndarray]:
    """The two number lists of an optional section (``noise_correlation``, ``reference_level``); zeros of
    ``absent_len`` when it is absent. A section is given whole: a missing list is not read as zeros."""
    section = _optional(d, name, {})
    if not isinstance(section, dict):
        raise fail(f"'{name}' must be a mapping, got {type(section).__name__}")
    refuse_unknown(section, keys, f"{name}.", fail_key)
    if not section:
        return np.zeros(absent_len), np.zeros(absent_len)
    for key in keys:
        if key not in section:
            raise fail(f"missing key '{name}.{key}' (the section needs both of {', '.join(keys)}, or none{none_means})")
    first, second = (number_array(section[key], f"{name}.{key}", fail, finite=False) for key in keys)
    return first, second


def _agrees(value: Any, written: Any) -> bool:
    """Whether a correction term's key as the file gives it is what the term writes: numbers (nested lists too) equal
    to 1e-9 relative (a hand-computed ``group_delay_s``), anything else (text, lists of names) exactly."""
    try:
        a = number_array(value, "", ValueError)
        w = np.asarray(written, dtype=float)
    except (TypeError, ValueError):
        return bool(value == written)
    return a.shape == w.shape and bool(np.allclose(a, w, rtol=1e-9, atol=1e-15))


def _text(d: dict[str, Any], key: str, max_chars: int, fail: Callable[[str], CalibrationFileError]) -> str:
    v = d.get(key, "")
    if v is None:
        v = ""
    if not isinstance(v, str):
        raise fail(f"'{key}' must be a string, got {type(v).__name__} {v!r:.40} (quote it in the YAML)")
    if len(v) > max_chars:
        raise fail(f"'{key}' has {len(v)} characters, at most {max_chars} are accepted")
    if key != "notes":  # echoed by the driver and the tools: no escape sequence, no line break
        try:
            check_name_text(v, f"'{key}'")
        except ValueError as exc:
            raise fail(str(exc)) from None
    return v


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
