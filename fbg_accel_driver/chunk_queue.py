"""Bounded byte-chunk queue between the serial reader thread and its consumer (no ROS).

The reader thread must never block on a slow consumer (it would stop reading the port and the
kernel buffer would overflow), and the queue must not grow without bound when the source is
faster than the decoder. So ``put`` never blocks: when the
queued bytes exceed ``max_bytes`` it drops the *oldest* chunks and counts them, keeping the newest
data (for a navigation consumer the newest sample is the valuable one; the decoder sees the gap as
lost frames through the board's sequence counter).

It wraps ``queue.SimpleQueue`` (a C queue whose blocking ``get`` wakes in 10-30 us, see
bench/bench_driver_stages.py) and keeps the byte count beside it under a lock. A ``wake()`` puts a
``None`` item that ``get`` returns as is: the consumer uses it to look at state changes.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass

Chunk = tuple[int, bytes, int]  # (host time in ns when the read returned, bytes, steady time in ns then)


@dataclass(frozen=True)
class QueueStats:
    """Counters of a :class:`ChunkQueue` (cumulative since creation)."""

    queued_bytes: int  # bytes waiting now
    max_bytes: int  # the bound
    dropped_chunks: int  # chunks discarded to keep the bound
    dropped_bytes: int
    high_water_bytes: int  # most bytes ever waiting (after dropping)


class ChunkQueue:
    """FIFO of ``(host_ns, bytes, steady_ns)`` chunks holding at most ``max_bytes`` bytes (the newest ones).

    One producer (``put``, ``wake``) and one consumer (``get``, ``get_nowait``); both may run in
    different threads. A single chunk larger than ``max_bytes`` is kept alone (the bound is then
    exceeded by that one chunk, never more).
    """

    def __init__(self, max_bytes: int = 262_144) -> None:
        if max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self._q: queue.SimpleQueue[Chunk | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._bytes = 0
        self._chunks = 0
        self._dropped_chunks = 0
        self._dropped_bytes = 0
        self._high = 0

    def put(self, host_ns: int, data: bytes, steady_ns: int | None = None) -> None:
        """Append a chunk read at host time ``host_ns`` and steady time ``steady_ns`` (None: the host clock is
        steady, ``clock_sync``); never blocks. Drops the oldest chunks while the bound is exceeded."""
        with self._lock:
            self._bytes += len(data)
            self._chunks += 1
            self._q.put((host_ns, data, host_ns if steady_ns is None else steady_ns))
            while self._bytes > self.max_bytes and self._chunks > 1:
                try:
                    old = self._q.get_nowait()
                except queue.Empty:  # pragma: no cover - the consumer took them meanwhile
                    break
                if old is None:  # a wake-up: keep it (moved behind the data, still delivered)
                    self._q.put(None)
                    continue
                self._bytes -= len(old[1])
                self._chunks -= 1
                self._dropped_chunks += 1
                self._dropped_bytes += len(old[1])
            self._high = max(self._high, self._bytes)

    def wake(self) -> None:
        """Make a blocked ``get`` return ``None`` (a state change to look at, or shutdown)."""
        self._q.put(None)

    def get(self, timeout: float | None = None) -> Chunk | None:
        """The oldest chunk, or ``None`` for a wake-up; blocks up to ``timeout`` s (None: forever).
        Raises ``queue.Empty`` on timeout."""
        return self._taken(self._q.get(timeout=timeout))

    def get_nowait(self) -> Chunk | None:
        """Like :meth:`get` without blocking (``queue.Empty`` when nothing is queued)."""
        return self._taken(self._q.get_nowait())

    def empty(self) -> bool:
        return self._q.empty()

    def _taken(self, item: Chunk | None) -> Chunk | None:
        if item is not None:
            with self._lock:
                self._bytes -= len(item[1])
                self._chunks -= 1
        return item

    def stats(self) -> QueueStats:
        with self._lock:
            return QueueStats(self._bytes, self.max_bytes, self._dropped_chunks, self._dropped_bytes, self._high)
