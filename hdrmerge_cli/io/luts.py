"""Weight tables on disk (``weights-lut``'s output, ``merge --lut``'s input): one row per
code value, one column per exposure (and channel), as CSV, NPY or JSON."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.atomic import write_text

LUT_FORMATS = (".csv", ".npy", ".json")


def luts_writer(path: Path, table: np.ndarray, labels: list[str], meta: dict):
    """A writer of the table in the format of ``path``'s suffix (checked here), for
    :func:`~hdrmerge_cli.io.atomic.write_together`."""
    suffix = Path(path).suffix.lower()
    if suffix not in LUT_FORMATS:
        raise HdrMergeError(f"{path}: unknown table format (use {', '.join(LUT_FORMATS)})")

    def write(tmp: str) -> None:
        if suffix == ".npy":
            np.save(tmp, table)
        elif suffix == ".json":
            write_text(tmp, json.dumps(meta | {"columns": labels, "weights": table.T.tolist()}) + "\n")
        else:
            z = np.arange(table.shape[0])[:, None]
            np.savetxt(tmp, np.hstack([z, table]), delimiter=",", header="z," + ",".join(labels),
                       comments="", fmt=["%d"] + ["%.9g"] * table.shape[1])

    return write


def read_luts(path: str) -> np.ndarray:
    """A table written by :func:`luts_writer`: ``(n_codes, columns)`` float64 in [0, 1]."""
    suffix = Path(path).suffix.lower()
    try:
        if suffix == ".npy":
            table = np.load(path, allow_pickle=False)
        elif suffix == ".json":
            table = np.asarray(json.loads(Path(path).read_text())["weights"], dtype=np.float64).T
        elif suffix == ".csv":
            table = _read_csv(path)
        else:
            raise HdrMergeError(f"{path}: unknown table format (use {', '.join(LUT_FORMATS)})")
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as exc:
        raise HdrMergeError(f"{path}: not a weights table ({str(exc)[:120] or type(exc).__name__})") from None
    table = np.asarray(table, dtype=np.float64)
    if table.size == 0:
        raise HdrMergeError(f"{path}: the weights table is empty")
    if table.ndim != 2 or not np.all(np.isfinite(table)) or table.min() < 0 or table.max() > 1:
        raise HdrMergeError(f"{path}: a weights table holds values in [0, 1], one row per code value")
    return table


def _read_csv(path: str) -> np.ndarray:
    """A CSV table: a header line if its first line is not numbers (``weights-lut`` writes
    ``# z,...``), then rows whose first column is the code value z = 0, 1, 2, ...; the
    columns after it."""
    with open(path, encoding="utf-8", errors="replace") as f:
        first = f.readline().lstrip("#").split(",")
    try:
        [float(v) for v in first]
        header = False
    except ValueError:
        header = True
    with warnings.catch_warnings():  # an empty file: refused by the caller
        warnings.simplefilter("ignore", UserWarning)
        table = np.loadtxt(path, delimiter=",", skiprows=int(header), ndmin=2)
    if table.size and (table.shape[1] < 2 or not np.array_equal(table[:, 0], np.arange(len(table)))):
        raise HdrMergeError(f"{path}: the first column must be the code value z = 0, 1, 2, ... (as weights-lut "
                            f"writes it), then one column of weights per exposure; this table has "
                            f"{table.shape[1]} column{'s' if table.shape[1] != 1 else ''}")
    return table[:, 1:]
