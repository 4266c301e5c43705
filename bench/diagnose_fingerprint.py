#!/usr/bin/env python3
"""Every result of one diagnosis at full precision, to check that a speed-up changed none of them.

Not a test. Diagnoses the calibration benchmark's simulated run (``bench_calibration.scenario``, ``--seed``, 0) of
``--samples`` samples and writes, as JSON with every float at full precision (``repr``): the effects added
with their hyper-parameters, each step's candidates (held-out gain, p-value, hyper-parameter, plausibility
verdict) and confounding verdicts (gains and p-values both ways, correlation), the held-out error, the
calibration (M, b), the final residual's structure (its test's verdict and p-values) and the findings' texts. Run it
before and after a change and compare the two files byte for byte (``cmp``); with ``--lanes 1`` and ``--lanes 2``,
the diagnosis with its searches one after the other and side by side:

    .venv/bin/python bench/diagnose_fingerprint.py --samples 100000 --output before.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_calibration import scenario  # noqa: E402

from fbg_accel_calibration.diagnosis.diagnose import diagnose  # noqa: E402
from fbg_accel_sim.board_physics import simulate_recording  # noqa: E402


def exact(value: Any) -> Any:
    """``value`` with every float as its repr (JSON would round-trip them too, but repr says so)."""
    if isinstance(value, np.ndarray):
        return exact(value.tolist())
    if isinstance(value, (list, tuple)):
        return [exact(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, np.integer):
        return int(value)
    return value


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--output", type=Path, required=True)
    ap.add_argument("--lanes", type=int, default=None, help="searches side by side (default: diagnose's own choice)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the simulated run (default 0)")
    args = ap.parse_args(argv)
    cfg, duration = scenario(args.samples)
    res = diagnose(simulate_recording(cfg, seed=args.seed, duration_s=duration), lanes=args.lanes)
    doc = {
        "samples": args.samples,
        "added": exact(res.added),
        "steps": [{"chosen": st.chosen,
                   "candidates": [exact([c.name, c.rel_gain, c.p_value, c.hyper, c.implausible])
                                  for c in st.candidates],
                   "confounding": [exact([c.a, c.b, c.verdict, c.gain_b_beyond_a, c.p_b_beyond_a, c.gain_a_beyond_b,
                                          c.p_a_beyond_b, c.corr_contributions]) for c in st.confounding]}
                  for st in res.steps],
        "heldout_rmse_after_mps2": exact(res.after_heldout_rmse),
        "structure": exact([res.structure.significant, res.structure.verdict, res.structure.pose_chi2_p,
                             res.structure.direction_chi2_p, res.structure.pose_mean_rms, res.structure.excess_rms]),
        "findings": [f.text for f in res.findings],
        "M": exact(res.calibration.M),
        "b": exact(res.calibration.b),
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"added {[a[0] for a in res.added]}; written to {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
