"""The delay between two records of one tone (second seed: D'Emilia, Gaspari, Natale, JSSS 8, 223, 2019): the peak of
their cross-correlation refined below a sample (seed 2.2, MATLAB's finddelay), checked by the phase of their
cross-spectrum at the tone (seed 2.3). Delays in s, positive when ``sig`` lags ``ref`` (``tone_analysis``'s
conventions); a tone fixes a delay only modulo its period, so both return it in (-T/2, T/2]. The whole periods of a tone
in a record (``whole_period_length``) are cut here too: the cross-spectrum and every tone estimate use them.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from scipy import signal
from scipy.optimize import minimize_scalar

PEAK_TIE = 0.01  # correlation peaks within 1 % of the largest count as equal (periodic records)


def whole_period_length(n_samples: int, fs_hz: float, f_hz: float) -> tuple[int, int]:
    """``(n_periods, n_used)``: ``n_used <= n_samples`` samples spanning ``n_periods`` whole periods.

    ``n_used = round(n_periods fs / f)``. Among the period counts from half the maximum (at least 2 when 2
    fit: one period has no measured repeatability) up to the maximum,
    the one whose span is closest to a whole number of samples wins (ties: the longest), so that e.g. 9
    periods of 1.5 Hz at 100 Hz (600 samples, exact) are preferred to 10 (666.7 samples); the span then
    differs from whole periods by at most half a sample. A record of exactly ``round(k fs / f)`` samples
    holds k periods by the same rule (also when that rounds below ``k fs / f``), so a span this function
    returns is accepted back. Raises ``ValueError`` when not one period fits.
    """
    per = fs_hz / f_hz
    k_max = int(np.floor((n_samples + 0.5) / per + 1e-9))
    while k_max >= 1 and round(k_max * per) > n_samples:
        k_max -= 1
    if k_max < 1:
        raise ValueError(f"less than one period of {f_hz} Hz in {n_samples} samples at {fs_hz} Hz")
    ks = np.arange(max(min(2, k_max), (k_max + 1) // 2), k_max + 1)  # 2 periods if they fit: a repeatability
    # misfit in samples, quantised to 0.01 sample so that a rate read from time stamps (1000.0000001 Hz)
    # does not prefer a short span for a difference nobody can see
    frac = np.round(np.abs(ks * per - np.round(ks * per)), 2)
    k = int(ks[np.flatnonzero(frac == frac.min())[-1]])
    return k, round(k * per)


def delay_by_cross_correlation(ref: np.ndarray, sig: np.ndarray, fs_hz: float, max_lag_s: float | None = None,
                               refine: Literal["cosine", "parabolic", "none"] = "cosine", circular: bool = False) -> float:
    """Delay of ``sig`` behind ``ref`` in s by the cross-correlation peak with sub-sample refinement (seed 2.2).

    Positive when the sensor ``sig`` lags the reference: ``sig(t) ~ ref(t - delay)``. Both records are
    uniformly sampled at ``fs_hz`` on the same time base; means are removed. The correlation at lag k is
    ``sum sig[n] ref[n - k]`` divided by the number of overlapping samples (unbiased), over the lags with at
    least half the record overlapping and ``|k| <= max_lag_s fs`` (default: no further limit). The integer
    peak is the largest value of its lobe (a run of lags above half the largest value); lobes whose peaks
    are within ``PEAK_TIE`` (relative) of the largest -- the equal peaks a whole period apart of a periodic
    record -- resolve to the one nearest zero, as MATLAB ``finddelay`` does; a tone fixes a delay only
    modulo its period. Noise ripples on one flat peak do not tie (:func:`_tied_peak`). Refinement around
    the integer peak, when it is narrow (fewer than 2 lags on a side above 3/4 of its value):

    * ``"cosine"`` (default): fit ``A cos(w (k - d))`` through the three points around the peak; exact for a
      sinusoid, close to parabolic for broadband signals; falls back to parabolic when the three points
      are not cosine-shaped;
    * ``"parabolic"``: vertex of the parabola through the three points (bias grows with f/fs);
    * ``"none"``: integer samples (the resolution 1/fs of seed Table 3).

    A wide peak (a slow tone: its curvature between neighbouring lags is below the noise) is refined by a
    least-squares parabola over its lags above 3/4 of its value, on a window re-centred on the vertex
    (:func:`_refined_offset`; up to 0.008 sample off on a noiseless tone), and with ``"cosine"`` then by a
    least-squares cosine over the same window (exact for a tone).

    ``circular``: correlate circularly (via the FFT, records cut to the shorter length). Use it for a
    periodic excitation cut to whole periods (as :func:`analyse_run` does): the circular correlation of
    one whole-period block equals the linear correlation of an endless steady-state record, an exact
    cosine in the lag for a tone, so the cosine refinement is exact. The linear correlation of a tone
    with only a few periods carries edge terms of relative size ~1/(N sin(2 pi f/fs)) that bias the
    sub-sample refinement (about 0.25 ms for 20 periods of 5 Hz at 1 kHz); for broadband signals the
    linear correlation is the right one.
    """
    ref = np.asarray(ref, dtype=float)
    sig = np.asarray(sig, dtype=float)
    if ref.ndim != 1 or sig.ndim != 1 or ref.size < 3 or sig.size < 3:
        raise ValueError("ref and sig must be 1-D with at least 3 samples")
    if circular:
        n = min(ref.size, sig.size)
        r = ref[:n] - ref[:n].mean()
        s = sig[:n] - sig[:n].mean()
        cc = np.fft.irfft(np.conj(np.fft.rfft(r)) * np.fft.rfft(s), n) / n  # cc[k] = mean s[m] r[m - k mod n]
        lags = np.arange(n)
        lags[lags > n // 2] -= n
        valid = np.ones(n, dtype=bool)
    else:
        r = ref - ref.mean()
        s = sig - sig.mean()
        raw = signal.correlate(s, r, mode="full", method="fft")
        lags = signal.correlation_lags(s.size, r.size, mode="full")
        overlap = np.minimum(s.size, r.size + lags) - np.maximum(0, lags)
        valid = overlap >= max(2, min(s.size, r.size) // 2)
        cc = raw / np.maximum(overlap, 1)
    ok = valid.copy()
    if max_lag_s is not None:
        ok &= np.abs(lags) <= max_lag_s * fs_hz
    if not np.any(ok):
        raise ValueError("no lag within max_lag_s")
    i = _tied_peak(cc, lags, valid, ok, circular)
    d = float(lags[i])
    if refine != "none":
        d += _refined_offset(cc, i, valid, circular, refine)
    return d / fs_hz


def _lobes(mask: np.ndarray, circular: bool) -> list[np.ndarray]:
    """Index runs where ``mask`` holds; with ``circular`` the last index neighbours the first."""
    n = mask.size
    if not mask.any():
        return []
    if circular and mask.all():
        return [np.arange(n)]
    shift = int(np.flatnonzero(~mask)[0]) if circular else 0  # start the scan on a gap
    mm = np.roll(mask, -shift)
    edges = np.diff(np.concatenate([[0], mm.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(np.arange(a, e) + shift) % n for a, e in zip(starts, ends, strict=True)]


def _tied_peak(cc: np.ndarray, lags: np.ndarray, valid: np.ndarray, ok: np.ndarray, circular: bool) -> int:
    """Index of the integer correlation peak within the allowed lags ``ok`` (``valid``: the lags where the
    correlation means something, every lag of a circular one; ``ok``: those within the lag limit too).

    The correlation splits into lobes: runs of lags above half the largest allowed value. Each lobe's peak is
    its largest allowed value; lobes whose peaks are within ``PEAK_TIE`` (relative) of the largest tie -- the
    equal peaks a whole period apart of a periodic record -- and the one nearest zero lag wins (MATLAB
    ``finddelay``). Within a lobe only its true maximum counts: a slow tone's peak is so flat that noise
    ripples on it lie within 1 % of the top over a wide span of lags (about +-0.02 periods), and letting
    those tie pulled the delay towards zero (100 ms read as about 0 at 0.1 Hz).
    """
    top = float(np.max(cc[ok]))
    if not top > 0:  # no positive correlation: nothing to split, the largest allowed value
        idx = np.flatnonzero(ok & (cc == top))
        return int(idx[np.argmin(np.abs(lags[idx]))])
    peaks: list[tuple[float, int]] = []
    for lobe in _lobes(valid & (cc > 0.5 * top), circular):
        allowed = lobe[ok[lobe]]
        if allowed.size:
            j = int(allowed[np.argmax(cc[allowed])])
            peaks.append((float(cc[j]), j))
    tied = [j for v, j in peaks if v >= top - PEAK_TIE * abs(top)]  # the largest allowed value lies in a lobe
    return min(tied, key=lambda j: abs(int(lags[j])))  # the first of equal distances, as before


def _refined_offset(cc: np.ndarray, i: int, valid: np.ndarray, circular: bool, refine: str) -> float:
    """Sub-sample offset (samples) of the peak at index ``i`` of the correlation ``cc`` (``valid`` lags only).

    A narrow peak (fewer than 2 lags on either side above three quarters of its value) is refined from the
    three points around it (:func:`peak_offset`: cosine or parabolic; exact for a tone). A wide one -- a
    slow tone, whose top carries noise ripples larger than the curvature between neighbouring lags -- by a
    least-squares parabola over the lags above three quarters of the peak (+-41 degrees of a tone), on a
    window symmetric about the integer lag nearest the vertex (re-centred until it stays), so that neither
    the noise on three points nor the cosine's quartic term moves it much; ``refine="cosine"`` then fits a
    cosine over the same window (:func:`_cosine_vertex`), exact for a tone.
    """
    m = cc.size
    y0 = float(cc[i])
    inside = valid & (cc > 0.75 * y0) if y0 > 0 else np.zeros(m, bool)
    inside[i] = True

    def reach(c: int, step: int) -> int:  # lags from c, in direction step, still inside the top quarter
        r = 0
        while r < m // 2 and (circular or 0 <= c + step * (r + 1) < m) and inside[(c + step * (r + 1)) % m]:
            r += 1
        return r

    h = min(reach(i, -1), reach(i, +1))
    if h < 2:
        if circular:
            return peak_offset(cc[(i - 1) % m], y0, cc[(i + 1) % m], refine)
        return peak_offset(cc[i - 1], y0, cc[i + 1], refine) if 0 < i < m - 1 else 0.0
    c = i
    off = 0.0
    for _ in range(4):
        k = np.arange(-h, h + 1).astype(float)
        y = cc[(c + np.arange(-h, h + 1)) % m] if circular else cc[np.clip(c + np.arange(-h, h + 1), 0, m - 1)]
        c2, c1, c0 = np.polyfit(k, y, 2)
        v = float(np.clip(-c1 / (2 * c2), -h, h)) if c2 < 0 else 0.0
        off = (c - i) + v
        nc = i + round(off)
        if nc == c:
            break
        c = nc
        h = max(2, min(h, reach(c, -1), reach(c, +1)))
    if refine == "cosine" and c2 < 0 and c0 > 0:  # the parabola's vertex, refined to the cosine it approximates
        off = (c - i) + _cosine_vertex(k, y, math.sqrt(-2.0 * c2 / c0), v)
    return off


def _cosine_vertex(k: np.ndarray, y: np.ndarray, w0: float, v0: float) -> float:
    """Peak position (samples) of ``b cos(w k) + c sin(w k)`` fitted to ``y`` at lags ``k`` by least squares,
    ``w`` (rad/sample) searched within a factor 2 of ``w0``; ``v0`` (the parabola's vertex) when the fit fails.
    Exact for the correlation of a tone, which a parabola over +-41 degrees misses by up to 0.008 sample."""
    def fit(w: float) -> tuple[float, np.ndarray]:
        a = np.column_stack([np.cos(w * k), np.sin(w * k)])
        coef, *_ = np.linalg.lstsq(a, y, rcond=None)
        r = y - a @ coef
        return float(r @ r), coef

    res = minimize_scalar(lambda w: fit(w)[0], bounds=(0.5 * w0, 2.0 * w0),
                          method="bounded", options={"xatol": 1e-6 * w0})
    w = float(res.x)
    b, c = fit(w)[1]
    if not (res.success and b > 0):
        return v0
    vertex = math.atan2(c, b) / w
    return vertex if abs(vertex - v0) <= 1.0 else v0


def peak_offset(ym: float, y0: float, yp: float, refine: str = "parabolic") -> float:
    """Sub-sample offset (in samples, |offset| <= 1) of a peak sampled at -1, 0, +1."""
    if refine == "cosine" and y0 > 0:
        c = (ym + yp) / (2 * y0)
        if -1.0 < c < 1.0:
            w = math.acos(c)
            if w > 1e-6:
                return float(np.clip(math.atan((yp - ym) / (2 * y0 * math.sin(w))) / w, -1.0, 1.0))
    den = ym - 2 * y0 + yp
    if den >= 0:  # not a maximum: keep the integer lag
        return 0.0
    return float(np.clip(0.5 * (ym - yp) / den, -1.0, 1.0))


def cross_spectrum_at(ref: np.ndarray, sig: np.ndarray, fs_hz: float, f_hz: float) -> complex:
    """Cross-spectrum ``conj(R(f)) S(f)`` at the tone ``f_hz`` over the largest whole number of periods.

    Rectangular window over whole periods (see :func:`fft_amplitude_phase`), scaled so that for two tones
    it equals ``A_r A_s exp(j (phi_s - phi_r))``. Evaluating the DFT at the tone itself avoids the
    frequency-resolution problem of a Welch cross-spectrum at low frequency (seed 3.3).
    """
    ref = np.asarray(ref, dtype=float)
    sig = np.asarray(sig, dtype=float)
    n_all = min(ref.size, sig.size)
    _, n = whole_period_length(n_all, fs_hz, f_hz)
    e = np.exp(-2j * np.pi * f_hz * np.arange(n) / fs_hz)
    R = 2 * np.sum((ref[:n] - ref[:n].mean()) * e) / n
    S = 2 * np.sum((sig[:n] - sig[:n].mean()) * e) / n
    return complex(np.conj(R) * S)


def delay_by_cross_spectrum(ref: np.ndarray, sig: np.ndarray, fs_hz: float, f_hz: float) -> float:
    """Delay of ``sig`` behind ``ref`` in s from the cross-spectrum phase at ``f_hz`` (seed 2.3, 3.3).

    ``delay = -arg(conj(R) S) / (2 pi f)``, positive when the sensor lags, in (-T/2, T/2] with T = 1/f
    (the phase delay at f; equal to a pure delay only when the chain has no other phase).
    """
    g = cross_spectrum_at(ref, sig, fs_hz, f_hz)
    return -wrap_phase(float(np.angle(g))) / (2 * np.pi * f_hz)


def wrap_phase(phase_rad: float) -> float:
    """Phase wrapped to (-pi, pi]."""
    p = (phase_rad + np.pi) % (2 * np.pi) - np.pi
    return float(np.pi if p == -np.pi else p)
