"""Files to a fitted calibration: the one fit path of ``fbg-accel-calib fit`` and of the calibration node.

MCAP inputs (and rosbag2 bags) are streamed block by block into the fit's cell sums
(``fit_stream.prepare_stream``; CSV files are re-read on every pass), so memory is a few blocks
whatever the file sizes; an MCAP whose raw stamps go backwards, or ``in_memory=True``, loads every
sample first, then goes through the same preparation run by run (``fit_stream.prepare``). Then: degree
by held-out cross-validation (``model_selection.select_degree``) unless given, eq. 28
(``fit_thermal``), and the noise model of the calibrated output (``noise_correlation``) on
the first samples of the first input. Pure: no argparse, no ROS.
"""

from __future__ import annotations

import datetime as _dt
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fbg_accel_driver.coefficient_covariance import CoefficientCovariance
from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2, LOW_REFERENCE_COUNTS, STANDARD_GRAVITY
from fbg_accel_driver.thermal_model import ThermalCalibration

from ..io.input_validation import DEFAULT_MAX_DEGREE
from ..io.recording import Recording
from .coefficient_uncertainty import cluster_covariance
from .fit_stream import FitData, prepare, prepare_stream
from .model_selection import SelectionResult, select_degree
from .slow_error import attach as attach_slow_error
from .slow_error import check_same_sensor
from .static_detector import DEFAULT_MIN_INTERVAL, DEFAULT_WINDOW
from .thermal_fit import (
    DEFAULT_CHUNK,
    DEFAULT_LEVEL_GAP_C,
    NotIdentifiedError,
    check_identified,
    check_level_consistency,
    check_level_excitation,
    check_pose_excitation,
    coefficients_to_model,
    reference_range,
    sensor_id_of,
    solve_normal_equations,
)


def fit_thermal(rec: Recording | FitData, degree: int, *, sensor_id: str | None = None,
                window: int = DEFAULT_WINDOW, min_interval: int = DEFAULT_MIN_INTERVAL,
                level_gap_c: float = DEFAULT_LEVEL_GAP_C, chunk: int = DEFAULT_CHUNK,
                usable: np.ndarray | None = None) -> ThermalCalibration:
    """Fit eq. 28 of degree ``degree`` to a recording, or to the data ``fit_stream.prepare`` or
    ``fit_stream.prepare_stream`` prepared (:class:`fit_stream.FitData`, accumulated at a degree >= ``degree``).

    The result's ``fit`` dict holds sample counts, temperature levels, the in-sample RMSE per axis
    (m/s^2 and normalised by the 20 g full scale), the within-pose noise floor of the calibrated
    output and the condition number. ``noise_sigma_mps2`` is that within-pose noise floor.
    """
    if isinstance(rec, Recording):
        data = prepare(rec, degree, window, min_interval, level_gap_c, usable, chunk)
    else:
        data = rec
    if len(data) == 0:
        raise NotIdentifiedError("no usable static samples (check pose ids, reference and the static detector)")
    check_identified(degree, len(data.level_means_c))
    if data.n_poses < 4:
        raise NotIdentifiedError(f"{data.n_poses} orientation(s): at least 4 non-coplanar poses are needed for M and b")
    center, scale = data.t_center_c, data.t_scale_c
    stats = data.cell_stats(degree, chunk)
    spread = check_pose_excitation(stats)
    check_level_excitation(stats, degree)
    check_level_consistency(stats, data.level_means_c)
    xtx, xtg, _, n = stats.select(np.ones(len(stats.count), bool), degree)
    A, cond = solve_normal_equations(xtx, xtg)
    rss = stats.cell_rss(A, degree).sum(axis=0)
    rmse = np.sqrt(rss / n)
    noise = np.sqrt(stats.visit_scatter(A, degree) / max(n - stats.n_visits, 1.0))
    M, b = coefficients_to_model(A, degree)
    cov, cov_method, clusters = cluster_covariance(stats, A, degree)
    src = rec.metadata.get("sources", rec.metadata.get("source")) if isinstance(rec, Recording) else None
    fit_info = {
        "method": "least squares, eq. 28-30, streamed normal equations",
        "degree": degree,
        "samples_used": int(n),
        "samples_total": data.n_total,
        "samples_excluded_in_motion": data.n_excluded_motion,
        "samples_excluded_invalid": data.n_excluded_other,
        "samples_excluded_clipped": data.n_excluded_clipped,  # their visit has a channel at an ADC rail
        "visits_excluded_clipped": data.n_clipped_visits,
        "samples_excluded_low_reference": data.n_excluded_low_reference,  # no source light (Recording.low_reference)
        "poses": data.n_poses,
        "temperature_levels_c": [round(float(v), 3) for v in data.level_means_c],
        "rmse_mps2": rmse.tolist(),
        "rmse_over_full_scale": (rmse / FULL_SCALE_MPS2).tolist(),
        "within_pose_noise_mps2": noise.tolist(),
        "condition_number_scaled": cond,
        "pose_spread_mps2": spread.tolist(),
        "reference_range_mps2": np.round(reference_range(stats), 4).tolist(),  # per table axis: (lowest, highest)
        "static_detector": data.detector,
    }
    if data.n_excluded_low_reference:
        fit_info["low_reference"] = data.low_reference.as_dict()  # how many, where (recording.low_reference_warning)
    if data.n_rejected:  # per source: the samples the input check dropped, by reason (input_validation.SampleCheck)
        fit_info["samples_rejected"] = [c.as_dict() for c in data.checks]
    if src is not None:
        fit_info["sources"] = src
    return ThermalCalibration(
        M=M, b=b, temperature_range_c=data.temperature_range_c,
        sensor_id=sensor_id or (sensor_id_of(rec.metadata) if isinstance(rec, Recording) else None) or "unknown",
        t_center_c=center, t_scale_c=scale, noise_sigma_mps2=noise,
        created=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"), fit=fit_info,
        reference_level_temperature_c=data.level_means_c, reference_level_counts=data.level_reference_counts,
        coefficient_covariance=CoefficientCovariance(cov, cov_method, clusters))


@dataclass
class FitOptions:
    """How the inputs are read and which samples are fitted (``fbg-accel-calib fit`` options)."""

    window: int = DEFAULT_WINDOW  # static detector window, samples
    min_interval: int = DEFAULT_MIN_INTERVAL  # shortest static interval kept, samples
    level_gap_c: float = DEFAULT_LEVEL_GAP_C  # temperatures further apart belong to different levels, degC
    rate_hz: float | None = None  # CSV without a time column
    temperature_c: float | None = None  # CSV without a temperature column
    g_mps2: float = STANDARD_GRAVITY  # local gravity for a CSV's pose columns, m/s^2
    namespace: str | None = None  # raw topic of MCAP inputs (mcap_format.TopicSelection)
    topic: str | None = None
    in_memory: bool = False
    progress: bool = False  # progress bars on stderr
    # the ADC's code table (fbg_accel_driver.adc_code_table): the counts mapped before eq. 24 and the table written
    # into the calibration; the samples are then read into memory
    adc_codes: Any = None
    # the run-to-run component of an earlier calibration of the sensor (slow_error.CarriedRunToRun), used when this
    # campaign does not identify it (one run per temperature level)
    run_to_run_from: Any = None


@dataclass
class FitOutcome:
    calibration: ThermalCalibration
    selection: SelectionResult


def _source(path: Path, opt: FitOptions):
    from ..io.csv_import import CsvSampleSource
    from ..io.mcap_reader import McapSampleStream

    if path.suffix.lower() == ".csv" and path.is_file():
        return CsvSampleSource(path, rate_hz=opt.rate_hz, temperature_c=opt.temperature_c, g_mps2=opt.g_mps2)
    return McapSampleStream(path, opt.namespace, opt.topic)


def _warn(line: str) -> None:
    print(line, file=sys.stderr)


def _streamed(paths: list[Path], max_degree: int, opt: FitOptions):
    from ..io.mcap_reader import McapSampleStream
    from ..io.mcap_records import read_warnings
    from ..io.source_progress import CountedSource

    sources = [CountedSource(_source(p, opt), f"fit {p.name}", opt.progress) for p in paths]
    data = prepare_stream(sources, max_degree, opt.window, opt.min_interval, opt.level_gap_c)
    parts = []  # what the full passes read: taken before the partial read of the first run below
    for path, counted in zip(paths, sources, strict=True):
        md = counted.source.metadata()
        if isinstance(counted.source, McapSampleStream):
            for line in read_warnings(path, md["read_report"], md["pose_events"]):
                _warn(line)
        parts.append(md)
    first = _first_block(sources[0].source)
    return data, {"parts": parts, **(parts[0] if len(parts) == 1 else {})}, first


def _first_block(source: Any) -> Any:
    """The first samples (up to ``noise_correlation.SAMPLE_ROWS``) of a source the fit has read in full, with
    their poses (its pose events are known after those passes)."""
    from .noise_correlation import SAMPLE_ROWS

    blocks = source.blocks(SAMPLE_ROWS, True)
    try:
        return next(iter(blocks))
    finally:
        blocks.close()


def fit_files(paths: list[Path], *, degree: int | None = None, max_degree: int = DEFAULT_MAX_DEGREE,
              sensor_id: str | None = None, options: FitOptions | None = None) -> FitOutcome:
    """Fit eq. 28 to the recordings ``paths`` (one run each). ``degree`` None: the cross-validated choice.

    Raises ``ValueError`` (``NotIdentifiedError`` included) with the reason when the data cannot give a
    calibration. The damaged-file warnings and notes go to stderr.
    """
    from ..io.input_files import check_inputs, load_recording
    from ..io.mcap_reader import StreamOrderError
    from .noise_correlation import from_recording, within_visit_factor

    opt = options or FitOptions()
    paths = [Path(p) for p in paths]
    check_inputs(paths)  # each a recording, none given twice
    max_degree = max(max_degree, degree or 0)
    data = None
    if not opt.in_memory and opt.adc_codes is None:
        try:
            data, metadata, first = _streamed(paths, max_degree, opt)
        except StreamOrderError as exc:
            _warn(f"note: {exc}; reading all samples into memory instead")
    rec = None
    if data is None:
        rec = load_recording(paths, rate=opt.rate_hz, temperature=opt.temperature_c, g=opt.g_mps2,
                             namespace=opt.namespace, topic=opt.topic)
        metadata = rec.metadata
        if opt.adc_codes is not None:
            from .adc_codes import mapped_recording

            rec = mapped_recording(rec, opt.adc_codes)
        data = prepare(rec, max_degree, opt.window, opt.min_interval, opt.level_gap_c)
    recorded_sensor = sensor_id_of(metadata)  # refuses recordings of two sensors before the fit's work
    names = ", ".join(map(str, paths))
    for line in data.rejected_warnings([str(p) for p in paths] if len(data.checks) == len(paths)
                                       else [f"{names} run {i}" for i in range(len(data.checks))]):
        _warn(f"WARNING: {line}")
    if len(data) == 0:
        raise ValueError(f"{names}: none of the {data.n_total} samples can be fitted "
                         f"({data.n_excluded_motion} not static, {data.n_excluded_other} without a pose, reference, "
                         "valid temperature or finite counts"
                         + (f", {data.n_excluded_low_reference} with the reference below {LOW_REFERENCE_COUNTS} counts"
                            if data.n_excluded_low_reference else "") + "); check the temperature column (or --temperature), "
                         "the pose/reference columns and --window/--min-interval")
    try:
        selection = select_degree(data, max_degree=max_degree)
    except NotIdentifiedError as exc:
        raise NotIdentifiedError(f"{names}: {exc}") from None
    if degree is None:
        if selection.chosen_degree is None:
            raise NotIdentifiedError("no degree could be validated on held-out data: " + "; ".join(selection.notes)
                                     + " (give the degree: --degree, or the node's fit_degree parameter)")
        degree = selection.chosen_degree
    elif not selection.scores[degree].identified:
        raise NotIdentifiedError(f"degree {degree}: {selection.scores[degree].note}")
    cal = fit_thermal(data, degree, sensor_id=sensor_id or recorded_sensor)
    if opt.run_to_run_from is not None:
        note = check_same_sensor(opt.run_to_run_from, cal.sensor_id)
        if note:
            _warn(note)
    # the noise model from the first input's first samples, the same whether streamed or not
    if rec is not None:
        first = rec.select(rec.run_id == rec.run_id[0])
    corr = from_recording(first, cal, opt.window, opt.min_interval)
    cal.noise_correlated_fraction, cal.noise_time_constant_s = corr.correlated_fraction, corr.time_constant_s
    cal.fit["noise_correlation"] = {**corr.as_dict(), "static_intervals": corr.segments, "samples": corr.samples}
    # the within-visit scatter of correlated noise reads its variance low (a visit's mean takes more than 1/n of it):
    # the published sigma is corrected by what that scatter expects under the fitted correlation
    factor = within_visit_factor(corr, corr.dt_s, data.stats.visit_lengths)
    cal.noise_sigma_mps2 = np.asarray(cal.noise_sigma_mps2) / np.sqrt(factor)
    cal.fit["noise_sigma_correction"] = [round(float(v), 4) for v in 1.0 / np.sqrt(factor)]
    # with the final noise model: what the visits carry beyond it
    attach_slow_error(cal, data.stats, corr.dt_s, opt.run_to_run_from)
    if "run_to_run_not_carried" in cal.fit.get("slow_error", {}):
        _warn(f"note: {cal.fit['slow_error']['run_to_run_not_carried']}")
    cal.fit["sources"] = [str(p) for p in paths]
    cal.fit["degree_selection"] = selection.as_dict()
    cal.adc_codes = opt.adc_codes  # after everything above has evaluated the model on the mapped counts
    return FitOutcome(cal, selection)
