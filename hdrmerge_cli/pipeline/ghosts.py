"""The ghosts stage (``merge --deghost``): per frame, the blocks inconsistent with the
reference frame (moving objects), cleaned and feathered (:func:`find_ghosts`, on
:mod:`hdrmerge_cli.core.deghost`)."""
from __future__ import annotations

import logging

import numpy as np

from hdrmerge_cli.core import deghost
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.io.frames import Frame
from hdrmerge_cli.io.metadata import reference_index
from hdrmerge_cli.io.noisespec import per_channel
from hdrmerge_cli.pipeline.records import Ghosts


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

