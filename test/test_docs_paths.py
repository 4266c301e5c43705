"""Every repository file the README and docs/*.md name in backticks exists.

A moved or renamed module leaves its old path in the docs (docs/simulator.md listed the simulator's modules as
``sim/*.py`` after they had moved to ``fbg_accel_sim/``). Paths are taken relative to the repository root or the
doc's own directory; ``../shared/...`` (outside the repository) and patterns (``*``) are not checked. Pure.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = ["README.md", *(str(p.relative_to(REPO)) for p in sorted([*(REPO / "docs").glob("*.md"),
                                                        *(REPO / "docs" / "results").glob("*.md")]))]
# source, config, script and test files: names of outputs (report.md, *.png) are not repository files
PATH = re.compile(r"`((?:[A-Za-z0-9_.-]+/)+[A-Za-z0-9_.-]+\.(?:py|yaml|sh|c|h|ino|toml|cfg|xml))`")


@pytest.mark.parametrize("doc", DOCS)
def test_every_named_repository_file_exists(doc: str) -> None:
    text = (REPO / doc).read_text(encoding="utf-8")
    missing = []
    for m in PATH.finditer(text):
        name = m.group(1)
        if name.startswith("../") or "*" in name:
            continue
        if not ((REPO / name).exists() or (REPO / doc).parent.joinpath(name).exists()):
            missing.append(f"{doc}:{text.count(chr(10), 0, m.start()) + 1}: {name}")
    assert not missing, "named in the docs but not in the repository:\n" + "\n".join(missing)


def _test_functions() -> dict[str, set[str]]:
    """test function name -> the test files defining it."""
    out: dict[str, set[str]] = {}
    for f in (REPO / "test").glob("*.py"):
        for m in re.finditer(r"^\s*def (test_\w+)", f.read_text(encoding="utf-8"), re.M):
            out.setdefault(m.group(1), set()).add(f.name)
    return out


@pytest.mark.parametrize("doc", DOCS)
def test_every_named_test_exists(doc: str) -> None:
    """The docs cite tests as evidence (``test_x.py::test_name``, ``test_name``, ``test_x.py``); a renamed or
    removed test would leave the claim without its evidence."""
    text = (REPO / doc).read_text(encoding="utf-8")
    defs = _test_functions()
    files = {f.name for f in (REPO / "test").glob("*.py")}
    missing = [f"{f}::{n}" for f, n in re.findall(r"(test_\w+\.py)::(test_\w+)", text) if f not in defs.get(n, set())]
    missing += [n for n in re.findall(r"`(test_\w+)`", text) if n not in defs]
    missing += [f for f in re.findall(r"\b(test_\w+\.py)\b", text) if f not in files]
    assert not missing, f"{doc} cites tests that do not exist: {sorted(set(missing))}"
