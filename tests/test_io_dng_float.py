"""The floating-point DNG writer: read back through tifffile, LibRaw
(rawpy), darktable-cli and rawtherapee-cli (the last two skip when not installed)."""
from __future__ import annotations

import shutil
import subprocess
import numpy as np
import pytest

tifffile = pytest.importorskip("tifffile")
imagecodecs = pytest.importorskip("imagecodecs")
rawpy = pytest.importorskip("rawpy")

from hdrmerge_cli.core.errors import HdrMergeError  # noqa: E402
from hdrmerge_cli.io.dng_float import write_float_dng  # noqa: E402

#: a Canon-like XYZ (D65) -> camera matrix
CM = np.array([[0.6722, -0.0635, -0.0963], [-0.4287, 1.2460, 0.2028], [-0.0908, 0.2162, 0.5668]])
#: linear sRGB (D65) -> XYZ
SRGB_TO_XYZ = np.linalg.inv([[3.2404542, -1.5371385, -0.4985314], [-0.9692660, 1.8760108, 0.0415560],
                             [0.0556434, -0.2040259, 1.0572252]])
NEUTRAL = CM @ SRGB_TO_XYZ @ np.ones(3)  # camera RGB of D65 white
NEUTRAL = NEUTRAL / NEUTRAL[1]
#: sRGB-linear colour patches, left to right: grey, red, green, blue
PATCHES = [(0.18, 0.18, 0.18), (0.40, 0.05, 0.05), (0.05, 0.30, 0.05), (0.05, 0.05, 0.40)]


def patch_mosaic(height: int, width: int, pattern: str = "RGGB", seed: int = 0) -> np.ndarray:
    """A CFA mosaic of four vertical colour patches (camera RGB through CM), slight noise."""
    img = np.zeros((height, width, 3))
    for i, colour in enumerate(PATCHES):
        img[:, i * width // 4:(i + 1) * width // 4] = colour
    cam = img @ (CM @ SRGB_TO_XYZ).T / (CM @ SRGB_TO_XYZ @ np.ones(3)).max() * 0.9
    idx = {"R": 0, "G": 1, "B": 2}
    mosaic = np.zeros((height, width), np.float32)
    for i, c in enumerate(pattern):
        mosaic[i // 2::2, i % 2::2] = cam[i // 2::2, i % 2::2, idx[c]]
    rng = np.random.default_rng(seed)
    return (mosaic * (1 + 0.002 * rng.standard_normal(mosaic.shape))).astype(np.float32)


def write(path, mosaic, **kw):
    args = dict(cfa_pattern="RGGB", xyz_to_camera=CM, as_shot_neutral=NEUTRAL, make="Acme", model="HDR-1",
                exposure_time=1 / 60, iso=200, aperture=5.6, baseline_exposure=0.5,
                preview=np.full((24, 32, 3), 128, np.uint8))
    args.update(kw)
    write_float_dng(path, mosaic, **args)
    return path


def raw_page(tif):
    return tif.pages.first.pages[0]


def stored_values(path) -> np.ndarray:
    """The raw SubIFD's samples as float32."""
    with tifffile.TiffFile(path) as tif:
        return raw_page(tif).asarray().astype(np.float32)


@pytest.mark.parametrize("bits,rtol", [(32, 0.0), (16, 2.0 ** -11)])
def test_round_trip_values_and_tags(tmp_path, bits, rtol):
    mosaic = np.random.default_rng(7).uniform(1e-3, 0.95, (64, 96)).astype(np.float32)
    path = write(tmp_path / "out.dng", mosaic, bits=bits, datetime="2024:05:01 12:34:56")
    values = stored_values(path)
    assert values.shape == mosaic.shape
    np.testing.assert_allclose(values, mosaic, rtol=rtol, atol=0)
    with tifffile.TiffFile(path) as tif:
        ifd0, raw = tif.pages.first, raw_page(tif)
        assert ifd0.tags["NewSubfileType"].value == 1 and raw.tags["NewSubfileType"].value == 0
        assert bytes(ifd0.tags["DNGVersion"].value) == b"\x01\x04\x00\x00"
        assert raw.tags["SampleFormat"].value == 3 and raw.bitspersample == bits
        assert raw.compression == 8 and raw.predictor == 3
        assert raw.is_tiled and raw.tilelength <= 64 and raw.tilewidth <= 96
        assert ifd0.tags["UniqueCameraModel"].value == "Acme HDR-1"
        assert ifd0.tags["Software"].value.startswith("hdrmerge-cli")
        assert ifd0.tags["DateTime"].value == "2024:05:01 12:34:56"
    # LibRaw: pattern, levels, white balance, and the data (LibRaw hands floats over as
    # integers scaled to 0..16383 for white, truncating)
    with rawpy.imread(str(path)) as raw:
        pattern = "".join(raw.color_desc.decode()[i] for i in raw.raw_pattern.ravel())
        assert pattern == "RGGB"
        assert raw.black_level_per_channel == [0, 0, 0, 0]
        codes = raw.raw_image_visible.astype(np.float64)
        scale = raw.white_level  # white (1.0) -> 16383
        assert scale == 16383
        np.testing.assert_allclose(codes / scale, mosaic, atol=1 / scale + rtol)
        wb = np.asarray(raw.camera_whitebalance[:3])
        np.testing.assert_allclose(wb / wb[1], 1 / NEUTRAL, rtol=1e-5)
        assert raw.postprocess(use_camera_wb=True).shape == (64, 96, 3)


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_cfa_pattern(tmp_path, pattern):
    path = write(tmp_path / "p.dng", patch_mosaic(32, 48, pattern), cfa_pattern=pattern)
    with rawpy.imread(str(path)) as raw:
        assert "".join(raw.color_desc.decode()[i] for i in raw.raw_pattern.ravel()) == pattern


def test_colour_matrix_exif_and_white_level(tmp_path):
    path = write(tmp_path / "c.dng", patch_mosaic(64, 96) * 1000, white_level=1000, orientation=6,
                 datetime="2026:01:02 03:04:05")
    with tifffile.TiffFile(path) as tif:
        ifd0, raw = tif.pages.first, raw_page(tif)
        cm = np.asarray(ifd0.tags["ColorMatrix1"].value, float).reshape(9, 2)
        np.testing.assert_allclose((cm[:, 0] / cm[:, 1]).reshape(3, 3), CM, atol=1e-4)
        assert ifd0.tags["CalibrationIlluminant1"].value == 21
        neutral = np.asarray(ifd0.tags["AsShotNeutral"].value, float).reshape(3, 2)
        np.testing.assert_allclose(neutral[:, 0] / neutral[:, 1], NEUTRAL, rtol=1e-5)
        be = ifd0.tags["BaselineExposure"].value
        assert be[0] / be[1] == 0.5
        assert ifd0.tags["Orientation"].value == 6
        assert ifd0.tags["Make"].value == "Acme" and ifd0.tags["Model"].value == "HDR-1"
        exif = ifd0.tags["ExifTag"].value  # the shooting data stand in the EXIF IFD, not in IFD0
        assert not {"ExposureTime", "ISOSpeedRatings", "FNumber"} & {t.name for t in ifd0.tags.values()}
        assert tuple(exif["ExposureTime"]) == (1, 60)
        assert exif["ISOSpeedRatings"] == 200
        assert exif["FNumber"][0] / exif["FNumber"][1] == 5.6
        assert exif["DateTimeOriginal"] == "2026:01:02 03:04:05"
        assert raw.tags["WhiteLevel"].value == 1000 and raw.tags["BlackLevel"].value == 0
        assert bytes(raw.tags["CFAPattern"].value) == b"\x00\x01\x01\x02"
    with rawpy.imread(str(path)) as raw:
        assert raw.sizes.flip == 6  # LibRaw's code for EXIF orientation 6
        assert raw.other.shutter_speed == pytest.approx(1 / 60)
        assert raw.other.iso_speed == 200
        assert raw.other.aperture == pytest.approx(5.6)
        # LibRaw's rgb_cam (camera -> sRGB) is built from ColorMatrix1: white stays white
        rgb_cam = np.asarray(raw.color_matrix)[:, :3]
        np.testing.assert_allclose(rgb_cam.sum(axis=1), 1, atol=1e-3)
        expected = np.linalg.inv(CM @ SRGB_TO_XYZ)
        expected /= expected.sum(axis=1, keepdims=True)
        # rgb_cam acts on white-balanced camera RGB; compare on the balanced matrix
        balanced = np.linalg.inv(np.diag(1 / NEUTRAL) @ CM @ SRGB_TO_XYZ)
        np.testing.assert_allclose(rgb_cam, balanced / balanced.sum(axis=1, keepdims=True), atol=2e-3)


def test_embedded_preview_and_thumbnail(tmp_path):
    preview = np.zeros((120, 180, 3), np.uint8)
    preview[:, :90] = (200, 40, 40)
    preview[:, 90:] = (40, 40, 200)
    path = write(tmp_path / "pv.dng", patch_mosaic(64, 96), preview=preview)
    with tifffile.TiffFile(path) as tif:
        thumb = tif.pages.first.asarray()
        jpeg_page = tif.pages.first.pages[1]
        assert jpeg_page.tags["NewSubfileType"].value == 1 and jpeg_page.compression == 7
        decoded = jpeg_page.asarray()
    assert thumb.shape == (120, 180, 3)  # at most 256 px: kept as is
    assert decoded.shape == (120, 180, 3)
    assert np.abs(decoded.astype(int) - preview).mean() < 6
    with rawpy.imread(str(path)) as raw:
        thumb = raw.extract_thumb()
        assert thumb.format in (rawpy.ThumbFormat.JPEG, rawpy.ThumbFormat.BITMAP)


@pytest.mark.parametrize("bits", [16, 32])
@pytest.mark.parametrize("shape", [(192, 256), (256, 256), (128, 130), (130, 128), (640, 960)])
def test_raw_has_at_least_two_tiles(tmp_path, shape, bits):
    """RawTherapee renders a one-tile float DNG black: from 128 x 128 up, tiles never
    cover the whole image (multiples of 16, no larger than the image); LibRaw reads the
    data back."""
    mosaic = np.random.default_rng(2).uniform(1e-3, 0.95, shape).astype(np.float32)
    path = write(tmp_path / "t.dng", mosaic, bits=bits)
    with tifffile.TiffFile(path) as tif:
        raw = raw_page(tif)
        th, tw = raw.tilelength, raw.tilewidth
        assert raw.is_tiled and th % 16 == 0 and tw % 16 == 0 and th <= shape[0] and tw <= shape[1]
        assert len(raw.dataoffsets) == -(-shape[0] // th) * -(-shape[1] // tw) >= 2
    with rawpy.imread(str(path)) as raw:  # LibRaw: float data as integers, 1.0 -> 16383
        np.testing.assert_allclose(raw.raw_image_visible / raw.white_level, mosaic, atol=1 / 16383 + 2.0 ** -11)


def test_small_image_is_written_in_strips(tmp_path):
    mosaic = np.random.default_rng(1).random((10, 40)).astype(np.float32)
    path = write(tmp_path / "s.dng", mosaic)
    with tifffile.TiffFile(path) as tif:
        assert not raw_page(tif).is_tiled
    np.testing.assert_array_equal(stored_values(path), mosaic)  # (LibRaw refuses images under 22 pixels)


@pytest.mark.parametrize("kw,message", [
    (dict(bits=24), "16- or 32-bit"),
    (dict(cfa_pattern="RGBW"), "CFA pattern"),
    (dict(xyz_to_camera=np.zeros((3, 3))), "colour matrix"),
    (dict(as_shot_neutral=[1, 0, 1]), "as-shot neutral"),
    (dict(white_level=0.5), "white level"),
    (dict(orientation=9), "orientation"),
    (dict(preview=np.zeros((4, 4), np.uint8)), "preview"),
    (dict(datetime="yesterday"), "date"),
])
def test_invalid_arguments(tmp_path, kw, message):
    with pytest.raises(HdrMergeError, match=message):
        write(tmp_path / "x.dng", np.ones((32, 32), np.float32), **kw)
    assert not (tmp_path / "x.dng").exists()


def test_invalid_data_and_unwritable_path(tmp_path):
    bad = np.ones((32, 32), np.float32)
    bad[3, 3] = np.nan
    with pytest.raises(HdrMergeError, match="non-finite"):
        write(tmp_path / "x.dng", bad)
    with pytest.raises(HdrMergeError, match="16-bit"):
        write(tmp_path / "x.dng", np.full((32, 32), 70000, np.float32), bits=16, white_level=70000)
    with pytest.raises(HdrMergeError, match="cannot write"):
        write(tmp_path / "missing" / "x.dng", np.ones((32, 32), np.float32))


def render_colours(image: np.ndarray) -> list[np.ndarray]:
    """Mean colour of the middle of each of the four patches of a rendering."""
    h, w = image.shape[:2]
    return [image[h // 4:3 * h // 4, (4 * i + 1) * w // 16:(4 * i + 3) * w // 16].reshape(-1, 3).mean(0)
            for i in range(4)]


def check_colours(image: np.ndarray, program: str):
    grey, red, green, blue = render_colours(image.astype(float))
    assert grey.mean() > 20, f"{program} rendered the image black"
    assert np.ptp(grey) < 0.12 * grey.mean() + 4, f"{program}: grey patch is tinted {grey}"
    assert red[0] > 1.5 * max(red[1], red[2]), f"{program}: red patch {red}"
    assert green[1] > 1.2 * max(green[0], green[2]), f"{program}: green patch {green}"
    assert blue[2] > 1.5 * max(blue[0], blue[1]), f"{program}: blue patch {blue}"


def read_jpeg(path) -> np.ndarray:
    return imagecodecs.jpeg_decode(open(path, "rb").read())


def test_rawpy_renders_sensible_colours(tmp_path):
    path = write(tmp_path / "r.dng", patch_mosaic(128, 192))
    with rawpy.imread(str(path)) as raw:
        check_colours(raw.postprocess(use_camera_wb=True, no_auto_bright=True), "LibRaw")


@pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool not installed (Debian: libimage-exiftool-perl)")
@pytest.mark.parametrize("bits", [16, 32])
def test_exiftool_validates_the_dng_without_a_warning(tmp_path, bits):
    """``exiftool -validate``: shooting data in the EXIF IFD (not IFD0), SubIFDs of type
    LONG; no warning at all."""
    path = write(tmp_path / "v.dng", patch_mosaic(64, 96), bits=bits, datetime="2026:01:02 03:04:05")
    run = subprocess.run(["exiftool", "-validate", "-warning", "-a", str(path)], capture_output=True, text=True)
    assert run.stdout.split() == ["Validate", ":", "OK"], run.stdout


@pytest.mark.skipif(shutil.which("darktable-cli") is None, reason="darktable-cli not installed (Debian: darktable)")
@pytest.mark.parametrize("bits", [16, 32])
def test_darktable_renders(tmp_path, bits):
    path = write(tmp_path / "d.dng", patch_mosaic(128, 192), bits=bits)
    out = tmp_path / "d.jpg"
    home = tmp_path / "home"
    home.mkdir()
    run = subprocess.run(["darktable-cli", str(path), str(out), "--core", "--configdir", str(tmp_path / "dtconf")],
                         capture_output=True, text=True, timeout=300, env={"HOME": str(home), "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0 and out.exists(), run.stdout + run.stderr
    check_colours(read_jpeg(out), "darktable")


@pytest.mark.skipif(shutil.which("rawtherapee-cli") is None,
                    reason="rawtherapee-cli not installed (Debian: rawtherapee)")
def test_rawtherapee_renders(tmp_path):
    # RawTherapee 5.9 (Debian 12) reads float DNGs only when they are 32-bit and Deflate
    # compressed, and renders this size only from a tiled raw (io/dng_float.py)
    path = write(tmp_path / "rt.dng", patch_mosaic(192, 256))
    out = tmp_path / "rt.jpg"
    run = subprocess.run(["rawtherapee-cli", "-o", str(out), "-Y", "-c", str(path)], capture_output=True, text=True,
                         timeout=300, env={"HOME": str(tmp_path), "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0 and out.exists(), run.stdout + run.stderr
    check_colours(read_jpeg(out), "RawTherapee")


def test_cell_rgb_is_the_area_mean_of_whole_cells():
    """The DNG preview's picture (pipeline.output.cell_rgb) against a direct computation:
    per 2 x 2 cell R, mean of the greens, B; white balance; f x f blocks of cells averaged
    (f from block_factor, partial blocks dropped); the matrix.  Odd sizes and a GBRG layout."""
    from types import SimpleNamespace

    from hdrmerge_cli.core.preview import block_factor
    from hdrmerge_cli.pipeline.output import cell_rgb

    rng = np.random.default_rng(5)
    mosaic = rng.random((83, 121), dtype=np.float32) * 4
    frame = SimpleNamespace(cfa_pattern="GBRG", white_balance=np.array([1.8, 1.0, 1.4]))
    matrix = rng.random((3, 3))
    got = cell_rgb(mosaic, frame, matrix, 16)
    ch, cw = 83 // 2, 121 // 2
    f = block_factor(ch, cw, 16)
    cells = np.zeros((ch, cw, 3))
    for y in range(ch):
        for x in range(cw):
            cell = mosaic[2 * y:2 * y + 2, 2 * x:2 * x + 2].ravel()
            greens = [v for v, c in zip(cell, "GBRG") if c == "G"]
            cells[y, x] = [cell["GBRG".index("R")], np.mean(greens), cell["GBRG".index("B")]]
    cells *= frame.white_balance
    hb, wb = ch // f, cw // f
    want = cells[:hb * f, :wb * f].reshape(hb, f, wb, f, 3).mean(axis=(1, 3)) @ matrix.T
    assert got.shape == (hb, wb, 3) and max(hb, wb) <= 16
    np.testing.assert_allclose(got, want, rtol=1e-6)
