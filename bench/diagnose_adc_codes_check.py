"""Does the diagnosis name the ADC's code widths when the simulator injects them, and claim nothing when it does not?

Not a test (test/test_diagnose_adc_code_widths.py asserts the candidate's decision with fewer seeds and margin). For
each seed, the campaign of bench/adc_code_widths_check.py (the measured run's 156-pose grid with the board's measured
noise), once with ``effects.adc_code_widths`` on (the measured pattern) and once off, same seed; ``diagnose`` on each:

* ``named``: the candidate ``adc_code_widths`` added (``fbg_accel_calibration.diagnosis.adc_code_candidate``), its held-out gain
  and p-value (each fold's table estimated from its training visits only);
* ``claimed_without``: the candidate added on the campaign without the pattern (it should not be);
* what else the diagnosis added on each.

    .venv/bin/python bench/diagnose_adc_codes_check.py [--seeds 10] [--output PATH] [--update-results]

Writes diagnose_adc_codes_check.json to the scratch directory (bench/output_paths.py) by default;
``--update-results``: bench/results/diagnose_adc_codes_check.json. About a minute per seed on one core.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import output_paths
from adc_code_widths_check import NOISE_SCALE, campaign

from fbg_accel_calibration.diagnosis.adc_code_candidate import NAME
from fbg_accel_calibration.diagnosis.diagnose import diagnose

RESULTS = output_paths.COMMITTED / "diagnose_adc_codes_check.json"


def check(seed: int, pattern: bool) -> dict:
    """One campaign's verdict on the candidate."""
    res = diagnose(campaign(seed, pattern))
    c = next(c for st in res.steps for c in st.candidates if c.name == NAME)
    return {"seed": seed, "pattern": pattern, "named": c.significant, "applicable": c.applicable,
            "gain": c.rel_gain, "p_value": c.p_value, "level": res.steps[-1].alpha_each,
            "added": [a[0] for a in [*res.added, *res.noise_remedies, *res.run_terms]], "detail": c.detail or c.reason}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--output", type=Path, default=output_paths.scratch_dir() / "diagnose_adc_codes_check.json")
    ap.add_argument("--update-results", action="store_true", help=f"write {RESULTS}")
    args = ap.parse_args(argv)
    runs = []
    for seed in range(1, args.seeds + 1):
        for pattern in (True, False):
            runs.append(r := check(seed, pattern))
            print(f"seed {seed} pattern {'on ' if pattern else 'off'}: named {r['named']}, gain {100 * r['gain']:+.1f} %, "
                  f"p {r['p_value']:.2g} (level {r['level']:.2g}); added {', '.join(r['added']) or 'nothing'}", flush=True)
    on = [r for r in runs if r["pattern"]]
    off = [r for r in runs if not r["pattern"]]
    out = {"noise_scale": NOISE_SCALE, "runs": runs, "named_with": sum(r["named"] for r in on),
           "claimed_without": sum(r["named"] for r in off), "seeds": args.seeds}
    print(f"named with the pattern in {out['named_with']} of {len(on)} seeds; claimed without it in "
          f"{out['claimed_without']} of {len(off)}")
    path = RESULTS if args.update_results else args.output
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1), encoding="utf-8")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
