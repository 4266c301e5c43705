"""The calibration node's watch of the sample stream (``fbg_accel_calibration.recorder.stream_watch``; no open issue: a dynamic
run whose node started a few seconds after the board waited forever once the board's stream had ended, its file open,
and said nothing). The node runs it once a second; its process test is in ``test_calibration_node_process.py``."""

from __future__ import annotations

import pytest

from fbg_accel_calibration.recorder.stream_watch import STALL_WARN_S, StreamWatch


def test_a_stall_is_reported_once_and_its_end_too_and_by_default_the_run_waits() -> None:
    w = StreamWatch()
    assert w.check(100.0) == ("", "")  # nothing is judged before the first sample (the node may start first)
    assert w.sample(0.0) == ""
    assert w.check(STALL_WARN_S - 0.1) == ("", "")
    warning, reason = w.check(STALL_WARN_S)
    assert warning.startswith("no imu/raw sample for 5.0 s") and "waits for the stream" in warning and reason == ""
    assert w.check(3600.0) == ("", "")  # once per stall, and never an end without a timeout
    assert w.sample(3601.0) == "imu/raw samples again after 3601.0 s without any"
    assert w.sample(3601.01) == ""
    assert w.check(3601.02) == ("", "")


def test_with_a_timeout_the_run_ends_after_that_long_without_a_sample() -> None:
    w = StreamWatch(timeout_s=30.0)
    w.sample(10.0)
    warning, reason = w.check(10.0 + STALL_WARN_S)
    assert "the run ends after 30 s without one" in warning and reason == ""
    assert w.check(39.9) == ("", "")
    warning, reason = w.check(40.0)
    assert warning == "" and reason.startswith("no imu/raw sample for 30.0 s (stream_timeout_s 30)")
    short = StreamWatch(timeout_s=2.0)  # a timeout below the warning time ends the run without a warning first
    short.sample(0.0)
    assert short.check(2.0)[1]


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_a_bad_timeout_is_refused(bad: float) -> None:
    with pytest.raises(ValueError, match="stream_timeout_s"):
        StreamWatch(timeout_s=bad)
