"""Bounds of every number that enters the offline tools from outside (CLI options, CSV columns, MCAP and bag values).

Pure Python and numpy. Each bound is what the instrument or the file format can physically hold; a value
outside it is a typo or a corrupted file, and accepting it would write wrong calibrations with exit 0:
``--g -9.81`` inverts the calibration, ``--g nan`` makes every sample "moving",
``--level-gap -1`` splits one temperature into 31 "levels" and defeats the over-fitting guard,
``--alpha nan`` flips the diagnosis' verdict, counts of 60880 cannot come from a 12-bit ADC.

The argparse ``type=`` factories below turn a bad option into argparse's usage error (exit 2, one
line naming the option, the value and the accepted range); :func:`check_range` does the same for
CSV cells (the importer adds file and line).

The samples themselves, whatever route brought them (a CSV, an MCAP, a rosbag2 bag), go through one check
before the fit sees them (:class:`SampleCheck`, applied by ``fit_stream.prepare_stream``): counts, temperature,
temperature spikes, the reference's magnitude. A bad sample is dropped and counted, not its file: one count of
1e308 made a whole file vanish from the fit (its moving variances overflowed), and the CSV importer refuses such
rows with the same words (:func:`count_problem`, :func:`temperature_unit_hint`).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from fbg_accel_driver.frame_codec import ADC_MAX
from fbg_accel_driver.sensor_constants import (
    FULL_SCALE_MPS2,  # noqa: F401  (iv.FULL_SCALE_MPS2 for the CSV bounds)
    GRAVITY_RANGE_MPS2,  # one bound for the tools and the driver's check
)

# AHT10 operating range -40 .. 85 degC (AHT10 datasheet, Aosong); the sensor cannot report outside it.
TEMPERATURE_RANGE_C = (-40.0, 85.0)
# a reference beyond the sensor's range (+-20 g, FULL_SCALE_MPS2) is not a table pose
# MCAP / ROS stamps of the recordings: builtin_interfaces/Time has an int32 second field, so board times
# must lie in 0 .. 2^31 - 1 s (68 years); a negative or larger time cannot be stored.
TIME_RANGE_S = (0.0, float(2**31 - 1))
POSE_ID_MAX = 2**31 - 1  # pose ids are int32 in the pose events
ANGLE_LIMIT_DEG = 360.0  # table angles psi/theta, degrees
MAX_DEGREE = 10  # temperature degree of eq. 28 (paper Table 4 goes to 6)
# largest degree scored when none is forced (fit, report, the node's refit): paper Table 4 goes up to n = 6.
# Here, not in fit_pipeline, so that the CLI's option defaults do not import the fit (~0.5 s at start-up).
DEFAULT_MAX_DEGREE = 6
if TYPE_CHECKING:  # numpy is imported where the samples are checked: the CLI's option parsing does not wait for it
    import numpy as np
RATE_RANGE_HZ = (1e-6, 1e6)


def check_range(name: str, value: float, lo: float, hi: float, unit: str = "") -> float:
    """``value`` if ``lo <= value <= hi`` (and finite), else ValueError naming ``name``, value and range."""
    if not (math.isfinite(value) and lo <= value <= hi):
        raise ValueError(f"{name} = {value:g} is outside {lo:g} .. {hi:g}{(' ' + unit) if unit else ''}")
    return value


def float_in(lo: float, hi: float, unit: str = "", *, lo_open: bool = False, hi_open: bool = False,
             what: str = "") -> Callable[[str], float]:
    """argparse type: a finite float in [lo, hi] (open ends with ``lo_open`` / ``hi_open``)."""
    left, right = ("(" if lo_open else "["), (")" if hi_open else "]")
    rng = f"{left}{lo:g}, {hi:g}{right}{(' ' + unit) if unit else ''}"

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number{what}; give a value in {rng}") from None
        ok = math.isfinite(v) and (lo < v if lo_open else lo <= v) and (v < hi if hi_open else v <= hi)
        if not ok:
            raise argparse.ArgumentTypeError(f"{text} is outside {rng}{what}")
        return v

    parse.__name__ = "number"
    return parse


def int_in(lo: int, hi: int, what: str = "") -> Callable[[str], int]:
    """argparse type: an integer in [lo, hi]."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer; give one in [{lo}, {hi}]{what}") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"{v} is outside [{lo}, {hi}]{what}")
        return v

    parse.__name__ = "integer"
    return parse


rate_hz = float_in(*RATE_RANGE_HZ, "Hz")
gravity_mps2 = float_in(*GRAVITY_RANGE_MPS2, "m/s^2", what=" (local gravity on the Earth's surface)")
temperature_c = float_in(*TEMPERATURE_RANGE_C, "degC", what=" (AHT10 range)")
level_gap_c = float_in(0.0, 100.0, "degC", lo_open=True)
skip_s = float_in(0.0, TIME_RANGE_S[1], "s")
period_s = float_in(0.0, TIME_RANGE_S[1], "s", lo_open=True)
probability = float_in(0.0, 1.0, lo_open=True, hi_open=True)
fraction = float_in(0.0, 1.0, hi_open=True)
degree = int_in(0, MAX_DEGREE)
window_samples = int_in(2, 1_000_000)
min_interval_samples = int_in(1, 1_000_000)
folds = int_in(2, 10_000)
max_effects = int_in(0, 100)
seed = int_in(0, 2**32 - 1)
lanes = int_in(1, 64, " (searches of the diagnosis side by side)")
search_rows = int_in(0, 10**9, " (0: the diagnosis searches on every fitted sample)")
cutoff_hz = float_in(1e-3, 1e5, "Hz", what=" (a TIA stage's first-order cut-off)")


def sensor_id(text: str) -> str:
    """``--sensor-id``: printable text of at most 256 characters (no ANSI escape sequence, no line break: the id is
    echoed in messages and stored in the recording and the calibration)."""
    from fbg_accel_driver.command_line import check_name_text

    try:
        check_name_text(text, "sensor id")
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if len(text) > 256:
        raise argparse.ArgumentTypeError(f"sensor id of {len(text)} characters; at most 256 are accepted")
    return text


def start_time_ns(text: str) -> int:
    """``--start-time``: an ISO 8601 time with its zone (``2026-11-20T09:30:00Z``, ``...+01:00``) or seconds
    since the Unix epoch; returned as ns since the epoch. Refused: no zone (ambiguous), before 1970, or past
    the int32-second limit of a ROS stamp (2038-01-19)."""
    import datetime as dt

    when: dt.datetime | None = None
    try:
        seconds = float(text)
    except ValueError:
        try:
            when = dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text!r} is neither an ISO 8601 time (e.g. 2026-11-20T09:30:00Z) nor seconds since 1970") from None
    if when is not None:
        if when.tzinfo is None:
            raise argparse.ArgumentTypeError(f"{text!r} has no time zone; add Z (UTC) or an offset like +01:00")
        seconds = when.timestamp()
    if not (math.isfinite(seconds) and TIME_RANGE_S[0] <= seconds <= TIME_RANGE_S[1]):
        raise argparse.ArgumentTypeError(f"{text!r} is outside 1970-01-01 .. 2038-01-19 (a ROS stamp's int32 seconds)")
    return round(seconds * 1e9)


# ---------------------------------------------------------------------------- samples of every input route
# A temperature reading that leaves the readings around it by this much and comes back within SPIKE_MAX_S is a junk
# reading (an AHT10 read while busy, a bad I2C transfer): the sensor sits on the aluminium structure inside a sealed
# housing (sensor_facts.md) and a climatic chamber moves it by ~1 degC a minute; its accuracy is +-0.3 degC.
TEMPERATURE_SPIKE_C = 2.0
TEMPERATURE_SPIKE_MAX_S = 10.0
SAMPLE_REASONS = {
    "counts": "ADC counts outside the 12-bit range 0 .. 4095 or not finite",
    "temperature": f"a temperature outside the AHT10 range {TEMPERATURE_RANGE_C[0]:g} .. {TEMPERATURE_RANGE_C[1]:g} degC",
    "temperature_spike": (f"a temperature reading {TEMPERATURE_SPIKE_C:g} degC or more off the readings before and "
                          f"after it for less than {TEMPERATURE_SPIKE_MAX_S:g} s (a junk reading of the sensor)"),
    "reference": (f"a reference gravity |g_ref| outside {GRAVITY_RANGE_MPS2[0]:g} .. {GRAVITY_RANGE_MPS2[1]:g} m/s^2 "
                  "(gravity in g? another unit?)"),
}


def count_problem(name: str, value: float) -> str:
    """Why ``value`` cannot be an ADC count of channel ``name`` (12-bit: 0 .. 4095), or ``""``."""
    if not math.isfinite(value):
        return f"{name} = {value:g} is not finite"
    if value < 0:
        return f"{name} = {value:g} is negative"
    if value > ADC_MAX:
        return f"{name} = {value:g} is beyond the 12-bit ADC range 0 .. {ADC_MAX:g} counts"
    return ""


def temperature_unit_hint(value: float) -> str:
    """What a temperature outside the AHT10 range (degC) looks like: the range in kelvin or in Fahrenheit."""
    lo, hi = TEMPERATURE_RANGE_C
    if lo + 273.15 <= value <= hi + 273.15:
        return f"; it looks like kelvin: give degC ({value:g} K = {value - 273.15:.2f} degC)"
    if hi < value <= hi * 1.8 + 32.0:
        return f"; it looks like Fahrenheit: give degC ({value:g} F = {(value - 32.0) / 1.8:.2f} degC)"
    return ""


def temperature_spikes(t_s: np.ndarray, temp_c: np.ndarray, before: float = math.nan) -> np.ndarray:
    """(N,) bool: the readings of ``temp_c`` (degC, NaN = none, at times ``t_s`` s) that are junk: a stretch of equal
    readings :data:`TEMPERATURE_SPIKE_C` or more off both the reading before it and the one after it, whose
    neighbours agree with each other, and that lasts less than :data:`TEMPERATURE_SPIKE_MAX_S` (a real change of
    level persists; the chamber changes the temperature slowly). ``before``: the last reading before the first one.
    The last stretch has no reading after it: never judged here (:class:`SampleCheck` keeps it for the next block)."""
    import numpy as np

    out = np.zeros(len(temp_c), bool)
    idx = np.flatnonzero(np.isfinite(temp_c))
    if len(idx) == 0:
        return out
    v = temp_c[idx]
    starts = np.flatnonzero(np.r_[True, v[1:] != v[:-1]])  # stretches of equal readings
    vals = v[starts]
    prev = np.r_[before, vals[:-1]]
    nxt = np.r_[vals[1:], math.nan]
    dur = np.r_[t_s[idx[starts[1:]]], math.nan] - t_s[idx[starts]]  # to the next stretch's first reading
    with np.errstate(invalid="ignore"):
        spike = ((np.abs(vals - prev) >= TEMPERATURE_SPIKE_C) & (np.abs(vals - nxt) >= TEMPERATURE_SPIKE_C)
                 & (np.abs(prev - nxt) < TEMPERATURE_SPIKE_C) & (dur < TEMPERATURE_SPIKE_MAX_S))
    ends = np.r_[starts[1:], len(v)]
    for k in np.flatnonzero(spike):
        out[idx[starts[k]:ends[k]]] = True
    return out


class SampleCheck:
    """What the fit must not take from one input (a file, a bag, a run), block after block in time order, and a tally
    of it per reason (:data:`SAMPLE_REASONS`): counts outside the ADC range or not finite (one count of 1e308
    overflowed the moving variances of its whole file) drop their sample; a temperature outside the AHT10 range
    (kelvin, 1e300) or a junk reading (:func:`temperature_spikes`) leaves its sample without a temperature, a
    reference gravity whose magnitude is not the local gravity (the fit's reference is gravity on a table: in g it is
    ~1) leaves it without a reference, so the fit does not take it. Only the bad samples are affected, and their
    number is said (:meth:`warnings`); an input without a single temperature reading is said too. Temperatures and
    references are blanked, not dropped, so that every pass over the input sees the same samples (the first pass has
    no poses yet).

    :meth:`apply` holds back the last stretch of equal temperature readings of a block until the next block tells
    whether it was a spike; ``recording.without_samples`` passes the held samples again at the front of the next
    block."""

    def __init__(self) -> None:
        self.samples = 0
        self.no_temperature = 0  # samples without a temperature reading as read (NaN)
        self.dropped = dict.fromkeys(SAMPLE_REASONS, 0)
        self.example: dict[str, str] = {}
        self._before = math.nan  # the last temperature reading judged, degC

    def apply(self, blk: Any, last: bool = False) -> tuple[Any, np.ndarray, np.ndarray]:
        """(block, drop, hold) of a ``Recording`` block: the block with its bad temperatures and references blanked
        (a copy, when any), the samples to drop and the samples to hold back ((N,) bool each); ``last``: no block
        follows (nothing is held)."""
        import dataclasses

        import numpy as np

        counts = np.column_stack([blk.ref, blk.xyz])
        temp_c, gref = blk.temp_c, blk.gref_mps2
        with np.errstate(invalid="ignore", over="ignore"):
            bad_counts = ~np.all(np.isfinite(counts) & (counts >= 0) & (counts <= ADC_MAX), axis=1)
            finite_t = np.isfinite(temp_c)
            bad_temp = finite_t & ((temp_c < TEMPERATURE_RANGE_C[0]) | (temp_c > TEMPERATURE_RANGE_C[1]))
            g = np.sqrt(np.sum(gref * gref, axis=1))
            bad_ref = ((blk.pose_id >= 0) & np.isfinite(g)
                       & ((g < GRAVITY_RANGE_MPS2[0]) | (g > GRAVITY_RANGE_MPS2[1])))
        judged = np.where(bad_temp | bad_counts, np.nan, temp_c)
        hold = np.zeros(len(temp_c), bool)
        readings = np.flatnonzero(np.isfinite(judged))
        if not last and len(readings):  # the last stretch of equal readings waits for the next block
            other = readings[judged[readings] != judged[readings[-1]]]
            hold[(other[-1] + 1) if len(other) else 0:] = True
        spike = np.zeros(len(temp_c), bool)
        spike[~hold] = temperature_spikes(blk.t_s[~hold], judged[~hold], self._before)
        kept = np.flatnonzero(np.isfinite(judged) & ~hold & ~spike)
        if len(kept):
            self._before = float(judged[kept[-1]])
        done = ~hold
        self.samples += int(done.sum())
        self.no_temperature += int((done & ~finite_t).sum())
        tallies = (("counts", bad_counts & done, None), ("temperature", bad_temp & done & ~bad_counts, temp_c),
                   ("temperature_spike", spike & ~bad_counts, temp_c),
                   ("reference", bad_ref & done & ~bad_counts, g))
        for reason, mask, values in tallies:
            n = int(mask.sum())
            if not n:
                continue
            self.dropped[reason] += n
            if reason not in self.example:
                i = int(np.flatnonzero(mask)[0])
                self.example[reason] = (_count_example(counts[i]) if values is None else f"{values[i]:g}"
                                        + (temperature_unit_hint(float(values[i])) if reason == "temperature" else ""))
        blank_t, blank_g = (bad_temp | spike) & done, bad_ref & done
        if blank_t.any() or blank_g.any():
            blk = dataclasses.replace(blk, temp_c=np.where(blank_t, np.nan, temp_c),
                                      gref_mps2=np.where(blank_g[:, None], np.nan, gref))
        return blk, bad_counts & done, hold

    @property
    def count(self) -> int:
        """Samples dropped (bad counts)."""
        return self.dropped["counts"]

    @property
    def flagged(self) -> int:
        """Samples dropped or not fitted, all reasons."""
        return sum(self.dropped.values())

    def as_dict(self) -> dict[str, object]:
        return {"samples": self.samples, "no_temperature": self.no_temperature,
                "by_reason": {k: v for k, v in self.dropped.items() if v}, "examples": dict(self.example)}

    def warnings(self, where: str) -> list[str]:
        """One line per reason (``where``: the input's name), and one for an input without any temperature reading."""
        out = [f"{where}: {n} of {self.samples} samples {'dropped' if reason == 'counts' else 'not fitted'}: "
               f"{SAMPLE_REASONS[reason]} (first: {self.example[reason]}); the fit uses the rest"
               for reason, n in self.dropped.items() if n]
        if self.samples and self.no_temperature == self.samples:
            out.append(f"{where}: none of its {self.samples} samples has a temperature reading: it contributes "
                       "nothing to the fit (a temperature column or topic missing? give --temperature for a CSV)")
        return out


def _count_example(counts: np.ndarray) -> str:
    """The first channel of ``counts`` (ref, x, y, z) that is not an ADC count, in :func:`count_problem`'s words."""
    for name, value in zip(("ref_counts", "x_counts", "y_counts", "z_counts"), counts, strict=True):
        problem = count_problem(name, float(value))
        if problem:
            return problem
    return ""
