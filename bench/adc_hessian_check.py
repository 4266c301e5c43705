#!/usr/bin/env python3
"""Does the code-width fit's analytic Hessian give the results of the finite-difference one it replaced?

Not a test (``test/test_adc_code_widths_hessian.py`` checks the analytic Hessian against differences of the gradient).
The code-width model (``adc_codes._WidthModel``) takes damped Newton steps on its Hessian and states the pattern's
covariance from it (``profile_hessian``). Its Hessian is analytic; it used to be central differences of the gradient
(``fd_hessian_parts`` below, the computation before, kept here only). Each estimate below is made with both, and the
script prints the largest difference of the pooled (and per-channel) widths, of their 95 % half-widths (u95), of the
pattern test's p-value (as log10), whether the verdicts (pattern found, odd codes) are identical, the Newton steps
of every fit, and the CPU time of each:

* the campaigns of ``bench/adc_gate_check.py``: those of ``bench/diagnose_adc_codes_check.py`` (the measured run's
  156-pose grid with the board's measured noise, the measured width pattern on and off, seeds ``--seeds``) and the
  clean campaigns of ``test/test_diagnose_sim.py`` (seed 1); for each, the diagnosis candidate's two estimates
  (``diagnosis.adc_code_candidate``): the gate and one fold pair's table;
* the measured series (``../shared/data/measured/fig13_multiposition_23C.csv``, when there): every channel and the
  pooled estimate as ``fbg-accel-calib adc-codes`` makes them, and the diagnosis's gate;
* ``diagnose`` on the campaigns of ``bench/diagnose_adc_codes_check.py`` for ``--diagnose-seeds`` seeds (pattern on
  and off) and on the measured series: the candidate's verdict, held-out gain and p-value.

    .venv/bin/python bench/adc_hessian_check.py [--seeds 3] [--diagnose-seeds 1] [--output PATH]

Writes adc_hessian_check.json to the scratch directory (``bench/output_paths.py``) by default. Exit status 1 when a
verdict differs.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "test"))

import output_paths  # noqa: E402
from adc_code_widths_check import campaign  # noqa: E402
from adc_gate_check import campaigns as gate_campaigns  # noqa: E402

from fbg_accel_calibration.diagnosis import adc_code_candidate as cand  # noqa: E402
from fbg_accel_calibration.diagnosis.design import prepare_data  # noqa: E402
from fbg_accel_calibration.fit import adc_codes  # noqa: E402

MEASURED = next((p / "shared" / "data" / "measured" / "fig13_multiposition_23C.csv" for p in ROOT.parents[:2]
                 if (p / "shared" / "data" / "measured" / "fig13_multiposition_23C.csv").is_file()), None)
ANALYTIC = adc_codes._WidthModel._hessian_parts
FIT = adc_codes._WidthModel.fit


def fd_hessian_parts(self, theta: np.ndarray, local_only: bool = False, h: float = 1e-5) -> tuple[np.ndarray, ...]:
    """``_WidthModel._hessian_parts`` as it was: the NLL's Hessian from its gradient by central differences (2 x 3
    gradient calls for the pieces' blocks, moving one kind of every piece's parameters at once, and 2 x G for the
    global block and the cross terms)."""
    G, V, L = self.G, self.V, self.L

    def column(direction: np.ndarray) -> np.ndarray:
        return (self.nll(theta + h * direction)[1] - self.nll(theta - h * direction)[1]) / (2 * h)

    n = len(theta)
    h_ll = np.zeros((V, L, L))
    for k in range(L):
        d = np.zeros(n)
        d[G + k * V:G + (k + 1) * V] = 1.0
        c = column(d)[G:].reshape(L, V)
        h_ll[:, :, k] = c.T
    h_ll = 0.5 * (h_ll + h_ll.transpose(0, 2, 1))
    if local_only:
        return np.eye(G), np.zeros((G, V, L)), h_ll
    cols = np.column_stack([column(np.eye(1, n, i)[0]) for i in range(G)])
    b = cols[G:].reshape(L, V, G).transpose(2, 1, 0)
    return 0.5 * (cols[:G] + cols[:G].T), b, h_ll


_count = threading.local()  # Hessians worked out by the fit running in this thread (the diagnosis fits two at a time)
STEPS: list[int] = []  # Newton steps of every fit since the last ``_run``


@contextlib.contextmanager
def hessian(kind: str) -> Iterator[None]:
    """``_WidthModel`` with the analytic (``"analytic"``) or the finite-difference (``"fd"``) Hessian, its fits'
    Newton steps recorded in ``STEPS``."""
    parts = ANALYTIC if kind == "analytic" else fd_hessian_parts

    def counted(self, theta: np.ndarray, local_only: bool = False) -> tuple[np.ndarray, ...]:
        _count.n = getattr(_count, "n", 0) + 1
        return parts(self, theta, local_only)

    def fit(self, theta: np.ndarray | None = None, fixed_global: bool = False) -> np.ndarray:
        _count.n = 0
        out = FIT(self, theta, fixed_global)
        STEPS.append(_count.n)
        return out

    adc_codes._WidthModel._hessian_parts, adc_codes._WidthModel.fit = counted, fit
    try:
        yield
    finally:
        adc_codes._WidthModel._hessian_parts, adc_codes._WidthModel.fit = ANALYTIC, FIT


def _fields(w: adc_codes.CodeWidths | None, reason: str | None = None) -> dict:
    if w is None:
        return {"reason": reason}
    return {"pattern": w.pattern.tolist(), "u95": w.pattern_u95.tolist(), "chi2": w.chi2, "p_value": w.p_value,
            "found": bool(w.pattern_found), "odd": [(o.code, o.kind) for o in w.odd]}


def _run(kind: str, make: Callable[[], dict]) -> tuple[dict, list[int], float]:
    STEPS.clear()
    t = time.process_time()
    with hessian(kind):
        out = make()
    return out, list(STEPS), time.process_time() - t


def _differences(fd: dict, an: dict) -> dict:
    """Per estimate (a key of both): largest |difference| of the widths and u95, of log10 p, verdicts the same."""
    out = {"widths": 0.0, "u95": 0.0, "log10_p": 0.0, "p_rel": 0.0, "verdicts_same": True}
    for key in fd:
        if key.startswith("_"):  # figures within rounding, not verdicts
            continue
        a, b = fd[key], an[key]
        if "pattern" not in a or "pattern" not in b:
            out["verdicts_same"] &= a == b
            continue
        out["widths"] = max(out["widths"], float(np.max(np.abs(np.subtract(a["pattern"], b["pattern"])))))
        out["u95"] = max(out["u95"], float(np.max(np.abs(np.subtract(a["u95"], b["u95"])))))
        if a["p_value"] > 0 and b["p_value"] > 0:
            out["log10_p"] = max(out["log10_p"], abs(float(np.log10(a["p_value"] / b["p_value"]))))
            out["p_rel"] = max(out["p_rel"], abs(a["p_value"] - b["p_value"]) / a["p_value"])
        else:
            out["verdicts_same"] &= a["p_value"] == b["p_value"]
        out["verdicts_same"] &= a["found"] == b["found"] and a["odd"] == b["odd"]
    return out


def compare(label: str, make: Callable[[], dict]) -> dict:
    """Both Hessians on one estimate (``make``: the estimates, each a ``_fields`` dict, by name)."""
    fd, steps_fd, cpu_fd = _run("fd", make)
    an, steps_an, cpu_an = _run("analytic", make)
    row = {"case": label, **_differences(fd, an), "steps_fd": steps_fd, "steps_analytic": steps_an,
           "cpu_s_fd": cpu_fd, "cpu_s_analytic": cpu_an, "fd": fd, "analytic": an}
    print(f"{label}: widths {row['widths']:.1e}, u95 {row['u95']:.1e}, log10 p {row['log10_p']:.1e} (rel "
          f"{row['p_rel']:.1e}), verdicts same {row['verdicts_same']}; Newton steps {steps_fd} -> {steps_an}; "
          f"CPU {cpu_fd:.2f} -> {cpu_an:.2f} s", flush=True)
    return row


def _candidate_estimates(rec) -> Callable[[], dict]:
    """The diagnosis candidate's gate and one fold pair's table (as ``bench/adc_gate_check.py``)."""
    data = prepare_data(rec)
    rows = cand.width_rows(data)
    rows_gate = cand._thinned(rows, cand.GATE_SAMPLES)
    pair = np.flatnonzero(np.isin(data.group, np.unique(data.group[rows])[::5]))
    rows_fold = rows.copy()
    rows_fold[pair] = False
    rows_fold = cand._thinned(rows_fold)

    def make() -> dict:
        out = {}
        for name, r in (("gate", rows_gate), ("fold_table", rows_fold)):
            try:
                res = cand.pooled_widths(data, r)
                out[name] = _fields(res.pooled, res.reasons.get("pooled"))
            except ValueError as exc:
                out[name] = _fields(None, str(exc))
        return out
    return make


def _measured_estimates(rec) -> Callable[[], dict]:
    """Every channel and the pooled estimate of ``fbg-accel-calib adc-codes``, and the diagnosis's gate."""
    from fbg_accel_calibration.commands.adc_codes_cli import visits_of

    groups, rows = visits_of(rec)
    gate = _candidate_estimates(rec)

    def make() -> dict:
        res = adc_codes.recording_code_widths(np.column_stack([rec.ref, rec.xyz]), groups, rows)
        out = {name: _fields(w, res.reasons.get(name)) for name, w in res.channels.items()}
        out["pooled"] = _fields(res.pooled, res.reasons.get("pooled"))
        out["diagnosis gate"] = gate()["gate"]
        return out
    return make


def _diagnosis(rec) -> Callable[[], dict]:
    """The diagnosis's verdict on the code-width candidate."""
    from fbg_accel_calibration.diagnosis.diagnose import diagnose

    def make() -> dict:
        res = diagnose(rec)
        c = next(c for st in res.steps for c in st.candidates if c.name == cand.NAME)
        return {"verdict": {"named": bool(c.significant), "applicable": bool(c.applicable),
                            "added": [a[0] for a in [*res.added, *res.noise_remedies, *res.run_terms]]},
                "_figures": {"gain": c.rel_gain, "p_value": c.p_value}}
    return make


def _diagnosis_row(label: str, rec) -> dict:
    row = compare(label, _diagnosis(rec))
    a, b = row["fd"]["_figures"], row["analytic"]["_figures"]
    row["gain_diff"] = abs(a["gain"] - b["gain"]) if a["gain"] is not None else None
    row["p_rel"] = abs(a["p_value"] - b["p_value"]) / a["p_value"] if a["p_value"] else None
    print(f"  verdict same {row['verdicts_same']}; gain {a['gain']} -> {b['gain']}; p {a['p_value']} -> "
          f"{b['p_value']}", flush=True)
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--diagnose-seeds", type=int, default=1)
    ap.add_argument("--output", type=Path, default=output_paths.scratch_dir() / "adc_hessian_check.json")
    args = ap.parse_args(argv)
    rows = [compare(label, _candidate_estimates(rec)) for label, rec in gate_campaigns(args.seeds)]
    measured = None
    if MEASURED is not None:
        from fbg_accel_calibration.io.input_files import load_recording

        measured = load_recording([MEASURED], rate=1.0, temperature=23.4, g=9.81)
        rows.append(compare("measured series: adc-codes (ref, x, y, z, pooled) and the diagnosis gate",
                            _measured_estimates(measured)))
    else:
        print("measured series not found (../shared/data/measured): left out")
    for seed in range(1, args.diagnose_seeds + 1):
        for pattern in (True, False):
            rows.append(_diagnosis_row(f"diagnose, diagnose_adc_codes_check seed {seed} pattern "
                                       f"{'on' if pattern else 'off'}", campaign(seed, pattern)))
    if measured is not None and args.diagnose_seeds > 0:
        rows.append(_diagnosis_row("diagnose, measured series", measured))
    same = sum(r["verdicts_same"] for r in rows)
    est = [r for r in rows if "widths" in r and not r["case"].startswith("diagnose,")]
    print(f"verdicts identical in {same} of {len(rows)} cases; largest differences over the estimates: widths "
          f"{max(r['widths'] for r in est):.1e}, u95 {max(r['u95'] for r in est):.1e}, log10 p "
          f"{max(r['log10_p'] for r in est):.1e}; Newton steps equal in "
          f"{sum(r['steps_fd'] == r['steps_analytic'] for r in rows)} of {len(rows)} cases; CPU "
          f"{sum(r['cpu_s_fd'] for r in rows):.1f} -> {sum(r['cpu_s_analytic'] for r in rows):.1f} s")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({"rows": rows, "identical_verdicts": same, "cases": len(rows)}, indent=1),
                           encoding="utf-8")
    print(f"wrote {args.output}")
    return 0 if same == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
