"""Unit tests of the board-clock -> ROS-time estimator (pure, deterministic, no timing)."""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_driver.clock_sync import ClockSync, ClockSyncConfig

RATE_HZ = 100.0
OFFSET_S = 1_700_000_000.25  # host epoch time at board time 0


def run(
    n: int,
    *,
    drift: float = 0.0,
    delay_mean_s: float = 2e-3,
    seed: int = 0,
    chunk: int = 1,
    outlier_every: int = 0,
    sync: ClockSync | None = None,
    board_start_s: float = 0.0,
    offset_s: float = OFFSET_S,
    steady: bool = False,
    extra_delay_s: np.ndarray | None = None,
) -> tuple[ClockSync, np.ndarray, np.ndarray]:
    """Simulate ``n`` frames at 100 Hz; returns (sync, stamps in ns, true host time of sampling in s). ``steady``:
    pass a steady clock that does not see the host clock's step from ``OFFSET_S`` to ``offset_s``;
    ``extra_delay_s`` (n,): delay added to each frame (frames stay in order)."""
    rng = np.random.default_rng(seed)
    sync = sync or ClockSync()
    board = board_start_s + np.arange(n) / RATE_HZ
    true_host = offset_s + board * (1.0 + drift)
    delays = 150e-6 + rng.exponential(delay_mean_s, n)
    if outlier_every:
        delays[::outlier_every] += 0.2  # a 200 ms scheduler stall now and then
    arrive = true_host + delays
    if extra_delay_s is not None:
        arrive = np.maximum.accumulate(arrive + extra_delay_s)  # a FIFO link
    step_ns = round((offset_s - OFFSET_S) * 1e9)
    stamps = np.empty(n, dtype=np.int64)
    for start in range(0, n, chunk):
        idx = range(start, min(n, start + chunk))
        host_ns = round(max(arrive[i] for i in idx) * 1e9)  # the chunk arrives with its last frame
        for i in idx:
            sync.observe(round(board[i] * 1e6), host_ns, host_ns - step_ns if steady else None)
        for i in idx:
            stamps[i] = sync.stamp(round(board[i] * 1e6))
    return sync, stamps, true_host


def errors_s(stamps_ns: np.ndarray, true_host_s: np.ndarray) -> np.ndarray:
    """Stamp minus true sampling time, s (computed relative to OFFSET_S to keep float precision)."""
    return (stamps_ns - int(OFFSET_S * 1e9)) * 1e-9 - (true_host_s - OFFSET_S)


def test_primed_after_prime_s_of_board_time() -> None:
    sync = ClockSync()
    for i in range(20):  # frames 0..19 span 0.19 s of board time (prime_s = 0.2 s)
        sync.observe(i * 10_000, 1_000_000_000 + i * 10_000_000)
        assert not sync.primed
    sync.observe(210_000, 1_210_000_000)
    assert sync.primed
    sync.reset()
    assert not sync.primed


def test_constant_offset_converges_below_jitter() -> None:
    _, stamps, true_host = run(3000)
    err = errors_s(stamps, true_host)
    settled = err[500:]  # after 5 s
    # The minimum-delay estimator lands near the fixed part of the delay (150 us), far below the 2 ms mean jitter.
    assert np.all(np.abs(settled) < 0.6e-3), np.abs(settled).max()
    assert abs(np.median(settled) - 150e-6) < 0.2e-3


def test_stamps_strictly_increasing_and_spacing_within_slew() -> None:
    sync, stamps, _ = run(3000, chunk=7)
    d = np.diff(stamps) * 1e-9
    assert np.all(d > 0)
    nominal = 1.0 / RATE_HZ
    cfg = sync.config
    # Spacing follows the board clock; only slew and drift estimate may change it, never the 2 ms jitter.
    warm = int(cfg.warmup_s * RATE_HZ)
    bound_warm = nominal * (cfg.warmup_slew + cfg.max_drift) + 2e-9
    bound = nominal * (cfg.max_slew + cfg.max_drift) + 2e-9
    assert np.all(np.abs(d[:warm] - nominal) < bound_warm), np.abs(d[:warm] - nominal).max()
    assert np.all(np.abs(d[warm:] - nominal) < bound), np.abs(d[warm:] - nominal).max()
    assert bound_warm < 0.01 * nominal  # the 1 % promised in docs/topics.md


@pytest.mark.parametrize("drift", [120e-6, -80e-6])
def test_drift_is_estimated(drift: float) -> None:
    sync, stamps, true_host = run(6000, drift=drift)
    assert abs(sync.drift - drift) < 15e-6
    err = errors_s(stamps, true_host)
    assert np.all(np.abs(err[3000:]) < 1e-3), np.abs(err[3000:]).max()


def test_backlog_chunk_is_not_stamped_at_arrival_time() -> None:
    # 300 frames (3 s) sat in a buffer and arrive in one chunk; then real-time frames follow.
    rng = np.random.default_rng(1)
    sync = ClockSync()
    board = np.arange(600) / RATE_HZ
    true_host = OFFSET_S + board
    arrive = true_host + 150e-6 + rng.exponential(1e-3, 600)
    arrive[:300] = arrive[299]
    stamps = []
    backlog_ns = round(arrive[299] * 1e9)
    for i in range(300):
        sync.observe(round(board[i] * 1e6), backlog_ns)
    stamps += [sync.stamp(round(board[i] * 1e6)) for i in range(300)]
    for i in range(300, 600):
        host_ns = round(arrive[i] * 1e9)
        sync.observe(round(board[i] * 1e6), host_ns)
        stamps.append(sync.stamp(round(board[i] * 1e6)))
    err = errors_s(np.asarray(stamps), true_host)
    assert np.all(np.abs(err) < 5e-3), np.abs(err).max()  # not 3 s of error for the oldest frames


def test_outliers_do_not_move_the_estimate() -> None:
    _, stamps, true_host = run(3000, outlier_every=97)
    err = errors_s(stamps, true_host)
    assert np.all(np.abs(err[500:]) < 0.6e-3)


def test_board_reset_reinitialises_and_keeps_stamps_monotonic() -> None:
    sync, s1, _ = run(1000)
    sync.reset()
    # Board rebooted: its clock restarts at 0.5 s, the host clock moved on by 10.5 s.
    sync, s2, true2 = run(1000, sync=sync, seed=2, board_start_s=0.5, offset_s=OFFSET_S + 10.0)
    assert sync.resets == 1
    assert s2[0] > s1[-1]
    assert np.all(np.diff(s2) > 0)
    assert np.all(np.abs(errors_s(s2[200:], true2[200:])) < 0.6e-3)


def test_host_clock_step_moves_the_stamps_at_once() -> None:
    sync, s1, _ = run(1000, steady=True)
    steps = sync.steps
    # Host clock jumps forward by 2 s (e.g. an NTP correction) while the board and the steady clock keep counting:
    # the stamps follow from the first frame on, and the estimate (on the steady clock) does not restart.
    sync, s2, true2 = run(500, sync=sync, board_start_s=10.0, offset_s=OFFSET_S + 2.0, seed=3, steady=True)
    assert sync.steps == steps
    assert np.all(np.abs(errors_s(s2, true2)) < 1e-3)
    assert np.all(np.diff(np.concatenate([s1, s2])) > 0)
    # back by 1 s: the monotonic guard holds the stamps for ~1 s, then they follow the host time
    sync, s3, true3 = run(500, sync=sync, board_start_s=15.0, offset_s=OFFSET_S + 1.0, seed=5, steady=True)
    assert np.all(np.diff(np.concatenate([s2, s3])) > 0)
    assert np.all(np.abs(errors_s(s3[110:], true3[110:])) < 1e-3)


@pytest.mark.parametrize("extra_s", [0.1, 0.3, 1.0])
def test_a_congested_link_delays_the_bytes_not_the_stamps(extra_s: float) -> None:
    """The transport delay rises by ``extra_s`` for 5 s (a congested link, a busy host), frames in order. A delay
    cannot be told from a forward step of the host clock by the observations alone; with the steady clock the
    estimate never has to guess, so the stamps stay on the lower envelope. Before: taken for a host clock jump
    after 2 s, stamps up to 0.104 / 0.302 / 1.000 s late."""
    n = 7000
    t = np.arange(n) / RATE_HZ
    extra = extra_s * np.clip(np.minimum(t - 30.0, 36.0 - t), 0.0, 1.0)  # 1 s ramps, 4 s above half
    _, stamps, true_host = run(n, extra_delay_s=extra, steady=True)
    err = errors_s(stamps, true_host)
    assert np.all(np.abs(err[1000:]) < 1e-3), np.abs(err[1000:]).max()


@pytest.mark.parametrize("stall_s", [0.5, 1.5])
def test_a_stalled_read_does_not_tilt_the_drift(stall_s: float) -> None:
    """The host stops reading for ``stall_s``, then reads the backlog at once: the late observations lie above the
    lower envelope and must not tilt it. Before: a least-squares line through the bin minima followed them and
    stamped samples up to 2.2 / 9.6 ms before they were taken."""
    n = 6000
    t = np.arange(n) / RATE_HZ
    stalled = (t >= 30.0) & (t < 30.0 + stall_s)
    extra = np.where(stalled, 30.0 + stall_s - t, 0.0)  # every frame of the stall arrives at its end
    sync, stamps, true_host = run(n, drift=20e-6, extra_delay_s=extra, steady=True)
    err = errors_s(stamps, true_host)
    assert np.all(err[1000:] > -0.1e-3), err[1000:].min()  # never before the sample was taken
    assert np.all(err[1000:] < 1e-3), err[1000:].max()
    assert abs(sync.drift - 20e-6) < 5e-6


def test_host_clock_step_back_restarts_at_once() -> None:
    """Without a steady clock, a host clock that steps back is seen at once (no delay is negative)."""
    sync, s1, _ = run(1000)
    sync, s2, true2 = run(500, sync=sync, board_start_s=10.0, offset_s=OFFSET_S - 1.0, seed=4)
    assert sync.steps >= 1
    assert np.all(np.diff(np.concatenate([s1, s2])) > 0)  # the monotonic guard holds stamps for ~1 s ...
    assert np.all(np.abs(errors_s(s2[200:], true2[200:])) < 1e-3)  # ... then they follow the new host time


def test_config_limits_drift() -> None:
    sync, _, _ = run(3000, drift=5e-3, sync=ClockSync(ClockSyncConfig(max_drift=1e-4)))
    assert abs(sync.drift) <= 1e-4 + 1e-12


def test_jitter_between_the_host_and_the_steady_read_stays_out_of_the_stamp_spacing() -> None:
    """The host and steady clocks are read one after the other; a thread switch between the reads makes their
    difference jitter by up to a millisecond. Passed straight into the stamps that broke the board spacing by
    1.5 % (a process test under load); the offset now moves at most at the slew rate below a clock step."""
    rng = np.random.default_rng(9)
    sync = ClockSync()
    n = 3000
    board = np.arange(n) / RATE_HZ
    true_host = OFFSET_S + board
    arrive = true_host + 150e-6 + rng.exponential(2e-3, n)
    stamps = np.empty(n, dtype=np.int64)
    for i in range(n):
        host_ns = round(arrive[i] * 1e9)
        steady_ns = host_ns - 10**12 - int(rng.uniform(0.0, 1e6))  # 1000 s apart, read up to 1 ms apart
        sync.observe(round(board[i] * 1e6), host_ns, steady_ns)
        stamps[i] = sync.stamp(round(board[i] * 1e6))
    spacing = np.diff(stamps[500:]) * 1e-9
    assert np.all(np.abs(spacing - 1 / RATE_HZ) < 0.002 / RATE_HZ), (spacing.min(), spacing.max())
    assert np.all(np.abs(errors_s(stamps[500:], true_host[500:])) < 1.5e-3)


def bursty_link(n: int, link: str, ppm: float, seed: int, sync: ClockSync) -> tuple[np.ndarray, np.ndarray, float]:
    """``n`` frames at 100 Hz from a board clock ``ppm`` fast, delivered as a USB-serial adapter or a Bluetooth SPP
    link delivers them. ``usb``: the adapter flushes its buffer at a free-running 16 ms latency timer (FTDI default),
    1 ms floor, 0.3 ms mean exponential host wake-up jitter. ``bt``: deliveries at random 20-60 ms intervals (radio
    scheduling), each with everything sent before it, 15 ms floor, a 1 s retransmission stall every 30 s on average,
    2 ms mean jitter. Returns (stamp minus (true sampling time + floor), s; drift estimate after each frame; true
    drift of the host against the board clock)."""
    rng = np.random.default_rng(seed)
    board = np.arange(n) / RATE_HZ
    true = board / (1.0 + ppm * 1e-6)
    if link == "usb":
        floor, jitter_s = 1e-3, 0.3e-3
        arrive = np.ceil(true / 16e-3) * 16e-3 + floor
    else:
        floor, jitter_s = 15e-3, 2e-3
        events = np.cumsum(rng.uniform(20e-3, 60e-3, int(true[-1] / 20e-3) + 10))
        arrive = events[np.searchsorted(events, true)] + floor
        for start in rng.uniform(0.0, true[-1], int(true[-1] / 30.0)):
            stalled = (arrive >= start) & (arrive < start + 1.0)
            arrive[stalled] = start + 1.0
    arrive = np.maximum.accumulate(arrive + rng.exponential(jitter_s, n))  # a FIFO link
    stamps = np.empty(n, dtype=np.int64)
    drift = np.empty(n)
    t_us = np.round(board * 1e6).astype(np.int64).tolist()
    for chunk in np.split(np.arange(n), np.flatnonzero(np.diff(arrive) > 0) + 1):
        host_ns = round((OFFSET_S + arrive[chunk[-1]]) * 1e9)
        for i in chunk.tolist():
            sync.observe(t_us[i], host_ns)
        for i in chunk.tolist():
            stamps[i] = sync.stamp(t_us[i])
            drift[i] = sync.drift
    err = (stamps - int(OFFSET_S * 1e9)) * 1e-9 - true - floor
    return err, drift, -ppm * 1e-6 / (1.0 + ppm * 1e-6)


@pytest.mark.parametrize("ppm", [150.0, -150.0])
@pytest.mark.parametrize("link", ["usb", "bt"])
def test_bursty_usb_and_bluetooth_delivery_keep_the_drift_and_the_stamps(link: str, ppm: float) -> None:
    """Ten minutes through a USB-serial latency timer or a bursty Bluetooth link (``bursty_link``): after the first
    minute the drift estimate stays within 30 ppm of the truth and no stamp comes before the transport delay floor
    (which is what a minimum-delay estimator can reach), nor more than 2.5 ms after it. Before (a 20 s window: the
    lower-hull edge at the window's middle was often two bins 0.5-1 s apart, its slope the ms jitter of their minima
    over that second): drift off by up to 157 / 153 / 200 / 206 ppm (usb +150 / usb -150 / bt +150 / bt -150), stamps
    from 0.64 / 1.46 / 1.30 / 1.31 ms before the floor to 2.06 / 0.58 / 3.29 / 3.09 ms after it; with the
    driver's simulator over 3 h the estimate swung over the whole +-500 ppm clamp on the Bluetooth link."""
    n = 60_000
    err, drift, true_drift = bursty_link(n, link, ppm, seed=1, sync=ClockSync())
    settled = slice(int(60 * RATE_HZ), None)
    assert np.abs(drift[settled] - true_drift).max() < 30e-6, np.abs(drift[settled] - true_drift).max()
    assert err[settled].min() > -0.3e-3, err[settled].min()
    assert err[settled].max() < 2.5e-3, err[settled].max()


def test_the_status_states_the_drift_and_whether_it_sits_at_its_clamp() -> None:
    """``ClockSync.status`` (the driver's ``clock mapping`` diagnostic): the board clock's rate in ppm, the restarts and
    steps of ROS time; at the ``max_drift`` clamp the estimate is not tracking (a board clock beyond the clamp here)."""
    sync, _, _ = run(6000, drift=120e-6)
    st = sync.status()
    assert abs(st["board_clock_ppm"] + 120.0) < 15.0 and not st["drift_at_limit"]  # the host runs 120 ppm fast
    assert (st["restarts"], st["ros_time_steps"]) == (0, 0)
    sync.reset()
    assert sync.status()["restarts"] == 1
    clamped, _, _ = run(6000, drift=120e-6, sync=ClockSync(ClockSyncConfig(max_drift=50e-6)))
    assert clamped.status()["drift_at_limit"] and clamped.status()["board_clock_ppm"] == -50.0


def test_the_status_counts_every_restart_and_mapping_step_and_gives_the_rate_to_a_hundredth_of_a_ppm() -> None:
    """The counters of ``clock mapping`` count every event, not only the first: two board restarts are 2, two steps
    back of a host clock without a steady clock (each taken at once as a step of the mapping) are 2, and with one two
    steps of ROS time; and the board clock's rate is given to 0.01 ppm (-19.99 for an estimate of -19.985..., not
    -20 nor -19.985)."""
    sync, _, _ = run(6000, drift=20e-6)
    ppm = sync.status()["board_clock_ppm"]
    assert ppm == round(-sync.drift * 1e6, 2) and ppm != round(ppm) and ppm != round(-sync.drift * 1e6, 3)
    sync.reset()
    sync.reset()
    assert sync.status()["restarts"] == 2
    sync, _, _ = run(1000)
    for k in (1, 2):
        sync, _, _ = run(500, sync=sync, board_start_s=10.0 * k, offset_s=OFFSET_S - k, seed=3 + k)
        assert sync.status()["mapping_steps"] == k
    sync, _, _ = run(1000, steady=True)  # with a steady clock the same steps are steps of ROS time
    for k in (1, 2):
        sync, _, _ = run(500, sync=sync, board_start_s=10.0 * k, offset_s=OFFSET_S - k, seed=3 + k, steady=True)
        assert sync.status()["ros_time_steps"] == k


def test_ros_time_slewed_within_the_read_jitter_band_is_followed_at_the_slew_rate() -> None:
    """ntpd slews ROS time by 1.5 ms at 50 ppm (within the 2 ms band kept for the read jitter of the host and steady
    clocks): the applied host-minus-steady offset follows it at up to max_slew, so the stamps stay within 0.5 ms of ROS
    time (measured: 0.16 ms). An offset that never moved inside the band would leave them 1.35 ms behind at the end."""
    n = 6000
    rng = np.random.default_rng(1)
    t = np.arange(n) / RATE_HZ
    slew = 1.5e-3 * np.clip((t - 20.0) / 30.0, 0.0, 1.0)  # ROS minus steady, s, against true time
    steady = OFFSET_S + t + 150e-6 + rng.exponential(2e-3, n)
    sync = ClockSync()
    stamps = np.empty(n, dtype=np.int64)
    for i in range(n):
        steady_ns = round(steady[i] * 1e9)
        sync.observe(round(t[i] * 1e6), steady_ns + round(float(np.interp(steady[i] - OFFSET_S, t, slew)) * 1e9),
                     steady_ns)
        stamps[i] = sync.stamp(round(t[i] * 1e6))
    err = errors_s(stamps, OFFSET_S + t + slew)
    assert np.abs(err[1000:]).max() < 0.5e-3, np.abs(err[1000:]).max()

@pytest.mark.parametrize("size_s", [0.01, -0.01])
def test_a_small_step_of_ros_time_is_reached_from_the_side_the_stamps_were_on(size_s: float) -> None:
    """ROS time steps by 10 ms (below the 50 ms step threshold, beyond the 2 ms read-jitter band) with a steady clock
    beside it: the applied offset jumps to within the band short of the new ROS time, then slews the rest, so the
    stamps approach it from the side they were on and never pass it by more than the transport floor (measured:
    -1.80..+0.16 ms after a step forward, +0.15..+2.10 ms after a step back). An offset that overshot by the band
    would put them 2 ms past it on the other side."""
    n = 6000
    rng = np.random.default_rng(2)
    t = np.arange(n) / RATE_HZ
    steady = OFFSET_S + t + 150e-6 + rng.exponential(2e-3, n)
    sync = ClockSync()
    stamps = np.empty(n, dtype=np.int64)
    for i in range(n):
        steady_ns = round(steady[i] * 1e9)
        sync.observe(round(t[i] * 1e6), steady_ns + (round(size_s * 1e9) if steady[i] - OFFSET_S >= 30.0 else 0),
                     steady_ns)
        stamps[i] = sync.stamp(round(t[i] * 1e6))
    err = errors_s(stamps, OFFSET_S + t + np.where(t >= 30.0, size_s, 0.0))[t >= 30.1]
    assert np.abs(err).max() < 2.5e-3, np.abs(err).max()
    if size_s > 0:
        assert err.max() < 0.5e-3, err.max()
    else:
        assert err.min() > -0.5e-3, err.min()

def test_stamps_held_back_by_a_step_back_of_ros_time_are_1_ns_apart_and_counted() -> None:
    """ROS time steps back by 0.5 s (steady clock beside it): stamps never go back, so the next half second of samples
    is held 1 ns after the last stamp published, each 1 ns after the one before, and ``held_stamps`` counts every one
    of them; the others keep the board's 10 ms spacing."""
    sync, s1, _ = run(1000, steady=True)
    sync, s2, _ = run(500, sync=sync, board_start_s=10.0, offset_s=OFFSET_S - 0.5, seed=3, steady=True)
    spacing = np.diff(np.concatenate([s1, s2]))
    held = int(np.sum(spacing == 1))
    assert 40 <= held <= 60 and np.all((spacing == 1) | (spacing > 5_000_000)), held
    assert sync.status()["held_stamps"] == held

@pytest.mark.parametrize("drift", [-400e-6, 400e-6])
def test_a_link_of_constant_delay_is_stamped_at_its_floor_once_the_drift_is_known(drift: float) -> None:
    """Every frame arrives exactly 150 us after it was taken, from a board whose clock starts at 0 (a board just
    powered up) and runs 400 ppm slow or fast: the lower envelope is exact, so from 1.5 s on (three 0.5 s bins) every
    stamp is the true time plus that 150 us (measured: within 0.3 us). Board time 0 is a valid reference: a reference
    taken as 1 s when it is 0 puts the line 400 us off."""
    _, stamps, true_host = run(1000, drift=drift, delay_mean_s=0.0)
    err = errors_s(stamps, true_host)[150:] - 150e-6
    assert np.abs(err).max() < 20e-6, np.abs(err).max()


def test_a_thread_switch_on_the_first_read_lets_no_later_single_one_through() -> None:
    """The host-minus-steady offset is read 3 ms off at the very first read and then at one read in a hundred (a
    thread switch between the two clock reads): a single read off is never two of the last three, so after the
    first one is slewed out the stamps stay at the transport floor (measured: 0.14..0.16 ms from 10 s on). A window
    of reads that kept the first one would take each later single one as agreed and step the stamps by 1 ms."""
    n = 3000
    rng = np.random.default_rng(4)
    t = np.arange(n) / RATE_HZ
    steady = OFFSET_S + t + 150e-6 + rng.exponential(2e-3, n)
    off = np.zeros(n, dtype=np.int64)
    off[0] = off[100::100] = 3_000_000
    sync = ClockSync()
    stamps = np.empty(n, dtype=np.int64)
    for i in range(n):
        steady_ns = round(steady[i] * 1e9)
        sync.observe(round(t[i] * 1e6), steady_ns + int(off[i]), steady_ns)
        stamps[i] = sync.stamp(round(t[i] * 1e6))
    err = errors_s(stamps, OFFSET_S + t)[1000:]
    assert err.min() > 0.0 and err.max() < 0.5e-3, (err.min(), err.max())

def test_a_change_of_the_crystal_rate_leaves_the_window_with_its_bins() -> None:
    """The board's crystal runs 100 ppm fast, then 140 ppm from 300 s on (a board warming up), read at 10 Hz: once the
    200 s window holds only bins after the change, the drift estimate is the new rate and the stamps are back at the
    floor (measured: 139.95 ppm, within 7 us from 550 s). A window that kept its first bin for ever would stay
    anchored to the old rate: 126.8 ppm and stamps 0.19 ms late."""
    rate_hz = 10.0
    n = int(900 * rate_hz)
    t = np.arange(n) / rate_hz
    ppm = np.where(t < 300.0, 100.0, 140.0)
    board = np.concatenate([[0.0], np.cumsum((1.0 + ppm[:-1] * 1e-6) / rate_hz)])
    arrive = np.maximum.accumulate(OFFSET_S + t + 150e-6 + np.random.default_rng(2).exponential(2e-3, n))
    sync = ClockSync()
    t_us = np.round(board * 1e6).astype(np.int64).tolist()
    stamps = np.empty(n, dtype=np.int64)
    for i in range(n):
        host_ns = round(arrive[i] * 1e9)
        sync.observe(t_us[i], host_ns, host_ns)
        stamps[i] = sync.stamp(t_us[i])
    err = errors_s(stamps, OFFSET_S + t)[t >= 550.0] - 150e-6
    assert np.abs(err).max() < 50e-6, np.abs(err).max()
    assert abs(sync.status()["board_clock_ppm"] - 140.0) < 3.0, sync.status()

# -100 ppm: bench/seed_sweeps.py (the sign of the crystal's offset moves neither statistic: ramp 13.68 / 13.66 ppm,
# cycle -0.324 / -0.325 ms at +100 / -100 ppm; the offset's sign is tested by the drift tests above)
@pytest.mark.parametrize("base_ppm", [100.0, pytest.param(-100.0, marks=pytest.mark.sweep)])
def test_a_board_crystal_drifting_with_temperature_keeps_the_stamps(base_ppm: float) -> None:
    """The board's crystal is ``base_ppm`` off and its rate moves with temperature: +40 ppm over 5 min (a board
    warming up; an AT-cut crystal moves by tens of ppm over its range), or +-10 ppm in a 20-min cycle. The 200 s
    window's line lags the rate by about half the window, so the stamps may not keep the floor exactly: after the
    first minute they stay within 0.4 ms of it (measured -0.31..+0.06 ms) and the rate estimate within 15 ppm of the
    truth (13.6 ppm in the ramp, 5.5 in the cycle). Measured when written, no defect found."""
    n = 180_000
    t = np.arange(n) / RATE_HZ  # true time, s
    for ppm in (base_ppm + 40.0 * np.clip((t - 300.0) / 300.0, 0.0, 1.0), base_ppm + 10.0 * np.sin(2 * np.pi * t / 1200.0)):
        board = np.concatenate([[0.0], np.cumsum((1.0 + ppm[:-1] * 1e-6) / RATE_HZ)])  # board clock: rate integrated
        arrive = np.maximum.accumulate(OFFSET_S + t + 150e-6 + np.random.default_rng(2).exponential(2e-3, n))
        sync = ClockSync()
        t_us = np.round(board * 1e6).astype(np.int64).tolist()
        stamps = np.empty(n, dtype=np.int64)
        rate_err = np.empty(n)
        for i in range(n):
            host_ns = round(arrive[i] * 1e9)
            sync.observe(t_us[i], host_ns, host_ns)
            stamps[i] = sync.stamp(t_us[i])
            rate_err[i] = -sync.drift / (1.0 - sync.drift) * 1e6 - ppm[i]  # board rate against the steady clock, ppm
        err = errors_s(stamps, OFFSET_S + t) - 150e-6
        settled = slice(int(60 * RATE_HZ), None)
        assert np.abs(err[settled]).max() < 0.4e-3, (err[settled].min(), err[settled].max())
        assert np.abs(rate_err[settled]).max() < 15.0, np.abs(rate_err[settled]).max()
        assert np.all(np.diff(stamps) > 0)


def test_a_board_booted_an_hour_before_the_driver_with_a_drifting_crystal_and_after_its_reset() -> None:
    """The mapping's line is anchored at the first board time it sees, not at board time 0: a board that booted
    1 h before the driver (t_us starts at 3.6e9) with a 20 ppm crystal is stamped as well as one that booted with it,
    and so is the same board after a reset restarts its clock at 0.5 s. Every other drift test starts the board at 0,
    where an anchor mixed up with 0 (``board_s + ref`` for ``board_s - ref``) goes unnoticed; here it is 144 ms off."""
    drift = 20e-6
    sync, stamps, true_host = run(6000, drift=drift, board_start_s=3600.0)
    err = errors_s(stamps, true_host)
    assert abs(sync.drift - drift) < 15e-6
    assert np.all(np.abs(err[3000:]) < 1.5e-3), np.abs(err[3000:]).max()  # a wrong anchor: > 0.1 s
    sync.reset()
    sync, stamps2, true2 = run(6000, drift=drift, sync=sync, seed=3, board_start_s=0.5,
                               offset_s=OFFSET_S + 3700.0)
    assert stamps2[0] > stamps[-1] and np.all(np.diff(stamps2) > 0)
    err2 = errors_s(stamps2, true2)
    assert np.all(np.abs(err2[3000:]) < 1.5e-3), np.abs(err2[3000:]).max()


def test_the_status_names_every_figure_the_diagnostics_publish() -> None:
    sync, _, _ = run(300)
    assert set(sync.status()) == {"board_clock_ppm", "drift_at_limit", "restarts", "ros_time_steps", "mapping_steps",
                                  "held_stamps"}


def test_each_step_is_counted_once() -> None:
    """``steps`` and ``host_steps`` count events (the diagnostics publish them): none on a steady run, one for one
    forward step of the host clock (2 s), one for one board clock jump ahead (5 s, no reboot)."""
    sync, _, _ = run(1000, steady=True)
    assert (sync.steps, sync.host_steps) == (0, 0)
    sync, _, _ = run(500, sync=sync, board_start_s=10.0, offset_s=OFFSET_S + 2.0, seed=3, steady=True)
    assert (sync.steps, sync.host_steps) == (0, 1)
    jumped, _, _ = run(1000)
    jumped, _, _ = run(500, sync=jumped, board_start_s=15.0, offset_s=OFFSET_S - 5.0, seed=4)  # board 10 s -> 15 s
    assert (jumped.steps, jumped.host_steps) == (1, 0)


def test_one_read_s_host_offset_alone_does_not_move_the_stamps_whatever_the_chunk() -> None:
    """The host-minus-steady offset follows a change two of the last three READS agree on; the frames of one chunk
    share one read and count once. One read 10 ms off (a thread switch between the two clock reads, inside the step
    threshold) in chunks of 5 frames: counted per frame, that read would make the three last "reads" and the stamps
    would jump by 8 ms."""
    sync = ClockSync()
    rng = np.random.default_rng(7)
    stamps, truth = [], []
    for k in range(400):  # chunks of 5 frames at 100 Hz
        board = np.arange(5 * k, 5 * k + 5) / RATE_HZ
        steady_ns = round((100.0 + board[-1] + 150e-6 + rng.exponential(1e-3)) * 1e9)
        host_ns = steady_ns + round(OFFSET_S * 1e9) + (10_000_000 if k == 300 else 0)
        for b in board:
            sync.observe(round(b * 1e6), host_ns, steady_ns)
        for b in board:
            stamps.append(sync.stamp(round(b * 1e6)))
            truth.append(OFFSET_S + 100.0 + b)
    err = errors_s(np.asarray(stamps), np.asarray(truth))
    assert np.all(np.abs(err[1000:]) < 2.5e-3), np.abs(err[1000:]).max()


def test_the_lower_envelope_drops_a_point_above_the_chord_of_its_neighbours() -> None:
    from fbg_accel_driver.clock_sync import lower_envelope_slope

    assert lower_envelope_slope([0.0, 1.0, 2.0], [0.0, 5.0, 0.0]) == 0.0  # the middle point lies above: not the hull
    assert lower_envelope_slope([0.0, 1.0, 2.0], [0.0, -1.0, 0.0]) == -1.0  # below: the edge that reaches the mean x


def test_before_any_observation_the_estimate_is_no_drift() -> None:
    sync = ClockSync()
    assert sync.drift == 0.0 and sync.status()["board_clock_ppm"] == 0.0
    run(300, sync=sync)
    sync.reset()
    assert sync.drift == 0.0 and sync.status()["board_clock_ppm"] == 0.0


def test_a_small_host_offset_change_adds_to_the_offset_already_followed() -> None:
    """ROS time 1 s ahead of the steady clock from the start (followed at once), then 10 ms more (an NTP step below
    the step threshold): the stamps follow the 10 ms on top of the 1 s, to within the read band, without a step."""
    sync, _, _ = run(1000, steady=True, offset_s=OFFSET_S + 1.0)
    sync, stamps, truth = run(1000, sync=sync, board_start_s=10.0, offset_s=OFFSET_S + 1.01, seed=3, steady=True)
    err = errors_s(stamps[1:], truth[1:])  # the first read of the new offset alone is not followed (no agreement yet)
    assert np.all(np.abs(err) < 3e-3), np.abs(err).max()
    assert sync.host_steps == 0  # followed within the band, not stepped


@pytest.mark.parametrize("change_ns, stepped", [(50_000_000, False), (50_000_001, True)])
def test_a_change_of_ros_time_is_a_step_only_beyond_the_threshold(change_ns: int, stepped: bool) -> None:
    """ROS time (the host clock) moving against the steady clock by exactly ``step_threshold_s`` (50 ms, integer ns
    both) is no step: it is followed once three reads agree and is not counted; one nanosecond more is a step, taken
    at once and counted in ``ros_time_steps`` ("beyond the threshold", docs/topics.md)."""
    sync = ClockSync()
    t0_ns = 1_700_000_000_250_000_000
    for k in range(200):  # 2 s of frames at 100 Hz, a read per frame, ROS time = steady + t0
        t_us = 10_000 * k
        steady = 1_000_000 + 1000 * t_us + 2_000_000
        host = t0_ns + steady + (change_ns if k >= 100 else 0)
        sync.observe(t_us, host, steady)
        sync.stamp(t_us)
    assert sync.status()["ros_time_steps"] == int(stepped)
