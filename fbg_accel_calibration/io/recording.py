"""In-memory calibration recording: the arrays every fitting and diagnosis step works on.

Pure numpy. Produced by the MCAP reader (``mcap_reader``), the CSV importer and the simulator's
batch API, so the fit and the diagnosis never care where the data came from.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fbg_accel_driver.frame_codec import clipped_reading
from fbg_accel_driver.sensor_constants import LOW_REFERENCE_COUNTS

_SAMPLE_FIELDS = ("t_s", "ref", "xyz", "temp_c", "gref_mps2", "pose_id")  # the (N, ...) arrays before run_id

@dataclass
class Recording:
    """Time-ordered samples of one run (N samples).

    * ``t_s`` (N,): board time in seconds (monotonic within a run).
    * ``ref`` (N,): reference photodetector ADC counts.
    * ``xyz`` (N, 3): x, y, z channel ADC counts.
    * ``temp_c`` (N,): AHT10 temperature in degC, NaN where the sensor reported invalid.
    * ``gref_mps2`` (N, 3): reference specific force of the pose in the table frame, m/s^2;
      NaN rows where no reference is known (between poses).
    * ``pose_id`` (N,): integer id of the commanded pose, -1 while moving or unknown.
    * ``run_id`` (N,): integer id of the run (file / temperature level) each sample came from.
    * ``metadata``: free-form run information (sensor id, plan, operator notes, source files).
    * ``aux`` (N,) or None: auxiliary ADC counts (protocol version 2: the reference transducer of a
      dynamic calibration, same board clock); None when the source has no such channel.
    * ``table_deg`` (N, 2) or None: the table's angle readings psi (inner axis), theta (outer axis), degrees, that
      ``gref_mps2`` was computed from (``table_geometry``); None when the source gives the reference as a vector.
    """

    t_s: np.ndarray
    ref: np.ndarray
    xyz: np.ndarray
    temp_c: np.ndarray
    gref_mps2: np.ndarray
    pose_id: np.ndarray
    run_id: np.ndarray | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    aux: np.ndarray | None = None
    table_deg: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.t_s = np.asarray(self.t_s, dtype=float)
        n = self.t_s.shape[0]
        self.ref = np.asarray(self.ref, dtype=float).reshape(n)
        self.xyz = np.asarray(self.xyz, dtype=float).reshape(n, 3)
        self.temp_c = np.broadcast_to(np.asarray(self.temp_c, dtype=float), (n,)).copy()
        self.gref_mps2 = np.asarray(self.gref_mps2, dtype=float).reshape(n, 3)
        self.pose_id = np.asarray(self.pose_id, dtype=int).reshape(n)
        self.run_id = np.zeros(n, dtype=int) if self.run_id is None else np.asarray(self.run_id, int).reshape(n)
        if self.aux is not None:
            self.aux = np.asarray(self.aux, dtype=float).reshape(n)
        if self.table_deg is not None:
            self.table_deg = np.asarray(self.table_deg, dtype=float).reshape(n, 2)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def clipped(self) -> np.ndarray:
        """Samples (N,) with a channel at a rail of the 12-bit ADC (paper 3.5: the ESP32's converters;
        ``frame_codec.clipped_reading``): the reading bounds the signal instead of measuring it. Counts below 0 are
        no reading of the ADC at all (the importers refuse them)."""
        return clipped_reading(self.ref, self.xyz[:, 0], self.xyz[:, 1], self.xyz[:, 2])

    def low_reference(self) -> np.ndarray:
        """Samples (N,) whose reference is below ``sensor_constants.LOW_REFERENCE_COUNTS`` (0 included): no source light
        (SLD off, fiber unplugged), so Psi = counts / ref (eq. 24) is no measurement, tens of times its normal size.
        The driver publishes no acceleration for them (``min_reference_counts``); every fit and diagnosis leaves
        them out (:func:`without_low_reference`). A NaN reference is no reading, not a dark one."""
        return self.ref < LOW_REFERENCE_COUNTS

    def select(self, mask: np.ndarray) -> Recording:
        """A new recording with the samples ``mask`` selects (a boolean mask, indices or a slice; order kept)."""
        return Recording(*(getattr(self, name)[mask] for name in _SAMPLE_FIELDS), self.run_id[mask], dict(self.metadata),
                         None if self.aux is None else self.aux[mask],
                         None if self.table_deg is None else self.table_deg[mask])

    def runs(self) -> list[Recording]:
        """Each run (``run_id``) as its own recording (views of these arrays but the temperature, which a
        ``Recording`` copies), in order. Raises ``ValueError`` when
        the samples of one run are not contiguous (every reader and ``concatenate`` keeps them together)."""
        starts = np.flatnonzero(np.r_[True, self.run_id[1:] != self.run_id[:-1]]) if len(self) else np.zeros(0, int)
        if len(np.unique(self.run_id[starts])) != len(starts):
            raise ValueError("the samples of one run must be contiguous")
        return [self.select(slice(a, b)) for a, b in zip(starts, [*starts[1:], len(self)], strict=True)]

    def blocks(self, block_rows: int, with_poses: bool = True) -> Iterator[Recording]:
        """Consecutive blocks of ``block_rows`` samples (views), as a file source serves a run block by block
        (``fit_stream.SampleBlockSource``): a run in memory goes through the same streamed steps as a file."""
        for start in range(0, len(self), block_rows):
            yield self.select(slice(start, start + block_rows))

    @staticmethod
    def concatenate(parts: list[Recording]) -> Recording:
        """Join runs; each part keeps its own ``run_id`` offset so runs stay distinguishable."""
        if not parts:
            raise ValueError("no recordings to concatenate")
        run_ids, offset = [], 0
        for p in parts:
            run_ids.append(p.run_id + offset)
            offset += int(p.run_id.max()) + 1 if len(p) else 1
        return _joined(parts, np.concatenate(run_ids), {"parts": [p.metadata for p in parts]})


def _joined(parts: list[Recording], run_id: np.ndarray, metadata: dict[str, Any]) -> Recording:
    """The samples of ``parts`` one after the other, under ``run_id`` and ``metadata``."""
    aux = np.concatenate([p.aux for p in parts]) if all(p.aux is not None for p in parts) else None
    table = (np.concatenate([p.table_deg for p in parts]) if all(p.table_deg is not None for p in parts) else None)
    return Recording(*(np.concatenate([getattr(p, name) for p in parts]) for name in _SAMPLE_FIELDS), run_id, metadata, aux,
                     table)


def join_blocks(parts: list[Recording]) -> Recording:
    """Consecutive blocks of one run joined into one (``run_id`` and metadata kept as they are, unlike
    :meth:`Recording.concatenate`)."""
    if len(parts) == 1:
        return parts[0]
    return _joined(parts, np.concatenate([p.run_id for p in parts]), dict(parts[0].metadata))


class LowReference:
    """The samples of a reference too low to be data (:meth:`Recording.low_reference`) that were left out, counted block
    after block in time order: how many, in how many stretches, and the first few stretches (run, first and last
    time, samples). Memory bounded whatever a reference that flickers around the limit does."""

    SHOWN = 3  # stretches described in full

    def __init__(self) -> None:
        self.count = 0
        self.stretches = 0
        self.shown: list[list[float]] = []  # [run, t_first_s, t_last_s, samples]
        self.runs: set[int] = set()  # the runs that have such samples
        self._last: tuple[int, bool, bool] | None = None  # (run, last sample low, its stretch shown)

    def add(self, run: int, t_s: np.ndarray, low: np.ndarray) -> None:
        """The next block (``t_s`` (n,), ``low`` (n,) bool) of run ``run`` (the i-th run or file)."""
        low = np.asarray(low, dtype=bool)
        if not len(low):
            return
        go_on = self._last is not None and self._last[:2] == (run, True)  # the previous block ended in a stretch
        shown_open = go_on and self._last[2]  # type: ignore[index]
        last_shown = False
        if low.any():
            self.count += int(low.sum())
            self.runs.add(int(run))
            starts = np.flatnonzero(low & ~np.r_[False, low[:-1]])
            ends = np.flatnonzero(low & ~np.r_[low[1:], False])
            for a, b in zip(starts, ends, strict=True):
                if a == 0 and go_on:  # the stretch of the previous block goes on
                    if shown_open:
                        self.shown[-1][2] = float(t_s[b])
                        self.shown[-1][3] += int(b - a + 1)
                    last_shown = shown_open
                    continue
                self.stretches += 1
                last_shown = len(self.shown) < self.SHOWN
                if last_shown:
                    self.shown.append([int(run), float(t_s[a]), float(t_s[b]), int(b - a + 1)])
        self._last = (int(run), bool(low[-1]), bool(low[-1]) and last_shown)

    def add_recording(self, rec: Recording) -> None:
        """Every run of ``rec`` at once (an in-memory recording)."""
        low = rec.low_reference()
        if low.any():
            for i, run in enumerate(rec.runs()):
                self.add(i, run.t_s, run.low_reference())

    def as_dict(self) -> dict[str, Any]:
        return {"samples": self.count, "stretches": self.stretches, "runs": sorted(self.runs),
                "first_stretches": [list(s) for s in self.shown]}

    def warning(self) -> str:
        """One line: how many samples, where, why (without a ``warning:`` prefix); empty when none."""
        return low_reference_warning(self.as_dict())


def low_reference_warning(summary: dict[str, Any] | None) -> str:
    """The one line that says which samples of a reference too low were left out (``LowReference.as_dict``, as a
    calibration's ``fit["low_reference"]`` keeps it); empty when none."""
    if not summary or not summary.get("samples"):
        return ""
    shown = summary["first_stretches"]
    runs = summary.get("runs") != [0]  # name the run unless every stretch is in the first (or only) one
    where = ", ".join(f"t = {s[1]:.2f}-{s[2]:.2f} s" + (f" of run {int(s[0])}" if runs else "") for s in shown)
    more = summary["stretches"] - len(shown)
    return (f"{summary['samples']} samples with the reference below {LOW_REFERENCE_COUNTS} counts left out (no source "
            f"light: SLD off or fiber unplugged; Psi = counts/ref is no measurement there), in {summary['stretches']} "
            f"stretch(es) at {where}" + (f" and {more} more" if more > 0 else "")
            + "; the driver does not publish them either (min_reference_counts)")


def without_low_reference(blocks: Iterator[Recording], block_rows: int, tally: LowReference | None = None,
                          run: int = 0) -> Iterator[Recording]:
    """The blocks of one run with the samples of a reference too low (:meth:`Recording.low_reference`) taken out, each
    counted in ``tally`` (as run ``run``); :func:`without_samples`."""

    def flags(blk: Recording, _last: bool) -> tuple[Recording, np.ndarray, np.ndarray]:
        low = blk.low_reference()
        if tally is not None:
            tally.add(run, blk.t_s, low)
        return blk, low, np.zeros(len(blk), bool)

    return without_samples(blocks, block_rows, flags)


def without_samples(blocks: Iterator[Recording], block_rows: int,
                    flags: Callable[[Recording, bool], tuple[Recording, np.ndarray, np.ndarray]]
                    ) -> Iterator[Recording]:
    """The blocks of one run, each as ``flags(block, last)`` gives it back, without the samples marked in its first
    array (``last``: no block follows); the samples marked in its second array are held back and judged again at the
    front of the next block (a check that needs the samples after them). Blocks without either pass unchanged (a run
    without any: the same blocks, the same results bit for bit); after one, the samples left are cut again into
    blocks of ``block_rows``, so the run gives the blocks the run without those samples would give (the fit's moving
    windows and interval rules then see the samples before and after a dropped stretch as neighbours, as in a
    recording without the stretch)."""
    held: list[Recording] = []
    n_held = 0
    back: Recording | None = None  # held back by flags
    it = iter(blocks)
    blk = next(it, None)
    while blk is not None:
        following = next(it, None)
        if back is not None:
            blk, back = join_blocks([back, blk]), None
        blk, drop, hold = flags(blk, following is None)
        if hold.any():
            first = int(np.argmax(hold))
            if hold[first:].all():  # a held tail (the usual): views of the block, not copies
                back, blk, drop = blk.select(slice(first, None)), blk.select(slice(0, first)), drop[:first]
            else:
                back, blk, drop = blk.select(hold), blk.select(~hold), drop[~hold]
        if not held and not drop.any() and back is None:
            yield blk
            blk = following
            continue
        part = blk.select(~drop) if drop.any() else blk
        if len(part):
            held.append(part)
            n_held += len(part)
        while n_held >= block_rows:
            joined = join_blocks(held)
            yield joined.select(slice(0, block_rows))
            rest = joined.select(slice(block_rows, None))
            held, n_held = ([rest] if len(rest) else []), len(rest)
        blk = following
    if held:
        yield join_blocks(held)


def time_axis_label(metadata: dict[str, Any]) -> str:
    """Axis label of ``Recording.t_s`` for reports: ``time [s]`` when the source had a time base (MCAP board
    time, a CSV ``t_s`` column), ``sample index`` for a CSV timed by ``--rate 1`` (time = row / 1 Hz),
    ``sample index / <rate> Hz [s]`` for another rate. Several parts (concatenated runs): the first
    part that has no time base decides, so a label never claims seconds that are not there."""
    parts = metadata.get("parts") if isinstance(metadata.get("parts"), list) else [metadata]
    for md in parts:
        base = (md.get("import") or {}).get("time_base", "t_s column") if isinstance(md, dict) else "t_s column"
        if base != "t_s column":
            rate = base.rsplit("/", 1)[-1].replace("Hz", "").strip()
            return "sample index" if rate in ("1", "1.0") else f"sample index / {rate} Hz [s]"
    return "time [s]"
