"""Write-then-rename outputs: an interrupted run never leaves a half-written file."""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from hdrmerge_cli.core.errors import HdrMergeError


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


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, overwrite: bool):
    """Yield a temporary path beside ``path`` (same extension, so writers pick the same
    format); rename it onto ``path`` when the block succeeds, delete it otherwise."""
    path = check_writable(path, overwrite)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".part{path.suffix}", dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        # mkstemp creates 0600; give the file the mode a plain open() would (or keep the
        # mode of the file it replaces)
        os.chmod(tmp, path.stat().st_mode & 0o7777 if path.exists() else 0o666 & ~UMASK)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_paths(paths: list, overwrite: bool):
    """Several outputs that appear together or not at all: yields temporary paths, renames
    them all on success (each check done before anything is written)."""
    for p in paths:
        check_writable(p, overwrite)
    with contextlib.ExitStack() as stack:
        tmps = [stack.enter_context(atomic_path(p, True)) for p in paths]
        yield tmps


def atomic_text(path: str | os.PathLike, text: str, overwrite: bool) -> None:
    with atomic_path(path, overwrite) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
