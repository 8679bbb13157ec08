"""Alignment (core/align.py) and ghost rejection (core/deghost.py), and merge --align/--deghost."""
import json

import cv2
import numpy as np
import pytest

from conftest import SHARED, frames_of, needs_shared
from hdrmerge_cli.core import align, deghost
from hdrmerge_cli.core.scene import procedural_scene


def _two_exposures(shift, size=(256, 384)):
    """Luminance of the built-in scene at two exposures 3 stops apart, the second seeing
    the scene at x + shift (x right, y down); 8-bit through x^(1/2.2) with noise."""
    e = procedural_scene(size[0] + 32, size[1] + 32).mean(axis=-1)
    e = e / np.percentile(e, 99)
    rng = np.random.default_rng(1)
    out = []
    for t, (tx, ty) in ((0.1, (0.0, 0.0)), (0.8, shift)):
        m = np.float32([[1, 0, 16 + tx], [0, 1, 16 + ty]])
        img = cv2.warpAffine(e.astype(np.float32), m, size[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
        v = np.clip(np.maximum(img, 0) * t + rng.normal(0, 0.002, img.shape), 0, 1)
        out.append((np.rint(v ** (1 / 2.2) * 255) / 255) ** 2.2)
    return out, (0.1, 0.8)


def test_ecc_recovers_a_subpixel_shift_between_exposures():
    (a, b), times = _two_exposures((2.3, -1.6))
    lo, hi = align.common_range(times)
    w = align.estimate_warp(align.log_irradiance(a, times[0], lo, hi), align.log_irradiance(b, times[1], lo, hi))
    # the second frame sees the scene at x + shift: it is brought back by sampling it at x - shift
    np.testing.assert_allclose(w[:, 2], [-2.3, 1.6], atol=0.1)
    np.testing.assert_allclose(w[:, :2], np.eye(2))


def test_warp_algebra():
    a = np.array([[1.0, 0.1, 2.0], [0.0, 1.0, 3.0]])
    b = np.array([[0.9, 0.0, 1.0], [0.2, 1.1, -1.0]])
    full = np.vstack([a, [0, 0, 1]]) @ np.vstack([b, [0, 0, 1]])
    np.testing.assert_allclose(align.compose(a, b), full[:2])
    # a warp found on 2 x 2 blocks (block u centred at 2u + 0.5) moves full-resolution points the same way
    w = np.array([[0.99, -0.02, 1.5], [0.02, 0.99, -0.5]])
    full_w = align.rescale_warp(w, 2, 0.5)
    u = np.array([10.0, 7.0])
    np.testing.assert_allclose(full_w[:, :2] @ (2 * u + 0.5) + full_w[:, 2], 2 * (w[:, :2] @ u + w[:, 2]) + 0.5)
    win = align.shift_warp(w, (30, 40))
    np.testing.assert_allclose(align.shift_warp(win, (-30, -40)), w)


def test_mosaic_moves_by_whole_cfa_periods_and_clipping_survives_resampling():
    rng = np.random.default_rng(0)
    codes = rng.integers(0, 4000, (12, 16)).astype(np.uint16)
    w = np.array([[1.0, 0.0, 2.7], [0.0, 1.0, -1.2]])  # rounds to (+2, -2): whole periods
    out = align.apply_warp_mosaic(codes, w, 4095, "translation")
    np.testing.assert_array_equal(out[2:, :14], codes[:10, 2:])
    # sites from outside the frame repeat the nearest edge site of the same colour
    np.testing.assert_array_equal(out[:2, :14], codes[:2, 2:])
    np.testing.assert_array_equal(out[2:, 14:], codes[:10, 14:16])
    huge = align.apply_warp_mosaic(codes, np.array([[1.0, 0, 40.0], [0, 1.0, -30.0]]), 4095, "translation")
    assert huge.shape == codes.shape  # a shift beyond the frame is no crash
    img = np.full((8, 8), 100, np.uint16)
    img[4, 4] = 4095
    moved = align.apply_warp(img, np.array([[1.0, 0, 0.5], [0, 1.0, 0.0]]), 4095)
    assert moved[4, 3] == 4095 and moved[4, 4] == 4095  # half-clipped neighbours read as clipped


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
    saved = deghost.MODEL_TOLERANCE
    deghost.MODEL_TOLERANCE = 0.0
    try:
        bad = deghost.inconsistent_cells(x, s, ok, xa, s, ok, flat, (1, 3), p_fa=0.01)
        assert 0.007 < bad.mean() < 0.013
        x[100:150, 300:390] *= 1.5
        bad = deghost.inconsistent_cells(x, s, ok, xa, s, ok, flat, (1, 3), p_fa=0.001)
    finally:
        deghost.MODEL_TOLERANCE = saved
    cleaned = deghost.clean(bad)
    assert cleaned[100:150, 100:130].mean() > 0.95 and cleaned[:80].mean() == 0


def test_dark_reference_bounds_a_bright_reading():
    x = np.array([0.5, 0.001, 0.3])  # beyond the bounds by more than BOUND_FACTOR = 2: 0.5 > 0.02, 0.3 < 0.45
    s = np.full(3, 1e-6)
    bound = np.array([0.01, 0.01, -0.9])  # dark, dark (upper bound 0.01), clipped (lower bound 0.9)
    assert deghost.violates_bound(x, s, bound).tolist() == [True, False, True]


def test_static_bracket_is_neither_aligned_nor_deghosted(run, tmp_path, dng_bracket):
    folder, meta = dng_bracket
    s = json.loads(run("merge", *frames_of(folder, meta), "-o", tmp_path / "m.exr", "--align", "auto", "--deghost",
                       "auto", "--extra-channels", "ghost", "--json").stdout)
    assert s["alignment"]["applied"] is False and s["deghost"]["applied"] is False
    assert max(s["alignment"]["largest_displacement_px"]) < 0.25
    assert "ghost" in s["channels"]


@needs_shared
def test_handheld_bracket_is_aligned(run, tmp_path):
    paths = sorted((SHARED / "brackets" / "stack_handheld_jpg").glob("*.jpg"))
    s = json.loads(run("merge", *paths, "-o", tmp_path / "m.exr", "--align", "auto", "--json").stdout)
    assert s["alignment"]["applied"] and max(s["alignment"]["largest_displacement_px"]) > 5


@needs_shared
def test_moving_people_are_deghosted(run, tmp_path):
    paths = sorted((SHARED / "brackets" / "stack_ghost_jpg").glob("*.JPG"))
    s = json.loads(run("merge", *paths, "-o", tmp_path / "m.exr", "--deghost", "on", "--extra-channels", "ghost",
                       "--json").stdout)
    assert s["deghost"]["applied"] and 0.001 < max(s["deghost"]["rejected_fraction"]) < 0.2


def test_deghost_with_irls_is_refused(run, tmp_path, dng_bracket):
    folder, meta = dng_bracket
    proc = run("merge", *frames_of(folder, meta), "-o", tmp_path / "m.exr", "--deghost", "on", "--irls", "2",
               "--noise", "sigma_o2=4,alpha=1", check=False)
    assert proc.returncode == 1 and "--irls" in proc.stderr and not (tmp_path / "m.exr").exists()


@pytest.mark.parametrize("mode", ["translation", "similarity"])
def test_explicit_alignment_modes_run(run, tmp_path, jpeg_bracket, mode):
    folder, meta = jpeg_bracket
    s = json.loads(run("merge", *frames_of(folder, meta), "-o", tmp_path / "m.exr", "--crf", "srgb", "--align", mode,
                       "--json").stdout)
    assert s["alignment"]["motion"] == mode and max(s["alignment"]["largest_displacement_px"]) < 1.0


def test_samples_shifted_in_from_outside_get_no_weight():
    """An aligned frame covers the reference only partly: ``covered`` marks the rest (RAW:
    whole CFA periods; images: every channel of a pixel alike)."""
    from hdrmerge_cli.io.frames import Frame
    from hdrmerge_cli.pipeline.motion import covered

    def frame(kind, channels):
        return Frame(path="x", kind=kind, width=10, height=6, exposure_time=1.0, iso=None, aperture=None, make="",
                     model="", timestamp=None, bits=8, n_codes=256, black=np.zeros(channels),
                     white=np.full(channels, 255.0), channels=channels)

    w = np.array([[1.0, 0.0, 2.7], [0.0, 1.0, -1.2]])
    raw = covered(frame("raw", 4), w, "translation")  # moved by (+2, -2): the last 2 columns, first 2 rows
    assert raw.shape == (6, 10) and not raw[:2].any() and not raw[:, 8:].any() and raw[2:, :8].all()
    rgb = covered(frame("image", 3), w, "translation")  # x + 2.7 beyond 9.5 from x = 7
    assert rgb.shape == (6, 30) and not rgb[:, 21:].any() and rgb[3:, :21].all()
