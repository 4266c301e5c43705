"""The approach-direction signature of a motion-history (mechanical) hysteresis: does one direction of gravity read
differently by the side each axis' specific force came from (``approach_direction``)?

A hysteresis of the motion's history (micro-slip or viscoelastic lag of the bonds holding the fibre segments,
cyanoacrylate and epoxy, paper 3.1; or the backlash of the table's gears) is no function of the orientation, of the
temperature or of time: no candidate of the library represents it, and what it leaves reads as a non-linearity (over
the poses) or a drift (over a pose order). Its own signature is the sign of the last change: visits of one direction
of gravity approached from below and from above on an axis differ on that axis by the hysteresis' gap. A campaign
that approaches every direction from one side only (a fixed pose order, each pose visited once or always after the
same one) cannot reveal it, and says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from .data import DiagnosisData, direction_labels, finite_rows, group_index
from .findings import Finding

# A change of an axis' reference between visits smaller than this (m/s^2) is no approach from either side: the table's
# reference at one pose repeats to far better (its angles, table_geometry), the poses of a plan differ by tens of
# degrees (a 10 degree step moves an axis by 1.7 m/s^2).
MIN_APPROACH_CHANGE_MPS2 = 0.5
TELLS_IT = ("visit the poses from both directions (the plan forward and backward in turn, or in shuffled orders): a "
            "hysteresis comes back with the side of approach, a drift follows time and a non-linearity the orientation; "
            "turning the sensor 90 degrees on the table tells the sensor's (it turns with the sensor) from the table's "
            "backlash (it stays with the table's axis)")


@dataclass
class ApproachSignature:
    """Per axis x/y/z: the half gap between visits of one direction approached from below and from above (m/s^2, the
    output's mean when its force rose to it minus that when it fell, halved: positive, it reads high after a rise),
    its two-sided p (t test on the visit means' own scatter within the directions, ``dof`` degrees of freedom), the
    visits and directions that take part (approached from both sides)."""

    half_gap_mps2: np.ndarray
    p: np.ndarray
    dof: np.ndarray
    visits: np.ndarray
    directions: np.ndarray

    @property
    def testable(self) -> bool:
        return bool(np.any(self.dof >= 1))


def approach_signs(data: DiagnosisData, g_mean: np.ndarray, first: np.ndarray, run: np.ndarray) -> np.ndarray:
    """(V, 3) the side each visit's axis was approached from: +1 its specific force rose to it, -1 fell, 0 unknown.
    ``g_mean`` (V, 3) the visits' mean reference (m/s^2), ``first`` (V,) the index of each one's first sample, ``run``
    (V,) their run. The side is that of the last reference before the visit (the table's path, where the recording
    gives the reference in motion; else the earlier visits, latest first) that differs from the visit's on the axis
    by more than ``MIN_APPROACH_CHANGE_MPS2``: a path that overshoots and comes back is approached from its last
    side, not from the previous pose's."""
    out = np.zeros(g_mean.shape, dtype=int)
    for r in np.unique(run):
        idx = np.flatnonzero(run == r)
        idx = idx[np.argsort(first[idx], kind="stable")]
        if len(idx) < 2:
            continue
        # visit idx[k + 1]'s path: the samples from the first of the visit before it to its own first, one pass over
        # the run for all of them (the paths follow one another)
        start, end = first[idx[:-1]], first[idx[1:]]
        lo = int(start[0])
        g = data.gref[lo:end[-1]]
        ok = (data.run_id[lo:end[-1]] == r) & finite_rows(g)
        path_of = np.repeat(np.arange(len(idx) - 1), end - start)  # each sample's path
        for j in range(3):
            d = g_mean[idx[1:], j][path_of] - g[:, j]
            moved = np.flatnonzero(ok & (np.abs(d) > MIN_APPROACH_CHANGE_MPS2))
            last = np.searchsorted(moved, end - lo) - 1  # the latest sample of each path that differs
            found = last >= 0
            found[found] = moved[last[found]] >= start[found] - lo
            out[idx[1:][found], j] = np.sign(d[moved[last[found]]]).astype(int)
            for k in np.flatnonzero(~found):  # none on its path: the earlier visits, latest first
                d_visits = g_mean[idx[k + 1], j] - g_mean[idx[:k + 1][::-1], j]
                differs = np.flatnonzero(np.abs(d_visits) > MIN_APPROACH_CHANGE_MPS2)
                if differs.size:
                    out[idx[k + 1], j] = int(np.sign(d_visits[differs[0]]))
    return out


def approach_signature(data: DiagnosisData, res: np.ndarray, rows: np.ndarray) -> ApproachSignature:
    """The signature on the held-out residual ``res`` (N, 3) m/s^2 over the visits of ``rows``: per axis, the visit
    means about their direction's mean regressed on the side of approach (also about its mean in the direction), with
    the scatter of the visit means themselves (a bias instability between visits minutes apart, the fit's own error
    are in it) as the t test's error, and a line in time beside it: a plan run forward then backward approaches each
    pose from one side per pass, and a drift between the passes is no hysteresis."""
    r = rows & (data.group >= 0) & finite_rows(res) & finite_rows(data.gref)
    ug, inv = group_index(data.group[r])
    n = np.bincount(inv).astype(float)

    def means(x: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(inv, weights=x[:, j]) / n for j in range(x.shape[1])], axis=1)

    m, g = means(res[r]), means(data.gref[r])
    idx = np.flatnonzero(r)
    first = np.full(len(ug), len(data.t_s), dtype=np.int64)
    np.minimum.at(first, inv, idx)
    run = data.run_id[first]
    side = approach_signs(data, g, first, run)
    tv = np.bincount(inv, weights=data.t_s[r]) / n
    label = direction_labels(g)
    half, p, dof = np.zeros(3), np.ones(3), np.zeros(3)
    visits, dirs = np.zeros(3, dtype=int), np.zeros(3, dtype=int)
    for j in range(3):
        known = side[:, j] != 0
        if not known.any():
            continue
        lab = np.unique(label[known], return_inverse=True)[1]
        cnt = np.bincount(lab)

        def centred(x: np.ndarray, lab: np.ndarray = lab, cnt: np.ndarray = cnt) -> np.ndarray:
            return x - (np.bincount(lab, weights=x) / cnt)[lab]  # about its direction's mean

        s_c, t_c, y_c = centred(side[known, j].astype(float)), centred(tv[known]), centred(m[known, j])
        both = np.bincount(lab, weights=s_c ** 2)[lab] > 1e-12  # directions approached from both sides
        visits[j], dirs[j] = int(both.sum()), len(np.unique(lab[both]))
        dof[j] = max(visits[j] - dirs[j] - 2, 0)  # the side and the time, within the directions
        if dof[j] < 1:
            continue
        X = np.column_stack([s_c[both], t_c[both]])
        coef, *_ = np.linalg.lstsq(X, y_c[both], rcond=None)
        e = y_c[both] - X @ coef
        try:
            var = float(np.sum(e ** 2)) / dof[j] * np.linalg.inv(X.T @ X)[0, 0]
        except np.linalg.LinAlgError:  # the side goes with the time: not told apart
            dof[j] = 0
            continue
        half[j] = -coef[0]  # the output's: the residual is the reference minus the output
        p[j] = float(2 * stats.t.sf(abs(coef[0]) / np.sqrt(var), dof[j])) if var > 0 else 1.0
    return ApproachSignature(half, p, dof, visits, dirs)


def approach_findings(sig: ApproachSignature, alpha: float, added: list[str]) -> list[Finding]:
    """The finding of the signature: out of reach when no direction was approached from both sides on any axis; a
    motion-history hysteresis named when an axis differs by its side of approach (p < ``alpha`` / 3, Bonferroni over
    the axes), with the terms of the model (``added``) that may stand in for it."""
    if not sig.testable:
        return [Finding("cannot_reveal", "this campaign cannot reveal a motion-history (mechanical) hysteresis (one pose "
                        "reading differently by the side it was approached from): no direction of gravity was approached "
                        "from both sides on any axis, so it reads as an effect of the orientation; " + TELLS_IT,
                        effect="motion_hysteresis", separates=TELLS_IT)]
    axes = [j for j in range(3) if sig.p[j] < alpha / 3]
    if not axes:
        return []
    stand_in = [a for a in added if a in ("time_drift", "spectral_nonlinearity", "run_drift", "run_offset")]
    text = ("one direction of gravity reads differently by the side it was approached from on "
            + ", ".join(f"{'xyz'[j]} (half gap {sig.half_gap_mps2[j]:+.3g} m/s^2 over {sig.visits[j]} visits of "
                        f"{sig.directions[j]} directions, p {sig.p[j]:.1e})" for j in axes)
            + ": a motion-history (mechanical) hysteresis of the sensor (its bonds) or of the table (backlash), which no "
            "term of the calibration represents; it is neither a drift nor a non-linearity"
            + (f" ({', '.join(stand_in)} in the model may stand in for part of it)" if stand_in else "")
            + "; " + TELLS_IT)
    return [Finding("approach_direction", text, effect="motion_hysteresis",
                    numbers={"axes": ["xyz"[j] for j in axes], "half_gap_mps2": sig.half_gap_mps2, "p": sig.p},
                    separates=TELLS_IT)]
