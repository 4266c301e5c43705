"""Entry point of the ``board_sim`` console script: Ctrl-C and SIGTERM are handled from the first instant
(``command_line.exit_quietly_on_interrupt``: one line, exit 130 / 143) while the simulator's modules (numpy)
are imported and the configuration is read; ``board_sim.main`` then installs its own handlers, which
end the run in order. No heavy import at module level."""

from __future__ import annotations

import sys

from fbg_accel_driver.command_line import exit_quietly_on_interrupt


def main(argv: list[str] | None = None) -> int:
    exit_quietly_on_interrupt("board_sim")
    from .board_sim import main as board_sim_main

    return board_sim_main(argv)


if __name__ == "__main__":
    sys.exit(main())
