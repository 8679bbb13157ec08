"""Which samples a frame measures, and whether a bracket covers its scene.

A stored code ``z`` of a channel with black level ``b`` and white (clipping) level ``w``
is *clipped* when ``z >= w`` and *dark* when ``z <= b``: there the normalised signal
``v = (z - b) / (w - b)`` is 1 or 0 and every weighting function of (7) gives it no
weight.  A sample that is clipped or dark in every frame of a bracket is not measured by
it (the merge flags it and writes a bound, see :meth:`~hdrmerge_cli.core.reconstruct.LogMerge.finish`):
the bracket covers the scene when there is no such sample.
"""
from __future__ import annotations

import numpy as np


def clip_classes(codes: np.ndarray, pattern: np.ndarray, black, white) -> tuple[np.ndarray, np.ndarray]:
    """``(clipped, dark)`` boolean arrays of ``codes``' shape.

    codes : ``(H, W)`` mosaic or ``(H, W, C)`` interleaved channels, uint8/uint16
    pattern : ``(ph, pw)`` int, the channel of each sample, periodic over ``(H, W)`` (a CFA
        cell) or ``(H, W * C)`` (``[[0, 1, 2]]`` for RGB)
    black, white : per channel, stored code values
    """
    rows = codes.reshape(codes.shape[0], -1)
    clipped = np.empty(rows.shape, bool)
    dark = np.empty(rows.shape, bool)
    ph, pw = pattern.shape
    for dy in range(ph):
        for dx in range(pw):
            c = pattern[dy, dx]
            view = rows[dy::ph, dx::pw]
            np.greater_equal(view, white[c], out=clipped[dy::ph, dx::pw])
            np.less_equal(view, black[c], out=dark[dy::ph, dx::pw])
    return clipped.reshape(codes.shape), dark.reshape(codes.shape)


class Coverage:
    """Accumulates, over the frames of a bracket given shortest exposure first, which
    samples some frame measures (neither clipped nor dark).

    After the frames, fractions of *pixels* (a pixel of an ``(H, W, C)`` image counts
    when any of its channels does): :attr:`uncovered`, no frame measures it;
    :attr:`too_bright`, unmeasured and clipped in the shortest frame (a shorter exposure
    is missing); :attr:`too_dark`, unmeasured and dark in the longest frame (a longer one
    is missing); :attr:`gap`, unmeasured, dark in one frame and clipped in the next longer
    (two exposures too far apart)."""

    def __init__(self):
        self.measured = self.bright_first = self.dark_last = None

    def add(self, clipped: np.ndarray, dark: np.ndarray) -> None:
        seen = ~(clipped | dark)
        if self.measured is None:
            self.measured, self.bright_first = seen, clipped
        else:
            self.measured |= seen
        self.dark_last = dark

    def _pixels(self, samples: np.ndarray) -> float:
        return float(np.mean(samples.any(axis=-1) if samples.ndim == 3 else samples))

    @property
    def uncovered(self) -> float:
        return self._pixels(~self.measured)

    @property
    def too_bright(self) -> float:
        return self._pixels(~self.measured & self.bright_first)

    @property
    def too_dark(self) -> float:
        return self._pixels(~self.measured & self.dark_last)

    @property
    def gap(self) -> float:
        return self._pixels(~self.measured & ~self.bright_first & ~self.dark_last)
