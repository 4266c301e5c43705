"""Independent searches of a diagnosis run side by side, one thread per lane (no ROS, no rclpy).

A lane is an object a task needs to itself while it runs (an ``Evaluator`` with its own caches of designs): ``map``
hands each task a free lane, runs the tasks on a pool of as many threads as there are lanes, and returns their
results in the order of the tasks, whatever order they finish in. The diagnosis's searches spend their time in
numpy, scipy and BLAS calls that let go of the interpreter lock (products, filters, reductions over 10^5 to 10^6
samples), so two lanes on two cores run two searches in little more than the time of one.

What the tasks share must not depend on which lane or in which order they run (caches of values that depend on
their key alone); then the results are those of one lane, bit for bit. Once every task of a map has started, a task
may borrow the lanes the others have left idle for work of its own that can be split (``idle_lanes``); between maps,
the caller lends itself the other lanes the same way (``Lanes.lending``).
"""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any, Generic, TypeVar

L = TypeVar("L")
T = TypeVar("T")
R = TypeVar("R")


def default_lane_count() -> int:
    """Lanes for a large diagnosis: one per core this process may run on, at most two (what the benchmark machine
    has; a third lane would add memory for the designs it caches and compete with the BLAS calls)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(2, cores))


class Lanes(Generic[L]):
    """Lanes (``lanes``, each used by one task at a time) that tasks run on side by side. One lane: the tasks run in
    the caller's thread, one after the other; more: each ``map`` starts as many threads as there are lanes and ends
    them before it returns (no thread outlives a map, none is left behind by an exception)."""

    def __init__(self, lanes: list[L]) -> None:
        if not lanes:
            raise ValueError("at least one lane")
        self.lanes = list(lanes)

    def map(self, task: Callable[[L, T], R], items: Iterable[T], done: Callable[[R], None] | None = None,
            cost: Callable[[T], float] | None = None) -> list[R]:
        """``[task(lane, item) for item in items]``, each task on a free lane; ``done(result)`` is called in the
        caller's thread for each result in the items' order as soon as it and those before it are there. An exception
        of a task is raised once every task has ended (the first in the items' order). ``cost(item)``: what the task is
        expected to take (any unit); the tasks start in order of falling cost (equal costs in the items' order), so
        that a long one does not start last while the other lanes have nothing left to do."""
        items = list(items)
        if len(self.lanes) == 1 or len(items) <= 1:
            out = []
            for it in items:
                out.append(task(self.lanes[0], it))
                if done is not None:
                    done(out[-1])
            return out
        free: queue.SimpleQueue[L] = queue.SimpleQueue()
        for lane in self.lanes:
            free.put(lane)
        state = _MapState(free, len(items))

        def run(item: T) -> R:
            lane = free.get()
            with state.lock:
                state.to_start -= 1
            before, _in_task.state = getattr(_in_task, "state", None), state
            try:
                return task(lane, item)
            finally:
                _in_task.state = before
                free.put(lane)

        out: list[R] = []
        failed: BaseException | None = None
        with ThreadPoolExecutor(min(len(self.lanes), len(items)), thread_name_prefix="search-lane") as pool:
            order = range(len(items)) if cost is None else sorted(range(len(items)), key=lambda i: -cost(items[i]))
            started = {i: pool.submit(run, items[i]) for i in order}
            for f in (started[i] for i in range(len(items))):
                exc = f.exception()  # waits for it
                failed = failed or exc
                if failed is None:
                    out.append(f.result())
                    if done is not None:
                        done(out[-1])
        if failed is not None:
            raise failed
        return out

    @contextmanager
    def lending(self) -> Iterator[L]:
        """The first lane, for work of the caller's own between maps, with the other lanes lent to it meanwhile
        (``idle_lanes`` in the ``with`` block, on the caller's thread): a search the caller runs itself uses them.
        Not within a task of a map (its lanes are the map's to lend)."""
        if getattr(_in_task, "state", None) is not None:
            raise RuntimeError("Lanes.lending within a task of a map or another lending")
        free: queue.SimpleQueue[L] = queue.SimpleQueue()
        for lane in self.lanes[1:]:
            free.put(lane)
        _in_task.state = _MapState(free, 0)
        try:
            yield self.lanes[0]
        finally:
            _in_task.state = None

    def each(self, task: Callable[[L], None]) -> None:
        """``task(lane)`` on every lane, in the caller's thread (between maps: while no task runs)."""
        for lane in self.lanes:
            task(lane)


class _MapState:
    """The free lanes of a map and how many of its tasks have not started (``idle_lanes``)."""

    def __init__(self, free: queue.SimpleQueue[Any], to_start: int) -> None:
        self.free = free
        self.to_start = to_start
        self.lock = threading.Lock()


_in_task = threading.local()  # .state: the _MapState of the map whose task this thread runs


@contextmanager
def idle_lanes(most: int) -> Iterator[list[Any]]:
    """Up to ``most`` lanes of the map whose task the calling thread runs that are free now while every task of the
    map has started (no task waits for them), lent until the ``with`` block ends; none outside a task of a map of
    more than one lane. A search uses them for the trials of a batch that do not depend on each other, when the
    other tasks of its map are done."""
    state = getattr(_in_task, "state", None)
    lent: list[Any] = []
    if state is not None and most > 0:
        with state.lock:
            while state.to_start == 0 and len(lent) < most:
                try:
                    lent.append(state.free.get_nowait())
                except queue.Empty:
                    break
    try:
        yield lent
    finally:
        for lane in lent:
            state.free.put(lane)


def beside(fn: Callable[..., R], *args: object, thread: bool = True) -> Future[R]:
    """``fn(*args)`` started on a thread of its own while the caller goes on (its result: ``.result()``, an exception
    raised there); ``thread`` False: worked out now, in the caller's thread (a diagnosis of one lane)."""
    if not thread:
        done: Future[R] = Future()
        try:
            done.set_result(fn(*args))
        except Exception as exc:  # raised by .result(), where a thread's would be
            done.set_exception(exc)
        return done
    pool = ThreadPoolExecutor(1, thread_name_prefix="search-lane-beside")
    try:
        return pool.submit(fn, *args)
    finally:
        pool.shutdown(wait=False)  # the thread ends once fn has returned
