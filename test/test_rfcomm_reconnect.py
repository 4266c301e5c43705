"""The driver (a real process over DDS) follows a Bluetooth rfcomm-like device that disappears and returns.

With the board on Bluetooth SPP (docs/firmware.md), the host reads /dev/rfcomm0. The device made by
``rfcomm connect`` exists while that command holds the connection: when the radio link drops, the tty
hangs up and the name goes away; a reconnect loop running ``rfcomm connect`` again brings the name
back (a new tty). The board itself does not reboot: it keeps sampling and counting ``seq`` while no client is connected,
so the host must see the gap as lost samples, not as a board reset.

Here ``board_sim`` serves the frames on a pty behind the symlink the driver is given, with
``faults.disconnects.remove_link: true``: at 2 s the pty is closed and the symlink removed; 2.5 s later a
new pty appears under the same name (2.5 s: at least two of the driver's 1 Hz diagnostics fall in the
outage, so one of them shows the failed open of the missing name). The test checks that the name
really vanished and came back, that the driver reported the outage and reconnected on its single
reader thread, and that its counters equal the simulator's truth exactly (the gap counted as lost frames,
no reset), with every delivered frame published once, in order.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from test_driver_process import (
    Listener,
    assert_counters,
    assert_published_once_in_order,
    expected_counters,
    python_threads,
    start_driver,
    start_sim,
    stop,
    stop_all,
)

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)


def test_rfcomm_like_device_removed_and_recreated(ros, tmp_path: Path) -> None:
    link = tmp_path / "rfcomm0"
    truth_file = tmp_path / "truth.npz"
    listener = Listener("test_rfcomm_reconnect", ros)
    driver = start_driver({"port": str(link), "reconnect_backoff_max_s": 0.2}, tmp_path / "driver.log")
    sim = None
    try:
        listener.wait_until(listener.matched, 30, "driver publishers discovered and diagnostics received")
        sim, first_pty = start_sim([
            "--link", str(link), "--duration", "7", "--truth", str(truth_file), "--seed", "11",
            "--set", "faults.disconnects={at_s: [2.0], down_s: 2.5, remove_link: true}",
        ])
        listener.wait_until(lambda: listener.last("serial link")[0] == 0, 20, "serial link OK")
        threads_before = python_threads(listener)
        n_diag_up = len(listener.diag)
        assert os.readlink(link) == first_pty
        # The device name disappears with the link ...
        listener.wait_until(lambda: not os.path.lexists(link), 20, f"{link} removed while the link is down")
        listener.wait_until(lambda: listener.last("serial link")[0] == 2, 20, "serial link ERROR while the device is gone")
        # ... and reappears under the same name: a new tty (the kernel may reuse the pts number, as
        # /dev/rfcomm0 keeps its number).
        listener.wait_until(lambda: os.path.lexists(link), 20, f"{link} created again")
        n_before = len(listener.raw)
        listener.wait_until(lambda: listener.last("serial link")[0] == 0, 20, "serial link OK after the device returned")
        # the link's counters while it is up again: once board_sim ends its run (below) the driver sees that hang-up
        # too, a disconnect that is not the outage's
        up_again = listener.last("serial link")[2]
        listener.wait_until(lambda: len(listener.raw) > n_before + 50, 10, "publishing again after the reconnect")
        listener.wait_until(lambda: sim.poll() is not None, 30, "board_sim finished its 7 s run")
        assert sim.returncode == 0, sim.stderr.read() if sim.stderr else ""
        truth = np.load(truth_file)
        expected = expected_counters(truth)
        assert expected["lost_frames"] >= 250 and expected["resets"] == 0  # >= 2.5 s at 100 Hz unsent, no reboot
        listener.wait_until(lambda: int(listener.last("frames")[2]["frames"]) >= expected["frames"]
                            and len(listener.raw) >= expected["frames"], 15,
                            lambda: f"{expected['frames']} frames published: driver counters {listener.last('frames')[2]}, "
                                    f"{len(listener.raw)} imu/raw received, truth {expected}, "
                                    f"unread at the unplug {int(truth['unplug_unread_bytes'])} B")
        assert_counters(listener, expected)
        assert int(up_again["connects"]) == 2 and int(up_again["disconnects"]) == 1, up_again
        assert int(up_again["failed_attempts"]) >= 2, up_again  # retried while the name did not exist
        down_messages = [d["serial link"][1] for d in listener.diag[n_diag_up:] if d["serial link"][0] == 2]
        assert any("No such file" in m for m in down_messages), down_messages
        assert python_threads(listener) == threads_before  # the reconnect reused the reader thread
        assert stop(driver) == 0, (tmp_path / "driver.log").read_text()
    finally:
        stop_all(sim, driver, listener)
    assert_published_once_in_order(listener, truth)
