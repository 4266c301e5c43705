"""Model of a measuring chain fitted to dynamic-calibration points (seed 3.1: "comparison with theoretical models").

The chain of one axis, as the ratio sensor / projected reference (sign conventions of
:mod:`tone_analysis`: negative phase = sensor lags), is

    H(f) = K * LP(f) * exp(-j 2 pi f tau) * HP(f)^s,
    LP(f) = 1 / (1 + j f / fc),   HP(f) = (j f / fhp) / (1 + j f / fhp),

with ``K`` the static gain (unitless), ``fc`` the first-order low-pass cut-off (Hz; for this sensor the
axis' TIA, sensor_facts.md: x 1.7 Hz, y/z 1.3 Hz in the static-test build, ~50 Hz in flight), ``tau`` a
pure delay (s; ESP32 sequential sampling skew, transport), and an optional first-order high-pass ``fhp``
(Hz) with s = -1 when it sits in the reference (an AC-coupled LDV, seed 3.1 Fig. 5: ~0.5 Hz; the ratio
then *divides* by it) or s = +1 in the sensor path (seed 3.1 Fig. 4, AC-coupled acquisition).

Why only the axis' low-pass: the output is eq. 24 Psi = c_axis / c_ref; under a slide with a constant
source c_ref is constant, so the reference photodiode's own TIA low-pass (1 Hz) does not act on the
acceleration path. It would only matter if the source power moved during the test.

The fit is weighted nonlinear least squares (``scipy.optimize.least_squares``) on amplitude ratio and phase
together; parameter standard uncertainties come from the Jacobian at the solution.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scipy.optimize import least_squares

from fbg_accel_driver.chain_compensation import MAX_ABS_DELAY_S, first_order_group_delay_s
from fbg_accel_driver.mapping_fields import number

from .tone_analysis import DynamicPoint

HP_LOCATIONS = ("reference", "sensor")


@dataclass
class ChainModel:
    """First-order low-pass + pure delay (+ optional first-order high-pass) of one axis.

    ``gain`` (unitless), ``cutoff_hz``, ``delay_s``, ``highpass_cutoff_hz`` (None: no high-pass),
    ``highpass_in`` ('reference' divides the response by the high-pass, 'sensor' multiplies);
    ``u_*``: standard uncertainties of the fitted parameters (NaN when not fitted / unknown);
    ``axis`` ('x', 'y', 'z' or ''); ``fit``: fit figures (residual rms of amplitude ratio and phase,
    points, degrees of freedom, uncertainty scaling used).
    """

    gain: float = 1.0
    cutoff_hz: float = math.inf
    delay_s: float = 0.0
    highpass_cutoff_hz: float | None = None
    highpass_in: str = "reference"
    u_gain: float = math.nan
    u_cutoff_hz: float = math.nan
    u_delay_s: float = math.nan
    u_highpass_cutoff_hz: float = math.nan
    axis: str = ""
    fit: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for a YAML calibration file; units in the key names."""
        out: dict[str, Any] = {
            "model": "first_order_lowpass_delay" + ("_highpass" if self.highpass_cutoff_hz is not None else ""),
            "axis": self.axis,
            "gain": float(self.gain),
            "cutoff_hz": float(self.cutoff_hz),
            "delay_s": float(self.delay_s),
            "group_delay_dc_s": self.sensor_group_delay_dc_s(),
            "u_gain": _plain(self.u_gain),
            "u_cutoff_hz": _plain(self.u_cutoff_hz),
            "u_delay_s": _plain(self.u_delay_s),
        }
        if self.highpass_cutoff_hz is not None:
            out["highpass_cutoff_hz"] = float(self.highpass_cutoff_hz)
            out["highpass_in"] = self.highpass_in
            out["u_highpass_cutoff_hz"] = _plain(self.u_highpass_cutoff_hz)
        if self.fit:
            out["fit"] = {k: _plain(v) for k, v in self.fit.items()}
        return out

    def sensor_group_delay_dc_s(self) -> float:
        """Group delay at DC (s) of the axis's own chain, ``delay + 1 / (2 pi fc)``: what the driver's stamp
        correction removes (``ChainDynamics.group_delay_s``), the ``group_delay_dc_s`` of :meth:`to_dict` and
        of the report. A fitted high-pass is not in it: in the reference (an AC-coupled LDV) it is not the
        sensor's; in the sensor path its gain at DC is 0 (quote :func:`group_delay_s` at a stated frequency)."""
        return float(first_order_group_delay_s(self.cutoff_hz)) + float(self.delay_s)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ChainModel:
        """Inverse of :meth:`to_dict` (derived keys such as ``group_delay_dc_s`` are ignored)."""
        def num(key: str, default: float | None = None, **check: Any) -> float:
            return number(d.get(key, default), key, ValueError, **check)

        def uncertainty(key: str) -> float:  # absent or null: not known
            return math.nan if d.get(key) is None else num(key, finite=False)

        if "cutoff_hz" not in d:
            raise ValueError("chain model needs cutoff_hz")
        hp = d.get("highpass_cutoff_hz")
        where = str(d.get("highpass_in", "reference"))
        if where not in HP_LOCATIONS:
            raise ValueError(f"highpass_in must be one of {HP_LOCATIONS}, got {where!r}")
        return cls(gain=num("gain", 1.0), cutoff_hz=num("cutoff_hz", positive=True, finite=False), delay_s=num("delay_s", 0.0),
                   highpass_cutoff_hz=None if hp is None else num("highpass_cutoff_hz", positive=True), highpass_in=where,
                   u_gain=uncertainty("u_gain"), u_cutoff_hz=uncertainty("u_cutoff_hz"), u_delay_s=uncertainty("u_delay_s"),
                   u_highpass_cutoff_hz=uncertainty("u_highpass_cutoff_hz"),
                   axis=str(d.get("axis", "")), fit=dict(d.get("fit", {})))


def _plain(v: Any) -> Any:
    """NaN/inf as None-free floats YAML can hold; numpy scalars to Python."""
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and math.isnan(v):
        return None
    return v


def response(model: ChainModel, f_hz: float | np.ndarray) -> np.ndarray:
    """Complex response ``H(f)`` of the chain (unitless), negative phase = sensor lags. ``f_hz`` in Hz."""
    f = np.asarray(f_hz, dtype=float)
    return _response(f, model.gain, model.cutoff_hz, model.delay_s, model.highpass_cutoff_hz, model.highpass_in)


def _response(f: np.ndarray, k: float, fc: float, tau: float, fhp: float | None, where: str) -> np.ndarray:
    h = k / (1.0 + 1j * f / fc) * np.exp(-2j * np.pi * f * tau)
    if fhp is not None:
        hp = (1j * f / fhp) / (1.0 + 1j * f / fhp)
        h = h / hp if where == "reference" else h * hp
    return h


def group_delay_s(model: ChainModel, f_hz: float | np.ndarray) -> np.ndarray | float:
    """Group delay ``-d arg H / d omega`` (s) at ``f_hz``.

    First-order low-pass: ``(1 / (2 pi fc)) / (1 + (f / fc)^2)`` (``1 / (2 pi fc)`` at DC); pure delay: ``tau``;
    a first-order high-pass has the same group delay as a low-pass of its cut-off, added when in the sensor
    path and subtracted when in the reference (the ratio divides by it). The high-pass' group delay at
    exactly DC is its limit ``1 / (2 pi fhp)``, but its gain there is 0: quote it at a stated frequency.
    """
    f = np.asarray(f_hz, dtype=float)
    g = model.delay_s + first_order_group_delay_s(model.cutoff_hz, f)
    if model.highpass_cutoff_hz is not None:
        sign = -1.0 if model.highpass_in == "reference" else 1.0
        g = g + sign * first_order_group_delay_s(model.highpass_cutoff_hz, f)
    return float(g) if np.ndim(g) == 0 else g


def phase_delay_s(model: ChainModel, f_hz: float | np.ndarray) -> np.ndarray | float:
    """Phase delay ``-arg H(f) / (2 pi f)`` (s), what a cross-correlation of tones at f measures (f > 0).

    The phase is unwrapped from the model's parts (low-pass atan, delay, high-pass), not from arg H modulo 2 pi.
    """
    f = np.asarray(f_hz, dtype=float)
    ph = -np.arctan(f / model.cutoff_hz) - 2 * np.pi * f * model.delay_s
    if model.highpass_cutoff_hz is not None:
        php = np.pi / 2 - np.arctan(f / model.highpass_cutoff_hz)
        ph = ph - php if model.highpass_in == "reference" else ph + php
    out = -ph / (2 * np.pi * f)
    return float(out) if np.ndim(out) == 0 else out


def fit_chain_model(points: Sequence[DynamicPoint], highpass: bool = False,
                    highpass_in: Literal["reference", "sensor"] = "reference",
                    uncertainty_scaling: Literal["residual", "points"] = "residual",
                    fit_gain: bool = True) -> ChainModel:
    """Fit :class:`ChainModel` to the measurable points of one axis (seed 3.1: chain vs theoretical model).

    Residuals, for every point: ``(|H_model| - S) / u(S)`` and ``wrap(arg H_model - phase) / u(phase)``
    (phase in rad), i.e. amplitude ratio and phase together, each weighted by its combined standard
    uncertainty from the budget. Points with no usable uncertainty (0 or NaN) fall back to weights of
    1 % in amplitude and 1 degree in phase for every point (then only ``"residual"`` scaling is meaningful).

    ``uncertainty_scaling``: ``"residual"`` -- covariance ``(J^T J)^-1 * chi2 / (m - p)`` (the scatter of the
    points about the model sets the scale; default); ``"points"`` -- ``(J^T J)^-1``, trusting the points'
    uncertainties as absolute. The start is a grid over the cut-offs with the delay and gain solved from
    the phase and amplitude at each grid node, so no initial guess is needed.
    """
    pts = [p for p in points if p.measurable and np.isfinite(p.sensitivity) and np.isfinite(p.phase_deg)]
    axes = {p.axis for p in pts}
    if len(axes) > 1:
        raise ValueError(f"points of several axes {sorted(axes)}: fit one axis at a time")
    n_par = 2 + int(fit_gain) + int(highpass)
    if len(pts) * 2 < n_par + 1:
        raise ValueError(f"{len(pts)} points are too few for {n_par} parameters")
    if highpass_in not in HP_LOCATIONS:
        raise ValueError(f"highpass_in must be one of {HP_LOCATIONS}")
    f = np.array([p.f_hz for p in pts])
    S = np.array([p.sensitivity for p in pts])
    ph = np.deg2rad([p.phase_deg for p in pts])
    uS = np.array([p.u_sensitivity for p in pts])
    uph = np.deg2rad([p.u_phase_deg for p in pts])
    weighted = bool(np.all(np.isfinite(uS) & (uS > 0) & np.isfinite(uph) & (uph > 0)))
    if not weighted:
        uS = 0.01 * S
        uph = np.full_like(f, np.deg2rad(1.0))

    def unpack(x: np.ndarray) -> tuple[float, float, float, float | None]:  # x: ([log K,] log fc, tau[, log fhp])
        i = int(fit_gain)
        return (float(np.exp(x[0])) if fit_gain else 1.0, float(np.exp(x[i])), float(x[i + 1]),
                float(np.exp(x[i + 2])) if highpass else None)

    def resid(x: np.ndarray) -> np.ndarray:
        k, fc, tau, fhp = unpack(x)
        h = _response(f, k, fc, tau, fhp, highpass_in)
        dphi = np.angle(h * np.exp(-1j * ph))  # wrapped phase difference
        return np.concatenate([(np.abs(h) - S) / uS, dphi / uph])

    x0 = _initial_guess(f, S, ph, 1.0 / uph ** 2, fit_gain, highpass, highpass_in, resid)
    sol = least_squares(resid, x0, method="lm" if len(f) * 2 > len(x0) else "trf", x_scale="jac")
    k, fc, tau, fhp = unpack(sol.x)
    # Jacobian is in (log K, log fc, tau, log fhp): chain rule to (K, fc, tau, fhp)
    Jp = sol.jac / np.array(([k] if fit_gain else []) + [fc, 1.0] + ([fhp] if highpass else []))
    dof = sol.jac.shape[0] - sol.jac.shape[1]
    chi2 = float(sol.fun @ sol.fun)
    cov = np.linalg.pinv(Jp.T @ Jp)
    if uncertainty_scaling == "residual":
        cov = cov * (chi2 / dof if dof > 0 else math.nan)
    elif uncertainty_scaling != "points":
        raise ValueError("uncertainty_scaling must be 'residual' or 'points'")
    u = np.sqrt(np.clip(np.diag(cov), 0, None))
    j = int(fit_gain)
    h = _response(f, k, fc, tau, fhp, highpass_in)
    model = ChainModel(gain=k, cutoff_hz=fc, delay_s=tau, highpass_cutoff_hz=fhp, highpass_in=highpass_in,
                       u_gain=float(u[0]) if fit_gain else math.nan,
                       u_cutoff_hz=float(u[j]), u_delay_s=float(u[j + 1]),
                       u_highpass_cutoff_hz=float(u[j + 2]) if highpass else math.nan,
                       axis=pts[0].axis if pts else "")
    model.fit = {"n_points": len(f), "dof": dof, "chi2": chi2, "weighted_by_point_uncertainty": weighted,
                 "uncertainty_scaling": uncertainty_scaling,
                 "rms_amplitude_ratio": float(np.sqrt(np.mean((np.abs(h) - S) ** 2))),
                 "rms_phase_deg": float(np.rad2deg(np.sqrt(np.mean(np.angle(h * np.exp(-1j * ph)) ** 2)))),
                 "f_min_hz": float(f.min()), "f_max_hz": float(f.max()), "converged": bool(sol.success)}
    return model


def _initial_guess(f: np.ndarray, S: np.ndarray, ph: np.ndarray, w_ph: np.ndarray, fit_gain: bool, highpass: bool,
                   where: str, resid: Any) -> np.ndarray:
    """Grid over cut-offs; at each node the candidate delays for the phase left after the low-pass (and
    high-pass), the gain from the amplitude; the candidate with the smallest weighted residual wins, and among
    equal ones (a plan whose frequencies share a common divisor F fixes a delay only modulo 1/F) the one of the
    smallest |delay|.

    The remaining phase (``ph`` in rad less the low-pass' and high-pass' phase) is ``-2 pi f tau + 2 pi k_i``
    with an unknown integer ``k_i`` per point. Candidates: the local minima of its weighted wrapped misfit
    over delays within +-``MAX_ABS_DELAY_S`` (:func:`_delay_candidates`; ``w_ph`` = 1/u(phase)^2 in rad^-2),
    and the line through the phase unwrapped along ``f`` (Hz), with the branch where that line meets f = 0 and
    its neighbours. (Unwrapping alone fails when the phase turns by more than 180 degrees between neighbouring
    frequencies: 80 ms or more on the shipped 0.5-20 Hz plan gave fc 24.7 Hz and 128 ms for 1.7 Hz and 80 ms;
    choosing the branch by the median remaining phase failed whenever the lowest frequency's phase was already
    past -180 degrees.)
    """
    fcs = np.geomspace(max(f.min() / 20, 1e-3), f.max() * 50, 40)
    fhps = np.geomspace(max(f.min() / 20, 1e-3), f.max(), 25) if highpass else [None]
    found: list[tuple[float, float, np.ndarray]] = []  # (cost, |delay|, x)
    for fc in fcs:
        for fhp in fhps:
            h0 = _response(f, 1.0, fc, 0.0, fhp, where)
            left = ph - np.angle(h0)
            rest = np.unwrap(left)
            if f.size >= 2 and np.ptp(f) > 0:
                n0 = round(float(np.polyfit(f, rest, 1)[1]) / (2 * np.pi))
            else:
                n0 = round(float(rest[0]) / (2 * np.pi))
            taus = [float(-(f @ (rest - 2 * np.pi * n)) / (2 * np.pi * (f @ f))) for n in (n0 - 1, n0, n0 + 1)]
            taus += _delay_candidates(f, left, w_ph, MAX_ABS_DELAY_S)
            k = float(np.exp(np.mean(np.log(S / np.abs(h0))))) if fit_gain else 1.0
            for tau in taus:
                x = np.array(([math.log(k)] if fit_gain else []) + [math.log(fc), tau] + ([math.log(fhp)] if highpass else []))
                found.append((float(np.sum(resid(x) ** 2)), abs(tau), x))
    best = min(c for c, _, _ in found)
    tie = best + 1e-9 + 1e-6 * best  # equal up to rounding: the same phases modulo 2 pi
    return min((a for a in found if a[0] <= tie), key=lambda a: a[1])[2]


def _delay_candidates(f: np.ndarray, left: np.ndarray, w: np.ndarray, max_abs_s: float, keep: int = 2) -> list[float]:
    """Delays (s) within +-``max_abs_s`` at the local minima of ``sum w (1 - cos(left + 2 pi f tau))``, the
    weighted misfit of the phases ``left`` (rad, any branch) at ``f`` (Hz) to a pure delay, each refined by
    Gauss-Newton on the wrapped residual; the ``keep`` lowest and every one tied with the lowest.

    The scan's step is 1/(8 f_max), so every minimum has a grid point within 1/16 of the highest frequency's
    period (22.5 degrees) of it; the refinement needs no unwrapping.
    """
    step = 1.0 / (8.0 * float(f.max()))
    grid = np.arange(-max_abs_s, max_abs_s + step / 2, step)
    cost = (w * (1.0 - np.cos(left[None, :] + 2 * np.pi * f[None, :] * grid[:, None]))).sum(axis=1)
    inner = (cost[1:-1] <= cost[:-2]) & (cost[1:-1] <= cost[2:])
    idx = np.flatnonzero(inner) + 1
    if idx.size == 0:
        return []
    # a grid point lies within step/2 of each minimum, so its cost exceeds the minimum's by at most `slack`:
    # refine the `keep` lowest and every one that may tie with the lowest
    slack = float((w * (1.0 - np.cos(np.pi * f * step))).sum())
    order = idx[np.argsort(cost[idx], kind="stable")]
    lowest_grid = float(cost[order[0]])
    chosen = [i for n, i in enumerate(order) if n < keep or cost[i] <= lowest_grid + slack]
    out = []
    for tau in grid[chosen]:
        for _ in range(4):
            r = np.angle(np.exp(1j * (left + 2 * np.pi * f * tau)))
            tau -= float((w * f) @ r) / (2 * np.pi * float((w * f) @ f))
        out.append((float((w * (1.0 - np.cos(left + 2 * np.pi * f * tau))).sum()), float(tau)))
    out.sort()
    lowest = out[0][0]
    return [tau for n, (c, tau) in enumerate(out) if n < keep or c <= lowest + 1e-9 + 1e-6 * lowest]


def fit_chain_models(points: Sequence[DynamicPoint], **kwargs: Any) -> dict[str, ChainModel]:
    """:func:`fit_chain_model` per axis with measurable points; keys 'x', 'y', 'z'."""
    out: dict[str, ChainModel] = {}
    for ax in ("x", "y", "z"):
        pts = [p for p in points if p.axis == ax and p.measurable]
        if pts:
            out[ax] = fit_chain_model(pts, **kwargs)
    return out


def axis_response_matrices(m_static: np.ndarray, models: Sequence[ChainModel], f_hz: float | np.ndarray) -> np.ndarray:
    """The output axes' responses ``M diag(H_channel(f)) M^-1`` (..., 3, 3), complex, unitless.

    ``m_static`` (3, 3): eq. 28's ``M`` at the run's temperature; ``models``: the x, y, z channels' chains (each
    the response of a channel to the component of the acceleration it sees, ``(M^-1 a)_j``); ``f_hz`` in Hz. Row i,
    column k: what output axis i reads of an acceleration along sensor axis k (the diagonal: an axis's own
    response; off the diagonal: the mix of the channels' different dynamics through ``M``, 0 when they are equal).
    """
    m = np.asarray(m_static, dtype=float)
    if m.shape != (3, 3) or len(models) != 3:
        raise ValueError("axis responses need M (3, 3) and the three axis channels' models")
    f = np.asarray(f_hz, dtype=float)
    h = np.stack([response(mod, f) for mod in models], axis=-1)  # (..., 3)
    return np.einsum("ij,...j,jk->...ik", m, h, np.linalg.inv(m))


def axis_response_along(m_static: np.ndarray, models: Sequence[ChainModel], direction: Sequence[float],
                        f_hz: float | np.ndarray) -> np.ndarray:
    """Each output axis's response (..., 3) to an acceleration along ``direction`` (unit vector, sensor frame), as
    :func:`tone_analysis.analyse_run` measures it: ``(M diag(H) M^-1 d)_i / d_i`` (complex, unitless)."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    return np.einsum("...ik,k->...i", axis_response_matrices(m_static, models, f_hz), d) / d
