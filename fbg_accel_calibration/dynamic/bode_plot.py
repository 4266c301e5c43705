"""Bode plot of dynamic-calibration points against the fitted chain models (seed Figs. 5-10; matplotlib Agg).

Top: amplitude ratio (sensitivity, unitless) against log frequency; bottom: phase (degrees, negative = sensor
lags the reference). Points carry error bars of ``coverage`` times their combined standard uncertainty
(coverage 2 as in seed 2.4 / ISO 16063-21); the fitted :class:`ChainModel` of each axis is drawn as a line.
matplotlib is imported lazily so the analysis modules stay importable without it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .chain_model import ChainModel, phase_delay_s, response
from .tone_analysis import AXES, DynamicPoint

COLORS = {"x": "tab:red", "y": "tab:green", "z": "tab:blue"}
MARKERS = {"x": "o", "y": "s", "z": "^"}  # distinct shapes: axes with equal cut-offs overlap


Response = ChainModel | Callable[[np.ndarray], np.ndarray]  # a fitted chain, or f (Hz) -> complex response


def plot_bode(points: Sequence[DynamicPoint], models: Mapping[str, Response] | None, path: str | Path,
              title: str = "Dynamic calibration", coverage: float = 2.0,
              axis_points: Sequence[DynamicPoint] | None = None,
              axis_responses: Mapping[str, Response] | None = None) -> Path:
    """Write a PNG Bode plot of ``points`` (all axes or channels) with ``models`` (per key x, y, z: a
    :class:`ChainModel` or a function of f in Hz giving the complex response) to ``path``; returns the path.

    With ``axis_points``, a second column shows them (the measured output axes) with ``axis_responses`` (the
    responses the channel models predict for them, ``chain_model.axis_response_along``): the left column is then
    titled per channel, the right per axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    two = axis_points is not None
    fig, grid = plt.subplots(2, 2 if two else 1, sharex=True, figsize=(13.0 if two else 7.5, 7.0), squeeze=False)
    _draw(grid[0, 0], grid[1, 0], points, models, coverage, "channel " if two else "")
    grid[0, 0].set_title(f"{title}{': per channel' if two else ''} (error bars: k = {coverage:g})", fontsize=9)
    if two:
        _draw(grid[0, 1], grid[1, 1], axis_points or [], axis_responses, coverage, "axis ")
        grid[0, 1].set_title("per output axis: measured, and M diag(H_channel) M^-1 of the channel models", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _draw(ax_a: Any, ax_p: Any, points: Sequence[DynamicPoint], models: Mapping[str, Response] | None,
          coverage: float, kind: str) -> None:
    """Amplitude (``ax_a``) and phase (``ax_p``) of ``points`` with the ``models``' curves; ``kind`` prefixes labels."""
    pts = [p for p in points if p.measurable]
    f_all = np.array([p.f_hz for p in pts]) if pts else np.array([0.5, 20.0])
    f_line = np.geomspace(f_all.min() / 1.5, f_all.max() * 1.5, 300)
    for ax in AXES:
        sel = [p for p in pts if p.axis == ax]
        if not sel:
            continue
        c = COLORS[ax]
        f = np.array([p.f_hz for p in sel])
        ax_a.errorbar(f, [p.sensitivity for p in sel], yerr=[coverage * p.u_sensitivity for p in sel], fmt=MARKERS[ax],
                      color=c, capsize=3, label=f"{kind}{ax} measured")
        m = (models or {}).get(ax)
        phase = np.array([p.phase_deg for p in sel])
        if m is not None:
            h, line_phase, label = _curve(m, f_line)
            # a measured phase is known modulo 360 deg: show it on the model's branch
            model_phase = np.interp(f, f_line, line_phase)
            phase = phase + 360.0 * np.round((model_phase - phase) / 360.0)
            ls = {"x": "-", "y": "--", "z": ":"}[ax]
            ax_a.semilogx(f_line, np.abs(h), ls, color=c, lw=1, label=f"{kind}{ax} model{label}")
            ax_p.semilogx(f_line, line_phase, ls, color=c, lw=1)
        ax_p.errorbar(f, phase, yerr=[coverage * p.u_phase_deg for p in sel], fmt=MARKERS[ax], color=c, capsize=3)
    ax_a.set_xscale("log")
    ax_a.set_ylabel("amplitude ratio sensor / reference [1]")
    ax_p.set_ylabel("phase [deg] (negative = sensor lags)")
    ax_p.set_xlabel("frequency [Hz]")
    for a in (ax_a, ax_p):
        a.grid(True, which="both", alpha=0.3)
    ax_a.legend(fontsize=7)


def _curve(m: Response, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """(complex response, continuous phase in degrees, label suffix) of ``m`` on the grid ``f`` (Hz, ascending)."""
    if isinstance(m, ChainModel):
        hp = "" if m.highpass_cutoff_hz is None else f", HP {m.highpass_cutoff_hz:.3g} Hz ({m.highpass_in})"
        # continuous phase from the model's parts (no wrapping jumps)
        return (response(m, f), -360.0 * f * phase_delay_s(m, f),
                f": LP {m.cutoff_hz:.3g} Hz, delay {1e3 * m.delay_s:.3g} ms{hp}")
    h = np.asarray(m(f))
    return h, np.degrees(np.unwrap(np.angle(h))), ""
