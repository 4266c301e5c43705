"""ADC codes that hold whole visits and carry the residual: a code of the board's ADC that swallows a range of
inputs (``diagnose``).

A successive-approximation ADC such as the ESP32's has codes of unequal width (differential non-linearity, worst at
the major carry transitions of its capacitor array): a *wide* code reads one value over an input range several
counts wide, and the codes it takes the range from are never read (missing codes). A user report on the ESP32
shows one value returned over a whole range of input voltages (esp32.com forum, "Strange ADC Measurements",
viewtopic.php?t=18674); on the measured series (``../shared/data/measured``) the y channel reads 1535 (0x5FF, the
transition to 0x600) through five whole visits while the codes 1536-1543 never occur.

A reading at such a code is censored: the input sat anywhere across the code's width, so eq. 28 sees one value where
the input differed between visits, and the output of those visits is off by up to the width times the sensitivity.
No calibration term restores it; what can be done is to find the visits, say how far off they are, and measure the
code widths (a slow ramp of the input across the code: the histogram of the codes read gives each code's width).

Found in two steps. A visit is *held* on a channel when at least ``HELD_SHARE`` of its judged samples read one code
(a visit whose input sat near the code's edge reads the next code now and then). Holding alone
proves little (a quiet channel holds visits by chance), so the held visits of each (channel, code) are then tested
for what matters: do they carry the residual? The sum of their ``score`` (the caller's measure of how far a visit's
output is off) against the sums of as many visits drawn at random (``PERMUTATIONS`` draws, seeded: the same answer
every run); the sum, not ranks, because a wide code puts the visits whose input sat near its far edge far off and
leaves those near the code itself alone. Bonferroni over the (channel, code) pairs that hold any visit (which
visits are held does not depend on the residual, so the family is fixed before the test). One visit alone cannot
pass unless the campaign has hundreds of visits: its p-value is at least one over the number of visits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CHANNEL_NAMES = ("ref", "x", "y", "z")
MIN_VISIT_SAMPLES = 3  # a visit shorter than this does not show a held code
HELD_SHARE = 0.9  # a visit is held on a code when at least this share of its samples read it
PERMUTATIONS = 20_000  # random draws of the test (its smallest p-value is 1 / (PERMUTATIONS + 1))


@dataclass
class HeldCode:
    """One ADC code whose whole visits carry the residual (see the module docstring)."""

    channel: str  # "ref", "x", "y" or "z"
    code: int  # the ADC code (counts)
    visits: np.ndarray  # (k,) labels of the visits held on it
    n_samples: int  # their judged samples
    n_at_code: int  # of those, the samples that read the code
    p_value: float  # of their summed scores against as many visits drawn at random
    sigma_counts: float  # the channel's within-visit noise (median standard deviation of a visit's counts)
    missing_above: tuple[int, int] | None  # (first, last) codes just above never read in the recording, or None
    missing_below: tuple[int, int] | None  # likewise just below
    worst_offset: np.ndarray | None = None  # (3,) m/s^2: per axis, the visit mean residual largest in magnitude (caller)
    rmse_without: np.ndarray | None = None  # (3,) m/s^2: the held-out RMSE without these visits (set by the caller)

    def sentence(self) -> str:
        """The finding in one sentence (the report's warning)."""
        gaps = [f"codes {r[0]}-{r[1]}" if r[1] > r[0] else f"code {r[0]}"
                for r in (self.missing_below, self.missing_above) if r is not None]
        gap = f"; {' and '.join(gaps)} next to it never occur in the recording (missing codes)" if gaps else ""
        res = ("" if self.worst_offset is None else
               "; their visit means are off by up to " + " / ".join(f"{v:+.3f}" for v in self.worst_offset)
               + " m/s^2 (x/y/z)")
        if self.rmse_without is not None:
            res += "; without them the held-out RMSE is " + " / ".join(f"{v:.3f}" for v in self.rmse_without) + " m/s^2"
        return (f"ADC code {self.code} of channel {self.channel} holds {len(self.visits)} visit(s) ({self.n_at_code} of their "
                f"{self.n_samples} samples read it, where the channel's noise, {self.sigma_counts:.2g} counts rms within a "
                "visit, spreads a visit over several codes), "
                f"and these visits carry the residual (their summed offset against as many random visits: p = "
                f"{self.p_value:.2g}){gap}{res}: a "
                "wide code of the ADC (differential non-linearity) reads one value over a range of inputs, so these "
                "readings are censored and no calibration term restores them; measure the code widths with a slow ramp "
                "of that channel's input across the code (the histogram of the codes read), and take those visits' "
                "output as uncertain by that width")


def _missing_run(present: np.ndarray, code: int, step: int, lo: int) -> tuple[int, int] | None:
    """(first, last) of the run of codes never read next to ``code`` on the side ``step`` (+1 above, -1 below), inside
    the channel's read range (``present``: a flag per code from ``lo``); None when the next code is read or the run
    reaches the end of that range."""
    c = code + step
    while 0 <= c - lo < len(present) and not present[c - lo]:
        c += step
    if c == code + step or not 0 <= c - lo < len(present):
        return None
    a, b = sorted((code + step, c - step))
    return a, b


def held_codes(counts: np.ndarray, groups: np.ndarray, rows: np.ndarray, score: np.ndarray,
               alpha: float = 0.01) -> list[HeldCode]:
    """(Channel, code) pairs whose held visits carry the residual (module docstring), most significant first.

    ``counts`` (N, C) raw ADC counts, a column per channel (``CHANNEL_NAMES`` when C = 4); ``groups`` (N,) visit
    labels; ``rows`` (N,) the samples to judge (settled static samples); ``score`` (N,) how far each sample's visit
    is off (constant within a visit, e.g. its mean residual over the floor; NaN: a visit not judged). Channels whose
    counts are not integers (averaged or converted data) are not judged. Every sample counts for the missing codes."""
    counts = np.asarray(counts, float)
    idx = np.flatnonzero(rows & np.isfinite(score))
    if len(idx) == 0:
        return []
    order = idx[np.argsort(groups[idx], kind="stable")]
    labels, starts, n = np.unique(groups[order], return_index=True, return_counts=True)
    keep = n >= MIN_VISIT_SAMPLES
    labels, starts, n = labels[keep], starts[keep], n[keep]
    visit_score = score[order][starts]
    candidates: list[tuple[int, int, np.ndarray, int, float]] = []  # channel, code, held visits, samples at code, sigma
    for j in range(counts.shape[1]):
        col = counts[:, j]
        v = col[order]
        if not np.all(np.isfinite(v)) or np.any(v != np.round(v)):
            continue
        sd = np.array([v[s:s + k].std() for s, k in zip(starts, n, strict=True)])
        modal = [np.unique(v[s:s + k], return_counts=True) for s, k in zip(starts, n, strict=True)]
        codes = np.array([int(u[np.argmax(c)]) for u, c in modal])
        at_code = np.array([c.max() for _, c in modal])
        held = at_code >= HELD_SHARE * n
        for code in np.unique(codes[held]):
            at = np.flatnonzero(held & (codes == code))
            candidates.append((j, int(code), at, int(at_code[at].sum()), float(np.median(sd))))
    out = []
    rng = np.random.default_rng(0)
    for j, code, at, n_at, sigma in candidates:
        if len(at) == len(labels):
            continue
        # drawn with replacement (cheap for any number of visits; a wider null, so the p-value errs high)
        drawn = visit_score[rng.integers(0, len(labels), (PERMUTATIONS, len(at)))].sum(axis=1)
        p = (1.0 + float(np.sum(drawn >= visit_score[at].sum()))) / (PERMUTATIONS + 1.0)
        if p < alpha / len(candidates):
            col = counts[:, j]
            read = col[np.isfinite(col)].astype(np.int64)
            lo = int(read.min())
            present = np.zeros(int(read.max()) - lo + 1, bool)
            present[read - lo] = True
            name = CHANNEL_NAMES[j] if counts.shape[1] == len(CHANNEL_NAMES) else str(j)
            out.append(HeldCode(name, code, labels[at], int(n[at].sum()), n_at, p, sigma,
                                _missing_run(present, code, 1, lo), _missing_run(present, code, -1, lo)))
    return sorted(out, key=lambda h: h.p_value)
