"""The calibration model and its loader at their edges (fbg_accel_driver.thermal_model; docs/calibration_file.md).

What a user gets that the other tests of the module left unchecked: the defaults of every optional key of a file,
the limits of section 5 at and one past their value, each refusal's whole message, the optional sections
(``coefficient_covariance``, ``slow_error``, ``adc_codes``) written and read back, and the model's values where it has
to hold them (a term that changes its arrays, the extrapolation of fitted terms, the plausibility grid of section 5 and
its corners).
"""

from __future__ import annotations

import locale
import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from test_thermal_model import make_cal, refused, write

from fbg_accel_driver import correction_terms, thermal_model
from fbg_accel_driver.adc_code_table import ADC_CODES, AdcCodeTable
from fbg_accel_driver.coefficient_covariance import CoefficientCovariance
from fbg_accel_driver.correction_terms import TimeDrift
from fbg_accel_driver.slow_error import SlowErrorSection
from fbg_accel_driver.thermal_model import (
    FORMAT_NAME,
    MAX_REFERENCE_LEVELS,
    OUTPUT_MAX_MPS2,
    UNITS,
    CalibrationFileError,
    ThermalCalibration,
    check_plausible,
    migrate,
)

M_SENSOR = 80.0 * np.eye(3)  # m/s^2 per unit Psi: 16x the 5 g span bound over the count range, every axis


def minimal_doc(degree: int = 1) -> dict[str, Any]:
    """A file with the required keys only: M_0 = 80 I, M_1 = 2 I per unit tau, b_0 = -100, b_1 = 0.5 m/s^2."""
    m = np.zeros((degree + 1, 3, 3))
    b = np.zeros((degree + 1, 3))
    m[0], b[0] = M_SENSOR, -100.0
    if degree:
        m[1], b[1] = 2.0 * np.eye(3), 0.5
    return {"format": FORMAT_NAME, "format_version": 1, "units": dict(UNITS), "model": "thermal_polynomial",
            "degree": degree, "M": m.tolist(), "b": b.tolist(), "temperature_range_c": [15.0, 45.0],
            "noise_sigma_mps2": [0.01, 0.01, 0.01]}


def message(doc: Any, source: str = "cal.yaml") -> str:
    """The loader's refusal of the parsed document ``doc``."""
    with pytest.raises(CalibrationFileError) as info:
        ThermalCalibration.from_dict(doc, source=source)
    return str(info.value)


# ----------------------------------------------------------------------------- defaults of the optional keys
def test_a_file_with_the_required_keys_only_is_the_paper_s_eq28_in_degc(tmp_path: Path) -> None:
    """Without ``temperature_center_c`` / ``temperature_scale_c`` the polynomial is in degC itself (centre 0, scale
    1: the paper's eq. 28); without the descriptive keys the calibration is of sensor "unknown", undated, without
    notes, fit figures, terms or optional sections."""
    cal = ThermalCalibration.load(write(tmp_path, minimal_doc()))
    assert (cal.t_center_c, cal.t_scale_c) == (0.0, 1.0)
    assert (cal.sensor_id, cal.created, cal.notes, cal.fit, cal.corrections) == ("unknown", "", "", {}, [])
    assert (cal.dynamic, cal.coefficient_covariance, cal.adc_codes) == (None, None, None)
    np.testing.assert_array_equal(cal.noise_correlated_fraction, np.zeros(3))
    assert cal.reference_level_counts.shape == (0,) and cal.calibration_weights_at(30.0) is None
    # at 30 degC: M = (80 + 30 * 2) I, b = -100 + 30 * 0.5; counts (1000, 500, 0) over a reference of 2000
    np.testing.assert_allclose(cal.apply_counts([2000.0], [[1000.0, 500.0, 0.0]], [30.0], [0.0]),
                               [[140.0 * 0.5 - 85.0, 140.0 * 0.25 - 85.0, -85.0]], rtol=1e-12)


@pytest.mark.parametrize("degree", [0, thermal_model.MAX_DEGREE])
def test_degrees_zero_and_the_maximum_load(degree: int) -> None:
    """Degree 0 (the paper's eq. 25, no temperature terms) and degree 6, the largest of section 5, are accepted."""
    assert ThermalCalibration.from_dict(minimal_doc(degree)).degree == degree


# ----------------------------------------------------------------------------- texts
def test_text_fields_at_their_limits_and_with_control_characters() -> None:
    """A ``sensor_id`` of exactly 256 characters loads; ``notes`` hold more than that, line breaks included (the one
    place for prose); a ``sensor_id`` or ``created`` with an escape sequence or a line break is refused, naming the key
    and showing the value escaped."""
    doc = minimal_doc()
    doc.update(sensor_id="s" * thermal_model.MAX_TEXT_CHARS, notes="first line\nsecond line\n" + "n" * 1000)
    cal = ThermalCalibration.from_dict(doc)
    assert len(cal.sensor_id) == 256 and cal.notes.startswith("first line\nsecond line\n")
    assert message({**doc, "sensor_id": "fbg\x1b[31m01"}) == (
        "cal.yaml: 'sensor_id' 'fbg\\x1b[31m01' holds control characters (escape sequences, line breaks); use printable "
        "characters only")
    assert message({**doc, "created": "2026-11-29\nforged line"}).startswith(
        "cal.yaml: 'created' '2026-11-29\\nforged line' holds control characters")


# ----------------------------------------------------------------------------- the optional sections
def test_a_reference_level_section_is_refused_whole_with_its_message() -> None:
    """Each refusal of ``reference_level`` says what is wrong: a list for the section, one list missing, an entry
    that is no number, a NaN, lists of different lengths or nested, more than 64 levels (64 load)."""
    doc = minimal_doc()

    def with_levels(**section: Any) -> dict[str, Any]:
        return {**doc, "reference_level": section}

    assert message({**doc, "reference_level": []}) == "cal.yaml: 'reference_level' must be a mapping, got list"
    assert message(with_levels(temperature_c=[16.0, 45.0])) == (
        "cal.yaml: missing key 'reference_level.counts' (the section needs both of temperature_c, counts, or none)")
    assert message(with_levels(temperature_c=[16.0, 45.0], counts=[880.0, "x"])) == (
        "cal.yaml: reference_level.counts[1] must be a number, got str 'x'")
    assert message(with_levels(temperature_c=[16.0, math.nan], counts=[880.0, 860.0])) == (
        "cal.yaml: reference_level.temperature_c must be finite and strictly ascending, got [16.0, nan]")
    assert message(with_levels(temperature_c=[16.0, 30.0, 45.0], counts=[880.0, 860.0])) == (
        "cal.yaml: reference_level.temperature_c and .counts must be lists of equal length (at most 64), got shapes "
        "(3,) and (2,)")
    assert "got shapes (2, 1) and (2, 1)" in message(with_levels(temperature_c=[[16.0], [45.0]],
                                                                 counts=[[880.0], [860.0]]))
    temps = np.linspace(-40.0, 85.0, MAX_REFERENCE_LEVELS + 1).tolist()
    cal = ThermalCalibration.from_dict(with_levels(temperature_c=temps[:-1], counts=[870.0] * MAX_REFERENCE_LEVELS))
    assert len(cal.reference_level_counts) == MAX_REFERENCE_LEVELS
    assert "(at most 64), got shapes (65,) and (65,)" in message(with_levels(temperature_c=temps,
                                                                             counts=[870.0] * len(temps)))


def test_noise_correlation_needs_three_entries_in_each_list() -> None:
    doc = {**minimal_doc(), "noise_correlation": {"correlated_fraction": [0.1, 0.1], "time_constant_s": [0.1] * 3}}
    assert message(doc) == (
        "cal.yaml: noise_correlation.correlated_fraction and .time_constant_s must have 3 entries each")


def test_the_expected_reference_counts_are_nan_without_levels() -> None:
    """A file without ``reference_level`` has no reference to expect, at any temperature (the driver then flags no
    reference as off its level), also when asked again (the cached value)."""
    cal = ThermalCalibration.from_dict(minimal_doc())
    assert math.isnan(cal.expected_reference_counts(25.0)) and math.isnan(cal.expected_reference_counts(25.0))


def _covariance(degree: int, seed: int = 0) -> CoefficientCovariance:
    """A dense, positive definite covariance of the 12 (degree + 1) coefficients."""
    n = 12 * (degree + 1)
    a = np.random.default_rng(seed).normal(0.0, 1.0, (n, n))
    return CoefficientCovariance(a @ a.T * 1e-4, "test", 30)


def test_the_covariance_and_the_adc_table_go_through_the_file_s_content() -> None:
    """The two optional sections are written into the file's mapping, read back equal and used: the output
    covariance's weights come from the section (None without it), and counts go through the code table before eq. 24
    (a table whose intervals are 0.3 counts off the nominal codes moves the output)."""
    edges = np.tile(np.arange(ADC_CODES + 1) - 0.2, (4, 1))
    cal = make_cal(degree=1)
    cal.coefficient_covariance, cal.adc_codes = _covariance(1), AdcCodeTable(edges, {"source": "test"})
    back = ThermalCalibration.from_dict(cal.to_dict())  # the file's content without its YAML (4 x 4097 edges)
    assert back == cal and back.coefficient_covariance == cal.coefficient_covariance and back.adc_codes == cal.adc_codes
    weights = back.calibration_weights_at(33.0)
    assert weights is not None and weights == cal.coefficient_covariance.weights_at(33.0, cal.t_center_c, cal.t_scale_c)
    ref, xyz, temp, t = [1000.0, 2000.0], [[500.0, 700.0, 900.0], [1500.0, 100.0, 4000.0]], [30.0, 31.0], [0.0, 0.01]
    plain = make_cal(degree=1)
    mapped = plain.apply_counts(*cal.adc_codes.map_counts(np.array(ref), np.array(xyz)), temp, t)
    np.testing.assert_array_equal(back.apply_counts(ref, xyz, temp, t), mapped)
    assert np.max(np.abs(mapped - plain.apply_counts(ref, xyz, temp, t))) > 1e-3


def test_the_slow_error_goes_through_the_file_s_content_and_is_refused_with_its_message() -> None:
    """The ``slow_error`` section (the bias a still mean carries beyond the noise) is written under its key, read back
    equal, and a file without it has none; a section that breaks its contract is refused naming the file."""
    cal = make_cal(degree=1)
    cal.slow_error = SlowErrorSection(np.diag([1e-3, 2e-3, 3e-3]), "test", 30)
    doc = cal.to_dict()
    assert doc["slow_error"] == cal.slow_error.to_dict()
    back = ThermalCalibration.from_dict(doc)
    assert back == cal and back.slow_error == cal.slow_error
    np.testing.assert_allclose(back.slow_error.sigma_mps2, np.sqrt([1e-3, 2e-3, 3e-3]))
    assert ThermalCalibration.from_dict({k: v for k, v in doc.items() if k != "slow_error"}).slow_error is None
    doc["slow_error"] = {**doc["slow_error"], "visits": 2.5}
    assert message(doc) == "cal.yaml: slow_error.visits must be an integer, got 2.5"


def test_the_optional_sections_are_refused_with_their_messages() -> None:
    """A covariance of a degree-1 model in a file of degree 2 is refused, by the loader as by the constructor; so are
    a covariance section without its keys and a code table that is no mapping."""
    doc = make_cal(degree=2).to_dict()
    doc["coefficient_covariance"] = _covariance(1).to_dict()
    assert "cal.yaml: coefficient_covariance.matrix" in message(doc)
    doc["coefficient_covariance"] = {"format_version": 1}
    assert message(doc) == "cal.yaml: missing key 'coefficient_covariance.method'"
    del doc["coefficient_covariance"]
    assert message({**doc, "adc_codes": [0.5]}).startswith("cal.yaml: 'adc_codes' must be a mapping with edges")
    cal = make_cal(degree=2)
    with pytest.raises(ValueError) as info:
        ThermalCalibration(M=cal.M, b=cal.b, temperature_range_c=(15.0, 45.0), coefficient_covariance=_covariance(1))
    assert str(info.value) == "coefficient_covariance is of degree 1, the model of degree 2"


def test_at_most_32_correction_terms_load() -> None:
    doc = minimal_doc()
    term = {"kind": "channel_offset", "coeff_mps2_counts": [0.0, 0.0, 0.0]}
    assert len(ThermalCalibration.from_dict({**doc, "corrections": [term] * 32}).corrections) == 32
    assert message({**doc, "corrections": [term] * 33}) == "cal.yaml: 33 correction terms, at most 32 are accepted"


# ----------------------------------------------------------------------------- the constructor
def test_the_constructor_names_the_shape_it_expected() -> None:
    with pytest.raises(ValueError) as info:
        ThermalCalibration(M=np.ones((1, 3, 2)), b=np.zeros((1, 3)), temperature_range_c=(0, 1))
    assert str(info.value) == "M must have shape (n+1, 3, 3), got (1, 3, 2)"
    with pytest.raises(ValueError) as info:
        ThermalCalibration(M=np.ones((0, 3, 3)), b=np.zeros((0, 3)), temperature_range_c=(0, 1))
    assert str(info.value) == "M must have shape (n+1, 3, 3), got (0, 3, 3)"
    with pytest.raises(ValueError) as info:
        ThermalCalibration(M=np.ones((2, 3, 3)), b=np.zeros((1, 3)), temperature_range_c=(0, 1))
    assert str(info.value) == "b must have shape (2, 3), got (1, 3)"


def test_integer_values_make_a_float_calibration_with_zero_noise_accepted() -> None:
    """Coefficients typed as integers are held as floats (an adjustment in place keeps its fraction), and a noise of
    exactly zero (a simulated, noise-free sensor) is accepted: only a negative one is refused."""
    cal = ThermalCalibration(M=[[[80, 0, 0], [0, 80, 0], [0, 0, 80]]], b=[[-100, -100, -100]],
                             temperature_range_c=(15, 45), noise_sigma_mps2=[0, 0, 0],
                             reference_level_temperature_c=[20, 40], reference_level_counts=[880, 860])
    cal.M[0, 0, 0] += 0.25
    cal.reference_level_counts[0] += 0.5
    assert cal.M[0, 0, 0] == 80.25 and cal.reference_level_counts[0] == 880.5
    assert check_plausible(cal) == ""


# ----------------------------------------------------------------------------- messages
def test_each_message_names_its_source_and_ends_with_the_reason(tmp_path: Path) -> None:
    """A parsed document without a source is "<dict>"; the messages end where the reason ends."""
    with pytest.raises(CalibrationFileError) as info:
        ThermalCalibration.from_dict([1, 2])
    assert str(info.value) == "<dict>: top level is not a mapping"
    with pytest.raises(CalibrationFileError) as info:
        migrate({"format": FORMAT_NAME})
    assert str(info.value) == "<dict>: missing key 'format_version'"
    assert message({**minimal_doc(), "temperature_scale_c": "warm"}) == (
        "cal.yaml: 'temperature_scale_c' must be a number, got str 'warm'")
    mcap = tmp_path / "run.mcap"
    mcap.write_bytes(thermal_model.MCAP_MAGIC + bytes(range(256)))
    assert refused(mcap).endswith("(or the calibration node's end-of-run fit)")


def test_a_migration_that_does_not_reach_its_version_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(thermal_model, "FORMAT_VERSION", 2)
    monkeypatch.setitem(thermal_model.MIGRATIONS, 1, lambda d: d)  # forgets to set format_version
    with pytest.raises(CalibrationFileError) as info:
        migrate(minimal_doc(), "old.yaml")
    assert str(info.value) == "old.yaml: migration to format_version 2 failed"


# ----------------------------------------------------------------------------- what the loader is given
def test_a_directory_names_the_first_three_calibrations_in_it(tmp_path: Path) -> None:
    for name in ("d.yaml", "a.yaml", "c.yaml", "b.yaml"):
        (tmp_path / name).write_text("x: 1\n")
    assert refused(tmp_path).endswith(
        f"a directory, not a calibration file; the YAML in it: {tmp_path / 'a.yaml'}, {tmp_path / 'b.yaml'}, "
        f"{tmp_path / 'c.yaml'}")


def test_a_fifo_is_named_as_one_and_not_read(tmp_path: Path) -> None:
    fifo = tmp_path / "cal.yaml"
    os.mkfifo(fifo)
    assert refused(fifo).endswith("cal.yaml: a FIFO (named pipe), not a calibration file")


def test_a_file_of_exactly_the_size_bound_loads(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The bound is inclusive: a file of exactly MAX_FILE_BYTES loads, one byte more is refused before parsing (the
    bound lowered to this file's size, so the test does not parse a megabyte)."""
    path = write(tmp_path, minimal_doc())
    size = path.stat().st_size
    monkeypatch.setattr(thermal_model, "MAX_FILE_BYTES", size)
    assert ThermalCalibration.load(path).degree == 1
    monkeypatch.setattr(thermal_model, "MAX_FILE_BYTES", size - 1)
    assert refused(path).endswith(f"file of {size} bytes is above the {size - 1}-byte bound of a calibration file "
                                  "(docs/calibration_file.md, section 5)")


def test_a_utf8_file_loads_under_an_ascii_locale(tmp_path: Path) -> None:
    """The file is UTF-8 whatever the locale the process runs in (here switched to C for the read)."""
    path = tmp_path / "cal.yaml"
    path.write_text(yaml.safe_dump({**minimal_doc(), "notes": "25 \u00b0C"}, allow_unicode=True), encoding="utf-8")
    before = locale.setlocale(locale.LC_CTYPE)
    try:
        locale.setlocale(locale.LC_CTYPE, "C")
        if locale.getencoding().lower().replace("-", "") == "utf8":
            pytest.skip("the C locale of this platform is UTF-8")
        notes = ThermalCalibration.load(path).notes
    finally:
        locale.setlocale(locale.LC_CTYPE, before)
    assert notes == "25 \u00b0C"


# ----------------------------------------------------------------------------- the file written
def test_a_saved_file_is_dated_in_utc_and_has_no_empty_sections(tmp_path: Path) -> None:
    cal = ThermalCalibration.from_dict(minimal_doc())
    cal.noise_time_constant_s = np.full(3, 0.1)  # a time constant alone, no correlated part: white noise
    doc = cal.to_dict()
    assert doc["created"].endswith("+00:00"), doc["created"]
    assert not {"noise_correlation", "reference_level", "coefficient_covariance", "adc_codes", "notes"} & set(doc)


# ----------------------------------------------------------------------------- the model's values
def test_single_precision_inputs_give_the_double_precision_output() -> None:
    """Counts and temperatures given as float32 (a recording's columns) are evaluated as the same values in double
    precision: with a reference dark offset (subtracted from the reference) and at temperatures off the centre."""
    cal = make_cal(degree=2)
    cal.corrections = [correction_terms.ReferenceDarkOffset(12.345)]
    rng = np.random.default_rng(7)
    ref, xyz = rng.integers(800, 4096, 20).astype(np.float32), rng.integers(0, 4096, (20, 3)).astype(np.float32)
    temp = rng.uniform(15.0, 45.0, 20).astype(np.float32)
    t = np.arange(20) * 0.01
    np.testing.assert_array_equal(cal.apply_counts(ref, xyz, temp, t),
                                  cal.apply_counts(ref.astype(float), xyz.astype(float), temp.astype(float), t))
    for got, want in zip(cal.coefficients(temp), cal.coefficients(temp.astype(float)), strict=True):
        np.testing.assert_array_equal(got, want)


class _ReusesItsArray:
    """Test-only term: evaluates eq. 28 at the batch's temperatures + 1 degC, then + 2 degC in the same array changed
    in place, and adds the difference (what a term that reuses a work array sees)."""

    kind = "test_reuses_its_array"

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind}

    def new_state(self) -> None:
        return None

    def contribution(self, cal: ThermalCalibration, inputs: correction_terms.TermInputs, state: None) -> np.ndarray:
        work = inputs.temp_c + 1.0
        first = cal.base_acceleration(inputs.psi, work)
        work += 1.0
        return cal.base_acceleration(inputs.psi, work) - first


def test_a_term_that_changes_its_temperatures_in_place_gets_the_model_at_the_new_ones() -> None:
    cal = make_cal(degree=2)
    cal.corrections = [_ReusesItsArray()]
    ref, xyz, temp = np.full(4, 2000.0), np.full((4, 3), 1000.0), np.array([20.0, 25.0, 30.0, 35.0])
    psi = xyz / ref[:, None]
    expected = (cal.base_acceleration(psi, temp) + cal.base_acceleration(psi, temp + 2.0)
                - cal.base_acceleration(psi, temp + 1.0))
    np.testing.assert_allclose(cal.apply_counts(ref, xyz, temp, np.zeros(4)), expected, rtol=1e-12)


def test_the_extrapolation_of_terms_beyond_their_span_is_added_per_sample() -> None:
    """``correction_sum`` adds to ``extrapolation``, per sample and axis, what each term evaluated beyond its fitted
    board-time span would have added past its edge: 0 inside, creep x time beyond, summed over the terms and on top of
    what the array held (the driver flags those samples)."""
    cal = make_cal(degree=1)
    cal.corrections = [TimeDrift(np.array([0.01, 0.0, -0.02]), np.zeros(3), 1.0, span_s=(0.0, 10.0)),
                       TimeDrift(np.array([0.03, 0.0, 0.0]), np.zeros(3), 1.0, span_s=(0.0, 20.0))]
    n = 3
    ref, xyz, temp, t = np.full(n, 2000.0), np.full((n, 3), 1000.0), np.full(n, 30.0), np.array([5.0, 15.0, 30.0])
    held = np.full((n, 3), 1.0)
    cal.correction_sum(ref, xyz, xyz / ref[:, None], temp, t, cal.new_state(), held)
    np.testing.assert_allclose(held, 1.0 + np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.1], [0.2 + 0.3, 0.0, 0.4]]),
                               rtol=1e-12)


# ----------------------------------------------------------------------------- plausibility at the grid's corners
def test_the_output_bound_holds_at_every_combination_of_dark_and_saturated_channels() -> None:
    """|a| is judged at every combination of 0 (a dark channel: the output is b) and 4095 counts per axis:

    * x reading the difference of two channels, 2000 m/s^2 per unit Psi each: 32 000 m/s^2 (above the bound) only
      with one of them saturated and the other dark, refused;
    * the same with 1100 m/s^2 per unit Psi (17 600 m/s^2 at that corner) loads;
    * b 0.5 m/s^2 beyond the bound, with a gain that brings the output back inside from 1 count on: the dark channel
      is judged, refused;
    * a model within the bound at 4095 counts by 1e-4 of it, and above it at 4096 (no such count): loads."""
    def plausible(m: np.ndarray, b: float = -100.0) -> str:
        return check_plausible(ThermalCalibration(M=m[None], b=np.full((1, 3), b), temperature_range_c=(20.0, 25.0)))

    diff = M_SENSOR.copy()
    diff[0] = [2000.0, -2000.0, 0.0]
    assert "the model gives |a| up to 3.21e+04 m/s^2 inside its calibrated range" in plausible(diff)
    diff[0] = [1100.0, -1100.0, 0.0]
    assert plausible(diff) == ""
    assert "the model gives |a| up to 1.96e+04 m/s^2" in plausible(2100.0 * np.eye(3), -(OUTPUT_MAX_MPS2 + 0.5))
    gain = (OUTPUT_MAX_MPS2 * (1.0 - 1e-4) + 100.0) / (4095.0 / 256.0)  # |M psi + b| at 4095 counts, reference 256
    assert gain * 4096.0 / 256.0 - 100.0 > OUTPUT_MAX_MPS2 * (1.0 + 1e-4)
    assert plausible(gain * np.eye(3)) == ""


def test_a_model_that_overflows_is_refused_without_numpy_warnings() -> None:
    """The plausibility check evaluates absurd models on purpose: its overflows are the finding, said in one line,
    not printed as numpy RuntimeWarnings around it (here M Psi + b: 1.6e308 + 1e308 overflows)."""
    cal = ThermalCalibration(M=1e307 * np.eye(3)[None], b=np.full((1, 3), 1e308), temperature_range_c=(20.0, 25.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_plausible(cal).startswith("the model gives a non-finite acceleration")


def test_an_insensitive_axis_is_shown_with_m_to_four_decimals_on_one_line() -> None:
    m = M_SENSOR.copy()
    m[1, 1] = 0.123456789  # y: 2 m/s^2 over the whole count range
    reason = check_plausible(ThermalCalibration(M=m[None], b=np.full((1, 3), -100.0), temperature_range_c=(20.0, 25.0)))
    assert "along its least sensitive direction y the output changes by at most 1.97 m/s^2" in reason, reason
    assert reason.endswith("(M(T) = [[80.      0.      0.    ] [ 0.      0.1235  0.    ] [ 0.      0.     80.    ]])")


class _Probe:
    """Test-only stateful term: records what it is fed and adds ``gain`` x (1 + the board time in s since its inputs
    last changed) on x, a filter that has not settled (what the hold before judging a grid point is for)."""

    kind = "test_probe"

    def __init__(self, gain: float) -> None:
        self.gain, self.fed = gain, []

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind}

    def new_state(self) -> None:
        return None

    def contribution(self, cal: ThermalCalibration, inputs: correction_terms.TermInputs, state: None) -> np.ndarray:
        self.fed.append((inputs.ref.copy(), inputs.xyz.copy(), inputs.temp_c.copy(), inputs.t_s.copy()))
        rows = np.column_stack([inputs.ref, inputs.xyz, inputs.temp_c])
        changed = np.r_[True, np.any(rows[1:] != rows[:-1], axis=1)]
        since = inputs.t_s - inputs.t_s[np.maximum.accumulate(np.where(changed, np.arange(len(rows)), 0))]
        out = np.zeros((len(rows), 3))
        out[:, 0] = self.gain * (1.0 + since)
        return out


def test_the_plausibility_grid_is_the_documented_one() -> None:
    """docs/calibration_file.md, section 5: reference counts 256, 1024, 2048 and 4095; axis counts 0, 2048 and 4095 on
    each axis (27 combinations, x slowest); 5 temperatures across the calibrated range, then 8 across the AHT10's
    -40..85 degC (its ends first); each grid point held for 0.5 s of 100 Hz samples and judged on its last sample. The
    order is part of it: a thermal lag of tens of seconds has not settled within a point, so which combination meets
    which lagged temperature follows from it."""
    cal = ThermalCalibration(M=M_SENSOR[None], b=np.full((1, 3), -100.0), temperature_range_c=(20.0, 30.0))
    probe = _Probe(0.0)
    cal.corrections = [probe]
    assert check_plausible(cal) == ""
    (ref_in, xyz_in, temp_in, t_in), (_, _, temp_wide, t_wide) = probe.fed
    np.testing.assert_allclose(np.diff(t_in), 0.01, rtol=1e-9)
    np.testing.assert_allclose(t_wide[:3], [0.0, 0.01, 0.02], rtol=1e-9)
    held = np.column_stack([ref_in, xyz_in, temp_in])
    assert np.all(held.reshape(-1, 50, 5) == held[::50, None, :])  # runs of 50 samples
    points = held[::50]
    assert len(points) == 4 * 27 * 5 and len(temp_wide) == 4 * 27 * 8 * 50
    levels = (0.0, 2048.0, 4095.0)
    np.testing.assert_array_equal(points[:27, 1:4], [(x, y, z) for x in levels for y in levels for z in levels])
    np.testing.assert_array_equal(points[:, 1:4], np.tile(points[:27, 1:4], (4 * 5, 1)))
    np.testing.assert_array_equal(points[::27, 0], np.tile([256.0, 1024.0, 2048.0, 4095.0], 5))
    np.testing.assert_allclose(points[::108, 4], [20.0, 22.5, 25.0, 27.5, 30.0], rtol=1e-12)
    np.testing.assert_allclose(temp_wide[::108 * 50], [-40.0, 85.0, -40.0, -15.0, 10.0, 35.0, 60.0, 85.0], rtol=1e-12)
    # judged 0.49 s after each step: 1e6 x 1.49 (eq. 28 adds at most 1.4e3 m/s^2)
    cal.corrections = [_Probe(1e6)]
    assert check_plausible(cal).startswith("the model gives |a| up to 1.49e+06 m/s^2 inside its calibrated range")
