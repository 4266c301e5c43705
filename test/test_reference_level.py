"""The reference (source) power away from its level in the calibration: flagged, warned, covariance inflated.

Eq. 24 divides the axis counts by the reference counts so that the source power cancels; it cancels only if
the counts carry no offset (detector dark current, ADC zero: the simulator's ``reference_dark_offset``, 20
counts on the reference), and the detector noise, in counts, does not scale with the power at all. So when the
reference reads well off the level it had at the calibration's temperature (a connector re-mated, a fibre bend,
an ageing source), the calibrated output is biased and noisier than the calibration's ``noise_sigma_mps2``.
Measured on the unchanged driver with this file's ``run`` (24 degC, z up, after the drop): a source at 0.9 of its
power gave mean NEES (e^2 / published variance) 4.6 / 18.4 / 9.7 (x / y / z; bias -0.34 / -0.40 / -0.38 m/s^2),
at 0.8 16.9 / 89 / 47, with no flag, no counter and every diagnostic OK: the covariance was silently far too small
(``bench/nees_probe.py``, case ``source_power``, 12 poses: 41 / 260 / 120 at 0.7). The calibration now records the
reference level per temperature level of its fit (``reference_level``), and the driver flags a reading more than
``reference_level_tolerance`` (default 3 %) off it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from test_driver_core import levels, snapshot, values  # the diagnostics' snapshot of the unit tests

from fbg_accel_driver.driver_core import CoreConfig, DriverCore
from fbg_accel_driver.driver_diagnostics import OK, WARN, DriverDiagnostics
from fbg_accel_driver.thermal_model import CalibrationFileError, ThermalCalibration
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig

REPO = Path(__file__).resolve().parents[1]
HOST_DELAY_S = 0.002


def run(cal: ThermalCalibration, level: float, cfg: CoreConfig | None = None, seconds: float = 40.0):
    """24 degC, z up, the source at ``level`` of its power from 20 s on; (core, truth time, records, true accel)."""
    sim_cfg = SimConfig.default().with_overrides({
        "scenario.temperature.initial_c": 24.0, "scenario.duration_s": seconds,
        "faults.source_dropout.windows": [{"start_s": 20.0, "duration_s": 1e6, "level": level}]})
    sim = BoardSimulator(sim_cfg, seed=5)
    blk = sim.step(sim.samples_for(seconds))
    pieces = blk.wire_pieces()
    core = DriverCore(cal, cfg or CoreConfig())
    recs = []
    for k in range(0, len(pieces), 10):
        last = min(k + 10, len(pieces)) - 1
        recs += core.feed(b"".join(pieces[k:last + 1]), round(float(blk.t_s[last] + HOST_DELAY_S) * 1e9)).imu
    t = np.array([r.stamp_ns for r in recs]) * 1e-9 - HOST_DELAY_S
    truth = np.stack([np.interp(t, blk.t_s, blk.accel_true_mps2[:, j]) for j in range(3)], axis=1)
    return core, t, recs, truth


def nees(recs: list, truth: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Mean e^2 / published variance per axis over the selected records."""
    acc = np.array([r.accel_mps2 for r in recs])[sel]
    var = np.array([(r.covariance[0], r.covariance[4], r.covariance[8]) for r in recs])[sel]
    return np.mean((acc - truth[sel]) ** 2 / var, axis=0)


def test_the_shipped_calibration_records_the_reference_level_of_its_fit() -> None:
    cal = ThermalCalibration.load(REPO / "config" / "calibration_sim.yaml")
    t, c = cal.reference_level_temperature_c, cal.reference_level_counts
    assert len(t) == 3 and np.all(np.diff(t) > 0)  # the three chamber levels, ascending
    assert np.all((c > 700) & (c < 1000)), c  # the simulated reference: 870 counts at 23.4 degC, -0.5 %/degC
    # between levels the expected level is interpolated linearly in temperature
    mid = 0.5 * (t[0] + t[1])
    assert cal.expected_reference_counts(mid) == pytest.approx(0.5 * (c[0] + c[1]))


@pytest.mark.parametrize("level", [0.9, 0.8])
def test_a_reference_off_its_calibrated_level_is_flagged_warned_and_inflated(level: float) -> None:
    cal = ThermalCalibration.load(REPO / "config" / "calibration_sim.yaml")
    core, t, recs, truth = run(cal, level)
    before, after = (t > 2.0) & (t < 19.5), t > 21.0
    flagged = np.array(["reference_level_changed" in r.flags for r in recs])
    assert not flagged[before].any()  # the source's own wander stays inside the tolerance
    assert flagged[after].all()
    assert core.counters.reference_level_changed == int(flagged.sum())
    # the variance grows at least by the noise growth (counts noise over a smaller reference) times the factor
    var = np.array([(r.covariance[0], r.covariance[4], r.covariance[8]) for r in recs])
    base = np.median(var[before], axis=0)
    assert np.all(var[after] >= base * core.config.out_of_range_variance_factor / level**2 * 0.9)
    got = nees(recs, truth, after)
    print(f"source x{level}: mean NEES after the drop {np.round(got, 2)} (before the fix: see the module docstring)")
    assert np.all(got < (3.0 if level == 0.9 else 10.0)), got
    assert np.all(nees(recs, truth, before) < 1.5)
    d = DriverDiagnostics()
    d.report(snapshot(0.0, frames=0))
    e = d.report(snapshot(1.0, frames=100, core=core.counters.as_dict()))
    assert levels(e)["reference level"] == WARN
    assert values(e, "reference level")["reference_level_changed"] == str(core.counters.reference_level_changed)
    assert levels(d.report(snapshot(2.0, frames=200, core=core.counters.as_dict())))["reference level"] == OK


def test_without_a_recorded_level_nothing_is_flagged_and_the_tolerance_is_a_setting() -> None:
    cal = ThermalCalibration.load(REPO / "config" / "calibration_sim.yaml")
    older = dataclasses.replace(cal, reference_level_temperature_c=np.zeros(0), reference_level_counts=np.zeros(0))
    core, *_ = run(older, 0.8, seconds=25.0)
    assert core.counters.reference_level_changed == 0  # a file from before this key: no level to compare with
    wide, *_ = run(cal, 0.8, CoreConfig(reference_level_tolerance=0.25), seconds=25.0)
    assert wide.counters.reference_level_changed == 0
    with pytest.raises(ValueError, match="reference_level_tolerance"):
        CoreConfig(reference_level_tolerance=0.0).validate()


def test_the_reference_level_round_trips_and_a_bad_one_is_refused(tmp_path: Path) -> None:
    cal = ThermalCalibration.load(REPO / "config" / "calibration_sim.yaml")
    cal.save(tmp_path / "c.yaml")
    assert ThermalCalibration.load(tmp_path / "c.yaml") == cal
    text = (tmp_path / "c.yaml").read_text()
    for bad, message in ((text.replace("counts: [", "counts: [-5.0, "), "reference_level"),
                         (text.replace("reference_level:", "reference_level: 3\nx_reference_level:"), "reference_level")):
        (tmp_path / "bad.yaml").write_text(bad)
        with pytest.raises(CalibrationFileError, match=message):
            ThermalCalibration.load(tmp_path / "bad.yaml")


def test_the_fit_records_the_reference_level_of_its_samples() -> None:
    """``fbg-accel-calib fit`` (``fit_thermal``, the streamed preparation's per-level sums) writes the mean
    reference counts of the samples it fitted at each temperature level."""
    from fbg_accel_calibration.fit.fit_pipeline import fit_thermal
    from fbg_accel_sim.board_physics import simulate_recording

    cfg = SimConfig.default().with_overrides({"scenario.poses.mode": "six_position", "scenario.poses.dwell_s": 8.0,
                                              "scenario.poses.move_s": 3.0, "scenario.temperature.initial_c": 30.0})
    rec = simulate_recording(cfg, seed=2)
    cal = fit_thermal(rec, 0)
    assert len(cal.reference_level_counts) == 1
    still = rec.pose_id >= 0
    assert cal.reference_level_counts[0] == pytest.approx(np.mean(rec.ref[still]), abs=2.0)  # static samples only
    assert cal.reference_level_temperature_c[0] == pytest.approx(np.nanmean(rec.temp_c[still]), abs=0.05)
