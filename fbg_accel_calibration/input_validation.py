"""Bounds of every number that enters the offline tools from outside (CLI options and CSV columns).

Pure Python. Each bound is what the instrument or the file format can physically hold; a value
outside it is a typo or a corrupted file, and accepting it wrote wrong calibrations with exit 0
(issue 11): ``--g -9.81`` inverts the calibration, ``--g nan`` makes every sample "moving",
``--level-gap -1`` splits one temperature into 31 "levels" and defeats the over-fitting guard,
``--alpha nan`` flips the diagnosis' verdict, counts of 60880 cannot come from a 12-bit ADC.

The argparse ``type=`` factories below turn a bad option into argparse's usage error (exit 2, one
line naming the option, the value and the accepted range); :func:`check_range` does the same for
CSV cells (the importer adds file and line).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2  # noqa: F401  (iv.FULL_SCALE_MPS2 for the CSV bounds)

# Local gravity on the Earth's surface: WGS-84 normal gravity 9.780 m/s^2 (equator) .. 9.832 m/s^2
# (poles), minus 3.1e-6 m/s^2 per metre of altitude; 9.7 .. 9.9 leaves room for local anomalies.
GRAVITY_RANGE_MPS2 = (9.7, 9.9)
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
