"""Board clock -> host (ROS) time mapping, robust to serial jitter and board resets (pure Python).

The board stamps every sample with its own microsecond clock (``t_us``). The host only learns
when the bytes *arrived*, which is the true sampling time plus a transport delay that is always
positive and jittery (UART, USB/pty buffering, scheduler). Mapping model, per sample, on the
host's steady clock (host time minus a host-minus-steady offset measured at each read, see below)::

    steady_s = board_s + offset(board_s) + delay,      delay >= 0
    offset(board_s) = a + d * (board_s - board_ref_s)  (a: offset in s, d: relative drift)

Estimator (a minimum-delay / lower-envelope estimator, as used by NTP/PTP-style clock filters):

* observations ``steady_s - board_s`` are grouped into bins of ``bin_s`` board seconds and only the
  minimum of each bin is kept: the minimum is the sample that travelled with the least delay;
* the line is the lower envelope of the last ``window_bins`` bin minima: below all of them and
  highest at their mean board time (the edge of their lower convex hull there,
  ``lower_envelope_slope``; drift ``d`` limited to +-``max_drift``), so observations delayed by a
  stall or a backlog, which lie above it, do not tilt it;
* the *applied* offset follows that target by slewing at most ``max_slew`` seconds per board
  second (``warmup_slew`` during the first ``warmup_s`` after a (re)start, while the estimate is
  still coarse), so consecutive stamps keep the board's sample spacing to within the slew rate
  (plus the drift estimate), i.e. 0.55 % at worst and 0.1 % once settled; an error larger
  than ``step_threshold_s`` (first sample, a restart) is stepped at once;
* host clock jumps are measured, not guessed: the caller reads a steady clock that NTP neither steps nor slews
  (CLOCK_MONOTONIC_RAW, ``serial_link.steady_clock_ns``) next to the host clock at each read, the estimate runs on
  the steady clock and each stamp adds the host-minus-steady offset: a step beyond ``step_threshold_s`` at once and
  exactly, a smaller change (an NTP slew, a small step) at once to within ``host_offset_band_s`` once two of the last
  three reads agree on it, and inside that band at ``max_slew`` (the read jitter of the two clocks).
  Observations far *above* the envelope are therefore always a delay (a stall, a backlog, a congested
  link) and never restart the estimate (they did when they lasted 2 s, and a 0.3 s congestion of the
  link then stamped samples 0.3 s late for 20 s); an observation far *below* it cannot be a delay (the
  board clock jumped ahead without a reboot, or a caller without a steady clock saw its host clock
  step back): the estimate restarts from the new data;
* stamps are strictly increasing: a stamp never goes below the previous stamp + 1 ns;
* ``reset()`` (board reboot: sequence and clock restart) forgets the estimate but keeps the
  monotonic guard, so stamps keep increasing across a reboot.

Units: seconds (float) for board time and offsets, integer nanoseconds for host/ROS stamps.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass


@dataclass(frozen=True)
class ClockSyncConfig:
    """Tuning of the estimator (see module docstring)."""

    bin_s: float = 0.5  # board seconds per minimum-delay bin
    # bins used for the line fit (200 s at the default bin length). The slope is the lower-hull edge at the window's
    # middle; over 20 s (40 bins) that edge was often two bins 0.5-1 s apart, its slope their minima's ms of jitter over
    # that second: +-150..500 ppm through a USB-serial latency timer or a bursty Bluetooth link, stamps wandering
    # ms before and after the delay floor (test_bursty_usb_and_bluetooth_delivery_keep_the_drift_and_the_stamps).
    # A crystal's drift changes by far less than a ppm over 200 s, so the longer baseline costs no tracking.
    window_bins: int = 400
    max_drift: float = 500e-6  # |d| limit: +-500 ppm, far beyond a crystal's +-50 ppm
    max_slew: float = 500e-6  # applied offset changes by at most 0.5 ms per board second
    warmup_s: float = 5.0  # after a (re)start the estimate is still coarse ...
    warmup_slew: float = 5e-3  # ... so it may be slewed 10x faster (stamp spacing still within 0.55 %)
    step_threshold_s: float = 0.05  # larger errors are stepped, not slewed
    prime_s: float = 0.2  # board (or arrival) seconds observed before the first stamp is worth giving (``primed``)
    # The host-minus-steady offset (ROS time minus the steady clock, ``stamp``) is followed at once to within this band
    # once two of the last three reads agree on it (their median), and inside the band at ``max_slew``: the read
    # jitter of the two clocks (up to ~1 ms, a thread switch between the reads) stays out of the stamp spacing, while a
    # fast NTP slew (chrony: up to 83333 ppm) or a step below ``step_threshold_s`` reaches the stamps at once. Before,
    # everything below the step threshold was slewed at max_slew: up to 50 ms off ROS time for 80 s.
    host_offset_band_s: float = 2e-3


def lower_envelope_slope(xs: list[float], ys: list[float]) -> float:
    """Slope of the line below every point (``xs`` increasing) that lies highest at their mean x: the edge of the
    points' lower convex hull above the mean x (the linear-programming estimate of clock skew, Moon, Skelly &
    Towsley, IEEE INFOCOM 1999). A delay only adds to an observation, so points above the hull -- a stall, a
    backlog read at once, a congested link -- cannot tilt it, where a least-squares line through the bin minima
    followed them (a 1.5 s stall stamped samples up to 9.6 ms early, ``test_a_stalled_read_does_not_tilt_the_drift``)."""
    hull: list[tuple[float, float]] = []
    for p in zip(xs, ys, strict=True):
        while len(hull) >= 2 and ((hull[-1][0] - hull[-2][0]) * (p[1] - hull[-2][1])
                                  - (hull[-1][1] - hull[-2][1]) * (p[0] - hull[-2][0])) <= 0.0:
            hull.pop()  # hull[-1] is not below the chord from hull[-2] to p
        hull.append(p)
    mean_x = sum(xs) / len(xs)
    for (x0, y0), (x1, y1) in itertools.pairwise(hull):
        if x1 >= mean_x and x1 > x0:
            return (y1 - y0) / (x1 - x0)
    return 0.0


@dataclass
class _Bin:
    index: int
    board_s: float  # board time of the minimum
    offset_s: float  # minimum of steady_s - board_s in this bin


class ClockSync:
    """Map board timestamps (microseconds) onto host/ROS time (nanoseconds).

    Usage per received chunk: call ``observe(t_us, host_ns, steady_ns)`` for every frame of the chunk
    (with the host and steady clock times the chunk arrived), then ``stamp(t_us)`` for each frame in order.
    """

    def __init__(self, config: ClockSyncConfig | None = None) -> None:
        self.config = config or ClockSyncConfig()
        self._last_stamp_ns: int | None = None
        # Offsets are kept relative to an integer-ns base (steady - board at the first observation)
        # so float arithmetic stays at sub-ns precision even with epoch-sized host times.
        self._base_ns: int | None = None
        self._host_minus_steady_ns = 0  # of the latest observation
        self._host_reads: list[tuple[int, int]] = []  # (steady ns, host-minus-steady ns) of the last three reads
        self._agreed_host_ns = 0  # their median (the latest alone until there are three), worked out once a read
        self._applied_host_ns: int | None = None  # the host-minus-steady offset the stamps carry (ns, see ``stamp``)
        self.resets = 0
        self.steps = 0  # steps of the applied board-to-steady offset (errors above step_threshold_s: a clock jump)
        self.host_steps = 0  # steps of ROS time against the steady clock (above step_threshold_s) the stamps followed
        self.held_stamps = 0  # stamps the monotonic guard moved forward (ROS time went back, or a mapping step back)
        self._clear()

    def _clear(self) -> None:
        self._bins: list[_Bin] = []
        self._board_ref_s: float | None = None
        self._a = 0.0  # target offset at board_ref_s, s
        self._d = 0.0  # target drift, s/s
        self._applied: float | None = None  # applied offset, s
        self._applied_at_s: float | None = None  # board time the applied offset refers to
        self._started_s: float | None = None  # board time of the first observation since the (re)start
        self._last_obs_s: float | None = None
        self._started_steady_ns = 0  # steady time of that first observation
        self._last_steady_ns = 0

    # ------------------------------------------------------------------ inputs
    def reset(self) -> None:
        """Board reset: the board clock restarted, forget the estimate (stamps stay monotonic)."""
        self.resets += 1
        self._clear()

    def observe(self, t_us: int, host_ns: int, steady_ns: int | None = None) -> None:
        """One observation: a frame stamped ``t_us`` on the board had arrived by host time ``host_ns`` (ns),
        which a steady clock read at the same moment gave as ``steady_ns`` (ns; ``time.monotonic_ns``). Without
        ``steady_ns`` the host clock is taken as steady: a forward step of it then counts as a delay."""
        board_s = t_us * 1e-6
        steady = host_ns if steady_ns is None else steady_ns
        self._host_minus_steady_ns = host_ns - steady
        reads = self._host_reads
        if not reads or reads[-1][0] != steady:  # a new read (the frames of one chunk share theirs)
            reads.append((steady, host_ns - steady))
            if len(reads) > 3:
                del reads[0]
            self._agreed_host_ns = sorted(r[1] for r in reads)[1] if len(reads) == 3 else reads[-1][1]
        if self._base_ns is None:
            self._base_ns = steady - t_us * 1000
        offset = (steady - t_us * 1000 - self._base_ns) * 1e-9
        if self._bins and offset - self.target_offset_s(board_s) < -self.config.step_threshold_s:
            self._restart()  # far below the lower envelope: no delay does that (module docstring)
        if self._board_ref_s is None:
            self._board_ref_s = board_s
            self._started_s = board_s
            self._started_steady_ns = steady
        self._last_obs_s = board_s
        self._last_steady_ns = steady
        index = int((board_s - self._board_ref_s) // self.config.bin_s)
        bins = self._bins
        if bins and bins[-1].index == index:
            if offset < bins[-1].offset_s:
                bins[-1].board_s, bins[-1].offset_s = board_s, offset
                # a lower minimum in the open bin: the line (slope kept until the bin closes) goes below it. O(1): a
                # burst's frames lower the minimum one after another, and a hull of window_bins points per frame
                # would cost tens of % of a core at 1 kHz
                self._a = min(self._a, offset - self._d * (board_s - (self._board_ref_s or 0.0)))
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
        d = 0.0
        if len(bins) >= 3:
            d = lower_envelope_slope([b.board_s - ref for b in bins], [b.offset_s for b in bins])
            d = max(-self.config.max_drift, min(self.config.max_drift, d))
        # the line of slope d through the lowest point: below every observation
        self._a, self._d = min(b.offset_s - d * (b.board_s - ref) for b in bins), d

    def _restart(self) -> None:
        """Forget the bins after a clock jump; the next stamp() steps to the new estimate."""
        self._bins.clear()
        self._board_ref_s = None

    # ------------------------------------------------------------------ outputs
    def target_offset_s(self, board_s: float) -> float:
        """Current estimate of steady - board offset at ``board_s`` (s, relative to the internal base)."""
        return self._a + self._d * (board_s - (self._board_ref_s or 0.0))

    @property
    def drift(self) -> float:
        """Estimated relative drift of the host's steady clock against the board clock (s/s)."""
        return self._d

    def status(self) -> dict[str, float | int | bool]:
        """For the diagnostics: the board clock's rate against the host's steady clock from the drift estimate (ppm,
        + when the board's runs fast: ``-drift``), whether the estimate sits at the ``max_drift`` clamp (the link or the
        board clock is not what the estimator assumes), the restarts (board resets, clock jumps), the steps of ROS
        time against the steady clock the stamps followed, the steps of the board-to-steady mapping (errors above
        ``step_threshold_s``: a board clock that jumped, a host clock without a steady one that stepped back) and the
        stamps held 1 ns after the previous one because they would have gone back (cumulative counts)."""
        return {"board_clock_ppm": round(-self._d * 1e6, 2), "drift_at_limit": abs(self._d) >= self.config.max_drift,
                "restarts": self.resets, "ros_time_steps": self.host_steps, "mapping_steps": self.steps,
                "held_stamps": self.held_stamps}

    @property
    def primed(self) -> bool:
        """True once ``prime_s`` of board time was observed since the (re)start, or observations kept arriving
        for ``prime_s`` (steady clock) without that: a board clock that crawls (a sample counter sent as microseconds)
        would otherwise prime only after thousands of frames, all held by a caller waiting for it.

        A caller that can wait (the driver core does) holds the first frames until then, so the
        first stamps already come from a minimum over many delays instead of from one delay that
        might be a start-up stall; otherwise a large first error would have to be stepped back
        later, which breaks the stamp spacing.
        """
        if self._started_s is None or self._last_obs_s is None:
            return False
        prime_s = self.config.prime_s
        return (self._last_obs_s - self._started_s >= prime_s
                or (self._last_steady_ns - self._started_steady_ns) * 1e-9 >= prime_s)

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
        prev_at = self._applied_at_s
        self._applied, self._applied_at_s = applied, board_s
        # the host-minus-steady offset: a step of the host clock (NTP) beyond step_threshold_s is taken at once; a
        # change that two of the last three reads agree on (a fast NTP slew, a smaller step) at once to within
        # host_offset_band_s; within the band (the two clocks' read jitter) at most at max_slew, so read jitter
        # never reaches the stamps' spacing
        target_ns = self._host_minus_steady_ns
        if self._applied_host_ns is None or abs(target_ns - self._applied_host_ns) > cfg.step_threshold_s * 1e9:
            if self._applied_host_ns is not None:
                self.host_steps += 1  # a step of ROS time, followed
            self._applied_host_ns = target_ns
        else:
            band = cfg.host_offset_band_s * 1e9
            beyond = self._agreed_host_ns - self._applied_host_ns
            if abs(beyond) > band:
                self._applied_host_ns += round(beyond - math.copysign(band, beyond))
            limit = cfg.max_slew * max(board_s - (prev_at if prev_at is not None else board_s), 0.0) * 1e9
            self._applied_host_ns += round(max(-limit, min(limit, target_ns - self._applied_host_ns)))
        stamp_ns = t_us * 1000 + (self._base_ns or 0) + round(applied * 1e9) + self._applied_host_ns
        if self._last_stamp_ns is not None and stamp_ns <= self._last_stamp_ns:
            stamp_ns = self._last_stamp_ns + 1
            self.held_stamps += 1
        self._last_stamp_ns = stamp_ns
        return stamp_ns
