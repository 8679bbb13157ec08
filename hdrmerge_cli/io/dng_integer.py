"""Writing Bayer-mosaic DNG files (pidng) that LibRaw reads back bit-exactly."""
from __future__ import annotations

import os
from fractions import Fraction

import numpy as np


def rational(x: float, limit: int = 1_000_000) -> list[int]:
    """Nearest fraction whose numerator and denominator fit the DNG's 32-bit fields."""
    limit = max(1, min(limit, int(0xFFFFFFFF / max(abs(x), 1e-9))))
    f = Fraction(float(x)).limit_denominator(limit)
    return [f.numerator, f.denominator]


def write_dng(
    path: str,
    mosaic: np.ndarray,
    *,
    pattern: str | list[int],
    black: int,
    white: int,
    exposure_time: float,
    iso: int | None = None,
    aperture: float | None = None,
    make: str = "hdrmerge-cli",
    model: str = "simulated sensor",
    xyz_to_camera: np.ndarray | None = None,
) -> None:
    """Write a ``(H, W)`` uint16 Bayer mosaic as an uncompressed DNG; ``pattern`` is a
    name (``"RGGB"``...) or the CFAPattern tag's four colour indices (0 R, 1 G, 2 B).

    ``xyz_to_camera`` is the DNG ColorMatrix1 (D65); the default makes the camera's
    native RGB equal to linear Rec.709, so LibRaw's camera -> sRGB matrix is identity.
    """
    from pidng.core import DNGTags, Tag
    from pidng.defs import CalibrationIlluminant, CFAPattern, Orientation, PhotometricInterpretation

    if xyz_to_camera is None:
        from hdrmerge_cli.core.output_colorspace import xyz_to

        xyz_to_camera = xyz_to("rec709")
    h, w = mosaic.shape
    tags = DNGTags()
    tags.set(Tag.ImageWidth, w)
    tags.set(Tag.ImageLength, h)
    tags.set(Tag.TileWidth, w)
    tags.set(Tag.TileLength, h)
    tags.set(Tag.Orientation, Orientation.Horizontal)
    tags.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    tags.set(Tag.SamplesPerPixel, 1)
    tags.set(Tag.BitsPerSample, 16)
    tags.set(Tag.CFARepeatPatternDim, [2, 2])
    tags.set(Tag.CFAPattern, getattr(CFAPattern, pattern) if isinstance(pattern, str) else list(pattern))
    tags.set(Tag.BlackLevel, int(black))
    tags.set(Tag.WhiteLevel, int(white))
    tags.set(Tag.ColorMatrix1, [rational(v, 10000) for v in np.asarray(xyz_to_camera, float).ravel()])
    tags.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    tags.set(Tag.AsShotNeutral, [[1, 1], [1, 1], [1, 1]])
    finish_dng(tags, path, np.ascontiguousarray(mosaic, dtype=np.uint16), exposure_time, iso, aperture, make, model)


def finish_dng(tags, path: str, pixels: np.ndarray, exposure_time: float, iso, aperture, make: str,
                model: str) -> None:
    """The exposure and camera tags every DNG written here carries, then the file (pidng)."""
    from pidng.core import RAW2DNG, Tag
    from pidng.defs import DNGVersion

    tags.set(Tag.ExposureTime, [rational(exposure_time)])
    if iso:
        tags.set(Tag.PhotographicSensitivity, [int(iso)])
    if aperture:
        tags.set(Tag.FNumber, [rational(aperture, 100)])
    tags.set(Tag.Make, make)
    tags.set(Tag.Model, model)
    tags.set(Tag.UniqueCameraModel, f"{make} {model}")
    tags.set(Tag.DNGVersion, DNGVersion.V1_4)
    tags.set(Tag.DNGBackwardVersion, DNGVersion.V1_2)
    writer = RAW2DNG()
    writer.options(tags, path="", compress=False)
    base, ext = os.path.splitext(path)
    writer.convert(pixels, filename=base)
    if ext.lower() != ".dng":  # pidng always appends .dng
        os.replace(base + ".dng", path)
