"""merge: the stages of a merge, each called once, in reading order.

The CLI (``hdrmerge-cli merge``, ``--batch``), ``plan``'s check merge and the Python API
(:mod:`hdrmerge_cli.api`) all go through :func:`merge_frames` (``estimate-crf`` runs the
read, exposures and response stages through :func:`estimate_crf`):

1. read: the frames' metadata, their codes (each file decoded once, held by frame) and the
   response given or assumed (:func:`~hdrmerge_cli.pipeline.bracket.read`, a
   :class:`~hdrmerge_cli.pipeline.records.Bracket`);
2. exposures: one sample set of every frame, its order checked
   (:func:`~hdrmerge_cli.pipeline.exposure_check.ordered_samples`);
3. response: measured on those samples when none was given
   (:func:`~hdrmerge_cli.pipeline.response.measure_response`);
4. registration: the warps that bring the frames onto the reference, and whether they are
   applied (:func:`align`); the exposure labels are then checked on the registered samples
   (:func:`~hdrmerge_cli.pipeline.exposure_check.resolve_exposures`);
5. noise (:mod:`~hdrmerge_cli.pipeline.noise`), the excess variance of camera-processed
   frames (:mod:`~hdrmerge_cli.pipeline.excess`), then the automatic choices and the
   weights' tables (:func:`~hdrmerge_cli.pipeline.choices.choose_models`);
6. ghosts (:func:`~hdrmerge_cli.pipeline.ghosts.find_ghosts`), and whether they are dropped
   (:func:`~hdrmerge_cli.pipeline.choices.choose_deghost`);
7. merge: the held codes through (7) and re-weighting, in one strip loop
   (:func:`~hdrmerge_cli.pipeline.merge.reconstruct`), and the checks after it;
8. colour and write (:class:`~hdrmerge_cli.pipeline.output.Merged`).
"""
from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.output_colorspace import COLORSPACES
from hdrmerge_cli.io.atomic import check_distinct, check_writable
from hdrmerge_cli.io.frames import Frame, cfa_corner, load_codes
from hdrmerge_cli.io.images import exr_compression
from hdrmerge_cli.io.metadata import reference_exposure
from hdrmerge_cli.io.times import ESTIMATE
from hdrmerge_cli.pipeline.bracket import read, read_bracket
from hdrmerge_cli.pipeline.choices import (
    choose_alignment, choose_deghost, choose_models, registration_plan, wanted,
)
from hdrmerge_cli.pipeline.excess import measure_excess
from hdrmerge_cli.pipeline.exposure_check import check_labels, check_overlap, ordered_samples, resolve_exposures
from hdrmerge_cli.pipeline.ghosts import find_ghosts
from hdrmerge_cli.pipeline.merge import reconstruct
from hdrmerge_cli.pipeline.noise import bracket_noise, resolve_noise_by_iso
from hdrmerge_cli.pipeline.options import EXTRA_CHANNELS, MergeOptions
from hdrmerge_cli.pipeline.output import PREVIEW_SUFFIXES, Merged, default_profile_path
from hdrmerge_cli.pipeline.records import Alignment, Bracket
from hdrmerge_cli.pipeline.register import estimate_alignment, frame_validity, loader, output_alpha
from hdrmerge_cli.pipeline.response import (
    CRFOptions, decoded, finish_crf, fit_bracket, measure_response, start_crf,
)

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
    b = given_noise(read(paths, opts.inputs), opts.inputs)
    if Path(opts.io.output).suffix.lower() == ".dng" and b.frames[0].kind != "raw":
        raise HdrMergeError(f"{opts.io.output}: a DNG output holds a CFA mosaic, but {b.frames[0].path} is not a "
                            "Bayer RAW frame; name the output *.exr")
    merged = merge_frames(b, opts, t_start=t0)
    b.codes = None  # the frames' codes are not needed for colour and writing: freed before their peak
    t0 = time.perf_counter()
    written = merged.write(inputs=inputs)
    merged.bracket.timings["color_and_write"] = time.perf_counter() - t0
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
def merge_bracket(paths: list[str], opts: MergeOptions, noise: dict | None = None, crf: CRF | None = None) -> Merged:
    """The stages on files: :func:`~hdrmerge_cli.pipeline.bracket.read`, then
    :func:`merge_frames`; ``noise`` (per channel ``NoiseParams``) and ``crf`` (image
    frames' response) in place of what the options' text gives (the Python API's objects)."""
    t0 = time.perf_counter()
    b = read(paths, opts.inputs)
    b.noise = noise
    given_noise(b, opts.inputs)
    first = b.frames[0]
    if crf is not None and first.kind == "image":
        if crf.table is not None and crf.table.shape[1] != first.n_codes:
            raise HdrMergeError(f"crf: the inverse table has {crf.table.shape[1]} entries per channel, but "
                                f"{first.path} has {first.n_codes} code values")
        b.crf = crf
    return merge_frames(b, opts, t_start=t0)


def given_noise(b: Bracket, inputs) -> Bracket:
    """The noise the options give (``--noise``, a profile's, per ISO where the frames' differ:
    :func:`~hdrmerge_cli.pipeline.noise.resolve_noise_by_iso`) unless ``b`` carries one, read
    with the bracket, before a pixel is decoded: a bad ``--noise`` fails first."""
    if b.noise is None:
        b.noise, b.noise_by_iso = resolve_noise_by_iso(b.frames, inputs.noise, inputs.profile, inputs.crf)
    return b


def merge_frames(b: Bracket, opts: MergeOptions, t_start: float | None = None) -> Merged:
    """The stages after reading, each called once, in order, on a read bracket ``b``
    (frames sorted by exposure, its given noise read: :func:`given_noise`); each stage's
    result is kept in ``b``.  Nothing is written."""
    t0 = time.perf_counter() if t_start is None else t_start
    settings, inputs, outputs = opts.algorithm, opts.inputs, opts.io
    timings = b.timings
    warn_unused_options(b, opts)
    if len(b.frames) == 1:
        log.warning("%s: only one frame; the result has that frame's dynamic range", b.frames[0].path)
    if len(b.frames) > 1 or b.crf.assumed:  # exposures: the frames' order; the response
        t1 = time.perf_counter()
        b.samples = ordered_samples(b.frames, b.exposures, b.codes, b.pattern)  # a disordered bracket fails first
        if b.crf.assumed:  # an image bracket given no response: the bracket's own, or sRGB with a warning
            b.crf = measure_response(b.frames, b.exposures, b.samples, cache=outputs.noise_cache) or b.crf
            timings["response"] = time.perf_counter() - t1
    if settings.align != "off":  # registration
        t1 = time.perf_counter()
        b.alignment = align(b.frames, b.exposures, b.crf, settings.align, b.codes)
        timings["align"] = time.perf_counter() - t1
    t1 = time.perf_counter()  # the labels checked on the registered samples (or replaced: --times estimate)
    checked = resolve_exposures(b.frames, b.exposures, b.crf, b.samples, inputs.times == ESTIMATE, b.alignment)
    b.settle_exposures(checked.frames, checked.exposures, settings.reference)
    b.exposure_report, b.samples = checked.report, checked.samples
    timings["exposure_check"] = time.perf_counter() - t1
    # the noise stage (given, cached or measured, where the options need it), the excess variance
    # of a camera-processed bracket (which picks its estimator), then the choices on what they measured
    with_variance = "variance" in outputs.extra_channels
    want, excess = wanted(b.frames, b.crf, settings, b.samples, with_variance), None
    # the noise is measured on the frames as decoded: resampling smooths it, and frames that
    # moved fail the exposure pairs' check (core.calibrate._pairs_moved) either way
    noise = bracket_noise(b, want.noise, (want.noise or want.excess) and not settings.lut, outputs.noise_cache)
    if want.excess:
        t1 = time.perf_counter()
        excess = measure_excess(b.samples, b.exposures, b.crf, noise.noise, b.frames[0].channel_names)
        timings["excess_variance"] = time.perf_counter() - t1
    b.models = choose_models(b.frames, b.exposures, b.crf, settings, b.codes, noise.noise, noise.estimated, excess,
                             noise.frame_noise, pattern=b.pattern, with_variance=with_variance, timings=timings)
    b.samples = None  # no stage reads the samples after the choices
    timings["read_metadata"] = time.perf_counter() - t0 - sum(timings.values())  # the stages timed so far aside
    aligned, validity = loader(b.alignment, b.codes), frame_validity(b.frames, b.alignment, b.codes)
    if settings.deghost != "off":  # the ghosts found, whether they are applied, and its log line
        t1 = time.perf_counter()
        found = find_ghosts(b.frames, b.exposures, b.pattern, b.crf, b.models.noise, aligned)
        b.ghosts = choose_deghost(found, settings.deghost)
        b.ghosts.report()
        timings["deghost"] = time.perf_counter() - t1
    merged = reconstruct(b, aligned, validity, outputs.half, settings.reference, with_variance)
    return Merged(b, merged.reconstruction, opts, b.h_ref, b.orientation, merged.repeats,
                  output_alpha(b.frames, validity))


def align(frames: list[Frame], exposures: np.ndarray, crf: CRF, mode: str, load=load_codes) -> Alignment:
    """Registration under ``--align mode`` (not ``off``): the warps found as the mode plans
    (:func:`~hdrmerge_cli.pipeline.choices.registration_plan`,
    :func:`~hdrmerge_cli.pipeline.register.estimate_alignment`), whether they are applied
    (:func:`~hdrmerge_cli.pipeline.choices.choose_alignment`), and its log lines."""
    alignment = choose_alignment(estimate_alignment(frames, exposures, crf, registration_plan(mode), load), mode)
    alignment.report()
    return alignment


def estimate_crf(paths, output: Path | None, opts: CRFOptions) -> dict:
    """``hdrmerge-cli estimate-crf``: its outputs checked
    (:func:`~hdrmerge_cli.pipeline.response.start_crf`) and the bracket read; for images (or linear data under
    ``--force``) the frames decoded, their one sample set drawn with its order and overlap
    checked (the exposures stage), the response fitted
    (:func:`~hdrmerge_cli.pipeline.response.fit_bracket`) and the labels judged through it;
    then the profile written (:func:`~hdrmerge_cli.pipeline.response.finish_crf`)."""
    job = start_crf(output, opts)
    frames = read_bracket(list(paths), opts.times, opts.times_file, equal_ok=True)
    first, fit = frames[0], None
    if first.kind not in ("raw", "linear") or opts.force:
        codes, labels = decoded(frames, opts)
        by_frame = {id(f): c for f, c in zip(frames, codes)}
        samples = ordered_samples(frames, labels, lambda f: by_frame[id(f)],  # constant borders off
                                  cfa_corner(first) if first.kind == "raw" else None)
        check_overlap(frames, samples)
        fit = fit_bracket(frames, codes, labels, samples, job.method, opts, job.smoothing, job.n_samples)
        estimates = opts.times == ESTIMATE
        fit.exposure_check = check_labels(frames, labels, samples, fit.crf, "" if estimates else
                                          "; estimate-crf --times estimate fits with the estimates", estimates)
    return finish_crf(job, frames, fit, opts)


def warn_unused_options(b: Bracket, opts: MergeOptions) -> None:
    """Options the bracket's kind makes moot, named once (a camera space or a mosaic asked
    of camera-processed images)."""
    first = b.frames[0]
    if opts.io.colorspace == "camera" and first.kind == "image":
        log.warning("--colorspace camera: %s carries no camera matrix (camera-processed image); the output is "
                    "Rec.709 (sRGB primaries)", first.path)
    if opts.io.cfa and first.kind != "raw":
        log.warning("--cfa: %s holds %s, no mosaic; writing RGB", first.path,
                    "linear RGB (already demosaiced)" if first.kind == "linear" else "a camera-processed image")
