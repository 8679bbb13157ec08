"""merge: read a bracket, reconstruct (7) frame by frame, write the EXR and its profile."""
from __future__ import annotations

import hashlib
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hdrmerge_cli import __version__
from hdrmerge_cli.core.color import REC709_CHROMATICITIES, bayer_channels, camera_to_rec709, demosaic
from hdrmerge_cli.core.color_fused import raw_to_rgb_rows
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import DEFAULT_K, NoiseParams
from hdrmerge_cli.core.preview import BlockMean, block_factor, tonemap_srgb
from hdrmerge_cli.core.reconstruct import (
    FLAG_DARK, FLAG_SATURATED, LogMerge, channel_index, exposure_tables, irls, noise_rows, table_size,
)
from hdrmerge_cli.core.weights import NOISE_MODEL_WEIGHTS
from hdrmerge_cli.io.noisespec import noise_from_profile, parse_bounds, parse_noise, per_channel
from hdrmerge_cli.io.atomic import atomic_paths, check_distinct, check_writable
from hdrmerge_cli.io.crfspec import resolve_crf
from hdrmerge_cli.io.frames import Frame, load_codes, raw_channel_map, read_frame
from hdrmerge_cli.io.images import exr_compression, write_exr, write_ldr
from hdrmerge_cli.io.profile import crf_from_json, dumps, load_profile, new_profile
from hdrmerge_cli.io.times import ESTIMATE, apply_times
from hdrmerge_cli.pipeline import motion
from hdrmerge_cli.pipeline.exposures import SampleTee, resolve_exposures

log = logging.getLogger("hdrmerge_cli")

#: extra EXR channels a user may ask for
EXTRA_CHANNELS = ("clipped", "weight", "ghost")

#: estimator choices: log = the paper's (7), ml = linear inverse-variance (censored)
ESTIMATORS = ("auto", "log", "ml")
#: relative difference under which two exposures count as equal
EQUAL_EXPOSURE_RTOL = 1e-3


@dataclass
class MergeOptions:
    output: Path
    profile_out: Path | None = None
    overwrite: bool = False
    weights: str = "auto"
    crf: str | None = None
    times: list[float] | None = None
    times_file: str | None = None
    reference: str = "geomean"
    cfa: bool = False
    half: bool = False
    extra_channels: tuple[str, ...] = field(default_factory=tuple)
    noise: str | None = None
    profile: str | None = None
    variance: str = "auto"
    estimator: str = "auto"
    irls: int | None = None  # None: default_irls
    k: float = DEFAULT_K
    lut: str | None = None
    bounds: str | None = None
    preview: Path | None = None
    preview_size: int = 2048
    align: str = "off"
    deghost: str = "off"
    #: read/store bracket noise measurements in the per-camera cache (``--no-cache``: off)
    noise_cache: bool = True
    #: OpenEXR compression (a key of :data:`hdrmerge_cli.io.images.EXR_COMPRESSIONS`)
    compression: str = "auto"


#: file types ``--preview`` writes (by suffix)
PREVIEW_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")


def default_profile_path(output: Path) -> Path:
    return output.with_name(output.stem + ".profile.json")


# ---------------------------------------------------------------- bracket checks
def read_bracket(paths: list[str], times: list[float] | None = None, times_file: str | None = None,
                 equal_ok: bool = False) -> list[Frame]:
    """Read and check the frames' metadata; apply user exposure times; sort by exposure.
    Frames of equal exposure are refused unless ``equal_ok`` (merge averages them; a
    response or weight table needs distinct exposures)."""
    if not paths:
        raise HdrMergeError("no input frames given")
    frames = [read_frame(p) for p in paths]
    apply_times(frames, times, times_file)  # "estimate": labels here, estimates after decoding
    first = frames[0]
    for f in frames[1:]:
        for what, a, b in (
            ("file type", first.kind, f.kind),
            ("size", (first.width, first.height), (f.width, f.height)),
            ("bit depth", first.bits, f.bits),
            ("channel count", first.channels, f.channels),
            ("colour filter", first.cfa_pattern, f.cfa_pattern),
        ):
            if a != b:
                raise HdrMergeError(f"{f.path}: {what} {_fmt(b)} differs from {_fmt(a)} of {first.path}")
        if first.camera and f.camera and first.camera != f.camera:
            raise HdrMergeError(f"{f.path}: taken with {f.camera!r}, but {first.path} with {first.camera!r}")
    exposures = exposure_values(frames)
    order = np.argsort(exposures, kind="stable")
    frames = [frames[i] for i in order]
    exposures = exposures[order]
    # merge averages frames of equal exposure (bursts, repeated brackets: noise variance
    # / N) and checks that they agree (_check_repeats)
    for k in range(1, len(frames)):
        if not equal_ok and exposures[k] <= exposures[k - 1] * (1 + EQUAL_EXPOSURE_RTOL):
            raise HdrMergeError(
                f"{frames[k].path}: same exposure ({_fmt_time(frames[k].exposure_time)}) as {frames[k - 1].path}; "
                "this needs different exposures (check --times)"
            )
    apertures = sorted({f.aperture for f in frames if f.aperture})
    if len(apertures) > 1:
        log.warning("%s: apertures differ between frames (f/%g .. f/%g): the exposures count them (f-number "
                    "squared), but the depth of field changes between frames", frames[0].path, apertures[0],
                    apertures[-1])
    return frames


def equal_exposure_groups(exposures) -> list[list[int]]:
    """Indices of runs of frames (sorted by exposure) whose exposures agree within
    :data:`EQUAL_EXPOSURE_RTOL`, each run of two or more frames."""
    groups, run = [], [0]
    for k in range(1, len(exposures)):
        if exposures[k] <= exposures[run[0]] * (1 + EQUAL_EXPOSURE_RTOL):
            run.append(k)
        else:
            groups, run = groups + [run] * (len(run) > 1), [k]
    return groups + [run] * (len(run) > 1)


def exposure_values(frames: list[Frame]) -> np.ndarray:
    """``h_j``: the exposure time, times ISO / ISO of the first frame (the gain
    ``sqrt(alpha_j)`` of (1)), times (f-number of the first frame / f-number)^2 (the light
    the aperture lets through).  A factor counts only when every frame states it; with
    equal ISOs and apertures ``h_j`` is the exposure time in seconds."""
    h = np.array([f.exposure_time for f in frames], dtype=np.float64)
    isos = [f.iso for f in frames]
    if all(isos):
        h = h * np.array(isos, dtype=np.float64) / isos[0]
    apertures = [f.aperture for f in frames]
    if all(apertures):
        h = h * (apertures[0] / np.array(apertures, dtype=np.float64)) ** 2
    return h


def _fmt(v) -> str:
    if isinstance(v, tuple):
        return "x".join(str(x) for x in v)
    return str(v)


def _fmt_time(t: float) -> str:
    return f"1/{1 / t:.4g} s" if t < 1 else f"{t:.4g} s"


def reference_exposure(spec: str, exposures: np.ndarray) -> float:
    """``geomean`` (default), ``shortest``, ``longest`` or a number of seconds."""
    if spec == "geomean":
        return float(np.exp(np.mean(np.log(exposures))))
    if spec == "shortest":
        return float(exposures[0])
    if spec == "longest":
        return float(exposures[-1])
    from hdrmerge_cli.io.times import parse_seconds

    return parse_seconds(spec)


def default_estimator(frame: Frame, crf: CRF) -> str:
    """``--estimator auto``: the linear ML estimate for RAW and linear images (sensor data:
    on simulated 12-bit DNGs it is 2.0 dB closer to the Cramer-Rao bound than the log
    estimator), the paper's log-domain (7) for camera-processed images (a non-linear
    response), whose errors are the response's and the camera's processing more than
    noise: on the real brackets' leave-one-out the ML estimate's error is 1.33x the log
    estimator's (benchmarks/results/real_loo.md, cli_defaults.md)."""
    return "ml" if frame.kind == "raw" or crf.is_linear else "log"


def default_weights(estimator: str) -> str:
    """``--weights auto``: ``uniform`` for the ML estimator, whose inverse-variance weights
    are already the noise-optimal ones (simulated RAW brackets, dB below the exact bound
    over samples whose bound is < 0.1, mean / worst: uniform 0.40 / 0.81, triangle
    0.53 / 0.76, probabilistic 0.87 / 1.32, benchmarks/results/cli_defaults.md); the
    classical ``triangle`` for the log estimator, the best weighting on the real brackets'
    leave-one-out (real_loo.md)."""
    return "uniform" if estimator == "ml" else "triangle"


def default_variance(noise, crf: CRF) -> str:
    """``--variance auto``: ``model`` with noise parameters (given, or measured on a RAW
    bracket); without them ``codes`` for a non-linear response (the quantisation of the
    codes through it plus a 1 % model tolerance: 0.94x the leave-one-out error of
    ``photon`` on the real brackets, benchmarks/results/real_loo.md), else ``photon``."""
    if noise:
        return "model"
    return "photon" if crf.is_linear else "codes"


def default_irls(estimator: str, noise, opts: MergeOptions) -> int:
    """``--irls`` unset: one re-weighting pass for the ML estimator of a bracket with a noise
    model and no deghosting.  Its one-pass weights take each frame's variance at that
    frame's own noisy reading, which favours readings that came out low (photon noise);
    one pass at the merged estimate removes that bias: 2.50 dB below the Cramer-Rao bound
    on average instead of 3.33 (worst 5.11 instead of 5.98) on the simulated 12-bit DNG
    brackets of benchmarks/results/cli_defaults.md; a second pass adds 0.02 dB."""
    return int(estimator == "ml" and bool(noise) and opts.deghost == "off" and not opts.lut)


def choose_crf(frames: list[Frame], spec: str | None, from_profile: bool = False) -> CRF:
    """RAW is linear; images use ``spec`` (``--crf``, or the profile's CRF when
    ``from_profile``) or sRGB with a warning."""
    if frames[0].kind in ("raw", "linear"):
        if spec and spec != "linear" and not from_profile:
            log.warning("RAW data is linear: --crf %s is ignored", spec)
        return CRF("linear")
    if spec:
        crf = crf_from_json(load_profile(spec)["crf"], spec) if from_profile else resolve_crf(spec)
        n = frames[0].n_codes
        if crf.table is not None and crf.table.shape[1] != n:
            raise HdrMergeError(f"{spec}: the response table covers codes 0..{crf.table.shape[1] - 1}, but "
                                f"{frames[0].path} has codes 0..{n - 1} ({frames[0].bits}-bit)")
        return crf
    log.warning(
        "%s: no camera response given; assuming sRGB. For better accuracy run "
        "'hdrmerge-cli estimate-crf' on this bracket and pass --crf PROFILE.json",
        frames[0].path,
    )
    return CRF("srgb", assumed=True)


# ---------------------------------------------------------------- the merge
def merge(paths: list[str], opts: MergeOptions) -> dict:
    """Merge a bracket; returns the JSON summary.  Writes nothing if anything fails."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    for extra in opts.extra_channels:
        if extra not in EXTRA_CHANNELS:
            raise HdrMergeError(f"unknown extra channel {extra!r} (choose from {', '.join(EXTRA_CHANNELS)})")
    exr_compression(opts.compression, opts.half)  # an unknown name fails before any work
    output = Path(opts.output)
    profile_out = Path(opts.profile_out) if opts.profile_out else default_profile_path(output)
    if output.suffix.lower() != ".exr":
        raise HdrMergeError(f"{output}: merge writes OpenEXR only; name the output *.exr")
    check_writable(output, opts.overwrite)
    check_writable(profile_out, opts.overwrite)
    if opts.preview is not None:
        if Path(opts.preview).suffix.lower() not in PREVIEW_SUFFIXES:
            raise HdrMergeError(f"{opts.preview}: a preview is written as {', '.join(PREVIEW_SUFFIXES)} (by suffix)")
        check_writable(opts.preview, opts.overwrite)
    inputs = list(paths) + [p for p in (opts.profile, opts.lut, opts.times_file, opts.crf)
                            if p and Path(p).is_file()]
    check_distinct([output, profile_out] + ([opts.preview] if opts.preview is not None else []), inputs)
    frames = read_bracket(paths, opts.times, opts.times_file, equal_ok=True)
    if len(frames) == 1:
        log.warning("%s: only one frame; the result has that frame's dynamic range", frames[0].path)
    crf = choose_crf(frames, opts.crf or opts.profile, from_profile=not opts.crf)
    exposures = exposure_values(frames)
    h_ref = reference_exposure(opts.reference, exposures)
    first = frames[0]
    noise = resolve_noise(opts, frames)
    alignment = None
    if opts.align != "off":
        t1 = time.perf_counter()
        alignment = motion.estimate_alignment(frames, exposures, crf, opts.align)
        timings["align"] = time.perf_counter() - t1
    load = motion.loader(frames, alignment)
    # labels checked against the frames (a warning per label off by > 1/3 EV), or replaced
    # (--times estimate: before the merge, on a pass of its own; otherwise checked after it
    # on samples of the frames the merge decodes anyway)
    tee = None
    if opts.times == ESTIMATE:
        frames, exposures, exposure_check = resolve_exposures(frames, exposures, crf, load, True)
        h_ref = reference_exposure(opts.reference, exposures)
    else:
        load = tee = SampleTee(frames, load)
    load, repeats, seen = _watch_repeats(load, frames, exposures)
    if opts.cfa and first.kind == "linear":
        log.warning("--cfa: %s holds linear RGB (already demosaiced), no mosaic; writing RGB", first.path)
    orientation = output_orientation(frames)
    estimated = None
    estimator = opts.estimator if opts.estimator != "auto" else default_estimator(first, crf)
    weights = opts.weights if opts.weights != "auto" else default_weights(estimator)
    # RAW: always measured (the ML default needs it); images only where the options ask for
    # a noise model (their default, the log estimator with code-error variances, does not)
    needs_noise = (opts.variance == "model" or (weights in NOISE_MODEL_WEIGHTS and weights != "bounded")
                   or bool(opts.irls) or estimator == "ml" or (opts.variance == "auto" and first.kind in ("raw", "linear")))
    if noise is None and needs_noise and not opts.lut:
        t1 = time.perf_counter()
        noise, estimated = _estimate_noise(frames, crf, load, cache=opts.noise_cache)
        timings["noise_estimate"] = time.perf_counter() - t1
    variance = opts.variance if opts.variance != "auto" else default_variance(noise, crf)
    if weights in NOISE_MODEL_WEIGHTS and weights != "bounded" and not noise and not opts.lut:
        log.warning("no noise parameters (--noise or --profile): --weights %s uses the bounded scheme's "
                    "conservative upper bounds", weights)
    if opts.irls and not noise:
        raise HdrMergeError("--irls needs noise parameters (--noise or --profile)")
    n_irls = opts.irls if opts.irls is not None else default_irls(estimator, noise, opts)
    timings["read_metadata"] = time.perf_counter() - t0 - timings.get("noise_estimate", 0.0) - timings.get("align", 0.0)

    t0 = time.perf_counter()
    prior = prior_rate(frames, exposures, crf) if weights in NOISE_MODEL_WEIGHTS and not opts.lut else None
    luts = _lut_columns(opts.lut, frames) if opts.lut else None
    bounds = parse_bounds(opts.bounds) if opts.bounds else None
    tables, pattern, table_channels = _tables(frames, exposures, crf, weights, noise, variance, prior, opts.k,
                                             estimator, luts, bounds)
    timings["tables"] = time.perf_counter() - t0

    ghosts = None
    if opts.deghost != "off":
        if opts.irls:
            raise HdrMergeError("--deghost and --irls cannot be combined yet; drop one of them")
        t0 = time.perf_counter()
        ghosts = motion.find_ghosts(frames, exposures, crf, motion.require_noise(noise, frames, crf, load), load,
                                    opts.deghost)
        timings["deghost"] = time.perf_counter() - t0

    # without IRLS the stream's last pass returns the linear image directly
    result, flags, den, timings_stream = _stream(frames, tables, pattern, estimator == "ml",
                                                 None if n_irls else h_ref, load,
                                                 motion.sample_weights(tables, pattern, frames, ghosts, alignment))
    timings.update(timings_stream)
    if tee is not None:
        t0 = time.perf_counter()
        exposure_check = resolve_exposures(frames, exposures, crf, samples=tee.samples(frames))[2]
        timings["exposure_check"] = time.perf_counter() - t0
    repeat_report = _check_repeats(repeats, seen, frames, crf)
    iterations = 0
    if n_irls:
        t0 = time.perf_counter()
        maps = noise_rows(per_channel(noise, table_channels))
        y_full = [float(f.white[0] - f.black[0]) for f in frames]
        log_e, flags, den, iterations, change = irls(lambda k: load(frames[k]), tables, pattern, result,
                                                     exposures, y_full, maps, estimator == "ml", n_irls)
        log.info("IRLS: %d passes, largest change of the last %.2e", iterations, change)
        result = np.exp(log_e, out=log_e)
        result *= np.float32(h_ref)
        del log_e
        timings["irls"] = time.perf_counter() - t0
    check_range(result, opts.half, opts.reference, h_ref)

    if first.kind == "raw":
        channels = ["Y"] if opts.cfa else ["R", "G", "B"]
        flag_img = flags
    else:
        channels = ["R", "G", "B"] if first.channels == 3 else ["Y"]
        flag_img = np.where((flags == FLAG_SATURATED).any(-1), FLAG_SATURATED, np.where((flags == FLAG_DARK).any(-1), FLAG_DARK, 0))
    wsum = (den if den.ndim == 2 else den.mean(axis=-1)) if "weight" in opts.extra_channels else None
    ghost_img = None
    if "ghost" in opts.extra_channels:  # frames dropped per pixel (soft: fractions of a frame)
        ghost_img = motion.ghost_image(ghosts, first.height, first.width)
    names = channels + [c for c in EXTRA_CHANNELS if c in opts.extra_channels]

    def strip(y0):
        """Rows ``y0:y0 + STRIP_ROWS`` of the EXR: colour (RAW: white balance, demosaic,
        camera matrix) and extra channels, so no full-size RGB copy is ever held."""
        y1 = min(first.height, y0 + STRIP_ROWS)
        if first.kind == "raw" and not opts.cfa:
            rgb = _raw_to_rec709_rows(result, first, y0, y1)
        else:
            rgb = result[y0:y1].reshape(y1 - y0, first.width, -1)
            if first.kind == "linear" and first.channels == 3:  # demosaiced camera RGB
                rgb = camera_to_rec709(rgb * first.white_balance.astype(np.float32), first.color_matrix)
        planes = [rgb]
        if "clipped" in opts.extra_channels:
            planes.append(flag_img[y0:y1, :, None].astype(np.float32))
        if "weight" in opts.extra_channels:
            planes.append(wsum[y0:y1, :, None].astype(np.float32))
        if ghost_img is not None:
            planes.append(ghost_img[y0:y1, :, None])
        return y0, np.concatenate(planes, axis=-1) if len(planes) > 1 else rgb

    profile = new_profile(
        {"make": first.make, "model": first.model}, first.bits, crf, [f.path for f in frames], "merge"
    )
    profile["weights"] = f"lut:{Path(opts.lut).name}" if opts.lut else weights
    noise_used = ({ch: vars(p) for ch, p in zip(first.channel_names, per_channel(noise, first.channel_names))}
                  if noise else None)
    if noise:
        profile["noise"] = {"used": noise_used}
    if estimated:
        profile["noise"]["estimated_from_bracket"] = estimated
    profile_text = dumps(profile)
    attrs = {
        "Software": f"hdrmerge-cli {__version__}",
        "hdrmerge:version": __version__,
        "hdrmerge:exposureTimes": [f.exposure_time for f in frames],
        "hdrmerge:exposures": list(exposures),
        "hdrmerge:referenceExposure": h_ref,
        "hdrmerge:units": (
            "scene-linear; 1.0 = the full-scale (clipping) signal of an exposure of "
            "hdrmerge:referenceExposure seconds" + (", after white balance (green = 1)" if (
                first.kind == "raw" and not opts.cfa) or (first.kind == "linear" and first.channels == 3) else "")
        ),
        "hdrmerge:weights": weights,
        "hdrmerge:estimator": estimator,
        "hdrmerge:variance": variance,
        "hdrmerge:crf": crf.describe(),
        "hdrmerge:profile": profile_out.name,
        "hdrmerge:profileSHA256": hashlib.sha256(profile_text.encode()).hexdigest(),
        "hdrmerge:inputs": "; ".join(f.name for f in frames),
        "ExposureTime": h_ref,
    }
    if first.camera:
        attrs["Make"], attrs["Model"] = first.make, first.model
    if channels == ["R", "G", "B"]:
        attrs["chromaticities"] = list(REC709_CHROMATICITIES)
    if first.kind == "raw" and opts.cfa:
        attrs["hdrmerge:cfaPattern"] = first.cfa_pattern
    if orientation != 1:  # the pixels stay in sensor order; viewers rotate by the header
        attrs["Orientation"] = orientation

    t0 = time.perf_counter()
    strips = prefetched(strip, range(0, first.height, STRIP_ROWS))
    preview = None
    if opts.preview is not None:
        f = block_factor(first.height, first.width, opts.preview_size)
        preview = BlockMean(first.height, first.width, len(channels), f)
        strips = _tee_preview(strips, preview, len(channels))
    outputs = [output, profile_out] + ([opts.preview] if preview else [])
    with atomic_paths(outputs, opts.overwrite, inputs) as tmps:
        write_exr(tmps[0], strips, names, attrs, half=opts.half, size=(first.height, first.width),
                  compression=opts.compression)
        Path(tmps[1]).write_text(profile_text, encoding="utf-8")
        if preview:
            rgb = upright(preview.result(), orientation)
            write_ldr(tmps[2], tonemap_srgb(rgb if rgb.shape[-1] == 3 else np.repeat(rgb[..., :1], 3, axis=-1)), {})
    timings["color_and_write"] = time.perf_counter() - t0

    n = flags.size
    return {
        "output": str(output),
        "profile": str(profile_out),
        **({"preview": str(opts.preview)} if preview else {}),
        "frames": [f.summary() | {"exposure": float(h)} for f, h in zip(frames, exposures)],
        "reference_exposure": h_ref,
        "exposure_check": exposure_check,
        "orientation": orientation,
        **({"equal_exposures": repeat_report} if repeat_report else {}),
        "weights": weights,
        "estimator": estimator,
        "variance": variance,
        "irls_iterations": iterations,
        "noise": noise_used,
        "noise_source": (f"measured earlier on the same camera and ISO (cache {estimated['cached']['file']})"
                         if estimated and "cached" in estimated
                         else "measured on the bracket (calibrate-noise fast path)" if estimated
                         else "given (--noise or --profile)" if noise_used else None),
        "prior_rate": prior,
        "bounds": list(bounds) if bounds else None,
        "crf": crf.describe(),
        "width": first.width,
        "height": first.height,
        "channels": names,
        "saturated_fraction": float(np.count_nonzero(flags == FLAG_SATURATED) / n),
        "dark_fraction": float(np.count_nonzero(flags == FLAG_DARK) / n),
        **({"alignment": {k: v for k, v in alignment.items() if k != "warps"}
                | {"warps": [np.round(w, 6).tolist() for w in alignment["warps"]]}} if alignment else {}),
        **({"deghost": {k: v for k, v in ghosts.items() if k != "masks"}}
           if ghosts else {}),
        "timing_seconds": {k: round(v, 4) for k, v in timings.items()},
    }


def output_orientation(frames: list[Frame]) -> int:
    """The EXIF orientation of the output: the frames' (the first frame's, with a
    warning, when they differ)."""
    values = sorted({f.orientation for f in frames})
    if len(values) > 1:
        log.warning("%s: the frames' orientations differ (EXIF %s); the output takes the first frame's (%d)",
                    frames[0].path, ", ".join(map(str, values)), frames[0].orientation)
    return frames[0].orientation


def upright(image: np.ndarray, orientation: int) -> np.ndarray:
    """An ``(H, W, ...)`` image stored with EXIF ``orientation``, as it is meant to be seen
    (6: rotated 90 degrees clockwise, 8: counter-clockwise, 3: 180; 2, 4, 5, 7 mirrored)."""
    return {
        2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
        5: lambda a: a.swapaxes(0, 1), 6: lambda a: np.rot90(a, -1), 7: lambda a: a.swapaxes(0, 1)[::-1, ::-1],
        8: lambda a: np.rot90(a, 1),
    }.get(orientation, lambda a: a)(image)


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
                log.warning("%s: the same exposure (%s) as %s by its metadata, but %.2f stops %s: the exposure "
                            "changed between them (check the metadata or give --times)", b.path,
                            _fmt_time(b.exposure_time), a.name, abs(check.ratio_ev),
                            "brighter" if check.ratio_ev > 0 else "darker")
            elif check.content_differs:
                log.warning("%s: the same exposure as %s, but %.1f %% of the pixels differ beyond the noise (motion "
                            "between the frames?); consider --align auto or --deghost auto", b.path, a.name,
                            100 * check.outliers)
    return report


#: largest finite value and smallest normal value of the output types
OUTPUT_RANGE = {True: (65504.0, 6.1e-5), False: (3.4e38, 1.2e-38)}


def check_range(result: np.ndarray, half: bool, reference: str, h_ref: float) -> None:
    """Refuse a result that the output type cannot hold (instead of writing clamped values
    or a mostly zero image): values above its largest finite value, or a median below its
    smallest normal value.  The scale is set by ``--reference``, so the error names it."""
    top, tiny = OUTPUT_RANGE[half]
    peak = float(np.max(result, initial=0.0))
    kind = "half" if half else "float"
    if not np.isfinite(peak) or peak > top:
        raise HdrMergeError(f"--reference {reference} ({h_ref:.3g} s): the brightest values ({peak:.3g}) exceed what "
                            f"{kind} EXR holds ({top:g}); use a shorter --reference (e.g. shortest)"
                            + (" or drop --half" if half else ""))
    flat = result.reshape(-1)
    if np.median(flat[::max(1, flat.size // 100_000)]) < tiny:
        raise HdrMergeError(f"--reference {reference} ({h_ref:.3g} s): most values are below what {kind} EXR holds "
                            f"({tiny:g}); use a longer --reference (e.g. the default, geomean)"
                            + (" or drop --half" if half else ""))


def _estimate_noise(frames: list[Frame], crf: CRF, load=load_codes, cache: bool = True):
    """No --noise or --profile: measure (17) on the bracket itself (the calibrate-noise
    code, fast path; for images on the signal linearised by ``crf``); on failure fall back
    to photon-noise weights.  With ``cache``, an earlier merge's measurement of the same
    camera and ISO is read from the per-camera cache (:mod:`hdrmerge_cli.io.noisecache`)
    instead, and a new measurement is stored there."""
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

    try:
        used, entries = estimate_bracket_noise(frames, crf, load)
    except HdrMergeError as exc:
        log.warning("could not measure the noise on the bracket (%s); photon-noise weights are used", exc)
        return None, None
    log.info("noise measured on the bracket: %s",
             ", ".join(f"{ch} sigma_o2={p['sigma_o2']:.3g} alpha={p['alpha']:.3g}" for ch, p in used.items()))
    if key is not None and noisecache.store(key, used, entries, [f.path for f in frames]):
        log.debug("noise of %s stored in %s", key, noisecache.cache_file())
    return {ch.upper(): NoiseParams(**p) for ch, p in used.items()}, entries


def resolve_noise(opts: MergeOptions, frames: list[Frame]) -> dict[str, NoiseParams] | None:
    """Noise parameters from ``--noise``, else from the profile (``--profile``, or a
    profile given as ``--crf``), else None (a CRF-only profile from estimate-crf included:
    the noise is then measured on a RAW bracket, as without a profile)."""
    if opts.noise:
        return parse_noise(opts.noise)
    source = opts.profile or (opts.crf if opts.crf and opts.crf.lower().endswith(".json") else None)
    if source:
        prof = load_profile(source)
        if prof.get("noise") and any(k.startswith("ISO") for k in prof["noise"]):
            isos = {f.iso for f in frames}
            return noise_from_profile(prof, isos.pop() if len(isos) == 1 else None, source)
        log.info("%s: the profile has no noise parameters; %s", source,
                 "measuring them on the bracket" if frames[0].kind == "raw" else "using the weights' defaults")
    return None


def prior_rate(frames: list[Frame], exposures: np.ndarray, crf: CRF) -> float:
    """Mean of the exponential irradiance prior (code values per second), estimated from
    the middle frame (the paper assumes it known); see :func:`prior_rate_of`."""
    k = len(frames) // 2
    f = frames[k]
    return prior_rate_of(load_codes(f), float(f.black[0]), float(f.white[0]), exposures[k], crf, f.kind == "raw",
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


def _lut_columns(path: str, frames: list[Frame]) -> list[np.ndarray]:
    """``merge --lut``: each frame's ``(C, N)`` weights from a ``weights-lut`` table whose
    columns follow the exposures in increasing order (one per frame, or per frame and channel)."""
    from hdrmerge_cli.pipeline.lut import read_luts

    first = frames[0]
    if first.kind == "raw":
        raise HdrMergeError(f"{path}: weight tables apply to JPEG/TIFF/PNG brackets (RAW black levels vary)")
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


def _tables(frames, exposures, crf, weights, noise=None, variance="none", prior=None, k=DEFAULT_K, estimator="log",
            luts=None, bounds=None):
    """Per-frame lookup tables (each frame with its own black and white levels), the
    periodic pattern of table rows (see :class:`LogMerge`; None when one row serves every
    channel) and the table rows' channel names."""
    first = frames[0]
    names = first.channel_names
    chan_noise = per_channel(noise, names) if noise else None
    shared = all(np.all(f.black == f.black[0]) and np.all(f.white == f.white[0]) for f in frames)
    shared &= crf.table is None or crf.table.shape[0] == 1
    shared &= chan_noise is None or all(p == chan_noise[0] for p in chan_noise)
    shared &= luts is None or luts[0].shape[0] == 1
    rows = 1 if shared else len(first.black)
    names = names[:rows]
    row_noise = chan_noise[:rows] if chan_noise else None
    tables = [exposure_tables(f.n_codes if luts else table_size(f.white, f.n_codes),
                              f.black[:rows], f.white[:rows], crf, weights, h, row_noise, variance, prior,
                              tuple(exposures), k, certainty=None if luts is None else luts[j], estimator=estimator,
                              bounds=bounds)
              for j, (f, h) in enumerate(zip(frames, exposures))]
    return tables, None if shared else sample_pattern(first), names


def sample_pattern(frame: Frame) -> np.ndarray:
    """Which table row each sample reads, as the periodic pattern of :class:`LogMerge`:
    the 2 x 2 CFA cell of a RAW frame, the channel order of an image."""
    if frame.kind == "raw":
        return cfa_cell(raw_channel_map(frame.path))
    return np.arange(frame.channels, dtype=np.intp)[None, :]


def cfa_cell(channel_map: np.ndarray) -> np.ndarray:
    """The 2 x 2 repeating cell of a Bayer CFA's ``(H, W)`` channel map."""
    cell = channel_map[:2, :2].astype(np.intp)
    if not np.array_equal(channel_map, channel_index(channel_map.shape, cell)):
        raise HdrMergeError("the colour filter array does not repeat with a 2 x 2 cell (Bayer only)")
    return cell


def _stream(frames, tables, pattern, linear=False, scale=None, load=load_codes, weights_of=None):
    """Decode frame k+1 in a worker thread while frame k is merged; keeps at most two
    decoded frames in memory.  Returns ``log E``, or ``E * scale`` when ``scale`` is given
    (see :meth:`LogMerge.finish`), the flags and the summed weights."""
    shape = (frames[0].height, frames[0].width) + (() if frames[0].kind == "raw" else (frames[0].channels,))
    acc = LogMerge(shape, pattern)
    decode_time = 0.0
    merge_time = 0.0

    def decode(frame):
        t = time.perf_counter()
        codes = load(frame)
        if codes.shape != shape:
            raise HdrMergeError(f"{frame.path}: decoded size {codes.shape} differs from the metadata {shape}")
        return codes, time.perf_counter() - t

    t_start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending = pool.submit(decode, frames[0])
        for k, frame in enumerate(frames):
            codes, dt = pending.result()
            decode_time += dt
            if k + 1 < len(frames):
                pending = pool.submit(decode, frames[k + 1])
            t = time.perf_counter()
            acc.add(codes, tables[k], last=k == len(frames) - 1,
                    weight=None if weights_of is None else weights_of(k, codes))
            del codes
            merge_time += time.perf_counter() - t
    t = time.perf_counter()
    result, flags = acc.finish(linear, scale)
    merge_time += time.perf_counter() - t
    total = time.perf_counter() - t_start
    return result, flags, acc.den, {"decode": decode_time, "merge": merge_time, "decode_and_merge_wall": total}


def _tee_preview(strips, preview, n_channels: int):
    """Pass the EXR strips on, adding each one's image channels to the preview."""
    for y0, data in strips:
        preview.add(y0, data[..., :n_channels])
        yield y0, data


def prefetched(fn, items, ahead: int = 2):
    """``fn(item)`` for each item in order, computed up to ``ahead`` items in advance on
    worker threads (so the colour conversion of the next strips runs while the EXR
    writer compresses this one), holding at most ``ahead + 1`` results."""
    with ThreadPoolExecutor(ahead) as pool:
        pending = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) > ahead:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


#: rows per strip of the colour conversion and EXR writing (even: keeps the CFA phase)
STRIP_ROWS = 256
#: rows of context around a strip for the demosaic (Malvar's 5 x 5 kernels need 2; even)
STRIP_HALO = 4


def _raw_to_rec709_rows(mosaic: np.ndarray, frame: Frame, y0: int, y1: int) -> np.ndarray:
    """Rows ``y0:y1`` of the Rec.709 image: white balance (green = 1) per CFA colour,
    demosaic (Malvar-He-Cutler, reading the rows around the strip, so strips join
    seamlessly), camera matrix; one compiled pass that releases the GIL (strips run on the
    prefetch threads, one per core).  :func:`_raw_to_rec709_rows_reference` is the same
    arithmetic through colour-demosaicing (the tests compare the two)."""
    return raw_to_rgb_rows(mosaic, frame.cfa_pattern, frame.white_balance, frame.color_matrix, y0, y1)


def _raw_to_rec709_rows_reference(mosaic: np.ndarray, frame: Frame, y0: int, y1: int) -> np.ndarray:
    """The reference of :func:`_raw_to_rec709_rows`: NumPy white balance, colour-demosaicing's
    Malvar (2004) on the strip with a halo of rows, the camera matrix."""
    a, b = max(0, y0 - STRIP_HALO), min(mosaic.shape[0], y1 + STRIP_HALO)
    part = mosaic[a:b]
    colors = bayer_channels(frame.cfa_pattern, part.shape)  # a is even: same CFA phase as row 0
    balanced = part * frame.white_balance.astype(np.float32)[colors]
    rgb = demosaic(balanced, frame.cfa_pattern)[y0 - a:y1 - a]
    return camera_to_rec709(rgb, frame.color_matrix)
