"""ADC codes that hold whole visits and carry the residual: a code of the board's ADC that swallows a range of
inputs (``diagnose``).

A successive-approximation ADC such as the ESP32's has codes of unequal width (differential non-linearity, worst at
the major carry transitions of its capacitor array): a *wide* code reads one value over an input range several
counts wide, and the codes it takes the range from are never read (missing codes). A user report on the ESP32
shows one value returned over a whole range of input voltages (esp32.com forum, "Strange ADC Measurements",
viewtopic.php?t=18674); on the measured series (``../shared/data/measured``) the y channel reads 1535 (0x5FF, the
transition to 0x600) through five whole visits while the codes 1536-1543 never occur.

A reading at such a code is censored: the input sat anywhere across the code's width, so eq. 28 sees one value where
the input differed between visits, and the output of those visits is off by up to the width times the sensitivity.
No calibration term restores it; what can be done is to find the visits, say how far off they are, and measure the
code widths (a slow ramp of the input across the code: the histogram of the codes read gives each code's width).

Found in two steps. A visit is *held* on a channel when at least ``HELD_SHARE`` of its judged samples read one code
(a visit whose input sat near the code's edge reads the next code now and then). Holding alone
proves little (a quiet channel holds visits by chance), so the held visits of each (channel, code) are then tested
for what matters: do they carry the residual? The sum of their ``score`` (the caller's measure of how far a visit's
output is off) against the sums of as many visits drawn at random (``PERMUTATIONS`` draws, seeded: the same answer
every run); the sum, not ranks, because a wide code puts the visits whose input sat near its far edge far off and
leaves those near the code itself alone. Bonferroni over the (channel, code) pairs that hold any visit (which
visits are held does not depend on the residual, so the family is fixed before the test). One visit alone cannot
pass unless the campaign has hundreds of visits: its p-value is at least one over the number of visits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fbg_accel_driver.adc_code_table import ADC_CODES, AdcCodeTable, pattern_edges, pattern_offsets

CHANNEL_NAMES = ("ref", "x", "y", "z")
MIN_VISIT_SAMPLES = 3  # a visit shorter than this does not show a held code
HELD_SHARE = 0.9  # a visit is held on a code when at least this share of its samples read it
PERMUTATIONS = 20_000  # random draws of the test (its smallest p-value is 1 / (PERMUTATIONS + 1))


@dataclass
class HeldCode:
    """One ADC code whose whole visits carry the residual (see the module docstring)."""

    channel: str  # "ref", "x", "y" or "z"
    code: int  # the ADC code (counts)
    visits: np.ndarray  # (k,) labels of the visits held on it
    n_samples: int  # their judged samples
    n_at_code: int  # of those, the samples that read the code
    p_value: float  # of their summed scores against as many visits drawn at random
    sigma_counts: float  # the channel's within-visit noise (median standard deviation of a visit's counts)
    missing_above: tuple[int, int] | None  # (first, last) codes just above never read in the recording, or None
    missing_below: tuple[int, int] | None  # likewise just below
    worst_offset: np.ndarray | None = None  # (3,) m/s^2: per axis, the visit mean residual largest in magnitude (caller)
    rmse_without: np.ndarray | None = None  # (3,) m/s^2: the held-out RMSE without these visits (set by the caller)

    def sentence(self) -> str:
        """The finding in one sentence (the report's warning)."""
        gaps = [f"codes {r[0]}-{r[1]}" if r[1] > r[0] else f"code {r[0]}"
                for r in (self.missing_below, self.missing_above) if r is not None]
        gap = f"; {' and '.join(gaps)} next to it never occur in the recording (missing codes)" if gaps else ""
        res = ("" if self.worst_offset is None else
               "; their visit means are off by up to " + " / ".join(f"{v:+.3f}" for v in self.worst_offset)
               + " m/s^2 (x/y/z)")
        if self.rmse_without is not None:
            res += "; without them the held-out RMSE is " + " / ".join(f"{v:.3f}" for v in self.rmse_without) + " m/s^2"
        return (f"ADC code {self.code} of channel {self.channel} holds {len(self.visits)} visit(s) ({self.n_at_code} of their "
                f"{self.n_samples} samples read it, where the channel's noise, {self.sigma_counts:.2g} counts rms within a "
                "visit, spreads a visit over several codes), "
                f"and these visits carry the residual (their summed offset against as many random visits: p = "
                f"{self.p_value:.2g}){gap}{res}: a "
                "wide code of the ADC (differential non-linearity) reads one value over a range of inputs, so these "
                "readings are censored and no calibration term restores them; measure the code widths with a slow ramp "
                "of that channel's input across the code (the histogram of the codes read), and take those visits' "
                "output as uncertain by that width")


def modal_codes(v: np.ndarray, starts: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the code read most often in each stretch ``v[s:s + k]`` of the whole-number counts ``v``, the smallest of
    those read equally often; how many samples read it), each (m,) for the stretches (``starts``, ``n``; each k > 0):
    ``np.unique(v[s:s + k], return_counts=True)``'s most counted value (the first ``argmax``) and count, for every
    stretch at once (one sort of the samples by stretch and code, not a sort per visit: some 10^4 calls at 10^6
    samples)."""
    n = np.asarray(n, dtype=np.intp)
    if len(n) == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=np.intp)
    seg = np.repeat(np.arange(len(n)), n)
    vals = v[np.arange(len(seg)) + np.repeat(np.asarray(starts, dtype=np.intp) - (np.cumsum(n) - n), n)]
    order = np.lexsort((vals, seg))
    sv, ss = vals[order], seg[order]
    run = np.flatnonzero(np.r_[True, (ss[1:] != ss[:-1]) | (sv[1:] != sv[:-1])])  # each (stretch, code)'s first
    run_len = np.diff(np.r_[run, len(ss)])
    run_seg = ss[run]
    first = np.flatnonzero(np.r_[True, run_seg[1:] != run_seg[:-1]])  # each stretch's first run (every one has one)
    most = np.maximum.reduceat(run_len, first)
    top = np.flatnonzero(run_len == most[run_seg])  # runs at their stretch's most, in code order: the first of each
    top = top[np.r_[True, run_seg[top[1:]] != run_seg[top[:-1]]]]
    return sv[run[top]].astype(int), most


def _missing_run(present: np.ndarray, code: int, step: int, lo: int) -> tuple[int, int] | None:
    """(first, last) of the run of codes never read next to ``code`` on the side ``step`` (+1 above, -1 below), inside
    the channel's read range (``present``: a flag per code from ``lo``); None when the next code is read or the run
    reaches the end of that range."""
    c = code + step
    while 0 <= c - lo < len(present) and not present[c - lo]:
        c += step
    if c == code + step or not 0 <= c - lo < len(present):
        return None
    a, b = sorted((code + step, c - step))
    return a, b


def held_codes(counts: np.ndarray, groups: np.ndarray, rows: np.ndarray, score: np.ndarray,
               alpha: float = 0.01) -> list[HeldCode]:
    """(Channel, code) pairs whose held visits carry the residual (module docstring), most significant first.

    ``counts`` (N, C) raw ADC counts, a column per channel (``CHANNEL_NAMES`` when C = 4); ``groups`` (N,) visit
    labels; ``rows`` (N,) the samples to judge (settled static samples); ``score`` (N,) how far each sample's visit
    is off (constant within a visit, e.g. its mean residual over the floor; NaN: a visit not judged). Channels whose
    counts are not integers (averaged or converted data) are not judged. Every sample counts for the missing codes."""
    counts = np.asarray(counts, float)
    idx = np.flatnonzero(rows & np.isfinite(score))
    if len(idx) == 0:
        return []
    order = idx[np.argsort(groups[idx], kind="stable")]
    labels, starts, n = np.unique(groups[order], return_index=True, return_counts=True)
    keep = n >= MIN_VISIT_SAMPLES
    labels, starts, n = labels[keep], starts[keep], n[keep]
    visit_score = score[order][starts]
    candidates: list[tuple[int, int, np.ndarray, int, float]] = []  # channel, code, held visits, samples at code, sigma
    for j in range(counts.shape[1]):
        col = counts[:, j]
        v = col[order]
        if not np.all(np.isfinite(v)) or np.any(v != np.round(v)):
            continue
        codes, at_code = modal_codes(v, starts, n)
        held = at_code >= HELD_SHARE * n
        found = np.unique(codes[held])
        if not len(found):  # no code held a visit: the channel's noise is not asked for
            continue
        # the channel's noise, the median of its visits' standard deviations: worked out for a channel with a
        # candidate only (some 2500 visits at 10^6 samples, one call each)
        sigma = float(np.median([v[s:s + k].std() for s, k in zip(starts, n, strict=True)]))
        for code in found:
            at = np.flatnonzero(held & (codes == code))
            candidates.append((j, int(code), at, int(at_code[at].sum()), sigma))
    out = []
    rng = np.random.default_rng(0)
    for j, code, at, n_at, sigma in candidates:
        if len(at) == len(labels):
            continue
        # drawn with replacement (cheap for any number of visits; a wider null, so the p-value errs high)
        drawn = visit_score[rng.integers(0, len(labels), (PERMUTATIONS, len(at)))].sum(axis=1)
        p = (1.0 + float(np.sum(drawn >= visit_score[at].sum()))) / (PERMUTATIONS + 1.0)
        if p < alpha / len(candidates):
            col = counts[:, j]
            read = col[np.isfinite(col)].astype(np.int64)
            lo = int(read.min())
            present = np.zeros(int(read.max()) - lo + 1, bool)
            present[read - lo] = True
            name = CHANNEL_NAMES[j] if counts.shape[1] == len(CHANNEL_NAMES) else str(j)
            out.append(HeldCode(name, code, labels[at], int(n[at].sum()), n_at, p, sigma,
                                _missing_run(present, code, 1, lo), _missing_run(present, code, -1, lo)))
    return sorted(out, key=lambda h: h.p_value)


# ============================================================================ code widths (code-density estimate)
# IEEE Std 1241-2010 (section 4.1.6, the histogram or code-density test) measures each code's width as the share of
# samples read at it over the share a known input density would put there. A calibration campaign gives no ramp, but
# each visit is a still input with ~1-4 counts of noise: the visit's own smooth density (a line in time through its
# samples, Gaussian noise of one standard deviation per channel) is the known input density, fitted jointly with the
# widths by maximum likelihood. What a few hundred visits support is a width pattern periodic in the code (the ESP32's
# SAR ADC repeats its capacitor array's small-bit errors with a period of 16 codes: the measured series reads codes
# 16k 1.5-2.4x and 16k + 8 3-6x less often than an even spread), pooled over every code, plus codes that differ on
# their own (wide or missing), each tested against the pattern's expected count.
PERIOD = 16  # codes: the period of the width pattern
MIN_WIDTH_VISIT_SAMPLES = 4  # a visit with fewer samples tells nothing of a line through them and its noise
PIECE_SAMPLES = 24  # a longer visit is cut into pieces of about this many samples, each with its own line: a local
# smooth fit that follows a slow drift (bias instability, a slow ramp) where one line through minutes would not
ODD_ALPHA = 0.01  # family-wise level of the individual-code test (Bonferroni over the codes tested)
MAX_NEWTON_STEPS = 100  # the fit converges in ~10
NEWTON_TOL = 1e-4  # log-likelihood: a step that gains less ends the fit
SIGMA_FLOOR = 0.05  # counts: the least noise a piece is given
Z95 = 1.959963984540054  # two-sided 95 % normal quantile: the stated uncertainty of a width is its 95 % interval
# standard scores beyond which the normal CDF (scipy.special.ndtr) is exactly 0.0 (below -37.7) and exactly 1.0 (above
# 8.3) in double precision: a code whose two edges are both out of a sample's reach gets exactly 0.0 of it
CDF_ZERO_BELOW, CDF_ONE_ABOVE = -40.0, 10.0
EXPECTED_BLOCK = 4096  # samples whose probabilities are summed together before they are added to the total
P_FLOOR = 1e-300  # the least probability of a cell (its log stays finite)
LOG_SIGMA_RANGE = (-20.0, 5.0)  # the pieces' log noise parameters are clipped to this range (sigma - SIGMA_FLOOR)


def _cell(z_lo: np.ndarray, z_hi: np.ndarray) -> tuple[np.ndarray, ...]:
    """log P(z_lo <= Z < z_hi) for a standard normal Z, phi(z_lo)/P and phi(z_hi)/P (from the side with the smaller
    tail, so that cells far out keep their precision), and whether P is above its floor ``P_FLOOR`` (where it is not,
    P is held at the floor and does not move with the edges)."""
    from scipy.special import ndtr

    flip = z_lo > 0
    a = np.where(flip, -z_hi, z_lo)
    b = np.where(flip, -z_lo, z_hi)
    raw = ndtr(b) - ndtr(a)
    p = np.maximum(raw, P_FLOOR)
    c = 1.0 / np.sqrt(2.0 * np.pi)
    return np.log(p), c * np.exp(-0.5 * z_lo ** 2) / p, c * np.exp(-0.5 * z_hi ** 2) / p, raw > P_FLOOR


def _cell_curvature(z_lo: np.ndarray, z_hi: np.ndarray, g_lo: np.ndarray, g_hi: np.ndarray,
                    live: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Second derivatives of log P(z_lo <= Z < z_hi) (``_cell``) in (z_lo, z_hi): d2/dz_lo2, d2/dz_lo dz_hi,
    d2/dz_hi2, from the same ratios ``g_lo`` = phi(z_lo)/P and ``g_hi`` = phi(z_hi)/P as the first derivatives
    (-g_lo, g_hi); where P sits at its floor (``live`` False) only the densities move."""
    return z_lo * g_lo - live * g_lo ** 2, live * g_lo * g_hi, -z_hi * g_hi - live * g_hi ** 2


@dataclass
class _Visits:
    """One channel's samples of the visits judged: code, visit index, centred sample position within the visit."""

    code: np.ndarray  # (n,) int
    visit: np.ndarray  # (n,) int 0..V-1
    u: np.ndarray  # (n,) sample position minus the visit's mean position (samples)
    mean0: np.ndarray  # (V,) the piece's mean code (the origin of its level)
    n_visits: int  # pieces
    cluster: np.ndarray  # (n,) the visit label of each sample (pieces of one visit are not independent)


def pieces(groups: np.ndarray, rows: np.ndarray, piece: int = PIECE_SAMPLES) -> np.ndarray:
    """Labels (N,) of the pieces (-1: not used): each visit's samples among ``rows`` cut, in time order, into
    consecutive pieces of ``piece`` samples or a few more (a visit of up to 2 ``piece`` - 1 samples is one piece)."""
    out = np.full(len(groups), -1, np.int64)
    idx = np.flatnonzero(rows)
    idx = idx[np.argsort(groups[idx], kind="stable")]
    _, starts, n = np.unique(groups[idx], return_index=True, return_counts=True)
    pos = np.arange(len(idx)) - np.repeat(starts, n)  # position within the visit
    k = np.maximum(n // piece, 1)  # pieces of the visit
    within = np.minimum(pos // piece, np.repeat(k, n) - 1)
    out[idx] = np.repeat(np.cumsum(k) - k, n) + within
    return out


def _visits_of(col: np.ndarray, groups: np.ndarray, rows: np.ndarray, clusters: np.ndarray | None = None) -> _Visits:
    """The pieces (``pieces``) of at least ``MIN_WIDTH_VISIT_SAMPLES`` samples of ``col`` among ``rows``, each sample
    with its visit label for the clustered covariance (``clusters``, default ``groups``)."""
    visits = groups if clusters is None else clusters
    groups = pieces(groups, rows & np.isfinite(col))
    idx = np.flatnonzero(groups >= 0)
    idx = idx[np.argsort(groups[idx], kind="stable")]
    _, inv, n = np.unique(groups[idx], return_inverse=True, return_counts=True)
    keep = n[inv] >= MIN_WIDTH_VISIT_SAMPLES
    idx, inv = idx[keep], inv[keep]
    _, visit = np.unique(inv, return_inverse=True)
    v_n = np.bincount(visit).astype(float)
    pos = np.arange(len(idx), dtype=float)  # positions in time order within a visit (idx is stably sorted)
    u = pos - (np.bincount(visit, pos) / v_n)[visit]
    code = col[idx].astype(np.int64)
    return _Visits(code, visit, u, np.bincount(visit, code.astype(float)) / v_n, len(v_n), visits[idx])


def _local_inverse(h_ll: np.ndarray) -> np.ndarray:
    """The inverse of each piece's local block (V, L, L); a block that is not positive definite (a piece whose line
    or noise is not determined) gives zeros: it adds nothing."""
    ok = np.all(np.linalg.eigvalsh(h_ll) > 1e-10, axis=1)
    out = np.zeros_like(h_ll)
    if ok.any():
        out[ok] = np.linalg.inv(h_ll[ok])
    return out


def _schur(h_gg: np.ndarray, b: np.ndarray, h_ll: np.ndarray) -> np.ndarray:
    """H_gg - H_gl H_ll^-1 H_lg for the arrow-shaped Hessian (``_WidthModel._hessian_parts``)."""
    return h_gg - np.einsum("gvk,vkl,hvl->gh", b, _local_inverse(h_ll), b)


def _arrow_solve(h_gg: np.ndarray, b: np.ndarray, h_ll: np.ndarray, g_g: np.ndarray, g_l: np.ndarray) -> np.ndarray:
    """The Newton step H^-1 g for the arrow-shaped Hessian (global block, a local block per piece; ``g_l`` (V, L)),
    as one vector (global, then the local parameters kind by kind)."""
    inv = _local_inverse(h_ll)
    schur = h_gg - np.einsum("gvk,vkl,hvl->gh", b, inv, b)
    d_g = np.linalg.solve(schur, g_g - np.einsum("gvk,vk->g", b, np.einsum("vkl,vl->vk", inv, g_l)))
    d_l = np.einsum("vkl,vl->vk", inv, g_l - np.einsum("gvk,g->vk", b, d_g))
    return np.concatenate([d_g, d_l.T.ravel()])


class _WidthModel:
    """Negative log-likelihood of one channel's pieces under a periodic width pattern. Parameters: the pattern's
    log-weights a[1:] (a[0] fixed at 0: the pattern is P softmax(a)); then, per piece, its level offset, slope and
    log noise (sigma = SIGMA_FLOOR + exp: a piece that reads one code throughout has no noise to measure)."""

    L = 3  # local parameters per piece

    def __init__(self, vis: _Visits, period: int) -> None:
        self.vis, self.P = vis, period
        q, self.r = np.divmod(vis.code, period)
        self.base = period * q.astype(float) - 0.5
        self.V = vis.n_visits
        self.G = period - 1
        self.k = (period - np.arange(period) - 0.5) / period  # d shift / d w_s

    def unpack(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(pattern w (P,), per piece: sigma, level offset, slope)."""
        G, V = self.G, self.V
        a = np.concatenate([[0.0], theta[:G]])
        e = np.exp(a - a.max())
        loc = theta[G:].reshape(self.L, V)
        return self.P * e / e.sum(), SIGMA_FLOOR + np.exp(np.clip(loc[2], *LOG_SIGMA_RANGE)), loc[0], loc[1]

    def _terms(self, theta: np.ndarray) -> tuple[np.ndarray, ...]:
        """(w, sigma, each sample's sigma, log P, z_lo, z_hi, phi(z_lo)/P, phi(z_hi)/P, P above its floor)."""
        vis = self.vis
        w, sigma, dm, slope = self.unpack(theta)
        low, shift = pattern_offsets(w)
        e_lo = self.base + low[self.r] - shift
        m = vis.mean0[vis.visit] + dm[vis.visit] + slope[vis.visit] * vis.u
        sg = sigma[vis.visit]
        z_lo, z_hi = (e_lo - m) / sg, (e_lo + w[self.r] - m) / sg
        logp, g_lo, g_hi, live = _cell(z_lo, z_hi)
        return w, sigma, sg, logp, z_lo, z_hi, g_lo, g_hi, live

    def _grad_w(self, d_lo: np.ndarray, d_hi: np.ndarray) -> np.ndarray:
        """d logL / d w (P,) from each sample's d logp / d (lower, upper edge) ``d_lo``, ``d_hi`` (n,): a sample of
        residue r has its lower edge at ``base + low[r] - shift`` and its upper one ``w[r]`` above it."""
        s = d_lo + d_hi
        by_r = np.bincount(self.r, s, self.P)
        above = np.concatenate([np.cumsum(by_r[::-1])[::-1][1:], [0.0]])  # sum over the samples with r > s
        return above - s.sum() * self.k + np.bincount(self.r, d_hi, self.P)

    def _sample_scores_a(self, w: np.ndarray, sg: np.ndarray, g_lo: np.ndarray, g_hi: np.ndarray) -> np.ndarray:
        """d logp / d a[1:] of each sample (n, G)."""
        d_lo, d_hi = -g_lo / sg, g_hi / sg  # d logp / d edges
        s = d_lo + d_hi
        g_w = s[:, None] * ((np.arange(self.P)[None, :] < self.r[:, None]) - self.k[None, :])
        g_w[np.arange(len(s)), self.r] += d_hi
        return (w[None, :] * (g_w - (g_w @ w)[:, None] / self.P))[:, 1:]

    def nll(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        vis, V = self.vis, self.V
        w, sigma, sg, logp, z_lo, z_hi, g_lo, g_hi, _ = self._terms(theta)
        d_m = (g_lo - g_hi) / sg  # d logp / d m
        d_s = -(z_hi * g_hi - z_lo * g_lo) / sg  # d logp / d sigma
        g_w = self._grad_w(-g_lo / sg, g_hi / sg)
        g_a = w * (g_w - np.dot(g_w, w) / self.P)
        grad = np.concatenate([g_a[1:], np.bincount(vis.visit, d_m, V), np.bincount(vis.visit, d_m * vis.u, V),
                               np.bincount(vis.visit, d_s, V) * (sigma - SIGMA_FLOOR)])
        return -float(logp.sum()), -grad

    def cluster_scores(self, theta: np.ndarray, cluster: np.ndarray) -> np.ndarray:
        """The score in a[1:] summed over each cluster's samples (C, G): at the fit the pieces' own scores are zero, so
        these are the efficient scores of the robust (sandwich) covariance."""
        w, _, sg, _, _, _, g_lo, g_hi, _ = self._terms(theta)
        per = self._sample_scores_a(w, sg, g_lo, g_hi)
        _, c = np.unique(cluster, return_inverse=True)
        return np.stack([np.bincount(c, per[:, j]) for j in range(self.G)], axis=1)

    def start(self) -> np.ndarray:
        vis, V = self.vis, self.V
        su2 = np.bincount(vis.visit, vis.u ** 2, V)
        slope = np.where(su2 > 0, np.bincount(vis.visit, vis.u * vis.code, V) / np.maximum(su2, 1e-12), 0.0)
        res = vis.code - vis.mean0[vis.visit] - slope[vis.visit] * vis.u
        n = np.bincount(vis.visit, minlength=V)
        sd = np.sqrt(np.bincount(vis.visit, res ** 2, V) / np.maximum(n - 2, 1))
        return np.concatenate([np.zeros(self.G), np.zeros(V), slope, np.log(np.maximum(sd, 0.3))])

    def fit(self, theta: np.ndarray | None = None, fixed_global: bool = False) -> np.ndarray:
        """Maximum-likelihood parameters: damped Newton steps on the arrow-shaped Hessian (global block, a 3x3 block
        per piece; ``_hessian_parts``), from ``theta`` (default ``start()``); ``fixed_global``: the pattern held,
        only the pieces' own parameters fitted."""
        theta = self.start() if theta is None else theta.copy()
        f, g = self.nll(theta)
        lam = 1e-3
        G, V, L = self.G, self.V, self.L
        for _ in range(MAX_NEWTON_STEPS):
            h_gg, b, h_ll = self._hessian_parts(theta, fixed_global)
            g_g = 0.0 * g[:G] if fixed_global else g[:G]
            g_l = g[G:].reshape(L, V).T
            while True:
                step = _arrow_solve(h_gg + lam * np.eye(G), b, h_ll + lam * np.eye(L)[None], g_g, g_l)
                f_new, g_new = self.nll(theta - step)
                if np.isfinite(f_new) and f_new <= f:
                    break
                lam *= 10.0
                if lam > 1e12:
                    return theta
            theta, done = theta - step, f - f_new < NEWTON_TOL
            f, g = f_new, g_new
            lam = max(lam / 10.0, 1e-9)
            if done:
                break
        return theta

    def _hessian_parts(self, theta: np.ndarray, local_only: bool = False) -> tuple[np.ndarray, ...]:
        """The NLL's Hessian at ``theta``, analytic: the global block (G, G), its cross terms with the pieces'
        parameters (G, V, L), and each piece's block (V, L, L). ``local_only``: the global block is the identity and
        the cross terms zero (not worked out).

        A sample's log P depends on its cell's edges (e_lo, e_hi), its piece's line m = mean0 + dm + slope u and
        noise sigma; its second derivatives in these come from those in (z_lo, z_hi) (``_cell_curvature``). The edges
        depend on the pattern through the sample's residue r alone and are linear in w, so the global block and the
        cross terms are sums per residue (and per piece and residue) times d e / d a, plus the gradient in w times the
        softmax's second derivative. sigma = SIGMA_FLOOR + exp(clip(s)): the gradient takes d sigma / d s as
        sigma - SIGMA_FLOOR also where the clip holds s; the Hessian is the gradient's Jacobian, made symmetric (its
        two off-diagonal halves averaged where the clip makes them differ)."""
        vis, G, V, P = self.vis, self.G, self.V, self.P
        w, sigma, sg, _, z_lo, z_hi, g_lo, g_hi, live = self._terms(theta)
        f_ll, f_lh, f_hh = _cell_curvature(z_lo, z_hi, g_lo, g_hi, live)
        delta = g_lo - g_hi
        x_lo, x_hi = f_ll * z_lo + f_lh * z_hi, f_lh * z_lo + f_hh * z_hi
        inv2 = 1.0 / sg ** 2
        # second derivatives of log P per sample: (m, m), (m, sigma), (sigma, sigma), and d log P / d sigma
        mm = (z_lo * g_lo - z_hi * g_hi - live * delta ** 2) * inv2
        ms = (x_lo + x_hi - delta) * inv2
        ss = (z_lo * x_lo + z_hi * x_hi - 2.0 * (z_lo * g_lo - z_hi * g_hi)) * inv2
        d_s = -(z_hi * g_hi - z_lo * g_lo) / sg
        s_loc = theta[G + 2 * V:]
        e = sigma - SIGMA_FLOOR  # d sigma / d s as the gradient takes it
        inside = (s_loc > LOG_SIGMA_RANGE[0]) & (s_loc < LOG_SIGMA_RANGE[1])  # where the clip lets s move sigma
        e_cross = e * (1.0 + inside) / 2.0
        v, u = vis.visit, vis.u
        h_ll = np.empty((V, 3, 3))
        h_ll[:, 0, 0] = np.bincount(v, mm, V)
        h_ll[:, 0, 1] = h_ll[:, 1, 0] = np.bincount(v, mm * u, V)
        h_ll[:, 1, 1] = np.bincount(v, mm * u * u, V)
        h_ll[:, 0, 2] = h_ll[:, 2, 0] = np.bincount(v, ms, V) * e_cross
        h_ll[:, 1, 2] = h_ll[:, 2, 1] = np.bincount(v, ms * u, V) * e_cross
        h_ll[:, 2, 2] = (np.bincount(v, ss, V) * e ** 2 + np.bincount(v, d_s, V) * e) * inside
        h_ll = -h_ll
        if local_only:
            return np.eye(G), np.zeros((G, V, self.L)), h_ll
        # d e_lo / d w and d e_hi / d w of a sample of residue r (rows r), then in a[1:] through dw/da
        idx = np.arange(P)
        de_lo = (idx[None, :] < idx[:, None]) - self.k[None, :]
        jac = np.diag(w) - np.outer(w, w) / P  # d w / d a
        c_lo, c_hi = (de_lo @ jac)[:, 1:], ((de_lo + np.eye(P)) @ jac)[:, 1:]  # (P, G)
        r = self.r
        s_ll, s_lh, s_hh = (np.bincount(r, f * inv2, P)[:, None] for f in (f_ll, f_lh, f_hh))
        h_aa = c_lo.T @ (s_ll * c_lo) + c_lo.T @ (s_lh * c_hi) + c_hi.T @ (s_lh * c_lo) + c_hi.T @ (s_hh * c_hi)
        g_w = self._grad_w(-g_lo / sg, g_hi / sg)
        g_a = w * (g_w - np.dot(g_w, w) / P)
        h_aa += (np.diag(g_a) - (np.outer(w, g_a) + np.outer(g_a, w)) / P)[1:, 1:]  # gradient x d2 w / da2
        # cross terms: per (piece, residue) sums of the edges' second derivatives with m and sigma
        vr = v * P + r
        lo_m, hi_m = -g_lo * (z_lo - live * delta) * inv2, -g_hi * (live * delta - z_hi) * inv2
        lo_s, hi_s = (g_lo - x_lo) * inv2, (-g_hi - x_hi) * inv2
        b = np.empty((G, V, self.L))
        for j, (lo, hi) in enumerate(((lo_m, hi_m), (lo_m * u, hi_m * u), (lo_s, hi_s))):
            by_lo = np.bincount(vr, lo, V * P).reshape(V, P)
            by_hi = np.bincount(vr, hi, V * P).reshape(V, P)
            b[:, :, j] = (by_lo @ c_lo + by_hi @ c_hi).T
        b[:, :, 2] *= e_cross[None, :]
        return -0.5 * (h_aa + h_aa.T), -b, h_ll

    def profile_hessian(self, theta: np.ndarray) -> np.ndarray:
        """Hessian (G, G) of the NLL in a[1:] with the pieces' own parameters profiled out (the Schur complement)."""
        return _schur(*self._hessian_parts(theta))

    def expected(self, theta: np.ndarray, codes: np.ndarray) -> np.ndarray:
        """Expected samples at each code of ``codes`` (K,) under the fitted model: every sample's own density."""
        vis = self.vis
        w, sigma, dm, slope = self.unpack(theta)
        m = vis.mean0[vis.visit] + dm[vis.visit] + slope[vis.visit] * vis.u
        return expected_hits(pattern_edges(w, np.append(codes, codes[-1] + 1)), m, sigma[vis.visit])


def expected_hits(edges: np.ndarray, m: np.ndarray, sg: np.ndarray) -> np.ndarray:
    """Expected samples at each of K codes (K,): the sum over the samples of the probability that a normal reading
    of mean ``m`` (n,) and standard deviation ``sg`` (n,) falls between the code's edges ``edges`` (K + 1,),
    increasing, counts. Only the edges within a sample's reach (standard scores from ``CDF_ZERO_BELOW`` to
    ``CDF_ONE_ABOVE``, and one more on each side) are evaluated: beyond them the CDF is exactly 0.0 or 1.0, so every
    code left out would add an exact 0.0. Each code's sum runs over the samples in their order, a block of
    ``EXPECTED_BLOCK`` samples at a time, the blocks' sums added in turn: the figures of the (samples x codes) table
    of CDFs summed down its columns, bit for bit, at a cost in proportion to the samples times the codes each
    reaches (a few dozen) instead of all K."""
    from scipy.special import ndtr

    K = len(edges) - 1
    out = np.zeros(K)
    for b in range(0, len(m), EXPECTED_BLOCK):
        mb, sb = m[b:b + EXPECTED_BLOCK], sg[b:b + EXPECTED_BLOCK]
        first = np.maximum(np.searchsorted(edges, mb + CDF_ZERO_BELOW * sb, "left") - 1, 0)
        stop = np.minimum(np.searchsorted(edges, mb + CDF_ONE_ABOVE * sb, "right") + 1, K + 1)
        span = np.maximum(stop - first, 0)  # edges of each sample evaluated
        sample = np.repeat(np.arange(len(mb)), span)
        edge = np.arange(len(sample)) - np.repeat(np.cumsum(span) - span, span) + first[sample]
        cdf = ndtr((edges[edge] - mb[sample]) / sb[sample])
        inside = sample[1:] == sample[:-1]  # a code: two consecutive edges of one sample
        out += np.bincount(edge[:-1][inside], (cdf[1:] - cdf[:-1])[inside], K)  # in sample order, from 0.0
    return out


@dataclass
class OddCode:
    """A code read significantly more (wide) or less (narrow, missing) often than the width pattern predicts."""

    code: int
    hits: int  # samples read at it
    expected: float  # samples the pattern and the visits' densities put there
    width: float  # counts: its pattern width times hits / expected
    width_u95: float  # counts: half-width of its 95 % interval (Poisson count of hits)
    p_value: float  # two-sided Poisson, before the Bonferroni factor

    @property
    def kind(self) -> str:
        return "missing" if self.hits == 0 else ("wide" if self.hits > self.expected else "narrow")


@dataclass
class CodeWidths:
    """A channel's code widths from a recording (module section above); widths in counts of input (1 = nominal)."""

    channel: str
    period: int
    pattern: np.ndarray  # (P,) width of the codes k with k mod P = r; sums to P
    pattern_sd: np.ndarray  # (P,) their standard deviations (robust covariance clustered by visit)
    chi2: float  # Wald statistic (Hotelling's T^2) of the pattern against equal widths
    dof: int  # P - 1
    p_value: float  # of chi2 (F distribution: the covariance is estimated from the visits)
    sigma_counts: float  # the median noise of a sample about its piece's line (counts)
    n_samples: int
    n_visits: int
    codes: np.ndarray  # (K,) every code from the lowest to the highest read in the visits judged
    hits: np.ndarray  # (K,) samples read at each
    expected: np.ndarray  # (K,) samples the fitted model expects at each
    odd: list[OddCode]  # codes that differ from the pattern on their own (Bonferroni at ODD_ALPHA over the K codes)
    alpha: float = 0.01  # level of the pattern's test

    @property
    def pattern_found(self) -> bool:
        """The pattern differs from equal widths at level ``alpha`` (otherwise the table keeps the nominal widths)."""
        return self.p_value < self.alpha

    @property
    def pattern_u95(self) -> np.ndarray:
        """(P,) half-width of each pattern width's 95 % interval (counts): the uncertainty this module states."""
        return Z95 * self.pattern_sd

    def edges(self) -> np.ndarray:
        """(ADC_CODES + 1,) lower edge of every code (the last: the top code's upper edge), counts of input: the
        pattern's when found, else the nominal c - 0.5; a wide code next to a run of missing codes takes over the run
        (its interval spans them; they keep a zero width at the run's far end), the run's total width unchanged."""
        codes = np.arange(ADC_CODES + 1)
        e = pattern_edges(self.pattern, codes) if self.pattern_found else codes - 0.5
        missing = {o.code for o in self.odd if o.kind == "missing"}
        for o in self.odd:
            if o.kind != "wide":
                continue
            hi = o.code + 1
            while hi in missing:
                hi += 1
            e[o.code + 1:hi] = e[hi]  # missing codes above: zero width at the run's top
            lo = o.code - 1
            while lo in missing:
                lo -= 1
            e[lo + 2:o.code + 1] = e[lo + 1]  # missing codes below: zero width at the run's bottom
        return e

    def summary(self) -> str:
        """One paragraph: the pattern, its test, and the odd codes."""
        head = (f"channel {self.channel}: {self.n_samples} samples in {self.n_visits} visits, codes {self.codes[0]}-"
                f"{self.codes[-1]}, noise {self.sigma_counts:.2f} counts about each visit's line; width pattern (period "
                f"{self.period}) against equal widths: chi2 = {self.chi2:.1f} on {self.dof} dof, p = {self.p_value:.2g}"
                + (" (found)" if self.pattern_found else " (not found: nominal widths kept)"))
        odd = "; ".join(f"code {o.code} {o.kind} ({o.hits} read, {o.expected:.1f} expected, width {o.width:.2f} "
                        f"+- {o.width_u95:.2f})" for o in self.odd)
        return head + (f"; codes on their own: {odd}" if odd else "")


def _odd_codes(codes: np.ndarray, hits: np.ndarray, expected: np.ndarray, w: np.ndarray) -> list[OddCode]:
    from scipy.stats import poisson

    tested = expected > 0.5  # a code the model puts (almost) nothing at tells nothing
    p = np.ones(len(codes))
    e, h = expected[tested], hits[tested]
    p[tested] = np.minimum(1.0, 2.0 * np.minimum(poisson.sf(h - 1, e), poisson.cdf(h, e)))
    out = []
    for i in np.flatnonzero(p < ODD_ALPHA / max(int(tested.sum()), 1)):
        width = w[codes[i] % len(w)]
        out.append(OddCode(int(codes[i]), int(hits[i]), float(expected[i]), float(width * hits[i] / expected[i]),
                           float(width * Z95 * max(np.sqrt(hits[i]), 1.0) / expected[i]), float(p[i])))
    return out


def code_widths(col: np.ndarray, groups: np.ndarray, rows: np.ndarray, channel: str = "",
                period: int = PERIOD, alpha: float = 0.01, clusters: np.ndarray | None = None) -> CodeWidths:
    """The code widths of one channel (section above): ``col`` (N,) integer ADC counts, ``groups`` (N,) visit labels
    (a visit: a still or slowly moving input), ``rows`` (N,) the samples to use, in time order. Pieces near a code
    found odd on a first pass are left out of the pattern's second pass (a wide code holding a visit would bend the
    pattern). The pattern's covariance is the robust (sandwich) one, clustered by visit (``clusters`` (N,), default
    ``groups``): the samples of a visit are not independent (the TIA low-pass, bias instability), and a model that
    took them as independent would claim a pattern from noise. Raises ValueError when the counts are not integers
    or too few pieces remain."""
    col = np.asarray(col, float)
    use = rows & np.isfinite(col)
    if np.any(col[use] != np.round(col[use])):
        raise ValueError(f"channel {channel or '?'}: the counts are not integers (averaged or converted data): no ADC "
                         "codes to count")
    vis = _visits_of(col, groups, use, clusters)
    if vis.n_visits < 2 * period or len(np.unique(vis.cluster)) < 2 * period:
        raise ValueError(f"channel {channel or '?'}: {len(np.unique(vis.cluster))} visits ({vis.n_visits} pieces) of at "
                         f"least {MIN_WIDTH_VISIT_SAMPLES} samples; the width pattern needs at least {2 * period}")
    codes = np.arange(vis.code.min(), vis.code.max() + 1)
    if len(np.unique(vis.code)) < 2 * period:
        raise ValueError(f"channel {channel or '?'}: {len(np.unique(vis.code))} distinct codes read; the width pattern "
                         f"needs at least {2 * period} (each of its {period} widths seen at two codes)")
    hits = np.bincount(vis.code - codes[0], minlength=len(codes)).astype(float)
    model = _WidthModel(vis, period)
    theta = model.fit()
    expected = model.expected(theta, codes)  # of every piece (refitted below when the pattern is fitted again)
    odd = _odd_codes(codes, hits, expected, model.unpack(theta)[0])
    if odd:  # the pattern again without the pieces near an odd code
        _, sigma, dm, _ = model.unpack(theta)
        level = vis.mean0 + dm
        near = np.zeros(vis.n_visits, bool)
        for o in odd:
            near |= np.abs(level - o.code) < 3.0 * sigma + 1.0
        keep = ~near[vis.visit]
        if len(np.unique(vis.cluster[keep])) >= 2 * period:
            _, visit = np.unique(vis.visit[keep], return_inverse=True)
            sub = _Visits(vis.code[keep], visit, vis.u[keep], vis.mean0[~near], int((~near).sum()), vis.cluster[keep])
            model = _WidthModel(sub, period)
            theta = model.fit()
            expected = _expected_all(vis, theta, period, codes)
            odd = _odd_codes(codes, hits, expected, model.unpack(theta)[0])
    w, sigma = model.unpack(theta)[:2]
    G = period - 1
    h_inv = np.linalg.pinv(model.profile_hessian(theta))
    u = model.cluster_scores(theta, model.vis.cluster)
    n_c = len(u)
    a_cov = h_inv @ (u.T @ u) @ h_inv * (n_c / (n_c - 1.0))
    a = theta[:G]
    chi2 = float(a @ np.linalg.solve(a_cov, a))
    J = w[:, None] * (np.eye(period) - w[None, :] / period)  # d w / d a
    w_cov = J[:, 1:] @ a_cov @ J[:, 1:].T
    from scipy.stats import f as f_dist

    # Hotelling's T^2 with a covariance estimated from n_c clusters: F(G, n_c - G)
    p = float(f_dist.sf(chi2 * (n_c - G) / (G * (n_c - 1.0)), G, n_c - G))
    return CodeWidths(channel, period, w, np.sqrt(np.maximum(np.diag(w_cov), 0.0)), chi2, G, p,
                      float(np.median(sigma)), len(model.vis.code), n_c, codes, hits, expected, odd, alpha)


def _expected_all(vis: _Visits, theta_sub: np.ndarray, period: int, codes: np.ndarray) -> np.ndarray:
    """Expected counts of every piece under the pattern of ``theta_sub`` (a fit on a subset of the pieces), the
    pieces' own parameters refitted with the pattern held."""
    model = _WidthModel(vis, period)
    start = model.start()
    start[:period - 1] = theta_sub[:period - 1]
    return model.expected(model.fit(start, fixed_global=True), codes)


@dataclass
class RecordingWidths:
    """The code widths of a recording: each channel's own estimate (None where the channel cannot support one, with
    the reason) and the pattern pooled over every channel (one converter is multiplexed over them)."""

    channels: dict[str, CodeWidths | None]
    reasons: dict[str, str]  # why a channel has no estimate of its own
    pooled: CodeWidths | None

    def summary(self) -> list[str]:
        out = [w.summary() if w is not None else f"channel {name}: no estimate of its own ({self.reasons[name]})"
               for name, w in self.channels.items()]
        if self.pooled is not None:
            out.append(self.pooled.summary())
        return out


def recording_code_widths(counts: np.ndarray, groups: np.ndarray, rows: np.ndarray, alpha: float = 0.01,
                          per_channel: bool = True) -> RecordingWidths:
    """``code_widths`` of each channel of ``counts`` (N, 4): ref, x, y, z (``CHANNEL_NAMES``), and pooled over the
    channels read over two periods of codes or more (their pieces together, one pattern: the ESP32's channels share
    one converter, so the table applies it to every channel, the reference included). ``per_channel`` False:
    the pooled estimate alone (the channels' entries None)."""
    channels: dict[str, CodeWidths | None] = {}
    reasons = {}
    for j, name in enumerate(CHANNEL_NAMES[:counts.shape[1]]):
        if not per_channel:
            channels[name], reasons[name] = None, "not asked for"
            continue
        try:
            channels[name] = code_widths(counts[:, j], groups, rows, name, alpha=alpha)
        except ValueError as exc:
            channels[name], reasons[name] = None, str(exc).split(": ", 1)[-1]
    _, g = np.unique(groups, return_inverse=True)
    n_g = int(g.max()) + 1 if len(g) else 0
    # the channels whose readings spread over two periods of codes or more: a channel read over fewer codes (the
    # reference, ~20) cannot tell the widths from where its visits happen to sit, and would bend the pooled pattern
    wide = [j for j in range(counts.shape[1])
            if len(np.unique(counts[rows & np.isfinite(counts[:, j]), j])) >= 2 * PERIOD]
    try:
        if not wide:
            raise ValueError("no channel read two periods of codes or more")
        # one cluster per visit over the channels: their readings of one visit are not taken as independent
        pooled = code_widths(counts[:, wide].T.ravel(), np.concatenate([g + k * n_g for k in range(len(wide))]),
                             np.tile(rows, len(wide)), "pooled", alpha=alpha, clusters=np.tile(g, len(wide)))
    except ValueError as exc:
        pooled, reasons["pooled"] = None, str(exc).split(": ", 1)[-1]
    return RecordingWidths(channels, reasons, pooled)


def code_table(widths: RecordingWidths, provenance: dict[str, str | int | float]) -> AdcCodeTable:
    """The calibration's code-to-value table (ref, x, y, z): the pooled pattern on every channel when it was found
    (nominal widths otherwise), each channel's own wide codes with their missing runs folded in
    (``CodeWidths.edges``), with ``provenance`` and the tests behind it."""
    prov = dict(provenance)
    pooled = widths.pooled
    prov["pattern"] = ("not measured" if pooled is None else
                       ("found" if pooled.pattern_found else "not found, nominal widths") +
                       f" (pooled over the channels: chi2 {pooled.chi2:.1f} on {pooled.dof} dof, p {pooled.p_value:.2g}; "
                       f"{pooled.n_visits} visits)")
    rows = []
    for name in CHANNEL_NAMES:
        own = widths.channels.get(name)
        base = pooled if pooled is not None else own
        odd = own.odd if own is not None else []
        wide = [o.code for o in odd if o.kind == "wide"]
        if wide:
            prov[f"{name}_wide_codes"] = ", ".join(map(str, wide))
        if base is None:
            rows.append(np.arange(ADC_CODES + 1) - 0.5)
            continue
        rows.append(CodeWidths(**{**base.__dict__, "odd": odd}).edges())
    return AdcCodeTable(np.array(rows), prov)


def mapped_recording(rec, table: AdcCodeTable):
    """A copy of the recording ``rec`` whose counts are the centres of their codes' intervals (``table.map_counts``,
    the mapping the driver applies per frame): what the fit and the diagnosis see when a code table is given."""
    out = rec.select(np.arange(len(rec)))
    out.ref, out.xyz = table.map_counts(rec.ref, rec.xyz)
    return out
