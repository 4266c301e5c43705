"""Pose sequencer state machine: operator and auto modes, fed sample by sample without ROS."""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_calibration.recorder.pose_plan import PosePlan
from fbg_accel_calibration.recorder.pose_sequencer import Mode, Phase, PoseSequencer
from fbg_accel_driver.stillness_monitor import StillnessMonitor, first_order_noise_floor

RATE_HZ = 100.0


def _plan(poses=None, samples=10, dwell=1.0, move=0.5) -> PosePlan:
    poses = poses or [{"name": "z_up", "psi_deg": 0, "theta_deg": 0}, {"name": "x_up", "psi_deg": 90, "theta_deg": 90},
                      {"name": "z_down", "psi_deg": 0, "theta_deg": 180}]
    return PosePlan.from_dict({"dwell_s": dwell, "move_s": move, "samples_per_pose": samples, "poses": poses})


class Feeder:
    """Feeds ``still`` verdicts at RATE_HZ and keeps every returned label."""

    def __init__(self, seq: PoseSequencer, t0: float = 0.0) -> None:
        self.seq, self.t, self.labels = seq, t0, []

    def feed(self, n: int, still: bool, departed: bool | None = None) -> list[int]:
        out = []
        for _ in range(n):
            out.append(self.seq.step(self.t, still, departed))
            self.t += 1.0 / RATE_HZ
        self.labels.extend(out)
        return out

    def kinds(self) -> list[str]:
        return [e.kind for e in self.seq.pop_events()]


def _started(mode: Mode, plan: PosePlan | None = None) -> tuple[PoseSequencer, Feeder]:
    seq = PoseSequencer(plan or _plan(), mode)
    return seq, Feeder(seq)


def test_service_mode_records_exactly_n_samples_per_pose_and_waits_for_motion_after_an_early_trigger():
    seq, f = _started(Mode.SERVICE)
    assert f.feed(5, False) == [-1] * 5 and seq.phase is Phase.WAIT_STILL
    labels = f.feed(30, True)
    assert labels[:10] == [0] * 10 and labels[10:] == [-1] * 20
    assert seq.phase is Phase.RECORDED
    assert "recorded" in f.kinds()
    ok, msg = seq.request_next()  # operator pressed before turning the table
    assert ok and "move the table" in msg and seq.phase is Phase.WAIT_MOTION and seq.index == 1
    assert f.feed(50, True) == [-1] * 50, "the old orientation must never be recorded as the new pose"
    f.feed(20, False)
    assert seq.phase is Phase.WAIT_STILL
    assert f.feed(10, True) == [1] * 10 and seq.phase is Phase.RECORDED
    f.feed(10, False)  # operator turns first, then presses
    ok, _ = seq.request_next()
    assert ok and seq.phase is Phase.WAIT_STILL and seq.index == 2
    assert f.feed(12, True)[:10] == [2] * 10
    assert seq.phase is Phase.DONE and seq.finished
    assert [f.labels.count(k) for k in range(3)] == [10, 10, 10]
    assert seq.request_next()[0] is False
    assert [p["samples"] for p in seq.summary()] == [10, 10, 10]


def test_service_mode_refuses_a_trigger_before_the_pose_is_recorded():
    seq, f = _started(Mode.SERVICE)
    f.feed(4, True)
    ok, msg = seq.request_next()
    assert not ok and "not recorded yet: 4/10 samples" in msg
    assert seq.index == 0 and seq.phase is Phase.RECORDING


def test_service_mode_loss_of_stillness_at_the_pose_pauses_and_resumes_the_count():
    seq, f = _started(Mode.SERVICE)
    f.feed(6, True, departed=False)
    f.feed(3, False, departed=False)  # a knock: the signal stays at the pose's level
    events = seq.pop_events()
    assert any(e.kind == "paused" and "6/10" in e.message for e in events)
    assert seq.phase is Phase.WAIT_STILL and seq.samples_recorded(0) == 6
    f.feed(10, True, departed=False)
    assert f.labels.count(0) == 10 and seq.phase is Phase.RECORDED


def test_service_mode_table_moved_before_the_pose_was_recorded_closes_it_short():
    seq, f = _started(Mode.SERVICE)
    f.feed(6, True, departed=False)
    f.feed(3, False, departed=False)
    f.feed(5, False, departed=True)  # paused, then the signal leaves the pose: the operator turned the table
    assert any(e.kind == "short" and e.warning for e in seq.pop_events())
    assert seq.phase is Phase.RECORDED and seq.summary()[0]["closed_short"]
    assert f.feed(20, True, departed=True) == [-1] * 20, "nothing recorded until the operator triggers"
    ok, _ = seq.request_next()
    assert ok and seq.phase is Phase.WAIT_STILL and seq.index == 1  # motion already seen
    assert f.feed(10, True, departed=False) == [1] * 10


def test_auto_mode_detector_false_alarm_at_a_pose_neither_advances_nor_mislabels():
    seq, f = _started(Mode.AUTO)
    f.feed(5, True, departed=False)
    f.feed(2, False, departed=False)  # false alarm during recording
    f.feed(20, True, departed=False)
    assert seq.index == 0 and seq.samples_recorded(0) == 10 and seq.phase is Phase.RECORDED
    f.feed(3, False, departed=False)  # false alarm after recording: the table has not left
    assert seq.index == 0 and seq.phase is Phase.RECORDED
    f.feed(5, False, departed=True)
    assert seq.index == 1 and seq.phase is Phase.WAIT_STILL


def test_auto_mode_advances_on_motion_and_records_the_next_still_pose():
    seq, f = _started(Mode.AUTO)
    f.feed(40, True)
    assert seq.phase is Phase.RECORDED and seq.index == 0
    f.feed(30, False)  # table turning
    assert seq.index == 1 and seq.phase is Phase.WAIT_STILL
    f.feed(40, True)
    f.feed(30, False)
    f.feed(40, True)
    assert seq.phase is Phase.DONE
    assert [f.labels.count(k) for k in range(3)] == [10, 10, 10]
    labels = np.array(f.labels)
    assert np.all(labels[40:70] == -1), "moving samples carry no pose"


@pytest.mark.parametrize("mode", [Mode.AUTO, Mode.SERVICE])
def test_stillness_held_since_the_previous_pose_is_not_taken_for_stillness_at_the_next(mode):
    """The table leaves pose 0 slowly: the signal departs from the pose's level while the detector still
    reports the stillness it has held since pose 0. That verdict must not record pose 1 (it did, at once:
    the run fell out of step); only a still run that starts after the motion was seen counts."""
    seq, f = _started(mode)
    f.feed(20, True, departed=False)
    assert seq.phase is Phase.RECORDED
    if mode is Mode.SERVICE:
        assert seq.request_next()[0] and seq.phase is Phase.WAIT_MOTION
    assert f.feed(60, True, departed=True) == [-1] * 60, "recorded during the move on the old pose's stillness"
    assert seq.index == 1 and seq.phase is Phase.WAIT_STILL and seq.stillness_stale
    f.feed(3, False, departed=True)  # the detector restarts (the recorder resets it) or sees the move
    assert not seq.stillness_stale
    assert f.feed(10, True, departed=True) == [1] * 10


def test_auto_mode_advances_on_the_dwell_time_when_the_plan_expects_no_visible_change():
    # a turn about the vertical (psi at theta = 0) does not change gravity in the sensor frame
    plan = _plan([{"psi_deg": 0, "theta_deg": 0}, {"psi_deg": 90, "theta_deg": 0}], dwell=1.0, move=0.5)
    seq = PoseSequencer(plan, Mode.AUTO)
    assert not seq.expects_motion(0)
    f = Feeder(seq)
    f.feed(5, False)
    labels = f.feed(300, True)
    first_still = 5
    due = first_still + int((1.0 + 0.5) * RATE_HZ)  # still since sample 5, + dwell + move
    pose1 = [i + 5 for i, v in enumerate(labels) if v == 1]
    assert len(pose1) == 10 and pose1[0] in (due, due + 1)
    assert seq.phase is Phase.DONE


def test_auto_mode_warns_once_when_the_table_is_late_and_keeps_waiting():
    seq, f = _started(Mode.AUTO, _plan(dwell=1.0, move=0.5))
    f.feed(400, True)
    late = [e for e in seq.pop_events() if e.kind == "late"]
    assert len(late) == 1 and late[0].warning and seq.index == 0
    f.feed(10, False)
    f.feed(20, True)
    assert seq.index == 1 and seq.samples_recorded(1) == 10


def test_auto_mode_closes_a_pose_short_when_the_table_leaves_during_recording():
    seq, f = _started(Mode.AUTO)
    f.feed(4, True)
    f.feed(5, False)
    short = [e for e in seq.pop_events() if e.kind == "short"]
    assert short and short[0].warning and "4/10" in short[0].message
    assert seq.index == 1 and seq.phase is Phase.WAIT_STILL
    assert seq.summary()[0]["closed_short"] is True
    f.feed(15, True)
    assert seq.samples_recorded(1) == 10


def test_auto_mode_not_still_within_dwell_warns():
    seq, f = _started(Mode.AUTO, _plan(dwell=1.0, move=0.5))
    f.feed(200, False)
    assert [e.kind for e in seq.pop_events() if e.warning] == ["not_still"]


def test_auto_mode_trigger_skips_the_current_pose():
    seq, f = _started(Mode.AUTO)
    f.feed(3, False)
    ok, _ = seq.request_next()
    assert ok and seq.index == 1
    assert any(e.kind == "skipped" for e in seq.pop_events())
    f.feed(12, True)
    assert seq.samples_recorded(0) == 0 and seq.samples_recorded(1) == 10


@pytest.mark.parametrize("skip_in", [Phase.RECORDED, Phase.RECORDING])
def test_auto_mode_skip_with_the_table_still_at_the_old_pose_waits_for_motion(skip_in):
    """The documented reaction to "table late" is next_pose, pressed while the table is still at pose k. The
    skip used to take the stillness held at pose k for pose k+1 (2 g away here): pose k+1 recorded at once at
    pose k's orientation, every later pose shifted by one. After a skip with the sensor still, pose k+1 is
    recorded only after the table has been seen moving, as service mode's wait_motion."""
    seq = PoseSequencer(_plan([{"name": "z_up", "psi_deg": 0, "theta_deg": 0, "dwell_s": 4.0},
                               {"name": "z_down", "psi_deg": 0, "theta_deg": 180},
                               {"name": "x_up", "psi_deg": 90, "theta_deg": 90}], dwell=3.0, move=2.0), Mode.AUTO)
    f = Feeder(seq)
    if skip_in is Phase.RECORDED:
        f.feed(700, True)  # recorded, then late: dwell 4 s + move 2 s passed, the table never left
        assert seq.phase is Phase.RECORDED and "late" in f.kinds()
    else:
        f.feed(4, True)
        assert seq.phase is Phase.RECORDING
    ok, _ = seq.request_next()
    assert ok and seq.index == 1 and seq.phase is Phase.WAIT_MOTION
    labels = f.feed(50, True)  # the table is still where it was: at pose 0
    assert seq.samples_recorded(1) == 0, f"{labels.count(1)} samples at pose 0's orientation recorded as pose 1"
    f.feed(30, False)  # now the table turns
    f.feed(20, True)
    assert seq.samples_recorded(1) == 10


def test_abort_stops_labelling():
    seq, f = _started(Mode.SERVICE)
    f.feed(3, True)
    seq.abort("test")
    assert seq.phase is Phase.ABORTED and f.feed(20, True) == [-1] * 20
    assert seq.request_next()[0] is False


def test_board_clock_reset_adds_no_time_and_keeps_deadlines():
    plan = _plan([{"psi_deg": 0, "theta_deg": 0}, {"psi_deg": 90, "theta_deg": 0}], dwell=1.0, move=0.5)
    seq = PoseSequencer(plan, Mode.AUTO)
    f = Feeder(seq, t0=1000.0)
    f.feed(50, True)  # 0.5 s of the 1.5 s to the timed advance
    f.t = 0.0  # board reboots: its clock restarts
    f.feed(90, True)  # 0.9 s more: 1.4 s < 1.5 s
    assert seq.index == 0
    f.feed(20, True)
    assert seq.index == 1


def test_status_reports_progress():
    seq = PoseSequencer(_plan(samples=10), Mode.SERVICE)
    Feeder(seq).feed(4, True)
    st = seq.status()
    assert (st.pose_index, st.pose_count, st.pose_name, st.samples, st.samples_target, st.still) == (0, 3, "z_up", 4, 10, True)
    assert st.phase is Phase.RECORDING and st.total_samples == 4 and st.poses_recorded == 0


@pytest.mark.parametrize("mode", [Mode.AUTO, Mode.SERVICE])
def test_with_the_static_detector_on_a_synthetic_signal_only_static_samples_of_the_right_pose_are_labelled(mode):
    """Psi moves between three levels through ramps; the monitor + sequencer must label each pose's
    samples only while Psi sits at that pose's value."""
    rng = np.random.default_rng(1)
    plan = _plan(samples=50, dwell=3.0, move=1.0)
    levels = np.array([[1.20, 1.75, 1.25], [1.32, 1.75, 1.13], [1.20, 1.75, 1.01]])  # Psi at the three poses
    sigma = 1e-3
    parts, truth = [], []
    for k, lev in enumerate(levels):
        parts.append(np.repeat(lev[None], 300, axis=0))
        truth += [k] * 300
        if k + 1 < len(levels):
            ramp = np.linspace(lev, levels[k + 1], 100)
            parts.append(ramp)
            truth += [-1] * 100
    psi = np.vstack(parts) + rng.normal(0, sigma, (sum(len(p) for p in parts), 3))
    truth = np.array(truth)
    monitor = StillnessMonitor(first_order_noise_floor(np.full(3, sigma), 0.0, 10), window=10, hold=20,
                               run_samples=len(psi))
    seq = PoseSequencer(plan, mode)
    labels = []
    for i, row in enumerate(psi):
        labels.append(seq.step(i / RATE_HZ, monitor.update(row)))
        if mode is Mode.SERVICE and seq.phase is Phase.RECORDED and truth[i] == -1:
            assert seq.request_next()[0]  # operator presses while the table turns
    labels = np.array(labels)
    assert seq.phase is Phase.DONE
    for k in range(3):
        idx = np.flatnonzero(labels == k)
        assert len(idx) == 50
        assert np.all(truth[idx] == k), f"pose {k} samples taken outside the pose"



# ------------------------------------------------------------------ progress display
def test_progress_line_shows_pose_stillness_samples_and_temperature():
    from fbg_accel_calibration.recorder.progress_display import format_progress

    seq = PoseSequencer(_plan(samples=10), Mode.SERVICE)
    Feeder(seq).feed(5, True)
    line = format_progress(seq.status(), 24.314, setpoint_c=24.0, bar_width=10)
    assert line.startswith("pose 1/3 z_up | recording | STILL | 5/10 [#####.....]")
    assert "24.31 degC (set 24)" in line
    assert "--.-- degC" in format_progress(seq.status(), float("nan"))


def test_progress_line_after_a_recorded_pose_asks_the_operator_only_in_service_mode():
    """In auto mode nobody is asked anything after a pose is recorded: the run advances when the table moves.

    Found in a simulated six-position campaign (auto mode, 2026-11-26): every pose's progress line read
    ``recorded, next pose?`` for the rest of its 30 s dwell, as if the operator had to press ``next_pose``.
    """
    from fbg_accel_calibration.recorder.progress_display import format_progress

    for mode, phrase in ((Mode.SERVICE, "| recorded, next pose? |"),
                         (Mode.AUTO, "| recorded, advancing when the table moves |")):
        seq = PoseSequencer(_plan(samples=10), mode)
        Feeder(seq).feed(12, True)
        assert str(seq.status().phase) == "recorded"
        assert phrase in format_progress(seq.status(), 24.0), (mode, format_progress(seq.status(), 24.0))


def test_progress_display_plain_text_when_not_a_tty_only_on_change():
    import io

    from fbg_accel_calibration.recorder.progress_display import ProgressDisplay

    now = [0.0]
    out = io.StringIO()
    disp = ProgressDisplay(out, clock=lambda: now[0], plain_interval_s=10.0)
    assert not disp.is_tty
    seq, f = _started(Mode.SERVICE, _plan(samples=10))
    written = []
    for _ in range(8):  # phase changes once (wait_still -> recording), then 7 quiet samples
        f.feed(1, True)
        now[0] += 0.01
        written.append(disp.update(seq.status(), 20.0))
    assert written == [True] + [False] * 7
    now[0] += 10.0
    assert disp.update(seq.status(), 20.0)  # periodic line
    disp.event(seq.pop_events()[0])
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text
    assert text.count("\n") == 3


def test_progress_display_redraws_in_place_on_a_tty():
    import io

    from fbg_accel_calibration.recorder.progress_display import ProgressDisplay

    now = [0.0]
    out = io.StringIO()
    disp = ProgressDisplay(out, is_tty=True, clock=lambda: now[0], tty_interval_s=0.1)
    seq = PoseSequencer(_plan(samples=10), Mode.SERVICE)
    Feeder(seq).feed(2, True)
    assert disp.update(seq.status(), 20.0)
    assert not disp.update(seq.status(), 20.0)
    now[0] = 0.2
    assert disp.update(seq.status(), 20.0)
    disp.message("note")
    disp.close()
    assert out.getvalue().count("\r\x1b[2K") == 2 and out.getvalue().endswith("note\n")
