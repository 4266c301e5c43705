#!/usr/bin/env python3
"""Driver under a source faster than its decoder: resident memory and what the reader queue dropped.

Not a test. Issue 11 found that a source faster than the decoder made the driver's reader queue
grow without bound (322 MB, RSS +10 MB/s). This script

* pre-encodes valid v1 frames (increasing seq and board time, counts of a sensor at rest, a valid
  temperature) with ``frame_codec.encode_frame``;
* serves them on a raw pseudo-terminal as fast as the driver's reader thread takes them (blocking
  ``os.write`` of 64 KiB blocks: a pty carries several MB/s, far above the 92 kB/s of the real
  921600-baud link and above what the decoder and publishers handle);
* runs the real driver as a separate process (``python -m fbg_accel_driver.driver_main``, only
  ``port`` and ``reader_queue_max_bytes`` set) and samples its VmRSS every second;
* subscribes to ``/diagnostics`` in this process and keeps the driver's ``reader queue`` entry.

Results: bench/results/reader_flood.json (RSS per second, the slope over the second half, bytes
written, the queue counters at the end).

Usage::

    ROS_DOMAIN_ID=37 .venv/bin/python bench/bench_reader_flood.py --duration 60
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import pty
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_driver_ingest import proc_rss_kib  # noqa: E402
from machine_info import machine  # noqa: E402
from output_paths import add_update_results, results_dir  # noqa: E402

from fbg_accel_driver.frame_codec import SEQ_MODULO, Frame, Status, encode_frame  # noqa: E402


def make_stream(n: int) -> bytes:
    """``n`` valid frames at a nominal 10 kHz board clock (the rate only sets the stamps)."""
    rng = np.random.default_rng(1)
    noise = rng.integers(-3, 4, size=(n, 4))
    return b"".join(
        encode_frame(Frame(seq=i % SEQ_MODULO, t_us=1_000_000 + 100 * i, ref=2000 + int(noise[i, 0]),
                           x=1500 + int(noise[i, 1]), y=1500 + int(noise[i, 2]), z=2600 + int(noise[i, 3]),
                           temp_cc=2500, status=int(Status.TEMP_VALID)))
        for i in range(n)
    )


def driver_has_open(pid: int, path: str) -> bool:
    try:
        return any(os.readlink(f"/proc/{pid}/fd/{fd}") == path for fd in os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return False


def diagnostics_listener(latest: dict, ready: threading.Event, stop: threading.Event) -> None:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Imu, JointState

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("reader_flood_bench", context=ctx)

    def on_diag(msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name.endswith("reader queue") or s.name.endswith("frames"):
                latest[s.name.split(": ", 1)[1]] = {"level": s.level[0], "message": s.message,
                                                     **{kv.key: kv.value for kv in s.values}}
                ready.set()

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    counts = latest.setdefault("_received", {"imu/raw": 0, "imu/data_raw": 0})

    def counter(topic: str):
        def cb(_msg: object) -> None:
            counts[topic] += 1
        return cb

    # a consumer of the data topics: delivering to a subscriber is what makes publishing cost
    node.create_subscription(JointState, "imu/raw", counter("imu/raw"), qos_profile_sensor_data)
    node.create_subscription(Imu, "imu/data_raw", counter("imu/data_raw"), qos_profile_sensor_data)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.2)
    node.destroy_node()
    rclpy.shutdown(context=ctx)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of flood")
    ap.add_argument("--queue-bytes", type=int, default=262144, help="driver parameter reader_queue_max_bytes")
    ap.add_argument("--frames", type=int, default=400_000, help="frames pre-encoded (the stream is cycled)")
    ap.add_argument("--driver-src", type=Path, default=ROOT,
                    help="source tree whose fbg_accel_driver is run (e.g. a worktree of an older commit)")
    ap.add_argument("--out", type=Path, help="output file (default: reader_flood.json in the scratch or results directory)")
    add_update_results(ap)
    args = ap.parse_args(argv)
    args.out = args.out or results_dir(args.update_results) / "reader_flood.json"

    print(f"encoding {args.frames} frames ...", flush=True)
    stream = make_stream(args.frames)
    master, slave = pty.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    latest: dict = {}
    diag_ready, stop = threading.Event(), threading.Event()
    listener = threading.Thread(target=diagnostics_listener, args=(latest, diag_ready, stop), daemon=True)
    listener.start()
    drv = subprocess.Popen([sys.executable, "-m", "fbg_accel_driver.driver_main", "--ros-args", "-p", f"port:={path}",
                            "-p", "calibration_file:=sim",
                            "-p", f"reader_queue_max_bytes:={args.queue_bytes}"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=str(args.driver_src))
    rss: list[tuple[float, int]] = []
    written = 0
    try:
        deadline = time.monotonic() + 60
        while not driver_has_open(drv.pid, path):
            if time.monotonic() > deadline or drv.poll() is not None:
                raise RuntimeError("the driver did not open the pty")
            time.sleep(0.05)
        time.sleep(0.5)  # pyserial flushes its input right after opening the port
        t0 = time.monotonic()
        next_rss = t0
        view = memoryview(stream)
        pos = 0
        while (now := time.monotonic()) - t0 < args.duration:
            if now >= next_rss:
                rss.append((now - t0, proc_rss_kib(drv.pid)))
                next_rss += 1.0
            chunk = view[pos:pos + 65536]
            n = os.write(master, chunk)
            written += n
            pos = (pos + n) % len(stream)
        diag_ready.clear()
        if not diag_ready.wait(5.0):
            print("warning: no /diagnostics received after the flood", flush=True)
        time.sleep(1.2)  # one more 1 Hz diagnostics report after the flood ended
    finally:
        drv.terminate()
        drv.wait(10)
        stop.set()
        listener.join(5)
        os.close(master)
        os.close(slave)
    t = np.array([r[0] for r in rss])
    m = np.array([r[1] for r in rss], float) / 1024.0
    half = t >= t[-1] / 2
    slope = float(np.polyfit(t[half], m[half], 1)[0]) if half.sum() >= 2 else float("nan")
    result = {
        "when": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": machine(),
        "duration_s": args.duration,
        "reader_queue_max_bytes": args.queue_bytes,
        "driver_source": subprocess.run(["git", "-C", str(args.driver_src), "rev-parse", "--short", "HEAD"],
                                        capture_output=True, text=True).stdout.strip(),
        "bytes_written": written,
        "write_rate_MBps": written / args.duration / 1e6,
        "rss_mib_start": float(m[0]), "rss_mib_max": float(m.max()), "rss_mib_end": float(m[-1]),
        "rss_slope_second_half_mib_per_s": slope,
        "rss_series": [[round(a, 1), b] for a, b in rss],
        "diagnostics_at_end": latest,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    q = latest.get("reader queue", {})
    print(f"wrote {written / 1e6:.1f} MB in {args.duration:g} s ({result['write_rate_MBps']:.2f} MB/s); driver RSS "
          f"{m[0]:.1f} -> max {m.max():.1f} MiB, slope over the second half {slope * 1024:+.1f} KiB/s; reader queue: "
          f"dropped {q.get('queue_dropped_bytes', '?')} bytes in {q.get('queue_dropped_chunks', '?')} chunks "
          f"(bound {q.get('queue_max_bytes', '?')})")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
