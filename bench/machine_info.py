"""What machine a benchmark ran on: CPU model, logical CPUs, RAM, Python, OS (for every results file)."""

from __future__ import annotations

import os
import platform
from pathlib import Path


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (else what platform knows)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine() -> dict:
    """CPU model, logical CPUs, RAM in GiB, Python, numpy, OS and the load average right now."""
    mem_gib = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                mem_gib = int(line.split()[1]) / 1024**2
                break
    except OSError:
        pass
    import numpy as np

    return {"cpu": cpu_model(), "logical_cpus": os.cpu_count(), "ram_gib": round(mem_gib, 1) if mem_gib else None,
            "python": platform.python_version(), "numpy": np.__version__, "platform": platform.platform(),
            "load_average_1_5_15": [round(v, 2) for v in os.getloadavg()]}
