"""Ghost rejection by the noise model (array code).

A frame ``j`` reads at each sample an estimate of the exposure-normalised signal,
``x_j = gamma^-1(z_j) / h_j`` (full scale 1 at an exposure of 1 s), whose variance the noise
model predicts: ``s_j = (v(y) / y_full^2 + q(z)) / h_j^2`` with ``v`` the clipping-free
variance (17)/(21) at ``y = gamma^-1(z) y_full`` and ``q`` the quantisation variance of
one code step (step^2 / 12).  In a static scene every frame that measures a sample
estimates the same ``x`` (after :func:`match_anchor` removes what differs globally, and
with a 1 % model tolerance and half a pixel of registration tolerance along edges); a frame is inconsistent with the *anchor* (the reference frame,
or where the reference does not measure the sample, the measuring frame nearest to it in
exposure) when, over the ``k`` samples of a cell (a 2 x 2 CFA period, or a pixel's
channels) that both measure,

    T = sum (x_j - x_anchor)^2 / (s_j + s_anchor)  >  chi2_k quantile (1 - p_fa),

a chi-square test at false-alarm rate ``p_fa`` per cell.  Rejections are cleaned
morphologically (an opening removes isolated false alarms, a dilation covers the soft
edges of moving objects) and the frame is dropped from those cells' average; the anchor
is never dropped, so the result shows one moment.  Where the reference reads dark or
clipped it still bounds the signal (:func:`violates_bound`): a frame reading far outside
that bound is dropped too, and never becomes the anchor.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from hdrmerge_cli.core.calibrate import equal_count_bins
from hdrmerge_cli.core.noise import NoiseParams, code_variance

#: false-alarm rate of the per-cell test
P_FALSE_ALARM = 1e-3
#: samples the intensity matching of :func:`match_anchor` is fitted on
FIT_SAMPLES = 1 << 20
#: relative error allowed beyond the noise (residual model error after :func:`match_anchor`)
MODEL_TOLERANCE = 0.01
#: registration error allowed (pixels): an edge's contrast times this is not motion
ALIGN_TOLERANCE_PX = 0.5
#: how far beyond a dark / clipped reference's bound a reading must be to be motion
BOUND_FACTOR = 2.0
#: smallest connected region of rejected cells kept as motion
MIN_BLOB = 64
#: ``auto`` deghosts when a frame has more than this fraction of its cells rejected
AUTO_FRACTION = 0.002


def ghost_tables(n_codes: int, black: float, white: float, lin_of, exposure: float,
                 noise: NoiseParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per stored code ``r = 0..N-1`` of one channel: ``x`` (exposure-normalised linear
    value), its predicted variance ``s`` and whether it measures (strictly between black
    and white).  ``lin_of(v)``: the inverse CRF on the normalised code ``v``."""
    y_full = white - black
    v = (np.arange(n_codes, dtype=np.float64) - black) / y_full
    valid = (v > 0) & (v < 1)
    lin = lin_of(np.clip(v, 0.0, 1.0))
    step = np.gradient(lin)  # linear value per code step
    var = code_variance(np.maximum(lin, 0.0) * y_full, noise) / y_full**2 + step * step / 12.0
    return lin / exposure, var / exposure**2, valid


def match_anchor(x: np.ndarray, xa: np.ndarray, both: np.ndarray, bins: int = 64) -> np.ndarray:
    """``x`` mapped onto the anchor's scale: the median log-ratio ``log xa - log x`` in
    quantile bins of ``log x`` (over samples both measure), interpolated.  It absorbs what
    is global, not motion: nominal exposure times that are a few per cent off, a camera
    response that is not exactly the assumed one; medians ignore a moving minority."""
    ok = both & (x > 0) & (xa > 0)
    n_ok = np.count_nonzero(ok)
    if n_ok < 10 * bins:
        return x
    pick = np.flatnonzero(ok)[:: max(1, n_ok // FIT_SAMPLES)]  # a smooth curve: a subsample fits it
    lx = np.log(x.ravel()[pick])
    d = np.log(xa.ravel()[pick]) - lx
    edges, order, starts = equal_count_bins(lx, bins)
    d_sorted, lx_sorted = d[order], lx[order]
    centres, shifts = [], []
    for b in range(edges.size - 1):
        if starts[b + 1] - starts[b] >= 10:
            centres.append(np.median(lx_sorted[starts[b]:starts[b + 1]]))
            shifts.append(np.median(d_sorted[starts[b]:starts[b + 1]]))
    if not centres:
        return x
    with np.errstate(divide="ignore"):
        return x * np.exp(np.interp(np.log(x), centres, shifts)).astype(x.dtype)


def violates_bound(x: np.ndarray, s: np.ndarray, bound: np.ndarray, p_fa: float = P_FALSE_ALARM) -> np.ndarray:
    """Where the reference does not measure a sample it still bounds it: a dark reading
    says ``x <= bound`` (``bound > 0``, the x of its lowest measuring code), a clipped one
    ``x >= -bound`` (``bound < 0``).  True where a frame's reading is beyond that bound by
    more than :data:`BOUND_FACTOR` and the one-sided ``p_fa`` quantile of its noise: it
    shows another moment (e.g. a moving object where the reference saw dark background).
    The factor absorbs camera-response errors, which are largest far from mid-grey."""
    from scipy.stats import norm

    out = np.zeros(x.shape, bool)
    where = np.flatnonzero(bound)  # only where the reference reads dark or clipped
    xb, bb = x.ravel()[where], bound.ravel()[where]
    k = np.float32(norm.isf(p_fa)) * np.sqrt(s.ravel()[where])
    out.ravel()[where] = ((bb > 0) & (xb - k > bb * np.float32(BOUND_FACTOR))) | (
        (bb < 0) & (xb + k < -bb / np.float32(BOUND_FACTOR)))
    return out


def cell_sums(a: np.ndarray, ph: int, pw: int) -> np.ndarray:
    """Sum over cells of ``ph x pw`` samples of a 2-D array (partial cells dropped)."""
    h, w = a.shape[0] // ph * ph, a.shape[1] // pw * pw
    return a[:h, :w].reshape(h // ph, ph, w // pw, pw).sum(axis=(1, 3))


def chi2_thresholds(k_max: int, p_fa: float = P_FALSE_ALARM) -> np.ndarray:
    """``t[k]``: the (1 - p_fa) quantile of chi-square with ``k`` degrees of freedom
    (``t[0] = inf``: no test)."""
    from scipy.stats import chi2

    return np.concatenate([[np.inf], chi2.isf(p_fa, np.arange(1, k_max + 1))])


def squared_gradient(xa: np.ndarray, layout: str) -> np.ndarray:
    """``|grad x|^2`` per sample (per pixel squared), from same-colour neighbours:
    ``layout`` "mosaic" (``(H, W)`` Bayer, neighbours 2 apart) or "rgb" (``(H, W, C)``)."""
    if layout == "mosaic":
        out = np.empty(xa.shape, np.float32)
        for dy in (0, 1):
            for dx in (0, 1):
                sub = xa[dy::2, dx::2]
                gy, gx = (np.gradient(sub, 2.0, axis=a) if sub.shape[a] > 1 else np.zeros_like(sub) for a in (0, 1))
                out[dy::2, dx::2] = gy * gy + gx * gx
        return out
    gy, gx = (np.gradient(xa, axis=a) if xa.shape[a] > 1 else np.zeros_like(xa) for a in (0, 1))
    return (gy * gy + gx * gx).astype(np.float32)


def inconsistent_cells(x: np.ndarray, s: np.ndarray, valid: np.ndarray, xa: np.ndarray, sa: np.ndarray,
                       valid_a: np.ndarray, grad2: np.ndarray, cell: tuple[int, int],
                       p_fa: float = P_FALSE_ALARM) -> np.ndarray:
    """Cells where a frame disagrees with the anchor: all inputs ``(H, W')`` per sample
    (``W' = W * C`` for interleaved channels), ``grad2`` the anchor's squared gradient
    (:func:`squared_gradient`), ``cell = (ph, pw)`` samples per cell.  The variance of a
    difference is the noise of both frames, the model tolerance and a registration
    tolerance of :data:`ALIGN_TOLERANCE_PX` along the gradient.  Returns
    ``(H // ph, W' // pw)`` bool."""
    both = valid & valid_a
    x = match_anchor(x, xa, both)
    var = s + sa + (MODEL_TOLERANCE * xa) ** 2 + ALIGN_TOLERANCE_PX**2 * grad2
    t = np.where(both, (x - xa) ** 2 / np.maximum(var, 1e-30), 0.0)
    stat = cell_sums(t, *cell)
    k = cell_sums(both.astype(np.int32), *cell)
    return stat > chi2_thresholds(cell[0] * cell[1], p_fa)[k]


def clean(mask: np.ndarray, open_radius: int = 1, min_cells: int = MIN_BLOB, grow: int = 2) -> np.ndarray:
    """Morphological clean-up of a rejection mask: an opening and the removal of
    connected regions smaller than ``min_cells`` (isolated false alarms, and the sparse
    ones along edges, go; a moving object is a large connected region), then a dilation by
    ``grow`` cells (its soft edge is covered)."""
    st = ndimage.generate_binary_structure(2, 1)
    out = ndimage.binary_opening(mask, st, iterations=open_radius) if open_radius else mask
    if min_cells > 1 and out.any():
        labels, n = ndimage.label(out, st)
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        big = sizes >= min_cells
        big[0] = False
        out = big[labels]
    return ndimage.binary_dilation(out, st, iterations=grow) if grow else out


def expand(cells: np.ndarray, cell: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """Cell decisions back to samples ``shape`` (partial cells at the edges take their
    neighbour's decision)."""
    full = np.repeat(np.repeat(cells, cell[0], axis=0), cell[1], axis=1)
    pad = ((0, shape[0] - full.shape[0]), (0, shape[1] - full.shape[1]))
    return np.pad(full, pad, mode="edge") if any(p[1] for p in pad) else full
