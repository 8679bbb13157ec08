"""The Python API: merge a bracket from files or from arrays, arrays out.

``hdrmerge-cli merge`` runs the same stages (:mod:`hdrmerge_cli.pipeline.merge`); this
module only builds the options and, for arrays, the frames' metadata.

>>> import hdrmerge_cli
>>> merged = hdrmerge_cli.merge(["a.CR2", "b.CR2", "c.CR2"], align="auto")   # doctest: +SKIP
>>> merged.image.shape, merged.flags.shape                                     # doctest: +SKIP
((3456, 5184, 3), (3456, 5184))
>>> merged.write("out.exr")                                                    # doctest: +SKIP
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.frames import Frame
from hdrmerge_cli.pipeline.merge import check_options, merge_bracket, merge_frames
from hdrmerge_cli.pipeline.options import MergeOptions
from hdrmerge_cli.pipeline.output import Merged

__all__ = ["Merged", "MergeOptions", "merge", "merge_arrays"]

#: LibRaw's colour index (R 0, G 1, B 2, second green 3) of each Bayer pattern's 2 x 2 cell
_CFA_INDEX = {"RGGB": [[0, 1], [3, 2]], "BGGR": [[2, 3], [1, 0]], "GRBG": [[1, 0], [2, 3]], "GBRG": [[3, 2], [0, 1]]}


def merge(paths: Sequence[str | Path], **options) -> Merged:
    """Merge the bracket of image or RAW files ``paths`` (any order).

    Parameters
    ----------
    paths : sequence of str or Path
        The frames: RAW files (LibRaw), or 8/16-bit JPEG/TIFF/PNG; exposure times from EXIF
        unless ``times`` is given.
    **options
        The fields of :class:`MergeOptions`, as the command line takes them (``crf="srgb"``,
        ``align="auto"``, ``deghost="auto"``, ``extra_channels=("variance",)``,
        ``colorspace="acescg"`` ...); ``output`` is not needed (:meth:`Merged.write` takes it).

    Returns
    -------
    Merged
        ``.image`` (H, W, 3) float32 scene-linear (1.0 = the full-scale signal of an
        exposure of ``.h_ref`` seconds), ``.flags`` (H, W) int8 (1 saturated, -1 dark),
        ``.variance`` (with ``extra_channels=("variance",)``), ``.profile()``, ``.summary()``
        and ``.write(path)`` (EXR, or a float DNG from RAW).

    Raises
    ------
    HdrMergeError
        Unreadable or inconsistent frames, bad options (one-line message).
    """
    opts = _options(options)
    return merge_bracket([str(p) for p in paths], opts)


def merge_arrays(codes: Sequence[np.ndarray], exposure_times: Sequence[float], *, crf: str | CRF = "srgb",
                 cfa_pattern: str | None = None, black: float = 0.0, white: float | None = None,
                 bits: int | None = None, **options) -> Merged:
    """Merge decoded frames held in memory.

    Parameters
    ----------
    codes : sequence of arrays, all of one shape and dtype
        The stored code values of each frame: ``(H, W, 3)`` or ``(H, W)`` uint8/uint16
        camera-processed images (through the response ``crf``), or, with ``cfa_pattern``,
        ``(H, W)`` uint16 Bayer mosaics of linear sensor data.
    exposure_times : sequence of float
        Each frame's exposure in seconds (or any unit proportional to the light collected).
    crf : str or CRF
        The images' camera response: ``"srgb"``, ``"linear"``, ``"gamma:2.2"``, a CSV table
        or profile JSON path, or a :class:`~hdrmerge_cli.core.crf.CRF`; ignored for mosaics
        (linear).
    cfa_pattern : str, optional
        The mosaic's 2 x 2 colour filter: ``"RGGB"``, ``"BGGR"``, ``"GRBG"`` or ``"GBRG"``.
    black, white : float
        The code values of no light and of clipping (default: 0 and the dtype's maximum,
        or ``2**bits - 1``).
    bits : int, optional
        Significant bits of the codes (default: the dtype's).
    **options
        As for :func:`merge`.

    Returns
    -------
    Merged
        As :func:`merge`.  Mosaics have as-shot white balance 1 and the identity camera
        matrix (native camera RGB is taken as linear Rec.709).
    """
    arrays = [np.asarray(c) for c in codes]
    times = [float(t) for t in exposure_times]
    if not arrays:
        raise HdrMergeError("no input frames given")
    if len(times) != len(arrays):
        raise HdrMergeError(f"{len(arrays)} frames but {len(times)} exposure times")
    first = arrays[0]
    for k, a in enumerate(arrays):
        if a.shape != first.shape or a.dtype != first.dtype:
            raise HdrMergeError(f"frame {k}: {a.dtype} {a.shape} differs from frame 0's {first.dtype} {first.shape}")
        if not np.isfinite(times[k]) or times[k] <= 0:
            raise HdrMergeError(f"frame {k}: exposure time {times[k]!r} is not a positive number")
    if first.dtype not in (np.uint8, np.uint16):
        raise HdrMergeError(f"codes must be uint8 or uint16, not {first.dtype}")
    container = 8 * first.dtype.itemsize
    bits = bits or container
    white = float(white if white is not None else (2**bits - 1))
    if not black < white:
        raise HdrMergeError(f"white level {white:g} is not above the black level {black:g}")
    order = np.argsort(times, kind="stable")
    arrays, times = [arrays[i] for i in order], [times[i] for i in order]
    frames = [_frame(f"<array {order[k]}>", a, t, cfa_pattern, black, white, bits, container)
              for k, (a, t) in enumerate(zip(arrays, times))]
    grey = frames[0].kind == "image" and first.ndim == 2  # decoded images are (H, W, C)
    by_path = {f.path: a[..., None] if grey else a for f, a in zip(frames, arrays)}
    options.setdefault("noise_cache", False)  # no camera to key a cache entry by
    opts = _options(options)
    if frames[0].kind == "raw":
        response = CRF("linear")
    elif isinstance(crf, CRF):
        response = crf
    else:
        from hdrmerge_cli.pipeline.bracket import choose_crf

        response = choose_crf(frames, crf, warn=False)  # none given: merge_frames measures it
    return merge_frames(frames, response, opts, load=lambda f: by_path[f.path])


def _options(options: dict) -> MergeOptions:
    """The checked :class:`MergeOptions` of the API's keywords.  Times may be numbers
    (seconds) or text as on the command line: ``reference=0.01`` or ``"1/100"``,
    ``times=[0.01, 0.04]``, ``"1/100,1/25"`` or ``"estimate"``."""
    from hdrmerge_cli.io.times import ESTIMATE, parse_times, seconds

    times = options.get("times")
    if isinstance(times, str):
        options["times"] = ESTIMATE if times.strip().lower() == ESTIMATE else parse_times(times)
    elif times is not None:
        try:
            options["times"] = [seconds(t) for t in times]
        except (HdrMergeError, TypeError) as exc:
            raise HdrMergeError(f"times: {exc}") from None
    opts = MergeOptions(**options)
    check_options(opts)
    return opts


def _frame(name: str, a: np.ndarray, t: float, cfa_pattern: str | None, black: float, white: float, bits: int,
           container: int) -> Frame:
    h, w = a.shape[:2]
    common = dict(path=name, width=w, height=h, exposure_time=t, iso=None, aperture=None, make="", model="",
                  timestamp=None, bits=bits, n_codes=2**container)
    if cfa_pattern is not None:
        if cfa_pattern not in _CFA_INDEX:
            raise HdrMergeError(f"unsupported colour filter pattern {cfa_pattern!r} (choose from {', '.join(_CFA_INDEX)})")
        if a.ndim != 2 or h % 2 or w % 2:
            raise HdrMergeError(f"a Bayer mosaic is an (H, W) array of even sides, not {a.shape}")
        return Frame(**common, kind="raw", black=np.full(4, black), white=np.full(4, white), channels=4,
                     cfa_pattern=cfa_pattern, channel_colors="RGBG",
                     cfa_cell=np.array(_CFA_INDEX[cfa_pattern], np.intp))
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (1, 3)):
        raise HdrMergeError(f"an image is (H, W) or (H, W, 3), not {a.shape} (give cfa_pattern for a mosaic)")
    channels = 1 if a.ndim == 2 else a.shape[2]
    return Frame(**common, kind="image", black=np.full(channels, black), white=np.full(channels, white),
                 channels=channels, channel_colors="RGB" if channels == 3 else "Y")
