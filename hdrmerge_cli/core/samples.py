"""The bracket's one sample set, drawn once and read by every check.

:class:`Samples` holds every frame decoded, subsampled (:func:`normalised_samples`) and
normalised to ``v = (z - black) / (white - black)`` (drawn by the exposures stage,
:func:`~hdrmerge_cli.pipeline.exposure_check.ordered_samples`), off the constant borders
(:func:`constant_border`), with each frame's floor, and their order checked
(:func:`disordered_pair`).  What is measured on the samples (ratios, exposures, motion) is
:mod:`hdrmerge_cli.core.exposure_estimate`; what a response fit asks of their overlap,
:mod:`hdrmerge_cli.core.crf_estimate`.

Everything here is pure array code: no paths, no printing.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np

#: fewest pixels both frames must measure for a pair's ratio to count as measured
MIN_RATIO_PIXELS = 200
#: well-exposed range of v (normalised codes) whose ratios are trusted: linear data
#: (RAW, a linear response) and a verified response (a table: a profile or CSV)
RANGE_LINEAR = (0.01, 0.9)
RANGE_VERIFIED = (0.04, 0.94)
#: an unverified named response (sRGB assumed, gamma:G): the mid range only
RANGE_UNVERIFIED = (0.1, 0.9)
#: above a frame's floor (:attr:`Samples.floors`) by at least this (v): readings at the floor (film
#: fog, a scanner's or a sensor's black, a crushed toe) are no evidence of the light
FLOOR_MARGIN = 0.03
#: a frame's floor is what it reads on this share of the pixels its longer neighbour
#: reads below clipping, those it sees darkest
FLOOR_SHARE = 0.1
#: standard deviations of the floor's noise a single reading must stand above the floor to
#: count for an order (:attr:`Samples.noise_floors`)
FLOOR_SIGMAS = 3.0
#: tiles per side over which a ratio's standard error is measured (:attr:`Samples.tiles`)
TILES = 8
#: the order check fails when more than this fraction of the pixels that changed got darker
ORDER_DOWN_FRACTION = 0.75
#: ... and at least this many pixels changed by more than the margin
ORDER_MIN_CHANGED = 100


@dataclass
class Samples:
    """Frames decoded, subsampled and normalised: ``v`` per frame ``(H', W', C)`` float32
    (C = 1 for a RAW mosaic, every site normalised by its own black and white levels);
    ``inside``: (H', W') pixels off the constant borders; ``step``: the subsampling (images:
    every ``step``-th row and column; RAW: whole 2 x 2 CFA cells, one every ``step`` cells,
    so consecutive sample rows pair up into cells ``2 step`` pixels apart); ``levels``:
    ``(black, white - black, n_codes)`` of the codes normalised, per channel of ``v``
    (float32), for :attr:`codes`."""

    v: list[np.ndarray]
    inside: np.ndarray
    border: tuple[int, int, int, int]
    step: int
    codes_step: float  # one code value in units of v
    raw: bool = False  # a RAW mosaic (samples in whole CFA cells)
    levels: tuple[np.ndarray, np.ndarray, int] | None = None

    @property
    def top(self) -> float:
        """Half a code below full scale (``v``): a sample at or above it reads the top code, clipped."""
        return 1 - 0.5 * self.codes_step

    @property
    def pitch(self) -> int:
        """Full-resolution pixels between the samples :func:`~hdrmerge_cli.core.registration.sample_plane` reads
        (RAW: between CFA cells)."""
        return 2 * self.step if self.raw else self.step

    @functools.cached_property
    def floors(self) -> list[np.ndarray]:
        """Per frame, ``(C,)`` the level of ``v`` up to which the frame reads its floor rather
        than the light, :data:`FLOOR_MARGIN` included: where the response has no slope (film
        fog, a scanner's or a sensor's black, a crushed toe) a code says nothing of the light,
        so a frame's codes there are no evidence for a ratio.  The floor is what the frame
        reads where the light is least: its median over the pixels its longer neighbour sees
        darkest (:data:`FLOOR_SHARE` of those that neighbour reads below clipping, per
        channel), or its own 0.5th percentile where that is higher (the longest frame: that
        alone).  Off the borders."""
        return [level + FLOOR_MARGIN for level, _ in self._floor_readings]

    @property
    def floor_codes(self) -> list[np.ndarray]:
        """:attr:`floors` as code values: per frame, ``(C,)`` int64 the highest code at its floor."""
        black, span, _ = self.levels
        return [np.floor(np.asarray(f, np.float64) * span + black).astype(np.int64) for f in self.floors]

    @functools.cached_property
    def noise_floors(self) -> list[np.ndarray]:
        """:attr:`floors` with the margin raised to :data:`FLOOR_SIGMAS` times the noise of
        the frame's readings at its floor where that is more (from the differences of
        neighbouring samples of one colour there: their 84th percentile over sqrt 2, as
        readings at black are clipped at zero): a single reading below it may be the
        floor's noise, so it is no evidence for an order or for a frame reading anything.
        (The ratios keep :attr:`floors`: their own outlier rejection handles that noise.)"""
        return [level + np.maximum(FLOOR_MARGIN, FLOOR_SIGMAS * noise) for level, noise in self._floor_readings]

    @functools.cached_property
    def _floor_readings(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per frame, ``(C,)`` float32 its floor's level and noise (:attr:`floors`)."""
        out, top = [], self.top
        for k, v in enumerate(self.v):
            inside = v[self.inside]  # (N, C)
            level = np.percentile(inside, 0.5, axis=0) if inside.size else np.zeros(v.shape[-1])
            noise = np.zeros(v.shape[-1])
            if k + 1 < len(self.v) and inside.size:
                longer = self.v[k + 1]
                for c in range(v.shape[-1]):
                    seen = (longer[..., c] < top) & self.inside  # the light as the longer frame reads it
                    if np.count_nonzero(seen) < MIN_RATIO_PIXELS:
                        continue
                    darkest = (longer[..., c] <= np.percentile(longer[..., c][seen], 100 * FLOOR_SHARE)) & self.inside
                    level[c] = max(level[c], float(np.median(v[..., c][darkest])))
                    # the noise there from neighbouring samples of one colour (they share their
                    # light), so that frames that moved (whose darkest pixels differ) still agree
                    n = 2 if self.raw else 1  # a mosaic's samples alternate colours along a row
                    pair = darkest[:, :-n] & darkest[:, n:]
                    if np.count_nonzero(pair) >= MIN_RATIO_PIXELS:
                        d = np.abs(v[:, n:, c][pair] - v[:, :-n, c][pair])
                        noise[c] = float(np.percentile(d, 84.13)) / np.sqrt(2)
            out.append((level.astype(np.float32), noise.astype(np.float32)))
        return out

    @functools.cached_property
    def tiles(self) -> np.ndarray:
        """``(H', W', C)`` int: each sample's spatial tile, :data:`TILES` x :data:`TILES`
        over the frame, over which the errors of the pairs' ratios are measured
        (neighbouring pixels share their errors)."""
        h, w, c = self.v[0].shape
        rows = np.arange(h) * TILES // max(h, 1)
        cols = np.arange(w) * TILES // max(w, 1)
        return np.broadcast_to((rows[:, None] * TILES + cols[None, :])[..., None], (h, w, c))

    @functools.cached_property
    def codes(self) -> list[np.ndarray]:
        """The samples off the constant borders back as integer code values (images: exact),
        ``(N, C)`` int64 per frame (made once: the response's fit and the quick response read them)."""
        black, span, n_codes = self.levels
        return [np.rint(v[self.inside] * span + black).clip(0, n_codes - 1).astype(np.int64) for v in self.v]

    @functools.cached_property
    def knots(self) -> tuple[list[np.ndarray], int]:
        """:attr:`codes` on the knots of :func:`~hdrmerge_cli.core.crf_goossens2012.to_knots`
        (at most :data:`~hdrmerge_cli.core.crf_goossens2012.MAX_LEVELS` levels), and the number
        of levels: made once for every fit of the quick response on these samples
        (:func:`~hdrmerge_cli.core.exposure_estimate.quick_response`)."""
        from hdrmerge_cli.core.crf_goossens2012 import knot_levels, to_knots  # (numba: only an unverified response)

        n = self.levels[2]
        levels = knot_levels(n)
        return [to_knots(c, n, levels) for c in self.codes], levels

    def read_nothing(self) -> list[int]:
        """The frames with fewer than :data:`MIN_RATIO_PIXELS`
        samples between their floor and its noise (:attr:`noise_floors`) and clipping, off the
        borders: black (or white) frames, which say nothing of the light, their label or
        their order."""
        top = self.top
        return [k for k, (v, floor) in enumerate(zip(self.v, self.noise_floors))
                if np.count_nonzero(((v > floor) & (v < top)).any(-1) & self.inside) < MIN_RATIO_PIXELS]

    def registered(self, warps: list[np.ndarray]) -> Samples:
        """The samples brought onto the reference by the full-resolution ``warps`` (one
        ``(2, 3)`` per frame mapping reference pixels to the frame's, as
        the alignment stage returns them), bilinear
        (RAW: each site of the CFA cells from the same site of its neighbour cells);
        ``inside`` keeps only the samples every frame covers."""
        import cv2

        inside = self.inside.copy()
        out = []
        for v, w in zip(self.v, warps):
            m = np.array(w, np.float64)
            if np.allclose(m, np.eye(2, 3)):
                out.append(v)
                continue
            m[:, 2] /= self.pitch  # full-resolution pixels -> samples (RAW: cells)
            planes = _cell_planes(v) if self.raw else v
            h, wd = planes.shape[:2]
            flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            moved = cv2.warpAffine(np.ascontiguousarray(planes), m, (wd, h), flags=flags,
                                   borderMode=cv2.BORDER_REPLICATE).reshape(planes.shape)
            covered = cv2.warpAffine(np.ones((h, wd), np.uint8), m, (wd, h), flags=flags, borderValue=0) > 0
            if self.raw:
                moved, covered = _from_cell_planes(moved, v), _from_cell_planes(np.repeat(covered[..., None], 4, -1), np.zeros(v.shape, bool))[..., 0]
            out.append(moved)
            inside &= covered
        return replace(self, v=out, inside=inside)


def _cell_planes(v: np.ndarray) -> np.ndarray:
    """RAW samples ``(H', W', 1)`` (whole 2 x 2 cells) as ``(H' // 2, W' // 2, 4)`` planes."""
    h2, w2 = v.shape[0] // 2, v.shape[1] // 2
    return v[:2 * h2, :2 * w2, 0].reshape(h2, 2, w2, 2).transpose(0, 2, 1, 3).reshape(h2, w2, 4)


def _from_cell_planes(planes: np.ndarray, like: np.ndarray) -> np.ndarray:
    """:func:`_cell_planes` inverted into an array shaped as ``like`` (an odd last row or
    column, outside every whole cell, keeps ``like``'s values)."""
    h2, w2 = planes.shape[:2]
    out = like.copy()
    out[:2 * h2, :2 * w2, 0] = planes.reshape(h2, w2, 2, 2).transpose(0, 2, 1, 3).reshape(2 * h2, 2 * w2)
    return out


# ---------------------------------------------------------------- constant borders
def constant_border(codes: list[np.ndarray], tol: float, max_fraction: float = 0.25) -> tuple[int, int, int, int]:
    """Rows and columns at the edges of the frames that are constant in every frame
    (scan borders, letterboxing, a lens hood's black): ``(top, bottom, left, right)``
    counts of lines to drop.

    A line counts as constant when, in every frame and channel, the spread of its codes
    (95th minus 5th percentile) is at most ``tol``; lines are taken from each edge inward
    until the first textured one, at most ``max_fraction`` of the size per side.  Lines
    constant in every frame carry no exposure information (their codes do not follow the
    exposure), and they fool statistics of whole frames such as the mean code.

    codes : P arrays (H, W) or (H, W, C), one per frame (same shape)
    """
    h, w = codes[0].shape[:2]

    def spread(axis: int) -> np.ndarray:  # largest line spread over frames and channels, per line
        out = None
        for z in codes:
            z3 = z.reshape(h, w, -1).astype(np.float32)
            lo, hi = np.percentile(z3, [5, 95], axis=axis)  # (lines, C)
            s = np.max(hi - lo, axis=-1)
            out = s if out is None else np.maximum(out, s)
        return out

    def run(flat: np.ndarray, limit: int) -> int:
        n = 0
        while n < limit and flat[n]:
            n += 1
        return n

    rows = spread(1) <= tol  # (H,)
    cols = spread(0) <= tol  # (W,)
    mh, mw = int(h * max_fraction), int(w * max_fraction)
    return run(rows, mh), run(rows[::-1], mh), run(cols, mw), run(cols[::-1], mw)


def border_mask(shape: tuple[int, int], border: tuple[int, int, int, int]) -> np.ndarray:
    """(H, W) bool: True inside the frame, False on the border lines of :func:`constant_border`."""
    top, bottom, left, right = border
    m = np.zeros(shape[:2], dtype=bool)
    m[top:shape[0] - bottom, left:shape[1] - right] = True
    return m



def _subsample_index(n: int, step: int, mosaic: bool) -> np.ndarray:
    idx = np.arange(n)
    return idx[(idx // 2) % step == 0] if mosaic else idx[::step]


def normalised_samples(codes: np.ndarray, black, white, step: int = 1, cell: np.ndarray | None = None) -> np.ndarray:
    """``v = (z - black) / (white - black)`` of a frame's codes, float32, every ``step``-th
    row and column: an image's ``(H, W, C)`` codes with ``(C,)`` levels, ``(H', W', C)``; a
    mosaic's ``(H, W)`` codes in whole 2 x 2 cells (every ``step``-th cell), each site with
    the levels of its colour index in ``cell`` (2 x 2; None: the first), ``(H', W', 1)``."""
    mosaic = codes.ndim == 2
    ys = _subsample_index(codes.shape[0], step, mosaic)
    xs = _subsample_index(codes.shape[1], step, mosaic)
    z = codes[np.ix_(ys, xs)].astype(np.float32)
    black = np.asarray(black, dtype=np.float32)
    white = np.asarray(white, dtype=np.float32)
    if mosaic:
        c = cell[(ys % 2)[:, None], (xs % 2)[None, :]] if cell is not None else np.zeros((len(ys), len(xs)), np.intp)
        return ((z - black[c]) / (white[c] - black[c]))[..., None]
    return (z - black[: z.shape[-1]]) / (white[: z.shape[-1]] - black[: z.shape[-1]])


def sample_set(v: list[np.ndarray], step: int, black, white, n_codes: int, raw: bool, border_tol: float) -> Samples:
    """The :class:`Samples` of every frame's :func:`normalised_samples` ``v`` (subsampled by
    ``step``; ``black``, ``white``: the frames' levels per channel), off the
    :func:`constant_border` lines (spread at most ``border_tol``)."""
    border = constant_border(v, border_tol)
    span = float(np.min(white - black))
    c = v[0].shape[-1]
    levels = (np.asarray(black, np.float32)[:c], np.asarray(white - black, np.float32)[:c], n_codes)
    return Samples(v, border_mask(v[0].shape, border), border, step, 1.0 / max(span, 1.0), raw, levels)


# ---------------------------------------------------------------- order check
@dataclass
class OrderTest:
    """Sign test of a neighbour pair: of the pixels both frames measure, how many got
    brighter (``up``) and darker (``down``) by more than the noise margin in the frame
    labelled longer."""

    up: int
    down: int
    usable: int

    @property
    def down_fraction(self) -> float:
        return self.down / max(1, self.up + self.down)

    @property
    def disordered(self) -> bool:
        """The longer-labelled frame is darker on most changed pixels: a monotone response
        cannot do that, so the labels (or the files) are out of order.  Frames at the noise
        floor or of equal exposure change both ways about equally and pass."""
        return self.up + self.down >= ORDER_MIN_CHANGED and self.down_fraction > ORDER_DOWN_FRACTION


def order_test(z_short: np.ndarray, z_long: np.ndarray, usable: np.ndarray, margin: float) -> OrderTest:
    """The sign test of :class:`OrderTest` on code values (any monotone response keeps the
    sign of a change, so no response is needed; Wilcoxon-style sign test on the pixels that
    neither frame clips, borders excluded).

    z_short, z_long : codes of the frames labelled shorter and longer (same shape)
    usable : bool mask of the samples to compare; margin : changes of at most this are noise
    """
    d = z_long[usable].astype(np.float32) - z_short[usable].astype(np.float32)
    return OrderTest(int(np.count_nonzero(d > margin)), int(np.count_nonzero(d < -margin)), int(d.size))


def disordered_pair(s: Samples, exposures: np.ndarray, equal_rtol: float) -> tuple[int, OrderTest] | None:
    """The first neighbour pair ``(k - 1, k)`` the longer-labelled frame ``k`` of which is
    darker (:attr:`OrderTest.disordered`), as ``(k, its test)``, or None: per pair the sign
    test of :func:`order_test` on the pixels both frames read above their floors and its
    noise (:attr:`Samples.noise_floors`) and neither clips, off the constant borders, with a
    margin of 1.5 codes.  Pairs whose labels tie (within ``equal_rtol``) are not ordered by
    them."""
    margin = max(1.5 * s.codes_step, 0.004)
    top = s.top
    for k in range(1, len(s.v)):
        if exposures[k] <= exposures[k - 1] * (1 + equal_rtol):
            continue
        a, b = s.v[k - 1], s.v[k]
        usable = (a > s.noise_floors[k - 1]) & (b > s.noise_floors[k]) & (a < top) & (b < top) & s.inside[..., None]
        t = order_test(a, b, usable, margin)
        if t.disordered:
            return k, t
    return None
