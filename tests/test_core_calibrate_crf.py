"""Noise fit (17) and CRF estimation against closed forms and Monte-Carlo."""
import numpy as np
import pytest

from hdrmerge_cli.core.calibrate import binned_variance, fit_noise_model, window_statistics
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.crf_estimate import crf_debevec1997, inverse_from_log, sample_pixels
from hdrmerge_cli.core.errors import HdrMergeError


@pytest.mark.parametrize("sigma_o2,alpha,beta", [(16.0, 1.0, 0.0), (4.0, 0.25, 0.0), (9.0, 2.0, 5e-3)])
def test_fit_recovers_parameters_from_exact_points(sigma_o2, alpha, beta):
    mu = np.linspace(5, 3000, 40)
    x = mu / np.sqrt(alpha)
    var = sigma_o2 + alpha * x + beta * x**2
    fit = fit_noise_model(mu, var, np.full(mu.size, 1000))
    assert fit.model == ("quadratic" if beta else "affine")
    assert fit.sigma_o2 == pytest.approx(sigma_o2, rel=1e-4)
    assert fit.alpha == pytest.approx(alpha, rel=1e-4)
    assert fit.beta == pytest.approx(beta, rel=1e-3, abs=1e-9)


def test_window_statistics_measure_gaussian_noise_on_a_ramp():
    """Monte-Carlo: white noise of variance 25 on a steep smooth ramp (shading must not
    count as noise)."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:300, 0:300]
    plane = 100 + 2.0 * xx + 0.5 * yy + rng.normal(0, 5, (300, 300))
    ws = window_statistics(plane, -1e9, 1e9)
    assert np.mean(ws.var) == pytest.approx(25, rel=0.03)


def test_calibration_pipeline_on_simulated_poisson_gaussian_planes():
    rng = np.random.default_rng(1)
    sigma_o2, alpha = 16.0, 1.0
    levels = np.repeat(np.linspace(20, 3000, 30), 10)[:, None] * np.ones((1, 300))
    y = np.sqrt(alpha) * rng.poisson(levels / np.sqrt(alpha)) + rng.normal(0, np.sqrt(sigma_o2), levels.shape)
    fit = fit_noise_model(*binned_variance(window_statistics(y, -1e9, 1e9)))
    assert fit.model == "affine"
    assert fit.alpha == pytest.approx(alpha, rel=0.05) and fit.sigma_o2 == pytest.approx(sigma_o2, rel=0.15)


def test_too_few_windows_is_an_error():
    with pytest.raises(HdrMergeError, match="too few"):
        binned_variance(window_statistics(np.zeros((12, 12)), 1, 2))


def test_debevec_recovers_a_gamma_curve_from_a_noise_free_bracket():
    rng = np.random.default_rng(2)
    e = rng.uniform(0.002, 1.0, 5000)
    times = np.array([0.25, 1.0, 4.0])
    z = np.stack([np.rint(255 * np.clip(e * t, 0, 1) ** (1 / 2.2)) for t in times], axis=1).astype(int)
    g = crf_debevec1997(z, np.log(times), 256, smoothing=10.0).g
    inv, _ = inverse_from_log(g)
    true = CRF("gamma", 2.2).inverse(np.arange(256) / 255)
    codes = np.arange(20, 250)
    np.testing.assert_allclose(np.log(inv[codes] / inv[128]), np.log(true[codes] / true[128]), atol=0.05)


def test_sample_pixels_spreads_over_intensities():
    img = np.arange(10000).reshape(100, 100) % 256
    idx = sample_pixels(img, 256, np.random.default_rng(0))
    assert len(np.unique(img.ravel()[idx])) > 200
