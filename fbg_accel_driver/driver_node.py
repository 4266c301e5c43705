"""ROS 2 node ``driver``: the thin rclpy shell around SerialLink + DriverCore + DriverDiagnostics.

``DriverNode`` (plain) and ``ManagedDriverNode`` (``--managed``, lifecycle); the entry point, parameter
table and usage are in ``driver_main`` (no ROS import, so ``--help`` needs none).

Topics (see docs/topics.md): ``imu/data_raw`` (sensor_msgs/Imu), ``imu/temperature``
(sensor_msgs/Temperature), ``imu/raw`` (sensor_msgs/JointState), ``/diagnostics``
(diagnostic_msgs/DiagnosticArray, 1 Hz). Data topics are published with the system-default
(reliable, volatile) QoS of REP 2003, keep-last 100, overridable per topic by the ``qos_overrides``
parameters (rclpy ``QoSOverridingOptions``); consumers subscribe with the sensor-data profile (or
any reliable profile: ``ros2 topic echo`` without flags works).

Shutdown: SIGINT/SIGTERM only set a flag (and wake the executor, ``node_support.signal_wakes_executor``); the main
loop then stops the serial reader and the publisher thread *before* the ROS context is shut down, so no publish races
a dead context. A link that ends at most ``LINK_CLOSE_AT_SHUTDOWN_S`` before a signal arrives (the simulator of a
launch file stopped by the same Ctrl-C) is logged as closed at shutdown (INFO), a link lost otherwise as an ERROR once
that time has passed (checked by the diagnostics timer; ``/diagnostics`` reports the link at once).

Threads: ``SerialLink``'s reader thread owns the port and queues byte chunks; a publisher thread
blocks on that queue, runs ``DriverCore`` and publishes (rclpy publishers may be used from any
thread); the executor only runs the 1 Hz diagnostics timer. Neither the executor nor the data path
ever blocks on the port, and a chunk costs one thread wake-up, not an executor cycle (an rclpy
guard-condition wake-up costs 180-280 us of CPU, a queue wake-up 10-30 us: bench/bench_driver_stages.py).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import Imu, JointState, Temperature

from .chain_compensation import MODES as CHAIN_MODES
from .command_line import StartupError, first_line, one_line
from .driver_core import COVARIANCE_SOURCES, CoreConfig, CoreOutput, DriverCore
from .driver_diagnostics import DiagnosticsSnapshot, DriverDiagnostics, calibration_uncertainty_values
from .driver_parameters import (
    CALIBRATION_NONE,
    CALIBRATION_SIM,
    DEFAULT_CALIBRATION,
    PARAMETERS,
    RUNTIME_PARAMETERS,
    default_calibration_path,
)
from .node_support import (
    c_stderr_held,
    declare_parameters,
    destroyed_if_refused,
    init_ros,
    refuse_unknown_parameters,
    signal_wakes_executor,
    signals_to,
)
from .ros_messages import DriverMessages
from .serial_link import LinkState, SerialLink
from .thermal_model import CalibrationFileError, ThermalCalibration

__all__ = ["DriverNode", "ManagedDriverNode", "run"]

NODE_NAME = "fbg_accel_driver"
# A link that ends at most this long before a SIGINT/SIGTERM arrives ended because of the shutdown (s)
LINK_CLOSE_AT_SHUTDOWN_S = 2.0
INTEGER_RANGES = {"baud": (1200, 4_000_000), "decimation": (1, 10000), "min_reference_counts": (0, 4095),
                  "reader_queue_max_bytes": (4096, 1 << 30)}
FLOAT_RANGES = {"temperature_hold_s": (0.0, 3600.0), "out_of_range_variance_factor": (1.0, 1e6),
                "temperature_range_margin_c": (0.0, 50.0), "reference_level_tolerance": (1e-6, 1.0),
                "reconnect_backoff_max_s": (0.1, 60.0), "accel_stddev_mps2": (0.0, 1000.0),
                "silence_timeout_s": (0.0, 3600.0), "equalise_bandwidth_hz": (0.01, 1e5),
                "gravity_mps2": (0.0, 9.9), "gravity_tolerance_mps2": (0.0, 10.0), "gravity_check_period_s": (1.0, 3600.0)}
CONSTRAINTS = {"covariance_source": "one of " + ", ".join(COVARIANCE_SOURCES),
               "chain_compensation": "one of auto, " + ", ".join(CHAIN_MODES)}


def data_qos() -> QoSProfile:
    """REP 2003: sensor drivers publish with the system-default QoS (reliable, volatile); keep-last 100 holds 0.1 s
    at 1 kHz for a reliable subscriber that is briefly slow. A new object per publisher: rclpy writes a topic's
    ``qos_overrides`` into the profile it is given, so a shared one would carry one topic's override to the others."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def _overridable() -> QoSOverridingOptions:
    """The data topics' QoS may be overridden per topic by the ``qos_overrides`` parameters."""
    return QoSOverridingOptions.with_default_policies()


def diagnostic_prefix(fully_qualified_name: str) -> str:
    """The node's status names' prefix on the shared ``/diagnostics``: its fully qualified name without the
    leading ``/`` (``fbg_accel_driver`` at the root, ``acc_a/fbg_accel_driver`` under ``/acc_a``, the remapped name
    after ``-r __node:=...``). Two drivers of one graph never share a status name: a diagnostic aggregator keys
    statuses by name, so a shared name let one sensor's OK overwrite the other's ERROR."""
    return fully_qualified_name.lstrip("/")


def run(argv: list[str], managed: bool = False) -> int:
    """Run the node until SIGINT/SIGTERM (``argv``: the ROS arguments); StartupError on a refused start-up."""
    init_ros("driver", argv)
    stop = threading.Event()
    node: DriverNode | None = None
    with signals_to(lambda _signum: stop.set()) as shutdown:
        try:
            node = (ManagedDriverNode if managed else DriverNode)()
            node.shutdown_signalled = shutdown.wait
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            with signal_wakes_executor(node, shutdown):
                try:
                    while not stop.is_set() and rclpy.ok():
                        executor.spin_once(timeout_sec=1.0)  # a signal wakes it at once
                except ExternalShutdownException:
                    pass
            return 0
        finally:
            if node is not None:
                node.close()  # reader and publisher threads end here, while the context is still valid
                node.destroy_node()
            rclpy.try_shutdown()


class DriverNode(Node):
    """The plain node: configured and active from construction (a StartupError if the parameters or the
    calibration are refused). ``node_options`` go to rclpy's Node (context, parameter_overrides, ...)."""

    managed = False
    # Whether SIGINT/SIGTERM arrives within the given seconds: run() hands in node_support.ShutdownSignal.wait; None
    # (a node built in-process, which handles no signal) reports a link that ends as lost at once
    shutdown_signalled: Callable[[float], bool] | None = None

    def __init__(self, **node_options: Any) -> None:
        super().__init__(NODE_NAME, **node_options)
        self.core: DriverCore | None = None
        self.link: SerialLink | None = None
        self.pub_imu: Publisher | None = None
        self.pub_temp: Publisher | None = None
        self.pub_raw: Publisher | None = None
        self.pub_diag: Publisher | None = None
        self.timer: Any = None
        self._publishing = False
        with destroyed_if_refused(self, self._cleanup):
            declare_parameters(self, PARAMETERS, writable=RUNTIME_PARAMETERS, integer_ranges=INTEGER_RANGES,
                               float_ranges=FLOAT_RANGES, constraints=CONSTRAINTS)
            self.add_on_set_parameters_callback(self._on_set_parameters)
            if not self.managed:
                self._configure()
                self._publishing = True

    def _data_publisher(self, msg_type: Any, topic: str) -> Publisher:
        return self.create_publisher(msg_type, topic, data_qos(), qos_overriding_options=_overridable())

    def _create_data_publisher(self, msg_type: Any, topic: str) -> Publisher:
        """A data topic's publisher; a ``qos_overrides`` value rclpy cannot apply (a policy name it does not know, a
        negative depth, a wrong type) is a StartupError naming the topic, not a traceback."""
        name = self.resolve_topic_name(topic)
        depth_key = f"qos_overrides.{name}.publisher.depth"
        depth = getattr(self, "_parameter_overrides", {}).get(depth_key)
        if depth is not None and isinstance(depth.value, int) and not 0 <= depth.value < 2**31:
            raise StartupError(f"invalid QoS override for {name}: parameter {depth_key} is {depth.value} "
                               f"(a queue depth, 0..{2**31 - 1})")
        try:
            with c_stderr_held():  # rcutils' 10-line error-state block of a refused QoS: one line instead
                return self._data_publisher(msg_type, topic)
        except Exception as exc:  # RuntimeError, RCLError (not exported), ParameterException: all a bad override
            raise StartupError(f"invalid QoS override for {name} (parameters qos_overrides.{name}.publisher.*): "
                               f"{first_line(exc)}") from None

    def _destroy_data_publisher(self, pub: Publisher) -> None:
        self.destroy_publisher(pub)

    # ------------------------------------------------------------ life cycle
    def _configure(self) -> None:
        refuse_unknown_parameters(self, "driver", before_publishers=True)  # a misspelt name first, not what it causes
        p = self._read_parameters()
        self.frame_id: str = p["frame_id"]
        choice = p["calibration_file"].strip()
        if not choice:
            raise StartupError(
                f"parameter 'calibration_file' is required: the sensor's calibration YAML, '{CALIBRATION_SIM}' "
                f"for the simulated sensor's (config/{DEFAULT_CALIBRATION}), or '{CALIBRATION_NONE}' to publish "
                "imu/raw and imu/temperature only")
        self.calibration: ThermalCalibration | None = None
        cal_path: Path | None = None
        if choice != CALIBRATION_NONE:
            cal_path = default_calibration_path() if choice == CALIBRATION_SIM else Path(choice)
            try:
                self.calibration = ThermalCalibration.load(cal_path)
            except CalibrationFileError as exc:
                raise StartupError(f"calibration file rejected: {exc}") from None
        core_cfg = CoreConfig(  # the parameters of these names set the CoreConfig fields of the same names
            chain_compensation=self._chain_mode(p["chain_compensation"]),
            **{name: p[name] for name in ("decimation", "min_reference_counts", "temperature_hold_s", "covariance_source",
                                          "accel_stddev_mps2", "out_of_range_variance_factor", "temperature_range_margin_c",
                                          "reference_level_tolerance", "equalise_bandwidth_hz",
                                          "covariance_includes_calibration", "gravity_mps2", "gravity_tolerance_mps2",
                                          "gravity_check_period_s")})
        try:
            core = DriverCore(self.calibration, core_cfg)
        except ValueError as exc:
            raise StartupError(f"invalid parameter: {exc}") from None
        cal = self.calibration
        self.cal_info = {"calibration_file": str(cal_path) if cal_path else "none (raw only)",
                         "sensor_id": cal.sensor_id if cal else "uncalibrated",
                         "degree": cal.degree if cal else "none"}
        self.temperature_range_c = cal.temperature_range_c if cal else (-math.inf, math.inf)
        self.diag = DriverDiagnostics(prefix=diagnostic_prefix(self.get_fully_qualified_name()))
        self.msgs = DriverMessages(self.frame_id)  # used by the publisher thread only
        self.pub_imu = self._create_data_publisher(Imu, "imu/data_raw") if cal is not None else None
        self.pub_temp = self._create_data_publisher(Temperature, "imu/temperature")
        self.pub_raw = self._create_data_publisher(JointState, "imu/raw")
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)  # also while inactive
        refuse_unknown_parameters(self, "driver")  # after the publishers: they declare the qos_overrides parameters
        clock = self.get_clock()
        self.link = SerialLink(
            p["port"], p["baud"], notify=self._wake_publisher,
            clock_ns=lambda: clock.now().nanoseconds,
            backoff_max_s=p["reconnect_backoff_max_s"], silence_timeout_s=p["silence_timeout_s"],
            max_queued_bytes=p["reader_queue_max_bytes"],
        )
        self.core = core
        self._link_state = LinkState.CONNECTING
        self._link_changes = 0
        self._link_down: tuple[str, float] | None = None  # a lost link not yet logged: (message, log-by time)
        self._link_down_lock = threading.Lock()
        self._stopping = threading.Event()
        self._publisher_thread = threading.Thread(target=self._publisher_loop, name="fbg-accel publisher",
                                                  daemon=True)
        self.timer = self.create_timer(1.0, self._publish_diagnostics)
        self._publisher_thread.start()
        self.link.start()
        if cal is None:
            what = "no calibration: publishing imu/raw and imu/temperature only"
        else:
            what = (f"calibration {cal_path} (sensor {cal.sensor_id}, degree {cal.degree}, "
                    f"{cal.temperature_range_c[0]:g}..{cal.temperature_range_c[1]:g} degC)")
        self.get_logger().info(f"reading {p['port']} at {p['baud']} baud, {what}, decimation {p['decimation']}")

    def _cleanup(self) -> None:
        """Stop the reader (the port is closed) and the publisher thread; drop publishers and timer. Also after a
        configure that failed half-way (a parameter refused after the first publishers were created): whatever it
        created goes, so the node is as unconfigured as before."""
        self._publishing = False
        if self.link is not None:
            self.close()
            self.link = None
        if self.timer is not None:
            self.destroy_timer(self.timer)
            self.timer = None
        for pub in (self.pub_imu, self.pub_temp, self.pub_raw):
            if pub is not None:
                self._destroy_data_publisher(pub)
        if self.pub_diag is not None:
            self.destroy_publisher(self.pub_diag)
        self.pub_imu = self.pub_temp = self.pub_raw = self.pub_diag = None
        self.core = None

    # ------------------------------------------------------------ parameters
    def _read_parameters(self) -> dict[str, Any]:
        """The declared values (as set now: a managed node may have been given new ones before configure),
        with the checks a range descriptor cannot express."""
        values = {name: self.get_parameter(name).value for name in PARAMETERS}
        if not values["port"]:
            raise StartupError("invalid parameter 'port': empty (give the serial device, e.g. -p port:=/dev/ttyUSB0)")
        fid = values["frame_id"]
        if not fid or fid.startswith("/") or any(c.isspace() for c in fid):
            raise StartupError(f"invalid parameter 'frame_id': {fid!r} (non-empty, no leading '/', no spaces)")
        for name in ("temperature_hold_s", "out_of_range_variance_factor", "temperature_range_margin_c",
                     "reference_level_tolerance", "accel_stddev_mps2", "gravity_mps2", "gravity_tolerance_mps2",
                     "gravity_check_period_s"):
            if not math.isfinite(values[name]):
                raise StartupError(f"invalid parameter '{name}': {values[name]} is not finite")
        return values

    def _chain_mode(self, value: str) -> str:
        if value == "auto":
            cal = self.calibration
            return "delay" if cal is not None and cal.dynamic is not None else "none"
        if value not in CHAIN_MODES:
            raise StartupError(f"invalid parameter 'chain_compensation': {value!r} (one of auto, {', '.join(CHAIN_MODES)})")
        return value

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """``ros2 param set``: RUNTIME_PARAMETERS go to DriverCore.reconfigure (validated as a whole);
        read-only ones are already refused by rclpy through their descriptor."""
        changes = {q.name: q.value for q in params if q.name in RUNTIME_PARAMETERS}
        if not changes or self.core is None:  # not configured: read at configure
            return SetParametersResult(successful=True)
        try:
            self.core.reconfigure(**changes)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.get_logger().info("set " + ", ".join(f"{k}={v}" for k, v in changes.items()))
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------ data path
    def _wake_publisher(self) -> None:
        """SerialLink's notify: only a state change needs it (data chunks wake the queue's reader)."""
        if self.link.state_changes != self._link_changes:
            self.link.queue.wake()

    def _publisher_loop(self) -> None:
        """Publisher thread: block on the link's queue, decode, calibrate, publish; until close()."""
        q = self.link.queue
        log = self.get_logger()
        while not self._stopping.is_set():
            item = q.get()
            if self._stopping.is_set():
                break
            if item is not None:  # None: a wake-up (link state change or close)
                host_ns, chunk, steady_ns = item
                try:
                    self._publish(self.core.feed(chunk, host_ns, steady_ns))
                except Exception as exc:  # a shut-down context while exiting, or a bug: never kill the data path
                    if self._stopping.is_set():
                        break
                    log.error(f"publishing failed: {exc!r}", throttle_duration_sec=5.0)
            if self.link.state_changes != self._link_changes:
                self._log_link_change()

    def _log_link_change(self) -> None:
        status = self.link.status()
        if status.state is LinkState.CONNECTED:
            self._report_link_down(now=True)  # a loss that came before this reconnection
            self.get_logger().info(f"serial link up: {status.port}")
        elif status.state is LinkState.DISCONNECTED and self._link_state is not LinkState.DISCONNECTED:
            if self.shutdown_signalled is None:
                self.get_logger().error(f"serial link down: {status.message}; retrying with back-off")
            else:
                with self._link_down_lock:
                    self._link_down = (status.message, time.monotonic() + LINK_CLOSE_AT_SHUTDOWN_S)
        self._link_state = status.state
        self._link_changes = self.link.state_changes

    def _report_link_down(self, now: bool) -> None:
        """Log the link loss not yet logged: closed at shutdown (INFO) once a signal has arrived; lost (ERROR) once
        LINK_CLOSE_AT_SHUTDOWN_S has passed without one, or at once with ``now``. Publisher thread, diagnostics timer
        and close() call it."""
        with self._link_down_lock:
            if self._link_down is None or self.shutdown_signalled is None:
                return
            message, log_by = self._link_down
            if self.shutdown_signalled(0.0):
                self.get_logger().info(f"serial link closed at shutdown: {message}")
            elif now or time.monotonic() >= log_by:
                self.get_logger().error(f"serial link down: {message}; retrying with back-off")
            else:
                return
            self._link_down = None

    def _publish(self, out: CoreOutput) -> None:
        if not self._publishing:  # managed and inactive: frames are decoded and diagnosed, not published
            return
        msgs = self.msgs
        for r in out.raw:
            self.pub_raw.publish(msgs.raw_msg(r))
        for t in out.temperature:
            self.pub_temp.publish(msgs.temperature_msg(t))
        if self.pub_imu is not None:
            for s in out.imu:
                self.pub_imu.publish(msgs.imu_msg(s))

    # ------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self) -> None:
        self._report_link_down(now=False)
        st = self.link.status()
        core = self.core
        snap = DiagnosticsSnapshot(
            now_s=time.monotonic(),
            link_connected=st.state is LinkState.CONNECTED,
            link_message=st.message,
            link_values={"port": st.port, "baud": st.baud, "connects": st.connects, "disconnects": st.disconnects,
                         "failed_attempts": st.failed_attempts, "next_retry_s": st.next_retry_s,
                         "bytes_read": st.bytes_read, "reader_thread_alive": st.thread_alive,
                         "python_threads": threading.active_count(), "queued_bytes": st.queued_bytes,
                         "queue_max_bytes": self.link.queue.max_bytes, "queue_dropped_chunks": st.queue_dropped_chunks,
                         "queue_dropped_bytes": st.queue_dropped_bytes},
            decoder=core.decoder.stats.as_dict(), core=core.counters.as_dict(),
            temperature_valid=core.last_temperature_valid, temperature_age_s=core.temperature_age_s,
            last_temperature_c=core.last_good_temperature_c, temperature_hold_s=core.config.temperature_hold_s,
            temperature_range_c=self.temperature_range_c, temperature_range_margin_c=core.config.temperature_range_margin_c,
            reference_level_tolerance=core.config.reference_level_tolerance, calibration=self.cal_info,
            chain=core.chain_status(), clock=core.clock_status(),
            calibration_uncertainty={} if self.calibration is None else calibration_uncertainty_values(
                core.calibration_uncertainty(), self.calibration.coefficient_covariance is not None,
                core.config.covariance_includes_calibration,
                None if self.calibration.slow_error is None else self.calibration.slow_error.sigma_mps2,
                0.0 if self.calibration.slow_error is None else self.calibration.slow_error.unstated_run_to_run_sigma_mps2),
            gravity=core.gravity_status())
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        for e in self.diag.report(snap):
            arr.status.append(DiagnosticStatus(
                level=bytes([e.level]), name=e.name, message=e.message, hardware_id=self.cal_info["sensor_id"],
                values=[KeyValue(key=k, value=v) for k, v in e.values],
            ))
        self.pub_diag.publish(arr)

    def close(self) -> None:
        """Stop the reader thread (closing the port) and the publisher thread; idempotent."""
        if self.link is None:
            return
        self.link.stop()
        self._stopping.set()
        self.link.queue.wake()
        self._publisher_thread.join(2.0)
        self._report_link_down(now=True)


class ManagedDriverNode(DriverNode, LifecycleNode):
    """``driver --managed``: configure loads the calibration, creates the publishers and opens the port (the
    reader runs, frames are decoded and diagnosed); activate publishes; deactivate stops publishing (the port
    stays open); cleanup closes the port and drops the publishers."""

    managed = True

    def _data_publisher(self, msg_type: Any, topic: str) -> Publisher:
        return self.create_lifecycle_publisher(msg_type, topic, data_qos(), qos_overriding_options=_overridable())

    def _destroy_data_publisher(self, pub: Publisher) -> None:
        self.destroy_lifecycle_publisher(pub)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._configure()
        except StartupError as exc:
            self.get_logger().error(f"configure failed: {one_line(str(exc))}")
            self._cleanup()
            return TransitionCallbackReturn.FAILURE
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._publishing = True
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._publishing = False
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._cleanup()
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._cleanup()
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """A transition raised something unexpected: leave nothing running before rclpy returns to unconfigured."""
        self._cleanup()
        return super().on_error(state)

    def destroy_node(self) -> None:
        """Destroy the node now, as a plain node's ``destroy_node`` does: rclpy's LifecycleNode leaves its state
        machine, which holds the rcl node, to the garbage collector, so a managed driver built in a process that goes
        on (composition, tests) stayed in the ROS graph, its lifecycle services answering, after it was destroyed."""
        super().destroy_node()
        self._state_machine.destroy_when_not_in_use()
