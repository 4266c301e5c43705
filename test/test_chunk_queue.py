"""The bounded reader queue: never blocks the reader, never exceeds its bound, keeps the newest
bytes and counts what it dropped (issue 11: an unbounded queue grew by 10 MB/s under a flood)."""

from __future__ import annotations

import os
import pty
import queue
import threading
import tty

import pytest

from fbg_accel_driver.chunk_queue import ChunkQueue
from fbg_accel_driver.serial_link import LinkState, SerialLink

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)


def test_bound_keeps_newest_and_counts_drops() -> None:
    q = ChunkQueue(max_bytes=100)
    for i in range(10):
        q.put(i, bytes([i]) * 30)
    st = q.stats()
    assert st.queued_bytes == 90 and st.dropped_chunks == 7 and st.dropped_bytes == 210
    assert st.high_water_bytes <= 100
    got = [q.get_nowait() for _ in range(3)]
    assert [g[0] for g in got] == [7, 8, 9]  # the newest three, in order
    assert q.stats().queued_bytes == 0 and q.empty()


def test_oversized_chunk_is_kept_alone_and_wakes_survive_drops() -> None:
    q = ChunkQueue(max_bytes=10)
    q.put(0, b"a" * 5)
    q.wake()
    q.put(1, b"b" * 50)  # larger than the bound: kept, everything older dropped, the wake-up kept
    items = []
    while not q.empty():
        items.append(q.get_nowait())
    assert items.count(None) == 1
    chunks = [i for i in items if i is not None]
    assert chunks == [(1, b"b" * 50, 1)]  # no steady time given: the host time is taken as steady
    assert q.stats().dropped_bytes == 5 and q.stats().queued_bytes == 0
    with pytest.raises(queue.Empty):
        q.get_nowait()


def test_concurrent_producer_consumer_accounts_every_byte() -> None:
    """Every byte put is either delivered (in order) or counted as dropped, under contention."""
    q = ChunkQueue(max_bytes=1000)
    n, size = 20000, 37
    delivered: list[int] = []
    done = threading.Event()

    def consume() -> None:
        while True:
            item = q.get()
            if item is None:
                if done.is_set():
                    return
                continue
            delivered.append(item[0])

    t = threading.Thread(target=consume)
    t.start()
    for i in range(n):
        q.put(i, b"x" * size)
    done.set()
    q.wake()
    t.join(30)
    while not q.empty():
        item = q.get_nowait()
        if item is not None:
            delivered.append(item[0])
    st = q.stats()
    assert delivered == sorted(delivered)
    assert len(delivered) * size + st.dropped_bytes == n * size
    assert st.queued_bytes == 0 and st.high_water_bytes <= 1000


def test_serial_link_under_a_flood_without_consumer_stays_bounded() -> None:
    """A pty source writing 4 MB that nobody consumes: the link's queue holds at most its bound,
    the last bytes written are the ones kept, and status() reports the dropped bytes."""
    master, slave = pty.openpty()
    tty.setraw(slave)  # raw before the first byte (the link sets it raw only once it has opened the port)
    path = os.ttyname(slave)
    total = 4 * 1024 * 1024
    payload = bytes(range(256)) * (total // 256)
    all_read, connected = threading.Event(), threading.Event()
    link_box: list[SerialLink] = []

    def notify() -> None:
        if not link_box:
            return
        st = link_box[0].status()
        if st.state is LinkState.CONNECTED:
            connected.set()
        if st.bytes_read >= total:
            all_read.set()

    link = SerialLink(path, 921600, notify=notify, max_queued_bytes=65536, read_timeout_s=0.05)
    link_box.append(link)
    link.start()
    try:
        assert connected.wait(30), link.status()  # pyserial flushes the input buffer when it opens the port
        view = memoryview(payload)
        while view:
            written = os.write(master, view[:4096])
            view = view[written:]
        assert all_read.wait(60), link.status()
        st = link.status()
        assert st.bytes_read == total
        assert st.queued_bytes <= 65536  # a chunk is at most max_chunk = 65536 bytes, so the bound holds exactly
        assert st.queue_dropped_bytes == total - st.queued_bytes and st.queue_dropped_chunks > 0
        kept = b""
        while not link.queue.empty():
            item = link.queue.get_nowait()
            if item is not None:
                kept += item[1]
        assert kept == payload[-len(kept):]  # the newest bytes, contiguous
    finally:
        link.stop()
        os.close(master)
        os.close(slave)
