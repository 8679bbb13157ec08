"""The merge stage: the frames' held codes through (7) and re-weighting at the merged
estimate, strip by strip (:func:`reconstruct`, one call of
:func:`~hdrmerge_cli.core.reconstruct.merge`); and the checks after it, which read its
result (the output type's range, samples no frame measured, frames of equal exposure that
disagree)."""
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
from hdrmerge_cli.core.reconstruct import FLAG_DARK, FLAG_SATURATED, Reconstruction, merge
from hdrmerge_cli.io.frames import Frame, bracket_label
from hdrmerge_cli.io.metadata import fmt_time

log = logging.getLogger("hdrmerge_cli")

if TYPE_CHECKING:
    from hdrmerge_cli.pipeline.records import Bracket


@dataclass
class Merge:
    """What :func:`reconstruct` returns.

    reconstruction : the merged samples (:class:`~hdrmerge_cli.core.reconstruct.Reconstruction`)
    repeats : the comparisons of frames of equal exposure (:func:`check_repeats`), for ``--json``
    """

    reconstruction: Reconstruction
    repeats: list[dict]


def reconstruct(b: Bracket, load, validity: list, half: bool, reference: str, with_variance: bool = False) -> Merge:
    """The merge of the bracket ``b`` with its models (``b.models``): each frame's codes
    decoded once (``load``: the merge's loader, an
    :class:`~hdrmerge_cli.pipeline.register.AlignedLoader` when it keeps the resampling's
    spreads), weighted per sample where frames moved, are transparent or hold ghosts
    (:func:`sample_weights`; ``validity``:
    :func:`~hdrmerge_cli.pipeline.register.frame_validity`), through (7) and the models'
    re-weighting passes in one strip loop (:func:`~hdrmerge_cli.core.reconstruct.merge`),
    the variance of ``E * h_ref`` with ``with_variance``; then the checks on its result:
    the output type's range (``half``, ``reference``: :func:`check_range`), samples no
    frame measured, and frames of equal exposure.  The stages' seconds go to ``b.timings``."""
    frames, models = b.frames, b.models
    watching, repeats = watch_repeats(load, frames, b.repeats)
    weights = sample_weights(models.tables, models.pattern, frames, b.ghosts, b.alignment, load, validity)
    t0 = time.perf_counter()
    codes = _decode(frames, watching)
    decoded = time.perf_counter() - t0
    rec = merge(codes, models.tables, models.pattern, models.estimator == "ml", b.h_ref, weights, with_variance,
                models.n_irls, models.row_noise, b.exposures, [float(f.white[0] - f.black[0]) for f in frames],
                None if weights is None else weights.adjust)
    total = time.perf_counter() - t0 - rec.irls_seconds
    b.timings.update(decode=decoded, merge=total - decoded, decode_and_merge_wall=total)
    if models.n_irls:
        b.timings["irls"] = rec.irls_seconds
        log.info("IRLS: %d passes, largest change of the last %.2e", rec.iterations, rec.change)
    check_range(rec, half, reference, b.h_ref, b.exposures, b.crf)
    warn_unmeasured(frames, rec.result, rec.flags)
    return Merge(rec, check_repeats(repeats, frames, b.crf))


def _decode(frames: list[Frame], load) -> list[np.ndarray]:
    """Every frame's codes (``load``: held, or resampled on first use), two frames at a
    time; a frame whose decoded size is not its metadata's fails."""
    shape = (frames[0].height, frames[0].width) + (() if frames[0].kind == "raw" else (frames[0].channels,))

    def decode(frame):
        codes = load(frame)
        if codes.shape != shape:
            raise HdrMergeError(f"{frame.path}: decoded size {codes.shape} differs from the metadata {shape}")
        return codes

    with ThreadPoolExecutor(max_workers=2) as pool:
        return list(pool.map(decode, frames))


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
    re-weighting passes (:func:`~hdrmerge_cli.core.reconstruct.reweight`)."""

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


def check_range(rec: Reconstruction, half: bool, reference: str, h_ref: float, exposures: np.ndarray,
                crf: CRF) -> None:
    """Refuse a result that the output type cannot hold (instead of writing clamped values
    or a mostly zero image): values above its largest finite value, or a median below its
    smallest normal value (``rec.peak``, ``rec.median``).  The scale is set by ``--reference`` (any of the
    ``exposures``), so the error names it where another reference would fit, and the
    response (``crf``) where none would."""
    top, tiny = OUTPUT_RANGE[half]
    peak, median = rec.peak, rec.median
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
    where = bracket_label(frames)
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
