"""Dynamic calibration end to end (issue 9): the simulator runs the stepped-sine plan (slide + LDV on the
aux channel, protocol version 2), ``fbg-accel-calib dynamic`` recovers the chain, and the driver applies
it (seed Fig. 12's check on a frequency the fit did not use; a step on the reference's time line)."""

from __future__ import annotations

import functools
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from fbg_accel_calibration.dynamic.dynamic_calibration import DynamicCalibrationError, DynamicCalibrationResult, run_dynamic
from fbg_accel_calibration.dynamic.dynamic_check import step_check
from fbg_accel_calibration.dynamic.excitation_plan import ExcitationPlan
from fbg_accel_calibration.dynamic.tone_analysis import uniformly_sampled
from fbg_accel_calibration.io.dynamic_csv import DynamicCsvError, read_dynamic_csv, write_dynamic_csv
from fbg_accel_calibration.io.recording import Recording
from fbg_accel_driver.driver_core import RAW_AUX_NAME, RAW_NAMES
from fbg_accel_driver.driver_parameters import default_calibration_path
from fbg_accel_driver.frame_codec import ADC_MAX
from fbg_accel_driver.thermal_model import ThermalCalibration
from fbg_accel_sim.dynamic_run import simulate_dynamic_run, simulated_tone_check
from fbg_accel_sim.sim_config import SimConfig

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

REPO = Path(__file__).resolve().parents[1]
PLAN = ExcitationPlan.load(REPO / "config" / "excitation_plan_stepped_sine.yaml")
CLI = str(Path(sys.executable).parent / "fbg-accel-calib")
RATE_HZ = 500.0


def _truth() -> tuple[np.ndarray, np.ndarray]:
    """The simulated chain: TIA cut-offs (reference, x, y, z) and the pure delay of the axes (s)."""
    cfg = SimConfig.default()
    fc = np.asarray(cfg.get("electronics.tia_cutoff_hz"), float) * 1.0
    delay = cfg.scale("channel_delay") * float(cfg.get("effects.channel_delay.delay_s"))
    return fc, np.full(3, delay)


@pytest.fixture(scope="module")
def static_cal() -> ThermalCalibration:
    return ThermalCalibration.load(default_calibration_path())


@functools.cache
def simulated(seed: int) -> Recording:
    """The simulated slide run of PLAN at RATE_HZ (``simulate_dynamic_run``), built once per test run: the tests read
    seed 1 (and its fit, ``calibrated``) unless they change the run itself; a seed of their own would cost a simulation
    and a fit for nothing they check (the further seeds are sweep cases, bench/seed_sweeps.py). Its arrays are
    read-only, so a test that changed them in place, instead of a copy (``Recording.select`` with a mask), would fail
    instead of changing what the tests after it read."""
    rec = simulate_dynamic_run(PLAN, rate_hz=RATE_HZ, seed=seed)[0]
    for value in vars(rec).values():
        if isinstance(value, np.ndarray):
            value.flags.writeable = False
    return rec


@functools.cache
def calibrated(seed: int) -> DynamicCalibrationResult:
    """``run_dynamic`` of ``simulated(seed)`` with the shipped calibration, once per test run (tests only read it)."""
    return run_dynamic(simulated(seed), PLAN, ThermalCalibration.load(default_calibration_path()))


@pytest.mark.parametrize("seed", [1, pytest.param(2, marks=pytest.mark.sweep)])  # seed 2: bench/seed_sweeps.py
def test_cli_recovers_the_simulated_chain(tmp_path, static_cal, seed):
    rec = simulated(seed)
    csv = tmp_path / "run.csv"
    write_dynamic_csv(csv, rec)
    out = tmp_path / "cal.yaml"
    res = subprocess.run([CLI, "dynamic", str(csv), "--plan", str(REPO / "config" / "excitation_plan_stepped_sine.yaml"),
                          "--calibration", str(default_calibration_path()), "-o", str(out), "--bode",
                          str(tmp_path / "bode.png"), "--json", str(tmp_path / "dyn.json")],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    cal = ThermalCalibration.load(out)
    assert np.array_equal(cal.M, static_cal.M)  # the static model is untouched
    fc_true, delay_true = _truth()
    models = cal.dynamic.fit["models"]
    for a, ax in enumerate("xyz"):
        fc, u_fc = cal.dynamic.cutoff_hz[a + 1], models[ax]["u_cutoff_hz"]
        assert abs(fc - fc_true[a + 1]) <= max(0.05 * fc_true[a + 1], 2 * u_fc), (ax, fc, u_fc)
        d, u_d = cal.dynamic.delay_s[a], models[ax]["u_delay_s"]
        assert abs(d - delay_true[a]) <= max(1e-3, 2 * u_d), (ax, d, u_d)
    assert math.isnan(cal.dynamic.cutoff_hz[0])  # the slide run cannot see the reference channel
    assert (tmp_path / "bode.png").stat().st_size > 10_000
    assert "not measured" in res.stdout


def test_compensation_cuts_the_error_at_a_frequency_the_fit_did_not_use(static_cal):
    """Seed Fig. 12: the RMS difference to the reference over whole periods falls by >= 25 % with the
    correction on (equalise); the delay-only correction is reported as it is."""
    rec = simulated(1)
    res = run_dynamic(rec, PLAN, static_cal, reference_cutoff_hz=1.0)
    assert 3.0 not in res.dynamics.fit["frequencies_hz"]
    cal = ThermalCalibration.from_dict({**static_cal.to_dict(), "dynamic": res.dynamics.to_dict()})
    chk = simulated_tone_check(PLAN.with_tone(3.0, 8.0, 14.0), cal, rate_hz=100.0, seed=8)
    assert chk.periods >= 20
    assert all(r >= 25.0 for r in chk.reduction_pct["equalise"]), chk.as_dict()
    assert all(r > 0.0 for r in chk.reduction_pct["delay"]), chk.as_dict()


def test_a_step_appears_within_one_sample_period_once_equalised(static_cal):
    from fbg_accel_driver.chain_compensation import ChainDynamics

    cal = ThermalCalibration.from_dict(static_cal.to_dict())
    cal.dynamic = ChainDynamics(cutoff_hz=(1.0, 1.7, 1.3, 1.3), delay_s=(0.02, 0.02, 0.02))
    eq = step_check(cal, "equalise", rate_hz=100.0, bandwidth_hz=10.0)
    for ax in "xyz":
        assert abs(eq[f"{ax}_half_step_s"]) <= eq["sample_period_s"], eq
    # a shift by the DC group delay alone moves a first-order stage's half-step point 0.31 tau early
    delay = step_check(cal, "delay", rate_hz=100.0)
    assert all(delay[f"{ax}_half_step_s"] < -2 * delay["sample_period_s"] for ax in "xyz"), delay


def test_runs_it_cannot_use_are_refused_with_the_reason(static_cal, tmp_path):
    rec = simulated(1)
    no_aux = rec.select(np.ones(len(rec), bool))
    no_aux.aux = None
    with pytest.raises(DynamicCalibrationError, match="no aux channel"):
        run_dynamic(no_aux, PLAN, static_cal)
    short = rec.select(rec.t_s < 50.0)  # killed early: the 0.5 Hz segment only
    with pytest.raises(DynamicCalibrationError, match=r"only 1 steady segment\(s\)"):
        run_dynamic(short, PLAN, static_cal)
    with pytest.raises(DynamicCalibrationError, match="too short to align"):
        run_dynamic(rec.select(rec.t_s < 20.0), PLAN, static_cal)
    cut = run_dynamic(rec.select(rec.t_s < 90.0), PLAN, static_cal)  # killed in the 5 Hz segment
    assert cut.slide_start_s == pytest.approx(PLAN.start_s, abs=0.1) and len(cut.windows) == 3
    # started late, 1 s into the first segment's steady part: aligned backwards, the segment it cut left out with
    # a note (before: the start was put 24 s late, and the chain fit failed in the driver's range check)
    late = run_dynamic(rec.select(rec.t_s >= PLAN.steady_windows(PLAN.start_s)[0][1] + 1.0), PLAN, static_cal)
    assert late.slide_start_s == pytest.approx(PLAN.start_s, abs=0.1) and len(late.windows) == len(PLAN.segments) - 1
    d = PLAN.to_dict()
    d["direction"] = [1.0, 0.0, 0.05]
    with pytest.raises(DynamicCalibrationError, match="not excited"):
        run_dynamic(rec, ExcitationPlan.from_dict(d), static_cal)
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,ref,x,y,z\n0,1,2,3,4\n")
    with pytest.raises(DynamicCsvError, match="missing column"):
        read_dynamic_csv(bad)


def test_a_segment_with_a_clipped_reading_is_left_out_with_a_note(static_cal):
    """A sine whose peaks hit a rail of the ADC reads a smaller amplitude and a shifted phase: the segment
    that holds a clipped sample (x here, moved up until its peaks clip at 4095) is left out, the rest of the
    run gives the same points as without it."""
    rec, clean = simulated(1), calibrated(1)
    f_hit, a, b = clean.windows[3]
    inside = (rec.t_s >= a) & (rec.t_s <= b)
    x = rec.xyz[:, 0].copy()
    x[inside] = np.minimum(x[inside] + (ADC_MAX - x[inside].max()) + 20.0, ADC_MAX)
    clipped = rec.select(np.ones(len(rec), bool))
    clipped.xyz[:, 0] = x
    res = run_dynamic(clipped, PLAN, static_cal)
    assert f_hit in clean.dynamics.fit["frequencies_hz"] and f_hit not in res.dynamics.fit["frequencies_hz"]
    assert [n for n in res.notes if "clipped" in n and f"{f_hit:g} Hz" in n]
    kept = [p.to_dict() for p in clean.points if p.f_hz != f_hit]
    assert [p.to_dict() for p in res.points] == kept


def test_a_segment_with_the_reference_dark_is_left_out_with_a_note(static_cal):
    """A moment without source light (reference below LOW_REFERENCE_COUNTS: the driver publishes nothing then, the
    static fit leaves such samples out) inside a segment's steady part: Psi = counts / ref is no measurement, so that
    segment is left out, with a note, and the rest of the run gives the same points as without it."""
    rec, clean = simulated(1), calibrated(1)
    f_hit, a, b = clean.windows[3]  # not the sensitivity's reference frequency, which every point is compared with
    dark = rec.select(np.ones(len(rec), bool))
    dark.ref[np.flatnonzero((rec.t_s >= a) & (rec.t_s <= b))[:5]] = 3.0
    res = run_dynamic(dark, PLAN, static_cal)
    assert f_hit in clean.dynamics.fit["frequencies_hz"] and f_hit not in res.dynamics.fit["frequencies_hz"]
    assert [n for n in res.notes if "reference" in n and "dark" in n and f"{f_hit:g} Hz" in n], res.notes
    kept = [p.to_dict() for p in clean.points if p.f_hz != f_hit]
    assert [p.to_dict() for p in res.points] == kept


def test_a_ros2_bag_of_imu_raw_with_aux_counts_is_read(tmp_path, static_cal):
    """What `ros2 bag record /imu/raw` writes from the driver on a version-2 board (written here by
    rosbags, an independent writer)."""
    from rosbags.rosbag2 import StoragePlugin, Writer  # a test dependency: missing, the test fails (no skip)
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    t = ts.types
    rec = simulated(1)
    bag = tmp_path / "bag"
    names = [*RAW_NAMES, RAW_AUX_NAME]
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/veh1/imu/raw", "sensor_msgs/msg/JointState", typestore=ts)
        empty = np.array([], dtype=np.float64)
        for i in range(len(rec)):
            stamp = 1_700_000_000_000_000_000 + round(rec.t_s[i] * 1e9)
            header = t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9),
                                              "fbg_accel_link")
            pos = np.array([rec.ref[i], *rec.xyz[i], rec.temp_c[i], 1.0, 3.0, float(i % 65536), rec.t_s[i], rec.aux[i]])
            msg = t["sensor_msgs/msg/JointState"](header, names, pos, empty, empty)
            w.write(conn, stamp, ts.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
    out = tmp_path / "cal.yaml"
    res = subprocess.run([CLI, "dynamic", str(bag), "--plan", str(REPO / "config" / "excitation_plan_stepped_sine.yaml"),
                          "--calibration", str(default_calibration_path()), "-o", str(out), "--reference-cutoff-hz", "1.0"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    section = yaml.safe_load(out.read_text())["dynamic"]
    assert section["cutoff_hz"]["reference"] == 1.0
    fc_true, _ = _truth()
    for a, ax in enumerate("xyz"):
        assert section["cutoff_hz"][ax] == pytest.approx(fc_true[a + 1], rel=0.06)


def test_board_sim_runs_the_plan_file_with_the_reference_on_aux(tmp_path):
    from fbg_accel_driver.stream_decoder import StreamDecoder

    out = tmp_path / "run.bin"
    res = subprocess.run([str(Path(sys.executable).parent / "board_sim"), "--dynamic-plan",
                          str(REPO / "config" / "excitation_plan_stepped_sine.yaml"), "--rate", "200", "--output", str(out)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    frames = StreamDecoder().feed(out.read_bytes())
    assert len(frames) >= round((PLAN.start_s + PLAN.duration_s) * 200) * 0.99  # the whole plan (link faults aside)
    assert all(f.version == 2 for f in frames)
    aux = np.array([f.aux for f in frames], float)
    assert aux.max() - aux.min() > 500  # the LDV sees the slide
    bad = subprocess.run([str(Path(sys.executable).parent / "board_sim"), "--dynamic-plan", "/nonexistent.yaml",
                          "--output", str(tmp_path / "x.bin")], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "excitation plan not found" in bad.stderr


def test_a_lost_frame_is_harmless_at_rest_and_shortens_its_segment(static_cal):
    """One lost frame (a 2-sample step) at rest before the slide changes nothing; one inside a segment's
    steady part keeps the longest stretch of it without the lost frame, with a note naming its frequency. Both
    made the whole run fail ('time base is not uniformly sampled'); later the segment was left out whole, so four
    lost frames in four steady parts refused the run
    (``test_lost_frames_in_the_steady_parts_keep_their_segments_on_the_longest_uniform_stretch``)."""
    rec, clean = simulated(1), calibrated(1)
    at_rest = run_dynamic(rec.select(np.arange(len(rec)) != 1000), PLAN, static_cal)  # t = 2 s
    assert at_rest.slide_start_s == pytest.approx(clean.slide_start_s, abs=1e-9)
    assert [p.to_dict() for p in at_rest.points] == [p.to_dict() for p in clean.points]
    f_hit, a, b = clean.windows[3]
    lost = run_dynamic(rec.select(np.arange(len(rec)) != int(np.searchsorted(rec.t_s, 0.5 * (a + b)))),
                       PLAN, static_cal)
    assert lost.dynamics.fit["frequencies_hz"] == clean.dynamics.fit["frequencies_hz"]
    assert [n for n in lost.notes if "lost" in n and f"{f_hit:g} Hz" in n]
    assert [p.to_dict() for p in lost.points if p.f_hz != f_hit] == [p.to_dict() for p in clean.points if p.f_hz != f_hit]
    for p, q in zip((p for p in lost.points if p.f_hz == f_hit), (q for q in clean.points if q.f_hz == f_hit), strict=True):
        assert abs(p.sensitivity - q.sensitivity) <= 3 * math.hypot(p.u_sensitivity, q.u_sensitivity)
        assert abs(p.phase_deg - q.phase_deg) <= 3 * math.hypot(p.u_phase_deg, q.u_phase_deg)


def test_fitted_highpass_leaves_the_yaml_and_report_group_delay_equal(static_cal):
    """--fit-highpass: the YAML's dynamic.fit.models.<axis>.group_delay_dc_s, the report's 'group delay at
    DC' and the driver's per-axis group delay are one number (the YAML's had the reference high-pass's
    group delay subtracted: -223 ms against the report's +114 ms for x)."""
    rec = simulated(1)
    res = run_dynamic(rec, PLAN, static_cal, fit_highpass=True)
    report = res.report()
    for a, ax in enumerate("xyz"):
        gd = res.dynamics.fit["models"][ax]["group_delay_dc_s"]
        assert gd == pytest.approx(res.dynamics.group_delay_s(a), rel=1e-12) and gd > 0
        assert [line for line in report.splitlines() if line.startswith(f"| {ax} |") and f"| {gd * 1e3:.2f} |" in line]


def test_an_implausible_chain_fit_is_refused_with_the_reason(static_cal, monkeypatch):
    """A fit that ran away (fc 2e-17 Hz, gain 8e16: what the wrong phase branch gave for a 20-80 Hz plan)
    or that does not describe its points is refused by name instead of failing in ChainDynamics' range
    check ('cutoff_hz of x must be in 0.001..100000 Hz')."""
    import fbg_accel_calibration.dynamic.dynamic_calibration as dc
    from fbg_accel_calibration.dynamic.chain_model import ChainModel

    rec = simulated(1)
    fit = dc.fit_chain_models

    def runaway(points, **kw):
        models = fit(points, **kw)
        models["x"] = ChainModel(gain=8.0e16, cutoff_hz=2.1e-17, delay_s=-4.9e-4, u_gain=1.0, axis="x",
                                 fit={"chi2": 6923.0, "dof": 9, "converged": True})
        return models

    monkeypatch.setattr(dc, "fit_chain_models", runaway)
    with pytest.raises(DynamicCalibrationError, match=r"x: the chain fit is not plausible .*cut-off 2\.1e-17 Hz"):
        run_dynamic(rec, PLAN, static_cal)

    def misfit(points, **kw):
        models = fit(points, **kw)
        models["y"].fit["chi2"] = 2000.0
        return models

    monkeypatch.setattr(dc, "fit_chain_models", misfit)
    with pytest.raises(DynamicCalibrationError, match=r"y: the chain fit is not plausible .*chi2/dof 222"):
        run_dynamic(rec, PLAN, static_cal)


def test_a_segment_of_one_period_is_left_out_with_a_note(static_cal):
    """A steady part holding one whole period (1 Hz, 6.2 s with its ramps and settling: 1.2 s) has no measured
    repeatability: it is left out with a note naming it, the other segments are used as before."""
    d = PLAN.to_dict()
    d["segments"][1]["duration_s"] = 6.2  # 1 Hz
    plan = ExcitationPlan.from_dict(d)
    rec, _, _ = simulate_dynamic_run(plan, rate_hz=RATE_HZ, seed=2)
    res = run_dynamic(rec, plan, static_cal)
    assert 1.0 not in res.dynamics.fit["frequencies_hz"] and len(res.windows) == len(PLAN.segments) - 1
    assert [n for n in res.notes if "1 Hz" in n and "one whole period" in n]
    assert all(p.n_repeats >= 2 for p in res.points)


def test_a_malformed_row_of_a_dynamic_csv_is_named_by_its_line_in_the_file(tmp_path):
    """docs/csv_interchange.md: a bad row is reported with its line number. Comment and blank lines were
    filtered out before the rows were counted, so the message named a line 5 lines early (and a short row
    said "list index out of range")."""
    rows = [f"{i * 0.002:.3f},2000,1500,1600,1700,2048,24.0" for i in range(40)]
    rows[20] = "0.040,2000,abc,1600,1700,2048,24.0"
    rows[30] = "0.060,2000,1500"
    text = "# slide run\n# operator notes\nt_s,ref,x,y,z,aux,temperature_c\n\n" + "\n".join(rows[:10]) + "\n\n# pause\n" \
        + "\n".join(rows[10:]) + "\n"
    path = tmp_path / "dyn.csv"
    path.write_text(text)
    lines = text.splitlines()
    bad = [n for n, line in enumerate(lines, start=1) if "abc" in line or line == rows[30]]
    with pytest.raises(DynamicCsvError) as err:
        read_dynamic_csv(path)
    msg = str(err.value)
    assert f"line {bad[0]}: x = 'abc' is not a number" in msg, (bad, msg)
    assert f"line {bad[1]}: 3 fields, header has 7" in msg, (bad, msg)


def test_lost_frames_in_the_steady_parts_keep_their_segments_on_the_longest_uniform_stretch(static_cal):
    """One frame dropped on the link in the middle of four of the six steady parts (the simulator's
    ``faults.dropped``: 4 frames of 50 000, 0.008 %). Before, each such segment was left out whole and the run was
    refused with "only 2 steady segment(s) in the recording: the chain model needs at least 3 frequencies", a message
    that named neither the lost frames nor the segments they cost. Now a steady part with a lost frame keeps its
    longest stretch without one (a note says so): every frequency stays, and the recovered cut-offs and delays hold
    the simulator's within 3 of their standard uncertainties."""
    clean = calibrated(1)
    hit = [clean.windows[i] for i in (0, 2, 3, 5)]
    rec, _, _ = simulate_dynamic_run(PLAN, rate_hz=RATE_HZ, seed=1,
                                     overrides={"faults.dropped.at_s": [0.5 * (a + b) for _, a, b in hit]})
    assert len(rec) == len(simulated(1)) - 4
    res = run_dynamic(rec, PLAN, static_cal)
    assert res.dynamics.fit["frequencies_hz"] == clean.dynamics.fit["frequencies_hz"]
    note = next(n for n in res.notes if "lost frame" in n)
    assert all(f"{f:g} Hz" in note for f, _, _ in hit), note
    for f, a, b in hit:  # the longer half of the steady part, nothing across the lost frame
        w = next(w for w in res.windows if w[0] == f)
        inside = rec.t_s[(rec.t_s >= w[1]) & (rec.t_s < w[2])]
        assert uniformly_sampled(inside, RATE_HZ) and 0.45 * (b - a) <= w[2] - w[1] <= 0.55 * (b - a), (w, a, b)
    fc_true, delay_true = _truth()
    for i, ax in enumerate("xyz"):
        m = res.models[ax]
        assert abs(m.cutoff_hz - fc_true[i + 1]) <= 3 * m.u_cutoff_hz, (ax, m.cutoff_hz, m.u_cutoff_hz)
        assert abs(m.delay_s - delay_true[i]) <= 3 * m.u_delay_s, (ax, m.delay_s, m.u_delay_s)


def test_a_run_refused_for_too_few_segments_says_what_cost_them(static_cal):
    """A frame lost every 0.3 s (a bad link): no stretch without one holds 2 whole periods below 10 Hz, so only 10 and
    20 Hz remain and the run is refused. Before, the message was "only 2 steady segment(s) in the recording: the chain
    model needs at least 3 frequencies" (the plan has 6; why they went was only in the notes, which a refusal never
    shows). Now the refusal carries the notes: the lost frames and the segments they cost."""
    rec = simulated(1)
    t0 = PLAN.start_s
    every = np.arange(len(rec)) % 150 != 75  # one frame in 150 (0.3 s at 500 Hz) lost
    with pytest.raises(DynamicCalibrationError) as info:
        run_dynamic(rec.select(every | (rec.t_s < t0)), PLAN, static_cal)
    msg = str(info.value)
    assert "only 2 steady segment(s)" in msg and "lost frame" in msg, msg
    assert all(f"{f:g} Hz" in msg for f in (0.5, 1.0, 2.0, 5.0)), msg


def test_the_report_says_where_the_delay_mode_stops_being_a_correction(static_cal):
    """The driver's ``delay`` mode (what ``auto`` picks with a ``dynamic`` section) shifts the stamps by the DC group
    delay, a correction only below about 2.3 fc. On the static-test build (fc 1.3-1.7 Hz) that limit, 4.0 Hz, lies
    inside the measured 0.5-20 Hz, and before the report said nothing of it (the driver's diagnostic was OK too);
    now a note states it, as the driver's diagnostic does. The flight build (fc 50 Hz) gets no such note."""
    res = calibrated(1)
    lim = min(res.dynamics.delay_helps_below_hz())
    assert 0.5 < lim < 20.0
    assert [n for n in res.notes if "'delay'" in n and f"below {lim:.3g} Hz" in n], res.notes
    flight = simulate_dynamic_run(PLAN, rate_hz=RATE_HZ, seed=1,
                                  overrides={"electronics.tia_cutoff_hz": [50.0, 50.0, 50.0, 50.0]})[0]
    res = run_dynamic(flight, PLAN, static_cal)
    assert min(res.dynamics.delay_helps_below_hz()) > 20.0 and not [n for n in res.notes if "'delay'" in n], res.notes


@pytest.mark.parametrize(("reset_at_s", "kept_hz"), [(60.0, [2.0, 5.0, 10.0, 20.0]), (85.0, [0.5, 1.0, 2.0])])
def test_a_board_reset_during_the_run_uses_the_board_run_that_holds_most_of_the_plan(static_cal, reset_at_s, kept_hz):
    """The board reboots during the run (the simulator's ``faults.resets``: its clock restarts at 0, as the raw board
    time of a ``ros2 bag record /imu/raw`` recording does). Before, the two board runs' samples were sorted into one
    time base and interleaved: at 60 s (in the 1 Hz segment) the run was refused with "only 0 steady segment(s) in the
    recording" and notes about lost frames, at 85 s (in the 5 Hz segment) it failed with "segment 1 Hz [22.998,
    36.921) s is not uniformly sampled"; neither named the reset. Now the recording is split where its board time
    goes back, the board run whose alignment with the plan holds the most steady segments is used (after the reset at
    60 s: 2-20 Hz, aligned backwards; before the one at 85 s: 0.5-2 Hz), a note names the reset, and the chain is
    recovered within 3 standard uncertainties."""
    rec, _, _ = simulate_dynamic_run(PLAN, rate_hz=RATE_HZ, seed=2, overrides={"faults.resets.at_s": [reset_at_s]})
    assert np.any(np.diff(rec.t_s) < 0)  # the board clock restarted
    res = run_dynamic(rec, PLAN, static_cal)
    assert res.dynamics.fit["frequencies_hz"] == kept_hz
    assert [n for n in res.notes if "board reset" in n], res.notes
    fc_true, delay_true = _truth()
    for i, ax in enumerate("xyz"):
        m = res.models[ax]
        assert abs(m.cutoff_hz - fc_true[i + 1]) <= 3 * m.u_cutoff_hz, (ax, m.cutoff_hz, m.u_cutoff_hz)
        assert abs(m.delay_s - delay_true[i]) <= 3 * m.u_delay_s, (ax, m.delay_s, m.u_delay_s)
