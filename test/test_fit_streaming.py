"""The streamed fit from MCAP (``fit_stream.prepare_stream`` + ``mcap_reader.McapSampleStream``) equals the
in-memory fit (``read_recording`` + ``prepare`` + ``select_degree`` + ``fit_thermal``) on generated files,
including a truncated one, and its memory does not grow with the number of samples."""

from __future__ import annotations

import math
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest

from fbg_accel_calibration.commands.cli import main as cli_main
from fbg_accel_calibration.fit import fit_stream, noise_correlation, static_detector
from fbg_accel_calibration.fit.fit_stream import prepare, prepare_stream
from fbg_accel_calibration.fit.model_selection import select_degree
from fbg_accel_calibration.fit.thermal_fit import TemperatureClusters, temperature_levels
from fbg_accel_calibration.io import mcap_reader
from fbg_accel_calibration.io.mcap_reader import McapSampleStream, StreamOrderError, read_recording
from fbg_accel_calibration.io.mcap_writer import RecordingWriter, write_recording
from fbg_accel_calibration.io.recording import Recording
from fbg_accel_driver.thermal_model import ThermalCalibration

G = 9.80665


def make_run(seed: int, temp_c: float, n_poses: int = 10, sweep_c: float = 0.0, t0_s: float = 0.0) -> Recording:
    """A calibration run: moves (pose -1, no reference, Psi ramping) between dwells of random length,
    Psi spikes that break static intervals into short pieces, a few invalid temperatures, and a
    temperature either at a set-point (noise 0.05 degC) or sweeping ``sweep_c`` degC over the run."""
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(n_poses, 3))
    poses = G * dirs / np.linalg.norm(dirs, axis=1)[:, None]
    pose_id, gref = [], []
    for k in range(n_poses):
        move, dwell = int(rng.integers(2, 12)), int(rng.integers(60, 250))
        pose_id += [-1] * move + [k] * dwell
        gref += [[np.nan] * 3] * move + [poses[k]] * dwell
    pose_id, gref = np.asarray(pose_id), np.asarray(gref, dtype=float)
    n = len(pose_id)
    temp = temp_c + (np.linspace(0.0, sweep_c, n) if sweep_c else rng.normal(0.0, 0.05, n))
    m_inv = np.diag([1 / 80.0, 1 / 78.0, 1 / 107.0]) + rng.normal(0.0, 1e-4, (3, 3))
    g_fill = np.where(np.isfinite(gref), gref, rng.normal(0.0, G, (n, 3)))  # the table moves: any direction
    psi = (g_fill @ m_inv.T) * (1.0 + 2e-3 * (temp - 25.0))[:, None] + 1e-2 * (temp - 25.0)[:, None] + 0.5
    psi += rng.normal(0.0, 3e-4, psi.shape)
    psi[rng.random(n) < 0.01] += 0.05  # spikes: short static pieces around them
    temp[rng.random(n) < 0.005] = np.nan
    ref = 900.0 + rng.normal(0.0, 1.0, n)
    return Recording(t0_s + np.arange(n) * 0.01, ref, psi * ref[:, None], temp, gref, pose_id)


@pytest.fixture
def small_blocks(monkeypatch: pytest.MonkeyPatch) -> int:
    """Blocks of 301 samples in both paths, so every file spans many blocks and carries between them;
    decompressed chunks are split 16 KiB at a time (instead of 1 MiB) so the small files exceed it."""
    monkeypatch.setattr(mcap_reader, "_JOIN_BYTES", 1 << 14)
    monkeypatch.setattr(static_detector, "BLOCK_ROWS", 301)
    monkeypatch.setattr(fit_stream, "BLOCK_ROWS", 301)
    return 301


@pytest.fixture
def runs(tmp_path: Path) -> list[Path]:
    """Three set-point runs and a sweep; the last set-point file is cut inside a chunk (a SIGKILLed writer)."""
    paths = []
    for i, (temp, sweep) in enumerate([(15.0, 0.0), (25.0, 0.0), (31.0, 7.0), (40.0, 0.0)]):
        path = tmp_path / f"run{i}.mcap"
        write_recording(path, make_run(i, temp, sweep_c=sweep), {"sensor_id": "fbg-test"})
        paths.append(path)
    data = paths[-1].read_bytes()
    paths[-1].write_bytes(data[: int(len(data) * 0.6)])
    return paths


def _assert_same_fit(a: ThermalCalibration, b: ThermalCalibration) -> None:
    np.testing.assert_allclose(b.M, a.M, rtol=1e-9, atol=1e-9 * np.abs(a.M).max())
    np.testing.assert_allclose(b.b, a.b, rtol=1e-9, atol=1e-9 * np.abs(a.b).max())
    np.testing.assert_allclose(b.noise_sigma_mps2, a.noise_sigma_mps2, rtol=1e-6)
    assert (b.t_center_c, b.t_scale_c, b.temperature_range_c) == (a.t_center_c, a.t_scale_c, a.temperature_range_c)
    for key, value in a.fit.items():
        if key in ("rmse_mps2", "rmse_over_full_scale", "within_pose_noise_mps2", "condition_number_scaled"):
            np.testing.assert_allclose(b.fit[key], value, rtol=1e-6)
        elif key == "degree_selection":
            _assert_same_selection(value, b.fit[key])
        else:
            assert b.fit[key] == value, key


def _assert_same_selection(a: dict, b: dict) -> None:
    skip = ("degrees", "level_means_c")
    assert {k: v for k, v in a.items() if k not in skip} == {k: v for k, v in b.items() if k not in skip}
    np.testing.assert_allclose(b["level_means_c"], a["level_means_c"], rtol=1e-13)
    for da, db in zip(a["degrees"], b["degrees"], strict=True):
        assert (da["degree"], da["identified"], da["note"]) == (db["degree"], db["identified"], db["note"])
        for key in ("in_sample_rmse_mps2", "held_out_pose_rmse_mps2", "held_out_level_rmse_mps2"):
            np.testing.assert_allclose(db[key], da[key], rtol=1e-6)


@pytest.mark.parametrize(("window", "min_interval"), [(5, 5), (8, 3)])
def test_files_read_whole_or_block_by_block_give_the_same_preparation(runs: list[Path], small_blocks: int, window: int,
                                                                      min_interval: int) -> None:
    """The one preparation (fit_stream.prepare_stream) of the runs read into memory and of the files streamed: the
    selection, levels, scaling, per-cell sums and degree selection are the same bit for bit."""
    rec = read_recording(runs)
    assert not rec.metadata["parts"][-1]["read_report"]["complete"]
    data = prepare(rec, 3, window, min_interval, chunk=700)
    streams = [McapSampleStream(p) for p in runs]
    sd = prepare_stream(streams, 3, window, min_interval, chunk=700)
    assert not streams[-1].report.complete and streams[0].report.complete
    assert (sd.n_used, sd.n_total, sd.n_excluded_motion, sd.n_excluded_other) == (
        data.n_used, data.n_total, data.n_excluded_motion, data.n_excluded_other)
    assert 0 < data.n_excluded_motion and 0 < data.n_excluded_other
    assert sd.detector == data.detector
    assert len(sd.level_means_c) >= 5  # the sweep is split into bins
    assert np.array_equal(sd.level_means_c, data.level_means_c)
    assert (sd.t_center_c, sd.t_scale_c, sd.temperature_range_c) == (data.t_center_c, data.t_scale_c,
                                                                      data.temperature_range_c)
    for name in ("pose", "level", "xtx", "xtg", "gtg", "xsum", "gsum", "count"):
        assert np.array_equal(getattr(sd.stats, name), getattr(data.stats, name)), name
    sel = select_degree(data, 3)
    assert sel.chosen_degree is not None
    assert sel.as_dict() == select_degree(sd, 3).as_dict()


def test_the_detector_decides_each_block_once_and_the_sums_are_those_of_deciding_it_again(
        runs: list[Path], small_blocks: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """After the noise floor, the static detector's decisions of the first pass over a run are kept for the next one
    (``pass_spill.PassSpill``): the preparation is bit for bit the one that runs the detector in both passes."""
    calls: list[int] = []
    original = fit_stream.usable_blocks

    def counted(*args: object, **kwargs: object):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(fit_stream, "usable_blocks", counted)
    kept = prepare_stream([McapSampleStream(p) for p in runs], 3, chunk=700)
    assert len(calls) == len(runs)
    with monkeypatch.context() as m:
        m.setattr(fit_stream, "PassSpill", lambda *args, **kwargs: None)  # nothing kept: decided in both passes
        again = prepare_stream([McapSampleStream(p) for p in runs], 3, chunk=700)
    assert len(calls) == 3 * len(runs)
    assert (kept.n_used, kept.n_total, kept.n_excluded_motion, kept.detector) == (
        again.n_used, again.n_total, again.n_excluded_motion, again.detector)
    for name in ("pose", "level", "xtx", "xtg", "gtg", "xsum", "gsum", "count"):
        assert np.array_equal(getattr(kept.stats, name), getattr(again.stats, name)), name


def test_cli_fit_streams_the_files_and_writes_the_in_memory_result(runs: list[Path], tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    files = [str(p) for p in runs]
    assert cli_main(["fit", *files, "--in-memory", "-o", str(tmp_path / "mem.yaml")]) == 0

    def no_whole_file(*args: object, **kwargs: object) -> None:
        raise AssertionError("the streaming fit must not read a whole file")

    monkeypatch.setattr(mcap_reader, "read_file", no_whole_file)
    monkeypatch.setattr(mcap_reader, "read_recording", no_whole_file)
    reads: list[Path] = []  # the passes after the first take the samples it kept: each file is read once
    original = McapSampleStream._file_batches

    def counted(self: McapSampleStream, path: Path, *args: object):
        reads.append(path)
        return original(self, path, *args)

    monkeypatch.setattr(McapSampleStream, "_file_batches", counted)
    monkeypatch.setattr(mcap_reader, "REPLAY_ROWS", 777)  # kept batches given back cut elsewhere than read
    capsys.readouterr()
    assert cli_main(["fit", *files, "-o", str(tmp_path / "stream.yaml")]) == 0
    assert sorted(reads) == sorted(runs)
    err = capsys.readouterr().err
    assert f"warning: {runs[-1]} is truncated" in err  # the first pass's report stands for the truncated file
    mem, streamed = ThermalCalibration.load(tmp_path / "mem.yaml"), ThermalCalibration.load(tmp_path / "stream.yaml")
    assert streamed.sensor_id == mem.sensor_id == "fbg-test"
    assert streamed.fit["degree"] == mem.fit["degree"]
    _assert_same_fit(mem, streamed)


def test_a_run_longer_than_the_noise_sample_is_not_reported_truncated(runs: list[Path], tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """The streamed fit reads the first samples of the first run once more for the noise model
    (``noise_correlation.SAMPLE_ROWS``, 65 536) and stops there. That partial pass must not stand for the file: before,
    the reader's report was the one of its last pass, so every first file longer than the sample (11 min at 100 Hz,
    66 s at 1 kHz) was called truncated on stderr: a simulated 1 kHz six-position run of 230 004 samples, read whole
    (all 539 949 static samples of the three runs fitted), gave ``warning: run0_16C.mcap is truncated (); recovered
    66860 messages up to the last complete chunk``. Here the sample is shrunk to 301 rows so that the small files
    exceed it; the unchanged code printed that warning for ``run0.mcap`` (recovered 348 of its messages)."""
    monkeypatch.setattr(noise_correlation, "SAMPLE_ROWS", 301)
    files = [str(p) for p in runs]
    capsys.readouterr()
    assert cli_main(["fit", *files, "-o", str(tmp_path / "cal.yaml")]) == 0
    err = capsys.readouterr().err
    assert f"warning: {runs[0]} is truncated" not in err, err
    assert f"warning: {runs[-1]} is truncated" in err  # the file that is cut is still named
    # the reader itself: a pass its consumer closes early leaves the report of the last pass that read the file
    stream = McapSampleStream(runs[0])
    n = sum(len(b) for b in stream.blocks(301, False))
    full = stream.report.as_dict()
    assert full["complete"] and full["per_topic"]["/imu/raw"] == n > 301
    blocks = stream.blocks(301, True)
    next(iter(blocks))
    blocks.close()
    assert stream.report.as_dict() == full
    assert stream.metadata()["read_report"] == full


def test_streaming_memory_does_not_grow_with_the_samples(tmp_path: Path, small_blocks: int) -> None:
    """Peak traced memory of the streamed preparation for 8x more samples (same poses, cells and
    levels) stays within 25 % of the small case (reading them into memory, read_recording + prepare, peaks 0.8 MB -> 6.5 MB)."""
    peaks = []
    for n_copies in (1, 8):
        parts = [make_run(10 + k, 20.0, n_poses=6, t0_s=100.0 * k) for k in range(n_copies)]
        path = tmp_path / f"big{n_copies}.mcap"
        write_recording(path, Recording.concatenate(parts).select(slice(None)), {})
        src = McapSampleStream(path)
        list(src.blocks(small_blocks, with_poses=False))  # warm-up: decoder and schema caches
        tracemalloc.start()
        sd = prepare_stream([src], 1, chunk=500)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        assert sd.n_total == sum(len(p) for p in parts)
    assert peaks[1] < 1.25 * peaks[0], peaks


def test_exact_streaming_median_equals_nanmedian() -> None:
    rng = np.random.default_rng(3)
    passes_seen = set()
    for n, cap in ((1, 4), (2, 4), (1001, 4), (1000, 1 << 18), (5000, 16), (20000, 1 << 18)):
        values = rng.chisquare(4, size=(n, 3)) * 1e-7
        values[rng.random((n, 3)) < 0.1] = np.nan
        values[: n // 3, 1] = np.round(values[: n // 3, 1], 8)  # ties
        values[0, 0] = -0.0
        med = static_detector.ExactMedian(3, cap=cap)
        passes = 0
        while not med.done:
            for part in np.array_split(values, 7):
                med.add(part)
            med.end_pass()
            passes += 1
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN column
            expected = np.nanmedian(values, axis=0)
        assert np.array_equal(med.result, expected, equal_nan=True), (n, cap)
        passes_seen.add(passes)
    shifted = np.r_[rng.chisquare(4, 3000) * 1e-7, rng.chisquare(4, 9000) * 1e-5][:, None]  # first block misleads
    med = static_detector.ExactMedian(1)
    passes = 0
    while not med.done:
        for part in np.array_split(shifted, 4):
            med.add(part)
        med.end_pass()
        passes += 1
    assert med.result[0] == np.median(shifted) and passes >= 2
    assert 1 in passes_seen and max(passes_seen) >= 3  # speculation hit; radix refinement with a small cap


def test_temperature_levels_added_in_parts_equal_those_added_at_once() -> None:
    """The streamed fit adds a file's temperatures block by block; in memory they are added at once."""
    rng = np.random.default_rng(5)
    temps = np.concatenate([rng.normal(16, 0.1, 500), rng.normal(24, 0.3, 700), np.linspace(30, 41, 900),
                            rng.normal(45, 0.05, 300), [17.05, 17.9]])
    rng.shuffle(temps)
    labels, means = temperature_levels(temps)
    clusters = TemperatureClusters(1.0)
    for part in np.array_split(temps, 13):
        clusters.add(part)
    clusters.finish()
    provisional = clusters.labels(temps)
    present = np.flatnonzero(np.bincount(provisional))
    relabel = np.full(clusters.n_labels, -1)
    relabel[present] = np.arange(len(present))
    assert np.array_equal(relabel[provisional], labels)
    assert len(means) == len(present) >= 7


def test_backward_stamps_are_refused_by_the_stream_and_the_cli_reads_in_memory(tmp_path: Path,
                                                                               capsys: pytest.CaptureFixture[str]) -> None:
    rec = make_run(7, 25.0, n_poses=6)
    path = tmp_path / "shuffled.mcap"
    stamps = np.round(rec.t_s * 1e9).astype(np.int64)
    order = np.arange(len(rec))
    order[100], order[101] = 101, 100
    with RecordingWriter(path, {"sensor_id": "x"}) as w:
        last_pose = None
        for i in order:
            pose = int(rec.pose_id[i])
            if pose != last_pose:
                if pose >= 0:
                    w.write_reference_gravity(int(stamps[i]), rec.gref_mps2[i])
                w.write_pose(int(stamps[i]), pose, "recording" if pose >= 0 else "moving")
                last_pose = pose
            t = float(rec.temp_c[i])
            w.write_raw(int(stamps[i]), rec.ref[i], rec.xyz[i], temperature_c=t, temperature_valid=math.isfinite(t))
    with pytest.raises(StreamOrderError, match="stamps go backwards"):
        list(McapSampleStream(path).blocks(1000, with_poses=False))
    assert cli_main(["fit", str(path), "--degree", "0", "-o", str(tmp_path / "cal.yaml")]) == 0
    assert "reading all samples into memory instead" in capsys.readouterr().err


def test_the_within_visit_factor_is_what_the_pooled_scatter_of_correlated_noise_expects() -> None:
    """``noise_correlation.within_visit_factor``: short visits of first-order noise (f = 0.9, tau = 8 samples, the TIA
    low-pass at 100 Hz) scatter about their own means by less than the noise variance, because each mean takes more
    than 1/n of it. The pooled within-visit variance (n_v - 1 degrees of freedom each, as the fit divides) over
    sigma^2 matches the factor; the fit's published sigma is divided by its square root (``fit_pipeline``). White
    noise: 1. The fit had published that scatter as the noise variance."""
    from fbg_accel_calibration.fit.noise_correlation import NoiseCorrelation, within_visit_factor

    rng = np.random.default_rng(7)
    f, tau, dt, n, visits = 0.9, 0.08, 0.01, 60, 4000
    a = np.exp(-dt / tau)
    gm = np.empty((visits, n))
    gm[:, 0] = rng.standard_normal(visits)
    for k in range(1, n):
        gm[:, k] = a * gm[:, k - 1] + np.sqrt(1 - a * a) * rng.standard_normal(visits)
    x = np.sqrt(f) * gm + np.sqrt(1 - f) * rng.standard_normal((visits, n))  # variance 1, rho_k = f a^k
    pooled = float(np.sum((x - x.mean(axis=1, keepdims=True)) ** 2) / (visits * (n - 1)))
    corr = NoiseCorrelation(np.full(3, f), np.full(3, tau), visits, visits * n)
    factor = within_visit_factor(corr, dt, np.full(visits, n))
    assert pooled < 0.85 and np.allclose(factor, pooled, rtol=0.02)  # factor 0.803 (docs/calibration_fit.md)
    assert np.allclose(within_visit_factor(NoiseCorrelation(np.zeros(3), np.zeros(3), 1, n), dt, [n]), 1.0)
