"""Weighting (certainty) functions ``w(z)`` for the reconstruction formula (7).

Every function here is evaluated once per exposure and channel over *all* code values,
giving a table that the merge gathers from (the paper notes that such weights depend on
``z`` and ``j`` alone).  Arguments:

v : (N,) float64
    normalised code values ``z / z_max`` of the table, increasing; entries ``<= 0`` are
    dark-clipped (or below the black level) and entries ``>= 1`` are saturated.
lin : (N,) float64
    the linear signal ``gamma^-1(v)`` in [0, 1] at the same codes (eq. (2) without log).

ctx : a :class:`~hdrmerge_cli.core.weights_goossens2012.WeightContext` (noise model,
    exposure, prior); ignored by the classical functions (8)-(11).

Each returns ``(N,)`` float64 weights in [0, 1] with maximum 1 over the valid codes and
exactly 0 at clipped codes, so that clipped observations never bias the estimate (the
paper's condition ``nu != 0 => w = 0`` below (23)).

Callers pick a function by name from :data:`WEIGHTING_FUNCTIONS`.
"""
from __future__ import annotations

import numpy as np

from hdrmerge_cli.core.weights_goossens2012 import (
    weights_goossens2012_bounded,
    weights_goossens2012_direct,
    weights_goossens2012_optimal,
    weights_goossens2012_probabilistic,
)

#: exponent ``a`` and width ``b`` of the exponential power weight (11).  The paper says
#: they "were determined experimentally" without giving values; these keep the weight
#: above 0.5 over the central 95 % of the code range.
DENEVE_A = 12.0
DENEVE_B = 1.0


def _finish(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Zero the clipped codes, clamp to [0, 1] and scale the maximum to 1."""
    w = np.where((v > 0.0) & (v < 1.0), np.nan_to_num(w, nan=0.0, posinf=0.0), 0.0)
    w = np.clip(w, 0.0, None)
    top = w.max(initial=0.0)
    return w / top if top > 0 else w


def weights_debevec1997_triangle(v: np.ndarray, lin: np.ndarray, ctx=None) -> np.ndarray:
    """Triangle ("hat") weight of Debevec and Malik, eq. (8):
    ``w = z - z_min`` below mid-scale, ``z_max - z`` above."""
    return _finish(np.minimum(v, 1.0 - v), v)


def weights_mann1995_slope(v: np.ndarray, lin: np.ndarray, ctx=None) -> np.ndarray:
    """Mann and Picard / Mitsunaga and Nayar, eqs. (9)-(10): ``w = dz / d log q(z)``,
    the inverse slope of ``g(z) = log gamma^-1(z)``; for a linear CRF ``w = z``.

    The derivative is taken numerically on the table (central differences)."""
    x = np.clip(lin, 0.0, None)
    dx = np.gradient(x, v)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = x / dx
    return _finish(w, v)


def weights_deneve2009_exponential_power(v: np.ndarray, lin: np.ndarray, ctx=None) -> np.ndarray:
    """Exponential power weight of the authors' earlier work, eq. (11):
    ``w = exp(-|(z - z_mid) / (b z_mid)|^a)`` with :data:`DENEVE_A`, :data:`DENEVE_B`."""
    return _finish(np.exp(-np.abs((2.0 * v - 1.0) / DENEVE_B) ** DENEVE_A), v)


def weights_robertson2003_gaussian(v: np.ndarray, lin: np.ndarray, ctx=None) -> np.ndarray:
    """Gaussian weight of Robertson, Borman and Stevenson (2003):
    ``w = exp(-4 (z - z_mid)^2 / z_mid^2)``."""
    return _finish(np.exp(-4.0 * (2.0 * v - 1.0) ** 2), v)


def weights_uniform(v: np.ndarray, lin: np.ndarray, ctx=None) -> np.ndarray:
    """Constant weight over the unclipped codes: the "w_ij = 1" case of (12)."""
    return _finish(np.ones_like(v), v)


#: name -> weighting function ``(v, lin, ctx) -> w``, one per name of
#: :data:`hdrmerge_cli.core.choices.WEIGHTINGS` (the CLI's choices).  The last four need a :class:`~hdrmerge_cli.core.weights_goossens2012.WeightContext`
#: (the noise model); ``bounded`` needs no noise parameters (it uses upper bounds).
WEIGHTING_FUNCTIONS = {
    "triangle": weights_debevec1997_triangle,
    "mann": weights_mann1995_slope,
    "deneve": weights_deneve2009_exponential_power,
    "gaussian": weights_robertson2003_gaussian,
    "uniform": weights_uniform,
    "probabilistic": weights_goossens2012_probabilistic,
    "direct": weights_goossens2012_direct,
    "optimal": weights_goossens2012_optimal,
    "bounded": weights_goossens2012_bounded,
}

#: weightings that use the noise model (they need a WeightContext)
NOISE_MODEL_WEIGHTS = ("probabilistic", "direct", "optimal", "bounded")
