"""Bounded-time fuzzing (hypothesis) of the two inputs that come from outside: board bytes and calibration files.

* Frame decoder: arbitrary bytes, mutated valid streams (version-1 and version-2 frames mixed;
  overwrites, insertions, deletions, repeated slices), arbitrary chunking (non-bytes arguments:
  test_stream_decoder).
  It must never raise, keep its memory bounded, keep its byte balance, and never output a frame that is not literally present,
  CRC and all, in the input.
* Calibration YAML loader: mutated valid documents (values replaced by arbitrary YAML values,
  keys deleted or added, nested coefficients replaced, text-level edits) and arbitrary text. The
  result is a ``ThermalCalibration`` or a ``CalibrationFileError``, never another exception.

Bounded: fixed ``max_examples`` and a per-example ``deadline`` that only trips on a pathological
slow-down (normal examples take milliseconds); the file runs in well under 30 s.
"""

from __future__ import annotations

import math
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from frame_strategies import frames, frames_v2
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from test_stream_decoder import split

from fbg_accel_driver import correction_terms
from fbg_accel_driver.frame_codec import ADC_MAX, CRC_SIZE, HEADER_SIZE, Frame, encode_frame, frame_size
from fbg_accel_driver.stream_decoder import MAX_BODY_LEN, StreamDecoder
from fbg_accel_driver.thermal_model import CalibrationFileError, ThermalCalibration

FUZZ = settings(max_examples=300, deadline=timedelta(seconds=5),
               suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FUZZ_FILES = settings(FUZZ, max_examples=200)  # loader cases write and read files: fewer, still bounded
MAX_CANDIDATE = HEADER_SIZE + MAX_BODY_LEN + CRC_SIZE


# ============================================================================ frame decoder


@st.composite
def mutated_streams(draw: st.DrawFn) -> bytes:
    data = bytearray(b"".join(encode_frame(f) for f in draw(st.lists(st.one_of(frames, frames_v2), max_size=25))))
    for _ in range(draw(st.integers(0, 12))):
        op = draw(st.sampled_from(["flip", "insert", "delete", "repeat", "overwrite"]))
        at = draw(st.integers(0, len(data)))
        if op == "flip" and at < len(data):
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif op == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=30))
        elif op == "delete":
            del data[at : at + draw(st.integers(1, 30))]
        elif op == "repeat":
            n = draw(st.integers(1, 60))
            data[at:at] = data[max(0, at - n) : at]
        elif op == "overwrite":
            patch = draw(st.binary(min_size=1, max_size=8))
            data[at : at + len(patch)] = patch
    return bytes(data)


def check_decoder_invariants(data: bytes, sizes: list[int]) -> None:
    dec = StreamDecoder()
    out: list[Frame] = []
    for chunk in split(data, sizes):
        out += dec.feed(chunk)
        assert dec.buffered < MAX_CANDIDATE
    s = dec.stats
    assert s.bytes_received == len(data)
    assert s.bytes_received == s.bytes_discarded + dec.frame_bytes + dec.buffered
    if s.duplicates == 0:
        assert dec.frame_bytes == sum(frame_size(f.version) for f in out)
    assert s.frames == len(out)
    assert min(s.as_dict().values()) >= 0
    for f in out:
        assert encode_frame(f) in data  # never a frame that was not on the wire
        assert max(f.ref, f.x, f.y, f.z) <= ADC_MAX


@FUZZ
@given(data=st.binary(max_size=3000), sizes=st.lists(st.integers(1, 300), min_size=1, max_size=6))
def test_fuzz_decoder_arbitrary_bytes(data: bytes, sizes: list[int]) -> None:
    check_decoder_invariants(data, sizes)


@FUZZ
@given(data=mutated_streams(), sizes=st.lists(st.integers(1, 100), min_size=1, max_size=6))
def test_fuzz_decoder_mutated_streams(data: bytes, sizes: list[int]) -> None:
    check_decoder_invariants(data, sizes)


# ============================================================================ calibration YAML loader
yaml_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**80), 2**80), st.integers(-(10**400), 10**400),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
    st.sampled_from(["1", "m/s^2", "degC", "thermal_polynomial", "fbg_accel_calibration", "1e-3", "nan", ".inf", "kind"]),
)
yaml_values = st.recursive(
    yaml_scalars,
    lambda children: st.one_of(st.lists(children, max_size=4), st.dictionaries(st.text(max_size=8), children, max_size=4)),
    max_leaves=20,
)
KEYS = ["format", "format_version", "units", "model", "sensor_id", "created", "degree", "temperature_center_c",
        "temperature_scale_c", "temperature_range_c", "M", "b", "noise_sigma_mps2", "fit", "corrections"]


def valid_doc() -> dict[str, Any]:
    rng = np.random.default_rng(0)
    return ThermalCalibration(M=rng.normal(0, 1, (3, 3, 3)), b=rng.normal(0, 1, (3, 3)), temperature_range_c=(15.0, 45.0),
                              sensor_id="fuzz", t_center_c=30.0, t_scale_c=15.0,
                              created="2026-11-21T00:00:00+00:00").to_dict()


CORRECTION_PARAMS = [
    "tau_s", "tia_tau_s", "delay_s", "psi0", "coeff_mps2", "coeff_mps2_counts", "ref_offset_counts",
    "creep_mps2_per_s", "warmup_mps2", "warmup_tau_s", "half_gap_mps2", "rate_tau_s", "channels", "features", "x",
]  # fmt: skip


def correction_docs() -> st.SearchStrategy[dict[str, Any]]:
    """Correction-term mappings: a registered or unknown kind with arbitrary parameters."""
    kinds = [*sorted(correction_terms.CORRECTION_TYPES), "no_such_term"]
    return st.builds(lambda kind, params: {"kind": kind, **params}, st.sampled_from(kinds),
                     st.dictionaries(st.sampled_from(CORRECTION_PARAMS), yaml_values, max_size=4))


@st.composite
def mutated_docs(draw: st.DrawFn) -> dict[str, Any]:
    doc = valid_doc()
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["set", "delete", "add", "coef", "unit", "corrections"]))
        if op == "set":
            doc[draw(st.sampled_from(KEYS))] = draw(yaml_values)
        elif op == "delete":
            doc.pop(draw(st.sampled_from(KEYS)), None)
        elif op == "add":
            doc[draw(st.text(max_size=10))] = draw(yaml_values)
        elif op == "coef" and isinstance(doc.get("M"), list) and isinstance(doc.get("b"), list):
            target = doc[draw(st.sampled_from(["M", "b"]))]
            k = draw(st.integers(0, 2))
            if k < len(target) and isinstance(target[k], list) and target[k]:
                target[k][draw(st.integers(0, len(target[k]) - 1))] = draw(yaml_values)
        elif op == "unit" and isinstance(doc.get("units"), dict):
            doc["units"][draw(st.sampled_from(["psi", "temperature", "acceleration", "time", "x"]))] = draw(yaml_values)
        elif op == "corrections":
            doc["corrections"] = draw(st.lists(st.one_of(correction_docs(), yaml_values), max_size=3))
    return doc


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz_calibration")


def load_text(fuzz_dir: Path, text: str | bytes) -> ThermalCalibration | None:
    """Write ``text`` to a file and load it: a calibration, or None after a CalibrationFileError."""
    path = fuzz_dir / "cal.yaml"
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    try:
        cal = ThermalCalibration.load(path)
    except CalibrationFileError as exc:
        assert str(exc).startswith(f"{path}: ")
        event("refused")
        return None
    assert type(cal) is ThermalCalibration
    event("accepted")
    return cal


def check_accepted(cal: ThermalCalibration | None, fuzz_dir: Path) -> None:
    """An accepted calibration is usable: finite coefficients, evaluates, and round-trips through save/load."""
    if cal is None:
        return
    assert np.all(np.isfinite(cal.M)) and np.all(np.isfinite(cal.b))
    lo, hi = cal.temperature_range_c
    assert math.isfinite(lo) and math.isfinite(hi) and lo <= hi
    out = cal.apply_counts(np.array([3000.0]), np.array([[1000.0, 2000.0, 1500.0]]), np.array([cal.t_center_c]), np.zeros(1))
    assert out.shape == (1, 3)
    cal.save(fuzz_dir / "resaved.yaml")
    again = ThermalCalibration.load(fuzz_dir / "resaved.yaml")
    np.testing.assert_array_equal(again.M, cal.M)


@FUZZ_FILES
@given(doc=mutated_docs())
def test_fuzz_loader_mutated_documents(fuzz_dir: Path, doc: dict[str, Any]) -> None:
    check_accepted(load_text(fuzz_dir, yaml.safe_dump(doc, sort_keys=False)), fuzz_dir)


@FUZZ_FILES
@given(
    edits=st.lists(st.tuples(st.integers(0, 3000), st.integers(0, 40), st.text(max_size=12)), min_size=1, max_size=5),
    cut=st.one_of(st.none(), st.integers(0, 3000)),
)
def test_fuzz_loader_text_edits(fuzz_dir: Path, edits: list[tuple[int, int, str]], cut: int | None) -> None:
    text = yaml.safe_dump(valid_doc(), sort_keys=False)
    for at, n_del, insert in edits:
        at = at % (len(text) + 1)
        text = text[:at] + insert + text[at + n_del :]
    if cut is not None:
        text = text[:cut]
    check_accepted(load_text(fuzz_dir, text), fuzz_dir)


@FUZZ
@given(content=st.one_of(st.text(max_size=400), st.binary(max_size=400)))
def test_fuzz_loader_arbitrary_content(fuzz_dir: Path, content: str | bytes) -> None:
    check_accepted(load_text(fuzz_dir, content), fuzz_dir)


@FUZZ
@given(obj=yaml_values)
def test_fuzz_from_dict_arbitrary_objects(obj: Any) -> None:
    try:
        ThermalCalibration.from_dict(obj, source="fuzz")
    except CalibrationFileError as exc:
        assert str(exc).startswith("fuzz: ")


# ============================================================================ every YAML file the project reads
REPO = Path(__file__).resolve().parents[1]
BAG_METADATA = """rosbag2_bagfile_information:
  version: 9
  storage_identifier: mcap
  relative_file_paths: [run_0.mcap]
  topics_with_message_count:
    - topic_metadata: {name: /imu/raw, type: sensor_msgs/msg/JointState}
      message_count: 5
  compression_mode: ''
"""
YAML_SEEDS = {  # reader name (test_yaml_input.READERS) -> a valid document it reads
    "calibration file": (REPO / "config" / "calibration_sim.yaml").read_text(),
    "pose plan": (REPO / "config" / "pose_plan_six_position.yaml").read_text(),
    "excitation plan": (REPO / "config" / "excitation_plan_stepped_sine.yaml").read_text(),
    "simulator config": "scenario:\n  rate_hz: 200.0\neffects:\n  tia_lowpass:\n    scale: 0.5\n",
    "rosbag2 metadata": BAG_METADATA,
}
YAML_INSERTS = ["[" * 200, "{", "*a", "&a ", "!!int x", "!!python/name:os.system", "2026-13-45", "1:22", "0x52",
                "\t", "\x00", "\ufeff", ": :", "- ", "\n  - ", "'", '"', "? ", "%YAML 1.1\n---\n", "...\n", "<<: *a"]


@settings(FUZZ_FILES, max_examples=60, deadline=None)  # first example imports every reader
@given(reader=st.sampled_from(sorted(YAML_SEEDS)),
       edits=st.lists(st.tuples(st.integers(0, 5000), st.integers(0, 30),
                                st.one_of(st.sampled_from(YAML_INSERTS), st.text(max_size=8))), min_size=1, max_size=4))
def test_fuzz_every_yaml_reader_has_one_error_contract(tmp_path_factory: pytest.TempPathFactory, reader: str,
                                                       edits: list[tuple[int, int, str]]) -> None:
    """Issue 42, item 8: each YAML file the project reads, edited at random, is read or refused with a
    ``ValueError`` whose message is one line starting with the file's path -- never another exception (a
    TypeError out of the bag reader, a RecursionError, a date's bare ValueError)."""
    from test_yaml_input import READERS, check_one_line

    text = YAML_SEEDS[reader]
    for at, n_del, insert in edits:
        at = at % (len(text) + 1)
        text = text[:at] + insert + text[at + n_del:]
    d = tmp_path_factory.mktemp("yaml")
    (d / "run_0.mcap").write_bytes(b"\x89MCAP0\r\n")
    path = d / "metadata.yaml"
    path.write_text(text, encoding="utf-8", errors="surrogateescape")
    try:
        READERS[reader](path)
    except Exception as exc:  # the contract is checked, whatever the class
        check_one_line(exc, path)
        event(f"{reader}: refused")
    else:
        event(f"{reader}: read")
