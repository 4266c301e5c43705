#!/usr/bin/env python3
"""Does the driver's Python data path keep memory? tracemalloc over a long stream (no ROS, no DDS).

Not a test. Feeds ``--frames`` simulated 100 Hz frames, one frame per call as the serial link
delivers them at that rate, through ``DriverCore.feed`` and the node's message filling
(``DriverMessages``; nothing is published), and compares the Python heap (``tracemalloc``, after a
full ``gc.collect()``) after a warm-up of ``--warmup`` frames with the heap at the end. The bytes
the simulator generates are excluded (only the driver's files count). It separates a leak in the
driver's own Python code from the resident-memory slope of the whole process that
bench_driver_ingest.py reports (which also contains DDS, the allocator and the interpreter).

    .venv/bin/python bench/bench_core_memory.py             # writes bench/results/core_memory.json
"""

from __future__ import annotations

import argparse
import gc
import sys
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from machine_info import results_doc, write_results  # noqa: E402
from output_paths import add_update_results, results_dir  # noqa: E402

from fbg_accel_driver.driver_core import DriverCore  # noqa: E402
from fbg_accel_driver.frame_codec import FRAME_SIZE_V1  # noqa: E402
from fbg_accel_driver.ros_messages import DriverMessages  # noqa: E402
from fbg_accel_driver.thermal_model import ThermalCalibration  # noqa: E402
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig  # noqa: E402

RATE_HZ = 100.0


def driver_heap_bytes(snapshot: tracemalloc.Snapshot) -> int:
    """Bytes allocated from the driver's own modules still alive (the simulator is the package fbg_accel_sim)."""
    keep = tracemalloc.Filter(True, str(ROOT / "fbg_accel_driver" / "*"))
    return sum(s.size for s in snapshot.filter_traces([keep]).statistics("filename"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=360_000, help="measured frames (default: 1 h at 100 Hz)")
    ap.add_argument("--warmup", type=int, default=20_000, help="frames before the first snapshot")
    ap.add_argument("--output", type=Path, help="output file (default: core_memory.json in the scratch or results directory)")
    add_update_results(ap)
    args = ap.parse_args(argv)
    args.output = args.output or results_dir(args.update_results) / "core_memory.json"

    cal = ThermalCalibration.load(ROOT / "config" / "calibration_sim.yaml")
    sim = BoardSimulator(SimConfig.default().with_overrides({"scenario.rate_hz": RATE_HZ}), seed=0)
    core = DriverCore(cal)
    msgs = DriverMessages("fbg_accel_link")
    fed = 0

    def run(n: int) -> None:
        nonlocal fed
        while n > 0:
            block = min(n, 5000)
            data = sim.step_bytes(block)
            for j in range(0, len(data), FRAME_SIZE_V1):
                out = core.feed(data[j:j + FRAME_SIZE_V1], 1_000_000_000 + round(fed * 1e9 / RATE_HZ))
                fed += 1
                for r in out.raw:
                    msgs.raw_msg(r)
                for t in out.temperature:
                    msgs.temperature_msg(t)
                for s in out.imu:
                    msgs.imu_msg(s)
            n -= block

    tracemalloc.start()
    run(args.warmup)
    gc.collect()
    before = driver_heap_bytes(tracemalloc.take_snapshot())
    run(args.frames)
    gc.collect()
    after = driver_heap_bytes(tracemalloc.take_snapshot())
    tracemalloc.stop()
    hours = args.frames / RATE_HZ / 3600
    res = results_doc("bench_core_memory.py", argv, "driver data path Python heap over a long stream (tracemalloc)") | {
        "rate_hz": RATE_HZ, "warmup_frames": args.warmup, "measured_frames": args.frames, "board_hours": hours,
        "imu_published": core.counters.imu_published, "driver_heap_kib_after_warmup": before / 1024,
        "driver_heap_kib_at_end": after / 1024, "growth_kib": (after - before) / 1024,
        "growth_kib_per_board_hour": (after - before) / 1024 / hours}
    write_results(args.output, res, indent=1)
    print(f"{args.frames} frames ({hours:.2f} h at {RATE_HZ:g} Hz): driver heap {before / 1024:.1f} -> {after / 1024:.1f} KiB "
          f"({(after - before) / 1024:+.1f} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
