"""``fbg-accel-calib`` leaves the interpreter's last garbage collections nothing to walk: the objects alive when it
exits (its libraries' modules, a diagnosis' results) are frozen out of them (``cli_main.main``), once however often
``main`` runs in the process. Checked in a fresh interpreter, as a user's command runs."""

from __future__ import annotations

import subprocess
import sys

# an exit handler registered before main() runs after main's own (last in, first out): it sees what the
# interpreter's final collections will see, and how often the objects were frozen
_PROBE = """
import atexit, contextlib, gc, io
freeze, calls = gc.freeze, []
gc.freeze = lambda: calls.append(1) or freeze()
atexit.register(lambda: print("frozen", gc.get_freeze_count(), "times", len(calls)))
from fbg_accel_calibration.commands.cli_main import main
for _ in range(2):
    with contextlib.redirect_stdout(io.StringIO()):
        try:
            main(["--help"])
        except SystemExit:
            pass
"""


def test_the_command_freezes_what_is_left_at_exit_once() -> None:
    out = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, check=True, timeout=120)
    words = out.stdout.split()
    assert words[0] == "frozen" and int(words[1]) > 1000, out.stdout  # the modules' objects, not a handful
    assert words[2:] == ["times", "1"], out.stdout  # one exit handler for two runs of main()
