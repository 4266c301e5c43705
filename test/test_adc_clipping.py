"""A channel at a rail of the 12-bit ADC (0 or 4095 counts) in a calibration recording.

A clipped reading bounds the signal instead of measuring it: a calibration fit that takes it as a
value is pulled by the difference (a 6 s saturation window on x took the x residual of the fit far above
the noise floor, and ``diagnose`` added a spectral non-linearity to absorb it). Where the signal sits
near the rail, the samples of the visit that are not clipped are a censored, biased subset. So a visit
(one contiguous stay at one pose) with any clipped sample is left out whole, by the static detector
(``fit``, degree selection, reports) and by ``diagnose``, and both say how many samples and visits went.
The simulator's ``faults.adc_saturation`` windows force a channel to full scale (paper 3.5: the ESP32's
12-bit converters).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_diagnose_sim import _config

from fbg_accel_calibration.commands.cli import main as cli_main
from fbg_accel_calibration.diagnosis.design import SAMPLE_SELECTIONS, prepare_data
from fbg_accel_calibration.diagnosis.diagnose import diagnose
from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_calibration.fit.fit_stream import SampleBlockSource, prepare_stream
from fbg_accel_calibration.fit.static_detector import calibration_samples
from fbg_accel_calibration.io.mcap_reader import McapSampleStream, read_recording
from fbg_accel_calibration.io.mcap_writer import write_recording
from fbg_accel_calibration.io.recording import Recording
from fbg_accel_driver.frame_codec import ADC_MAX
from fbg_accel_sim.board_physics import simulate_recording

SEED = 11  # a seed of test_diagnose_sim's "nothing injected, nothing added"


@pytest.fixture(scope="module")
def clean() -> Recording:
    return simulate_recording(_config({}), seed=SEED)


@pytest.fixture(scope="module")
def saturated(clean: Recording) -> Recording:
    """The same run with x forced to full scale for 6 s from a third of the way in (a visit and a half)."""
    t0 = float(clean.t_s[len(clean) // 3])
    return simulate_recording(_config({"faults.adc_saturation.windows": [
        {"start_s": t0, "duration_s": 6.0, "channels": ["x"]}]}), seed=SEED)


def _visits(rec: Recording) -> np.ndarray:
    """Visit number (N,) of every sample: a new one where the pose or the run changes."""
    change = np.r_[True, (np.diff(rec.pose_id) != 0) | (np.diff(rec.run_id) != 0)]
    return np.cumsum(change) - 1


def _with_visit_near_the_rail(rec: Recording, rail: int) -> tuple[Recording, np.ndarray]:
    """``rec`` with the x counts of one mid-run visit moved next to ``rail``: the noise clips some of its
    samples, not all. Returns the recording and that visit's samples (N,) bool."""
    visits = _visits(rec)
    posed = np.flatnonzero(rec.pose_id >= 0)
    visit = visits == visits[posed[len(posed) // 2]]
    x = rec.xyz[:, 0].copy()
    target = ADC_MAX - 1.0 if rail else 1.0  # the visit's mean one count inside the rail
    x[visit] = np.clip(x[visit] - np.mean(x[visit]) + target, 0, ADC_MAX)
    assert 0 < np.mean(x[visit] == rail) < 1  # some samples clipped, some not
    xyz = rec.xyz.copy()
    xyz[:, 0] = x
    out = Recording(rec.t_s, rec.ref, xyz, rec.temp_c, rec.gref_mps2, rec.pose_id, rec.run_id, dict(rec.metadata))
    return out, visit


@pytest.mark.parametrize("rail", [0, ADC_MAX])
def test_a_visit_with_a_clipped_sample_is_left_out_whole(clean: Recording, rail: int) -> None:
    rec, visit = _with_visit_near_the_rail(clean, rail)
    usable_clean, _ = calibration_samples(clean)
    usable, _ = calibration_samples(rec)
    assert usable_clean[visit].any()  # the detector took that visit when it was not clipped
    assert not usable[visit].any()
    # the other visits keep their samples (the noise floor, hence the threshold, may move a little)
    assert usable[~visit].sum() >= 0.98 * usable_clean[~visit].sum()
    for static in SAMPLE_SELECTIONS:  # and the diagnosis, whichever samples it judges
        use, use_clean = prepare_data(rec, static).use, prepare_data(clean, static).use
        assert use_clean[visit].any() and not use[visit].any(), static
        assert use[~visit].sum() >= 0.98 * use_clean[~visit].sum(), static


def test_visits_across_blocks_are_left_out_as_in_one_block(saturated: Recording, monkeypatch: pytest.MonkeyPatch) -> None:
    """The visits are numbered block after block (a file is read so): blocks that cut the clipped visits
    leave out the same samples as one block."""
    import fbg_accel_calibration.fit.static_detector as sd

    whole = calibration_samples(saturated)[0]
    monkeypatch.setattr(sd, "BLOCK_ROWS", 97)  # cuts most visits (a visit is 300 samples)
    assert np.array_equal(calibration_samples(saturated)[0], whole)
    assert not whole[saturated.clipped()].any()


def test_a_saturation_window_leaves_the_fit_as_without_it(clean: Recording, saturated: Recording) -> None:
    assert saturated.clipped().sum() > 0 and not clean.clipped().any()
    base, cal = fit_thermal(clean, 0), fit_thermal(saturated, 0)
    # the visits taken out cost precision, not accuracy: the residual as without the window, and the two
    # calibrations agree on the clean run's static samples to a fraction of the noise of one sample
    assert np.all(np.asarray(cal.fit["rmse_mps2"]) <= 1.1 * np.asarray(base.fit["rmse_mps2"]))
    usable, _ = calibration_samples(clean)
    r = clean.select(usable)
    diff = cal.apply_counts(r.ref, r.xyz, r.temp_c, r.t_s) - base.apply_counts(r.ref, r.xyz, r.temp_c, r.t_s)
    assert np.all(np.sqrt(np.mean(diff**2, axis=0)) < 0.2 * np.asarray(base.noise_sigma_mps2))
    visits = _visits(saturated)
    tainted = np.unique(visits[saturated.clipped() & (saturated.pose_id >= 0)])
    posed = np.isin(visits, tainted) & (saturated.pose_id >= 0)
    assert cal.fit["visits_excluded_clipped"] == len(tainted) >= 2  # the window spans two visits
    assert cal.fit["samples_excluded_clipped"] == int(posed.sum())
    assert base.fit["visits_excluded_clipped"] == 0 == base.fit["samples_excluded_clipped"]


def test_a_file_streamed_leaves_out_the_same_visits(saturated: Recording, tmp_path: Path) -> None:
    path = tmp_path / "saturated.mcap"
    write_recording(path, saturated)
    sources: list[SampleBlockSource] = [McapSampleStream(path)]
    streamed = prepare_stream(sources, 0)
    back = read_recording(path)  # no reference between poses in a file: not the simulator's samples in motion
    usable, _ = calibration_samples(back)
    assert streamed.n_used == int(usable.sum())
    assert streamed.n_excluded_clipped == fit_thermal(back, 0).fit["samples_excluded_clipped"] > 0
    assert streamed.n_clipped_visits == fit_thermal(back, 0).fit["visits_excluded_clipped"] >= 2


def test_a_source_dropout_is_not_a_clipped_reading(clean: Recording) -> None:
    """No light reads 0 on every channel: those samples are invalid one by one (Psi undefined), and the
    rest of their visit is kept."""
    visits, posed = _visits(clean), np.flatnonzero(clean.pose_id >= 0)
    t0 = float(clean.t_s[visits == visits[posed[len(posed) // 2]]][0]) + 1.0  # 1 s into a 3 s visit
    rec = simulate_recording(_config({"faults.source_dropout.windows": [
        {"start_s": t0, "duration_s": 0.5, "level": 0.0}]}), seed=SEED)
    dark = (rec.t_s >= t0) & (rec.t_s < t0 + 0.5) & (rec.ref == 0)
    assert dark.sum() > 20 and (rec.xyz[dark] == 0).any()
    assert not rec.clipped().any()
    cal = fit_thermal(rec, 0)
    assert cal.fit["visits_excluded_clipped"] == 0
    visit = _visits(rec) == _visits(rec)[np.flatnonzero(dark)[0]]
    usable, _ = calibration_samples(rec)
    assert usable[visit & ~dark].any()  # the visit's samples with light are kept


def test_fit_command_warns_of_the_visits_it_left_out(saturated: Recording, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "saturated.mcap"
    write_recording(path, saturated)
    assert cli_main(["fit", str(path), "-o", str(tmp_path / "cal.yaml"), "--degree", "0"]) == 0
    cal = fit_thermal(read_recording(path), 0)
    assert (f"warning: {cal.fit['samples_excluded_clipped']} samples of {cal.fit['visits_excluded_clipped']} visit(s) "
            "left out") in capsys.readouterr().err


def test_no_clipped_sample_is_judged_whichever_the_selection(saturated: Recording) -> None:
    clipped = saturated.clipped()
    assert (clipped & (saturated.pose_id < 0)).any()  # the window reaches into a move
    for static in SAMPLE_SELECTIONS:  # "all" judges samples taken while the table moves too
        assert not prepare_data(saturated, static).use[clipped].any(), static


def test_diagnose_adds_nothing_for_a_saturation_window_and_says_what_it_left_out(saturated: Recording) -> None:
    res = diagnose(saturated)
    assert res.added == [], [(c.name, round(c.rel_gain, 3), c.p_value) for c in res.ranked]
    assert not res.structure.significant, res.structure.verdict
    note = [w for w in res.warnings if "clipped" in w]
    assert len(note) == 1 and f"{res.data.n_clipped_samples} samples" in note[0]
    assert res.data.n_clipped_visits >= 2
