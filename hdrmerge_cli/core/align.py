"""Aligning the frames of a hand-held bracket (array code; OpenCV's phase correlation and
ECC registration).

Frames differ in exposure, so they are compared in an exposure-invariant form: the
linearised signal divided by the frame's exposure (an irradiance estimate), limited to the
irradiance range *both* frames of a pair measure (so clipping and darkness look the same
in both), in log units (:func:`log_irradiance`).  Registration engages whenever the pair
shares :data:`MIN_TEXTURED` textured pixels, however small a fraction of the frame that
is (in an HDR pair the shared band is narrow).  Phase correlation (OpenCV) finds the
translation on area-averaged images at most :data:`PHASE_SIDE` wide; the enhanced
correlation coefficient maximisation (Evangelidis and Psarakis 2008,
``cv2.findTransformECC``, invariant to gain and offset) refines it on a pyramid down to a
central full-resolution window, and for ``similarity`` adds a rotation (ECC's Euclidean
model), kept only where it beats the translation.

A warp is a ``(2, 3)`` affine matrix ``W`` mapping reference-frame coordinates ``(x, y)``
(pixel centres, x to the right) to the frame's own coordinates: the frame is brought onto
the reference by sampling it at ``W @ (x, y, 1)``.  ``translation`` has ``W = [I | t]``;
``similarity`` a rotation ``[[cos, -sin], [sin, cos]]`` (scale 1: exposure brackets do not
zoom) and a translation.
"""
from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError

#: longest side of the coarse registration level
COARSE_SIDE = 1024
#: how far (in pixels of the pyramid's finest level) the full-resolution similarity ECC
#: may move the window's corners from the pyramid's estimate (:func:`_fine_ecc`)
FINE_REACH = 4
#: longest side of the phase correlation's images: only ECC's start (within
#: :data:`MAX_REFINE_PX`), so half the coarse level suffices.  1024 -> 512: 8-bit
#: alignment 10-25 % faster on the motion benchmark, every warp within 0.01 px
PHASE_SIDE = 512
#: side of the full-resolution refinement window
FINE_SIDE = 1024
#: longest side of the coarsest ECC pyramid level (at least)
PYRAMID_MIN = 64
MOTIONS = ("translation", "similarity")
#: registration needs this many textured pixels off the plateaus in both frames
MIN_TEXTURED = 400
#: registration images narrower than this (pixels) are not registered: the texture test's
#: 3 x 3 smoothing and gradient need an interior, and ECC's pyramid a few levels
MIN_SIDE = 8
#: ... and this many of them textured across each axis (:func:`texture`; a quarter: the
#: motion benchmark's darkest short frame has 314 of 400+)
MIN_ACROSS = 100
#: log-irradiance gradient per pixel (about 10 % contrast) that counts as texture
TEXTURE_LOG_GRAD = 0.1
#: largest correction (pixels) ECC may make to the phase-correlation translation
MAX_REFINE_PX = 3.0
#: a rotation is kept when it moves some corner of the frame by more than this (pixels)
ROTATION_PX = 0.25


def _cv2():
    import cv2

    return cv2


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
    through a response, whose 16 codes are far darker than that (16-bit through gamma 2.2:
    2e-8), in the sensor's noise -- a static simulated bracket of 16-bit TIFFs 5.4 EV apart
    registered 0.55 px off there, against 0.04 px for each frame on the truth."""
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


def matched(reference: np.ndarray, image: np.ndarray, warp: np.ndarray) -> tuple[np.ndarray, float]:
    """Pixels of the reference that ``image`` (brought onto it by ``warp``) matches to
    :data:`MATCH_TOL` (plateaus included), and the fraction matched among the pixels the
    warped image covers off the plateaus.  Moving objects and misregistered texture are
    the unmatched ones."""
    cv2 = _cv2()
    h, w = reference.shape
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    moved = cv2.warpAffine(image, warp.astype(np.float32), (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=np.nan)
    lo, hi = float(reference.min()), float(reference.max())
    # pixels on the clipping plateaus of the common range match trivially: they do not vote
    inside = np.isfinite(moved) & (reference > lo + 1e-4) & (reference < hi - 1e-4)
    ok = inside & (np.abs(np.where(inside, moved, 0) - reference) < MATCH_TOL)
    return ok | ~inside, float(ok.sum() / max(inside.sum(), 1))


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


def texture(img: np.ndarray, grad: float = TEXTURE_LOG_GRAD) -> tuple[int, int]:
    """``(textured, across)``: how many pixels off the plateaus carry texture, a
    log-irradiance gradient (3 x 3 box-smoothed, so single-pixel noise does not count) above
    ``grad`` per pixel; and the fewer of those whose gradient's x component, and
    those whose y component, is above ``grad`` / sqrt 2 -- edges in one
    direction only fix no shift along them (the aperture problem: a burst of vertical bands
    registered 1-3 px off vertically, and that was applied)."""
    cv2 = _cv2()
    f = max(1, -(-max(img.shape) // COARSE_SIDE))
    small = block_mean(img, f)
    smooth = cv2.blur(small, (3, 3))
    inside = off_plateau(small) > 0
    gy, gx = np.gradient(smooth)
    limit = grad * f  # per full-resolution pixel
    textured = int(np.count_nonzero((np.hypot(gx, gy) > limit) & inside))
    across = min(int(np.count_nonzero((np.abs(g) > limit / np.sqrt(2)) & inside)) for g in (gx, gy))
    return textured * f * f, across * f * f


def registrable(a: np.ndarray, b: np.ndarray) -> str | None:
    """Why two exposure-invariant images cannot be registered, or None: each needs
    :data:`MIN_TEXTURED` textured pixels and :data:`MIN_ACROSS` textured across each axis
    (:func:`texture`), so an image of fewer than :data:`MIN_TEXTURED` pixels, or narrower
    than :data:`MIN_SIDE`, never is."""
    if min(a.shape) < MIN_SIDE or a.size < MIN_TEXTURED:
        return f"a {a.shape[0]} x {a.shape[1]} registration image is too small to register"
    (ta, xa), (tb, xb) = texture(a), texture(b)
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
    than :data:`FINE_REACH` pixels of the pyramid's finest level: a refinement does not
    jump, a false optimum does (a moving object filling half the window of a 6 MP frame
    took it 82 px and 3.6 degrees off; parallax in the hand-held iphone6_window_jpg moves it
    up to 8.4 px from the 4 x 4 level's estimate).  At most :data:`FINE_ITERATIONS`
    iterations, and None if the run has not settled by then; a similarity run is checked
    after :data:`FINE_CHECK` iterations too (one wandering 5-19 px per iteration on the
    benchmark's 6 MP render, yet within its reach, ran all 30 before being refused)."""
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


#: iterations of :func:`_fine_ecc`: from the pyramid's estimate it converges in 8-15 (the
#: warps of the motion benchmark's 32 cases and of the real brackets are the same with 15 as
#: with 100); a run drifting to a false optimum stops here (it ran all 100 before the reach
#: refused it: 2 of the 3.2 s of aligning the benchmark's 6 MP render)
FINE_ITERATIONS = 30
#: a fine run has settled when one more iteration moves no window corner farther (pixels):
#: after 30 iterations the benchmark's runs move 0.00-0.14 px, the drifting ones 4-7 px
FINE_SETTLED_PX = 0.5
#: a similarity run is checked after this many iterations too: refused if it moved a corner
#: beyond :data:`FINE_REACH` or its last iteration moved one by more than :data:`FINE_WANDER_PX`
FINE_CHECK = 10
FINE_WANDER_PX = 2.0
#: ... and taken as converged if that iteration moved no corner by this much (pixels)
FINE_CONVERGED_PX = 0.01


#: a registered pair's log difference farther than this many robust deviations (1.4826 MAD)
#: from its median is a moving object's (:func:`_moved_region`)
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
    dark short frame's few textured tiles do not (the motion benchmark's case 13: a ghost
    in the reference pulled ECC 0.22 px off, with 2 of 3 tiles registering)."""
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
    f = max(1, -(-max(h, w) // PHASE_SIDE))
    ref_c, img_c = block_mean(reference, f), block_mean(image, f)
    candidates = [np.hstack([np.eye(2), np.zeros((2, 1))]), _phase_shift(ref_c, img_c)]
    return rescale_warp(max(candidates, key=lambda c: matched(ref_c, img_c, c)[1]), f, (f - 1) / 2)


#: tiles per side of the robust consensus (:func:`_tile_consensus`)
CONSENSUS_TILES = 5
#: a tile's correction farther than this (pixels) from the consensus is an outlier (motion)
CONSENSUS_TOL_PX = 0.25
#: textured pixels a tile needs to take part: log-irradiance gradient above
#: :data:`TEXTURE_LOG_GRAD` per 1/:data:`COARSE_SIDE` of the frame's longer side (per pixel
#: up to that size).  The same scene has less contrast per pixel on a sensor with more
#: pixels: counted per pixel, `iphone6_window_jpg`'s 8 MP frames had 1-2 textured tiles of 25
#: and the motion benchmark's 6 MP render 0-3, so no tile checked ECC there (a ghost pulled
#: it 1.5 px off; now 0.011 px; the phone bracket's leave-one-out 12.93 -> 12.66)
CONSENSUS_MIN_TEXTURED = 200
#: tiles that must register for their disagreement to mean a non-rigid scene (a third of
#: them; with 4 of a 25, one moving object made a rotation of 0.8 degrees be refused)
CONSENSUS_JUDGE = 8
#: a tile is registered on its central window at most this many pixels on a side (at 24 MP
#: the 25 whole tiles would be the whole frame at full resolution)
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
    """A correction of ``warp`` that a moving object cannot bias: ``image`` resampled onto
    ``reference`` by ``warp`` (bicubic), each of :data:`CONSENSUS_TILES` x
    :data:`CONSENSUS_TILES` tiles registered on its own (ECC translation, from no motion, on
    its central window of at most :data:`CONSENSUS_TILE_SIDE` pixels a side),
    and the tile centres' displacements fitted robustly: the median for ``translation``,
    OpenCV's least-median-of-squares similarity (``cv2.estimateAffinePartial2D``, LMEDS) for
    ``similarity``; tiles farther than :data:`CONSENSUS_TOL_PX` from the fit are outliers
    and the fit is redone on the rest, without scale (:func:`_euclidean_fit`; its rotation
    kept where ``warp`` rotates already or it moves a corner by more than
    :data:`ROTATION_PX` beyond the inliers' mean shift).  Whole-image ECC weighs every pixel, so an object
    that moved between the frames (a ghost) pulls it by tenths of a pixel and a rotation by
    hundredths of a degree; here its tiles are outvoted.  Returns ``(warp, judged)``: the
    corrected warp, or None unless at least 4 tiles are textured
    (:data:`CONSENSUS_MIN_TEXTURED`), registered within :data:`MAX_REFINE_PX`, and at least
    half of them (and 4) agree; ``judged``: whether the tiles' verdict stands -- True with a
    warp, and with None when :data:`CONSENSUS_JUDGE` tiles registered but disagree (no rigid
    motion describes the scene, e.g. foliage in wind; fewer may disagree through one moving
    object)."""
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


def estimate_warp(reference: np.ndarray, image: np.ndarray, motion: str = "translation") -> tuple[np.ndarray, float]:
    """The warp bringing ``image`` onto ``reference`` (both ``(H, W)`` float32 exposure-
    invariant images, see :func:`log_irradiance`) and its confidence, the enhanced
    correlation coefficient of the registered pair off the plateaus (1 = identical up to
    gain and offset; :func:`ecc_score`).

    A coarse translation (:func:`_translation`: phase correlation against no motion, by the
    vote of the pixels) starts ECC (Evangelidis and Psarakis 2008, ``cv2.findTransformECC``)
    on a pyramid of area-averaged levels (:func:`_pyramid_ecc`) and then at full resolution
    on the central window (:func:`_fine_ecc`): every textured pixel of the band an HDR pair
    shares counts, however small a fraction of the frame it is.  ECC's result stands unless
    it wandered more than :data:`MAX_REFINE_PX` from the phase correlation's.
    ``similarity`` then adds a rotation (ECC's Euclidean model, from the translation, on the
    pyramid: what it changes must be mostly a rotation, the frame's centre moved by at most
    :data:`MAX_REFINE_PX` or half what the corners move -- with a frame's label 1 EV off,
    the pyramid drifted 31 px and the correlation, 0.978 against 0.976, accepted it; true
    rotations of the motion benchmark move the centre 1.4-3.0 px and the corners 5-9 px;
    refined only where it moves some corner of the frame by more than
    :data:`ROTATION_PX`: by the tile consensus over the whole frame, else at full resolution
    on the central window) and keeps it only if it correlates better and still moves a
    corner that far (a negligible rotation is not worth resampling for), and never where
    the tiles registered but agree on no rigid motion: a non-rigid scene, where ECC's extra
    parameter always correlates a little better (``ex2f_trees_jpg``, trees in wind: a
    0.22 degree rotation that raised the leave-one-out error of 4 of its 6 frames; refused,
    5 of 6 gained on no alignment).  Last, the tile
    consensus (:func:`_tile_consensus`) corrects what a moving object pulled, where enough
    tiles are textured; once more after it refined a rotation (on the motion benchmark's
    32 cases against the full-resolution refinement: median shift error 0.032 -> 0.023 px,
    alignment 11 % faster; one consensus pass alone left case 12 0.20 px off, two 0.18).
    Where too few tiles register for a consensus (a dark short frame: its texture is
    scarce), the region a moving object covers, if any, is left out of a last ECC run
    instead (:func:`_masked_fine_ecc`; the motion benchmark's case 13 0.217 -> 0.020 px, and
    the leave-one-out error of ``eos350d_lamps_night_jpg``'s darkest frames 7.71 -> 6.84
    and 6.21 -> 6.02).
    Where the pyramid's rotation turns the full-resolution window's corners by more than
    :data:`FINE_SETTLED_PX` about its centre, the rotation is refined first, and the
    translation at full resolution only if the rotation is not kept: a translation cannot
    fit such a window (on the benchmark's 32 cases the same warps within 0.003 px, and
    alignment 19 % faster).
    Returns ``((2, 3), rho)``."""
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
    # translation fits that window no better than the pyramid (on the benchmark's 6 MP render it
    # wandered 0.6-1.8 px per iteration for 30 iterations, and was refused), and is refined only
    # if the rotation is not kept
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
    return best, rho


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


def corner_distance(a: np.ndarray, b: np.ndarray, height: int, width: int) -> float:
    """Largest distance (pixels) between where two warps take a corner of the frame."""
    corners = np.array([[0, 0, 1], [width - 1, 0, 1], [0, height - 1, 1], [width - 1, height - 1, 1]], np.float64)
    return float(np.max(np.hypot(*(corners @ a.T - corners @ b.T).T)))


def warp_size(warp: np.ndarray, height: int, width: int) -> float:
    """Largest displacement (pixels) the warp causes anywhere in the frame."""
    return corner_distance(warp, np.hstack([np.eye(2), np.zeros((2, 1))]), height, width)


def apply_warp(codes: np.ndarray, warp: np.ndarray, clip_code: int) -> np.ndarray:
    """Resample ``(H, W)`` or ``(H, W, C)`` code values onto the reference (bilinear,
    rounded to codes; bicubic measured worse on mosaic colour sites).  A result touched by
    a clipped code (``>= clip_code``) is clipped; samples from outside the frame repeat its
    nearest edge (a dark or clipped stand-in would turn the border into a no-data
    fallback)."""
    cv2 = _cv2()
    h, w = codes.shape[:2]
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    m = np.asarray(warp, np.float32)
    # OpenCV interpolates 8/16-bit codes in fixed point and rounds: no float copy of the frame
    out = cv2.warpAffine(np.ascontiguousarray(codes), m, (w, h), flags=flags,
                         borderMode=cv2.BORDER_REPLICATE).reshape(codes.shape)
    clipped = codes >= clip_code
    if clipped.any():  # a short frame often has none: no second warp
        spread = cv2.warpAffine(clipped.view(np.uint8) * np.uint8(255), m, (w, h), flags=flags,
                                borderMode=cv2.BORDER_REPLICATE)  # 255: any share of a clipped code survives
        out[spread.reshape(codes.shape) > 0] = clip_code
    return out


def covered_mask(warp: np.ndarray, height: int, width: int) -> np.ndarray:
    """Which reference pixels ``(x, y)`` the warp takes inside the frame (``W @ (x, y, 1)``
    within half a pixel of its edge), ``(height, width)`` bool.  The set is convex: each
    row's pixels inside form one interval, found from the four edge inequalities."""
    y = np.arange(height, dtype=np.float64)
    lo, hi = np.full(height, -np.inf), np.full(height, np.inf)
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
    out = np.zeros((height, width), bool)
    for i in np.flatnonzero(last > first):  # row by row: 7x faster at 24 MP than a comparison per pixel
        out[i, first[i]:last[i]] = True
    return out


def _same_colour_index(n: int, shift: int) -> np.ndarray:
    """Source rows (or columns) ``i + shift`` (``shift`` even), those beyond the frame
    replaced by the nearest in-frame one of the same CFA parity."""
    src = np.arange(n) + shift
    low, high = src < 0, src > n - 1
    src[low] = src[low] % 2
    src[high] = (n - 1) - ((n - 1 - src[high]) % 2)
    return src


def shift_mosaic(codes: np.ndarray, warp: np.ndarray) -> np.ndarray:
    """Bring a Bayer mosaic ``(H, W)`` onto the reference by whole 2 x 2 CFA periods: its
    translation rounded to even pixels, no resampling, no colours mixed (otherwise see
    :func:`resample_mosaic`).  Sites from outside the frame repeat the nearest same-colour
    edge site."""
    tx, ty = (2 * np.rint(warp[:, 2] / 2)).astype(int)
    return codes[np.ix_(_same_colour_index(codes.shape[0], ty), _same_colour_index(codes.shape[1], tx))]


def _site_warp(warp: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """The warp of the sub-plane of CFA site ``(dy, dx)`` (its samples ``(2u + dx, 2v + dy)``)."""
    a, d = warp[:, :2], np.array([dx, dy], np.float64)
    return np.hstack([a, ((a @ d + warp[:, 2] - d) / 2)[:, None]])


#: the colour correction of :func:`resample_mosaic` is regularised by this fraction of the
#: full-scale signal: where green is not well above it (noise), red and blue keep their plain
#: bilinear estimate
COLOUR_RATIO_FLOOR = 0.002


def resample_mosaic(codes: np.ndarray, warp: np.ndarray, clip_code: int, cfa: str = "RGGB",
                    black=0.0, spread: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Resample a Bayer mosaic ``(H, W)`` (codes) onto the reference, colour by colour, using
    green's denser lattice:

    - green on its quincunx (pitch sqrt 2, not the 2 of a same-colour sub-plane): its value
      at the red and blue sites filled by the mean of their four green neighbours, that
      full-resolution green image warped (bicubic) and read at the output's green sites;
    - red and blue: each sub-plane warped (bilinear), times ``(G + c) / (G_taps + c)``, the
      warped green at the output site over green interpolated from the same taps' sites:
      the colour ratio is what is interpolated (Cok 1987's smooth-hue transition), so detail
      that green resolves is not blurred to the sub-plane's pitch.  ``c`` =
      :data:`COLOUR_RATIO_FLOOR` of full scale keeps noise out where green is dark (the
      factor tends to 1 there).

    Values are signals above ``black`` (one value or one per site of the 2 x 2 cell).  Its
    RMS error is 0.5-0.7x that of resampling every sub-plane on its own on detail of 0.1-0.3
    cycles per pixel (``tests/test_motion.py``); on the RAW cases of ``benchmarks.motion`` the
    merge away from the ghost gained 0.5 dB on average (-0.5 to +2.4).  Green is warped by
    OpenCV's bicubic (the full-resolution green image is not aliased the way a sub-plane is).

    Clipping: a clipped code bounds its sample from below, so it is interpolated at that
    floor, the clipping level; an output is clipped only where most of its taps' weight is
    clipped.  (Any clipped tap clipping the output lost the ring of every highlight, where
    only the resampled short frame measures.  Leaving clipped taps out and renormalising
    the others read that ring far too dark -- the left-out tap is the brightest: on
    ``benchmarks.motion``'s case 2 a red lamp's ring came out at half its level; the floor
    gained 2.0 dB there, 0.5 dB on case 18, and lost nothing on the other RAW cases.)  A red
    or blue output whose correction would touch clipped green keeps its plain estimate;
    outputs are capped one code below ``clip_code``.  Samples from outside the frame repeat
    its nearest edge.

    Bands of :data:`BAND_ROWS` output rows are resampled two at a time (both cores), each
    from the source rows its warp reaches plus :data:`BAND_MARGIN` (the fills', cubic's and
    the dilation's reach): two bands' temporaries, not a frame's (a 24 MP frame: 1.0 GB
    above its codes whole).  A 24 MP frame took 0.59-0.87 s in 256-row bands one at a
    time, 0.45-0.58 s in 128-row bands two at a time, at the same peak memory (OpenCV
    places a warp's samples on a 1/32-pixel grid from each band's origin: codes differ by
    one in 4e-5 of the samples).

    With ``spread``, also the taps' spread of every output (:func:`tap_variance` of what it
    is interpolated from, made from the same band's images): red and blue on their own
    sub-plane (taps 2 px apart); green on the full-resolution green image it is resampled
    from (taps 1 px apart: the sub-plane's spread overstates green's interpolation error),
    as :func:`spread_code` codes: returns ``(codes, spread codes)``."""
    out = np.empty_like(codes)
    coded = np.empty(codes.shape, np.uint16) if spread else None

    def one(item):
        r0, r1, source, band = item
        out[r0:r1], u = _resample_band(source, band, clip_code, cfa, black, r1 - r0, spread)
        if spread:
            coded[r0:r1] = spread_code(u)

    with ThreadPoolExecutor(2) as pool:
        list(pool.map(one, _bands(codes, warp)))
    return (out, coded) if spread else out


def _bands(codes: np.ndarray, warp: np.ndarray):
    """``(r0, r1, source rows, band warp)`` for each band of :data:`BAND_ROWS` output rows
    ``r0:r1`` of a mosaic warped by ``warp``: the source rows its warp reaches plus
    :data:`BAND_MARGIN` (whole CFA periods), and the warp from the band's output rows to
    them."""
    h, w = codes.shape
    for r0 in range(0, h, BAND_ROWS):
        r1 = min(h, r0 + BAND_ROWS)
        ys = [warp[1, 0] * x + warp[1, 1] * y + warp[1, 2] for x in (0, w - 1) for y in (r0, r1 - 1)]
        s0 = max(0, min(int(np.floor(min(ys))) - BAND_MARGIN, h - 2)) // 2 * 2  # whole CFA periods
        s1 = min(h, max(int(np.ceil(max(ys))) + BAND_MARGIN + 1, s0 + 2))
        band = np.asarray(warp, np.float64).copy()
        band[:, 2] += band[:, 1] * r0  # output rows from r0, source rows from s0
        band[1, 2] -= s0
        yield r0, r1, codes[s0:s1], band


#: the mean of a site's four edge neighbours (green's at a red or blue site of a Bayer mosaic)
_MEAN4 = np.array([[0, 0.25, 0], [0.25, 0, 0.25], [0, 0.25, 0]], np.float32)
#: output rows per band of :func:`resample_mosaic` (even: whole CFA periods)
BAND_ROWS = 128
#: source rows beyond a band's reach that it also reads
BAND_MARGIN = 16


def _resample_band(codes: np.ndarray, warp: np.ndarray, clip_code: int, cfa: str, black, out_rows: int,
                   spread: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`resample_mosaic` of ``out_rows`` output rows from the source rows ``codes``
    (``warp``: output to source coordinates of this band), and with ``spread`` their taps'
    spread (float32; else None)."""
    cv2 = _cv2()
    w = codes.shape[1]

    def warped(a, m, rows, interpolation=cv2.INTER_LINEAR):
        return cv2.warpAffine(np.ascontiguousarray(a), np.asarray(m, np.float32), (a.shape[1], rows),
                              flags=interpolation | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)

    def lost(usable, m, rows):  # where most of the taps' weight is clipped
        return warped(usable, m, rows) < 0.5

    black = np.broadcast_to(np.asarray(black, np.float32).reshape(-1), (4,)).reshape(2, 2)
    sites = [(dy, dx) for dy in (0, 1) for dx in (0, 1)]
    green = {(dy, dx): cfa[2 * dy + dx] == "G" for dy, dx in sites}
    # a band without a clipped code (most of a frame but its highlights) needs none of the
    # clipping's bookkeeping (24 MP: 0.59 -> 0.23 s for a frame with little clipping, 0.79 ->
    # 0.70 s with 3.8 % clipped; the same output)
    clipped = bool((codes >= clip_code).any())
    usable = (codes < clip_code).astype(np.float32) if clipped else None
    signal = _above_black(codes, black)  # a clipped code stays at its floor, the clipping level
    full_g = _green_image(signal, cfa)
    g_out = warped(full_g, warp, out_rows, cv2.INTER_CUBIC)
    g_lost = near_g = None
    if clipped:
        n4 = cv2.filter2D(usable, -1, _MEAN4, borderType=cv2.BORDER_REFLECT_101)
        g_ok = usable.copy()
        for dy, dx in sites:
            if not green[dy, dx]:
                g_ok[dy::2, dx::2] = n4[dy::2, dx::2] > 0.3
        g_lost = lost(g_ok, warp, out_rows)
        # clipped green within reach of a red or blue output's correction (cubic: 2 px, plus the fills)
        near_g = warped(cv2.dilate(((g_ok == 0) * 255).astype(np.uint8), np.ones((7, 7), np.uint8)), warp, out_rows) > 0
    c = np.float32(COLOUR_RATIO_FLOOR * (clip_code - float(black.mean())))
    out = np.empty((out_rows, w), np.float32)
    clip_out = np.zeros((out_rows, w), bool)
    u = np.empty((out_rows, w), np.float32) if spread else None
    g_spread = tap_variance(full_g, warp, out_rows) if spread else None  # green's taps 1 px apart
    for dy, dx in sites:
        if green[dy, dx]:
            out[dy::2, dx::2] = g_out[dy::2, dx::2]
            if clipped:
                clip_out[dy::2, dx::2] = g_lost[dy::2, dx::2]
            if spread:
                u[dy::2, dx::2] = g_spread[dy::2, dx::2]
            continue
        m, rows = _site_warp(warp, dx, dy), (out_rows - dy + 1) // 2
        plain = warped(signal[dy::2, dx::2], m, rows)
        if spread:  # the sub-plane's taps, around the plain bilinear estimate
            u[dy::2, dx::2] = tap_variance(signal[dy::2, dx::2], m, rows, mean=plain)
        g_taps = warped(full_g[dy::2, dx::2], m, rows)
        ratio = (np.maximum(g_out[dy::2, dx::2], 0) + c) / (np.maximum(g_taps, 0) + c)
        if clipped:
            out[dy::2, dx::2] = np.where(near_g[dy::2, dx::2], plain, plain * ratio)
            clip_out[dy::2, dx::2] = lost(usable[dy::2, dx::2], m, rows)
        else:
            out[dy::2, dx::2] = plain * ratio
    for dy, dx in sites:
        out[dy::2, dx::2] += black[dy, dx]
    np.rint(out, out=out)
    np.clip(out, 0, clip_code - 1, out=out)
    if clipped:
        out[clip_out] = clip_code
    return out.astype(codes.dtype), u


def tap_variance(codes: np.ndarray, warp: np.ndarray, out_rows: int | None = None,
                 mean: np.ndarray | None = None) -> np.ndarray:
    """The spread of the source samples bilinear resampling (:func:`apply_warp`) mixes into
    each output sample, float32 in squared codes, shape of ``codes`` (``out_rows`` rows if
    given: the warp's output rows read from these source rows; ``mean``: the bilinear
    resampling itself, float32, when the caller has it): ``sum_i w_i z_i^2 -
    (sum_i w_i z_i)^2`` over the (up to 4) taps ``z_i`` with their bilinear weights ``w_i``
    (two float warps).  It is the variance of the interpolated value if the true one were
    any of the taps, in proportion to their weights: 0 where the warp lands on a sample or
    the neighbourhood is flat, the squared contrast across an edge the warp falls inside.
    The merge adds it to a resampled sample's variance (:func:`hdrmerge_cli.pipeline.motion.sample_weights`),
    so that where resampling cannot reproduce the scene (sharp edges, detail finer than the
    sample pitch, e.g. a CFA colour's sub-plane) the frames that were not resampled decide.
    float32 round-off of ``z^2`` is ``6e-8 z^2``, far below the noise of a reading ``z``."""
    cv2 = _cv2()
    h, w = codes.shape[:2]
    rows = h if out_rows is None else out_rows
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    m = np.asarray(warp, np.float32)
    z = np.ascontiguousarray(codes, np.float32)
    if mean is None:
        mean = cv2.warpAffine(z, m, (w, rows), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    second = cv2.warpAffine(z * z, m, (w, rows), flags=flags, borderMode=cv2.BORDER_REPLICATE)  # z may be codes
    second -= mean * mean
    return np.maximum(second, 0.0, out=second).reshape((rows,) + codes.shape[1:])


def resampled_weight_mosaic(w: np.ndarray | None, codes: np.ndarray, pattern: np.ndarray | None, slope: np.ndarray,
                            certainty: np.ndarray, n_codes: int, spread: np.ndarray, warp: np.ndarray,
                            out: np.ndarray | None = None, weight: np.ndarray | None = None,
                            cfa: str | None = None) -> np.ndarray:
    """Inverse-variance weights of the samples of a mosaic resampled by ``warp``
    (:func:`resample_mosaic`), the variance of a resampled reading in the weights of (7):
    a table weight ``w = c / v`` (``c`` the weighting function ``w(z)``, ``v`` the variance
    of the sample's value) becomes ``c / (e v + max(u - (1 - e) v, 0))``, ``u`` the taps'
    spread ``spread`` (:func:`resample_mosaic`'s, squared codes) times the squared slope
    of the value table at the sample's code, ``e`` the interpolation's ``sum w_i^2``: for
    bilinear taps on a colour's sub-plane ``(fx^2 + (1 - fx)^2) (fy^2 + (1 - fy)^2)``, ``(fx,
    fy)`` the sample's fractional position there (1 on a tap, 1/4 midway between four).
    Interpolating between taps with independent noise averages it (``e v``, (17)'s noise
    through the interpolation), and the spread holds ``(1 - e) v`` of that noise on
    average, which is not interpolation error.  Green, read on its filled full-resolution
    image, has correlated taps: there ``e v + max(u - (s - e) v, 0)`` with ``e`` and ``s``
    from the taps' covariance (:func:`_filled_green_noise`).
    ``w``, ``codes``, ``spread``: ``(H, W)`` (``out`` may be ``w``; ``spread`` as
    :func:`spread_code` codes, or float32, then coded first); ``w`` None: the
    table ``weight`` at each code.  ``slope``, ``certainty``, ``weight``: flattened
    ``(C * n_codes,)`` tables, the row of a sample from ``pattern`` (``(ph, pw)`` table
    rows tiled over the mosaic; None: row 0).  One pass, no temporaries (numba): before,
    numpy in bands took 0.4 s per 24 MP frame and pass."""
    sites = np.array([[_site_warp(warp, dx, dy) for dx in (0, 1)] for dy in (0, 1)], np.float64)
    rows = np.zeros((1, 1), np.intp) if pattern is None else np.asarray(pattern, np.intp)
    green = np.zeros((2, 2), np.bool_) if cfa is None else np.array([[c == "G" for c in cfa[:2]], [c == "G" for c in cfa[2:4]]])
    if out is None:
        out = np.empty(codes.shape, np.float32)
    table = w is None
    _resampled_weight_rows(np.empty((1, 1), np.float32) if table else w,
                           np.asarray(weight if table else np.empty(1), np.float32), table, codes, rows,
                           np.asarray(slope, np.float32), np.asarray(certainty, np.float32), n_codes,
                           spread if spread.dtype == np.uint16 else spread_code(spread), _spread_table(), sites,
                           np.asarray(warp, np.float64), green, out)
    return out


#: :func:`spread_code`'s scale (squared codes) and steps per octave: ``2^32`` (a 16-bit
#: range squared) takes code 65520
SPREAD_FLOOR = 2.0**-8
SPREAD_STEPS = 1638


def spread_code(u: np.ndarray) -> np.ndarray:
    """Resampling spreads ``u`` (:func:`resample_mosaic`'s, squared codes, ``(H, W)``
    float32) as uint16 codes ``round(SPREAD_STEPS log2(1 + u / SPREAD_FLOOR))``, up to ``u
    = 2^32`` (a 16-bit range squared); ``u + SPREAD_FLOOR`` within 2.2e-4 (half a step).
    :func:`spread_value` inverts it.  The spread of a moved frame is kept for every pass of
    the merge: in half the memory of float32 (24 MP: 48 MB less per moved frame, held at
    the merge's peak)."""
    out = np.empty(u.shape, np.uint16)
    _spread_code_rows(np.ascontiguousarray(u, np.float32).reshape(u.shape[0], -1), out.reshape(u.shape[0], -1),
                      np.float32(1.0 / SPREAD_FLOOR), np.float32(SPREAD_STEPS))
    return out


@numba.njit(parallel=True, nogil=True, cache=True)
def _spread_code_rows(u, out, inv_floor, steps):  # pragma: no cover - compiled
    for r in numba.prange(u.shape[0]):
        for c in range(u.shape[1]):
            v = np.log2(np.float32(1.0) + max(u[r, c], np.float32(0.0)) * inv_floor) * steps + np.float32(0.5)
            out[r, c] = min(int(v), 65535)


@functools.cache
def _spread_table() -> np.ndarray:
    """The spread (squared codes, float32) of each :func:`spread_code` code, ``(65536,)``."""
    return (SPREAD_FLOOR * (np.exp2(np.arange(65536) / SPREAD_STEPS) - 1.0)).astype(np.float32)


def spread_value(code: np.ndarray) -> np.ndarray:
    """The spreads (squared codes, float32) that :func:`spread_code` codes stand for."""
    return _spread_table()[code]


@numba.njit(inline="always")
def _filled_green_noise(fx, fy, on_green):  # pragma: no cover - compiled
    """``(e, s)`` of bilinear taps 1 px apart on the filled green image, in units of a
    green reading's noise variance: ``e = w' C w`` the interpolated value's, ``s = sum
    w_i C_ii`` the taps' mean; ``C``: real greens 1 and independent, a filled site (the
    mean of four greens) 1/4, its covariance with each real tap 1/4 (both real taps are
    among its four), between the two filled taps 1/8 (two greens shared).  ``on_green``:
    the top-left tap is a real green (then the bottom-right too)."""
    w00, w11 = (1 - fx) * (1 - fy), fx * fy
    w10, w01 = fx * (1 - fy), (1 - fx) * fy
    if on_green:
        a, b, p, q = w00, w11, w10, w01
    else:
        a, b, p, q = w10, w01, w00, w11
    e = a * a + b * b + 0.25 * (p * p + q * q) + 0.5 * (a + b) * (p + q) + 0.25 * p * q
    s = a + b + 0.25 * (p + q)
    return e, s


@numba.njit(parallel=True, nogil=True, cache=True)
def _resampled_weight_rows(w, weight, table, codes, rows, slope, certainty, n_codes, spread, spread_of, sites, warp,
                           green, out):  # pragma: no cover - compiled
    h, width = codes.shape
    ph, pw = rows.shape
    zero = np.float32(0.0)
    for r in numba.prange(h):
        dy, v = r & 1, r >> 1
        for col in range(width):
            dx, u = col & 1, col >> 1
            if green[dy, dx]:  # read on the filled full-resolution green image
                x = warp[0, 0] * col + warp[0, 1] * r + warp[0, 2]
                y = warp[1, 0] * col + warp[1, 1] * r + warp[1, 2]
                x0, y0 = np.floor(x), np.floor(y)
                e, s = _filled_green_noise(x - x0, y - y0, green[int(y0) & 1, int(x0) & 1])
            else:
                fx = sites[dy, dx, 0, 0] * u + sites[dy, dx, 0, 1] * v + sites[dy, dx, 0, 2]
                fy = sites[dy, dx, 1, 0] * u + sites[dy, dx, 1, 1] * v + sites[dy, dx, 1, 2]
                fx -= np.floor(fx)
                fy -= np.floor(fy)
                e, s = (fx * fx + (1 - fx) ** 2) * (fy * fy + (1 - fy) ** 2), 1.0
            e32, s32 = np.float32(e), np.float32(s)
            i = rows[r % ph, col % pw] * n_codes + min(codes[r, col], n_codes - 1)
            g = slope[i]
            spread_u = g * g * spread_of[spread[r, col]]
            c = certainty[i]
            wr = weight[i] if table else w[r, col]
            den = e32 * c + max(wr * spread_u - (s32 - e32) * c, zero)
            out[r, col] = wr * c / den if den > 0 else zero


def _above_black(codes: np.ndarray, black) -> np.ndarray:
    """A mosaic's codes minus ``black`` (one value or one per site of the 2 x 2 cell), float32."""
    black = np.broadcast_to(np.asarray(black, np.float32).reshape(-1), (4,)).reshape(2, 2)
    signal = codes.astype(np.float32)
    for dy in (0, 1):
        for dx in (0, 1):
            signal[dy::2, dx::2] -= black[dy, dx]
    return signal


def _green_image(signal: np.ndarray, cfa: str) -> np.ndarray:
    """Green at every site of a mosaic's ``signal`` (float32, a new array): green sites as
    read, red and blue sites the mean of their four green neighbours (green's quincunx
    filled, as :func:`resample_mosaic` reads it)."""
    cv2 = _cv2()
    mean4 = cv2.filter2D(signal, -1, _MEAN4, borderType=cv2.BORDER_REFLECT_101)
    full_g = signal.copy()
    for dy in (0, 1):
        for dx in (0, 1):
            if cfa[2 * dy + dx] != "G":
                full_g[dy::2, dx::2] = mean4[dy::2, dx::2]
    return full_g
