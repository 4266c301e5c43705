"""The process tests' waiting primitive: woken by notifications, never by polling, and able to time out."""

from __future__ import annotations

import sys
import threading

import pytest
from process_harness import ChildProcess, Notifier

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)


def test_a_notification_from_another_thread_ends_the_wait() -> None:
    notifier, state = Notifier(), {"done": False}

    def worker() -> None:
        state["done"] = True
        notifier.notify()

    t = threading.Thread(target=worker)
    t.start()
    notifier.wait_until(lambda: state["done"], 30, "the worker")
    t.join()


def test_a_wait_with_nothing_to_wake_it_times_out_naming_what_it_waited_for() -> None:
    calls = []
    with pytest.raises(AssertionError, match="waiting for the impossible"):
        Notifier().wait_until(lambda: calls.append(1) is not None, 0.2, "the impossible")
    assert len(calls) == 2  # checked at the start and at the deadline, nothing in between: no polling


def test_a_child_wakes_the_notifier_per_line_and_at_the_end_of_its_output() -> None:
    notifier = Notifier()
    child = ChildProcess("echo", [sys.executable, "-c", "print('one'); print('two')"], notifier)
    notifier.wait_until(lambda: child.output_ended, 30, "the end of the child's output")
    assert child.lines == ["one", "two"] and child.wait_exit(10) == 0
