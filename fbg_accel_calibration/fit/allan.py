"""Allan deviation of a static recording, velocity random walk and bias instability (paper 4.4, Table 2).

Pure numpy + allantools + matplotlib (Agg). The overlapping Allan deviation (NIST SP 1065 eq. 11,
frequency data: the samples are the calibrated specific force, a rate-like quantity) is computed per axis
at log-spaced cluster times. A series cut into continuous segments (breaks in the time base) pools the
clusters of every segment; no cluster spans a break. Figures in the units of paper Table 2:

* VRW = 60 * ADEV(tau = 1 s), m/s/sqrt(h) (paper eq. 26), interpolated log-log when 1 s is not an exact
  cluster time. ADEV(1 s) equals the white-noise coefficient N (m/s/sqrt(s)) only where the ADEV is
  already on its tau^-1/2 line at 1 s. Behind the amplifier's first-order low-pass (1-1.7 Hz) it is not:
  the low-pass with time constant T lowers the Allan variance by about 1.5 T / tau, so 60 ADEV(1 s) is
  8-12 % below 60 N. Hence also:
* white-noise VRW = 60 N, N from a fit of a -1/2 slope line (IEEE Std 952 style) over the white-noise
  region: the longest run of cluster times tau <= length / 20 on which the local log-log slope (least
  squares over +-1/4 decade) is within -1/2 +- ``WHITE_SLOPE_TOL``; N = geometric mean of ADEV(tau)
  sqrt(tau) there. The region is reported (``white_tau_range_s``); without one of at least
  ``WHITE_MIN_DECADES`` the figure is NaN (the low-pass and the bias-instability floor leave no
  white-noise region). ``vrw_differs`` flags axes where the two VRWs differ by more than 5 %.
* bias instability = min ADEV / 0.664, in mg (paper eq. 27; 0.664 = sqrt(2 ln 2 / pi), the flicker
  floor of a bias-instability PSD B^2/(2 pi f), two-sided as in IEEE Std 952). The minimum is
  searched for tau >= 1 s and tau <= record length / 20 (``MIN_CLUSTERS_FOR_MIN``): the last
  octaves rest on a handful of clusters, their confidence interval is very wide (SP 1065) and the
  minimum of noisy values is biased low (``bench/allan_check.py``: one hour of flicker noise reads
  the floor 0.69..1.01 times the configured value, about 10 % low on average). When the ADEV has no
  minimum in that window (still falling at its upper edge, still rising at its lower edge, or a record
  shorter than 20 s) the figure is only an upper bound of the floor (``bi_is_upper_bound``; "< x" in
  the table), not a bias instability: white noise alone reads ADEV(length/20)/0.664. A floor beyond
  length/20 (e.g. a minimum at ~1600 s, which needs ~9 h) is not reached: record longer (the paper
  used 6 h).
* error bars: ADEV / sqrt(2 edf), edf from ``allantools.edf_greenhall`` for white frequency noise and
  the overlapping estimator, summed over the segments (the overlapping terms are strongly correlated;
  their count N - 2m is not the number of independent terms).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import allantools
import numpy as np

MG_TO_MPS2 = 9.80665e-3
BI_FACTOR = 0.664
MIN_CLUSTERS_FOR_MIN = 20  # tau_max for the minimum search = duration / 20
TAUS_PER_DECADE = 20
WHITE_OTHER_TERMS = 0.05  # white-noise region: the other terms below this fraction of N^2/tau (2.5 % in ADEV)
WHITE_MIN_DECADES = 0.5  # shortest white-noise region used for the -1/2 line
VRW_DIFF_FLAG = 0.05  # flag when the two VRWs differ by more than this fraction
AXES = ("x", "y", "z")


@dataclass
class AllanResult:
    """Allan deviation per axis: ``taus_s`` (T,), ``adev_mps2`` (T, 3), ``err_mps2`` (T, 3).

    ``vrw_mps_per_sqrt_h`` (3,) = 60 ADEV(1 s) (paper eq. 26), ``bias_instability_mg`` (3,) and the
    cluster time of the minimum ``bi_tau_s`` (3,), ``bi_is_upper_bound`` (3,) when there is no minimum;
    ``white_noise_vrw_mps_per_sqrt_h`` (3,) from the -1/2 line over ``white_tau_range_s`` (3, 2),
    ``vrw_differs`` (3,); ``rate_hz``, ``duration_s`` (sum of the segments) and ``segments`` of the input.
    """

    taus_s: np.ndarray
    adev_mps2: np.ndarray
    err_mps2: np.ndarray
    vrw_mps_per_sqrt_h: np.ndarray
    bias_instability_mg: np.ndarray
    bi_tau_s: np.ndarray
    rate_hz: float
    duration_s: float
    bi_is_upper_bound: np.ndarray = field(default_factory=lambda: np.zeros(3, bool))
    white_noise_vrw_mps_per_sqrt_h: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    white_tau_range_s: np.ndarray = field(default_factory=lambda: np.full((3, 2), np.nan))
    segments: int = 1

    @property
    def vrw_differs(self) -> np.ndarray:
        """Axes whose white-noise VRW differs from 60 ADEV(1 s) by more than ``VRW_DIFF_FLAG``."""
        with np.errstate(invalid="ignore"):
            rel = np.abs(self.vrw_mps_per_sqrt_h / self.white_noise_vrw_mps_per_sqrt_h - 1.0)
        return np.nan_to_num(rel, nan=0.0) > VRW_DIFF_FLAG

    def bi_text(self, j: int) -> str:
        return ("< " if self.bi_is_upper_bound[j] else "") + f"{self.bias_instability_mg[j]:.3g}"

    def white_text(self, j: int) -> str:
        if not np.isfinite(self.white_noise_vrw_mps_per_sqrt_h[j]):
            return "no white region"
        lo, hi = self.white_tau_range_s[j]
        return (f"{self.white_noise_vrw_mps_per_sqrt_h[j]:.3g} (τ {lo:.3g}..{hi:.3g} s)"
                + (" ≠" if self.vrw_differs[j] else ""))

    def table_markdown(self) -> str:
        lines = ["| axis | VRW = 60·ADEV(1 s) [m/s/√h] | white-noise VRW, −1/2 line [m/s/√h] | "
                 "bias instability [mg] | τ at minimum [s] |", "|---|---|---|---|---|"]
        for i, ax in enumerate(AXES[: len(self.vrw_mps_per_sqrt_h)]):
            lines.append(f"| {ax} | {self.vrw_mps_per_sqrt_h[i]:.3g} | {self.white_text(i)} | {self.bi_text(i)} | "
                         f"{self.bi_tau_s[i]:.3g} |")
        if self.bi_is_upper_bound.any():
            lines.append("\n< x: no minimum of the ADEV within 1 s .. length/20: an upper bound of the "
                         "bias-instability floor, not a measurement of it (record longer)")
        if self.vrw_differs.any():
            lines.append("≠: 60·ADEV(1 s) and the −1/2 line differ by more than 5 % (the noise is not white at "
                         "τ = 1 s, e.g. behind the amplifier low-pass)")
        return "\n".join(lines)

    def as_dict(self) -> dict:
        return {"rate_hz": self.rate_hz, "duration_s": self.duration_s, "segments": self.segments,
                "vrw_mps_per_sqrt_h": self.vrw_mps_per_sqrt_h.tolist(),
                "white_noise_vrw_mps_per_sqrt_h": [None if not np.isfinite(v) else float(v)
                                                    for v in self.white_noise_vrw_mps_per_sqrt_h],
                "white_tau_range_s": [None if not np.all(np.isfinite(r)) else [float(v) for v in r]
                                      for r in self.white_tau_range_s],
                "vrw_differs": self.vrw_differs.tolist(),
                "bias_instability_mg": self.bias_instability_mg.tolist(),
                "bi_is_upper_bound": np.asarray(self.bi_is_upper_bound, bool).tolist(),
                "bi_tau_s": [float(f"{v:.6g}") for v in self.bi_tau_s],
                "definitions": "VRW = 60*ADEV(1 s) (paper eq. 26); white-noise VRW = 60*N from a -1/2 slope line "
                               "over white_tau_range_s; BI = min ADEV / 0.664 (eq. 27), over 1 s <= tau <= "
                               "length/20; bi_is_upper_bound: no minimum there, BI is only an upper bound"}


def cluster_taus(rate_hz: float, n_samples: int) -> np.ndarray:
    """Log-spaced cluster times (s), multiples of the sample period, including 1 s when reachable."""
    m_max = max(1, (n_samples - 1) // 2)
    m = np.unique(np.round(np.logspace(0, np.log10(m_max), int(TAUS_PER_DECADE * np.log10(max(m_max, 10))) + 1)))
    one_s = round(rate_hz)
    if 1 <= one_s <= m_max and abs(one_s - rate_hz) < 1e-9:
        m = np.unique(np.r_[m, one_s])
    return m / rate_hz


def _pooled_oadev(segments: list[np.ndarray], ms: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping AVAR (T, k) pooled over segments (clusters within one segment only), term counts (T,)
    and Greenhall edf (T,) summed over the segments (white FM)."""
    k = segments[0].shape[1]
    ss = np.zeros((len(ms), k))
    cnt = np.zeros(len(ms))
    edf = np.zeros(len(ms))
    for seg in segments:
        n = len(seg)
        c = np.vstack([np.zeros((1, k)), np.cumsum(seg - seg.mean(axis=0), axis=0)])  # phase, x_0..x_n
        for i, m in enumerate(ms):
            m = int(m)
            if n < 2 * m + 1:
                continue
            d2 = c[2 * m:] - 2 * c[m:-m] + c[: -2 * m]  # second differences of the phase: m (ybar_2 - ybar_1)
            ss[i] += np.sum(d2**2, axis=0) / m**2
            cnt[i] += len(d2)
            edf[i] += allantools.edf_greenhall(alpha=0, d=2, m=m, N=n + 1, overlapping=True, modified=False)
    with np.errstate(invalid="ignore", divide="ignore"):
        avar = ss / (2.0 * cnt[:, None])
    return avar, cnt, edf


def _white_noise_line(taus: np.ndarray, adev: np.ndarray, edf: np.ndarray, tau_max: float) -> tuple[float, float, float]:
    """N (m/s/sqrt(s)) and the tau range of the -1/2 line fit, NaNs without a white-noise region.

    The region is located with the IEEE Std 952 (Annex C) least-squares fit of the Allan variance
    A/tau^2 + N^2/tau + C + K tau over 1 s <= tau <= ``tau_max`` (weights: the estimate's relative error
    sqrt(2/edf); N^2, C, K >= 0); A < 0 is the low-pass (A > 0 quantisation), C the flicker floor, K a rate
    random walk. The white-noise region is the
    run of cluster times, around the one where N^2/tau dominates most, on which the other terms are within
    ``WHITE_OTHER_TERMS`` of N^2/tau. N is then the -1/2 line through the measured ADEV there (edf-weighted mean
    of log(ADEV sqrt(tau))), not the model's coefficient."""
    sel = (taus >= 1.0) & (taus <= tau_max)
    if sel.sum() < 6:
        return np.nan, np.nan, np.nan
    t, avar, e = taus[sel], adev[sel] ** 2, edf[sel]
    basis = np.stack([t**-2, 1 / t, np.ones_like(t), t], axis=1)
    w = np.sqrt(e / 2.0) / avar
    from scipy.optimize import lsq_linear

    scale = np.array([t[0] ** 2, t[0], 1.0, 1.0 / t[0]]) * avar[0]  # well-conditioned coefficients
    fit = lsq_linear(basis * scale * w[:, None], avar * w, bounds=([-np.inf, 0, 0, 0], np.inf))
    coef = fit.x * scale
    if coef[1] <= 0:
        return np.nan, np.nan, np.nan
    white = coef[1] / t
    other = np.abs(basis @ coef - white) / white
    ok = other <= WHITE_OTHER_TERMS
    if not ok.any():
        return np.nan, np.nan, np.nan
    c = int(np.argmin(other))
    lo, hi = c, c
    while lo > 0 and ok[lo - 1]:
        lo -= 1
    while hi + 1 < len(ok) and ok[hi + 1]:
        hi += 1
    if np.log10(t[hi] / t[lo]) < WHITE_MIN_DECADES - 1e-9:
        return np.nan, np.nan, np.nan
    r = slice(lo, hi + 1)
    n_white = float(np.exp(np.average(np.log(adev[sel][r] * np.sqrt(t[r])), weights=e[r])))
    return n_white, float(t[lo]), float(t[hi])


def allan_deviation(accel_mps2: np.ndarray | list[np.ndarray], rate_hz: float) -> AllanResult:
    """Overlapping ADEV of a static series (N,) or (N, k) of specific force (m/s^2) sampled at ``rate_hz``,
    or of a list of such series: continuous segments of one recording, separated by breaks in the time base,
    whose clusters are pooled without any cluster crossing a break."""
    parts = accel_mps2 if isinstance(accel_mps2, list) else [accel_mps2]
    segs = []
    for p in parts:
        x = np.asarray(p, dtype=float)
        segs.append(x[:, None] if x.ndim == 1 else x)
    if rate_hz <= 0:
        raise ValueError(f"rate must be positive, got {rate_hz}")
    longest = max(len(s) for s in segs)
    if longest < 3 * rate_hz:
        raise ValueError(f"{longest} samples at {rate_hz} Hz: need at least 3 s of continuous data for ADEV(1 s)")
    if not all(np.all(np.isfinite(s)) for s in segs):
        raise ValueError("the series contains NaN/inf samples (drop invalid frames first)")
    k = segs[0].shape[1]
    taus_req = cluster_taus(rate_hz, longest)
    ms = np.round(taus_req * rate_hz).astype(int)
    avar, _, edf = _pooled_oadev(segs, ms)
    keep = np.all(np.isfinite(avar), axis=1) & (edf > 0)
    taus, adev, edf = ms[keep] / rate_hz, np.sqrt(avar[keep]), edf[keep]
    err = adev / np.sqrt(2.0 * edf)[:, None]
    adev_1s = np.array([np.exp(np.interp(0.0, np.log(taus), np.log(adev[:, j]))) for j in range(k)])
    duration = sum(len(s) for s in segs) / rate_hz
    tau_max = duration / MIN_CLUSTERS_FOR_MIN
    window = (taus >= 1.0) & (taus <= tau_max)
    upper = np.zeros(k, bool)
    if not window.any():
        window = taus >= 1.0
        upper[:] = True
    idx = np.flatnonzero(window)
    arg = idx[np.argmin(adev[idx], axis=0)]
    upper |= arg == idx[-1]  # still falling at the upper edge: no floor reached
    if idx[0] > 0:  # still rising at 1 s: the floor lies below the window
        upper |= (arg == idx[0]) & (adev[idx[0] - 1] < adev[idx[0]])
    min_adev = adev[arg, np.arange(k)]
    white = np.array([_white_noise_line(taus, adev[:, j], edf, tau_max) for j in range(k)])
    return AllanResult(taus, adev, err, 60.0 * adev_1s, min_adev / BI_FACTOR / MG_TO_MPS2, taus[arg], float(rate_hz),
                       duration, upper, 60.0 * white[:, 0], white[:, 1:], len(segs))


def plot_allan(result: AllanResult, path: str | Path, title: str = "Overlapping Allan deviation",
               reference: dict[str, np.ndarray] | None = None) -> Path:
    """Log-log ADEV plot per axis with the VRW and bias-instability read-outs; PNG at ``path``.

    ``reference`` optionally maps a label to expected ADEV curves (T, 3) on ``result.taus_s``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    colors = ("tab:red", "tab:green", "tab:blue")
    for j in range(result.adev_mps2.shape[1]):
        label = (f"{AXES[j]}: VRW {result.vrw_mps_per_sqrt_h[j]:.3g} m/s/√h, "
                 f"BI {result.bi_text(j)} mg")
        ax.loglog(result.taus_s, result.adev_mps2[:, j], color=colors[j % 3], label=label)
        ax.fill_between(result.taus_s, np.maximum(result.adev_mps2[:, j] - result.err_mps2[:, j], 1e-12),
                        result.adev_mps2[:, j] + result.err_mps2[:, j], color=colors[j % 3], alpha=0.15)
        ax.plot([result.bi_tau_s[j]], [result.bias_instability_mg[j] * BI_FACTOR * MG_TO_MPS2], "o", color=colors[j % 3])
    for name, curves in (reference or {}).items():
        for j in range(curves.shape[1]):
            ax.loglog(result.taus_s, curves[:, j], "--", color=colors[j % 3], lw=0.8,
                      label=f"{name}" if j == 0 else None)
    ax.axvline(1.0, color="0.6", lw=0.8, ls=":")
    ax.set_xlabel("cluster time τ [s]")
    ax.set_ylabel("Allan deviation [m/s²]")
    ax.set_title(f"{title} ({result.duration_s / 3600:.2f} h at {result.rate_hz:g} Hz)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
