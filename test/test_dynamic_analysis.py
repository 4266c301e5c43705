"""Dynamic calibration core: seed validation actions (JSSS 8, 223, 2019, section 2.3), sine approximation,
a synthetic TIA chain recovered by the chain-model fit, sign conventions and the uncertainty budget."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from fbg_accel_calibration.dynamic.bode_plot import plot_bode
from fbg_accel_calibration.dynamic.chain_model import (
    ChainModel,
    fit_chain_model,
    fit_chain_models,
    group_delay_s,
    phase_delay_s,
    response,
)
from fbg_accel_calibration.dynamic.tone_analysis import (
    DynamicPoint,
    ReferenceUncertainty,
    analyse_run,
    budget_table_markdown,
    fft_amplitude_phase,
    points_table_markdown,
    resolution_components,
    sine_approximation,
)
from fbg_accel_calibration.dynamic.tone_delay import delay_by_cross_correlation, delay_by_cross_spectrum, whole_period_length

FS = 1000.0
FREQS = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0)
FC = (1.7, 1.3, 1.3)  # TIA cut-offs x, y, z of the static-test build (sensor_facts.md)
TAU = 2.5e-3  # pure delay, s
SEED_DIRECTION = (0.5, -0.5, math.sqrt(0.5))  # seed eq. 1-3: 45 deg plate, 45 deg rotation


# --- seed 2.3 validation actions -----------------------------------------------------------------------

def test_same_signal_on_two_channels_gives_zero_delay() -> None:
    rng = np.random.default_rng(1)
    t = np.arange(0, 4.0, 1 / FS)
    x = np.sin(2 * np.pi * 5 * t) + 0.01 * rng.standard_normal(t.size)
    assert abs(delay_by_cross_correlation(x, x, FS)) < 1e-6
    assert abs(delay_by_cross_correlation(x, x, FS, circular=True)) < 1e-6
    assert abs(delay_by_cross_spectrum(x, x, FS, 5.0)) < 1e-6


@pytest.mark.parametrize("delay_s", [3.37e-3, -3.37e-3, 0.42e-3, 12.71e-3])
def test_digitally_delayed_tone_is_recovered_by_both_methods(delay_s: float) -> None:
    t = np.arange(0, 4.0, 1 / FS)  # 20 whole periods of 5 Hz
    rng = np.random.default_rng(2)
    ref = np.sin(2 * np.pi * 5 * t) + 0.002 * rng.standard_normal(t.size)
    sig = np.sin(2 * np.pi * 5 * (t - delay_s)) + 0.002 * rng.standard_normal(t.size)  # exact fractional delay
    d_xc = delay_by_cross_correlation(ref, sig, FS, circular=True)
    d_cs = delay_by_cross_spectrum(ref, sig, FS, 5.0)
    assert abs(d_xc - delay_s) < 1e-4
    assert abs(d_cs - delay_s) < 1e-4
    # integer-sample xcorr is only good to the resolution 1/fs (seed Table 3)
    assert abs(delay_by_cross_correlation(ref, sig, FS, circular=True, refine="none") - delay_s) <= 0.5 / FS + 1e-4


def test_digitally_delayed_broadband_signal_is_recovered() -> None:
    n = 8192
    rng = np.random.default_rng(3)
    X = np.fft.rfft(rng.standard_normal(n))
    fr = np.fft.rfftfreq(n, 1 / FS)
    X[fr > 100] = 0
    delay = 3.37e-3
    ref = np.fft.irfft(X, n)
    sig = np.fft.irfft(X * np.exp(-2j * np.pi * fr * delay), n)  # band-limited fractional delay
    for refine in ("cosine", "parabolic"):
        assert abs(delay_by_cross_correlation(ref, sig, FS, refine=refine) - delay) < 1e-4
    f_bin = fr[np.argmax(np.abs(X[(fr > 15) & (fr < 25)])) + np.flatnonzero(fr > 15)[0]]
    assert abs(delay_by_cross_spectrum(ref, sig, FS, float(f_bin)) - delay) < 1e-4


def test_swapped_reference_and_sensor_give_negative_delay() -> None:
    t = np.arange(0, 4.0, 1 / FS)
    ref = np.sin(2 * np.pi * 2 * t)
    sig = np.sin(2 * np.pi * 2 * (t - 0.02))
    assert delay_by_cross_correlation(ref, sig, FS, circular=True) == pytest.approx(0.02, abs=1e-5)
    assert delay_by_cross_correlation(sig, ref, FS, circular=True) == pytest.approx(-0.02, abs=1e-5)
    assert delay_by_cross_spectrum(sig, ref, FS, 2.0) == pytest.approx(-0.02, abs=1e-5)


# --- sine approximation ---------------------------------------------------------------------------------

def test_sine_approximation_recovers_amplitude_and_phase_within_its_uncertainty() -> None:
    rng = np.random.default_rng(4)
    t = np.arange(0, 2.0, 1 / FS)
    amp, phase, f = 1.3, 0.7, 3.0
    z_amp, z_ph = [], []
    for _ in range(300):
        y = amp * np.cos(2 * np.pi * f * t + phase) + 0.2 + 0.05 * rng.standard_normal(t.size)
        fit = sine_approximation(t, y, f)
        z_amp.append((fit.amplitude - amp) / fit.u_amplitude)
        z_ph.append((fit.phase_rad - phase) / fit.u_phase_rad)
    # stated standard uncertainty is right: normalised errors have unit spread, ~68 % within 1 u
    for z in (np.array(z_amp), np.array(z_ph)):
        assert 0.85 < np.std(z) < 1.15
        assert 0.6 < np.mean(np.abs(z) < 1) < 0.76
        assert np.max(np.abs(z)) < 4.5
    # expected white-noise value: u(A) = sigma sqrt(2/N)
    assert fit.u_amplitude == pytest.approx(0.05 * math.sqrt(2 / t.size), rel=0.1)


def test_four_parameter_fit_refines_the_frequency() -> None:
    rng = np.random.default_rng(5)
    t = np.arange(0, 5.0, 1 / FS) + 100.0  # far from t = 0
    y = 2.0 * np.cos(2 * np.pi * 5.003 * t - 1.0) + 0.01 * rng.standard_normal(t.size)
    fit = sine_approximation(t, y, 5.0, fit_frequency=True)
    assert fit.f_hz == pytest.approx(5.003, abs=3 * fit.u_f_hz + 1e-6)
    assert fit.amplitude == pytest.approx(2.0, abs=1e-3)
    assert abs(math.remainder(fit.phase_rad + 1.0, 2 * math.pi)) < 4 * fit.u_phase_rad  # phase at t = 0, 100 s away
    assert sine_approximation(t, y, 5.0).residual_rms > 3 * fit.residual_rms  # 3-parameter fit at 5 Hz is off


def test_fft_over_whole_periods_matches_the_sine_fit() -> None:
    fs = 100.0
    t = np.arange(0, 7.3, 1 / fs)
    y = 0.8 * np.cos(2 * np.pi * 1.5 * t + 2.0) + 5.0
    tone = fft_amplitude_phase(y, fs, 1.5)
    assert tone.n_periods == 9 and tone.n_samples == 600  # 9 periods are exactly 600 samples
    assert tone.amplitude == pytest.approx(0.8, rel=1e-9)
    assert tone.phase_rad == pytest.approx(2.0, abs=1e-9)


# --- synthetic measuring chain --------------------------------------------------------------------------

def _piecewise_tones(freqs: tuple[float, ...], settle_s: float, periods: int, min_s: float, amp: float
                     ) -> tuple[Callable[[np.ndarray], np.ndarray], list[tuple[float, float, float]], float]:
    """Slide acceleration a(t) (m/s^2): one tone per block, settling then whole measured periods."""
    starts, segs = [], []
    t0 = 0.0
    for f in freqs:
        n_per = max(periods, math.ceil(min_s * f))
        meas = n_per / f
        starts.append((t0, f))
        segs.append((f, t0 + settle_s, t0 + settle_s + meas))
        t0 += settle_s + meas + 0.05

    def a(t: np.ndarray) -> np.ndarray:
        out = np.zeros_like(t)
        for (ts, f), (_, _, te) in zip(starts, segs, strict=True):
            m = (t >= ts) & (t < te + 0.05)
            out[m] = amp * np.sin(2 * np.pi * f * (t[m] - ts))
        return out

    return a, segs, t0


def _synthetic_run(seed: int, ref_highpass_hz: float | None = None, direction: tuple[float, ...] = SEED_DIRECTION,
                   noise: float = 0.005, fs: float = FS):
    """Reference = slide acceleration (optionally AC-coupled: first-order high-pass); each axis = projection
    through its first-order TIA low-pass (bilinear, pre-warped: exact -3 dB at fc) after a pure delay TAU."""
    rng = np.random.default_rng(seed)
    a, segs, t_end = _piecewise_tones(FREQS, settle_s=4.0, periods=10, min_s=2.0, amp=1.0)
    t = np.arange(0, t_end, 1 / fs)
    ref = a(t)
    if ref_highpass_hz is not None:
        b, aa = signal.butter(1, ref_highpass_hz, btype="high", fs=fs)
        ref = signal.lfilter(b, aa, ref)
    delayed = a(t - TAU)  # exact fractional delay of the analytic input
    sens = np.empty((t.size, 3))
    for i, fc in enumerate(FC):
        b, aa = signal.butter(1, fc, btype="low", fs=fs)
        sens[:, i] = signal.lfilter(b, aa, delayed * direction[i] / np.linalg.norm(direction))
    sens += noise * rng.standard_normal(sens.shape)
    ref = ref + 0.5 * noise * rng.standard_normal(t.size)
    return t, ref, sens, segs


@pytest.fixture(scope="module")
def chain_run():
    t, ref, sens, segs = _synthetic_run(6)
    pts = analyse_run(t, ref, sens, SEED_DIRECTION, segs, ReferenceUncertainty(sensitivity_rel=0.005, phase_deg=0.2))
    return pts, fit_chain_models(pts)


def test_points_follow_the_first_order_lowpass_and_delay(chain_run) -> None:
    pts, _ = chain_run
    assert len(pts) == len(FREQS) * 3 and all(p.measurable for p in pts)
    for p in pts:
        truth = ChainModel(cutoff_hz=FC[p.axis_index], delay_s=TAU)
        h = complex(response(truth, p.f_hz))
        assert p.sensitivity == pytest.approx(abs(h), rel=0.01, abs=0.002)
        assert p.phase_deg == pytest.approx(math.degrees(np.angle(h)), abs=0.5)
        # both delay methods agree with the model's phase delay (seed 3.3: < 1 deg between methods)
        assert p.delay_xcorr_s == pytest.approx(phase_delay_s(truth, p.f_hz), abs=1e-3)
        assert p.delay_cross_spectrum_s == pytest.approx(phase_delay_s(truth, p.f_hz), abs=1e-3)
        assert abs(p.delay_xcorr_s - p.delay_cross_spectrum_s) * 360 * p.f_hz < 1.0
    # seed eq. 5: differences from the 2 Hz value; y's sign flip (direction -0.5) is absorbed, not a 180 deg phase
    y2 = next(p for p in pts if p.axis == "y" and p.f_hz == 2.0)
    assert y2.sensitivity_diff_pct == 0.0 and y2.sensitivity_reference_f_hz == 2.0
    y05 = next(p for p in pts if p.axis == "y" and p.f_hz == 0.5)
    assert y05.sensitivity_diff_pct > 30  # |LP(0.5)| / |LP(2)| - 1 at 1.3 Hz = +55 %
    assert -30 < y05.phase_deg < 0


def test_chain_fit_recovers_cutoff_and_delay(chain_run) -> None:
    _, models = chain_run
    for i, ax in enumerate("xyz"):
        m = models[ax]
        err_fc = abs(m.cutoff_hz - FC[i]) / FC[i]
        err_tau = abs(m.delay_s - TAU)
        print(f"{ax}: fc {m.cutoff_hz:.4f} Hz (err {100 * err_fc:.3f} %, u {m.u_cutoff_hz:.2g}), "
              f"delay {1e3 * m.delay_s:.4f} ms (err {1e3 * err_tau:.4f} ms, u {1e3 * m.u_delay_s:.2g} ms), "
              f"gain {m.gain:.4f}")
        assert err_fc < 0.05
        assert err_tau < 1e-3
        assert m.gain == pytest.approx(1.0, rel=0.01)
        assert np.isfinite(m.u_cutoff_hz) and m.u_cutoff_hz > 0 and np.isfinite(m.u_delay_s)
        assert m.fit["converged"]
        # group delay at DC: delay + 1/(2 pi fc)
        assert group_delay_s(m, 0.0) == pytest.approx(m.delay_s + 1 / (2 * np.pi * m.cutoff_hz))


def test_chain_at_the_esp32_rate_of_100_hz_is_recovered() -> None:
    """100 Hz sampling (sensor_facts.md): 5 samples per period at 20 Hz. Steady-state tones are generated
    analytically (a bilinear filter warps 20 Hz by 15 % at this rate, which would be the generator's error)."""
    fs = 100.0
    rng = np.random.default_rng(10)
    a, segs, t_end = _piecewise_tones(FREQS, settle_s=4.0, periods=10, min_s=2.0, amp=1.0)
    t = np.arange(0, t_end, 1 / fs)
    d = np.array(SEED_DIRECTION)
    sens = np.zeros((t.size, 3))
    for f, ts, te in segs:
        m = (t >= ts) & (t < te)
        for i in range(3):
            h = complex(response(ChainModel(cutoff_hz=FC[i], delay_s=TAU), f))
            sens[m, i] = d[i] * abs(h) * np.sin(2 * np.pi * f * (t[m] - (ts - 4.0)) + np.angle(h))
    sens += 0.005 * rng.standard_normal(sens.shape)
    pts = analyse_run(t, a(t), sens, d, segs)
    for i, m in enumerate(fit_chain_models(pts).values()):
        print(f"100 Hz {m.axis}: fc err {100 * (m.cutoff_hz / FC[i] - 1):+.3f} %, delay err "
              f"{1e3 * (m.delay_s - TAU):+.4f} ms (u {1e3 * m.u_delay_s:.2g} ms)")
        assert m.cutoff_hz == pytest.approx(FC[i], rel=0.05)
        assert m.delay_s == pytest.approx(TAU, abs=1e-3)


def test_reference_highpass_is_recovered_when_present() -> None:
    t, ref, sens, segs = _synthetic_run(7, ref_highpass_hz=0.5)
    pts = analyse_run(t, ref, sens, SEED_DIRECTION, segs)
    x = [p for p in pts if p.axis == "x"]
    with_hp = fit_chain_model(x, highpass=True, highpass_in="reference")
    print(f"high-pass: fhp {with_hp.highpass_cutoff_hz:.4f} Hz, fc {with_hp.cutoff_hz:.4f} Hz, "
          f"delay {1e3 * with_hp.delay_s:.4f} ms")
    assert with_hp.highpass_cutoff_hz == pytest.approx(0.5, rel=0.05)
    assert with_hp.cutoff_hz == pytest.approx(FC[0], rel=0.05)
    assert with_hp.delay_s == pytest.approx(TAU, abs=1e-3)
    without = fit_chain_model(x)
    assert without.fit["chi2"] > 100 * with_hp.fit["chi2"]  # the plain model cannot explain the points


def test_axis_orthogonal_to_the_slide_is_not_measurable(caplog) -> None:
    direction = (0.6, 0.8, 0.0)
    t, ref, sens, segs = _synthetic_run(8, direction=direction)
    with caplog.at_level("WARNING"):
        pts = analyse_run(t, ref, sens, direction, segs[:2])
    z = [p for p in pts if p.axis == "z"]
    assert len(z) == 2 and not any(p.measurable for p in z)
    assert all("not measurable" in p.note and math.isnan(p.sensitivity) for p in z)
    assert "not measurable" in caplog.text
    assert all(p.measurable for p in pts if p.axis != "z")
    assert "z" not in fit_chain_models(pts, fit_gain=False)
    assert "not measurable" in points_table_markdown(pts)


def test_swapped_run_gives_negative_delay(chain_run) -> None:
    t, ref, sens, segs = _synthetic_run(6)
    # the x-axis output as "reference", the slide acceleration projected on x as "sensor" (direction x only)
    swapped = np.column_stack([ref * SEED_DIRECTION[0], np.zeros_like(ref), np.zeros_like(ref)])
    pts = analyse_run(t, sens[:, 0], swapped, (1.0, 0.0, 0.0), segs)
    normal = [p for p in chain_run[0] if p.axis == "x"]
    for p, q in zip([p for p in pts if p.axis == "x"], normal, strict=True):
        assert p.delay_xcorr_s < 0 and p.delay_cross_spectrum_s < 0 and p.phase_deg > 0
        assert p.delay_xcorr_s == pytest.approx(-q.delay_xcorr_s, abs=2e-4)


# --- uncertainty budget (seed 2.4, Tables 2-3) ------------------------------------------------------------

def test_resolution_term_is_one_sample_in_delay_and_its_phase_equivalent() -> None:
    d, p = resolution_components(100.0, 5.0)
    assert d.value == 1 / 100.0 and d.unit == "s"
    assert p.value == pytest.approx(360 * 5.0 / 100.0) and p.unit == "deg"
    assert d.standard_uncertainty == pytest.approx(d.value / math.sqrt(3))


def test_point_budget_keeps_its_components(chain_run) -> None:
    pts, _ = chain_run
    p = next(p for p in pts if p.axis == "x" and p.f_hz == 5.0)
    names = [c.name for c in p.budget_delay]
    assert names == ["repeatability", "resolution", "reference"]
    res = p.budget_delay[1]
    assert res.value == pytest.approx(1 / FS)
    assert p.budget_phase[1].value == pytest.approx(360 * 5.0 / FS)
    assert p.budget_delay[2].value == pytest.approx(0.2 / (360 * 5.0))  # reference phase 0.2 deg as delay
    assert p.u_delay_s == pytest.approx(math.sqrt(sum(c.standard_uncertainty ** 2 for c in p.budget_delay)))
    assert p.budget_sensitivity[1].standard_uncertainty == pytest.approx(0.005 * p.sensitivity)
    assert p.n_repeats == 8 and p.budget_phase[0].kind == "A"  # 10 periods -> 8 whole-period sub-blocks
    text = budget_table_markdown(p)
    assert "resolution" in text and "combined" in text


def test_repeats_at_one_frequency_are_pooled() -> None:
    t, ref, sens, segs = _synthetic_run(9)
    f, a, b = segs[3]  # 5 Hz, 10 periods
    mid = a + (b - a) / 2
    pts = analyse_run(t, ref, sens, SEED_DIRECTION, [(f, a, mid), (f, mid, b)])
    assert len(pts) == 3 and all(p.n_repeats == 2 for p in pts)
    assert "2 repeats" in pts[0].budget_delay[0].note


def test_chain_model_round_trips_through_a_dict() -> None:
    m = ChainModel(gain=0.98, cutoff_hz=1.7, delay_s=2.5e-3, highpass_cutoff_hz=0.5, u_cutoff_hz=0.01, axis="x")
    d = m.to_dict()
    assert d["cutoff_hz"] == 1.7 and d["delay_s"] == 2.5e-3 and d["highpass_in"] == "reference"
    assert d["u_delay_s"] is None  # unknown uncertainty, YAML-safe
    back = ChainModel.from_dict(d)
    np.testing.assert_allclose(response(back, [0.3, 2.0, 30.0]), response(m, [0.3, 2.0, 30.0]))
    assert back.u_cutoff_hz == 0.01
    for bad in ({"cutoff_hz": -1.0}, {"cutoff_hz": math.nan}, {"delay_s": 0.0}, {"cutoff_hz": 1.0, "highpass_in": "ldv"}):
        with pytest.raises(ValueError):
            ChainModel.from_dict(bad)


def test_a_chain_without_a_lowpass_round_trips_through_yaml() -> None:
    """The default chain has no low-pass (cut-off +inf): what to_dict writes, from_dict must read back."""
    import yaml

    back = ChainModel.from_dict(yaml.safe_load(yaml.safe_dump(ChainModel().to_dict())))
    assert back.cutoff_hz == math.inf and back.gain == 1.0


def test_group_delay_formula_matches_the_numerical_derivative() -> None:
    m = ChainModel(cutoff_hz=1.3, delay_s=2.5e-3, highpass_cutoff_hz=0.5, highpass_in="sensor")
    f = np.array([0.2, 1.0, 3.0, 10.0])
    df = 1e-5
    ph = lambda x: np.unwrap(np.angle(response(m, x)))  # noqa: E731
    num = -(ph(f + df) - ph(f - df)) / (2 * 2 * np.pi * df)
    np.testing.assert_allclose(group_delay_s(m, f), num, rtol=1e-5)
    assert group_delay_s(ChainModel(cutoff_hz=50.0), 0.0) == pytest.approx(1 / (2 * np.pi * 50.0))


def test_bode_plot_is_written(chain_run, tmp_path: Path) -> None:
    pts, models = chain_run
    out = plot_bode(pts, models, tmp_path / "bode.png", title="synthetic chain")
    assert out.exists() and out.stat().st_size > 10_000
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --- periods that are not a whole number of samples ---------------------------------------------------

@pytest.mark.parametrize(("fs", "f", "dur"), [(500.0, 0.7, 20.0), (100.002, 0.5, 20.0), (500.0, 3.3, 4.0),
                                              (333.0, 0.7, 20.0), (500.0, 2.2, 6.0)])
def test_segment_of_few_non_integer_periods_is_analysed(fs: float, f: float, dur: float) -> None:
    """Fewer than 16 periods of a tone whose period is not a whole number of samples: the one-period
    sub-blocks for the repeatability must still hold one whole period (they rounded down below it)."""
    rng = np.random.default_rng(11)
    t = np.arange(int(dur * fs)) / fs
    d = np.array(SEED_DIRECTION)
    ref = 2.0 * np.sin(2 * np.pi * f * t) + 0.002 * rng.standard_normal(t.size)
    sens = np.outer(0.9 * np.sin(2 * np.pi * f * (t - 0.01)), d) + 0.002 * rng.standard_normal((t.size, 3))
    pts = analyse_run(t, ref, sens, d, [(f, 0.0, dur)])
    for p in pts:
        assert p.n_repeats >= 4
        assert p.sensitivity == pytest.approx(0.45, rel=1e-3)  # 0.9 d_i / (2 d_i)
        assert p.delay_cross_spectrum_s == pytest.approx(0.01, abs=2e-4)
        assert p.delay_xcorr_s == pytest.approx(0.01, abs=2e-4)


def test_whole_period_span_is_accepted_back_as_whole_periods() -> None:
    """``whole_period_length`` returns ``round(k fs / f)`` samples for k periods; a block of exactly that
    many samples must count as k periods again (it counted as k - 1, or none for k = 1)."""
    for per in (714.2857142857143, 151.51515151515153, 200.004, 227.27272727272728, 100.5, 476.0):
        for k in range(1, 5):
            n = round(k * per)
            k_back, n_back = whole_period_length(n, per, 1.0)
            assert n_back <= n and abs(k_back * per - n_back) <= 0.5 + 1e-9
            assert k_back >= (k + 1) // 2 and (k > 1 or k_back == 1)


# --- lost frames ---------------------------------------------------------------------------------------

def test_a_lost_frame_outside_the_segments_does_not_matter() -> None:
    """The rate is the median step: one sample missing between two segments changes nothing (the whole run
    was refused as 'not uniformly sampled'); a sample missing inside a segment is refused naming it."""
    t, ref, sens, segs = _synthetic_run(4)
    clean = analyse_run(t, ref, sens, SEED_DIRECTION, segs)
    gap = int(np.searchsorted(t, 0.5 * (segs[1][2] + segs[2][1])))  # between the 2nd and 3rd segment
    keep = np.arange(t.size) != gap
    lost = analyse_run(t[keep], ref[keep], sens[keep], SEED_DIRECTION, segs)
    assert [p.to_dict() for p in lost] == [p.to_dict() for p in clean]
    f, a, b = segs[2]
    keep = np.arange(t.size) != int(np.searchsorted(t, 0.5 * (a + b)))
    with pytest.raises(ValueError, match=rf"segment {f:g} Hz .* not uniformly sampled"):
        analyse_run(t[keep], ref[keep], sens[keep], SEED_DIRECTION, segs)


# --- cross-correlation peak of a slow tone -------------------------------------------------------------

@pytest.mark.parametrize("f", [0.1, 0.5])
def test_slow_tone_delay_is_read_at_the_true_correlation_peak(f: float) -> None:
    """At low f/fs the tone's correlation peak is so flat that noise ripples on it lay within 1 % of the top
    over +-0.02 periods; taking the ripple nearest zero lag read a 100 ms delay as about 0 (0.1 Hz, 500 Hz).
    The xcorr delay must agree with the cross-spectrum's on the same noisy data, and be exact without noise."""
    fs, true_d = 500.0, 0.100
    n = round(5 * fs / f)  # 5 whole periods
    t = np.arange(n) / fs
    errs = []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        ref = np.cos(2 * np.pi * f * t) + 0.2 * rng.standard_normal(n)
        sig = 0.8 * np.cos(2 * np.pi * f * (t - true_d)) + 0.2 * rng.standard_normal(n)
        d_xc = delay_by_cross_correlation(ref, sig, fs, max_lag_s=0.5 / f, circular=True)
        d_cs = delay_by_cross_spectrum(ref, sig, fs, f)
        assert abs(d_xc - d_cs) < 1e-3, (seed, d_xc, d_cs)
        errs.append(d_xc - true_d)
    assert abs(np.mean(errs)) < 3e-3 and np.max(np.abs(errs)) < 10e-3, errs
    for d in (true_d, -0.037):
        clean = delay_by_cross_correlation(np.cos(2 * np.pi * f * t), np.cos(2 * np.pi * f * (t - d)), fs,
                                           max_lag_s=0.5 / f, circular=True)
        assert clean == pytest.approx(d, abs=1e-6)


def test_equal_peaks_a_period_apart_resolve_to_the_one_nearest_zero_lag() -> None:
    """The tie rule's purpose (kept): the circular correlation of whole periods, with no lag limit, has equal
    peaks a whole period apart; the delay is the one nearest zero (MATLAB finddelay), here 0.3 periods, not
    -0.7 or 1.3, whichever of them noise makes a little higher."""
    f, d = 2.0, 0.15  # 0.3 periods
    t = np.arange(0, 5.0, 1 / FS)  # 10 whole periods
    for seed in range(4):
        rng = np.random.default_rng(seed)
        ref = np.sin(2 * np.pi * f * t) + 0.05 * rng.standard_normal(t.size)
        sig = np.sin(2 * np.pi * f * (t - d)) + 0.05 * rng.standard_normal(t.size)
        assert delay_by_cross_correlation(ref, sig, FS, circular=True) == pytest.approx(d, abs=1e-3)
        assert delay_by_cross_correlation(sig, ref, FS, circular=True) == pytest.approx(-d, abs=1e-3)


@pytest.mark.parametrize("where", ["reference", "sensor"])
def test_group_delay_at_dc_is_the_sensor_chain_s_whatever_the_highpass(where: str) -> None:
    """``group_delay_dc_s`` is what the driver's stamp correction removes, ``delay + 1/(2 pi fc)`` of the
    axis (ChainDynamics.group_delay_s); a fitted high-pass (the LDV's, or one with no gain at DC) is not in
    it. With a reference high-pass of 0.47 Hz it read -223 ms instead of +114 ms."""
    from fbg_accel_driver.chain_compensation import ChainDynamics

    m = ChainModel(cutoff_hz=1.6954, delay_s=0.020064, highpass_cutoff_hz=0.4717, highpass_in=where)
    expected = 0.020064 + 1 / (2 * np.pi * 1.6954)
    assert m.to_dict()["group_delay_dc_s"] == pytest.approx(expected, rel=1e-12)
    assert m.sensor_group_delay_dc_s() == pytest.approx(expected, rel=1e-12)
    dyn = ChainDynamics(cutoff_hz=(math.nan, 1.6954, 1.3, 1.3), delay_s=(0.020064, 0.0, 0.0))
    assert dyn.group_delay_s(0) == pytest.approx(m.to_dict()["group_delay_dc_s"], rel=1e-12)


def _model_points(model: ChainModel, freqs: Sequence[float], u_rel: float = 0.01, u_deg: float = 0.5
                  ) -> list[DynamicPoint]:
    """Noise-free points of ``model`` (axis x) with the given standard uncertainties."""
    pts = []
    for f in freqs:
        h = complex(response(model, f))
        pts.append(DynamicPoint(f_hz=f, axis="x", axis_index=0, direction_component=1.0, sensitivity=abs(h),
                                phase_deg=math.degrees(np.angle(h)), u_sensitivity=u_rel * abs(h), u_phase_deg=u_deg))
    return pts


@pytest.mark.parametrize("freqs", [(20.0, 30.0, 40.0, 60.0, 80.0), (15.0, 20.0, 25.0, 30.0), (0.5, 1.0, 2.0, 5.0, 10.0, 20.0)])
def test_chain_fit_starts_on_the_right_phase_branch(freqs: tuple[float, ...]) -> None:
    """The start's delay comes from the phase left after the low-pass, which is -2 pi f tau only up to a
    common multiple of 2 pi: with the lowest frequency already past -180 deg (20 ms at 20-80 Hz) the start sat
    on the wrong branch and the fit ran away (fc 2e-17 Hz, gain 8e16). The branch is where the line through
    the unwrapped phase meets f = 0."""
    truth = ChainModel(cutoff_hz=1.7, delay_s=0.020)
    m = fit_chain_model(_model_points(truth, freqs), uncertainty_scaling="points")
    assert m.cutoff_hz == pytest.approx(1.7, rel=1e-4) and m.delay_s == pytest.approx(0.020, abs=1e-7)
    assert m.gain == pytest.approx(1.0, rel=1e-4) and m.fit["chi2"] < 1e-6


@pytest.mark.parametrize("fc_hz", [1.7, 50.0])
@pytest.mark.parametrize("delay_s", [0.08, 0.15, 0.3, 0.5, -0.2])
def test_chain_fit_finds_a_long_delay_on_the_shipped_plan(fc_hz: float, delay_s: float) -> None:
    """On the shipped plan's frequencies (0.5, 1, 2, 5, 10, 20 Hz) the phase of a pure delay of 80 ms or more
    turns by more than 180 deg between neighbouring points (2 -> 5 Hz: 3 Hz x 80 ms = 86 deg of delay plus the
    low-pass' change; 5 -> 10 Hz: 144 deg), so unwrapping along the frequencies started the fit on a wrong
    branch. On noise-free points, before: 80 ms with fc 1.7 Hz came back as fc 24.7 Hz, 128 ms, gain 0.17
    (chi2 9.5e4), 300 ms as fc 0.49 Hz, 138 ms; 500 ms with fc 50 Hz as fc 3e-9 Hz, gain 2.4e8 (fbg-accel-calib
    dynamic then refused the run on a simulated 300 ms channel_delay). These frequencies fix a delay modulo
    2 s, so every delay the driver accepts (|delay| <= 1 s) is identified."""
    truth = ChainModel(cutoff_hz=fc_hz, delay_s=delay_s)
    m = fit_chain_model(_model_points(truth, (0.5, 1.0, 2.0, 5.0, 10.0, 20.0)), uncertainty_scaling="points")
    assert m.cutoff_hz == pytest.approx(fc_hz, rel=1e-4) and m.delay_s == pytest.approx(delay_s, abs=1e-7)
    assert m.gain == pytest.approx(1.0, rel=1e-4) and m.fit["chi2"] < 1e-6


def test_a_single_period_point_is_refused() -> None:
    """One whole period gives no measured repeatability; the sine fits' white-noise covariance it fell back to
    understated the scatter 5-13x on the simulator's coloured noise (p14: rms z 9.6 / 13 / 9.5 in S), so such
    a point would dominate the chain fit. Two periods (two sub-blocks) or two one-period repeats are enough."""
    t, ref, sens, segs = _synthetic_run(5)
    f, a, _ = segs[3]  # 5 Hz
    with pytest.raises(ValueError, match=r"segment 5 Hz .* one whole period"):
        analyse_run(t, ref, sens, SEED_DIRECTION, [(f, a, a + 1.5 / f)])
    two = analyse_run(t, ref, sens, SEED_DIRECTION, [(f, a, a + 2.0 / f + 1e-9)])
    assert all(p.n_repeats == 2 for p in two)
    rep = analyse_run(t, ref, sens, SEED_DIRECTION, [(f, a, a + 1.0 / f + 1e-9), (f, a + 1.0 / f, a + 2.0 / f + 1e-9)])
    assert all(p.n_repeats == 2 for p in rep)
    # two periods of 0.7 Hz at 500 Hz (1428.57 samples): the cut must keep both, not the one period whose span
    # is nearer a whole number of samples (714.29)
    t7 = np.arange(1430) / 500.0
    d = np.array(SEED_DIRECTION)
    two7 = analyse_run(t7, np.sin(2 * np.pi * 0.7 * t7), np.outer(0.5 * np.sin(2 * np.pi * 0.7 * t7), d), d,
                       [(0.7, 0.0, 3.0)])
    assert all(p.n_repeats == 2 for p in two7)
