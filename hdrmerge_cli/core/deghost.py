"""Ghost detection by the noise model (array code): which blocks of each frame show another
moment than the reference.

A frame ``j`` reads at each sample an estimate of the exposure-normalised signal,
``x_j = gamma^-1(z_j) / h_j`` (the paper's (7) before the weighting), whose variance the
noise model predicts: ``s_j = (v(y) / y_full^2 + q(z)) / h_j^2``, ``v`` the variance
(17)/(21) and ``q`` one code step's quantisation (step^2 / 12).  The test runs on block
means (:func:`block_size`).  Where the frame and the *anchor* (the reference frame, or where
it does not measure, the measuring frame nearest to it in exposure) both measure, after
:func:`match_channels` removes what differs globally and smoothly, a cell of ``k`` samples
is inconsistent when

    T = sum (x_j - x_anchor)^2 / (lambda (s_j + s_anchor + tolerances))  >  chi2_k^-1(1 - p_fa),

a chi-square test at false-alarm rate ``p_fa`` per cell, ``lambda >= 1`` the noise the model
leaves out, measured on the pair from medians (:func:`level_scale`).  Where the reference
reads dark or clipped it still bounds the signal (:func:`violates_bound`).  A RAW mosaic is
also tested over regions against the pair's empirical null (:func:`region_shifts`).
Rejections are cleaned (:func:`clean`) and feathered (:func:`feather`), so a frame's weight
falls smoothly to zero over a moving object (``w (1 - m)``); the anchor is never dropped.

The decisions (:func:`ghost_masks`) take one :class:`DeghostParams`: :data:`RAW_PARAMS` for
linear mosaics, :data:`IMAGE_PARAMS` for processed images.
"""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from hdrmerge_cli.core.jit import njit, prange
from hdrmerge_cli.core.noise import NoiseParams, code_variance


@dataclass(frozen=True)
class DeghostParams:
    """The parameters of the ghost test for one kind of input (:data:`RAW_PARAMS`,
    :data:`IMAGE_PARAMS`); pass a modified copy (``dataclasses.replace``) to change one."""

    #: readings linear in light with a physical noise model (RAW): a code below black is a
    #: reading, the reference's dark bound carries its noise, glare cancels between exposures
    #: (only blooming excuses), and the exposure-factor fit and the region test read only
    #: blocks none of whose readings is truncated.  Else (images) the dark bound is measured
    #: on the frame and glare is bounded by the light of what clips
    linear: bool
    #: degree of the polynomial in log x matching each channel to the anchor (0: a constant
    #: exposure factor measured over regions, :func:`region_ratio`)
    match_degree: int
    #: divide out a smooth field of the log ratio (:func:`smooth_ratio_field`)
    smooth_field: bool
    #: region sides (cells) of the region test (:func:`region_shifts`); () none
    coarse_scales: tuple[int, ...]
    #: registration tolerance as a local range (blocks, :func:`envelope_residual`); 0: the
    #: anchor's gradient times :attr:`align_tolerance_px` instead
    envelope_reach: int
    #: fraction of the code range from which an image's reading bounds the light from below
    #: (:func:`shoulder_excuse`); None: never
    shoulder_code: float | None
    #: false-alarm rate per cell of the chi-square test (and of the bound and region tests)
    p_fa: float = 1e-3
    #: relative error allowed beyond the noise (what the tone match leaves)
    model_tolerance: float = 0.01
    #: registration error allowed (pixels) along the anchor's gradient
    align_tolerance_px: float = 0.5
    #: smallest |mean log ratio| of a cell that can be motion (tone mapping, glare and an
    #: unlike response differ by a few tenths at most between static frames)
    min_log_change: float = 0.3
    #: smallest connected rejected region kept (pixels; at least 8 blocks)
    min_blob_px: int = 64
    #: Gaussian sigma of a mask's soft edge (pixels; at least 1.5 blocks)
    feather_px: float = 4.0
    #: distance (pixels) from a clipped region within which it may spread (blooming, the
    #: lens's point-spread core, sharpening halos)
    bloom_px: float = 8.0
    #: measure the factor ``lambda`` the noise model leaves out (:func:`level_scale`)
    level_scale: bool = True


#: a linear RAW mosaic: one exposure factor measured over regions, no smooth field, the
#: region test over 2-8 cells, the gradient form of the registration tolerance
RAW_PARAMS = DeghostParams(linear=True, match_degree=0, smooth_field=False, coarse_scales=(2, 4, 8),
                           envelope_reach=0, shoulder_code=None)
#: a processed image (tone curve, compression, sharpening): a cubic tone match per channel,
#: a smooth ratio field, a registration tolerance of one block, readings from 0.9 of the
#: code range (registration's upper margin) bounding the light from below
IMAGE_PARAMS = DeghostParams(linear=False, match_degree=3, smooth_field=True, coarse_scales=(),
                             envelope_reach=1, shoulder_code=0.9)

#: samples the intensity matching and the level scale are fitted on
FIT_SAMPLES = 1 << 16
#: regions (of a scale, per channel) from which :func:`region_shifts` measures its null, at
#: most (a subsample beyond)
NULL_SAMPLES = 1 << 18
#: smallest robust scale of :func:`robust_poly` (log units)
MATCH_MIN_SCALE = 0.02
#: median of chi-square with one degree of freedom
CHI2_1_MEDIAN = 0.454936
#: largest variance factor :func:`level_scale` may measure (10x the model's deviation)
LAMBDA_MAX = 100.0
#: how far beyond a dark / clipped reference's bound a reading must be to be motion (a
#: factor on the bound, absorbing the response's errors far from mid-grey)
BOUND_FACTOR = 2.0
#: quantile of a static scene's readings against a dark bound (``violates_bound(adapt=True)``)
BOUND_QUANTILE = 0.9
#: the test runs on at most about this many blocks per frame
CELL_TARGET = 1 << 20
#: tiles across the longer side of the frame for :func:`smooth_ratio_field`
FIELD_TILES = 16
#: largest |log ratio| :func:`smooth_ratio_field` absorbs
FIELD_MAX = 0.5
#: glare reach (fraction of the frame's longer side): within it of a clipped region of the
#: longer exposure of a pair, that frame reading brighter is not motion (:func:`glare_excuse`)
GLARE_REACH = 0.05
#: the most of its surround's mean light that veiling glare adds to a dark patch (ISO 9358's
#: veiling glare index of camera lenses is a few per cent)
GLARE_FRACTION = 0.1


class CodeTable(NamedTuple):
    """Per stored code ``r = 0..N-1`` of one channel (:func:`ghost_tables`): ``x`` the
    exposure-normalised linear value, ``s`` its predicted variance, ``ok`` whether it measures."""

    x: np.ndarray
    s: np.ndarray
    ok: np.ndarray

    def measuring(self) -> tuple[int, int]:
        """The lowest and the highest measuring code, ``(N, -1)`` when none measures."""
        valid = np.flatnonzero(self.ok)
        return (int(valid[0]), int(valid[-1])) if valid.size else (self.x.size, -1)


def ghost_tables(n_codes: int, black: float, white: float, lin: np.ndarray, exposure: float,
                 noise: NoiseParams, footroom: bool = False) -> CodeTable:
    """One channel's :class:`CodeTable`: ``x``, ``s`` (float64) and whether a code measures
    (strictly between black and white).  ``lin``: the inverse CRF at each code (a row of
    :meth:`~hdrmerge_cli.core.crf.CRF.codes_table`), ``(N,)``.  With
    ``footroom`` (a linear RAW) every code below white is a reading, ``x <= 0`` at and below
    black: read noise spreads a dark signal's codes to both sides of black, so dropping
    those at or below it would bias the mean of a dark region upwards (by more in the
    noisier frame).  A camera that clips at black reads the lower half as black itself;
    as readings of 0 those stay comparable between frames too."""
    y_full = white - black
    v = (np.arange(n_codes, dtype=np.float64) - black) / y_full
    valid = ((v >= -black / y_full) if footroom else (v > 0)) & (v < 1)
    if footroom:
        lin = np.where(v < 0, v, lin)  # a linear response continues below black
    step = np.gradient(lin)  # linear value per code step
    var = code_variance(np.maximum(lin, 0.0) * y_full, noise) / y_full**2 + step * step / 12.0
    return CodeTable(lin / exposure, var / exposure**2, valid)


def frame_tables(lin: np.ndarray, black: np.ndarray, white: np.ndarray, exposure: float,
                 noise: list[NoiseParams] | None, footroom: bool) -> list[CodeTable]:
    """Per channel of one frame, its :func:`ghost_tables` in float32 (``lin`` ``(C, N)``,
    ``black``, ``white`` ``(C,)``); without ``noise`` (one parameter set per channel, code
    units), the quantisation of half a code of an 8-bit range (:func:`level_scale`
    measures the rest on the frames themselves)."""
    out = []
    for c in range(len(black)):
        nz = noise[min(c, len(noise) - 1)] if noise else NoiseParams(
            (0.5 * float(white[c] - black[c]) / 255.0) ** 2, 1e-12, 0.0)
        x_t, s_t, ok_t = ghost_tables(lin.shape[1], black[c], white[c], lin[c], exposure, nz, footroom=footroom)
        out.append(CodeTable(x_t.astype(np.float32), s_t.astype(np.float32), ok_t))
    return out


def near_white(x: np.ndarray, valid: np.ndarray, exposure: np.ndarray | float, lin_hi: np.ndarray) -> np.ndarray:
    """Per cell, whether an image's readings ``x`` ``(h, w, C)`` (where ``valid``; from
    frames of ``exposure``, a scalar or per reading) reach ``lin_hi`` (linear, full scale
    1, per channel; :attr:`DeghostParams.shoulder_code` through the response) in some channel."""
    return any_channel(valid & (x * exposure >= lin_hi))


def reduce_channels(op, a: np.ndarray) -> np.ndarray:
    """``op.reduce(a, axis=-1)`` of ``(h, w, C)``, as ``op`` over the channel planes
    (NumPy's reduction over a short trailing axis is about ten times slower)."""
    out = a[..., 0].copy()
    for c in range(1, a.shape[-1]):
        op(out, a[..., c], out=out)
    return out


def any_channel(a: np.ndarray) -> np.ndarray:
    """``a.any(axis=-1)`` of ``(h, w, C)`` bool (:func:`reduce_channels`)."""
    return reduce_channels(np.logical_or, a)


def shoulder_excuse(anchor_near: np.ndarray, frame_near: np.ndarray) -> np.ndarray:
    """Per cell, the sign of change that an image's readings near white
    (:func:`near_white`) leave unexplained (int8, as :func:`glare_excuse`): +1 where the
    anchor reads near white, -1 where the tested frame does, 2 (either sign) where both
    do, 0 elsewhere.  A camera's tone curve rolls off towards white and desaturates
    highlights where the assumed response runs straight on, so there a code stands for
    more light than that response says: such a reading bounds the light from below, as a
    clipped one does, and a static frame compared with it reads brighter (the anchor near
    white) or darker (the frame near white)."""
    return (anchor_near.astype(np.int8) - frame_near.astype(np.int8)
            + 2 * (anchor_near & frame_near).astype(np.int8))


def either_excuse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Two per-cell excuses (int8: +1, -1, 2 = either sign, 0 = none) in one: a sign one
    excuses and the other does not stays; opposite signs (or a 2) excuse either."""
    return np.where(a == 0, b, np.where((b == 0) | (a == b), a, np.int8(2))).astype(np.int8)


def block_statistics(plane: np.ndarray, table: CodeTable, b: int, out: tuple) -> None:
    """One channel's block estimates from its codes in one compiled pass (the readings
    ``x_j = g(z) / h_j`` of (7) before the weighting and their variance (17)/(21) plus
    quantisation, as tabulated by :func:`ghost_tables`, averaged over blocks): ``plane`` ``(H, W)``
    integer codes (any strides), per code its :class:`CodeTable` (codes beyond it read the
    last entry).  Per ``b x b`` block (partial blocks dropped), written to ``out``, four
    float32/bool ``(H // b, W // b)`` arrays (e.g. one channel of ``(h, w, C)`` ones): the
    mean of ``x``, the mean of ``s`` over ``b^2`` (the variance of a mean of ``b^2``
    independent readings), whether every code measures, and the bound a block sets where
    the frame does not measure it: the ``x`` of the lowest measuring code where every code
    lies below it (dark), minus the ``x`` of the highest where every code lies above it
    (clipped), 0 elsewhere (see :func:`violates_bound`)."""
    lo, hi = table.measuring()
    _block_statistics(plane, np.ascontiguousarray(table.x, np.float32), np.ascontiguousarray(table.s, np.float32),
                      np.ascontiguousarray(table.ok, np.bool_), lo, hi, b, *out)


@njit(parallel=True, nogil=True, cache=True)
def _block_statistics(plane, x_t, s_t, ok_t, lo, hi, b, xs, ss, ok, bound):  # pragma: no cover - compiled
    last = x_t.size - 1
    inv = 1.0 / (b * b)
    dark_x = x_t[min(max(lo, 0), last)]
    clip_x = x_t[min(max(hi, 0), last)]
    for i in prange(xs.shape[0]):
        for j in range(xs.shape[1]):
            sx = 0.0
            sv = 0.0
            all_ok = True
            dark = True
            clipped = True
            for u in range(i * b, i * b + b):
                for v in range(j * b, j * b + b):
                    z = np.int64(plane[u, v])
                    r = min(z, last)
                    sx += x_t[r]
                    sv += s_t[r]
                    all_ok = all_ok and ok_t[r]
                    dark = dark and z < lo
                    clipped = clipped and z > hi
            xs[i, j] = sx * inv
            ss[i, j] = sv * inv * inv
            ok[i, j] = all_ok
            bound[i, j] = dark_x if dark else (-clip_x if clipped else 0.0)


def block_size(h: int, w: int) -> int:
    """Side (in cells of the frame's own layout) of the blocks the test runs on: the
    smallest giving at most :data:`CELL_TARGET` blocks (1 for small frames)."""
    return max(1, int(np.ceil(np.sqrt(h * w / CELL_TARGET))))


def _block_estimates(codes: np.ndarray, pattern: np.ndarray, tables: list[CodeTable], b: int) -> Blocks:
    """One frame's :class:`Blocks` ``(h, w, C)``: :func:`block_statistics` of each plane of
    its codes through its table, the planes in the order of ``pattern.ravel()`` (an image's
    ``(H, W, C)`` channels, or the positions of a mosaic's ``(H, W)`` periodic ``pattern``,
    one sample per period); every block ``steady`` (:func:`_untruncated` narrows that for
    linear data)."""
    if codes.ndim == 3:
        planes = [codes[..., c] for c in range(codes.shape[-1])]
    else:
        ph, pw = pattern.shape
        planes = [codes[dy::ph, dx::pw] for dy in range(ph) for dx in range(pw)]
    shape = (planes[0].shape[0] // b, planes[0].shape[1] // b, len(planes))
    x, s, bound = (np.empty(shape, np.float32) for _ in range(3))
    ok = np.empty(shape, bool)
    for c, (plane, table) in enumerate(zip(planes, tables)):
        block_statistics(plane, table, b, (x[..., c], s[..., c], ok[..., c], bound[..., c]))
    return Blocks(x, s, ok, bound, ok)


def _untruncated(blocks: Blocks, tables: list[CodeTable], b: int) -> np.ndarray:
    """Where a frame's block readings ``(h, w, C)`` lie more than 3 sample noise deviations
    inside its measuring range (per channel, the x of its lowest and highest measuring
    code): there no reading of a block was lost to black or to clipping, which biases the
    mean of those kept."""
    x = blocks.x
    sd = np.sqrt(blocks.s) * np.float32(3 * b)
    out = np.empty(x.shape, bool)
    for c, table in enumerate(tables):
        lo, hi = table.measuring()
        lo, hi = (table.x[lo], table.x[hi]) if hi >= 0 else (np.inf, -np.inf)
        out[..., c] = (x[..., c] - sd[..., c] > lo) & (x[..., c] + sd[..., c] < hi)
    return out


def _level_bins(values: np.ndarray, bins: int) -> np.ndarray:
    """Edges of (about) equal-count bins of ``values`` (1-D)."""
    return np.unique(np.quantile(values, np.linspace(0.0, 1.0, bins + 1)))


class Binned(NamedTuple):
    """Per bin of :func:`_binned_median`: the median key, the median value and the count."""

    centres: np.ndarray
    medians: np.ndarray
    counts: np.ndarray


def _binned_median(key: np.ndarray, val: np.ndarray, bins: int) -> Binned:
    """The :class:`Binned` medians of ``val`` in equal-count bins of ``key`` (bins with at
    least 10 samples; bin ``j`` holds ``edges[j] <= key < edges[j + 1]``, the last one its
    upper edge too, the edges from :func:`_level_bins`).  One sort of ``key`` makes each bin
    a run of the sorted samples."""
    order = np.argsort(key)
    ks, vs = key[order], val[order]
    edges = _level_bins(ks, bins)  # the same edges, from the sorted samples (faster)
    starts = np.concatenate([[0], np.searchsorted(ks, edges[1:-1], side="left"), [ks.size]])
    c, m, n = [], [], []
    for lo, hi in zip(starts[:-1], starts[1:]):
        if hi - lo >= 10:
            c.append(np.median(ks[lo:hi]))
            m.append(np.median(vs[lo:hi]))
            n.append(hi - lo)
    return Binned(np.asarray(c), np.asarray(m), np.asarray(n, float))


def robust_poly(c: np.ndarray, d: np.ndarray, n: np.ndarray, degree: int) -> np.ndarray:
    """Polynomial coefficients fitted to points ``(c, d)`` with weights ``n`` by ten rounds
    of Tukey-bisquare re-weighting (tuning constant 4.685 robust scales; start: the weighted
    median, a constant): an outlying minority of points (a moving object that is alone at
    its brightness) gets no weight."""
    order = np.argsort(d)
    cw = np.cumsum(n[order])
    coef = np.array([d[order][np.searchsorted(cw, cw[-1] / 2)]])
    deg = min(degree, max(c.size - 2, 0))
    for _ in range(10):
        r = d - np.polyval(coef, c)
        scale = max(1.4826 * np.median(np.abs(r)), MATCH_MIN_SCALE)
        u = r / (4.685 * scale)
        w = n * np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
        if np.count_nonzero(w) <= deg:
            break
        coef = np.polyfit(c, d, deg, w=np.sqrt(w))
    return coef


def _inlier_range(coef: np.ndarray, c: np.ndarray, d: np.ndarray) -> tuple[float, float]:
    """The range of the points :func:`robust_poly` kept (within 3 robust scales): the fitted
    curve is clamped to it, so it never overshoots between or beyond its support."""
    r = d - np.polyval(coef, c)
    keep = np.abs(r) <= 3 * max(1.4826 * np.median(np.abs(r)), MATCH_MIN_SCALE)
    return (float(d[keep].min()), float(d[keep].max())) if keep.any() else (0.0, 0.0)


def match_anchor(x: np.ndarray, xa: np.ndarray, both: np.ndarray, degree: int) -> np.ndarray:
    """``x`` mapped onto the anchor's scale: ``x exp(p(log x))`` with ``p`` a low-degree
    polynomial fitted robustly (:func:`robust_poly`) to the median log-ratio
    ``log xa - log x`` in equal-count bins of ``log x`` (over samples both measure).  It
    absorbs what is global and smooth, not motion: nominal exposure times that are a few
    per cent off (a constant), a camera response that is not exactly the assumed one (a
    slow curve).  A bin-by-bin curve would also absorb a moving object that is the only
    thing at its brightness in both frames (e.g. a bright object in the short frame over
    what the reference sees dark): the robust smooth fit leaves it out."""
    if degree == 0:
        return x * np.float32(region_ratio(x, xa, both))
    bins = 32
    ok = both & (x > 0) & (xa > 0)
    n_ok = np.count_nonzero(ok)
    if n_ok < 10 * bins:
        return x
    pick = np.flatnonzero(ok)[:: max(1, n_ok // FIT_SAMPLES)]
    lx = np.log(x.ravel()[pick])
    c, m, n = _binned_median(lx, np.log(xa.ravel()[pick]) - lx, bins)
    if c.size == 0:
        return x
    coef = robust_poly(c, m, n, degree=degree)
    lo, hi = _inlier_range(coef, c, m)
    with np.errstate(divide="ignore", invalid="ignore"):
        lxx = np.clip(np.log(np.maximum(x, 1e-30)), c[0], c[-1])
    shift = np.clip(np.polyval(coef.astype(np.float32), lxx), lo, hi)
    return (x * np.exp(shift)).astype(x.dtype)


def region_ratio(x: np.ndarray, xa: np.ndarray, both: np.ndarray) -> float:
    """The constant ``c`` with ``xa ~ c x`` (``(H, W)`` readings, used where ``both``): the
    median over 8 x 8 regions of ``sum xa / sum x``, weighted by the anchor's sum (its
    signal: the ratio of a dark region is mostly noise).
    Sums over a region first, so readings of any noise (zero or negative ones of a linear
    RAW near black included) enter unbiased: a median of per-sample ratios, or of ratios
    binned by one frame's own noisy reading, is pulled away from 1 by the noise (regression
    dilution); the median over regions ignores a moving minority.  1 when no region has
    both sums positive."""
    m = 8
    sx = cell_sums(np.where(both, x, 0.0).astype(np.float64), m, m)
    sa = cell_sums(np.where(both, xa, 0.0).astype(np.float64), m, m)
    n = cell_sums(both.astype(np.float64), m, m)
    ok = (sx > 0) & (sa > 0) & (n >= m * m / 2)
    if not ok.any():
        return 1.0
    r, wt = np.log(sa[ok] / sx[ok]), sa[ok]
    order = np.argsort(r)
    cw = np.cumsum(wt[order])
    return float(np.exp(r[order][np.searchsorted(cw, cw[-1] / 2)]))


def match_channels(x: np.ndarray, xa: np.ndarray, both: np.ndarray, nc: int, degree: int) -> np.ndarray:
    """:func:`match_anchor` for each of the ``nc`` interleaved channels of ``(H, W * nc)``
    samples on its own: a camera applies its tone curve per channel after white balance,
    so where the assumed response is not the camera's, each channel is off by a curve of
    its own, which one curve over all channels cannot absorb (a coloured surface then
    differs between exposures by tens of per cent in one channel)."""
    if nc == 1:
        return match_anchor(x, xa, both, degree=degree)
    out = np.empty_like(x)
    for c in range(nc):
        out[:, c::nc] = match_anchor(x[:, c::nc], xa[:, c::nc], both[:, c::nc], degree=degree)
    return out


def level_scale(t: np.ndarray, x: np.ndarray, xa: np.ndarray, both: np.ndarray) -> np.ndarray:
    """Per sample, the factor ``lambda`` by which the model variance under-predicts the
    spread of a static scene's differences: ``median(T) / median(chi2_1)`` in equal-count
    bins of the lower of the two readings (``T`` the per-sample normalised squared
    difference), at least 1, as a smooth robust curve (:func:`robust_poly` on
    ``log lambda``) capped at :data:`LAMBDA_MAX`.  What it measures is what the model
    leaves out (JPEG compression and sharpening, denoising, an unknown noise model).
    Medians and the robust curve ignore a moving minority; binning by the *lower* reading
    puts a moving object among static samples of its level (a bright object in a short
    frame sits at the dark level the anchor reads, a dark one in a long frame at its own),
    so it cannot make up a bin of its own and raise its own threshold."""
    bins = 32
    lo = np.minimum(x, xa)
    ok = both & (lo > 0)
    n_ok = np.count_nonzero(ok)
    if n_ok < 10 * bins:
        return np.ones(1, np.float32)
    pick = np.flatnonzero(ok)[:: max(1, n_ok // FIT_SAMPLES)]
    c, m, n = _binned_median(np.log(lo.ravel()[pick]), t.ravel()[pick], bins)
    if c.size == 0:
        return np.ones(1, np.float32)
    log_lam = np.log(np.maximum(m / CHI2_1_MEDIAN, 1.0))
    coef = robust_poly(c, log_lam, n, degree=2)
    top = min(_inlier_range(coef, c, log_lam)[1], np.log(LAMBDA_MAX))
    with np.errstate(divide="ignore"):
        key = np.clip(np.log(np.maximum(lo, 1e-30)), c[0], c[-1])
    lam = np.exp(np.clip(np.polyval(coef.astype(np.float32), key), 0.0, top))
    return lam.astype(np.float32)


def violates_bound(x: np.ndarray, s: np.ndarray, bound: np.ndarray, p_fa: float,
                   adapt: bool = False, s_bound: np.ndarray | None = None) -> np.ndarray:
    """Where the reference does not measure a sample it still bounds it: a dark reading
    says ``x <= bound`` (``bound > 0``, the x of its lowest measuring code), a clipped one
    ``x >= -bound`` (``bound < 0``), each up to the bounding reading's own noise ``s_bound``
    (same shape as ``x``; a RAW reading at black is read noise about the signal, so the
    signal may lie some noise above the lowest measuring code; None: no such noise).  True
    where a frame's reading is beyond that bound by more than :data:`BOUND_FACTOR` and the
    one-sided ``p_fa`` quantile of the two readings' noise: it shows another moment (e.g. a
    moving object where the reference saw dark background).
    The factor absorbs camera-response errors, which are largest far from mid-grey.  With
    ``adapt`` the bounds are also measured on the frame: a JPEG's tone curve may crush to
    code 0 (or clip) values far beyond what the assumed response puts at the lowest (highest)
    measuring code, so a dark bound is raised to the :data:`BOUND_QUANTILE` quantile of
    ``x / bound`` over the samples it bounds: a static scene is then within it, a moving
    minority still beyond it (clipped bounds are kept: a moving object may fill a small
    clipped region)."""
    from scipy.special import ndtri

    out = np.zeros(x.shape, bool)
    where = np.flatnonzero(bound)  # only where the reference reads dark or clipped
    xb, bb = x.ravel()[where], bound.ravel()[where]
    var = s.ravel()[where] if s_bound is None else s.ravel()[where] + s_bound.ravel()[where]
    k = np.float32(-ndtri(p_fa)) * np.sqrt(var)  # the normal's upper p_fa quantile
    up, down = np.float32(BOUND_FACTOR), np.float32(BOUND_FACTOR)
    if adapt:
        dark = (bb > 0) & (xb > 0)
        if np.count_nonzero(dark) >= 100:
            up *= np.float32(max(1.0, np.quantile(xb[dark] / bb[dark], BOUND_QUANTILE)))
    out.ravel()[where] = ((bb > 0) & (xb - k > bb * up)) | ((bb < 0) & (xb + k < -bb / down))
    return out


def cell_sums(a: np.ndarray, ph: int, pw: int) -> np.ndarray:
    """Sum over cells of ``ph x pw`` samples of a 2-D array (partial cells dropped): the
    cells' strided sub-arrays added up (a reduction over a short trailing axis is ten
    times slower)."""
    h, w = a.shape[0] // ph * ph, a.shape[1] // pw * pw
    out = a[0:h:ph, 0:w:pw].copy()
    for dy in range(ph):
        for dx in range(pw):
            if dy or dx:
                out += a[dy:h:ph, dx:w:pw]
    return out


def chi2_thresholds(k_max: int, p_fa: float) -> np.ndarray:
    """``t[k]``: the (1 - p_fa) quantile of chi-square with ``k`` degrees of freedom
    (``t[0] = inf``: no test)."""
    from scipy.special import chdtri

    return np.concatenate([[np.inf], chdtri(np.arange(1, k_max + 1), p_fa)])


def squared_gradient(xa: np.ndarray) -> np.ndarray:
    """``|grad x|^2`` per sample of ``(H, W, C)`` (per pixel squared), from neighbours along
    both axes."""
    gy, gx = (np.gradient(xa, axis=a) if xa.shape[a] > 1 else np.zeros_like(xa) for a in (0, 1))
    return (gy * gy + gx * gx).astype(np.float32)


def smooth_ratio_field(r: np.ndarray, ok: np.ndarray, nc: int) -> np.ndarray:
    """A smooth, low-frequency field of the log ratio ``r`` (``(H, W * nc)`` per sample, used
    where ``ok``): per-tile medians over about :data:`FIELD_TILES` across the longer side (tiles
    with under 10 % usable samples take their nearest neighbour's), a 3 x 3 median across
    tiles (a moving object filling most of one tile does not make its value), clipped to
    ``+-FIELD_MAX`` and interpolated bilinearly.  Dividing it out absorbs what varies slowly
    over the frame (vignetting, in-camera local tone mapping, broad glare) while a compact
    object with sharp edges stays."""
    from scipy import ndimage  # deghosting only: not on a plain merge's start-up
    h, w = r.shape[0], r.shape[1] // nc
    t = max(8, int(np.ceil(max(h, w) / FIELD_TILES)))
    gh, gw = -(-h // t), -(-w // t)
    grid = np.full((gh, gw), np.nan, np.float32)
    rr = np.where(ok, r, np.nan).reshape(h, w, nc)
    for i in range(gh):
        for j in range(gw):
            v = rr[i * t:(i + 1) * t, j * t:(j + 1) * t].ravel()
            v = v[np.isfinite(v)]
            if v.size >= 0.1 * t * t:
                grid[i, j] = np.median(v)
    if np.all(np.isnan(grid)):
        return np.zeros(r.shape, np.float32)
    idx = ndimage.distance_transform_edt(np.isnan(grid), return_distances=False, return_indices=True)
    grid = np.clip(ndimage.median_filter(grid[tuple(idx)], 3, mode="nearest"), -FIELD_MAX, FIELD_MAX)
    import cv2

    f = cv2.resize(grid, (gw * t, gh * t), interpolation=cv2.INTER_LINEAR)[:h, :w]
    return np.repeat(f, nc, axis=1)


def glare_excuse(clipped: np.ndarray, sign: int, reach: float = GLARE_REACH, source: np.ndarray | None = None,
                 need: np.ndarray | None = None, bloom: float = 0.0) -> np.ndarray:
    """Per cell, the sign of a difference (frame minus anchor) that is not motion: ``sign``
    (+1: the frame is the longer exposure and may read brighter; -1: the anchor is) within
    ``reach`` times the longer side of the cells ``clipped`` in the longer exposure (veiling
    glare and blooming around clipped highlights grow with exposure), 0 elsewhere.
    With ``source`` (per cell, the anchor's level; inf where it is unknown, e.g. clipped in
    every frame) and ``need`` (per cell, the light glare would have to add, same units) a
    cell is excused only where :data:`GLARE_FRACTION` of the mean light of the clipped cells
    around it (``source`` where clipped, 0 elsewhere, averaged over the part of the square
    of side ``2 reach + 1`` inside the frame) reaches ``need``, where a clipped cell of
    unknown level lies in that square, or within ``bloom`` cells of a clipped cell (glare
    scales with how much of the surround is bright).  Returns ``(h, w)`` int8."""
    import cv2

    if not clipped.any() or not sign:
        return np.zeros(clipped.shape, np.int8)
    r = reach * max(clipped.shape)
    # the exact Euclidean distance to the nearest clipped cell, compared as a whole squared
    # distance so that no rounding moves the boundary
    d = cv2.distanceTransform(np.ascontiguousarray(~clipped, np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d2 = np.rint(np.square(d, dtype=np.float64))
    near = d2 <= r**2
    if source is not None:
        side = 2 * int(r) + 1
        unknown = clipped & ~np.isfinite(source)
        light = np.where(clipped & ~unknown, source, 0.0).astype(np.float64)

        def box_sum(a):
            return cv2.boxFilter(a, cv2.CV_64F, (side, side), normalize=False, borderType=cv2.BORDER_CONSTANT)

        mean = box_sum(light) / box_sum(np.ones(clipped.shape, np.float64))
        near &= ((GLARE_FRACTION * mean >= need) | (box_sum(unknown.astype(np.float64)) > 0.5)
                 | (d2 <= bloom**2))
    return np.where(near, np.int8(sign), np.int8(0))


def envelope(a: np.ndarray, nc: int, reach: int) -> tuple[np.ndarray, np.ndarray]:
    """Per sample of ``(H, W * nc)`` interleaved channels, the smallest and largest value of
    its channel within ``reach`` samples along both axes (edges repeated): OpenCV's erosion
    and dilation by a ``(2 reach + 1)`` square, each channel on its own."""
    import cv2

    img = np.ascontiguousarray(a, np.float32).reshape(a.shape[0], -1, nc)
    kernel = np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)
    lo = cv2.erode(img, kernel, borderType=cv2.BORDER_REPLICATE).reshape(a.shape)
    hi = cv2.dilate(img, kernel, borderType=cv2.BORDER_REPLICATE).reshape(a.shape)
    return lo, hi


def envelope_residual(x: np.ndarray, xa: np.ndarray, nc: int, reach: int) -> np.ndarray:
    """The signed difference (frame minus anchor) between ``x`` and the anchor ``xa`` that no
    local shift within ``reach`` samples explains (both ``(H, W * nc)``, channels
    interleaved): the smaller of the distance of ``x`` to the range of the anchor's values
    within reach and that of ``xa`` to the range of the frame's (0 inside either).  A
    registration tolerance that needs no gradient model: an edge, a line one sample wide,
    a halo or a ringing lobe that is displaced, blurred or sharpened differently in the
    two frames lies within the other's local range; an object that is in one frame only
    lies outside it wherever its value differs from everything around it in the other
    (over a flat surround: everywhere; over texture: where it is brighter or darker than
    the texture's local extremes).  The symmetric form excuses blur and sharpening in
    either frame.  Returns float32 ``(H, W * nc)``."""
    lo, hi = envelope(xa, nc, reach)
    d1 = x - np.clip(x, lo, hi)
    lo, hi = envelope(x, nc, reach)
    d2 = np.clip(xa, lo, hi) - xa
    return np.where(np.abs(d1) < np.abs(d2), d1, d2).astype(np.float32)


class LogChange(NamedTuple):
    """What :func:`_log_change` finds per sample: the log change ``r``, where it is measured
    (``pos``) and the anchor's reading raised to the noise (``xaf``)."""

    r: np.ndarray
    pos: np.ndarray
    xaf: np.ndarray


def _log_change(x: np.ndarray, xa: np.ndarray, var: np.ndarray, both: np.ndarray) -> LogChange:
    """The :class:`LogChange` ``r = log(xf / xaf)`` of each sample where both readings,
    each raised to at least the pair's noise deviation ``sqrt(var)``, are positive
    (``pos``; 0 elsewhere), float32; a reading within its noise of zero is about that
    dark, so the change of a dark object over a bright surround is large, not undefined."""
    floor = np.sqrt(var, dtype=np.float32)
    xf, xaf = np.maximum(x, floor), np.maximum(xa, floor)
    del floor
    pos = both & (xf > 0) & (xaf > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(pos, np.log(np.maximum(xf, 1e-30) / np.maximum(xaf, 1e-30)), 0.0).astype(np.float32)
    return LogChange(r, pos, xaf)


def inconsistent_cells(x: np.ndarray, s: np.ndarray, valid: np.ndarray, xa: np.ndarray, sa: np.ndarray,
                       valid_a: np.ndarray, grad2: np.ndarray | None, nc: int, params: DeghostParams,
                       excuse: np.ndarray | None = None, steady: np.ndarray | None = None) -> np.ndarray:
    """Cells where a frame disagrees with the anchor, by the chi-square test at ``params.p_fa``.

    ``x, s, valid`` (frame) and ``xa, sa, valid_a`` (anchor): readings, variances and
    whether they measure, ``(H, W')`` float32 / bool per sample (``W' = W * C``, channels
    interleaved); ``grad2``: the anchor's squared gradient times the squared registration
    tolerance (used when ``params.envelope_reach`` is 0); ``nc`` channels, a cell's
    samples; ``excuse``: per cell, the sign of change that is not motion (:func:`glare_excuse`,
    :func:`shoulder_excuse`; 2 either); ``steady``: the samples the tone match and the
    region test read (None: all).  Returns ``(H, W)`` bool, a cell per pixel.
    Notes: the variance of a difference is both readings' noise, ``params.model_tolerance``
    and the registration tolerance, times :func:`level_scale`'s ``lambda``; a cell is kept
    only where its mean log change exceeds ``params.min_log_change``."""
    p = params
    both = valid & valid_a
    use = both if steady is None else both & steady
    x = match_channels(x, xa, use, nc, p.match_degree)
    r = None
    var = s + sa
    if p.smooth_field or p.min_log_change > 0 or excuse is not None:
        r, pos, xaf = _log_change(x, xa, var, both)
        if p.smooth_field:
            f = smooth_ratio_field(r, pos, nc)
            r = np.where(pos, r - f, 0.0).astype(np.float32)
            x = x * np.exp(-f).astype(np.float32)
            del f
    tol = p.model_tolerance * xa
    tol *= tol
    var += tol
    del tol
    if p.envelope_reach:
        d = envelope_residual(x, xa, nc, p.envelope_reach)
        if r is not None:  # the log change beyond what a shift within reach explains
            with np.errstate(divide="ignore", invalid="ignore"):
                r = np.where(pos, np.sign(d) * np.minimum(np.abs(r), np.log1p(np.abs(d) / np.maximum(xaf, 1e-30))),
                             0.0).astype(np.float32)
    else:
        d = x - xa
        var = var + grad2
    if r is not None:
        del xaf
    with np.errstate(over="ignore", invalid="ignore"):
        t = d * d
        t /= np.maximum(var, 1e-30)
    t[~both] = 0.0
    if p.level_scale:
        lam = level_scale(t, x, xa, both)
        t /= lam
        if p.coarse_scales:  # the region test's variances
            var *= lam
        del lam
    stat = cell_sums(t, 1, nc)
    k = cell_sums(both.astype(np.int32), 1, nc)
    bad = stat > chi2_thresholds(nc, p.p_fa)[k]
    if p.coarse_scales:
        bad |= region_shifts(np.where(use, d, 0.0), np.where(use, var, 0.0),
                             np.where(use, np.maximum(np.minimum(x, xa), 0.0), 0.0), nc, p.p_fa,
                             p.coarse_scales)
    if r is not None and (p.min_log_change > 0 or excuse is not None):
        rm = cell_sums(r, 1, nc) / np.maximum(cell_sums(pos.astype(np.int32), 1, nc), 1)
        if p.coarse_scales:  # a region's change is its mean change (a noisy cell's own mean may not pass)
            rm = np.where(np.abs(rm) > p.min_log_change, rm, region_mean(r, pos, nc, p.coarse_scales))
        if p.min_log_change > 0:
            bad &= np.abs(rm) > p.min_log_change
        if excuse is not None:
            bad &= ~((excuse * rm > 0) | (excuse == 2))
    return bad


def region_shifts(d: np.ndarray, var: np.ndarray, level: np.ndarray, nc: int, p_fa: float,
                  scales: tuple[int, ...]) -> np.ndarray:
    """Cells inside an ``m x m`` region (for each ``m`` of ``scales``, regions on a grid)
    whose differences ``d`` (frame minus anchor, ``(H, W * nc)`` with ``nc`` interleaved
    channels, 0 where not both measure) are shifted together.  Per region and channel the
    standardised mean ``z = sum d / sqrt(sum var)``; a moving object changes every cell it
    covers the same way, so a region finds an object whose change is below each cell's
    noise (a dim ghost in a short, noisy frame) that the per-cell test cannot.  But what a
    static scene's cells leave (a noise model's bias where readings are truncated at black
    or at clipping, resampling, texture) adds up over a region too, so ``z`` is measured
    against the empirical null of the pair itself (Efron 2004): its centre and spread as
    smooth robust curves (:func:`robust_poly`) of the region's level (log of the lower of
    the two mean readings, ``level`` = ``min(x, xa)`` per sample, as in
    :func:`level_scale`; medians, which a moving minority does not move), the spread at
    least 1.  A cell is rejected when ``sum_c z'^2`` of its region exceeds the chi-square
    quantile of the region's channels at ``p_fa / m^2`` (the same expected false-alarm area
    at every scale).  Returns ``(H, W)`` bool per cell."""
    h, w = d.shape[0], d.shape[1] // nc
    out = np.zeros((h, w), bool)
    bins = 16
    for m in scales:
        if h < 2 * m or w < 2 * m:
            continue
        sd = np.stack([cell_sums(d[:, c::nc], m, m) for c in range(nc)], axis=-1).astype(np.float64)
        sv = np.stack([cell_sums(var[:, c::nc], m, m) for c in range(nc)], axis=-1).astype(np.float64)
        n = np.stack([cell_sums((var[:, c::nc] > 0).astype(np.float32), m, m) for c in range(nc)], axis=-1)
        lv = np.stack([cell_sums(level[:, c::nc], m, m) for c in range(nc)], axis=-1)
        has = (sv > 0) & (n > 0) & (lv > 0)
        z = np.where(has, sd / np.sqrt(np.where(has, sv, 1.0)), 0.0)
        key = np.log(np.where(has, lv / np.maximum(n, 1), 1.0))
        if np.count_nonzero(has) < 10 * bins:
            continue
        where = np.flatnonzero(has)
        where = where[:: max(1, where.size // NULL_SAMPLES)]  # the null's medians from a subsample
        keys = key.ravel()[where]
        c, centre, cnt = _binned_median(keys, z.ravel()[where], bins)
        coef = robust_poly(c, centre, cnt, degree=2)
        kk = np.clip(key, c[0], c[-1])
        dz = z - np.polyval(coef, kk)
        c2, spread, cnt2 = _binned_median(keys, np.abs(dz.ravel()[where]), bins)
        log_spread = np.log(np.maximum(spread * 1.4826, 1.0))
        coef2 = robust_poly(c2, log_spread, cnt2, degree=2)
        top = _inlier_range(coef2, c2, log_spread)[1]
        s = np.exp(np.clip(np.polyval(coef2, np.clip(key, c2[0], c2[-1])), 0.0, top))
        stat = np.where(has, (dz / s) ** 2, 0.0).sum(axis=-1)
        hit = stat > chi2_thresholds(nc, p_fa / (m * m))[has.sum(axis=-1)]
        out |= expand(hit, (m, m), (h, w))
    return out


def region_mean(r: np.ndarray, pos: np.ndarray, nc: int, scales: tuple[int, ...]) -> np.ndarray:
    """Per cell of ``(H, W * nc)`` samples, the mean of ``r`` over ``pos`` in the ``m x m``
    region around it (grid regions as in :func:`region_shifts`) with the largest magnitude
    over ``scales`` (0 where none is measured)."""
    h, w = r.shape[0], r.shape[1] // nc
    best = np.zeros((h, w), np.float32)
    rr, pp = np.where(pos, r, 0.0).astype(np.float32), pos.astype(np.float32)
    for m in scales:
        if h < m or w < m:
            continue
        mean = cell_sums(cell_sums(rr, 1, nc), m, m) / np.maximum(cell_sums(cell_sums(pp, 1, nc), m, m), 1)
        full = expand(mean.astype(np.float32), (m, m), (h, w))
        best = np.where(np.abs(full) > np.abs(best), full, best)
    return best


def clean(mask: np.ndarray, min_cells: int) -> np.ndarray:
    """Morphological clean-up of a rejection mask: an opening and the removal of
    connected regions smaller than ``min_cells`` (isolated false alarms, and the sparse
    ones along edges, go; a moving object is a large connected region), then a dilation by
    two cells (its soft edge is covered).  ``mask``: ``(h, w)`` bool; returns the same."""
    from scipy import ndimage  # deghosting only: not on a plain merge's start-up
    st = ndimage.generate_binary_structure(2, 1)
    out = ndimage.binary_opening(mask, st, iterations=1)
    if min_cells > 1 and out.any():
        labels, n = ndimage.label(out, st)
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        big = sizes >= min_cells
        big[0] = False
        out = big[labels]
    return ndimage.binary_dilation(out, st, iterations=2)


def expand(cells: np.ndarray, cell: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """Cell decisions back to samples ``shape`` (partial cells at the edges take their
    neighbour's decision)."""
    full = np.repeat(np.repeat(cells, cell[0], axis=0), cell[1], axis=1)
    pad = ((0, shape[0] - full.shape[0]), (0, shape[1] - full.shape[1]))
    return np.pad(full, pad, mode="edge") if any(p[1] for p in pad) else full


def min_blob(min_px: float, block_px: float) -> int:
    """An area of ``min_px`` pixels in blocks of ``block_px`` pixels a side (at least 8)."""
    return max(8, int(round(min_px / block_px**2)))


def feather(mask: np.ndarray, sigma: float) -> np.ndarray:
    """A soft mask in [0, 1] (float32): the region grown by ``3 sigma`` and blurred by a
    Gaussian of ``sigma`` (at least Phi(3) = 0.9987 on the region itself, falling smoothly
    to 0 about ``5 sigma`` outside it).  Weights ``w (1 - m)`` then fade a frame out over a
    moving object instead of cutting it off.  The region sits well inside the plateau: a
    frame whose weight is 10x the anchor's (a longer exposure) still shows through a mask
    of 0.98 by a sixth."""
    from scipy import ndimage  # deghosting only: not on a plain merge's start-up
    if not mask.any():
        return np.zeros(mask.shape, np.float32)
    grow = int(np.ceil(3 * sigma))
    st = ndimage.generate_binary_structure(2, 2)
    wide = ndimage.binary_dilation(mask, st, iterations=grow) if grow else mask
    soft = ndimage.gaussian_filter(wide.astype(np.float32), sigma, mode="nearest")
    return np.maximum(soft, mask, dtype=np.float32)


# ------------------------------------------------------------------------------ decisions
class Blocks(NamedTuple):
    """One frame's block estimates, each ``(h, w, C)``: ``x`` float32 readings, ``s`` their
    variance, ``ok`` bool (every sample of the block measures), ``bound`` float32 (> 0: the
    x below which an all-dark block lies, < 0: minus the x above which an all-clipped one
    lies, 0 elsewhere; :func:`block_statistics`), ``steady`` bool (the blocks the tone
    match and the region test may read: for linear data those with no truncated reading)."""

    x: np.ndarray
    s: np.ndarray
    ok: np.ndarray
    bound: np.ndarray
    steady: np.ndarray


@dataclass
class Anchor:
    """What every frame is tested against (:func:`build_anchor`), ``(h, w, C)`` per block
    unless noted: the anchor's readings ``x``, variances ``s``, ``valid`` and ``steady``
    blocks; ``source`` (int16) the frame each block is read from (-1: none); the reference's
    ``bound`` and, for linear data, its variance ``s_bound``; per frame (``{k: (h, w)
    bool}``) its ``clipped`` blocks and the blocks ``beyond`` the reference's bound; ``level``
    ``(h, w)`` its brightest channel (inf where clipped in every frame; images); ``near``
    ``(h, w)`` its readings near white (images); ``grad2`` ``(h, w * C)`` the registration
    tolerance's variance; and the test's setting: the frames' ``exposures``, the reference
    ``ref``, the ``params``, a block's side ``block_px`` and ``lin_hi``; ``last`` the frame
    read last and ``last_blocks`` its :class:`Blocks` (its test reuses them)."""

    x: np.ndarray
    s: np.ndarray
    valid: np.ndarray
    steady: np.ndarray
    source: np.ndarray
    bound: np.ndarray
    s_bound: np.ndarray | None
    clipped: dict
    beyond: dict
    exposures: np.ndarray
    ref: int
    params: DeghostParams
    block_px: float
    lin_hi: np.ndarray | None = None
    level: np.ndarray | None = None
    near: np.ndarray | None = None
    grad2: np.ndarray | None = None
    last: int = -1
    last_blocks: Blocks | None = None


def anchor_order(exposures: np.ndarray, ref: int) -> list[int]:
    """The frames in the order the anchor takes them: the reference, then by distance in
    exposure (log ratio) from it."""
    return sorted(range(len(exposures)), key=lambda k: (k != ref, abs(np.log(exposures[k] / exposures[ref])), k))


def build_anchor(estimate: Callable[[int], Blocks], exposures: np.ndarray, ref: int, params: DeghostParams,
                 block_px: float, lin_hi: np.ndarray | None = None) -> Anchor:
    """The anchor: the reference where it measures, else the nearest frame in exposure that
    measures and is not beyond the reference's bound (:func:`violates_bound`; for images the
    dark bound adapts to each frame).  ``estimate(k)``: frame ``k``'s :class:`Blocks`, called
    once per frame; ``block_px``: a block's side in pixels; ``lin_hi``: per channel the
    linear value of :attr:`DeghostParams.shoulder_code` (images)."""
    p = params
    order = anchor_order(exposures, ref)
    a = None
    for k in order:
        blocks = estimate(k)
        x, s, ok, bound, steady = blocks
        if a is None:
            s_r = s.copy() if p.linear else None
            beyond = violates_bound(x, s, bound, p.p_fa, s_bound=s_r) & ok
            ok = ok & ~beyond
            a = Anchor(x=x, s=s, valid=ok, steady=steady & ok, source=np.where(ok, k, -1).astype(np.int16),
                       bound=bound, s_bound=s_r, clipped={}, beyond={k: beyond}, exposures=exposures, ref=ref,
                       params=p, block_px=block_px, lin_hi=lin_hi)
            a.clipped[k] = any_channel(bound < 0)
            continue
        a.clipped[k] = any_channel(bound < 0)
        a.beyond[k] = violates_bound(x, s, a.bound, p.p_fa, adapt=not p.linear, s_bound=a.s_bound) & ok
        ok = ok & ~a.beyond[k]
        take = ok & ~a.valid
        a.x[take], a.s[take], a.steady[take], a.source[take] = x[take], s[take], steady[take], k
        a.valid |= ok
        if k != order[-1]:
            del x, s, ok, bound, steady, blocks
    if not p.linear:  # what a clipped region can spread as glare: the anchor's level (unknown where clipped)
        a.level = reduce_channels(np.maximum, np.where(a.valid, a.x, np.where(a.bound < 0, np.float32(np.inf),
                                                                               np.float32(0.0))))
    if not p.envelope_reach:  # the anchor's contrast along the registration tolerance
        reg = (p.align_tolerance_px / block_px) ** 2
        a.grad2 = _samples(squared_gradient(a.x) * np.float32(reg))
    if p.shoulder_code is not None and lin_hi is not None:
        a.near = near_white(a.x, a.valid, exposures[np.maximum(a.source, 0)].astype(np.float32), lin_hi)
    a.last, a.last_blocks = order[-1], blocks
    return a


def _samples(a: np.ndarray) -> np.ndarray:
    """``(h, w, C)`` as ``(h, w * C)`` samples, channels interleaved."""
    return a.reshape(a.shape[0], -1)


def _clipped_beyond_anchor(a: Anchor, k: int, blocks: Blocks) -> np.ndarray:
    """Per block ``(h, w)`` bool: a clipped reading of frame ``k``, the longer exposure,
    that the anchor makes impossible (it measures far below the clipping level), unless
    glare from what clips in agreement with the anchor explains it (:func:`glare_excuse`:
    for linear data within blooming only, else bounded by the light glare can add)."""
    clip_bound = np.where(blocks.bound < 0, blocks.bound, np.float32(0.0))
    violated = violates_bound(a.x, a.s, clip_bound, a.params.p_fa) & a.valid
    impossible = any_channel(violated)
    need = None if a.params.linear else reduce_channels(np.maximum, np.where(violated, -clip_bound - a.x,
                                                                              np.float32(0.0)))
    impossible &= glare_excuse(a.clipped[k] & ~impossible, 1, **_glare(a, need)) == 0
    return impossible


def _glare(a: Anchor, need: np.ndarray | None) -> dict:
    """:func:`glare_excuse`'s keywords: linear data within the bloom alone; images as far as
    glare can add the light ``need`` (None: unbounded)."""
    bloom = a.params.bloom_px / a.block_px
    if a.params.linear:
        return dict(reach=bloom / max(a.x.shape[:2]))
    return {} if need is None else dict(source=a.level, need=need, bloom=bloom)


class FrameMask(NamedTuple):
    """One frame's verdict (:func:`frame_mask`): the fraction of its blocks rejected and its
    feathered mask, ``(h, w)`` uint8, 255 = dropped."""

    fraction: float
    mask: np.ndarray


def frame_mask(a: Anchor, k: int, blocks: Blocks) -> FrameMask:
    """Frame ``k`` (its :class:`Blocks`) tested against the anchor (:class:`FrameMask`).  Rejected are the cells
    :func:`inconsistent_cells` finds (excused where glare or a reading near white explains
    the sign of the change), the blocks beyond the reference's bound and, for the longer
    exposure of the pair, its clipped readings the anchor makes impossible; cleaned
    (:func:`clean`), never where the frame is the anchor, and feathered (:func:`feather`)."""
    p = a.params
    x, s, ok, _, steady = blocks
    longer = int(np.sign(np.log(a.exposures[k] / a.exposures[a.ref])))  # +1: frame k is the longer of the pair
    impossible = _clipped_beyond_anchor(a, k, blocks) if longer > 0 else np.zeros(a.clipped[k].shape, bool)
    del blocks
    brighter = (reduce_channels(np.maximum, np.where(ok & a.valid, x - a.x, np.float32(0.0)))
                if longer > 0 and not p.linear else None)
    glare = _glare(a, brighter) if p.linear or longer > 0 else {}
    excuse = glare_excuse(a.clipped[k] & ~impossible if longer > 0 else a.clipped[a.ref], longer, **glare)
    if a.near is not None:
        frame_near = near_white(x, ok, np.float32(a.exposures[k]), a.lin_hi)
        excuse = either_excuse(excuse, shoulder_excuse(a.near, frame_near))
    bad = inconsistent_cells(_samples(x), _samples(s), _samples(ok), _samples(a.x), _samples(a.s),
                             _samples(a.valid), a.grad2, x.shape[-1], p, excuse=excuse,
                             steady=_samples(steady & a.steady) if p.linear else None)
    bad |= any_channel(a.beyond.pop(k)) | impossible
    del x, s, ok, steady
    bad = clean(bad, min_blob(p.min_blob_px, a.block_px))
    own = any_channel(a.source == k)  # the anchor itself stays
    bad &= ~own
    soft = feather(bad, max(1.5, p.feather_px / a.block_px))
    soft[own] = 0.0
    return FrameMask(float(bad.mean()), np.rint(soft * 255).astype(np.uint8))


class GhostMasks(NamedTuple):
    """What :func:`ghost_masks` finds: per frame (in order) its :class:`FrameMask`; the side
    of a block in cells of the frames' planes (:func:`block_size`) and the pixels per cell
    side (a mosaic's period, 1 for an image)."""

    frames: list[FrameMask]
    block: int
    per_px: int


def ghost_masks(codes_of: Callable[[int], np.ndarray], lin: list[np.ndarray], black: list[np.ndarray],
                white: list[np.ndarray], exposures: np.ndarray, noise: list[NoiseParams] | None, pattern: np.ndarray,
                size: tuple[int, int], ref: int, params: DeghostParams,
                lin_hi: np.ndarray | None = None) -> GhostMasks:
    """Every frame's :func:`frame_mask` against one anchor (:func:`build_anchor`), in frame
    order.  Per frame ``k``: ``codes_of(k)`` its codes (``(H, W)`` mosaic or ``(H, W, C)``
    image, ``size = (H, W)``), ``lin[k]`` the response's inverse at each code ``(C, N)``,
    ``black[k]``, ``white[k]`` ``(C,)`` and ``exposures[k]``, tabulated once
    (:func:`frame_tables`, ``noise`` per channel or None); ``pattern``: the table row of each
    sample (a mosaic's CFA cell, an image's channels); ``ref``: the reference frame;
    ``lin_hi``: per channel the linear value of :attr:`DeghostParams.shoulder_code`
    (images).  ``codes_of(k)`` is called twice per frame (for the anchor, then for the test;
    once for the anchor's last frame), so that only the anchor's estimates are held; two
    frames are tested at a time where blocks are larger than a cell (one's test beside the
    other's estimates; with blocks of one cell a test's temporaries are as large as the
    frame's samples)."""
    per_px = pattern.shape[0]  # pixels per cell side of the planes
    b = block_size(size[0] // per_px, size[1] // per_px)
    tables = [frame_tables(t, lo, hi, e, noise, params.linear) for t, lo, hi, e in zip(lin, black, white, exposures)]
    rows = [int(r) for r in pattern.ravel()]  # the table row of each plane (:func:`_block_estimates`)
    one_at_a_time = threading.Lock()  # Numba's workqueue layer runs one parallel kernel at a time

    def estimate(k: int) -> Blocks:
        by_plane = [tables[k][r] for r in rows]
        with one_at_a_time:
            blocks = _block_estimates(codes_of(k), pattern, by_plane, b)
        if params.linear:
            blocks = blocks._replace(steady=_untruncated(blocks, by_plane, b) & blocks.ok)
        return blocks

    anchor = build_anchor(estimate, exposures, ref, params, b * per_px, lin_hi)
    last, blocks = anchor.last, anchor.last_blocks
    anchor.last_blocks = None  # handed over: its memory goes with its test

    def test(k: int, blocks: Blocks | None = None) -> FrameMask:
        return frame_mask(anchor, k, blocks if blocks is not None else estimate(k))

    with ThreadPoolExecutor(2 if b > 1 else 1) as pool:
        jobs = {last: pool.submit(test, last, blocks)}
        del blocks
        jobs.update({k: pool.submit(test, k) for k in range(len(exposures)) if k not in jobs})
        return GhostMasks([jobs[k].result() for k in range(len(exposures))], b, per_px)
