"""Sequence and board-clock bookkeeping of the ``imu/raw`` stream, shared by the calibration recorders.

The driver's raw message carries the board's frame ``seq`` (u16, wraps), its ``status`` flags and its
board time (s). A board reset restarts both the sequence and the clock, so neither a sequence gap nor
a clock difference across it means anything: the decoder of the driver
(``fbg_accel_driver.stream_decoder``) counts no loss across a reset, and the recorders must not either.
The reset rule is the decoder's: a board time that goes backwards, or the ``BOOT`` status bit on a
message after the first, starts a new board run.

:class:`BoardStream` counts lost messages (gaps in ``seq`` within one board run), repeated ones (a
``seq`` equal to or just behind the previous one, within one board run) and resets, and keeps the
board time elapsed since the first message, continuous across resets (a reset adds no time: the
length of the outage is unknown; a forward jump within a board run, an outage of the link, counts;
without a board time, the host stamps measure it).
Pure, no ROS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fbg_accel_driver.frame_codec import SEQ_MODULO, Status


@dataclass(frozen=True)
class StreamStep:
    """What one message meant: ``reset`` it starts a new board run; ``elapsed_s`` board time (s) since the
    first message, continuous across resets (the lost and repeated messages are the tracker's running counts)."""

    reset: bool
    elapsed_s: float


@dataclass
class BoardStream:
    """Tracker of one stream of raw messages (module docstring)."""

    lost: int = 0
    repeated: int = 0
    resets: int = 0
    elapsed_s: float = 0.0  # s of board time since the first message, continuous across resets

    def __post_init__(self) -> None:
        self._last_seq: int | None = None
        self._last_t: float | None = None
        self._last_host: float | None = None

    def update(self, seq: int, board_time_s: float | None, status: int,
               host_time_s: float | None = None) -> StreamStep:
        """Account for one message: frame ``seq``, board time (s; None or NaN when unknown), ``status`` and
        the host stamp (s; only for the elapsed time of a message without a board time, never for resets)."""
        seq = int(seq)
        t = float(board_time_s) if board_time_s is not None and math.isfinite(board_time_s) else None
        reset = False
        if self._last_seq is not None:
            back = t is not None and self._last_t is not None and t < self._last_t
            reset = back or bool(int(status) & Status.BOOT)
            if reset:
                self.resets += 1
            else:
                gap = (seq - self._last_seq) % SEQ_MODULO
                if gap == 0 or gap > SEQ_MODULO // 2:
                    self.repeated += 1
                elif gap > 1:
                    self.lost += gap - 1
                if t is not None and self._last_t is not None:
                    self.elapsed_s += t - self._last_t
                elif t is None and host_time_s is not None and self._last_host is not None:
                    self.elapsed_s += max(0.0, host_time_s - self._last_host)
        self._last_seq = seq
        self._last_host = host_time_s
        if t is not None:
            self._last_t = t
        return StreamStep(reset, self.elapsed_s)
