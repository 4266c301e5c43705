"""Issue 11, "data destroyed": outputs never overwrite an input, replace a file only with --force, are
written to a temporary file and renamed on success, and leave nothing behind on failure or Ctrl-C."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from test_input_validation import one_line, run, six_pose_csv

from fbg_accel_calibration.io import atomic_output
from fbg_accel_calibration.io.mcap_reader import read_recording
from fbg_accel_calibration.io.mcap_writer import RecordingWriter


def leftovers(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if ".part" in p.name)


def test_output_that_is_an_input_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`import s.csv -o s.csv` replaced the CSV with MCAP; `fit good.mcap -o good.mcap` the recording with YAML."""
    csv = six_pose_csv(tmp_path / "s.csv")
    before = csv.read_bytes()
    link = tmp_path / "alias.csv"
    link.symlink_to(csv)
    for out in (csv, tmp_path / "." / "s.csv", link):
        rc, err = run(["import", csv, "-o", out, "--force"], capsys)
        assert rc == 2 and "output is the input file" in err
    assert csv.read_bytes() == before
    mcap = tmp_path / "good.mcap"
    assert run(["import", csv, "-o", mcap], capsys)[0] == 0
    rec_bytes = mcap.read_bytes()
    for argv in (["fit", mcap, "-o", mcap, "--force"], ["diagnose", mcap, "--yaml", mcap, "--force"]):
        rc, err = run(argv, capsys)
        assert rc == 2 and "output is the input file" in err and mcap.read_bytes() == rec_bytes
    assert not leftovers(tmp_path)


def test_existing_output_needs_force(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv = six_pose_csv(tmp_path / "s.csv")
    out = tmp_path / "out.mcap"
    out.write_bytes(b"precious")
    rc, err = run(["import", csv, "-o", out], capsys)
    assert rc == 2 and "exists; give --force" in err and out.read_bytes() == b"precious"
    assert run(["import", csv, "-o", out, "--force"], capsys)[0] == 0
    assert len(read_recording(out)) == 300
    assert (out.stat().st_mode & 0o777) == 0o644


def test_failed_import_over_an_existing_file_leaves_it_untouched(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """A failed import over an existing file left a 486-byte stub."""
    csv = six_pose_csv(tmp_path / "s.csv", "9.99,880,abc,1,1,0,0,9.8,23.4,5", at=-1)
    out = tmp_path / "out.mcap"
    out.write_bytes(b"precious")
    rc, err = run(["import", csv, "-o", out, "--force"], capsys)
    assert rc == 2 and "malformed" in err
    assert out.read_bytes() == b"precious" and not leftovers(tmp_path)
    rc, _ = run(["import", csv, "-o", tmp_path / "new.mcap"], capsys)
    assert rc == 2 and not (tmp_path / "new.mcap").exists() and not leftovers(tmp_path)


def test_ctrl_c_during_import_leaves_no_stub(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """KeyboardInterrupt after 100 samples were written (as Ctrl-C during a long import)."""
    csv = six_pose_csv(tmp_path / "s.csv")
    out = tmp_path / "out.mcap"
    out.write_bytes(b"precious")
    real = RecordingWriter.write_raw
    calls = {"n": 0}

    def interrupted(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 100:
            raise KeyboardInterrupt
        return real(self, *a, **k)

    monkeypatch.setattr(RecordingWriter, "write_raw", interrupted)
    rc, err = run(["import", csv, "-o", out, "--force"], capsys)
    assert rc == 130 and "interrupted; no output written" in err and calls["n"] == 100
    assert out.read_bytes() == b"precious" and not leftovers(tmp_path)


def test_an_output_directory_that_cannot_be_made_is_found_before_the_computation(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    csv = six_pose_csv(tmp_path / "s.csv")
    from fbg_accel_calibration.diagnosis import diagnose
    from fbg_accel_calibration.io import csv_import

    def never(*a, **k):
        raise AssertionError("computation started before the output was checked")

    monkeypatch.setattr(csv_import.CsvBlocks, "blocks", never)
    monkeypatch.setattr(diagnose, "diagnose", never)
    (tmp_path / "file").write_text("x")
    for argv in (["fit", csv, "-o"], ["diagnose", csv, "--yaml"], ["diagnose", csv, "--out"]):
        rc, err = run([*argv, tmp_path / "file" / "r" / "d.md"], capsys)
        assert rc == 2 and "cannot be created (a file is in its path)" in one_line(err)


# every fbg-accel-calib option that names a path, by subcommand: the files it writes, the directories it writes into,
# the files it reads (a new path option must be put in one of them: test_every_output_makes_its_directory_or_...)
FILE_OUTPUTS = {"import": ["--output"], "fit": ["--output"], "allan": ["--output", "--json"],
                "field-check": ["--output"], "report-measured": ["--md", "--png"], "uncertainty-measured": ["--md"],
                "dynamic": ["--output", "--bode", "--json"], "diagnose": ["--out", "--yaml"],
                "adc-codes": ["--plot", "--json", "--output"]}
DIRECTORY_OUTPUTS = {"report": ["--output-dir"], "diagnose": ["--img-dir"]}
PATH_INPUTS = {"fit": ["--adc-codes", "--run-to-run-from"], "allan": ["--calibration"],
               "field-check": ["--calibration"], "report": ["--calibration"], "report-measured": ["--csv"],
               "uncertainty-measured": ["--csv"], "dynamic": ["--plan", "--calibration"], "diagnose": ["--adc-codes"]}


def _path_options() -> dict[str, set[str]]:
    """Subcommand -> its options of type Path (their long names), from the parser itself."""
    import argparse

    from fbg_accel_calibration.commands.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return {name: {max(a.option_strings, key=len) for a in p._actions if a.option_strings and a.type is Path}
            for name, p in sub.choices.items()}


def test_every_output_makes_its_directory_or_is_refused_before_the_computation(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """One rule for every output of every subcommand: a missing directory is made when the outputs are written (as
    the report's always was), and one that cannot be made (a file in its path) is refused before any input is read,
    in one line, exit 2, nothing created. `diagnose --out X/r.md --yaml X/c.yaml` made X for the report and refused
    it for the YAML ("create it first")."""
    found = _path_options()
    for name, options in found.items():
        said = [*FILE_OUTPUTS.get(name, []), *DIRECTORY_OUTPUTS.get(name, []), *PATH_INPUTS.get(name, [])]
        assert options == set(said), (name, options, said)  # each path option is an output or an input
    data = six_pose_csv(tmp_path / "s.csv")
    needs = {"import": [data], "fit": [data], "allan": [data, "--calibration", data],
             "field-check": [data, "--calibration", data], "report-measured": ["--csv", data],
             "uncertainty-measured": ["--csv", data], "dynamic": [data, "--plan", data, "--calibration", data],
             "diagnose": [data], "adc-codes": [data], "report": [data, "--calibration", data]}
    (tmp_path / "file").write_text("x")
    blocked = tmp_path / "file" / "d"
    for name, options in [*FILE_OUTPUTS.items(), *DIRECTORY_OUTPUTS.items()]:
        for option in options:
            rest = list(needs[name])
            if name == "dynamic" and option != "--output":  # its calibration output is required
                rest += ["-o", tmp_path / "o.yaml"]
            if name == "report-measured":  # both outputs have defaults in the repository: the other one here
                rest += ["--png" if option == "--md" else "--md", tmp_path / "other.x"]
            if option == "--img-dir":
                rest += ["--out", tmp_path / "r.md"]
            rc, err = run([name, *rest, option, blocked / "f.x"], capsys)
            assert rc == 2 and "cannot be created (a file is in its path)" in one_line(err), (name, option, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "s.csv"]  # nothing written, nothing half-written
    # made when written: the YAML's directory as the report's, and a failed run takes away what it made
    out = tmp_path / "new" / "deeper"
    rc, err = run(["fit", data, "-o", out / "c.yaml"], capsys)
    assert rc == 0 and (out / "c.yaml").is_file(), err
    bad = six_pose_csv(tmp_path / "bad.csv", "9.99,880,abc,1,1,0,0,9.8,23.4,5", at=-1)
    rc, err = run(["import", bad, "-o", tmp_path / "gone" / "deeper" / "x.mcap"], capsys)
    assert rc == 2 and "malformed" in one_line(err) and not (tmp_path / "gone").exists()


def test_fit_writes_through_a_temporary_file(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The YAML appears only complete: a failure while saving leaves the old file and no temporary."""
    from fbg_accel_driver.thermal_model import ThermalCalibration

    csv = six_pose_csv(tmp_path / "s.csv")
    out = tmp_path / "c.yaml"
    assert run(["fit", csv, "-o", out], capsys)[0] == 0
    good = out.read_bytes()

    def half_then_fail(self, path):
        Path(path).write_text("format: fbg_accel")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ThermalCalibration, "save", half_then_fail)
    rc, err = run(["fit", csv, "-o", out, "--force"], capsys)
    assert rc == 2 and "No space left" in err
    assert out.read_bytes() == good and not leftovers(tmp_path)


def test_atomic_path_keeps_the_suffix_and_cleans_up(tmp_path: Path) -> None:
    target = tmp_path / "plot.png"
    with atomic_output.atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".png" and tmp != target
        tmp.write_bytes(b"png")
    assert target.read_bytes() == b"png"
    with pytest.raises(RuntimeError), atomic_output.atomic_path(target) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("boom")
    assert target.read_bytes() == b"png" and not leftovers(tmp_path)


def test_exclusive_create_refuses_a_dangling_symlink(tmp_path: Path) -> None:
    """The calibration node's recording: a dangling link in output_dir was followed and written outside it."""
    outside = tmp_path / "outside"
    outside.mkdir()
    out_dir = tmp_path / "runs"
    out_dir.mkdir()
    link = out_dir / "run.mcap"
    link.symlink_to(outside / "victim.mcap")  # dangling
    with pytest.raises(FileExistsError):
        atomic_output.create_exclusive(link)
    with pytest.raises(FileExistsError):
        RecordingWriter(link, {"sensor_id": "x"}, exclusive=True)
    assert not (outside / "victim.mcap").exists() and link.is_symlink()
    existing = out_dir / "old.mcap"
    existing.write_bytes(b"precious")
    with pytest.raises(FileExistsError):
        RecordingWriter(existing, exclusive=True)
    assert existing.read_bytes() == b"precious"
    with RecordingWriter(out_dir / "new.mcap", {"sensor_id": "x"}, exclusive=True) as w:
        w.write_raw(1_000_000, 880.0, [1.0, 2.0, 3.0], temperature_c=23.0, seq=0)
    assert len(read_recording(out_dir / "new.mcap")) == 1
    assert os.stat(out_dir / "new.mcap").st_size > 0


def test_an_existing_candidate_plot_of_diagnose_needs_force(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """diagnose writes a plot per candidate effect (candidate_<effect>.png) beside the two fixed ones; only the
    fixed ones were checked, so an earlier run's candidate plots were replaced without --force."""
    csv = six_pose_csv(tmp_path / "s.csv")
    img = tmp_path / "img"
    img.mkdir()
    plot = img / "candidate_time_drift.png"
    plot.write_bytes(b"precious")
    rc, err = run(["diagnose", csv, "--out", tmp_path / "d.md", "--img-dir", img], capsys)
    assert rc == 2 and "candidate_time_drift.png: exists; give --force" in err and plot.read_bytes() == b"precious"
    assert not (tmp_path / "d.md").exists()


@pytest.mark.parametrize("option", [["--img-dir", "img"], ["--figures", "all"], ["--figures", "report"]])
def test_a_figure_option_without_a_report_is_refused(option: list[str], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """The figures belong to the markdown report (--out): given without it, --img-dir or --figures used to be ignored
    without a word, the user left looking for figures that were never drawn."""
    csv = six_pose_csv(tmp_path / "s.csv")
    value = str(tmp_path / option[1]) if option[0] == "--img-dir" else option[1]
    rc, err = run(["diagnose", csv, option[0], value, "--yaml", tmp_path / "c.yaml"], capsys)
    assert rc == 2 and option[0] in err and "--out" in err and one_line(err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv"]


def test_a_rerun_of_diagnose_leaves_only_the_figures_its_report_shows(tmp_path: Path) -> None:
    """`diagnose --force` after a `--figures all` run left the earlier candidate_*.png beside a report that does not
    link them. A re-run removes the figures a diagnosis wrote that its report does not show, and no other file: the
    user's own (a PNG, a file under one of a figure's names that the tool did not write) stay. (One diagnosis, its
    outputs written as the command writes them, with each --figures.)"""
    import argparse
    import re

    from fbg_accel_calibration.commands.diagnose_cli import register, write_outputs
    from fbg_accel_calibration.diagnosis.diagnose import diagnose
    from fbg_accel_calibration.diagnosis.library import LIBRARY
    from fbg_accel_calibration.io.input_files import load_recording

    csv = six_pose_csv(tmp_path / "s.csv")
    res = diagnose(load_recording([csv]), static="table")
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    md, img = tmp_path / "d.md", tmp_path / "img"
    img.mkdir()
    own = {img / "holiday.png": b"\x89PNG\r\n\x1a\n the user's", img / "notes.txt": b"the user's"}
    for path, data in own.items():
        path.write_bytes(data)
    drawn: set[str] = set()
    for figures in ("all", "report", "none"):
        write_outputs(res, parser.parse_args(["diagnose", str(csv), "--out", str(md), "--figures", figures, "--force"]),
                      "")
        shown = set(re.findall(r"img/([\w.]+\.png)", md.read_text()))
        assert {p.name for p in img.iterdir()} == shown | {p.name for p in own}, figures
        assert {p: p.read_bytes() for p in own} == own
        if figures == "all":
            drawn = {n for n in shown if n.startswith("candidate_")}
            assert len(drawn) >= 3, drawn
            spare = img / next(f"candidate_{e.name}.png" for e in LIBRARY if f"candidate_{e.name}.png" not in drawn)
            own[spare] = b"\x89PNG\r\n\x1a\n the user's, under a figure's name"
            spare.write_bytes(own[spare])
        else:
            assert bool(shown) == (figures == "report") and drawn - shown  # earlier figures this report does not show


# ---------------------------------------------------------------------------- issue 42: one commit for all writers
def test_the_outputs_of_one_run_are_committed_together_or_not_at_all(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A failure or Ctrl-C between two renames puts back the output already replaced (diagnose replaced 10 PNGs
    and then said "no output written" beside a stale report)."""
    a, b = tmp_path / "a.png", tmp_path / "b.md"
    a.write_bytes(b"old a")
    real_replace = os.replace
    for failure in (OSError(28, "No space left on device"), KeyboardInterrupt()):
        calls = {"n": 0}

        def second_fails(src, dst, _failure=failure, _calls=calls):
            _calls["n"] += 1
            if _calls["n"] == 2:
                raise _failure
            return real_replace(src, dst)

        monkeypatch.setattr(atomic_output.os, "replace", second_fails)
        with pytest.raises(type(failure)), atomic_output.committed_outputs() as outs:
            outs.path(a).write_bytes(b"new a")
            outs.path(b).write_bytes(b"new b")
        monkeypatch.setattr(atomic_output.os, "replace", real_replace)
        assert a.read_bytes() == b"old a" and not b.exists() and calls["n"] >= 2
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]  # no temporary, no backup left
    with atomic_output.committed_outputs() as outs:
        outs.path(a).write_bytes(b"new a")
        outs.path(b).write_bytes(b"new b")
    assert a.read_bytes() == b"new a" and b.read_bytes() == b"new b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.md"]


def test_diagnose_interrupted_while_writing_replaces_none_of_its_outputs(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str],
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from fbg_accel_calibration.reports import diagnose_report

    csv = six_pose_csv(tmp_path / "s.csv")
    img = tmp_path / "img"
    img.mkdir()
    old = {img / "before_after.png": b"old plot", tmp_path / "d.md": b"old report", tmp_path / "d.yaml": b"old yaml"}
    for p, data in old.items():
        p.write_bytes(data)

    def interrupted(*a, **k):  # Ctrl-C after the plots were drawn, while the report is written
        raise KeyboardInterrupt

    monkeypatch.setattr(diagnose_report, "markdown", interrupted)
    rc, err = run(["diagnose", csv, "--out", tmp_path / "d.md", "--yaml", tmp_path / "d.yaml", "--force"], capsys)
    assert rc == 130 and "interrupted; no output written" in err
    assert {p: p.read_bytes() for p in old} == old
    assert sorted(p.name for p in img.iterdir()) == ["before_after.png"] and not leftovers(tmp_path)


def test_report_measured_needs_force_to_replace_its_pages(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """report-measured replaced any existing --md/--png without --force."""
    csv = six_pose_csv(tmp_path / "m.csv")
    md, png = tmp_path / "r.md", tmp_path / "r.png"
    md.write_text("precious notes")
    argv = ["report-measured", "--csv", csv, "--md", md, "--png", png]
    rc, err = run(argv, capsys)
    assert rc == 2 and "r.md: exists; give --force" in err and md.read_text() == "precious notes" and not png.exists()
    assert run([*argv, "--force"], capsys)[0] == 0
    assert "report-measured" in md.read_text() and png.stat().st_size > 0 and not leftovers(tmp_path)


def test_a_read_only_directory_is_found_before_the_computation_and_named(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str],
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Found only after the fit, naming the hidden temporary file. /sys takes no new file, even for root."""
    if not Path("/sys").is_dir() or _creatable("/sys"):
        pytest.skip("no read-only directory here")
    from fbg_accel_calibration.io import csv_import

    def never(*a, **k):
        raise AssertionError("computation started before the output was checked")

    monkeypatch.setattr(csv_import.CsvBlocks, "blocks", never)
    csv = six_pose_csv(tmp_path / "s.csv")
    rc, err = run(["fit", csv, "-o", "/sys/c.yaml"], capsys)
    assert rc == 2 and "/sys/c.yaml: cannot write in /sys" in err and ".part" not in err


def _creatable(d: str) -> bool:
    import tempfile

    try:
        fd, name = tempfile.mkstemp(dir=d)
    except OSError:
        return False
    os.close(fd)
    os.unlink(name)
    return True


def test_a_writer_error_names_the_output_not_its_temporary_file(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "c.yaml"
    with pytest.raises(OSError) as info, atomic_output.committed_outputs() as outs:
        tmp = outs.path(out)
        raise OSError(28, "No space left on device", str(tmp))
    assert info.value.filename == str(out) and str(out) in str(info.value) and not leftovers(tmp_path)


# ---------------------------------------------------------------------------- board_sim
def board_sim(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    from fbg_accel_sim.board_sim import main as board_sim_main

    rc = board_sim_main([str(a) for a in argv])
    return rc, capsys.readouterr().err


def test_board_sim_outputs_destroy_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--link onto a file replaced it by a symlink and deleted it at exit; --output, --truth and --config ==
    --output overwrote without asking. Each is refused (exit 2, one line) before the simulation starts."""
    precious = tmp_path / "notes.txt"
    precious.write_text("precious")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("scenario:\n  rate_hz: 100.0\n")
    cases = [(["--link", precious], "--link"), (["--output", precious, "--duration", "0.1"], "exists; give --force"),
             (["--config", cfg, "--output", cfg, "--duration", "0.1"], "output is the input file"),
             (["--config", cfg, "--truth", cfg, "--link", tmp_path / "l"], "output is the input file"),
             (["--output", tmp_path / "o.bin", "--truth", tmp_path / "o.bin", "--duration", "0.1"], "given twice"),
             (["--link", tmp_path], "directory")]
    for argv, message in cases:
        rc, err = board_sim(argv, capsys)
        assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, (argv, err)
    assert precious.read_text() == "precious" and cfg.read_text().startswith("scenario:")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.yaml", "notes.txt"]
    out, truth = tmp_path / "run.bin", tmp_path / "t.npz"
    out.write_bytes(b"old")
    rc, err = board_sim(["--config", cfg, "--output", out, "--truth", truth, "--duration", "0.2", "--force"], capsys)
    assert rc == 0, err
    assert out.stat().st_size > 100 and truth.stat().st_size > 100 and not leftovers(tmp_path)


def test_a_signal_between_a_block_and_its_commit_leaves_no_temporary_file(tmp_path: Path) -> None:
    """A Ctrl-C that lands after a ``committed_outputs`` block's body, inside ``contextlib``'s ``__exit__`` before the
    generator resumes, leaves the generator suspended with its temporary file on disk; the command's interrupt
    handler then removes every such file (``discard_open_outputs``), and nothing is written."""
    manager = atomic_output.committed_outputs()
    outs = manager.__enter__()  # the body ran; its __exit__ (the commit) never will
    tmp = outs.path(tmp_path / "cal.yaml")
    tmp.write_text("partial")
    atomic_output.discard_open_outputs()
    assert list(tmp_path.iterdir()) == []
    atomic_output.discard_open_outputs()  # nothing left to do: no error


def test_an_interrupt_right_after_a_temporary_file_is_created_leaves_nothing(tmp_path: Path, monkeypatch) -> None:
    """SIGINT/SIGTERM blocked in the main thread still reach a process with other threads (a BLAS worker takes the
    signal, the handler then runs in the main thread at once), so the handler may run just after the temporary file
    was created and before it was recorded: the name is recorded first, and nothing stays behind."""
    real_open = os.open

    def open_then_interrupt(path, flags, mode=0o777, *args, **kwargs):
        os.close(real_open(path, flags, mode, *args, **kwargs))
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "open", open_then_interrupt)
    with pytest.raises(KeyboardInterrupt), atomic_output.committed_outputs() as outs:
        outs.path(tmp_path / "cal.yaml")
    monkeypatch.undo()
    atomic_output.discard_open_outputs()
    assert list(tmp_path.iterdir()) == []
