"""The merge core on decoded frames in memory, every option given explicitly: for the
benchmarks (accuracy, speed, leave-one-out) and the tests, not a user path.

``hdrmerge-cli merge`` and the Python API (:func:`hdrmerge_cli.merge`) run the same tables
and kernels of :mod:`hdrmerge_cli.core.reconstruct` (``exposure_tables``, ``LogMerge``,
``reweight``) through :func:`hdrmerge_cli.core.reconstruct.merge`, with the weights,
variance factor, noise and re-weighting passes the choices stage picked; here they are the
caller's.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.noise import DEFAULT_K, NoiseParams
from hdrmerge_cli.core import reconstruct
from hdrmerge_cli.core.reconstruct import ExposureTables, LogMerge, exposure_tables, noise_rows, reweight
from hdrmerge_cli.pipeline.choices import table_size


def merge_frames(codes: list[np.ndarray], exposures, crf: CRF, black, white, weighting: str = "triangle",
                 noise: list[NoiseParams] | None = None, variance: str = "none", estimator: str = "log",
                 prior_rate: float | None = None, k: float = DEFAULT_K, pattern: np.ndarray | None = None,
                 scale: float = 1.0, irls_iterations: int = 0, with_variance: bool = False,
                 variance_tables=None, excess=None, frame_noise: list[list[NoiseParams]] | None = None):
    """The merge core on decoded frames in memory: (7) (or the ML estimator) with the
    tables of :func:`~hdrmerge_cli.core.reconstruct.exposure_tables`, optionally re-weighted
    (:func:`~hdrmerge_cli.core.reconstruct.irls`), every option given explicitly.

    with_variance : also return the noise model's variance of ``E * scale`` (streamed
        with ``LogMerge(variance=True)``, or from ``irls``), a fourth element;
        ``variance_tables`` optional per-frame ``(R * N,)`` tables to use instead of
        ``estimate_variance_table``'s defaults (e.g. with ``tolerance=0``)
    excess : the variance beyond the noise model measured on the bracket, for the tables
        (``exposure_tables``)

    codes : P arrays ``(H, W)`` or ``(H, W, C)`` uint8/uint16 in increasing exposure order
    exposures : (P,) ``h_j`` in seconds
    black, white : (R,) levels per table row (R = 1, or one per row of ``pattern``)
    noise : R noise parameter sets (code units), needed by the noise-model weights'
        exact form, ``variance='model'``, ``estimator='ml'`` and IRLS
    frame_noise : P lists of R noise parameter sets, frame j's own (frames that differ in
        ISO: code units of that frame, whose gain ``h_j`` already counts); it replaces
        ``noise`` in the tables and the IRLS passes
    Returns ``(E * scale, flags, summed weights)``, float32/int8/float32.
    """
    black = np.atleast_1d(np.asarray(black, np.float64))
    white = np.broadcast_to(np.asarray(white, np.float64), black.shape)
    n_codes = table_size(white, int(np.iinfo(codes[0].dtype).max) + 1)
    streamed_var = with_variance and not irls_iterations  # IRLS brings its own variance
    if frame_noise is not None and len(frame_noise) != len(exposures):
        raise ValueError(f"frame_noise: {len(frame_noise)} sets for {len(exposures)} frames")
    noise_of = [noise] * len(exposures) if frame_noise is None else list(frame_noise)
    tables = [exposure_tables(crf.at_codes(n_codes, black, white), weighting, h, noise_of[j], variance, prior_rate,
                              tuple(exposures), k, estimator=estimator,
                              with_variance=streamed_var and variance_tables is None, excess=excess)
              for j, h in enumerate(exposures)]
    if streamed_var:
        if variance_tables is not None:
            tables = [replace(t, variance=np.asarray(q, np.float32)) for t, q in zip(tables, variance_tables)]
        acc = LogMerge(codes[0].shape, pattern, variance=True)
        for j, z in enumerate(codes):
            acc.add(z, tables[j], last=j == len(codes) - 1)
        out, flags = acc.finish(estimator == "ml", scale)
        return out, flags, acc.den, acc.variance
    if not irls_iterations:
        return merge_in_memory(codes, tables, pattern, estimator == "ml", scale)
    log_e, flags, den = merge_in_memory(codes, tables, pattern, estimator == "ml")
    y_full = [float(white[0] - black[0])] * len(codes)
    rows = [noise_rows(noise)] * len(codes) if frame_noise is None else [noise_rows(p) for p in frame_noise]
    it = irls(codes.__getitem__, tables, pattern, log_e, exposures, y_full, rows, estimator == "ml", irls_iterations,
              variance=with_variance, den=den)
    log_e, flags, den, var = it.result, it.flags, it.den, it.variance
    out = np.exp(log_e, out=log_e)
    out *= np.float32(scale)
    if not with_variance:
        return out, flags, den
    var *= out * out  # Var(E scale) = (E scale)^2 Var(log E), the delta method
    return out, flags, den, np.minimum(var, np.float32(3.4e38), out=var)


def merge_in_memory(codes, tables: list[ExposureTables], pattern: np.ndarray | None = None, linear: bool = False,
            scale: float | None = None):
    """(7) over the frames, streamed one at a time through ``LogMerge`` (as the merge's
    first pass): ``(result, flag, den)`` as ``LogMerge.finish`` with ``den`` the summed
    weights."""
    acc = LogMerge(codes[0].shape, pattern)
    for j, z in enumerate(codes):
        acc.add(z, tables[j], last=j == len(codes) - 1)
    out, flags = acc.finish(linear, scale)
    return out, flags, acc.den


def irls(codes_of, tables: list[ExposureTables], pattern, log_e: np.ndarray, exposures, y_full, rows,
         linear: bool, iterations: int, tol: float = reconstruct.IRLS_TOLERANCE, variance: bool = False, adjust=None,
         den: np.ndarray | None = None) -> reconstruct.Reconstruction:
    """:func:`~hdrmerge_cli.core.reconstruct.reweight` over strips of
    :data:`~hdrmerge_cli.core.reconstruct.STRIP_ROWS` rows, each iterated to its own
    convergence, as the merge runs it (:func:`~hdrmerge_cli.core.reconstruct.merge`): the
    new estimate and ``den`` written over ``log_e`` and ``den``; ``adjust(k, codes, w, own,
    rows)`` gets each strip's rows.  Returns a ``Reconstruction`` (the passes and change the
    most of any strip)."""
    flags = np.empty(log_e.shape, np.int8)
    given = den is not None
    den = den if given else np.empty(log_e.shape, np.float32)
    var = np.empty(log_e.shape, np.float32) if variance else None
    passes, change = 0, 0.0
    for r0 in range(0, log_e.shape[0], reconstruct.STRIP_ROWS):
        part = slice(r0, min(log_e.shape[0], r0 + reconstruct.STRIP_ROWS))
        piece = reweight(lambda k: codes_of(k)[part], tables, pattern, log_e[part], exposures, y_full, rows, linear,
                         iterations, tol, variance, None if adjust is None else (lambda *a: adjust(*a, part)),
                         den[part] if given else None)
        log_e[part], flags[part], den[part] = piece.result, piece.flags, piece.den
        if variance:
            var[part] = piece.variance
        passes, change = max(passes, piece.iterations), max(change, piece.change)
    return reconstruct.Reconstruction(log_e, flags, den, var, passes, change)
