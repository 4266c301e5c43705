"""The chain's dynamics section and its live compensation (fbg_accel_driver.chain_compensation)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from fbg_accel_driver.chain_compensation import ChainDynamics, ChannelEqualiser

FS = 100.0
STATIC_BUILD = ChainDynamics(cutoff_hz=(1.0, 1.7, 1.3, 1.3), delay_s=(0.0, 0.0025, 0.005))


def _lowpass(u: np.ndarray, fc: float, fs: float) -> np.ndarray:
    """First-order low-pass, exact for a signal held between samples (the simulator's TIA model)."""
    a = 1.0 - math.exp(-2 * math.pi * fc / fs)
    y = np.empty_like(u)
    s = u[0]
    for i, v in enumerate(u):
        s += a * (v - s)
        y[i] = s
    return y


def _amp_phase(t: np.ndarray, y: np.ndarray, f: float) -> tuple[Any, Any]:
    """Amplitude and phase (rad) of the ``f`` Hz sine in ``y`` (N,) or in each column of ``y`` (N, k), with an offset."""
    X = np.column_stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t), np.ones_like(t)])
    s, c, _ = np.linalg.lstsq(X, y, rcond=None)[0]
    return np.hypot(s, c), np.arctan2(c, s)


@pytest.mark.parametrize("f_hz", [0.5, 2.0, 5.0])
def test_equaliser_restores_amplitude_and_phase_of_every_channel(f_hz):
    """Each channel through its own low-pass and pure delay (the model's): after the equaliser every axis channel
    lags by the largest pure delay and the new low-pass only, the reference by the new low-pass only."""
    eq = ChannelEqualiser(STATIC_BUILD, bandwidth_hz=20.0)
    t = np.arange(int(40 * FS)) / FS
    delays = (0.0, *STATIC_BUILD.delay_s)
    chans = [_lowpass(1000.0 + 200.0 * np.sin(2 * np.pi * f_hz * (t - d)), fc, FS)
             for fc, d in zip(STATIC_BUILD.cutoff_hz, delays, strict=True)]
    out = np.array([eq.step(1 / FS, tuple(float(c[i]) for c in chans)) for i in range(len(t))])
    keep = t > 10.0
    aligned = max(STATIC_BUILD.delay_s)
    for j in range(4):
        common = 2 * np.pi * f_hz * (aligned if j else 0.0)  # the phase of the delay every axis channel keeps
        _, ph_in = _amp_phase(t[keep], chans[j][keep], f_hz)
        amp, ph = _amp_phase(t[keep], out[keep, j], f_hz)
        lag_before = ph_in + 2 * np.pi * f_hz * delays[j]  # negative: the TIA lags
        lag = (aligned - delays[j]) * FS if j else 0.0  # the alignment in samples, by linear interpolation
        frac = lag - math.floor(lag)
        droop = abs(1.0 - frac + frac * np.exp(-2j * np.pi * f_hz / FS))
        assert abs(amp / 200.0 / droop - 1.0) < 0.03, (j, amp, droop)
        # what remains is the 20 Hz low-pass (plus the discretisation): far below the TIA's own lag
        assert abs(ph + common) < 0.15 * abs(lag_before) + 0.02, (j, ph, lag_before)
        r, w = math.exp(-2 * math.pi * 20.0 / FS), 2 * math.pi * f_hz / FS
        assert ph + common == pytest.approx(-math.atan2(r * math.sin(w), 1 - r * math.cos(w)), abs=2e-3)  # new low-pass


def test_equaliser_is_unity_at_dc_and_stable_for_any_step():
    eq = ChannelEqualiser(STATIC_BUILD, bandwidth_hz=10.0)
    for _ in range(50):
        out = eq.step(0.01, (870.0, 1100.0, 1600.0, 1100.0))
    assert np.allclose(out, (870.0, 1100.0, 1600.0, 1100.0))
    eq.reset()
    eq.step(0.01, (0.0, 0.0, 0.0, 0.0))
    ys = [eq.step(dt, (1.0, 1.0, 1.0, 1.0)) for dt in (0.01, 5.0, 1e-6, 0.3) * 20]
    assert all(math.isfinite(v) and abs(v) <= 1e3 for y in ys for v in y)
    assert np.allclose(ys[-1], 1.0, atol=1e-6)


def test_equaliser_bandwidth_must_exceed_every_cutoff():
    with pytest.raises(ValueError, match="above every channel"):
        ChannelEqualiser(STATIC_BUILD, bandwidth_hz=1.5)


def test_stamp_delay_is_the_group_delay_at_dc_of_the_axes():
    tau = [1 / (2 * math.pi * fc) + d for fc, d in zip(STATIC_BUILD.cutoff_hz[1:], STATIC_BUILD.delay_s, strict=True)]
    assert STATIC_BUILD.stamp_delay_s("delay", 0.0) == pytest.approx(np.mean(tau))
    # the axes' DC group delays are the diagonal of M diag(tau_channel) M^-1: their mean is the channels' mean
    m = np.array([[81.6, 2.89, 0.71], [1.59, 77.66, 3.75], [0.24, 1.23, 107.66]])
    assert np.trace(m @ np.diag(tau) @ np.linalg.inv(m)) / 3 == pytest.approx(np.mean(tau))
    # equalised: the channels' own low-passes and the largest pure delay (every axis channel is aligned to it),
    # minus the sampled low-pass the equaliser inverts, plus its own
    dt = 1 / FS
    r = [math.exp(-2 * math.pi * fc * dt) for fc in STATIC_BUILD.cutoff_hz[1:]]
    rp = math.exp(-2 * math.pi * 20.0 * dt)
    own = np.mean([1 / (2 * math.pi * fc) for fc in STATIC_BUILD.cutoff_hz[1:]]) + max(STATIC_BUILD.delay_s)
    expected = own - np.mean([x / (1 - x) for x in r]) * dt + rp / (1 - rp) * dt
    assert STATIC_BUILD.stamp_delay_s("equalise", 20.0, dt) == pytest.approx(expected)
    assert abs(expected - (max(STATIC_BUILD.delay_s) + 1 / (2 * math.pi * 20))) < dt  # about tau_p + delay
    assert STATIC_BUILD.stamp_delay_s("none", 20.0) == 0.0
    # at a frequency the first-order delay is smaller: tau / (1 + (f/fc)^2)
    assert STATIC_BUILD.group_delay_s(0, 1.7) == pytest.approx(0.5 / (2 * math.pi * 1.7) + 0.0)


def test_variance_factor_matches_monte_carlo_for_white_and_correlated_noise():
    eq = ChannelEqualiser(STATIC_BUILD, bandwidth_hz=10.0)
    rng = np.random.default_rng(3)
    n = 200_000
    for frac, tau in ((0.0, 0.0), (0.7, 0.12)):
        w = rng.normal(size=n)
        rho = math.exp(-1 / FS / tau) if tau else 0.0
        ar = np.empty(n)
        s = 0.0
        e = rng.normal(size=n) * math.sqrt(1 - rho * rho)
        for i in range(n):
            s = rho * s + e[i]
            ar[i] = s
        noise = math.sqrt(1 - frac) * w + math.sqrt(frac) * ar
        base = 1000.0 + noise
        chans = [base] * 4
        eq.reset()
        out = np.array([eq.step(1 / FS, tuple(float(c[i]) for c in chans)) for i in range(n)])
        for axis in range(3):
            empirical = float(np.var(out[1000:, axis + 1]) / np.var(noise))
            assert eq.variance_factor(axis, 1 / FS, frac, tau) == pytest.approx(empirical, rel=0.05)
            # the mean of 10 consecutive equalised samples (decimation): its variance from the filtered noise
            means = out[1000:, axis + 1].reshape(-1, 10).mean(axis=1)
            empirical10 = float(np.var(means) / np.var(noise))
            assert eq.variance_factor(axis, 1 / FS, frac, tau, n=10) == pytest.approx(empirical10, rel=0.08)
    assert eq.variance_factor(0, 1 / FS, 0.0, 0.0) > 3.0  # the lead amplifies: the price is stated, not hidden


def test_dynamic_section_round_trips_and_refuses_what_it_does_not_know():
    def fail(msg: str) -> ValueError:
        return ValueError(msg)

    d = STATIC_BUILD.to_dict()
    assert ChainDynamics.from_dict(d, fail) == STATIC_BUILD
    # the reference channel's cut-off may be absent (a slide run with a constant source cannot see it)
    no_ref = ChainDynamics.from_dict({**d, "cutoff_hz": {**d["cutoff_hz"], "reference": None}}, fail)
    assert math.isnan(no_ref.cutoff_hz[0]) and no_ref.to_dict()["cutoff_hz"]["reference"] is None
    assert no_ref.stamp_delay_s("delay") == STATIC_BUILD.stamp_delay_s("delay")
    with pytest.raises(ValueError, match="needs the reference channel's cut-off"):
        ChannelEqualiser(no_ref, 20.0)
    for bad, message in [
        ({**d, "format_version": 3}, "format_version 3 is not supported"),
        ({**d, "cutof_hz": {}}, "unknown key 'dynamic.cutof_hz'"),
        ({**d, "cutoff_hz": {"reference": 1.0, "x": 1.7, "y": 1.3}}, "missing key 'dynamic.cutoff_hz.z'"),
        ({**d, "cutoff_hz": {**d["cutoff_hz"], "w": 1.0}}, "unknown key 'dynamic.cutoff_hz.w'"),
        ({**d, "cutoff_hz": {**d["cutoff_hz"], "x": -1.0}}, "cutoff_hz of x must be in"),
        ({**d, "cutoff_hz": {**d["cutoff_hz"], "x": "fast"}}, "must be a number"),
        ({**d, "delay_s": {"x": 5.0}}, "delay_s of x must be within"),
        ("none", "'dynamic' must be a mapping"),
    ]:
        with pytest.raises(ValueError, match=message):
            ChainDynamics.from_dict(bad, fail)


def test_the_delay_shift_limit_is_where_the_dc_shift_starts_to_over_correct():
    """Equal axes without a pure delay: the shift is ``1/(2 pi fc)``, the residual phase ``x - atan x`` against
    ``atan x`` (x = f/fc), so the limit is the root of ``x = 2 atan x``; a pure delay on one axis moves the common shift
    past twice another axis's own DC group delay, and the shift never helps that axis (0)."""
    from scipy.optimize import brentq

    root = brentq(lambda x: x - 2.0 * math.atan(x), 1.0, 5.0)  # 2.3311
    for fc in (1.3, 50.0):
        lim = ChainDynamics(cutoff_hz=(fc, fc, fc, fc)).delay_helps_below_hz()
        assert lim == pytest.approx((root * fc,) * 3, rel=1e-6)
    lim = ChainDynamics(cutoff_hz=(1.0, 1.7, 1.3, 1.3), delay_s=(0.9, 0.0, 0.0)).delay_helps_below_hz()
    assert lim[1] == lim[2] == 0.0 and 0.0 < lim[0] < math.inf
    assert ChainDynamics(cutoff_hz=(50.0,) * 4).delay_helps_below_hz(f_max_hz=20.0) == (math.inf,) * 3


def test_a_format_1_section_fitted_per_axis_still_loads_and_says_so():
    """Format 1 (one first-order stage fitted per output axis, written as the channels' values) loads as before and
    writes back as format 1; :attr:`identified_per_axis` tells it from a hand-written format-1 section."""
    def fail(msg: str) -> ValueError:
        return ValueError(msg)

    d = {**STATIC_BUILD.to_dict(), "format_version": 1}
    hand = ChainDynamics.from_dict(d, fail)
    assert hand.cutoff_hz == STATIC_BUILD.cutoff_hz and hand.format_version == 1 and not hand.identified_per_axis
    fitted = ChainDynamics.from_dict({**d, "fit": {"models": {"x": {"cutoff_hz": 1.7}}}}, fail)
    assert fitted.identified_per_axis and fitted.to_dict()["format_version"] == 1
    assert not STATIC_BUILD.identified_per_axis and STATIC_BUILD.to_dict()["format_version"] == 2
