"""The noise floor a residual is judged against: the within-visit noise and how it correlates (``within_visit_noise``,
``VisitNoise``), visits noisier than the rest, the settling transient after a table move, and the floor of a
recording measured with them (``measure_floor``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import fft as scipy_fft
from scipy import optimize, stats

from .data import DiagnosisData, finite_rows, take_rows
from .effects import TIA_TAU_S
from .periodic_disturbance import PeriodicDisturbance, find_periodic_disturbance
from .search_lanes import beside

# ============================================================================ noise floor, settling, degree
# Settling window after a table move, from the measuring chain's physics: every TIA is a first-order
# low-pass (paper Table 1: 1 / 1.7 / 1.3 / 1.3 Hz for ref / x / y / z, time constants 0.09-0.16 s), so a
# transient left at the end of a move decays as A exp(-t/tau). The floor leaves out the first sample of
# every visit and every sample before the measured transient has fallen below a tenth of the noise
# (t < tau ln(10 A / sigma): under 0.5 % on the floor in quadrature). Without a measurable transient only
# the first sample goes. The window never exceeds 10 x the slowest TIA time constant (1.6 s): a slower
# "transient" is not the chain's and is reported, not hidden.
SETTLE_NOISE_FRACTION = 0.1
MAX_SETTLE_S = float(10.0 * np.max(TIA_TAU_S))


def visit_index(g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``np.unique(g, return_inverse=True)`` and, when ``g`` never decreases (visits numbered in time order,
    ``visit_ids``, at rows in time order), where each value's samples start (else None): then found from where ``g``
    changes instead of by sorting it, the same arrays in a tenth of the time at 10^6 samples."""
    if g.size and bool(np.all(g[1:] >= g[:-1])):
        change = np.empty(g.size, bool)
        change[0] = True
        np.not_equal(g[1:], g[:-1], out=change[1:])
        return g[change], np.cumsum(change) - 1, np.flatnonzero(change)
    ug, inv = np.unique(g, return_inverse=True)
    return ug, inv, None


def per_visit(extreme: np.ufunc, t: np.ndarray, inv: np.ndarray, starts: np.ndarray | None, n: int) -> np.ndarray:
    """``extreme`` (``np.minimum`` or ``np.maximum``) of ``t`` over each of the ``n`` visits (``visit_index``'s
    ``inv`` and ``starts``): over each visit's side-by-side samples when ``starts`` is known, else gathered by index."""
    if starts is not None:
        return extreme.reduceat(t, starts)
    out = np.full(n, np.inf if extreme is np.minimum else -np.inf)
    extreme.at(out, inv, t)
    return out


def settled_mask(t_s: np.ndarray, groups: np.ndarray, rows: np.ndarray, settle_s: float = 0.0,
                 end_s: float | None = None) -> np.ndarray:
    """Settled samples (N,) among ``rows``: the first sample of every visit and every sample less than
    ``settle_s`` (s, board time) after it are dropped (the settling transient after a table move).
    At least the first sample of a visit is always dropped, whatever the sample rate. ``end_s`` (s): the same at
    the other end, for a visit whose end is disturbed (``SettlingTransient.end_detected``): the last sample and
    every sample less than ``end_s`` before it are dropped; None (the default): the end is kept."""
    idx = np.flatnonzero(rows)
    out = np.zeros(len(t_s), bool)
    if idx.size == 0:
        return out
    g = groups[idx]
    t = t_s[idx]
    ug, inv, starts = visit_index(g)
    age = t - per_visit(np.minimum, t, inv, starts, len(ug))[inv]
    first = np.zeros(len(idx), bool)  # idx is time-ordered within a run
    first[np.unique(inv, return_index=True)[1] if starts is None else starts] = True
    keep = (age >= settle_s) & ~first
    if end_s is not None:
        last = np.zeros(len(idx), bool)
        last[len(idx) - 1 - np.unique(inv[::-1], return_index=True)[1] if starts is None
             else np.r_[starts[1:], len(idx)] - 1] = True
        keep &= (per_visit(np.maximum, t, inv, starts, len(ug))[inv] - t >= end_s) & ~last
    out[idx] = keep
    return out


# Noise floor of correlated noise. The noise of this sensor is white noise through the first-order TIA
# low-passes (time constants up to 0.16 s: 16 samples at 100 Hz, 64 at 400 Hz) plus the ADC's white rounding. Removing
# a visit's mean and line removes about two integrated correlation times' worth of it, not two samples' worth: the
# expected sum of squares is sigma^2 tr((I - H) R) (H the hat matrix of the mean and line over the visit, R the noise's
# correlation matrix), about sigma^2 (n - 2 kappa) with kappa = 1 + 2 sum_l rho_l samples (~70 at 400 Hz). Divided by
# n - 2, the floor of 1 s visits came out 13-19 % low (clean simulated recordings, 100 and 400 Hz), and the held-out
# error stood 1.15-1.26x above it: a clean recording was judged to hold an unexplained residual. So the pooled lag
# products of the detrended residual, lags 0..K, are fitted with their exact expectation (``detrended_lag_matrix``:
# E[sum_i d_i d_{i+k}] = sum_m A_km gamma_m) under white noise plus a first-order process, gamma_l = a delta_l +
# b exp(-l / tau), which is the chain (as ``stillness_monitor`` models it, plus the white part). The floor is
# sqrt(a + b); the variance of a visit mean that the chi^2 of ``residual_structure`` needs follows from the same fit
# (``VisitNoise``), so floor and test agree on what the noise is. A free gamma_0..gamma_K solved from the same equations
# is unbiased but, from 1 s visits at 400 Hz, so uncertain at long lags (they make the variance of a visit mean) that it
# came out negative on some seeds (integrated correlation < 0, floor 0.82x the truth); it is used only where the model
# has too few lags (``MODEL_MIN_LAGS``). K covers NOISE_CORR_S, five of the slowest TIA time constants (a first-order
# correlation is e^-5 = 0.7 % there), and at most half the median visit. Slower noise (bias instability, drift) is
# removed with the line within a visit, and is not in the floor.
NOISE_CORR_S = 5.0 * float(np.max(TIA_TAU_S))


@dataclass
class VisitNoise:
    """Noise floor of a residual (``within_visit_noise``): what no static model can remove, and how it correlates."""

    sigma: np.ndarray  # (3,) per-sample standard deviation, m/s^2 (table frame)
    acf: np.ndarray  # (3, L + 1) normalised autocorrelation at lags 0..L samples (acf[:, 0] = 1), zero beyond L
    # (3,) degrees of freedom of the variance of a visit mean as an estimate (inf: known exactly)
    mean_dof: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    # visits left out of the floor, their scatter far beyond the others' (``noisy_visits``): label, (3,) scatter /
    # floor, (3,) p-value of the check
    flagged: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)
    n_checked: int = 0  # visits the check ran over (its Bonferroni count)

    def mean_variance(self, n: np.ndarray) -> np.ndarray:
        """Variance (len(n), 3) in (m/s^2)^2 of the mean of ``n`` (V,) consecutive samples of the noise:
        sigma^2 (n + 2 sum_l (n - l) rho_l) / n^2, kept within [sigma^2 / n^2, sigma^2] (estimated rho may be noisy)."""
        cnt = np.asarray(n, dtype=float)[:, None]
        lag = np.arange(1, self.acf.shape[1], dtype=float)
        pairs = np.clip(cnt - lag[None, :], 0.0, None)  # (V, L) pairs of samples at each lag
        var = self.sigma**2 * (cnt + 2.0 * pairs @ self.acf[:, 1:].T) / cnt**2
        return np.clip(var, self.sigma**2 / cnt**2, self.sigma**2)

    @property
    def correlation_samples(self) -> np.ndarray:
        """(3,) integrated correlation time 1 + 2 sum_l rho_l, samples (1 for white noise): a visit of n samples
        holds about n / this many independent ones."""
        return 1.0 + 2.0 * self.acf[:, 1:].sum(axis=1)


def _range_products(qa: tuple[float, float], qb: tuple[float, float], n: int, lo: np.ndarray, hi: np.ndarray,
                    alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """sum_{i=lo}^{hi} q_a[i + alpha] q_b[i + beta] (0 for an empty range) for q(i) = A + B (i - (n - 1) / 2), ``qa``
    and ``qb`` their (A, B); arrays broadcast. Centred on the range's mean, so that nothing large cancels."""
    (aa, ba), (ab, bb) = qa, qb
    cnt = np.maximum(hi - lo + 1.0, 0.0)
    mu = (lo + hi) / 2.0 - (n - 1) / 2.0  # mean of i - (n - 1) / 2 over the range
    spread = (cnt**2 - 1.0) / 12.0  # variance of consecutive integers
    a0, b0 = aa + ba * alpha, ab + bb * beta
    return cnt * (a0 * b0 + (a0 * bb + b0 * ba) * mu + ba * bb * (mu * mu + spread))


def detrended_lag_matrix(n: int, lags: int, model_lags: int, line: bool = True) -> np.ndarray:
    """A (lags + 1, model_lags + 1): E[sum_i d_i d_{i+k}] = sum_m A[k, m] gamma_m for d the residual of
    ``n`` consecutive samples of a stationary process (autocovariance gamma_m at lag m samples, zero beyond
    ``model_lags``) after removing their least-squares mean and, with ``line`` (and n >= 2), a straight line in the
    sample index.

    d = (I - P) x with P = sum_a q_a q_a' (q_a orthonormal: the constant, the centred index), so
    E[d d'] = (I - P) S (I - P) with S = sum_m gamma_m T_m (T_0 = I, T_m ones where |i - j| = m). Expanded, every
    entry is a sum over an index range of products of two linear functions of the index (``_range_products``), so A
    is exact and costs O(lags model_lags), not O(n lags model_lags)."""
    k = np.arange(lags + 1, dtype=float)[:, None]
    m = np.arange(model_lags + 1, dtype=float)[None, :]
    basis = [(1.0 / math.sqrt(n), 0.0)]
    if line and n >= 2:
        basis.append((0.0, 1.0 / math.sqrt(n * (n * n - 1.0) / 12.0)))
    zero = np.zeros(1)

    def cross(a: tuple[float, float], b: tuple[float, float], lag: np.ndarray) -> np.ndarray:
        """sum_{i=0}^{n-1-lag} q_a[i] q_b[i + lag]."""
        return _range_products(a, b, n, zero, n - 1.0 - lag, zero, lag)

    out = np.where((k == m) & (k <= n - 1), n - k, 0.0)  # sum_i (S)_{i, i+k}
    for q in basis:  # - sum_i (P S + S P)_{i, i+k}: (T_m q)[j] = q[j - m] (j >= m) + q[j + m] (j + m <= n - 1)
        ps = (_range_products(q, q, n, np.maximum(0.0, m - k), n - 1.0 - k, zero, k - m)
              + _range_products(q, q, n, zero, n - 1.0 - k - m, zero, k + m))
        sp = (_range_products(q, q, n, m, n - 1.0 - k, -m, k)
              + _range_products(q, q, n, zero, np.minimum(n - 1.0 - k, n - 1.0 - m), m, k))
        out = out - np.where(m == 0, 2.0 * cross(q, q, k), ps + sp)
    for ia, qa in enumerate(basis):  # + sum_i (P S P)_{i, i+k} = sum_ab (q_a' S q_b) sum_i q_a[i] q_b[i + k]
        for ib, qb in enumerate(basis):
            g = np.where(m == 0, float(ia == ib), cross(qa, qb, m) + cross(qb, qa, m))
            out = out + g * cross(qa, qb, k)
    return out


def _noise_lags(t_s: np.ndarray | None, groups: np.ndarray, r: np.ndarray, cnt: np.ndarray) -> int:
    """Lags (samples) of the lag products the floor is fitted to: NOISE_CORR_S at the median sample interval within
    visits (s), at most half the median visit; 0 (white noise) without times."""
    if t_s is None or cnt.size == 0:
        return 0
    t, g = t_s[r], groups[r]
    step = np.diff(t)[(g[1:] == g[:-1]) & (np.diff(t) > 0)]
    if step.size == 0:
        return 0
    return int(max(min(math.ceil(NOISE_CORR_S / float(np.median(step))), int(np.median(cnt)) // 2), 0))


MIN_MEAN_DOF = 2.0  # least degrees of freedom of the floor's mean variance in the F test (F(df, nu) tails ~ x^(-nu/2))
FLOOR_VISIT_ALPHA = 0.01  # level of the check for a visit noisier than the others (Bonferroni over visits and axes)
FLOOR_VISIT_RATIO = 2.0  # and its variance at least this many times the others' (scatter 1.41x): one that matters
MODEL_MIN_LAGS = 3  # with fewer lag products than the white + first-order model's 3 parameters: a free autocovariance
JACKKNIFE_GROUPS = 20  # groups of visits left out in turn to measure how well the variance of a visit mean is known
TAU_GRID = 48  # correlation times tried by the fit (log-spaced)


@dataclass
class _LagMoments:
    """The lag products of the detrended visits and the expectations they are fitted to (``within_visit_noise``)."""

    prods: np.ndarray  # (V, K + 1, 3) lag-k products of every visit
    kind: np.ndarray  # (V,) index of the visit's (length, line) among ``expect``'s
    expect: np.ndarray  # (kinds, T, K + 1, 2) expected lag products per unit white / first-order variance
    tau: np.ndarray  # (T,) correlation times, samples
    model_lags: int  # M: lags of the model autocovariance

    def fit(self, visits: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(a, b, tau) per axis (3,) of the autocovariance a delta_l + b exp(-l / tau) (a, b >= 0, tau in samples)
        that fits the lag products of ``visits`` best (least squares over the lags, for each tau of the grid)."""
        w = np.bincount(self.kind[visits], minlength=self.expect.shape[0]).astype(float)
        D = np.tensordot(w, self.expect, axes=1)  # (T, K + 1, 2)
        c = self.prods[visits].sum(axis=0)  # (K + 1, 3)
        G = np.einsum("tki,tkj->tij", D, D)
        h = np.einsum("tki,kj->tij", D, c)  # (T, 2, 3)
        det = G[:, 0, 0] * G[:, 1, 1] - G[:, 0, 1] ** 2
        both = np.stack([G[:, 1, 1, None] * h[:, 0] - G[:, 0, 1, None] * h[:, 1],
                         G[:, 0, 0, None] * h[:, 1] - G[:, 0, 1, None] * h[:, 0]], axis=1)
        both /= np.where(np.abs(det) > 1e-300, det, np.inf)[:, None, None]
        # with a negative part, the better of the white part alone and the first-order part alone
        alone = np.clip(h / np.maximum(np.diagonal(G, axis1=1, axis2=2), 1e-300)[:, :, None], 0.0, None)
        cands = np.zeros((3, *both.shape))  # (white alone, first-order alone, both; T, 2, 3)
        cands[0, :, 0], cands[1, :, 1], cands[2] = alone[:, 0], alone[:, 1], both
        # residual sum of squares less the constant c'c: coef' G coef - 2 coef' h
        score = np.einsum("ctik,tij,ctjk->ctk", cands, G, cands) - 2.0 * np.einsum("ctik,tik->ctk", cands, h)
        score[2][np.any(both < 0.0, axis=1)] = np.inf
        ci, ti = np.unravel_index(np.argmin(score.reshape(-1, 3), axis=0), score.shape[:2])
        axis = np.arange(3)
        return cands[ci, ti, 0, axis], cands[ci, ti, 1, axis], self.tau[ti]

    def noise(self, visits: np.ndarray) -> VisitNoise | None:
        a, b, tau = self.fit(visits)
        var = a + b
        if not np.all(var > 0):
            return None
        lag = np.arange(self.model_lags + 1)
        acf = (a[:, None] * (lag == 0) + b[:, None] * np.exp(-lag[None, :] / tau[:, None])) / var[:, None]
        return VisitNoise(np.sqrt(var), acf)


def _lag_products(dev: np.ndarray, n_v: np.ndarray, lags: int, batch: int = 256) -> np.ndarray:
    """(V, K + 1, 3): sum_i d_i d_{i+k} of every visit for k = 0..K (``lags``), ``dev`` (N, 3) the visits one after the
    other (``n_v`` (V,) samples each). By FFT, zero-padded against wrap-around up to lag K; the visits of one length
    are transformed together, ``batch`` at a time (the same transform of each: its values are those of one at a time)."""
    bounds = np.r_[0, np.cumsum(n_v)]
    prods = np.zeros((len(n_v), lags + 1, 3))
    for n in np.unique(n_v):
        size = scipy_fft.next_fast_len(int(n) + lags + 1, real=True)
        keep = min(lags + 1, int(n))
        same = np.flatnonzero(n_v == n)
        for lo in range(0, len(same), batch):
            vs = same[lo:lo + batch]
            x = take_rows(dev, (bounds[vs][:, None] + np.arange(n)[None, :]).ravel()).reshape(len(vs), int(n), 3)
            spec = scipy_fft.rfft(x, size, axis=1)
            prods[vs, :keep] = scipy_fft.irfft(spec.real**2 + spec.imag**2, size, axis=1)[:, :keep]
    return prods


def within_visit_noise(res: np.ndarray, groups: np.ndarray, rows: np.ndarray, t_s: np.ndarray | None = None,
                       jackknife: bool = True, reference: np.ndarray | None = None,
                       axis_counts: np.ndarray | None = None) -> VisitNoise:
    """The noise floor (3,) m/s^2 of a residual (N, 3) m/s^2, table frame, and its autocorrelation (see above).

    ``groups`` are visits (``DiagnosisData.group``), ``rows`` the samples that count (settled ones: see ``settled_mask``).
    The mean of every visit is removed and, with ``t_s`` (s), a straight line in time (so that slow changes within
    a visit, temperature ramps, drift, do not count as noise). What is left is the noise seen through I - H; its
    pooled lag products over 0..K lags (``_noise_lags``) are fitted with their exact expectation
    (``detrended_lag_matrix``) under white noise plus a first-order process, a delta_l + b exp(-l / tau): the chain's
    white noise through the TIA low-pass plus the ADC's white rounding and read noise (as ``stillness_monitor``). The
    floor is sqrt(a + b). A free autocovariance fitted the same way is unbiased but, from short visits, far too
    uncertain at long lags (they matter for the variance of a visit mean and the floor); with fewer than
    ``MODEL_MIN_LAGS`` lags it is what is used (white noise with none: the pooled standard deviation over the
    degrees of freedom left). Lags count the samples of a visit in ``rows`` in order (evenly spaced; a lost sample
    shifts the lags across it by one).

    How well the variance of a visit mean is known (``VisitNoise.mean_dof``) is measured by a grouped jackknife over
    the visits (``JACKKNIFE_GROUPS``): short visits tell little about the correlation at long lags, on which it rests.
    ``jackknife`` False: not measured (``mean_dof`` stays inf), for a caller that needs the floor alone.
    ``reference`` (N,) the reference channel's counts and ``axis_counts`` (N, 3) the axis channels': a visit's noise is
    judged by the check for a noisy visit (``noisy_visits``) against what its reference level and its ratios make it
    (``visit_noise_levels``).
    """
    r = rows & finite_rows(res)
    if not r.any():
        return VisitNoise(np.full(3, np.nan), np.ones((3, 1)))
    idx = np.flatnonzero(r)
    ug, inv, starts = visit_index(groups[idx])
    cnt = np.bincount(inv).astype(float)
    dev = take_rows(res, idx)
    dev -= take_rows(np.stack([np.bincount(inv, weights=dev[:, j]) / cnt for j in range(3)], axis=1), inv)
    stt = np.zeros(len(ug))  # sum of squared centred times of each visit (s^2), 0 where no line is fitted
    if t_s is not None:
        # times from each visit's first sample: the line does not depend on the time origin (a CSV with seconds since
        # 1970, ~1.7e9 s, gives what the same run from 0 s gives); no line where a visit's samples share one time
        t = t_s[idx]
        t_first = per_visit(np.minimum, t, inv, starts, len(ug))
        t_rel = t - t_first[inv]
        tmean_rel = np.bincount(inv, weights=t_rel) / cnt
        tc = t_rel - tmean_rel[inv]
        stt = np.bincount(inv, weights=tc * tc)
        ok = stt > 1e-12 * np.maximum(tmean_rel**2, 1.0)
        slope = np.zeros((len(ug), 3))
        for j in range(3):
            slope[ok, j] = np.bincount(inv, weights=tc * dev[:, j])[ok] / stt[ok]
        stt = np.where(ok, stt, 0.0)
        dev -= take_rows(slope, inv) * (t - (t_first + tmean_rel)[inv])[:, None]
    lags = _noise_lags(t_s, groups, r, cnt)
    n_v = cnt.astype(int)
    if starts is None:
        dev = dev[np.argsort(inv, kind="stable")]  # by visit, in time order within a visit
    prods = _lag_products(dev, n_v, lags)
    kinds, kind = np.unique(np.column_stack([n_v, stt > 0]), axis=0, return_inverse=True)
    kind = kind.ravel()
    if lags >= MODEL_MIN_LAGS:
        tau = np.geomspace(0.25, lags / 2.0, TAU_GRID)
        model_lags = int(min(math.ceil(10.0 * tau[-1]), n_v.max() - 1))
        lag = np.arange(model_lags + 1)
        basis = np.stack([np.broadcast_to((lag == 0).astype(float)[:, None], (len(lag), len(tau))),
                          np.exp(-lag[:, None] / tau[None, :])], axis=-1)  # (M + 1, T, 2)
        expect = np.stack([np.einsum("km,mtj->tkj", detrended_lag_matrix(int(n), lags, model_lags, bool(h)), basis)
                           for n, h in kinds])
        moments = _LagMoments(prods, kind, expect, tau, model_lags)
        estimate: Callable[[np.ndarray], VisitNoise | None] = moments.noise
    else:
        A_k = np.array([detrended_lag_matrix(int(n), lags, lags, bool(h)) for n, h in kinds])

        def estimate(visits: np.ndarray) -> VisitNoise | None:
            A = np.tensordot(np.bincount(kind[visits], minlength=len(kinds)).astype(float), A_k, axes=1)
            try:
                gamma = np.linalg.solve(A, prods[visits].sum(axis=0))
            except np.linalg.LinAlgError:
                return None
            if not (np.all(np.isfinite(gamma)) and np.all(gamma[0] > 0)):
                return None
            return VisitNoise(np.sqrt(gamma[0]), (gamma / gamma[0]).T)

    every = np.arange(len(n_v))
    noise = estimate(every)
    if noise is None:
        return VisitNoise(np.full(3, np.nan), np.ones((3, 1)))
    level = None if reference is None else visit_noise_levels(
        reference[idx], None if axis_counts is None else take_rows(axis_counts, idx), inv, cnt)
    flagged = np.zeros(len(n_v), bool)
    for _ in range(3):  # the autocorrelation the check uses is refitted without the visits it flags
        ratio, p = noisy_visits(prods[:, 0], n_v, stt > 0, noise.acf, level)
        now = np.any((p < FLOOR_VISIT_ALPHA / (3 * len(n_v))) & (ratio > FLOOR_VISIT_RATIO), axis=1)
        if np.array_equal(now, flagged) or now.all():
            break
        flagged = now
        refit = estimate(every[~flagged])
        if refit is None:
            flagged[:] = False
            break
        noise = refit
    every = every[~flagged]
    # grouped jackknife of log(variance of the mean of a median-length visit): its spread gives the degrees of freedom
    # of that variance as an estimate, nu = 2 / var(log), as for a scaled chi^2(nu) / nu
    n_groups = min(JACKKNIFE_GROUPS, len(every))
    if jackknife and n_groups >= 3:
        ref = np.array([np.median(cnt)])
        member = np.arange(len(every)) % n_groups
        parts = [estimate(every[member != gi]) for gi in range(n_groups)]
        logs = np.array([np.log(part.mean_variance(ref)[0]) for part in parts if part is not None])
        if len(logs) >= 3:  # a group without a fit of its own (too few visits left) does not count
            spread = (len(logs) - 1) / len(logs) * np.sum((logs - logs.mean(axis=0)) ** 2, axis=0)
            noise.mean_dof = 2.0 / np.maximum(spread, 1e-12)
    noise.flagged = [(int(ug[v]), np.sqrt(ratio[v]), p[v]) for v in np.flatnonzero(flagged)]
    noise.n_checked = len(n_v)
    return noise


def visit_noise_levels(reference: np.ndarray, axis_counts: np.ndarray | None, inv: np.ndarray,
                       cnt: np.ndarray) -> np.ndarray | None:
    """(V, 3, B) what each visit's noise variance on each axis is made of, as its counts set it (``noisy_visits`` fits
    how much of each there is): the output is the axis channels' counts x_j over the reference channel's r (eq. 24),
    Psi_j = x_j / r, so a count noise of variance s_x^2 on x_j and s_r^2 on r (the reference's read noise: ~1 count rms
    on the measured board) gives Psi_j the variance (s_x^2 + Psi_j^2 s_r^2) / r^2. Column 0 is the visit's mean of
    1 / r^2 (the axis channels' noise: the detectors and ADCs count it, paper Table 2's noise is injected on the counts
    through the small-signal slope), column 1 (with ``axis_counts``) its mean of Psi_j^2 / r^2 (the reference's noise,
    carried into every axis in proportion to its ratio). On the simulator's clean ramps (15 -> 45 -> 15 degC) the
    reference falls by ~12 % when hot (x +40 % from the coldest to the hottest visit, seed 20), and the read noise makes
    a visit's variance rise with the specific force along the axis (by -7 to -10 % at -1 g, +6 to +9 % at +1 g,
    ``bench/noisy_visit_levels.py``): against 1 / r^2 alone, the 3 s visits at 10 Hz (~24 degrees of freedom, read at
    ~1e-5 per visit and axis, where a variance 9 % above what it is judged against is flagged 6 x as often) were left
    out on 6 of 100 clean campaigns. ``reference`` (n,) counts of the rows, ``axis_counts`` (n, 3) (None: column 0
    alone), ``inv`` (n,) each row's visit, ``cnt`` (V,) rows per visit; each column over its median visit; a visit
    without a positive finite reference counts as the median. None when no visit has one."""
    ok = np.isfinite(reference) & (reference > 0)
    r = np.where(ok, reference, 1.0).astype(float)
    cols = [np.broadcast_to((1.0 / r**2)[:, None], (len(r), 3))]
    if axis_counts is not None:
        ok &= finite_rows(axis_counts)
        cols.append(np.where(ok[:, None], axis_counts, 0.0) ** 2 / r[:, None] ** 4)
    n_ok = np.bincount(inv, weights=ok.astype(float), minlength=len(cnt))
    if not np.any(n_ok > 0):
        return None
    out = np.stack([np.stack([np.bincount(inv, weights=np.where(ok, c[:, j], 0.0), minlength=len(cnt))
                              for j in range(3)], axis=1) for c in cols], axis=-1) / np.maximum(n_ok, 1.0)[:, None, None]
    out[n_ok == 0] = np.nan
    out /= np.nanmedian(out, axis=0)
    return np.where(np.isfinite(out), out, 1.0)


TRIM_P = 1e-3  # visits beyond this upper tail are left out of the fit of what the others' variance is


def expected_visit_variance(var: np.ndarray, nu: np.ndarray, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What each visit's variance (``var`` (V,), as estimates of chi^2(``nu``) / nu x their expectation) is expected to
    be, e = basis c (``basis`` (V, B), c >= 0 by non-negative least squares weighted by nu / 2 e^2, the inverse
    variance of each estimate), and the degrees of freedom (V,) of e as an estimate, 2 e^2 / var(e). Robust: a visit
    beyond ``TRIM_P`` of its upper tail is left out of the fit (three passes), and the kept visits are fitted by their
    mean below that tail, so that the rest is not biased low."""
    cut = stats.chi2.isf(TRIM_P, nu)
    below = stats.chi2.cdf(cut, nu + 2.0) / np.maximum(stats.chi2.cdf(cut, nu), 1e-300)  # E[x | kept], x ~ chi2/nu
    keep = np.ones(len(var), bool)
    e = np.full(len(var), max(float(np.median(var)), 1e-300))
    for _ in range(3):
        w = np.sqrt(nu / 2.0) / np.maximum(e, 1e-300)
        c = optimize.nnls(basis[keep] * w[keep, None], var[keep] / below[keep] * w[keep])[0]
        e = np.maximum(basis @ c, 1e-300)
        now = nu * var / e <= cut
        if np.array_equal(now, keep) or now.sum() < basis.shape[1] + 1:
            break
        keep = now
    # var(e_v) = b_v' (B' W B)^-1 b_v over the kept visits and the columns in use, from the SVD of W^1/2 B (a column
    # that nearly repeats another, a reference that never changes, adds no variance)
    w = np.sqrt(np.where(keep, nu / 2.0, 0.0)) / e
    used = basis[:, c > 0]
    _, sv, vt = np.linalg.svd(used * w[:, None], full_matrices=False)
    big = sv > (sv[0] * 1e-8 if sv.size else 0.0)
    proj = used @ (vt[big].T / sv[big])  # rows b_v' V S^-1: var(e_v) = |row|^2
    var_e = np.sum(proj**2, axis=1)
    return e, 2.0 * e**2 / np.maximum(var_e, 1e-300 * e**2)


def noisy_visits(lag0: np.ndarray, n: np.ndarray, line: np.ndarray, acf: np.ndarray,
                 level: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Is a visit's scatter far beyond the others'? For every visit (``lag0`` (V, 3) its sum of squared detrended
    residuals, ``n`` (V,) samples, ``line`` (V,) a line in time removed too) and axis: the ratio (V, 3) of its
    variance to what the visits' variances make it expected to be, and the p-value (V, 3) of that ratio under the noise.

    A visit's variance is its sum of squares over E = the sum expected per unit variance after the detrending under
    the floor's autocorrelation ``acf`` (3, L + 1) (``detrended_lag_matrix``). Under the noise the sum is about
    sigma^2 chi^2(nu) / nu E with the effective degrees of freedom of a variance from correlated samples,
    nu = E / (1 + 2 sum_l rho_l^2) (Bartlett; on 29-sample visits with the ramps' autocorrelation its tail holds to
    1e-5). What it is expected to be is fitted to the visits' variances (``expected_visit_variance``) on ``level``
    (V, 3, B), what each visit's counts make of its variance (``visit_noise_levels``; (V,) one column; None: the same
    for every visit); that fit is an estimate too (its degrees of freedom nu_e), so the ratio is referred to
    F(nu, nu_e): read at 1e-5, the tail of chi^2(24) / 24 is 1.1-1.3 x too thin against a centre known to 2-3 %.
    One-sided: a quieter visit does not dominate the pooled floor."""
    lag = acf.shape[1] - 1
    kinds, kind = np.unique(np.column_stack([n, line]), axis=0, return_inverse=True)
    expect = np.array([detrended_lag_matrix(int(k), 0, lag, bool(h))[0] @ acf.T for k, h in kinds])  # (kinds, 3)
    E = np.maximum(expect[kind.ravel()], 1e-12)
    nu = np.maximum(E / (1.0 + 2.0 * np.sum(acf[:, 1:] ** 2, axis=1)), 1.0)
    var = lag0 / E
    basis = np.ones((len(var), 3, 1)) if level is None else (
        np.broadcast_to(level[:, None, None], (len(var), 3, 1)) if level.ndim == 1 else level)
    ratio, p = np.empty_like(var), np.empty_like(var)
    for j in range(3):
        e, nu_e = expected_visit_variance(var[:, j], nu[:, j], basis[:, j])
        ratio[:, j] = var[:, j] / e
        p[:, j] = stats.f.sf(ratio[:, j], nu[:, j], nu_e)
    return ratio, p


@dataclass
class SettlingTransient:
    """Settling transient after the table stops, and disturbance before it moves on, measured on the declared
    model's residual (m/s^2).

    The k-th sample after the start of a visit is compared with its mirror about a window of the visit's samples:
    the window [K, n - 2K) for the start (mirror: the (K + k)-th sample before the end), [2K, n - K) for the end
    (mirror: the (K + k)-th after the start), each sample referred to the window's mean. A sample and its mirror lie
    at the same distance from the window, so noise of any colour and a linear drift cancel, and the mirror is clear
    of both ends, so a start and an end disturbed alike do not cancel. The excess power, averaged over visits, is
    modelled as A^2 exp(-2 age/tau) (first-order chain), one tau for all axes, at the start (the transient after a
    table move) and, with the time counted back from the last sample, at the end (samples taken while the table
    already moves to the next pose: its reading changes late, or the chain is delayed against the reference). Each
    is detected at 3 standard errors on some axis (a disturbance of either sign adds power).
    """

    settle_s: float  # samples within this time (s) of a visit's first sample are not in the floor
    n_visits: int  # visits long enough to measure it
    n_dropped: int  # static samples left out of the floor (both ends)
    age_s: np.ndarray  # (K,) median time since the visit's first sample, s
    excess_rms: np.ndarray  # (K, 3) signed sqrt of the excess power (start over its mirror), m/s^2
    amplitude_mps2: np.ndarray  # (3,) A per axis at the first sample, m/s^2 (0 where none)
    tau_s: float  # time constant, s (an upper bound if not resolved; NaN if not detected)
    tau_resolved: bool  # the decay shows in at least two sample positions
    detected: bool  # the excess at the first sample is > 3 standard errors on some axis
    residual_after_settle_mps2: np.ndarray  # (3,) A exp(-settle_s/tau): what may still reach the floor
    # the end of a visit, as above with the sign of the excess reversed and the time counted back from the last sample
    end_age_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (K,) median time before the last sample, s
    end_excess_rms: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (K, 3) m/s^2
    end_amplitude_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) at the last sample, m/s^2
    end_tau_s: float = np.nan
    end_tau_resolved: bool = False
    end_detected: bool = False  # the excess of the last sample over the first is > 3 standard errors on some axis
    end_settle_s: float | None = None  # samples within this time (s) of a visit's last sample are not in the floor
    end_n_dropped: int = 0  # of n_dropped, those left out at the end of a visit
    end_residual_after_settle_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def _end_first(self) -> np.ndarray:
        return self.end_excess_rms[0] if len(self.end_excess_rms) else np.zeros(3)

    @staticmethod
    def _decay(tau_s: float, resolved: bool, when: str) -> str:
        return (f"time constant {tau_s:.3g} s" if resolved else
                f"gone by the {when} sample (time constant <= {tau_s:.3g} s, not resolved by the sample rate)")

    def end_summary(self) -> str:
        """The end-of-visit disturbance in one sentence (empty without one)."""
        if not self.end_detected:
            return ""
        return f"{self._end_sentence()}; {self.end_n_dropped} samples at the ends of visits are left out of the noise floor"

    def _end_sentence(self) -> str:
        return (f"ends of visits disturbed: the table moves before its reading changes, or the chain is delayed against "
                f"the reference: amplitude {_fmt3(self.end_amplitude_mps2)} m/s^2 (x/y/z, at the last sample of a visit, "
                f"above the noise), {self._decay(self.end_tau_s, self.end_tau_resolved, 'previous')} before the end")

    def summary(self) -> str:
        cut = ["the first of each visit" + (f" and those within {self.settle_s:.3g} s of it" if self.settle_s > 0 else "")]
        if self.end_settle_s is not None:
            cut.append("the last of each visit" + (f" and those within {self.end_settle_s:.3g} s of it"
                                                   if self.end_settle_s > 0 else ""))
        drop = f"{self.n_dropped} samples ({', '.join(cut)}) are left out of the noise floor"
        if not self.detected:
            first = self.excess_rms[0] if len(self.excess_rms) else np.zeros(3)
            where = "first sample" if self.end_detected else "first or the last sample"
            out = (f"no settling transient above the noise at the {where} of a visit (excess "
                   f"{_fmt3(first)} m/s^2" + ("" if self.end_detected else
                                             f" at the first, {_fmt3(self._end_first())} m/s^2 at the last")
                   + f", {self.n_visits} visits)")
        else:
            out = (f"settling transient after a table move: amplitude {_fmt3(self.amplitude_mps2)} m/s^2 (x/y/z, at the "
                   f"first sample of a visit, above the noise), {self._decay(self.tau_s, self.tau_resolved, 'next')}, "
                   f"{self.n_visits} visits")
        if self.end_detected:
            out += "; " + self._end_sentence()
        return f"{out}; {drop}"


def _decay_fit(P: np.ndarray, SE: np.ndarray, age: np.ndarray, dt: float) -> tuple[np.ndarray, float, bool, bool]:
    """A first-order decay A^2 exp(-2 age/tau) fitted to an excess power ``P`` (K, 3) (m/s^2)^2 with standard errors
    ``SE`` at ages ``age`` (K,) s: (A (3,) m/s^2, tau s, tau resolved, detected). Detected: P > 3 SE at age 0 on
    some axis; resolved: also at the next position (else tau is bounded by the detection limit there)."""
    signif = P > 3 * SE
    detected = bool(np.any(signif[0]))
    amp, tau, resolved = np.zeros(3), np.nan, False
    if not detected:
        return amp, tau, resolved, detected
    resolved = bool(len(P) > 1 and np.any(signif[1]))
    if resolved:
        best = (np.inf, np.nan, np.zeros(3))
        for tau_try in np.geomspace(dt / 20, max(age[-1], dt) * 5, 300):
            f = np.exp(-2 * age / tau_try)
            w = 1.0 / SE**2
            a2 = np.clip(np.sum(w * f[:, None] * P, axis=0) / np.sum(w * f[:, None] ** 2, axis=0), 0, None)
            sse = float(np.sum(w * (P - f[:, None] * a2[None, :]) ** 2))
            if sse < best[0]:
                best = (sse, tau_try, a2)
        tau, amp = float(best[1]), np.sqrt(best[2])
    else:
        amp = np.sqrt(np.clip(P[0], 0, None))
        if len(P) > 1:  # below the detection limit one sample later: bound tau
            ratio = float(np.max(np.clip(P[0], 0, None) / (3 * SE[1])))
            tau = float((age[1] - age[0]) / max(0.5 * np.log(max(ratio, 1.0 + 1e-9)), 1e-9))
        else:
            tau = dt
    return amp, tau, resolved, detected


def settling_transient(res: np.ndarray, t_s: np.ndarray, groups: np.ndarray, rows: np.ndarray,
                       max_window_s: float = MAX_SETTLE_S) -> SettlingTransient:
    """Measure the settling transient and the end-of-visit disturbance (see ``SettlingTransient``) from a residual
    (N, 3) m/s^2.

    ``rows``: static samples of the visits (time-ordered, visits contiguous). Sample positions
    k = 0 .. K-1 with K covering ``max_window_s`` (s) plus one sample, at most a third of the median visit;
    visits shorter than 2 K + 1 samples (no middle sample left to refer to) are not used. The k-th sample from
    the start and the k-th from the end lie at the same distance from the middle whatever its length, so a
    visit one sample shorter than 3 K counts as well (it was left out: with jittered visit lengths, every
    visit shorter than the median). The start is fitted to the positive excess, the end to the negative one
    (``_decay_fit``). ``settle_s``, ``end_settle_s`` and the counts dropped are left unset (set by the caller once
    the windows are chosen).
    """
    r = rows & finite_rows(res)
    idx = np.flatnonzero(r)
    empty = SettlingTransient(0.0, 0, 0, np.zeros(0), np.zeros((0, 3)), np.zeros(3), np.nan, False, False, np.zeros(3))
    if idx.size < 9:
        return empty
    g = groups[idx]
    first = np.r_[True, g[1:] != g[:-1]]
    vid = np.cumsum(first) - 1  # contiguous block number
    length = np.bincount(vid)
    start = np.flatnonzero(first)
    pos = np.arange(len(idx)) - start[vid]
    rpos = length[vid] - 1 - pos
    dts = np.diff(t_s[idx])[~first[1:]]
    dt = float(np.median(dts)) if dts.size else 1.0
    K = int(min(np.ceil(max_window_s / max(dt, 1e-12)) + 1, np.median(length) // 3))
    if K < 1:
        return empty
    ok_v = length >= 2 * K + 1
    if ok_v.sum() < 3:
        return empty
    Kv = np.minimum(K, (length - 1) // 3)  # positions used at each end of a visit: a middle is left between mirrors
    x = res[idx]
    t = t_s[idx]
    last = start + length - 1
    nv = len(length)

    def window_mean(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:  # per visit, positions lo <= pos < length - hi
        w = ok_v[vid] & (pos >= lo[vid]) & (rpos >= hi[vid])
        c = np.maximum(np.bincount(vid[w], minlength=nv), 1).astype(float)
        return np.stack([np.bincount(vid[w], weights=x[w, j], minlength=nv) for j in range(3)], axis=1) / c[:, None]

    # each end is compared with the samples mirrored about a window that ends K_v samples before the other end: the
    # same distance from the window (noise of any colour and a linear drift cancel), away from both ends' disturbances
    d_s = x - window_mean(Kv, 2 * Kv)[vid]  # the start against [K_v, n - 2 K_v)
    d_e = x - window_mean(2 * Kv, Kv)[vid]  # the end against [2 K_v, n - K_v)
    ages, end_ages, start_excess, end_excess = [], [], [], []

    def excess(near: np.ndarray, far: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        diff = d[near] ** 2 - d[far] ** 2  # visits in the same order in both
        if len(diff) == 0:
            return np.zeros(3), np.full(3, np.inf)
        return diff.mean(axis=0), (diff.std(axis=0, ddof=1) / np.sqrt(len(diff)) if len(diff) > 1 else np.full(3, np.inf))

    vs = np.flatnonzero(ok_v)  # the visits used, in order: one sample of each at every position k
    for k in range(K):
        v = vs[Kv[vs] > k]
        near_s, far_s = start[v] + k, last[v] - (Kv[v] + k)  # pos == k and rpos == K_v + k
        near_e, far_e = last[v] - k, start[v] + (Kv[v] + k)  # rpos == k and pos == K_v + k
        start_excess.append(excess(near_s, far_s, d_s))
        end_excess.append(excess(near_e, far_e, d_e))
        ages.append(float(np.median(t[near_s] - t[start[v]])) if v.size else np.nan)
        end_ages.append(float(np.median(t[last[v]] - t[near_e])) if v.size else np.nan)
    (P, SE), (Pe, SEe) = (np.array(e).transpose(1, 0, 2) for e in (start_excess, end_excess))
    age, end_age = np.array(ages), np.array(end_ages)
    amp, tau, resolved, detected = _decay_fit(P, np.maximum(SE, 1e-300), age, dt)
    e_amp, e_tau, e_resolved, e_detected = _decay_fit(Pe, np.maximum(SEe, 1e-300), end_age, dt)
    return SettlingTransient(0.0, int(ok_v.sum()), 0, age, np.sign(P) * np.sqrt(np.abs(P)), amp, tau, resolved, detected,
                             np.zeros(3), end_age, np.sign(Pe) * np.sqrt(np.abs(Pe)), e_amp, e_tau, e_resolved, e_detected)


def settle_window(st: SettlingTransient, sigma: np.ndarray, end: bool = False) -> float:
    """Time (s) after a visit's first sample (``end``: before its last) that the floor leaves out: where the
    measured transient A exp(-t/tau) falls below ``SETTLE_NOISE_FRACTION`` x the noise ``sigma`` (3,) m/s^2, capped
    at ``MAX_SETTLE_S``; 0 (only the first, or last, sample) without a detected transient.

    Only a resolved decay (significant at two positions or more) is extrapolated with its fitted tau: the fit is then
    what says how far below the detection limit the transient still reaches (with tau 0.12 s at 50 Hz it is
    significant for 0.42 s but above a tenth of the noise for 0.72 s). An unresolved one (significant at the first
    position only) has just an upper bound on tau, which grows without limit as the excess at the first position
    nears its detection limit (a chance 3-standard-error excess on a clean recording trimmed ~1 s, nearly whole 1 s
    visits): its window is the positions where it is significant, the first (or last) sample, always dropped."""
    detected, tau, amp, resolved = ((st.end_detected, st.end_tau_s, st.end_amplitude_mps2, st.end_tau_resolved) if end
                                    else (st.detected, st.tau_s, st.amplitude_mps2, st.tau_resolved))
    if not detected or not resolved or not np.isfinite(tau) or tau <= 0:
        return 0.0
    ratio = float(np.max(amp / np.maximum(sigma, 1e-12)))
    if ratio <= SETTLE_NOISE_FRACTION:
        return 0.0
    return float(min(tau * np.log(ratio / SETTLE_NOISE_FRACTION), MAX_SETTLE_S))


def _first_kept_age(window_s: float, resolved: bool, age_s: np.ndarray) -> float:
    """Age (s, from the visit's first or last sample) of the first sample a settle window keeps, as far as the
    transient's measurement says: the window itself, or for an unresolved transient (window 0: the first, or last,
    sample dropped) the next position, where its time constant was bounded."""
    if resolved or len(age_s) < 2 or not np.isfinite(age_s[1] - age_s[0]):
        return float(window_s)
    return float(max(window_s, age_s[1] - age_s[0]))


def _fmt3(v: np.ndarray) -> str:
    return " / ".join(f"{x:.3f}" for x in v)


@dataclass
class FloorMeasurement:
    """The noise floor a residual is judged against and how it was measured: ``noise`` (3,) m/s^2 per axis, its model
    (``VisitNoise``), the settled samples it is worked out on (``settled`` (N,)), the windows left out at the start
    (``settle_s``) and end (``end_s``, None: none) of each visit, the settling transient, and a periodic disturbance
    of the visits (when found, ``noise`` is the floor without it)."""

    noise: np.ndarray
    noise_model: VisitNoise
    settled: np.ndarray
    settle_s: float
    end_s: float | None
    settling: SettlingTransient
    disturbance: PeriodicDisturbance


def measure_floor(data: DiagnosisData, res0: np.ndarray, rows: np.ndarray, settle_s: float | None,
                  side_by_side: bool) -> FloorMeasurement:
    """The noise floor of the declared model's residual ``res0`` (N, 3) m/s^2 on the samples ``rows`` (fitted, at a
    pose): the scatter within visits over settled samples (``within_visit_noise``), the settling windows by the rule
    of ``SETTLE_NOISE_FRACTION`` at either end (``settle_s`` given: the start is fixed; the end is trimmed only where
    it is measured disturbed), a periodic disturbance named and taken out (``periodic_disturbance``). With
    ``side_by_side`` the settling transient is measured on a thread beside the first floor."""
    groups = data.group
    settling_later = beside(settling_transient, res0, data.t_s, groups, rows, thread=side_by_side)
    auto_start = settle_s is None
    settle_s = 0.0 if settle_s is None else float(settle_s)

    def floor(start_s: float, stop_s: float | None) -> tuple[float, float | None, VisitNoise]:
        return start_s, stop_s, within_visit_noise(res0, groups, settled_mask(data.t_s, groups, rows, start_s, stop_s),
                                                   data.t_s, reference=data.ref, axis_counts=data.xyz)

    # the last floor worked out, at (settle_s, end_s): meanwhile the transient is measured, the first one with the end
    # kept (as it is unless the end is disturbed)
    floor_at: tuple[float, float | None, VisitNoise] | None = floor(settle_s, None) if side_by_side else None
    settling = settling_later.result()
    end_s = 0.0 if settling.end_detected else None
    for _ in range(4):
        if not auto_start and end_s is None:
            break
        if floor_at is None or floor_at[:2] != (settle_s, end_s):
            floor_at = floor(settle_s, end_s)
        sigma = floor_at[2].sigma
        grew = False
        if auto_start and (nxt := settle_window(settling, sigma)) > settle_s * (1 + 1e-3):
            settle_s, grew = nxt, True
        if end_s is not None and (nxt := settle_window(settling, sigma, end=True)) > end_s * (1 + 1e-3):
            end_s, grew = nxt, True
        if not grew:
            break
    settled = settled_mask(data.t_s, groups, rows, settle_s, end_s)
    # the windows that did not grow are those of the last floor worked out: that floor, not the same one again
    noise_model = (floor_at[2] if floor_at is not None and floor_at[:2] == (settle_s, end_s)
                   else within_visit_noise(res0, groups, settled, data.t_s, reference=data.ref,
                                           axis_counts=data.xyz))
    noise = noise_model.sigma
    if not np.all(np.isfinite(noise)) or np.any(noise <= 0):
        raise ValueError(f"no noise floor: {int(settled.sum())} settled samples (every visit shorter than "
                         f"{settle_s:.3g} s plus one sample?); lower settle_s")
    # a periodic disturbance during the visits (a table that sways, a fan) is no noise of the sensor: named, and the
    # floor is the scatter without it (its floor with it reported beside: PeriodicDisturbance.floor_with_lines)
    disturbance = find_periodic_disturbance(res0, data.t_s, groups, data.run_id, settled)
    if disturbance.found:
        disturbance.floor_with_lines = noise
        noise_model = within_visit_noise(res0 - disturbance.model(data.t_s, data.run_id), groups, settled, data.t_s,
                                         reference=data.ref, axis_counts=data.xyz)
        noise = noise_model.sigma
    settling.settle_s, settling.n_dropped = float(settle_s), int((rows & ~settled).sum())
    settling.end_settle_s = end_s
    settling.end_n_dropped = int((settled_mask(data.t_s, groups, rows, settle_s) & ~settled).sum())
    # what may still reach the floor: the decay at the window's edge, for an unresolved one (window: the first, or
    # last, sample) its bound at the next position, the first kept
    if settling.detected and np.isfinite(settling.tau_s) and settling.tau_s > 0:
        kept = _first_kept_age(settle_s, settling.tau_resolved, settling.age_s)
        settling.residual_after_settle_mps2 = settling.amplitude_mps2 * np.exp(-max(kept, 1e-12) / settling.tau_s)
    if end_s is not None and np.isfinite(settling.end_tau_s) and settling.end_tau_s > 0:
        kept = _first_kept_age(end_s, settling.end_tau_resolved, settling.end_age_s)
        settling.end_residual_after_settle_mps2 = (settling.end_amplitude_mps2
                                                   * np.exp(-max(kept, 1e-12) / settling.end_tau_s))
    return FloorMeasurement(noise, noise_model, settled, settle_s, end_s, settling, disturbance)
