"""Robustness of ``fbg-accel-calib diagnose`` on simulator recordings over many seeds (not a test).

For every scenario of ``test/test_diagnose_sim.py`` (one injected effect each) and seeds 2..6:
is the injected effect ranked first, added, and is the held-out error within 1.5x the floor? With
every named effect off (seeds 20..29): is nothing added? With the unmodelled cable torque (seeds
3..7): is a significant unexplained residual reported? Writes bench/results/diagnose_robustness.md.

    .venv/bin/python bench/diagnose_robustness.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "test"))

from output_paths import output_dir_from_command_line  # noqa: E402
from test_diagnose_sim import SCENARIOS, _config  # noqa: E402

from fbg_accel_calibration.diagnose import diagnose  # noqa: E402
from fbg_accel_sim.board_physics import simulate_recording  # noqa: E402


def main() -> int:
    out_dir = output_dir_from_command_line(__doc__.splitlines()[0])
    rows, n_ok = [], 0

    def add(injected: str, seed: int, ok: bool, cells: str, res, ratio) -> None:
        """One row: ``cells`` (first, second), then the effects added and a ratio per axis."""
        nonlocal n_ok
        rows.append(f"| {injected} | {seed} | {'OK' if ok else 'FAIL'} | {cells} | "
                    f"{', '.join(a[0] for a in res.added) or '-'} | {' / '.join(f'{r:.2f}' for r in ratio)} |")
        n_ok += ok
        print(rows[-1], flush=True)

    for eff, (scale, extra, static) in SCENARIOS.items():
        for seed in range(2, 7):
            res = diagnose(simulate_recording(_config({**extra, f"effects.{eff}.scale": scale}), seed=seed), static=static)
            ratio = res.after_heldout_rmse / res.noise_floor
            ok = (res.ranked[0].name == eff and res.ranked[0].significant and bool(res.added)
                  and res.added[0][0] == eff and bool(np.all(ratio <= 1.5)))
            runner = res.ranked[1]
            add(f"{eff} x{scale:g}", seed, ok, f"{res.ranked[0].name} {100 * res.ranked[0].rel_gain:+.1f} % | "
                f"{runner.name} {100 * runner.rel_gain:+.1f} %", res, ratio)
    for seed in range(20, 30):
        res = diagnose(simulate_recording(_config({}), seed=seed))
        ok = not res.added and not res.structure.significant
        add("none", seed, ok, "- | -", res, res.after_heldout_rmse / res.noise_floor)
    for seed in range(3, 8):
        res = diagnose(simulate_recording(_config({"effects.unmodelled_cable_torque.scale": 3.0}), seed=seed))
        s = res.structure
        ok = s.significant and s.ratio[0] > 1.1 and s.ratio[1] > 1.1
        add("unmodelled_cable_torque x3", seed, ok, f"unexplained: {s.significant} | serial corr. of pose means "
            f"{' / '.join(f'{v:+.2f}' for v in s.serial_corr_pose_means)}", res, s.ratio)
    n_all = len(rows)
    out = out_dir / "diagnose_robustness.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("# Diagnosis robustness over seeds (simulator)\n\nProduced by `.venv/bin/python bench/diagnose_robustness.py`."
                   f"\n\n**{n_ok} of {n_all} runs as expected.**\n\n"
                   "| injected | seed | result | first | second | added | after / floor x/y/z |\n|---|---|---|---|---|---|---|\n"
                   + "\n".join(rows) + "\n")
    print(f"{n_ok}/{n_all} OK; wrote {out}")
    return 0 if n_ok == n_all else 1


if __name__ == "__main__":
    raise SystemExit(main())
