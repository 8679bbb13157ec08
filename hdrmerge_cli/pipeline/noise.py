"""The noise stage: the noise model (17) the merge weighs with, per channel in code
units: given (``--noise``, a profile, per ISO where the frames' ISOs differ:
:func:`resolve_noise_by_iso`), from the per-camera cache, or measured on the bracket's own
codes (:func:`measure_noise`, calibrate-noise's fast path)."""
from __future__ import annotations

import logging
import time

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.io.frames import Frame, load_codes
from hdrmerge_cli.io.noisespec import iso_key, noise_from_profile, parse_noise
from hdrmerge_cli.io.profile import load_profile

log = logging.getLogger("hdrmerge_cli")


def frame_noise_of(frames: list[Frame], noise: dict[str, NoiseParams] | None,
                   noise_by_iso: dict[str, dict[str, NoiseParams]] | None):
    """``(noise, frame_noise)``: with ``noise_by_iso`` (frames of several ISOs, a profile
    with each) every frame takes its own ISO's entry, ``noise`` becoming the first frame's;
    ``frame_noise`` is None where every frame has ``noise``."""
    if not noise_by_iso:
        return noise, None
    frame_noise = [noise_by_iso[iso_key(f.iso)] for f in frames]
    noise = frame_noise[0]
    return noise, None if all(n == noise for n in frame_noise) else frame_noise


def bracket_noise(frames: list[Frame], crf: CRF, load, needed: bool, cache: bool, timings: dict):
    """The noise measured on the bracket (:func:`measure_noise`) for a merge that was given
    none; ``needed``: the weights need it (else it was wanted only to test an image
    bracket's excess variance, and a failure is quiet).  Returns ``(noise, how it was
    estimated)``; the seconds go to ``timings["noise_estimate"]``."""
    t1 = time.perf_counter()
    noise, estimated = measure_noise(frames, crf, load, cache=cache, quiet=not needed)
    timings["noise_estimate"] = time.perf_counter() - t1
    isos = sorted({f.iso for f in frames if f.iso})
    if noise and needed and len(isos) > 1:
        log.warning("the frames differ in ISO (%s): the noise measured on the bracket is one model for all of "
                    "them; a profile with every ISO (calibrate-noise, then --profile) gives each frame its own "
                    "noise", ", ".join(f"{i:g}" for i in isos))
    return noise, estimated


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
