"""The log-domain noise model (19)-(22), (47)-(48) against independent computations."""
import numpy as np
import pytest
from hypothesis import assume, given, settings, strategies as st
from scipy import integrate, stats

from benchmarks.fig17 import log_moments_approx
from hdrmerge_cli.core.noise import DEFAULT_K, NoiseParams, clipping_safe_range_exact, code_variance, log_moments_exact

P = NoiseParams(25.0, 1.0, 0.0)


def _quad_moments(x, p, y_min, y_max):
    """(19) by adaptive quadrature (scipy.integrate.quad), clipped masses in closed form."""
    mu, sd = np.sqrt(p.alpha) * x, np.sqrt(p.sigma_o2 + p.alpha * x + p.beta * x * x)
    m = []
    for n in (1, 2):
        inner = integrate.quad(lambda u: np.log(u) ** n * stats.norm.pdf(u, mu, sd), y_min, y_max,
                               points=[min(max(mu, y_min), y_max)], limit=400, epsabs=1e-13)[0]
        m.append(inner + np.log(y_min) ** n * stats.norm.cdf(y_min, mu, sd)
                 + np.log(y_max) ** n * stats.norm.sf(y_max, mu, sd))
    return m[0] - np.log(np.clip(mu, y_min, y_max)), m[1] - m[0] ** 2


@pytest.mark.parametrize("p", [P, NoiseParams(0.01, 4.0, 0.0), NoiseParams(100.0, 0.25, 1e-4)])
def test_exact_moments_match_adaptive_quadrature(p):
    xs = np.array([0.3, 3.0, 30.0, 120.0, 200.0, 260.0, 400.0]) / np.sqrt(p.alpha)
    nu, var = log_moments_exact(xs, p, 0.5, 255.0)
    for k, x in enumerate(xs):
        qn, qv = _quad_moments(x, p, 0.5, 255.0)
        assert nu[k] == pytest.approx(qn, abs=2e-6)
        assert var[k] == pytest.approx(qv, rel=1e-5, abs=1e-9)


def test_exact_moments_match_monte_carlo():
    rng = np.random.default_rng(0)
    for x in (10.0, 80.0, 240.0):
        y = rng.normal(x, np.sqrt(25 + x), 400_000)
        ly = np.log(np.clip(y, 0.5, 255.0))
        nu, var = log_moments_exact(np.array([x]), P, 0.5, 255.0)
        assert nu[0] == pytest.approx(ly.mean() - np.log(x), abs=4 * ly.std() / 630)
        assert var[0] == pytest.approx(ly.var(), rel=0.01)


def test_approximations_hold_inside_the_safe_range_and_fail_outside():
    lo, hi = clipping_safe_range_exact(P, 0.5, 255.0)
    mu = np.linspace(lo, hi, 200)
    nu_e, var_e = log_moments_exact(mu, P, 0.5, 255.0)
    nu_a, var_a = log_moments_approx(mu, P)
    # inside, where the log is near-linear over the noise (s / mu^2 <= 2 %): within 6 %
    small = var_a <= 0.02
    assert small.sum() > 140
    np.testing.assert_allclose(var_a[small], var_e[small], rtol=0.06)
    np.testing.assert_allclose(nu_a[small], nu_e[small], atol=0.004)
    # beyond y'_max clipping takes over: > 20 % off two standard deviations out (measured
    # 23 %), > 60 % from y_max on, growing to ~100 %
    out = np.linspace(hi + 2 * np.sqrt(code_variance(hi, P)), 300, 20)
    nu_e, var_e = log_moments_exact(out, P, 0.5, 255.0)
    nu_a, var_a = log_moments_approx(out, P)
    rel = np.abs(var_a - var_e) / var_a
    assert np.all(rel > 0.2) and np.all(rel[out >= 255] > 0.6) and rel[-1] > 0.99 and np.all(np.diff(rel) > 0)


def clipping_safe_range_taylor(p: NoiseParams, y_min: float, y_max: float, k: float = DEFAULT_K):
    """``[y'_min, y'_max]`` of (48): (47) with ``sqrt(v(mu))`` linearised at the clipping
    points, ``y' = y_0 +- k v_0 / (sqrt(v_0) -+ k v'_0 / 2)``, ``v_0 = v(y_0)``,
    ``v'_0 = sqrt(alpha) + 2 beta y_0 / alpha``.  Where the linearisation has no solution
    (denominator <= 0: almost no noise at the clipping point, ``v_0 < (k v'_0 / 2)^2``)
    the exact root of (47) is used.  Returns ``(lo, hi)``."""
    exact = clipping_safe_range_exact(p, y_min, y_max, k)

    def bound(y0, sign, fallback):
        v0 = float(code_variance(y0, p))
        dv0 = np.sqrt(p.alpha) + 2 * p.beta * y0 / p.alpha
        den = np.sqrt(v0) - sign * k * dv0 / 2
        return y0 + sign * k * v0 / den if den > 0 else fallback

    return float(bound(y_min, +1.0, exact[0])), float(bound(y_max, -1.0, exact[1]))


@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 400.0), st.floats(0.05, 20.0), st.floats(0.0, 1e-3))
def test_taylor_bounds_48_track_the_exact_solution_of_47(sigma_o2, alpha, beta):
    p = NoiseParams(sigma_o2, alpha, beta)
    # (48) linearises sqrt(v) over the margin: only meaningful where it changes little
    for y0 in (0.5, 4095.0):
        slope = np.sqrt(alpha) + 2 * beta * y0 / alpha
        assume(3 * slope / (2 * np.sqrt(code_variance(y0, p))) < 0.3)
    lo, hi = clipping_safe_range_exact(p, 0.5, 4095.0)
    tlo, thi = clipping_safe_range_taylor(p, 0.5, 4095.0)
    if lo < hi:
        # linearising sqrt(v) at the clipping point errs by a fraction of the margin
        assert tlo == pytest.approx(lo, rel=0.25, abs=1.0)
        assert thi == pytest.approx(hi, rel=0.05)
        sd = np.sqrt(code_variance(np.array([lo, hi]), p))
        assert lo - 0.5 == pytest.approx(3 * sd[0], rel=1e-6) and 4095 - hi == pytest.approx(3 * sd[1], rel=1e-6)


def test_bounds_shrink_as_noise_grows_like_fig15():
    base = clipping_safe_range_exact(NoiseParams(25.0, 1.0), 0.5, 255.0)
    width = lambda p: np.subtract(*clipping_safe_range_exact(p, 0.5, 255.0)[::-1])
    assert width(NoiseParams(100.0, 1.0)) < width(NoiseParams(25.0, 1.0))          # sigma_o^2 grows
    assert width(NoiseParams(25.0, 1.0, 1e-3)) < width(NoiseParams(25.0, 1.0))     # beta grows
    # more photon-noise variance per code value (alpha grows at fixed sigma_o^2 in code units)
    assert width(NoiseParams(25.0, 5.0)) < width(NoiseParams(25.0, 1.0))
    assert base[0] < 127.75 < base[1]


def test_no_safe_region_is_reported_as_empty():
    lo, hi = clipping_safe_range_exact(NoiseParams(1e4, 1.0), 0.5, 255.0)
    assert lo >= hi
