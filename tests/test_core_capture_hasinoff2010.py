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
    rng = np.random.default_rng(seed)
    lo = 10 ** rng.uniform(0, 2.5)
    scene = cap.SceneRange((lo,), (lo * 2 ** rng.uniform(8, 16),))
    st = settings()
    budget = 10 ** rng.uniform(-1.5, 0.5)
    plan = cap.best_plan(st, scene, budget, 8)
    for step in (1, 2):
        conv = cap.best_conventional(st, scene, step, 8, budget)
        if conv is not None:
            assert plan.worst_snr_db >= conv.worst_snr_db - 1e-6


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
