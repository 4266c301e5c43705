"""The ADC's unequal code widths as a candidate of the diagnosis: a code table before eq. 24, tested on held-out visits.

The physical hypothesis: the ESP32's successive-approximation ADC reads each code over an input interval of its own
width (differential non-linearity, DNL; Espressif's ESP32 datasheet, "ADC characteristics": DNL up to +-7 LSB, INL up
to +-12 LSB at 12 bits), with a pattern periodic in the code (period 16: the converter's capacitor array repeats its
small-bit errors; ``adc_codes``). A code twice as wide pulls a visit's mean toward it, so a visit's output is off by a
fraction of a count in a way that depends on where its counts fall: an error of the orientation that no term of eq. 28
takes. The remedy is not a term but a table (``fbg_accel_driver.adc_code_table``): every count mapped to the centre of
its code's interval before eq. 24, by the driver as by the fit.

The candidate is judged like the library's (``diagnose``): its own held-out test against the model the diagnosis
ends with (held-out gain in noise-weighted MSE, paired by visit, one-sided signed-rank test, the step's rule: p below
its level and a gain of at least ``min_rel_gain``), with its physical bound, and a row in the report's step table.
What differs is where the table comes from: it is estimated from the counts (``adc_codes.recording_code_widths``,
the pattern pooled over the channels), so the visits held out are mapped through a table estimated without them (no
leak). It is tested once, on top of the final model
(the strictest place: it must gain beyond every effect added), and only when the whole recording shows a pattern at
all (the pattern's own test, ``CodeWidths.pattern_found``): a recording without one claims nothing and costs one fit.
A table is estimated without two of the diagnosis' folds at a time and predicts both (half the fits of a table per
fold, each still blind to the visits it predicts).

Bound: the fitted widths must be those of a converter within its datasheet: no width beyond 1 + ``DNL_MAX_LSB``
counts, and the table's integral non-linearity (a code's centre minus the code) within ``INL_MAX_LSB``; a fit beyond
is refused, whatever its gain (a pattern fitted to something that is not the converter).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from fbg_accel_driver.adc_code_table import ADC_CODES, AdcCodeTable

from ..fit.adc_codes import CHANNEL_NAMES, RecordingWidths, code_table, recording_code_widths
from .cv import CvResult, cross_validate
from .data import DiagnosisData, column_rms, finite_rows
from .design import Design, ModelSpec, build_design
from .search import CandidateResult, Refusal, _corr, paired_gain_test
from .search_lanes import beside, default_lane_count

NAME = "adc_code_widths"
TITLE = "unequal widths of the ADC's codes (a code table of the counts before eq. 24)"
DNL_MAX_LSB = 7.0  # Espressif ESP32 datasheet, ADC characteristics: DNL up to +-7 LSB (a width up to 8 counts)
INL_MAX_LSB = 12.0  # same table: INL up to +-12 LSB
# samples a table is estimated from at most (every k-th of the visits' samples above): a few hundred visits decide the
# pattern (the measured series: 145 visits, p = 2e-22); a long recording's millions of correlated samples add little
# and would cost seconds per fit
MAX_WIDTH_SAMPLES = 10_000
# samples the whole recording's test for a pattern is made on at most: every diagnosis of integer counts pays it, and
# 3000 samples find the measured pattern by far (1409 samples: p = 2e-22)
GATE_SAMPLES = 3_000
TABLE_FOLD_GROUP = 2  # folds left out of each table together (``code_width_step``)


@dataclass
class CodeWidthStep:
    """The candidate's evaluation on top of the final model (``code_width_step``)."""

    result: CandidateResult  # its row in the report's step table
    alpha_each: float  # the level it was tested at
    table: AdcCodeTable | None = None  # the whole recording's table, when the candidate is added
    design: Design | None = None  # the final model on the mapped counts (whole recording's table), when added
    cv: CvResult | None = None  # its fit, with the held-out residual of the per-fold tables, when added

    @property
    def added(self) -> bool:
        return self.result.significant


class _FoldTableHeldOut(CvResult):
    """A fit on the counts mapped through the whole recording's table, whose held-out residual is that of the folds'
    tables (each estimated without the visits it predicts): the after figures of a model with the table leak nothing."""

    def __init__(self, cv: CvResult, heldout: np.ndarray) -> None:
        self.__dict__.update(cv.__dict__)
        self._own_heldout = heldout

    @property
    def heldout(self) -> np.ndarray:
        return self._own_heldout


def _counts(data: DiagnosisData, idx: np.ndarray) -> np.ndarray:
    """(n, 4) the counts ref, x, y, z of the samples ``idx`` (indices or a mask of the recording's samples)."""
    return np.column_stack([data.ref[idx], data.xyz[idx]])


def width_rows(data: DiagnosisData) -> np.ndarray:
    """The samples the widths are estimated from: those fitted at a pose (still inputs)."""
    return data.use & (data.pose_id >= 0) & (data.group >= 0) & np.isfinite(data.ref) & finite_rows(data.xyz)


def pooled_widths(data: DiagnosisData, rows: np.ndarray) -> RecordingWidths:
    """``recording_code_widths`` pooled over the channels, of the samples ``rows`` (N,) bool alone. They are taken out
    first: the estimate reads nothing else (each visit's samples in time order), and its arrays of four channels are
    then of a few thousand samples, not of the recording's 10^6."""
    idx = np.flatnonzero(rows)
    return recording_code_widths(_counts(data, idx), data.group[idx], np.ones(len(idx), bool), per_channel=False)


def _integer_codes(data: DiagnosisData, rows: np.ndarray) -> bool:
    """Whether every count of the samples ``rows`` is an integer (an ADC code), channel by channel."""
    return all(np.all(c == np.round(c)) for c in (data.ref[rows], *(data.xyz[rows, j] for j in range(3))))


def _thinned(rows: np.ndarray, cap: int = MAX_WIDTH_SAMPLES) -> np.ndarray:
    idx = np.flatnonzero(rows)
    if len(idx) <= cap:
        return rows
    out = np.zeros_like(rows)
    out[idx[::math.ceil(len(idx) / cap)]] = True
    return out


def implausible(table: AdcCodeTable, pattern: np.ndarray) -> str:
    """Why a fitted pattern is not the converter's (empty if it is): a width beyond the datasheet's DNL, or an INL
    beyond its bound."""
    if np.max(pattern) > 1.0 + DNL_MAX_LSB:
        return (f"a width of {np.max(pattern):.2f} counts is beyond the ESP32's DNL of {DNL_MAX_LSB:g} LSB (a width of "
                f"{1 + DNL_MAX_LSB:g} counts)")
    inl = float(np.max(np.abs(table.centres - np.arange(ADC_CODES)[None, :])))
    if inl > INL_MAX_LSB:
        return f"an INL of {inl:.2f} counts is beyond the ESP32's {INL_MAX_LSB:g} LSB"
    return ""


def mapped_data(data: DiagnosisData, table: AdcCodeTable) -> DiagnosisData:
    """``data`` with its counts mapped to their codes' centres (``AdcCodeTable.map_counts``, the driver's mapping);
    its visits, folds and reference the same."""
    ref, xyz = table.map_counts(data.ref, data.xyz)
    return replace(data, ref=ref, xyz=xyz)


def fold_table(data: DiagnosisData, train: np.ndarray, source: str) -> AdcCodeTable:
    """The code table estimated from the samples ``train`` (N,) alone (the pooled pattern; nominal widths when
    ``train`` does not show one)."""
    return code_table(pooled_widths(data, _thinned(width_rows(data) & train)), {"source": source})


def code_width_step(data: DiagnosisData, spec: ModelSpec, fold: np.ndarray, weights: np.ndarray,
                    base_heldout: np.ndarray, alpha_each: float, min_rel_gain: float) -> CodeWidthStep:
    """The code-width candidate on top of ``spec`` (the final model; module docstring): ``fold`` (N,) the diagnosis's
    folds (-1: not fitted, -2: fitted, never held out), ``weights`` (3,) 1 / floor^2, ``base_heldout`` (N, 3) the
    final model's held-out residual on the same folds; the candidate is significant at ``alpha_each`` with a gain
    of at least ``min_rel_gain``."""
    out = CandidateResult(NAME, TITLE, True)
    step = CodeWidthStep(out, alpha_each)
    if not _integer_codes(data, width_rows(data)):
        out.applicable, out.reason = False, ("the counts are not integer codes (a code table already applied, or "
                                             "averaged data)")
        return step
    try:
        whole = pooled_widths(data, _thinned(width_rows(data), GATE_SAMPLES))
    except ValueError as exc:  # too few visits or codes: no estimate at all
        out.applicable, out.reason = False, str(exc).split(": ", 1)[-1]
        return step
    if whole.pooled is None:
        out.applicable, out.reason = False, whole.reasons.get("pooled", "no channel read two periods of codes")
        return step
    p = whole.pooled
    test = f"pattern of period {p.period} against equal widths chi2 = {p.chi2:.1f} on {p.dof} dof, p = {p.p_value:.2g}"
    if not p.pattern_found:  # nothing to map: every fold's table would be (nearly) nominal
        out.detail = f"no width pattern in this recording ({test}): nothing claimed"
        return step
    fit_rows = data.use & (fold != -1)
    K = int(fold[fold >= 0].max()) + 1 if np.any(fold >= 0) else 0
    heldout = np.full((len(fold), 3), np.nan)
    # one table for each pair of folds (2k, 2k + 1), estimated without either: fold f is predicted through the table of
    # its pair, which never saw its visits, while the model is fitted on the same training visits as the final model's
    # held-out residual (a fair pair); half the estimates of a table per fold
    pair = np.where(fold >= 0, fold // TABLE_FOLD_GROUP, -1)
    n_pairs = (K + TABLE_FOLD_GROUP - 1) // TABLE_FOLD_GROUP
    two = default_lane_count() > 1  # two tables at a time on a machine of two cores or more (the same results)
    tables: list[AdcCodeTable] = []
    for k in range(0, n_pairs, 2):
        later = beside(fold_table, data, fit_rows & (pair != k + 1), f"training visits of fold pair {k + 1}",
                       thread=two) if k + 1 < n_pairs else None
        tables.append(fold_table(data, fit_rows & (pair != k), f"training visits of fold pair {k}"))
        if later is not None:
            tables.append(later.result())
    for f in range(K):
        des = build_design(mapped_data(data, tables[f // TABLE_FOLD_GROUP]), spec)
        one = np.where(fold == f, 0, np.where(fold == -1, -1, -2))  # fold f held out, every other fitted row trained on
        at, res = cross_validate(des, fit_rows, one, weights).fold_heldout(0)
        heldout[at] = res
    rows = data.use & (fold >= 0) & finite_rows(base_heldout) & finite_rows(heldout)
    gain, pv, ng, out.detectable_gain = paired_gain_test(base_heldout, heldout, data.group, rows, weights, alpha_each)
    out.rel_gain, out.p_value, out.n_groups = gain, pv, ng
    out.heldout_rmse = column_rms(heldout[rows])
    change = base_heldout - heldout  # the change of the held-out prediction the table makes
    out.corr_with_residual = np.array([_corr(base_heldout[rows, j], change[rows, j]) for j in range(3)])
    table = code_table(whole, {})  # the pattern tested: its bound (the table the file would carry is made below)
    inl = table.centres - np.arange(ADC_CODES)[None, :]
    out.detail = (f"{test}; widths of k mod {p.period} = 0..{p.period - 1}: "
                  + " ".join(f"{w:.2f}" for w in p.pattern)
                  + f" counts; INL {np.ptp(inl[CHANNEL_NAMES.index('x')]):.2f} counts peak to peak; each fold "
                  "predicted through a table estimated without it")
    out.implausible = implausible(table, p.pattern)
    if out.implausible:
        out.detail += f"; REFUSED: {out.implausible}"
    out.significant = pv < alpha_each and gain >= min_rel_gain and not out.implausible
    if not out.significant:
        if not out.implausible:
            out.refuse(Refusal.NO_GAIN, f"the table's held-out gain {100 * gain:+.1f} % (p = {pv:.2g}) does not "
                       f"reach p < {alpha_each:.2g} with a gain of {100 * min_rel_gain:.0f} % or more")
        return step
    step.table = fold_table(data, fit_rows, "the diagnosed recording (fbg-accel-calib diagnose), its fitted visits")
    step.design = build_design(mapped_data(data, step.table), spec)
    step.cv = _FoldTableHeldOut(cross_validate(step.design, fit_rows, fold, weights), heldout)
    return step


def describe(step: CodeWidthStep) -> str:
    """The added table in one line (the report's "Added" entry)."""
    prov = step.table.provenance if step.table is not None else {}
    return ("counts mapped to the centres of their codes' intervals before eq. 24 (the calibration file's adc_codes "
            f"section; {prov.get('pattern', '')})")
