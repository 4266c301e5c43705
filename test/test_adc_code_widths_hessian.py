"""The analytic Hessian of the code-width model (``adc_codes._WidthModel._hessian_parts``) against central differences
of its analytic gradient (``_WidthModel.nll``), column by column, at start points, random points, the fitted point, a
point with pieces far out in the tails (some of their cells at the probability floor) and one with pieces whose noise
parameter sits beyond either end of its clip (apart: the tails' entries are far larger than the others). The fitted
results of the analytic Hessian against those of the finite-difference one it replaced, on the bench campaigns and
the measured series: ``bench/adc_hessian_check.py``."""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_calibration.fit.adc_codes import LOG_SIGMA_RANGE, _visits_of, _WidthModel
from fbg_accel_driver.adc_code_table import pattern_codes
from fbg_accel_sim.sim_config import SimConfig

PATTERN = np.asarray(SimConfig.default().get("effects.adc_code_widths.widths"), float)
RTOL = 1e-6  # of the largest entry of the column
ATOL = 1e-9  # of the largest entry of the whole matrix: the differences' rounding (the gradient's sums over samples)
STEP = 5e-5  # the differences' step, halved once for Richardson's extrapolation (error O(STEP^4))


def _model() -> _WidthModel:
    """30 visits of 24 samples at random levels over 240 codes, 1.5 counts of noise, read through the measured width
    pattern, and 3 visits whose input sits inside one code with 0.02 counts of noise (they read one code throughout)."""
    rng = np.random.default_rng(1)
    level = np.concatenate([np.repeat(rng.uniform(1000.0, 1240.0, 30), 24), np.repeat([1100.3, 1150.1, 1201.0], 24)])
    noise = np.concatenate([rng.normal(0.0, 1.5, 30 * 24), rng.normal(0.0, 0.02, 3 * 24)])
    codes = pattern_codes(level + noise, PATTERN)
    vis = _visits_of(codes, np.repeat(np.arange(33), 24), np.ones(len(codes), bool))
    assert np.all([len(np.unique(vis.code[vis.visit == v])) == 1 for v in range(30, 33)])
    return _WidthModel(vis, len(PATTERN))


MODEL = _model()


def _points() -> dict[str, np.ndarray]:
    m, rng = MODEL, np.random.default_rng(2)
    G, V = m.G, m.V
    fit = m.fit()
    out = {"start": m.start(), "fitted": fit}
    for k in range(3):
        out[f"random {k}"] = m.start() + rng.normal(0.0, 0.5, len(fit))
    tails = fit.copy()
    sigma = m.unpack(fit)[1]
    for v, z in enumerate((10.0, -25.0, 35.0, -37.5)):  # the line this many of its sigmas off the codes read
        tails[G + v] += z * sigma[v]
    out["tails"] = tails
    clips = fit.copy()
    clips[G + 2 * V + 5] = LOG_SIGMA_RANGE[0] - 5.0  # clipped: sigma at its floor, s does not move it
    clips[G + 2 * V + 6] = LOG_SIGMA_RANGE[1] + 1.0  # clipped above
    out["clips"] = clips
    return out


POINTS = _points()


def _assemble(m: _WidthModel, h_gg: np.ndarray, b: np.ndarray, h_ll: np.ndarray) -> np.ndarray:
    """The whole (G + L V) Hessian from its arrow-shaped parts, in ``theta``'s order."""
    G, V, L = m.G, m.V, m.L
    out = np.zeros((G + L * V, G + L * V))
    out[:G, :G] = h_gg
    at = np.arange(V)
    for k in range(L):
        out[:G, G + k * V:G + (k + 1) * V] = b[:, :, k]
        out[G + k * V:G + (k + 1) * V, :G] = b[:, :, k].T
        for j in range(L):
            out[G + k * V + at, G + j * V + at] = h_ll[:, k, j]
    return out


def _differences(m: _WidthModel, theta: np.ndarray, h: float) -> np.ndarray:
    """The gradient's Jacobian by central differences of step ``h``, made symmetric."""
    n = len(theta)
    jac = np.empty((n, n))
    for i in range(n):
        d = np.zeros(n)
        d[i] = h
        jac[:, i] = (m.nll(theta + d)[1] - m.nll(theta - d)[1]) / (2.0 * h)
    return 0.5 * (jac + jac.T)


@pytest.mark.parametrize("name", list(POINTS))
def test_the_analytic_hessian_is_the_gradient_s_jacobian(name: str) -> None:
    """Every column of the assembled Hessian within ``RTOL`` of its largest entry (plus ``ATOL`` of the matrix's) of
    the Richardson-extrapolated central differences of the gradient; the local-only parts are the same local blocks."""
    m, theta = MODEL, POINTS[name]
    parts = m._hessian_parts(theta)
    got = _assemble(m, *parts)
    ref = (4.0 * _differences(m, theta, STEP / 2.0) - _differences(m, theta, STEP)) / 3.0
    tol = np.broadcast_to(RTOL * np.max(np.abs(ref), axis=0) + ATOL * np.max(np.abs(ref)), ref.shape)
    err = np.abs(got - ref)
    worst = np.unravel_index(np.argmax(err / tol), err.shape)
    assert np.all(err <= tol), (name, worst, got[worst], ref[worst], tol[worst])
    h_gg, b, h_ll = m._hessian_parts(theta, local_only=True)
    np.testing.assert_array_equal(h_ll, parts[2])
    np.testing.assert_array_equal(h_gg, np.eye(m.G))
    assert not b.any()


def test_the_points_reach_the_tails_the_clips_and_the_probability_floor() -> None:
    """The cases the Hessian's special terms are for are in the points checked above."""
    m = MODEL
    terms = m._terms(POINTS["tails"])
    live, z = terms[-1], np.concatenate(terms[4:6])
    assert (~live).sum() > 0 and live.sum() > 0 and np.max(np.abs(z[np.isfinite(z)])) > 30.0
    s = POINTS["clips"][m.G + 2 * m.V:]
    assert np.any(s < LOG_SIGMA_RANGE[0]) and np.any(s > LOG_SIGMA_RANGE[1])
    fit = POINTS["fitted"]
    assert np.max(np.abs(m.nll(fit)[1][:m.G])) < 1.0 < np.max(np.abs(m.nll(POINTS["start"])[1][:m.G]))
