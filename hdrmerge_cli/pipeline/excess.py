"""The excess variance of a camera-processed bracket
(:mod:`hdrmerge_cli.core.excess_variance`) measured on the samples the exposure check drew."""
from __future__ import annotations

import logging

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.excess_variance import (MATERIAL_DB, ExcessVariance, fit_excess_variance, level_of,
                                               with_effect)
from hdrmerge_cli.core.noise import DEFAULT_K, NoiseParams, code_variance
from hdrmerge_cli.core.reconstruct import quantisation_variance
from hdrmerge_cli.io.noisespec import per_channel

log = logging.getLogger("hdrmerge_cli")

#: largest model standard deviation of ``log E`` of a reading the pairs use: the moments of
#: ``g(z)`` are expanded to second order in the relative deviation ``s`` (variance
#: ``s^2 + 2.5 s^4``, bias ``-s^2 / 2``); at 15 % the terms left out are below 1 % of the
#: variance
MAX_MODEL_SD = 0.15

#: pair samples in all (a seeded draw shared evenly by the frame pairs and channels): the
#: term's few levels need no more
MAX_SAMPLES = 1 << 17


def _log_tables(lin: np.ndarray, noise: NoiseParams | None):
    """Per code value of one channel (``lin``: its row of
    :meth:`~hdrmerge_cli.core.crf.CRF.codes_table`, ``(N,)``; the results ``(N,)`` each): ``g(z)``
    less its bias and the model's variance of it, from the relative variance ``s^2 = v(y) / y^2`` of the noise (17) and
    the quantisation through the response to second order (``-s^2 / 2``, ``s^2 + 2.5 s^4``);
    NaN where ``g`` is undefined or the reading lies outside the clipping-safe range of (47)
    (``k = 3`` standard deviations from black and full scale)."""
    y_full = lin.size - 1.0
    y = lin * y_full
    var = quantisation_variance(lin, y_full) + (code_variance(y, noise) if noise is not None else 0.0)
    # inside the clipping-safe range of (47): a reading within k standard deviations of
    # black or full scale is a truncated one, whose pair difference the model misjudges
    sd = DEFAULT_K * np.sqrt(var)
    ok = (lin > 0) & (y - sd > 0) & (y + sd < y_full)
    with np.errstate(divide="ignore", invalid="ignore"):
        s2 = np.where(ok, var / np.where(ok, y, 1.0) ** 2, np.nan)
        g = np.where(ok, np.log(np.where(ok, lin, 1.0)) + s2 / 2.0, np.nan)
        v_log = s2 + 2.5 * s2 * s2
    return g, v_log


def measure_excess(samples, exposures: np.ndarray, crf: CRF, noise: dict[str, NoiseParams] | None,
                   channel_names: list[str], seed: int = 0) -> ExcessVariance:
    """Fit the excess term on every pair of frames, each channel's readings where both
    frames' codes are unclipped and the model's sd of ``log E`` is at most
    :data:`MAX_MODEL_SD`, off the constant borders; keep it where it is pinned and changes
    the predicted error of the merge materially
    (:func:`~hdrmerge_cli.core.excess_variance.with_effect`, over every sample's readings).

    samples : :class:`~hdrmerge_cli.core.samples.Samples` of an image bracket
        (registered onto the reference where the bracket was aligned)
    exposures : (K,) the frames' exposures in seconds, as the merge uses them
    noise : per channel parameters of (17) in code units, or None (quantisation alone)
    """
    rng = np.random.default_rng(seed)
    params = per_channel(noise, channel_names) if noise else [None] * len(channel_names)
    channels = samples.v[0].shape[-1]
    lin = crf.codes_table(int(round(1.0 / samples.codes_step)) + 1, np.zeros(channels))
    tables = [_log_tables(lin[c], params[min(c, len(params) - 1)]) for c in range(channels)]
    terms = []
    for k, v in enumerate(samples.v):
        flat = v[samples.inside]
        z = np.rint(np.clip(flat, 0.0, 1.0) * (tables[0][0].size - 1)).astype(np.int64)
        terms.append((flat, np.log(exposures[k]), [(g[z[:, c]], var[z[:, c]]) for c, (g, var) in enumerate(tables)]))
    d_all, base_all, la, lb = [], [], [], []
    limit = MAX_MODEL_SD ** 2 * (1.0 + 2.5 * MAX_MODEL_SD ** 2)  # v_log at s = MAX_MODEL_SD
    per_pair = MAX_SAMPLES // max(1, len(terms) * (len(terms) - 1) // 2 * channels)
    for j in range(len(terms)):
        for m in range(j + 1, len(terms)):
            (vj, hj, cj), (vm, hm, cm) = terms[j], terms[m]
            for c in range(vj.shape[1]):
                gj, bj = cj[c]
                gm, bm = cm[c]
                ok = np.flatnonzero(np.isfinite(gj) & np.isfinite(gm) & (bj <= limit) & (bm <= limit))
                if ok.size < 2:
                    continue
                if ok.size > per_pair:
                    ok = np.sort(rng.choice(ok, per_pair, replace=False))
                d = (gm[ok] - hm) - (gj[ok] - hj)
                d_all.append(d - np.median(d))
                base_all.append(bj[ok] + bm[ok])
                la.append(level_of(vj[ok, c]))
                lb.append(level_of(vm[ok, c]))
    empty = [np.zeros(0)], [np.ones(0)], [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    d_all, base_all, la, lb = (x or e for x, e in zip((d_all, base_all, la, lb), empty))
    fit = fit_excess_variance(np.concatenate(d_all), np.concatenate(base_all), np.concatenate(la), np.concatenate(lb))
    # every sample's readings (K, n x channels): the model's variance of log E and the level
    model_var = np.stack([np.concatenate([var for _, var in chans]) for _, _, chans in terms])
    levels = np.stack([level_of(flat.T.ravel()) for flat, _, _ in terms])
    fit = with_effect(fit, model_var, levels)
    if not fit.tested:
        log.info("variance beyond the noise model: %d pair samples, too few to test the model", fit.samples)
    elif np.isnan(fit.effect_db):
        log.info("variance beyond the noise model on %d pair samples: the pairs' variance is %.3g x the "
                 "model's, within its test (statistic %.1f): no excess kept", fit.samples, fit.chi_model, fit.statistic)
    else:
        log.info("variance beyond the noise model on %d pair samples: the pairs' variance is %.3g +- %.2g x the "
                 "model's; it raises the predicted error of the merge by %.2f dB (at least %.2f dB), %s",
                 fit.samples, fit.chi_model, fit.chi_stderr, fit.effect_db, fit.effect_db_low,
                 f"excess kept, sd of log E per level up to {np.sqrt(fit.levels.max()):.3f}" if fit.kept
                 else f"below the {MATERIAL_DB:g} dB that matters: no excess kept")
    return fit
