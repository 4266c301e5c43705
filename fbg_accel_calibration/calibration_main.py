"""Entry point of the ROS 2 node ``calibration`` (``ros2 run fbg_accel_driver calibration``): its parameter
table, usage text and ``main``. No ROS import: ``--help`` and ``--version`` answer without rclpy; the node
itself (``calibration_node``, rclpy) is imported only to run.
"""

from __future__ import annotations

import sys

from fbg_accel_driver.command_line import (
    ParameterTable,
    StartupError,
    missing_module_message,
    parameter_help,
    print_help_or_version,
)
from fbg_accel_driver.stillness_monitor import DEFAULT_FALSE_ALARM_PER_RUN, DEFAULT_NOISE_CORR_S

PACKAGE = "fbg_accel_driver"
EXIT_OK, EXIT_FIT_FAILED, EXIT_STARTUP, EXIT_INTERRUPTED, EXIT_RECORDING_FAILED = 0, 1, 2, 3, 4

# name: (type, default, description), ROS-free so that --help needs no ROS (command_line.ParameterTable;
# a default of None declares the parameter by type only, unset unless given)
PARAMETERS: ParameterTable = {
    "plan_file": ("string", "", "pose plan YAML (required), e.g. config/pose_plan_six_position.yaml, or an excitation "
                  "plan (dynamic run: records imu/raw with aux_counts and the reference for the plan's duration)"),
    "output_dir": ("string", ".", "directory of the run's MCAP file and calibration YAML (created if missing)"),
    "run_label": ("string", "", "file stem of this run (empty: <sensor_id>[_L<level>]_<YYYYmmddTHHMMSSZ>)"),
    "sensor_id": ("string", "unknown", "sensor identifier written into the MCAP metadata and the calibration"),
    "operator_notes": ("string", "", "free text stored in the MCAP metadata"),
    "mode": ("string", "service", "pose advance: service (operator calls calibration/next_pose) or auto (table motion/dwell)"),
    "temperature_level": ("integer", -1, "index of the plan's chamber level of this run (-1: none)"),
    "fit": ("bool", True, "refit at the end of a complete run and write the calibration YAML"),
    "fit_degree": ("integer", -1, "temperature degree n of eq. 28, 0..6 (-1: chosen by held-out cross-validation)"),
    "fit_with": ("string_array", None, "earlier runs' MCAP files or glob patterns fitted together with this run"),
    "calibration_file": ("string", "", "output calibration YAML (empty: <output_dir>/<run_label>_calibration.yaml); "
                         "never one of the fitted recordings"),
    "force": ("bool", False, "replace an existing calibration_file (default: refuse it at start-up)"),
    "still_window_s": ("double", 0.25, "static detector moving window (s)"),
    "still_hold_s": ("double", 1.0, "continuous stillness (s) required before a pose is recorded (covers TIA settling)"),
    "still_noise_std": ("double_array", None, "Psi noise floor per axis x,y,z (unset: learnt at the start of the run)"),
    "still_noise_corr_s": ("double", DEFAULT_NOISE_CORR_S, "correlation time (s) of a configured still_noise_std (TIA low-pass)"),
    "noise_learn_s": ("double", 5.0, "seconds at the start of the run used to learn the noise floor (table still)"),
    "still_false_alarm_per_run": ("double", DEFAULT_FALSE_ALARM_PER_RUN,
                                  "expected false still->moving transitions per run of a still sensor, (0, 1)"),
    "motion_expect_g": ("double", 0.1, "pose changes above this (g) must show motion before the next pose is recorded"),
    "stream_timeout_s": ("double", 0.0, "end the run (file closed, status 3) after this many seconds without an imu/raw "
                         "sample once samples have come; 0: wait for them to come back (a stall is reported after 5 s)"),
    "exit_when_done": ("bool", True, "exit once the run is complete (and fitted)"),
    "progress": ("bool", True, "print the progress line (pose k of N, stillness, samples, temperature) on stdout"),
}


def _usage() -> str:
    """The --help text (built only when asked for)."""
    return f"""usage: calibration [-h] [--version] [--stopped-ok] --ros-args -p plan_file:=PLAN.yaml [-p NAME:=VALUE ...]

  --stopped-ok  exit status 0 (not 3) when SIGINT or SIGTERM stops the run (MCAP closed, no fit):
                calibration.launch.py passes it, so that Ctrl-C, a normal end of a run, is no launch ERROR

Calibration recorder of the FBG triaxial accelerometer (package {PACKAGE}). Follows a pose plan,
waits per pose until the sensor is still (static-interval detector on Psi = counts/ref), records
N samples per pose from imu/raw into one MCAP file (ROS 2 profile), advances on the
calibration/next_pose service (mode service) or on table motion/dwell (mode auto), and at the end
fits the thermal model (paper eq. 28) and writes a calibration YAML that the driver loads.

parameters:
""" + parameter_help(PARAMETERS, 20, 13) + """
example:
  ros2 run fbg_accel_driver calibration --ros-args -p plan_file:=config/pose_plan_six_position.yaml \\
      -p output_dir:=runs -p sensor_id:=acc4 -p temperature_level:=0 -p mode:=service
  ros2 service call /calibration/next_pose std_srvs/srv/Trigger
exit status: 0 run complete (and fitted), 1 run complete but the fit failed (MCAP kept),
             2 invalid parameters or plan, 3 interrupted (SIGINT/SIGTERM/abort; MCAP closed cleanly),
             4 recording failed (disk full, MCAP or output_dir removed): run aborted, no fit.
"""


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if print_help_or_version("calibration", argv, _usage):
        return EXIT_OK
    stopped_ok = "--stopped-ok" in (argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv)
    try:
        try:
            from .calibration_node import run  # rclpy: only once neither --help nor --version answered
        except ModuleNotFoundError as exc:
            raise StartupError(missing_module_message(exc)) from None
        return run([a for a in argv if a != "--stopped-ok"], stopped_ok)
    except StartupError as exc:
        print(f"calibration: error: {exc}", file=sys.stderr, flush=True)
        return EXIT_STARTUP


if __name__ == "__main__":
    sys.exit(main())
