"""Scenario of a simulated run: table angles over time, chamber temperature profile, vibration, slide.

Pure numpy; every function is a deterministic function of time, so the simulator can evaluate
it at any sample (and at ``t - delay`` for the channel-delay effect) without state.

Table motion: the table holds each pose for ``dwell_s`` and moves to the next one in ``move_s``
with a raised-cosine profile on both angles, so a sample taken while moving carries an
intermediate angle (as in the measured run, ../shared/data/measured/README.md). Angles follow
the table convention of ``fbg_accel_calibration.io.table_geometry``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

SIX_POSITION = [  # paper 3.6.2 and Fig. 11: z down, z up, x down, x up, y down, y up (config/pose_plan_six_position.yaml)
    (0.0, 180.0), (0.0, 0.0), (270.0, 90.0), (90.0, 90.0), (180.0, 90.0), (0.0, 90.0),
]


def grid_poses(theta_step_deg: float, psi_step_deg: float) -> list[tuple[float, float]]:
    """Multi-position grid of the measured run: theta 0..360 (inclusive), psi 0..(360 - step) at each theta."""
    out = []
    for theta in np.arange(0.0, 360.0 + 1e-9, theta_step_deg):
        for psi in np.arange(0.0, 360.0 - 1e-9, psi_step_deg):
            out.append((float(psi), float(theta)))
    return out


@dataclass
class PoseTrajectory:
    """Piecewise table trajectory. ``psi``/``theta`` (P,) pose angles (deg), ``dwell`` (P,) s."""

    psi: np.ndarray
    theta: np.ndarray
    dwell: np.ndarray
    move_s: float
    repeat: int  # 0 = forever
    names: list[str]

    def __post_init__(self) -> None:
        n = len(self.psi)
        # One cycle: dwell_0, move_0->1, dwell_1, ..., dwell_{P-1}, move_{P-1}->0 (the last move only between repeats).
        seg = np.empty(2 * n)
        seg[0::2] = self.dwell
        seg[1::2] = self.move_s if n > 1 else 0.0
        self._seg_start = np.concatenate([[0.0], np.cumsum(seg)])
        self.cycle_s = float(self._seg_start[-1])
        self.static = n == 1

    @property
    def duration_s(self) -> float:
        """End of the last dwell (inf if looping or static)."""
        if self.static or self.repeat == 0:
            return math.inf
        return self.repeat * self.cycle_s - (self.move_s if len(self.psi) > 1 else 0.0)

    def evaluate(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Angles at times ``t_s`` (N,): psi_deg, theta_deg, pose_id (-1 moving), in_motion, visit (dwell counter)."""
        t = np.asarray(t_s, dtype=float)
        n = len(self.psi)
        if self.static:
            z = np.zeros(t.shape)
            return z + self.psi[0], z + self.theta[0], np.zeros(t.shape, int), np.zeros(t.shape, bool), np.zeros(t.shape, int)
        cycle, tin, seg = self._locate(t, hold_at_end=True)
        pose = seg // 2
        moving = (seg % 2) == 1
        nxt = (pose + 1) % n
        frac = np.where(moving, (tin - self._seg_start[seg]) / max(self.move_s, 1e-12), 0.0)
        s = 0.5 - 0.5 * np.cos(np.pi * np.clip(frac, 0.0, 1.0))
        psi = self.psi[pose] + s * (self.psi[nxt] - self.psi[pose])
        theta = self.theta[pose] + s * (self.theta[nxt] - self.theta[pose])
        pose_id = np.where(moving, -1, pose)
        visit = (cycle.astype(int) * n + pose).astype(int)
        return psi, theta, pose_id, moving, visit

    def arrival_time(self, t_s: np.ndarray) -> np.ndarray:
        """Time (s) since the table arrived at the current pose (0 while moving; t for a static plan)."""
        t = np.asarray(t_s, dtype=float)
        if self.static:
            return t.copy()
        _, tin, seg = self._locate(t, hold_at_end=False)
        return np.where(seg % 2 == 0, tin - self._seg_start[seg], 0.0)

    def _locate(self, t: np.ndarray, hold_at_end: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(cycle, time in the cycle (s), segment: 2 i = dwell at pose i, 2 i + 1 = move after it) at ``t`` (s).
        ``hold_at_end``: a finite plan's times past its end count as its end."""
        tc = np.maximum(t, 0.0)
        if hold_at_end and self.repeat > 0:
            tc = np.minimum(tc, self.duration_s)
        cycle = np.floor(tc / self.cycle_s)
        if self.repeat > 0:
            cycle = np.minimum(cycle, self.repeat - 1)
        tin = tc - cycle * self.cycle_s
        return cycle, tin, np.clip(np.searchsorted(self._seg_start, tin, side="right") - 1, 0, 2 * len(self.psi) - 1)


def build_trajectory(poses_cfg: dict[str, Any]) -> PoseTrajectory:
    """Pose trajectory from ``scenario.poses`` of the simulator config."""
    mode = poses_cfg.get("mode", "static")
    dwell = float(poses_cfg.get("dwell_s", 10.0))
    move = float(poses_cfg.get("move_s", 2.0))
    repeat = int(poses_cfg.get("repeat", 1))
    names: list[str] = []
    dwells: list[float] | None = None
    if mode == "static":
        st = poses_cfg.get("static") or {}
        pts = [(float(st.get("psi_deg", 0.0)), float(st.get("theta_deg", 0.0)))]
    elif mode == "list":
        pts = [(float(p[0]), float(p[1])) for p in poses_cfg.get("list") or []]
    elif mode == "six_position":
        pts = list(SIX_POSITION)
        names = ["z_down", "z_up", "x_down", "x_up", "y_down", "y_up"]
    elif mode == "grid":
        g = poses_cfg.get("grid") or {}
        pts = grid_poses(float(g.get("theta_step_deg", 30.0)), float(g.get("psi_step_deg", 30.0)))
    elif mode == "plan_file":
        from fbg_accel_calibration.recorder.pose_plan import PosePlan  # pure module; local import keeps sim importable alone

        path = poses_cfg.get("plan_file")
        if not path:
            raise ValueError("scenario.poses.mode is plan_file but scenario.poses.plan_file is not set")
        p = Path(path)
        if not p.is_file():
            from .sim_config import config_dir

            p = config_dir() / Path(path).name
        plan = PosePlan.load(p)
        pts, dwells = [], []
        for pose in plan.poses:
            if pose.psi_deg is None or pose.theta_deg is None:
                raise ValueError(f"{path}: pose '{pose.name}' has no table angles; the simulated table needs psi/theta")
            pts.append((float(pose.psi_deg), float(pose.theta_deg)))
            dwells.append(float(pose.dwell_s))
            names.append(pose.name)
        move = float(getattr(plan, "move_s", move))
    else:
        raise ValueError(f"scenario.poses.mode '{mode}' unknown (static, list, six_position, grid, plan_file)")
    if not pts:
        raise ValueError(f"scenario.poses: mode '{mode}' gives no poses")
    arr = np.asarray(pts, dtype=float)
    dw = np.asarray(dwells if dwells is not None else [dwell] * len(pts), dtype=float)
    if np.any(dw <= 0) or move < 0:
        raise ValueError("scenario.poses: dwell_s must be > 0 and move_s >= 0")
    return PoseTrajectory(arr[:, 0], arr[:, 1], dw, move, repeat, names or [f"pose_{i}" for i in range(len(pts))])


class TemperatureProfile:
    """Chamber temperature (degC) as a piecewise-linear function of time (s)."""

    def __init__(self, initial_c: float, segments: list[dict[str, Any]]) -> None:
        times, temps = [0.0], [float(initial_c)]
        for i, seg in enumerate(segments or []):
            if "hold_s" in seg:
                times.append(times[-1] + float(seg["hold_s"]))
                temps.append(temps[-1])
            elif "ramp_to_c" in seg:
                dur = float(seg.get("duration_s", 0.0))
                if dur <= 0:
                    raise ValueError(f"scenario.temperature.profile[{i}]: ramp needs duration_s > 0")
                times.append(times[-1] + dur)
                temps.append(float(seg["ramp_to_c"]))
            else:
                raise ValueError(f"scenario.temperature.profile[{i}]: expected hold_s or ramp_to_c+duration_s, got {seg}")
        self.times = np.asarray(times)
        self.temps = np.asarray(temps)

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        return np.interp(np.asarray(t_s, float), self.times, self.temps)

    @property
    def end_s(self) -> float:
        return float(self.times[-1])


def vibration(t_s: np.ndarray, sines: list[dict[str, Any]], response=None) -> np.ndarray:
    """Sum of sinusoidal vibrations (N, 3) in m/s^2, sensor frame.

    ``response(freq_hz) -> complex``: a linear frequency response applied to each sine (None: the true motion).
    """
    t = np.asarray(t_s, float)
    out = np.zeros((t.shape[0], 3))
    for s in sines or []:
        amp = np.asarray(s.get("amplitude_mps2", [0.0, 0.0, 0.0]), float).reshape(3)
        ph = math.radians(float(s.get("phase_deg", 0.0)))
        if response is not None:
            h = complex(response(float(s["freq_hz"])))
            amp, ph = amp * abs(h), ph + math.atan2(h.imag, h.real)
        out += np.sin(2.0 * np.pi * float(s["freq_hz"]) * t + ph)[:, None] * amp[None, :]
    return out


# ----------------------------------------------------------------------------- dynamic excitation (linear slide)
@dataclass(frozen=True)
class SlideSegment:
    """One sinusoidal segment of a slide plan: ``freq_hz`` (Hz), ``amplitude_mps2`` (m/s^2, steady-state
    acceleration amplitude along the slide direction), ``duration_s`` (s, ramps included)."""

    freq_hz: float
    amplitude_mps2: float
    duration_s: float


class SlidePlan:
    """Sinusoidal motion of a linear slide along a fixed unit ``direction`` of the sensor frame.

    Second seed (amplitude_phase_calibration_paper.txt) section 2: a horizontal linear slide moved
    according to a sinusoidal law, the accelerometer tilted so that one direction excites its three
    axes at once (eqs. 1-3: a_x = a cos45 cos45, a_y = -a cos45 cos45, a_z = a sin45). Segments follow
    one another from ``start_s`` with ``gap_s`` of rest between them; each starts at phase 0 and is
    faded in and out over ``ramp_cycles`` periods (raised cosine, at most half the segment) so that the
    slide's displacement and velocity stay continuous, as a real long-stroke shaker's must. In a
    segment, displacement x = -e(t) A/w^2 sin(w tau), tau = t - segment start, so that in the
    steady part the acceleration along ``direction`` is A sin(w tau) (m/s^2); velocity and
    acceleration are the exact derivatives, envelope included.
    """

    def __init__(self, segments: list[SlideSegment], direction: np.ndarray, start_s: float = 0.0,
                 gap_s: float = 0.0, ramp_cycles: float = 2.0) -> None:
        d = np.asarray(direction, float).reshape(3)
        norm = float(np.linalg.norm(d))
        if not norm > 0:
            raise ValueError("scenario.slide.direction must be a non-zero 3-vector (sensor frame)")
        self.direction = d / norm
        for i, s in enumerate(segments):
            if not (s.freq_hz > 0 and s.duration_s > 0 and math.isfinite(s.amplitude_mps2)):
                raise ValueError(f"scenario.slide.segments[{i}]: freq_hz and duration_s must be > 0, amplitude finite")
        if start_s < 0 or gap_s < 0 or ramp_cycles < 0:
            raise ValueError("scenario.slide: start_s, gap_s and ramp_cycles must be >= 0")
        self.segments = list(segments)
        self.ramp_cycles = float(ramp_cycles)
        starts, t0 = [], float(start_s)
        for s in self.segments:
            starts.append(t0)
            t0 += s.duration_s + gap_s
        self.starts = np.asarray(starts, float)
        self.end_s = float(self.starts[-1] + self.segments[-1].duration_s) if self.segments else float(start_s)

    def segment_index(self, t_s: np.ndarray) -> np.ndarray:
        """Index of the segment active at each time (N,), -1 at rest."""
        t = np.asarray(t_s, float)
        out = np.full(t.shape, -1, dtype=np.int64)
        for i, (t0, s) in enumerate(zip(self.starts, self.segments, strict=True)):
            out[(t >= t0) & (t < t0 + s.duration_s)] = i
        return out

    def kinematics(self, t_s: np.ndarray, response=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Displacement (m), velocity (m/s), acceleration (m/s^2) along ``direction`` at times ``t_s`` (N,).

        ``response(freq_hz) -> complex`` applies a linear frequency response to each segment's sinusoid
        (gain and phase at the segment frequency; quasi-steady for the slow envelope), e.g. the
        mechanical resonance of the sensor; None: the true motion.
        """
        t = np.asarray(t_s, float)
        x, v, a = np.zeros(t.shape), np.zeros(t.shape), np.zeros(t.shape)
        for t0, s in zip(self.starts, self.segments, strict=True):
            m = (t >= t0) & (t < t0 + s.duration_s)
            if not m.any():
                continue
            w = 2.0 * math.pi * s.freq_hz
            h = complex(response(s.freq_hz)) if response is not None else 1.0 + 0.0j
            gain, ph = abs(h), math.atan2(h.imag, h.real)
            tau = t[m] - t0
            ramp = min(self.ramp_cycles / s.freq_hz, 0.5 * s.duration_s)
            e, de, dde = np.ones(tau.shape), np.zeros(tau.shape), np.zeros(tau.shape)
            if ramp > 0:
                k = math.pi / ramp
                # fade in over the first ramp s (time since the start), out over the last (time to the end)
                for since, sign in ((tau, 1.0), (s.duration_s - tau, -1.0)):
                    r = since < ramp
                    e[r] = 0.5 - 0.5 * np.cos(k * since[r])
                    de[r] = sign * 0.5 * k * np.sin(k * since[r])
                    dde[r] = 0.5 * k * k * np.cos(k * since[r])
            amp = gain * s.amplitude_mps2 / (w * w)
            sn, cs = np.sin(w * tau + ph), np.cos(w * tau + ph)
            sig, dsig, ddsig = -amp * sn, -amp * w * cs, amp * w * w * sn
            x[m] = e * sig
            v[m] = de * sig + e * dsig
            a[m] = dde * sig + 2.0 * de * dsig + e * ddsig
        return x, v, a


def build_slide(slide_cfg: dict[str, Any]) -> SlidePlan | None:
    """``SlidePlan`` from ``scenario.slide`` of the simulator config (None when not enabled)."""
    if not slide_cfg or not slide_cfg.get("enabled", False):
        return None
    segs = slide_cfg.get("segments") or []
    if not segs:
        raise ValueError("scenario.slide.enabled but scenario.slide.segments is empty")
    out = []
    for i, s in enumerate(segs):
        try:
            out.append(SlideSegment(float(s["freq_hz"]), float(s["amplitude_mps2"]), float(s["duration_s"])))
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"scenario.slide.segments[{i}]: expected {{freq_hz, amplitude_mps2, duration_s}}, "
                             f"got {s!r}") from None
    return SlidePlan(out, np.asarray(slide_cfg.get("direction", [0.0, 0.0, 1.0]), float),
                     float(slide_cfg.get("start_s", 0.0)), float(slide_cfg.get("gap_s", 0.0)),
                     float(slide_cfg.get("ramp_cycles", 2.0)))


def second_order_response(freq_hz: float, natural_hz: float, damping: float) -> complex:
    """H(f) = 1 / (1 - (f/fn)^2 + 2 j zeta f/fn): seismic mass on its suspension, acceleration in ->
    relative displacement out, normalised to 1 at DC (unitless)."""
    r = freq_hz / natural_hz
    return 1.0 / complex(1.0 - r * r, 2.0 * damping * r)
