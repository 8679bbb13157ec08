"""Writing a merged CFA mosaic as a floating-point DNG (DNG 1.4) that raw editors open.

:func:`write_float_dng` lays the file out as DNG writers do (Adobe DNG Converter,
HDRMerge): IFD0 is a small RGB thumbnail (NewSubfileType 1) carrying the DNG and TIFF/EP
tags that describe the whole file (versions, camera, colour, white balance, EXIF-like
shooting data); its SubIFDs hold the raw CFA mosaic (NewSubfileType 0: 16-, 24- or 32-bit
IEEE floats, tiled, Deflate with the floating-point predictor) and, when a preview is
given, that preview as a JPEG (NewSubfileType 1).  The TIFF structure is written by
tifffile, Deflate and the predictor by imagecodecs; 24-bit floats, which no NumPy type
holds, are encoded here (:func:`_fp24`; imagecodecs' encoder mis-rounds) with the
floating-point predictor's byte regrouping (:func:`_fp_predict`, checked against imagecodecs'
for 32 bits) and zlib from imagecodecs.

What the readers need, beyond the DNG specification:

* LibRaw (rawpy, RawTherapee's DNG path shares its float decoder) reads a tiled float DNG
  only when a tile is no larger than the image: a single tile padded past the image edge
  (as HDRMerge writes small images) makes it treat the data as untiled and fail with
  "Corrupted data".  Tiles are therefore at most the image size, multiples of 16 as TIFF
  requires; an image under 16 pixels in a dimension is written in strips.
* RawTherapee 5.9 (Debian 12) opens only 32-bit Deflate float DNGs, renders one whose raw
  is a single tile (or strips) all black with exit 0 (an HDRMerge DNG of that size too), so
  :func:`_tiling` makes at least two tiles, and refuses some small ones ("Error loading
  file": 128 x 192, 192 x 128 and 192 x 160 pixels; 176 x 176 and 128 x 256 open); its
  uncompressed-float path needs the raw in IFD0 alone (with a thumbnail IFD it renders
  black).  darktable 4.2 (rawspeed) reads 16/24/32 bits, Deflate or not; LibRaw
  (rawpy 0.28) all of them too.  Hence the default: 32 bits, Deflate, Predictor 3.
* Shooting data (ExposureTime, FNumber, ISOSpeedRatings) go in IFD0 as TIFF/EP tags:
  tifffile writes no EXIF IFD, and LibRaw reads ISO only from one (exposure and aperture
  it reads from IFD0).
* WhiteLevel is a whole number (SHORT/LONG in the specification): the mosaic's values
  are stored as given, so ``white_level`` must be a positive whole number; values above it
  are clipped by raw editors, so pass the mosaic's maximum (or more) when it exceeds 1.
"""
from __future__ import annotations

import datetime as _dt
import math
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError

#: DNG CFAPattern codes of CFAPlaneColor (0 = red, 1 = green, 2 = blue)
_CFA_CODES = {"R": 0, "G": 1, "B": 2}
#: TIFF tag data types (tifffile's codes)
_BYTE, _ASCII, _SHORT, _LONG, _RATIONAL, _SRATIONAL = 1, 2, 3, 4, 5, 10
#: largest finite half-precision value
_HALF_MAX = 65504.0
#: XYZ (D65) -> linear sRGB, for the thumbnail made when no preview is given
_XYZ_TO_SRGB = np.array([[3.2404542, -1.5371385, -0.4985314],
                         [-0.9692660, 1.8760108, 0.0415560],
                         [0.0556434, -0.2040259, 1.0572252]])
_THUMB_SIZE = 256
_TILE = 256
_PREDICTOR = 3


def write_float_dng(path, mosaic, *, cfa_pattern: str, xyz_to_camera, as_shot_neutral, make: str, model: str,
                    exposure_time: float | None, iso: float | None = None, aperture: float | None = None,
                    baseline_exposure: float = 0.0, orientation: int = 1, preview=None, bits: int = 32,
                    compression: str = "deflate", white_level: float = 1.0, software: str | None = None,
                    datetime: _dt.datetime | str | None = None, deflate_level: int = 6) -> None:
    """Write a scene-linear CFA mosaic as a floating-point DNG 1.4.

    Parameters
    ----------
    path : str or os.PathLike
        Where to write (the caller makes it atomic: a temporary name, then a rename).
    mosaic : (H, W) array of float
        Scene-linear CFA data, black 0, ``white_level`` = white (the clipping point raw
        editors use); finite.  Stored as given, rounded to ``bits``.
    cfa_pattern : str
        Colours of the 2 x 2 CFA cell in reading order, e.g. ``"RGGB"`` (LibRaw's colours,
        as :attr:`Frame.cfa_pattern` holds them).
    xyz_to_camera : (3, 3) array
        The DNG ColorMatrix1: XYZ (D65) -> camera RGB (LibRaw's ``rgb_xyz_matrix[:3, :3]``,
        :attr:`Frame.xyz_to_camera`); stored with CalibrationIlluminant1 = D65 (21).
    as_shot_neutral : (3,) array
        Camera RGB of a neutral (white) object, any scale (stored normalised to green 1);
        e.g. the reciprocal of the white-balance multipliers.
    make, model : str
        Camera make and model (also give UniqueCameraModel).
    exposure_time : float or None
        The reference exposure in seconds (EXIF ExposureTime); ``iso``, ``aperture``
        (f-number) likewise, each omitted when None.
    baseline_exposure : float
        DNG BaselineExposure in EV: how far raw editors brighten the default rendering.
    orientation : int
        EXIF orientation (1-8) of the whole image.
    preview : (h, w, 3) uint8 array, optional
        An sRGB rendering.  Written as a JPEG preview SubIFD, and downscaled to the IFD0
        thumbnail; without it the thumbnail is a rough rendering of the mosaic.
    bits : 16, 24 or 32
        Float sample size.  16 = IEEE half (range 6e-5 .. 65504 at full precision: keep
        ``white_level`` within it); 24 = DNG's 24-bit float (16-bit mantissa, needs
        Deflate with the floating-point predictor, as DNG 1.4 specifies); 32 = single.
    compression : "deflate" or "none"
        Deflate uses the floating-point predictor (TIFF Predictor 3), which LibRaw,
        rawspeed (darktable) and RawTherapee decode.
    white_level : float
        WhiteLevel, a positive whole number in the mosaic's units.
    software : str, optional
        The Software tag (default "hdrmerge-cli <version>").
    datetime : datetime or "YYYY:MM:DD HH:MM:SS", optional
        DateTime and DateTimeOriginal (of the shot); omitted when None.
    deflate_level : int
        zlib level 1-9.

    Raises
    ------
    HdrMergeError
        Invalid arguments or data, or the file could not be written (a one-line message
        starting with the path).
    """
    where = os.fspath(path)
    _require_codecs(where)
    mosaic, cfa, matrix, neutral, white = _check(where, mosaic, cfa_pattern, xyz_to_camera, as_shot_neutral,
                                                 bits, compression, white_level, orientation)
    preview, thumb = _preview_and_thumbnail(where, preview, mosaic, cfa, matrix, neutral, white, baseline_exposure)
    if software is None:
        from hdrmerge_cli._version import __version__
        software = f"hdrmerge-cli {__version__}"
    stamp = _stamp(where, datetime)
    try:
        _write(where, mosaic, cfa=cfa, matrix=matrix, neutral=neutral, white=white, make=make, model=model,
               exposure_time=exposure_time, iso=iso, aperture=aperture, baseline_exposure=baseline_exposure,
               orientation=orientation, thumb=thumb, preview=preview, bits=bits, compression=compression,
               software=software, stamp=stamp, level=deflate_level)
    except HdrMergeError:
        raise
    except OSError as exc:
        raise HdrMergeError(f"{where}: cannot write the DNG ({exc.strerror or exc})") from None
    except (ValueError, TypeError, RuntimeError) as exc:  # tifffile/imagecodecs refusing the data
        raise HdrMergeError(f"{where}: cannot write the DNG ({' '.join(str(exc).split())})") from None



def _require_codecs(where: str) -> None:
    """Refuse, naming ``where``, to write a DNG when tifffile or imagecodecs is not installed."""
    try:
        import tifffile  # noqa: F401  (a missing package is reported like any other failure)
        import imagecodecs  # noqa: F401
    except ImportError as exc:
        raise HdrMergeError(f"{where}: cannot write a DNG: {exc.name} is not installed "
                            f"(pip install tifffile imagecodecs)") from None


def _preview_and_thumbnail(where: str, preview, mosaic: np.ndarray, cfa: str, matrix: np.ndarray,
                           neutral: np.ndarray, white: int, baseline_exposure: float) -> tuple:
    """The checked preview ((h, w, 3) uint8, or None) and the IFD0 thumbnail ((h', w', 3) uint8)."""
    if preview is None:
        return None, _rough_thumbnail(mosaic, cfa, matrix, neutral, white, baseline_exposure)
    preview = np.asarray(preview)
    if preview.ndim != 3 or preview.shape[2] != 3 or preview.dtype != np.uint8 or min(preview.shape[:2]) < 1:
        raise HdrMergeError(f"{where}: the DNG preview must be an (h, w, 3) uint8 image, "
                            f"not {preview.dtype} {preview.shape}")
    return preview, _downscale(preview, _THUMB_SIZE)

def _check(where, mosaic, cfa_pattern, xyz_to_camera, as_shot_neutral, bits, compression, white_level,
           orientation):
    mosaic = np.asarray(mosaic)
    if mosaic.ndim != 2 or min(mosaic.shape) < 2 or mosaic.dtype.kind not in "fiu":
        raise HdrMergeError(f"{where}: a DNG mosaic must be a 2-D numeric array of at least 2 x 2, "
                            f"not {mosaic.dtype} {mosaic.shape}")
    mosaic = mosaic.astype(np.float32, copy=False)
    if not np.isfinite(mosaic).all():
        raise HdrMergeError(f"{where}: the mosaic has non-finite values (NaN or infinity), "
                            "which a DNG cannot carry")
    cfa = str(cfa_pattern).upper()
    if len(cfa) != 4 or set(cfa) - set(_CFA_CODES) or set(cfa) != {"R", "G", "B"}:
        raise HdrMergeError(f"{where}: CFA pattern {cfa_pattern!r} is not a 2 x 2 RGB Bayer cell such as 'RGGB'")
    matrix = np.asarray(xyz_to_camera, dtype=np.float64)
    if matrix.shape != (3, 3) or not np.isfinite(matrix).all() or abs(np.linalg.det(matrix)) < 1e-12:
        raise HdrMergeError(f"{where}: the colour matrix (XYZ -> camera) must be an invertible, finite 3 x 3 "
                            f"matrix, not {np.array2string(matrix.ravel(), precision=4)}")
    neutral = np.asarray(as_shot_neutral, dtype=np.float64).ravel()
    if neutral.shape != (3,) or not np.isfinite(neutral).all() or neutral.min() <= 0:
        raise HdrMergeError(f"{where}: the as-shot neutral must be 3 positive numbers, not {neutral.tolist()}")
    neutral = neutral / neutral[1]
    if bits not in (16, 24, 32):
        raise HdrMergeError(f"{where}: a float DNG has 16-, 24- or 32-bit samples, not {bits}")
    if compression not in ("deflate", "none"):
        raise HdrMergeError(f"{where}: DNG compression must be 'deflate' or 'none', not {compression!r}")
    if bits == 24 and compression != "deflate":
        raise HdrMergeError(f"{where}: 24-bit float DNG data must be Deflate-compressed "
                            "(DNG 1.4 allows 24-bit floats only with the floating-point predictor)")
    white = float(white_level)
    if not (math.isfinite(white) and white >= 1 and white == round(white) and white < 2 ** 32):
        raise HdrMergeError(f"{where}: the DNG white level must be a positive whole number, not {white_level!r} "
                            "(scale the mosaic instead)")
    if bits == 16 and max(white, float(np.abs(mosaic).max(initial=0.0))) > _HALF_MAX:
        raise HdrMergeError(f"{where}: values above {_HALF_MAX:g} do not fit 16-bit floats; "
                            "use 24 or 32 bits or scale the mosaic")
    if orientation not in range(1, 9):
        raise HdrMergeError(f"{where}: EXIF orientation must be 1 to 8, not {orientation!r}")
    return mosaic, cfa, matrix, neutral, int(white)


def _stamp(where, value) -> str | None:
    if value is None:
        return None
    if isinstance(value, _dt.datetime):
        return value.strftime("%Y:%m:%d %H:%M:%S")
    text = str(value)
    for fmt in ("%Y:%m:%d %H:%M:%S", "%Y-%m-%dT%H:%M:%S", "%Y-%m-%d %H:%M:%S"):
        try:
            return _dt.datetime.strptime(text[:19], fmt).strftime("%Y:%m:%d %H:%M:%S")
        except ValueError:
            pass
    raise HdrMergeError(f"{where}: date {value!r} is not 'YYYY:MM:DD HH:MM:SS' or ISO 8601")


def _rational(values, signed: bool, denominator: int = 10000) -> tuple:
    out = []
    for v in np.ravel(values):
        num = int(round(float(v) * denominator))
        if not signed:
            num = max(num, 0)
        out += [num, denominator]
    return tuple(out)


def _exposure_rational(t: float) -> tuple:
    """Exposure time as EXIF writes it: 1/250 s as (1, 250), 2.5 s as (25, 10)."""
    if t < 1:
        return (1, int(round(1 / t))) if abs(1 / t - round(1 / t)) < 1e-3 * (1 / t) else (int(round(t * 1e6)), 1000000)
    return int(round(t * 1000)), 1000


def _tiling(height: int, width: int) -> tuple | None:
    """Tile shape: at most 256 x 256 and never larger than the image (LibRaw reads a tile
    larger than the image as untiled data), multiples of 16 (TIFF), and at least two tiles
    from 128 x 128 up (RawTherapee 5.9 renders a float DNG of one tile, or of strips, all
    black; below that it opens none, and LibRaw fails on some small tiles, e.g. 16-bit
    64 x 48); None = strips."""
    if height < 16 or width < 16:
        return None
    th, tw = min(_TILE, height // 16 * 16), min(_TILE, width // 16 * 16)
    if th >= height and tw >= width and min(height, width) >= 128:  # one tile: halve the longer side
        if height >= width:
            th = height // 2 // 16 * 16
        else:
            tw = width // 2 // 16 * 16
    return th, tw


def _write(where, mosaic, *, cfa, matrix, neutral, white, make, model, exposure_time, iso, aperture,
           baseline_exposure, orientation, thumb, preview, bits, compression, software, stamp, level):
    import tifffile

    make, model = str(make or "").strip(), str(model or "").strip()
    unique = model if make and model.lower().startswith(make.lower()) else f"{make} {model}".strip()
    ifd0 = [  # (code, dtype, count, value, writeonce)
        (50706, _BYTE, 4, (1, 4, 0, 0), True),  # DNGVersion 1.4 (floating point needs 1.4)
        (50707, _BYTE, 4, (1, 4, 0, 0), True),  # DNGBackwardVersion
        (50708, _ASCII, 0, unique or "hdrmerge-cli", True),  # UniqueCameraModel
        (50721, _SRATIONAL, 9, _rational(matrix, signed=True), True),  # ColorMatrix1
        (50778, _SHORT, 1, 21, True),  # CalibrationIlluminant1 = D65
        (50728, _RATIONAL, 3, _rational(neutral, signed=False, denominator=1000000), True),  # AsShotNeutral
        (50730, _SRATIONAL, 1, _rational([baseline_exposure], signed=True, denominator=100), True),
        (274, _SHORT, 1, int(orientation), True),  # Orientation
        (37398, _BYTE, 4, (1, 0, 0, 0), True),  # TIFF/EPStandardID
    ]
    if make:
        ifd0.append((271, _ASCII, 0, make, True))
    if model:
        ifd0.append((272, _ASCII, 0, model, True))
    # shooting data as TIFF/EP tags in IFD0 (where TIFF/EP and DNG put them; LibRaw, exiv2 read them there)
    if exposure_time is not None and exposure_time > 0:
        ifd0.append((33434, _RATIONAL, 1, _exposure_rational(float(exposure_time)), True))
    if aperture is not None and aperture > 0:
        ifd0.append((33437, _RATIONAL, 1, (int(round(aperture * 100)), 100), True))
    if iso is not None and iso > 0:
        ifd0.append((34855, _SHORT, 1, min(int(round(iso)), 65535), True))
    if stamp:
        ifd0.append((36867, _ASCII, 0, stamp, True))  # DateTimeOriginal
    cfa_codes = tuple(_CFA_CODES[c] for c in cfa)
    raw_tags = [
        (33421, _SHORT, 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, _BYTE, 4, cfa_codes, True),  # CFAPattern
        (50710, _BYTE, 3, (0, 1, 2), True),  # CFAPlaneColor
        (50711, _SHORT, 1, 1, True),  # CFALayout: rectangular
        (50714, _LONG, 1, 0, True),  # BlackLevel
        (50717, _LONG, 1, white, True),  # WhiteLevel
        (50719, _LONG, 2, (0, 0), True),  # DefaultCropOrigin
        (50720, _LONG, 2, (mosaic.shape[1], mosaic.shape[0]), True),  # DefaultCropSize
    ]
    height, width = mosaic.shape
    tile = _tiling(height, width)
    deflate = compression == "deflate"
    raw_args = dict(photometric=tifffile.PHOTOMETRIC.CFA, subfiletype=0, extratags=raw_tags, metadata=None,
                    planarconfig="contig")
    if tile is not None:
        raw_args["tile"] = tile
    else:
        raw_args["rowsperstrip"] = height
    if deflate:
        raw_args.update(compression="adobe_deflate", compressionargs={"level": int(level)},
                        predictor=_PREDICTOR, maxworkers=min(4, os.cpu_count() or 1))
    if bits == 24:  # no NumPy type: encode the chunks here, then mark the samples as 24-bit
        data = iter(_fp24_chunks(mosaic, tile, int(level)))
        raw_args.update(shape=mosaic.shape, dtype=np.float32)
    else:
        data = mosaic.astype(np.float16 if bits == 16 else np.float32, copy=False)

    with tifffile.TiffWriter(where, byteorder="<", bigtiff=False) as tw:
        tw.write(thumb, photometric="rgb", subfiletype=1, subifds=1 if preview is None else 2, software=software,
                 datetime=stamp, extratags=ifd0, metadata=None, description=None, compression=None,
                 planarconfig="contig")
        tw.write(data, **raw_args)
        if preview is not None:
            tw.write(preview, photometric="rgb", subfiletype=1, compression="jpeg", compressionargs={"level": 90}, metadata=None,
                     planarconfig="contig", rowsperstrip=preview.shape[0],
                     extratags=[(50970, _LONG, 1, 2, True)])  # PreviewColorSpace: sRGB
    if bits == 24:
        _mark_24_bit(where)


def _mark_24_bit(where):
    """Set the raw SubIFD's BitsPerSample to 24 in place (tifffile writes the 24-bit
    chunks encoded here under a float32 shape, which it cannot label otherwise)."""
    import tifffile

    with tifffile.TiffFile(where, mode="r+b") as tif:
        raw = tif.pages.first.pages[0]
        raw.tags[258].overwrite(24)


def _fp24(values: np.ndarray) -> np.ndarray:
    """float32 -> DNG's 24-bit float (sign, 7-bit exponent biased by 63, 16-bit mantissa)
    as (..., 3) bytes, most significant first: rounded to nearest even (a mantissa that
    rounds up past all ones carries into the exponent, which imagecodecs' FLOAT24 encoder
    gets wrong: 0.0624999 comes out as 0.03125); magnitudes below 2^-62 become 0 and
    above the largest 24-bit float that largest value."""
    bits32 = np.ascontiguousarray(values, dtype=np.float32).view(np.uint32)
    sign = (bits32 >> 8) & 0x800000
    magnitude = (bits32 & 0x7FFFFFFF).astype(np.int64)
    magnitude += 0x3F + ((magnitude >> 7) & 1)  # round the 7 dropped bits, ties to even
    exponent = (magnitude >> 23) - 64  # float32 bias 127 -> 24-bit bias 63
    word = ((magnitude >> 7) & 0xFFFF) | (np.clip(exponent, 0, 126) << 16)
    word = np.where(exponent <= 0, 0, np.where(exponent >= 127, 0x7EFFFF, word)).astype(np.uint32) | sign
    return np.stack([(word >> 16) & 0xFF, (word >> 8) & 0xFF, word & 0xFF], axis=-1).astype(np.uint8)


def _fp_predict(rows: np.ndarray) -> np.ndarray:
    """TIFF's floating-point predictor (Predictor 3, one sample per pixel) on (..., n, B)
    big-endian sample bytes: each row's bytes regrouped most significant first, then
    differenced byte by byte."""
    planes = np.swapaxes(rows, -1, -2).reshape(*rows.shape[:-2], -1)
    out = planes.copy()
    out[..., 1:] = np.diff(planes, axis=-1)  # uint8 arithmetic wraps modulo 256
    return out


def _fp24_chunks(mosaic: np.ndarray, tile, level: int) -> list:
    """Deflated, predicted 24-bit float tiles (or the single strip) in TIFF order."""
    import imagecodecs

    height, width = mosaic.shape
    th, tw = tile if tile is not None else (height, width)
    ny, nx = -(-height // th), -(-width // tw)
    chunks = []
    for ty in range(ny):
        for tx in range(nx):
            block = mosaic[ty * th:(ty + 1) * th, tx * tw:(tx + 1) * tw]
            if block.shape != (th, tw):  # edge tiles are padded to the full tile (TIFF)
                block = np.pad(block, ((0, th - block.shape[0]), (0, tw - block.shape[1])))
            chunks.append(block)

    def encode(block):
        return imagecodecs.zlib_encode(np.ascontiguousarray(_fp_predict(_fp24(block))), level=level)

    with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        return list(pool.map(encode, chunks))


def _downscale(image: np.ndarray, size: int) -> np.ndarray:
    """Box-filter an (h, w, 3) uint8 image so that its long side is at most ``size``."""
    h, w = image.shape[:2]
    k = max(1, math.ceil(max(h, w) / size))
    if k == 1:
        return np.ascontiguousarray(image)
    hh, ww = max(1, h // k), max(1, w // k)
    block = image[:hh * k, :ww * k].astype(np.float32).reshape(hh, k, ww, k, 3).mean(axis=(1, 3))
    return np.clip(np.rint(block), 0, 255).astype(np.uint8)


def _rough_thumbnail(mosaic, cfa, xyz_to_camera, neutral, white, baseline_exposure) -> np.ndarray:
    """A small sRGB rendering of the mosaic for IFD0 when no preview is given: 2 x 2
    cells to camera RGB, white balanced, through the colour matrix to sRGB, exposed so the
    median lands at 18 % grey (at most to white) plus the baseline exposure."""
    h2, w2 = mosaic.shape[0] // 2, mosaic.shape[1] // 2
    cells = mosaic[:h2 * 2, :w2 * 2].reshape(h2, 2, w2, 2)
    cam = np.zeros((h2, w2, 3), np.float64)
    for i, c in enumerate(cfa):
        cam[..., _CFA_CODES[c]] += cells[:, i // 2, :, i % 2]
    cam[..., 1] /= 2
    k = max(1, math.ceil(max(h2, w2) / _THUMB_SIZE))
    hh, ww = max(1, h2 // k), max(1, w2 // k)
    cam = cam[:hh * k, :ww * k].reshape(hh, k, ww, k, 3).mean(axis=(1, 3))
    camera_to_srgb = _XYZ_TO_SRGB @ np.linalg.inv(xyz_to_camera) @ np.diag(neutral)
    camera_to_srgb /= camera_to_srgb.sum(axis=1, keepdims=True)  # neutral -> grey
    rgb = (cam / neutral) @ camera_to_srgb.T
    luma = np.median(rgb.mean(axis=2))
    gain = (0.18 / luma if luma > 0 else 1.0 / white) * 2.0 ** baseline_exposure
    rgb = np.clip(rgb * min(gain, 1e6), 0, 1)
    srgb = np.where(rgb <= 0.0031308, 12.92 * rgb, 1.055 * rgb ** (1 / 2.4) - 0.055)
    return np.clip(np.rint(srgb * 255), 0, 255).astype(np.uint8)
