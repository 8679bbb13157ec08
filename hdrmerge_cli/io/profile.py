"""Camera profile JSON: versioned, validated on load (jsonschema), unknown keys kept.

Layout (schema 1)::

    {"schema": 1, "kind": "hdrmerge-cli camera profile",
     "camera": {"make": "...", "model": "..."}, "bit_depth": 8,
     "crf": {"model": "linear" | "srgb" | "gamma" | "table", "gamma": 2.2,
             "channels": "RGB", "inverse": [[gamma^-1(z) for z in 0..2^B-1], ...]},
     "noise": {...}, "weights": "...", "provenance": {...}}

``crf.inverse`` holds the linear value ``gamma^-1(z)`` in [0, 1] per channel (the paper's
``g(z)`` is its logarithm); it is present only for ``model: table``.
"""
from __future__ import annotations

import datetime as _dt
import json
import os

import numpy as np

from hdrmerge_cli import __version__
from hdrmerge_cli.core.crf import CRF, table_crf
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.atomic import atomic_text

SCHEMA_VERSION = 1
KIND = "hdrmerge-cli camera profile"

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


def crf_from_json(entry: dict) -> CRF:
    model = entry["model"]
    if model == "table":
        return table_crf(np.asarray(entry["inverse"], dtype=np.float64), "profile")
    if model == "gamma":
        return CRF("gamma", float(entry["gamma"]))
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
    return profile


def load_profile(path: str | os.PathLike) -> dict:
    path = str(path)
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except OSError as exc:
        raise HdrMergeError(f"{path}: cannot read ({exc.strerror})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise HdrMergeError(f"{path}: not JSON ({exc})") from None
    return validate(data, path)


def dumps(profile: dict) -> str:
    return json.dumps(profile, indent=1, allow_nan=False) + "\n"


def save_profile(path: str | os.PathLike, profile: dict, overwrite: bool) -> None:
    validate(profile, str(path))
    atomic_text(path, dumps(profile), overwrite)
