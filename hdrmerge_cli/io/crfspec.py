"""Resolve a ``--crf`` argument: a model name, a CSV table or a profile JSON."""
from __future__ import annotations

import os

import numpy as np

from hdrmerge_cli.core.crf import CRF, parse_crf, table_crf
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.profile import crf_from_json, load_profile


def read_crf_csv(path: str) -> CRF:
    """CSV of ``z, linear`` (or ``z, R, G, B``) rows; a header line is allowed.  The table
    is interpolated onto every code value from 0 to the largest ``z``."""
    try:
        data = np.genfromtxt(path, delimiter=",", comments="#", dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise HdrMergeError(f"{path}: not a readable CSV table ({exc})") from None
    data = np.atleast_2d(data)
    data = data[np.all(np.isfinite(data), axis=1)]
    if data.shape[0] < 2 or data.shape[1] < 2:
        raise HdrMergeError(f"{path}: a CRF table needs rows 'z, linear value' (at least two)")
    z = data[:, 0]
    if np.any(np.diff(z) <= 0) or z[0] < 0:
        raise HdrMergeError(f"{path}: the z column must increase from 0")
    grid = np.arange(0, int(round(z[-1])) + 1, dtype=np.float64)
    table = np.stack([np.interp(grid, z, data[:, c]) for c in range(1, data.shape[1])])
    try:
        return table_crf(table, os.path.basename(path))
    except HdrMergeError as exc:
        raise HdrMergeError(f"{path}: {exc}") from None


def resolve_crf(spec: str) -> CRF:
    if spec.lower().endswith(".json"):
        return crf_from_json(load_profile(spec)["crf"])
    if spec.lower().endswith((".csv", ".txt")):
        if not os.path.isfile(spec):
            raise HdrMergeError(f"{spec}: no such file")
        return read_crf_csv(spec)
    return parse_crf(spec)
