"""White balance, Malvar-He-Cutler demosaic and camera matrix in one compiled pass.

The same arithmetic as colour-demosaicing's ``demosaicing_CFA_Bayer_Malvar2004`` (scipy
``convolve`` with ``mode="reflect"`` at the image border; the tests' reference) applied to
the white-balanced mosaic and followed by
:func:`~hdrmerge_cli.core.cfa.camera_to_rec709`, but per output row band and without the
intermediates (balanced mosaic, four full-size convolutions, the RGB image): each output
pixel reads its 5 x 5 neighbourhood once.  The kernel releases the GIL, so strips converted
on two threads use both cores.  Differences from the reference path are float rounding
(sums here are accumulated in float64).

Malvar, He, Cutler, "High-quality linear interpolation for demosaicing of Bayer-patterned
color images", ICASSP 2004.
"""
from __future__ import annotations

import numpy as np

from hdrmerge_cli.core.cfa import BAYER_PATTERNS
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.jit import njit


@njit(inline="always")
def _reflect(i, n):  # pragma: no cover - compiled
    """scipy.ndimage ``mode="reflect"`` (d c b a | a b c d | d c b a)."""
    while i < 0 or i >= n:
        if i < 0:
            i = -i - 1
        if i >= n:
            i = 2 * n - i - 1
    return i


@njit(nogil=True, cache=True, error_model="numpy")
def _malvar_rows(mosaic, cell, wb, matrix, y0, y1, out):  # pragma: no cover - compiled
    """Rows ``y0:y1`` of ``mosaic`` (H, W) -> ``out`` (y1 - y0, W, 3) float32.

    cell : (2, 2) colour index (0 R, 1 G, 2 B) of the Bayer cell at rows/columns mod 2
    wb   : (3,) white balance per colour, applied to each mosaic sample before interpolation
    matrix : (3, 3) camera RGB -> output RGB."""
    h, w = mosaic.shape
    # row/column indices of the 5 x 5 neighbourhood, reflected at the border
    rows = np.empty(5, np.int64)
    cols = np.empty((w, 5), np.int64)
    for x in range(w):
        for d in range(5):
            cols[x, d] = _reflect(x + d - 2, w)
    wrow = np.empty((5, 2), np.float32)
    m00, m01, m02 = np.float64(matrix[0, 0]), np.float64(matrix[0, 1]), np.float64(matrix[0, 2])
    m10, m11, m12 = np.float64(matrix[1, 0]), np.float64(matrix[1, 1]), np.float64(matrix[1, 2])
    m20, m21, m22 = np.float64(matrix[2, 0]), np.float64(matrix[2, 1]), np.float64(matrix[2, 2])
    # whether row parity p has red (blue) sites, column parity q has red (blue) sites
    red_row = np.zeros(2, np.bool_)
    blue_row = np.zeros(2, np.bool_)
    red_col = np.zeros(2, np.bool_)
    blue_col = np.zeros(2, np.bool_)
    for p in range(2):
        for q in range(2):
            if cell[p, q] == 0:
                red_row[p] = True
                red_col[q] = True
            elif cell[p, q] == 2:
                blue_row[p] = True
                blue_col[q] = True
    for y in range(y0, y1):
        for d in range(5):
            rows[d] = _reflect(y + d - 2, h)
            for q in range(2):
                wrow[d, q] = wb[cell[rows[d] & 1, q]]
        py = y & 1
        ra, rb, rc, rd, re = mosaic[rows[0]], mosaic[rows[1]], mosaic[rows[2]], mosaic[rows[3]], mosaic[rows[4]]
        for x in range(w):
            c0, c1, c2, c3, c4 = cols[x, 0], cols[x, 1], cols[x, 2], cols[x, 3], cols[x, 4]
            # the 13 samples within |dy| + |dx| <= 2 that Malvar's kernels read, white-balanced
            # (float32 products, as the reference's balanced mosaic), named by (row, column)
            n02 = np.float64(ra[c2] * wrow[0, c2 & 1])
            n11 = np.float64(rb[c1] * wrow[1, c1 & 1])
            n12 = np.float64(rb[c2] * wrow[1, c2 & 1])
            n13 = np.float64(rb[c3] * wrow[1, c3 & 1])
            n20 = np.float64(rc[c0] * wrow[2, c0 & 1])
            n21 = np.float64(rc[c1] * wrow[2, c1 & 1])
            centre = np.float64(rc[c2] * wrow[2, c2 & 1])
            n23 = np.float64(rc[c3] * wrow[2, c3 & 1])
            n24 = np.float64(rc[c4] * wrow[2, c4 & 1])
            n31 = np.float64(rd[c1] * wrow[3, c1 & 1])
            n32 = np.float64(rd[c2] * wrow[3, c2 & 1])
            n33 = np.float64(rd[c3] * wrow[3, c3 & 1])
            n42 = np.float64(re[c2] * wrow[4, c2 & 1])
            colour = cell[py, x & 1]
            if colour == 1:
                g = centre
                # Rg_RB_Bg_BR: the horizontal neighbours' colour
                horiz = (0.5 * (n02 + n42) - (n11 + n13 + n31 + n33)
                         - (n20 + n24) + 4.0 * (n21 + n23) + 5.0 * centre) / 8.0
                # its transpose: the vertical neighbours' colour
                vert = (0.5 * (n20 + n24) - (n11 + n13 + n31 + n33)
                        - (n02 + n42) + 4.0 * (n12 + n32) + 5.0 * centre) / 8.0
                if red_row[py] and blue_col[x & 1]:
                    rr, bb = horiz, vert
                elif blue_row[py] and red_col[x & 1]:
                    rr, bb = vert, horiz
                else:  # pragma: no cover - not a Bayer cell
                    rr, bb = 0.0, 0.0
            else:
                # GR_GB: green at a red or blue site
                g = (4.0 * centre + 2.0 * (n12 + n32 + n21 + n23)
                     - (n02 + n42 + n20 + n24)) / 8.0
                # Rb_BB_Br_RR: the opposite colour from the diagonals
                other = (6.0 * centre + 2.0 * (n11 + n13 + n31 + n33)
                         - 1.5 * (n02 + n42 + n20 + n24)) / 8.0
                if colour == 0:
                    rr, bb = centre, other
                else:
                    rr, bb = other, centre
            # the reference rounds the demosaiced planes to float32 before the matrix
            rr = np.float64(np.float32(rr))
            g = np.float64(np.float32(g))
            bb = np.float64(np.float32(bb))
            o = out[y - y0, x]
            o[0] = np.float32(m00 * rr + m01 * g + m02 * bb)
            o[1] = np.float32(m10 * rr + m11 * g + m12 * bb)
            o[2] = np.float32(m20 * rr + m21 * g + m22 * bb)


def bayer_cell(pattern: str) -> np.ndarray:
    """The 2 x 2 colour index cell (0 R, 1 G, 2 B) of a Bayer pattern name."""
    if pattern not in BAYER_PATTERNS:
        raise HdrMergeError(f"unsupported colour filter pattern {pattern!r} (Bayer only: {', '.join(BAYER_PATTERNS)})")
    return np.array(["RGB".index(ch) for ch in pattern], np.int64).reshape(2, 2)


def raw_to_rgb_rows(mosaic: np.ndarray, pattern: str, white_balance, matrix, y0: int, y1: int,
                    out: np.ndarray | None = None) -> np.ndarray:
    """Rows ``y0:y1`` of white balance (per CFA colour) -> Malvar demosaic -> ``matrix``:
    ``(y1 - y0, W, 3)`` float32.  The whole ``mosaic`` (H, W) is passed so the rows near a
    strip's edge see their real neighbours (and the image border is reflected as in the
    reference)."""
    h, w = mosaic.shape
    if not 0 <= y0 <= y1 <= h:
        raise ValueError(f"rows {y0}:{y1} outside 0:{h}")
    if out is None:
        out = np.empty((y1 - y0, w, 3), np.float32)
    if mosaic.dtype != np.float32:
        mosaic = mosaic.astype(np.float32)
    _malvar_rows(mosaic, bayer_cell(pattern), np.asarray(white_balance, np.float32).reshape(3),
                 np.asarray(matrix, np.float32).reshape(3, 3), int(y0), int(y1), out)
    return out
