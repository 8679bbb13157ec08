"""Noise-optimal capture: which exposures (time, ISO) to shoot for a scene.

Hasinoff, Durand, Freeman, "Noise-optimal capture for high dynamic range photography",
CVPR 2010 (below: "Hasinoff"), with the noise model (17) of Goossens et al. 2012 per ISO.

Units.  ``r`` is the scene's irradiance at a photosite in code values per second at the
reference ISO (the ISO a gain of 1 stands for); a frame of exposure time ``t`` at gain
``g = ISO / reference ISO`` reads ``y ~ N(mu, v(mu))`` with ``mu = r t g`` and ``v`` the
code variance of (17) at that ISO (:func:`~hdrmerge_cli.core.noise.code_variance`).  The
frame's estimate of ``r`` is ``y / (t g)``, of variance ``v(mu) / (t g)^2``.

The merge of several frames is the inverse-variance (maximum-likelihood) average of the
frames' estimates, (7) with the weights of (12), clipped readings taken as censored; its
variance is ``1 / sum_j I_j(r)`` with ``I_j(r) = (t_j g_j)^2 / v_j(mu_j) T(z_j)`` the
Fisher information of frame j, ``T`` the share a reading censored at white keeps
(:func:`censored_factor`, ``z_j = (white - mu_j) / sd``), and its SNR is

    SNR(r) = r^2 sum_j I_j(r)          (as a power ratio; 10 log10 for dB).

Worst case.  The worst-case SNR of a bracket over a scene is the minimum of SNR(r) over
the scene's irradiances (Hasinoff's objective over the range ``[r_lo, r_hi]``), ``r_lo``
a low percentile of the scene's photosites, ``r_hi`` the brightest, and of that range
only the intervals the scene's photosites hold (:class:`SceneRange`; an irradiance no
photosite has is not part of the picture).  Away from the frames' clipping SNR(r) grows
with r (each term ``r^2 / (a + b r + c r^2)`` does); where a frame clips, SNR(r) dips as
its information goes, and turns to rise when little is left, about :data:`DIP_SDS`
standard deviations past white.  So the minimum lies at the start of an interval, at
the brightest photosite or at a frame's dip: :func:`critical_irradiances` lists those
(the programs at two points per dip, :data:`DIP_SDS`; a given plan's worst case at 35,
within 0.1 dB of the minimum over a dense grid, tested).

Plans.  SNR(r) is linear in the number of frames ``n_s`` shot with each setting s, so
the best worst case is a mixed-integer linear program over the counts (Hasinoff, Sec.
4): maximise ``tau`` subject to ``sum_s n_s r_i^2 I_s(r_i) >= tau`` at every critical
irradiance ``r_i``, ``sum_s n_s t_s <= T`` and ``sum_s n_s <= N``; or minimise the total
time subject to ``tau >= tau_min`` (:func:`shortest_plan`).  Both are solved by HiGHS
(``scipy.optimize.milp``) to a relative gap of 1e-2 (0.04 dB) unless its time limit
stops the branch and bound first (then the best plan found, with its gap).  Of the plans
within :data:`MARGIN_DB` of the best worst case, :func:`best_plan` then takes the one of
least mean error over the protected photosites (:func:`mean_snr_db`,
:func:`_least_mean_error`): the last fraction of a dB at the worst irradiance is not
worth several dB over the rest of the scene.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.excess_variance import MATERIAL_DB
from hdrmerge_cli.core.noise import NoiseParams, code_variance

#: shutter times of the 1/3-stop series as cameras label them (s), 1/8000 to 30 s
SHUTTER_THIRD_STOPS = (
    1 / 8000, 1 / 6400, 1 / 5000, 1 / 4000, 1 / 3200, 1 / 2500, 1 / 2000, 1 / 1600, 1 / 1250, 1 / 1000, 1 / 800,
    1 / 640, 1 / 500, 1 / 400, 1 / 320, 1 / 250, 1 / 200, 1 / 160, 1 / 125, 1 / 100, 1 / 80, 1 / 60, 1 / 50,
    1 / 40, 1 / 30, 1 / 25, 1 / 20, 1 / 15, 1 / 13, 1 / 10, 1 / 8, 1 / 6, 1 / 5, 1 / 4, 0.3, 0.4, 0.5, 0.6,
    0.8, 1.0, 1.3, 1.6, 2.0, 2.5, 3.2, 4.0, 5.0, 6.0, 8.0, 10.0, 13.0, 15.0, 20.0, 25.0, 30.0,
)

#: seconds HiGHS may search one program before it returns the best plan found
TIME_LIMIT = 4.0


#: standard deviations above white of a frame's mean at which the programs evaluate its
#: SNR dip: the censored reading keeps 13 % and 0.06 % of its information there
#: (:func:`censored_factor`); the merged SNR, falling as the frame's information goes,
#: turns to rise with r in between where other frames cover r, beyond where none does
DIP_SDS = (2.0, 4.0)
#: the same for a given plan's worst case (:func:`worst_case_snr_db`): dense, to 8 sds
DIP_SDS_DENSE = tuple(np.linspace(-0.5, 8.0, 35))


def censored_factor(z):
    """``T(z) = Phi(z) - z phi(z) + phi(z)^2 / Phi(-z)``: the Fisher information about the
    mean of a normal reading censored above white, relative to an uncensored reading (the
    Tobit model), ``z = (white - mean) / sd``.  1 far below white, 0.82 at white, 0.13 two
    sds above.  The merge's ML estimator takes clipped readings as censored
    (the censored terms of :func:`~hdrmerge_cli.core.reconstruct.irls`)."""
    from scipy.special import log_ndtr, ndtr

    z = np.asarray(z, dtype=np.float64)
    log_phi = -0.5 * z * z - 0.5 * np.log(2 * np.pi)
    phi = np.exp(log_phi)
    mills = np.exp(log_phi - log_ndtr(-z))  # phi(z) / Phi(-z), without 0 / 0 far below white
    return np.clip(ndtr(z) - z * phi + phi * mills, 0.0, 1.0)


@dataclass(frozen=True)
class Setting:
    """One camera setting: exposure ``time`` (s) at ``iso``, its ``gain`` (ISO over the
    reference ISO), the noise (17) per channel at that ISO (code values), and per channel
    the full scale ``white`` (code values above black)."""

    time: float
    iso: float
    gain: float
    noise: tuple[NoiseParams, ...]
    white: tuple[float, ...]

    @property
    def scale(self) -> float:
        """``t g``: code values per unit of ``r``."""
        return self.time * self.gain

    def information(self, r, channel: int) -> np.ndarray:
        """``I(r) = (t g)^2 / v(mu) T(z)`` with ``mu = r t g``, ``z = (white - mu) /
        sqrt(v(mu))``: the Fisher information about ``r`` of one frame ((12) per frame),
        its clipped readings censored (:func:`censored_factor`).  ``r``: array, code values
        per second."""
        r = np.asarray(r, dtype=np.float64)
        mu = r * self.scale
        v = code_variance(mu, self.noise[channel])
        return self.scale ** 2 / v * censored_factor((self.white[channel] - mu) / np.sqrt(v))

    def clipping_point(self, channel: int, sds=0.0):
        """The irradiance at which the frame's mean lies ``sds`` standard deviations above
        white (:func:`dip_mean`; 0: at white); ``sds`` a number or an array."""
        return dip_mean(self.noise[channel], self.white[channel], sds) / self.scale


def dip_mean(p: NoiseParams, white: float, sds):
    """The mean ``mu`` with ``mu - white = sds sqrt(v(mu))``, ``v`` of (17): a quadratic
    in ``mu`` (cf. (47), whose clipping-safe bound is ``sds = -k``).  ``sds``: a number
    or an array (then an array of means)."""
    z = np.asarray(sds, dtype=np.float64)
    c = 1.0 - z * z * p.beta / p.alpha
    b = 2 * white + z * z * np.sqrt(p.alpha)
    root = np.sqrt(np.maximum(b * b - 4 * c * (white * white - z * z * p.sigma_o2), 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        mu = (b + np.sign(z) * root) / (2 * np.where(c > 0, c, 1.0))
    # gain FPN so large that the sd grows as fast as the mean: a step past white
    step = white + z * np.sqrt(code_variance(np.float64(white), p))
    mu = np.where(z == 0, white, np.where(c > 0, mu, step))
    return float(mu) if mu.ndim == 0 else mu


def make_settings(times, isos, noise_at_iso: dict, reference_iso: float, y_full) -> list[Setting]:
    """Every (time, ISO) pair as a :class:`Setting`.  ``noise_at_iso``: ISO -> per-channel
    tuple of :class:`NoiseParams`; ``y_full``: full scale (white minus black, code values),
    one for every channel or one per channel."""
    out = []
    for iso in isos:
        noise = tuple(noise_at_iso[iso])
        white = tuple(float(w) for w in np.broadcast_to(np.asarray(y_full, dtype=np.float64), (len(noise),)))
        out += [Setting(float(t), float(iso), float(iso) / reference_iso, noise, white) for t in times]
    return out


@dataclass(frozen=True)
class SceneRange:
    """The irradiances a plan must measure, per channel: ``lo`` and ``hi``, the ends of the
    range it protects (code values per second at the reference ISO; the darkest and the
    brightest photosites beyond them may be lost); ``occupied``: per channel, the
    ``(start, end)`` intervals of that range the scene's photosites hold (empty: all of
    it); ``photosites``: per channel ``(r, share)``, the scene's photosites as irradiances
    (bin centres; 0 for those that read no light) and the share of the channel's
    photosites at each (empty: the range held evenly in log r, :data:`EVEN_BIN_EV`)."""

    lo: tuple[float, ...]
    hi: tuple[float, ...]
    occupied: tuple = ()
    photosites: tuple = field(default=(), compare=False)

    def intervals(self, channel: int) -> list[tuple[float, float]]:
        if not self.occupied or not len(self.occupied[channel]):
            return [(self.lo[channel], self.hi[channel])]
        lo, hi = self.lo[channel], self.hi[channel]
        spans = [(max(a, lo), min(b, hi)) for a, b in self.occupied[channel] if b >= lo and a <= hi]
        return spans or [(lo, hi)]

    def population(self, channel: int, protected: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """``(r, share)`` of the channel's photosites; with ``protected``, only those from
        ``lo`` to ``hi`` (their shares still of all the channel's photosites)."""
        if self.photosites:
            r, w = (np.asarray(a, dtype=np.float64) for a in self.photosites[channel])
        else:
            lo, hi = self.lo[channel], self.hi[channel]
            n = max(1, int(np.ceil(np.log2(hi / lo) / EVEN_BIN_EV)))
            r = lo * 2.0 ** ((np.arange(n) + 0.5) * np.log2(hi / lo) / n)
            w = np.full(n, 1.0 / n)
        if protected:
            keep = (r >= self.lo[channel]) & (r <= self.hi[channel])
            r, w = r[keep], w[keep]
        return r, w

    @property
    def channels(self) -> int:
        return len(self.lo)


#: bins (EV) of a scene's photosites when only its range is known (:class:`SceneRange`)
EVEN_BIN_EV = 1 / 12


def critical_irradiances(settings: list[Setting], scene: SceneRange, channel: int,
                          sds: tuple = DIP_SDS) -> np.ndarray:
    """Where a worst case over the scene's irradiances (its occupied intervals of
    ``[lo, hi]``) lies for any plan built from ``settings``: the start of each interval,
    each setting's dip (its mean ``sds`` standard deviations past white) inside one (see
    the module notes), and ``hi``, however few photosites are that bright.  Sorted, code
    values per second."""
    spans = np.array(scene.intervals(channel))
    # settings of one scale and noise share their points
    keys = {(s.scale, s.noise[channel], s.white[channel]): s for s in settings}
    z = np.asarray(sds, dtype=np.float64)
    points = np.concatenate([s.clipping_point(channel, z) for s in keys.values()])
    inside = np.any((points[:, None] > spans[None, :, 0]) & (points[:, None] <= spans[None, :, 1]), axis=1)
    return np.unique(np.r_[spans[:, 0], scene.hi[channel], points[inside]])


def snr_power(r, plan: list[tuple[Setting, int]], channel: int) -> np.ndarray:
    """``SNR(r) = r^2 sum_j n_j I_j(r)`` of a plan of ``(setting, count)`` pairs (a power
    ratio; 0 where no frame measures r)."""
    r = np.asarray(r, dtype=np.float64)
    info = sum((n * s.information(r, channel) for s, n in plan if n), np.zeros_like(r))
    return r * r * info


def snr_db(r, plan: list[tuple[Setting, int]], channel: int) -> np.ndarray:
    """:func:`snr_power` in dB (``-inf`` where nothing measures r)."""
    with np.errstate(divide="ignore"):
        return 10.0 * np.log10(snr_power(r, plan, channel))


def worst_case_snr_db(plan: list[tuple[Setting, int]], scene: SceneRange) -> float:
    """The minimum of SNR(r) over every channel's irradiances (:meth:`SceneRange.intervals`
    and ``hi``), in dB, at the critical irradiances of the plan's own settings with
    :data:`DIP_SDS_DENSE`; ``-inf`` where some irradiance is measured by no frame."""
    settings = [s for s, n in plan if n]
    if not settings:
        return float("-inf")
    return float(min(np.min(snr_db(critical_irradiances(settings, scene, c, DIP_SDS_DENSE), plan, c))
                     for c in range(scene.channels)))


def mean_snr_db(plan: list[tuple[Setting, int]], scene: SceneRange) -> float:
    """The SNR of the mean error over the protected photosites: ``-10 log10`` of the mean
    of ``1 / SNR(r)`` over every channel's photosites from ``lo`` to ``hi``
    (:meth:`SceneRange.population`, each channel weighed alike), i.e. the predicted mean
    squared error of the merged log E (the relative error of E to first order); ``-inf``
    where a protected photosite is measured by no frame."""
    total = weight = 0.0
    for c in range(scene.channels):
        r, w = scene.population(c, protected=True)
        p = snr_power(r, plan, c)
        if np.any(p[w > 0] <= 0):
            return float("-inf")
        total += float(np.sum(w / np.where(p > 0, p, 1.0)))
        weight += float(np.sum(w))
    return float(10.0 * np.log10(weight / total)) if total > 0 else float("inf")


def percentile_snr_db(plan: list[tuple[Setting, int]], scene: SceneRange, q: float) -> float:
    """The SNR (dB) that all but ``q`` % of the scene's photosites reach or pass: the
    ``q``-th percentile of SNR(r) over every channel's photosites, lost ones included
    (:meth:`SceneRange.population`, each channel weighed alike)."""
    values, weights = [], []
    for c in range(scene.channels):
        r, w = scene.population(c)
        values.append(snr_db(r, plan, c))
        weights.append(w / max(float(np.sum(w)), 1e-300))
    return weighted_percentile(np.concatenate(values), np.concatenate(weights), q)


def weighted_percentile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    """The ``q``-th percentile (%) of ``values`` (N,) each counted ``weights`` (N,) times:
    the smallest value whose cumulative weight reaches ``q`` % of the total."""
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(weights[order]) / np.sum(weights)
    return float(values[order][min(int(np.searchsorted(cum, q / 100.0)), values.size - 1)])


#: of the scene's photosites, the share (%) at which a plan's low end is reported
LOW_PERCENTILE = 1.0


@dataclass(frozen=True)
class Plan:
    """A solved plan: ``frames`` as ``(setting, count)`` pairs in increasing exposure, its
    worst-case SNR, the SNR of its mean error over the protected photosites
    (:func:`mean_snr_db`) and the SNR its :data:`LOW_PERCENTILE` % lowest photosites miss
    (:func:`percentile_snr_db`) (dB), total time (s), and how the solver ended
    (``optimal``, or the relative gap of the best plan found when the time limit stopped
    it); ``lowest_iso``: the best plan at the lowest ISO alone, where the search solved it
    first."""

    frames: list
    worst_snr_db: float
    total_time: float
    mean_snr_db: float = float("nan")
    low_snr_db: float = float("nan")
    optimal: bool = True
    gap: float = 0.0
    lowest_iso: "Plan | None" = None


def evaluate(frames: list[tuple[Setting, int]], scene: SceneRange, optimal: bool = True, gap: float = 0.0) -> Plan:
    """``frames`` as a :class:`Plan`, sorted by exposure, with its statistics over ``scene``."""
    frames = sorted(((s, int(n)) for s, n in frames if n > 0), key=lambda p: (p[0].scale, p[0].iso))
    return Plan(frames, worst_case_snr_db(frames, scene), float(sum(s.time * n for s, n in frames)),
                mean_snr_db(frames, scene), percentile_snr_db(frames, scene, LOW_PERCENTILE), optimal, gap)


def _program(settings, scene):
    """The rows ``r_i^2 I_s(r_i)`` of the program (one per channel and critical
    irradiance) over the settings' columns."""
    rows = []
    for c in range(scene.channels):
        r = critical_irradiances(settings, scene, c)
        rows.append(np.stack([r * r * s.information(r, c) for s in settings], axis=1))
    return np.vstack(rows)


def _solve(c, constraints, n_settings, max_frames, time_limit, at_least: float = 0.0):
    """HiGHS on counts (integers, the first ``n_settings`` variables) and any continuous
    variables after them (``tau``, bounded below by ``at_least``)."""
    from scipy.optimize import Bounds, milp

    integrality = np.r_[np.ones(n_settings), np.zeros(len(c) - n_settings)]
    upper = np.r_[np.full(n_settings, float(max_frames)), np.full(len(c) - n_settings, np.inf)]
    lower = np.r_[np.zeros(n_settings), np.full(len(c) - n_settings, at_least)]
    res = milp(c, constraints=constraints, integrality=integrality, bounds=Bounds(lower, upper),
               options={"time_limit": time_limit, "mip_rel_gap": 1e-2})
    if res.x is None:
        return None, False, np.inf
    counts = np.rint(res.x[:n_settings]).astype(int)
    gap = float(getattr(res, "mip_gap", 0.0) or 0.0)
    return counts, res.status == 0, gap


#: worst-case SNR (dB) a plan may give up against the best for a lower mean error over
#: the rest of the scene (:func:`best_plan`): a difference the tool calls material
MARGIN_DB = MATERIAL_DB
#: bins (EV) of the protected photosites in the relaxation that guides the mean-error
#: search (each at its share-weighted geometric mean irradiance)
RELAX_BIN_EV = 1 / 3
#: spacing (dB) of the relaxation's tangents below ``1 / SNR``, from 3 dB under its floor
#: to :data:`TANGENT_SPAN_DB` over it: within 1.4 % of ``1 / SNR`` (0.06 dB); photosites
#: further above weigh under 10^-3 of those at the floor
TANGENT_DB, TANGENT_SPAN_DB = 1.0, 30.0


def _least_mean_error(settings, scene, a, floor, budget, max_frames, counts) -> np.ndarray:
    """Counts of least mean error over the protected photosites (:func:`mean_snr_db`) that
    keep ``a @ counts >= floor`` (the worst-case program's rows), the total time within
    ``budget`` and at most ``max_frames`` frames.

    An exchange search (:func:`_exchange`) from two starts, the better result kept:
    ``counts`` (the best worst case's plan) and the rounded optimum of the problem with
    the counts continuous (:func:`_relaxed_counts`), which spreads the frames as the whole
    scene asks and leads the search past the local optima around the first."""
    rows, weights = [], []
    for c in range(scene.channels):
        r, w = scene.population(c, protected=True)
        rows.append(np.stack([r * r * s.information(r, c) for s in settings], axis=1))
        weights.append(w)
    b, w = np.vstack(rows), np.concatenate(weights)
    if not w.size:
        return counts
    times = np.array([s.time for s in settings])
    starts = [counts]
    relaxed = _relaxed_counts(settings, scene, a, floor, times, budget, max_frames)
    if relaxed is not None:
        starts.append(_rounded(relaxed, times, budget, max_frames))
    found = [_exchange(b, w, a, floor, times, budget, max_frames, start) for start in starts]
    return min(found, key=lambda f: f[1])[0]


def _relaxed_counts(settings, scene, a, floor, times, budget, max_frames) -> np.ndarray | None:
    """The counts, taken as continuous, that minimise the mean of ``1 / SNR`` over the
    protected photosites (in :data:`RELAX_BIN_EV` bins) subject to ``a @ n >= floor``,
    the budget and the frames: a linear program in which each bin k has ``x_k = SNR(r_k)
    / floor`` and ``u_k`` above every tangent of ``1 / x`` at :data:`TANGENT_DB` steps,
    ``u_k >= 2 / x_j - x_k / x_j^2``; minimise ``sum w_k u_k``.  None if HiGHS finds none."""
    from scipy.optimize import Bounds, LinearConstraint, milp
    from scipy.sparse import bmat, csr_matrix, identity, vstack

    rows, weights = [], []
    for c in range(scene.channels):
        r, w = _coarsen(*scene.population(c, protected=True), scene.lo[c], RELAX_BIN_EV)
        rows.append(np.stack([r * r * s.information(r, c) for s in settings], axis=1) / floor)
        weights.append(w)
    b, w = np.vstack(rows), np.concatenate(weights)
    n, k = len(settings), len(w)
    x0 = 10 ** (np.arange(-3.0, TANGENT_SPAN_DB + TANGENT_DB, TANGENT_DB) / 10)
    eye, pad = identity(k, format="csr"), csr_matrix((1, 2 * k))
    blocks = [bmat([[csr_matrix(-b), eye, csr_matrix((k, k))]])]  # x - B n = 0
    blocks += [bmat([[csr_matrix((k, n)), eye / (x * x), eye]]) for x in x0]  # the tangents
    blocks += [bmat([[csr_matrix(a / floor), csr_matrix((a.shape[0], 2 * k))]]),
               bmat([[csr_matrix(times[None]), pad]]), bmat([[csr_matrix(np.ones((1, n))), pad]])]
    lower = np.r_[np.zeros(k), np.repeat(2.0 / x0, k), np.ones(a.shape[0]), -np.inf, 1.0]
    upper = np.r_[np.zeros(k), np.full(k * len(x0), np.inf), np.full(a.shape[0], np.inf), budget, max_frames]
    res = milp(np.r_[np.zeros(n + k), w / w.sum()],
               constraints=[LinearConstraint(vstack(blocks, format="csr"), lower, upper)],
               bounds=Bounds(np.zeros(n + 2 * k), np.r_[np.full(n, float(max_frames)), np.full(2 * k, np.inf)]))
    return None if res.x is None else res.x[:n]


def _coarsen(r: np.ndarray, w: np.ndarray, lo: float, step_ev: float) -> tuple[np.ndarray, np.ndarray]:
    """Photosites ``(r, share)`` (all ``r >= lo > 0``) in bins of ``step_ev`` from ``lo``:
    each bin's share-weighted geometric mean irradiance and its share."""
    keep = w > 0
    r, w = r[keep], w[keep]
    _, index = np.unique(np.floor(np.log2(r / lo) / step_ev), return_inverse=True)
    share = np.bincount(index, w)
    return np.exp2(np.bincount(index, w * np.log2(r)) / share), share


def _rounded(x: np.ndarray, times: np.ndarray, budget: float, max_frames: int) -> np.ndarray:
    """Continuous counts ``x`` rounded down, then the frames of the largest remainders
    added while the budget and the frames allow."""
    counts = np.floor(x + 1e-9).astype(int)
    for j in np.argsort(-(x - counts), kind="stable"):
        if counts.sum() < max_frames and times @ counts + times[j] <= budget * (1 + 1e-12):
            counts[j] += 1
    return counts


def _exchange(b, w, a, floor, times, budget, max_frames, counts) -> tuple[np.ndarray, tuple]:
    """From ``counts``, while one improves, the best move that adds a frame of any setting
    or puts one frame at another setting, within the budget and the frames.  Moves are
    ranked first by how far the worst case falls short of ``floor`` (``1 - min(a n) /
    floor``, 0 when it holds), then by the mean error ``sum_k w_k / SNR_k`` (``b``: the
    photosites' ``r^2 I``).  Returns the counts and their (shortfall, mean error)."""
    counts = counts.copy()

    def score(snr, worst):
        with np.errstate(divide="ignore"):
            error = w @ np.where(snr > 0, 1.0 / np.maximum(snr, 1e-300), np.inf)
        return np.maximum(0.0, 1.0 - np.min(worst, axis=0) / floor), error

    while True:
        snr, worst, spent = b @ counts, a @ counts, float(times @ counts)
        now = tuple(float(v[0]) for v in score(snr[:, None], worst[:, None]))
        best = None
        outs = ([-1] if counts.sum() < max_frames else []) + list(np.flatnonzero(counts))
        for i in outs:
            less_b, less_a, less_t = (0.0, 0.0, 0.0) if i < 0 else (b[:, [i]], a[:, [i]], times[i])
            short, error = score(snr[:, None] - less_b + b, worst[:, None] - less_a + a)
            fits = spent - less_t + times <= budget * (1 + 1e-12)
            fits[i] &= i < 0
            for j in np.flatnonzero(fits):
                if best is None or (short[j], error[j]) < best[0]:
                    best = ((short[j], error[j]), i, j)
        if best is None or not (best[0][0] < now[0] - 1e-12 or (best[0][0] <= now[0] and best[0][1] < now[1] * (1 - 1e-6))):
            return counts, now
        _, out, into = best
        if out >= 0:
            counts[out] -= 1
        counts[into] += 1


def _with_least_mean_error(settings, scene, a, counts, floor, budget, max_frames, optimal, gap) -> Plan:
    """The plan of ``counts`` after :func:`_least_mean_error`."""
    better = _least_mean_error(settings, scene, a, floor, budget, max_frames, counts)
    return evaluate([(s, n) for s, n in zip(settings, better)], scene, optimal, gap)


def best_plan(settings: list[Setting], scene: SceneRange, budget: float, max_frames: int,
              time_limit: float = TIME_LIMIT, at_least_db: float = float("-inf"),
              margin_db: float = MARGIN_DB) -> Plan:
    """The plan of at most ``max_frames`` frames and ``budget`` seconds in all: of the
    plans within ``margin_db`` of the best worst-case SNR (the program of the module
    notes), and not below ``at_least_db`` where the best reaches it, the one of least mean
    error over the protected photosites (:func:`mean_snr_db`).  Raises if no setting fits
    the budget.

    With several ISOs, the plan at the lowest ISO alone (a program of fewer variables) is
    solved first and bounds the search from below; it is returned unless the other ISOs
    gain more than 0.01 dB of worst case, so a plan is never worse than it, even when the
    time limit stops the search."""
    from scipy.optimize import LinearConstraint

    settings = [s for s in settings if s.time <= budget]
    if not settings:
        raise HdrMergeError(f"a budget of {budget:g} s is shorter than the shortest shutter time")
    start = None
    base = min(s.iso for s in settings)
    if any(s.iso != base for s in settings):
        start = best_plan([s for s in settings if s.iso == base], scene, budget, max_frames, time_limit,
                          at_least_db, margin_db)
    a = _program(settings, scene)
    times = np.array([s.time for s in settings])
    n = len(settings)
    within = [LinearConstraint(times[None], -np.inf, budget), LinearConstraint(np.ones((1, n)), 1.0, max_frames)]
    tau = [LinearConstraint(np.hstack([a, -np.ones((a.shape[0], 1))]), 0.0, np.inf)] + [
        LinearConstraint(np.hstack([c.A, np.zeros((1, 1))]), c.lb, c.ub) for c in within]
    floor = 0.0 if start is None or not np.isfinite(start.worst_snr_db) else 10 ** (start.worst_snr_db / 10)
    counts, optimal, gap = _solve(np.r_[np.zeros(n), -1.0], tau, n, max_frames, time_limit, floor)
    reached = None if counts is None else float(np.min(a @ counts))
    if reached is None or not reached > 0:
        if start is not None and np.isfinite(start.worst_snr_db):
            return replace(start, lowest_iso=start)
        raise HdrMergeError("no plan within the budget measures every irradiance of the scene (its brightest "
                            "photosites clip in every frame allowed, or its darkest read no light)")
    # the lowest-ISO plan unless other ISOs gain more than 0.01 dB (on a sensor without
    # read noise after the amplifier they gain nothing, and a higher ISO only clips sooner)
    if start is not None and 10 * np.log10(reached) <= start.worst_snr_db + 0.01:
        return replace(start, lowest_iso=start)
    # of the plans within the margin (and not below at_least_db), the least mean error
    least = min(reached, max(reached * 10 ** (-margin_db / 10), 10 ** (at_least_db / 10)))
    plan = _with_least_mean_error(settings, scene, a, counts, least, budget, max_frames, optimal, gap)
    return replace(plan, lowest_iso=start)


def shortest_plan(settings: list[Setting], scene: SceneRange, min_snr_db: float, max_frames: int,
                  budget: float | None = None, time_limit: float = TIME_LIMIT) -> Plan | None:
    """The plan of least total time whose worst-case SNR reaches ``min_snr_db`` with at
    most ``max_frames`` frames (and ``budget`` seconds), then among plans within 0.01 %
    of that time the one of least mean error (:func:`mean_snr_db`); None when none
    reaches the SNR."""
    from scipy.optimize import LinearConstraint

    settings = [s for s in settings if budget is None or s.time <= budget]
    if not settings:
        return None
    a = _program(settings, scene)
    times = np.array([s.time for s in settings])
    n = len(settings)
    floor = 10 ** (min_snr_db / 10)
    cons = [LinearConstraint(a, floor, np.inf), LinearConstraint(np.ones((1, n)), 1.0, max_frames)]
    if budget is not None:
        cons.append(LinearConstraint(times[None], -np.inf, budget))
    counts, optimal, gap = _solve(times, cons, n, max_frames, time_limit)
    if counts is None:
        return None
    return _with_least_mean_error(settings, scene, a, counts, floor, float(times @ counts) * 1.0001, max_frames,
                                  optimal, gap)


def conventional_brackets(settings: list[Setting], step_ev: float, max_frames: int):
    """Every conventional bracket at the lowest ISO of ``settings``: 1 to ``max_frames``
    distinct frames ``step_ev`` stops apart (the nearest times of the settings' series)
    from any first time, the sequence shot ``k`` times over (``k`` times the frames at
    most ``max_frames``).  Yields ``(frames, k)``: the sequence's settings and the
    largest ``k``."""
    base = min(s.iso for s in settings)
    series = sorted((s for s in settings if s.iso == base), key=lambda s: s.time)
    log_t = np.log([s.time for s in series])
    for first in series:
        frames = []
        for j in range(max_frames):
            s = series[int(np.argmin(np.abs(log_t - np.log(first.time * 2.0 ** (step_ev * j)))))]
            if frames and s.time <= frames[-1].time:
                break
            frames.append(s)
            yield list(frames), max_frames // len(frames)


def best_conventional(settings: list[Setting], scene: SceneRange, step_ev: float, max_frames: int,
                      budget: float | None = None, min_snr_db: float | None = None) -> Plan | None:
    """The best of :func:`conventional_brackets`, each shot as many times over as
    ``budget`` seconds allow: the highest worst-case SNR, then the least mean error
    (:func:`mean_snr_db`), then the shortest; or, with ``min_snr_db``, the shortest that
    reaches it (then the least mean error).  None when none qualifies.

    A sequence shot ``k`` times has ``k`` times its SNR at every irradiance, so each
    sequence is evaluated once and its repeats by adding ``10 log10 k`` dB."""
    best, best_key = None, None
    for frames, most in conventional_brackets(settings, step_ev, max_frames):
        once = sum(s.time for s in frames)
        worst = worst_case_snr_db([(s, 1) for s in frames], scene)
        if not np.isfinite(worst):
            continue
        if min_snr_db is None:
            k = most if budget is None else min(most, int(np.floor(budget * (1 + 1e-9) / once)))
        else:
            k = max(1, int(np.ceil(10 ** ((min_snr_db - worst) / 10) * (1 - 1e-12))))
            if budget is not None and k * once > budget * (1 + 1e-9):
                continue
        if not 1 <= k <= most or (best_key is not None and worst + 10 * np.log10(k) < best_key[0]
                                  and min_snr_db is None):
            continue
        p = _repeated(evaluate([(s, 1) for s in frames], scene), k)
        key = (-p.total_time, p.mean_snr_db) if min_snr_db is not None else (
            p.worst_snr_db, p.mean_snr_db, -p.total_time)
        if best_key is None or key > best_key:
            best, best_key = p, key
    return best


def _repeated(plan: Plan, k: int) -> Plan:
    """``plan`` shot ``k`` times over: its SNRs ``10 log10 k`` dB higher."""
    gain = 10 * np.log10(k)
    return replace(plan, frames=[(s, n * k) for s, n in plan.frames], total_time=plan.total_time * k,
                   worst_snr_db=plan.worst_snr_db + gain, mean_snr_db=plan.mean_snr_db + gain,
                   low_snr_db=plan.low_snr_db + gain)
