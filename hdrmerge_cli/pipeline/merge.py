"""The merge stage: the frames' held codes through (7), strip by strip, then re-weighting
at the merged estimate (:func:`reconstruct`); and the checks after it (the output type's
range, samples no frame measured, frames of equal exposure that disagree)."""
from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core import resample
from hdrmerge_cli.core.reconstruct import FLAG_DARK, FLAG_SATURATED, STRIP_ROWS, LogMerge, irls, noise_rows
from hdrmerge_cli.io.frames import Frame
from hdrmerge_cli.io.metadata import fmt_time
from hdrmerge_cli.io.noisespec import per_channel

log = logging.getLogger("hdrmerge_cli")

if TYPE_CHECKING:
    from hdrmerge_cli.pipeline.choices import Models


@dataclass
class Reconstruction:
    """What :func:`reconstruct` returns, per sample of the frames (a RAW mosaic ``(H, W)``,
    an image ``(H, W, C)``).

    result : float32, ``E * h_ref``: scene-linear, 1.0 = the full-scale signal of an
        exposure of ``h_ref`` seconds
    flags : int8, 0, ``FLAG_DARK`` (below every frame's noise floor: an upper bound) or
        ``FLAG_SATURATED`` (clipped in every frame: a lower bound)
    den : float32, the summed weights of the frames that measured each sample
    variance : float32 like ``result``, its variance under the noise model, or None
    iterations : the re-weighting passes run
    """

    result: np.ndarray
    flags: np.ndarray
    den: np.ndarray
    variance: np.ndarray | None = None
    iterations: int = 0


def reconstruct(frames: list[Frame], exposures: np.ndarray, h_ref: float, models: Models, load, weights_of,
                timings: dict, with_variance: bool = False) -> Reconstruction:
    """The frames through (7) (:func:`_first_pass`), then ``models.n_irls`` passes of
    re-weighting at the merged estimate (:func:`~hdrmerge_cli.core.reconstruct.irls`), both
    reading the frames' held codes (``load``), with the per-sample weights ``weights_of``
    (:class:`~hdrmerge_cli.pipeline.merge.SampleWeights`, or None); the variance of
    ``E * h_ref`` with ``with_variance``.  The stages' seconds are added to ``timings``."""
    ml = models.estimator == "ml"
    # without IRLS the first pass returns the linear image directly
    first = _first_pass(frames, models.tables, models.pattern, ml, None if models.n_irls else h_ref, load, weights_of,
                        with_variance and not models.n_irls, timings)
    if not models.n_irls:
        return first
    t0 = time.perf_counter()
    maps = [noise_rows(per_channel(n, models.table_channels))
            for n in models.frame_noise or [models.noise] * len(frames)]
    y_full = [float(f.white[0] - f.black[0]) for f in frames]
    result, den = first.result, first.den  # IRLS makes its own flags; it writes over the estimate and weights
    del first
    it = irls(lambda k: load(frames[k]), models.tables, models.pattern, result, exposures, y_full, maps, ml,
              models.n_irls, variance=with_variance, adjust=None if weights_of is None else weights_of.adjust, den=den)
    log.info("IRLS: %d passes, largest change of the last %.2e", it.passes, it.change)
    result = np.exp(it.log_e, out=it.log_e)
    result *= np.float32(h_ref)
    variance = it.variance
    if variance is not None:  # Var(E h_ref) = (E h_ref)^2 Var(log E), the delta method
        variance *= result * result
    timings["irls"] = time.perf_counter() - t0
    return Reconstruction(result, it.flags, it.den, variance, it.passes)


# ---------------------------------------------------------------- per-sample weights
def sample_weights(tables, pattern, frames: list[Frame], ghosts, alignment, load, validity: list):
    """The per-sample weights of the merge (a :class:`SampleWeights`), or None when no
    frame has transparent pixels and neither the deghosting nor the alignment is applied.
    ``ghosts``, ``alignment``: the stages' results (or None); ``load``: the merge's
    loader, an :class:`~hdrmerge_cli.pipeline.register.AlignedLoader` when it keeps the
    resampling's spreads; ``validity``: :func:`~hdrmerge_cli.pipeline.register.frame_validity`."""
    ghosts = ghosts if ghosts is not None and ghosts.applied else None
    alignment = alignment if alignment is not None and alignment.applied else None
    if ghosts is None and alignment is None and all(v is None for v in validity):
        return None
    return SampleWeights(tables, pattern, frames, ghosts, alignment, load if hasattr(load, "spread") else None,
                         validity)


class SampleWeights:
    """``(k, codes) -> weights`` of frame ``k`` for the merge (see :meth:`LogMerge.add`):
    its table weight ``w(z) sigma^-2`` through :meth:`adjust`, which also re-weights the
    IRLS passes (:func:`~hdrmerge_cli.core.reconstruct.irls`)."""

    def __init__(self, tables, pattern, frames, ghosts, alignment, load, validity=None):
        self.tables, self.pattern, self.frames = tables, pattern, frames
        self.ghosts, self.alignment, self.load = ghosts, alignment, load
        self.validity = validity or [None] * len(frames)
        self.slopes: dict[int, np.ndarray] = {}  # per frame, its value table's slope

    def factor(self, k: int, rows: slice | None = None) -> np.ndarray | None:
        """``(H, W)`` float32 in [0, 1] per pixel (an image's channels share it), or None
        (all 1): zero where the aligned frame does not cover the reference or is
        transparent, ``1 - m`` in its rejected ghost cells (feathered ``m``, so no seam);
        ``rows``: those rows only."""
        frame, ghosts, alignment = self.frames[k], self.ghosts, self.alignment
        out = None
        if ghosts is not None and ghosts.mask_of(frame).any():
            out = ghosts.weight(frame, frame.height, frame.width, rows)
            np.subtract(np.float32(1.0), out, out=out)
        valid = self.validity[k]
        masks = [None if valid is None else valid[rows or slice(None)]]
        if alignment is not None:
            masks.append(alignment.coverage(frame, rows))
        for inside in masks:
            if inside is not None:
                out = inside.astype(np.float32) if out is None else np.multiply(out, inside, out=out)
        return out

    def _weighted(self, k: int, codes: np.ndarray, w: np.ndarray | None, own: bool,
                  rows: slice | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """``w`` (None: the table's, for a resampled frame) with the resampling's variance
        added and times :meth:`factor` (broadcast over an image's channels), and the
        factor; ``own``: ``w`` may be overwritten (a fresh full-size array costs its page
        faults, tenths of a second at 24 MP); ``rows``: ``codes`` and ``w`` are those rows
        of the frame."""
        spread = self.load.spread(self.frames[k]) if self.load is not None else None
        if spread is not None:
            rows = rows or slice(0, spread.shape[0])
            if k not in self.slopes:
                self.slopes[k] = value_slope(self.tables[k])
            part = spread[rows]
            w, own = resampled_weight(w, self.tables[k], codes, self.pattern, part.reshape(part.shape[0], -1),
                                      self.alignment.warp_of(self.frames[k]), self.slopes[k], out=w if own else None,
                                      cfa=self.frames[k].cfa_pattern, row0=rows.indices(spread.shape[0])[0]), True
        f = self.factor(k, rows)
        if f is None:
            return w, None
        per_pixel = w.reshape(f.shape + (-1,))
        out = np.multiply(per_pixel, f[..., None], out=per_pixel if own else None)
        return out.reshape(w.shape), f

    def adjust(self, k: int, codes: np.ndarray, w: np.ndarray, own: bool = False,
               rows: slice | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Inverse-variance weights ``w`` (``(H, W')``) of frame ``k``'s ``codes`` with the
        resampling's variance added (:func:`resampled_weight`), times :meth:`factor`;
        returns ``(weights, factor)``, the factor per sample ``(H, W')``.  ``own``: the
        weights may be written into ``w`` (the caller's buffer, else left as it is);
        ``rows``: ``codes`` and ``w`` are those rows of the frame (a strip of the IRLS)."""
        out, f = self._weighted(k, codes, w, own=own, rows=rows)
        if f is not None and f.shape != out.shape:
            f = np.repeat(f, out.shape[1] // f.shape[1], axis=1)
        return out, f

    def __call__(self, k: int, codes: np.ndarray, rows: slice | None = None
                 ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``(weight, factor)`` for :meth:`LogMerge.add` of frame ``k``'s ``codes`` (``rows``:
        those rows of the frame): where the frame was not resampled with a spread (images;
        RAW moved by whole CFA periods) only the per-pixel :meth:`factor` (weight None),
        which the merge applies to the table's weights in its own pass; else the per-sample
        weights (``codes``' shape, float32) with the factor in them, and the factor, which
        then only says where the frame is a sample's own."""
        if self.load is None or self.load.spread(self.frames[k]) is None:
            return None, self.factor(k, rows)
        w, f = self._weighted(k, codes, None, own=True, rows=rows)  # the table's weights, read in the same pass
        return w.reshape(codes.shape).astype(np.float32, copy=False), f


def resampled_weight(w: np.ndarray | None, tables, codes: np.ndarray, pattern, spread: np.ndarray,
                     warp: np.ndarray, slope: np.ndarray, out: np.ndarray | None = None, cfa: str | None = None,
                     row0: int = 0) -> np.ndarray:
    """Inverse-variance weights ``w`` (``(H, W)``; None: the table's) of the samples of a
    mosaic resampled by ``warp`` with the interpolation's variance added
    (:func:`~hdrmerge_cli.core.resample.resampled_weight_mosaic`), from the frame's
    ``tables``: the slope of its value table (linear or log value per code) and its
    certainty ``w(z)`` (``slope``: :func:`value_slope`).  ``out`` may be ``w``; ``row0``:
    the arrays are rows ``row0`` on of the frame."""
    return resample.resampled_weight_mosaic(w, codes, pattern, slope, tables.certainty, tables.n_codes, spread, warp,
                                         out, weight=tables.weight, cfa=cfa, row0=row0)


def value_slope(tables) -> np.ndarray:
    """The slope of a frame's value table per code (flattened ``(R * N,)`` float32), for
    :func:`resampled_weight`."""
    n = tables.n_codes
    return np.gradient(tables.value.reshape(-1, n).astype(np.float64), axis=1).astype(np.float32).ravel()


# ---------------------------------------------------------------- checks after the merge
#: samples (about) of each equal-exposure frame kept to check that the frames agree
REPEAT_SAMPLES = 1 << 18


@dataclass
class Repeats:
    """Frames of equal exposure (indices into the frames, runs of two or more) and, by
    frame, the subsample of codes the merge's loader kept of each (:func:`watch_repeats`)."""

    groups: list[list[int]]
    seen: dict[int, np.ndarray]


def watch_repeats(load, frames: list[Frame], groups: list[list[int]]) -> tuple:
    """Frames of equal exposure (``groups``: the bracket's runs,
    :func:`~hdrmerge_cli.io.metadata.equal_exposure_groups`) are merged; to check that they
    agree, a loader that keeps an even subsample of their codes as the merge decodes them
    (no extra decode).  Returns ``(loader, Repeats)``."""
    seen: dict[int, np.ndarray] = {}
    if not groups:
        return load, Repeats(groups, seen)
    watched = {id(frames[i]) for g in groups for i in g}
    h, w = frames[0].height, frames[0].width
    step = 2 * max(1, int(np.ceil(np.sqrt(h * w / REPEAT_SAMPLES) / 2)))  # even: one CFA colour

    def watching(frame):
        codes = load(frame)
        if id(frame) in watched:
            seen[id(frame)] = codes[::step, ::step].copy()
        return codes

    return watching, Repeats(groups, seen)


def _linear_sample(frame: Frame, codes: np.ndarray, crf: CRF) -> np.ndarray:
    """Linear values (1 = full scale) of a frame's codes (RAW: one CFA colour, mean black)."""
    if frame.kind == "raw":
        black = float(np.mean(frame.black))
        return (codes.astype(np.float64) - black) / (float(np.max(frame.white)) - black)
    return crf.linear(codes, frame.n_codes)


def check_repeats(repeats: Repeats, frames: list[Frame], crf: CRF) -> list[dict]:
    """Each frame of an equal-exposure group against the group's first: a warning when
    they disagree beyond the noise (:func:`~hdrmerge_cli.core.repeats.compare_repeat`): a
    changed exposure, or content (motion).  Returns the comparisons for ``--json``."""
    from hdrmerge_cli.core.repeats import compare_repeat

    report = []
    seen = repeats.seen
    for g in repeats.groups:
        a = frames[g[0]]
        for k in g[1:]:
            b = frames[k]
            if id(a) not in seen or id(b) not in seen:
                continue
            (za, la), (zb, lb) = [(seen[id(f)], _linear_sample(f, seen[id(f)], crf)) for f in (a, b)]
            check = compare_repeat(za, zb, la, lb)
            entry = {"frames": [a.path, b.path], "exposure_time": b.exposure_time}
            if check is None:
                report.append(entry | {"compared": False})
                continue
            report.append(entry | {"compared": True, "ratio_ev": round(check.ratio_ev, 4),
                                   "outlier_fraction": check.outliers, "samples": check.samples})
            if check.exposure_changed:
                given = b.time_source != "its metadata"
                log.warning("%s: the same exposure (%s) as %s by %s, but %.2f stops %s: the exposure changed "
                            "between them (%s)", b.path, fmt_time(b.exposure_time), a.name, b.time_source,
                            abs(check.ratio_ev), "brighter" if check.ratio_ev > 0 else "darker",
                            f"check {b.time_source}" if given else "check the metadata or give --times")
            elif check.content_differs:
                log.warning("%s: the same exposure as %s, but %.1f %% of the pixels differ beyond the noise (motion "
                            "between the frames?); consider --align auto or --deghost auto", b.path, a.name,
                            100 * check.outliers)
    return report


#: largest finite value and smallest normal value of the output types
OUTPUT_RANGE = {True: (65504.0, 6.1e-5), False: (3.4e38, 1.2e-38)}


def check_range(result: np.ndarray, half: bool, reference: str, h_ref: float, exposures: np.ndarray,
                crf: CRF) -> None:
    """Refuse a result that the output type cannot hold (instead of writing clamped values
    or a mostly zero image): values above its largest finite value, or a median below its
    smallest normal value.  The scale is set by ``--reference`` (any of the
    ``exposures``), so the error names it where another reference would fit, and the
    response (``crf``) where none would."""
    top, tiny = OUTPUT_RANGE[half]
    peak = float(np.max(result, initial=0.0))
    flat = result.reshape(-1)
    median = float(np.median(flat[::max(1, flat.size // 100_000)]))
    kind = "half" if half else "float"
    drop = " or drop --half" if half else ""
    low, high = float(np.min(exposures)) / h_ref, float(np.max(exposures)) / h_ref  # the rescaling any reference gives
    over, under = not np.isfinite(peak) or peak > top, median < tiny
    if not over and not under:
        return
    if (over and not peak * low <= top) or (under and not median * high >= tiny):
        raise HdrMergeError(f"the camera response ({crf.describe()}) maps the codes to merged values from {median:.3g} "
                            f"(the median) to {peak:.3g}, which {kind} EXR cannot hold ({tiny:g} to {top:g}) at any "
                            f"--reference; check the response{drop}")
    if over:
        raise HdrMergeError(f"--reference {reference} ({h_ref:.3g} s): the brightest values ({peak:.3g}) exceed what "
                            f"{kind} EXR holds ({top:g}); use a shorter --reference (e.g. shortest){drop}")
    raise HdrMergeError(f"--reference {reference} ({h_ref:.3g} s): most values are below what {kind} EXR holds "
                        f"({tiny:g}); use a longer --reference (e.g. longest){drop}")


def warn_unmeasured(frames: list[Frame], result: np.ndarray, flags: np.ndarray) -> None:
    """One warning when no sample was measured in any frame (``flags`` all dark or
    saturated): the output then holds bounds, not measurements, and says which."""
    dark = np.count_nonzero(flags == FLAG_DARK)
    saturated = np.count_nonzero(flags == FLAG_SATURATED)
    if dark + saturated < flags.size:
        return
    where = f"{frames[0].path} ... {frames[-1].name}" if len(frames) > 1 else frames[0].path
    if saturated == 0:
        log.warning("%s: every pixel reads black in every frame; the output holds only an upper bound (%.3g, half a "
                    "code in the longest exposure), not a measurement", where, float(np.max(result)))
    elif dark == 0:
        log.warning("%s: every pixel is clipped in every frame; the output holds only a lower bound (%.3g, the "
                    "shortest exposure's clipping level), not a measurement", where, float(np.min(result)))
    else:
        log.warning("%s: no pixel is measured in any frame (%.1f %% read black in every frame, %.1f %% are clipped in "
                    "every frame); the output holds only bounds, not measurements", where,
                    100 * dark / flags.size, 100 * saturated / flags.size)


# ---------------------------------------------------------------- the first pass
def _first_pass(frames, tables, pattern, linear, scale, load, weights_of, variance, timings: dict) -> Reconstruction:
    """(7) over the frames' codes (``load``: held, or resampled on first use, two frames at
    a time), in strips of :data:`~hdrmerge_cli.core.reconstruct.STRIP_ROWS` rows of
    every frame: the sums, and the per-sample weights of moved or deghosted frames
    (``weights_of(k, codes, rows)``), are strip-sized.  Returns a :class:`Reconstruction`
    whose result is ``log E``, or ``E * scale`` when ``scale`` is given (see
    :meth:`LogMerge.finish`), with ``variance`` its variance (:attr:`LogMerge.variance`);
    the seconds of decoding and merging go to ``timings``."""
    shape = (frames[0].height, frames[0].width) + (() if frames[0].kind == "raw" else (frames[0].channels,))

    def decode(frame):
        codes = load(frame)
        if codes.shape != shape:
            raise HdrMergeError(f"{frame.path}: decoded size {codes.shape} differs from the metadata {shape}")
        return codes

    t_start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=2) as pool:
        codes = list(pool.map(decode, frames))
    decode_time = time.perf_counter() - t_start
    result = np.empty(shape, np.float32)
    flags = np.empty(shape, np.int8)
    den = np.empty(shape, np.float32)
    var = np.empty(shape, np.float32) if variance else None
    height, last = shape[0], len(frames) - 1
    for r0 in range(0, height, STRIP_ROWS):
        part = slice(r0, min(height, r0 + STRIP_ROWS))
        acc = LogMerge(result[part].shape, pattern, variance=variance)
        for k, z in enumerate(codes):
            weight, factor = (None, None) if weights_of is None else weights_of(k, z[part], part)
            acc.add(z[part], tables[k], last=k == last, weight=weight, factor=factor)
        result[part], flags[part] = acc.finish(linear, scale)
        den[part] = acc.den
        if variance:
            var[part] = acc.variance
    total = time.perf_counter() - t_start
    timings.update(decode=decode_time, merge=total - decode_time, decode_and_merge_wall=total)
    return Reconstruction(result, flags, den, var)
