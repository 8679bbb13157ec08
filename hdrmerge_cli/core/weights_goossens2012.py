"""The paper's noise-model weighting functions (section "Probabilistic formulation of the
weighting function", Appendices 3-4), as tables over code values.

All work in the linear code domain of :mod:`hdrmerge_cli.core.noise`: a code ``z`` of a
frame with exposure ``h`` is the observation ``y = gamma^-1(z) * y_full``; its mean is
``mu = sqrt(alpha) h E``.  The irradiance prior is exponential (maximum entropy) with mean
``prior_rate`` code values per second, so ``mu`` has prior mean ``prior_rate * h``.

- :func:`weights_goossens2012_probabilistic`, (32): ``Pr[E_min < E < E_max | z]``, the
  posterior probability that the pixel lies in the clipping-safe range (47);
- :func:`weights_goossens2012_direct`, (33): the same with ``s`` evaluated at the
  observation (Appendix 4), a closed form of normal CDFs;
- :func:`weights_goossens2012_optimal`, (28)-(29): the posterior expectation of
  ``A sigma^2 / (sigma^2 + P nu^2)`` with the exact moments (19).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hdrmerge_cli.core.jit import njit, prange
from hdrmerge_cli.core.noise import DEFAULT_K, NoiseParams, clipping_safe_range_exact, code_variance, log_moments_exact

#: code levels on which the posterior weights are computed (then interpolated)
LEVELS = 1024
#: points of the posterior integration grid over the mean signal
GRID = 2400


#: the paper's upper bounds for JPEG input ("HDR reconstruction from JPEG compressed LDR
#: digital photographs"): max(1/alpha) = 0.005, max(sigma_o^2) = 0.02, beta = 0, read on
#: the normalised signal scale [0, 1] (where they give the bell-shaped weights of Fig. 16:
#: sigma_o = 0.14 of full scale, i.e. 36 codes of 255).  Here "1/alpha" is the
#: photon-noise variance per unit signal, ``sqrt(alpha)`` in this module's code units.
BOUNDED_INV_ALPHA = 0.005
BOUNDED_SIGMA_O2 = 0.02


@dataclass(frozen=True)
class WeightContext:
    """What noise-model weights need beyond the code values.

    y_full : full scale of the linear signal in code values (RAW: white - black)
    exposure : this frame's exposure ``h`` (s)
    noise : the (17) parameters of this channel, in code values of ``y``
    prior_rate : mean of the exponential irradiance prior, code values per second
    exposures : every exposure of the bracket (``P`` and the normalisation ``A`` of (28))
    k : clipping margin of (47) in standard deviations
    y_min : the lowest positive reading (half a code value)
    bounds : upper bounds ``(1/alpha, sigma_o^2, beta)`` on the normalised scale, used by
        ``bounded`` (default: the paper's JPEG values)
    """

    y_full: float
    exposure: float
    noise: NoiseParams
    prior_rate: float
    exposures: tuple = field(default_factory=tuple)
    k: float = DEFAULT_K
    y_min: float = 0.5
    bounds: tuple = (BOUNDED_INV_ALPHA, BOUNDED_SIGMA_O2, 0.0)  # (max 1/alpha, max sigma_o^2, max beta)

    @property
    def frames(self) -> int:
        return max(len(self.exposures), 1)

    def safe_range(self) -> tuple[float, float]:
        """``[y'_min, y'_max]`` of (47) in code values of this frame."""
        return clipping_safe_range_exact(self.noise, self.y_min, self.y_full, self.k)


def log_normal_interval(a, b):
    """``log(Phi(b) - Phi(a))`` for ``a <= b`` without cancellation: computed on the side
    of the tails that is small (``log_ndtr``), as DESIGN.md asks for erf differences."""
    from scipy.special import log_ndtr  # here, not at the top: importing scipy.special costs 0.2 s

    a, b = np.broadcast_arrays(np.asarray(a, np.float64), np.asarray(b, np.float64))
    upper = a > 0  # both in the upper tail: use Phi(-a) - Phi(-b)
    hi = np.where(upper, log_ndtr(-a), log_ndtr(b))
    lo = np.where(upper, log_ndtr(-b), log_ndtr(a))
    with np.errstate(divide="ignore", invalid="ignore"):
        out = hi + np.log1p(-np.exp(lo - hi))
    return np.where(b > a, out, -np.inf)


def _levels(v: np.ndarray) -> np.ndarray:
    return np.linspace(0.0, 1.0, LEVELS) if v.size > LEVELS else np.clip(v, 0.0, 1.0)


def _observations(v: np.ndarray, lin: np.ndarray, levels: np.ndarray, ctx: WeightContext) -> np.ndarray:
    """The observation ``y = gamma^-1(z) y_full`` at each of ``levels``."""
    return (np.interp(levels, np.clip(v, 0, 1), lin) if levels.size != v.size else lin) * ctx.y_full


def _to_table(v, vals_at, levels):
    """Interpolate weights computed at ``levels`` onto the table's codes ``v``."""
    w = np.interp(np.clip(v, 0, 1), levels, vals_at) if levels.size != v.size else vals_at
    return np.where((v > 0) & (v < 1), np.clip(np.nan_to_num(w), 0.0, 1.0), 0.0)


def _posterior_expectation(y_obs: np.ndarray, ctx: WeightContext, func_of_mu) -> np.ndarray:
    """``E[func(mu) | y]`` under ``y ~ N(mu, v(mu))`` and ``mu ~ Exp(mean prior_rate * h)``,
    by trapezoid integration on a log-spaced grid of ``mu``.  y_obs : (L,) -> (L,)."""
    m_prior = ctx.prior_rate * ctx.exposure
    mu = np.geomspace(1e-4, 50.0 * max(ctx.y_full, m_prior), GRID)
    var = code_variance(mu, ctx.noise)
    base = -0.5 * np.log(var) - mu / m_prior + np.log(mu)  # prior and d mu = mu d log mu
    f = np.broadcast_to(np.asarray(func_of_mu(mu), np.float64), mu.shape)
    return _posterior_mean(np.asarray(y_obs, np.float64), mu, 0.5 / var, base, np.ascontiguousarray(f))


#: posterior terms this far (in log) below the largest are skipped: their total is below
#: GRID * exp(-60) ~ 2e-23 of the sum
_LOG_NEGLIGIBLE = 60.0


@njit(parallel=True, cache=True)
def _posterior_mean(y_obs, mu, half_inv_var, base, f):  # pragma: no cover
    """``sum_g p_g f_g / sum_g p_g`` per observation with ``log p_g = -(y - mu_g)^2 / (2 v_g)
    + base_g``, shifted by its maximum; exponentials only where they are not negligible."""
    out = np.empty(y_obs.shape[0])
    for i in prange(y_obs.shape[0]):
        y = y_obs[i]
        top = -np.inf
        for g in range(mu.shape[0]):
            top = max(top, base[g] - (y - mu[g]) ** 2 * half_inv_var[g])
        num = 0.0
        den = 0.0
        for g in range(mu.shape[0]):
            lp = base[g] - (y - mu[g]) ** 2 * half_inv_var[g] - top
            if lp > -_LOG_NEGLIGIBLE:
                p = np.exp(lp)
                num += p * f[g]
                den += p
        out[i] = num / den
    return out


def weights_goossens2012_probabilistic(v: np.ndarray, lin: np.ndarray, ctx: WeightContext) -> np.ndarray:
    """(32): ``w = Pr[E_min < E < E_max | z]`` with ``[E_min, E_max]`` the clipping-safe
    range (47) of this frame; the posterior is integrated numerically (Bayes' rule (53))."""
    levels = _levels(v)
    lo, hi = ctx.safe_range()
    if lo >= hi:
        return np.zeros_like(v)
    w = _posterior_expectation(_observations(v, lin, levels, ctx), ctx,
                               lambda mu: ((mu >= lo) & (mu <= hi)).astype(float))
    return _to_table(v, w, levels)


def _log_direct(lin: np.ndarray, ctx: WeightContext) -> np.ndarray:
    """``log w`` of (33) (see :func:`weights_goossens2012_direct`)."""
    from scipy.special import log_ndtr

    lo, hi = ctx.safe_range()
    y = lin * ctx.y_full
    s = code_variance(np.maximum(y, 0.0), ctx.noise)
    sd = np.sqrt(np.maximum(s, 1e-300))
    m = y - s / (ctx.prior_rate * ctx.exposure)
    return np.minimum(log_normal_interval((lo - m) / sd, (hi - m) / sd) - log_ndtr(m / sd), 0.0)


def weights_goossens2012_direct(v: np.ndarray, lin: np.ndarray, ctx: WeightContext) -> np.ndarray:
    """(33) of Appendix 4: with ``s`` taken at the observation ``y = gamma^-1(z)`` (52), the
    posterior of ``mu`` is a normal ``N(y - s(y) / (prior_rate h), s(y))`` truncated to
    ``mu >= 0``, and ``w = [Phi((y'_max - m) / sd) - Phi((y'_min - m) / sd)] /
    [1 - Phi(-m / sd)]``, evaluated in logs on the small side of the tails."""
    lo, hi = ctx.safe_range()
    if lo >= hi:
        return np.zeros_like(v)
    return _to_table(v, np.exp(_log_direct(lin, ctx)), v)


def _optimal_ratio(mu: np.ndarray, ctx: WeightContext) -> np.ndarray:
    """``A sigma^2 / (sigma^2 + P nu^2)`` of (28) at the means ``mu`` of this frame, with
    ``A`` normalising the maximum over the bracket's exposures at the same E to 1."""
    p, a = ctx.noise, np.sqrt(ctx.noise.alpha)

    def ratio(m):
        nu, var = log_moments_exact(m / a, p, ctx.y_min, ctx.y_full)
        den = var + ctx.frames * nu * nu
        return np.where(den > 0, var / np.maximum(den, 1e-300), 1.0)

    own = ratio(mu)
    others = [ratio(mu * h / ctx.exposure) for h in ctx.exposures] or [own]
    return own / np.maximum(np.max(others, axis=0), 1e-300)


def weights_goossens2012_optimal(v: np.ndarray, lin: np.ndarray, ctx: WeightContext) -> np.ndarray:
    """(29): the posterior expectation of the optimal weight (28), ``E[A sigma^2 /
    (sigma^2 + P nu^2) | z]``, with the exact bias and variance (19)."""
    levels = _levels(v)
    w = _posterior_expectation(_observations(v, lin, levels, ctx), ctx, lambda mu: _optimal_ratio(mu, ctx))
    return _to_table(v, w, levels)


def bounded_noise(y_full: float, inv_alpha: float = BOUNDED_INV_ALPHA, sigma_o2: float = BOUNDED_SIGMA_O2,
                  beta: float = 0.0) -> NoiseParams:
    """Noise parameters (code units of a signal with full scale ``y_full``) from upper
    bounds given on the normalised scale, for "Dealing with unknown camera model
    parameters": variance ``sigma_o2 + inv_alpha * y`` on [0, 1] becomes
    ``sigma_o2 y_full^2 + (inv_alpha y_full) mu`` in code values."""
    gain = inv_alpha * y_full  # sqrt(alpha) in code units
    return NoiseParams(sigma_o2 * y_full**2, gain**2, beta * gain**2)


def bounds_for_width(delta: float, inv_alpha: float | None = None, sigma_o2: float | None = None, beta: float = 0.0,
                     k: float = DEFAULT_K) -> tuple[float, float, float]:
    """"Dealing with unknown camera model parameters": fix the width of the clipping-safe
    range, ``Delta = (y'_max - y'_min)`` as a fraction of full scale, and one upper bound
    (``inv_alpha`` or ``sigma_o2``, normalised scale); solve for the other (the range
    narrows monotonically as either grows).  Returns ``(inv_alpha, sigma_o2, beta)``."""
    from scipy.optimize import brentq

    if (inv_alpha is None) == (sigma_o2 is None):
        raise ValueError("give exactly one of inv_alpha and sigma_o2 with delta")
    if not 0 < delta < 1:
        raise ValueError("delta is a fraction of full scale, between 0 and 1")
    y_full = 1000.0  # any scale: the width is scale-free on the normalised signal

    def width(free):
        noise = bounded_noise(y_full, *((inv_alpha, free) if sigma_o2 is None else (free, sigma_o2)), beta)
        lo, hi = clipping_safe_range_exact(noise, 0.5, y_full, k)
        return (hi - lo) / y_full - delta

    top = 1.0
    if width(1e-12) < 0:
        raise ValueError(f"the fixed bound alone leaves a range narrower than delta = {delta:g}")
    while width(top) > 0:
        top *= 4
    free = brentq(width, 1e-12, top, xtol=1e-14, rtol=1e-10)
    return (inv_alpha, free, beta) if sigma_o2 is None else (free, sigma_o2, beta)


def weights_goossens2012_bounded(v: np.ndarray, lin: np.ndarray, ctx: WeightContext) -> np.ndarray:
    """Unknown camera parameters: the direct formula (33) evaluated with upper bounds on
    ``1/alpha``, ``sigma_o^2`` and ``beta`` (:func:`bounded_noise`), which shrink the
    clipping-safe range and make the weights conservative (Fig. 16).

    Scaled to max 1 per exposure, in the log domain: with such large noise bounds the
    exponential prior pulls a short exposure's posterior to E ~ 0, and (33) underflows for
    every code; the frame then keeps the shape of its weights instead of none at all."""
    bctx = WeightContext(ctx.y_full, ctx.exposure, bounded_noise(ctx.y_full, *ctx.bounds), ctx.prior_rate,
                         ctx.exposures, ctx.k, ctx.y_min)
    logw = np.where((v > 0) & (v < 1), _log_direct(lin, bctx), -np.inf)
    top = logw.max(initial=-np.inf)
    if not np.isfinite(top):
        return np.zeros_like(v)
    return _to_table(v, np.exp(logw - top), v)
