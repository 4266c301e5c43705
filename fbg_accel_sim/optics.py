"""Optical model of one axis: a push-pull FBG pair read by dual reflection (paper 3.3-3.4).

Pure numpy. The detected power of an axis is (paper eq. 13)::

    P = A_b/16 * integral s(lambda) r2(lambda) r1(lambda) dlambda

Grating profiles (per axis, both gratings of a pair alike): super-Gaussian

    r(lambda) = R exp(-ln 2 |2 (lambda - lambda_j) / FWHM|^(2 m))

with order ``m`` (1 = Gaussian, larger = flatter top and steeper edges). The paper gives no analytic
shape: its gratings are ~3 nm wide (3.2), above 80 % reflectivity, and the six differ in bandwidth,
reflectivity and side-lobe suppression, which is why the axes' non-linearities differ (4.2, Fig. 7).
The order and the FWHM of each axis are the two numbers that stand for that shape (config
``optics.grating_super_gaussian_order`` and ``optics.grating_fwhm_nm``).

For a pair centred at lambda_c with separation d, r1 r2 = R^2 p(lambda - lambda_c + d/2) p(lambda - lambda_c - d/2),
so with the SLD nearly flat across the gratings (40 nm vs 3 nm, the paper's own simplification,
eq. 12) the integral splits into

* an overlap O(d) = integral p(x + d/2) p(x - d/2) dx (the autocorrelation of the profile, even in d,
  largest at d = 0 where the peaks cross) that carries the acceleration: d = d0 - S a, S = 112 pm/g,
  d0 = 2.5 nm; monotonic for d > 0, i.e. a < d0/S = 22.3 g, non-injective beyond (eq. 22, Fig. 9).
  Computed numerically (FFT autocorrelation on a 1 pm grid) and tabulated once; and
* a source factor exp(-k (lambda_c - lambda_s)^2) that carries the SLD wavelength drift relative to the
  gratings (paper 3.6.2), exact for Gaussian gratings, k = (1/sigma_g^2)(1/(2 sigma_s^2)) / (1/sigma_g^2 + 1/(2 sigma_s^2)),
  evaluated with the Gaussian sigma of the same FWHM (the grating shape changes k by < 0.3 %).

The sign convention: the peaks approach for positive acceleration along the axis, so Psi grows
with acceleration, as the positive diagonal of the published calibration matrix implies (the
paper's Fig. 9 draws the crossing on the negative side; that is a sign of the mounting).

Non-linearity (paper 3.4, eq. after 22, and 4.2, Fig. 12): ``nonlinearity_percent_fs`` =
max |y_m - y_f| / (max y_m - min y_m) x 100, y_m the relative optical power O(d0 - S a)/O(d0) on a
uniform grid of a over [-a_fs, a_fs], y_f its least-squares line. ``python -m
fbg_accel_sim.optics --report`` prints it per axis for a config (docs/simulator.md).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
STANDARD_G = 9.80665  # m/s^2 per g: the paper's 112 pm/g is per g_E, taken there as 9.81 (section 1; 0.03 % apart)
PAPER_NONLINEARITY_PERCENT = {"x": 6.6, "y": 6.3}  # paper 4.2 at 180 m/s^2; z "the lowest" (no number given)
PAPER_RANGE_MPS2 = 180.0  # paper 4.2: "within the range up to 180 m/s^2"
_TABLE_STEP_NM = 0.001  # lag step of the tabulated overlap (nm)


def grating_sigma_nm(fwhm_nm: np.ndarray | float) -> np.ndarray:
    """Gaussian sigma (nm) of a grating with the given FWHM (nm)."""
    return np.asarray(fwhm_nm, dtype=float) * FWHM_TO_SIGMA


def super_gaussian(x_nm: np.ndarray, fwhm_nm: float, order: float) -> np.ndarray:
    """Peak-normalised super-Gaussian reflectivity profile exp(-ln2 |2x/FWHM|^(2 order)), x in nm from the peak."""
    z = np.abs(2.0 * np.asarray(x_nm, dtype=float) / float(fwhm_nm))
    return np.exp(-math.log(2.0) * z ** (2.0 * float(order)))


class PairOverlap:
    """Overlap O(d) of the FBG pairs of k axes, super-Gaussian gratings of given FWHM and order.

    ``values(d)`` takes separations d (nm) of shape (..., k) and returns O(d) normalised to O(0) = 1
    (the spectra crossing). The table covers |d| <= ``max_lag_nm``; beyond it O is held at its last
    (negligible) value.
    """

    def __init__(self, fwhm_nm: Sequence[float] | np.ndarray, order: Sequence[float] | np.ndarray,
                 max_lag_nm: float = 20.0) -> None:
        self.fwhm_nm = np.atleast_1d(np.asarray(fwhm_nm, dtype=float))
        self.order = np.atleast_1d(np.asarray(order, dtype=float))
        if self.fwhm_nm.shape != self.order.shape:
            raise ValueError("grating FWHM and order need one value per axis each")
        if np.any(~(self.fwhm_nm > 0)) or np.any(~(self.order >= 0.5)):
            raise ValueError("grating FWHM must be > 0 nm and super-Gaussian order >= 0.5")
        h = _TABLE_STEP_NM
        n_lag = round(max_lag_nm / h)
        self.lag_nm = np.arange(n_lag + 1) * h
        tables = []
        for w, m in zip(self.fwhm_nm, self.order, strict=True):
            half = _profile_half_support(w, m)
            x = np.arange(-half, half + h / 2, h)
            p = super_gaussian(x, w, m)
            nfft = 1 << math.ceil(math.log2(max(2 * len(x), n_lag + 1)))
            f = np.fft.rfft(p, nfft)
            ac = np.fft.irfft(f * np.conj(f), nfft)[: n_lag + 1] * h  # lag j*h: sum p(x) p(x + j h) h
            tables.append(ac / ac[0])
        self.table = np.array(tables)  # (k, n_lag + 1), O(0) = 1

    @property
    def n_axes(self) -> int:
        return len(self.fwhm_nm)

    def select(self, axis: int) -> PairOverlap:
        """A one-axis view (shares the table)."""
        out = object.__new__(PairOverlap)
        out.fwhm_nm = self.fwhm_nm[axis:axis + 1]
        out.order = self.order[axis:axis + 1]
        out.lag_nm = self.lag_nm
        out.table = self.table[axis:axis + 1]
        return out

    def values(self, d_nm: np.ndarray) -> np.ndarray:
        """O(d) / O(0) for separations ``d_nm`` (..., k) in nm (O is even in d)."""
        d = np.abs(np.asarray(d_nm, dtype=float))
        d_b = np.broadcast_to(d, np.broadcast_shapes(d.shape, (self.n_axes,)))
        out = np.empty(d_b.shape)
        for j in range(self.n_axes):
            out[..., j] = np.interp(d_b[..., j], self.lag_nm, self.table[j])
        return out

    def exact(self, d_nm: float, axis: int = 0) -> float:
        """O(d) / O(0) by direct quadrature (no table), for slopes at a point."""
        w, m = float(self.fwhm_nm[axis]), float(self.order[axis])
        h = _TABLE_STEP_NM / 2.0
        half = _profile_half_support(w, m) + abs(d_nm)
        x = np.arange(-half, half + h / 2, h)
        num = np.sum(super_gaussian(x + d_nm / 2.0, w, m) * super_gaussian(x - d_nm / 2.0, w, m))
        den = np.sum(super_gaussian(x, w, m) ** 2)
        return float(num / den)

    def log_derivatives(self, d_nm: float, step_nm: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
        """(O'/O, O''/O) at separation ``d_nm`` for each axis (1/nm, 1/nm^2), central differences on ``exact``."""
        k1, k2 = [], []
        for j in range(self.n_axes):
            lo, mid, hi = (self.exact(d_nm + s, j) for s in (-step_nm, 0.0, step_nm))
            k1.append((hi - lo) / (2.0 * step_nm) / mid)
            k2.append((hi - 2.0 * mid + lo) / step_nm**2 / mid)
        return np.array(k1), np.array(k2)


def _profile_half_support(fwhm_nm: float, order: float) -> float:
    """Half-width (nm) beyond which the profile is below 1e-18 of its peak (it adds nothing to the overlap)."""
    # ln2 (2x/w)^(2m) = 18 ln 10  ->  x = w/2 (18 ln10 / ln2)^(1/(2m))
    return 0.5 * fwhm_nm * (18.0 * math.log(10.0) / math.log(2.0)) ** (1.0 / (2.0 * order))


def source_factor(center_offset_nm: np.ndarray, sigma_g_nm: np.ndarray, sigma_s_nm: float) -> np.ndarray:
    """Source spectral factor exp(-k (lambda_c - lambda_s)^2) of the factorised eq. 13 integral."""
    a = 1.0 / np.asarray(sigma_g_nm) ** 2
    b = 1.0 / (2.0 * sigma_s_nm**2)
    k = a * b / (a + b)
    off = np.asarray(center_offset_nm, dtype=float)
    return np.exp(-k * off * off)


def relative_response(u_mps2: np.ndarray, d0_nm: float, s_nm_per_mps2: float, pair: PairOverlap,
                      nonlinearity: float, d_extra_nm: np.ndarray | float = 0.0,
                      rest_log_slope_per_nm: np.ndarray | None = None) -> np.ndarray:
    """Detected power of the axes relative to rest, for axis inputs ``u_mps2`` (..., k) in m/s^2.

    ``d_extra_nm`` adds a separation change that is not acceleration (thermal mismatch, creep).
    ``nonlinearity`` = 1 gives the physical overlap; 0 the tangent at rest (linearised response);
    values in between scale the difference (the ``spectral_nonlinearity`` effect).
    ``rest_log_slope_per_nm`` (O'/O at d0, per axis) may be passed to avoid recomputing it.
    """
    d = d0_nm - s_nm_per_mps2 * np.asarray(u_mps2, dtype=float) + d_extra_nm
    o0 = pair.values(np.full(pair.n_axes, d0_nm))
    phys = pair.values(d) / o0
    if nonlinearity == 1.0:
        return phys
    if rest_log_slope_per_nm is None:
        rest_log_slope_per_nm = pair.log_derivatives(d0_nm)[0]
    lin = 1.0 + np.asarray(rest_log_slope_per_nm) * (d - d0_nm)
    return lin + nonlinearity * (phys - lin)


def nonlinearity_percent_fs(a_mps2: np.ndarray, y: np.ndarray) -> float:
    """Paper 3.4 non-linearity: max |y_m - y_f| / FS x 100, y_f the least-squares line, FS = max y_m - min y_m."""
    a = np.asarray(a_mps2, dtype=float)
    ym = np.asarray(y, dtype=float)
    coeff = np.polyfit(a, ym, 1)
    yf = np.polyval(coeff, a)
    return float(np.max(np.abs(ym - yf)) / (ym.max() - ym.min()) * 100.0)


def target_log_slope_per_nm(cfg: Any) -> np.ndarray:
    """O'/O at rest (1/nm, magnitude) each axis needs so the simulated sensor reproduces the published M.

    With axis inputs u = D^-1 J f (J = M^-1, D = diag J) and counts_i = rest_i (1 + k_i S u_i), the fitted
    Psi -> f matrix is M D diag(ref / (rest k S)), so M is reproduced when k_i = ref J_ii / (rest_i S),
    ref and rest_i the rest counts (ref with its dark offset, axes without).
    """
    o = cfg.get("optics")
    rc = o["rest_counts"]
    dark = np.asarray(cfg.get("effects.reference_dark_offset.counts"), float)
    rest = np.array([float(rc[k]) for k in ("x", "y", "z")]) - dark[1:]
    ref = float(rc["ref"])
    s = float(o["differential_sensitivity_pm_per_g"]) * 1e-3 / STANDARD_G
    jd = np.diag(np.linalg.inv(np.asarray(o["published_M"], float)))
    if not o.get("cross_axis_from_published_M", True):
        jd = 1.0 / np.diag(np.asarray(o["published_M"], float))
    return ref * jd / (rest * s)


def fwhm_for_log_slope(target_per_nm: float, order: float, d0_nm: float, lo: float = 0.5, hi: float = 20.0) -> float:
    """FWHM (nm) of a super-Gaussian pair of the given order whose O'/O at d0 is ``-target_per_nm`` (bisection)."""
    for _ in range(50):
        w = math.sqrt(lo * hi)
        k = -PairOverlap([w], [order], max_lag_nm=d0_nm + 1.0).log_derivatives(d0_nm)[0][0]
        if k > target_per_nm:
            lo = w  # too steep: wider grating
        else:
            hi = w
        if hi / lo < 1 + 1e-7:
            break
    return math.sqrt(lo * hi)


def axis_linearity(pair: PairOverlap, d0_nm: float, s_nm_per_mps2: float, a_fs_mps2: float, n: int = 721) -> list[float]:
    """Non-linearity (% FS) of each axis over [-a_fs, a_fs] (paper metric, ``nonlinearity_percent_fs``)."""
    a = np.linspace(-a_fs_mps2, a_fs_mps2, n)
    y = relative_response(a[:, None], d0_nm, s_nm_per_mps2, pair, 1.0)
    return [nonlinearity_percent_fs(a, y[:, j]) for j in range(pair.n_axes)]


def linearity_report(cfg: Any) -> dict[str, Any]:
    """Per-axis optics figures of a simulator config: shape, slope and curvature at rest, non-linearity, injectivity."""
    o = cfg.get("optics")
    d0 = float(o["pair_separation_nm"])
    s = float(o["differential_sensitivity_pm_per_g"]) * 1e-3 / STANDARD_G
    fwhm = np.asarray(o["grating_fwhm_nm"], float)
    order = np.asarray(o["grating_super_gaussian_order"], float)
    pair = PairOverlap(fwhm, order)
    k1, k2 = pair.log_derivatives(d0)
    target = target_log_slope_per_nm(cfg)
    eps_paper = axis_linearity(pair, d0, s, PAPER_RANGE_MPS2)
    eps_20g = axis_linearity(pair, d0, s, 20.0 * STANDARD_G)
    a20 = np.linspace(-20.0, 20.0, 4001) * STANDARD_G
    r20 = relative_response(a20[:, None], d0, s, pair, 1.0)
    beyond = np.linspace(20.0, 30.0, 2001) * STANDARD_G
    rb = relative_response(beyond[:, None], d0, s, pair, 1.0)
    axes = {}
    for j, name in enumerate("xyz"):
        cross = float(super_gaussian(np.array([d0 / 2.0]), fwhm[j], order[j])[0])
        peak_g = float(beyond[int(np.argmax(rb[:, j]))] / STANDARD_G)
        axes[name] = {
            "grating_fwhm_nm": float(fwhm[j]), "super_gaussian_order": float(order[j]),
            "reflectivity_at_crossing_rel_peak": cross,
            "log_slope_at_rest_per_nm": float(-k1[j]), "log_slope_for_published_M_per_nm": float(target[j]),
            "relative_slope_per_g": float(-k1[j] * s * STANDARD_G),
            # where the tangent at rest reaches zero power: a response this steep at rest cannot stay linear beyond
            "tangent_zero_power_at_g": float(1.0 / (k1[j] * s * STANDARD_G)),
            "curvature_at_rest_per_mps2_sq": float(0.5 * k2[j] * s * s),
            "nonlinearity_1g_percent_of_1g": float(0.5 * k2[j] * s * s * STANDARD_G / (-k1[j] * s) * 100.0),
            "nonlinearity_pct_fs_pm180": eps_paper[j], "nonlinearity_pct_fs_pm20g": eps_20g[j],
            "paper_nonlinearity_pct_fs_180": PAPER_NONLINEARITY_PERCENT.get(name),
            "monotonic_pm20g": bool(np.all(np.diff(r20[:, j]) > 0)),
            "max_overlap_at_g": peak_g,
            "crossing_g": d0 / (s * STANDARD_G),
        }
    return {"range_mps2": PAPER_RANGE_MPS2, "metric": "max|y_m - y_f| / (max y_m - min y_m) x 100, y_f least squares, "
            "y_m = O(d0 - S a)/O(d0) on 721 points over [-a_fs, a_fs]", "axes": axes}


def order_scan(cfg: Any, orders: Sequence[float]) -> dict[str, list[dict[str, float]]]:
    """For each axis and super-Gaussian order: the FWHM that reproduces the published M, and the figures it gives."""
    o = cfg.get("optics")
    d0 = float(o["pair_separation_nm"])
    s = float(o["differential_sensitivity_pm_per_g"]) * 1e-3 / STANDARD_G
    target = target_log_slope_per_nm(cfg)
    out: dict[str, list[dict[str, float]]] = {}
    for j, name in enumerate("xyz"):
        rows = []
        for m in orders:
            w = fwhm_for_log_slope(float(target[j]), float(m), d0)
            pair = PairOverlap([w], [m])
            k2 = pair.log_derivatives(d0)[1][0]
            rows.append({"order": float(m), "fwhm_nm": w,
                         "reflectivity_at_crossing_rel_peak": float(super_gaussian(np.array([d0 / 2]), w, m)[0]),
                         "curvature_at_rest_per_mps2_sq": float(0.5 * k2 * s * s),
                         "nonlinearity_pct_fs_pm180": axis_linearity(pair, d0, s, PAPER_RANGE_MPS2)[0],
                         "nonlinearity_pct_fs_pm20g": axis_linearity(pair, d0, s, 20.0 * STANDARD_G)[0]})
        out[name] = rows
    return out


SCAN_ORDERS = (1.0, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 3.5, 4.0)
ORDER_TOLERANCE_PCT_FS = 0.25


def choose_order(rows: list[dict[str, float]], tol_pct_fs: float = ORDER_TOLERANCE_PCT_FS) -> dict[str, float]:
    """The lowest order whose +-180 m/s^2 non-linearity is within ``tol_pct_fs`` of the lowest in ``rows``.

    Higher orders than that buy less than ``tol_pct_fs`` of linearity while making the gratings wider and
    flatter, i.e. further from the paper's ~3 nm and 50 % crossing (3.2, 3.4).
    """
    best = min(r["nonlinearity_pct_fs_pm180"] for r in rows)
    return min((r for r in rows if r["nonlinearity_pct_fs_pm180"] <= best + tol_pct_fs), key=lambda r: r["order"])


def _print_report(rep: dict[str, Any]) -> None:
    print(f"non-linearity metric: {rep['metric']}")
    print("axis  order  FWHM_nm  r(d0/2)/R  O'/O@rest  (for M)  tangent_0_g  curv_1g_%  NL_%FS_+-180  NL_%FS_+-20g  paper"
          "  monotonic  peak_g")
    for name, a in rep["axes"].items():
        paper = a["paper_nonlinearity_pct_fs_180"]
        paper_txt = f"{paper:.1f}" if paper else "lowest"
        print(f"{name:>4}  {a['super_gaussian_order']:5.2f}  {a['grating_fwhm_nm']:7.3f}"
              f"  {a['reflectivity_at_crossing_rel_peak']:9.2f}"
              f"  {a['log_slope_at_rest_per_nm']:9.4f}  {a['log_slope_for_published_M_per_nm']:7.4f}"
              f"  {a['tangent_zero_power_at_g']:11.2f}"
              f"  {a['nonlinearity_1g_percent_of_1g']:9.2f}  {a['nonlinearity_pct_fs_pm180']:12.2f}"
              f"  {a['nonlinearity_pct_fs_pm20g']:12.2f}  {paper_txt:>5}"
              f"  {a['monotonic_pm20g']!s:>9}  {a['max_overlap_at_g']:6.2f}")


def main(argv: list[str] | None = None) -> int:
    """``python -m fbg_accel_sim.optics --report [--config F] [--set k=v]... [--scan-orders] [--json FILE]``."""
    from .sim_config import SimConfig, SimConfigError, parse_set_argument

    p = argparse.ArgumentParser(prog="python -m fbg_accel_sim.optics",
                                description="Per-axis optics figures of the simulated sensor (paper 3.4, 4.2).")
    p.add_argument("--report", action="store_true", help="print the per-axis non-linearity report")
    p.add_argument("--config", default=None, help="simulator config merged on sim_default.yaml")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key (repeatable)")
    p.add_argument("--scan-orders", action="store_true",
                   help="for super-Gaussian orders 1..4: the FWHM reproducing the published M, its non-linearity, "
                        "the chosen order")
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    p.add_argument("--force", action="store_true", help="replace an existing --json file")
    args = p.parse_args(argv)
    if not (args.report or args.scan_orders):
        p.error("nothing to do: give --report and/or --scan-orders")
    from fbg_accel_calibration.io.atomic_output import atomic_path, check_outputs

    try:
        check_outputs([args.json], [args.config] if args.config else [], args.force)
        cfg = SimConfig.load(args.config) if args.config else SimConfig.default()
        if args.set:
            cfg = cfg.with_overrides(dict(parse_set_argument(s) for s in args.set))
        out: dict[str, Any] = {}
        if args.report:
            out["report"] = linearity_report(cfg)
            _print_report(out["report"])
        if args.scan_orders:
            out["scan"] = order_scan(cfg, SCAN_ORDERS)
            print(f"orders {SCAN_ORDERS}, FWHM solved for the published M; '<' = chosen (lowest order within "
                  f"{ORDER_TOLERANCE_PCT_FS} % FS of the axis' lowest +-180 m/s^2 non-linearity)")
            print("axis  order  FWHM_for_M_nm  r(d0/2)/R  curv_1g_%  NL_%FS_+-180  NL_%FS_+-20g")
            s = float(cfg.get("optics.differential_sensitivity_pm_per_g")) * 1e-3 / STANDARD_G
            target = target_log_slope_per_nm(cfg)
            out["chosen"] = {}
            for j, (name, rows) in enumerate(out["scan"].items()):
                chosen = choose_order(rows)
                out["chosen"][name] = chosen
                for r in rows:
                    c1g = r["curvature_at_rest_per_mps2_sq"] * STANDARD_G / (target[j] * s) * 100.0
                    print(f"{name:>4}  {r['order']:5.2f}  {r['fwhm_nm']:13.3f}  {r['reflectivity_at_crossing_rel_peak']:9.2f}"
                          f"  {c1g:9.2f}  {r['nonlinearity_pct_fs_pm180']:12.2f}  {r['nonlinearity_pct_fs_pm20g']:12.2f}"
                          f"{'  <' if r is chosen else ''}")
    except (SimConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        with atomic_path(args.json) as tmp:  # a file written whole or not at all
            tmp.write_text(json.dumps(out, indent=2), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
