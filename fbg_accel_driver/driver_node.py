"""ROS 2 node ``driver``: the thin rclpy shell around SerialLink + DriverCore + DriverDiagnostics.

Topics (see docs/topics.md): ``imu/data_raw`` (sensor_msgs/Imu), ``imu/temperature``
(sensor_msgs/Temperature), ``imu/raw`` (sensor_msgs/JointState), ``/diagnostics``
(diagnostic_msgs/DiagnosticArray, 1 Hz). Data topics are published with the system-default
(reliable, volatile) QoS of REP 2003, keep-last 100, overridable per topic by the ``qos_overrides``
parameters (rclpy ``QoSOverridingOptions``); consumers subscribe with the sensor-data profile (or
any reliable profile: ``ros2 topic echo`` without flags works).

Shutdown: SIGINT/SIGTERM only set a flag; the main loop then stops the serial reader and the
publisher thread *before* the ROS context is shut down, so no publish races a dead context.

Threads: ``SerialLink``'s reader thread owns the port and queues byte chunks; a publisher thread
blocks on that queue, runs ``DriverCore`` and publishes (rclpy publishers may be used from any
thread); the executor only runs the 1 Hz diagnostics timer. Neither the executor nor the data path
ever blocks on the port, and a chunk costs one thread wake-up, not an executor cycle (an rclpy
guard-condition wake-up costs 180-280 us of CPU, a queue wake-up 10-30 us: bench/bench_driver_stages.py).
"""

from __future__ import annotations

import math
import sys
import threading
import time
from pathlib import Path
from typing import Any

from .command_line import (
    StartupError,
    first_line,
    one_line,
    unknown_parameters,
    version_line,
    wants_help,
    wants_version,
)

PACKAGE = "fbg_accel_driver"
DEFAULT_CALIBRATION = "calibration_sim.yaml"
CALIBRATION_SIM = "sim"  # calibration_file value: the simulated sensor's calibration shipped in config/
CALIBRATION_NONE = "none"  # calibration_file value: raw counts and temperature only
# parameters ``ros2 param set`` may change while streaming (DriverCore.reconfigure); the rest are read-only
RUNTIME_PARAMETERS = ("decimation", "min_reference_counts", "temperature_hold_s", "out_of_range_variance_factor")

# name: (type, default, description); the ROS types are resolved lazily so --help needs no ROS.
PARAMETERS: dict[str, tuple[str, Any, str]] = {
    "port": ("string", "/dev/ttyUSB0", "serial device of the board (a pty path for the simulator)"),
    "baud": ("integer", 921600, "UART baud rate, 1200..4000000"),
    "frame_id": ("string", "fbg_accel_link", "frame_id of the published messages (sensor frame)"),
    "calibration_file": (
        "string",
        "",
        f"REQUIRED: the sensor's calibration YAML; '{CALIBRATION_SIM}' = the package's config/{DEFAULT_CALIBRATION} "
        f"(the simulated sensor); '{CALIBRATION_NONE}' = no imu/data_raw, imu/raw and imu/temperature only",
    ),
    "decimation": ("integer", 1, "average this many board samples per imu/data_raw message, 1..10000 (settable)"),
    "covariance_source": (
        "string",
        "calibration",
        "linear_acceleration_covariance from: calibration (noise_sigma_mps2), parameter (accel_stddev_mps2), unknown "
        "(zeros); decimated variance uses the calibration's noise_correlation",
    ),
    "accel_stddev_mps2": ("double", 0.0, "per-axis sigma in m/s^2 when covariance_source is 'parameter'"),
    "chain_compensation": (
        "string",
        "auto",
        "measuring-chain dynamics from the calibration's 'dynamic' section: none, delay (stamps moved back by the "
        "group delay at DC), equalise (each channel's TIA low-pass inverted before eq. 24), auto (= delay when the "
        "calibration has a dynamic section, else none); docs/dynamic_calibration.md",
    ),
    "equalise_bandwidth_hz": ("double", 10.0,
                              "common low-pass (Hz) left in place of the TIA stages by chain_compensation 'equalise'"),
    "min_reference_counts": ("integer", 50,
                             "reference counts below this: reference power too low, sample not published (settable)"),
    "temperature_hold_s": ("double", 5.0,
                           "seconds the last good temperature may be used while the sensor is invalid (settable)"),
    "out_of_range_variance_factor": ("double", 10.0,
                                     "variance factor outside the calibrated temperature range (>= 1) (settable)"),
    "reconnect_backoff_max_s": ("double", 2.0, "longest wait between reconnection attempts (back-off doubles from 0.1 s)"),
    "silence_timeout_s": ("double", 2.0, "reopen the port after this many seconds without any byte (0 = never)"),
    "reader_queue_max_bytes": (
        "integer",
        262144,
        "bytes the serial reader may queue ahead of the decoder; beyond it the oldest are dropped and counted",
    ),
}

USAGE = f"""usage: driver [-h] [--version] [--managed] [--ros-args -p NAME:=VALUE ... | --params-file FILE]

  --managed   run as a managed (lifecycle) node: configure loads the calibration and opens the port,
              activate publishes, deactivate stops publishing, cleanup closes the port

ROS 2 driver for the FBG triaxial accelerometer acquisition board (package {PACKAGE}).
Reads binary frames from a serial port (pyserial), stamps them with the board clock mapped to ROS
time, applies the thermal calibration (paper eq. 24 and 28) and publishes:
  imu/data_raw     sensor_msgs/Imu          specific force in m/s^2 (REP 145)
  imu/temperature  sensor_msgs/Temperature  AHT10 temperature in degC
  imu/raw          sensor_msgs/JointState   raw counts, temperature, status, seq, board time
  /diagnostics     diagnostic_msgs/DiagnosticArray, 1 Hz

parameters:
""" + "".join(f"  {n:<30} {t:<8} default {d!r}\n      {desc}\n" for n, (t, d, desc) in PARAMETERS.items()) + """
example:
  ros2 run fbg_accel_driver driver --ros-args -p port:=/dev/ttyUSB0 -p decimation:=10
exit status: 0 on clean shutdown, 2 on invalid parameters or calibration file.
"""


def default_calibration_path() -> Path:
    """The shipped calibration: the installed share directory, else the source tree's config/."""
    candidates: list[Path] = []
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

        try:
            candidates.append(Path(get_package_share_directory(PACKAGE)) / "config" / DEFAULT_CALIBRATION)
        except (PackageNotFoundError, ValueError, LookupError, OSError):
            pass
    except ImportError:
        pass
    here = Path(__file__).resolve()
    # colcon install layout: <prefix>/lib/pythonX.Y/site-packages/fbg_accel_driver/driver_node.py
    for parent in here.parents:
        candidates.append(parent / "share" / PACKAGE / "config" / DEFAULT_CALIBRATION)
        if parent.name == "lib":
            break
    candidates.append(here.parents[1] / "config" / DEFAULT_CALIBRATION)  # source tree / editable install
    for c in candidates:
        if c.is_file():
            return c
    return candidates[-1]


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if wants_version(argv):
        print(version_line("driver"))
        return 0
    if wants_help(argv):
        print(USAGE, end="")
        print(f"calibration_file '{CALIBRATION_SIM}': {default_calibration_path()}")
        return 0
    try:
        user = argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv
        managed = "--managed" in user
        user = [a for a in user if a != "--managed"]
        if user:
            raise StartupError(f"unknown argument(s) {user}; parameters go after --ros-args (see driver --help)")
        return _run([a for a in argv if a != "--managed"], managed)
    except StartupError as exc:
        print(f"driver: error: {one_line(str(exc))}", file=sys.stderr, flush=True)
        return 2
    except KeyboardInterrupt:
        return 0


def _run(argv: list[str], managed: bool = False) -> int:
    import signal

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    try:
        # rclpy's own handler would shut the context down at once, under the publisher thread's feet
        rclpy.init(args=["driver", *argv], signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # RCLError: unparsable --ros-args; its text is the only useful part
        raise StartupError(f"invalid ROS arguments {argv}: {first_line(exc)}") from None
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    node = None
    try:
        node = _make_node(managed)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        try:
            while not stop.is_set() and rclpy.ok():
                executor.spin_once(timeout_sec=0.1)  # a signal is seen within 0.1 s
        except ExternalShutdownException:
            pass
        return 0
    finally:
        if node is not None:
            node.close()  # reader and publisher threads end here, while the context is still valid
            node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _make_node(managed: bool = False) -> Any:
    """Build the node class lazily (keeps rclpy out of --help and of the pure modules)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType, SetParametersResult
    from rclpy.exceptions import ParameterException
    from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.qos_overriding_options import QoSOverridingOptions
    from sensor_msgs.msg import Imu, JointState, Temperature

    from .chain_compensation import MODES as CHAIN_MODES
    from .driver_core import COVARIANCE_SOURCES, CoreConfig, DriverCore
    from .driver_diagnostics import DiagnosticsSnapshot, DriverDiagnostics
    from .ros_messages import DriverMessages
    from .serial_link import LinkState, SerialLink
    from .thermal_model import CalibrationFileError, ThermalCalibration

    ptypes = {"string": ParameterType.PARAMETER_STRING, "integer": ParameterType.PARAMETER_INTEGER,
              "double": ParameterType.PARAMETER_DOUBLE}
    int_ranges = {"baud": (1200, 4_000_000), "decimation": (1, 10000), "min_reference_counts": (0, 4095),
                  "reader_queue_max_bytes": (4096, 1 << 30)}
    float_ranges = {"temperature_hold_s": (0.0, 3600.0), "out_of_range_variance_factor": (1.0, 1e6),
                    "reconnect_backoff_max_s": (0.1, 60.0), "accel_stddev_mps2": (0.0, 1000.0),
                    "silence_timeout_s": (0.0, 3600.0), "equalise_bandwidth_hz": (0.01, 1e5)}

    # REP 2003: sensor drivers publish with the system-default QoS (reliable, volatile); keep-last 100
    # holds 0.1 s at 1 kHz for a reliable subscriber that is briefly slow
    data_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)

    base = LifecycleNode if managed else Node

    class DriverNode(base):  # type: ignore[valid-type, misc]
        """Plain node: configured and active from construction. Managed (``--managed``): configure loads the
        calibration, creates the publishers and opens the port (the reader runs, frames are decoded and
        diagnosed); activate publishes; deactivate stops publishing (the port stays open); cleanup
        closes the port and drops the publishers."""

        def __init__(self) -> None:
            super().__init__("fbg_accel_driver")
            self._declare_all()
            self.core: DriverCore | None = None
            self.link: SerialLink | None = None
            self._publishing = False
            self.add_on_set_parameters_callback(self._on_set_parameters)
            if not managed:
                self._configure()
                self._activate()

        # ------------------------------------------------------------ life cycle
        def _configure(self) -> None:
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
            core_cfg = CoreConfig(
                decimation=p["decimation"],
                min_reference_counts=p["min_reference_counts"],
                temperature_hold_s=p["temperature_hold_s"],
                covariance_source=p["covariance_source"],
                accel_stddev_mps2=p["accel_stddev_mps2"],
                out_of_range_variance_factor=p["out_of_range_variance_factor"],
                chain_compensation=self._chain_mode(p["chain_compensation"]),
                equalise_bandwidth_hz=p["equalise_bandwidth_hz"],
            )
            try:
                core = DriverCore(self.calibration, core_cfg)
            except ValueError as exc:
                raise StartupError(f"invalid parameter: {exc}") from None
            cal = self.calibration
            self.cal_info = {"calibration_file": str(cal_path) if cal_path else "none (raw only)",
                             "sensor_id": cal.sensor_id if cal else "uncalibrated",
                             "degree": cal.degree if cal else "none"}
            self.temperature_range_c = cal.temperature_range_c if cal else (-math.inf, math.inf)
            self.diag = DriverDiagnostics(prefix="fbg_accel_driver")
            self.msgs = DriverMessages(self.frame_id)  # used by the publisher thread only
            overridable = QoSOverridingOptions.with_default_policies()
            create = self.create_lifecycle_publisher if managed else self.create_publisher
            self.pub_imu = create(Imu, "imu/data_raw", data_qos, qos_overriding_options=overridable) \
                if cal is not None else None
            self.pub_temp = create(Temperature, "imu/temperature", data_qos, qos_overriding_options=overridable)
            self.pub_raw = create(JointState, "imu/raw", data_qos, qos_overriding_options=overridable)
            self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)  # also while inactive
            self._refuse_unknown_parameters()  # after the publishers: they declare the qos_overrides parameters
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

        def _activate(self) -> None:
            self._publishing = True

        def _deactivate(self) -> None:
            self._publishing = False

        def _cleanup(self) -> None:
            """Stop the reader (the port is closed) and the publisher thread; drop publishers and timer."""
            self._publishing = False
            if self.link is None:
                return
            self.close()
            self.destroy_timer(self.timer)
            for pub in (self.pub_imu, self.pub_temp, self.pub_raw):
                if pub is not None:
                    (self.destroy_lifecycle_publisher if managed else self.destroy_publisher)(pub)
            self.destroy_publisher(self.pub_diag)
            self.link = None
            self.core = None

        def on_configure(self, state: Any) -> Any:
            try:
                self._configure()
            except StartupError as exc:
                self.get_logger().error(f"configure failed: {one_line(str(exc))}")
                self._cleanup()
                return TransitionCallbackReturn.FAILURE
            return super().on_configure(state)

        def on_activate(self, state: Any) -> Any:
            self._activate()
            return super().on_activate(state)

        def on_deactivate(self, state: Any) -> Any:
            self._deactivate()
            return super().on_deactivate(state)

        def on_cleanup(self, state: Any) -> Any:
            self._cleanup()
            return super().on_cleanup(state)

        def on_shutdown(self, state: Any) -> Any:
            self._cleanup()
            return super().on_shutdown(state)

        # ------------------------------------------------------------ parameters
        def _declare_all(self) -> None:
            for name, (typ, default, desc) in PARAMETERS.items():
                d = ParameterDescriptor(name=name, type=ptypes[typ], description=desc,
                                        read_only=name not in RUNTIME_PARAMETERS)
                if name in int_ranges:
                    lo, hi = int_ranges[name]
                    d.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=1)]
                    d.additional_constraints = f"{lo}..{hi}"
                if name in float_ranges:
                    lo, hi = float_ranges[name]
                    d.floating_point_range = [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]
                    d.additional_constraints = f"{lo}..{hi}"
                if name == "covariance_source":
                    d.additional_constraints = "one of " + ", ".join(COVARIANCE_SOURCES)
                if name == "chain_compensation":
                    d.additional_constraints = "one of auto, " + ", ".join(CHAIN_MODES)
                try:
                    self.declare_parameter(name, default, d)
                except ParameterException as exc:
                    raise StartupError(f"invalid parameter '{name}': {first_line(exc)} ({desc})") from None

        def _read_parameters(self) -> dict[str, Any]:
            """The declared values (as set now: a managed node may have been given new ones before configure),
            with the checks a range descriptor cannot express."""
            values = {name: self.get_parameter(name).value for name in PARAMETERS}
            if not values["port"]:
                raise StartupError("invalid parameter 'port': empty (give the serial device, e.g. -p port:=/dev/ttyUSB0)")
            fid = values["frame_id"]
            if not fid or fid.startswith("/") or any(c.isspace() for c in fid):
                raise StartupError(f"invalid parameter 'frame_id': {fid!r} (non-empty, no leading '/', no spaces)")
            for name in ("temperature_hold_s", "out_of_range_variance_factor", "accel_stddev_mps2"):
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

        def _refuse_unknown_parameters(self) -> None:
            """A misspelt ``-p``/params-file name would be ignored by rclpy: refuse it, naming the nearest."""
            given = getattr(self, "_parameter_overrides", {})  # what --ros-args and params files set
            unknown = unknown_parameters(given, self._parameters)
            if unknown:
                raise StartupError("; ".join(unknown) + " (driver --help lists the parameters)")

        def _on_set_parameters(self, params: list[Any]) -> Any:
            """``ros2 param set``: RUNTIME_PARAMETERS go to DriverCore.reconfigure (validated as a whole);
            read-only ones are already refused by rclpy through their descriptor."""
            changes = {q.name: q.value for q in params if q.name in RUNTIME_PARAMETERS}
            if not changes or getattr(self, "core", None) is None:  # not configured: read at configure
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
                    host_ns, chunk = item
                    try:
                        self._publish(self.core.feed(chunk, host_ns))
                    except Exception as exc:  # a shut-down context while exiting, or a bug: never kill the data path
                        if self._stopping.is_set():
                            break
                        log.error(f"publishing failed: {exc!r}", throttle_duration_sec=5.0)
                if self.link.state_changes != self._link_changes:
                    self._log_link_change()

        def _log_link_change(self) -> None:
            status = self.link.status()
            if status.state is LinkState.CONNECTED:
                self.get_logger().info(f"serial link up: {status.port}")
            elif status.state is LinkState.DISCONNECTED and self._link_state is not LinkState.DISCONNECTED:
                self.get_logger().error(f"serial link down: {status.message}; retrying with back-off")
            self._link_state = status.state
            self._link_changes = self.link.state_changes

        def _publish(self, out: Any) -> None:
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
                decoder=core.decoder.stats.as_dict(),
                core=core.counters.as_dict(),
                temperature_valid=core.last_temperature_valid,
                temperature_age_s=core.temperature_age_s,
                last_temperature_c=core.last_good_temperature_c,
                temperature_hold_s=core.config.temperature_hold_s,
                temperature_range_c=self.temperature_range_c,
                calibration=self.cal_info,
                chain=core.chain_status(),
            )
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

    return DriverNode()


if __name__ == "__main__":
    sys.exit(main())
