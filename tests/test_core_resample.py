"""Resampling onto the reference (core/resample.py): mosaics by CFA periods or colour by colour, the taps' spread and the resampled weights."""
import cv2
import numpy as np
import pytest

from hdrmerge_cli.core import registration, resample


def spread_value(code):
    """The spreads (squared codes, float32) that :func:`resample.spread_code` codes stand
    for: the table the merge's kernels read."""
    return resample._spread_table()[code]


def _bayer(rgb: np.ndarray, cfa: str) -> np.ndarray:
    out = np.empty(rgb.shape[:2], rgb.dtype)
    for k, colour in enumerate(cfa):
        out[k // 2::2, k % 2::2] = rgb[k // 2::2, k % 2::2, "RGB".index(colour)]
    return out


# ---------------------------------------------------------------- resampling variance
def _tap_variance_mosaic(codes: np.ndarray, warp: np.ndarray, cfa: str | None = None, black=0.0) -> np.ndarray:
    """The reference taps' spread of a resampled mosaic, frame-wide: ``tap_variance`` of
    each same-colour sub-plane on its own, and with ``cfa`` green's on the full-resolution
    green image (red and blue sites filled by the mean of their four greens) of the codes
    above ``black``."""

    out = np.empty(codes.shape, np.float32)
    for dy in (0, 1):
        for dx in (0, 1):
            if cfa is None or cfa[2 * dy + dx] != "G":
                sub = codes[dy::2, dx::2].astype(np.float32) - np.float32(np.ravel(black)[(2 * dy + dx) % np.size(black)])
                out[dy::2, dx::2] = resample.tap_variance(sub, resample._site_warp(warp, dx, dy))
    if cfa is not None:
        g = resample.tap_variance(resample._green_image(resample._above_black(codes, black), cfa), warp)
        for dy in (0, 1):
            for dx in (0, 1):
                if cfa[2 * dy + dx] == "G":
                    out[dy::2, dx::2] = g[dy::2, dx::2]
    return out


def _resampled_spread(codes: np.ndarray, warp: np.ndarray, cfa: str = "RGGB", black=0.0) -> np.ndarray:
    """The spread resample_mosaic keeps for the merge, decoded (squared codes)."""

    return spread_value(resample.resample_mosaic(codes, warp, 65535, cfa, black, spread=True)[1])


def _tap_weight_energy(warp: np.ndarray, h: int, w: int) -> np.ndarray:
    """The reference ``sum_i w_i^2`` of bilinear taps on each colour's sub-plane, written out
    with numpy: ``(fx^2 + (1 - fx)^2) (fy^2 + (1 - fy)^2)``, ``(fx, fy)`` a site's
    fractional position in its sub-plane under :func:`resample._site_warp`."""

    out = np.empty((h, w), np.float64)
    for dy in (0, 1):
        for dx in (0, 1):
            m = resample._site_warp(warp, dx, dy)
            v = np.arange(dy // 2, (h - dy + 1) // 2, dtype=np.float64)[:, None]  # sub-plane rows
            u = np.arange((w - dx + 1) // 2, dtype=np.float64)[None, :]
            fx = m[0, 0] * u + m[0, 1] * v + m[0, 2]
            fy = m[1, 0] * u + m[1, 1] * v + m[1, 2]
            fx -= np.floor(fx)
            fy -= np.floor(fy)
            out[dy::2, dx::2] = (fx * fx + (1 - fx) ** 2) * (fy * fy + (1 - fy) ** 2)
    return out


def test_mosaic_moves_by_whole_cfa_periods_and_clipping_survives_resampling():
    rng = np.random.default_rng(0)
    codes = rng.integers(0, 4000, (12, 16)).astype(np.uint16)
    w = np.array([[1.0, 0.0, 2.7], [0.0, 1.0, -1.2]])  # rounds to (+2, -2): whole periods
    out = resample.shift_mosaic(codes, w)
    np.testing.assert_array_equal(out[2:, :14], codes[:10, 2:])
    # sites from outside the frame repeat the nearest edge site of the same colour
    np.testing.assert_array_equal(out[:2, :14], codes[:2, 2:])
    np.testing.assert_array_equal(out[2:, 14:], codes[:10, 14:16])
    huge = resample.shift_mosaic(codes, np.array([[1.0, 0, 40.0], [0, 1.0, -30.0]]))
    assert huge.shape == codes.shape  # a shift beyond the frame is no crash
    img = np.full((8, 8), 100, np.uint16)
    img[4, 4] = 4095
    moved = resample.apply_warp(img, np.array([[1.0, 0, 0.5], [0, 1.0, 0.0]]), 4095)
    assert moved[4, 3] == 4095 and moved[4, 4] == 4095  # half-clipped neighbours read as clipped


@pytest.mark.parametrize("cfa", ["RGGB", "GBRG"])
def test_resample_mosaic_reads_green_on_its_quincunx_and_interpolates_colour_ratios(cfa):
    """resample_mosaic against the truth: an identity warp returns the codes; on a sharp,
    colourful scene (six random sinusoids up to 0.2 cycles/px, times a smooth colour field)
    rendered at the frame's and the reference's positions, a warp of (0.5, 0.3) px and
    0.3 deg recovers the reference's mosaic with at most 0.7x the RMS error of resampling
    each colour's sub-plane on its own; only the inside of a clipped highlight is clipped."""
    rng = np.random.default_rng(3)
    h, w, black, clip = 96, 128, 256.0, 4095
    codes = rng.integers(300, 3000, (h, w)).astype(np.uint16)
    same = resample.resample_mosaic(codes, np.array([[1.0, 0, 0], [0, 1.0, 0]]), clip, cfa, black)
    np.testing.assert_array_equal(same, codes)

    waves = [(rng.uniform(-0.2, 0.2, 2) * 2 * np.pi, rng.uniform(0, 2 * np.pi)) for _ in range(6)]
    tint = rng.uniform(0.6, 1.4, 3)

    def scene(x, y):  # (..., 3) linear values, 200..2800 codes above black
        lum = sum(np.cos(k[0] * x + k[1] * y + ph) for k, ph in waves) / 6
        colour = tint * (1 + 0.3 * np.sin(2 * np.pi * x[..., None] / 97 + np.array([0, 2, 4])))
        return 200 + 700 * (1 + lum[..., None]) * colour

    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    warp = np.array([[np.cos(0.005), -np.sin(0.005), 0.5], [np.sin(0.005), np.cos(0.005), 0.3]])
    # the frame sees at its pixel p what the reference sees at warp^-1(p): render the frame
    # on its own grid from the inverse map, the reference's truth on the reference grid
    inv = cv2.invertAffineTransform(warp)
    gx = inv[0, 0] * xx + inv[0, 1] * yy + inv[0, 2]
    gy = inv[1, 0] * xx + inv[1, 1] * yy + inv[1, 2]
    frame = np.rint(_bayer(scene(gx, gy), cfa) + black).astype(np.uint16)
    truth = _bayer(scene(xx, yy), cfa) + black
    new = resample.resample_mosaic(frame, warp, clip, cfa, black).astype(np.float64)
    old = np.empty_like(new)
    for dy in (0, 1):
        for dx in (0, 1):
            old[dy::2, dx::2] = resample.apply_warp(frame[dy::2, dx::2], resample._site_warp(warp, dx, dy), clip)
    inner = (slice(6, -6), slice(6, -6))
    err_new = np.sqrt(np.mean((new - truth)[inner] ** 2))
    err_old = np.sqrt(np.mean((old - truth)[inner] ** 2))
    assert err_new < 0.7 * err_old, (err_new, err_old)

    # a clipped highlight: the outputs inside it are clipped, its ring and the rest are not
    hl = frame.copy()
    hl[40:52, 60:72] = clip
    out = resample.resample_mosaic(hl, warp, clip, cfa, black)
    assert (out[43:49, 63:69] == clip).all()
    assert not (out[:, :56] == clip).any() and not (out[:36] == clip).any()


@pytest.mark.parametrize("cfa", ["RGGB", "GBRG"])
def test_resample_mosaic_reads_a_clipped_code_as_its_floor(cfa):
    """A clipped code bounds its sample from below, so resample_mosaic interpolates it at
    the clipping level.  A lamp (Gaussian, sigma 3 px, peak 4x the clipping level) on a dim
    wall, shifted by (0.5, 0.5) px: in its ring (outputs that are values, truth above twice
    the wall) the RMS relative error is at most 0.1 and none is more than 30 % too dark."""
    h, w, black, clip = 96, 128, 256.0, 4095
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)

    def scene(x, y):
        lamp = 4 * (clip - black) * np.exp(-((x - 64.3) ** 2 + (y - 47.6) ** 2) / (2 * 3.0 ** 2))
        return (300 + lamp)[..., None] * np.array([1.0, 0.8, 0.6])

    warp = np.array([[1.0, 0, 0.5], [0, 1.0, 0.5]])
    frame = np.minimum(np.rint(_bayer(scene(xx - 0.5, yy - 0.5), cfa) + black), clip).astype(np.uint16)
    truth = _bayer(scene(xx, yy), cfa) + black
    out = resample.resample_mosaic(frame, warp, clip, cfa, black).astype(np.float64)
    ring = (out < clip) & (truth > black + 600)
    assert ring.sum() > 100
    rel = (out - truth)[ring] / (truth[ring] - black)
    assert np.sqrt(np.mean(rel ** 2)) < 0.1 and rel.min() > -0.3, (np.sqrt(np.mean(rel ** 2)), rel.min())

def test_covered_mask_matches_a_pixelwise_test():
    h, w = 37, 53
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    for warp in (np.array([[1.0, 0.0, 2.7], [0.0, 1.0, -1.2]]), registration.compose(
            np.array([[np.cos(0.1), -np.sin(0.1), 3.0], [np.sin(0.1), np.cos(0.1), -4.0]]), np.eye(3)[:2]),
            np.array([[0.0, -1.0, 40.0], [1.0, 0.0, 0.0]])):
        sx, sy = warp[0, 0] * x + warp[0, 1] * y + warp[0, 2], warp[1, 0] * x + warp[1, 1] * y + warp[1, 2]
        brute = (sx >= -0.5) & (sx <= w - 0.5) & (sy >= -0.5) & (sy <= h - 0.5)
        np.testing.assert_array_equal(registration.covered_mask(warp, h, w), brute)


def test_resample_mosaic_spread_is_the_taps_spread():
    """resample_mosaic's spread (made band by band, kept as 16-bit codes) against the
    reference computed on the whole frame, on a rotated RGGB mosaic of textured codes above a
    black level: the median within the code's precision (2.2e-4), 99 % within 1e-3 (float32
    round-off of E z^2 - (E z)^2), all but 1 in 10^4 within 10 % (OpenCV places bilinear taps
    on a 1/32 px grid, which a band's warp and the whole frame's round apart at a few sharp
    samples: 1 of 210,000 here on OpenCV 5.1, a spread of 2.5 against 3 squared codes).  The
    spread's resampled codes are the plain resampling's."""
    from scipy import ndimage as ndi

    rng = np.random.default_rng(4)
    h, w = 700, 300  # several bands of BAND_ROWS
    codes = (512 + 3000 * np.abs(ndi.gaussian_filter(rng.normal(0, 1, (h, w)), 1.5))
             + rng.normal(0, 20, (h, w))).clip(0, 65535).astype(np.uint16)
    a = np.radians(1.1)
    warp = np.array([[np.cos(a), -np.sin(a), 2.3], [np.sin(a), np.cos(a), -5.6]])
    out, coded = resample.resample_mosaic(codes, warp, 65535, "RGGB", 512.0, spread=True)
    np.testing.assert_array_equal(out, resample.resample_mosaic(codes, warp, 65535, "RGGB", 512.0))
    got = spread_value(coded).astype(np.float64)
    want = _tap_variance_mosaic(codes, warp, "RGGB", 512.0).astype(np.float64)
    rel = np.abs(got - want) / (want + 1.0)
    assert np.median(rel) <= 2.2e-4 and np.quantile(rel, 0.99) <= 1e-3 and np.mean(rel > 0.1) <= 1e-4
    assert np.median(want) > 100  # texture: the comparison is not of zeros


def test_tap_variance_is_zero_on_the_grid_and_the_contrast_inside_an_edge():
    """The spread of the bilinear taps: nothing where the warp lands on samples or the
    image is flat, ``t (1 - t) (b - a)^2`` between two samples ``a``, ``b`` at fraction ``t``."""
    codes = np.zeros((20, 30), np.uint16)
    codes[:, 15:] = 1000
    whole = resample.tap_variance(codes, np.float64([[1, 0, 2], [0, 1, -1]]))
    assert np.all(whole == 0)
    quarter = resample.tap_variance(codes, np.float64([[1, 0, 0.25], [0, 1, 0]]))
    np.testing.assert_allclose(quarter[5, 14], 0.25 * 0.75 * 1000**2, rtol=1e-3)  # between columns 14 and 15
    assert np.all(quarter[:, :13] == 0) and np.all(quarter[:, 16:] == 0)
    # per colour on a mosaic: a flat colour plane has no spread whatever red does (green's
    # image fills the red sites from the greens)
    mosaic = np.full((20, 30), 500, np.uint16)
    mosaic[0::2, 0::2] = np.arange(15)[None, :] * 60
    v = _resampled_spread(mosaic, np.float64([[1, 0, 0.7], [0, 1, 0.3]]))
    assert np.all(v[1::2, 1::2] == 0) and np.all(v[0::2, 1::2] == 0) and np.all(v[1::2, 0::2] == 0)
    assert v[0::2, 0::2][2:-2, 2:-2].min() > 0


def test_resampled_weight_mosaic_equals_its_formula_per_colour():
    """The one-pass kernel against the formula written out with numpy on a rotated, shifted
    RGGB mosaic with a table row per colour: ``c / (e v + max(u - (1 - e) v, 0))`` with
    ``e`` from :func:`_tap_weight_energy`, ``u`` the spread through the row's slope
    (float32 round-off)."""

    rng = np.random.default_rng(3)
    h, w, n = 36, 50, 1024
    pattern = np.array([[0, 1], [1, 2]])
    slope = rng.uniform(1e-4, 1e-3, 3 * n).astype(np.float32)
    cert = rng.uniform(0.0, 1.0, 3 * n).astype(np.float32)
    cert[::7] = 0.0  # no weight: 0 out
    codes = rng.integers(0, n + 40, (h, w)).astype(np.uint16)  # beyond the table: its last entry
    wt = rng.uniform(1e3, 1e6, (h, w)).astype(np.float32)
    spread = rng.uniform(0.0, 400.0, (h, w)).astype(np.float32)
    a = np.radians(1.3)
    warp = np.array([[np.cos(a), -np.sin(a), 2.6], [np.sin(a), np.cos(a), -7.1]])
    row = np.tile(pattern, (h // 2, w // 2))
    i = row * n + np.minimum(codes, n - 1)
    e = _tap_weight_energy(warp, h, w)
    u = slope[i].astype(np.float64) ** 2 * spread_value(resample.spread_code(spread))  # as it is kept
    c = cert[i].astype(np.float64)
    den = e * c + np.maximum(wt * u - (1 - e) * c, 0.0)
    want = np.where(den > 0, wt * c / np.where(den > 0, den, 1.0), 0.0)
    got = resample.resampled_weight_mosaic(wt, codes, pattern, slope, cert, n, spread, warp)
    assert np.count_nonzero(got == 0) == np.count_nonzero(want == 0) > 0
    np.testing.assert_allclose(got, want, rtol=1e-5)
    same = wt.copy()  # in place
    resample.resampled_weight_mosaic(same, codes, pattern, slope, cert, n, spread, warp, out=same)
    np.testing.assert_array_equal(same, got)
    table = rng.uniform(1e3, 1e6, 3 * n).astype(np.float32)  # the weights read from a table
    np.testing.assert_array_equal(resample.resampled_weight_mosaic(None, codes, pattern, slope, cert, n, spread, warp,
                                                                weight=table),
                                  resample.resampled_weight_mosaic(table[i], codes, pattern, slope, cert, n, spread, warp))


def test_spread_code_round_trip():
    """A spread kept as a 16-bit code comes back within 2.2e-4 of ``u + SPREAD_FLOOR``
    (half a step of SPREAD_STEPS per octave) from far below a code's noise to a 16-bit
    range squared, 0 exactly, codes increasing with the spread; beyond, the last code."""

    u = np.exp(np.random.default_rng(0).uniform(np.log(1e-4), np.log(2.0**32), (200, 500))).astype(np.float32)
    u[0, :3] = 0.0, 0.0, 2.0**32
    code = resample.spread_code(u)
    assert code.dtype == np.uint16 and code.shape == u.shape
    back = spread_value(code).astype(np.float64)
    assert back[0, 0] == 0.0
    # half a step, 2^(1/3276) - 1 = 2.116e-4, and float32 round-off
    assert np.max(np.abs(back - u) / (u + resample.SPREAD_FLOOR)) <= 2.2e-4
    order = np.argsort(u.ravel())
    assert np.all(np.diff(code.ravel()[order].astype(np.int64)) >= 0)
    assert resample.spread_code(np.float32([[1e12]]))[0, 0] == 65535


def test_tap_weight_energy_against_monte_carlo():
    """Pure noise (sigma 10 codes) resampled colour by colour by bilinear interpolation
    (OpenCV's, as resample_mosaic reads red and blue) under a rotation and a shift: the
    interpolated values' variance is sigma^2 sum w^2 and the taps' spread (resample_mosaic's,
    at the red and blue sites) averages sigma^2 (1 - sum w^2), sum w^2 from
    _tap_weight_energy (both within 3 %)."""

    rng = np.random.default_rng(7)
    h, w, sigma = 400, 600, 10.0
    a = np.radians(0.7)
    warp = np.array([[np.cos(a), -np.sin(a), 3.3], [np.sin(a), np.cos(a), -1.7]])
    e = _tap_weight_energy(warp, h, w)
    assert e.min() >= 0.25 - 1e-6 and e.max() <= 1.0 + 1e-6
    inner = np.zeros((h, w), bool)
    inner[20:-20, 20:-20] = True  # away from the replicated edges
    red_blue = np.zeros((h, w), bool)
    red_blue[0::2, 0::2] = red_blue[1::2, 1::2] = True  # RGGB
    var_i, spreads = [], []
    for _ in range(20):
        codes = (1000.0 + rng.normal(0.0, sigma, (h, w))).astype(np.float32)
        interp = np.empty_like(codes)
        for dy in (0, 1):
            for dx in (0, 1):
                m = resample._site_warp(warp, dx, dy).astype(np.float32)
                sub = np.ascontiguousarray(codes[dy::2, dx::2])
                interp[dy::2, dx::2] = cv2.warpAffine(sub, m, sub.shape[::-1], flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                                      borderMode=cv2.BORDER_REPLICATE)
        var_i.append(((interp - 1000.0) ** 2)[inner])
        spreads.append(_resampled_spread(np.rint(codes).astype(np.uint16), warp)[inner & red_blue])
    assert np.mean(var_i) == pytest.approx(sigma**2 * np.mean(e[inner]), rel=0.03)
    # the codes' rounding adds 1/12 to sigma^2 = 100
    assert np.mean(spreads) == pytest.approx(sigma**2 * np.mean(1 - e[inner & red_blue]), rel=0.03)


def test_filled_green_noise_against_monte_carlo():
    """Pure noise (sigma 10 codes) on an RGGB mosaic, green resampled bilinearly from the
    filled full-resolution green image (taps 1 px apart; red and blue sites the mean of
    their four greens) under a rotation and a shift: the interpolated green's variance is
    sigma^2 e and the taps' spread (resample_mosaic's at the green sites) averages
    sigma^2 (s - e) (both within 3 %), with e and s written out here from the taps'
    covariance and recovered from resampled_weight_mosaic's weights (exactly)."""

    rng = np.random.default_rng(8)
    h, w, sigma = 400, 600, 10.0
    a = np.radians(0.7)
    warp = np.array([[np.cos(a), -np.sin(a), 3.3], [np.sin(a), np.cos(a), -1.7]])
    green = np.zeros((h, w), bool)
    green[0::2, 1::2] = green[1::2, 0::2] = True
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = warp[0, 0] * xx + warp[0, 1] * yy + warp[0, 2], warp[1, 0] * xx + warp[1, 1] * yy + warp[1, 2]
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    taps = [(0, 0), (1, 0), (0, 1), (1, 1)]  # (dx, dy) from the top-left tap
    wt = np.stack([(fx if dx else 1 - fx) * (fy if dy else 1 - fy) for dx, dy in taps], -1)
    tl_green = ((y0.astype(int) + x0.astype(int)) % 2) == 1  # RGGB: green where row + col is odd
    real = np.stack([tl_green == ((dx + dy) % 2 == 0) for dx, dy in taps], -1)  # which taps are greens
    cov = np.where(real[..., :, None] & real[..., None, :], np.eye(4), 0.0)  # real greens: independent
    fill = ~real
    cov = np.where(fill[..., :, None] & fill[..., None, :], np.where(np.eye(4, dtype=bool), 0.25, 0.125), cov)
    cov = np.where(real[..., :, None] ^ real[..., None, :], 0.25, cov)  # a filled tap holds both real ones
    e = np.einsum("...i,...ij,...j->...", wt, cov, wt)
    s_ = np.einsum("...i,...ii->...", wt, cov)
    # the kernel's: with no spread the weight is w / e; with spread u, 1 / (2 e + u - s)
    ones = np.ones((h, w), np.float32)
    codes = np.full((h, w), 100, np.uint16)
    table = np.ones(256, np.float32)
    got_e = 1.0 / resample.resampled_weight_mosaic(ones, codes, None, table, table, 256, np.zeros((h, w), np.float32),
                                                warp, cfa="RGGB")
    u = np.full((h, w), 10.0, np.float32)
    got_s = 2 * got_e + spread_value(resample.spread_code(u)) - 1.0 / resample.resampled_weight_mosaic(
        ones, codes, None, table, table, 256, u, warp, cfa="RGGB")
    np.testing.assert_allclose(got_e[green], e[green], rtol=1e-5)
    np.testing.assert_allclose(got_s[green], s_[green], rtol=1e-4)
    inner = green.copy()
    inner[:20], inner[-20:], inner[:, :20], inner[:, -20:] = False, False, False, False
    var_i, spreads = [], []
    for _ in range(20):
        mosaic = (1000.0 + rng.normal(0.0, sigma, (h, w))).astype(np.float32)
        full_g = resample._green_image(mosaic, "RGGB")
        interp = cv2.warpAffine(full_g, warp.astype(np.float32), (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_REPLICATE)
        var_i.append(((interp - 1000.0) ** 2)[inner])
        spreads.append(_resampled_spread(np.rint(mosaic).astype(np.uint16), warp)[inner])
    assert np.mean(var_i) == pytest.approx(sigma**2 * np.mean(e[inner]), rel=0.03)
    assert np.mean(spreads) == pytest.approx(sigma**2 * np.mean((s_ - e)[inner]), rel=0.03)


def test_inner_rectangle_lies_inside_the_pixels_every_warp_covers():
    """For translations the intersection of the covered masks is itself a rectangle, found
    whole; for rotations the rectangle lies inside the convex intersection and keeps most
    of it; ``even`` keeps a CFA's phase."""
    from hdrmerge_cli.core.registration import covered_mask
    from hdrmerge_cli.core.resample import inner_rectangle

    h, w = 120, 160
    shifts = [np.array([[1, 0, dx], [0, 1, dy]], float) for dx, dy in ((0, 0), (7.0, -3.0), (-4.0, 5.0))]
    every = np.logical_and.reduce([covered_mask(m, h, w) for m in shifts])
    r0, r1, c0, c1 = inner_rectangle(every)
    assert every[r0:r1, c0:c1].all() and (r1 - r0) * (c1 - c0) == every.sum()
    angle = np.radians(2.0)
    rot = np.array([[np.cos(angle), -np.sin(angle), 3.0], [np.sin(angle), np.cos(angle), -2.0]])
    every = covered_mask(rot, h, w) & covered_mask(np.eye(2, 3), h, w)
    r0, r1, c0, c1 = inner_rectangle(every, even=True)
    assert every[r0:r1, c0:c1].all() and (r1 - r0) * (c1 - c0) > 0.8 * every.sum()
    assert r0 % 2 == c0 % 2 == (r1 - r0) % 2 == (c1 - c0) % 2 == 0
    assert inner_rectangle(np.zeros((4, 4), bool)) is None
