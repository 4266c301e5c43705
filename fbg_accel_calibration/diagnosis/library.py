"""The candidate library: the one place the candidates of the diagnosis are registered (``LIBRARY``, in the order the
report lists them when they tie), and what measurement separates two of them that the data cannot tell apart.

A new candidate is an ``effects.Effect`` subclass in a module of its own (its role, bound with its source, checks and
hooks declared on the class, ``docs/effects.md``), added to ``LIBRARY`` here.
"""

from __future__ import annotations

from .chain_effects import ChannelDelayEffect, TiaLowpassEffect
from .effects import (
    Effect,
    ReferenceDarkOffsetEffect,
    ReferenceReadNoiseEffect,
    SpectralNonlinearityEffect,
    ThermalHysteresisEffect,
    ThermalLagEffect,
    TimeDriftEffect,
)
from .rig_effects import TELLS_A_REMOUNT_FROM_THE_SENSOR, MountChangeEffect, TableThetaOffsetEffect
from .run_effects import RunDriftEffect, RunOffsetEffect

LIBRARY: tuple[Effect, ...] = (
    ReferenceReadNoiseEffect(),
    ReferenceDarkOffsetEffect(),
    ThermalLagEffect(),
    SpectralNonlinearityEffect(),
    TimeDriftEffect(),
    ChannelDelayEffect(),
    TiaLowpassEffect(),
    ThermalHysteresisEffect(),
    RunOffsetEffect(),
    RunDriftEffect(),
    TableThetaOffsetEffect(),
    MountChangeEffect(),
)


def library_by_name() -> dict[str, Effect]:
    return {e.name: e for e in LIBRARY}


# What measurement separates two candidates that this data cannot tell apart (for the report).
SEPARATING_MEASUREMENT: dict[frozenset[str], str] = {
    frozenset({"reference_dark_offset", "time_drift"}): (
        "change the source power independently of time (step the SLD drive current or insert a calibrated "
        "attenuator after the source at fixed poses, and repeat the pose sequence in reverse order): a dark "
        "offset follows the reference counts, a drift follows the clock; also record the detectors dark "
        "(source off) to measure d directly"),
    frozenset({"channel_delay", "tia_lowpass"}): (
        "record the transitions at a higher sample rate (or a fast tilt step) and compare the step response: "
        "a delay is a shifted step, the TIA low-pass an exponential approach; a sine sweep separates them by "
        "the phase (linear in frequency for a delay, arctan for a first-order low-pass)"),
    frozenset({"thermal_lag", "thermal_hysteresis"}): (
        "hold temperature plateaus long enough (> 5 time constants) after heating and after cooling: a lag "
        "decays on the plateau, hysteresis stays"),
    frozenset({"thermal_lag", "time_drift"}): (
        "repeat the run with a different temperature profile (e.g. a plateau then a ramp): a thermal lag "
        "follows the temperature rate, a drift follows time since power-on"),
    frozenset({"run_drift", "time_drift"}): (
        "record each run after the same warm-up from power-on: a drift shared by all runs follows the time since "
        "power-on, a per-run drift comes back at every run start"),
    frozenset({"run_offset", "thermal_lag"}): (
        "hold each chamber level longer, until the housing temperature has settled: a lag ends, a run offset stays"),
    frozenset({"spectral_nonlinearity", "table_theta_offset"}): (
        "turn the sensor 90 degrees about the table's z axis on its mount and repeat, or check the table's theta zero "
        "against a level: a table offset stays with the table's axis, a non-linearity turns with the sensor"),
    frozenset({"mount_change", "run_offset"}): TELLS_A_REMOUNT_FROM_THE_SENSOR,
    frozenset({"mount_change", "spectral_nonlinearity"}): TELLS_A_REMOUNT_FROM_THE_SENSOR,
    frozenset({"mount_change", "thermal_lag"}): TELLS_A_REMOUNT_FROM_THE_SENSOR,
    frozenset({"time_drift", "thermal_hysteresis"}): (
        "cycle the temperature up and down twice: hysteresis repeats with the branch, drift does not"),
}


def separating_measurement(a: str, b: str) -> str:
    return SEPARATING_MEASUREMENT.get(frozenset({a, b}), (
        "repeat the calibration with the two explanatory variables decorrelated (randomised pose order, "
        "temperature and power changes at different times)"))
