"""Ghost detection primitives and decisions (core/deghost.py) on arrays."""
import cv2
import numpy as np
import pytest

from dataclasses import replace

from hdrmerge_cli.core import deghost
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.noise import NoiseParams

#: the per-cell chi-square test alone: a cubic tone match, the gradient registration
#: tolerance, no smooth field, no region test, no minimum change
CELL = replace(deghost.IMAGE_PARAMS, smooth_field=False, envelope_reach=0, min_log_change=0.0)
#: ... with the image's smooth ratio field and minimum log change
GATED = replace(CELL, smooth_field=True, min_log_change=deghost.IMAGE_PARAMS.min_log_change)


def _gain_field_case(rng, ghost: bool):
    """Block estimates of a static frame pair whose ratio varies smoothly over the frame (a
    vignetting / local-tone-mapping-like gain of up to +-0.25 in log), optionally with a
    compact object (a 40 x 40 patch, 1.0 in log) in the frame."""
    h, w = 300, 400
    yy, xx = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    truth = np.exp(rng.uniform(np.log(0.05), np.log(0.8), (h, w, 3))).astype(np.float32)
    gain = 0.25 * np.cos(2.5 * xx + 1.0) * np.sin(2.0 * yy + 0.5)  # smooth, 0.25 at most
    sd = 0.01
    xa = truth * np.exp(rng.normal(0, sd, truth.shape))
    x = truth * np.exp(gain[..., None] + rng.normal(0, sd, truth.shape))
    if ghost:
        x[120:160, 200:240] *= np.e
    x, xa = x.reshape(h, -1).astype(np.float32), xa.reshape(h, -1).astype(np.float32)
    s = ((sd * xa) ** 2).astype(np.float32)
    ok = np.ones(x.shape, bool)
    return x, s, ok, xa, np.zeros(x.shape, np.float32)


def test_ghost_test_false_alarm_rate_and_detection():
    """Monte-Carlo: pure noise cells are rejected at about p_fa (3 samples per cell, chi2_3);
    a block that changed is found."""
    rng = np.random.default_rng(3)
    shape = (400, 600)
    truth = rng.uniform(0.1, 1.0, shape)
    s = np.full(shape, 1e-4)
    xa = truth + rng.normal(0, 1e-2, shape)
    x = truth + rng.normal(0, 1e-2, shape)
    ok = np.ones(shape, bool)
    flat = np.zeros(shape, np.float32)
    exact = replace(CELL, model_tolerance=0.0)
    bad = deghost.inconsistent_cells(x, s, ok, xa, s, ok, flat, 3, replace(exact, p_fa=0.01))
    assert 0.007 < bad.mean() < 0.013
    x[100:150, 300:390] *= 1.5
    bad = deghost.inconsistent_cells(x, s, ok, xa, s, ok, flat, 3, replace(exact, p_fa=0.001))
    cleaned = deghost.clean(bad, 64)
    assert cleaned[100:150, 100:130].mean() > 0.95 and cleaned[:80].mean() == 0


def test_dark_reference_bounds_a_bright_reading():
    x = np.array([0.5, 0.001, 0.3])  # beyond the bounds by more than BOUND_FACTOR = 2: 0.5 > 0.02, 0.3 < 0.45
    s = np.full(3, 1e-6)
    bound = np.array([0.01, 0.01, -0.9])  # dark, dark (upper bound 0.01), clipped (lower bound 0.9)
    assert deghost.violates_bound(x, s, bound, 1e-3).tolist() == [True, False, True]


# ---------------------------------------------------------------- deghosting decision rules
@pytest.mark.parametrize("dtype, n_codes", [(np.uint8, 256), (np.uint16, 4096)])
@pytest.mark.parametrize("b", [1, 2, 3])
def test_block_statistics_match_table_lookups_and_block_means(dtype, n_codes, b):
    """The compiled block pass equals, to float32 rounding (1e-6 relative), table lookups
    followed by block means and all-of tests in NumPy, on one strided channel of
    interleaved codes with dark and clipped regions and codes beyond the table."""
    rng = np.random.default_rng(7)
    codes = rng.integers(0, n_codes, (61, 3 * 47), dtype=dtype)
    codes[:8, :12], codes[10:20, 30:60] = 0, n_codes - 1
    plane = codes[:, 1::3]
    x_t = np.sort(rng.random(n_codes - 10)).astype(np.float32)  # shorter than the codes: last entry repeats
    s_t = rng.random(n_codes - 10).astype(np.float32)
    ok_t = np.zeros(n_codes - 10, bool)
    ok_t[3:-5] = True
    lo, hi = 3, n_codes - 16
    h, w = plane.shape[0] // b, plane.shape[1] // b
    xs, ss, ok, bound = out = (np.empty((h, w), np.float32), np.empty((h, w), np.float32), np.empty((h, w), bool),
                               np.empty((h, w), np.float32))
    deghost.block_statistics(plane, deghost.CodeTable(x_t, s_t, ok_t), b, out)
    z = np.minimum(plane[:h * b, :w * b].astype(np.int64), x_t.size - 1).reshape(h, b, w, b)
    np.testing.assert_allclose(xs, x_t[z].astype(np.float64).mean(axis=(1, 3)), rtol=1e-6)
    np.testing.assert_allclose(ss, s_t[z].astype(np.float64).mean(axis=(1, 3)) / b**2, rtol=1e-6)
    np.testing.assert_array_equal(ok, ok_t[z].all(axis=(1, 3)))
    raw = plane[:h * b, :w * b].reshape(h, b, w, b)
    dark, clipped = (raw < lo).all(axis=(1, 3)), (raw > hi).all(axis=(1, 3))
    assert dark.any() and clipped.any()
    np.testing.assert_array_equal(bound, np.where(dark, x_t[lo], np.where(clipped, -x_t[hi], 0.0)).astype(np.float32))


def test_level_scale_keeps_the_false_alarm_rate_when_the_model_underestimates_the_noise():
    """Monte-Carlo: the noise is 3x what the model says (as with JPEG processing); the
    measured level scale brings the false-alarm rate back to about p_fa."""
    rng = np.random.default_rng(11)
    shape = (400, 600)
    truth = np.exp(rng.uniform(np.log(0.05), 0.0, shape))
    s = (0.01 * truth) ** 2
    xa = truth + rng.normal(0, 3 * 0.01 * truth)
    x = truth + rng.normal(0, 3 * 0.01 * truth)
    ok = np.ones(shape, bool)
    flat = np.zeros(shape, np.float32)
    exact = replace(CELL, model_tolerance=0.0, p_fa=0.01)
    raw = deghost.inconsistent_cells(x, s, ok, xa, s, ok, flat, 3, replace(exact, level_scale=False))
    scaled = deghost.inconsistent_cells(x, s, ok, xa, s, ok, flat, 3, exact)
    assert raw.mean() > 0.3
    assert 0.005 < scaled.mean() < 0.015


def test_intensity_matching_does_not_absorb_an_object_alone_at_its_brightness():
    """A bright patch in a short frame where the anchor reads dark is the only jointly
    measured sample at its level; the smooth robust curve leaves it out (a bin-by-bin
    curve mapped it onto the anchor)."""
    rng = np.random.default_rng(5)
    xa = np.exp(rng.uniform(np.log(0.01), np.log(0.2), 200_000)).astype(np.float32)
    x = (xa * 1.05).astype(np.float32)  # 5 % exposure error: absorbed
    x[:4000] = 0.6  # the object: 2 % of the samples, far above everything else
    both = np.ones(x.size, bool)
    m = deghost.match_anchor(x, xa, both, degree=3)
    np.testing.assert_allclose(m[4000:], xa[4000:], rtol=0.01)
    assert np.all(m[:4000] > 0.4)


def test_glare_excuse_bounds_the_light_glare_adds():
    """With ``source`` and ``need``: excused exactly where the cell is within reach (the
    exact disc) and GLARE_FRACTION of the mean light of the clipped cells in the square of
    side 2 reach + 1 (its part inside the frame; unclipped cells give none) reaches
    ``need``, or a clipped cell of unknown (inf) level lies in that square, or the cell is
    within ``bloom`` of a clipped cell (brute force; cells within 1e-6 of the threshold
    skipped)."""
    rng = np.random.default_rng(8)
    shape, reach, bloom = (60, 80), 0.1, 2.5
    r = reach * max(shape)
    clipped = rng.random(shape) < 0.05
    source = np.where(rng.random(shape) < 0.02, np.inf, rng.uniform(1, 100, shape)).astype(np.float32)
    need = rng.uniform(0, 1.5, shape).astype(np.float32)
    got = deghost.glare_excuse(clipped, 1, reach, source=source, need=need, bloom=bloom)
    ys, xs = np.nonzero(clipped)
    want = np.zeros(shape, np.int8)
    close = np.zeros(shape, bool)
    h = int(r)
    for i in range(shape[0]):
        for j in range(shape[1]):
            d2 = (ys - i) ** 2 + (xs - j) ** 2
            rows, cols = slice(max(0, i - h), i + h + 1), slice(max(0, j - h), j + h + 1)
            lit = np.where(clipped[rows, cols], source[rows, cols].astype(np.float64), 0.0)
            unknown = np.isinf(lit).any()
            mean = np.where(np.isinf(lit), 0.0, lit).mean()
            close[i, j] = abs(deghost.GLARE_FRACTION * mean - need[i, j]) < 1e-6 * (1 + need[i, j])
            if (d2 <= r * r).any() and (deghost.GLARE_FRACTION * mean >= need[i, j] or unknown or (d2 <= bloom**2).any()):
                want[i, j] = 1
    np.testing.assert_array_equal(got[~close], want[~close])
    assert 0 < want.sum() < (deghost.glare_excuse(clipped, 1, reach) != 0).sum()


def test_feathered_mask_has_no_seam():
    """1 - Phi(3) of a frame leaks through the region's edge at most (a Gaussian of sigma
    3 px around a region grown by 9 px), nothing far away, and no step."""
    from scipy.stats import norm

    mask = np.zeros((80, 80), bool)
    mask[30:50, 30:50] = True
    soft = deghost.feather(mask, 3.0)
    assert soft[mask].min() >= norm.cdf(3.0) - 1e-4 and soft[:3].max() < 0.01
    assert np.abs(np.diff(soft, axis=1)).max() < 0.2 and np.abs(np.diff(soft, axis=0)).max() < 0.2


def test_smooth_gain_field_is_not_motion_but_a_compact_object_over_it_is():
    """A static pair differing by a smooth spatial gain (tone mapping, vignetting): the plain
    chi-square test rejects much of it; with the smooth ratio field and the minimum log
    change nothing is rejected.  A compact object over the same field still is."""
    rng = np.random.default_rng(21)
    x, s, ok, xa, flat = _gain_field_case(rng, ghost=False)
    plain = deghost.clean(deghost.inconsistent_cells(x, s, ok, xa, s, ok, flat, 3,
                                                     replace(CELL, level_scale=False)), 64)
    assert plain.mean() > 0.05  # the noise model alone calls the gain motion
    new = deghost.inconsistent_cells(x, s, ok, xa, s, ok, flat, 3, GATED)
    assert deghost.clean(new, 64).mean() <= 0.002
    x, s, ok, xa, flat = _gain_field_case(np.random.default_rng(22), ghost=True)
    new = deghost.clean(deghost.inconsistent_cells(x, s, ok, xa, s, ok, flat, 3, GATED), 64)
    assert new[125:155, 205:235].mean() > 0.95
    outside = np.ones(new.shape, bool)
    outside[110:170, 190:250] = False
    assert new[outside].mean() <= 0.002


def test_glare_near_the_clipped_highlights_of_the_longer_frame_is_not_motion():
    """The longer frame reads brighter around its clipped highlights (glare): excused in
    that direction only; a darker object there is still found."""
    clipped = np.zeros((100, 100), bool)
    clipped[40:60, 40:60] = True
    e = deghost.glare_excuse(clipped, +1)
    assert e[50, 63] == 1 and e[5, 5] == 0  # reach: 5 % of 100 cells
    assert not deghost.glare_excuse(clipped, 0).any()
    rng = np.random.default_rng(23)
    xa = rng.uniform(0.2, 0.4, (100, 300)).astype(np.float32)
    s = np.full(xa.shape, 1e-6, np.float32)
    ok = np.ones(xa.shape, bool)
    x = xa.copy()
    x[36:40, 126:174] *= 2.0  # brighter next to the highlight: glare
    x[60:64, 126:174] *= 0.3  # darker next to it: an object
    x[80:84, 126:174] *= 2.0  # brighter, but beyond the glare's reach
    bad = deghost.inconsistent_cells(x, s, ok, xa, s, ok, np.zeros_like(xa), 3,
                                     replace(CELL, min_log_change=GATED.min_log_change), excuse=e)
    assert not bad[36:40, 42:58].any() and bad[60:64, 42:58].all() and bad[80:84, 42:58].all()


def test_shoulder_excuse_signs_and_their_union_with_glare():
    """+1 where the anchor reads near white, -1 where the frame does, 2 (either) where both;
    combined with another excuse, opposite signs excuse either."""
    a = np.array([False, True, False, True])
    f = np.array([False, False, True, True])
    assert deghost.shoulder_excuse(a, f).tolist() == [0, 1, -1, 2]
    g = np.int8([[0, 0, 0, 0], [1, 1, 1, 1], [-1, -1, -1, -1], [2, 2, 2, 2]])
    s = np.int8([0, 1, -1, 2])
    assert deghost.either_excuse(g, np.broadcast_to(s, g.shape)).tolist() == [
        [0, 1, -1, 2], [1, 1, 2, 2], [-1, 2, -1, 2], [2, 2, 2, 2]]
    x = np.float32([[[0.2, 0.5, 0.95]], [[0.2, 0.5, 0.6]]])
    ok = np.ones(x.shape, bool)
    assert deghost.near_white(x, ok, 1.0, np.float32([0.8, 0.8, 0.8])).tolist() == [[True], [False]]
    ok[0, 0, 2] = False
    assert not deghost.near_white(x, ok, 1.0, np.float32([0.8, 0.8, 0.8])).any()


def test_dark_bound_adapts_to_a_crushed_toe_but_still_finds_a_bright_object():
    """A JPEG tone curve crushes to code 0 values up to 4x the assumed lowest code: the
    adapted dark bound accepts them; a reading 50x beyond still violates it."""
    rng = np.random.default_rng(24)
    bound = np.full(10_000, 0.01, np.float32)
    x = rng.uniform(0.0, 0.04, 10_000).astype(np.float32)
    x[:200] = 0.5
    s = np.full(x.shape, 1e-8, np.float32)
    fixed = deghost.violates_bound(x, s, bound, 1e-3)
    adapted = deghost.violates_bound(x, s, bound, 1e-3, adapt=True)
    assert fixed[200:].mean() > 0.3 and adapted[200:].mean() < 0.01
    assert adapted[:200].all()


@pytest.mark.parametrize("nc, reach", [(1, 1), (3, 1), (3, 2), (4, 1), (5, 1)])
def test_envelope_is_the_per_channel_min_and_max_within_reach(nc, reach):
    """OpenCV's erosion / dilation equal SciPy's minimum / maximum filter of each
    interleaved channel on its own, edges repeated (a footprint over the interleaved
    samples would take the neighbouring channel's values at the left and right edges)."""
    from scipy import ndimage

    a = np.random.default_rng(3).normal(size=(23, 17 * nc)).astype(np.float32)
    lo, hi = deghost.envelope(a, nc, reach)
    for c in range(nc):
        np.testing.assert_array_equal(lo[:, c::nc], ndimage.minimum_filter(a[:, c::nc], 2 * reach + 1, mode="nearest"))
        np.testing.assert_array_equal(hi[:, c::nc], ndimage.maximum_filter(a[:, c::nc], 2 * reach + 1, mode="nearest"))


@pytest.mark.parametrize("ph, pw", [(1, 1), (1, 3), (2, 2), (3, 4)])
def test_cell_sums_equal_reshaped_sums(ph, pw):
    a = np.random.default_rng(4).normal(size=(25, 38)).astype(np.float32)
    h, w = 25 // ph * ph, 38 // pw * pw
    want = a[:h, :w].astype(np.float64).reshape(h // ph, ph, w // pw, pw).sum(axis=(1, 3))
    np.testing.assert_allclose(deghost.cell_sums(a, ph, pw), want, rtol=1e-5, atol=1e-5)
    counts = deghost.cell_sums((a > 0).astype(np.int32), ph, pw)
    np.testing.assert_array_equal(counts, (a[:h, :w] > 0).reshape(h // ph, ph, w // pw, pw).sum(axis=(1, 3)))


def test_binned_median_equals_per_bin_numpy_medians():
    """deghost._binned_median (one sort per array) equals np.median bin by bin (bins of
    at least 10 samples), ties and odd/even counts included, float32 and float64."""
    rng = np.random.default_rng(8)
    for n, dtype in ((50, np.float32), (999, np.float64), (65536, np.float32)):
        key, val = rng.normal(size=n).astype(dtype), rng.normal(size=n).astype(dtype)
        key[: n // 3] = key[0]
        edges = deghost._level_bins(key, 32)
        which = np.clip(np.searchsorted(edges, key, side="right") - 1, 0, max(edges.size - 2, 0))
        want = [(np.median(key[which == b]), np.median(val[which == b]), np.count_nonzero(which == b))
                for b in range(edges.size - 1) if np.count_nonzero(which == b) >= 10]
        c, m, cnt = deghost._binned_median(key, val, 32)
        np.testing.assert_array_equal(c, [w[0] for w in want])
        np.testing.assert_array_equal(m, [w[1] for w in want])
        np.testing.assert_array_equal(cnt, [w[2] for w in want])


def test_glare_excuse_equals_scipy_euclidean_distance():
    """glare_excuse (OpenCV's exact distance transform, compared as whole squared
    distances) marks exactly the cells SciPy's EDT puts within reach of a clipped cell."""
    from scipy import ndimage

    rng = np.random.default_rng(2)
    for shape, frac, reach in (((100, 140), 0.001, 0.05), ((300, 410), 0.01, 0.1), ((37, 5), 0.05, 0.02)):
        clipped = rng.random(shape) < frac
        clipped[0, 0] = True
        want = np.where(ndimage.distance_transform_edt(~clipped) <= reach * max(shape), -1, 0)
        np.testing.assert_array_equal(deghost.glare_excuse(clipped, -1, reach), want)
    assert not deghost.glare_excuse(np.zeros((8, 8), bool), 1).any()


# --- RAW deghosting: readings below black, the reference's noise, regions


def test_ghost_tables_with_footroom_read_codes_below_black_linearly():
    """A linear RAW: codes at and below black are readings (x <= 0, continuing the line
    through black with the same slope), only clipped codes are not; without footroom (an
    image) every code at or below black is censored."""
    noise = NoiseParams(9.0, 0.25, 0.0)
    lin = CRF("linear").codes_table(1024, 64.0, 1000.0)[0]
    x, s, ok = deghost.ghost_tables(1024, 64.0, 1000.0, lin, 2.0, noise, footroom=True)
    slope = 1.0 / (936.0 * 2.0)
    np.testing.assert_allclose(x[[1, 32, 63, 64, 65, 500]], (np.array([1, 32, 63, 64, 65, 500]) - 64) * slope, rtol=1e-12)
    assert ok[:1000].all() and not ok[1000:].any()
    # below black the variance is the read noise's (9 codes^2) plus quantisation, in x units
    np.testing.assert_allclose(s[10], (9.0 + 1 / 12) * slope**2, rtol=1e-6)
    _, _, ok_img = deghost.ghost_tables(1024, 64.0, 1000.0, lin, 2.0, noise)
    assert not ok_img[:65].any() and ok_img[65:1000].all()


def test_a_dark_bound_carries_the_reference_noise():
    """A reference reading at black bounds the signal only up to its own read noise: a
    frame reading within about 3 of the reference's deviations above the lowest measuring
    code is consistent; far beyond it is motion.  Without ``s_bound`` the bound ignores
    that noise and fires on the first case."""
    bound = np.full(4, 0.001, np.float32)  # the x of the lowest measuring code
    s_ref = np.full(4, 0.01**2, np.float32)  # the reference's read noise: sd 0.01
    x = np.array([0.02, 0.028, 0.2, 0.5], np.float32)
    s = np.full(4, 0.002**2, np.float32)
    assert deghost.violates_bound(x, s, bound, 1e-3, s_bound=s_ref).tolist() == [False, False, True, True]
    assert deghost.violates_bound(x, s, bound, 1e-3).tolist() == [True, True, True, True]


def test_region_mean_against_brute_force():
    """:func:`region_mean`: per cell, over each scale's grid region holding it, the mean of
    ``r`` over the ``pos`` samples of its channels, the largest in magnitude over the scales
    (0 where none is measured); cells beyond the last whole region take its neighbour's
    (``expand``).  Checked cell by cell, float64, to 1e-5."""
    rng = np.random.default_rng(12)
    h, w, nc, scales = 19, 22, 3, (2, 4, 8)
    r = rng.normal(0, 1, (h, w * nc)).astype(np.float32)
    pos = rng.random((h, w * nc)) < 0.7
    got = deghost.region_mean(r, pos, nc, scales)
    want = np.zeros((h, w))
    for i in range(h):
        for j in range(w):
            best = 0.0
            for m in scales:
                gi, gj = min(i // m, h // m - 1), min(j // m, w // m - 1)  # partial regions: the last whole one
                rows, cols = slice(gi * m, gi * m + m), slice(gj * m * nc, (gj * m + m) * nc)
                n = pos[rows, cols].sum()
                mean = r[rows, cols][pos[rows, cols]].astype(np.float64).sum() / max(n, 1)
                if abs(mean) > abs(best):
                    best = mean
            want[i, j] = best
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_channel_reductions_equal_numpy():
    """``deghost.reduce_channels``/``any_channel`` (plane by plane) equal NumPy's reductions over the last axis."""
    from hdrmerge_cli.core.deghost import any_channel as _any, reduce_channels as _reduce

    rng = np.random.default_rng(4)
    a = rng.normal(size=(7, 9, 3)).astype(np.float32)
    np.testing.assert_array_equal(_reduce(np.maximum, a), a.max(axis=-1))
    b = rng.random((7, 9, 4)) < 0.2
    np.testing.assert_array_equal(_any(b), b.any(axis=-1))


def test_region_ratio_is_not_pulled_by_noise():
    """The exposure factor between two noisy linear frames of a dark scene (readings below
    0 included) is found within 2 % by :func:`region_ratio`, where binned medians of
    per-sample log ratios are off by tens of per cent; a moving minority (20 % of the
    frame, 3x brighter) does not move it."""
    rng = np.random.default_rng(11)
    truth = np.exp(rng.uniform(np.log(0.02), np.log(2.0), (64, 64)))
    truth = cv2.resize(truth, (512, 512), interpolation=cv2.INTER_LINEAR)
    xa = truth + rng.normal(0, 0.05, truth.shape)
    x = 0.97 * truth + rng.normal(0, 0.2, truth.shape)  # a noisy short frame, 3 % off
    x[:100] *= 3.0
    both = np.ones(truth.shape, bool)
    assert abs(deghost.region_ratio(x, xa, both) * 0.97 - 1) < 0.02
    ok = both & (x > 0) & (xa > 0)
    naive = np.exp(np.median(np.log(xa[ok] / x[ok])))
    assert abs(naive * 0.97 - 1) > 0.1


def test_the_log_change_of_a_reading_at_zero_is_bounded_by_the_noise_not_undefined():
    """A RAW anchor reading exactly 0 (at black) where the frame reads 5 (noise sd 0.01):
    the log change counts each reading as at least the pair's noise deviation, log(5 /
    0.014) ~ 5.9, so the min_log_change gate passes and the cells are rejected; readings
    within the noise of each other are not."""
    rng = np.random.default_rng(3)
    shape = (64, 64 * 4)
    xa = np.zeros(shape, np.float32)
    x = np.where(np.arange(shape[1]) < 128, 5.0, 0.0).astype(np.float32) + rng.normal(0, 0.01, shape).astype(np.float32)
    s = np.full(shape, 1e-4, np.float32)
    ok = np.ones(shape, bool)
    bad = deghost.inconsistent_cells(x, s, ok, xa, s, ok, np.zeros(shape, np.float32), 4,
                                     replace(CELL, level_scale=False, min_log_change=GATED.min_log_change))
    assert bad[:, :32].all() and not bad[:, 32:].any()


@pytest.mark.parametrize("seed", [0, 1])
def test_region_shifts_false_alarms_and_a_dim_ghost(seed):
    """Monte-Carlo: on pure noise (with a level-dependent bias and a variance the model
    under-states by 2x, which the empirical null absorbs) the region test rejects under
    0.5 % of the cells (its rate is p_fa / m^2 per region, 1e-3 expected area); a region
    whose cells all shift by 0.5 of their own noise deviation, which the per-cell test
    cannot see (chi-square at 1e-3 needs 3.3 deviations), is found."""
    rng = np.random.default_rng(seed)
    h, w, nc = 256, 256, 4
    level = np.exp(rng.uniform(-3, 1, (h, w * nc))).astype(np.float32)
    var = np.full((h, w * nc), 1.0, np.float32)
    d = (rng.normal(0, np.sqrt(2.0), (h, w * nc)) + 0.3 * np.log(level)).astype(np.float32)
    scales = deghost.RAW_PARAMS.coarse_scales
    quiet = deghost.region_shifts(d, var, level, nc, 1e-3, scales)
    assert quiet.mean() < 0.005
    ghost = d.copy()
    ghost[100:140, 400:560] += np.float32(0.5 * np.sqrt(2.0))  # 40 x 40 cells of 4 channels
    found = deghost.region_shifts(ghost, var, level, nc, 1e-3, scales)
    assert found[104:136, 104:136].mean() > 0.9
    assert (found & ~quiet).sum() < 2 * 48 * 48
