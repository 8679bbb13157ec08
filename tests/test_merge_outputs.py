"""What merge hands on (issue 20): EXRs that state their colour space."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import frames_of
from hdrmerge_cli.core.colorspace import COLORSPACES, rec709_to
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


@pytest.mark.skipif(not shutil.which("oiiotool", path=str(Path(sys.executable).parent)), reason="no oiiotool")
def test_oiiotool_shows_the_colour_space(raw_by_space):
    _, out = raw_by_space
    tool = shutil.which("oiiotool", path=str(Path(sys.executable).parent))
    info = subprocess.run([tool, "--info", "-v", str(out / "acescg.exr")], capture_output=True, text=True).stdout
    assert 'colorInteropID: "lin_ap1_scene"' in info and "chromaticities: 0.713, 0.293" in info
