"""Choose the models a merge uses: the estimator, the weights, the noise parameters
(given, cached or measured on the bracket), the variance mode and the per-frame lookup
tables of (7)."""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import DEFAULT_K, NoiseParams
from hdrmerge_cli.core.reconstruct import exposure_tables, table_size
from hdrmerge_cli.core.weights import NOISE_MODEL_WEIGHTS
from hdrmerge_cli.io.frames import Frame, load_codes
from hdrmerge_cli.io.noisespec import iso_key, noise_from_profile, parse_bounds, parse_noise, per_channel
from hdrmerge_cli.io.profile import load_profile
from hdrmerge_cli.io.metadata import sample_pattern
from hdrmerge_cli.pipeline.options import MergeSettings

log = logging.getLogger("hdrmerge_cli")


@dataclass
class Models:
    """What a merge reconstructs with (the second stage, :func:`choose_models`).

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
    timings: dict[str, float] = field(default_factory=dict)
    frame_noise: list[dict[str, NoiseParams]] | None = None

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


def choose_models(frames: list[Frame], exposures: np.ndarray, crf: CRF, settings: MergeSettings, load=load_codes,
                  noise: dict[str, NoiseParams] | None = None, samples=None,
                  noise_by_iso: dict[str, dict[str, NoiseParams]] | None = None, *, with_variance: bool = False,
                  noise_cache: bool = True) -> Models:
    """The estimator, weights, noise parameters (``noise``, from :func:`resolve_noise`;
    with ``noise_by_iso`` (:func:`resolve_noise_by_iso`: frames of several ISOs, a profile
    with each) every frame takes its own ISO's entry ``noise_by_iso[iso_key(frame.iso)]``;
    else measured on the bracket's codes (``load``, the merge's held codes) where the
    options need them and the per-camera cache has none), the variance beyond the noise model of a camera-processed bracket
    (measured on the exposure check's ``samples``, :mod:`hdrmerge_cli.pipeline.excess`: it
    picks the estimator, and the ML estimator's variance holds it), variance mode and the
    per-frame tables, each option's ``auto`` resolved by the defaults below.  The log
    estimator keeps the fixed :data:`~hdrmerge_cli.core.reconstruct.MODEL_TOLERANCE`: on the
    real brackets' leave-one-out the measured excess in its place did not lower the error
    (benchmarks/results/real_loo.md)."""
    first = frames[0]
    timings = {}
    estimated = None
    frame_noise = None
    if noise_by_iso:
        frame_noise = [noise_by_iso[iso_key(f.iso)] for f in frames]
        noise = frame_noise[0]
        if all(n == noise for n in frame_noise):
            frame_noise = None
    processed = first.kind == "image" and not crf.is_linear and not settings.lut
    measure_excess_term = processed and samples is not None and len(frames) > 1
    needs_noise = (settings.variance == "model" or (settings.weights in NOISE_MODEL_WEIGHTS and settings.weights != "bounded")
                   or bool(settings.irls) or settings.estimator == "ml"
                   or (settings.estimator == "auto" and (first.kind == "raw" or crf.is_linear))
                   or (settings.variance == "auto" and first.kind in ("raw", "linear"))
                   or with_variance)
    if noise is None and (needs_noise or measure_excess_term) and not settings.lut:
        t1 = time.perf_counter()
        # measured only to test the excess: a failure leaves the log estimator, no warning
        noise, estimated = measure_noise(frames, crf, load, cache=noise_cache, quiet=not needs_noise)
        timings["noise_estimate"] = time.perf_counter() - t1
        isos = sorted({f.iso for f in frames if f.iso})
        if noise and needs_noise and len(isos) > 1:
            log.warning("the frames differ in ISO (%s): the noise measured on the bracket is one model for all of "
                        "them; a profile with every ISO (calibrate-noise, then --profile) gives each frame its own "
                        "noise", ", ".join(f"{i:g}" for i in isos))
    excess = None
    if measure_excess_term:
        from hdrmerge_cli.pipeline.excess import measure_excess

        t1 = time.perf_counter()
        excess = measure_excess(samples, exposures, crf, noise, first.channel_names)
        timings["excess_variance"] = time.perf_counter() - t1
    estimator = settings.estimator if settings.estimator != "auto" else default_estimator(first, crf, noise, excess)
    weights = settings.weights if settings.weights != "auto" else default_weights(estimator)
    variance = settings.variance if settings.variance != "auto" else default_variance(noise, crf, estimator)
    if weights in NOISE_MODEL_WEIGHTS and weights != "bounded" and not noise and not settings.lut:
        log.warning("no noise parameters (--noise or --profile): --weights %s uses the bounded scheme's "
                    "conservative upper bounds", weights)
    if settings.irls and not noise:
        raise HdrMergeError("--irls needs noise parameters (--noise or --profile)")
    n_irls = settings.irls if settings.irls is not None else default_irls(estimator, noise, bool(settings.lut))
    t0 = time.perf_counter()
    prior = prior_rate(frames, exposures, crf, load) if weights in NOISE_MODEL_WEIGHTS and not settings.lut else None
    luts = lut_columns(settings.lut, frames) if settings.lut else None
    bounds = parse_bounds(settings.bounds) if settings.bounds else None
    tables, pattern, table_channels = build_tables(frames, exposures, crf, weights, noise, variance, prior, settings.k,
                                                   estimator, luts, bounds,
                                                   with_variance=with_variance and not n_irls,
                                                   excess=excess if estimator == "ml" else None,
                                                   frame_noise=frame_noise)
    timings["tables"] = time.perf_counter() - t0
    if settings.lut:  # the table's weights are the merge's, whatever --weights says
        if settings.weights != "auto":
            log.warning("--weights %s is not used: --lut %s gives the weights", settings.weights, settings.lut)
        weights = f"lut:{Path(settings.lut).name}"
    return Models(estimator, weights, variance, n_irls, noise, estimated, prior, bounds, tables, pattern,
                  table_channels, excess, timings, frame_noise)


def default_estimator(frame: Frame, crf: CRF, noise=None, excess=None) -> str:
    """``--estimator auto``: the maximum-likelihood estimator of the errors the bracket
    shows.  ``"ml"`` (the linear-domain estimate, eq. (7) with inverse-variance weights)
    where the noise model (17) explains the codes: RAW frames and linear images, and a
    camera-processed bracket whose exposure pairs show no variance beyond the model (the
    test of :mod:`hdrmerge_cli.core.excess_variance`), or too few readings to test it
    (every reading's modelled deviation above 15 % or near clipping: noise dominates).
    ``"log"`` (the paper's log-domain (7)) where they show more, or where the noise could
    not be measured: that excess is the camera's processing (tone curves, local tone
    mapping, noise reduction), relative errors that the log domain averages.  Evidence:
    benchmarks/results/cli_defaults.md, real_loo.md."""
    if frame.kind == "raw" or crf.is_linear:
        return "ml"
    return "ml" if noise and excess is not None and not excess.kept else "log"


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


#: ``NoiseDraw`` sites that keep every site of a channel
WHOLE_FRAME = 1 << 62


def measure_noise(frames: list[Frame], crf: CRF, load=load_codes, cache: bool = True, quiet: bool = False):
    """No --noise or --profile: measure (17) on the bracket itself (the calibrate-noise
    code, fast path; for images on the signal linearised by ``crf``); where the drawn sites
    cannot pin some channel, again on every site; on failure fall back
    to photon-noise weights.  The sites are drawn here, from ``load``.  With ``cache``, an
    earlier merge's measurement of the same camera and ISO is read from the per-camera
    cache (:mod:`hdrmerge_cli.io.noisecache`) instead, and a new measurement is stored there.
    ``quiet``: a failure, or a channel that takes the others' noise, is logged at info level,
    not as a warning (the noise was wanted only to test an image bracket's excess variance)."""
    from hdrmerge_cli.io import noisecache

    key = noisecache.cache_key(frames[0], crf.describe()) if cache else None
    hit = noisecache.lookup(key)
    if hit is not None:
        used = hit["used"]
        log.info("noise of %s from the cache %s: %s", key, noisecache.cache_file(),
                 ", ".join(f"{ch} sigma_o2={p['sigma_o2']:.3g} alpha={p['alpha']:.3g}" for ch, p in used.items()))
        cached = {"file": str(noisecache.cache_file()), "key": key, "date": hit.get("date"),
                  "measured_on": hit.get("inputs")}
        return {ch.upper(): NoiseParams(**p) for ch, p in used.items()}, (hit.get("estimated_from_bracket") or {}) | {
            "cached": cached}

    from hdrmerge_cli.pipeline.calibrate import estimate_bracket_noise
    from hdrmerge_cli.pipeline.noise_draw import NoiseDraw

    # a camera-processed bracket's pairs hold what the processing adds: (17) from each
    # frame's own statistics, the rest from the pairs (pipeline.excess)
    pairs = frames[0].kind != "image" or crf.is_linear
    try:
        used, entries = estimate_bracket_noise(frames, crf, load, pairs=pairs)
        failed = [ch for ch, e in entries.items() if "stand_in_from" in e]
    except HdrMergeError as exc:
        failed = [str(exc)]
    # too few levels on the drawn tiles (a dark or flat bracket): drawn again, on every site
    # (one measurement whatever it is for: the excess test and the ML weights read the same)
    if failed:
        log.info("the noise could not be measured on the drawn sites (%s); measuring on every site", failed[0])
        try:
            used, entries = estimate_bracket_noise(frames, crf, load, NoiseDraw(frames, sites=WHOLE_FRAME), pairs)
        except HdrMergeError as exc:
            if quiet:
                log.info("could not measure the noise on the bracket (%s)", exc)
            else:
                log.warning("could not measure the noise on the bracket (%s); photon-noise weights are used", exc)
            return None, None
    say = log.info if quiet else log.warning
    for e in entries.values():
        if "stand_in_from" in e:
            say("%s; its noise is taken as the median of channels %s", e["reason"], ", ".join(e["stand_in_from"]))
    log.info("noise measured on the bracket: %s",
             ", ".join(f"{ch} sigma_o2={p['sigma_o2']:.3g} alpha={p['alpha']:.3g}" for ch, p in used.items()))
    if key is not None and noisecache.store(key, used, entries, [f.path for f in frames]):
        log.debug("noise of %s stored in %s", key, noisecache.cache_file())
    return {ch.upper(): NoiseParams(**p) for ch, p in used.items()}, entries


def resolve_noise(frames: list[Frame], noise: str | None, profile: str | None,
                  crf: str | None) -> dict[str, NoiseParams] | None:
    """The noise of :func:`resolve_noise_by_iso` for the first frame's ISO (every
    frame's, where it is one; a warning where the frames' ISOs differ), or None."""
    noise, by_iso = resolve_noise_by_iso(frames, noise, profile, crf)
    if by_iso:
        log.warning("the frames differ in ISO (%s): the noise of %s is used for all of them", ", ".join(by_iso),
                    iso_key(frames[0].iso))
    return noise


def resolve_noise_by_iso(frames: list[Frame], noise: str | None, profile: str | None, crf: str | None
                         ) -> tuple[dict[str, NoiseParams] | None, dict[str, dict[str, NoiseParams]] | None]:
    """``noise``, ``profile``, ``crf``: the options' strings (:class:`~hdrmerge_cli.pipeline.options.InputOptions`).
    Noise parameters from ``--noise`` (for every frame, whatever its ISO), else from the
    profile (``--profile``, or a profile given as ``--crf``), else None (a CRF-only
    profile from estimate-crf included: the noise is then measured on a RAW bracket, as
    without a profile).

    Returns ``(noise, by_iso)``: ``noise`` {channel: NoiseParams} of the first frame's ISO;
    ``by_iso`` {``ISO100``: {channel: NoiseParams}} for every ISO of ``frames`` where they
    differ (each frame is merged with its own), else None.  Frames of several ISOs and a
    profile that lacks one of them (a profile of one entry too) is an error: ``--noise``
    gives one noise for all."""
    if noise:
        return parse_noise(noise), None
    source = profile or (crf if crf and crf.lower().endswith(".json") else None)
    if source:
        prof = load_profile(source)
        if prof.get("noise") and any(k.startswith("ISO") for k in prof["noise"]):
            isos = list(dict.fromkeys(f.iso for f in frames))
            if len(isos) <= 1:  # one ISO: its entry, or the profile's only entry
                return noise_from_profile(prof, isos[0] if isos else None, source), None
            missing = [iso_key(i) for i in isos if iso_key(i) not in prof["noise"]]
            if missing:
                raise HdrMergeError(f"{source}: no noise entry for {', '.join(missing)} (the frames' ISOs differ; "
                                    f"the profile has {', '.join(repr(k[:20]) for k in prof['noise'])})")
            by_iso = {iso_key(i): noise_from_profile(prof, i, source) for i in isos}
            return by_iso[iso_key(isos[0])], by_iso
        log.info("%s: the profile has no noise parameters; %s", source,
                 "measuring them on the bracket" if frames[0].kind == "raw" else "using the weights' defaults")
    return None, None


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
    sub = codes.reshape(codes.shape[0] * codes.shape[1], -1)[::step].astype(np.float64)
    v = np.clip((sub - black) / full, 0, 1)
    lin = crf.inverse(v) if raw else np.stack([crf.inverse(v[:, c], c) for c in range(v.shape[1])], axis=-1)
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
    from hdrmerge_cli.pipeline.lut import read_luts

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


def build_tables(frames, exposures, crf, weights, noise=None, variance="none", prior=None, k=DEFAULT_K, estimator="log",
                 luts=None, bounds=None, with_variance=False, excess=None, frame_noise=None):
    """Per-frame lookup tables (each frame with its own black and white levels), the
    periodic pattern of table rows (see :class:`LogMerge`; None when one row serves every
    channel) and the table rows' channel names.  ``with_variance``: the tables also hold
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
    return tables, None if shared else sample_pattern(first), names
