"""The excess variance of a camera-processed bracket
(:mod:`hdrmerge_cli.core.excess_variance`) measured on the samples the exposure check drew."""
from __future__ import annotations

import logging

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.excess_variance import MATERIAL_DB, ExcessVariance, pair_excess
from hdrmerge_cli.core.noise import NoiseParams, log_tables

log = logging.getLogger("hdrmerge_cli")


def measure_excess(samples, exposures: np.ndarray, crf: CRF, noise: dict[str, NoiseParams] | None,
                   channel_names: list[str], seed: int = 0) -> ExcessVariance:
    """Fit the excess term on every pair of frames, each channel's readings where both
    frames' codes are unclipped and the model's sd of ``log E`` is at most
    :data:`~hdrmerge_cli.core.excess_variance.MAX_MODEL_SD`, off the constant borders
    (:func:`~hdrmerge_cli.core.excess_variance.pair_excess`, the model's moments of ``log
    E`` per code value by :func:`~hdrmerge_cli.core.noise.log_tables`); keep it where it is
    pinned and changes the predicted error of the merge materially.

    samples : :class:`~hdrmerge_cli.core.samples.Samples` of an image bracket
        (registered onto the reference where the bracket was aligned)
    exposures : (K,) the frames' exposures in seconds, as the merge uses them
    noise : per channel parameters of (17) in code units, or None (quantisation alone)
    """
    channels = samples.v[0].shape[-1]
    lin = crf.codes_table(int(round(1.0 / samples.codes_step)) + 1, np.zeros(channels))
    fit = pair_excess([v[samples.inside] for v in samples.v], exposures, log_tables(lin, noise, channel_names), seed)
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
