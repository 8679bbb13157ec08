"""Registration of the frames of a hand-held bracket (array code; OpenCV's phase correlation
and ECC).

Frames differ in exposure, so they are compared in an exposure-invariant form: the
linearised signal divided by the frame's exposure, limited to the irradiance range both
frames of a pair measure, in log units (:func:`log_irradiance`).  Phase correlation finds a
coarse translation; the enhanced correlation coefficient maximisation (Evangelidis and
Psarakis 2008, ``cv2.findTransformECC``, invariant to gain and offset) refines it on a
pyramid and on a central full-resolution window, and for ``similarity`` adds a rotation
(ECC's Euclidean model), kept only where it beats the translation.  A consensus of tiles
registered on their own removes what a moving object pulls (:func:`estimate_warp`).

A warp is a ``(2, 3)`` affine matrix ``W`` mapping reference-frame coordinates ``(x, y)``
(pixel centres, x to the right) to the frame's own coordinates: the frame is brought onto
the reference by sampling it at ``W @ (x, y, 1)`` (:mod:`hdrmerge_cli.core.resample`).
``translation`` has ``W = [I | t]``; ``similarity`` a rotation and a translation (scale 1:
exposure brackets do not zoom).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.resample import _cv2
from hdrmerge_cli.core.samples import Samples

#: longest side of the coarse registration level
COARSE_SIDE = 1024
#: how far (in pixels of the pyramid's finest level) the full-resolution similarity ECC
#: may move the window's corners from the pyramid's estimate (:func:`_fine_ecc`)
FINE_REACH = 4
#: longest side of the phase correlation's images (pixels): it only starts ECC, which may
#: correct it by up to :data:`MAX_REFINE_PX`, so half the coarse level suffices
PHASE_SIDE = 512
#: side of the full-resolution refinement window
FINE_SIDE = 1024
#: longest side of the coarsest ECC pyramid level (at least)
PYRAMID_MIN = 64
#: the motion models :func:`estimate_warp` fits
MOTIONS = ("translation", "similarity")
#: registration needs this many textured pixels off the plateaus in both frames
MIN_TEXTURED = 400
#: registration images narrower than this (pixels) are not registered: the texture test's
#: 3 x 3 smoothing and gradient need an interior, and ECC's pyramid a few levels
MIN_SIDE = 8
#: ... and this many of them (a quarter) textured across each axis (:func:`texture`): edges
#: all one way fix no shift along them
MIN_ACROSS = 100
#: log-irradiance gradient per pixel (about 10 % contrast) that counts as texture
TEXTURE_LOG_GRAD = 0.1
#: largest correction (pixels) ECC may make to the phase-correlation translation: beyond
#: it ECC has left the optimum the phase correlation started it in
MAX_REFINE_PX = 3.0
#: a rotation is kept when it moves some corner of the frame by more than this (pixels): a
#: smaller one is not worth resampling for
ROTATION_PX = 0.25
#: a registration is trusted (``--align`` keeps it) when its correlation coefficient reaches this
MIN_CONFIDENCE = 0.3


def _reduction(shape, side: int) -> int:
    """The least integer factor that brings the longest of ``shape`` to at most ``side``."""
    return max(1, -(-max(shape) // side))


def log_irradiance(lin: np.ndarray, exposure: float, lo: float, hi: float) -> np.ndarray:
    """``log(clip(lin / exposure, 0, hi) + lo)`` as float32: ``lin`` the linearised signal
    (full scale 1), ``[lo, hi]`` the irradiance range both frames of a pair measure (see
    :func:`common_range`).  Above ``hi`` a plateau (the longer frame clips there); below
    ``lo`` a soft floor rather than a hard one, so the noise of the shorter frame's darkest
    readings is not turned into a biased edge where they meet the floor."""
    out = np.clip(np.asarray(lin, np.float32) * np.float32(1.0 / exposure), 0.0, np.float32(hi))
    out += np.float32(lo)
    return np.log(out, out=out)


def dark_floor(code_step: float | None) -> float:
    """The darkest signal (fraction of full scale) registration trusts in a frame, the
    ``lo_code`` of :func:`common_range`: 2 %, or 16 codes where the codes are linear
    (``code_step``: one code as a fraction of full scale) and that is lower.  None: codes
    through a response, whose lowest codes stand for signals deep in the sensor's noise."""
    return 0.02 if code_step is None else min(0.02, 16.0 * code_step)


def common_range(exposures, lo_code: float = 0.02, hi_code: float = 0.9) -> tuple[float, float]:
    """The irradiance range every frame of a pair measures well: above ``lo_code`` of full
    scale in the shorter exposure (RAW: 16 codes) and below ``hi_code`` in the longer one."""
    h = np.asarray(exposures, np.float64)
    lo, hi = lo_code / h.min(), hi_code / h.max()
    if lo >= hi:
        raise HdrMergeError("two frames share no well-exposed irradiance range; they cannot be aligned")
    return lo, hi


def block_mean(img: np.ndarray, f: int) -> np.ndarray:
    """Area average over ``f x f`` blocks (rows and columns beyond whole blocks dropped)."""
    if f == 1:
        return img
    h, w = img.shape[0] // f * f, img.shape[1] // f * f
    return _cv2().resize(np.ascontiguousarray(img[:h, :w], np.float32), (w // f, h // f),
                         interpolation=_cv2().INTER_AREA)  # an integer factor: exactly the block mean


def rescale_warp(warp: np.ndarray, f: float, c: float) -> np.ndarray:
    """A warp found on images reduced by ``f`` (coarse pixel ``u`` has its centre at full-
    resolution ``f u + c``) expressed at full resolution."""
    a = warp[:, :2]
    out = warp.copy()
    out[:, 2] = f * warp[:, 2] + (np.eye(2) - a) @ np.array([c, c])
    return out


def shift_warp(warp: np.ndarray, origin) -> np.ndarray:
    """The warp in the coordinates of a window whose top-left corner is ``origin = (x0, y0)``
    in both images (and back with ``-origin``)."""
    out = warp.copy()
    out[:, 2] = warp[:, 2] + (warp[:, :2] - np.eye(2)) @ np.asarray(origin, np.float64)
    return out


#: log-irradiance difference (about 25 %) within which a pixel counts as matched
MATCH_TOL = 0.25


def matched(reference: np.ndarray, image: np.ndarray, warp: np.ndarray) -> float:
    """The fraction of the reference's pixels that ``image`` (brought onto it by ``warp``)
    matches to :data:`MATCH_TOL`, among those the warped image covers off the plateaus.
    Moving objects and misregistered texture are the unmatched ones."""
    cv2 = _cv2()
    h, w = reference.shape
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    moved = cv2.warpAffine(image, warp.astype(np.float32), (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=np.nan)
    lo, hi = float(reference.min()), float(reference.max())
    # pixels on the clipping plateaus of the common range match trivially: they do not vote
    inside = np.isfinite(moved) & (reference > lo + 1e-4) & (reference < hi - 1e-4)
    ok = inside & (np.abs(np.where(inside, moved, 0) - reference) < MATCH_TOL)
    return float(ok.sum() / max(inside.sum(), 1))


def _phase_shift(template: np.ndarray, image: np.ndarray) -> np.ndarray:
    """The translation warp of the phase-correlation peak (OpenCV, Hann window)."""
    cv2 = _cv2()
    win = cv2.createHanningWindow(template.shape[::-1], cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(template.astype(np.float64), image.astype(np.float64), win)
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]])


def _window(n: int) -> tuple[int, int]:
    """The central :data:`FINE_SIDE` span of ``n`` pixels."""
    start = max(0, (n - FINE_SIDE) // 2)
    return start, min(n, start + FINE_SIDE)


def _central(reference: np.ndarray, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Both images' central :data:`FINE_SIDE` window (:func:`_window`, contiguous) and its
    origin ``(x0, y0)`` in the frame."""
    (y0, y1), (x0, x1) = _window(reference.shape[0]), _window(reference.shape[1])
    return (np.ascontiguousarray(reference[y0:y1, x0:x1]), np.ascontiguousarray(image[y0:y1, x0:x1]), (x0, y0))


def off_plateau(img: np.ndarray) -> np.ndarray:
    """Pixels strictly inside the clipped range of an exposure-invariant image (its
    plateaus are where one frame of the pair reads dark or clipped), uint8 0/1."""
    lo, hi = float(img.min()), float(img.max())
    return ((img > lo + 1e-4) & (img < hi - 1e-4)).astype(np.uint8)


def texture(img: np.ndarray, grad: float = TEXTURE_LOG_GRAD, scale: int = 1) -> tuple[int, int]:
    """``(textured, across)``: how many pixels off the plateaus carry texture, a
    log-irradiance gradient (3 x 3 box-smoothed, so single-pixel noise does not count) above
    ``grad`` per pixel; and the fewer of those whose gradient's x component, and
    those whose y component, is above ``grad`` / sqrt 2: edges in one direction only fix
    no shift along them (the aperture problem).  Measured at most :data:`COARSE_SIDE` on a
    side; ``scale``: full-resolution pixels per pixel of ``img`` (counts and gradients are per
    full-resolution pixel)."""
    cv2 = _cv2()
    f = _reduction(img.shape, COARSE_SIDE)
    small = block_mean(img, f)
    smooth = cv2.blur(small, (3, 3))
    inside = off_plateau(small) > 0
    gy, gx = np.gradient(smooth)
    f *= scale
    limit = grad * f  # per full-resolution pixel
    textured = int(np.count_nonzero((np.hypot(gx, gy) > limit) & inside))
    across = min(int(np.count_nonzero((np.abs(g) > limit / np.sqrt(2)) & inside)) for g in (gx, gy))
    return textured * f * f, across * f * f


def registrable(a: np.ndarray, b: np.ndarray, scale: int = 1) -> str | None:
    """Why two exposure-invariant images cannot be registered, or None: each needs
    :data:`MIN_TEXTURED` textured pixels and :data:`MIN_ACROSS` textured across each axis
    (:func:`texture`), so an image of fewer than :data:`MIN_TEXTURED` pixels, or narrower
    than :data:`MIN_SIDE`, never is.  ``scale``: full-resolution pixels per pixel of the
    images (reduced images: :func:`coarse_factor`)."""
    if min(a.shape) * scale < MIN_SIDE or a.size * scale * scale < MIN_TEXTURED:
        return f"a {a.shape[0] * scale} x {a.shape[1] * scale} registration image is too small to register"
    (ta, xa), (tb, xb) = texture(a, scale=scale), texture(b, scale=scale)
    if min(ta, tb) < MIN_TEXTURED:
        return f"only {min(ta, tb)} textured pixels"
    if min(xa, xb) < MIN_ACROSS:
        return f"only {min(xa, xb)} pixels textured across each axis (edges all one way)"
    return None


def ecc_score(reference: np.ndarray, image: np.ndarray, warp: np.ndarray) -> float:
    """The enhanced correlation coefficient (Evangelidis and Psarakis 2008) of ``reference``
    and ``image`` sampled at ``warp`` (OpenCV's ``computeECC``), over a set of pixels that
    does not depend on the warp beyond the frame's edge: the reference's pixels off its
    plateaus that the warped image covers.  The image's own plateaus count (misplaced,
    they fall on the reference's texture).  -1 when too few pixels overlap."""
    cv2 = _cv2()
    h, w = reference.shape
    m = warp.astype(np.float32)
    flags = cv2.WARP_INVERSE_MAP
    moved = cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_LINEAR | flags, borderMode=cv2.BORDER_REPLICATE)
    inside = cv2.warpAffine(np.ones(image.shape, np.uint8), m, (w, h), flags=cv2.INTER_NEAREST | flags,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    mask = inside & off_plateau(reference)
    if np.count_nonzero(mask) < 16:
        return -1.0
    try:
        return float(cv2.computeECC(reference, moved, mask))
    except cv2.error:
        return -1.0


def _ecc(template: np.ndarray, image: np.ndarray, warp: np.ndarray, motion: str, eps: float = 1e-5,
         count: int = 100, template_mask: np.ndarray | None = None) -> np.ndarray | None:
    """OpenCV's ECC maximisation from ``warp`` (translation, or rotation + translation for
    ``similarity``; no pre-smoothing: it biases the optimum where plateaus meet texture), None when it does not converge.  No
    mask on the image: the plateaus are where either frame of the pair clips, the same irradiance in
    both, so their edges register like any other (a nearest-neighbour-warped mask biases
    the sub-pixel optimum by tenths of a pixel).  ``template_mask`` (uint8, 0 = left out;
    ``findTransformECCWithMask``) is not warped, so it adds no such pull.  OpenCV writes the
    warp it is given: it gets a copy."""
    cv2 = _cv2()
    mode = cv2.MOTION_TRANSLATION if motion == "translation" else cv2.MOTION_EUCLIDEAN
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, count, eps)
    try:
        if template_mask is None:
            _, found = cv2.findTransformECC(template, image, warp.astype(np.float32), mode, criteria, None, 1)
        else:
            _, found = cv2.findTransformECCWithMask(template, image, template_mask, np.full(image.shape, 255, np.uint8),
                                                    warp.astype(np.float32), mode, criteria, 1)
    except cv2.error:
        return None
    return found.astype(np.float64)


def _pyramid_ecc(reference: np.ndarray, image: np.ndarray, warp: np.ndarray, motion: str) -> np.ndarray:
    """ECC coarse to fine on area-averaged levels (factors 2^k, every level between
    :data:`PYRAMID_MIN` and :data:`COARSE_SIDE` pixels wide; loosely converged), each level
    starting from the one before; a level that does not converge leaves the warp as it
    was.  Full resolution is :func:`_fine_ecc`'s."""
    side = max(reference.shape)
    levels = [f for f in (2**k for k in range(1, 16)) if PYRAMID_MIN <= side / f <= COARSE_SIDE]
    for f in sorted(levels, reverse=True):
        c = (f - 1) / 2
        level = rescale_warp(warp, 1 / f, -c / f)
        found = _ecc(block_mean(reference, f), block_mean(image, f), level, motion, eps=1e-4)
        if found is not None:
            warp = rescale_warp(found, f, c)
    return warp


def _finest_level(shape: tuple[int, ...]) -> int:
    """The factor of :func:`_pyramid_ecc`'s finest level (at most :data:`COARSE_SIDE` wide)."""
    return next(f for f in (2**k for k in range(1, 32)) if max(shape) / f <= COARSE_SIDE)


def _fine_ecc(reference: np.ndarray, image: np.ndarray, warp: np.ndarray, motion: str) -> np.ndarray | None:
    """ECC at full resolution on the central :data:`FINE_SIDE` window, from ``warp``; None
    when it does not converge or, for ``similarity``, moves a corner of the window by more
    than :data:`FINE_REACH` pixels of the pyramid's finest level (a refinement does not
    jump; a false optimum, e.g. a moving object filling the window, does).  At most
    :data:`FINE_ITERATIONS` iterations, and None if the run has not settled by then
    (:data:`FINE_SETTLED_PX`); a similarity run is also checked after :data:`FINE_CHECK`
    iterations (:data:`FINE_WANDER_PX`, :data:`FINE_CONVERGED_PX`)."""
    ref, img, (x0, y0) = _central(reference, image)
    start = shift_warp(warp, (x0, y0))
    reach = max(MAX_REFINE_PX, FINE_REACH * _finest_level(reference.shape))
    size = ref.shape

    def jumped(warp):
        return motion == "similarity" and corner_distance(warp, start, *size) > reach

    found = _ecc(ref, img, start, motion, count=FINE_ITERATIONS if motion == "translation" else FINE_CHECK - 1)
    if found is None:
        return None
    if motion == "similarity":  # checked after FINE_CHECK iterations too: a run that jumped, or still
        # moves a corner by FINE_WANDER_PX per iteration, is not refining; one that moves none by
        # FINE_CONVERGED_PX has converged (a restarted run takes at least two iterations more)
        step = _ecc(ref, img, found, motion, count=1)
        moved = None if step is None else corner_distance(step, found, *size)
        if step is None or moved > FINE_WANDER_PX or jumped(step):
            return None
        if moved <= FINE_CONVERGED_PX:
            return shift_warp(step, (-x0, -y0))
        found = _ecc(ref, img, step, motion, count=FINE_ITERATIONS - FINE_CHECK)
        if found is None:
            return None
    step = _ecc(ref, img, found, motion, count=1)  # settled: it moves no corner by FINE_SETTLED_PX
    if step is None or corner_distance(step, found, *size) > FINE_SETTLED_PX or jumped(found):
        return None
    return shift_warp(found, (-x0, -y0))


#: iterations of :func:`_fine_ecc` at most: from the pyramid's estimate a refinement
#: converges in far fewer; a run drifting to a false optimum stops here
FINE_ITERATIONS = 30
#: a fine run has settled when one more iteration moves no window corner farther (pixels)
FINE_SETTLED_PX = 0.5
#: a similarity run is checked after this many iterations too: refused if it moved a corner
#: beyond :data:`FINE_REACH` or its last iteration moved one by more than :data:`FINE_WANDER_PX`
FINE_CHECK = 10
#: the most (pixels) a window corner may move in one iteration at that check
FINE_WANDER_PX = 2.0
#: ... and taken as converged if that iteration moved no corner by this much (pixels)
FINE_CONVERGED_PX = 0.01


#: a registered pair's log difference farther than this many robust deviations (1.4826 MAD)
#: from its median is a moving object's (:func:`_moved_region`): for Gaussian noise a
#: two-sided false-alarm rate of 6e-7 per pixel, before the opening and the area test
MOVED_SIGMAS = 5.0
#: a moved region covers at least this fraction of the window (noise outliers are scattered)
MOVED_MIN_AREA = 1e-3
#: a moved region is grown by this many pixels (its blurred edge, the warp's error)
MOVED_GROW_PX = 4


def _moved_region(reference: np.ndarray, moved: np.ndarray) -> np.ndarray | None:
    """Where a registered pair disagrees over a region (a moving object), ``(H, W)`` uint8
    255 = moved, or None where no region does: the log difference beyond
    :data:`MOVED_SIGMAS` robust deviations of its median, opened (isolated noise goes), its
    connected regions of at least :data:`MOVED_MIN_AREA` of the frame kept and grown by
    :data:`MOVED_GROW_PX`.  Both images on the reference's grid, off the reference's
    plateaus only (where one frame clips or reads dark the difference says nothing)."""
    cv2 = _cv2()
    on = off_plateau(reference) > 0
    if np.count_nonzero(on) < MIN_TEXTURED:
        return None
    d = reference - moved
    med = float(np.median(d[on]))
    scale = 1.4826 * float(np.median(np.abs(d[on] - med)))
    far = (on & (np.abs(d - med) > MOVED_SIGMAS * max(scale, 1e-6))).astype(np.uint8)
    far = cv2.morphologyEx(far, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    _, labels, stats, _ = cv2.connectedComponentsWithStats(far, connectivity=8)
    big = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= MOVED_MIN_AREA * far.size)
    big = big[big > 0]
    if big.size == 0:
        return None
    region = np.isin(labels, big).astype(np.uint8) * np.uint8(255)
    side = 2 * MOVED_GROW_PX + 1
    return cv2.dilate(region, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (side, side)))


def _masked_fine_ecc(reference: np.ndarray, image: np.ndarray, warp: np.ndarray, motion: str) -> np.ndarray | None:
    """``warp`` refined at full resolution on the central window (as :func:`_fine_ecc`) with
    the region a moving object covers in the reference left out (:func:`_moved_region`,
    found on the pair registered by ``warp``; OpenCV's ``findTransformECCWithMask``, whose
    template mask is not warped, so the mask adds no pull of its own).  None where no
    region moved, ECC does not converge, or it moves a window corner by more than
    :data:`MAX_REFINE_PX`.  The tile consensus does this where enough tiles register; a
    dark short frame's few textured tiles do not."""
    cv2 = _cv2()
    ref, img, (x0, y0) = _central(reference, image)
    start = shift_warp(warp, (x0, y0)).astype(np.float32)
    moved = cv2.warpAffine(img, start, ref.shape[::-1], flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_REPLICATE)
    region = _moved_region(ref, moved)
    if region is None:
        return None
    found = _ecc(ref, img, start, motion, count=FINE_ITERATIONS, template_mask=cv2.bitwise_not(region))
    if found is None or corner_distance(found, start, *ref.shape) > MAX_REFINE_PX:
        return None
    return shift_warp(found, (-x0, -y0))


def _translation(reference: np.ndarray, image: np.ndarray) -> np.ndarray:
    """Whole-image translation: the phase-correlation peak (OpenCV, sub-pixel) on area-
    averaged images against no motion, the one matching more pixels kept (a bright object
    crossing a still scene can win the correlation peak, but not the vote of the pixels)."""
    h, w = reference.shape
    f = _reduction((h, w), PHASE_SIDE)
    ref_c, img_c = block_mean(reference, f), block_mean(image, f)
    candidates = [np.eye(2, 3), _phase_shift(ref_c, img_c)]
    return rescale_warp(max(candidates, key=lambda c: matched(ref_c, img_c, c)), f, (f - 1) / 2)


#: tiles per side of the robust consensus (:func:`_tile_consensus`)
CONSENSUS_TILES = 5
#: a tile's correction farther than this (pixels) from the consensus is an outlier (motion);
#: the registration accuracy asked of a static tile
CONSENSUS_TOL_PX = 0.25
#: textured pixels a tile needs to take part: log-irradiance gradient above
#: :data:`TEXTURE_LOG_GRAD` per 1/:data:`COARSE_SIDE` of the frame's longer side (per pixel
#: up to that size: the same scene has less contrast per pixel on a sensor with more pixels)
CONSENSUS_MIN_TEXTURED = 200
#: tiles (a third of them) that must register for their disagreement to mean a non-rigid
#: scene rather than one moving object
CONSENSUS_JUDGE = 8
#: a tile is registered on its central window at most this many pixels on a side
CONSENSUS_TILE_SIDE = 256
#: ECC's convergence threshold (change of the correlation) for a tile
CONSENSUS_EPS = 1e-4


def _euclidean_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The rotation and translation (no scale: a camera that turned, not zoomed) taking the
    points ``src`` nearest to ``dst`` in least squares (2-D Procrustes: the angle of the
    summed cross and dot products of the centred points), ``(2, 3)``."""
    a, b = src - src.mean(axis=0), dst - dst.mean(axis=0)
    theta = np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b))
    r = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    return np.hstack([r, (dst.mean(axis=0) - r @ src.mean(axis=0))[:, None]])


def _tile_consensus(reference: np.ndarray, image: np.ndarray, warp: np.ndarray, motion: str) -> tuple[np.ndarray | None, bool]:
    """A correction of ``warp`` that a moving object cannot bias, by a consensus of tiles.

    ``image`` is resampled onto ``reference`` by ``warp`` (bicubic) and each of
    :data:`CONSENSUS_TILES` x :data:`CONSENSUS_TILES` tiles registered on its own (ECC
    translation on its central :data:`CONSENSUS_TILE_SIDE` window); the tile shifts are
    fitted robustly (the median, or for ``similarity`` OpenCV's least-median-of-squares
    similarity), tiles beyond :data:`CONSENSUS_TOL_PX` of the fit dropped and the fit redone
    without scale (:func:`_euclidean_fit`; its rotation kept where ``warp`` rotates or it
    moves a corner by :data:`ROTATION_PX`).  Returns ``(warp, judged)``: the corrected
    ``(2, 3)`` warp, or None unless at least 4 textured tiles
    (:data:`CONSENSUS_MIN_TEXTURED`) registered within :data:`MAX_REFINE_PX` and at least
    half of them agree; ``judged``: True with a warp, and with None when
    :data:`CONSENSUS_JUDGE` tiles registered but agree on no rigid motion."""
    cv2 = _cv2()
    h, w = reference.shape
    n = CONSENSUS_TILES
    th, tw = h // n, w // n
    if min(th, tw) < 32:
        return None, False
    moved = cv2.warpAffine(image, warp.astype(np.float32), (w, h), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_REPLICATE)
    inside = covered_mask(warp, *image.shape)
    sh, sw = min(th, CONSENSUS_TILE_SIDE), min(tw, CONSENSUS_TILE_SIDE)
    grad = TEXTURE_LOG_GRAD / max(1.0, max(h, w) / COARSE_SIDE)  # per pixel, as at the coarse level

    def register(corner):  # one tile: its centre and shift, or None
        y0, x0 = corner
        rows, cols = slice(y0, y0 + sh), slice(x0, x0 + sw)
        if not inside[rows, cols].all():
            return None
        tile = np.ascontiguousarray(reference[rows, cols])
        if texture(tile, grad)[0] < CONSENSUS_MIN_TEXTURED:  # isotropic: the directional count lost rotations
            return None
        found = _ecc(tile, np.ascontiguousarray(moved[rows, cols]), np.eye(2, 3), "translation", eps=CONSENSUS_EPS)
        if found is None or not np.all(np.abs(found[:, 2]) <= MAX_REFINE_PX):
            return None
        return (x0 + (sw - 1) / 2, y0 + (sh - 1) / 2), found[:, 2]

    corners = [(i * th + (th - sh) // 2, j * tw + (tw - sw) // 2) for i in range(n) for j in range(n)]
    with ThreadPoolExecutor(2) as pool:  # OpenCV's ECC releases the GIL: both cores
        results = [r for r in pool.map(register, corners) if r is not None]
    centres = [c for c, _ in results]
    shifts = [d for _, d in results]
    if len(shifts) < 4:
        return None, False
    src = np.asarray(centres, np.float64)
    dst = src + np.asarray(shifts, np.float64)
    fit = cv2.estimateAffinePartial2D(src, dst, method=cv2.LMEDS)[0] if motion == "similarity" else None
    pred = src + np.median(dst - src, axis=0) if fit is None else src @ fit[:, :2].T + fit[:, 2]
    keep = np.hypot(*(pred - dst).T) <= CONSENSUS_TOL_PX
    if keep.sum() < max(4, len(src) // 2):
        return None, len(src) >= CONSENSUS_JUDGE
    correction = np.hstack([np.eye(2), np.mean(dst[keep] - src[keep], axis=0)[:, None]])
    if motion == "similarity":  # the rotation too: the warp rotates already, or it moves a corner by > ROTATION_PX
        rotated = _euclidean_fit(src[keep], dst[keep])
        if not np.allclose(warp[:, :2], np.eye(2)) or corner_distance(rotated, correction, h, w) > ROTATION_PX:
            correction = rotated
    return compose(warp, correction.astype(np.float64)), True


class Registered(NamedTuple):
    """:func:`estimate_warp`'s result: the ``(2, 3)`` float64 warp and its correlation ``rho``."""

    warp: np.ndarray
    rho: float


def estimate_warp(reference: np.ndarray, image: np.ndarray, motion: str = "translation") -> Registered:
    """The warp bringing ``image`` onto ``reference`` and its confidence.

    ``reference``, ``image``: ``(H, W)`` float32 exposure-invariant images
    (:func:`log_irradiance`); ``motion``: one of :data:`MOTIONS`.  Returns the
    :class:`Registered` warp (reference to image coordinates) and the enhanced correlation
    coefficient of the registered pair off the plateaus (:func:`ecc_score`).
    Phase correlation (:func:`_translation`) starts ECC (Evangelidis and Psarakis 2008) on
    a pyramid (:func:`_pyramid_ecc`) and the central full-resolution window
    (:func:`_fine_ecc`), kept within :data:`MAX_REFINE_PX` of it.  ``similarity`` adds a
    rotation where the change is mostly one (:func:`_turned`), refined by the tile consensus
    or on the window, kept where it correlates better and moves a corner by
    :data:`ROTATION_PX`, never where the tiles agree on no rigid motion.  Last the tile
    consensus (:func:`_tile_consensus`), or with too few tiles :func:`_masked_fine_ecc`,
    removes what a moving object pulled."""
    if motion not in MOTIONS:
        raise ValueError(f"unknown motion {motion!r}")
    ref_w, img_w, origin = _central(reference, image)

    def score(warp):
        return ecc_score(ref_w, img_w, shift_warp(warp, origin))

    phase = _translation(reference, image)

    def near(warp):  # ECC's result stands within MAX_REFINE_PX of the phase correlation's
        return warp is not None and np.max(np.abs(warp[:, 2] - phase[:, 2])) <= MAX_REFINE_PX

    coarse = _pyramid_ecc(reference, image, phase, "translation")
    best = coarse if near(coarse) else phase

    def refine_translation():  # at full resolution, on the central window
        refined = _fine_ecc(reference, image, coarse, "translation")
        return refined if near(refined) else phase

    rotated = _pyramid_ecc(reference, image, best, "similarity") if motion == "similarity" else None
    # a rotation the fine window sees (its corners turn by FINE_SETTLED_PX) is tried first: a
    # translation cannot fit that window, and is refined only if the rotation is not kept
    later = (rotated is not None and _turned(rotated, best, reference.shape)
             and _window_turn(rotated, best, reference.shape) > FINE_SETTLED_PX)
    if not later:
        best = refine_translation()
    rho = score(best)
    if motion == "similarity":
        corners = corner_distance(rotated, best, *reference.shape)
        if corners > ROTATION_PX and _turned(rotated, best, reference.shape):  # the coarse levels see a
            # rotation that is not negligible: refine it over the whole frame by the tile consensus, or at full
            # resolution on the central window where the tiles cannot (the pyramid's estimate stands where both
            # fail), keep it if it correlates better.  Tiles that registered but agree on no rigid motion (a
            # non-rigid scene: foliage in wind) refuse it: ECC's extra parameter always correlates a little better
            fine, judged = _tile_consensus(reference, image, rotated, motion)
            if fine is not None or not judged:
                fine = _fine_ecc(reference, image, rotated, "similarity") if fine is None else fine
                rotated = rotated if fine is None else fine
                if ((r := score(rotated)) > rho
                        and corner_distance(rotated, best, *reference.shape) > ROTATION_PX):
                    best, rho = rotated, r
                    later = False
    if later:  # the rotation was not kept
        best = refine_translation()
        rho = score(best)
    robust, _ = _tile_consensus(reference, image, best, motion)
    if robust is None:  # too few tiles registered: leave out what moved, if anything did
        turned = not np.allclose(best[:, :2], np.eye(2))
        robust = _masked_fine_ecc(reference, image, best, "similarity" if turned else "translation")
    if robust is not None:
        best, rho = robust, score(robust)
    return Registered(best, rho)


def _turned(rotated: np.ndarray, warp: np.ndarray, shape: tuple[int, ...]) -> bool:
    """Whether what a rotation step changed from ``warp`` is mostly a rotation: the frame's
    centre moved by at most :data:`MAX_REFINE_PX` or half what its corners move (a drift
    moves the centre as far as the corners)."""
    centre = np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2, 1.0])
    return bool(np.hypot(*((rotated - warp) @ centre)) <= max(MAX_REFINE_PX, corner_distance(rotated, warp, *shape) / 2))


def _window_turn(rotated: np.ndarray, warp: np.ndarray, shape: tuple[int, ...]) -> float:
    """How far (pixels) ``rotated`` moves the corners of :func:`_fine_ecc`'s window (of a frame
    of ``shape``) about its centre, beyond ``warp``: what a translation of the window cannot fit."""
    a = (rotated - warp)[:, :2]
    hy, hx = ((min(FINE_SIDE, n) - 1) / 2 for n in shape[:2])
    return float(max(np.hypot(*(a @ np.array([sx * hx, sy * hy]))) for sx in (-1, 1) for sy in (-1, 1)))


def compose(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """``outer o inner``: first ``inner``, then ``outer`` (both ``(2, 3)``)."""
    out = outer[:, :2] @ inner
    out[:, 2] += outer[:, 2]
    return out


def pair_displacement(a: np.ndarray, b: np.ndarray) -> float | None:
    """How far (in pixels of the images) ``b`` sits from ``a``: the length of the
    translation registering them (:func:`hdrmerge_cli.core.estimate_warp`: phase
    correlation against no motion by the vote of the pixels, refined by ECC), or None when
    the pair cannot be registered (too little texture in either,
    :func:`hdrmerge_cli.core.registrable`, or a correlation under
    :data:`MIN_CONFIDENCE`).

    a, b : (H, W) float32 exposure-invariant images of the same pixels (see
    :func:`log_irradiance`)
    """
    a, b = np.ascontiguousarray(a, np.float32), np.ascontiguousarray(b, np.float32)
    if min(a.shape) < 16 or registrable(a, b) is not None:
        return None
    warp, rho = estimate_warp(a, b, "translation")
    if not np.isfinite(rho) or rho < MIN_CONFIDENCE:
        return None
    return float(np.hypot(warp[0, 2], warp[1, 2]))


def corner_distance(a: np.ndarray, b: np.ndarray, height: int, width: int) -> float:
    """Largest distance (pixels) between where two warps take a corner of the frame."""
    corners = np.array([[0, 0, 1], [width - 1, 0, 1], [0, height - 1, 1], [width - 1, height - 1, 1]], np.float64)
    return float(np.max(np.hypot(*(corners @ a.T - corners @ b.T).T)))


def warp_size(warp: np.ndarray, height: int, width: int) -> float:
    """Largest displacement (pixels) the warp causes anywhere in the frame."""
    return corner_distance(warp, np.eye(2, 3), height, width)


def covered_mask(warp: np.ndarray, height: int, width: int, rows: slice | None = None) -> np.ndarray:
    """Which reference pixels ``(x, y)`` the warp takes inside the frame (``W @ (x, y, 1)``
    within half a pixel of its edge), ``(height, width)`` bool (``rows``: those rows
    only).  The set is convex: each row's pixels inside form one interval, found from the
    four edge inequalities."""
    y = np.arange(height, dtype=np.float64)[rows if rows is not None else slice(None)]
    lo, hi = np.full(y.size, -np.inf), np.full(y.size, np.inf)
    for row, size in ((warp[0], width), (warp[1], height)):  # -0.5 <= p x + q(y) <= size - 0.5
        p, q = row[0], row[1] * y + row[2]
        if abs(p) < 1e-12:
            ok = (q >= -0.5) & (q <= size - 0.5)
            lo[~ok], hi[~ok] = np.inf, -np.inf
            continue
        a, b = (-0.5 - q) / p, (size - 0.5 - q) / p
        lo, hi = np.maximum(lo, np.minimum(a, b)), np.minimum(hi, np.maximum(a, b))
    first = np.clip(np.ceil(lo - 1e-9), 0, width).astype(np.int64)  # each row's pixels first..last
    last = np.clip(np.floor(hi + 1e-9) + 1, 0, width).astype(np.int64)
    out = np.zeros((y.size, width), bool)
    for i in np.flatnonzero(last > first):  # row by row: faster than a comparison per pixel
        out[i, first[i]:last[i]] = True
    return out


#: the still test's error rate (:func:`still_test`): a pair displaced by its tolerance or
#: more is declared still with at most this probability
STILL_P_MISS = 1e-3
#: side (coarse pixels) of the tiles whose scores :func:`still_test`'s covariance sums
#: (residuals correlated within a tile are allowed for)
STILL_TILE = 16
#: the least side (pixels) of :func:`linear_step`'s images
STILL_MIN_SIDE = 2 * STILL_TILE + 4


def _quantile(p_miss: float) -> float:
    """``z(1 - p_miss)``, the standard normal's upper ``p_miss`` quantile."""
    from statistics import NormalDist

    return NormalDist().inv_cdf(1.0 - p_miss)


def coarse_factor(height: int, width: int, cell: int = 1) -> int:
    """Frame pixels per coarse pixel: ``cell`` (a registration image's pixel: 2 for a RAW
    frame's CFA cells) times the reduction :func:`texture` makes of the registration image
    (at most :data:`COARSE_SIDE` on a side)."""
    return cell * _reduction((height // cell, width // cell), COARSE_SIDE)


def _dft_side(n: int) -> int:
    """The longest side at most ``n`` that is even and a product of 2, 3 and 5 only."""
    for m in range(n - n % 2, 1, -2):
        k = m
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
    return n


class StillTest(NamedTuple):
    """:func:`still_test`'s verdict.

    still : displaced by less than the tolerance at every corner, at the test's confidence
    warp : the estimated translation as a warp (the frame centre's displacement)
    bound : the corner bound (frame pixels): estimate plus ``z(1 - p_miss)`` deviations
    rho : the correlation coefficient (:func:`correlation`)
    """

    still: bool
    warp: np.ndarray
    bound: float
    rho: float


def still_test(reference: np.ndarray, image: np.ndarray, scale: int, height: int, width: int, tol: float,
               p_miss: float = STILL_P_MISS) -> StillTest:
    """Whether ``image`` lies within ``tol`` frame pixels of ``reference`` everywhere, decided
    on coarse images without registering them.

    ``reference``, ``image``: :func:`log_irradiance` images of block means, pixel ``u`` centred
    on frame pixel ``scale u + (scale - 1) / 2`` of a ``height`` x ``width`` frame.  Rule: the
    motion (rotation, translation; gain, offset) of :func:`linear_step`, with its covariance;
    still when at each frame corner the estimated displacement plus ``z(1 - p_miss)``
    standard deviations along its least certain direction is below ``tol``.  Meaning: a pair
    displaced by ``tol`` or more at some corner is declared still with probability at most
    ``p_miss`` (the linear step's range: a phase correlation a pixel or more off is never
    still).  A still pair needs no registration; any other is registered in full.
    Returns a :class:`StillTest`."""
    cv2 = _cv2()
    identity = np.eye(2, 3)
    k = _reduction(reference.shape, PHASE_SIDE)
    a, b = block_mean(reference, k), block_mean(image, k)
    h, w = _dft_side(a.shape[0]), _dft_side(a.shape[1])  # even (OpenCV's phase correlation is biased on odd
    # sides) and fast to transform
    a, b = np.ascontiguousarray(a[:h, :w], np.float32), np.ascontiguousarray(b[:h, :w], np.float32)
    scale *= k
    if min(h, w) < STILL_MIN_SIDE:
        return StillTest(False, identity, float("inf"), -1.0)
    rho = correlation(a, b)
    (px, py), _ = cv2.phaseCorrelate(a.astype(np.float64), b.astype(np.float64),
                                     cv2.createHanningWindow((w, h), cv2.CV_64F))
    if max(abs(px), abs(py)) >= 1.0:
        return StillTest(False, identity, float("inf"), rho)
    step = linear_step(a, b)
    if step is None:
        return StillTest(False, identity, float("inf"), rho)
    theta, cov = step
    z = _quantile(p_miss)
    bound = max(float(np.hypot(*(lin @ theta))) + z * _spread(lin, cov)
                for lin in _corner_maps((h, w), scale, height, width))
    warp = identity.copy()
    warp[:, 2] = scale * theta[:2]
    return StillTest(bound < tol, warp, bound, rho)


def _corner_maps(shape: tuple[int, int], scale: int, height: int, width: int) -> list[np.ndarray]:
    """Per frame corner, the ``(2, 5)`` map from :func:`linear_step`'s ``theta`` (on an image
    of ``shape`` whose pixel ``u`` is centred on frame pixel ``scale u + (scale - 1) / 2``)
    to that corner's displacement in frame pixels."""
    h, w = shape
    cy, cx = (h - 1) / 2, (w - 1) / 2
    s = max(cx, cy)
    out = []
    for fx, fy in ((0, 0), (width - 1, 0), (0, height - 1), (width - 1, height - 1)):
        ux, uy = (fx - (scale - 1) / 2) / scale, (fy - (scale - 1) / 2) / scale  # in the test's pixels
        out.append(scale * np.array([[1.0, 0.0, -(uy - cy) / s, 0.0, 0.0], [0.0, 1.0, (ux - cx) / s, 0.0, 0.0]]))
    return out


def _spread(lin: np.ndarray, cov: np.ndarray) -> float:
    """The standard deviation of ``lin @ theta`` along its least certain direction, for
    ``theta`` of covariance ``cov``."""
    return float(np.sqrt(max(np.linalg.eigvalsh(lin @ cov @ lin.T)[-1], 0.0)))


def displacement_margin(reference: np.ndarray, image: np.ndarray, warp: np.ndarray, scale: int, height: int,
                        width: int, p_miss: float = STILL_P_MISS) -> float:
    """What a registration cannot tell from no motion: ``z(1 - p_miss)`` standard deviations of
    the displacement at the least certain frame corner (frame pixels), from the covariance
    of :func:`linear_step` of ``reference`` against ``image`` brought onto it by ``warp``
    (frame pixels; the images as in :func:`still_test`, reduced to at most
    :data:`PHASE_SIDE` on a side).  A registered displacement below it is one the pair does
    not pin.  inf where the step is singular or the images too small."""
    cv2 = _cv2()
    k = _reduction(reference.shape, PHASE_SIDE)
    f, c = scale * k, (scale * k - 1) / 2
    a = np.ascontiguousarray(block_mean(reference, k), np.float32)
    h, w = a.shape
    if min(h, w) < STILL_MIN_SIDE:
        return float("inf")
    coarse = rescale_warp(np.asarray(warp, np.float64), 1.0 / f, -c / f)  # frame -> test pixels: x = f u + c
    b = cv2.warpAffine(np.ascontiguousarray(block_mean(image, k), np.float32), coarse.astype(np.float32), (w, h),
                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
    step = linear_step(a, b)
    if step is None:
        return float("inf")
    z = _quantile(p_miss)
    return z * max(_spread(lin, step.cov) for lin in _corner_maps((h, w), f, height, width))


class LinearStep(NamedTuple):
    """:func:`linear_step`'s estimate ``theta`` ``(5,)`` and its covariance ``cov`` ``(5, 5)``."""

    theta: np.ndarray
    cov: np.ndarray


def linear_step(reference: np.ndarray, image: np.ndarray) -> LinearStep | None:
    """The motion of ``image`` against ``reference`` (``(h, w)`` float32, at least
    :data:`STILL_MIN_SIDE` on a side) by one linearised step from no motion (:class:`LinearStep`),
    ``theta`` = (x, y translation in pixels, rotation about the centre in radians times half
    the longer side, gain, offset), or None when the step is singular.  Instrumental
    variables: ``reference``'s gradients are the regressors, ``image``'s the instruments
    (five-tap differences that leave a pixel's own value out), so noise does not shrink the
    estimate; ``cov``, ``(5, 5)``, is the sandwich over tiles of :data:`STILL_TILE` pixels
    (noise of any level, correlated within a tile)."""
    h, w = reference.shape
    a, b = reference, image
    t = STILL_TILE
    ny, nx = (h - 4) // t * t, (w - 4) // t * t  # interior pixels in whole tiles
    rows, cols = slice(2, 2 + ny), slice(2, 2 + nx)
    cy, cx = (h - 1) / 2, (w - 1) / 2
    s = np.float32(max(cx, cy))
    ry = (-(np.arange(2, 2 + ny, dtype=np.float32) - np.float32(cy)) / s)[:, None]  # a rotation's displacement per
    rx = ((np.arange(2, 2 + nx, dtype=np.float32) - np.float32(cx)) / s)[None, :]  # radian and s
    m = a + b
    near = m[rows, 3:3 + nx] + m[rows, 1:1 + nx] + m[3:3 + ny, cols] + m[1:1 + ny, cols]  # neighbours (not the pixel)
    near -= near.mean(dtype=np.float64)

    def columns(img):  # gradients by five-tap central differences (the pixel's own value left out), rotation,
        # gain, offset
        out = np.empty((5, ny, nx), np.float32)
        for c, (lo2, lo1, hi1, hi2) in enumerate(((img[rows, 0:nx], img[rows, 1:1 + nx], img[rows, 3:3 + nx],
                                                   img[rows, 4:4 + nx]),
                                                  (img[0:ny, cols], img[1:1 + ny, cols], img[3:3 + ny, cols],
                                                   img[4:4 + ny, cols]))):
            np.subtract(hi1, lo1, out=out[c])
            out[c] *= np.float32(8.0 / 12.0)
            out[c] -= (hi2 - lo2) * np.float32(1.0 / 12.0)
        np.multiply(out[0], ry, out=out[2])
        out[2] += out[1] * rx
        out[3] = near
        out[4] = 1.0
        return out.reshape(5, -1)

    x_reg, z_ins = columns(a), columns(b)
    r = (a - b)[rows, cols].reshape(-1)
    zx = (z_ins @ x_reg.T).astype(np.float64)
    try:
        inv = np.linalg.inv(zx)
    except np.linalg.LinAlgError:
        return None
    theta = inv @ (z_ins @ r).astype(np.float64)
    e = r - (theta.astype(np.float32) @ x_reg)
    z_ins *= e
    scores = z_ins.reshape(5, ny // t, t, nx // t, t).sum(axis=(2, 4), dtype=np.float64).reshape(5, -1)
    g = scores.shape[1]
    cov = inv @ (scores @ scores.T) @ inv.T * (g / max(g - 1, 1))
    return LinearStep(theta, cov)


def correlation(reference: np.ndarray, image: np.ndarray) -> float:
    """The correlation coefficient of two images over the reference's pixels off its
    plateaus (the measure :func:`ecc_score` takes of a registered pair); -1 when fewer than
    16 pixels are."""
    on = off_plateau(reference).ravel().astype(np.float32)
    n = float(on.sum(dtype=np.float64))
    if n < 16:
        return -1.0
    a, b = reference.ravel(), image.ravel()
    a = (a - np.float32(np.dot(a, on) / n)) * on
    b = (b - np.float32(np.dot(b, on) / n)) * on
    den = float(np.sqrt(float(np.dot(a, a)) * float(np.dot(b, b))))
    return float(np.dot(a, b)) / den if den > 0 else -1.0


def registration_image(codes: np.ndarray, crf, mosaic: bool, black: float, white: float,
                       n_codes: int) -> np.ndarray:
    """The image a frame is registered on, linear with full scale 1, float32: a Bayer
    mosaic's ``(H, W)`` codes as the mean of each 2 x 2 CFA cell, ``black`` subtracted and
    divided by ``white - black`` (half resolution, ``(H // 2, W // 2)``); an image's ``(H,
    W, C)`` codes (``n_codes`` values) as the mean of its channels linearised through the
    inverse response ``crf`` (:class:`~hdrmerge_cli.core.crf.CRF`), ``(H, W)``."""
    if mosaic:
        scale = white - black
        h, w = codes.shape[0] // 2 * 2, codes.shape[1] // 2 * 2
        out = np.empty((h // 2, w // 2), np.float32)
        rows = 64  # in strips: small temporaries, reused rather than faulted in afresh
        for r in range(0, h, rows):
            strip = codes[r:min(h, r + rows), :w].astype(np.float32)
            strip -= black
            strip /= scale
            out[r // 2:(r + strip.shape[0]) // 2] = block_mean(strip, 2)
        return out
    lut = crf.codes_table(n_codes, np.zeros(codes.shape[-1])).T.astype(np.float32)  # (N, C)
    if codes.shape[-1] == 1:  # monochrome: the table lookup is the image
        return lut[codes[..., 0], 0]
    if codes.dtype == np.uint8:  # OpenCV's table lookup, all channels in one pass
        cv2 = _cv2()
        lin = cv2.LUT(codes, lut[None])
        if lin.shape[-1] <= 4:  # the channels' mean in one OpenCV pass
            return cv2.transform(lin, np.full((1, lin.shape[-1]), 1.0 / lin.shape[-1], np.float32))
    else:
        lin = np.stack([lut[codes[..., c], c] for c in range(codes.shape[-1])], axis=-1)
    return lin.mean(axis=-1, dtype=np.float32)


def coarse_mosaic_image(codes: np.ndarray, black: float, white: float, f: int) -> np.ndarray:
    """A Bayer mosaic's :func:`registration_image` reduced to blocks of ``f`` x ``f`` frame
    pixels (block means of whole CFA cells, ``f`` even; coarse pixel ``u`` centred on frame
    pixel ``f u + (f - 1) / 2``), float32 ``(H // f, W // f)``, from its codes in strips (an
    image's is the block mean of its registration image)."""
    cv2 = _cv2()
    h, w = codes.shape[0] // f * f, codes.shape[1] // f * f
    out = np.empty((h // f, w // f), np.float32)
    rows = 32  # coarse rows per strip: small temporaries, reused rather than faulted in afresh
    for r in range(0, h // f, rows):
        strip = codes[r * f:min(h, (r + rows) * f), :w]
        cells = cv2.resize(strip, (w // 2, strip.shape[0] // 2), interpolation=cv2.INTER_AREA)  # 2 x 2 means
        out[r:r + strip.shape[0] // f] = block_mean(cells.astype(np.float32), f // 2)
    out -= np.float32(black)
    out *= np.float32(1.0 / (white - black))
    return out


# ---------------------------------------------------------------- motion between exposures (on the samples)
#: a pair registered on the samples counts as moved when displaced by more than this many
#: sample pitches (:func:`moved_threshold_px`)
MOVED_PITCHES = 1.5
#: ... and by more than this many full-resolution pixels
MOVED_MIN_PX = 1.0


def moved_threshold_px(pitch: float) -> float:
    """Displacement (full-resolution pixels) beyond which a pair registered on samples
    ``pitch`` pixels apart counts as moved: :data:`MOVED_PITCHES` pitches, at least
    :data:`MOVED_MIN_PX`.

    The samples are a strided subsample (no prefilter: aliased), so their registration
    resolves about one pitch, not one full-resolution pixel: on the static real brackets
    of the test data (pitch 2 to 4) neighbour pairs registered on the samples at up to
    0.87 pitch (1.7 px), where full-resolution alignment found up to 1.9 px of real
    (tripod) movement and differed from the samples' registration by up to 0.7 pitch; the
    hand-held ones registered at 7 to 12 pitches (14 to 26 px).  A displacement under a
    pitch also barely reaches the ratio, which is read on the same samples: it moves the
    pixels next to edges by a fraction of a sample, and the ratio's 3-sigma rejection drops
    them."""
    return max(MOVED_MIN_PX, MOVED_PITCHES * float(pitch))


@dataclass
class Motion:
    """Neighbour pairs' displacement: ``px`` per pair index (frames ``j``, ``j + 1``) in
    full-resolution pixels, None where the pair could not be registered (too little texture
    in the range both expose, a weak correlation); pairs not asked about are absent.
    ``threshold_px``: beyond it a pair moved (:func:`moved_threshold_px` of the samples' pitch)."""

    px: dict[int, float | None]
    threshold_px: float

    @property
    def moved(self) -> frozenset[int]:
        """The pairs that moved (beyond ``threshold_px``)."""
        return frozenset(j for j, d in self.px.items() if d is not None and d > self.threshold_px)


def moved_pairs(s: Samples, exposures: np.ndarray, planes: dict[int, np.ndarray], pairs) -> Motion:
    """Register each neighbour pair in ``pairs`` (indices ``j``: frames ``j``, ``j + 1``) on
    the samples (:func:`pair_displacement` of their ``planes``, by frame index, the
    :func:`~hdrmerge_cli.core.exposure_estimate.sample_plane`, as :func:`log_irradiance`
    over the irradiance range both expose, exposure-normalised by ``exposures``, the
    labels: registration is invariant to the gain a wrong label makes), in full-resolution
    pixels (the samples' pitch).  A few tens of milliseconds a pair on the merge's default
    samples; only the pairs asked about are registered."""
    px: dict[int, float | None] = {}
    for j in sorted(set(pairs)):
        try:
            lo, hi = common_range([exposures[j], exposures[j + 1]], lo_code=dark_floor(s.codes_step if s.raw else None))
        except HdrMergeError:
            px[j] = None
            continue
        d = pair_displacement(log_irradiance(planes[j], exposures[j], lo, hi),
                              log_irradiance(planes[j + 1], exposures[j + 1], lo, hi))
        px[j] = None if d is None else d * s.pitch
    return Motion(px, moved_threshold_px(s.pitch))


def warp_motion(warps: list[np.ndarray], aligned: list[bool], applied: bool, height: int, width: int,
                pitch: float) -> Motion:
    """The neighbour pairs' displacement as a registration measured it, ``warps`` ``(2, 3)``
    per frame (``aligned``: False where a frame was left unaligned), for samples brought onto
    the reference with them when ``applied`` (:meth:`~hdrmerge_cli.core.samples.Samples.registered`): 0 left between
    two registered frames, unknown (None) where either was left unaligned; otherwise the
    largest distance between where the two frames' warps take a corner of the
    ``height`` x ``width`` frame.  ``pitch``: the samples' (:func:`moved_threshold_px`)."""
    px: dict[int, float | None] = {}
    for j in range(len(warps) - 1):
        if not (aligned[j] and aligned[j + 1]):
            px[j] = None
        else:
            px[j] = 0.0 if applied else corner_distance(warps[j], warps[j + 1], height, width)
    return Motion(px, moved_threshold_px(pitch))
