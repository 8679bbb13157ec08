"""What the merge's stages return and the :class:`Bracket` carries: the records every stage
may read (a stage imports this module, never another stage).

* :class:`Bracket`: what was read, and each stage's result as the runner sets it;
* :class:`Decision`: one automatic choice as it was made (:mod:`~hdrmerge_cli.pipeline.choices`);
* :class:`RegistrationPlan`, :class:`Alignment`: what the registration stage measures and finds;
* :class:`Ghosts`: what the ghosts stage finds;
* :class:`Models`: what the merge reconstructs with (the choices' tables)."""
from __future__ import annotations

import dataclasses
import functools
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from hdrmerge_cli.core import registration, resample
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.io.frames import Frame, HeldCodes
from hdrmerge_cli.io.metadata import (
    equal_exposure_groups, exposure_values, of_frame, output_orientation, reference_exposure, sample_pattern,
)
from hdrmerge_cli.io.noisespec import iso_key, per_channel

if TYPE_CHECKING:
    from hdrmerge_cli.core.samples import Samples

log = logging.getLogger("hdrmerge_cli")


@dataclass(frozen=True)
class Decision:
    """One choice of a merge, as it was made.

    value : what was chosen
    measured : whether a measurement of the bracket decided it (False: the option was
        given, or the choice follows from the bracket's kind and the other choices)
    reason : why, in one line
    statistic, threshold : the measured number and the value it was held against (one unit)
    uncertainty : the statistic's standard error, where measured
    effect_db : the choice's effect on the merge's predicted error (dB), where measured
    """

    value: object
    measured: bool
    reason: str
    statistic: float | None = None
    threshold: float | None = None
    uncertainty: float | None = None
    effect_db: float | None = None

    def summary(self) -> dict:
        """``merge --json``'s record: the fields that are set (numbers rounded to 6 digits)."""
        out = {"value": self.value, "measured": self.measured, "reason": self.reason}
        for name in ("statistic", "threshold", "uncertainty", "effect_db"):
            v = getattr(self, name)
            if v is not None and np.isfinite(v):
                out[name] = round(float(v), 6)
        return out


@dataclass(frozen=True)
class RegistrationPlan:
    """What the registration stage measures (:func:`registration_plan`).

    motion : the model fitted, ``translation`` or ``similarity``
    screen : each pair is tested before its step is kept: a pair found still at coarse
        resolution (within ``tolerance_px`` shared by the steps to the reference) is not
        registered in full, and a registered step is kept only where the pair pins it
    tolerance_px : the displacement below which a frame counts as still (pixels)
    """

    motion: str
    screen: bool
    tolerance_px: float


@dataclasses.dataclass
class Alignment:
    """What :func:`estimate_alignment` found: per frame (the lists in the order of
    ``frames``) its warp onto the reference, ``(2, 3)`` float64 in the frame's own sample
    coordinates; :meth:`warp_of` finds a frame's by identity, whatever order the frames are
    in later (``--times estimate`` may re-sort them).  ``mode``, ``motion``, ``resampling``,
    ``applied`` and ``decision`` are set by the choice made on it
    (:func:`~hdrmerge_cli.pipeline.choices.choose_alignment`; as found: the model fitted,
    nothing applied).

    mode : the ``--align`` mode; motion : ``translation`` or ``similarity``
    resampling : RAW ``cfa-periods`` or ``per-colour``; images ``none``
    reference : the reference frame's path; applied : whether the merge moves the frames
    confidence : each registration's correlation to its neighbour (1 for the reference)
    unaligned, still : paths of the frames left unaligned, and found still at coarse resolution
    left : by frame index, why a frame is left unaligned
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
    left: dict[int, str] = dataclasses.field(default_factory=dict)
    decision: Decision | None = None

    def report(self) -> None:
        """The log lines of a chosen alignment: each frame left unaligned (a warning when
        alignment was asked for or the others moved, a hand-held bracket; only logged under
        ``auto`` on a bracket where nothing registered moved: a tripod, or frames too far apart
        in exposure to share tones), the largest displacement, and the share of the image
        outside some moved frame."""
        say = log.warning if self.applied else log.info
        for j, why in self.left.items():
            say("%s: %s; left unaligned", self.frames[j].path, why)
        log.info("alignment (%s): largest displacement %.2f px; %s", self.motion, max(self.sizes),
                 "applied" if self.applied else "not needed")
        if self.applied:
            share = self.covered_by_every_frame()
            if share < 1:
                log.info("alignment: %.1f %% of the image lies outside some moved frame and is measured by fewer "
                         "frames (its borders)", 100 * (1 - share))

    def warp_of(self, frame: Frame) -> np.ndarray:
        return of_frame(frame, self.frames, self.warps)

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
        for f in self.frames:
            inside = self.coverage(f)
            every = inside if every is None else every & inside
        return every

    def coverage(self, frame: Frame, rows: slice | None = None) -> np.ndarray:
        """Which pixels of the aligned ``frame`` come from inside it (:func:`covered`),
        ``(H, W)`` bool (``rows``: those rows only)."""
        return covered(frame, self.warp_of(frame), self.resampling == "cfa-periods", rows)

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


def covered(frame: Frame, warp: np.ndarray, periods: bool, rows: slice | None = None) -> np.ndarray:
    """Which pixels of the aligned frame come from inside it, ``(H, W)`` bool (``rows``:
    those rows only; a pixel's channels share its value); the others are stand-ins (the
    edge repeated) and get no weight in the merge.  ``periods``: a RAW frame moved by whole
    CFA periods."""
    h, w = frame.height, frame.width
    if frame.kind == "raw" and periods:  # whole CFA periods
        tx, ty = resample.period_shift(warp)
        inside = ((np.arange(h) + ty >= 0) & (np.arange(h) + ty <= h - 1))[rows or slice(None)]
        cols = (np.arange(w) + tx >= 0) & (np.arange(w) + tx <= w - 1)
        return inside[:, None] & cols[None, :]
    return registration.covered_mask(warp, h, w, rows)


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


@dataclass
class Models:
    """What a merge reconstructs with (the choices stage, :func:`choose_models`).

    tables : per frame, the :class:`~hdrmerge_cli.core.reconstruct.ExposureTables` of (7)
    pattern : the periodic table row of each sample (None: one row serves all)
    table_channels : the tables' row names (``R``, ``G``, ``B``, ``G2`` ...)
    row_noise : per frame (in the order of ``tables``) the noise of each table row, as the
        tables and the re-weighting passes use it; None without a noise model
    noise : per channel :class:`NoiseParams` in code units, or None; where the frames'
        noise differs (ISOs), that of the reference (first) frame
    frame_noise : per frame (in the order of ``tables``) its own per channel noise, where
        the frames' noise differs (a bracket of several ISOs and a profile with each); None
        when every frame has ``noise``
    estimated : how the noise was measured (bracket or cache), for the profile
    excess : the variance beyond the noise model measured on an image bracket, or None
    """

    estimator: str
    weights: str
    variance: str
    n_irls: int
    noise: dict[str, NoiseParams] | None
    estimated: dict | None
    prior: float | None
    bounds: tuple | None
    tables: list
    pattern: np.ndarray | None
    table_channels: list[str]
    row_noise: list[list[NoiseParams]] | None = None
    excess: object = None  # core.excess_variance.ExcessVariance of a camera-processed bracket, or None
    frame_noise: list[dict[str, NoiseParams]] | None = None
    #: the estimator, weights, variance and irls decisions (:func:`model_decisions`)
    decisions: dict[str, Decision] = field(default_factory=dict)

    def noise_used(self, frame: Frame, noise: dict[str, NoiseParams] | None = None) -> dict | None:
        """The noise parameters per channel name, as the profile and ``--json`` give them
        (``noise``, default :attr:`noise`)."""
        noise = self.noise if noise is None else noise
        if not noise:
            return None
        return {ch: vars(p) for ch, p in zip(frame.channel_names, per_channel(noise, frame.channel_names))}

    def noise_per_iso(self, frames: list[Frame]) -> dict | None:
        """Where the frames' noise differs: ``{"ISO100": {channel: {sigma_o2, alpha,
        beta}}, ...}``, the noise each ISO of ``frames`` (the merged frames, in the order of
        :attr:`frame_noise`) was merged with; else None."""
        if not self.frame_noise:
            return None
        return {iso_key(f.iso): self.noise_used(f, n) for f, n in zip(frames, self.frame_noise)}


@dataclass
class Bracket:
    """A bracket as the merge's stages share it: what was read, and what each stage derived
    from it, set by the runner (:func:`hdrmerge_cli.pipeline.run.merge_frames`) as each stage
    returns, in reading order.  A stage reads the fields it needs; none calls another.

    frames : sorted by exposure (re-sorted once, by the exposures stage, under ``--times estimate``)
    crf : the response: linear (RAW), given, or sRGB assumed until the response stage measures it
    codes : every frame's codes, decoded once and held (:class:`~hdrmerge_cli.io.frames.HeldCodes`)
    noise : the given noise (``--noise``, a profile), per channel; measured when None and needed
    noise_by_iso : per ``ISO100``-style key, each ISO's noise where the frames' ISOs differ
    exposures : ``(P,)`` float64, each frame's ``h_j`` (:func:`~hdrmerge_cli.io.metadata.exposure_values`)
    pattern : the table row each sample reads (:func:`~hdrmerge_cli.io.metadata.sample_pattern`)
    h_ref, repeats, orientation : the reference exposure, the runs of equal exposures
        (:func:`~hdrmerge_cli.io.metadata.equal_exposure_groups`) and the output's EXIF
        orientation (:func:`~hdrmerge_cli.io.metadata.output_orientation`), set with the
        exposures the merge uses (:meth:`settle_exposures`)
    samples : the one sample set every check reads (:class:`~hdrmerge_cli.core.samples.Samples`),
        drawn by the exposures stage; brought onto the reference once the frames are aligned
    alignment, exposure_report, models, ghosts : the stages' results (None: not run)
    timings : seconds per stage, for ``--json``
    """

    frames: list[Frame]
    crf: CRF
    codes: HeldCodes
    noise: dict[str, NoiseParams] | None = None
    noise_by_iso: dict[str, dict[str, NoiseParams]] | None = None
    exposures: np.ndarray | None = None
    samples: Samples | None = None
    alignment: Alignment | None = None
    exposure_report: dict | None = None
    models: Models | None = None
    ghosts: Ghosts | None = None
    timings: dict[str, float] = field(default_factory=dict)
    pattern: np.ndarray | None = field(init=False, default=None)
    orientation: int | None = field(init=False, default=None)
    h_ref: float | None = field(init=False, default=None)
    repeats: list[list[int]] | None = field(init=False, default=None)

    def __post_init__(self):
        if self.exposures is None:
            self.exposures = exposure_values(self.frames)
        self.pattern = sample_pattern(self.frames[0])  # the frames share their kind and CFA (read_bracket)

    def settle_exposures(self, frames: list[Frame], exposures: np.ndarray, reference: str | float) -> None:
        """The frames and exposures the merge uses (as the exposures stage returns them), and
        what follows from them alone: the reference exposure (``--reference``,
        :func:`~hdrmerge_cli.io.metadata.reference_exposure`), the runs of equal exposures and
        the output's orientation (the first frame's, of the frames in their final order)."""
        self.frames, self.exposures = frames, exposures
        self.orientation = output_orientation(frames)
        self.h_ref = reference_exposure(reference, exposures)
        self.repeats = equal_exposure_groups(exposures)

    def decisions(self) -> dict[str, dict]:
        """Every choice made on the bracket by name, as ``merge --json`` and the profile give
        them (:class:`~hdrmerge_cli.pipeline.records.Decision`): the models', the alignment's
        and the deghosting's."""
        made = dict(self.models.decisions) if self.models else {}
        for name, result in (("align", self.alignment), ("deghost", self.ghosts)):
            if result is not None and result.decision is not None:
                made[name] = result.decision
        return {name: d.summary() for name, d in made.items()}
