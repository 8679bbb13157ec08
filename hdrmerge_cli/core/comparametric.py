"""Exposures measured on the frames themselves, and the checks that read real frames.

Labels (EXIF ExposureTime, ``--times``) are often rounded or wrong: a camera that hit
its shortest shutter speed, a hand-typed list, a film scan with published times.  The
relative exposure of two frames of a static scene is in the pixels both measure: for a
linear signal ``y = h E`` (eq. (1) without noise) the comparametric relation of the pair
is ``y_b = (h_b / h_a) y_a`` (Mann & Picard 1995; Mann 2000, "Comparametric equations"),
so one ratio per neighbour pair, chained from a reference frame, gives every exposure up
to the reference's label.  This is the pairwise method of Hanji & Mantiuk's HDRutils
(``estimate_exposures(method='pairwise', solver='wls')``: weighted least squares of
``log y_b - log y_a`` with inverse-variance weights ``1 / (1/y_a + 1/y_b)`` and 3-sigma
outlier rejection, Cerman & Hlavac 2006), made robust here by a median/MAD start.

A hand-held bracket merged without alignment breaks the premise (the same pixels in both
frames): a pair's ratio is then read across edges that moved, and a label can look wrong
when only the camera moved.  Before a label is called wrong, the pairs its estimate chains
through are registered on the same samples (:func:`~hdrmerge_cli.core.samples.moved_pairs`, OpenCV through
:mod:`hdrmerge_cli.core.registration`); past :func:`~hdrmerge_cli.core.samples.moved_threshold_px` the label is reported as
unchecked instead.

Everything here is pure array code: no paths, no printing.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: fewest pixels both frames must measure for a pair's ratio to count as measured
MIN_RATIO_PIXELS = 200
#: a label more than this many EV from its estimate is reported (1/3 EV, a camera's step)
LABEL_TOLERANCE_EV = 1.0 / 3.0
#: the order check fails when more than this fraction of the pixels that changed got darker
ORDER_DOWN_FRACTION = 0.75
#: a pair measured on less than this fraction of the frame (a lamp, a window) leans on
#: the ends of the response: the labels its ratio decides are not measured
WEAK_COVERAGE = 0.05
#: a label is called wrong only when its difference from the estimate exceeds this many
#: standard errors of the estimate (as well as the tolerance)
LABEL_SIGMAS = 3.0
#: ... and at least this many pixels changed by more than the margin
ORDER_MIN_CHANGED = 100


# ---------------------------------------------------------------- constant borders
def constant_border(codes: list[np.ndarray], tol: float, max_fraction: float = 0.25) -> tuple[int, int, int, int]:
    """Rows and columns at the edges of the frames that are constant in every frame
    (scan borders, letterboxing, a lens hood's black): ``(top, bottom, left, right)``
    counts of lines to drop.

    A line counts as constant when, in every frame and channel, the spread of its codes
    (95th minus 5th percentile) is at most ``tol``; lines are taken from each edge inward
    until the first textured one, at most ``max_fraction`` of the size per side.  Lines
    constant in every frame carry no exposure information (their codes do not follow the
    exposure), and they fool statistics of whole frames such as the mean code.

    codes : P arrays (H, W) or (H, W, C), one per frame (same shape)
    """
    h, w = codes[0].shape[:2]

    def spread(axis: int) -> np.ndarray:  # largest line spread over frames and channels, per line
        out = None
        for z in codes:
            z3 = z.reshape(h, w, -1).astype(np.float32)
            lo, hi = np.percentile(z3, [5, 95], axis=axis)  # (lines, C)
            s = np.max(hi - lo, axis=-1)
            out = s if out is None else np.maximum(out, s)
        return out

    def run(flat: np.ndarray, limit: int) -> int:
        n = 0
        while n < limit and flat[n]:
            n += 1
        return n

    rows = spread(1) <= tol  # (H,)
    cols = spread(0) <= tol  # (W,)
    mh, mw = int(h * max_fraction), int(w * max_fraction)
    return run(rows, mh), run(rows[::-1], mh), run(cols, mw), run(cols[::-1], mw)


def border_mask(shape: tuple[int, int], border: tuple[int, int, int, int]) -> np.ndarray:
    """(H, W) bool: True inside the frame, False on the border lines of :func:`constant_border`."""
    top, bottom, left, right = border
    m = np.zeros(shape[:2], dtype=bool)
    m[top:shape[0] - bottom, left:shape[1] - right] = True
    return m


# ---------------------------------------------------------------- order check
@dataclass
class OrderTest:
    """Sign test of a neighbour pair: of the pixels both frames measure, how many got
    brighter (``up``) and darker (``down``) by more than the noise margin in the frame
    labelled longer."""

    up: int
    down: int
    usable: int

    @property
    def down_fraction(self) -> float:
        return self.down / max(1, self.up + self.down)

    @property
    def disordered(self) -> bool:
        """The longer-labelled frame is darker on most changed pixels: a monotone response
        cannot do that, so the labels (or the files) are out of order.  Frames at the noise
        floor or of equal exposure change both ways about equally and pass."""
        return self.up + self.down >= ORDER_MIN_CHANGED and self.down_fraction > ORDER_DOWN_FRACTION


def order_test(z_short: np.ndarray, z_long: np.ndarray, usable: np.ndarray, margin: float) -> OrderTest:
    """The sign test of :class:`OrderTest` on code values (any monotone response keeps the
    sign of a change, so no response is needed; Wilcoxon-style sign test on the pixels that
    neither frame clips, borders excluded).

    z_short, z_long : codes of the frames labelled shorter and longer (same shape)
    usable : bool mask of the samples to compare; margin : changes of at most this are noise
    """
    d = z_long[usable].astype(np.float32) - z_short[usable].astype(np.float32)
    return OrderTest(int(np.count_nonzero(d > margin)), int(np.count_nonzero(d < -margin)), int(d.size))


# ---------------------------------------------------------------- ratio estimate
@dataclass
class PairRatio:
    """``log(h_long / h_short)`` of a neighbour pair measured on its pixels (natural log),
    with the standard error and spread of the per-pixel log ratios kept, and how many
    pixels were used and kept."""

    log_ratio: float
    stderr: float
    spread: float
    pixels: int
    kept: int
    coverage: float = 1.0  # fraction of the frame's samples both frames expose well
    moved: bool = False  # the frames moved between the two exposures: the ratio is not used
    trend: float = 0.0  # how much the per-pixel log ratio changes over the pair's brightness range

    @property
    def counted(self) -> bool:
        """Enough pixels kept for a ratio."""
        return self.kept >= MIN_RATIO_PIXELS and bool(np.isfinite(self.log_ratio))

    @property
    def measured(self) -> bool:
        """A ratio the estimates use: counted, and the frames did not move."""
        return self.counted and not self.moved


def robust_log_ratio(y_short: np.ndarray, y_long: np.ndarray, k: float = 3.0, iterations: int = 10,
                     max_pixels: int = 1 << 17, tiles: np.ndarray | None = None) -> PairRatio:
    """Comparametric exposure ratio of two linearised frames: ``log(h_b/h_a)`` from
    ``d_i = log y_b,i - log y_a,i`` over pixels both measure.

    Start at the median of ``d`` with the MAD scale (``s = 1.4826 MAD``), then iterate the
    weighted mean of the pixels within ``k s`` of the current estimate, weights
    ``1 / (1/y_a + 1/y_b)`` (the inverse variance of ``d`` under photon noise, as HDRutils'
    ``wls`` solver; Hanji & Mantiuk 2020), re-estimating ``s`` on the kept pixels, until the
    kept set stops changing (Cerman & Hlavac 2006's iterated 3-sigma rejection, started
    robustly).  Pixels off the comparametric line (motion, edges that moved, flare,
    a clipped channel's processing) fall out; the scale has a floor of 0.005 so that
    quantised data keep their neighbours.

    The standard error is honest about neighbouring pixels sharing their errors (the
    response's misfit, the camera's processing, motion): with ``tiles``, the cluster-robust
    (sandwich) variance of the weighted mean over the spatial tiles,
    ``T / (T - 1) sum_t (sum_{i in t} w_i (d_i - m))^2 / (sum w)^2`` (Liang and Zeger 1986),
    never below the independent-pixel one; without, the pixels are taken as independent.

    y_short, y_long : 1-D positive linear values of the same pixels in both frames (an even
    subsample of at most ``max_pixels`` of them is used)
    tiles : 1-D int, the spatial tile of each pixel (the same length), or None
    """
    ok = (y_short > 0) & (y_long > 0) & np.isfinite(y_short) & np.isfinite(y_long)
    a, b = y_short[ok], y_long[ok]
    n = int(a.size)
    step = max(1, -(-n // max_pixels))  # an even subsample of at most max_pixels
    a, b = a[::step].astype(np.float64), b[::step].astype(np.float64)
    tiles = None if tiles is None else tiles[ok][::step]
    if n == 0:
        return PairRatio(float("nan"), float("inf"), float("nan"), 0, 0)
    d = np.log(b) - np.log(a)
    w = 1.0 / (1.0 / a + 1.0 / b)
    m = float(np.median(d))
    s = max(1.4826 * float(np.median(np.abs(d - m))), 0.005)
    keep = np.abs(d - m) <= k * s
    for _ in range(iterations):
        if not np.any(keep):
            break
        m = float(np.sum(w[keep] * d[keep]) / np.sum(w[keep]))
        s = max(1.4826 * float(np.median(np.abs(d[keep] - m))), 0.005)
        new = np.abs(d - m) <= k * s
        if np.array_equal(new, keep):
            break
        keep = new
    kept = int(np.count_nonzero(keep))
    if kept == 0:
        return PairRatio(float("nan"), float("inf"), s, n, 0)
    wk = w[keep]
    n_eff = float(np.sum(wk) ** 2 / np.sum(wk**2))
    spread = float(np.sqrt(np.sum(wk * (d[keep] - m) ** 2) / np.sum(wk)))
    stderr = spread / np.sqrt(max(n_eff, 1.0))
    if tiles is not None:
        stderr = max(stderr, cluster_stderr(wk * (d[keep] - m), tiles[keep], float(np.sum(wk))))
    return PairRatio(m, stderr, spread, n, kept, trend=ratio_trend(a[keep], d[keep], wk))


def cluster_stderr(scores: np.ndarray, tiles: np.ndarray, total_weight: float) -> float:
    """The cluster-robust standard error of a weighted mean from its per-pixel scores
    ``w_i (d_i - m)`` grouped by ``tiles``: ``sqrt(T / (T - 1) sum_t S_t^2) / sum w``,
    ``S_t`` the scores' sum in tile ``t`` of the ``T`` tiles holding any; infinite with
    fewer than two tiles (one tile cannot tell its error from the others')."""
    ids, inverse = np.unique(tiles, return_inverse=True)
    if ids.size < 2:
        return float("inf")
    sums = np.bincount(inverse, weights=scores)
    return float(np.sqrt(ids.size / (ids.size - 1) * np.sum(sums**2)) / total_weight)


def ratio_trend(y: np.ndarray, d: np.ndarray, w: np.ndarray) -> float:
    """How much the per-pixel log ratios ``d`` change with brightness: the weighted least-
    squares slope of ``d`` on ``log y`` times the span of ``log y`` (5th to 95th
    percentile), natural log units.  Through the right response every pixel's log ratio is
    the one constant ``log(h_b / h_a)`` of (3)/(35), so a wrong exposure label moves every
    ratio alike (no trend); a response that does not fit the frames bends them with
    brightness."""
    if y.size < 3:
        return 0.0
    u = np.log(y)
    um = np.sum(w * u) / np.sum(w)
    var = np.sum(w * (u - um) ** 2)
    if var <= 0:
        return 0.0
    slope = np.sum(w * (u - um) * d) / var
    lo, hi = np.percentile(u, [5, 95])
    return float(slope * (hi - lo))


def chain_pairs(k: int, reference: int) -> range:
    """The neighbour pairs (pair ``j``: frames ``j`` and ``j + 1``) that :func:`chain_exposures`
    chains frame ``k``'s estimate through from the reference's."""
    return range(min(k, reference), max(k, reference))


def chain_exposures(log_label: np.ndarray, pairs: list[PairRatio]) -> np.ndarray:
    """``log h`` of every frame (up to a common offset, the first frame at 0) from the
    neighbour ratios: ``log h_k = log h_{k-1} + r_k``, where an unmeasured pair (too few
    pixels both frames measure: a frame at the noise floor) keeps its labels' ratio.

    log_label : (P,) labelled ``log h``; pairs : P - 1 ratios of frames (k-1, k)
    """
    out = np.zeros(len(log_label))
    for k, p in enumerate(pairs, 1):
        step = p.log_ratio if p.measured else log_label[k] - log_label[k - 1]
        out[k] = out[k - 1] + step
    return out


def fit_to_labels(log_est: np.ndarray, log_label: np.ndarray, free_slope: bool,
                  slope_range: tuple[float, float] = (0.5, 2.0)) -> tuple[float, float, int]:
    """Place chained estimates on the labels' scale: ``log_label ~ a + b log_est`` by
    least median of squares (Rousseeuw 1984; breakdown 50 %: a run of wrong labels shorter
    than half the bracket cannot move it), then refined by least squares on the frames
    within :data:`LABEL_TOLERANCE_EV` of the line.

    ``b = 1`` unless ``free_slope``: a linear signal (RAW, a verified response) leaves only
    the offset free, which is the reference frame's label; with an unverified response
    (sRGB assumed) the estimated log ratios are scaled by the mismatch of the true and
    assumed responses (for a power-law mismatch exactly ``b``), so the slope is fitted too,
    within ``slope_range``, and only with four frames or more.
    Returns ``(a, b, reference)``: the reference is the frame nearest the line (ties: the
    middle frame), whose label gives the absolute scale.
    """
    n = len(log_est)
    tol = LABEL_TOLERANCE_EV * np.log(2.0)
    mid = (n - 1) / 2
    candidates = [(float(log_label[r] - log_est[r]), 1.0) for r in range(n)]
    if free_slope and n >= 4:
        for i in range(n):
            for j in range(i + 1, n):
                if abs(log_est[j] - log_est[i]) > 1e-6:
                    b = float((log_label[j] - log_label[i]) / (log_est[j] - log_est[i]))
                    if slope_range[0] <= b <= slope_range[1]:
                        candidates.append((float(log_label[i] - b * log_est[i]), b))
    best = min(candidates, key=lambda ab: (float(np.median(np.abs(log_label - ab[0] - ab[1] * log_est))),
                                           abs(ab[1] - 1.0)))
    a, b = best
    inl = np.abs(log_label - a - b * log_est) <= tol
    if np.count_nonzero(inl) >= (2 if free_slope and n >= 4 else 1):
        if free_slope and n >= 4 and np.ptp(log_est[inl]) > 1e-6:
            b_ls, a_ls = np.polyfit(log_est[inl], log_label[inl], 1)
            if slope_range[0] <= b_ls <= slope_range[1]:
                a, b = float(a_ls), float(b_ls)
        else:
            a = float(np.mean(log_label[inl] - b * log_est[inl]))
    res = np.abs(log_label - a - b * log_est)
    ref = int(min(range(n), key=lambda r: (round(float(res[r]), 9), abs(r - mid))))
    return a, b, ref


@dataclass
class ExposureEstimate:
    """Exposures of a bracket measured on its frames, on the labels' scale.

    log_h : (P,) estimated ``log h`` (natural log), anchored at the reference's label
    difference_ev : (P,) label minus estimate, in EV (log2); positive: labelled too long
    model_slope : where the response is a model (sRGB, gamma) checked against a fit on the
        bracket, the slope of the estimates read through the model itself against the
        labels (1 where the model reads the frames' ratios right); else None
    """

    log_h: np.ndarray
    difference_ev: np.ndarray
    pairs: list[PairRatio]
    reference: int
    slope: float
    model_slope: float | None = None

    def stderr_ev(self) -> np.ndarray:
        """Per frame: the standard error of its estimate (EV), the pair ratios' errors summed
        in quadrature along the pairs it chains through from the reference (0 for the
        reference)."""
        return np.array([np.sqrt(sum(self.pairs[j].stderr ** 2 for j in chain_pairs(k, self.reference))) / np.log(2)
                         for k in range(len(self.difference_ev))])

    def share(self) -> np.ndarray:
        """Per frame: the smallest share of the frame both frames of a pair expose well,
        along the pairs its estimate chains through (1 for the reference)."""
        return np.array([min((self.pairs[j].coverage for j in chain_pairs(k, self.reference)), default=1.0)
                         for k in range(len(self.difference_ev))])

    def measured(self) -> np.ndarray:
        """Per frame: whether its estimate is measured: every pair it chains through has a
        ratio (:attr:`PairRatio.measured`) on at least :data:`WEAK_COVERAGE` of the frame."""
        share = self.share()
        return np.array([all(self.pairs[j].measured for j in chain_pairs(k, self.reference))
                         and share[k] >= WEAK_COVERAGE for k in range(len(self.difference_ev))])

    def mislabelled(self, tol_ev: float = LABEL_TOLERANCE_EV) -> list[int]:
        """The frames whose label is off: the estimate is measured (:meth:`measured`) and
        differs from the label by more than ``tol_ev`` (what matters) and by more than
        :data:`LABEL_SIGMAS` standard errors (what the pairs pin)."""
        se, ok = self.stderr_ev(), self.measured()
        return [k for k, d in enumerate(self.difference_ev) if ok[k] and abs(d) > max(tol_ev, LABEL_SIGMAS * se[k])]


def estimate_exposures(log_label: np.ndarray, pairs: list[PairRatio], free_slope: bool = False) -> ExposureEstimate:
    """Chain the neighbour ratios (:func:`chain_exposures`) and place them on the labels'
    scale (:func:`fit_to_labels`): the reference frame keeps its label, every other frame
    gets ``exp(a + b log h_chained)``, and the difference of each label from its estimate.

    log_label : (P,) labelled ``log h`` in increasing order; pairs : P - 1 neighbour ratios
    """
    log_label = np.asarray(log_label, dtype=np.float64)
    chained = chain_exposures(log_label, pairs)
    a, b, ref = fit_to_labels(chained, log_label, free_slope)
    log_h = a + b * chained
    log_h += log_label[ref] - log_h[ref]  # the reference's label exactly
    diff = (log_label - log_h) / np.log(2.0)
    return ExposureEstimate(log_h, diff, pairs, ref, b)


# ---------------------------------------------------------------- quick response
def comparagram(z_a: np.ndarray, z_b: np.ndarray, levels: int) -> np.ndarray:
    """Joint histogram ``J[i, j]`` of the knot codes of the same pixels in two frames
    (Mann 2000's comparagram; the data of the paper's (36)-(37))."""
    return np.bincount(z_a.astype(np.int64).ravel() * levels + z_b.astype(np.int64).ravel(),
                       minlength=levels * levels).reshape(levels, levels).astype(np.float64)


def response_from_comparagrams(grams: list[np.ndarray], log_ratios: np.ndarray, smoothing: float = 1.0) -> np.ndarray:
    """``g = log gamma^-1`` on ``L`` knots from the comparagrams of neighbour pairs and their
    log exposure ratios: weighted least squares of ``g(j) - g(i) = log(h_b / h_a)`` over
    the cells of each comparagram (weight: the cell's count times the hat weights of both
    codes, Debevec-Malik's ``w(z)``; clipped codes 0 and L-1 left out), plus
    ``smoothing`` times the second differences of ``g`` (scaled to the data's total weight)
    and ``g(L/2) = 0``: the paper's (36) without its monotonicity constraints, solved in
    closed form through the ``L x L`` normal equations (no per-pixel unknowns, so it costs
    one histogram per pair).  Not made monotone here.

    grams : comparagrams ``(L, L)`` of the pairs; log_ratios : their ``log(h_b / h_a)``
    """
    levels = grams[0].shape[0]
    hat = np.minimum(np.arange(levels), levels - 1 - np.arange(levels)).astype(np.float64)
    hat /= max(hat.max(), 1.0)
    ata = np.zeros((levels, levels))
    atb = np.zeros(levels)
    total = 0.0
    for j_ab, d in zip(grams, log_ratios):
        w = j_ab * hat[:, None] * hat[None, :]
        rs, cs = w.sum(axis=1), w.sum(axis=0)
        ata += np.diag(rs + cs) - w - w.T
        atb += d * (cs - rs)
        total += float(w.sum())
    lam = smoothing * max(total, 1.0) / levels
    dd = np.zeros((levels - 2, levels))
    idx = np.arange(levels - 2)
    dd[idx, idx], dd[idx, idx + 1], dd[idx, idx + 2] = 1.0, -2.0, 1.0
    ata += lam * dd.T @ dd
    mid = levels // 2
    ata[mid, mid] += max(total, 1.0)  # g(mid) = 0
    return np.linalg.solve(ata, atb)


def _subsample_index(n: int, step: int, mosaic: bool) -> np.ndarray:
    idx = np.arange(n)
    return idx[(idx // 2) % step == 0] if mosaic else idx[::step]


def normalised_samples(codes: np.ndarray, black, white, step: int = 1, cell: np.ndarray | None = None) -> np.ndarray:
    """``v = (z - black) / (white - black)`` of a frame's codes, float32, every ``step``-th
    row and column: an image's ``(H, W, C)`` codes with ``(C,)`` levels, ``(H', W', C)``; a
    mosaic's ``(H, W)`` codes in whole 2 x 2 cells (every ``step``-th cell), each site with
    the levels of its colour index in ``cell`` (2 x 2; None: the first), ``(H', W', 1)``."""
    mosaic = codes.ndim == 2
    ys = _subsample_index(codes.shape[0], step, mosaic)
    xs = _subsample_index(codes.shape[1], step, mosaic)
    z = codes[np.ix_(ys, xs)].astype(np.float32)
    black = np.asarray(black, dtype=np.float32)
    white = np.asarray(white, dtype=np.float32)
    if mosaic:
        c = cell[(ys % 2)[:, None], (xs % 2)[None, :]] if cell is not None else np.zeros((len(ys), len(xs)), np.intp)
        return ((z - black[c]) / (white[c] - black[c]))[..., None]
    return (z - black[: z.shape[-1]]) / (white[: z.shape[-1]] - black[: z.shape[-1]])
