"""The ADC's code-to-value table of a calibration (optional ``adc_codes`` section; docs/calibration_file.md).

Pure numpy, no ROS. The ESP32's successive-approximation ADC (paper 3.5) has codes of unequal width (differential
non-linearity; Espressif's ESP32 datasheet, "ADC characteristics": DNL up to +-7 LSB, INL up to +-12 LSB at 12 bits):
a code stands for the range of inputs it reads, not for its own number. The table gives, per channel (ref, x, y, z),
the lower edge of every code's input interval (``ADC_CODES + 1`` edges: the last is the top code's upper edge, in
counts of input, nominal c - 0.5); a reading is replaced by the centre of its code's interval before eq. 24. Tables
are measured from recordings (``fbg-accel-calib adc-codes``; ``fbg_accel_calibration.fit.adc_codes``).

The one implementation of the mapping: :meth:`AdcCodeTable.values` (the driver, one frame at a time, plain floats)
and :meth:`AdcCodeTable.map_counts` (arrays: the fit, the diagnosis, ``ThermalCalibration.apply_counts``) read the
same centres; an integer code gives the same value through both.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ADC_CODES = 4096  # codes of the 12-bit converter (paper 3.5)
CHANNELS = ("ref", "x", "y", "z")
# counts: how far an edge may sit from its nominal place. The datasheet's INL bound is 12 LSB; a wide code that takes
# over its missing neighbours moves its own edges by its width (the measured series: about 9 codes at y = 1535)
MAX_EDGE_OFFSET = 32.0
TABLE_KEYS = ("edges", "provenance")
MAX_PROVENANCE_ITEMS = 32
EDGE_DECIMALS = 4  # counts: 1e-4 of a code, far below any width's uncertainty
MAX_PROVENANCE_CHARS = 1024


def pattern_offsets(w: np.ndarray) -> tuple[np.ndarray, float]:
    """The lower edges within one period (P,) of a width pattern ``w`` (P,) summing to P (the cumulative width), and
    the shift that puts the codes' centres on the codes on average over a period (``pattern_edges``)."""
    low = np.concatenate([[0.0], np.cumsum(w)[:-1]])
    return low, float(np.mean(low + w / 2.0)) - len(w) / 2.0


def pattern_edges(w: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """Lower edge (counts of input) of each code of ``codes`` under a width pattern ``w`` (P,) periodic in the code
    and summing to P: code c = P q + r reads inputs from ``P q + low[r] - shift - 0.5`` to that plus ``w[r]``, where
    ``low`` is the cumulative width within a period and ``shift`` puts the codes' centres on the codes on average over a
    period (no offset of the table as a whole). Equal widths give the nominal c - 0.5."""
    w = np.asarray(w, float)
    low, shift = pattern_offsets(w)
    q, r = np.divmod(np.asarray(codes, np.int64), len(w))
    return len(w) * q + low[r] - shift - 0.5


def pattern_codes(x: np.ndarray, w: np.ndarray, adc_max: int = ADC_CODES - 1) -> np.ndarray:
    """The codes (float array of integers, 0..adc_max) an ADC with the periodic width pattern ``w`` (``pattern_edges``)
    reads for inputs ``x`` (counts): the code whose interval holds the input."""
    w = np.asarray(w, float)
    P = len(w)
    e0 = pattern_edges(w, np.arange(P))  # edges of codes 0..P-1; period P in the input too
    t = np.asarray(x, float) - e0[0]
    q = np.floor(t / P)
    r = np.searchsorted(e0 - e0[0], t - P * q, side="right") - 1
    return np.clip(P * q + r, 0, adc_max)


@dataclass
class AdcCodeTable:
    """Per channel (``CHANNELS``), the lower edge of every code's input interval: ``edges`` (4, ADC_CODES + 1),
    non-decreasing, in counts of input; ``provenance``: where the table came from (recording, command, method, date)."""

    edges: np.ndarray
    provenance: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.edges = np.round(np.asarray(self.edges, float), EDGE_DECIMALS)  # as the file holds them
        problem = table_problem(self.edges)
        if problem:
            raise ValueError(problem)
        self.centres = 0.5 * (self.edges[:, :-1] + self.edges[:, 1:])  # (4, ADC_CODES)
        self._lists = [c.tolist() for c in self.centres]  # the per-frame path reads plain floats

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return bool(np.array_equal(self.edges, other.edges)) and self.provenance == other.provenance

    __hash__ = None  # type: ignore[assignment]

    def values(self, ref: int, x: int, y: int, z: int) -> tuple[float, float, float, float]:
        """The centres of the codes of one frame, counts; a count outside the codes 0..ADC_CODES - 1 (no reading of
        this ADC: the frame's fields are wider) as read."""
        c, top = self._lists, ADC_CODES
        return (c[0][ref] if 0 <= ref < top else ref, c[1][x] if 0 <= x < top else x,
                c[2][y] if 0 <= y < top else y, c[3][z] if 0 <= z < top else z)

    def map_counts(self, ref: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ref (N,), xyz (N, 3)) ADC codes to the centres of their intervals (counts); a non-integer count (averaged
        data) is interpolated between the centres of the codes either side; NaN, and a count outside the codes, stay
        as they are (as :meth:`values`)."""
        ref = np.asarray(ref, float)
        xyz = np.atleast_2d(np.asarray(xyz, float))
        grid = np.arange(ADC_CODES, dtype=float)

        def mapped(v: np.ndarray, j: int) -> np.ndarray:
            return np.where((v >= 0) & (v <= ADC_CODES - 1), np.interp(v, grid, self.centres[j]), v)

        return mapped(ref, 0), np.column_stack([mapped(xyz[:, j], j + 1) for j in range(3)])

    def to_dict(self) -> dict[str, Any]:
        return {"edges": {name: [float(v) for v in e] for name, e in zip(CHANNELS, self.edges, strict=True)},
                "provenance": dict(self.provenance)}

    @classmethod
    def from_dict(cls, d: Any, fail: Callable[[str], Exception]) -> AdcCodeTable:
        """The section as read from a file; ``fail(message)`` makes the one-line error raised."""
        if not isinstance(d, dict):
            raise fail(f"'adc_codes' must be a mapping with {' and '.join(TABLE_KEYS)}, got {type(d).__name__}")
        unknown = sorted(set(d) - set(TABLE_KEYS))
        if unknown:
            raise fail(f"unknown key 'adc_codes.{unknown[0]}' (the section holds {', '.join(TABLE_KEYS)})")
        edges = d.get("edges")
        if not isinstance(edges, dict) or set(edges) != set(CHANNELS):
            raise fail(f"'adc_codes.edges' must map each of {', '.join(CHANNELS)} to its {ADC_CODES + 1} code edges")
        rows = []
        for name in CHANNELS:
            e = edges[name]
            if not isinstance(e, list) or len(e) != ADC_CODES + 1:
                n = len(e) if isinstance(e, list) else type(e).__name__
                raise fail(f"'adc_codes.edges.{name}' has {n} entries, expected {ADC_CODES + 1} (the lower edge of each "
                           f"of the {ADC_CODES} codes and the top code's upper edge)")
            if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in e):
                raise fail(f"'adc_codes.edges.{name}' holds a value that is not a number")
            rows.append(e)
        prov = d.get("provenance", {})
        if not isinstance(prov, dict) or len(prov) > MAX_PROVENANCE_ITEMS or not all(
                isinstance(k, str) and isinstance(v, str | int | float) and len(str(v)) <= MAX_PROVENANCE_CHARS
                for k, v in prov.items()):
            raise fail(f"'adc_codes.provenance' must be a mapping of at most {MAX_PROVENANCE_ITEMS} names to short "
                       "texts or numbers")
        arr = np.array(rows, float)
        problem = table_problem(arr)
        if problem:
            raise fail(problem)
        return cls(arr, dict(prov))


def table_problem(edges: np.ndarray) -> str:
    """What makes ``edges`` no code table (one line), or ''."""
    if edges.shape != (len(CHANNELS), ADC_CODES + 1):
        return f"'adc_codes.edges' has shape {edges.shape}, expected {(len(CHANNELS), ADC_CODES + 1)}"
    if not np.all(np.isfinite(edges)):
        return "'adc_codes.edges' holds a value that is not finite"
    for name, e in zip(CHANNELS, edges, strict=True):
        down = np.flatnonzero(np.diff(e) < 0)
        if len(down):
            c = int(down[0])
            return (f"'adc_codes.edges.{name}': the intervals are not monotone: code {c} reads from {e[c]:.4g} to "
                    f"{e[c + 1]:.4g} counts (an edge below the one before it)")
        off = np.abs(e - (np.arange(ADC_CODES + 1) - 0.5))
        if off.max() > MAX_EDGE_OFFSET:
            c = int(np.argmax(off))
            return (f"'adc_codes.edges.{name}': the edge of code {c} sits {off[c]:.4g} counts from its nominal place, "
                    f"beyond the {MAX_EDGE_OFFSET:g} an ESP32 code table can hold")
    return ""


def save_table(table: AdcCodeTable, path: str | Path) -> None:
    """A table of its own (``fbg-accel-calib adc-codes -o``): the calibration file's ``adc_codes`` section alone."""
    text = "# ESP32 ADC code table (fbg-accel-calib adc-codes); see docs/calibration_file.md\n"
    text += yaml.safe_dump({"adc_codes": table.to_dict()}, sort_keys=False, default_flow_style=None, width=100)
    Path(path).write_text(text, encoding="utf-8")


def load_table(path: str | Path) -> AdcCodeTable:
    """A table file (``save_table``) or a calibration file's ``adc_codes`` section; ValueError (one line) when it is
    neither or the table is refused."""
    from .yaml_input import load_yaml

    p = Path(path)

    def fail(msg: str) -> ValueError:
        return ValueError(f"{p}: {msg}")

    try:
        d = load_yaml(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise fail(f"cannot be read as a code table ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    if not isinstance(d, dict) or d.get("adc_codes") is None:
        raise fail("no 'adc_codes' section (write one with fbg-accel-calib adc-codes RECORDING -o TABLE.yaml)")
    return AdcCodeTable.from_dict(d["adc_codes"], fail)
