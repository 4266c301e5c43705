"""``fbg-accel-calib adc-codes``: the ESP32 ADC's code widths measured from a recording (``adc_codes``).

Prints each channel's width pattern (period 16) with its test, the pattern pooled over the channels, and the codes
that differ on their own; ``--plot`` draws the widths with their 95 % intervals and the integral non-linearity (INL:
each code's centre minus the code, counts) over the codes each channel read; ``-o`` writes the code table
(``fbg_accel_driver.adc_code_table``) that ``ThermalCalibration`` carries as its ``adc_codes`` section.

Example (the paper's measured series)::

    .venv/bin/fbg-accel-calib adc-codes ../shared/data/measured/fig13_multiposition_23C.csv --rate 1 \\
        --temperature 23.4 --g 9.81 --plot adc_codes.png -o adc_codes.yaml
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..io import input_validation as iv

if TYPE_CHECKING:
    import numpy as np



def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``adc-codes`` subcommand to the ``fbg-accel-calib`` parser; returns the sub-parser."""
    p = subparsers.add_parser("adc-codes", help="the ADC's code widths (periodic pattern, wide and missing codes) and "
                              "their code table, from any recording")
    p.add_argument("inputs", nargs="+", type=Path, help="recordings: .csv, .mcap or rosbag2 directories")
    p.add_argument("--rate", type=iv.rate_hz, default=None, help="CSV without t_s: sample rate in Hz")
    p.add_argument("--temperature", type=iv.temperature_c, default=None,
                   help="CSV without temperature_c: temperature of every sample, degC")
    p.add_argument("--g", type=iv.gravity_mps2, default=None, help="gravity for psi/theta references, m/s^2")
    p.add_argument("--namespace", default=None, help="MCAP/bag: the driver namespace of the raw topic")
    p.add_argument("--topic", default=None, help="MCAP/bag: the raw topic")
    p.add_argument("--plot", type=Path, default=None, help="PNG: widths with their 95 %% intervals, and the INL")
    p.add_argument("--json", type=Path, default=None, help="the estimates as JSON")
    p.add_argument("-o", "--output", type=Path, default=None,
                   help="code table YAML (the calibration file's adc_codes section; fit/diagnose --adc-codes)")
    p.add_argument("--alpha", type=float, default=0.01, help="level of the pattern's test (default %(default)s)")
    p.add_argument("--force", action="store_true", help="replace existing output files (default: refuse)")
    p.set_defaults(func=run)
    return p


def visits_of(rec) -> tuple[np.ndarray, np.ndarray]:
    """(groups, rows) of a recording for the code-density estimate: the table's poses held for at least
    ``diagnosis.data.MIN_HELD_SAMPLES`` samples (visit labels ``visit_ids``); a recording without poses (a static or
    slow-ramp run): every sample, each run one visit (cut into pieces by ``adc_codes.pieces``). Clipped samples and a
    dark reference are left out."""
    import numpy as np

    from ..diagnosis.data import held_poses, visit_ids

    good = ~rec.clipped() & ~rec.low_reference() & np.isfinite(rec.ref) & np.all(np.isfinite(rec.xyz), axis=1)
    if np.any(rec.pose_id >= 0):
        return visit_ids(rec.pose_id, rec.run_id), good & held_poses(rec.pose_id, rec.run_id)
    return rec.run_id.astype(np.int64), good


def plot(widths, table, path: Path) -> None:
    """Widths (pooled and per channel, 95 % intervals) against the code mod the period, and the INL per channel."""
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 7))
    ests = [(n, w) for n, w in widths.channels.items() if w is not None]
    if widths.pooled is not None:
        ests.append(("pooled", widths.pooled))
    for k, (name, w) in enumerate(ests):
        r = np.arange(w.period) + (k - len(ests) / 2) * 0.08
        ax1.errorbar(r, w.pattern, yerr=w.pattern_u95, fmt="o" if name == "pooled" else ".", capsize=2,
                     label=f"{name} (p = {w.p_value:.1g})")
    ax1.axhline(1.0, color="k", lw=0.8)
    ax1.set_xlabel("code mod 16")
    ax1.set_ylabel("code width (counts of input)")
    ax1.set_title("code widths, 95 % intervals")
    ax1.legend(fontsize=8)
    for j, name in enumerate(("ref", "x", "y", "z")):
        own = widths.channels.get(name)
        if own is None and widths.pooled is None:
            continue
        codes = own.codes if own is not None else np.arange(*_span(widths.pooled))
        ax2.plot(codes, table.centres[j, codes] - codes, ".-", ms=2, lw=0.6, label=name)
    ax2.set_xlabel("code")
    ax2.set_ylabel("INL: centre - code (counts)")
    ax2.set_title("integral non-linearity over the codes each channel read (the table's)")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _span(w) -> tuple[int, int]:
    return int(w.codes[0]), int(w.codes[-1]) + 1


def _as_json(widths) -> dict:
    def one(w):
        if w is None:
            return None
        return {"pattern": w.pattern.round(4).tolist(), "pattern_u95": w.pattern_u95.round(4).tolist(),
                "chi2": w.chi2, "dof": w.dof, "p_value": w.p_value, "found": w.pattern_found,
                "sigma_counts": w.sigma_counts, "samples": w.n_samples, "visits": w.n_visits,
                "codes": [int(w.codes[0]), int(w.codes[-1])],
                "odd": [{"code": o.code, "kind": o.kind, "hits": o.hits, "expected": o.expected, "width": o.width,
                         "width_u95": o.width_u95, "p_value": o.p_value} for o in w.odd]}

    return {"channels": {n: one(w) for n, w in widths.channels.items()}, "reasons": widths.reasons,
            "pooled": one(widths.pooled)}


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from fbg_accel_driver.adc_code_table import save_table

    from ..fit.adc_codes import code_table, recording_code_widths
    from ..io.atomic_output import check_outputs, committed_outputs
    from ..io.input_files import load_recording

    outputs = [p for p in (args.plot, args.json, args.output) if p is not None]
    try:
        if not 0.0 < args.alpha < 1.0:
            raise ValueError(f"--alpha {args.alpha} is outside (0, 1)")
        check_outputs(outputs, args.inputs, args.force)
        rec = load_recording(args.inputs, rate=args.rate, temperature=args.temperature, g=args.g,
                             namespace=args.namespace, topic=args.topic)
        groups, rows = visits_of(rec)
        widths = recording_code_widths(np.column_stack([rec.ref, rec.xyz]), groups, rows, alpha=args.alpha)
        if widths.pooled is None:
            raise ValueError(f"{', '.join(map(str, args.inputs))}: no code widths can be measured: "
                             f"{widths.reasons['pooled']}")
    except (OSError, ValueError) as exc:
        print(f"fbg-accel-calib adc-codes: {exc}", file=sys.stderr)
        return 2
    argv = getattr(args, "argv", None)
    argv = sys.argv[1:] if argv is None else argv
    command = "fbg-accel-calib " + " ".join(shlex.quote(str(a)) for a in argv)
    table = code_table(widths, {"source": ", ".join(str(p) for p in args.inputs), "command": command[:512],
                                "method": "code density (IEEE Std 1241 histogram test) over the visits' own densities, "
                                          "period-16 pattern pooled over the channels read over 32 codes or more",
                                "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")})
    for line in widths.summary():
        print(line)
    if widths.pooled is not None:
        print("pooled widths (code mod 16 = 0..15): " + " ".join(f"{v:.2f}" for v in widths.pooled.pattern))
        print("their 95 % intervals (+-):           " + " ".join(f"{v:.2f}" for v in widths.pooled.pattern_u95))
    with committed_outputs() as outs:  # the plot, JSON and table together or none of them
        if args.plot is not None:
            plot(widths, table, outs.path(args.plot))
        if args.json is not None:
            outs.path(args.json).write_text(json.dumps(_as_json(widths), indent=1), encoding="utf-8")
        if args.output is not None:
            save_table(table, outs.path(args.output))
    for p in outputs:
        print(f"wrote {p}")
    return 0
