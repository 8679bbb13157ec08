"""Writing a merged CFA mosaic as a floating-point DNG (DNG 1.4) that raw editors open.

:func:`write_float_dng` lays the file out as DNG writers do (Adobe DNG Converter,
HDRMerge): IFD0 is a small RGB thumbnail (NewSubfileType 1) carrying the DNG and TIFF/EP
tags that describe the whole file (versions, camera, colour, white balance, EXIF-like
shooting data); its SubIFDs hold the raw CFA mosaic (NewSubfileType 0: 16- or 32-bit
IEEE floats, tiled, Deflate with the floating-point predictor) and
that preview as a JPEG (NewSubfileType 1).  The TIFF structure is written by tifffile,
Deflate and the predictor by imagecodecs.

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
  (rawpy 0.28) all of them too.  Hence 32 bits (``--half``: 16), Deflate, Predictor 3.
* Shooting data (ExposureTime, FNumber, ISOSpeedRatings, DateTimeOriginal) go in an
  EXIF IFD, where EXIF puts them and LibRaw reads ISO; tifffile writes no EXIF IFD, so
  :func:`_add_exif` appends one after the file is written and points IFD0's ExifTag at
  it, and gives IFD0's SubIFDs the LONG type the TIFF note on SubIFDs and DNG writers use
  (tifffile writes type IFD, which ``exiftool -validate`` flags).
* WhiteLevel is a whole number (SHORT/LONG in the specification): the mosaic's values
  are stored as given, so ``white_level`` must be a positive whole number; values above it
  are clipped by raw editors, so pass the mosaic's maximum (or more) when it exceeds 1.
"""
from __future__ import annotations

import datetime as _dt
import math
import os

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError

#: DNG CFAPattern codes of CFAPlaneColor (0 = red, 1 = green, 2 = blue)
_CFA_CODES = {"R": 0, "G": 1, "B": 2}
#: TIFF tag data types (tifffile's codes)
_BYTE, _ASCII, _SHORT, _LONG, _RATIONAL, _UNDEFINED, _SRATIONAL = 1, 2, 3, 4, 5, 7, 10
#: an unassigned tag code just below ExifTag (34665), written by tifffile in its place
_EXIF_PLACEHOLDER = 34664
#: largest finite half-precision value
_HALF_MAX = 65504.0
_THUMB_SIZE = 256
_TILE = 256
_PREDICTOR = 3


def write_float_dng(path, mosaic, *, cfa_pattern: str, xyz_to_camera, as_shot_neutral, make: str, model: str,
                    exposure_time: float | None, iso: float | None = None, aperture: float | None = None,
                    preview, baseline_exposure: float = 0.0, orientation: int = 1, bits: int = 32,
                    white_level: float = 1.0, datetime: _dt.datetime | str | None = None) -> None:
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
    preview : (h, w, 3) uint8 array
        An sRGB rendering.  Written as a JPEG preview SubIFD, and downscaled to the IFD0
        thumbnail.
    bits : 16 or 32
        Float sample size.  16 = IEEE half (range 6e-5 .. 65504 at full precision: keep
        ``white_level`` within it); 32 = single.  Deflate-compressed with the
        floating-point predictor (TIFF Predictor 3), which LibRaw, rawspeed (darktable)
        and RawTherapee decode.
    white_level : float
        WhiteLevel, a positive whole number in the mosaic's units.
    datetime : datetime or "YYYY:MM:DD HH:MM:SS", optional
        DateTime and DateTimeOriginal (of the shot); omitted when None.

    Raises
    ------
    HdrMergeError
        Invalid arguments or data, or the file could not be written (a one-line message
        starting with the path).
    """
    where = os.fspath(path)
    _require_codecs(where)
    mosaic, cfa, matrix, neutral, white = _check(where, mosaic, cfa_pattern, xyz_to_camera, as_shot_neutral,
                                                 bits, white_level, orientation)
    preview = np.asarray(preview)
    if preview.ndim != 3 or preview.shape[2] != 3 or preview.dtype != np.uint8 or min(preview.shape[:2]) < 1:
        raise HdrMergeError(f"{where}: the DNG preview must be an (h, w, 3) uint8 image, "
                            f"not {preview.dtype} {preview.shape}")
    stamp = _stamp(where, datetime)
    try:
        _write(where, mosaic, cfa=cfa, matrix=matrix, neutral=neutral, white=white, make=make, model=model,
               exposure_time=exposure_time, iso=iso, aperture=aperture, baseline_exposure=baseline_exposure,
               orientation=orientation, thumb=_downscale(preview, _THUMB_SIZE), preview=preview, bits=bits,
               stamp=stamp)
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


def _check(where, mosaic, cfa_pattern, xyz_to_camera, as_shot_neutral, bits, white_level, orientation):
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
    if bits not in (16, 32):
        raise HdrMergeError(f"{where}: a float DNG has 16- or 32-bit samples, not {bits}")
    white = float(white_level)
    if not (math.isfinite(white) and white >= 1 and white == round(white) and white < 2 ** 32):
        raise HdrMergeError(f"{where}: the DNG white level must be a positive whole number, not {white_level!r} "
                            "(scale the mosaic instead)")
    if bits == 16 and max(white, float(np.abs(mosaic).max(initial=0.0))) > _HALF_MAX:
        raise HdrMergeError(f"{where}: values above {_HALF_MAX:g} do not fit 16-bit floats; "
                            "use 32 bits or scale the mosaic")
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
           baseline_exposure, orientation, thumb, preview, bits, stamp):
    import tifffile

    from hdrmerge_cli._version import __version__

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
    exif = [(36864, _UNDEFINED, 4, b"0232")]  # ExifVersion 2.32; then the shooting data, appended by _add_exif
    if exposure_time is not None and exposure_time > 0:
        exif.append((33434, _RATIONAL, 1, _exposure_rational(float(exposure_time))))
    if aperture is not None and aperture > 0:
        exif.append((33437, _RATIONAL, 1, (int(round(aperture * 100)), 100)))
    if iso is not None and iso > 0:
        exif.append((34855, _SHORT, 1, (min(int(round(iso)), 65535),)))
    if stamp:
        exif.append((36867, _ASCII, 20, stamp.encode("ascii") + b"\0"))  # DateTimeOriginal
    ifd0.append((_EXIF_PLACEHOLDER, _LONG, 1, 0, True))  # becomes ExifTag in _add_exif
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
    layout = {"tile": tile} if tile is not None else {"rowsperstrip": height}
    with tifffile.TiffWriter(where, byteorder="<", bigtiff=False) as tw:
        tw.write(thumb, photometric="rgb", subfiletype=1, subifds=2, software=f"hdrmerge-cli {__version__}",
                 datetime=stamp, extratags=ifd0, metadata=None, description=None, compression=None,
                 planarconfig="contig")
        tw.write(mosaic.astype(np.float16 if bits == 16 else np.float32, copy=False),
                 photometric=tifffile.PHOTOMETRIC.CFA, subfiletype=0, extratags=raw_tags, metadata=None,
                 planarconfig="contig", compression="adobe_deflate", compressionargs={"level": 6},
                 predictor=_PREDICTOR, maxworkers=min(4, os.cpu_count() or 1), **layout)
        tw.write(preview, photometric="rgb", subfiletype=1, compression="jpeg", compressionargs={"level": 90},
                 metadata=None, planarconfig="contig", rowsperstrip=preview.shape[0],
                 extratags=[(50970, _LONG, 1, 2, True)])  # PreviewColorSpace: sRGB
    _add_exif(where, exif)


def _add_exif(where: str, entries: list) -> None:
    """Append an EXIF IFD of ``entries`` ((tag, TIFF type, count, value)) to the written
    file, turn IFD0's placeholder entry into ExifTag (34665) pointing at it, and give
    IFD0's SubIFDs (330) type LONG: fields of entries tifffile wrote are patched in place
    (little-endian, classic TIFF, as :func:`_write` writes).  tifffile refuses to write
    tag 34665 itself; the placeholder's code sorts where 34665 does, so IFD0's entries
    stay in ascending order."""
    import struct

    import tifffile

    with tifffile.TiffFile(where) as tif:
        tags = tif.pages.first.tags
        exif_entry, subifds_entry = tags[_EXIF_PLACEHOLDER].offset, tags[330].offset
    size = {_BYTE: 1, _ASCII: 1, _SHORT: 2, _LONG: 4, _RATIONAL: 8, _UNDEFINED: 1}
    entries = sorted(entries, key=lambda e: e[0])
    with open(where, "r+b") as f:
        start = f.seek(0, os.SEEK_END) + 1 & ~1  # IFDs begin on a word boundary
        data_at = start + 2 + 12 * len(entries) + 4
        head, data = [struct.pack("<H", len(entries))], b""
        for tag, kind, count, value in entries:
            raw = value if isinstance(value, bytes) else struct.pack(f"<{len(value)}{'H' if kind == _SHORT else 'I'}",
                                                                     *value)
            if size[kind] * count <= 4:
                field = raw.ljust(4, b"\0")
            else:
                field, data = struct.pack("<I", data_at + len(data)), data + raw + b"\0" * (len(raw) % 2)
            head.append(struct.pack("<HHI", tag, kind, count) + field)
        f.seek(start)
        f.write(b"".join(head) + struct.pack("<I", 0) + data)
        f.seek(exif_entry)
        f.write(struct.pack("<HHII", 34665, _LONG, 1, start))
        f.seek(subifds_entry + 2)
        f.write(struct.pack("<H", _LONG))


def _downscale(image: np.ndarray, size: int) -> np.ndarray:
    """Box-filter an (h, w, 3) uint8 image so that its long side is at most ``size``."""
    h, w = image.shape[:2]
    k = max(1, math.ceil(max(h, w) / size))
    if k == 1:
        return np.ascontiguousarray(image)
    hh, ww = max(1, h // k), max(1, w // k)
    block = image[:hh * k, :ww * k].astype(np.float32).reshape(hh, k, ww, k, 3).mean(axis=(1, 3))
    return np.clip(np.rint(block), 0, 255).astype(np.uint8)
