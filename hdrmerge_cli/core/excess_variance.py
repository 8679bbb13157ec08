"""Variance beyond the noise model, measured on exposure pairs.

Two frames ``j`` and ``l`` of a still bracket see the same irradiance, so their terms of
(7), ``x = g(z) - log h`` with ``g = log gamma^-1``, differ at a pixel by
``d = x_l - x_j``, whose variance under the model is ``V_j + V_l``: ``V`` the variance of
``g(z)`` from (17) carried through the response (the delta method: ``v(y) / y^2``) plus
the quantisation of the codes (:func:`hdrmerge_cli.core.noise.quantisation_variance`), both as
:func:`hdrmerge_cli.core.noise.log_tables` gives them per code value.
What a camera's processing adds on top (tone curves that differ between frames, local tone
mapping, noise reduction, sharpening, compression) shows as ``d^2`` above that sum.  It is
modelled as a variance of ``log E`` per code level, shared by the frames,
``e(v) >= 0`` on :data:`N_LEVELS` bins of the normalised code ``v``::

    E[d^2] = V_j(z_j) + V_l(z_l) + e(v_j) + e(v_l)

and fitted by non-negative weighted least squares of ``d^2``, each weighted by the inverse of
its standard deviation ``sqrt(2) E[d^2]`` at the current fit (for Gaussian ``d``,
``d^2 / E[d^2]`` is chi-square with one degree of freedom), with a soft-L1 loss of scale
:data:`SOFT_L1_SCALE` on those standardised residuals, so that the few pixels where
something moved do not decide the fit.  A robust loss cuts the chi-square's long upper
tail and would bias the variance low; the residuals are therefore taken against
``KAPPA E[d^2]``, with :data:`KAPPA` the root of ``E[u((x - k) / sqrt 2) (x - k)] = 0`` for
``x ~ chi^2_1`` and the soft-L1 weight ``u(r) = (1 + (r / f)^2)^(-1/2)`` (Fisher
consistency: the fit is unbiased on Gaussian pairs).

The term is kept only where the pairs pin it and it matters (:func:`excess_effect_db`):

- *pinned*: without excess the statistic ``T = sum(d^2 / (V_j + V_l) - 1) / sqrt(2 n)`` is
  asymptotically standard normal, and ``T`` must exceed its ``1 - P_FALSE_ALARM`` quantile;
- *material*: with 10^5 pair samples any misfit above ~1.5 % passes that test, so the fitted
  excess must also raise the predicted error of the merged ``log E`` (the inverse-variance
  mean of the frames' readings, model variance against model plus excess) by at least
  :data:`MATERIAL_DB`, with the excess scaled down to the lower end of its uncertainty
  (``chi_model - 1`` less two standard errors of ``chi_model``).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, replace

import numpy as np

#: code-level bins of the excess term (uniform in the normalised code)
N_LEVELS = 32
#: false-alarm rate of the test that keeps the excess term (a bracket the model explains
#: gets one with this probability)
P_FALSE_ALARM = 1e-3
#: the least change of the predicted error of the merged ``log E`` (dB) for which the term
#: is kept: below it the noise model explains the bracket to within 26 % of its variance
MATERIAL_DB = 1.0
#: fewest pair samples to fit the term from
MIN_SAMPLES = 500
#: scale of the soft-L1 loss on the standardised residuals of ``d^2``
SOFT_L1_SCALE = 3.0
#: Fisher-consistency factor of that loss for chi-square(1) residuals (module docstring;
#: a test checks it by numerical integration)
KAPPA = 0.90344
#: largest model standard deviation of ``log E`` of a reading the pairs use: the moments of
#: ``g(z)`` are expanded to second order in the relative deviation ``s`` (variance
#: ``s^2 + 2.5 s^4``, bias ``-s^2 / 2``); at 15 % the terms left out are below 1 % of the
#: variance
MAX_MODEL_SD = 0.15
#: pair samples in all (a seeded draw shared evenly by the frame pairs and channels): the
#: term's few levels need no more
MAX_SAMPLES = 1 << 17


@dataclass(frozen=True)
class ExcessVariance:
    """The measured excess (see the module docstring).

    levels : (N_LEVELS,) float64, the excess variance of ``log E`` per code-level bin
        (zeros when the term is not kept)
    kept : whether the term is kept (pinned and material: module docstring)
    chi_model : mean ``d^2 / (V_j + V_l)`` of the model alone (1 when it explains the pairs)
    chi_fit : the same with the excess term
    statistic : the test statistic ``T``
    samples : pair samples used
    chi_stderr : standard error of ``chi_model`` (the sample standard deviation of
        ``d^2 / (V_j + V_l)`` over ``sqrt(n)``: no Gaussian assumption)
    effect_db : how much the fitted excess raises the predicted error of the merged
        ``log E`` (dB; nan where not fitted)
    effect_db_low : the same with the excess at the lower end of its uncertainty
    """

    levels: np.ndarray
    kept: bool
    chi_model: float
    chi_fit: float
    statistic: float
    samples: int
    chi_stderr: float = float("nan")
    effect_db: float = float("nan")
    effect_db_low: float = float("nan")

    @property
    def tested(self) -> bool:
        """Whether the pairs were enough to test the model (:data:`MIN_SAMPLES`)."""
        return self.samples >= MIN_SAMPLES

    def at(self, v: np.ndarray) -> np.ndarray:
        """The excess at normalised codes ``v`` (any shape; linear between bin centres,
        constant beyond the outer ones), in variance of ``log E``."""
        if not self.kept:
            return np.zeros(np.shape(v))
        centres = (np.arange(self.levels.size) + 0.5) / self.levels.size
        return np.interp(np.clip(v, 0.0, 1.0), centres, self.levels)

    def as_dict(self) -> dict:
        def num(x, digits):
            return round(float(x), digits) if np.isfinite(x) else None

        return {"tested": self.tested, "kept": self.kept, "levels_sd": [num(s, 4) for s in np.sqrt(self.levels)],
                "chi_model": num(self.chi_model, 4), "chi_fit": num(self.chi_fit, 4),
                "statistic": num(self.statistic, 2), "samples": self.samples,
                "chi_stderr": num(self.chi_stderr, 5), "effect_db": num(self.effect_db, 3),
                "effect_db_low": num(self.effect_db_low, 3), "material_db": MATERIAL_DB}


def level_of(v: np.ndarray, n_levels: int = N_LEVELS) -> np.ndarray:
    """The bin index of normalised codes ``v`` (int64, same shape)."""
    return np.minimum((np.clip(v, 0.0, 1.0) * n_levels).astype(np.int64), n_levels - 1)


def fit_excess_variance(d: np.ndarray, base: np.ndarray, level_a: np.ndarray, level_b: np.ndarray,
                        n_levels: int = N_LEVELS, p_false_alarm: float = P_FALSE_ALARM,
                        iterations: int = 8) -> ExcessVariance:
    """Fit ``e`` of ``E[d^2] = base + e[level_a] + e[level_b]`` (module docstring).

    d : (n,) pair differences of ``log E`` (each pair's median removed by the caller: the
        exposures' errors are the label check's business)
    base : (n,) ``V_j + V_l`` of the model, > 0
    level_a, level_b : (n,) int code-level bins of the two readings (:func:`level_of`)
    Returns an :class:`ExcessVariance` whose ``kept`` says only that the test found the
    model short (pinned); :func:`with_effect` adds whether that matters.
    """
    from scipy.optimize import nnls
    from scipy.special import ndtri

    d2 = np.asarray(d, np.float64) ** 2
    base = np.maximum(np.asarray(base, np.float64), 1e-300)
    n = d2.size
    if n < MIN_SAMPLES:
        return ExcessVariance(np.zeros(n_levels), False, float("nan"), float("nan"), float("nan"), n)
    ratio = d2 / base
    chi_model = float(ratio.mean())
    chi_stderr = float(ratio.std(ddof=1) / np.sqrt(n))
    statistic = float((ratio - 1.0).sum() / np.sqrt(2.0 * n))
    if statistic <= ndtri(1.0 - p_false_alarm):
        return ExcessVariance(np.zeros(n_levels), False, chi_model, chi_model, statistic, n, chi_stderr)
    la, lb = np.asarray(level_a, np.int64), np.asarray(level_b, np.int64)
    used = np.bincount(np.concatenate([la, lb]), minlength=n_levels) > 0
    levels = np.zeros(n_levels)
    y = d2 / KAPPA
    for _ in range(iterations):
        pred = base + levels[la] + levels[lb]
        w = 1.0 / (np.sqrt(2.0) * pred)
        r = w * (y - pred)
        u2 = (w / np.sqrt(np.sqrt(1.0 + (r / SOFT_L1_SCALE) ** 2))) ** 2  # soft-L1 as re-weighted least squares
        levels[used] = _nnls_two_hot(la, lb, u2, y - base, n_levels, used, nnls)
    levels = _fill_empty(levels, used)
    chi_fit = float(np.mean(d2 / (base + levels[la] + levels[lb])))
    return ExcessVariance(levels, True, chi_model, chi_fit, statistic, n, chi_stderr)


def pair_excess(readings: list[np.ndarray], exposures: np.ndarray, tables: list[tuple[np.ndarray, np.ndarray]],
                seed: int = 0) -> ExcessVariance:
    """The excess term fitted on every pair of frames of a still bracket, kept where it is
    pinned and changes the predicted error of the merge materially (:func:`with_effect`,
    over every reading).

    readings : per frame ``(n, C)`` normalised codes of the same ``n`` pixels (registered
        onto the reference where the bracket was aligned), the frames sorted by exposure
    exposures : ``(K,)`` the frames' exposures
    tables : per channel ``(g, v_log)`` per code value
        (:func:`~hdrmerge_cli.core.noise.log_tables`)

    Each pair's channels use the readings where both frames' ``g`` is defined and the
    model's sd of ``log E`` is at most :data:`MAX_MODEL_SD` (at most :data:`MAX_SAMPLES`
    pair samples in all, a draw seeded by ``seed``), each pair's median difference removed.
    """
    rng = np.random.default_rng(seed)
    terms = []
    for flat, h in zip(readings, exposures):
        z = np.rint(np.clip(flat, 0.0, 1.0) * (tables[0][0].size - 1)).astype(np.int64)
        terms.append((flat, np.log(h), [(g[z[:, c]], var[z[:, c]]) for c, (g, var) in enumerate(tables)]))
    d_all, base_all, la, lb = [], [], [], []
    limit = MAX_MODEL_SD ** 2 * (1.0 + 2.5 * MAX_MODEL_SD ** 2)  # v_log at s = MAX_MODEL_SD
    per_pair = MAX_SAMPLES // max(1, len(terms) * (len(terms) - 1) // 2 * len(tables))
    for (vj, hj, cj), (vm, hm, cm) in itertools.combinations(terms, 2):
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
    return with_effect(fit, model_var, levels)


def excess_effect_db(model_var: np.ndarray, excess_var: np.ndarray) -> float:
    """How much an excess raises the predicted error of a merge (dB).

    model_var, excess_var : (K, n) variances of ``log E`` of the K frames' readings of n
        pixel-channels under the model and the excess; NaN or inf where a frame's reading
        is not used (clipped, undefined).
    Returns ``10 log10(sum_i m_i(V + e) / sum_i m_i(V))`` over the pixel-channels some frame
    reads, with ``m_i(V) = 1 / sum_k 1 / V_ki`` the variance of the inverse-variance mean
    of pixel ``i``'s readings (the linearised (7) with the weights of (20): the bound each
    estimator approaches); 0 where no frame reads any pixel.
    """
    v = np.where(np.isfinite(model_var), model_var, np.inf)
    e = np.where(np.isfinite(excess_var), excess_var, 0.0)
    info_model = np.sum(1.0 / v, axis=0)
    info_with = np.sum(1.0 / (v + e), axis=0)
    read = info_model > 0
    if not read.any():
        return 0.0
    return float(10.0 * np.log10(np.sum(1.0 / info_with[read]) / np.sum(1.0 / info_model[read])))


def with_effect(fit: ExcessVariance, model_var: np.ndarray, levels_of: np.ndarray) -> ExcessVariance:
    """``fit`` with its effect on the predicted error (:func:`excess_effect_db`) and
    ``kept`` only where the term is pinned and material (module docstring).

    model_var : (K, n) model variances of ``log E`` of the readings (as in
        :func:`excess_effect_db`)
    levels_of : (K, n) int code-level bins of the same readings (:func:`level_of`)
    """
    if not fit.kept:
        return fit
    excess = fit.levels[levels_of]
    effect = excess_effect_db(model_var, excess)
    excess_size = fit.chi_model - 1.0
    low = max(0.0, excess_size - 2.0 * fit.chi_stderr) / excess_size if excess_size > 0 else 0.0
    effect_low = excess_effect_db(model_var, low * excess)
    kept = effect_low >= MATERIAL_DB
    return replace(fit, kept=kept, levels=fit.levels if kept else np.zeros_like(fit.levels),
                   chi_fit=fit.chi_fit if kept else fit.chi_model, effect_db=effect, effect_db_low=effect_low)


def _nnls_two_hot(la, lb, u2, target, n_levels, used, nnls) -> np.ndarray:
    """``argmin_{e >= 0} sum u2 (e[la] + e[lb] - target)^2`` over the ``used`` levels, each
    row holding two ones (one 2 where ``la == lb``), by NNLS on the Cholesky factor of the
    normal equations (``n_levels^2`` numbers instead of an ``n x n_levels`` design)."""
    pair = np.bincount(la * n_levels + lb, u2, n_levels * n_levels).reshape(n_levels, n_levels)
    gram = pair + pair.T
    gram[np.diag_indices(n_levels)] += np.bincount(la, u2, n_levels) + np.bincount(lb, u2, n_levels)
    rhs = np.bincount(la, u2 * target, n_levels) + np.bincount(lb, u2 * target, n_levels)
    g, b = gram[np.ix_(used, used)], rhs[used]
    chol = np.linalg.cholesky(g + np.eye(g.shape[0]) * 1e-12 * np.trace(g) / g.shape[0])
    return nnls(chol.T, np.linalg.solve(chol, b))[0]


def _fill_empty(levels: np.ndarray, used: np.ndarray) -> np.ndarray:
    """Bins no pair sample reached take their nearest measured neighbour's value."""
    if used.all() or not used.any():
        return levels
    idx = np.flatnonzero(used)
    nearest = idx[np.abs(np.arange(levels.size)[:, None] - idx[None, :]).argmin(axis=1)]
    return levels[nearest]
