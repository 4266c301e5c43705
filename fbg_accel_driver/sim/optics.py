"""Optical model of one axis: a push-pull FBG pair read by dual reflection (paper 3.3-3.4).

Pure numpy. The detected power of an axis is (paper eq. 13)::

    P = A_b/16 * integral s(lambda) r2(lambda) r1(lambda) dlambda

with Gaussian grating profiles r_j(lambda) = R exp(-(lambda - lambda_j)^2 / (2 sigma_g^2)) (FWHM
~3 nm, paper 3.2) and a Gaussian SLD spectrum s(lambda) (FWHM ~40 nm, paper 3.3) instead of the
paper's flat-source simplification. For a pair centred at lambda_c with separation d the product
r1 r2 = R^2 exp(-d^2 / (4 sigma_g^2)) exp(-(lambda - lambda_c)^2 / sigma_g^2), so the integral
factorises exactly into

* an overlap factor O(d) = exp(-d^2 / (4 sigma_g^2)) that carries the acceleration
  (d = d0 - S a, S = 112 pm/g, d0 = 2.5 nm: monotonic for d > 0, i.e. a < d0/S = 22.3 g, and
  non-injective beyond, where the spectra cross, paper eq. 22 and Fig. 9), and
* a source factor exp(-(lambda_c - lambda_s)^2 * k) that carries the SLD wavelength drift
  relative to the gratings (paper 3.6.2), k = (1/sigma_g^2)(1/(2 sigma_s^2)) / (1/sigma_g^2 + 1/(2 sigma_s^2)).

The sign convention: the peaks approach for positive acceleration along the axis, so Psi grows
with acceleration, as the positive diagonal of the published calibration matrix implies (the
paper's Fig. 9 draws the crossing on the negative side; that is a sign of the mounting).
"""

from __future__ import annotations

import math

import numpy as np

FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
STANDARD_G = 9.80665  # m/s^2 per g (the paper's sensitivity is per g_E)


def grating_sigma_nm(fwhm_nm: np.ndarray | float) -> np.ndarray:
    """Gaussian sigma (nm) of a grating with the given FWHM (nm)."""
    return np.asarray(fwhm_nm, dtype=float) * FWHM_TO_SIGMA


def overlap(d_nm: np.ndarray, sigma_g_nm: np.ndarray) -> np.ndarray:
    """Normalised overlap factor O(d) = exp(-d^2/(4 sigma_g^2)) of a pair with separation d (nm)."""
    d = np.asarray(d_nm, dtype=float)
    return np.exp(-(d * d) / (4.0 * np.asarray(sigma_g_nm) ** 2))


def overlap_slope(d_nm: np.ndarray, sigma_g_nm: np.ndarray) -> np.ndarray:
    """dO/dd (1/nm)."""
    s2 = np.asarray(sigma_g_nm) ** 2
    return -np.asarray(d_nm) / (2.0 * s2) * overlap(d_nm, sigma_g_nm)


def source_factor(center_offset_nm: np.ndarray, sigma_g_nm: np.ndarray, sigma_s_nm: float) -> np.ndarray:
    """Source spectral factor exp(-k (lambda_c - lambda_s)^2) of the factorised eq. 13 integral."""
    a = 1.0 / np.asarray(sigma_g_nm) ** 2
    b = 1.0 / (2.0 * sigma_s_nm**2)
    k = a * b / (a + b)
    off = np.asarray(center_offset_nm, dtype=float)
    return np.exp(-k * off * off)


def relative_response(u_mps2: np.ndarray, d0_nm: float, s_nm_per_mps2: float, sigma_g_nm: np.ndarray,
                      nonlinearity: float, d_extra_nm: np.ndarray | float = 0.0) -> np.ndarray:
    """Detected power of the axes relative to rest, for axis inputs ``u_mps2`` (N, 3).

    ``d_extra_nm`` adds a separation change that is not acceleration (thermal mismatch, creep).
    ``nonlinearity`` = 1 gives the physical overlap; 0 the tangent at rest (linearised response);
    values in between scale the difference (the ``spectral_nonlinearity`` effect).
    """
    d = d0_nm - s_nm_per_mps2 * np.asarray(u_mps2) + d_extra_nm
    o0 = overlap(d0_nm, sigma_g_nm)
    phys = overlap(d, sigma_g_nm) / o0
    if nonlinearity == 1.0:
        return phys
    lin = 1.0 + overlap_slope(d0_nm, sigma_g_nm) / o0 * (d - d0_nm)
    return lin + nonlinearity * (phys - lin)


def sigma_for_relative_slope(rel_slope_per_mps2: np.ndarray, d0_nm: float, s_nm_per_mps2: float) -> np.ndarray:
    """Grating sigma (nm) whose overlap has the given relative slope dO/O per m/s^2 at rest.

    From O = exp(-d^2/(4 s^2)): (dO/da)/O = d0 * S / (2 s^2)  ->  s = sqrt(d0 S / (2 slope)).
    """
    return np.sqrt(d0_nm * s_nm_per_mps2 / (2.0 * np.asarray(rel_slope_per_mps2, dtype=float)))
