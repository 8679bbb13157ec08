"""Image files through OpenImageIO: EXR (read and write) and 8/16-bit images with EXIF."""
from __future__ import annotations

import os

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


def read_header(path: str) -> tuple[int, int, int, str]:
    """(width, height, channels, sample type: ``uint8``, ``uint16``, ``half``, ``float``...)
    of an image file, from its header alone."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        reason = (oiio.geterror().strip() or "unknown error").splitlines()[-1]
        raise HdrMergeError(f"{path}: not a readable image ({reason})")
    spec = inp.spec()
    inp.close()
    return spec.width, spec.height, spec.nchannels, str(spec.format)


def _set_attribute(spec, name: str, value) -> None:
    import OpenImageIO as oiio

    if isinstance(value, (list, tuple, np.ndarray)):
        vals = [float(v) for v in value]
        spec.attribute(name, oiio.TypeDesc(f"float[{len(vals)}]"), tuple(vals))
    elif isinstance(value, bool):
        spec.attribute(name, int(value))
    else:
        spec.attribute(name, value)


#: OpenEXR compressions (``merge --compression``): name -> what it does to float / half data.
#: The noise in a merged image's low mantissa bits leaves lossless codecs little to gain on
#: float data at many times the write time, so ``auto`` writes float uncompressed and half
#: with zips (write times and sizes: benchmarks/results/speed.md).
EXR_COMPRESSIONS = {
    "auto": "none for float, zips for --half (lossless; the best write time against size measured)",
    "none": "uncompressed",
    "rle": "run-length (lossless)",
    "zips": "deflate per scanline (lossless)",
    "zip": "deflate per 16 scanlines (lossless)",
    "piz": "wavelet + Huffman (lossless)",
    "pxr24": "float rounded to 24 bits (lossy for float, lossless for half)",
    "b44": "4x4 blocks (lossy, half only; float stays uncompressed)",
    "b44a": "b44, flat areas smaller (lossy, half only)",
    "dwaa": "DCT, 32 scanlines (lossy)",
    "dwab": "DCT, 256 scanlines (lossy)",
    "htj2k256": "High-Throughput JPEG 2000 (lossless; needs OpenEXR 3.4+ to read)",
}


def exr_compression(name: str, half: bool) -> str:
    """The OpenEXR compression that ``name`` (a key of :data:`EXR_COMPRESSIONS`) means."""
    if name not in EXR_COMPRESSIONS:
        raise HdrMergeError(f"unknown EXR compression {name!r} (choose from {', '.join(EXR_COMPRESSIONS)})")
    if name == "auto":
        return "zips" if half else "none"
    return name


def _exr_threads() -> int:
    """Threads for OpenEXR's compression pool: the cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def write_exr(path: str, pixels, channel_names: list[str], attributes: dict, half: bool = False,
              size: tuple[int, int] | None = None, compression: str = "auto") -> None:
    """Write float pixels as an EXR (``compression``: see :data:`EXR_COMPRESSIONS`;
    OpenEXR compresses the blocks of each strip on its thread pool, one thread per core).

    pixels : ``(H, W, C)`` (or ``(H, W)``) floats, or, with ``size = (H, W)``, an iterable
        of ``(y0, strip)`` with strips ``(rows, W, C)`` in increasing ``y0`` that together
        cover the image (so the whole image never needs to be in memory at once)
    half : store 16-bit floats (values beyond 65504 are clamped to it, with no inf)."""
    import OpenImageIO as oiio

    codec = exr_compression(compression, half)
    oiio.attribute("exr_threads", _exr_threads())
    if size is None:
        pixels = np.asarray(pixels)
        size, pixels = pixels.shape[:2], [(0, pixels)]
    h, w = size
    spec = oiio.ImageSpec(w, h, len(channel_names), "half" if half else "float")
    spec.channelnames = tuple(channel_names)
    spec.attribute("compression", codec)
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
