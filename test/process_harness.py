"""Child processes for the process-level tests: output collected line by line, waits on conditions.

No fixed sleeps and no polling: every wait is woken by the event it waits for (a line, the end of the
output, a callback) and fails at a deadline with the output so far.
"""

from __future__ import annotations

import re
import signal
import subprocess
import threading
import time
from collections.abc import Callable


class Notifier:
    """A condition several sources notify: a ROS callback, a publishing thread, a child's output.

    ``wait_until(pred)`` re-checks ``pred`` each time it is woken: a source changes its state, then calls
    ``notify``. The predicate is checked and the wait begun under one lock, so no notification is lost.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()

    def notify(self, *_: object) -> None:
        """Wake the waiters (any arguments are ignored, so this can be a callback as it is)."""
        with self._cond:
            self._cond.notify_all()

    def wait_until(self, pred: Callable[[], bool], timeout: float, what: str) -> None:
        """Return once ``pred()`` holds; AssertionError naming ``what`` after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not pred():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
                self._cond.wait(remaining)


class ChildProcess:
    """A child process whose combined stdout/stderr is collected line by line in a thread."""

    def __init__(self, name: str, args: list, notifier: Notifier | None = None) -> None:
        self.name = name
        self._notifier = notifier or Notifier()  # also woken by each line and at the end of the output
        self.proc = subprocess.Popen([str(a) for a in args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, bufsize=1)
        self.lines: list[str] = []
        self._lock = threading.Lock()
        self._new_output = threading.Condition(self._lock)  # notified per line and at end of output
        self._ended = False
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._new_output:
                self.lines.append(line.rstrip("\n"))
                self._new_output.notify_all()
            self._notifier.notify()
        with self._new_output:
            self._ended = True
            self._new_output.notify_all()
        self._notifier.notify()

    @property
    def output_ended(self) -> bool:
        """The child closed its output (it exited, or is exiting)."""
        with self._lock:
            return self._ended

    def output(self) -> str:
        with self._lock:
            return "\n".join(self.lines)

    def find(self, pattern: str) -> str | None:
        """First output line matching the regular expression ``pattern``, or None."""
        rx = re.compile(pattern)
        with self._lock:
            return next((ln for ln in self.lines if rx.search(ln)), None)

    def wait_line(self, pattern: str, timeout: float = 30.0) -> str:
        """Wait for an output line matching ``pattern``, woken by each new line (no polling); fails early if
        the process's output ends (it exited) first."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        with self._new_output:
            while True:
                hit = next((ln for ln in self.lines if rx.search(ln)), None)
                if hit is not None:
                    return hit
                if self._ended:
                    self.proc.wait(timeout=10)
                    raise AssertionError(f"{self.name} exited ({self.proc.returncode}) before /{pattern}/:\n"
                                         + "\n".join(self.lines))
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {self.name} output /{pattern}/\n"
                                         "--- output so far:\n" + "\n".join(self.lines))
                self._new_output.wait(remaining)

    def wait_exit(self, timeout: float = 30.0) -> int:
        """Exit code; kills the process and fails if it does not exit within ``timeout`` s."""
        try:
            rc = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise AssertionError(f"{self.name} did not exit within {timeout} s:\n{self.output()}") from None
        self._reader.join(timeout=5)
        return rc

    def stop(self, timeout: float = 15.0) -> int:
        """SIGINT, then SIGKILL if it does not exit within ``timeout`` s; returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        return self.proc.returncode

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
