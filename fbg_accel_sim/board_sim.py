"""``board_sim``: the simulated acquisition board (command-line entry point, no ROS).

Serves the board's binary frames on a pseudo-terminal in real time and prints exactly one line
``PTY <path>`` on stdout once the port is ready; or, with ``--output FILE``, writes the same byte
stream to a file as fast as it can. ``--truth FILE.npz`` saves the truth arrays and the fault
counters (what a decoder must report). On a pty, SIGTERM/SIGINT end the run cleanly (truth is written);
with ``--output`` they abandon it (exit 130 / 143, neither file written: a shortened stream is not the
run asked for).

Outputs never destroy data (``fbg_accel_calibration.io.atomic_output``): ``--output`` and ``--truth`` are
refused if they exist (unless ``--force``), name an input (``--config``, ``--dynamic-plan``) or each
other, and are written to temporary files renamed together at the end; ``--link`` is refused if
something other than a symbolic link is at its path (it is replaced by a link and removed at exit).

Examples::

    board_sim --link /tmp/fbg_board                       # real time, symlink to the current pty
    board_sim --rate 1000 --set effects.tia_lowpass.scale=0
    board_sim --duration 60 --output run.bin --truth run_truth.npz --set faults.bit_flips.count=5
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import warnings
from pathlib import Path

from fbg_accel_calibration.io import input_validation as iv
from fbg_accel_driver.command_line import OneLineErrorParser, one_line, printable, version_line

from .sim_config import SimConfig, SimConfigError, parse_set_argument

# Bounds of the options (a hostile value is refused in one line, never a traceback or a run without end): frames
# of >= 14 bytes at the fastest baud rate the driver accepts (4 Mbaud) cannot exceed ~28 kHz; a year of samples.
MAX_RATE_HZ = 1e5
MAX_DURATION_S = 3.2e7


def build_parser() -> argparse.ArgumentParser:
    p = OneLineErrorParser(prog="board_sim",
                                description="Simulated FBG accelerometer board (binary frames v1, or v2 with the aux channel).")
    p.add_argument("--config", help="simulator config YAML merged on config/sim_default.yaml")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key (dotted, value parsed as YAML); repeatable")
    p.add_argument("--dynamic-plan", metavar="FILE",
                   help="run an excitation plan (fbg_accel_excitation_plan YAML: slide + reference transducer on the "
                        "aux channel, protocol version 2), e.g. config/excitation_plan_stepped_sine.yaml")
    p.add_argument("--seed", type=iv.seed, default=0, help="random seed (default 0)")
    p.add_argument("--duration", type=iv.float_in(0.0, MAX_DURATION_S, "s", lo_open=True), default=None,
                   help="seconds to run (default: the scenario's end, or until killed; with --dynamic-plan until killed "
                        "on a pty, the plan + 2 s to --output)")
    p.add_argument("--rate", type=iv.float_in(0.0, MAX_RATE_HZ, "Hz", lo_open=True), default=None,
                   help="board sample rate in Hz (scenario.rate_hz)")
    p.add_argument("--output", help="write the byte stream to this file instead of a pty (not paced)")
    p.add_argument("--truth", help="write truth arrays and fault counters to this .npz at exit")
    p.add_argument("--link", help="symlink kept pointing at the current pty slave (re-pointed after a disconnect); "
                                  "refused if a file or directory is at that path")
    p.add_argument("--force", action="store_true", help="replace existing --output / --truth files (default: refuse)")
    p.add_argument("--no-wait-client", action="store_true",
                   help="start streaming at once instead of when a client first opens the pty (board reset on open)")
    p.add_argument("--print-config", action="store_true", help="print the merged config as YAML and exit")
    p.add_argument("--version", action="version", version=version_line("board_sim"))
    return p


def load_config(args: argparse.Namespace) -> SimConfig:
    cfg = SimConfig.load(args.config) if args.config else SimConfig.default()
    overrides: dict = {}
    if args.dynamic_plan:
        from fbg_accel_calibration.dynamic.excitation_plan import ExcitationPlan, ExcitationPlanError

        try:
            plan = ExcitationPlan.load(args.dynamic_plan)
        except ExcitationPlanError as exc:
            raise SimConfigError(str(exc)) from None
        overrides.update(plan.sim_overrides())
        if args.duration is None:
            # A file ends 2 s after the plan. On a pty the board streams on at rest until killed, as a real board does
            # when the slide stops: a recorder started after the board (the README's order) counts the plan from its
            # own first sample, and a board that stopped at its own plan end left it waiting for the stream forever.
            overrides["scenario.duration_s"] = plan.start_s + plan.duration_s + 2.0 if args.output else math.inf
    overrides.update(parse_set_argument(s) for s in args.set)
    if args.rate is not None:
        overrides["scenario.rate_hz"] = float(args.rate)
    if args.duration is not None:
        overrides["scenario.duration_s"] = float(args.duration)
    return cfg.with_overrides(overrides) if overrides else cfg


def check_outputs(args: argparse.Namespace) -> None:
    """Before any simulation: the outputs destroy nothing (module docstring). Raises ``OutputError``."""
    from fbg_accel_calibration.io.atomic_output import OutputError
    from fbg_accel_calibration.io.atomic_output import check_outputs as check

    inputs = [p for p in (args.config, args.dynamic_plan) if p]
    check([p and Path(p) for p in (args.output, args.truth)], inputs, args.force)
    if args.link and os.path.lexists(args.link) and not os.path.islink(args.link):
        raise OutputError(f"--link {args.link}: a {'directory' if os.path.isdir(args.link) else 'file'} is at that "
                          "path; give a path that is free or a symbolic link (the link is replaced and removed at "
                          "exit)")


def main(argv: list[str] | None = None) -> int:
    from fbg_accel_calibration.io.atomic_output import committed_outputs

    args = build_parser().parse_args(argv)
    from .board_physics import BoardSimulator  # numpy: only once --help and --version have answered
    from .pty_server import TruthRecorder, serve_pty

    try:
        check_outputs(args)
        cfg = load_config(args)
        if args.print_config:
            print(cfg.to_yaml())
            return 0
        with warnings.catch_warnings(record=True) as held:  # numpy's warnings on an absurd value: shown if it runs
            warnings.simplefilter("always")
            sim = BoardSimulator(cfg, seed=args.seed)
            if not 0 < sim.rate_hz <= MAX_RATE_HZ:
                raise ValueError(f"scenario.rate_hz = {sim.rate_hz:g} is outside (0, {MAX_RATE_HZ:g}] Hz")
        for w in held:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    except (SimConfigError, ValueError, OSError) as exc:
        print(f"board_sim: error: {printable(one_line(str(exc)))}", file=sys.stderr)
        return 2
    except (TypeError, ArithmeticError) as exc:  # a --set / --config value of the wrong kind or size
        print(f"board_sim: error: invalid simulator configuration: {printable(one_line(str(exc)))}", file=sys.stderr)
        return 2

    stop = {"signal": 0}

    def on_signal(signum, frame):
        stop["signal"] = signum

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    truth = TruthRecorder() if args.truth else None
    duration = sim.duration_s
    extra: dict = {"disconnect_windows_s": [[t, t + d] for t, d in sim.disconnects] or [[math.nan, math.nan]]}
    if args.output and not math.isfinite(duration):
        print("board_sim: error: --output needs a finite run: give --duration (the scenario never ends)",
              file=sys.stderr)
        return 2
    try:
        with committed_outputs() as outs:
            if args.output:
                n_total = sim.samples_for(duration)
                with open(outs.path(args.output), "wb") as fh:
                    while sim.sample_index < n_total and not stop["signal"]:
                        block = sim.step(min(65536, n_total - sim.sample_index))
                        fh.write(block.wire_bytes())
                        if truth is not None:
                            truth.add(block)
                if stop["signal"]:
                    raise KeyboardInterrupt  # the outputs are discarded
            else:
                stats = serve_pty(sim, duration, args.link, truth, lambda: bool(stop["signal"]),
                                  announce=lambda line: print(line, flush=True), wait_client=not args.no_wait_client)
                extra.update({k: stats[k] for k in ("reconnects", "overflow_bytes", "written_bytes",
                                                    "frames_lost_no_client", "unplug_unread_bytes")})
            if truth is not None:
                truth.save(outs.path(args.truth), sim, extra)
    except KeyboardInterrupt:
        print("board_sim: interrupted; no output written", file=sys.stderr)
        return 128 + (stop["signal"] or signal.SIGINT)
    except (OSError, ValueError) as exc:
        print(f"board_sim: error: {printable(str(exc))}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
