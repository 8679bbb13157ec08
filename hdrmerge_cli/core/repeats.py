"""Frames of equal exposure (bursts, repeated brackets): do they agree within the noise?

Frames of one exposure are merged like any others: the estimator weights every
observation by its information, so N equal frames average the noise variance down to 1/N
(each frame's weight is the same function of its code).  What must not be averaged is a
pair that disagrees in content: a changed exposure (metadata that lies, an automatic
exposure between burst frames) or motion.  :func:`compare_repeat` measures both on a
subsample of two such frames, with the noise model measured on the pair itself: the
spread of the code differences as a function of the code level (the same local
mean/variance idea as the noise calibration), so it needs no noise parameters.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: a pair whose brightness differs by more than this (stops) had different exposures
RATIO_TOLERANCE_EV = 0.1
#: a difference beyond this many robust standard deviations is beyond the noise
OUTLIER_SIGMAS = 6.0
#: a pair with more than this fraction of such differences disagrees in content
OUTLIER_FRACTION = 0.01
#: level bins of the difference spread
LEVEL_BINS = 16
#: fewest samples a comparison needs
MIN_SAMPLES = 500


@dataclass
class RepeatCheck:
    """``ratio_ev``: log2 of frame b's brightness over frame a's (median over samples
    well inside both frames' range); ``outliers``: fraction of samples whose difference
    lies beyond :data:`OUTLIER_SIGMAS` robust standard deviations of its level;
    ``samples``: how many samples were compared."""

    ratio_ev: float
    outliers: float
    samples: int

    @property
    def exposure_changed(self) -> bool:
        return abs(self.ratio_ev) > RATIO_TOLERANCE_EV

    @property
    def content_differs(self) -> bool:
        return self.outliers > OUTLIER_FRACTION


def compare_repeat(codes_a: np.ndarray, codes_b: np.ndarray, lin_a: np.ndarray, lin_b: np.ndarray,
                   lo: float = 0.02, hi: float = 0.95) -> RepeatCheck | None:
    """Compare two frames of nominally equal exposure, sample by sample.

    codes_a, codes_b : the stored code values of the same sites (any shape, equal)
    lin_a, lin_b : their linear values (1 = full scale), e.g. through the inverse response
    lo, hi : linear values outside which a sample is too dark or clipped to compare

    The brightness ratio is the median of ``lin_b / lin_a``; the differences
    ``codes_b - codes_a`` are judged per level bin (quantiles of the mean code) against
    1.4826 times their median absolute deviation, with a floor of three of the smallest
    code steps seen (noise-free quantised data have a zero deviation).  Returns None when
    fewer than :data:`MIN_SAMPLES` samples are usable."""
    la, lb = np.ravel(lin_a).astype(np.float64), np.ravel(lin_b).astype(np.float64)
    ok = (la > lo) & (la < hi) & (lb > lo) & (lb < hi)
    n = int(np.count_nonzero(ok))
    if n < MIN_SAMPLES:
        return None
    ratio_ev = float(np.median(np.log2(lb[ok] / la[ok])))
    za, zb = np.ravel(codes_a).astype(np.float64)[ok], np.ravel(codes_b).astype(np.float64)[ok]
    diff = zb - za
    steps = np.abs(diff[diff != 0])
    floor = 3.0 * float(steps.min()) if steps.size else 3.0
    level = 0.5 * (za + zb)
    edges = np.unique(np.quantile(level, np.linspace(0, 1, LEVEL_BINS + 1)))
    which = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, max(len(edges) - 2, 0))
    outliers = 0
    for k in np.unique(which):
        d = diff[which == k]
        centre = np.median(d)
        spread = 1.4826 * float(np.median(np.abs(d - centre)))
        outliers += int(np.count_nonzero(np.abs(d - centre) > max(OUTLIER_SIGMAS * spread, floor)))
    return RepeatCheck(ratio_ev, outliers / n, n)
