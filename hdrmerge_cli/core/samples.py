"""The bracket's one sample set and what is measured on it.

:class:`Samples` holds every frame decoded, subsampled and normalised to
``v = (z - black) / (white - black)`` (drawn by the exposures stage,
:func:`~hdrmerge_cli.pipeline.exposure_check.sample_frames`).  On it: the neighbour pairs'
overlap (:func:`thin_overlap`), their ratios through a response (:func:`measure_pairs`), the
exposures chained from them (:func:`estimate`; :mod:`hdrmerge_cli.core.comparametric` holds
the estimators), a quick response fitted on the samples when the one in use is only
assumed (:func:`quick_response`), and whether the response or a label explains a frame's
difference from its label (:func:`label_at_fault`, :func:`response_fits`).  The response
stage, the exposures stage and the excess-variance test all read the same samples here.

Everything here is pure array code: no paths, no printing.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np

from hdrmerge_cli.core.comparametric import (
    LABEL_TOLERANCE_EV, MIN_RATIO_PIXELS, ExposureEstimate, PairRatio, chain_pairs, comparagram, estimate_exposures,
    response_from_comparagrams, robust_log_ratio,
)
from hdrmerge_cli.core.crf import CRF, linearise, table_crf
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.registration import (
    block_mean, common_range, corner_distance, dark_floor, log_irradiance, pair_displacement,
)

#: a pair registered on the samples counts as moved when displaced by more than this many
#: sample pitches (:func:`moved_threshold_px`)
MOVED_PITCHES = 1.5
#: ... and by more than this many full-resolution pixels
MOVED_MIN_PX = 1.0

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
#: fewest pixels consecutive frames must both expose (neither code clipped) for a CRF fit
MIN_OVERLAP = 50


@dataclass
class Samples:
    """Frames decoded, subsampled and normalised: ``v`` per frame ``(H', W', C)`` float32
    (C = 1 for a RAW mosaic, every site normalised by its own black and white levels);
    ``inside``: (H', W') pixels off the constant borders; ``step``: the subsampling (images:
    every ``step``-th row and column; RAW: whole 2 x 2 CFA cells, one every ``step`` cells,
    so consecutive sample rows pair up into cells ``2 step`` pixels apart); ``levels``:
    ``(black, white - black, n_codes)`` of the codes normalised, per channel of ``v``
    (float32), for :func:`samples_codes`."""

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
        """Full-resolution pixels between the samples :func:`sample_plane` reads
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

    def read_nothing(self) -> list[int]:
        """The frames with fewer than :data:`~hdrmerge_cli.core.comparametric.MIN_RATIO_PIXELS`
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


def thin_overlap(s: Samples) -> tuple[int, int] | None:
    """The first neighbour pair sharing fewer than :data:`MIN_OVERLAP` pixels that neither
    frame clips (0 < z < max; constant borders excluded), as ``(k, pixels)`` with ``k`` the
    pair's longer frame, or None: a response cannot be chained across such a pair."""
    lo, hi = 0.5 * s.codes_step, s.top
    for k in range(1, len(s.v)):
        a, b = s.v[k - 1], s.v[k]
        both = int(np.count_nonzero(((a > lo) & (a < hi) & (b > lo) & (b < hi)).all(-1) & s.inside)) * s.step**2
        if both < MIN_OVERLAP:
            return k, both
    return None


def well_exposed_overlap(s: Samples) -> list[int]:
    """Per neighbour pair ``(k - 1, k)``, the pixels (off the borders, at full resolution)
    both frames expose well in every channel: within :data:`RANGE_UNVERIFIED`, where any
    camera's response has slope, and above each frame's floor (:attr:`Samples.floors`).
    Pixel pairs pin a response only through such pixels; elsewhere one of the two codes is
    at a floor or a shoulder, and its noise there biases a fit on pairs (errors in the
    variables)."""
    lo, hi = RANGE_UNVERIFIED
    ok = [((v >= np.maximum(lo, floor)) & (v <= hi)).all(-1) & s.inside for v, floor in zip(s.v, s.floors)]
    return [int(np.count_nonzero(ok[k - 1] & ok[k])) * s.step**2 for k in range(1, len(ok))]


def pairs_pin_response(s: Samples) -> bool:
    """Whether some neighbour pair shares :data:`MIN_OVERLAP` well-exposed pixels
    (:func:`well_exposed_overlap`): else a response is fitted on the frames' histograms
    (:func:`~hdrmerge_cli.core.crf_estimate.histogram_correspondences`), not on pixel pairs."""
    return len(s.v) < 2 or max(well_exposed_overlap(s)) >= MIN_OVERLAP


def crf_verified(crf: CRF) -> bool:
    """Linear data and measured response tables (a profile's, a CSV, one fitted on the
    bracket) are trusted; a model (sRGB or ``gamma:G``, assumed for want of a response or
    named by the user) is not: it is a guess at this camera's curve, so its ratios are read
    in the mid range, up to a power, and a label is judged only where the bracket's own
    fitted response agrees."""
    return crf.is_linear or (crf.table is not None and not crf.assumed)


def usable_range(crf: CRF) -> tuple[float, float]:
    return RANGE_LINEAR if crf.is_linear else RANGE_VERIFIED if crf_verified(crf) else RANGE_UNVERIFIED


def measure_pairs(s: Samples, crf: CRF, value_range: tuple[float, float] | None = None) -> list[PairRatio]:
    """:func:`~hdrmerge_cli.core.comparametric.robust_log_ratio` of every neighbour pair, on the
    pixels both frames expose well: ``v`` within ``value_range`` (default by the response,
    :func:`usable_range`) and above each frame's own floor, off the borders; linearised by
    ``crf`` per channel (RAW: ``v`` itself)."""
    lo, hi = value_range or usable_range(crf)
    masks, lin = [], []
    for v, floor in zip(s.v, s.floors):
        ok = (v >= np.maximum(lo, floor)) & (v <= hi) & s.inside[..., None]
        masks.append(ok)
        lin.append(linearise(v, crf, s.codes_step))
    total = max(1, int(np.count_nonzero(s.inside)) * s.v[0].shape[-1])
    tiles = s.tiles
    out = []
    for k in range(1, len(s.v)):
        both = masks[k - 1] & masks[k]
        r = robust_log_ratio(lin[k - 1][both], lin[k][both], tiles=tiles[both])
        r.coverage = int(np.count_nonzero(both)) / total
        out.append(r)
    return out


def estimate(exposures: np.ndarray, s: Samples, crf: CRF, value_range: tuple[float, float] | None = None, free_slope: bool = False,
             moved: frozenset[int] = frozenset()) -> ExposureEstimate:
    """Every frame's exposure measured on the samples (see :mod:`hdrmerge_cli.core.comparametric`),
    on the labels' scale (the reference frame keeps its label).  The pairs in ``moved``
    (frames that moved between the exposures) are marked so: their labels' ratio is kept."""
    pairs = [replace(p, moved=True) if k in moved else p for k, p in enumerate(measure_pairs(s, crf, value_range))]
    return estimate_exposures(np.log(exposures), pairs, free_slope=free_slope or not crf_verified(crf))


def samples_codes(s: Samples) -> list[np.ndarray]:
    """The samples off the constant borders back as integer code values (images: exact),
    ``(N, C)`` int64 per frame."""
    black, span, n_codes = s.levels
    return [np.rint(v[s.inside] * span + black).clip(0, n_codes - 1).astype(np.int64) for v in s.v]


def quick_response(exposures: np.ndarray, s: Samples, skip: frozenset[int] = frozenset()) -> CRF:
    """An image bracket's inverse response fitted on its samples (constant borders off)
    with the given exposures, per channel, from the neighbour pairs' comparagrams
    (:func:`~hdrmerge_cli.core.comparametric.response_from_comparagrams`): the check's own
    response when the one in use is an unverified model (sRGB assumed), whose ratios are
    off by up to a stop on real cameras' tone curves.  Pairs in ``skip`` (frames that
    moved) are left out while others remain."""
    from hdrmerge_cli.core.crf_estimate import inverse_from_log  # (numba: only a bracket given no response)
    from hdrmerge_cli.core.crf_goossens2012 import from_knots, knot_levels, to_knots

    n = s.levels[2]
    levels = knot_levels(n)
    codes = [to_knots(c, n, levels) for c in samples_codes(s)]  # (N, C)
    log_r = np.diff(np.log(exposures))
    used = [k for k in range(1, len(codes)) if k - 1 not in skip] or list(range(1, len(codes)))
    tables = []
    for ch in range(codes[0].shape[-1]):
        grams = [comparagram(codes[k - 1][:, ch], codes[k][:, ch], levels) for k in used]
        g = from_knots(response_from_comparagrams(grams, log_r[[k - 1 for k in used]]), n)
        tables.append(inverse_from_log(g)[0])
    return table_crf(np.stack(tables), "fitted on the bracket")


def estimate_with_response(exposures: np.ndarray, s: Samples, crf: CRF, rounds: int = 1,
                           moved: frozenset[int] = frozenset()) -> tuple[ExposureEstimate, CRF]:
    """:func:`estimate` through ``crf`` when it is trusted (linear, a measured table);
    otherwise through a response fitted on the bracket (:func:`quick_response`), jointly:
    fit with the labels, estimate, refit with the estimates, ``rounds`` times.  Pairs in
    ``moved`` are not used (their labels' ratio is kept)."""
    if crf_verified(crf):
        return estimate(exposures, s, crf, moved=moved), crf
    h = np.asarray(exposures, dtype=np.float64)
    fitted = quick_response(h, s, moved)  # its least squares shrink the ratios a little: slope fitted
    est = estimate(exposures, s, fitted, free_slope=True, moved=moved)
    for _ in range(rounds - 1):
        fitted = quick_response(np.exp(est.log_h), s, moved)
        est = estimate(exposures, s, fitted, free_slope=True, moved=moved)
    # a label is called wrong only where the assumed response agrees (same sign; the smaller
    # of the two differences): a fit on pairs that barely overlap, or a camera curve far
    # from the assumed one, each alone makes false alarms
    model = estimate(exposures, s, crf, moved=moved)
    assumed = model.difference_ev
    agree = np.sign(assumed) == np.sign(est.difference_ev)
    diff = np.where(agree, np.sign(assumed) * np.minimum(np.abs(assumed), np.abs(est.difference_ev)), 0.0)
    return replace(est, difference_ev=diff, model_slope=model.slope), fitted


def label_at_fault(est: ExposureEstimate, k: int) -> bool:
    """Whether frame ``k``'s difference from its label is what a wrong label makes rather
    than a response that does not fit the frame.  A wrong label moves every pixel's ratio
    alike; a wrong response (or a frame processed or lit differently) bends the ratios with
    brightness.  The label is blamed when the ratios' change over the brightness range,
    summed over the pairs frame ``k``'s estimate chains through (:func:`ratio_bend_ev`), is
    smaller than the difference itself."""
    return bool(ratio_bend_ev(est, k) < abs(est.difference_ev[k]))


def power_explains(est: ExposureEstimate, tol_ev: float = LABEL_TOLERANCE_EV) -> bool:
    """Whether the differences from the labels grow in proportion to each frame's distance
    from the reference in exposure, as a response of the wrong power makes (every ratio
    read through it is scaled alike): one slope fitted through the reference leaves every
    frame within ``tol_ev``.  Needs three frames; a single wrong label leaves at least half
    its error off such a line."""
    d = np.asarray(est.difference_ev, np.float64)
    x = (est.log_h - est.log_h[est.reference]) / np.log(2)
    if d.size < 3 or not np.any(x):
        return False
    slope = float(np.dot(x, d) / np.dot(x, x))
    return bool(np.max(np.abs(d - slope * x)) <= tol_ev)


def response_fits(est: ExposureEstimate) -> bool:
    """Whether the response in use fits the bracket: the median measured pair's ratios
    change by less than the label tolerance over their brightness range.  The response is
    common to every frame, so where it bends most pairs no label can be judged through it."""
    trends = [abs(p.trend) for p in est.pairs if p.measured]
    return not trends or float(np.median(trends)) / np.log(2) < LABEL_TOLERANCE_EV


def model_power_error_ev(est: ExposureEstimate) -> float:
    """Where the response is a model checked against the bracket's own fit
    (:func:`estimate_with_response`): how far the model's reading of the ratios puts the
    bracket's outermost frame from its label (EV), ``|slope - 1|`` times its distance from
    the reference; 0 otherwise.  A response of another power than the camera's scales
    every log ratio alike."""
    if est.model_slope is None:
        return 0.0
    span = np.abs(est.log_h - est.log_h[est.reference]) / np.log(2)
    return float(abs(est.model_slope - 1.0) * np.max(span))


def ratio_bend_ev(est: ExposureEstimate, k: int) -> float:
    """The change of the pixels' ratios over brightness (EV), summed over the pairs frame
    ``k``'s estimate chains through (:attr:`~hdrmerge_cli.core.comparametric.PairRatio.trend`)."""
    return sum(abs(est.pairs[j].trend) for j in chain_pairs(k, est.reference)) / np.log(2)


# ---------------------------------------------------------------- motion between exposures
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

    def moved(self) -> frozenset[int]:
        return frozenset(j for j, d in self.px.items() if d is not None and d > self.threshold_px)

    def decided_by_motion(self, k: int, reference: int) -> int | None:
        """The pair that moved most among those frame ``k``'s estimate chains through from
        the reference (:func:`~hdrmerge_cli.core.comparametric.chain_pairs`), or None when none
        of them moved."""
        moved = [j for j in chain_pairs(k, reference) if j in self.moved()]
        return max(moved, key=lambda j: self.px[j]) if moved else None


def sample_plane(s: Samples, k: int, crf: CRF) -> np.ndarray:
    """Frame ``k``'s samples linearised through ``crf`` as one plane for registration (the
    channels' mean), the constant borders cut off; RAW: the mean of each 2 x 2 CFA cell."""
    top, bottom, left, right = s.border
    v = s.v[k]
    if s.raw:  # whole cells: start on an even sample row and column
        top, left = top + top % 2, left + left % 2
    v = v[top:v.shape[0] - bottom, left:v.shape[1] - right]
    lin = linearise(v, crf, s.codes_step).mean(axis=-1, dtype=np.float32)
    return block_mean(lin, 2) if s.raw else lin


def moved_pairs(s: Samples, exposures: np.ndarray, crf: CRF, pairs) -> Motion:
    """Register each neighbour pair in ``pairs`` (indices ``j``: frames ``j``, ``j + 1``) on
    the samples (:func:`~hdrmerge_cli.core.registration.pair_displacement` of their
    :func:`sample_plane` as :func:`~hdrmerge_cli.core.registration.log_irradiance`
    over the irradiance range both expose, exposure-normalised by ``exposures``, the
    labels: registration is invariant to the gain a wrong label makes), in full-resolution
    pixels (the samples' pitch).  A few tens of milliseconds a pair on the merge's default
    samples; only the pairs asked about are registered."""
    lin: dict[int, np.ndarray] = {}
    px: dict[int, float | None] = {}
    for j in sorted(set(pairs)):
        try:
            lo, hi = common_range([exposures[j], exposures[j + 1]], lo_code=dark_floor(s.codes_step if s.raw else None))
        except HdrMergeError:
            px[j] = None
            continue
        for k in (j, j + 1):
            if k not in lin:
                lin[k] = sample_plane(s, k, crf)
        d = pair_displacement(log_irradiance(lin[j], exposures[j], lo, hi),
                              log_irradiance(lin[j + 1], exposures[j + 1], lo, hi))
        px[j] = None if d is None else d * s.pitch
        lin.pop(j, None)  # pairs in order: frame j is not needed again
    return Motion(px, moved_threshold_px(s.pitch))


def label_motion(s: Samples, exposures: np.ndarray, crf: CRF, est: ExposureEstimate) -> Motion:
    """:func:`moved_pairs` of only the pairs that decided a label in question (none: no cost)."""
    return moved_pairs(s, exposures, crf, {j for k in est.mislabelled() for j in chain_pairs(k, est.reference)})


def warp_motion(warps: list[np.ndarray], aligned: list[bool], applied: bool, height: int, width: int,
                pitch: float) -> Motion:
    """The neighbour pairs' displacement as a registration measured it, ``warps`` ``(2, 3)``
    per frame (``aligned``: False where a frame was left unaligned), for samples brought onto
    the reference with them when ``applied`` (:meth:`Samples.registered`): 0 left between
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
