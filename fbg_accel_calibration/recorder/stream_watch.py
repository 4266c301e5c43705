"""Watch of the sample stream during a calibration run: say when it stops, and end the run if asked to.

Pure Python (no ROS). The calibration node feeds it the host's monotonic time of every ``imu/raw`` sample and asks it
once a second what to do. A run in a climatic chamber can outlast a link outage the driver recovers from (it
reconnects without end), so by default a stopped stream is only reported, once per stall, and reported again when
samples come back; with a timeout the run is ended after that long without a sample (an unattended run whose board
or driver has stopped for good would otherwise wait forever, its file open).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

STALL_WARN_S = 5.0  # s without a sample after which a stall is reported (a few hundred samples of any plan)


@dataclass
class StreamWatch:
    """``timeout_s``: end the run after this long without a sample (0: never). Times are the host's monotonic
    seconds; nothing is judged before the first sample (the node may start before the driver)."""

    timeout_s: float = 0.0
    warn_s: float = STALL_WARN_S
    _last: float | None = field(default=None, init=False)  # time of the latest sample
    _warned: bool = field(default=False, init=False)  # the current stall is reported

    def __post_init__(self) -> None:
        if not (math.isfinite(self.timeout_s) and self.timeout_s >= 0):
            raise ValueError(f"stream_timeout_s must be a finite value >= 0, got {self.timeout_s}")

    def sample(self, now: float) -> str:
        """A sample arrived at ``now``; returns the message that the stream is back after a reported stall, or ""."""
        back = ""
        if self._warned and self._last is not None:
            back = f"imu/raw samples again after {now - self._last:.1f} s without any"
        self._last, self._warned = now, False
        return back

    def check(self, now: float) -> tuple[str, str]:
        """(warning, reason to end the run) at ``now``, each "" when there is none: the warning once per stall, after
        ``warn_s``; the reason once ``timeout_s`` (when set) has passed without a sample."""
        if self._last is None:
            return "", ""
        silent = now - self._last
        if self.timeout_s > 0 and silent >= self.timeout_s:
            return "", (f"no imu/raw sample for {silent:.1f} s (stream_timeout_s {self.timeout_s:g}): the board or the "
                        "driver stopped")
        if silent >= self.warn_s and not self._warned:
            self._warned = True
            end = (f"the run ends after {self.timeout_s:g} s without one (stream_timeout_s)" if self.timeout_s > 0 else
                   "the run waits for the stream to come back (calibration/abort or Ctrl-C ends it, the file closed)")
            return (f"no imu/raw sample for {silent:.1f} s: the board or the driver stopped, or the link is down; {end}",
                    "")
        return "", ""
