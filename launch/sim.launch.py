"""The simulated board (``board_sim`` on a pseudo-terminal) and the driver reading it: no hardware.

    ros2 launch fbg_accel_driver sim.launch.py
    ros2 launch fbg_accel_driver sim.launch.py namespace:=veh1 sim_config:=/path/my_sim.yaml

``board_sim`` keeps the symbolic link ``link`` pointing at its current pty; the driver starts once
board_sim has announced it (``PTY <path>`` on its output), opens that link and uses the simulated
sensor's calibration. Other driver parameters come from ``params_file`` (default config/driver.yaml).
The default link is named after the namespace (``<tmp>/fbg_accel_sim_board_<uid>_acc_a`` for
``namespace:=acc_a``), so two launches under two namespaces simulate two boards, one per driver.
At Ctrl-C both end together; the driver reports the link closed at shutdown as INFO.
"""

from __future__ import annotations

import os
import tempfile
from typing import Any

DRIVER_PARAMS = "driver.yaml"
SIM_CONFIG = "sim_default.yaml"
SIM_CALIBRATION = "calibration_sim.yaml"
LINK_STEM = "fbg_accel_sim_board_"


def launch_arguments(share_dir: str) -> dict[str, tuple[str, str]]:
    """Launch arguments: name -> (default, description)."""
    config = os.path.join(share_dir, "config")
    from fbg_accel_driver.launch_support import NODE_OPTIONS

    return {
        "params_file": (os.path.join(config, DRIVER_PARAMS), "driver parameters (ROS 2 params file)"),
        "sim_config": (os.path.join(config, SIM_CONFIG), "board_sim configuration YAML (merged on sim_default.yaml)"),
        "calibration_file": (os.path.join(config, SIM_CALIBRATION), "calibration the driver applies (the simulated sensor's)"),
        "link": ("", "symbolic link to the simulator's pty, the driver's port; empty: "
                     f"{os.path.join(tempfile.gettempdir(), LINK_STEM)}<uid>[_<namespace>], one per namespace"),
        "seed": ("0", "board_sim random seed"),
        "namespace": ("", "namespace of the driver and its topics; empty: none"),
        **NODE_OPTIONS,
    }


def default_link(namespace: str) -> str:
    """The board's link when ``link`` is empty: per user and per namespace (``a/b`` -> ``_a_b``), so that the
    simulated boards of two namespaces never share one link (the second board_sim would re-point it and both
    drivers would be given one board)."""
    ns = namespace.strip().strip("/").replace("/", "_")
    return os.path.join(tempfile.gettempdir(), f"{LINK_STEM}{os.getuid()}" + (f"_{ns}" if ns else ""))


def node_descriptions(share_dir: str, args: dict[str, str]) -> list[dict[str, Any]]:
    """board_sim (a plain program) and the driver on its pty link (see fbg_accel_driver.launch_support)."""
    from fbg_accel_driver.launch_support import int_argument, node_options

    link = args["link"] or default_link(args["namespace"])
    return [
        {
            "executable": "board_sim",
            "ros_node": False,
            "arguments": ["--config", args["sim_config"], "--link", link,
                          "--seed", str(int_argument(args, "seed"))],
        },
        node_options(args, {
            "executable": "driver",
            "name": "fbg_accel_driver",
            "namespace": args["namespace"],
            "parameters": [args["params_file"], {"port": link, "calibration_file": args["calibration_file"]}],
            "start_after_output": ("board_sim", "PTY "),  # the link exists: no "cannot open" ERROR at start-up
        }),
    ]


def generate_launch_description() -> Any:
    from fbg_accel_driver.launch_support import generate

    return generate(launch_arguments, node_descriptions)
