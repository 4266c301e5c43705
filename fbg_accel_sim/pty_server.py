"""Serve the simulated board's byte stream on a pseudo-terminal, in real time (no ROS).

The slave side of the pty behaves like the board's USB/Bluetooth serial port: a driver opens it
with pyserial exactly as it opens /dev/ttyUSB0. The server

* puts the pty in raw mode (no echo, no line discipline: binary frames pass unchanged),
* keeps its own handle on the slave so the port survives a client closing and reopening it,
* paces the frames against ``time.monotonic()`` (sample k is written when its board time is
  due; no sleep drift accumulates, a late loop catches up by writing several frames),
* on a simulated disconnect closes the pty (the client's reads fail as on an unplugged USB
  adapter) and after the down time opens a new one, re-pointing the ``--link`` symlink (as
  /dev/serial/by-id does) so a reconnecting client finds it under the same name; with
  ``faults.disconnects.remove_link`` the name is removed while the link is down (an rfcomm device
  that exists only while the Bluetooth connection is up), else it dangles (``UNPLUGGED``). The link
  never names a pty the server does not hold: it is re-pointed or removed before the pty is closed
  (the kernel gives a closed pty's number to the next process that opens one: a client reconnecting
  through a link left on it would open another process' terminal),
* by default waits until a client opens the port before the board starts (an ESP32 board
  reboots when its USB-serial port is opened: DTR auto-reset); bytes written to a pty that no
  client ever opened are garbled by the line discipline, so nothing is written before,
* never blocks on a client that does not read: bytes the pty cannot take (about 20 KB) wait in a
  backlog of ``backlog_s`` seconds of data; beyond that they are dropped, as a UART overflows,
  and counted in ``overflow_bytes``.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import select
import struct
import sys
import termios
import time
import tty
from pathlib import Path

import numpy as np

from .board_physics import BoardSimulator, SimBlock

# what the link names while the board is unplugged: no file, and never a pty (devpts names its terminals by number)
UNPLUGGED = "/dev/pts/unplugged"


def _point_link(link: str, target: str) -> None:
    """Make ``link`` a symlink to ``target`` in one step (a new link renamed over it)."""
    tmp = f"{link}.tmp{os.getpid()}"
    if os.path.lexists(tmp):
        os.unlink(tmp)
    os.symlink(target, tmp)
    os.replace(tmp, link)


class PtyEndpoint:
    """One pseudo-terminal pair; ``path`` is the slave device name."""

    def __init__(self, link: str | None = None, max_backlog_bytes: int = 65536) -> None:
        self.link = link
        self.master = -1
        self.slave = -1
        self.path = ""
        self.overflow_bytes = 0
        self.max_backlog_bytes = max_backlog_bytes
        self._pending = bytearray()

    def open(self, hold: bool = True) -> str:
        """Create a new pty (raw mode). ``hold``: keep a slave handle so the port persists between clients."""
        self.master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(slave)
        self._pending.clear()
        if hold:
            self.slave = slave
        else:
            os.close(slave)
            self.slave = -1
        if self.link:
            _point_link(self.link, self.path)  # the new pty is open before the link names it
        return self.path

    def client_present(self) -> bool:
        """True once some process has the slave open (the master stops reporting POLLHUP)."""
        p = select.poll()
        p.register(self.master, select.POLLHUP)
        return not any(ev & select.POLLHUP for _, ev in p.poll(0))

    def wait_client(self, should_stop, poll_s: float = 0.01) -> bool:
        """Block until a client opens the port (or ``should_stop()``). False if stopped."""
        while not self.client_present():
            if should_stop():
                return False
            time.sleep(poll_s)
        return True

    def hold_slave(self) -> None:
        """Keep our own slave handle so the port (and its raw settings) survive a client closing it."""
        if self.slave < 0:
            self.slave = os.open(self.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)

    def unplug(self, remove_link: bool) -> None:
        """The board unplugged: the link removed (``remove_link``) or re-pointed to ``UNPLUGGED``, then the pty
        closed (the client's reads fail). In that order: once the pty is closed its number is free for any process,
        and the link must not name it then."""
        if remove_link:
            self.remove_link()
        elif self._names_ours():
            _point_link(self.link, UNPLUGGED)
        self.close()

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = -1

    def _link_target(self) -> str | None:
        """What the link names, None when there is no link (or it is not a symlink)."""
        try:
            return os.readlink(self.link) if self.link and os.path.islink(self.link) else None
        except OSError:
            return None

    def _names_ours(self) -> bool:
        """The link exists and names this endpoint's pty (not one re-pointed by someone else since)."""
        return self._link_target() == self.path

    def remove_link(self) -> None:
        """Remove the link if it names this endpoint's pty (or ``UNPLUGGED``: the board is unplugged)."""
        if self._link_target() in (self.path, UNPLUGGED):
            with contextlib.suppress(OSError):
                os.unlink(self.link)

    def write(self, data: bytes) -> int:
        """Write without blocking; bytes that do not fit are dropped and counted. Returns bytes written."""
        if self.master < 0:
            return 0
        self._pending += data
        view = memoryview(self._pending)
        written = 0
        while written < len(view):
            try:
                written += os.write(self.master, view[written:])
            except BlockingIOError:
                break
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EAGAIN):
                    break
                raise
        view.release()
        del self._pending[:written]
        excess = len(self._pending) - self.max_backlog_bytes
        if excess > 0:  # UART overflow: the newest bytes are lost
            del self._pending[len(self._pending) - excess:]
            self.overflow_bytes += excess
        self.drain_input()
        return written

    def unread_bytes(self) -> int:
        """Bytes written but not yet read by the client: TIOCINQ on the slave, after a poll of the slave.

        Bytes written to the master reach the slave's read queue through the tty flip buffer, pushed by a
        kernel work item (Linux drivers/tty/tty_buffer.c, flush_to_ldisc): until it has run, TIOCINQ does not
        count them (right after a write it often reads 0). Polling the slave for input when its queue looks
        empty makes the kernel finish that work item first (drivers/tty/n_tty.c, n_tty_poll calls
        tty_buffer_flush_work), so the count that follows holds every byte written before the call, at any
        CPU load; nothing is taken from the queue."""
        if self.slave < 0:
            return 0
        try:
            poller = select.poll()
            poller.register(self.slave, select.POLLIN)
            poller.poll(0)
            return struct.unpack("i", fcntl.ioctl(self.slave, termios.TIOCINQ, b"\0\0\0\0"))[0]
        except OSError:
            return 0

    def linger(self, timeout_s: float, grace_s: float) -> None:
        """Give the client up to ``timeout_s`` to read what was sent (before an unplug, at the end of a run),
        then ``grace_s`` more: a reader blocked in ``read(n)`` with a timeout holds bytes it has taken from
        the pty until the call returns, and pyserial discards them if the port vanishes meanwhile. Done
        when nothing is pending here and nothing is unread in the slave's queue (``unread_bytes``)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._pending:
                self.write(b"")
            if not self._pending and self.unread_bytes() == 0:
                break
            time.sleep(0.005)
        time.sleep(grace_s)

    def drain_input(self) -> None:
        """Discard what the client wrote (the board ignores host commands)."""
        try:
            while os.read(self.master, 4096):
                pass
        except (BlockingIOError, OSError):
            pass


class TruthRecorder:
    """Accumulates the truth arrays of served blocks (only when a truth file was requested)."""

    def __init__(self) -> None:
        self.blocks: list[SimBlock] = []

    def add(self, block: SimBlock) -> None:
        if len(block):
            self.blocks.append(block)

    def save(self, path: str | Path, sim: BoardSimulator, extra: dict) -> None:
        blocks = self.blocks
        out = {key: np.concatenate([b.arrays[key] for b in blocks]) for key in (blocks[0].arrays if blocks else ())}
        out.update({key: np.array(value) for key, value in sim.totals.items()})
        out.update({f"expected_{key}": np.array(value) for key, value in sim.expected_decoder_stats().items()})
        out.update({f"noise_{key}": np.asarray(v) for key, v in sim.configured_noise().items() if key != "model"})
        out["aht10_offset_c"] = np.array(sim.aht_offset)
        out["config_yaml"] = np.array(sim.cfg.to_yaml())
        out["seed"] = np.array(sim.seed)
        out.update({key: np.asarray(value) for key, value in extra.items()})
        with open(path, "wb") as fh:  # a file object: numpy adds no ".npz" to the caller's (temporary) name
            np.savez_compressed(fh, **out)


def serve_pty(sim: BoardSimulator, duration_s: float, link: str | None, truth: TruthRecorder | None,
              should_stop, announce=print, linger_s: float = 5.0, grace_s: float = 1.0, wait_client: bool = True,
              backlog_s: float = 2.0, client_settle_s: float = 1.0, unplug_linger_s: float = 5.0) -> dict:
    """Serve until ``duration_s`` (inf: until ``should_stop()``). Returns serving statistics.

    The board starts when a client first opens the pty (unless ``wait_client`` is False). After a
    simulated disconnect the new pty gets no bytes until a client has opened it and
    ``client_settle_s`` has passed (pyserial flushes the input queue while it opens the port, and a
    loaded host can take hundreds of ms between the open and the flush: 0.25 s was once too short while
    the whole test suite ran on 2 cores, so 1 s); the frames the board produces
    meanwhile are lost, and are logged as unsent in the truth, so the truth still predicts the
    decoder's counts exactly. Before an "unplug" the client gets up to ``unplug_linger_s`` to read
    what was already sent (a real unplug loses bytes in flight, but then no truth could predict the
    decoder; the wait ends as soon as the client has read everything, so the 5 s bound costs nothing
    on an idle host and covers a reader starved by a loaded one); bytes it still had not read are
    counted in ``unplug_unread_bytes``. When the run reaches
    its end (not when stopped by a signal) the pty stays open until the client has read everything,
    at most ``linger_s``, plus ``grace_s``.
    """
    ep = PtyEndpoint(link, max_backlog_bytes=max(65536, int(backlog_s * sim.rate_true_hz * 27)))
    path = ep.open(hold=not wait_client)
    announce(f"PTY {path}")
    stats = {"reconnects": 0, "written_bytes": 0, "paths": [path], "overflow_bytes": 0, "frames_lost_no_client": 0,
             "unplug_unread_bytes": 0}
    if wait_client:
        if not ep.wait_client(should_stop):
            ep.remove_link()
            ep.close()
            return stats
        time.sleep(client_settle_s)
        ep.hold_slave()
    n_total = sim.samples_for(duration_s) if np.isfinite(duration_s) else None
    bounds = sorted({b for a0, b0 in sim._disc_k for b in (a0, b0)})
    disc_starts = {a0 for a0, _ in sim._disc_k}
    disc_ends = {b0 for _, b0 in sim._disc_k}
    dt = sim.dt_true
    t0 = time.monotonic()
    k = sim.sample_index
    state = "open"  # open | down | waiting | settling
    settle_until = 0.0
    try:
        while not should_stop():
            if n_total is not None and k >= n_total:
                break
            if k in disc_ends and state == "down":
                path = ep.open(hold=False)
                state = "waiting"
                stats["reconnects"] += 1
                stats["paths"].append(path)
                print(f"RECONNECT {path}", file=sys.stderr, flush=True)
            if k in disc_starts and state != "down":
                if state == "open":  # let the client take what was sent before the "unplug"
                    ep.linger(unplug_linger_s, 0.0)
                    stats["unplug_unread_bytes"] += ep.unread_bytes() + len(ep._pending)
                # the device name vanishes with the link (rfcomm-like), or the link dangles
                ep.unplug(remove_link=sim.disconnect_removes_link)
                state = "down"
                print("DISCONNECT", file=sys.stderr, flush=True)
            now = time.monotonic()
            if state == "waiting" and ep.client_present():
                state, settle_until = "settling", now + client_settle_s
            if state == "settling" and now >= settle_until:
                ep.hold_slave()
                state = "open"
            due = int((now - t0) / dt) + 1  # samples whose time has come
            if due <= k:
                time.sleep(min(0.002, max(0.0, t0 + k * dt - now)))
                continue
            n = due - k
            if n_total is not None:
                n = min(n, n_total - k)
            nxt = [b for b in bounds if b > k]
            if nxt:
                n = min(n, nxt[0] - k)
            n = min(n, 4096)
            deliver = state == "open"
            if truth is not None:
                block = sim.step(n, deliver=deliver)
                data = block.wire_bytes()
                truth.add(block)
            else:
                data = sim.step_bytes(n)
            if not deliver and state != "down":
                stats["frames_lost_no_client"] += n
            k = sim.sample_index
            if deliver:
                stats["written_bytes"] += ep.write(data)
        if state == "open" and not should_stop():
            ep.linger(linger_s, grace_s)
    finally:
        stats["overflow_bytes"] = ep.overflow_bytes
        ep.remove_link()  # first: a closed pty's number is free for another process
        ep.close()
    return stats
