"""Photon-transfer calibration from dark and flat-field frames (EMVA 1288, release 4.0,
sections 6-8), in the units of the paper's model (17):

- temporal variance from a pair of frames A, B of the same exposure:
  ``sigma^2 = Var[A - B] / 2`` (scene, vignetting and fixed patterns cancel);
- darks: dark offset ``mu_dark`` = mean of the darks, read noise
  ``sigma_o^2 = sigma^2_dark`` (quantisation included, as the paper lumps it);
- flats at several exposures: ``sigma^2_temporal(mu) = sigma_o^2 + K mu`` with
  ``mu = mean - mu_dark``; the slope ``K = sqrt(alpha)`` (the "system gain" in code values
  per electron) by least squares over the exposures whose mean is at most 70 % of the
  range (EMVA's linear range);
- gain FPN (PRNU): the spatial variance of the average of the L frames of one exposure,
  ``s^2 = (beta / alpha) mu^2 + sigma^2_temporal / L + DSNU^2``, measured with the
  Immerkaer residual so that smooth illumination falloff does not count; the dark-signal
  non-uniformity is measured the same way on the averaged darks.  ``beta / alpha`` is the
  weighted least-squares slope of the excess over ``mu^2`` (weights from the sampling
  variance of each level's variances), kept only when its one-sided z-test gives
  ``p < 0.01``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, special

from hdrmerge_cli.core.calibrate import IMMERKAER
from hdrmerge_cli.core.errors import HdrMergeError

#: sum over all lags of the squared autocorrelation of the Immerkaer residual of white
#: noise, ((1 + 16 + 36 + 16 + 1) / 36)^2: its plane mean has the variance of N / 3.78
#: independent squares
IMMERKAER_SUM_RHO2 = (70.0 / 36.0) ** 2

#: EMVA 1288: the gain is fitted on exposures up to 70 % of saturation
LINEAR_RANGE = 0.7


def temporal_variance(frames: list[np.ndarray]) -> float:
    """``Var[A - B] / 2`` averaged over consecutive pairs of ``frames`` (each (H, W))."""
    if len(frames) < 2:
        raise HdrMergeError("a temporal variance needs at least two frames of one exposure")
    return float(np.mean([np.var(np.asarray(a, np.float64) - b) / 2.0 for a, b in zip(frames[:-1], frames[1:])]))


def spatial_variance(plane: np.ndarray) -> float:
    """Variance of the pixel-to-pixel (white) part of ``plane`` (H, W): the mean squared
    Immerkaer residual / 36, blind to smooth shading (interior pixels only)."""
    r = ndimage.convolve(np.asarray(plane, np.float64), IMMERKAER, mode="reflect")[1:-1, 1:-1]
    return float(np.mean(r * r) / 36.0)


@dataclass
class PTCResult:
    """Photon-transfer results for one channel.  ``levels``: per flat exposure the mean
    above the dark offset, the temporal variance, the spatial variance of the averaged
    frames and whether it lies in the linear range (arrays of equal length)."""

    sigma_o2: float | None
    alpha: float
    beta: float
    model: str
    dark_offset: float | None
    dsnu2: float
    mean: np.ndarray
    temporal: np.ndarray
    spatial: np.ndarray
    used: np.ndarray
    z_statistic: float
    p_value: float
    residual_rms: float
    sigma_o2_stderr: float


def photon_transfer(darks: list[np.ndarray] | None, flats: list[list[np.ndarray]], full_scale: float,
                    p_threshold: float = 0.01) -> PTCResult:
    """EMVA 1288 photon transfer for one channel: the parameters of (17).

    darks : frames (H, W) with no light, at least 2, or None (then the read noise is the
        intercept of the photon-transfer line and the offset is taken as 0).  The read
        noise's standard error is that of the darks' temporal variance, or of the intercept.
    flats : per exposure level a list of at least 2 frames (H, W) of a uniform field.
    full_scale : the largest value above black (saturation), for the 70 % linear range.
    Values are linear code values above the black level."""
    if darks is not None and len(darks) >= 2:
        dark_offset = float(np.mean([np.mean(d) for d in darks]))
        dark_var = temporal_variance(darks)
        dsnu2 = max(spatial_variance(np.mean(darks, axis=0)) - dark_var / len(darks), 0.0)
    elif darks:
        raise HdrMergeError("darks: need at least two dark frames (the temporal variance needs a pair)")
    else:
        dark_offset, dark_var, dsnu2 = None, None, 0.0
    levels = [lv for lv in flats if len(lv) >= 2]
    if len(levels) < 3:
        raise HdrMergeError(f"flats: need at least two frames at each of three or more exposures "
                            f"(found {len(levels)} usable exposure levels)")
    offset = dark_offset or 0.0
    mean = np.array([np.mean([np.mean(f) for f in lv]) - offset for lv in levels])
    temporal = np.array([temporal_variance(lv) for lv in levels])
    spatial = np.array([spatial_variance(np.mean(lv, axis=0)) for lv in levels])
    count = np.array([len(lv) for lv in levels])
    used = (mean > 0) & (mean <= LINEAR_RANGE * full_scale)
    if np.count_nonzero(used) < 2:
        raise HdrMergeError("flats: fewer than two exposure levels between black and 70 % of saturation")
    n = levels[0][0].size
    if dark_var is not None:  # EMVA: sigma^2_y - sigma^2_dark = K mu, through the origin, weighted by the
        w = 1.0 / temporal[used] ** 2  # sampling variance of each level's temporal variance (~ 2 sigma^4 / N)
        k = float(np.sum(w * mean[used] * (temporal[used] - dark_var)) / np.sum(w * mean[used] ** 2))
        sigma_o2 = dark_var
        sigma_o2_stderr = dark_var * float(np.sqrt(2.0 / (n * (len(darks) - 1))))
        pred = dark_var + k * mean
    else:  # no darks: read noise from the intercept
        if np.count_nonzero(used) < 3:
            raise HdrMergeError("flats without darks: need three exposure levels in the linear range")
        (sigma_o2, k), sigma_o2_stderr = _weighted_line(mean[used], temporal[used], n * (count[used] - 1))
        sigma_o2 = max(sigma_o2, 0.0)
        pred = sigma_o2 + k * mean
    if not k > 0:
        raise HdrMergeError("flats: the temporal variance does not grow with the signal (are they flat fields "
                            "at different exposures?)")
    # PRNU: excess spatial variance of the averaged frames over mu^2, weighted by the
    # sampling variance of each level's excess (both terms are sample variances of N
    # Gaussian values, independent because (A + B) and (A - B) are)
    excess = spatial - temporal / count - dsnu2
    sel = mean > 0
    var_excess = 2 * spatial**2 * IMMERKAER_SUM_RHO2 / n + 2 * (temporal / count) ** 2 / (n * (count - 1))
    w = 1.0 / var_excess[sel]
    m2 = mean[sel] ** 2
    slope = float(np.sum(w * m2 * excess[sel]) / np.sum(w * m2 * m2))
    t = slope / float(np.sqrt(1.0 / np.sum(w * m2 * m2)))
    p = float(special.ndtr(-t))  # the normal survival function
    quadratic = slope > 0 and p < p_threshold
    alpha = k * k
    rel = (temporal[used] - pred[used]) / pred[used]
    return PTCResult(float(sigma_o2), float(alpha), float(slope * alpha) if quadratic else 0.0,
                     "quadratic" if quadratic else "affine", dark_offset, float(dsnu2), mean, temporal, spatial, used,
                     float(t), p, float(np.sqrt(np.mean(rel**2))), float(sigma_o2_stderr))


def _weighted_line(x: np.ndarray, y: np.ndarray, dof: np.ndarray) -> tuple[tuple[float, float], float]:
    """``y = a + b x`` by least squares weighted by the sampling variance of each ``y``, a
    variance of ``dof`` degrees of freedom (``2 y^2 / dof``): ``((a, b), stderr of a)``,
    the covariance scaled up by the residuals' reduced chi-square where it exceeds 1."""
    design = np.c_[np.ones_like(x), x]
    w = dof / (2.0 * y * y)
    cov = np.linalg.inv(design.T @ (w[:, None] * design))
    coef = cov @ design.T @ (w * y)
    chi2 = float(np.sum(w * (y - design @ coef) ** 2)) / max(len(y) - 2, 1)
    return (float(coef[0]), float(coef[1])), float(np.sqrt(cov[0, 0] * max(chi2, 1.0)))
