"""Resolve a ``--crf`` argument: a model name, a CSV table or a profile JSON."""
from __future__ import annotations

import os

import numpy as np

from hdrmerge_cli.core.crf import CRF, parse_crf, table_crf
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.profile import MAX_CRF_CHANNELS, crf_from_json, load_profile, read_text
from hdrmerge_cli.io.times import parse_number

#: largest CSV table read (bytes), and the largest code value ``z`` (16-bit)
MAX_CSV_BYTES, MAX_CODE = 16 * 2**20, 65535


def read_crf_csv(path: str) -> CRF:
    """CSV of ``z, linear`` (or ``z, R, G, B``) rows; ``#`` starts a comment and the first
    line may be a header.  ``z`` are integer codes in 0..65535, strictly increasing; the
    linear values finite numbers, non-decreasing; at least two rows, all of the same
    width.  The table is interpolated onto every code value from 0 to the largest ``z``."""
    rows, header_allowed = [], True
    for n, line in enumerate(read_text(path, MAX_CSV_BYTES).splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.split(",")
        try:
            row = [parse_number(f) for f in fields]
        except HdrMergeError as exc:
            if header_allowed:  # a header line: z,linear
                header_allowed = False
                continue
            raise HdrMergeError(f"{path}:{n}: {exc}") from None
        header_allowed = False
        if not 2 <= len(row) <= MAX_CRF_CHANNELS + 1:
            raise HdrMergeError(f"{path}:{n}: expected 'z, linear' or 'z, R, G, B', got {len(row)} columns")
        if rows and len(row) != len(rows[0]):
            raise HdrMergeError(f"{path}:{n}: {len(row)} columns where the first row has {len(rows[0])}")
        z = row[0]
        if not (z == int(z) and 0 <= z <= MAX_CODE):
            raise HdrMergeError(f"{path}:{n}: z = {z:g} is not an integer code in 0..{MAX_CODE}")
        if rows and z <= rows[-1][0]:
            raise HdrMergeError(f"{path}:{n}: the z column must increase (z = {z:g} after {rows[-1][0]:g})")
        rows.append(row)
    if len(rows) < 2:
        raise HdrMergeError(f"{path}: a CRF table needs rows 'z, linear value' (at least two)")
    data = np.array(rows, dtype=np.float64)
    z = data[:, 0]
    grid = np.arange(0, int(z[-1]) + 1, dtype=np.float64)
    table = np.stack([np.interp(grid, z, data[:, c]) for c in range(1, data.shape[1])])
    try:
        return table_crf(table, os.path.basename(path))
    except HdrMergeError as exc:
        raise HdrMergeError(f"{path}: {exc}") from None


def resolve_crf(spec: str) -> CRF:
    """``--crf``: a profile JSON (``.json``), a CSV table (``.csv``/``.txt``) or a model
    name (:func:`parse_crf`)."""
    if os.path.isdir(spec):
        raise HdrMergeError(f"{spec}: is a folder, not a camera response (linear, srgb, gamma:G, a CSV table or "
                            "a profile JSON)")
    if spec.lower().endswith(".json"):
        return crf_from_json(load_profile(spec)["crf"], spec)
    if spec.lower().endswith((".csv", ".txt")):
        if not os.path.isfile(spec):
            raise HdrMergeError(f"{spec}: no such file")
        return read_crf_csv(spec)
    try:
        return parse_crf(spec)
    except HdrMergeError:
        if os.path.isfile(spec):
            raise HdrMergeError(f"{spec}: not a camera response: a response file is a CSV table (.csv, .txt) or a "
                                "profile JSON (.json)") from None
        raise
