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
3. amplitude and phase per frequency and axis with their budgets (:func:`dynamic_analysis.analyse_run`);
4. per axis a first-order low-pass + pure delay (+ the LDV's AC-coupling high-pass on the reference
   side when the plan declares one) fitted to the points (:func:`chain_model.fit_chain_models`);
5. the ``dynamic`` section: the axes' cut-offs and delays; the reference channel's cut-off only when
   given (a constant source hides it from a slide run).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fbg_accel_driver.chain_compensation import CUTOFF_LIMITS_HZ, MAX_ABS_DELAY_S, ChainDynamics
from fbg_accel_driver.frame_codec import at_adc_rail
from fbg_accel_driver.sensor_constants import LOW_REFERENCE_COUNTS
from fbg_accel_driver.thermal_model import ThermalCalibration

from .chain_model import ChainModel, fit_chain_models
from .dynamic_analysis import (
    AXES,
    STEP_TOL,
    DynamicPoint,
    ReferenceUncertainty,
    analyse_run,
    points_table_markdown,
    sampling_rate,
    uniformly_sampled,
    whole_period_length,
)
from .excitation_plan import ExcitationPlan, find_slide_start, reference_acceleration
from .recording import Recording

MAX_CHI2_PER_DOF = 100.0  # a chain fit missing its points by > 10 standard uncertainties (rms) is refused


class DynamicCalibrationError(ValueError):
    """The recording cannot give a dynamic calibration (no aux channel, too short, an axis not excited)."""


@dataclass
class DynamicCalibrationResult:
    plan: ExcitationPlan
    slide_start_s: float
    windows: list[tuple[float, float, float]]
    points: list[DynamicPoint]
    models: dict[str, ChainModel]
    dynamics: ChainDynamics
    fs_hz: float
    notes: list[str] = field(default_factory=list)

    def report(self) -> str:
        """Plain-text tables: points per frequency and axis, then the fitted chain per axis."""
        lines = [f"dynamic calibration: plan '{self.plan.name}', slide starts at t = {self.slide_start_s:.3f} s, "
                 f"{len(self.windows)} steady windows, sampling {self.fs_hz:.1f} Hz",
                 "",
                 points_table_markdown(self.points)]
        lines += ["", "| axis | gain | cut-off [Hz] | delay [ms] | group delay at DC [ms] | reference high-pass [Hz] |",
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
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        return {"plan": self.plan.name, "slide_start_s": self.slide_start_s, "fs_hz": self.fs_hz,
                "windows": [list(w) for w in self.windows], "points": [p.to_dict() for p in self.points],
                "models": {ax: m.to_dict() for ax, m in self.models.items()}, "dynamic": self.dynamics.to_dict(),
                "notes": list(self.notes)}


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
    models = fit_chain_models(points, highpass=fit_highpass, highpass_in="reference", uncertainty_scaling="points")
    for ax in AXES:
        models[ax].axis = ax
        _check_plausible(ax, models[ax])
        if abs(models[ax].gain - 1.0) > 3 * max(models[ax].u_gain, 1e-3):
            notes.append(f"{ax}: dynamic gain {models[ax].gain:.4f} differs from 1: the static calibration's "
                         "sensitivity and the slide reference disagree (check the reference's sensitivity)")
    dyn = ChainDynamics(
        cutoff_hz=(math.nan if reference_cutoff_hz is None else float(reference_cutoff_hz),
                   *(float(models[ax].cutoff_hz) for ax in AXES)),
        delay_s=tuple(float(models[ax].delay_s) for ax in AXES),  # type: ignore[arg-type]
        fit={"plan": plan.name, "slide_start_s": start, "fs_hz": fs,
             "frequencies_hz": sorted({w[0] for w in windows}),
             "models": {ax: m.to_dict() for ax, m in models.items()},
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
    return DynamicCalibrationResult(plan, start, windows, points, models, dyn, fs, notes)


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
    """Refuse a chain fit that cannot be a calibration, naming the axis and the figures: not converged,
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
            f"{ax}: the chain fit is not plausible (gain {m.gain:.3g}, cut-off {m.cutoff_hz:.3g} Hz, delay "
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
