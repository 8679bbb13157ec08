"""Whether two small thumbnails of differently exposed frames show the same scene.

The test compares image structure, not brightness: the gradients of the log thumbnails
over the pixels both frames expose well.  A monotone camera response and an exposure
change rescale those gradients locally but keep where the edges are and which way they
point, so frames of one scene correlate strongly; frames of different scenes have
unrelated edges.
"""
from __future__ import annotations

import numpy as np

#: smallest gradient correlation of one scene: the structure the frames share explains at
#: least half of each frame's gradient variance (r^2 >= 1/2)
SAME_SCENE_CORRELATION = 2 ** -0.5
#: the correlation must also stand this many standard errors (1/sqrt(n) for unrelated
#: frames) above zero, so that a few well-exposed pixels cannot decide
SAME_SCENE_Z = 5.0


def structure_correlation(a: np.ndarray, b: np.ndarray, lo: float, hi: float,
                          max_shift: int = 1) -> tuple[float, int]:
    """Correlation of the log gradients of two thumbnails of one shape.

    ``a`` and ``b``: 2-D arrays of values in [0, 1] (a monotone encoding of the signal);
    a pixel counts where ``lo < value < hi`` in both, and a gradient (the difference of
    two horizontal or vertical neighbours) where both of its pixels count.  ``b`` is tried
    at every integer shift up to ``max_shift`` pixels each way (hand-held frames) and the
    best shift is kept.  Returns ``(r, n)``: the uncentred correlation of the two sets of
    gradients, in [-1, 1], and ``n`` the number of gradient pairs it was measured on;
    ``(nan, 0)`` when no shift leaves a gradient pair with contrast on both sides."""
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"thumbnails of different shapes: {a.shape} and {b.shape}")
    la, lb = (np.log(np.clip(x, lo, hi)) for x in (a, b))
    oka, okb = ((x > lo) & (x < hi) for x in (a, b))
    h, w = a.shape
    best = (np.nan, 0)
    for dy in range(-max_shift, max_shift + 1):
        for dx in range(-max_shift, max_shift + 1):
            ya, yb = slice(max(dy, 0), h + min(dy, 0)), slice(max(-dy, 0), h + min(-dy, 0))
            xa, xb = slice(max(dx, 0), w + min(dx, 0)), slice(max(-dx, 0), w + min(-dx, 0))
            r, n = _gradient_correlation(la[ya, xa], lb[yb, xb], oka[ya, xa] & okb[yb, xb])
            if n and (np.isnan(best[0]) or r > best[0]):
                best = (r, n)
    return best


def _gradient_correlation(la: np.ndarray, lb: np.ndarray, ok: np.ndarray) -> tuple[float, int]:
    ga, gb = [], []
    for axis in (0, 1):
        both = ok[1:] & ok[:-1] if axis == 0 else ok[:, 1:] & ok[:, :-1]
        ga.append(np.diff(la, axis=axis)[both])
        gb.append(np.diff(lb, axis=axis)[both])
    ga, gb = np.concatenate(ga).astype(np.float64), np.concatenate(gb).astype(np.float64)
    norm = np.sqrt(np.dot(ga, ga) * np.dot(gb, gb))
    if not ga.size or norm == 0:
        return np.nan, 0
    return float(np.dot(ga, gb) / norm), int(ga.size)


def same_scene(r: float, n: int) -> bool:
    """Whether a :func:`structure_correlation` ``(r, n)`` is clearly that of one scene:
    ``r`` at least :data:`SAME_SCENE_CORRELATION` and ``r sqrt(n)`` at least
    :data:`SAME_SCENE_Z` (unrelated frames give ``r`` about 0 with standard error
    ``1/sqrt(n)``)."""
    return bool(n > 0 and r >= SAME_SCENE_CORRELATION and r * np.sqrt(n) >= SAME_SCENE_Z)
