"""Static-interval detection from the sensor signal itself (multi-position calibration practice).

Pure numpy/scipy. Used by the fit to exclude samples taken while the table moves (offline, on a
whole recording). The calibration node's live test, which must hold a false-alarm rate per run on
correlated noise, is :mod:`fbg_accel_calibration.stillness_monitor`.

Method (the static detector of multi-position IMU calibration, e.g. Tedaldi, Pretto & Menegatti,
"A robust and easy to implement method for IMU calibration without external equipments", ICRA
2014): for every sample the variance of each component of the signal (normally
Psi = counts / ref, eq. 24) over a centred moving window of ``window`` samples is compared with a
threshold derived from the noise floor; a sample is static when every component is below its
threshold, and only runs of at least ``min_interval`` consecutive static samples are kept.

Threshold. For white noise of variance s^2 the window variance v (``window`` samples, ddof=1)
follows s^2 * chi2(w-1)/(w-1). The threshold per component is therefore
``s^2 * chi2.ppf(1 - false_alarm, w-1) / (w-1) * margin``: a still sample is flagged as moving with
probability ``false_alarm`` (for independent samples; low-pass-filtered noise has fewer degrees of
freedom, which ``margin`` (default 2) absorbs). The noise floor s^2 is either given (a known still
period, the node's configuration) or estimated robustly from the recording itself as
``median(v) / (median(chi2(w-1))/(w-1))``, valid when most samples are static -- true for any
calibration run, where dwell times are much longer than moves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from fbg_accel_driver.thermal_model import normalise

from .recording import Recording

DEFAULT_WINDOW = 5
DEFAULT_FALSE_ALARM = 1e-3
DEFAULT_MARGIN = 2.0
DEFAULT_MIN_INTERVAL = 5


@dataclass
class StaticDetection:
    """Result of :func:`detect_static`.

    * ``mask`` (N,) bool: sample is in a kept static interval.
    * ``intervals``: list of ``(start, stop)`` index pairs (stop exclusive) of the static intervals.
    * ``statistic`` (N, k): moving-window variance of each component (signal units squared).
    * ``noise_var`` (k,): noise floor variance used; ``threshold`` (k,): variance threshold used.
    """

    mask: np.ndarray
    intervals: list[tuple[int, int]]
    statistic: np.ndarray
    noise_var: np.ndarray
    threshold: np.ndarray


BLOCK_ROWS = 65536  # moving variances are computed in blocks of this many rows (bounded memory)


def moving_variance(signal: np.ndarray, window: int) -> np.ndarray:
    """Variance (ddof=1) of each column over a centred window of ``window`` samples, (N, k).

    Near the ends the window is truncated to the available samples (NaN if only one is left).
    NaN anywhere in a window gives NaN for that window. Computed in blocks of ``BLOCK_ROWS`` rows
    (with the window's overlap), so the temporaries do not grow with N.
    """
    x = np.asarray(signal, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    if window < 2:
        raise ValueError(f"window must be >= 2 samples, got {window}")
    n = x.shape[0]
    out = np.empty(x.shape)
    half_lo = (window - 1) // 2
    half_hi = window - 1 - half_lo
    for start in range(0, n, BLOCK_ROWS):
        stop = min(n, start + BLOCK_ROWS)
        lo, hi = max(0, start - half_lo), min(n, stop + half_hi)
        out[start:stop] = _moving_variance_block(x[lo:hi], window)[start - lo:stop - lo]
    return out


def _moving_variance_block(x: np.ndarray, window: int) -> np.ndarray:
    n = x.shape[0]
    half_lo = (window - 1) // 2
    half_hi = window - 1 - half_lo
    finite = np.isfinite(x)
    centre = np.nanmean(x, axis=0) if finite.any() else np.zeros(x.shape[1])
    z = np.where(finite, x - np.nan_to_num(centre), 0.0)
    c1 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(z, axis=0)])
    c2 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(z * z, axis=0)])
    cn = np.concatenate([[0], np.cumsum(~np.all(finite, axis=1))])
    idx = np.arange(n)
    lo = np.clip(idx - half_lo, 0, n)
    hi = np.clip(idx + half_hi + 1, 0, n)
    m = (hi - lo).astype(float)[:, None]
    s1 = c1[hi] - c1[lo]
    var = (c2[hi] - c2[lo] - s1 * s1 / m) / np.maximum(m - 1.0, 1.0)
    var = np.maximum(var, 0.0)
    var[(cn[hi] - cn[lo]) > 0] = np.nan
    var[m[:, 0] < 2] = np.nan  # a single sample has no variance
    return var


def variance_threshold(noise_var: np.ndarray, window: int, false_alarm: float = DEFAULT_FALSE_ALARM,
                       margin: float = DEFAULT_MARGIN) -> np.ndarray:
    """Window-variance threshold for a noise floor ``noise_var`` (see module docstring)."""
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f"false_alarm must be in (0, 1), got {false_alarm}")
    dof = window - 1
    return np.asarray(noise_var, dtype=float) * chi2.ppf(1.0 - false_alarm, dof) / dof * margin


def estimate_noise_var(statistic: np.ndarray, window: int) -> np.ndarray:
    """Robust noise-floor variance per column from moving-window variances (mostly static data)."""
    dof = window - 1
    med = np.nanmedian(statistic, axis=0)
    return med / (chi2.median(dof) / dof)


def intervals_from_mask(mask: np.ndarray) -> list[tuple[int, int]]:
    """Runs of True in ``mask`` as ``(start, stop)`` pairs, stop exclusive."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[0::2], edges[1::2], strict=True)]


def detect_static(signal: np.ndarray, window: int = DEFAULT_WINDOW, min_interval: int = DEFAULT_MIN_INTERVAL,
                  false_alarm: float = DEFAULT_FALSE_ALARM, margin: float = DEFAULT_MARGIN,
                  noise_var: np.ndarray | None = None, groups: np.ndarray | None = None) -> StaticDetection:
    """Static samples of ``signal`` (N,) or (N, k) (normally Psi, dimensionless).

    ``groups`` (N,) (e.g. run ids) keeps windows and intervals from spanning two runs; the noise
    floor is then estimated per group unless ``noise_var`` is given. ``min_interval`` is in samples.
    """
    x = np.asarray(signal, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    n, k = x.shape
    if min_interval < 1:
        raise ValueError(f"min_interval must be >= 1 sample, got {min_interval}")
    groups = np.zeros(n, dtype=int) if groups is None else np.asarray(groups)
    mask = np.zeros(n, dtype=bool)
    stat = np.full((n, k), np.nan)
    noise_out = np.zeros(k)
    thr_out = np.zeros(k)
    intervals: list[tuple[int, int]] = []
    for g in np.unique(groups):
        idx = np.flatnonzero(groups == g)
        if np.any(np.diff(idx) != 1):
            raise ValueError("samples of one group must be contiguous")
        s = moving_variance(x[idx], window)
        nv = estimate_noise_var(s, window) if noise_var is None else np.broadcast_to(np.asarray(noise_var, float), (k,))
        thr = variance_threshold(nv, window, false_alarm, margin)
        still = np.all(s <= thr, axis=1)  # NaN compares False -> not static
        for a, b in intervals_from_mask(still):
            if b - a >= min_interval:
                mask[idx[a]:idx[a] + (b - a)] = True
                intervals.append((int(idx[a]), int(idx[a] + (b - a))))
        stat[idx] = s
        noise_out = np.maximum(noise_out, nv)
        thr_out = np.maximum(thr_out, thr)
    return StaticDetection(mask, intervals, stat, noise_out, thr_out)


DEFAULT_REFERENCE_TOLERANCE_MPS2 = 1e-3


def reference_still(gref_mps2: np.ndarray, window: int = DEFAULT_WINDOW,
                    tolerance_mps2: float = DEFAULT_REFERENCE_TOLERANCE_MPS2,
                    groups: np.ndarray | None = None) -> np.ndarray:
    """True where the table reference (N, 3) m/s^2 is constant over the same centred window.

    The reference of a pose comes from the table's angle readings or the pose plan, so it is
    constant (to ``tolerance_mps2``, standard deviation) while the table stands still. A sample
    whose window includes a reference change (the table moved, or an intermediate angle reading)
    or a NaN reference (no pose) is not usable for the fit even when the sensor signal looks still,
    e.g. right after a move, when the TIA low-pass (Table 1, ~1 Hz) has not yet settled.
    """
    g = np.asarray(gref_mps2, dtype=float)
    n = g.shape[0]
    groups = np.zeros(n, dtype=int) if groups is None else np.asarray(groups)
    out = np.zeros(n, dtype=bool)
    for gid in np.unique(groups):
        idx = np.flatnonzero(groups == gid)
        v = moving_variance(g[idx], window)
        out[idx] = np.all(v <= tolerance_mps2**2, axis=1)
    return out


def calibration_samples(rec: Recording, window: int = DEFAULT_WINDOW, min_interval: int = DEFAULT_MIN_INTERVAL,
                        false_alarm: float = DEFAULT_FALSE_ALARM, margin: float = DEFAULT_MARGIN,
                        tolerance_mps2: float = DEFAULT_REFERENCE_TOLERANCE_MPS2) -> tuple[np.ndarray, StaticDetection]:
    """Samples of a :class:`Recording` usable for a static calibration fit, and the signal detection.

    Usable = belongs to a pose (``pose_id >= 0``, finite reference) AND the sensor signal Psi is
    still (:func:`detect_static`, noise floor estimated per run) AND the reference is constant over
    the window (:func:`reference_still`) AND, after those, the sample lies in a run of at least
    ``min_interval`` usable samples of one pose.
    """
    psi = normalise(rec.xyz, rec.ref)
    det = detect_static(psi, window, min_interval, false_alarm, margin, groups=rec.run_id)
    usable = det.mask & reference_still(rec.gref_mps2, window, tolerance_mps2, groups=rec.run_id)
    usable &= (rec.pose_id >= 0) & np.all(np.isfinite(rec.gref_mps2), axis=1)
    # keep only runs of >= min_interval usable samples of one pose within one run
    if len(rec) == 0:
        return usable, det
    change = np.r_[True, (np.diff(rec.pose_id) != 0) | (np.diff(rec.run_id) != 0) | (np.diff(usable.astype(np.int8)) != 0)]
    segment = np.cumsum(change) - 1
    lengths = np.bincount(segment)
    out = usable & (lengths[segment] >= min_interval)
    return out, det
