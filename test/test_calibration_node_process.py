"""The ``calibration`` node as a real process over real DDS (ROS_DOMAIN_ID from the environment).

The test process publishes a synthetic ``imu/raw`` stream (a known linear sensor model on a table
following the plan, noise, integer ADC counts) and checks what the node wrote:

* the MCAP round-trips through the ``mcap`` reader with the ROS 2 decoder (``mcap_ros2``), message
  for message against what was published (count and content), with the poses labelled;
* SIGKILL mid-run leaves a file that reads up to its last chunk, and the fit uses it;
* SIGINT / SIGTERM close the file cleanly (summary and footer), exit status 3;
* operator mode over the ``calibration/next_pose`` service; bad start-up input gives one clear error.

No sleeps as synchronisation: every wait is on a condition (a line printed by the node, a process
exit, a DDS match, a future) with a deadline.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from process_harness import ChildProcess, Notifier
from ros2_mcap import ros2_messages

from fbg_accel_calibration.io.mcap_reader import read_file, read_recording
from fbg_accel_calibration.io.table_geometry import table_specific_force
from fbg_accel_calibration.recorder.pose_plan import PosePlan

ROOT = Path(__file__).resolve().parents[1]
CALIBRATION_EXE = Path(sys.executable).parent / "calibration"
RATE_HZ = 200.0  # board rate of the synthetic stream (board time; published faster than real time)
PUBLISH_BATCH = 5  # messages per 5 ms timer tick: 1000 messages/s of wall time
# Known linear sensor (paper section 4.3 magnitudes): a = M Psi + b, Psi = M^-1 (a - b)
M_TRUE = np.array([[81.60, 2.89, 0.71], [1.59, 77.66, 3.75], [0.24, 1.23, 107.66]])
B_TRUE = np.array([-101.08, -153.59, -137.16])
REF_COUNTS = 870.0
PSI_NOISE = 8e-4  # Psi noise std per sample (~0.07 m/s^2)

PLAN = {
    "format": "fbg_accel_pose_plan", "format_version": 1, "name": "process_test",
    "samples_per_pose": 60, "dwell_s": 2.0, "move_s": 0.5,
    "poses": [
        {"name": "z_up", "psi_deg": 0, "theta_deg": 0, "dwell_s": 4.0},  # first pose: noise learning (2 s, set below) + record
        {"name": "z_down", "psi_deg": 0, "theta_deg": 180},
        {"name": "x_up", "psi_deg": 90, "theta_deg": 90},
        {"name": "y_up", "psi_deg": 0, "theta_deg": 90},
        {"name": "x_down", "psi_deg": 270, "theta_deg": 90},
    ],
}

pytestmark = [pytest.mark.real_time, pytest.mark.timeout(120)]


# ---------------------------------------------------------------------------- synthetic stream
@dataclass
class Stream:
    positions: np.ndarray  # (N, 9) JointState.position in RAW_NAMES order
    stamps_ns: np.ndarray  # (N,)
    pose_of_sample: np.ndarray  # (N,) pose index while the table stands, -1 while it moves


def make_stream(plan: PosePlan, seed: int = 0, t0_ns: int = 1_700_000_000_000_000_000, tail_s: float = 1.0) -> Stream:
    """Table following the plan (dwell, then a linear move in the table angles), sensor = known linear model."""
    rng = np.random.default_rng(seed)
    seg_g, seg_pose = [], []
    angles = [(p.psi_deg, p.theta_deg) for p in plan.poses]
    for k, p in enumerate(plan.poses):
        n = round(p.dwell_s * RATE_HZ)
        seg_g.append(np.repeat(p.gref_mps2[None], n, axis=0))
        seg_pose.append(np.full(n, k))
        if k + 1 < len(plan.poses):
            m = round(plan.move_s * RATE_HZ)
            s = np.linspace(0, 1, m + 2)[1:-1]
            (pa, ta), (pb, tb) = angles[k], angles[k + 1]
            seg_g.append(table_specific_force(pa + s * (pb - pa), ta + s * (tb - ta), plan.local_g_mps2))
            seg_pose.append(np.full(m, -1))
    n_tail = int(tail_s * RATE_HZ)
    seg_g.append(np.repeat(plan.poses[-1].gref_mps2[None], n_tail, axis=0))
    seg_pose.append(np.full(n_tail, len(plan.poses) - 1))
    g = np.vstack(seg_g)
    n = len(g)
    psi = np.linalg.solve(M_TRUE, (g - B_TRUE).T).T + rng.normal(0, PSI_NOISE, (n, 3))
    ref = np.round(REF_COUNTS + rng.normal(0, 1.0, n))
    counts = np.round(psi * ref[:, None])
    temp = np.round((23.4 + rng.normal(0, 0.01, n)) * 100) / 100
    t_board = np.arange(n) / RATE_HZ
    seq = np.arange(n) % 65536
    pos = np.column_stack([ref, counts, temp, np.ones(n), np.full(n, 3.0), seq, t_board])
    return Stream(pos, t0_ns + np.round(t_board * 1e9).astype(np.int64), np.concatenate(seg_pose))


def psi_to_accel(ref: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    return (M_TRUE @ (xyz / ref[:, None]).T).T + B_TRUE


# ---------------------------------------------------------------------------- ROS side of the test
class RosHarness:
    """rclpy in the test process: a publisher of the synthetic stream and service clients."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.event_handler import PublisherEventCallbacks
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import JointState, Temperature
        from std_srvs.srv import Trigger

        self.rclpy = rclpy
        # every wait below is woken by what it waits for: a publisher matched, a response, a batch published,
        # a line of the node's output
        self.notifier = Notifier()
        self._matched = PublisherEventCallbacks(matched=self.notifier.notify)
        self.JointState, self.Temperature, self.Trigger = JointState, Temperature, Trigger
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("calibration_test_publisher", context=self.context)
        # the driver's QoS: sensor data (best effort)
        self._qos = qos_profile_sensor_data
        self._endpoints: dict[str, tuple] = {}
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._lock = threading.Lock()
        self._stream: Stream | None = None
        self._next = 0
        self._stop_at = 0
        self._drop: frozenset[int] = frozenset()
        self.published_temperature: list[tuple[int, float]] = []
        self.timer = self.node.create_timer(0.005, self._tick)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def use(self, ns: str) -> None:
        """Talk to the node in namespace ``/ns`` (each test has its own, so a SIGKILLed node's reader, which
        DDS keeps announcing until its lease expires, never shares a topic with a later test)."""
        if ns not in self._endpoints:
            self._endpoints[ns] = (
                self.node.create_publisher(self.JointState, f"/{ns}/imu/raw", self._qos, event_callbacks=self._matched),
                self.node.create_publisher(self.Temperature, f"/{ns}/imu/temperature", self._qos,
                                           event_callbacks=self._matched),
                self.node.create_client(self.Trigger, f"/{ns}/calibration/next_pose"),
                self.node.create_client(self.Trigger, f"/{ns}/calibration/abort"))
        with self._lock:
            self.pub_raw, self.pub_temp, self.next_client, self.abort_client = self._endpoints[ns]

    @property
    def published(self) -> int:
        with self._lock:
            return self._next

    def publish(self, stream: Stream, stop_at: int | None = None, drop: Iterable[int] = ()) -> None:
        """Start publishing ``stream`` from its beginning (up to sample ``stop_at``); the samples ``drop`` are left out
        (as a message lost on its way: the node sees a gap in ``seq``)."""
        with self._lock:
            self._stream, self._next = stream, 0
            self._stop_at = len(stream.stamps_ns) if stop_at is None else stop_at
            self._drop = frozenset(drop)
            self.published_temperature = []

    def resume(self) -> None:
        """Publish the rest of the stream."""
        with self._lock:
            assert self._stream is not None
            self._stop_at = len(self._stream.stamps_ns)

    def pause(self) -> None:
        with self._lock:
            self._stop_at = self._next

    def _tick(self) -> None:
        with self._lock:
            s = self._stream
            if s is None:
                return
            end = min(self._next + PUBLISH_BATCH, self._stop_at)
            for i in range(self._next, end):
                if i in self._drop:
                    continue
                m = self.JointState()
                ns = int(s.stamps_ns[i])
                m.header.stamp.sec, m.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
                m.header.frame_id = "fbg_accel_link"
                m.name = ["ref_counts", "x_counts", "y_counts", "z_counts", "temperature_c", "temperature_valid",
                          "status", "seq", "board_time_s"]
                m.position = [float(v) for v in s.positions[i]]
                self.pub_raw.publish(m)
                if i % 20 == 0:  # the driver publishes the temperature at a lower rate
                    t = self.Temperature()
                    t.header = m.header
                    t.temperature, t.variance = float(s.positions[i, 4]), 0.09
                    self.pub_temp.publish(t)
                    self.published_temperature.append((ns, t.temperature))
            self._next = max(self._next, end)
        self.notifier.notify()

    def wait_subscribed(self, node: NodeProcess, timeout: float = 30.0) -> None:
        self.use(node.ns)
        def matched() -> bool:
            if node.output_ended:
                raise AssertionError(f"node exited ({node.proc.wait(timeout=10)}):\n{node.output()}")
            return self.pub_raw.get_subscription_count() >= 1 and self.pub_temp.get_subscription_count() >= 1

        self.notifier.wait_until(matched, timeout, "the calibration node to subscribe to imu/raw and imu/temperature")
        # best effort: the node's reader must know our writer too, or the first messages are dropped
        node.wait_line(r"imu/raw: \d+ publisher\(s\) matched", timeout)
        node.wait_line(r"imu/temperature: \d+ publisher\(s\) matched", timeout)

    def call(self, client, node: NodeProcess, timeout: float = 10.0):
        assert client.wait_for_service(timeout_sec=timeout), f"service {client.srv_name} not available"
        fut = client.call_async(self.Trigger.Request())
        fut.add_done_callback(self.notifier.notify)

        def answered() -> bool:
            if node.output_ended:
                raise AssertionError(f"node exited during {client.srv_name}:\n{node.output()}")
            return fut.done()

        self.notifier.wait_until(answered, timeout, f"response of {client.srv_name}")
        return fut.result()

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)
        self.thread.join(timeout=5)


@pytest.fixture(scope="module")
def ros():
    if "ROS_DOMAIN_ID" not in os.environ:
        pytest.fail("ROS_DOMAIN_ID is not set: ROS tests must run in their own DDS domain (scripts/test.sh sets one)")
    h = RosHarness()
    yield h
    h.close()


class NodeProcess(ChildProcess):
    """The ``calibration`` executable with its stdout collected line by line."""

    def __init__(self, tmp: Path, *params: str, label: str = "run", notifier: Notifier | None = None) -> None:
        assert CALIBRATION_EXE.is_file(), f"{CALIBRATION_EXE} missing: run .venv/bin/pip install --no-deps -e ."
        self.ns = f"calib_test_{label}"
        args = [str(CALIBRATION_EXE), "--ros-args", "-r", f"__ns:=/{self.ns}", "-p", f"plan_file:={tmp / 'plan.yaml'}",
                "-p", f"output_dir:={tmp}", "-p", f"run_label:={label}", "-p", "sensor_id:=synthetic",
                "-p", "operator_notes:=process test",
                # 2 s of learning fits the short synthetic first pose; the learning statistics themselves are
                # tested in test_stillness_monitor.py
                "-p", "noise_learn_s:=2.0", *[a for p in params for a in ("-p", p)]]
        self.mcap = tmp / f"{label}.mcap"
        self.yaml = tmp / f"{label}_calibration.yaml"
        super().__init__("node", args, notifier)


@pytest.fixture()
def plan_dir(tmp_path: Path) -> Path:
    (tmp_path / "plan.yaml").write_text(yaml.safe_dump(PLAN, sort_keys=False))
    return tmp_path


@pytest.fixture()
def start_node(ros, plan_dir):
    """Starts a NodeProcess on ``plan_dir`` and waits until it subscribed to the test's publishers; kills it at the end."""
    started: list[NodeProcess] = []

    def start(*params: str, label: str = "run") -> NodeProcess:
        started.append(NodeProcess(plan_dir, *params, label=label, notifier=ros.notifier))
        ros.wait_subscribed(started[-1])
        return started[-1]

    yield start
    for p in started:
        p.kill()


# ---------------------------------------------------------------------------- checks
def raw_with_mcap_ros2(path: Path, ns: str, complete: bool = True) -> list:
    """(log time, message) of the node's ``/<ns>/imu/raw`` through the mcap library and the ROS 2 decoder."""
    raw = [(t, schema, m) for topic, t, schema, m in ros2_messages(path, complete) if topic == f"/{ns}/imu/raw"]
    assert {schema for _, schema, _ in raw} == {"sensor_msgs/msg/JointState"}
    return [(t, m) for t, _, m in raw]


def assert_raw_matches_published(decoded: list, stream: Stream) -> np.ndarray:
    """Message for message: each recorded message is the published one with its stamp (its log time too), in the
    order published, with its frame, names and every position value. Returns the published index of each (the
    stream's sample, in the recording's order). The topic is best effort (the driver's QoS, REP 2003): on a loaded
    machine a message may be dropped on its way (none on an idle one), which the node counts from the gaps in ``seq``
    (``lost_messages``, ``missing_between``); what it records must still be exactly what was published."""
    assert len(decoded) > 0
    published = {int(ns): i for i, ns in enumerate(stream.stamps_ns)}
    at = np.empty(len(decoded), np.int64)
    for k, (log_time, msg) in enumerate(decoded):
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert ns == log_time, f"message {k}: stamp {ns} != its log time {log_time}"
        i = published.get(ns)
        assert i is not None, f"message {k}: stamp {ns} was never published"
        assert k == 0 or i > at[k - 1], f"message {k}: sample {i} recorded after sample {at[k - 1]}"
        assert msg.header.frame_id == "fbg_accel_link"
        assert list(msg.name)[:4] == ["ref_counts", "x_counts", "y_counts", "z_counts"]
        np.testing.assert_array_equal(np.asarray(msg.position), stream.positions[i], err_msg=f"message {k}")
        at[k] = i
    return at


def missing_between(at: np.ndarray) -> int:
    """The published messages not recorded between the first and the last recorded (``at``: their published indices,
    ascending): what the node counts lost from the gaps in ``seq``."""
    return int(at[-1] - at[0] + 1 - len(at))


def refused_side_by_side(cases: dict[str, tuple[tuple[str, ...], tuple[str, ...]]],
                         timeout: float = 20) -> dict[str, subprocess.CompletedProcess]:
    """The node started once per case (its ``params`` (-p) and ``remaps`` (-r)), every case at once: each must refuse
    to start, exit 2, within ``timeout`` s per case (all of them together: the budget of the cases one after the
    other, within the module's pytest timeout, so that a case that never exits is named with what it printed). A
    refusal costs the start-up of rclpy (~1 s of CPU): side by side the cases take about the time of one per core,
    not of all of them one after the other."""
    procs = {}
    deadline = time.monotonic() + timeout * len(cases)
    try:
        for name, (params, remaps) in cases.items():
            args = [str(CALIBRATION_EXE), "--ros-args", *[a for r in remaps for a in ("-r", r)],
                    *[a for p in params for a in ("-p", p)]]
            procs[name] = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out = {}
        for name, proc in procs.items():
            try:
                stdout, stderr = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                stdout, stderr = proc.communicate(timeout=10)
                raise AssertionError(f"{name}: still running {timeout * len(cases):g} s after the start of "
                                     f"{len(cases)} refusals side by side; it printed:\n{stdout + stderr}") from None
            assert proc.returncode == 2, (name, stdout + stderr)
            out[name] = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
        return out
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)


def _stream_and_plan(plan_dir: Path, seed: int = 0) -> tuple[PosePlan, Stream]:
    plan = PosePlan.load(plan_dir / "plan.yaml")
    return plan, make_stream(plan, seed=seed)


# ---------------------------------------------------------------------------- tests
def test_mcap_round_trips_message_for_message_and_the_run_is_fitted(ros, plan_dir, start_node):
    plan, stream = _stream_and_plan(plan_dir)
    node = start_node("mode:=auto", "fit_degree:=0")
    dropped = range(len(stream.stamps_ns) // 3, len(stream.stamps_ns) // 3 + 3)  # three messages lost on the way
    ros.publish(stream, drop=dropped)
    rc = node.wait_exit(timeout=60)
    out = node.output()
    assert rc == 0, out
    assert "calibration written to" in out and "lost" in out

    # (1) the mcap reader + ROS 2 decoder give back exactly what was published, in order
    raw = raw_with_mcap_ros2(node.mcap, node.ns)
    temp = [(t, m) for topic, t, _, m in ros2_messages(node.mcap) if topic == f"/{node.ns}/imu/temperature"]
    n = len(raw)
    assert n <= ros.published and n > 0.8 * len(stream.stamps_ns)
    at = assert_raw_matches_published(raw, stream)
    assert not set(at) & set(dropped) and missing_between(at) >= len(dropped)
    # the temperatures recorded are published ones, in order, up to at least the last raw sample's stamp but for those
    # dropped on the way (best effort, as imu/raw; the last one may race the end of the run); the two topics are
    # delivered apart, so a few published after the last raw sample may have been taken before the run ended (4 in 1
    # run of 4 on an idle 2-core machine)
    recorded_temp = [(lt, m.temperature) for lt, m in temp]
    published_temp = iter(ros.published_temperature)
    assert all(any(t == p for p in published_temp) for t in recorded_temp), "temperatures not published, or reordered"
    expected_temp = sum(t[0] <= stream.stamps_ns[at[-1]] for t in ros.published_temperature)
    assert len(temp) >= 0.8 * expected_temp - 1, (len(temp), expected_temp)

    # (2) poses: exactly N samples each, taken only while the table stood at that pose, with its reference
    rec = read_recording(node.mcap)
    assert rec.metadata["read_report"]["complete"]
    assert rec.metadata["run"]["sensor_id"] == "synthetic" and rec.metadata["run"]["operator_notes"] == "process test"
    assert PosePlan.from_dict(yaml.safe_load(rec.metadata["run"]["plan"])).gref_mps2.shape == (5, 3)
    assert len(rec) == n  # the recording's samples are the raw messages above, in their order
    assert rec.metadata["run_end"]["lost_messages"] == str(missing_between(at))
    assert rec.metadata["run_end"]["result"] == "done"
    for k, pose in enumerate(plan.poses):
        idx = np.flatnonzero(rec.pose_id == k)
        assert len(idx) == pose.samples, f"pose {k}: {len(idx)} samples"
        assert np.all(stream.pose_of_sample[at[idx]] == k), f"pose {k} labelled samples outside the pose"
        np.testing.assert_allclose(rec.gref_mps2[idx], np.repeat(pose.gref_mps2[None], len(idx), 0))
    # (3) the fitted calibration is the driver's format and recovers the known sensor
    from fbg_accel_driver.thermal_model import ThermalCalibration

    cal = ThermalCalibration.load(node.yaml)
    assert cal.degree == 0 and cal.sensor_id == "synthetic"
    sel = rec.pose_id >= 0
    est = cal.apply_counts(rec.ref[sel], rec.xyz[sel], rec.temp_c[sel], rec.t_s[sel])
    truth = psi_to_accel(rec.ref[sel], rec.xyz[sel])
    assert np.sqrt(np.mean((est - truth) ** 2)) < 0.05  # m/s^2, against ~0.07 m/s^2 noise per sample


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_closes_the_file_cleanly_in_operator_mode(ros, plan_dir, start_node, sig):
    plan, stream = _stream_and_plan(plan_dir, seed=2)
    node = start_node("mode:=service", label=f"closed_{sig.name}")
    # publish pose 0 only (the table waits for the operator); the move to pose 1 is held back
    end_pose0 = int(np.flatnonzero(stream.pose_of_sample == 0)[-1]) + 1
    ros.publish(stream, stop_at=end_pose0)
    node.wait_line(r"pose 0 \(z_up\) recorded", timeout=60)
    resp = ros.call(ros.next_client, node)
    assert resp.success, resp.message
    assert "move the table" in resp.message  # plan expects motion: the node waits for it
    resp = ros.call(ros.next_client, node)
    assert not resp.success and "already waiting" in resp.message
    ros.resume()  # the table turns to pose 1 and stands
    node.wait_line(r"pose 1 \(z_down\) still, recording", timeout=60)
    ros.notifier.wait_until(lambda: ros.published >= len(stream.stamps_ns) or node.output_ended, 30, "the stream")
    node.proc.send_signal(sig)
    rc = node.wait_exit(timeout=20)
    assert rc == 3, node.output()

    raw = raw_with_mcap_ros2(node.mcap, node.ns)  # needs the summary: proves the clean close
    assert_raw_matches_published(raw, stream)
    rec, report = read_file(node.mcap)
    assert report.complete
    assert int(np.sum(rec.pose_id == 0)) == plan.poses[0].samples
    assert int(np.sum(rec.pose_id == 1)) == plan.poses[1].samples  # pose 1 completed before the signal
    assert rec.metadata["run_end"]["reason"] == sig.name
    assert not node.yaml.exists(), "an interrupted run must not write a calibration"


def test_abort_service_ends_the_run(ros, plan_dir, start_node):
    _, stream = _stream_and_plan(plan_dir, seed=3)
    node = start_node("mode:=service", label="aborted")
    ros.publish(stream, stop_at=int(3.0 * RATE_HZ))
    node.wait_line(r"static detector", timeout=60)
    resp = ros.call(ros.abort_client, node)
    assert resp.success, resp.message
    assert node.wait_exit(timeout=20) == 3
    rec, report = read_file(node.mcap)
    assert report.complete and rec.metadata["run_end"]["result"] == "aborted"


def test_a_stream_that_stops_is_reported_and_ends_the_run_after_stream_timeout_s(ros, plan_dir, start_node):
    """The stream stops 3 s into the run (the board or the driver stopped for good): with ``stream_timeout_s`` the node
    says so, closes the file as it is and exits 3, as an aborted run does. Before, it waited with the file open until
    it was killed, and said nothing."""
    _, stream = _stream_and_plan(plan_dir, seed=3)
    node = start_node("mode:=auto", "stream_timeout_s:=2.0", label="stalled")
    ros.publish(stream, stop_at=int(3.0 * RATE_HZ))
    node.wait_line(r"no imu/raw sample for .* \(stream_timeout_s 2\)", timeout=60)
    assert node.wait_exit(timeout=20) == 3
    rec, report = read_file(node.mcap)
    assert report.complete and rec.metadata["run_end"]["result"] == "aborted"
    assert "stream_timeout_s" in rec.metadata["run_end"]["reason"]
    assert not node.yaml.exists()


# runs after the other DDS tests of this module: a SIGKILLed participant stays announced until its lease expires
def test_sigkill_mid_recording_leaves_a_file_read_up_to_its_last_chunk_that_the_fit_uses(ros, plan_dir, start_node):
    plan, stream = _stream_and_plan(plan_dir, seed=1)
    node = start_node("mode:=auto", label="killed")
    ros.publish(stream)
    node.wait_line(r"pose 3 \(y_up\) recorded", timeout=60)  # 4 of 5 poses recorded: enough for M and b
    # stop the stream first: Fast DDS's shared-memory transport can stall a writer that keeps pushing into
    # the port of a SIGKILLed reader until its lease expires, which would starve the next test
    ros.pause()
    node.proc.send_signal(signal.SIGKILL)
    node.wait_exit(timeout=10)
    assert node.proc.returncode == -signal.SIGKILL

    rec, report = read_file(node.mcap)
    assert not report.complete, "a SIGKILLed writer cannot have written the footer"
    assert report.messages > 0
    # everything recovered is exactly what was published (a prefix but for what best effort dropped on the way), by the
    # mcap library's own stream reader too
    raw = raw_with_mcap_ros2(node.mcap, node.ns, complete=False)
    assert_raw_matches_published(raw, stream)
    assert len(raw) == len(rec)
    # each finished pose ended a chunk, so all four are on disk: every sample the node said it recorded (best effort may
    # have dropped some of a pose's on the way, as the stamps show above)
    said = {int(k): int(n) for k, n in re.findall(r"pose (\d+) \(\w+\) recorded: (\d+) samples", node.output())}
    for k in range(4):
        assert 0 < int(np.sum(rec.pose_id == k)) == said[k] <= plan.poses[k].samples, f"pose {k} lost"
    # `fbg-accel-calib fit` uses the partial file
    from fbg_accel_driver.thermal_model import ThermalCalibration

    fit = subprocess.run([str(CALIBRATION_EXE.parent / "fbg-accel-calib"), "fit", str(node.mcap), "-o",
                          str(plan_dir / "partial.yaml"), "--degree", "0"], capture_output=True, text=True, timeout=60)
    assert fit.returncode == 0, fit.stdout + fit.stderr
    cal = ThermalCalibration.load(plan_dir / "partial.yaml")
    assert cal.fit["poses"] == 4
    sel = rec.pose_id >= 0
    est = cal.apply_counts(rec.ref[sel], rec.xyz[sel], rec.temp_c[sel], rec.t_s[sel])
    assert np.sqrt(np.mean((est - psi_to_accel(rec.ref[sel], rec.xyz[sel])) ** 2)) < 0.05


# case: (-p parameters besides output_dir (and plan_file, unless given or the case has none), message). The process's
# side of a refusal (exit 2, the message on stderr, no recording) and a parameter read from its command line; the
# rules of the other refusals (a file that is no plan, a bad mode, still_window_s, run_to_run_from, a recording or a
# dangling link already at the recording's name, topic remaps the recording cannot name) are tested on the node class in
# process (test_node_classes.py), where a case costs no start-up of rclpy.
BAD_START_UP = {
    "no plan_file": ([], "parameter 'plan_file' is required"),
    "plan missing": (["plan_file:=/nonexistent/plan.yaml"], "pose plan file not found"),
    "no chamber": (["temperature_level:=4"], "no 'chamber' section"),
    "still_noise_std": (["still_noise_std:=[1.0, 2.0]"], "noise_std must be 3 positive numbers"),
}


def test_bad_start_up_input_gives_one_clear_error(tmp_path):
    """Each case of BAD_START_UP, a process of its own in a directory of its own (all started at once)."""
    dirs, cases = {}, {}
    for name, (params, _) in BAD_START_UP.items():
        dirs[name] = tmp_path / f"case{len(dirs)}"
        dirs[name].mkdir()
        (dirs[name] / "plan.yaml").write_text(yaml.safe_dump(PLAN, sort_keys=False))
        plan = [f"plan_file:={dirs[name] / 'plan.yaml'}"] if params and not any(p.startswith("plan_file:=")
                                                                               for p in params) else []
        cases[name] = ((f"output_dir:={dirs[name]}", *plan, *params), ())
    for name, res in refused_side_by_side(cases).items():
        assert BAD_START_UP[name][1] in res.stderr, (name, res.stderr)
        assert not list(dirs[name].glob("*.mcap")), f"{name}: no recording may be started on bad input"


def test_help_needs_no_ros():
    res = subprocess.run([str(CALIBRATION_EXE), "--help"], capture_output=True, text=True, timeout=30)
    assert res.returncode == 0 and "plan_file" in res.stdout and "calibration/next_pose" in res.stdout
