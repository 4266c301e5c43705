#!/usr/bin/env python3
"""Driver ingest benchmark: simulated board on a pty -> ``driver`` process -> rclpy subscriber process.

Not a test. For each board rate (default: 100 Hz, 1 kHz and the frame rate a 921600-baud 8N1 link
can carry, ``link_frame_rate_limit(921600)`` = 3413.3 frames/s) this script

* pre-generates the board's frames with the simulator (``BoardSimulator``, default physics, no
  injected faults, ``scenario.rate_hz`` set so the board's true rate is the wanted rate) so the
  physics costs nothing during the run;
* serves them on a pseudo-terminal (the simulator's ``PtyEndpoint``, raw mode) from this process,
  one ``write`` per frame, paced against ``CLOCK_MONOTONIC`` at the board rate (a pty does not
  emulate a baud rate, so the writer never offers more than the link could carry), and records the
  monotonic time just before each frame is written;
* runs the real driver as a separate process (``python -m fbg_accel_driver.driver_main``, default
  parameters, only ``port`` set: the publishers are exactly what users get) and a subscriber as a
  third process (this script with ``--role subscriber``: rclpy, best-effort QoS with a 100000-deep
  history as docs/topics.md recommends for a loss-free consumer) that stamps every ``imu/raw`` and
  ``imu/data_raw`` message with ``CLOCK_MONOTONIC`` on arrival in its callback;
* after a warm-up (discovery, clock-sync lock; frames of the warm-up are not evaluated) measures
  for ``--duration`` seconds: frames received once / written (loss and duplicates, matched by the
  board time stamp carried in ``imu/raw``), latency write -> subscriber callback (p50/p99/p99.9/max)
  for ``imu/raw`` and for ``imu/data_raw`` (matched through the shared header stamp), CPU of the
  driver process in % of one core (utime+stime of all its threads from /proc/<pid>/stat over the
  measured window) and its resident memory (VmRSS, sampled every second; growth = slope of a line
  fitted to the second half of the run);
* reads the driver's own counters from ``/diagnostics`` (decoder lost frames, CRC errors) so a loss
  can be attributed to the serial side or to DDS delivery.

``CLOCK_MONOTONIC`` is one clock for all processes of the machine, so write and receive times are
directly comparable. Results go to bench/results/driver_ingest.json.

Usage::

    # full: 100 Hz for 600 s, 1 kHz and the link rate for 60 s each
    ROS_DOMAIN_ID=31 .venv/bin/python bench/bench_driver_ingest.py
    ROS_DOMAIN_ID=31 .venv/bin/python bench/bench_driver_ingest.py --quick         # 20 s / 10 s / 10 s
    ROS_DOMAIN_ID=31 .venv/bin/python bench/bench_driver_ingest.py --case link --duration 30
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from machine_info import proc_field, results_doc, write_results  # noqa: E402
from output_paths import add_update_results, results_dir  # noqa: E402

from fbg_accel_driver.frame_codec import FRAME_SIZE_V1, link_frame_rate_limit  # noqa: E402

BAUD = 921600
LINK_RATE = link_frame_rate_limit(BAUD)
MONO = time.CLOCK_MONOTONIC
# case name -> (board rate in Hz, full duration s, quick duration s, subscribe imu/data_raw too)
# At the link rate the subscriber takes imu/raw only: a second 3413 msg/s subscription would cost the
# benchmark's own consumer another ~30 % of a core on a 2-core machine, which the driver then lacks.
CASES: dict[str, tuple[float, float, float, bool]] = {
    "100hz": (100.0, 600.0, 20.0, True),
    "1khz": (1000.0, 60.0, 10.0, True),
    "link": (LINK_RATE, 60.0, 10.0, False),
}
WARMUP_S = 3.0
GOALS = {"link_zero_loss": True, "p99_latency_ms_at_1khz": 5.0, "cpu_percent_of_core_at_100hz": 10.0}


def mono_ns() -> int:
    return time.clock_gettime_ns(MONO)


def realtime_minus_monotonic_ns(n: int = 20) -> int:
    """CLOCK_REALTIME - CLOCK_MONOTONIC in ns (the pair read closest together of ``n`` tries)."""
    best = None
    for _ in range(n):
        a = time.clock_gettime_ns(MONO)
        r = time.time_ns()
        b = time.clock_gettime_ns(MONO)
        if best is None or b - a < best[0]:
            best = (b - a, r - (a + b) // 2)
    return best[1]


# ----------------------------------------------------------------------------- /proc sampling
CLK_TCK = os.sysconf("SC_CLK_TCK")


def proc_cpu_s(pid: int) -> float:
    """utime + stime of all threads of ``pid`` in seconds (/proc/<pid>/stat fields 14, 15)."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def system_busy_s() -> float:
    """CPU seconds spent busy by all cores of the machine so far (/proc/stat, all but idle and iowait)."""
    with open("/proc/stat") as fh:
        v = [int(x) for x in fh.readline().split()[1:]]
    return (sum(v[:8]) - v[3] - v[4]) / CLK_TCK


def proc_rss_kib(pid: int) -> int:
    """Resident set size of ``pid`` in KiB (VmRSS of /proc/<pid>/status)."""
    return int((proc_field(f"/proc/{pid}/status", "VmRSS:") or "0").split()[0])


def proc_threads(pid: int) -> int:
    return int(proc_field(f"/proc/{pid}/status", "Threads:") or 0)


# ----------------------------------------------------------------------------- subscriber role
def run_subscriber(out_path: Path, with_imu: bool) -> int:
    """Subscribe imu/raw (+ imu/data_raw, /diagnostics), stamp arrivals, save on 'stop' from stdin."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu, JointState

    rclpy.init()
    node = rclpy.create_node("bench_ingest_subscriber")
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100000, reliability=ReliabilityPolicy.BEST_EFFORT)
    # *_src: DDS source timestamp (CLOCK_REALTIME ns at the driver's publish); raw_pubseq: DDS publication
    # sequence number (gaps = lost in delivery)
    cols: dict[str, list[int]] = {k: [] for k in ("raw_recv", "raw_tus", "raw_stamp", "raw_src", "raw_pubseq",
                                                  "imu_recv", "imu_stamp", "imu_src")}
    diag: dict[str, dict[str, str]] = {}

    def on_raw_one(msg: JointState, info: dict) -> None:
        cols["raw_recv"].append(time.clock_gettime_ns(MONO))
        cols["raw_tus"].append(round(msg.position[8] * 1e6))
        cols["raw_stamp"].append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
        cols["raw_src"].append(info["source_timestamp"])
        cols["raw_pubseq"].append(info["publication_sequence_number"])

    def on_imu_one(msg: Imu, info: dict) -> None:
        cols["imu_recv"].append(time.clock_gettime_ns(MONO))
        cols["imu_stamp"].append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
        cols["imu_src"].append(info["source_timestamp"])

    def subscribe_draining(msg_type: type, topic: str, one) -> None:
        """A subscription whose callback handles its message, then takes every further message already queued
        (one executor wake-up per burst instead of per message: the stock rclpy executor costs ~100 us per
        wake-up, which would make this subscriber, not the driver, the bottleneck)."""

        def cb(msg, info) -> None:
            one(msg, info)
            with sub.handle:
                while (taken := sub.handle.take_message(sub.msg_type, False)) is not None:
                    one(*taken)

        sub = node.create_subscription(msg_type, topic, cb, qos)

    def on_diag(msg: DiagnosticArray) -> None:
        for st in msg.status:
            diag[st.name] = {kv.key: kv.value for kv in st.values} | {"_level": str(st.level[0]), "_message": st.message}

    subscribe_draining(JointState, "imu/raw", on_raw_one)
    if with_imu:
        subscribe_draining(Imu, "imu/data_raw", on_imu_one)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    stop = threading.Event()

    def read_stdin() -> None:
        for line in sys.stdin:
            if line.strip() == "stop":
                break
        stop.set()

    threading.Thread(target=read_stdin, daemon=True).start()
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    print("READY", flush=True)
    next_report = time.monotonic()
    while not stop.is_set():
        ex.spin_once(timeout_sec=0.05)
        now = time.monotonic()
        if now >= next_report:
            print(f"COUNT {len(cols['raw_recv'])} {len(cols['imu_recv'])} {node.count_publishers('imu/raw')}", flush=True)
            next_report = now + 0.25
    np.savez(out_path, **{k: np.array(v, np.int64) for k, v in cols.items()}, diag=np.array(json.dumps(diag)))
    node.destroy_node()
    rclpy.try_shutdown()
    print("DONE", flush=True)
    return 0


class SubscriberProc:
    """The subscriber process and the latest counts it reported."""

    def __init__(self, out_path: Path, with_imu: bool, env: dict[str, str]) -> None:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--role", "subscriber", "--sub-out", str(out_path)]
        if not with_imu:
            cmd.append("--raw-only")
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        self.ready = threading.Event()
        self.done = threading.Event()
        self.raw = self.imu = self.publishers = 0
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "READY":
                self.ready.set()
            elif parts[0] == "COUNT":
                self.raw, self.imu, self.publishers = int(parts[1]), int(parts[2]), int(parts[3])
            elif parts[0] == "DONE":
                self.done.set()
        self.done.set()

    def stop(self, timeout_s: float = 60.0) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write("stop\n")
        self.proc.stdin.flush()
        self.done.wait(timeout_s)
        self.proc.wait(timeout_s)


def wait_for(cond, timeout_s: float, what: str, poll_s: float = 0.02) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(poll_s)


# ----------------------------------------------------------------------------- one case
def make_frames(rate_true_hz: float, n: int, seed: int) -> tuple[list[bytes], np.ndarray, float]:
    """``n`` clean frames of the default simulated board at a true rate of ``rate_true_hz``."""
    from fbg_accel_sim.board_physics import BoardSimulator, SimConfig

    cfg = SimConfig.default()
    ppm = float(cfg.get("board.clock_ppm"))
    sim = BoardSimulator(cfg.with_overrides({"scenario.rate_hz": rate_true_hz / (1.0 + ppm * 1e-6)}), seed=seed)
    pieces: list[bytes] = []
    t_us: list[np.ndarray] = []
    while len(pieces) < n:
        block = sim.step(min(65536, n - len(pieces)))
        data = block.wire_bytes()
        if len(data) != FRAME_SIZE_V1 * len(block):
            raise RuntimeError("simulator produced a faulty stream; the benchmark needs a clean one")
        pieces += [data[i : i + FRAME_SIZE_V1] for i in range(0, len(data), FRAME_SIZE_V1)]
        t_us.append(np.array([f.t_us for f in block.frames()], np.int64))
    return pieces, np.concatenate(t_us), sim.dt_true


def pct(a: np.ndarray, q: float) -> float | None:
    return float(np.percentile(a, q)) if len(a) else None


def latency_stats_ms(lat_ns: np.ndarray) -> dict[str, float | None]:
    ms = lat_ns / 1e6
    return {"p50": pct(ms, 50), "p90": pct(ms, 90), "p99": pct(ms, 99), "p99_9": pct(ms, 99.9),
            "max": float(ms.max()) if len(ms) else None, "mean": float(ms.mean()) if len(ms) else None}


def chain_calibration(mode: str, workdir: Path) -> str:
    """``sim``, or with a chain compensation a copy of the simulated sensor's calibration with a
    ``dynamic`` section holding the simulator's configured TIA cut-offs (config/sim_default.yaml):
    the bench measures the driver's cost, not a dynamic calibration."""
    if mode == "none":
        return "sim"
    import yaml

    from fbg_accel_driver.chain_compensation import ChainDynamics
    from fbg_accel_driver.driver_parameters import default_calibration_path
    from fbg_accel_driver.thermal_model import ThermalCalibration

    cutoffs = yaml.safe_load((ROOT / "config" / "sim_default.yaml").read_text())["electronics"]["tia_cutoff_hz"]
    cal = ThermalCalibration.load(default_calibration_path())
    cal.dynamic = ChainDynamics(cutoff_hz=tuple(float(v) for v in cutoffs))
    out = workdir / f"calibration_{mode}.yaml"
    cal.save(out)
    return str(out)


def run_case(name: str, rate_hz: float, duration_s: float, with_imu: bool, args: argparse.Namespace, workdir: Path) -> dict:
    from fbg_accel_sim.pty_server import PtyEndpoint

    n_warm = round(WARMUP_S * rate_hz)
    n_meas = round(duration_s * rate_hz)
    n_max_warm = round(30.0 * rate_hz)  # warm-up may be extended up to 30 s while discovery completes
    print(f"[{name}] generating {n_max_warm + n_meas} frames at {rate_hz:.1f} Hz ...", flush=True)
    pieces, t_us, dt_true = make_frames(rate_hz, n_max_warm + n_meas, args.seed)
    env = dict(os.environ)
    sub_out = workdir / f"sub_{name}.npz"
    ep = PtyEndpoint(None)
    path = ep.open(hold=False)
    sub = SubscriberProc(sub_out, with_imu, env)
    drv_log = open(workdir / f"driver_{name}.log", "w")
    cal = chain_calibration(args.chain_compensation, workdir)
    drv = subprocess.Popen([sys.executable, "-m", "fbg_accel_driver.driver_main", "--ros-args", "-p", f"port:={path}",
                            "-p", f"calibration_file:={cal}", "-p", f"chain_compensation:={args.chain_compensation}"],
                           stdout=drv_log, stderr=subprocess.STDOUT, env=env, cwd=str(args.driver_src or ROOT))
    spy = None
    write_ns = np.zeros(len(pieces), np.int64)
    late_ns = np.zeros(len(pieces), np.int64)
    rss: list[tuple[float, int]] = []
    cpu_series: list[tuple[float, float, float]] = []  # (s since start, driver CPU s, machine busy s)
    result: dict = {"case": name, "rate_hz": rate_hz, "duration_s": duration_s, "port": path}
    try:
        wait_for(sub.ready.is_set, 60, "the subscriber to start")
        wait_for(ep.client_present, 60, "the driver to open the pty")
        time.sleep(0.05)  # as the simulator's server: pyserial flushes its input while it opens the port
        ep.hold_slave()
        wait_for(lambda: sub.publishers > 0, 60, "the subscriber to discover the driver's imu/raw publisher")
        rt_off0 = realtime_minus_monotonic_ns()
        # ---- paced writing; warm-up until the subscriber has received frames, then the measured window
        t0 = mono_ns()
        period_ns = dt_true * 1e9
        k = 0
        meas_start = None
        next_sample = t0
        cpu0 = wall0 = cpu_sub0 = None
        while True:
            if meas_start is None and k >= n_warm and sub.raw > 0:
                meas_start = k
                wall0, cpu0, cpu_sub0 = mono_ns(), proc_cpu_s(drv.pid), proc_cpu_s(sub.proc.pid)
                cpu_self0, busy0 = time.process_time(), system_busy_s()
                if args.profile:
                    spy = start_profiler(drv.pid, duration_s, args.profile / f"profile_{name}.txt")
            if meas_start is None and k >= n_max_warm:
                raise RuntimeError(f"no imu/raw message reached the subscriber within {k / rate_hz:.0f} s of streaming")
            if meas_start is not None and k >= meas_start + n_meas:
                break
            due = t0 + int(k * period_ns)
            now = mono_ns()
            if now < due:
                time.sleep((due - now) / 1e9)  # no busy wait: the writer must not steal a core from the driver
                continue
            write_ns[k] = now
            late_ns[k] = now - due
            ep.write(pieces[k])
            k += 1
            if now >= next_sample:
                rss.append(((now - t0) / 1e9, proc_rss_kib(drv.pid)))
                cpu_series.append(((now - t0) / 1e9, proc_cpu_s(drv.pid), system_busy_s()))
                next_sample = now + 1_000_000_000
        wall1, cpu1, cpu_sub1 = mono_ns(), proc_cpu_s(drv.pid), proc_cpu_s(sub.proc.pid)
        cpu_self1, busy1 = time.process_time(), system_busy_s()
        rss.append(((wall1 - t0) / 1e9, proc_rss_kib(drv.pid)))
        threads = proc_threads(drv.pid)
        rt_off1 = realtime_minus_monotonic_ns()
        n_written = k
        # ---- let the pipeline drain: wait until the subscriber count stops changing (deadline 30 s)
        last, stable_since = -1, time.monotonic()
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            if sub.raw != last:
                last, stable_since = sub.raw, time.monotonic()
            elif sub.raw >= n_written or time.monotonic() - stable_since > 2.0:
                break
            time.sleep(0.05)
        if spy is not None:
            spy.wait(30)
        time.sleep(1.2)  # one more /diagnostics report (1 Hz) after the last frame; benchmark only, not a test
        sub.stop()
        drv.send_signal(signal.SIGINT)
        try:
            drv.wait(15)
        except subprocess.TimeoutExpired:
            drv.kill()
            drv.wait()
    except Exception:
        drv_log.flush()
        print(f"[{name}] driver log:\n" + (workdir / f"driver_{name}.log").read_text()[-3000:], file=sys.stderr)
        raise
    finally:
        if sub.proc.poll() is None:
            sub.proc.kill()
        if drv.poll() is None:
            drv.kill()
            drv.wait()
        drv_log.close()
        overflow = ep.overflow_bytes
        ep.close()
    d = np.load(sub_out)
    if args.save_raw:
        args.save_raw.mkdir(parents=True, exist_ok=True)
        np.savez(args.save_raw / f"ingest_{name}.npz", write_ns=write_ns[:n_written], t_us=t_us[:n_written],
                 meas_start=meas_start, n_meas=n_meas, **{k: d[k] for k in d.files})
    diag = json.loads(str(d["diag"]))
    # ---- evaluation over the measured frames [meas_start, meas_start + n_meas)
    idx_of = {int(t): i for i, t in enumerate(t_us[:n_written])}
    raw_idx = np.array([idx_of.get(int(t), -1) for t in d["raw_tus"]], np.int64)
    in_meas = (raw_idx >= meas_start) & (raw_idx < meas_start + n_meas)
    got = raw_idx[in_meas]
    uniq = np.unique(got)
    lat_raw = d["raw_recv"][in_meas] - write_ns[got]
    received_in_window = len(np.unique(got[d["raw_recv"][in_meas] <= wall1]))
    # imu/data_raw carries the same header stamp as the imu/raw message of the same frame
    stamp_to_idx = dict(zip(d["raw_stamp"].tolist(), raw_idx.tolist(), strict=True))
    imu_idx = np.array([stamp_to_idx.get(int(s), -1) for s in d["imu_stamp"]], np.int64)
    imu_in = (imu_idx >= meas_start) & (imu_idx < meas_start + n_meas)
    lat_imu = d["imu_recv"][imu_in] - write_ns[imu_idx[imu_in]]
    meas_wall_s = (wall1 - wall0) / 1e9
    # DDS source timestamps are CLOCK_REALTIME at the driver's publish(): split the latency there
    rt_off = (rt_off0 + rt_off1) // 2
    pub_mono = d["raw_src"][in_meas] - rt_off
    to_publish = pub_mono - write_ns[got]
    to_callback = d["raw_recv"][in_meas] - pub_mono
    pubseq = d["raw_pubseq"][in_meas]
    dds_lost = int(pubseq.max() - pubseq.min() + 1 - len(np.unique(pubseq))) if len(pubseq) else None
    rss_arr = np.array(rss, float)
    second_half = rss_arr[rss_arr[:, 0] >= rss_arr[:, 0].min() + 0.5 * (rss_arr[:, 0].max() - rss_arr[:, 0].min())]
    slope_kib_per_min = float(np.polyfit(second_half[:, 0], second_half[:, 1], 1)[0] * 60) if len(second_half) > 2 else None
    frames_diag = diag.get("fbg_accel_driver: frames", {})
    # driver CPU and the machine's busy cores per 60 s of the measured window (does the cost per frame drift?)
    cs = np.array([c for c in cpu_series if c[0] >= (wall0 - t0) / 1e9], float)
    per_min = []
    if len(cs) > 1:
        edges = np.arange(cs[0, 0], cs[-1, 0] + 1e-9, 60.0)
        for a0, a1 in itertools.pairwise(edges):
            i0, i1 = np.searchsorted(cs[:, 0], a0), min(np.searchsorted(cs[:, 0], a1), len(cs) - 1)
            if i1 > i0:
                span = cs[i1, 0] - cs[i0, 0]
                per_min.append([round(float(a0 - cs[0, 0])), round(100 * (cs[i1, 1] - cs[i0, 1]) / span, 1),
                                round(100 * (cs[i1, 2] - cs[i0, 2]) / span, 1)])
    late = late_ns[meas_start : meas_start + n_meas] / 1e6
    result.update({
        "frames_written": n_meas,
        "write_rate_fps": n_meas / meas_wall_s,
        "write_ratio_to_link_limit": (n_meas / meas_wall_s) / LINK_RATE,
        "frames_received_once": len(uniq),
        "frames_lost": int(n_meas - len(uniq)),
        "duplicates_received": int(len(got) - len(uniq)),
        "zero_loss": bool(len(uniq) == n_meas),
        "handled_rate_fps": len(uniq) / meas_wall_s,
        # sustained: measured frames whose imu/raw reached the subscriber before the writer finished (a driver
        # that falls behind delivers its backlog after the window: it loses nothing but does not keep up)
        "sustained_rate_fps": received_in_window / meas_wall_s,
        "ratio_to_link_limit": received_in_window / meas_wall_s / LINK_RATE,
        "backlog_at_end_frames": int(n_meas - received_in_window),
        "subscribed_imu_data_raw": with_imu,
        "imu_data_raw_received": int(imu_in.sum()) if with_imu else None,
        "latency_imu_raw_ms": latency_stats_ms(lat_raw),
        "latency_imu_data_raw_ms": latency_stats_ms(lat_imu) if with_imu else None,
        "latency_imu_raw_split_ms": {"write_to_driver_publish": latency_stats_ms(to_publish),
                                     "driver_publish_to_subscriber_callback": latency_stats_ms(to_callback),
                                     "realtime_minus_monotonic_drift_ns": int(rt_off1 - rt_off0)},
        "imu_raw_lost_in_dds_delivery": dds_lost,
        "writer_lateness_ms": {"p50": pct(late, 50), "p99": pct(late, 99), "max": float(late.max())},
        "pty_overflow_bytes": overflow,
        "driver_cpu_percent_of_core": 100.0 * (cpu1 - cpu0) / meas_wall_s,
        "subscriber_cpu_percent_of_core": 100.0 * (cpu_sub1 - cpu_sub0) / meas_wall_s,
        "writer_cpu_percent_of_core": 100.0 * (cpu_self1 - cpu_self0) / meas_wall_s,
        "other_processes_cpu_percent_of_core": 100.0 * ((busy1 - busy0) - (cpu1 - cpu0) - (cpu_sub1 - cpu_sub0)
                                                        - (cpu_self1 - cpu_self0)) / meas_wall_s,
        "load_average_1min_after": os.getloadavg()[0],
        "driver_threads": threads,
        "per_minute_driver_cpu_and_machine_busy_percent": per_min,
        "driver_rss_mib": {"start": rss_arr[0, 1] / 1024, "end": rss_arr[-1, 1] / 1024, "max": rss_arr[:, 1].max() / 1024,
                           "slope_second_half_kib_per_min": slope_kib_per_min,
                           "samples_every_1s": [[round(t, 1), int(v)] for t, v in rss] if args.keep_rss else None},
        "driver_diagnostics_frames": frames_diag,
        "profile": summarise_profile(args.profile / f"profile_{name}.txt") if args.profile else None,
        "measured_wall_s": meas_wall_s,
        "warmup_frames": meas_start,
    })
    return result


def start_profiler(pid: int, duration_s: float, out: Path) -> subprocess.Popen:
    """py-spy (requirements-dev.txt) sampling the driver for the measured window, collapsed stacks to ``out``."""
    out.parent.mkdir(parents=True, exist_ok=True)
    spy = Path(sys.executable).with_name("py-spy")
    return subprocess.Popen([str(spy), "record", "--pid", str(pid), "--duration", str(max(1, int(duration_s))), "--rate", "250",
                             "--nonblocking", "--format", "raw", "-o", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def summarise_profile(path: Path, top: int = 25) -> dict | None:
    """Share of py-spy samples per function (inclusive and self) from collapsed stacks.

    py-spy samples threads that are not idle, by wall clock: on a loaded machine a runnable thread
    waiting for a core counts too, so read these as shares of the driver's busy time, not CPU times.
    """
    if not path.exists():
        return None
    incl: dict[str, int] = {}
    self_: dict[str, int] = {}
    total = 0
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        stack, n_text = line.rsplit(" ", 1)
        n = int(n_text)
        total += n
        frames = [f.replace(str(ROOT) + "/", "").split("site-packages/")[-1] for f in stack.split(";")]
        for f in set(frames):
            incl[f] = incl.get(f, 0) + n
        self_[frames[-1]] = self_.get(frames[-1], 0) + n

    def share(d: dict[str, int]) -> list[list]:
        return [[f, round(100 * n / total, 1)] for f, n in sorted(d.items(), key=lambda kv: -kv[1])[:top]]

    return {"samples": total, "file": str(path), "inclusive_percent": share(incl), "self_percent": share(self_)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 epilog="Cases: 100hz (100 Hz, 600 s), 1khz (1000 Hz, 60 s), "
                                        "link (3413.3 Hz = 921600 baud, 60 s).")
    ap.add_argument("--case", action="append", choices=list(CASES), help="run only this case (repeatable; default all)")
    ap.add_argument("--quick", action="store_true", help="short runs (20 s at 100 Hz, 10 s otherwise); not for the README")
    ap.add_argument("--duration", type=float, help="measured seconds of every selected case (overrides the defaults)")
    ap.add_argument("--seed", type=int, default=0, help="simulator seed")
    ap.add_argument("--chain-compensation", choices=["none", "delay", "equalise"], default="none",
                    help="driver parameter chain_compensation (a calibration with the simulator's TIA cut-offs)")
    ap.add_argument("--raw-only", action="store_true", help="subscribe imu/raw only (not imu/data_raw) in every case")
    ap.add_argument("--keep-rss", action="store_true", help="store the 1 s RSS series in the JSON")
    ap.add_argument("--driver-src", type=Path,
                    help="run the driver from this source tree instead of the repository (A/B test of a driver change)")
    ap.add_argument("--profile", type=Path, help="sample the driver with py-spy during each measured window; "
                    "collapsed stacks into this directory, top functions into the JSON")
    ap.add_argument("--save-raw", type=Path, help="also save write/receive times per case as .npz in this directory")
    ap.add_argument("--output", type=Path, help="output file (default: driver_ingest.json in the scratch or results directory)")
    add_update_results(ap)
    ap.add_argument("--role", choices=["bench", "subscriber"], default="bench", help=argparse.SUPPRESS)
    ap.add_argument("--sub-out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.output = args.output or results_dir(args.update_results) / "driver_ingest.json"
    if args.role == "subscriber":
        return run_subscriber(args.sub_out, not args.raw_only)
    if "ROS_DOMAIN_ID" not in os.environ:
        print("bench_driver_ingest: warning: ROS_DOMAIN_ID not set; other ROS processes on this machine may cross-talk",
              file=sys.stderr)
    cases = args.case or list(CASES)
    results = []
    with tempfile.TemporaryDirectory(prefix="bench_ingest_") as tmp:
        for name in cases:
            rate, full, quick, with_imu = CASES[name]
            duration = args.duration if args.duration is not None else (quick if args.quick else full)
            r = run_case(name, rate, duration, with_imu and not args.raw_only, args, Path(tmp))
            results.append(r)
            lr, li = r["latency_imu_raw_ms"], r["latency_imu_data_raw_ms"] or {}
            print(f"[{name}] {r['frames_received_once']}/{r['frames_written']} frames once "
                  f"(sustained {r['sustained_rate_fps']:.1f} fps = {r['ratio_to_link_limit']:.3f} x link), "
                  f"lost {r['frames_lost']}, backlog at end {r['backlog_at_end_frames']}, "
                  f"latency imu/raw p50 {lr['p50']:.2f} p99 {lr['p99']:.2f} ms, "
                  f"imu/data_raw p99 {li.get('p99') or float('nan'):.2f} ms, "
                  f"driver CPU {r['driver_cpu_percent_of_core']:.1f} %, RSS {r['driver_rss_mib']['start']:.1f}->"
                  f"{r['driver_rss_mib']['end']:.1f} MiB", flush=True)
    by = {r["case"]: r for r in results}
    goals = {}
    if "link" in by:
        lk = by["link"]
        goals["link_zero_loss"] = lk["zero_loss"]
        # in real time: at the end of the window at most 50 ms of frames not yet delivered
        goals["link_kept_up_in_real_time"] = lk["backlog_at_end_frames"] <= 0.05 * lk["rate_hz"]
    if "1khz" in by:
        goals["p99_latency_under_5ms_at_1khz"] = by["1khz"]["latency_imu_raw_ms"]["p99"] < GOALS["p99_latency_ms_at_1khz"]
    if "100hz" in by:
        goals["cpu_under_10pct_at_100hz"] = by["100hz"]["driver_cpu_percent_of_core"] < GOALS["cpu_percent_of_core_at_100hz"]
    doc = results_doc("bench_driver_ingest.py", argv, "driver ingest: pty -> driver process -> rclpy subscriber process") | {
        "quick": bool(args.quick),
        "ros_domain_id": os.environ.get("ROS_DOMAIN_ID"),
        "link": {"baud": BAUD, "frame_bytes": FRAME_SIZE_V1, "bits_per_byte": 10, "frames_per_s_limit": LINK_RATE},
        "warmup_s_min": WARMUP_S,
        "goals": goals,
        "results": results,
    }
    write_results(args.output, doc)
    print(f"goals: {goals}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
