"""The paper's measured multi-position series (../shared/data/measured): import, static detection, linear fit.

Needs the team's shared directory next to the repository; fails with a clear message if it is absent.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fbg_accel_calibration.commands.cli import main as cli_main
from fbg_accel_calibration.reports.measured_report import PAPER_B_ABS, PAPER_M, fit_measured

CSV = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "measured" / "fig13_multiposition_23C.csv"


@pytest.fixture(scope="module")
def measured():
    if not CSV.is_file():
        pytest.fail(f"measured data missing: {CSV} (the shared data directory ../shared is not next to the repository)")
    return fit_measured(CSV)


def test_static_detector_excludes_the_moving_samples(measured) -> None:
    rec, usable = measured.rec, measured.usable
    assert len(rec) == 1560
    assert 1000 <= usable.sum() <= 1400
    # samples taken while the table moved have intermediate angles (README); every one the detector kept
    # must have the same reference as both neighbours (turning psi about the vertical changes nothing)
    raw = np.genfromtxt(CSV, delimiter=",", names=True)
    inter = (np.mod(raw["psi_deg"], 30.0) != 0) | (np.mod(raw["theta_deg"], 30.0) != 0)
    assert inter.sum() == measured.n_intermediate == 163
    for i in np.flatnonzero(inter & usable):
        np.testing.assert_allclose(rec.gref_mps2[i - 1:i + 2], np.repeat(rec.gref_mps2[i][None], 3, 0), atol=1e-9)
    assert (inter & ~usable).sum() >= 150


def test_linear_fit_matches_the_published_values(measured) -> None:
    P = measured.perm
    M, b = P @ measured.M, P @ measured.b
    assert np.allclose(np.abs(P).sum(axis=0), 1) and np.allclose(np.abs(P).sum(axis=1), 1)  # a signed permutation
    np.testing.assert_allclose(np.abs(M), PAPER_M, atol=0.6)  # published to 0.01; signs partly lost in the paper
    np.testing.assert_allclose(np.abs(b), PAPER_B_ABS, atol=1.5)
    assert measured.selection.chosen_degree == 0
    assert not any(s.identified for s in measured.selection.scores if s.degree >= 1)


def test_rmse_against_noise_floor(measured) -> None:
    rin, rout, floor = measured.rmse_in, measured.rmse_held_out, measured.noise_floor
    assert np.all(rout >= rin) and np.all(rout < 1.2 * rin)  # held out is a little worse, not much
    assert np.all(rin >= floor)  # a fit cannot beat the within-pose scatter
    assert np.all(rin / 196.133 < 5e-3)  # order of the paper's Table 4 figures (1e-3 of the 20 g full scale)
    assert np.all((floor > 0.1) & (floor < 0.5))


def test_report_measured_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    if not CSV.is_file():
        pytest.fail(f"measured data missing: {CSV}")
    md, png = tmp_path / "r.md", tmp_path / "img" / "m.png"
    assert cli_main(["report-measured", "--csv", str(CSV), "--md", str(md), "--png", str(png)]) == 0
    text = md.read_text()
    assert "held-out RMSE" in text and "81.60" in text and "![" in text
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert cli_main(["report-measured", "--csv", str(tmp_path / "nope.csv"), "--md", str(md), "--png", str(png),
                     "--force"]) == 2
    err = capsys.readouterr().err
    assert "measured data not found" in err and "nope.csv" in err


def test_report_measured_is_atomic_and_never_writes_over_its_input(tmp_path: Path, monkeypatch,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """An interrupted report keeps the previous one whole; an output naming the input CSV is refused
    before any work (issue 11)."""
    if not CSV.is_file():
        pytest.fail(f"measured data missing: {CSV}")
    import shutil

    import fbg_accel_calibration.reports.measured_report as mr

    csv = tmp_path / "m.csv"
    shutil.copy(CSV, csv)
    before = csv.read_bytes()
    assert cli_main(["report-measured", "--csv", str(csv), "--md", str(csv), "--png", str(tmp_path / "m.png")]) == 2
    assert "is the input file" in capsys.readouterr().err and csv.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv"]

    md, png = tmp_path / "r.md", tmp_path / "r.png"
    md.write_text("previous report\n")
    png.write_bytes(b"previous png")

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(mr, "report_markdown", interrupted)
    with pytest.raises(KeyboardInterrupt):
        mr.run_report(csv, md, png)
    assert md.read_text() == "previous report\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv", "r.md", "r.png"]  # no temporary left behind


def test_coefficient_uncertainty_of_the_measured_fit(measured) -> None:
    """The by-visit covariance (what a calibration file carries) agrees with the bootstrap over visits, and the
    paper's published matrix lies within two combined standard uncertainties of this fit (measured: |z| <= 1.2)."""
    from fbg_accel_calibration.reports.measured_uncertainty import compare

    c = compare(measured)
    assert c["visits"] == len(measured.stats.pose) and c["bootstrap_draws"] >= 990
    ratio = np.r_[(c["uM_bootstrap"] / c["uM_visit"]).ravel(), c["ub_bootstrap"] / c["ub_visit"]]
    assert np.all((ratio > 0.7) & (ratio < 1.3)), ratio  # measured 0.84-1.0
    assert np.all(np.abs(np.r_[c["zM_visit"].ravel(), c["zb_visit"]]) < 2.0)
    assert np.all(c["u_output"] < 0.3) and np.all(c["ub_visit"] > 2 * c["u_output"])  # correlated entries


def test_uncertainty_measured_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    if not CSV.is_file():
        pytest.fail(f"measured data missing: {CSV}")
    md = tmp_path / "results" / "u.md"
    assert cli_main(["uncertainty-measured", "--csv", str(CSV), "--md", str(md)]) == 0
    text = md.read_text()
    assert "u by visit" in text and "81.60" in text and "12 of 12" in text
    assert cli_main(["uncertainty-measured", "--csv", str(tmp_path / "nope.csv"), "--md", str(md), "--force"]) == 2
    assert "measured data not found" in capsys.readouterr().err
    md.write_text("kept")  # an existing page is replaced only with --force
    assert cli_main(["uncertainty-measured", "--csv", str(CSV), "--md", str(md)]) == 2 and md.read_text() == "kept"
    assert "--force" in capsys.readouterr().err
    assert cli_main(["uncertainty-measured", "--csv", str(CSV), "--md", str(CSV)]) == 2  # never over its input
    assert CSV.is_file()
