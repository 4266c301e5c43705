"""Tests of the thermal calibration model and its YAML file (fbg_accel_driver.thermal_model).

Covers: eq. 24 normalisation and eq. 28 evaluation against a plain-loop reference, the equivalence
of the centred/scaled parametrisation with the paper's raw polynomial in degC, save/load round
trip, and every refusal of the loader with its message (docs/calibration_file.md).
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from fbg_accel_driver import correction_terms
from fbg_accel_driver.thermal_model import (
    FORMAT_NAME,
    FORMAT_VERSION,
    UNITS,
    CalibrationFileError,
    ThermalCalibration,
    normalise,
)


def make_cal(degree: int = 2, center: float = 25.0, scale: float = 10.0, seed: int = 3) -> ThermalCalibration:
    rng = np.random.default_rng(seed)
    M = rng.normal(0.0, 0.2, (degree + 1, 3, 3))
    M[0] += np.diag([9.0, -8.5, 10.2])  # m/s^2 per unit Psi: a realistic leading term
    b = rng.normal(0.0, 0.3, (degree + 1, 3))
    return ThermalCalibration(
        M=M,
        b=b,
        temperature_range_c=(14.5, 46.0),
        sensor_id="fbg-sim-001",
        t_center_c=center,
        t_scale_c=scale,
        noise_sigma_mps2=np.array([0.011, 0.012, 0.013]),
        created="2026-11-21T12:00:00+00:00",
        fit={"rmse_mps2": [0.001, 0.002, 0.003], "n_samples": 1800, "source": "unit test"},
    )


def reference_eq28(cal: ThermalCalibration, ref: np.ndarray, xyz: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
    """Eq. 24 + eq. 28 with plain loops, independent of the vectorised implementation."""
    out = np.zeros((len(ref), 3))
    for i in range(len(ref)):
        psi = xyz[i] / ref[i]
        tau = (temp_c[i] - cal.t_center_c) / cal.t_scale_c
        acc = np.zeros(3)
        for k in range(cal.degree + 1):
            acc += (cal.M[k] @ psi) * tau**k + cal.b[k] * tau**k
        out[i] = acc
    return out


def to_raw_parametrisation(cal: ThermalCalibration) -> ThermalCalibration:
    """Expand sum_k M_k ((T - c)/s)^k into the paper's sum_j M'_j T^j (binomial theorem), same for b."""
    c, s, n = cal.t_center_c, cal.t_scale_c, cal.degree
    M_raw = np.zeros_like(cal.M)
    b_raw = np.zeros_like(cal.b)
    for k in range(n + 1):
        for j in range(k + 1):
            w = math.comb(k, j) * (-c) ** (k - j) / s**k
            M_raw[j] += w * cal.M[k]
            b_raw[j] += w * cal.b[k]
    return ThermalCalibration(M=M_raw, b=b_raw, temperature_range_c=cal.temperature_range_c, t_center_c=0.0, t_scale_c=1.0)


def counts_batch(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ref = rng.integers(1500, 4096, n).astype(float)
    xyz = rng.integers(0, 4096, (n, 3)).astype(float)
    temp = rng.uniform(10.0, 50.0, n)
    t_s = np.arange(n) * 0.01
    return ref, xyz, temp, t_s


# ----------------------------------------------------------------------------- evaluation
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_apply_counts_matches_eq28_reference(degree: int) -> None:
    cal = make_cal(degree=degree)
    ref, xyz, temp, t_s = counts_batch(200)
    got = cal.apply_counts(ref, xyz, temp, t_s)
    assert got.shape == (200, 3)
    np.testing.assert_allclose(got, reference_eq28(cal, ref, xyz, temp), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_one_sample_in_plain_floats_gives_eq28(degree: int) -> None:
    """``acceleration_at`` (the driver's per-sample path) reproduces eq. 28 sample by sample, in plain floats."""
    cal = make_cal(degree=degree)
    ref, xyz, temp, _ = counts_batch(20)
    for i in range(20):
        psi = xyz[i] / ref[i]
        got = cal.acceleration_at(*(float(v) for v in psi), float(temp[i]))
        assert all(type(v) is float for v in got)
        np.testing.assert_allclose(got, reference_eq28(cal, ref[i:i + 1], xyz[i:i + 1], temp[i:i + 1])[0], rtol=1e-12, atol=1e-12)


def test_per_temperature_cache_is_the_objects_own() -> None:
    """The cached M(T), b(T) belong to one calibration: a replaced calibration starts empty, and the
    cache stays bounded over a long stream of distinct readings."""
    cal = make_cal(degree=2)
    first = cal.acceleration_at(0.1, 0.2, 0.3, 30.0)
    b = cal.b.copy()
    b[0] += 1.0  # b(T) = sum_k b_k tau^k: the constant term moves every axis by 1 m/s^2
    other = replace(cal, b=b)
    np.testing.assert_allclose(other.acceleration_at(0.1, 0.2, 0.3, 30.0), np.add(first, 1.0), rtol=1e-12)
    assert cal.acceleration_at(0.1, 0.2, 0.3, 30.0) == first
    for k in range(1000):
        cal.coefficients_at(20.0 + 0.01 * k)
    assert len(cal._coef_cache) <= 256


def test_the_model_at_a_batchs_temperatures_is_worked_out_once_per_call_and_not_kept(monkeypatch) -> None:
    """Within apply_counts a thermal lag asks for the model at the batch's temperatures before and after: M(T), b(T)
    are worked out once for each set of temperatures, nothing is kept after the call, and temperatures changed in the
    caller's array are new ones (the same output as a fresh calibration)."""
    def with_lag() -> ThermalCalibration:
        cal = make_cal()
        cal.corrections = [correction_terms.ThermalLag(30.0)]
        return cal

    cal, fresh = with_lag(), with_lag()
    rng = np.random.default_rng(0)
    ref, xyz = rng.uniform(2000.0, 3000.0, 50), rng.uniform(500.0, 1500.0, (50, 3))
    temp, t = rng.uniform(10.0, 40.0, 50), np.arange(50) * 0.01
    calls = []
    real = ThermalCalibration.coefficients
    monkeypatch.setattr(ThermalCalibration, "coefficients", lambda self, tc: calls.append(1) or real(self, tc))
    first = cal.apply_counts(ref, xyz, temp, t)
    assert len(calls) == 2  # the recorded temperatures (eq. 28 and the lag's before), the lagged ones
    assert cal._last_coefficients is None
    cal.base_acceleration(xyz / ref[:, None], temp)
    cal.base_acceleration(xyz / ref[:, None], temp)
    assert len(calls) == 4  # outside apply_counts every call works it out
    temp += 5.0  # the caller's array changed in place
    again = cal.apply_counts(ref, xyz, temp, t)
    np.testing.assert_array_equal(again, fresh.apply_counts(ref, xyz, temp, t))
    assert not np.array_equal(again, first)


def test_base_acceleration_broadcasts_scalar_temperature() -> None:
    cal = make_cal()
    psi = np.array([[0.3, 0.4, 0.5], [0.1, 0.2, 0.9]])
    np.testing.assert_allclose(cal.base_acceleration(psi, 30.0), cal.base_acceleration(psi, np.array([30.0, 30.0])))


def test_degree_zero_is_the_linear_model_eq25() -> None:
    """n = 0: a = M_0 Psi + b_0, independent of temperature (paper eq. 25)."""
    cal = make_cal(degree=0)
    psi = np.array([[0.2, 0.5, 0.7]])
    expected = cal.M[0] @ psi[0] + cal.b[0]
    for temp in (-40.0, 0.0, 85.0):
        np.testing.assert_allclose(cal.base_acceleration(psi, temp)[0], expected, rtol=1e-12)


@pytest.mark.parametrize("degree", [1, 2, 4])
def test_centred_scaled_model_equals_paper_eq28_in_degc(degree: int) -> None:
    cal = make_cal(degree=degree, center=27.5, scale=15.5)
    raw = to_raw_parametrisation(cal)
    ref, xyz, temp, t_s = counts_batch(300, seed=7)
    np.testing.assert_allclose(cal.apply_counts(ref, xyz, temp, t_s), raw.apply_counts(ref, xyz, temp, t_s), rtol=1e-9, atol=1e-9)
    # and the raw form is literally sum_k M_k T^k Psi + sum_k b_k T^k
    psi = xyz / ref[:, None]
    lit = sum(raw.M[k] @ psi[0] * temp[0] ** k + raw.b[k] * temp[0] ** k for k in range(degree + 1))
    np.testing.assert_allclose(cal.apply_counts(ref[:1], xyz[:1], temp[:1], t_s[:1])[0], lit, rtol=1e-9)


def test_zero_or_negative_reference_gives_nan_row_not_an_exception() -> None:
    cal = make_cal()
    ref = np.array([3000.0, 0.0, -5.0, 2500.0])
    xyz = np.full((4, 3), 1200.0)
    temp = np.full(4, 25.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no divide-by-zero RuntimeWarning either
        out = cal.apply_counts(ref, xyz, temp, np.zeros(4))
        psi = normalise(xyz, ref)
    assert np.all(np.isnan(out[1])) and np.all(np.isnan(out[2]))
    assert np.all(np.isfinite(out[[0, 3]]))
    assert np.all(np.isnan(psi[1])) and np.all(np.isfinite(psi[0]))
    np.testing.assert_allclose(psi[0], xyz[0] / 3000.0)


def test_in_range_and_degree() -> None:
    cal = make_cal(degree=3)
    assert cal.degree == 3
    assert cal.in_range(14.5, 0.0) and cal.in_range(46.0, 0.0) and cal.in_range(30.0, 0.0)
    assert not cal.in_range(14.49, 0.0) and not cal.in_range(46.01, 0.0)
    # by default the AHT10's uncertainty (the driver's temperature_range_margin_c default) counts as inside
    np.testing.assert_array_equal(cal.in_range(np.array([14.2, 14.19, 46.3, 46.31, np.nan])),
                                  [True, False, True, False, False])
    assert cal.new_state() == []


# ----------------------------------------------------------------------------- file round trip
def test_save_load_round_trip_is_exact(tmp_path: Path) -> None:
    cal = make_cal(degree=3)
    path = tmp_path / "cal.yaml"
    cal.save(path)
    text = path.read_text()
    assert text.startswith("#")
    doc = yaml.safe_load(text)
    assert (doc["format"], doc["format_version"], doc["units"]) == (FORMAT_NAME, FORMAT_VERSION, UNITS)
    back = ThermalCalibration.load(path)
    np.testing.assert_array_equal(back.M, cal.M)
    np.testing.assert_array_equal(back.b, cal.b)
    np.testing.assert_array_equal(back.noise_sigma_mps2, cal.noise_sigma_mps2)
    assert back.temperature_range_c == cal.temperature_range_c
    assert (back.t_center_c, back.t_scale_c, back.sensor_id, back.created) == (25.0, 10.0, "fbg-sim-001", cal.created)
    assert back.fit == cal.fit
    ref, xyz, temp, t_s = counts_batch(50)
    np.testing.assert_array_equal(back.apply_counts(ref, xyz, temp, t_s), cal.apply_counts(ref, xyz, temp, t_s))


def test_save_converts_numpy_values_in_fit(tmp_path: Path) -> None:
    cal = make_cal()
    cal.fit = {"rmse": np.float64(0.5), "per_axis": np.array([1.0, 2.0, 3.0]), "n": np.int64(7), 3: "int key"}
    cal.save(tmp_path / "c.yaml")
    back = ThermalCalibration.load(tmp_path / "c.yaml")
    assert back.fit == {"rmse": 0.5, "per_axis": [1.0, 2.0, 3.0], "n": 7, "3": "int key"}


def test_created_is_stamped_when_empty(tmp_path: Path) -> None:
    cal = make_cal()
    cal.created = ""
    cal.save(tmp_path / "c.yaml")
    assert ThermalCalibration.load(tmp_path / "c.yaml").created.startswith("20")


class _CountingOffset:
    """Test-only correction term: adds offset * (number of samples seen before) on x; stateful."""

    kind = "test_counting_offset"

    def __init__(self, offset: float) -> None:
        self.offset = offset

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "offset_mps2": self.offset}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> _CountingOffset:
        return cls(float(d["offset_mps2"]))

    def new_state(self) -> dict[str, int]:
        return {"seen": 0}

    def contribution(self, cal: ThermalCalibration, inputs: correction_terms.TermInputs, state: dict[str, int]) -> np.ndarray:
        n = len(inputs.ref)
        out = np.zeros((n, 3))
        out[:, 0] = self.offset * (state["seen"] + np.arange(n))
        state["seen"] += n
        return out


def test_correction_terms_round_trip_and_carry_state(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(correction_terms.CORRECTION_TYPES, _CountingOffset.kind, _CountingOffset)
    cal = make_cal()
    cal.corrections = [_CountingOffset(0.5)]
    cal.save(tmp_path / "c.yaml")
    back = ThermalCalibration.load(tmp_path / "c.yaml")
    assert [c.to_dict() for c in back.corrections] == [{"kind": "test_counting_offset", "offset_mps2": 0.5}]
    ref, xyz, temp, t_s = counts_batch(10)
    whole = back.apply_counts(ref, xyz, temp, t_s)
    state = back.new_state()
    parts = np.vstack(
        [
            back.apply_counts(ref[:4], xyz[:4], temp[:4], t_s[:4], state),
            back.apply_counts(ref[4:], xyz[4:], temp[4:], t_s[4:], state),
        ]
    )
    np.testing.assert_allclose(parts, whole)
    np.testing.assert_allclose(whole[:, 0] - back.base_acceleration(xyz / ref[:, None], temp)[:, 0], 0.5 * np.arange(10))


# ----------------------------------------------------------------------------- loader refusals
@pytest.fixture()
def good_doc() -> dict[str, Any]:
    return make_cal(degree=2).to_dict()


def write(tmp_path: Path, doc: Any, raw: str | None = None) -> Path:
    """``tmp_path``/cal.yaml holding ``doc`` as YAML, or the text ``raw``."""
    path = tmp_path / "cal.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False) if raw is None else raw)
    return path


def refused(path: Path) -> str:
    with pytest.raises(CalibrationFileError) as info:
        ThermalCalibration.load(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: "), msg  # every message names the file
    return msg


def test_good_doc_loads(tmp_path: Path, good_doc: dict[str, Any]) -> None:
    assert ThermalCalibration.load(write(tmp_path, good_doc)).degree == 2


def test_a_missing_file_is_refused(tmp_path: Path) -> None:
    assert refused(tmp_path / "nope.yaml").endswith("calibration file not found")


def test_a_directory_is_refused_naming_the_calibrations_in_it(tmp_path: Path, good_doc: dict[str, Any]) -> None:
    """A run directory given for the calibration file (the calibration node writes its YAML inside one) was
    answered "calibration file not found", which sends the user looking for a missing file; it is said to be a
    directory, and the YAML files in it are named."""
    run = tmp_path / "run1"
    run.mkdir()
    assert refused(run).endswith("a directory, not a calibration file (no .yaml in it)")
    write(run, good_doc)
    (run / "notes.txt").write_text("x")
    assert refused(run).endswith(f"a directory, not a calibration file; the YAML in it: {run / 'cal.yaml'}")


def test_unreadable_file(tmp_path: Path, good_doc: dict[str, Any], monkeypatch: pytest.MonkeyPatch) -> None:
    path = write(tmp_path, good_doc)

    def deny(self: Path, *args: Any, **kwargs: Any) -> str:
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "read_text", deny)  # running as root: chmod 000 would not stop the read
    assert "calibration file cannot be read (Permission denied)" in refused(path)


@pytest.mark.parametrize(
    "content,message",
    [(b"M: [1, 2\nb: {", "not valid YAML"), (b"\xff\xfe\x00binary\x00", "not valid YAML"),
     (b"key: value\n  bad indent: [", "not valid YAML"), (b"a: " + b"[" * 3000 + b"]" * 3000, "not valid YAML"),
     *((text, "top level is not a mapping") for text in (b"", b"just a string\n", b"- 1\n- 2\n", b"42\n"))],
    ids=["unclosed", "binary", "indent", "nested_too_deeply", "empty", "string", "list", "number"],
)
def test_a_file_that_is_no_yaml_mapping_is_refused(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "cal.yaml"
    path.write_bytes(content)
    assert message in refused(path)


def test_a_recording_given_for_the_calibration_says_so(tmp_path: Path) -> None:
    """The calibration node writes the run's MCAP beside its calibration YAML, so giving the recording where the YAML
    belongs is a likely slip. Before: "not valid YAML ('utf-8' codec can't decode byte 0x89 in position 0: invalid
    start byte)". After: what the file is and how to make a calibration from it."""
    path = tmp_path / "acc4_L0.mcap"
    path.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 4)  # the MCAP magic, then binary records
    msg = refused(path)
    assert "an MCAP recording, not a calibration YAML" in msg and "fbg-accel-calib fit" in msg, msg


_DELETE = object()  # the field is left out
_GOOD_2 = make_cal(degree=2).to_dict()  # the shapes and values the bad fields below are made from
_M3x2 = [[row[:2] for row in mk] for mk in _GOOD_2["M"]]
_RAGGED = [_GOOD_2["M"][0], [*_GOOD_2["M"][1][:2], [1.0, 2.0]], _GOOD_2["M"][2]]
_NAN, _INF = float("nan"), float("inf")
_FIELD_REFUSALS = [  # (path into the document, value, end of the message; '...' ends a message cut short here)
    *(((key,), _DELETE, f"missing key '{key}'") for key in ("format", "format_version", "units", "model", "M", "b",
                                                             "temperature_range_c", "degree", "noise_sigma_mps2")),
    (("format",), "imu_calibration", "format is 'imu_calibration', expected 'fbg_accel_calibration'"),
    *((("format_version",), v, f"format_version {v!r} is not supported (this driver reads 1)...")
      for v in (2, 0, "1", True, 1.0, None, 1.5)),
    *((("units", key), bad, f"unit of '{key}' is {None if bad is _DELETE else bad!r}, expected '{UNITS[key]}'")
      for key, bad in (("acceleration", "g"), ("temperature", "K"), ("psi", "counts"), ("time", _DELETE))),
    (("units",), ["m/s^2"], "'units' is not a mapping"),
    (("model",), "neural_net", "model 'neural_net' is not supported"),
    (("M",), _M3x2, "M has shape (3, 3, 2), expected (3, 3, 3) for degree 2"),
    (("b",), [[*bk, 0.0] for bk in _GOOD_2["b"]], "b has shape (3, 4), expected (3, 3) for degree 2"),
    (("b",), _GOOD_2["b"][:2], "b has shape (2, 3), expected (3, 3) for degree 2"),
    (("M",), _RAGGED, "coefficients are not numeric arrays (M is not a numeric array..."),
    *((("degree",), d, f"M has shape (3, 3, 3), expected ({d + 1}, 3, 3) for degree {d}") for d in (1, 3)),
    *((("degree",), d, f"degree must be a non-negative integer, got {d!r}") for d in (-1, 2.0, True, "2")),
    (("degree",), 7, "degree 7 is above 6 (docs/calibration_file.md, section 5)"),
    *((path, v, f"{path[0]} contains NaN or infinite values") for v in (_NAN, _INF, -_INF)
      for path in (("M", 1, 0, 2), ("b", 2, 1), ("noise_sigma_mps2", 0))),
    *((("M", 0, 0, 0), v, f"coefficients are not numeric arrays (M[0][0][0] {why})") for v, why in (
        ("abc", "must be a number, got str 'abc'"), ({"a": 1}, "must be a number, got dict {'a': 1}"),
        (10**400, "is too large for a float"))),
    # YAML 1.1 reads yes / on / true as a bool, which numpy took for 1.0
    *((path, True, f"coefficients are not numeric arrays ({where} must be a number, got bool True)") for path, where in (
        (("M", 0, 0, 0), "M[0][0][0]"), (("b", 0, 1), "b[0][1]"), (("noise_sigma_mps2", 2), "noise_sigma_mps2[2]"))),
    (("corrections",), [{"kind": "channel_offset", "coeff_mps2_counts": [True, 0.0, 0.0]}],
     "bad correction term: corrections[0]: channel_offset: parameter 'coeff_mps2_counts'[0] must be a number, got bool True"),
    (("M", 0, 0, 0), [1, 2], "coefficients are not numeric arrays (M is not a numeric array..."),
    *((("temperature_range_c",), rng, message) for rng, message in (
        ([40.0, 10.0], "temperature_range_c must be finite [min, max], got [40.0, 10.0]"),
        ([_NAN, 10.0], "temperature_range_c must be finite [min, max], got [nan, 10.0]"),
        ([0.0, _INF], "temperature_range_c must be finite [min, max], got [0.0, inf]"),
        ([10.0], "temperature_range_c must be [min, max]"),
        ([1.0, 2.0, 3.0], "temperature_range_c must be [min, max]"),
        ("hot", "temperature_range_c must be [min, max]"),
        (["cold", 3.0], "'temperature_range_c' must be a number, got str 'cold'"),
        ([10**400, 3.0], "'temperature_range_c' is too large for a float"))),
    *(((key,), v, "temperature_scale_c must be positive and temperature_center_c finite") for key, v in (
        ("temperature_scale_c", 0.0), ("temperature_scale_c", -3.0), ("temperature_scale_c", _NAN),
        ("temperature_center_c", _INF))),
    (("temperature_center_c",), "warm", "'temperature_center_c' must be a number, got str 'warm'"),
    (("noise_sigma_mps2",), [0.1, -0.1, 0.1], "noise_sigma_mps2 must be non-negative"),
    (("noise_sigma_mps2",), [0.1, 0.1], "noise_sigma_mps2 must have 3 entries, got shape (2,)"),
    (("sensor_id",), 7, "'sensor_id' must be a string, got int 7 (quote it in the YAML)"),
    (("sensor_id",), "x" * 300, "'sensor_id' has 300 characters, at most 256 are accepted"),
    (("created",), [2026], "'created' must be a string, got list [2026] (quote it in the YAML)"),
    (("fit",), [1, 2], "'fit' must be a mapping of figures, got list"),
    (("fit",), [], "'fit' must be a mapping of figures, got list"),
    (("noise_correlation",), [], "'noise_correlation' must be a mapping, got list"),
    (("corrections",), {}, "'corrections' must be a list"),
    (("corrections",), [{"kind": "warp_drive", "gain": 1.0}],
     "bad correction term: corrections[0]: unknown correction kind 'warp_drive' (known: [..."),
    (("corrections",), {"kind": "x"}, "'corrections' must be a list"),
    (("corrections",), [{"gain": 1.0}], "corrections[0].kind must be a string, got NoneType"),
    (("corrections",), ["time_drift"], "corrections[0] must be a mapping with a 'kind', got str"),
    (("corrections",), [{"kind": [1]}], "corrections[0].kind must be a string, got list"),
    # found by test_fuzz_inputs: an OverflowError from a term's parameter parsing escaped the loader
    (("corrections",), [{"kind": "thermal_lag", "tau_s": 10**400}],
     "bad correction term: corrections[0]: thermal_lag: parameter 'tau_s' is too large for a float"),
]


@pytest.mark.parametrize("path,value,message", _FIELD_REFUSALS, ids=[
    ".".join(map(str, p)) + (" left out" if v is _DELETE else f"={v!r}" if len(repr(v)) < 40 else f": {m[:40]}")
    for p, v, m in _FIELD_REFUSALS])
def test_a_bad_field_is_refused_with_its_message(tmp_path: Path, good_doc: dict[str, Any], path: tuple, value: Any,
                                                 message: str) -> None:
    """A degree-2 document with one field set to ``value`` (or left out) is refused, the message naming the file
    and ending with ``message`` (or holding it up to its '...')."""
    parent = good_doc
    for key in path[:-1]:
        parent = parent[key]
    if value is _DELETE:
        del parent[path[-1]]
    else:
        parent[path[-1]] = value
    msg = refused(write(tmp_path, good_doc))
    assert message[:-3] in msg if message.endswith("...") else msg.endswith(message), msg


def test_scientific_notation_without_a_dot_is_a_number(tmp_path: Path, good_doc: dict[str, Any]) -> None:
    """PyYAML (YAML 1.1) reads a hand-written 1e-3 as a string; the loader resolves it as YAML 1.2 does (documented)."""
    path = tmp_path / "cal.yaml"
    path.write_text(yaml.safe_dump(good_doc, sort_keys=False, default_flow_style=None))
    text = re.sub(r"^noise_sigma_mps2:.*$", "noise_sigma_mps2: [1e-3, 2E-3, 3e-3]", path.read_text(), flags=re.M)
    path.write_text(re.sub(r"^temperature_scale_c:.*$", "temperature_scale_c: 1e1", text, flags=re.M))
    cal = ThermalCalibration.load(path)
    np.testing.assert_array_equal(cal.noise_sigma_mps2, [1e-3, 2e-3, 3e-3])
    assert cal.t_scale_c == 10.0


def test_constructor_validates_too() -> None:
    with pytest.raises(ValueError, match="M must have shape"):
        ThermalCalibration(M=np.zeros((3, 3)), b=np.zeros((1, 3)), temperature_range_c=(0, 1))
    with pytest.raises(ValueError, match="b must have shape"):
        ThermalCalibration(M=np.zeros((2, 3, 3)), b=np.zeros((1, 3)), temperature_range_c=(0, 1))


@pytest.mark.parametrize(
    "key,value",
    [
        ("noise_sigma_mps2", "&r [*r, *r, *r]"),  # self-referencing: numpy would expand it until memory runs out
        ("sensor_id", "&s fbg-01\nsensor_alias: *s"),  # harmless, but aliases are refused as a rule
    ],
    ids=["self_reference", "harmless_alias"],
)
def test_yaml_aliases_are_refused(tmp_path: Path, good_doc: dict[str, Any], key: str, value: str) -> None:
    path = write(tmp_path, good_doc)
    path.write_text(path.read_text().replace(f"\n{key}:", f"\n{key}: {value}\nold_{key}:", 1))
    assert "not valid YAML (aliases (*name) are not allowed in a calibration file" in refused(path)


def test_anchor_without_alias_is_accepted(tmp_path: Path, good_doc: dict[str, Any]) -> None:
    path = write(tmp_path, good_doc)
    path.write_text(path.read_text().replace("\nsensor_id:", "\nsensor_id: &s fbg-01\nnotes:", 1))
    assert ThermalCalibration.load(path).sensor_id == "fbg-01"


def test_a_date_is_text(tmp_path: Path, good_doc: dict[str, Any]) -> None:
    """An impossible date made PyYAML fail ("month must be in 1..12"); the project's loader reads dates as text."""
    path = write(tmp_path, good_doc)
    path.write_text(path.read_text().replace("\ncreated:", "\ncreated: 2026-13-45\nnotes:", 1))
    assert ThermalCalibration.load(path).created == "2026-13-45"


def test_yaml_written_by_save_has_no_aliases(tmp_path: Path) -> None:
    cal = make_cal()
    shared = [1.0, 2.0]
    cal.fit = {"a": shared, "b": shared}  # the same object twice: safe_dump would anchor it if _plain did not copy
    cal.save(tmp_path / "c.yaml")
    assert "*id" not in (tmp_path / "c.yaml").read_text()
    assert ThermalCalibration.load(tmp_path / "c.yaml").fit == {"a": [1.0, 2.0], "b": [1.0, 2.0]}
