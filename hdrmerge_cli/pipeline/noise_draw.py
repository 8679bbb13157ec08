"""The sites merge measures a bracket's noise on, drawn from the integer codes as the
merge decodes each frame (:class:`NoiseDraw`): tiles spread over each channel
(:func:`noise_tiles`) and an even stride for the usability test.  The measurement itself
is :func:`hdrmerge_cli.pipeline.noise.estimate_bracket_noise`; this module keeps
calibrate-noise's imports off a merge's start-up."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from hdrmerge_cli.io.frames import Frame, cfa_corner


def channel_codes(frame: Frame, codes: np.ndarray, corner: np.ndarray | None = None, pick=None):
    """(name, channel index, that channel's codes) per channel, still integer: the CFA sites
    of one colour for RAW (``corner``: LibRaw's colour index of the top-left 2 x 2 visible
    sites, read from the file when not given), the colour channels otherwise.  ``pick(codes,
    fill)`` chooses the sites to keep (``fill``: the channel's white code, which every
    statistic takes as clipped), e.g. :func:`noise_tiles`."""
    if frame.kind == "raw":
        corner = cfa_corner(frame) if corner is None else corner
        for k, name in enumerate(frame.channel_names):
            ys, xs = np.nonzero(corner == k)
            if ys.size:
                view = codes[ys[0]::2, xs[0]::2]
                yield name, k, view if pick is None else pick(view, int(np.ceil(frame.white[k])))
        return
    for c in range(frame.channels):
        view = codes[..., c]
        yield frame.channel_colors[c], c, view if pick is None else pick(view, frame.n_codes - 1)


#: merge's fast path measures the noise on at most this many sites per channel and frame
#: (on simulated RAW brackets of 3 to 5 frames the standard errors this gives, in the profile
#: entry, are 1-2 % of sigma_o^2 and 2-3.5 % of alpha per channel; the fit takes ~0.1 s of CPU)
FAST_PATH_SITES = 1 << 15
#: the fast path's tiles: NOISE_TILE x NOISE_TILE sites of one channel
NOISE_TILE = 64
#: the fast path judges a frame usable on an even stride of at most this many sites per channel
USABILITY_SITES = 1 << 17


def _grid(h: int, w: int, sites: int, tile: int) -> tuple[int, int] | None:
    """Rows and columns of :func:`noise_tiles`' grid on a channel (H, W), None: the whole channel."""
    if h * w <= sites or h < 2 * tile or w < 2 * tile:
        return None
    count = max(sites // tile**2, 1)
    ny = min(max(int(round(np.sqrt(count * h / w))), 1), h // tile)
    return ny, min(max(count // ny, 1), w // tile)


def noise_tiles(codes: np.ndarray, fill: int, sites: int = FAST_PATH_SITES, tile: int = NOISE_TILE) -> np.ndarray:
    """At most ``sites`` codes of one channel (H, W), still integer: tiles of ``tile`` x
    ``tile`` spread evenly over the frame (a grid of the frame's aspect), laid side by side
    with a line of ``fill`` (a clipped code) between them, so that no window, residual or
    neighbour mean of the statistics mixes two tiles (clipping drops what touches the
    line).  The whole channel when it holds at most ``sites`` or is smaller than 2 x 2 tiles."""
    h, w = codes.shape
    grid = _grid(h, w, sites, tile)
    if grid is None:
        return codes.copy()  # not a view: it would keep the whole decoded frame alive
    ny, nx = grid
    step = tile + 1
    out = np.full((ny * step - 1, nx * step - 1), fill, codes.dtype)
    for i, y in enumerate(np.linspace(0, h - tile, ny).astype(int)):
        for j, x in enumerate(np.linspace(0, w - tile, nx).astype(int)):
            out[i * step:i * step + tile, j * step:j * step + tile] = codes[y:y + tile, x:x + tile]
    return out


def strided(codes: np.ndarray, sites: int = USABILITY_SITES) -> np.ndarray:
    """An even stride of at most about ``sites`` codes of one channel (H, W), a copy (a view
    would keep the whole decoded frame alive)."""
    step = max(1, int(np.ceil(np.sqrt(codes.size / sites))))
    return codes[::step, ::step].copy()


class DrawnChannel(NamedTuple):
    """One channel's codes drawn for merge's noise measurement (integer codes, linearised
    once the response is known)."""

    name: str
    index: int  #: the channel's index (CFA colour or image channel)
    tiles: np.ndarray  #: :func:`noise_tiles`
    drawn: int  #: sites in ``tiles`` (the separating lines not counted)
    stride: np.ndarray  #: :func:`strided`, for the usability test
    sites: int  #: sites of the whole channel


def draw_codes(frame: Frame, codes: np.ndarray, corner: np.ndarray | None = None,
               sites: int = FAST_PATH_SITES) -> list[DrawnChannel]:
    """:class:`DrawnChannel` per channel of a frame's decoded ``codes`` (a few ms at 24 MP)."""
    def pick(view, fill):
        grid = _grid(*view.shape, sites, NOISE_TILE)
        return noise_tiles(view, fill, sites), view.size if grid is None else grid[0] * grid[1] * NOISE_TILE**2, \
            strided(view), view.size

    return [DrawnChannel(name, k, *picked) for name, k, picked in channel_codes(frame, codes, corner, pick)]


class NoiseDraw:
    """``(frame, codes) ->`` keeps :func:`draw_codes` of each frame the first time it is
    decoded (the merge's exposure check decodes every frame), for
    :func:`~hdrmerge_cli.pipeline.noise.estimate_bracket_noise`: the noise needs no
    decode of its own.  Thread-safe
    (frames are decoded two at a time)."""

    def __init__(self, frames: list[Frame], sites: int = FAST_PATH_SITES):
        self.corner = cfa_corner(frames[0]) if frames and frames[0].kind == "raw" else None
        self.sites = sites
        self.drawn: dict[str, list[DrawnChannel]] = {}

    def __call__(self, frame: Frame, codes: np.ndarray) -> None:
        if frame.path not in self.drawn:
            self.drawn[frame.path] = draw_codes(frame, codes, self.corner, self.sites)
