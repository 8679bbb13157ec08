"""weights-lut: the weighting functions as per-exposure tables over all code values."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.reconstruct import exposure_tables
from hdrmerge_cli.io.atomic import atomic_path

LUT_FORMATS = (".csv", ".npy", ".json")


def weight_luts(crf: CRF, n_codes: int, exposures: list[float], weights: str) -> tuple[np.ndarray, list[str]]:
    """``(n_codes, P * C)`` weights: one column per exposure (and channel when the CRF
    differs per channel), with their labels."""
    channels = 1 if crf.table is None else crf.table.shape[0]
    cols, labels = [], []
    for h in exposures:
        tab = exposure_tables(n_codes, np.zeros(channels), np.full(channels, n_codes - 1.0), crf, weights, h)
        for c in range(channels):
            cols.append(tab.weight[c * n_codes:(c + 1) * n_codes].astype(np.float64))
            labels.append(f"t={h:.6g}" + (f":{'RGB'[c] if channels == 3 else c}" if channels > 1 else ""))
    return np.stack(cols, axis=1), labels


def write_luts(path: Path, table: np.ndarray, labels: list[str], meta: dict, overwrite: bool) -> None:
    suffix = Path(path).suffix.lower()
    if suffix not in LUT_FORMATS:
        raise HdrMergeError(f"{path}: unknown table format (use {', '.join(LUT_FORMATS)})")
    with atomic_path(path, overwrite) as tmp:
        if suffix == ".npy":
            np.save(tmp, table)
        elif suffix == ".json":
            Path(tmp).write_text(json.dumps(meta | {"columns": labels, "weights": table.T.tolist()}) + "\n")
        else:
            z = np.arange(table.shape[0])[:, None]
            np.savetxt(tmp, np.hstack([z, table]), delimiter=",", header="z," + ",".join(labels),
                       comments="", fmt=["%d"] + ["%.9g"] * table.shape[1])
