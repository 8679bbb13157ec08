"""The noise stage: the noise model (17) the merge weighs with, per channel in code
units: given (``--noise``, a profile, per ISO where the frames' ISOs differ:
:func:`resolve_noise_by_iso`), from the per-camera cache, or measured on the bracket's own
codes (:func:`measure_noise`: :func:`estimate_bracket_noise`, calibrate-noise's fast
path).  The frames' planes, their usability and the fit's profile entries here are
calibrate-noise's too (:mod:`hdrmerge_cli.pipeline.calibrate`)."""
from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.io.frames import Frame, load_codes
from hdrmerge_cli.io.noisespec import iso_key, noise_from_profile, parse_noise
from hdrmerge_cli.io.profile import load_profile
from hdrmerge_cli.pipeline.noise_draw import NoiseDraw, channel_codes

log = logging.getLogger("hdrmerge_cli")

if TYPE_CHECKING:
    from hdrmerge_cli.core.calibrate import NoiseFit


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


# ---------------------------------------------------------------- measured on frames
#: a frame with less than this fraction of unclipped pixels is skipped
MIN_UNCLIPPED = 0.01


def linear_plane(frame: Frame, k: int, codes: np.ndarray, crf):
    """(plane of linear values above black (H', W') float64, lo, hi) of channel ``k``'s codes
    (:func:`channel_codes`): RAW minus its black level, images linearised by ``crf`` at
    their bit depth; a value ``<= lo`` or ``>= hi`` is clipped."""
    if frame.kind == "raw":
        return codes.astype(np.float64) - frame.black[k], -frame.black[k], frame.white[k] - frame.black[k]
    full = frame.n_codes - 1.0
    lo, hi = crf.inverse(np.array([0.5 / full, (full - 0.5) / full]), k) * full
    return crf.codes_table(frame.n_codes, np.zeros(len(frame.black)))[k][codes] * full, lo, hi


def channel_planes(frame: Frame, codes: np.ndarray, crf, corner: np.ndarray | None = None):
    """(name, plane of linear values above black (H', W') float64, lo, hi) per channel
    (:func:`channel_codes` through :func:`linear_plane`)."""
    for name, k, sub in channel_codes(frame, codes, corner):
        yield (name, *linear_plane(frame, k, sub, crf))


def unusable_reason(frame: Frame, planes, sites: int | None = None) -> str | None:
    """Why a frame cannot be used (all clipped, or black), or None.  planes: as
    :func:`channel_planes` yields them, whole or an even subsample of planes of ``sites``
    sites each (see :func:`has_signal`)."""
    inside = np.mean([np.mean((p > lo) & (p < hi)) for _, p, lo, hi in planes])
    if inside < MIN_UNCLIPPED:
        dark = np.mean([np.mean(p <= lo) for _, p, lo, hi in planes])
        bright = 1 - inside - dark
        parts = [f"{100 * v:.1f} % of its pixels {what}" for v, what in ((dark, "read black"),
                                                                         (bright, "are clipped at white")) if v > 0]
        return " and ".join(parts)
    if not any(has_signal(p, lo, hi, sites) for _, p, lo, hi in planes):
        if frame.width * frame.height < MIN_SIGNAL_SITES:
            return (f"it holds {frame.width * frame.height} pixels, too few to measure noise on (at least "
                    f"{MIN_SIGNAL_SITES})")
        return "it is black (no signal above its noise floor)"
    return None


#: a frame has signal when at least this many of its sites (and this fraction) lie above the noise floor
MIN_SIGNAL_SITES, MIN_SIGNAL_FRACTION = 64, 1e-4


#: and, judged on an even subsample, at least this many of the subsample's sites
MIN_SIGNAL_SAMPLES = 8


def has_signal(plane: np.ndarray, lo: float, hi: float, sites: int | None = None) -> bool:
    """Whether a plane holds signal: enough sites (:data:`MIN_SIGNAL_SITES`, a fraction
    :data:`MIN_SIGNAL_FRACTION`) above its noise floor, 6 robust standard deviations of
    the darker half of the sites (1.4826 times their median absolute deviation) above
    black and at least 0.2 % of the range.  A count, not a percentile: a night frame whose
    99th percentile is near black but whose lamps and windows are bright has signal.

    ``sites``: the plane is an even subsample of a plane of that many sites, whose count
    above the floor is estimated from the subsample's fraction (and at least
    :data:`MIN_SIGNAL_SAMPLES` of the subsample's sites must lie above it)."""
    sub = (plane[::2, ::2] if plane.size > 1 << 22 else plane).ravel()
    med = float(np.median(sub))
    low = sub[sub <= med]
    sigma = 1.4826 * float(np.median(np.abs(low - np.median(low)))) if low.size else 0.0
    floor = max(6 * sigma, 0.002 * (hi - max(lo, 0.0)))
    above = int(np.count_nonzero(sub > floor))
    if sites is None or sites <= sub.size:
        return above >= max(MIN_SIGNAL_SITES, MIN_SIGNAL_FRACTION * sub.size)
    return (above >= MIN_SIGNAL_SAMPLES
            and above * sites / sub.size >= max(MIN_SIGNAL_SITES, MIN_SIGNAL_FRACTION * sites))


def usable_frames(frames: list[Frame], results, skipped: str = "skipped",
                   level: int = logging.WARNING) -> list[tuple[Frame, list]]:
    """[(frame, planes)] of ``results`` (``(why the frame is unusable or None, its planes)``
    per frame), each unusable frame left out with a message (``skipped``, at ``level``)."""
    out = []
    for f, (reason, planes) in zip(frames, results):
        if reason:
            log.log(level, "%s: %s, %s", f.path, skipped, reason)
        else:
            out.append((f, planes))
    return out


def fit_entry(fit: NoiseFit, pairs: list[float], window: int) -> dict:
    source = "exposure pairs" if pairs else "local statistics"
    return fit.as_dict() | {
        "method": {"sigma_o2": source, "alpha": source,
                   "beta": "not measured: in photographs scene texture and gain FPN look alike (--flats "
                           "measures beta); 0 is used"},
        "window": window, "exposure_ratios": [round(r, 5) for r in pairs],
    }


def _read_drawn(frames: list[Frame], crf, load, draw: NoiseDraw, pool) -> list[tuple[Frame, list]]:
    """:func:`_read_group`'s list from the drawn codes (frames not yet drawn decoded through
    ``load``), two frames at a time on ``pool``: each frame's usability judged on its even
    stride (the rule of :func:`unusable_reason`), its tiles linearised."""
    def read(f):
        if f.path not in draw.drawn:
            draw(f, load(f))
        channels = draw.drawn[f.path]
        reason = unusable_reason(f, [(c.name, *linear_plane(f, c.index, c.stride, crf)) for c in channels],
                         min(c.sites for c in channels))
        return reason, None if reason else [(c.name, *linear_plane(f, c.index, c.tiles, crf)) for c in channels]

    # merge goes on with such a frame: not a warning
    return usable_frames(frames, pool.map(read, frames), "not used to measure the noise", logging.INFO)


def achievable(read: list[tuple[Frame, list]], k: int, fit: NoiseFit) -> tuple[float, float]:
    """Cramer-Rao standard errors (sigma_o^2, alpha) of channel ``k``'s exposure contrasts on
    the drawn sites (:func:`~hdrmerge_cli.core.calibrate.achievable_errors`) at the fitted
    parameters, the frames' exposure ratios from their times (inf with one frame)."""
    from hdrmerge_cli.core.calibrate import achievable_errors  # scipy.ndimage: only where the noise is measured

    if len(read) < 2:
        return float("inf"), float("inf")
    times = [f.exposure_time for f, _ in read]
    ratios = [b / a if a and b and b > a else None for a, b in zip(times[:-1], times[1:])]
    _, _, lo, hi = read[0][1][k]
    return achievable_errors([planes[k][1] for _, planes in read], lo, hi, ratios, fit.coef)


def estimate_bracket_noise(frames: list[Frame], crf, load=load_codes, draw: NoiseDraw | None = None,
                           pairs: bool = True) -> tuple[dict, dict]:
    """merge without noise parameters: (17) per channel from the bracket itself, by the
    calibrate-noise code on :data:`~hdrmerge_cli.pipeline.noise_draw.FAST_PATH_SITES`
    sites per channel and frame (:func:`~hdrmerge_cli.pipeline.noise_draw.noise_tiles`;
    ``draw``: the codes drawn as the merge decoded the frames, else decoded here through
    ``load``).  Returns ({channel: {"sigma_o2", "alpha", "beta"}},
    {channel: profile entry}); the entry's ``stderr`` holds the fit's standard errors of
    sigma_o2 and alpha (:func:`~hdrmerge_cli.core.calibrate.fit_standard_errors`) and
    ``achievable_stderr`` the Cramer-Rao bound of the drawn sites' exposure contrasts
    (None where they hold none).

    Photographs do not measure beta (:mod:`hdrmerge_cli.core.calibrate`): it is 0.  ``pairs=False``:
    each frame's own local statistics alone, not the exposure pairs (a camera-processed
    bracket, whose pairs also hold what the processing adds, measured apart:
    :mod:`hdrmerge_cli.pipeline.excess`)."""
    from hdrmerge_cli.core.calibrate import estimate_noise, fit_standard_errors  # scipy.ndimage: only here

    iso = iso_key(frames[0].iso)
    draw = draw if draw is not None else NoiseDraw(frames)
    with ThreadPoolExecutor(2) as pool:  # SciPy's filters and NumPy's sorts release the GIL: both cores
        read = _read_drawn(sorted(frames, key=lambda f: f.exposure_time or 0.0), crf, load, draw, pool)
        if not read:
            raise HdrMergeError("no usable frame (all clipped or black)")

        def fit(k):
            name, _, lo, hi = read[0][1][k]
            try:
                est, ratios = estimate_noise([planes[k][1] for _, planes in read], lo, hi, pairs=pairs)
            except HdrMergeError as exc:
                return name, None, f"{read[0][0].path} ({iso}, channel {name}): {exc}", None, None
            return name, est, ratios, fit_standard_errors(est, bool(ratios)), achievable(read, k, est)

        fits = list(pool.map(fit, range(len(read[0][1]))))
    measured = [f for f in fits if f[1] is not None]
    if not measured:
        raise HdrMergeError(fits[0][2])
    used, entries = {}, {}
    sites = min(c.drawn for c in draw.drawn[read[0][0].path])
    for name, est, ratios, se, crb in measured:
        entries[name] = fit_entry(est, ratios, 7) | {"subsample_sites": sites} | precision_entry(se, crb)
        used[name] = {"sigma_o2": est.sigma_o2, "alpha": est.alpha, "beta": 0.0}
    # a channel the bracket cannot measure (clipped or black nearly everywhere) takes the
    # median of the measured channels': the same sensor, up to the white balance's gain (the
    # entry says so; the caller tells the user)
    stand_in = {p: float(np.median([used[f[0]][p] for f in measured])) for p in ("sigma_o2", "alpha")}
    for name, est, why, _, _ in fits:
        if est is None:
            used[name] = stand_in | {"beta": 0.0}
            entries[name] = {"stand_in_from": [f[0] for f in measured], "reason": why}
    return {name: used[name] for name, *_ in fits}, {name: entries[name] for name, *_ in fits}


def precision_entry(se: tuple[float, float], crb: tuple[float, float]) -> dict:
    """A profile entry's ``stderr`` (the fit's standard errors of sigma_o2 and alpha) and
    ``achievable_stderr`` (the Cramer-Rao bound of the bracket's exposure contrasts; None
    where it holds none)."""
    return {"stderr": {"sigma_o2": rounded(se[0]), "alpha": rounded(se[1])},
            "achievable_stderr": ({"sigma_o2": rounded(crb[0]), "alpha": rounded(crb[1])}
                                  if np.isfinite(crb[0]) and np.isfinite(crb[1]) else None)}


def rounded(x: float) -> float | None:
    return float(f"{x:.4g}") if np.isfinite(x) else None
