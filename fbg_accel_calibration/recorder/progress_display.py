"""Terminal progress display of a calibration run (pure, no ROS).

One status line: pose k of N with its name, the sequencer phase, stillness, samples of the pose,
and the sensor temperature. On a terminal the line is redrawn in place (carriage return) at most
``tty_interval_s`` apart; when the output is not a TTY (a log file, a pipe, ``ros2 launch``) a plain
line is written only when the pose, the phase or the stillness changes, or ``plain_interval_s``
after the previous line, so logs stay readable. Event messages (warnings, prompts) always go out
on their own line.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from typing import TextIO

from .pose_sequencer import SequencerEvent, SequencerStatus

_PHASE_TEXT = {
    "wait_still": "waiting for stillness",
    "recording": "recording",
    "recorded": "recorded, next pose?",
    "wait_motion": "waiting for the table to move",
    "done": "done",
    "aborted": "aborted",
}
# Auto mode: after a pose is recorded the run advances by itself when the table moves (or its dwell ends);
# "next pose?" there read as a prompt to call calibration/next_pose, which auto mode does not need.
_PHASE_TEXT_AUTO = {**_PHASE_TEXT, "recorded": "recorded, advancing when the table moves"}


def format_progress(status: SequencerStatus, temperature_c: float, setpoint_c: float | None = None,
                    bar_width: int = 20) -> str:
    """The status line (no newline): ``pose 2/6 x_down | recording | STILL | 40/100 [#####...] | 24.31 degC``."""
    done = min(status.samples, status.samples_target)
    filled = round(bar_width * done / status.samples_target) if status.samples_target else 0
    bar = "#" * filled + "." * (bar_width - filled)
    temp = "--.-- degC" if not math.isfinite(temperature_c) else f"{temperature_c:.2f} degC"
    if setpoint_c is not None:
        temp += f" (set {setpoint_c:g})"
    still = "STILL" if status.still else "moving"
    phase = (_PHASE_TEXT_AUTO if status.auto else _PHASE_TEXT).get(str(status.phase), str(status.phase))
    return (f"pose {status.pose_index + 1}/{status.pose_count} {status.pose_name} | {phase} | {still} | "
            f"{status.samples}/{status.samples_target} [{bar}] | {temp} | total {status.total_samples}")


class ProgressDisplay:
    """Writes the status line to ``stream`` (default stderr); see the module docstring."""

    def __init__(self, stream: TextIO | None = None, is_tty: bool | None = None, tty_interval_s: float = 0.1,
                 plain_interval_s: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.stream = stream if stream is not None else sys.stderr
        if is_tty is None:
            isatty = getattr(self.stream, "isatty", None)
            is_tty = bool(isatty()) if callable(isatty) else False
        self.is_tty = is_tty
        self.tty_interval_s = tty_interval_s
        self.plain_interval_s = plain_interval_s
        self.clock = clock
        self._last_time = -math.inf
        self._last_key: tuple | None = None
        self._line_open = False  # a TTY line is drawn without newline

    def update(self, status: SequencerStatus, temperature_c: float, setpoint_c: float | None = None,
               force: bool = False) -> bool:
        """Draw the status if due; returns True when something was written."""
        now = self.clock()
        key = (status.pose_index, str(status.phase), status.still)
        interval = self.tty_interval_s if self.is_tty else self.plain_interval_s
        if not (force or key != self._last_key or now - self._last_time >= interval):
            return False
        line = format_progress(status, temperature_c, setpoint_c)
        if self.is_tty:
            self.stream.write("\r\x1b[2K" + line)
            self._line_open = True
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
        self._last_time, self._last_key = now, key
        return True

    def event(self, event: SequencerEvent) -> None:
        """An event on its own line (after ending a status line drawn in place)."""
        self.message(("WARNING: " if event.warning else "") + event.message)

    def message(self, text: str) -> None:
        self._end_line()
        self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        self._end_line()
        self.stream.flush()

    def _end_line(self) -> None:
        if self._line_open:
            self.stream.write("\n")
            self._line_open = False
