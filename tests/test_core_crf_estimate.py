"""CRF estimation (Debevec-Malik baseline) against closed forms."""
import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.crf_estimate import crf_debevec1997, inverse_from_log, sample_pixels


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
