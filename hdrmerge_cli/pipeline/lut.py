"""weights-lut: the weighting functions as per-exposure tables over all code values
(written and read back for ``merge --lut`` by :mod:`hdrmerge_cli.io.luts`)."""
from __future__ import annotations

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import DEFAULT_K
from hdrmerge_cli.core.reconstruct import certainty_table
from hdrmerge_cli.io.plots import pyplot

#: without a bracket, the prior mean puts mid-grey (18 % of full scale) at the middle exposure
MID_GREY = 0.18
#: range of --prior-rate (code values per second): from a few codes in 11 days to 65535
#: codes in 1 ns, and beyond; wider values overflow the prior's integrals
PRIOR_RATE_RANGE = (1e-12, 1e20)


def default_prior_rate(n_codes: int, exposures) -> float:
    return MID_GREY * (n_codes - 1) / float(np.exp(np.mean(np.log(exposures))))


def weight_luts(crf: CRF, n_codes: int, exposures: list[float], weights: str, noise=None, prior_rate=None,
                k: float = DEFAULT_K, bounds=None) -> tuple[np.ndarray, list[str]]:
    """``(n_codes, P * C)`` weights ``w(z)`` in [0, 1]: one column per exposure (and per
    channel when the CRF or the noise differs per channel), with their labels."""
    channels = max(1 if crf.table is None else crf.table.shape[0], len(noise) if noise else 1)
    prior = prior_rate or default_prior_rate(n_codes, exposures)
    cols, labels = [], []
    for h in exposures:
        tab = certainty_table(n_codes, np.zeros(channels), np.full(channels, n_codes - 1.0), crf, weights, h, noise,
                              prior, tuple(exposures), k, bounds)
        for c in range(channels):
            cols.append(tab[c])
            labels.append(f"t={h:.6g}" + (f":{'RGB'[c] if channels == 3 else c}" if channels > 1 else ""))
    return np.stack(cols, axis=1), labels


def check_luts(table: np.ndarray, labels: list[str], weights: str, prior_rate: float | None = None) -> None:
    """Refuse a table with a column of no positive weight: that exposure would be ignored
    (and 'merge --lut' refuses it).  ``prior_rate``: the user's --prior-rate, the likely
    cause (the prior puts that exposure's signal where it records nothing)."""
    empty = [label for label, col in zip(labels, table.T) if not np.any(col > 0)]
    if not empty:
        return
    what = f"the {weights} weights of {', '.join(empty[:3])}{' ...' if len(empty) > 3 else ''} are zero at every code"
    if prior_rate is not None:
        raise HdrMergeError(f"--prior-rate {prior_rate:g}: {what} (the prior puts the signal where that exposure "
                            "records nothing); give a rate nearer the scene's mean code value per second")
    raise HdrMergeError(f"{what}: that exposure would be ignored (check --noise, --bounds and --k)")


def luts_figure(table: np.ndarray, labels: list[str], title: str):
    """The weight curves against the code value, like the paper's Figs. 13 and 16."""
    fig, ax = pyplot().subplots(figsize=(7, 4), dpi=110)
    z = np.arange(table.shape[0])
    for col, label in zip(table.T, labels):
        ax.plot(z, col, label=label, lw=1.4)
    ax.set_xlabel("code value z")
    ax.set_ylabel("weight w(z)")
    ax.set_ylim(-0.02, 1.05)
    ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig
