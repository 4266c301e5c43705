"""The offline tools' progress bars: off, they draw nothing and start nothing."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)


def test_a_bar_that_is_off_starts_no_thread_and_imports_no_tqdm() -> None:
    """``--no-progress`` (or stderr not a terminal): every pass of a counted source and the diagnosis' bar go through
    without tqdm, whose disabled bar still starts a monitor thread that lives to the end of the process."""
    code = (
        "import sys, threading\n"
        "from fbg_accel_calibration.io.source_progress import CountedSource, bar\n"
        "class Source:\n"
        "    def blocks(self):\n"
        "        yield [1, 2, 3]\n"
        "        yield [4]\n"
        "src = CountedSource(Source(), 'x', on=False)\n"
        "assert [len(b) for b in src.blocks()] == [3, 1] and [len(b) for b in src.blocks()] == [3, 1]\n"
        "with bar(False, 'diagnose') as b:\n"
        "    b.update(1)\n"
        "print(sorted(t.name for t in threading.enumerate()), 'tqdm' in sys.modules, src.total)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.split() == ["['MainThread']", "False", "4"], out.stdout + out.stderr
    assert out.stderr == ""
