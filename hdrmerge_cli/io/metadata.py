"""What a bracket's metadata says, read off its frames (no pixels): each frame's exposure
``h_j``, runs of equal exposures, the reference exposure, the CFA cell a sample reads,
the output's orientation, and exposure times as text.  Every stage reads these; none
decides anything."""
from __future__ import annotations

import logging

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.reconstruct import channel_index
from hdrmerge_cli.io.frames import Frame, raw_channel_window

log = logging.getLogger("hdrmerge_cli")

#: relative difference under which two exposures count as equal
EQUAL_EXPOSURE_RTOL = 1e-3


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


def fmt_time(t: float) -> str:
    """An exposure time as a photographer writes it: ``1/250 s``, ``2 s``."""
    return f"1/{1 / t:.4g} s" if t < 1 else f"{t:.4g} s"


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


def reference_index(frames: list[Frame]) -> int:
    """The reference frame of alignment and deghosting: the middle exposure."""
    return len(frames) // 2


def of_frame(frame: Frame, frames: list[Frame], items: list):
    """The item of ``items`` that stands beside ``frame`` itself (not its path or position)
    in ``frames``."""
    for f, item in zip(frames, items):
        if f is frame:
            return item
    raise KeyError(frame.path)
