#!/usr/bin/env python3
"""Which results of two diagnoses differ, and by how much (not a test).

Compares two files of ``bench/diagnose_fingerprint.py`` (the same run diagnosed by two versions of the code) field by
field: every text (the effects added, each candidate's name and plausibility verdict, each confounding verdict) must be
the same; every number that differs is listed with its relative change |b - a| / |a| (its absolute change where a is
0), largest first, and each kind of number (hyper-parameters, gains, p-values, M, b, held-out RMSE) gets its largest
change. A change that is exact (the same values bit for bit) lists nothing: ``cmp`` of the two files says the same.
Where the algebra changed (a recursion in closed form), this says by how much the diagnosis' numbers moved:

    .venv/bin/python bench/fingerprint_compare.py before.json after.json [--show 15]

Exit status 1 when a text (a verdict, an effect added, a candidate's order) differs, else 0.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

CANDIDATE_FIELDS = ("name", "rel_gain", "p_value", "hyper", "implausible")
CONFOUNDING_FIELDS = ("a", "b", "verdict", "gain_b_beyond_a", "p_b_beyond_a", "gain_a_beyond_b", "p_a_beyond_b",
                      "corr_contributions")


def _kind(path: list[str]) -> str:
    """The kind of number at ``path`` (keys and list positions of the fingerprint)."""
    if path[0] == "steps" and len(path) >= 5 and path[2] == "candidates":  # steps/i/candidates/j/field
        return "candidate " + CANDIDATE_FIELDS[int(path[4])]
    if path[0] == "steps" and len(path) >= 5 and path[2] == "confounding":
        return "confounding " + CONFOUNDING_FIELDS[min(int(path[4]), len(CONFOUNDING_FIELDS) - 1)]
    if path[0] == "added":
        return "added hyper-parameter"
    return path[0]


def _number(v: Any) -> float | None:
    if isinstance(v, bool) or v is None:
        return None
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def compare(a: Any, b: Any, path: list[str], numbers: list[tuple[float, str, str, Any, Any]],
            texts: list[tuple[str, Any, Any]]) -> None:
    """Walk both documents: differing numbers into ``numbers`` (change, kind, path, a, b), other differences into
    ``texts``."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                texts.append(("/".join([*path, k]), a.get(k), b.get(k)))
            else:
                compare(a[k], b[k], [*path, k], numbers, texts)
        return
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            texts.append(("/".join(path) + " (length)", len(a), len(b)))
            return
        for i, (u, v) in enumerate(zip(a, b, strict=True)):
            compare(u, v, [*path, str(i)], numbers, texts)
        return
    if a == b:
        return
    fa, fb = _number(a), _number(b)
    if fa is None or fb is None or (isinstance(a, str) and isinstance(b, str) and fa is None):
        texts.append(("/".join(path), a, b))
        return
    change = abs(fb - fa) / abs(fa) if fa != 0 else abs(fb - fa)
    numbers.append((change, _kind(path), "/".join(path), a, b))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--show", type=int, default=15, help="the largest changes listed (default 15)")
    args = ap.parse_args(argv)
    before, after = (json.loads(p.read_text()) for p in (args.before, args.after))
    numbers: list[tuple[float, str, str, Any, Any]] = []
    texts: list[tuple[str, Any, Any]] = []
    compare(before, after, [], numbers, texts)
    print(f"{args.before} -> {args.after}: {len(texts)} texts differ, {len(numbers)} numbers differ")
    for path, a, b in texts:
        print(f"  TEXT {path}: {a!r} -> {b!r}")
    largest: dict[str, float] = {}
    for change, kind, *_ in numbers:
        largest[kind] = max(largest.get(kind, 0.0), change)
    if largest:
        print("| kind | numbers changed | largest change (relative; absolute from 0) |")
        print("|---|---|---|")
        for kind in sorted(largest, key=lambda k: -largest[k]):
            print(f"| {kind} | {sum(1 for n in numbers if n[1] == kind)} | {largest[kind]:.2g} |")
    for change, _, path, a, b in sorted(numbers, reverse=True)[:args.show]:
        print(f"  {change:.2g}  {path}: {a} -> {b}")
    return 1 if texts else 0


if __name__ == "__main__":
    sys.exit(main())
