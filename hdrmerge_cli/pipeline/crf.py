"""estimate-crf: recover the inverse camera response of a bracket into a profile."""
from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.crf_estimate import CRF_ESTIMATORS
from hdrmerge_cli.core.crf_goossens2012 import DEFAULT_COUPLING, DEFAULT_WEIGHTING, DEFAULT_ANCHOR, knot_levels
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.samples import estimate
from hdrmerge_cli.core.weights import weights_debevec1997_triangle
from hdrmerge_cli.io.atomic import check_writable, write_together
from hdrmerge_cli.io.frames import load_codes
from hdrmerge_cli.io.metadata import exposure_values
from hdrmerge_cli.io.noisespec import parse_bounds
from hdrmerge_cli.io.plots import check_figure_path, figure_writer, pyplot
from hdrmerge_cli.io.profile import crf_to_json, load_profile, new_profile, profile_writer
from hdrmerge_cli.io.times import ESTIMATE
from hdrmerge_cli.pipeline import exposure_check
from hdrmerge_cli.pipeline.bracket import read_bracket
from hdrmerge_cli.pipeline.response import fit_crf, is_flat

log = logging.getLogger("hdrmerge_cli")

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


def estimate_crf(paths, output: Path | None, opts: CRFOptions) -> dict:
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
    frames = read_bracket(list(paths), opts.times, opts.times_file)
    first = frames[0]
    smoothing = method.smoothing if opts.smoothing is None else opts.smoothing
    n_samples = method.samples if opts.samples is None else opts.samples
    fits, changed, points, label_report = [], False, None, None
    if first.kind in ("raw", "linear") and not opts.force:
        log.info("RAW data is linear: no CRF to estimate; writing an identity (linear) CRF (use --force to fit one)")
        crf = CRF("linear")
    else:
        if len(frames) < 2:
            raise HdrMergeError(f"{first.path}: estimating a CRF needs at least two exposures")
        check_samples(opts.samples, len(frames), first.n_codes, first.width * first.height)
        with ThreadPoolExecutor(2) as pool:  # the decoders release the GIL: both cores
            codes = list(pool.map(load_codes, frames))
        by_frame = {id(f): c for f, c in zip(frames, codes)}
        labels = exposure_values(frames)
        samples = exposure_check.ordered_samples(frames, labels, lambda f: by_frame[id(f)])  # constant borders off
        del by_frame
        if first.kind == "raw":
            codes = [c[..., None] for c in codes]
        exposure_check.check_overlap(frames, samples)
        log_h = np.log(labels)
        options = {}
        if method.noise_weighted:
            options.update(pair_weight=opts.pair_weight, bounds=parse_bounds(opts.bounds) if opts.bounds else None,
                           coupling=opts.coupling, anchor=opts.anchor,
                           **({"weighting": opts.weighting} if opts.weighting else {}))
        crf, fits, changed = fit_crf(codes, log_h, first.n_codes, opts.method, smoothing, n_samples, options,
                                     np.random.default_rng(opts.seed))
        check_not_flat(crf, opts.method, smoothing)
        # the labels checked through the fitted response (the comparagrams the fit used);
        # --times estimate: refit with the estimates, until they settle (at most 3 rounds)
        est = estimate(labels, samples, crf)
        for _ in range(3 if opts.times == ESTIMATE else 0):
            new_log_h = est.log_h
            crf, fits, changed = fit_crf(codes, new_log_h, first.n_codes, opts.method, smoothing, n_samples, options,
                                         np.random.default_rng(opts.seed))
            check_not_flat(crf, opts.method, smoothing)
            est = estimate(labels, samples, crf)
            moved = float(np.max(np.abs(est.log_h - new_log_h))) / np.log(2)
            log_h = new_log_h
            if moved < 0.01:
                break
        motion = exposure_check.label_motion(samples, labels, crf, est)
        exposure_check.warn_mislabelled(frames, labels, est, "" if opts.times == ESTIMATE
                                       else "; estimate-crf --times estimate fits with the estimates", motion=motion,
                                       crf=crf)
        label_report = exposure_check.report(frames, labels, est,
                                              "estimates" if opts.times == ESTIMATE else "labels", crf, motion=motion)
        points = (codes, log_h)
    details = {"method": opts.method, "channels": first.channel_colors if first.kind == "image" else "linear"}
    if fits:
        details |= {"lambda": smoothing, "samples": n_samples or "all",
                    "iterations": [f.iterations for f in fits], "converged": all(f.converged for f in fits)}
        if method.noise_weighted:
            details |= {"weighting": opts.weighting or DEFAULT_WEIGHTING,
                        "pair_weight": opts.pair_weight, "coupling": opts.coupling,
                        "anchor": opts.anchor, "prior": "srgb"}
    command = f"estimate-crf --method {opts.method}"
    if base is not None:
        profile = base
        profile["crf"] = crf_to_json(crf)
        profile.setdefault("provenance", {})["crf_command"] = command
    else:
        profile = new_profile({"make": first.make, "model": first.model}, first.bits, crf,
                              [f.path for f in frames], command)
    profile["crf"].update(details)
    writers = [(output, profile_writer(profile, output))]
    if opts.plot is not None and points is not None:
        writers.append((opts.plot, figure_writer(crf_figure(np.log(np.maximum(crf.table, 1e-300)), *points, frames,
                                                            opts.seed), opts.plot)))
    write_together(writers, opts.overwrite or updating)
    return {
        "output": str(output), "method": opts.method, "frames": [f.summary() for f in frames],
        "crf": crf.describe(), "made_monotone": changed, "exposure_check": label_report, **{k: v for k, v in details.items() if k != "method"},
        "seconds": round(time.perf_counter() - t0, 4),
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
