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


def test_histogram_correspondences_match_colour_hdris_grossberg_samples():
    """core.crf_estimate.histogram_correspondences against colour-hdri's
    samples_Grossberg2003 (an independent implementation of Grossberg & Nayar 2003: the
    code nearest each cumulative-histogram level): within one code at every level away
    from the ends, and monotone; the pixels' order does not matter."""
    import colour_hdri

    from hdrmerge_cli.core.crf_estimate import histogram_correspondences

    rng = np.random.default_rng(3)
    e = rng.lognormal(0.0, 1.0, (4000, 3))
    frames = [np.clip(np.rint(255 * np.clip(e * t, 0, 1) ** (1 / 2.2)), 0, 255).astype(np.int64) for t in (0.1, 0.4)]
    ours = histogram_correspondences(frames, 256, rows=200)
    assert all(o.shape == (200, 3) and np.all(np.diff(o, axis=0) >= 0) for o in ours)
    shuffled = histogram_correspondences([f[rng.permutation(len(f))] for f in frames], 256, rows=200)
    assert all(np.array_equal(a, b) for a, b in zip(ours, shuffled))
    stack = np.stack([f.reshape(40, 100, 3) / 255.0 for f in frames], axis=-1)  # (H, W, C, P)
    theirs = colour_hdri.samples_Grossberg2003(stack, samples=401, n=256)[1::2]  # levels j/400, j odd: ours
    mid = slice(10, 190)
    for k in range(2):
        np.testing.assert_allclose(ours[k][mid], theirs[mid, k, :], atol=1)


def test_histogram_rows_at_a_frames_floor_are_no_evidence():
    """A frame's codes at its floor give no row of the fit (they read code 0, which (36)
    weights 0), so the response fitted on the histograms of two frames 6 EV apart does not
    depend on what the short frame reads at its floor (code 3 or code 9 for everything
    below it), and it follows the true curve where both frames read the light."""
    from hdrmerge_cli.core.crf_estimate import fit_response, histogram_correspondences

    rng = np.random.default_rng(4)
    e = np.exp(rng.uniform(np.log(1e-4), 0.0, (20000, 3)))
    times = np.array([1.0, 64.0])
    true = CRF("gamma", 2.2)

    def frame(t, floor):
        return np.maximum(np.rint(255 * np.clip(e * t, 0, 1) ** (1 / 2.2)), floor).astype(np.int64)

    fits = []
    for floor in (3, 9):
        frames = [frame(times[0], floor), frame(times[1], 0)]
        rows = histogram_correspondences(frames, 256, floors=[np.full(3, 9), np.zeros(3, np.int64)])
        assert np.all(rows[0][rows[0] > 0] > 9) and not np.any((rows[0] > 0) & (rows[0] <= 9))
        fits.append(fit_response([r[:, None, :] for r in rows], np.log(times), 256).crf)
    z = np.arange(20, 250) / 255
    a, b = (np.stack([f.inverse(z, c) for c in range(3)]) for f in fits)
    np.testing.assert_array_equal(a, b)
    ref = np.log(true.inverse(z) / true.inverse(z[-1]))
    assert np.max(np.abs(np.log(a[1] / a[1][-1]) - ref)) < 0.25
