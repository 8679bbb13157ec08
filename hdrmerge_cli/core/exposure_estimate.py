"""Exposures measured on the bracket's samples, and the checks that read them.

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

On the one sample set (:class:`~hdrmerge_cli.core.samples.Samples`, whose order is checked
there): the neighbour pairs' ratios through a response (:func:`measure_pairs`,
:func:`robust_log_ratio`), the exposures chained from them (:func:`estimate`,
:func:`estimate_exposures`), a quick response fitted on the samples when the one in use is
only assumed (:func:`quick_response`, :func:`estimate_with_response`), and whether the
response or a label explains a frame's difference from its label (:func:`label_at_fault`,
:func:`response_fits`).  The response stage, the exposures stage and ``info`` read them.

A hand-held bracket merged without alignment breaks the premise (the same pixels in both
frames): a pair's ratio is then read across edges that moved, and a label can look wrong
when only the camera moved.  Before a label is called wrong, the pairs its estimate chains
through are registered on the same samples (:func:`~hdrmerge_cli.core.registration.moved_pairs`, OpenCV through
:mod:`hdrmerge_cli.core.registration`); past :func:`~hdrmerge_cli.core.registration.moved_threshold_px` the label is reported as
unchecked instead.

Everything here is pure array code: no paths, no printing.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.registration import Motion, block_mean, moved_pairs, warp_motion
from hdrmerge_cli.core.samples import (
    MIN_RATIO_PIXELS, RANGE_LINEAR, RANGE_UNVERIFIED, RANGE_VERIFIED, Samples,
)

#: a label more than this many EV from its estimate is reported (1/3 EV, a camera's step)
LABEL_TOLERANCE_EV = 1.0 / 3.0
#: a pair measured on less than this fraction of the frame (a lamp, a window) leans on
#: the ends of the response: the labels its ratio decides are not measured
WEAK_COVERAGE = 0.05
#: a label is called wrong only when its difference from the estimate exceeds this many
#: standard errors of the estimate (as well as the tolerance)
LABEL_SIGMAS = 3.0


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


def crf_verified(crf: CRF) -> bool:
    """Linear data and measured response tables (a profile's, a CSV, one fitted on the
    bracket) are trusted; a model (sRGB or ``gamma:G``, assumed for want of a response or
    named by the user) is not: it is a guess at this camera's curve, so its ratios are read
    in the mid range, up to a power, and a label is judged only where the bracket's own
    fitted response agrees."""
    return crf.is_linear or (crf.table is not None and not crf.assumed)


def usable_range(crf: CRF) -> tuple[float, float]:
    return RANGE_LINEAR if crf.is_linear else RANGE_VERIFIED if crf_verified(crf) else RANGE_UNVERIFIED


def linearise(v: np.ndarray, crf: CRF, codes_step: float) -> np.ndarray:
    """``g(v)``, the inverse response of normalised codes ``v`` (``(..., C)``, full scale 1,
    clipped to [0, 1]) per channel; ``v`` itself for a linear response.  Where ``v`` holds
    whole codes (``codes_step``: one code as a fraction of full scale, at most 2^16 codes)
    through :meth:`CRF.linear` in float32, else evaluated per value."""
    vc = np.clip(v, 0.0, 1.0)
    if crf.is_linear:
        return vc
    n = int(round(1.0 / codes_step)) + 1
    if n > 1 << 16:
        return np.stack([crf.inverse(vc[..., c], c) for c in range(v.shape[-1])], -1)
    return crf.linear(np.rint(vc * (n - 1)).astype(np.int64), n).astype(np.float32)


def measure_pairs(s: Samples, crf: CRF, value_range: tuple[float, float] | None = None) -> list[PairRatio]:
    """:func:`robust_log_ratio` of every neighbour pair, on the
    pixels both frames expose well: ``v`` within ``value_range`` (default by the response,
    :func:`usable_range`) and above each frame's own floor, off the borders; linearised by
    ``crf`` per channel (RAW: ``v`` itself)."""
    lo, hi = value_range or usable_range(crf)
    masks, lin = [], []
    for v, floor in zip(s.v, s.floors):
        ok = (v >= np.maximum(lo, floor)) & (v <= hi) & s.inside[..., None]
        masks.append(ok)
        lin.append(linearise(v, crf, s.codes_step))
    total = max(1, int(np.count_nonzero(s.inside)) * s.v[0].shape[-1])
    tiles = s.tiles
    out = []
    for k in range(1, len(s.v)):
        both = masks[k - 1] & masks[k]
        r = robust_log_ratio(lin[k - 1][both], lin[k][both], tiles=tiles[both])
        r.coverage = int(np.count_nonzero(both)) / total
        out.append(r)
    return out


def estimate(exposures: np.ndarray, s: Samples, crf: CRF, value_range: tuple[float, float] | None = None, free_slope: bool = False,
             moved: frozenset[int] = frozenset()) -> ExposureEstimate:
    """Every frame's exposure measured on the samples (:func:`estimate_exposures` of :func:`measure_pairs`),
    on the labels' scale (the reference frame keeps its label).  The pairs in ``moved``
    (frames that moved between the exposures) are marked so: their labels' ratio is kept."""
    pairs = [replace(p, moved=True) if k in moved else p for k, p in enumerate(measure_pairs(s, crf, value_range))]
    return estimate_exposures(np.log(exposures), pairs, free_slope=free_slope or not crf_verified(crf))


# ---------------------------------------------------------------- quick response (the samples' comparagrams)
def pair_comparagram(z_a: np.ndarray, z_b: np.ndarray, levels: int) -> np.ndarray:
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


def quick_response(exposures: np.ndarray, s: Samples, skip: frozenset[int] = frozenset()) -> CRF:
    """An image bracket's inverse response fitted on its samples' knot codes
    (:attr:`~hdrmerge_cli.core.samples.Samples.knots`, constant borders off) with the given
    exposures, per channel, from the neighbour pairs' comparagrams
    (:func:`response_from_comparagrams`), interpolated from the knots to every code as
    :func:`~hdrmerge_cli.core.crf_goossens2012.from_knots` does: the check's own response
    when the one in use is an unverified model (sRGB assumed), whose ratios are off by up to
    a stop on real cameras' tone curves.  Pairs in ``skip`` (frames that moved) are left out
    while others remain."""
    from hdrmerge_cli.core.crf import table_crf
    from hdrmerge_cli.core.crf_estimate import inverse_from_log

    (codes, levels), n = s.knots, s.levels[2]
    at_codes = np.arange(levels) * ((n - 1) / (levels - 1))  # the knots' codes
    log_r = np.diff(np.log(exposures))
    used = [k for k in range(1, len(codes)) if k - 1 not in skip] or list(range(1, len(codes)))
    tables = []
    for ch in range(codes[0].shape[-1]):
        grams = [pair_comparagram(codes[k - 1][:, ch], codes[k][:, ch], levels) for k in used]
        g_knots = response_from_comparagrams(grams, log_r[[k - 1 for k in used]])
        tables.append(inverse_from_log(np.interp(np.arange(n), at_codes, g_knots))[0])
    return table_crf(np.stack(tables), "fitted on the bracket")


def estimate_with_response(exposures: np.ndarray, s: Samples, crf: CRF, rounds: int = 1,
                           moved: frozenset[int] = frozenset()) -> tuple[ExposureEstimate, CRF]:
    """:func:`estimate` through ``crf`` when it is trusted (linear, a measured table);
    otherwise through a response fitted on the bracket
    (:func:`quick_response`), jointly:
    fit with the labels, estimate, refit with the estimates, ``rounds`` times.  Pairs in
    ``moved`` are not used (their labels' ratio is kept)."""
    if crf_verified(crf):
        return estimate(exposures, s, crf, moved=moved), crf
    h = np.asarray(exposures, dtype=np.float64)
    for _ in range(rounds):  # fitted with the labels, then with the estimates
        fitted = quick_response(h, s, moved)  # its least squares shrink the ratios a little: slope fitted
        est = estimate(exposures, s, fitted, free_slope=True, moved=moved)
        h = np.exp(est.log_h)
    # a label is called wrong only where the assumed response agrees (same sign; the smaller
    # of the two differences): a fit on pairs that barely overlap, or a camera curve far
    # from the assumed one, each alone makes false alarms
    model = estimate(exposures, s, crf, moved=moved)
    assumed = model.difference_ev
    agree = np.sign(assumed) == np.sign(est.difference_ev)
    diff = np.where(agree, np.sign(assumed) * np.minimum(np.abs(assumed), np.abs(est.difference_ev)), 0.0)
    return replace(est, difference_ev=diff, model_slope=model.slope), fitted


def label_at_fault(est: ExposureEstimate, k: int) -> bool:
    """Whether frame ``k``'s difference from its label is what a wrong label makes rather
    than a response that does not fit the frame.  A wrong label moves every pixel's ratio
    alike; a wrong response (or a frame processed or lit differently) bends the ratios with
    brightness.  The label is blamed when the ratios' change over the brightness range,
    summed over the pairs frame ``k``'s estimate chains through (:func:`ratio_bend_ev`), is
    smaller than the difference itself."""
    return bool(ratio_bend_ev(est, k) < abs(est.difference_ev[k]))


def power_explains(est: ExposureEstimate, tol_ev: float = LABEL_TOLERANCE_EV) -> bool:
    """Whether the differences from the labels grow in proportion to each frame's distance
    from the reference in exposure, as a response of the wrong power makes (every ratio
    read through it is scaled alike): one slope fitted through the reference leaves every
    frame within ``tol_ev``.  Needs three frames; a single wrong label leaves at least half
    its error off such a line."""
    d = np.asarray(est.difference_ev, np.float64)
    x = (est.log_h - est.log_h[est.reference]) / np.log(2)
    if d.size < 3 or not np.any(x):
        return False
    slope = float(np.dot(x, d) / np.dot(x, x))
    return bool(np.max(np.abs(d - slope * x)) <= tol_ev)


def response_fits(est: ExposureEstimate) -> bool:
    """Whether the response in use fits the bracket: the median measured pair's ratios
    change by less than the label tolerance over their brightness range.  The response is
    common to every frame, so where it bends most pairs no label can be judged through it."""
    trends = [abs(p.trend) for p in est.pairs if p.measured]
    return not trends or float(np.median(trends)) / np.log(2) < LABEL_TOLERANCE_EV


def model_power_error_ev(est: ExposureEstimate) -> float:
    """Where the response is a model checked against the bracket's own fit
    (:func:`estimate_with_response`): how far the model's reading of the ratios puts the
    bracket's outermost frame from its label (EV), ``|slope - 1|`` times its distance from
    the reference; 0 otherwise.  A response of another power than the camera's scales
    every log ratio alike."""
    if est.model_slope is None:
        return 0.0
    span = np.abs(est.log_h - est.log_h[est.reference]) / np.log(2)
    return float(abs(est.model_slope - 1.0) * np.max(span))


def ratio_bend_ev(est: ExposureEstimate, k: int) -> float:
    """The change of the pixels' ratios over brightness (EV), summed over the pairs frame
    ``k``'s estimate chains through (:attr:`PairRatio.trend`)."""
    return sum(abs(est.pairs[j].trend) for j in chain_pairs(k, est.reference)) / np.log(2)


# ---------------------------------------------------------------- motion between exposures
def sample_plane(s: Samples, k: int, crf: CRF) -> np.ndarray:
    """Frame ``k``'s samples linearised through ``crf`` as one plane for registration (the
    channels' mean), the constant borders cut off; RAW: the mean of each 2 x 2 CFA cell."""
    top, bottom, left, right = s.border
    v = s.v[k]
    if s.raw:  # whole cells: start on an even sample row and column
        top, left = top + top % 2, left + left % 2
    v = v[top:v.shape[0] - bottom, left:v.shape[1] - right]
    lin = linearise(v, crf, s.codes_step).mean(axis=-1, dtype=np.float32)
    return block_mean(lin, 2) if s.raw else lin


# ---------------------------------------------------------------- the labels judged
class Verdict(NamedTuple):
    """What :func:`label_verdicts` blames for a frame off its label: ``kind`` one of
    ``"moved"``, ``"pair"``, ``"given"``, ``"response"``, ``"label"``; ``why``: the
    response's fault (:func:`response_at_fault`) or None; ``pair``: for ``"moved"``, the
    pair that moved most on the frame's chain."""

    kind: str
    why: str | None = None
    pair: int | None = None


def response_at_fault(est: ExposureEstimate, k: int, tol_ev: float = LABEL_TOLERANCE_EV) -> str | None:
    """Why frame ``k``'s difference from its label points at the response rather than the
    label (:func:`power_explains`, :func:`response_fits`, :func:`label_at_fault`), or None."""
    if power_explains(est, tol_ev):
        return ("the frames' differences grow with their distance in exposure from the reference frame, as a "
                "response of the wrong power makes")
    if not response_fits(est):
        return "the ratios of most frame pairs change with brightness"
    if not label_at_fault(est, k):
        return (f"its ratios change with brightness (by {ratio_bend_ev(est, k):.2f} EV from shadows to "
                "highlights)")
    return None


def label_verdicts(est: ExposureEstimate, given: list[bool], tol_ev: float = LABEL_TOLERANCE_EV,
                   motion: Motion | None = None) -> dict[int, Verdict]:
    """Per frame whose estimate is off its label (:meth:`ExposureEstimate.mislabelled`),
    what is blamed, and why: ``"moved"`` (its estimate chains through a pair that moved:
    ``motion``, :func:`moved_pairs`), ``"pair"`` (two frames:
    neither label outvotes the other), ``"given"`` (the user's time, the first suspect
    whatever the ratios say; ``given``: per frame whether its time is the user's, not its
    metadata's), ``"response"`` (the response explains the difference better
    than the label, :func:`response_at_fault`, the reason beside it) or ``"label"``.  The
    one judgement the warnings and ``--json`` both read."""
    out = {}
    for k in est.mislabelled(tol_ev):
        moved = [j for j in chain_pairs(k, est.reference) if motion is not None and j in motion.moved]
        j = max(moved, key=lambda j: motion.px[j]) if moved else None
        if j is not None:
            out[k] = Verdict("moved", None, j)
            continue
        by_user = given[k] or given[est.reference]
        why = response_at_fault(est, k, tol_ev)
        out[k] = Verdict("pair" if len(given) == 2 and (why is None or by_user) else
                         "given" if why is not None and by_user else "response" if why is not None else "label", why)
    return out


@dataclass
class LabelCheck:
    """The labels judged once (:func:`check_exposures`) on the exposures ``est`` measured: the
    pairs' ``motion`` and the :func:`label_verdicts`, which the warnings and the ``--json``
    record read; ``used``: the response the estimate read, and
    ``response`` as the record names it; ``model``: the response in use, named, and
    ``power_ev`` its power error (:func:`model_power_error_ev`)."""

    est: ExposureEstimate
    motion: Motion
    verdicts: dict[int, Verdict]
    used: CRF
    response: str
    model: str
    power_ev: float


def check_exposures(exposures: np.ndarray, s: Samples, crf: CRF, given: list[bool], use_estimates: bool = False,
                    warps: list[np.ndarray] | None = None, aligned: list[bool] | None = None, applied: bool = False,
                    size: tuple[int, int] = (0, 0)) -> LabelCheck:
    """The frames' exposures measured on the samples ``s`` through ``crf``
    (:func:`estimate_with_response`; ``use_estimates``: two rounds, and a pair that moved
    keeps its labels' ratio) and the labels judged (:func:`label_verdicts`).  With the
    merge's registration (``warps`` per frame, ``aligned``: False where a frame was left
    unaligned, ``applied``: the samples are then brought onto the reference already,
    :meth:`~hdrmerge_cli.core.samples.Samples.registered`; ``size``: the frames' height and
    width) the pairs' motion is what it measured (:func:`warp_motion`); without, every pair
    (``use_estimates``) or the pairs that decided a label in question are registered on
    the samples (``given``: per frame whether its time is the user's)."""
    est, used = estimate_with_response(exposures, s, crf, rounds=2 if use_estimates else 1)
    # the pairs registered on the samples: every pair (every estimate is used), or those that
    # decided a label in question (none: no cost); their frames' sample_plane by index
    pairs = range(len(exposures) - 1) if use_estimates else {j for k in est.mislabelled()
                                                             for j in chain_pairs(k, est.reference)}
    planes = {} if warps is not None else {k: sample_plane(s, k, crf) for k in {k for j in pairs for k in (j, j + 1)}}
    if warps is not None:  # the pairs' motion as the merge's registration measured it
        motion = warp_motion(warps, aligned, applied, size[0], size[1], s.pitch)
    else:  # the pairs registered on the samples
        motion = moved_pairs(s, exposures, planes, pairs)
    if use_estimates and motion.moved:  # a pair that moved keeps its labels' ratio
        est, used = estimate_with_response(exposures, s, crf, rounds=2, moved=motion.moved)
    verdicts = label_verdicts(est, given, motion=motion)
    name = used.describe() + ("" if crf_verified(used) else " (unverified: mid-range codes, slope fitted)")
    return LabelCheck(est, motion, verdicts, used, name, crf.describe(), model_power_error_ev(est))
