"""Read and check a bracket: the frames' metadata, their exposures, the response, as a
:class:`~hdrmerge_cli.pipeline.records.Bracket`, the one object the merge's stages share.

The first stage of every command that reads a bracket (merge, estimate-crf,
calibrate-noise, info); it decodes no pixels itself (a RAW frame's codes come from the
open that reads its metadata)."""
from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.crfspec import resolve_crf
from hdrmerge_cli.io.frames import Frame, HeldCodes, check_distinct_frames, read_frame
from hdrmerge_cli.io.metadata import EQUAL_EXPOSURE_RTOL, exposure_values, fmt_time
from hdrmerge_cli.io.profile import crf_from_json, load_profile
from hdrmerge_cli.io.times import apply_times
from hdrmerge_cli.pipeline.records import Bracket

log = logging.getLogger("hdrmerge_cli")

if TYPE_CHECKING:
    from hdrmerge_cli.pipeline.options import InputOptions


def read(paths: list[str], inputs: InputOptions) -> Bracket:
    """The read stage of a merge: the frames' metadata, checked and sorted by exposure
    (:func:`read_bracket`; frames of equal exposure are merged as repeats), the response
    given (``--crf``, a profile's) or assumed, and the frames' codes as each is decoded (a
    RAW frame's from the open that read its metadata)."""
    codes = HeldCodes()
    frames = read_bracket(paths, inputs.times, inputs.times_file, equal_ok=True, held=codes)
    return Bracket(frames, choose_crf(frames, inputs.crf or inputs.profile, from_profile=not inputs.crf, warn=False),
                   codes)


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
    # / N) and checks that they agree (pipeline.merge.check_repeats)
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


def _fmt(v) -> str:
    if isinstance(v, tuple):
        return "x".join(str(x) for x in v)
    return str(v)


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
