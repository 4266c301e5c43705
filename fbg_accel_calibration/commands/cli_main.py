"""Entry point of the ``fbg-accel-calib`` console script: Ctrl-C and SIGTERM are handled from the first instant
(``command_line.exit_quietly_on_interrupt``) before the tool's heavy modules (numpy, scipy) are imported; then
they interrupt the run and ``cli.main`` removes its partial outputs (exit 130 / 143, one line). No heavy import
at module level."""

from __future__ import annotations

import sys

from fbg_accel_driver.command_line import exit_quietly_on_interrupt, interrupted_status, raise_on_interrupt

PROG = "fbg-accel-calib"


def main(argv: list[str] | None = None) -> int:
    exit_quietly_on_interrupt(PROG)
    from .cli import main as cli_main

    raise_on_interrupt()
    try:
        return cli_main(argv)
    except KeyboardInterrupt as exc:  # before or after the subcommand's own handling (argument parsing)
        print(f"{PROG}: interrupted", file=sys.stderr)
        return interrupted_status(exc)


if __name__ == "__main__":
    sys.exit(main())
