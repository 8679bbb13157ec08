"""Noise-parameter estimation from ordinary photographs (section "HDR reconstruction of
RAW sensor data"): local means and noise variances in 7 x 7 windows, rejection of
textured windows by the local Laplacian magnitude, and a fit of the variance model (17),

    Var[y] = sigma_o^2 + alpha x + beta x^2,   E[y] = mu = sqrt(alpha) x,

rewritten in the measured mean ``mu`` (code values above black):

    Var[y] = c0 + c1 mu + c2 mu^2,  c0 = sigma_o^2, c1 = sqrt(alpha), c2 = beta / alpha.

The affine model (beta = 0) is kept unless an F-test says the quadratic term is needed.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage, optimize, stats

from hdrmerge_cli.core.errors import HdrMergeError


@dataclass
class WindowStats:
    """Per-window statistics of one channel plane (flattened, valid windows only)."""

    mean: np.ndarray
    var: np.ndarray
    texture: np.ndarray  # max |Laplacian| in the window


#: Immerkaer (1996) noise mask: the product of two second differences, blind to any
#: signal that is linear in x or in y (ramps, smooth shading); white noise of variance
#: s^2 gives an output of variance 36 s^2.
_IMMERKAER = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])


def window_statistics(plane: np.ndarray, lo: float, hi: float, window: int = 7) -> WindowStats:
    """Local mean, noise variance and texture of ``plane`` (H, W) in ``window`` x
    ``window`` windows.  The variance is the window mean of the squared Immerkaer
    residual / 36 (smooth shading does not count as noise); the texture is the max
    |Laplacian|.  Windows touching a value ``<= lo`` or ``>= hi`` (clipping) or the
    border are dropped."""
    x = np.asarray(plane, dtype=np.float64)
    mean = ndimage.uniform_filter(x, window, mode="reflect")
    resid = ndimage.convolve(x, _IMMERKAER, mode="reflect")
    var = ndimage.uniform_filter(resid * resid, window, mode="reflect") / 36.0
    texture = ndimage.maximum_filter(np.abs(ndimage.laplace(x)), window)
    ok = (ndimage.minimum_filter(x, window + 2) > lo) & (ndimage.maximum_filter(x, window + 2) < hi)
    r = window // 2 + 2
    ok[:r], ok[-r:], ok[:, :r], ok[:, -r:] = False, False, False, False
    return WindowStats(mean[ok], var[ok], texture[ok])


def binned_variance(ws: WindowStats, bins: int = 64, reject: float = 3.0, min_count: int = 20):
    """Variance against mean: windows binned by mean (equal counts); in each bin, windows
    whose texture exceeds ``reject`` times the bin's median texture (edges, strong
    texture) are dropped and the variance is the mean over the rest.  Rejecting only
    outliers keeps the selection from favouring windows whose noise happened to be low.
    Returns (means, variances, counts) of the bins."""
    if ws.mean.size < bins * min_count:
        bins = max(ws.mean.size // min_count, 0)
    if bins < 3:
        raise HdrMergeError(f"too few usable flat windows ({ws.mean.size}) to measure the noise")
    edges = np.unique(np.quantile(ws.mean, np.linspace(0, 1, bins + 1)))
    which = np.clip(np.searchsorted(edges, ws.mean, side="right") - 1, 0, edges.size - 2)
    mus, vs, ns = [], [], []
    for b in range(edges.size - 1):
        sel = which == b
        if np.count_nonzero(sel) < min_count:
            continue
        tex = ws.texture[sel]
        flat = tex <= reject * np.median(tex)
        if np.count_nonzero(flat) < min_count:
            continue
        mus.append(np.mean(ws.mean[sel][flat]))
        vs.append(np.mean(ws.var[sel][flat]))
        ns.append(np.count_nonzero(flat))
    return np.array(mus), np.array(vs), np.array(ns)


@dataclass
class NoiseFit:
    sigma_o2: float
    alpha: float
    beta: float
    model: str  # "affine" or "quadratic"
    points: int
    f_statistic: float
    p_value: float
    residual_rms: float  # relative residual of the variance, RMS over the bins

    def as_dict(self) -> dict:
        return {k: float(v) if isinstance(v, (float, np.floating)) else v for k, v in asdict(self).items()}


def fit_noise_model(mu: np.ndarray, var: np.ndarray, counts: np.ndarray, p_threshold: float = 0.01) -> NoiseFit:
    """Weighted non-negative least squares of (17) on binned (mean, variance) points.

    Each bin's variance estimate has relative variance ~ 2 / count, so its weight is
    ``count / var_model^2`` (two re-weighting passes).  The quadratic term is kept when
    the F-test of the nested models gives ``p < p_threshold``."""
    mu, var, counts = (np.asarray(a, np.float64) for a in (mu, var, counts))
    if mu.size < 4:
        raise HdrMergeError(f"too few intensity levels ({mu.size}) to fit the noise model")

    def solve(deg):
        design = np.stack([mu**k for k in range(deg + 1)], axis=1)
        pred = np.maximum(var, 1e-12)
        for _ in range(3):
            w = np.sqrt(counts) / np.maximum(pred, 1e-12)
            coef, _ = optimize.nnls(design * w[:, None], var * w)
            pred = design @ coef
        rss = float(np.sum((counts / np.maximum(pred, 1e-12) ** 2) * (var - pred) ** 2))
        return coef, rss, pred

    c_aff, rss_aff, pred_aff = solve(1)
    c_quad, rss_quad, pred_quad = solve(2)
    dof = mu.size - 3
    f_stat = max((rss_aff - rss_quad), 0.0) / max(rss_quad / dof, 1e-300) if dof > 0 else 0.0
    p = float(stats.f.sf(f_stat, 1, dof)) if dof > 0 else 1.0
    quadratic = p < p_threshold and c_quad[2] > 0
    coef, pred = (c_quad, pred_quad) if quadratic else (np.append(c_aff, 0.0), pred_aff)
    if coef[1] <= 0:
        raise HdrMergeError("the noise does not grow with the signal: cannot estimate the gain")
    alpha = coef[1] ** 2
    resid = float(np.sqrt(np.mean(((var - pred) / np.maximum(pred, 1e-12)) ** 2)))
    return NoiseFit(float(coef[0]), float(alpha), float(coef[2] * alpha), "quadratic" if quadratic else "affine",
                    int(mu.size), float(f_stat), p, resid)
