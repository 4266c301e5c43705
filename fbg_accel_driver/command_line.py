"""Command-line conventions shared by the package's executables (no ROS import)."""

from __future__ import annotations

DISTRIBUTION = "fbg_accel_driver"  # the setup.py ``name`` whose metadata carries the version


def _user_args(argv: list[str]) -> list[str]:
    """The user's own arguments: those before ``--ros-args`` (the rest belongs to rcl)."""
    return argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv


def wants_help(argv: list[str]) -> bool:
    """True if ``-h``/``--help`` appears among the user's arguments (those before ``--ros-args``)."""
    return any(a in ("-h", "--help") for a in _user_args(argv))


def wants_version(argv: list[str]) -> bool:
    """True if ``--version`` appears among the user's arguments (those before ``--ros-args``)."""
    return "--version" in _user_args(argv)


def package_version() -> str:
    """Version of the installed distribution (setup.py ``version``), read from its metadata."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(DISTRIBUTION)
    except PackageNotFoundError:
        return "unknown (package metadata not found: install with pip or colcon build)"


def version_line(prog: str) -> str:
    """What ``PROG --version`` prints, e.g. ``fbg-accel-calib 0.1.0``."""
    return f"{prog} {package_version()}"
