"""The reconstruction formula (7) and its streamed table implementation."""
import numpy as np
import pytest

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core import reconstruct
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.core.reconstruct import FLAG_DARK, FLAG_OK, FLAG_SATURATED, LogMerge, exposure_tables
from hdrmerge_cli.core.weights import NOISE_MODEL_WEIGHTS, WEIGHTING_FUNCTIONS

import references
from benchmarks.core_merge import merge_frames

CLASSICAL = sorted(set(WEIGHTING_FUNCTIONS) - set(NOISE_MODEL_WEIGHTS))


def _merge(frames, exposures, crf, weights, n_codes=256, black=0.0, white=255.0, pattern=None, rows=1):
    acc = LogMerge(frames[0].shape, pattern)
    for k, (z, h) in enumerate(zip(frames, exposures)):
        tab = exposure_tables(crf.at_codes(n_codes, np.full(rows, black), np.full(rows, white)), weights, h)
        acc.add(z, tab, last=k == len(frames) - 1)
    return acc.finish()


@pytest.mark.parametrize("weights", CLASSICAL)
def test_streamed_tables_equal_direct_eq7(weights):
    """Independent per-pixel float64 evaluation of (7) with w(z) and g(z) = log gamma^-1(z)."""
    rng = np.random.default_rng(0)
    crf = CRF("gamma", 2.2)
    frames = [rng.integers(0, 256, (17, 23, 3)).astype(np.uint8) for _ in range(4)]
    exposures = [0.01, 0.04, 0.16, 0.64]
    log_e, flag = _merge(frames, exposures, crf, weights)
    num = np.zeros(frames[0].shape)
    den = np.zeros(frames[0].shape)
    for z, h in zip(frames, exposures):
        v = z / 255.0
        w = WEIGHTING_FUNCTIONS[weights](np.arange(256) / 255, crf.inverse(np.arange(256) / 255))[z]
        with np.errstate(divide="ignore"):
            g = np.log(np.where(w > 0, v, 1.0) ** 2.2)
        num += w * (g - np.log(h))
        den += w
    ok = den > 0
    np.testing.assert_allclose(log_e[ok], (num / np.where(ok, den, 1))[ok], atol=2e-5)
    assert np.all(flag[ok] == FLAG_OK)


def test_noise_free_bracket_recovers_irradiance_to_quantisation():
    """Closed form: z = round(255 * min(E t, 1)) -> log E within half a code (relative)."""
    e = np.geomspace(0.05, 900.0, 4000).reshape(40, 100)  # covered: E t_min < 1, E t_max > 12 codes
    times = [1e-3, 1e-2, 1e-1, 1.0]
    frames = [np.clip(np.rint(255 * e * t), 0, 255).astype(np.uint8) for t in times]
    log_e, flag = _merge(frames, times, CRF("linear"), "triangle")
    assert np.all(flag == FLAG_OK)
    # each frame's relative error is at most 0.5 / z; weights favour z near mid-scale
    assert np.max(np.abs(log_e - np.log(e))) < 0.5 / 8
    assert np.sqrt(np.mean((log_e - np.log(e)) ** 2)) < 0.01


def test_pixels_clipped_or_dark_everywhere_get_flagged_finite_bounds():
    times = [0.01, 0.1]
    frames = [np.array([[255, 0], [128, 0]], np.uint8), np.array([[255, 0], [255, 3]], np.uint8)]
    log_e, flag = _merge(frames, times, CRF("linear"), "triangle")
    assert np.all(np.isfinite(log_e))
    assert flag[0, 0] == FLAG_SATURATED and flag[0, 1] == FLAG_DARK
    assert flag[1, 0] == FLAG_OK and flag[1, 1] == FLAG_OK
    # saturated: the clipping level of the shortest exposure (a lower bound)
    assert log_e[0, 0] == pytest.approx(np.log(1.0 / 0.01), rel=1e-6)
    # dark: half a code value in the longest exposure (an upper bound)
    assert log_e[0, 1] == pytest.approx(np.log(0.5 / 255 / 0.1), rel=1e-6)


def test_single_frame_merge_is_that_frame():
    z = np.arange(1, 255, dtype=np.uint8).reshape(2, 127)
    log_e, flag = _merge([z], [0.5], CRF("linear"), "uniform")
    np.testing.assert_allclose(log_e, np.log(z / 255 / 0.5), rtol=1e-6)


def test_per_channel_tables_use_each_channels_black_level():
    """A mosaic whose channels have different black levels: offsets pick the right row."""
    blacks = np.array([10.0, 20.0])
    cmap = np.array([[0, 1], [1, 0]])
    z = np.array([[110, 120], [120, 110]], np.uint16)
    acc = LogMerge(z.shape, cmap)
    tab = exposure_tables(CRF("linear").at_codes(65536, blacks, blacks + 1000.0), "uniform", 1.0)
    acc.add(z, tab, last=True)
    log_e, _ = acc.finish()
    np.testing.assert_allclose(np.exp(log_e), np.full((2, 2), 100 / 1000), rtol=1e-6)


def test_frames_with_different_black_levels_use_their_own():
    """Two RAW-like frames of one scene whose black levels differ (as some cameras' do per
    shot): each frame's own table must be used."""
    from hdrmerge_cli.io.frames import Frame
    from hdrmerge_cli.pipeline.choices import choose_models
    from hdrmerge_cli.pipeline.options import MergeSettings

    def frame(black):
        return Frame(path="x", kind="raw", width=2, height=1, exposure_time=1.0, iso=None, aperture=None, make="",
                     model="", timestamp=None, bits=12, n_codes=65536, black=np.full(4, black),
                     white=np.full(4, 4095.0), channels=4, cfa_pattern="RGGB")

    frames = [frame(100.0), frame(200.0)]
    settings = MergeSettings(estimator="log", weights="uniform", variance="none")
    models = choose_models(frames, np.array([1.0, 2.0]), CRF("linear"), settings, pattern=np.array([[0, 1], [1, 2]]),
                           timings={})
    tables = models.tables
    assert models.pattern is None
    acc = LogMerge((1, 2))
    signal = np.array([[500.0, 1000.0]])  # code values above black at exposure 1
    for k, (f, t, h) in enumerate(zip(frames, tables, (1.0, 2.0))):
        acc.add(np.rint(signal * h + f.black[0]).astype(np.uint16), t, last=k == 1)
    log_e, _ = acc.finish()
    # frame 0 reads signal / (4095 - 100) at h = 1, frame 1 reads 2 signal / (4095 - 200) at h = 2;
    # uniform weights average the two in log
    expected = np.exp(0.5 * (np.log(signal / 3995.0) + np.log(2 * signal / 3895.0 / 2)))
    np.testing.assert_allclose(np.exp(log_e), expected, rtol=1e-5)


def _reference(frames, tables, rows, linear, weights=None):
    """The streamed merge written plainly in numpy (float64), with a separate fallback
    array: an independent check of the fused kernels' sentinel bookkeeping."""
    num = np.zeros(frames[0].shape)
    den = np.zeros(frames[0].shape)
    for k, (z, tab) in enumerate(zip(frames, tables)):
        n = tab.n_codes
        idx = z.astype(np.intp) + (0 if rows is None else rows * n)
        w = tab.weight[idx].astype(np.float64) if weights is None else weights[k]
        num += w * tab.value[idx] if weights is not None else tab.weighted_log[idx]
        den += w
        if k == 0:
            fallback = tab.fallback_log[idx].astype(np.float64)
            saturated = tab.above_mid[idx]
        if k == len(frames) - 1:
            fallback = np.where(saturated, fallback, tab.fallback_log[idx])
            floor = tab.fallback_log[(0 if rows is None else rows * n)]
    with np.errstate(divide="ignore", invalid="ignore"):
        est = num / den
    measured = den > 0
    flag = np.where(measured, FLAG_OK, np.where(saturated, FLAG_SATURATED, FLAG_DARK))
    if linear:
        black = measured & ~(est > 0)
        flag = np.where(black, FLAG_DARK, flag)
        with np.errstate(divide="ignore", invalid="ignore"):
            est = np.where(black, floor, np.log(est))
    return np.where(measured, est, fallback), flag


@pytest.mark.parametrize("layout", ["rgb", "mosaic", "shared"])
@pytest.mark.parametrize("estimator", ["log", "ml"])
@pytest.mark.parametrize("irls", [False, True])
def test_fused_kernel_equals_numpy_reference(layout, estimator, irls):
    """Random codes with many clipped and black samples, per-channel black levels: the
    fused accumulate/finish kernels against :func:`_reference` (tolerance: float32 sums)."""
    rng = np.random.default_rng(7)
    exposures = [0.002, 0.01, 0.05, 0.25]
    if layout == "rgb":
        shape, n, rows_n, pattern = (19, 23, 3), 256, 3, np.array([[0, 1, 2]])
        black, white = np.array([0.0, 2.0, 4.0]), np.array([255.0, 250.0, 255.0])
    elif layout == "mosaic":
        shape, n, rows_n, pattern = (22, 31), 4096, 4, np.array([[0, 1], [3, 2]])
        black, white = np.array([60.0, 64.0, 64.0, 70.0]), np.full(4, 4000.0)
    else:
        shape, n, rows_n, pattern = (13, 17), 1024, 1, None
        black, white = np.array([16.0]), np.array([1000.0])
    rows = None if pattern is None else np.tile(pattern, (shape[0], shape[1] * (3 if layout == "rgb" else 1)))[
        :shape[0], :int(np.prod(shape[1:]))].reshape(shape)
    dtype = np.uint8 if n == 256 else np.uint16
    frames = [rng.choice([0, 1, n - 1, *rng.integers(0, n, 20)], size=shape).astype(dtype) for _ in exposures]
    crf = CRF("linear")
    tables = [exposure_tables(crf.at_codes(n, black, white), "probabilistic" if irls else "triangle", h, estimator=estimator,
                              noise=[NoiseParams(4.0, 1.0, 0.0)] * rows_n,
                              prior_rate=1e4, exposures=tuple(exposures)) for h in exposures]
    weights = [rng.random(shape).astype(np.float32) * (rng.random(shape) < 0.7) for _ in exposures] if irls else None
    acc = LogMerge(shape, pattern)
    for k, (z, tab) in enumerate(zip(frames, tables)):
        acc.add(z, tab, last=k == len(frames) - 1, weight=None if weights is None else weights[k])
    got, flag = acc.finish(linear=estimator == "ml")
    want, want_flag = _reference(frames, tables, rows, estimator == "ml", weights)
    np.testing.assert_array_equal(flag, want_flag)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-5)
    assert np.all(acc.den >= 0)


def test_finish_with_scale_returns_the_linear_image():
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 256, (8, 9, 3)).astype(np.uint8) for _ in range(3)]
    times = [0.01, 0.1, 1.0]
    log_e, flag = _merge(frames, times, CRF("gamma", 2.2), "triangle")
    log_e = log_e.copy()
    acc = LogMerge(frames[0].shape)
    for k, (z, h) in enumerate(zip(frames, times)):
        acc.add(z, exposure_tables(CRF("gamma", 2.2).at_codes(256, np.zeros(1), np.full(1, 255.0)), "triangle", h), last=k == 2)
    lin, flag2 = acc.finish(scale=0.5)
    np.testing.assert_array_equal(flag, flag2)
    np.testing.assert_allclose(lin, 0.5 * np.exp(log_e), rtol=1e-5)


def test_merge_frames_equals_direct_eq7_in_linear_units():
    """merge_frames (tables, fused kernels, linear output) against a per-pixel float64
    evaluation of (7) with triangle weights; tolerance: float32 sums."""
    from benchmarks.core_merge import merge_frames

    rng = np.random.default_rng(11)
    crf = CRF("gamma", 2.2)
    frames = [rng.integers(1, 255, (9, 13, 3)).astype(np.uint8) for _ in range(3)]
    times = [0.01, 0.05, 0.25]
    out, flag, den = merge_frames(frames, times, crf, 0.0, 255.0, "triangle", scale=2.0)
    num = np.zeros(frames[0].shape)
    wsum = np.zeros(frames[0].shape)
    for z, h in zip(frames, times):
        v = z / 255.0
        w = WEIGHTING_FUNCTIONS["triangle"](v, v**2.2)
        num += w * (np.log(v**2.2) - np.log(h))
        wsum += w
    assert np.all(flag == FLAG_OK)
    np.testing.assert_allclose(out, 2.0 * np.exp(num / wsum), rtol=1e-5)
    np.testing.assert_allclose(den, wsum, rtol=1e-5)


def test_merge_frames_irls_recovers_a_noise_free_irradiance():
    """Closed form: codes round(4095 min(E t, 1)); re-weighted ML and log estimates both
    stay within the quantisation error of the truth."""
    from benchmarks.core_merge import merge_frames

    e = np.geomspace(1e3, 1e7, 1200).reshape(30, 40)  # every pixel >= 100 codes in some frame
    times = [1e-4, 1e-3, 1e-2, 1e-1]
    frames = [np.clip(np.rint(e * t), 0, 4095).astype(np.uint16) for t in times]
    for estimator in ("log", "ml"):
        out, flag, _ = merge_frames(frames, times, CRF("linear"), 0.0, 4095.0, "probabilistic",
                                    [NoiseParams(1.0, 1.0, 0.0)], estimator=estimator, prior_rate=1e3,
                                    irls_iterations=3)
        ok = flag == FLAG_OK
        assert ok.mean() > 0.99
        err = np.abs(np.log(out[ok] * 4095 / e[ok]))
        # out is E / 4095 per second; half a code at >= 100 codes is 0.005 (measured 0.0060 both)
        # away from the clip; ML reads a clipped frame as censored (y > 4094.5 with the model's
        # sd ~64 codes), which these noise-free codes just above full scale do not fit: there
        # it may move by a fraction of the unclipped frame's model sd (5 %; measured 0.021)
        near = np.any([np.abs(e * t - 4095) < 3 * np.sqrt(1 + 4095) for t in times], axis=0)[ok]
        assert np.max(err[~near] if estimator == "ml" else err) < 0.008
        assert np.max(err) < 0.03


def test_codes_above_the_table_read_as_clipped():
    """A corrupt 12-bit frame holding codes above 4095 (a uint16 container): the fused
    kernel reads them as the table's clipped last entry instead of past its end."""
    tab = exposure_tables(CRF("linear").at_codes(4096, np.zeros(1), np.full(1, 4095.0)), "triangle", 1.0)
    acc = LogMerge((1, 3))
    acc.add(np.array([[2048, 4095, 60000]], np.uint16), tab, last=True)
    log_e, flag = acc.finish()
    assert flag.tolist() == [[FLAG_OK, FLAG_SATURATED, FLAG_SATURATED]]
    assert log_e[0, 1] == log_e[0, 2] and np.isfinite(log_e).all()
    # the per-sample lookup of IRLS and deghosting reads them the same way
    codes = np.array([[2048, 4095, 60000]], np.uint16)
    np.testing.assert_array_equal(reconstruct.lookup(tab.weight, 4096, codes, None), tab.weight[[[2048, 4095, 4095]]])
    two = np.concatenate([tab.weight, 2 * tab.weight])  # a second table row
    pattern = np.array([[0, 1, 1]])
    np.testing.assert_array_equal(reconstruct.lookup(two, 4096, codes, pattern),
                                  [[tab.weight[2048], *2 * tab.weight[[4095, 4095]]]])


@pytest.mark.parametrize("shape, pattern", [((6, 8), np.array([[0, 1], [2, 3]])), ((5, 7, 3), np.array([[0, 1, 2]]))])
def test_lookup_by_pattern_matches_a_per_sample_index(shape, pattern):
    rng = np.random.default_rng(3)
    table = rng.random(4 * 256).astype(np.float32)
    codes = rng.integers(0, 300, shape).astype(np.uint16)  # some above the table
    rows = reconstruct.channel_index(shape, pattern)
    expected = table.reshape(4, 256)[rows, np.minimum(codes, 255)]
    np.testing.assert_array_equal(reconstruct.lookup(table, 256, codes, pattern), expected)


@pytest.mark.parametrize("crf", [CRF("srgb"), CRF("gamma", 2.5), CRF("linear")])
def test_quantisation_variance_matches_monte_carlo(crf):
    """(dy/dz)^2 / 12: the variance of the rounding error of a code, seen through the
    inverse response, against Monte-Carlo: a continuous signal near each code is encoded,
    rounded to 8 bits and linearised; the error's variance per code is compared."""
    full = 255.0
    lin = crf.inverse(np.arange(256) / full)
    predicted = reconstruct.quantisation_variance(lin, full)
    rng = np.random.default_rng(7)
    v = rng.uniform(0.5, 254.5, 4_000_000) / full  # code values, continuous
    z = np.rint(v * full).astype(np.int64)
    err = (lin[z] - crf.inverse(v)) * full
    var = np.bincount(z, weights=err * err, minlength=256) / np.maximum(np.bincount(z, minlength=256), 1)
    codes = np.arange(8, 250)  # away from the rounding of the ends
    np.testing.assert_allclose(var[codes], predicted[codes], rtol=0.06)
    if crf.is_linear:
        np.testing.assert_allclose(predicted, 1 / 12)


def test_code_error_variance_in_the_log_domain():
    """c(y) / y^2 = (d log gamma^-1 / dz)^2 / 12 + tolerance^2: for gamma^-1(v) = v^p,
    d log gamma^-1 / dz = p / z (independent, analytic)."""
    p, full = 2.2, 255.0
    z = np.arange(256.0)
    lin = (z / full) ** p
    c = reconstruct.code_error_variance(lin, full, tolerance=0.01)
    codes = np.arange(10, 250)
    y = lin[codes] * full
    np.testing.assert_allclose(c[codes] / y**2, (p / codes) ** 2 / 12 + 1e-4, rtol=0.01)


def _censored_ml(codes, times, full, p):
    """Independent float64 solution of the censored (Tobit) quasi-likelihood equation of one
    sample: readings below full scale as N(mu_j, v(mu_j)) means, readings at full scale as
    ``y > full - 1/2``; ``mu_j = t_j E``, ``v = sigma_o2 + sqrt(alpha) mu``; by brentq."""
    from scipy.optimize import brentq
    from scipy.stats import norm

    def score(log_mu_unit):
        e = np.exp(log_mu_unit)
        out = 0.0
        for z, t in zip(codes, times):
            mu = e * t
            v = p.sigma_o2 + np.sqrt(p.alpha) * mu
            if z >= full:
                a = (full - 0.5 - mu) / np.sqrt(v)
                out += t * np.exp(norm.logpdf(a) - norm.logsf(a)) / np.sqrt(v)
            elif z > 0:
                out += t * (z - mu) / v
        return out

    return np.exp(brentq(score, np.log(10.0), np.log(1e5), xtol=1e-12))


def test_ml_irls_treats_clipped_readings_as_censored():
    """Near saturation the ML estimator's re-weighting reads a clipped frame as 'above full
    scale' (censored_terms): converged, it solves the censored likelihood equation of an
    independent scipy computation, and on noisy brackets around the clipping level its rms
    log error is lower than the one-pass tables' (which drop the clipped readings)."""
    from benchmarks.core_merge import merge_frames

    full, p = 4095, NoiseParams(sigma_o2=400.0, alpha=16.0)
    times = [1.0, 4.0]
    rng = np.random.default_rng(3)
    e = np.repeat(np.linspace(800.0, 1400.0, 7), 3000)  # frame 2 at 3200..5600 codes: partly clipped
    frames = [np.clip(np.rint(t * e + rng.normal(0, np.sqrt(p.sigma_o2 + np.sqrt(p.alpha) * t * e))), 0,
                      full).astype(np.uint16).reshape(1, -1) for t in times]
    kw = dict(noise=[p], estimator="ml")
    out, flag, _ = merge_frames(frames, times, CRF("linear"), 0.0, float(full), "uniform", irls_iterations=30, **kw)
    assert (flag == FLAG_OK).all()
    est = out.ravel() * full  # codes per unit time
    pick = rng.choice(e.size, 40, replace=False)
    ref = np.array([_censored_ml([f.ravel()[i] for f in frames], times, full, p) for i in pick])
    assert np.max(np.abs(np.log(est[pick] / ref))) < 1e-3
    one, _, _ = merge_frames(frames, times, CRF("linear"), 0.0, float(full), "uniform", **kw)
    for level in np.unique(e):  # rms log error, converged vs one pass without the clipped readings
        m = e == level
        new, old = (np.sqrt(np.mean(np.log(x[m] / level) ** 2)) for x in (est, one.ravel() * full))
        assert new <= old * 1.005
        if abs(level * times[1] - full) < 2 * np.sqrt(p.sigma_o2 + 4 * full):  # frame 2 partly clipped
            assert new < 0.93 * old  # measured 0.0357 vs 0.0388 (E = 1000), 0.0490 vs 0.0628 (1100)


@pytest.mark.parametrize("estimator", ["ml", "log"])
@pytest.mark.parametrize("layout", ["mosaic", "rgb"])
@pytest.mark.parametrize("with_den", [True, False])
@pytest.mark.parametrize("adjusted", [False, True])
def test_irls_in_strips_equals_irls_on_whole_frames(monkeypatch, estimator, layout, with_den, adjusted):
    """irls re-weights strips of rows each on its own: a sample's weights read only its own
    estimate, so one pass equals the whole-frame pass (same float32 arithmetic, to 1e-6),
    and iterated passes agree within the tolerance each strip converges to; flags equal.
    With ``adjust`` (a per-pixel factor by the frame's own row, as the merge's coverage and
    ghost weights), each strip's call gets its rows."""
    from benchmarks.core_merge import merge_in_memory
    from benchmarks.core_merge import irls
    from hdrmerge_cli.core.reconstruct import noise_rows

    rng = np.random.default_rng(11)
    full, p = 4095, NoiseParams(sigma_o2=30.0, alpha=4.0)
    times = [1.0, 4.0, 16.0]
    shape = (50, 36) if layout == "mosaic" else (50, 12, 3)
    pattern = np.array([[0, 1], [2, 3]]) if layout == "mosaic" else np.array([[0, 1, 2]])
    rows = 4 if layout == "mosaic" else 3
    e = np.exp(rng.uniform(np.log(5.0), np.log(3000.0), shape))
    codes = [np.clip(np.rint(t * e + rng.normal(0, np.sqrt(p.sigma_o2 + 2 * t * e))), 0, full).astype(np.uint16)
             for t in times]
    tables = [exposure_tables(CRF("linear").at_codes(full + 1, np.zeros(rows), np.full(rows, float(full))), "uniform", t,
                              [p] * rows, "model", None, tuple(times), estimator=estimator) for t in times]
    linear = estimator == "ml"
    maps = [noise_rows([p] * rows)] * 3
    factors = [np.clip(rng.uniform(-0.5, 1.5, shape[:2]), 0, 1).astype(np.float32) for _ in times]
    calls = []

    def adjust(k, z, w, own, part):  # frame k's factor on the rows ``part``, per sample
        calls.append(part)
        f = np.repeat(factors[k][part], w.shape[1] // shape[1], axis=1)
        return w * f, f

    for passes in (1, 4):
        out = {}
        for strip in (8, 1000):  # strips of 8 rows (the last one 2), and one piece
            monkeypatch.setattr(reconstruct, "STRIP_ROWS", strip)
            log_e, flags, den = merge_in_memory(codes, tables, pattern, linear)
            out[strip] = irls(codes.__getitem__, tables, pattern, log_e, times, [float(full)] * 3, maps, linear,
                              passes, variance=True, den=den if with_den else None,
                              adjust=adjust if adjusted else None)
        (a, fa, da, na, va), (b, fb, db, nb, vb) = ((r.result, r.flags, r.den, r.iterations, r.variance)
                                                  for r in (out[8], out[1000]))
        np.testing.assert_array_equal(fa, fb)
        ok = fa == FLAG_OK
        if passes == 1:
            np.testing.assert_allclose(a[ok], b[ok], atol=1e-6)
            np.testing.assert_allclose(da[ok], db[ok], rtol=1e-5)
            np.testing.assert_allclose(va[ok], vb[ok], rtol=1e-5)
        else:  # converged within the tolerance; the information (den) near a clipping level, where
            # the censored terms' weight is steep in the estimate, moves more on a few samples
            np.testing.assert_allclose(a[ok], b[ok], atol=2 * reconstruct.IRLS_TOLERANCE)
            for x, y in ((da, db), (va, vb)):
                assert np.quantile(np.abs(x[ok] / y[ok] - 1), 0.99) < 0.02
        assert na <= passes and nb <= passes
    if adjusted:
        assert {(c.start, c.stop) for c in calls} == {(r, min(r + 8, 50)) for r in range(0, 50, 8)} | {(0, 50)}


@pytest.mark.parametrize("linear", [True, False])
@pytest.mark.parametrize("shape, pattern", [((6, 8), np.array([[0, 1], [2, 3]])), ((5, 7, 3), np.array([[0, 1, 2]]))])
def test_fused_irls_weights_match_the_reference(shape, pattern, linear):
    """The compiled per-frame weights of IRLS equal :func:`irls_weights` (lookup + numpy) with
    each sample's own noise parameters."""
    rng = np.random.default_rng(4)
    rows = pattern.max() + 1
    certainty = rng.random((rows, 256)).astype(np.float32)
    certainty[:, [0, 255]] = 0.0
    codes = rng.integers(0, 300, shape).astype(np.uint16)
    log_e = rng.normal(-3, 1, shape).astype(np.float32)
    params = [NoiseParams(float(rng.uniform(1, 20)), float(rng.uniform(0.5, 4)), float(rng.uniform(0, 1e-3)))
              for _ in range(rows)]
    per_row = reconstruct.noise_rows(params)
    idx = reconstruct.channel_index(shape, pattern)
    expected = references.irls_weights(reconstruct.lookup(certainty.ravel(), 256, codes, pattern), log_e, 0.01, 255.0,
                                        [m[idx] for m in per_row], linear)
    flat = reconstruct._rows_cols(shape)
    out = np.empty(flat, np.float32)
    reconstruct._irls_weights_rows(codes.reshape(flat), pattern.astype(np.intp), certainty, log_e.reshape(flat),
                                   np.float32(0.01 * 255.0), *per_row, linear, out)
    np.testing.assert_allclose(out.reshape(shape), expected, rtol=2e-6)


@pytest.mark.parametrize("use_den, use_factor", [(False, False), (True, True)])
def test_fused_censored_terms_match_the_reference(use_den, use_factor):
    """The compiled censored terms of IRLS (_censored_rows) equal censored_terms (scipy's
    log_ndtr) on the readings the numpy selection keeps: clipped, not CENSORED_SDS sds
    above full scale, and (with the previous pass's den) measured by the previous pass and
    not CENSORED_SDS combined sds below it; estimates from far below to far above full
    scale (a from about -40 to 60).  They add to sums already started and set those that
    are not (den 0 or a class mark -1)."""
    rng = np.random.default_rng(11)
    pattern = np.array([[0, 1], [1, 2]], np.intp)
    shape, full, h = (40, 60), 4095.0, 0.5
    params = [NoiseParams(float(rng.uniform(5, 50)), float(rng.uniform(0.5, 4)), float(rng.uniform(0, 1e-4)))
              for _ in range(3)]
    rows = reconstruct.noise_rows(params)
    saturated = np.zeros((3, 4096), bool)
    saturated[:, 4095] = True
    codes = np.where(rng.random(shape) < 0.7, 4095, rng.integers(0, 4095, shape)).astype(np.uint16)
    log_e = np.log(rng.uniform(0.2, 2.5, shape) * full / (h * full)).astype(np.float32)
    den = np.where(rng.random(shape) < 0.2, 0.0, rng.uniform(1e-6, 1e3, shape)).astype(np.float32)
    factor = rng.random(shape).astype(np.float32)
    k = h * full
    sd_full2 = float(max(rows[0]) + max(rows[1]) * full + max(rows[2]) * full ** 2)
    log_hi = np.float32(np.log((full - 0.5 + reconstruct.CENSORED_SDS * np.sqrt(sd_full2)) / k))
    # the reference: numpy selection, then censored_terms
    idx = reconstruct.channel_index(shape, pattern)
    sat = (codes == 4095) & (log_e < log_hi)
    if use_den:
        sat &= den > 0
        sd = np.sqrt(sd_full2 + np.where(den > 0, k * k / np.where(den > 0, den, 1.0), np.inf))
        sat &= np.exp(log_e.astype(np.float64)) * k > full - 0.5 - reconstruct.CENSORED_SDS * sd
    assert 0 < sat.sum() < sat.size
    cw, cv = references.censored_terms(log_e[sat], h, full, [m[idx][sat] for m in rows])
    if use_factor:
        cw = cw * factor[sat]
    start_num = rng.uniform(1, 2, shape).astype(np.float32)
    start_den = rng.choice(np.float32([-1.0, 0.0, 0.5, 2.0]), shape)
    started = start_den > 0
    num, den_c = start_num.copy(), start_den.copy()
    num[sat] = np.where(started[sat], num[sat], 0.0) + cw * cv
    den_c[sat] = np.where(started[sat], den_c[sat], 0.0) + cw
    var_c = np.where(sat, den_c, np.where(started, start_den, 7.0))  # var follows den where a term was added
    out_num, out_den, out_var = start_num.copy(), start_den.copy(), np.where(started, start_den, 7.0)
    reconstruct._censored_rows(codes, pattern, saturated, log_e, den, use_den, k, full, sd_full2, log_hi, *rows,
                               factor, use_factor, out_num, out_den, out_var, True)
    np.testing.assert_allclose(out_den, den_c, rtol=1e-5, atol=1e-30)
    np.testing.assert_allclose(out_num, num, rtol=1e-5, atol=1e-30)
    np.testing.assert_allclose(out_var, var_c, rtol=1e-5)
    # Mills' ratio on both sides of the switch to the asymptotic series
    from scipy.special import log_ndtr
    for a in (-38.0, -5.0, 0.0, 3.0, 29.99, 30.0, 45.0, 300.0):
        ref = np.exp(-0.5 * a * a - 0.5 * np.log(2 * np.pi) - log_ndtr(-a))
        assert reconstruct._inverse_mills(a) == pytest.approx(ref, rel=1e-10, abs=1e-300)


def _layout(layout: str):
    """``(shape, n_codes, pattern, black, white)`` of a small 8-bit RGB image or 12-bit
    RGGB mosaic."""
    if layout == "rgb":
        return (17, 21, 3), 256, np.array([[0, 1, 2]]), np.zeros(3), np.full(3, 255.0)
    return (18, 26), 4096, np.array([[0, 1], [3, 2]]), np.full(4, 64.0), np.full(4, 4000.0)


def _codes(rng, shape, n: int) -> np.ndarray:
    """Random codes with black (0, 1) and clipped (n - 1) ones among them."""
    return rng.choice([0, 1, n - 1, *rng.integers(0, n, 30)], size=shape).astype(np.uint8 if n == 256 else np.uint16)


@pytest.mark.parametrize("linear", [True, False])
@pytest.mark.parametrize("layout", ["rgb", "mosaic"])
def test_add_irls_equals_add_with_numpy_irls_weights(layout, linear):
    """LogMerge.add_irls (weights computed inside the accumulation) gives the sums and
    flags of LogMerge.add with the weights of :func:`irls_weights` (lookup + NumPy, each
    sample's own noise parameters), frame for frame, with black and clipped codes."""
    rng = np.random.default_rng(21)
    exposures = [0.004, 0.02, 0.1]
    shape, n, pattern, black, white = _layout(layout)
    rows_n = pattern.max() + 1
    params = [NoiseParams(float(rng.uniform(1, 20)), float(rng.uniform(0.5, 4)), float(rng.uniform(0, 1e-3)))
              for _ in range(rows_n)]
    tables = [exposure_tables(CRF("linear").at_codes(n, black, white), "probabilistic", h, noise=params,
                              estimator="ml" if linear else "log", prior_rate=1e4, exposures=tuple(exposures))
              for h in exposures]
    frames = [_codes(rng, shape, n) for _ in exposures]
    log_e = rng.normal(-1, 1.5, shape).astype(np.float32)
    per_row = reconstruct.noise_rows(params)
    idx = reconstruct.channel_index(shape, pattern)
    fused, ref = LogMerge(shape, pattern), LogMerge(shape, pattern)
    y_full = float(white[0] - black[0])
    for k, (z, tab, h) in enumerate(zip(frames, tables, exposures)):
        last = k == len(frames) - 1
        fused.add_irls(z, tab, last, log_e.reshape(reconstruct._rows_cols(shape)), h * y_full, per_row, linear)
        w = references.irls_weights(reconstruct.lookup(tab.certainty.ravel(), n, z, pattern), log_e, h, y_full,
                                     [m[idx] for m in per_row], linear)
        ref.add(z, tab, last=last, weight=w)
    np.testing.assert_allclose(fused.num, ref.num, rtol=1e-5)
    np.testing.assert_allclose(fused.den, ref.den, rtol=1e-5)
    got, flag = fused.finish(linear)
    want, want_flag = ref.finish(linear)
    np.testing.assert_array_equal(flag, want_flag)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("variance", [False, True])
@pytest.mark.parametrize("per_sample", [False, True])
def test_a_dark_sample_takes_the_fallback_of_the_longest_frame_that_is_its_own(per_sample, variance):
    """Where no frame has weight (dark in every frame), the result is the longest frame's
    fallback, ``log(max(lin(z), lin(1/2)) / h)``, of the frames whose factor is at least
    1/2 there: a frame rejected as a ghost or not covering the pixel (factor < 1/2) does
    not set it, so a dark object in the reference does not take the brighter background
    of a rejected long frame.  Same with per-sample weights
    (resampled RAW, IRLS) and with the variance accumulator."""
    shape = (4, 6, 3)
    exposures = [0.01, 0.04, 0.16]
    tables = [exposure_tables(CRF("srgb").at_codes(256, 0.0, 255.0), "probabilistic", h, noise=[NoiseParams(4.0, 1.0, 0.0)],
                              prior_rate=1e4, exposures=tuple(exposures), with_variance=variance) for h in exposures]
    codes = [np.zeros(shape, np.uint8) for _ in exposures]  # dark in the short frames
    codes[2][:, [0, 1, 5]] = 40  # the long frame measures columns 0, 1 and 5
    factors = [np.ones(shape[:2], np.float32) for _ in exposures]
    factors[2][:, :3] = 0.0  # the long frame is rejected in columns 0-2 ...
    factors[2][:, 3] = 0.4  # ... mostly rejected in column 3, kept in 4 and 5
    acc = LogMerge(shape, variance=variance)
    for k, (z, tab, f) in enumerate(zip(codes, tables, factors)):
        if per_sample:
            w = reconstruct.lookup(tab.weight.ravel(), 256, z, np.zeros((1, 1), np.intp)) * f[..., None]
            acc.add(z, tab, last=k == 2, weight=w.astype(np.float32), factor=f)
        else:
            acc.add(z, tab, last=k == 2, factor=f)
    out, flag = acc.finish()
    lin = CRF("srgb").inverse(np.array([0.5 / 255.0, 40 / 255.0]), 0)
    assert np.all(flag[:, :5] == -1) and np.all(flag[:, 5] == 0)
    np.testing.assert_allclose(out[:, :4], np.log(lin[0] / 0.04), rtol=1e-5)  # the middle frame's half code
    np.testing.assert_allclose(out[:, 4], np.log(lin[0] / 0.16), rtol=1e-5)  # the long frame's, kept there
    np.testing.assert_allclose(out[:, 5], np.log(lin[1] / 0.16), rtol=1e-3)  # measured


@pytest.mark.parametrize("variance", [False, True])
@pytest.mark.parametrize("layout", ["rgb", "mosaic"])
def test_add_with_a_per_pixel_factor_equals_add_with_the_weights(layout, variance):
    """LogMerge.add(factor=f) (the table's weight times a per-pixel factor, shared by an
    image's channels, inside the accumulation) gives the sums, flags and variance of
    LogMerge.add(weight=w(z) sigma^-2 f, factor=f) built with NumPy (the factor then only
    says which frame's dark fallback a sample takes), with zero and partial factors, black
    and clipped codes (float rounding apart)."""
    rng = np.random.default_rng(5)
    exposures = [0.004, 0.02, 0.1]
    shape, n, pattern, black, white = _layout(layout)
    tables = [exposure_tables(CRF("linear").at_codes(n, black, white), "probabilistic", h, noise=[NoiseParams(4.0, 1.0, 0.0)],
                              prior_rate=1e4, exposures=tuple(exposures), with_variance=variance) for h in exposures]
    frames = [_codes(rng, shape, n) for _ in exposures]
    fused, ref = LogMerge(shape, pattern, variance=variance), LogMerge(shape, pattern, variance=variance)
    for k, (z, tab) in enumerate(zip(frames, tables)):
        f = rng.choice([0.0, 0.3, 1.0], size=shape[:2]).astype(np.float32)
        w = reconstruct.lookup(tab.weight.ravel(), n, z, pattern) * (f[..., None] if z.ndim == 3 else f)
        fused.add(z, tab, last=k == 2, factor=f)
        ref.add(z, tab, last=k == 2, weight=w, factor=f)
    np.testing.assert_allclose(fused.num, ref.num, rtol=1e-5, atol=1e-30)
    np.testing.assert_allclose(fused.den, ref.den, rtol=1e-5, atol=1e-30)
    got, flag = fused.finish()
    want, want_flag = ref.finish()
    np.testing.assert_array_equal(flag, want_flag)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    if variance:
        np.testing.assert_allclose(fused.variance, ref.variance, rtol=1e-5)


def _mixed_iso_bracket(seed, times, gains, alpha, pre, post, full=4095.0, shape=(128, 128), e_range=(2.0, 3e4)):
    """A linear bracket drawn in numpy: frame j of exposure time ``times[j]`` and gain
    ``gains[j]`` (ISO_j / ISO_first) reads ``y ~ N(mu, sigma_o2_j + sqrt(alpha_j) mu)``,
    ``mu = sqrt(alpha_j) t_j E``, with ``alpha_j = alpha g_j^2`` and ``sigma_o2_j = pre
    alpha_j + post`` (read noise before and after the gain), rounded and clipped to
    [0, full].  Returns (codes, h_j = t_j g_j, per-frame NoiseParams, truth in the merge's
    units: ``sqrt(alpha) E / full``)."""
    rng = np.random.default_rng(seed)
    e = np.exp(rng.uniform(*np.log(e_range), shape))  # electrons per unit exposure
    codes, params = [], []
    for t, g in zip(times, gains):
        a = alpha * g * g
        p = NoiseParams(sigma_o2=pre * a + post, alpha=a)
        mu = np.sqrt(a) * t * e
        y = mu + rng.standard_normal(shape) * np.sqrt(p.sigma_o2 + np.sqrt(a) * mu)
        codes.append(np.clip(np.rint(y), 0, full).astype(np.uint16))
        params.append(p)
    h = np.asarray(times, float) * np.asarray(gains, float)
    return codes, h, params, np.sqrt(alpha) * e / full


@pytest.mark.parametrize("irls", [0, 2])
@pytest.mark.parametrize("estimator", ["ml", "log"])
def test_per_frame_noise_shared_by_every_frame_equals_the_single_noise(irls, estimator):
    """merge_frames with frame_noise = the same noise for every frame gives exactly the
    single-noise result (tables, IRLS passes with their censored terms, variance)."""
    codes, h, params, _ = _mixed_iso_bracket(3, [1.0, 4.0, 16.0], [1, 1, 1], 0.25, 4.0, 30.0, shape=(40, 60))
    pattern = np.array([[0, 1], [1, 2]])
    noise = [params[0], NoiseParams(40.0, 0.3), NoiseParams(20.0, 0.2)]
    kw = dict(weighting="uniform" if estimator == "ml" else "triangle", variance="model", estimator=estimator,
              pattern=pattern, irls_iterations=irls, with_variance=True)
    one = merge_frames(codes, h, CRF("linear"), [0.0] * 3, [4095.0] * 3, noise=noise, **kw)
    per = merge_frames(codes, h, CRF("linear"), [0.0] * 3, [4095.0] * 3, frame_noise=[noise] * 3, **kw)
    for a, b in zip(one, per):
        np.testing.assert_array_equal(a, b)


def test_irls_takes_one_noise_rows_tuple_per_frame():
    codes, h, params, _ = _mixed_iso_bracket(4, [1.0, 4.0], [1, 1], 0.25, 4.0, 30.0, shape=(8, 8))
    tables = [exposure_tables(CRF("linear").at_codes(4096, [0.0], [4095.0]), "uniform", x, [params[0]], estimator="ml")
              for x in h]
    with pytest.raises(ValueError, match="one noise_rows tuple per frame"):
        reconstruct.reweight(codes.__getitem__, tables, None, np.zeros((8, 8), np.float32), h, [4095.0] * 2,
                         reconstruct.noise_rows([params[0]]), True, 1)


@pytest.mark.parametrize("irls", [0, 1])
def test_mixed_iso_bracket_merged_with_each_frames_noise_is_closer_to_the_optimum(irls):
    """A bracket whose second frame has 4x the gain (ISO): alpha_j = alpha g^2, sigma_o2_j =
    pre alpha_j + post.  The ML merge with each frame's own noise has a lower error than
    with the first frame's noise for all, and matches the inverse-variance optimum computed
    here from the true per-frame variances (seeded; tolerances stated below)."""
    times, gains = [1.0, 4.0, 16.0], [1.0, 4.0, 1.0]
    codes, h, params, truth = _mixed_iso_bracket(7, times, gains, alpha=0.25, pre=4.0, post=30.0, shape=(256, 256),
                                                 e_range=(20.0, 450.0))  # the longest frames reach 88 % of full
    kw = dict(weighting="uniform", variance="model", estimator="ml", irls_iterations=irls)
    per, flags, _ = merge_frames(codes, h, CRF("linear"), 0.0, 4095.0,
                                            frame_noise=[[p] for p in params], **kw)
    first, _, _ = merge_frames(codes, h, CRF("linear"), 0.0, 4095.0, noise=[params[0]], **kw)
    # the optimum: every unclipped frame's y / (h full), weighted by the inverse of its true
    # variance at the true mean (no frame clipped: the censored terms play no part)
    full = 4095.0
    num = den = 0.0
    unclipped = np.ones(truth.shape, bool)
    for z, x, p in zip(codes, h, params):
        mu = truth * x * full
        w = (x * full) ** 2 / (p.sigma_o2 + np.sqrt(p.alpha) * mu)
        num = num + w * z / (x * full)
        den = den + w
        unclipped &= z < full
    optimum = num / den
    ok = unclipped & (flags == 0)
    assert ok.mean() > 0.99

    def rms(est):
        return float(np.sqrt(np.mean((est[ok] / truth[ok] - 1) ** 2)))

    assert rms(per) < 0.9 * rms(first)  # the first frame's noise for all: > 10 % more error (seed 7: 21 %)
    assert rms(per) < 1.02 * rms(optimum)  # within 2 % of the optimum's error (seed 7: 0.3 %)


def test_neutral_bounds_give_a_bound_no_colour():
    """An image pixel with a channel clipped in every frame holds a lower bound: all its
    channels take the largest and the saturated flag (a clipped channel's frames measured
    none of the pixel's colour); a pixel measured in every channel, and a mosaic, are left
    as they are."""
    from hdrmerge_cli.core.reconstruct import FLAG_DARK, FLAG_OK, FLAG_SATURATED, neutral_bounds

    result = np.array([[[0.60, 0.88, 0.63], [0.60, 0.88, 0.63], [0.60, 0.88, 0.63], [0.1, 0.2, 0.3]]],
                      dtype=np.float32)
    flags = np.array([[[FLAG_SATURATED] * 3, [FLAG_OK, FLAG_SATURATED, FLAG_OK], [FLAG_DARK, FLAG_OK, FLAG_OK],
                       [FLAG_OK] * 3]], dtype=np.int8)
    assert neutral_bounds(result, flags) == 2
    np.testing.assert_array_equal(result[0, :2], np.float32([[0.88, 0.88, 0.88]] * 2))
    np.testing.assert_array_equal(flags[0, :2], FLAG_SATURATED)
    np.testing.assert_array_equal(result[0, 2:], np.float32([[0.60, 0.88, 0.63], [0.1, 0.2, 0.3]]))
    np.testing.assert_array_equal(flags[0, 2], [FLAG_DARK, FLAG_OK, FLAG_OK])
    mosaic = np.ones((2, 2), np.float32)
    assert neutral_bounds(mosaic, np.full((2, 2), FLAG_SATURATED, np.int8)) == 0


def test_a_sample_the_shortest_frame_does_not_cover_is_bounded_by_the_shortest_that_does():
    """A border strip the shortest frame does not cover (``factor`` 0 there, as after
    alignment) and the longer frames clip: its bound is the clipping level of the shortest
    frame that covers it, ``log(gamma^-1(z_max) / h_1)``, flagged saturated: a true lower
    bound.  (Not the uncovered frame's reading, which never saw the light there; nor a
    dark flag.)  Where the shortest frame covers, it still sets the class."""
    crf = CRF("gamma", 2.2)
    exposures = [0.01, 0.04, 0.16]
    tabs = [exposure_tables(crf.at_codes(256, np.zeros(1), np.full(1, 255.0)), "triangle", h) for h in exposures]
    # column 0: the shortest frame does not cover it (its codes there are filler: 0) and the others clip;
    # column 1: every frame covers it and clips
    codes = [np.array([[[0, 0, 0], [255, 255, 255]]], np.uint8), np.full((1, 2, 3), 255, np.uint8),
             np.full((1, 2, 3), 255, np.uint8)]
    cover = [np.array([[0.0, 1.0]], np.float32), np.ones((1, 2), np.float32), np.ones((1, 2), np.float32)]
    acc = LogMerge((1, 2, 3))
    for k, (z, t, f) in enumerate(zip(codes, tabs, cover)):
        acc.add(z, t, last=k == 2, factor=f)
    log_e, flag = acc.finish()
    assert np.all(flag == FLAG_SATURATED)
    np.testing.assert_allclose(log_e[0, 0], np.log(1.0 / exposures[1]), rtol=1e-6)
    np.testing.assert_allclose(log_e[0, 1], np.log(1.0 / exposures[0]), rtol=1e-6)
