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
        sd = np.array([v[s:s + k].std() for s, k in zip(starts, n, strict=True)])
        modal = [np.unique(v[s:s + k], return_counts=True) for s, k in zip(starts, n, strict=True)]
        codes = np.array([int(u[np.argmax(c)]) for u, c in modal])
        at_code = np.array([c.max() for _, c in modal])
        held = at_code >= HELD_SHARE * n
        for code in np.unique(codes[held]):
            at = np.flatnonzero(held & (codes == code))
            candidates.append((j, int(code), at, int(at_code[at].sum()), float(np.median(sd))))
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
ADC_CODES = 4096  # codes of the 12-bit converter (paper 3.5)
MIN_WIDTH_VISIT_SAMPLES = 4  # a visit with fewer samples tells nothing of a line through them and its noise
ODD_ALPHA = 0.01  # family-wise level of the individual-code test (Bonferroni over the codes tested)
MAX_NEWTON_STEPS = 100  # the fit converges in ~10
Z95 = 1.959963984540054  # two-sided 95 % normal quantile: the stated uncertainty of a width is its 95 % interval


def _pattern_edges(w: np.ndarray) -> tuple[np.ndarray, float]:
    """Lower edges within one period (P,) of a width pattern ``w`` (P,) summing to P, and the shift that makes the
    codes' centres sit on the codes on average over a period (no offset of the table as a whole)."""
    low = np.concatenate([[0.0], np.cumsum(w)[:-1]])
    shift = float(np.mean(low + w / 2.0)) - (len(w) - 1) / 2.0
    return low, shift


def pattern_edges(w: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """Lower edge (counts of input) of each code of ``codes`` under the periodic width pattern ``w`` (P,) summing to
    P: code c = P q + r reads inputs from ``P q + low[r] - shift - 0.5`` to that plus ``w[r]`` (equal widths: c - 0.5)."""
    w = np.asarray(w, float)
    low, shift = _pattern_edges(w)
    codes = np.asarray(codes, np.int64)
    q, r = np.divmod(codes, len(w))
    return len(w) * q + low[r] - shift - 0.5


def _log_cell(z_lo: np.ndarray, z_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """log P(z_lo <= Z < z_hi) for a standard normal Z, and phi(z_lo)/P, phi(z_hi)/P (from the side with the smaller
    tail, so that cells far out keep their precision)."""
    from scipy.special import ndtr

    flip = z_lo > 0
    a = np.where(flip, -z_hi, z_lo)
    b = np.where(flip, -z_lo, z_hi)
    p = np.maximum(ndtr(b) - ndtr(a), 1e-300)
    c = 1.0 / np.sqrt(2.0 * np.pi)
    return np.log(p), c * np.exp(-0.5 * z_lo ** 2) / p, c * np.exp(-0.5 * z_hi ** 2) / p


@dataclass
class _Visits:
    """One channel's samples of the visits judged: code, visit index, centred sample position within the visit."""

    code: np.ndarray  # (n,) int
    visit: np.ndarray  # (n,) int 0..V-1
    u: np.ndarray  # (n,) sample position minus the visit's mean position (samples)
    mean0: np.ndarray  # (V,) the visit's mean code (the origin of its level)
    n_visits: int


def _visits_of(col: np.ndarray, groups: np.ndarray, rows: np.ndarray) -> _Visits:
    idx = np.flatnonzero(rows & np.isfinite(col))
    idx = idx[np.argsort(groups[idx], kind="stable")]
    _, inv, n = np.unique(groups[idx], return_inverse=True, return_counts=True)
    keep = n[inv] >= MIN_WIDTH_VISIT_SAMPLES
    idx, inv = idx[keep], inv[keep]
    _, visit = np.unique(inv, return_inverse=True)
    v_n = np.bincount(visit).astype(float)
    pos = np.arange(len(idx), dtype=float)  # positions in time order within a visit (idx is stably sorted)
    u = pos - (np.bincount(visit, pos) / v_n)[visit]
    code = col[idx].astype(np.int64)
    return _Visits(code, visit, u, np.bincount(visit, code.astype(float)) / v_n, len(v_n))


def _local_inverse(h_mm: np.ndarray, h_sm: np.ndarray, h_ss: np.ndarray) -> tuple[np.ndarray, ...]:
    """The inverse of each visit's 2x2 block [[h_mm, h_sm], [h_sm, h_ss]] as (i_mm, i_sm, i_ss); a block that is
    not positive definite (a visit whose line is not determined) gives zeros (it adds nothing)."""
    det = h_mm * h_ss - h_sm ** 2
    ok = (det > 1e-12) & (h_mm > 0)
    inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    return h_ss * inv_det, -h_sm * inv_det, h_mm * inv_det


def _schur(h_gg: np.ndarray, b_m: np.ndarray, b_s: np.ndarray, h_mm: np.ndarray, h_sm: np.ndarray,
           h_ss: np.ndarray) -> np.ndarray:
    """H_gg - H_gl H_ll^-1 H_lg for the arrow-shaped Hessian (``_WidthModel._hessian_parts``)."""
    i_mm, i_sm, i_ss = _local_inverse(h_mm, h_sm, h_ss)
    return h_gg - ((b_m * i_mm) @ b_m.T + (b_m * i_sm) @ b_s.T + (b_s * i_sm) @ b_m.T + (b_s * i_ss) @ b_s.T)


def _arrow_solve(h_gg: np.ndarray, b_m: np.ndarray, b_s: np.ndarray, h_mm: np.ndarray, h_sm: np.ndarray,
                 h_ss: np.ndarray, g_g: np.ndarray, g_m: np.ndarray, g_s: np.ndarray) -> np.ndarray:
    """The Newton step H^-1 g for the arrow-shaped Hessian, as one vector (global, levels, slopes)."""
    i_mm, i_sm, i_ss = _local_inverse(h_mm, h_sm, h_ss)
    l_m, l_s = i_mm * g_m + i_sm * g_s, i_sm * g_m + i_ss * g_s  # D^-1 g_l
    d_g = np.linalg.solve(_schur(h_gg, b_m, b_s, h_mm, h_sm, h_ss), g_g - b_m @ l_m - b_s @ l_s)
    r_m, r_s = g_m - b_m.T @ d_g, g_s - b_s.T @ d_g
    return np.concatenate([d_g, i_mm * r_m + i_sm * r_s, i_sm * r_m + i_ss * r_s])


class _WidthModel:
    """Negative log-likelihood of one channel's visits under a periodic width pattern (parameters: the pattern's
    log-weights a (P; a[0] fixed at 0: the pattern is P softmax(a)), log sigma, each visit's level offset and slope)."""

    def __init__(self, vis: _Visits, period: int) -> None:
        self.vis, self.P = vis, period
        q, self.r = np.divmod(vis.code, period)
        self.base = period * q.astype(float) - 0.5
        self.V = vis.n_visits
        below = np.arange(period)[None, :] < self.r[:, None]  # (n, P): s < r
        self.below = below.astype(float)
        self.k = (period - np.arange(period) - 0.5) / period  # d shift / d w_s

    def unpack(self, theta: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
        P, V = self.P, self.V
        a = np.concatenate([[0.0], theta[:P - 1]])
        w = P * np.exp(a - a.max()) / np.exp(a - a.max()).sum()
        return w, float(np.exp(theta[P - 1])), theta[P:P + V], theta[P + V:]

    def nll(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        P, V, vis = self.P, self.V, self.vis
        w, sigma, dm, slope = self.unpack(theta)
        low, shift = _pattern_edges(w)
        e_lo = self.base + low[self.r] - shift
        e_hi = e_lo + w[self.r]
        m = vis.mean0[vis.visit] + dm[vis.visit] + slope[vis.visit] * vis.u
        z_lo, z_hi = (e_lo - m) / sigma, (e_hi - m) / sigma
        logp, g_lo, g_hi = _log_cell(z_lo, z_hi)
        d_m = (g_lo - g_hi) / sigma  # d logp / d m
        d_ls = -(z_hi * g_hi - z_lo * g_lo)  # d logp / d log sigma
        d_lo, d_hi = -g_lo / sigma, g_hi / sigma  # d logp / d edges
        s = d_lo + d_hi
        g_w = (s @ self.below) - s.sum() * self.k + np.bincount(self.r, d_hi, P)  # d logp / d w
        g_a = w * (g_w - np.dot(g_w, w) / P)  # through w = P softmax(a)
        grad = np.concatenate([g_a[1:], [d_ls.sum()], np.bincount(vis.visit, d_m, V),
                               np.bincount(vis.visit, d_m * vis.u, V)])
        return -float(logp.sum()), -grad

    def start(self) -> np.ndarray:
        vis = self.vis
        su2 = np.bincount(vis.visit, vis.u ** 2, self.V)
        slope = np.where(su2 > 0, np.bincount(vis.visit, vis.u * vis.code, self.V) / np.maximum(su2, 1e-12), 0.0)
        res = vis.code - vis.mean0[vis.visit] - slope[vis.visit] * vis.u
        dof = max(len(res) - 2 * self.V, 1)
        sigma = max(float(np.sqrt(np.sum(res ** 2) / dof)), 0.3)
        return np.concatenate([np.zeros(self.P - 1), [np.log(sigma)], np.zeros(self.V), slope])

    def fit(self, theta: np.ndarray | None = None, fixed_global: bool = False) -> np.ndarray:
        """Maximum-likelihood parameters: damped Newton steps on the arrow-shaped Hessian (global block, 2x2 per
        visit; ``_hessian_parts``), from ``theta`` (default ``start()``); ``fixed_global``: the pattern and noise
        held, only the visits' levels and slopes fitted."""
        theta = self.start() if theta is None else theta.copy()
        f, g = self.nll(theta)
        lam = 1e-3
        G, V = self.P, self.V
        for _ in range(MAX_NEWTON_STEPS):
            h_gg, b_m, b_s, h_mm, h_sm, h_ss = self._hessian_parts(theta)
            g_g = g[:G]
            if fixed_global:
                b_m, b_s, h_gg, g_g = 0.0 * b_m, 0.0 * b_s, np.eye(G), 0.0 * g_g
            while True:
                step = _arrow_solve(h_gg + lam * np.eye(G), b_m, b_s, h_mm + lam, h_sm, h_ss + lam,
                                    g_g, g[G:G + V], g[G + V:])
                f_new, g_new = self.nll(theta - step)
                if np.isfinite(f_new) and f_new <= f:
                    break
                lam *= 10.0
                if lam > 1e12:
                    return theta
            theta, done = theta - step, f - f_new < 1e-10 * max(abs(f), 1.0)
            f, g = f_new, g_new
            lam = max(lam / 10.0, 1e-9)
            if done:
                break
        return theta

    def _hessian_parts(self, theta: np.ndarray, h: float = 1e-5) -> tuple[np.ndarray, ...]:
        """The NLL's Hessian at ``theta`` from its gradient by central differences: the global block (G, G), its
        cross terms with the visits' levels and slopes (G, V) each, and the 2x2 block of each visit ((V,) x 3). The
        visits' own parameters meet only their own visit, so the local block is read off by moving every visit's
        level (or slope) at once."""
        G, V = self.P, self.V

        def column(direction: np.ndarray) -> np.ndarray:
            return (self.nll(theta + h * direction)[1] - self.nll(theta - h * direction)[1]) / (2 * h)

        eye = np.eye(len(theta))
        cols_g = np.column_stack([column(eye[i]) for i in range(G)])  # (n_par, G)
        e_m, e_s = np.zeros(len(theta)), np.zeros(len(theta))
        e_m[G:G + V], e_s[G + V:] = 1.0, 1.0
        c_m, c_s = column(e_m), column(e_s)
        return (0.5 * (cols_g[:G] + cols_g[:G].T), cols_g[G:G + V].T, cols_g[G + V:].T,
                c_m[G:G + V], 0.5 * (c_m[G + V:] + c_s[G:G + V]), c_s[G + V:])

    def profile_hessian(self, theta: np.ndarray) -> np.ndarray:
        """Hessian (P, P) of the NLL in the global parameters (a[1:], log sigma) with the visits' levels and slopes
        profiled out (the Schur complement of the visits' blocks)."""
        return _schur(*self._hessian_parts(theta))

    def expected(self, theta: np.ndarray, codes: np.ndarray) -> np.ndarray:
        """Expected samples at each code of ``codes`` (K,) under the fitted model: every sample's own density."""
        vis = self.vis
        w, sigma, dm, slope = self.unpack(theta)
        m = vis.mean0[vis.visit] + dm[vis.visit] + slope[vis.visit] * vis.u
        edges = pattern_edges(w, np.append(codes, codes[-1] + 1))
        from scipy.special import ndtr

        out = np.zeros(len(codes))
        for lo in range(0, len(m), 4096):  # (block, K + 1) at a time
            cdf = ndtr((edges[None, :] - m[lo:lo + 4096, None]) / sigma)
            out += np.diff(cdf, axis=1).sum(axis=0)
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
    pattern_sd: np.ndarray  # (P,) their standard deviations (observed information, visit parameters profiled out)
    chi2: float  # Wald statistic of the pattern against equal widths
    dof: int  # P - 1
    p_value: float  # of chi2
    sigma_counts: float  # the noise of a sample about its visit's line (counts)
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

    def centres(self) -> np.ndarray:
        """(ADC_CODES,) the centre of each code's interval (counts): the value a reading at the code stands for."""
        e = self.edges()
        return 0.5 * (e[:-1] + e[1:])

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
                period: int = PERIOD, alpha: float = 0.01) -> CodeWidths:
    """The code widths of one channel (section above): ``col`` (N,) integer ADC counts, ``groups`` (N,) visit labels
    (a visit: a still input), ``rows`` (N,) the samples to use (still ones), in time order. Visits touching a code
    found odd on a first pass are left out of the pattern's second pass (a wide code holding a visit would bend the
    pattern). Raises ValueError when the channel's counts are not integers or too few visits remain."""
    col = np.asarray(col, float)
    use = rows & np.isfinite(col)
    if np.any(col[use] != np.round(col[use])):
        raise ValueError(f"channel {channel or '?'}: the counts are not integers (averaged or converted data): no ADC "
                         "codes to count")
    vis = _visits_of(col, groups, use)
    if vis.n_visits < 2 * period:
        raise ValueError(f"channel {channel or '?'}: {vis.n_visits} visits of at least {MIN_WIDTH_VISIT_SAMPLES} "
                         f"samples; the width pattern needs at least {2 * period}")
    codes = np.arange(vis.code.min(), vis.code.max() + 1)
    hits = np.bincount(vis.code - codes[0], minlength=len(codes)).astype(float)
    model = _WidthModel(vis, period)
    theta = model.fit()
    odd = _odd_codes(codes, hits, model.expected(theta, codes), model.unpack(theta)[0])
    if odd:  # the pattern again without the visits near an odd code
        sigma = model.unpack(theta)[1]
        level = vis.mean0 + theta[period:period + vis.n_visits]
        near = np.zeros(vis.n_visits, bool)
        for o in odd:
            near |= np.abs(level - o.code) < 3.0 * sigma + 1.0
        if vis.n_visits - near.sum() >= 2 * period:
            keep = ~near[vis.visit]
            _, visit = np.unique(vis.visit[keep], return_inverse=True)
            sub = _Visits(vis.code[keep], visit, vis.u[keep], vis.mean0[~near], int((~near).sum()))
            model2 = _WidthModel(sub, period)
            theta2 = model2.fit()
            w2 = model2.unpack(theta2)[0]
            # the odd codes' expected counts with the pattern of the second pass, every visit's level of the first
            theta_all = np.concatenate([theta2[:period], theta[period:]])
            odd = _odd_codes(codes, hits, model.expected(theta_all, codes), w2)
            model, theta = model2, theta2
    w, sigma = model.unpack(theta)[:2]
    H = model.profile_hessian(theta)
    cov = np.linalg.pinv(H)
    a_cov = cov[:period - 1, :period - 1]
    a = theta[:period - 1]
    chi2 = float(a @ np.linalg.solve(a_cov, a))
    J = w[:, None] * (np.eye(period) - w[None, :] / period)  # d w / d a
    w_cov = J[:, 1:] @ a_cov @ J[:, 1:].T
    from scipy.stats import chi2 as chi2_dist

    return CodeWidths(channel, period, w, np.sqrt(np.maximum(np.diag(w_cov), 0.0)), chi2, period - 1,
                      float(chi2_dist.sf(chi2, period - 1)), sigma, len(model.vis.code), model.vis.n_visits, codes,
                      hits, model.expected(theta, codes) if model.vis is vis else _expected_all(vis, theta, period, codes),
                      odd, alpha)


def _expected_all(vis: _Visits, theta_sub: np.ndarray, period: int, codes: np.ndarray) -> np.ndarray:
    """Expected counts of every visit under the pattern and noise of ``theta_sub`` (a fit on a subset of the
    visits), the visits' own levels and slopes refitted with those held."""
    model = _WidthModel(vis, period)
    start = model.start()
    start[:period] = theta_sub[:period]
    return model.expected(model.fit(start, fixed_global=True), codes)


def recording_code_widths(counts: np.ndarray, groups: np.ndarray, rows: np.ndarray,
                          alpha: float = 0.01) -> list[CodeWidths]:
    """``code_widths`` of each channel of ``counts`` (N, 4): ref, x, y, z (``CHANNEL_NAMES``)."""
    return [code_widths(counts[:, j], groups, rows, CHANNEL_NAMES[j], alpha=alpha) for j in range(counts.shape[1])]
