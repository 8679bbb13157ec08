"""The last stages of a merge: finish (colour, extra channels) and write (EXR, profile,
preview).  :class:`Merged` holds a reconstructed bracket in memory; the CLI writes it
strip by strip, the Python API (:func:`hdrmerge_cli.merge`) also hands out its arrays."""
from __future__ import annotations

import hashlib
import logging
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hdrmerge_cli._version import __version__
from hdrmerge_cli.core.cfa import bayer_channels, camera_to_rec709, demosaic_variance
from hdrmerge_cli.core.output_colorspace import COLORSPACES, camera_chromaticities, rec709_to
from hdrmerge_cli.core.cfa_to_rgb import raw_to_rgb_rows
from hdrmerge_cli.core.reconstruct import FLAG_DARK, FLAG_SATURATED
from hdrmerge_cli.io.frames import Frame
from hdrmerge_cli.io.metadata import upright
from hdrmerge_cli.pipeline.options import EXTRA_CHANNELS, MergeOptions

log = logging.getLogger("hdrmerge_cli")

if TYPE_CHECKING:
    from hdrmerge_cli.pipeline.records import Bracket
    from hdrmerge_cli.core.reconstruct import Reconstruction

#: file types ``--preview`` writes (by suffix)
PREVIEW_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
#: rows per strip of the colour conversion and EXR writing (even: keeps the CFA phase)
STRIP_ROWS = 256
#: rows of context around a strip for the demosaic (Malvar's 5 x 5 kernels need 2; even)
STRIP_HALO = 4


def default_profile_path(output: Path) -> Path:
    return output.with_name(output.stem + ".profile.json")


@dataclass
class Merged:
    """A merged bracket (what :func:`hdrmerge_cli.pipeline.run.merge_frames` returns): the
    bracket with every stage's result, and the merge's :class:`~hdrmerge_cli.pipeline.merge.Reconstruction`
    (in camera RGB: before white balance, demosaic and the camera matrix, which
    :meth:`strip` applies), with the options it was merged and is written with.

    h_ref : the reference exposure (s) whose full-scale signal is 1.0
    orientation : the output's EXIF orientation; repeats : equal-exposure comparisons for ``--json``
    """

    bracket: Bracket
    reconstruction: Reconstruction
    options: MergeOptions
    h_ref: float
    orientation: int = 1
    repeats: list = field(default_factory=list)
    #: ``(H, W)`` float32: the most any frame's alpha measured of each pixel; None when the
    #: frames have no alpha channel (then the EXR has none)
    alpha: np.ndarray | None = None

    # ------------------------------------------------------------ what it holds
    @property
    def first(self) -> Frame:
        return self.bracket.frames[0]

    @property
    def shape(self) -> tuple[int, int]:
        return self.first.height, self.first.width

    @property
    def colour_channels(self) -> list[str]:
        """The EXR's colour channels: ``Y`` for a mosaic (``--cfa``) or a grey image."""
        if self.first.kind == "raw":
            return ["Y"] if self.options.io.cfa else ["R", "G", "B"]
        return ["R", "G", "B"] if self.first.channels == 3 else ["Y"]

    @cached_property
    def crop_box(self) -> tuple[int, int, int, int] | None:
        """``--crop``: the rows and columns ``(r0, r1, c0, c1)`` (half-open) of the rectangle
        every aligned frame covers (:func:`~hdrmerge_cli.core.resample.inner_rectangle`;
        even for RAW, which keeps its CFA phase); None: the whole frame."""
        from hdrmerge_cli.core.resample import inner_rectangle

        if not self.options.io.crop:
            return None
        every = self.bracket.alignment.every_frame_mask if self.bracket.alignment is not None else None
        if every is None or every.all():
            log.info("--crop: every frame covers the whole image; nothing is cut")
            return None
        return inner_rectangle(every, even=self.first.kind == "raw")

    @property
    def channel_names(self) -> list[str]:
        """The EXR's channels: colour, then the data channels asked for, whose names end
        in no R, G or B (the Color Interop Forum's rule for channels that are not colour)."""
        extra = [c for c in EXTRA_CHANNELS if c in self.options.io.extra_channels and c != "variance"]
        return self.colour_channels + (["A"] if self.alpha is not None else []) + extra + self.variance_channels

    @property
    def variance_channels(self) -> list[str]:
        """``variance`` (one colour channel) or ``variance.red/green/blue``."""
        if "variance" not in self.options.io.extra_channels:
            return []
        return ["variance"] if len(self.colour_channels) == 1 else ["variance.red", "variance.green", "variance.blue"]

    @cached_property
    def flags(self) -> np.ndarray:
        """``(H, W)`` int8 per pixel: ``FLAG_SATURATED`` where a channel had no unclipped
        reading, else ``FLAG_DARK`` where one was below every frame's noise floor, else 0."""
        f = self.reconstruction.flags
        if f.ndim == 2:
            return f
        return np.where((f == FLAG_SATURATED).any(-1), FLAG_SATURATED,
                        np.where((f == FLAG_DARK).any(-1), FLAG_DARK, 0)).astype(np.int8)

    @property
    def image(self) -> np.ndarray:
        """``(H, W, 3)`` (or ``(H, W, 1)``) float32 scene-linear colour, as the EXR holds it."""
        return np.concatenate([self.colour_rows(y0, min(self.shape[0], y0 + STRIP_ROWS))
                               for y0 in range(0, self.shape[0], STRIP_ROWS)])

    @property
    def variance(self) -> np.ndarray | None:
        """``(H, W, 3)`` (or ``(H, W, 1)``) float32: the variance of each value of
        :attr:`image` (:meth:`variance_rows`); None unless ``extra_channels`` has
        ``variance``."""
        if self.reconstruction.variance is None:
            return None
        return np.concatenate([self.variance_rows(y0, min(self.shape[0], y0 + STRIP_ROWS))
                               for y0 in range(0, self.shape[0], STRIP_ROWS)])

    @property
    def white_balanced(self) -> bool:
        first = self.first
        return (first.kind == "raw" and not self.options.io.cfa) or (first.kind == "linear" and first.channels == 3)

    # ------------------------------------------------------------ finish
    @property
    def colorspace(self) -> str | None:
        """The output's colour space (``--colorspace``); None for a mosaic or grey image.
        Camera-processed images count as Rec.709 (sRGB primaries) in their native RGB."""
        if self.colour_channels != ["R", "G", "B"]:
            return None
        cs = self.options.io.colorspace
        return "rec709" if cs == "camera" and self.first.kind == "image" else cs

    @cached_property
    def colour_matrix(self) -> np.ndarray | None:
        """``(3, 3)`` from the merged (white-balanced) camera RGB to the output space (RAW
        and linear RGB: the camera matrix, then :func:`rec709_to`; ``camera``: identity);
        for images from Rec.709; None where nothing is converted."""
        cs, first = self.colorspace, self.first
        if cs is None:
            return None
        if first.kind == "image":
            return None if cs == "rec709" else rec709_to(cs)
        if cs == "camera":
            return np.eye(3)
        return first.color_matrix if cs == "rec709" else rec709_to(cs) @ first.color_matrix

    def colour_rows(self, y0: int, y1: int) -> np.ndarray:
        """Rows ``y0:y1`` of the output colour: RAW white balance, demosaic and
        :attr:`colour_matrix`; linear RGB white balance and that matrix; images as merged,
        or through it."""
        first, matrix = self.first, self.colour_matrix
        if first.kind == "raw" and not self.options.io.cfa:
            return _raw_to_rgb_rows(self.reconstruction.result, first, y0, y1, matrix)
        rgb = self.reconstruction.result[y0:y1].reshape(y1 - y0, first.width, -1)
        if first.kind == "linear" and first.channels == 3:  # demosaiced camera RGB
            rgb = rgb * first.white_balance.astype(np.float32)
        return rgb if matrix is None else camera_to_rec709(rgb, matrix)

    def colour_tags(self) -> dict:
        """The EXR header's colour attributes: ``chromaticities`` and ``colorInteropID``
        (Color Interop Forum), none for a mosaic, a grey image, or a camera space whose
        primaries are unknown."""
        cs = self.colorspace
        if cs is None:
            return {}
        if cs == "camera":
            first = self.first
            chroma = camera_chromaticities(camera_xyz_matrix(first), first.white_balance)
            return {"chromaticities": list(chroma)} if chroma else {}
        space = COLORSPACES[cs]
        return {"chromaticities": list(space.chromaticities), "colorInteropID": space.interop_id}

    def variance_rows(self, y0: int, y1: int) -> np.ndarray:
        """Rows ``y0:y1`` of the variance of :meth:`colour_rows`, ``(y1 - y0, W, C)``
        float32 in the colour's units squared, under the noise model: each value's variance
        scaled as the colour is (gain^2 for the white balance, the matrix's squared
        entries), correlations between channels ignored.  RAW RGB: the white-balanced
        samples' variances through the demosaic's squared weights
        (:func:`~hdrmerge_cli.core.cfa.demosaic_variance`; the samples are independent,
        so exact before the matrix).  Exact for a mosaic (``--cfa``), for images in their
        own colour space, and for RAW RGB through an identity matrix."""
        first, matrix = self.first, self.colour_matrix
        sq = None if matrix is None else np.square(np.asarray(matrix, np.float32))
        if first.kind == "raw" and not self.options.io.cfa:
            a, b = max(0, y0 - STRIP_HALO), min(self.shape[0], y1 + STRIP_HALO)  # y0, a even: same CFA phase
            gains = np.square(first.white_balance)[bayer_channels(first.cfa_pattern, (b - a, self.shape[1]))]
            var = demosaic_variance(self.reconstruction.variance[a:b] * gains, first.cfa_pattern)[y0 - a:y1 - a]
        else:
            var = self.reconstruction.variance[y0:y1].reshape(y1 - y0, first.width, -1)
            if first.kind == "linear" and first.channels == 3:
                var = var * np.square(first.white_balance).astype(np.float32)
        return var if sq is None else camera_to_rec709(var, sq)

    def strip(self, y0: int, ghost_img: np.ndarray | None = None, wsum: np.ndarray | None = None):
        """``(y0, rows)``: rows ``y0:y0 + STRIP_ROWS`` of the EXR, colour and extra
        channels, so no full-size RGB copy is ever held."""
        y1 = min(self.shape[0], y0 + STRIP_ROWS)
        rgb = self.colour_rows(y0, y1)
        extra = self.options.io.extra_channels
        planes = [rgb]
        if self.alpha is not None:  # OpenEXR's alpha is associated: colour times alpha
            a = self.alpha[y0:y1, :, None]
            planes = [rgb * a, a]
        if "clipped" in extra:
            planes.append(self.flags[y0:y1, :, None].astype(np.float32))
        if "weight" in extra:
            planes.append(wsum[y0:y1, :, None].astype(np.float32))
        if ghost_img is not None:
            planes.append(ghost_img[y0:y1, :, None])
        if "variance" in extra:
            planes.append(self.variance_rows(y0, y1))
        return y0, np.concatenate(planes, axis=-1) if len(planes) > 1 else rgb

    def profile(self, profile_name: str | None = None) -> dict:
        """The JSON camera profile this merge used (response, weights, noise)."""
        from hdrmerge_cli.io.profile import new_profile

        first, m = self.first, self.bracket.models
        profile = new_profile({"make": first.make, "model": first.model}, first.bits, self.bracket.crf,
                              [f.path for f in self.bracket.frames], "merge")
        profile["weights"] = m.weights
        profile["decisions"] = self.bracket.decisions()
        if m.noise:
            profile["noise"] = {"used": m.noise_used(first)}
            if m.frame_noise:  # the frames' ISOs differ: "used" is the reference frame's
                profile["noise"]["noise_per_iso"] = m.noise_per_iso(self.bracket.frames)
        if m.estimated:
            profile["noise"]["estimated_from_bracket"] = m.estimated
        if m.excess is not None:
            profile["excess_variance"] = m.excess.as_dict()
        return profile

    def header(self, profile_name: str, profile_text: str) -> dict:
        """The EXR header attributes: provenance, units, colour, orientation."""
        first, m = self.first, self.bracket.models
        attrs = {
            "Software": f"hdrmerge-cli {__version__}",
            "hdrmerge:version": __version__,
            "hdrmerge:exposureTimes": [f.exposure_time for f in self.bracket.frames],
            "hdrmerge:exposures": list(self.bracket.exposures),
            "hdrmerge:referenceExposure": self.h_ref,
            "hdrmerge:units": (
                "scene-linear; 1.0 = the full-scale (clipping) signal of an exposure of "
                "hdrmerge:referenceExposure seconds" + (", after white balance (green = 1)" if self.white_balanced
                                                        else "")
            ),
            "hdrmerge:weights": m.weights,
            "hdrmerge:estimator": m.estimator,
            "hdrmerge:variance": m.variance,
            "hdrmerge:crf": self.bracket.crf.describe(),
            "hdrmerge:profile": profile_name,
            "hdrmerge:profileSHA256": hashlib.sha256(profile_text.encode()).hexdigest(),
            "hdrmerge:inputs": "; ".join(f.name for f in self.bracket.frames),
            "ExposureTime": self.h_ref,
        }
        if first.camera:
            attrs["Make"], attrs["Model"] = first.make, first.model
        attrs.update(self.colour_tags())
        if first.kind == "raw" and self.options.io.cfa:
            attrs["hdrmerge:cfaPattern"] = first.cfa_pattern
        if self.variance_channels:
            attrs["hdrmerge:varianceChannels"] = (
                "variance of each colour value under the noise model (inverse of the summed Fisher information of "
                "the frames that measured it, or the exact variance of the weighted mean), in the colour channels' "
                "units squared; samples no frame measured: the value squared")
        if self.orientation != 1:  # the pixels stay in sensor order; viewers rotate by the header
            attrs["Orientation"] = self.orientation
        return attrs

    # ------------------------------------------------------------ write
    def write(self, output=None, profile_out=None, preview=None, overwrite: bool | None = None,
              inputs=()) -> dict:
        """Write the EXR, its profile and (optionally) a preview, all or none (each to a
        temporary name first); the options' paths unless given.  Returns the paths written."""
        from hdrmerge_cli.core.preview import BlockMean, block_factor, tonemap_srgb
        from hdrmerge_cli.io.atomic import atomic_paths, write_text
        from hdrmerge_cli.io.images import write_exr, write_ldr
        from hdrmerge_cli.io.profile import dumps

        opts = self.options
        output = Path(output if output is not None else opts.io.output)
        profile_out = Path(profile_out or opts.io.profile_out or default_profile_path(output))
        preview = preview if preview is not None else opts.io.preview
        overwrite = opts.io.overwrite if overwrite is None else overwrite
        profile_text = dumps(self.profile())
        if output.suffix.lower() == ".dng":
            with atomic_paths([output, profile_out], overwrite, list(inputs)) as tmps:
                baseline = self.write_dng(tmps[0])
                write_text(tmps[1], profile_text)
            return {"output": str(output), "profile": str(profile_out), "dng_baseline_exposure_ev": round(baseline, 2)}
        attrs = self.header(profile_out.name, profile_text)
        extra = opts.io.extra_channels
        den = self.reconstruction.den
        wsum = (den if den.ndim == 2 else den.mean(axis=-1)) if "weight" in extra else None
        ghosts = self.bracket.ghosts
        ghost_img = None if "ghost" not in extra else (
            ghosts.image(*self.shape) if ghosts is not None else np.zeros(self.shape, np.float32))
        strips = prefetched(lambda y0: self.strip(y0, ghost_img, wsum), range(0, self.shape[0], STRIP_ROWS))
        shape, box = self.shape, self.crop_box
        if box is not None:
            strips, shape = _cropped(strips, box), (box[1] - box[0], box[3] - box[2])
            attrs["hdrmerge:crop"] = (f"rows {box[0]} to {box[1] - 1}, columns {box[2]} to {box[3] - 1} of the "
                                      "reference frame: the rectangle every aligned frame covers")
        n_colour = len(self.colour_channels)
        thumb = None
        if preview is not None:
            thumb = BlockMean(*shape, n_colour, block_factor(*shape, opts.io.preview_size))
            strips = _tee_preview(strips, thumb, n_colour)
        outputs = [output, profile_out] + ([Path(preview)] if thumb else [])
        with atomic_paths(outputs, overwrite, list(inputs)) as tmps:
            write_exr(tmps[0], strips, self.channel_names, attrs, half=opts.io.half, size=shape,
                      compression=opts.io.compression)
            write_text(tmps[1], profile_text)
            if thumb:
                rgb = upright(thumb.result(), self.orientation)
                write_ldr(tmps[2], tonemap_srgb(rgb if rgb.shape[-1] == 3 else np.repeat(rgb[..., :1], 3, axis=-1)),
                          {"Software": f"hdrmerge-cli {__version__}", "ImageDescription": f"preview of {output.name}"})
        return {"output": str(output), "profile": str(profile_out)} | ({"preview": str(preview)} if thumb else {})

    def write_dng(self, path) -> float:
        """The merged CFA mosaic as a floating-point DNG (:func:`hdrmerge_cli.io.dng_float.write_float_dng`)
        that raw editors open like the camera's own raw files: black 0, WhiteLevel the
        smallest whole number above the brightest value (no highlight clipped), BaselineExposure
        log2 of it (so the default rendering shows the reference exposure: 1.0 = white), the
        camera matrix and as-shot white balance that the EXR path uses (:func:`camera_xyz_matrix`),
        32-bit floats (``--half``: 16), and an embedded preview.  Returns the BaselineExposure
        (EV), which editors that ignore the tag (darktable 4.2) leave to the user to apply:
        they show the image that much darker."""
        from hdrmerge_cli.core.errors import HdrMergeError
        from hdrmerge_cli.core.preview import tonemap_srgb
        from hdrmerge_cli.io.dng_float import write_float_dng

        first = self.first
        if first.kind != "raw":
            raise HdrMergeError(f"{path}: a DNG output holds a CFA mosaic; {first.path} is not a Bayer RAW frame "
                                "(write an EXR)")
        white = max(1.0, float(np.ceil(np.max(self.reconstruction.result))))
        baseline = float(np.log2(white))
        preview = tonemap_srgb(cell_rgb(self.reconstruction.result, first, first.color_matrix, DNG_PREVIEW_SIZE))
        write_float_dng(path, self.reconstruction.result, cfa_pattern=first.cfa_pattern,
                        xyz_to_camera=camera_xyz_matrix(first),
                        as_shot_neutral=1.0 / first.white_balance, make=first.make or "hdrmerge-cli",
                        model=first.model or "merged", exposure_time=self.h_ref, iso=first.iso,
                        aperture=first.aperture, baseline_exposure=baseline,
                        orientation=self.orientation, preview=preview, bits=16 if self.options.io.half else 32,
                        white_level=white, datetime=first.timestamp)
        return baseline

    def summary(self) -> dict:
        """What ``merge --json`` prints (without the paths written)."""
        b, first, flags = self.bracket, self.first, self.reconstruction.flags
        m, estimated, n = b.models, b.models.estimated, flags.size
        alignment, ghosts = b.alignment, b.ghosts
        return {
            "frames": [f.summary() | {"exposure": float(h)} for f, h in zip(b.frames, b.exposures)],
            "reference_exposure": self.h_ref,
            "exposure_check": b.exposure_report,
            "orientation": self.orientation,
            **({"equal_exposures": self.repeats} if self.repeats else {}),
            "weights": m.weights,
            "estimator": m.estimator,
            "variance": m.variance,
            "irls_iterations": self.reconstruction.iterations,
            "decisions": b.decisions(),
            "noise": m.noise_used(first),
            **({"noise_per_iso": m.noise_per_iso(b.frames)} if m.frame_noise else {}),
            "noise_source": (f"measured earlier on the same camera and ISO (cache {estimated['cached']['file']})"
                             if estimated and "cached" in estimated
                             else "measured on the bracket (calibrate-noise fast path)" if estimated
                             else "given (--noise or --profile)" if m.noise else None),
            "prior_rate": m.prior,
            "bounds": list(m.bounds) if m.bounds else None,
            "crf": b.crf.describe(),
            "width": first.width,
            "height": first.height,
            **({"crop": {"rows": [self.crop_box[0], self.crop_box[1]], "columns": [self.crop_box[2],
                                                                                   self.crop_box[3]]}}
               if self.crop_box else {}),
            "channels": self.channel_names,
            "saturated_fraction": float(np.count_nonzero(flags == FLAG_SATURATED) / n),
            "dark_fraction": float(np.count_nonzero(flags == FLAG_DARK) / n),
            **({"alignment": alignment.summary()} if alignment else {}),
            **({"deghost": ghosts.summary()} if ghosts else {}),
            "timing_seconds": {k: round(v, 4) for k, v in b.timings.items()},
        }


#: longest side of the preview embedded in a DNG
DNG_PREVIEW_SIZE = 1024


def camera_xyz_matrix(frame: Frame) -> np.ndarray:
    """The DNG ColorMatrix (XYZ D65 -> the camera's native RGB) that makes a raw editor
    render the colours of the EXR path: that path takes native RGB ``c`` to Rec.709 as
    ``color_matrix @ (white_balance * c)``, so XYZ = ``N @ color_matrix @ diag(wb) @ c``
    with ``N`` the Rec.709 -> XYZ matrix, and the ColorMatrix is that product's inverse.
    (LibRaw's own camera table, where it has one, is what ``color_matrix`` was made from.)"""
    from hdrmerge_cli.core.output_colorspace import COLORSPACES, D65, rgb_to_xyz_matrix

    to_xyz = rgb_to_xyz_matrix(COLORSPACES["rec709"].primaries, D65)
    return np.linalg.inv(to_xyz @ np.asarray(frame.color_matrix, np.float64) @ np.diag(frame.white_balance))


def cell_rgb(mosaic: np.ndarray, frame: Frame, matrix: np.ndarray, max_side: int) -> np.ndarray:
    """A small ``(h, w, 3)`` float RGB picture of a mosaic without demosaicing: each 2 x 2
    CFA cell gives one pixel (its greens averaged), white balance and ``matrix`` applied,
    then area-averaged to at most ``max_side`` pixels on the longer side.  Each CFA site's
    plane is area-averaged first (strided views, one pass over the mosaic; the same means,
    as every block holds as many cells)."""
    from hdrmerge_cli.core.preview import block_factor

    f = block_factor(mosaic.shape[0] // 2, mosaic.shape[1] // 2, max_side)
    hh, ww = mosaic.shape[0] // 2 // f * f, mosaic.shape[1] // 2 // f * f
    planes = {"R": [], "G": [], "B": []}
    for i, colour in enumerate(frame.cfa_pattern):
        site = mosaic[i // 2:2 * hh:2, i % 2:2 * ww:2]
        planes[colour].append(site.reshape(hh // f, f, ww // f, f).mean(axis=(1, 3), dtype=np.float64))
    rgb = np.stack([np.mean(planes[c], axis=0) for c in "RGB"], axis=-1) * frame.white_balance
    return rgb @ np.asarray(matrix, np.float64).T


def _cropped(strips, box: tuple[int, int, int, int]):
    """The EXR strips ``(y0, rows)`` cut to ``box`` = ``(r0, r1, c0, c1)``, ``y0`` counted
    from ``r0``."""
    r0, r1, c0, c1 = box
    for y0, data in strips:
        a, b = max(y0, r0), min(y0 + data.shape[0], r1)
        if b > a:
            yield a - r0, data[a - y0:b - y0, c0:c1]


def _tee_preview(strips, preview, n_channels: int):
    """Pass the EXR strips on, adding each one's image channels to the preview."""
    for y0, data in strips:
        preview.add(y0, data[..., :n_channels])
        yield y0, data


def prefetched(fn, items, ahead: int = 2):
    """``fn(item)`` for each item in order, computed up to ``ahead`` items in advance on
    worker threads (so the colour conversion of the next strips runs while the EXR
    writer compresses this one), holding at most ``ahead + 1`` results."""
    with ThreadPoolExecutor(ahead) as pool:
        pending = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) > ahead:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def _raw_to_rgb_rows(mosaic: np.ndarray, frame: Frame, y0: int, y1: int, matrix=None) -> np.ndarray:
    """Rows ``y0:y1`` of the output RGB: white balance (green = 1) per CFA colour,
    demosaic (Malvar-He-Cutler, reading the rows around the strip, so strips join
    seamlessly), ``matrix`` (default: the camera matrix, to Rec.709); one compiled pass
    that releases the GIL (strips run on the prefetch threads, one per core).  The tests
    compare it with the same arithmetic through colour-demosaicing."""
    matrix = frame.color_matrix if matrix is None else matrix
    return raw_to_rgb_rows(mosaic, frame.cfa_pattern, frame.white_balance, matrix, y0, y1)
