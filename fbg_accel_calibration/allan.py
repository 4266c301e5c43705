"""Allan deviation of a static recording, velocity random walk and bias instability (paper 4.4, Table 2).

Pure numpy + allantools + matplotlib (Agg). The overlapping Allan deviation (NIST SP 1065 eq. 11,
``allantools.oadev`` with ``data_type='freq'``: the samples are the calibrated specific force,
a rate-like quantity) is computed per axis at log-spaced cluster times. Figures in the units of
paper Table 2:

* VRW = 60 * ADEV(tau = 1 s), m/s/sqrt(h) (paper eq. 26): ADEV(1 s) in m/s^2 equals the white-noise
  coefficient in m/s/sqrt(s); times sqrt(3600 s/h) = 60. ADEV(1 s) is interpolated log-log when
  1 s is not an exact cluster time.
* bias instability = min ADEV / 0.664, in mg (paper eq. 27; 0.664 = sqrt(2 ln 2 / pi), the flicker
  floor of a bias-instability PSD B^2/(2 pi f), two-sided as in IEEE Std 952). The minimum is
  searched for tau >= 1 s and tau <= record length / 20 (``MIN_CLUSTERS_FOR_MIN``): the last
  octaves rest on a handful of clusters, their confidence interval is very wide (SP 1065) and the
  minimum of noisy values is biased low (``bench/allan_check.py``: one hour of flicker noise reads
  the floor 0.69..1.01 times the configured value, about 10 % low on average). A floor beyond
  length/20 (e.g. a minimum at ~1600 s, which needs ~9 h) is not reached: record longer (the paper
  used 6 h).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import allantools
import numpy as np

MG_TO_MPS2 = 9.80665e-3
BI_FACTOR = 0.664
MIN_CLUSTERS_FOR_MIN = 20  # tau_max for the minimum search = duration / 20
TAUS_PER_DECADE = 20
AXES = ("x", "y", "z")


@dataclass
class AllanResult:
    """Allan deviation per axis: ``taus_s`` (T,), ``adev_mps2`` (T, 3), ``err_mps2`` (T, 3).

    ``vrw_mps_per_sqrt_h`` (3,), ``bias_instability_mg`` (3,) and the cluster time of the minimum
    ``bi_tau_s`` (3,); ``rate_hz`` and ``duration_s`` of the input.
    """

    taus_s: np.ndarray
    adev_mps2: np.ndarray
    err_mps2: np.ndarray
    vrw_mps_per_sqrt_h: np.ndarray
    bias_instability_mg: np.ndarray
    bi_tau_s: np.ndarray
    rate_hz: float
    duration_s: float

    def table_markdown(self) -> str:
        lines = ["| axis | VRW [m/s/√h] | bias instability [mg] | τ at minimum [s] |", "|---|---|---|---|"]
        for i, ax in enumerate(AXES):
            lines.append(f"| {ax} | {self.vrw_mps_per_sqrt_h[i]:.3g} | {self.bias_instability_mg[i]:.3g} | "
                         f"{self.bi_tau_s[i]:.3g} |")
        return "\n".join(lines)

    def as_dict(self) -> dict:
        return {"rate_hz": self.rate_hz, "duration_s": self.duration_s,
                "vrw_mps_per_sqrt_h": self.vrw_mps_per_sqrt_h.tolist(),
                "bias_instability_mg": self.bias_instability_mg.tolist(), "bi_tau_s": self.bi_tau_s.tolist(),
                "definitions": "VRW = 60*ADEV(1 s); BI = min ADEV / 0.664 (paper eq. 26-27)"}


def cluster_taus(rate_hz: float, n_samples: int) -> np.ndarray:
    """Log-spaced cluster times (s), multiples of the sample period, including 1 s when reachable."""
    m_max = max(1, (n_samples - 1) // 2)
    m = np.unique(np.round(np.logspace(0, np.log10(m_max), int(TAUS_PER_DECADE * np.log10(max(m_max, 10))) + 1)))
    one_s = round(rate_hz)
    if 1 <= one_s <= m_max and abs(one_s - rate_hz) < 1e-9:
        m = np.unique(np.r_[m, one_s])
    return m / rate_hz


def allan_deviation(accel_mps2: np.ndarray, rate_hz: float) -> AllanResult:
    """Overlapping ADEV of a static series (N,) or (N, k) of specific force (m/s^2) sampled at ``rate_hz``."""
    x = np.asarray(accel_mps2, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    n, k = x.shape
    if rate_hz <= 0:
        raise ValueError(f"rate must be positive, got {rate_hz}")
    if n < 3 * rate_hz:
        raise ValueError(f"{n} samples at {rate_hz} Hz: need at least 3 s of data for ADEV(1 s)")
    if not np.all(np.isfinite(x)):
        raise ValueError("the series contains NaN/inf samples (drop invalid frames first)")
    taus_req = cluster_taus(rate_hz, n)
    adevs, errs, taus = [], [], None
    for j in range(k):
        t, ad, err, _ = allantools.oadev(x[:, j] - x[:, j].mean(), rate=rate_hz, data_type="freq", taus=taus_req)
        taus = t if taus is None else taus
        adevs.append(ad)
        errs.append(err)
    assert taus is not None
    adev = np.stack(adevs, axis=1)
    err = np.stack(errs, axis=1)
    adev_1s = np.array([np.exp(np.interp(0.0, np.log(taus), np.log(adev[:, j]))) for j in range(k)])
    duration = n / rate_hz
    window = (taus >= 1.0) & (taus <= duration / MIN_CLUSTERS_FOR_MIN)
    if not window.any():
        window = taus >= 1.0
    idx = np.flatnonzero(window)
    arg = idx[np.argmin(adev[idx], axis=0)]
    min_adev = adev[arg, np.arange(k)]
    return AllanResult(taus, adev, err, 60.0 * adev_1s, min_adev / BI_FACTOR / MG_TO_MPS2, taus[arg], float(rate_hz),
                       duration)


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
                 f"BI {result.bias_instability_mg[j]:.3g} mg")
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
