"""Declared extra model terms added by ``fbg-accel-calib diagnose`` (registry; pure numpy).

Each term is a class with a ``kind`` string, ``to_dict``/``from_dict`` for the calibration
YAML (``from_dict`` refuses missing, non-numeric, wrongly shaped or unphysical parameters with a
``ValueError`` naming the term and parameter), ``new_state()`` for streaming state (``None`` for a
stateless term) and ``contribution(cal, inputs, state) -> (N, 3)`` additive m/s^2 on top of
eq. 28, where ``inputs`` is a :class:`TermInputs` (``ref`` (N,), ``xyz`` (N, 3) counts, ``psi``
(N, 3), ``temp_c`` (N,) degC, ``t_s`` (N,) board time in s). :class:`CorrectionTerm` is that contract.

Terms are evaluated in list order. Two families exist:

* *input corrections* (``tia_inverse_filter``, ``reference_lowpass``, ``reference_dark_offset``, ``thermal_lag``)
  correct what eq. 28 is fed with (counts, Psi or temperature). Such a term replaces the corrected
  fields of ``inputs`` (so later terms see them) and contributes the resulting change of
  eq. 28, ``base(psi', T') - base(psi, T)``. The contributions telescope, so the calibrated output
  is exactly eq. 28 evaluated on the fully corrected inputs, plus the additive terms.
* *additive terms* (``spectral_nonlinearity``, ``time_drift``, ``thermal_hysteresis``,
  ``channel_offset``) add their own regressors times fitted coefficients (m/s^2).

The empirical additive terms (``spectral_nonlinearity``, ``time_drift``) may carry the span of inputs they were
fitted on (``psi_span``, ``span_s``; ``diagnose`` writes them). Outside it such a term is held at the span's nearest
edge, not extrapolated (a creep fitted on a 10-minute table run is not extended to hours after power-on, nor a
quadratic fitted at +-1 g to a rocket's 10 g), and ``extrapolation(inputs)`` gives, per sample, what the formula
would have added beyond the edge: the driver flags the sample and inflates its covariance by it. A term without
a span (files written before spans existed) is evaluated as written and reports nothing.

Stateful terms (filters) keep everything they need from the previous batch in their state, so a
stream processed in one batch or in many consecutive batches with the same state gives the same
result (``test/test_correction_terms.py``). ``fbg_accel_calibration.diagnosis.effects`` builds the same
regressors for the fit, from these very classes, so the driver and the offline model agree.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import numpy as np

from .mapping_fields import number, number_array


@dataclass
class TermInputs:
    """What eq. 28 is fed with, one row per sample; input corrections replace fields as they go."""

    ref: np.ndarray  # (N,) reference counts
    xyz: np.ndarray  # (N, 3) axis counts
    psi: np.ndarray  # (N, 3) xyz / ref (eq. 24), dimensionless
    temp_c: np.ndarray  # (N,) temperature, degC
    t_s: np.ndarray  # (N,) board time, s


class BaseModel(Protocol):
    """What a term needs of the calibration: eq. 28 without corrections (``ThermalCalibration``)."""

    def base_acceleration(self, psi: np.ndarray, temp_c: np.ndarray | float) -> np.ndarray: ...


class CorrectionTerm(Protocol):
    """A declared term of the calibration file (see the module docstring)."""

    kind: ClassVar[str]

    def new_state(self) -> Any: ...

    def contribution(self, cal: BaseModel, inputs: TermInputs, state: Any) -> np.ndarray: ...

    def to_dict(self) -> dict[str, Any]: ...

    def extrapolation(self, inputs: TermInputs) -> np.ndarray | None:
        """(N, 3) m/s^2: the formula's value minus the value held at its fitted span's edge (0 inside the span);
        ``None`` for a term without a span."""
        ...


CORRECTION_TYPES: dict[str, type] = {}


def correction_from_dict(d: Any) -> CorrectionTerm:
    """Build a correction term from its YAML mapping; unknown kinds are refused. The only caller of the terms'
    ``from_dict``, which therefore get a mapping of their own kind."""
    if not isinstance(d, dict) or "kind" not in d:
        raise ValueError("a correction term must be a mapping with a 'kind'")
    kind = d["kind"]
    if kind not in CORRECTION_TYPES:
        raise ValueError(f"unknown correction kind '{kind}' (known: {sorted(CORRECTION_TYPES)})")
    return CORRECTION_TYPES[kind].from_dict(d)


def _register(cls: type) -> type:
    CORRECTION_TYPES[cls.kind] = cls
    return cls


# ----------------------------------------------------------------------------- parameter parsing
def _scalar(d: dict, key: str, kind: str, *, positive: bool = False, nonneg: bool = False,
            nonzero: bool = False, default: float | None = None) -> float:
    if key not in d:
        if default is not None:
            return float(default)
        raise ValueError(f"{kind}: missing parameter '{key}'")
    v = number(d[key], f"{kind}: parameter '{key}'", ValueError, positive=positive, minimum=0.0 if nonneg else None)
    if nonzero and v == 0:
        raise ValueError(f"{kind}: parameter '{key}' must be non-zero")
    return v


def _array(d: dict, key: str, kind: str, shape: tuple[int, ...], *, nonneg: bool = False) -> np.ndarray:
    if key not in d:
        raise ValueError(f"{kind}: missing parameter '{key}'")
    a = number_array(d[key], f"{kind}: parameter '{key}'", ValueError, finite=False)  # a bool is not a number
    if a.shape != shape:
        raise ValueError(f"{kind}: parameter '{key}' has shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{kind}: parameter '{key}' contains NaN or infinite values")
    if nonneg and np.any(a < 0):
        raise ValueError(f"{kind}: parameter '{key}' must be >= 0")
    return a


def _span(d: dict, key: str, kind: str, shape: tuple[int, ...]) -> np.ndarray | None:
    """An optional fitted span: ``shape`` (..., 2) of finite [low, high] with low <= high; None when absent."""
    if key not in d:
        return None
    a = _array(d, key, kind, shape)
    if np.any(a[..., 0] > a[..., 1]):
        raise ValueError(f"{kind}: parameter '{key}' has a low end above its high end")
    return a


def _lst(a: np.ndarray) -> list:
    return np.asarray(a, dtype=float).tolist()


# ----------------------------------------------------------------------------- streaming filters
# relative change of the sampling step below which the filter coefficient a = 1 - exp(-dt/tau) cannot change by the
# 1e-9 that ``first_order_lowpass`` treats as a new coefficient: |da|/a <= |d dt|/dt (x e^-x <= 1 - e^-x)
_STEP_CHANGE = 5e-10
_SMALLEST_STEP_OVER_TAU = 1e-4  # below, a's rounding error (~1e-16 tau/dt) is no longer far below 1e-9


@dataclass(frozen=True)
class SampleSteps:
    """The sampling steps of a time series that ``first_order_lowpass`` filters many times from a fresh state
    (the diagnosis tries many time constants on one recording): worked out once by :func:`sample_steps`."""

    dt: np.ndarray  # (N,) s, step before each sample (0 before the first; negative steps as 0)
    # indices i >= 1 where dt[i] differs from dt[i-1] by more than _STEP_CHANGE relative and resolution_s, or either is 0
    changes: np.ndarray
    smallest_s: float  # the smallest step at the other samples (inf if there are none)
    resolution_s: float  # time_resolution of the times


def time_resolution(*t_s: float) -> float:
    """The smallest difference of two steps (s) that times as large as ``t_s`` (s) can show: a step is the difference
    of two float64 times, each rounded by up to half a unit in the last place (~2.4e-7 s at 1.7e9 s since 1970, ~1e-12 s
    at an hour of board time), so two steps that differ by less are the same step as far as the times can tell."""
    return 4.0 * np.finfo(float).eps * max(abs(v) for v in t_s)


def sample_steps(t_s: np.ndarray) -> SampleSteps:
    """:class:`SampleSteps` of the board times ``t_s`` (N,) s, for a filter that starts at the first sample."""
    t_s = np.asarray(t_s, dtype=float).reshape(-1)
    resolution = time_resolution(t_s[0], t_s[-1]) if t_s.size else 0.0
    dt = np.zeros_like(t_s)
    np.subtract(t_s[1:], t_s[:-1], out=dt[1:])
    np.maximum(dt, 0.0, out=dt)
    same = np.abs(np.diff(dt)) <= np.maximum(_STEP_CHANGE * dt[1:], resolution)
    same &= dt[1:] > 0
    same &= dt[:-1] > 0
    changes = np.flatnonzero(~same) + 1
    rest = dt[1:][same]
    dt.flags.writeable = False
    return SampleSteps(dt, changes, float(rest.min()) if rest.size else math.inf, resolution)


def _coefficient_cuts(dt: np.ndarray, tau_s: float, steps: SampleSteps | None,
                      resolution_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(a at the first sample of each run of constant coefficient, the runs' bounds) for a = 1 - exp(-dt/tau):
    a new run starts where a differs from the previous sample's by more than 1e-9 relative and by more than a
    step change of ``resolution_s`` (``time_resolution``) moves it (da/d dt = (1 - a) / tau). With ``steps`` (of
    these very ``dt``), a is worked out only where the step changes: elsewhere it cannot change by that much, so
    the runs are the same as from a worked out at every sample."""
    def changed(a: np.ndarray, a_prev: np.ndarray) -> np.ndarray:
        return np.abs(a - a_prev) > np.maximum(1e-9 * np.maximum(a, 1e-300), (1.0 - a) / tau_s * resolution_s)

    if steps is not None and steps.smallest_s / tau_s > _SMALLEST_STEP_OVER_TAU:
        at = np.concatenate([[0], steps.changes])
        a_at = 1.0 - np.exp(-dt[at] / tau_s)
        a_prev = 1.0 - np.exp(-dt[steps.changes - 1] / tau_s)
        new = changed(a_at[1:], a_prev)
        cut = steps.changes[new]
        a_start = np.concatenate([a_at[:1], a_at[1:][new]])
    else:
        a = 1.0 - np.exp(-dt / tau_s)
        cut = np.flatnonzero(changed(a[1:], a[:-1])) + 1
        a_start = a[np.concatenate([[0], cut])]
    return a_start, np.concatenate([[0], cut, [dt.size]])


def uniform_coefficient(tau_s: float, steps: SampleSteps) -> float | None:
    """The coefficient a (y[n] = a x[n] + (1 - a) y[n-1]) that :func:`first_order_lowpass`, started afresh on finite
    input with ``steps``, uses at every sample after the first, when that is one coefficient for the whole series (it
    starts at y[0] = x[0]); None when the sampling makes it change (then only the filter itself knows the runs)."""
    a_start, bounds = _coefficient_cuts(steps.dt, tau_s, steps, steps.resolution_s)
    return float(a_start[1]) if len(bounds) == 3 and bounds[1] == 1 else None


def _same_bits(a: float, b: float) -> bool:
    return np.float64(a).tobytes() == np.float64(b).tobytes()


def _first_sample_then_one_run(xs: np.ndarray, a_start: np.ndarray, bounds: np.ndarray,
                               y_prev: float) -> np.ndarray | None:
    """``first_order_lowpass``'s output of ``xs`` when its runs of one coefficient (``a_start``, ``bounds``) are the
    first sample alone and the rest (a filter started afresh: no step before the first sample, a = 0): the first run
    as the loop works it out, the rest by ``lowpass_after_first`` (one ``lfilter`` call over every sample where it
    gives the same bits); None for other runs."""
    from scipy.signal import lfilter

    if len(a_start) != 2 or bounds[1] != 1:
        return None
    a0 = a_start[0]
    first, _ = lfilter([a0], [1.0, a0 - 1.0], xs[:1], zi=[(1.0 - a0) * y_prev])  # the first run, as the loop does it
    return lowpass_after_first(xs, a_start[1], float(first[0]))


def lowpass_after_first(x: np.ndarray, a: float, y0: float) -> np.ndarray:
    """(n,) y[0] = ``y0``, then y[k] = a x[k] + (1 - a) y[k - 1]: ``lfilter`` over x[1:] from the state (1 - a) y0,
    bit for bit, without the copy of its output into a third array: one call over every sample of ``x`` from a state
    z0 for which its first output and its state after it are, bit for bit, y0 and (1 - a) y0 (checked on the first
    sample by the filter itself; from there on it is the same recursion on the same samples); else the two pieces."""
    from scipy.signal import lfilter

    num, den = [a], [1.0, a - 1.0]
    if len(x) >= 2:
        z0 = y0 - a * float(x[0])  # y0 = a x[0] + z0, up to rounding: checked
        got, zf = lfilter(num, den, x[:1], zi=[z0])
        if _same_bits(float(got[0]), y0) and _same_bits(float(zf[0]), (1.0 - a) * y0):
            return lfilter(num, den, x, zi=[z0])[0]
    out = np.empty(len(x))
    out[0] = y0
    if len(x) > 1:
        out[1:] = lfilter(num, den, x[1:], zi=[(1.0 - a) * y0])[0]
    return out


def first_order_lowpass(x: np.ndarray, t_s: np.ndarray, tau_s: float, state: dict | None,
                        steps: SampleSteps | None = None) -> np.ndarray:
    """Exact first-order low-pass y' = (x - y)/tau for a piecewise-constant input sampled at ``t_s``.

    ``x`` (N,); ``state`` (dict with ``y`` and ``t``, updated in place) continues a previous
    batch; ``None`` or an empty state starts the filter at the first finite sample. NaN input
    samples hold the filter and give NaN output. Vectorised (scipy ``lfilter``) on runs of
    uniform sampling, so 10^6 samples take milliseconds. ``steps`` (``sample_steps(t_s)``, optional):
    the steps of ``t_s`` worked out once for many calls; used when the filter starts afresh on finite
    ``x`` (the result is the same with or without it).
    """
    from scipy.signal import lfilter

    x = np.asarray(x, dtype=float).reshape(-1)
    t_s = np.asarray(t_s, dtype=float).reshape(-1)
    st = state if state is not None else {}
    finite = np.isfinite(x)
    good = None if finite.all() else np.flatnonzero(finite)  # None: every sample (no gather, no scatter)
    if x.size == 0 or (good is not None and good.size == 0):
        return np.full_like(x, np.nan)
    xs, ts = (x, t_s) if good is None else (x[good], t_s[good])
    y_prev, t_prev = st.get("y"), st.get("t")
    if y_prev is None and good is None and steps is not None and steps.dt.size == xs.size:
        y_prev, dt = float(xs[0]), steps.dt
    else:
        steps = None
        if y_prev is None:
            y_prev, t_prev = float(xs[0]), float(ts[0])
        dt = np.empty_like(ts)
        dt[0] = ts[0] - t_prev
        np.subtract(ts[1:], ts[:-1], out=dt[1:])
        np.maximum(dt, 0.0, out=dt)
    # split into runs of (nearly) constant coefficient a (uniform sampling) and filter each run at once
    resolution = steps.resolution_s if steps is not None else time_resolution(ts[0], ts[-1], t_prev)
    a_start, bounds = _coefficient_cuts(dt, tau_s, steps, resolution)
    ys = _first_sample_then_one_run(xs, a_start, bounds, y_prev)
    if ys is not None:
        y_prev = float(ys[-1])
    else:
        ys = np.empty_like(xs)
        for ai, (i, j) in zip(a_start, itertools.pairwise(bounds), strict=True):
            seg, _ = lfilter([ai], [1.0, ai - 1.0], xs[i:j], zi=[(1.0 - ai) * y_prev])
            ys[i:j] = seg
            y_prev = float(seg[-1])
    st["y"], st["t"] = y_prev, float(ts[-1])
    if good is None:
        return ys
    out = np.full_like(x, np.nan)
    out[good] = ys
    return out


class _Base:
    kind: ClassVar[str] = ""

    def new_state(self) -> Any:
        return None

    def extrapolation(self, inputs: TermInputs) -> np.ndarray | None:
        return None  # no fitted span (every term but the empirical additive ones)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.to_dict()})"

    def to_dict(self) -> dict[str, Any]:  # pragma: no cover - overridden
        raise NotImplementedError

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self.to_dict() == other.to_dict()  # type: ignore[attr-defined]

    __hash__ = None  # type: ignore[assignment]


class _HeldInSpan(_Base):
    """An additive term of one input that, outside the span of that input it was fitted on, is held at the span's
    nearest edge (module docstring). Subclasses give ``_input`` (the input from ``TermInputs``), ``_value`` (the
    term's formula, (N, 3) m/s^2) and ``_bounds`` ((low, high) broadcasting against the input, or None)."""

    def _input(self, inputs: TermInputs) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    def _value(self, x: np.ndarray) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    def _bounds(self) -> tuple[Any, Any] | None:  # pragma: no cover - overridden
        raise NotImplementedError

    def _held(self, x: np.ndarray) -> np.ndarray:
        bounds = self._bounds()
        return x if bounds is None else np.clip(x, *bounds)

    def contribution(self, cal: BaseModel, inputs: TermInputs, state: Any) -> np.ndarray:
        return self._value(self._held(self._input(inputs)))

    def extrapolation(self, inputs: TermInputs) -> np.ndarray | None:
        if self._bounds() is None:
            return None
        x = self._input(inputs)
        with np.errstate(over="ignore", invalid="ignore"):  # a warm-up far before its span overflows: inf, capped by the driver
            d = self._value(x) - self._value(self._held(x))
        return np.where(np.isnan(d), np.inf, d)


# ----------------------------------------------------------------------------- input corrections
@_register
class TiaInverseFilter(_Base):
    """Inverse of the first-order TIA low-pass of each channel (paper §3.5, Table 1 cut-offs).

    ``tau_s`` (4,) time constants of ref, x, y, z in s (0 = channel not corrected). The exact
    inverse of the discrete low-pass ``y_k = y_{k-1} + a (x_k - y_{k-1})``, ``a = 1 - exp(-dt/tau)``,
    is ``x_k = y_{k-1} + (y_k - y_{k-1}) / a``; it restores the step response and amplifies
    white noise by about ``1/a``. State: the previous raw counts and board time.
    """

    kind = "tia_inverse_filter"

    def __init__(self, tau_s: np.ndarray) -> None:
        self.tau_s = np.asarray(tau_s, dtype=float).reshape(4)

    @classmethod
    def from_dict(cls, d: dict) -> TiaInverseFilter:
        return cls(_array(d, "tau_s", cls.kind, (4,), nonneg=True))

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "tau_s": _lst(self.tau_s), "channels": ["ref", "x", "y", "z"]}

    def new_state(self) -> dict:
        return {"prev": None, "t": None}

    def correct_counts(self, counts: np.ndarray, t_s: np.ndarray, state: dict) -> np.ndarray:
        """Counts (N, 4) [ref, x, y, z] -> inverse-filtered counts (N, 4); updates ``state``."""
        counts = np.asarray(counts, dtype=float).reshape(-1, 4)
        t_s = np.asarray(t_s, dtype=float).reshape(-1)
        if counts.shape[0] == 0:
            return counts.copy()
        prev, t_prev = state.get("prev"), state.get("t")
        have_prev = prev is not None
        prev_rows = np.vstack([prev if have_prev else counts[0], counts[:-1]])
        prev_t = np.concatenate([[t_prev if have_prev else t_s[0]], t_s[:-1]])
        dt = (t_s - prev_t)[:, None]
        tau = self.tau_s[None, :]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            a = -np.expm1(-dt / np.where(tau > 0, tau, np.inf))
            inv = prev_rows + (counts - prev_rows) / a
        use = (tau > 0) & (dt > 0)
        out = np.where(use, inv, counts)
        state["prev"], state["t"] = counts[-1].copy(), float(t_s[-1])
        return out

    def contribution(self, cal: BaseModel, inputs: TermInputs, state: dict | None) -> np.ndarray:
        if state is None:
            state = self.new_state()
        counts = np.column_stack([inputs.ref, inputs.xyz])
        corr = self.correct_counts(counts, inputs.t_s, state)
        return _replace_psi(cal, inputs, corr[:, 0], corr[:, 1:])


@_register
class ReferenceLowpass(_Base):
    """Causal first-order low-pass of the reference counts before eq. 24: ref' = LPF(ref).

    The ESP32's ADC reads the reference photodetector with its own noise (about 1 count rms on the
    measured series, uncorrelated with the axis channels); dividing by a noisy reference adds that
    noise to Psi. The source power changes slowly (the SLD's wander: minutes), so averaging the
    reference over ``time_constant_s`` (s) removes the read noise and keeps the normalisation.
    Exact for a piecewise-constant input (:func:`first_order_lowpass`); state: the filter
    output and the board time of the last sample, so the driver's stream gives the offline result.
    """

    kind = "reference_lowpass"
    MAX_TIME_CONSTANT_S = 100.0  # slower than that and the filter would smooth the source's own changes

    def __init__(self, time_constant_s: float) -> None:
        self.time_constant_s = float(time_constant_s)

    @classmethod
    def from_dict(cls, d: dict) -> ReferenceLowpass:
        tau = _scalar(d, "time_constant_s", cls.kind, positive=True)
        if tau > cls.MAX_TIME_CONSTANT_S:
            raise ValueError(f"{cls.kind}: time_constant_s {tau} s is above {cls.MAX_TIME_CONSTANT_S:g} s")
        return cls(tau)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "time_constant_s": self.time_constant_s}

    def new_state(self) -> dict:
        return {}

    def contribution(self, cal: BaseModel, inputs: TermInputs, state: dict | None) -> np.ndarray:
        ref_f = first_order_lowpass(inputs.ref, inputs.t_s, self.time_constant_s, {} if state is None else state)
        return _replace_psi(cal, inputs, ref_f, inputs.xyz)


@_register
class ReferenceDarkOffset(_Base):
    """Dark current / ADC offset of the reference detector: Psi' = xyz / (ref - d) (paper eq. 24).

    ``ref_offset_counts`` d in ADC counts. Eq. 24 only cancels source-power changes if the counts
    are proportional to optical power; an offset d on the reference breaks that. Offsets on the
    axis channels are the separate ``channel_offset`` term (regressor 1/(ref - d)). Stateless.
    """

    kind = "reference_dark_offset"

    def __init__(self, ref_offset_counts: float) -> None:
        self.ref_offset_counts = float(ref_offset_counts)

    @classmethod
    def from_dict(cls, d: dict) -> ReferenceDarkOffset:
        v = _scalar(d, "ref_offset_counts", cls.kind)
        if abs(v) >= 4096:
            raise ValueError(f"{cls.kind}: ref_offset_counts {v} is outside the 12-bit ADC range")
        return cls(v)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "ref_offset_counts": self.ref_offset_counts}

    def contribution(self, cal: BaseModel, inputs: TermInputs, state: Any) -> np.ndarray:
        return _replace_psi(cal, inputs, inputs.ref - self.ref_offset_counts, inputs.xyz)


@_register
class ThermalLag(_Base):
    """The optics and the AHT10 are not at the same temperature while it changes (paper §3.6).

    ``tau_s`` > 0: the optics lag the sensor, T_optics = LPF_tau(T). ``tau_s`` < 0: the sensor lags
    the optics (AHT10 on the PCB) by a first-order lag, whose exact inverse is T_optics = T + |tau| dT/dt. The rate
    is estimated causally, with ``s = rate_smoothing_s`` (default |tau|/4) and r = |tau|/s:

    * ``rate_order`` 2 (what the diagnosis writes): T_optics = (1 + 2r) T - 3r LPF_s(T) + r LPF_s(LPF_s(T)), the
      transfer (1 + (tau + 2s) p + (2 s tau + s^2) p^2) / (1 + s p)^2 = 1 + |tau| p - |tau| s^2 p^3 / (1 + s p)^2:
      exact to the second derivative of T, so a turn of a ramp no longer leaves an error of |tau| s d^2T/dt^2; it
      amplifies the AHT10 noise by about 1 + 2r (9).
    * ``rate_order`` 1 (a file without the key: what older diagnoses wrote): the rate (T - LPF_s(T)) / s, transfer
      1 + |tau| p / (1 + s p): exact on a ramp after ~3 s, but at a turn short by |tau| s d^2T/dt^2 (a fit then takes
      tau some 10-20 % long and leaves a residual); noise amplified by about 1 + r.

    Eq. 28 is evaluated at T_optics. State: the filters.
    """

    kind = "thermal_lag"
    RATE_ORDERS = (1, 2)

    def __init__(self, tau_s: float, rate_smoothing_s: float | None = None, rate_order: int = 2) -> None:
        self.tau_s = float(tau_s)
        self.rate_smoothing_s = float(rate_smoothing_s) if rate_smoothing_s is not None else abs(self.tau_s) / 4.0
        if rate_order not in self.RATE_ORDERS:
            raise ValueError(f"{self.kind}: parameter 'rate_order' must be 1 or 2, got {rate_order!r}")
        self.rate_order = int(rate_order)

    @classmethod
    def from_dict(cls, d: dict) -> ThermalLag:
        tau = _scalar(d, "tau_s", cls.kind, nonzero=True)
        order = d.get("rate_order", 1)  # a file written before the second-order estimate has its first-order one
        if isinstance(order, bool) or order not in cls.RATE_ORDERS:
            raise ValueError(f"{cls.kind}: parameter 'rate_order' must be 1 or 2, got {order!r}")
        return cls(tau, _scalar(d, "rate_smoothing_s", cls.kind, positive=True, default=abs(tau) / 4.0), int(order))

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "tau_s": self.tau_s, "rate_smoothing_s": self.rate_smoothing_s,
                "rate_order": self.rate_order}

    def new_state(self) -> dict:
        return {}

    def effective_temperature(self, temp_c: np.ndarray, t_s: np.ndarray, state: dict | None,
                              steps: SampleSteps | None = None) -> np.ndarray:
        """Optics temperature (N,) degC from the AHT10 reading; updates ``state``. ``steps``: those of ``t_s``
        (``first_order_lowpass``; the result is the same without them)."""
        temp_c = np.asarray(temp_c, float)
        if self.tau_s > 0:
            return first_order_lowpass(temp_c, t_s, self.tau_s, state, steps)
        s = self.rate_smoothing_s
        r = abs(self.tau_s) / s
        if self.rate_order == 1:
            lp = first_order_lowpass(temp_c, t_s, s, state, steps)
            return temp_c + r * (temp_c - lp)
        st = state if state is not None else {}
        lp = first_order_lowpass(temp_c, t_s, s, st.setdefault("lowpass", {}), steps)
        lp2 = first_order_lowpass(lp, t_s, s, st.setdefault("lowpass2", {}), steps)
        return temp_c + r * (2.0 * (temp_c - lp) - (lp - lp2))

    def contribution(self, cal: BaseModel, inputs: TermInputs, state: dict | None) -> np.ndarray:
        t_eff = self.effective_temperature(inputs.temp_c, inputs.t_s, state if state is not None else {})
        before = cal.base_acceleration(inputs.psi, inputs.temp_c)
        after = cal.base_acceleration(inputs.psi, t_eff)
        inputs.temp_c = t_eff
        return after - before


def _replace_psi(cal: BaseModel, inputs: TermInputs, ref: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        psi_new = np.asarray(xyz, float) / np.where(np.asarray(ref) > 0, ref, np.nan)[:, None]
    before = cal.base_acceleration(inputs.psi, inputs.temp_c)
    after = cal.base_acceleration(psi_new, inputs.temp_c)
    inputs.ref, inputs.xyz, inputs.psi = np.asarray(ref, float), np.asarray(xyz, float), psi_new
    return after - before


@_register
class ChainDynamics(_Base):
    """Declared dynamics of the measuring chain, found by the diagnosis: TIA time constants and delay.

    ``tia_tau_s`` (4,) first-order time constants of ref, x, y, z (s; paper Table 1) and ``delay_s``
    (s) of the sensor channels behind the table reference. The calibration accounts for them on the
    reference side (the fit compares the output with the filtered/delayed reference), so the model's
    M and b are free of them. At run time the contribution is zero: the output keeps the chain's
    band limit (deconvolving it would amplify the noise by ~1/(1 - exp(-dt/tau)), about 10 at 100 Hz;
    use ``tia_inverse_filter`` deliberately if that is wanted). ``group_delay_s`` (delay plus the
    low-frequency group delay of the axis filters) is what a consumer may subtract from time stamps.
    Stateless.
    """

    kind = "chain_dynamics"

    def __init__(self, tia_tau_s: np.ndarray, delay_s: float) -> None:
        self.tia_tau_s = np.asarray(tia_tau_s, float).reshape(4)
        self.delay_s = float(delay_s)

    @classmethod
    def from_dict(cls, d: dict) -> ChainDynamics:
        return cls(_array(d, "tia_tau_s", cls.kind, (4,), nonneg=True), _scalar(d, "delay_s", cls.kind, nonneg=True))

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "tia_tau_s": _lst(self.tia_tau_s), "delay_s": self.delay_s,
                "group_delay_s": _lst(self.group_delay_s), "channels": ["ref", "x", "y", "z"], "runtime": "none"}

    @property
    def group_delay_s(self) -> np.ndarray:
        """(3,) low-frequency group delay of the x, y, z outputs (s)."""
        return self.delay_s + self.tia_tau_s[1:]

    def contribution(self, cal: BaseModel, inputs: TermInputs, state: Any) -> np.ndarray:
        return np.zeros((np.asarray(inputs.ref).shape[0], 3))


# ----------------------------------------------------------------------------- additive terms
def quadratic_features(psi: np.ndarray, psi0: np.ndarray) -> np.ndarray:
    """(N, 6) second-order monomials of Psi - psi0: xx, yy, zz, xy, xz, yz (dimensionless)."""
    u = np.asarray(psi, float) - psi0
    return np.column_stack([u[:, 0] ** 2, u[:, 1] ** 2, u[:, 2] ** 2, u[:, 0] * u[:, 1], u[:, 0] * u[:, 2], u[:, 1] * u[:, 2]])


@_register
class SpectralNonlinearity(_HeldInSpan):
    """Second-order terms of the spectral-overlap response (paper §3.4, §4.2, Figs. 9 and 12).

    a += Q · [u_x², u_y², u_z², u_x u_y, u_x u_z, u_y u_z], u = Psi - psi0; Q (3, 6) in m/s^2,
    ``psi0`` (3,) the centre of the calibration data (conditioning only). ``psi_span`` (3, 2), optional:
    [low, high] Psi of each channel the coefficients were fitted on; outside it Psi is held at the edge
    (module docstring). Stateless.
    """

    kind = "spectral_nonlinearity"

    def __init__(self, psi0: np.ndarray, coeff_mps2: np.ndarray, psi_span: np.ndarray | None = None) -> None:
        self.psi0 = np.asarray(psi0, float).reshape(3)
        self.coeff_mps2 = np.asarray(coeff_mps2, float).reshape(3, 6)
        self.psi_span = None if psi_span is None else np.asarray(psi_span, float).reshape(3, 2)

    @classmethod
    def from_dict(cls, d: dict) -> SpectralNonlinearity:
        return cls(_array(d, "psi0", cls.kind, (3,)), _array(d, "coeff_mps2", cls.kind, (3, 6)),
                   _span(d, "psi_span", cls.kind, (3, 2)))

    def to_dict(self) -> dict[str, Any]:
        out = {"kind": self.kind, "psi0": _lst(self.psi0), "coeff_mps2": _lst(self.coeff_mps2),
               "features": ["xx", "yy", "zz", "xy", "xz", "yz"]}
        if self.psi_span is not None:
            out["psi_span"] = _lst(self.psi_span)
        return out

    def _input(self, inputs: TermInputs) -> np.ndarray:
        return np.asarray(inputs.psi, float)

    def _value(self, psi: np.ndarray) -> np.ndarray:
        return quadratic_features(psi, self.psi0) @ self.coeff_mps2.T

    def _bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        return None if self.psi_span is None else (self.psi_span[:, 0], self.psi_span[:, 1])


@_register
class ChannelOffset(_Base):
    """Dark/ADC offsets c0 on the axis channels: (xyz - c0)/ref adds -M c0 / ref, i.e. k / ref.

    ``coeff_mps2_counts`` k (3,) in m/s^2·counts (k = -M0 c0). Uses the (corrected) reference of
    ``inputs``. Stateless.
    """

    kind = "channel_offset"

    def __init__(self, coeff_mps2_counts: np.ndarray) -> None:
        self.coeff_mps2_counts = np.asarray(coeff_mps2_counts, float).reshape(3)

    @classmethod
    def from_dict(cls, d: dict) -> ChannelOffset:
        return cls(_array(d, "coeff_mps2_counts", cls.kind, (3,)))

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "coeff_mps2_counts": _lst(self.coeff_mps2_counts)}

    def contribution(self, cal: BaseModel, inputs: TermInputs, state: Any) -> np.ndarray:
        ref = np.asarray(inputs.ref, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / np.where(ref > 0, ref, np.nan)
        return inv[:, None] * self.coeff_mps2_counts[None, :]


@_register
class TimeDrift(_HeldInSpan):
    """Bias drift with board time since power-on: warm-up exponential and linear creep (§4.4).

    a += creep (t - t0) + warmup exp(-(t - t0)/tau); ``creep_mps2_per_s`` (3,), ``warmup_mps2``
    (3,), ``warmup_tau_s`` > 0 (s), ``t0_s`` board time origin. Only meaningful if the board
    clock restarts at power-on. ``span_s`` (low, high), optional: the board times (s) it was fitted on;
    outside them t is held at the edge (module docstring). Stateless.
    """

    kind = "time_drift"

    def __init__(self, creep_mps2_per_s: np.ndarray, warmup_mps2: np.ndarray, warmup_tau_s: float, t0_s: float = 0.0,
                 span_s: tuple[float, float] | np.ndarray | None = None) -> None:
        self.creep_mps2_per_s = np.asarray(creep_mps2_per_s, float).reshape(3)
        self.warmup_mps2 = np.asarray(warmup_mps2, float).reshape(3)
        self.warmup_tau_s = float(warmup_tau_s)
        self.t0_s = float(t0_s)
        self.span_s = None if span_s is None else (float(span_s[0]), float(span_s[1]))

    @classmethod
    def from_dict(cls, d: dict) -> TimeDrift:
        return cls(_array(d, "creep_mps2_per_s", cls.kind, (3,)), _array(d, "warmup_mps2", cls.kind, (3,)),
                   _scalar(d, "warmup_tau_s", cls.kind, positive=True), _scalar(d, "t0_s", cls.kind, default=0.0),
                   _span(d, "span_s", cls.kind, (2,)))

    def to_dict(self) -> dict[str, Any]:
        out = {"kind": self.kind, "creep_mps2_per_s": _lst(self.creep_mps2_per_s), "warmup_mps2": _lst(self.warmup_mps2),
               "warmup_tau_s": self.warmup_tau_s, "t0_s": self.t0_s}
        if self.span_s is not None:
            out["span_s"] = list(self.span_s)
        return out

    @staticmethod
    def features(t_s: np.ndarray, tau_s: float, t0_s: float) -> np.ndarray:
        """(N, 2): [t - t0 (s), exp(-(t - t0)/tau)]."""
        dt = np.asarray(t_s, float) - t0_s
        return np.column_stack([dt, np.exp(-dt / tau_s)])

    def _value(self, t_s: np.ndarray) -> np.ndarray:
        f = self.features(t_s, self.warmup_tau_s, self.t0_s)
        return f[:, [0]] * self.creep_mps2_per_s + f[:, [1]] * self.warmup_mps2

    def _input(self, inputs: TermInputs) -> np.ndarray:
        return np.asarray(inputs.t_s, float)

    def _bounds(self) -> tuple[float, float] | None:
        return self.span_s


@_register
class ThermalHysteresis(_Base):
    """Bias that differs between heating and cooling branches (paper §4.4 warm-up, §3.6.2).

    The branch s = +1 (heating) / -1 (cooling) follows the sign of the temperature rate, smoothed
    by a first-order low-pass ``rate_tau_s`` (s); it only switches when the smoothed rate passes
    ``deadband_c_per_s`` (degC/s) the other way, so it keeps its memory across a constant
    temperature (that is the hysteresis). a += s · ``half_gap_mps2`` (3,). State: filter + branch.
    """

    kind = "thermal_hysteresis"

    def __init__(self, half_gap_mps2: np.ndarray, rate_tau_s: float, deadband_c_per_s: float) -> None:
        self.half_gap_mps2 = np.asarray(half_gap_mps2, float).reshape(3)
        self.rate_tau_s = float(rate_tau_s)
        self.deadband_c_per_s = float(deadband_c_per_s)

    @classmethod
    def from_dict(cls, d: dict) -> ThermalHysteresis:
        return cls(_array(d, "half_gap_mps2", cls.kind, (3,)), _scalar(d, "rate_tau_s", cls.kind, positive=True),
                   _scalar(d, "deadband_c_per_s", cls.kind, nonneg=True))

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "half_gap_mps2": _lst(self.half_gap_mps2), "rate_tau_s": self.rate_tau_s,
                "deadband_c_per_s": self.deadband_c_per_s}

    def new_state(self) -> dict:
        return {"lp": {}, "branch": 0.0, "tprev": None, "lpprev": None}

    @staticmethod
    def branch(temp_c: np.ndarray, t_s: np.ndarray, rate_tau_s: float, deadband: float, state: dict,
               steps: SampleSteps | None = None) -> np.ndarray:
        """(N,) branch indicator +1/-1 (0 before the first decision); updates ``state``. ``steps``: those of
        ``t_s`` for the rate filter (``first_order_lowpass``; the result is the same without them)."""
        decision = ThermalHysteresis.decisions(temp_c, t_s, rate_tau_s, deadband, state, steps)
        out = ThermalHysteresis.held(decision, state["branch"])
        if out.shape[0]:
            state["branch"] = float(out[-1])
        return out

    @staticmethod
    def decisions(temp_c: np.ndarray, t_s: np.ndarray, rate_tau_s: float, deadband: float, state: dict,
                  steps: SampleSteps | None = None) -> np.ndarray:
        """(N,) int8: +1 / -1 where the smoothed rate (degC/s) passes ``deadband`` up / down, 0 where the branch is
        held (:meth:`branch`'s decisions, before :meth:`held` carries them on); updates ``state`` but for its branch.
        ``steps``: those of ``t_s`` (:meth:`branch`)."""
        t_s = np.asarray(t_s, float).reshape(-1)
        lp = first_order_lowpass(np.asarray(temp_c, float), t_s, rate_tau_s, state["lp"], steps)
        n = lp.shape[0]
        finite = np.isfinite(lp)
        good = None if finite.all() else np.flatnonzero(finite)  # None: every sample (no gather, no scatter)
        decision = np.zeros(n, np.int8)  # +1 / -1 where the rate decides, 0 where the branch is held
        if n and (good is None or good.size):
            lp_g, t_g = (lp, t_s) if good is None else (lp[good], t_s[good])
            # the rate from the previous finite sample (the state's across batches), where time moves on
            dlp = np.empty_like(lp_g)
            dlp[0] = lp_g[0] - (state["lpprev"] if state["lpprev"] is not None else np.nan)
            np.subtract(lp_g[1:], lp_g[:-1], out=dlp[1:])
            if good is None and state["tprev"] is None and steps is not None and steps.dt.size == n:
                # the steps' dt: t_s's steps where time moves on, 0 at the first sample and where it does not (there
                # the step is NaN or negative here otherwise): where time moves on, the same; elsewhere no decision
                dt = steps.dt
            else:
                dt = np.empty_like(t_g)
                dt[0] = t_g[0] - (state["tprev"] if state["tprev"] is not None else np.nan)
                np.subtract(t_g[1:], t_g[:-1], out=dt[1:])
            with np.errstate(invalid="ignore", divide="ignore"):
                rate = np.divide(dlp, dt, out=dlp)
            moving = dt > 0
            d = decision if good is None else np.zeros(good.size, np.int8)
            if deadband >= 0:  # up and down exclusive: +1 - 0, 0 - 1 or 0 (a NaN rate neither), no masked writes
                up = np.greater(rate, deadband)
                up &= moving
                down = np.less(rate, -deadband)
                down &= moving
                np.subtract(up.view(np.int8), down.view(np.int8), out=d)
            else:  # both where the rate is within the negative band: down wins
                d[(rate > deadband) & moving] = 1
                d[(rate < -deadband) & moving] = -1
            if good is not None:
                decision[good] = d
            state["tprev"], state["lpprev"] = float(t_g[-1]), float(lp_g[-1])
        return decision

    @staticmethod
    def held(decision: np.ndarray, start: float, rows: np.ndarray | None = None) -> np.ndarray:
        """(N,) float, or (len(rows),) at the samples ``rows``: the last nonzero ``decision`` (int8, :meth:`decisions`)
        up to each sample, ``start`` (the branch before them) where none is (the hysteresis's memory)."""
        n = decision.shape[0]
        # the index of the last decision up to each sample, -1 before the first (arithmetic, not a select on the mask)
        last = np.arange(1, n + 1)
        last *= decision != 0
        last -= 1
        np.maximum.accumulate(last, out=last)
        if rows is not None:
            at = last[rows]
            return np.where(at >= 0, decision[np.maximum(at, 0)], start)
        out = np.empty(n, np.result_type(decision.dtype, start))  # np.where's type: float for a float start
        first = int(np.searchsorted(last, 0))  # ascending: the samples before the first decision
        out[:first] = start
        out[first:] = decision.take(last[first:])
        return out

    def contribution(self, cal: BaseModel, inputs: TermInputs, state: dict | None) -> np.ndarray:
        st = state if state is not None else self.new_state()
        s = self.branch(inputs.temp_c, inputs.t_s, self.rate_tau_s, self.deadband_c_per_s, st)
        return s[:, None] * self.half_gap_mps2[None, :]
