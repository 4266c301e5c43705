"""The calibration file as a strict, typed contract (issue 11; docs/calibration_file.md sections 3 and 5).

Unknown keys are refused with the nearest valid name, sizes are bounded before parsing (every field typed and
``noise_sigma_mps2`` required: test_thermal_model's table of bad fields), and a file whose model gives non-finite or absurd output
anywhere the driver can evaluate it is refused at load, not discovered sample by sample. Format
versions migrate through one table of steps.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from test_thermal_model import refused, write

from fbg_accel_driver import thermal_model
from fbg_accel_driver.chain_compensation import ChainDynamics
from fbg_accel_driver.correction_terms import TimeDrift
from fbg_accel_driver.thermal_model import (
    MAX_FILE_BYTES,
    CalibrationFileError,
    ThermalCalibration,
    check_plausible,
    migrate,
)

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture()
def good() -> dict[str, Any]:
    return yaml.safe_load((REPO / "config" / "calibration_sim.yaml").read_text())


def test_the_shipped_calibration_passes_every_check(good: dict[str, Any]) -> None:
    cal = ThermalCalibration.from_dict(good)
    assert check_plausible(cal) == ""


@pytest.mark.parametrize("key,near", [("correction", "corrections"), ("noise_sigma_mps", "noise_sigma_mps2"),
                                      ("temperature_centre_c", "temperature_center_c")])
def test_unknown_top_level_key_names_the_nearest(tmp_path: Path, good: dict[str, Any], key: str, near: str) -> None:
    good[key] = [] if key == "correction" else yaml.safe_load(yaml.safe_dump(good[near]))  # a copy: no YAML anchor
    assert f"unknown key '{key}' (did you mean '{near}'?)" in refused(write(tmp_path, good))


def test_unknown_key_inside_a_correction_term(tmp_path: Path, good: dict[str, Any]) -> None:
    good["corrections"] = [{"kind": "reference_dark_offset", "ref_offset_counts": 5.0, "ref_ofset": 1.0}]
    assert "unknown key 'corrections[0].ref_ofset' (did you mean 'corrections[0].ref_offset_counts'?)" in \
        refused(write(tmp_path, good))


def test_notes_are_the_place_for_free_text_and_round_trip(tmp_path: Path, good: dict[str, Any]) -> None:
    good["notes"] = "re-fitted after the fibre was re-spliced; see log 2026-11-20"
    good["corrections"] = [{"kind": "reference_dark_offset", "ref_offset_counts": 5.0, "notes": "measured dark"}]
    p = write(tmp_path, good)
    cal = ThermalCalibration.load(p)
    assert cal.notes == good["notes"]
    cal.save(tmp_path / "again.yaml")
    assert ThermalCalibration.load(tmp_path / "again.yaml").notes == good["notes"]


def test_sizes_are_bounded_before_parsing(tmp_path: Path, good: dict[str, Any]) -> None:
    term = {"kind": "reference_dark_offset", "ref_offset_counts": 1.0}
    good["corrections"] = [dict(term) for _ in range(33)]
    assert "33 correction terms, at most 32 are accepted" in refused(write(tmp_path, good))
    # 100 000 terms (21.7 s and 658 MB before): refused on its size, the YAML is never parsed. The file is the
    # one-term file with that term's lines repeated (what safe_dump writes for 100 000 terms, without its 5 s)
    one, item = yaml.safe_dump(dict(good, corrections=[term])), yaml.safe_dump([term])
    assert one.count(item) == 1
    big = one.replace(item, item * 100_000)
    assert len(big) > MAX_FILE_BYTES
    parsed: list[int] = []
    real_load = yaml.load

    def counting_load(*args: Any, **kwargs: Any) -> Any:
        parsed.append(1)
        return real_load(*args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(thermal_model.yaml, "load", counting_load)
        assert f"above the {MAX_FILE_BYTES}-byte bound" in refused(write(tmp_path, None, raw=big))
    assert parsed == []


@pytest.mark.parametrize("change,message", [
    ({"noise_sigma_mps2": [1e300, 0.1, 0.1]}, "noise_sigma_mps2 [1e+300, 0.1, 0.1] is above 19.6 m/s^2"),
    ({"temperature_scale_c": 1e-300}, "temperature_scale_c 1e-300 is outside [0.001, 1000.0] degC"),
    ({"temperature_center_c": 1e300}, "temperature_center_c 1e+300 is outside [-100.0, 200.0] degC"),
    ({"temperature_range_c": [-300.0, 20.0]}, "temperature_range_c [-300.0, 20.0] is outside"),
    ({"M": "huge"}, "the model gives |a| up to"),
    ({"M": "overflow"}, "non-finite acceleration"),
    ({"corrections": [{"kind": "reference_dark_offset", "ref_offset_counts": 4095.0}]}, "non-finite acceleration"),
])
def test_finite_but_absurd_files_are_refused(tmp_path: Path, good: dict[str, Any], change: dict[str, Any],
                                             message: str) -> None:
    if change.get("M") == "huge":  # within a float, 100x beyond anything this sensor can output
        change = {"M": (np.asarray(good["M"]) * 1e3).tolist()}
    elif change.get("M") == "overflow":  # finite entries whose products overflow to inf
        change = {"M": np.full_like(np.asarray(good["M"], dtype=float), 1e308).tolist()}
    good.update(change)
    assert message in refused(write(tmp_path, good))


def test_every_refused_absurd_file_did_poison_the_driver_before(good: dict[str, Any]) -> None:
    """The grid evaluation is the driver's own evaluation: a dark offset of 4095 counts makes the
    driver's output non-finite for a full-scale reference (the case that published nothing)."""
    good["corrections"] = [{"kind": "reference_dark_offset", "ref_offset_counts": 4095.0}]
    with pytest.raises(CalibrationFileError):
        ThermalCalibration.from_dict(good)
    cal = ThermalCalibration.from_dict(dict(good, corrections=[]))
    from fbg_accel_driver.correction_terms import correction_from_dict

    cal.corrections = [correction_from_dict(good["corrections"][0])]
    with np.errstate(all="ignore"):
        out = cal.apply_counts(np.array([4095.0]), np.array([[2000.0, 2000.0, 2000.0]]), np.array([25.0]),
                               np.array([0.0]))
    assert not np.all(np.isfinite(out))


def test_format_versions_migrate_through_one_table(monkeypatch: pytest.MonkeyPatch, good: dict[str, Any]) -> None:
    assert migrate(dict(good)) == good  # version 1 is current: nothing to do
    with pytest.raises(CalibrationFileError, match=r"format_version 2 is not supported \(this driver reads 1\)"):
        migrate(dict(good, format_version=2), "f.yaml")

    # a future version 2 that renamed noise_sigma_mps2: the one step, registered in the table
    def v1_to_v2(d: dict[str, Any]) -> dict[str, Any]:
        d["white_noise_mps2"] = d.pop("noise_sigma_mps2")
        d["format_version"] = 2
        return d

    monkeypatch.setattr(thermal_model, "FORMAT_VERSION", 2)
    monkeypatch.setattr(thermal_model, "MIGRATIONS", {1: v1_to_v2})
    out = migrate(dict(good), "old.yaml")
    assert out["format_version"] == 2 and out["white_noise_mps2"] == good["noise_sigma_mps2"]
    assert "noise_sigma_mps2" not in out
    monkeypatch.setattr(thermal_model, "MIGRATIONS", {})
    with pytest.raises(CalibrationFileError, match=r"format_version 1 is not supported \(this driver reads 2\)"):
        migrate(dict(good), "old.yaml")


# ---------------------------------------------------------------------------- hand-edited files (calibration file loading)
DYNAMIC = {"format_version": 1, "cutoff_hz": {"reference": None, "x": 1.7, "y": 1.3, "z": 1.3},
           "delay_s": {"x": 0.002, "y": 0.0, "z": 0.0}}
TERMS = {"reference_lowpass": {"kind": "reference_lowpass", "time_constant_s": 5.0},
         "thermal_lag": {"kind": "thermal_lag", "tau_s": 30.0},
         "time_drift": {"kind": "time_drift", "creep_mps2_per_s": [0, 0, 0], "warmup_mps2": [0, 0, 0], "warmup_tau_s": 100}}


@pytest.mark.parametrize("missing", ["time_constant_s", "correlated_fraction"])
def test_noise_correlation_needs_both_lists(tmp_path: Path, good: dict[str, Any], missing: str) -> None:
    """A fraction of 0.97 without its time constant was read as white noise: the driver's covariance of a decimated
    mean came out 17 times too small."""
    del good["noise_correlation"][missing]
    assert refused(write(tmp_path, good)).endswith(f"missing key 'noise_correlation.{missing}' (the section needs both of "
                                            "correlated_fraction, time_constant_s, or none for white noise)")
    good["noise_correlation"] = {"correlated_fraction": [0.9, 0.0, 0.0], "time_constant_s": [0.0, 0.0, 0.0]}
    assert "a correlated_fraction above 0 needs a time_constant_s above 0" in refused(write(tmp_path, good))


@pytest.mark.parametrize("extra, key", [("degree: 2\n", "degree"), ("corrections:\n- {kind: thermal_lag, tau_s: 30}\n",
                                                                    "corrections")])
def test_a_duplicated_key_is_refused_with_its_lines(tmp_path: Path, extra: str, key: str) -> None:
    text = (REPO / "config" / "calibration_sim.yaml").read_text(encoding="utf-8")
    msg = refused(write(tmp_path, None, text.replace("model: thermal_polynomial\n", "model: thermal_polynomial\n" + extra)))
    assert f"found duplicate key '{key}' (first given on line 6)" in msg and ", column 1:" in msg
    nested = text.replace("corrections: []", "corrections:\n- {kind: thermal_lag, tau_s: 30.0, tau_s: -30.0}")
    assert "found duplicate key 'tau_s'" in refused(write(tmp_path, None, nested))


@pytest.mark.parametrize("term, key, value", [
    ({"kind": "tia_inverse_filter", "tau_s": [0.09, 0.12, 0.12, 0.16]}, "channels", ["x", "y", "z", "ref"]),
    ({"kind": "spectral_nonlinearity", "psi0": [0.1, 0.1, 0.9], "coeff_mps2": [[0.1] * 6 for _ in range(3)]},
     "features",
     ["xy", "xz", "yz", "xx", "yy", "zz"]),
    ({"kind": "chain_dynamics", "tia_tau_s": [0.1] * 4, "delay_s": 0.0}, "group_delay_s", [5.0, 5.0, 5.0]),
    ({"kind": "chain_dynamics", "tia_tau_s": [0.1] * 4, "delay_s": 0.0}, "runtime", "inverse"),
])
def test_a_descriptive_key_that_disagrees_with_the_term_is_refused(tmp_path: Path, good: dict[str, Any], term: dict,
                                                                  key: str, value: Any) -> None:
    good["corrections"] = [term]
    written = ThermalCalibration.from_dict(good).corrections[0].to_dict()[key]
    good["corrections"] = [{**term, key: written}]  # what the term writes (a hand-computed sum within 1e-9 too)
    ThermalCalibration.from_dict(good)
    good["corrections"] = [{**term, key: value}]
    assert f"corrections[0].{key} is {value!r}, but this {term['kind']} term is {written!r}" in refused(write(tmp_path, good))


def test_a_descriptive_number_agrees_to_1e9_relative_and_names_given_as_numbers_disagree(tmp_path: Path,
                                                                                         good: dict[str, Any]) -> None:
    """``group_delay_s`` as the file gives it may be a hand-computed sum: within 1e-10 relative of what the term writes
    it is accepted, 1e-8 or 10 % off it is refused (to 1e-9 relative: neither to exact equality nor to numpy's default
    1e-5); ``channels`` given as numbers is refused with the message, like any other disagreement."""
    term = {"kind": "chain_dynamics", "tia_tau_s": [0.1] * 4, "delay_s": 0.0}
    good["corrections"] = [term]
    written = np.asarray(ThermalCalibration.from_dict(good).corrections[0].to_dict()["group_delay_s"], dtype=float)
    assert np.all((written > 0.01) & (written < 1.0))
    good["corrections"] = [{**term, "group_delay_s": (written * (1.0 + 1e-10)).tolist()}]
    ThermalCalibration.from_dict(good)
    for rel in (1e-8, 0.1):
        good["corrections"] = [{**term, "group_delay_s": (written * (1.0 + rel)).tolist()}]
        assert "corrections[0].group_delay_s is [" in refused(write(tmp_path, good))
    tia = {"kind": "tia_inverse_filter", "tau_s": [0.09, 0.12, 0.12, 0.16]}
    good["corrections"] = [{**tia, "channels": [1, 2, 3, 4]}]
    assert "corrections[0].channels is [1, 2, 3, 4], but this tia_inverse_filter term is" in \
        refused(write(tmp_path, good))

@pytest.mark.parametrize("line, where", [("delay_s: {x: 2e-3, y: 0.0, z: 0.0}", "delay"),
                                         ("cutoff_hz: {reference: null, x: 17e-1, y: 1.3, z: 1.3}", "cutoff"),
                                         *((kind, kind) for kind in TERMS)])
def test_scientific_notation_without_a_dot_is_a_number_everywhere(tmp_path: Path, good: dict[str, Any], line: str,
                                                                   where: str) -> None:
    """docs/calibration_file.md promises it; YAML 1.1 made '3e1' a string, refused in the dynamic section and terms."""
    if where in TERMS:
        key = next(k for k, v in TERMS[where].items() if isinstance(v, float | int) and k != "kind")
        good["corrections"] = [{**TERMS[where], key: "@"}]
    else:
        good["dynamic"] = DYNAMIC
    text = yaml.safe_dump(good, sort_keys=False, default_flow_style=None)
    text = text.replace("'@'", "3e1") if where in TERMS else text.replace(line.replace("2e-3", "0.002").replace(
        "17e-1", "1.7"), line)
    p = tmp_path / "cal.yaml"
    p.write_text(text, encoding="utf-8")
    cal = ThermalCalibration.load(p)
    got = {"delay": lambda: cal.dynamic.delay_s[0], "cutoff": lambda: cal.dynamic.cutoff_hz[1]}.get(
        where, lambda: cal.corrections[0].to_dict()[key])()
    assert got == {"delay": 2e-3, "cutoff": 1.7}.get(where, 30.0)


def test_a_dynamic_section_error_names_the_file_once(tmp_path: Path, good: dict[str, Any]) -> None:
    good["dynamic"] = {**DYNAMIC, "delay_s": {"x": "soon", "y": 0.0, "z": 0.0}}
    msg = refused(write(tmp_path, good))
    assert msg.count("cal.yaml") == 1 and msg.endswith("dynamic.delay_s.x must be a number, got str 'soon'"), msg


@pytest.mark.parametrize("version", [True, 1.0, "1", 3])
def test_every_format_version_is_an_integer(tmp_path: Path, good: dict[str, Any], version: Any) -> None:
    good["dynamic"] = {**DYNAMIC, "format_version": version}
    """The dynamic section's version as the file's (test_thermal_model's table of bad fields); formats 1 (fitted per
    axis) and 2 (per channel) are read."""
    reads = "1, 2" if version == 3 else "2"
    msg = refused(write(tmp_path, good))
    assert msg.endswith(f"dynamic.format_version {version!r} is not supported (this driver reads {reads})"), msg


def test_a_utf8_file_loads_whatever_the_locale(tmp_path: Path) -> None:
    """The file is UTF-8 (section 5); under LC_ALL=C without UTF-8 mode the loader decoded it with the locale."""
    p = tmp_path / "cal.yaml"
    p.write_text((REPO / "config" / "calibration_sim.yaml").read_text(encoding="utf-8") + "notes: 25 \u00b0C\n",
                 encoding="utf-8")
    code = ("import sys; from fbg_accel_driver.thermal_model import ThermalCalibration as T; "
            "print(ascii(T.load(sys.argv[1]).notes))")
    env = {**os.environ, "LC_ALL": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0",
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, "-c", code, str(p)], env=env, capture_output=True, text=True, check=False)
    assert run.stdout.strip() == ascii("25 \u00b0C"), run.stderr[-400:]


def test_a_saved_file_is_utf8_whatever_the_locale_dated_in_utc_and_without_empty_sections(tmp_path: Path) -> None:
    """The writer's side of section 5: saved under LC_ALL=C without UTF-8 mode, a note with a degree sign is written
    as UTF-8 and loads back; ``created`` is UTC and says so (+00:00), not the host's local time without a zone; a
    white-noise calibration without reference levels writes no noise_correlation or reference_level section."""
    code = ("import sys, numpy as np; from fbg_accel_driver.thermal_model import ThermalCalibration as T; "
            "T(M=80.0 * np.eye(3)[None], b=np.full((1, 3), -120.0), temperature_range_c=(20.0, 25.0), "
            "notes='25 \\u00b0C').save(sys.argv[1])")
    env = {**os.environ, "LC_ALL": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0",
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, "-c", code, str(tmp_path / "c.yaml")], env=env, capture_output=True,
                         text=True, check=False)
    assert run.returncode == 0, run.stderr[-400:]
    cal = ThermalCalibration.load(tmp_path / "c.yaml")
    assert cal.notes == "25 \u00b0C"
    doc = yaml.safe_load((tmp_path / "c.yaml").read_text(encoding="utf-8"))
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\+00:00", doc["created"]), doc["created"]
    assert "noise_correlation" not in doc and "reference_level" not in doc, list(doc)

@pytest.mark.parametrize("fields", [
    {"temperature_range_c": (-100.0, 200.0)}, {"temperature_range_c": (24.0, 24.0)},
    {"t_center_c": -100.0}, {"t_center_c": 200.0}, {"t_scale_c": 1e-3}, {"t_scale_c": 1e3},
])
def test_values_exactly_at_their_documented_limits_are_accepted(fields: dict[str, Any]) -> None:
    """The limits of section 5 are inclusive, as documented: values a user types at a limit (a temperature range of
    exactly -100..200 degC, a single temperature, a centre at -100 or 200 degC, a scale of 1e-3 or 1e3 degC) pass."""
    cal = ThermalCalibration(M=80.0 * np.eye(3)[None], b=np.full((1, 3), -120.0),
                             **{"temperature_range_c": (20.0, 25.0), **fields})
    assert check_plausible(cal) == ""

def test_calibrations_that_differ_in_one_coefficient_are_not_equal() -> None:
    """``==`` (what a reload is checked with) is coefficients and metadata: two calibrations that differ only in one
    entry of M are different, whatever else they share."""
    def make(m01: float) -> ThermalCalibration:
        m = 80.0 * np.eye(3)[None]
        m[0, 0, 1] = m01
        return ThermalCalibration(M=m, b=np.full((1, 3), -120.0), temperature_range_c=(20.0, 25.0),
                                  created="2026-11-29T00:00:00+00:00")
    assert make(0.5) == make(0.5)
    assert make(0.5) != make(0.6)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_zero_row_of_m_is_named_by_its_axis(axis: int) -> None:
    """M with the row of one axis zero: the reason names that axis as the least sensitive direction."""
    m = 80.0 * np.eye(3)[None]
    m[0, axis] = 0.0
    reason = check_plausible(ThermalCalibration(M=m, b=np.full((1, 3), -120.0), temperature_range_c=(20.0, 25.0)))
    assert f"along its least sensitive direction {'xyz'[axis]} the output changes by at most" in reason, reason

def test_a_model_with_non_finite_output_is_refused_with_the_whole_reason() -> None:
    """Finite entries whose products overflow: the reason, word for word as docs/calibration_file.md gives it, names
    the AHT10 range the driver can read and what would happen to every such sample."""
    cal = ThermalCalibration(M=np.full((1, 3, 3), 1e308), b=np.full((1, 3), -120.0), temperature_range_c=(20.0, 25.0))
    assert check_plausible(cal) == (
        "the model gives a non-finite acceleration at temperatures the driver can read (-40..85 degC) and 12-bit "
        "counts: every such sample would be dropped (coefficients, temperature scaling or a correction term out of "
        "range)")

def test_a_saved_calibration_loads_equal_to_itself(tmp_path: Path) -> None:
    cal = ThermalCalibration.load(REPO / "config" / "calibration_sim.yaml")
    cal.dynamic = ChainDynamics((math.nan, 1.7, 1.3, 1.3), (0.002, 0.0, 0.0), {"sigma": math.nan})
    cal.corrections = [TimeDrift(np.zeros(3), np.ones(3) * 1e-3, 100.0, span_s=(0.0, 600.0))]
    cal.save(tmp_path / "c.yaml")
    back = ThermalCalibration.load(tmp_path / "c.yaml")
    assert back.dynamic == cal.dynamic and back == cal  # NaN was unequal to itself; arrays raised ValueError
    back.corrections[0].t0_s = 1.0
    back.M[0, 0, 0] += 1e-12
    assert back != cal and ThermalCalibration.load(tmp_path / "c.yaml") != back


INSENSITIVE = "the output changes by at most"


@pytest.mark.parametrize("row", [0, 2])
def test_a_singular_m_is_refused(tmp_path: Path, good: dict[str, Any], row: int) -> None:
    """A zero row of M(T) at the middle of the range: that axis read the bias only, whatever the acceleration."""
    cal = ThermalCalibration.from_dict(good)
    centre = sum(cal.temperature_range_c) / 2
    m_centre = cal.coefficients(centre)[0][0]
    good["M"][0][row] = [float(v) for v in np.asarray(good["M"][0][row]) - m_centre[row]]  # M_0 cancels the others
    msg = refused(write(tmp_path, good))
    assert INSENSITIVE in msg and "xyz"[row] in msg.split("direction")[1][:12], msg


@pytest.mark.parametrize("case", ["zero row of M0", "1e-6 I", "1e-300 I", "dependent rows"])
def test_a_model_that_cannot_read_the_sensor_s_range_is_refused(tmp_path: Path, good: dict[str, Any],
                                                                 case: str) -> None:
    """Judged by what the model does, not by a scale-free rank: the output's change over the whole 12-bit range of
    the counts, along its least sensitive direction, at temperatures across the calibrated range, against the
    sensor's +-20 g range. Before, all four loaded: a zero row of M_0 (x then read -113 m/s^2 whatever the counts;
    the temperature terms keep M(T) of rank 3 but 1000x too weak), M = 1e-6 I (the output is the constant b) and
    1e-300 I (rank 3 for a scale-free test; ``allan`` then printed LAPACK noise)."""
    m = np.asarray(good["M"], dtype=float)
    if case == "zero row of M0":
        m[0][0] = 0.0
    elif case == "dependent rows":
        m[:, 2] = m[:, 0] + m[:, 1]
    else:
        m = np.zeros_like(m)
        m[0] = float(case.split()[0]) * np.eye(3)
    good["M"] = m.tolist()
    msg = refused(write(tmp_path, good))
    assert INSENSITIVE in msg and "m/s^2 over the whole 12-bit range" in msg and len(msg.splitlines()) == 1, msg
    assert ("m/s^2 over the whole 12-bit range of the counts (reference 256 counts), below 49 m/s^2 (5 g, an eighth of "
            "the sensor's +-20 g span): a zero row or column, dependent rows, or coefficients in the wrong unit (M(T) = "
            "[[") in msg, msg
    if case == "dependent rows":  # the weak direction is no axis: given as a unit vector
        assert re.search(r"least sensitive direction \(-?0\.\d\d, -?0\.\d\d, -?0\.\d\d\) the output", msg), msg


def test_a_weak_but_physical_model_loads(good: dict[str, Any]) -> None:
    """The bound is far from real calibrations: M scaled down 10x (a sensor whose axes see 10x more light than its
    reference) still loads, 2.5x above the bound; the shipped one is 25x above it (smallest singular value 77 m/s^2
    per unit Psi)."""
    good["M"] = (np.asarray(good["M"], dtype=float) / 10.0).tolist()
    cal = ThermalCalibration.from_dict(good)
    assert check_plausible(cal) == ""


def _loads(tmp_path: Path, doc: dict[str, Any]) -> str:
    """"" when ``doc`` loads, else the loader's message."""
    try:
        ThermalCalibration.load(write(tmp_path, doc))
    except CalibrationFileError as exc:
        return str(exc)
    return ""


@pytest.mark.parametrize(("section", "key", "values", "accepted"), [
    # reference-level temperatures strictly ascending: equal neighbours and a step back are refused
    ("reference_level", "temperature_c", [16.0, 24.0, 45.0], True),
    ("reference_level", "temperature_c", [16.0, 16.0 + 1e-9, 45.0], True),
    ("reference_level", "temperature_c", [16.0, 16.0, 45.0], False),
    ("reference_level", "temperature_c", [16.0, 45.0, 24.0], False),
    # reference-level counts: ADC counts 1..4095
    ("reference_level", "counts", [1.0, 860.0, 4095.0], True),
    ("reference_level", "counts", [0.999, 860.0, 800.0], False),
    ("reference_level", "counts", [880.0, 860.0, 4095.001], False),
    # correlated fraction 0..1 (above 0 with a time constant above 0)
    ("noise_correlation", "correlated_fraction", [0.0, 1.0, 0.5], True),
    ("noise_correlation", "correlated_fraction", [-0.001, 0.5, 0.5], False),
    ("noise_correlation", "correlated_fraction", [0.5, 1.001, 0.5], False),
    # time constant 0..100 s
    ("noise_correlation", "time_constant_s", [0.1, 100.0, 0.1], True),
    ("noise_correlation", "time_constant_s", [0.1, 100.001, 0.1], False),
    ("noise_correlation", "time_constant_s", [0.1, -0.001, 0.1], False),
])
def test_section_bounds_at_and_around_their_edges(tmp_path: Path, good: dict[str, Any], section: str, key: str,
                                                  values: list[float], accepted: bool) -> None:
    """Each bound of the optional sections at its edge (accepted) and just beyond it (refused, naming the key)."""
    good[section][key] = values
    msg = _loads(tmp_path, good)
    assert (msg == "") == accepted, msg
    if not accepted:
        assert f"{section}.{key}" in msg and len(msg.splitlines()) == 1, msg


@pytest.mark.parametrize(("sigma", "accepted"), [(thermal_model.NOISE_MAX_MPS2, True),
                                                 (thermal_model.NOISE_MAX_MPS2 * (1 + 1e-9), False), (1e300, False)])
def test_noise_sigma_at_and_above_its_maximum(tmp_path: Path, good: dict[str, Any], sigma: float,
                                              accepted: bool) -> None:
    """A white noise of a tenth of the full scale is the largest accepted: it goes into the published covariance."""
    good["noise_sigma_mps2"] = [0.1, float(sigma), 0.1]
    msg = _loads(tmp_path, good)
    assert (msg == "") == accepted, msg
    if not accepted:
        assert "noise_sigma_mps2" in msg and "a tenth of full scale" in msg, msg


def test_a_reference_of_exactly_the_minimum_counts_is_normalised() -> None:
    """Eq. 24 at ``MIN_REFERENCE_COUNTS``: a reference of exactly that many counts is used, one below it is NaN."""
    lo = thermal_model.MIN_REFERENCE_COUNTS
    psi = thermal_model.normalise(np.full((3, 3), 100.0), np.array([lo, lo - 1e-9, lo + 1.0]))
    assert np.all(np.isfinite(psi[0])) and np.all(np.isnan(psi[1])) and np.all(np.isfinite(psi[2]))
    np.testing.assert_allclose(psi[0], 100.0 / lo)


@pytest.mark.parametrize("section,key", [("reference_level", "temperature"), ("noise_correlation", "fraction")])
def test_an_unknown_key_in_a_section_is_named_with_its_section(tmp_path: Path, good: dict[str, Any], section: str,
                                                               key: str) -> None:
    good[section][key] = 1.0
    assert f"unknown key '{section}.{key}'" in refused(write(tmp_path, good))


def test_the_saved_file_keeps_the_documented_key_order_and_flow_lists(tmp_path: Path) -> None:
    """What people read: the keys in the order of docs/calibration_file.md (format first), short lists on one line."""
    cal = ThermalCalibration.load(REPO / "config" / "calibration_sim.yaml")
    cal.save(tmp_path / "c.yaml")
    text = (tmp_path / "c.yaml").read_text()
    keys = [ln.split(":")[0] for ln in text.splitlines() if ln[:1].isalpha()]
    assert keys == [k for k in thermal_model.TOP_LEVEL_KEYS if k in keys], keys
    assert f"temperature_range_c: [{cal.temperature_range_c[0]}, {cal.temperature_range_c[1]}]" in text


def test_the_expected_reference_counts_follow_the_levels_linearly_and_hold_beyond_them() -> None:
    cal = ThermalCalibration(M=80.0 * np.eye(3)[None], b=np.zeros((1, 3)), temperature_range_c=(16.0, 45.0),
                             reference_level_temperature_c=np.array([16.0, 46.0]),
                             reference_level_counts=np.array([880.0, 820.0]))
    assert cal.expected_reference_counts(31.0) == pytest.approx(850.0)
    assert cal.expected_reference_counts(31.0) == pytest.approx(850.0)  # the cached value
    assert (cal.expected_reference_counts(0.0), cal.expected_reference_counts(60.0)) == (880.0, 820.0)
    assert math.isnan(cal.expected_reference_counts(math.nan))


def test_file_and_field_messages_name_what_they_judge(tmp_path: Path, good: dict[str, Any]) -> None:
    """Whole messages: a file over the size bound, the second bound of the range not a number; an empty sensor_id
    (``sensor_id:`` with nothing after it) is the empty text."""
    big = "notes: '" + "x" * (MAX_FILE_BYTES + 10) + "'\n"
    assert refused(write(tmp_path, None, raw=big)).endswith(
        f"above the {MAX_FILE_BYTES}-byte bound of a calibration file (docs/calibration_file.md, section 5)")
    bad_range = dict(good, temperature_range_c=[16.0, "warm"])
    assert "'temperature_range_c' must be a number, got str" in refused(write(tmp_path, bad_range))
    good["sensor_id"] = None
    assert ThermalCalibration.load(write(tmp_path, good)).sensor_id == ""
