"""Command-line conventions shared by the package's executables (no ROS import)."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable
from typing import Any

DISTRIBUTION = "fbg_accel_driver"  # the setup.py ``name`` whose metadata carries the version


class OneLineErrorParser(argparse.ArgumentParser):
    """argparse parser whose usage errors are one line (option, value, accepted range) and exit 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def print_help_or_version(prog: str, argv: list[str], usage: Callable[[], str]) -> bool:
    """Answer ``--version`` or ``-h``/``--help`` among the user's arguments (those before ``--ros-args``: the rest
    belongs to rcl), before any ROS start-up; True if one was answered."""
    user_args = argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv
    if "--version" in user_args:
        print(version_line(prog))
        return True
    if "-h" in user_args or "--help" in user_args:
        print(usage(), end="")
        return True
    return False


# A node's parameters, name: (type, default, description); the type is a word (string, integer, double,
# bool, string_array, double_array) so that the table and --help need no ROS. A default of None declares
# the parameter by type only (unset unless given).
ParameterTable = dict[str, tuple[str, Any, str]]


def parameter_help(table: ParameterTable, name_width: int, type_width: int) -> str:
    """The ``parameters:`` section of a node's usage text; the widths are minimums (a longer name or type widens its
    column for every row)."""
    name_width = max(name_width, *(len(n) for n in table))
    type_width = max(type_width, *(len(t) for t, _, _ in table.values()))
    return "".join(f"  {n:<{name_width}} {t:<{type_width}} default {d!r}\n      {desc}\n" for n, (t, d, desc) in table.items())


def version_line(prog: str) -> str:
    """What ``PROG --version`` prints, e.g. ``fbg-accel-calib 0.1.0``: the installed distribution's version (setup.py
    ``version``), read from its metadata."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"{prog} {version(DISTRIBUTION)}"
    except PackageNotFoundError:
        return f"{prog} unknown (package metadata not found: install with pip or colcon build)"


# Parameters every rclpy node has, besides its own (rclpy declares them itself).
ROS_BUILTIN_PARAMETERS = frozenset({"use_sim_time", "start_type_description_service"})


def unknown_parameters(given: Iterable[str], declared: Iterable[str]) -> list[str]:
    """One message per parameter name in ``given`` (``-p``/params-file overrides) that the node did not
    declare, naming the nearest declared name: rclpy would silently ignore them (``-p calibraton_file:=...``)."""
    import difflib

    known = set(declared) | ROS_BUILTIN_PARAMETERS
    out = []
    for name in sorted(set(given) - known):
        if name.startswith("qos_overrides."):  # only declared for the node's own topics; others are typos too
            near = difflib.get_close_matches(name, sorted(k for k in known if k.startswith("qos_overrides.")), n=1)
        else:
            near = difflib.get_close_matches(name, sorted(k for k in known if not k.startswith("qos_overrides.")), n=1,
                                             cutoff=0.5)
        hint = f" (did you mean '{near[0]}'?)" if near else ""
        out.append(f"unknown parameter '{name}'{hint}")
    return out


class StartupError(Exception):
    """A configuration problem that stops a node's start-up with one clear message (exit status 2). Control
    characters of the message (a parameter's escape sequence or line break echoed in it) are escaped
    (:func:`printable`): it is printed and logged as it is."""

    def __init__(self, message: str = "") -> None:
        super().__init__(printable(str(message)))


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (its type name if it has none)."""
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def one_line(text: str) -> str:
    """Fold a multi-line message (e.g. a YAML parser error with its caret lines) into one line."""
    parts = [ln.strip() for ln in text.splitlines()]
    return " ".join(p for p in parts if p and set(p) != {"^"})


# Top-level modules that come with ROS 2 (a sourced Jazzy install or the ros-jazzy-* wheels), not with ``pip install .``
ROS_MODULES = frozenset({"rclpy", "rcl_interfaces", "lifecycle_msgs", "sensor_msgs", "diagnostic_msgs", "geometry_msgs",
                         "std_msgs", "std_srvs", "builtin_interfaces", "ament_index_python", "rosidl_runtime_py"})


def missing_module_message(exc: ModuleNotFoundError) -> str:
    """One line saying what to install when a node's import fails with ``exc`` (a ROS 2 module, or another)."""
    name = (exc.name or "").split(".")[0] or "a module"
    if name in ROS_MODULES:
        return (f"ROS 2 Python module '{name}' not found: source a ROS 2 Jazzy install (source /opt/ros/jazzy/setup.bash) "
                f"or install the ROS 2 wheels (pip install -r requirements.txt)")
    return f"Python module '{name}' not found: install the package's dependencies (pip install -r requirements.txt)"


class Terminated(KeyboardInterrupt):
    """SIGTERM raised as an interruption (like Ctrl-C's ``KeyboardInterrupt``), so that every ``finally`` and every
    temporary-file clean-up runs; the exit status is ``128 + SIGTERM`` (143)."""


def interrupted_status(exc: KeyboardInterrupt) -> int:
    """Exit status of a run ended by ``exc``: 143 for SIGTERM (:class:`Terminated`), 130 for Ctrl-C."""
    import signal

    return 128 + (signal.SIGTERM if isinstance(exc, Terminated) else signal.SIGINT)


def exit_quietly_on_interrupt(prog: str) -> None:
    """First thing in an entry point, before its heavy imports (numpy, matplotlib, rclpy): Ctrl-C or
    SIGTERM then ends the process at once with one line and status 130 / 143 instead of a ``KeyboardInterrupt``
    traceback out of some import. Nothing is written yet at that stage, so nothing needs cleaning up."""
    import os
    import signal

    def leave(signum: int, frame: object) -> None:
        os.write(2, f"{prog}: interrupted\n".encode())
        os._exit(128 + signum)

    signal.signal(signal.SIGINT, leave)
    signal.signal(signal.SIGTERM, leave)


def raise_on_interrupt() -> None:
    """Once the entry point's own error handling is in place: Ctrl-C raises ``KeyboardInterrupt`` and SIGTERM
    :class:`Terminated`, so that the outputs being written are cleaned up (``atomic_output``)."""
    import signal

    def terminated(signum: int, frame: object) -> None:
        raise Terminated

    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, terminated)


def printable(text: str) -> str:
    """``text`` as is when every character is printable, else with its control characters (ANSI escape sequences,
    line breaks) written as escapes (``\\x1b``, ``\\n``): safe to echo in a one-line message or a log."""
    return text if text.isprintable() else text.encode("unicode_escape").decode("ascii")


def check_name_text(text: str, what: str) -> str:
    """``text`` if it holds no control character; else ``ValueError`` naming ``what`` with the value escaped. For
    names that are echoed and stored (a sensor_id: an ANSI escape sequence or a line break in it would recolour or
    forge lines of a terminal, a log or a report)."""
    if not text.isprintable():
        raise ValueError(f"{what} '{printable(text)}' holds control characters (escape sequences, line breaks); "
                         "use printable characters only")
    return text
