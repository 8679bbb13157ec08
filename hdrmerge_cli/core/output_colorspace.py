"""Output colour spaces of a merged EXR (``merge --colorspace``): chromaticities, Color
Interop IDs and the 3 x 3 matrices from linear Rec.709 (array code, numpy only).

Every space here is scene-linear.  A space is described as an OpenEXR ``chromaticities``
attribute describes it (ImfChromaticities.h: "the CIE x and y coordinates of the RGB triples
(1,0,0), (0,1,0), (0,0,1) and (1,1,1)") plus its *adopted* white, the chromaticity that an
observer of the scene is adapted to and that must come out neutral.  For the RGB spaces the
two whites coincide; for CIE XYZ they do not: X = Y = Z is illuminant E (so OpenEXR's own
``Chromaticities/XYZ.exr`` test image carries white (1/3, 1/3)), while the adopted white of
the Color Interop Forum's ``lin_ciexyzd65_scene`` is D65 ("Color Space Encodings for Texture
Assets and CG Rendering", v1.1.0: "For CIE XYZ, equal XYZ values must always correspond to
illuminant E, so in that case neutrals have the chromaticity of D65").  Rec.709 -> XYZ-D65
is therefore the plain normalised primary matrix, with no chromatic adaptation.

Chromatic adaptation (D65 -> the ACES white, x = 0.32168, y = 0.33767) is a von Kries
transform in Bradford cone space: the Color Interop Forum recommends it for every
conversion among its spaces (same document, "White Points"), and it is what OpenColorIO's
built-in ACES / CG configs and colour-science's ``chromatic_adaptation_transform='Bradford'``
compute, so these matrices agree with both to ~1e-12.

colour-science is deliberately not imported (it takes ~1 s to import); the tests check
every number here against it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: CIE xy of the white points used here: D65 as ITU-R BT.709 rounds it (the value the
#: Color Interop Forum, OpenEXR and OCIO use) and the ACES white (SMPTE ST 2065-1,
#: Academy TB-2018-001), which is close to, but not, CIE D60.
D65 = (0.3127, 0.3290)
ACES_WHITE = (0.32168, 0.33767)
E_WHITE = (1.0 / 3.0, 1.0 / 3.0)

#: The Bradford cone-response matrix (Lam 1985; as in ICC.1:2010 Annex E, colour-science's
#: ``CAT_BRADFORD`` and the ACES / OCIO configs): XYZ -> "sharpened" cone responses.
BRADFORD = np.array([[0.8951, 0.2664, -0.1614],
                     [-0.7502, 1.7135, 0.0367],
                     [0.0389, -0.0685, 1.0296]])


@dataclass(frozen=True)
class ColorSpace:
    """A scene-linear output colour space.

    primaries : CIE xy of the R, G and B primaries, ``((xr, yr), (xg, yg), (xb, yb))``, or
        None for ``camera`` (they are the camera's, see :func:`camera_chromaticities`)
    white : CIE xy of RGB (1, 1, 1), the white of the OpenEXR ``chromaticities`` attribute
    adopted_white : CIE xy that is neutral for an observer of the image (equals ``white``
        except for CIE XYZ, whose (1, 1, 1) is illuminant E while the adopted white is D65)
    interop_id : the Color Interop Forum ID for the EXR ``colorInteropID`` attribute, or None
    description : one line for ``--help``"""

    name: str
    primaries: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] | None
    white: tuple[float, float] | None
    adopted_white: tuple[float, float] | None
    interop_id: str | None
    description: str

    @property
    def chromaticities(self) -> tuple[float, ...] | None:
        """The 8 floats of the OpenEXR ``chromaticities`` attribute (red xy, green xy, blue
        xy, white xy), or None when the space has no fixed primaries."""
        if self.primaries is None or self.white is None:
            return None
        return tuple(float(v) for xy in (*self.primaries, self.white) for v in xy)


#: ``merge --colorspace`` choices.  Primaries from ITU-R BT.709-6 (Rec.709), the ACES
#: specifications S-2014-004 (AP1) and SMPTE ST 2065-1 (AP0), and CIE 1931 XYZ; the
#: interop IDs from the Color Interop Forum recommendation cited in the module docstring.
COLORSPACES: dict[str, ColorSpace] = {
    "rec709": ColorSpace(
        "rec709", ((0.64, 0.33), (0.30, 0.60), (0.15, 0.06)), D65, D65, "lin_rec709_scene",
        "linear Rec.709 / sRGB primaries, D65 white (the default)"),
    "acescg": ColorSpace(
        "acescg", ((0.713, 0.293), (0.165, 0.830), (0.128, 0.044)), ACES_WHITE, ACES_WHITE,
        "lin_ap1_scene", "ACEScg: linear AP1 primaries, ACES white (~D60), Bradford-adapted from D65"),
    "aces2065-1": ColorSpace(
        "aces2065-1", ((0.7347, 0.2653), (0.0, 1.0), (0.0001, -0.0770)), ACES_WHITE, ACES_WHITE,
        "lin_ap0_scene", "ACES2065-1: linear AP0 primaries, ACES white (~D60), Bradford-adapted from D65"),
    "xyz": ColorSpace(
        "xyz", ((1.0, 0.0), (0.0, 1.0), (0.0, 0.0)), E_WHITE, D65, "lin_ciexyzd65_scene",
        "CIE 1931 XYZ (R, G, B channels hold X, Y, Z), D65 adopted white, Y = 1 for a D65 white"),
    "camera": ColorSpace(
        "camera", None, None, None, None,
        "the camera's native RGB (RAW input; chromaticities from its colour matrix)"),
}


def xy_to_XYZ(xy) -> np.ndarray:
    """CIE xy -> XYZ with Y = 1, float64 ``(3,)``."""
    x, y = (float(v) for v in xy)
    if y == 0.0:
        raise ValueError(f"chromaticity {xy!r} has y = 0 (no finite XYZ with Y = 1)")
    return np.array([x / y, 1.0, (1.0 - x - y) / y])


def XYZ_to_xy(XYZ) -> tuple[float, float] | None:
    """CIE XYZ -> xy, or None when X + Y + Z is 0 or not finite."""
    XYZ = np.asarray(XYZ, dtype=np.float64)
    s = float(XYZ.sum())
    if not np.isfinite(s) or abs(s) < 1e-12 * max(float(np.abs(XYZ).max()), 1e-300):
        return None
    return (float(XYZ[0] / s), float(XYZ[1] / s))


def rgb_to_xyz_matrix(primaries, white) -> np.ndarray:
    """The normalised primary matrix (SMPTE RP 177-1993): linear RGB -> CIE XYZ, float64
    ``(3, 3)``, scaled so that RGB (1, 1, 1) has the chromaticity ``white`` and Y = 1.

    primaries : ``(3, 2)`` CIE xy of R, G, B (a primary may have y = 0, e.g. XYZ's Z)
    white : ``(2,)`` CIE xy of RGB (1, 1, 1)

    Each column is a primary's (x, y, 1 - x - y) scaled by the amount that makes the three
    add up to the white's XYZ.  Raises ValueError when the primaries are collinear."""
    p = np.asarray(primaries, dtype=np.float64).reshape(3, 2)
    chroma = np.stack([p[:, 0], p[:, 1], 1.0 - p[:, 0] - p[:, 1]])  # columns = primaries
    try:
        scale = np.linalg.solve(chroma, xy_to_XYZ(white))
    except np.linalg.LinAlgError:
        raise ValueError(f"primaries {p.tolist()} are collinear (no RGB -> XYZ matrix)") from None
    return chroma * scale


def bradford_matrix(source_white, target_white) -> np.ndarray:
    """Von Kries chromatic adaptation in Bradford cone space, XYZ under ``source_white`` ->
    XYZ under ``target_white`` (CIE xy), float64 ``(3, 3)``; as colour-science's
    ``matrix_chromatic_adaptation_VonKries(..., transform='Bradford')`` and OCIO's ACES
    configs.  The identity when the whites are equal."""
    src, dst = BRADFORD @ xy_to_XYZ(source_white), BRADFORD @ xy_to_XYZ(target_white)
    return np.linalg.solve(BRADFORD, np.diag(dst / src) @ BRADFORD)


def _space(name: str) -> ColorSpace:
    try:
        return COLORSPACES[name]
    except KeyError:
        raise ValueError(f"unknown colour space {name!r} (choose from {', '.join(COLORSPACES)})") from None


def xyz_to(name: str) -> np.ndarray:
    """CIE XYZ with a D65 adopted white (Y = 1 for a D65 white) -> the linear RGB of
    colour space ``name`` (a key of :data:`COLORSPACES` other than ``camera``), float64
    ``(3, 3)``, Bradford-adapting D65 to the space's adopted white where they differ."""
    cs = _space(name)
    if cs.primaries is None:
        raise ValueError(f"colour space {name!r} has no fixed primaries (use the camera's matrix)")
    to_xyz = rgb_to_xyz_matrix(cs.primaries, cs.white)
    return np.linalg.solve(to_xyz, bradford_matrix(D65, cs.adopted_white))


def rec709_to(name: str) -> np.ndarray:
    """Linear Rec.709 (D65) -> the linear RGB of colour space ``name``, float64 ``(3, 3)``,
    to apply as ``rgb @ M.T`` (a column vector ``M @ rgb``).

    With Bradford chromatic adaptation D65 -> the ACES white for ``acescg`` and
    ``aces2065-1`` (the Color Interop Forum's recommendation; what colour-science's
    ``matrix_RGB_to_RGB(..., chromatic_adaptation_transform='Bradford')`` and OCIO's ACES
    configs compute), so Rec.709 (1, 1, 1) maps to (1, 1, 1).  For ``xyz`` it is the plain
    Rec.709 normalised primary matrix: (1, 1, 1) maps to D65's XYZ (0.9505, 1, 1.0891)."""
    return xyz_to(name) @ rgb_to_xyz_matrix(COLORSPACES["rec709"].primaries, D65)


def camera_chromaticities(xyz_to_camera, white_balance=None) -> tuple[float, ...] | None:
    """The OpenEXR ``chromaticities`` (8 floats: red, green, blue, white xy) of a camera's
    native RGB, from its DNG-style ``(3, 3)`` XYZ -> camera matrix (ColorMatrix, e.g.
    LibRaw's ``rgb_xyz_matrix[:3, :3]``); None when the matrix is singular or not finite or
    a primary has no chromaticity (X + Y + Z = 0).  ``white_balance``: the per-channel gains
    the data were multiplied by before writing (``rgb * white_balance``), or None for raw
    camera RGB.

    Notes: the primaries are the xy of the inverse matrix's columns, independent of how the
    matrix is scaled.  The white is by OpenEXR's definition the xy of camera (1, 1, 1), the
    inverse's row sums, and depends on the gains: without them it is the camera's own
    equal-response white (usually magenta-ish); with them, the illuminant the balance made
    neutral (the as-shot balance: the scene's white; ``1 / (M @ XYZ_D65)``: D65)."""
    m = np.asarray(xyz_to_camera, dtype=np.float64)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        return None
    if white_balance is not None:
        gains = np.asarray(white_balance, dtype=np.float64).reshape(-1)[:3]
        if gains.shape != (3,) or not np.all(np.isfinite(gains)) or np.any(gains == 0):
            return None
        m = gains[:, None] * m
    cond = np.linalg.cond(m)
    if not np.isfinite(cond) or cond > 1e12:
        return None
    to_xyz = np.linalg.inv(m)
    points = [XYZ_to_xy(to_xyz[:, i]) for i in range(3)] + [XYZ_to_xy(to_xyz.sum(axis=1))]
    if any(p is None for p in points):
        return None
    return tuple(v for p in points for v in p)
