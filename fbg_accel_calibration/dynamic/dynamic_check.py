"""Checks of a dynamic calibration applied by the driver (issue 9; seed Fig. 12; docs/dynamic_calibration.md).

* :func:`tone_check`: a slide run at a frequency the fit did not use goes through the driver's own
  pipeline (``DriverCore``: decoding, clock mapping, eq. 24/28, chain compensation); the RMS difference
  between the published acceleration, at its stamps, and the reference over whole periods is compared
  with and without the compensation (seed Fig. 12: about 25 % less with gain and delay corrected).
* :func:`step_check`: a step of the acceleration through each channel's TIA stage (the sampled
  first-order model) into ``DriverCore``: when does the published output cross half the step, on the
  reference's time line?

Pure numpy, no ROS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fbg_accel_driver.driver_core import CoreConfig, DriverCore
from fbg_accel_driver.frame_codec import Frame, Status, encode_frame
from fbg_accel_driver.thermal_model import ThermalCalibration

T0_NS = 1_700_000_000_000_000_000  # ROS time of board time 0 in the replays
TRANSPORT_NS = 2_000_000  # a constant 2 ms between sampling and arrival


def replay(data: bytes, cal: ThermalCalibration, mode: str, bandwidth_hz: float = 10.0,
           chunk_bytes: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """(board time (s) of every published stamp, acceleration (N, 3) m/s^2) of ``DriverCore`` fed ``data``.

    Bytes arrive ``TRANSPORT_NS`` after the sampling of the last complete frame in each chunk; a
    published stamp is put back on the board's time line with the clock offset of the raw records.
    """
    core = DriverCore(cal, CoreConfig(chain_compensation=mode, equalise_bandwidth_hz=bandwidth_hz))
    stamps: list[int] = []
    acc: list[tuple[float, float, float]] = []
    offsets: list[tuple[int, int]] = []  # (raw stamp ns, board time ns)

    def collect(out: Any) -> None:
        offsets.extend((r.stamp_ns, r.frame.t_us * 1000) for r in out.raw)
        stamps.extend(s.stamp_ns for s in out.imu)
        acc.extend(s.accel_mps2 for s in out.imu)

    for k in range(0, len(data), chunk_bytes):  # arriving TRANSPORT_NS after the last frame fed was sampled
        collect(core.feed(data[k:k + chunk_bytes], T0_NS + (offsets[-1][1] if offsets else 0) + TRANSPORT_NS))
    collect(core.flush())
    if not stamps:
        raise ValueError("the driver published no acceleration")
    raw_stamp = np.array([o[0] for o in offsets], dtype=np.int64)
    board_ns = np.array([o[1] for o in offsets], dtype=np.int64)
    st = np.array(stamps, dtype=np.int64)
    i = np.clip(np.searchsorted(raw_stamp, st), 0, len(raw_stamp) - 1)
    return (st - (raw_stamp[i] - board_ns[i])) * 1e-9, np.array(acc)


@dataclass
class ToneCheck:
    f_hz: float
    rms_mps2: dict[str, list[float]]  # mode -> per axis RMS difference to the reference (m/s^2)
    reduction_pct: dict[str, list[float]]  # mode -> per axis reduction against "none" (%)
    periods: int
    # mode -> per axis RMS of the difference's part at f_hz (m/s^2): the chain's error on the tone; the rest is noise
    tone_rms_mps2: dict[str, list[float]] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"f_hz": self.f_hz, "periods": self.periods, "rms_mps2": self.rms_mps2,
                "reduction_pct": self.reduction_pct, "tone_rms_mps2": self.tone_rms_mps2}


def tone_check(data: bytes, truth_t_s: np.ndarray, truth_slide_mps2: np.ndarray, direction: np.ndarray,
               f_hz: float, window: tuple[float, float], cal: ThermalCalibration,
               modes: tuple[str, ...] = ("none", "delay", "equalise"), bandwidth_hz: float = 10.0) -> ToneCheck:
    """RMS difference (per axis) between the published acceleration and the reference ``slide *
    direction`` at the published stamps, over the whole periods of ``window`` (board time, s), the
    mean difference (gravity, bias) removed: what is left is the chain's dynamic error, and the noise (the
    equaliser's gain ``bandwidth / fc`` amplifies it); ``tone_rms_mps2`` keeps the part at ``f_hz`` alone (a
    least-squares sine at f over the same whole periods), the chain's error without the noise."""
    periods = int((window[1] - window[0]) * f_hz)
    t_end = window[0] + periods / f_hz
    rms: dict[str, list[float]] = {}
    tone: dict[str, list[float]] = {}
    for mode in modes:
        t, a = replay(data, cal, mode, bandwidth_hz)
        m = (t >= window[0]) & (t < t_end)
        ref = np.interp(t[m], truth_t_s, truth_slide_mps2)[:, None] * np.asarray(direction)[None, :]
        err = a[m] - ref
        err -= err.mean(axis=0)
        rms[mode] = [float(v) for v in np.sqrt(np.mean(err**2, axis=0))]
        w = 2.0 * math.pi * f_hz * t[m]
        basis = np.column_stack([np.cos(w), np.sin(w)])
        tone[mode] = [float(v) for v in np.sqrt(np.mean((basis @ np.linalg.lstsq(basis, err, rcond=None)[0]) ** 2, axis=0))]
    base = rms.get("none")
    red = {mode: [100.0 * (1.0 - v / b) for v, b in zip(vals, base, strict=True)] for mode, vals in rms.items()
           if base is not None and mode != "none"}
    return ToneCheck(f_hz, rms, red, periods, tone)


def step_check(cal: ThermalCalibration, mode: str, rate_hz: float = 100.0, bandwidth_hz: float = 10.0,
               step_counts: tuple[float, float, float] = (300.0, -200.0, 100.0), t_step_s: float = 2.0037
               ) -> dict[str, Any]:
    """A step of the acceleration at board time ``t_step_s`` (between two samples): the axis channels
    step by ``step_counts`` at ``t_step_s`` plus their pure delay, and each passes its continuous
    first-order TIA stage (``cal.dynamic`` cut-offs), sampled exactly: ``1 - exp(-(t - t0)/tau)``.
    Returns, per axis, when the published output crosses half the step minus ``t_step_s`` (s; negative
    = early, on the reference's time line), and the sample period."""
    dyn = cal.dynamic
    if dyn is None:
        raise ValueError("the calibration has no dynamic section")
    dt = 1.0 / rate_hz
    n = int(4.0 * rate_hz)
    t = np.arange(n) * dt
    counts = np.tile(np.array([870.0, 1100.0, 1600.0, 1100.0]), (n, 1))
    for j in range(3):
        t0 = t_step_s + dyn.delay_s[j]
        tau = 1.0 / (2.0 * math.pi * dyn.cutoff_hz[j + 1])
        counts[:, j + 1] += step_counts[j] * np.where(t >= t0, -np.expm1(-(t - t0) / tau), 0.0)
    good = int(Status.TEMP_VALID | Status.TEMP_PRESENT)
    frames = [Frame(seq=i % 65536, t_us=round(t[i] * 1e6), ref=round(c[0]), x=round(c[1]), y=round(c[2]), z=round(c[3]),
                    temp_cc=2340, status=good) for i, c in enumerate(counts)]
    tb, a = replay(b"".join(encode_frame(f) for f in frames), cal, mode, bandwidth_hz, chunk_bytes=27 * 5)
    out: dict[str, Any] = {"mode": mode, "rate_hz": rate_hz, "bandwidth_hz": bandwidth_hz, "sample_period_s": dt}
    for j, ax in enumerate("xyz"):
        before = a[(tb > 1.0) & (tb < t_step_s - 0.1), j].mean()
        after = a[tb > t_step_s + 1.5, j].mean()
        half = 0.5 * (before + after)
        sign = np.sign(after - before)
        k = np.flatnonzero((tb > t_step_s - 0.5) & (sign * (a[:, j] - half) >= 0))
        if k.size == 0 or k[0] == 0:
            out[f"{ax}_half_step_s"] = math.nan
            continue
        i = int(k[0])
        frac = (half - a[i - 1, j]) / (a[i, j] - a[i - 1, j])  # linear interpolation between the two samples
        out[f"{ax}_half_step_s"] = float(tb[i - 1] + frac * (tb[i] - tb[i - 1]) - t_step_s)
    return out
