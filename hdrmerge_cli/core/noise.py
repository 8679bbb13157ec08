"""The paper's camera noise model in the log domain: bias, variance, clipping-safe range.

Units (the same as :mod:`hdrmerge_cli.core.sensor`): ``x = t E`` in photo-electrons, the
linear signal ``y`` in code values (RAW: above the black level; JPEG/TIFF: ``gamma^-1(z)``
times the full scale), so that (17) reads

    y ~ N(mu, s(x)),   mu = sqrt(alpha) x,   s(x) = sigma_o^2 + alpha x + beta x^2,

or, as a function of the mean code value, ``v(mu) = sigma_o^2 + sqrt(alpha) mu +
(beta / alpha) mu^2`` (:func:`code_variance`).  Clipping ``f`` keeps ``y`` in
``[y_min, y_max]``; ``y_min > 0`` (default half a code value) keeps ``log f(y)`` finite,
like a dark pixel read as half a code.  The CRF cancels in ``g(z) = log gamma^-1(z) =
log f(y)``, so these moments hold for any CRF (quantisation aside).

A note on direction: with ``sigma_o^2`` fixed in code units, a larger gain ``alpha`` puts
more photon-noise variance on each code value (``sqrt(alpha) mu``), so the clipping-safe
range of (47)-(48) *narrows* as alpha grows.  The paper's text says it narrows as alpha
falls; its own formula (48), evaluated as printed, narrows as alpha grows, as here.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError


@functools.cache
def _gauss_legendre() -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights for the moment integrals of (19), computed on first
    use (an eigenproblem of 160: tens of ms that a merge without these integrals skips)."""
    return np.polynomial.legendre.leggauss(160)

#: default number of standard deviations between the mean and a clipping point, ``k``
#: of (47); erfc(k / sqrt 2) / 2 = 0.13 % of the mass may be clipped at k = 3
DEFAULT_K = 3.0


@dataclass(frozen=True)
class NoiseParams:
    """Parameters of (17) for one channel and ISO: read noise ``sigma_o2`` (code
    values^2), squared gain ``alpha`` (code values^2 per electron), gain FPN ``beta``."""

    sigma_o2: float
    alpha: float
    beta: float = 0.0

    def __post_init__(self):
        if not (self.alpha > 0 and np.isfinite(self.alpha)) or self.sigma_o2 < 0 or self.beta < 0:
            raise ValueError("noise parameters need alpha > 0, sigma_o2 >= 0, beta >= 0")


def noise_variance(x, sigma_o2: float, alpha: float, beta: float):
    """``s(x) = sigma_o^2 + alpha x + beta x^2`` of (17), x in photo-electrons."""
    x = np.asarray(x, dtype=np.float64)
    return sigma_o2 + alpha * x + beta * x * x


def code_variance(mu, p: NoiseParams):
    """Variance of ``y`` as a function of its mean ``mu = sqrt(alpha) x`` (code values):
    ``sigma_o^2 + sqrt(alpha) mu + (beta / alpha) mu^2``, (17) rewritten."""
    mu = np.asarray(mu, dtype=np.float64)
    return p.sigma_o2 + np.sqrt(p.alpha) * mu + (p.beta / p.alpha) * mu * mu


def quantisation_variance(lin: np.ndarray, y_full: float) -> np.ndarray:
    """Variance that the quantisation of the codes adds to the linearised signal
    ``y = gamma^-1(z) y_full``, beside the sensor variance (17) (the paper's (2) maps codes
    through ``gamma^-1``; its noise model stops at the ADC): a code step is worth ``dy/dz = y_full d gamma^-1 / dz``, and a
    uniform rounding error of one step has variance ``(dy/dz)^2 / 12``.

    lin : (N,) ``gamma^-1`` at every stored code value (one channel), in [0, 1]
    Returns (N,) variances in squared code values of ``y`` (``1/12`` for a linear CRF).
    """
    step = np.gradient(np.asarray(lin, dtype=np.float64) * y_full) if lin.size > 1 else np.ones(1)
    return step * step / 12.0


def per_channel(noise: dict[str, NoiseParams], names: list[str]) -> list[NoiseParams]:
    """Order the parameters by table channel ``names`` (``G2`` falls back to ``G``, any
    channel to ``*``)."""
    out = []
    for name in names:
        for key in (name.upper(), name.upper().rstrip("2"), "*"):
            if key in noise:
                out.append(noise[key])
                break
        else:
            raise HdrMergeError(f"no noise parameters for channel {name} (give {name}:sigma_o2=...,alpha=...)")
    return out


def log_tables(lin: np.ndarray, noise: dict[str, NoiseParams] | None, names: list[str],
               k: float = DEFAULT_K) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per channel ``c`` of ``lin`` (``(C, N)``, :meth:`~hdrmerge_cli.core.crf.CRF.codes_table`
    on the codes' grid), per code value ``(g, v_log)``, each ``(N,)``: ``g(z) = log
    gamma^-1(z)`` less its bias and the model's variance of it, from the relative variance
    ``s^2 = v(y) / y^2`` of the noise (17) (``noise`` by channel ``names``, None:
    quantisation alone) and of the quantisation through the response
    (:func:`quantisation_variance`), to second order (bias ``-s^2 / 2``, variance ``s^2 +
    2.5 s^4``); NaN where ``g`` is undefined or the reading lies outside the clipping-safe
    range of (47) (``k`` standard deviations from black and full scale: a truncated
    reading, whose log the model misjudges)."""
    params = per_channel(noise, names) if noise else [None] * len(names)
    out = []
    for c, row in enumerate(lin):
        p = params[min(c, len(params) - 1)]
        y_full = row.size - 1.0
        y = row * y_full
        var = quantisation_variance(row, y_full) + (code_variance(y, p) if p is not None else 0.0)
        sd = k * np.sqrt(var)
        ok = (row > 0) & (y - sd > 0) & (y + sd < y_full)
        with np.errstate(divide="ignore", invalid="ignore"):
            s2 = np.where(ok, var / np.where(ok, y, 1.0) ** 2, np.nan)
            out.append((np.where(ok, np.log(np.where(ok, row, 1.0)) + s2 / 2.0, np.nan), s2 + 2.5 * s2 * s2))
    return out


def log_moments_exact(x, p: NoiseParams, y_min: float = 0.5, y_max: float = 255.0):
    """Bias ``nu`` and variance ``sigma^2`` of ``log f(y)`` given ``x = t E``, by numerical
    integration of (19) with clipping, written as the moment function (45)-(46):
    ``M_n = int_{y_min}^{y_max} (log u)^n phi(u) du + (log y_min)^n P(y < y_min)
    + (log y_max)^n P(y > y_max)``.  The interior integral uses 160-point Gauss-Legendre
    on the part of ``[y_min, y_max]`` within 12 standard deviations of the mean.

    x : array of photo-electron counts (any shape).  Returns ``(nu, var)`` arrays, with
    ``nu = M_1 - log f(mu)`` (the paper's definition)."""
    from scipy.special import ndtr  # here, not at the top: merge --help's option list imports this module

    x = np.asarray(x, dtype=np.float64)
    mu = np.sqrt(p.alpha) * x
    sd = np.sqrt(np.maximum(noise_variance(x, p.sigma_o2, p.alpha, p.beta), 1e-300))
    gl_x, gl_w = _gauss_legendre()
    lo_mass = ndtr((y_min - mu) / sd)
    hi_mass = ndtr((mu - y_max) / sd)
    a = np.clip(mu - 12 * sd, y_min, y_max)
    b = np.clip(mu + 12 * sd, y_min, y_max)
    half = (b - a)[..., None] / 2
    u = (a + b)[..., None] / 2 + half * gl_x
    pdf = np.exp(-0.5 * ((u - mu[..., None]) / sd[..., None]) ** 2) / (np.sqrt(2 * np.pi) * sd[..., None])
    lu = np.log(u)
    m1 = np.sum(gl_w * lu * pdf, axis=-1) * half[..., 0]
    m2 = np.sum(gl_w * lu * lu * pdf, axis=-1) * half[..., 0]
    l_lo, l_hi = np.log(y_min), np.log(y_max)
    m1 = m1 + l_lo * lo_mass + l_hi * hi_mass
    m2 = m2 + l_lo**2 * lo_mass + l_hi**2 * hi_mass
    var = np.maximum(m2 - m1 * m1, 0.0)
    nu = m1 - np.log(np.clip(mu, y_min, y_max))
    return nu, var


def clipping_safe_range_exact(p: NoiseParams, y_min: float, y_max: float, k: float = DEFAULT_K):
    """``[y'_min, y'_max]``: the means ``mu`` with ``y_min + k sd(mu) <= mu <= y_max - k sd(mu)``,
    (47) solved exactly (each side is a quadratic in mu).  Returns ``(lo, hi)``; ``lo >= hi``
    means no clipping-safe region exists."""
    c = 1.0 - k * k * p.beta / p.alpha
    sa = np.sqrt(p.alpha)

    def roots(y0, sign):
        # (mu - y0)^2 = k^2 v(mu)  ->  c mu^2 - (2 y0 + k^2 sa) mu + y0^2 - k^2 s0 = 0
        bq = -(2 * y0 + k * k * sa)
        cq = y0 * y0 - k * k * p.sigma_o2
        disc = bq * bq - 4 * c * cq
        if disc < 0 or c <= 0:
            return None
        r = np.sqrt(disc)
        return (-bq + sign * r) / (2 * c)

    lo = roots(y_min, +1.0)
    hi = roots(y_max, -1.0)
    if lo is None or hi is None:
        return y_max, y_min  # empty
    return float(lo), float(hi)
