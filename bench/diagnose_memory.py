#!/usr/bin/env python3
"""Where the diagnosis's resident memory peaks, phase by phase (not a test).

Reads the simulator's benchmark run of ``--samples`` samples from MCAP (``diagnose_command.recording``, written once
into ``--dir``), then diagnoses it as the command does (``diagnose()`` with its defaults, ``--lanes`` searches side
by side) while a thread samples the process's resident set (``VmRSS`` of ``/proc/self/status``, every 20 ms) and the
diagnosis function the main thread is in. Prints, for each phase (reading the recording, the declared model and its
floor, the searches, the final model with the residual's test, what follows), the highest resident set seen in it
and the line it was seen at, then the process's peak (``ru_maxrss``) and the diagnosis's CPU time. Linux only.

    .venv/bin/python bench/diagnose_memory.py --samples 1000000 --lanes 1
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

# the phases, by the first of these functions found on the main thread's stack (innermost first)
PHASES = (("fit_final", "final model and the residual's test"), ("forward_selection", "searches"),
          ("measure_floor", "declared model and its floor"), ("declared_model", "declared model and its floor"),
          ("prepare_data", "preparing the data"), ("load_recording", "reading the recording"),
          ("diagnose", "findings and the rest"))
ORDER = ("start", "reading the recording", "preparing the data", "declared model and its floor", "searches",
         "final model and the residual's test", "findings and the rest")


def rss_mib() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    return float("nan")


def phase_of(stack: list[traceback.FrameSummary]) -> tuple[str, str]:
    """(the phase, the innermost line of the project's code) of a main-thread stack (outermost first)."""
    names = [f.name for f in stack]
    phase = next((label for fn, label in PHASES if fn in names), "start")
    ours = [f for f in stack if "fbg_accel" in f.filename]
    where = f"{Path(ours[-1].filename).name}:{ours[-1].lineno} {ours[-1].name}" if ours else ""
    return phase, where


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--lanes", type=int, default=None, help="searches side by side (default: diagnose's own choice)")
    ap.add_argument("--dir", type=Path, default=None, help="where the recording is written once (default: a temporary "
                                                          "directory)")
    args = ap.parse_args(argv)
    from diagnose_command import recording

    from fbg_accel_calibration.diagnosis.diagnose import diagnose
    from fbg_accel_calibration.diagnosis.heap_policy import set_process_heap_policy
    from fbg_accel_calibration.io.input_files import load_recording

    with tempfile.TemporaryDirectory() as tmp:
        path = recording(args.samples, args.dir or Path(tmp))
        set_process_heap_policy()  # as the command's entry point does
        main_id = threading.main_thread().ident
        highest: dict[str, tuple[float, str]] = {}
        done = threading.Event()

        def watch() -> None:
            while not done.is_set():
                r = rss_mib()
                frame = sys._current_frames().get(main_id)
                phase, where = phase_of(traceback.extract_stack(frame)) if frame is not None else ("start", "")
                if r > highest.get(phase, (0.0, ""))[0]:
                    highest[phase] = (r, where)
                time.sleep(0.02)

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        rec = load_recording([str(path)], rate=None, temperature=None, g=None, namespace=None, topic=None)
        cpu = time.process_time()
        diagnose(rec, sensor_id="bench", lanes=args.lanes)
        cpu = time.process_time() - cpu
        done.set()
        watcher.join()
    print(f"{args.samples} samples, lanes {args.lanes or 'default'}: diagnose() {cpu:.1f} s CPU (with the sampling "
          "thread's)")
    for phase in ORDER:
        if phase in highest:
            r, where = highest[phase]
            print(f"  {phase:<38} highest {r:6.0f} MiB  at {where}")
    print(f"peak (ru_maxrss) {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
