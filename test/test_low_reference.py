"""A reference too low to be data (source light missing: SLD off, fiber unplugged) in a calibration recording.

Eq. 24 divides each channel by the reference: with the reference dark (a few counts) Psi = counts/ref is ~100x its
normal size, and those samples are leverage points that wreck a fit (the gains came out a tenth of their value on a
minute of dark reference). The driver never publishes such a sample (``min_reference_counts``); the offline tools
leave out the same samples (``Recording.low_reference``, below ``sensor_constants.LOW_REFERENCE_COUNTS``): the fit
in memory and streamed, the diagnosis and the reports give the calibration of the recording without them, and say
how many and where. The simulator's ``faults.source_dropout`` windows scale the source power (ref ~3 counts at
level 0.004).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_diagnose_sim import _config

from fbg_accel_calibration.commands.cli import main as cli_main
from fbg_accel_calibration.diagnosis.design import SAMPLE_SELECTIONS, prepare_data
from fbg_accel_calibration.diagnosis.diagnose import diagnose
from fbg_accel_calibration.fit import fit_stream, static_detector
from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_calibration.fit.fit_stream import prepare, prepare_stream
from fbg_accel_calibration.fit.static_detector import calibration_samples
from fbg_accel_calibration.io.mcap_reader import McapSampleStream, read_recording
from fbg_accel_calibration.io.mcap_writer import write_recording
from fbg_accel_calibration.io.recording import Recording
from fbg_accel_driver.driver_core import CoreConfig
from fbg_accel_driver.driver_parameters import PARAMETERS
from fbg_accel_driver.sensor_constants import LOW_REFERENCE_COUNTS
from fbg_accel_driver.thermal_model import ThermalCalibration
from fbg_accel_sim.board_physics import simulate_recording

SEED = 11  # a seed of test_diagnose_sim's "nothing injected, nothing added"
T0_S, DARK_S = 60.5, 60.0  # the stretch starts half a second into a visit and ends inside another


@pytest.fixture(scope="module")
def dark() -> tuple[Recording, np.ndarray]:
    """A simulated run with the source power at 0.4 % for a minute (reference ~3 counts, axes a few counts), and
    those samples (N,) bool."""
    rec = simulate_recording(_config({"faults.source_dropout.windows": [
        {"start_s": T0_S, "duration_s": DARK_S, "level": 0.004}]}), seed=SEED)
    low = (rec.t_s >= T0_S) & (rec.t_s < T0_S + DARK_S)
    assert np.all(rec.ref[low] < 10) and np.all(rec.ref[~low] > 500)
    return rec, low


def _assert_same_calibration(a: ThermalCalibration, b: ThermalCalibration) -> None:
    np.testing.assert_allclose(a.M, b.M, rtol=1e-12, atol=1e-12 * np.abs(b.M).max())
    np.testing.assert_allclose(a.b, b.b, rtol=1e-12, atol=1e-12 * np.abs(b.b).max())
    np.testing.assert_allclose(a.noise_sigma_mps2, b.noise_sigma_mps2, rtol=1e-12)
    np.testing.assert_allclose(a.fit["rmse_mps2"], b.fit["rmse_mps2"], rtol=1e-12)
    assert a.fit["samples_used"] == b.fit["samples_used"]


def test_the_driver_default_is_the_shared_definition() -> None:
    assert CoreConfig().min_reference_counts == LOW_REFERENCE_COUNTS
    assert PARAMETERS["min_reference_counts"][1] == LOW_REFERENCE_COUNTS


def test_a_recording_names_its_samples_below_the_reference_limit(dark: tuple[Recording, np.ndarray]) -> None:
    rec, low = dark
    assert np.array_equal(rec.low_reference(), low)
    assert not rec.clipped()[low].any()  # an axis at its dark level (0 counts) is no light, not a clipped signal
    edge = Recording(np.arange(4.0), [0.0, LOW_REFERENCE_COUNTS - 1, LOW_REFERENCE_COUNTS, np.nan], np.full((4, 3), 9.0),
                     20.0, np.zeros((4, 3)), np.zeros(4))
    assert edge.low_reference().tolist() == [True, True, False, False]  # NaN: no reading, not a dark one


def test_the_fit_leaves_out_a_dark_stretch_and_says_so(dark: tuple[Recording, np.ndarray]) -> None:
    rec, low = dark
    cal, without = fit_thermal(rec, 0), fit_thermal(rec.select(~low), 0)
    _assert_same_calibration(cal, without)
    assert cal.fit["samples_excluded_low_reference"] == int(low.sum())
    assert cal.fit["samples_total"] == len(rec)
    assert without.fit["samples_excluded_low_reference"] == 0
    # the calibration is the sensor's, not the dark stretch's: the gains of the clean run
    clean = fit_thermal(simulate_recording(_config({}), seed=SEED), 0)
    np.testing.assert_allclose(np.diag(cal.M[0]), np.diag(clean.M[0]), rtol=0.01)
    # a visit partly dark keeps its lit samples
    usable, _ = calibration_samples(rec)
    visit = (rec.pose_id == rec.pose_id[np.flatnonzero(low)[0]]) & (rec.t_s > T0_S - 0.6) & (rec.t_s < T0_S)
    assert visit.sum() >= 40 and usable[visit].any() and not usable[low].any()
    assert np.array_equal(usable[~low], calibration_samples(rec.select(~low))[0])


def test_a_dark_stretch_across_blocks_is_left_out_as_in_one_block(dark: tuple[Recording, np.ndarray],
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Blocks of 301 samples, the stretch across many of them: the preparation equals that of the recording without
    the stretch, bit for bit (the blocks left are cut again as a file without them would be)."""
    rec, low = dark
    monkeypatch.setattr(static_detector, "BLOCK_ROWS", 301)
    monkeypatch.setattr(fit_stream, "BLOCK_ROWS", 301)
    a, b = prepare(rec, 1, chunk=700), prepare(rec.select(~low), 1, chunk=700)
    for name in ("pose", "level", "xtx", "xtg", "gtg", "xsum", "gsum", "count"):
        assert np.array_equal(getattr(a.stats, name), getattr(b.stats, name)), name
    assert (a.n_used, a.n_excluded_motion, a.n_excluded_other) == (b.n_used, b.n_excluded_motion, b.n_excluded_other)
    assert a.detector == b.detector
    assert (a.n_total, a.n_excluded_low_reference) == (len(rec), int(low.sum()))
    t = rec.t_s[low]
    assert a.low_reference.as_dict() == {"samples": int(low.sum()), "stretches": 1, "runs": [0],
                                         "first_stretches": [[0, float(t[0]), float(t[-1]), int(low.sum())]]}
    assert np.array_equal(calibration_samples(rec)[0][~low], calibration_samples(rec.select(~low))[0])
    # a given selection that names dark samples does not fit them either
    given = prepare(rec, 1, usable=np.ones(len(rec), bool), chunk=700)
    assert given.n_excluded_low_reference == int(low.sum()) and given.n_used <= int((~low).sum())


def test_streamed_and_in_memory_fits_leave_out_the_stretch_and_warn(dark: tuple[Recording, np.ndarray], tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    rec, low = dark
    path, lit = tmp_path / "dark.mcap", tmp_path / "lit.mcap"
    write_recording(path, rec, {"sensor_id": "sim"})
    write_recording(lit, rec.select(~low), {"sensor_id": "sim"})
    back = read_recording(path)
    streamed = prepare_stream([McapSampleStream(path)], 0)
    in_memory = prepare(back, 0)
    assert (streamed.n_used, streamed.n_total, streamed.n_excluded_low_reference) == (
        in_memory.n_used, in_memory.n_total, in_memory.n_excluded_low_reference) == (
        in_memory.n_used, len(rec), int(low.sum()))
    assert streamed.low_reference.as_dict() == in_memory.low_reference.as_dict()
    cals = {}
    for name, src, extra in (("streamed", path, []), ("memory", path, ["--in-memory"]), ("lit", lit, [])):
        capsys.readouterr()
        assert cli_main(["fit", str(src), "-o", str(tmp_path / f"{name}.yaml"), "--degree", "0", *extra]) == 0
        cals[name] = ThermalCalibration.load(tmp_path / f"{name}.yaml")
        lines = [w for w in capsys.readouterr().err.splitlines() if "reference below" in w]
        if name == "lit":
            assert lines == []
            continue
        assert len(lines) == 1, lines
        assert lines[0].startswith(f"warning: {int(low.sum())} samples with the reference below {LOW_REFERENCE_COUNTS}")
        assert f"t = {rec.t_s[low][0]:.2f}-{rec.t_s[low][-1]:.2f} s" in lines[0]
        assert "driver" in lines[0]
    _assert_same_calibration(cals["streamed"], cals["lit"])
    _assert_same_calibration(cals["memory"], cals["lit"])
    assert "clipped" not in " ".join(str(v) for v in cals["streamed"].fit.values() if isinstance(v, str))
    assert cals["streamed"].fit["visits_excluded_clipped"] == 0


def test_diagnose_gives_the_diagnosis_without_the_stretch_and_says_so(dark: tuple[Recording, np.ndarray]) -> None:
    rec, low = dark
    for static in SAMPLE_SELECTIONS:
        data = prepare_data(rec, static)
        ref = prepare_data(rec.select(~low), static)
        assert data.n_low_reference == int(low.sum()) and ref.n_low_reference == 0
        assert np.array_equal(data.use, ref.use), static
        assert data.n_clipped_visits == 0
    res, ref = diagnose(rec, search_rows=None), diagnose(rec.select(~low), search_rows=None)
    assert [a[0] for a in res.added] == [a[0] for a in ref.added]
    np.testing.assert_allclose(res.noise_floor, ref.noise_floor, rtol=1e-12)
    np.testing.assert_allclose(res.after_heldout_rmse, ref.after_heldout_rmse, rtol=1e-12)
    np.testing.assert_allclose(res.before_heldout_rmse, ref.before_heldout_rmse, rtol=1e-12)
    note = [w for w in res.warnings if "reference below" in w]
    assert len(note) == 1 and note[0].startswith(f"{int(low.sum())} samples with the reference below")
    assert "driver" in note[0]
    assert [w for w in res.warnings if w not in note] == ref.warnings


def test_report_statistics_leave_out_the_stretch_and_warn(dark: tuple[Recording, np.ndarray], tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    rec, low = dark
    cal = tmp_path / "cal.yaml"
    fit_thermal(rec.select(~low), 0).save(cal)
    texts = {}
    for name, part in (("dark", rec), ("lit", rec.select(~low))):
        write_recording(tmp_path / f"{name}.mcap", part, {"sensor_id": "sim"})
        capsys.readouterr()
        assert cli_main(["report", str(tmp_path / f"{name}.mcap"), "--calibration", str(cal), "--max-degree", "0",
                         "-o", str(tmp_path / name)]) == 0
        lines = [w for w in capsys.readouterr().err.splitlines() if "reference below" in w]
        assert len(lines) == (name == "dark"), lines
        texts[name] = [t for t in (tmp_path / name / "report.md").read_text().splitlines() if "mcap" not in t]
    assert texts["dark"] == texts["lit"]
