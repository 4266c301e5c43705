"""The calibration file as a strict, typed contract (issue 11; docs/calibration_file.md sections 3 and 5).

Unknown keys are refused with the nearest valid name, every field is typed, sizes are bounded before
parsing, ``noise_sigma_mps2`` is required, and a file whose model gives non-finite or absurd output
anywhere the driver can evaluate it is refused at load, not discovered sample by sample. Format
versions migrate through one table of steps.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from fbg_accel_driver import thermal_model
from fbg_accel_driver.thermal_model import (
    MAX_FILE_BYTES,
    CalibrationFileError,
    ThermalCalibration,
    check_plausible,
    migrate,
)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture()
def good() -> dict[str, Any]:
    return yaml.safe_load((REPO / "config" / "calibration_sim.yaml").read_text())


def refused(tmp_path: Path, doc: Any, raw: str | None = None) -> str:
    p = tmp_path / "cal.yaml"
    p.write_text(raw if raw is not None else yaml.safe_dump(doc))
    with pytest.raises(CalibrationFileError) as info:
        ThermalCalibration.load(p)
    msg = str(info.value)
    assert msg.startswith(f"{p}: "), msg
    return msg


def test_the_shipped_calibration_passes_every_check(good: dict[str, Any]) -> None:
    cal = ThermalCalibration.from_dict(good)
    assert check_plausible(cal) == ""


@pytest.mark.parametrize("key,near", [("correction", "corrections"), ("noise_sigma_mps", "noise_sigma_mps2"),
                                      ("temperature_centre_c", "temperature_center_c")])
def test_unknown_top_level_key_names_the_nearest(tmp_path: Path, good: dict[str, Any], key: str, near: str) -> None:
    good[key] = [] if key == "correction" else yaml.safe_load(yaml.safe_dump(good[near]))  # a copy: no YAML anchor
    assert f"unknown key '{key}' (did you mean '{near}'?)" in refused(tmp_path, good)


def test_unknown_key_inside_a_correction_term(tmp_path: Path, good: dict[str, Any]) -> None:
    good["corrections"] = [{"kind": "reference_dark_offset", "ref_offset_counts": 5.0, "ref_ofset": 1.0}]
    assert "unknown key 'corrections[0].ref_ofset' (did you mean 'corrections[0].ref_offset_counts'?)" in \
        refused(tmp_path, good)


def test_notes_are_the_place_for_free_text_and_round_trip(tmp_path: Path, good: dict[str, Any]) -> None:
    good["notes"] = "re-fitted after the fibre was re-spliced; see log 2026-11-20"
    good["corrections"] = [{"kind": "reference_dark_offset", "ref_offset_counts": 5.0, "notes": "measured dark"}]
    p = tmp_path / "cal.yaml"
    p.write_text(yaml.safe_dump(good))
    cal = ThermalCalibration.load(p)
    assert cal.notes == good["notes"]
    cal.save(tmp_path / "again.yaml")
    assert ThermalCalibration.load(tmp_path / "again.yaml").notes == good["notes"]


def test_noise_sigma_is_required_not_invented(tmp_path: Path, good: dict[str, Any]) -> None:
    del good["noise_sigma_mps2"]
    assert refused(tmp_path, good).endswith("missing key 'noise_sigma_mps2'")


@pytest.mark.parametrize("key,value,message", [
    ("sensor_id", 7, "'sensor_id' must be a string, got int 7 (quote it in the YAML)"),
    ("sensor_id", "x" * 300, "'sensor_id' has 300 characters, at most 256 are accepted"),
    ("created", [2026], "'created' must be a string, got list"),
    ("fit", [1, 2], "'fit' must be a mapping of figures, got list"),
    ("temperature_center_c", "warm", "'temperature_center_c' must be a number, got str 'warm'"),
    ("degree", 7, "degree 7 is above 6"),
])
def test_typed_fields(tmp_path: Path, good: dict[str, Any], key: str, value: Any, message: str) -> None:
    good[key] = value
    assert message in refused(tmp_path, good)


def test_sizes_are_bounded_before_parsing(tmp_path: Path, good: dict[str, Any]) -> None:
    term = {"kind": "reference_dark_offset", "ref_offset_counts": 1.0}
    good["corrections"] = [dict(term) for _ in range(33)]
    assert "33 correction terms, at most 32 are accepted" in refused(tmp_path, good)
    # 100 000 terms (21.7 s and 658 MB before): refused on its size, the YAML is never parsed
    big = yaml.safe_dump(dict(good, corrections=[dict(term) for _ in range(100_000)]))
    assert len(big) > MAX_FILE_BYTES
    parsed: list[int] = []
    real_load = yaml.load

    def counting_load(*args: Any, **kwargs: Any) -> Any:
        parsed.append(1)
        return real_load(*args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(thermal_model.yaml, "load", counting_load)
        assert f"above the {MAX_FILE_BYTES}-byte bound" in refused(tmp_path, None, raw=big)
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
    assert message in refused(tmp_path, good)


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
