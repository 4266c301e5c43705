"""A small calibration campaign for which eq. 28 holds exactly: the statistical rig of the coefficient uncertainty.

Pure numpy. The physics simulator (``board_physics``) has effects eq. 28 does not contain (the spectral
non-linearity, the time drift), so its "true coefficients" are not defined; this campaign's are, and what is left is
what the coefficient covariance (``fbg_accel_calibration.fit.coefficient_uncertainty``) must account for:

* the table's pose error, shared by all samples of one visit: a random tilt of the true specific force (sigma
  ``tilt_sigma_deg``; a rotation table's repeatability is of the order of 0.1 deg, and the measured series' poses are
  read back to whole degrees, ../shared/data/measured/README.md), so the reference is wrong by a constant per visit;
* the detector noise low-passed by the transimpedance stage: first-order (AR(1)) noise of time constant ``tau_s``
  (0.15 s: the paper's TIA stages cut off at 1-1.7 Hz, paper Table 1 / docs/simulator.md), so the samples of one
  visit are correlated;
* optionally a run's own constant bias (``run_offset_mps2`` per axis, a new one per run; ``runs_per_level`` runs at
  each level): what a sensor keeps over one run and changes from turn-on to turn-on (the slow error's run-to-run part,
  ``fbg_accel_calibration.fit.slow_error``).

Returns a ``Recording`` (``runs_per_level`` runs per temperature level, default one, poses visited ``repeats`` times
in turn) and the true coefficients A (p, 3) in the fit's tau scaling (levels 15/25/35 degC: centre 25, half-range 10).
"""

from __future__ import annotations

import numpy as np

from fbg_accel_calibration.fit.thermal_fit import model_to_coefficients
from fbg_accel_calibration.io.recording import Recording

G = 9.80665
LEVELS_C = (15.0, 25.0, 35.0)  # centre 25, half-range 10: the fit's own tau scaling
RATE_HZ = 100.0


def _truth(degree: int) -> tuple[np.ndarray, np.ndarray]:
    M = [np.array([[80.0, 1.5, -2.0], [0.8, 78.0, 1.1], [-1.2, 2.2, 107.0]])]
    b = [np.array([-101.0, -153.0, -137.0])]  # Psi near 1.2-1.4: counts about 1100-1250 at a reference of 880
    for k in range(1, degree + 1):
        M.append(np.array([[1.0, -0.4, 0.3], [0.2, -0.8, 0.5], [0.6, 0.1, 1.4]]) / k)
        b.append(np.array([0.7, -0.5, 0.9]) / k)
    return np.array(M), np.array(b)


def campaign(seed: int, degree: int = 1, n_poses: int = 8, repeats: int = 2, visit_s: float = 3.0,
             tilt_sigma_deg: float = 0.3, noise_mps2: float = 0.05, tau_s: float = 0.15, runs_per_level: int = 1,
             run_offset_mps2: float = 0.0) -> tuple[Recording, np.ndarray]:
    """Counts that eq. 28 with known (M, b) maps onto random poses at three chamber levels, each pose visited
    ``repeats`` times. Per visit the table's pose is off by a random tilt (sigma ``tilt_sigma_deg``, shared by the
    visit's samples: the reference is wrong by a constant), and the output carries first-order low-passed noise
    (sigma ``noise_mps2``, time constant ``tau_s``), as the TIA stages low-pass the detector noise. Returns the
    recording and the true coefficients A (p, 3) in the fit's tau scaling. ``runs_per_level`` runs at each level, each
    with its own constant bias (sigma ``run_offset_mps2`` per axis, drawn from a stream of its own so that the
    campaign without it is unchanged)."""
    rng = np.random.default_rng(seed)
    offsets = np.random.default_rng([seed, 1]).normal(0.0, run_offset_mps2, (len(LEVELS_C) * runs_per_level, 3))
    M, b = _truth(degree)
    poses = rng.normal(size=(n_poses, 3))
    poses = G * poses / np.linalg.norm(poses, axis=1)[:, None]
    n = round(visit_s * RATE_HZ)
    phi = np.exp(-1.0 / (RATE_HZ * tau_s))
    parts = []
    for li, temp_c in enumerate(LEVELS_C):
        tau = (temp_c - 25.0) / 10.0
        Mt = sum(M[k] * tau**k for k in range(degree + 1))
        bt = sum(b[k] * tau**k for k in range(degree + 1))
        for k in range(runs_per_level):
            run_id = li * runs_per_level + k
            for _ in range(repeats):
                for p in range(n_poses):
                    axis = rng.normal(size=3)
                    tilt = np.radians(tilt_sigma_deg) * rng.normal()
                    true_g = poses[p] + tilt * np.cross(axis / np.linalg.norm(axis), poses[p])  # small rotation
                    w = rng.normal(0.0, noise_mps2 * np.sqrt(1 - phi**2), (n, 3))
                    w[0] = rng.normal(0.0, noise_mps2, 3)
                    for i in range(1, n):
                        w[i] += phi * w[i - 1]
                    psi = np.linalg.solve(Mt, (true_g + w + offsets[run_id] - bt).T).T
                    parts.append((psi, np.full(n, temp_c), np.repeat(poses[p][None], n, 0), np.full(n, p),
                                  np.full(n, run_id)))
    psi, temp, gref, pose, run = (np.concatenate(x) for x in zip(*parts, strict=True))
    ref = np.full(len(temp), 880.0)
    t = np.arange(len(temp)) / RATE_HZ
    return Recording(t, ref, psi * ref[:, None], temp, gref, pose, run), model_to_coefficients(M, b)
