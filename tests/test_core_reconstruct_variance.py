"""The noise model's variance of each merged value (``merge --extra-channels variance``).

Unit tests check the streamed accumulators against an independent NumPy evaluation of
``Var = sum_j w_j^2 Var(x_j) / (sum_j w_j)^2``; Monte-Carlo tests simulate many brackets
of a known irradiance ramp with the project's sensor model (16)-(18)
(:mod:`hdrmerge_cli.core.sensor`), merge each and compare the predicted variance (its mean
over the repetitions) with the empirical variance of the merged values over the
repetitions, over the irradiances that some frame measures: its mean reading inside the
clipping-safe range (47) at k = 3 (3 noise sds from black and from full scale).

Tolerances: 3000 repetitions give each level's empirical variance a relative sd of
sqrt(2 / 2999) = 2.6 %; per 2-stop band (about 12 levels) the mean ratio predicted /
empirical must lie within 10 % of 1 (measured 0.99..1.07), each level within 20 %
(measured worst 14 %: at the dark end of the log estimator a frame's variance is
evaluated at its own noisy reading, ``E[v(y) / y^2] > v(mu) / mu^2``, +3 cv^2).
"""
import numpy as np
import pytest

from hdrmerge_cli.api import merge_arrays

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.noise import NoiseParams, clipping_safe_range_exact
from hdrmerge_cli.core.reconstruct import (
    FLAG_DARK, FLAG_OK, FLAG_SATURATED, UNMEASURED_RELATIVE_VARIANCE, LogMerge,
    estimate_variance_table, exposure_tables, lookup, noise_rows,
)
from hdrmerge_cli.core.sensor import SensorModel, expose, quantise_crf, quantise_raw
from benchmarks.core_merge import irls, merge_frames
from references import combined_variance, irls_weights

REPS, LEVELS = 3000, 96
TIMES = [1.0, 4.0, 16.0]
BAND_TOL, LEVEL_TOL = 0.10, 0.20


# ---------------------------------------------------------------- unit tests


def _direct(frames, tables, pattern, linear, scale):
    """Independent float64 evaluation of the weighted mean and its variance."""
    w = np.stack([lookup(t.weight, t.n_codes, z, pattern) for z, t in zip(frames, tables)]).astype(np.float64)
    x = np.stack([lookup(t.value, t.n_codes, z, pattern) for z, t in zip(frames, tables)]).astype(np.float64)
    q = np.stack([lookup(t.variance, t.n_codes, z, pattern) for z, t in zip(frames, tables)]).astype(np.float64)
    den = w.sum(0)
    mean = (w * x).sum(0) / np.where(den > 0, den, 1.0)
    var = combined_variance(w, q)
    var_by_hand = (w**2 * np.where(w > 0, q, 0)).sum(0) / np.where(den > 0, den, 1.0) ** 2
    np.testing.assert_allclose(var[den > 0], var_by_hand[den > 0], rtol=1e-12)
    if linear:
        return mean * scale, var * scale**2, den
    e = np.exp(mean) * scale
    return e, e * e * var, den  # the delta method: Var(E) = E^2 Var(log E)


@pytest.mark.parametrize("estimator", ["log", "ml"])
def test_streamed_variance_equals_direct_sum_w2_var(estimator):
    """A Bayer mosaic with per-row black levels and noise: LogMerge(variance=True) equals
    sum w^2 Var / (sum w)^2 computed directly (float32 sums: rtol 1e-4), in E * scale and
    in log E, and turning it on changes neither the result nor the flags."""
    rng = np.random.default_rng(5)
    pattern = np.array([[0, 1], [1, 2]])
    black, white = np.array([64.0, 60.0, 70.0]), np.full(3, 4095.0)
    noise = [NoiseParams(4.0, 0.25), NoiseParams(3.0, 0.2), NoiseParams(5.0, 0.3)]
    times = [0.5, 2.0, 8.0]
    weights = "uniform" if estimator == "ml" else "triangle"
    tables = [exposure_tables(CRF("linear").at_codes(4096, black, white), weights, h, noise, "model", estimator=estimator,
                              with_variance=True) for h in times]
    frames = [rng.integers(0, 4096, (24, 30)).astype(np.uint16) for _ in times]
    for z in frames:
        z[0, :4] = 4095  # saturated everywhere
        z[1, :4] = 10  # dark everywhere (below every black level)
    linear, scale = estimator == "ml", 3.0
    ref, ref_var, ref_den = _direct(frames, tables, pattern, linear, scale)
    for with_scale in (True, False):
        acc = LogMerge(frames[0].shape, pattern, variance=True)
        plain = LogMerge(frames[0].shape, pattern)
        for k, z in enumerate(frames):
            acc.add(z, tables[k], last=k == 2)
            plain.add(z, tables[k], last=k == 2)
        out, flag = acc.finish(linear, scale if with_scale else None)
        out0, flag0 = plain.finish(linear, scale if with_scale else None)
        np.testing.assert_array_equal(out, out0)
        np.testing.assert_array_equal(flag, flag0)
        var = acc.variance
        ok = flag == FLAG_OK
        assert flag[0, :4].tolist() == [FLAG_SATURATED] * 4 and flag[1, :4].tolist() == [FLAG_DARK] * 4
        assert np.all(np.isfinite(var)) and np.all(var > 0)
        if with_scale:
            np.testing.assert_allclose(out[ok], ref[ok], rtol=1e-5)
            np.testing.assert_allclose(var[ok], ref_var[ok], rtol=1e-4)
            # unmeasured: the bound's own size as its standard deviation
            np.testing.assert_allclose(var[~ok], UNMEASURED_RELATIVE_VARIANCE * out[~ok] ** 2, rtol=1e-6)
            if linear:  # inverse-variance weights: the inverse of the summed information, times scale^2
                np.testing.assert_allclose(var[ok], scale**2 / ref_den[ok], rtol=1e-4)
        else:  # log E and its variance Var(E) / E^2
            e = np.exp(out.astype(np.float64)) * scale
            np.testing.assert_allclose(var[ok], ref_var[ok] / e[ok] ** 2, rtol=1e-4)
            np.testing.assert_allclose(var[~ok], UNMEASURED_RELATIVE_VARIANCE)
        np.testing.assert_allclose(acc.den[ok], ref_den[ok], rtol=1e-5)


def test_per_sample_weights_use_w2_times_the_tables_variance():
    """Per-sample weights (deghosting, alignment) instead of the table's: still
    sum w^2 Var / (sum w)^2 with the table's per-code variance."""
    rng = np.random.default_rng(8)
    crf = CRF("gamma", 2.2)
    noise = [NoiseParams(0.02, 0.004)]
    times = [0.01, 0.04, 0.16]
    tables = [exposure_tables(crf.at_codes(256, [0.0], [255.0]), "triangle", h, noise, "model", with_variance=True)
              for h in times]
    frames = [rng.integers(1, 255, (16, 20, 3)).astype(np.uint8) for _ in times]
    acc = LogMerge(frames[0].shape, None, variance=True)
    ws, qs, xs = [], [], []
    for k, (z, t) in enumerate(zip(frames, tables)):
        w = lookup(t.weight, 256, z, None) * rng.uniform(0.0, 1.0, z.shape).astype(np.float32)
        acc.add(z, t, last=k == 2, weight=w)
        ws.append(w)
        qs.append(lookup(t.variance, 256, z, None))
        xs.append(lookup(t.value, 256, z, None))
    out, flag = acc.finish(False, 1.0)
    w = np.array(ws, np.float64)
    e = np.exp((w * np.array(xs)).sum(0) / w.sum(0))
    np.testing.assert_allclose(out, e, rtol=1e-5)
    np.testing.assert_allclose(acc.variance, e * e * combined_variance(w, qs), rtol=1e-4)


@pytest.mark.filterwarnings("ignore:divide by zero")  # the reference formulas at y = 0 (compared where y > 0)
def test_variance_table_is_the_noise_model():
    """Per code: log y's variance v(y) / y^2 (21) and ML's v(y) / (h y_full)^2 with
    v = sigma_o^2 + sqrt(alpha) y; a non-linear response adds its quantisation
    (dy/dz)^2 / 12 (and the tolerance); without noise only the quantisation remains."""
    p = NoiseParams(4.0, 0.25)
    y = np.arange(4096.0) - 96.0
    v = 4.0 + 0.5 * y
    lg = estimate_variance_table(CRF("linear").at_codes(4096, [96.0], [4095.0]), 2.0, [p], "log")
    ml = estimate_variance_table(CRF("linear").at_codes(4096, [96.0], [4095.0]), 2.0, [p], "ml")
    pos = y > 0
    np.testing.assert_allclose(lg[pos], (v / y**2)[pos], rtol=1e-6)
    np.testing.assert_allclose(ml[pos], (v / (2.0 * 3999.0) ** 2)[pos], rtol=1e-6)
    assert np.all(np.isfinite(lg)) and np.all(np.isfinite(ml))
    crf = CRF("gamma", 2.2)
    z = np.arange(256.0)
    lin = (z / 255) ** 2.2
    q = np.gradient(lin * 255) ** 2 / 12
    tab = estimate_variance_table(crf.at_codes(256, [0.0], [255.0]), 1.0, [p], "log", tolerance=0.0)
    yy = lin * 255
    np.testing.assert_allclose(tab[1:], ((4.0 + 0.5 * yy + q) / yy**2)[1:], rtol=1e-5)
    tab = estimate_variance_table(crf.at_codes(256, [0.0], [255.0]), 1.0, None, "log", tolerance=0.01)
    np.testing.assert_allclose(tab[1:], (q / yy**2 + 1e-4)[1:], rtol=1e-5)


@pytest.mark.parametrize("linear", [True, False])
def test_irls_variance_is_certainty_weighted_information(linear):
    """One IRLS pass: sum_j w(z_j) w_j / (sum_j w_j)^2 with w_j = irls_weights at the
    previous estimate, independently evaluated; with uniform certainty (ML) 1 / sum w_j,
    a clipped reading's censored information included in the sum."""
    rng = np.random.default_rng(2)
    full = 4095.0
    p = NoiseParams(4.0, 0.25)
    times = [1.0, 4.0]
    weights = "uniform" if linear else "triangle"
    tables = [exposure_tables(CRF("linear").at_codes(4096, [0.0], [full]), weights, h, [p], "model",
                              estimator="ml" if linear else "log") for h in times]
    e = np.geomspace(20.0, 5000.0, 600).reshape(20, 30)  # the long frame clips above ~1000
    frames = [np.clip(np.rint(e * t * 0.5 + rng.normal(0, np.sqrt(4 + 0.25 * e * t), e.shape)), 0, full)
              .astype(np.uint16) for t in times]
    log0, _, _ = merge_frames(frames, times, CRF("linear"), 0.0, full, weights, [p], "model",
                              "ml" if linear else "log")
    log0 = np.log(log0)
    out = irls(frames.__getitem__, tables, None, log0.copy(), times, [full] * 2, [noise_rows([p])] * 2, linear, 1,
               tol=0.0, variance=True)
    log_e, flags, den, var = out.result, out.flags, out.den, out.variance
    maps = [m[0] for m in noise_rows([p])]
    cert = [lookup(t.certainty, t.n_codes, z, None).astype(np.float64) for z, t in zip(frames, tables)]
    w = [irls_weights(c, log0, h, full, maps, linear).astype(np.float64) for c, h in zip(cert, times)]
    num = sum(c * wj for c, wj in zip(cert, w))
    den_ref = sum(w)
    ok = flags == FLAG_OK
    clipped = (frames[1] >= full) & ok
    assert clipped.any() and (ok & ~clipped).any()
    free = ok & ~clipped  # no censored term: the certainty-weighted information alone
    ref = num / den_ref**2
    if linear:  # back from Var(E) to Var(log E)
        ref = ref / np.exp(2.0 * log_e.astype(np.float64))
        np.testing.assert_allclose(var[free], ref[free], rtol=2e-4)
        # with a censored term: 1 / (summed information including the censored one), as Var(log E)
        np.testing.assert_allclose(var[clipped], 1.0 / den[clipped] / np.exp(2.0 * log_e[clipped]), rtol=2e-4)
        # the censored information was added (~0 for readings far above full scale)
        assert np.all(den[clipped] >= den_ref[clipped] * (1 - 1e-5)) and np.any(den[clipped] > 1.5 * den_ref[clipped])
    else:
        np.testing.assert_allclose(var[ok], ref[ok], rtol=2e-4)
    np.testing.assert_allclose(var[~ok], UNMEASURED_RELATIVE_VARIANCE)


# ---------------------------------------------------------------- Monte Carlo


def _ramp(sensor: SensorModel, noise_12bit: NoiseParams):
    """LEVELS irradiances (electrons / s) from a third of the darkest to three times the
    brightest that a frame of TIMES measures, and which levels some frame measures: its
    mean reading within the clipping-safe range (47), k = 3."""
    lo, hi = clipping_safe_range_exact(noise_12bit, 0.5, sensor.full_scale, 3.0)
    g = np.sqrt(sensor.alpha)
    e = np.geomspace(lo / g / TIMES[-1] / 3, hi / g / TIMES[0] * 3, LEVELS)
    measured = np.any([(g * t * e >= lo) & (g * t * e <= hi) for t in TIMES], axis=0)
    return e, measured


def _compare(e, measured, out, flag, var):
    """Per level: the mean predicted variance over the repetitions / their empirical
    variance; returns ``(per-level ratios, [(band low E, high E, mean ratio)])``."""
    m = np.flatnonzero(measured)
    ok = flag[:, m] == FLAG_OK  # a dark-end sample read black in every frame is rare
    assert ok.mean() > 0.999
    emp = np.array([np.var(out[ok[:, i], j].astype(np.float64), ddof=1) for i, j in enumerate(m)])
    pred = np.array([np.mean(var[ok[:, i], j].astype(np.float64)) for i, j in enumerate(m)])
    ratio = pred / emp
    stops = np.log2(e[m] / e[m[0]])
    bands = [(e[m][sel][0], e[m][sel][-1], float(ratio[sel].mean()))
             for a in np.arange(0, stops[-1] + 1e-9, 2.0) if (sel := (stops >= a) & (stops < a + 2)).any()]
    return ratio, bands


def _check(ratio, bands):
    for lo, hi, r in bands:
        assert abs(r - 1) < BAND_TOL, f"E {lo:.3g}..{hi:.3g}: predicted / empirical variance {r:.3f}"
    assert np.max(np.abs(ratio - 1)) < LEVEL_TOL, ratio


RAW_SENSOR = SensorModel(alpha=0.25, sigma_o2=4.0, beta=0.0, bits=12, black=256)


@pytest.fixture(scope="module")
def raw_bracket():
    """3000 simulated 12-bit RAW-like brackets (linear codes above a black level of 256)
    of a 96-level irradiance ramp, one bracket per row; beta = 0 (a fixed-pattern gain
    would be shared by the frames of a pixel, which the variance model (17) treats as
    independent)."""
    rng = np.random.default_rng(20)
    p = NoiseParams(RAW_SENSOR.sigma_o2_total, RAW_SENSOR.alpha)
    e, measured = _ramp(RAW_SENSOR, p)
    grid = np.broadcast_to(e, (REPS, LEVELS))
    frames = [quantise_raw(expose(grid, t, RAW_SENSOR, rng, np.zeros(grid.shape)), RAW_SENSOR) for t in TIMES]
    return e, measured, frames, p


@pytest.mark.parametrize("case", ["log-triangle", "log-triangle-irls1", "ml-uniform", "ml-uniform-irls1"])
def test_variance_agrees_with_monte_carlo_raw(raw_bracket, case):
    """12-bit linear codes: the log estimator (7) with triangle weights, the ML estimator
    with uniform certainty, each alone and plus one IRLS pass (ML + IRLS: the RAW default)."""
    e, measured, frames, p = raw_bracket
    estimator, weights = ("log", "triangle") if case.startswith("log") else ("ml", "uniform")
    out, flag, _, var = merge_frames(frames, TIMES, CRF("linear"), float(RAW_SENSOR.black), float(RAW_SENSOR.white),
                                     weights, [p], "model", estimator, scale=0.5,
                                     irls_iterations=1 if case.endswith("irls1") else 0, with_variance=True)
    assert np.all(np.isfinite(var)) and np.all(var > 0)
    _check(*_compare(e, measured, out, flag, var))


def test_variance_agrees_with_monte_carlo_8bit_crf():
    """8-bit codes through a gamma-2.2 response (a 12-bit ADC, then the CRF, then 8-bit
    quantisation): the log estimator with triangle weights; the noise model in the 8-bit
    image's linear units (y scaled by 255 / 4095), plus the quantisation through the
    response.  The model tolerance of real cameras' responses (1 %) is set to 0: the
    simulator's response is exact (with it the prediction exceeds the empirical variance
    by up to 1.6x in the highlights, where the tolerance dominates)."""
    sensor = SensorModel(alpha=0.25, sigma_o2=4.0, beta=0.0, bits=12, black=0)
    crf = CRF("gamma", 2.2)
    s = 255.0 / sensor.full_scale
    p12 = NoiseParams(sensor.sigma_o2_total, sensor.alpha)
    p8 = NoiseParams(s * s * p12.sigma_o2, s * s * p12.alpha)
    rng = np.random.default_rng(21)
    e, measured = _ramp(sensor, p12)
    grid = np.broadcast_to(e, (REPS, LEVELS))
    frames = [quantise_crf(expose(grid, t, sensor, rng, np.zeros(grid.shape)), sensor, crf, 8) for t in TIMES]
    vt = [estimate_variance_table(crf.at_codes(256, [0.0], [255.0]), h, [p8], "log", tolerance=0.0) for h in TIMES]
    out, flag, _, var = merge_frames(frames, TIMES, crf, 0.0, 255.0, "triangle", [p8], "model", "log",
                                     with_variance=True, variance_tables=vt)
    _check(*_compare(e, measured, out, flag, var))


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
def test_demosaic_variance_is_the_squared_weights(pattern):
    """Away from the edges (2 pixels, where the kernels reflect), the variance of each
    demosaiced value equals sum_k (d out / d sample_k)^2 var_k, the derivatives taken by
    demosaicing impulses."""
    from hdrmerge_cli.core.cfa import demosaic_variance
    from references import demosaic

    rng = np.random.default_rng(5)
    var = rng.uniform(0.5, 2.0, (12, 14))
    exact = np.zeros(var.shape + (3,))
    for k in np.ndindex(var.shape):
        impulse = np.zeros(var.shape)
        impulse[k] = 1.0
        exact += demosaic(impulse, pattern).astype(np.float64) ** 2 * var[k]
    np.testing.assert_allclose(demosaic_variance(var, pattern)[2:-2, 2:-2], exact[2:-2, 2:-2], rtol=1e-5)


@pytest.mark.parametrize("colour", [(0.25, 1.0, 0.25), (2.0, 1.0, 0.5)])
def test_raw_rgb_variance_agrees_with_monte_carlo(colour):
    """The default RAW output (demosaiced RGB; merge_arrays: white balance 1, identity
    matrix) of a flat coloured field: per channel and CFA site, the predicted variance
    over the empirical variance across the field is within 10 % (measured 0.97-1.04; the
    former cell estimate, which left out the demosaic's weights, ranged 0.08-3.6)."""
    rng = np.random.default_rng(21)
    alpha, times, black, white, size = 0.5, [1.0, 4.0, 16.0], 64.0, 4095.0, 192
    cell = np.array([[colour[0], colour[1]], [colour[1], colour[2]]])
    electrons = 200.0 * np.tile(cell, (size // 2, size // 2)) / np.sqrt(alpha)
    codes = [np.clip(np.round(np.sqrt(alpha) * rng.poisson(electrons * t) + 2.0 * rng.standard_normal(electrons.shape)
                              + black), 0, white).astype(np.uint16) for t in times]
    m = merge_arrays(codes, times, cfa_pattern="RGGB", black=black, white=white, bits=12,
                                  extra_channels=("variance",), reference="1", noise="sigma_o2=4,alpha=0.5,beta=0")
    image, variance = m.image[8:-8, 8:-8], m.variance[8:-8, 8:-8]
    for c in range(3):
        for i, j in np.ndindex(2, 2):
            ratio = variance[i::2, j::2, c].mean() / image[i::2, j::2, c].var()
            assert 0.9 < ratio < 1.1, (c, i, j, ratio)
