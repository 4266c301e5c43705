"""Serial link to the acquisition board: a pyserial reader in its own thread (no ROS).

The reader thread owns the port. It opens it, reads whatever bytes are available (it waits for the first byte and
takes all that arrived with it in the same read, so a frame is one chunk, not 1 + 26 bytes, and a backlog of
many frames is one chunk too) and
puts ``(host_ns, bytes, steady_ns)`` chunks on a bounded queue (``chunk_queue.ChunkQueue``: the oldest chunks
are dropped and counted when a consumer falls ``max_queued_bytes`` behind), stamped with the host
time right after the read returned (the clock is injectable so the ROS node can pass its ROS clock) and the steady
time of that instant (``steady_clock_ns``).
It never blocks on its consumer: the consumer blocks on ``queue`` (the driver node's publisher
thread), or drains it when ``notify`` fires.

The port is opened exclusively (pyserial ``exclusive=True``: an advisory ``flock``, taken before pyserial
configures the port or flushes its input): a second reader of the same port, such as a second driver, is refused
("in use") and retries with the back-off below, taking the port over once the first closes it. Two readers would
otherwise split the stream between them, each losing frames.

When the port vanishes or fails (unplugged USB adapter, closed pty, I/O error, the path does not
exist yet) the thread closes it, reports the link as DISCONNECTED with the reason, and tries
again after an exponential back-off (``backoff_initial_s`` doubling up to ``backoff_max_s``),
forever, until ``stop()``. The back-off resets once a connection delivered data. One thread for
the whole life of the link: reconnecting never starts another thread.
"""

from __future__ import annotations

import enum
import errno
import os
import select
import termios
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import serial

from .chunk_queue import ChunkQueue

# What a port that fails or vanishes raises through pyserial: SerialException and OSError mostly, but also
# termios.error (not an OSError) from the tcsetattr/tcflush of open() when the tty hangs up meanwhile, and
# TypeError/ValueError on a closed fd. Each of them is a lost port to retry, never the end of the reader thread.
PORT_ERRORS = (serial.SerialException, OSError, termios.error, TypeError, ValueError)

# The steady clock each read is stamped with next to the host (ROS) clock (``clock_sync`` fits the board clock
# against it with a straight line over 200 s). CLOCK_MONOTONIC does not step, but NTP (ntpd, chrony) slews it
# together with the host clock (clock_gettime(2)): a slew bent that line and the stamps lagged ROS time by the
# slewed amount for minutes (a 20 ms ntpd slew: up to 20 ms for 100 s). CLOCK_MONOTONIC_RAW is the oscillator NTP
# does not adjust, so the slew shows in the host-minus-steady offset, which the stamps follow. Elsewhere (no
# CLOCK_MONOTONIC_RAW) the monotonic clock.
if hasattr(time, "CLOCK_MONOTONIC_RAW"):
    def steady_clock_ns() -> int:
        """NTP-unadjusted monotonic time, ns (CLOCK_MONOTONIC_RAW)."""
        return time.clock_gettime_ns(time.CLOCK_MONOTONIC_RAW)
else:  # pragma: no cover - not Linux
    steady_clock_ns = time.monotonic_ns


class LinkState(enum.Enum):
    """State of the serial link as reported in diagnostics."""

    CONNECTING = "connecting"  # not opened yet (first attempt pending)
    CONNECTED = "connected"
    DISCONNECTED = "disconnected"  # failed or vanished; waiting for the back-off to retry
    STOPPED = "stopped"


@dataclass(frozen=True)
class LinkStatus:
    """Snapshot of the link for diagnostics."""

    state: LinkState
    port: str
    baud: int
    message: str  # last error or "open"
    connects: int  # successful opens
    disconnects: int  # connections lost or attempts failed after a success
    failed_attempts: int  # opens that failed
    next_retry_s: float  # back-off currently applied (0 when connected)
    bytes_read: int
    thread_alive: bool
    queued_bytes: int = 0  # waiting for the consumer now
    queue_dropped_chunks: int = 0  # discarded (oldest first) because the consumer fell behind
    queue_dropped_bytes: int = 0


class SerialLink:
    """Reader thread for one serial port, with reconnect and exponential back-off."""

    def __init__(
        self,
        port: str,
        baud: int,
        notify: Callable[[], None] | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
        steady_ns: Callable[[], int] = steady_clock_ns,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = 2.0,
        read_timeout_s: float = 0.1,
        max_chunk: int = 65536,
        silence_timeout_s: float = 0.0,
        max_queued_bytes: int = 262_144,
    ) -> None:
        self.port = port
        self.baud = baud
        self.queue = ChunkQueue(max_queued_bytes)
        self._notify = notify or (lambda: None)
        self._clock_ns = clock_ns
        self._steady_ns = steady_ns
        self._backoff_initial = backoff_initial_s
        self._backoff_max = backoff_max_s
        self._read_timeout = read_timeout_s
        self._max_chunk = max_chunk
        self._silence_timeout = silence_timeout_s
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._state = LinkState.CONNECTING
        self._message = "not opened yet"
        self._connects = 0
        self._disconnects = 0
        self._failed = 0
        self._backoff = 0.0
        self._bytes = 0
        self._state_changes = 0

    # ------------------------------------------------------------------ control
    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError("SerialLink already started")
        self._thread = threading.Thread(target=self._run, name=f"serial-link {self.port}", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the reader thread and close the port (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        self._set_state(LinkState.STOPPED, "stopped")

    def status(self) -> LinkStatus:
        qs = self.queue.stats()
        with self._lock:
            return LinkStatus(
                state=self._state,
                port=self.port,
                baud=self.baud,
                message=self._message,
                connects=self._connects,
                disconnects=self._disconnects,
                failed_attempts=self._failed,
                next_retry_s=self._backoff if self._state is LinkState.DISCONNECTED else 0.0,
                bytes_read=self._bytes,
                thread_alive=self._thread is not None and self._thread.is_alive(),
                queued_bytes=qs.queued_bytes,
                queue_dropped_chunks=qs.dropped_chunks,
                queue_dropped_bytes=qs.dropped_bytes,
            )

    @property
    def state_changes(self) -> int:
        """Number of state transitions so far (lets a consumer notice a flap between polls)."""
        return self._state_changes

    # ------------------------------------------------------------------ thread
    def _read_clocks(self) -> tuple[int, int]:
        """(host ns, steady ns) of one instant: the host clock (ROS time, which may step) read between two reads
        of the steady clock (``steady_clock_ns``: not slewed by NTP), the steady time their midpoint; of three tries
        the tightest bracket, so a thread switch between two reads does not put its delay into the host-minus-steady
        offset of the stamps."""
        best: tuple[int, int, int] | None = None
        steady = self._steady_ns
        for _ in range(3):
            before = steady()
            host = self._clock_ns()
            after = steady()
            if best is None or after - before < best[0]:
                best = (after - before, host, (before + after) // 2)
            if after - before < 20_000:  # 20 us: tight enough
                break
        return best[1], best[2]

    def _set_state(self, state: LinkState, message: str) -> None:
        with self._lock:
            if state is not self._state:
                self._state_changes += 1
            self._state, self._message = state, message
        self._wake()

    def _wake(self) -> None:
        """Tell the consumer there is something to look at; a failing consumer must not kill the reader."""
        try:
            self._notify()
        except Exception:  # e.g. the ROS context is already shut down while the node exits
            pass

    def _run(self) -> None:
        backoff = self._backoff_initial
        while not self._stop.is_set():
            # the device the name designates now is the one opened, so a later re-pointing is always seen
            opened_target = os.path.realpath(self.port)
            try:
                ser = serial.Serial(opened_target, self.baud, timeout=self._read_timeout, exclusive=True)
            except PORT_ERRORS as exc:
                with self._lock:
                    self._failed += 1
                    self._backoff = backoff
                why = _reason(exc)
                if getattr(exc, "errno", None) in (errno.EAGAIN, errno.EWOULDBLOCK):  # the flock of exclusive=True
                    why = f"in use by another process (a second driver on this port?): {why}"
                self._set_state(LinkState.DISCONNECTED, f"cannot open {self.port}: {why}")
                if self._stop.wait(backoff):
                    break
                backoff = min(backoff * 2.0, self._backoff_max)
                continue
            with self._lock:
                self._connects += 1
            self._set_state(LinkState.CONNECTED, "open")
            got_data = False
            last_data = last_target_check = time.monotonic()
            try:
                read_ready = _ReadReady(ser)
                while not self._stop.is_set():
                    data = read_ready(self._max_chunk)
                    now = time.monotonic()
                    if now - last_target_check >= self._read_timeout:  # also while data flows: the old device may
                        last_target_check = now                          # stream on after the name moved
                        if (target := os.path.realpath(self.port)) != opened_target:
                            raise _StaleLinkError(f"{self.port} now points to {target}")
                    if not data:
                        silent = now - last_data
                        if self._silence_timeout > 0 and silent >= self._silence_timeout:
                            raise _StaleLinkError(f"no data for {silent:.1f} s")
                        continue
                    host_ns, steady_ns = self._read_clocks()  # every byte of ``data`` had arrived by then
                    last_data = now
                    with self._lock:
                        self._bytes += len(data)
                    self.queue.put(host_ns, data, steady_ns)
                    self._wake()
                    if not got_data:
                        got_data = True
                        backoff = self._backoff_initial
            except (*PORT_ERRORS, _StaleLinkError) as exc:
                if not self._stop.is_set():
                    with self._lock:
                        self._disconnects += 1
                        self._backoff = backoff
                    self._set_state(LinkState.DISCONNECTED, f"{self.port} lost: {_reason(exc)}")
            finally:
                try:
                    ser.close()
                except PORT_ERRORS:
                    pass
            if self._stop.wait(backoff if not self._stop.is_set() else 0):
                break
            backoff = min(backoff * 2.0, self._backoff_max)


class _ReadReady:
    """Whatever the open port ``ser`` holds, in one read: wait up to its timeout for the first byte (``poll``),
    then one ``os.read`` of all that is waiting, up to ``max_bytes``; ``b""`` on timeout.

    pyserial's own ``read(n)`` costs a ``select``, a timeout object and a loop per call, and taking what is waiting
    with it needs ``in_waiting`` (an ioctl) before and after a ``read(1)``: six system calls for each frame at 1 kHz
    (ioctl, select, read, ioctl, select, read), where this makes two (poll, read). pyserial still opens,
    configures, locks and closes the port (its file descriptor is non-blocking, ``O_NONBLOCK``). As in pyserial, a
    port that reports readiness but gives no data (a device gone) raises, and EAGAIN/EINTR are an empty read."""

    __slots__ = ("_fd", "_poll", "_timeout_ms")

    def __init__(self, ser: serial.Serial) -> None:
        self._fd = ser.fileno()
        self._poll = select.poll()
        self._poll.register(self._fd, select.POLLIN)
        timeout = ser.timeout
        self._timeout_ms = None if timeout is None else max(0, round(timeout * 1000))

    def __call__(self, max_bytes: int) -> bytes:
        events = self._poll.poll(self._timeout_ms)
        if not events:
            return b""
        if events[0][1] & select.POLLNVAL:
            raise serial.SerialException("the port was closed")
        try:
            data = os.read(self._fd, max_bytes)
        except (BlockingIOError, InterruptedError):
            return b""
        if not data:
            raise serial.SerialException("device reports readiness to read but returned no data "
                                         "(device disconnected or multiple access on port?)")
        return data


class _StaleLinkError(Exception):
    """The open port stopped delivering (silence) or its name now points to another device."""


def _reason(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0][:200]
