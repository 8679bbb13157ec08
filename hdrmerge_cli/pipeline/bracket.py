"""Read and check a bracket: the frames' metadata, their exposures, the response.

The first stage of every command that reads a bracket (merge, estimate-crf,
calibrate-noise, info); it decodes no pixels."""
from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.reconstruct import channel_index
from hdrmerge_cli.io.crfspec import resolve_crf
from hdrmerge_cli.io.frames import Frame, HeldCodes, check_distinct_frames, raw_channel_window, read_frame
from hdrmerge_cli.io.profile import crf_from_json, load_profile
from hdrmerge_cli.io.times import apply_times

log = logging.getLogger("hdrmerge_cli")

#: relative difference under which two exposures count as equal
EQUAL_EXPOSURE_RTOL = 1e-3


def read_bracket(paths: list[str], times: list[float] | None = None, times_file: str | None = None,
                 equal_ok: bool = False, held: HeldCodes | None = None) -> list[Frame]:
    """Read and check the frames' metadata; apply user exposure times; sort by exposure.
    Frames of equal exposure are refused unless ``equal_ok`` (merge averages them; a
    response or weight table needs distinct exposures).  ``held``: takes the RAW frames'
    codes from the opens that read their metadata (:func:`~hdrmerge_cli.io.frames.read_frame`)."""
    if not paths:
        raise HdrMergeError("no input frames given")
    if len(paths) > 1:  # LibRaw unpacks each RAW to report its CFA layout, releasing the GIL: both cores
        with ThreadPoolExecutor(2) as pool:  # the first bad file in order is reported
            frames = list(pool.map(lambda p: read_frame(p, held), paths))
    else:
        frames = [read_frame(p, held) for p in paths]
    check_distinct_frames(paths)
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
                f"{frames[k].path}: same exposure ({fmt_time(frames[k].exposure_time)}) as {frames[k - 1].path}; "
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


def fmt_time(t: float) -> str:
    return f"1/{1 / t:.4g} s" if t < 1 else f"{t:.4g} s"


def reference_exposure(spec: str | float, exposures: np.ndarray) -> float:
    """``geomean`` (default), ``shortest``, ``longest`` or seconds (a number, or text such
    as ``1/100``: :func:`~hdrmerge_cli.io.times.seconds`)."""
    if spec == "geomean":
        return float(np.exp(np.mean(np.log(exposures))))
    if spec == "shortest":
        return float(exposures[0])
    if spec == "longest":
        return float(exposures[-1])
    from hdrmerge_cli.io.times import seconds

    try:
        return seconds(spec)
    except HdrMergeError as exc:
        raise HdrMergeError(f"--reference: {exc} (or geomean, shortest, longest)") from None


def choose_crf(frames: list[Frame], spec: str | None, from_profile: bool = False, warn: bool = True) -> CRF:
    """RAW is linear; images use ``spec`` (``--crf``, or the profile's CRF when
    ``from_profile``) or sRGB, marked as assumed (with a warning unless not ``warn``: merge
    measures the response on the bracket first)."""
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
    if warn:
        log.warning("%s: no camera response given; assuming sRGB. For better accuracy run "
                    "'hdrmerge-cli estimate-crf' on this bracket and pass --crf PROFILE.json", frames[0].path)
    return CRF("srgb", assumed=True)


def sample_pattern(frame: Frame) -> np.ndarray:
    """Which table row each sample reads, as the periodic pattern of :class:`LogMerge`:
    the 2 x 2 CFA cell of a RAW frame, the channel order of an image."""
    if frame.kind == "raw":
        if frame.cfa_cell is not None:
            return np.asarray(frame.cfa_cell, np.intp)
        return cfa_cell(raw_channel_window(frame.path))
    return np.arange(frame.channels, dtype=np.intp)[None, :]


def cfa_cell(channel_map: np.ndarray) -> np.ndarray:
    """The 2 x 2 repeating cell of a Bayer CFA's ``(H, W)`` channel map (or a window of it,
    :func:`~hdrmerge_cli.io.frames.raw_channel_window`)."""
    cell = channel_map[:2, :2].astype(np.intp)
    if not np.array_equal(channel_map, channel_index(channel_map.shape, cell)):
        raise HdrMergeError("the colour filter array does not repeat with a 2 x 2 cell (Bayer only)")
    return cell


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
