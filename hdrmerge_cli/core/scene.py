"""A built-in procedural HDR scene: the embedded ground truth for the demo and tests."""
from __future__ import annotations

import numpy as np


def procedural_scene(height: int = 512, width: int = 768, seed: int = 0) -> np.ndarray:
    """Scene irradiance in photo-electrons per second, ``(height, width, 3)`` float64,
    about 18 stops (from ~300 to ~1.6e8 e-/s).

    A 12-stop horizontal illumination ramp over a smoothly textured, coloured wall; a
    6 x 4 grid of patches with random reflectances; a shadowed band (1/8 light) at the
    bottom; a bright lamp disk (2^14 relative) with a soft halo.  Smooth enough that demosaicing
    adds little error, textured enough for noise statistics.  Deterministic in ``seed``.
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    u, v = xx / max(width - 1, 1), yy / max(height - 1, 1)
    light = 2.0 ** (12.0 * u)
    light = light * np.where(v > 0.8, 0.125, 1.0)
    phases = rng.uniform(0, 2 * np.pi, (3, 2))
    texture = np.stack(
        [0.45 + 0.25 * np.sin(2 * np.pi * (3 + c) * u + phases[c, 0]) * np.cos(2 * np.pi * (2 + c) * v + phases[c, 1])
         for c in range(3)],
        axis=-1,
    )
    reflect = texture * np.array([1.0, 0.9, 0.8])
    rows, cols = 4, 6
    patch = rng.uniform(0.03, 0.9, (rows, cols, 3))
    y0, y1, x0, x1 = 0.15 * height, 0.7 * height, 0.08 * width, 0.92 * width
    ph, pw = (y1 - y0) / rows, (x1 - x0) / cols
    iy, ix = np.floor((yy - y0) / ph).astype(int), np.floor((xx - x0) / pw).astype(int)
    inside = (iy >= 0) & (iy < rows) & (ix >= 0) & (ix < cols)
    inside &= ((yy - y0) % ph > 0.12 * ph) & ((xx - x0) % pw > 0.12 * pw)
    reflect = np.where(inside[..., None], patch[np.clip(iy, 0, rows - 1), np.clip(ix, 0, cols - 1)], reflect)
    scene = light[..., None] * reflect
    cy, cx, r = 0.12 * height, 0.85 * width, 0.06 * min(height, width)
    d = np.hypot(yy - cy, xx - cx) / r
    lamp = 2.0**14 * np.clip(1.5 - d, 0.0, 1.0) + 2.0**11 * np.exp(-(d**2) / 8.0)
    return 1e4 * (scene + lamp[..., None] * np.array([1.0, 0.95, 0.85]))
