"""DriverCore with a calibration's ``dynamic`` section: stamps moved back by the chain delay, counts
equalised before eq. 24 (issue 9; fbg_accel_driver.chain_compensation)."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_chain_compensation import _amp_phase, _lowpass
from test_driver_core import feed_frames, make_cal

from fbg_accel_driver.chain_compensation import ChainDynamics
from fbg_accel_driver.driver_core import CoreConfig, DriverCore
from fbg_accel_driver.frame_codec import Frame
from fbg_accel_driver.thermal_model import ThermalCalibration

FS = 100.0
GOOD = 3
DYN = ChainDynamics(cutoff_hz=(1.0, 1.7, 1.3, 1.3), delay_s=(0.0, 0.0, 0.0))


def _frames(true_counts: np.ndarray) -> list[Frame]:
    """Frames of (N, 4) true channel counts (ref, x, y, z) after each channel's own TIA low-pass."""
    seen = np.column_stack([_lowpass(true_counts[:, j], DYN.cutoff_hz[j], FS) for j in range(4)])
    c = np.round(seen).astype(int)
    return [Frame(seq=i % 65536, t_us=i * 10_000, ref=int(c[i, 0]), x=int(c[i, 1]), y=int(c[i, 2]), z=int(c[i, 3]),
                  temp_cc=2340, status=GOOD) for i in range(len(c))]


def _core(mode: str, bandwidth: float = 10.0) -> DriverCore:
    return DriverCore(make_cal(dynamic=DYN), CoreConfig(chain_compensation=mode, equalise_bandwidth_hz=bandwidth))


def _truth(cal: ThermalCalibration, true_counts: np.ndarray) -> np.ndarray:
    n = len(true_counts)
    return cal.apply_counts(true_counts[:, 0], true_counts[:, 1:], np.full(n, 23.4), np.arange(n) / FS)


def test_delay_mode_moves_every_stamp_back_by_the_dc_group_delay_and_keeps_the_samples():
    n = 400
    counts = np.tile([870.0, 1100.0, 1600.0, 1100.0], (n, 1))
    frames = _frames(counts)
    raw0, imu0, _ = feed_frames(_core("none"), frames)
    raw1, imu1, _ = feed_frames(_core("delay"), frames)
    shift = round(DYN.stamp_delay_s("delay") * 1e9)
    assert shift == pytest.approx(np.mean([1 / (2 * math.pi * fc) for fc in (1.7, 1.3, 1.3)]) * 1e9, abs=1)
    assert [r.stamp_ns for r in raw1] == [r.stamp_ns for r in raw0]  # imu/raw keeps the board sample's time
    assert [r.stamp_ns for r in imu1] == [r.stamp_ns - shift for r in imu0]
    assert [r.accel_mps2 for r in imu1] == [r.accel_mps2 for r in imu0]


def test_equalise_undoes_the_ratio_distortion_when_the_source_power_moves():
    """Source power +-10 % at 0.5 Hz, no acceleration: Psi is constant, but the reference (1 Hz) and
    the axes (1.3-1.7 Hz) low-pass it differently, so the plain ratio of eq. 24 oscillates."""
    t = np.arange(int(30 * FS)) / FS
    p = 1.0 + 0.1 * np.sin(2 * np.pi * 0.5 * t)
    counts = np.column_stack([870.0 * p, 1100.0 * p, 1600.0 * p, 1100.0 * p])
    frames = _frames(counts)
    keep = slice(int(5 * FS), None)
    ripple = {}  # amplitude of the 0.5 Hz component (the equaliser's gain also raises the quantisation noise)
    for mode in ("none", "equalise"):
        _, imu, _ = feed_frames(_core(mode), frames)
        a = np.array([r.accel_mps2 for r in imu])[keep]
        ripple[mode] = _amp_phase(t[keep][: len(a)], a, 0.5)[0]
    assert np.all(ripple["none"] > 0.5)  # m/s^2: the distortion the issue describes
    assert np.all(ripple["equalise"] < 0.05 * ripple["none"]), ripple


@pytest.mark.parametrize("f_hz", [0.5, 2.0, 4.0])
def test_equalised_output_follows_the_true_acceleration_at_its_stamps(f_hz):
    t = np.arange(int(30 * FS)) / FS
    s = np.sin(2 * np.pi * f_hz * t)
    counts = np.column_stack([np.full_like(t, 870.0), 1100 + 300 * s, 1600 - 200 * s, 1100 + 100 * s])
    cal = make_cal(dynamic=DYN)
    true_t = t * 1e9
    truth = _truth(cal, counts)
    err = {}
    for mode in ("none", "equalise"):
        raw, imu, _ = feed_frames(_core(mode, bandwidth=20.0), _frames(counts))
        t_raw0 = raw[0].stamp_ns  # board time 0 on the ROS time line
        st = np.array([r.stamp_ns - t_raw0 for r in imu], dtype=float)
        a = np.array([r.accel_mps2 for r in imu])
        keep = st > 5e9
        ref = np.column_stack([np.interp(st[keep], true_t, truth[:, k]) for k in range(3)])
        err[mode] = np.sqrt(np.mean((a[keep] - ref) ** 2, axis=0))
    assert np.all(err["equalise"] < 0.2 * err["none"]), err


def test_equalised_covariance_carries_the_noise_gain():
    counts = np.tile([870.0, 1100.0, 1600.0, 1100.0], (100, 1))
    _, imu0, _ = feed_frames(_core("none"), _frames(counts))
    _, imu1, _ = feed_frames(_core("equalise"), _frames(counts))
    c0, c1 = np.array(imu0[-1].covariance), np.array(imu1[-1].covariance)
    assert np.all(c1[[0, 4, 8]] > 3 * c0[[0, 4, 8]])


def test_compensation_without_a_dynamic_section_is_refused():
    with pytest.raises(ValueError, match="needs a calibration with a 'dynamic' section"):
        DriverCore(make_cal(), CoreConfig(chain_compensation="delay"))
    with pytest.raises(ValueError, match="chain_compensation must be one of"):
        CoreConfig(chain_compensation="fast").validate()
    with pytest.raises(ValueError, match="above every channel"):
        _core("equalise", bandwidth=1.5)


def test_equalising_a_calibration_that_already_inverts_the_tia_is_refused():
    """diagnose can declare a tia_inverse_filter term; equalise inverts the same stages: never both."""
    from fbg_accel_driver.correction_terms import TiaInverseFilter

    cal = make_cal(dynamic=DYN)
    cal.corrections = [TiaInverseFilter(np.array([0.16, 0.094, 0.12, 0.12]))]
    with pytest.raises(ValueError, match="invert them twice"):
        DriverCore(cal, CoreConfig(chain_compensation="equalise"))
    DriverCore(cal, CoreConfig(chain_compensation="delay"))  # a stamp shift does not touch the counts


def test_dynamic_section_survives_the_calibration_file(tmp_path):
    cal = make_cal(dynamic=DYN)
    cal.save(tmp_path / "c.yaml")
    assert ThermalCalibration.load(tmp_path / "c.yaml").dynamic == DYN


@pytest.mark.parametrize("mode", ["delay", "equalise"])
def test_stamps_stay_strictly_increasing_from_the_first_sample_and_across_a_reboot(mode):
    """The equaliser cannot shift the first sample after a (re)start consistently (no interval, no previous
    sample): that one sample is not published, so the stamps never go back."""
    counts = np.tile([870.0, 1100.0, 1600.0, 1100.0], (200, 1))
    frames = _frames(counts)
    reboot = [Frame(seq=i, t_us=i * 10_000, ref=870, x=1100, y=1600, z=1100, temp_cc=2340, status=GOOD | (8 if i == 0 else 0))
              for i in range(200)]
    core = _core(mode)
    raw, imu, _ = feed_frames(core, frames + reboot)
    stamps = [r.stamp_ns for r in imu]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    primed = core.counters.chain_priming
    assert primed == (2 if mode == "equalise" else 0) and core.counters.board_resets == 1
    assert len(imu) == len(raw) - primed


def test_out_of_range_variance_comes_from_the_equalised_counts_the_value_comes_from():
    """Beyond the calibrated range the variance grows by how far eq. 28 has moved from the range edge,
    (a(Psi, T) - a(Psi, edge))^2. Under 'equalise' Psi must be the equalised one the published value comes
    from: then the variance minus that term is the same for every sample while the source power swings."""
    import dataclasses

    n = 300
    power = 1 + 0.2 * np.sin(2 * np.pi * 2.0 * np.arange(n) / FS)
    counts = np.column_stack([870 * power, 1100 * power, 1600 * power, 1100 * power])
    frames = [dataclasses.replace(f, temp_cc=5000) for f in _frames(counts)]  # 50 degC, range 10..40
    core = _core("equalise")
    _, imu, _ = feed_frames(core, frames)
    cal = core.cal
    M, b = cal.coefficients(50.0)
    rest = []
    for r in imu:
        assert "temperature_out_of_range" in r.flags
        psi = np.linalg.solve(M[0], np.array(r.accel_mps2) - b[0])
        d = np.array(cal.acceleration_at(*psi, 50.0)) - np.array(cal.acceleration_at(*psi, 40.0))
        rest.append(np.array(r.covariance)[[0, 4, 8]] - d**2)
    assert len(rest) > 200
    np.testing.assert_allclose(rest, np.repeat([rest[-1]], len(rest), 0), rtol=1e-9)


def test_equalised_counts_also_feed_the_declared_correction_terms():
    """A 40-count dark offset on the reference, declared as a correction term, and a source power swinging by
    +-10 % at 0.5 Hz with no acceleration. Under 'equalise' the correction must see the same (equalised) counts
    as eq. 28: fed the raw, differently low-passed counts it would put back part of the ripple the equaliser
    removed."""
    from fbg_accel_driver.correction_terms import ReferenceDarkOffset

    t = np.arange(int(30 * FS)) / FS
    p = 1.0 + 0.1 * np.sin(2 * np.pi * 0.5 * t)
    counts = np.column_stack([870.0 * p + 40.0, 1100.0 * p, 1600.0 * p, 1100.0 * p])
    core = DriverCore(make_cal(dynamic=DYN, corrections=[ReferenceDarkOffset(40.0)]),
                      CoreConfig(chain_compensation="equalise", equalise_bandwidth_hz=10.0))
    _, imu, _ = feed_frames(core, _frames(counts))
    a = np.array([r.accel_mps2 for r in imu])[int(5 * FS):]
    ripple = _amp_phase(t[int(5 * FS):][: len(a)], a, 0.5)[0]
    assert np.all(ripple < 0.03), ripple  # m/s^2 (raw counts: 0.26-0.30)


def test_a_calibration_without_a_dynamic_section_states_that_the_lag_is_unknown():
    """Without a ``dynamic`` section nothing moves the stamps, and the static-test build's TIA stages (1-1.7 Hz) make
    the published acceleration lag them by about 0.1 s: during the simulator's 5 s table moves between 12 poses at
    24 degC (``bench/nees_probe.py``, case ``chain``, mode none) the mean NEES was 5.2 / 22.7 / 8.8 (x / y / z; p99
    62 / 194 / 121, errors up to 1.76 m/s^2), against 1.2 / 1.15 / 1.04 with ``delay`` from the simulator's true
    dynamics. Before, ``chain_status`` was empty for such a calibration and the diagnostics had no ``chain
    compensation`` entry: the lag was stated only when the calibration knew it. Now the entry says that the chain is
    not compensated and its lag is unknown (OK: not a fault of the stream, a property of the calibration)."""
    from test_driver_core import levels, snapshot, values

    from fbg_accel_driver.driver_diagnostics import OK, DriverDiagnostics

    core = DriverCore(make_cal(), CoreConfig())
    status = core.chain_status()
    assert status["mode"] == "none" and status["dynamic_section"] == "absent"
    e = DriverDiagnostics().report(replace(snapshot(0.0), chain=status))
    assert levels(e)["chain compensation"] == OK
    entry = next(x for x in e if x.name.endswith("chain compensation"))
    assert "unknown" in entry.message and "dynamic section" in entry.message, entry.message
    assert values(e, "chain compensation")["mode"] == "none"
    assert DriverCore(None).chain_status() == {}  # raw only: no acceleration, nothing to state


def test_a_delay_shift_that_makes_tones_in_the_calibrated_band_worse_is_warned_about():
    """``delay`` (what ``auto`` picks with a ``dynamic`` section) moves the stamps back by the group delay at DC,
    ``tau + 1/(2 pi fc)``; a tone at f lags by less (its phase delay), so above some frequency the shift leaves a
    larger timing error than no shift at all, and a larger RMS error. With the TIA time constants twice paper Table 1
    (cut-offs 0.85 / 0.65 / 0.65 Hz, 20 ms channel delay: the simulator's ``tia_lowpass`` scale 2) and a calibration
    made over 0.5-20 Hz, the limit lies at 1.7-2.0 Hz, inside that band. Before, the ``chain compensation`` entry was
    OK ("delay: stamps moved back by 245.65 ms, bandwidth 0.65 Hz"), said nothing of it, and at 3 Hz (seed 7, 100 Hz,
    through ``DriverCore``) ``delay`` left an RMS error of 1.81 / 1.70 / 2.41 m/s^2 (x / y / z) against 1.51 / 1.50 /
    2.12 uncompensated (x lag 87 -> -159 ms; at 1 Hz it helps: 0.81 / 0.78 / 1.10 against 1.23 / 1.30 / 1.82).
    Now the entry states, per axis, the frequency below which the shift is a correction and WARNs when that lies
    inside the calibrated band; the limit is checked here against tones through the simulator and the driver, below
    it (better than none) and above it (worse)."""
    from test_driver_core import levels, snapshot, values

    from fbg_accel_calibration.dynamic.dynamic_check import tone_check
    from fbg_accel_calibration.dynamic.excitation_plan import ExcitationPlan
    from fbg_accel_driver.driver_diagnostics import WARN, DriverDiagnostics
    from fbg_accel_driver.driver_parameters import default_calibration_path
    from fbg_accel_sim.dynamic_run import simulate_dynamic_run
    from fbg_accel_sim.sim_config import SimConfig

    over = {"effects.tia_lowpass.scale": 2.0}
    sim_cfg = SimConfig.default().with_overrides(over)
    fc = tuple(float(v) / 2.0 for v in sim_cfg.get("electronics.tia_cutoff_hz"))  # Hz: time constants x 2
    tau = float(sim_cfg.get("effects.channel_delay.delay_s"))
    cal = ThermalCalibration.load(default_calibration_path())
    cal.dynamic = ChainDynamics(cutoff_hz=fc, delay_s=(tau, tau, tau),  # type: ignore[arg-type]
                                fit={"frequencies_hz": [0.5, 1.0, 2.0, 5.0, 10.0, 20.0]})
    status = DriverCore(cal, CoreConfig(chain_compensation="delay")).chain_status()
    e = DriverDiagnostics().report(replace(snapshot(0.0), chain=status))
    entry = next(x for x in e if x.name.endswith("chain compensation"))
    assert levels(e)["chain compensation"] == WARN, entry.message
    v = values(e, "chain compensation")
    limits = [float(v[f"delay_helps_below_hz_{ax}"]) for ax in "xyz"]
    assert all(0.5 < lim < 20.0 for lim in limits), limits
    assert f"{min(limits):g} Hz" in entry.message and "equalise" in entry.message, entry.message

    plan = ExcitationPlan.load(Path(__file__).resolve().parents[1] / "config" / "excitation_plan_stepped_sine.yaml")
    for f_hz, worse in ((0.6 * min(limits), False), (1.5 * max(limits), True)):
        tone = plan.with_tone(round(f_hz, 3), 4.0, 14.0)
        _, block, _ = simulate_dynamic_run(tone, rate_hz=100.0, seed=7, overrides=over)
        _, a, b = tone.steady_windows(tone.start_s)[0]
        check = tone_check(block.wire_bytes(), block.arrays["t_s"], block.arrays["slide_accel_mps2"],
                           np.array(tone.direction), tone.segments[0].freq_hz, (a, b), cal, modes=("none", "delay"))
        none, delay = check.rms_mps2["none"], check.rms_mps2["delay"]
        assert all((d > n) == worse for d, n in zip(delay, none, strict=True)), (f_hz, none, delay)


def test_a_delay_shift_right_over_the_calibrated_band_is_ok_and_states_its_limit():
    """The flight build (paper 3.5: TIA cut-offs about 50 Hz) calibrated over 0.5-20 Hz: the DC shift is a correction
    up to 117 Hz, beyond the band, so the entry stays OK and states that limit."""
    from scipy.optimize import brentq
    from test_driver_core import levels, snapshot

    from fbg_accel_driver.driver_diagnostics import OK, DriverDiagnostics

    dyn = ChainDynamics(cutoff_hz=(50.0,) * 4, fit={"frequencies_hz": [0.5, 20.0]})  # type: ignore[arg-type]
    status = DriverCore(make_cal(dynamic=dyn), CoreConfig(chain_compensation="delay")).chain_status()
    e = DriverDiagnostics().report(replace(snapshot(0.0), chain=status))
    entry = next(x for x in e if x.name.endswith("chain compensation"))
    assert levels(e)["chain compensation"] == OK, entry.message
    root = brentq(lambda x: x - 2.0 * math.atan(x), 1.0, 5.0)  # the limit of a first-order stage: x = 2 atan x
    assert f"below {round(root * 50.0, 3):g} Hz" in entry.message, entry.message


def test_a_section_fitted_per_output_axis_says_to_re_run_the_dynamic_calibration():
    """A format-1 section written by a dynamic calibration (one first-order stage fitted per output axis, wrong on an
    axis whose channels' cut-offs differ) is still used, and the ``chain compensation`` entry says what it is and
    what to do; a format-2 section (per channel) says nothing of it."""
    from test_driver_core import snapshot, values

    from fbg_accel_driver.driver_diagnostics import DriverDiagnostics

    def fail(msg: str) -> ValueError:
        return ValueError(msg)

    old = ChainDynamics.from_dict({**DYN.to_dict(), "format_version": 1, "fit": {"models": {}}}, fail)
    for dyn, per in ((old, "axis"), (DYN, "channel")):
        status = DriverCore(make_cal(dynamic=dyn), CoreConfig(chain_compensation="delay")).chain_status()
        e = DriverDiagnostics().report(replace(snapshot(0.0), chain=status))
        entry = next(x for x in e if x.name.endswith("chain compensation"))
        assert values(e, "chain compensation")["identified_per"] == per
        assert ("re-run fbg-accel-calib dynamic" in entry.message) == (per == "axis"), entry.message
