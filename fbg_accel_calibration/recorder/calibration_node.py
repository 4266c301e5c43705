"""ROS 2 node ``calibration``: record the poses of a pose plan to MCAP, then refit the thermal model.

``CalibrationNode``; the entry point, parameter table and usage are in ``calibration_main`` (no ROS
import, so ``--help`` needs none). The thin rclpy shell around
:class:`~fbg_accel_calibration.recorder.pose_recorder.RunRecorder` (stillness, pose sequence, MCAP writing) and
:func:`~fbg_accel_calibration.recorder.run_refit.refit` (the fit). See docs/calibration_node.md.

Subscribes (best effort, keep last 2000: compatible with the driver's reliable REP 2003 publishers):
  ``imu/raw`` sensor_msgs/JointState (raw counts, see docs/topics.md), ``imu/temperature`` sensor_msgs/Temperature.
Services (std_srvs/Trigger): ``calibration/next_pose`` (operator: advance after a pose is recorded;
auto mode: skip the current pose), ``calibration/abort`` (end the run now, file closed, no fit).

SIGINT/SIGTERM end the run: the MCAP gets its summary and footer and the node exits with status 3. A failed
write of the recording (disk full, the file or output_dir removed) aborts the run: status 4.
"""

from __future__ import annotations

import datetime as _dt
import math
import re
import signal
import sys
import time
from pathlib import Path
from typing import Any

import rclpy
from rclpy.event_handler import QoSSubscriptionMatchedInfo, SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState, Temperature
from std_srvs.srv import Trigger

from fbg_accel_driver.command_line import StartupError, check_name_text
from fbg_accel_driver.driver_core import RAW_AUX_NAME, RAW_NAMES
from fbg_accel_driver.node_support import (
    declare_parameters,
    destroyed_if_refused,
    init_ros,
    refuse_unknown_parameters,
    signal_wakes_executor,
    signals_to,
)
from fbg_accel_driver.yaml_input import YamlFileError, read_yaml_file

from ..dynamic.excitation_plan import FORMAT_NAME as EXCITATION_FORMAT
from ..dynamic.excitation_plan import ExcitationPlan, ExcitationPlanError
from ..fit.slow_error import CarriedRunToRun, carried_run_to_run, check_same_sensor
from ..io.atomic_output import OutputError, check_outputs
from ..io.mcap_format import TOPIC_RAW, TOPIC_TEMPERATURE, full_topic_name
from ..io.mcap_writer import RecordingWriter
from .calibration_parameters import (
    EXIT_FIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_RECORDING_FAILED,
    PARAMETERS,
)
from .dynamic_recorder import DynamicRunRecorder
from .pose_plan import PosePlan, PosePlanError
from .pose_recorder import DetectorSettings, RawSample, RunRecorder
from .pose_sequencer import Mode
from .progress_display import ProgressDisplay
from .run_refit import RefitError, expand_sources, refit
from .stream_watch import StreamWatch

__all__ = ["CalibrationNode", "run"]

NODE_NAME = "calibration"
# Deep best-effort queue: compatible with the driver's sensor-data publishers, and a burst while
# the executor writes a chunk is queued instead of dropped. Losses are counted from seq anyway.
RAW_QOS = QoSProfile(reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST, depth=2000)


def plan_format(path: str) -> str | None:
    """The ``format`` key of a plan file (pose plan or excitation plan), None if unreadable (the plan's
    own loader then says why)."""
    try:
        data = read_yaml_file(path, "plan file")
    except YamlFileError:
        return None
    return data.get("format") if isinstance(data, dict) else None


def run(argv: list[str], stopped_ok: bool = False) -> int:
    """One run until it is complete (and ``exit_when_done``), aborted or interrupted; returns the exit status
    (``argv``: the ROS arguments; ``stopped_ok``: a run stopped by SIGINT/SIGTERM exits 0, not 3). StartupError on
    a refused start-up."""
    stop: list[str] = []
    # Own handlers: a signal only sets a flag, the loop below then closes the MCAP in order.
    init_ros("calibration", argv)
    node: CalibrationNode | None = None
    with signals_to(lambda signum: stop.append(signal.Signals(signum).name)) as shutdown:
        try:
            node = CalibrationNode()
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            # spin_once returns at once on a signal, and after the callback that finishes the run
            with signal_wakes_executor(node, shutdown):
                while not stop and not (node.recorder.finished and node.exit_when_done):
                    executor.spin_once(timeout_sec=1.0)
            executor.remove_node(node)
            if stop:
                node.recorder.abort(f"{stop[0]} received")
            status = node.finish(interrupted_by=stop[0] if stop else "")
            return EXIT_OK if stopped_ok and stop and status == EXIT_INTERRUPTED else status
        finally:
            if node is not None:
                node.destroy_node()
            if rclpy.ok():
                rclpy.try_shutdown()


class CalibrationNode(Node):
    """One calibration run: records the plan's poses (or a dynamic run's excitation) from construction; a
    StartupError if the parameters or the plan are refused. ``node_options`` go to rclpy's Node (context,
    parameter_overrides, ...)."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__(NODE_NAME, **node_options)
        with destroyed_if_refused(self):
            self._start()

    def _start(self) -> None:
        """Read and check the parameters, load the plan, open the recording and subscribe (StartupError if refused)."""
        self.p = p = self._read_parameters()
        self.end_reason = ""  # why the node itself ended the run (the stream stopped), for the run_end record
        try:
            self.watch = StreamWatch(p["stream_timeout_s"])
        except ValueError as exc:
            raise StartupError(f"invalid parameter: {exc}") from None
        self.exit_when_done = bool(p["exit_when_done"])
        self.dynamic = plan_format(p["plan_file"]) == EXCITATION_FORMAT
        if self.dynamic:
            self._start_dynamic(p)
            return
        try:
            self.plan = PosePlan.load(p["plan_file"])
            self.setpoint_c = self.plan.level_setpoint_c(p["temperature_level"])
        except PosePlanError as exc:
            raise StartupError(f"pose plan rejected: {exc}") from None
        try:
            self.mode = Mode(p["mode"])
        except ValueError:
            raise StartupError(f"invalid parameter 'mode': {p['mode']!r} (auto or service)") from None
        self.degree = self._parse_degree(p["fit_degree"])
        noise = p["still_noise_std"]
        detector = DetectorSettings(window_s=p["still_window_s"], hold_s=p["still_hold_s"],
                                    noise_std=tuple(noise) if noise else None, learn_s=p["noise_learn_s"],
                                    false_alarm_per_run=p["still_false_alarm_per_run"],
                                    noise_corr_s=p["still_noise_corr_s"])
        try:
            detector.validate()
        except ValueError as exc:
            raise StartupError(f"invalid static detector parameter: {exc}") from None
        self.fit_with = [s for s in (p["fit_with"] or []) if s]
        metadata = {
            "sensor_id": p["sensor_id"], "operator_notes": p["operator_notes"],
            "mode": self.mode.value, "plan_file": str(Path(p["plan_file"]).resolve()), "plan_name": self.plan.name,
            "plan": self.plan.to_yaml(), "temperature_level": p["temperature_level"],
            "chamber_setpoint_c": "" if self.setpoint_c is None else self.setpoint_c,
            "started": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "static_detector": {"window_s": detector.window_s, "hold_s": detector.hold_s,
                                "noise_std_psi": list(noise) if noise else "learnt", "learn_s": detector.learn_s,
                                "noise_corr_s": detector.noise_corr_s,
                                "false_alarm_per_run": detector.false_alarm_per_run},
            "node": "fbg_accel_driver calibration",
        }
        writer = self._open_recording(p, metadata)
        self.recorder = RunRecorder(self.plan, writer, self.mode, detector, sensor_id=p["sensor_id"],
                                    setpoint_c=self.setpoint_c, motion_expect_g=p["motion_expect_g"])
        self._subscribe()
        how = ("call calibration/next_pose after each pose is recorded" if self.mode is Mode.SERVICE
               else "poses advance on table motion / dwell times")
        sp = "" if self.setpoint_c is None else f", chamber level {p['temperature_level']} ({self.setpoint_c:g} degC)"
        self.get_logger().info(
            f"plan '{self.plan.name}': {len(self.plan)} poses, {self.plan.total_samples} samples{sp}; "
            f"mode {self.mode.value} ({how}); recording to {self.mcap_path}")

    def _start_dynamic(self, p: dict[str, Any]) -> None:
        """A dynamic run (excitation plan): record for the plan's duration, no poses, no fit."""
        try:
            plan = ExcitationPlan.load(p["plan_file"])
        except ExcitationPlanError as exc:
            raise StartupError(f"excitation plan rejected: {exc}") from None
        self.setpoint_c = None
        writer = self._open_recording(p, {
            "sensor_id": p["sensor_id"], "operator_notes": p["operator_notes"], "kind": "dynamic",
            "plan_file": str(Path(p["plan_file"]).resolve()), "plan_name": plan.name,
            "excitation_plan": plan.to_dict(), "started": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "node": "fbg_accel_driver calibration"})
        self.recorder = DynamicRunRecorder(plan, writer, sensor_id=p["sensor_id"])
        self._subscribe()
        self.get_logger().info(
            f"dynamic plan '{plan.name}': {len(plan.segments)} segments, "
            f"{', '.join(f'{s.freq_hz:g}' for s in plan.segments)} Hz, {self.recorder.length_s:.0f} s from the "
            f"first sample; recording imu/raw with aux_counts to {self.mcap_path}")

    def _open_recording(self, p: dict[str, Any], metadata: dict[str, Any]) -> RecordingWriter:
        """The run's MCAP, created exclusively (never over a file, never through a link)."""
        namespace = self._recorded_namespace()  # before anything is created
        out_dir = Path(p["output_dir"])
        label = p["run_label"] or self._default_label(p["sensor_id"], p["temperature_level"])
        if not re.fullmatch(r"[A-Za-z0-9_.+-]+", label):
            raise StartupError(f"invalid parameter 'run_label': {label!r} (letters, digits, _ . + - only)")
        self.mcap_path = out_dir / f"{label}.mcap"
        self.yaml_path = Path(p["calibration_file"]) if p["calibration_file"] else out_dir / f"{label}_calibration.yaml"
        try:
            taken = self.mcap_path.exists() or self.mcap_path.is_symlink()
        except (OSError, ValueError) as exc:  # a name too long, a NUL character
            raise StartupError(f"invalid parameter 'output_dir' or 'run_label': {self.mcap_path}: {exc}") from None
        if taken:
            raise StartupError(f"{self.mcap_path} exists; choose another run_label (a recording is never overwritten)")
        self.run_to_run: CarriedRunToRun | None = None  # R for the end-of-run fit (run_to_run_from)
        if p["fit"] and not self.dynamic:
            self._check_calibration_file(p)
            self.run_to_run = self._load_run_to_run(p)
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StartupError(f"cannot create output_dir {out_dir}: {exc}") from None
        try:
            return RecordingWriter(self.mcap_path, {"run_label": label, **metadata}, exclusive=True,
                                   namespace=namespace)
        except FileExistsError:
            raise StartupError(f"{self.mcap_path} exists (a file or a symbolic link); choose another run_label "
                               "(a recording is never overwritten nor written through a link)") from None
        except OSError as exc:
            raise StartupError(f"cannot create {self.mcap_path}: {exc}") from None

    def _check_calibration_file(self, p: dict[str, Any]) -> None:
        """Before the run: the calibration YAML written at its end is neither one of the recordings it is fitted
        from (``fit_with``, the run's own MCAP) nor an existing file without ``force`` (StartupError); the end of the
        run checks again (``refit``)."""
        try:
            sources = expand_sources(self.mcap_path, self.fit_with)
        except (RefitError, OSError, ValueError) as exc:  # a fit_with file that does not exist: found now
            raise StartupError(f"invalid parameter 'fit_with': {exc}") from None
        try:
            own_dir = self.yaml_path.parent == Path(p["output_dir"])  # created next if missing
            check_outputs([self.yaml_path], sources, bool(p["force"]), create_dirs=own_dir)
        except (OutputError, OSError, ValueError) as exc:  # OSError, ValueError: a name too long, a NUL
            msg = str(exc).replace("give --force", "set force:=true")
            raise StartupError(f"invalid parameter 'calibration_file': {msg}") from None

    def _load_run_to_run(self, p: dict[str, Any]) -> CarriedRunToRun | None:
        """Before the run: the run-to-run component R of ``run_to_run_from`` (an earlier calibration of this sensor
        that identified it), read now so that a file missing, unreadable, without R or of another sensor stops
        start-up (StartupError) instead of the end-of-run fit; R is then kept for that fit (None: not given)."""
        if not p["run_to_run_from"]:
            return None
        try:
            carried = carried_run_to_run(p["run_to_run_from"], option="run_to_run_from")
            note = check_same_sensor(carried, p["sensor_id"])
        except ValueError as exc:
            raise StartupError(f"invalid parameter 'run_to_run_from': {exc}") from None
        if note:
            self.get_logger().warning(note.removeprefix("note: "))
        self.get_logger().info(f"run-to-run component R taken from {carried.source} for the end-of-run fit (used "
                               "when this campaign's runs do not identify their own: one run per temperature level)")
        return carried

    def _recorded_namespace(self) -> str:
        """The namespace the recording names its topics under: that of the topics the node subscribes to, after
        remapping (``-r __ns:=/acc_a``, or ``-r imu/raw:=/acc_a/imu/raw -r imu/temperature:=/acc_a/imu/temperature``
        for a node left elsewhere), so the file says which sensor it recorded. The file and the fit name a run's
        topics ``<namespace>/imu/raw``, ``<namespace>/imu/temperature``, ...: remaps that cannot be written so
        are a StartupError."""
        raw = self.resolve_topic_name(TOPIC_RAW)
        temperature = self.resolve_topic_name(TOPIC_TEMPERATURE)
        if not raw.endswith("/" + TOPIC_RAW):
            raise StartupError(f"{TOPIC_RAW} resolves to {raw}: a recording names the raw topic <namespace>/{TOPIC_RAW}; "
                               f"remap it to a name ending in /{TOPIC_RAW}, or run the node in the sensor's namespace "
                               "(-r __ns:=/<namespace>)")
        namespace = raw[: -len(TOPIC_RAW) - 1] or "/"
        if temperature != full_topic_name(namespace, TOPIC_TEMPERATURE):
            raise StartupError(f"{TOPIC_TEMPERATURE} resolves to {temperature} and {TOPIC_RAW} to {raw}: a recording "
                               f"names both under one namespace; remap {TOPIC_TEMPERATURE} to "
                               f"{full_topic_name(namespace, TOPIC_TEMPERATURE)} too, or run the node in the sensor's "
                               "namespace (-r __ns:=/<namespace>)")
        return namespace

    def _subscribe(self) -> None:
        self.display = ProgressDisplay(sys.stdout) if self.p["progress"] else None
        self._name_index: dict[tuple[str, ...], list[int | None]] = {}
        self._bad_names_warned = False
        self.sub_raw = self.create_subscription(
            JointState, "imu/raw", self._on_raw, RAW_QOS,
            event_callbacks=SubscriptionEventCallbacks(matched=lambda info: self._on_matched(self.sub_raw.topic_name, info)))
        self.sub_temp = self.create_subscription(
            Temperature, "imu/temperature", self._on_temperature, RAW_QOS,
            event_callbacks=SubscriptionEventCallbacks(matched=lambda info: self._on_matched(self.sub_temp.topic_name, info)))
        self.srv_next = self.create_service(Trigger, "calibration/next_pose", self._on_next)
        self.srv_abort = self.create_service(Trigger, "calibration/abort", self._on_abort)
        self.watch_timer = self.create_timer(1.0, self._check_stream)

    # ------------------------------------------------------------ parameters
    def _read_parameters(self) -> dict[str, Any]:
        """Declare the parameters (all read-only) and check what a descriptor cannot express."""
        values = declare_parameters(self, PARAMETERS)
        refuse_unknown_parameters(self, "calibration")  # before any file is created
        if not values["plan_file"]:
            raise StartupError("parameter 'plan_file' is required (e.g. -p plan_file:=config/pose_plan_six_position.yaml)")
        for name, (typ, _, _) in PARAMETERS.items():  # names and paths are echoed in messages and logs
            texts = values[name] if typ == "string_array" else [values[name]] if typ == "string" else []
            for text in texts or []:
                if name != "operator_notes":  # free text, stored only
                    try:
                        check_name_text(text, "sensor id" if name == "sensor_id" else "value")
                    except ValueError as exc:
                        raise StartupError(f"invalid parameter '{name}': {exc}") from None
        for name in ("still_window_s", "still_hold_s", "noise_learn_s", "motion_expect_g"):
            if not (math.isfinite(values[name]) and values[name] > 0):
                raise StartupError(f"invalid parameter '{name}': {values[name]} (must be > 0)")
        return values

    @staticmethod
    def _parse_degree(degree: int) -> int | None:
        if degree == -1:
            return None
        if not 0 <= degree <= 6:
            raise StartupError(f"invalid parameter 'fit_degree': {degree} (-1 for auto, or 0..6)")
        return degree

    @staticmethod
    def _default_label(sensor_id: str, level: int) -> str:
        stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ")
        safe = re.sub(r"[^A-Za-z0-9_.+-]", "_", sensor_id) or "sensor"
        return f"{safe}_L{level}_{stamp}" if level >= 0 else f"{safe}_{stamp}"

    # ------------------------------------------------------------ data path
    def _on_raw(self, msg: JointState) -> None:
        if self.recorder.finished:
            return
        names = tuple(msg.name)
        idx = self._name_index.get(names)
        if idx is None:
            idx = [names.index(n) if n in names else None for n in (*RAW_NAMES, RAW_AUX_NAME)]
            self._name_index[names] = idx
        if any(i is None for i in idx[:4]):
            if not self._bad_names_warned:
                self._bad_names_warned = True
                self.get_logger().error(f"imu/raw message without the count names {list(RAW_NAMES[:4])}: {list(names)}; "
                                        "ignored (see docs/topics.md)")
            return
        pos = msg.position

        def val(k: int, default: float) -> float:
            i = idx[k]
            return float(pos[i]) if i is not None and i < len(pos) else default

        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        sample = RawSample(
            stamp_ns=stamp_ns, ref=val(0, math.nan), x=val(1, math.nan), y=val(2, math.nan), z=val(3, math.nan),
            temperature_c=val(4, math.nan), temperature_valid=val(5, 1.0) >= 0.5, status=int(val(6, 0.0)),
            seq=int(val(7, 0.0)), board_time_s=val(8, math.nan), frame_id=msg.header.frame_id,
            aux=val(9, math.nan))
        self.recorder.on_raw(sample)
        back = self.watch.sample(time.monotonic())
        if back:
            self._end_progress_line()
            self.get_logger().info(back)
        self._report()

    def _check_stream(self) -> None:
        """Once a second: report a stopped stream, and end the run after ``stream_timeout_s`` (``StreamWatch``)."""
        if self.recorder.finished:
            return
        warning, reason = self.watch.check(time.monotonic())
        if warning:
            self._end_progress_line()
            self.get_logger().warning(warning)
        if reason:
            self._end_progress_line()
            self.get_logger().error(f"{reason}; the run is ended, {self.mcap_path} closed as it is")
            self.end_reason = reason
            self.recorder.abort(reason)
            self._report()

    def _on_matched(self, topic: str, info: QoSSubscriptionMatchedInfo) -> None:
        """Publisher (dis)connected: say so, the operator sees whether the driver is there."""
        if info.current_count_change > 0:
            self.get_logger().info(f"{topic}: {info.current_count} publisher(s) matched")
        elif info.current_count_change < 0:
            self.get_logger().warning(f"{topic}: publisher lost ({info.current_count} left)")

    def _on_temperature(self, msg: Temperature) -> None:
        if not self.recorder.finished:
            stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            self.recorder.on_temperature(stamp_ns, msg.temperature, msg.variance, frame_id=msg.header.frame_id)

    def _on_next(self, _req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        resp.success, resp.message = self.recorder.request_next()
        # one call site per severity: rclpy refuses a severity change at a call site
        if resp.success:
            self.get_logger().info(f"next_pose: {resp.message}")
        else:
            self.get_logger().warning(f"next_pose: {resp.message}")
        self._report()
        return resp

    def _on_abort(self, _req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        if self.recorder.finished:
            resp.success, resp.message = False, "run already finished"
        else:
            self.recorder.abort("calibration/abort service")
            resp.success, resp.message = True, f"run aborted; {self.mcap_path} will be closed"
        self._report()
        return resp

    def _report(self) -> None:
        log = self.get_logger()
        for level, text in self.recorder.pop_messages():
            self._end_progress_line()
            if level == "warn":
                log.warning(text)
            else:
                log.info(text)
        for ev in self.recorder.pop_events():
            if ev.warning:
                self._end_progress_line()
                log.warning(ev.message)
            elif self.display is not None:
                self.display.event(ev)
            else:
                log.info(ev.message)
        if self.display is not None and self.recorder.monitor is not None:
            self.display.update(self.recorder.sequencer.status(), self.recorder.temperature_c, self.setpoint_c)

    def _end_progress_line(self) -> None:
        if self.display is not None:
            self.display.close()

    # ------------------------------------------------------------ end of run
    def finish(self, interrupted_by: str = "") -> int:
        """Close the MCAP (summary + footer), then refit a complete run; returns the exit status."""
        rec = self.recorder
        self._report()
        complete = rec.done
        reason = interrupted_by or self.end_reason or ("complete" if complete else "aborted")
        summary = rec.close(reason)
        self._end_progress_line()
        log = self.get_logger()
        if summary.get("write_error"):
            where = (f"{self.mcap_path} reads up to its last complete chunk" if self.mcap_path.exists() else
                     f"{self.mcap_path} no longer exists: nothing of this run is on disk")
            log.error(f"run aborted, recording failed: {summary['write_error']}; {where}; no fit")
            return EXIT_RECORDING_FAILED
        if self.dynamic:
            log.info(f"dynamic run {reason}: {self.mcap_path} closed ({summary['messages_raw']} raw messages, "
                     f"{summary['aux_samples']} with the reference, {summary['lost_messages']} lost, "
                     f"{summary['recorded_s']:.1f} of {summary['planned_s']:.1f} s)")
            log.info(f"fit it with: fbg-accel-calib dynamic {self.mcap_path} --plan {self.p['plan_file']} "
                     "--calibration STATIC.yaml -o OUT.yaml")
            return EXIT_OK if complete else EXIT_INTERRUPTED
        short = [p for p in summary["poses"] if p["samples"] < p["target"]]
        log.info(f"run {reason}: {self.mcap_path} closed ({summary['messages_raw']} raw messages, "
                 f"{summary['lost_messages']} lost, {len(short)} pose(s) short)")
        if summary["lost_messages"]:
            log.warning(f"{summary['lost_messages']} imu/raw messages missing (gaps in seq): driver/DDS losses")
        if not complete:
            carry = f" --run-to-run-from {self.p['run_to_run_from']}" if self.run_to_run is not None else ""
            log.warning(f"run not complete: no fit. Fit later with: fbg-accel-calib fit {self.mcap_path} ...{carry}")
            return EXIT_INTERRUPTED
        if not self.p["fit"]:
            return EXIT_OK
        try:
            sources = expand_sources(self.mcap_path, self.fit_with)
            result = refit(sources, self.yaml_path, self.degree, sensor_id=self.p["sensor_id"], force=self.p["force"],
                           run_to_run_from=self.run_to_run)
        except (RefitError, ValueError, OSError) as exc:
            kept = (f"the recording {self.mcap_path} is kept" if self.mcap_path.exists() else
                    f"the recording {self.mcap_path} no longer exists")
            log.error(f"fit failed: {exc}; {kept}")
            return EXIT_FIT_FAILED
        print(result.report(), flush=True)
        log.info(f"calibration written to {self.yaml_path}")
        return EXIT_OK

