"""The driver as a real process, against the ROS 2 conventions a navigation stack relies on (issue 10).

One launch of the simulated board with two drivers:

* driver A on the board (``calibration_file: sim``): REP 2003 QoS (a *default* reliable subscriber
  receives ``imu/data_raw``, the publisher offers RELIABLE), ``hardware_id`` is the calibrated
  sensor's id, ``decimation`` is settable with a parameter call while data flows and the message
  rate follows it, a read-only parameter is refused, and SIGINT while data flows ends with status 0
  and no ERROR in the log;
* driver B under a namespace on a port that does not exist, ``calibration_file: none`` and a QoS
  override: no ``imu/data_raw`` publisher, ``imu/raw`` offered BEST_EFFORT as overridden.

No sleeps: every wait is a condition polled with a deadline while spinning the executor.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from rcl_interfaces.msg import ParameterType
from rclpy.context import Context
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import ReliabilityPolicy
from sensor_msgs.msg import Imu
from test_driver_process import REPO, Listener, start_driver, start_sim, stop

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)


def _call(listener: Listener, future, what: str):
    listener.wait_until(future.done, 20, what)
    return future.result()


def test_qos_parameters_hardware_id_and_clean_shutdown(ros: Context, tmp_path: Path) -> None:
    link = tmp_path / "board"
    listener = Listener("test_ros_conventions", ros)
    default_imu: list[Imu] = []
    listener.node.create_subscription(Imu, "imu/data_raw", default_imu.append, 10)  # rclpy default: reliable
    sim, _ = start_sim(["--link", str(link), "--duration", "60", "--seed", "5"])
    log_a, log_b = tmp_path / "driver_a.log", tmp_path / "driver_b.log"
    drv_a = start_driver({"port": str(link)}, log_a)
    drv_b = start_driver({"port": str(tmp_path / "absent"), "calibration_file": "none",
                          "qos_overrides./veh2/imu/raw.publisher.reliability": "best_effort"},
                         log_b, ros_args=("-r", "__ns:=/veh2"))
    try:
        node = listener.node
        listener.wait_until(lambda: len(default_imu) >= 50, 40, "a default (reliable) subscriber receives imu/data_raw")
        offered = node.get_publishers_info_by_topic("/imu/data_raw")
        assert [i.qos_profile.reliability for i in offered] == [ReliabilityPolicy.RELIABLE]

        listener.wait_until(lambda: node.count_publishers("/veh2/imu/raw") >= 1, 30, "driver B's imu/raw publisher")
        assert [i.qos_profile.reliability for i in node.get_publishers_info_by_topic("/veh2/imu/raw")] == \
            [ReliabilityPolicy.BEST_EFFORT]
        assert node.count_publishers("/veh2/imu/data_raw") == 0  # raw only: no calibrated topic at all

        sensor_id = yaml.safe_load((REPO / "config" / "calibration_sim.yaml").read_text())["sensor_id"]
        hw: set[str] = set()
        from diagnostic_msgs.msg import DiagnosticArray

        node.create_subscription(DiagnosticArray, "/diagnostics",
                                 lambda m: hw.update(s.hardware_id for s in m.status
                                                     if s.name.split(": ")[0] in ("fbg_accel_driver",
                                                                                  "veh2/fbg_accel_driver")), 10)
        listener.wait_until(lambda: sensor_id in hw and "uncalibrated" in hw, 10,
                            "hardware_id = the calibration's sensor id (driver A) and 'uncalibrated' (driver B)")
        assert not any("/" in h for h in hw), hw  # not the port

        # decimation at run time: the imu/data_raw rate follows, imu/raw stays at the board rate
        client = AsyncParameterClient(node, "fbg_accel_driver")
        assert client.wait_for_services(timeout_sec=20.0)
        res = _call(listener, client.set_parameters([Parameter("decimation", Parameter.Type.INTEGER, 10)]),
                    "set decimation")
        assert res.results[0].successful, res.results[0].reason
        res = _call(listener, client.set_parameters([Parameter("baud", Parameter.Type.INTEGER, 115200)]), "set baud")
        assert not res.results[0].successful and "read-only" in res.results[0].reason.lower()
        res = _call(listener, client.set_parameters([Parameter("decimation", Parameter.Type.INTEGER, 0)]),
                    "set decimation 0")
        assert not res.results[0].successful
        got = _call(listener, client.get_parameters(["decimation"]), "get decimation")
        assert got.values[0].type == ParameterType.PARAMETER_INTEGER and got.values[0].integer_value == 10

        n_imu, n_raw = len(default_imu), len(listener.raw)
        listener.wait_until(lambda: len(listener.raw) - n_raw >= 400, 20, "400 more raw samples")
        ratio = (len(listener.raw) - n_raw) / max(1, len(default_imu) - n_imu)
        assert 8.0 <= ratio <= 12.5, ratio

        # Ctrl-C while data flows: status 0, nothing logged at ERROR, no rosout failure
        assert stop(drv_a) == 0
        assert stop(drv_b) == 0
        text_a = log_a.read_text()
        assert "[ERROR]" not in text_a, text_a  # (driver B logs its absent port at ERROR, rightly)
        for text in (text_a, log_b.read_text()):
            assert "Failed to publish log message" not in text and "context is invalid" not in text, text
            assert "Traceback" not in text, text
    finally:
        stop(sim)
        stop(drv_a)
        stop(drv_b)
        listener.close()


def _has_open(pid: int, path: Path) -> bool:
    """Whether process ``pid`` holds ``path`` (the pty behind the simulator's link) open."""
    import os

    target = os.path.realpath(path)
    fd_dir = Path(f"/proc/{pid}/fd")
    for fd in fd_dir.iterdir():
        try:
            if os.readlink(fd) == target:
                return True
        except OSError:
            continue
    return False


def test_managed_driver_follows_its_lifecycle(ros: Context, tmp_path: Path) -> None:
    """``driver --managed``: unconfigured = port closed, nothing published; configure opens the port and
    decodes (diagnostics count frames) without publishing; activate publishes; deactivate stops
    publishing; cleanup closes the port; SIGINT exits 0."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState
    from test_driver_process import BIN

    link = tmp_path / "board"
    listener = Listener("test_lifecycle", ros)
    raw: list = []
    from sensor_msgs.msg import JointState

    listener.node.create_subscription(JointState, "imu/raw", raw.append, 10)
    sim, _ = start_sim(["--link", str(link), "--duration", "60", "--seed", "6"])
    log = tmp_path / "managed.log"
    import subprocess

    drv = subprocess.Popen([str(BIN / "driver"), "--managed", "--ros-args", "-p", f"port:={link}",
                            "-p", "calibration_file:=sim"], stdout=log.open("w"), stderr=subprocess.STDOUT)
    try:
        node = listener.node
        client = node.create_client(ChangeState, "/fbg_accel_driver/change_state")
        assert client.wait_for_service(timeout_sec=30.0), log.read_text()

        def change(tid: int) -> bool:
            fut = client.call_async(ChangeState.Request(transition=Transition(id=tid)))
            listener.wait_until(fut.done, 20, f"transition {tid}")
            return fut.result().success

        assert not _has_open(drv.pid, link) and not listener.diag  # unconfigured: nothing opened or published
        assert change(Transition.TRANSITION_CONFIGURE)
        listener.wait_until(lambda: bool(listener.diag) and int(listener.last("frames")[2]["frames"]) >= 50, 20,
                            "configured: frames decoded and diagnosed")
        assert _has_open(drv.pid, link) and raw == [] and listener.imu == []
        assert change(Transition.TRANSITION_ACTIVATE)
        listener.wait_until(lambda: len(raw) >= 50 and len(listener.imu) >= 50, 20, "active: data published")
        assert change(Transition.TRANSITION_DEACTIVATE)
        n_after = len(raw)
        frames_then = int(listener.last("frames")[2]["frames"])
        listener.wait_until(lambda: int(listener.last("frames")[2]["frames"]) >= frames_then + 150, 20,
                            "inactive: 150 more frames decoded")
        assert len(raw) <= n_after + 5  # at most what was already in flight
        assert change(Transition.TRANSITION_CLEANUP)
        assert not _has_open(drv.pid, link)  # the port is released
        assert stop(drv) == 0
        text = log.read_text()
        assert "[ERROR]" not in text and "Traceback" not in text, text
    finally:
        stop(sim)
        stop(drv)
        listener.close()
