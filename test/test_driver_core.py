"""Unit tests of the pure driver core and its diagnostics (frames built with frame_codec)."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fbg_accel_driver import correction_terms
from fbg_accel_driver.correction_terms import ReferenceDarkOffset, ThermalLag, TiaInverseFilter
from fbg_accel_driver.driver_core import AHT10_SIGMA_C, CoreConfig, DriverCore
from fbg_accel_driver.driver_diagnostics import ERROR, OK, STALE, WARN, DiagnosticsSnapshot, DriverDiagnostics
from fbg_accel_driver.frame_codec import ADC_MAX, Frame, Status, encode_frame
from fbg_accel_driver.thermal_model import ThermalCalibration

REPO = Path(__file__).resolve().parents[1]
T0_NS = 1_700_000_000_000_000_000
GOOD = int(Status.TEMP_VALID | Status.TEMP_PRESENT)


def make_cal(**kw: Any) -> ThermalCalibration:
    """Degree-1 model with distinct, non-trivial coefficients (range 10..40 degC)."""
    M = np.array([[[80.0, 3.0, 0.7], [1.6, 77.0, 3.7], [0.2, 1.2, 107.0]], np.diag([0.05, -0.03, 0.02])])
    b = np.array([[-100.0, -150.0, -137.0], [0.1, 0.2, -0.1]])
    args = {"M": M, "b": b, "temperature_range_c": (10.0, 40.0), "t_center_c": 25.0, "t_scale_c": 10.0,
            "noise_sigma_mps2": np.array([0.02, 0.03, 0.04]), "sensor_id": "unit"}
    args.update(kw)
    return ThermalCalibration(**args)


def frame(i: int, ref: int = 870, xyz: tuple[int, int, int] = (1100, 1600, 1100), temp_cc: int = 2340,
          status: int = GOOD, t0_us: int = 0) -> Frame:
    return Frame(seq=i % 65536, t_us=t0_us + i * 10_000, ref=ref, x=xyz[0], y=xyz[1], z=xyz[2], temp_cc=temp_cc, status=status)


def feed_frames(core: DriverCore, frames: list[Frame], chunk: int = 5) -> tuple[list, list, list]:
    """Feed frames in chunks of ``chunk`` frames, as arriving 2 ms after their board time."""
    raw, imu, temp = [], [], []
    for k in range(0, len(frames), chunk):
        part = frames[k : k + chunk]
        data = b"".join(encode_frame(f) for f in part)
        out = core.feed(data, T0_NS + part[-1].t_us * 1000 + 2_000_000)
        raw += out.raw
        imu += out.imu
        temp += out.temperature
    out = core.flush()
    return raw + out.raw, imu + out.imu, temp + out.temperature


def all_finite(records: list) -> bool:
    return all(math.isfinite(v) for r in records for v in (*r.accel_mps2, *r.covariance, r.temperature_c))


def test_calibrated_values_match_eq24_eq28() -> None:
    cal = make_cal()
    core = DriverCore(cal)
    rng = np.random.default_rng(0)
    frames = [frame(i, ref=int(rng.integers(800, 900)), xyz=tuple(int(v) for v in rng.integers(900, 1800, 3)),
                    temp_cc=int(rng.integers(1500, 3500))) for i in range(50)]
    raw, imu, temp = feed_frames(core, frames, chunk=7)
    assert len(raw) == len(imu) == len(temp) == 50
    ref = np.array([f.ref for f in frames], float)
    xyz = np.array([(f.x, f.y, f.z) for f in frames], float)
    t = np.array([f.temp_cc / 100 for f in frames])
    psi = xyz / ref[:, None]  # eq. 24
    tau = (t - 25.0) / 10.0
    expected = np.einsum("nij,nj->ni", cal.M[0] + tau[:, None, None] * cal.M[1], psi) + cal.b[0] + tau[:, None] * cal.b[1]
    got = np.array([r.accel_mps2 for r in imu])
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-9)
    cov = np.array(imu[0].covariance).reshape(3, 3)
    np.testing.assert_allclose(np.diag(cov), cal.noise_sigma_mps2**2)
    assert cov[0, 1] == cov[1, 2] == 0.0
    assert temp[3].temperature_c == frames[3].temp_cc / 100 and temp[3].variance == AHT10_SIGMA_C**2
    assert [r.frame for r in raw] == frames
    stamps = [r.stamp_ns for r in raw]
    assert stamps == [r.stamp_ns for r in imu] and all(np.diff(stamps) > 0)


def test_driver_output_with_stateful_terms_equals_the_offline_model() -> None:
    """Frames through DriverCore in reads of 101 bytes (frames cut across reads; the terms' state carried from read
    to read) equal ``apply_counts`` of the whole stream in one batch (what fit and diagnose evaluate), with stateful
    terms (TIA inverse filter, thermal lag) around a reference dark offset. The terms move the output by more than
    0.01 m/s^2, so a term left out or a state reset at a read shows."""
    terms = [TiaInverseFilter(np.array([0.0, 0.09, 0.12, 0.12])), ReferenceDarkOffset(-40.0), ThermalLag(30.0)]
    cal = make_cal(corrections=terms, temperature_range_c=(0.0, 60.0))
    rng = np.random.default_rng(7)
    n = 900
    frames = [frame(i, ref=int(rng.integers(860, 880)), xyz=tuple(int(v) for v in rng.integers(1090, 1110, 3)),
                    temp_cc=round(2200 + 0.2 * i)) for i in range(n)]
    ref = np.array([f.ref for f in frames], float)
    xyz = np.array([(f.x, f.y, f.z) for f in frames], float)
    temp, t_s = np.array([f.temp_cc / 100 for f in frames]), np.arange(n) * 0.01
    offline = cal.apply_counts(ref, xyz, temp, t_s)
    core, data = DriverCore(cal), b"".join(encode_frame(f) for f in frames)
    got = np.array([r.accel_mps2 for k in range(0, len(data), 101)
                    for r in core.feed(data[k:k + 101], T0_NS + k // 27 * 10_000_000 + 2_000_000).imu])
    assert got.shape == offline.shape
    np.testing.assert_allclose(got, offline, rtol=0, atol=1e-9)
    assert np.max(np.abs(make_cal(temperature_range_c=(0.0, 60.0)).apply_counts(ref, xyz, temp, t_s) - offline)) > 0.01


def test_zero_and_low_reference_are_dropped_never_nan() -> None:
    core = DriverCore(make_cal(), CoreConfig(min_reference_counts=50))
    frames = [frame(0), frame(1, ref=0), frame(2, ref=49), frame(3, ref=50), frame(4, ref=0, xyz=(0, 0, 0))]
    raw, imu, _ = feed_frames(core, frames)
    assert len(raw) == 5  # raw counts always published
    assert len(imu) == 2 and all_finite(imu)
    assert core.counters.reference_low == 3
    assert core.decoder.stats.frames == 5


def test_adc_saturation_inflates_covariance_of_affected_axes() -> None:
    cfg = CoreConfig()
    core = DriverCore(make_cal(), cfg)
    # an axis at either rail (4095 or 0 counts) is clipped; the reference at full scale clips every axis
    frames = [frame(0), frame(1, xyz=(ADC_MAX, 1600, 1100)), frame(2, ref=ADC_MAX), frame(3, xyz=(1500, 1600, 0))]
    _, imu, _ = feed_frames(core, frames)
    assert len(imu) == 4 and all_finite(imu)
    c0, c1, c2, c3 = (np.diag(np.reshape(r.covariance, (3, 3))) for r in imu)
    fs2 = cfg.full_scale_mps2**2
    assert c1[0] == fs2 and c1[1] == c0[1] and c1[2] == c0[2]
    np.testing.assert_array_equal(c2, [fs2] * 3)
    assert c3[2] == fs2 and c3[0] == c0[0] and c3[1] == c0[1]
    assert "adc_saturated" in imu[1].flags and "adc_saturated" in imu[3].flags and not imu[0].flags
    assert core.counters.adc_saturated == 3


def test_temperature_invalid_is_held_then_dropped() -> None:
    core = DriverCore(make_cal(), CoreConfig(temperature_hold_s=0.5))
    # 10 valid frames at 24 degC, then 100 frames (1 s) with the AHT10 invalid and garbage temperature.
    frames = [frame(i, temp_cc=2400) for i in range(10)]
    frames += [frame(i, temp_cc=-27315, status=int(Status.TEMP_PRESENT)) for i in range(10, 110)]
    frames += [frame(i, temp_cc=2500) for i in range(110, 115)]
    raw, imu, temp = feed_frames(core, frames)
    c = core.counters
    assert c.temperature_invalid == 100
    assert c.temperature_held == 50  # 0.01 .. 0.50 s after the last good reading
    assert c.temperature_stale_dropped == 50
    assert len(imu) == 10 + 50 + 5 and all_finite(imu)
    assert all(r.temperature_c == 24.0 for r in imu[10:60]) and all("temperature_held" in r.flags for r in imu[10:60])
    assert len(temp) == 15  # only fresh valid readings go to imu/temperature
    assert raw[50].temperature_c == 24.0 and not raw[50].temperature_valid
    assert core.last_temperature_valid is True


def test_temperature_never_valid_drops_imu_and_raw_temperature_is_nan() -> None:
    core = DriverCore(make_cal())
    frames = [frame(i, status=0) for i in range(20)]
    raw, imu, temp = feed_frames(core, frames)
    assert imu == [] and temp == []
    assert all(math.isnan(r.temperature_c) for r in raw)
    assert core.counters.temperature_stale_dropped == 20
    assert core.temperature_age_s is None


def test_out_of_range_temperature_inflates_covariance() -> None:
    cfg = CoreConfig(out_of_range_variance_factor=10.0)
    core = DriverCore(make_cal(), cfg)
    frames = [frame(0, temp_cc=2500), frame(1, temp_cc=5000), frame(2, temp_cc=500)]
    _, imu, _ = feed_frames(core, frames)
    base = np.diag(np.reshape(imu[0].covariance, (3, 3)))
    for r in imu[1:]:
        var = np.diag(np.reshape(r.covariance, (3, 3)))
        assert np.all(var >= 10.0 * base) and "temperature_out_of_range" in r.flags
    assert core.counters.temperature_out_of_range == 2 and all_finite(imu)
    # The extrapolation term is the distance between the model at 50 degC and at the 40 degC edge.
    cal = make_cal()
    f = frames[1]
    psi = np.array([[f.x, f.y, f.z]], float) / f.ref
    extrap = cal.base_acceleration(psi, 50.0)[0] - cal.base_acceleration(psi, cal.temperature_range_c[1])[0]
    var1 = np.diag(np.reshape(imu[1].covariance, (3, 3)))
    np.testing.assert_allclose(var1, 10.0 * base + extrap**2, rtol=1e-9)
    assert np.all(extrap**2 > 1e-6)


def test_a_reading_within_the_temperature_margin_of_the_calibrated_range_is_inside() -> None:
    """The calibrated range is the span of the few AHT10 readings the fit used (about 12 independent readings per level
    in a six-position campaign), so the same chamber level read later goes a little beyond it: in a simulated campaign
    the driver flagged a few percent of the samples it read at the lowest calibrated level as out of range, with 10x
    the variance, the WARN coming and going. A reading within ``temperature_range_margin_c`` (default: the AHT10's
    stated uncertainty, the standard deviation the driver publishes with each temperature) of the range is inside;
    beyond it the policy is as before, its extrapolation measured from the range edge itself. On the code before, all
    four readings beyond the range here were flagged."""
    cal = make_cal()  # range 10..40 degC
    frames = [frame(0, temp_cc=2500), frame(1, temp_cc=995), frame(2, temp_cc=4025), frame(3, temp_cc=960),
              frame(4, temp_cc=4045)]
    core = DriverCore(cal, CoreConfig(out_of_range_variance_factor=10.0))
    assert core.config.temperature_range_margin_c == AHT10_SIGMA_C
    _, imu, _ = feed_frames(core, frames)
    base = np.diag(np.reshape(imu[0].covariance, (3, 3)))
    for r in imu[1:3]:  # 0.05 and 0.25 degC beyond the range: within the margin
        assert "temperature_out_of_range" not in r.flags
        np.testing.assert_allclose(np.diag(np.reshape(r.covariance, (3, 3))), base, rtol=1e-12)
    for r in imu[3:]:  # 0.4 and 0.45 degC beyond: outside
        assert "temperature_out_of_range" in r.flags
        assert np.all(np.diag(np.reshape(r.covariance, (3, 3))) >= 10.0 * base)
    assert core.counters.temperature_out_of_range == 2
    # the diagnostics judge the latest reading by the same margin (the node passes the core's)
    d = DriverDiagnostics()
    near = replace(snapshot(0.0, last_t=40.25), temperature_range_margin_c=AHT10_SIGMA_C)
    assert levels(d.report(near))["temperature range"] == OK
    assert levels(d.report(replace(near, now_s=0.1, last_temperature_c=40.45)))["temperature range"] == WARN
    strict = DriverCore(cal, CoreConfig(temperature_range_margin_c=0.0))
    feed_frames(strict, frames)
    assert strict.counters.temperature_out_of_range == 4
    with pytest.raises(ValueError, match="temperature_range_margin_c"):
        CoreConfig(temperature_range_margin_c=-0.1).validate()


def test_a_correction_term_outside_its_fitted_span_is_held_flagged_and_inflates_covariance() -> None:
    """A time drift fitted on board time 0..0.5 s (a short calibration run): after the span the creep is held at
    its last value, not extrapolated; the sample is flagged and counted, and each axis variance is inflated as
    outside the temperature range: factor x sigma^2 + (what the formula would have added beyond the edge)^2."""
    drift = correction_terms.TimeDrift(np.array([2.0, -1.0, 0.5]), np.zeros(3), 100.0, 0.0, span_s=(0.0, 0.5))
    cfg = CoreConfig(out_of_range_variance_factor=10.0)
    core = DriverCore(make_cal(corrections=[drift]), cfg)
    frames = [frame(i) for i in range(100)]  # board time 0 .. 0.99 s
    _, imu, _ = feed_frames(core, frames)
    plain = feed_frames(DriverCore(make_cal()), frames)[1]
    assert len(imu) == len(plain) == 100 and all_finite(imu)
    sigma2 = np.diag(np.reshape(plain[0].covariance, (3, 3)))
    for i, (r, p) in enumerate(zip(imu, plain, strict=True)):
        t = i * 0.01
        shift = np.subtract(r.accel_mps2, p.accel_mps2)
        np.testing.assert_allclose(shift, drift.creep_mps2_per_s * min(t, 0.5), rtol=0, atol=1e-9)
        var = np.diag(np.reshape(r.covariance, (3, 3)))
        if t <= 0.5:
            assert "correction_out_of_span" not in r.flags
            np.testing.assert_allclose(var, sigma2, rtol=1e-12)
        else:
            assert "correction_out_of_span" in r.flags
            np.testing.assert_allclose(var, 10.0 * sigma2 + (drift.creep_mps2_per_s * (t - 0.5)) ** 2, rtol=1e-9)
    assert core.counters.correction_out_of_span == 49
    d = DriverDiagnostics()
    d.report(snapshot(0.0, frames=0))
    e = d.report(snapshot(1.0, frames=100, core=core.counters.as_dict()))
    assert levels(e)["correction span"] == WARN and values(e, "correction span")["correction_out_of_span"] == "49"
    assert levels(d.report(snapshot(2.0, frames=200, core=core.counters.as_dict())))["correction span"] == OK


def test_decimation_averages_and_scales_variance() -> None:
    cal = make_cal()
    frames = [frame(i, xyz=(1000 + i, 1600, 1100 - i)) for i in range(22)]
    _, full, _ = feed_frames(DriverCore(cal), frames)
    _, dec, _ = feed_frames(DriverCore(cal, CoreConfig(decimation=4)), frames, chunk=3)
    assert len(dec) == 5  # 22 // 4, the last 2 samples wait for their block
    for k, r in enumerate(dec):
        block = full[4 * k : 4 * k + 4]
        np.testing.assert_allclose(r.accel_mps2, np.mean([b.accel_mps2 for b in block], axis=0), rtol=1e-12)
        np.testing.assert_allclose(r.covariance, np.array(block[0].covariance) / 4, rtol=1e-12)
        assert r.stamp_ns == sum(b.stamp_ns for b in block) // 4


def test_board_reset_bad_crc_duplicates_counted_every_intact_frame_once() -> None:
    core = DriverCore(make_cal())
    first = [frame(i) for i in range(30)]
    second = [frame(i, status=GOOD | int(Status.BOOT) if i == 0 else GOOD, t0_us=5_000) for i in range(20)]
    stream = b""
    for f in first[:10]:
        stream += encode_frame(f)
    bad = bytearray(encode_frame(first[10]))
    bad[12] ^= 0x10  # bit flip
    stream += bytes(bad) + b"\x00\xa5garbage\xa5\x5a" + encode_frame(first[11]) + encode_frame(first[11])  # duplicate
    stream += encode_frame(first[12])[:15]  # truncated
    stream += b"".join(encode_frame(f) for f in first[13:]) + b"".join(encode_frame(f) for f in second)
    raw, imu = [], []
    decimated = DriverCore(make_cal(), CoreConfig(decimation=3))
    n_dec = 0
    for k in range(0, len(stream), 13):  # odd chunk size, frames straddle chunks
        out = core.feed(stream[k : k + 13], T0_NS + k * 40_000)
        raw += out.raw
        imu += out.imu
        n_dec += len(decimated.feed(stream[k : k + 13], T0_NS + k * 40_000).imu)
    out = core.flush()
    raw += out.raw
    imu += out.imu
    n_dec += len(decimated.flush().imu)
    assert n_dec == 28 // 3 + 20 // 3  # a decimation block never spans a board reset
    intact = first[:10] + first[11:12] + first[13:] + second
    assert [r.frame for r in raw] == intact
    assert len(imu) == len(intact)
    s = core.decoder.stats
    assert s.crc_errors >= 2 and s.duplicates == 1 and s.resets == 1 and s.lost_frames == 2
    assert core.counters.board_resets == 1
    stamps = [r.stamp_ns for r in raw]
    assert all(b > a for a, b in itertools.pairwise(stamps))


@settings(max_examples=60, deadline=None)
@given(
    fields=st.lists(
        st.tuples(st.integers(0, ADC_MAX), st.integers(0, ADC_MAX), st.integers(0, ADC_MAX), st.integers(0, ADC_MAX),
                  st.integers(-32768, 32767), st.integers(0, 255)),
        min_size=1, max_size=40),
    noise=st.binary(max_size=64),
)
def test_nothing_non_finite_ever_leaves_the_core(fields: list, noise: bytes) -> None:
    core = DriverCore(make_cal())
    frames = [Frame(i, i * 10_000, *f) for i, f in enumerate(fields)]
    data = noise + b"".join(encode_frame(f) for f in frames)
    out = core.feed(data, T0_NS)
    rest = core.flush()
    out.raw += rest.raw
    out.imu += rest.imu
    out.temperature += rest.temperature
    assert all_finite(out.imu)
    assert all(math.isfinite(t.temperature_c) for t in out.temperature)
    assert len(out.raw) == core.decoder.stats.frames


def test_core_config_validation() -> None:
    for bad in (CoreConfig(decimation=0), CoreConfig(covariance_source="guess"), CoreConfig(temperature_hold_s=math.nan),
                CoreConfig(covariance_source="parameter", accel_stddev_mps2=0.0)):
        with pytest.raises(ValueError):
            DriverCore(make_cal(), bad)
    core = DriverCore(make_cal(), CoreConfig(covariance_source="parameter", accel_stddev_mps2=0.5))
    _, imu, _ = feed_frames(core, [frame(0)])
    np.testing.assert_allclose(np.diag(np.reshape(imu[0].covariance, (3, 3))), [0.25] * 3)
    core = DriverCore(make_cal(), CoreConfig(covariance_source="unknown"))
    _, imu, _ = feed_frames(core, [frame(0)])
    assert imu[0].covariance == (0.0,) * 9


def test_unknown_covariance_stays_unknown_under_every_policy() -> None:
    """``covariance_source: unknown`` publishes the all-zero matrix, REP 145's "covariance unknown", also for the
    samples a policy would inflate: there is no variance to inflate. Before, a saturated x gave diag((20 g)^2, 0, 0),
    which states y and z exactly known, and a temperature outside the calibrated range gave diag(d^2), d the
    polynomial's move from the range edge: for the simulated sensor at 46 degC (0.7 degC above its range) 0.002
    and 0.001 (m/s^2)^2 on y and z, below its in-range noise variance (0.009, 0.017). A consumer trusted most
    exactly the samples the policies flag."""
    drift = correction_terms.TimeDrift(np.array([2.0, -1.0, 0.5]), np.zeros(3), 100.0, 0.0, span_s=(0.0, 0.05))
    core = DriverCore(make_cal(corrections=[drift]), CoreConfig(covariance_source="unknown"))
    frames = [frame(0), frame(1), frame(2), frame(3), frame(4), frame(5, xyz=(ADC_MAX, 1600, 1100)),
              frame(6, ref=ADC_MAX), frame(7, xyz=(1500, 1600, 0)), frame(8, temp_cc=5000), frame(9, temp_cc=500),
              frame(10, temp_cc=-27315, status=int(Status.TEMP_PRESENT))]
    _, imu, _ = feed_frames(core, frames)
    assert len(imu) == len(frames) and all_finite(imu)
    assert [r.covariance for r in imu] == [(0.0,) * 9] * len(frames)
    c = core.counters  # the policies still flag and count the samples (diagnostics)
    assert (c.adc_saturated, c.temperature_out_of_range, c.temperature_held, c.correction_out_of_span) == (3, 3, 1, 5)
    assert "adc_saturated" in imu[5].flags and "temperature_out_of_range" in imu[8].flags


# ----------------------------------------------------------------------------- diagnostics
def snapshot(now: float, *, connected: bool = True, frames: int = 0, crc: int = 0, lost: int = 0,
             core: dict | None = None, temp_valid: bool | None = True, age: float | None = 0.0,
             last_t: float | None = 24.0) -> DiagnosticsSnapshot:
    return DiagnosticsSnapshot(
        now_s=now, link_connected=connected, link_message="open" if connected else "cannot open /dev/x: gone",
        link_values={"port": "/dev/x"}, decoder={"frames": frames, "crc_errors": crc, "lost_frames": lost, "resets": 0},
        core=core or {}, temperature_valid=temp_valid, temperature_age_s=age, last_temperature_c=last_t,
        temperature_hold_s=5.0, temperature_range_c=(10.0, 40.0),
    )


def levels(entries: list) -> dict[str, int]:
    return {e.name.split(": ", 1)[1]: e.level for e in entries}


def values(entries: list, what: str) -> dict[str, str]:
    return dict(next(e for e in entries if e.name.endswith(what)).values)


def test_the_clock_mapping_is_stated_and_warned_when_its_drift_sits_at_the_clamp() -> None:
    d = DriverDiagnostics()
    assert "clock mapping" not in levels(d.report(snapshot(0.0)))  # no clock status given: no entry
    ok = {"board_clock_ppm": 23.5, "drift_at_limit": False, "restarts": 1, "ros_time_steps": 0}
    e = d.report(replace(snapshot(1.0, frames=100), clock=ok))
    assert levels(e)["clock mapping"] == OK and values(e, "clock mapping")["board_clock_ppm"] == "23.5"
    stuck = {**ok, "board_clock_ppm": 500.0, "drift_at_limit": True}
    assert levels(d.report(replace(snapshot(2.0, frames=200), clock=stuck)))["clock mapping"] == WARN


def test_diagnostics_levels_follow_deltas_and_states() -> None:
    d = DriverDiagnostics()
    e = d.report(snapshot(0.0, frames=0, temp_valid=None, age=None, last_t=None))
    assert levels(e)["serial link"] == ERROR and levels(e)["temperature sensor"] == STALE
    e = d.report(snapshot(1.0, frames=100))
    assert set(levels(e).values()) == {OK}
    assert float(values(e, "frames")["frame_rate_hz"]) == pytest.approx(100.0)
    e = d.report(snapshot(2.0, frames=195, crc=3, lost=5))
    assert levels(e)["frames"] == WARN
    v = values(e, "frames")
    assert v["crc_errors"] == "3" and v["lost_frames"] == "5"
    e = d.report(snapshot(3.0, frames=295, crc=3, lost=5))
    assert levels(e)["frames"] == OK and values(e, "frames")["crc_errors"] == "3"  # cumulative count kept
    e = d.report(snapshot(4.0, connected=False, frames=295, crc=3, lost=5))
    assert levels(e)["serial link"] == ERROR
    e = d.report(snapshot(5.0, frames=300, core={"adc_saturated": 2, "reference_low": 1}, temp_valid=False, age=2.0))
    lv = levels(e)
    assert lv["serial link"] == OK and lv["ADC saturation"] == WARN and lv["reference power"] == ERROR
    assert lv["temperature sensor"] == WARN
    e = d.report(snapshot(6.0, frames=400, core={"adc_saturated": 2, "reference_low": 1}, temp_valid=False, age=6.0))
    lv = levels(e)
    assert lv["temperature sensor"] == ERROR and lv["ADC saturation"] == OK and lv["reference power"] == OK
    e = d.report(snapshot(7.0, frames=500, last_t=45.0))
    assert levels(e)["temperature range"] == WARN
    e = d.report(snapshot(8.0, frames=500))
    assert levels(e)["serial link"] == ERROR  # connected, but silent for a second


def test_start_up_stall_does_not_break_stamp_spacing() -> None:
    """The first chunk arrives 80 ms late (process start-up); later ones 2 ms after sampling.

    Stamping the first frames from that one delay would need a 78 ms step back later; the core
    holds them until the clock estimate is primed, so every spacing stays the board period.
    """
    core = DriverCore(make_cal())
    frames = [frame(i) for i in range(300)]
    stamps = []
    for k in range(0, 300, 5):
        part = frames[k : k + 5]
        delay_ns = 80_000_000 if k == 0 else 2_000_000
        out = core.feed(b"".join(encode_frame(f) for f in part), T0_NS + part[-1].t_us * 1000 + delay_ns)
        stamps += [r.stamp_ns for r in out.raw]
    assert len(stamps) == 300 and core.clock.steps == 0
    spacing = np.diff(stamps) * 1e-9
    assert np.all(np.abs(spacing - 0.01) < 0.01 * 0.01), (spacing.min(), spacing.max())
    assert abs(stamps[-1] - (T0_NS + frames[-1].t_us * 1000)) < 3_000_000  # within the 2 ms floor (+ slew residue)


def test_non_finite_drops_and_reader_queue_drops_are_reported() -> None:
    """``non_finite_dropped`` (the core's last guard) is published and is an ERROR while it grows;
    bytes dropped by the bounded reader queue are a WARN while they grow (issue 11)."""
    d = DriverDiagnostics()
    d.report(snapshot(0.0, frames=100))
    e = d.report(snapshot(1.0, frames=200, core={"non_finite_dropped": 7}))
    assert levels(e)["calibrated output"] == ERROR
    assert values(e, "calibrated output")["non_finite_dropped"] == "7"
    e = d.report(snapshot(2.0, frames=300, core={"non_finite_dropped": 7}))
    assert levels(e)["calibrated output"] == OK and values(e, "calibrated output")["non_finite_dropped"] == "7"

    def link(dropped: int) -> dict:
        return {"port": "/dev/x", "queued_bytes": 10, "queue_max_bytes": 4096, "queue_dropped_chunks": dropped // 100,
                "queue_dropped_bytes": dropped}

    base = snapshot(3.0, frames=400)
    e = d.report(DiagnosticsSnapshot(**{**base.__dict__, "link_values": link(0)}))
    assert levels(e)["reader queue"] == OK
    e = d.report(DiagnosticsSnapshot(**{**base.__dict__, "now_s": 4.0, "decoder": {**base.decoder, "frames": 500},
                                        "link_values": link(5000)}))
    assert levels(e)["reader queue"] == WARN and "5000 byte(s) dropped" in next(
        x.message for x in e if x.name.endswith("reader queue"))
    assert values(e, "reader queue")["queue_dropped_bytes"] == "5000"


def test_samples_calibrated_counts_exactly_the_samples_in_published_records() -> None:
    """``samples_calibrated`` is "board samples that went into an ImuRecord": a partial decimation block ended
    by a board reset is not published, so its samples go to ``decimation_discarded`` instead (shown in the
    ``calibrated output`` diagnostic). Before the fix they were counted as calibrated (28 + 20 samples with
    decimation 3: samples_calibrated 48 for 15 records of 3)."""
    first = [frame(i) for i in range(28)]
    second = [frame(i, status=GOOD | int(Status.BOOT) if i == 0 else GOOD, t0_us=5_000) for i in range(20)]
    core = DriverCore(make_cal(), CoreConfig(decimation=3))
    _, imu, _ = feed_frames(core, first + second, chunk=4)
    c = core.counters
    assert c.board_resets == 1 and len(imu) == c.imu_published == 28 // 3 + 20 // 3
    assert c.samples_calibrated == 3 * c.imu_published  # every record holds 3 samples
    assert c.decimation_discarded == 28 % 3  # the block pending at the reset
    assert c.samples_calibrated + c.decimation_discarded + 20 % 3 == 48  # the rest still waits for its block
    d = DriverDiagnostics()
    e = d.report(snapshot(1.0, frames=48, core=c.as_dict()))
    shown = values(e, "calibrated output")
    assert shown["samples_calibrated"] == str(c.samples_calibrated) and shown["decimation_discarded"] == "1"


def _feed_blocks(core: DriverCore, blocks: list) -> list:
    """Feed simulator blocks frame by frame, each arriving 0.2 ms after its true time; return the ImuRecords."""
    imu = []
    for b in blocks:
        for piece, t in zip(b.wire_pieces(), b.t_s, strict=True):
            imu += core.feed(piece, T0_NS + round((t + 0.0002) * 1e9)).imu
    return imu


def test_a_decimation_block_never_spans_a_link_outage() -> None:
    """A 30 s outage (the board keeps sampling, no frame arrives: seq and board clock jump) ends the pending
    block like a board reset: its partial samples are discarded (``decimation_discarded``), never averaged
    with the samples after the outage. Before the fix one record averaged 5 samples from before 30 s and 5
    from after 60 s and was stamped at 45 s, inside the outage."""
    from fbg_accel_sim.board_physics import BoardSimulator, SimConfig

    sim = BoardSimulator(SimConfig.default(), seed=4)
    before = sim.step(3005)
    sim.step(3000, deliver=False)  # 30 s: the board samples, the link carries nothing
    after = sim.step(1000)
    core = DriverCore(ThermalCalibration.load(REPO / "config" / "calibration_sim.yaml"), CoreConfig(decimation=10))
    imu = _feed_blocks(core, [before, after])
    stamps = (np.array([r.stamp_ns for r in imu]) - T0_NS) * 1e-9
    assert not np.any((stamps > before.t_s[-1]) & (stamps < after.t_s[0])), stamps[(stamps > 30) & (stamps < 61)]
    c = core.counters
    assert c.decimation_discarded == 3005 % 10 and c.decimation_gaps == 1 and c.board_resets == 0
    assert c.samples_calibrated == 10 * c.imu_published == 10 * (3005 // 10 + 1000 // 10)
    # every record's window lies on one side of the outage: stamps 0.1 s apart there, one jump across it
    assert np.count_nonzero(np.diff(stamps) > 0.2) == 1


def test_a_few_lost_frames_inside_a_block_do_not_end_it() -> None:
    """Tolerance: a block may miss samples as long as its samples lie within 2 N board sample intervals (half
    its window or more received): one lost frame (a CRC error) costs that sample only."""
    kept = [frame(i) for i in range(40) if i != 13]
    core = DriverCore(make_cal(), CoreConfig(decimation=10))
    _, imu, _ = feed_frames(core, kept)
    assert len(imu) == 3 and core.counters.decimation_discarded == 0 == core.counters.decimation_gaps
    assert core.counters.samples_calibrated == 30
    # lowering the decimation while streaming: the longer block in progress is no gap, it is emitted whole
    core = DriverCore(make_cal(), CoreConfig(decimation=20))
    feed_frames(core, [frame(i) for i in range(12)])
    core.reconfigure(decimation=5)
    _, imu, _ = feed_frames(core, [frame(i) for i in range(12, 20)])
    assert len(imu) == 2 and core.counters.samples_calibrated == 13 + 5 and core.counters.decimation_gaps == 0


@pytest.mark.parametrize("step_us", [1, 100])
def test_a_board_clock_that_does_not_advance_does_not_hold_the_stream(step_us: int) -> None:
    """The first frames are held until the clock estimate is primed, "a one-off latency of at most 0.2 s"
    (docs/topics.md). A board whose ``t_us`` crawls (a sample counter sent as microseconds, a timer in the wrong
    unit) shows 0.2 s of board time only after 2000 to 200 000 frames: before, every frame was held until then
    (1000 frames fed over 10 s, none published, memory growing by about 330 bytes a frame, no diagnostic).
    The hold now also ends after ``prime_s`` of arrival time."""
    core = DriverCore(make_cal())
    n = 1000
    released = 0
    for i in range(n):
        f = Frame(seq=i, t_us=5_000_000 + i * step_us, ref=870, x=1100, y=1600, z=1100, temp_cc=2340, status=GOOD)
        released += len(core.feed(encode_frame(f), T0_NS + i * 10_000_000).raw)  # 100 frames/s of arrivals
    assert core.decoder.stats.frames == n
    assert released >= n - 21, released  # held for 0.2 s of arrivals (21 frames), then every frame at once


def test_the_chain_priming_count_is_in_the_diagnostics() -> None:
    """docs/topics.md documents chain_priming (the equaliser's first sample after a start, not published); it was
    counted by the core but shown by no diagnostic entry."""
    d = DriverDiagnostics()
    e = d.report(snapshot(1.0, frames=100, core={"chain_priming": 2}))
    assert values(e, "calibrated output")["chain_priming"] == "2"


def catch_up(frames: list[Frame], late_k: int, late_us: int, dt: int = 10_000, read_us: int = 40) -> list[Frame]:
    """``frames`` (consecutive, ``dt`` us apart) as the firmware takes them when read ``late_k`` is ``late_us`` late:
    the reads already due follow back to back, ``read_us`` apart, ADC_OVERRUN on each read taken at or after the next
    read's time (firmware/core/fbg_scheduler.c fbg_sched_take, firmware/host/fbg_board_host.c --late)."""
    out, read = [], -read_us
    for k, f in enumerate(frames):
        due = f.t_us + (late_us if k == late_k else 0)
        read = max(due, read + read_us)
        late = read >= f.t_us + dt
        out.append(Frame(f.seq, read, f.ref, f.x, f.y, f.z, f.temp_cc, f.status | (int(Status.ADC_OVERRUN) if late else 0)))
    return out


@pytest.mark.parametrize("late_us", [15_000, 35_000])  # 100 Hz: 1 or 3 reads caught up back to back, none skipped
def test_a_late_read_and_its_catch_up_are_not_a_decimation_gap(late_us: int) -> None:
    """A late read (ADC_OVERRUN) and the reads the firmware then takes back to back (40 us apart) lose nothing: no
    decimation gap, no discarded block. Before, the one 40 us step became the board's sample interval, and the next
    block's span (more than 2 N x 40 us) was taken for a gap: decimation_gaps 1, decimation_discarded 3. A real gap (30
    missing sequence numbers) after it is still one."""
    frames = catch_up([frame(i) for i in range(400)], 205, late_us)
    assert [f.t_us - frames[204].t_us for f in frames[205:210]][:2] == [late_us + 10_000, late_us + 10_040]
    core = DriverCore(make_cal(), CoreConfig(decimation=10))
    feed_frames(core, frames, chunk=1)
    c = core.counters
    assert core.decoder.stats.lost_frames == 0
    assert (c.decimation_gaps, c.decimation_discarded, c.imu_published) == (0, 0, 40)
    core = DriverCore(make_cal(), CoreConfig(decimation=10))
    feed_frames(core, frames[:305] + frames[335:], chunk=1)
    c = core.counters
    assert (core.decoder.stats.lost_frames, c.decimation_gaps, c.decimation_discarded) == (30, 1, 5)


@pytest.mark.parametrize("late_us", [15_000, 35_000])
def test_equalised_stamps_keep_the_board_spacing_through_a_catch_up(late_us: int) -> None:
    """With chain_compensation 'equalise' the stamps move back by the delay the equaliser leaves at the board's
    sample interval. It was recomputed from each sample's own step: around a catch-up read (40 us after the late one)
    the published stamps were off the board spacing by -2.2 and +2.7 ms. The filters still step by each sample's
    own interval; the stamp delay is that of the nominal interval."""
    from fbg_accel_driver.chain_compensation import ChainDynamics

    dyn = ChainDynamics(cutoff_hz=(1.0, 1.7, 1.3, 1.3), delay_s=(0.0, 0.0, 0.0))
    frames = catch_up([frame(i) for i in range(400)], 205, late_us)
    core = DriverCore(make_cal(dynamic=dyn), CoreConfig(chain_compensation="equalise", equalise_bandwidth_hz=10.0))
    _, imu, _ = feed_frames(core, frames, chunk=1)
    assert len(imu) == 399  # all but the equaliser's first sample
    steps = [(b.stamp_ns - a.stamp_ns) - (fb.t_us - fa.t_us) * 1000
             for (a, b), (fa, fb) in zip(itertools.pairwise(imu), itertools.pairwise(frames[1:]), strict=True)]
    assert max(abs(s) for s in steps) < 100_000, max(steps, key=abs)  # 0.1 ms: the board clock's spacing


@pytest.mark.parametrize("late_s", [0.015, 0.035])
def test_the_simulator_s_late_read_passes_the_driver_without_a_gap(late_s: float) -> None:
    """End to end through the board simulator (faults.late_reads: the firmware's catch-up after a late read): the
    board spacing is kept and no decimation block is lost, with and without chain compensation 'equalise'."""
    from dataclasses import replace

    from fbg_accel_driver.chain_compensation import ChainDynamics
    from fbg_accel_sim.board_physics import BoardSimulator, SimConfig

    cfg = SimConfig.default().with_overrides({"faults.late_reads.at_s": [2.05, 3.0], "faults.late_reads.late_s": late_s})
    blk = BoardSimulator(cfg, seed=3).run(5.0)
    over = np.flatnonzero(blk.status & int(Status.ADC_OVERRUN))
    steps = np.diff(blk.t_us)
    assert len(over) == 2 * round(late_s * 100 - 0.5) and np.count_nonzero(steps < 100) == len(over)
    assert np.all(np.abs(steps[steps >= 100] - 10_000) <= 10_000 * late_s * 100)  # one long step, then short ones
    cal = ThermalCalibration.load(REPO / "config" / "calibration_sim.yaml")
    core = DriverCore(cal, CoreConfig(decimation=10))
    _feed_blocks(core, [blk])
    c = core.counters
    assert (core.decoder.stats.lost_frames, c.decimation_gaps, c.decimation_discarded, c.imu_published) == (0, 0, 0, 50)
    dyn = ChainDynamics(cutoff_hz=tuple(cfg.get("electronics.tia_cutoff_hz")))
    core = DriverCore(replace(cal, dynamic=dyn), CoreConfig(chain_compensation="equalise", equalise_bandwidth_hz=10.0))
    imu = _feed_blocks(core, [blk])
    assert len(imu) == 499
    spacing = np.diff([r.stamp_ns for r in imu]) - np.diff(blk.t_us[1:]) * 1000
    assert np.max(np.abs(spacing)) < 100_000  # ns: the board clock's spacing (20 ppm crystal: < 0.3 us a step)
