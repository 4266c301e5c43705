"""``fbg-accel-calib diagnose``: argparse wiring of the residual diagnosis (issue 4).

The CLI module (``cli.py``) calls ``register(subparsers)``; this module only parses arguments,
loads the recording(s) and hands them to :func:`fbg_accel_calibration.diagnosis.diagnose.diagnose` and
:mod:`fbg_accel_calibration.reports.diagnose_report`.

Example (the measured series of the paper, no time base and no temperature column)::

    .venv/bin/fbg-accel-calib diagnose /work/shared/data/measured/fig13_multiposition_23C.csv \\
        --rate 1 --temperature 23.4 --g 9.81 --out docs/results/measured_diagnosis.md \\
        --yaml docs/results/measured_diagnosis.yaml
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from fbg_accel_driver.command_line import printable

from ..io import input_validation as iv
from ..io.source_progress import add_progress_option
from .cli_options import add_topic_options


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``diagnose`` subcommand to the ``fbg-accel-calib`` parser; returns the sub-parser."""
    p = subparsers.add_parser(
        "diagnose",
        help="fit the declared model, trace its residual to candidate physical effects, add the winners",
        description="Fit eq. 28 (degree by held-out CV over visits), test the candidate-effect library "
        "(docs/effects.md) on the static residual, add significant effects as declared correction terms of the "
        "calibration YAML and report before/after on held-out poses next to the noise floor.",
    )
    p.add_argument("inputs", nargs="+", help="recordings: .csv (interchange format, docs/csv_interchange.md), .mcap "
                   "or a rosbag2 bag directory (ros2 bag record -s mcap)")
    add_topic_options(p)
    p.add_argument("--rate", type=iv.rate_hz, default=None,
                   help="CSV without t_s: sample rate in Hz (time = sample index / rate); no default, as for the "
                        "other subcommands (--rate 1 counts time in samples)")
    p.add_argument("--temperature", type=iv.temperature_c, default=None,
                   help="CSV without temperature_c: temperature of every sample, degC")
    p.add_argument("--g", type=iv.gravity_mps2, default=None,
                   help="local gravity for psi/theta CSV columns, m/s^2 (default 9.80665)")
    p.add_argument("--static", choices=["table", "detector", "all"], default="table",
                   help="samples to fit and judge: 'table' (default) every sample of a pose the table held for >= 5 "
                        "samples; 'detector' the fit's static-interval detector (hides settling, i.e. chain dynamics); "
                        "'all' also the samples taken while the table moves (needs the table's angle readings during "
                        "motion, e.g. simulator recordings)")
    p.add_argument("--degree", type=iv.degree, default=None, help="force the degree of eq. 28 (default: held-out CV)")
    p.add_argument("--max-degree", type=iv.degree, default=4, help="largest degree of eq. 28 scored (default %(default)s)")
    p.add_argument("--folds", type=iv.folds, default=10, help="cross-validation folds over visits (default %(default)s)")
    p.add_argument("--alpha", type=iv.probability, default=0.01,
                   help="family-wise significance level per selection step (default %(default)s)")
    p.add_argument("--min-gain", type=iv.fraction, default=0.02,
                   help="minimum held-out gain (fraction of the noise-weighted MSE) for an effect to be added "
                        "(default %(default)s)")
    p.add_argument("--max-effects", type=iv.max_effects, default=3, help="most effects added (default %(default)s)")
    p.add_argument("--seed", type=iv.seed, default=0, help="seed of the fold assignment (default %(default)s)")
    p.add_argument("--lanes", type=iv.lanes, default=None,
                   help="searches run side by side on threads; the results are the same with any number (default: one "
                        "per core up to two from 20000 searched samples on, else one; 1 holds the least memory)")
    p.add_argument("--search-rows", type=iv.search_rows, default=None,
                   help="above this many fitted samples the candidates are searched on every k-th one (default "
                        "50000, diagnose.SEARCH_ROWS; k no larger than keeps 80 %% of what a visit's samples tell of "
                        "its mean); 0: on every sample (slower; an effect seen only in the first tenths of a second "
                        "of each visit, as the TIA's, keeps all its samples)")
    p.add_argument("--sensor-id", type=iv.sensor_id, default=None,
                   help="sensor id written into --yaml (default: the recordings' own, else unknown)")
    p.add_argument("--out", type=Path, default=None, help="markdown report (PNG plots go to --img-dir)")
    p.add_argument("--img-dir", type=Path, default=None, help="directory for the PNG plots (default: <out dir>/img)")
    p.add_argument("--figures", choices=FIGURES, default=None,
                   help="PNG plots of --out: 'report' (default) before/after, the residual's structure and a figure of "
                        "each candidate effect the summary names (added, remedy, per-run, rig, stand-in, confounded); "
                        "'all' also every other candidate's of the first step; 'none' no plots")
    p.add_argument("--yaml", type=Path, default=None, help="write the refitted calibration (with the added terms) here")
    p.add_argument("--force", action="store_true", help="replace existing output files (default: refuse)")
    add_progress_option(p)
    p.add_argument("--adc-codes", type=Path, default=None,
                   help="code table YAML (fbg-accel-calib adc-codes -o): counts mapped to their codes' centres before "
                        "eq. 24, the table written into the --yaml calibration")
    p.set_defaults(func=run)
    return p


FIGURES = ("report", "all", "none")  # diagnose_report.FIGURES (not imported here: it loads the diagnosis for --help)


def _figures(args: argparse.Namespace) -> str:
    return FIGURES[0] if args.figures is None else args.figures


def _img_dir(args: argparse.Namespace) -> Path | None:
    if args.out is None:
        return None
    return Path(args.img_dir) if args.img_dir is not None else args.out.parent / "img"


def check_diagnose_outputs(args: argparse.Namespace) -> None:
    """Before any computation: outputs are not inputs, exist only with --force, and their directories exist or can
    be made (``atomic_output``: made when the outputs are written, as for every command)."""
    from ..io.atomic_output import OutputError, check_output_dir, check_outputs

    if args.out is None:  # the figures belong to the report: an option of theirs alone would draw nothing, silently
        for option, value in (("--img-dir", args.img_dir), ("--figures", args.figures)):
            if value is not None:
                raise OutputError(f"{option} {value}: the figures belong to the report; give --out too")
    inputs = [*args.inputs, *([args.adc_codes] if getattr(args, "adc_codes", None) is not None else [])]
    check_outputs([args.out, args.yaml], inputs, args.force)
    img = _img_dir(args)
    # whichever figures the run draws, or removes as those of an earlier run the new report does not show
    if img is not None and (_figures(args) != "none" or img.is_dir()):
        from ..reports.diagnose_report import figure_files

        check_output_dir(img, figure_files(), args.inputs, args.force)


def write_outputs(res, args: argparse.Namespace, command: str) -> list[Path]:
    """Markdown report, its PNGs and the YAML, each written to a temporary file; all renamed together when all
    are written (an interrupted run replaces none of them: no fresh plots beside a stale report)."""
    from ..io.atomic_output import committed_outputs
    from ..reports.diagnose_report import write_report

    written: list[Path] = []
    with committed_outputs() as outs:
        if args.out is not None:
            written += write_report(res, args.out, _img_dir(args), command, outs,
                                    figures=_figures(args))
        if args.yaml is not None:
            res.calibration.fit.setdefault("source", [str(p) for p in args.inputs])
            res.calibration.save(outs.path(args.yaml))
            written.append(args.yaml)
    return written


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..diagnosis.diagnose import diagnose
    from ..diagnosis.heap_policy import set_process_heap_policy
    from ..diagnosis.search import SEARCH_ROWS
    from ..fit.thermal_fit import check_recording_excitation
    from ..reports.diagnose_report import text

    set_process_heap_policy()  # the command's process diagnoses: its searches' arrays reuse the pages of those dropped

    try:
        check_diagnose_outputs(args)
        from ..fit.thermal_fit import sensor_id_of
        from ..io.input_files import load_recording

        rec = load_recording(args.inputs, rate=args.rate, temperature=args.temperature, g=args.g,
                             namespace=args.namespace, topic=args.topic)
        table = None
        if args.adc_codes is not None:  # the counts as the driver will map them (one implementation: map_counts)
            from fbg_accel_driver.adc_code_table import load_table

            from ..fit.adc_codes import mapped_recording

            table = load_table(args.adc_codes)
            rec = mapped_recording(rec, table)
    except (OSError, ValueError) as exc:
        print(f"fbg-accel-calib diagnose: {printable(str(exc))}", file=sys.stderr)
        return 2
    # the recordings' own id (their run records; before: a top-level key MCAP recordings do not have, so 'unknown')
    sensor_id = args.sensor_id or sensor_id_of(rec.metadata) or "unknown"
    from ..io.source_progress import bar, enabled

    try:
        check_recording_excitation(rec)
        with bar(enabled(args), "diagnose: candidate effects evaluated", unit="fits") as b:
            res = diagnose(rec, static=args.static, max_degree=args.max_degree, folds=args.folds, alpha=args.alpha,
                           min_rel_gain=args.min_gain, max_effects=args.max_effects, degree=args.degree,
                           sensor_id=sensor_id, seed=args.seed, progress=lambda name: b.update(1), lanes=args.lanes,
                           search_rows=SEARCH_ROWS if args.search_rows is None else (args.search_rows or None))
    except ValueError as exc:
        print(f"fbg-accel-calib diagnose: {', '.join(args.inputs)}: {exc}", file=sys.stderr)
        return 2
    except np.linalg.LinAlgError as exc:  # a degenerate case the checks above did not foresee: still one line
        print(f"fbg-accel-calib diagnose: {', '.join(args.inputs)}: the data do not determine the model ({exc}); "
              "check that the poses differ and every channel responds", file=sys.stderr)
        return 2
    res.calibration.adc_codes = table  # the file the driver reads maps the counts as the diagnosis did
    print(text(res), end="")
    argv = getattr(args, "argv", None)  # what main() was given; sys.argv for the console script
    argv = sys.argv[1:] if argv is None else argv
    command = "fbg-accel-calib " + " ".join(shlex.quote(str(a)) for a in argv) if len(argv) > 1 else ""
    try:
        written = write_outputs(res, args, command)
    except (OSError, ValueError) as exc:
        print(f"fbg-accel-calib diagnose: {printable(str(exc))}", file=sys.stderr)
        return 2
    for p in written:
        print(f"wrote {p}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry (``python -m fbg_accel_calibration.commands.diagnose_cli ...``) until ``cli.py`` wires it."""
    parser = argparse.ArgumentParser(prog="fbg-accel-calib")
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(argv)
    args.argv = None if argv is None else list(argv)
    return int(args.func(args))


if __name__ == "__main__":
    raise SystemExit(main())
