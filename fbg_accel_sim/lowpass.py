"""First-order low-pass filters of the simulator's signal chain (pure numpy), their state carried from one generation
chunk to the next: the optics' thermal inertia and the AHT10 die's lag, the TIA, the LDV's AC coupling."""

from __future__ import annotations

import math

import numpy as np

from .noise import first_order_filter


def _first_order(x: np.ndarray, alpha: float, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """y[k] = alpha y[k-1] + (1 - alpha) x[k] along axis 0 (columns independent); returns (y, new state)."""
    if alpha <= 0.0:
        return x.copy(), np.atleast_1d(x[-1]).copy()
    y = first_order_filter(x, alpha, -math.expm1(math.log(alpha)), np.asarray(state, float).reshape(x.shape[1:]))
    return y, np.atleast_1d(y[-1]).copy()


def _lowpass(x: np.ndarray, tau_s: float, dt_s: float, y_prev: float, x_prev: float,
             linear: bool) -> tuple[np.ndarray, float, float]:
    """First-order low-pass 1/(1 + s tau) of a 1-D sampled signal; returns (y, last y, last x).

    ``linear``: exact response to an input linear between samples (first-order hold, no phase error);
    else the input is held over each interval (y[k] = a y[k-1] + (1 - a) x[k]). ``tau_s`` 0: y = x.
    """
    x = np.asarray(x, float)
    if tau_s <= 0.0:
        return x.copy(), float(x[-1]), float(x[-1])
    a = math.exp(-dt_s / tau_s)
    if linear:
        r = tau_s / dt_s * -math.expm1(-dt_s / tau_s)  # tau/dt (1 - a)
        prev = np.concatenate([[x_prev], x[:-1]])
        v = (1.0 - r) * x + (r - a) * prev
        y = first_order_filter(v, a, 1.0, y_prev)
    else:
        y = first_order_filter(x, a, -math.expm1(-dt_s / tau_s), y_prev)
    return y, float(y[-1]), float(x[-1])
