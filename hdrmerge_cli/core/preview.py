"""Tone-mapped sRGB previews of a scene-linear image (array code).

The image is first reduced by area averaging in scene-linear units (the physically right
mean of the light in each block), then tone-mapped by Reinhard and Devlin's photoreceptor
operator (2005, "Dynamic range reduction inspired by photoreceptor physiology", with
colour-hdri's default parameters) and sRGB-encoded.
"""
from __future__ import annotations

import numpy as np

from hdrmerge_cli.core.crf import srgb_eotf_inverse
from hdrmerge_cli.core.output_colorspace import COLORSPACES, D65, rgb_to_xyz_matrix


def block_factor(height: int, width: int, max_side: int) -> int:
    """The integer reduction ``f`` that brings the longer side to at most ``max_side``
    (1: full size; ``max_side`` 0 means full size)."""
    if max_side <= 0:
        return 1
    return max(1, min(-(-max(height, width) // max_side), height, width))  # at least one pixel


class BlockMean:
    """Area-average an image of ``(height, width, C)`` by ``factor`` while it arrives in
    strips of rows (so the full-size image is never held): ``(height // f, width // f, C)``
    float64; rows and columns beyond whole blocks are dropped."""

    def __init__(self, height: int, width: int, channels: int, factor: int):
        self.f = factor
        self.sum = np.zeros((height // factor, width // factor, channels))

    def add(self, y0: int, rows: np.ndarray) -> None:
        """Rows ``y0 : y0 + len(rows)`` of the image, ``(n, width, C)``."""
        f, (h, w, c) = self.f, self.sum.shape
        cols = rows[:, : w * f].reshape(rows.shape[0], w, f, c).sum(axis=2, dtype=np.float64)
        block = (y0 + np.arange(rows.shape[0])) // f
        keep = block < h
        np.add.at(self.sum, block[keep], cols[keep])

    def result(self) -> np.ndarray:
        return self.sum / (self.f * self.f)


#: the photoreceptor operator's contrast ``m`` (Reinhard & Devlin 2005; colour-hdri's default)
REINHARD_DEVLIN_M = 0.3


def reinhard_devlin(rgb: np.ndarray, m: float = REINHARD_DEVLIN_M) -> np.ndarray:
    """Reinhard & Devlin's photoreceptor operator (2005, eq. 4 with global adaptation):
    ``V = I / (I + (f I_a)^m)`` per channel, at colour-hdri's defaults
    (``tonemapping_operator_Reinhard2004(RGB)``: intensity ``f = 1``, light adaptation
    ``a = 0`` and chromatic adaptation ``c = 0``), where the adaptation level ``I_a`` is then
    the log-average luminance ``exp(mean(log(L + eps)))`` of the Rec.709 luminance ``L``.
    The same values as colour-hdri's (a test compares them) without importing colour-science,
    whose package import (plotting, matplotlib) cost 1.2 s of every preview.

    rgb : ``(H, W, 3)`` float64 scene-linear Rec.709, non-negative -> ``(H, W, 3)`` in [0, 1)
    """
    lum = rgb @ rgb_to_xyz_matrix(COLORSPACES["rec709"].primaries, D65)[1]  # Y, as colour-science's
    adapt = np.exp(np.mean(np.log(lum + np.finfo(np.float64).eps)))
    return rgb / (rgb + adapt ** m)


def tonemap_srgb(rgb: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` scene-linear Rec.709 -> ``(H, W, 3)`` uint8 sRGB: Reinhard-Devlin
    (:func:`reinhard_devlin`), then the sRGB encoding (IEC 61966-2-1).  Negative or
    non-finite values are treated as black."""
    rgb = np.nan_to_num(np.maximum(np.asarray(rgb, np.float64), 0.0), posinf=0.0)
    if not np.any(rgb > 0):
        return np.zeros(rgb.shape, np.uint8)
    mapped = np.clip(np.nan_to_num(reinhard_devlin(rgb)), 0.0, 1.0)
    return np.rint(np.clip(srgb_eotf_inverse(mapped), 0.0, 1.0) * 255.0).astype(np.uint8)
