"""The response: an image bracket's inverse response for the merge, measured on the
bracket's samples when none was given (:func:`measure_response`), else the per-camera
cache's, else none (sRGB assumed, with a warning); and ``estimate-crf``'s fit of a bracket
into a profile (:func:`start_crf`, :func:`fit_bracket`, :func:`finish_crf`, run in order by
:func:`hdrmerge_cli.pipeline.run.estimate_crf`), with the log lines of the fitter both go
through (:func:`~hdrmerge_cli.core.crf_estimate.fit_response`, :func:`log_fit`)."""
from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.crf import CRF, table_crf
from hdrmerge_cli.core.crf_estimate import (
    CRF_ESTIMATORS, MIN_OVERLAP, LabelledFit, ResponseFit, fit_response, histogram_correspondences, labelled_fit,
    pairs_pin_response, thin_overlap,
)
from hdrmerge_cli.core.crf_goossens2012 import DEFAULT_ANCHOR, DEFAULT_COUPLING, DEFAULT_WEIGHTING, knot_levels
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.exposure_estimate import estimate, response_fits
from hdrmerge_cli.core.samples import Samples
from hdrmerge_cli.core.weights import weights_debevec1997_triangle
from hdrmerge_cli.io.atomic import check_writable, write_together
from hdrmerge_cli.io.frames import Frame, load_codes
from hdrmerge_cli.io.metadata import equal_exposure_groups, exposure_values, fmt_time
from hdrmerge_cli.io.noisespec import parse_bounds
from hdrmerge_cli.io.plots import check_figure_path, figure_writer, pyplot
from hdrmerge_cli.io.profile import crf_to_json, load_profile, new_profile, profile_writer
from hdrmerge_cli.io.times import ESTIMATE

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
    :data:`~hdrmerge_cli.core.crf_estimate.MIN_OVERLAP` well-exposed pixels
    (:func:`~hdrmerge_cli.core.crf_estimate.pairs_pin_response`), else on the frames'
    histograms (Grossberg & Nayar 2003), which link frames with no such pixels through
    the scene's ranking; stored in the per-camera cache (``cache``,
    :mod:`hdrmerge_cli.io.noisecache`).  Where the frames cannot support a fit (fewer than
    two distinct exposures, or neighbours sharing fewer than :data:`~hdrmerge_cli.core.crf_estimate.MIN_OVERLAP` unclipped
    pixels) the cached response of the same camera and style, unless the frames contradict
    it (:func:`~hdrmerge_cli.core.exposure_estimate.response_fits`); else None, with a warning
    saying why and that sRGB is assumed."""
    from hdrmerge_cli.io import noisecache

    thin = thin_overlap(samples)
    fit, why, histograms = None, None, False
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
        why = "the fit is flat" if is_flat(fit.crf) else None
    key = noisecache.response_key(frames[0]) if cache else None
    if why is None:
        if noisecache.store_response(key, fit.crf.table, [f.path for f in frames]):
            log.debug("response of %s stored in %s", key, noisecache.response_file())
        return CRF(MEASURED_HISTOGRAMS if histograms else MEASURED, table=fit.crf.table)
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


# ---------------------------------------------------------------- estimate-crf

#: largest --lambda and --coupling: far beyond any useful smoothing (goossens solves up to
#: about 1, debevec's response is flat from about 1e7), below where the solvers overflow
MAX_SMOOTHING = 1e6


@dataclass
class CRFOptions:
    method: str = "goossens"
    smoothing: float | None = None  # None: the method's default
    samples: int | None = None  # None: the method's default; 0: every pixel
    weighting: str | None = None  # goossens only; None: its default
    pair_weight: str = "photon"
    bounds: str | None = None  # upper bounds of the bounded weights (noisespec syntax)
    times: list | None = None
    times_file: str | None = None
    seed: int = 0
    force: bool = False
    profile: str | None = None
    plot: Path | None = None
    overwrite: bool = False
    coupling: float = DEFAULT_COUPLING  # goossens: channel coupling of the joint solve
    anchor: float = DEFAULT_ANCHOR  # goossens: weight of the prior towards the standard curve


def check_samples(samples: int | None, n_frames: int, n_codes: int, n_pixels: int) -> None:
    """Refuse a --samples too few to determine the response: every code level needs data,
    N (P - 1) >= Zmax - Zmin (Debevec & Malik 1997); 0 or None (all pixels) passes."""
    need = -(-(knot_levels(n_codes) - 1) // (n_frames - 1))
    if samples and samples < min(need, n_pixels):
        raise HdrMergeError(f"--samples {samples}: too few pixels to determine a response of {n_codes} codes from "
                            f"{n_frames} frames; give at least {min(need, n_pixels)} (N (P - 1) >= Zmax - Zmin), "
                            "or 0 for all")


def check_not_flat(crf: CRF, method: str, smoothing: float | None) -> None:
    """Refuse an :func:`is_flat` fit, naming what flattened it."""
    if is_flat(crf):
        cause = (f"--lambda {smoothing:g} smooths the data away; give a smaller --lambda" if smoothing
                 else "the frames do not determine it; try --method goossens")
        raise HdrMergeError(f"the {method} fit is flat (less than one stop from code 1 to white): {cause}")


@dataclass
class BracketFit:
    """What :func:`fit_bracket` returns: a bracket's fitted response and what the profile, the figure and the report take from
    the fit (``fits`` empty, ``points`` and ``exposure_check`` None for the identity CRF of
    linear data)."""

    crf: CRF
    fits: list = field(default_factory=list)  # per channel the solver's result
    changed: bool = False  # whether the fit was made monotone
    points: tuple | None = None  # (codes, log_h): the frames' (H, W, C) codes and (P,) log exposures
    exposure_check: dict | None = None  # the labels checked through the response
    histograms: bool = False  # fitted on the frames' histograms (no neighbour pair pins it on pixels)


def _solver_options(method, opts: CRFOptions) -> dict:
    """The noise-weighted solvers' keywords (pair weight, bounds, coupling, anchor,
    weighting); empty for the others."""
    if not method.noise_weighted:
        return {}
    return dict(pair_weight=opts.pair_weight, bounds=parse_bounds(opts.bounds) if opts.bounds else None,
                coupling=opts.coupling, anchor=opts.anchor, **({"weighting": opts.weighting} if opts.weighting else {}))


def _fit_checked(codes, log_h: np.ndarray, n_codes: int, opts: CRFOptions, smoothing, n_samples,
                 options: dict) -> ResponseFit:
    """:func:`~hdrmerge_cli.core.crf_estimate.fit_response` at the log exposures ``log_h``
    ``(P,)`` (its log lines: :func:`log_fit`), refused when flat (:func:`check_not_flat`)."""
    fit = fit_response(codes, log_h, n_codes, opts.method, smoothing, n_samples, options,
                       np.random.default_rng(opts.seed))
    log_fit(fit, opts.method)
    check_not_flat(fit.crf, opts.method, smoothing)
    return fit


def decoded(frames, opts: CRFOptions) -> tuple[list[np.ndarray], np.ndarray]:
    """The frames' codes (decoded two at a time: the decoders release the GIL) and labels of
    a bracket to fit a response to, refused with fewer than two frames, too few
    ``--samples`` (:func:`check_samples`) or repeats that read differently
    (:func:`check_repeated_exposures`)."""
    first = frames[0]
    if len(frames) < 2:
        raise HdrMergeError(f"{first.path}: estimating a CRF needs at least two exposures")
    check_samples(opts.samples, len(frames), first.n_codes, first.width * first.height)
    with ThreadPoolExecutor(2) as pool:
        codes = list(pool.map(load_codes, frames))
    labels = exposure_values(frames)
    check_repeated_exposures(frames, labels, codes)
    return codes, labels


def fit_bracket(frames, codes: list[np.ndarray], labels: np.ndarray, samples: Samples, method, opts: CRFOptions,
                smoothing, n_samples) -> BracketFit:
    """The response fitted to a bracket of images (or of RAW frames under --force) on its
    decoded ``codes`` (the goossens method on the frames' histograms where no neighbour pair
    pins it on ``samples``' pixels); under --times estimate refitted with the estimates
    measured through it until they settle."""
    first = frames[0]
    if first.kind == "raw":
        codes = [c[..., None] for c in codes]
    histograms = opts.method == "goossens" and first.kind == "image" and not pairs_pin_response(samples)
    if histograms:
        log.info("no two neighbouring frames share %d well-exposed pixels: the response is fitted on the frames' "
                 "histograms", MIN_OVERLAP)
        codes = [h[:, None, :] for h in histogram_correspondences([c.reshape(-1, c.shape[-1]) for c in codes],
                                                                  first.n_codes, floors=samples.floor_codes)]
    log_h = np.log(labels)
    options = _solver_options(method, opts)
    fit = _fit_checked(codes, log_h, first.n_codes, opts, smoothing, n_samples, options)
    # --times estimate: refit with the estimates measured through the fit, until they settle (at most 3 rounds)
    est = estimate(labels, samples, fit.crf)
    for _ in range(3 if opts.times == ESTIMATE else 0):
        new_log_h = est.log_h
        fit = _fit_checked(codes, new_log_h, first.n_codes, opts, smoothing, n_samples, options)
        est = estimate(labels, samples, fit.crf)
        moved = float(np.max(np.abs(est.log_h - new_log_h))) / np.log(2)
        log_h = new_log_h
        if moved < 0.01:
            break
    return BracketFit(fit.crf, fit.fits, fit.changed, (codes, log_h), None, histograms)


def _fit_details(first, method, opts: CRFOptions, fit: BracketFit, smoothing, n_samples) -> dict:
    """The profile's ``crf`` details of the fit (method, channels, and for a fit its
    smoothing, samples, iterations, convergence and the noise-weighted solvers' settings)."""
    details = {"method": opts.method, "channels": first.channel_colors if first.kind == "image" else "linear"}
    if fit.fits:
        details |= {"lambda": smoothing, "samples": n_samples or "all",
                    "correspondences": ("the frames' histograms (no neighbour pair shares well-exposed pixels)"
                                        if fit.histograms else "pixels"),
                    "iterations": [f.iterations for f in fit.fits], "converged": all(f.converged for f in fit.fits)}
        if method.noise_weighted:
            details |= {"weighting": opts.weighting or DEFAULT_WEIGHTING,
                        "pair_weight": opts.pair_weight, "coupling": opts.coupling,
                        "anchor": opts.anchor, "prior": "srgb"}
    return details


def _profile_of(base: dict | None, frames, crf: CRF, details: dict, method_name: str) -> dict:
    """The profile to write: ``base`` (--profile) with its CRF replaced, or a new one for the
    bracket's camera; its ``crf`` carrying ``details``."""
    first = frames[0]
    command = f"estimate-crf --method {method_name}"
    if base is not None:
        profile = base
        profile["crf"] = crf_to_json(crf)
        profile.setdefault("provenance", {})["crf_command"] = command
    else:
        profile = new_profile({"make": first.make, "model": first.model}, first.bits, crf,
                              [f.path for f in frames], command)
    profile["crf"].update(details)
    return profile


@dataclass
class CRFJob:
    """An estimate-crf run once its options and outputs are checked (:func:`start_crf`): the
    method, where the profile goes (``updating``: in place), the ``--profile`` it updates,
    and the smoothing and samples in use."""

    method: object
    output: Path
    updating: bool
    base: dict | None
    smoothing: float | None
    n_samples: int | None
    t0: float


def start_crf(output: Path | None, opts: CRFOptions) -> CRFJob:
    """estimate-crf's outputs checked (before any frame is read)."""
    t0 = time.perf_counter()
    method = CRF_ESTIMATORS[opts.method]
    if output is None:
        if not opts.profile:
            raise HdrMergeError("give -o/--output (or --profile to update a profile in place)")
        output = Path(opts.profile)
    updating = opts.profile is not None and Path(opts.profile).resolve() == Path(output).resolve()
    check_writable(output, opts.overwrite or updating)
    if opts.plot is not None:
        check_figure_path(opts.plot, opts.overwrite)
    base = load_profile(opts.profile) if opts.profile else None
    smoothing = method.smoothing if opts.smoothing is None else opts.smoothing
    n_samples = method.samples if opts.samples is None else opts.samples
    return CRFJob(method, Path(output), updating, base, smoothing, n_samples, t0)


def finish_crf(job: CRFJob, frames: list[Frame], fit: BracketFit | None, opts: CRFOptions) -> dict:
    """The profile of the fit (an identity CRF for linear data, ``fit`` None) written with
    --plot's figure; the report."""
    first = frames[0]
    if fit is None:
        log.info("RAW data is linear: no CRF to estimate; writing an identity (linear) CRF (use --force to fit one)")
        fit = BracketFit(CRF("linear"))
    crf = fit.crf
    details = _fit_details(first, job.method, opts, fit, job.smoothing, job.n_samples)
    profile = _profile_of(job.base, frames, crf, details, opts.method)
    writers = [(job.output, profile_writer(profile, job.output))]
    if opts.plot is not None and fit.points is not None:
        writers.append((opts.plot, figure_writer(crf_figure(np.log(np.maximum(crf.table, 1e-300)), *fit.points, frames,
                                                            opts.seed), opts.plot)))
    write_together(writers, opts.overwrite or job.updating)
    return {
        "output": str(job.output), "method": opts.method, "frames": [f.summary() for f in frames],
        "crf": crf.describe(), "made_monotone": fit.changed, "exposure_check": fit.exposure_check,
        **{k: v for k, v in details.items() if k != "method"},
        "seconds": round(time.perf_counter() - job.t0, 4),
    }


def crf_figure(g: np.ndarray, codes: list[np.ndarray], log_h: np.ndarray, frames, seed: int = 0, points: int = 200):
    """Like Debevec & Malik's Fig. 3: per channel the recovered ``g(z)`` (log exposure
    against code value) and, for a few pixels, each frame's sample placed at
    ``log E_i + log h_j`` (``log E_i`` merged from its frames with triangle weights).

    g : (C, N) ``log gamma^-1``; codes : P arrays (H, W, C); log_h : (P,)
    """
    n_codes = g.shape[1]
    rng = np.random.default_rng(seed)
    v = np.arange(n_codes) / (n_codes - 1)
    w = weights_debevec1997_triangle(v, v)
    fig, axes = pyplot().subplots(1, g.shape[0], figsize=(4.2 * g.shape[0], 4), dpi=110, squeeze=False)
    names = frames[0].channel_names
    for c, ax in enumerate(axes[0]):
        z = np.stack([fr[..., c].ravel() for fr in codes], axis=1)
        z = z[rng.choice(len(z), min(points, len(z)), replace=False)].astype(np.int64)
        wz = w[z]
        ok = wz.sum(axis=1) > 0
        log_e = np.sum(wz * (g[c][z] - log_h), axis=1)[ok] / wz.sum(axis=1)[ok]
        for j in range(z.shape[1]):
            seen = (z[ok, j] > 0) & (z[ok, j] < n_codes - 1)  # clipped codes say nothing about g
            ax.plot((log_e + log_h[j])[seen], z[ok, j][seen], ".", ms=2.5, alpha=0.6, label=frames[j].name)
        ax.plot(g[c], np.arange(n_codes), "k-", lw=1.2, label="g(z)")
        ax.set_xlabel("log exposure  g(z) = log E + log h")
        ax.set_ylabel("code value z")
        ax.set_title(f"channel {names[c] if c < len(names) else c}")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, markerscale=3)
    fig.tight_layout()
    return fig


def check_repeated_exposures(frames, labels: np.ndarray, codes: list[np.ndarray]) -> None:
    """Frames labelled with one exposure are more data for the response, unless they read
    differently: a frame brighter or darker than its repeat (by more than
    :data:`~hdrmerge_cli.core.repeats.RATIO_TOLERANCE_EV` in code values, a monotone
    response's lower bound on the change) had another exposure, and is refused."""
    from hdrmerge_cli.core.repeats import compare_repeat

    top = float(frames[0].n_codes - 1)
    step = max(1, int(np.sqrt(codes[0].size / 300_000)))
    for group in equal_exposure_groups(labels):
        a = frames[group[0]]
        for k in group[1:]:
            za, zb = codes[group[0]][::step, ::step], codes[k][::step, ::step]
            check = compare_repeat(za, zb, za / top, zb / top)
            if check is not None and check.exposure_changed:
                raise HdrMergeError(f"{frames[k].path}: labelled the same exposure ({fmt_time(frames[k].exposure_time)}) "
                                    f"as {a.path}, but its code values are {2.0 ** check.ratio_ev:.3g}x "
                                    "that frame's: check the exposure times")
