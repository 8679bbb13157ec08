"""Image files through OpenImageIO: EXR (read and write) and 8/16-bit images with EXIF."""
from __future__ import annotations

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError


def read_exr(path: str) -> tuple[np.ndarray, dict]:
    """Float pixels ``(H, W, C)`` float32 and the header attributes of an image file."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise HdrMergeError(f"{path}: not a readable image ({oiio.geterror().strip().splitlines()[-1]})")
    try:
        spec = inp.spec()
        pixels = inp.read_image(format=oiio.FLOAT)
        attrs = {a.name: a.value for a in spec.extra_attribs}
        attrs["channelnames"] = tuple(spec.channelnames)
    finally:
        inp.close()
    if pixels is None:
        raise HdrMergeError(f"{path}: could not decode the pixels")
    return np.asarray(pixels, np.float32).reshape(spec.height, spec.width, spec.nchannels), attrs


def _set_attribute(spec, name: str, value) -> None:
    import OpenImageIO as oiio

    if isinstance(value, (list, tuple, np.ndarray)):
        vals = [float(v) for v in value]
        spec.attribute(name, oiio.TypeDesc(f"float[{len(vals)}]"), tuple(vals))
    elif isinstance(value, bool):
        spec.attribute(name, int(value))
    else:
        spec.attribute(name, value)


def write_exr(path: str, pixels, channel_names: list[str], attributes: dict, half: bool = False,
              size: tuple[int, int] | None = None) -> None:
    """Write float pixels as a zip-compressed (lossless) EXR.

    pixels : ``(H, W, C)`` (or ``(H, W)``) floats, or, with ``size = (H, W)``, an iterable
        of ``(y0, strip)`` with strips ``(rows, W, C)`` in increasing ``y0`` that together
        cover the image (so the whole image never needs to be in memory at once)
    half : store 16-bit floats (values beyond 65504 are clamped to it, with no inf)."""
    import OpenImageIO as oiio

    if size is None:
        pixels = np.asarray(pixels)
        size, pixels = pixels.shape[:2], [(0, pixels)]
    h, w = size
    spec = oiio.ImageSpec(w, h, len(channel_names), "half" if half else "float")
    spec.channelnames = tuple(channel_names)
    spec.attribute("compression", "zip")
    for key, value in attributes.items():
        _set_attribute(spec, key, value)
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise HdrMergeError(f"{path}: cannot write ({oiio.geterror().strip() or 'unknown error'})")
    try:
        for y0, strip in pixels:
            data = np.ascontiguousarray(strip, dtype=np.float32)
            if data.ndim == 2:
                data = data[..., None]
            if not np.all(np.isfinite(data)):
                raise HdrMergeError(f"{path}: refusing to write non-finite values (internal error)")
            if half:
                data = np.clip(data, -65504.0, 65504.0)
            if not out.write_scanlines(y0, y0 + data.shape[0], 0, data):
                raise HdrMergeError(f"{path}: cannot write ({out.geterror().strip() or 'unknown error'})")
    finally:
        out.close()


def write_ldr(path: str, codes: np.ndarray, exif: dict) -> None:
    """Write 8- or 16-bit ``(H, W, C)`` code values (JPEG quality 95; TIFF/PNG lossless)
    with EXIF attributes such as ``ExposureTime`` (seconds), ``FNumber``, ``Make``."""
    import OpenImageIO as oiio

    h, w, c = codes.shape
    spec = oiio.ImageSpec(w, h, c, "uint8" if codes.dtype == np.uint8 else "uint16")
    for key, value in exif.items():
        _set_attribute(spec, key, value)
    if str(path).lower().endswith((".jpg", ".jpeg")):
        spec.attribute("Compression", "jpeg:95")
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise HdrMergeError(f"{path}: cannot write ({oiio.geterror().strip() or 'unknown error'})")
    ok = out.write_image(np.ascontiguousarray(codes))
    out.close()
    if not ok:
        raise HdrMergeError(f"{path}: cannot write ({out.geterror().strip()})")
