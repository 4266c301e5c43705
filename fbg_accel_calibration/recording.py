"""In-memory calibration recording: the arrays every fitting and diagnosis step works on.

Pure numpy. Produced by the MCAP reader (``mcap_io``), the CSV importer and the simulator's
batch API, so the fit and the diagnosis never care where the data came from.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fbg_accel_driver.frame_codec import clipped_reading


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

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def clipped(self) -> np.ndarray:
        """Samples (N,) with a channel at a rail of the 12-bit ADC (paper 3.5: the ESP32's converters;
        ``frame_codec.clipped_reading``): the reading bounds the signal instead of measuring it. Counts below 0 are
        no reading of the ADC at all (the importers refuse them)."""
        return clipped_reading(self.ref, self.xyz[:, 0], self.xyz[:, 1], self.xyz[:, 2])

    def select(self, mask: np.ndarray) -> Recording:
        """A new recording with the samples ``mask`` selects (a boolean mask, indices or a slice; order kept)."""
        return Recording(
            self.t_s[mask], self.ref[mask], self.xyz[mask], self.temp_c[mask],
            self.gref_mps2[mask], self.pose_id[mask], self.run_id[mask], dict(self.metadata),
            None if self.aux is None else self.aux[mask],
        )

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
        return Recording(
            np.concatenate([p.t_s for p in parts]),
            np.concatenate([p.ref for p in parts]),
            np.concatenate([p.xyz for p in parts]),
            np.concatenate([p.temp_c for p in parts]),
            np.concatenate([p.gref_mps2 for p in parts]),
            np.concatenate([p.pose_id for p in parts]),
            np.concatenate(run_ids),
            {"parts": [p.metadata for p in parts]},
            np.concatenate([p.aux for p in parts]) if all(p.aux is not None for p in parts) else None,
        )


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
