#!/usr/bin/env python3
"""Are the ADC code-width candidate's estimates those of the whole table of CDFs, bit for bit, and how long do they take?

Not a test (``test/test_adc_code_widths.py`` checks ``expected_hits`` against the whole table on crafted inputs). The
code-width estimate (``adc_codes.code_widths``) counts the samples its fitted model expects at each code; it works
them out from the edges within each sample's reach (``adc_codes.expected_hits``), where it used to evaluate every
sample's CDF at every edge of the codes read. For each campaign below, the candidate's two estimates
(``diagnosis.adc_code_candidate``): the gate (the whole recording's pattern on at most ``GATE_SAMPLES`` samples) and
one fold pair's table (at most ``MAX_WIDTH_SAMPLES`` samples), each made with ``expected_hits`` and with the whole
table (``dense_expected``, the computation before), compared field by field (pattern, its covariance, chi2,
p-value, expected counts, odd codes), with their CPU times:

* the campaigns of ``bench/diagnose_adc_codes_check.py`` (the measured run's 156-pose grid with the board's
  measured noise), the measured width pattern on and off, seeds ``--seeds``;
* the clean campaigns of ``test/test_diagnose_sim.py`` (every named effect off, and one effect on at a time), seed 1.

    .venv/bin/python bench/adc_gate_check.py [--seeds 3] [--output PATH]

Writes adc_gate_check.json to the scratch directory (``bench/output_paths.py``) by default.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "test"))

import output_paths  # noqa: E402
from adc_code_widths_check import campaign  # noqa: E402
from test_diagnose_sim import SCENARIOS, _config  # noqa: E402

from fbg_accel_calibration.diagnosis import adc_code_candidate as cand  # noqa: E402
from fbg_accel_calibration.diagnosis.design import prepare_data  # noqa: E402
from fbg_accel_calibration.fit import adc_codes  # noqa: E402
from fbg_accel_calibration.io.recording import Recording  # noqa: E402
from fbg_accel_driver.adc_code_table import pattern_edges  # noqa: E402
from fbg_accel_sim.board_physics import simulate_recording  # noqa: E402

BLOCK = 4096  # the whole table's block of samples


def dense_expected(self, theta: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """``_WidthModel.expected`` as it was: every sample's CDF at every edge, summed down the codes a block at a time."""
    from scipy.special import ndtr

    vis = self.vis
    w, sigma, dm, slope = self.unpack(theta)
    m = vis.mean0[vis.visit] + dm[vis.visit] + slope[vis.visit] * vis.u
    sg = sigma[vis.visit]
    edges = pattern_edges(w, np.append(codes, codes[-1] + 1))
    out = np.zeros(len(codes))
    for lo in range(0, len(m), BLOCK):
        cdf = ndtr((edges[None, :] - m[lo:lo + BLOCK, None]) / sg[lo:lo + BLOCK, None])
        out += np.diff(cdf, axis=1).sum(axis=0)
    return out


def _fields(w: adc_codes.CodeWidths | None) -> dict | None:
    if w is None:
        return None
    return {"pattern": w.pattern.tolist(), "pattern_sd": w.pattern_sd.tolist(), "chi2": w.chi2, "p_value": w.p_value,
            "sigma": w.sigma_counts, "expected": w.expected.tolist(),
            "odd": [(o.code, o.hits, o.expected, o.p_value) for o in w.odd]}


def _estimates(data, rows_gate: np.ndarray, rows_fold: np.ndarray) -> tuple[dict, dict]:
    out, cpu = {}, {}
    for name, rows in (("gate", rows_gate), ("fold_table", rows_fold)):
        t = time.process_time()
        try:
            res = cand.pooled_widths(data, rows)
            out[name] = _fields(res.pooled) or res.reasons.get("pooled")
        except ValueError as exc:
            out[name] = str(exc)
        cpu[name] = time.process_time() - t
    return out, cpu


def compare(label: str, rec) -> dict:
    """Both computations on one campaign (module docstring)."""
    data = prepare_data(rec)
    rows = cand.width_rows(data)
    rows_gate = cand._thinned(rows, cand.GATE_SAMPLES)
    pair = np.flatnonzero(np.isin(data.group, np.unique(data.group[rows])[::5]))  # a fold pair's visits left out
    rows_fold = rows.copy()
    rows_fold[pair] = False
    rows_fold = cand._thinned(rows_fold)
    now, cpu_now = _estimates(data, rows_gate, rows_fold)
    real = adc_codes._WidthModel.expected
    adc_codes._WidthModel.expected = dense_expected
    try:
        before, cpu_before = _estimates(data, rows_gate, rows_fold)
    finally:
        adc_codes._WidthModel.expected = real
    gate = now["gate"]
    row = {"campaign": label, "samples": len(rec.t_s), "identical": now == before,
           "gate_p": gate["p_value"] if isinstance(gate, dict) else gate,
           "pattern_found": isinstance(gate, dict) and gate["p_value"] < 0.01,
           "cpu_s_before": cpu_before, "cpu_s_now": cpu_now}
    print(f"{label}: identical {row['identical']}; gate p {row['gate_p']}; CPU gate {cpu_before['gate']:.3f} -> "
          f"{cpu_now['gate']:.3f} s, fold table {cpu_before['fold_table']:.3f} -> {cpu_now['fold_table']:.3f} s",
          flush=True)
    return row


def campaigns(seeds: int) -> Iterator[tuple[str, Recording]]:
    """(label, recording) of each campaign checked: those of ``bench/diagnose_adc_codes_check.py`` for ``seeds`` seeds,
    the measured width pattern on and off, then the clean campaigns of ``test/test_diagnose_sim.py`` (seed 1)."""
    for seed in range(1, seeds + 1):
        for pattern in (True, False):
            yield f"diagnose_adc_codes_check seed {seed} pattern {'on' if pattern else 'off'}", campaign(seed, pattern)
    yield "test_diagnose_sim baseline (every named effect off)", simulate_recording(_config({}), seed=1)
    for effect, (scale, extra, _) in SCENARIOS.items():
        yield (f"test_diagnose_sim {effect}",
               simulate_recording(_config({**extra, f"effects.{effect}.scale": scale}), seed=1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--output", type=Path, default=output_paths.scratch_dir() / "adc_gate_check.json")
    args = ap.parse_args(argv)
    rows = [compare(label, rec) for label, rec in campaigns(args.seeds)]
    same = sum(r["identical"] for r in rows)
    print(f"identical in {same} of {len(rows)} campaigns")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({"rows": rows, "identical": same, "campaigns": len(rows)}, indent=1),
                           encoding="utf-8")
    print(f"wrote {args.output}")
    return 0 if same == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
