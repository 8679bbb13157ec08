"""HDR reconstruction by the paper's main formula (7), streamed frame by frame.

(7):  log E_i = sum_j w_ij s_ij (g(z_ij) - log h_j) / sum_j w_ij s_ij

with ``g = log gamma^-1`` (2), ``h_j`` the exposure of frame j (exposure time times the
gain ratio ``sqrt(alpha_j)``, see (1)), ``w_ij = w(z_ij)`` a weighting function and
``s_ij`` the variance factor ``sigma^-2(E_i, t_j)`` evaluated at each frame's own
estimate (:func:`inverse_variance`).

Because ``w`` and ``g`` depend on the code value ``z`` and the frame ``j`` only, each
frame is reduced to lookup tables over all code values (:func:`exposure_tables`), and
merging a frame is two gathers and two additions per sample (:class:`LogMerge`).

Tables are indexed by the *stored* code value ``r`` (for RAW: before black-level
subtraction), ``z = r - black``, full scale ``z_max = white - black``.  A table has one
row per channel ``c``; a sample of channel ``c`` with stored code ``r`` reads entry
``c * N + r`` of the flattened table.

Pixels that no frame measures (weight 0 in every frame) get a finite, documented value
and a flag (see :meth:`LogMerge.finish`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import DEFAULT_K, NoiseParams, code_variance
from hdrmerge_cli.core.weights import NOISE_MODEL_WEIGHTS, WEIGHTING_FUNCTIONS
from hdrmerge_cli.core.weights_goossens2012 import (
    BOUNDED_INV_ALPHA, BOUNDED_SIGMA_O2, WeightContext, bounded_noise,
)

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
    """

    weight: np.ndarray
    weighted_log: np.ndarray
    fallback_log: np.ndarray
    above_mid: np.ndarray
    n_codes: int
    value: np.ndarray | None = None
    certainty: np.ndarray | None = None


def code_grid(n_codes: int, black: float, white: float) -> np.ndarray:
    """Normalised code values ``v = (r - black) / (white - black)`` for ``r = 0..N-1``."""
    return (np.arange(n_codes, dtype=np.float64) - black) / float(white - black)


#: smallest weight of an unclipped code: noise-model weights of codes far outside the
#: clipping-safe range underflow, and where every frame of a pixel is such a code (gaps
#: in a bracket) the frames' own codes must still decide, not the no-information fallback
WEIGHT_FLOOR = 1e-30

#: choices for the variance factor ``sigma^-2(E, t_j)`` of (7)
VARIANCE_FACTORS = ("none", "photon", "model")


def _context(weighting, y_full, exposure, noise, prior_rate, exposures, k, bounds=None):
    if weighting not in NOISE_MODEL_WEIGHTS:
        return None
    if noise is None:  # unknown camera: the conservative upper bounds of the bounded scheme
        noise = bounded_noise(y_full, *(bounds or (BOUNDED_INV_ALPHA, BOUNDED_SIGMA_O2, 0.0)))
    if not prior_rate or prior_rate <= 0:
        raise HdrMergeError("the irradiance prior needs a positive mean (the bracket looks black)")
    ctx = WeightContext(y_full, exposure, noise, prior_rate, tuple(exposures), k,
                        **({"bounds": tuple(bounds)} if bounds else {}))
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
    black = np.atleast_1d(np.asarray(black, dtype=np.float64))
    white = np.broadcast_to(np.asarray(white, dtype=np.float64), black.shape)
    rows = []
    for c, (b, wl) in enumerate(zip(black, white)):
        v = code_grid(n_codes, b, wl)
        lin = crf.inverse(np.clip(v, 0.0, 1.0), c)
        ctx = _context(weighting, wl - b, exposure, None if noise is None else noise[min(c, len(noise) - 1)],
                       prior_rate, exposures, k, bounds)
        rows.append(WEIGHTING_FUNCTIONS[weighting](v, lin, ctx))
    return np.stack(rows)


def inverse_variance(variance: str, lin: np.ndarray, y_full: float, noise: NoiseParams | None) -> np.ndarray:
    """The factor ``sigma^-2(E, t_j)`` of (7) at each frame's own estimate ``mu = y``:
    ``none`` 1; ``photon`` ``t E`` up to the common gain (the photon-limited case of (22),
    which needs no parameters); ``model`` ``mu^2 / v(mu)``, the clipping-free variance (21)
    with the noise parameters (clipping is the weights' business)."""
    y = np.clip(lin, 0.0, 1.0) * y_full
    if variance == "none":
        return np.ones_like(y)
    if variance == "photon":
        return y
    if noise is None:
        raise HdrMergeError("--variance model needs noise parameters (--noise or a profile)")
    return y * y / code_variance(y, noise)


def exposure_tables(
    n_codes: int,
    black: np.ndarray,
    white: np.ndarray,
    crf: CRF,
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
) -> ExposureTables:
    """Build the per-channel tables of one exposure for (7): the weight ``w(z)`` times the
    variance factor ``sigma^-2`` of :func:`inverse_variance`.

    n_codes : number of stored code values (256 for 8-bit, 65536 for 16-bit containers)
    black, white : (C,) black and white (clipping) level of each channel, in stored codes
    crf : the camera response; ``crf.inverse`` gives ``gamma^-1`` per channel
    weighting : a name in :data:`~hdrmerge_cli.core.weights.WEIGHTING_FUNCTIONS`
    exposure : ``h_j`` in seconds (times the gain ratio where frames differ in ISO)
    certainty : a precomputed ``(C, N)`` weight table (``merge --lut``) instead of ``weighting``
    estimator : ``log`` for (7); ``ml`` for the linear-domain inverse-variance estimate
        (Granados et al. 2010): value ``gamma^-1(z) / h``, weight ``w(z) h^2 / v(y)`` (the
        variance of ``y / h``; ``variance`` is then ignored), saturated codes censored
        (weight 0) as every weight is there
    """
    black = np.atleast_1d(np.asarray(black, dtype=np.float64))
    white = np.broadcast_to(np.asarray(white, dtype=np.float64), black.shape)
    if certainty is None:
        certainty = certainty_table(n_codes, black, white, crf, weighting, exposure, noise, prior_rate, exposures, k,
                                    bounds)
    log_h = np.log(exposure)
    rows = []
    for c, (b, wl) in enumerate(zip(black, white)):
        v = code_grid(n_codes, b, wl)
        lin = crf.inverse(np.clip(v, 0.0, 1.0), c)
        chan_noise = None if noise is None else noise[min(c, len(noise) - 1)]
        cert = certainty[min(c, certainty.shape[0] - 1)]
        if weighting in NOISE_MODEL_WEIGHTS:  # underflowed weights of unclipped codes still count
            cert = np.where((v > 0) & (v < 1), np.maximum(cert, WEIGHT_FLOOR), 0.0)
        half_code = crf.inverse(np.array([0.5 / (wl - b)]), c)[0]
        fallback = np.log(np.maximum(lin, max(half_code, np.finfo(np.float64).tiny))) - log_h
        if estimator == "ml":
            y = lin * (wl - b)
            var_y = code_variance(y, chan_noise) if chan_noise is not None else np.maximum(y, 1.0)
            w = cert * (exposure * (wl - b)) ** 2 / np.maximum(var_y, 1e-12)  # 1 / Var[gamma^-1(z) / h]
            value = lin / exposure
        else:
            w = cert * inverse_variance(variance, lin, wl - b, chan_noise)
            with np.errstate(divide="ignore"):
                value = np.where(lin > 0, np.log(lin) - log_h, 0.0)  # finite wherever it is used
        w = np.where((v > 0) & (v < 1), np.maximum(w, WEIGHT_FLOOR), 0.0) if weighting in NOISE_MODEL_WEIGHTS else w
        rows.append((w, w * value, fallback, v > 0.5, value, cert))
    w, wv, fb, hi, val, cert = (np.concatenate(col) for col in zip(*rows))
    return ExposureTables(
        w.astype(np.float32), wv.astype(np.float32), fb.astype(np.float32), hi, n_codes,
        val.astype(np.float32), cert.astype(np.float32),
    )


def flat_index(codes: np.ndarray, channel_offset: np.ndarray | None) -> np.ndarray:
    """Index of each sample into flattened ``(C * N,)`` tables.

    codes : (H, W) or (H, W, C) integer stored code values
    channel_offset : ``c * N`` for each sample's channel, broadcastable to ``codes``
        (``(C,)`` for interleaved RGB, ``(H, W)`` for a CFA mosaic), or None when all
        channels share one table.
    """
    if channel_offset is None:
        return codes
    return codes.astype(np.int32) + channel_offset


def irls_weights(certainty: np.ndarray, log_e: np.ndarray, exposure: float, y_full: float, noise_maps,
                 linear: bool) -> np.ndarray:
    """Per-sample weights of one frame at the current estimate (iteratively re-weighted
    (7)): ``w(z) sigma^-2(E_i, t_j)`` with ``mu_j = E_i h_j y_full`` and the clipping-free
    variance (21), ``mu^2 / v(mu)`` (log estimator) or ``(h y_full)^2 / v(mu)`` (ML);
    a sample with any certainty keeps at least :data:`WEIGHT_FLOOR`, as in the tables.

    noise_maps : (sigma_o2, sqrt_alpha, beta / alpha), each broadcastable to the samples."""
    s_o2, sqrt_a, b_a = noise_maps
    mu = np.exp(log_e) * np.float32(exposure * y_full)
    var = s_o2 + sqrt_a * mu + b_a * mu * mu
    num = mu * mu if not linear else np.float32((exposure * y_full) ** 2)
    w = certainty * (num / np.maximum(var, np.float32(1e-12)))
    return np.where(certainty > 0, np.maximum(w, np.float32(WEIGHT_FLOOR)), np.float32(0.0))


class LogMerge:
    """Accumulate (7) over frames given in increasing exposure order.

    shape : the sample array shape, ``(H, W)`` (mosaic) or ``(H, W, C)``.
    Memory: three float32 and one bool array of that shape.
    """

    def __init__(self, shape: tuple[int, ...]):
        self.num = np.zeros(shape, np.float32)
        self.den = np.zeros(shape, np.float32)
        self.fallback = np.empty(shape, np.float32)
        self.saturated = None  # set by the first (shortest) frame
        self.frames = 0

    def add(self, index: np.ndarray, tables: ExposureTables, last: bool = False, weight: np.ndarray | None = None) -> None:
        """Add one frame; ``index`` from :func:`flat_index`; ``last`` for the longest;
        ``weight`` per-sample weights (IRLS) instead of the table's."""
        if weight is None:
            self.den += tables.weight.take(index)
            self.num += tables.weighted_log.take(index)
        else:
            self.den += weight
            self.num += weight * tables.value.take(index)
        if self.saturated is None:
            self.saturated = tables.above_mid.take(index)
            np.copyto(self.fallback, tables.fallback_log.take(index))
        elif last:
            np.copyto(self.fallback, tables.fallback_log.take(index), where=~self.saturated)
        self.frames += 1

    def finish(self, linear: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(log_E, flag)``: the log-exposure-normalised irradiance (float32, finite)
        and an int8 flag per sample.

        Where some frame has weight: (7).  Where none has (flag != 0):
        ``FLAG_SATURATED`` (above mid-scale in the shortest frame): the clipping level of
        the shortest frame, ``log(gamma^-1(z_max) / h_min)``, a lower bound;
        ``FLAG_DARK``: the longest frame's value with a floor of half a code value,
        ``log(max(gamma^-1(z), gamma^-1(1/2)) / h_max)``, an upper bound.
        ``linear``: the sums hold linear values (the ML estimator); their ratio is logged.
        """
        if self.frames == 0:
            raise ValueError("no frame was added")
        measured = self.den > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            est = self.num / self.den
            if linear:
                measured &= est > 0
                est = np.log(est)
            log_e = np.where(measured, est, self.fallback)
        flag = np.zeros(self.num.shape, np.int8)
        flag[~measured & self.saturated] = FLAG_SATURATED
        flag[~measured & ~self.saturated] = FLAG_DARK
        return log_e, flag
