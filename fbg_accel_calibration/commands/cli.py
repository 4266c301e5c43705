"""``fbg-accel-calib``: offline calibration tool (console script; also ``ros2 run fbg_accel_driver fbg-accel-calib``).

Subcommands (``fbg-accel-calib SUBCOMMAND --help`` for the options):

* ``import``   CSV (interchange format, docs/csv_interchange.md) -> calibration MCAP.
* ``fit``      one or more MCAP (or CSV) files or rosbag2 bag directories (``--namespace``/``--topic``),
               e.g. one per chamber temperature -> calibration YAML;
               the degree is chosen by held-out cross-validation unless ``--degree`` is given.
* ``allan``    a static recording + calibration -> Allan deviation PNG, VRW and bias instability per axis.
* ``report``   a fit -> markdown report with tables and PNG plots (calibrated vs reference per pose,
               residuals per degree).
* ``report-measured``  the paper's measured series (../shared) -> docs/results/measured_fit.md + PNG.
* ``uncertainty-measured``  the coefficient uncertainty of the paper's linear model on that series, next to the
               published matrix -> docs/results/calibration_uncertainty.md.
* ``field-check`` an ordinary recording (MCAP, rosbag2 bag, CSV) + calibration -> bias and scale per axis from its
               still periods against local gravity, what the orientations cannot identify; ``--output``: the
               updated calibration.
* ``diagnose`` residual diagnosis (``fbg_accel_calibration.commands.diagnose_cli``).
* ``adc-codes`` a recording -> the ADC's code widths, their plot and code table
               (``fbg_accel_calibration.commands.adc_codes_cli``).
* ``dynamic``  a slide run (MCAP / bag with imu/raw ``aux_counts``, or a dynamic CSV) + excitation plan +
               static calibration -> the calibration with its ``dynamic`` section (chain cut-offs and
               delays), points and budgets, Bode PNG (docs/dynamic_calibration.md).

Exit codes: 0 success, 2 bad input (message on stderr).
"""

from __future__ import annotations

import argparse
import itertools
import json
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from fbg_accel_driver.command_line import OneLineErrorParser, Terminated, interrupted_status, printable, version_line
from fbg_accel_driver.sensor_constants import AHT10_SIGMA_C

from ..io import input_validation as iv
from ..io.atomic_output import atomic_path, check_output_dir, check_outputs, committed_outputs, discard_open_outputs
from ..io.source_progress import add_progress_option
from ..reports.measured_paths import FIT_MD, FIT_PNG, MEASURED_CSV, UNCERTAINTY_MD
from . import adc_codes_cli, diagnose_cli
from .cli_options import add_csv_options, add_detector_options, add_force, add_topic_options

if TYPE_CHECKING:
    import numpy as np

# numpy and every numerical module are imported by the commands that compute (building the parser, --help, needs none)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineErrorParser(prog="fbg-accel-calib", description="Offline calibration of the FBG triaxial accelerometer.")
    parser.add_argument("--version", action="version", version=version_line("fbg-accel-calib"))
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("import", help="CSV (interchange format) to a calibration MCAP")
    p.add_argument("csv", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True, help="MCAP file to write")
    add_csv_options(p)
    p.add_argument("--drop-bad-rows", action="store_true",
                   help="import the good rows and list every rejected line (default: reject the file)")
    p.add_argument("--sensor-id", type=iv.sensor_id, default="unknown",
                   help="sensor id stored in the MCAP metadata (default unknown)")
    p.add_argument("--notes", default="", help="operator notes stored in the MCAP metadata")
    p.add_argument("--start-time", type=iv.start_time_ns, default=None,
                   help="ROS time of the first row: ISO 8601 with zone (2026-11-20T09:30:00Z) or seconds since 1970; "
                        "default: the file's own t_s (absolute if it is)")
    add_force(p)
    add_progress_option(p)
    p.set_defaults(func=cmd_import)

    p = sub.add_parser("fit", help="MCAP (or CSV) files to a calibration YAML")
    p.add_argument("inputs", nargs="+", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True, help="calibration YAML to write")
    p.add_argument("--degree", type=iv.degree, default=None, help="force the degree n (default: held-out cross-validation)")
    p.add_argument("--max-degree", type=iv.degree, default=iv.DEFAULT_MAX_DEGREE,
                   help=f"largest degree scored (default {iv.DEFAULT_MAX_DEGREE}, as paper Table 4)")
    p.add_argument("--sensor-id", type=iv.sensor_id, default=None,
                   help="sensor id written into the calibration (default: the recordings' own, else unknown)")
    add_topic_options(p)
    p.add_argument("--in-memory", action="store_true",
                   help="load every sample before fitting (default: stream MCAP files block by block, same result)")
    p.add_argument("--adc-codes", type=Path, default=None,
                   help="code table YAML (fbg-accel-calib adc-codes -o): counts mapped to their codes' centres before "
                        "eq. 24, the table written into the calibration (reads every sample into memory)")
    p.add_argument("--run-to-run-from", type=Path, default=None, metavar="EARLIER.yaml",
                   help="an earlier calibration of the same sensor whose slow_error holds its run-to-run component: "
                        "used when this campaign cannot identify it (one run per temperature level); a campaign that "
                        "identifies its own keeps it and says so (docs/calibration_fit.md)")
    add_force(p)
    add_detector_options(p)
    add_csv_options(p)
    add_progress_option(p)
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("allan", help="static recording to Allan deviation, VRW and bias instability")
    p.add_argument("inputs", nargs="+", type=Path, help="static recording(s): MCAP or CSV")
    p.add_argument("--calibration", type=Path, required=True, help="calibration YAML applied to the counts")
    p.add_argument("-o", "--output", type=Path, default=Path("allan.png"), help="PNG plot (default allan.png)")
    p.add_argument("--json", type=Path, default=None, help="write the figures as JSON here")
    p.add_argument("--skip", type=iv.skip_s, default=0.0, help="seconds to drop at the start (warm-up)")
    add_topic_options(p)
    add_force(p)
    add_csv_options(p)
    p.set_defaults(func=cmd_allan)

    p = sub.add_parser("field-check", help="still periods of a recording against local gravity: bias and scale per axis")
    p.add_argument("inputs", nargs="+", type=Path, help="recording(s): MCAP, rosbag2 bag directory or CSV")
    p.add_argument("--calibration", type=Path, required=True, help="calibration YAML to check")
    gravity = p.add_mutually_exclusive_group()
    gravity.add_argument("--gravity", type=iv.gravity_mps2, default=None, help="local gravity, m/s^2 (default: normal gravity "
                         "at --latitude, else standard gravity 9.80665)")
    gravity.add_argument("--latitude", type=float, default=None, help="geodetic latitude, deg (WGS-84 normal gravity)")
    p.add_argument("--height", type=float, default=0.0, help="ellipsoidal height, m, with --latitude (default 0)")
    p.add_argument("--min-period", type=iv.period_s, default=2.0, help="shortest still period used, s (default 2)")
    p.add_argument("-o", "--output", type=Path, default=None,
                   help="write the calibration updated with the identified bias and scale here (never over an input)")
    add_topic_options(p)
    add_force(p)
    add_detector_options(p)
    add_csv_options(p)
    p.set_defaults(func=cmd_field_check)

    p = sub.add_parser("report", help="tables and plots of a fit")
    p.add_argument("inputs", nargs="+", type=Path)
    p.add_argument("--calibration", type=Path, required=True, help="calibration YAML applied to the recordings")
    p.add_argument("-o", "--output-dir", type=Path, required=True, help="directory for report.md and PNGs")
    p.add_argument("--max-degree", type=iv.degree, default=iv.DEFAULT_MAX_DEGREE,
                   help="largest degree scored in the report's degree table (default %(default)s)")
    add_topic_options(p)
    add_force(p)
    add_detector_options(p)
    add_csv_options(p)
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("report-measured", help="fit the paper's measured series (../shared) and write its report")
    p.add_argument("--csv", type=Path, default=MEASURED_CSV,
                   help=f"measured CSV (default {MEASURED_CSV}, relative to the cwd)")
    p.add_argument("--md", type=Path, default=FIT_MD, help=f"markdown output (default {FIT_MD})")
    p.add_argument("--png", type=Path, default=FIT_PNG, help=f"plot output (default {FIT_PNG})")
    add_force(p)
    p.set_defaults(func=cmd_report_measured)

    p = sub.add_parser("uncertainty-measured", help="coefficient uncertainty of the linear model on the measured series "
                       "(../shared) next to the paper's matrix")
    p.add_argument("--csv", type=Path, default=MEASURED_CSV,
                   help=f"measured CSV (default {MEASURED_CSV}, relative to the cwd)")
    p.add_argument("--md", type=Path, default=UNCERTAINTY_MD, help=f"markdown output (default {UNCERTAINTY_MD})")
    add_force(p)
    p.set_defaults(func=cmd_uncertainty_measured)

    p = sub.add_parser("dynamic", help="slide run to the chain's dynamics (calibration 'dynamic' section, Bode plot)")
    p.add_argument("recording", type=Path, help="MCAP file or rosbag2 bag directory (imu/raw with aux_counts), or a "
                   "dynamic-run CSV (t_s, ref, x, y, z, aux[, temperature_c])")
    p.add_argument("--plan", type=Path, required=True, help="excitation plan YAML (config/excitation_plan_*.yaml)")
    p.add_argument("--calibration", type=Path, required=True, help="the sensor's static calibration YAML")
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="calibration YAML to write: the static calibration with the 'dynamic' section")
    p.add_argument("--reference-cutoff-hz", type=iv.cutoff_hz, default=None,
                   help="cut-off of the reference photodetector's TIA (Hz), from its own measurement or design; "
                        "a slide run cannot see it (needed by chain_compensation 'equalise')")
    p.add_argument("--fit-highpass", action="store_true",
                   help="fit the reference's AC-coupling high-pass instead of undoing the plan's declared value")
    p.add_argument("--method", choices=["sine", "fft"], default="sine",
                   help="amplitude/phase per segment: sine approximation (default) or whole-period DFT")
    p.add_argument("--slide-start", type=iv.float_in(*iv.TIME_RANGE_S, "s"), default=None,
                   help="time (s, recording time base) the first segment starts (default: found from aux)")
    p.add_argument("--bode", type=Path, default=None, help="write the Bode plot (PNG) here")
    p.add_argument("--json", type=Path, default=None, help="write points, budgets and fits (JSON) here")
    p.add_argument("--temperature", type=iv.temperature_c, default=None,
                   help="CSV without temperature_c: the run's temperature, degC")
    p.add_argument("--accept-misfit", action="store_true",
                   help="write the calibration even when the per-channel model misses the measured axes beyond their "
                        "uncertainty (the report's axis check; docs/dynamic_calibration.md)")
    add_topic_options(p)
    add_force(p)
    p.set_defaults(func=cmd_dynamic)

    diagnose_cli.register(sub)
    adc_codes_cli.register(sub)
    return parser


def _load(paths: list[Path], args: argparse.Namespace):
    """``load_recording`` with a subcommand's input options."""
    from ..io.input_files import load_recording

    return load_recording(paths, rate=args.rate, temperature=args.temperature, g=args.g,
                          namespace=getattr(args, "namespace", None), topic=getattr(args, "topic", None))


def cmd_import(args: argparse.Namespace) -> int:
    """CSV -> MCAP, streamed block by block (memory: one block), written to a temporary file that replaces
    the output only when the whole import succeeded."""
    from ..io.csv_import import CsvBlocks, write_mcap
    from ..io.source_progress import CountedSource, enabled

    check_outputs([args.output], [args.csv], args.force)
    src = CountedSource(CsvBlocks(args.csv, rate_hz=args.rate, temperature_c=args.temperature, g_mps2=args.g),
                        f"import {args.csv.name} (1: check, 2: write)", enabled(args))
    metadata = {"sensor_id": args.sensor_id, "operator_notes": args.notes, "source": str(args.csv),
                "plan": "imported from CSV"}
    with atomic_path(args.output) as tmp:
        n, poses, first_s = write_mcap(src, tmp, metadata, sensor_id=args.sensor_id,
                                       drop_bad_rows=args.drop_bad_rows, start_ns=args.start_time)
    report = src.report
    print(report.summary())
    if args.start_time is None and first_s is not None and first_s < 3.2e7:  # relative times (before 1971)
        print(f"note: stamps are the file's t_s from {first_s:g} s, i.e. on 1970-01-01; give --start-time to place "
              "the recording at its real time", file=sys.stderr)
    print(f"wrote {args.output}: {report.rows_kept} samples, {poses} poses, {n} messages")
    return 0


def cmd_fit(args: argparse.Namespace) -> int:
    """Fit from the files (``fit_pipeline.fit_files``: MCAP streamed, memory bounded by one block,
    docs/calibration_fit.md; ``--in-memory`` loads every sample first)."""
    import numpy as np

    from fbg_accel_driver.sensor_constants import FULL_SCALE_MPS2

    from ..fit.fit_pipeline import FitOptions, fit_files
    from ..fit.thermal_fit import reference_reach_warnings
    from ..io.recording import low_reference_warning
    from ..io.source_progress import enabled

    # the inputs are checked first thing by fit_files; the code table read is an input too
    extra = [f for f in (args.adc_codes, args.run_to_run_from) if f is not None]
    check_outputs([args.output], [*args.inputs, *extra], args.force)
    from fbg_accel_driver.adc_code_table import load_table

    from ..fit.slow_error import carried_run_to_run
    from ..fit.slow_error import summary_line as slow_error_line

    table = load_table(args.adc_codes) if args.adc_codes is not None else None
    carried = carried_run_to_run(args.run_to_run_from) if args.run_to_run_from is not None else None
    options = FitOptions(args.window, args.min_interval, args.level_gap, args.rate, args.temperature, args.g,
                         getattr(args, "namespace", None), getattr(args, "topic", None), args.in_memory, enabled(args),
                         table, carried)
    out = fit_files(args.inputs, degree=args.degree, max_degree=args.max_degree, sensor_id=args.sensor_id,
                    options=options)
    selection, cal = out.selection, out.calibration
    print(f"degree selection ({selection.criterion}):")
    print(selection.table_markdown())
    for note in selection.notes:
        print(f"note: {note}")
    if args.degree is not None and args.degree != selection.chosen_degree:
        print(f"note: --degree {args.degree} overrides the cross-validated choice {selection.chosen_degree}")
    corr = cal.fit["noise_correlation"]
    print("noise correlation x/y/z: correlated fraction " + " / ".join(f"{v:.2f}" for v in cal.noise_correlated_fraction)
          + ", time constant " + " / ".join(f"{v:.3f}" for v in cal.noise_time_constant_s)
          + f" s ({corr['static_intervals']} static intervals, {corr['samples']} samples)")
    with atomic_path(args.output) as tmp:
        cal.save(tmp)
    rmse = np.asarray(cal.fit["rmse_mps2"])
    print(f"degree n = {cal.degree}: in-sample RMSE x/y/z " + " / ".join(f"{v:.4f}" for v in rmse) + " m/s^2 ("
          + " / ".join(f"{v / FULL_SCALE_MPS2:.2e}" for v in rmse) + " of 20 g), within-pose noise "
          + " / ".join(f"{v:.4f}" for v in cal.noise_sigma_mps2) + " m/s^2")
    print(f"temperature range {cal.temperature_range_c[0]:.2f} .. {cal.temperature_range_c[1]:.2f} degC; "
          f"{cal.fit['samples_used']} of {cal.fit['samples_total']} samples used")
    slow = slow_error_line(cal.fit.get("slow_error", {}))  # the run-to-run part is a number, or why it is not one
    if slow is not None:
        print(slow)
    if cal.fit["visits_excluded_clipped"]:
        print(f"warning: {cal.fit['samples_excluded_clipped']} samples of {cal.fit['visits_excluded_clipped']} visit(s) "
              "left out: a channel at a rail of the ADC (an axis at 0 or 4095 counts, or the reference at 4095) in "
              "each", file=sys.stderr)
    if cal.fit.get("low_reference"):
        print("warning: " + low_reference_warning(cal.fit["low_reference"]), file=sys.stderr)
    for line in reference_reach_warnings(cal.fit["reference_range_mps2"]):
        print(f"warning: {line}", file=sys.stderr)
    print(f"wrote {args.output}")
    return 0


def cmd_dynamic(args: argparse.Namespace) -> int:
    """Slide run -> calibration with a ``dynamic`` section (+ report on stdout, optional Bode PNG / JSON)."""
    from fbg_accel_driver.thermal_model import ThermalCalibration

    from ..dynamic.dynamic_calibration import run_dynamic
    from ..dynamic.excitation_plan import ExcitationPlan
    from ..io.dynamic_csv import read_dynamic_csv
    from ..io.input_files import check_input
    from ..io.mcap_reader import read_recording
    from ..io.mcap_records import read_warnings

    outputs = [o for o in (args.output, args.bode, args.json) if o is not None]
    check_outputs(outputs, [args.recording, args.plan, args.calibration], args.force)
    plan = ExcitationPlan.load(args.plan)
    static_cal = ThermalCalibration.load(args.calibration)
    check_input(args.recording)
    if args.recording.suffix.lower() == ".csv" and args.recording.is_file():
        rec = read_dynamic_csv(args.recording, args.temperature)
    else:
        rec = read_recording(args.recording, args.namespace, args.topic)
        for line in read_warnings(args.recording, rec.metadata.get("read_report", {}), rec.metadata.get("pose_events")):
            print(line, file=sys.stderr)
    other = another_sensor(static_cal, rec.metadata)  # the output would join two sensors' models in one file
    if other:
        raise ValueError(f"{other}: give the static calibration of the sensor that made this run, not {args.calibration} "
                         "(if they are one sensor under two names, make them agree: the calibration's sensor_id is one "
                         "line of its YAML)")
    result = run_dynamic(rec, plan, static_cal, reference_cutoff_hz=args.reference_cutoff_hz,
                         fit_highpass=args.fit_highpass, slide_start_s=args.slide_start, method=args.method)
    print(result.report())
    misfit = result.check.misfit and not args.accept_misfit
    if not misfit:
        static_cal.dynamic = result.dynamics
        static_cal.fit.setdefault("dynamic_sources", []).append(str(args.recording))
    # the calibration, Bode plot and JSON together or none of them; on a misfit the plot and JSON alone (to find why)
    written = [f for f in (args.bode, args.json, None if misfit else args.output) if f is not None]
    with committed_outputs() as outs:
        if not misfit:
            static_cal.save(outs.path(args.output))
            ThermalCalibration.load(outs.path(args.output))  # what is written loads (the driver's own check)
        if args.bode is not None:
            from ..dynamic.bode_plot import plot_bode
            from ..dynamic.chain_model import axis_response_along

            chain = [result.models[ax] for ax in "xyz"]
            predicted = {ax: (lambda f, i=i: axis_response_along(result.m_static, chain, plan.direction, f)[..., i])
                         for i, ax in enumerate("xyz")}
            plot_bode(result.channel_points, result.models, outs.path(args.bode), title=f"Dynamic calibration: {plan.name}",
                      axis_points=result.points, axis_responses=predicted)
        if args.json is not None:
            outs.path(args.json).write_text(json.dumps(result.as_dict(), indent=1, default=_json_default),
                                            encoding="utf-8")
    for path in written:
        print(f"wrote {path}")
    if misfit:
        raise ValueError(f"{args.output} not written: the per-channel chain model misses the measured axes by "
                         f"{result.check.max_abs_z:.2g} standard uncertainties as a normal deviate (beyond "
                         f"{result.check.threshold:g}; the report's axis check): find the cause, or give --accept-misfit "
                         "to write it anyway")
    return 0


def _json_default(o: object) -> object:
    if hasattr(o, "tolist"):
        return o.tolist()  # type: ignore[attr-defined]
    if hasattr(o, "to_dict"):
        return o.to_dict()  # type: ignore[attr-defined]
    return str(o)


def _command_line(args: argparse.Namespace) -> str:
    """The command as given to :func:`main` (its argv; sys.argv only for the console script)."""
    argv = getattr(args, "argv", None)
    argv = sys.argv[1:] if argv is None else argv
    return "fbg-accel-calib " + " ".join(shlex.quote(str(a)) for a in argv)


def another_sensor(cal, metadata: dict) -> str | None:
    """"calibration of another sensor: ..." when the calibration and the recording (its metadata) both name a sensor
    and not the same one, else None. Raises ``ValueError`` for recordings of two sensors (``sensor_id_of``)."""
    from ..fit.thermal_fit import UNNAMED_SENSOR_IDS, sensor_id_of

    rec_id, cal_id = sensor_id_of(metadata), cal.sensor_id
    if rec_id is None or cal_id is None or rec_id in UNNAMED_SENSOR_IDS or cal_id in UNNAMED_SENSOR_IDS \
            or rec_id == cal_id:
        return None
    return f"calibration of another sensor: the calibration is for sensor '{cal_id}', the recording is of sensor '{rec_id}'"


def calibration_match_warnings(cal, rec) -> list[str]:
    """Warnings when a calibration is applied to a recording it may not describe: another sensor id (both known),
    samples outside the calibrated temperature range by more than the driver's margin (``AHT10_SIGMA_C``; count, fraction,
    range; of the samples that are data: those with
    a reference too low to be data, ``Recording.low_reference``, are not counted)."""
    import numpy as np

    out = []
    other = another_sensor(cal, rec.metadata)
    if other:
        out.append(other)
    lo, hi = cal.temperature_range_c
    temp = np.asarray(rec.temp_c, dtype=float)[~rec.low_reference()]
    fin = np.isfinite(temp)
    margin = AHT10_SIGMA_C  # the driver's temperature_range_margin_c default: this close to the range is inside it
    outside = int(np.sum(fin & ~cal.in_range(temp, margin)))
    if outside:
        out.append(f"{outside} of {int(fin.sum())} samples ({100.0 * outside / max(int(fin.sum()), 1):.1f} %) are "
                   f"outside the calibrated temperature range {lo:.2f} .. {hi:.2f} degC by more than {margin:g} degC "
                   f"(recorded {np.nanmin(temp):.2f} .. {np.nanmax(temp):.2f} degC): the model is extrapolated there")
    return out


def time_base_segments(t_s: np.ndarray, kept: np.ndarray) -> tuple[float, list[np.ndarray], list[str]]:
    """Sample rate, continuous segments (index arrays into ``t_s``) and one line per break.

    ``kept`` marks the samples used (after --skip and without invalid ones). A break is a step of the time stamps
    <= 0 (board time restarting: a reboot), a step longer than 1.5 sample periods (a gap), or dropped samples
    between two kept ones. No ADEV cluster spans a break (``allan_deviation`` pools the segments)."""
    import numpy as np

    idx = np.flatnonzero(kept)
    t = t_s[idx]
    dt = np.diff(t)
    pos = dt[dt > 0]
    if len(pos) == 0:
        raise ValueError("cannot determine the sample rate from the time stamps")
    rate = 1.0 / float(np.median(pos))
    cut = (dt <= 0) | (dt > 1.5 / rate) | (np.diff(idx) > 1)
    lines = []
    elapsed = np.r_[0.0, np.cumsum(np.where(cut, 1.0 / rate, dt))]  # time of data before each sample
    for b in np.flatnonzero(cut):
        where = f"after {elapsed[b + 1]:.1f} s of data (sample {idx[b + 1]}, t = {t[b + 1]:.3f} s)"
        if dt[b] <= 0:
            what = f"time stamps go backward by {-dt[b]:.3f} s (board time reset: a reboot?)"
        elif np.diff(idx)[b] > 1:
            what = f"{int(np.diff(idx)[b] - 1)} samples without a valid calibrated output dropped"
        else:
            what = f"gap of {dt[b]:.3f} s ({dt[b] * rate - 1:.0f} missing samples)"
        lines.append(f"break {where}: {what}")
    edges = np.r_[0, np.flatnonzero(cut) + 1, len(idx)]
    return rate, [idx[a:b] for a, b in itertools.pairwise(edges) if b > a], lines


def cmd_allan(args: argparse.Namespace) -> int:
    """ADEV of a static recording. Breaks in the time base (board time restarting, gaps, dropped invalid samples)
    split it into continuous segments whose clusters are pooled; none spans a break (each break is named)."""
    import numpy as np

    from fbg_accel_driver.thermal_model import ThermalCalibration

    from ..fit.allan import AXES, allan_deviation, plot_allan
    from ..io.recording import LowReference

    check_outputs([args.output, args.json], [*args.inputs, args.calibration], args.force)
    cal = ThermalCalibration.load(args.calibration)
    rec = _load(args.inputs, args)
    if len(np.unique(rec.run_id)) > 1:
        raise ValueError("allan needs one continuous static recording")
    if len(rec.t_s) < 2:
        raise ValueError("cannot determine the sample rate from the time stamps")
    # --skip: the first seconds of data (time stamps may restart, so elapsed along the recording, not t - t0)
    steps = np.diff(rec.t_s)
    elapsed = np.r_[0.0, np.cumsum(np.where(steps > 0, steps, 0.0))]
    keep = elapsed >= args.skip
    for line in calibration_match_warnings(cal, rec.select(keep)):
        print(f"warning: {line}", file=sys.stderr)
    accel = cal.apply_counts(rec.ref, rec.xyz, rec.temp_c, rec.t_s)
    dark = LowReference()
    dark.add_recording(rec.select(keep))
    if dark.count:  # not data, whatever the calibration makes of them (the driver publishes none, the fit uses none)
        print("warning: " + dark.warning(), file=sys.stderr)
    ok = np.all(np.isfinite(accel), axis=1) & ~rec.low_reference()
    if not ok[keep].all():
        print(f"warning: {int((~ok[keep]).sum())} samples without a valid calibrated output dropped", file=sys.stderr)
    rate, segments, breaks = time_base_segments(rec.t_s, keep & ok)
    if breaks:
        print(f"warning: {len(breaks)} break(s) in the time base; the ADEV pools the clusters of {len(segments)} "
              "continuous segments, none spans a break:", file=sys.stderr)
        for line in breaks:
            print(f"warning:   {line}", file=sys.stderr)
    res = allan_deviation([accel[s] for s in segments], rate)
    for j in np.flatnonzero(res.bi_is_upper_bound):
        print(f"warning: {AXES[j]}: no minimum of the ADEV within 1 s .. length/20 ({res.duration_s / 20:.3g} s): "
              f"bias instability < {res.bias_instability_mg[j]:.3g} mg is an upper bound, not a floor", file=sys.stderr)
    for j in np.flatnonzero(res.vrw_differs):
        print(f"note: {AXES[j]}: VRW 60*ADEV(1 s) {res.vrw_mps_per_sqrt_h[j]:.3g} vs white-noise VRW "
              f"{res.white_noise_vrw_mps_per_sqrt_h[j]:.3g} m/s/sqrt(h) (-1/2 line): the noise is not white at 1 s",
              file=sys.stderr)
    with committed_outputs() as outs:  # the plot and the JSON together
        plot_allan(res, outs.path(args.output), title=f"Allan deviation of {', '.join(p.name for p in args.inputs)}")
        if args.json:
            outs.path(args.json).write_text(json.dumps({**res.as_dict(), "breaks": breaks}, indent=2), encoding="utf-8")
    print(res.table_markdown())
    print(f"wrote {args.output}")
    if args.json:
        print(f"wrote {args.json}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    import numpy as np

    from fbg_accel_driver.thermal_model import ThermalCalibration

    from ..fit.fit_stream import prepare
    from ..fit.model_selection import select_degree
    from ..fit.static_detector import calibration_samples
    from ..fit.thermal_fit import reference_reach_warnings, sensor_id_of
    from ..reports.fit_report import fit_report_markdown, plot_calibrated_vs_reference, plot_residuals_per_degree, pose_statistics

    out = args.output_dir
    check_output_dir(out, REPORT_FILES, [*args.inputs, args.calibration], args.force)
    cal = ThermalCalibration.load(args.calibration)
    rec = _load(args.inputs, args)
    usable, _ = calibration_samples(rec, window=args.window, min_interval=args.min_interval)
    data = prepare(rec, args.max_degree, usable=usable, level_gap_c=args.level_gap)
    if data.low_reference.count:  # left out of the selection and the statistics, as by the fit
        print("warning: " + data.low_reference.warning(), file=sys.stderr)
    selection = select_degree(data, max_degree=args.max_degree)
    stats = pose_statistics(cal, rec, usable & np.isfinite(rec.temp_c))
    report_md, vs_reference_png, per_degree_png = REPORT_FILES
    warnings = calibration_match_warnings(cal, rec)
    if (cal.fit or {}).get("reference_range_mps2") is not None:  # files written before it was recorded lack it
        warnings += reference_reach_warnings(cal.fit["reference_range_mps2"])
    for line in warnings:
        print(f"warning: {line}", file=sys.stderr)
    text = fit_report_markdown(cal, selection, stats, {"calibrated vs reference": vs_reference_png,
                                                       "residuals per degree": per_degree_png},
                               _command_line(args), recording_sensor_id=sensor_id_of(rec.metadata), warnings=warnings)
    with committed_outputs() as outs:  # the report and its two plots are replaced together
        plot_calibrated_vs_reference(cal, rec, usable, outs.path(out / vs_reference_png))
        plot_residuals_per_degree(selection, outs.path(out / per_degree_png))
        outs.path(out / report_md).write_text(text, encoding="utf-8")
    print(selection.table_markdown())
    print("wrote " + ", ".join(str(out / name) for name in REPORT_FILES))
    return 0


REPORT_FILES = ("report.md", "calibrated_vs_reference.png", "residuals_per_degree.png")


def cmd_report_measured(args: argparse.Namespace) -> int:
    from ..reports.measured_report import main_args

    return main_args(args.csv, args.md, args.png, argv=getattr(args, "argv", None), force=args.force)


def cmd_field_check(args: argparse.Namespace) -> int:
    """Still periods at unknown orientations against local gravity (``field_check``); the updated calibration only
    with ``--output``."""
    import numpy as np

    from fbg_accel_driver.sensor_constants import STANDARD_GRAVITY
    from fbg_accel_driver.thermal_model import ThermalCalibration

    from ..fit.field_check import (
        DRIFT_SIGMAS,
        PARAMETERS,
        drifted,
        estimate,
        normal_gravity,
        still_periods,
        updated_calibration,
    )
    from ..fit.static_detector import calibration_samples

    check_outputs([args.output], [*args.inputs, args.calibration], args.force)
    g = (args.gravity if args.gravity is not None else normal_gravity(args.latitude, args.height)
         if args.latitude is not None else STANDARD_GRAVITY)
    cal = ThermalCalibration.load(args.calibration)
    rec = _load(args.inputs, args)
    still = calibration_samples(rec, args.window, args.min_interval)[1]  # the signal alone is still
    periods = still_periods(rec, cal, still, args.min_period)
    fc = estimate(periods, g, slow_error=None if cal.slow_error is None else cal.slow_error.published_matrix)
    units = ("m/s^2",) * 3 + ("",) * 3
    print(f"{len(periods.mean)} still period(s), {int(periods.samples.sum())} samples; g = {g:.6f} m/s^2; "
          f"| |a| - g | before: rms {np.sqrt(np.mean(fc.residual_before_mps2**2)):.4f} m/s^2, after "
          f"{np.sqrt(np.mean(fc.residual_mps2**2)):.4f} m/s^2")
    values = np.r_[fc.bias, fc.scale]
    for name, v, sd, ok, unit in zip(PARAMETERS, values, fc.sigma, fc.identified, units, strict=True):
        print(f"  {name:8s} " + (f"{v:+.4f} +- {sd:.4f} {unit}" if ok else "not identified by these orientations"))
    for note in fc.notes:
        print(f"note: {note}")
    moved = drifted(fc)
    slow = "" if cal.slow_error is None else ", the calibration's slow error included"
    if moved:
        print(f"WARNING: the calibration has moved: {', '.join(moved)} beyond {DRIFT_SIGMAS:g} sigma{slow}")
    else:
        print(f"no drift beyond {DRIFT_SIGMAS:g} sigma{slow}")
    if args.output is not None:
        with atomic_path(args.output) as tmp:
            updated_calibration(cal, fc).save(tmp)
        print(f"wrote {args.output}")
    return 0


def cmd_uncertainty_measured(args: argparse.Namespace) -> int:
    from ..reports.measured_uncertainty import main_args

    return main_args(args.csv, args.md, argv=getattr(args, "argv", None), force=args.force)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = None if argv is None else list(argv)  # quoted by the reports' "Produced by"
    try:
        return int(args.func(args) or 0)
    except (OSError, ValueError) as exc:
        print(f"fbg-accel-calib {args.command}: {printable(str(exc))}", file=sys.stderr)  # a path's ESC escaped
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM through cli_main (Terminated): outputs rolled back
        discard_open_outputs()
        print(f"fbg-accel-calib {args.command}: {'terminated' if isinstance(exc, Terminated) else 'interrupted'}; "
              "no output written", file=sys.stderr)
        return interrupted_status(exc)


if __name__ == "__main__":
    sys.exit(main())
