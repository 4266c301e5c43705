"""Board clock -> host (ROS) time mapping, robust to serial jitter and board resets (pure Python).

The board stamps every sample with its own microsecond clock (``t_us``). The host only learns
when the bytes *arrived*, which is the true sampling time plus a transport delay that is always
positive and jittery (UART, USB/pty buffering, scheduler). Mapping model, per sample::

    host_s = board_s + offset(board_s) + delay,        delay >= 0
    offset(board_s) = a + d * (board_s - board_ref_s)  (a: offset in s, d: relative drift)

Estimator (a minimum-delay / lower-envelope estimator, as used by NTP/PTP-style clock filters):

* observations ``host_s - board_s`` are grouped into bins of ``bin_s`` board seconds and only the
  minimum of each bin is kept: the minimum is the sample that travelled with the least delay;
* a line is fitted by least squares through the last ``window_bins`` bin minima (drift ``d``
  limited to +-``max_drift``) and then lowered until it touches the lowest minimum, so it is a
  lower envelope of the observations;
* the *applied* offset follows that target by slewing at most ``max_slew`` seconds per board
  second (``warmup_slew`` during the first ``warmup_s`` after a (re)start, while the estimate is
  still coarse), so consecutive stamps keep the board's sample spacing to within the slew rate
  (plus the drift estimate), i.e. 0.55 % at worst and 0.1 % once settled; an error larger
  than ``step_threshold_s`` (first sample, host clock jump) is stepped at once;
* an observation far below the envelope, or observations far above it for ``jump_confirm_s``,
  mean the host clock jumped: the estimate restarts from the new data;
* stamps are strictly increasing: a stamp never goes below the previous stamp + 1 ns;
* ``reset()`` (board reboot: sequence and clock restart) forgets the estimate but keeps the
  monotonic guard, so stamps keep increasing across a reboot.

Units: seconds (float) for board time and offsets, integer nanoseconds for host/ROS stamps.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ClockSyncConfig:
    """Tuning of the estimator (see module docstring)."""

    bin_s: float = 0.5  # board seconds per minimum-delay bin
    window_bins: int = 40  # bins used for the line fit (20 s at the default bin length)
    max_drift: float = 500e-6  # |d| limit: +-500 ppm, far beyond a crystal's +-50 ppm
    max_slew: float = 500e-6  # applied offset changes by at most 0.5 ms per board second
    warmup_s: float = 5.0  # after a (re)start the estimate is still coarse ...
    warmup_slew: float = 5e-3  # ... so it may be slewed 10x faster (stamp spacing still within 0.55 %)
    step_threshold_s: float = 0.05  # larger errors are stepped, not slewed
    prime_s: float = 0.2  # board seconds observed before the first stamp is worth giving (see ``primed``)
    jump_confirm_s: float = 2.0  # all observations this long above the estimate + threshold: host clock jumped


@dataclass
class _Bin:
    index: int
    board_s: float  # board time of the minimum
    offset_s: float  # minimum of host_s - board_s in this bin


class ClockSync:
    """Map board timestamps (microseconds) onto host/ROS time (nanoseconds).

    Usage per received chunk: call ``observe(t_us, host_ns)`` for every frame of the chunk (with
    the host time the chunk arrived), then ``stamp(t_us)`` for each frame in order.
    """

    def __init__(self, config: ClockSyncConfig | None = None) -> None:
        self.config = config or ClockSyncConfig()
        self._last_stamp_ns: int | None = None
        # Offsets are kept relative to an integer-ns base (host - board at the first observation)
        # so float arithmetic stays at sub-ns precision even with epoch-sized host times.
        self._base_ns: int | None = None
        self.resets = 0
        self.steps = 0
        self._clear()

    def _clear(self) -> None:
        self._bins: list[_Bin] = []
        self._board_ref_s: float | None = None
        self._a = 0.0  # target offset at board_ref_s, s
        self._d = 0.0  # target drift, s/s
        self._applied: float | None = None  # applied offset, s
        self._applied_at_s: float | None = None  # board time the applied offset refers to
        self._high_since_s: float | None = None  # board time since when every observation was far above the estimate
        self._started_s: float | None = None  # board time of the first observation since the (re)start
        self._last_obs_s: float | None = None

    # ------------------------------------------------------------------ inputs
    def reset(self) -> None:
        """Board reset: the board clock restarted, forget the estimate (stamps stay monotonic)."""
        self.resets += 1
        self._clear()

    def observe(self, t_us: int, host_ns: int) -> None:
        """One observation: a frame stamped ``t_us`` on the board had arrived by ``host_ns``."""
        board_s = t_us * 1e-6
        if self._base_ns is None:
            self._base_ns = host_ns - t_us * 1000
        offset = (host_ns - t_us * 1000 - self._base_ns) * 1e-9
        if self._bins:
            # Host clock jumps: far below the lower envelope at once (impossible with a positive
            # delay), or far above it for jump_confirm_s (a delay that large cannot last that long).
            err = offset - self.target_offset_s(board_s)
            cfg = self.config
            if err < -cfg.step_threshold_s:
                self._restart()
            elif err > cfg.step_threshold_s:
                if self._high_since_s is None:
                    self._high_since_s = board_s
                elif board_s - self._high_since_s >= cfg.jump_confirm_s:
                    self._restart()
            else:
                self._high_since_s = None
        if self._board_ref_s is None:
            self._board_ref_s = board_s
            self._started_s = board_s
        self._last_obs_s = board_s
        index = int((board_s - self._board_ref_s) // self.config.bin_s)
        bins = self._bins
        if bins and bins[-1].index == index:
            if offset < bins[-1].offset_s:
                bins[-1].board_s, bins[-1].offset_s = board_s, offset
            else:
                return
        elif bins and index < bins[-1].index:
            return  # out of order (cannot happen after a reset; ignore defensively)
        else:
            bins.append(_Bin(index, board_s, offset))
            if len(bins) > self.config.window_bins:
                del bins[0]
        self._refit()

    def _refit(self) -> None:
        bins = self._bins
        ref = self._board_ref_s or 0.0
        if len(bins) >= 3:
            xs = [b.board_s - ref for b in bins]
            ys = [b.offset_s for b in bins]
            n = len(xs)
            mx, my = sum(xs) / n, sum(ys) / n
            sxx = sum((x - mx) ** 2 for x in xs)
            d = sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sxx if sxx > 0 else 0.0
            d = max(-self.config.max_drift, min(self.config.max_drift, d))
            a = my - d * mx
            # Lower envelope: lower the line until it touches the lowest point.
            a += min(y - (a + d * x) for x, y in zip(xs, ys, strict=True))
        else:
            d = 0.0
            a = min(b.offset_s for b in bins)
        self._a, self._d = a, d

    def _restart(self) -> None:
        """Forget the bins after a host clock jump; the next stamp() steps to the new estimate."""
        self._bins.clear()
        self._board_ref_s = None
        self._high_since_s = None

    # ------------------------------------------------------------------ outputs
    def target_offset_s(self, board_s: float) -> float:
        """Current estimate of host - board offset at ``board_s`` (s, relative to the internal base)."""
        return self._a + self._d * (board_s - (self._board_ref_s or 0.0))

    @property
    def drift(self) -> float:
        """Estimated relative drift of the host clock against the board clock (s/s)."""
        return self._d

    @property
    def primed(self) -> bool:
        """True once ``prime_s`` of board time was observed since the (re)start.

        A caller that can wait (the driver core does) holds the first frames until then, so the
        first stamps already come from a minimum over many delays instead of from one delay that
        might be a start-up stall; otherwise a large first error would have to be stepped back
        later, which breaks the stamp spacing.
        """
        if self._started_s is None or self._last_obs_s is None:
            return False
        return self._last_obs_s - self._started_s >= self.config.prime_s

    def stamp(self, t_us: int) -> int:
        """Host/ROS time in ns for board time ``t_us``; call ``observe`` for it first."""
        board_s = t_us * 1e-6
        target = self.target_offset_s(board_s)
        cfg = self.config
        if self._applied is None or self._applied_at_s is None:
            applied = target
        else:
            dt = board_s - self._applied_at_s
            # Follow the drift, then slew towards the target.
            applied = self._applied + self._d * max(dt, 0.0)
            err = target - applied
            if abs(err) > cfg.step_threshold_s:
                applied = target
                self.steps += 1
            else:
                warm = self._started_s is not None and board_s - self._started_s < cfg.warmup_s
                limit = (cfg.warmup_slew if warm else cfg.max_slew) * max(dt, 0.0)
                applied += max(-limit, min(limit, err))
        self._applied, self._applied_at_s = applied, board_s
        stamp_ns = t_us * 1000 + (self._base_ns or 0) + round(applied * 1e9)
        if self._last_stamp_ns is not None and stamp_ns <= self._last_stamp_ns:
            stamp_ns = self._last_stamp_ns + 1
        self._last_stamp_ns = stamp_ns
        return stamp_ns
