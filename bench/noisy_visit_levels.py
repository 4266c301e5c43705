"""What sets a visit's noise variance on clean simulated campaigns (not a test): the declared model's residual of
each visit against what the noisy-visit check judges it by (``floor.noisy_visits``).

For each seed, the clean campaign (as ``residual_false_alarm.py`` makes it: every named effect off, the measured
board's reference read noise) gets the diagnosis' declared model (eq. 28, its degree by cross-validation) and the
floor's settled samples (``measure_floor``). Each visit's detrended variance over what its reference level alone makes
it (1 / r^2, column 0 of ``floor.visit_noise_levels``) is printed by the specific force along each axis (bins of the
reference's component, m/s^2), with the correlation of the three axes' variances of one visit; then the rate of
p < q over q of the check's per-visit p-values, with its levels from the reference alone and from the reference and
the ratios (what it uses). A calibrated check gives 1; at ~1e-5 (the ramps' Bonferroni level) a few tens of seeds
hold only a few events.

    nice -n 19 .venv/bin/python bench/noisy_visit_levels.py --seeds 40 --campaign ramps   # ~3 min on 2 cores
"""

from __future__ import annotations

import argparse
import os
from concurrent.futures import ProcessPoolExecutor

import numpy as np
from residual_false_alarm import CAMPAIGNS, GRID, NAMED

QS = (1e-1, 1e-2, 1e-3, 1e-4, 1e-5)
BINS = (-7.0, -3.0, 3.0, 7.0)  # m/s^2: about -1 g, -0.5 g, 0, +0.5 g, +1 g along an axis


def one(args: tuple[int, dict]) -> dict:
    seed, extra = args
    from fbg_accel_calibration.diagnosis import floor as fl
    from fbg_accel_calibration.diagnosis.cv import cross_validate
    from fbg_accel_calibration.diagnosis.data import finite_rows
    from fbg_accel_calibration.diagnosis.design import build_design, prepare_data
    from fbg_accel_calibration.diagnosis.library import LIBRARY
    from fbg_accel_calibration.diagnosis.selection import declared_model
    from fbg_accel_sim.board_physics import simulate_recording
    from fbg_accel_sim.sim_config import SimConfig

    cfg = SimConfig.default().with_overrides({**{f"effects.{k}.scale": 0.0 for k in NAMED}, **GRID, **extra,
                                              "noise.reference_noise_counts": 1.0})
    data = prepare_data(simulate_recording(cfg, seed=seed))
    spec, _, fold, _ = declared_model(data, LIBRARY, 4, None, 10, 0, False)
    des = build_design(data, spec)
    res0 = des.G - cross_validate(des, data.use, fold, np.ones(3)).fitted_full
    rows = data.use & des.valid & (data.pose_id >= 0)
    floor = fl.measure_floor(data, res0, rows, None, False)
    r = floor.settled & finite_rows(res0)
    idx = np.flatnonzero(r)
    _, inv, _ = fl.visit_index(data.group[idx])
    cnt = np.bincount(inv).astype(float)
    dev = res0[idx] - (np.stack([np.bincount(inv, weights=res0[idx, j]) for j in range(3)], axis=1) / cnt[:, None])[inv]
    t = data.t_s[idx]
    tc = t - (np.bincount(inv, weights=t) / cnt)[inv]
    slope = np.stack([np.bincount(inv, weights=tc * dev[:, j]) for j in range(3)], axis=1) / np.bincount(
        inv, weights=tc * tc)[:, None]
    dev -= slope[inv] * tc[:, None]
    lag0 = np.stack([np.bincount(inv, weights=dev[:, j] ** 2) for j in range(3)], axis=1)
    levels = fl.visit_noise_levels(data.ref[idx], data.xyz[idx], inv, cnt)
    n, line, acf = cnt.astype(int), np.ones(len(cnt), bool), floor.noise_model.acf
    ratio_ref, p_ref = fl.noisy_visits(lag0, n, line, acf, levels[:, :, :1])
    _, p_both = fl.noisy_visits(lag0, n, line, acf, levels)
    g = np.stack([np.bincount(inv, weights=data.gref[idx, j]) for j in range(3)], axis=1) / cnt[:, None]
    return {"seed": seed, "ratio": ratio_ref, "g": g, "p_ref": p_ref, "p_both": p_both}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--campaign", choices=sorted(CAMPAIGNS), default="ramps")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    a = ap.parse_args(argv)
    with ProcessPoolExecutor(a.workers) as pool:
        rows = list(pool.map(one, [(s, CAMPAIGNS[a.campaign]) for s in range(1, a.seeds + 1)]))
    ratio, g = np.concatenate([r["ratio"] for r in rows]), np.concatenate([r["g"] for r in rows])
    print(f"{a.seeds} clean {a.campaign} campaigns, {len(ratio)} visits; variance over what the reference level alone "
          "makes it, mean by the specific force along the axis (m/s^2 bins, visits):")
    edges = ("< -7", "-7..-3", "-3..3", "3..7", "> 7")
    for j in range(3):
        b = np.digitize(g[:, j], BINS)
        print(f"  {'xyz'[j]}: " + ", ".join(f"{edges[k]}: {ratio[b == k, j].mean():.3f} ({int(np.sum(b == k))})"
                                              for k in range(5) if np.any(b == k)))
    c = np.corrcoef(np.log(ratio).T)
    print(f"  correlation of one visit's log variances x-y / x-z / y-z: {c[0, 1]:.2f} / {c[0, 2]:.2f} / {c[1, 2]:.2f}")
    for key, name in (("p_ref", "reference level alone"), ("p_both", "reference level and ratios (the check)")):
        p = np.concatenate([r[key] for r in rows]).ravel()
        print(f"rate of p < q over q, {name}: " + ", ".join(f"{q:g}: {np.mean(p < q) / q:.2f} ({int(np.sum(p < q))})"
                                                            for q in QS))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
