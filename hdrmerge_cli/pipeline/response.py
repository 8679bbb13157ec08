"""The response stage: an image bracket's inverse response, measured on the bracket's
samples when none was given (:func:`measure_response`), else the per-camera cache's, else
none (sRGB assumed, with a warning); and the fitter every response estimate goes through
(:func:`fit_crf`, which ``estimate-crf`` shares)."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.crf import CRF, table_crf
from hdrmerge_cli.core.crf_estimate import ResponseFit, fit_response, labelled_fit
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.exposure_estimate import estimate, response_fits
from hdrmerge_cli.core.samples import MIN_OVERLAP, Samples, pairs_pin_response, thin_overlap
from hdrmerge_cli.io.frames import Frame

log = logging.getLogger("hdrmerge_cli")


def is_flat(crf: CRF) -> bool:
    """A fitted response that spans less than one stop from code 1 to white (any camera's
    spans many: sRGB 12 stops at 8 bits), which would merge every code to about white."""
    return bool(np.all(crf.table[:, 1] > 0.5))


def fit_crf(codes: list[np.ndarray], log_h: np.ndarray, n_codes: int, method: str = "goossens",
            smoothing: float | None = None, samples: int | None = None, options: dict | None = None,
            rng: np.random.Generator | None = None):
    """The inverse response of decoded frames: ``method`` of
    :data:`~hdrmerge_cli.core.crf_estimate.CRF_ESTIMATORS`, the channels in one coupled
    solve for a ``joint`` method (goossens: see its ``coupling``), one by one for the others.

    codes : P arrays (H, W, C) in increasing exposure order; log_h : (P,) ``log h_j``
    smoothing, samples : None for the method's defaults; options : the method's keywords
    Returns (CRF with a ``(C, n_codes)`` table, the per-channel fits, whether a fit had to
    be made monotone).
    """
    fit = fit_response(codes, log_h, n_codes, method, smoothing, samples, options, rng)
    log_fit(fit, method)
    return fit.crf, fit.fits, fit.changed


def log_fit(fit: ResponseFit, method: str) -> None:
    """The log lines of a fit: per channel its iterations and data rows, and a warning when
    it had to be made monotone."""
    for c, f in enumerate(fit.fits):
        log.info("channel %d: %s fit in %d iteration(s)%s, %d data rows", c, method, f.iterations,
                 "" if f.converged else " (not converged)", f.rows)
    if fit.changed:
        log.warning("the %s fit was not monotone; it was made non-decreasing", method)


def measure_response(frames: list[Frame], exposures: np.ndarray, samples: Samples, cache: bool = True) -> CRF | None:
    """The response of an image bracket given none, fitted on the samples the merge draws
    (:func:`~hdrmerge_cli.pipeline.exposure_check.sample_frames`, constant borders off) by
    estimate-crf's default method, its prior towards sRGB deciding where the frames leave
    the curve open: on the samples' pixel pairs where some neighbour pair shares
    :data:`~hdrmerge_cli.core.samples.MIN_OVERLAP` well-exposed pixels
    (:func:`~hdrmerge_cli.core.samples.pairs_pin_response`), else on the frames'
    histograms (Grossberg & Nayar 2003), which link frames with no such pixels through
    the scene's ranking; stored in the per-camera cache (``cache``,
    :mod:`hdrmerge_cli.io.noisecache`).  Where the frames cannot support a fit (fewer than
    two distinct exposures, or neighbours sharing fewer than :data:`~hdrmerge_cli.core.samples.MIN_OVERLAP` unclipped
    pixels) the cached response of the same camera and style, unless the frames contradict
    it (:func:`~hdrmerge_cli.core.exposure_estimate.response_fits`); else None, with a warning
    saying why and that sRGB is assumed."""
    from hdrmerge_cli.io import noisecache

    key = noisecache.response_key(frames[0]) if cache else None
    thin = thin_overlap(samples)
    if len(np.unique(exposures)) < 2:
        why = "one exposure only"
    elif thin is not None:
        k, both = thin
        why = f"{frames[k - 1].name} and {frames[k].name} share {both} unclipped pixels"
    else:
        histograms = not pairs_pin_response(samples)
        if histograms:
            log.info("no two neighbouring frames share %d well-exposed pixels: the response is measured on the "
                     "frames' histograms", MIN_OVERLAP)
        crf = fit_with_labels(frames, exposures, samples, histograms)
        if not is_flat(crf):
            if noisecache.store_response(key, crf.table, [f.path for f in frames]):
                log.debug("response of %s stored in %s", key, noisecache.response_file())
            return CRF(MEASURED_HISTOGRAMS if histograms else MEASURED, table=crf.table)
        why = "the fit is flat"
    cached = _cached_response(frames, exposures, samples, key)
    if cached is not None:
        return cached
    log.warning("%s: no camera response given and none can be measured on this bracket (%s); assuming sRGB. Run "
                "'hdrmerge-cli estimate-crf' on a bracket of this camera and pass --crf PROFILE.json",
                frames[0].path, why)
    return None


def _cached_response(frames: list[Frame], exposures: np.ndarray, samples: Samples,
                     key: str | None) -> CRF | None:
    """The cached response of ``key`` (:func:`measure_response`), or None: none stored, a
    damaged entry, or frames whose ratios bend through it (most pairs, beyond the label
    tolerance)."""
    from hdrmerge_cli.io import noisecache

    hit = noisecache.lookup_response(key)
    if hit is None:
        return None
    try:
        crf = CRF(CACHED, table=table_crf(np.asarray(hit["inverse"], np.float64)).table)
        if crf.table.shape != (frames[0].channels, frames[0].n_codes):
            return None
    except (HdrMergeError, ValueError):
        return None
    if len(frames) > 1 and not response_fits(estimate(exposures, samples, crf)):
        log.info("the cached response of %s does not fit these frames; not used", key)
        return None
    log.info("camera response of %s from the cache %s (measured on %s, %s)", key, noisecache.response_file(),
             ", ".join(Path(p).name for p in hit.get("inputs", [])), hit.get("date"))
    return crf


def fit_with_labels(frames: list[Frame], exposures: np.ndarray, samples: Samples, histograms: bool = False) -> CRF:
    """The response and the labels judged together
    (:func:`~hdrmerge_cli.core.crf_estimate.labelled_fit`: fit with the labels on the
    samples' pixels, or with ``histograms`` on their histograms, and while a frame's label
    is off in a way a label explains, refit with that frame's estimate in place of its
    label), with its log lines."""
    fit = labelled_fit(samples, exposures, histograms)
    for r in fit.rounds:
        log_fit(r, "goossens")
    log.info("camera response measured on the bracket (goossens, %d %s per frame%s)", fit.rows,
             "histogram levels" if histograms else "samples",
             f"; fitted with the measured exposures of {', '.join(frames[k].name for k in fit.replaced)}"
             if fit.replaced else "")
    return fit.crf


#: the name of a response :func:`measure_response` fitted on the bracket being merged
MEASURED = "measured on the bracket (estimate-crf defaults)"
#: ... fitted on the frames' histograms: no neighbour pair shares enough well-exposed pixels
MEASURED_HISTOGRAMS = "measured on the bracket's histograms (no neighbours share enough well-exposed pixels)"
#: the name of a response :func:`measure_response` read from the per-camera cache
CACHED = "measured earlier on this camera (cache)"
