"""Property-based test of every ``fbg-accel-calib`` subcommand with generated hostile inputs (issue 11).

Inputs: a valid six-pose CSV mutated cell by cell (numbers out of range, NaN, text, huge fields, empty
cells), line by line (deleted, duplicated, truncated) and byte by byte (flips, invalid UTF-8, a BOM, a bare CR,
CR or CRLF line ends);
a valid MCAP and calibration YAML truncated or with bytes overwritten; hostile option values.
Every subcommand is called in process (``cli.main``). Asserted for every example:

* the exit code is 0 or 2 (an argparse usage error is ``SystemExit(2)``), never an exception;
* stderr holds no traceback;
* on failure no output file is left behind, and no input is ever modified.

Bounded: fixed ``max_examples`` per subcommand, no per-example deadline (plots and fits take
0.05-1 s), the whole file runs in well under a minute.
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from fbg_accel_calibration.commands.cli import main

HEADER = ["t_s", "ref_counts", "x_counts", "y_counts", "z_counts", "gref_x_mps2", "gref_y_mps2", "gref_z_mps2",
          "temperature_c", "pose"]
SIX = [(0, 0, 9.8), (0, 0, -9.8), (9.8, 0, 0), (-9.8, 0, 0), (0, 9.8, 0), (0, -9.8, 0)]
HOSTILE_CELLS = ["", "nan", "inf", "-inf", "1e300", "-1e300", "60880", "-1", "0", "1e10", "-0.5", "abc", "1.5",
                 "0x10", "  ", '"', '"a,b"', "x" * 70_000, "\u00e9", "1e-320", "4096", "4095", "-40", "85.1"]
HOSTILE_OPTIONS = {
    "--rate": ["0", "nan", "-1", "1e300", "1", "100", "100", "abc"],
    "--temperature": ["nan", "1e300", "-273", "23.4", "inf"],
    "--g": ["nan", "-9.81", "0", "9.81", "1e300"],
    "--window": ["0", "1", "2", "5", "-3", "1e9"],
    "--min-interval": ["0", "1", "5", "x"],
    "--level-gap": ["-1", "0", "nan", "0.5", "1e300"],
    "--degree": ["-1", "0", "1", "6", "99"],
    "--max-degree": ["-1", "0", "2", "50"],
}
DIAGNOSE_OPTIONS = {
    "--alpha": ["nan", "0", "1", "0.01", "-1"],
    "--min-gain": ["nan", "-0.1", "0.02", "2"],
    "--folds": ["0", "1", "2", "3", "1000000"],
    "--max-effects": ["-1", "0", "1"],
    "--seed": ["-1", "0", "99999999999"],
    "--static": ["table", "detector", "all", "bogus"],
    "--figures": ["report", "all", "none", "bogus"],
}
FEW = [0, 0, 0, 0, 1, 1, 2, 4]  # mutations per kind: most inputs keep most of the file valid, so deep code runs
# HOSTILE_EXAMPLES=500 (environment) for a longer, randomised search; the default run is short and fixed
EXAMPLES = int(os.environ.get("HOSTILE_EXAMPLES", "0"))
SETTINGS = settings(max_examples=EXAMPLES or 25, deadline=None, derandomize=not EXAMPLES,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.function_scoped_fixture])


def base_rows(per_pose: int = 25) -> list[list[str]]:
    rng = np.random.default_rng(0)
    rows, i = [], 0
    for p, (gx, gy, gz) in enumerate(SIX):
        for _ in range(per_pose):
            c = np.array([1000 + 80 * gx, 1500 + 80 * gy, 1200 + 80 * gz]) + rng.normal(0, 0.5, 3)
            rows.append([f"{i * 0.01:.2f}", "880", f"{c[0]:.2f}", f"{c[1]:.2f}", f"{c[2]:.2f}", str(gx), str(gy),
                         str(gz), "23.4", str(p)])
            i += 1
    return rows


@st.composite
def hostile_csv(draw: st.DrawFn, per_pose: int = 25) -> bytes:
    rows = base_rows(per_pose)
    header = list(HEADER)
    if draw(st.integers(0, 3)) == 0:  # drop or rename a column (1 in 4)
        k = draw(st.integers(0, len(header) - 1))
        if draw(st.booleans()):
            header.pop(k)
            rows = [r[:k] + r[k + 1:] for r in rows]
        else:
            header[k] = draw(st.sampled_from(["", "t_s", "ref_counts", "psi_deg", "bogus"]))
    for _ in range(draw(st.sampled_from(FEW))):  # cell mutations
        r, c = draw(st.integers(0, len(rows) - 1)), draw(st.integers(0, len(header) - 1))
        if c < len(rows[r]):
            rows[r][c] = draw(st.sampled_from(HOSTILE_CELLS) | st.text(max_size=8))
    for _ in range(draw(st.sampled_from(FEW))):  # line mutations
        op = draw(st.sampled_from(["delete", "duplicate", "shorten", "extend"]))
        r = draw(st.integers(0, len(rows) - 1))
        if op == "delete" and len(rows) > 1:
            rows.pop(r)
        elif op == "duplicate":
            rows.insert(r, list(rows[r]))
        elif op == "shorten":
            rows[r] = rows[r][:-1]
        else:
            rows[r] = [*rows[r], "1"]
    text = ",".join(header) + "\n" + "".join(",".join(r) + "\n" for r in rows)
    data = bytearray(text.encode("utf-8", "surrogatepass"))
    for _ in range(draw(st.sampled_from(FEW))):  # byte mutations
        op = draw(st.sampled_from(["flip", "bad_utf8", "truncate", "bom", "nul", "cr", "line_ends"]))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        if op == "flip" and data:
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif op == "bad_utf8":
            data[at:at] = b"\xff\xfe"
        elif op == "truncate":
            del data[at:]
        elif op == "bom":
            data[0:0] = b"\xef\xbb\xbf"
        elif op == "cr":  # a bare carriage return inside a line
            data[at:at] = b"\r"
        elif op == "line_ends":  # the whole file with other line ends: bare CR (classic Mac OS) or CRLF
            data[:] = data.replace(b"\n", draw(st.sampled_from([b"\r", b"\r\n"])))
        else:
            data[at:at] = b"\x00"
    return bytes(data)


def mutated(data: bytes, draw: st.DrawFn) -> bytes:
    out = bytearray(data)
    op = draw(st.sampled_from(["truncate", "overwrite", "flip", "none", "none"]))
    at = draw(st.integers(0, len(out) - 1))
    if op == "truncate":
        del out[at:]
    elif op == "overwrite":
        patch = draw(st.binary(min_size=1, max_size=16))
        out[at:at + len(patch)] = patch
    elif op == "flip":
        out[at] ^= 1 << draw(st.integers(0, 7))
    return bytes(out)


def options(draw: st.DrawFn, pool: dict[str, list[str]], names: list[str]) -> list[str]:
    out: list[str] = []
    for name in draw(st.lists(st.sampled_from(names), max_size=2, unique=True)):
        out += [name, draw(st.sampled_from(pool[name]))]
    return out


@pytest.fixture(scope="module")
def good_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    d = tmp_path_factory.mktemp("good")
    csv = d / "good.csv"
    csv.write_text(",".join(HEADER) + "\n" + "".join(",".join(r) + "\n" for r in base_rows()))
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["import", str(csv), "-o", str(d / "good.mcap")]) == 0
        assert main(["fit", str(csv), "-o", str(d / "good.yaml")]) == 0
    return {"csv": csv.read_bytes(), "mcap": (d / "good.mcap").read_bytes(), "yaml": (d / "good.yaml").read_bytes()}


def check(argv: list[str], work: Path, inputs: dict[str, bytes]) -> int:
    """Run ``main(argv)`` in ``work``; assert exit 0/2, no traceback, inputs unchanged, no outputs on failure."""
    before = {p.name for p in work.iterdir()}
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            rc = main(argv)
        except SystemExit as exc:  # argparse usage error
            rc = exc.code
    text = err.getvalue()
    event(f"{argv[0]}: exit {rc}")
    assert rc in (0, 2), (argv, rc, text)
    assert "Traceback" not in text, text
    for name, data in inputs.items():
        assert (work / name).read_bytes() == data, f"input {name} was modified"
    after = {p.name for p in work.iterdir()}
    assert not [n for n in after if ".part" in n or n.startswith(".plots.")], after
    if rc != 0:
        assert after == before, f"output left behind on failure: {sorted(after - before)} ({text})"
    return rc


def in_dir(files: dict[str, bytes]) -> tuple[tempfile.TemporaryDirectory, Path]:
    tmp = tempfile.TemporaryDirectory(prefix="hostile-")
    work = Path(tmp.name)
    for name, data in files.items():
        (work / name).write_bytes(data)
    return tmp, work


@SETTINGS
@given(data=st.data())
def test_import_never_crashes(data: st.DataObject) -> None:
    csv = data.draw(hostile_csv())
    opts = options(data.draw, HOSTILE_OPTIONS, ["--rate", "--temperature", "--g"])
    extra = data.draw(st.sampled_from([[], ["--drop-bad-rows"], ["--force"]]))
    tmp, work = in_dir({"in.csv": csv})
    with tmp:
        check(["import", str(work / "in.csv"), "-o", str(work / "out.mcap"), *opts, *extra], work, {"in.csv": csv})


@SETTINGS
@given(data=st.data())
def test_fit_never_crashes(data: st.DataObject, good_files: dict[str, bytes]) -> None:
    kind = data.draw(st.sampled_from(["csv", "mcap"]))
    blob = data.draw(hostile_csv()) if kind == "csv" else mutated(good_files["mcap"], data.draw)
    name = f"in.{kind}"
    opts = options(data.draw, HOSTILE_OPTIONS, list(HOSTILE_OPTIONS))
    extra = data.draw(st.sampled_from([[], ["--in-memory"]]))
    tmp, work = in_dir({name: blob})
    with tmp:
        check(["fit", str(work / name), "-o", str(work / "cal.yaml"), *opts, *extra], work, {name: blob})


@settings(SETTINGS, max_examples=EXAMPLES or 12)
@given(data=st.data())
def test_diagnose_never_crashes(data: st.DataObject, good_files: dict[str, bytes]) -> None:
    kind = data.draw(st.sampled_from(["csv", "mcap"]))
    blob = data.draw(hostile_csv()) if kind == "csv" else mutated(good_files["mcap"], data.draw)
    name = f"in.{kind}"
    opts = options(data.draw, {**HOSTILE_OPTIONS, **DIAGNOSE_OPTIONS},
                   ["--rate", "--temperature", "--g", "--degree", *DIAGNOSE_OPTIONS])
    tmp, work = in_dir({name: blob})
    with tmp:
        check(["diagnose", str(work / name), "--yaml", str(work / "d.yaml"), *opts], work, {name: blob})


@settings(SETTINGS, max_examples=EXAMPLES or 10)
@given(data=st.data())
def test_allan_and_report_never_crash(data: st.DataObject, good_files: dict[str, bytes]) -> None:
    cmd = data.draw(st.sampled_from(["allan", "report"]))
    rec = data.draw(st.sampled_from(["csv", "mcap"]))
    blob = data.draw(hostile_csv(120)) if rec == "csv" else mutated(good_files["mcap"], data.draw)
    cal = mutated(good_files["yaml"], data.draw) if data.draw(st.booleans()) else good_files["yaml"]
    files = {f"in.{rec}": blob, "cal.yaml": cal}
    tmp, work = in_dir(files)
    with tmp:
        base = [cmd, str(work / f"in.{rec}"), "--calibration", str(work / "cal.yaml")]
        if cmd == "allan":
            argv = [*base, "-o", str(work / "a.png"), "--json", str(work / "a.json"),
                    *options(data.draw, HOSTILE_OPTIONS, ["--rate", "--g"])]
        else:
            argv = [*base, "-o", str(work / "rep"), "--max-degree", "1",
                    *options(data.draw, HOSTILE_OPTIONS, ["--window", "--level-gap", "--g"])]
        check(argv, work, files)


@settings(SETTINGS, max_examples=EXAMPLES or 8)
@given(data=st.data())
def test_report_measured_never_crashes(data: st.DataObject) -> None:
    blob = data.draw(hostile_csv())
    tmp, work = in_dir({"m.csv": blob})
    with tmp:
        check(["report-measured", "--csv", str(work / "m.csv"), "--md", str(work / "r.md"), "--png",
               str(work / "r.png")], work, {"m.csv": blob})


@settings(SETTINGS, max_examples=EXAMPLES or 8)
@given(data=st.data())
def test_field_check_never_crashes(data: st.DataObject, good_files: dict[str, bytes]) -> None:
    rec = data.draw(st.sampled_from(["csv", "mcap"]))
    blob = data.draw(hostile_csv(120)) if rec == "csv" else mutated(good_files["mcap"], data.draw)
    cal = mutated(good_files["yaml"], data.draw) if data.draw(st.booleans()) else good_files["yaml"]
    files = {f"in.{rec}": blob, "cal.yaml": cal}
    tmp, work = in_dir(files)
    with tmp:
        where = data.draw(st.sampled_from([["--gravity", "9.81"], ["--gravity", "nan"], ["--latitude", "45"],
                                           ["--latitude", "100"], ["--latitude", "45", "--height", "1e9"], []]))
        check(["field-check", str(work / f"in.{rec}"), "--calibration", str(work / "cal.yaml"), "-o",
               str(work / "new.yaml"), *where, *options(data.draw, HOSTILE_OPTIONS, ["--window", "--rate"])],
              work, files)


@settings(SETTINGS, max_examples=EXAMPLES or 8)
@given(data=st.data())
def test_uncertainty_measured_never_crashes(data: st.DataObject) -> None:
    blob = data.draw(hostile_csv())
    tmp, work = in_dir({"m.csv": blob})
    with tmp:
        check(["uncertainty-measured", "--csv", str(work / "m.csv"), "--md", str(work / "u.md")], work, {"m.csv": blob})


# ---------------------------------------------------------------------------- board_sim (issue 42)
def _sim_keys() -> list[str]:
    """Dotted keys of the simulator's numeric scalars (config/sim_default.yaml)."""
    from fbg_accel_sim.sim_config import SimConfig

    out: list[str] = []

    def walk(d: dict, prefix: str) -> None:
        for k, v in d.items():
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}.")
            elif isinstance(v, int | float) and not isinstance(v, bool):
                out.append(f"{prefix}{k}")

    walk(SimConfig.default().data, "")
    return sorted(out)


SIM_KEYS = ["scenario.rate_hz", "scenario.duration_s", "faults.garbage.count", "faults.bit_flips.count",
            "effects.tia_lowpass.scale", "board.protocol_version", "scenario.no_such_key", ""]
SIM_VALUES = ["nan", "-1", "1e300", "[1]", "{a: 1}", "abc", "null", "true", "0", "0x52", "1:22", "2026-13-45",
              "[" * 3000 + "]" * 3000, "!!int x", "*a"]
BOARD_SIM_OPTIONS = {
    "--rate": ["0", "nan", "-1", "1e300", "inf", "abc", "100", "1000"],
    "--duration": ["0", "nan", "-1", "1e300", "inf", "abc", "0.05", "0.2"],
    "--seed": ["-1", "0", "99999999999", "1.5", "abc"],
}
CONFIG_TEXTS = ["scenario:\n  rate_hz: 100.0\n", "scenario: 5\n", "[" * 3000 + "]" * 3000, "a: &x 1\nb: *x\n",
                "scenario:\n  rate_hz: 1:22\n", "\xff", "", "scenario:\n  rate_hz: 100\n  rate_hz: 200\n",
                "no_such_section: {}\n"]


def board_sim_check(argv: list[str], work: Path, inputs: dict[str, bytes]) -> int:
    """``board_sim.main(argv)`` in process, as :func:`check`: exit 0 or 2 with one line, nothing destroyed."""
    import signal

    from fbg_accel_sim.board_sim import main as board_sim_main

    before = {p.name for p in work.iterdir()}
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}  # main installs its own
    err = io.StringIO()
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            try:
                rc = board_sim_main(argv)
            except SystemExit as exc:
                rc = exc.code
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
    text = err.getvalue()
    event(f"board_sim: exit {rc}")
    assert rc in (0, 2), (argv, rc, text)
    assert "Traceback" not in text and (rc == 0 or len(text.strip().splitlines()) == 1), (argv, text)
    for name, data in inputs.items():
        assert (work / name).read_bytes() == data, f"input {name} was modified"
    after = {p.name for p in work.iterdir()}
    assert not [n for n in after if ".part" in n], after
    if rc != 0:
        assert after == before, f"output left behind on failure: {sorted(after - before)} ({text})"
    return rc


@settings(SETTINGS, max_examples=EXAMPLES or 30)
@given(data=st.data())
def test_board_sim_never_crashes(data: st.DataObject) -> None:
    """Issue 42: board_sim's options, --set values and --config files, hostile: one line and exit 2, or a run;
    never a traceback (``--rate 1e300`` gave an OverflowError), an endless run or a destroyed file."""
    config = data.draw(st.sampled_from(CONFIG_TEXTS)).encode("utf-8", "surrogateescape")
    files = {"c.yaml": config, "notes.txt": b"precious"}
    tmp, work = in_dir(files)
    with tmp:
        argv = options(data.draw, BOARD_SIM_OPTIONS, list(BOARD_SIM_OPTIONS))
        for _ in range(data.draw(st.sampled_from(FEW))):
            argv += ["--set", f"{data.draw(st.sampled_from(SIM_KEYS))}={data.draw(st.sampled_from(SIM_VALUES))}"]
        if data.draw(st.booleans()):
            argv += ["--config", str(work / "c.yaml")]
        out = data.draw(st.sampled_from(["out.bin", "out.bin", "notes.txt", "c.yaml", "."]))
        argv += ["--output", str(work / out), "--duration" if "--duration" not in argv else "--seed", "0.1"
                 if "--duration" not in argv else "1"]
        truth = data.draw(st.sampled_from([None, "t.npz", "out.bin", "notes.txt"]))
        if truth:
            argv += ["--truth", str(work / truth)]
        if data.draw(st.booleans()):
            argv += ["--link", str(work / data.draw(st.sampled_from(["l", "notes.txt", "."])))]
        board_sim_check(argv, work, files)
