"""Shared glue of the package's launch files (``launch/*.launch.py``); no ROS import until :func:`generate`.

Each launch file states what it starts as two pure functions, so that it can be checked (and its
command lines run) without ``launch``/``launch_ros``, which are not on PyPI:

* ``launch_arguments(share_dir) -> {name: (default, description)}``: its launch arguments, defaults
  resolved against the package's share directory (``share/fbg_accel_driver``, or the source tree);
* ``node_descriptions(share_dir, args) -> [dict, ...]``: the processes for the argument values ``args``
  (plain strings, exactly as given on the ``ros2 launch`` command line). Each dict has ``executable``
  (a console script of this package, setup.py ``entry_points``) and optionally ``arguments`` (list of
  str), ``name``, ``namespace`` ("" or absent: none) and ``parameters``: applied in order, later ones
  win (as ``--params-file`` does); a ``str`` is a params YAML path, a ``dict`` holds overrides with
  their Python types (str, int, float, bool); ``ros_arguments`` (list of str) go after ``--ros-args``
  (``--log-level``). ``ros_node`` False: a plain program without ``--ros-args`` (``board_sim``); then only
  ``executable`` and ``arguments`` apply. ``ends_launch`` True: the launch shuts down (stopping the other
  processes) when this one exits. ``start_after_output`` ``(executable, text)``: the node starts once that plain
  program of the same launch file prints a line containing ``text`` (the driver once ``board_sim`` has made
  its link), not at once.

Every launch file also takes the arguments of :data:`NODE_OPTIONS` (``managed``, ``use_sim_time``,
``log_level``); :func:`node_options` turns them into the driver's ``--managed``, a ``use_sim_time`` parameter
and ``--log-level`` for each ROS node.

:func:`generate` turns the two into a ``LaunchDescription``: one ``DeclareLaunchArgument`` each, and
an ``OpaqueFunction`` that calls ``node_descriptions`` with the resolved values at launch time and
starts a ``launch_ros`` ``Node`` per ROS node and an ``ExecuteProcess`` per plain program.
"""

from __future__ import annotations

from typing import Any

PACKAGE = "fbg_accel_driver"
LOG_LEVELS = ("debug", "info", "warn", "error", "fatal")
# The launch arguments every launch file of the package has: name -> (default, description)
NODE_OPTIONS: dict[str, tuple[str, str]] = {
    "managed": ("false", "true: the driver is a managed (lifecycle) node, publishing only once configured and "
                         "activated (ros2 lifecycle set <node> configure, then activate)"),
    "use_sim_time": ("false", "true: the nodes' ROS clock follows /clock (parameter use_sim_time)"),
    "log_level": ("info", "minimum severity the nodes log: " + ", ".join(LOG_LEVELS)),
}


def bool_argument(args: dict[str, str], name: str) -> bool:
    """A boolean launch argument (true/false, 1/0, yes/no; any case); ValueError naming it otherwise."""
    value = args[name].strip().lower()
    if value in ("true", "1", "yes"):
        return True
    if value in ("false", "0", "no"):
        return False
    raise ValueError(f"launch argument {name}:={args[name]!r} is not a boolean (true or false)")


def int_argument(args: dict[str, str], name: str) -> int:
    """An integer launch argument; ValueError naming it otherwise."""
    try:
        return int(args[name])
    except ValueError:
        raise ValueError(f"launch argument {name}:={args[name]!r} is not an integer") from None


def choice_argument(args: dict[str, str], name: str, choices: tuple[str, ...]) -> str:
    """A launch argument that must be one of ``choices`` (any case); ValueError naming it otherwise."""
    value = args[name].strip().lower()
    if value not in choices:
        raise ValueError(f"launch argument {name}:={args[name]!r} is not one of {', '.join(choices)}")
    return value


def node_options(args: dict[str, str], description: dict[str, Any]) -> dict[str, Any]:
    """``description`` (a ROS node's) with the :data:`NODE_OPTIONS` values of ``args`` applied: ``--managed`` for the
    driver, ``use_sim_time`` as the last parameter override, ``--log-level`` among its ROS arguments."""
    d = dict(description)
    if d["executable"] == "driver" and bool_argument(args, "managed"):
        d["arguments"] = [*d.get("arguments", []), "--managed"]
    d["parameters"] = [*d.get("parameters", []), {"use_sim_time": bool_argument(args, "use_sim_time")}]
    d["ros_arguments"] = [*d.get("ros_arguments", []), "--log-level", choice_argument(args, "log_level", LOG_LEVELS)]
    return d


def _start_once_on(text: str, action: Any) -> Any:
    """An ``OnProcessIO`` callback that returns ``[action]`` the first time an output chunk contains ``text``."""
    started: list[bool] = []

    def on_output(event: Any) -> list[Any] | None:
        if started or text not in event.text.decode(errors="replace"):
            return None
        started.append(True)
        return [action]

    return on_output


def generate(launch_arguments: Any, node_descriptions: Any) -> Any:
    """The ``LaunchDescription`` of a launch file given its two pure functions (imports launch lazily)."""
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, EmitEvent, ExecuteProcess, OpaqueFunction, RegisterEventHandler
    from launch.event_handlers import OnProcessExit, OnProcessIO
    from launch.events import Shutdown
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node
    from launch_ros.parameter_descriptions import ParameterValue
    from launch_ros.substitutions import ExecutableInPackage

    share = get_package_share_directory(PACKAGE)
    arguments: dict[str, tuple[str, str]] = launch_arguments(share)

    def typed(params: dict[str, Any]) -> dict[str, Any]:
        # launch_ros parses a str value as YAML ("007" would become an int): keep strings strings
        return {k: ParameterValue(v, value_type=str) if isinstance(v, str) else v for k, v in params.items()}

    def actions(context: Any) -> list[Any]:
        values = {name: LaunchConfiguration(name).perform(context) for name in arguments}
        out: list[Any] = []
        programs: dict[str, Any] = {}
        for d in node_descriptions(share, values):
            if not d.get("ros_node", True):
                programs[d["executable"]] = ExecuteProcess(
                    cmd=[ExecutableInPackage(d["executable"], PACKAGE), *d.get("arguments", [])],
                    name=d["executable"], output="screen")
                out.append(programs[d["executable"]])
                continue
            params = [p if isinstance(p, str) else typed(p) for p in d.get("parameters", [])]
            node = Node(package=PACKAGE, executable=d["executable"], name=d.get("name"),
                        namespace=d.get("namespace") or None, parameters=params, arguments=d.get("arguments", []),
                        ros_arguments=d.get("ros_arguments", []), output="screen")
            if "start_after_output" in d:
                program, text = d["start_after_output"]
                out.append(RegisterEventHandler(OnProcessIO(target_action=programs[program],
                                                            on_stdout=_start_once_on(text, node))))
            else:
                out.append(node)
            if d.get("ends_launch"):  # its end (run complete, fit written) ends the launch: the others get SIGINT
                out.append(RegisterEventHandler(OnProcessExit(
                    target_action=node, on_exit=[EmitEvent(event=Shutdown(reason=f"{d['executable']} ended"))])))
        return out

    return LaunchDescription([
        *(DeclareLaunchArgument(name, default_value=default, description=text)
          for name, (default, text) in arguments.items()),
        OpaqueFunction(function=actions),
    ])
