"""The ESP32 ADC's code widths (issue 38): the code-density estimate (``fbg_accel_calibration.fit.adc_codes``), the
simulator's periodic width pattern, the calibration's code table (``fbg_accel_driver.adc_code_table``) in the file,
``apply_counts`` and the driver. The 10-seed recovery on the simulator is ``bench/adc_code_widths_check.py``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_driver_core import T0_NS, frame, make_cal

from fbg_accel_calibration.commands.cli import main as calib_main
from fbg_accel_calibration.fit.adc_codes import code_table, code_widths, recording_code_widths
from fbg_accel_driver.adc_code_table import ADC_CODES, AdcCodeTable, load_table, pattern_codes, pattern_edges
from fbg_accel_driver.driver_core import DriverCore
from fbg_accel_driver.frame_codec import encode_frame
from fbg_accel_driver.thermal_model import CalibrationFileError, ThermalCalibration
from fbg_accel_sim.board_physics import simulate_recording
from fbg_accel_sim.sim_config import SimConfig

PATTERN = np.asarray(SimConfig.default().get("effects.adc_code_widths.widths"), float)  # the measured series', rounded
CODES = np.arange(ADC_CODES + 1)


def campaign(seed: int, widths: np.ndarray, visits: int = 150, n: int = 24, sigma: float = 1.5):
    """(codes (V n,), visit labels, rows): still inputs spread over 240 codes, Gaussian noise, read by an ADC with
    the width pattern ``widths``."""
    rng = np.random.default_rng(seed)
    level = np.repeat(rng.uniform(1000.0, 1240.0, visits), n)
    codes = pattern_codes(level + rng.normal(0.0, sigma, visits * n), widths)
    return codes, np.repeat(np.arange(visits), n), np.ones(visits * n, bool)


def test_equal_widths_are_the_nominal_codes_and_a_pattern_reads_each_input_in_its_interval() -> None:
    np.testing.assert_array_equal(pattern_edges(np.ones(16), CODES), CODES - 0.5)
    e = pattern_edges(PATTERN, CODES)
    centres = 0.5 * (e[:-1] + e[1:])
    assert abs(np.mean(centres - CODES[:-1])) < 1e-9 and np.ptp(centres - CODES[:-1]) > 0.5  # no offset, an INL
    x = np.linspace(500.0, 700.0, 20001)
    k = pattern_codes(x, PATTERN).astype(int)
    assert np.all(e[k] <= x) and np.all(x < e[k + 1])


def test_expected_hits_from_each_sample_s_reach_are_the_sums_of_the_whole_table_bit_for_bit() -> None:
    """``expected_hits`` evaluates only the edges within a sample's reach; the figures are those of every sample's CDF
    at every edge summed down the codes, a block of ``EXPECTED_BLOCK`` samples at a time, to the last bit: for noise
    far below a code (a piece reading one code), of a few counts, and wider than the codes read (every edge in reach),
    over more samples than one block, and for samples beyond either end of the codes."""
    from scipy.special import ndtr

    from fbg_accel_calibration.fit.adc_codes import EXPECTED_BLOCK, expected_hits

    rng = np.random.default_rng(4)
    for sigma_log in ((-20.0, 1.0), (-3.0, 2.0), (3.0, 5.0)):
        codes = np.arange(900, 1200)
        edges = pattern_edges(PATTERN, np.append(codes, codes[-1] + 1))
        n = EXPECTED_BLOCK + 1500
        m = rng.uniform(860.0, 1240.0, n)
        sg = 0.05 + np.exp(rng.uniform(*sigma_log, n))
        whole = np.zeros(len(codes))
        for b in range(0, n, EXPECTED_BLOCK):
            cdf = ndtr((edges[None, :] - m[b:b + EXPECTED_BLOCK, None]) / sg[b:b + EXPECTED_BLOCK, None])
            whole += np.diff(cdf, axis=1).sum(axis=0)
        np.testing.assert_array_equal(expected_hits(edges, m, sg), whole)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_injected_pattern_is_recovered_within_its_stated_uncertainty(seed: int) -> None:
    """95 % intervals: about 15 of 16 widths in each; 12 leaves the margin. The pattern is found by far."""
    w = code_widths(*campaign(seed, PATTERN), "x")
    assert np.sum(np.abs(w.pattern - PATTERN) <= w.pattern_u95) >= 12, (w.pattern.round(2), w.pattern_u95.round(2))
    assert w.pattern_found and w.p_value < 1e-10


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_with_equal_widths_no_pattern_is_claimed_and_the_table_is_nominal(seed: int) -> None:
    codes, groups, rows = campaign(seed, np.ones(16))
    counts = np.column_stack([codes - 200.0, codes, codes + 300.0, codes + 40.0])
    res = recording_code_widths(counts, groups, rows, per_channel=False)
    assert res.pooled is not None and res.pooled.p_value > 1e-3, res.summary()
    table = code_table(res, {"source": "test"})
    np.testing.assert_array_equal(table.edges, np.tile(CODES - 0.5, (4, 1)))


def test_the_simulated_pattern_is_recovered_and_its_table_removes_the_bias() -> None:
    """The simulator's ``adc_code_widths`` on an 84-pose campaign with the measured board's noise: the pooled pattern
    holds the injected widths in its intervals, and the table brings the visits' mean codes back to those read without
    the pattern (same seed, same noise) far better than the raw codes."""
    base = {**{f"effects.{k}.scale": 0.0 for k in ("reference_dark_offset", "thermal_lag", "spectral_nonlinearity",
                                                    "time_drift", "channel_delay", "tia_lowpass", "thermal_hysteresis",
                                                    "unmodelled_cable_torque")},
            "scenario.poses.mode": "grid", "scenario.poses.dwell_s": 1.0, "scenario.poses.move_s": 1.0,
            "scenario.poses.grid.theta_step_deg": 60.0, "scenario.poses.grid.psi_step_deg": 30.0,
            "noise.reference_noise_counts": 1.0, "effects.white_noise.scale": 3.0}
    on = simulate_recording(SimConfig.default().with_overrides({**base, "effects.adc_code_widths.scale": 1.0}), seed=5)
    off = simulate_recording(SimConfig.default().with_overrides(base), seed=5)
    from fbg_accel_calibration.commands.adc_codes_cli import visits_of

    groups, rows = visits_of(on)
    res = recording_code_widths(np.column_stack([on.ref, on.xyz]), groups, rows, per_channel=False)
    p = res.pooled
    assert np.sum(np.abs(p.pattern - PATTERN) <= p.pattern_u95) >= 12, (p.pattern.round(2), p.pattern_u95.round(2))
    table = code_table(res, {"source": "test"})
    ref_c, xyz_c = table.map_counts(on.ref, on.xyz)
    _, inv = np.unique(groups[rows], return_inverse=True)

    def means(c: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(inv, c[rows, j]) / np.bincount(inv) for j in range(4)], axis=1)

    truth = means(np.column_stack([off.ref, off.xyz]))
    before = np.sqrt(np.mean((means(np.column_stack([on.ref, on.xyz])) - truth) ** 2))
    after = np.sqrt(np.mean((means(np.column_stack([ref_c, xyz_c])) - truth) ** 2))
    assert before > 0.15 and after < 0.5 * before, (before, after)


def _table() -> AdcCodeTable:
    return AdcCodeTable(np.tile(pattern_edges(PATTERN, CODES), (4, 1)), {"source": "test"})


def test_the_table_round_trips_through_the_calibration_file_and_without_it_nothing_changes(tmp_path) -> None:
    ref = np.array([870.0, 871.0, 880.0])
    xyz = np.array([[1100.0, 1536.0, 1100.0], [1101.0, 1544.0, 1102.0], [1120.0, 1600.0, 1008.0]])
    t, temp = np.zeros(3), np.full(3, 25.0)
    plain, with_table = make_cal(), make_cal(adc_codes=_table())
    assert "adc_codes" not in plain.to_dict()
    nominal = make_cal(adc_codes=AdcCodeTable(np.tile(CODES - 0.5, (4, 1))))
    np.testing.assert_array_equal(plain.apply_counts(ref, xyz, temp, t), nominal.apply_counts(ref, xyz, temp, t))
    with_table.save(tmp_path / "cal.yaml")
    back = ThermalCalibration.load(tmp_path / "cal.yaml")
    assert back.adc_codes == with_table.adc_codes
    centred = make_cal().apply_counts(*_table().map_counts(ref, xyz), temp, t)
    np.testing.assert_array_equal(back.apply_counts(ref, xyz, temp, t), centred)
    assert np.max(np.abs(centred - plain.apply_counts(ref, xyz, temp, t))) > 0.01


@pytest.mark.parametrize("edit, message", [
    (lambda e: e[:-1], "has 4096 entries, expected 4097"),
    (lambda e: [*e[:100], e[101], e[100], *e[102:]], "the intervals are not monotone: code 100"),
])
def test_a_table_of_the_wrong_size_or_with_intervals_out_of_order_is_refused_in_one_line(tmp_path, edit, message) -> None:
    d = make_cal(adc_codes=_table()).to_dict()
    d["adc_codes"]["edges"]["y"] = edit(d["adc_codes"]["edges"]["y"])
    with pytest.raises(CalibrationFileError) as exc:
        ThermalCalibration.from_dict(d, source="cal.yaml")
    assert message in str(exc.value) and "adc_codes.edges.y" in str(exc.value) and "\n" not in str(exc.value)


def test_the_driver_maps_each_count_as_apply_counts_does() -> None:
    cal = make_cal(adc_codes=_table())
    rng = np.random.default_rng(3)
    frames = [frame(i, ref=int(rng.integers(860, 880)), xyz=tuple(int(v) for v in rng.integers(1000, 1700, 3)))
              for i in range(120)]
    data = b"".join(encode_frame(f) for f in frames)
    core = DriverCore(cal)
    got = np.array([r.accel_mps2 for k in range(0, len(data), 270)
                    for r in core.feed(data[k:k + 270], T0_NS + k // 27 * 10_000_000 + 2_000_000).imu])
    ref = np.array([f.ref for f in frames], float)
    xyz = np.array([(f.x, f.y, f.z) for f in frames], float)
    offline = cal.apply_counts(ref, xyz, np.full(len(frames), 23.4), np.arange(len(frames)) * 0.01)
    np.testing.assert_allclose(got, offline[-len(got):], rtol=0, atol=1e-9)
    # a field wider than the ADC's codes (no reading of this ADC) is used as read by both paths, never looked up
    table = cal.adc_codes
    assert table.values(870, 1100, 5000, 1100)[2] == 5000
    assert table.map_counts(np.array([870.0]), np.array([[1100.0, 5000.0, -1.0]]))[1][0, 1:].tolist() == [5000.0, -1.0]
    core.feed(encode_frame(frame(len(frames), ref=870, xyz=(1100, 5000, 1100))), T0_NS + 10 ** 10)
    assert np.max(np.abs(offline - make_cal().apply_counts(ref, xyz, np.full(len(frames), 23.4), np.zeros(len(frames))))) > 0.01


def test_adc_codes_command_writes_a_table_the_loader_reads_and_refuses_too_few_visits(tmp_path, capsys) -> None:
    codes, groups, _ = campaign(4, PATTERN, visits=80, n=12)
    rows = ["t_s,ref_counts,x_counts,y_counts,z_counts,temperature_c,psi_deg,theta_deg"]
    for i, (c, g) in enumerate(zip(codes, groups, strict=True)):
        rows.append(f"{i * 0.01:.2f},{int(c) - 200},{int(c)},{int(c) + 300},{int(c) + 40},23.4,{(g % 12) * 30},"
                    f"{(g // 12) * 30}")
    csv = tmp_path / "run.csv"
    csv.write_text("\n".join(rows) + "\n", encoding="utf-8")
    out = tmp_path / "codes.yaml"
    assert calib_main(["adc-codes", str(csv), "-o", str(out), "--plot", str(tmp_path / "w.png")]) == 0
    table = load_table(out)
    assert table.provenance["pattern"].startswith("found")
    assert "pooled widths" in capsys.readouterr().out
    bad = tmp_path / "short.csv"
    bad.write_text("\n".join(rows[:200]) + "\n", encoding="utf-8")  # 16 visits: too few for the pattern
    assert calib_main(["adc-codes", str(bad), "-o", str(tmp_path / "no.yaml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the width pattern needs at least 32" in err
    assert not (tmp_path / "no.yaml").exists()


# ../shared next to the repository (a worktree one level deeper finds it one level up)
MEASURED = next((p / "shared" / "data" / "measured" / "fig13_multiposition_23C.csv"
                 for p in Path(__file__).resolve().parents[2:4]
                 if (p / "shared" / "data" / "measured" / "fig13_multiposition_23C.csv").is_file()),
                Path(__file__).resolve().parents[2] / "shared" / "data" / "measured" / "fig13_multiposition_23C.csv")


def test_measured_series_pattern_is_found_and_fit_carries_the_table_it_was_fitted_with(tmp_path) -> None:
    """The measured series (issue 38): the pooled pattern is found far beyond its level, codes 16k wider and 16k + 8
    narrower than nominal; ``fit --adc-codes`` maps the counts before eq. 24 and writes the same table into the
    calibration, whose ``apply_counts`` on the raw counts is the no-table model on the mapped ones."""
    assert MEASURED.is_file(), f"measured data not found: {MEASURED} (../shared/data/measured/ is needed for this test)"
    table_path, cal_path = tmp_path / "codes.yaml", tmp_path / "cal.yaml"
    common = ["--rate", "1", "--temperature", "23.4", "--g", "9.81"]
    assert calib_main(["adc-codes", str(MEASURED), *common, "-o", str(table_path)]) == 0
    table = load_table(table_path)
    assert table.provenance["pattern"].startswith("found")
    widths = np.diff(table.edges[1, 1024:1041])  # x: codes 1024..1039, one period
    assert widths[0] > 1.3 and widths[8] < 0.6, widths.round(2)
    kept = table_path.read_bytes()  # the table read is an input: never written over, even with --force
    for cmd in (["fit", str(MEASURED)], ["diagnose", str(MEASURED), "--out", str(tmp_path / "d.md")]):
        out = ["-o" if cmd[0] == "fit" else "--yaml", str(table_path)]
        assert calib_main([*cmd, *common, "--adc-codes", str(table_path), *out, "--force"]) == 2
        assert table_path.read_bytes() == kept
    assert calib_main(["fit", str(MEASURED), *common, "--adc-codes", str(table_path), "-o", str(cal_path)]) == 0
    cal = ThermalCalibration.load(cal_path)
    assert cal.adc_codes == table
    ref, xyz = np.array([870.0, 866.0]), np.array([[1100.0, 1600.0, 1100.0], [1024.0, 1536.0, 1048.0]])
    t = np.full(2, 23.4)
    bare = ThermalCalibration.from_dict({**cal.to_dict(), "adc_codes": None})
    np.testing.assert_array_equal(cal.apply_counts(ref, xyz, t, t), bare.apply_counts(*table.map_counts(ref, xyz), t, t))
