"""Noise-optimal capture: which exposures (time, ISO) to shoot for a scene.

Hasinoff, Durand, Freeman, "Noise-optimal capture for high dynamic range photography",
CVPR 2010 (below: "Hasinoff"), with the noise model (17) of Goossens et al. 2012 per ISO.

Units.  ``r`` is the scene's irradiance at a photosite in code values per second at the
reference ISO (the ISO a gain of 1 stands for); a frame of exposure time ``t`` at gain
``g = ISO / reference ISO`` reads ``y ~ N(mu, v(mu))`` with ``mu = r t g`` and ``v`` the
code variance of (17) at that ISO (:func:`~hdrmerge_cli.core.noise.code_variance`).  The
frame's estimate of ``r`` is ``y / (t g)``, of variance ``v(mu) / (t g)^2``.

The merge of several frames is the inverse-variance (maximum-likelihood) average of the
frames' estimates, (7) with the weights of (12); its variance is ``1 / sum_j I_j(r)`` with
``I_j(r) = (t_j g_j)^2 / v_j(r t_j g_j)`` the Fisher information of frame j, and its SNR is

    SNR(r) = r^2 sum_j I_j(r)          (as a power ratio; 10 log10 for dB)

summed over the frames in which ``r`` is measured: those whose mean lies below the
clipping-safe upper bound ``y'_max`` of (47) (a reading closer to white than k standard
deviations is clipped often enough to be left to the other frames).

Worst case.  The worst-case SNR of a bracket over a scene is the minimum of SNR(r) over
the scene's irradiances (Hasinoff's objective over the range ``[r_lo, r_hi]``), ``r_lo``
a low percentile of the scene's photosites, ``r_hi`` the brightest, and of that range
only the intervals the scene's photosites hold (:class:`SceneRange`; an irradiance no
photosite has is not part of the picture).  Between the clipping points of the frames
SNR(r) grows with r (each term ``r^2 / (a + b r + c r^2)`` does), so the minimum lies at
the start of an interval or just above some frame's clipping point inside one:
:func:`critical_irradiances` lists those, and the worst case over them is exact.

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
from hdrmerge_cli.core.noise import DEFAULT_K, NoiseParams, clipping_safe_range_exact, code_variance

#: shutter times of the 1/3-stop series as cameras label them (s), 1/8000 to 30 s
SHUTTER_THIRD_STOPS = (
    1 / 8000, 1 / 6400, 1 / 5000, 1 / 4000, 1 / 3200, 1 / 2500, 1 / 2000, 1 / 1600, 1 / 1250, 1 / 1000, 1 / 800,
    1 / 640, 1 / 500, 1 / 400, 1 / 320, 1 / 250, 1 / 200, 1 / 160, 1 / 125, 1 / 100, 1 / 80, 1 / 60, 1 / 50,
    1 / 40, 1 / 30, 1 / 25, 1 / 20, 1 / 15, 1 / 13, 1 / 10, 1 / 8, 1 / 6, 1 / 5, 1 / 4, 0.3, 0.4, 0.5, 0.6,
    0.8, 1.0, 1.3, 1.6, 2.0, 2.5, 3.2, 4.0, 5.0, 6.0, 8.0, 10.0, 13.0, 15.0, 20.0, 25.0, 30.0,
)

#: relative step above a clipping point at which the SNR is evaluated (the frame is lost there)
ABOVE = 1.0 + 1e-6

#: seconds HiGHS may search one program before it returns the best plan found
TIME_LIMIT = 4.0


@dataclass(frozen=True)
class Setting:
    """One camera setting: exposure ``time`` (s) at ``iso``, its ``gain`` (ISO over the
    reference ISO), the noise (17) per channel at that ISO (code values), and per channel
    the clipping-safe upper bound ``y_hi`` of (47) (code values above black)."""

    time: float
    iso: float
    gain: float
    noise: tuple[NoiseParams, ...]
    y_hi: tuple[float, ...]

    @property
    def scale(self) -> float:
        """``t g``: code values per unit of ``r``."""
        return self.time * self.gain

    def information(self, r, channel: int) -> np.ndarray:
        """``I(r) = (t g)^2 / v(r t g)`` where ``r t g <= y_hi``, else 0 (Fisher information
        about ``r`` of one frame, (12) per frame).  ``r``: array, code values per second."""
        r = np.asarray(r, dtype=np.float64)
        mu = r * self.scale
        info = self.scale ** 2 / code_variance(mu, self.noise[channel])
        return np.where(mu <= self.y_hi[channel] * (1 + 1e-12), info, 0.0)  # y_hi / scale * scale rounds

    def clipping_point(self, channel: int) -> float:
        """The irradiance at which the frame's mean reaches ``y_hi``."""
        return self.y_hi[channel] / self.scale


def make_settings(times, isos, noise_at_iso: dict, reference_iso: float, y_full,
                  k: float = DEFAULT_K) -> list[Setting]:
    """Every (time, ISO) pair as a :class:`Setting`.  ``noise_at_iso``: ISO -> per-channel
    tuple of :class:`NoiseParams`; ``y_full``: full scale (white minus black, code values),
    one for every channel or one per channel; ``k``: standard deviations of (47) between a
    measured mean and white."""
    out = []
    for iso in isos:
        noise = tuple(noise_at_iso[iso])
        y_full = np.broadcast_to(np.asarray(y_full, dtype=np.float64), (len(noise),))
        ranges = [clipping_safe_range_exact(p, 0.5, full, k) for p, full in zip(noise, y_full)]
        y_hi = tuple(hi for _, hi in ranges)
        if any(lo >= hi for lo, hi in ranges):
            raise HdrMergeError(f"ISO {iso:g}: the noise model leaves no clipping-safe range below white")
        out += [Setting(float(t), float(iso), float(iso) / reference_iso, noise, y_hi) for t in times]
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


def critical_irradiances(settings: list[Setting], scene: SceneRange, channel: int) -> np.ndarray:
    """Where a worst case over the scene's irradiances (its occupied intervals of
    ``[lo, hi]``) can lie for any plan built from ``settings``: the start of each interval
    and just above each setting's clipping point inside one (see the module notes), and
    ``hi``, however few photosites are that bright.  Sorted, code values per second."""
    spans = scene.intervals(channel)
    points = [s.clipping_point(channel) * ABOVE for s in settings]
    # the brightest photosite always counts: a plan never clips the scene's highlights
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
    and ``hi``), in dB: exact, at the critical irradiances of the plan's own settings;
    ``-inf`` where some irradiance is measured by no frame."""
    settings = [s for s, n in plan if n]
    if not settings:
        return float("-inf")
    return float(min(np.min(snr_db(critical_irradiances(settings, scene, c), plan, c))
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
    lowest_iso: "Plan | None" = None  # the best plan at the lowest ISO alone, where it was solved

    @property
    def count(self) -> int:
        return int(sum(n for _, n in self.frames))


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
    solved first and bounds the search from below: the search's plan is never worse than
    it, even when the time limit stops the search."""
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
    if counts is None or not np.min(a @ counts) > 0:
        if start is not None and np.isfinite(start.worst_snr_db):
            return replace(start, lowest_iso=start)
        raise HdrMergeError("no plan within the budget measures every irradiance of the scene (its brightest "
                            "photosites clip in every frame allowed, or its darkest read no light)")
    # the shortest plan within 0.01 dB of the best (a frame more never lowers the SNR, so
    # the first solution may hold frames that add time but nothing to the worst case)
    best = LinearConstraint(a, float(np.min(a @ counts)) * 10 ** -0.001, np.inf)
    short, _, _ = _solve(times, [best] + within, n, max_frames, time_limit)
    plan = replace(_plan(settings, counts if short is None else short, scene, optimal, gap), lowest_iso=start)
    # the lowest-ISO plan where the search, stopped by its time limit, found no better one
    return replace(start, lowest_iso=start) if start is not None and start.worst_snr_db > plan.worst_snr_db + 0.01 \
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
