"""The noise-model weights (28)/(29), (32), (33) and the unknown-parameter scheme."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.special import ndtr

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.core.reconstruct import certainty_table, exposure_tables
from hdrmerge_cli.core.weights_goossens2012 import (
    WeightContext, bounded_noise, log_normal_interval, weights_goossens2012_bounded, weights_goossens2012_direct,
    weights_goossens2012_optimal, weights_goossens2012_probabilistic,
)

V = np.arange(256) / 255.0
CTX = WeightContext(255.0, 0.1, NoiseParams(4.0, 1.0), prior_rate=500.0, exposures=(0.01, 0.1, 1.0))


def test_probabilistic_32_matches_a_monte_carlo_posterior():
    """Independent: draw E from the exponential prior, observe y through (17) and 8-bit
    rounding; per code, the fraction of draws whose mean lies in [y'_min, y'_max]."""
    rng = np.random.default_rng(0)
    mu = rng.exponential(CTX.prior_rate * CTX.exposure, 4_000_000)
    y = rng.normal(mu, np.sqrt(4.0 + mu))
    z = np.clip(np.rint(y), 0, 255).astype(int)
    lo, hi = CTX.safe_range()
    inside = (mu >= lo) & (mu <= hi)
    counts = np.bincount(z, minlength=256)
    mc = np.bincount(z, weights=inside, minlength=256) / np.maximum(counts, 1)
    w = weights_goossens2012_probabilistic(V, V, CTX)
    ok = (counts > 2000) & (z.max() > 0)
    ok[[0, 255]] = False
    np.testing.assert_allclose(w[ok], mc[ok], atol=0.03)


def test_direct_33_approximates_probabilistic_32():
    w32 = weights_goossens2012_probabilistic(V, V, CTX)
    w33 = weights_goossens2012_direct(V, V, CTX)
    assert np.max(np.abs(w32 - w33)) < 0.1
    assert np.mean(np.abs(w32 - w33)) < 0.02


def test_optimal_29_is_the_most_generous_fig14():
    w29 = weights_goossens2012_optimal(V, V, CTX)
    w32 = weights_goossens2012_probabilistic(V, V, CTX)
    # 'generally' (the paper): at most 0.05 below (32) where (32) is ~1, far above elsewhere
    assert np.all(w29[1:-1] >= w32[1:-1] - 0.05) and w29.mean() > w32.mean()


@pytest.mark.parametrize("fn", [weights_goossens2012_probabilistic, weights_goossens2012_direct,
                                weights_goossens2012_optimal, weights_goossens2012_bounded])
def test_tables_finite_in_unit_interval_zero_at_clipping(fn):
    w = fn(V, CRF("srgb").inverse(V), CTX)
    assert np.all(np.isfinite(w)) and w.min() >= 0 and w.max() <= 1 and w[0] == 0 and w[-1] == 0
    assert w.max() > 0.1


def test_more_offset_noise_lowers_the_weights_fig13():
    quiet = weights_goossens2012_probabilistic(V, V, CTX)
    noisy = weights_goossens2012_probabilistic(V, V, WeightContext(255.0, 0.1, NoiseParams(64.0, 1.0), 500.0))
    assert noisy.sum() < quiet.sum()


def test_photon_noise_makes_the_weight_asymmetric_and_offset_noise_symmetric():
    photon = weights_goossens2012_direct(V, V, WeightContext(255.0, 0.1, NoiseParams(0.01, 4.0), 1e4))
    offset = weights_goossens2012_direct(V, V, WeightContext(255.0, 0.1, NoiseParams(400.0, 0.01), 1e4))
    # offset-limited: symmetric about mid-scale; photon-limited: the top is cut harder
    assert np.max(np.abs(offset[1:128] - offset[254:127:-1])) < 0.1
    assert photon[1:128].sum() > photon[128:255].sum()


@settings(max_examples=30, deadline=None)
@given(st.sampled_from([8, 12, 14, 16]), st.floats(1e-6, 100.0), st.floats(1e-3, 50.0), st.floats(1e-4, 1.0))
def test_hard_cases_give_finite_tables_or_a_clear_error(bits, sigma_o2, alpha, t):
    """sigma_o -> 0, tiny/huge alpha, every bit depth: finite tables in [0, 1], or an
    HdrMergeError when no clipping-safe range exists (never silent all-zero weights)."""
    n = 2**bits
    try:
        w = certainty_table(n, [0.0], [n - 1.0], CRF("linear"), "direct", t, [NoiseParams(sigma_o2, alpha)],
                            prior_rate=(n - 1) / t / 4, exposures=(t,))
    except HdrMergeError as exc:
        assert "clipping-safe" in str(exc)
        return
    assert np.all(np.isfinite(w)) and w.min() >= 0 and w.max() <= 1 and w.max() > 0


def test_no_safe_range_is_a_clear_error():
    with pytest.raises(HdrMergeError, match="clipping-safe"):
        certainty_table(256, [0.0], [255.0], CRF("linear"), "probabilistic", 0.1, [NoiseParams(1e5, 1.0)], 500.0)
    # without noise parameters: the bounded scheme's conservative upper bounds
    unknown = certainty_table(256, [0.0], [255.0], CRF("linear"), "direct", 0.1, None, 500.0)
    bounds = certainty_table(256, [0.0], [255.0], CRF("linear"), "direct", 0.1, [bounded_noise(255.0)], 500.0)
    np.testing.assert_array_equal(unknown, bounds)


def test_bounded_uses_the_papers_jpeg_bounds_and_is_bell_shaped():
    p = bounded_noise(255.0)
    assert p.sigma_o2 == pytest.approx(0.02 * 255**2) and np.sqrt(p.alpha) == pytest.approx(0.005 * 255)
    w = certainty_table(256, [0.0], [255.0], CRF("linear"), "bounded", 0.1, None, prior_rate=1275.0)[0]
    peak = int(np.argmax(w))
    assert 90 < peak < 170 and w[peak] == 1 and w[10] < 0.5 and w[245] < 0.5
    assert np.all(np.diff(w[1:peak]) >= -1e-9) and np.all(np.diff(w[peak:255]) <= 1e-9)


def test_log_normal_interval_is_cancellation_free():
    a, b = np.array([-1.0, 0.5, -3.0]), np.array([2.0, 1.5, -2.0])
    np.testing.assert_allclose(np.exp(log_normal_interval(a, b)), ndtr(b) - ndtr(a), rtol=1e-12)
    # far tails: the naive difference is exactly 0 (log -inf); Mills' ratio gives the answer
    for x in (40.0, 60.0):
        got = log_normal_interval(np.array([x]), np.array([x + 1]))[0]
        mills = -x * x / 2 - np.log(x * np.sqrt(2 * np.pi))
        assert np.isfinite(got) and got == pytest.approx(mills, rel=1e-3)
        assert ndtr(x + 1) - ndtr(x) == 0.0  # what the naive formula would give


def test_variance_factor_model_and_photon():
    tabs = {v: exposure_tables(CRF("linear").at_codes(256, [0.0], [255.0]), "uniform", 1.0, [NoiseParams(4.0, 1.0)], variance=v)
            for v in ("none", "photon", "model")}
    z = np.array([10, 100, 200])
    assert np.all(tabs["none"].weight[z] == 1)
    np.testing.assert_allclose(tabs["photon"].weight[z], z, rtol=1e-6)
    np.testing.assert_allclose(tabs["model"].weight[z], z**2 / (4.0 + z), rtol=1e-5)  # mu^2 / v(mu), (21)


def test_unclipped_codes_never_get_zero_weight_in_the_merge_tables():
    """A bracket with gaps: codes far outside the clipping-safe range (weights that
    underflow) must still count where no frame has better, instead of the no-information
    fallback."""
    for weights in ("direct", "probabilistic", "bounded"):
        tab = exposure_tables(CRF("gamma", 2.5).at_codes(256, [0.0], [255.0]), weights, 0.1, [NoiseParams(64.0, 1.0)], "model",
                              500.0, (0.1,))
        assert np.all(tab.weight[1:255] > 0) and tab.weight[0] == 0 and tab.weight[255] == 0
        assert np.all(tab.certainty[1:255] > 0) and tab.certainty[0] == 0  # what IRLS re-weights
        assert np.all(np.isfinite(tab.value[1:255])) and np.all(np.diff(tab.value[1:255]) > 0)
        # and on IRLS passes: a far-tail code at the current estimate keeps a weight
        from references import irls_weights

        w = irls_weights(tab.certainty[[1, 254]], np.log(np.array([1e-6, 1e3], np.float32)), 0.1, 255.0,
                         (np.float32(64.0), np.float32(1.0), np.float32(0.0)), False)
        assert np.all(w > 0)


def test_bounds_for_width_recovers_the_papers_jpeg_pair():
    """The paper's JPEG bounds (1/alpha <= 0.005, sigma_o^2 <= 0.02) are one pair of a
    clipping-safe range 10 % of full scale wide: fixing either and the width gives the other."""
    from hdrmerge_cli.core.weights_goossens2012 import bounds_for_width

    assert bounds_for_width(0.1, inv_alpha=0.005)[1] == pytest.approx(0.02, rel=0.01)
    assert bounds_for_width(0.1, sigma_o2=0.02)[0] == pytest.approx(0.005, rel=0.01)
    # a wider range leaves room for less noise
    assert bounds_for_width(0.3, inv_alpha=0.005)[1] < bounds_for_width(0.1, inv_alpha=0.005)[1]
    with pytest.raises(ValueError):
        bounds_for_width(0.1)
