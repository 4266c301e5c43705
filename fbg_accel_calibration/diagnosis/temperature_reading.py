"""Jumps of the temperature reading that no temperature change can make (pure numpy).

The AHT10 (paper §3.5) reads the temperature of the structure its PCB is anchored to, which changes over minutes
(the housing took hours to settle, §4.4); two readings of one temperature differ by at most twice its repeatability
(±0.1 °C, AHT10 datasheet). A reading that departs from the line through its own last ``PAST_S`` seconds by more than
``JUMP_C`` is therefore not a temperature: the sensor re-seated (its thermal contact changed, a step), one bit of the
20-bit temperature word flipped (a spike, T = S_T / 2^20 x 200 - 50 °C), or the end of a stretch where the firmware
read the same result again (a frozen reading catching up). None of them is flagged by the firmware (TEMP_VALID stays
set), and eq. 28 evaluated at such a reading moves the output once, which a function of time or of the temperature's
history can follow (``diagnose``: it is not added while the reading jumps).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

JUMP_C = 0.2  # degC: 2 x the AHT10 repeatability (+-0.1 degC, datasheet): two reads of one temperature differ by no more
PAST_S = 10.0  # s of the reading's own course a new reading is compared with (the structure changes over minutes)
MIN_PAST_S = 1.0  # s: the past must span at least this (two reads at the firmware's 2 Hz) to give a course


@dataclass(frozen=True)
class ReadingJump:
    """The reading departs from its recent course by ``size_c`` (degC, signed) at board time ``t_s`` (s) of ``run``;
    ``t_before_s`` is the sample before it. Departures within ``PAST_S`` of each other are one jump (the first)."""

    t_s: float
    t_before_s: float
    run: int
    size_c: float


def reading_jumps(t_s: np.ndarray, temp_c: np.ndarray, run_id: np.ndarray) -> list[ReadingJump]:
    """The jumps of the temperature reading ``temp_c`` (degC, NaN = no reading) at board times ``t_s`` (s), time-ordered
    within each run of ``run_id``: each finite reading is compared with the least-squares line through the finite
    readings of the ``PAST_S`` seconds before it (when they span ``MIN_PAST_S``), extrapolated to its time."""
    t_s, temp_c, run_id = np.asarray(t_s, float), np.asarray(temp_c, float), np.asarray(run_id)
    jumps: list[ReadingJump] = []
    for run in np.unique(run_id):
        idx = np.flatnonzero((run_id == run) & np.isfinite(temp_c) & np.isfinite(t_s))
        if idx.size < 3:
            continue
        t, y = t_s[idx], temp_c[idx]
        t0 = t - t[0]  # about the run's start: the sums below stay exact enough over 2^31 s
        # prefix sums of 1, t, y, t^2, t y: the line through samples [lo, i) of each i in O(1)
        c = [np.concatenate([[0.0], np.cumsum(v)]) for v in (np.ones_like(t0), t0, y, t0 * t0, t0 * y)]
        i = np.arange(len(t))
        lo = np.searchsorted(t, t - PAST_S, side="left")
        n, st, sy, stt, sty = (v[i] - v[lo] for v in c)
        span = np.where(i > lo, t[np.maximum(i - 1, 0)] - t[lo], 0.0)
        ok = (n >= 2) & (span >= MIN_PAST_S)
        with np.errstate(divide="ignore", invalid="ignore"):
            var = stt - st * st / n
            slope = np.where(var > 0, (sty - st * sy / n) / var, 0.0)
            pred = sy / n + slope * (t0 - st / n)
        excess = np.where(ok, y - pred, 0.0)
        last = -np.inf
        for k in np.flatnonzero(np.abs(excess) > JUMP_C):
            if t[k] - last > PAST_S:  # the readings after a jump have it in their past: one jump
                jumps.append(ReadingJump(float(t[k]), float(t[k - 1]), int(run), float(excess[k])))
            last = t[k]
    return jumps


def jump_warning(jumps: list[ReadingJump], eq28_reads_it: bool) -> str:
    """One sentence naming the jumps (empty when none); ``eq28_reads_it``: the recording has two temperature levels or
    more, so eq. 28 reads the temperature and the candidates that follow a step are not added (``diagnose``)."""
    if not jumps:
        return ""
    where = ", ".join(f"{j.size_c:+.2f} degC at t = {j.t_s:.1f} s (run {j.run})" for j in jumps[:10])
    more = f" and {len(jumps) - 10} more" if len(jumps) > 10 else ""
    return (f"the AHT10 reading jumps {len(jumps)} time(s), by {where}{more}: more than two reads of one temperature "
            f"differ (2 x its +-0.1 degC repeatability) beyond the course of its last {PAST_S:g} s, which no temperature "
            "of the structure does; a sensor re-seated, a flipped bit of its word (a spike) or a frozen reading catching "
            "up, none flagged by the firmware. "
            + ("Eq. 28 reads this temperature, so nothing that can follow a step of the output (a drift, a lag, a "
               "hysteresis, a dark offset) is added" if eq28_reads_it else
               "Eq. 28 of one temperature level does not read it")
            + ": check the sensor and the I2C bus and record again, or leave the stretch out")
