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

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.core.reconstruct import exposure_tables, prior_rate_of
from hdrmerge_cli.core.weights import NOISE_MODEL_WEIGHTS
from hdrmerge_cli.io.frames import Frame, load_codes
from hdrmerge_cli.io.luts import read_luts
from hdrmerge_cli.io.noisespec import parse_bounds, per_channel
from hdrmerge_cli.pipeline.options import MergeSettings
from hdrmerge_cli.pipeline.records import Alignment, Decision, Ghosts, Models, RegistrationPlan


log = logging.getLogger("hdrmerge_cli")


def given(name: str, value) -> Decision:
    """An option set on the command line: nothing decided."""
    return Decision(value, False, f"--{name} {value} given")


# ---------------------------------------------------------------- registration
#: ``--align auto`` applies the warps when some frame is displaced by more than this (pixels)
AUTO_ALIGN_PX = 0.25


def registration_plan(align: str) -> RegistrationPlan:
    """``--align``: ``auto`` fits a similarity (a rotation is kept only where it beats
    translation, :func:`choose_alignment`) and screens each pair; a named model is fitted
    to every pair."""
    return RegistrationPlan("similarity" if align == "auto" else align, align == "auto", AUTO_ALIGN_PX)


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
    some period moves), else resampled colour by colour.  Sets on ``found`` its ``mode``,
    ``motion``, ``resampling``, ``applied`` and ``decision``, and returns it."""
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
    found.mode, found.motion, found.resampling, found.applied = align, motion, resampling, bool(applied)
    found.decision = Decision(bool(applied), auto, reason, largest, AUTO_ALIGN_PX if auto else None)
    return found


# ---------------------------------------------------------------- deghosting
#: ``--deghost auto`` applies the masks when some frame has more than this share of its
#: blocks rejected
AUTO_DEGHOST_FRACTION = 0.002


def choose_deghost(found: Ghosts, mode: str) -> Ghosts:
    """``--deghost``: ``on`` applies the masks found; ``auto`` only when some frame has more
    than :data:`AUTO_DEGHOST_FRACTION` of its blocks rejected (fewer are the test's false
    alarms at its rate).  Sets on ``found`` its ``mode``, ``applied`` and ``decision``, and
    returns it."""
    largest, auto = found.largest, mode == "auto"
    applied = not auto or largest > AUTO_DEGHOST_FRACTION
    reason = ("--deghost on given" if not auto else
              f"a frame has {100 * largest:.2f} % of its blocks rejected, "
              f"{'more' if applied else 'no more'} than {100 * AUTO_DEGHOST_FRACTION:g} %")
    found.mode, found.applied = mode, bool(applied)
    found.decision = Decision(bool(applied), auto, reason, largest, AUTO_DEGHOST_FRACTION if auto else None)
    return found


# ---------------------------------------------------------------- the models


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
    (:func:`~hdrmerge_cli.core.reconstruct.exposure_tables`, one table row per channel unless
    every frame shares one: ``pattern``, the bracket's
    :func:`~hdrmerge_cli.io.metadata.sample_pattern`, says which row a sample reads),
    from the response's inverse at each frame's codes and the noise per row, and the
    irradiance prior of the noise-model weights from the middle frame's codes (``load``).
    The log estimator keeps the fixed
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
    first, luts = frames[0], lut_columns(settings.lut, frames) if settings.lut else None
    sizes = [f.n_codes if luts else table_size(f.white, f.n_codes) for f in frames]
    mid = len(frames) // 2
    mid_codes = load(frames[mid]) if weights in NOISE_MODEL_WEIGHTS and not settings.lut else None
    names = first.channel_names  # the noise per channel, then the table rows (one when every frame shares it)
    chan_noise = [per_channel(n, names) for n in frame_noise] if frame_noise else (
        [per_channel(noise, names)] * len(frames) if noise else None)
    shared = all(np.all(f.black == f.black[0]) and np.all(f.white == f.white[0]) for f in frames)
    shared &= crf.table is None or crf.table.shape[0] == 1
    shared &= chan_noise is None or all(p == c[0] for c in chan_noise for p in c)
    shared &= luts is None or luts[0].shape[0] == 1
    rows = 1 if shared else len(first.black)
    inverses = [crf.at_codes(n, f.black[:rows], f.white[:rows]) for f, n in zip(frames, sizes)]
    black, white = float(frames[mid].black[0]), float(frames[mid].white[0])
    mid_inverse = None if mid_codes is None or first.kind == "raw" else crf.at_codes(
        int(white) + 1, np.broadcast_to(black, (mid_codes.size // (mid_codes.shape[0] * mid_codes.shape[1]),)), white)
    prior = None if mid_codes is None else prior_rate_of(mid_codes, black, white, exposures[mid], mid_inverse,
                                                         frames[mid].path)
    bounds = parse_bounds(settings.bounds) if settings.bounds else None
    row_noise = None if chan_noise is None else [c[:rows] for c in chan_noise]
    tables = [exposure_tables(inv, weights, h, None if row_noise is None else row_noise[j], variance, prior,
                              tuple(exposures), settings.k, certainty=None if luts is None else luts[j],
                              estimator=estimator, bounds=bounds, with_variance=with_variance and not n_irls,
                              excess=excess if estimator == "ml" else None)
              for j, (inv, h) in enumerate(zip(inverses, exposures))]
    timings["tables"] = time.perf_counter() - t0
    if settings.lut:  # the table's weights are the merge's, whatever --weights says
        if settings.weights != "auto":
            log.warning("--weights %s is not used: --lut %s gives the weights", settings.weights, settings.lut)
        weights = f"lut:{Path(settings.lut).name}"
        decisions["weights"] = Decision(weights, False, f"--lut {settings.lut} gives the weights")
    return Models(estimator, weights, variance, n_irls, noise, estimated, prior, bounds, tables,
                  None if shared else pattern, names[:rows], row_noise, excess, frame_noise, decisions)


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
    the middle frame (the paper assumes it known); see
    :func:`~hdrmerge_cli.core.reconstruct.prior_rate_of`."""
    k = len(frames) // 2
    f, codes = frames[k], load(frames[k])
    black, white = float(f.black[0]), float(f.white[0])
    inverse = None if f.kind == "raw" else crf.at_codes(
        int(white) + 1, np.broadcast_to(black, (codes.size // (codes.shape[0] * codes.shape[1]),)), white)
    return prior_rate_of(codes, black, white, exposures[k], inverse, f.path)


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


def table_size(white, n_codes: int) -> int:
    """Entries of a frame's lookup tables: the smallest power of two above every white
    level (a 14-bit RAW in a uint16 container needs 16384, not 65536), at most the
    container's ``n_codes``.  Stored codes above it are clipped codes and read the table's
    last (clipped) entry."""
    return min(int(2 ** np.ceil(np.log2(float(np.max(white)) + 1))), n_codes)
