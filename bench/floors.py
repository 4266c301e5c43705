#!/usr/bin/env python3
"""The floors of issue 36 beside the project's own figures, measured in the same run, so that each ratio is one command.

Every measure is a pair of child processes run alternately (floor, project, floor, project, ...), so that the other
load of a shared machine falls on both alike; a child's CPU time (user + system, all its threads) and peak resident
set come from ``os.wait4``. A ratio is the median of the per-pair ratios of CPU time. The load average before and after
the run is in the results.

* ``startup``: each command's ``--help`` against ``python -c pass`` (``bench/startup.py``); goal <= 0.2 s.
* ``fit``: ``fbg-accel-calib fit`` of N samples from MCAP files (one per temperature level, written by the node's
  writer) against the floor: a plain-numpy process that loads the same N samples (uncompressed ``.npy``, the cheapest
  read), fits eq. 28 at degree 2 (36 coefficients) by least squares and runs a 10-fold cross-validation by visit
  from per-fold X^T X and X^T Y. Goal: <= 2x.
* ``diagnose``: the diagnosis alone (``bench/diagnose_command.py --diagnosis-alone``: import the engine, read the
  recording from MCAP, ``diagnose()`` with the command's defaults but one lane, the goal's measure) on the
  simulator's benchmark run (``bench_calibration.scenario``, every effect at its default) of N samples, against the
  same floor as ``fit`` (least squares of eq. 28 at degree 2 and a 10-fold cross-validation by visit) on the same
  samples (those with a reference, from ``.npz``). Goals: CPU <= 10x, peak RSS <= 600 MiB. The floor runs as numpy
  does by default, its products on every core, and the waits of OpenBLAS's threads count in its CPU time (half again
  its CPU time on one thread, or more: docs/results/performance.md): each pair of the one-lane measure also runs it
  with OpenBLAS on one thread, as the diagnosis runs its own products, and gives that ratio beside the goal's. Then the
  same with the command's default lanes (two searches side by side on a machine of two cores or more: less wall
  time, more CPU and memory), in pairs of their own with the floor.
* ``driver``: CPU of the ``driver`` process (all threads, /proc/<pid>/stat) over a window of frames written to a pty
  at 100 Hz and 1 kHz (the simulator's clean frames, one write per frame, paced), against the floor node
  (:func:`driver_floor`, a minimal rclpy node publishing the same three messages per frame) fed the same way,
  alternately; with a subscriber process (:func:`subscriber`, sensor-data QoS) and without. Goal: <= 1.5x.

The data: ``fbg_accel_sim.eq28_campaign`` (eq. 28 holds exactly; three chamber levels, 24 poses visited twice, TIA
low-passed noise), sized to N samples, its temperatures read as an AHT10 reads them (0.01 degC steps, 0.02 degC noise:
a chamber level held to the last bit for minutes is not what the sensor gives).

    .venv/bin/python bench/floors.py                          # all, N = 10^6, scratch results
    .venv/bin/python bench/floors.py --only fit --pairs 5
    .venv/bin/python bench/floors.py --update-results         # bench/results/floors.json, docs/results/performance.md
    .venv/bin/python bench/floors.py --only diagnose --pairs 2 --update-results   # the other rows kept from before
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from machine_info import machine, results_doc, write_results
from output_paths import RESULTS_PAGES, add_update_results, results_dir

HERE = Path(__file__).resolve().parent
FIT_GOAL = 2.0
DIAGNOSE_GOAL, DIAGNOSE_RSS_GOAL_MIB = 10.0, 600.0
MEASURES = ("startup", "fit", "diagnose", "driver")
LEVELS, POSES, REPEATS, RATE_HZ = 3, 24, 2, 100.0  # eq28_campaign's levels and rate
AHT10_STEP_C, AHT10_NOISE_C = 0.01, 0.02
ONE_BLAS_THREAD = {"OPENBLAS_NUM_THREADS": "1"}  # numpy's OpenBLAS (its wheels') on one thread


def run_child(argv: list[str], env: dict[str, str] | None = None) -> dict:
    """CPU s (user + system; and system alone), wall s and peak RSS MiB of one child process (output discarded; a
    failure stops the benchmark; ``env``: variables set for it on top of this process's). The RSS includes the
    parent's resident set at the fork (``ru_maxrss``), tens of MiB (the files measured are made in a child of their
    own, ``made_in_a_child``): it tells only of larger figures."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env=None if env is None else {**os.environ, **env})
    err = proc.stderr.read()  # type: ignore[union-attr]
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{argv} failed: {err.decode(errors='replace')[-2000:]}")
    return {"cpu_s": usage.ru_utime + usage.ru_stime, "sys_s": usage.ru_stime, "wall_s": wall,
            "rss_mib": usage.ru_maxrss / 1024}


def interleaved(floor_argv: list[str], project_argv: list[str], pairs: int, one_blas_thread: bool = False) -> dict:
    """Median figures of ``pairs`` alternate runs and the median per-pair CPU ratio project / floor. ``one_blas_thread``:
    each pair also runs the floor with OpenBLAS on one thread (``floor_one_blas_thread``, ``cpu_ratio_one_blas_thread``):
    numpy's default uses every core for the floor's products, and the waits of its threads count as CPU time."""
    floor, alone, project = [], [], []
    for _ in range(pairs):
        floor.append(run_child(floor_argv))
        if one_blas_thread:
            alone.append(run_child(floor_argv, env=ONE_BLAS_THREAD))
        project.append(run_child(project_argv))

    def med(runs: list[dict]) -> dict:
        return {k: round(statistics.median(r[k] for r in runs), 3) for k in runs[0]}

    def ratios(floors: list[dict]) -> list[float]:
        return [p["cpu_s"] / f["cpu_s"] for p, f in zip(project, floors, strict=True)]

    out = {"floor": med(floor), "project": med(project), "cpu_ratio": round(statistics.median(ratios(floor)), 2),
           "cpu_ratio_range": [round(min(ratios(floor)), 2), round(max(ratios(floor)), 2)], "pairs": pairs}
    if one_blas_thread:
        r = ratios(alone)
        out.update(floor_one_blas_thread=med(alone), cpu_ratio_one_blas_thread=round(statistics.median(r), 2),
                   cpu_ratio_one_blas_thread_range=[round(min(r), 2), round(max(r), 2)])
    return out


# -- fit
def campaign_files(n: int, folder: Path) -> tuple[list[Path], Path]:
    """The MCAP files (one per level) and the floor's .npz of an N-sample campaign, written once into ``folder``."""
    files = [folder / f"level{i}.mcap" for i in range(LEVELS)]
    arrays = folder / "samples.npz"
    stamp = folder / f"samples_{n}.done"
    if stamp.exists() and arrays.exists() and all(f.exists() for f in files):
        return files, arrays
    import numpy as np

    from fbg_accel_calibration.io.mcap_writer import write_recording
    from fbg_accel_sim.eq28_campaign import campaign

    rec, _ = campaign(0, degree=2, n_poses=POSES, repeats=REPEATS, visit_s=n / (LEVELS * POSES * REPEATS * RATE_HZ))
    # the chamber's temperature as the AHT10 reads it: 0.01 degC steps (../shared/docs/sensor_facts.md), 0.02 degC noise
    noise = np.random.default_rng(1).normal(0.0, AHT10_NOISE_C, len(rec))
    rec.temp_c[:] = np.round((rec.temp_c + noise) / AHT10_STEP_C) * AHT10_STEP_C
    for i, path in enumerate(files):
        part = rec.select(rec.run_id == i)
        part.run_id[:] = 0
        write_recording(path, part, {"sensor_id": "bench"})
    np.savez(arrays, ref=rec.ref, xyz=rec.xyz, temp_c=rec.temp_c, gref=rec.gref_mps2, pose=rec.pose_id, run=rec.run_id)
    stamp.touch()
    return files, arrays


def fit_floor(arrays: Path, degree: int = 2, folds: int = 10) -> None:
    """The floor of ``fit`` (in its own process): load, eq. 28 least squares, 10-fold CV by visit from sums."""
    import numpy as np

    d = dict(np.load(arrays))
    keep = np.all(np.isfinite(d["gref"]), axis=1)  # the samples at a pose (a diagnosis' recording has moves too)
    if not keep.all():
        d = {k: v[keep] for k, v in d.items()}
    psi = d["xyz"] / d["ref"][:, None]
    temp = d["temp_c"]
    tau = (temp - (temp.min() + temp.max()) / 2) / ((temp.max() - temp.min()) / 2)
    powers = tau[:, None] ** np.arange(degree + 1)  # (N, n+1)
    X = np.column_stack([(psi[:, :, None] * powers[:, None, :]).reshape(len(tau), -1), powers])  # (N, 4(n+1))
    Y = d["gref"]
    A = np.linalg.lstsq(X, Y, rcond=None)[0]  # (12, 3): 36 coefficients
    change = np.r_[True, (np.diff(d["pose"]) != 0) | (np.diff(d["run"]) != 0)]
    visit = np.cumsum(change) - 1
    fold = np.random.default_rng(0).permutation(visit[-1] + 1)[visit] % folds
    xtx = np.stack([X[fold == f].T @ X[fold == f] for f in range(folds)])
    xty = np.stack([X[fold == f].T @ Y[fold == f] for f in range(folds)])
    yty = np.stack([np.einsum("ij,ij->j", Y[fold == f], Y[fold == f]) for f in range(folds)])
    rss = np.zeros(3)
    for f in range(folds):
        Af = np.linalg.solve(xtx.sum(0) - xtx[f], xty.sum(0) - xty[f])
        rss += yty[f] - 2 * np.einsum("ij,ij->j", Af, xty[f]) + np.einsum("ij,ik,kj->j", Af, xtx[f], Af)
    assert np.all(np.isfinite(A)) and np.all(rss > 0)


def made_in_a_child(kind: str, n: int, folder: Path) -> None:
    """Write the files of ``kind`` ("fit": ``campaign_files``, "diagnose": ``diagnose_files``) in a process of their
    own: a child's peak RSS (``ru_maxrss``) counts the parent's resident set at the fork, so the parent must not grow
    by simulating and writing 10^6 samples before it measures."""
    run_child([sys.executable, str(Path(__file__).resolve()), "--make-files", kind, str(n), str(folder)])


def measure_fit(n: int, pairs: int, folder: Path) -> dict:
    made_in_a_child("fit", n, folder)
    files, arrays = campaign_files(n, folder)
    out = folder / "fit_out.yaml"
    project = [sys.executable, "-c", "import sys; from fbg_accel_calibration.commands.cli_main import main; sys.exit(main())",
               "fit", *map(str, files), "-o", str(out), "--force", "--no-progress"]
    floor = [sys.executable, str(Path(__file__).resolve()), "--fit-floor", str(arrays)]
    run_child(project)  # page cache and .pyc files
    res = interleaved(floor, project, pairs)
    res.update(samples=n, files=len(files), file_mb=round(sum(f.stat().st_size for f in files) / 2**20, 1),
               goal=FIT_GOAL, goal_met=res["cpu_ratio"] <= FIT_GOAL,
               command="fbg-accel-calib fit level0.mcap level1.mcap level2.mcap -o cal.yaml")
    print(f"fit {n} samples: project CPU {res['project']['cpu_s']:.2f} s ({res['project']['rss_mib']:.0f} MiB), floor "
          f"{res['floor']['cpu_s']:.2f} s ({res['floor']['rss_mib']:.0f} MiB): {res['cpu_ratio']:.2f}x (goal <= "
          f"{FIT_GOAL}x: {'met' if res['goal_met'] else 'NOT met'})", flush=True)
    return res


# -- diagnose
def diagnose_files(n: int, folder: Path) -> tuple[Path, Path]:
    """The benchmark run of ``n`` samples as MCAP (``diagnose_command.recording``) and the same samples, read back
    from it, as the floor's .npz (written once into ``folder``)."""
    from diagnose_command import recording

    path = recording(n, folder)
    arrays = folder / f"diagnose_{n}.npz"
    if not arrays.exists():
        import numpy as np

        from fbg_accel_calibration.io.input_files import load_recording

        rec = load_recording([str(path)], rate=None, temperature=None, g=None, namespace=None, topic=None)
        np.savez(arrays, ref=rec.ref, xyz=rec.xyz, temp_c=rec.temp_c, gref=rec.gref_mps2, pose=rec.pose_id,
                 run=rec.run_id)
    return path, arrays


def measure_diagnose(n: int, pairs: int, folder: Path) -> dict:
    """The diagnosis alone with one lane against the floor (the goal's measure), then with the default lanes (the
    result's ``default_lanes``)."""
    made_in_a_child("diagnose", n, folder)
    path, arrays = diagnose_files(n, folder)
    project = [sys.executable, str(HERE / "diagnose_command.py"), "--diagnosis-alone", str(path)]
    floor = [sys.executable, str(Path(__file__).resolve()), "--fit-floor", str(arrays)]
    run_child(floor)  # page cache and .pyc files
    out: dict = {}
    for lanes, argv in (("one lane", [*project, "--lanes", "1"]), ("default lanes", project)):
        res = interleaved(floor, argv, pairs, one_blas_thread=lanes == "one lane")
        rss = res["project"]["rss_mib"]
        res.update(samples=n, goal=DIAGNOSE_GOAL, rss_goal_mib=DIAGNOSE_RSS_GOAL_MIB, lanes=lanes,
                   goal_met=res["cpu_ratio"] <= DIAGNOSE_GOAL, rss_goal_met=rss <= DIAGNOSE_RSS_GOAL_MIB,
                   command="diagnose() of the recording read from MCAP (bench/diagnose_command.py "
                           f"--diagnosis-alone{' --lanes 1' if lanes == 'one lane' else ''})")
        print(f"diagnose {n} samples, {lanes}: diagnosis CPU {res['project']['cpu_s']:.2f} s ({rss:.0f} MiB), floor "
              f"{res['floor']['cpu_s']:.2f} s: {res['cpu_ratio']:.2f}x (goal <= {DIAGNOSE_GOAL:g}x: "
              f"{'met' if res['goal_met'] else 'NOT met'}; RSS goal <= {DIAGNOSE_RSS_GOAL_MIB:g} MiB: "
              f"{'met' if res['rss_goal_met'] else 'NOT met'})", flush=True)
        if "floor_one_blas_thread" in res:
            print(f"  the floor with OpenBLAS on one thread: {res['floor_one_blas_thread']['cpu_s']:.2f} s: "
                  f"{res['cpu_ratio_one_blas_thread']:.2f}x", flush=True)
        if out:
            out["default_lanes"] = res
        else:
            out = res
    return out


# -- driver
DRIVER_RATES_HZ = (100.0, 1000.0)
DRIVER_GOAL = 1.5


def driver_floor(port: str) -> None:
    """The floor of the driver (in its own process): a minimal rclpy node that reads the port as the bytes come, finds
    the 27-byte version-1 frames (sync, CRC-16/CCITT-FALSE), stamps each with the ROS clock and publishes what the
    driver publishes per frame (imu/raw JointState, imu/temperature, imu/data_raw with eq. 24 through one fixed 3x3
    matrix), with the driver's QoS (reliable, keep-last 100). No clock mapping, decimation, covariance, diagnostics or
    reconnection: the essential work only."""
    import binascii
    import signal
    import struct

    import rclpy
    import serial
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import Imu, JointState, Temperature

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    rclpy.init()
    node = rclpy.create_node("floor_driver")
    qos = QoSProfile(depth=100)
    pub_raw, pub_temp, pub_imu = (node.create_publisher(t, n, qos) for t, n in
                                  ((JointState, "imu/raw"), (Temperature, "imu/temperature"), (Imu, "imu/data_raw")))
    names = ["ref_counts", "x_counts", "y_counts", "z_counts", "temperature_c", "temperature_valid", "status", "seq",
             "board_time_s"]
    body = struct.Struct("<HQHHHHhB")
    m = ((80.0, 0.0, 0.0), (0.0, 78.0, 0.0), (0.0, 0.0, 107.0))
    ser = serial.Serial(port, 921600, timeout=0.5)
    buf = bytearray()
    clock = node.get_clock()
    while True:
        buf += ser.read(max(1, ser.in_waiting))
        while len(buf) >= 27:
            i = buf.find(b"\xa5\x5a")
            if i < 0:
                del buf[:-1]
                break
            del buf[:i]
            if len(buf) < 27:
                break
            if binascii.crc_hqx(bytes(buf[2:25]), 0xFFFF) != buf[25] | buf[26] << 8:
                del buf[:1]
                continue
            seq, t_us, ref, x, y, z, temp_cc, status = body.unpack_from(buf, 4)
            del buf[:27]
            stamp = clock.now().to_msg()
            raw = JointState(name=names, position=[float(ref), float(x), float(y), float(z), temp_cc / 100.0, 1.0,
                                                   float(status), float(seq), t_us * 1e-6])
            raw.header.stamp = stamp
            pub_raw.publish(raw)
            temp = Temperature(temperature=temp_cc / 100.0)
            temp.header.stamp = stamp
            pub_temp.publish(temp)
            psi = (x / ref, y / ref, z / ref)
            imu = Imu()
            imu.header.stamp = stamp
            imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z = (
                sum(a * b for a, b in zip(row, psi, strict=True)) for row in m)
            imu.orientation_covariance[0] = imu.angular_velocity_covariance[0] = -1.0
            pub_imu.publish(imu)


def subscriber() -> None:
    """A consumer of the three data topics (sensor-data QoS, as docs/topics.md tells consumers), in its own process:
    what a navigation filter beside the driver does with the messages, nothing more."""
    import signal

    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Imu, JointState, Temperature

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    rclpy.init()
    node = rclpy.create_node("floor_subscriber")
    for t, n in ((JointState, "imu/raw"), (Temperature, "imu/temperature"), (Imu, "imu/data_raw")):
        node.create_subscription(t, n, lambda msg: None, qos_profile_sensor_data)
    rclpy.spin(node)


def node_cpu(argv: list[str], rate_hz: float, window_s: float, frames: list[bytes], with_subscriber: bool) -> float:
    """CPU (% of one core) of the node ``argv`` (``{port}`` in it: the pty's path) over ``window_s`` of frames written
    at ``rate_hz``, one write per frame paced on the monotonic clock, after a 3 s warm-up."""
    from fbg_accel_sim.pty_server import PtyEndpoint

    ep = PtyEndpoint(None)
    path = ep.open(hold=False)
    sub = (subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--subscriber"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL) if with_subscriber else None)
    proc = subprocess.Popen([a.replace("{port}", path) for a in argv], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while not ep.client_present():
            if time.monotonic() > deadline or proc.poll() is not None:
                raise SystemExit(f"{argv} did not open the pty")
            time.sleep(0.05)
        time.sleep(0.2)
        ep.hold_slave()
        period, t0, k, start = 1.0 / rate_hz, time.monotonic(), 0, None
        warm = round(3.0 * rate_hz)
        end = warm + round(window_s * rate_hz)
        while k < end:
            if k == warm:
                start = (time.monotonic(), _proc_cpu_s(proc.pid))
            ep.write(frames[k % len(frames)])
            k += 1
            delay = t0 + k * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        wall, cpu = time.monotonic() - start[0], _proc_cpu_s(proc.pid) - start[1]  # type: ignore[index]
        return 100.0 * cpu / wall
    finally:
        for p in (proc, sub):
            if p is None:
                continue
            p.terminate()
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        ep.close()


def _proc_cpu_s(pid: int) -> float:
    """utime + stime of all threads of ``pid`` (/proc/<pid>/stat), s."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure_driver(pairs: int, window_s: float) -> list[dict]:
    from bench_driver_ingest import make_frames

    rows = []
    for rate, with_subscriber in itertools.product(DRIVER_RATES_HZ, (True, False)):
        frames = make_frames(rate, round((window_s + 3.0) * rate) + 10, seed=0)[0]
        driver = [sys.executable, "-m", "fbg_accel_driver.driver_main", "--ros-args", "-p", "port:={port}",
                  "-p", "calibration_file:=sim"]
        floor = [sys.executable, str(Path(__file__).resolve()), "--driver-floor", "{port}"]
        f_cpu, d_cpu = [], []
        for _ in range(pairs):
            f_cpu.append(node_cpu(floor, rate, window_s, frames, with_subscriber))
            d_cpu.append(node_cpu(driver, rate, window_s, frames, with_subscriber))
        ratios = [d / f for d, f in zip(d_cpu, f_cpu, strict=True)]
        row = {"rate_hz": rate, "subscriber": with_subscriber, "window_s": window_s, "pairs": pairs,
               "driver_cpu_pct": round(statistics.median(d_cpu), 1),
               "floor_cpu_pct": round(statistics.median(f_cpu), 1), "cpu_ratio": round(statistics.median(ratios), 2),
               "cpu_ratio_range": [round(min(ratios), 2), round(max(ratios), 2)], "goal": DRIVER_GOAL}
        row["goal_met"] = row["cpu_ratio"] <= DRIVER_GOAL
        rows.append(row)
        print(f"driver at {rate:g} Hz, {'a' if with_subscriber else 'no'} subscriber: CPU {row['driver_cpu_pct']} % "
              f"of a core, floor node {row['floor_cpu_pct']} %: "
              f"{row['cpu_ratio']}x (goal <= {DRIVER_GOAL}x: {'met' if row['goal_met'] else 'NOT met'})", flush=True)
    return rows


# -- results page
def page(doc: dict) -> str:
    m = doc["machine"]
    lines = ["# Performance against the floors", "",
             f"Generated by `{doc['command']}` on {doc['date_utc']}. Machine: {m['cpu']}, {m['logical_cpus']} logical "
             f"CPUs, {m['ram_gib']} GiB, Python {m['python']}, numpy {m['numpy']}; load average before "
             f"{doc['load_average_before']}, after {m['load_average_1_5_15']} (other work on the machine: CPU times, "
             "interleaved pairs, median of the per-pair ratios). Method: the docstring of `bench/floors.py`.", "",
             *([f"The rows of {', '.join(doc['kept']['measures'])} are those of `{doc['kept']['command']}` on "
                f"{doc['kept']['date_utc']} (`--update-results` with `--only` keeps the measures it did not run).", ""]
               if "kept" in doc else []),
             "| measure | project CPU | floor | floor CPU | ratio (range) | goal |", "|---|---|---|---|---|---|"]
    for row in doc.get("startup", []):
        lines.append(f"| `{row['command']}` | {row['cpu_s']:.3f} s | `python -c pass` | "
                     f"{row['floor_cpu_s']:.3f} s | {row['cpu_ratio']:.1f}x | <= 0.2 s: "
                     f"{'met' if row['goal_met'] else 'not met'} |")
    if "fit" in doc:
        f = doc["fit"]
        lines.append(f"| `fbg-accel-calib fit`, {f['samples']:.0e} samples from {f['files']} MCAP files "
                     f"({f['file_mb']} MiB) | {f['project']['cpu_s']:.2f} s, {f['project']['rss_mib']:.0f} MiB | "
                     "eq. 28 degree 2 least squares + 10-fold CV by visit, numpy, samples from .npy | "
                     f"{f['floor']['cpu_s']:.2f} s, {f['floor']['rss_mib']:.0f} MiB | {f['cpu_ratio']:.2f}x "
                     f"({f['cpu_ratio_range'][0]}-{f['cpu_ratio_range'][1]}) | <= {f['goal']}x: "
                     f"{'met' if f['goal_met'] else 'not met'} |")
    diag = doc.get("diagnose")
    for f in [] if diag is None else [diag, *([diag["default_lanes"]] if "default_lanes" in diag else [])]:
        lanes = f" ({f['lanes']})" if "lanes" in f else ""
        lines.append(f"| the diagnosis alone (`diagnose()` of a recording read from MCAP{lanes}), {f['samples']:.0e} "
                     f"samples of the simulator's benchmark run | {f['project']['cpu_s']:.2f} s, "
                     f"{f['project']['rss_mib']:.0f} MiB | the same floor as `fit`, on the same samples | "
                     f"{f['floor']['cpu_s']:.2f} s, {f['floor']['rss_mib']:.0f} MiB | {f['cpu_ratio']:.2f}x "
                     f"({f['cpu_ratio_range'][0]}-{f['cpu_ratio_range'][1]}) | <= {f['goal']:g}x: "
                     f"{'met' if f['goal_met'] else 'not met'}; <= {f['rss_goal_mib']:g} MiB: "
                     f"{'met' if f['rss_goal_met'] else 'not met'} |")
        if "floor_one_blas_thread" in f:
            one = f["floor_one_blas_thread"]
            lines.append(f"| the same, one lane | | the same floor, OpenBLAS on one thread | {one['cpu_s']:.2f} s, "
                         f"{one['rss_mib']:.0f} MiB | {f['cpu_ratio_one_blas_thread']:.2f}x "
                         f"({f['cpu_ratio_one_blas_thread_range'][0]}-{f['cpu_ratio_one_blas_thread_range'][1]}) | "
                         f"<= {f['goal']:g}x against the algebra alone: "
                         f"{'met' if f['cpu_ratio_one_blas_thread'] <= f['goal'] else 'not met'} |")
    for row in doc.get("driver", []):
        lines.append(f"| `driver` at {row['rate_hz']:g} Hz (pty, default parameters, calibration 'sim'), "
                     f"{'a subscriber process' if row['subscriber'] else 'no subscriber'}, {row['window_s']:g} s | "
                     f"{row['driver_cpu_pct']} % of a core | minimal rclpy node: read, "
                     f"CRC, publish imu/raw, imu/temperature, imu/data_raw | {row['floor_cpu_pct']} % | "
                     f"{row['cpu_ratio']:.2f}x ({row['cpu_ratio_range'][0]}-{row['cpu_ratio_range'][1]}) | <= "
                     f"{row['goal']}x: {'met' if row['goal_met'] else 'not met'} |")
    lines += ["", "The floors: `python -c pass` (the interpreter's own start); for `fit`, a plain-numpy process that loads "
              "the same samples from an uncompressed `.npy`, builds eq. 28's degree-2 design (12 columns per axis, 36 "
              "coefficients), solves it by least squares and runs a 10-fold cross-validation by visit from per-fold "
              "XᵀX and XᵀY; for the diagnosis, the same floor on the samples of the diagnosed run that have a "
              "reference (those at a pose), read from an `.npz` of what the diagnosis reads from MCAP, as numpy runs it "
              "by default (its products on every core: the waits of OpenBLAS's threads count in its CPU time) and, "
              "for comparison with one lane, with OpenBLAS on one thread (`OPENBLAS_NUM_THREADS=1`), as the diagnosis "
              "runs its products; for the driver, "
              "a minimal rclpy node (`floors.driver_floor`: read what is waiting, find "
              "the frames, check the CRC, stamp with the ROS clock, publish imu/raw, imu/temperature and "
              "imu/data_raw through a fixed matrix; no clock mapping, covariance, diagnostics or reconnection), fed "
              "the simulator's clean frames on a pty exactly as the driver is, with the same subscriber process (sensor-data "
              "QoS) or none. "
              "The fit's samples: `fbg_accel_sim.eq28_campaign`, three chamber levels, 24 poses visited twice, "
              "temperatures in the AHT10's 0.01 degC steps; the command's calibration is bit for bit the one before "
              "the changes that brought it near its floor (`test/test_fit_streaming.py`).",
              "", "RSS: `ru_maxrss` of the child, which includes the benchmark's own resident set at the fork (tens of "
              "MiB); the start-up rows leave it out for that reason."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=",".join(MEASURES),
                    help="comma-separated measures (startup, fit, diagnose, driver)")
    ap.add_argument("--samples", type=float, default=1e6,
                    help="samples of the fit's campaign and of the diagnosed run (default 10^6)")
    ap.add_argument("--pairs", type=int, default=3, help="interleaved pairs of the fit (startup: 5x as many)")
    ap.add_argument("--dir", type=Path, default=None, help="keep the campaign's files here (reused by later runs)")
    ap.add_argument("--output", type=Path, default=None, help="results JSON (default: floors.json in the results dir)")
    ap.add_argument("--driver-window", type=float, default=10.0, help="seconds each driver run is measured")
    ap.add_argument("--fit-floor", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--driver-floor", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--subscriber", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--make-files", nargs=3, default=None, help=argparse.SUPPRESS)  # kind, samples, folder
    add_update_results(ap)
    args = ap.parse_args(argv)
    if args.make_files is not None:
        kind, n, folder = args.make_files
        (campaign_files if kind == "fit" else diagnose_files)(int(n), Path(folder))
        return 0
    if args.fit_floor is not None:
        fit_floor(args.fit_floor)
        return 0
    if args.driver_floor is not None:
        driver_floor(args.driver_floor)
        return 0
    if args.subscriber:
        subscriber()
        return 0
    only = set(args.only.split(","))
    if only - set(MEASURES):
        ap.error(f"--only: unknown measure(s) {sorted(only - set(MEASURES))}; known: {','.join(MEASURES)}")
    load_before = [round(v, 2) for v in os.getloadavg()]
    doc = results_doc("floors.py", argv, benchmark="floors", load_average_before=load_before)
    if "startup" in only:
        from startup import measure

        doc["startup"] = measure(5 * args.pairs)
    if only & {"fit", "diagnose"}:
        tmp = tempfile.TemporaryDirectory() if args.dir is None else None
        folder = Path(tmp.name) if tmp else args.dir
        folder.mkdir(parents=True, exist_ok=True)
        if "fit" in only:
            doc["fit"] = measure_fit(int(args.samples), args.pairs, folder)
        if "diagnose" in only:
            doc["diagnose"] = measure_diagnose(int(args.samples), args.pairs, folder)
        if tmp:
            tmp.cleanup()
    if "driver" in only:
        doc["driver"] = measure_driver(max(1, args.pairs - 1), args.driver_window)
    doc["machine"] = machine()  # the load average after
    out = args.output or results_dir(args.update_results) / "floors.json"
    if args.update_results and out.exists():  # the measures not run (--only) are kept from the results before
        old_doc = json.loads(out.read_text(encoding="utf-8"))
        kept = [k for k in MEASURES if k not in doc and k in old_doc]
        for k in kept:
            doc[k] = old_doc[k]
        if kept:
            doc["kept"] = {"measures": kept, "command": old_doc.get("kept", {}).get("command", old_doc["command"]),
                           "date_utc": old_doc.get("kept", {}).get("date_utc", old_doc["date_utc"])}
    write_results(out, doc)
    md = (RESULTS_PAGES if args.update_results else out.parent) / "performance.md"
    old = md.read_text(encoding="utf-8") if md.exists() else ""
    others = old[old.index("\n## ") + 1:] if "\n## " in old else ""  # sections other benches add (none of its own)
    md.write_text(page(doc) + ("\n" + others if others else ""), encoding="utf-8")
    print(f"page written to {md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
