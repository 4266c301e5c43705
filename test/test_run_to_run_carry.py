"""The slow error's run-to-run component R: written to the calibration file when the campaign identifies it, and
carried into a later one-run-per-level recalibration of the same sensor (``fit --run-to-run-from``)."""

from __future__ import annotations

import dataclasses
import hashlib
import re

import numpy as np
import pytest
import yaml
from test_driver_core import make_cal

from fbg_accel_calibration.commands.cli import main as cli_main
from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
from fbg_accel_calibration.fit.fit_stream import prepare
from fbg_accel_calibration.fit.slow_error import attach, carried_run_to_run
from fbg_accel_calibration.io.mcap_writer import write_recording
from fbg_accel_driver.slow_error import SlowErrorSection
from fbg_accel_driver.thermal_model import CalibrationFileError, ThermalCalibration
from fbg_accel_sim.eq28_campaign import campaign

NOISE, TAU_S, RUN_OFFSET = 0.05, 0.15, 0.04  # as test_slow_error's run-to-run campaigns
R = np.diag([1e-3, 2e-3, 3e-3])


def fitted(seed: int, runs_per_level: int) -> ThermalCalibration:
    rec, _ = campaign(seed, degree=2, tilt_sigma_deg=0.0, noise_mps2=NOISE, tau_s=TAU_S, visit_s=1.0, repeats=1,
                      runs_per_level=runs_per_level, run_offset_mps2=RUN_OFFSET)
    data = prepare(rec, 2, usable=np.ones(len(rec), bool))
    cal = fit_thermal(data, 2, sensor_id="SN-A")
    attach(cal, data.stats, 0.01)
    return cal


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """An earlier calibration of sensor SN-A with R identified (two runs per level), one without (one run per level),
    and a later one-run-per-level recording of the sensor."""
    d = tmp_path_factory.mktemp("r2r")
    fitted(11, 2).save(d / "earlier.yaml")
    fitted(12, 1).save(d / "one_run.yaml")
    rec, _ = campaign(13, degree=2, tilt_sigma_deg=0.0, noise_mps2=NOISE, tau_s=TAU_S, visit_s=1.0, repeats=1,
                      run_offset_mps2=RUN_OFFSET)
    write_recording(d / "later.mcap", rec)
    rec2, _ = campaign(14, degree=2, tilt_sigma_deg=0.0, noise_mps2=NOISE, tau_s=TAU_S, visit_s=1.0, repeats=1,
                       runs_per_level=2, run_offset_mps2=RUN_OFFSET)
    for k in np.unique(rec2.run_id):  # a file per run: the fit's runs are its inputs
        write_recording(d / f"repeated_{k}.mcap", rec2.select(rec2.run_id == k))
    return d


def test_an_identified_run_to_run_component_is_written_and_read_back(files) -> None:
    """Before, only the total (S + R (1 + h)) was written: a later campaign had nothing to take R from."""
    cal = ThermalCalibration.load(files / "earlier.yaml")
    run = cal.slow_error.run_to_run
    assert run is not None and run.shape == (3, 3)
    assert cal.fit["slow_error"]["run_to_run_sigma_mps2"] == [round(float(v), 5) for v in np.sqrt(np.diag(run))]
    assert ThermalCalibration.load(files / "one_run.yaml").slow_error.run_to_run is None  # not identified: not written


def test_the_section_reads_old_files_and_refuses_a_bad_run_to_run_matrix() -> None:
    d = make_cal(slow_error=SlowErrorSection(2 * R, "test", 30, R)).to_dict()
    assert ThermalCalibration.from_dict(d).slow_error.run_to_run.tolist() == R.tolist()
    del d["slow_error"]["run_to_run_matrix"]  # a file written before the key: loads, R not known
    assert ThermalCalibration.from_dict(d).slow_error.run_to_run is None
    for value, message in (([[1e-3, 0.0], [0.0, 1e-3]], "slow_error.run_to_run_matrix must be 3 x 3"),
                           ([[1e-3, 2e-3, 0], [2e-3, 1e-3, 0], [0, 0, 1e-3]], "not positive semi-definite")):
        d["slow_error"]["run_to_run_matrix"] = value
        with pytest.raises(CalibrationFileError, match=message):
            ThermalCalibration.from_dict(d)
    del d["slow_error"]["run_to_run_matrix"]
    d["slow_error"]["run_to_run_matrx"] = R.tolist()
    with pytest.raises(CalibrationFileError, match=re.escape("did you mean 'slow_error.run_to_run_matrix'")):
        ThermalCalibration.from_dict(d)


def fit(files, out: str, *extra: str, recording: str = "later.mcap") -> int:
    inputs = [str(p) for p in sorted(files.glob(recording))]
    return cli_main(["fit", *inputs, "--degree", "2", "--sensor-id", "SN-A", "-o", str(files / out), *extra])


def test_a_one_run_recalibration_carries_the_earlier_run_to_run_component(files, capsys) -> None:
    """The carried R is added as for a new run, (1 + h) R with h = 1 (b(T) took up each of this campaign's runs'
    constants), to the visit part this campaign estimates; the method names the file, its date and hash."""
    earlier = ThermalCalibration.load(files / "earlier.yaml")
    assert fit(files, "plain.yaml") == 0
    # without the option, fit tells the user of the paper's design that the run-to-run part is not in the slow error
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("slow error of a pose mean"))
    assert "run-to-run component not identified (one run per temperature level" in line
    assert fit(files, "carried.yaml", "--run-to-run-from", str(files / "earlier.yaml")) == 0
    out = capsys.readouterr().out
    plain, carried = (ThermalCalibration.load(files / n).slow_error for n in ("plain.yaml", "carried.yaml"))
    assert plain.run_to_run is None
    np.testing.assert_array_equal(carried.run_to_run, earlier.slow_error.run_to_run)
    np.testing.assert_allclose(carried.matrix - plain.matrix, 2.0 * carried.run_to_run, rtol=1e-6, atol=1e-12)
    digest = hashlib.sha256((files / "earlier.yaml").read_bytes()).hexdigest()[:12]
    source = f"earlier.yaml (created {earlier.created}, sha256 {digest})"
    assert carried.method.endswith(f"; plus the run-to-run component carried from {source} (not identified by this "
                                   "campaign: one run per temperature level)")
    assert f"m/s^2 (carried from {source})" in out


def refused(files, capsys, out: str, *extra: str) -> str:
    assert fit(files, out, *extra) == 2
    assert not (files / out).exists() and not list(files.glob(f".{out}*"))  # nothing written, not even half
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    return err[0]


def test_refusals_are_one_line_and_write_nothing(files, capsys) -> None:
    one = files / "one_run.yaml"
    assert refused(files, capsys, "r1.yaml", "--run-to-run-from", str(one)) == (
        f"fbg-accel-calib fit: --run-to-run-from {one}: no run-to-run component in its slow_error (its campaign did "
        "not identify it); give the calibration of a campaign with a temperature level run twice")
    missing = files / "nope.yaml"
    assert refused(files, capsys, "r2.yaml", "--run-to-run-from", str(missing)) == (
        f"fbg-accel-calib fit: --run-to-run-from: {missing}: calibration file not found")
    other = yaml.safe_load((files / "earlier.yaml").read_text())
    other["sensor_id"] = "SN-B"
    (files / "other.yaml").write_text(yaml.safe_dump(other, sort_keys=False))
    digest = hashlib.sha256((files / "other.yaml").read_bytes()).hexdigest()[:12]
    assert refused(files, capsys, "r3.yaml", "--run-to-run-from", str(files / "other.yaml")) == (
        f"fbg-accel-calib fit: --run-to-run-from: other.yaml (created {other['created']}, sha256 {digest}) is a "
        "calibration of sensor 'SN-B', this campaign is of sensor 'SN-A': the run-to-run component belongs to one "
        "sensor")


def test_a_campaign_that_identifies_its_own_keeps_it_and_says_the_earlier_one_was_not_used(files, capsys) -> None:
    assert fit(files, "own.yaml", "--run-to-run-from", str(files / "earlier.yaml"), recording="repeated_*.mcap") == 0
    err = capsys.readouterr().err
    own = ThermalCalibration.load(files / "own.yaml")
    earlier = ThermalCalibration.load(files / "earlier.yaml").slow_error.run_to_run
    assert own.slow_error.run_to_run is not None and not np.array_equal(own.slow_error.run_to_run, earlier)
    assert "carried" not in own.slow_error.method and "run_to_run_not_carried" in own.fit["slow_error"]
    assert "note: --run-to-run-from earlier.yaml (created " in err
    assert (") not used: this campaign identifies its own run-to-run component (a temperature level with two or more "
            "runs), which is the sensor's now") in err


def test_a_carried_component_that_cannot_be_used_is_said_so(files) -> None:
    """A campaign whose slow error is not estimated (here: the visits' own sums were not kept) cannot
    take an earlier R either: the fit's figures say so instead of dropping it without a word."""
    rec, _ = campaign(15, degree=2, tilt_sigma_deg=0.0, noise_mps2=NOISE, tau_s=TAU_S, visit_s=1.0, repeats=1)
    data = prepare(rec, 2, usable=np.ones(len(rec), bool))
    cal = fit_thermal(data, 2, sensor_id="SN-A")
    earlier = carried_run_to_run(files / "earlier.yaml")
    kept_none = dataclasses.replace(data.stats, visit_cell=np.zeros(0, np.int64))  # the visits' own sums not kept
    assert attach(cal, kept_none, 0.01, earlier) is None and cal.slow_error is None
    note = cal.fit["slow_error"]["run_to_run_not_carried"]
    assert note.startswith("--run-to-run-from earlier.yaml (created ")
    assert "not used: this campaign's slow error is not estimated (the visits' own sums were not kept" in note


def test_an_unknown_sensor_id_cannot_be_checked_and_is_said_so(files, capsys) -> None:
    """The campaign's recordings name no sensor and no --sensor-id is given: R is carried, with a note that the match
    of the sensors could not be checked."""
    assert cli_main(["fit", str(files / "later.mcap"), "--degree", "2", "-o", str(files / "anon.yaml"),
                     "--run-to-run-from", str(files / "earlier.yaml")]) == 0
    err = capsys.readouterr().err
    assert ThermalCalibration.load(files / "anon.yaml").slow_error.run_to_run is not None
    assert ": the sensor ids ('SN-A', this campaign 'unknown') do not tell whether it is the same sensor; its " \
           "run-to-run component is used" in err


def test_the_calibration_node_end_of_run_fit_carries_r_as_the_fit_command_does(files, capsys) -> None:
    """The node's end-of-run fit (``run_refit.refit``, parameter ``run_to_run_from``) goes through the same fit
    pipeline as ``fit --run-to-run-from``: the same slow error, R carried and named, and its report says where R came
    from. Before, ``refit`` took no R: a one-run-per-level refit by the node wrote "not identified"."""
    from fbg_accel_calibration.fit.slow_error import carried_run_to_run
    from fbg_accel_calibration.recorder.run_refit import refit

    earlier = ThermalCalibration.load(files / "earlier.yaml").slow_error.run_to_run
    assert fit(files, "cli_carried.yaml", "--run-to-run-from", str(files / "earlier.yaml")) == 0
    carried = carried_run_to_run(files / "earlier.yaml", option="run_to_run_from")
    result = refit([str(files / "later.mcap")], files / "node.yaml", degree=2, sensor_id="SN-A",
                   run_to_run_from=carried)
    capsys.readouterr()
    node, cli = (ThermalCalibration.load(files / n).slow_error for n in ("node.yaml", "cli_carried.yaml"))
    np.testing.assert_array_equal(node.run_to_run, earlier)
    np.testing.assert_allclose(node.matrix, cli.matrix, rtol=1e-9, atol=1e-15)
    assert node.method == cli.method and "carried from earlier.yaml (created " in node.method
    line = next(x for x in result.report().splitlines() if x.startswith("slow error of a pose mean"))
    assert line.endswith(f"m/s^2 (carried from {carried.source})")
    plain = refit([str(files / "later.mcap")], files / "node_plain.yaml", degree=2, sensor_id="SN-A")
    assert "run-to-run component not identified (one run per temperature level" in plain.report()
    assert plain.calibration.slow_error.run_to_run is None
