#!/usr/bin/env python3
"""Per-frame cost of the driver's stages, to locate the hot path (companion of bench_driver_ingest.py).

Not a test. Each stage is timed in this process with the CPU time of the calling thread
(``time.thread_time_ns``), at the frame spacing of a real stream (100 Hz, 1 kHz, the 921600-baud
link limit) or back to back, because the cost per frame of a Python + numpy pipeline depends a lot on
whether the caches are warm:

* ``serial_chunks``: ``SerialLink`` reading a pty on which one frame is written every 10 ms: chunks
  (and consumer notifications) per frame;
* ``core_feed``: ``DriverCore.feed`` (decoder, clock sync, calibration eq. 24/28, policies) with one
  frame per call (as the serial link delivers it at 100 Hz), also split in 1 + 26 bytes, and with 10 or
  100 frames per call;
* ``messages``: filling the ``imu/raw``, ``imu/temperature`` and ``imu/data_raw`` messages of one frame
  (the driver's ``DriverMessages``) and publishing them (rclpy, sensor-data QoS, no subscriber);
* ``executor_wakeup``: one wake-up of rclpy's ``SingleThreadedExecutor`` by a guard condition
  triggered from another thread (how the driver node first handed chunks to its publisher), against one
  wake-up of a plain Python thread blocked in ``queue.SimpleQueue.get`` (how it does now).

Writes driver_stages.json to the scratch directory (``--output`` a file, ``--update-results`` the committed
bench/results/). Needs ROS_DOMAIN_ID for the rclpy steps. ``--core-only`` times ``core_feed`` back to back only (no
serial, no rclpy). ``--calibration-uncertainty`` times ``core_feed`` with a calibration that carries a
``coefficient_covariance`` (a positive definite one of the right size: the cost does not depend on its values),
``reported`` (only the last sample's point kept for the diagnostics) or ``included``
(``covariance_includes_calibration``: J Sigma J^T per published sample). ``--adc-codes TABLE``: the calibration
carries that code table (``fbg-accel-calib adc-codes -o``), so its cost shows against a run without.
``--gravity-check``: the live gravity check on (``gravity_mps2`` set), its cost against a run without.

    ROS_DOMAIN_ID=31 .venv/bin/python bench/bench_driver_stages.py
    .venv/bin/python bench/bench_driver_stages.py --core-only --calibration-uncertainty included
    .venv/bin/python bench/bench_driver_stages.py --core-only [--adc-codes TABLE.yaml] [--gravity-check]
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from machine_info import results_doc, write_results  # noqa: E402
from output_paths import add_update_results, results_dir  # noqa: E402

from fbg_accel_driver.coefficient_covariance import CoefficientCovariance  # noqa: E402
from fbg_accel_driver.driver_core import CoreConfig, DriverCore  # noqa: E402
from fbg_accel_driver.frame_codec import FRAME_SIZE_V1, link_frame_rate_limit  # noqa: E402
from fbg_accel_driver.sensor_constants import STANDARD_GRAVITY  # noqa: E402
from fbg_accel_driver.thermal_model import ThermalCalibration  # noqa: E402
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig  # noqa: E402

LINK_RATE = link_frame_rate_limit(921600)
RATES = {"back_to_back": None, "1khz": 1000.0, "100hz": 100.0}


def frames_bytes(n: int) -> bytes:
    sim = BoardSimulator(SimConfig.default().with_overrides({"scenario.rate_hz": 1000.0}), seed=0)
    return sim.step_bytes(n)


def paced(n: int, rate: float | None, work) -> float:
    """Mean thread CPU (us) of ``work(i)`` called ``n`` times, ``1/rate`` apart (back to back if None)."""
    total = 0
    t_next = time.monotonic()
    for i in range(n):
        if rate:
            t_next += 1.0 / rate
            time.sleep(max(0.0, t_next - time.monotonic()))
        t = time.thread_time_ns()
        work(i)
        total += time.thread_time_ns() - t
    return total / n / 1e3


def bench_core(n: int, data: bytes, cal: ThermalCalibration, config: CoreConfig | None = None,
               rates: dict[str, float | None] = RATES) -> dict:
    out: dict[str, dict[str, float]] = {}
    splits = {"1+26 bytes": None, "1 frame": 1, "10 frames": 10, "100 frames": 100}
    for label, per in splits.items():
        if per is None:
            pieces = [p for i in range(0, len(data), FRAME_SIZE_V1) for p in (data[i:i + 1], data[i + 1:i + FRAME_SIZE_V1])]
            calls_per_frame = 2
        else:
            pieces = [data[i:i + per * FRAME_SIZE_V1] for i in range(0, len(data), per * FRAME_SIZE_V1)]
            calls_per_frame = 1 / per
        out[label] = {}
        for rname, rate in rates.items():
            if per is not None and per > 1 and rate:
                continue  # batches only happen when the consumer is behind: back to back is the relevant case
            core = DriverCore(cal, config)
            h = time.time_ns()
            m = min(len(pieces), int(n * calls_per_frame))
            def work(i: int, c: DriverCore = core, p: list[bytes] = pieces, h: int = h) -> None:
                c.feed(p[i], h + i * 500_000)

            us = paced(m, rate * calls_per_frame if rate else None, work)
            out[label][rname] = us * calls_per_frame  # per frame
    return out


def bench_messages(n: int) -> dict:
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Imu, JointState, Temperature

    from fbg_accel_driver.driver_core import ImuRecord, RawRecord, TemperatureRecord
    from fbg_accel_driver.frame_codec import Frame
    from fbg_accel_driver.ros_messages import DriverMessages

    node = rclpy.create_node("bench_driver_stages_pub")
    pr = node.create_publisher(JointState, "bench_stages/raw", qos_profile_sensor_data)
    pt = node.create_publisher(Temperature, "bench_stages/temperature", qos_profile_sensor_data)
    pi = node.create_publisher(Imu, "bench_stages/imu", qos_profile_sensor_data)
    msgs = DriverMessages("fbg_accel_link")  # the driver node's message filling
    frame = Frame(seq=1, t_us=1000, ref=870, x=1130, y=1650, z=1130, temp_cc=2340, status=3)
    cov = (0.01, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0, 0.0, 0.01)

    def work(i: int) -> None:
        stamp = 1_000_000_000 + i
        pr.publish(msgs.raw_msg(RawRecord(stamp, frame, 23.4, True)))
        pt.publish(msgs.temperature_msg(TemperatureRecord(stamp, 23.4, 0.09)))
        pi.publish(msgs.imu_msg(ImuRecord(stamp, (0.01, -0.02, 9.81), cov, 23.4, frozenset())))

    res = {rname: paced(n if rate is None else min(n, int(3 * rate)), rate, work) for rname, rate in RATES.items()}
    node.destroy_node()
    return res


def bench_wakeups(seconds: float) -> dict:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    res: dict[str, dict[str, float]] = {"rclpy_guard_condition": {}, "python_queue_thread": {}}
    for rname, rate in (("100hz", 100.0), ("1khz", 1000.0), ("link", LINK_RATE)):
        # rclpy executor woken by a guard condition (the node also holds a 1 Hz timer, as the driver)
        node = rclpy.create_node("bench_driver_stages_wake")
        count = [0]
        guard = node.create_guard_condition(lambda c=count: c.__setitem__(0, c[0] + 1))
        node.create_timer(1.0, lambda: None)
        ex = SingleThreadedExecutor()
        ex.add_node(node)
        stop = threading.Event()

        def trigger(rate: float = rate, g=guard, stop: threading.Event = stop) -> None:
            t_next = time.monotonic()
            while not stop.is_set():
                t_next += 1.0 / rate
                time.sleep(max(0.0, t_next - time.monotonic()))
                g.trigger()

        th = threading.Thread(target=trigger, daemon=True)
        th.start()
        t_end = time.monotonic() + seconds
        c0 = time.thread_time_ns()
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.1)
        cpu = time.thread_time_ns() - c0
        stop.set()
        th.join()
        res["rclpy_guard_condition"][rname] = cpu / max(1, count[0]) / 1e3
        ex.shutdown()
        node.destroy_node()
        # a plain thread blocked in SimpleQueue.get
        q: queue.SimpleQueue = queue.SimpleQueue()
        got = [0, 0]

        def consumer(q=q, got=got) -> None:
            c = time.thread_time_ns()
            while (item := q.get()) is not None:
                got[0] += 1
                del item
            got[1] = time.thread_time_ns() - c

        th = threading.Thread(target=consumer, daemon=True)
        th.start()
        t_next = time.monotonic()
        t_end = t_next + seconds
        while t_next < t_end:
            t_next += 1.0 / rate
            time.sleep(max(0.0, t_next - time.monotonic()))
            q.put(1)
        q.put(None)
        th.join()
        res["python_queue_thread"][rname] = got[1] / max(1, got[0]) / 1e3
    return res


def bench_serial_chunks(n: int, data: bytes) -> dict:
    from fbg_accel_driver.serial_link import SerialLink
    from fbg_accel_sim.pty_server import PtyEndpoint

    ep = PtyEndpoint(None)
    path = ep.open(hold=True)
    wakes = [0]
    link = SerialLink(path, 921600, notify=lambda: wakes.__setitem__(0, wakes[0] + 1))
    link.start()
    deadline = time.monotonic() + 10
    while link.status().state.value != "connected" and time.monotonic() < deadline:
        time.sleep(0.01)
    wakes[0] = 0
    t_next = time.monotonic()
    for i in range(n):
        t_next += 0.01
        time.sleep(max(0.0, t_next - time.monotonic()))
        ep.write(data[i * FRAME_SIZE_V1:(i + 1) * FRAME_SIZE_V1])
    deadline = time.monotonic() + 5
    chunks, nbytes = 0, 0
    while nbytes < n * FRAME_SIZE_V1 and time.monotonic() < deadline:
        try:
            _, c, _ = link.queue.get(timeout=0.1)
        except queue.Empty:
            continue
        chunks += 1
        nbytes += len(c)
    link.stop()
    ep.close()
    return {"frames": n, "bytes": nbytes, "chunks": chunks, "chunks_per_frame": chunks / n,
            "notifications_per_frame": wakes[0] / n}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=2000, help="frames per timed case (paced cases take at most 3 s)")
    ap.add_argument("--wake-seconds", type=float, default=3.0, help="seconds per wake-up case")
    ap.add_argument("--output", type=Path, help="output file (default: driver_stages.json in the scratch or results directory)")
    add_update_results(ap)
    ap.add_argument("--calibration-uncertainty", choices=["absent", "reported", "included"], default="absent",
                    help="the calibration's coefficient_covariance: absent, reported in the diagnostics only, or "
                    "included in the covariance (covariance_includes_calibration)")
    ap.add_argument("--gravity-check", action="store_true", help="with the live gravity check on (gravity_mps2 set)")
    ap.add_argument("--core-only", action="store_true", help="time core_feed only, back to back (no serial, no rclpy)")
    ap.add_argument("--adc-codes", type=Path, default=None, help="code table YAML the calibration carries")
    args = ap.parse_args(argv)
    output = args.output or results_dir(args.update_results) / "driver_stages.json"

    data = frames_bytes(max(args.frames, 1000) * 2)
    cal = ThermalCalibration.load(ROOT / "config" / "calibration_sim.yaml")
    if args.adc_codes is not None:
        from fbg_accel_driver.adc_code_table import load_table

        cal.adc_codes = load_table(args.adc_codes)
    config = None
    if args.calibration_uncertainty != "absent":
        p = 12 * (cal.degree + 1)
        cal.coefficient_covariance = CoefficientCovariance(np.eye(p) * 1e-4 + 1e-5, "bench", 18)
        config = CoreConfig(covariance_includes_calibration=args.calibration_uncertainty == "included")
    if args.gravity_check:
        config = replace(config or CoreConfig(), gravity_mps2=STANDARD_GRAVITY)
    results: dict = {"calibration_uncertainty": args.calibration_uncertainty, "gravity_check": args.gravity_check,
                     "adc_codes": str(args.adc_codes) if args.adc_codes else None}
    n100 = min(args.frames, 300)
    rates = {"back_to_back": None} if args.core_only else RATES
    results["core_feed_us_cpu_per_frame"] = bench_core(args.frames, data, cal, config, rates) | {"frames_at_100hz": n100}
    print("core:", json.dumps(results["core_feed_us_cpu_per_frame"]), flush=True)
    if args.core_only:
        write_results(output, results_doc("bench_driver_stages.py", argv, "driver stage costs per frame (thread CPU "
                                          "time, us)", results=results))
        return 0
    results["serial_chunks_at_100hz"] = bench_serial_chunks(300, data)
    print("serial:", results["serial_chunks_at_100hz"], flush=True)
    import rclpy

    rclpy.init()
    try:
        results["messages_build_publish_us_cpu_per_frame"] = bench_messages(args.frames)
        print("messages:", results["messages_build_publish_us_cpu_per_frame"], flush=True)
        results["wakeup_us_cpu"] = bench_wakeups(args.wake_seconds)
        print("wake-ups:", results["wakeup_us_cpu"], flush=True)
    finally:
        rclpy.try_shutdown()
    write_results(output, results_doc("bench_driver_stages.py", argv, "driver stage costs per frame (thread CPU time, us)",
                                      results=results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
