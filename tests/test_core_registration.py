"""Registration (core/registration.py): ECC and phase correlation, the tile consensus, warp algebra."""
import cv2
import numpy as np
import pytest

from hdrmerge_cli.core import registration
from hdrmerge_cli.core.scene import procedural_scene


def _two_exposures(shift, size=(256, 384)):
    """Luminance of the built-in scene at two exposures 3 stops apart, the second seeing
    the scene at x + shift (x right, y down); 8-bit through x^(1/2.2) with noise.  Each
    frame integrates its pixels: rendered at 4x, warped there and area-averaged (warping
    sharp edges at the frames' own resolution would blur one frame and not the other)."""
    e = procedural_scene(4 * (size[0] + 32), 4 * (size[1] + 32)).mean(axis=-1)
    e = e / np.percentile(e, 99)
    rng = np.random.default_rng(1)
    out = []
    for t, (tx, ty) in ((0.1, (0.0, 0.0)), (0.8, shift)):
        # full-resolution pixel u has its centre at 4 u + 1.5 on the 4x grid
        m = np.float32([[1, 0, 64 + 4 * tx], [0, 1, 64 + 4 * ty]])
        img = cv2.warpAffine(e.astype(np.float32), m, (4 * size[1], 4 * size[0]),
                             flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        img = img.reshape(size[0], 4, size[1], 4).mean(axis=(1, 3))
        v = np.clip(np.maximum(img, 0) * t + rng.normal(0, 0.002, img.shape), 0, 1)
        out.append((np.rint(v ** (1 / 2.2) * 255) / 255) ** 2.2)
    return out, (0.1, 0.8)


def _textured_pair(rotation, shift, size=(480, 640), seed=5, sigma=2.0):
    """A smooth random log-irradiance texture (Gaussian-filtered noise, ``sigma`` pixels) and
    the same seen through ``_rigid(rotation, *shift)`` (reference pixel x -> frame pixel),
    bicubic."""
    from scipy import ndimage as ndi

    rng = np.random.default_rng(seed)
    big = ndi.gaussian_filter(rng.normal(0, 1, (size[0] + 64, size[1] + 64)), sigma).astype(np.float32)
    big *= np.float32(0.2 / big.std())
    true = _rigid(rotation, *shift)
    inv = cv2.invertAffineTransform(true.astype(np.float32))
    inv[:, 2] += 32
    ib = cv2.warpAffine(big, inv, size[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    return np.ascontiguousarray(big[32:-32, 32:-32]), ib, true


def _rigid(deg, tx, ty):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, tx], [s, c, ty]])


def _sparse_ghosted_pair(seed):
    """A pair whose texture lies in the centre only (as a dark short frame's: too few
    consensus tiles register) moved by (3.3, -1.7) px, and the reference with a moving
    object there: a brighter copy of its own texture displaced by (3, 6) px."""
    ia, ib, true = _textured_pair(0.0, (3.3, -1.7), seed=seed)
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:ia.shape[0], 0:ia.shape[1]].astype(np.float32)

    def centre(dx, dy):  # the texture's envelope, in each image's own pixels
        return np.exp(-(((yy - 240 - dy) / 90.0) ** 2 + ((xx - 320 - dx) / 120.0) ** 2)).astype(np.float32)

    ia, ib = ia * centre(0.0, 0.0), ib * centre(-3.3, 1.7)
    ia += rng.normal(0, 0.01, ia.shape).astype(np.float32)
    ib += rng.normal(0, 0.01, ib.shape).astype(np.float32)
    ghosted = ia.copy()
    ghosted[200:300, 300:400] = np.float32(0.2) + ia[206:306, 303:403]
    return ia, ghosted, ib, true


def test_ecc_recovers_a_subpixel_shift_between_exposures():
    (a, b), times = _two_exposures((2.3, -1.6))
    lo, hi = registration.common_range(times)
    w, rho = registration.estimate_warp(registration.log_irradiance(a, times[0], lo, hi), registration.log_irradiance(b, times[1], lo, hi))
    # the second frame sees the scene at x + shift: it is brought back by sampling it at x - shift
    np.testing.assert_allclose(w[:, 2], [-2.3, 1.6], atol=0.15)  # 8-bit clip edges bias it ~0.1 px
    np.testing.assert_allclose(w[:, :2], np.eye(2))
    assert rho > 0.9


def test_euclidean_fit_matches_opencv_without_scale():
    """_euclidean_fit (2-D Procrustes) against OpenCV's similarity fit on exact rigid
    correspondences (scale 1), and it never scales noisy ones."""
    rng = np.random.default_rng(3)
    src = rng.uniform(0, 1000, (12, 2))
    true = _rigid(0.7, 3.2, -1.1)
    dst = src @ true[:, :2].T + true[:, 2]
    ocv, _ = cv2.estimateAffinePartial2D(src, dst, method=cv2.LMEDS)
    np.testing.assert_allclose(registration._euclidean_fit(src, dst), true, atol=1e-9)
    np.testing.assert_allclose(registration._euclidean_fit(src, dst), ocv, atol=1e-4)  # LMEDS refines to ~2e-5
    fit = registration._euclidean_fit(src, dst * 1.003 + rng.normal(0, 0.1, dst.shape))
    assert np.linalg.det(fit[:, :2]) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("motion, rotation", [("translation", 0.0), ("similarity", 0.4)])
def test_a_moving_object_does_not_bias_the_registration(motion, rotation):
    """A flat object in one frame only (6 % of the frame, hard edges) over a textured
    scene pulls whole-image ECC away even from the true warp (by more than a pixel); the
    full-resolution similarity step refuses the run (a jump or a run that does not settle), and the
    tile consensus (tiles registered on their own, a least-median fit) recovers the true
    warp within 0.1 px at every corner."""
    from scipy import ndimage as ndi

    size = (480, 640)
    rng = np.random.default_rng(5)
    big = ndi.gaussian_filter(rng.normal(0, 1, (size[0] + 64, size[1] + 64)), 2.0).astype(np.float32)
    big *= np.float32(0.2 / big.std())  # log-irradiance texture
    true = _rigid(rotation, 3.3, -2.7)  # reference pixel x -> frame pixel true @ x
    ia = np.ascontiguousarray(big[32:-32, 32:-32])
    inv = cv2.invertAffineTransform(true.astype(np.float32))
    inv[:, 2] += 32  # frame pixel y sees padded-scene pixel true^-1 y + 32
    ib = cv2.warpAffine(big, inv, size[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    ib[100:230, 150:300] = 1.5  # the moved object, brighter than the scene around it
    warp, _ = registration.estimate_warp(ia, ib, motion)
    assert registration.corner_distance(warp, true, *size) < 0.1, (warp, true)
    pulled = registration._ecc(ia, ib, true, motion)
    assert registration.corner_distance(pulled, true, *size) > 1.0  # 14.6 px (translation), 7.3 (similarity) on OpenCV 5.1
    if motion == "similarity":
        assert registration._fine_ecc(ia, ib, true, motion) is None


@pytest.mark.parametrize("seed", [0, 4, 5])
def test_a_non_rigid_scene_gets_no_rotation(seed):
    """A scene that no rigid motion describes (a smooth displacement field of +-1.5 px
    across the frame, like foliage in wind, on top of a (2, -1) px shift): the tiles
    register but disagree, so the similarity registration keeps no rotation.  The
    translation stays within the field's range."""
    from scipy import ndimage as ndi

    size = (480, 640)
    rng = np.random.default_rng(seed)
    ia = ndi.gaussian_filter(rng.normal(0, 1, size), 2.0).astype(np.float32)
    ia *= np.float32(0.2 / ia.std())
    coarse = rng.uniform(-1.5, 1.5, (2, 4, 5)).astype(np.float32)
    dx, dy = (cv2.resize(c, size[::-1], interpolation=cv2.INTER_CUBIC) for c in coarse)
    yy, xx = np.mgrid[0:size[0], 0:size[1]].astype(np.float32)
    ib = cv2.remap(ia, xx + dx + 2.0, yy + dy - 1.0, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    rotated = registration._pyramid_ecc(ia, ib, np.hstack([np.eye(2), [[-2.0], [1.0]]]), "similarity")
    assert registration._tile_consensus(ia, ib, rotated, "similarity") == (None, True)  # registered, disagreeing
    warp, _ = registration.estimate_warp(ia, ib, "similarity")
    np.testing.assert_array_equal(warp[:, :2], np.eye(2))
    assert -2.0 - 1.5 < warp[0, 2] < -2.0 + 1.5 and 1.0 - 1.5 < warp[1, 2] < 1.0 + 1.5


@pytest.mark.parametrize("shape", [(480, 640), (3000, 4000)])
def test_window_turn_is_the_chord_a_rotation_moves_the_window_corners(shape):
    """_window_turn against the chord 2 sin(theta / 2) r a rotation by theta moves a point at
    distance r from its centre, r the half-diagonal of the full-resolution window (the
    frame below FINE_SIDE, else FINE_SIDE square); a translation adds nothing."""
    theta = np.radians(0.4)
    hy, hx = ((min(registration.FINE_SIDE, n) - 1) / 2 for n in shape)
    expected = 2 * np.sin(theta / 2) * np.hypot(hx, hy)
    assert registration._window_turn(_rigid(0.4, 5.0, -3.0), _rigid(0.0, 1.0, 2.0), shape) == pytest.approx(expected, rel=1e-9)
    assert registration._window_turn(_rigid(0.0, 5.0, -3.0), _rigid(0.0, 1.0, 2.0), shape) == pytest.approx(0.0, abs=1e-12)


def test_consensus_tiles_of_a_large_soft_frame_count_as_textured():
    """The same scene at 9x the pixel count (2400 x 1800, the texture's scale 6 px instead
    of 2) has a third of the contrast per pixel.  The consensus tiles' texture is counted per
    1/1024 of the frame's width, as at the pyramid's coarse level, so the tiles still check
    the warp: within 0.02 px at every corner."""
    ia, ib, true = _textured_pair(0.0, (3.9, -2.1), size=(1800, 2400), sigma=6.0)
    warp, _ = registration.estimate_warp(ia, ib, "translation")
    assert registration.corner_distance(warp, true, *ia.shape) < 0.02, (warp, true)
    limit = registration.TEXTURE_LOG_GRAD / (max(ia.shape) / registration.COARSE_SIDE)
    tile = np.ascontiguousarray(ia[:256, :256])
    assert registration.texture(tile)[0] < registration.CONSENSUS_MIN_TEXTURED <= registration.texture(tile, limit)[0]


@pytest.mark.parametrize("rotation", [0.0, 0.6])
def test_a_turned_window_is_refined_as_a_rotation_first(monkeypatch, rotation):
    """Where the pyramid's rotation turns the full-resolution window's corners by more than
    FINE_SETTLED_PX (0.6 degrees: 4 px here), the rotation is refined first and no
    full-resolution translation ECC runs (it cannot fit a turned window: it wandered 0.6-1.8
    px per iteration on such a pair and was refused); without rotation it runs.  Either way
    the warp is within 0.1 px at every corner."""
    ia, ib, true = _textured_pair(rotation, (3.3, -2.7))
    runs = []
    fine = registration._fine_ecc
    monkeypatch.setattr(registration, "_fine_ecc", lambda r, i, w, motion: runs.append(motion) or fine(r, i, w, motion))
    warp, _ = registration.estimate_warp(ia, ib, "similarity")
    assert registration.corner_distance(warp, true, *ia.shape) < 0.1, (warp, true)
    assert ("translation" in runs) == (rotation == 0.0), runs


@pytest.mark.parametrize("per_iteration, counts, kept", [
    (3.0, [registration.FINE_CHECK - 1, 1], False),  # wanders (within its reach): refused at the check
    (0.0, [registration.FINE_CHECK - 1, 1], True),  # converged by the check: not restarted
    (0.05, [registration.FINE_CHECK - 1, 1, registration.FINE_ITERATIONS - registration.FINE_CHECK, 1], True),  # still refining
])
def test_a_full_resolution_similarity_run_is_judged_at_its_check(monkeypatch, per_iteration, counts, kept):
    """_fine_ecc's similarity run is looked at after FINE_CHECK iterations: an iteration there
    moving a window corner by more than FINE_WANDER_PX refuses it without the remaining
    iterations; by at most FINE_CONVERGED_PX, it is taken as converged; in between it runs on
    (and must then settle).  ECC stands in for a stub whose every iteration shifts the warp by
    ``per_iteration`` pixels, back and forth (so it never leaves the run's reach)."""
    seen = []

    def ecc(template, image, warp, motion, eps=1e-5, count=100):
        seen.append(count)
        out = warp.copy()
        out[0, 2] += per_iteration * (count % 2)  # back and forth: an even count returns
        return out

    monkeypatch.setattr(registration, "_ecc", ecc)
    img = np.zeros((480, 640), np.float32)
    found = registration._fine_ecc(img, img, _rigid(0.3, 1.0, 2.0), "similarity")
    assert seen == counts
    assert (found is not None) == kept


def test_warp_algebra():
    a = np.array([[1.0, 0.1, 2.0], [0.0, 1.0, 3.0]])
    b = np.array([[0.9, 0.0, 1.0], [0.2, 1.1, -1.0]])
    full = np.vstack([a, [0, 0, 1]]) @ np.vstack([b, [0, 0, 1]])
    np.testing.assert_allclose(registration.compose(a, b), full[:2])
    # a warp found on 2 x 2 blocks (block u centred at 2u + 0.5) moves full-resolution points the same way
    w = np.array([[0.99, -0.02, 1.5], [0.02, 0.99, -0.5]])
    full_w = registration.rescale_warp(w, 2, 0.5)
    u = np.array([10.0, 7.0])
    np.testing.assert_allclose(full_w[:, :2] @ (2 * u + 0.5) + full_w[:, 2], 2 * (w[:, :2] @ u + w[:, 2]) + 0.5)
    win = registration.shift_warp(w, (30, 40))
    np.testing.assert_allclose(registration.shift_warp(win, (-30, -40)), w)


def test_edges_all_one_way_are_not_registered():
    """Vertical bands fix no vertical shift (the aperture problem): ``registrable`` refuses
    them whatever their count of textured pixels, and accepts the same bands with a few
    horizontal edges."""
    rng = np.random.default_rng(2)
    bands = np.repeat(rng.uniform(-2, 0, 40), 16)[None].repeat(480, axis=0).astype(np.float32)
    textured, across = registration.texture(bands)
    assert textured > 5000 and across == 0
    assert "across" in registration.registrable(bands, bands)
    checks = bands + np.float32(0.5) * ((np.arange(480) // 40) % 2)[:, None].astype(np.float32)
    assert registration.registrable(checks, checks) is None


@pytest.mark.parametrize("side", [300, 1000, 1024, 1025, 3000, 6000])
def test_finest_level_is_the_pyramids_finest(side):
    """_finest_level (the unit of _fine_ecc's reach) is the finest of _pyramid_ecc's levels."""
    levels = [2**k for k in range(1, 16) if registration.PYRAMID_MIN <= side / 2**k <= registration.COARSE_SIDE]
    assert registration._finest_level((side // 2, side)) == min(levels)


def test_a_moving_object_in_a_sparsely_textured_reference_is_left_out():
    """Where too few consensus tiles register (texture in the centre only), a moving object
    in the reference pulls the full-resolution ECC off; the region it covers is found on the
    registered pair and left out of a last ECC run: the warp within 0.1 px, and nothing is
    left out where nothing moved."""
    calls = []
    original = registration._masked_fine_ecc

    def spy(*args):
        calls.append(original(*args))
        return calls[-1]

    for seed in (5, 6):
        static, ghosted, image, true = _sparse_ghosted_pair(seed)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(registration, "_masked_fine_ecc", spy)
            calls.clear()
            warp, _ = registration.estimate_warp(ghosted, image, "translation")
            assert len(calls) == 1 and calls[0] is not None
            assert registration.corner_distance(warp, true, *image.shape) < 0.1, (warp, true)
            calls.clear()
            warp, _ = registration.estimate_warp(static, image, "translation")
            assert calls == [None]  # no region moved: nothing left out, the warp as ECC found it
            assert registration.corner_distance(warp, true, *image.shape) < 0.1
            mp.setattr(registration, "_masked_fine_ecc", lambda *args: None)  # without the last run: pulled off
            warp, _ = registration.estimate_warp(ghosted, image, "translation")
            assert registration.corner_distance(warp, true, *image.shape) > 0.2


def test_moved_region_finds_a_moved_object_and_no_false_alarm_on_noise():
    """``_moved_region``: the displaced object's rectangle (grown by MOVED_GROW_PX) on a
    registered pair; on 20 static pairs of independent Gaussian noise (a 5 sigma robust
    threshold, regions of at least 0.1 % of the frame) none."""
    static, ghosted, _, _ = _sparse_ghosted_pair(5)
    region = registration._moved_region(ghosted, static)
    assert region is not None
    inside = region[200:300, 300:400] > 0
    assert inside.mean() > 0.5
    assert np.count_nonzero(region) < 2.0 * 110 * 110  # the object and its grown edge, not the frame
    rng = np.random.default_rng(11)
    for _ in range(20):
        a = static + rng.normal(0, 0.01, static.shape).astype(np.float32)
        assert registration._moved_region(a, static + rng.normal(0, 0.01, static.shape).astype(np.float32)) is None


def test_masked_ecc_that_runs_away_is_refused():
    """A last masked ECC run that moves the window's corners by more than MAX_REFINE_PX is
    refused.  OpenCV writes the warp it is given: judged against the start it was given
    (not that array, which by then holds the result, so nothing was ever refused)."""
    _, ghosted, image, true = _sparse_ghosted_pair(5)
    real = cv2.findTransformECCWithMask

    def runaway(template, img, tmask, imask, warp, *rest):
        warp[:, 2] += 10.0  # as OpenCV does: the argument becomes the result
        return 0.9, warp

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cv2, "findTransformECCWithMask", runaway)
        assert registration._masked_fine_ecc(ghosted, image, true, "translation") is None
    assert cv2.findTransformECCWithMask is real
    found = registration._masked_fine_ecc(ghosted, image, true, "translation")
    assert found is not None and registration.corner_distance(found, true, *image.shape) < 0.1


def _still_scene(rng, n=96):
    """A smooth random log-irradiance texture, ``(n, n)`` float64."""
    s = cv2.GaussianBlur(rng.standard_normal((n, n)), (0, 0), 2.0)
    return s / s.std() * 0.5


def _shifted(scene, dx):
    """``scene`` seen ``dx`` px further right (exactly: a Fourier phase ramp)."""
    kx = np.fft.fftfreq(scene.shape[1])[None, :]
    return np.real(np.fft.ifft2(np.fft.fft2(scene) * np.exp(2j * np.pi * kx * dx)))


def test_still_test_covariance_holds_on_noise():
    """On 200 seeded noise draws over a still scene, the linear step's estimate falls outside
    its 95 % confidence ellipse (translation and rotation) in 5 % of the draws, within the
    binomial spread (99.9 % bounds of 200 draws: 2 to 21)."""
    from scipy.stats import chi2

    rng = np.random.default_rng(7)
    scene = _still_scene(rng)
    limit = chi2.ppf(0.95, 3)
    outside = 0
    for _ in range(200):
        a = (scene + 0.05 * rng.standard_normal(scene.shape)).astype(np.float32)
        b = (scene + 0.05 * rng.standard_normal(scene.shape)).astype(np.float32)
        theta, cov = registration.linear_step(a, b)
        d = theta[:3]
        outside += float(d @ np.linalg.solve(cov[:3, :3], d)) > limit
    assert 2 <= outside <= 21


def test_still_test_declares_a_frame_displaced_by_the_tolerance_still_at_most_at_its_rate():
    """A frame displaced by exactly the tolerance, in noise that puts the undisplaced pair's
    bound near the tolerance, is declared still in at most p_miss = 5 % of 200 seeded draws
    (binomial 99.9 % bound: 21; the corner bound is conservative), while the same scene
    undisplaced is declared still in most."""
    rng = np.random.default_rng(11)
    scene = _still_scene(rng)
    moved = _shifted(scene, 0.25)
    still = {0.0: 0, 0.25: 0}
    for d, other in ((0.0, scene), (0.25, moved)):
        for _ in range(200):
            a = (scene + 0.2 * rng.standard_normal(scene.shape)).astype(np.float32)
            b = (other + 0.2 * rng.standard_normal(scene.shape)).astype(np.float32)
            still[d] += registration.still_test(a, b, 1, 96, 96, 0.25, p_miss=0.05)[0]
    assert still[0.25] <= 21 and still[0.0] >= 100


def test_still_test_sends_large_motion_to_the_full_registration():
    """Shifts of 0.5 to 5 px and a 1 degree turn are never still at a quarter-pixel tolerance."""
    rng = np.random.default_rng(3)
    scene = _still_scene(rng, 128).astype(np.float32)
    for dx in (0.5, 1.5, 5.0):
        assert not registration.still_test(scene, _shifted(scene, dx).astype(np.float32), 1, 128, 128, 0.25)[0]
    turn = cv2.getRotationMatrix2D((63.5, 63.5), 1.0, 1.0).astype(np.float32)
    turned = cv2.warpAffine(scene, turn, (128, 128), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    assert not registration.still_test(scene, turned, 1, 128, 128, 0.25)[0]


def test_displacement_margin_holds_a_still_pairs_registration_and_not_a_real_shift():
    """On 100 seeded noise draws over a still scene, the full registration's displacement
    exceeds the pair's margin (p_miss = 5 %) in at most 5 % of them (binomial 99.9 % bound of
    100 draws: 13); a real 1.5 px shift in the same noise is always beyond its margin.  The
    margin is in frame pixels: the same pair read as 2x block means of a frame twice the size
    gives twice the margin, within 25 %."""
    rng = np.random.default_rng(5)
    scene = _still_scene(rng, 128)
    moved = _shifted(scene, 1.5)
    beyond = {0.0: 0, 1.5: 0}
    margins = []
    for d, other in ((0.0, scene), (1.5, moved)):
        for _ in range(100):
            a = (scene + 0.3 * rng.standard_normal(scene.shape)).astype(np.float32)
            b = (other + 0.3 * rng.standard_normal(scene.shape)).astype(np.float32)
            warp, _ = registration.estimate_warp(a, b, "translation")
            margin = registration.displacement_margin(a, b, warp, 1, 128, 128, p_miss=0.05)
            margins.append(margin)
            beyond[d] += registration.warp_size(warp, 128, 128) > margin
    assert beyond[0.0] <= 13 and beyond[1.5] == 100
    a = (scene + 0.3 * rng.standard_normal(scene.shape)).astype(np.float32)
    b = (scene + 0.3 * rng.standard_normal(scene.shape)).astype(np.float32)
    identity = np.hstack([np.eye(2), np.zeros((2, 1))])
    one = registration.displacement_margin(a, b, identity, 1, 128, 128)
    two = registration.displacement_margin(a, b, identity, 2, 256, 256)
    assert two == pytest.approx(2 * one, rel=0.25)


def test_registration_images_against_direct_means():
    """A mosaic's registration image is the mean of each 2 x 2 cell, black-subtracted and
    scaled (numpy reshape, float64, to 1e-6); its coarse image the block mean of that (to
    half a code); an
    image's the channels' mean through the inverse response, for 8 and 16 bits."""
    from hdrmerge_cli.core.crf import CRF
    from hdrmerge_cli.core.registration import coarse_mosaic_image, registration_image

    rng = np.random.default_rng(5)
    mosaic = rng.integers(500, 16000, (96, 128)).astype(np.uint16)
    fine = registration_image(mosaic, CRF("linear"), True, 512.0, 16383.0, 65536)
    direct = (mosaic.astype(np.float64).reshape(48, 2, 64, 2).mean(axis=(1, 3)) - 512.0) / (16383.0 - 512.0)
    np.testing.assert_allclose(fine, direct, atol=1e-6)
    coarse = coarse_mosaic_image(mosaic, 512.0, 16383.0, 8)
    # its 2 x 2 cell means are taken in whole codes (OpenCV's area resize of uint16): half a code
    np.testing.assert_allclose(coarse, direct.reshape(12, 4, 16, 4).mean(axis=(1, 3)), atol=0.5 / (16383 - 512))
    crf = CRF("gamma", 2.2)
    for dtype, n in ((np.uint8, 256), (np.uint16, 65536)):
        image = rng.integers(0, n, (40, 60, 3)).astype(dtype)
        lin = registration_image(image, crf, False, 0.0, n - 1.0, n)
        np.testing.assert_allclose(lin, ((image / (n - 1.0)) ** 2.2).mean(axis=-1), atol=1e-5)
