"""Exposure times given by the user: ``--times 1/100,1/25,0.5`` or ``--times-file F``."""
from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path

from hdrmerge_cli.core.errors import HdrMergeError


def parse_seconds(text: str) -> float:
    """``0.5``, ``1/100`` or ``2"`` (seconds) -> float > 0."""
    t = text.strip().rstrip('"s')
    try:
        value = float(Fraction(t))
    except (ValueError, ZeroDivisionError):
        raise HdrMergeError(f"{text!r} is not an exposure time (use seconds, e.g. 0.5 or 1/100)") from None
    if not (value > 0 and math.isfinite(value)):
        raise HdrMergeError(f"{text!r}: exposure times must be positive")
    return value


def parse_times(text: str) -> list[float]:
    return [parse_seconds(part) for part in text.split(",") if part.strip()]


def read_times_file(path: str) -> dict[str, float]:
    """Lines ``name seconds`` (``#`` starts a comment) -> {file name: seconds}."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise HdrMergeError(f"{path}: cannot read ({exc})") from None
    times = {}
    for n, line in enumerate(lines, 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 2:
            raise HdrMergeError(f"{path}:{n}: expected 'name seconds', got {line!r}")
        try:
            times[Path(parts[0]).name] = parse_seconds(parts[1])
        except HdrMergeError as exc:
            raise HdrMergeError(f"{path}:{n}: {exc}") from None
    return times
