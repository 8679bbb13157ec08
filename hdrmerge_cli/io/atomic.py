"""Write-then-rename outputs: an interrupted run never leaves a half-written file."""
from __future__ import annotations

import contextlib
import errno
import os
import secrets
from pathlib import Path

from hdrmerge_cli.core.errors import HdrMergeError, check_not_stopped


def check_writable(path: str | os.PathLike, overwrite: bool) -> Path:
    """Refuse an existing output without ``overwrite`` and a missing parent folder."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise HdrMergeError(f"{path}: already exists (use --overwrite to replace it)")
    if path.is_dir():
        raise HdrMergeError(f"{path}: is a folder, not a file name")
    if not path.parent.is_dir():
        raise HdrMergeError(f"{path}: the folder {path.parent} does not exist")
    return path


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: the process umask, read once (reading it means setting it)
UMASK = _umask()


def check_distinct(outputs: list, inputs: list = ()) -> None:
    """Refuse, before any work and whatever ``--overwrite`` says, two outputs that are one
    file and an output that is one of the inputs."""
    seen = {}
    for p in outputs:
        key = os.path.realpath(p)
        if key in seen:
            raise HdrMergeError(f"{p}: given for two outputs ({seen[key]} too); name them apart")
        seen[key] = p
    for src in inputs:
        key = os.path.realpath(src)
        if key in seen or any(os.path.exists(o) and os.path.samefile(o, src) for o in outputs):
            raise HdrMergeError(f"{seen.get(key, src)}: is an input; refusing to write over it")


def _user_error(exc: BaseException, tmps: list[str], paths: list[Path]) -> HdrMergeError:
    """An error raised while writing a temporary, told with the user's path instead."""
    if isinstance(exc, OSError) and not isinstance(exc, FileExistsError):
        where = next((str(p) for t, p in zip(tmps, paths) if exc.filename in (t, str(p))), None)
        if where is None:  # a failed write() names no file
            where = exc.filename or ", ".join(str(p) for p in paths)
        text = f"{where}: cannot write ({exc.strerror or exc})"
    else:
        text = str(exc)
    for t, p in zip(tmps, paths):
        text = text.replace(t, str(p))
    return HdrMergeError(text)


@contextlib.contextmanager
def atomic_paths(paths: list, overwrite: bool, inputs: list = ()):
    """Several outputs committed as one transaction: yields temporary paths beside them
    (same extension, so writers pick the same format); when the block succeeds every
    temporary is moved onto its output, else every temporary is removed.

    The commit never replaces a file that appeared since the start unless ``overwrite``
    (a concurrent run's output is not silently clobbered: the new name is made with a hard
    link, which fails if the name exists); files it replaces are kept aside until every
    output is in place, so a failure part-way restores them and removes the new ones.
    Errors name the user's paths, not the temporaries."""
    paths = [Path(p) for p in paths]
    check_distinct(paths, inputs)
    for p in paths:
        check_writable(p, overwrite)
    tmps: list[str] = []
    try:
        try:
            for p in paths:
                create_temporary(p, tmps)
        except OSError as exc:
            raise _user_error(exc, tmps, paths) from None
        try:
            yield tmps
        except (OSError, HdrMergeError) as exc:
            raise _user_error(exc, tmps, paths) from None
        _commit(tmps, paths, overwrite)
    finally:
        _remove(tmps)


def _remove(tmps: list[str]) -> None:
    """Remove the temporaries, every one of them even when a stop signal (SIGTERM, Ctrl-C)
    unwinds in between: it is raised again once all are gone, so a signal between two
    removals leaves none behind."""
    pending = None
    for tmp in tmps:
        for _ in range(3):  # a signal may land before or after the removal itself
            try:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
                break
            except BaseException as exc:  # raised by a signal handler: finish first
                pending = pending or exc
    if pending is not None:
        raise pending


def create_temporary(path: Path, tmps: list[str]) -> None:
    """A new empty file (mode 0600) beside ``path``, named ``.<stem>.<random>.part<suffix>``
    (the same extension, so writers pick the same format), appended to ``tmps``.  The name
    is listed before the file is created (``O_EXCL``; a name taken is drawn again), so a
    signal that unwinds at any point leaves no file that the caller's clean-up does not
    know of (``mkstemp`` creates the file before its name can be listed)."""
    while True:
        tmp = str(path.parent / f".{path.stem}.{secrets.token_hex(4)}.part{path.suffix}")
        tmps.append(tmp)
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
            return
        except FileExistsError:
            tmps.pop()  # someone else's: not ours to remove


def _commit(tmps: list[str], paths: list[Path], overwrite: bool) -> None:
    check_not_stopped()  # a Ctrl-C whose exception a library swallowed still stops the run
    done: list[tuple[Path, str | None]] = []  # (output, the backup of the file it replaced)
    try:
        for tmp, path in zip(tmps, paths):
            # mkstemp creates 0600: give the file the mode a plain open() would (or keep
            # the mode of the file it replaces)
            os.chmod(tmp, path.stat().st_mode & 0o7777 if path.exists() else 0o666 & ~UMASK)
            backup = None
            if path.exists():
                if not overwrite:
                    raise FileExistsError(errno.EEXIST, "appeared while this run was working", str(path))
                backup = f"{tmp}.old"
                os.replace(path, backup)
            try:
                os.link(tmp, path)  # fails if the name was taken meanwhile
            except FileExistsError:
                if backup:
                    os.replace(backup, path)
                raise FileExistsError(errno.EEXIST, "appeared while this run was working", str(path)) from None
            except OSError:  # no hard links on this file system: rename (a tiny race remains)
                os.replace(tmp, path)
            done.append((path, backup))
    except BaseException as exc:
        for path, backup in reversed(done):
            with contextlib.suppress(OSError):
                if backup:
                    os.replace(backup, path)
                else:
                    os.unlink(path)
        if isinstance(exc, FileExistsError):
            raise HdrMergeError(f"{exc.filename}: {exc.strerror} (use --overwrite to replace it)") from None
        if isinstance(exc, OSError):
            raise HdrMergeError(f"{exc.filename or paths[len(done)]}: cannot write ({exc.strerror or exc})") from None
        raise
    for _, backup in done:
        if backup:
            with contextlib.suppress(OSError):
                os.unlink(backup)


def write_text(tmp: str, text: str) -> None:
    """Write ``text`` (UTF-8) to a temporary of :func:`atomic_paths`; an OSError names it
    (one raised by write(), such as a full disk, names no file by itself)."""
    try:
        Path(tmp).write_text(text, encoding="utf-8")
    except OSError as exc:
        exc.filename = exc.filename or tmp
        raise


def write_together(writers: list, overwrite: bool) -> None:
    """Outputs committed as one transaction (:func:`atomic_paths`): ``writers`` is a list of
    ``(path, write)``, ``write(tmp)`` writing that output to its temporary; if one fails,
    none is written (a plot is not left behind when its profile cannot be written)."""
    with atomic_paths([p for p, _ in writers], overwrite) as tmps:
        for (_, write), tmp in zip(writers, tmps):
            write(tmp)


@contextlib.contextmanager
def output_folder(folder: str | os.PathLike):
    """Create ``folder`` and its missing parents for the block; when the block ends (done,
    failed or interrupted), remove again, deepest first, those it created that are still
    empty: an output committed into one keeps it and its parents.  A folder that cannot
    be created is an error naming it."""
    missing, f = [], Path(folder)
    while not f.exists() and f.parent != f:
        missing.append(f)
        f = f.parent
    try:
        for f in reversed(missing):
            f.mkdir(exist_ok=True)
    except OSError as exc:
        _remove_empty(missing)
        raise HdrMergeError(f"{folder}: cannot create the folder ({exc.strerror or exc})") from None
    try:
        yield Path(folder)
    finally:
        _remove_empty(missing)


def _remove_empty(folders: list[Path]) -> None:
    """Remove the folders (deepest first) as long as they are empty."""
    for f in folders:
        try:
            f.rmdir()
        except FileNotFoundError:
            continue
        except OSError:
            return
