"""Per-camera cache of the noise parameters and the image response that ``merge`` measures
on a bracket.

A bracket merged without ``--noise``/``--profile`` has the noise model (17) measured on
itself (the calibrate-noise fast path, on a few 10^5 sites drawn as the frames are decoded).  The parameters belong to
the camera at an ISO, not to the scene, so the first merge of a camera and ISO stores them
here and later merges of that camera and ISO read them back instead of measuring again.

Location: ``$HDRMERGE_CLI_CACHE_DIR/noise.json`` if that variable is set, else
``$XDG_CACHE_HOME/hdrmerge-cli/noise.json`` (``~/.cache/hdrmerge-cli/noise.json`` when
``XDG_CACHE_HOME`` is unset).  ``merge --no-cache`` neither reads nor writes it; deleting the
file forgets every entry.  A damaged or foreign file is ignored (and replaced on the next
store), never an error.

Key: make, model, ISO, the kind of data and its code scale (RAW: black and white levels, so
a camera's 12- and 14-bit modes stay apart; images: bit depth and the response curve the
signal was linearised with).  Frames without make, model or ISO are not cached, nor are
simulated ones (``hdrmerge-cli simulate``: its sensor is whatever the options made it).

The response of JPEG/TIFF/PNG frames (``response.json`` beside it) is the camera's and its
picture style's, not the scene's: keyed by make, model, bit depth and the processing the
file states (:attr:`~hdrmerge_cli.io.frames.Frame.style`), so another style or bit depth is
never mistaken for it.  ``merge`` stores every response it measures and reads one back only
where a bracket cannot pin its own (a single frame, frames too far apart).
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
from pathlib import Path

from hdrmerge_cli.io.atomic import create_temporary

SCHEMA = 1
ENV_DIR = "HDRMERGE_CLI_CACHE_DIR"
#: ``Make`` of the frames ``simulate`` writes (never cached)
SIMULATED_MAKE = "hdrmerge-cli"


def cache_dir() -> Path:
    """The folder of the cache (see the module docstring)."""
    if os.environ.get(ENV_DIR):
        return Path(os.environ[ENV_DIR])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "hdrmerge-cli"


def cache_file() -> Path:
    return cache_dir() / "noise.json"


def response_file() -> Path:
    return cache_dir() / "response.json"


def _num(x) -> str:
    return f"{float(x):g}"


def cache_key(frame, crf_description: str | None = None) -> str | None:
    """The cache key of a bracket's first frame, or ``None`` when it cannot be cached."""
    make, model = (frame.make or "").strip(), (frame.model or "").strip()
    if not make or not model or not frame.iso or make == SIMULATED_MAKE:
        return None
    parts = [make, model, f"iso={_num(frame.iso)}", frame.kind]
    if frame.kind == "raw":
        parts += ["black=" + ",".join(_num(b) for b in frame.black), "white=" + ",".join(_num(w) for w in frame.white)]
    else:
        parts += [f"bits={frame.bits}", f"crf={crf_description}"]
    return " | ".join(parts)


def _load(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    if not isinstance(data, dict) or data.get("schema") != SCHEMA or not isinstance(data.get("entries"), dict):
        return {}
    return data["entries"]


def lookup(key: str | None) -> dict | None:
    """The stored entry (``{"used": {channel: {sigma_o2, alpha, beta}}, "estimated_from_bracket":
    ..., "inputs": [...], "date": ...}``) or ``None``."""
    if key is None:
        return None
    entry = _load(cache_file()).get(key)
    try:
        used = {str(ch): {k: float(p[k]) for k in ("sigma_o2", "alpha", "beta")} for ch, p in entry["used"].items()}
    except (TypeError, KeyError, ValueError, AttributeError):
        return None
    return entry | {"used": used}


def response_key(frame) -> str | None:
    """The response cache key of an image bracket's first frame, or ``None``."""
    make, model = (frame.make or "").strip(), (frame.model or "").strip()
    if frame.kind != "image" or not make or not model or make == SIMULATED_MAKE:
        return None
    return " | ".join([make, model, f"bits={frame.bits}", f"style={frame.style}"])


def lookup_response(key: str | None) -> dict | None:
    """The stored response entry (``{"inverse": (C, N) list, "inputs": [...], "date": ...}``)
    or ``None``."""
    if key is None:
        return None
    entry = _load(response_file()).get(key)
    if not isinstance(entry, dict) or not isinstance(entry.get("inverse"), list):
        return None
    return entry


def store_response(key: str | None, table, inputs: list[str]) -> Path | None:
    """Add (or replace) a response entry, as :func:`store` does a noise entry."""
    return _store(response_file(), key, {"inverse": [[float(x) for x in row] for row in table]}, inputs)


def store(key: str | None, used: dict, estimated: dict | None, inputs: list[str]) -> Path | None:
    """Add (or replace) one noise entry (see :func:`_store`)."""
    return _store(cache_file(), key, {"used": used, "estimated_from_bracket": estimated}, inputs)


def _store(path: Path, key: str | None, entry: dict, inputs: list[str]) -> Path | None:
    """Add (or replace) one entry of ``path``; written to a temporary file and renamed, so
    concurrent merges (``--batch -j``) never leave a torn file (the last writer wins).
    Returns the file, or ``None`` if it could not be written (a read-only home: no cache,
    no error)."""
    if key is None:
        return None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        entries = _load(path)
        entries[key] = entry | {"inputs": [str(p) for p in inputs],
                                "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}
        tmps: list[str] = []
        try:
            create_temporary(path, tmps)  # listed before it exists: a signal leaves no stray file
            with open(tmps[0], "w", encoding="utf-8") as fh:
                json.dump({"schema": SCHEMA, "entries": entries}, fh, indent=1, sort_keys=True)
            os.replace(tmps[0], path)
        except BaseException:
            for tmp in tmps:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
            raise
    except OSError:
        return None
    return path
