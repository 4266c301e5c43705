"""Pose sequencer of a calibration run: a pure state machine, no ROS, no clock of its own.

The calibration node feeds it one call per board sample, ``step(t_s, still)``, where ``t_s`` is
the board time (s) and ``still`` the verdict of the static-interval detector
(``fbg_accel_calibration.fit.static_detector``) on the signal itself. The sequencer answers with
the pose id of that sample: the index of the plan's pose when the sample is one of the N samples
recorded for that pose, else -1 (moving, settling, waiting). Operator commands arrive through
``request_next()`` (the ``calibration/next_pose`` Trigger service) and ``abort()``.

Per pose k (``Phase``)::

    WAIT_STILL --still--> RECORDING --N still samples--> RECORDED --advance--> WAIT_STILL (k+1)
                              | motion                        (last pose: DONE)
                              v
        service mode: back to WAIT_STILL(k), the count is kept (the samples were static at pose k)
        auto mode:    the table has left: pose k is closed short (warning), on to pose k+1

A "still" verdict counts only if its run of still verdicts began after the table was last seen leaving
a pose (``stillness_stale``): a slow move departs from the pose's level before the detector's variance
notices it, and the stillness it still holds is the previous pose's (the caller restarts its detector).

Advancing from RECORDED:

* service mode (operator): on ``request_next()``. If the plan says the gravity vector changes
  between pose k and k+1 (by more than ``motion_expect_g`` g) and no motion has been seen since
  pose k was recorded, the sequencer first waits for motion (``WAIT_MOTION``), so a trigger
  pressed before the table is turned never records the old orientation as the new pose.
* auto mode: on motion (the table leaving pose k). When the plan expects no visible change
  (e.g. a turn about the vertical), on time: at ``t_still_k + dwell_k + move_s``, i.e. once the
  table, following the same plan, must already be at pose k+1. The plan's dwell is also the bound
  for the warnings "pose not still within its dwell" and "table late" (the sequencer then keeps
  waiting; ``request_next()`` in auto mode skips the pose). A skip while the sensor is still and the
  plan expects motion to the next pose waits for motion too (``WAIT_MOTION``): the operator skips
  because the table is late, i.e. still at the old pose, which must not be recorded as the next one.

Time is the board clock; a backwards or > ``MAX_TIME_STEP_S`` jump (board reset) adds no time,
so deadlines survive a reset of the board clock.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from .pose_plan import Pose, PosePlan

MAX_TIME_STEP_S = 5.0  # s; a larger forward jump of the board clock is treated as a clock reset
DEFAULT_MOTION_EXPECT_G = 0.1  # g; a pose change of less than 0.1 g (~5.7 deg tilt) may be invisible to the detector


class Mode(enum.StrEnum):
    AUTO = "auto"
    SERVICE = "service"


class Phase(enum.StrEnum):
    WAIT_STILL = "wait_still"  # at (or moving to) pose k, waiting for the detector to report still
    RECORDING = "recording"  # still at pose k, counting its samples
    RECORDED = "recorded"  # pose k complete, waiting for the advance (trigger or table motion)
    WAIT_MOTION = "wait_motion"  # operator asked for pose k (=next); waiting to see the table move there
    DONE = "done"
    ABORTED = "aborted"


@dataclass(frozen=True)
class SequencerEvent:
    """Something an operator should see: ``kind`` is a short tag, ``warning`` marks problems."""

    t_s: float
    kind: str
    pose_index: int
    message: str
    warning: bool = False


@dataclass(frozen=True)
class SequencerStatus:
    """Snapshot for the progress display."""

    pose_index: int  # 0-based index of the current pose
    pose_count: int
    pose_name: str
    phase: Phase
    samples: int  # samples recorded for the current pose
    samples_target: int
    still: bool
    poses_recorded: int
    total_samples: int
    auto: bool = False  # auto mode: the run advances on table motion / dwell times, the operator is not asked


@dataclass
class _PoseLog:
    samples: int = 0
    t_first_still: float | None = None  # elapsed time when the pose was first still
    closed_short: bool = False


@dataclass
class PoseSequencer:
    """State machine of one run over ``plan`` in ``mode`` (see the module docstring)."""

    plan: PosePlan
    mode: Mode = Mode.SERVICE
    motion_expect_g: float = DEFAULT_MOTION_EXPECT_G
    phase: Phase = field(default=Phase.WAIT_STILL, init=False)
    index: int = field(default=0, init=False)
    events: list[SequencerEvent] = field(default_factory=list, init=False)

    def __post_init__(self) -> None:
        self.mode = Mode(self.mode)
        self._logs = [_PoseLog() for _ in self.plan.poses]
        self._elapsed = 0.0  # s of board time since the first sample, robust to clock resets
        self._t_prev: float | None = None
        self._t_now = float("nan")  # board time of the last sample (for event stamps)
        self._still = False
        self._motion_since_recorded = False
        self._stale = False  # the detector's current still run began before motion away from a pose was seen
        self._phase_since = 0.0  # elapsed time when the current phase began
        self._warned: set[tuple[int, str]] = set()
        self._total = 0

    # ------------------------------------------------------------------ queries
    @property
    def finished(self) -> bool:
        return self.phase in (Phase.DONE, Phase.ABORTED)

    @property
    def pose(self) -> Pose:
        return self.plan.poses[self.index]

    @property
    def stillness_stale(self) -> bool:
        """True while the detector's current "still" began before the table was last seen leaving a pose
        (a slow move departs from the pose's level long before the window variance notices it): that
        verdict belongs to the previous pose and is not accepted as stillness at the next one. The
        caller restarts its detector (``StillnessMonitor.reset``) so stillness is re-established from
        samples after the motion; any "not still" verdict does the same."""
        return not self.finished and self._stale

    def samples_recorded(self, index: int) -> int:
        return self._logs[index].samples

    def expects_motion(self, index: int) -> bool:
        """True if the plan's gravity changes by more than ``motion_expect_g`` between pose ``index`` and the next."""
        if index + 1 >= len(self.plan.poses):
            return False
        g = self.plan.poses
        delta = float(np.linalg.norm(g[index + 1].gref_mps2 - g[index].gref_mps2))
        return delta > self.motion_expect_g * self.plan.local_g_mps2

    def status(self) -> SequencerStatus:
        p = self.pose
        return SequencerStatus(
            pose_index=self.index, pose_count=len(self.plan.poses), pose_name=p.name, phase=self.phase,
            samples=self._logs[self.index].samples, samples_target=p.samples, still=self._still,
            poses_recorded=sum(1 for i, log in enumerate(self._logs) if log.samples >= self.plan.poses[i].samples),
            total_samples=self._total, auto=self.mode is Mode.AUTO,
        )

    def pop_events(self) -> list[SequencerEvent]:
        out, self.events = self.events, []
        return out

    def summary(self) -> list[dict]:
        """Per pose: name, samples recorded, target, whether it was closed short."""
        return [{"index": p.index, "name": p.name, "samples": log.samples, "target": p.samples,
                 "closed_short": log.closed_short} for p, log in zip(self.plan.poses, self._logs, strict=True)]

    # ------------------------------------------------------------------ inputs
    def step(self, t_s: float, still: bool, departed: bool | None = None) -> int:
        """Feed one sample; returns its pose id or -1.

        ``t_s`` board time (s); ``still`` the static detector's verdict; ``departed`` whether the signal
        has left the level of the current (or last recorded) pose, i.e. the table really moved (None:
        unknown, then any loss of stillness counts as motion). With ``departed`` given, a brief loss of
        stillness at the pose (a detector false alarm, a knock) only pauses the recording.
        """
        self._advance_clock(float(t_s))
        self._still = bool(still)
        if not still:
            self._stale = False  # a new still run starts after this sample
        moved = (not still) if departed is None else bool(departed)
        if self.finished:
            return -1
        if self.phase is Phase.WAIT_MOTION:
            if moved:
                self._mark_motion()
                self._emit("moving", f"table moving to pose {self.index} ({self.pose.name})")
                self._set_phase(Phase.WAIT_STILL)
            return -1
        if self.phase is Phase.WAIT_STILL:
            if self._logs[self.index].samples > 0 and departed:  # paused pose: the table left it
                return self._left_during_recording()
            if not still or self.stillness_stale:
                self._check_still_bound()
                return -1
            log = self._logs[self.index]
            if log.t_first_still is None:
                log.t_first_still = self._elapsed
            verb = "resuming" if log.samples else "recording"
            self._emit("still", f"pose {self.index} ({self.pose.name}) still, {verb}")
            self._set_phase(Phase.RECORDING)
            return self._count()
        if self.phase is Phase.RECORDING:
            if still:
                return self._count()
            if moved:
                return self._left_during_recording()
            log = self._logs[self.index]
            self._emit("paused", f"pose {self.index} ({self.pose.name}): stillness lost at the pose after {log.samples}/"
                       f"{self.pose.samples} samples (table still there); pausing")
            self._set_phase(Phase.WAIT_STILL)
            return -1
        # RECORDED
        if moved and not self._motion_since_recorded:
            self._mark_motion()
            self._motion_since_recorded = True
        if self.mode is Mode.AUTO:
            if self._motion_since_recorded:
                self._advance(f"table left pose {self.index}")
            else:
                self._check_timed_advance()
        return -1

    def request_next(self) -> tuple[bool, str]:
        """Operator's ``next_pose`` trigger; returns (accepted, message for the service response)."""
        if self.finished:
            return False, f"run is {self.phase.value}; nothing to advance"
        log = self._logs[self.index]
        target = self.pose.samples
        if self.mode is Mode.SERVICE:
            if self.phase in (Phase.WAIT_STILL, Phase.RECORDING):
                return False, (f"pose {self.index} ({self.pose.name}) not recorded yet: {log.samples}/{target} samples; "
                               "wait until it is recorded (or call calibration/abort)")
            if self.phase is Phase.WAIT_MOTION:
                return False, f"already waiting for the table to move to pose {self.index} ({self.pose.name})"
            self._advance("operator trigger")
            return True, self._next_message()
        # auto mode: the trigger skips ahead. The operator presses it when the table is late, i.e. still at
        # pose k: if the table is still now and the plan expects motion to pose k+1, pose k+1 is recorded only
        # after the table has been seen moving (WAIT_MOTION), as in service mode; else the old orientation
        # would be recorded as pose k+1 and every later pose shifted by one
        hold = self._still and self.expects_motion(self.index) and not self._motion_since_recorded
        if self.phase in (Phase.WAIT_STILL, Phase.RECORDING):
            log.closed_short = log.samples < target
            self._emit("skipped", f"pose {self.index} ({self.pose.name}) skipped by operator with {log.samples}/{target} "
                       "samples", warning=log.samples < target)
            if self.index + 1 >= len(self.plan.poses):
                self._finish()
                return True, "last pose skipped; run complete"
        self._advance("operator trigger", wait_motion=hold)
        return True, self._next_message()

    def retract(self, index: int, n: int, why: str) -> None:
        """Take back the last ``n`` samples counted for pose ``index`` (they turn out not to belong to it: taken
        after the table began to leave, or never written); a pose left below its target is closed short."""
        log = self._logs[index]
        n = min(int(n), log.samples)
        if n <= 0:
            return
        log.samples -= n
        self._total -= n
        if log.samples < self.plan.poses[index].samples:
            log.closed_short = True
        pose = self.plan.poses[index]
        self.events.append(SequencerEvent(self._t_now, "retracted", index, f"pose {index} ({pose.name}): {n} sample(s) "
                                          f"taken back ({why}); {log.samples}/{pose.samples} kept", warning=True))

    def abort(self, reason: str = "operator abort", even_if_done: bool = False) -> None:
        """End the run now; ``even_if_done``: also a run whose last pose was just counted (its recording failed)."""
        if not self.finished or (even_if_done and self.phase is Phase.DONE):
            self.phase = Phase.ABORTED
            self._emit("aborted", f"run aborted at pose {self.index} ({self.pose.name}): {reason}", warning=True)

    # ------------------------------------------------------------------ internals
    def _advance_clock(self, t_s: float) -> None:
        if self._t_prev is not None:
            dt = t_s - self._t_prev
            if 0.0 <= dt <= MAX_TIME_STEP_S:
                self._elapsed += dt
        self._t_prev = t_s
        self._t_now = t_s

    def _emit(self, kind: str, message: str, warning: bool = False) -> None:
        self.events.append(SequencerEvent(self._t_now, kind, self.index, message, warning))

    def _warn_once(self, kind: str, message: str) -> None:
        key = (self.index, kind)
        if key not in self._warned:
            self._warned.add(key)
            self._emit(kind, message, warning=True)

    def _mark_motion(self) -> None:
        """The table was seen leaving a pose on this sample: stillness must be re-established after it."""
        self._stale = self._still  # a still run that began before this sample is the previous pose's

    def _set_phase(self, phase: Phase) -> None:
        self.phase = phase
        self._phase_since = self._elapsed

    def _count(self) -> int:
        log = self._logs[self.index]
        log.samples += 1
        self._total += 1
        pose_id = self.index
        if log.samples >= self.pose.samples:
            self._emit("recorded", f"pose {self.index} ({self.pose.name}) recorded: {log.samples} samples")
            if self.index + 1 >= len(self.plan.poses):
                self._finish()
            else:
                self._motion_since_recorded = False
                self._set_phase(Phase.RECORDED)
                if self.mode is Mode.SERVICE:
                    nxt = self.plan.poses[self.index + 1]
                    self._emit("prompt", f"move the table to pose {self.index + 1} ({nxt.name}) and call calibration/next_pose")
        return pose_id

    def _left_during_recording(self) -> int:
        """The table left pose k before its N samples: the samples taken are kept (they were static at
        pose k); the pose is closed short. Auto mode moves on to pose k+1; service mode waits for the
        operator's trigger (who moved the table early)."""
        log = self._logs[self.index]
        log.closed_short = True
        self._emit("short", f"pose {self.index} ({self.pose.name}) left after {log.samples}/{self.pose.samples} samples; "
                   + ("dwell too short for the stillness hold plus the samples?" if self.mode is Mode.AUTO
                      else "the table was moved before the pose was recorded"), warning=True)
        self._mark_motion()
        if self.index + 1 >= len(self.plan.poses):
            self._finish()
            return -1
        self._motion_since_recorded = True
        if self.mode is Mode.AUTO:
            self._advance("table left during recording")
        else:
            self._set_phase(Phase.RECORDED)
            nxt = self.plan.poses[self.index + 1]
            self._emit("prompt", f"call calibration/next_pose for pose {self.index + 1} ({nxt.name})")
        return -1

    def _advance(self, why: str, wait_motion: bool = False) -> None:
        """Go from pose k (recorded or closed) to pose k+1 (``wait_motion``: wait to see the table move first)."""
        expect = self.expects_motion(self.index)
        seen = self._motion_since_recorded
        self.index += 1
        self._motion_since_recorded = False
        if wait_motion or (self.mode is Mode.SERVICE and expect and not seen):
            self._set_phase(Phase.WAIT_MOTION)
            self._emit("advanced", f"{why}: waiting for the table to move to pose {self.index} ({self.pose.name})")
        else:
            self._set_phase(Phase.WAIT_STILL)
            self._emit("advanced", f"{why}: pose {self.index} ({self.pose.name}), waiting for stillness")

    def _next_message(self) -> str:
        if self.phase is Phase.WAIT_MOTION:
            return f"pose {self.index} ({self.pose.name}): move the table; recording starts when it is still again"
        return f"pose {self.index} ({self.pose.name}): recording starts when the sensor is still"

    def _finish(self) -> None:
        self.phase = Phase.DONE
        self._emit("done", f"all {len(self.plan.poses)} poses done, {self._total} samples recorded")

    def _check_still_bound(self) -> None:
        if self.mode is Mode.AUTO and self._elapsed - self._phase_since > self.pose.dwell_s + self.plan.move_s:
            self._warn_once("not_still", f"pose {self.index} ({self.pose.name}) not still within its dwell "
                            f"({self.pose.dwell_s:g} s + move {self.plan.move_s:g} s); still waiting")

    def _check_timed_advance(self) -> None:
        log = self._logs[self.index]
        start = log.t_first_still if log.t_first_still is not None else self._phase_since
        due = start + self.pose.dwell_s + self.plan.move_s
        if self._elapsed < due:
            return
        if not self.expects_motion(self.index):
            self._advance(f"dwell of pose {self.index} over (no visible change expected)")
        else:
            self._warn_once("late", f"table has not left pose {self.index} ({self.pose.name}) "
                            f"{self.pose.dwell_s + self.plan.move_s:g} s after it became still; still waiting")
