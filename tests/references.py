"""NumPy / colour-demosaicing reference implementations that the tests check the compiled
kernels of :mod:`hdrmerge_cli` against.  No command or API function reaches these; they
are the formulas written out plainly, each an independent check of a fused kernel."""
from __future__ import annotations

import numpy as np

from benchmarks import quiet_import
from hdrmerge_cli.core.cfa import bayer_channels, camera_to_rec709
from hdrmerge_cli.core.reconstruct import WEIGHT_FLOOR


def demosaic(cfa: np.ndarray, pattern: str) -> np.ndarray:
    """Bayer mosaic ``(H, W)`` -> ``(H, W, 3)`` float32 by Malvar, He and Cutler (2004),
    colour-demosaicing's ``demosaicing_CFA_Bayer_Malvar2004``: the reference of the fused
    kernel :func:`hdrmerge_cli.core.cfa_to_rgb.raw_to_rgb_rows` and of
    :func:`hdrmerge_cli.core.cfa.demosaic_variance`."""
    malvar = quiet_import("colour_demosaicing").demosaicing_CFA_Bayer_Malvar2004
    # colour computes in its default float dtype (float64); float32 is what the fused kernel
    # stores.  The default is process-wide, so it is put back: colour's other functions in
    # the same test session keep float64.
    utilities = quiet_import("colour").utilities
    utilities.set_default_float_dtype(np.float32)
    try:
        return np.asarray(malvar(cfa, pattern), dtype=np.float32)
    finally:
        utilities.set_default_float_dtype(np.float64)


def raw_to_rgb_rows(mosaic: np.ndarray, frame, y0: int, y1: int, matrix=None) -> np.ndarray:
    """The reference of :func:`hdrmerge_cli.pipeline.output._raw_to_rgb_rows`: NumPy white
    balance, colour-demosaicing's Malvar (2004) on the strip with a halo of rows, the
    matrix (default: the frame's camera matrix)."""
    from hdrmerge_cli.pipeline.output import STRIP_HALO

    a, b = max(0, y0 - STRIP_HALO), min(mosaic.shape[0], y1 + STRIP_HALO)
    part = mosaic[a:b]
    colors = bayer_channels(frame.cfa_pattern, part.shape)  # a is even: same CFA phase as row 0
    balanced = part * frame.white_balance.astype(np.float32)[colors]
    rgb = demosaic(balanced, frame.cfa_pattern)[y0 - a:y1 - a]
    return camera_to_rec709(rgb, frame.color_matrix if matrix is None else matrix)


def combined_variance(weights, variances) -> np.ndarray:
    """Variance of a weighted mean of independent estimates, the reference formula the
    streamed accumulators implement: ``Var(sum_j w_j x_j / sum_j w_j) = sum_j w_j^2
    Var(x_j) / (sum_j w_j)^2`` (weights taken as fixed); for inverse-variance weights
    ``w_j = 1 / Var(x_j)`` it is ``1 / sum_j w_j``, the inverse of the summed Fisher
    information.  weights, variances : ``(P, ...)``; returns ``(...)`` float64, NaN where
    every weight is 0."""
    w = np.asarray(weights, np.float64)
    q = np.asarray(variances, np.float64)
    den = w.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, (w * w * np.where(w > 0, q, 0.0)).sum(axis=0) / (den * den), np.nan)


def irls_weights(certainty: np.ndarray, log_e: np.ndarray, exposure: float, y_full: float, noise_maps,
                 linear: bool) -> np.ndarray:
    """Per-sample weights of one frame at the current estimate (iteratively re-weighted
    (7)): ``w(z) sigma^-2(E_i, t_j)`` with ``mu_j = E_i h_j y_full`` and the clipping-free
    variance (21), ``mu^2 / v(mu)`` (log estimator) or ``(h y_full)^2 / v(mu)`` (ML);
    a sample with any certainty keeps at least
    :data:`~hdrmerge_cli.core.reconstruct.WEIGHT_FLOOR`, as in the tables.

    noise_maps : (sigma_o2, sqrt_alpha, beta / alpha), each broadcastable to the samples."""
    s_o2, sqrt_a, b_a = noise_maps
    mu = np.exp(log_e) * np.float32(exposure * y_full)
    var = s_o2 + sqrt_a * mu + b_a * mu * mu
    num = mu * mu if not linear else np.float32((exposure * y_full) ** 2)
    w = certainty * (num / np.maximum(var, np.float32(1e-12)))
    return np.where(certainty > 0, np.maximum(w, np.float32(WEIGHT_FLOOR)), np.float32(0.0))


def censored_terms(log_e: np.ndarray, exposure: float, y_full: float, noise_maps) -> tuple[np.ndarray, np.ndarray]:
    """A reading clipped at full scale in the ML estimator's re-weighting: the censored
    observation ``y > y_full - 1/2`` (the top code's lower edge) of ``y ~ N(mu, v(mu))``,
    ``mu = E h y_full``, as a pseudo-observation ``(weight, value)`` of the weighted mean,
    so that one pass is a Fisher-scoring (Newton) step on the censored likelihood.

    With ``a = (y_full - 1/2 - mu) / sd`` and the inverse Mills ratio
    ``lam = phi(a) / Phi(-a)``, the censored log-likelihood ``log Phi(-a)`` has score
    ``k lam / sd`` and observed information ``k^2 lam (lam - a) / sd^2`` in ``E``
    (``k = h y_full``; the dependence of ``sd`` on ``mu`` is neglected).  Weight = that
    information, value = ``E + score / information = E + sd / (k (lam - a))``: at a fixed point
    the weighted mean solves the censored likelihood equation, where dropping the clipped
    readings (the tables' weight 0) biases a sample near saturation low (its unclipped
    readings are the truncated lower part of their distribution) and ignores that the
    clipped frames saw more than full scale.  A reading far above full scale carries no
    information and gets weight ~0.  Returns float32 ``(weight, value)`` like ``log_e``."""
    from scipy.special import log_ndtr

    s_o2, sqrt_a, b_a = (np.asarray(m, np.float64) for m in noise_maps)
    k = float(exposure) * float(y_full)
    e = np.exp(np.asarray(log_e, np.float64))
    mu = e * k
    sd = np.sqrt(np.maximum(s_o2 + sqrt_a * mu + b_a * mu * mu, 1e-12))
    a = (y_full - 0.5 - mu) / sd
    lam = np.exp(-0.5 * a * a - 0.5 * np.log(2 * np.pi) - log_ndtr(-a))
    gap = np.maximum(lam - a, 1e-12)  # > 0 always; lam - a -> 1/a for large a
    weight = k * k * lam * gap / (sd * sd)
    value = e + sd / (k * gap)
    return weight.astype(np.float32), value.astype(np.float32)
