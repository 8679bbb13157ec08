"""Estimating the inverse camera response ``g(z) = log gamma^-1(z)`` from a bracket.

The relation is (3): ``g(z_ij) - log t_j = log E_i`` for every pixel i and frame j.
Methods are picked by name from :data:`CRF_ESTIMATORS`: the paper's monotone QP
(:mod:`~hdrmerge_cli.core.crf_goossens2012`) and two baselines, Debevec & Malik (1997) and
Robertson, Borman & Stevenson (2003).  Every method returns a
:class:`~hdrmerge_cli.core.crf_goossens2012.CRFFit`.  Before a fit, whether the bracket's samples
can chain a response at all (:func:`thin_overlap`) and whether pixel pairs pin it
(:func:`pairs_pin_response`), else the frames' histograms do (:func:`histogram_correspondences`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hdrmerge_cli.core.crf import CRF, table_crf
from hdrmerge_cli.core.crf_goossens2012 import (
    DEFAULT_LAMBDA, CRFFit, crf_goossens2012_prior, from_knots, knot_levels, to_knots,
)
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.samples import RANGE_UNVERIFIED, Samples
from hdrmerge_cli.core.weights import weights_debevec1997_triangle

#: Debevec & Malik's lambda (their scale: per sampled pixel, unnormalised)
DEBEVEC_LAMBDA = 30.0
#: fewest pixels consecutive frames must both expose (neither code clipped) for a CRF fit
MIN_OVERLAP = 50


# ---------------------------------------------------------------- what a fit needs of the samples
def thin_overlap(s: Samples) -> tuple[int, int] | None:
    """The first neighbour pair sharing fewer than :data:`MIN_OVERLAP` pixels that neither
    frame clips (0 < z < max; constant borders excluded), as ``(k, pixels)`` with ``k`` the
    pair's longer frame, or None: a response cannot be chained across such a pair."""
    lo, hi = 0.5 * s.codes_step, s.top
    for k in range(1, len(s.v)):
        a, b = s.v[k - 1], s.v[k]
        both = int(np.count_nonzero(((a > lo) & (a < hi) & (b > lo) & (b < hi)).all(-1) & s.inside)) * s.step**2
        if both < MIN_OVERLAP:
            return k, both
    return None


def pairs_pin_response(s: Samples) -> bool:
    """Whether some neighbour pair ``(k - 1, k)`` shares :data:`MIN_OVERLAP` pixels (off the
    borders, at full resolution) both frames expose well in every channel: within
    :data:`~hdrmerge_cli.core.samples.RANGE_UNVERIFIED`, where any camera's response has
    slope, and above each frame's floor (:attr:`~hdrmerge_cli.core.samples.Samples.floors`).
    Pixel pairs pin a response only through such pixels; elsewhere one of the two codes is at
    a floor or a shoulder, and its noise there biases a fit on pairs (errors in the
    variables): the response is then fitted on the frames' histograms
    (:func:`histogram_correspondences`)."""
    lo, hi = RANGE_UNVERIFIED
    ok = [((v >= np.maximum(lo, floor)) & (v <= hi)).all(-1) & s.inside for v, floor in zip(s.v, s.floors)]
    return len(s.v) < 2 or max(int(np.count_nonzero(ok[k - 1] & ok[k])) * s.step**2
                               for k in range(1, len(ok))) >= MIN_OVERLAP


def sample_pixels(middle: np.ndarray, samples: int, rng: np.random.Generator) -> np.ndarray:
    """Flat indices of ``samples`` pixels spread evenly over the code values of
    ``middle`` (the bracket's middle frame, one channel, any shape)."""
    flat = middle.ravel()
    order = np.argsort(flat, kind="stable")
    picks = np.linspace(0, flat.size - 1, min(samples, flat.size)).astype(np.int64)
    jitter = rng.integers(-(flat.size // (2 * len(picks)) or 0), (flat.size // (2 * len(picks))) + 1, len(picks))
    return order[np.clip(picks + jitter, 0, flat.size - 1)]


#: rows of :func:`histogram_correspondences` (colour-hdri's default for the same method)
HISTOGRAM_ROWS = 1000


def histogram_correspondences(codes: list[np.ndarray], n_codes: int, rows: int = HISTOGRAM_ROWS,
                              floors: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """Grossberg & Nayar (2003)'s correspondences: for a monotone response the frames of
    one scene rank its pixels alike, so the code at which each frame's cumulative
    histogram reaches a fraction ``u`` is one scene irradiance seen at each exposure
    (their brightness transfer function), with no pixel-to-pixel match: motion,
    misregistration and pixels at the floor of one frame beside those of another do not
    enter it.  ``u`` runs over ``rows`` even steps strictly inside (0, 1).

    A frame's codes at its floor (``floors``) are no evidence: where the response has no
    slope, one code holds a wide range of quantiles (every irradiance below the floor's),
    which its rows would pair with as many different codes of the other frames, pulling
    ``g`` at the floor towards their average.  Those rows read code 0 instead, which every
    weighting of (36) gives no weight, so the fit reads each frame only above its floor.

    codes : P arrays ``(N, C)`` of integer codes (below ``n_codes``), one per frame, the
        same pixels' in each (their order is not used)
    floors : None, or P arrays ``(C,)``: the code up to which each frame reads its floor
        (:attr:`~hdrmerge_cli.core.samples.Samples.floor_codes`)
    Returns P arrays ``(rows, C)`` int64: row ``i`` the code of each frame at ``u_i``, per
    channel (monotone in ``i``), as :func:`fit_response`'s samples."""
    u = (np.arange(rows) + 0.5) / rows
    out = []
    for z in codes:
        cols = []
        for c in range(z.shape[-1]):
            cdf = np.cumsum(np.bincount(z[..., c].ravel(), minlength=n_codes)) / z[..., c].size
            cols.append(np.searchsorted(cdf, u))
        out.append(np.stack(cols, axis=-1).clip(0, n_codes - 1).astype(np.int64))
    if floors is not None:
        out = [np.where(z <= np.asarray(f), 0, z) for z, f in zip(out, floors)]
    return out


def crf_debevec1997(
    codes: np.ndarray, log_exposures: np.ndarray, n_codes: int, smoothing: float = DEBEVEC_LAMBDA
) -> CRFFit:
    """Debevec and Malik (1997): least squares for ``g`` and ``log E_i`` with hat weights,
    a second-difference smoothness term ``lambda`` and ``g(mid-scale) = 0``
    (no monotonicity constraint: the baseline the paper's (37) improves on).

    codes : (N, P) integer code values of N sampled pixels in P frames
    log_exposures : (P,) ``log t_j``
    n_codes : number of code values 2^B
    """
    import scipy.sparse as sp  # here, not at the top: a merge that estimates no response does not load it
    from scipy.sparse.linalg import lsqr

    codes = np.asarray(codes)
    n_pix, n_frames = codes.shape
    levels = knot_levels(n_codes)
    z = to_knots(codes, n_codes, levels)
    v = np.arange(levels) / (levels - 1)
    w = weights_debevec1997_triangle(v, v)
    wz = w[z]
    rows_data = np.arange(n_pix * n_frames)
    # data terms: w (g(z_ij) - log E_i) = w log t_j
    a_g = sp.csr_matrix((wz.ravel(), (rows_data, z.ravel())), shape=(n_pix * n_frames, levels))
    a_e = sp.csr_matrix((-wz.ravel(), (rows_data, np.repeat(np.arange(n_pix), n_frames))), shape=(n_pix * n_frames, n_pix))
    b_data = (wz * log_exposures[None, :]).ravel()
    # g(mid) = 0
    mid = levels // 2
    a_fix = sp.csr_matrix(([1.0], ([0], [mid])), shape=(1, levels + n_pix))
    # smoothness: lambda w(z) (g(z-1) - 2 g(z) + g(z+1)) = 0
    inner = np.arange(1, levels - 1)
    scale = smoothing * w[inner]
    r = np.repeat(np.arange(inner.size), 3)
    c = (inner[:, None] + np.array([-1, 0, 1])).ravel()
    vals = (scale[:, None] * np.array([1.0, -2.0, 1.0])).ravel()
    a_smooth = sp.csr_matrix((vals, (r, c)), shape=(inner.size, levels + n_pix))
    a = sp.vstack([sp.hstack([a_g, a_e]), a_fix, a_smooth]).tocsr()
    b = np.concatenate([b_data, [0.0], np.zeros(inner.size)])
    sol = lsqr(a, b, atol=1e-10, btol=1e-10, iter_lim=20000)[0]
    g = sol[:levels]
    if not np.all(np.isfinite(g)):
        raise HdrMergeError("the CRF fit failed (no finite solution)")
    return CRFFit(from_knots(g, n_codes), 1, True, n_pix * n_frames)


def crf_robertson2003(
    codes: np.ndarray, log_exposures: np.ndarray, n_codes: int, smoothing: float = 0.0, max_iterations: int = 30,
    tol: float = 1e-3,
) -> CRFFit:
    """Robertson, Borman & Stevenson (2003): alternate the maximum-likelihood irradiance
    ``E_i = sum_j w t_j I(z_ij) / sum_j w t_j^2`` and the response
    ``I(m) = mean over {(i, j): z_ij = m} of t_j E_i`` with Gaussian-like weights
    ``w(v) = exp(-16 (v - 1/2)^2)``, normalised to ``I(mid-scale) = 1``, until ``I``
    settles (no smoothness, no monotonicity; ``smoothing`` is unused).

    codes : (N, P) integer code values; log_exposures : (P,) ``log t_j``
    """
    levels = knot_levels(n_codes)
    k = to_knots(np.asarray(codes), n_codes, levels)
    v = np.arange(levels) / (levels - 1)
    w = np.exp(-16.0 * (v - 0.5) ** 2)
    w[[0, -1]] = 0.0
    t = np.exp(np.asarray(log_exposures, dtype=np.float64))
    mid = levels // 2
    resp = np.maximum(v / v[mid], 1e-6)  # linear start
    count = np.bincount(k.ravel(), minlength=levels)
    seen = count > 0
    wz = w[k]
    denom = wz @ (t * t)
    ok = denom > 0
    converged, it = False, 0
    for it in range(1, max_iterations + 1):
        e = (wz[ok] * resp[k[ok]]) @ t / denom[ok]
        tot = np.bincount(k[ok].ravel(), weights=(e[:, None] * t[None, :]).ravel(), minlength=levels)
        cnt = np.bincount(k[ok].ravel(), minlength=levels)
        new = np.interp(v, v[cnt > 0], tot[cnt > 0] / cnt[cnt > 0])
        new = np.maximum(new / new[mid], 1e-12)
        change = np.max(np.abs(np.log(new[seen]) - np.log(resp[seen])))
        resp = new
        if change < tol:
            converged = True
            break
    return CRFFit(from_knots(np.log(resp), n_codes), it, converged, int(k.size))


def inverse_from_log(g: np.ndarray) -> tuple[np.ndarray, bool]:
    """``gamma^-1 = exp(g)`` scaled to end at 1, made non-decreasing where the fit was not
    (returns whether that was needed).  Monotonicity is imposed from the top down
    (``min`` over higher codes), so a kink in the poorly constrained dark end lowers only
    itself instead of flattening everything above it."""
    lin = np.exp(g - g[-1])
    mono = np.minimum.accumulate(lin[::-1])[::-1]
    return mono, bool(np.any(mono < lin * (1 - 1e-12)))


@dataclass(frozen=True)
class CRFMethod:
    """An entry of :data:`CRF_ESTIMATORS`.

    estimate : ``f(codes (N, P), log_exposures (P,), n_codes, smoothing, **options) -> CRFFit``
    smoothing : default lambda (None: the method has none)
    samples : default number of pixels per channel (None: all of them)
    noise_weighted : whether it takes ``weighting``, ``noise``, ``bounds``, ``pair_weight``
    joint : whether it takes every channel at once (a list of ``(N, P)`` arrays; ``coupling``)
    """

    estimate: object
    smoothing: float | None
    samples: int | None
    noise_weighted: bool = False
    joint: bool = False


#: name -> method; the paper's (37) first
CRF_ESTIMATORS = {
    "goossens": CRFMethod(crf_goossens2012_prior, DEFAULT_LAMBDA, None, True, True),
    "debevec": CRFMethod(crf_debevec1997, DEBEVEC_LAMBDA, 1000),
    "robertson": CRFMethod(crf_robertson2003, None, None),
}


def _channel_samples(codes: list[np.ndarray], c: int, samples: int | None, method: str, rng) -> np.ndarray:
    """(N, P) codes of channel ``c``: every pixel, or ``samples`` of them (Debevec-Malik's
    stratified choice over the middle frame's codes, else uniformly at random)."""
    n = codes[0][..., c].size
    if not samples or samples >= n:
        out = np.empty((n, len(codes)), codes[0].dtype)
        for j, fr in enumerate(codes):
            out[:, j] = fr[..., c].reshape(-1)
        return out
    idx = (sample_pixels(codes[len(codes) // 2][..., c], samples, rng) if method == "debevec"
           else rng.choice(n, samples, replace=False))
    return np.stack([fr[..., c].ravel()[idx] for fr in codes], axis=1)


@dataclass
class ResponseFit:
    """What :func:`fit_response` returns: the response (a ``(C, n_codes)`` table), the
    per-channel fits, and whether a fit had to be made monotone."""

    crf: CRF
    fits: list[CRFFit]
    changed: bool


def fit_response(codes: list[np.ndarray], log_h: np.ndarray, n_codes: int, method: str = "goossens",
                 smoothing: float | None = None, samples: int | None = None, options: dict | None = None,
                 rng: np.random.Generator | None = None) -> ResponseFit:
    """The inverse response of decoded frames: ``method`` of :data:`CRF_ESTIMATORS`, the
    channels in one coupled solve for a ``joint`` method (goossens: see its ``coupling``;
    its prior towards the standard curve where the frames leave ``g`` open,
    :func:`~hdrmerge_cli.core.crf_goossens2012.crf_goossens2012_prior`), one by one for
    the others.

    codes : P arrays (H, W, C) in increasing exposure order; log_h : (P,) ``log h_j``
    smoothing, samples : None for the method's defaults; options : the method's keywords
    """
    m = CRF_ESTIMATORS[method]
    rng = rng if rng is not None else np.random.default_rng(0)
    samples = m.samples if samples is None else samples
    samples_of = [_channel_samples(codes, c, samples, method, rng) for c in range(codes[0].shape[-1])]
    options = dict(options or {})
    if m.smoothing is not None:
        options["smoothing"] = m.smoothing if smoothing is None else smoothing
    if m.joint:  # one solve of every channel, coupled
        fit = m.estimate(samples_of, log_h, n_codes, **options)
        fits = [CRFFit(g, fit.iterations, fit.converged, fit.rows) for g in fit.g]
    else:
        fits = [m.estimate(z, log_h, n_codes, **options) for z in samples_of]
    tables, fixed = zip(*(inverse_from_log(f.g) for f in fits))
    return ResponseFit(table_crf(np.stack(tables), f"estimate-crf:{method}"), fits, any(fixed))


@dataclass
class LabelledFit:
    """What :func:`labelled_fit` returns: the response, each round's :class:`ResponseFit`
    (for the log), the frames whose measured exposure replaced their label, and the codes
    per frame the fit read (pixels or histogram levels)."""

    crf: CRF
    rounds: list[ResponseFit]
    replaced: list[int]
    rows: int


def labelled_fit(s: Samples, exposures: np.ndarray, histograms: bool = False) -> LabelledFit:
    """The response and the labels judged together: fit with the labels (on the samples'
    codes, or with ``histograms`` on their :func:`histogram_correspondences`), check them
    through the fit (:func:`~hdrmerge_cli.core.exposure_estimate.estimate`), and while a
    frame's label is off by more than the tolerance in a way a label explains (its ratios
    do not change with brightness, :func:`~hdrmerge_cli.core.exposure_estimate.label_at_fault`),
    refit with that frame's estimate in place of its label, the frame furthest off first,
    at most half the frames.  A wrong label then does not bend the curve; the labels are
    judged (and warned about) afterwards against the response returned."""
    from hdrmerge_cli.core.exposure_estimate import estimate, label_at_fault

    n_codes = s.levels[2]
    codes = histogram_correspondences(s.codes, n_codes, floors=s.floor_codes) if histograms else s.codes
    log_h = np.log(np.asarray(exposures, np.float64))
    replaced: list[int] = []
    rounds: list[ResponseFit] = []
    for r in range(len(s.v) // 2 + 1):
        rounds.append(fit_response(codes, log_h, n_codes))
        if r == len(s.v) // 2:
            break
        est = estimate(np.exp(log_h), s, rounds[-1].crf)
        off = [k for k in est.mislabelled() if k not in replaced and label_at_fault(est, k)]
        if not off:
            break
        k = max(off, key=lambda j: abs(est.difference_ev[j]))
        log_h[k], replaced = est.log_h[k], replaced + [k]
    return LabelledFit(rounds[-1].crf, rounds, replaced, codes[0].shape[0])
