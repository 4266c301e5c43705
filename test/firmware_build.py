"""Compile the firmware's host programs (firmware/host) into a temporary directory for the tests.

A missing C compiler or a failing build fails the test with the compiler's message: the firmware
core is part of what the suite checks, so it must not be skipped silently.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HOST_DIR = REPO / "firmware" / "host"
CORE_DIR = REPO / "firmware" / "core"


@dataclass(frozen=True)
class FirmwareHostPrograms:
    """Paths of the compiled host programs."""

    fbg_encode: Path
    fbg_board_host: Path


def find_compiler() -> str:
    """The C compiler: $CC, else ``cc``, else ``gcc``. AssertionError with what to do if none."""
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and shutil.which(name):
            return name
    raise AssertionError(
        "no C compiler found ($CC, cc, gcc): the firmware core tests need one to build firmware/host; "
        "install gcc (Debian/Ubuntu: apt-get install gcc make)"
    )


CFLAGS = ["-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic"]  # as in firmware/host/Makefile
PROGRAMS = {"fbg_encode": ["fbg_encode.c"], "fbg_board_host": ["fbg_board_host.c", "aht10_sim_device.c"]}


def build_host_programs(out_dir: Path) -> FirmwareHostPrograms:
    """Compile fbg_encode and fbg_board_host into ``out_dir`` with the Makefile's strict flags (no make needed)."""
    cc = find_compiler()
    core = sorted(str(p) for p in CORE_DIR.glob("*.c"))
    for name, sources in PROGRAMS.items():
        cmd = [cc, *CFLAGS, f"-I{CORE_DIR}", "-o", str(out_dir / name), *(str(HOST_DIR / s) for s in sources), *core]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if res.returncode != 0:
            raise AssertionError(f"compiling firmware/host/{name} failed (exit {res.returncode}):\n{' '.join(cmd)}\n"
                                 f"{res.stdout}{res.stderr}")
    return FirmwareHostPrograms(out_dir / "fbg_encode", out_dir / "fbg_board_host")
