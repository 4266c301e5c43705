"""Entry point of the ``fbg-accel-calib`` console script: Ctrl-C and SIGTERM are handled from the first instant
(``command_line.exit_quietly_on_interrupt``) before the tool's heavy modules (numpy, scipy) are imported; then
they interrupt the run and ``cli.main`` removes its partial outputs (exit 130 / 143, one line). No heavy import
at module level."""

from __future__ import annotations

import atexit
import gc
import sys

from fbg_accel_driver.command_line import exit_quietly_on_interrupt, interrupted_status, raise_on_interrupt

PROG = "fbg-accel-calib"


def _freeze_at_exit() -> None:
    """At exit, the interpreter's last garbage collections walk every object still alive (numpy's, scipy's and
    matplotlib's modules, a diagnosis' results): 0.1-0.2 s CPU of a command (bench/diagnose_command.py). Frozen out of
    them instead, the objects go with the process's memory; every output is closed (and renamed) before main returns."""
    gc.freeze()


def main(argv: list[str] | None = None) -> int:
    exit_quietly_on_interrupt(PROG)
    atexit.unregister(_freeze_at_exit)  # once however often main() runs in one process
    atexit.register(_freeze_at_exit)
    from .cli import main as cli_main

    raise_on_interrupt()
    try:
        return cli_main(argv)
    except KeyboardInterrupt as exc:  # before or after the subcommand's own handling (argument parsing)
        print(f"{PROG}: interrupted", file=sys.stderr)
        return interrupted_status(exc)


if __name__ == "__main__":
    sys.exit(main())
