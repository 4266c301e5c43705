#!/usr/bin/env python3
"""The read of a calibration MCAP recording by this tree against an older commit's: the same results, and the time.

Not a test (never run by pytest). The older commit's reader (``--base``, default ``a41d18c``) is taken out with
``git archive`` into a scratch directory; each read runs in a fresh child process of this venv's Python, the old
and the new tree alternated (old, new, old, new, ...), so that the two see the same minutes of a shared machine.
Two reads are measured:

* ``load``: ``input_files.load_recording`` of the file (what ``fbg-accel-calib diagnose`` and ``fit --in-memory``
  read first), CPU and wall seconds of that call alone;
* ``stream``: the streamed read of ``fbg-accel-calib fit`` (``McapSampleStream.blocks``): a first pass of blocks
  without poses, then a pass with poses (replayed from the first pass's spill).

Equality, for each file and read, old against new: every array of the Recording(s) (``np.array_equal`` with NaN
equal to NaN, same dtype, shape and C-contiguity), its metadata (the read report, pose events, ...), the stream's report, and
the lines written to stderr; an error, if the read raises, must be the same type and message. Prints every run and
the medians, and writes them as JSON (``--output``, default the scratch directory's ``mcap_read_check.json``).

    .venv/bin/python bench/mcap_read_check.py FILE.mcap [FILE ...] [--repeats 5] [--modes load,stream]
    .venv/bin/python bench/mcap_read_check.py --equal-only test_recordings/*.mcap   # equality, no timing
"""

from __future__ import annotations

import argparse
import json
import pickle
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from output_paths import results_dir

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("fbg_accel_calibration", "fbg_accel_driver")


def base_tree(ref: str, folder: Path) -> Path:
    """The packages of commit ``ref``, extracted into ``folder``/``ref``."""
    tree = folder / ref
    if not (tree / PACKAGES[0]).is_dir():
        tree.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref, *PACKAGES], check=True, capture_output=True)
        subprocess.run(["tar", "-x", "-C", str(tree)], input=archive.stdout, check=True)
    return tree


def _arrays(obj: Any) -> dict[str, Any]:
    """The fields of a Recording (or anything with ``__dict__``), as plain values."""
    return {k: v for k, v in vars(obj).items()}


def child(tree: str, mode: str, path: str, out: str) -> None:
    """One read in this fresh process with the packages of ``tree`` first on the path; the result pickled to
    ``out``, the seconds printed as JSON on the last stdout line."""
    import contextlib
    import io
    import time

    sys.path.insert(0, tree)
    from fbg_accel_calibration.io import input_files, mcap_reader  # noqa: F401  (imports outside the timing)
    from fbg_accel_calibration.io.mcap_reader import McapSampleStream

    assert Path(input_files.__file__).resolve().is_relative_to(Path(tree).resolve()), input_files.__file__
    if path.startswith("@"):  # a list of files, one a line: their results in one pickle (equality only)
        results = {}
        for line in Path(path[1:]).read_text().splitlines():
            child(tree, mode, line, out)
            results[line] = pickle.loads(Path(out).read_bytes())
        Path(out).write_bytes(pickle.dumps(results))
        return
    err = io.StringIO()
    result: dict[str, Any] = {}
    cpu0, wall0 = time.process_time(), time.perf_counter()
    with contextlib.redirect_stderr(err):
        try:
            if mode == "load":
                rec = input_files.load_recording([path])
                result["recording"] = _arrays(rec)
            else:
                stream = McapSampleStream(path)
                passes = []
                for with_poses in (False, True):
                    blocks = [_arrays(b) for b in stream.blocks(65536, with_poses)]
                    passes.append({k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]
                                   if isinstance(blocks[0][k], np.ndarray)})
                result["passes"] = passes
                result["metadata"] = stream.metadata()
                result["samples"] = stream.samples
        except Exception as exc:  # the same error is part of the same result
            result["error"] = (type(exc).__name__, str(exc))
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    result["stderr"] = err.getvalue()
    with open(out, "wb") as fh:
        pickle.dump(result, fh)
    print(json.dumps({"cpu_s": cpu, "wall_s": wall}))


def same(a: Any, b: Any, where: str = "") -> list[str]:
    """Where ``a`` and ``b`` differ (arrays: dtype, shape and values, NaN equal to NaN); empty when equal."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)) or a.dtype != b.dtype or a.shape != b.shape:
            return [f"{where}: {getattr(a, 'dtype', type(a))}{getattr(a, 'shape', '')} vs "
                    f"{getattr(b, 'dtype', type(b))}{getattr(b, 'shape', '')}"]
        if a.flags.c_contiguous != b.flags.c_contiguous:
            return [f"{where}: C-contiguous {a.flags.c_contiguous} vs {b.flags.c_contiguous}"]
        eq = np.array_equal(a, b, equal_nan=a.dtype.kind in "fc")
        return [] if eq else [f"{where}: values differ"]
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{where}: keys {sorted(a)} vs {sorted(b)}"]
        return [d for k in a for d in same(a[k], b[k], f"{where}.{k}")]
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        if type(a) is not type(b) or len(a) != len(b):
            return [f"{where}: {type(a).__name__} of {len(a)} vs {type(b).__name__} of {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in same(x, y, f"{where}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b):
        return []
    return [] if (type(a) is type(b) and a == b) else [f"{where}: {a!r:.200} vs {b!r:.200}"]


def run(tree: Path, mode: str, path: Path, out: Path) -> dict[str, float]:
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", str(tree), mode, str(path),
                           str(out)], capture_output=True, text=True, check=False)
    if proc.returncode:
        raise SystemExit(f"child failed ({tree}, {mode}, {path}):\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="*", type=Path)
    ap.add_argument("--base", default="a41d18c", help="the commit the reader is compared with")
    ap.add_argument("--repeats", type=int, default=5, help="old/new pairs timed per file and read")
    ap.add_argument("--modes", default="load,stream", help="reads: load, stream (comma separated)")
    ap.add_argument("--equal-only", action="store_true", help="one pair per file and read, equality only")
    ap.add_argument("--output", type=Path, default=None)
    ap.add_argument("--child", nargs=4, metavar=("TREE", "MODE", "FILE", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return 0
    repeats = 1 if args.equal_only else args.repeats
    report: dict[str, Any] = {"base": args.base, "repeats": repeats, "files": {}}
    failures = 0
    with tempfile.TemporaryDirectory(prefix="mcap_read_check_") as tmp:
        trees = {"old": base_tree(args.base, Path(tmp)), "new": ROOT}
        if args.equal_only and len(args.files) > 4:  # many files: one child per tree and read reads them all
            listing = Path(tmp) / "files.txt"
            listing.write_text("\n".join(str(f) for f in args.files))
            for mode in args.modes.split(","):
                outs = {k: Path(tmp) / f"{k}.pkl" for k in trees}
                for name in trees:
                    run(trees[name], mode, Path("@" + str(listing)), outs[name])
                loaded = {k: pickle.loads(outs[k].read_bytes()) for k in trees}
                for path in args.files:
                    diffs = same(loaded["old"][str(path)], loaded["new"][str(path)], mode)
                    failures += bool(diffs)
                    err = loaded["new"][str(path)].get("error")
                    report["files"].setdefault(str(path), {})[mode] = {"equal": not diffs, "error": err}
                    if diffs:
                        print(f"{path} {mode}: DIFFERENT", *diffs[:20], sep="\n    ")
                n_err = sum(1 for v in report["files"].values() if v[mode]["error"])
                print(f"{mode}: {len(args.files)} inputs, {len(args.files) - failures} equal ({n_err} raise the same "
                      "error in both)", flush=True)
            out = args.output or results_dir(False) / "mcap_read_check.json"
            out.write_text(json.dumps(report, indent=1))
            print(f"wrote {out}; {'all equal' if not failures else f'{failures} DIFFERENT'}")
            return 1 if failures else 0
        for path in args.files:
            for mode in args.modes.split(","):
                times: dict[str, list[dict[str, float]]] = {"old": [], "new": []}
                outs = {k: Path(tmp) / f"{k}.pkl" for k in trees}
                for i in range(repeats):
                    for name in ("old", "new"):
                        times[name].append(run(trees[name], mode, path, outs[name]))
                    if i == 0:
                        loaded = {k: pickle.loads(outs[k].read_bytes()) for k in trees}
                        diffs = same(loaded["old"], loaded["new"], mode)
                        failures += bool(diffs)
                        err = loaded["new"].get("error")
                        print(f"{path} {mode}: {'EQUAL' if not diffs else 'DIFFERENT'}"
                              f"{' (both raise ' + err[0] + ')' if err else ''}", flush=True)
                        for d in diffs[:20]:
                            print(f"    {d}")
                    line = "  ".join(f"{k} cpu {times[k][-1]['cpu_s']:.3f} s wall {times[k][-1]['wall_s']:.3f} s"
                                     for k in ("old", "new"))
                    if not args.equal_only:
                        print(f"  run {i + 1}: {line}", flush=True)
                entry = {"equal": not diffs, "runs": times}
                if not args.equal_only:
                    med = {k: {m: statistics.median(t[m] for t in times[k]) for m in ("cpu_s", "wall_s")}
                           for k in times}
                    entry["median"] = med
                    entry["cpu_ratio_new_old"] = med["new"]["cpu_s"] / med["old"]["cpu_s"]
                    print(f"  median: old cpu {med['old']['cpu_s']:.3f} s wall {med['old']['wall_s']:.3f} s, new cpu "
                          f"{med['new']['cpu_s']:.3f} s wall {med['new']['wall_s']:.3f} s: new/old cpu "
                          f"{entry['cpu_ratio_new_old']:.2f}", flush=True)
                report["files"].setdefault(str(path), {})[mode] = entry
    out = args.output or results_dir(False) / "mcap_read_check.json"
    out.write_text(json.dumps(report, indent=1))
    print(f"wrote {out}; {'all equal' if not failures else f'{failures} DIFFERENT'}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
