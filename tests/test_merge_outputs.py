"""What merge hands on: EXRs that state their colour space."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import frames_of
from hdrmerge_cli.core.output_colorspace import COLORSPACES, rec709_to
from hdrmerge_cli.io.images import read_exr

NOISE = ["--noise", "sigma_o2=9,alpha=0.25,beta=0"]


@pytest.fixture(scope="module")
def raw_by_space(tmp_path_factory, run, dng_bracket):
    """The DNG bracket merged once per colour space."""
    folder, meta = dng_bracket
    out = tmp_path_factory.mktemp("cs")
    for name in COLORSPACES:
        run("merge", *frames_of(folder, meta), "-o", out / f"{name}.exr", "--colorspace", name, "-q", *NOISE)
    return {name: read_exr(out / f"{name}.exr") for name in COLORSPACES}, out


@pytest.mark.parametrize("name", [n for n in COLORSPACES if n != "camera"])
def test_colorspace_header_and_pixels(raw_by_space, name):
    """Each fixed space: colorInteropID and chromaticities of the registry, and the pixels
    are the Rec.709 merge through :func:`rec709_to` (float rounding)."""
    images, _ = raw_by_space
    pixels, attrs = images[name]
    assert attrs["colorInteropID"] == COLORSPACES[name].interop_id
    np.testing.assert_allclose(attrs["chromaticities"], COLORSPACES[name].chromaticities, atol=1e-6)
    base = images["rec709"][0]
    expected = base @ rec709_to(name).T
    np.testing.assert_allclose(pixels, expected, rtol=1e-4, atol=1e-5 * float(np.abs(base).max()))


def test_colorspace_camera_is_white_balanced_camera_rgb(raw_by_space):
    """``camera``: no interop ID (no standard space); the simulated camera's native RGB is
    Rec.709, so its pixels equal the Rec.709 merge's."""
    images, _ = raw_by_space
    pixels, attrs = images["camera"]
    assert "colorInteropID" not in attrs
    base = images["rec709"][0]
    np.testing.assert_allclose(pixels, base, rtol=1e-3, atol=1e-4 * float(np.abs(base).max()))


def test_colorspace_of_images_converts_from_srgb_primaries(tmp_path, run, jpeg_bracket):
    folder, meta = jpeg_bracket
    frames = frames_of(folder, meta)
    run("merge", *frames, "-o", tmp_path / "a.exr", "--crf", "srgb", "-q")
    run("merge", *frames, "-o", tmp_path / "b.exr", "--crf", "srgb", "--colorspace", "acescg", "-q")
    a, _ = read_exr(tmp_path / "a.exr")
    b, attrs = read_exr(tmp_path / "b.exr")
    assert attrs["colorInteropID"] == "lin_ap1_scene"
    np.testing.assert_allclose(b, a @ rec709_to("acescg").T, rtol=1e-4, atol=1e-6)


def test_colorspace_camera_of_images_warns_and_writes_rec709(tmp_path, run, jpeg_bracket):
    """Images carry no camera matrix: ``--colorspace camera`` says so once, in one line,
    and writes the Rec.709 merge (same pixels and tags)."""
    folder, meta = jpeg_bracket
    frames = frames_of(folder, meta)
    run("merge", *frames, "-o", tmp_path / "a.exr", "--crf", "srgb", "-q")
    proc = run("merge", *frames, "-o", tmp_path / "b.exr", "--crf", "srgb", "--colorspace", "camera")
    warned = [ln for ln in proc.stderr.splitlines() if "--colorspace camera" in ln]
    assert len(warned) == 1 and "no camera matrix" in warned[0] and "Rec.709" in warned[0], proc.stderr
    (a, attrs_a), (b, attrs_b) = read_exr(tmp_path / "a.exr"), read_exr(tmp_path / "b.exr")
    np.testing.assert_array_equal(a, b)
    assert attrs_b["colorInteropID"] == attrs_a["colorInteropID"] == "lin_rec709_scene"


@pytest.mark.skipif(not shutil.which("oiiotool", path=str(Path(sys.executable).parent)), reason="no oiiotool")
def test_oiiotool_shows_the_colour_space(raw_by_space):
    _, out = raw_by_space
    tool = shutil.which("oiiotool", path=str(Path(sys.executable).parent))
    info = subprocess.run([tool, "--info", "-v", str(out / "acescg.exr")], capture_output=True, text=True).stdout
    assert 'colorInteropID: "lin_ap1_scene"' in info and "chromaticities: 0.713, 0.293" in info


# ------------------------------------------------------------------ float DNG output
def _block_means(a: np.ndarray, f: int = 8) -> np.ndarray:
    h, w = a.shape[0] // f * f, a.shape[1] // f * f
    return a[:h, :w].reshape(h // f, f, w // f, f, -1).mean(axis=(1, 3))


@pytest.fixture(scope="module")
def merged_dng(tmp_path_factory, run, dng_bracket):
    folder, meta = dng_bracket
    out = tmp_path_factory.mktemp("dng")
    run("merge", *frames_of(folder, meta), "-o", out / "m.dng", "-q", *NOISE)
    run("merge", *frames_of(folder, meta), "-o", out / "e.exr", "-q", *NOISE)
    return out


def test_dng_output_opens_in_libraw_with_the_colours_of_the_exr(merged_dng):
    """rawpy (LibRaw) renders the merged float DNG with the as-shot white balance and the
    camera matrix; its colours match the EXR path's within 1 % (median over 8 x 8 blocks
    of well-exposed pixels; the two demosaics differ at edges: 90th percentile 5 %)."""
    import rawpy

    assert (merged_dng / "m.profile.json").exists()
    with rawpy.imread(str(merged_dng / "m.dng")) as raw:
        assert raw.raw_type == rawpy.RawType.Flat and raw.num_colors == 3
        rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True,
                              output_color=rawpy.ColorSpace.sRGB, user_flip=0).astype(np.float64)
    exr, _ = read_exr(merged_dng / "e.exr")
    a, b = _block_means(rgb), _block_means(exr.astype(np.float64))
    ok = (a > 0.002 * 65535) & (a < 0.9 * 65535) & (b > 0)
    scale = np.median(a[ok] / b[ok])  # LibRaw rescales the float data to its integer range
    rel = np.abs(a[ok] / scale / b[ok] - 1)
    assert ok.sum() > 500
    assert np.median(rel) < 0.01 and np.percentile(rel, 90) < 0.05


def test_dng_output_refused_for_images_and_extra_channels(tmp_path, run, jpeg_bracket, dng_bracket):
    folder, meta = jpeg_bracket
    proc = run("merge", *frames_of(folder, meta), "-o", tmp_path / "x.dng", "--crf", "srgb", check=False)
    assert proc.returncode == 1 and "not a Bayer RAW frame" in proc.stderr and "Traceback" not in proc.stderr
    folder, meta = dng_bracket
    proc = run("merge", *frames_of(folder, meta), "-o", tmp_path / "y.dng", "--extra-channels", "clipped", check=False)
    assert proc.returncode == 1 and "--extra-channels" in proc.stderr
    assert not list(tmp_path.iterdir())


def test_dng_output_warns_about_exr_only_options(tmp_path, run, dng_bracket):
    """--colorspace and --compression do not apply to a DNG: one warning line each, and
    the DNG is written as without them (32-bit floats, Deflate)."""
    folder, meta = dng_bracket
    proc = run("merge", *frames_of(folder, meta), "-o", tmp_path / "w.dng", "--colorspace", "acescg",
               "--compression", "zip", *NOISE)
    for option in ("--colorspace acescg", "--compression zip"):
        warned = [ln for ln in proc.stderr.splitlines() if option in ln]
        assert len(warned) == 1 and "does not apply" in warned[0] and "w.dng" in warned[0], proc.stderr
    import tifffile

    with tifffile.TiffFile(tmp_path / "w.dng") as tif:
        raw = tif.pages.first.pages[0]
        assert raw.compression == tifffile.COMPRESSION.ADOBE_DEFLATE and raw.dtype == np.float32


def _linear(path) -> np.ndarray:
    """A 16-bit sRGB TIFF rendering, decoded to linear RGB in [0, 1]."""
    import tifffile

    v = tifffile.imread(path)[..., :3].astype(np.float64) / 65535
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _agreement(render: np.ndarray, exr: np.ndarray) -> tuple[float, float, float, int]:
    """A raw editor's linear rendering against the EXR path (Rec.709 = sRGB primaries),
    per channel over 8 x 8 blocks where the rendering is between 1 % and 90 % of white
    (the editors crop a border: the EXR is centred on the rendering).  Returns (scale:
    the median rendering / EXR ratio, median and 90th percentile of |ratio / scale - 1|,
    blocks used)."""
    dy, dx = (exr.shape[0] - render.shape[0]) // 2, (exr.shape[1] - render.shape[1]) // 2
    a = _block_means(render)
    b = _block_means(exr[dy:dy + render.shape[0], dx:dx + render.shape[1]].astype(np.float64))
    ok = (a > 0.01) & (a < 0.9) & (b > 0)
    scale = float(np.median(a[ok] / b[ok]))
    rel = np.abs(a[ok] / scale / b[ok] - 1)
    return scale, float(np.median(rel)), float(np.percentile(rel, 90)), int(ok.sum())


def _baseline_ev(merged_dng) -> float:
    import tifffile

    with tifffile.TiffFile(merged_dng / "m.dng") as tif:
        num, den = tif.pages.first.tags["BaselineExposure"].value
    return num / den


@pytest.mark.skipif(shutil.which("darktable-cli") is None, reason="darktable-cli not installed (Debian: darktable)")
def test_darktable_renders_the_merged_dng(merged_dng, tmp_path):
    """darktable 4.2 (linear workflow 'none', 16-bit sRGB TIFF) renders the merged DNG with
    the EXR's colours: median difference < 1 %, 90th percentile < 5 % over 8 x 8 blocks
    (measured 0.3 %, 2.6 %).  It ignores BaselineExposure (README): the rendering is that
    many EV darker than the EXR (within 0.05 EV), and not black."""
    out, home = tmp_path / "d.tif", tmp_path / "home"
    home.mkdir()
    proc = subprocess.run(["darktable-cli", str(merged_dng / "m.dng"), str(out), "--core", "--configdir",
                           str(tmp_path / "dtconf"), "--conf", "plugins/darkroom/workflow=none",
                           "--conf", "plugins/imageio/format/tiff/bpp=16"], capture_output=True, text=True,
                          timeout=300, env={"HOME": str(home), "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0 and out.exists(), proc.stdout + proc.stderr
    render = _linear(out)
    scale, median, p90, n = _agreement(render, read_exr(merged_dng / "e.exr")[0])
    assert n > 300 and render.mean() > 0.01, "darktable rendered the image (nearly) black"
    assert abs(np.log2(scale) + _baseline_ev(merged_dng)) < 0.05, np.log2(scale)
    assert median < 0.01 and p90 < 0.05, (median, p90)


@pytest.mark.skipif(shutil.which("rawtherapee-cli") is None,
                    reason="rawtherapee-cli not installed (Debian: rawtherapee)")
def test_rawtherapee_renders_the_merged_dng(merged_dng, tmp_path):
    """RawTherapee 5.9 (its neutral default, 16-bit sRGB TIFF) renders the merged DNG of
    the 256 x 192 bracket (a raw of several tiles) at the EXR's brightness (it applies
    BaselineExposure: scale within 5 %) with its colours: median difference < 2 %, 90th
    percentile < 10 % over 8 x 8 blocks (its AMaZE demosaic differs from ours at the
    scene's many edges)."""
    out = tmp_path / "r.tif"
    proc = subprocess.run(["rawtherapee-cli", "-o", str(out), "-t", "-b16", "-Y", "-c", str(merged_dng / "m.dng")],
                          capture_output=True, text=True, timeout=300,
                          env={"HOME": str(tmp_path), "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0 and out.exists(), proc.stdout + proc.stderr
    render = _linear(out)
    scale, median, p90, n = _agreement(render, read_exr(merged_dng / "e.exr")[0])
    assert n > 300 and render.mean() > 0.05, "RawTherapee rendered the image (nearly) black"
    assert abs(scale - 1) < 0.05, scale
    assert median < 0.02 and p90 < 0.10, (median, p90)


def test_dng_closing_line_gives_the_baseline_exposure(merged_dng, run, dng_bracket, tmp_path):
    """The EV a darktable user adds (README) is printed, and is the DNG's BaselineExposure."""
    folder, meta = dng_bracket
    proc = run("merge", *frames_of(folder, meta), "-o", tmp_path / "m.dng", *NOISE)
    ev = _baseline_ev(merged_dng)
    assert ev > 5 and f"BaselineExposure is {ev:+.2f} EV" in proc.stderr and f"by {ev:.2f} EV" in proc.stderr


def test_bounds_at_a_moved_brackets_borders_carry_no_colour(tmp_path, run):
    """pi_ov5647_moved_jpg (frames moved up to 30 px, a bright neutral sky): along the
    borders only one frame covers, and where its green clipped the pixel is one neutral
    bound (neutral_bounds): the flagged pixels' median max/min channel is near 1, not the
    green cast of a clipped channel beside two measured ones (2.36 channel by channel)."""
    from conftest import SHARED

    folder = SHARED / "brackets" / "pi_ov5647_moved_jpg"
    if not folder.is_dir():
        pytest.skip(f"shared test data not found at {SHARED}")
    run("merge", *sorted(folder.glob("*.jpg")), "-o", tmp_path / "m.exr", "--extra-channels", "clipped", "--no-cache")
    pixels, header = read_exr(str(tmp_path / "m.exr"))
    flagged = pixels[..., 3] > 0  # saturated: a lower bound
    assert flagged.sum() > 1000
    rgb = pixels[..., :3][flagged]
    assert np.median(rgb.max(-1) / rgb.min(-1)) <= 1.15
