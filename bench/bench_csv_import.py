"""Benchmark: peak memory and time of ``fbg-accel-calib import`` on a large CSV (issue 11).

Not a test (never run by pytest). Writes a synthetic interchange CSV of about ``--mb`` MB (t_s,
counts, gref, temperature, pose: six poses repeated, 100 Hz), then runs in fresh processes, so that
each peak resident set (``ru_maxrss`` of the child, KiB -> MB) is its own:

* ``import``: ``fbg-accel-calib import CSV -o OUT.mcap`` (streamed block by block, the CLI path);
* ``import_csv``: ``csv_import.import_csv`` (the whole recording in arrays, used by fit/diagnose/allan
  when given a CSV), for comparison;
* ``fit``: ``fbg-accel-calib fit CSV -o OUT.yaml --degree 0 --max-degree 0`` (streamed: the CSV is
  re-read block by block on every pass of ``fit_stream.prepare_stream``);
* ``baseline``: a Python process that imports the same modules and opens and closes one empty MCAP
  writer (the fixed cost of the message definitions and the compressor), nothing else.

The figure of merit is ``peak - baseline`` against the file size. For comparison, the import of the
code before issue 11 (``import_csv`` to Python lists, then ``write_recording``) peaked at 2251 MB on
the same 200 MB file (37.7 s), measured by hand with that commit's tree on PYTHONPATH. Writes bench/results/csv_import.json.

    .venv/bin/python bench/bench_csv_import.py [--mb 200] [--dir DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from machine_info import machine
from output_paths import add_update_results, results_dir

HERE = Path(__file__).resolve().parent
PY = sys.executable
HEADER = "t_s,ref_counts,x_counts,y_counts,z_counts,gref_x_mps2,gref_y_mps2,gref_z_mps2,temperature_c,pose\n"
SIX = [(0, 0, 9.80665), (0, 0, -9.80665), (9.80665, 0, 0), (-9.80665, 0, 0), (0, 9.80665, 0), (0, -9.80665, 0)]
PER_POSE = 3000  # 30 s at 100 Hz


def write_csv(path: Path, mb: float) -> int:
    """A CSV of about ``mb`` MB; returns the number of data rows."""
    rng = np.random.default_rng(0)
    target = int(mb * 1e6)
    n = 0
    with open(path, "w") as fh:
        fh.write(HEADER)
        while fh.tell() < target:
            block = []
            for _ in range(PER_POSE):
                p = (n // PER_POSE) % 6
                gx, gy, gz = SIX[p]
                c = np.array([1000 + 8 * gx, 1500 + 8 * gy, 1200 + 8 * gz]) + rng.normal(0, 0.5, 3)
                block.append(f"{n * 0.01:.2f},880,{c[0]:.2f},{c[1]:.2f},{c[2]:.2f},{gx},{gy},{gz},23.40,{n // PER_POSE}\n")
                n += 1
            fh.write("".join(block))
    return n


CHILD = """
import resource, sys, time
from fbg_accel_calibration.commands import cli
from fbg_accel_calibration.io import csv_import, mcap_writer  # noqa: F401
mode, csv, out = sys.argv[1], sys.argv[2], sys.argv[3]
t0 = time.perf_counter()
if mode == "import":
    rc = cli.main(["import", csv, "-o", out, "--force"])
    assert rc == 0
elif mode == "fit":
    rc = cli.main(["fit", csv, "-o", out.replace(".mcap", ".yaml"), "--degree", "0", "--max-degree", "0", "--force"])
    assert rc == 0
elif mode == "baseline":  # the fixed cost: modules, ROS 2 message definitions, one empty MCAP writer
    with mcap_writer.RecordingWriter(out, {"sensor_id": "baseline"}):
        pass
elif mode == "import_csv":
    rec, _ = csv_import.import_csv(csv)
    print("rows", len(rec), file=sys.stderr)
wall = time.perf_counter() - t0
print(f"RESULT {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.1f} {wall:.2f}")
"""


def run(mode: str, csv: Path, out: Path) -> dict:
    res = subprocess.run([PY, "-c", CHILD, mode, str(csv), str(out)], capture_output=True, text=True, check=True)
    line = next(ln for ln in res.stdout.splitlines() if ln.startswith("RESULT"))
    peak, wall = (float(v) for v in line.split()[1:])
    return {"peak_rss_mb": peak, "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mb", type=float, default=200.0, help="CSV size, MB (default 200)")
    ap.add_argument("--dir", type=Path, default=None, help="work directory (default: a temporary one)")
    add_update_results(ap)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        d = Path(tmp)
        csv = d / "big.csv"
        t0 = time.perf_counter()
        rows = write_csv(csv, args.mb)
        size_mb = csv.stat().st_size / 1e6
        print(f"wrote {csv}: {size_mb:.1f} MB, {rows} rows in {time.perf_counter() - t0:.1f} s", flush=True)
        result = {"machine": machine(), "csv_mb": round(size_mb, 1), "rows": rows,
                  "command": f".venv/bin/python bench/bench_csv_import.py --mb {args.mb:g}"}
        for mode in ("baseline", "import", "import_csv", "fit"):
            r = run(mode, csv, d / "out.mcap")
            result[mode] = r
            print(mode, r, flush=True)
        base = result["baseline"]["peak_rss_mb"]
        for mode in ("import", "import_csv", "fit"):
            result[mode]["peak_minus_baseline_mb"] = round(result[mode]["peak_rss_mb"] - base, 1)
            result[mode]["over_file_size"] = round((result[mode]["peak_rss_mb"] - base) / size_mb, 3)
        result["mcap_mb"] = round((d / "out.mcap").stat().st_size / 1e6, 1)
    out = results_dir(args.update_results) / "csv_import.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "machine"}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
