"""Dynamic calibration of one slide run: recording + excitation plan + static calibration -> the
measuring chain's dynamics (the calibration file's ``dynamic`` section) with points, fits and a report.

Pure numpy/scipy, no ROS (``fbg-accel-calib dynamic`` is the shell). Steps (docs/dynamic_calibration.md):

1. the slide's start on the recording's time base (:func:`excitation_plan.find_slide_start`; after a board
   reset, on the board run that holds the most of the plan), the steady
   part of every segment (:meth:`ExcitationPlan.steady_windows`); a segment with a channel clipped at a rail
   of the ADC in its steady part is left out with a note, one with a lost frame keeps its longest stretch without
   one (a note says so); a refusal for too few segments carries the notes;
2. the reference acceleration from the aux channel (:func:`excitation_plan.reference_acceleration`) and
   the sensor's acceleration from its counts by the **static** calibration (eq. 24 and 28, no chain
   compensation), so what is measured is the whole chain after eq. 28;
3. per **channel** (x, y, z: the counts normalised by eq. 24, where the TIA stages and delays are), the
   channel's signal ``M^-1 a`` (``M`` of eq. 28 at the run's temperature; exact: eq. 28 is ``M Psi + b``)
   against the component ``(M^-1 d)_j`` of the slide's acceleration it sees: amplitude and phase per
   frequency with their budgets (:func:`tone_analysis.analyse_run`), and the same per output axis (the
   measured axes' responses);
4. per channel a first-order low-pass + pure delay (+ the LDV's AC-coupling high-pass on the reference
   side when the plan declares one) fitted to the channel's points (:func:`chain_model.fit_chain_models`);
5. the check (:func:`check_axes`): the output axes' responses the channel models predict,
   ``M diag(H_channel) M^-1`` (:func:`chain_model.axis_response_along`), against the measured per-axis points,
   at every tone, in units of the points' standard uncertainties read with their degrees of freedom (a normal deviate
   of the same tail probability, :func:`normal_equivalent`); beyond ``MISFIT_Z`` the chain is not what the model
   describes (a warning in the report; ``fbg-accel-calib dynamic`` then writes the file only with
   ``--accept-misfit``);
6. the ``dynamic`` section (format 2): the channels' cut-offs and delays; the reference channel's cut-off only
   when given (a constant source hides it from a slide run).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import special

from fbg_accel_driver.chain_compensation import CUTOFF_LIMITS_HZ, MAX_ABS_DELAY_S, ChainDynamics
from fbg_accel_driver.frame_codec import at_adc_rail
from fbg_accel_driver.sensor_constants import LOW_REFERENCE_COUNTS
from fbg_accel_driver.thermal_model import ThermalCalibration

from ..io.recording import Recording
from .chain_model import ChainModel, axis_response_along, fit_chain_models
from .excitation_plan import ExcitationPlan, find_slide_start, reference_acceleration
from .tone_analysis import (
    AXES,
    STEP_TOL,
    DynamicPoint,
    ReferenceUncertainty,
    analyse_run,
    points_table_markdown,
    sampling_rate,
    uniformly_sampled,
)
from .tone_delay import whole_period_length

MAX_CHI2_PER_DOF = 100.0  # a chain fit missing its points by > 10 standard uncertainties (rms) is refused
MISFIT_Z = 3.0  # an axis point the channel models miss beyond this normal deviate (AxisCheck): a misfit


def normal_equivalent(z: float, dof: float) -> float:
    """``|z|``, a difference in units of a standard uncertainty that rests on ``dof`` effective degrees of freedom,
    as the normal deviate of the same two-sided tail probability: ``Phi^-1(1 - P(|t_dof| > |z|))`` (Student's t,
    GUM G.3). Equal to ``|z|`` for infinitely many; smaller for few (|z| 3.6 on 4.6 degrees of freedom is 2.4)."""
    a = abs(float(z))
    if not math.isfinite(a):
        return a
    tail = float(special.stdtr(dof, -a))
    return a if tail <= 0.0 else max(float(-special.ndtri(tail)), 0.0)


@dataclass
class AxisCheck:
    """The per-channel model against the measured per-axis responses (module docstring, step 5).

    ``rows``: per tone and output axis, the measured sensitivity and phase (deg) with their combined standard
    uncertainties and those uncertainties' effective degrees of freedom (``dof_sensitivity``, ``dof_phase``;
    Welch-Satterthwaite: the repeatability is a standard deviation over 3-8 sub-blocks,
    :meth:`DynamicPoint.degrees_of_freedom`), the model's prediction
    ``(M diag(H) M^-1 d)_i / d_i``, the differences in units of the uncertainties (``z_sensitivity``, ``z_phase``;
    the phase difference wrapped to +-180 deg) and the same read as normal deviates of equal tail probability
    (``normal_z_sensitivity``, ``normal_z_phase``: :func:`normal_equivalent`). The decision is on the latter: a
    standard deviation from 3 sub-blocks is itself uncertain (its ratio to the true one spreads by about 35 % on the
    4 degrees of freedom of amplitude and phase pooled), so a raw z beyond 3 is not rare on a plan of short segments.
    ``threshold``: the largest normal deviate that is not a misfit."""

    rows: list[dict[str, float | str]]
    threshold: float = MISFIT_Z

    @staticmethod
    def _z(r: dict[str, float | str]) -> float:
        return max(float(r["normal_z_sensitivity"]), float(r["normal_z_phase"]))

    @property
    def max_abs_z(self) -> float:
        """The largest normal-equivalent difference over the rows (the decision's figure)."""
        return max((self._z(r) for r in self.rows), default=0.0)

    @property
    def misfit(self) -> bool:
        return self.max_abs_z > self.threshold

    def worst(self) -> dict[str, float | str] | None:
        return max(self.rows, key=self._z, default=None)

    def verdict(self) -> str:
        """One line: the largest difference, and whether it is a misfit."""
        w = self.worst()
        if w is None:
            return "axis check: no measurable axis point"
        q = "sensitivity" if float(w["normal_z_sensitivity"]) >= float(w["normal_z_phase"]) else "phase"
        line = (f"axis check: the per-channel model misses the measured axes by at most {self.max_abs_z:.2g} standard "
                f"uncertainties as a normal deviate ({w['axis']} {q} at {float(w['f_hz']):g} Hz: "
                f"{abs(float(w['z_' + q])):.2g} on {float(w['dof_' + q]):.3g} degrees of freedom; misfit beyond "
                f"{self.threshold:g})")
        if self.misfit:
            line += (": WARNING the chain is not a first-order low-pass + delay per channel (another stage, a resonance, "
                     "a non-linearity?); the compensation built on it would be wrong")
        return line

    def markdown(self) -> str:
        lines = ["| f [Hz] | axis | S measured | S model | z (dof) | phase measured [deg] | phase model [deg] | z (dof) | "
                 "normal deviate |",
                 "|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in self.rows:
            lines.append(f"| {float(r['f_hz']):.4g} | {r['axis']} | {float(r['sensitivity']):.4f} +- "
                         f"{float(r['u_sensitivity']):.2g} | {float(r['model_sensitivity']):.4f} | "
                         f"{float(r['z_sensitivity']):+.2f} ({float(r['dof_sensitivity']):.3g}) | "
                         f"{float(r['phase_deg']):.2f} +- {float(r['u_phase_deg']):.2g} | {float(r['model_phase_deg']):.2f} | "
                         f"{float(r['z_phase']):+.2f} ({float(r['dof_phase']):.3g}) | {self._z(r):.2f} |")
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        rows = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()}
                for r in self.rows]  # infinitely many degrees of freedom (no type-A part) as null in JSON
        return {"threshold": self.threshold, "max_abs_z": self.max_abs_z, "misfit": self.misfit, "rows": rows}


def check_axes(points: list[DynamicPoint], m_static: np.ndarray, models: dict[str, ChainModel],
               direction: tuple[float, float, float] | list[float] | np.ndarray, threshold: float = MISFIT_Z) -> AxisCheck:
    """:class:`AxisCheck` of the channel ``models`` (keys x, y, z) against the measured per-axis ``points`` of a
    slide along ``direction`` (sensor frame), ``m_static`` (3, 3) eq. 28's M at the run's temperature.

    M's own error (the static calibration's, ``coefficient_covariance``) is not added: the axis points are M times
    the channel points, through the same M, and an error of M changes the component of the slide each channel is
    compared with by a real factor per channel, which its fitted gain takes up; the differences checked here are the
    channel fits' residuals as the axes see them (docs/dynamic_calibration.md, "The axis check")."""
    chain = [models[ax] for ax in AXES]
    rows: list[dict[str, float | str]] = []
    for p in points:
        if not p.measurable:
            continue
        h = complex(axis_response_along(m_static, chain, direction, p.f_hz)[p.axis_index])
        dphi = math.degrees(math.remainder(math.atan2(h.imag, h.real) - math.radians(p.phase_deg), 2 * math.pi))
        z_s, z_p = (abs(h) - p.sensitivity) / p.u_sensitivity, dphi / p.u_phase_deg
        nu_s, nu_p = p.degrees_of_freedom("sensitivity"), p.degrees_of_freedom("phase")
        rows.append({"f_hz": p.f_hz, "axis": p.axis, "sensitivity": p.sensitivity, "u_sensitivity": p.u_sensitivity,
                     "dof_sensitivity": nu_s, "model_sensitivity": abs(h), "z_sensitivity": z_s,
                     "normal_z_sensitivity": normal_equivalent(z_s, nu_s),
                     "phase_deg": p.phase_deg, "u_phase_deg": p.u_phase_deg, "dof_phase": nu_p,
                     "model_phase_deg": p.phase_deg + dphi, "z_phase": z_p, "normal_z_phase": normal_equivalent(z_p, nu_p)})
    return AxisCheck(rows, threshold)


class DynamicCalibrationError(ValueError):
    """The recording cannot give a dynamic calibration (no aux channel, too short, an axis not excited)."""


@dataclass
class DynamicCalibrationResult:
    plan: ExcitationPlan
    slide_start_s: float
    windows: list[tuple[float, float, float]]
    points: list[DynamicPoint]  # measured per output axis
    models: dict[str, ChainModel]  # per channel x, y, z
    dynamics: ChainDynamics
    fs_hz: float
    notes: list[str] = field(default_factory=list)
    channel_points: list[DynamicPoint] = field(default_factory=list)  # measured per channel x, y, z
    m_static: np.ndarray = field(default_factory=lambda: np.eye(3))  # eq. 28's M at the run's temperature
    run_temperature_c: float = math.nan
    check: AxisCheck = field(default_factory=lambda: AxisCheck([]))

    def report(self) -> str:
        """Plain-text tables: points per frequency and channel, the fitted chain per channel, then the output
        axes' measured points against the per-channel model (the check)."""
        lines = [f"dynamic calibration: plan '{self.plan.name}', slide starts at t = {self.slide_start_s:.3f} s, "
                 f"{len(self.windows)} steady windows, sampling {self.fs_hz:.1f} Hz; static calibration's M at the "
                 f"run's {self.run_temperature_c:.2f} degC",
                 "",
                 "Per channel (x, y, z: the counts after eq. 24 against the component M^-1 d of the slide's "
                 "acceleration the channel sees):",
                 "",
                 points_table_markdown(self.channel_points)]
        lines += ["", "| channel | gain | cut-off [Hz] | delay [ms] | group delay at DC [ms] | reference high-pass [Hz] |",
                  "|---|---:|---:|---:|---:|---:|"]
        for ax, m in self.models.items():
            hp = (f"{m.highpass_cutoff_hz:.3f} +- {m.u_highpass_cutoff_hz:.3f}" if m.highpass_cutoff_hz is not None
                  else "-")
            lines.append(f"| {ax} | {m.gain:.4f} +- {m.u_gain:.4f} | {m.cutoff_hz:.4f} +- {m.u_cutoff_hz:.4f} | "
                         f"{m.delay_s * 1e3:.2f} +- {m.u_delay_s * 1e3:.2f} | {m.sensor_group_delay_dc_s() * 1e3:.2f} | {hp} |")
        ref = self.dynamics.cutoff_hz[0]
        lines.append("")
        lines.append("reference channel cut-off: " + ("not measured (constant source); chain_compensation 'delay' only"
                                                       if math.isnan(ref) else f"{ref:g} Hz (given)"))
        lines += ["", "Per output axis (eq. 28's output against the slide's acceleration along the axis), measured and "
                  "as the channel models predict it, M diag(H_channel) M^-1:", "", points_table_markdown(self.points),
                  "", self.check.markdown(), "", self.check.verdict(),
                  "(z: difference / standard uncertainty, on the uncertainty's effective degrees of freedom; the static "
                  "calibration's own error in M is not in it: the axes are M times the channels through the same M, "
                  "and an error of M changes only the channels' gains)"]
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        return {"plan": self.plan.name, "slide_start_s": self.slide_start_s, "fs_hz": self.fs_hz,
                "windows": [list(w) for w in self.windows], "points": [p.to_dict() for p in self.points],
                "channel_points": [p.to_dict() for p in self.channel_points],
                "models": {ax: m.to_dict() for ax, m in self.models.items()}, "dynamic": self.dynamics.to_dict(),
                "run_temperature_c": self.run_temperature_c, "m_static": self.m_static.tolist(),
                "axis_check": self.check.as_dict(), "notes": list(self.notes)}


def run_dynamic(rec: Recording, plan: ExcitationPlan, static_cal: ThermalCalibration, *,
                reference_cutoff_hz: float | None = None, fit_highpass: bool = False,
                slide_start_s: float | None = None, method: str = "sine") -> DynamicCalibrationResult:
    """The dynamic calibration of one slide run (module docstring).

    The reference's AC coupling (an LDV's declared ``ac_coupling_hz``) is undone on the reference signal
    (:func:`reference_acceleration`) unless ``fit_highpass``: then it is left in and fitted as a
    parameter of the chain model (when the data-sheet value is unknown; it trades off against the gain
    and the cut-off, so the cut-offs come out less certain). ``slide_start_s``: the slide's start on the
    recording's time base (default: found from the aux channel). Parameter uncertainties come from the
    points' budgets (``uncertainty_scaling='points'``).
    """
    if rec.aux is None or not np.any(np.isfinite(rec.aux)):
        raise DynamicCalibrationError("the recording has no aux channel (protocol version 2 frames, imu/raw "
                                      "'aux_counts', CSV column 'aux'): the reference transducer is missing")
    notes: list[str] = []
    # a board reset restarts the board clock: sorting both board runs into one time base would interleave them
    rec, reset_note = _one_board_run(rec, plan, slide_start_s)
    if reset_note:
        notes.append(reset_note)
    order = np.argsort(rec.t_s, kind="stable")
    t, aux = rec.t_s[order], rec.aux[order]
    ok = np.isfinite(t) & np.isfinite(aux) & np.isfinite(rec.ref[order]) & np.all(np.isfinite(rec.xyz[order]), axis=1)
    t, aux = t[ok], aux[ok]
    ref_c, xyz = rec.ref[order][ok], rec.xyz[order][ok]
    temp = _filled_temperature(rec.temp_c[order][ok])
    fs = sampling_rate(t)  # the median step: a lost frame outside the steady parts does not matter
    try:
        start = find_slide_start(t, aux, plan) if slide_start_s is None else float(slide_start_s)
    except ValueError as exc:
        raise DynamicCalibrationError(f"{exc}: give --slide-start to use the segments it holds") from None
    windows = [w for w in plan.steady_windows(start) if w[1] >= t[0] and w[2] <= t[-1]]
    lost = len(plan.segments) - len(windows)
    if lost:
        notes.append(f"{lost} segment(s) of the plan are not (wholly) in the recording or too short once settled")
    # a sine whose peaks hit a rail of the ADC reads a smaller amplitude and a shifted phase (Recording.clipped;
    # the reference transducer on aux is read by the same 12-bit converters); with no source light
    # (Recording.low_reference: the driver publishes nothing then, the static fit leaves such samples out)
    # Psi = counts / ref is no measurement: a segment with such a sample in its steady part is left out
    for bad, why in ((rec.clipped()[order][ok] | at_adc_rail(aux),
                      "a channel clipped at a rail of the ADC during the steady part (lower the slide's amplitude there)"),
                     (rec.low_reference()[order][ok], f"the reference dark (below {LOW_REFERENCE_COUNTS} counts, no "
                                                      "source light) during the steady part")):
        hit = [w for w in windows if bad[_steady(t, w)].any()]
        if hit:
            windows = [w for w in windows if w not in hit]
            notes.append(f"segment(s) at {', '.join(f'{w[0]:g} Hz' for w in hit)} left out: {why}")
    # the whole-period cuts, the DFT and the circular cross-correlation count samples: a lost frame (or a
    # sample dropped above for a non-finite value, or a late read) inside a steady part would shift every later
    # sample, so such a part keeps its longest uniformly sampled stretch (left out below if it holds < 2 periods)
    gappy = [w for w in windows if not uniformly_sampled(t[_steady(t, w)], fs)]
    if gappy:
        kept = {w: _longest_uniform_stretch(t, w, fs) for w in gappy}
        windows = [kept.get(w, w) for w in windows]
        windows = [w for w in windows if w is not None]
        notes.append("steady part(s) at " + ", ".join(
            f"{w[0]:g} Hz ({(k[2] - k[1]) if k else 0.0:.3g} of {w[2] - w[1]:.3g} s kept)" for w, k in kept.items())
            + f": a lost frame or an irregular time step (other than the nominal {1e3 / fs:.4g} ms); the longest "
            "stretch without one is used")
    # a point's repeatability is measured over whole-period sub-blocks: one period has none (the sine fit's
    # white-noise covariance understates coloured noise 5-13x and would dominate the chain fit)
    few = sorted({w[0] for w in windows if _whole_periods(t, fs, [v for v in windows if v[0] == w[0]]) < 2})
    if few:
        windows = [w for w in windows if w[0] not in few]
        notes.append(f"segment(s) at {', '.join(f'{f:g} Hz' for f in few)} left out: fewer than 2 whole periods in "
                     "the steady part (one whole period gives no measured repeatability; lengthen the segment)")
    if len(windows) < 3:
        raise DynamicCalibrationError(f"only {len(windows)} steady segment(s) in the recording: the chain model needs "
                                      "at least 3 frequencies" + "".join(f"; {n}" for n in notes))
    nyq = [w for w in windows if w[0] >= 0.45 * fs]
    if nyq:
        raise DynamicCalibrationError(f"segments at {', '.join(f'{w[0]:g}' for w in nyq)} Hz are too close to the "
                                      f"Nyquist frequency of {fs / 2:.1f} Hz: record at a higher board rate")
    a_ref = reference_acceleration(t, aux, plan, windows, undo_ac_coupling=not fit_highpass)
    a_sensor = static_cal.apply_counts(ref_c, xyz, temp, t)
    ru = ReferenceUncertainty(sensitivity_rel=plan.reference.relative_uncertainty,
                              phase_deg=plan.reference.phase_uncertainty_deg)
    points = analyse_run(t, np.nan_to_num(a_ref), a_sensor, plan.direction, windows, reference_uncertainty=ru,
                         method=method)  # type: ignore[arg-type]
    not_measurable = sorted({p.axis for p in points if not p.measurable})
    if not_measurable:
        raise DynamicCalibrationError(f"axes {not_measurable} are not excited by the slide direction {plan.direction}: "
                                      "tilt the sensor so the direction has a component on every axis (seed 2, eqs. 1-3)")
    # per channel: eq. 28 is a = M Psi + b, so M^-1 a is the channels' Psi (offsets aside, which the sine fits remove),
    # and the component of the slide's acceleration channel j sees is (M^-1 d)_j times the reference
    steady = np.zeros(len(t), dtype=bool)
    for w in windows:
        steady |= _steady(t, w)
    run_temp = float(np.median(temp[steady]))
    m_run = static_cal.coefficients(run_temp)[0][0]
    d_unit = np.asarray(plan.direction, dtype=float) / np.linalg.norm(plan.direction)
    seen = np.linalg.solve(m_run, d_unit)
    scale = float(np.linalg.norm(seen))  # analyse_run normalises the direction: the signal scaled alike
    psi = np.linalg.solve(m_run, a_sensor.T).T / scale
    channel_points = analyse_run(t, np.nan_to_num(a_ref), psi, seen, windows, reference_uncertainty=ru,
                                 method=method)  # type: ignore[arg-type]
    faint = sorted({p.axis for p in channel_points if not p.measurable})
    if faint:
        raise DynamicCalibrationError(f"channels {faint} see too little of the slide direction {plan.direction} through "
                                      "the static calibration's M^-1: tilt the sensor so every channel is excited")
    models = fit_chain_models(channel_points, highpass=fit_highpass, highpass_in="reference",
                              uncertainty_scaling="points")
    for ax in AXES:
        models[ax].axis = ax
        _check_plausible(ax, models[ax])
        if abs(models[ax].gain - 1.0) > 3 * max(models[ax].u_gain, 1e-3):
            notes.append(f"channel {ax}: dynamic gain {models[ax].gain:.4f} differs from 1: the static calibration's "
                         "sensitivity and the slide reference disagree (check the reference's sensitivity)")
    check = check_axes(points, m_run, models, d_unit)
    if check.misfit:
        notes.append(check.verdict())
    dyn = ChainDynamics(
        cutoff_hz=(math.nan if reference_cutoff_hz is None else float(reference_cutoff_hz),
                   *(float(models[ax].cutoff_hz) for ax in AXES)),
        delay_s=tuple(float(models[ax].delay_s) for ax in AXES),  # type: ignore[arg-type]
        fit={"plan": plan.name, "slide_start_s": start, "fs_hz": fs,
             "frequencies_hz": sorted({w[0] for w in windows}),
             "identified_per": "channel", "run_temperature_c": run_temp,
             "models": {ax: m.to_dict() for ax, m in models.items()},
             "axis_check": {"max_abs_z": check.max_abs_z, "threshold": check.threshold, "misfit": check.misfit},
             "reference_cutoff": "given" if reference_cutoff_hz is not None else "not measured"})
    # what the driver's `delay` mode (chain_compensation auto) does with this section: the DC shift over-corrects tones
    # above a limit; said here as the driver's diagnostic says it (ChainDynamics.delay_helps_below_hz)
    helps = dyn.delay_helps_below_hz()
    f_top = max(w[0] for w in windows)
    if min(helps) < f_top:
        ax = AXES[int(np.argmin(helps))]
        notes.append(f"chain_compensation 'delay' (what 'auto' picks) moves the stamps back by "
                     f"{dyn.stamp_delay_s('delay') * 1e3:.4g} ms, a correction below {min(helps):.3g} Hz only ({ax}): "
                     f"above it, inside the measured band (up to {f_top:g} Hz), a tone's error is larger than "
                     "uncompensated; for such content use 'equalise' (it needs the reference channel's cut-off)")
    return DynamicCalibrationResult(plan, start, windows, points, models, dyn, fs, notes, channel_points, m_run,
                                    run_temp, check)


def _one_board_run(rec: Recording, plan: ExcitationPlan, slide_start_s: float | None) -> tuple[Recording, str | None]:
    """``rec`` as it is when its board time (s) never goes back; else (a board reset: the board clock restarts at 0,
    ``stream_decoder``'s rule) the board run, in recorded order, whose alignment with the plan
    (:func:`find_slide_start`, or the given ``slide_start_s``) holds the most steady segments (then the most
    samples), and a note naming the reset(s). The plan's timing does not carry across a reset: the outage's length
    is unknown, so the slide's start must be found in each board run on its own clock."""
    t = rec.t_s
    back = np.flatnonzero(np.diff(t) < 0) + 1  # the first sample of each new board run
    if back.size == 0:
        return rec, None
    bounds = [0, *back.tolist(), len(t)]
    idx = np.arange(len(t))
    best: tuple[tuple[int, int], int, int] | None = None
    for a, b in itertools.pairwise(bounds):
        part = rec.select((idx >= a) & (idx < b))
        ok = np.isfinite(part.t_s) & np.isfinite(part.aux)  # type: ignore[arg-type]
        n_win = 0
        if ok.sum() >= 3:
            try:
                start = find_slide_start(part.t_s[ok], part.aux[ok], plan) if slide_start_s is None else slide_start_s  # type: ignore[index]
                n_win = sum(1 for w in plan.steady_windows(start) if w[1] >= part.t_s[ok][0] and w[2] <= part.t_s[ok][-1])
            except ValueError:
                pass
        key = (n_win, b - a)
        if best is None or key > best[0]:
            best = (key, a, b)
    assert best is not None
    (n_win, _), a, b = best
    where = ", ".join(f"{t[i - 1]:.3f} -> {t[i]:.3f} s" for i in back)
    note = (f"{back.size} board reset(s) (board time going back at {where}): the plan's timing does not carry across "
            f"one, so only the board run of samples {a}..{b - 1} ({t[a]:.3f}..{t[b - 1]:.3f} s, {n_win} steady "
            f"segment(s) aligned) is used; the other {len(t) - (b - a)} samples are ignored")
    return rec.select((idx >= a) & (idx < b)), note


def _steady(t: np.ndarray, window: tuple[float, float, float]) -> np.ndarray:
    """The samples (mask over ``t``) of the steady window ``(f_hz, t0_s, t1_s)``: [t0, t1), as ``analyse_run`` cuts them."""
    return (t >= window[1]) & (t < window[2])


def _longest_uniform_stretch(t: np.ndarray, window: tuple[float, float, float], fs: float
                             ) -> tuple[float, float, float] | None:
    """The longest stretch of the steady window ``(f_hz, t0_s, t1_s)`` whose every time step is the nominal
    ``1 / fs`` (``uniformly_sampled``): ``(f_hz, first sample's t, last sample's t + half a step)``, so that
    :func:`_steady` selects exactly its samples; None when no two consecutive samples qualify."""
    idx = np.flatnonzero(_steady(t, window))
    if idx.size < 2:
        return None
    ok = np.abs(np.diff(t[idx]) * fs - 1.0) <= STEP_TOL  # step k joins samples k and k + 1
    best, best_len, start = (0, 0), 0, None
    for k, good in enumerate(np.append(ok, False)):
        if good and start is None:
            start = k
        elif not good and start is not None:
            if k - start > best_len:
                best, best_len = (start, k), k - start
            start = None
    if best_len == 0:
        return None
    return (window[0], float(t[idx[best[0]]]), float(t[idx[best[1]]]) + 0.5 / fs)


def _whole_periods(t: np.ndarray, fs: float, windows: list[tuple[float, float, float]]) -> int:
    """Whole periods (at ``fs`` Hz, :func:`whole_period_length`) in the steady windows ``(f_hz, t0_s, t1_s)``
    of one frequency, summed; a window with less than one period counts 0."""
    total = 0
    for f, a, b in windows:
        try:
            total += whole_period_length(int(np.count_nonzero(_steady(t, (f, a, b)))), fs, f)[0]
        except ValueError:
            pass
    return total


def _check_plausible(ax: str, m: ChainModel) -> None:
    """Refuse a chain fit that cannot be a calibration, naming the channel and the figures: not converged,
    a parameter not finite or outside what the driver accepts (cut-off CUTOFF_LIMITS_HZ in Hz, |delay| up to
    MAX_ABS_DELAY_S in s, gain > 0), or the model missing its points by more than MAX_CHI2_PER_DOF (chi2
    per degree of freedom with the points' own uncertainties: about 1 for a chain the model describes)."""
    chi2, dof = float(m.fit.get("chi2", math.nan)), int(m.fit.get("dof", 0))
    per_dof = chi2 / dof if dof > 0 else math.nan
    why = []
    if not m.fit.get("converged", True):
        why.append("the least-squares fit did not converge")
    if not (math.isfinite(m.cutoff_hz) and CUTOFF_LIMITS_HZ[0] <= m.cutoff_hz <= CUTOFF_LIMITS_HZ[1]):
        why.append(f"the cut-off is outside {CUTOFF_LIMITS_HZ[0]:g}..{CUTOFF_LIMITS_HZ[1]:g} Hz")
    if not (math.isfinite(m.delay_s) and abs(m.delay_s) <= MAX_ABS_DELAY_S):
        why.append(f"the delay is beyond +-{MAX_ABS_DELAY_S:g} s")
    if not (math.isfinite(m.gain) and m.gain > 0):
        why.append("the gain is not a positive number")
    if per_dof > MAX_CHI2_PER_DOF:
        why.append(f"the model misses its points by {math.sqrt(per_dof):.0f} standard uncertainties (rms)")
    if why:
        raise DynamicCalibrationError(
            f"channel {ax}: the chain fit is not plausible (gain {m.gain:.3g}, cut-off {m.cutoff_hz:.3g} Hz, delay "
            f"{m.delay_s * 1e3:.4g} ms, chi2/dof {per_dof:.0f}): {'; '.join(why)}. The points do not pin down a "
            "first-order low-pass + delay: check that the plan's band reaches the cut-off, the points' phases "
            "(--json) and the reference")


def _filled_temperature(temp: np.ndarray) -> np.ndarray:
    """Temperatures with invalid readings (NaN) replaced by the last valid one (the first valid before it)."""
    temp = np.asarray(temp, dtype=float).copy()
    ok = np.isfinite(temp)
    if not ok.any():
        raise DynamicCalibrationError("no valid temperature in the recording: the static calibration cannot be applied")
    idx = np.where(ok, np.arange(len(temp)), -1)
    np.maximum.accumulate(idx, out=idx)
    first = int(np.flatnonzero(ok)[0])
    idx[idx < 0] = first
    return temp[idx]
