"""Live demo: simulated board on a pty + the driver, acceleration and temperature printed live.

``python -m fbg_accel_sim.demo --seconds N`` (used by scripts/demo.sh) starts ``board_sim``
and ``driver`` as separate processes (exactly as on a ROS machine: the driver reads the pty
through pyserial), subscribes with rclpy, prints a line twice a second for N seconds, then stops
both processes with SIGINT and reports what it received. Uses the ROS_DOMAIN_ID of the
environment. Exit status 0 when data arrived, 1 otherwise.
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import subprocess
import sys
import time
from typing import Any

SIM_CMD = "import sys; from fbg_accel_sim.board_sim import main; sys.exit(main())"
DRIVER_CMD = "import sys; from fbg_accel_driver.driver_main import main; sys.exit(main())"


def start_board_sim(extra: list[str], timeout_s: float = 20.0) -> tuple[subprocess.Popen, str]:
    """Start ``board_sim`` on a pty; return the process and the pty path it printed."""
    proc = subprocess.Popen([sys.executable, "-c", SIM_CMD, *extra], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ready, _, _ = select.select([proc.stdout], [], [], max(0.0, deadline - time.monotonic()))
        if not ready:
            break
        line = proc.stdout.readline()
        if not line:
            break
        if line.startswith("PTY "):
            return proc, line.split(None, 1)[1].strip()
    stop(proc)
    raise RuntimeError(f"board_sim did not print 'PTY <path>' within {timeout_s:g} s (exit status {proc.poll()})")


def start_driver(port: str, extra_params: dict[str, Any] | None = None) -> subprocess.Popen:
    args = [sys.executable, "-c", DRIVER_CMD, "--ros-args", "-p", f"port:={port}", "-p", "calibration_file:=sim"]
    for k, v in (extra_params or {}).items():
        args += ["-p", f"{k}:={v}"]
    return subprocess.Popen(args)


def stop(proc: subprocess.Popen, timeout_s: float = 10.0) -> int | None:
    """SIGINT, then wait; SIGKILL only if it does not exit in time. Returns the exit status."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if proc.stdout is not None:
        proc.stdout.close()
    return proc.returncode


def run(seconds: float) -> int:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu, Temperature

    print(f"ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')}; starting the simulated board ...", flush=True)
    sim, pty = start_board_sim([])
    print(f"board_sim serves {pty}; starting the driver on it ...", flush=True)
    driver = start_driver(pty)
    rclpy.init()
    node = rclpy.create_node("fbg_accel_demo")
    state: dict[str, Any] = {"imu": None, "n": 0, "temp": None, "diag": {}}

    def on_imu(m: Imu) -> None:
        state["imu"] = m
        state["n"] += 1

    def on_temp(m: Temperature) -> None:
        state["temp"] = m.temperature

    def on_diag(m: DiagnosticArray) -> None:
        state["diag"] = {s.name.split(": ", 1)[-1]: (s.level[0] if isinstance(s.level, bytes) else s.level, s.message)
                         for s in m.status}

    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    node.create_subscription(Imu, "imu/data_raw", on_imu, qos)
    node.create_subscription(Temperature, "imu/temperature", on_temp, qos)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    received = 0
    try:
        first_deadline = time.monotonic() + 20.0
        while state["imu"] is None and time.monotonic() < first_deadline and driver.poll() is None:
            rclpy.spin_once(node, timeout_sec=0.1)
        if state["imu"] is None:
            print("error: no imu/data_raw message within 20 s (driver exit status "
                  f"{driver.poll()}); see the driver's messages above", file=sys.stderr)
            return 1
        t0 = time.monotonic()
        next_print = t0
        last_n = state["n"]
        while (now := time.monotonic()) < t0 + seconds:
            rclpy.spin_once(node, timeout_sec=0.05)
            if now >= next_print:
                m = state["imu"]
                a = m.linear_acceleration
                norm = (a.x**2 + a.y**2 + a.z**2) ** 0.5
                rate = (state["n"] - last_n) / 0.5 if now > t0 else 0.0
                last_n = state["n"]
                t = state["temp"]
                t_txt = f"{t:6.2f} degC" if t is not None else "  n/a"
                print(f"t={now - t0:5.1f} s  a = [{a.x:+8.4f} {a.y:+8.4f} {a.z:+8.4f}] m/s^2  |a| = {norm:7.4f}  "
                      f"T = {t_txt}  ({rate:5.1f} msg/s)", flush=True)
                next_print += 0.5
        received = state["n"]
        diag = state["diag"]
        if diag:
            worst = max(level for level, _ in diag.values())
            names = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
            print(f"diagnostics: {names.get(worst, worst)}; " + "; ".join(f"{k}: {msg}" for k, (_, msg) in diag.items()))
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        rc_driver = stop(driver)
        rc_sim = stop(sim)
        print(f"received {received} imu/data_raw messages; driver exit {rc_driver}, board_sim exit {rc_sim}", flush=True)
    return 0 if received > 0 else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fbg_accel_sim.demo", description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0, help="how long to show live data (s, default 8)")
    args = ap.parse_args(argv)
    if args.seconds <= 0:
        ap.error("--seconds must be > 0")
    try:
        return run(args.seconds)
    except RuntimeError as exc:
        print(f"demo: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
