"""A periodic disturbance in the static visits: a line in the within-visit residual. Pure numpy/scipy.

The noise floor of ``diagnose`` is the scatter of the residual within visits (settled samples, each visit's mean and
line removed). A periodic motion during the visits, a table or chamber that sways, a fan, a pump (a few 0.01-0.1
m/s^2 at 0.2-2 Hz), is in that scatter too: the floor came out 13-18 % above the sensor's noise on a simulated run
with a 0.37 Hz sine of 0.1 / 0.06 m/s^2 on x / y, and nothing named it. Such a disturbance is one frequency shared by
every visit and, as long as it keeps its frequency, phase-coherent over a run: a line in the periodogram of the
residual, the visits being gaps of one time series.

Detection (``find_periodic_disturbance``): per run, the detrended residual of the settled samples is put on the time
grid of the median sample interval (zeros in the gaps: moves, settling, other samples), summed in blocks of grid
samples short enough for ``FMAX_HZ`` (a boxcar: the line and the noise alike) and Fourier transformed,
zero-padded ``PAD`` x (a line between two bins loses at most 19 % of its power). Each ordinate is divided by the
local spectral level: the mean periodogram over ``LEVEL_HALF_WIDTH`` padded bins on each side, leaving out the
``GUARD`` bins around it (a line's main lobe). Under Gaussian noise whose spectrum is smooth over that window a
periodogram ordinate is S(f) chi^2_2 / 2 and the level an independent S(f) chi^2_2k / 2k, so the ratio is F(2, 2k)
distributed (Percival & Walden 1993, Spectral Analysis for Physical Applications, ch. 6 and 10.9: a line against the
local continuum; Thomson 1982 uses the same F for multitaper lines), k the independent bins of the window
(its padded bins / ``PAD``). Runs are summed on one frequency grid (ratio of sums over runs: F(2K, 2Kk)). A line is
called at ``PERIODIC_ALPHA``, Bonferroni over the padded bins of the band (a conservative count of the frequencies
tried), the three axes and the ``MAX_LINES`` lines searched. The band is from ``MIN_CYCLES_PER_VISIT`` cycles per
median visit (slower motion is mostly removed with each visit's mean and line) to ``FMAX_HZ`` (above the TIAs'
cut-offs: a faster disturbance reaches the output attenuated; not searched).

A called line is fitted by least squares, one sine per axis and run with a common frequency, its regressors
detrended within each visit as the residual is (``_Detrender``); the frequency is refined by a golden-section search
of the fitted power over one padded bin either side of the peak. The fitted sines are removed from the residual and
the search repeated (at most ``MAX_LINES``). ``PeriodicDisturbance.model`` gives the fitted sines on any samples of
the runs, so that ``diagnose`` can take them out of the floor and report the floor with them too.

Limits: the disturbance must hold its frequency (to about one resolution cell, 1 / run length) over a run; a sway
whose frequency wanders spreads over many bins and is not called (it stays in the floor). Lines slower than half a
cycle per visit are not searched. A pattern locked to the visits (the same shape in every visit) shows at multiples of
1 / (visit period) and is named like a disturbance (``PeriodicLine.visit_harmonic`` says so). A run whose time grid
would be more than ``MAX_GRID_FILL`` x its samples (hours of gaps) is not searched.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import fft as scipy_fft
from scipy import stats

PERIODIC_ALPHA = 1e-3  # family-wise false-alarm level of the line search (Bonferroni: frequencies x axes x lines)
MAX_LINES = 3  # lines searched for, one after the other
PAD = 2  # zero-padding factor of the transforms
LEVEL_HALF_WIDTH = 64  # padded bins on each side of a frequency whose mean periodogram is its local level
GUARD = 3 * PAD  # padded bins on each side left out of the level (the line's own main lobe)
MIN_CYCLES_PER_VISIT = 0.5  # lowest frequency searched: this many cycles over the median visit
MAX_GRID_FILL = 16  # a run whose time grid is longer than this many times its samples is not searched
GOLDEN_STEPS = 14  # golden-section steps of the frequency refinement (2 padded bins -> 1e-3 of one)
# Highest frequency searched (Hz). Every TIA is a first-order low-pass at 1-1.7 Hz (paper Table 1): a disturbance at
# 5 Hz reaches the output at 0.25-0.32 of its size and one at 20 Hz at under 0.09, so what matters to the floor is
# slower; the sway of a table or chamber, 0.2-2 Hz, is well inside.
FMAX_HZ = 5.0
HARMONIC_TOL = 0.5  # a line within this many resolution cells of a multiple of 1 / visit period is visit-locked


@dataclass
class PeriodicLine:
    """One sinusoidal disturbance found in the within-visit residual."""

    freq_hz: float  # Hz
    amplitude_mps2: np.ndarray  # (3,) sine amplitude per axis, m/s^2, table frame, as in the calibrated output (after
    # the TIA low-pass); the root mean square over runs weighted by their samples
    axis_p: np.ndarray  # (3,) p-value of the line on each axis alone at its peak (F against the local level), raw
    p_value: float  # Bonferroni-corrected p-value of the detection (over frequencies, axes and lines)
    power_ratio: float  # periodogram / local level at the peak, on the axis that found it (summed over runs: / runs)
    coeffs: dict[int, np.ndarray] = field(default_factory=dict)  # run id -> (2, 3) cos / sin coefficients, m/s^2
    t0_s: dict[int, float] = field(default_factory=dict)  # run id -> phase origin (s, that run's time)
    visit_harmonic: int = 0  # k > 0: the line sits at k / (median visit period): it may be locked to the visits

    def model(self, t_s: np.ndarray, run_id: np.ndarray) -> np.ndarray:
        """The fitted sine (N, 3) m/s^2 at times ``t_s`` (s) of runs ``run_id``; zero in a run it was not fitted on."""
        out = np.zeros((len(t_s), 3))
        for run, c in self.coeffs.items():
            m = run_id == run
            ph = 2.0 * np.pi * self.freq_hz * (t_s[m] - self.t0_s[run])
            out[m] = np.cos(ph)[:, None] * c[0] + np.sin(ph)[:, None] * c[1]
        return out


@dataclass
class PeriodicDisturbance:
    """What the line search found (``find_periodic_disturbance``) and, filled in by ``diagnose``, what it does."""

    lines: list[PeriodicLine]
    band_hz: tuple[float, float]  # frequencies searched (Hz)
    n_tests: int  # the Bonferroni count
    alpha: float
    threshold: float  # periodogram / level ratio a line must exceed (one run)
    note: str = ""  # why nothing was searched, if so
    floor_with_lines: np.ndarray | None = None  # (3,) m/s^2: the within-visit floor with the lines left in
    heldout_without_lines: np.ndarray | None = None  # (3,) m/s^2: held-out RMSE with the fitted lines taken out

    @property
    def found(self) -> bool:
        return bool(self.lines)

    def model(self, t_s: np.ndarray, run_id: np.ndarray) -> np.ndarray:
        """Every fitted line (N, 3) m/s^2 at times ``t_s`` (s) of runs ``run_id``."""
        return sum((line.model(t_s, run_id) for line in self.lines), np.zeros((len(t_s), 3)))

    def refit(self, res: np.ndarray, t_s: np.ndarray, groups: np.ndarray, run_id: np.ndarray,
              rows: np.ndarray) -> np.ndarray:
        """The lines (N, 3) m/s^2 at their frequencies, amplitudes and phases fitted again on another residual ``res``
        (N, 3) over ``rows`` (detrended within ``groups`` like the search's): e.g. the held-out residual, or the
        output of a filtered model. Zero without lines or rows."""
        out = np.zeros((len(t_s), 3))
        idx = np.flatnonzero(rows & np.all(np.isfinite(res), axis=1))
        if not self.lines or idx.size < 3:
            return out
        t, rid = t_s[idx], run_id[idx]
        inv, starts = _segments(groups[idx], rid)
        runs = [_Run(int(r), np.flatnonzero(rid == r), np.zeros(0, np.int64), float(t[rid == r][0]))
                for r in np.unique(rid)]
        detrend = _Detrender(inv, starts, t)
        dev = detrend(res[idx])
        for ln in self.lines:
            _, coeffs, fitted = _fit(dev, t, runs, detrend, ln.freq_hz)
            dev = dev - fitted
            out += replace(ln, coeffs=coeffs, t0_s={r.run: r.t0 for r in runs}).model(t_s, run_id)
        return out

    def summary(self) -> str:
        """One sentence per line, for the report and the warnings; "" when none was found."""
        if not self.lines:
            return ""
        parts = []
        for ln in self.lines:
            amp = "/".join(f"{a:.3g}" for a in ln.amplitude_mps2)
            locked = (f" (at {ln.visit_harmonic} x 1 / the visit period: it may be a pattern repeated in every visit "
                      "rather than a motion)" if ln.visit_harmonic else "")
            parts.append(f"{ln.freq_hz:.4g} Hz, amplitude {amp} m/s^2 on x/y/z (p = {ln.p_value:.2g}){locked}")
        return ("a periodic disturbance during the static visits: " + "; ".join(parts)
                + " (a table or chamber that sways, a fan, a pump: not the sensor's noise)")


def _segments(groups: np.ndarray, run_id: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Labels (n,) 0, 1, ... of the contiguous stretches of one visit in one run of time-ordered samples, and the index
    of each stretch's first sample. A visit is one contiguous static interval (``effects.visit_ids``), so a stretch is
    a visit (its settled samples); O(n), no sort."""
    change = np.r_[True, (groups[1:] != groups[:-1]) | (run_id[1:] != run_id[:-1])]
    return np.cumsum(change) - 1, np.flatnonzero(change)


class _Detrender:
    """Removes each visit's least-squares mean and straight line in time from columns of samples (the projection
    ``within_visit_noise`` applies to the residual)."""

    def __init__(self, inv: np.ndarray, starts: np.ndarray, t_s: np.ndarray) -> None:
        self.inv = inv
        self.nv = len(starts)
        cnt = np.bincount(inv, minlength=self.nv).astype(float)
        self.cnt = np.maximum(cnt, 1.0)
        tr = t_s - t_s[starts][inv]
        self.tc = tr - (np.bincount(inv, weights=tr, minlength=self.nv) / self.cnt)[inv]
        stt = np.bincount(inv, weights=self.tc * self.tc, minlength=self.nv)
        self.stt = np.where(stt > 1e-12, stt, np.inf)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """x (n, k) -> x with every visit's mean and line removed (n, k)."""
        out = np.empty_like(x)
        for j in range(x.shape[1]):
            c = x[:, j] - (np.bincount(self.inv, weights=x[:, j], minlength=self.nv) / self.cnt)[self.inv]
            slope = np.bincount(self.inv, weights=self.tc * c, minlength=self.nv) / self.stt
            out[:, j] = c - slope[self.inv] * self.tc
        return out


def _local_level(p: np.ndarray) -> np.ndarray:
    """Mean of ``p`` (F, 3) over LEVEL_HALF_WIDTH bins either side, without the GUARD bins either side (F, 3)."""
    cs = np.vstack([np.zeros((1, p.shape[1])), np.cumsum(p, axis=0)])
    i = np.arange(len(p))
    n = len(p)

    def window(half: int) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = np.clip(i - half, 0, n), np.clip(i + half + 1, 0, n)
        return cs[hi] - cs[lo], (hi - lo).astype(float)

    s_out, n_out = window(LEVEL_HALF_WIDTH)
    s_in, n_in = window(GUARD)
    return (s_out - s_in) / np.maximum(n_out - n_in, 1.0)[:, None]


@dataclass
class _Run:
    run: int
    rows: np.ndarray  # indices into the settled samples of this run
    k: np.ndarray  # grid positions (samples of the median interval since t0)
    t0: float


def _fit(dev: np.ndarray, t: np.ndarray, runs: list[_Run], detrend: _Detrender, freq: float,
         ) -> tuple[float, dict[int, np.ndarray], np.ndarray]:
    """Least-squares sine at ``freq`` (Hz) per axis and run on ``dev`` (n, 3), regressors detrended like it: (power
    explained in units of each axis's variance, summed; run -> (2, 3) coefficients; the fitted part (n, 3))."""
    reg = np.zeros((len(t), 2))
    for r in runs:
        ph_r = 2.0 * np.pi * freq * (t[r.rows] - r.t0)
        reg[r.rows, 0], reg[r.rows, 1] = np.cos(ph_r), np.sin(ph_r)
    reg = detrend(reg)
    fitted = np.zeros_like(dev)
    coeffs: dict[int, np.ndarray] = {}
    power = 0.0
    scale = np.maximum(np.mean(dev * dev, axis=0), 1e-300)
    for r in runs:
        X, y = reg[r.rows], dev[r.rows]
        G = X.T @ X
        if np.linalg.cond(G) > 1e12:
            continue
        c = np.linalg.solve(G, X.T @ y)  # (2, 3)
        coeffs[r.run] = c
        fitted[r.rows] = X @ c
        power += float(np.sum(np.sum(c * (X.T @ y), axis=0) / scale))
    return power, coeffs, fitted


def find_periodic_disturbance(res: np.ndarray, t_s: np.ndarray, groups: np.ndarray, run_id: np.ndarray,
                              rows: np.ndarray, alpha: float = PERIODIC_ALPHA,
                              max_lines: int = MAX_LINES) -> PeriodicDisturbance:
    """Search the residual ``res`` (N, 3) m/s^2 (table frame) of the samples ``rows`` (N,) (the settled ones of the
    floor) for sinusoidal lines shared by the visits ``groups`` (N,) of each run ``run_id`` (N,), times ``t_s`` (N,) s.
    See the module docstring for the test and its limits."""
    empty = PeriodicDisturbance([], (math.nan, math.nan), 0, alpha, math.inf)
    idx = np.flatnonzero(rows & np.all(np.isfinite(res), axis=1))
    if idx.size < 4 * LEVEL_HALF_WIDTH:
        return replace(empty, note=f"not searched: {idx.size} settled samples")
    t, g, rid = t_s[idx], groups[idx], run_id[idx]
    inv, starts = _segments(g, rid)
    step = np.diff(t)
    same = (inv[1:] == inv[:-1]) & (step > 0)
    if not same.any():
        return replace(empty, note="not searched: no two consecutive samples in a visit")
    dt = float(np.median(step[same]))
    t_first, t_last = t[starts], t[np.r_[starts[1:], len(t)] - 1]
    visit_s = float(np.median(t_last - t_first)) + dt
    # block sums of ``block`` grid samples (a boxcar, then one value per block: the line and the noise alike) keep
    # the transforms short; the band ends at FMAX_HZ, or 0.45 of the Nyquist frequency of the blocks
    block = max(1, int(0.45 / (dt * FMAX_HZ)))
    band = (MIN_CYCLES_PER_VISIT / visit_s, min(FMAX_HZ, 0.45 / (block * dt)))
    empty.band_hz = band
    if band[0] >= band[1]:
        return replace(empty, note="not searched: visits too short for a cycle")
    runs: list[_Run] = []
    for run in np.unique(rid):
        r = np.flatnonzero(rid == run)
        t0 = float(t[r[0]])
        k = np.rint((t[r] - t0) / dt).astype(np.int64) // block
        if k.min() < 0 or k.max() + 1 > MAX_GRID_FILL * len(r) / block:
            continue
        runs.append(_Run(int(run), r, k, t0))
    if not runs:
        return replace(empty, note="not searched: the runs' samples are too sparse in time (long gaps)")
    n_fft = scipy_fft.next_fast_len(PAD * int(max(r.k.max() + 1 for r in runs)), real=True)
    freqs = np.arange(n_fft // 2 + 1) / (n_fft * block * dt)
    in_band = np.flatnonzero((freqs >= band[0]) & (freqs <= band[1]))
    if in_band.size < 2 * LEVEL_HALF_WIDTH:
        return replace(empty, note="not searched: too few frequencies in the band")
    K = len(runs)
    dfd = 2.0 * K * 2.0 * (LEVEL_HALF_WIDTH - GUARD) / PAD
    n_tests = int(in_band.size) * 3 * max_lines
    threshold = float(stats.f.isf(alpha / n_tests, 2 * K, dfd))
    out = PeriodicDisturbance([], band, n_tests, alpha, threshold)
    detrend = _Detrender(inv, starts, t)
    dev = detrend(res[idx])
    period_s = _visit_period(t_first, rid[starts])
    for _ in range(max_lines):
        ratio = np.zeros((len(freqs), 3))
        for r in runs:
            y = np.stack([np.bincount(r.k, weights=dev[r.rows, j], minlength=n_fft) for j in range(3)], axis=1)
            spec = scipy_fft.rfft(y, n_fft, axis=0)
            p = spec.real**2 + spec.imag**2
            ratio += p / np.maximum(_local_level(p), 1e-300)
        ratio /= K
        sub = ratio[in_band]
        i_b, axis = np.unravel_index(int(np.argmax(sub)), sub.shape)
        if sub[i_b, axis] <= threshold:
            break
        i = int(in_band[i_b])
        f0 = freqs[i]
        if 0 < i < len(freqs) - 1:  # parabolic peak of the log ratio
            a, b, c = np.log(np.maximum(ratio[i - 1:i + 2, axis], 1e-300))
            den = a - 2.0 * b + c
            if den < 0:
                f0 += float(np.clip(0.5 * (a - c) / den, -0.5, 0.5)) * (freqs[1] - freqs[0])
        freq = _refine(dev, t, runs, detrend, f0, float(freqs[1] - freqs[0]))
        _, coeffs, fitted = _fit(dev, t, runs, detrend, freq)
        if not coeffs:
            break
        w = np.array([len(r.rows) for r in runs if r.run in coeffs], float)
        amp2 = np.array([np.sum(c**2, axis=0) for run, c in coeffs.items()])  # (runs, 3)
        amplitude = np.sqrt(w @ amp2 / w.sum())
        p_axis = stats.f.sf(sub[i_b], 2 * K, dfd)
        harmonic = 0
        if period_s > 0:
            h = round(freq * period_s)
            cell = PAD * float(freqs[1])  # one resolution cell (Hz)
            if h >= 1 and abs(freq - h / period_s) < HARMONIC_TOL * cell:
                harmonic = int(h)
        out.lines.append(PeriodicLine(float(freq), amplitude, p_axis, min(1.0, float(p_axis[axis]) * n_tests),
                                      float(sub[i_b, axis]), coeffs, {r.run: r.t0 for r in runs}, harmonic))
        dev = dev - fitted
    return out


def _visit_period(t_first: np.ndarray, run_of_visit: np.ndarray) -> float:
    """Median time (s) from one visit's start to the next within a run; 0 without two visits in a run."""
    order = np.lexsort((t_first, run_of_visit))
    ts, rs = t_first[order], run_of_visit[order]
    d = np.diff(ts)[rs[1:] == rs[:-1]]
    return float(np.median(d)) if d.size else 0.0


def _refine(dev: np.ndarray, t: np.ndarray, runs: list[_Run], detrend: _Detrender, f0: float, step: float) -> float:
    """The frequency (Hz) within ``f0`` +- ``step`` whose least-squares sine explains most of ``dev`` (golden section)."""
    lo, hi = f0 - step, f0 + step
    g = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = _fit(dev, t, runs, detrend, a)[0], _fit(dev, t, runs, detrend, b)[0]
    for _ in range(GOLDEN_STEPS):
        if fa >= fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = _fit(dev, t, runs, detrend, a)[0]
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = _fit(dev, t, runs, detrend, b)[0]
    return (a + b) / 2.0
