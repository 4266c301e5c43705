"""Searches side by side (``search_lanes``) and the diagnosis run on two lanes (issue 8 §7).

The lanes must change when the diagnosis is done, never what it finds: the same report, the same numbers to the last
bit, with one lane or two. The unit tests use events, not sleeps, to make the tasks finish out of order.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_diagnose_sim import THERMAL, _config

from fbg_accel_calibration.commands.cli import main
from fbg_accel_calibration.diagnosis.diagnose import diagnose
from fbg_accel_calibration.diagnosis.search import Evaluator
from fbg_accel_calibration.diagnosis.search_lanes import Lanes, beside, idle_lanes
from fbg_accel_calibration.fit.thermal_fit import NotIdentifiedError
from fbg_accel_calibration.io.mcap_writer import write_recording
from fbg_accel_calibration.reports.diagnose_report import markdown
from fbg_accel_sim.board_physics import simulate_recording


class Lane:
    """A lane that notes whether two tasks ever hold it at once."""

    def __init__(self) -> None:
        self.busy = False
        self.shared = False

    def __enter__(self) -> Lane:
        self.shared |= self.busy
        self.busy = True
        return self

    def __exit__(self, *exc: object) -> None:
        self.busy = False


def test_the_results_come_in_the_order_of_the_tasks_whatever_order_they_finish_in() -> None:
    lanes = [Lane(), Lane()]
    second_done = threading.Event()
    finished: list[int] = []

    def task(lane: Lane, i: int) -> tuple[int, int]:
        with lane:
            if i == 0:  # the first task ends only once the second has: they run side by side
                assert second_done.wait(30.0), "the second task never ran beside the first"
            finished.append(i)
            if i == 1:
                second_done.set()
            return i, threading.get_ident()

    seen: list[int] = []
    out = Lanes(lanes).map(task, range(6), done=lambda r: seen.append(r[0]))
    assert [i for i, _ in out] == list(range(6)) and seen == list(range(6))
    assert finished.index(1) < finished.index(0)
    assert threading.get_ident() not in {t for _, t in out}
    assert not any(lane.shared for lane in lanes)


def test_the_costliest_tasks_start_first_and_the_results_keep_the_items_order() -> None:
    """With ``cost``, the two lanes start the two costliest tasks first (without it, the first two items); the results
    and the ``done`` calls stay in the items' order."""
    started: list[int] = []
    lock = threading.Lock()
    both_started = threading.Barrier(2, timeout=30)

    def task(lane: Lane, item: int) -> int:
        with lock:
            started.append(item)
            first = len(started) <= 2
        if first:  # no lane takes a third task before the first two have both started
            both_started.wait()
        return 10 * item

    for cost, first_two in ((None, {0, 1}), ({0: 1.0, 1: 3.0, 2: 2.0, 3: 0.0}.get, {1, 2})):
        started.clear()
        both_started.reset()
        seen: list[int] = []
        out = Lanes([Lane(), Lane()]).map(task, range(4), seen.append, cost=cost)
        assert out == seen == [0, 10, 20, 30]
        assert set(started[:2]) == first_two, started


def test_one_lane_runs_the_tasks_in_the_callers_thread_in_order() -> None:
    order: list[int] = []
    out = Lanes([Lane()]).map(lambda lane, i: (order.append(i), threading.get_ident())[1], range(4))
    assert order == [0, 1, 2, 3] and set(out) == {threading.get_ident()}


def test_a_failed_task_is_raised_once_every_task_has_ended() -> None:
    ended: list[int] = []
    seen: list[int] = []

    def task(lane: Lane, i: int) -> int:
        if i == 1:
            raise ValueError("task 1")
        ended.append(i)
        return i

    with pytest.raises(ValueError, match="task 1"):
        Lanes([Lane(), Lane()]).map(task, range(5), done=seen.append)
    assert sorted(ended) == [0, 2, 3, 4] and seen == [0]  # no result after the failed one is handed on


def test_idle_lanes_are_lent_between_maps_and_never_while_a_task_waits_for_one() -> None:
    """Outside a map nothing is lent; in ``lending`` the caller works on the first lane and is lent the others until
    its block ends; in a map, a task is lent no lane while a task of the map has not started."""
    with idle_lanes(5) as lent:
        assert lent == []
    lanes = Lanes([Lane(), Lane(), Lane()])
    with lanes.lending() as first:
        assert first is lanes.lanes[0]
        with idle_lanes(5) as lent:
            assert lent == lanes.lanes[1:]
        with idle_lanes(1) as lent:  # given back at the end of the block before
            assert lent == [lanes.lanes[1]]
    with idle_lanes(5) as lent:
        assert lent == []
    second_done = threading.Event()

    def task(lane: Lane, item: int) -> int:
        if item == 0:  # item 2 waits for a lane until item 0 or 1 ends; item 1 ends only after this check
            with idle_lanes(2) as lent:
                got = len(lent)
            second_done.set()
            return got
        if item == 1:
            second_done.wait()
        return 0

    assert Lanes([Lane(), Lane()]).map(task, range(3))[0] == 0


class CvLane:
    """A lane whose ``cv`` of a spec (a string) returns (the spec, the thread it ran on); "singular" is not identified,
    "boom" fails."""

    def __init__(self) -> None:
        self.done: list[str] = []

    def cv(self, spec: str) -> tuple[str, int]:
        self.done.append(spec)
        if spec == "singular":
            raise NotIdentifiedError("singular design")
        if spec == "boom":
            raise ValueError("boom")
        return spec, threading.get_ident()


def test_a_batch_of_trials_runs_on_the_lent_lanes_and_is_used_in_order() -> None:
    """``Evaluator.cv_each`` with two lanes lent: every spec worked out once, some on the lent lanes' threads, the results
    (a NotIdentifiedError as a value) used in the specs' order; a failure on a lent lane is raised and the lanes are
    given back."""
    lanes = Lanes([CvLane(), CvLane(), CvLane()])
    specs = [f"s{k}" for k in range(7)] + ["singular", "s8"]
    used: list[tuple[int, object]] = []
    with lanes.lending() as first:
        Evaluator.cv_each(first, specs, lambda k, r: used.append((k, r)))
        with idle_lanes(5) as lent:
            assert lent == lanes.lanes[1:]  # given back
    assert [k for k, _ in used] == list(range(len(specs)))
    assert [r[0] for _, r in used if not isinstance(r, NotIdentifiedError)] == [s for s in specs if s != "singular"]
    assert isinstance(used[7][1], NotIdentifiedError)
    assert sorted(spec for lane in lanes.lanes for spec in lane.done) == sorted(specs)
    assert all(lane.done for lane in lanes.lanes[1:])
    threads = {r[1] for _, r in used if not isinstance(r, NotIdentifiedError)}
    assert threading.get_ident() in threads and len(threads) >= 2  # the caller's and the lent lanes' own
    with lanes.lending() as first:
        with pytest.raises(ValueError, match="boom"):
            Evaluator.cv_each(first, ["s0", "boom", "s2"], lambda k, r: None)
        with idle_lanes(5) as lent:
            assert lent == lanes.lanes[1:]
    with idle_lanes(5) as lent:  # without lending nothing is lent: the specs run in the caller's thread
        assert lent == []


def test_work_beside_runs_on_its_own_thread_and_hands_back_its_result_or_error() -> None:
    here = threading.get_ident()
    assert beside(threading.get_ident).result() != here
    assert beside(threading.get_ident, thread=False).result() == here
    for thread in (True, False):
        with pytest.raises(ZeroDivisionError):
            beside(lambda: 1 / 0, thread=thread).result()


# A temperature-cycled run (test_diagnose_sim's THERMAL case, 503 s at 25 Hz) with the TIA low-pass, a thermal lag and a
# hysteresis: the diagnosis goes through every part that runs on lanes (the candidates, the confounding checks, the step
# check of the hysteresis, the degree chosen again)
THERMAL_EFFECTS = _config({**THERMAL, "effects.tia_lowpass.scale": 1.0, "effects.thermal_lag.scale": 0.25,
                           "effects.thermal_hysteresis.scale": 10.0})


@pytest.mark.parametrize("search_rows", [None, 4000], ids=["every-sample", "thinned"])
def test_the_diagnosis_on_two_lanes_is_the_diagnosis_on_one(search_rows: int | None) -> None:
    rec = simulate_recording(THERMAL_EFFECTS, seed=1)
    one, two = (diagnose(rec, lanes=n, search_rows=search_rows) for n in (1, 2))
    assert sum(len(st.confounding) for st in one.steps) > 0 and any(
        c.step_check is not None for st in one.steps for c in st.candidates), "the case no longer reaches every part"
    assert markdown(two) == markdown(one)
    for a, b in zip(one.steps, two.steps, strict=True):
        assert [(c.name, c.rel_gain, c.p_value, c.hyper, c.detail) for c in a.candidates] == \
            [(c.name, c.rel_gain, c.p_value, c.hyper, c.detail) for c in b.candidates]
    for field in ("M", "b"):
        assert np.array_equal(getattr(one.calibration, field), getattr(two.calibration, field))
    assert np.array_equal(one.residual_after, two.residual_after, equal_nan=True)


# The command's plumbing of --lanes, on a grid run (167 s at 100 Hz) with the TIA low-pass: its candidates are searched
# and judged on the lanes like any campaign's; every part of the diagnosis on lanes is the test above's
GRID_EFFECT = _config({"effects.tia_lowpass.scale": 1.0})


def test_the_command_s_lanes_option_changes_nothing_it_writes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mcap = tmp_path / "run.mcap"
    write_recording(mcap, simulate_recording(GRID_EFFECT, seed=2))
    outputs = []
    for n in ("1", "2"):
        (tmp_path / n).mkdir()
        rc = main(["diagnose", str(mcap), "--lanes", n, "--out", str(tmp_path / n / "r.md"),
                   "--yaml", str(tmp_path / n / "c.yaml")])
        assert rc == 0
        report = (tmp_path / n / "r.md").read_text().replace(f"--lanes {n}", "")
        cal = yaml.safe_load((tmp_path / n / "c.yaml").read_text())
        cal.pop("created")  # the time it was written
        outputs.append([text.replace(str(tmp_path / n), "") for text in (capsys.readouterr().out, report)] + [cal])
    assert outputs[0] == outputs[1]
