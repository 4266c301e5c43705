"""A calibration run: the driver and the ``calibration`` recorder, each with its params file.

    ros2 launch fbg_accel_driver calibration.launch.py port:=/dev/ttyUSB0 sensor_id:=acc4 temperature_level:=0
    ros2 launch fbg_accel_driver calibration.launch.py start_driver:=false   # driver already running (sim.launch.py)

The recorder's parameters come from ``params_file`` (default config/calibration.yaml), the driver's
from ``driver_params_file`` (config/driver.yaml); ``plan_file`` and every non-empty argument below
override the file. Advance poses with ``ros2 service call calibration/next_pose std_srvs/srv/Trigger``
(in the namespace, if one is given). The launch ends when the recorder does (run complete and
fitted, or aborted): the driver it started is stopped with it. Ctrl-C ends the run with its file closed;
the recorder then exits 0 (``--stopped-ok``), so launch reports no ERROR.
``managed:=true`` starts the driver as a lifecycle node, which publishes (and so feeds the recorder)
only once configured and activated.
docs/calibration_node.md describes the run.
"""

from __future__ import annotations

import os
from typing import Any

CALIBRATION_PARAMS = "calibration.yaml"
DRIVER_PARAMS = "driver.yaml"
POSE_PLAN = "pose_plan_six_position.yaml"


def launch_arguments(share_dir: str) -> dict[str, tuple[str, str]]:
    """Launch arguments: name -> (default, description)."""
    config = os.path.join(share_dir, "config")
    from fbg_accel_driver.launch_support import NODE_OPTIONS

    return {
        "params_file": (os.path.join(config, CALIBRATION_PARAMS), "calibration node parameters (ROS 2 params file)"),
        "plan_file": (os.path.join(config, POSE_PLAN), "pose plan YAML of the run"),
        "sensor_id": ("", "sensor identifier; empty: the params file's"),
        "output_dir": ("", "directory of the run's MCAP and calibration YAML; empty: the params file's"),
        "temperature_level": ("", "index of the plan's chamber level of this run; empty: the params file's"),
        "mode": ("", "service or auto; empty: the params file's"),
        "start_driver": ("true", "also start the driver (false: one is already running in this namespace)"),
        "driver_params_file": (os.path.join(config, DRIVER_PARAMS), "driver parameters (ROS 2 params file)"),
        "port": ("", "serial device of the board; empty: the driver params file's port"),
        "calibration_file": ("none", "the driver's calibration: 'none' (the recorder needs raw counts only), "
                                     "'sim' or a YAML; empty: the driver params file's"),
        "namespace": ("", "namespace of both nodes and their topics; empty: none"),
        **NODE_OPTIONS,
    }


def node_descriptions(share_dir: str, args: dict[str, str]) -> list[dict[str, Any]]:
    """Driver (unless start_driver is false) and calibration node (see fbg_accel_driver.launch_support)."""
    from fbg_accel_driver.launch_support import bool_argument, int_argument, node_options

    calib: dict[str, Any] = {"plan_file": args["plan_file"]}
    for name in ("sensor_id", "output_dir", "mode"):
        if args[name]:
            calib[name] = args[name]
    if args["temperature_level"]:
        calib["temperature_level"] = int_argument(args, "temperature_level")
    nodes: list[dict[str, Any]] = []
    if bool_argument(args, "start_driver"):
        overrides = {k: args[k] for k in ("port", "calibration_file") if args[k]}
        nodes.append(node_options(args, {
            "executable": "driver",
            "name": "fbg_accel_driver",
            "namespace": args["namespace"],
            "parameters": [args["driver_params_file"], *([overrides] if overrides else [])],
        }))
    nodes.append(node_options(args, {
        "executable": "calibration",
        "arguments": ["--stopped-ok"],  # Ctrl-C is a normal end here: exit 0, no launch ERROR
        "name": "calibration",
        "namespace": args["namespace"],
        "parameters": [args["params_file"], calib],
        "ends_launch": True,  # the run's end (complete and fitted, or aborted) stops the driver and the launch
    }))
    return nodes


def generate_launch_description() -> Any:
    from fbg_accel_driver.launch_support import generate

    return generate(launch_arguments, node_descriptions)
