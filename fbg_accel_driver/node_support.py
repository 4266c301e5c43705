"""What the two ROS shells (``driver_node`` here and the calibration package's ``calibration_node``) share:
ROS start-up with a clear error, a node refused at start-up destroyed at once, signals that only set a flag and
wake the executor, and declaring a parameter table with descriptors.

Only the node modules import this (it imports rclpy); the ROS-free conventions (``StartupError``,
``--help``/``--version``, unknown-parameter messages) are in ``command_line``.
"""

from __future__ import annotations

import os
import select
import signal
import sys
import tempfile
import threading
from collections.abc import Callable, Collection, Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.exceptions import ParameterException
from rclpy.guard_condition import GuardCondition
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions

from .command_line import ParameterTable, StartupError, first_line, unknown_parameters

# table type word: (descriptor type, the value that declares an unset parameter of that type)
_TYPES: dict[str, tuple[int, Any]] = {
    "string": (ParameterType.PARAMETER_STRING, Parameter.Type.STRING),
    "integer": (ParameterType.PARAMETER_INTEGER, Parameter.Type.INTEGER),
    "double": (ParameterType.PARAMETER_DOUBLE, Parameter.Type.DOUBLE),
    "bool": (ParameterType.PARAMETER_BOOL, Parameter.Type.BOOL),
    "string_array": (ParameterType.PARAMETER_STRING_ARRAY, Parameter.Type.STRING_ARRAY),
    "double_array": (ParameterType.PARAMETER_DOUBLE_ARRAY, Parameter.Type.DOUBLE_ARRAY),
}


def init_ros(prog: str, argv: list[str]) -> None:
    """``rclpy.init`` with the node's ROS arguments and without rclpy's signal handler (that would shut the
    context down at once, under a node that still writes); unparsable ``--ros-args`` become a StartupError."""
    try:
        with c_stderr_held():  # rcl's own "[ERROR] ... Failed to parse global arguments" line: ours says it
            rclpy.init(args=[prog, *argv], signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # RCLError (not exported): its text is the only useful part
        raise StartupError(f"invalid ROS arguments {argv}: {first_line(exc)}") from None


@contextmanager
def destroyed_if_refused(node: Node, cleanup: Callable[[], None] | None = None) -> Iterator[None]:
    """The body of a node's constructor after rclpy's own: if it raises (a refused parameter or plan), ``cleanup``
    (the threads the body started) and ``destroy_node`` end what rclpy already made (parameter services, a rosout
    publisher) before the exception leaves the constructor. Nothing else would: the half-built node is held only by
    the exception's frames, and the garbage collector destroys it whenever they go, in a process perhaps after its
    context has shut down, where Fast DDS can hang on handles destroyed out of order (rclpy issue #456)."""
    try:
        yield
    except BaseException:
        try:
            if cleanup is not None:
                cleanup()
        finally:
            node.destroy_node()
        raise


class ShutdownSignal:
    """Whether SIGINT or SIGTERM has arrived, known from the moment the kernel delivers it, in any thread: the
    interpreter writes a byte to a wakeup pipe at once (``signal.set_wakeup_fd``), while the Python-level handler
    runs only when the main thread next executes bytecode (it may be waiting in the executor for up to its
    timeout). A thread that sees the serial link end can so tell a shutdown (Ctrl-C of a launch file signals the
    simulator and the driver together, and the simulator's pty closes first) from a lost link."""

    def __init__(self) -> None:
        self._read_fd, self.write_fd = os.pipe()
        os.set_blocking(self._read_fd, False)
        os.set_blocking(self.write_fd, False)

    def wait(self, timeout_s: float) -> bool:
        """True once a signal has arrived (at once if it already has), False if none came within ``timeout_s``."""
        if self._read_fd < 0:
            return False
        readable, _, _ = select.select([self._read_fd], [], [], timeout_s)
        return bool(readable)

    def close(self) -> None:
        for fd in (self._read_fd, self.write_fd):
            if fd >= 0:
                os.close(fd)
        self._read_fd = self.write_fd = -1


@contextmanager
def c_stderr_held() -> Iterator[None]:
    """What is written to file descriptor 2 inside the block -- by rcl and rcutils too, which print their own
    error lines and multi-line "error state is being overwritten" blocks -- is held back: written out when the
    block succeeds, dropped when it raises (the caller then reports the error in one line)."""
    sys.stderr.flush()
    saved = os.dup(2)
    ok = False
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
            ok = True
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            if ok and held.tell():
                held.seek(0)
                os.write(2, held.read())


@contextmanager
def signals_to(handler: Callable[[int], None]) -> Iterator[ShutdownSignal]:
    """SIGINT and SIGTERM call ``handler(signum)`` (which only sets a flag) inside the block; restored after. The
    block gets a :class:`ShutdownSignal` that other threads may ask whether a signal has arrived."""
    watch = ShutdownSignal()
    previous_fd = signal.set_wakeup_fd(watch.write_fd, warn_on_full_buffer=False)
    previous = {sig: signal.signal(sig, lambda signum, _frame: handler(signum)) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield watch
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
        signal.set_wakeup_fd(previous_fd)
        watch.close()


@contextmanager
def signal_wakes_executor(node: Node, shutdown: ShutdownSignal) -> Iterator[None]:
    """Inside the block, SIGINT/SIGTERM wakes the executor that spins ``node`` at once (a guard condition of the
    node, triggered by a thread that waits on ``shutdown``'s pipe), so that the main thread returns from
    ``spin_once`` and runs the Python signal handler. The main loop can then spin with a long timeout: an empty
    ``spin_once`` costs ~0.1 ms of CPU, and ten a second would be a twentieth of the driver's cost at 100 Hz
    (bench/floors.py)."""
    stop = threading.Event()
    woken = node.create_guard_condition(lambda: None)
    threading.Thread(target=_trigger_on_signal, args=(shutdown, woken, stop), name="signal wake-up",
                     daemon=True).start()
    try:
        yield
    finally:
        stop.set()


def _trigger_on_signal(shutdown: ShutdownSignal, woken: GuardCondition, stop: threading.Event) -> None:
    """Trigger ``woken`` as soon as a signal arrives; looks at ``stop`` once a second; ends with it, after the
    trigger, or once the pipe is closed."""
    while not stop.is_set():
        try:
            signalled = shutdown.wait(1.0)
        except (OSError, ValueError):  # the wake-up pipe closed meanwhile: the run is over
            return
        if signalled:
            try:
                woken.trigger()
            except Exception:  # the node is being destroyed: the executor loop is ending anyway
                pass
            return


def declare_parameters(
    node: Node,
    table: ParameterTable,
    *,
    writable: Collection[str] = (),
    integer_ranges: Mapping[str, tuple[int, int]] | None = None,
    float_ranges: Mapping[str, tuple[float, float]] | None = None,
    constraints: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """Declare every parameter of ``table`` (read-only unless ``writable``) with its description, range and
    constraint text; returns the values. A value rclpy refuses (wrong type, out of range) is a StartupError
    naming the parameter and what it means."""
    values: dict[str, Any] = {}
    for name, (typ, default, desc) in table.items():
        ptype, unset = _TYPES[typ]
        d = ParameterDescriptor(name=name, type=ptype, description=desc, read_only=name not in writable)
        if integer_ranges and name in integer_ranges:
            lo, hi = integer_ranges[name]
            d.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=1)]
            d.additional_constraints = f"{lo}..{hi}"
        if float_ranges and name in float_ranges:
            lo_f, hi_f = float_ranges[name]
            d.floating_point_range = [FloatingPointRange(from_value=lo_f, to_value=hi_f, step=0.0)]
            d.additional_constraints = f"{lo_f}..{hi_f}"
        if constraints and name in constraints:
            d.additional_constraints = constraints[name]
        try:
            values[name] = node.declare_parameter(name, unset if default is None else default, d).value
        except ParameterException as exc:
            raise StartupError(f"invalid parameter '{name}': {first_line(exc)} ({desc})") from None
    return values


def refuse_unknown_parameters(node: Node, prog: str, *, before_publishers: bool = False) -> None:
    """A misspelt ``-p``/params-file name would be ignored by rclpy: refuse it, naming the nearest. Call it
    after every declaration (publishers declare their ``qos_overrides`` parameters), and with
    ``before_publishers`` (``qos_overrides.*`` names left for that later call) before anything that reads the
    parameters' values, so that the errors a misspelling causes (the parameter it meant is missing) never
    come first."""
    given = getattr(node, "_parameter_overrides", {})  # what --ros-args, params files and the constructor set
    if before_publishers:
        given = [name for name in given if not name.startswith("qos_overrides.")]
    unknown = unknown_parameters(given, node._parameters)
    if unknown:
        raise StartupError("; ".join(unknown) + f" ({prog} --help lists the parameters)")
