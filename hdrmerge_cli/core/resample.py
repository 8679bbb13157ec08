"""Resampling frames onto the reference by a warp (array code): images bilinearly, Bayer
mosaics by whole CFA periods or colour by colour, and the variance resampling adds.

A warp is a ``(2, 3)`` affine matrix mapping reference-frame coordinates to the frame's
own (:mod:`hdrmerge_cli.core.registration`).  A resampled sample mixes up to four taps; its
variance in the merge is the interpolated noise plus the taps' spread
(:func:`tap_variance`, :func:`resampled_weight_mosaic`), so that where resampling cannot
reproduce the scene the frames that were not resampled decide.
"""
from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from hdrmerge_cli.core.jit import njit, prange


def _cv2():
    """OpenCV, imported when first used (here and in :mod:`hdrmerge_cli.core.registration`)."""
    import cv2

    return cv2


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


def inner_rectangle(mask: np.ndarray, even: bool = False) -> tuple[int, int, int, int] | None:
    """An axis-aligned rectangle inside a convex ``mask`` ``(H, W)`` bool (the pixels every
    frame covers): from the mask's bounding box, the side whose edge holds the most pixels
    outside moves in by one until none does.  ``(r0, r1, c0, c1)``, half-open; ``even``:
    even offsets and sizes (a CFA mosaic keeps its phase).  None when nothing is inside."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not rows.size:
        return None
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    while r0 < r1 and c0 < c1:
        outside = [np.count_nonzero(~mask[r0, c0:c1]), np.count_nonzero(~mask[r1 - 1, c0:c1]),
                   np.count_nonzero(~mask[r0:r1, c0]), np.count_nonzero(~mask[r0:r1, c1 - 1])]
        side = int(np.argmax(outside))
        if outside[side] == 0:
            break
        if side == 0:
            r0 += 1
        elif side == 1:
            r1 -= 1
        elif side == 2:
            c0 += 1
        else:
            c1 -= 1
    if even:
        r0, c0 = r0 + r0 % 2, c0 + c0 % 2
        r1, c1 = r0 + (r1 - r0) // 2 * 2, c0 + (c1 - c0) // 2 * 2
    return (r0, r1, c0, c1) if r1 > r0 and c1 > c0 else None


def _same_colour_index(n: int, shift: int) -> np.ndarray:
    """Source rows (or columns) ``i + shift`` (``shift`` even), those beyond the frame
    replaced by the nearest in-frame one of the same CFA parity."""
    src = np.arange(n) + shift
    low, high = src < 0, src > n - 1
    src[low] = src[low] % 2
    src[high] = (n - 1) - ((n - 1 - src[high]) % 2)
    return src


def period_shift(warp: np.ndarray) -> np.ndarray:
    """The warp's translation ``(tx, ty)`` rounded to whole CFA periods (even pixels)."""
    return (2 * np.rint(warp[:, 2] / 2)).astype(int)


def shift_mosaic(codes: np.ndarray, warp: np.ndarray) -> np.ndarray:
    """Bring a Bayer mosaic ``(H, W)`` onto the reference by whole 2 x 2 CFA periods: its
    translation rounded to even pixels, no resampling, no colours mixed (otherwise see
    :func:`resample_mosaic`).  Sites from outside the frame repeat the nearest same-colour
    edge site."""
    tx, ty = period_shift(warp)
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
    """Resample a Bayer mosaic ``(H, W)`` (codes) onto the reference, colour by colour.

    Green is read on its quincunx: red and blue sites filled by the mean of their four
    green neighbours, that full-resolution image warped (bicubic).  Red and blue: each
    sub-plane warped (bilinear) times ``(G + c) / (G_taps + c)``, the warped green over green
    interpolated from the same taps' sites (Cok 1987's smooth-hue transition), ``c`` =
    :data:`COLOUR_RATIO_FLOOR` of full scale.  Values are signals above ``black`` (one value
    or one per site of the 2 x 2 cell).  A clipped code is interpolated at its floor; an
    output is clipped only where most of its taps' weight is clipped, and a red or blue
    output whose correction would touch clipped green keeps its plain estimate.  Outputs
    are capped one code below ``clip_code``; samples outside the frame repeat its edge.
    With ``spread`` also the taps' spread (:func:`tap_variance`; red and blue on their
    sub-plane, green on the filled green image) as :func:`spread_code` codes: returns
    ``(codes, spread codes)``, both ``(H, W)``."""
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
#: output rows per band of :func:`resample_mosaic` (even: whole CFA periods); two bands'
#: temporaries are held at a time, not a frame's
BAND_ROWS = 128
#: source rows beyond a band's reach that it also reads (the green fills', bicubic's and
#: the clipping dilation's reach)
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
    # clipping's bookkeeping
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
    The merge adds it to a resampled sample's variance (:func:`hdrmerge_cli.pipeline.merge.sample_weights`),
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
                            cfa: str | None = None, row0: int = 0) -> np.ndarray:
    """Inverse-variance weights of the samples of a mosaic resampled by ``warp``.

    A table weight ``w = c / v`` (``c`` the weighting function, ``v`` the variance of the
    sample's value, (7)) becomes ``c / (e v + max(u - (s - e) v, 0))``: ``u`` the taps'
    spread (:func:`resample_mosaic`'s) times the squared slope of the value table, ``e``
    the interpolated noise's share ``w' C w`` and ``s`` the taps' mean noise ``sum w_i C_ii``
    (independent taps on a colour's sub-plane: ``e = (fx^2 + (1 - fx)^2) (fy^2 + (1 -
    fy)^2)``, ``s = 1``; green's correlated taps: :func:`_filled_green_noise`).
    ``w``, ``codes``, ``spread``: ``(H, W)`` (``w`` None: the table ``weight`` at each code;
    ``out`` may be ``w``; ``spread`` :func:`spread_code` codes, or float32).  ``slope``,
    ``certainty``, ``weight``: flattened ``(C * n_codes,)`` float32 tables, a sample's row
    from ``pattern`` (``(ph, pw)`` rows tiled over the mosaic; None: row 0).  ``row0``
    (even): the arrays are rows ``row0`` on of the mosaic.  Returns ``(H, W)`` float32 (one
    compiled pass)."""
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
                           np.asarray(warp, np.float64), green, int(row0), out)
    return out


#: :func:`spread_code`'s scale (squared codes) and steps per octave: ``2^32`` (a 16-bit
#: range squared) takes code 65520
SPREAD_FLOOR = 2.0**-8
SPREAD_STEPS = 1638


def spread_code(u: np.ndarray) -> np.ndarray:
    """Resampling spreads ``u`` (:func:`resample_mosaic`'s, squared codes, ``(H, W)``
    float32) as uint16 codes ``round(SPREAD_STEPS log2(1 + u / SPREAD_FLOOR))``, up to ``u
    = 2^32`` (a 16-bit range squared); ``u + SPREAD_FLOOR`` within 2.2e-4 (half a step).
    :func:`_spread_table` inverts it.  The spread of a moved frame is kept for every pass of
    the merge, in half the memory of float32."""
    out = np.empty(u.shape, np.uint16)
    _spread_code_rows(np.ascontiguousarray(u, np.float32).reshape(u.shape[0], -1), out.reshape(u.shape[0], -1),
                      np.float32(1.0 / SPREAD_FLOOR), np.float32(SPREAD_STEPS))
    return out


@njit(parallel=True, nogil=True, cache=True)
def _spread_code_rows(u, out, inv_floor, steps):  # pragma: no cover - compiled
    for r in prange(u.shape[0]):
        for c in range(u.shape[1]):
            v = np.log2(np.float32(1.0) + max(u[r, c], np.float32(0.0)) * inv_floor) * steps + np.float32(0.5)
            out[r, c] = min(int(v), 65535)


@functools.cache
def _spread_table() -> np.ndarray:
    """The spread (squared codes, float32) of each :func:`spread_code` code, ``(65536,)``."""
    return (SPREAD_FLOOR * (np.exp2(np.arange(65536) / SPREAD_STEPS) - 1.0)).astype(np.float32)


@njit(inline="always")
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


@njit(parallel=True, nogil=True, cache=True)
def _resampled_weight_rows(w, weight, table, codes, rows, slope, certainty, n_codes, spread, spread_of, sites, warp,
                           green, row0, out):  # pragma: no cover - compiled
    h, width = codes.shape
    ph, pw = rows.shape
    zero = np.float32(0.0)
    for r in prange(h):
        ra = r + row0  # the mosaic's row
        dy, v = ra & 1, ra >> 1
        for col in range(width):
            dx, u = col & 1, col >> 1
            if green[dy, dx]:  # read on the filled full-resolution green image
                x = warp[0, 0] * col + warp[0, 1] * ra + warp[0, 2]
                y = warp[1, 0] * col + warp[1, 1] * ra + warp[1, 2]
                x0, y0 = np.floor(x), np.floor(y)
                e, s = _filled_green_noise(x - x0, y - y0, green[int(y0) & 1, int(x0) & 1])
            else:
                fx = sites[dy, dx, 0, 0] * u + sites[dy, dx, 0, 1] * v + sites[dy, dx, 0, 2]
                fy = sites[dy, dx, 1, 0] * u + sites[dy, dx, 1, 1] * v + sites[dy, dx, 1, 2]
                fx -= np.floor(fx)
                fy -= np.floor(fy)
                e, s = (fx * fx + (1 - fx) ** 2) * (fy * fy + (1 - fy) ** 2), 1.0
            e32, s32 = np.float32(e), np.float32(s)
            i = rows[ra % ph, col % pw] * n_codes + min(codes[r, col], n_codes - 1)
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
