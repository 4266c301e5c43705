"""Driver diagnostics: counters and states -> status entries (pure Python, no ROS).

``DriverDiagnostics.report(snapshot)`` returns a list of ``DiagnosticEntry`` (level, name,
message, key/values), one per concern, which the node turns into a
``diagnostic_msgs/DiagnosticArray``. Counters in the key/values are cumulative since start;
levels look at what changed since the previous report (a CRC error last minute is not a
problem now) or at the current state.

Entries (names are prefixed with ``<prefix>: ``):

=========================  =====================================================================
name                       level
=========================  =====================================================================
serial link                OK connected and frames flowing; ERROR disconnected (message: reason,
                           back-off); ERROR connected but no frame for ``no_data_timeout_s``
reader queue               OK; WARN if the reader dropped queued bytes since the previous report (the
                           decoder fell ``queue_max_bytes`` behind; the oldest were dropped)
frames                     OK; WARN if CRC errors, lost frames, invalid frames or unsupported
                           versions appeared since the previous report
board resets               OK; WARN if the board rebooted since the previous report
ADC saturation             OK; WARN if saturated samples appeared since the previous report
reference power            OK; ERROR if reference-too-low samples appeared since the previous report
temperature sensor         OK valid; WARN invalid but holding the last good value; ERROR when
                           the hold time ran out or no valid reading was ever received
temperature range          OK inside the calibrated range; WARN outside (extrapolation)
correction span            OK; WARN if a correction term was held at the edge of the span it was fitted on
                           since the previous report (``correction_out_of_span``)
calibrated output          OK; ERROR if samples were dropped since the previous report because the
                           calibration gave a non-finite acceleration (``non_finite_dropped``)
clock mapping              OK (drift estimate, restarts, steps of ROS time); WARN when the drift estimate sits at
                           its clamp (``ClockSyncConfig.max_drift``): the mapping is not tracking; WARN when the
                           stamps stepped since the previous report (a step of ROS time, of the mapping, or
                           stamps held 1 ns apart because they would have gone back)
gravity check              OK while every test of a still stretch finds |a| within its threshold of gravity_mps2
                           (stating the last discrepancy), or before the first test, or off; WARN when the last test,
                           or one since the previous report, found |a| - g beyond the threshold: the calibration no
                           longer holds (message: the discrepancy, the threshold and its parts, and the sensor
                           axes a bias on which no orientation still so far has seen)
chain compensation         OK, stating the mode and its cost; WARN in ``delay`` mode when the frequency above which
                           the stamp shift makes a tone's error larger than none lies inside the calibrated band
=========================  =====================================================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from .thermal_model import widened_range

OK, WARN, ERROR, STALE = 0, 1, 2, 3  # diagnostic_msgs/DiagnosticStatus levels


@dataclass(frozen=True)
class DiagnosticEntry:
    level: int
    name: str
    message: str
    values: tuple[tuple[str, str], ...]


@dataclass
class DiagnosticsSnapshot:
    """Everything the report needs, sampled by the node at report time."""

    now_s: float  # monotonic seconds (any origin), for rates
    link_connected: bool
    link_message: str
    link_values: dict[str, Any]  # port, baud, connects, disconnects, failed_attempts, next_retry_s ...
    decoder: dict[str, int]  # StreamDecoder.stats.as_dict()
    core: dict[str, int]  # CoreCounters.as_dict()
    temperature_valid: bool | None  # validity of the latest frame (None: no frame yet)
    temperature_age_s: float | None  # since the last valid reading (None: never valid)
    last_temperature_c: float | None
    temperature_hold_s: float
    temperature_range_c: tuple[float, float]
    temperature_range_margin_c: float = 0.0  # a temperature this close to the range is inside it (CoreConfig)
    reference_level_tolerance: float | None = None  # relative (CoreConfig); None: not given
    calibration: dict[str, Any] = field(default_factory=dict)  # sensor id, file, degree
    chain: dict[str, Any] = field(default_factory=dict)  # DriverCore.chain_status(); empty: raw only, no entry
    clock: dict[str, Any] = field(default_factory=dict)  # DriverCore.clock_status(); empty: no entry
    # calibration_uncertainty_values(); empty: raw only, no entry
    calibration_uncertainty: dict[str, Any] = field(default_factory=dict)
    gravity: dict[str, Any] = field(default_factory=dict)  # DriverCore.gravity_status(); empty: raw only, no entry


class DriverDiagnostics:
    """Turns successive snapshots into diagnostic entries (keeps the previous counters)."""

    def __init__(self, prefix: str = "fbg_accel_driver", no_data_timeout_s: float = 1.0) -> None:
        self.prefix = prefix
        self.no_data_timeout_s = no_data_timeout_s
        self._prev: DiagnosticsSnapshot | None = None
        self._last_frame_change_s: float | None = None

    def _name(self, what: str) -> str:
        return f"{self.prefix}: {what}"

    def report(self, snap: DiagnosticsSnapshot) -> list[DiagnosticEntry]:
        prev = self._prev
        dec, core = snap.decoder, snap.core
        pdec = prev.decoder if prev else {k: 0 for k in dec}
        pcore = prev.core if prev else {k: 0 for k in core}

        def delta(cur: dict[str, Any], old: dict[str, Any], key: str) -> int:
            return int(cur.get(key, 0)) - int(old.get(key, 0))

        def counted(n: int, level: int, what: str, values: dict[str, Any], ok: str, bad: str) -> None:
            """``level`` with ``bad`` (``{n}``: the count since the last report) when ``n`` > 0, else OK with ``ok``."""
            entries.append(self._entry(level, what, bad.format(n=n), values) if n > 0 else self._entry(OK, what, ok, values))

        def core_counted(key: str, level: int, what: str, ok: str, bad: str, **more: Any) -> None:
            counted(delta(core, pcore, key), level, what, {key: core.get(key, 0), **more}, ok, bad)

        frames_new = delta(dec, pdec, "frames")
        if frames_new > 0 or self._last_frame_change_s is None:
            self._last_frame_change_s = snap.now_s
        dt = snap.now_s - prev.now_s if prev else 0.0
        rate = frames_new / dt if dt > 0 else 0.0
        entries: list[DiagnosticEntry] = []

        # serial link
        link_vals = {**snap.link_values, "state": "connected" if snap.link_connected else "disconnected"}
        silent_s = snap.now_s - self._last_frame_change_s
        if not snap.link_connected:
            level, msg = ERROR, f"disconnected: {snap.link_message}"
        elif dec.get("frames", 0) == 0 or (frames_new == 0 and silent_s >= self.no_data_timeout_s):
            link_vals["seconds_without_frames"] = round(silent_s, 3)
            level, msg = ERROR, "connected but no frames received"
        else:
            level, msg = OK, "connected, receiving frames"
        entries.append(self._entry(level, "serial link", msg, link_vals))

        # reader queue (the serial reader thread -> decoder hand-off, bounded)
        q_vals = {k: snap.link_values[k] for k in ("queued_bytes", "queue_max_bytes", "queue_dropped_chunks",
                                                    "queue_dropped_bytes") if k in snap.link_values}
        counted(delta(snap.link_values, prev.link_values if prev else {}, "queue_dropped_bytes"), WARN, "reader queue",
                q_vals, "keeping up, nothing dropped since last report",
                "{n} byte(s) dropped since last report: the decoder fell "
                f"{snap.link_values.get('queue_max_bytes', '?')} bytes behind the port (oldest dropped, newest kept)")

        # frames
        frame_vals = {"frame_rate_hz": round(rate, 3), **dec, "samples": core.get("samples", 0),
                      "imu_published": core.get("imu_published", 0)}
        problems = {k: delta(dec, pdec, k) for k in ("crc_errors", "lost_frames", "invalid_frames", "unsupported_version")}
        bad = {k: v for k, v in problems.items() if v > 0}
        if bad:
            level, msg = WARN, "since last report: " + ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in bad.items())
        else:
            level, msg = OK, f"{rate:.1f} frames/s, no errors since last report"
        entries.append(self._entry(level, "frames", msg, frame_vals))

        counted(delta(dec, pdec, "resets"), WARN, "board resets",
                {"resets": dec.get("resets", 0), "duplicates": dec.get("duplicates", 0)},
                "no reset since last report", "board reset {n} time(s) since last report")
        core_counted("adc_saturated", WARN, "ADC saturation", "no saturated sample since last report",
                     "{n} sample(s) with an ADC channel at full scale (4095) since last report; variance inflated")
        core_counted("reference_low", ERROR, "reference power", "reference power sufficient",
                     "reference power too low in {n} sample(s) since last report; acceleration not published for them")
        # reference power off the level the calibration's fit saw at this temperature (eq. 24 extrapolating)
        core_counted("reference_level_changed", WARN, "reference level", "reference counts at the calibrated level",
                     "{n} sample(s) since last report with the reference counts off the calibration's level at their "
                     "temperature (source power, connector or fibre loss): the output may be biased, covariance inflated",
                     tolerance=_fmt(snap.reference_level_tolerance))

        # temperature sensor
        t_vals = {
            "temperature_invalid": core.get("temperature_invalid", 0),
            "temperature_held": core.get("temperature_held", 0),
            "temperature_stale_dropped": core.get("temperature_stale_dropped", 0),
            "last_good_temperature_c": _fmt(snap.last_temperature_c),
            "seconds_since_valid": _fmt(snap.temperature_age_s),
            "hold_s": snap.temperature_hold_s,
        }
        age = snap.temperature_age_s
        if snap.temperature_valid is None:
            level, msg = STALE, "no frame received yet"
        elif snap.temperature_valid:
            level, msg = OK, "valid"
        elif age is None:
            level, msg = ERROR, "temperature sensor invalid, no valid reading yet: acceleration not published"
        elif age > snap.temperature_hold_s:
            level = ERROR
            msg = f"temperature sensor invalid for {age:.1f} s (> hold {snap.temperature_hold_s:g} s): acceleration not published"
        else:
            level = WARN
            msg = f"temperature sensor invalid, holding last good value for {age:.1f} s (max {snap.temperature_hold_s:g} s)"
        entries.append(self._entry(level, "temperature sensor", msg, t_vals))

        # temperature range
        lo, hi = snap.temperature_range_c
        margin = snap.temperature_range_margin_c
        r_vals = {"calibrated_min_c": lo, "calibrated_max_c": hi, "margin_c": margin,
                  "temperature_out_of_range": core.get("temperature_out_of_range", 0), **snap.calibration}
        t = snap.last_temperature_c
        oor = delta(core, pcore, "temperature_out_of_range")
        inside_lo, inside_hi = widened_range((lo, hi), margin)
        if t is not None and not inside_lo <= t <= inside_hi:
            level = WARN
            msg = f"temperature {t:.2f} degC outside calibrated range [{lo:g}, {hi:g}] degC: extrapolating, covariance inflated"
        elif oor > 0:
            level, msg = WARN, f"{oor} sample(s) outside calibrated range [{lo:g}, {hi:g}] degC since last report"
        else:
            level, msg = OK, "inside calibrated range"
        entries.append(self._entry(level, "temperature range", msg, r_vals))

        # correction terms held at the edge of the span they were fitted on (time drift, spectral non-linearity)
        core_counted("correction_out_of_span", WARN, "correction span", "every correction term inside its fitted span",
                     "{n} sample(s) since last report outside the span a correction term was fitted on: the term is held "
                     "at the span's edge, covariance inflated")
        # calibrated output: the last guard of DriverCore (a validated calibration should never trip it);
        # chain_priming: first samples after a (re)start with 'equalise'
        core_counted("non_finite_dropped", ERROR, "calibrated output", "no non-finite output since last report",
                     "{n} sample(s) dropped since last report: the calibration gave a non-finite acceleration",
                     **{k: core.get(k, 0) for k in ("imu_published", "samples_calibrated", "decimation_discarded",
                                                    "decimation_gaps", "chain_priming")})

        # measuring-chain compensation (calibration's dynamic section)
        if snap.chain:
            c = snap.chain
            level = OK
            if c.get("dynamic_section") == "absent":
                msg = ("not compensated, lag unknown: the calibration has no dynamic section, so the published "
                       "acceleration lags its stamps by the measuring chain's delay, which the driver does not know "
                       "(about 0.1 s on the static-test build's 1-1.7 Hz TIA stages); while the input changes the "
                       "error exceeds the covariance (docs/topics.md)")
            elif c["mode"] == "none":  # a choice, stated with its cost
                msg = (f"not compensated: the published acceleration lags by about {c['group_delay_dc_ms_x']:g}/"
                       f"{c['group_delay_dc_ms_y']:g}/{c['group_delay_dc_ms_z']:g} ms (x/y/z, at DC)")
            else:
                msg = f"{c['mode']}: stamps moved back by {c['applied_delay_ms']:g} ms, bandwidth {c['bandwidth_hz']:g} Hz"
                helps = {ax: float(c[f"delay_helps_below_hz_{ax}"]) for ax in "xyz" if f"delay_helps_below_hz_{ax}" in c}
                if helps:  # delay mode: the DC shift over-corrects tones above a limit (ChainDynamics.delay_helps_below_hz)
                    ax, lim = min(helps.items(), key=lambda kv: kv[1])
                    msg += (f"; a correction below {lim:g} Hz only ({ax}; above it a tone's error is larger than "
                            "uncompensated)")
                    top = float(c.get("calibrated_band_max_hz", math.nan))
                    if math.isfinite(top) and lim < top:
                        level = WARN
                        msg += (f", inside the calibrated band (up to {top:g} Hz): for content above {lim:g} Hz use "
                                "chain_compensation equalise")
            if c.get("identified_per") == "axis":
                msg += ("; the dynamic section (format 1) was fitted per output axis, right only when the channels' "
                        "cut-offs are equal: re-run fbg-accel-calib dynamic for per-channel values")
            entries.append(self._entry(level, "chain compensation", msg, c))

        # the calibration's own uncertainty at the current Psi and temperature (J Sigma J^T)
        if snap.calibration_uncertainty:
            u = snap.calibration_uncertainty
            if u.get("coefficient_covariance") == "absent":
                msg = ("not known: the calibration file has no coefficient_covariance section (refit with this version "
                       "of fbg-accel-calib fit)" + ("" if "slow_sigma_x_mps2" in u else "; the covariance is the noise only"))
            elif "sigma_x_mps2" not in u:
                msg = "no calibrated sample yet"
            else:
                msg = (f"{u['sigma_x_mps2']:.3g}/{u['sigma_y_mps2']:.3g}/{u['sigma_z_mps2']:.3g} m/s^2 (x/y/z, 1 sigma) "
                       f"at {u['temperature_c']:.2f} degC, a bias common to all samples; "
                       + ("included in" if u["included_in_covariance"] else "not included in")
                       + " linear_acceleration_covariance")
            if "slow_sigma_x_mps2" in u:
                unstated = u.get("unstated_run_to_run_sigma_mps2")
                msg += (f"; slow error of a still mean {u['slow_sigma_x_mps2']:.3g}/{u['slow_sigma_y_mps2']:.3g}/"
                        f"{u['slow_sigma_z_mps2']:.3g} m/s^2 (x/y/z, 1 sigma, a bias)"
                        + (f" plus {unstated:.3g} m/s^2 per axis for the run-to-run part the file does not state (one "
                           "run per temperature level)" if unstated else "") + ", "
                        + ("included in" if u["included_in_covariance"] else "not included in")
                        + " linear_acceleration_covariance")
            entries.append(self._entry(OK, "calibration uncertainty", msg, u))

        # the live gravity check: |a| of each still stretch against local gravity (gravity_check)
        if snap.gravity:
            entries.append(self._gravity_entry(snap.gravity, prev.gravity if prev else {}))

        # the board clock's mapping onto ROS time (clock_sync): a drift estimate at its clamp means it is not tracking
        if snap.clock:
            c = snap.clock
            clock = f"board clock {c['board_clock_ppm']:+g} ppm against the host's steady clock"
            jumps = {k: delta(c, prev.clock if prev else {}, k) for k in ("ros_time_steps", "mapping_steps", "held_stamps")}
            if c["drift_at_limit"]:
                level, msg = WARN, (f"{clock}, at the limit of the drift estimate: the board clock or the link is not "
                                    "what the estimator assumes, the stamps may drift from the sampling times")
            elif any(v > 0 for v in jumps.values()):
                level, msg = WARN, (f"{clock}; since the last report the stamps stepped: {jumps['ros_time_steps']} "
                                    f"step(s) of ROS time, {jumps['mapping_steps']} step(s) of the board clock mapping, "
                                    f"{jumps['held_stamps']} stamp(s) held 1 ns after the previous one because they "
                                    "would have gone back")
            else:
                level, msg = OK, f"{clock}; {c['restarts']} restart(s), {c['ros_time_steps']} step(s) of ROS time followed"
            entries.append(self._entry(level, "clock mapping", msg, c))

        self._prev = snap
        return entries

    def _gravity_entry(self, g: dict[str, Any], old: dict[str, Any]) -> DiagnosticEntry:
        if g["state"] == "off":
            return self._entry(OK, "gravity check", "off (gravity_mps2 is 0)", g)
        if "discrepancy_mps2" not in g:
            return self._entry(OK, "gravity check", f"no still stretch of {g['period_s']:g} s yet "
                               f"({'still now' if g['still'] else 'not still'})", g)
        new_failures = int(g["failures"]) - int(old.get("failures", 0))
        allow = float(g.get("unstated_slow_error_mps2", 0.0))
        unstated = f" + {allow:g} for the slow error the calibration does not state" if allow else ""
        figures = (f"|a| - g = {g['discrepancy_mps2']:+.3f} m/s^2 over {g['period_s']:g} s still at "
                   f"{g['temperature_c']:.1f} degC, threshold {g['threshold_mps2']:.3f} m/s^2 (tolerance "
                   f"{g['tolerance_mps2']:g}{unstated} + {g['k_sigma']:g} sigma; sigma noise {g['sigma_noise_mps2']:.3f}, "
                   f"calibration {g['sigma_calibration_mps2']:.3f}, slow error {g.get('sigma_slow_mps2', 0.0):.3f})")
        if g.get("unseen_axes"):  # what one orientation cannot see (gravity_check: a drift perpendicular to gravity)
            figures += (f"; a bias on {g['unseen_axes']} is not seen from the orientations still so far (|a| changes by it "
                        "to second order only)")
        if g["last_failed"] or new_failures > 0:
            which = "the last still stretch" if g["last_failed"] else f"{new_failures} still stretch(es) since last report"
            return self._entry(WARN, "gravity check", f"calibration no longer holds ({which}): {figures}; recalibrate, "
                               "or estimate the drift with fbg-accel-calib field-check", g)
        return self._entry(OK, "gravity check", f"calibration holds: {figures}", g)

    def _entry(self, level: int, what: str, message: str, values: dict[str, Any]) -> DiagnosticEntry:
        return DiagnosticEntry(level, self._name(what), message, tuple((str(k), str(v)) for k, v in values.items()))


def calibration_uncertainty_values(point: tuple[float, float, float, float] | None, has_section: bool,
                                   included: bool, slow_sigma_mps2: Any = None,
                                   unstated_run_to_run_sigma_mps2: float = 0.0) -> dict[str, Any]:
    """The diagnostic's values from ``DriverCore.calibration_uncertainty()`` (``point``), whether the calibration has a
    ``coefficient_covariance`` section, whether the terms are in the published covariance, the ``slow_error``
    section's standard deviations (x, y, z m/s^2; None without the section) and the allowance (m/s^2, 1 sigma per axis)
    for the run-to-run part it does not state (``SlowErrorSection.unstated_run_to_run_sigma_mps2``; 0: none)."""
    slow: dict[str, Any] = {}
    if slow_sigma_mps2 is not None:
        slow = {f"slow_sigma_{a}_mps2": round(float(v), 6) for a, v in zip("xyz", slow_sigma_mps2, strict=True)}
        if unstated_run_to_run_sigma_mps2:
            slow["unstated_run_to_run_sigma_mps2"] = float(unstated_run_to_run_sigma_mps2)
    if not has_section:
        return {"coefficient_covariance": "absent", "included_in_covariance": included and bool(slow), **slow}
    out: dict[str, Any] = {"coefficient_covariance": "present", "included_in_covariance": included, **slow}
    if point is not None:
        out.update({"sigma_x_mps2": round(point[0], 6), "sigma_y_mps2": round(point[1], 6),
                    "sigma_z_mps2": round(point[2], 6), "temperature_c": round(point[3], 2)})
    return out


def _fmt(v: float | None) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "none"
    return f"{v:.3f}"
