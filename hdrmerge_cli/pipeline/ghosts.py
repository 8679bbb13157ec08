"""The ghosts stage (``merge --deghost``): per frame, the blocks inconsistent with the
reference frame (moving objects), cleaned and feathered (:func:`find_ghosts`, on
:mod:`hdrmerge_cli.core.deghost`)."""
from __future__ import annotations

import dataclasses
import logging
import threading
from typing import TYPE_CHECKING

import numpy as np

from hdrmerge_cli.core import deghost
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.io.frames import Frame
from hdrmerge_cli.io.metadata import of_frame, reference_index, sample_pattern

if TYPE_CHECKING:
    from hdrmerge_cli.pipeline.choices import Decision

log = logging.getLogger("hdrmerge_cli")


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


def _block_estimates(frame: Frame, codes: np.ndarray, pattern: np.ndarray, tables: list[deghost.CodeTable],
                     b: int) -> deghost.Blocks:
    """One frame's :class:`~hdrmerge_cli.core.deghost.Blocks` ``(h, w, C)``
    (:func:`~hdrmerge_cli.core.deghost.block_statistics` per channel), every block
    ``steady`` (:func:`_untruncated` narrows that for linear data)."""
    planes = _planes(frame, codes, pattern)
    shape = (planes[0][0].shape[0] // b, planes[0][0].shape[1] // b, len(planes))
    x, s, bound = (np.empty(shape, np.float32) for _ in range(3))
    ok = np.empty(shape, bool)
    for c, (plane, row) in enumerate(planes):
        deghost.block_statistics(plane, tables[row], b, (x[..., c], s[..., c], ok[..., c], bound[..., c]))
    return deghost.Blocks(x, s, ok, bound, ok)


def _untruncated(blocks: deghost.Blocks, frame: Frame, pattern: np.ndarray, tables: list[deghost.CodeTable],
                 b: int) -> np.ndarray:
    """Where a frame's block readings ``(h, w, C)`` lie more than 3 sample noise deviations
    inside its measuring range (per channel, the x of its lowest and highest measuring
    code): there no reading of a block was lost to black or to clipping, which biases the
    mean of those kept."""
    x = blocks.x
    sd = np.sqrt(blocks.s) * np.float32(3 * b)
    out = np.empty(x.shape, bool)
    for c, row in enumerate(_rows(frame, pattern, x.shape[-1])):
        lo, hi = tables[row].measuring()
        lo, hi = (tables[row].x[lo], tables[row].x[hi]) if hi >= 0 else (np.inf, -np.inf)
        out[..., c] = (x[..., c] - sd[..., c] > lo) & (x[..., c] + sd[..., c] < hi)
    return out


def _ghost_tables(frame: Frame, exposure: float, crf: CRF, noise: list[NoiseParams] | None,
                  linear: bool) -> list[deghost.CodeTable]:
    """Per channel of ``frame``, :func:`~hdrmerge_cli.core.deghost.ghost_tables` (float32
    ``x`` and ``s``); without ``noise``, the quantisation of half a code of an 8-bit range."""
    lin = crf.codes_table(frame.n_codes, frame.black, frame.white)
    out = []
    for c in range(len(frame.black)):
        nz = noise[min(c, len(noise) - 1)] if noise else NoiseParams(
            (0.5 * float(frame.white[c] - frame.black[c]) / 255.0) ** 2, 1e-12, 0.0)
        x_t, s_t, ok_t = deghost.ghost_tables(frame.n_codes, frame.black[c], frame.white[c], lin[c], exposure, nz,
                                              footroom=linear)
        out.append(deghost.CodeTable(x_t.astype(np.float32), s_t.astype(np.float32), ok_t))
    return out


def find_ghosts(frames: list[Frame], exposures: np.ndarray, crf: CRF, noise: list[NoiseParams] | None, load,
                p_fa: float | None = None, params: deghost.DeghostParams | None = None) -> Ghosts:
    """Per frame, the blocks inconsistent with the anchor (:func:`~hdrmerge_cli.core.deghost.ghost_masks`),
    cleaned and feathered.  ``noise``: one parameter set per channel (code units), or None
    (the codes' quantisation; :func:`~hdrmerge_cli.core.deghost.level_scale` measures the
    rest); ``params``: :data:`~hdrmerge_cli.core.deghost.RAW_PARAMS` or ``IMAGE_PARAMS`` by
    the frames' kind unless given, ``p_fa`` overriding its false-alarm rate.  Each frame is
    read twice (anchor, test).  Returns :class:`Ghosts` as found, not yet applied
    (:func:`~hdrmerge_cli.pipeline.choices.choose_deghost` decides that)."""
    first = frames[0]
    raw = first.kind == "raw"
    params = params or (deghost.RAW_PARAMS if raw else deghost.IMAGE_PARAMS)
    if p_fa is not None:
        params = dataclasses.replace(params, p_fa=p_fa)
    pattern = sample_pattern(first)
    per_px = 2 if raw else 1  # pixels per cell side of the planes
    h, w = (first.height // 2, first.width // 2) if raw else (first.height, first.width)
    b = deghost.block_size(h, w)
    tables = [_ghost_tables(f, e, crf, noise, params.linear) for f, e in zip(frames, exposures)]
    one_at_a_time = threading.Lock()  # Numba's workqueue layer runs one parallel kernel at a time

    def estimate(k: int) -> deghost.Blocks:
        with one_at_a_time:
            blocks = _block_estimates(frames[k], load(frames[k]), pattern, tables[k], b)
        if params.linear:
            blocks = blocks._replace(steady=_untruncated(blocks, frames[k], pattern, tables[k], b) & blocks.ok)
        return blocks

    lin_hi = None
    if params.shoulder_code is not None:  # an image's reading near white bounds the light from below
        lin_hi = np.float32([crf.inverse(np.float64(params.shoulder_code), c) for c in range(len(first.black))])
    # two frames at a time where blocks are larger than a cell (one's test beside the other's
    # estimates); with blocks of one cell a test's temporaries are as large as the frame's samples
    found = deghost.ghost_masks(estimate, np.asarray(exposures), reference_index(frames), params, b * per_px, lin_hi,
                                workers=2 if b > 1 else 1)
    hb, wb = found[0].mask.shape
    fractions = [m.fraction for m in found]
    return Ghosts(mode=None, applied=False, p_false_alarm=params.p_fa, block=b,
                  covered=(hb * b * per_px, wb * b * per_px), rejected_fraction=[round(f, 6) for f in fractions],
                  frames=list(frames), masks=[m.mask for m in found], per_px=per_px, largest=max(fractions))


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


def require_noise(noise, frames) -> list[NoiseParams] | None:
    """Noise parameters for the ghost test: the given (or the merge's measured) ones, else
    None: the test then starts from the codes' quantisation and measures what that leaves
    out on the frames themselves (:func:`~hdrmerge_cli.core.deghost.level_scale`), which
    costs nothing like a noise calibration of the whole bracket."""
    if noise:
        from hdrmerge_cli.io.noisespec import per_channel

        return per_channel(noise, frames[0].channel_names)
    return None
