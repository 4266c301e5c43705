"""Issue 42, items 9 and 11: Ctrl-C or SIGTERM at any moment of ``fbg-accel-calib`` and ``board_sim`` (the console
scripts, as real processes): while their modules are still being imported (the first ~0.8 s / 0.15 s: a
``KeyboardInterrupt`` traceback and exit -2 before) or while they write (a partial ``.part.mcap`` of tens of MB
was left by SIGTERM). Always one line on stderr, exit 130 (SIGINT) or 143 (SIGTERM), no file left behind.

Synchronisation is on observable states, never on sleeps: the process has mapped numpy (it is importing: numpy
is not imported before the entry point's handler is installed), or its temporary output file exists."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

BIN = Path(sys.executable).parent
HEADER = "t_s,ref_counts,x_counts,y_counts,z_counts,gref_x_mps2,gref_y_mps2,gref_z_mps2,temperature_c,pose\n"
POSES = ["0,0,9.8", "0,0,-9.8", "9.8,0,0", "-9.8,0,0", "0,9.8,0", "0,-9.8,0"]


def big_csv(path: Path, rows: int = 30_000) -> Path:
    """A six-pose CSV long enough that importing it takes about a second (the window for a signal)."""
    per = rows // len(POSES)
    path.write_text(HEADER + "".join(f"{i * 0.01:.2f},880,{1000 + i % 7}.5,1500.25,1200.75,{POSES[i // per]},23.4,"
                                     f"{i // per}\n" for i in range(per * len(POSES))))
    return path


def wait_for(condition: Callable[[], bool], proc: subprocess.Popen, timeout_s: float = 120.0) -> None:
    """Poll ``condition`` (a state of the process, not a time) until true; fail if the process ended first."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert proc.poll() is None, f"ended early ({proc.returncode}): {proc.communicate()[1][-2000:]}"
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.001)  # polling interval, not synchronisation


def importing(proc: subprocess.Popen) -> Callable[[], bool]:
    def mapped() -> bool:
        try:
            return "numpy" in Path(f"/proc/{proc.pid}/maps").read_text()
        except OSError:
            return False

    return mapped


def writing(work: Path) -> Callable[[], bool]:
    return lambda: any(".part" in p.name for p in work.iterdir())


COMMANDS = {
    "fbg-accel-calib": ["import", "big.csv", "-o", "out.mcap"],
    "board_sim": ["--duration", "100000", "--output", "out.bin", "--truth", "truth.npz"],
}


def run_and_signal(work: Path, prog: str, sig: int, when: str) -> tuple[int, str]:
    inputs = {"big.csv"}
    big_csv(work / "big.csv")
    proc = subprocess.Popen([str(BIN / prog), *COMMANDS[prog]], cwd=work, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        wait_for(importing(proc) if when == "importing" else writing(work), proc)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert sorted(p.name for p in work.iterdir()) == sorted(inputs), "a file was left behind"
    return proc.returncode, err


@pytest.mark.parametrize("prog", sorted(COMMANDS))
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("when", ["importing", "writing"])
def test_an_interrupt_at_any_moment_is_one_line_and_leaves_nothing(tmp_path: Path, prog: str, sig: int,
                                                                   when: str) -> None:
    rc, err = run_and_signal(tmp_path, prog, sig, when)
    lines = err.strip().splitlines()
    assert rc == 128 + sig, (rc, err[-2000:])
    assert len(lines) == 1 and "Traceback" not in err and prog in lines[0], err[-2000:]
    # fbg-accel-calib loads numpy only in the command, after its handlers are set: a SIGTERM while it loads is the
    # command's "terminated"; board_sim says "interrupted" for both signals
    assert ("terminated" if sig == signal.SIGTERM and prog != "board_sim" else "interrupted") in lines[0], lines[0]
