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
