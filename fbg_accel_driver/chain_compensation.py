"""Dynamics of the measuring chain and its live compensation (docs/dynamic_calibration.md).

Pure Python + numpy, no ROS. The calibration file's optional ``dynamic`` section (:class:`ChainDynamics`)
holds what a dynamic calibration measured, **per channel** (the counts before eq. 24, where the stages are):

* ``cutoff_hz``: the first-order low-pass of each photodetector's transimpedance stage, for the
  reference and the x, y, z channels (paper section 3.5 and Table 1: about 1, 1.7, 1.3, 1.3 Hz in the
  static-test build, about 50 Hz in the flight build). A slide run with a constant source cannot see
  the reference channel's stage (eq. 24 divides by a constant), so its value may be absent (NaN, ``null``
  in the file): ``delay`` works without it, ``equalise`` needs it;
* ``delay_s``: a pure delay of each axis channel x, y, z (ESP32 sequential sampling skew, anything after the
  analogue stage), s, positive when the channel lags the board time stamp.

An output axis is eq. 28's ``M`` applied to the three channels, so its response is ``M diag(H_channel) M^-1``
(a mix of the three channels' poles, not one first-order stage when their cut-offs differ). Section format 2
(``fbg-accel-calib dynamic``) identifies the values per channel; format 1 fitted one first-order
stage per output axis and wrote those as the channels' values (right only when the channels' cut-offs are
equal): it still loads, and :attr:`ChainDynamics.identified_per_axis` says so.

Two live compensations (driver parameter ``chain_compensation``):

* ``delay``: the published stamp is moved back by the acceleration path's **group delay at DC**, the
  mean over the channels of ``1 / (2 pi fc) + delay`` (a first-order low-pass delays slow signals by its
  time constant; at a frequency f the delay is ``tau / (1 + (f/fc)^2)``, less: the seed's point that a
  low-pass stage shifts phase well inside its band). That is also the mean over the output axes: the axes'
  DC group delays are the diagonal of ``M diag(tau_channel) M^-1``, whose trace is the channels' sum. The
  samples are unchanged.
* ``equalise``: each channel's counts pass, **before** eq. 24, through a causal and stable filter
  that cancels its own low-pass and puts a common one at ``bandwidth_hz`` in its place (the
  discrete form of ``(1 + s/wc) / (1 + s/wp)``, :class:`ChannelEqualiser`), and the axis channels that lag
  less than the latest one are delayed to it (linear interpolation in time), so that every axis channel
  reaches eq. 28 with the same dynamics. The reference and the
  axes are filtered differently, so only a correction of each channel before the ratio restores
  Psi = c_axis/c_ref when the source power or the acceleration moves. The stamp then moves back by
  what remains: about ``1/(2 pi bandwidth_hz)`` plus the largest pure delay (exactly:
  :meth:`ChainDynamics.stamp_delay_s`). The price is noise: the high-frequency gain is about
  ``bandwidth_hz / fc`` (:meth:`ChannelEqualiser.variance_factor` gives the published variance
  factor, and that of a decimated mean: the equalised noise is nearly white, so averaging N samples
  cuts it much more than it cuts the TIA-correlated noise of the uncompensated output).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .mapping_fields import format_version, number, refuse_unknown, same_values
from .noise_model import filtered_mean_variance_factor, geometric_length

DYNAMIC_FORMAT_VERSION = 2  # 2: identified per channel; 1: one stage fitted per output axis
READS_DYNAMIC_FORMAT_VERSIONS = (1, 2)
CHANNELS = ("reference", "x", "y", "z")
AXES = ("x", "y", "z")
MODES = ("none", "delay", "equalise")
DYNAMIC_KEYS = ("format_version", "cutoff_hz", "delay_s", "fit")
CUTOFF_LIMITS_HZ = (1e-3, 1e5)  # beyond a TIA stage's physics either way
MAX_ABS_DELAY_S = 1.0  # a pure delay of a second is not a sampling skew


@dataclass(frozen=True)
class ChainDynamics:
    """First-order low-pass per channel (reference, x, y, z; Hz) and pure delay per axis channel x, y, z (s).

    ``format_version``: that of the section read (written back unchanged); 1 = the values were fitted per output
    axis (:attr:`identified_per_axis`)."""

    cutoff_hz: tuple[float, float, float, float]
    delay_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fit: dict[str, Any] = field(default_factory=dict)  # figures for people (points, uncertainties)
    format_version: int = DYNAMIC_FORMAT_VERSION

    def __post_init__(self) -> None:
        if len(self.cutoff_hz) != 4 or len(self.delay_s) != 3:
            raise ValueError("cutoff_hz needs 4 values (reference, x, y, z), delay_s 3 (x, y, z)")
        for name, fc in zip(CHANNELS, self.cutoff_hz, strict=True):
            if name == "reference" and isinstance(fc, float) and math.isnan(fc):
                continue  # not measured
            if not (isinstance(fc, float | int) and math.isfinite(fc) and CUTOFF_LIMITS_HZ[0] <= fc <= CUTOFF_LIMITS_HZ[1]):
                lo, hi = CUTOFF_LIMITS_HZ
                raise ValueError(f"cutoff_hz of {name} must be in {lo:g}..{hi:g} Hz, got {fc!r}")
        for name, d in zip(AXES, self.delay_s, strict=True):
            if not (isinstance(d, float | int) and math.isfinite(d) and abs(d) <= MAX_ABS_DELAY_S):
                raise ValueError(f"delay_s of {name} must be within +-{MAX_ABS_DELAY_S:g} s, got {d!r}")
        if self.format_version not in READS_DYNAMIC_FORMAT_VERSIONS:
            raise ValueError(f"format_version {self.format_version!r} is not one of {READS_DYNAMIC_FORMAT_VERSIONS}")

    @property
    def identified_per_axis(self) -> bool:
        """True for a format-1 section written by a dynamic calibration (it holds per-axis ``fit.models``): its
        cut-offs and delays are first-order fits per output axis, taken as the channels' (right when the channels'
        cut-offs are equal; re-run ``fbg-accel-calib dynamic`` for per-channel values)."""
        return self.format_version == 1 and "models" in self.fit

    def __eq__(self, other: object) -> bool:
        """Equal by the file form (``to_dict``): an unmeasured reference cut-off (NaN) equals itself."""
        if type(other) is not type(self):
            return NotImplemented
        return same_values(self.to_dict(), other.to_dict())  # type: ignore[attr-defined]

    def group_delay_s(self, axis: int, f_hz: float = 0.0) -> float:
        """Group delay (s) of axis ``axis`` (0..2) at ``f_hz``: ``tau / (1 + (f/fc)^2) + delay``."""
        return float(first_order_group_delay_s(self.cutoff_hz[axis + 1], f_hz)) + self.delay_s[axis]

    def stamp_delay_s(self, mode: str, bandwidth_hz: float = 0.0, dt_s: float = 0.0) -> float:
        """Delay (s) the published stamps are moved back by in ``mode`` (module docstring).

        ``equalise`` needs the sample interval ``dt_s``: the DC group delay that remains is the chain's
        own (``tau`` per channel, and the largest pure delay, to which :class:`ChannelEqualiser` aligns the
        channels) minus what it removes (its exact inverse of the sampled low-pass, ``r_c/(1-r_c) dt``) plus
        what its own low-pass adds (``r_p/(1-r_p) dt``).
        """
        if mode == "none":
            return 0.0
        if mode == "delay":
            return sum(self.group_delay_s(a) for a in range(3)) / 3.0
        if mode == "equalise":
            if not dt_s > 0.0:
                raise ValueError("equalise needs the sample interval dt_s > 0")
            removed = sum(_dc_delay_samples(fc, dt_s) for fc in self.cutoff_hz[1:]) / 3.0 * dt_s
            lowpass = sum(float(first_order_group_delay_s(fc)) for fc in self.cutoff_hz[1:]) / 3.0
            return lowpass + max(self.delay_s) - removed + _dc_delay_samples(bandwidth_hz, dt_s) * dt_s
        raise ValueError(f"chain_compensation must be one of {MODES}, got {mode!r}")

    def delay_helps_below_hz(self, f_max_hz: float = CUTOFF_LIMITS_HZ[1]) -> tuple[float, float, float]:
        """Per axis (x, y, z), the lowest frequency (Hz) at which the ``delay`` mode's stamp shift stops reducing
        the error of a tone; ``inf`` when it helps up to ``f_max_hz``.

        The axis's model is ``H(f) = exp(-j 2 pi f delay) / (1 + j f/fc)`` (this section), the shift ``D`` =
        :meth:`stamp_delay_s` ``('delay')``; the RMS error of a unit tone read through the chain against the truth is
        ``|H - 1|`` unshifted and ``|H exp(j 2 pi f D) - 1|`` shifted, and the second is the smaller exactly while
        ``|wrap(arg H + 2 pi f D)| < |wrap(arg H)|``, whatever ``|H|``. A first-order low-pass delays a tone at f by
        less than at DC (its phase delay falls from ``1/(2 pi fc)`` towards 0), so past about 2.3 fc (no pure delay)
        the DC shift over-corrects by more than the lag it removes; 0 when the common shift is more than twice
        the axis's own DC group delay (it never helps that axis)."""
        shift = self.stamp_delay_s("delay")

        def helps(axis: int, f: np.ndarray) -> np.ndarray:
            ph = -np.arctan(f / self.cutoff_hz[axis + 1]) - 2.0 * math.pi * f * self.delay_s[axis]
            return np.abs(np.angle(np.exp(1j * (ph + 2.0 * math.pi * f * shift)))) < np.abs(np.angle(np.exp(1j * ph)))

        out = []
        for a in range(3):
            # log grid from far below the slowest stage to f_max (steps of 0.05 %, fine against both the cut-offs
            # and the period 1/shift of the wrapped phase), then bisection between the last good and first bad node
            lo = min(min(self.cutoff_hz[1:]), 1.0 / (2.0 * math.pi * max(abs(shift), 1e-9))) * 1e-4
            f = np.geomspace(lo, f_max_hz, max(2, int(math.log(f_max_hz / lo) / 5e-4)))
            bad = np.flatnonzero(~helps(a, f))
            if bad.size == 0:
                out.append(math.inf)
                continue
            if bad[0] == 0:
                out.append(0.0)
                continue
            good_f, bad_f = float(f[bad[0] - 1]), float(f[bad[0]])
            for _ in range(50):
                mid = 0.5 * (good_f + bad_f)
                if helps(a, np.array([mid]))[0]:
                    good_f = mid
                else:
                    bad_f = mid
            out.append(bad_f)
        return out[0], out[1], out[2]

    def calibrated_band_hz(self) -> tuple[float, float] | None:
        """(lowest, highest) frequency (Hz) the dynamic calibration measured (``fit.frequencies_hz``, written by
        ``fbg-accel-calib dynamic``); None for a section without them (e.g. design values written by hand)."""
        f = self.fit.get("frequencies_hz")
        try:
            vals = [float(v) for v in f] if isinstance(f, list | tuple) else []
        except (TypeError, ValueError):
            return None
        vals = [v for v in vals if math.isfinite(v) and v > 0]
        return (min(vals), max(vals)) if vals else None

    def to_dict(self) -> dict[str, Any]:
        return {"format_version": self.format_version,
                "cutoff_hz": dict(zip(CHANNELS, (None if math.isnan(v) else float(v) for v in self.cutoff_hz), strict=True)),
                "delay_s": dict(zip(AXES, (float(v) for v in self.delay_s), strict=True)),
                **({"fit": self.fit} if self.fit else {})}

    @classmethod
    def from_dict(cls, d: Any, fail: Callable[[str], Exception]) -> ChainDynamics:
        """The ``dynamic`` section of a calibration file; ``fail(message)`` makes the error to raise."""
        if not isinstance(d, dict):
            raise fail(f"'dynamic' must be a mapping, got {type(d).__name__}")
        refuse_unknown(d, DYNAMIC_KEYS, "dynamic.", fail)
        if "format_version" not in d:
            raise fail("missing key 'dynamic.format_version'")
        version = format_version(d["format_version"], "dynamic.format_version", fail, reads=DYNAMIC_FORMAT_VERSION,
                                 exact=False)
        if version not in READS_DYNAMIC_FORMAT_VERSIONS:
            raise fail(f"dynamic.format_version {version!r} is not supported (this driver reads "
                       f"{', '.join(map(str, READS_DYNAMIC_FORMAT_VERSIONS))})")

        def mapping(key: str, names: tuple[str, ...], default: float | None) -> tuple[float, ...]:
            m = d.get(key, {} if default is not None else None)
            if not isinstance(m, dict):
                raise fail(f"dynamic.{key} must be a mapping of {', '.join(names)}")
            refuse_unknown(m, names, f"dynamic.{key}.", fail)
            out = []
            for n in names:
                if key == "cutoff_hz" and n == "reference" and n in m and m[n] is None:
                    out.append(math.nan)  # not measured
                    continue
                v = m.get(n, default)
                if v is None:
                    raise fail(f"missing key 'dynamic.{key}.{n}'")
                out.append(number(v, f"dynamic.{key}.{n}", fail, finite=False))  # __post_init__ checks the range
            return tuple(out)

        fit = d.get("fit", {})
        if fit is None:
            fit = {}
        if not isinstance(fit, dict):
            raise fail(f"dynamic.fit must be a mapping of figures, got {type(fit).__name__}")
        # read outside the try: their errors are fail()'s already (a ValueError too), not to be wrapped again
        cutoff_hz, delay_s = mapping("cutoff_hz", CHANNELS, None), mapping("delay_s", AXES, 0.0)
        try:
            return cls(cutoff_hz=cutoff_hz, delay_s=delay_s, fit=dict(fit), format_version=version)  # type: ignore[arg-type]
        except ValueError as exc:
            raise fail(f"dynamic: {exc}") from None


def first_order_group_delay_s(cutoff_hz: float, f_hz: float | np.ndarray = 0.0) -> float | np.ndarray:
    """Group delay (s) of a first-order low-pass at ``f_hz``: ``(1 / (2 pi fc)) / (1 + (f / fc)^2)``; 0 for an
    infinite cut-off."""
    return (1.0 / (2.0 * math.pi * cutoff_hz)) / (1.0 + (np.asarray(f_hz) / cutoff_hz) ** 2)


def _dc_delay_samples(fc_hz: float, dt_s: float) -> float:
    """DC group delay, in samples, of ``y_n = r y_{n-1} + (1-r) u_n`` with ``r = exp(-2 pi fc dt)``."""
    r = math.exp(-2.0 * math.pi * fc_hz * dt_s)
    return r / (1.0 - r)


class ChannelEqualiser:
    """Causal, stable per-channel inverse of the TIA low-passes (module docstring), in counts.

    The TIA stage of time constant ``1/wc`` sampled every ``dt`` is the first-order recursion
    ``c_n = c_{n-1} + (1 - r_c)(u_n - c_{n-1})``, ``r_c = exp(-wc dt)`` (the simulator's model of it,
    board_physics). Each channel is inverted exactly, ``v_n = (c_n - r_c c_{n-1}) / (1 - r_c)``, and
    low-passed again at ``bandwidth_hz``: ``y_n = y_{n-1} + (1 - r_p)(v_n - y_{n-1})``. Gain 1 at DC, one
    pole ``r_p`` inside the unit circle for every ``dt > 0``, so causal and stable; the zero at ``r_c``
    is the TIA's pole, cancelled. ``dt`` is each sample's own interval (board clock). The state starts
    at the first sample (no start transient) and is cleared by :meth:`reset` (board reboot).

    Then each axis channel that lags less than the latest (``dynamics.delay_s``) is delayed by the difference,
    by linear interpolation in time between its equalised samples (DC group delay exactly the difference; at
    f the interpolation's gain is at least ``cos(pi f dt)``), so the three axis channels reach eq. 28 with one
    delay: channels of different delays would otherwise mix, through eq. 28's ``M``, tones of different phases.
    Until the history covers the lag, the oldest sample is held.
    """

    def __init__(self, dynamics: ChainDynamics, bandwidth_hz: float) -> None:
        if math.isnan(dynamics.cutoff_hz[0]):
            raise ValueError("equalise needs the reference channel's cut-off, which the calibration does not hold "
                             "(dynamic.cutoff_hz.reference is null: measure it, or use chain_compensation 'delay')")
        if not (math.isfinite(bandwidth_hz) and bandwidth_hz > max(dynamics.cutoff_hz)):
            raise ValueError(f"equalise bandwidth {bandwidth_hz!r} Hz must be above every channel's cut-off "
                             f"(max {max(dynamics.cutoff_hz):g} Hz)")
        self.bandwidth_hz = float(bandwidth_hz)
        self._wc = tuple(2.0 * math.pi * fc for fc in dynamics.cutoff_hz)
        self._wp = 2.0 * math.pi * bandwidth_hz
        self._prev: list[float] | None = None  # previous input counts per channel
        self._out: list[float] = [0.0] * 4
        self._coef_dt = -1.0
        self._coef: tuple[tuple[float, float], ...] = ()
        self._ap = 0.0
        latest = max(dynamics.delay_s)
        self.alignment_s = (0.0, *(latest - d for d in dynamics.delay_s))  # extra delay per channel (s), ref first
        self._align = [j for j in range(4) if self.alignment_s[j] > 0.0]
        self._keep_s = max(self.alignment_s)
        self._t = 0.0  # board time (s) since the first sample, summed from the steps
        self._hist_t: deque[float] = deque()
        self._hist: deque[tuple[float, float, float, float]] = deque()

    def reset(self) -> None:
        self._prev = None
        self._t = 0.0
        self._hist_t.clear()
        self._hist.clear()

    def _coefficients(self, dt_s: float) -> None:
        dt = max(dt_s, 1e-9)
        self._coef_dt = dt_s
        self._coef = tuple((math.exp(-wc * dt), 1.0 / (1.0 - math.exp(-wc * dt))) for wc in self._wc)
        self._ap = 1.0 - math.exp(-self._wp * dt)

    def step(self, dt_s: float, counts: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        """Equalised (reference, x, y, z) counts of one sample taken ``dt_s`` (s) after the previous one."""
        prev = self._prev
        if prev is None:
            self._prev = list(counts)
            self._out = list(counts)
            return self._aligned(counts) if self._align else counts
        if dt_s != self._coef_dt:
            self._coefficients(dt_s)
        out = self._out
        ap = self._ap
        for j in range(4):
            rc, inv = self._coef[j]
            u = counts[j]
            v = (u - rc * prev[j]) * inv
            prev[j] = u
            out[j] += ap * (v - out[j])
        self._t += dt_s
        if self._align:
            return self._aligned((out[0], out[1], out[2], out[3]))
        return out[0], out[1], out[2], out[3]

    def _aligned(self, now: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        """``now`` (the equalised counts at the current time) with the channels in ``_align`` read
        ``alignment_s`` earlier from the history (linear interpolation in time; the oldest sample held before it)."""
        ht, h = self._hist_t, self._hist
        ht.append(self._t)
        h.append(now)
        while len(ht) > 2 and ht[1] <= self._t - self._keep_s:  # keep one sample at or before the longest lag
            ht.popleft()
            h.popleft()
        out = list(now)
        for j in self._align:
            t_j = self._t - self.alignment_s[j]
            i = bisect.bisect_right(ht, t_j)  # ht[i - 1] <= t_j < ht[i]
            if i == 0:
                out[j] = h[0][j]
            elif i >= len(ht):
                out[j] = h[-1][j]
            else:
                t0, t1 = ht[i - 1], ht[i]
                w = (t_j - t0) / (t1 - t0) if t1 > t0 else 1.0
                out[j] = h[i - 1][j] + w * (h[i][j] - h[i - 1][j])
        return out[0], out[1], out[2], out[3]

    def impulse_response(self, channel: int, dt_s: float) -> np.ndarray:
        """Impulse response of channel ``channel`` (0 reference, 1..3 x, y, z) at the sample interval ``dt_s``
        (s): the exact inverse ``(1 - r_c z^-1) / (1 - r_c)`` followed by the low-pass ``(1 - r_p) / (1 - r_p
        z^-1)``, cut where it has decayed (``noise_model.geometric_length``), and the channel's alignment delay
        (linear interpolation between the samples around it: it averages two neighbours, which lowers the
        variance of the nearly white equalised noise)."""
        rc = math.exp(-self._wc[channel] * dt_s)
        rp = math.exp(-self._wp * dt_s)
        lp = (1.0 - rp) * rp ** np.arange(geometric_length(rp), dtype=float)
        h = np.convolve(np.array([1.0, -rc]) / (1.0 - rc), lp)
        lag = self.alignment_s[channel] / dt_s
        if lag > 0.0:
            whole = math.floor(lag)
            frac = lag - whole
            h = np.convolve(np.concatenate([np.zeros(whole), [1.0 - frac, frac]]), h)
        return h

    def variance_factor(self, axis: int, dt_s: float, correlated_fraction: float, time_constant_s: float,
                        n: int = 1) -> float:
        """Variance of the mean of ``n`` consecutive equalised samples of axis ``axis`` (0..2), as a factor
        on the calibrated per-sample variance (``n = 1``: one published sample).

        The calibrated noise of an axis is modelled as in :mod:`noise_model` (white part + first-order
        part of time constant ``time_constant_s``, fitted on the output at rest) and passed through the
        axis channel's equaliser: :func:`noise_model.filtered_mean_variance_factor` with
        :meth:`impulse_response`. The axis channel's, because that is where the calibrated noise sits:
        its correlated part has the axis TIA's time constant (the fit finds 0.099 / 0.125 s for the
        simulated x / y axes, whose TIAs have 0.094 / 0.122 s; the reference's is 0.159 s), and the source
        power noise common to both channels cancels in Psi. The former upper bound (the larger of the
        reference's and the axis's gains) overstated the variance 1.5-2.6 times on a static simulated run.
        """
        return filtered_mean_variance_factor(n, correlated_fraction, time_constant_s, dt_s,
                                             self.impulse_response(axis + 1, dt_s))
