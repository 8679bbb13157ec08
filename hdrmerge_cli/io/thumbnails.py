"""Small grey thumbnails of frames, read cheaply, for comparing frames' content."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from hdrmerge_cli.io.frames import Frame, quiet_c_stderr, load_codes

#: the exponent that encodes linear data like a camera's JPEG (so that one pair of
#: well-exposed bounds fits every kind of frame)
LINEAR_ENCODING = 1 / 2.2


def thumbnail_shape(frame: Frame, long_side: int) -> tuple[int, int]:
    """``(rows, columns)`` of a thumbnail whose longer side is ``long_side`` pixels (or the
    frame's own size, if smaller), in the frame's stored orientation."""
    h, w = frame.height, frame.width
    scale = min(1.0, long_side / max(h, w, 1))
    return max(1, round(h * scale)), max(1, round(w * scale))


def read_thumbnail(frame: Frame, shape: tuple[int, int]) -> np.ndarray:
    """The frame's brightness, area-averaged to ``shape`` (stored orientation), float32 in
    [0, 1] of full scale: a camera-encoded image's grey codes, linear data raised to
    :data:`LINEAR_ENCODING`.  JPEGs are decoded at 1/8 size; a RAW file's embedded JPEG
    preview is used when it has one, else its mosaic (2 x 2 cells summed).  Raises
    HdrMergeError (the frame's path and the reason) when the pixels cannot be read."""
    import cv2

    grey = None
    if frame.kind == "image" and frame.path.lower().endswith((".jpg", ".jpeg")):
        try:
            grey = _reduced_jpeg(Path(frame.path).read_bytes())
        except OSError:
            pass  # load_codes says why
    elif frame.kind == "raw":
        grey = _raw_preview(frame.path)
    if grey is None:
        grey = _from_codes(frame)
    return np.clip(cv2.resize(grey, shape[::-1], interpolation=cv2.INTER_AREA), 0.0, 1.0)


def _reduced_jpeg(data: bytes) -> np.ndarray | None:
    """A JPEG's grey codes / 255 decoded at 1/8 size (libjpeg's DCT scaling), or None."""
    import cv2

    flags = cv2.IMREAD_REDUCED_GRAYSCALE_8 | cv2.IMREAD_IGNORE_ORIENTATION
    try:
        with quiet_c_stderr():
            img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error:
        return None
    if img is None or img.ndim != 2 or img.dtype != np.uint8:
        return None
    return img.astype(np.float32) / 255


def _raw_preview(path: str) -> np.ndarray | None:
    """A RAW file's embedded JPEG preview as :func:`_reduced_jpeg`, or None."""
    import rawpy

    try:
        with quiet_c_stderr(), rawpy.imread(path) as raw:
            thumb = raw.extract_thumb()
    except (rawpy.LibRawError, OSError):
        return None
    if thumb.format != rawpy.ThumbFormat.JPEG:
        return None
    return _reduced_jpeg(thumb.data)


def _from_codes(frame: Frame) -> np.ndarray:
    codes = load_codes(frame)
    if frame.kind == "raw":
        mosaic = codes.astype(np.float32) - np.float32(np.mean(frame.black))
        h, w = mosaic.shape[0] // 2 * 2, mosaic.shape[1] // 2 * 2
        cells = mosaic[:h:2, :w:2] + mosaic[1:h:2, :w:2] + mosaic[:h:2, 1:w:2] + mosaic[1:h:2, 1:w:2]
        scale = 4 * float(np.max(frame.white) - np.mean(frame.black))
        return np.clip(cells / scale, 0, 1) ** LINEAR_ENCODING
    grey = codes.astype(np.float32).mean(axis=2) / np.float32(np.max(frame.white))
    return grey ** LINEAR_ENCODING if frame.kind == "linear" else grey
