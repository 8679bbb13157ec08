"""merge: read a bracket, reconstruct (7) frame by frame, write the EXR and its profile.

The merge runs as stages, each entered once, that the CLI and the Python API
(:mod:`hdrmerge_cli.api`) share:

1. read: the frames' metadata, their codes (each file decoded once, held by frame:
   :class:`~hdrmerge_cli.io.frames.HeldCodes`) and the response (:func:`open_bracket`);
2. exposures: one sample set of every frame, its order checked
   (:func:`~hdrmerge_cli.pipeline.exposure_check.ordered_samples`), the response measured on
   it when none was given (:func:`~hdrmerge_cli.pipeline.crf.measure_response`);
3. registration: the warps that bring the frames onto the reference
   (:func:`~hdrmerge_cli.pipeline.motion.estimate_alignment`); the exposure labels are then
   checked on the registered samples, with the motion registration measured
   (:func:`~hdrmerge_cli.pipeline.exposure_check.resolve_exposures`);
4. noise and the weights' tables (:func:`~hdrmerge_cli.pipeline.model_choice.choose_models`);
5. ghosts (:func:`~hdrmerge_cli.pipeline.motion.find_ghosts`);
6. merge: the held codes through (7), then re-weighting in strips (:func:`reconstruct`);
7. colour and write (:class:`~hdrmerge_cli.pipeline.output.Merged`).
"""
from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.output_colorspace import COLORSPACES
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.reconstruct import (FLAG_DARK, FLAG_SATURATED, STRIP_ROWS, LogMerge, irls, neutral_bounds,
                                           noise_rows)
from hdrmerge_cli.io.atomic import check_distinct, check_writable
from hdrmerge_cli.io.frames import Frame, HeldCodes, load_codes
from hdrmerge_cli.io.images import exr_compression
from hdrmerge_cli.io.metadata import equal_exposure_groups, exposure_values, fmt_time, output_orientation, reference_exposure
from hdrmerge_cli.io.noisespec import per_channel
from hdrmerge_cli.io.times import ESTIMATE
from hdrmerge_cli.pipeline import motion
from hdrmerge_cli.pipeline.bracket import choose_crf, read_bracket
from hdrmerge_cli.pipeline.crf import measure_response
from hdrmerge_cli.pipeline.exposure_check import ordered_samples, resolve_exposures
from hdrmerge_cli.pipeline.model_choice import Models, choose_models, resolve_noise_by_iso
from hdrmerge_cli.pipeline.options import EXTRA_CHANNELS, MergeOptions
from hdrmerge_cli.pipeline.output import PREVIEW_SUFFIXES, Merged, default_profile_path

log = logging.getLogger("hdrmerge_cli")


# ---------------------------------------------------------------- the command
def merge(paths: list[str], opts: MergeOptions) -> dict:
    """``hdrmerge-cli merge``: merge a bracket and write the EXR, its profile and the
    preview; returns the JSON summary.  Writes nothing if anything fails, and fails on
    bad options or outputs before decoding a pixel."""
    check_options(opts)
    inputs = check_outputs(paths, opts)
    t0 = time.perf_counter()
    start_preparing_kernels()
    frames, crf, codes = open_bracket(paths, opts)
    if Path(opts.io.output).suffix.lower() == ".dng" and frames[0].kind != "raw":
        raise HdrMergeError(f"{opts.io.output}: a DNG output holds a CFA mosaic, but {frames[0].path} is not a Bayer "
                            "RAW frame; name the output *.exr")
    merged = merge_frames(frames, crf, opts, load=codes, t_start=t0)
    del codes  # the frames' codes are not needed for colour and writing: freed before their peak
    t0 = time.perf_counter()
    written = merged.write(inputs=inputs)
    merged.timings["color_and_write"] = time.perf_counter() - t0
    return written | merged.summary()


def start_preparing_kernels() -> None:
    """Start :func:`prepare_kernels` in a thread, so that it overlaps the reading and
    decoding of the frames.  SciPy's linear algebra, which the set-up imports (Numba looks
    for its BLAS) and the noise fit imports too (through scipy.optimize, on other
    threads), is imported here first: the thread then imports only Numba's own modules
    and theirs, which no other thread imports, so no two threads import one module at once."""
    import scipy.linalg  # noqa: F401

    threading.Thread(target=prepare_kernels, name="prepare-kernels", daemon=True).start()


def prepare_kernels() -> None:
    """Set up Numba's code generator, which the first compiled kernel loaded from Numba's
    cache otherwise sets up on the merge's path (0.2-0.3 s of CPU: its registries and the
    modules behind them).  Holds Numba's compiler lock, as a kernel's load does."""
    try:
        from numba.core.compiler_lock import global_compiler_lock
        from numba.core.registry import cpu_target

        with global_compiler_lock:
            cpu_target.target_context.refresh()
    except Exception:  # noqa: BLE001  (a preparation only: the first kernel's load does it otherwise)
        log.debug("Numba's code generator was not prepared ahead", exc_info=True)


def check_options(opts: MergeOptions) -> None:
    """Refuse unknown option values before any work."""
    for extra in opts.io.extra_channels:
        if extra not in EXTRA_CHANNELS:
            raise HdrMergeError(f"unknown extra channel {extra!r} (choose from {', '.join(EXTRA_CHANNELS)})")
    exr_compression(opts.io.compression, opts.io.half)  # an unknown name fails before any work
    if opts.io.colorspace not in COLORSPACES:
        raise HdrMergeError(f"unknown colour space {opts.io.colorspace!r} (choose from {', '.join(COLORSPACES)})")
    reference_exposure(opts.algorithm.reference, np.ones(1))  # a bad --reference fails before any work
    if opts.io.cfa and opts.io.colorspace != "rec709":
        log.warning("--cfa writes the camera's mosaic: --colorspace %s does not apply", opts.io.colorspace)


def check_outputs(paths: list[str], opts: MergeOptions) -> list:
    """Refuse outputs that cannot or must not be written (wrong type, existing without
    ``overwrite``, the same as an input); returns the inputs the outputs must not replace."""
    output = Path(opts.io.output)
    profile_out = Path(opts.io.profile_out) if opts.io.profile_out else default_profile_path(output)
    if output.suffix.lower() not in (".exr", ".dng"):
        raise HdrMergeError(f"{output}: merge writes OpenEXR (*.exr) or, from RAW, a floating-point DNG (*.dng)")
    if output.suffix.lower() == ".dng" and (opts.io.extra_channels or opts.io.preview is not None):
        raise HdrMergeError(f"{output}: a DNG holds the colour mosaic only (it embeds its own preview); "
                            "--extra-channels and --preview need an EXR output")
    if output.suffix.lower() == ".dng":
        for name, value, default in (("colorspace", opts.io.colorspace, "rec709"),
                                     ("compression", opts.io.compression, "auto")):
            if value != default:
                log.warning("%s: a DNG holds the camera's mosaic (Deflate-compressed): --%s %s does not apply",
                            output, name, value)
    check_writable(output, opts.io.overwrite)
    check_writable(profile_out, opts.io.overwrite)
    if opts.io.preview is not None:
        if Path(opts.io.preview).suffix.lower() not in PREVIEW_SUFFIXES:
            raise HdrMergeError(f"{opts.io.preview}: a preview is written as {', '.join(PREVIEW_SUFFIXES)} (by suffix)")
        check_writable(opts.io.preview, opts.io.overwrite)
    given = (opts.inputs.profile, opts.algorithm.lut, opts.inputs.times_file, opts.inputs.crf)
    inputs = list(paths) + [p for p in given if p and Path(p).is_file()]
    check_distinct([output, profile_out] + ([opts.io.preview] if opts.io.preview is not None else []), inputs)
    return inputs


# ---------------------------------------------------------------- the stages
def merge_bracket(paths: list[str], opts: MergeOptions) -> Merged:
    """Stages 1-6 on files: :func:`open_bracket`, then :func:`merge_frames`."""
    t0 = time.perf_counter()
    frames, crf, codes = open_bracket(paths, opts)
    return merge_frames(frames, crf, opts, load=codes, t_start=t0)


def open_bracket(paths: list[str], opts: MergeOptions) -> tuple[list[Frame], CRF, HeldCodes]:
    """Stage 1: the frames' metadata, checked and sorted by exposure, the response, and
    the frames' codes as each is decoded (a RAW frame's with its metadata, from one open)."""
    inputs, codes = opts.inputs, HeldCodes()
    frames = read_bracket(paths, inputs.times, inputs.times_file, equal_ok=True, held=codes)
    return frames, choose_crf(frames, inputs.crf or inputs.profile, from_profile=not inputs.crf, warn=False), codes


def merge_frames(frames: list[Frame], crf: CRF, opts: MergeOptions, load=load_codes,
                 t_start: float | None = None, noise: dict | None = None) -> Merged:
    """Stages 2-6 on read frames (sorted by exposure), ``load(frame)`` decoding each
    frame's codes.  Nothing is written."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter() if t_start is None else t_start
    if len(frames) == 1:
        log.warning("%s: only one frame; the result has that frame's dynamic range", frames[0].path)
    exposures = exposure_values(frames)
    # per channel NoiseParams, or None; frames of several ISOs and a profile with each: per ISO too
    settings, inputs, outputs = opts.algorithm, opts.inputs, opts.io
    noise, noise_by_iso = ((noise, None) if noise is not None
                           else resolve_noise_by_iso(frames, inputs.noise, inputs.profile, inputs.crf))
    alignment = None
    if not isinstance(load, HeldCodes):  # every pass below reads the frames: each decoded once
        load = HeldCodes(load)
    unaligned = load
    samples = None
    if len(frames) > 1 or crf.assumed:  # exposures: the frames' order, the response
        t1 = time.perf_counter()
        samples = ordered_samples(frames, load)  # a disordered bracket fails first
        if crf.assumed:  # an image bracket given no response: the bracket's own, or sRGB with a warning
            crf = measure_response(frames, samples, cache=outputs.noise_cache) or crf
            timings["response"] = time.perf_counter() - t1
    if settings.align != "off":  # registration
        t1 = time.perf_counter()
        alignment = motion.estimate_alignment(frames, exposures, crf, settings.align, load)
        timings["align"] = time.perf_counter() - t1
    t1 = time.perf_counter()  # the labels checked on the registered samples (or replaced: --times estimate)
    frames, exposures, exposure_report, samples = resolve_exposures(frames, exposures, crf, load,
                                                                    inputs.times == ESTIMATE, samples, alignment)
    timings["exposure_check"] = time.perf_counter() - t1
    aligned = motion.loader(alignment, load)
    load, groups, seen = _watch_repeats(aligned, frames, exposures)
    if outputs.colorspace == "camera" and frames[0].kind == "image":
        log.warning("--colorspace camera: %s carries no camera matrix (camera-processed image); the output is "
                    "Rec.709 (sRGB primaries)", frames[0].path)
    if outputs.cfa and frames[0].kind != "raw":
        log.warning("--cfa: %s holds %s, no mosaic; writing RGB", frames[0].path,
                    "linear RGB (already demosaiced)" if frames[0].kind == "linear" else "a camera-processed image")
    # the noise is measured on the frames as decoded: resampling smooths it, and frames that
    # moved fail the exposure pairs' check (core.calibrate._pairs_moved) either way
    models = choose_models(frames, exposures, crf, settings, unaligned, noise, samples, noise_by_iso,
                           with_variance="variance" in outputs.extra_channels, noise_cache=outputs.noise_cache)
    del samples
    timings.update(models.timings)
    timings["read_metadata"] = time.perf_counter() - t0 - sum(timings.values())  # the stages timed so far aside
    ghosts = None
    if settings.deghost != "off":
        t0 = time.perf_counter()
        ghosts = motion.find_ghosts(frames, exposures, crf, motion.require_noise(models.noise, frames, crf, load),
                                    load, settings.deghost)
        timings["deghost"] = time.perf_counter() - t0
    h_ref = reference_exposure(settings.reference, exposures)
    validity = motion.frame_validity(frames, alignment)
    result, flags, den, variance, iterations = reconstruct(
        frames, exposures, h_ref, models, load,
        motion.sample_weights(models.tables, models.pattern, frames, ghosts, alignment, aligned, validity), timings,
        "variance" in outputs.extra_channels)
    check_range(result, outputs.half, settings.reference, h_ref, exposures, crf)
    neutral_bounds(result, flags)
    warn_unmeasured(frames, result, flags)
    repeats = _check_repeats(groups, seen, frames, crf)
    return Merged(frames, exposures, h_ref, crf, models, opts, result, flags, den, variance, iterations,
                  output_orientation(frames), alignment, ghosts, exposure_report, repeats, timings,
                  motion.output_alpha(frames, validity))


def reconstruct(frames: list[Frame], exposures: np.ndarray, h_ref: float, models: Models, load, weights_of,
                timings: dict, with_variance: bool = False) -> tuple:
    """The frames through (7) (:func:`_first_pass`), then ``models.n_irls`` passes of
    re-weighting at the merged estimate (:func:`~hdrmerge_cli.core.reconstruct.irls`), both
    reading the frames' held codes (``load``).  Returns ``(E * h_ref, flags, summed
    weights, variance, IRLS passes)``; the variance of ``E * h_ref`` under the noise model
    (float32, like the result) with ``with_variance``, else None."""
    ml = models.estimator == "ml"
    # without IRLS the first pass returns the linear image directly
    result, flags, den, variance, pass_timings = _first_pass(
        frames, models.tables, models.pattern, ml, None if models.n_irls else h_ref, load, weights_of,
        with_variance and not models.n_irls)
    timings.update(pass_timings)
    if not models.n_irls:
        return result, flags, den, variance, 0
    t0 = time.perf_counter()
    if models.frame_noise is None:
        maps = [noise_rows(per_channel(models.noise, models.table_channels))] * len(frames)
    else:
        maps = [noise_rows(per_channel(n, models.table_channels)) for n in models.frame_noise]
    y_full = [float(f.white[0] - f.black[0]) for f in frames]
    del flags  # IRLS makes its own; it writes over the first pass's estimate and weights
    log_e, flags, den, iterations, change, *var = irls(lambda k: load(frames[k]), models.tables, models.pattern,
                                                       result, exposures, y_full, maps, ml, models.n_irls,
                                                       variance=with_variance,
                                                       adjust=None if weights_of is None else weights_of.adjust,
                                                       den=den)
    log.info("IRLS: %d passes, largest change of the last %.2e", iterations, change)
    result = np.exp(log_e, out=log_e)
    result *= np.float32(h_ref)
    variance = None
    if with_variance:  # Var(E h_ref) = (E h_ref)^2 Var(log E), the delta method
        variance = var[0]
        variance *= result * result
    timings["irls"] = time.perf_counter() - t0
    return result, flags, den, variance, iterations


# ---------------------------------------------------------------- checks after the merge
#: samples (about) of each equal-exposure frame kept to check that the frames agree
REPEAT_SAMPLES = 1 << 18


def _watch_repeats(load, frames: list[Frame], exposures: np.ndarray):
    """Frames of equal exposure (:func:`equal_exposure_groups`) are merged; to check that
    they agree, a loader that keeps an even subsample of their codes as the merge decodes
    them (no extra decode).  Returns (loader, groups, {id(frame): subsample})."""
    groups = equal_exposure_groups(exposures)
    seen: dict[int, np.ndarray] = {}
    if not groups:
        return load, groups, seen
    watched = {id(frames[i]) for g in groups for i in g}
    h, w = frames[0].height, frames[0].width
    step = 2 * max(1, int(np.ceil(np.sqrt(h * w / REPEAT_SAMPLES) / 2)))  # even: one CFA colour

    def watching(frame):
        codes = load(frame)
        if id(frame) in watched:
            seen[id(frame)] = codes[::step, ::step].copy()
        return codes

    return watching, groups, seen


def _linear_sample(frame: Frame, codes: np.ndarray, crf: CRF) -> np.ndarray:
    """Linear values (1 = full scale) of a frame's codes (RAW: one CFA colour, mean black)."""
    if frame.kind == "raw":
        black = float(np.mean(frame.black))
        return (codes.astype(np.float64) - black) / (float(np.max(frame.white)) - black)
    full = frame.n_codes - 1.0
    return np.stack([crf.inverse(codes[..., c] / full, c) for c in range(codes.shape[-1])], axis=-1)


def _check_repeats(groups, seen, frames: list[Frame], crf: CRF) -> list[dict]:
    """Each frame of an equal-exposure group against the group's first: a warning when
    they disagree beyond the noise (:func:`~hdrmerge_cli.core.repeats.compare_repeat`): a
    changed exposure, or content (motion).  Returns the comparisons for ``--json``."""
    from hdrmerge_cli.core.repeats import compare_repeat

    report = []
    for g in groups:
        a = frames[g[0]]
        for k in g[1:]:
            b = frames[k]
            if id(a) not in seen or id(b) not in seen:
                continue
            za, zb = seen[id(a)], seen[id(b)]
            check = compare_repeat(za, zb, _linear_sample(a, za, crf), _linear_sample(b, zb, crf))
            entry = {"frames": [a.path, b.path], "exposure_time": b.exposure_time}
            if check is None:
                report.append(entry | {"compared": False})
                continue
            report.append(entry | {"compared": True, "ratio_ev": round(check.ratio_ev, 4),
                                   "outlier_fraction": check.outliers, "samples": check.samples})
            if check.exposure_changed:
                given = b.time_source != "its metadata"
                log.warning("%s: the same exposure (%s) as %s by %s, but %.2f stops %s: the exposure changed "
                            "between them (%s)", b.path, fmt_time(b.exposure_time), a.name, b.time_source,
                            abs(check.ratio_ev), "brighter" if check.ratio_ev > 0 else "darker",
                            f"check {b.time_source}" if given else "check the metadata or give --times")
            elif check.content_differs:
                log.warning("%s: the same exposure as %s, but %.1f %% of the pixels differ beyond the noise (motion "
                            "between the frames?); consider --align auto or --deghost auto", b.path, a.name,
                            100 * check.outliers)
    return report


#: largest finite value and smallest normal value of the output types
OUTPUT_RANGE = {True: (65504.0, 6.1e-5), False: (3.4e38, 1.2e-38)}


def check_range(result: np.ndarray, half: bool, reference: str, h_ref: float, exposures: np.ndarray,
                crf: CRF) -> None:
    """Refuse a result that the output type cannot hold (instead of writing clamped values
    or a mostly zero image): values above its largest finite value, or a median below its
    smallest normal value.  The scale is set by ``--reference`` (any of the
    ``exposures``), so the error names it where another reference would fit, and the
    response (``crf``) where none would."""
    top, tiny = OUTPUT_RANGE[half]
    peak = float(np.max(result, initial=0.0))
    flat = result.reshape(-1)
    median = float(np.median(flat[::max(1, flat.size // 100_000)]))
    kind = "half" if half else "float"
    drop = " or drop --half" if half else ""
    low, high = float(np.min(exposures)) / h_ref, float(np.max(exposures)) / h_ref  # the rescaling any reference gives
    over, under = not np.isfinite(peak) or peak > top, median < tiny
    if not over and not under:
        return
    if (over and not peak * low <= top) or (under and not median * high >= tiny):
        raise HdrMergeError(f"the camera response ({crf.describe()}) maps the codes to merged values from {median:.3g} "
                            f"(the median) to {peak:.3g}, which {kind} EXR cannot hold ({tiny:g} to {top:g}) at any "
                            f"--reference; check the response{drop}")
    if over:
        raise HdrMergeError(f"--reference {reference} ({h_ref:.3g} s): the brightest values ({peak:.3g}) exceed what "
                            f"{kind} EXR holds ({top:g}); use a shorter --reference (e.g. shortest){drop}")
    raise HdrMergeError(f"--reference {reference} ({h_ref:.3g} s): most values are below what {kind} EXR holds "
                        f"({tiny:g}); use a longer --reference (e.g. longest){drop}")


def warn_unmeasured(frames: list[Frame], result: np.ndarray, flags: np.ndarray) -> None:
    """One warning when no sample was measured in any frame (``flags`` all dark or
    saturated): the output then holds bounds, not measurements, and says which."""
    dark = np.count_nonzero(flags == FLAG_DARK)
    saturated = np.count_nonzero(flags == FLAG_SATURATED)
    if dark + saturated < flags.size:
        return
    where = f"{frames[0].path} ... {frames[-1].name}" if len(frames) > 1 else frames[0].path
    if saturated == 0:
        log.warning("%s: every pixel reads black in every frame; the output holds only an upper bound (%.3g, half a "
                    "code in the longest exposure), not a measurement", where, float(np.max(result)))
    elif dark == 0:
        log.warning("%s: every pixel is clipped in every frame; the output holds only a lower bound (%.3g, the "
                    "shortest exposure's clipping level), not a measurement", where, float(np.min(result)))
    else:
        log.warning("%s: no pixel is measured in any frame (%.1f %% read black in every frame, %.1f %% are clipped in "
                    "every frame); the output holds only bounds, not measurements", where,
                    100 * dark / flags.size, 100 * saturated / flags.size)


# ---------------------------------------------------------------- the first pass
def _first_pass(frames, tables, pattern, linear=False, scale=None, load=load_codes, weights_of=None, variance=False):
    """(7) over the frames' codes (``load``: held, or resampled on first use, two frames at
    a time), in strips of :data:`~hdrmerge_cli.core.reconstruct.STRIP_ROWS` rows of
    every frame: the sums, and the per-sample weights of moved or deghosted frames
    (``weights_of(k, codes, rows)``), are strip-sized.  Returns ``log E``, or ``E * scale``
    when ``scale`` is given (see :meth:`LogMerge.finish`), the flags, the summed weights,
    with ``variance`` the result's variance (:attr:`LogMerge.variance`; else None), and the
    timings."""
    shape = (frames[0].height, frames[0].width) + (() if frames[0].kind == "raw" else (frames[0].channels,))

    def decode(frame):
        codes = load(frame)
        if codes.shape != shape:
            raise HdrMergeError(f"{frame.path}: decoded size {codes.shape} differs from the metadata {shape}")
        return codes

    t_start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=2) as pool:
        codes = list(pool.map(decode, frames))
    decode_time = time.perf_counter() - t_start
    result = np.empty(shape, np.float32)
    flags = np.empty(shape, np.int8)
    den = np.empty(shape, np.float32)
    var = np.empty(shape, np.float32) if variance else None
    height, last = shape[0], len(frames) - 1
    for r0 in range(0, height, STRIP_ROWS):
        part = slice(r0, min(height, r0 + STRIP_ROWS))
        acc = LogMerge(result[part].shape, pattern, variance=variance)
        for k, z in enumerate(codes):
            weight, factor = (None, None) if weights_of is None else weights_of(k, z[part], part)
            acc.add(z[part], tables[k], last=k == last, weight=weight, factor=factor)
        result[part], flags[part] = acc.finish(linear, scale)
        den[part] = acc.den
        if variance:
            var[part] = acc.variance
    total = time.perf_counter() - t_start
    return result, flags, den, var, {"decode": decode_time, "merge": total - decode_time,
                                     "decode_and_merge_wall": total}
