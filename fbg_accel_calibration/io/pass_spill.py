"""Arrays that one pass over a recording computed, kept for the later passes of the same run in unlinked temporary
files (the page cache holds them while there is room), so that the memory of a streamed fit stays independent of the
number of samples and a later pass need not compute them again.

Pure Python + numpy. Used by ``mcap_reader.McapSampleStream`` (the decoded ``imu/raw`` samples: each file is read once)
and ``fit_stream.prepare_stream`` (each block's selection: the static detector runs once per block after the noise
floor)."""

from __future__ import annotations

import tempfile
import weakref
from collections.abc import Iterator
from typing import Any

import numpy as np


class PassSpill:
    """Columns of equal length added piece by piece (:meth:`add`), read back in the same order (:meth:`pieces`): the
    same values, bit for bit. ``dtypes``: one per column; a column's trailing shape is that of its first piece."""

    def __init__(self, dtypes: tuple[Any, ...], keep_lengths: bool = False) -> None:
        self._dtypes = tuple(np.dtype(d) for d in dtypes)
        self._files = [tempfile.TemporaryFile(prefix="fbg_accel_pass_") for _ in self._dtypes]
        self._closer = weakref.finalize(self, _close_all, *self._files)  # with its owner: no file left open
        self._shapes: list[tuple[int, ...]] | None = None
        self._lengths: list[int] | None = [] if keep_lengths else None
        self.rows = 0

    def add(self, *columns: np.ndarray) -> None:
        """Append one piece: ``columns`` of equal length, each of its column's dtype and trailing shape."""
        shapes = [tuple(np.shape(c)[1:]) for c in columns]
        if self._shapes is None:
            self._shapes = shapes
        elif shapes != self._shapes:
            raise ValueError(f"a piece of shape {shapes} after pieces of shape {self._shapes}")
        for fh, col, dtype in zip(self._files, columns, self._dtypes, strict=True):
            fh.write(np.ascontiguousarray(col, dtype=dtype).data)
        n = len(columns[0])
        self.rows += n
        if self._lengths is not None:
            self._lengths.append(n)

    def pieces(self, rows: int | None = None) -> Iterator[tuple[np.ndarray, ...]]:
        """The columns again, piece by piece: as added (``rows`` None; needs ``keep_lengths``), else in pieces of at
        most ``rows`` rows."""
        if rows is None and self._lengths is None:
            raise ValueError("the lengths of the pieces were not kept")
        for fh in self._files:
            fh.seek(0)
        lengths = self._lengths if rows is None else [min(rows, self.rows - s) for s in range(0, self.rows, rows)]
        for n in lengths:
            out = tuple(np.empty((n, *shape), dtype) for shape, dtype in zip(self._shapes or (), self._dtypes,
                                                                                 strict=True))
            for fh, arr in zip(self._files, out, strict=True):
                if fh.readinto(arr) != arr.nbytes:
                    raise OSError("the temporary copy of a pass read back short")
            yield out

    def close(self) -> None:
        self._closer()


def _close_all(*files: Any) -> None:
    for f in files:
        f.close()
