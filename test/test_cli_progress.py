"""Progress bars of fbg-accel-calib (issue 10, operator polish): on stderr, per pass, never on stdout, and
absent by default when stderr is not a terminal (logs and pipes stay clean)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_fit_streaming import make_run

from fbg_accel_calibration.io.mcap_writer import write_recording

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

BIN = Path(sys.executable).parent


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "fbg-accel-calib"), *args], capture_output=True, text=True, timeout=300)


def test_fit_import_and_diagnose_show_progress_on_stderr_only_when_asked(tmp_path: Path) -> None:
    runs = [make_run(i, t, t0_s=i * 100.0) for i, t in enumerate((15.0, 25.0, 35.0))]
    paths = []
    for i, r in enumerate(runs):
        paths.append(tmp_path / f"run{i}.mcap")
        write_recording(paths[-1], r, {"sensor_id": "p"})
    res = _run("fit", *map(str, paths), "-o", str(tmp_path / "a.yaml"), "--progress")
    assert res.returncode == 0, res.stderr
    assert "fit run0.mcap: pass 1" in res.stderr and "fit run2.mcap: pass 3" in res.stderr
    assert "samples" in res.stderr and ": pass " not in res.stdout
    quiet = _run("fit", *map(str, paths), "-o", str(tmp_path / "b.yaml"))  # stderr is a pipe: no bars
    assert quiet.returncode == 0 and "pass 1" not in quiet.stderr
    assert quiet.stdout == res.stdout.replace(str(tmp_path / "a.yaml"), str(tmp_path / "b.yaml"))

    rec = runs[0]
    csv = tmp_path / "r.csv"
    rows = ["t_s,ref_counts,x_counts,y_counts,z_counts,gref_x_mps2,gref_y_mps2,gref_z_mps2,temperature_c,pose"]
    for i in range(len(rec)):
        g = rec.gref_mps2[i]
        if not np.all(np.isfinite(g)):
            continue  # moving rows: the interchange format needs a reference on every row
        rows.append(f"{rec.t_s[i]:.3f},{rec.ref[i]:.3f},{rec.xyz[i, 0]:.3f},{rec.xyz[i, 1]:.3f},{rec.xyz[i, 2]:.3f},"
                    + ",".join(f"{v:.6f}" for v in g)
                    + f",{25.0 if not np.isfinite(rec.temp_c[i]) else rec.temp_c[i]:.3f},{rec.pose_id[i]}")
    csv.write_text("\n".join(rows) + "\n")
    res = _run("import", str(csv), "-o", str(tmp_path / "r.mcap"), "--progress")
    assert res.returncode == 0, res.stderr
    assert "import r.csv (1: check, 2: write): pass 2" in res.stderr and ": pass " not in res.stdout
    res = _run("diagnose", str(paths[1]), "--max-effects", "1", "--progress")
    assert res.returncode == 0, res.stderr
    assert "diagnose: candidate effects evaluated" in res.stderr
