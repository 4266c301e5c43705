"""Progress bars of the offline tools on stderr (tqdm), for ``import``, ``fit`` and ``diagnose``.

Shown when stderr is a terminal (``--progress`` forces them on, e.g. under ``script`` or a CI log that
wants them; ``--no-progress`` off). The pure core never imports this: the CLI wraps the sample sources
(:class:`CountedSource`) or passes a callback (``diagnose(progress=...)``), so the fit and diagnosis
functions stay free of terminal concerns.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from tqdm import tqdm


def add_progress_option(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--progress", dest="progress", action="store_true", default=None,
                   help="show progress bars on stderr (default: when stderr is a terminal)")
    g.add_argument("--no-progress", dest="progress", action="store_false", help="never show progress bars")


def enabled(args: argparse.Namespace) -> bool:
    flag = getattr(args, "progress", None)
    return sys.stderr.isatty() if flag is None else bool(flag)


class NoBar:
    """What a command sees of a bar that is off: it counts nothing, draws nothing and starts no thread (a disabled
    tqdm still starts its monitor thread)."""

    def update(self, n: int = 1) -> None:
        pass

    def __enter__(self) -> NoBar:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


def bar(on: bool, desc: str, total: int | None = None, unit: str = "samples") -> tqdm | NoBar:
    """A tqdm bar on stderr; a :class:`NoBar` when ``on`` is false (tqdm is then not imported)."""
    if not on:
        return NoBar()
    from tqdm import tqdm  # here: the parsers import this module for its options, and --help needs no tqdm

    return tqdm(total=total, desc=desc, unit=unit, unit_scale=True, file=sys.stderr, leave=False, dynamic_ncols=True,
                mininterval=0.2)


class CountedSource:
    """A sample source (``McapSampleStream``, ``CsvSampleSource``, ``CsvBlocks``: a ``blocks(...)`` method
    giving Recording blocks, one pass per call) whose every pass advances a progress bar by the samples
    read. The first pass has no total; later passes know it from the first. Everything else is the
    wrapped source's."""

    def __init__(self, source: Any, name: str, on: bool) -> None:
        self.source, self.name, self.on = source, name, on
        self.passes = 0
        self.total: int | None = None

    def blocks(self, *args: Any, **kwargs: Any) -> Iterator[Any]:
        self.passes += 1
        n = 0
        with bar(self.on, f"{self.name}: pass {self.passes}", self.total) as b:
            for blk in self.source.blocks(*args, **kwargs):
                n += len(blk)
                b.update(len(blk))
                yield blk
        self.total = n

    def __getattr__(self, name: str) -> Any:  # metadata(), report, samples ... of the wrapped source
        return getattr(self.source, name)
