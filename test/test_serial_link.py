"""SerialLink against a real pseudo-terminal through pyserial (no ROS): data, vanish, back-off, reconnect."""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import serial
from process_harness import Notifier

from fbg_accel_driver.serial_link import LinkState, SerialLink, steady_clock_ns

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)


class Notified(Notifier):
    """The link's ``notify`` callback (called on every queued chunk and every state change), counting its calls: a
    test waits for a condition by re-checking it each time the link reports something, never on a timer."""

    calls = 0

    def __call__(self) -> None:
        self.calls += 1
        self.notify()


def open_pty(link: Path) -> tuple[int, int]:
    master, slave = os.openpty()
    tty.setraw(slave)
    tmp = link.with_suffix(".tmp")
    os.symlink(os.ttyname(slave), tmp)
    os.replace(tmp, link)
    return master, slave


@contextmanager
def pty_link(path: Path, baud: int = 115200, **options: Any) -> Iterator[tuple[SerialLink, Notified, int]]:
    """A started SerialLink on a fresh pty at ``path``: (the link, its ``notify`` callback, the pty's master fd); the
    link is stopped and the pty closed after the block."""
    master, slave = open_pty(path)
    notified = Notified()
    link = SerialLink(str(path), baud, notify=notified, **options)
    link.start()
    try:
        yield link, notified, master
    finally:
        link.stop()
        os.close(master)
        os.close(slave)


def drain(link: SerialLink) -> bytes:
    out = b""
    while not link.queue.empty():
        out += link.queue.get_nowait()[1]
    return out


def send_through(link: SerialLink, notified: Notified, master: int, data: bytes, what: str) -> bytes:
    """Write ``data`` to the pty ``master``, wait (on the link's ``notified``) until ``link`` has read that many more
    bytes, and return what it queued (``drain``)."""
    start = link.status().bytes_read
    os.write(master, data)
    notified.wait_until(lambda: link.status().bytes_read >= start + len(data), 10, what)
    return drain(link)


def test_reads_survives_vanish_backs_off_and_reconnects_in_one_thread(tmp_path: Path) -> None:
    path = tmp_path / "board"
    notified = Notified()
    wait_for = notified.wait_until
    link = SerialLink(str(path), 115200, notify=notified, backoff_initial_s=0.05, backoff_max_s=0.2)
    threads_before = threading.active_count()
    link.start()
    try:
        # Port missing at start: retries with exponential back-off 0.05, 0.1, 0.2, 0.2 ...
        seen: set[tuple[int, float]] = set()

        def record() -> bool:
            st = link.status()
            if st.state is LinkState.DISCONNECTED:
                seen.add((st.failed_attempts, st.next_retry_s))
            return st.failed_attempts >= 4

        wait_for(record, 10, "four failed open attempts")
        assert seen and all(r == min(0.05 * 2 ** (k - 1), 0.2) for k, r in seen), seen
        assert "cannot open" in link.status().message

        master, slave = open_pty(path)
        wait_for(lambda: link.status().state is LinkState.CONNECTED, 10, "connected")
        assert send_through(link, notified, master, b"hello board", "bytes read") == b"hello board" and notified.calls > 0
        assert threading.active_count() == threads_before + 1

        # The port vanishes (pty closed, as when the simulator disconnects or a USB adapter is pulled).
        os.close(master)
        os.close(slave)
        path.unlink()
        wait_for(lambda: link.status().state is LinkState.DISCONNECTED, 10, "disconnected")
        assert link.status().disconnects == 1

        master, slave = open_pty(path)
        wait_for(lambda: link.status().state is LinkState.CONNECTED, 10, "reconnected")
        assert send_through(link, notified, master, b"again", "bytes after reconnect") == b"again"
        st = link.status()
        assert st.connects == 2 and st.thread_alive
        assert threading.active_count() == threads_before + 1  # no thread per reconnect

        # The name is re-pointed to another device while the old one stays open (udev by-id after a replug).
        master2, slave2 = open_pty(path)
        wait_for(lambda: link.status().connects == 3, 10, "reopened after the link was re-pointed")
        assert send_through(link, notified, master2, b"third", "bytes from the new device") == b"third"
        assert link.status().disconnects == 2
        for fd in (master, slave, master2, slave2):
            os.close(fd)
    finally:
        link.stop()
    assert not link.status().thread_alive and link.status().state is LinkState.STOPPED
    assert threading.active_count() == threads_before


def test_silent_port_is_reopened(tmp_path: Path) -> None:
    with pty_link(tmp_path / "board", backoff_initial_s=0.05, backoff_max_s=0.1, silence_timeout_s=0.3) as (link, notified, _):
        notified.wait_until(lambda: link.status().connects >= 2, 10, "reopen after 0.3 s of silence")
        assert link.status().disconnects >= 1


def test_a_frame_written_at_once_arrives_as_one_chunk(tmp_path: Path) -> None:
    """A read that wakes on a frame's first byte takes the rest with it: one chunk (one consumer wake-up) per frame."""
    with pty_link(tmp_path / "board", 921600) as (link, notified, master):
        wait_for = notified.wait_until
        wait_for(lambda: link.status().state is LinkState.CONNECTED, 10, "connected")
        frames = [bytes([0xA5, k]) + bytes(range(25)) for k in range(20)]  # 27 bytes each, like a v1 frame
        chunks: list[bytes] = []

        def take(total: int) -> bool:
            while not link.queue.empty():
                chunks.append(link.queue.get_nowait()[1])
            return sum(map(len, chunks)) >= total

        for k, frame in enumerate(frames):
            os.write(master, frame)
            wait_for(lambda k=k: take(27 * (k + 1)), 10, f"frame {k} queued")
        assert b"".join(chunks) == b"".join(frames)
        assert len(chunks) == len(frames), [len(c) for c in chunks]  # with read(1) alone: 1 + 26 bytes, 40 chunks


def test_each_chunk_carries_the_host_and_the_steady_time_of_its_read(tmp_path: Path) -> None:
    """The reader reads the host (ROS) clock and the steady clock together, so the clock estimate can run on the
    steady one and host clock steps move the stamps exactly (``clock_sync``)."""
    host_ahead_ns = 7 * 10**9  # a host clock 7 s ahead of the steady clock
    with pty_link(tmp_path / "board", clock_ns=lambda: steady_clock_ns() + host_ahead_ns) as (link, notified, master):
        notified.wait_until(lambda: link.status().state is LinkState.CONNECTED, 10, "connected")
        before = steady_clock_ns()
        os.write(master, b"stamped")
        notified.wait_until(lambda: link.status().bytes_read >= 7, 10, "bytes read")
        after = steady_clock_ns()
        host_ns, data, steady_ns = link.queue.get_nowait()
        assert data == b"stamped" and before <= steady_ns <= after
        assert abs(host_ns - steady_ns - host_ahead_ns) < 10**8  # read one right after the other


@pytest.mark.skipif(not hasattr(time, "CLOCK_MONOTONIC_RAW"), reason="no NTP-unadjusted clock on this platform")
def test_the_steady_time_of_a_read_is_the_clock_ntp_does_not_slew(tmp_path: Path) -> None:
    """The clock estimate (``clock_sync``) fits a straight line between the board clock and the steady clock over
    200 s; NTP (ntpd, chrony) slews CLOCK_MONOTONIC together with the host clock, so a slew bent that line and the
    stamps lagged ROS time (``test_stamp_accuracy.py``: a 20 ms slew at ntpd's 500 ppm stamped samples up to 20 ms
    early for 100 s). The steady time must be CLOCK_MONOTONIC_RAW, which NTP leaves alone: the slew then shows in the
    host-minus-steady offset, which the stamps follow. Before: ``time.monotonic_ns``, 264 ms outside the
    CLOCK_MONOTONIC_RAW bracket of the read on the host this was written on (the NTP corrections since boot)."""
    with pty_link(tmp_path / "board") as (link, notified, master):
        notified.wait_until(lambda: link.status().state is LinkState.CONNECTED, 10, "connected")
        before = time.clock_gettime_ns(time.CLOCK_MONOTONIC_RAW)
        os.write(master, b"stamped")
        notified.wait_until(lambda: link.status().bytes_read >= 7, 10, "bytes read")
        after = time.clock_gettime_ns(time.CLOCK_MONOTONIC_RAW)
        _, data, steady_ns = link.queue.get_nowait()
        assert data == b"stamped"
        assert before <= steady_ns <= after, (steady_ns - before, after - steady_ns)


def test_a_port_that_hangs_up_while_it_is_being_opened_is_retried(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The port vanishes between pyserial's open() and its input flush (a pty closed and re-created in quick
    succession, a USB adapter pulled while the driver reconnects): the kernel answers the flush with EIO, which
    pyserial lets through as ``termios.error``, not as a SerialException or OSError. It is a failed open like any
    other: the reader retries and takes the port that appears next. Before, that exception ended the reader
    thread: the link stayed DISCONNECTED for good and the driver never read again (a quick flapping pty did this
    within seconds). The hang-up is real (the pty is closed); the hook only places it inside that window."""
    path = tmp_path / "board"
    first = open_pty(path)
    flush = serial.Serial._reset_input_buffer
    hung_up: list[int] = []

    def hang_up_then_flush(ser: serial.Serial) -> None:
        if not hung_up:  # the first open only: the pty goes away under it
            for fd in first:
                os.close(fd)
            hung_up.append(1)
        flush(ser)

    monkeypatch.setattr(serial.Serial, "_reset_input_buffer", hang_up_then_flush)
    notified = Notified()
    link = SerialLink(str(path), 115200, notify=notified, backoff_initial_s=0.05, backoff_max_s=0.1)
    link.start()
    master = slave = -1
    try:
        notified.wait_until(lambda: link.status().failed_attempts >= 1 or not link.status().thread_alive, 10,
                          "the open that hung up reported")
        assert hung_up and link.status().thread_alive, link.status()
        assert "cannot open" in link.status().message
        master, slave = open_pty(path)  # the port comes back under the same name
        notified.wait_until(lambda: link.status().state is LinkState.CONNECTED, 10, "connected to the new pty")
        assert send_through(link, notified, master, b"back", "bytes from the new pty") == b"back"
    finally:
        link.stop()
        for fd in (master, slave):
            if fd >= 0:
                os.close(fd)


def test_a_name_re_pointed_to_another_live_device_is_followed_while_data_flows(tmp_path: Path) -> None:
    """docs/topics.md: when the port name is a symlink that now points to another device, the driver reopens it
    and never stays attached to a stale device. Here the old device keeps streaming (a link a user or a udev rule
    moved to a second board while the first stays plugged in). Before, the target was compared only after a read
    that timed out empty, so a device that never paused kept the driver on it for good: it went on publishing
    the first board's data under the name of the second."""
    path = tmp_path / "board"
    old_master, old_slave = open_pty(path)
    new_master, new_slave = os.openpty()
    tty.setraw(new_slave)
    notified = Notified()
    link = SerialLink(str(path), 115200, notify=notified)
    stop = threading.Event()

    def stream_old() -> None:
        """Keep the old device's input queue full: every read of it returns data at once, none times out."""
        while not stop.is_set():
            _, writable, _ = select.select([], [old_master], [], 0.05)
            if writable:
                try:
                    os.write(old_master, b"A" * 256)
                except BlockingIOError:
                    pass

    writer = threading.Thread(target=stream_old, daemon=True)
    got = bytearray()

    def received(what: bytes) -> bool:
        while not link.queue.empty():
            item = link.queue.get_nowait()
            if item is not None:
                got.extend(item[1])
        return what in got

    link.start()
    writer.start()
    try:
        notified.wait_until(lambda: received(b"A" * 512), 10, "the old device's stream")
        tmp = path.with_suffix(".tmp")
        os.symlink(os.ttyname(new_slave), tmp)
        os.replace(tmp, path)
        # the new device's bytes are written once it is open (pyserial flushes the input queue when it opens)
        notified.wait_until(lambda: link.status().connects == 2, 10, "reopened on the new target")
        os.write(new_master, b"from the new board")
        notified.wait_until(lambda: received(b"from the new board"), 10, "bytes of the new device")
        assert link.status().disconnects == 1 and link.status().state is LinkState.CONNECTED
    finally:
        stop.set()
        writer.join(5)
        link.stop()
        for fd in (old_master, old_slave, new_master, new_slave):
            os.close(fd)


def test_a_second_reader_of_the_same_port_is_refused_and_takes_over_when_the_first_closes(tmp_path: Path) -> None:
    """Two drivers on one port (a launch file started twice, two namespaces given the same port): the port is
    opened exclusively, so the second is refused with a reason that says the port is in use, retries with back-off,
    and the first keeps every byte. Before, both opened it and split the stream between them: with two real drivers
    on the simulated board each lost about two thirds of the frames (CRC errors, lost frames) while their `serial
    link` diagnostics said OK, and the second's open flushed the first's input queue."""
    path = tmp_path / "board"
    master, slave = open_pty(path)
    first_notified, second_notified = Notified(), Notified()
    first = SerialLink(str(path), 115200, notify=first_notified)
    second = SerialLink(str(path), 115200, notify=second_notified, backoff_initial_s=0.05, backoff_max_s=0.1)
    first.start()
    try:
        first_notified.wait_until(lambda: first.status().state is LinkState.CONNECTED, 10, "the first reader connected")
        second.start()
        second_notified.wait_until(lambda: second.status().failed_attempts >= 2 or second.status().connects > 0, 10,
                                 "the second reader's open attempts")
        st = second.status()
        assert st.connects == 0 and st.state is LinkState.DISCONNECTED, st
        assert "in use" in st.message and str(path) in st.message, st.message
        payload = bytes(range(256)) * 40
        for k in range(0, len(payload), 512):
            os.write(master, payload[k:k + 512])
            first_notified.wait_until(lambda k=k: first.status().bytes_read >= k + 512, 10, f"bytes up to {k + 512}")
        assert drain(first) == payload  # nothing went to the second reader
        assert second.status().bytes_read == 0
        first.stop()  # the first driver exits: the second gets the port at its next attempt
        second_notified.wait_until(lambda: second.status().state is LinkState.CONNECTED, 10, "the second reader took over")
        assert send_through(second, second_notified, master, b"now yours", "bytes to the second reader") == b"now yours"
    finally:
        first.stop()
        second.stop()
        os.close(master)
        os.close(slave)
