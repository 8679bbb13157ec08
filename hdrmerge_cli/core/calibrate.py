"""Noise-parameter estimation from ordinary photographs (the paper's section "HDR
reconstruction of RAW sensor data"): a robust fit of the variance model (17),

    Var[y] = sigma_o^2 + alpha x + beta x^2,   E[y] = mu = sqrt(alpha) x,

written in the measured mean ``mu`` (code values above black) as ``Var[y] = c0 + c1 mu +
c2 mu^2`` with ``c0 = sigma_o^2``, ``c1 = sqrt(alpha)``, ``c2 = beta / alpha``.  Two kinds
of measurement are rows of the same linear fit:

- *local statistics* of one frame (:func:`window_statistics`, the paper's method): flat
  7 x 7 windows, rows ``[1, mu, mu^2]``;
- *exposure pairs* of a static bracket (:func:`pixel_pair_statistics`): ``d = y_long - r
  y_short`` cancels the scene and the gain FPN, ``Var[d] = c0 (1 + r^2) + c1 mu (1 + r)``,
  rows ``[1 + r^2, mu (1 + r), 0]``, every unclipped pixel counting.

Exposure pairs whose differences follow the scene's gradient saw frames that moved
(:func:`pair_gradient_test`); the local statistics then give the fit.  Photographs do not
measure the quadratic term: in local statistics gain FPN and static scene texture both add
variance in proportion to ``mu^2``, and exposure pairs cancel both, so the fit is the affine
one (``beta = 0``, not measured); only flat fields measure beta (:mod:`photon_transfer`).
:func:`achievable_errors` is the Cramer-Rao bound of what a bracket can tell;
:func:`fit_channel` gives a fit with its precision, and :func:`fit_bracket` is merge's
measurement of a bracket on the sites it drew (the frames' usability, each channel's fit).
Method: docs/method.md, "Calibrating the noise".
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np
from scipy import ndimage, special

from hdrmerge_cli.core.errors import HdrMergeError

#: Immerkaer (1996) noise mask: the product of two second differences, blind to any
#: signal that is linear in x or in y (ramps, smooth shading); white noise of variance
#: s^2 gives an output of variance 36 s^2.
IMMERKAER = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])

#: variance of :func:`scipy.ndimage.laplace` (4-neighbour) on white noise of variance 1
LAPLACE_GAIN = 20.0

#: a window is textured when its largest |Laplacian| exceeds this many standard deviations
#: of the Laplacian of the predicted noise (white noise exceeds 5.5 sd in 49 samples with
#: probability 2e-6, so flat windows are kept whatever their noise draw)
TEXTURE_SIGMAS = 5.5

#: frames with more than this fraction of pixels clipped at black (camera-processed
#: images, which cut the noise at 0; RAW keeps values below black) use the windowed pair
#: statistics, which drop every window touching a clipped pixel, instead of the per-pixel
#: ones, whose dark pixels would have their noise cut
BLACK_CLIPPED = 1e-3

#: least effective number of pixels (:func:`exposure_ratio`) that measure an exposure ratio:
#: its error then adds at most 1 / RATIO_PIXELS to the variances of the pairs it scales
RATIO_PIXELS = 1000
#: false-alarm rate of the test that tells frames that moved from a static bracket by the
#: scene's gradient in their exposure pairs' differences (:func:`pair_gradient_test`):
#: well below the usual, since on simulated brackets of real scenes a few channels show
#: up to 1.8 times the chi-square's degrees of freedom without motion (a shift of one
#: pixel gives p < 1e-80 on the test's own scenes)
PAIR_MOTION_P = 1e-6
#: exposure-pair pixels whose squared difference exceeds this many predicted standard
#: deviations (of a first fit) are outliers (hot pixels, motion)
OUTLIER_SIGMAS = 8.0
#: exposure pairs predicting more than this times the variance of the frames' own flat
#: windows did not see the same scene (:func:`_pairs_moved`): on a static bracket the two
#: agree within a few percent, while motion puts scene texture into the pairs' differences
#: and inflates their prediction by orders of magnitude
PAIR_EXCESS = 2.0


@dataclass
class WindowStats:
    """Per-window statistics of one channel plane, valid windows only, each (N,):
    ``mean`` (code values above black), ``var`` (noise variance estimate), ``texture``
    (largest |Laplacian| in the window; 0 for exposure pairs) and ``dof``, the effective
    degrees of freedom of one window's variance (scaled chi-square)."""

    mean: np.ndarray
    var: np.ndarray
    texture: np.ndarray
    dof: float

    @staticmethod
    def concat(parts: list["WindowStats"]) -> "WindowStats":
        return WindowStats(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("mean", "var", "texture")),
                           parts[0].dof)


def _valid(planes, lo: float, hi: float, window: int) -> np.ndarray:
    """Windows (centres) whose neighbourhood touches no value <= lo or >= hi in any of
    ``planes`` and does not reach the border."""
    clipped = np.zeros(planes[0].shape, np.float32)
    for x in planes:
        clipped += (x <= lo) | (x >= hi)
    ok = ndimage.uniform_filter(clipped, window + 2, mode="constant") < 0.5 / (window + 2) ** 2
    r = window // 2 + 2
    ok[:r], ok[-r:], ok[:, :r], ok[:, -r:] = False, False, False, False
    return ok


def immerkaer_dof(window: int) -> float:
    """Effective degrees of freedom of the window mean of the squared Immerkaer residual of
    Gaussian white noise: ``N^2 / sum_ij rho_ij^2`` with ``rho`` the residual's
    autocorrelation (exact for Gaussian noise: Cov(r_i^2, r_j^2) = 2 rho_ij^2 s^4)."""
    rho = ndimage.correlate(np.pad(IMMERKAER, 2), IMMERKAER, mode="constant") / 36.0
    c = rho.shape[0] // 2
    total = 0.0
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            pairs = max(window - abs(dy), 0) * max(window - abs(dx), 0)
            total += pairs * rho[c + dy, c + dx] ** 2
    return window**4 / total


def window_statistics(plane: np.ndarray, lo: float, hi: float, window: int = 7) -> WindowStats:
    """Local statistics of one frame (the paper's method).

    plane : (H, W) linear values (code values above black).  Per ``window`` x ``window``
    window: the mean; the noise variance as the window mean of the squared Immerkaer
    residual / 36 (smooth shading does not count as noise); the texture as the largest
    |Laplacian|.  Windows touching a value ``<= lo`` or ``>= hi`` (clipping) or the border
    are dropped."""
    x = np.asarray(plane, dtype=np.float64)
    mean = ndimage.uniform_filter(x, window, mode="reflect")
    resid = ndimage.convolve(x, IMMERKAER, mode="reflect")
    var = ndimage.uniform_filter(resid * resid, window, mode="reflect") / 36.0
    texture = ndimage.maximum_filter(np.abs(ndimage.laplace(x)), window)
    ok = _valid([x], lo, hi, window)
    return WindowStats(mean[ok], var[ok], texture[ok], immerkaer_dof(window))


#: mean of a pixel's 8 neighbours
_NEIGHBOURS = np.array([[1.0, 1.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0]]) / 8.0


def exposure_ratio(short: np.ndarray, long: np.ndarray, lo: float, hi: float,
                   black_clipped: bool | None = None, precise: bool = True) -> float:
    """Exposure ratio ``r = E[y_long] / E[y_short]`` of two frames of one static scene,
    measured (not taken from EXIF, whose times are nominal): the ratio of sums over pixels
    well exposed in both frames, the short frame above 2 % and the long one below 70 % of
    the range.  Frames too far apart to share enough such pixels (over about 35 times)
    use every pixel whose long frame lies below 70 % of the range, unless the short frame
    is clipped at black (``black_clipped``; by default when more than
    :data:`BLACK_CLIPPED` of its pixels lie at or below ``lo``, as in a camera-processed
    image), which would cut its noise: a RAW frame keeps its values below black, so by
    (17) the sums over its dark pixels are unbiased too.

    The choice is made on the mean of each pixel's 8 neighbours, whose noise is
    independent of the pixel's own: choosing on the pixel's own noisy values biases both
    sums (by 0.5 % at ratio 4 on a textured scene, which leaks texture into the pair
    variances).

    Precision: with ``d = y_long - r y_short``, ``Var[r] = sum Var[d] / (sum y_short)^2``,
    and the ratio's error adds ``Var[r] y_short^2`` to each pair's ``E[d^2]``: over the
    pixels used, a share ``1 / n_eff`` of their own ``sum Var[d]``, with
    ``n_eff = (sum y_short)^2 / sum y_short^2`` (Kish's effective number of pixels; the
    count itself when all are equal).  A choice of pixels is used when its ``n_eff``
    reaches :data:`RATIO_PIXELS`; raises :class:`HdrMergeError` when neither does (the
    ratio's error would add more than 0.1 % to the pairs' variances, or the short frame
    holds no signal there).  ``precise=False`` returns the last choice's ratio whatever its
    ``n_eff`` (a start for :func:`weighted_ratio`); it raises only where the short frame
    holds no signal."""
    s = np.asarray(short, np.float64)
    g = np.asarray(long, np.float64)
    base = max(lo, 0.0)
    ns = ndimage.correlate(s, _NEIGHBOURS, mode="reflect")
    ng = ndimage.correlate(g, _NEIGHBOURS, mode="reflect")
    unclipped = (ng < base + 0.7 * (hi - base)) & (s > lo) & (g < hi)
    unclipped[0], unclipped[-1], unclipped[:, 0], unclipped[:, -1] = False, False, False, False
    choices = [unclipped & (ns > base + 0.02 * (hi - base))]
    if not (np.mean(s <= lo) >= BLACK_CLIPPED if black_clipped is None else black_clipped):
        choices.append(unclipped)
    for i, use in enumerate(choices):
        total = float(np.sum(s[use]))
        if total > 0 and (total * total >= RATIO_PIXELS * float(np.sum(s[use] ** 2))
                          or not precise and i == len(choices) - 1):
            return float(np.sum(g[use]) / total)
    raise HdrMergeError("the frames share too few well-exposed pixels")


def pair_statistics(short: np.ndarray, long: np.ndarray, ratio: float, lo: float, hi: float,
                    window: int = 7) -> WindowStats:
    """Local statistics of the exposure-normalised difference ``d = long - ratio * short``
    of two frames (H, W) of one static scene: per window the mean of ``long`` and the
    sample variance of ``d`` (49 independent pixels, 48 degrees of freedom).  Scene texture
    and gain FPN cancel in ``d``; by (17) for each frame,
    ``Var[d] = sigma_o^2 (1 + r^2) + sqrt(alpha) mu (1 + r)``."""
    s = np.asarray(short, dtype=np.float64)
    g = np.asarray(long, dtype=np.float64)
    d = g - ratio * s
    n = window * window
    mean = ndimage.uniform_filter(g, window, mode="reflect")
    dm = ndimage.uniform_filter(d, window, mode="reflect")
    var = (ndimage.uniform_filter(d * d, window, mode="reflect") - dm * dm) * (n / (n - 1.0))
    ok = _valid([s, g], lo, hi, window)
    return WindowStats(mean[ok], var[ok], np.zeros(np.count_nonzero(ok)), float(n - 1))


@dataclass
class PixelPairs:
    """Per-pixel exposure-pair measurements of one pair (ratio ``ratio``), each (N,):
    ``long`` (the pixel's value in the longer frame, an unbiased estimate of its mean),
    ``d`` (the difference ``long - ratio * short``, zero-mean noise when ``ratio`` is exact;
    a ratio off by ``e`` leaves a mean ``e * short``, which :func:`binned_pairs` takes out
    bin by bin) and ``key``, an estimate of the pixel's mean whose noise is independent
    of both frames' (another frame of the bracket, or the neighbours), used to bin
    (binning by the pair's own noisy values would shift each bin's mean by about the noise
    variance times the log-slope of the scene's histogram, an error the fit multiplies
    into sigma_o^2 when photon noise dominates);
    ``key_scale`` the factor ``s`` by which the key's variance is ``s^2 c0 + s c1 key``
    (a frame scaled by ``s``; the 8-neighbour mean has ``s^2 = s = 1/8`` nearly);
    ``ratio_var`` the variance of a ratio fitted to these pixels (:func:`weighted_ratio`),
    which shrinks each ``E[d^2]`` by ``ratio_var * short^2`` (added back by
    :func:`binned_pairs`)."""

    long: np.ndarray
    d: np.ndarray
    key: np.ndarray
    ratio: float
    key_scale: np.ndarray | None = None
    ratio_var: float = 0.0

    @property
    def dsq(self) -> np.ndarray:
        return self.d * self.d

    def subset(self, keep: np.ndarray) -> "PixelPairs":
        return PixelPairs(self.long[keep], self.d[keep], self.key[keep], self.ratio,
                          None if self.key_scale is None else self.key_scale[keep], self.ratio_var)

    def at_ratio(self, ratio: float, ratio_var: float = 0.0) -> "PixelPairs":
        """The same pixels with ``d`` taken at another exposure ratio (``short`` is
        ``(long - d) / self.ratio``) of variance ``ratio_var``."""
        d = self.long - ratio * (self.long - self.d) / self.ratio
        return PixelPairs(self.long, d, self.key, float(ratio), self.key_scale, float(ratio_var))

    def usable(self, coef, lo: float, hi: float) -> np.ndarray:
        """Pixels :meth:`unclipped` and within :data:`OUTLIER_SIGMAS` predicted standard
        deviations of 0 under the model ``coef`` (hot pixels, motion; Gaussian noise loses
        1e-13 of its variance there)."""
        mu = np.maximum(np.maximum(self.key, self.long), 0.0)
        pred = coef[0] * (1 + self.ratio**2) + coef[1] * (1 + self.ratio) * mu
        return self.unclipped(coef, lo, hi) & (self.dsq <= OUTLIER_SIGMAS**2 * pred)

    def unclipped(self, coef, lo: float, hi: float, sigmas: float = 4.0) -> np.ndarray:
        """Pixels whose mean in both frames (from the key, give or take ``sigmas`` of its
        noise under the model ``coef``) lies ``sigmas`` noise standard deviations inside
        ``(lo, hi)``: their noise is not cut by the clipping (in the short frame, scaled up
        by the ratio, a cut at black weighs heavily)."""
        c0, c1 = float(coef[0]), float(coef[1])
        k = np.maximum(self.key, 0.0)
        sc = np.ones_like(k) if self.key_scale is None else self.key_scale
        key_sd = np.sqrt(sc * sc * c0 + sc * c1 * k)
        ok = np.ones(k.shape, bool)
        for scale in (1.0, 1.0 / self.ratio):  # the long frame, the short frame
            reach = sigmas * (scale * key_sd + np.sqrt(c0 + c1 * scale * k))
            ok &= (scale * self.key + reach < hi) & (scale * self.key - reach > lo)
        return ok


def _chain_gains(ratios: list, k: int) -> np.ndarray:
    """Exposure of each frame relative to frame ``k`` from the consecutive ``ratios``
    (None: not measured), NaN for frames not linked to ``k`` by measured ratios."""
    gains = np.full(len(ratios) + 1, np.nan)
    gains[k] = 1.0
    for j in range(k, len(ratios)):
        if ratios[j] is None:
            break
        gains[j + 1] = gains[j] * ratios[j]
    for j in range(k - 1, -1, -1):
        if ratios[j] is None:
            break
        gains[j] = gains[j + 1] / ratios[j]
    return gains


def selection_keys(planes: list[np.ndarray], gains: np.ndarray, k: int, lo: float,
                   hi: float) -> tuple[np.ndarray, np.ndarray]:
    """For the pair of frames ``k`` and ``k + 1`` of ``planes`` (sorted by exposure,
    ``gains[j]`` the exposure of frame ``j`` relative to frame 0): per pixel, an estimate
    of the mean of frame ``k + 1`` whose noise is independent of both frames': the longest
    frame unclipped there of those longer than ``k + 1`` (scaled down by ``s``, its noise
    shrinks), else the mean of the pixel's 8 neighbours in frame ``k + 1``.  A shorter
    frame scaled up by ``s > 1`` is never the less noisy (variance ``s^2 c0 + s c1 mu``
    against about ``(c0 + c1 mu) / 8``): on a dark bracket a shortest frame scaled up 16
    times is a key so noisy that the clipping test (:meth:`PixelPairs.unclipped`) keeps
    almost none of the next pair's pixels.

    Binning by a noisy estimate of the mean and using the same estimate as the bin's
    abscissa biases the abscissa (regression to the mean of the scene's histogram, by
    about the noise variance times the histogram's log-slope), which a variance fit turns
    into an error in sigma_o^2 many times its size when the photon noise dominates.
    Binning by an independent key and averaging the pixel's own value does not.  Returns
    the keys and their scale factors (:class:`PixelPairs`)."""
    key = ndimage.correlate(np.asarray(planes[k + 1], np.float64), _NEIGHBOURS, mode="reflect")
    scale = np.full(key.shape, 1.0 / 8.0)
    found = np.zeros(key.shape, bool)
    for j in range(len(planes) - 1, k + 1, -1):  # the longest unclipped first: the least noisy
        if not np.isfinite(gains[j]):
            continue
        y = np.asarray(planes[j], np.float64)
        use = ~found & (y > lo) & (y < hi)
        key[use] = y[use] * (gains[k + 1] / gains[j])
        scale[use] = gains[k + 1] / gains[j]
        found |= use
    return key, scale


def pixel_pair_statistics(short: np.ndarray, long: np.ndarray, ratio: float, lo: float, hi: float,
                          key: np.ndarray, key_scale: np.ndarray | None = None) -> PixelPairs:
    """:class:`PixelPairs` of two frames (H, W) of one static scene over the pixels
    unclipped in both (``lo < y < hi``) whose ``key`` lies below 90 % of the range (a
    pixel whose mean is near the white level has its noise cut by the clipping; once a
    noise model is known, :meth:`PixelPairs.unclipped` draws that line exactly).  Scene
    texture and gain FPN cancel in ``d = long - ratio * short``, and by (17) for each
    frame ``E[d^2] = sigma_o^2 (1 + r^2) + sqrt(alpha) mu (1 + r)``: every unclipped pixel
    counts, flat or not, next to a clipped one or not."""
    s = np.asarray(short, np.float64)
    g = np.asarray(long, np.float64)
    top = max(lo, 0.0) + 0.9 * (hi - max(lo, 0.0))
    ok = (s > lo) & (g < hi) & (g > lo) & (s < hi) & (key < top)
    return PixelPairs(g[ok], g[ok] - ratio * s[ok], np.asarray(key, np.float64)[ok], float(ratio),
                      None if key_scale is None else np.asarray(key_scale, np.float64)[ok])


def weighted_ratio(pp: PixelPairs, coef, lo: float, hi: float) -> tuple[float, float]:
    """The pair's exposure ratio by generalised least squares under the noise model
    ``coef``: ``r = sum w y_long / sum w y_short`` over the pixels :meth:`PixelPairs.usable`
    keeps, each weighted by what it tells of the ratio, ``w = (mu / r) / Var[d]`` (``mu``
    from the key, whose noise is independent of both frames', so the sums stay unbiased;
    ``Var[d]`` by (17)), and its variance ``sum w^2 Var[d] / (sum w y_short)^2``.

    The first measurement (:func:`exposure_ratio`) weighs every pixel alike; on a dark
    pair, where most pixels hold read noise and no signal, its error (1-2 % at ratio 4)
    leaves ``e * y_short`` in each difference, a term that grows with the brightness and
    reads as gain.  Weighted, the bright pixels that carry that term also fix the ratio."""
    c0, c1, r = float(coef[0]), float(coef[1]), pp.ratio
    keep = pp.usable(coef, lo, hi)
    mu = np.maximum(pp.key[keep], 0.0)
    var = np.maximum(c0 * (1 + r * r) + c1 * (1 + r) * mu, 1e-12)
    w = (mu / r) / var
    long = pp.long[keep]
    short = (long - pp.d[keep]) / r
    total = float(np.sum(w * short))
    if not total > 0:
        return r, float("inf")
    return float(np.sum(w * long) / total), float(np.sum(w * w * var)) / total**2


def pair_gradient_test(short: np.ndarray, long: np.ndarray, ratio: float, lo: float, hi: float, coef,
                       tile: int = 64, max_pixels: int = 1 << 20) -> tuple[float, int]:
    """Whether the difference of two frames follows the scene's gradient: the test of
    exposure pairs for frames that moved, as ``(chi-square statistic, degrees of
    freedom)``.

    For a static scene, by (17) ``d = y_long - r y_short`` is zero-mean noise at every
    pixel (the exposure ratio's error and any offset aside: a term ``a + b mu``), so it is
    uncorrelated with anything whose noise is independent of the pixel's own, such as the
    signed central differences ``gx = y[i, j+1] - y[i, j-1]``, ``gy = y[i+1, j] -
    y[i-1, j]`` of the longer frame.  Frames shifted by ``delta`` leave ``-r delta . grad
    x`` in ``d``.  Per ``tile`` x ``tile`` block, ``d`` is regressed on ``[1, m, gx, gy]``
    (``m`` the four neighbours' mean, for ``a + b mu``) by least squares weighted by the
    inverse of the variance (17) under ``coef`` predicts for ``d`` at ``m``, and the
    gradient coefficients are tested with their heteroscedasticity-consistent covariance
    (no noise model is trusted; HC3 of MacKinnon and White 1985, each residual divided by
    one minus its leverage, since the few pixels of a steep edge carry much of a block's
    gradient and HC0 understates their variance): per block a chi-square of 2 degrees of
    freedom for a static scene, their sum over blocks one of ``2 n`` (a rotation or a
    local motion shifts each block its own way).  Pixels clipped in either frame or whose
    neighbours' mean lies above 90 % of the range in the longer frame are left out (a
    clipped neighbour is not: its value is as independent of the pixel's noise as any),
    and blocks with fewer than 64
    pixels; of a larger plane, an even grid of blocks holding about ``max_pixels``."""
    s = np.asarray(short, np.float64)
    g = np.asarray(long, np.float64)
    ny, nx = (s.shape[0] - 2) // tile, (s.shape[1] - 2) // tile  # blocks inside the border
    if ny < 1 or nx < 1:
        return 0.0, 0
    step = max(1, int(np.ceil(np.sqrt(ny * nx * tile * tile / max_pixels))))

    def blocks(a, dy=0, dx=0):  # (by, tile, bx, tile) view of the chosen blocks, shifted by (dy, dx)
        v = a[1 + dy:1 + dy + ny * tile, 1 + dx:1 + dx + nx * tile].reshape(ny, tile, nx, tile)
        return v[::step, :, ::step, :]

    top = max(lo, 0.0) + 0.9 * (hi - max(lo, 0.0))
    sc, gc = blocks(s), blocks(g)
    left, right, up, down = blocks(g, 0, -1), blocks(g, 0, 1), blocks(g, -1, 0), blocks(g, 1, 0)
    m = 0.25 * (left + right + up + down)
    # chosen on the neighbours' mean: a cut on the pixel's own value would bias d where it bites
    ok = (sc > lo) & (sc < hi) & (gc > lo) & (gc < hi) & (m < top)
    sd = np.sqrt(np.maximum(coef[0] * (1 + ratio**2) + coef[1] * (1 + ratio) * np.maximum(m, 0.0), 1e-12))
    w = ok / sd  # square root of the weight; 0 for the pixels left out
    scale = max(float(np.median(np.abs(m))), 1.0)
    x = [w, w * (m / scale), w * (right - left) / sd, w * (down - up) / sd]
    y = w * (gc - ratio * sc)

    def total(a):
        return a.sum(axis=(1, 3)).ravel()

    count = total(ok)
    xtx = np.empty((count.size, 4, 4))
    xty = np.empty((count.size, 4))
    for i in range(4):
        xty[:, i] = total(x[i] * y)
        for j in range(i, 4):
            xtx[:, i, j] = xtx[:, j, i] = total(x[i] * x[j])
    use = (count >= 64) & (np.linalg.cond(xtx) < 1e12)
    if not np.any(use):
        return 0.0, 0
    beta = np.zeros((count.size, 4))
    beta[use] = np.linalg.solve(xtx[use], xty[use][..., None])[..., 0]
    by, bx = ok.shape[0], ok.shape[2]
    inv = np.zeros((count.size, 4, 4))
    inv[use] = np.linalg.inv(xtx[use])
    coefs, inv_px = beta.reshape(by, 1, bx, 1, 4), inv.reshape(by, 1, bx, 1, 4, 4)
    resid = y - sum(x[i] * coefs[..., i] for i in range(4))
    leverage = sum(x[i] * x[j] * inv_px[..., i, j] for i in range(4) for j in range(4))
    resid = resid / np.maximum(1.0 - leverage, 1e-3)  # HC3: a steep edge's few pixels weigh much
    meat = np.empty((count.size, 4, 4))
    for i in range(4):
        for j in range(i, 4):
            meat[:, i, j] = meat[:, j, i] = total(x[i] * x[j] * resid * resid)
    inv = inv[use]
    cov = inv @ meat[use] @ inv
    b = beta[use][:, 2:]
    chi2 = np.einsum("ni,ni->n", b, np.linalg.solve(cov[:, 2:, 2:], b[..., None])[..., 0])
    return float(np.sum(chi2)), int(2 * np.count_nonzero(use))


def binned_pairs(pp: PixelPairs, bins: int = 64, min_count: int = 20, coef=None) -> VariancePoints:
    """Exposure-pair rows ``[1 + r^2, mu (1 + r), 0]``: pixels binned by ``pp.key``, per
    bin the mean of ``long`` (mu) and the sample variance of ``d`` about the bin's own mean
    (``count`` its degrees of freedom).  Centred per bin, the variance holds none of the
    mean ``e * short`` that an exposure ratio off by ``e`` leaves in ``d``: that mean grows
    with the scene's brightness, so its square, left in, would add ``e^2 mu^2 / r^2`` to
    the bright bins and read as gain (on a dark bracket, whose darkest pair's ratio is
    measured to 1-2 %, it would triple alpha); within a bin of nearly one brightness it is
    nearly constant.  A ratio fitted to these pixels
    (:func:`weighted_ratio`) shrinks each difference's expected square by ``Var[r]
    short^2``; ``pp.ratio_var`` times the bin's ``sum (key / r)^2`` adds it back.

    Without a noise model the bins hold equal counts.  Given one (``coef``), a third hold
    equal counts, a third equal shares of the information about sigma_o^2 (each pixel's
    ``1 / Var[d]^2``: the few dark pixels that fix the read noise under strong photon
    noise keep their own bins) and a third equal shares of that about the gain (``mu^2 /
    Var[d]^2``: the few bright pixels of a dark scene, which carry most of it, are not
    pooled with a thousand dimmer ones); and each bin's degrees of freedom are those of
    its pixels' unequal variances under the model, ``(sum V)^2 / sum V^2`` less one, so
    that a bin whose mean rests on a few noisy pixels is weighed as such.  ``V`` is taken
    at each pixel's own level (``long``), not at its key: in a textured scene the
    neighbours' mean can put a bright pixel among a thousand dark ones (a fine highlight
    on a dark ground), whose few large variances then carry the bin, and a ``V`` read off
    the key would count it as a thousand equal pixels (on the StillLife scene such bins lie
    20 stated standard errors off and pull alpha down by 1-4 %)."""
    n = pp.key.size
    if n < bins * min_count:
        bins = max(n // min_count, 0)
    if bins < 1:
        return variance_points([], [], [], pp.ratio)
    key = np.maximum(pp.key, 0.0)
    pred = None if coef is None else np.maximum(coef[0] * (1 + pp.ratio**2) + coef[1] * (1 + pp.ratio) * key, 1e-12)
    if coef is None:
        edges = np.quantile(pp.key, np.linspace(0, 1, bins + 1))
    else:
        order = np.argsort(pp.key)
        parts = [np.quantile(pp.key, np.linspace(0, 1, bins - 2 * (bins // 3) + 1))]
        for info in (1.0 / pred[order] ** 2, (key[order] / pred[order]) ** 2):
            cw = np.cumsum(info)
            parts.append(pp.key[order][np.searchsorted(cw, cw[-1] * np.linspace(0, 1, bins // 3 + 1)[1:-1])])
        edges = np.concatenate(parts)
    edges = np.unique(edges)
    which = np.clip(np.searchsorted(edges, pp.key, side="right") - 1, 0, edges.size - 2)

    def total(x=None):
        return np.bincount(which, x, minlength=edges.size - 1).astype(np.float64)

    cnt, mu, s1, s2 = total(), total(pp.long), total(pp.d), total(pp.dsq)
    use = cnt >= max(min_count, 2)
    n = cnt[use]
    var = (s2[use] - s1[use] ** 2 / n + pp.ratio_var * total((key / pp.ratio) ** 2)[use]) / (n - 1)
    if pred is None:
        dof = n - 1
    else:  # each pixel's variance at its own level: where the key misplaces a pixel, it still counts as what it is
        own = np.maximum(coef[0] * (1 + pp.ratio**2) + coef[1] * (1 + pp.ratio) * np.maximum(pp.long, 0.0), 1e-12)
        dof = (total(own)[use] ** 2 / total(own * own)[use]) * (n - 1) / n
    return variance_points(mu[use] / n, var, dof, pp.ratio)


def texture_limit(mean: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """Largest |Laplacian| a flat window of mean ``mean`` shows under the noise model
    ``coef = (c0, c1, c2)``: ``TEXTURE_SIGMAS`` standard deviations of the Laplacian of
    white noise of the predicted variance."""
    pred = np.maximum(coef[0] + coef[1] * mean + coef[2] * mean * mean, 1e-12)
    return TEXTURE_SIGMAS * np.sqrt(LAPLACE_GAIN * pred)


@dataclass
class VariancePoints:
    """Binned measurements: ``mean``, ``var``, ``count`` (N,) and the model rows
    ``design`` (N, 3) such that ``E[var] = design @ (c0, c1, c2)``; ``kind`` (N,) names
    the measurement ("local" or "pair")."""

    mean: np.ndarray
    var: np.ndarray
    count: np.ndarray
    design: np.ndarray
    kind: np.ndarray

    @staticmethod
    def concat(parts: list["VariancePoints"]) -> "VariancePoints":
        return VariancePoints(*(np.concatenate([getattr(p, k) for p in parts])
                                for k in ("mean", "var", "count", "design", "kind")))


def equal_count_bins(values: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bins of (about) equal counts over ``values`` (N,): ``(edges, order, starts)`` with
    ``values[order][starts[b]:starts[b + 1]]`` the members of bin ``b`` (edges at the
    quantiles; repeated quantiles merge bins).  ``bins`` < 65536."""
    edges = np.unique(np.quantile(values, np.linspace(0, 1, bins + 1)))
    which = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, edges.size - 2).astype(np.uint16)
    order = np.argsort(which, kind="stable")  # a radix sort for 16-bit keys
    starts = np.concatenate([[0], np.cumsum(np.bincount(which, minlength=edges.size - 1))])
    return edges, order, starts


def binned_variance(ws: WindowStats, ratio: float | None = None, bins: int = 64, min_count: int = 20,
                    max_texture: np.ndarray | None = None, reject: float = 3.0, robust: bool = True) -> VariancePoints:
    """Variance against mean: windows binned by mean (equal counts).  Textured windows are
    dropped: those above ``max_texture`` (per window, from :func:`texture_limit`) or, when
    no noise model is known yet, above ``reject`` times the bin's median texture.  Each
    bin's variance is, with ``robust``, the *median* window variance divided by the median
    of a scaled chi-square of ``ws.dof`` degrees of freedom (unbiased for pure noise, and
    robust to texture that the Laplacian test lets through in a minority of windows), else
    the mean (unbiased also when the variance changes within a window, as in the
    exposure-pair differences, which hold no texture).

    ``ratio`` None gives local-statistics rows ``[1, mu, mu^2]``; a number gives the
    exposure-pair rows ``[1 + r^2, mu (1 + r), 0]``."""
    keep = np.ones(ws.mean.size, bool) if max_texture is None else ws.texture <= max_texture
    mean, var, tex = ws.mean[keep], ws.var[keep], ws.texture[keep]
    if mean.size < bins * min_count:
        bins = max(mean.size // min_count, 0)
    if bins < 1:
        return variance_points([], [], [], ratio)
    edges, order, starts = equal_count_bins(mean, bins)
    mean, var, tex = mean[order], var[order], tex[order]  # each bin is now a slice
    median_factor = special.chdtri(ws.dof, 0.5) / ws.dof  # the chi-square median (scipy.special: no scipy.stats import)
    mus, vs, ns = [], [], []
    for b in range(edges.size - 1):
        m, v = mean[starts[b]:starts[b + 1]], var[starts[b]:starts[b + 1]]
        if max_texture is None and m.size:
            t = tex[starts[b]:starts[b + 1]]
            flat = t <= reject * np.median(t)
            m, v = m[flat], v[flat]
        if m.size < min_count:
            continue
        mus.append(np.mean(m))
        vs.append(np.median(v) / median_factor if robust else np.mean(v))
        ns.append(m.size)
    return variance_points(mus, vs, ns, ratio)


def variance_points(mean, var, count, ratio: float | None = None) -> VariancePoints:
    """Binned (mean, var, count) as :class:`VariancePoints`: local-statistics rows when
    ``ratio`` is None, exposure-pair rows for that exposure ratio otherwise."""
    mu = np.asarray(mean, np.float64)
    if ratio is None:
        design = np.stack([np.ones_like(mu), mu, mu * mu], axis=1)
    else:
        design = np.stack([np.full_like(mu, 1 + ratio**2), mu * (1 + ratio), np.zeros_like(mu)], axis=1)
    kind = np.full(mu.size, "local" if ratio is None else "pair")
    return VariancePoints(mu, np.asarray(var, np.float64), np.asarray(count, np.float64), design.reshape(-1, 3), kind)


@dataclass
class NoiseFit:
    """Parameters of (17) measured on photographs with the fit's statistics: the model
    ("affine": photographs do not measure beta, module docstring), the number of binned
    points, their relative RMS residual, and the points themselves (for plots)."""

    sigma_o2: float
    alpha: float
    beta: float
    model: str
    points: int
    residual_rms: float
    data: VariancePoints | None = None

    @property
    def coef(self) -> np.ndarray:
        return np.array([self.sigma_o2, np.sqrt(self.alpha), self.beta / self.alpha])

    def as_dict(self) -> dict:
        out = {k: v for k, v in asdict(self).items() if k != "data"}
        return {k: float(v) if isinstance(v, (float, np.floating)) else v for k, v in out.items()}


def _soft_l1(d: np.ndarray, y: np.ndarray, w: np.ndarray, start: np.ndarray, f_scale: float,
             tol: float = 1e-10, max_iter: int = 200) -> np.ndarray:
    """``argmin_{c >= 0} sum rho((w (d c - y))^2)`` with the soft-L1 loss
    ``rho(z) = 2 f^2 (sqrt(1 + z / f^2) - 1)`` (scipy.optimize.least_squares' ``soft_l1``;
    convex in ``c``) by iteratively re-weighted non-negative least squares
    (``scipy.optimize.nnls``, weights ``1 / sqrt(1 + (r / f)^2)``) from ``start``: the
    same minimum as ``least_squares`` for the two or three coefficients of (17), at a
    fraction of its per-call cost."""
    from scipy.optimize import nnls

    c = start
    for _ in range(max_iter):
        r = w * (d @ c - y)
        u = w / np.sqrt(np.sqrt(1.0 + (r / f_scale) ** 2))  # w sqrt(q), q the soft-L1 weight
        nxt = nnls(d * u[:, None], y * u)[0]
        if np.all(np.abs(nxt - c) <= tol * np.maximum(np.abs(nxt), 1e-300)):
            return nxt
        c = nxt
    return c


def _robust_wls(design, var, counts):
    """Non-negative weighted least squares of ``var ~ design @ c`` over ``c0, c1`` (``c2``
    held at 0), with a soft-L1 loss on the standardised residuals ``sqrt(count / 2) (var -
    pred) / pred`` (a bin's variance estimate has relative variance ~2 / count;
    :func:`_soft_l1`); re-weighted three times.  Returns (c, residuals)."""
    from scipy.optimize import nnls  # here, not at the top: importing it costs every merge's start-up

    full = np.zeros(3)
    d = design[:, [0, 1]]
    pred = np.maximum(var, 1e-12)
    for _ in range(3):
        w = np.sqrt(counts / 2.0) / np.maximum(pred, 1e-12)
        start = nnls(d * w[:, None], var * w)[0]
        full[:2] = _soft_l1(d, var, w, start, 3.0)
        pred = np.maximum(design @ full, 1e-12)
    return full, np.sqrt(counts / 2.0) * (var - pred) / pred


def fit_noise_model(points: VariancePoints) -> NoiseFit:
    """Robust fit of the affine (17), ``Var = c0 + c1 mu``, to binned points
    (:class:`VariancePoints`; their quadratic column is not used: module docstring)."""
    if points.mean.size < 4:
        raise HdrMergeError(f"too few intensity levels ({points.mean.size}) to fit the noise model")
    var, counts, design = points.var, points.count, points.design
    coef, r = _robust_wls(design, var, counts)
    if coef[1] <= 0:
        raise HdrMergeError("the noise does not grow with the signal: cannot estimate the gain")
    rel = r / np.sqrt(counts / 2.0)
    return NoiseFit(float(coef[0]), float(coef[1] ** 2), 0.0, "affine", int(points.mean.size),
                    float(np.sqrt(np.mean(rel**2))), points)


def pair_information(planes: list[np.ndarray], lo: float, hi: float, ratios: list, coef) -> np.ndarray:
    """Fisher information (2, 2) about ``(c0, c1) = (sigma_o^2, sqrt(alpha))`` in the
    exposure contrasts of a bracket: the most any estimator can learn about them with every
    pixel's irradiance a free parameter.

    planes : frames (H, W) sorted by exposure; ratios : the exposure ratios of consecutive
    frames (None where not measured: the bracket splits there); coef : the true (or
    fitted) ``(c0, c1, ...)``.

    Notes: per pixel, its unclipped frames are independent Gaussians ``y_k ~ N(g_k mu,
    c0 + c1 g_k mu)``; restricting to contrasts removes ``mu`` (REML, Harville 1977):
    ``I_ij = 1/2 tr(P D_i P D_j)``, ``P = V^-1 - V^-1 g (g' V^-1 g)^-1 g' V^-1``, ``D_0 = I``,
    ``D_1 = diag(g mu)``, ``mu`` from the pixel's longest unclipped frame.  Gain FPN lies
    in ``g`` and does not enter.  Gaussian: a pixel of a few photons has heavier tails."""
    c0, c1 = float(coef[0]), float(coef[1])
    info = np.zeros((2, 2))
    segments, start = [], 0
    for k, r in enumerate(list(ratios) + [None]):
        if r is None:
            segments.append((start, k + 1))
            start = k + 1
    for a, b in segments:
        if b - a < 2:
            continue
        g = np.concatenate([[1.0], np.cumprod(np.asarray(ratios[a:b - 1], np.float64))])
        y = np.stack([np.asarray(p, np.float64).ravel() for p in planes[a:b]])
        ok = (y > lo) & (y < hi)
        last = (b - a - 1) - np.argmax(ok[::-1], axis=0)  # longest unclipped frame
        x = np.maximum(y[last, np.arange(y.shape[1])] / g[last], 0.0)
        m = g[:, None] * x[None]
        w = np.where(ok, 1.0 / np.maximum(c0 + c1 * m, 1e-12), 0.0)  # V^-1, 0 where clipped
        wg = w * g[:, None]
        s = np.sum(wg * g[:, None], axis=0)
        s = np.where(s > 0, s, np.inf)
        d = (ok.astype(np.float64), np.where(ok, m, 0.0))
        for k in range(b - a):
            for j in range(b - a):
                pkj = (w[k] if k == j else 0.0) - wg[k] * wg[j] / s
                pkj2 = pkj * pkj
                for u in range(2):
                    for v in range(2):  # a sum of products, not np.dot: BLAS threads stall beside the merge's own
                        info[u, v] += 0.5 * float(np.sum(d[u][k] * pkj2 * d[v][j]))
    return info


def achievable_errors(planes: list[np.ndarray], lo: float, hi: float, ratios: list, coef) -> tuple[float, float]:
    """Cramer-Rao standard errors ``(sigma_o^2, alpha)`` from :func:`pair_information`
    (``alpha = c1^2``, so its error is ``2 c1`` times that of ``c1``); inf when the
    bracket holds no contrast (one frame, or nothing unclipped in two)."""
    info = pair_information(planes, lo, hi, ratios, coef)
    if np.linalg.det(info) <= 0:
        return float("inf"), float("inf")
    cov = np.linalg.inv(info)
    return float(np.sqrt(cov[0, 0])), float(2 * abs(coef[1]) * np.sqrt(cov[1, 1]))


def fit_standard_errors(fit: NoiseFit, pairs: bool) -> tuple[float, float]:
    """Standard errors ``(sigma_o^2, alpha)`` of a fit from its own points: the weighted
    least-squares covariance ``s^2 (D' W D)^-1`` over the points that gave sigma_o^2 and
    alpha (the exposure pairs when ``pairs``, else the local statistics), ``W`` each
    point's inverse variance ``count / (2 pred^2)`` and ``s^2`` the squared robust scale
    (1.4826 times the median absolute value) of their standardised residuals, at least 1.

    Notes: the scale carries what the nominal counts do not: overlapping windows share
    pixels (a bin's windows are not independent), the median's efficiency and any misfit.
    ``alpha = c1^2``, so its error is ``2 c1`` times that of ``c1``; inf when the points
    do not identify both."""
    data = fit.data
    if data is None:
        return float("inf"), float("inf")
    use = data.kind == ("pair" if pairs else "local")
    cols = [0, 1]
    design, var, count = data.design[use][:, cols], data.var[use], data.count[use]
    if var.size <= len(cols):
        return float("inf"), float("inf")
    pred = np.maximum(design @ fit.coef[cols], 1e-12)
    r = np.sqrt(count / 2.0) * (var - pred) / pred
    scale2 = max(1.0, (1.4826 * float(np.median(np.abs(r)))) ** 2)
    info = design.T @ (design * (count / (2.0 * pred**2))[:, None])
    if np.linalg.det(info) <= 0:
        return float("inf"), float("inf")
    cov = scale2 * np.linalg.inv(info)
    return float(np.sqrt(cov[0, 0])), float(2 * abs(fit.coef[1]) * np.sqrt(cov[1, 1]))


def _local_fit(pooled: WindowStats, bins: int) -> NoiseFit:
    """(17) from the frames' local statistics alone: a first fit with median-relative texture
    rejection, then the noise-relative rejection (:func:`texture_limit`) and the final fit."""
    first = fit_noise_model(binned_variance(pooled, bins=bins)).coef
    points = binned_variance(pooled, bins=bins, max_texture=texture_limit(pooled.mean, first))
    if points.mean.size < 4:
        raise HdrMergeError(f"too few usable flat windows ({pooled.mean.size}) to measure the noise")
    return fit_noise_model(points)


def _pairs_moved(pairs: NoiseFit, alone: NoiseFit, pooled: WindowStats) -> bool:
    """Whether the exposure pairs saw more than noise: their model predicts over
    :data:`PAIR_EXCESS` times the variance of the frames' own flattest windows at the
    windows' median level.  Texture can only raise the windows' variance, so pairs above
    it differ by more than noise: the frames moved (a hand-held bracket, aligned or not, or
    resampled, which also smooths the noise)."""
    level = float(np.median(pooled.mean))
    return pairs.sigma_o2 + pairs.alpha * level > PAIR_EXCESS * (alone.sigma_o2 + alone.alpha * level)


def _measured_ratios(planes: list[np.ndarray], lo: float, hi: float, per_pixel: bool,
                     precise: bool = True) -> list[float | None]:
    """The exposure ratio of each pair of consecutive frames (len(planes) - 1), None where it
    cannot be measured (:func:`exposure_ratio`, ``precise`` as there)."""
    measured = []
    for s, g in zip(planes[:-1], planes[1:]):
        try:
            measured.append(exposure_ratio(s, g, lo, hi, black_clipped=not per_pixel, precise=precise))
        except HdrMergeError:
            measured.append(None)
    return measured


def _window_pair_points(planes: list[np.ndarray], measured: list, lo: float, hi: float, window: int,
                        bins: int) -> tuple[list[VariancePoints], list[float]]:
    """Per-window variance points of the exposure pairs (windows touching no clipped pixel) and their ratios."""
    points, ratios = [], []
    for k, r in enumerate(measured):
        if r is None or r <= 1.05:
            continue
        pts = binned_variance(pair_statistics(planes[k], planes[k + 1], r, lo, hi, window), ratio=r,
                              bins=max(bins // 2, 4), robust=False)
        if pts.mean.size >= 4:
            points.append(pts)
            ratios.append(r)
    return points, ratios


def _refined_pair_points(pp: PixelPairs, coef, lo: float, hi: float, pair_bins: int) -> VariancePoints:
    """Binned points of one pixel pair without the pixels the clipping or outliers affect (by the model ``coef``)."""
    return binned_pairs(pp.subset(pp.usable(coef, lo, hi)), pair_bins, coef=coef)


def _pixel_pair_points(planes: list[np.ndarray], measured: list, ratios: list, lo: float, hi: float,
                       pair_bins: int) -> tuple[list[VariancePoints], list[float], float]:
    """Per-pixel variance points of the exposure pairs, their ratios and the p-value of
    :func:`pair_gradient_test`.  The pairs whose ratio is ``measured`` give a first fit;
    then every pair's ratio in ``ratios`` (``measured``, or where that is None the
    provisional ratio of :func:`exposure_ratio`'s ``precise=False``) is measured again
    under it (:func:`weighted_ratio`), and the pairs are binned again without the pixels
    the fit calls clipped or outliers."""
    pixel_pairs, first_points, used = [], [], []
    for k, r in enumerate(ratios):
        if r is None or r <= 1.05:
            continue
        pp = pixel_pair_statistics(planes[k], planes[k + 1], r, lo, hi,
                                   *selection_keys(planes, _chain_gains(ratios, k), k, lo, hi))
        first = binned_pairs(pp, pair_bins)
        if first.mean.size >= 4:
            used.append(k)
            pixel_pairs.append(pp)
            if measured[k] is not None:
                first_points.append(first)
    if not first_points:
        return [], [], 1.0
    try:
        coef = fit_noise_model(VariancePoints.concat(first_points)).coef
    except HdrMergeError:  # the pairs do not show the gain (read noise swamps it)
        return [], [], 1.0
    pixel_pairs = [pp.at_ratio(*weighted_ratio(pp, coef, lo, hi)) for pp in pixel_pairs]
    keep = [np.isfinite(pp.ratio_var) for pp in pixel_pairs]
    used = [k for k, ok in zip(used, keep) if ok]
    pixel_pairs = [pp for pp, ok in zip(pixel_pairs, keep) if ok]
    points = [_refined_pair_points(pp, coef, lo, hi, pair_bins) for pp in pixel_pairs]
    chi2, dof = 0.0, 0
    for k, pp in zip(used, pixel_pairs):
        c, n = pair_gradient_test(planes[k], planes[k + 1], pp.ratio, lo, hi, coef)
        chi2, dof = chi2 + c, dof + n
    return points, [pp.ratio for pp in pixel_pairs], float(special.chdtrc(dof, chi2)) if dof else 1.0


def _pair_points(planes: list[np.ndarray], lo: float, hi: float, window: int, bins: int,
                 pair_bins: int) -> tuple[list[VariancePoints], list[float], float]:
    """The exposure pairs' variance points, the ratios of the pairs used and the gradient test's p-value (1 if none)."""
    per_pixel = max(np.mean(p <= lo) for p in planes) < BLACK_CLIPPED
    measured = _measured_ratios(planes, lo, hi, per_pixel)
    if per_pixel:
        ratios = [m if m is not None else _measured_ratios([s, g], lo, hi, per_pixel, precise=False)[0]
                  for m, s, g in zip(measured, planes[:-1], planes[1:])]
        return _pixel_pair_points(planes, measured, ratios, lo, hi, pair_bins)
    return (*_window_pair_points(planes, measured, lo, hi, window, bins), 1.0)


def estimate_noise(planes: list[np.ndarray], lo: float, hi: float, window: int = 7, bins: int = 64,
                   pairs: bool = True,
                   pair_bins: int = 128) -> tuple[NoiseFit, list[float]]:
    """Noise parameters of (17) for one channel from frames of one scene at one ISO.

    planes : list of (H, W) float arrays, linear values (code values above black),
        sorted by exposure (shortest first); one frame is allowed.
    lo, hi : values at or beyond which a pixel is clipped.
    pairs : use the exposure pairs of consecutive frames (needs a static scene).
    Returns the :class:`NoiseFit` and the measured exposure ratios of the pairs used
    (none when the pairs were not used).

    Notes: with pairs, sigma_o^2 and alpha come from the pairs (per pixel, or per window
    when the frames are clipped at black, :data:`BLACK_CLIPPED`; refitted without the
    pixels that clipping or outliers affect); the local statistics of every frame (windows
    beyond :data:`TEXTURE_SIGMAS` rejected) join the points for the plot and the residual.
    Beta is not measured (module docstring).  Without pairs, where they do not show the
    gain (their fit finds none), where their differences follow the scene's gradient (per pixel: :func:`pair_gradient_test` at the
    false-alarm rate :data:`PAIR_MOTION_P`) or where they predict more variance than the
    frames' own flat windows (:func:`_pairs_moved`), the frames moved or the pairs cannot
    tell, and the local statistics give everything.
    """
    local = [window_statistics(p, lo, hi, window) for p in planes]
    pair_points, ratios, gradient_p = [], [], 1.0
    if pairs and len(planes) > 1:
        pair_points, ratios, gradient_p = _pair_points(planes, lo, hi, window, bins, pair_bins)
    pooled = WindowStats.concat(local)
    fit = None
    if pair_points:
        pair_data = VariancePoints.concat(pair_points)
        try:
            fit = fit_noise_model(pair_data)
        except HdrMergeError:  # as above
            fit = None
    if fit is None:
        return _local_fit(pooled, bins), []
    try:
        alone = _local_fit(pooled, bins)
    except HdrMergeError:
        alone = None
    if alone is not None and (gradient_p < PAIR_MOTION_P or _pairs_moved(fit, alone, pooled)):
        return alone, []
    local_points = binned_variance(pooled, bins=bins, max_texture=texture_limit(pooled.mean, fit.coef))
    data = VariancePoints.concat([pair_data, local_points])
    rel = (data.var - data.design @ fit.coef) / np.maximum(data.design @ fit.coef, 1e-12)
    fit.data, fit.points, fit.residual_rms = data, int(data.mean.size), float(np.sqrt(np.mean(rel**2)))
    return fit, ratios


# ---------------------------------------------------------------- a bracket's frames and channels
#: a frame with less than this fraction of unclipped pixels is skipped
MIN_UNCLIPPED = 0.01
#: a frame has signal when at least this many of its sites (and this fraction) lie above the noise floor
MIN_SIGNAL_SITES, MIN_SIGNAL_FRACTION = 64, 1e-4
#: and, judged on an even subsample, at least this many of the subsample's sites
MIN_SIGNAL_SAMPLES = 8


def unusable_reason(planes, pixels: int, sites: int | None = None) -> str | None:
    """Why a frame cannot be used (all clipped, or black), or None.  planes: per channel
    ``(plane, lo, hi)``, its linear values (a value ``<= lo`` or ``>= hi`` is clipped), whole
    or an even subsample of planes of ``sites`` sites each (see :func:`has_signal`);
    ``pixels``: the frame's pixel count."""
    inside = np.mean([np.mean((p > lo) & (p < hi)) for p, lo, hi in planes])
    if inside < MIN_UNCLIPPED:
        dark = np.mean([np.mean(p <= lo) for p, lo, hi in planes])
        bright = 1 - inside - dark
        parts = [f"{100 * v:.1f} % of its pixels {what}" for v, what in ((dark, "read black"),
                                                                         (bright, "are clipped at white")) if v > 0]
        return " and ".join(parts)
    if not any(has_signal(p, lo, hi, sites) for p, lo, hi in planes):
        if pixels < MIN_SIGNAL_SITES:
            return f"it holds {pixels} pixels, too few to measure noise on (at least {MIN_SIGNAL_SITES})"
        return "it is black (no signal above its noise floor)"
    return None


def has_signal(plane: np.ndarray, lo: float, hi: float, sites: int | None = None) -> bool:
    """Whether a plane holds signal: enough sites (:data:`MIN_SIGNAL_SITES`, a fraction
    :data:`MIN_SIGNAL_FRACTION`) above its noise floor, 6 robust standard deviations of
    the darker half of the sites (1.4826 times their median absolute deviation) above
    black and at least 0.2 % of the range.  A count, not a percentile: a night frame whose
    99th percentile is near black but whose lamps and windows are bright has signal.

    ``sites``: the plane is an even subsample of a plane of that many sites, whose count
    above the floor is estimated from the subsample's fraction (and at least
    :data:`MIN_SIGNAL_SAMPLES` of the subsample's sites must lie above it)."""
    sub = (plane[::2, ::2] if plane.size > 1 << 22 else plane).ravel()
    med = float(np.median(sub))
    low = sub[sub <= med]
    sigma = 1.4826 * float(np.median(np.abs(low - np.median(low)))) if low.size else 0.0
    floor = max(6 * sigma, 0.002 * (hi - max(lo, 0.0)))
    above = int(np.count_nonzero(sub > floor))
    if sites is None or sites <= sub.size:
        return above >= max(MIN_SIGNAL_SITES, MIN_SIGNAL_FRACTION * sub.size)
    return (above >= MIN_SIGNAL_SAMPLES
            and above * sites / sub.size >= max(MIN_SIGNAL_SITES, MIN_SIGNAL_FRACTION * sites))


def rounded(x: float) -> float | None:
    """``x`` to 4 significant digits, None where it is not finite (a profile's numbers)."""
    return float(f"{x:.4g}") if np.isfinite(x) else None


@dataclass
class ChannelFit:
    """One channel's (17) measured on photographs (:func:`fit_channel`): the fit, the
    exposure ratios of the pairs it used (none: the local statistics alone), its standard
    errors ``(sigma_o^2, alpha)`` (:func:`fit_standard_errors`) and the Cramer-Rao bound of
    the frames' exposure contrasts (:func:`achievable_errors`; inf where they hold none)."""

    fit: NoiseFit
    ratios: list[float]
    stderr: tuple[float, float]
    achievable: tuple[float, float]

    def entry(self, window: int, sites: int | None = None) -> dict:
        """The profile's entry: the fit (:meth:`NoiseFit.as_dict`), what measured each
        parameter, the ``window``, the exposure ratios, ``subsample_sites`` (``sites``: merge
        measured on drawn sites), ``stderr`` and ``achievable_stderr`` (None where inf)."""
        source = "exposure pairs" if self.ratios else "local statistics"
        (se0, se1), (crb0, crb1) = self.stderr, self.achievable
        return self.fit.as_dict() | {
            "method": {"sigma_o2": source, "alpha": source,
                       "beta": "not measured: in photographs scene texture and gain FPN look alike (--flats "
                               "measures beta); 0 is used"},
            "window": window, "exposure_ratios": [round(r, 5) for r in self.ratios],
        } | ({} if sites is None else {"subsample_sites": sites}) | {
            "stderr": {"sigma_o2": rounded(se0), "alpha": rounded(se1)},
            "achievable_stderr": ({"sigma_o2": rounded(crb0), "alpha": rounded(crb1)}
                                  if np.isfinite(crb0) and np.isfinite(crb1) else None)}


def fit_channel(planes: list[np.ndarray], lo: float, hi: float, times: list, window: int = 7, bins: int = 64,
                pairs: bool = True) -> ChannelFit:
    """:func:`estimate_noise` of one channel's ``planes`` (sorted by exposure; ``times``
    their exposure times, whose ratios the Cramer-Rao bound takes) with its precision."""
    fit, ratios = estimate_noise(planes, lo, hi, window, bins, pairs)
    nominal = [b / a if a and b and b > a else None for a, b in zip(times[:-1], times[1:])]
    return ChannelFit(fit, ratios, fit_standard_errors(fit, bool(ratios)),
                      achievable_errors(planes, lo, hi, nominal, fit.coef))


class DrawnChannel(NamedTuple):
    """The codes of one channel of one frame that merge measures a bracket's noise on."""

    name: str
    index: int  #: the channel's index (CFA colour or image channel)
    tiles: np.ndarray  #: the sites drawn for the fit
    drawn: int  #: sites in ``tiles`` (what separates the tiles not counted)
    stride: np.ndarray  #: an even stride of the channel, for the usability test
    sites: int  #: sites of the whole channel


@dataclass
class BracketNoise:
    """A bracket's noise as merge measures it (:func:`fit_bracket`).

    used : the frames measured on (their indices); skipped : ``(frame, why)`` of the others
    channels : the channels' names; fits : per channel measured, its :class:`ChannelFit`
    failed : per channel not measured, why
    """

    used: list[int]
    skipped: list[tuple[int, str]]
    channels: list[str]
    fits: dict[str, ChannelFit]
    failed: dict[str, str]


def fit_bracket(frames: list[list[DrawnChannel]], scales: list[list[tuple[np.ndarray, float, float]]],
                pixels: list[int], times: list, pairs: bool = True, mapper=map) -> BracketNoise:
    """(17) per channel of a bracket from the codes merge drew of each frame (sorted by
    exposure; ``pixels`` and ``times`` each frame's pixel count and exposure time), each
    channel's linear values (code values above black) ``table[codes]`` by its ``(table, lo,
    hi)`` of ``scales`` (a value ``<= lo`` or ``>= hi`` is clipped): each frame's usability
    (:func:`unusable_reason`) judged on its strides, then :func:`fit_channel` of each
    channel on the usable frames' tiles (``pairs``: with the exposure pairs).  ``mapper``
    runs the frames' tests and the channels' fits (a pool's map)."""
    def reason(j):
        planes = [(scales[j][c.index][0][c.stride], *scales[j][c.index][1:]) for c in frames[j]]
        return unusable_reason(planes, pixels[j], min(c.sites for c in frames[j]))

    reasons = list(mapper(reason, range(len(frames))))
    used = [j for j, why in enumerate(reasons) if not why]
    names = [c.name for c in frames[used[0]]] if used else []

    def fit(k):
        chans = [(frames[j][k], scales[j][frames[j][k].index]) for j in used]
        _, lo, hi = chans[0][1]
        try:
            return fit_channel([table[c.tiles] for c, (table, _, _) in chans], lo, hi, [times[j] for j in used],
                               pairs=pairs)
        except HdrMergeError as exc:
            return str(exc)

    fits = dict(zip(names, mapper(fit, range(len(names)))))
    return BracketNoise(used, [(j, why) for j, why in enumerate(reasons) if why], names,
                        {n: f for n, f in fits.items() if not isinstance(f, str)},
                        {n: f for n, f in fits.items() if isinstance(f, str)})


@dataclass
class ReadNoiseSplit:
    """:func:`read_noise_split`'s result: ``pre`` electrons^2, ``post`` code values^2, their
    standard errors (nan where the points cannot tell them) and ``weighted``: whether
    the points' standard errors weighted the fit."""

    pre: float
    post: float
    pre_stderr: float
    post_stderr: float
    weighted: bool


def read_noise_split(alpha, sigma_o2, alpha_stderr=None, sigma_o2_stderr=None) -> ReadNoiseSplit:
    """The read noise before and after the ISO amplifier from fits of (17) at several ISOs
    (Hasinoff, Durand and Freeman, CVPR 2010): with gain ``g`` the pre-amplifier read
    noise (``pre`` electrons^2) is amplified like the photo-electrons and the
    post-amplifier read noise (``post`` code values^2) is not, so

        sigma_o^2(ISO) = pre alpha(ISO) + post,

    a straight line through the points ``(alpha, sigma_o^2)``, fitted by least squares.
    With the points' standard errors (both or neither) each point weighs
    ``1 / (se(sigma_o^2)^2 + pre^2 se(alpha)^2)`` (the effective variance of a line with
    errors in both coordinates; ``pre`` from the previous pass, three passes) and the
    standard errors are those of the weighted fit; without, the fit is unweighted and
    its standard errors come from the residuals (nan with two points).  Quantisation's
    1/12 code value^2 is read noise after the amplifier, so a fit of measured
    ``sigma_o^2`` puts it into ``post``.  Not constrained to be positive."""
    a = np.asarray(alpha, np.float64)
    s = np.asarray(sigma_o2, np.float64)
    if a.size < 2 or a.shape != s.shape:
        raise HdrMergeError("the read-noise split needs sigma_o^2 and alpha at two or more ISOs")
    if np.ptp(a) <= 1e-9 * np.max(np.abs(a)):
        raise HdrMergeError("the read-noise split needs two or more different gains (alpha)")
    design = np.stack([a, np.ones_like(a)], axis=1)
    weighted = alpha_stderr is not None and sigma_o2_stderr is not None
    if weighted:
        se_a, se_s = np.asarray(alpha_stderr, np.float64), np.asarray(sigma_o2_stderr, np.float64)
        if not (np.all(np.isfinite(se_a)) and np.all(np.isfinite(se_s)) and np.all(se_s > 0)):
            raise HdrMergeError("the read-noise split's standard errors must be finite and positive")
    coef = np.linalg.lstsq(design, s, rcond=None)[0]
    if weighted:
        for _ in range(3):
            w = 1.0 / (se_s**2 + (coef[0] * se_a) ** 2)
            info = design.T @ (design * w[:, None])
            coef = np.linalg.solve(info, design.T @ (w * s))
        cov = np.linalg.inv(info)
    elif a.size > 2:
        resid = s - design @ coef
        cov = float(resid @ resid) / (a.size - 2) * np.linalg.inv(design.T @ design)
    else:
        cov = np.full((2, 2), np.nan)
    return ReadNoiseSplit(float(coef[0]), float(coef[1]), float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1])),
                          weighted)
