"""Camera profile JSON: versioned, validated on load (jsonschema), unknown keys kept.

Layout (schema 1)::

    {"schema": 1, "kind": "hdrmerge-cli camera profile",
     "camera": {"make": "...", "model": "..."}, "bit_depth": 8,
     "crf": {"model": "linear" | "srgb" | "gamma" | "table", "gamma": 2.2,
             "channels": "RGB", "inverse": [[gamma^-1(z) for z in 0..2^B-1], ...]},
     "noise": {...}, "weights": "...", "provenance": {...}}

``crf.inverse`` holds the linear value ``gamma^-1(z)`` in [0, 1] per channel (the paper's
``g(z)`` is its logarithm); it is present only for ``model: table``.

Loading is defensive (the file may come from anywhere): at most :data:`MAX_PROFILE_BYTES`,
UTF-8, no ``NaN``/``Infinity`` or numbers overflowing a float, no duplicate keys, nesting
at most :data:`MAX_DEPTH` deep, and the CRF entry is checked as :func:`crf_from_json`
would read it.  Every problem is an :class:`HdrMergeError` naming the file.
"""
from __future__ import annotations

import datetime as _dt
import json
import math
import os

import numpy as np

from hdrmerge_cli._version import __version__
from hdrmerge_cli.core.crf import CRF, gamma_crf, table_crf
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.atomic import write_text

SCHEMA_VERSION = 1
KIND = "hdrmerge-cli camera profile"

#: largest profile file read (bytes); a 16-bit table CRF of 3 channels takes ~6 MB
MAX_PROFILE_BYTES = 64 * 2**20
#: deepest nesting of arrays/objects accepted in a profile (the layout needs 4)
MAX_DEPTH = 64
#: most channels and entries per channel of a table CRF (16-bit codes)
MAX_CRF_CHANNELS, MAX_CRF_ENTRIES = 4, 65536

JSON_SCHEMA = {
    "type": "object",
    "required": ["schema", "kind", "crf"],
    "properties": {
        "schema": {"type": "integer", "minimum": 1},
        "kind": {"const": KIND},
        "camera": {"type": "object", "properties": {"make": {"type": "string"}, "model": {"type": "string"}}},
        "bit_depth": {"type": "integer", "minimum": 1, "maximum": 32},
        "crf": {
            "type": "object",
            "required": ["model"],
            "properties": {
                "model": {"enum": ["linear", "srgb", "gamma", "table"]},
                "gamma": {"type": "number", "exclusiveMinimum": 0},
                "channels": {"type": "string"},
                "inverse": {
                    "type": "array", "minItems": 1,
                    "items": {"type": "array", "minItems": 2, "items": {"type": "number"}},
                },
            },
            "allOf": [
                {"if": {"properties": {"model": {"const": "gamma"}}}, "then": {"required": ["gamma"]}},
                {"if": {"properties": {"model": {"const": "table"}}}, "then": {"required": ["inverse"]}},
            ],
        },
        "noise": {"type": "object"},
        "provenance": {"type": "object"},
    },
}


def new_profile(camera: dict, bit_depth: int, crf: CRF, inputs: list[str], command: str) -> dict:
    return {
        "schema": SCHEMA_VERSION,
        "kind": KIND,
        "camera": camera,
        "bit_depth": int(bit_depth),
        "crf": crf_to_json(crf),
        "noise": {},
        "provenance": {
            "tool": "hdrmerge-cli",
            "version": __version__,
            "command": command,
            "inputs": inputs,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        },
    }


def crf_to_json(crf: CRF) -> dict:
    if crf.table is not None:
        return {"model": "table", "inverse": [[float(x) for x in row] for row in crf.table]}
    out = {"model": crf.name}
    if crf.name == "gamma":
        out["gamma"] = float(crf.param)
    return out


def crf_from_json(entry: dict, path: str = "profile") -> CRF:
    """The :class:`CRF` of a profile's ``crf`` entry (already schema-validated): a table
    must be 1 to 4 rows of equal length (2 to 65536 finite entries), non-decreasing."""
    model = entry["model"]
    if model == "table":
        rows = entry["inverse"]
        lengths = {len(row) for row in rows}
        if len(rows) > MAX_CRF_CHANNELS or len(lengths) != 1 or not 2 <= lengths.pop() <= MAX_CRF_ENTRIES:
            sizes = sorted({len(row) for row in rows})[:5]
            raise HdrMergeError(f"{path}: crf/inverse must be 1 to {MAX_CRF_CHANNELS} rows of one length, 2 to "
                                f"{MAX_CRF_ENTRIES} entries (got {len(rows)} rows of {sizes} entries)")
        try:
            return table_crf(np.asarray(rows, dtype=np.float64), "profile")
        except HdrMergeError as exc:
            raise HdrMergeError(f"{path}: crf/inverse: {exc}") from None
    if model == "gamma":
        return gamma_crf(float(entry["gamma"]), f"{path}: crf/gamma")
    return CRF(model)


def validate(profile, path: str = "profile") -> dict:
    import jsonschema

    if isinstance(profile, dict) and isinstance(profile.get("schema"), int) and profile["schema"] > SCHEMA_VERSION:
        raise HdrMergeError(
            f"{path}: profile schema {profile['schema']} is newer than this hdrmerge-cli understands "
            f"({SCHEMA_VERSION}); upgrade hdrmerge-cli"
        )
    try:
        jsonschema.validate(profile, JSON_SCHEMA)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "top level"
        raise HdrMergeError(f"{path}: not a valid profile ({where}: {exc.message[:160]})") from None
    crf_from_json(profile["crf"], path)
    return profile


def read_text(path: str | os.PathLike, max_bytes: int) -> str:
    """The UTF-8 text (a BOM is allowed) of a small input file of at most ``max_bytes``
    bytes.  Opened without blocking so that a FIFO without a writer reads as empty instead
    of hanging; every problem is an :class:`HdrMergeError` naming the file."""
    path = str(path)
    nonblock = getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(path, os.O_RDONLY | nonblock)
        with os.fdopen(fd, "rb") as fh:
            if nonblock:
                os.set_blocking(fd, True)  # a pipe with a writer, e.g. <(...), is read as it comes
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise HdrMergeError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if len(data) > max_bytes:
        raise HdrMergeError(f"{path}: larger than {max_bytes // 2**20} MB; not an input file of hdrmerge-cli")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise HdrMergeError(f"{path}: not UTF-8 text (bad byte at offset {exc.start})") from None


def parse_json(text: str, path: str) -> object:
    """JSON ``text`` with finite numbers only (no ``NaN``, ``Infinity``, ``1e400``, nor
    integers of more than 30 digits), no duplicate keys and at most :data:`MAX_DEPTH`
    levels of nesting."""
    def bad(msg):
        raise HdrMergeError(f"{path}: {msg}")

    def number(s):
        value = float(s)
        return value if math.isfinite(value) else bad(f"number {s[:40]} is out of range")

    def integer(s):
        return int(s) if len(s.lstrip("-")) <= 30 else bad(f"integer {s[:40]}... is too long")

    def no_duplicates(pairs):
        out = {}
        for key, value in pairs:
            if key in out:
                bad(f"key {key[:40]!r} appears twice in one object")
            out[key] = value
        return out

    try:
        data = json.loads(text, parse_float=number, parse_int=integer, object_pairs_hook=no_duplicates,
                          parse_constant=lambda c: bad(f"{c} is not allowed (numbers must be finite)"))
    except json.JSONDecodeError as exc:
        raise HdrMergeError(f"{path}: not JSON ({exc})") from None
    except RecursionError:
        raise HdrMergeError(f"{path}: nested more than {MAX_DEPTH} levels deep") from None
    level, depth = [data] if isinstance(data, (dict, list)) else [], 0
    while level:  # breadth first, without recursion
        depth += 1
        if depth > MAX_DEPTH:
            raise HdrMergeError(f"{path}: nested more than {MAX_DEPTH} levels deep")
        level = [c for item in level for c in (item.values() if isinstance(item, dict) else item)
                 if isinstance(c, (dict, list))]
    return data


def load_profile(path: str | os.PathLike) -> dict:
    """Read and check a profile JSON (see the module docstring)."""
    path = str(path)
    return validate(parse_json(read_text(path, MAX_PROFILE_BYTES), path), path)


def dumps(profile: dict) -> str:
    return json.dumps(profile, indent=1, allow_nan=False) + "\n"


def profile_writer(profile: dict, path: str | os.PathLike):
    """``profile`` checked, and a writer of it for
    :func:`~hdrmerge_cli.io.atomic.write_together`."""
    validate(profile, str(path))
    text = dumps(profile)
    return lambda tmp: write_text(tmp, text)
