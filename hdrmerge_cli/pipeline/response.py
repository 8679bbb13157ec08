"""The response stage: an image bracket's inverse response, measured on the bracket's
samples when none was given (:func:`measure_response`), else the per-camera cache's, else
none (sRGB assumed, with a warning); and the log lines of the fitter every response
estimate goes through (:func:`~hdrmerge_cli.core.crf_estimate.fit_response`, which
``estimate-crf`` shares: :func:`log_fit`)."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.crf import CRF, table_crf
from hdrmerge_cli.core.crf_estimate import LabelledFit, ResponseFit, labelled_fit
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.exposure_estimate import estimate, response_fits
from hdrmerge_cli.core.samples import MIN_OVERLAP, Samples, pairs_pin_response, thin_overlap
from hdrmerge_cli.io.frames import Frame

log = logging.getLogger("hdrmerge_cli")


def is_flat(crf: CRF) -> bool:
    """A fitted response that spans less than one stop from code 1 to white (any camera's
    spans many: sRGB 12 stops at 8 bits), which would merge every code to about white."""
    return bool(np.all(crf.table[:, 1] > 0.5))


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
    (:func:`~hdrmerge_cli.pipeline.exposure_check.ordered_samples`, constant borders off) by
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
        fit = labelled_fit(samples, exposures, histograms)
        log_labelled_fit(frames, fit, histograms)
        crf = fit.crf
        if not is_flat(crf):
            if noisecache.store_response(key, crf.table, [f.path for f in frames]):
                log.debug("response of %s stored in %s", key, noisecache.response_file())
            return CRF(MEASURED_HISTOGRAMS if histograms else MEASURED, table=crf.table)
        why = "the fit is flat"
    # the cached response of key, unless none is stored, the entry is damaged, or the frames'
    # ratios bend through it (most pairs, beyond the label tolerance)
    hit = noisecache.lookup_response(key)
    try:
        cached = None if hit is None else CRF(CACHED, table=table_crf(np.asarray(hit["inverse"], np.float64)).table)
    except (HdrMergeError, ValueError):
        cached = None
    if cached is not None and cached.table.shape != (frames[0].channels, frames[0].n_codes):
        cached = None
    if cached is not None and len(frames) > 1 and not response_fits(estimate(exposures, samples, cached)):
        log.info("the cached response of %s does not fit these frames; not used", key)
    elif cached is not None:
        log.info("camera response of %s from the cache %s (measured on %s, %s)", key, noisecache.response_file(),
                 ", ".join(Path(p).name for p in hit.get("inputs", [])), hit.get("date"))
        return cached
    log.warning("%s: no camera response given and none can be measured on this bracket (%s); assuming sRGB. Run "
                "'hdrmerge-cli estimate-crf' on a bracket of this camera and pass --crf PROFILE.json",
                frames[0].path, why)
    return None


def log_labelled_fit(frames: list[Frame], fit: LabelledFit, histograms: bool) -> None:
    """The log lines of :func:`~hdrmerge_cli.core.crf_estimate.labelled_fit`: each round's
    (:func:`log_fit`), then what the response was measured on and which labels it replaced."""
    for r in fit.rounds:
        log_fit(r, "goossens")
    log.info("camera response measured on the bracket (goossens, %d %s per frame%s)", fit.rows,
             "histogram levels" if histograms else "samples",
             f"; fitted with the measured exposures of {', '.join(frames[k].name for k in fit.replaced)}"
             if fit.replaced else "")


#: the name of a response :func:`measure_response` fitted on the bracket being merged
MEASURED = "measured on the bracket (estimate-crf defaults)"
#: ... fitted on the frames' histograms: no neighbour pair shares enough well-exposed pixels
MEASURED_HISTOGRAMS = "measured on the bracket's histograms (no neighbours share enough well-exposed pixels)"
#: the name of a response :func:`measure_response` read from the per-camera cache
CACHED = "measured earlier on this camera (cache)"
