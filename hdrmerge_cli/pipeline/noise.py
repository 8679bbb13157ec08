"""The noise stage: the noise model (17) the merge weighs with, per channel in code
units (:func:`bracket_noise`): given (``--noise``, a profile, per ISO where the frames'
ISOs differ: :func:`resolve_noise_by_iso`), from the per-camera cache, or measured on the
bracket's own codes (:func:`measure_noise`: :func:`estimate_bracket_noise`,
calibrate-noise's fast path, on sites drawn from the held codes and linearised once, by
:func:`~hdrmerge_cli.core.calibrate.fit_bracket`).  The frames' channels and their
linear values here are calibrate-noise's too (:mod:`hdrmerge_cli.pipeline.calibrate`)."""
from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.io import noisecache
from hdrmerge_cli.io.frames import Frame
from hdrmerge_cli.io.noisespec import iso_key, noise_from_profile, parse_noise
from hdrmerge_cli.io.profile import load_profile

log = logging.getLogger("hdrmerge_cli")

if TYPE_CHECKING:
    from hdrmerge_cli.core.calibrate import DrawnChannel
    from hdrmerge_cli.pipeline.records import Bracket


@dataclass
class Noise:
    """The noise stage's result (:func:`bracket_noise`).

    noise : per channel :class:`NoiseParams` in code units, or None (photon-noise weights);
        where the frames' noise differs (ISOs), that of the first frame
    frame_noise : per frame its own per channel noise, where the frames' ISOs differ and a
        profile has each; None when every frame has ``noise``
    estimated : how the noise was measured (the fits' profile entries, or the cache's), for
        the profile; None where it was given or not measured
    """

    noise: dict[str, NoiseParams] | None
    frame_noise: list[dict[str, NoiseParams]] | None = None
    estimated: dict | None = None


def bracket_noise(b: Bracket, needed: bool, measure: bool, cache: bool) -> Noise:
    """The noise a merge of ``b`` uses: ``b.noise`` (with ``b.noise_by_iso`` every frame
    takes its own ISO's entry), else, where ``measure``, the noise measured on the bracket
    (:func:`measure_noise`; ``cache``: the per-camera cache).  ``needed``: the weights need
    it (else it was wanted only to test an image bracket's excess variance, and a failure is
    quiet).  The seconds of a measurement go to ``b.timings["noise_estimate"]``."""
    if b.noise_by_iso:
        frame_noise = [b.noise_by_iso[iso_key(f.iso)] for f in b.frames]
        return Noise(frame_noise[0], None if all(n == frame_noise[0] for n in frame_noise) else frame_noise)
    if b.noise is not None or not measure:
        return Noise(b.noise)
    t1 = time.perf_counter()
    noise, estimated = measure_noise(b.frames, b.crf, b.codes, b.pattern, cache=cache, quiet=not needed)
    b.timings["noise_estimate"] = time.perf_counter() - t1
    isos = sorted({f.iso for f in b.frames if f.iso})
    if noise and needed and len(isos) > 1:
        log.warning("the frames differ in ISO (%s): the noise measured on the bracket is one model for all of "
                    "them; a profile with every ISO (calibrate-noise, then --profile) gives each frame its own "
                    "noise", ", ".join(f"{i:g}" for i in isos))
    return Noise(noise, None, estimated)


def measure_noise(frames: list[Frame], crf: CRF, load, pattern: np.ndarray, cache: bool = True,
                  quiet: bool = False):
    """No --noise or --profile: measure (17) on the bracket itself
    (:func:`estimate_bracket_noise`; for images on the signal linearised by ``crf``; ``load``
    the frames' codes, ``pattern`` a RAW bracket's 2 x 2 CFA cell); where the drawn sites
    cannot pin some channel, again on every site; on failure ``(None, None)``: photon-noise
    weights.  With ``cache``, an earlier merge's measurement of the same camera and ISO is
    read from the per-camera cache (:mod:`hdrmerge_cli.io.noisecache`) instead, and a new
    measurement is stored there.  ``quiet``: a failure, or a channel that takes the others'
    noise, is logged at info level, not as a warning (the noise was wanted only to test an
    image bracket's excess variance).  Returns ``(noise, how it was estimated)``."""
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

    # a camera-processed bracket's pairs hold what the processing adds: (17) from each
    # frame's own statistics, the rest from the pairs (pipeline.excess)
    pairs = frames[0].kind != "image" or crf.is_linear
    failed = None
    # too few levels on the drawn tiles (a dark or flat bracket): drawn again, on every site
    # (one measurement whatever it is for: the excess test and the ML weights read the same)
    for sites in (FAST_PATH_SITES, WHOLE_FRAME):
        if failed:
            log.info("the noise could not be measured on the drawn sites (%s); measuring on every site", failed)
        try:
            used, entries, stand_ins = estimate_bracket_noise(frames, crf, load, pattern, sites, pairs)
        except HdrMergeError as exc:
            if sites == FAST_PATH_SITES:
                failed = str(exc)
                continue
            if quiet:
                log.info("could not measure the noise on the bracket (%s)", exc)
            else:
                log.warning("could not measure the noise on the bracket (%s); photon-noise weights are used", exc)
            return None, None
        failed = next(iter(stand_ins), None)
        if not failed:
            break
    say = log.info if quiet else log.warning
    for name, why in stand_ins.items():
        say("%s; its noise is taken as the median of channels %s", why, ", ".join(entries[name]["stand_in_from"]))
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


# ---------------------------------------------------------------- the frames' channels, linear
def code_scales(frames: list[Frame], crf: CRF) -> list[list[tuple[np.ndarray, float, float]]]:
    """Per frame and channel: ``(table, lo, hi)``, ``table[codes]`` the linear values above
    black (float64) of its stored codes, a value ``<= lo`` or ``>= hi`` clipped: RAW its
    codes minus its black level, images the response's inverse
    (:meth:`~hdrmerge_cli.core.crf.CRF.codes_table`) at their bit depth (one table for every
    frame), clipped half a code from either end."""
    first = frames[0]
    if first.kind == "raw":
        codes = np.arange(first.n_codes, dtype=np.float64)
        return [[(codes - black, -black, white - black) for black, white in zip(f.black, f.white)] for f in frames]
    full = first.n_codes - 1.0
    table = crf.codes_table(first.n_codes, np.zeros(len(first.black))) * full
    ends = np.array([0.5 / full, (full - 0.5) / full])
    return [[(table[k], *(crf.inverse(ends, k) * full)) for k in range(len(table))]] * len(frames)


def channel_codes(frame: Frame, codes: np.ndarray, corner: np.ndarray):
    """(name, channel index, that channel's codes, its white code) per channel, still
    integer: the CFA sites of one colour for RAW (``corner``: the colour index of the
    top-left 2 x 2 visible sites), the colour channels otherwise."""
    if frame.kind == "raw":
        for k, name in enumerate(frame.channel_names):
            ys, xs = np.nonzero(corner == k)
            if ys.size:
                yield name, k, codes[ys[0]::2, xs[0]::2], int(np.ceil(frame.white[k]))
        return
    for c in range(frame.channels):
        yield frame.channel_colors[c], c, codes[..., c], frame.n_codes - 1


def channel_planes(frame: Frame, codes: np.ndarray, crf: CRF, corner: np.ndarray | None):
    """(name, plane of linear values above black (H', W') float64, lo, hi) per channel
    (:func:`channel_codes` through :func:`code_scales`)."""
    scales = code_scales([frame], crf)[0]
    for name, k, view, _ in channel_codes(frame, codes, corner):
        table, lo, hi = scales[k]
        yield name, table[view], lo, hi


# ---------------------------------------------------------------- merge's sites
#: merge's fast path measures the noise on at most this many sites per channel and frame
#: (on simulated RAW brackets of 3 to 5 frames the standard errors this gives, in the profile
#: entry, are 1-2 % of sigma_o^2 and 2-3.5 % of alpha per channel; the fit takes ~0.1 s of CPU)
FAST_PATH_SITES = 1 << 15
#: the fast path's tiles: NOISE_TILE x NOISE_TILE sites of one channel
NOISE_TILE = 64
#: the fast path judges a frame usable on an even stride of at most this many sites per channel
USABILITY_SITES = 1 << 17
#: sites that keep every site of a channel
WHOLE_FRAME = 1 << 62


def noise_tiles(codes: np.ndarray, fill: int, sites: int, tile: int = NOISE_TILE) -> tuple[np.ndarray, int]:
    """At most ``sites`` codes of one channel (H, W), still integer, and their count: tiles of
    ``tile`` x ``tile`` spread evenly over the frame (a grid of the frame's aspect), laid
    side by side with a line of ``fill`` (a clipped code) between them, so that no window,
    residual or neighbour mean of the statistics mixes two tiles (clipping drops what
    touches the line).  The whole channel when it holds at most ``sites`` or is smaller
    than 2 x 2 tiles."""
    h, w = codes.shape
    if h * w <= sites or h < 2 * tile or w < 2 * tile:
        return codes, codes.size
    count = max(sites // tile**2, 1)
    ny = min(max(int(round(np.sqrt(count * h / w))), 1), h // tile)
    nx = min(max(count // ny, 1), w // tile)
    step = tile + 1
    out = np.full((ny * step - 1, nx * step - 1), fill, codes.dtype)
    for i, y in enumerate(np.linspace(0, h - tile, ny).astype(int)):
        for j, x in enumerate(np.linspace(0, w - tile, nx).astype(int)):
            out[i * step:i * step + tile, j * step:j * step + tile] = codes[y:y + tile, x:x + tile]
    return out, ny * nx * tile**2


def drawn_channels(frame: Frame, codes: np.ndarray, corner: np.ndarray, sites: int) -> list[DrawnChannel]:
    """:class:`~hdrmerge_cli.core.calibrate.DrawnChannel` per channel of a frame's ``codes``:
    at most ``sites`` sites of tiles (:func:`noise_tiles`) and an even stride of at most
    :data:`USABILITY_SITES` (a few ms at 24 MP)."""
    from hdrmerge_cli.core.calibrate import DrawnChannel  # scipy.ndimage: only where the noise is measured

    out = []
    for name, k, view, white in channel_codes(frame, codes, corner):
        step = max(1, int(np.ceil(np.sqrt(view.size / USABILITY_SITES))))
        out.append(DrawnChannel(name, k, *noise_tiles(view, white, sites), view[::step, ::step], view.size))
    return out


def estimate_bracket_noise(frames: list[Frame], crf: CRF, load, pattern: np.ndarray, sites: int = FAST_PATH_SITES,
                           pairs: bool = True) -> tuple[dict, dict, dict]:
    """merge without noise parameters: (17) per channel from the bracket itself, by the
    calibrate-noise code (:func:`~hdrmerge_cli.core.calibrate.fit_bracket`) on at most
    ``sites`` sites per channel and frame (:func:`drawn_channels`, from the codes ``load``
    gives; ``pattern``: a RAW bracket's 2 x 2 CFA cell), frames that are all clipped or black
    left out.  Returns ``({channel: {"sigma_o2", "alpha", "beta"}}, {channel: profile
    entry}, {channel the sites could not measure: why})``; such a channel takes the median
    of the measured channels' (the same sensor, up to the white balance's gain; its entry
    says so).  The entry's ``stderr`` holds the fit's standard errors of sigma_o2 and alpha
    and ``achievable_stderr`` the Cramer-Rao bound of the drawn sites' exposure contrasts
    (None where they hold none).

    Photographs do not measure beta (:mod:`hdrmerge_cli.core.calibrate`): it is 0.  ``pairs=False``:
    each frame's own local statistics alone, not the exposure pairs (a camera-processed
    bracket, whose pairs also hold what the processing adds, measured apart:
    :mod:`hdrmerge_cli.pipeline.excess`)."""
    from hdrmerge_cli.core.calibrate import fit_bracket  # scipy.ndimage: only where the noise is measured

    iso = iso_key(frames[0].iso)
    frames = sorted(frames, key=lambda f: f.exposure_time or 0.0)
    with ThreadPoolExecutor(2) as pool:  # SciPy's filters and NumPy's sorts release the GIL: both cores
        drawn = list(pool.map(lambda f: drawn_channels(f, load(f), pattern, sites), frames))
        scales = code_scales(frames, crf)
        found = fit_bracket(drawn, scales, [f.width * f.height for f in frames], [f.exposure_time for f in frames],
                            pairs, pool.map)
    for j, why in found.skipped:  # merge goes on with such a frame: not a warning
        log.info("%s: not used to measure the noise, %s", frames[j].path, why)
    if not found.used:
        raise HdrMergeError("no usable frame (all clipped or black)")
    first = frames[found.used[0]]
    failed = {n: f"{first.path} ({iso}, channel {n}): {why}" for n, why in found.failed.items()}
    if not found.fits:
        raise HdrMergeError(next(iter(failed.values())))
    sites = min(c.drawn for c in drawn[found.used[0]])
    stand_in = {p: float(np.median([getattr(f.fit, p) for f in found.fits.values()])) for p in ("sigma_o2", "alpha")}
    used, entries = {}, {}
    for name in found.channels:
        if name in found.fits:
            fit = found.fits[name]
            used[name] = {"sigma_o2": fit.fit.sigma_o2, "alpha": fit.fit.alpha, "beta": 0.0}
            entries[name] = fit.entry(7, sites)
        else:
            used[name] = stand_in | {"beta": 0.0}
            entries[name] = {"stand_in_from": list(found.fits), "reason": failed[name]}
    return used, entries, failed
