"""Options that several ``fbg-accel-calib`` subcommands share (``cli``, ``diagnose_cli``): their names, types,
defaults and help text in one place. Light on purpose: building the parser (``--help``) imports no numerical library.
"""

from __future__ import annotations

import argparse

from fbg_accel_driver.sensor_constants import STANDARD_GRAVITY

from ..io import input_validation as iv


def add_force(p: argparse.ArgumentParser) -> None:
    """``--force``: replace existing outputs."""
    p.add_argument("--force", action="store_true", help="replace existing output files (default: refuse)")


def add_csv_options(p: argparse.ArgumentParser) -> None:
    """``--rate``/``--temperature``/``--g``: what a CSV without a time base, a temperature or a reference lacks."""
    p.add_argument("--rate", type=iv.rate_hz, default=None,
                   help="CSV without t_s: sample rate in Hz (time = sample index / rate)")
    p.add_argument("--temperature", type=iv.temperature_c, default=None,
                   help="CSV without temperature_c: temperature of every sample, degC")
    p.add_argument("--g", type=iv.gravity_mps2, default=STANDARD_GRAVITY,
                   help="gravity for psi/theta references, m/s^2 (default 9.80665)")


def add_detector_options(p: argparse.ArgumentParser) -> None:
    """The static-interval detector's window and shortest interval (samples), and the temperature level gap."""
    p.add_argument("--window", type=iv.window_samples, default=5, help="static detector window, samples (default 5)")
    p.add_argument("--min-interval", type=iv.min_interval_samples, default=5,
                   help="shortest static interval kept, samples (default 5)")
    p.add_argument("--level-gap", type=iv.level_gap_c, default=1.0,
                   help="temperatures further apart than this (degC) are different temperature levels (default 1)")


def add_topic_options(p: argparse.ArgumentParser) -> None:
    """``--namespace``/``--topic``: which raw topic of an MCAP file or rosbag2 bag directory to read."""
    p.add_argument("--namespace", default=None, metavar="NS",
                   help="read NS/imu/raw and NS/calibration/* (e.g. /veh1; default: the single .../imu/raw of type "
                        "sensor_msgs/msg/JointState)")
    p.add_argument("--topic", default=None, metavar="TOPIC",
                   help="full name of the raw JointState topic (e.g. /veh1/imu/raw; default: see --namespace)")
