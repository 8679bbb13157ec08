"""The forward noise model (16)-(18) against its stated moments (Monte-Carlo)."""
import numpy as np
import pytest

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.sensor import SensorModel, auto_exposure_times, expose, gain_pattern, noise_variance, quantise_crf, quantise_raw


@pytest.mark.parametrize("alpha,sigma_o2", [(0.25, 9.0), (4.0, 0.0), (1.0, 100.0)])
def test_expose_moments_match_eq17(alpha, sigma_o2):
    """Mean sqrt(alpha) t E and variance s(t E) within 4 standard errors."""
    sensor = SensorModel(alpha=alpha, sigma_o2=sigma_o2)
    rng = np.random.default_rng(1)
    n, e, t = 200_000, 300.0, 2.0
    y = expose(np.full(n, e), t, sensor, rng, np.zeros(n))
    x = e * t
    var = noise_variance(x, sigma_o2, alpha, 0.0)
    assert abs(y.mean() - np.sqrt(alpha) * x) < 4 * np.sqrt(var / n)
    assert abs(y.var() - var) < 4 * var * np.sqrt(2 / n)


def test_gain_fixed_pattern_adds_beta_x2_across_pixels():
    sensor = SensorModel(alpha=1.0, sigma_o2=0.0, beta=1e-3)
    rng = np.random.default_rng(2)
    n, x = 200_000, 5000.0
    y = expose(np.full(n, x), 1.0, sensor, rng, gain_pattern((n,), sensor, rng))
    var = noise_variance(x, 0.0, 1.0, 1e-3)
    assert y.var() == pytest.approx(var, rel=0.02)


def test_quantise_raw_clips_and_keeps_values_below_black():
    sensor = SensorModel(bits=12, black=256)
    z = quantise_raw(np.array([-1000.0, -10.2, 0.4, 1e9]), sensor)
    assert z.tolist() == [0, 246, 256, 4095] and z.dtype == np.uint16


def test_quantise_crf_inverts_with_the_crf():
    sensor = SensorModel(bits=12, black=0, sigma_o2=0)
    y = np.linspace(0, sensor.full_scale, 50)[:, None, None] * np.ones((1, 1, 3))
    z = quantise_crf(y, sensor, CRF("srgb"), 16)
    back = CRF("srgb").inverse(z / 65535.0) * sensor.full_scale
    np.testing.assert_allclose(back, y, atol=0.6)


def test_auto_times_cover_the_scene():
    sensor = SensorModel()
    e = np.geomspace(10, 1e7, 10000)
    t = auto_exposure_times(e, sensor, 5)
    assert np.all(np.diff(t) > 0) and t.size == 5
    assert np.percentile(e, 99.95) * t[0] * np.sqrt(sensor.alpha) < sensor.full_scale
    assert np.percentile(e, 1) * t[-1] * np.sqrt(sensor.alpha) >= 0.2 * sensor.full_scale
