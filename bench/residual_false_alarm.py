"""How often does the diagnosis call clean data "significant unexplained residual"? (its false-alarm rate)

Not a test. Simulates clean calibration campaigns (every named effect of the simulator off: eq. 28 is exact up to the
noise of Table 2, with the reference read noise of the measured board, 1 count rms, unless ``--reference-noise``
says otherwise), diagnoses each, and counts the verdicts the report states: the residual test ("significant
unexplained residual", nominal level ``alpha`` = 1 %, Bonferroni over the axes) and an effect added. A consistent
test fires on about ``alpha`` of the campaigns; the 95 % binomial interval of the measured rate is printed beside it.

    .venv/bin/python bench/residual_false_alarm.py --seeds 100                     # ~10 min on 2 cores
    .venv/bin/python bench/residual_false_alarm.py --seeds 100 --max-effects 0     # the declared model alone
    .venv/bin/python bench/residual_false_alarm.py --seeds 100 --output /tmp/fa.json

Writes the per-seed verdicts as JSON to ``--output`` (default: a file in the system's temporary folder).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor

import yaml

NAMED = ("reference_dark_offset", "thermal_lag", "spectral_nonlinearity", "time_drift", "channel_delay", "tia_lowpass",
         "thermal_hysteresis", "unmodelled_cable_torque")
# 7 x 6 poses (theta and psi in 60 degree steps), 3 s dwell, 1 s moves: the measured run's table, shortened
GRID = {"scenario.poses.mode": "grid", "scenario.poses.dwell_s": 3.0, "scenario.poses.move_s": 1.0,
        "scenario.poses.grid.theta_step_deg": 60.0, "scenario.poses.grid.psi_step_deg": 60.0}


def one(args: tuple[int, float, int, dict]) -> dict:
    seed, ref_noise, max_effects, extra = args
    from fbg_accel_calibration.diagnose import diagnose
    from fbg_accel_sim.board_physics import simulate_recording
    from fbg_accel_sim.sim_config import SimConfig

    cfg = SimConfig.default().with_overrides({**{f"effects.{k}.scale": 0.0 for k in NAMED}, **GRID, **extra,
                                              "noise.reference_noise_counts": ref_noise})
    res = diagnose(simulate_recording(cfg, seed=seed), max_effects=max_effects, lanes=1)
    return {"seed": seed, "significant": bool(res.structure.significant), "p": [float(v) for v in res.structure.pose_chi2_p],
            "added": [a[0] for a in res.added], "ratio": [float(v) for v in res.structure.ratio]}


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson interval of a binomial rate k / n."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(c - h, 0.0), min(c + h, 1.0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--reference-noise", type=float, default=1.0, help="reference read noise, counts rms")
    ap.add_argument("--max-effects", type=int, default=3)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a simulator setting (YAML value), e.g. noise.bias_instability_mg=[0,0,0]")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--output", default=os.path.join(tempfile.gettempdir(), "residual_false_alarm.json"))
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    extra = {k: yaml.safe_load(v) for k, v in (item.split("=", 1) for item in a.set)}
    jobs = [(s, a.reference_noise, a.max_effects, extra) for s in range(a.first_seed, a.first_seed + a.seeds)]
    with ProcessPoolExecutor(a.workers) as pool:
        rows = list(pool.map(one, jobs))
    n = len(rows)
    k = sum(r["significant"] for r in rows)
    lo, hi = wilson(k, n)
    added = [r for r in rows if r["added"]]
    print(f"{n} clean campaigns (reference read noise {a.reference_noise:g} counts, max_effects {a.max_effects}"
          + "".join(f", {k} = {v}" for k, v in extra.items()) + "), "
          f"{time.perf_counter() - t0:.0f} s")
    print(f"'significant unexplained residual': {k} / {n} = {100 * k / n:.1f} % (95 % interval {100 * lo:.1f}-"
          f"{100 * hi:.1f} %), nominal 1 %")
    print(f"an effect added: {len(added)} / {n}: " + ", ".join(f"seed {r['seed']}: {r['added']}" for r in added))
    with open(a.output, "w", encoding="utf-8") as f:
        json.dump({"argv": sys.argv[1:], "rows": rows}, f, indent=1)
    print(f"per seed: {a.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
