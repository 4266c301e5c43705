"""The mechanical front of the simulator's signal chain (``board_physics``): what the seismic mass feels -- the table's
angles and the specific force through the mount, the vibration and the linear slide through the mechanical resonance,
the channel delay and ADC skew -- and the axis inputs u = A f + the equivalent biases (time drift, thermal and motion
hysteresis, a bias step, the cable torque). Sources in each docstring and docs/simulator.md."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from fbg_accel_calibration.io.table_geometry import table_specific_force

from .scenario import vibration


def _play_branch(x: np.ndarray, width: float, p: float) -> tuple[np.ndarray, float]:
    """Branch (x - play(x)) / width in [-1/2, 1/2] of a play operator (backlash of ``width``, in the unit of ``x``) that
    starts at ``p``, and its last output: +1/2 after a rise of ``x`` by more than the width, -1/2 after a fall, in
    between on a reversal smaller than the width. Zeros when ``width`` is 0."""
    u_play = np.empty(x.shape[0])
    half = 0.5 * width
    for i, v in enumerate(x.tolist()):
        if v - p > half:
            p = v - half
        elif p - v > half:
            p = v + half
        u_play[i] = p
    return ((x - u_play) / width if width > 0 else np.zeros(x.shape[0])), p


class _TableMotion(NamedTuple):
    """Table stage of a chunk: readings at t, and what the seismic mass feels (arrays over the samples)."""

    psi_deg: np.ndarray  # table angle readings at t (deg)
    theta_deg: np.ndarray
    pose_id: np.ndarray
    in_motion: np.ndarray
    visit: np.ndarray
    time_at_pose_s: np.ndarray
    gref_mps2: np.ndarray  # (N, 3) table reference specific force at the reading (m/s^2)
    accel_true_mps2: np.ndarray  # (N, 3) true specific force at t, sensor frame (m/s^2)
    felt_mps2: np.ndarray  # (N, 3) felt by the mass: at t - delay, dynamic parts through the resonance (m/s^2)
    psi_felt_deg: np.ndarray  # inner angle at t - delay (deg): drives the cable torque


class _Slide(NamedTuple):
    """True linear-slide motion along its direction (arrays over the samples; segment -1 = at rest or no slide)."""

    displacement_m: np.ndarray
    velocity_mps: np.ndarray
    accel_mps2: np.ndarray
    segment: np.ndarray


class _MechanicsStages:
    """Methods of :class:`~fbg_accel_sim.board_physics.BoardSimulator`, on its state (set up in its ``__init__``):
    table motion, slide, axis biases and axis inputs."""

    def _sensed_force(self, tt: np.ndarray) -> np.ndarray:
        """Specific force (N, 3) m/s^2, sensor frame, that the seismic mass feels at times ``tt`` (s): table
        gravity + vibration + slide, dynamic parts through the mechanical resonance."""
        psi, theta, *_ = self.trajectory.evaluate(tt)
        f = table_specific_force(psi, theta, self.gravity) @ self.R_mount.T + vibration(tt, self.sines, self.resonance)
        if self.slide is not None:
            f = f + self.slide.kinematics(tt, self.resonance)[2][:, None] * self.slide.direction[None, :]
        return f

    def _table_motion(self, t: np.ndarray, delay: float) -> _TableMotion:
        """Table angle readings at ``t`` (s, deg) and the specific force (m/s^2, sensor frame) the seismic mass feels
        ``delay`` s later (channel_delay effect, ASSUMPTION): gravity through the table geometry and the mount rotation
        plus the vibration sines, whose dynamic part goes through the mechanical resonance (paper 3.4, facts)."""
        psi, theta, pose_id, moving, visit = self.trajectory.evaluate(t)
        arrival = self.trajectory.arrival_time(t)
        gref = table_specific_force(psi, theta, self.gravity)
        vib_true = vibration(t, self.sines)
        if delay != 0.0:
            psi_d, theta_d, *_ = self.trajectory.evaluate(t - delay)
            f_phys_table = table_specific_force(psi_d, theta_d, self.gravity)
        else:
            psi_d, f_phys_table = psi, gref
        vib_phys = vibration(t - delay, self.sines, self.resonance) if delay != 0.0 or self.resonance else vib_true
        accel_true = gref @ self.R_mount.T + vib_true
        f_phys = f_phys_table @ self.R_mount.T + vib_phys
        return _TableMotion(psi, theta, pose_id, moving, visit, arrival, gref, accel_true, f_phys, psi_d)

    def _linear_slide(self, t: np.ndarray, delay: float, table: _TableMotion) -> tuple[_Slide, _TableMotion]:
        """Linear slide of a dynamic calibration (seed 2, section 2): its true motion at ``t`` along the slide direction
        (m, m/s, m/s^2; truth and reference transducer) and ``table`` with the slide's acceleration added, true at ``t``
        and felt at ``t - delay`` through the resonance (m/s^2). Without a slide: zeros, segment -1, ``table`` as is."""
        if self.slide is None:
            zero = np.zeros(t.shape[0])
            return _Slide(zero, zero, zero, np.full(t.shape[0], -1, dtype=np.int64)), table
        sl_x, sl_v, sl_a = self.slide.kinematics(t)
        accel_true = table.accel_true_mps2 + sl_a[:, None] * self.slide.direction[None, :]
        felt = table.felt_mps2 + self.slide.kinematics(t - delay, self.resonance)[2][:, None] * self.slide.direction[None, :]
        return (_Slide(sl_x, sl_v, sl_a, self.slide.segment_index(t)),
                table._replace(accel_true_mps2=accel_true, felt_mps2=felt))

    def _axis_biases(self, t: np.ndarray, T_opt: np.ndarray, psi_felt_deg: np.ndarray, felt: np.ndarray) -> np.ndarray:
        """Equivalent acceleration biases (N, 3) on the axis inputs, m/s^2: time drift (warm-up and creep of the pair
        separation: bond relaxation, not characterised in the paper), thermal hysteresis (bond/mount stress; play
        operator on the optics temperature ``T_opt``, degC), a step of the bias at one time (``bias_step``: the calibration
        stops holding, what the driver's gravity check must see) and the unmodelled cable torque ~ sin(harmonic psi) (fibre
        pigtail drag at the felt inner angle ``psi_felt_deg``) and a motion-history hysteresis (each axis' branch set by the
        sign of the last change of the specific force it feels, ``felt`` (N, 3) m/s^2); amplitudes ASSUMPTION
        (config/sim_default.yaml)."""
        eff = self.cfg.get("effects")
        bias = np.zeros((t.shape[0], 3))
        td = eff["time_drift"]
        if float(td["scale"]) != 0.0:
            w = np.asarray(td["warmup_amplitude_mps2"], float) * -np.expm1(-t / float(td["warmup_time_constant_s"]))[:, None]
            bias += float(td["scale"]) * (w + np.asarray(td["creep_mps2_per_h"], float) * (t / 3600.0)[:, None])
        hy = eff["thermal_hysteresis"]
        if float(hy["scale"]) != 0.0:
            branch = self._hysteresis_branch(T_opt, float(hy["play_width_c"]))
            bias += float(hy["scale"]) * branch[:, None] * np.asarray(hy["amplitude_mps2"], float)
        bs = eff["bias_step"]
        if float(bs["scale"]) != 0.0:  # the response steps once after calibration (a knock, a mount shift; ASSUMPTION)
            bias += float(bs["scale"]) * (t >= float(bs["at_s"]))[:, None] * np.asarray(bs["amplitude_mps2"], float)
        ct = eff["unmodelled_cable_torque"]
        if float(ct["scale"]) != 0.0:
            ang = np.radians(float(ct["harmonic"]) * psi_felt_deg + float(ct["phase_deg"]))
            bias += float(ct["scale"]) * np.sin(ang)[:, None] * np.asarray(ct["amplitude_mps2"], float)
        mh = eff["motion_hysteresis"]
        if float(mh["scale"]) != 0.0:  # friction in the suspension and bonds (ASSUMPTION): the force's last change
            branch = self._motion_branches(felt, float(mh["play_width_mps2"]))
            bias += float(mh["scale"]) * branch * np.asarray(mh["amplitude_mps2"], float)
        return bias

    def _hysteresis_branch(self, T_opt: np.ndarray, width: float) -> np.ndarray:
        """Thermal hysteresis branch in [-1/2, 1/2] (``_play_branch`` of the optics temperature, ``width`` degC), the
        play operator's output kept in ``self._play`` from chunk to chunk."""
        branch, self._play = _play_branch(T_opt, width, self._play)
        return branch

    def _motion_branches(self, felt: np.ndarray, width: float) -> np.ndarray:
        """Motion-history branch (N, 3) in [-1/2, 1/2] of each axis: ``_play_branch`` of the specific force the axis
        feels (``felt``, m/s^2, sensor frame; ``width`` m/s^2), so it is set by the sign of the force's last change
        larger than the width; the play operators' outputs carry from chunk to chunk."""
        if self._force_play is None:
            self._force_play = np.array(felt[0], dtype=float)
        out = np.empty_like(felt)
        for j in range(3):
            out[:, j], self._force_play[j] = _play_branch(felt[:, j], width, float(self._force_play[j]))
        return out

    def _axis_inputs(self, t: np.ndarray, delay: float, felt: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """Axis inputs u = A f + bias (N, 3), m/s^2, with A the cross-axis coupling derived from the published
        calibration matrix (paper eq. 31a). With a channel skew (board.adc_channel_skew_us), the ESP32 one-shot
        sequential conversion (ESP-IDF adc_oneshot_read) makes each axis see its own, later instant."""
        u = felt @ self.A.T + bias
        if self.skew_s > 0.0 or np.any(self.channel_extra_delay_s):
            # ESP32 one-shot sequential conversion: axis channel j (x, y, z = 1, 2, 3 after ref) is converted
            # j skews after t_us, so it sees the input of that later instant (an LTI chain commutes with the shift);
            # an axis channel's own extra delay (axis_channel_extra_s) moves it the other way
            for j in range(3):
                u[:, j] = self._sensed_force(self._channel_time(t, delay, j)) @ self.A[j] + bias[:, j]
        return u

    def _channel_time(self, t: np.ndarray, delay: float, j: int) -> np.ndarray:
        """The instant (s) axis channel ``j`` (0..2: x, y, z) senses at sample time ``t``: the common channel delay,
        the channel's own extra delay and its ADC conversion skew."""
        return t - delay - float(self.channel_extra_delay_s[j]) + (j + 1) * self.skew_s
