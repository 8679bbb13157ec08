"""core.capture_hasinoff2010: the SNR of a plan, its exact worst case, and the programs."""
import itertools

import numpy as np
import pytest

from hdrmerge_cli.core import capture_hasinoff2010 as cap
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams

Y_FULL = 16383.0 - 512.0


def noise_at(iso, pre=4.0, post=16.0, alpha=0.25, base=100.0):
    """(17) at ``iso``: the gain squares alpha; pre-amplifier read noise (electrons^2) is
    amplified with it, post-amplifier read noise (code values^2) is not."""
    a = alpha * (iso / base) ** 2
    return (NoiseParams(pre * a + post, a),)


def settings(isos=(100, 400, 1600), times=cap.SHUTTER_THIRD_STOPS, **kw):
    return cap.make_settings(times, isos, {i: noise_at(i, **kw) for i in isos}, 100.0, Y_FULL)


SCENE = cap.SceneRange((20.0,), (20.0 * 2 ** 14,))


def test_information_is_the_inverse_variance_of_the_ml_merge():
    """Monte Carlo: the inverse-variance average of the frames' estimates y / (t g), with
    the true variances, has variance 1 / sum_j I_j (12), frames far below white; seeded,
    3 % tolerance."""
    rng = np.random.default_rng(5)
    st = [s for s in settings() if s.time in (1 / 500, 1 / 60, 1 / 8) and s.iso == 100]
    r = 3000.0
    ests, ws = [], []
    for s in st:
        mu = r * s.scale
        v = s.noise[0].sigma_o2 + np.sqrt(s.noise[0].alpha) * mu
        ests.append(rng.normal(mu, np.sqrt(v), 200_000) / s.scale)
        ws.append(s.scale ** 2 / v)
    merged = sum(w * e for w, e in zip(ws, ests)) / sum(ws)
    predicted = 1 / cap.snr_power(np.array([r]), [(s, 1) for s in st], 0)[0] * r * r
    assert merged.var() == pytest.approx(predicted, rel=0.03)
    # a frame far past white adds (almost) nothing
    assert st[-1].information(np.array([1e9]), 0)[0] < 1e-12 * st[-1].information(np.array([1.0]), 0)[0]


def test_censored_factor_is_the_information_of_a_censored_normal():
    """T(z) against numerical integration of the censored normal's score: the Fisher
    information about the mean of y ~ N(mu, 1) observed as min(y, c), z = c - mu."""
    from scipy import integrate
    from scipy.stats import norm

    for z in (-3.0, -1.0, 0.0, 0.7, 2.0, 4.0):
        inside = integrate.quad(lambda y: (y ** 2) * norm.pdf(y), -np.inf, z)[0]
        censored = norm.pdf(z) ** 2 / norm.sf(z)  # score phi/(1-Phi) at the censoring point
        assert cap.censored_factor(z) == pytest.approx(inside + censored, rel=1e-6)


def test_worst_case_at_the_critical_irradiances_is_within_0_1_db_of_a_dense_grid():
    st = settings()
    rng = np.random.default_rng(0)
    for _ in range(5):
        plan = [(st[j], 1) for j in rng.choice(len(st), 4, replace=False)]
        dense = np.geomspace(SCENE.lo[0], SCENE.hi[0], 200_001)
        grid_min = float(np.min(cap.snr_db(dense, plan, 0)))
        at_points = cap.worst_case_snr_db(plan, SCENE)
        assert at_points == pytest.approx(grid_min, abs=0.1)


def _brute_force(st, budget, max_frames):
    best = (-np.inf, 0.0)
    for n in range(1, max_frames + 1):
        for combo in itertools.combinations_with_replacement(range(len(st)), n):
            t = sum(st[j].time for j in combo)
            if t <= budget:
                plan = [(st[j], 1) for j in combo]
                best = max(best, (cap.worst_case_snr_db(plan, SCENE), -t))
    return best[0]


@pytest.mark.parametrize("budget", [0.02, 0.1, 0.5])
def test_best_plan_equals_brute_force_on_a_small_camera(budget):
    st = settings(isos=(100, 800), times=(1 / 4000, 1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4))
    plan = cap.best_plan(st, SCENE, budget, 3, margin_db=0.0)
    assert plan.optimal
    assert plan.total_time <= budget
    assert plan.worst_snr_db == pytest.approx(_brute_force(st, budget, 3), abs=0.01)


def test_shortest_plan_reaches_the_snr_in_the_least_time():
    st = settings(isos=(100, 800), times=(1 / 4000, 1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4))
    target = 8.0
    plan = cap.shortest_plan(st, SCENE, target, 3)
    assert plan.worst_snr_db >= target - 1e-6
    fastest = min(sum(st[j].time for j in combo)
                  for n in (1, 2, 3) for combo in itertools.combinations_with_replacement(range(len(st)), n)
                  if cap.worst_case_snr_db([(st[j], 1) for j in combo], SCENE) >= target)
    assert plan.total_time == pytest.approx(fastest, rel=1e-9)
    assert cap.shortest_plan(st, SCENE, 200.0, 3) is None


@pytest.mark.parametrize("seed", range(4))
def test_plan_is_at_least_the_best_conventional_bracket_of_the_same_time(seed):
    """At the worst case (the conventional brackets' best is the plan's floor) and in mean
    error (a conventional bracket is one of the plans the mean-error program may pick)."""
    rng = np.random.default_rng(seed)
    lo = 10 ** rng.uniform(0, 2.5)
    scene = cap.SceneRange((lo,), (lo * 2 ** rng.uniform(8, 16),))
    st = settings()
    budget = 10 ** rng.uniform(-1.5, 0.5)
    conv = [c for c in (cap.best_conventional(st, scene, step, 8, budget) for step in (1, 2)) if c is not None]
    plan = cap.best_plan(st, scene, budget, 8, at_least_db=max(c.worst_snr_db for c in conv))
    for c in conv:
        assert c.total_time <= budget * (1 + 1e-9) and sum(n for _, n in c.frames) <= 8
        assert plan.worst_snr_db >= c.worst_snr_db - 1e-6
        assert plan.mean_snr_db >= c.mean_snr_db - 0.1


def test_mean_and_percentile_snr_against_direct_sums():
    """mean_snr_db is -10 log10 of the share-weighted mean of 1 / SNR over the protected
    photosites, percentile_snr_db the weighted percentile over all of them: against sums
    written out here."""
    st = settings(isos=(100,))
    plan = [(st[10], 1), (st[25], 2)]
    r = np.array([0.0, 5.0, 40.0, 400.0, 4000.0, 9e4])
    w = np.array([0.004, 0.006, 0.3, 0.4, 0.28, 0.01])
    scene = cap.SceneRange((30.0,), (5e3,), photosites=((r, w),))
    snr = np.array([float(cap.snr_power(np.array([x]), plan, 0)[0]) for x in r])
    inside = (r >= 30.0) & (r <= 5e3)
    direct = -10 * np.log10(np.sum(w[inside] / snr[inside]) / np.sum(w[inside]))
    assert cap.mean_snr_db(plan, scene) == pytest.approx(direct, abs=1e-9)
    with np.errstate(divide="ignore"):
        db = 10 * np.log10(snr)
    assert cap.percentile_snr_db(plan, scene, 0.3) == -np.inf  # the photosites that read no light: 0.4 %
    assert cap.percentile_snr_db(plan, scene, 1.0) == pytest.approx(db[1])  # 0.4 + 0.6 %
    assert cap.percentile_snr_db(plan, scene, 50.0) == pytest.approx(db[3])


def test_plan_has_the_least_mean_error_of_the_plans_within_the_margin():
    """Brute force on a small camera: of every plan of at most 3 frames within the budget
    whose worst case is within MARGIN_DB of the best, the least mean error; best_plan's
    is within 0.05 dB of it (the program's tangents and gap) and its worst case within
    the margin."""
    st = settings(isos=(100, 800), times=(1 / 4000, 1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4))
    budget = 0.1
    plans = [[(st[j], 1) for j in combo] for n in (1, 2, 3)
             for combo in itertools.combinations_with_replacement(range(len(st)), n)
             if sum(st[j].time for j in combo) <= budget]
    worst = [cap.worst_case_snr_db(p, SCENE) for p in plans]
    best = max(worst)
    mean = max(cap.mean_snr_db(p, SCENE) for p, w in zip(plans, worst) if w >= best - cap.MARGIN_DB)
    plan = cap.best_plan(st, SCENE, budget, 3)
    assert plan.worst_snr_db >= best - cap.MARGIN_DB - 0.01
    assert plan.mean_snr_db == pytest.approx(mean, abs=0.05)


def test_a_conventional_bracket_is_shot_as_many_times_over_as_time_and_frames_allow():
    """A one-stop scene that no frame clips: of the 2-EV sequences, 1/4 s and 1 s fit a
    2.5 s budget twice over in 8 frames; in 3 frames 1 s twice beats 1/4 s and 1 s once.
    The repeats add 10 log10 k dB to every statistic, as evaluating them directly does."""
    st = settings(isos=(100,), times=(1 / 16, 1 / 4, 1.0))
    scene = cap.SceneRange((3000.0,), (6000.0,))
    conv = cap.best_conventional(st, scene, 2, 8, budget=2.5)
    assert [(s.time, n) for s, n in conv.frames] == [(1 / 4, 2), (1.0, 2)]
    direct = cap.evaluate(conv.frames, scene)
    assert conv.worst_snr_db == pytest.approx(direct.worst_snr_db, abs=1e-9)
    assert conv.mean_snr_db == pytest.approx(direct.mean_snr_db, abs=1e-9)
    assert conv.low_snr_db == pytest.approx(direct.low_snr_db, abs=1e-9)
    assert [(s.time, n) for s, n in cap.best_conventional(st, scene, 2, 3, budget=2.5).frames] == [(1.0, 2)]


def test_iso_gains_only_where_read_noise_follows_the_amplifier():
    """All read noise before the amplifier: in electrons the noise is the same at every
    ISO, and a higher ISO only clips sooner, so freeing the ISO gains nothing.  With
    post-amplifier read noise, a dark scene gains several dB."""
    scene = cap.SceneRange((2.0,), (2.0 * 2 ** 12,))
    budget = 0.05
    for post, least_gain in ((0.0, None), (100.0, 3.0)):
        st = settings(isos=(100, 400, 1600, 6400), pre=4.0, post=post)
        free = cap.best_plan(st, scene, budget, 6).worst_snr_db
        fixed = cap.best_plan([s for s in st if s.iso == 100], scene, budget, 6).worst_snr_db
        if least_gain is None:
            assert free == pytest.approx(fixed, abs=0.05)
        else:
            assert free - fixed >= least_gain


def test_a_budget_shorter_than_every_shutter_is_refused():
    with pytest.raises(HdrMergeError, match="shorter than the shortest shutter"):
        cap.best_plan(settings(), SCENE, 1e-5, 4)


def test_the_brightest_photosite_is_measured_even_when_rare():
    """Occupied intervals that stop short of the brightest photosite (a small highlight):
    the plan still keeps it unclipped."""
    scene = cap.SceneRange((20.0,), (20.0 * 2 ** 16,), occupied=(((20.0, 20.0 * 2 ** 8),),))
    plan = cap.best_plan(settings(), scene, 0.5, 4)
    assert any(s.clipping_point(0) >= scene.hi[0] for s, _ in plan.frames)


def test_dip_mean_solves_its_equation_and_meets_the_clipping_safe_bound_of_47():
    from hdrmerge_cli.core.noise import clipping_safe_range_exact, code_variance

    p = NoiseParams(36.0, 16.0, 0.001)
    white = Y_FULL
    for sds in (-3.0, -1.0, 0.5, 2.0, 4.0):
        mu = cap.dip_mean(p, white, sds)
        assert mu - white == pytest.approx(sds * np.sqrt(code_variance(mu, p)), rel=1e-9)
    # sds = -k: the upper clipping-safe bound of (47), solved there independently
    assert cap.dip_mean(p, white, -3.0) == pytest.approx(clipping_safe_range_exact(p, 0.5, white, 3.0)[1], rel=1e-9)


def test_weighted_percentile_against_repeated_values():
    """Integer weights: the weighted percentile is the plain percentile (lower value) of
    the values repeated that many times."""
    rng = np.random.default_rng(1)
    v, w = rng.normal(size=40), rng.integers(1, 6, size=40)
    repeated = np.sort(np.repeat(v, w))
    for q in (0.5, 1.0, 10.0, 50.0, 99.0):
        k = int(np.ceil(q / 100 * repeated.size)) - 1
        assert cap.weighted_percentile(v, w.astype(float), q) == repeated[max(k, 0)]
