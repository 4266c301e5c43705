"""The driver node's parameters (ROS-free): its parameter table (``command_line.ParameterTable``), the parameters it
takes at run time, and where the shipped calibration of ``calibration_file:=sim`` is found. Read by the node
(``driver_node``) and by its entry point's ``--help`` (``driver_main``), which answers without rclpy.
"""

from __future__ import annotations

import sys
from pathlib import Path

from .command_line import ParameterTable
from .sensor_constants import AHT10_SIGMA_C, LOW_REFERENCE_COUNTS

PACKAGE = "fbg_accel_driver"
DEFAULT_CALIBRATION = "calibration_sim.yaml"
CALIBRATION_SIM = "sim"  # calibration_file value: the simulated sensor's calibration shipped in config/
CALIBRATION_NONE = "none"  # calibration_file value: raw counts and temperature only
# parameters ``ros2 param set`` may change while streaming (DriverCore.reconfigure); the rest are read-only
RUNTIME_PARAMETERS = ("decimation", "min_reference_counts", "temperature_hold_s", "out_of_range_variance_factor")
# name: (type, default, description), ROS-free so that --help needs no ROS (command_line.ParameterTable)
PARAMETERS: ParameterTable = {
    "port": ("string", "/dev/ttyUSB0", "serial device of the board (a pty path for the simulator)"),
    "baud": ("integer", 921600, "UART baud rate, 1200..4000000"),
    "frame_id": ("string", "fbg_accel_link", "frame_id of the published messages (sensor frame)"),
    "calibration_file": (
        "string",
        "",
        f"REQUIRED: the sensor's calibration YAML; '{CALIBRATION_SIM}' = the package's config/{DEFAULT_CALIBRATION} "
        f"(the simulated sensor); '{CALIBRATION_NONE}' = no imu/data_raw, imu/raw and imu/temperature only",
    ),
    "decimation": ("integer", 1, "average this many board samples per imu/data_raw message, 1..10000 (settable)"),
    "covariance_source": (
        "string",
        "calibration",
        "linear_acceleration_covariance from: calibration (noise_sigma_mps2), parameter (accel_stddev_mps2), unknown "
        "(zeros); decimated variance uses the calibration's noise_correlation",
    ),
    "accel_stddev_mps2": ("double", 0.0, "per-axis sigma in m/s^2 when covariance_source is 'parameter'"),
    "covariance_includes_calibration": (
        "bool",
        False,
        "add the calibration's own uncertainty (J Sigma J^T from its coefficient_covariance) to "
        "linear_acceleration_covariance; a bias, correlated in time (docs/topics.md)",
    ),
    "gravity_mps2": ("double", 0.0,
                     "local gravity (m/s^2, 9.7..9.9) the live gravity check compares |a| with while the sensor stands "
                     "still; 0 (default) = check off (docs/topics.md, gravity check)"),
    "gravity_tolerance_mps2": ("double", 0.03,
                               "discrepancy of |a| from gravity_mps2 allowed beyond the noise, the calibration's "
                               "J Sigma J^T and its slow_error (m/s^2, 0..10; 0.03: standard gravity's error, kept also "
                               "with a measured local gravity; a slow_error without its run-to-run part adds 0.05, a "
                               "file without slow_error 0.12, docs/topics.md)"),
    "gravity_check_period_s": ("double", 20.0, "seconds of stillness each gravity test averages (1..3600)"),
    "chain_compensation": (
        "string",
        "auto",
        "measuring-chain dynamics from the calibration's 'dynamic' section: none, delay (stamps moved back by the "
        "group delay at DC), equalise (each channel's TIA low-pass inverted before eq. 24), auto (= delay when the "
        "calibration has a dynamic section, else none); docs/dynamic_calibration.md",
    ),
    "equalise_bandwidth_hz": ("double", 10.0,
                              "common low-pass (Hz) left in place of the TIA stages by chain_compensation 'equalise'"),
    "min_reference_counts": ("integer", LOW_REFERENCE_COUNTS,
                             "reference counts below this: reference power too low, sample not published (settable)"),
    "temperature_hold_s": ("double", 5.0,
                           "seconds the last good temperature may be used while the sensor is invalid (settable)"),
    "out_of_range_variance_factor": ("double", 10.0,
                                     "variance factor outside the calibrated temperature range (>= 1) (settable)"),
    "temperature_range_margin_c": ("double", AHT10_SIGMA_C,
                                   "a temperature this close (degC) to the calibration's temperature_range_c is inside it "
                                   "(default: the AHT10's stated uncertainty; 0 = the range exactly)"),
    "reference_level_tolerance": ("double", 0.03,
                                  "relative departure of the reference counts from the calibration's reference_level at "
                                  "this temperature beyond which a sample is flagged and its variance inflated (0..1]"),
    "reconnect_backoff_max_s": ("double", 2.0, "longest wait between reconnection attempts (back-off doubles from 0.1 s)"),
    "silence_timeout_s": ("double", 2.0, "reopen the port after this many seconds without any byte (0 = never)"),
    "reader_queue_max_bytes": (
        "integer",
        262144,
        "bytes the serial reader may queue ahead of the decoder; beyond it the oldest are dropped and counted",
    ),
}


def calibration_candidates() -> list[Path]:
    """Where the shipped calibration (``calibration_file:=sim``) is looked for, in order: the ament index's share
    directory, ``<prefix>/share/fbg_accel_driver/config`` of the install this module runs from (a colcon install or
    ``pip install .``: ``<prefix>/lib/pythonX.Y/site-packages/fbg_accel_driver/driver_parameters.py``), that of the running
    interpreter's prefix, and the source tree's config/ (editable install)."""
    candidates: list[Path] = []
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

        try:
            candidates.append(Path(get_package_share_directory(PACKAGE)) / "config" / DEFAULT_CALIBRATION)
        except (PackageNotFoundError, ValueError, LookupError, OSError):
            pass
    except ImportError:
        pass
    here = Path(__file__).resolve()
    for parent in here.parents:
        if parent.name == "lib":  # the install prefix is the parent of lib/
            candidates.append(parent.parent / "share" / PACKAGE / "config" / DEFAULT_CALIBRATION)
            break
    candidates.append(Path(sys.prefix) / "share" / PACKAGE / "config" / DEFAULT_CALIBRATION)
    candidates.append(here.parents[1] / "config" / DEFAULT_CALIBRATION)  # source tree / editable install
    return candidates


def default_calibration_path() -> Path:
    """The shipped calibration of the simulated sensor: the first of :func:`calibration_candidates` that exists (the
    last candidate if none does, so that the driver's refusal names a path)."""
    candidates = calibration_candidates()
    return next((c for c in candidates if c.is_file()), candidates[-1])
