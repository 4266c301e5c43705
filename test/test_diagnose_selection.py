"""Pieces of the forward selection (``diagnosis.selection``) on a small synthetic design, without a campaign: why a
candidate is not added is data its words come from, and a term beyond its bound in the selected model is not
claimed."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from fbg_accel_calibration.diagnosis.cv import check_folds, make_folds
from fbg_accel_calibration.diagnosis.data import DiagnosisData
from fbg_accel_calibration.diagnosis.design import ModelSpec
from fbg_accel_calibration.diagnosis.effects import MAX_CHANNEL_OFFSET_FRACTION, ReferenceDarkOffsetEffect
from fbg_accel_calibration.diagnosis.search import CandidateResult, Evaluator, Refusal
from fbg_accel_calibration.diagnosis.selection import beyond_bound_at_the_end
from fbg_accel_calibration.reports.diagnose_report import candidate_rows

ROOT = Path(__file__).resolve().parents[1]


def test_why_a_candidate_is_not_added_is_data_and_its_words_come_from_it() -> None:
    """The check that refused a candidate and its reason are fields of the result; the report's row says them."""
    r = CandidateResult("time_drift", "warm-up", True, detail="a = 1", rel_gain=0.2, p_value=1e-6, significant=True)
    r.refuse(Refusal.TIME_BLOCKS, "it does not predict contiguous blocks of time held out")
    assert not r.significant and r.refusal is Refusal.TIME_BLOCKS
    assert r.refusal_why == "it does not predict contiguous blocks of time held out"
    assert candidate_rows([r])[0][-1] == "a = 1; not added: it does not predict contiguous blocks of time held out"


def test_no_code_reads_why_a_candidate_was_refused_back_from_its_words() -> None:
    """Text and logic apart: the words "not added" are written in one place (``CandidateResult.refuse``, from its
    data), and no module of the package or of bench/ takes a candidate's ``detail`` apart (split, search, prefix) to
    find out what happened: that is read from the result's fields (``refusal``, ``implausible``)."""
    writes, reads = [], []
    for path in [*sorted((ROOT / "fbg_accel_calibration").rglob("*.py")), *sorted((ROOT / "bench").glob("*.py"))]:
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            where = f"{path.relative_to(ROOT)}:{i}"
            if re.search(r"[\"']; not added: ", line):
                writes.append(where)
            if re.search(r"detail\b[^=#]*\)?\.(r?split|r?partition|find|r?index|startswith|endswith)\(", line) \
                    or re.search(r"\bin \(?\w+(\.\w+)*\.detail\b", line):
                reads.append(where)
    assert [w.rsplit(":", 1)[0] for w in writes] == ["fbg_accel_calibration/diagnosis/search.py"] and reads == [], \
        (writes, reads)


def dark_offset_data(offset_fraction: float, seed: int = 3) -> DiagnosisData:
    """36 visits of one temperature level, each at its own orientation and its own source power (the reference's
    counts 2100-3900), the axis channels offset by ``offset_fraction`` of their mean counts (a dark offset that is a
    fraction of the signal)."""
    rng = np.random.default_rng(seed)
    g, pose, refs = [], [], []
    for v in range(36):
        u = rng.normal(size=3)
        u *= 9.80665 / np.linalg.norm(u)
        g.append(np.tile(u, (45, 1)))
        pose.append(np.r_[np.full(5, -1), np.full(40, v)])  # 5 samples of the table's move, 40 held
        refs.append(np.full(45, 3000.0 * (1 + 0.3 * rng.uniform(-1, 1))))
    gref, pose_id = np.concatenate(g), np.concatenate(pose)
    n = len(gref)
    ref = np.concatenate(refs) + rng.normal(0, 1, n)
    psi = gref @ np.array([[2e-3, 1e-4, 0.0], [0.0, 2.1e-3, 2e-4], [1e-4, 0.0, 1.9e-3]]).T + 0.5
    use = pose_id >= 0
    xyz = psi * ref[:, None] + offset_fraction * np.abs(psi[use] * 3000.0).mean(axis=0) + rng.normal(0, 0.3, (n, 3))
    return DiagnosisData(0.01 * np.arange(n), ref, xyz, np.full(n, 25.0), np.where(use[:, None], gref, np.nan),
                         pose_id, np.zeros(n, int), use, gref_filled=gref)


@pytest.mark.parametrize("offset_fraction", [0.05, 0.5])
def test_a_term_beyond_its_bound_in_the_selected_model_is_not_claimed(offset_fraction: float) -> None:
    """A term let in while its bound was not decided must be within it in the selected model
    (``beyond_bound_at_the_end``): reference dark offsets whose implied axis offsets are about 2.6x their bound
    (25 % of the counts) in the model are taken out of it, with an ``at_bound`` finding that names the measurement
    of their value; offsets at about 0.2x the bound stay, with no finding."""
    data = dark_offset_data(offset_fraction)
    fold = check_folds(data, data.group, make_folds(data.group, data.use, 10, 0))[0]
    ev = Evaluator(data, fold, np.ones(3), data.group, np.flatnonzero(data.use & (fold != -1)))
    eff = ReferenceDarkOffsetEffect()
    spec = ModelSpec(0, 25.0, 1.0, [(eff, 0.0)])
    des, cvr = ev.cv(spec)
    ratio = float(np.max(eff.bound_ratios(0.0, ev.coefficients(eff, des, cvr)[0], data, ev.model_matrix)))
    kept, findings = beyond_bound_at_the_end(ev, spec)
    if offset_fraction < MAX_CHANNEL_OFFSET_FRACTION:
        assert ratio < 0.5 and kept.names == [eff.name] and findings == [], (ratio, findings)
    else:
        assert ratio > 2.0 and kept.names == [] and kept.degree == spec.degree, ratio
        assert [(f.kind, f.effect, f.separates) for f in findings] == [("at_bound", eff.name, eff.measures_its_value)]
        assert "is not claimed: in the selected model implied axis-channel offsets" in findings[0].text


def test_the_constants_kept_for_the_trials_are_let_go_when_the_searches_end_and_made_again_the_same() -> None:
    """``DiagnosisData.once(..., for_trials=True)``: the expected Psi map's constants of the static samples (arrays of
    up to 10^6 samples kept to spare each trial of a search their making) are forgotten by ``drop_recent`` once the
    searches end, not held through the final model; asked for again, they are made again with the same values. The
    recording's other constants are kept."""
    from fbg_accel_calibration.diagnosis.data import Inputs, expected_psi_map

    data = dark_offset_data(0.05)
    P, q = expected_psi_map(data, Inputs.of(data))
    kept = {k: v for k, v in data._memo.items() if k.startswith("static_")}
    assert {"static_with_reference", "static_xyz", "static_design"} <= set(kept)
    runs = data.runs()
    data.drop_recent()
    assert not any(k.startswith("static_") for k in data._memo)
    assert data.runs() is runs  # a constant not kept for the trials alone
    P2, q2 = expected_psi_map(data, Inputs.of(data))
    assert np.array_equal(P, P2) and np.array_equal(q, q2)
    assert np.array_equal(data._memo["static_xyz"], kept["static_xyz"])


def test_a_search_judged_lets_go_of_its_trials() -> None:
    """Once a candidate's search is judged (``Evaluator.evaluate``, ``nested_heldout``), the lane's cache keeps nothing
    of the models with that candidate in (the corrected series of its trial values, their prefixes and design
    matrices: at 10^6 samples each series is tens of MiB, and they stayed beside the next searches' own); the lane
    judges it again the same."""
    from fbg_accel_calibration.diagnosis.effects import ReferenceReadNoiseEffect

    data = dark_offset_data(0.05)
    fold = check_folds(data, data.group, make_folds(data.group, data.use, 10, 0))[0]
    ev = Evaluator(data, fold, np.ones(3), data.group, np.flatnonzero(data.use & (fold != -1)))
    for base, eff in ((ModelSpec(0, 25.0, 1.0, [(ReferenceDarkOffsetEffect(), 30.0)]), ReferenceReadNoiseEffect()),
                      (ModelSpec(0, 25.0, 1.0, []), ReferenceDarkOffsetEffect())):
        des, cvr = ev.cv(base)
        judged = []
        for _ in range(2):
            r = ev.evaluate(base, eff, cvr.heldout, cvr.fitted_full, des.G)
            assert r.hyper is not None and not _named(ev, eff.name)
            assert not ev.designs._taken  # nor the arrays it took rows of (it holds them)
            held = ev.nested_heldout(base, eff)
            assert not _named(ev, eff.name)
            judged.append((r.hyper, r.rel_gain, r.p_value, held))
        (h0, g0, p0, ho0), (h1, g1, p1, ho1) = judged
        assert h0 == h1 and g0 == g1 and p0 == p1 and np.array_equal(ho0, ho1, equal_nan=True)
        ev.cv(base.plus(eff, r.hyper))  # a model with it: kept again
        assert _named(ev, eff.name)


def _named(ev: Evaluator, name: str) -> list:
    """The keys of ``ev``'s own caches (inputs, prefixes, design matrices) of models with the effect ``name``."""
    return [k for c in (ev.designs.inputs, ev.designs.prefixes, ev.designs.matrices) for k in c if name in repr(k)]


def test_a_refined_value_asked_for_again_is_the_search_s_not_a_new_search(monkeypatch) -> None:
    """``Evaluator.hyper_value`` (the backward step's search of the newest term without an earlier one, a search the
    step before made): the value ``fit_hyper`` refined, bit for bit, with no second search, on every lane; a model or an
    effect not searched before is searched."""
    from fbg_accel_calibration.diagnosis.effects import ReferenceReadNoiseEffect

    data = dark_offset_data(0.05)
    fold = check_folds(data, data.group, make_folds(data.group, data.use, 10, 0))[0]
    ev = Evaluator(data, fold, np.ones(3), data.group, np.flatnonzero(data.use & (fold != -1)))
    noise, dark = ReferenceReadNoiseEffect(), ReferenceDarkOffsetEffect()
    base = ModelSpec(0, 25.0, 1.0, [])
    searched: list[tuple] = []
    real = Evaluator._grid_search

    def spy(self, spec, eff):
        searched.append((spec.key, eff.name))
        return real(self, spec, eff)

    monkeypatch.setattr(Evaluator, "_grid_search", spy)
    h = ev.fit_hyper(base, noise)[0]
    assert searched == [(base.key, noise.name)]
    for lane in (ev, ev.lane()):
        got = lane.hyper_value(base, noise)
        assert np.float64(got).tobytes() == np.float64(h).tobytes() and len(searched) == 1
    other = base.plus(dark, 30.0)
    assert ev.hyper_value(other, noise) == ev.fit_hyper(other, noise)[0] and searched[1:] == [(other.key, noise.name)] * 2
