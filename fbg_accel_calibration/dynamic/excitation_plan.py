"""Excitation plan of a dynamic calibration run (issue 9; docs/dynamic_calibration.md).

A linear slide moves sinusoidally along one fixed direction of the sensor frame, segment after segment
(a stepped sine), and a reference transducer on the board's auxiliary ADC channel (protocol version 2,
same clock) measures the same motion (second seed, section 2). The plan is one YAML file that drives
both the simulator (``board_sim --dynamic-plan``: :meth:`ExcitationPlan.sim_overrides`) and the
processing (``fbg-accel-calib dynamic``): where the steady parts of the segments are, and how aux
counts become the reference acceleration (:func:`reference_acceleration`).

Units: s, Hz, m/s^2, m/s; ``direction`` is a unit vector in the sensor frame (REP 103).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal

from fbg_accel_driver.mapping_fields import format_version, number, refuse_unknown
from fbg_accel_driver.yaml_input import YamlFileError, read_yaml_file

FORMAT_NAME = "fbg_accel_excitation_plan"
FORMAT_VERSION = 1
TOP_KEYS = ("format", "format_version", "name", "description", "direction", "start_s", "gap_s", "ramp_cycles",
            "settle_s", "reference", "segments")
SENSITIVITY_KEYS = {"ldv": "sensitivity_counts_per_mps", "accelerometer": "sensitivity_counts_per_mps2"}
REFERENCE_TYPES = tuple(SENSITIVITY_KEYS)
REFERENCE_KEYS = ("type", "sensitivity_counts_per_mps", "sensitivity_counts_per_mps2", "offset_counts",
                  "ac_coupling_hz", "relative_uncertainty", "phase_uncertainty_deg")
SEGMENT_KEYS = ("freq_hz", "amplitude_mps2", "duration_s")
MAX_SEGMENTS = 200


class ExcitationPlanError(ValueError):
    """An excitation plan file is missing, malformed or not understood."""


@dataclass(frozen=True)
class Segment:
    """One sinusoidal segment: frequency (Hz), steady acceleration amplitude along the direction
    (m/s^2), duration including its fade-in and fade-out ramps (s)."""

    freq_hz: float
    amplitude_mps2: float
    duration_s: float


@dataclass(frozen=True)
class ReferenceTransducer:
    """What the aux channel carries. ``ldv``: velocity along the direction, ``counts = offset +
    sensitivity_counts_per_mps * v``, optionally AC-coupled (first-order high-pass at ``ac_coupling_hz``,
    seed Fig. 5); ``accelerometer``: ``counts = offset + sensitivity_counts_per_mps2 * a``. The reference's
    own standard uncertainties (relative sensitivity, phase in degrees) enter the budget (seed Tables 2-3)."""

    type: str
    sensitivity: float  # counts per m/s (ldv) or per m/s^2 (accelerometer)
    offset_counts: float = 2048.0
    ac_coupling_hz: float = 0.0
    relative_uncertainty: float = 0.01
    phase_uncertainty_deg: float = 0.5


@dataclass(frozen=True)
class ExcitationPlan:
    name: str
    direction: tuple[float, float, float]
    segments: tuple[Segment, ...]
    reference: ReferenceTransducer
    start_s: float = 5.0
    gap_s: float = 1.0
    ramp_cycles: float = 2.0
    settle_s: float = 1.0
    description: str = ""

    # ------------------------------------------------------------------ timing
    def segment_starts_s(self) -> list[float]:
        """Start (s after the slide's start) of each segment."""
        out, t = [], 0.0
        for seg in self.segments:
            out.append(t)
            t += seg.duration_s + self.gap_s
        return out

    @property
    def duration_s(self) -> float:
        """Seconds from the slide's start to the end of the last segment."""
        return sum(s.duration_s for s in self.segments) + self.gap_s * (len(self.segments) - 1)

    def steady_windows(self, slide_start_s: float) -> list[tuple[float, float, float]]:
        """``(f_hz, t_start_s, t_end_s)`` of each segment's steady part on the recording's time base:
        the fade ramps (``ramp_cycles`` periods, at most half the segment each) and ``settle_s``
        after the fade-in (the TIA stages' transient: five time constants of the slowest, 1 Hz, stage is
        0.8 s) are left out."""
        out = []
        for seg, t0 in zip(self.segments, self.segment_starts_s(), strict=True):
            ramp = min(self.ramp_cycles / seg.freq_hz, 0.5 * seg.duration_s)  # as the simulator (scenario.SlidePlan)
            a = slide_start_s + t0 + ramp + self.settle_s
            b = slide_start_s + t0 + seg.duration_s - ramp
            if b - a >= 1.0 / seg.freq_hz:
                out.append((seg.freq_hz, a, b))
        return out

    def envelope(self, t_rel_s: np.ndarray) -> np.ndarray:
        """Planned acceleration amplitude (m/s^2) at times after the slide's start (0 between segments)."""
        env = np.zeros_like(np.asarray(t_rel_s, dtype=float))
        for seg, t0 in zip(self.segments, self.segment_starts_s(), strict=True):
            env[(t_rel_s >= t0) & (t_rel_s < t0 + seg.duration_s)] = seg.amplitude_mps2
        return env

    # ------------------------------------------------------------------ simulator
    def sim_overrides(self) -> dict[str, Any]:
        """Dotted simulator-config keys that make ``board_sim`` run this plan (protocol version 2)."""
        ref = self.reference
        transducer = f"reference_transducer.{ref.type}."
        out: dict[str, Any] = {
            "board.protocol_version": 2,
            "scenario.slide.enabled": True,
            "scenario.slide.direction": list(self.direction),
            "scenario.slide.start_s": self.start_s,
            "scenario.slide.gap_s": self.gap_s,
            "scenario.slide.ramp_cycles": self.ramp_cycles,
            "scenario.slide.segments": [asdict(s) for s in self.segments],
            "reference_transducer.type": ref.type,
            transducer + SENSITIVITY_KEYS[ref.type]: ref.sensitivity,
            transducer + "offset_counts": ref.offset_counts,
        }
        if ref.type == "ldv":
            out[transducer + "ac_coupling_hz"] = ref.ac_coupling_hz
        return out

    def with_tone(self, freq_hz: float, amplitude_mps2: float, duration_s: float) -> ExcitationPlan:
        """This plan (slide, reference, timing) with one tone only, validated as a plan file is: a check at
        a frequency the fit did not use (seed Fig. 12)."""
        d = self.to_dict()
        d["segments"] = [{"freq_hz": freq_hz, "amplitude_mps2": amplitude_mps2, "duration_s": duration_s}]
        return ExcitationPlan.from_dict(d, source=f"{self.name} at {freq_hz:g} Hz")

    # ------------------------------------------------------------------ file I/O
    def to_dict(self) -> dict[str, Any]:
        ref = self.reference
        return {"format": FORMAT_NAME, "format_version": FORMAT_VERSION, "name": self.name,
                "description": self.description, "direction": list(self.direction), "start_s": self.start_s,
                "gap_s": self.gap_s, "ramp_cycles": self.ramp_cycles, "settle_s": self.settle_s,
                "reference": {"type": ref.type, SENSITIVITY_KEYS[ref.type]: ref.sensitivity, "offset_counts": ref.offset_counts,
                              "ac_coupling_hz": ref.ac_coupling_hz, "relative_uncertainty": ref.relative_uncertainty,
                              "phase_uncertainty_deg": ref.phase_uncertainty_deg},
                "segments": [asdict(s) for s in self.segments]}

    @classmethod
    def load(cls, path: str | Path) -> ExcitationPlan:
        p = Path(path)
        try:
            data = read_yaml_file(p, "excitation plan")
        except YamlFileError as exc:
            raise ExcitationPlanError(str(exc)) from None
        return cls.from_dict(data, str(p))

    @classmethod
    def from_dict(cls, d: Any, source: str = "<dict>") -> ExcitationPlan:
        def fail(msg: str) -> ExcitationPlanError:
            return ExcitationPlanError(f"{source}: {msg}")

        if not isinstance(d, dict):
            raise fail("top level is not a mapping")
        if d.get("format") != FORMAT_NAME:
            raise fail(f"format is {d.get('format')!r}, expected '{FORMAT_NAME}'")
        format_version(d.get("format_version"), "format_version", fail, reads=FORMAT_VERSION, reader="this tool")
        refuse_unknown(d, TOP_KEYS, "", fail)
        direction = d.get("direction")
        if not (isinstance(direction, list) and len(direction) == 3):
            raise fail("direction must be a list of 3 numbers (unit vector, sensor frame)")
        v = np.array([number(x, "direction", fail) for x in direction])
        norm = float(np.linalg.norm(v))
        if not norm > 0:
            raise fail("direction must not be zero")
        v = v / norm
        ref_d = d.get("reference")
        if not isinstance(ref_d, dict):
            raise fail("reference must be a mapping {type, sensitivity..., offset_counts, ...}")
        refuse_unknown(ref_d, REFERENCE_KEYS, "reference.", fail)
        rtype = ref_d.get("type")
        if rtype not in REFERENCE_TYPES:
            raise fail(f"reference.type must be one of {REFERENCE_TYPES}, got {rtype!r}")
        sens_key = SENSITIVITY_KEYS[rtype]
        if sens_key not in ref_d:
            raise fail(f"reference.{sens_key} is required for a reference of type {rtype}")
        sens = number(ref_d[sens_key], f"reference.{sens_key}", fail)
        if sens == 0:
            raise fail(f"reference.{sens_key} must not be 0")
        ref = ReferenceTransducer(
            type=rtype, sensitivity=sens,
            offset_counts=number(ref_d.get("offset_counts", 2048.0), "reference.offset_counts", fail),
            ac_coupling_hz=number(ref_d.get("ac_coupling_hz") or 0.0, "reference.ac_coupling_hz", fail, minimum=0.0),
            relative_uncertainty=number(ref_d.get("relative_uncertainty", 0.01), "reference.relative_uncertainty", fail,
                                        minimum=0.0),
            phase_uncertainty_deg=number(ref_d.get("phase_uncertainty_deg", 0.5), "reference.phase_uncertainty_deg",
                                         fail, minimum=0.0))
        segs_d = d.get("segments")
        if not isinstance(segs_d, list) or not segs_d:
            raise fail("segments must be a non-empty list of {freq_hz, amplitude_mps2, duration_s}")
        if len(segs_d) > MAX_SEGMENTS:
            raise fail(f"{len(segs_d)} segments, at most {MAX_SEGMENTS}")
        segs = []
        for i, s in enumerate(segs_d):
            where = f"segments[{i}]"
            if not isinstance(s, dict):
                raise fail(f"{where} must be a mapping {{freq_hz, amplitude_mps2, duration_s}}")
            refuse_unknown(s, SEGMENT_KEYS, f"{where}.", fail)
            for k in SEGMENT_KEYS:
                if k not in s:
                    raise fail(f"{where}.{k} is required")
            f = number(s["freq_hz"], f"{where}.freq_hz", fail, minimum=1e-3)
            seg = Segment(f, number(s["amplitude_mps2"], f"{where}.amplitude_mps2", fail, minimum=1e-9),
                          number(s["duration_s"], f"{where}.duration_s", fail, minimum=1e-3))
            if seg.duration_s * seg.freq_hz < 3:
                raise fail(f"{where}: {seg.duration_s:g} s at {f:g} Hz is under 3 periods")
            segs.append(seg)
        name = d.get("name", "")
        desc = d.get("description", "")
        if not isinstance(name, str) or not isinstance(desc, str):
            raise fail("name and description must be text")
        return cls(name=name, direction=(float(v[0]), float(v[1]), float(v[2])), segments=tuple(segs), reference=ref,
                   start_s=number(d.get("start_s", 5.0), "start_s", fail, minimum=0.0),
                   gap_s=number(d.get("gap_s", 1.0), "gap_s", fail, minimum=0.0),
                   ramp_cycles=number(d.get("ramp_cycles", 2.0), "ramp_cycles", fail, minimum=0.0),
                   settle_s=number(d.get("settle_s", 1.0), "settle_s", fail, minimum=0.0), description=desc)


def reference_acceleration(t_s: np.ndarray, aux_counts: np.ndarray, plan: ExcitationPlan,
                           windows: list[tuple[float, float, float]], undo_ac_coupling: bool = True) -> np.ndarray:
    """Reference acceleration (N,) along the slide direction, m/s^2, from the aux counts.

    An accelerometer is scaled. An LDV's velocity is differentiated inside each steady window by the
    central difference corrected for its tone, ``(v[k+1] - v[k-1]) / (2 dt) * (w dt / sin(w dt))``:
    exact in amplitude and phase for a sinusoid at the window's frequency ``w`` (a plain central
    difference reads 24 % low at 20 Hz and 100 Hz sampling). NaN outside the windows for an LDV.

    An AC-coupled LDV (``ac_coupling_hz`` = f_h > 0, seed Fig. 5) measures ``v_m = s/(s + w_h) v``; with
    ``undo_ac_coupling`` its declared high-pass is undone exactly: ``a = s v = (s + w_h) v_m =
    dv_m/dt + w_h v_m`` (the seed corrects its reference the same way, by the data-sheet filter).
    """
    t = np.asarray(t_s, dtype=float)
    ref = plan.reference
    x = (np.asarray(aux_counts, dtype=float) - ref.offset_counts) / ref.sensitivity
    if ref.type == "accelerometer":
        return x
    out = np.full_like(x, np.nan)
    for f, a, b in windows:
        idx = np.flatnonzero((t >= a) & (t < b))
        if idx.size < 3:
            continue
        lo, hi = max(idx[0], 1), min(idx[-1], len(t) - 2)
        k = np.arange(lo, hi + 1)
        dt = (t[k + 1] - t[k - 1]) / 2.0
        wdt = 2.0 * math.pi * f * dt
        if np.any(wdt >= math.pi):
            raise ValueError(f"{f:g} Hz is above the Nyquist frequency of the recording")
        out[k] = (x[k + 1] - x[k - 1]) / (2.0 * dt) * (wdt / np.sin(wdt))
        if undo_ac_coupling and ref.ac_coupling_hz > 0:
            out[k] += 2.0 * math.pi * ref.ac_coupling_hz * (x[k] - np.mean(x[k]))
    return out


START_MOTION_FRACTION = 0.02  # an aux envelope above this share of its largest value at the start: the slide moves


def find_slide_start(t_s: np.ndarray, aux_counts: np.ndarray, plan: ExcitationPlan) -> float:
    """Time (s, recording time base) the slide's first segment starts: the lag that best aligns the
    aux channel's 0.5 s moving-RMS envelope with the plan's amplitude envelope (both normalised), so a
    run can be processed whatever the recording started before the slide, a recording cut short
    (a killed run) still aligns with the segments it holds, and so does one started late, inside the plan
    (the start then lies before the recording's first sample; the segments it missed are left out). Accurate
    to a fraction of the 0.5 s envelope window (0.03 s in the tests), ample since the steady windows leave
    out the ramps and ``settle_s``."""
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(aux_counts, dtype=float)
    dt = float(np.median(np.diff(t)))
    n_win = max(3, round(0.5 / dt))
    dev = x - np.median(x)
    kernel = np.ones(n_win) / n_win
    env = np.sqrt(np.convolve(dev * dev, kernel, mode="same"))
    env = env / (np.max(env) or 1.0)
    n_plan = round(plan.duration_s / dt)
    if len(t) * dt < plan.segments[0].duration_s:  # not even the first segment: nothing to align
        raise ValueError(f"the recording ({len(t) * dt:.1f} s) is too short to align with the plan "
                         f"(its first segment alone lasts {plan.segments[0].duration_s:g} s)")
    plan_env = (plan.envelope(np.arange(n_plan) * dt) > 0).astype(float)
    # the plan may run past the recording's end (a killed run) and, when the recording starts while the slide
    # moves, start before the recording's first sample (a late start: only such lags are searched then, so a
    # short recording of one segment is not matched to a later part of the plan)
    rest = float(np.percentile(env, 5))
    late = float(np.mean(env[:n_win])) > max(START_MOTION_FRACTION, 3.0 * rest)
    padded = np.concatenate([np.zeros(n_plan - 1), env - env.mean(), np.zeros(n_plan)])
    # by FFT, O(N log N): a direct correlation takes (N + n_plan) x n_plan products (5e9 for the shipped 101 s plan at
    # 500 Hz) as one BLAS dot per lag, whose threads then wait for a loaded CPU on every call: the `dynamic` command of
    # test_a_ros2_bag_of_imu_raw_with_aux_counts_is_read, 6 s on its own, ran past its 120 s limit 1 time in 7 beside a
    # busy loop
    score = signal.correlate(padded, plan_env - plan_env.mean(), mode="valid", method="fft")[: len(env) + n_plan - 1]
    lags = np.arange(len(score)) - (n_plan - 1)  # samples from the recording's first sample to the slide's start
    score[(lags > 0) if late else (lags < 0)] = -np.inf
    k = int(lags[np.argmax(score)])
    # inside the recording the sample's own stamp (a lost frame before it does not shift it); before it, counted back
    return float(t[k]) if k >= 0 else float(t[0] + k * dt)
