"""Exposure times given by the user: ``--times 1/100,1/25,0.5`` or ``--times-file F``,
and :func:`parse_number`, the strict decimal parser of every number read from text."""
from __future__ import annotations

import math
import numbers
import re
from pathlib import Path

from hdrmerge_cli.core.errors import HdrMergeError

#: shortest and longest exposure time accepted (seconds): 1 ns to 11.6 days
MIN_SECONDS, MAX_SECONDS = 1e-9, 1e6
#: largest times file read (bytes)
MAX_TIMES_FILE_BYTES = 2**20

_DECIMAL = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)


def _decimal(text: str) -> float | None:
    """A plain decimal number as a float (``inf`` beyond the float range), or None."""
    t = text.strip()
    return float(t) if len(t) <= 100 and _DECIMAL.fullmatch(t) else None


def parse_number(text: str) -> float:
    """A plain decimal number (``12``, ``-0.5``, ``1e-3``; at most 100 characters) as a
    finite float.  ``nan``, ``inf``, ``0x10``, ``1_000`` and values beyond the float range
    (``1e400``) are refused with an :class:`HdrMergeError`, without ever building a huge
    integer or fraction."""
    value = _decimal(text)
    if value is None:
        raise HdrMergeError(f"{text[:40]!r} is not a number")
    if not math.isfinite(value):
        raise HdrMergeError(f"{text[:40]!r} is out of range")
    return value


def parse_seconds(text: str) -> float:
    """``0.5``, ``1/100``, ``2"`` or ``2s`` (seconds) -> a float between
    :data:`MIN_SECONDS` and :data:`MAX_SECONDS`."""
    num, slash, den = text.strip().rstrip('"s').partition("/")
    parts = [_decimal(num), _decimal(den) if slash else 1.0]
    if None in parts or parts[1] == 0:
        raise HdrMergeError(f"{text[:40]!r} is not an exposure time (use seconds, e.g. 0.5 or 1/100)")
    value = parts[0] / parts[1]  # inf / inf = nan: refused below
    if not MIN_SECONDS <= value <= MAX_SECONDS:
        raise HdrMergeError(f"{text[:40]!r}: exposure times must be between {MIN_SECONDS:g} and {MAX_SECONDS:g} s")
    return value


def seconds(value) -> float:
    """An exposure time given as a number of seconds (the Python API) or as text
    (:func:`parse_seconds`), checked alike."""
    if isinstance(value, str):
        return parse_seconds(value)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise HdrMergeError(f"{value!r} is not an exposure time (use seconds, e.g. 0.5 or '1/100')")
    if not MIN_SECONDS <= float(value) <= MAX_SECONDS:  # NaN fails too
        raise HdrMergeError(f"{value!r}: exposure times must be between {MIN_SECONDS:g} and {MAX_SECONDS:g} s")
    return float(value)


def parse_times(text: str) -> list[float]:
    """Comma-separated exposure times (:func:`parse_seconds`); at least one."""
    times = [parse_seconds(part) for part in text.split(",") if part.strip()]
    if not times:
        raise HdrMergeError("no exposure times given")
    return times


def read_times_file(path: str) -> dict[str, float]:
    """Lines ``name seconds`` (``#`` starts a comment) -> {file name: seconds}; each name
    once."""
    from hdrmerge_cli.io.profile import read_text

    times, lines_of = {}, {}
    for n, line in enumerate(read_text(path, MAX_TIMES_FILE_BYTES).splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        name = Path(parts[0]).name if len(parts) == 2 else ""
        if not name:
            raise HdrMergeError(f"{path}:{n}: expected 'name seconds', got {line[:80]!r}")
        if name in times:
            raise HdrMergeError(f"{path}:{n}: {name} is listed twice (also on line {lines_of[name]})")
        try:
            times[name] = parse_seconds(parts[1])
        except HdrMergeError as exc:
            raise HdrMergeError(f"{path}:{n}: {exc}") from None
        lines_of[name] = n
    return times


#: ``--times estimate``: exposures measured on the frames (labels give the absolute scale)
ESTIMATE = "estimate"


def apply_times(frames, times, times_file: str | None = None) -> None:
    """Set each frame's ``exposure_time`` from ``--times`` (a list in the order of the
    frames; the word ``estimate`` leaves the labels as they are) or ``--times-file``
    (lines ``name seconds``), in place; a frame still without a time is an error."""
    if times is not None and times != ESTIMATE:
        if len(times) != len(frames):
            raise HdrMergeError(f"--times gives {len(times)} values for {len(frames)} frames")
        for f, t in zip(frames, times):
            f.exposure_time, f.time_source = t, "--times"
    if times_file is not None:
        table = read_times_file(times_file)
        for f in frames:
            if f.name not in table:
                raise HdrMergeError(f"{f.path}: not listed in the times file {times_file}")
            f.exposure_time, f.time_source = table[f.name], f"the times file {times_file}"
    for f in frames:
        if f.exposure_time is None:
            hint = ("--times estimate needs one labelled frame for the scale: give the times with --times-file"
                    if times == ESTIMATE else "give them with --times or --times-file")
            raise HdrMergeError(f"{f.path}: no exposure time in the file's metadata ({hint})")
