"""merge --align / --deghost: bring hand-held frames onto a reference frame, and drop
moving objects from the frames that disagree with it (see core/registration.py, core/resample.py, core/deghost.py)."""
from __future__ import annotations

import dataclasses
import functools
import logging
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from hdrmerge_cli.core import deghost, registration, resample
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.io.frames import Frame, HeldCodes, load_codes, load_validity
from hdrmerge_cli.io.metadata import sample_pattern
from hdrmerge_cli.pipeline.options import ALIGN_MODES, DEGHOST_MODES  # noqa: F401  (read as motion.*)

log = logging.getLogger("hdrmerge_cli")

#: ``--align auto`` applies the warps when some frame is displaced by more than this (pixels)
AUTO_ALIGN_PX = 0.25
#: a registration is kept when its correlation coefficient reaches this
MIN_CONFIDENCE = 0.3


def reference_index(frames: list[Frame]) -> int:
    """The reference frame of alignment and deghosting: the middle exposure."""
    return len(frames) // 2


def _of_frame(frame: Frame, frames: list[Frame], items: list):
    """The item of ``items`` that stands beside ``frame`` itself (not its path or position)
    in ``frames``."""
    for f, item in zip(frames, items):
        if f is frame:
            return item
    raise KeyError(frame.path)


@dataclasses.dataclass
class Alignment:
    """What :func:`estimate_alignment` found: per frame (the lists in the order of
    ``frames``) its warp onto the reference, ``(2, 3)`` float64 in the frame's own sample
    coordinates; :meth:`warp_of` finds a frame's by identity, whatever order the frames are
    in later (``--times estimate`` may re-sort them).

    mode : the ``--align`` mode; motion : ``translation`` or ``similarity`` as found
    resampling : RAW ``cfa-periods`` or ``per-colour``; images ``none``
    reference : the reference frame's path; applied : whether the merge moves the frames
    confidence : each registration's correlation to its neighbour (1 for the reference)
    unaligned, still : paths of the frames left unaligned, and found still at coarse resolution
    """

    mode: str
    motion: str
    resampling: str
    reference: str
    applied: bool
    frames: list[Frame]
    warps: list[np.ndarray]
    confidence: list[float]
    unaligned: list[str]
    still: list[str]

    def warp_of(self, frame: Frame) -> np.ndarray:
        return _of_frame(frame, self.frames, self.warps)

    @property
    def sizes(self) -> list[float]:
        """Each frame's largest displacement at a corner (pixels)."""
        return [registration.warp_size(w, f.height, f.width) for w, f in zip(self.warps, self.frames)]

    @functools.cached_property
    def every_frame_mask(self) -> np.ndarray | None:
        """``(H, W)`` bool: the reference's pixels that every aligned frame covers; None when
        the alignment is not applied (all of them).  Made once (the log, ``--json`` and
        ``--crop`` read it)."""
        if not self.applied:
            return None
        every = None
        for f, w in zip(self.frames, self.warps):
            inside = covered(f, w, self.resampling == "cfa-periods")
            every = inside if every is None else every & inside
        return every

    def covered_by_every_frame(self) -> float:
        """The share of the reference's pixels that every aligned frame covers (1 when the
        alignment is not applied); the rest is measured by fewer frames."""
        every = self.every_frame_mask
        return 1.0 if every is None else round(float(np.mean(every)), 6)

    def summary(self) -> dict:
        """``merge --json``'s ``alignment``."""
        out = {"mode": self.mode, "motion": self.motion, "resampling": self.resampling, "reference": self.reference,
               "frames": [f.path for f in self.frames], "applied": self.applied,
               "shift_px": [[round(float(w[0, 2]), 3), round(float(w[1, 2]), 3)] for w in self.warps],
               "largest_displacement_px": [round(s, 3) for s in self.sizes], "confidence": self.confidence,
               "unaligned": self.unaligned, "still": self.still,
               "covered_by_every_frame": self.covered_by_every_frame()}
        if self.motion == "similarity":
            out["rotation_deg"] = [round(float(np.degrees(np.arctan2(w[1, 0], w[0, 0]))), 4) for w in self.warps]
            out["scale"] = [round(float(np.hypot(w[0, 0], w[1, 0])), 6) for w in self.warps]
        return out | {"warps": [np.round(w, 6).tolist() for w in self.warps]}


def _linear(frame: Frame, codes: np.ndarray, crf: CRF) -> np.ndarray:
    """The frame's :func:`~hdrmerge_cli.core.registration.registration_image`."""
    return registration.registration_image(codes, crf, frame.kind == "raw", float(np.mean(frame.black)),
                                           float(np.mean(frame.white)), frame.n_codes)


def _coarse_linear(frame: Frame, codes: np.ndarray, crf: CRF, f: int) -> np.ndarray:
    """The frame's :func:`~hdrmerge_cli.core.registration.coarse_registration_image`."""
    return registration.coarse_registration_image(codes, crf, frame.kind == "raw", float(np.mean(frame.black)),
                                                  float(np.mean(frame.white)), frame.n_codes, f)


def estimate_alignment(frames: list[Frame], exposures: np.ndarray, crf: CRF, mode: str, load=load_codes) -> Alignment:
    """Warps bringing every frame onto the reference (``core.registration``).  ``auto`` registers
    with rotation too and keeps a frame's rotation only where it beats translation, and
    applies the warps only when some frame is displaced by more than
    :data:`AUTO_ALIGN_PX`.  A pair is registered when both frames have texture in the
    irradiance range they share (:func:`~hdrmerge_cli.core.registration.registrable`: a count of
    pixels, however small a fraction of the frame), and the result is kept when its
    correlation reaches :data:`MIN_CONFIDENCE`.  A frame left unaligned is a warning when
    the mode was asked for or other frames moved; under ``auto`` with nothing applied, an
    info line.  Under ``auto`` each pair is first tested at coarse resolution (the level the
    texture test measures at): a pair without texture there is left unaligned, one
    found still (:func:`~hdrmerge_cli.core.registration.still_test`, at
    :data:`AUTO_ALIGN_PX` divided by the frame's steps from the reference, so the chained
    warp stays within it) is not registered at full resolution: an image keeps the coarse
    translation estimate, a RAW frame its neighbour's warp (no correction below the
    tolerance is worth resampling a mosaic colour by colour).  A pair registered in full
    keeps its warp only where its displacement exceeds what the pair can tell from no motion
    (:func:`~hdrmerge_cli.core.registration.displacement_margin`): a displacement the
    bracket does not pin is not applied.  Returns an :class:`Alignment`."""
    ref = reference_index(frames)
    motion = "similarity" if mode == "auto" else mode
    raw = frames[0].kind == "raw"
    identity = np.hstack([np.eye(2), np.zeros((2, 1))])
    steps, sides, confidence, judged_still = _register_steps(frames, exposures, crf, mode, motion, ref, load)
    warps = [None] * len(frames)
    warps[ref] = identity
    unaligned = []
    for j in sides[0] + sides[1]:
        w, why = steps[j]
        if why is not None:
            unaligned.append(frames[j].path)
        warps[j] = registration.compose(w, warps[j - 1 if j > ref else j + 1])
    rotated = any(abs(w[1, 0]) > 1e-9 for w in warps)
    if mode == "auto" and not rotated:
        motion = "translation"  # no frame's rotation beat its translation
    sizes = [registration.warp_size(w, f.height, f.width) for w, f in zip(warps, frames)]
    applied = mode != "auto" or max(sizes) > AUTO_ALIGN_PX
    # a frame left unaligned is a warning when alignment was asked for or the others moved (a
    # hand-held bracket); under auto on a bracket where nothing registered moved (a tripod, or
    # frames too far apart in exposure to share tones) it is only logged (-v)
    say = log.warning if applied else log.info
    for j in sorted(steps):  # in frame order, whichever side finished first
        if steps[j][1] is not None:
            say("%s: %s; left unaligned", frames[j].path, steps[j][1])
    periods = raw and motion == "translation" and (mode == "translation" or whole_periods_suffice(warps))
    if periods:
        applied &= any(np.any(np.rint(w[:, 2] / 2) != 0) for w in warps)
    # RAW: moved by whole CFA periods, or resampled colour by colour (core.resample.resample_mosaic)
    resampling = "none" if not raw else "cfa-periods" if periods else "per-colour"
    log.info("alignment (%s): largest displacement %.2f px; %s", motion, max(sizes),
             "applied" if applied else "not needed")
    out = Alignment(mode, motion, resampling, frames[ref].path, bool(applied), list(frames), warps, confidence,
                    unaligned, [frames[j].path for j in sorted(judged_still)])
    if applied:
        share = out.covered_by_every_frame()
        if share < 1:
            log.info("alignment: %.1f %% of the image lies outside some moved frame and is measured by fewer frames "
                     "(its borders)", 100 * (1 - share))
    return out


def _shared_range(frame: Frame, exposure_a: float, exposure_b: float) -> tuple[float, float] | None:
    """The irradiance range two frames both expose well
    (:func:`~hdrmerge_cli.core.registration.common_range`; ``frame``: the first, whose code
    step sets the dark floor of linear data), or None when there is none."""
    linear = frame.kind != "image"  # RAW or linear TIFF: 16 codes are a signal level
    code_step = 1.0 / float(np.min(frame.white - frame.black)) if linear else None
    try:
        return registration.common_range([exposure_a, exposure_b], lo_code=registration.dark_floor(code_step))
    except HdrMergeError:
        return None


def _register_steps(frames: list[Frame], exposures: np.ndarray, crf: CRF, mode: str, motion: str, ref: int, load):
    """The steps of :func:`estimate_alignment`: per frame ``j`` other than the reference,
    ``(warp from its neighbour towards the reference to it, why it is left unaligned or
    None)``, the two sides' frame orders, the confidences and the frames found still."""
    raw = frames[0].kind == "raw"
    identity = np.hstack([np.eye(2), np.zeros((2, 1))])
    confidence = [1.0] * len(frames)
    judged_still: list[int] = []

    def step(a: int, b: int, image) -> tuple[np.ndarray, str | None]:
        """Warp from frame a's coordinates to frame b's (neighbours in exposure), or the
        identity and why they cannot be registered."""
        shared = _shared_range(frames[a], exposures[a], exposures[b])
        if shared is None:
            return identity, "no irradiance range is well exposed in both it and its neighbour"
        lo, hi = shared
        ia = registration.log_irradiance(image(a), exposures[a], lo, hi)
        ib = registration.log_irradiance(image(b), exposures[b], lo, hi)
        why = registration.registrable(ia, ib)
        if why is not None:
            return identity, f"{why} in the range it shares with its neighbour"
        w, rho = registration.estimate_warp(ia, ib, motion)
        confidence[b] = round(rho, 4)
        if rho < MIN_CONFIDENCE:
            return identity, f"registration to its neighbour correlates only {rho:.2f}"
        return (registration.rescale_warp(w, 2, 0.5) if raw else w), None  # RAW: found on 2 x 2 cells (centre 2u + 0.5)

    def image(k: int) -> np.ndarray:  # made again for each pair rather than held: the codes are
        # decoded once (HeldCodes)
        return _linear(frames[k], load(frames[k]), crf)

    scale = registration.coarse_factor(frames[0].height, frames[0].width, 2 if raw else 1)
    small: dict[int, np.ndarray] = {}
    making = {k: threading.Lock() for k in range(len(frames))}

    def coarse(k: int) -> np.ndarray:  # the registration image reduced as the texture test
        # reduces it; the reference's made once for both sides
        with making[k]:
            if k not in small:
                small[k] = _coarse_linear(frames[k], load(frames[k]), crf, scale)
            return small[k]

    def still(a: int, b: int) -> tuple[np.ndarray, str | None] | None:
        """Under ``auto``: the step from frame a to b at coarse resolution when the pair is
        still (:func:`~hdrmerge_cli.core.registration.still_test`, the tolerance
        :data:`AUTO_ALIGN_PX` shared by the steps between b and the reference), else None."""
        shared = _shared_range(frames[a], exposures[a], exposures[b])
        if shared is None:
            return None
        lo, hi = shared
        ia = registration.log_irradiance(coarse(a), exposures[a], lo, hi)
        ib = registration.log_irradiance(coarse(b), exposures[b], lo, hi)
        why = registration.registrable(ia, ib, scale // (2 if raw else 1))
        if why is not None:  # the texture test measures at this level
            return identity, f"{why} in the range it shares with its neighbour"
        tol = AUTO_ALIGN_PX / abs(b - ref)
        is_still, w, bound, rho = registration.still_test(ia, ib, scale, frames[b].height, frames[b].width, tol)
        if not is_still:
            log.info("%s: may be displaced from its neighbour by %.3f px or more (coarse test); registered at full "
                     "resolution", frames[b].path, tol)
            return None
        confidence[b] = round(rho, 4)
        log.info("%s: still against its neighbour (coarse test: displaced at most %.3f px at %g confidence, by "
                 "(%.3f, %.3f) px as estimated); not registered at full resolution", frames[b].path, bound,
                 1 - registration.STILL_P_MISS, w[0, 2], w[1, 2])
        judged_still.append(b)
        if rho < MIN_CONFIDENCE:
            return identity, f"its still test correlates only {rho:.2f} with its neighbour"
        # RAW: within the tolerance at the test's confidence the frame stays where its
        # neighbour is: resampling a mosaic colour by colour for an estimate of a few
        # hundredths of a pixel costs more than it corrects (a colour's 2-px pitch, the taps'
        # spread in the weights, clipped taps near white)
        return (identity if raw else w), None

    def pinned(a: int, b: int, w: np.ndarray) -> bool:
        """Under ``auto``: whether the registered step from frame a to b moves b by more than
        the pair can tell from no motion
        (:func:`~hdrmerge_cli.core.registration.displacement_margin` on the coarse images)."""
        size = registration.warp_size(w, frames[b].height, frames[b].width)
        lo, hi = _shared_range(frames[a], exposures[a], exposures[b])
        margin = registration.displacement_margin(registration.log_irradiance(coarse(a), exposures[a], lo, hi),
                                                  registration.log_irradiance(coarse(b), exposures[b], lo, hi), w,
                                                  scale, frames[b].height, frames[b].width)
        if size > margin:
            return True
        log.info("%s: registered %.2f px from its neighbour, within the %.2f px the pair cannot tell from no "
                 "motion; not moved", frames[b].path, size, margin)
        judged_still.append(b)
        return False

    def chain(indices: list[int]) -> dict:
        """The steps of one side of the reference, outwards: under ``auto`` a step found still at
        coarse resolution is not registered at full resolution, and a registered one is kept
        only where the pair pins it (:func:`pinned`)."""
        out = {}
        for j in indices:
            a = j - 1 if j > ref else j + 1
            out[j] = (mode == "auto" and still(a, j)) or step(a, j, image)
            if mode == "auto" and out[j][1] is None and j not in judged_still and not pinned(a, j, out[j][0]):
                out[j] = identity, None
        return out

    # each frame is registered to its neighbour towards the reference (they share the most
    # well-exposed range) and the warps are chained: W_j = step(j -+ 1, j) o W_(j -+ 1).  The
    # two sides of the reference run on two threads (OpenCV's ECC releases the GIL)
    sides = [list(range(ref + 1, len(frames))), list(range(ref - 1, -1, -1))]
    with ThreadPoolExecutor(2) as pool:
        steps = {j: st for side in pool.map(chain, [s for s in sides if s]) for j, st in side.items()}
    return steps, sides, confidence, judged_still


def whole_periods_suffice(warps) -> bool:
    """RAW: a translation by whole 2 x 2 CFA periods moves codes without resampling them;
    ``auto`` resamples each colour's sites (``core.resample.resample_mosaic``) instead only when whole periods would
    leave some frame more than :data:`AUTO_ALIGN_PX` off along either axis."""
    return max(float(np.max(np.abs(w[:, 2] - 2 * np.rint(w[:, 2] / 2)))) for w in warps) <= AUTO_ALIGN_PX


def loader(alignment: Alignment | None, load=load_codes):
    """``frame -> codes`` (``load``), brought onto the reference when the alignment is
    applied (an :class:`AlignedLoader`)."""
    if alignment is None or not alignment.applied:
        return load
    return AlignedLoader(alignment, load)


class AlignedLoader:
    """``frame -> codes`` brought onto the reference.  A RAW frame resampled per CFA
    colour also leaves the spread of the samples each value was interpolated from
    (:func:`~hdrmerge_cli.core.resample.resample_mosaic`'s spread) for :class:`SampleWeights`.
    Each frame is resampled once: its resampled codes (and spread) are kept for every later
    pass (deghosting reads every frame twice, the merge and its re-weighting once each), in
    place of its decoded codes where ``load`` holds them (:class:`~hdrmerge_cli.io.frames.HeldCodes`)."""

    def __init__(self, alignment: Alignment, load=load_codes):
        self.load = load
        self.alignment = alignment
        self.periods = alignment.resampling == "cfa-periods"
        self.kept: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}
        self._lock = threading.Lock()

    def __call__(self, frame: Frame) -> np.ndarray:
        with self._lock:
            if id(frame) in self.kept:
                return self.kept[id(frame)][0]
        codes = self.load(frame)
        w = self.alignment.warp_of(frame)
        if is_identity(w):  # the reference: nothing to resample
            return codes
        clip = int(np.max(frame.white))
        spread = None
        if frame.kind != "raw":
            # full-resolution bilinear resampling of images: no tap variance (the taps' spread
            # is mostly the codes' noise and quantisation there, which the tables already hold)
            out = resample.apply_warp(codes, w, clip)
        else:
            cell = np.asarray(sample_pattern(frame)).ravel()  # black level per site of the 2 x 2 cell
            if self.periods:
                out = resample.shift_mosaic(codes, w)
            else:  # resampled colour by colour, with the taps' spread
                out, spread = resample.resample_mosaic(codes, w, clip, frame.cfa_pattern, np.asarray(frame.black)[cell],
                                                    spread=True)
        out.flags.writeable = False  # handed out again: read-only
        with self._lock:
            self.kept[id(frame)] = (out, spread)
        if isinstance(self.load, HeldCodes):  # the resampled codes are kept instead
            self.load.drop(frame)
        return out

    def spread(self, frame: Frame) -> np.ndarray | None:
        """The tap variance of the frame's resampled codes (coded,
        :func:`~hdrmerge_cli.core.resample.spread_code`), or None."""
        return self.kept[id(frame)][1] if id(frame) in self.kept else None


def is_identity(warp: np.ndarray) -> bool:
    """Whether a warp moves nothing (the reference's; no resampling)."""
    return bool(np.allclose(warp, np.hstack([np.eye(2), np.zeros((2, 1))]), rtol=0.0, atol=1e-9))


def _samples(codes: np.ndarray) -> np.ndarray:
    return codes.reshape(codes.shape[0], -1)


def _rows(frame: Frame, pattern: np.ndarray, channels: int) -> list[int]:
    """The table row of each channel of :func:`_planes`: an image's own channels, or the
    colours of a RAW mosaic's four CFA positions."""
    if frame.kind == "raw":
        return [int(pattern[dy, dx]) for dy in (0, 1) for dx in (0, 1)]
    return list(range(channels))


def _planes(frame: Frame, codes: np.ndarray, pattern: np.ndarray) -> list[tuple[np.ndarray, int]]:
    """(2-D plane, table row) per channel: an image's channels, or the four CFA positions
    of a RAW mosaic (one plane per position, one sample per 2 x 2 period)."""
    if frame.kind == "raw":
        planes = [codes[dy::2, dx::2] for dy in (0, 1) for dx in (0, 1)]
    else:
        codes = codes if codes.ndim == 3 else codes[..., None]
        planes = [codes[..., c] for c in range(codes.shape[-1])]
    return list(zip(planes, _rows(frame, pattern, len(planes))))


def _block_estimates(frame: Frame, codes: np.ndarray, pattern: np.ndarray, tables: list, b: int):
    """One frame's block estimates ``(h, w, C)`` (:func:`~hdrmerge_cli.core.deghost.block_statistics`
    per channel): x, its variance s, whether every sample of the block measures, and what a
    block whose samples are all dark (> 0) or all clipped (< 0) bounds (0 elsewhere)."""
    planes = _planes(frame, codes, pattern)
    shape = (planes[0][0].shape[0] // b, planes[0][0].shape[1] // b, len(planes))
    x, s, bound = (np.empty(shape, np.float32) for _ in range(3))
    ok = np.empty(shape, bool)
    for c, (plane, row) in enumerate(planes):
        deghost.block_statistics(plane, *tables[row], b, out=(x[..., c], s[..., c], ok[..., c], bound[..., c]))
    return x, s, ok, bound


def _untruncated(x: np.ndarray, s: np.ndarray, frame: Frame, pattern: np.ndarray, tables: list, b: int) -> np.ndarray:
    """Where a frame's block readings ``(h, w, C)`` lie more than 3 sample noise deviations
    inside its measuring range (per channel, the x of its lowest and highest measuring
    code): there no reading of a block was lost to black or to clipping, which biases the
    mean of those kept."""
    sd = np.sqrt(s) * np.float32(3 * b)
    out = np.empty(x.shape, bool)
    for c, row in enumerate(_rows(frame, pattern, x.shape[-1])):
        x_t, _, ok_t = tables[row]
        lo, hi = (x_t[ok_t][0], x_t[ok_t][-1]) if ok_t.any() else (np.inf, -np.inf)
        out[..., c] = (x[..., c] - sd[..., c] > lo) & (x[..., c] + sd[..., c] < hi)
    return out


def _ghost_tables(frame: Frame, exposure: float, crf: CRF, noise: list[NoiseParams] | None, linear: bool) -> list:
    """Per channel of ``frame``, :func:`~hdrmerge_cli.core.deghost.ghost_tables` (float32
    ``x`` and ``s``, bool ``ok`` per code); without ``noise``, the quantisation of half a
    code of an 8-bit range."""
    out = []
    for c in range(len(frame.black)):
        nz = noise[min(c, len(noise) - 1)] if noise else NoiseParams(
            (0.5 * float(frame.white[c] - frame.black[c]) / 255.0) ** 2, 1e-12, 0.0)
        x_t, s_t, ok_t = deghost.ghost_tables(frame.n_codes, frame.black[c], frame.white[c],
                                              lambda v, c=c: crf.inverse(v, 0 if linear else c), exposure, nz,
                                              footroom=linear)
        out.append((x_t.astype(np.float32), s_t.astype(np.float32), ok_t))
    return out


def find_ghosts(frames: list[Frame], exposures: np.ndarray, crf: CRF, noise: list[NoiseParams] | None, load,
                mode: str, p_fa: float | None = None, params: deghost.DeghostParams | None = None) -> Ghosts:
    """Per frame, the blocks inconsistent with the anchor (:func:`~hdrmerge_cli.core.deghost.ghost_masks`),
    cleaned and feathered.  ``noise``: one parameter set per channel (code units), or None
    (the codes' quantisation; :func:`~hdrmerge_cli.core.deghost.level_scale` measures the
    rest); ``params``: :data:`~hdrmerge_cli.core.deghost.RAW_PARAMS` or ``IMAGE_PARAMS`` by
    the frames' kind unless given, ``p_fa`` overriding its false-alarm rate.  Each frame is
    read twice (anchor, test).  Returns :class:`Ghosts`."""
    first = frames[0]
    raw = first.kind == "raw"
    params = params or (deghost.RAW_PARAMS if raw else deghost.IMAGE_PARAMS)
    if p_fa is not None:
        params = dataclasses.replace(params, p_fa=p_fa)
    pattern = sample_pattern(first)
    per_px = 2 if raw else 1  # pixels per cell side of the planes
    h, w = (first.height // 2, first.width // 2) if raw else (first.height, first.width)
    b = deghost.block_size(h, w)
    one_at_a_time = threading.Lock()  # Numba's workqueue layer runs one parallel kernel at a time

    def estimate(k: int) -> deghost.Blocks:
        t_k = _ghost_tables(frames[k], exposures[k], crf, noise, params.linear)
        with one_at_a_time:
            x, s, ok, bound = _block_estimates(frames[k], load(frames[k]), pattern, t_k, b)
        steady = (_untruncated(x, s, frames[k], pattern, t_k, b) & ok) if params.linear else ok
        return deghost.Blocks(x, s, ok, bound, steady)

    lin_hi = None
    if params.shoulder_code is not None:  # an image's reading near white bounds the light from below
        lin_hi = np.float32([crf.inverse(np.float64(params.shoulder_code), c) for c in range(len(first.black))])
    # two frames at a time where blocks are larger than a cell (one's test beside the other's
    # estimates); with blocks of one cell a test's temporaries are as large as the frame's samples
    fractions, masks = deghost.ghost_masks(estimate, np.asarray(exposures), reference_index(frames), params,
                                           b * per_px, lin_hi, workers=2 if b > 1 else 1)
    applied = deghost.applies(fractions, mode, params)
    log.info("deghosting (blocks of %d px): up to %.2f %% of a frame's blocks move; %s", b * per_px,
             100 * max(fractions), "applied" if applied else "not needed")
    hb, wb = masks[0].shape
    return Ghosts(mode, bool(applied), params.p_fa, b, (hb * b * per_px, wb * b * per_px),
                  [round(f, 6) for f in fractions], list(frames), masks)


@dataclasses.dataclass
class Ghosts:
    """What :func:`find_ghosts` found: per frame (in the order of ``frames``) a soft mask
    ``(h, w)`` uint8 over blocks of ``block`` x ``block`` pixels (RAW: CFA periods), 255 =
    dropped, covering the first ``covered`` = (rows, cols) samples; :meth:`mask_of` finds a
    frame's by identity.  ``applied``: whether the merge drops them."""

    mode: str
    applied: bool
    p_false_alarm: float
    block: int
    covered: tuple[int, int]
    rejected_fraction: list[float]
    frames: list[Frame]
    masks: list[np.ndarray]

    def mask_of(self, frame: Frame) -> np.ndarray:
        return _of_frame(frame, self.frames, self.masks)

    def image(self, height: int, width: int) -> np.ndarray:
        """The 'ghost' extra channel ``(height, width)`` float32: per pixel, the sum over
        frames of how much each is dropped (0 = none; all 0 when not applied)."""
        out = np.zeros((height, width), np.float32)
        if self.applied:
            for frame in self.frames:
                out += ghost_weight(self, frame, height, width)
        return out

    def summary(self) -> dict:
        """``merge --json``'s ``deghost``."""
        return {"mode": self.mode, "applied": self.applied, "p_false_alarm": self.p_false_alarm, "block": self.block,
                "covered": list(self.covered), "rejected_fraction": self.rejected_fraction}


def ghost_weight(ghosts: Ghosts, frame: Frame, height: int, width: int, rows: slice | None = None) -> np.ndarray:
    """The frame's soft rejection ``m`` in [0, 1] per pixel ``(height, width)`` float32
    (``rows``: those rows only): its block mask interpolated bilinearly (rows and columns
    beyond the blocks repeat the last ones)."""
    import cv2

    m = ghosts.mask_of(frame)
    ch, cw = ghosts.covered
    hb, wb = m.shape
    r0, r1, _ = (rows or slice(0, height)).indices(height)
    # pixel centre (x + 1/2) lands on block coordinate (x + 1/2) wb / cw - 1/2, as a resize
    # to the covered pixels reads it; beyond them the border repeats (one pass)
    sx, sy = wb / cw, hb / ch
    a = np.float64([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5 + sy * r0]])
    return cv2.warpAffine(m.astype(np.float32) * np.float32(1 / 255), a, (width, r1 - r0),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)


def covered(frame: Frame, warp: np.ndarray, periods: bool, rows: slice | None = None) -> np.ndarray:
    """Which pixels of the aligned frame come from inside it, ``(H, W)`` bool (``rows``:
    those rows only; a pixel's channels share its value); the others are stand-ins (the
    edge repeated) and get no weight in the merge.  ``periods``: a RAW frame moved by whole
    CFA periods."""
    h, w = frame.height, frame.width
    if frame.kind == "raw" and periods:  # whole CFA periods
        tx, ty = (2 * np.rint(warp[:, 2] / 2)).astype(int)
        inside = ((np.arange(h) + ty >= 0) & (np.arange(h) + ty <= h - 1))[rows or slice(None)]
        cols = (np.arange(w) + tx >= 0) & (np.arange(w) + tx <= w - 1)
        return inside[:, None] & cols[None, :]
    return resample.covered_mask(warp, h, w, rows)


def frame_validity(frames: list[Frame], alignment: Alignment | None) -> list:
    """Per frame, :func:`valid_pixels` in the reference's coordinates (by the alignment
    where it is applied)."""
    alignment = alignment if alignment is not None and alignment.applied else None
    return [valid_pixels(f, alignment.warp_of(f) if alignment else None) for f in frames]


def output_alpha(frames: list[Frame], validity: list) -> np.ndarray | None:
    """The merged image's alpha, ``(H, W)`` float32: per pixel the most any frame measured
    of it (:func:`frame_validity`); None when no frame has an alpha channel."""
    if all(f.alpha_channel is None for f in frames):
        return None
    h, w = frames[0].height, frames[0].width
    if any(v is None for v in validity):  # a frame measured all of every pixel
        return np.ones((h, w), np.float32)
    out = np.zeros((h, w), np.float32)
    for v in validity:
        np.maximum(out, v, out=out)
    return out


def sample_weights(tables, pattern, frames: list[Frame], ghosts: Ghosts | None, alignment: Alignment | None,
                   load=None, validity: list | None = None):
    """The per-sample weights of the merge (a :class:`SampleWeights`), or None when no
    frame has transparent pixels and neither the deghosting nor the alignment is applied.
    ``load``: the merge's :class:`AlignedLoader` (for the resampling spreads);
    ``validity``: :func:`frame_validity` (read here when not given)."""
    ghosts = ghosts if ghosts is not None and ghosts.applied else None
    alignment = alignment if alignment is not None and alignment.applied else None
    validity = validity if validity is not None else frame_validity(frames, alignment)
    if ghosts is None and alignment is None and all(v is None for v in validity):
        return None
    return SampleWeights(tables, pattern, frames, ghosts, alignment, load if isinstance(load, AlignedLoader) else None,
                         validity)


def valid_pixels(frame: Frame, warp: np.ndarray | None) -> np.ndarray | None:
    """How much of each pixel frame's alpha says it measured (:func:`load_validity`), in
    the reference frame's coordinates (brought there by ``warp``, nearest neighbour),
    ``(H, W)`` float32 in [0, 1], a weight of its readings; None: all of every pixel."""
    valid = load_validity(frame)
    if valid is None:
        return None
    log.info("%s: %.1f %% of its pixels are transparent (alpha 0) and carry no weight, %.1f %% partly", frame.path,
             100 * np.mean(valid == 0), 100 * np.mean((valid > 0) & (valid < 1)))
    if warp is None:
        return valid
    import cv2

    return cv2.warpAffine(valid, warp.astype(np.float32), (frame.width, frame.height),
                          flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


class SampleWeights:
    """``(k, codes) -> weights`` of frame ``k`` for the merge (see :meth:`LogMerge.add`):
    its table weight ``w(z) sigma^-2`` through :meth:`adjust`, which also re-weights the
    IRLS passes (:func:`~hdrmerge_cli.core.reconstruct.irls`)."""

    def __init__(self, tables, pattern, frames, ghosts, alignment, load, validity=None):
        self.tables, self.pattern, self.frames = tables, pattern, frames
        self.ghosts, self.alignment, self.load = ghosts, alignment, load
        self.validity = validity or [None] * len(frames)
        self.slopes: dict[int, np.ndarray] = {}  # per frame, its value table's slope

    def factor(self, k: int, rows: slice | None = None) -> np.ndarray | None:
        """``(H, W)`` float32 in [0, 1] per pixel (an image's channels share it), or None
        (all 1): zero where the aligned frame does not cover the reference or is
        transparent, ``1 - m`` in its rejected ghost cells (feathered ``m``, so no seam);
        ``rows``: those rows only."""
        frame, ghosts, alignment = self.frames[k], self.ghosts, self.alignment
        out = None
        if ghosts is not None and ghosts.mask_of(frame).any():
            out = ghost_weight(ghosts, frame, frame.height, frame.width, rows)
            np.subtract(np.float32(1.0), out, out=out)
        valid = self.validity[k]
        masks = [None if valid is None else valid[rows or slice(None)]]
        if alignment is not None:
            masks.append(covered(frame, alignment.warp_of(frame), alignment.resampling == "cfa-periods", rows))
        for inside in masks:
            if inside is not None:
                out = inside.astype(np.float32) if out is None else np.multiply(out, inside, out=out)
        return out

    def _weighted(self, k: int, codes: np.ndarray, w: np.ndarray | None, own: bool,
                  rows: slice | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """``w`` (None: the table's, for a resampled frame) with the resampling's variance
        added and times :meth:`factor` (broadcast over an image's channels), and the
        factor; ``own``: ``w`` may be overwritten (a fresh full-size array costs its page
        faults, tenths of a second at 24 MP); ``rows``: ``codes`` and ``w`` are those rows
        of the frame."""
        spread = self.load.spread(self.frames[k]) if self.load is not None else None
        if spread is not None:
            rows = rows or slice(0, spread.shape[0])
            if k not in self.slopes:
                self.slopes[k] = value_slope(self.tables[k])
            w, own = resampled_weight(w, self.tables[k], codes, self.pattern, _samples(spread[rows]),
                                      self.alignment.warp_of(self.frames[k]), out=w if own else None,
                                      cfa=self.frames[k].cfa_pattern, row0=rows.indices(spread.shape[0])[0],
                                      slope=self.slopes[k]), True
        f = self.factor(k, rows)
        if f is None:
            return w, None
        per_pixel = w.reshape(f.shape + (-1,))
        out = np.multiply(per_pixel, f[..., None], out=per_pixel if own else None)
        return out.reshape(w.shape), f

    def adjust(self, k: int, codes: np.ndarray, w: np.ndarray, own: bool = False,
               rows: slice | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Inverse-variance weights ``w`` (``(H, W')``) of frame ``k``'s ``codes`` with the
        resampling's variance added (:func:`resampled_weight`), times :meth:`factor`;
        returns ``(weights, factor)``, the factor per sample ``(H, W')``.  ``own``: the
        weights may be written into ``w`` (the caller's buffer, else left as it is);
        ``rows``: ``codes`` and ``w`` are those rows of the frame (a strip of the IRLS)."""
        out, f = self._weighted(k, codes, w, own=own, rows=rows)
        if f is not None and f.shape != out.shape:
            f = np.repeat(f, out.shape[1] // f.shape[1], axis=1)
        return out, f

    def __call__(self, k: int, codes: np.ndarray, rows: slice | None = None
                 ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``(weight, factor)`` for :meth:`LogMerge.add` of frame ``k``'s ``codes`` (``rows``:
        those rows of the frame): where the frame was not resampled with a spread (images;
        RAW moved by whole CFA periods) only the per-pixel :meth:`factor` (weight None),
        which the merge applies to the table's weights in its own pass; else the per-sample
        weights (``codes``' shape, float32) with the factor in them, and the factor, which
        then only says where the frame is a sample's own."""
        if self.load is None or self.load.spread(self.frames[k]) is None:
            return None, self.factor(k, rows)
        w, f = self._weighted(k, codes, None, own=True, rows=rows)  # the table's weights, read in the same pass
        return w.reshape(codes.shape).astype(np.float32, copy=False), f


def resampled_weight(w: np.ndarray | None, tables, codes: np.ndarray, pattern, spread: np.ndarray,
                     warp: np.ndarray, out: np.ndarray | None = None, cfa: str | None = None,
                     row0: int = 0, slope: np.ndarray | None = None) -> np.ndarray:
    """Inverse-variance weights ``w`` (``(H, W)``; None: the table's) of the samples of a
    mosaic resampled by ``warp`` with the interpolation's variance added
    (:func:`~hdrmerge_cli.core.resample.resampled_weight_mosaic`), from the frame's
    ``tables``: the slope of its value table (linear or log value per code) and its
    certainty ``w(z)`` (``slope``: :func:`value_slope`, computed when not given).  ``out``
    may be ``w``; ``row0``: the arrays are rows ``row0`` on of the frame."""
    slope = value_slope(tables) if slope is None else slope
    return resample.resampled_weight_mosaic(w, codes, pattern, slope, tables.certainty, tables.n_codes, spread, warp,
                                         out, weight=tables.weight, cfa=cfa, row0=row0)


def value_slope(tables) -> np.ndarray:
    """The slope of a frame's value table per code (flattened ``(R * N,)`` float32), for
    :func:`resampled_weight`."""
    n = tables.n_codes
    return np.gradient(tables.value.reshape(-1, n).astype(np.float64), axis=1).astype(np.float32).ravel()


def require_noise(noise, frames) -> list[NoiseParams] | None:
    """Noise parameters for the ghost test: the given (or the merge's measured) ones, else
    None: the test then starts from the codes' quantisation and measures what that leaves
    out on the frames themselves (:func:`~hdrmerge_cli.core.deghost.level_scale`), which
    costs nothing like a noise calibration of the whole bracket."""
    if noise:
        from hdrmerge_cli.io.noisespec import per_channel

        return per_channel(noise, frames[0].channel_names)
    return None
