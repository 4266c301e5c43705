"""``fbg-accel-calib``: the argument parser, the entry point and the subcommands' wiring (no numpy at import)."""
