"""The ghosts stage (``merge --deghost``): per frame, the blocks inconsistent with the
reference frame (moving objects), cleaned and feathered (:func:`find_ghosts`, on
:mod:`hdrmerge_cli.core.deghost`)."""
from __future__ import annotations

import dataclasses
import logging
from typing import TYPE_CHECKING

import numpy as np

from hdrmerge_cli.core import deghost
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.io.frames import Frame
from hdrmerge_cli.io.metadata import of_frame, reference_index
from hdrmerge_cli.io.noisespec import per_channel

if TYPE_CHECKING:
    from hdrmerge_cli.pipeline.choices import Decision

log = logging.getLogger("hdrmerge_cli")


def find_ghosts(frames: list[Frame], exposures: np.ndarray, pattern: np.ndarray, crf: CRF,
                noise: dict[str, NoiseParams] | None, load, params: deghost.DeghostParams | None = None) -> Ghosts:
    """Per frame, the blocks inconsistent with the anchor, cleaned and feathered
    (:func:`~hdrmerge_cli.core.deghost.ghost_masks`, one call).  ``pattern``: the bracket's
    table row of each sample (:func:`~hdrmerge_cli.io.metadata.sample_pattern`);
    ``noise``: the given (or the merge's measured) parameters per channel name, or None:
    the test then starts from the codes' quantisation and measures what that leaves out on
    the frames themselves (:func:`~hdrmerge_cli.core.deghost.level_scale`), which costs
    nothing like a noise calibration of the whole bracket; ``load(frame)``: its codes (read
    twice, anchor and test); ``params``: :data:`~hdrmerge_cli.core.deghost.RAW_PARAMS` or
    ``IMAGE_PARAMS`` by the frames' kind unless given.  Returns :class:`Ghosts` as found,
    not yet applied (:func:`~hdrmerge_cli.pipeline.choices.choose_deghost` decides that)."""
    first = frames[0]
    params = params or (deghost.RAW_PARAMS if first.kind == "raw" else deghost.IMAGE_PARAMS)
    lin = [crf.codes_table(f.n_codes, f.black, f.white) for f in frames]
    lin_hi = None
    if params.shoulder_code is not None:  # an image's reading near white bounds the light from below
        lin_hi = np.float32([crf.inverse(np.float64(params.shoulder_code), c) for c in range(len(first.black))])
    found = deghost.ghost_masks(lambda k: load(frames[k]), lin, [f.black for f in frames], [f.white for f in frames],
                                np.asarray(exposures), per_channel(noise, first.channel_names) if noise else None,
                                pattern, (first.height, first.width), reference_index(frames), params, lin_hi)
    fractions = [m.fraction for m in found.frames]
    hb, wb = found.frames[0].mask.shape
    side = found.block * found.per_px
    return Ghosts(mode=None, applied=False, p_false_alarm=params.p_fa, block=found.block, covered=(hb * side, wb * side),
                  rejected_fraction=[round(f, 6) for f in fractions], frames=list(frames),
                  masks=[m.mask for m in found.frames], per_px=found.per_px, largest=max(fractions))


@dataclasses.dataclass
class Ghosts:
    """What :func:`find_ghosts` found: per frame (in the order of ``frames``) a soft mask
    ``(h, w)`` uint8 over blocks of ``block`` x ``block`` pixels (RAW: CFA periods), 255 =
    dropped, covering the first ``covered`` = (rows, cols) samples; :meth:`mask_of` finds a
    frame's by identity.  ``mode``, ``applied`` (whether the merge drops them) and
    ``decision`` are set by the choice made on it
    (:func:`~hdrmerge_cli.pipeline.choices.choose_deghost`); ``largest``: the largest
    rejected fraction, unrounded; ``per_px``: pixels per block cell side (RAW 2)."""

    mode: str
    applied: bool
    p_false_alarm: float
    block: int
    covered: tuple[int, int]
    rejected_fraction: list[float]
    frames: list[Frame]
    masks: list[np.ndarray]
    per_px: int = 1
    largest: float = 0.0
    decision: Decision | None = None

    def report(self) -> None:
        """The log line of a chosen deghosting."""
        log.info("deghosting (blocks of %d px): up to %.2f %% of a frame's blocks move; %s", self.block * self.per_px,
                 100 * self.largest, "applied" if self.applied else "not needed")

    def mask_of(self, frame: Frame) -> np.ndarray:
        return of_frame(frame, self.frames, self.masks)

    def image(self, height: int, width: int) -> np.ndarray:
        """The 'ghost' extra channel ``(height, width)`` float32: per pixel, the sum over
        frames of how much each is dropped (0 = none; all 0 when not applied)."""
        out = np.zeros((height, width), np.float32)
        if self.applied:
            for frame in self.frames:
                out += self.weight(frame, height, width)
        return out

    def weight(self, frame: Frame, height: int, width: int, rows: slice | None = None) -> np.ndarray:
        """The frame's soft rejection ``m`` in [0, 1] per pixel ``(height, width)`` float32
        (``rows``: those rows only): its block mask interpolated bilinearly (rows and
        columns beyond the blocks repeat the last ones)."""
        import cv2

        m = self.mask_of(frame)
        ch, cw = self.covered
        hb, wb = m.shape
        r0, r1, _ = (rows or slice(0, height)).indices(height)
        # pixel centre (x + 1/2) lands on block coordinate (x + 1/2) wb / cw - 1/2, as a resize
        # to the covered pixels reads it; beyond them the border repeats (one pass)
        sx, sy = wb / cw, hb / ch
        a = np.float64([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5 + sy * r0]])
        return cv2.warpAffine(m.astype(np.float32) * np.float32(1 / 255), a, (width, r1 - r0),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)

    def summary(self) -> dict:
        """``merge --json``'s ``deghost``."""
        return {"mode": self.mode, "applied": self.applied, "p_false_alarm": self.p_false_alarm, "block": self.block,
                "covered": list(self.covered), "rejected_fraction": self.rejected_fraction}
