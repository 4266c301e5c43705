"""Text and markdown report and residual-versus-candidate plots of a diagnosis (matplotlib Agg).

Pure presentation of a :class:`fbg_accel_calibration.diagnosis.diagnose.DiagnosisResult`; no numbers are
computed here that the engine did not compute, except the conversion of the channel-offset
coefficient to counts (c0 = -M0^-1 k) for reading.
"""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2

from ..diagnosis.data import finite_rows
from ..diagnosis.diagnose import DiagnosisResult
from ..diagnosis.library import LIBRARY, library_by_name
from ..diagnosis.search import CandidateResult
from ..io.atomic_output import OutputSet, committed_outputs

AXES = "xyz"


def _v(a: np.ndarray | None, fmt: str = "{:.3f}") -> str:
    if a is None:
        return "-"
    return " / ".join("n/a" if not np.isfinite(x) else fmt.format(float(x)) for x in np.asarray(a, dtype=float).ravel())


def _p(p: float) -> str:
    return f"{p:.1e}" if p < 1e-3 else f"{p:.3f}"


def candidate_rows(cands: list[CandidateResult]) -> list[list[str]]:
    rows = []
    for i, c in enumerate(cands, 1):
        if not c.applicable:
            rows.append([str(i), c.name, "not testable", "-", "-", "-", "-", c.reason])
            continue
        rows.append([str(i), c.name, f"{100 * c.rel_gain:+.1f} %", _p(c.p_value), "yes" if c.significant else "no",
                     _v(c.heldout_rmse), _v(c.corr_with_residual, "{:+.2f}"), c.detail])
    return rows


CAND_HEAD = ["rank", "candidate", "held-out gain", "p (Wilcoxon, visits)", "significant",
             "held-out RMSE x/y/z [m/s^2]", "corr. with residual x/y/z", "fitted"]


def ordinal(k: int) -> str:
    """``k`` as an ordinal: 2nd, 3rd, 11th, 15th, 21st."""
    return f"{k}{'th' if 10 <= k % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(k % 10, 'th')}"


def _md_table(head: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def channel_offsets_counts(res: DiagnosisResult) -> np.ndarray | None:
    """Axis-channel offsets c0 (3,) in counts implied by a channel_offset term (k = -M0 c0)."""
    for term in res.calibration.corrections:
        if term.kind == "channel_offset":
            return -np.linalg.solve(res.calibration.M[0], term.coeff_mps2_counts)
    return None


def summary(res: DiagnosisResult, img_prefix: str = "img/", figures: str = "report") -> list[str]:
    """Bullet points: which effect, how it was traced, before/after per axis, floor, confounding, what remains; an
    added effect links its figure when ``figures`` (``FIGURES``) draws it."""
    out = []
    drawn = {c.name for c in plotted_candidates(res, figures)}
    if res.added:
        for name, _, desc in res.added:
            c = next((c for st in res.steps for c in st.candidates if c.name == name and st.chosen == name), None)
            how = ""
            if c is not None:
                how = (f"; traced by its held-out gain {100 * c.rel_gain:.1f} % (p = {_p(c.p_value)} over {c.n_groups} "
                       f"groups) and the correlation {_v(c.corr_with_residual, '{:+.2f}')} (x/y/z) of its contribution with "
                       "the residual" + (f", plot `{img_prefix}candidate_{name}.png`" if name in drawn else ""))
            conf = [c.b if c.a == name else c.a for st in res.steps if st.chosen == name for c in st.confounding
                    if c.verdict == "confounded" and name in (c.a, c.b)]
            if conf:
                how += (f". **Confounded with {', '.join(conf)} on this data: the data do not support choosing {name} "
                        f"over {', '.join(conf)}** (it was taken for its slightly larger held-out gain; see below)")
            out.append(f"- **Added: {name}** ({desc}){how}.")
    else:
        out.append("- **Nothing added**" + (" to the sensor model" if res.rig_terms or res.run_terms else
                                            ": no candidate improves the held-out error significantly") + ".")
    for name, _, desc in res.noise_remedies:
        out.append(f"- **Noise remedy: {name}** ({desc}): a filter, not a model effect; the floor of the filtered "
                   f"output is {_v(res.final_floor)} m/s^2.")
    for name, _, desc in res.run_terms:
        out.append(f"- **Per-run term: {name}** ({desc}): a property of these recordings, not of the sensor; fitted so "
                   "that it does not bias eq. 28, not in the calibration file. Expect a run of your own to carry a "
                   "term of this size that no calibration removes.")
    for name, _, desc in res.rig_terms:
        out.append(f"- **Rig property: {name}** ({desc}): the reference was corrected for it so that it does not bias "
                   "eq. 28; not in the calibration file.")
    out.append("- Held-out RMSE per axis x/y/z: before " + _v(res.before_heldout_rmse) + " m/s^2, after "
               + _v(res.after_heldout_rmse) + " m/s^2; noise floor " + _v(res.noise_floor) + " m/s^2.")
    out += [f"- **{'Out of reach' if f.kind == 'cannot_reveal' else 'Warning'}:** {f.text}." for f in res.findings]
    out.append(f"- Conditioning of the final model: condition number {res.condition_number:.3g} (scaled normal "
               "matrix)" + ("; largest |correlation| of each added effect's columns with the model's others: "
                            + ", ".join(f"{n} {c:.3f}" for n, c in res.column_correlation.items())
                            if res.column_correlation else "") + ".")
    for st in res.steps:
        for c in st.confounding:
            if c.verdict == "confounded":
                out.append(f"- **{c.a} and {c.b} are confounded on this data** (each adds nothing beyond the other; "
                           f"correlation of their contributions {c.corr_contributions:+.2f}). To separate them: "
                           f"{c.separating_measurement}.")
            elif abs(c.corr_contributions) > 0.7:
                out.append(f"- {c.a} and {c.b} look alike here (correlation of their contributions "
                           f"{c.corr_contributions:+.2f}) but the data tell them apart: {c.verdict} "
                           f"({c.b} on top of {c.a}: {100 * c.gain_b_beyond_a:+.1f} % held-out gain, p = {_p(c.p_b_beyond_a)}; "
                           f"{c.a} on top of {c.b}: {100 * c.gain_a_beyond_b:+.1f} %, p = {_p(c.p_a_beyond_b)}; an effect is "
                           f"kept only with p below the step's level and a gain of at least "
                           f"{100 * res.settings['min_rel_gain']:.0f} %). "
                           f"A measurement that would separate them cleanly: {c.separating_measurement}.")
    out.append(f"- What remains: {res.structure.verdict}.")
    return out


SIGNATURE_SE = 3.0  # a correlation of pose means this many standard errors (1/sqrt(visits - 1)) from 0 is a signature
ORIENTATION_SHARE = 0.5  # the orientation explains more than this share of the pose-mean variance
CONCENTRATED = 3.0  # one visit's |z| this many times the next one's (and above 5): the residual sits in that visit


def settling_measurements(res: DiagnosisResult) -> list[str]:
    """What would settle a significant unexplained residual: for each signature its pose means show (``ResidualStructure``:
    a slow change along the run, the temperature, the orientation, one visit) the measurement that tells its
    candidate causes apart, on the axes whose test is significant; [] when nothing significant remains."""
    s = res.structure
    if not s.significant:
        return []
    alpha = float(res.settings.get("alpha", 0.01))
    axes = [j for j in range(3) if s.pose_chi2_p[j] < alpha / 3]

    def on(mask: np.ndarray) -> list[int]:
        return [j for j in axes if bool(mask[j])]

    lim = SIGNATURE_SE / np.sqrt(max(len(s.per_pose) - 1, 1))  # a correlation's standard error under noise alone
    out, explained = [], set()
    # a function of time or of the temperature's history refused because a step of the response explains it
    # (diagnose.step_check): where it is, and what it was not
    steps: dict[float, tuple[CandidateResult, list[str]]] = {}
    for st in res.steps:
        for c in st.candidates:
            if c.step_check is not None and c.step_check.explained:
                known = library_by_name().get(c.name)
                what = known.sensor_property if known is not None and known.sensor_property else c.name
                seen = steps.setdefault(round(c.step_check.t_s, 3), (c, []))[1]
                if what not in seen:
                    seen.append(what)
    for c, what in steps.values():
        sc = c.step_check
        out.append(f"a step of the response {sc.when} explains the change along the run better "
                   f"than {' or '.join(what)}: look for what happened then (a connector knocked or re-mated, a fibre "
                   "moved, a knock), and visit the same poses before and after such a time")
    slow = on((s.serial_corr_pose_means > lim) | (np.abs(s.corr_time) > lim))
    if slow:
        out.append(f"a slow change along the run on {'/'.join(AXES[j] for j in slow)} (consecutive visit means "
                   "correlated, or a trend in time): log the chamber temperature and the source power (the reference "
                   "counts) with the series, and visit one pose again at the start, the middle and the end of the run: "
                   "a drift makes that pose read differently each time, an orientation effect does not")
    warm = on(np.abs(np.nan_to_num(s.corr_temperature)) > lim)
    if warm:
        out.append(f"it follows the temperature on {'/'.join(AXES[j] for j in warm)}: add chamber levels and hold each "
                   "longer (a lag shrinks with a slower ramp, a missing temperature term does not)")
    turned = on((s.orientation_r2 > ORIENTATION_SHARE) | (s.serial_corr_pose_means < -lim))
    if turned:
        out.append(f"it depends on the orientation on {'/'.join(AXES[j] for j in turned)} (explained by the reference "
                   "direction, or alternating from one visit to the next in the plan's order): visit the orientations "
                   "again in another order (an orientation effect repeats, a drift does not) and turn the sensor by 90 "
                   "degrees on the table (a table error stays with the table, a sensor error turns with the sensor)")
    again = on(s.same_pose_chi2_p < alpha / 3)
    if again:
        out.append(f"the same pose visited again reads differently on {'/'.join(AXES[j] for j in again)} (visits of one "
                   f"pose, the same table angles, {s.same_pose_span_s:.3g} s apart (median), differ beyond the noise): "
                   "only time sets them apart, neither the orientation nor the table's angles: a drift, a step (a "
                   "connector, a knock), the chamber or the source; log the chamber temperature and the source power "
                   "(the reference counts) with the series, and visit that pose again more often")
    table = on(s.other_pose_chi2_p < alpha / 3)
    if table:
        out.append(f"at one direction of gravity the visits disagree on {'/'.join(AXES[j] for j in table)} (poses of "
                   f"one direction at other table angles, {s.direction_span_s:.3g} s apart (median), differ beyond the "
                   "noise, which no model of the sensor does): turn the sensor by 90 degrees on the table and visit "
                   "each direction at several table angles in a random order; an error of the table's angles (an "
                   "encoder offset, axes not orthogonal, a tilted base) or a cable the table drags follows the table's "
                   "angles, a drift the clock")
    explained.update(slow + warm + turned + again + table)
    for j in axes:
        z = sorted((abs(float(p["z"][j])), i) for i, p in enumerate(s.per_pose))[::-1]
        if len(z) >= 2 and z[0][0] > 5 and z[0][0] > CONCENTRATED * z[1][0]:
            p = s.per_pose[z[0][1]]
            label = str(res.settings.get("time_label", "time [s]"))
            when = f"{p['t_s']:.4g} s from the first sample" if label.startswith("time") else f"{label} {p['t_s']:.4g}"
            out.append(f"on {AXES[j]} it sits in one visit (visit {p['visit']}, pose {p['pose']}, {when}, "
                       f"z = {float(p['z'][j]):+.1f}): visit that pose again, and look for what "
                       "happened then (a knock, the chamber door, a cable pulled, the start of the run)")
            explained.add(j)
    rest = [j for j in axes if j not in explained]
    if rest:
        out.append(f"no signature of time, temperature, orientation or one visit on {'/'.join(AXES[j] for j in rest)}: "
                   "run the whole plan again in a random pose order and see whether the visit means repeat")
    return out


def degree_table(table: list[dict], chosen: int | None, forced: bool = False) -> str:
    """Markdown table of a degree selection (eq. 28): RMSE / full scale per axis, in sample and held out. ``forced``:
    the degree ``chosen`` was given (``--degree``), not the rule's, whose note stands on the degree it chose."""
    rows = []
    for t in table:
        if not t["identified"]:
            rows.append([str(t["degree"]), "-", "-", t["note"]])
        else:
            words = [("chosen (given by --degree)" if forced else "chosen") if t["degree"] == chosen else "",
                     "the rule's choice" if forced and t.get("rule_choice") else "", str(t.get("note", ""))]
            rows.append([str(t["degree"]), _v(t["insample_rmse_fs"], "{:.2e}"), _v(t["heldout_rmse_fs"], "{:.2e}"),
                         "; ".join(w for w in words if w)])
    return _md_table(["degree n", "in-sample RMSE / 20 g (x/y/z)", "held-out RMSE / 20 g (x/y/z)", ""], rows)


def periodic_section(res: DiagnosisResult) -> list[str]:
    """Markdown lines on a periodic disturbance found in the visits (``periodic_disturbance``); none without one."""
    d = res.disturbance
    if not d.found:
        return []
    rows = [[f"{ln.freq_hz:.4g} Hz", *(f"{a:.4f}" for a in ln.amplitude_mps2), f"{ln.p_value:.2g}",
             f"visit-locked ({ln.visit_harmonic} / visit period)" if ln.visit_harmonic else ""] for ln in d.lines]
    out = ["## Periodic disturbance", "",
           "A sinusoidal line common to the visits, found in the within-visit residual of the settled samples "
           f"(periodogram against its local spectral level, {d.band_hz[0]:.3g}-{d.band_hz[1]:.3g} Hz searched, "
           f"Bonferroni over {d.n_tests} tests at alpha {d.alpha:g}; docs/effects.md). A table or chamber that sways, "
           "a fan or a pump moves the sensor: it is no noise of the sensor.", "",
           _md_table(["frequency", "amplitude x [m/s^2]", "amplitude y [m/s^2]", "amplitude z [m/s^2]", "p (corrected)",
                      "note"], rows), "",
           f"- noise floor without the disturbance: {_v(res.noise_floor)} m/s^2"
           + (f" (of the filtered output {_v(res.final_floor)} m/s^2)" if res.noise_floor_after is not None else "")
           + "; every ratio to the floor in this report is to a floor without it",
           f"- within-visit scatter with it (the floor it would have been): {_v(d.floor_with_lines)} m/s^2"]
    if d.heldout_without_lines is not None:
        out.append(f"- held-out RMSE {_v(res.after_heldout_rmse)} m/s^2 holds it; with the fitted lines taken out "
                   f"{_v(d.heldout_without_lines)} m/s^2")
    return [*out, ""]


def markdown(res: DiagnosisResult, command: str = "", img_prefix: str = "img/", figures: str = "report") -> str:
    """The markdown report; it links the figures that :func:`write_plots` draws with the same ``figures``
    (``FIGURES``) under ``img_prefix``, and no other."""
    s = res.structure
    lines = ["# Residual diagnosis", ""]
    if command:
        lines += ["Produced by:", "", "```", command, "```", ""]
    d = res.data
    lines += [f"Static samples used: {res.n_static} in {res.n_groups} visits (a visit: one contiguous static interval of "
              f"one pose within one run; {len(np.unique(d.pose_id[d.use & (d.pose_id >= 0)]))} distinct pose ids) "
              f"(selection: {res.settings['static']}), {res.settings['folds']}-fold cross-validation over visits"
              + (f" (candidates evaluated and the model chosen on {res.settings['search_rows']} evenly spread fitted "
                 f"samples, every {ordinal(res.settings['search_step'])}: they keep "
                 f"{100 * res.settings['search_information']:.0f} % of what a visit's samples tell of its mean, the "
                 "noise being correlated; the chosen model fitted on all)"
                 if res.settings.get("search_rows") else "") + ", "
              f"temperature levels: {res.n_levels} ({np.nanmin(d.temp_c[d.use]):.2f}-{np.nanmax(d.temp_c[d.use]):.2f} degC), "
              f"time span {d.duration_s:.4g} s.", ""]
    lines += ["## Summary", "", *summary(res, img_prefix, figures), ""]
    lines += ["## Declared model and degree (eq. 28)", ""]
    lines += [degree_table(res.degree_table, res.degree, bool(res.settings.get("degree_forced"))), ""]
    lines += ["Noise floor (per-sample standard deviation of the declared model's residual within visits over the "
              "settled samples, a straight line in time removed in every visit, corrected for what that removes of "
              f"correlated noise): **{_v(res.noise_floor)} m/s^2** (x/y/z), from {res.n_floor_samples} settled samples.",
              ""]
    if res.settling is not None:
        lines += ["Settling after a table move (an effect of its own, not in the floor): " + res.settling.summary() + ".", ""]
    lines += periodic_section(res)
    if res.fold_notes:
        lines += ["Cross-validation folds that could not be used as drawn:", "", *[f"- {n}" for n in res.fold_notes], ""]
    for st in res.steps:
        title = "on the declared model" if not st.model else "on top of " + " + ".join(st.model)
        lines += [f"## Step {st.step}: candidates {title}", "",
                  f"Significant = one-sided Wilcoxon p < {st.alpha_each:.2g} (alpha {res.settings['alpha']} / "
                  f"candidates tested) and held-out gain >= {100 * res.settings['min_rel_gain']:.0f} % of the "
                  "noise-weighted held-out MSE.", ""]
        lines += [_md_table(CAND_HEAD, candidate_rows(st.candidates)), ""]
        if st.confounding:
            lines += ["Confounding among the significant candidates (each added on top of the other):", ""]
            crow = [[c.a, c.b, f"{c.corr_contributions:+.2f}", f"{100 * c.gain_b_beyond_a:+.1f} %, p {_p(c.p_b_beyond_a)}",
                     f"{100 * c.gain_a_beyond_b:+.1f} %, p {_p(c.p_a_beyond_b)}", c.verdict,
                     c.separating_measurement if c.verdict == "confounded" or abs(c.corr_contributions) > 0.7 else ""]
                    for c in st.confounding]
            head = ["A", "B", "corr. of contributions", "B on top of A: gain, p", "A on top of B: gain, p", "verdict",
                    "measurement that separates them"]
            lines += [_md_table(head, crow), ""]
        lines += [f"Chosen: **{st.chosen or 'nothing (no significant candidate)'}**", ""]
        if st.degree_note:
            lines += [st.degree_note[0].upper() + st.degree_note[1:] + ".", "",
                      degree_table(st.degree_table, st.degree_after), ""]
        if st.removed_note:
            lines += [st.removed_note[0].upper() + st.removed_note[1:] + ".", ""]
        for c in st.candidates:
            if c.name == "channel_delay" and c.cross_correlation_delay_s is not None:
                lines += [f"Cross-correlation delay of the model output against the reference (finddelay): "
                          f"{c.cross_correlation_delay_s:.4g} s.", ""]
    lines += ["## Added to the model", ""]
    if res.added:
        for name, _, desc in res.added:
            lines.append(f"- **{name}**: {desc}")
        c0 = channel_offsets_counts(res)
        if c0 is not None:
            lines.append(f"- implied axis-channel offsets c0 = {_v(c0, '{:.1f}')} counts (x/y/z)")
    else:
        lines.append("- nothing: no candidate is significant; the declared model stands.")
    lines += ["", "## Before and after (held out, per axis)", ""]
    rows = []
    for j, a in enumerate(AXES):
        rows.append([a, f"{res.before_insample_rmse[j]:.3f}", f"{res.before_heldout_rmse[j]:.3f}",
                     f"{res.after_insample_rmse[j]:.3f}", f"{res.after_heldout_rmse[j]:.3f}", f"{res.final_floor[j]:.3f}",
                     f"{res.after_heldout_rmse[j] / res.final_floor[j]:.2f}",
                     f"{res.after_heldout_rmse[j] / FULL_SCALE_MPS2:.1e}"])
    lines += [_md_table(["axis", "before in-sample [m/s^2]", "before held-out [m/s^2]", "after in-sample [m/s^2]",
                         "after held-out [m/s^2]", "noise floor [m/s^2]", "after / floor", "after / 20 g"], rows), ""]
    if figures != "none":
        lines += [f"![before/after]({img_prefix}before_after.png)", ""]
    lines += ["## What remains", "", f"**{s.verdict}**", "",
              f"- pose-mean RMS of the held-out residual: {_v(s.pose_mean_rms)} m/s^2 (x/y/z)",
              f"- excess over the floor sqrt(RMSE^2 - floor^2): {_v(s.excess_rms)} m/s^2",
              f"- chi^2 p-value of the pose means against noise: {' / '.join(_p(p) for p in s.pose_chi2_p)} "
              f"(variance of a visit mean from the floor's autocorrelation: lag-1 {_v(s.lag1_autocorr, '{:.2f}')}, "
              f"integrated correlation time {_v(s.noise_corr_samples, '{:.1f}')} samples, known to "
              f"{_v(s.noise_mean_dof, '{:.0f}')} degrees of freedom, plus what the error of the coefficients that "
              "predict a held-out visit adds to its mean and the correlation it gives the visits: chi^2/df against "
              "F(df, dof), df by Satterthwaite)",
              (f"- noise slower than a visit (bias wander), in the test's null hypothesis: a visit mean's slow error "
               f"{_v(s.slow_sigma, '{:.3g}')} m/s^2 (x/y/z), from the scatter of {s.slow_revisits} revisits of a "
               "pose (the test is then of each pose's mean over its visits)" if s.slow_revisits else
               "- noise slower than a visit (bias wander): not in the test's null hypothesis, no pose is revisited "
               "in a run (a slow error cannot be told from an effect of the pose; revisit poses to separate them)"),
              f"- Spearman correlation of pose means with time: {_v(s.corr_time, '{:+.2f}')}, "
              f"with temperature: {_v(s.corr_temperature, '{:+.2f}')}",
              f"- correlation of consecutive pose means in time order (slow wander gives values near 1, a pose- or "
              f"angle-dependent effect values near 0 or below): {_v(s.serial_corr_pose_means, '{:+.2f}')}",
              f"- share of pose-mean variance explained by orientation (quadratic in the reference direction): "
              f"{_v(s.orientation_r2, '{:.2f}')}",
              f"- visits of one direction of gravity against each other (they disagree by what is not a function of "
              f"the orientation: table angles, a cable, time): chi^2 p {' / '.join(_p(p) for p in s.direction_chi2_p)} "
              f"over {s.direction_repeat_visits} visits in directions visited more than once "
              f"({s.direction_span_s:.3g} s apart, median); of it, visits of one pose (the same table angles, only "
              f"time between them): p {' / '.join(_p(p) for p in s.same_pose_chi2_p)}, poses of one direction at "
              f"other table angles: p {' / '.join(_p(p) for p in s.other_pose_chi2_p)}", ""]
    settle = settling_measurements(res)
    if settle:
        lines += [f"Measurements that would settle it (from the signatures above: a correlation beyond {SIGNATURE_SE:g} "
                  f"standard errors of noise alone, an orientation share above {ORIENTATION_SHARE:g}, visits of one "
                  f"direction that disagree, one visit above {CONCENTRATED:g}x the next):", "", *[f"- {m}" for m in settle], ""]
    held = {int(v): f"{h.channel} {h.code}" for h in res.held_codes for v in h.visits}  # the visits' ADC code (warning)
    rows = [[f"{p.get('visit', p['pose'])} / {p['pose']}", str(p["n"]),
             _v(p["mean_mps2"]), _v(p["z"], "{:+.1f}"), _v(p["gref_mps2"], "{:.2f}"),
             f"{p['t_s']:.4g}", f"{p['temp_c']:.2f}"] + ([held.get(int(p.get("visit", -1)), "-")] if held else [])
            for p in s.per_pose[:10]]
    lines += ["Visits with the largest residual (held out):", "",
              _md_table(["visit / pose", "n", "mean residual x/y/z [m/s^2]", "z-score x/y/z", "reference x/y/z [m/s^2]",
                         res.settings.get("time_label", "time [s]"), "temp [degC]"]
                        + (["held on ADC code"] if held else []), rows), ""]
    if figures != "none":
        lines += [f"![residual structure]({img_prefix}residual_structure.png)", ""]
    if res.moving_residual_rms is not None:
        lines += [f"Samples not used (moving or settling), final model against the time-interpolated reference: "
                  f"RMS {_v(res.moving_residual_rms)} m/s^2 (these carry table motion, not calibration error).", ""]
    lines += [f"Driver check: `ThermalCalibration.apply_counts` with the added terms, streamed with state, reproduces "
              f"the fit's prediction to {res.consistency_max_abs_mps2:.1e} m/s^2.", ""]
    lines += ["## Residual versus candidates", ""]
    drawn = plotted_candidates(res, figures)
    left = [c.name for c in plotted_candidates(res, "all") if c.name not in {d.name for d in drawn}]
    if left:  # figures not drawn: say which and how to draw them
        head = ("No figures drawn (`--figures none`)" if figures == "none" else
                "Figures of the candidates the summary names" + ("" if drawn else ": none"))
        lines += [f"{head}; not drawn: {', '.join(left)} (`--figures all` draws every candidate's).", ""]
    for c in drawn:
        lines += [f"![{c.name}]({img_prefix}candidate_{c.name}.png)", ""]
    return "\n".join(lines) + "\n"


def text(res: DiagnosisResult) -> str:
    out = [f"declared model: eq. 28, degree {res.degree} ({res.n_levels} temperature level(s)); "
           f"{res.n_static} static samples, {res.n_groups} visits",
           f"noise floor x/y/z: {_v(res.noise_floor)} m/s^2 (settled samples, within visits)"]
    if res.settling is not None:
        out.append(res.settling.summary())
    out += [f"folds: {n}" for n in res.fold_notes]
    for st in res.steps:
        out.append(f"step {st.step} (model: {' + '.join(['eq28', *st.model])}):")
        out.append("  " + " | ".join(CAND_HEAD))
        for row in candidate_rows(st.candidates):
            out.append("  " + " | ".join(row))
        for c in st.confounding:
            out.append(f"  confounding {c.a} / {c.b}: corr {c.corr_contributions:+.2f}, "
                       f"{c.b} on top: {100 * c.gain_b_beyond_a:+.1f} % p {c.p_b_beyond_a:.2g}, "
                       f"{c.a} on top: {100 * c.gain_a_beyond_b:+.1f} % p {c.p_a_beyond_b:.2g}: {c.verdict}")
        out.append(f"  chosen: {st.chosen or 'nothing'}")
        if st.degree_note:
            out.append(f"  {st.degree_note}")
        if st.removed_note:
            out.append(f"  {st.removed_note}")
    out.append("added: " + (", ".join(f"{n} ({d})" for n, _, d in res.added) if res.added else "nothing"))
    for n, _, d in res.noise_remedies:
        out.append(f"noise remedy: {n} ({d}); floor of the filtered output {_v(res.final_floor)} m/s^2")
    for n, _, d in res.run_terms:
        out.append(f"per-run term (fitted, not in the calibration file): {n} ({d})")
    for n, _, d in res.rig_terms:
        out.append(f"rig property (fitted, not in the calibration file): {n} ({d})")
    for j, a in enumerate(AXES):
        out.append(f"axis {a}: held-out RMSE before {res.before_heldout_rmse[j]:.3f} -> after {res.after_heldout_rmse[j]:.3f} "
                   f"m/s^2, noise floor {res.final_floor[j]:.3f} m/s^2")
    out += [f"{'OUT OF REACH' if f.kind == 'cannot_reveal' else 'WARNING'}: {f.text}" for f in res.findings]
    out.append(f"condition number of the final model {res.condition_number:.3g}"
               + "".join(f"; {n}: max |corr| with the model {c:.3f}" for n, c in res.column_correlation.items()))
    out.append(res.structure.verdict)
    out += [f"to settle it: {m}" for m in settling_measurements(res)]
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------- plots
# What a figure costs is its axes, ticks and text, not its points: drawn at 80 dpi (10-point text 11 pixels high), at
# most PLOT_TICKS + 1 ticks an axis (each tick is a line, a label and their layout), the PNG compressed at zlib level 1
# (faster to write than the default 6, the files somewhat larger).
PLOT_DPI = 80
PLOT_TICKS = 4
PNG_OPTIONS = {"compress_level": 1}
# the PNG text chunk "Software" of every figure a diagnosis writes: a re-run removes its earlier figures that the new
# report does not show, and only those (``stale_figures``), never a file of another writer under one of their names
FIGURE_SOFTWARE = "fbg-accel-calib diagnose"
# matplotlib's settings while the figures are drawn: glyphs rendered unhinted (matplotlib's default, FreeType's
# autohinter, redoes its work for every glyph drawn; at 80 dpi the text reads the same).
PLOT_RC = {"text.hinting": "no_hinting"}
# The grid (columns, rows) a scatter series is thinned on: finer than any panel's pixels at PLOT_DPI (the widest panel,
# a third of a 15-inch figure, is under 400 pixels wide and 250 high), so a sample left out falls within a pixel of
# one drawn: 10^6 points show nothing more than the few thousand cells they occupy, and cost seconds to draw.
PLOT_GRID = (512, 384)


def plotted(idx: np.ndarray, x: np.ndarray, y: np.ndarray, grid: tuple[int, int] = PLOT_GRID) -> np.ndarray:
    """The samples ``idx`` (indices into ``x`` and ``y``, in order) of a scatter of ``y`` against ``x`` that are drawn:
    the first of them in each occupied cell of ``grid`` (columns, rows) spanning the series' finite range, in their
    order; the non-finite ones left out."""
    xs, ys = x[idx], y[idx]
    ok = np.isfinite(xs) & np.isfinite(ys)
    idx, xs, ys = idx[ok], xs[ok], ys[ok]
    if len(idx) == 0:
        return idx

    def cell(v: np.ndarray, n: int) -> np.ndarray:
        lo, span = float(np.min(v)), float(np.max(v)) - float(np.min(v))
        if not span > 0:
            return np.zeros(len(v), np.int64)
        return np.minimum(((v - lo) * (n / span)).astype(np.int64), n - 1)

    _, first = np.unique(cell(xs, grid[0]) * grid[1] + cell(ys, grid[1]), return_index=True)
    return idx[np.sort(first)]


FIGURES = ("report", "all", "none")  # which figures a report draws and links (``--figures``); the first the default


def named_effects(res: DiagnosisResult) -> set[str]:
    """The effects the report's summary names as taken into the fit or kept out of it: the added terms, the noise
    remedies, the per-run and rig terms, the stand-ins not claimed and the effects confounded with another."""
    names = {n for n, _, _ in (*res.added, *res.noise_remedies, *res.run_terms, *res.rig_terms)}
    names |= {f.effect for f in res.findings if f.kind == "stand_in"}
    return names | {e for st in res.steps for c in st.confounding if c.verdict == "confounded" for e in (c.a, c.b)}


def plotted_candidates(res: DiagnosisResult, figures: str = "report") -> list[CandidateResult]:
    """The candidates whose residual-versus-contribution figure (``candidate_<name>.png``) the report links and
    :func:`write_plots` draws, of those of the first step with a contribution: the ones the summary names
    (:func:`named_effects`) for ``figures`` "report", all for "all", none for "none"."""
    if figures not in FIGURES:
        raise ValueError(f"figures must be one of {', '.join(FIGURES)}, got {figures!r}")
    if figures == "none":
        return []
    named = named_effects(res) if figures == "report" else None
    return [c for c in res.ranked if c.applicable and c.delta is not None and (named is None or c.name in named)]


class _Panels:
    """The report's figures drawn one after another on one figure of the Agg canvas (no pyplot state): each
    :meth:`layout` takes the panels it needs from those of the figures before it (an axis and its ticks are made once,
    not once per figure), places them by fixed margins (fractions of the figure) instead of a tight layout that renders
    every label to measure it, clears what the figure before drew and hides the panels it does not use. Each axis has
    at most ``PLOT_TICKS`` intervals."""

    def __init__(self) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        self.fig = Figure(dpi=PLOT_DPI)
        FigureCanvasAgg(self.fig)
        self.axes: list = []
        self.extra: list = []  # the current figure's own artists beside its panels (notes, a colour bar's axis)

    def layout(self, rows: int, cols: int, size_in: tuple[float, float], **margins: float) -> np.ndarray:
        """``rows`` x ``cols`` empty panels (an array of axes) on the figure, resized to ``size_in`` inches."""
        from matplotlib.gridspec import GridSpec

        for artist in self.extra:
            artist.remove()
        self.extra = []
        self.fig.set_size_inches(size_in)
        self.fig.suptitle("")
        grid = GridSpec(rows, cols, figure=self.fig, **margins)
        while len(self.axes) < rows * cols:
            self.axes.append(self.fig.add_subplot(grid[len(self.axes) // cols, len(self.axes) % cols]))
            self.axes[-1].locator_params(nbins=PLOT_TICKS)
        for k, ax in enumerate(self.axes):
            ax.set_visible(k < rows * cols)
            if k < rows * cols:
                ax.set_subplotspec(grid[k // cols, k % cols])
            for artist in (*ax.lines, *ax.collections, *ax.patches, *ax.texts):
                artist.remove()
            if ax.legend_ is not None:
                ax.legend_.remove()
            ax.set_title("")
            ax.set_xlabel("")
            ax.set_ylabel("")
            ax.set_prop_cycle(None)  # the first series of each figure in the first colour of the cycle
            ax.relim()
        return np.array(self.axes[: rows * cols], dtype=object).reshape(rows, cols)


def _thinning_note(panels: _Panels, y: float) -> None:
    """Says on the figure, at its right edge and height ``y`` (a fraction of the figure), how its scatters are thinned
    (``plotted``)."""
    panels.extra.append(panels.fig.text(
        0.995, y, f"dots: one sample per occupied cell of a {PLOT_GRID[0]} x {PLOT_GRID[1]} grid over a panel",
        ha="right", va="top" if y > 0.5 else "bottom", fontsize=7))


def _scatter(ax, x: np.ndarray, y: np.ndarray, idx: np.ndarray, **kw) -> None:
    """``y[idx]`` against ``x[idx]`` as dots, a sample per occupied cell of ``PLOT_GRID`` (``plotted``)."""
    shown = plotted(idx, x, y)
    ax.plot(x[shown], y[shown], ".", ms=2, **kw)


def write_plots(res: DiagnosisResult, out_dir: str | Path, figures: str = "report") -> list[Path]:
    """The PNG figures the report links (``markdown`` with the same ``figures``) into ``out_dir``:
    ``candidate_<name>.png`` for each of :func:`plotted_candidates`, ``before_after.png`` and
    ``residual_structure.png``, none for ``figures`` "none"; returns their paths."""
    cands = plotted_candidates(res, figures)
    if figures == "none":
        return []
    return _draw_plots(res, Path(out_dir), cands)


def _draw_plots(res: DiagnosisResult, out_dir: Path, cands: list[CandidateResult]) -> list[Path]:
    """:func:`write_plots` of the candidates ``cands``."""
    from matplotlib import rc_context

    out_dir.mkdir(parents=True, exist_ok=True)
    d = res.data
    r = d.use & finite_rows(res.residual_before)
    ri = np.flatnonzero(r)
    written: list[Path] = []

    panels = _Panels()
    fig = panels.fig

    def save(name: str) -> None:
        written.append(out_dir / name)
        with rc_context(PLOT_RC):  # the text is laid out and rendered when the figure is drawn, here
            fig.savefig(written[-1], dpi=PLOT_DPI, pil_kwargs=PNG_OPTIONS, metadata={"Software": FIGURE_SOFTWARE})

    # candidates: residual of the current model (held out) against the candidate's contribution. One figure, its
    # artists given each candidate's data in turn: its axes and ticks are made once, not once per candidate.
    if cands:
        axs = panels.layout(1, 4, (15, 3.6), left=0.05, right=0.99, bottom=0.15, top=0.83, wspace=0.33)[0]
        dots = [axs[j].plot([], [], ".", ms=2, alpha=0.4)[0] for j in range(3)]
        diagonal = [axs[j].plot([], [], "k--", lw=0.8)[0] for j in range(3)]
        for j in range(3):
            axs[j].set_xlabel(f"candidate contribution {AXES[j]} [m/s^2]")
            axs[j].set_ylabel(f"held-out residual {AXES[j]} [m/s^2]")
        profile = axs[3].plot([], [], "o-")[0]
        chosen = axs[3].axvline(0.0, color="r", lw=0.8)
        axs[3].set_ylabel("weighted training RSS")
        _thinning_note(panels, 0.995)
    for c in cands:
        # evaluated on the search's samples (search_samples: the fitted ones, or every k-th): those plotted
        delta = c.delta_of_every_sample(len(d.t_s))
        for j in range(3):
            shown = plotted(ri, delta[:, j], res.residual_before[:, j])
            dots[j].set_data(delta[shown, j], res.residual_before[shown, j])
            lim = np.nanmax(np.abs(delta[r, j])) if np.any(r) else 1
            diagonal[j].set_data([-lim, lim], [-lim, lim])
            axs[j].set_title(f"corr {c.corr_with_residual[j]:+.2f}", y=1.0)  # no ticks on top: no measuring
        axs[3].set_visible(bool(c.hyper_profile))
        if c.hyper_profile:
            h, v = np.array(c.hyper_profile).T
            profile.set_data(h, v)
            chosen.set_visible(c.hyper is not None)
            if c.hyper is not None:
                chosen.set_xdata([c.hyper, c.hyper])
            eff = library_by_name().get(c.name)
            axs[3].set_xlabel(f"{eff.hyper_name} [{eff.hyper_unit}]" if eff is not None and eff.hyper_name else "hyper-parameter")
        for ax in axs:
            ax.relim(visible_only=True)
            ax.autoscale_view()
        fig.suptitle(f"{c.name}: held-out gain {100 * c.rel_gain:+.1f} %, p = {_p(c.p_value)}")
        save(f"candidate_{c.name}.png")

    # before / after
    t = d.t_s - float(np.min(d.t_s))  # the time axis starts at the first sample, as the tables (a CSV: epoch seconds)
    axs = panels.layout(2, 3, (15, 6.5), left=0.05, right=0.99, bottom=0.1, top=0.91, wspace=0.25, hspace=0.3)
    ra = np.flatnonzero(r & finite_rows(res.residual_after))
    for j in range(3):
        ax = axs[0, j]
        _scatter(ax, t, res.residual_before[:, j], ri, alpha=0.5, label="declared model (held out)")
        _scatter(ax, t, res.residual_after[:, j], ra, alpha=0.5, label="with added effects (held out)")
        ax.axhline(res.noise_floor[j], color="k", lw=0.6, ls=":")
        ax.axhline(-res.noise_floor[j], color="k", lw=0.6, ls=":")
        ax.set_xlabel(res.settings.get("time_label", "time [s]"))
        ax.set_ylabel(f"residual {AXES[j]} [m/s^2]")
        if j == 0:  # the same two series in every panel: one legend
            ax.legend(fontsize=7)
        ax = axs[1, j]
        _scatter(ax, d.ref, res.residual_before[:, j], ri, alpha=0.5, label="declared model")
        _scatter(ax, d.ref, res.residual_after[:, j], ra, alpha=0.5, label="with added effects")
        ax.set_xlabel("reference counts")
        ax.set_ylabel(f"residual {AXES[j]} [m/s^2]")
    _thinning_note(panels, 0.003)
    fig.suptitle("held-out residual before/after; dotted: ± noise floor. RMSE x/y/z before "
                 f"{_v(res.before_heldout_rmse)} -> after {_v(res.after_heldout_rmse)} m/s^2")
    save("before_after.png")

    # structure of what remains: pose means vs time, temperature and orientation
    from matplotlib.ticker import MaxNLocator

    s = res.structure
    pm = np.array([q["mean_mps2"] for q in s.per_pose])
    pt = np.array([q["t_s"] for q in s.per_pose])
    pT = np.array([q["temp_c"] for q in s.per_pose])
    pg = np.array([q["gref_mps2"] for q in s.per_pose])
    axs = panels.layout(3, 3, (15, 9), left=0.05, right=0.92, bottom=0.06, top=0.94, wspace=0.3, hspace=0.3)
    # the orientation panels share one colour scale, symmetric about 0 (white) and the same on x/y/z: one colour bar
    top = float(np.nanmax(np.abs(pm))) if np.any(np.isfinite(pm)) else 1.0
    top = top if top > 0 else 1.0
    for j in range(3):
        axs[0, j].plot(pt, pm[:, j], "o", ms=3)
        axs[0, j].set_xlabel(res.settings.get("time_label", "time [s]"))
        axs[1, j].plot(pT, pm[:, j], "o", ms=3)
        axs[1, j].set_xlabel("temperature [degC]")
        sc = axs[2, j].scatter(pg[:, 0], pg[:, 1], c=pm[:, j], cmap="coolwarm", vmin=-top, vmax=top, s=18)
        axs[2, j].set_xlabel(f"reference x [m/s^2]; colour: pose-mean residual {AXES[j]}")
        axs[2, j].set_ylabel("reference y [m/s^2]")
        for i in range(2):
            axs[i, j].set_ylabel(f"pose-mean residual {AXES[j]} [m/s^2]")
            axs[i, j].axhline(0, color="k", lw=0.5)
    panels.extra.append(fig.add_axes((0.935, 0.06, 0.008, 0.22)))
    bar = fig.colorbar(sc, cax=panels.extra[-1], label="pose-mean residual [m/s^2]")
    bar.locator = MaxNLocator(PLOT_TICKS)
    fig.suptitle(s.verdict[:150])
    save("residual_structure.png")
    return written


def figure_files() -> tuple[str, ...]:
    """Every name a figure of a diagnosis may have (:func:`write_plots`): the before/after, the residual's structure
    and each library candidate's."""
    return ("before_after.png", "residual_structure.png", *(f"candidate_{e.name}.png" for e in LIBRARY))


def png_software(path: Path) -> str | None:
    """The "Software" text of the PNG file ``path`` (its chunks before the image data), None when it has none or is
    no PNG."""
    with contextlib.suppress(OSError), open(path, "rb") as fh:
        if fh.read(8) != b"\x89PNG\r\n\x1a\n":
            return None
        while len(head := fh.read(8)) == 8:
            size, kind = struct.unpack(">I4s", head)
            if kind in (b"IDAT", b"IEND"):
                return None
            if kind == b"tEXt" and size <= 4096:
                key, _, value = fh.read(size).partition(b"\0")
                if key == b"Software":
                    return value.decode("latin-1")
                fh.seek(4, 1)  # its CRC
            else:
                fh.seek(size + 4, 1)
    return None


def stale_figures(img_dir: Path, shown: Iterable[str]) -> list[Path]:
    """The figures in ``img_dir`` that a diagnosis wrote (:data:`FIGURE_SOFTWARE`, under one of
    :func:`figure_files`' names) and that are not ``shown``: beside a new report that does not link them they would
    be taken for its own. Any other file there is the user's: never listed."""
    shown = set(shown)
    return [img_dir / n for n in figure_files() if n not in shown and (img_dir / n).is_file()
            and png_software(img_dir / n) == FIGURE_SOFTWARE]


def write_report(res: DiagnosisResult, md_path: str | Path, img_dir: str | Path | None = None, command: str = "",
                 outs: OutputSet | None = None, figures: str = "report") -> list[Path]:
    """Markdown report at ``md_path`` with its PNGs in ``img_dir`` (default: ``<md dir>/img``; those of ``figures``,
    ``FIGURES``), staged in ``outs`` (``atomic_output``: renamed with the run's other outputs when it commits), or
    committed here together. The figures of an earlier diagnosis in ``img_dir`` that this report does not show are
    removed when it commits (``stale_figures``): the directory then holds the report's figures and the user's files."""
    import os
    import tempfile

    if outs is None:
        with committed_outputs() as own:
            return write_report(res, md_path, img_dir, command, own, figures)
    md_path = Path(md_path)
    img_dir = Path(img_dir) if img_dir is not None else md_path.parent / "img"
    written: list[Path] = []
    if figures != "none":
        outs.directory(img_dir)  # the plots are drawn in it first (made with the outputs: gone again if they fail)
        with tempfile.TemporaryDirectory(dir=img_dir, prefix=".plots.") as tmp_dir:
            for p in write_plots(res, tmp_dir, figures):
                os.replace(p, outs.path(img_dir / p.name))
                written.append(img_dir / p.name)
    for stale in stale_figures(img_dir, (p.name for p in written)):
        outs.remove(stale)
    rel = os.path.relpath(img_dir, md_path.parent).replace(os.sep, "/")
    outs.path(md_path).write_text(markdown(res, command, img_prefix=f"{rel}/", figures=figures), encoding="utf-8")
    return [md_path, *written]
