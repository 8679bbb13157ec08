"""The forward noise model (16)-(18) against its stated moments (Monte-Carlo)."""
import numpy as np
import pytest

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
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


# ---------------------------------------------------------------- ISO (Hasinoff et al. 2010)
def test_at_iso_matches_the_gain_model():
    """At ISO i, g = i / base ISO: alpha g^2, beta g^2, (sigma_o2 - sigma_post2) g^2 +
    sigma_post2, written out here from the electrons: the pre-amplifier read noise
    (sigma_o2 - sigma_post2) / alpha electrons^2 times the squared gain alpha g^2, plus the
    post-amplifier read noise.  Exact to rounding; at_iso chains and keeps the ADC."""
    base = SensorModel(alpha=0.3, sigma_o2=10.0, beta=2e-4, sigma_post2=2.5, base_iso=200, bits=12, black=256)
    pre_electrons2 = (10.0 - 2.5) / 0.3
    for iso in (50, 200, 800, 3200, 12800):
        gain2 = 0.3 * (iso / 200) ** 2
        s = base.at_iso(iso)
        assert s.alpha == pytest.approx(gain2, rel=1e-12)
        assert s.beta == pytest.approx(2e-4 * (iso / 200) ** 2, rel=1e-12)
        assert s.sigma_o2 == pytest.approx(pre_electrons2 * gain2 + 2.5, rel=1e-12)
        assert s.pre_amp_electrons2 == pytest.approx(pre_electrons2, rel=1e-12)
        assert (s.sigma_post2, s.base_iso, s.bits, s.black) == (2.5, iso, 12, 256)
        assert s.beta / s.alpha == pytest.approx(base.beta / base.alpha, rel=1e-12)  # the same gain pattern
        again = base.at_iso(1600).at_iso(iso)
        assert (again.alpha, again.sigma_o2, again.beta) == pytest.approx((s.alpha, s.sigma_o2, s.beta), rel=1e-12)
    assert base.at_iso(200) == base


def test_sensor_refuses_post_amp_noise_above_the_read_noise_and_bad_isos():
    with pytest.raises(HdrMergeError, match="sigma_post2"):
        SensorModel(sigma_o2=4.0, sigma_post2=5.0)
    with pytest.raises(HdrMergeError, match="sigma_post2"):
        SensorModel(sigma_post2=-1.0)
    with pytest.raises(HdrMergeError, match="base ISO"):
        SensorModel(base_iso=0)
    with pytest.raises(HdrMergeError, match="ISO"):
        SensorModel().at_iso(float("nan"))


def test_expose_at_iso_800_has_the_variance_of_eq17_at_that_iso():
    """ISO 800 from base 100 (g = 8) with sigma_post2 = 4 of sigma_o2 = 9: the variance of
    expose(.., at_iso(800)) is s(x) with alpha 0.25 g^2 = 16 and sigma_o2 5 g^2 + 4 = 324,
    within 4 standard errors of a sample variance (4 s sqrt(2 / n), 1.3 % here), and so
    is a two-stage rendering (electrons and pre-amplifier noise amplified, then the
    post-amplifier noise added); the mean is sqrt(16) x within 4 standard errors."""
    sensor = SensorModel(alpha=0.25, sigma_o2=9.0, sigma_post2=4.0)
    at = sensor.at_iso(800)
    n, e, t = 200_000, 150.0, 2.0
    x = e * t
    var = noise_variance(x, 324.0, 16.0, 0.0)
    y = expose(np.full(n, e), t, at, np.random.default_rng(5), np.zeros(n))
    assert abs(y.mean() - 4.0 * x) < 4 * np.sqrt(var / n)
    assert abs(y.var() - var) < 4 * var * np.sqrt(2 / n)
    rng = np.random.default_rng(6)
    pre = np.sqrt(sensor.alpha) * rng.poisson(x, n) + rng.normal(0, np.sqrt(9.0 - 4.0), n)
    two_stage = 8.0 * pre + rng.normal(0, 2.0, n)
    assert abs(two_stage.var() - var) < 4 * var * np.sqrt(2 / n)


def test_auto_times_at_a_higher_iso_keep_the_highlights():
    """At ISO 1600 saturation comes 16 times sooner (full scale / sqrt(alpha g^2)): the
    automatic times of the sensor at that ISO are 16 times shorter."""
    sensor = SensorModel()
    e = np.geomspace(10, 1e7, 10000)
    t100, t1600 = auto_exposure_times(e, sensor, 3), auto_exposure_times(e, sensor.at_iso(1600), 3)
    np.testing.assert_allclose(t100 / t1600, 16.0, rtol=1e-12)
    assert np.percentile(e, 99.95) * t1600[0] * np.sqrt(sensor.at_iso(1600).alpha) < sensor.full_scale


def test_read_noise_split_recovers_an_exact_line_and_its_errors():
    """sigma_o2 = pre alpha + post through three exact points: pre and post exactly; the
    weighted fit's standard errors are those of (D' W D)^-1, here checked against a
    Monte-Carlo of the same fit (5000 draws, seeded) within 10 %."""
    from hdrmerge_cli.core.calibrate import read_noise_split

    alpha = np.array([0.25, 4.0, 64.0])
    sigma = 20.0 * alpha + 4.0
    fit = read_noise_split(alpha, sigma)
    assert (fit.pre, fit.post) == pytest.approx((20.0, 4.0), rel=1e-12) and not fit.weighted
    se_a, se_s = 0.05 * alpha, np.array([0.2, 2.0, 30.0])
    fit = read_noise_split(alpha, sigma, se_a, se_s)
    assert fit.weighted and (fit.pre, fit.post) == pytest.approx((20.0, 4.0), rel=1e-9)
    rng = np.random.default_rng(7)
    draws = np.array([[f.pre, f.post] for f in (
        read_noise_split(alpha + rng.normal(0, se_a), sigma + rng.normal(0, se_s), se_a, se_s) for _ in range(5000))])
    assert draws.std(axis=0) == pytest.approx([fit.pre_stderr, fit.post_stderr], rel=0.1)
    with pytest.raises(HdrMergeError, match="two or more"):
        read_noise_split([1.0], [2.0])
    with pytest.raises(HdrMergeError, match="different gains"):
        read_noise_split([1.0, 1.0], [2.0, 3.0])
