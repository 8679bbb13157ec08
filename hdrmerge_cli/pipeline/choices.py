"""The choices: every ``auto`` of a merge decided here, from what the stages measured, each
as a :class:`Decision` that the log lines and ``merge --json``'s ``decisions`` read.

* registration (``--align``): what it measures (:func:`registration_plan`), then whether the
  warps are applied, with rotation or not, and how a mosaic is moved (:func:`choose_alignment`);
* the models: the estimator, the weights, the variance mode and the re-weighting passes
  (which measurements they need, :func:`wanted`), and the per-frame lookup tables of (7)
  they make (:func:`choose_models`);
* deghosting (``--deghost``): whether the masks are applied (:func:`choose_deghost`).

The runner (:mod:`hdrmerge_cli.pipeline.run`) calls each after the stage whose results it
reads; no stage reads an ``auto``."""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import DEFAULT_K, NoiseParams
from hdrmerge_cli.core.reconstruct import exposure_tables, table_size
from hdrmerge_cli.core.weights import NOISE_MODEL_WEIGHTS
from hdrmerge_cli.io.frames import Frame, load_codes
from hdrmerge_cli.io.luts import read_luts
from hdrmerge_cli.io.noisespec import iso_key, parse_bounds, per_channel
from hdrmerge_cli.pipeline.options import MergeSettings

if TYPE_CHECKING:
    from hdrmerge_cli.pipeline.ghosts import Ghosts
    from hdrmerge_cli.pipeline.register import Alignment

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


def given(name: str, value) -> Decision:
    """An option set on the command line: nothing decided."""
    return Decision(value, False, f"--{name} {value} given")


# ---------------------------------------------------------------- registration
#: ``--align auto`` applies the warps when some frame is displaced by more than this (pixels)
AUTO_ALIGN_PX = 0.25


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
    tolerance_px: float = AUTO_ALIGN_PX


def registration_plan(align: str) -> RegistrationPlan:
    """``--align``: ``auto`` fits a similarity (a rotation is kept only where it beats
    translation, :func:`choose_alignment`) and screens each pair; a named model is fitted
    to every pair."""
    return RegistrationPlan("similarity" if align == "auto" else align, align == "auto")


def whole_periods_suffice(warps) -> bool:
    """RAW: a translation by whole 2 x 2 CFA periods moves codes without resampling them;
    ``auto`` resamples each colour's sites (``core.resample.resample_mosaic``) instead only
    when whole periods would leave some frame more than :data:`AUTO_ALIGN_PX` off along
    either axis."""
    return max(float(np.max(np.abs(w[:, 2] - 2 * np.rint(w[:, 2] / 2)))) for w in warps) <= AUTO_ALIGN_PX


def choose_alignment(found: Alignment, align: str) -> Alignment:
    """The registration's choices on what it found (``found``, not yet applied): under
    ``auto`` the warps are applied only when some frame is displaced by more than
    :data:`AUTO_ALIGN_PX`, and the motion is ``translation`` when no frame's rotation beat
    its translation; a RAW bracket moved by translation only is moved by whole CFA periods
    (``translation``, or ``auto`` where :func:`whole_periods_suffice`; applied then only if
    some period moves), else resampled colour by colour.  Returns ``found`` with
    ``mode``, ``motion``, ``resampling``, ``applied`` and its ``decision``."""
    warps, raw, auto = found.warps, found.frames[0].kind == "raw", align == "auto"
    motion = found.motion
    if auto and not any(abs(w[1, 0]) > 1e-9 for w in warps):
        motion = "translation"  # no frame's rotation beat its translation
    largest = max(found.sizes)
    applied = not auto or largest > AUTO_ALIGN_PX
    periods = raw and motion == "translation" and (align == "translation" or whole_periods_suffice(warps))
    if periods:
        applied &= any(np.any(np.rint(w[:, 2] / 2) != 0) for w in warps)
    # RAW: moved by whole CFA periods, or resampled colour by colour (core.resample.resample_mosaic)
    resampling = "none" if not raw else "cfa-periods" if periods else "per-colour"
    if not auto:
        reason = f"--align {align} given" + ("" if applied else "; no frame moves by a whole CFA period")
    elif applied:
        reason = f"a frame is displaced by {largest:.2f} px, more than {AUTO_ALIGN_PX} px"
    else:
        reason = (f"every frame is within {AUTO_ALIGN_PX} px of the reference" if largest <= AUTO_ALIGN_PX
                  else "no frame moves by a whole CFA period")
    decision = Decision(bool(applied), auto, reason, largest, AUTO_ALIGN_PX if auto else None)
    return dataclasses.replace(found, mode=align, motion=motion, resampling=resampling, applied=bool(applied),
                               decision=decision)


# ---------------------------------------------------------------- deghosting
#: ``--deghost auto`` applies the masks when some frame has more than this share of its
#: blocks rejected
AUTO_DEGHOST_FRACTION = 0.002


def choose_deghost(found: Ghosts, mode: str) -> Ghosts:
    """``--deghost``: ``on`` applies the masks found; ``auto`` only when some frame has more
    than :data:`AUTO_DEGHOST_FRACTION` of its blocks rejected (fewer are the test's false
    alarms at its rate).  Records ``mode``, ``applied`` and its ``decision`` on ``found``
    (the stage's result, which nothing else holds yet) and returns it."""
    largest, auto = found.largest, mode == "auto"
    applied = not auto or largest > AUTO_DEGHOST_FRACTION
    reason = ("--deghost on given" if not auto else
              f"a frame has {100 * largest:.2f} % of its blocks rejected, "
              f"{'more' if applied else 'no more'} than {100 * AUTO_DEGHOST_FRACTION:g} %")
    decision = Decision(bool(applied), auto, reason, largest, AUTO_DEGHOST_FRACTION if auto else None)
    found.mode, found.applied, found.decision = mode, bool(applied), decision
    return found


# ---------------------------------------------------------------- the models


@dataclass
class Models:
    """What a merge reconstructs with (the choices stage, :func:`choose_models`).

    tables : per frame, the :class:`~hdrmerge_cli.core.reconstruct.ExposureTables` of (7)
    pattern : the periodic table row of each sample (None: one row serves all)
    table_channels : the tables' row names (``R``, ``G``, ``B``, ``G2`` ...)
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


@dataclass(frozen=True)
class Wanted:
    """What the choices need measured before they can be made (:func:`wanted`).

    noise : a noise model: the weights, the variance or the estimator read it
    excess : an image bracket's variance beyond the noise model, which picks the estimator
    """

    noise: bool
    excess: bool


def wanted(frames: list[Frame], crf: CRF, settings: MergeSettings, samples, with_variance: bool = False) -> Wanted:
    """Whether the options, each ``auto`` as the bracket is, need the bracket's noise
    measured (when none was given), and its excess variance: a camera-processed bracket
    of two or more frames with the exposures stage's ``samples`` to measure it on."""
    first = frames[0]
    processed = first.kind == "image" and not crf.is_linear and not settings.lut
    noise = (settings.variance == "model" or (settings.weights in NOISE_MODEL_WEIGHTS and settings.weights != "bounded")
             or bool(settings.irls) or settings.estimator == "ml"
             or (settings.estimator == "auto" and (first.kind == "raw" or crf.is_linear))
             or (settings.variance == "auto" and first.kind in ("raw", "linear"))
             or with_variance)
    return Wanted(noise, processed and samples is not None and len(frames) > 1)


def choose_models(frames: list[Frame], exposures: np.ndarray, crf: CRF, settings: MergeSettings, load=load_codes,
                  noise: dict[str, NoiseParams] | None = None, estimated: dict | None = None, excess=None,
                  frame_noise: list | None = None, *, pattern: np.ndarray, timings: dict,
                  with_variance: bool = False) -> Models:
    """The estimator, weights, variance mode and re-weighting passes, each option's
    ``auto`` resolved by the defaults below from what the bracket measured: its noise
    (``noise``, given or measured, ``estimated`` saying how; ``frame_noise``: each frame's
    own, frames of several ISOs) and the variance beyond the noise model of a
    camera-processed bracket (``excess``, :mod:`hdrmerge_cli.pipeline.excess`: it picks the
    estimator, and the ML estimator's variance holds it); then the per-frame tables of (7)
    (``load``: the frames' codes, for the prior; ``pattern``: the bracket's
    :func:`~hdrmerge_cli.io.metadata.sample_pattern`).  The log estimator keeps the fixed
    :data:`~hdrmerge_cli.core.reconstruct.MODEL_TOLERANCE`: on the real brackets'
    leave-one-out the measured excess in its place did not lower the error
    (benchmarks/results/real_loo.md).  The tables' seconds go to ``timings["tables"]``."""
    decisions = model_decisions(settings, frames[0], crf, noise, excess)
    estimator, weights, variance, n_irls = (decisions[k].value for k in ("estimator", "weights", "variance", "irls"))
    if weights in NOISE_MODEL_WEIGHTS and weights != "bounded" and not noise and not settings.lut:
        log.warning("no noise parameters (--noise or --profile): --weights %s uses the bounded scheme's "
                    "conservative upper bounds", weights)
    if settings.irls and not noise:
        raise HdrMergeError("--irls needs noise parameters (--noise or --profile)")
    t0 = time.perf_counter()
    prior = prior_rate(frames, exposures, crf, load) if weights in NOISE_MODEL_WEIGHTS and not settings.lut else None
    luts = lut_columns(settings.lut, frames) if settings.lut else None
    bounds = parse_bounds(settings.bounds) if settings.bounds else None
    tables, pattern, table_channels = build_tables(frames, exposures, crf, weights, noise, variance, prior, settings.k,
                                                   estimator, luts, bounds,
                                                   with_variance=with_variance and not n_irls,
                                                   excess=excess if estimator == "ml" else None,
                                                   frame_noise=frame_noise, pattern=pattern)
    timings["tables"] = time.perf_counter() - t0
    if settings.lut:  # the table's weights are the merge's, whatever --weights says
        if settings.weights != "auto":
            log.warning("--weights %s is not used: --lut %s gives the weights", settings.weights, settings.lut)
        weights = f"lut:{Path(settings.lut).name}"
        decisions["weights"] = Decision(weights, False, f"--lut {settings.lut} gives the weights")
    return Models(estimator, weights, variance, n_irls, noise, estimated, prior, bounds, tables, pattern,
                  table_channels, excess, frame_noise, decisions)


def model_decisions(settings: MergeSettings, frame: Frame, crf: CRF, noise, excess) -> dict[str, Decision]:
    """The estimator, weights, variance mode and re-weighting passes (``irls``), each
    option's ``auto`` (or unset ``irls``) by the defaults below, in that order (each reads
    the estimator)."""
    out = {"estimator": given("estimator", settings.estimator) if settings.estimator != "auto"
           else estimator_decision(frame, crf, noise, excess)}
    est = out["estimator"].value
    out["weights"] = (given("weights", settings.weights) if settings.weights != "auto" else
                      Decision(default_weights(est), False, f"the {est} estimator's weights"))
    variance = default_variance(noise, crf, est)
    out["variance"] = (given("variance", settings.variance) if settings.variance != "auto" else
                       Decision(variance, False, "the noise model (17) with the parameters known" if variance == "model"
                                else "photon noise of a linear response (no noise parameters)" if variance == "photon"
                                else "the codes' quantisation through the response, a camera-processed bracket "
                                + ("under the log estimator" if noise else "without a noise model")))
    n_irls = default_irls(est, noise, bool(settings.lut))
    out["irls"] = (given("irls", settings.irls) if settings.irls is not None else
                   Decision(n_irls, False, "the ML estimator, re-weighted once at the merged estimate" if n_irls
                            else "a --lut table gives the weights" if settings.lut and est == "ml" and noise
                            else "no noise model to re-weight with" if est == "ml"
                            else "the log estimator is not re-weighted"))
    return out


def estimator_decision(frame: Frame, crf: CRF, noise=None, excess=None) -> Decision:
    """``--estimator auto``: the maximum-likelihood estimator of the errors the bracket
    shows.  ``"ml"`` (the linear-domain estimate, eq. (7) with inverse-variance weights)
    where the noise model (17) explains the codes: RAW frames and linear images, and a
    camera-processed bracket whose exposure pairs show no variance beyond the model (the
    test of :mod:`hdrmerge_cli.core.excess_variance`), or too few readings to test it
    (every reading's modelled deviation above 15 % or near clipping: noise dominates).
    ``"log"`` (the paper's log-domain (7)) where they show more, or where the noise could
    not be measured: that excess is the camera's processing (tone curves, local tone
    mapping, noise reduction), relative errors that the log domain averages.  Evidence:
    benchmarks/results/cli_defaults.md, real_loo.md.

    Returns the :class:`Decision`, measured when the excess variance of a camera-processed
    bracket decided it (its ``chi_model``, the standard error of that, and the effect on
    the predicted error)."""
    if frame.kind == "raw" or crf.is_linear:
        return Decision("ml", False, "sensor data: the noise model (17) explains the codes")
    if not noise or excess is None:
        return Decision("log", False, "no noise model measured" if not noise else
                        "the variance beyond the noise model was not measured (one frame, or a --lut table)")
    reason = ("the exposure pairs show variance beyond the noise model" if excess.kept else
              "the exposure pairs show no material variance beyond the noise model" if excess.tested else
              "too few exposure-pair readings to test the noise model: noise dominates")
    return Decision("log" if excess.kept else "ml", bool(excess.tested), reason, excess.chi_model, 1.0,
                    excess.chi_stderr, excess.effect_db)


def default_weights(estimator: str) -> str:
    """``--weights auto``: ``"uniform"`` for the ML estimator, whose inverse-variance weights
    are already the noise-optimal ones; the classical ``"triangle"`` for the log estimator.
    Evidence: benchmarks/results/cli_defaults.md, real_loo.md."""
    return "uniform" if estimator == "ml" else "triangle"


def default_variance(noise, crf: CRF, estimator: str = "ml") -> str:
    """``--variance auto``: ``"model"`` when noise parameters are known (given, or measured
    on the bracket) and the estimator is ML or the frames are sensor data; otherwise
    ``"codes"`` for a non-linear response (the quantisation of the codes through it plus
    :data:`~hdrmerge_cli.core.reconstruct.MODEL_TOLERANCE`: the log estimator of a
    camera-processed bracket, whose errors the noise model does not hold) and ``"photon"``
    for a linear one.  Evidence: benchmarks/results/real_loo.md."""
    if noise and (estimator == "ml" or crf.is_linear):
        return "model"
    return "photon" if crf.is_linear else "codes"


def default_irls(estimator: str, noise, lut: bool = False) -> int:
    """``--irls`` unset: the number of re-weighting passes, 1 for the ML estimator of a
    bracket with a noise model (and no ``--lut``), else 0.

    Notes: one-pass weights take each frame's variance at that frame's own noisy reading,
    which favours readings that came out low under photon noise; one pass at the merged
    estimate removes that bias, and further passes change the result by far less than the
    noise.  The pass keeps the ghost and coverage weights
    (:class:`~hdrmerge_cli.pipeline.merge.SampleWeights`).  Evidence:
    benchmarks/results/cli_defaults.md, motion.md."""
    return int(estimator == "ml" and bool(noise) and not lut)


def prior_rate(frames: list[Frame], exposures: np.ndarray, crf: CRF, load=load_codes) -> float:
    """Mean of the exponential irradiance prior (code values per second), estimated from
    the middle frame (the paper assumes it known); see :func:`prior_rate_of`."""
    k = len(frames) // 2
    f = frames[k]
    return prior_rate_of(load(f), float(f.black[0]), float(f.white[0]), exposures[k], crf, f.kind == "raw",
                         f.path)


#: samples of the middle frame that estimate the prior's mean
PRIOR_SAMPLES = 1 << 18


def prior_rate_of(codes: np.ndarray, black: float, white: float, exposure: float, crf: CRF, raw: bool,
                  name: str = "the middle frame") -> float:
    """The prior's mean from one frame's unclipped samples: the mean linear signal (code
    values) per second over an even subsample of at most :data:`PRIOR_SAMPLES` samples.

    codes : (H, W) mosaic (``raw``) or (H, W, C) image of the frame of exposure ``exposure`` s
    """
    full = white - black
    step = max(1, codes.shape[0] * codes.shape[1] // PRIOR_SAMPLES)
    sub = codes.reshape(codes.shape[0] * codes.shape[1], -1)[::step]
    lin = np.clip((sub - black) / full, 0, 1) if raw else crf.linear(sub, int(white) + 1, black, white)
    ok = (lin > 0) & (lin < 1)
    if not np.any(ok):
        what = "black" if np.all(lin <= 0) else "clipped" if np.all(lin >= 1) else "black or clipped"
        raise HdrMergeError(f"{name}: every sample is {what}; cannot estimate the irradiance prior")
    return float(np.mean(lin[ok]) * full / exposure)


#: why a mosaic RAW bracket takes no weight table
RAW_HAS_NO_LUT = ("a RAW mosaic: weight tables serve image brackets (a code value per table row); a RAW bracket is "
                  "weighted from its noise model, per sample above its black level")


def lut_columns(path: str, frames: list[Frame]) -> list[np.ndarray]:
    """``merge --lut``: each frame's ``(C, N)`` weights from a ``weights-lut`` table whose
    columns follow the exposures in increasing order (one per frame, or per frame and channel)."""
    first = frames[0]
    if first.kind == "raw":
        raise HdrMergeError(f"{first.path}: {RAW_HAS_NO_LUT}")
    table = read_luts(path)
    if table.shape[0] != first.n_codes:
        raise HdrMergeError(f"{path}: {table.shape[0]} rows, but the frames have {first.n_codes} code values")
    per = table.shape[1] // len(frames)
    if per * len(frames) != table.shape[1] or per not in (1, first.channels):
        raise HdrMergeError(f"{path}: {table.shape[1]} columns do not fit {len(frames)} frames of {first.channels} channels")
    if not np.all(np.isfinite(table)) or np.any(table < 0):
        raise HdrMergeError(f"{path}: weights must be finite and non-negative")
    columns = [table[:, j * per:(j + 1) * per].T for j in range(len(frames))]
    for j, col in enumerate(columns):
        if not np.any(col > 0):
            raise HdrMergeError(f"{path}: the weights of frame {j + 1} ({frames[j].name}) are all zero; "
                                "that frame would be ignored (rebuild the table)")
    return columns


class Tables(NamedTuple):
    """What :func:`build_tables` returns: per frame its
    :class:`~hdrmerge_cli.core.reconstruct.ExposureTables`, the periodic pattern of table
    rows (see :class:`LogMerge`; None when one row serves every channel) and the rows'
    channel names."""

    tables: list
    pattern: np.ndarray | None
    channels: list[str]


def build_tables(frames, exposures, crf, weights, noise=None, variance="none", prior=None, k=DEFAULT_K, estimator="log",
                 luts=None, bounds=None, with_variance=False, excess=None, frame_noise=None, pattern=None) -> Tables:
    """Per-frame lookup tables (each frame with its own black and white levels), as
    :class:`Tables`.  ``with_variance``: the tables also hold
    each frame's per-code variance (``--extra-channels variance``, streamed by :class:`LogMerge`).
    ``frame_noise``: per frame its own {channel: NoiseParams} (frames of several ISOs),
    instead of ``noise`` for all."""
    first = frames[0]
    names = first.channel_names
    chan_noise = [per_channel(n, names) for n in frame_noise] if frame_noise else (
        [per_channel(noise, names)] * len(frames) if noise else None)
    shared = all(np.all(f.black == f.black[0]) and np.all(f.white == f.white[0]) for f in frames)
    shared &= crf.table is None or crf.table.shape[0] == 1
    shared &= chan_noise is None or all(p == c[0] for c in chan_noise for p in c)
    shared &= luts is None or luts[0].shape[0] == 1
    rows = 1 if shared else len(first.black)
    names = names[:rows]
    tables = [exposure_tables(f.n_codes if luts else table_size(f.white, f.n_codes),
                              f.black[:rows], f.white[:rows], crf, weights, h,
                              chan_noise[j][:rows] if chan_noise else None, variance, prior,
                              tuple(exposures), k, certainty=None if luts is None else luts[j], estimator=estimator,
                              bounds=bounds, with_variance=with_variance, excess=excess)
              for j, (f, h) in enumerate(zip(frames, exposures))]
    return Tables(tables, None if shared else pattern, names)
