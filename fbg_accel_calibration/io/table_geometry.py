"""Reference specific force on a two-axis rotation table (pure numpy).

Convention of ``../shared/data/measured/README.md``: theta turns about the table's x axis
(outer axis), psi about its z axis (inner axis); the specific force sensed at rest is
``f = Rz(psi)^T Rx(theta)^T (0, 0, g)`` in the table frame, in m/s^2 (REP 103: an accelerometer
at rest, z up, reads +g on z). Any fixed mounting rotation of the sensor on the table is absorbed
by the calibration matrix.
"""

from __future__ import annotations

import numpy as np

from fbg_accel_driver.sensor_constants import STANDARD_GRAVITY


def _rotation(angle_rad: np.ndarray, axis: int) -> np.ndarray:
    """Rotation matrices (..., 3, 3) by ``angle_rad`` (...) about the frame's axis ``axis`` (0: x, 2: z), filled in
    place (one array, where stacking rows of rows copies every sample's matrix several times)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    i, j = [k for k in range(3) if k != axis]
    out = np.zeros((*np.shape(c), 3, 3))
    out[..., axis, axis] = 1.0
    out[..., i, i], out[..., i, j], out[..., j, i], out[..., j, j] = c, -s, s, c
    return out


def rot_x(angle_rad: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about x by ``angle_rad`` (...)."""
    return _rotation(angle_rad, 0)


def rot_z(angle_rad: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about z by ``angle_rad`` (...)."""
    return _rotation(angle_rad, 2)


def table_specific_force(psi_deg: np.ndarray, theta_deg: np.ndarray, g: float = STANDARD_GRAVITY) -> np.ndarray:
    """Specific force (N, 3) in m/s^2 for table angles in degrees (arrays of shape (N,))."""
    psi = np.radians(np.atleast_1d(np.asarray(psi_deg, dtype=float)))
    theta = np.radians(np.atleast_1d(np.asarray(theta_deg, dtype=float)))
    up = np.array([0.0, 0.0, g])
    rz_t = np.swapaxes(rot_z(psi), -1, -2)
    rx_t = np.swapaxes(rot_x(theta), -1, -2)
    return np.einsum("nij,njk,k->ni", rz_t, rx_t, up)


def outer_angle_offset(gref_mps2: np.ndarray, psi_deg: np.ndarray, delta_deg: float) -> np.ndarray:
    """The specific force (N, 3, m/s^2) at an outer angle ``delta_deg`` (deg) larger than the one ``gref_mps2`` (N, 3)
    was computed at: f(theta + delta) = Rz(psi)^T Rx(delta)^T Rz(psi) f(theta), a rotation about the outer axis as it
    lies in the table frame, which the inner angle ``psi_deg`` (N,) alone places (theta need not be known)."""
    rz = rot_z(np.radians(np.asarray(psi_deg, dtype=float)))
    v = np.einsum("nij,nj->ni", rz, np.asarray(gref_mps2, dtype=float))  # Rz(psi) f, row by row
    v = v @ rot_x(np.radians(float(delta_deg)))  # Rx(delta)^T v, row by row
    return np.einsum("nji,nj->ni", rz, v)  # Rz(psi)^T v
