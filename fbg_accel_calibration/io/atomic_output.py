"""Outputs of the offline tools and nodes that never destroy data.

Rules, checked *before* any computation (:func:`check_outputs`):

* an output may not be one of the inputs (same file by ``os.path.samefile`` or by resolved path),
  nor two outputs the same file;
* an existing output is refused unless ``--force`` (a node: its ``force`` parameter) is given;
* the output's directory must take a new file: a missing one is made (with its parents) when the outputs are
  written, if it can be (its nearest existing ancestor is a directory that takes a new one), and refused before
  minutes of fitting if not; a read-only directory is found then too, and named, not the temporary file that would
  have failed. Every output of every command follows this one rule;
* a character device (``/dev/null``) or a FIFO is written through, never replaced.

Writing (:class:`OutputSet`, :func:`committed_outputs`; :func:`atomic_path` for one file): each writer gets a
temporary file in its output's directory (same file system, so the final ``os.replace`` is atomic; same suffix,
so writers that choose the format from the suffix, e.g. matplotlib, still do). When every output of the run is
written they are renamed over their outputs together; on any failure -- exception, Ctrl-C
(``KeyboardInterrupt``), SIGTERM (``command_line.Terminated``, a ``KeyboardInterrupt``), ``SystemExit`` -- before
or during those renames, the temporaries are removed and the outputs already renamed are put back as they were.
An existing output is therefore either untouched or replaced together with the run's other outputs, and a failed
run leaves no stub, nor a directory it made.

Also :func:`create_exclusive`: open a new file with ``O_CREAT | O_EXCL | O_NOFOLLOW`` so that an
existing file *or a symbolic link* (dangling or not) at the path is refused instead of followed.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import signal
import stat
from collections.abc import Iterable, Iterator
from pathlib import Path


class OutputError(ValueError):
    """An output would overwrite an input, replace a file without ``--force`` or has no directory."""


def _same(a: Path, b: Path) -> bool:
    with contextlib.suppress(OSError):
        if a.exists() and b.exists() and os.path.samefile(a, b):
            return True
    return os.path.realpath(a) == os.path.realpath(b)


def _existing_ancestor(d: Path) -> Path | None:
    """``d`` or its nearest ancestor that exists, None if none does."""
    return next((anc for anc in (d, *d.parents) if anc.exists()), None)


def _creatable_dir(d: Path) -> bool:
    """True if ``d`` is a directory or could be created (its nearest existing ancestor is a directory)."""
    anc = _existing_ancestor(d)
    return anc is not None and anc.is_dir()


def check_outputs(outputs: Iterable[Path | None], inputs: Iterable[Path | str], force: bool = False,
                  create_dirs: bool = True) -> None:
    """Refuse unsafe outputs (see module docstring); ``None`` outputs are skipped. A missing directory is accepted
    if it can be created (:meth:`OutputSet.path` creates it when writing); without ``create_dirs`` it is refused (the
    calibration node: a calibration file outside its own output directory).
    Raises :class:`OutputError`."""
    ins = [Path(p) for p in inputs]
    outs = [Path(p) for p in outputs if p is not None]
    writable: set[Path] = set()  # directories already probed
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
            anc = _existing_ancestor(parent)
            if anc not in writable:
                _check_writable(out, anc)  # type: ignore[arg-type]
                writable.add(anc)  # type: ignore[arg-type]
            continue
        if not parent.is_dir():
            raise OutputError(f"{out}: output directory {parent} does not exist; create it first")
        if is_stream(out):
            continue  # /dev/null, a FIFO: written through, nothing is replaced
        if out.is_symlink() or out.exists():
            if out.is_dir():
                raise OutputError(f"{out}: is a directory; give a file name")
            if not (out.is_file() or out.is_symlink()):
                raise OutputError(f"{out}: is not a regular file; give a file name")
            if not force:
                raise OutputError(f"{out}: exists; give --force to replace it, or another name")
        if parent not in writable:
            _check_writable(out)
            writable.add(parent)


def is_stream(path: Path | str) -> bool:
    """True for a character device (``/dev/null``) or a FIFO: an output written through, never renamed over."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return stat.S_ISCHR(mode) or stat.S_ISFIFO(mode)


# a new file only, never through a link, not inherited by child processes
_EXCLUSIVE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)


def _new_temporary(directory: Path, prefix: str, suffix: str) -> Path:
    """A hidden name in ``directory`` that no file has (128 random bits: a clash is not to be expected; the exclusive
    creation refuses one all the same)."""
    return directory / f"{prefix}{secrets.token_hex(16)}{suffix}"


def _check_writable(out: Path, directory: Path | None = None) -> None:
    """Refuse ``out`` when ``directory`` (default: its own) takes no new file (read-only directory or file system,
    no permission), by trying: ``os.access`` says yes to root on a read-only mount."""
    directory = out.parent if directory is None else directory
    probe = _new_temporary(directory, ".write-check.", "")
    with _signals_held():  # the probe never stays behind, even when the handler runs inside this block
        try:
            os.close(os.open(probe, _EXCLUSIVE, 0o600))
        except OSError as exc:
            raise OutputError(f"{out}: cannot write in {directory} ({exc.strerror or exc})") from None
        finally:
            with contextlib.suppress(OSError):
                os.unlink(probe)


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


class OutputSet:
    """The outputs of one run, each written to a temporary file (:meth:`path`) and renamed over its output by
    :meth:`commit`, all of them or none. Use through :func:`committed_outputs`."""

    def __init__(self) -> None:
        self._staged: dict[Path, Path] = {}  # output -> its temporary file
        self._made: list[Path] = []  # directories this set created, parents first: removed again if it fails
        self._removed: list[Path] = []  # files an output of this run supersedes: removed when it commits

    def remove(self, path: Path | str) -> None:
        """Remove ``path`` when the set commits, after its outputs are in place (a file of an earlier run that the new
        outputs supersede); kept when the run fails."""
        self._removed.append(Path(path))

    def directory(self, path: Path | str) -> Path:
        """``path`` as a directory, created with its missing parents (each removed again, if empty, when the set is
        discarded instead of committed)."""
        path = Path(path)
        missing = [d for d in (path, *path.parents) if not d.exists()][::-1]
        with _signals_held():
            _OPEN.add(self)
            for d in missing:
                try:
                    d.mkdir()
                except FileExistsError:
                    continue  # made meanwhile by another process: not ours to remove
                self._made.append(d)
        return path

    def path(self, output: Path | str) -> Path:
        """A new temporary file next to ``output`` (same suffix) that :meth:`commit` renames to ``output``."""
        output = Path(output)
        if output in self._staged:
            return self._staged[output]
        if is_stream(output):
            return output  # /dev/null, a FIFO: written through (a rename would replace the device node)
        self.directory(output.parent)
        # The name is recorded before the file is created, so that an interrupt at any point after the creation
        # finds it to remove: blocking SIGINT/SIGTERM here is not enough, since another thread of the process (a
        # BLAS worker) takes the signal and the handler then runs in this thread at once.
        with _signals_held():
            tmp = self._staged[output] = _new_temporary(output.parent, f".{output.stem}.", f".part{output.suffix}")
            _OPEN.add(self)
            try:
                fd = os.open(tmp, _EXCLUSIVE, 0o600)
            except OSError as exc:  # named by the user's path, not the temporary one
                del self._staged[output]
                raise OutputError(f"{output}: cannot write in {output.parent} ({exc.strerror or exc})") from None
            os.close(fd)
        os.chmod(tmp, 0o644)  # the output gets the usual permissions, whatever the umask
        return tmp

    def commit(self) -> None:
        """Rename every temporary file over its output. If a rename fails or is interrupted, the outputs already
        replaced get their earlier content back (or are removed if they did not exist) and the error is raised."""
        backups: dict[Path, Path | None] = {}
        done: list[Path] = []
        try:
            with _signals_held():  # each backup's name is recorded before its link exists: none is left behind
                for output in self._staged:
                    backups[output] = _new_temporary(output.parent, f".{output.name}.", ".previous")
                    if not _backup(output, backups[output]):  # type: ignore[arg-type]
                        backups[output] = None
            for output, tmp in self._staged.items():
                done.append(output)  # first: an interrupt right after the rename still rolls this output back
                os.replace(tmp, output)
            self._made.clear()  # committed: the directories now hold the outputs
            with _signals_held():
                for path in self._removed:
                    with contextlib.suppress(FileNotFoundError):
                        path.unlink()
        except BaseException:
            with _signals_held():
                for output in done:
                    with contextlib.suppress(OSError):
                        if backups.get(output) is not None:
                            os.replace(backups.pop(output), output)  # type: ignore[arg-type]
                        else:
                            output.unlink()
            raise
        finally:
            with _signals_held():
                for b in backups.values():
                    if b is not None:
                        with contextlib.suppress(OSError):
                            b.unlink()
                self.discard()

    def discard(self) -> None:
        """Remove the temporary files not renamed (all of them before :meth:`commit`) and the directories made for
        them that are empty."""
        for tmp in self._staged.values():
            with contextlib.suppress(OSError):
                tmp.unlink()
        self._staged.clear()
        for d in reversed(self._made):
            with contextlib.suppress(OSError):
                d.rmdir()
        self._made.clear()
        self._removed.clear()
        _OPEN.discard(self)

    def temporary_to_output(self, exc: OSError) -> OSError:
        """``exc`` naming the output instead of its temporary file (a writer's "No space left: '/d/.c.x.part.yaml'")."""
        names = {str(t): str(o) for o, t in self._staged.items()}
        if exc.filename in names:
            return type(exc)(exc.errno, exc.strerror, names[exc.filename])
        return exc


# the output sets with temporary files not yet renamed or removed (a set leaves it at its commit or discard)
_OPEN: set[OutputSet] = set()


def discard_open_outputs() -> None:
    """Remove the temporary files of every output set not yet committed or discarded: what a command's interrupt
    handler calls last. A signal that arrives after a ``committed_outputs`` block's body but before its generator
    resumes (inside ``contextlib``'s ``__exit__``) raises there, so the generator's own clean-up runs only when the
    generator is collected, which may be never before the process exits."""
    with _signals_held():
        for outs in list(_OPEN):
            outs.discard()


def _backup(output: Path, name: Path) -> bool:
    """A hard link ``name`` to ``output``'s current content, so that a commit can put it back; the output stays in
    place meanwhile. False (and no link) if there is no output yet."""
    if not os.path.lexists(output):
        return False
    os.link(output, name, follow_symlinks=False)
    return True


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held (delivered after the block) while a roll-back or clean-up runs."""
    sigs = {signal.SIGINT, signal.SIGTERM}
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    except (ValueError, OSError):  # not available here: run unprotected
        yield
        return
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextlib.contextmanager
def committed_outputs() -> Iterator[OutputSet]:
    """An :class:`OutputSet` committed when the block succeeds and discarded on any failure (also Ctrl-C and
    SIGTERM); an ``OSError`` of a writer names the output, not its temporary file."""
    outs = OutputSet()
    try:
        yield outs
    except OSError as exc:
        renamed = outs.temporary_to_output(exc)
        outs.discard()
        if renamed is exc:
            raise
        raise renamed from None
    except BaseException:
        outs.discard()
        raise
    outs.commit()


@contextlib.contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it to ``path`` when the block succeeds, remove it
    on any failure (including ``KeyboardInterrupt``). One output of :func:`committed_outputs`."""
    with committed_outputs() as outs:
        yield outs.path(path)


def create_exclusive(path: Path | str, mode: int = 0o644) -> int:
    """File descriptor of a new file at ``path`` opened for writing with ``O_CREAT | O_EXCL | O_NOFOLLOW``:
    ``FileExistsError`` if anything -- a file, a directory or a symbolic link, even a dangling one --
    is at ``path``, so a recording is never overwritten and never written through a link."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    return os.open(path, flags, mode)
