"""Bode plot of dynamic-calibration points against the fitted chain models (seed Figs. 5-10; matplotlib Agg).

Top: amplitude ratio (sensitivity, unitless) against log frequency; bottom: phase (degrees, negative = sensor
lags the reference). Points carry error bars of ``coverage`` times their combined standard uncertainty
(coverage 2 as in seed 2.4 / ISO 16063-21); the fitted :class:`ChainModel` of each axis is drawn as a line.
matplotlib is imported lazily so the analysis modules stay importable without it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .chain_model import ChainModel, phase_delay_s, response
from .dynamic_analysis import AXES, DynamicPoint

COLORS = {"x": "tab:red", "y": "tab:green", "z": "tab:blue"}
MARKERS = {"x": "o", "y": "s", "z": "^"}  # distinct shapes: axes with equal cut-offs overlap


def plot_bode(points: Sequence[DynamicPoint], models: Mapping[str, ChainModel] | None, path: str | Path,
              title: str = "Dynamic calibration", coverage: float = 2.0) -> Path:
    """Write a PNG Bode plot of ``points`` (all axes) with ``models`` (per axis key) to ``path``; returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, (ax_a, ax_p) = plt.subplots(2, 1, sharex=True, figsize=(7.5, 7.0))
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
                      color=c, capsize=3, label=f"{ax} measured")
        m = (models or {}).get(ax)
        phase = np.array([p.phase_deg for p in sel])
        if m is not None:  # a measured phase is known modulo 360 deg: show it on the model's branch
            model_phase = -360.0 * f * phase_delay_s(m, f)
            phase = phase + 360.0 * np.round((model_phase - phase) / 360.0)
        ax_p.errorbar(f, phase, yerr=[coverage * p.u_phase_deg for p in sel], fmt=MARKERS[ax], color=c, capsize=3)
        if m is not None:
            h = response(m, f_line)
            hp = "" if m.highpass_cutoff_hz is None else f", HP {m.highpass_cutoff_hz:.3g} Hz ({m.highpass_in})"
            ls = {"x": "-", "y": "--", "z": ":"}[ax]
            ax_a.semilogx(f_line, np.abs(h), ls, color=c, lw=1,
                          label=f"{ax} model: LP {m.cutoff_hz:.3g} Hz, delay {1e3 * m.delay_s:.3g} ms{hp}")
            # continuous phase from the model's parts (no wrapping jumps), in degrees
            ax_p.semilogx(f_line, -360.0 * f_line * phase_delay_s(m, f_line), ls, color=c, lw=1)
    ax_a.set_xscale("log")
    ax_a.set_ylabel("amplitude ratio sensor / reference [1]")
    ax_p.set_ylabel("phase [deg] (negative = sensor lags)")
    ax_p.set_xlabel("frequency [Hz]")
    for a in (ax_a, ax_p):
        a.grid(True, which="both", alpha=0.3)
    ax_a.legend(fontsize=7)
    ax_a.set_title(f"{title} (error bars: k = {coverage:g})")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
