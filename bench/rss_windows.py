#!/usr/bin/env python3
"""Resident-memory slope of the driver per window of a run, from a bench_driver_ingest.py JSON.

Needs a results file written with ``--keep-rss`` (the 1 s VmRSS series). A leak grows at a constant
rate; start-up allocations (DDS history, allocator arenas, caches) grow ever more slowly. The slope
per window (straight-line fit, KiB per minute) tells them apart.

    .venv/bin/python bench/rss_windows.py bench/results/driver_soak.json [--window-s 300]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def rss_slopes(samples: list[list[float]], window_s: float) -> list[dict]:
    """Per window of ``window_s`` seconds: start (s), RSS at its start and end (MiB), slope (KiB/min)."""
    s = np.asarray(samples, dtype=float)
    out = []
    for a in np.arange(s[0, 0], s[-1, 0], window_s):
        m = (s[:, 0] >= a) & (s[:, 0] < a + window_s)
        if m.sum() > 2 and np.ptp(s[m, 0]) >= 0.5 * window_s:  # a short last window says nothing
            slope = float(np.polyfit(s[m, 0] / 60.0, s[m, 1], 1)[0])
            out.append({"start_s": float(a), "rss_start_mib": float(s[m, 1][0] / 1024),
                        "rss_end_mib": float(s[m, 1][-1] / 1024), "slope_kib_per_min": round(slope, 1)})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="a bench_driver_ingest.py JSON written with --keep-rss")
    ap.add_argument("--window-s", type=float, default=300.0, help="window length in seconds (default 300)")
    args = ap.parse_args(argv)
    for case in json.loads(args.results.read_text())["results"]:
        samples = case["driver_rss_mib"].get("samples_every_1s")
        if not samples:
            print(f"{args.results}: case {case['case']} has no RSS series (run the benchmark with --keep-rss)", file=sys.stderr)
            return 2
        print(f"case {case['case']} ({case['duration_s']:.0f} s):")
        for w in rss_slopes(samples, args.window_s):
            print(f"  {w['start_s']:6.0f} s  {w['rss_start_mib']:.2f} -> {w['rss_end_mib']:.2f} MiB  "
                  f"{w['slope_kib_per_min']:+.1f} KiB/min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
