"""The registration stage (``merge --align``): the warps that bring hand-held frames onto
the reference frame (:func:`estimate_alignment`, on :mod:`hdrmerge_cli.core.registration`),
the frames' codes brought there once (:class:`AlignedLoader`, on
:mod:`hdrmerge_cli.core.resample`), and what each aligned frame covers."""
from __future__ import annotations

import dataclasses
import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from hdrmerge_cli.core import registration, resample
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.frames import Frame, HeldCodes, bracket_label, load_codes
from hdrmerge_cli.io.metadata import reference_index, sample_pattern
from hdrmerge_cli.pipeline.records import Alignment, RegistrationPlan


log = logging.getLogger("hdrmerge_cli")


def _linear(frame: Frame, codes: np.ndarray, crf: CRF) -> np.ndarray:
    """The frame's :func:`~hdrmerge_cli.core.registration.registration_image`."""
    return registration.registration_image(codes, crf, frame.kind == "raw", float(np.mean(frame.black)),
                                           float(np.mean(frame.white)), frame.n_codes)


def _coarse_linear(frame: Frame, codes: np.ndarray, f: int) -> np.ndarray:
    """A RAW frame's :func:`~hdrmerge_cli.core.registration.coarse_mosaic_image`."""
    return registration.coarse_mosaic_image(codes, float(np.mean(frame.black)), float(np.mean(frame.white)), f)


def estimate_alignment(frames: list[Frame], exposures: np.ndarray, crf: CRF, plan: RegistrationPlan,
                       load=load_codes) -> Alignment:
    """Warps bringing every frame onto the reference (``core.registration``), fitting
    ``plan.motion``.  A pair is registered when both frames have texture in the irradiance
    range they share (:func:`~hdrmerge_cli.core.registration.registrable`: a count of
    pixels, however small a fraction of the frame), and the result is kept when its
    correlation reaches :data:`~hdrmerge_cli.core.registration.MIN_CONFIDENCE`.  When the plan screens the pairs
    (``--align auto``), each pair is first tested at coarse resolution (the level the
    texture test measures at): a pair without texture there is left unaligned, one found
    still (:func:`~hdrmerge_cli.core.registration.still_test`, at ``plan.tolerance_px``
    divided by the frame's steps from the reference, so the chained warp stays within it)
    is not registered at full resolution: an image keeps the coarse translation estimate, a
    RAW frame its neighbour's warp (no correction below the tolerance is worth resampling a
    mosaic colour by colour).  A pair registered in full then keeps its warp only where its
    displacement exceeds what the pair can tell from no motion
    (:func:`~hdrmerge_cli.core.registration.displacement_margin`): a displacement the
    bracket does not pin is not applied.  Returns an :class:`Alignment` as found, not yet
    applied (:func:`~hdrmerge_cli.pipeline.choices.choose_alignment` decides that)."""
    ref = reference_index(frames)
    found = _Registrar(frames, exposures, crf, plan, ref, load).run()
    steps = found.steps
    warps = [None] * len(frames)
    warps[ref] = np.eye(2, 3)
    unaligned = []
    for j in found.sides[0] + found.sides[1]:
        if steps[j].why is not None:
            unaligned.append(frames[j].path)
        warps[j] = registration.compose(steps[j].warp, warps[j - 1 if j > ref else j + 1])
    left = {j: steps[j].why for j in sorted(steps) if steps[j].why is not None}  # in frame order
    return Alignment(mode=None, motion=plan.motion, resampling="none", reference=frames[ref].path, applied=False,
                     frames=list(frames), warps=warps, confidence=found.confidence, unaligned=unaligned,
                     still=[frames[j].path for j in sorted(found.still)], left=left)



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


class Step(NamedTuple):
    """One frame's step: the ``(2, 3)`` float64 warp from its neighbour towards the
    reference to it, and why it is left unaligned (None: it is not)."""

    warp: np.ndarray
    why: str | None


@dataclasses.dataclass
class _Steps:
    """What :class:`_Registrar` hands :func:`estimate_alignment`."""

    #: per frame ``j`` other than the reference, its :class:`Step`
    steps: dict[int, Step]
    #: the frame indices of each side of the reference, outwards (after it, before it)
    sides: list[list[int]]
    #: per frame, its registration's correlation to its neighbour (1 for the reference)
    confidence: list[float]
    #: the frames found still (coarse test, or a displacement the pair does not pin), as found
    still: list[int]


class _Registrar:
    """The steps of :func:`estimate_alignment` on one bracket: each frame registered to its
    neighbour towards the reference; each frame's registration image made once per
    resolution (coarse, full) and shared by the pairs and the two sides' threads that read it."""

    def __init__(self, frames: list[Frame], exposures: np.ndarray, crf: CRF, plan: RegistrationPlan, ref: int,
                 load):
        self.frames, self.exposures, self.crf, self.load = frames, exposures, crf, load
        self.plan, self.motion, self.ref = plan, plan.motion, ref
        self.raw = frames[0].kind == "raw"
        self.identity = np.eye(2, 3)
        self.confidence = [1.0] * len(frames)
        self.judged_still: list[int] = []
        self.scale = registration.coarse_factor(frames[0].height, frames[0].width, 2 if self.raw else 1)
        self._small: dict[int, np.ndarray] = {}
        self._full: dict[int, np.ndarray] = {}
        self._making = {k: threading.RLock() for k in range(len(frames))}
        # the pairs that may read each frame's full-resolution image: its own step and its
        # outward neighbour's (the reference: each side's first); dropped after the last
        self._uses = [0] * len(frames)
        for j in range(len(frames)):
            if j != ref:
                self._uses[j] += 1
                self._uses[j - 1 if j > ref else j + 1] += 1

    def image(self, k: int) -> np.ndarray:
        """Frame k's full-resolution registration image (:func:`_linear`), made once and held
        until the last pair that reads it is done (:meth:`done`)."""
        with self._making[k]:
            if k not in self._full:
                self._full[k] = _linear(self.frames[k], self.load(self.frames[k]), self.crf)
            return self._full[k]

    def done(self, *pair: int) -> None:
        """The pair's step is found: a full-resolution image no other pair reads is dropped."""
        for k in pair:
            with self._making[k]:
                self._uses[k] -= 1
                if self._uses[k] == 0:
                    self._full.pop(k, None)

    def coarse(self, k: int) -> np.ndarray:
        """Frame k's registration image reduced as the texture test reduces it (block means:
        a RAW frame's from its codes, :func:`_coarse_linear`; an image's from its full
        registration image, :meth:`image`); made once, the reference's for both sides."""
        with self._making[k]:
            if k not in self._small:
                self._small[k] = (_coarse_linear(self.frames[k], self.load(self.frames[k]), self.scale) if self.raw
                                  else registration.block_mean(self.image(k), self.scale))
            return self._small[k]

    def log_pair(self, a: int, b: int, image) -> tuple[np.ndarray, np.ndarray] | None:
        """Frames a's and b's ``image`` as log irradiance over the range both expose well
        (:func:`~hdrmerge_cli.core.registration.log_irradiance`), or None when there is none."""
        shared = _shared_range(self.frames[a], self.exposures[a], self.exposures[b])
        if shared is None:
            return None
        lo, hi = shared
        return (registration.log_irradiance(image(a), self.exposures[a], lo, hi),
                registration.log_irradiance(image(b), self.exposures[b], lo, hi))

    def step(self, a: int, b: int) -> Step:
        """Warp from frame a's coordinates to frame b's (neighbours in exposure), or the
        identity and why they cannot be registered."""
        pair = self.log_pair(a, b, self.image)
        if pair is None:
            return Step(self.identity, "no irradiance range is well exposed in both it and its neighbour")
        ia, ib = pair
        why = registration.registrable(ia, ib)
        if why is not None:
            return Step(self.identity, f"{why} in the range it shares with its neighbour")
        w, rho = registration.estimate_warp(ia, ib, self.motion)
        self.confidence[b] = round(rho, 4)
        if rho < registration.MIN_CONFIDENCE:
            return Step(self.identity, f"registration to its neighbour correlates only {rho:.2f}")
        # RAW: found on 2 x 2 cells (centre 2u + 0.5)
        return Step(registration.rescale_warp(w, 2, 0.5) if self.raw else w, None)

    def still(self, a: int, b: int, pair: tuple[np.ndarray, np.ndarray] | None) -> Step | None:
        """When screening: the step from frame a to b at coarse resolution (``pair``, their
        :meth:`coarse` :meth:`log_pair`) when the pair is still
        (:func:`~hdrmerge_cli.core.registration.still_test`, the plan's tolerance shared by
        the steps between b and the reference), else None."""
        if pair is None:
            return None
        ia, ib = pair
        why = registration.registrable(ia, ib, self.scale // (2 if self.raw else 1))
        if why is not None:  # the texture test measures at this level
            return Step(self.identity, f"{why} in the range it shares with its neighbour")
        frame = self.frames[b]
        tol = self.plan.tolerance_px / abs(b - self.ref)
        is_still, w, bound, rho = registration.still_test(ia, ib, self.scale, frame.height, frame.width, tol)
        if not is_still:
            log.info("%s: may be displaced from its neighbour by %.3f px or more (coarse test); registered at full "
                     "resolution", frame.path, tol)
            return None
        self.confidence[b] = round(rho, 4)
        log.info("%s: still against its neighbour (coarse test: displaced at most %.3f px at %g confidence, by "
                 "(%.3f, %.3f) px as estimated); not registered at full resolution", frame.path, bound,
                 1 - registration.STILL_P_MISS, w[0, 2], w[1, 2])
        self.judged_still.append(b)
        if rho < registration.MIN_CONFIDENCE:
            return Step(self.identity, f"its still test correlates only {rho:.2f} with its neighbour")
        # RAW: within the tolerance at the test's confidence the frame stays where its
        # neighbour is: resampling a mosaic colour by colour for an estimate of a few
        # hundredths of a pixel costs more than it corrects (a colour's 2-px pitch, the taps'
        # spread in the weights, clipped taps near white)
        return Step(self.identity if self.raw else w, None)

    def pinned(self, b: int, w: np.ndarray, pair: tuple[np.ndarray, np.ndarray]) -> bool:
        """When screening: whether the registered step to frame b moves it by more than the
        pair can tell from no motion (:func:`~hdrmerge_cli.core.registration.displacement_margin`
        on the coarse ``pair``, as :meth:`still` read it)."""
        frame = self.frames[b]
        size = registration.warp_size(w, frame.height, frame.width)
        ia, ib = pair
        margin = registration.displacement_margin(ia, ib, w, self.scale, frame.height, frame.width)
        if size > margin:
            return True
        log.info("%s: registered %.2f px from its neighbour, within the %.2f px the pair cannot tell from no "
                 "motion; not moved", frame.path, size, margin)
        self.judged_still.append(b)
        return False

    def chain(self, indices: list[int]) -> dict[int, Step]:
        """The steps of one side of the reference, outwards (``{j: Step}``): when
        screening, a step found still at coarse resolution is not registered at full
        resolution, and a registered one is kept only where the pair pins it (:meth:`pinned`)."""
        auto = self.plan.screen
        out = {}
        for j in indices:
            a = j - 1 if j > self.ref else j + 1
            coarse = self.log_pair(a, j, self.coarse) if auto else None  # read by the still test and the margin
            out[j] = (auto and self.still(a, j, coarse)) or self.step(a, j)
            if auto and out[j].why is None and j not in self.judged_still and not self.pinned(j, out[j].warp, coarse):
                out[j] = Step(self.identity, None)
            self.done(a, j)
        return out

    def run(self) -> _Steps:
        """Every frame's step, both sides of the reference (:class:`_Steps`)."""
        # each frame is registered to its neighbour towards the reference (they share the most
        # well-exposed range) and the warps are chained: W_j = step(j -+ 1, j) o W_(j -+ 1).  The
        # two sides of the reference run on two threads (OpenCV's ECC releases the GIL)
        sides = [list(range(self.ref + 1, len(self.frames))), list(range(self.ref - 1, -1, -1))]
        with ThreadPoolExecutor(2) as pool:
            steps = {j: st for side in pool.map(self.chain, [s for s in sides if s]) for j, st in side.items()}
        return _Steps(steps, sides, self.confidence, self.judged_still)


def loader(alignment: Alignment | None, load=load_codes):
    """``frame -> codes`` (``load``), brought onto the reference when the alignment is
    applied (an :class:`AlignedLoader`)."""
    if alignment is None or not alignment.applied:
        return load
    return AlignedLoader(alignment, load)


class AlignedLoader:
    """``frame -> codes`` brought onto the reference.  A RAW frame resampled per CFA
    colour also leaves the spread of the samples each value was interpolated from
    (:func:`~hdrmerge_cli.core.resample.resample_mosaic`'s spread) for the merge's
    :class:`~hdrmerge_cli.pipeline.merge.SampleWeights`.
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
    return bool(np.allclose(warp, np.eye(2, 3), rtol=0.0, atol=1e-9))


def frame_validity(frames: list[Frame], alignment: Alignment | None, codes: HeldCodes) -> list:
    """Per frame, :func:`valid_pixels` of its alpha (``codes.validity``) in the reference's
    coordinates (by the alignment where it is applied).  A bracket transparent everywhere in
    every frame measures nothing: refused (HdrMergeError)."""
    alignment = alignment if alignment is not None and alignment.applied else None
    validity = [valid_pixels(f, codes.validity(f), alignment.warp_of(f) if alignment else None) for f in frames]
    if all(v is not None and not v.any() for v in validity):
        where = bracket_label(frames)
        raise HdrMergeError(f"{where}: every pixel is transparent (alpha 0) in every frame, so no frame measures "
                            "any light and there is nothing to merge")
    return validity


def valid_pixels(frame: Frame, valid: np.ndarray | None, warp: np.ndarray | None) -> np.ndarray | None:
    """How much of each pixel the frame's alpha says it measured (``valid``, :func:`~hdrmerge_cli.io.frames.decode`),
    in the reference frame's coordinates (brought there by ``warp``, nearest neighbour),
    ``(H, W)`` float32 in [0, 1], a weight of its readings; None: all of every pixel."""
    if valid is None:
        return None
    log.info("%s: %.1f %% of its pixels are transparent (alpha 0) and carry no weight, %.1f %% partly", frame.path,
             100 * np.mean(valid == 0), 100 * np.mean((valid > 0) & (valid < 1)))
    if warp is None:
        return valid
    import cv2

    return cv2.warpAffine(valid, warp.astype(np.float32), (frame.width, frame.height),
                          flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


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
