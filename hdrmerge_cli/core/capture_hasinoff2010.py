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
the best plan is a mixed-integer linear program over the counts (Hasinoff, Sec. 4):
maximise ``tau`` subject to ``sum_s n_s r_i^2 I_s(r_i) >= tau`` at every critical
irradiance ``r_i``, ``sum_s n_s t_s <= T`` and ``sum_s n_s <= N`` (:func:`best_plan`); or
minimise the total time subject to ``tau >= tau_min`` (:func:`shortest_plan`).  Both are
solved by HiGHS (``scipy.optimize.milp``) to a relative gap of 1e-3 (0.004 dB) unless
its time limit stops the branch and bound first (then the best plan found, with its gap).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError
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
    (:func:`~hdrmerge_cli.core.reconstruct.censored_terms`)."""
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

    def clipping_point(self, channel: int, sds: float = 0.0) -> float:
        """The irradiance at which the frame's mean lies ``sds`` standard deviations above
        white (:func:`dip_mean`; 0: at white)."""
        return dip_mean(self.noise[channel], self.white[channel], sds) / self.scale


def dip_mean(p: NoiseParams, white: float, sds: float) -> float:
    """The mean ``mu`` with ``mu - white = sds sqrt(v(mu))``, ``v`` of (17): a quadratic
    in ``mu`` (cf. (47), whose clipping-safe bound is ``sds = -k``)."""
    if sds == 0:
        return float(white)
    c = 1.0 - sds * sds * p.beta / p.alpha
    b = 2 * white + sds * sds * np.sqrt(p.alpha)
    if c <= 0:  # gain FPN so large that the sd grows as fast as the mean: a step past white
        return white + sds * float(np.sqrt(code_variance(white, p)))
    root = np.sqrt(max(b * b - 4 * c * (white * white - sds * sds * p.sigma_o2), 0.0))
    return float((b + np.sign(sds) * root) / (2 * c))


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
    """The irradiances a plan must measure, per channel: ``lo`` (the low percentile of the
    scene's photosites) and ``hi`` (its brightest), code values per second at the
    reference ISO; ``occupied``: per channel, the ``(start, end)`` intervals of that range
    the scene's photosites hold (empty: all of it); ``histograms``: per channel
    ``(edges, counts)`` of log2 r (for reports)."""

    lo: tuple[float, ...]
    hi: tuple[float, ...]
    occupied: tuple = ()
    histograms: tuple = field(default=(), compare=False)

    def intervals(self, channel: int) -> list[tuple[float, float]]:
        if not self.occupied or not len(self.occupied[channel]):
            return [(self.lo[channel], self.hi[channel])]
        lo, hi = self.lo[channel], self.hi[channel]
        spans = [(max(a, lo), min(b, hi)) for a, b in self.occupied[channel] if b >= lo and a <= hi]
        return spans or [(lo, hi)]

    @property
    def channels(self) -> int:
        return len(self.lo)


def critical_irradiances(settings: list[Setting], scene: SceneRange, channel: int,
                          sds: tuple = DIP_SDS) -> np.ndarray:
    """Where a worst case over the scene's irradiances (its occupied intervals of
    ``[lo, hi]``) lies for any plan built from ``settings``: the start of each interval,
    each setting's dip (its mean ``sds`` standard deviations past white) inside one (see
    the module notes), and ``hi``, however few photosites are that bright.  Sorted, code
    values per second."""
    spans = scene.intervals(channel)
    # settings of one scale and noise share their points
    keys = {(s.scale, s.noise[channel], s.white[channel]): s for s in settings}
    points = [s.clipping_point(channel, z) for s in keys.values() for z in sds]
    return np.unique(np.array([a for a, _ in spans] + [scene.hi[channel]]
                              + [p for p in points if any(a < p <= b for a, b in spans)]))


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


@dataclass(frozen=True)
class Plan:
    """A solved plan: ``frames`` as ``(setting, count)`` pairs in increasing exposure, its
    worst-case SNR (dB), total time (s), and how the solver ended (``optimal``, or the
    relative gap of the best plan found when the time limit stopped it); ``lowest_iso``:
    the best plan at the lowest ISO alone, where the search solved it first."""

    frames: list
    worst_snr_db: float
    total_time: float
    optimal: bool = True
    gap: float = 0.0
    lowest_iso: "Plan | None" = None


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
               options={"time_limit": time_limit, "mip_rel_gap": 1e-3})
    if res.x is None:
        return None, False, np.inf
    counts = np.rint(res.x[:n_settings]).astype(int)
    gap = float(getattr(res, "mip_gap", 0.0) or 0.0)
    return counts, res.status == 0, gap


def _plan(settings, counts, scene, optimal, gap) -> Plan:
    frames = sorted(((s, int(n)) for s, n in zip(settings, counts) if n > 0), key=lambda p: (p[0].scale, p[0].iso))
    return Plan(frames, worst_case_snr_db(frames, scene), float(sum(s.time * n for s, n in frames)), optimal, gap)


def best_plan(settings: list[Setting], scene: SceneRange, budget: float, max_frames: int,
              time_limit: float = TIME_LIMIT) -> Plan:
    """The plan of at most ``max_frames`` frames and ``budget`` seconds in all with the
    best worst-case SNR (the program of the module notes), then among plans within
    0.01 dB of it the shortest.  Raises if no setting fits the budget.

    With several ISOs, the plan at the lowest ISO alone (a program of fewer variables) is
    solved first and bounds the search from below; it is returned unless the other ISOs
    gain more than 0.01 dB, so a plan is never worse than it, even when the time limit
    stops the search."""
    from scipy.optimize import LinearConstraint

    settings = [s for s in settings if s.time <= budget]
    if not settings:
        raise HdrMergeError(f"a budget of {budget:g} s is shorter than the shortest shutter time")
    start = None
    base = min(s.iso for s in settings)
    if any(s.iso != base for s in settings):
        start = best_plan([s for s in settings if s.iso == base], scene, budget, max_frames, time_limit)
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
    # the shortest plan within 0.01 dB of the best (a frame more never lowers the SNR, so
    # the first solution may hold frames that add time but nothing to the worst case)
    best = LinearConstraint(a, reached * 10 ** -0.001, np.inf)
    short, _, _ = _solve(times, [best] + within, n, max_frames, time_limit)
    plan = replace(_plan(settings, counts if short is None else short, scene, optimal, gap), lowest_iso=start)
    # the lowest-ISO plan unless other ISOs gain more than 0.01 dB (on a sensor without
    # read noise after the amplifier they gain nothing, and a higher ISO only clips sooner)
    return replace(start, lowest_iso=start) if start is not None and plan.worst_snr_db <= start.worst_snr_db + 0.01 \
        else plan


def shortest_plan(settings: list[Setting], scene: SceneRange, min_snr_db: float, max_frames: int,
                  budget: float | None = None, time_limit: float = TIME_LIMIT) -> Plan | None:
    """The plan of least total time whose worst-case SNR reaches ``min_snr_db`` with at
    most ``max_frames`` frames (and ``budget`` seconds), then among plans within 0.01 %
    of that time the one of fewest frames; None when none reaches the SNR."""
    from scipy.optimize import LinearConstraint

    settings = [s for s in settings if budget is None or s.time <= budget]
    if not settings:
        return None
    a = _program(settings, scene)
    times = np.array([s.time for s in settings])
    n = len(settings)
    cons = [LinearConstraint(a, 10 ** (min_snr_db / 10), np.inf), LinearConstraint(np.ones((1, n)), 1.0, max_frames)]
    if budget is not None:
        cons.append(LinearConstraint(times[None], -np.inf, budget))
    counts, optimal, gap = _solve(times, cons, n, max_frames, time_limit)
    if counts is None:
        return None
    fewest, _, _ = _solve(np.ones(n), cons + [LinearConstraint(times[None], -np.inf, float(times @ counts) * 1.0001)],
                          n, max_frames, time_limit)
    return _plan(settings, counts if fewest is None else fewest, scene, optimal, gap)


def conventional_brackets(settings: list[Setting], scene: SceneRange, step_ev: float, max_frames: int):
    """Every conventional bracket: at the lowest ISO of ``settings``, frames ``step_ev``
    stops apart (the nearest times of the settings' series), from any first time at which
    the scene's brightest photosite stays unclipped, 1 to ``max_frames`` frames.  Yields
    :class:`Plan` objects."""
    base = min(s.iso for s in settings)
    series = sorted((s for s in settings if s.iso == base), key=lambda s: s.time)
    log_t = np.log([s.time for s in series])
    for first in series:
        if any(scene.hi[c] > first.clipping_point(c) for c in range(scene.channels)):
            break
        frames, total = [], 0.0
        for j in range(max_frames):
            s = series[int(np.argmin(np.abs(log_t - np.log(first.time * 2.0 ** (step_ev * j)))))]
            if frames and s.time <= frames[-1][0].time:
                break
            frames.append((s, 1))
            total += s.time
            yield Plan(list(frames), worst_case_snr_db(frames, scene), total)


def best_conventional(settings: list[Setting], scene: SceneRange, step_ev: float, max_frames: int,
                      budget: float | None = None, min_snr_db: float | None = None) -> Plan | None:
    """The best of :func:`conventional_brackets` within ``budget`` seconds (highest
    worst-case SNR, then shortest), or with ``min_snr_db`` the shortest that reaches it;
    None when none qualifies."""
    plans = [p for p in conventional_brackets(settings, scene, step_ev, max_frames)
             if (budget is None or p.total_time <= budget * (1 + 1e-9))
             and (min_snr_db is None or p.worst_snr_db >= min_snr_db)]
    if not plans:
        return None
    if min_snr_db is not None:
        return min(plans, key=lambda p: (p.total_time, -p.worst_snr_db))
    return max(plans, key=lambda p: (p.worst_snr_db, -p.total_time))
