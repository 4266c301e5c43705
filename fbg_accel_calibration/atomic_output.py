"""Outputs of the offline tools that never destroy data (issue 11, "Data destroyed").

Rules, checked *before* any computation (:func:`check_outputs`):

* an output may not be one of the inputs (same file by ``os.path.samefile`` or by resolved path),
  nor two outputs the same file;
* an existing output is refused unless ``--force`` is given;
* the output's directory must exist (a missing directory is found before minutes of fitting).

Writing (:func:`atomic_path`): the writer gets a temporary file in the output's directory (same file
system, so the final ``os.replace`` is atomic; same suffix, so writers that choose the format from the
suffix, e.g. matplotlib, still do); on success it is renamed over the output, on any failure --
exception, Ctrl-C (``KeyboardInterrupt``), ``SystemExit`` -- it is removed. An existing output is
therefore either untouched or wholly replaced, and a failed run leaves no stub.

Also :func:`create_exclusive`: open a new file with ``O_CREAT | O_EXCL | O_NOFOLLOW`` so that an
existing file *or a symbolic link* (dangling or not) at the path is refused instead of followed.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path


class OutputError(ValueError):
    """An output would overwrite an input, replace a file without ``--force`` or has no directory."""


def _same(a: Path, b: Path) -> bool:
    with contextlib.suppress(OSError):
        if a.exists() and b.exists() and os.path.samefile(a, b):
            return True
    return os.path.realpath(a) == os.path.realpath(b)


def _creatable_dir(d: Path) -> bool:
    """True if ``d`` is a directory or could be created (its nearest existing ancestor is a directory)."""
    for anc in (d, *d.parents):
        if anc.exists():
            return anc.is_dir()
    return False


def check_outputs(outputs: Iterable[Path | None], inputs: Iterable[Path | str], force: bool = False,
                  create_dirs: bool = False) -> None:
    """Refuse unsafe outputs (see module docstring); ``None`` outputs are skipped. With ``create_dirs`` a
    missing directory is accepted if it can be created (the caller creates it when writing).
    Raises :class:`OutputError`."""
    ins = [Path(p) for p in inputs]
    outs = [Path(p) for p in outputs if p is not None]
    for i, out in enumerate(outs):
        for src in ins:
            if _same(out, src):
                raise OutputError(f"{out}: output is the input file {src}; write to another file")
        for other in outs[:i]:
            if _same(out, other):
                raise OutputError(f"{out}: given twice as an output")
        parent = out.parent
        if create_dirs and not parent.exists():
            if not _creatable_dir(parent):
                raise OutputError(f"{out}: output directory {parent} cannot be created (a file is in its path)")
            continue
        if not parent.is_dir():
            raise OutputError(f"{out}: output directory {parent} does not exist; create it first")
        if out.is_symlink() or out.exists():
            if out.is_dir():
                raise OutputError(f"{out}: is a directory; give a file name")
            if not force:
                raise OutputError(f"{out}: exists; give --force to replace it, or another name")


def check_output_dir(out_dir: Path, files: Iterable[str], inputs: Iterable[Path | str], force: bool = False) -> None:
    """Like :func:`check_outputs` for ``files`` inside ``out_dir``, which is created when writing (with its
    parents) if missing."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"{out_dir}: exists and is not a directory")
    if not out_dir.exists():
        if not _creatable_dir(out_dir):
            raise OutputError(f"{out_dir}: cannot be created (a file is in its path)")
        ins = [Path(p) for p in inputs]
        for f in files:
            for src in ins:
                if _same(out_dir / f, src):
                    raise OutputError(f"{out_dir / f}: output is the input file {src}")
        return
    check_outputs([out_dir / f for f in files], inputs, force)


@contextlib.contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it to ``path`` when the block succeeds, remove it
    on any failure (including ``KeyboardInterrupt``)."""
    path = Path(path)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".part{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    os.chmod(tmp, 0o644)  # mkstemp makes it 0600; the output gets the usual permissions
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def create_exclusive(path: Path | str, mode: int = 0o644) -> int:
    """File descriptor of a new file at ``path`` opened for writing with ``O_CREAT | O_EXCL | O_NOFOLLOW``:
    ``FileExistsError`` if anything -- a file, a directory or a symbolic link, even a dangling one --
    is at ``path``, so a recording is never overwritten and never written through a link."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    return os.open(path, flags, mode)
