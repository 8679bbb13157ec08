"""Colour filter arrays: Bayer layouts, mosaic, the variance of a demosaiced sample (the
demosaic itself is :mod:`hdrmerge_cli.core.cfa_to_rgb`), and camera RGB -> Rec.709 (array
code)."""
from __future__ import annotations

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError


#: CIE xy of the Rec.709 / sRGB primaries (R, G, B) and the D65 white point, in the
#: order of the OpenEXR ``chromaticities`` attribute.
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)

BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


def bayer_channels(pattern: str, shape: tuple[int, int]) -> np.ndarray:
    """Colour index (0 = R, 1 = G, 2 = B) of every site of a Bayer mosaic, ``(H, W)`` uint8."""
    if pattern not in BAYER_PATTERNS:
        raise HdrMergeError(f"unsupported colour filter pattern {pattern!r} (Bayer only: {', '.join(BAYER_PATTERNS)})")
    cell = np.array(["RGB".index(ch) for ch in pattern], np.uint8).reshape(2, 2)
    h, w = shape
    return np.tile(cell, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


def mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """Sample an ``(H, W, 3)`` image through a Bayer filter: ``(H, W)``."""
    idx = bayer_channels(pattern, rgb.shape[:2])
    return np.take_along_axis(rgb, idx[..., None].astype(np.intp), axis=-1)[..., 0]


#: Malvar-He-Cutler (2004)'s kernels (x 8, as colour-demosaicing has them): G at R/B sites,
#: R/B at G sites in an R/B row (``RB_ROW``; transposed: in a B/R row), R at B and B at R
_G_AT_RB = np.array([[0, 0, -1, 0, 0], [0, 0, 2, 0, 0], [-1, 2, 4, 2, -1], [0, 0, 2, 0, 0], [0, 0, -1, 0, 0]]) / 8
_RB_ROW = np.array([[0, 0, .5, 0, 0], [0, -1, 0, -1, 0], [-1, 4, 5, 4, -1], [0, -1, 0, -1, 0], [0, 0, .5, 0, 0]]) / 8
_RB_AT_BR = np.array([[0, 0, -1.5, 0, 0], [0, 2, 0, 2, 0], [-1.5, 0, 6, 0, -1.5], [0, 2, 0, 2, 0],
                      [0, 0, -1.5, 0, 0]]) / 8


def demosaic_variance(var: np.ndarray, pattern: str) -> np.ndarray:
    """The variance of the Malvar-He-Cutler demosaic's ``(H, W, 3)`` output
    (:mod:`hdrmerge_cli.core.cfa_to_rgb`) for a mosaic of independent samples whose
    variances are ``var`` ``(H, W)`` (in the squared units of the mosaic):
    the demosaic is linear, so each output's variance is the sum of its kernel's squared
    weights times the samples' variances (the same kernels and sites as colour-demosaicing's
    Malvar 2004, the same ``reflect`` edges, where a sample counted twice is taken as
    independent).  float32."""
    from scipy.ndimage import convolve

    var = np.asarray(var, np.float64)
    idx = bayer_channels(pattern, var.shape)
    r_row = (idx == 0).any(axis=1)[:, None]
    r_col = (idx == 0).any(axis=0)[None, :]
    b_row, b_col = ~r_row, ~r_col  # a Bayer row (column) holds R or B, not both
    at_rb = convolve(var, np.square(_G_AT_RB))
    in_rb_row = convolve(var, np.square(_RB_ROW))
    in_br_row = convolve(var, np.square(_RB_ROW.T))
    across = convolve(var, np.square(_RB_AT_BR))
    out = np.empty(var.shape + (3,), np.float32)
    out[..., 1] = np.where(idx == 1, var, at_rb)
    for c, (own_row, own_col, other_row, other_col) in ((0, (r_row, r_col, b_row, b_col)),
                                                        (2, (b_row, b_col, r_row, r_col))):
        plane = np.where(idx == c, var, 0.0)
        plane = np.where(own_row & other_col, in_rb_row, plane)  # G site in this colour's rows
        plane = np.where(other_row & own_col, in_br_row, plane)  # G site in the other colour's rows
        out[..., c] = np.where(other_row & other_col, across, plane)
    return out


def camera_to_rec709(rgb: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Apply a 3 x 3 camera-RGB -> linear Rec.709 matrix to ``(H, W, 3)`` in place-free form."""
    out = rgb @ np.asarray(matrix, dtype=np.float32).T
    return out.astype(np.float32, copy=False)
