"""HDR reconstruction by the paper's main formula (7), streamed frame by frame.

(7):  log E_i = sum_j w_ij s_ij (g(z_ij) - log h_j) / sum_j w_ij s_ij

with ``g = log gamma^-1`` (2), ``h_j`` the exposure of frame j (exposure time times the
gain ratio ``sqrt(alpha_j)``, see (1)), ``w_ij = w(z_ij)`` a weighting function and
``s_ij`` the variance factor ``sigma^-2(E_i, t_j)`` at each frame's own estimate
(:func:`inverse_variance`).  As ``w`` and ``g`` depend on the code and the frame only,
each frame is reduced to lookup tables over all code values (:func:`exposure_tables`,
from the response's inverse at the frame's stored codes, one row per channel, the row of
a sample given by a small periodic pattern), and merging a frame is two gathers and two
additions per sample (:class:`LogMerge`).  Pixels that no frame measures get a finite,
documented value and a flag (:meth:`LogMerge.finish`).  On request the noise model's
variance of each merged value is propagated too (:func:`estimate_variance_table`,
:class:`LogMerge` with ``variance``).  :func:`merge` runs (7) and the re-weighting passes
(:func:`reweight`) in one loop over strips of rows.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from hdrmerge_cli.core.crf import CodesInverse
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.jit import njit, prange
from hdrmerge_cli.core.noise import DEFAULT_K, NoiseParams, quantisation_variance
from hdrmerge_cli.core.weights import NOISE_MODEL_WEIGHTS, WEIGHTING_FUNCTIONS
from hdrmerge_cli.core.weights_goossens2012 import WeightContext, bounded_noise

#: flag values of :meth:`LogMerge.finish`
FLAG_OK, FLAG_SATURATED, FLAG_DARK = 0, 1, -1


@dataclass(frozen=True)
class ExposureTables:
    """Lookup tables of one exposure, each flattened ``(C * N,)`` float32.

    weight : ``w(z)`` (times the variance factor)
    weighted_log : ``w(z) * (g(z) - log h)``, the numerator term of (7); for the linear
        (maximum-likelihood) estimator ``w(z) * gamma^-1(z) / h`` instead
    value : ``g(z) - log h`` (or ``gamma^-1(z) / h``), the frame's own estimate, for IRLS
    certainty : ``w(z)`` alone (without the variance factor), for IRLS
    fallback_log : ``log(max(gamma^-1(z), half a code) / h)``, used where no frame has weight
    above_mid : bool, ``z > z_max / 2``: a pixel above mid-scale in the shortest frame and
        unmeasured everywhere is taken as saturated, otherwise as dark
    saturated : bool, ``z >= z_max``: a reading clipped at full scale (censored), which the
        ML estimator's re-weighting passes use (:func:`_censored_rows`)
    variance : the variance of ``value`` (the frame's own estimate, in the estimator's
        domain: ``log E`` or ``E``) at each code, :func:`estimate_variance_table`; only
        built when asked for (``exposure_tables(..., with_variance=True)``), None otherwise
    """

    weight: np.ndarray
    weighted_log: np.ndarray
    fallback_log: np.ndarray
    above_mid: np.ndarray
    n_codes: int
    value: np.ndarray | None = None
    certainty: np.ndarray | None = None
    saturated: np.ndarray | None = None
    variance: np.ndarray | None = None


def neutral_bounds(result: np.ndarray, flags: np.ndarray) -> int:
    """Where some channel of an image pixel is only a lower bound (clipped in every frame
    that covers it, ``FLAG_SATURATED``), give all its channels the largest, flagged so.  A
    camera-processed pixel's channels are mixed from one another (demosaicing, the colour
    matrix, the camera's highlight handling), so where one clipped in every covering frame,
    the others of those frames' readings are no measurement either (a sky whose green
    clipped reads green, not white); a bound carries no colour, and the largest bounds
    each channel from below as the clipped one's did.  ``result``, ``flags``: ``(H, W,
    C)``, changed in place (a mosaic's sites are measured apart: left as they are).
    Returns the pixels set."""
    if result.ndim != 3 or result.shape[-1] < 2:
        return 0
    bound = np.any(flags == FLAG_SATURATED, axis=-1)
    if bound.any():
        result[bound] = result[bound].max(axis=-1, keepdims=True)
        flags[bound] = FLAG_SATURATED
    return int(np.count_nonzero(bound))


def _channels(inverse: CodesInverse):
    """Per table row ``(c, black, white, v, lin)``: the normalised code values ``v = (r -
    black) / (white - black)`` for ``r = 0..N-1`` and ``gamma^-1`` at every stored code."""
    n_codes = inverse.table.shape[1]
    for c, (b, wl) in enumerate(zip(inverse.black, inverse.white)):
        yield c, b, wl, (np.arange(n_codes, dtype=np.float64) - b) / float(wl - b), inverse.table[c]


def _row(per_row, c: int):
    """Table row ``c``'s entry of per-row values (the last where there are fewer; None: None)."""
    return None if per_row is None else per_row[min(c, len(per_row) - 1)]


def _noise_variance(rows: NoiseRows, c: int, mu: np.ndarray) -> np.ndarray:
    """The sensor's variance (17) of table row ``c`` (the last where there are fewer) at
    the mean ``mu`` (code values), float64: ``sigma_o^2 + sqrt(alpha) mu + (beta / alpha)
    mu^2``, as :func:`~hdrmerge_cli.core.noise.code_variance` and the kernels' :func:`_irls_weight`."""
    c = min(c, rows.sigma_o2.shape[0] - 1)
    return rows.sigma_o2[c] + rows.sqrt_alpha[c] * mu + rows.beta_per_alpha[c] * mu * mu


#: smallest weight of an unclipped code: noise-model weights of codes far outside the
#: clipping-safe range underflow, and where every frame of a pixel is such a code (gaps
#: in a bracket) the frames' own codes must still decide, not the no-information fallback
WEIGHT_FLOOR = 1e-30

#: relative error of a camera-processed code's linearised value that no noise model
#: explains (the response's fit, the camera's processing): a 1 % floor on the standard
#: deviation of ``log gamma^-1(z)``, chosen on the real brackets' leave-one-out
#: (benchmarks/results/real_loo.md)
MODEL_TOLERANCE = 0.01


def _context(weighting, y_full, exposure, noise, prior_rate, exposures, k, bounds=None):
    if weighting not in NOISE_MODEL_WEIGHTS:
        return None
    bounds = tuple(bounds) if bounds else WeightContext.bounds
    if noise is None:  # unknown camera: the conservative upper bounds of the bounded scheme
        noise = bounded_noise(y_full, *bounds)
    if not prior_rate or prior_rate <= 0:
        raise HdrMergeError("the irradiance prior needs a positive mean (the bracket looks black)")
    ctx = WeightContext(y_full, exposure, noise, prior_rate, tuple(exposures), k, bounds=bounds)
    if weighting != "bounded":
        lo, hi = ctx.safe_range()
        if lo >= hi:
            raise HdrMergeError(
                f"no clipping-safe range for noise {noise} at k = {k:g} (the noise fills the code range); "
                "check the noise parameters or lower k"
            )
    return ctx


def certainty_table(n_codes, black, white, crf, weighting, exposure, noise=None, prior_rate=None, exposures=(),
                    k=DEFAULT_K, bounds=None) -> np.ndarray:
    """The weighting function ``w(z)`` of one exposure per channel, ``(C, N)`` float64 in
    [0, 1], zero at clipped codes.  ``noise`` is a list of per-channel
    :class:`~hdrmerge_cli.core.noise.NoiseParams` (code units) for the noise-model
    weights; without it they use the bounded scheme's conservative upper bounds; ``prior_rate`` is the mean of the exponential irradiance prior in
    code values per second; ``bounds`` the ``(1/alpha, sigma_o^2, beta)`` upper bounds of
    ``bounded`` on the normalised scale (default: the paper's JPEG values)."""
    return _certainty(crf.at_codes(n_codes, black, white), weighting, exposure, noise, prior_rate, exposures, k,
                      bounds)


def _certainty(inverse: CodesInverse, weighting, exposure, noise, prior_rate, exposures, k, bounds) -> np.ndarray:
    """:func:`certainty_table` on the response's inverse at the frame's codes."""
    return np.stack([WEIGHTING_FUNCTIONS[weighting](v, lin, _context(weighting, wl - b, exposure, _row(noise, c),
                                                                     prior_rate, exposures, k, bounds))
                     for c, b, wl, v, lin in _channels(inverse)])


#: samples of the middle frame that estimate the prior's mean
PRIOR_SAMPLES = 1 << 18


def prior_rate_of(codes: np.ndarray, black: float, white: float, exposure: float, inverse: CodesInverse | None,
                  name: str = "the middle frame") -> float:
    """The mean of the exponential irradiance prior of the noise-model weights (the paper
    assumes it known; code values per second), from one frame's unclipped samples: the
    mean linear signal per second over an even subsample of at most
    :data:`PRIOR_SAMPLES` samples.

    codes : (H, W) mosaic (``inverse`` None: linear between ``black`` and ``white``) or
        (H, W, C) image of the frame of exposure ``exposure`` s, linearised through
        ``inverse`` (:meth:`~hdrmerge_cli.core.crf.CRF.at_codes` on its codes)
    """
    full = white - black
    step = max(1, codes.shape[0] * codes.shape[1] // PRIOR_SAMPLES)
    sub = codes.reshape(codes.shape[0] * codes.shape[1], -1)[::step]
    if inverse is None:
        lin = np.clip((sub - black) / full, 0, 1)
    else:
        lin = np.stack([inverse.table[c][sub[..., c]] for c in range(sub.shape[-1])], axis=-1)
    ok = (lin > 0) & (lin < 1)
    if not np.any(ok):
        what = "black" if np.all(lin <= 0) else "clipped" if np.all(lin >= 1) else "black or clipped"
        raise HdrMergeError(f"{name}: every sample is {what}; cannot estimate the irradiance prior")
    return float(np.mean(lin[ok]) * full / exposure)


def code_error_variance(lin: np.ndarray, y_full: float, tolerance: float = MODEL_TOLERANCE) -> np.ndarray:
    """What a camera-processed code adds to the variance of its linearised value ``y``
    beyond the sensor noise (17), as used in the variance factor of (7): the quantisation through the inverse response
    (:func:`quantisation_variance`) plus the model tolerance ``(tolerance y)^2``.  In the log
    domain of (7) this is ``(d log gamma^-1 / dz)^2 / 12 + tolerance^2``: large for dark codes,
    where the inverse response is steep in log, and never below the tolerance.

    lin : (N,) ``gamma^-1`` per code value; returns (N,) squared code values of ``y``.
    """
    y = np.asarray(lin, dtype=np.float64) * y_full
    return quantisation_variance(lin, y_full) + (tolerance * y) ** 2


def inverse_variance(variance: str, lin: np.ndarray, y_full: float, noise: NoiseRows | None, row: int = 0,
                     code_error: np.ndarray | None = None) -> np.ndarray:
    """The factor ``sigma^-2(E, t_j)`` of (7) at each frame's own estimate ``mu = y``:
    ``none`` 1; ``photon`` ``t E`` up to the common gain (the photon-limited case of (22),
    which needs no parameters); ``codes`` ``mu^2 / c(mu)`` with ``code_error`` ``c``
    (:func:`code_error_variance`; 1/12 when None), the inverse variance of ``log y`` of a
    noise-free camera-processed code; ``model`` ``mu^2 / (v(mu) + c(mu))``, the
    clipping-free variance (21) with table row ``row``'s noise parameters plus
    ``code_error`` if given (clipping is the weights' business)."""
    y = np.clip(lin, 0.0, 1.0) * y_full
    if variance == "none":
        return np.ones_like(y)
    if variance == "photon":
        return y
    if variance == "codes":
        return y * y / (1.0 / 12.0 if code_error is None else np.maximum(code_error, 1e-300))
    if noise is None:
        raise HdrMergeError("--variance model needs noise parameters (--noise or a profile)")
    return y * y / (_noise_variance(noise, row, y) + (0.0 if code_error is None else code_error))


def _floored(w: np.ndarray, v: np.ndarray, weighting: str) -> np.ndarray:
    """Noise-model weights: the underflowed weights of unclipped codes kept at :data:`WEIGHT_FLOOR` (they still count)."""
    return np.where((v > 0) & (v < 1), np.maximum(w, WEIGHT_FLOOR), 0.0) if weighting in NOISE_MODEL_WEIGHTS else w


def _code_error(linear: bool, excess, v: np.ndarray | None, lin: np.ndarray, y_full: float,
                tolerance: float = MODEL_TOLERANCE) -> np.ndarray | None:
    """(N,) variance (squared code values of ``y``) a camera-processed code adds beyond (17); None for a linear CRF."""
    # camera-processed codes' own error; a linear sensor's measured read noise already
    # holds its quantisation
    if linear:
        return None
    if excess is not None:
        return quantisation_variance(lin, y_full) + excess.at(v) * (lin * y_full) ** 2
    return code_error_variance(lin, y_full, tolerance)


def _weight_and_value(estimator: str, variance: str, cert: np.ndarray, lin: np.ndarray, y_full: float,
                      exposure: float, noise: NoiseRows | None, row: int,
                      code_error: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N,) weights of one channel's codes and (N,) the frame's own estimate there (``log E``, or ``E`` for ml)."""
    if estimator == "ml":
        y = lin * y_full
        var_y = _noise_variance(noise, row, y) if noise is not None else np.maximum(y, 1.0)
        if code_error is not None:
            var_y = var_y + code_error
        w = cert * (exposure * y_full) ** 2 / np.maximum(var_y, 1e-12)  # 1 / Var[gamma^-1(z) / h]
        return w, lin / exposure
    w = cert * inverse_variance(variance, lin, y_full, noise, row, code_error)
    with np.errstate(divide="ignore"):
        value = np.where(lin > 0, np.log(lin) - np.log(exposure), 0.0)  # finite wherever it is used
    return w, value


def exposure_tables(
    inverse: CodesInverse,
    weighting: str,
    exposure: float,
    noise: list[NoiseParams] | None = None,
    variance: str = "none",
    prior_rate: float | None = None,
    exposures=(),
    k: float = DEFAULT_K,
    certainty: np.ndarray | None = None,
    estimator: str = "log",
    bounds=None,
    with_variance: bool = False,
    excess=None,
) -> ExposureTables:
    """Build the per-channel tables of one exposure for (7): the weight ``w(z)`` times the
    variance factor ``sigma^-2`` of :func:`inverse_variance`.

    inverse : ``gamma^-1`` at the frame's stored codes, with each table row's black and
        white level (:meth:`~hdrmerge_cli.core.crf.CRF.at_codes`; ``N`` stored code values:
        256 for 8-bit, 65536 for 16-bit containers)
    weighting : a name in :data:`~hdrmerge_cli.core.weights.WEIGHTING_FUNCTIONS`
    exposure : ``h_j`` in seconds (times the gain ratio where frames differ in ISO)
    noise : per table row the :class:`~hdrmerge_cli.core.noise.NoiseParams` (code units), or None
    certainty : a precomputed ``(C, N)`` weight table (``merge --lut``) instead of ``weighting``
    estimator : ``log`` for (7); ``ml`` for the linear-domain inverse-variance estimate
        (Granados et al. 2010): value ``gamma^-1(z) / h``, weight ``w(z) h^2 / v(y)`` (the
        variance of ``y / h``; ``variance`` is then ignored), saturated codes censored
        (weight 0) as every weight is there
    with_variance : also build the ``variance`` table (:func:`estimate_variance_table`),
        for ``LogMerge(..., variance=True)``; off by default (no cost)
    excess : the variance of ``log E`` a camera-processed code carries beyond (17) and its
        quantisation, measured on the bracket
        (:class:`~hdrmerge_cli.core.excess_variance.ExcessVariance`); it replaces the fixed
        :data:`MODEL_TOLERANCE` of :func:`code_error_variance`
    """
    if certainty is None:
        certainty = _certainty(inverse, weighting, exposure, noise, prior_rate, exposures, k, bounds)
    rows = None if noise is None else noise_rows(noise, np.float64)
    log_h = np.log(exposure)
    parts = []
    for c, b, wl, v, lin in _channels(inverse):
        cert = _floored(_row(certainty, c), v, weighting)
        fallback = np.log(np.maximum(lin, max(inverse.half_code[c], np.finfo(np.float64).tiny))) - log_h
        code_error = _code_error(inverse.linear, excess, v, lin, wl - b)
        w, value = _weight_and_value(estimator, variance, cert, lin, wl - b, exposure, rows, c, code_error)
        w = _floored(w, v, weighting)
        parts.append((w, w * value, fallback, v > 0.5, value, cert, v >= 1))
    w, wv, fb, hi, val, cert, sat = (np.concatenate(col) for col in zip(*parts))
    var = estimate_variance_table(inverse, exposure, noise, estimator) if with_variance else None
    return ExposureTables(
        w.astype(np.float32), wv.astype(np.float32), fb.astype(np.float32), hi, inverse.table.shape[1],
        val.astype(np.float32), cert.astype(np.float32), sat, var,
    )


#: largest per-code variance of a frame's value (codes whose linear value is 0 carry no
#: weight; a finite stand-in keeps ``w^2 var`` finite in float32 should one ever count)
VARIANCE_CAP = 1e30

#: variance of an unmeasured sample (flag != 0) relative to its squared value: the result
#: there is a bound (:meth:`LogMerge.finish`), and its variance is reported as
#: ``UNMEASURED_RELATIVE_VARIANCE * result^2``, i.e. a standard deviation equal to the
#: value itself (SNR 1): for a dark sample (true value in ``[0, bound]``) an upper bound of
#: the error, for a saturated one (true value above the bound) a floor; finite, NaN-free,
#: in the result's units; the flag channel tells which.  In ``log E``: variance 1.
UNMEASURED_RELATIVE_VARIANCE = 1.0


def estimate_variance_table(inverse: CodesInverse, exposure: float, noise: list[NoiseParams] | None = None,
                            estimator: str = "log", tolerance: float = MODEL_TOLERANCE) -> np.ndarray:
    """Variance of one frame's own estimate (the ``value`` table of :func:`exposure_tables`)
    at every stored code, in the estimator's domain, flattened ``(C * N,)`` float32:
    ``estimator="log"``: ``V(y) / y^2`` (dimensionless; the clipping-free (21), by the delta
    method); ``estimator="ml"``: ``V(y) / (h y_full)^2`` (in (full scale per second)^2).
    Codes at or below black read :data:`VARIANCE_CAP` (they carry no weight).

    inverse, exposure, noise : as :func:`exposure_tables`
    tolerance : the code error's relative model tolerance (:data:`MODEL_TOLERANCE`; 0 for
        a camera whose response is known exactly, e.g. a simulation)

    Notes: the linearised reading ``y = gamma^-1(z) y_full`` has the variance ``V(y) = v(y)
    + c(y)``: the sensor's (17) as a function of the mean (:func:`_noise_variance`) plus, for
    a non-linear response, the code error of :func:`code_error_variance`; both at the
    frame's own reading, as the tables' weights are.  Without ``noise`` only ``c(y)`` remains (``1/12`` for a linear response): the
    ``codes`` variance factor of (7), a lower bound.
    """
    rows = None if noise is None else noise_rows(noise, np.float64)
    out = []
    for c, b, wl, _, lin in _channels(inverse):
        y_full = wl - b
        y = np.clip(lin, 0.0, 1.0) * y_full
        var_y = np.zeros_like(y) if rows is None else _noise_variance(rows, c, y)
        code_error = _code_error(inverse.linear, None, None, lin, y_full, tolerance)
        if code_error is not None:
            var_y = var_y + code_error
        elif rows is None:
            var_y = var_y + 1.0 / 12.0
        if estimator == "ml":
            var = var_y / (exposure * y_full) ** 2
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                var = np.where(y > 0, var_y / np.maximum(y, 1e-300) ** 2, VARIANCE_CAP)
        out.append(np.minimum(var, VARIANCE_CAP))
    return np.concatenate(out).astype(np.float32)


def channel_index(shape: tuple[int, ...], pattern: np.ndarray | None) -> np.ndarray | None:
    """Table row of every sample, ``shape`` intp: ``pattern`` tiled over ``(H, W)``
    (a CFA mosaic) or ``(H, W * C)`` (interleaved channels); None when one row serves all."""
    if pattern is None:
        return None
    rows, cols = _rows_cols(shape)
    ph, pw = pattern.shape
    tiled = np.tile(pattern.astype(np.intp), (-(-rows // ph), -(-cols // pw)))[:rows, :cols]
    return tiled.reshape(shape)


def lookup(table: np.ndarray, n_codes: int, codes: np.ndarray, pattern: np.ndarray | None) -> np.ndarray:
    """Per-sample values of a flattened ``(C * N,)`` table (an :class:`ExposureTables`
    field), shape of ``codes``: the sample's table row from ``pattern`` tiled over
    ``(H, W)`` or ``(H, W * C)`` (as :func:`channel_index`; None: row 0), entry ``codes``;
    codes above the table read its last (clipped) entry, as the fused kernels do.  One
    strided gather per pattern cell (no per-sample index array); 8-bit interleaved images
    through OpenCV's lookup, as float32."""
    per_row = table.reshape(-1, n_codes)
    channels = codes.shape[-1] if codes.ndim == 3 else 1
    if (codes.dtype == np.uint8 and n_codes == 256 and per_row.dtype.kind == "f" and channels <= 4
            and (pattern is None or (codes.ndim == 3 and pattern.shape == (1, channels)))):
        import cv2  # 8-bit interleaved images: OpenCV's table lookup, every channel in one pass

        rows = np.zeros(channels, np.intp) if pattern is None else pattern[0]
        return cv2.LUT(np.ascontiguousarray(codes), np.ascontiguousarray(per_row[rows].T[None], np.float32))
    if pattern is None:
        return per_row[0][np.minimum(codes, n_codes - 1)]
    flat = codes.reshape(_rows_cols(codes.shape))
    out = np.empty(flat.shape, per_row.dtype)
    ph, pw = pattern.shape
    for i in range(ph):
        for j in range(pw):
            out[i::ph, j::pw] = per_row[pattern[i, j]][np.minimum(flat[i::ph, j::pw], n_codes - 1)]
    return out.reshape(codes.shape)


def _rows_cols(shape):
    return shape[0], int(np.prod(shape[1:]))


def _pattern(pattern: np.ndarray | None) -> np.ndarray:
    """The kernels' table-row pattern: ``pattern`` as intp, or one row for every sample."""
    return np.zeros((1, 1), np.intp) if pattern is None else np.ascontiguousarray(pattern, np.intp)


def _read_only(codes: np.ndarray) -> np.ndarray:
    """A read-only view of a frame's codes for the compiled kernels: decoded frames are
    writable, resampled ones read-only, and Numba compiles (and loads from its cache, tens
    of ms each) one specialisation per kind; as read-only views both share one."""
    view = codes.view()
    view.flags.writeable = False
    return view


class NoiseRows(NamedTuple):
    """The parameters of (21) per table row, ``(R,)`` each, in the kernels' order."""

    sigma_o2: np.ndarray
    sqrt_alpha: np.ndarray
    beta_per_alpha: np.ndarray


def noise_rows(params: list[NoiseParams], dtype=np.float32) -> NoiseRows:
    """:class:`NoiseRows` of ``params``, one :class:`~hdrmerge_cli.core.noise.NoiseParams` per
    table row: float32 for the kernels, float64 for the tables (:func:`_noise_variance`)."""
    return NoiseRows(*(np.array([[p.sigma_o2, np.sqrt(p.alpha), p.beta / p.alpha][i] for p in params], dtype)
                       for i in range(3)))


@njit(inline="always")
def _irls_weight(c, le, k, so, sq, ba, linear, floor):  # pragma: no cover
    """One sample's weight on an IRLS pass (iteratively re-weighted (7)) at the current
    estimate ``le`` = log E: ``w(z) sigma^-2(E, t_j)`` with ``mu = E h y_full`` and the
    clipping-free variance (21) ``v(mu) = so + sq mu + ba mu^2``, i.e. ``c mu^2 / v(mu)``
    (log estimator) or ``c k^2 / v(mu)`` (ML, ``linear``); certainty ``c``,
    ``k = h y_full``, the row's noise parameters (sigma_o2, sqrt_alpha, beta / alpha).
    0 without certainty; a sample with any certainty keeps at least ``floor``
    (:data:`WEIGHT_FLOOR`), as in the tables."""
    if not c > 0:
        return np.float32(0.0)
    mu = np.float32(np.exp(le) * k)
    var = max(so + sq * mu + ba * mu * mu, np.float32(1e-12))
    num = np.float32(k * k) if linear else mu * mu
    return max(c * (num / var), floor)


#: a stand-in for an absent per-sample or per-pixel array of the compiled kernels
_NO_WEIGHT = np.zeros((1, 1), np.float32)


#: ``den`` of a sample no own frame has classed yet (:func:`_add_sample`): saturated if none ever does
_UNOWNED = -2.0


@njit(inline="always")
def _add_sample(num, den, i, j, w, wv, fb_tab, hi_tab, r, z, mode, keep, per_keep, use_keep):  # pragma: no cover
    """One frame's sample ``(i, j)`` (table row ``r``, code ``z``, weight ``w``, weighted
    value ``wv``) into (7)'s sums, as :class:`LogMerge` keeps them (``mode`` 0: the
    shortest frame sets the fallback and class; 2: the longest fills the dark fallback;
    with ``use_keep`` every later frame fills it where it is the sample's own, ``keep[i,
    j // per_keep] >= 1/2``, so the longest own one's stays, not that of a frame rejected
    or not covering there; ``keep`` is read on that branch only, off the hot path).  The
    saturated class and its bound come from the shortest own frame: where the shortest
    frame is not the sample's own (it does not cover it, or it is a ghost there), ``den``
    holds :data:`_UNOWNED` until the first frame that is sets them, so a strip that only
    longer frames cover is bounded by their clipping level, not by a frame that never saw it."""
    if mode == 0:
        if w > 0:
            num[i, j] = wv
            den[i, j] = w
        else:
            num[i, j] = fb_tab[r, z]
            den[i, j] = _UNOWNED if use_keep and keep[i, j // per_keep] < 0.5 else (-1.0 if hi_tab[r, z] else 0.0)
    elif w > 0:
        if den[i, j] > 0:
            num[i, j] += wv
            den[i, j] += w
        else:
            num[i, j] = wv
            den[i, j] = w
    elif use_keep and den[i, j] == _UNOWNED:
        if keep[i, j // per_keep] >= 0.5:  # the first own frame: the class and its fallback
            num[i, j] = fb_tab[r, z]
            den[i, j] = -1.0 if hi_tab[r, z] else 0.0
    elif (keep[i, j // per_keep] >= 0.5 if use_keep else mode == 2) and den[i, j] == 0:
        num[i, j] = fb_tab[r, z]


@njit(parallel=True, nogil=True, cache=True)
def _irls_weights_rows(codes, pattern, certainty, log_e, k, s_o2, sqrt_a, b_a, linear, out):  # pragma: no cover
    """:func:`_irls_weight` fused with the table lookup, per 2-D sample: the row of a
    sample from ``pattern`` tiled, its noise parameters from the per-row arrays."""
    rows, cols = codes.shape
    ph, pw = pattern.shape
    n = certainty.shape[1]
    floor = np.float32(WEIGHT_FLOOR)
    for i in prange(rows):
        prow = pattern[i % ph]
        for q in range(min(pw, cols)):  # one table row at a time: no per-sample modulo
            r = prow[q]
            so, sq, ba = s_o2[r], sqrt_a[r], b_a[r]
            for j in range(q, cols, pw):
                out[i, j] = _irls_weight(certainty[r, min(codes[i, j], n - 1)], log_e[i, j], k, so, sq, ba, linear,
                                         floor)


@njit(parallel=True, nogil=True, cache=True)
def _accumulate_irls(codes, pattern, certainty, num_tab, fb_tab, hi_tab, log_e, k, s_o2, sqrt_a, b_a, linear, mode,
                     num, den):  # pragma: no cover
    """:func:`_irls_weights_rows` fused with :func:`_accumulate`: each sample's IRLS weight
    is computed and added to ``num``/``den`` at once, so no frame-sized weight array is
    written and read back (the same arithmetic, in the same order)."""
    rows, cols = codes.shape
    ph, pw = pattern.shape
    top = certainty.shape[1] - 1
    floor = np.float32(WEIGHT_FLOOR)
    for i in prange(rows):
        prow = pattern[i % ph]
        for q in range(min(pw, cols)):
            r = prow[q]
            so, sq, ba = s_o2[r], sqrt_a[r], b_a[r]
            for j in range(q, cols, pw):
                z = min(codes[i, j], top)
                w = _irls_weight(certainty[r, z], log_e[i, j], k, so, sq, ba, linear, floor)
                _add_sample(num, den, i, j, w, w * num_tab[r, z], fb_tab, hi_tab, r, z, mode, _NO_WEIGHT, 1, False)


#: IRLS stops when no measured sample's log-irradiance moves more than this
IRLS_TOLERANCE = 1e-3

#: clipped readings whose estimate is this many noise sds above full scale are not censored terms
CENSORED_SDS = 8.0


@njit(cache=True, nogil=True)
def _inverse_mills(a):  # pragma: no cover
    """``lam = phi(a) / Phi(-a)`` of :func:`_censored_rows` in float64: directly below
    a = 30 (erfc keeps its relative accuracy there), above it by the asymptotic series of
    Mills' ratio ``Phi(-a) / phi(a) = (1 - a^-2 + 3 a^-4 - 15 a^-6 + 105 a^-8) / a``
    (relative error < 1e-12 at a = 30)."""
    if a < 30.0:
        return math.exp(-0.5 * a * a) / (0.5 * math.erfc(a / math.sqrt(2.0)) * math.sqrt(2.0 * math.pi))
    q = 1.0 / (a * a)
    return a / (1.0 - q * (1.0 - q * (3.0 - q * (15.0 - 105.0 * q))))


@njit(parallel=True, nogil=True, cache=True)
def _censored_rows(codes, pattern, saturated, log_e, den, use_den, k, y_full, sd_full2, log_hi, s_o2, sqrt_a, b_a,
                   factor, use_factor, num_t, den_t, var_t, use_var):  # pragma: no cover
    """One frame's censored terms added to ``num_t`` (weight times value), ``den_t``
    (weight) and, with ``use_var``, ``var_t`` (weight), per 2-D sample.

    A reading clipped at full scale in the ML estimator's re-weighting: the censored
    observation ``y > y_full - 1/2`` (the top code's lower edge) of ``y ~ N(mu, v(mu))``,
    ``mu = E h y_full``, as a pseudo-observation ``(weight, value)`` of the weighted mean,
    so that one pass is a Fisher-scoring (Newton) step on the censored likelihood.
    With ``a = (y_full - 1/2 - mu) / sd`` and the inverse Mills ratio
    ``lam = phi(a) / Phi(-a)`` (:func:`_inverse_mills`), the censored log-likelihood
    ``log Phi(-a)`` has score ``k lam / sd`` and observed information
    ``k^2 lam (lam - a) / sd^2`` in ``E`` (``k = h y_full``; the dependence of ``sd`` on
    ``mu`` is neglected).  Weight = that information, value = ``E + score / information =
    E + sd / (k (lam - a))``: at a fixed point the weighted mean solves the censored
    likelihood equation, where dropping the clipped readings (the tables' weight 0) biases a
    sample near saturation low (its unclipped readings are the truncated lower part of
    their distribution) and ignores that the clipped frames saw more than full scale.  A
    reading far above full scale carries no information and gets weight ~0.

    Fused with the choice of the readings the terms apply to (see :func:`reweight`): clipped
    (``saturated`` table) and an estimate under ``log_hi`` (not :data:`CENSORED_SDS` sds
    above full scale); with ``use_den`` also only where the previous pass measured the
    sample (``den > 0``) and not :data:`CENSORED_SDS` combined sds below full scale.  A
    target sample whose ``den_t`` is not positive (no weight yet, or a class mark of
    :class:`LogMerge`) is set, as a first weight is."""
    rows, cols = codes.shape
    ph, pw = pattern.shape
    n = saturated.shape[1]
    top = y_full - 0.5
    for i in prange(rows):
        prow = pattern[i % ph]
        for q in range(min(pw, cols)):  # one table row at a time: no per-sample modulo
            r = prow[q]
            for j in range(q, cols, pw):
                le = log_e[i, j]
                if not saturated[r, min(codes[i, j], n - 1)] or not le < log_hi:
                    continue
                if use_den and not den[i, j] > 0:
                    continue
                e = math.exp(np.float64(le))
                mu = e * k
                if use_den and not mu > top - CENSORED_SDS * math.sqrt(sd_full2 + k * k / den[i, j]):
                    continue
                var = max(s_o2[r] + sqrt_a[r] * mu + b_a[r] * mu * mu, 1e-12)
                sd = math.sqrt(var)
                a = (top - mu) / sd
                lam = _inverse_mills(a)
                gap = max(lam - a, 1e-12)
                w = np.float32(k * k * lam * gap / var)
                v = np.float32(e + sd / (k * gap))
                if use_factor:
                    w *= factor[i, j]
                if den_t[i, j] > 0:
                    num_t[i, j] += w * v
                    den_t[i, j] += w
                    if use_var:
                        var_t[i, j] += w
                else:
                    num_t[i, j] = w * v
                    den_t[i, j] = w
                    if use_var:
                        var_t[i, j] = w


@njit(parallel=True, nogil=True, cache=True)
def _add_censored(num, den, var, cen_num, cen_den, use_var):  # pragma: no cover
    """``num += cen_num``, ``den += cen_den`` (and ``var += cen_den``) where ``den > 0``
    (2-D, in place)."""
    for i in prange(num.shape[0]):
        for j in range(num.shape[1]):
            if den[i, j] > 0:
                num[i, j] += cen_num[i, j]
                den[i, j] += cen_den[i, j]
                if use_var:
                    var[i, j] += cen_den[i, j]


@njit(parallel=True, nogil=True, cache=True)
def _largest_change(new, old, flags):  # pragma: no cover
    """``max |new - old|`` over the samples whose flag is 0 (0.0 when none), 2-D."""
    rows = new.shape[0]
    best = np.zeros(rows, np.float32)
    for i in prange(rows):
        m = np.float32(0.0)
        for j in range(new.shape[1]):
            if flags[i, j] == 0:
                m = max(m, abs(new[i, j] - old[i, j]))
        best[i] = m
    return float(best.max()) if rows else 0.0


def _censored_frame(acc: "LogMerge", codes, tab: ExposureTables, pat, log_e2, h: float, y_full: float, rows,
                    weight, prev_den, factor, cen, variance: bool):
    """Add one frame's clipped readings to a pass of :func:`reweight` as censored terms.

    A clipped reading whose current estimate lies more than :data:`CENSORED_SDS` noise sds
    above full scale carries no information (weight ~ phi(8)) and is skipped; one whose
    estimate lies more than that many sds below it is impossible under the model
    (probability ~ Phi(-8)): the frame saw something else there (motion, a ghost), and it is
    skipped too.  That sd combines the noise at full scale with the estimate's own
    uncertainty (``Var E = 1 / den`` of the previous pass: the prediction ``E h y_full`` is
    uncertain by ``h y_full / sqrt(den)``).

    With the previous pass's ``prev_den`` (which samples some frame measures) the terms go
    straight into ``acc``; without it they are held apart in ``cen = (num, den)``, made on
    first use, until every frame is in.  Returns ``cen`` (None when the terms go direct).

    rows : this frame's :func:`noise_rows`, whose largest values give the noise at full
        scale of the noisiest table row
    """
    shape2 = log_e2.shape
    so, sq, ba = (float(np.max(m)) for m in rows)
    sd_full2 = so + sq * y_full + ba * y_full ** 2
    log_hi = np.float32(np.log((y_full - 0.5 + CENSORED_SDS * np.sqrt(sd_full2)) / (h * y_full)))
    direct = prev_den is not None
    if not direct and cen is None:
        cen = (np.zeros(shape2, np.float32), np.zeros(shape2, np.float32))
    targets = ((acc.num.reshape(shape2), acc.den.reshape(shape2),
                (acc.var if variance else acc.num).reshape(shape2)) if direct
               else (cen[0], cen[1], cen[0]))
    _censored_rows(_read_only(codes.reshape(shape2)), pat, tab.saturated.reshape(-1, tab.n_codes), log_e2,
                   weight if prev_den is None else prev_den.reshape(shape2), direct,
                   float(h * y_full), float(y_full), float(sd_full2), log_hi, *rows,
                   weight if factor is None else factor.reshape(shape2), factor is not None,
                   *targets, direct and variance)
    return cen


#: rows of a strip of the merge (:func:`merge`; even: whole CFA periods): its sums and
#: per-sample weights stay strip-sized
STRIP_ROWS = 128


@dataclass
class Reconstruction:
    """What :func:`merge` returns, per sample of the frames (a RAW mosaic ``(H, W)``, an
    image ``(H, W, C)``).

    result : float32, ``E * scale``: scene-linear, 1.0 = the full-scale signal of an
        exposure of ``scale`` seconds
    flags : int8, 0, ``FLAG_DARK`` (below every frame's noise floor: an upper bound) or
        ``FLAG_SATURATED`` (clipped in every frame: a lower bound), after :func:`neutral_bounds`
    den : float32, the summed weights of the frames that measured each sample (of the last pass)
    variance : float32 like ``result``, its variance under the noise model, or None
    iterations : the re-weighting passes run (the most of any strip); change : the largest
        change of the last
    peak, median : the largest result and the median of an even subsample of about 100,000
        results, before :func:`neutral_bounds` (what the output type must hold)
    irls_seconds : the time the re-weighting passes took
    """

    result: np.ndarray
    flags: np.ndarray
    den: np.ndarray
    variance: np.ndarray | None = None
    iterations: int = 0
    change: float = 0.0
    peak: float = 0.0
    median: float = 0.0
    irls_seconds: float = 0.0


def merge(codes: list[np.ndarray], tables: list[ExposureTables], pattern, linear: bool, scale: float,
          weights=None, variance: bool = False, passes: int = 0, noise: list | None = None, exposures=(),
          y_full=(), adjust=None) -> Reconstruction:
    """(7) over the frames' codes (in increasing exposure), then ``passes`` re-weighting
    passes at the merged estimate (:func:`reweight`), in one loop over strips of
    :data:`STRIP_ROWS` rows of every frame: a sample's weights read only its own estimate,
    so each strip is merged and re-weighted on its own, at a strip's memory.  Pixels that
    some channel measures in no frame are given neutral bounds (:func:`neutral_bounds`).

    codes : per frame ``(H, W)`` or ``(H, W, C)`` stored codes; tables : per frame its
        :class:`ExposureTables`; pattern : the table row of each sample (see :class:`LogMerge`)
    linear : the ML estimator's linear sums; scale : the result is ``E * scale``
    weights : ``(k, codes, rows) -> (weight, factor)`` of frame k's codes in the slice
        ``rows`` for :meth:`LogMerge.add`, or None (the tables' weights)
    variance : also propagate the result's variance (:attr:`LogMerge.variance`)
    noise : per frame the per-row :class:`~hdrmerge_cli.core.noise.NoiseParams` of the
        passes; exposures, y_full : per frame ``h_j`` and ``white - black``
    adjust : the passes' ``(k, codes, w, own, rows) -> (w', factor)`` (see :func:`reweight`)
    """
    shape, last = codes[0].shape, len(codes) - 1
    log_e = np.empty(shape, np.float32)
    flags = np.empty(shape, np.int8)
    den = np.empty(shape, np.float32)
    var = np.empty(shape, np.float32) if variance else None
    rows = None if not passes else [noise_rows(n) for n in noise]
    done, change, seconds = 0, 0.0, 0.0
    for r0 in range(0, shape[0], STRIP_ROWS):
        part = slice(r0, min(shape[0], r0 + STRIP_ROWS))
        acc = LogMerge(log_e[part].shape, pattern, variance=variance and not passes)
        for k, z in enumerate(codes):
            weight, factor = (None, None) if weights is None else weights(k, z[part], part)
            acc.add(z[part], tables[k], last=k == last, weight=weight, factor=factor)
        log_e[part], flags[part] = acc.finish(linear, None if passes else scale)
        den[part] = acc.den
        if not passes:
            if variance:
                var[part] = acc.variance
            continue
        t0 = time.perf_counter()
        piece = reweight(lambda k: codes[k][part], tables, pattern, log_e[part], exposures, y_full, rows, linear,
                         passes, variance=variance, adjust=None if adjust is None else (lambda *a: adjust(*a, part)),
                         den=den[part])
        log_e[part], flags[part], den[part] = piece.result, piece.flags, piece.den
        if variance:
            var[part] = piece.variance
        done, change = max(done, piece.iterations), max(change, piece.change)
        seconds += time.perf_counter() - t0
    if passes:  # the passes' estimate is log E: E * scale, Var(E scale) = (E scale)^2 Var(log E) (the delta method)
        np.exp(log_e, out=log_e)
        log_e *= np.float32(scale)
        if variance:
            var *= log_e * log_e
    flat = log_e.reshape(-1)
    peak, median = float(np.max(log_e, initial=0.0)), float(np.median(flat[::max(1, flat.size // 100_000)]))
    neutral_bounds(log_e, flags)
    return Reconstruction(log_e, flags, den, var, done, change, peak, median, seconds)


def reweight(codes_of, tables: list[ExposureTables], pattern, log_e: np.ndarray, exposures, y_full, rows,
             linear: bool, iterations: int, tol: float = IRLS_TOLERANCE, variance: bool = False, adjust=None,
             den: np.ndarray | None = None) -> Reconstruction:
    """Iteratively re-weighted (7) on rows of every frame: each pass weights every frame
    by :func:`_irls_weight` at the previous estimate (one compiled pass per frame,
    :func:`_irls_weights_rows`), until no measured sample moves more than ``tol`` (in log
    E) or ``iterations`` passes; new arrays, as a :class:`Reconstruction` whose result is
    the estimate of ``log E`` (linear: of ``E``'s log) after the last pass, with the
    variance of ``log E`` of the last pass (``variance``) and its summed weights.

    codes_of : ``k -> codes`` of frame k, ``(H, W)`` or ``(H, W, C)``
    y_full : per frame, the full-scale code value ``white - black``
    rows : per frame, the :func:`noise_rows` of its noise (P tuples of three ``(R,)``
        float32 arrays, code values of that frame); frames that share one noise pass the
        same tuple (``[noise_rows(params)] * P``)
    adjust : optional ``(k, codes, w, own) -> (w', factor)``: frame k's weights ``w``
        (``(rows, cols)``) of its ``codes``, as the merge uses them (e.g. a resampling
        variance added), and a ghost / coverage ``factor`` in [0, 1] (or None), also
        applied to the frame's censored terms; ``own``: ``w`` is not read again, so ``w'``
        may be written into it
    den : the summed inverse-variance weights of ``log_e``'s estimate (:class:`LogMerge`'s
        ``den``).  With it the first pass drops clipped readings the estimate makes
        impossible and adds the censored terms straight into the sums; later passes use
        their predecessor's
    variance : also return the variance of ``log E`` of the last pass

    Notes: each frame's weight ``w_j = w(z) I_j`` is its certainty times its Fisher
    information ``I_j = 1 / Var(x_j)`` at the previous estimate, with the clipping-free
    variance (21), so the weighted mean's variance is ``sum_j w(z_j) w_j / (sum_j w_j)^2``
    (``1 / sum_j I_j`` for uniform certainty); censored terms (:func:`_censored_rows`) add
    their information to both sums.  ML: ``Var(E) / E^2`` (the delta method);
    unmeasured samples: :data:`UNMEASURED_RELATIVE_VARIANCE`.  The quantisation of a
    non-linear response (:func:`code_error_variance`) is not part of these weights.
    """
    if len(rows) != len(tables):
        raise ValueError(f"irls: {len(rows)} noise rows for {len(tables)} frames (one noise_rows tuple per frame)")
    prev_den = den if linear else None
    pat = _pattern(pattern)
    shape2 = _rows_cols(log_e.shape)
    # the weights as an array only where something else reads them (motion's adjustment, the
    # variance, the censored terms of a first pass without ``den``); else fused into the sums
    fused = adjust is None and not variance and (prev_den is not None or not linear)
    weight = np.empty(shape2, np.float32) if not fused else np.zeros((1, 1), np.float32)
    for it in range(1, iterations + 1):
        acc = LogMerge(log_e.shape, pattern, variance=variance)
        cen = None  # ML: the clipped readings as censored observations (_censored_rows), when held apart
        log_e2 = log_e.reshape(shape2)
        for k, (tab, h) in enumerate(zip(tables, exposures)):
            codes = codes_of(k)
            factor = None
            if fused:
                acc.add_irls(codes, tab, k == len(tables) - 1, log_e2, np.float32(h * y_full[k]), rows[k], linear)
            else:
                _irls_weights_rows(_read_only(codes.reshape(shape2)), pat, tab.certainty.reshape(-1, tab.n_codes),
                                   log_e2, np.float32(h * y_full[k]), *rows[k], linear, weight)
                # the censored terms of a pass without the previous den read the weights after
                w, factor = (weight, None) if adjust is None else adjust(k, codes, weight, prev_den is not None)
                acc.add(codes, tab, last=k == len(tables) - 1, weight=w.reshape(log_e.shape), information=True,
                        factor=factor)
            if linear and tab.saturated is not None:
                cen = _censored_frame(acc, codes, tab, pat, log_e2, h, y_full[k], rows[k], weight, prev_den, factor,
                                      cen, variance)
        # the previous pass's weights and the last frame's codes are not needed any more:
        # freed before the new sums are finished (the peak memory of the pass)
        codes = den = prev_den = None
        if cen is not None:  # only where some frame measured the sample (den > 0): a sample
            # clipped in every frame has no finite ML estimate and keeps its flag; with the
            # variance, certainty 1: w^2 Var = the information itself
            _add_censored(acc.num.reshape(shape2), acc.den.reshape(shape2),
                          (acc.var if variance else acc.num).reshape(shape2), *cen, variance)
        new, flags = acc.finish(linear)
        den = prev_den = acc.den
        change = _largest_change(new.reshape(shape2), log_e2, flags.reshape(shape2))
        log_e = new
        if change < tol:
            break
    return Reconstruction(log_e, flags, den, acc.variance if variance else None, it, change)


class LogMerge:
    """Accumulate (7) over frames given in increasing exposure order, in one fused pass per
    frame (numba, both cores): per sample one code read, two table reads and two
    read-modify-writes; nothing else is allocated.

    shape : the sample array shape, ``(H, W)`` (mosaic) or ``(H, W, C)``.
    pattern : ``(ph, pw)`` int, the table row of each sample, periodic over ``(H, W)`` for
        a mosaic (e.g. the 2 x 2 Bayer cell) or over ``(H, W * C)`` for interleaved
        channels (``[[0, 1, 2]]``); None when one table row serves every sample.

    variance : also propagate the noise model's variance of the result (a third float32
        array ``var``, and tables built ``with_variance``): per sample ``var`` sums
        ``w_j^2 Var(x_j)``, the frame's weight squared times the variance of its value
        (:func:`estimate_variance_table`), and :meth:`finish` turns it into the variance of
        the result, ``sum_j w_j^2 Var(x_j) / (sum_j w_j)^2`` (weights taken as fixed;
        ``1 / sum_j w_j`` for the ML estimator's inverse-variance weights), read from
        :attr:`variance`.  Off (the default): no ``var`` array and no variance kernels.

    Memory: two float32 arrays of ``shape`` (``num``, ``den``; three with ``variance``).
    A sample that no frame has measured yet keeps its fallback value in ``num`` and its
    class in ``den`` (0: dark, -1: saturated, decided by the shortest frame), so no flag
    array is needed.
    """

    def __init__(self, shape: tuple[int, ...], pattern: np.ndarray | None = None, variance: bool = False):
        self.shape = tuple(shape)
        self.num = np.zeros(self.shape, np.float32)
        self.den = np.zeros(self.shape, np.float32)
        self.var = np.zeros(self.shape, np.float32) if variance else None
        self.pattern = _pattern(pattern)
        self.frames = 0
        self.finished = False

    @property
    def variance(self) -> np.ndarray:
        """After :meth:`finish`: the variance of each result value, in the result's units
        (``shape`` float32, finite): of ``E * scale`` when ``finish`` got a ``scale``
        (``(E scale)^2 Var(log E)`` for the log estimator, the delta method), else of
        ``log E`` (``Var(E) / E^2`` for the ML estimator).  Unmeasured samples (flag != 0):
        :data:`UNMEASURED_RELATIVE_VARIANCE` times the squared result (1 in ``log E``)."""
        if self.var is None:
            raise ValueError("LogMerge(..., variance=True) was not asked for the variance")
        if not self.finished:
            raise ValueError("the variance is known after finish()")
        return self.var

    def _2d(self, a: np.ndarray) -> np.ndarray:
        if a.shape != self.shape:
            raise ValueError(f"samples of shape {a.shape}, expected {self.shape}")
        return a.reshape(_rows_cols(self.shape))

    def add(self, codes: np.ndarray, tables: ExposureTables, last: bool = False,
            weight: np.ndarray | None = None, information: bool = False,
            factor: np.ndarray | None = None) -> None:
        """Add one frame of stored code values ``codes`` (``shape``, uint8/uint16); ``last``
        for the longest exposure; ``weight`` per-sample weights (IRLS, deghosting) instead
        of the table's ``w(z) sigma^-2``, combined with the table's ``value``; or
        ``factor`` ``(H, W)`` float32, the table's weight times it per pixel (an image's channels share
        it; deghosting and alignment coverage), applied in the same pass, so that no
        frame-sized weight array is built (8 MP RGB: 96 MB).  With both, ``weight`` holds
        the factor already and ``factor`` (per pixel or per sample) only says where the
        frame is a sample's own (``>= 1/2``): where no frame has weight, a sample takes the
        longest own frame's fallback, not that of a frame rejected as a ghost there or not
        covering it.

        With ``variance``: ``var += w^2 Var(x_j)`` with the table's ``variance``; or, with
        ``information`` (IRLS), where ``weight = w(z) I_j`` is the certainty times the
        frame's Fisher information ``I_j = 1 / Var(x_j)`` at the current estimate
        (:func:`_irls_weight`), ``var += w(z) weight`` (``= w^2 Var(x_j)`` exactly)."""
        n = tables.n_codes
        keep = _NO_WEIGHT if factor is None else np.ascontiguousarray(factor, np.float32).reshape(factor.shape[0], -1)
        if factor is not None and weight is None and self.var is not None:  # the variance pass takes per-sample weights
            per_pixel = lookup(tables.weight, n, codes, self.pattern).reshape(factor.shape + (-1,))
            weight = (per_pixel * factor[..., None]).reshape(codes.shape)
        if weight is not None:  # 1: per-sample weights, with the table's values
            num_tab, per_sample, use_weight = tables.value, self._2d(weight.astype(np.float32, copy=False)), 1
        else:  # 2: the table's weights times the per-pixel factor; 0: the table's weights
            num_tab, per_sample, use_weight = tables.weighted_log, keep, 0 if factor is None else 2
        tabs = (tables.weight.reshape(-1, n), num_tab.reshape(-1, n), tables.fallback_log.reshape(-1, n),
                tables.above_mid.reshape(-1, n))
        use_cert, q_tab, var = information and weight is not None, _NO_WEIGHT, _NO_WEIGHT
        if self.var is not None:  # the third sum's per-code table (:func:`_accumulate`)
            q_tab = tables.certainty if use_cert else tables.variance
            if q_tab is None:
                raise ValueError("LogMerge(..., variance=True) needs tables built with_variance=True")
            q_tab, var = q_tab.reshape(-1, n), self._2d(self.var)
        _accumulate(_read_only(self._2d(codes)), self.pattern, *tabs, q_tab, per_sample, use_weight, use_cert,
                    self._mode(last), self._2d(self.num), self._2d(self.den), var, self.var is not None, keep,
                    factor is not None)
        self._added(tables)

    def add_irls(self, codes: np.ndarray, tables: ExposureTables, last: bool, log_e: np.ndarray, k: float, rows,
                 linear: bool) -> None:
        """:meth:`add` with the IRLS weights of :func:`_irls_weight` computed in the same
        pass (:func:`_accumulate_irls`): ``log_e`` the current estimate (2-D like the
        samples), ``k = h y_full``, ``rows`` :func:`noise_rows`.  Without ``variance``."""
        if self.var is not None:
            raise ValueError("add_irls does not propagate the variance: use add(weight=...)")
        n = tables.n_codes
        _accumulate_irls(_read_only(self._2d(codes)), self.pattern, tables.certainty.reshape(-1, n),
                         tables.value.reshape(-1, n), tables.fallback_log.reshape(-1, n),
                         tables.above_mid.reshape(-1, n), log_e, np.float32(k), *rows, linear, self._mode(last),
                         self._2d(self.num), self._2d(self.den))
        self._added(tables)

    def _mode(self, last: bool) -> int:
        """The kernels' ``mode``: 0 the shortest frame, 2 the longest, 1 one between."""
        return 0 if self.frames == 0 else 2 if last else 1

    def _added(self, tables: ExposureTables) -> None:
        # the ML estimator's dark floor: the longest frame's fallback at code 0, per row
        self._dark_floor = np.ascontiguousarray(tables.fallback_log.reshape(-1, tables.n_codes)[:, 0])
        self.frames += 1

    def finish(self, linear: bool = False, scale: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(result, flag)``: the log-exposure-normalised irradiance ``log E``
        (float32, finite), or with ``scale`` the linear ``E * scale`` (computed in the same
        pass), and an int8 flag per sample.  The result is written over ``num``; ``den`` is
        left as the summed weights (0 where unmeasured).

        Where some frame has weight: (7).  Where none has (flag != 0):
        ``FLAG_SATURATED`` (above mid-scale in the shortest frame): the clipping level of
        the shortest frame, ``log(gamma^-1(z_max) / h_min)``, a lower bound;
        ``FLAG_DARK``: the longest frame's value with a floor of half a code value,
        ``log(max(gamma^-1(z), gamma^-1(1/2)) / h_max)``, an upper bound (the longest frame
        that is the sample's own, see :meth:`add`).
        ``linear``: the sums hold linear values (the ML estimator); a sample whose weighted
        mean is not positive (every weighted frame read black) is dark, with the floor
        ``log(gamma^-1(1/2) / h_max)`` of its channel.

        With ``variance`` the same pass also turns ``var`` into :attr:`variance`.
        """
        if self.frames == 0:
            raise ValueError("no frame was added")
        flag = np.empty(self.shape, np.int8)
        _finish(self._2d(self.num), self._2d(self.den), _NO_WEIGHT if self.var is None else self._2d(self.var),
                self.var is not None, self.pattern, self._dark_floor, linear, -1.0 if scale is None else float(scale),
                UNMEASURED_RELATIVE_VARIANCE, self._2d(flag))
        self.finished = True
        return self.num, flag


@njit(inline="always")
def _weight_value(w_tab, num_tab, weight, use_weight, per_pixel, r, s, c, z):  # pragma: no cover
    """Sample ``(r, s)``'s weight and weighted value (table row ``c``, code ``z``) as
    :func:`_accumulate`'s ``use_weight`` says."""
    if use_weight == 1:
        w = weight[r, s]
        return w, w * num_tab[c, z]
    if use_weight == 2:
        f = weight[r, s // per_pixel]
        return w_tab[c, z] * f, num_tab[c, z] * f
    return w_tab[c, z], num_tab[c, z]


@njit(parallel=True, nogil=True, cache=True)
def _accumulate(codes, pattern, w_tab, num_tab, fb_tab, hi_tab, q_tab, weight, use_weight, use_cert, mode,
                num, den, var, use_var, keep, use_keep):  # pragma: no cover
    """One frame of (7) into ``num``/``den`` (2-D views), rows in parallel.  ``mode`` 0:
    the shortest frame (sets the fallback and the saturated/dark class), 1: a middle
    frame, 2: the longest (a dark sample takes the longest own frame's fallback).
    ``use_weight`` 0: the table's weights; 1: ``weight`` per sample (``num_tab`` the
    values); 2: the table's weights times ``weight`` per pixel (``(rows, cols /
    channels)``, ``num_tab`` the weighted values).  With ``use_keep`` the frame is a
    sample's own only where ``keep`` (per pixel or per sample) is at least 1/2.  See
    :class:`LogMerge`.

    With ``use_var``, the third accumulator of ``LogMerge(variance=True)``: ``var += w^2
    q`` (``q_tab`` the frame's per-code variance of its value), or with ``use_cert`` ``var
    += q w`` (``q_tab`` the certainty ``w(z)``, ``w`` an IRLS weight ``w(z) / Var``).
    ``var`` is set where ``den`` is (the first weighted frame)."""
    rows, cols = codes.shape
    ph, pw = pattern.shape
    top = w_tab.shape[1] - 1  # codes above the table (never valid data) read its last, clipped entry
    per_pixel = cols // weight.shape[1] if use_weight == 2 else 1
    per_keep = cols // keep.shape[1] if use_keep else 1
    for r in prange(rows):
        prow = pattern[r % ph]
        for q in range(min(pw, cols)):
            c = prow[q]
            for s in range(q, cols, pw):
                z = min(codes[r, s], top)
                w, wv = _weight_value(w_tab, num_tab, weight, use_weight, per_pixel, r, s, c, z)
                if use_var and w > 0:  # var follows den, which _add_sample then sets or adds to
                    wq = w * q_tab[c, z] if use_cert else (w * q_tab[c, z]) * w
                    if mode != 0 and den[r, s] > 0:
                        var[r, s] += wq
                    else:
                        var[r, s] = wq
                _add_sample(num, den, r, s, w, wv, fb_tab, hi_tab, c, z, mode, keep, per_keep, use_keep)


@njit(parallel=True, nogil=True, cache=True)
def _finish(num, den, var, use_var, pattern, dark_floor, linear, scale, unmeasured, flag):  # pragma: no cover
    """(7)'s ratio, the fallbacks and flags, in place over ``num``; ``scale > 0``: return
    ``exp(log E) * scale`` instead of ``log E``.

    With ``use_var`` also the variance of the result, in place over ``var``: ``q = var /
    den^2`` is the variance of the weighted mean ``num / den`` in the sums' domain; ``log
    E`` (log estimator) or ``E`` (``linear``).  Outputs: with ``scale > 0`` the variance of
    ``E scale``: ``q scale^2`` (linear) or ``(E scale)^2 q`` (from ``log E``, the delta
    method); else of ``log E``: ``q`` or ``q / E^2`` (linear).  Unmeasured samples:
    ``unmeasured`` in ``log E``, ``unmeasured (E scale)^2`` in linear units.  Capped at the
    float32 maximum (finite)."""
    rows, cols = num.shape
    ph, pw = pattern.shape
    nf = dark_floor.shape[0]
    big = np.float32(3.4e38)
    for r in prange(rows):
        prow = pattern[r % ph]
        for s in range(cols):
            d = den[r, s]
            f = 0
            q = unmeasured
            if d > 0:
                v = num[r, s] / d
                if use_var:
                    q = (var[r, s] / d) / d
                if linear:
                    if v > 0:
                        if scale > 0:
                            num[r, s] = v * scale
                            if use_var:
                                var[r, s] = min(q * scale * scale, big)
                            flag[r, s] = 0
                            continue
                        if use_var:
                            q = min((q / v) / v, big)
                        v = np.log(v)
                    else:
                        v = dark_floor[min(prow[s % pw], nf - 1)]
                        f = -1
                        q = unmeasured
            else:
                v = num[r, s]
                f = 1 if d < 0 else -1
                den[r, s] = 0.0
            if scale > 0:
                e = np.exp(v) * scale
                num[r, s] = e
                if use_var:
                    var[r, s] = min((e * e) * q, big)
            else:
                num[r, s] = v
                if use_var:
                    var[r, s] = q
            flag[r, s] = f
