"""How far into its tail the noisy-visit check's reference distribution holds (not a test).

``floor.noisy_visits`` refers a visit's detrended sum of squares to chi^2(nu) / nu with Bartlett's effective degrees of
freedom (against a fitted centre: F(nu, nu_e)), and the check (``FLOOR_VISIT_ALPHA`` = 1 %, Bonferroni over visits and
axes) reads it at about 1e-4 per visit and axis on a grid, 1e-5 on the ramps' 336 visits. This draws visits of the
sensor's noise (white plus a first-order low-pass of 0.12 s, the TIAs of paper Table 1; by default 300 samples at
100 Hz, mean and line removed), with the TRUE autocorrelation given to the check, so only its tail is under test, and
prints the rate of p < q over q for: the check as it is (its centre fitted to the visits), the chi^2 of
Satterthwaite's two moments, Bartlett's, and the four-cumulant match of Liu, Tang & Zhang (2009, Comput. Stat. Data
Anal. 53, 853-856) from the eigenvalues of the detrended correlation matrix. A calibrated tail gives 1.

    nice -n 19 .venv/bin/python bench/noisy_visit_tail.py --batches 40    # ~1 min on 2 cores
    # the clean ramps' visits: 29 samples at 10 Hz, white noise 1.34 x the low-pass's (lag-1 correlation 0.18)
    nice -n 19 .venv/bin/python bench/noisy_visit_tail.py --batches 500 --samples 29 --rate-hz 10 --white 1.34
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import stats
from scipy.linalg import toeplitz
from scipy.signal import lfilter

from fbg_accel_calibration.diagnosis.floor import noisy_visits

QS = (1e-2, 1e-3, 1e-4, 1e-5)


def ltz_sf(q: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """P(sum_i lam_i chi^2_1 > q) by Liu, Tang & Zhang's match of the first four cumulants (central case)."""
    c1, c2, c3, c4 = (float(np.sum(lam**k)) for k in (1, 2, 3, 4))
    s1, s2 = c3 / c2**1.5, c4 / c2**2
    if s1**2 > s2:
        a = 1.0 / (s1 - np.sqrt(s1**2 - s2))
        delta, df = s1 * a**3 - a**2, a**2 - 2.0 * (s1 * a**3 - a**2)
    else:
        a, delta, df = 1.0 / s1, 0.0, 1.0 / s1**2
    x = (q - c1) / np.sqrt(2.0 * c2) * np.sqrt(2.0) * a + df + delta
    return stats.ncx2.sf(x, df, delta) if delta > 0 else stats.chi2.sf(x, df)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, default=40, help="batches of 2000 visits x 3 axes")
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--rate-hz", type=float, default=100.0, help="sample rate (the low-pass is 0.12 s)")
    ap.add_argument("--white", type=float, default=0.09, help="white noise variance over the low-pass's")
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    n, phi, white = a.samples, float(np.exp(-1.0 / (0.12 * a.rate_hz))), a.white  # the 0.12 s low-pass
    lag = np.arange(n)
    acf1 = (phi**lag + white * (lag == 0)) / (1.0 + white)
    acf = np.tile(acf1[: min(n, 200)], (3, 1))
    t = np.arange(n) - (n - 1) / 2.0
    basis = np.column_stack([np.ones(n) / np.sqrt(n), t / np.sqrt(np.sum(t**2))])
    proj = np.eye(n) - basis @ basis.T
    lam = np.linalg.eigvalsh(proj @ toeplitz(acf1) @ proj)
    lam = lam[lam > 1e-10]
    c1, c2 = float(lam.sum()), float(np.sum(lam**2))
    nu_s, nu_b = c1**2 / c2, c1 / (1.0 + 2.0 * float(np.sum(acf1[1:] ** 2)))
    names = ("the check (fitted scale, Bartlett, F)", "Satterthwaite, true scale", "Bartlett, true scale",
             "Liu-Tang-Zhang, true scale")
    hits, total = np.zeros((len(names), len(QS))), 0
    for _ in range(a.batches):
        V = 2000
        x = rng.normal(size=(V * n, 3))
        y = (lfilter([1 - phi], [1, -phi], x, axis=0) * np.sqrt((1 + phi) / (1 - phi))
             + np.sqrt(white) * rng.normal(size=(V * n, 3))) / np.sqrt(1.0 + white)
        d = y.reshape(V, n, 3)
        d = d - d.mean(axis=1, keepdims=True)
        d = d - (np.einsum("vnj,n->vj", d, t) / np.sum(t**2))[:, None, :] * t[None, :, None]
        ss = np.sum(d**2, axis=1)
        p = (noisy_visits(ss, np.full(V, n), np.ones(V, bool), acf)[1], stats.chi2.sf(ss / c1 * nu_s, nu_s),
             stats.chi2.sf(ss / c1 * nu_b, nu_b), ltz_sf(ss, lam))
        total += ss.size
        for i, pi in enumerate(p):
            hits[i] += [np.sum(pi < q) for q in QS]
    print(f"{total} visit-axes of {n} samples; effective degrees of freedom: Satterthwaite {nu_s:.1f}, "
          f"Bartlett {nu_b:.1f}")
    print("rate of p < q over q, q = " + ", ".join(f"{q:g}" for q in QS))
    for name, h in zip(names, hits, strict=True):
        print(f"  {name}: " + ", ".join(f"{r:.2f}" for r in h / total / np.array(QS)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
