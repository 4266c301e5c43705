"""Simulated end to end: board_sim -> driver -> calibration node -> fbg-accel-calib fit -> driver reloads.

Real processes over real DDS (ROS_DOMAIN_ID from the environment), each chain in its own namespace:

1. Three chamber levels (16, 24, 45 degC, paper section 4.5), in parallel: ``board_sim`` runs the six-pose
   plan ``test/fixtures/pose_plan_sim_e2e.yaml`` at the paper's 100 Hz with its chamber at the level, the
   ``driver`` reads its pty and publishes ``imu/raw``, the ``calibration`` node (auto mode) records one
   MCAP per level.
2. ``fbg-accel-calib fit`` fits the three MCAPs into a calibration YAML.
3. Validation on poses held out of the fit (three oblique orientations that are not in the plan), at the
   three levels: new ``board_sim`` runs (a short lead-in pose, then the held-out poses:
   ``validation_plan``), the ``driver`` loads the fitted YAML, the test subscribes to its
   ``imu/data_raw`` and compares with the simulator's truth (matched through ``imu/raw``'s ``seq``). The
   calibrated error (RMS over the settled samples of all held-out poses and levels, per axis) must be within 1.5x the
   noise floor of the simulated sensor's output: the within-pose scatter of the same calibrated output
   (white noise + bias instability + ADC quantisation), itself checked against the simulator's configured
   per-sample noise so that a noisy pipeline cannot pass by inflating its own floor.

What the test does NOT claim. One simulator effect that the paper's model (eq. 28) cannot represent is
switched off here (``MODEL_EXTERNAL_EFFECTS``): the reference dark offset. With it, Psi = counts/ref no
longer cancels the source-power wander (0.7 %, ~120 s), which differs between the calibration runs and the
validation runs; eq. 28 then leaves 1.39x (mean) and up to 1.52x the noise floor on z on held-out poses,
against 1.30x / 1.40x without it (``bench/calibration_node_findings.py``, 3 seeds).
Finding and correcting it is the diagnosis's job (issue 4), not the recorder's. Every other effect stays at
its nominal value (spectral-overlap non-linearity, time drift, thermal hysteresis, noise, ADC, the thermal
chain of source, couplers, photodiodes and gratings, AHT10 offset/noise/lag, TIA low-pass, channel delay).
The temperature degree is chosen by the fit's own cross-validation (no ``--degree``): the simulated
sensor's thermal curvature needs n = 2, the largest that three levels identify (n = 1 leaves 2.2x the noise
floor on y, same bench), and the test asserts that the automatic choice finds it.

Each board starts only once the test's own view of the DDS graph shows its driver and the processes reading that
driver (both ends, as the test sees them), so the plan's first dwell and the validation's lead-in need not cover the
drivers' start-up and discovery; the three chains of each phase start together.

No sleeps as synchronisation: waits are on process output, process exit, the DDS graph or received data, each
with a deadline.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from process_harness import ChildProcess

from fbg_accel_calibration.io.mcap_reader import read_recording
from fbg_accel_calibration.recorder.pose_plan import PosePlan
from fbg_accel_driver.thermal_model import ThermalCalibration

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
PLAN = ROOT / "test" / "fixtures" / "pose_plan_sim_e2e.yaml"
RATE_HZ = 100.0  # paper section 3.5; the noise is low-passed at ~1 Hz (Table 1), a higher rate adds nothing
EXPECTED_DEGREE = 2  # the largest degree three temperature levels identify (see the module docstring)
MODEL_EXTERNAL_EFFECTS = ["reference_dark_offset"]
SIM_SET = [f"effects.{e}.scale=0.0" for e in MODEL_EXTERNAL_EFFECTS]
HELD_OUT = [[45.0, 45.0], [210.0, 120.0], [300.0, 60.0]]  # (psi, theta) deg, none of them in the plan
HELD_OUT_DWELL_S, MOVE_S = 4.0, 0.8  # s; 2.8 s settled: 280 samples per pose and level
# Unchecked first pose of each validation run (z up, 1 s): the board streams from the moment the driver opens the
# pty; the driver and this test's subscriber have matched before the board starts (the test waits for it), so the
# lead-in covers only the first DDS deliveries, not the discovery (~1 s, seconds on a loaded machine).
LEAD_IN = [[0.0, 0.0]]
LEAD_IN_DWELL_S = 1.0
SETTLED_S = 1.2  # s after arrival: the TIA low-pass (Table 1, >= 1 Hz) has settled to far below the noise
NOISE_FACTOR = 1.5

pytestmark = [pytest.mark.real_time, pytest.mark.timeout(240)]


@pytest.fixture()
def procs():
    started: list[ChildProcess] = []
    try:
        yield started
    except BaseException:
        raise
    finally:
        for p in started:
            if p.proc.poll() is None:
                p.proc.kill()
                p.proc.wait(timeout=5)


def dump(procs: list[ChildProcess]) -> str:
    """The last lines of every process (shown with a failure)."""
    return "\n".join(f"----- {p.name} (exit {p.proc.poll()}) -----\n" + "\n".join(p.output().splitlines()[-12:])
                     for p in procs)


def link_path(tmp: Path, tag: str) -> Path:
    """The pty link of chain ``tag``'s board (its driver is started before it and opens it once it appears)."""
    return tmp / f"pty_{tag}"


def start_sim(procs: list[ChildProcess], tmp: Path, tag: str, level_c: float, seed: int, plan: Path) -> ChildProcess:
    """``board_sim`` of chain ``tag`` following the pose plan ``plan`` (not waited for: see ``wait_sims``)."""
    args = [BIN / "board_sim", "--rate", str(RATE_HZ), "--seed", str(seed), "--link", link_path(tmp, tag),
            "--truth", tmp / f"truth_{tag}.npz", "--set", f"scenario.temperature.initial_c={level_c}"]
    for p in [*SIM_SET, "scenario.poses.mode=plan_file", f"scenario.poses.plan_file={plan}"]:
        args += ["--set", p]
    sim = ChildProcess(f"board_sim {tag}", args)
    procs.append(sim)
    return sim


def wait_sims(sims: list[ChildProcess]) -> None:
    for sim in sims:
        sim.wait_line(r"^PTY ", timeout=30)


def start_driver(procs: list[ChildProcess], tmp: Path, tag: str, calibration: Path) -> ChildProcess:
    """The driver of chain ``tag``, started before its board: it retries the missing port every 0.2 s at most."""
    drv = ChildProcess(f"driver {tag}", [BIN / "driver", "--ros-args", "-r", f"__ns:=/{tag}",
                                         "-p", f"port:={link_path(tmp, tag)}", "-p", f"calibration_file:={calibration}",
                                         "-p", "reconnect_backoff_max_s:=0.2"])
    procs.append(drv)
    return drv


def validation_plan(tmp: Path) -> Path:
    """The validation runs' pose plan: the lead-in pose, then the held-out poses (the simulator reads its angles
    and dwells; nothing records it)."""
    poses = [{"name": f"{kind}{i}", "psi_deg": psi, "theta_deg": theta, "dwell_s": dwell}
             for kind, dwell, angles in (("lead_in", LEAD_IN_DWELL_S, LEAD_IN), ("held_out", HELD_OUT_DWELL_S, HELD_OUT))
             for i, (psi, theta) in enumerate(angles)]
    path = tmp / "validation_plan.yaml"
    path.write_text(yaml.safe_dump({"format": "fbg_accel_pose_plan", "format_version": 1, "name": "e2e_validation",
                                    "move_s": MOVE_S, "poses": poses}, sort_keys=False))
    return path


def wait_graph(node, executor, ready, what: str, timeout: float = 60.0) -> None:
    """Spin this test's node until ``ready()`` (a condition on its view of the DDS graph) holds."""
    deadline = time.monotonic() + timeout
    while not ready():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        executor.spin_once(timeout_sec=0.05)


def test_simulated_end_to_end_calibration_at_three_chamber_temperatures(tmp_path, procs):
    try:
        run_end_to_end(tmp_path, procs)
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{dump(procs)}") from None


def run_end_to_end(tmp_path: Path, procs: list[ChildProcess]) -> None:
    if "ROS_DOMAIN_ID" not in os.environ:
        pytest.fail("ROS_DOMAIN_ID is not set: ROS tests must run in their own DDS domain (scripts/test.sh sets one)")
    plan = PosePlan.load(PLAN)
    assert plan.chamber is not None
    levels = list(plan.chamber.levels_c)
    shipped_cal = ROOT / "config" / "calibration_sim.yaml"
    assert shipped_cal.is_file(), f"missing {shipped_cal} (python -m fbg_accel_sim.make_default_calibration)"

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu, JointState

    # this test's node: its view of the DDS graph says when a board may start, and it receives the validation
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("e2e_validation", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    try:
        # ---- 1. record: one chain per chamber level, the three in parallel
        nodes = []
        for i, level in enumerate(levels):
            tag = f"e2e_rec{i}"
            rec_node = ChildProcess(f"calibration {tag}", [
                BIN / "calibration", "--ros-args", "-r", f"__ns:=/{tag}", "-p", f"plan_file:={PLAN}",
                "-p", f"output_dir:={tmp_path}", "-p", f"run_label:=level{i}", "-p", "mode:=auto",
                "-p", f"temperature_level:={i}", "-p", "fit:=false", "-p", "sensor_id:=sim-fbg-accel-001",
                "-p", f"operator_notes:=e2e test, chamber {level} degC"])
            procs.append(rec_node)
            nodes.append((rec_node, tag))
            start_driver(procs, tmp_path, tag, shipped_cal)
        for rec_node, _ in nodes:
            rec_node.wait_line(r"recording to ", timeout=30)  # subscribed; the driver's data is caught from its first match
        # each driver's imu/raw and its calibration node's subscription known (the plan's first dwell is left for the
        # node's start of the run, not for the discovery)
        wait_graph(node, executor, lambda: all(node.count_publishers(f"/{tag}/imu/raw") >= 1
                                               and node.count_subscribers(f"/{tag}/imu/raw") >= 1 for _, tag in nodes),
                   "the drivers' imu/raw and the calibration nodes' subscriptions")
        wait_sims([start_sim(procs, tmp_path, tag, levels[i], seed=10 + i, plan=PLAN) for i, (_, tag) in enumerate(nodes)])
        for rec_node, tag in nodes:
            rc = rec_node.wait_exit(timeout=90)
            assert rc == 0, f"{tag}: exit {rc}\n{rec_node.output()}"
            assert rec_node.find(r"0 lost, 0 pose\(s\) short"), rec_node.output()
        for p in procs:  # sims end with their scenario; drivers are stopped
            if p.name.startswith("driver"):
                assert p.stop() == 0, p.output()
        mcaps = [tmp_path / f"level{i}.mcap" for i in range(len(levels))]
        for i, m in enumerate(mcaps):
            rec = read_recording(m)
            assert rec.metadata["read_report"]["complete"]
            assert [int((rec.pose_id == k).sum()) for k in range(len(plan))] == [p.samples for p in plan.poses]
            assert abs(np.nanmean(rec.temp_c) - levels[i]) < plan.chamber.tolerance_c

        # ---- 2. fit (the offline tool, as an operator would run it)
        cal_path = tmp_path / "calibration_e2e.yaml"
        fit = subprocess.run([BIN / "fbg-accel-calib", "fit", *mcaps, "-o", cal_path, "--sensor-id", "sim-fbg-accel-001"],
                             capture_output=True, text=True, timeout=120)
        assert fit.returncode == 0, fit.stdout + fit.stderr
        cal = ThermalCalibration.load(cal_path)
        assert cal.degree == EXPECTED_DEGREE and cal.fit["poses"] == len(plan)
        lo, hi = cal.temperature_range_c
        assert lo < levels[0] + 1.0 and hi > levels[-1] - 1.0, cal.temperature_range_c
        print(fit.stdout)

        # ---- 3. validation on held-out poses: the driver reloads the fitted YAML
        qos = QoSProfile(reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST, depth=5000)
        received: dict[str, dict[str, dict[int, object]]] = {}
        lock = threading.Lock()

        def keep(tag: str, kind: str, stamp_ns: int, value: object) -> None:
            with lock:
                received.setdefault(tag, {"imu": {}, "raw": {}})[kind][stamp_ns] = value

        def stamp(msg) -> int:
            return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec

        tags = [f"e2e_val{i}" for i in range(len(levels))]
        for tag in tags:
            node.create_subscription(
                Imu, f"/{tag}/imu/data_raw",
                lambda m, t=tag: keep(t, "imu", stamp(m), (m.linear_acceleration.x, m.linear_acceleration.y,
                                                            m.linear_acceleration.z)), qos)
            node.create_subscription(
                JointState, f"/{tag}/imu/raw", lambda m, t=tag: keep(t, "raw", stamp(m), int(m.position[7])), qos)
        drivers = [start_driver(procs, tmp_path, tag, cal_path) for tag in tags]
        for drv in drivers:
            drv.wait_line(r"calibration .*calibration_e2e\.yaml", timeout=30)  # the driver loaded the fitted file
        wait_graph(node, executor, lambda: all(node.count_publishers(f"/{tag}/imu/{topic}") >= 1
                                               for tag in tags for topic in ("data_raw", "raw")),
                   "the validation drivers' imu/data_raw and imu/raw")
        spin.start()
        val_plan = validation_plan(tmp_path)
        sims = [start_sim(procs, tmp_path, tag, level, seed=20 + i, plan=val_plan)
                for i, (tag, level) in enumerate(zip(tags, levels, strict=True))]
        wait_sims(sims)
        for sim, drv in zip(sims, drivers, strict=True):
            assert sim.wait_exit(timeout=60) == 0, sim.output()
            assert drv.stop() == 0, drv.output()
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        if spin.is_alive():
            spin.join(timeout=5)

    from fbg_accel_sim.board_physics import BoardSimulator, SimConfig

    cfg = SimConfig.default().with_overrides({"scenario.rate_hz": RATE_HZ})
    configured = np.asarray(BoardSimulator(cfg, seed=0).configured_noise()["sample_sigma_mps2"], dtype=float)
    errors, deviations, per_level = [], [], []
    for i in range(len(levels)):
        tag = f"e2e_val{i}"
        truth = np.load(tmp_path / f"truth_{tag}.npz")
        t_seq = truth["seq"].astype(int)
        assert len(np.unique(t_seq)) == len(t_seq), "validation run longer than the u16 sequence"
        index_of_seq = {int(s): j for j, s in enumerate(t_seq)}
        with lock:
            imu, raw = dict(received[tag]["imu"]), dict(received[tag]["raw"])
        rows, est = [], []
        for st, seq in raw.items():
            if st in imu and seq in index_of_seq:
                rows.append(index_of_seq[seq])
                est.append(imu[st])
        rows_a, est_a = np.asarray(rows), np.asarray(est, dtype=float)
        pose = truth["pose_id"][rows_a]
        # the held-out poses (the lead-in before them is a pose of the fit)
        settled = (pose >= len(LEAD_IN)) & (truth["time_at_pose_s"][rows_a] >= SETTLED_S)
        err = est_a - truth["gref_mps2"][rows_a]
        for k in range(len(HELD_OUT)):  # every held-out pose is checked at every level
            sel = settled & (pose == k + len(LEAD_IN))
            assert sel.sum() > 100, f"{tag}: only {sel.sum()} settled samples of held-out pose {k} received"
            deviations.append(err[sel] - err[sel].mean(axis=0))
        errors.append(err[settled])
        per_level.append(np.sqrt(np.mean(err[settled] ** 2, axis=0)))
    rms = np.sqrt(np.mean(np.vstack(errors) ** 2, axis=0))
    floor = np.sqrt(np.mean(np.vstack(deviations) ** 2, axis=0))
    report = (f"held-out calibrated RMS error x/y/z {np.round(rms, 4)} m/s^2 (per level {[np.round(v, 4) for v in per_level]}); "
              f"noise floor (within-pose scatter) {np.round(floor, 4)} m/s^2, simulator's configured per-sample noise "
              f"{np.round(configured, 4)}; ratio {np.round(rms / floor, 3)} (limit {NOISE_FACTOR}); degree {cal.degree}")
    print(report)
    # the floor is the simulated sensor's noise (white + ADC quantisation), not something a broken pipeline inflated
    assert np.all(floor >= 0.8 * configured) and np.all(floor <= 1.5 * configured), report
    assert np.all(rms <= NOISE_FACTOR * floor), report
