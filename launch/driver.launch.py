"""The FBG accelerometer driver with its params file.

    ros2 launch fbg_accel_driver driver.launch.py port:=/dev/ttyUSB0 calibration_file:=/path/sensor_cal.yaml
    ros2 launch fbg_accel_driver driver.launch.py namespace:=veh1 params_file:=/path/my_driver.yaml
    ros2 launch fbg_accel_driver driver.launch.py port:=/dev/ttyUSB0 calibration_file:=sim managed:=true log_level:=debug

Every parameter comes from ``params_file`` (default: the package's config/driver.yaml); a
non-empty ``port`` or ``calibration_file`` overrides the file's. The driver needs an explicit
``calibration_file`` (the sensor's YAML, ``sim`` for the simulated sensor, ``none`` for raw counts
only): the shipped params file leaves it empty, so give it here or in your own params file.
``ros2 launch ... --show-args`` lists the arguments.
"""

from __future__ import annotations

import os
from typing import Any

DRIVER_PARAMS = "driver.yaml"


def launch_arguments(share_dir: str) -> dict[str, tuple[str, str]]:
    """Launch arguments: name -> (default, description)."""
    from fbg_accel_driver.launch_support import NODE_OPTIONS

    return {
        "params_file": (os.path.join(share_dir, "config", DRIVER_PARAMS), "driver parameters (ROS 2 params file)"),
        "port": ("", "serial device of the board; empty: the params file's port"),
        "calibration_file": ("", "the sensor's calibration YAML, 'sim' (simulated sensor) or 'none' (raw only); "
                                 "empty: the params file's (required there)"),
        "namespace": ("", "namespace of the driver and its topics; empty: none"),
        **NODE_OPTIONS,
    }


def node_descriptions(share_dir: str, args: dict[str, str]) -> list[dict[str, Any]]:
    """The driver node for the launch argument values ``args`` (see fbg_accel_driver.launch_support)."""
    from fbg_accel_driver.launch_support import node_options

    overrides = {k: args[k] for k in ("port", "calibration_file") if args[k]}
    return [node_options(args, {
        "executable": "driver",
        "name": "fbg_accel_driver",
        "namespace": args["namespace"],
        "parameters": [args["params_file"], *([overrides] if overrides else [])],
    })]


def generate_launch_description() -> Any:
    from fbg_accel_driver.launch_support import generate

    return generate(launch_arguments, node_descriptions)
