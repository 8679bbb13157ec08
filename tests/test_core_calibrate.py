"""Noise-parameter estimation (17): local statistics, exposure pairs and photon transfer,
against closed forms and Monte-Carlo simulations of the sensor model (seeded)."""
import numpy as np
import pytest
from scipy import ndimage, special

from hdrmerge_cli.core.calibrate import (
    IMMERKAER, PixelPairs, achievable_errors, binned_pairs, binned_variance, estimate_noise, exposure_ratio,
    fit_noise_model, immerkaer_dof, pair_gradient_test, pair_information, pair_statistics, texture_limit,
    variance_points, window_statistics,
)
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.photon_transfer import IMMERKAER_SUM_RHO2, photon_transfer, spatial_variance, temporal_variance


def expose(e, t, sigma_o2, alpha, rng, pattern=0.0):
    """(16)-(17): Poisson electrons, gain sqrt(alpha) (1 + pattern), Gaussian read noise."""
    return np.sqrt(alpha) * rng.poisson(e * t) * (1 + pattern) + rng.normal(0, np.sqrt(sigma_o2), np.shape(e))


def textured_scene(rng, n=400):
    """Strong texture at every scale (a real photograph's grain, edges and gradients)."""
    base = np.exp(ndimage.gaussian_filter(rng.normal(0, 1.0, (n, n)), 6) * 12)
    return 2000 * base / np.median(base) * np.abs(1 + 0.2 * rng.normal(0, 1, (n, n)))


@pytest.mark.parametrize("sigma_o2,alpha", [(16.0, 1.0), (4.0, 0.25)])
def test_fit_recovers_parameters_from_exact_points(sigma_o2, alpha):
    mu = np.linspace(5, 3000, 40)
    x = mu / np.sqrt(alpha)
    fit = fit_noise_model(variance_points(mu, sigma_o2 + alpha * x, np.full(mu.size, 1000)))
    assert fit.model == "affine" and fit.beta == 0.0
    assert fit.sigma_o2 == pytest.approx(sigma_o2, rel=1e-4)
    assert fit.alpha == pytest.approx(alpha, rel=1e-4)


def test_fit_resists_outlier_bins():
    """Soft-L1 loss: three bins 10x too high (texture) barely move the fit."""
    mu = np.linspace(5, 3000, 40)
    bad = 9 + 0.5 * mu
    bad[[10, 20, 30]] *= 10
    fit = fit_noise_model(variance_points(mu, bad, np.full(40, 5000)))
    assert fit.alpha == pytest.approx(0.25, rel=0.02) and fit.sigma_o2 == pytest.approx(9, rel=0.05)


def test_window_statistics_measure_gaussian_noise_on_a_ramp():
    """Monte-Carlo: white noise of variance 25 on a steep smooth ramp (shading must not
    count as noise)."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:300, 0:300]
    ws = window_statistics(100 + 2.0 * xx + 0.5 * yy + rng.normal(0, 5, (300, 300)), -1e9, 1e9)
    assert np.mean(ws.var) == pytest.approx(25, rel=0.03)


def test_immerkaer_degrees_of_freedom_match_monte_carlo():
    """The window variance of white noise is a scaled chi-square with dof = N^2 / sum rho^2:
    its relative variance 2 / dof matches the simulation to 5 %; and the plane mean's
    variance factor of photon_transfer (sum of rho^2 over all lags) matches the closed form."""
    rng = np.random.default_rng(1)
    ws = window_statistics(rng.normal(0, 1, (1200, 1200)), -1e9, 1e9)
    sub = ws.var[::7]  # decimate (neighbouring windows overlap) without changing the marginal
    assert np.var(sub) / np.mean(sub) ** 2 == pytest.approx(2 / immerkaer_dof(7), rel=0.05)
    rho = ndimage.correlate(np.pad(IMMERKAER, 2), IMMERKAER, mode="constant") / 36
    assert np.sum(rho**2) == pytest.approx(IMMERKAER_SUM_RHO2, rel=1e-12)


def test_texture_limit_keeps_flat_windows_of_pure_noise():
    """Monte-Carlo: on white noise of the predicted variance, fewer than 0.1 % of the
    windows exceed the 5.5-sigma Laplacian limit (so the test does not bias the variance).
    The limit is loose: a step of 5 noise sigmas passes (its Laplacian, 5 sigma, plus the
    noise stays below 5.5 sqrt(20) = 24.6 sigma; the median binning copes with such
    windows), a step of 40 sigmas is rejected."""
    rng = np.random.default_rng(8)
    ws = window_statistics(100 + rng.normal(0, 4, (800, 800)), -1e9, 1e9)
    coef = np.array([16.0, 0.0, 0.0])
    assert np.mean(ws.texture > texture_limit(ws.mean, coef)) < 1e-3
    for sigmas, rejected in ((5, False), (40, True)):
        edge = window_statistics(100 + 4.0 * sigmas * (np.arange(64) >= 32) + rng.normal(0, 4, (64, 64)), -1e9, 1e9)
        assert (np.max(edge.texture / texture_limit(edge.mean, coef)) > 1) == rejected


def test_median_binning_is_unbiased_for_pure_noise():
    rng = np.random.default_rng(2)
    plane = 500 + rng.normal(0, 3, (600, 600))
    pts = binned_variance(window_statistics(plane, -1e9, 1e9), bins=4)
    np.testing.assert_allclose(pts.var, 9, rtol=0.02)


def test_exposure_pairs_cancel_scene_texture():
    """A scene whose texture swamps the noise in most windows: the local statistics alone
    are off by more than 15 % (100-200 % for most seeds), the exposure pairs (ratio 4)
    recover sigma_o^2 and alpha within 3 % (within 1 % and 3 % over seeds 0-5)."""
    rng = np.random.default_rng(3)
    e = textured_scene(rng, 500)
    sigma_o2, alpha = 9.0, 0.25
    planes = [np.clip(expose(e, t, sigma_o2, alpha, rng), -50, 16000) for t in (0.1, 0.4, 1.6)]
    local = fit_noise_model(binned_variance(window_statistics(planes[1], -50, 16000), bins=32))
    assert abs(local.alpha / alpha - 1) > 0.15
    fit, ratios = estimate_noise(planes, -50, 16000)
    np.testing.assert_allclose(ratios, 4.0, rtol=0.01)
    assert fit.alpha == pytest.approx(alpha, rel=0.03) and fit.sigma_o2 == pytest.approx(sigma_o2, rel=0.03)


def test_pair_statistics_variance_closed_form():
    """Var[long - r short] = sigma_o^2 (1 + r^2) + sqrt(alpha) mu_long (1 + r) on a flat field."""
    rng = np.random.default_rng(4)
    e = np.full((300, 300), 1000.0)
    s, g = expose(e, 1.0, 4.0, 1.0, rng), expose(e, 3.0, 4.0, 1.0, rng)
    ws = pair_statistics(s, g, 3.0, -1e9, 1e9)
    assert np.mean(ws.var) == pytest.approx(4 * 10 + 3000 * 4, rel=0.01)


def test_pair_information_closed_form_on_dark_frames():
    """No light (and c1 = 0): each pixel's one contrast long - r short is N(0, c0 (1 + r^2)),
    so the information about c0 is N / (2 c0^2) whatever r, and a frame split off by an
    unmeasured ratio adds nothing."""
    rng = np.random.default_rng(9)
    c0, n = 3.0, 50 * 60
    planes = [rng.normal(0, np.sqrt(c0), (50, 60)) for _ in range(3)]
    info = pair_information(planes[:2], -1e9, 1e9, [4.0], (c0, 0.0))
    assert info[0, 0] == pytest.approx(n / (2 * c0**2), rel=1e-12)
    split = pair_information(planes, -1e9, 1e9, [4.0, None], (c0, 0.0))
    assert split[0, 0] == pytest.approx(info[0, 0], rel=1e-12)
    # three frames: two contrasts per pixel, twice the information
    assert pair_information(planes, -1e9, 1e9, [4.0, 2.0], (c0, 0.0))[0, 0] == pytest.approx(2 * info[0, 0], rel=1e-12)


def test_bracket_fit_spread_is_near_the_cramer_rao_bound():
    """Monte-Carlo, 30 seeds of a 3-frame bracket (ratio 4) of a smooth scene with dark
    parts, read noise small next to the photon noise: the spread of the fitted
    sigma_o^2 and alpha lies between 0.8 and 1.6 achievable standard errors (a spread's
    sampling error over 30 draws is 13 %), and the mean error within 3 standard errors of
    the mean (no bias)."""
    rng = np.random.default_rng(10)
    sigma_o2, alpha = 2.0, 4.0
    truth = sigma_o2 + 1 / 12
    yy, xx = np.mgrid[0:160, 0:160]
    e = 4000 * np.exp(-xx / 12.0) * (1 + 0.5 * np.sin(yy / 9.0)) + 0.5
    fits, se = [], None
    for _ in range(30):
        planes = [np.clip(np.rint(expose(e, t, sigma_o2, alpha, rng)), -500, 16000) for t in (0.25, 1.0, 4.0)]
        fit, ratios = estimate_noise(planes, -500, 16000)
        fits.append((fit.sigma_o2, fit.alpha))
        if se is None:
            se = np.array(achievable_errors(planes, -500, 16000, ratios, (truth, np.sqrt(alpha))))
    fits = np.array(fits)
    spread = fits.std(axis=0, ddof=1)
    assert np.all(spread >= 0.8 * se) and np.all(spread <= 1.6 * se), (spread, se)
    bias = fits.mean(axis=0) - (truth, alpha)
    assert np.all(np.abs(bias) <= 3 * spread / np.sqrt(30)), (bias, spread)


def test_pair_bins_are_unbiased_when_binned_by_an_independent_key():
    """Photon noise far above the read noise (c0 = 1, c1 = 4, ratio 4) on a scene of
    exponentially distributed means: binning pixels by their own value shifts each bin's
    mean by about the noise variance times the histogram's log-slope, which the fit turns
    into a sigma_o^2 error of over 100 standard errors; binning by an independent estimate
    of the mean (the true mean plus independent noise) and averaging the pixels' own
    values stays within 5 standard errors (|z| <= 4.2 over seeds 11-14: the noisy key
    pools the few darkest pixels with brighter ones, which costs efficiency, not bias).
    The standard errors are the Fisher information of the 400 000 Gaussian differences
    at their known means."""
    rng = np.random.default_rng(11)
    c0, c1, r = 1.0, 4.0, 4.0
    mu = rng.exponential(300.0, 400_000)
    long = mu + rng.normal(0, np.sqrt(c0 + c1 * mu))
    short = mu / r + rng.normal(0, np.sqrt(c0 + c1 * mu / r))
    d = long - r * short
    key = mu + rng.normal(0, np.sqrt(c0 + c1 * mu))
    rows = np.stack([np.full_like(mu, 1 + r * r), (1 + r) * mu]) / (c0 * (1 + r * r) + c1 * (1 + r) * mu)
    se = np.sqrt(np.diag(np.linalg.inv(rows @ rows.T / 2)))
    for kind, k in (("fair", key), ("own", long)):
        fit = fit_noise_model(binned_pairs(PixelPairs(long, d, k, r), 128))
        z = ((fit.sigma_o2 - c0) / se[0], (np.sqrt(fit.alpha) - c1) / se[1])
        if kind == "fair":
            assert abs(z[0]) <= 5 and abs(z[1]) <= 5, z
        else:
            assert abs(z[0]) > 100, z


def test_binned_pairs_counts_a_misplaced_bright_pixel_at_its_own_level():
    """A key from the neighbours can put a fine highlight among dark pixels.  Given a noise
    model, each bin's degrees of freedom are ``(sum V)^2 / sum V^2`` of its pixels'
    variances at their own level (written out here), so such a bin is not weighed as a
    thousand equal pixels.  Over 400 000 Gaussian differences with 1 % of the bright ones
    keyed as dark, the gain stays within 4 Fisher standard errors and sigma_o^2 within 15
    (seeds 3, 4, 5: -0.9, +3.1, -10.7; V read off the key gives -21, -3.5, -25: the
    bins of dark keys, which fix sigma_o^2, weighed as if their few bright pixels were
    dark).  Seed 5, the worst of the three."""
    rng = np.random.default_rng(5)
    c0, c1, r = 16.0, 2.0, 4.0
    mu = np.where(rng.random(400_000) < 0.7, rng.exponential(30.0, 400_000), rng.uniform(500, 9000, 400_000))
    long = mu + rng.normal(0, np.sqrt(c0 + c1 * mu))
    short = mu / r + rng.normal(0, np.sqrt(c0 + c1 * mu / r))
    key = mu + rng.normal(0, np.sqrt((c0 + c1 * mu) / 8))
    lost = (mu > 500) & (rng.random(mu.size) < 0.01)
    key[lost] = rng.exponential(30.0, np.count_nonzero(lost))
    pp = PixelPairs(long, long - r * short, key, r)
    coef = np.array([c0, c1])
    pts = binned_pairs(pp, 128, coef=coef)
    one = pp.subset(key < 60)  # one bin of dark keys, some pixels bright
    v = c0 * (1 + r * r) + c1 * (1 + r) * np.maximum(one.long, 0.0)
    n = one.key.size
    assert binned_pairs(one, 1, coef=coef).count[0] == pytest.approx(v.sum() ** 2 / (v * v).sum() * (n - 1) / n)
    fit = fit_noise_model(pts)
    rows = np.stack([np.full_like(mu, 1 + r * r), (1 + r) * mu]) / (c0 * (1 + r * r) + c1 * (1 + r) * mu)
    se = np.sqrt(np.diag(np.linalg.inv(rows @ rows.T / 2)))
    assert abs(np.sqrt(fit.alpha) - c1) <= 4 * se[1], ((np.sqrt(fit.alpha) - c1) / se[1])
    assert abs(fit.sigma_o2 - c0) <= 15 * se[0], ((fit.sigma_o2 - c0) / se[0])


def test_bracket_fit_ignores_hot_pixels():
    """Hot pixels (a fixed offset, not proportional to the exposure) do not cancel in the
    pair differences (one alone would add 1e4 to a bin's variance); they are dropped as
    outliers of a first fit: 40 of them move the fit by less than 0.5 standard errors
    (what they still move is the measured exposure ratio, their offset is in its sums),
    and the fit is within 3 standard errors of the truth."""
    rng = np.random.default_rng(12)
    yy, xx = np.mgrid[0:200, 0:200]
    e = 3000 * (1 + xx) / 200.0
    hot = rng.integers(0, 200, (2, 40))
    clean = [np.clip(expose(e, t, 9.0, 1.0, rng), -500, 16000) for t in (0.25, 1.0, 4.0)]
    fit, ratios = estimate_noise(clean, -500, 16000)
    se = achievable_errors(clean, -500, 16000, ratios, (9.0, 1.0))
    hot_planes = [p.copy() for p in clean]
    for p in hot_planes:
        p[hot[0], hot[1]] += 3000
    with_hot, _ = estimate_noise(hot_planes, -500, 16000)
    assert abs(with_hot.sigma_o2 - fit.sigma_o2) < 0.5 * se[0] and abs(with_hot.alpha - fit.alpha) < 0.5 * se[1]
    assert abs(fit.sigma_o2 - 9.0) < 3 * se[0] and abs(fit.alpha - 1.0) < 3 * se[1]


def test_photographs_do_not_measure_beta():
    """A still 3-frame bracket of a textured scene on a sensor without gain FPN: the local
    statistics' mu^2 variance is texture, and no beta is reported; sigma_o^2 and alpha
    come from the pairs within 5 % and 2 %.  A
    sensor with gain FPN (beta / alpha = 4e-4) gets beta = 0 too, and its alpha is still the
    pairs' (the pairs cancel the FPN)."""
    rng = np.random.default_rng(5)
    scene = textured_scene(rng, 300) / 8
    for fpn in (0.0, 0.02):
        pattern = rng.normal(0, fpn, scene.shape) if fpn else 0.0
        planes = [expose(scene, t, 16.0, 1.0, rng, pattern) for t in (0.25, 1.0, 4.0)]
        fit, ratios = estimate_noise(planes, -1e9, 12000)
        assert len(ratios) == 2 and fit.model == "affine" and fit.beta == 0.0
        assert fit.alpha == pytest.approx(1.0, rel=0.02) and fit.sigma_o2 == pytest.approx(16.0, rel=0.05)


def test_too_few_windows_is_an_error():
    with pytest.raises(HdrMergeError, match="too few"):
        estimate_noise([np.zeros((12, 12))], 1, 2)


def test_photon_transfer_recovers_the_model_from_darks_and_flats():
    """EMVA 1288 on simulated darks and flats (256 x 256, pairs at 7 levels): sigma_o^2
    and alpha within 1.5 %, beta within 5 %; beta = 0 is recognised."""
    rng = np.random.default_rng(6)
    for beta in (0.0, 1e-4):
        alpha, sigma_o2 = 0.25, 9.0
        pattern = rng.normal(0, np.sqrt(beta / alpha), (256, 256))
        darks = [np.rint(rng.normal(0, 3, (256, 256))) for _ in range(4)]
        flats = [[np.rint(expose(np.full((256, 256), 1000.0), t, sigma_o2, alpha, rng, pattern)) for _ in range(2)]
                 for t in np.geomspace(0.5, 25, 7)]
        r = photon_transfer(darks, flats, 16000)
        assert r.sigma_o2 == pytest.approx(sigma_o2 + 1 / 12, rel=0.015)
        assert r.alpha == pytest.approx(alpha, rel=0.015)
        assert r.model == ("quadratic" if beta else "affine")
        assert r.beta == pytest.approx(beta, rel=0.05, abs=1e-9)
        assert r.used.sum() == 6  # the brightest level is above 70 % of saturation


def test_photon_transfer_variances_against_closed_forms():
    rng = np.random.default_rng(7)
    a, b = rng.normal(0, 2, (500, 500)), rng.normal(0, 2, (500, 500))
    assert temporal_variance([a + 7, b + 7]) == pytest.approx(4, rel=0.01)
    yy, xx = np.mgrid[0:500, 0:500]
    assert spatial_variance(a + 0.3 * xx + 0.1 * yy) == pytest.approx(4, rel=0.02)


def test_photon_transfer_needs_three_levels_of_pairs():
    flat = [[np.zeros((8, 8)), np.zeros((8, 8))]]
    with pytest.raises(HdrMergeError, match="three or more exposures"):
        photon_transfer(None, flat * 2, 100)


def test_frames_that_moved_fall_back_to_the_local_statistics(monkeypatch):
    """A hand-held bracket: the frames see the scene shifted by a few pixels, so the
    exposure pairs measure texture, not noise (their alpha comes out over twice the
    truth); their model then predicts more than PAIR_EXCESS times the variance of the
    frames' own flat windows, and the local statistics give the fit (within 10 % of the
    truth; no pair ratios returned).  The same bracket without the shifts keeps its pairs."""
    import hdrmerge_cli.core.calibrate as calibrate

    rng = np.random.default_rng(21)
    n = 400
    e = 3000 * np.exp(ndimage.gaussian_filter(rng.normal(0, 1.0, (n + 16, n + 16)), 12) * 25)
    sigma_o2, alpha = 9.0, 0.25
    shifts = [(0, 0), (3, 5), (-4, 2)]
    times = (0.1, 0.4, 1.6)
    still = [np.clip(expose(e[8:-8, 8:-8], t, sigma_o2, alpha, rng), -50, 16000) for t in times]
    moved = [np.clip(expose(e[8 + dy:8 + dy + n, 8 + dx:8 + dx + n], t, sigma_o2, alpha, rng), -50, 16000)
             for t, (dy, dx) in zip(times, shifts)]
    fit, ratios = estimate_noise(still, -50, 16000)
    assert len(ratios) == 2 and fit.alpha == pytest.approx(alpha, rel=0.05)
    fit, ratios = estimate_noise(moved, -50, 16000)
    assert ratios == []
    assert fit.alpha == pytest.approx(alpha, rel=0.1) and fit.sigma_o2 == pytest.approx(sigma_o2, rel=0.1)
    monkeypatch.setattr(calibrate, "PAIR_EXCESS", np.inf)  # the pairs' own fit: neither check
    monkeypatch.setattr(calibrate, "PAIR_MOTION_P", 0.0)
    pairs, ratios = estimate_noise(moved, -50, 16000)
    assert len(ratios) == 2 and pairs.alpha > 2 * alpha


def wide_scene(rng, n=400):
    """A scene of about 20 stops (smooth, as a real scene's illumination)."""
    return 3000 * np.exp(ndimage.gaussian_filter(rng.normal(0, 1.0, (n + 16, n + 16)), 12) * 25)


def test_exposure_ratio_of_raw_frames_far_apart():
    """Frames 250 times apart share no pixel above 2 % of the range in the short frame and
    below 70 % in the long one; RAW keeps the noise below black, so the dark pixels
    measure the ratio (within 4 of its standard errors, sqrt(sum d^2) / sum y_short).  A
    frame clipped at black does not, and neither does a short frame without signal
    (effective number of pixels below 1000)."""
    rng = np.random.default_rng(5)
    e = wide_scene(rng)[8:-8, 8:-8]
    s, g = (np.clip(expose(e, t, 9.0, 1.0, rng), -500, 16000) for t in (0.004, 1.0))
    r = exposure_ratio(s, g, -500, 16000)
    neighbours = np.ones((3, 3)) / 8
    neighbours[1, 1] = 0
    use = ndimage.correlate(g, neighbours) < 0.7 * 16000  # the pixels that measure it
    se = np.sqrt(np.sum((g[use] - r * s[use]) ** 2)) / np.sum(s[use])
    assert abs(r - 250) < 4 * se and se < 0.02 * 250
    with pytest.raises(HdrMergeError):
        exposure_ratio(s, g, -500, 16000, black_clipped=True)
    with pytest.raises(HdrMergeError):
        exposure_ratio(rng.normal(0, 3, g.shape), g, -500, 16000)


@pytest.mark.parametrize("sigma_o2,alpha,seed", [(9.0, 0.25, 31), (16.0, 16.0, 32), (4.0, 1.0, 33)])
def test_still_bracket_far_apart_uses_its_pairs(sigma_o2, alpha, seed):
    """A still 3-frame bracket 8 stops apart (ratios 250): the exposure pairs give
    sigma_o^2 and alpha, each within 4 Cramer-Rao standard errors of the truth (the bound
    of the bracket's contrasts at the true ratios and parameters)."""
    rng = np.random.default_rng(seed)
    e = wide_scene(rng)[8:-8, 8:-8]
    times = (0.0016, 0.4, 100.0)
    frames = [np.clip(expose(e, t, sigma_o2, alpha, rng), -500, 16000) for t in times]
    fit, ratios = estimate_noise(frames, -500, 16000)
    assert len(ratios) >= 1 and all(r == pytest.approx(250, rel=0.03) for r in ratios)
    se = achievable_errors(frames, -500, 16000, [250.0, 250.0], (sigma_o2, np.sqrt(alpha)))
    assert abs(fit.sigma_o2 - sigma_o2) < 4 * se[0] and abs(fit.alpha - alpha) < 4 * se[1]


def test_pair_gradient_test_keeps_its_false_alarm_rate_and_finds_a_one_pixel_shift():
    """Still pairs, on a smooth and on a grainy scene at ratios 4 to 100: the block
    chi-squares add up to a chi-square of their degrees of freedom (pooled over 24 pairs,
    p > 1e-3), and at most 1 of the 24 pairs is below p = 0.01 (binomial: 2 or more
    has probability 0.02).  The same pairs with the long frame shifted by one pixel: every
    one below p = 1e-6."""
    rng = np.random.default_rng(40)
    n, coef = 256, None
    total, dof, small, shifted = 0.0, 0, 0, []
    for i in range(24):
        e = wide_scene(rng, n) if i % 2 else textured_scene(rng, n + 16)
        sigma_o2, alpha = [(9.0, 0.25), (16.0, 16.0), (64.0, 0.05)][i % 3]
        r = [4.0, 16.0, 100.0][(i // 2) % 3]
        coef = (sigma_o2, np.sqrt(alpha))
        t = 4000 / (np.sqrt(alpha) * np.median(e) * r)  # the long frame's median at a quarter of the range
        s = np.clip(expose(e[8:-8, 8:-8], t, sigma_o2, alpha, rng), -500, 16000)
        for dy, out in ((0, None), (1, shifted)):
            g = np.clip(expose(e[8 + dy:n + 8 + dy, 8:-8], r * t, sigma_o2, alpha, rng), -500, 16000)
            c, k = pair_gradient_test(s, g, r, -500, 16000, coef)
            if out is None:
                total, dof, small = total + c, dof + k, small + (special.chdtrc(k, c) < 0.01)
            else:
                out.append(special.chdtrc(k, c))
    assert special.chdtrc(dof, total) > 1e-3 and small <= 1
    assert max(shifted) < 1e-6


@pytest.mark.parametrize("sigma_o2,alpha", [(9.0, 0.25), (16.0, 16.0)])
def test_hand_held_bracket_far_apart_falls_back_to_the_local_statistics(sigma_o2, alpha):
    """The frames of a bracket 200 times apart shifted by a few pixels: the pairs'
    differences follow the scene's gradient, so the local statistics give the fit (within
    10 % of the truth; no pair ratios returned)."""
    rng = np.random.default_rng(22)
    n = 400
    e = wide_scene(rng, n)
    times, shifts = (0.002, 0.4, 80.0), [(0, 0), (3, 5), (-4, 2)]
    moved = [np.clip(expose(e[8 + dy:8 + dy + n, 8 + dx:8 + dx + n], t, sigma_o2, alpha, rng), -50, 16000)
             for t, (dy, dx) in zip(times, shifts)]
    fit, ratios = estimate_noise(moved, -50, 16000)
    assert ratios == []
    assert fit.alpha == pytest.approx(alpha, rel=0.1) and fit.sigma_o2 == pytest.approx(sigma_o2, rel=0.1)


def test_weighted_ratio_is_the_gls_ratio_with_its_stated_variance():
    """weighted_ratio against the generalised least-squares ratio written out with numpy
    (``sum w y_long / sum w y_short``, ``w = (key / r) / Var[d]`` by (17) on the pixels
    PixelPairs.usable keeps; equal to 1e-12), and over 300 brackets of 20 000 pixels
    (c0 = 36, c1 = 1, true ratio 4, started 2 % off): the mean within 3 standard errors of
    the truth and the spread of the estimates within 15 % of the stated standard error.
    at_ratio recomputes ``d = long - r short`` for the new ratio (to 1e-9)."""
    from hdrmerge_cli.core.calibrate import PixelPairs, weighted_ratio

    c0, c1, r_true, start = 36.0, 1.0, 4.0, 4.08
    coef = (c0, c1, 0.0)
    estimates, stated = [], []
    for seed in range(300):
        rng = np.random.default_rng(seed)
        mu = rng.exponential(60.0, 20_000)  # the long frame's mean, codes
        long = mu + rng.normal(0, np.sqrt(c0 + c1 * mu))
        short = mu / r_true + rng.normal(0, np.sqrt(c0 + c1 * mu / r_true))
        key = mu + rng.normal(0, np.sqrt(c0 + c1 * mu))  # another frame's reading: independent noise
        pp = PixelPairs(long, long - start * short, key, start)
        r, var = weighted_ratio(pp, coef, -500.0, 16000.0)
        if seed == 0:
            keep = pp.usable(coef, -500.0, 16000.0)
            m = np.maximum(key[keep], 0.0)
            w = (m / start) / (c0 * (1 + start**2) + c1 * (1 + start) * m)
            assert r == pytest.approx(np.sum(w * long[keep]) / np.sum(w * short[keep]), rel=1e-12)
            moved = pp.at_ratio(r, var)
            np.testing.assert_allclose(moved.d, long - r * short, rtol=0, atol=1e-9)
            assert moved.ratio_var == var
        estimates.append(r)
        stated.append(np.sqrt(var))
    estimates = np.array(estimates)
    se = float(np.mean(stated))
    assert abs(estimates.mean() - r_true) < 3 * se / np.sqrt(estimates.size), (estimates.mean(), se)
    assert estimates.std(ddof=1) == pytest.approx(se, rel=0.15)
