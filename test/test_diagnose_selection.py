"""Pieces of the forward selection (``diagnosis.selection``) on a small synthetic design, without a campaign: why a
candidate is not added is data its words come from, and a term beyond its bound in the selected model is not
claimed."""

from __future__ import annotations

import re
from pathlib import Path

from fbg_accel_calibration.diagnosis.search import CandidateResult, Refusal
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
    assert writes == ["fbg_accel_calibration/diagnosis/search.py:" + writes[0].rsplit(":", 1)[-1]] and reads == [], \
        (writes, reads)
