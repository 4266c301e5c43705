"""Entry point of the ROS 2 node ``calibration`` (``ros2 run fbg_accel_driver calibration``): its usage text and
``main`` (the parameter table and exit statuses: ``calibration_parameters``). No ROS import: ``--help`` and
``--version`` answer without rclpy; the node itself (``calibration_node``, rclpy) is imported only to run.
"""

from __future__ import annotations

import sys

from fbg_accel_driver.command_line import (
    StartupError,
    missing_module_message,
    parameter_help,
    print_help_or_version,
)

from .calibration_parameters import EXIT_OK, EXIT_STARTUP, PARAMETERS

PACKAGE = "fbg_accel_driver"


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
