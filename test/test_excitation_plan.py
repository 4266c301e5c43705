"""Excitation plan of a dynamic calibration: file contract, timing, reference conversion, slide start."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from fbg_accel_calibration.dynamic.excitation_plan import (
    ExcitationPlan,
    ExcitationPlanError,
    find_slide_start,
    reference_acceleration,
)

PLAN_FILE = Path(__file__).resolve().parents[1] / "config" / "excitation_plan_stepped_sine.yaml"


def _plan_dict() -> dict:
    return yaml.safe_load(PLAN_FILE.read_text())


def test_shipped_plan_loads_and_round_trips():
    plan = ExcitationPlan.load(PLAN_FILE)
    assert [s.freq_hz for s in plan.segments] == [0.5, 1.0, 2.0, 5.0, 10.0, 20.0]
    assert np.linalg.norm(plan.direction) == pytest.approx(1.0)
    assert ExcitationPlan.from_dict(plan.to_dict()) == plan


@pytest.mark.parametrize(("change", "message"), [
    ({"format": "other"}, "expected 'fbg_accel_excitation_plan'"),
    ({"format_version": 9}, "format_version 9 is not supported"),
    ({"directon": [1, 0, 0]}, "did you mean 'direction'"),
    ({"direction": [0, 0, 0]}, "direction must not be zero"),
    ({"direction": [1, 0]}, "list of 3 numbers"),
    ({"reference": {"type": "ldv", "offset_counts": 2048}}, "sensitivity_counts_per_mps is required"),
    ({"reference": {"type": "laser", "sensitivity_counts_per_mps": 1}}, "reference.type must be one of"),
    ({"segments": []}, "non-empty list"),
    ({"segments": [{"freq_hz": 5.0, "amplitude_mps2": 1.0}]}, "duration_s is required"),
    ({"segments": [{"freq_hz": 0.5, "amplitude_mps2": 1.0, "duration_s": 4.0}]}, "under 3 periods"),
    ({"segments": [{"freq_hz": -1, "amplitude_mps2": 1.0, "duration_s": 4.0}]}, "freq_hz must be >="),
    ({"gap_s": float("nan")}, "gap_s must be a finite number"),
])
def test_bad_plans_are_refused_with_a_clear_message(change, message):
    with pytest.raises(ExcitationPlanError, match=message):
        ExcitationPlan.from_dict({**_plan_dict(), **change})


def test_steady_windows_leave_out_the_ramps_and_the_settling():
    plan = ExcitationPlan.load(PLAN_FILE)
    windows = plan.steady_windows(100.0)
    starts = plan.segment_starts_s()
    for (f, a, b), seg, t0 in zip(windows, plan.segments, starts, strict=True):
        ramp = min(plan.ramp_cycles / seg.freq_hz, 0.5 * seg.duration_s)
        assert f == seg.freq_hz
        assert a == pytest.approx(100.0 + t0 + ramp + plan.settle_s)
        assert b == pytest.approx(100.0 + t0 + seg.duration_s - ramp)


@pytest.mark.parametrize("fs", [100.0, 500.0])
@pytest.mark.parametrize("ac_coupled", [False, True])
def test_ldv_velocity_becomes_the_exact_acceleration_of_each_tone(fs, ac_coupled):
    """The tone-corrected central difference is exact in amplitude and phase; an AC-coupled LDV's declared
    first-order high-pass (steady state of each tone: v_m = jw / (jw + w_h) v) is undone exactly."""
    plan = ExcitationPlan.load(PLAN_FILE)
    t = np.arange(0.0, 120.0, 1.0 / fs)
    windows = plan.steady_windows(0.0)
    v = np.zeros_like(t)
    a_true = np.full_like(t, np.nan)
    wh = 2 * math.pi * plan.reference.ac_coupling_hz
    for f, a, b in windows:
        w = 2 * math.pi * f
        m = (t >= a - 0.5) & (t < b + 0.5)
        hp = 1j * w / (1j * w + wh) if ac_coupled else 1.0
        v[m] = np.abs(hp) * 0.1 / w * np.sin(w * t[m] + 0.3 + np.angle(hp))
        a_true[m] = 0.1 * np.cos(w * t[m] + 0.3)
    counts = plan.reference.offset_counts + plan.reference.sensitivity * v
    a = reference_acceleration(t, counts, plan, windows, undo_ac_coupling=ac_coupled)
    inside = np.zeros_like(t, bool)
    for _, lo, hi in windows:
        inside |= (t >= lo + 0.02) & (t < hi - 0.02)
    # a plain central difference is 24 % low at 20 Hz and 100 Hz sampling
    np.testing.assert_allclose(a[inside], a_true[inside], atol=1e-3 if ac_coupled else 2e-9)
    assert np.all(np.isnan(a[t < windows[0][1]]))


@pytest.mark.parametrize("lead_s", [7.3, -1.0, -15.0])
def test_slide_start_is_found_from_the_aux_envelope(lead_s: float):
    """``lead_s``: the slide starts this long after the recording (negative: the recording started late, inside
    the first segment, whose start then lies before the recording's; before, the search only looked forward and
    put the start 24 s late)."""
    plan = ExcitationPlan.load(PLAN_FILE)
    fs = 200.0
    t = np.arange(0.0, 130.0, 1.0 / fs) + 12.345  # the recording's clock starts anywhere
    true_start = 12.345 + lead_s
    rel = t - true_start
    env = plan.envelope(rel)
    rng = np.random.default_rng(1)
    seg_f = np.zeros_like(t)
    for seg, t0 in zip(plan.segments, plan.segment_starts_s(), strict=True):
        seg_f[(rel >= t0) & (rel < t0 + seg.duration_s)] = seg.freq_hz
    v = env / np.maximum(2 * np.pi * seg_f, 1e-9) * np.sin(2 * np.pi * seg_f * rel)
    counts = 2048 + 2500 * v + rng.normal(0, 0.5, t.size)
    assert find_slide_start(t, counts, plan) == pytest.approx(true_start, abs=0.1)


def test_simulator_overrides_name_existing_keys():
    from fbg_accel_sim.sim_config import SimConfig

    plan = ExcitationPlan.load(PLAN_FILE)
    cfg = SimConfig.default().with_overrides(plan.sim_overrides())
    assert cfg.get("board.protocol_version") == 2 and cfg.get("scenario.slide.enabled") is True
    assert cfg.get("reference_transducer.ldv.ac_coupling_hz") == plan.reference.ac_coupling_hz
