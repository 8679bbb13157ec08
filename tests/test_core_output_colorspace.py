"""Output colour spaces (core/output_colorspace.py) against colour-science, OpenColorIO's published
matrices and OpenEXR's conventions; the attributes round-trip through an EXR."""
from __future__ import annotations

import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from hdrmerge_cli.core import output_colorspace as cs

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import colour

TOL = 1e-6
#: colour-science's colourspace for each of ours ("ITU-R BT.709", not "sRGB": colour's sRGB
#: carries the IEC 61966-2-1 matrix rounded to 4 decimals).
COLOUR_NAMES = {"rec709": "ITU-R BT.709", "acescg": "ACEScg", "aces2065-1": "ACES2065-1",
                "xyz": "lin_ciexyzd65_scene"}
FIXED = [n for n in cs.COLORSPACES if n != "camera"]


def _colour(name):
    return colour.RGB_COLOURSPACES[COLOUR_NAMES[name]]


def test_registry():
    assert list(cs.COLORSPACES) == ["rec709", "acescg", "aces2065-1", "xyz", "camera"]
    ids = {n: s.interop_id for n, s in cs.COLORSPACES.items()}
    assert ids == {"rec709": "lin_rec709_scene", "acescg": "lin_ap1_scene", "aces2065-1": "lin_ap0_scene",
                   "xyz": "lin_ciexyzd65_scene", "camera": None}
    for name, space in cs.COLORSPACES.items():
        assert space.name == name and space.description
        with pytest.raises(Exception):
            space.name = "other"  # frozen
    assert cs.COLORSPACES["camera"].chromaticities is None
    with pytest.raises(ValueError, match="camera"):
        cs.rec709_to("camera")
    with pytest.raises(ValueError, match="unknown colour space"):
        cs.rec709_to("srgb")


@pytest.mark.parametrize("name", FIXED)
def test_chromaticities_match_colour(name):
    ch = np.array(cs.COLORSPACES[name].chromaticities)
    assert ch.shape == (8,)
    ref = _colour(name)
    np.testing.assert_allclose(ch[:6].reshape(3, 2), ref.primaries, atol=1e-12)
    np.testing.assert_allclose(ch[6:], ref.whitepoint, atol=1e-12)


def test_chromaticities_match_interop_forum_and_openexr():
    # Color Interop Forum, "Identifying the Color Space of OpenEXR Files", Annex A
    assert cs.COLORSPACES["rec709"].chromaticities == (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)
    assert cs.COLORSPACES["acescg"].chromaticities == (0.713, 0.293, 0.165, 0.830, 0.128, 0.044, 0.32168, 0.33767)
    assert cs.COLORSPACES["aces2065-1"].chromaticities == (0.7347, 0.2653, 0.0, 1.0, 0.0001, -0.0770,
                                                           0.32168, 0.33767)
    # OpenEXR's Chromaticities/XYZ.exr: red (1 0), green (0 1), blue (0 0), white (1/3 1/3)
    np.testing.assert_allclose(cs.COLORSPACES["xyz"].chromaticities, [1, 0, 0, 1, 0, 0, 1 / 3, 1 / 3], atol=1e-15)
    assert cs.COLORSPACES["xyz"].adopted_white == cs.D65


@pytest.mark.parametrize("name", FIXED)
def test_normalised_primary_matrix_matches_colour(name):
    space = cs.COLORSPACES[name]
    ours = cs.rgb_to_xyz_matrix(space.primaries, space.white)
    ref = colour.normalised_primary_matrix(_colour(name).primaries, _colour(name).whitepoint)
    np.testing.assert_allclose(ours, ref, atol=1e-12)
    # and the published matrices colour carries (ACES: S-2014-004 / ST 2065-1, 10 decimals)
    np.testing.assert_allclose(ours, _colour(name).matrix_RGB_to_XYZ, atol=TOL)


def test_normalised_primary_matrix_random_primaries():
    rng = np.random.default_rng(7)
    for _ in range(20):
        prim = rng.uniform(0.05, 0.7, (3, 2))
        white = rng.uniform(0.28, 0.38, 2)
        np.testing.assert_allclose(cs.rgb_to_xyz_matrix(prim, white),
                                   colour.normalised_primary_matrix(prim, white), atol=1e-9, rtol=1e-9)
    with pytest.raises(ValueError, match="collinear"):
        cs.rgb_to_xyz_matrix([(0.1, 0.1), (0.2, 0.2), (0.3, 0.3)], cs.D65)


def test_bradford_matches_colour():
    for src, dst in [(cs.D65, cs.ACES_WHITE), (cs.ACES_WHITE, cs.D65), (cs.D65, (0.3457, 0.3585))]:
        ref = colour.adaptation.matrix_chromatic_adaptation_VonKries(
            colour.xy_to_XYZ(src), colour.xy_to_XYZ(dst), transform="Bradford")
        np.testing.assert_allclose(cs.bradford_matrix(src, dst), ref, atol=1e-12)
    np.testing.assert_allclose(cs.bradford_matrix(cs.D65, cs.D65), np.eye(3), atol=1e-15)


@pytest.mark.parametrize("name", ["rec709", "acescg", "aces2065-1"])
def test_rec709_to_matches_colour_bradford(name):
    ref = colour.matrix_RGB_to_RGB(_colour("rec709"), _colour(name), chromatic_adaptation_transform="Bradford")
    m = cs.rec709_to(name)
    assert m.shape == (3, 3) and m.dtype == np.float64
    np.testing.assert_allclose(m, ref, atol=TOL)
    # the same through colour.RGB_to_RGB on pixels
    rgb = np.random.default_rng(1).uniform(0, 4, (50, 3))
    np.testing.assert_allclose(rgb @ m.T, colour.RGB_to_RGB(rgb, _colour("rec709"), _colour(name),
                                                            chromatic_adaptation_transform="Bradford"),
                               atol=4 * TOL)


def test_rec709_to_xyz_is_unadapted():
    # XYZ-D65: the adopted white is D65, so no adaptation (colour's lin_ciexyzd65_scene has
    # whitepoint E, and with a Bradford CAT colour would adapt D65 -> E: not what the
    # Color Interop Forum's ID means, hence chromatic_adaptation_transform=None here).
    ref = colour.matrix_RGB_to_RGB(_colour("rec709"), _colour("xyz"), chromatic_adaptation_transform=None)
    np.testing.assert_allclose(cs.rec709_to("xyz"), ref, atol=TOL)
    np.testing.assert_allclose(cs.rec709_to("xyz"), _colour("rec709").matrix_RGB_to_XYZ, atol=TOL)
    np.testing.assert_allclose(cs.xyz_to("xyz"), np.eye(3), atol=1e-15)


def test_against_opencolorio_cg_config():
    # OpenColorIO src/OpenColorIO/builtinconfigs/CGConfig.cpp (reference ACES2065-1):
    # "sRGB - Scene-referred" (after linearising) and "CIE XYZ-D65 - Scene-referred" -> AP0
    rec709_to_ap0 = [[0.439632981919491, 0.382988698151554, 0.177378319928955],
                     [0.0897764429588424, 0.813439428748981, 0.0967841282921771],
                     [0.0175411703831727, 0.111546553302387, 0.87091227631444]]
    xyzd65_to_ap0 = [[1.0634954914942, 0.00640891019711789, -0.0158067866176054],
                     [-0.492074127923892, 1.36822340747333, 0.0913370883144736],
                     [-0.00281646163925351, 0.00464417105680067, 0.916418574593656]]
    np.testing.assert_allclose(cs.rec709_to("aces2065-1"), rec709_to_ap0, atol=1e-9)
    np.testing.assert_allclose(cs.xyz_to("aces2065-1"), xyzd65_to_ap0, atol=1e-9)


@pytest.mark.parametrize("name", FIXED)
def test_white_maps_to_adopted_white(name):
    out = cs.rec709_to(name) @ np.ones(3)
    if name == "xyz":
        np.testing.assert_allclose(out, colour.xy_to_XYZ(cs.D65), atol=1e-12)  # (0.9505, 1, 1.0891)
        np.testing.assert_allclose(colour.XYZ_to_xy(out), cs.D65, atol=1e-12)
    else:
        np.testing.assert_allclose(out, np.ones(3), atol=1e-12)
    # luminance is kept: the Y of a Rec.709 pixel equals the Y of the converted pixel
    space = cs.COLORSPACES[name]
    to_xyz = cs.rgb_to_xyz_matrix(space.primaries, space.white)
    adapt_back = cs.bradford_matrix(space.adopted_white, cs.D65)
    rgb = np.array([0.2, 0.5, 0.9])
    np.testing.assert_allclose((adapt_back @ to_xyz @ cs.rec709_to(name) @ rgb)[1],
                               (_colour("rec709").matrix_RGB_to_XYZ @ rgb)[1], atol=1e-12)


@pytest.mark.parametrize("a", FIXED)
@pytest.mark.parametrize("b", FIXED)
def test_round_trip_and_composition(a, b):
    a_to_b = cs.rec709_to(b) @ np.linalg.inv(cs.rec709_to(a))
    rgb = np.random.default_rng(3).uniform(-0.1, 10, (100, 3))
    there = rgb @ cs.rec709_to(a).T
    np.testing.assert_allclose(there @ np.linalg.inv(cs.rec709_to(a)).T, rgb, atol=1e-12)
    if "xyz" not in (a, b):  # between two RGB spaces: colour's Bradford RGB -> RGB
        ref = colour.matrix_RGB_to_RGB(_colour(a), _colour(b), chromatic_adaptation_transform="Bradford")
        np.testing.assert_allclose(a_to_b, ref, atol=TOL)


# -- camera ----------------------------------------------------------------------------

def _camera_like(prims, white, gains=(1.0, 1.0, 1.0)):
    """A DNG-style XYZ -> camera matrix for a camera whose native RGB has these
    primaries and white, with its channels scaled by ``gains``."""
    return np.diag(gains) @ np.linalg.inv(colour.normalised_primary_matrix(prims, white))


def test_camera_chromaticities_recover_primaries():
    prims = np.array([[0.70, 0.32], [0.24, 0.75], [0.11, 0.03]])
    white = (0.34, 0.36)
    got = np.array(cs.camera_chromaticities(_camera_like(prims, white)))
    np.testing.assert_allclose(got[:6].reshape(3, 2), prims, atol=1e-12)
    np.testing.assert_allclose(got[6:], white, atol=1e-12)
    # per-channel gains and overall scale leave the primaries alone but move the white...
    gains = (2.1, 1.0, 1.6)
    scaled = np.array(cs.camera_chromaticities(3.0 * _camera_like(prims, white, gains)))
    np.testing.assert_allclose(scaled[:6], got[:6], atol=1e-12)
    assert np.abs(scaled[6:] - got[6:]).max() > 0.01
    # ...which the white balance that undoes them restores
    undone = np.array(cs.camera_chromaticities(_camera_like(prims, white, gains), 1 / np.array(gains)))
    np.testing.assert_allclose(undone, got, atol=1e-12)


def test_camera_chromaticities_white_balanced_to_d65():
    # A typical DSLR's DNG ColorMatrix (XYZ D65 -> camera, tabulated x 1/10000): with the
    # channels balanced so that D65 maps to (1, 1, 1), the white is D65.
    xyz_to_cam = np.array([[4716, 603, -830], [-7798, 15474, 2480], [-1496, 1937, 6651]]) / 10000
    wb = 1 / (xyz_to_cam @ colour.xy_to_XYZ(cs.D65))
    got = cs.camera_chromaticities(xyz_to_cam, wb)
    np.testing.assert_allclose(got[6:], cs.D65, atol=1e-12)
    ref_prims = colour.XYZ_to_xy(np.linalg.inv(xyz_to_cam).T)  # rows = the columns
    np.testing.assert_allclose(np.array(got[:6]).reshape(3, 2), ref_prims, atol=1e-12)


def test_camera_chromaticities_degenerate():
    assert cs.camera_chromaticities(np.zeros((3, 3))) is None
    assert cs.camera_chromaticities(np.ones((3, 3))) is None
    assert cs.camera_chromaticities(np.full((3, 3), np.nan)) is None
    assert cs.camera_chromaticities(np.eye(2)) is None
    assert cs.camera_chromaticities(np.eye(3), (1, 0, 1)) is None
    # a primary whose XYZ sums to zero has no chromaticity
    m = np.linalg.inv(np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]))
    assert cs.camera_chromaticities(m) is None


def test_module_does_not_import_colour():
    code = "import sys, hdrmerge_cli.core.output_colorspace; print('colour' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# -- EXR attributes --------------------------------------------------------------------

@pytest.mark.parametrize("name", FIXED)
def test_exr_carries_interop_id_and_chromaticities(tmp_path: Path, name):
    oiio = pytest.importorskip("OpenImageIO")
    from hdrmerge_cli.io.images import write_exr

    space = cs.COLORSPACES[name]
    path = tmp_path / f"{name}.exr"
    rgb = np.full((4, 6, 3), 0.18, np.float32) @ cs.rec709_to(name).T.astype(np.float32)
    write_exr(str(path), rgb, ["R", "G", "B"],
              {"colorInteropID": space.interop_id, "chromaticities": list(space.chromaticities)})
    inp = oiio.ImageInput.open(str(path))
    try:
        spec = inp.spec()
        assert spec.getattribute("colorInteropID") == space.interop_id
        np.testing.assert_allclose(spec.getattribute("chromaticities"), space.chromaticities, atol=1e-7)
        np.testing.assert_allclose(inp.read_image("float"), rgb, rtol=1e-7)
    finally:
        inp.close()
    # stored with OpenEXR's own attribute types (name, type name), not as a generic float[8]
    header = path.read_bytes()[:4096]
    assert b"chromaticities\x00chromaticities\x00" in header
    assert b"colorInteropID\x00string\x00" in header
    tool = Path(sys.executable).parent / "oiiotool"
    tool = str(tool) if tool.exists() else shutil.which("oiiotool")
    if tool is None:
        pytest.skip("oiiotool not found")
    info = subprocess.run([tool, "--info", "-v", str(path)], capture_output=True, text=True, check=True).stdout
    assert f'colorInteropID: "{space.interop_id}"' in info
    line = next(ln for ln in info.splitlines() if ln.strip().startswith("chromaticities:"))
    shown = [float(v) for v in line.split(":", 1)[1].split(",")]
    np.testing.assert_allclose(shown, space.chromaticities, atol=1e-5)
