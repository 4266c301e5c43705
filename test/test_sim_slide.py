"""Dynamic excitation of the board simulator: linear slide, reference transducer (aux, protocol v2),
ADC channel skew, mechanical resonance (docs/simulator.md "Dynamic calibration").

Each test fits A + B sin(w tau) + C cos(w tau) to the steady part of one slide segment (noise and
quantisation off, so the fit is exact up to the discretisation) and compares amplitude and phase with
the analogue stage's closed form: first-order low-pass 1/(1 + j f/fc) (TIA, paper Table 1), first-order
high-pass (LDV AC coupling, seed 2 Fig. 5), a pure delay 2 pi f dt (skew). Deterministic, no sleeps.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from fbg_accel_driver.stream_decoder import StreamDecoder
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig
from fbg_accel_sim.scenario import SlidePlan, SlideSegment, second_order_response

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

DIRECTION = np.array([0.5, -0.5, math.sqrt(0.5)])  # seed 2 eqs. 1-3
QUIET = {  # everything that is not the dynamic chain off: noise, quantisation, slow drifts, delay, curvature
    "effects.white_noise.scale": 0.0, "effects.bias_instability.scale": 0.0, "effects.adc_quantisation.scale": 0.0,
    "effects.source_power_wander.scale": 0.0, "effects.time_drift.scale": 0.0, "effects.channel_delay.scale": 0.0,
    "effects.spectral_nonlinearity.scale": 0.0, "effects.thermal_hysteresis.scale": 0.0,
}


def slide_config(freq_hz: float, amp: float = 2.0, rate_hz: float = 200.0, duration_s: float = 12.0, **over) -> SimConfig:
    o = {**QUIET, "scenario.rate_hz": rate_hz, "scenario.slide.enabled": True, "scenario.slide.start_s": 1.0,
         "scenario.slide.segments": [{"freq_hz": freq_hz, "amplitude_mps2": amp, "duration_s": duration_s}],
         "board.protocol_version": 2, **over}
    return SimConfig.default().with_overrides(o)


def run(cfg: SimConfig, seed: int = 0):
    sim = BoardSimulator(cfg, seed=seed)
    return sim, sim.run(sim.duration_s)


def fit_sine(t: np.ndarray, y: np.ndarray, freq_hz: float) -> tuple[float, float]:
    """Amplitude and phase (rad) of y ~ c + amp sin(w t + phase)."""
    w = 2 * math.pi * freq_hz
    X = np.column_stack([np.ones_like(t), np.sin(w * t), np.cos(w * t)])
    _c, b, a = np.linalg.lstsq(X, y, rcond=None)[0]
    return math.hypot(b, a), math.atan2(a, b)


def steady(blk, sim: BoardSimulator, freq_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Mask of the steady part of segment 0 (after the ramp and 5 TIA time constants, before the fade-out)
    and tau = time since the segment start (s)."""
    t0 = float(sim.slide.starts[0])
    dur = sim.slide.segments[0].duration_s
    ramp = sim.slide.ramp_cycles / freq_hz
    tau = blk.t_s - t0
    m = (tau > ramp + 5 * max(sim.tia_tau)) & (tau < dur - ramp)
    return m, tau


@pytest.mark.parametrize("freq_hz", [0.5, 2.0, 5.0])
def test_axis_output_has_the_tia_first_order_gain_and_phase(freq_hz: float) -> None:
    sim, blk = run(slide_config(freq_hz, rate_hz=500.0 if freq_hz > 2 else 200.0, duration_s=16.0))
    m, tau = steady(blk, sim, freq_hz)
    amp_in = 2.0 * (sim.A @ DIRECTION)  # axis input amplitude (m/s^2): cross-axis coupling x direction x A
    fc = np.asarray(sim.cfg.get("electronics.tia_cutoff_hz"))[1:]
    h_res = second_order_response(freq_hz, 1330.0, 0.03)
    for j in range(3):
        amp, ph = fit_sine(tau[m], blk.counts_float[m, j + 1], freq_hz)
        h = 1.0 / complex(1.0, freq_hz / fc[j]) * h_res
        expected = abs(amp_in[j]) * sim.counts_per_mps2[j] * abs(h)
        assert amp == pytest.approx(expected, rel=0.02), (j, amp, expected)
        ph_expected = math.atan2(h.imag, h.real) + (0.0 if amp_in[j] > 0 else math.pi)
        d = (ph - ph_expected + math.pi) % (2 * math.pi) - math.pi
        assert abs(d) < math.radians(1.0), (j, math.degrees(ph), math.degrees(ph_expected))


def test_truth_has_slide_motion_and_accel_true_includes_it() -> None:
    sim, blk = run(slide_config(1.0))
    m, tau = steady(blk, sim, 1.0)
    amp, ph = fit_sine(tau[m], blk.slide_accel_mps2[m], 1.0)
    assert amp == pytest.approx(2.0, rel=1e-6) and abs(ph) < 1e-6
    g = blk.gref_mps2 @ sim.R_mount.T
    np.testing.assert_allclose(blk.accel_true_mps2 - g, blk.slide_accel_mps2[:, None] * DIRECTION[None, :], atol=1e-9)
    # derivatives are consistent (envelope included): v = dx/dt, a = dv/dt (trapezoid rule, O((w dt)^2) error)
    dt = np.diff(blk.t_s)
    x, v, a = blk.slide_displacement_m, blk.slide_velocity_mps, blk.slide_accel_mps2
    np.testing.assert_allclose(np.diff(x) / dt, 0.5 * (v[1:] + v[:-1]), atol=1e-4)
    np.testing.assert_allclose(np.diff(v) / dt, 0.5 * (a[1:] + a[:-1]), atol=2e-3)
    assert abs(x[0]) + abs(v[0]) + abs(x[-1]) + abs(v[-1]) < 1e-12  # at rest before and after


def test_ldv_aux_dc_coupled_is_the_scaled_velocity() -> None:
    _sim, blk = run(slide_config(1.0, **{"reference_transducer.ldv.ac_coupling_hz": 0.0}))
    np.testing.assert_allclose(blk.aux_float, 2048.0 + 2500.0 * blk.slide_velocity_mps, atol=1e-9)


@pytest.mark.parametrize("freq_hz", [0.5, 1.0, 5.0])
def test_ldv_aux_shows_the_ac_coupling_high_pass(freq_hz: float) -> None:
    sim, blk = run(slide_config(freq_hz, rate_hz=200.0, duration_s=20.0))
    m, tau = steady(blk, sim, freq_hz)
    m &= tau > sim.slide.ramp_cycles / freq_hz + 5 * sim.ldv_hp_tau
    amp_v, ph_v = fit_sine(tau[m], blk.slide_velocity_mps[m], freq_hz)
    amp, ph = fit_sine(tau[m], blk.aux_float[m], freq_hz)
    r = freq_hz / 0.5
    h = complex(0.0, r) / complex(1.0, r)  # first-order high-pass at 0.5 Hz (seed 2, Fig. 5)
    assert amp / (2500.0 * amp_v) == pytest.approx(abs(h), rel=0.01)
    d = (ph - ph_v - math.atan2(h.imag, h.real) + math.pi) % (2 * math.pi) - math.pi
    assert abs(d) < math.radians(0.5)


def test_reference_accelerometer_aux() -> None:
    _sim, blk = run(slide_config(2.0, **{"reference_transducer.type": "accelerometer"}))
    np.testing.assert_allclose(blk.aux_float, 2048.0 + 200.0 * blk.slide_accel_mps2, atol=1e-9)


def test_adc_channel_skew_is_a_delay_per_channel() -> None:
    f, skew_us = 5.0, 200.0
    sim0, b0 = run(slide_config(f, rate_hz=200.0, **{"reference_transducer.type": "accelerometer"}))
    _sim1, b1 = run(slide_config(f, rate_hz=200.0, **{"reference_transducer.type": "accelerometer",
                                                    "board.adc_channel_skew_us": skew_us}))
    m, tau = steady(b0, sim0, f)
    for j, col in [(1, 1), (2, 2), (3, 3)]:
        _, p0 = fit_sine(tau[m], b0.counts_float[m, col], f)
        _, p1 = fit_sine(tau[m], b1.counts_float[m, col], f)
        lead = (p1 - p0 + math.pi) % (2 * math.pi) - math.pi  # sampled later = phase advanced
        assert lead == pytest.approx(2 * math.pi * f * j * skew_us * 1e-6, rel=0.03), j
    _, p0 = fit_sine(tau[m], b0.aux_float[m], f)
    _, p1 = fit_sine(tau[m], b1.aux_float[m], f)
    assert p1 - p0 == pytest.approx(2 * math.pi * f * 4 * skew_us * 1e-6, rel=0.01)
    np.testing.assert_array_equal(b0.t_us, b1.t_us)  # t_us stays the trigger time


def test_mechanical_resonance_response() -> None:
    h = second_order_response(1330.0, 1330.0, 0.03)
    assert abs(h) == pytest.approx(1 / 0.06) and math.atan2(h.imag, h.real) == pytest.approx(-math.pi / 2)
    assert abs(second_order_response(20.0, 1330.0, 0.03)) == pytest.approx(1.0, abs=3e-4)  # negligible in seed 2's band
    assert abs(second_order_response(440.0, 1330.0, 0.03)) == pytest.approx(1.122, abs=0.002)  # top of the usable band


def test_v2_wire_decodes_with_aux_and_exact_fault_counts() -> None:
    cfg = slide_config(2.0, duration_s=6.0, **{"faults.bit_flips.count": 3, "faults.truncated.count": 2,
                                               "faults.dropped.count": 2, "faults.duplicated.count": 2,
                                               "faults.garbage.count": 3})
    sim, blk = run(cfg, seed=4)
    dec = StreamDecoder()
    out = dec.feed(blk.wire_bytes())
    frames = blk.frames()
    dedup = [f for i, f in enumerate(frames) if i == 0 or f != frames[i - 1]]  # the decoder drops duplicates
    assert out == dedup
    assert all(f.version == 2 for f in out) and len({f.aux for f in out}) > 100
    s = dec.stats.as_dict()
    exp = sim.expected_decoder_stats()
    assert {k: s[k] for k in exp} == exp


def test_slide_plan_validation() -> None:
    with pytest.raises(ValueError, match="non-zero"):
        SlidePlan([SlideSegment(1.0, 1.0, 5.0)], np.zeros(3))
    with pytest.raises(ValueError, match="must be > 0"):
        SlidePlan([SlideSegment(0.0, 1.0, 5.0)], DIRECTION)
    with pytest.raises(ValueError, match="segments is empty"):
        BoardSimulator(SimConfig.default().with_overrides({"scenario.slide.enabled": True, "scenario.slide.segments": []}))
    with pytest.raises(ValueError, match="protocol_version"):
        BoardSimulator(SimConfig.default().with_overrides({"board.protocol_version": 3}))


def test_default_slide_plan_runs_and_stays_in_range() -> None:
    cfg = SimConfig.default().with_overrides({"scenario.slide.enabled": True, "board.protocol_version": 2})
    sim = BoardSimulator(cfg, seed=1, wire=False)
    assert sim.duration_s == pytest.approx(sim.slide.end_s + 5.0)
    blk = sim.run(sim.duration_s)
    assert sorted({int(s) for s in blk.slide_segment}) == [-1, 0, 1, 2, 3, 4, 5]
    assert not blk.saturated.any() and 0 < blk.aux.min() and blk.aux.max() < 4095
    assert np.abs(blk.slide_displacement_m).max() < 0.075  # a long-stroke shaker's travel


# Static scenarios are unchanged by the dynamic additions: wire bytes of fixed seeds, recorded before they existed.
STATIC_GOLDEN = {
    "default": "2c886c09b0520010",
    "six_position_faults": "8e14588ff808386d",
}


@pytest.mark.parametrize("name", sorted(STATIC_GOLDEN))
def test_static_scenarios_bytes_unchanged(name: str) -> None:
    cfg = SimConfig.default()
    if name == "six_position_faults":
        cfg = cfg.with_overrides({"scenario.poses.mode": "six_position", "scenario.poses.dwell_s": 5.0,
                                  "faults.bit_flips.count": 3, "faults.truncated.count": 2, "faults.garbage.count": 3,
                                  "scenario.duration_s": 60.0})
    blk = BoardSimulator(cfg, seed=3).run(45.0)
    assert hashlib.sha256(blk.wire_bytes()).hexdigest()[:16] == STATIC_GOLDEN[name]


def test_board_sim_on_a_pty_keeps_streaming_after_the_dynamic_plan(tmp_path) -> None:
    """README's dynamic workflow starts ``board_sim --dynamic-plan PLAN --link L`` (no ``--duration``), then the driver,
    then the calibration node, which records ``start_s + duration + 2 s`` from *its* first sample. Before: the board
    stopped at ``start_s + duration + 2 s`` of its own time, i.e. before the node, started later, was done; the node
    then waited for the stream forever (stepped-sine plan: board ended at 108 s, the node had 105.4 of its 108 s, exit 3
    only on Ctrl-C). A real board does not stop when the slide does: on a pty the simulated board now streams on at
    rest until killed; a file (``--output``) still ends 2 s after the plan."""
    from pathlib import Path

    from fbg_accel_calibration.dynamic.excitation_plan import ExcitationPlan
    from fbg_accel_sim.board_sim import build_parser, load_config

    plan_file = str(Path(__file__).resolve().parents[1] / "config" / "excitation_plan_stepped_sine.yaml")
    plan = ExcitationPlan.load(plan_file)
    end_s = plan.start_s + plan.duration_s
    pty = BoardSimulator(load_config(build_parser().parse_args(["--dynamic-plan", plan_file, "--link", str(tmp_path / "L")])),
                         seed=0)
    assert math.isinf(pty.duration_s)
    to_file = BoardSimulator(load_config(build_parser().parse_args(["--dynamic-plan", plan_file, "--output",
                                                                    str(tmp_path / "run.bin")])), seed=0)
    assert to_file.duration_s == pytest.approx(end_s + 2.0)
    given = BoardSimulator(load_config(build_parser().parse_args(["--dynamic-plan", plan_file, "--duration", "30"])),
                           seed=0)
    assert given.duration_s == 30.0
    # past the plan the slide is at rest and the board goes on sampling
    pty.step(pty.samples_for(end_s + 1.0))
    after = pty.step(pty.samples_for(5.0))
    assert len(after.t_s) == pty.samples_for(5.0) and after.t_s[0] > end_s
    assert np.all(after.slide_accel_mps2 == 0.0) and np.all(after.slide_velocity_mps == 0.0)
