"""Command-line conventions shared by the package's ROS executables (no ROS import)."""

from __future__ import annotations


def wants_help(argv: list[str]) -> bool:
    """True if ``-h``/``--help`` appears among the user's arguments (those before ``--ros-args``)."""
    user = argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv
    return any(a in ("-h", "--help") for a in user)
