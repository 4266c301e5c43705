"""What machine a benchmark ran on (CPU model, logical CPUs, RAM, Python, OS), and the header and writing of
every results file."""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import sys
from pathlib import Path
from typing import Any


def proc_field(path: str, key: str) -> str | None:
    """What follows the colon on the first line of a /proc file that starts with ``key`` (None: no such line)."""
    with open(path) as fh:
        return next((line.split(":", 1)[1].strip() for line in fh if line.startswith(key)), None)


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (else what platform knows)."""
    try:
        return proc_field("/proc/cpuinfo", "model name") or platform.processor() or "unknown"
    except OSError:
        return platform.processor() or "unknown"


def machine() -> dict:
    """CPU model, logical CPUs, RAM in GiB, Python, numpy, OS and the load average right now."""
    try:
        mem_kib = proc_field("/proc/meminfo", "MemTotal:")
    except OSError:
        mem_kib = None
    mem_gib = int(mem_kib.split()[0]) / 1024**2 if mem_kib else None
    import numpy as np

    return {"cpu": cpu_model(), "logical_cpus": os.cpu_count(), "ram_gib": round(mem_gib, 1) if mem_gib else None,
            "python": platform.python_version(), "numpy": np.__version__, "platform": platform.platform(),
            "load_average_1_5_15": [round(v, 2) for v in os.getloadavg()]}


def results_doc(script: str, argv: list[str] | None, benchmark: str | None = None, **fields: Any) -> dict:
    """A results file's content: what ran (``benchmark``, the command line of ``bench/<script>`` with ``argv``,
    else this process's arguments), when (UTC) and on what machine, then ``fields``."""
    args = argv if argv is not None else sys.argv[1:]
    return {**({"benchmark": benchmark} if benchmark else {}), "command": f"python bench/{script} " + " ".join(args),
            "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), "machine": machine(), **fields}


def write_results(path: Path, doc: dict, indent: int = 2) -> None:
    """Write ``doc`` as JSON to ``path`` (folders made; numpy arrays as lists) and say where."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=indent, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)) + "\n")
    print(f"results written to {path}")
