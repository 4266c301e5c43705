"""Entry point of the ROS 2 node ``driver`` (``ros2 run fbg_accel_driver driver``): its usage text and ``main`` (the
parameter table: ``driver_parameters``). No ROS import: ``--help`` and ``--version`` answer without rclpy; the node itself
(``driver_node``, rclpy) is imported only to run.
"""

from __future__ import annotations

import sys

from .command_line import (
    StartupError,
    missing_module_message,
    one_line,
    parameter_help,
    print_help_or_version,
)
from .driver_parameters import CALIBRATION_SIM, PACKAGE, PARAMETERS, calibration_candidates, default_calibration_path

USAGE = f"""usage: driver [-h] [--version] [--managed] [--ros-args -p NAME:=VALUE ... | --params-file FILE]

  --managed   run as a managed (lifecycle) node: configure loads the calibration and opens the port,
              activate publishes, deactivate stops publishing, cleanup closes the port

ROS 2 driver for the FBG triaxial accelerometer acquisition board (package {PACKAGE}).
Reads binary frames from a serial port (pyserial), stamps them with the board clock mapped to ROS
time, applies the thermal calibration (paper eq. 24 and 28) and publishes:
  imu/data_raw     sensor_msgs/Imu          specific force in m/s^2 (REP 145)
  imu/temperature  sensor_msgs/Temperature  AHT10 temperature in degC
  imu/raw          sensor_msgs/JointState   raw counts, temperature, status, seq, board time
  /diagnostics     diagnostic_msgs/DiagnosticArray, 1 Hz

parameters:
""" + parameter_help(PARAMETERS, 30, 8) + """
example:
  ros2 run fbg_accel_driver driver --ros-args -p port:=/dev/ttyUSB0 -p decimation:=10
exit status: 0 on clean shutdown, 2 on invalid parameters or calibration file.
"""


def _usage() -> str:
    path = default_calibration_path()
    where = str(path) if path.is_file() else "not found in " + ", ".join(str(c.parent) for c in calibration_candidates())
    return USAGE + f"calibration_file '{CALIBRATION_SIM}': {where}\n"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if print_help_or_version("driver", argv, _usage):
        return 0
    try:
        user = argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv
        managed = "--managed" in user
        user = [a for a in user if a != "--managed"]
        if user:
            raise StartupError(f"unknown argument(s) {user}; parameters go after --ros-args (see driver --help)")
        try:
            from .driver_node import run  # rclpy: only once neither --help nor --version answered
        except ModuleNotFoundError as exc:
            raise StartupError(missing_module_message(exc)) from None
        return run([a for a in argv if a != "--managed"], managed)
    except StartupError as exc:
        print(f"driver: error: {one_line(str(exc))}", file=sys.stderr, flush=True)
        return 2
    except KeyboardInterrupt:
        return 0


if __name__ == "__main__":
    sys.exit(main())
