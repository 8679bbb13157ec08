"""Reading frames: RAW files through rawpy (LibRaw), JPEG/TIFF/PNG through OpenImageIO.

:func:`read_frame` reads a frame's metadata (cheap); :func:`load_codes` decodes its code
values.  Every failure is an :class:`~hdrmerge_cli.core.errors.HdrMergeError` whose
message starts with the file's path.
"""
from __future__ import annotations

import contextlib
import logging
import datetime as _dt
import os
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError

log = logging.getLogger("hdrmerge_cli")

#: extensions read through OpenImageIO; anything else is tried as RAW with LibRaw
IMAGE_EXTENSIONS = {".jpg", ".jpeg", ".tif", ".tiff", ".png"}


@dataclass
class Frame:
    """One frame of a bracket (metadata; pixels via :func:`load_codes`).

    kind : "raw" (CFA mosaic, linear), "linear" (linear RGB from a RAW container, already
        demosaiced: a LinearRaw DNG; decoded as interleaved channels like an image, black
        subtracted and scaled to the full 16-bit range, see :func:`load_codes`) or "image"
        (camera-processed, interleaved channels)
    black, white : (C,) per table channel, in the code values :func:`load_codes` returns;
        C = 4 raw colours for RAW (LibRaw's order, see ``channel_colors``), the image
        channels otherwise
    n_codes : size of the stored code range (2^8 or 2^16)
    bits : significant bits of the stored values
    orientation : EXIF orientation (1 = upright, 6 = rotate 90 degrees clockwise to view,
        8 = counter-clockwise, 3 = 180; 2, 4, 5, 7 mirrored), from EXIF or LibRaw's flip
    file_levels : the file's own (black per channel, white) when they differ from
        ``black``/``white`` (a "linear" frame's codes are rescaled on decoding)
    """

    path: str
    kind: str
    width: int
    height: int
    exposure_time: float | None
    iso: float | None
    aperture: float | None
    make: str
    model: str
    timestamp: str | None
    bits: int
    n_codes: int
    black: np.ndarray
    white: np.ndarray
    channels: int
    cfa_pattern: str | None = None
    channel_colors: str = "RGB"
    white_balance: np.ndarray = field(default_factory=lambda: np.ones(3))
    color_matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    orientation: int = 1
    file_levels: tuple | None = None
    #: RAW: the 2 x 2 cell of LibRaw's colour index (0..3): read with the metadata, or given
    #: (frames made from arrays, :func:`hdrmerge_cli.api.merge_arrays`); None where the colour
    #: index does not repeat with a 2 x 2 cell (:func:`cfa_corner` then reads the file)
    cfa_cell: np.ndarray | None = None
    #: images: the index of the file's alpha channel (gray+alpha, RGBA), else None; alpha is
    #: the share of a pixel the frame measured (:func:`decode`), 0 none
    alpha_channel: int | None = None
    #: images: the file stores colour multiplied by alpha (associated alpha: TIFF
    #: ExtraSamples 1); PNG and unassociated TIFF store it straight
    alpha_associated: bool = False
    #: images: the processing the file states (EXIF contrast, saturation, sharpness, custom
    #: rendering, software), which a camera's response depends on; "" when it states none
    style: str = ""
    #: images: EXIF ExposureMode is "auto bracket" (2): the camera took the frame as part of a
    #: bracket it set itself
    auto_bracket: bool = False
    #: images: EXIF ExposureBiasValue (EV), the exposure compensation of the frame, or None
    exposure_bias: float | None = None
    #: where ``exposure_time`` comes from: ``"its metadata"``, ``"--times"`` or the times file
    #: (:func:`~hdrmerge_cli.io.times.apply_times`), for messages that question it
    time_source: str = "its metadata"

    @property
    def name(self) -> str:
        return Path(self.path).name

    @property
    def channel_names(self) -> list[str]:
        """One name per table channel; a colour's second site is suffixed 2 (``G2``)."""
        return [c + "2" if self.channel_colors[:i].count(c) else c for i, c in enumerate(self.channel_colors)]

    @property
    def layout(self) -> tuple:
        """What frames of one bracket share: file kind, size, channels, CFA, camera."""
        return self.kind, self.width, self.height, self.channels, self.cfa_pattern, self.camera

    @property
    def camera(self) -> str:
        """Make and model ("Canon EOS REBEL T2i", not "Canon Canon EOS ...")."""
        if self.make and self.model.lower().startswith(self.make.lower()):
            return self.model.strip()
        return f"{self.make} {self.model}".strip()

    @property
    def data_format(self) -> str:
        """What the file holds, for ``info`` ("Bayer RGGB mosaic, 14-bit", ...)."""
        if self.kind == "raw":
            return f"Bayer {self.cfa_pattern} mosaic, {self.bits}-bit"
        if self.kind == "linear":
            what = "linear RGB" if self.channels == 3 else "linear monochrome"
            dng = " (LinearRaw DNG)" if Path(self.path).suffix.lower() == ".dng" else ""
            return f"{what}{dng}, demosaiced, {self.bits}-bit"
        return f"{self.bits}-bit {'RGB' if self.channels == 3 else 'grey'} image"

    def summary(self) -> dict:
        black, white = (self.black, self.white) if self.file_levels is None else self.file_levels
        return {
            "path": self.path,
            "exposure_time": self.exposure_time,
            "iso": self.iso,
            "aperture": self.aperture,
            "camera": self.camera,
            "kind": self.kind,
            "format": self.data_format,
            "orientation": self.orientation,
            "bits": self.bits,
            "black": [float(b) for b in np.atleast_1d(black)],
            "white": [float(w) for w in np.atleast_1d(white)],
        }


_STDERR_LOCK = threading.Lock()
_silenced = 0  # threads inside quiet_c_stderr
_saved_fd = None


@contextlib.contextmanager
def quiet_c_stderr():
    """Silence what LibRaw prints on C-level stderr (we report its errors ourselves).

    Frames are decoded on several threads: file descriptor 2 is pointed at /dev/null by the
    first thread in and restored by the last one out.  Python's own messages do not go
    through it once :func:`separate_python_stderr` has run."""
    global _silenced, _saved_fd
    with _STDERR_LOCK:
        if _silenced == 0:
            try:
                _saved_fd = os.dup(2)
                with open(os.devnull, "wb") as null:
                    os.dup2(null.fileno(), 2)
            except OSError:  # no stderr to silence
                _saved_fd = None
        _silenced += 1
    try:
        yield
    finally:
        with _STDERR_LOCK:
            _silenced -= 1
            if _silenced == 0 and _saved_fd is not None:
                os.dup2(_saved_fd, 2)
                os.close(_saved_fd)
                _saved_fd = None


def separate_python_stderr() -> None:
    """Point ``sys.stderr`` at a duplicate of file descriptor 2, so that silencing C
    libraries (:func:`quiet_c_stderr`, while another thread decodes) never swallows a log
    line or an error message of ours."""
    try:
        fd = os.dup(2)
    except OSError:
        return
    sys.stderr = os.fdopen(fd, "w", buffering=1, encoding=getattr(sys.stderr, "encoding", None) or "utf-8",
                           errors="backslashreplace")


def _positive(value) -> float | None:
    """``value`` as a finite float above 0, or None."""
    v = _finite(value)
    return v if v is not None and v > 0 else None


#: suffixes of files that are never frames (outputs and sidecars), with what they are
NOT_FRAMES = {".exr": "an OpenEXR image (floating point)", ".hdr": "a Radiance HDR image (floating point)",
              ".json": "a JSON file", ".xmp": "an XMP sidecar", ".txt": "a text file", ".csv": "a CSV table",
              ".md": "a Markdown file"}


def bracket_label(frames: list[Frame]) -> str:
    """How a message names a bracket: ``first/path ... last_name`` (one frame: its path)."""
    return f"{frames[0].path} ... {frames[-1].name}" if len(frames) > 1 else frames[0].path


def list_frames(folder: str | os.PathLike) -> list[str]:
    """The frames in ``folder``: every regular, non-hidden file that is not a sidecar or
    an output (:data:`NOT_FRAMES`), sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise HdrMergeError(f"{folder}: not a folder")
    return [str(p) for p in sorted(folder.iterdir())
            if p.is_file() and not p.name.startswith(".") and p.suffix.lower() not in NOT_FRAMES]


def read_frame(path: str | os.PathLike, held: "HeldCodes | None" = None) -> Frame:
    """Metadata of one frame (RAW or image), validated; raises HdrMergeError.  ``held``:
    the codes of a RAW frame, which LibRaw unpacks to tell its colour filter and levels,
    are handed to it from the same open (a RAW frame is then decoded once)."""
    path = str(path)
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:  # bytes the OS allows but the image libraries cannot be given
        shown = os.fsencode(path).decode("utf-8", "backslashreplace")
        raise HdrMergeError(f"{shown}: the file name is not valid UTF-8, which the image libraries cannot open; "
                            "rename the file") from None
    if not os.path.isfile(path):
        if not os.path.exists(path):
            raise HdrMergeError(f"{path}: no such file")
        what = "is a folder" if os.path.isdir(path) else "not a regular file (a pipe, socket or device)"
        raise HdrMergeError(f"{path}: {what}; a frame is a RAW or image file")
    if not os.access(path, os.R_OK):
        raise HdrMergeError(f"{path}: not readable (permission denied)")
    if Path(path).suffix.lower() in NOT_FRAMES:
        raise HdrMergeError(f"{path}: {NOT_FRAMES[Path(path).suffix.lower()]} is not an input frame "
                            "(frames are RAW files or 8/16-bit JPEG/TIFF/PNG)")
    return _read_image(path) if Path(path).suffix.lower() in IMAGE_EXTENSIONS else _read_raw(path, held)


def check_distinct_frames(paths) -> None:
    """Refuse a file given twice, under any name (a repeated shell glob, a link, another
    relative path): its noise would count twice as if independent, and the merge would
    average the frame with itself.  After :func:`read_frame` (the files exist)."""
    seen: dict[tuple[int, int], str] = {}
    for p in map(str, paths):
        st = os.stat(p)
        key = (st.st_dev, st.st_ino)
        if key in seen:
            raise HdrMergeError(f"{p}: the same file as {seen[key]}, given twice; give each frame once")
        seen[key] = p


def _oiio_meta(path: str) -> dict:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        oiio.geterror()
        return {}
    spec = inp.spec()
    meta = {k: spec.getattribute(k) for k in ("Make", "Model", "Exif:PhotographicSensitivity", "Exif:ISOSpeedRatings",
                                              "tiff:PhotometricInterpretation")}
    inp.close()
    return meta


#: TIFF PhotometricInterpretation of a colour filter array (DNG: a mosaic)
CFA_PHOTOMETRIC = 32803

#: LibRaw's ``flip`` (dcraw's code) -> the EXIF orientation it came from
LIBRAW_FLIP_TO_EXIF = {0: 1, 1: 2, 2: 4, 3: 3, 4: 5, 5: 8, 6: 6, 7: 7}


def _read_raw(path: str, held: "HeldCodes | None" = None) -> Frame:
    """A RAW file's metadata.  Bayer mosaics are kind "raw"; linear RGB data (LinearRaw
    DNGs, and other already demosaiced data LibRaw hands over as 3 colours per pixel) kind
    "linear"; what cannot be merged (X-Trans, 4-colour sensors) is refused with what it is.
    ``held``: the unpacked codes are handed to it (:func:`read_frame`)."""
    import rawpy

    raw = rawpy.RawPy()
    stored = None
    try:
        with quiet_c_stderr():
            raw.open_file(path)
            num_colors = raw.num_colors  # known before unpacking: refuse at once
            if num_colors not in (1, 3):
                raise HdrMergeError(f"{path}: a {num_colors}-colour sensor ({raw.color_desc.decode('ascii', 'replace')} "
                                    "filters); only Bayer RGB mosaics and linear RGB RAW data are supported")
            pattern = raw.raw_pattern  # unpacks
            # the colour index window at no extra cost now (cfa_corner would open and unpack again)
            window = _channel_window(raw) if pattern is not None and np.shape(pattern) == (2, 2) else None
            raw_type = raw.raw_type
            sizes = raw.sizes
            black = np.asarray(raw.black_level_per_channel, dtype=np.float64)
            white = float(raw.white_level)
            colors = raw.color_desc.decode("ascii", "replace")
            wb = np.asarray(raw.camera_whitebalance, dtype=np.float64)
            daylight = np.asarray(raw.daylight_whitebalance, dtype=np.float64)
            matrix = np.asarray(raw.color_matrix, dtype=np.float64)[:, :3]
            other = raw.other
            if held is not None:
                stored = _visible(raw)
    except rawpy.LibRawError as exc:
        raise HdrMergeError(f"{path}: not a readable RAW file ({_libraw_reason(exc, path)})") from None
    finally:
        if stored is None:  # else the codes may be LibRaw's buffer itself, freed with them (_visible)
            raw.close()
    pattern = None if pattern is None else np.asarray(pattern)
    meta = _oiio_meta(path)
    kind, channels = _raw_kind(path, pattern, num_colors, colors, raw_type == rawpy.RawType.Stack, meta)
    if white <= black.max():
        raise HdrMergeError(f"{path}: white level {white:g} is not above the black level {black.max():g}")
    ts = other.timestamp
    stamp = ts.isoformat() if isinstance(ts, _dt.datetime) and ts.year > 1970 else None
    bits = int(np.ceil(np.log2(white + 1)))
    common = dict(
        path=path, kind=kind, width=sizes.width, height=sizes.height,
        exposure_time=_positive(other.shutter_speed),
        iso=_positive(other.iso_speed) or _image_iso(meta),
        aperture=_positive(other.aperture), make=str(meta.get("Make") or ""),
        model=str(meta.get("Model") or ""), timestamp=stamp, bits=bits, n_codes=65536,
        white_balance=_white_balance(wb, daylight), color_matrix=_matrix_or_identity(matrix),
        orientation=LIBRAW_FLIP_TO_EXIF.get(int(sizes.flip), 1),
    )
    if kind == "linear":  # decoded as codes (black 0, white 65535): see load_codes
        frame = Frame(**common, black=np.zeros(channels), white=np.full(channels, 65535.0), channels=channels,
                      channel_colors="RGB" if channels == 3 else "Y", file_levels=(black[:channels], white))
        if stored is not None:
            held.hold(frame, linear_codes(stored, frame))
        return frame
    cfa = "".join(colors[i] for i in pattern.ravel())
    cell = window[:2, :2]
    periodic = np.array_equal(window, np.tile(cell, (CFA_WINDOW // 2, CFA_WINDOW // 2)))
    frame = Frame(**common, black=black, white=np.full(4, white), channels=4, cfa_pattern=cfa, channel_colors=colors,
                  cfa_cell=cell.astype(np.intp) if periodic else None)  # else sample_pattern reports it
    if stored is not None:
        held.hold(frame, stored)
    return frame


def _raw_kind(path: str, pattern: np.ndarray | None, num_colors: int, colors: str, stack: bool,
              meta: dict) -> tuple[str, int]:
    """``(kind, channels)`` of a RAW file from LibRaw's colour filter ``pattern`` (None: none),
    its ``num_colors`` and ``colors`` (LibRaw's color_desc) and ``stack`` (3 colours per
    pixel): a Bayer mosaic is ("raw", 4), linear data ("linear", 3 or 1); anything else,
    or a CFA-tagged file whose pattern is not Bayer RGB, is refused with what it is."""
    bayer = pattern is not None and pattern.shape == (2, 2) and num_colors == 3
    if bayer and {colors[i] for i in pattern.ravel()} != set("RGB") or (
            not bayer and meta.get("tiff:PhotometricInterpretation") == CFA_PHOTOMETRIC):
        named = f" ({''.join(colors[i] for i in pattern.ravel())})" if bayer else ""
        raise HdrMergeError(f"{path}: a colour filter (CFA) mosaic whose CFAPattern{named} is not a Bayer pattern "
                            "(2 x 2 of red, green and blue, each present); the file's CFAPattern tag is wrong")
    if stack or (num_colors == 1 and (pattern is None or pattern.size == 1)):
        return "linear", 3 if stack else 1
    if pattern is not None and pattern.shape == (6, 6):
        raise HdrMergeError(f"{path}: a Fujifilm X-Trans RAW file (6 x 6 colour filter), which cannot be merged: only "
                            "Bayer (2 x 2) mosaics and linear RGB RAW data are supported; convert it to a linear "
                            "(demosaiced) DNG first, e.g. with Adobe DNG Converter")
    if pattern is None or pattern.shape != (2, 2) or num_colors != 3:
        shape = "no" if pattern is None else f"a {pattern.shape[0]} x {pattern.shape[1]}"
        raise HdrMergeError(f"{path}: a RAW file with {shape} colour filter pattern and {num_colors} colours, which "
                            "cannot be merged: only Bayer (2 x 2 RGB) mosaics and linear RGB RAW data are supported")
    return "raw", 4


def _visible(raw) -> np.ndarray:
    """The visible area of an unpacked ``rawpy.RawPy``: LibRaw's buffer itself when it has
    no margins (the view keeps its RawPy, and so the buffer, alive, and it is freed with the
    view: the RawPy must not be closed under it), a copy otherwise (compiled kernels take
    contiguous arrays)."""
    return np.ascontiguousarray(raw.raw_image_visible)


#: sides (pixels) of the smallest RAW image LibRaw reads (16 x 16 fails, 24 x 24 reads)
MIN_RAW_SIDE = 32


def _libraw_reason(exc, path: str | None = None) -> str:
    name = type(exc).__name__
    if name == "LibRawFileUnsupportedError" and path and Path(path).suffix.lower() == ".x3f":
        return "a Sigma Foveon X3F file, which LibRaw does not read; convert it to a linear DNG first"
    if name == "LibRawFileUnsupportedError" and path:
        size = _tiff_size(path)
        if size and min(size) < MIN_RAW_SIDE:
            return (f"its image is {size[0]} x {size[1]} pixels; LibRaw reads RAW images of at least {MIN_RAW_SIDE} x "
                    f"{MIN_RAW_SIDE}")
    return {
        "LibRawIOError": "unreadable or truncated data",
        "LibRawFileUnsupportedError": "unsupported file format",
        "LibRawDataError": "corrupt data",
        "LibRawTooBigError": "image too large",
    }.get(name, name)


def _tiff_size(path: str) -> tuple[int, int] | None:
    """Width and height of a TIFF-based file (a DNG) as its header states them, or None."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        oiio.geterror()
        return None
    try:
        return inp.spec().width, inp.spec().height
    finally:
        inp.close()


def _white_balance(wb: np.ndarray, daylight: np.ndarray) -> np.ndarray:
    """As-shot RGB multipliers with green = 1 (daylight or unity when absent)."""
    for cand in (wb, daylight):
        if cand.size >= 3 and np.all(np.isfinite(cand[:3])) and np.all(cand[:3] > 0):
            return cand[:3] / cand[1]
    return np.ones(3)


def _matrix_or_identity(m: np.ndarray) -> np.ndarray:
    if m.shape == (3, 3) and np.all(np.isfinite(m)) and np.abs(m).sum() > 0:
        return m
    return np.eye(3)


def _open_image(path: str):
    """An OpenImageIO input that reads the values as stored: straight (unassociated) alpha
    is not multiplied into the colour (OpenImageIO does by default); the spec then says
    whether the file's alpha is straight (``oiio:UnassociatedAlpha`` 1)."""
    import OpenImageIO as oiio

    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    return oiio.ImageInput.open(path, config)


def _read_image(path: str) -> Frame:
    import OpenImageIO as oiio

    inp = _open_image(path)
    if inp is None:
        raise HdrMergeError(f"{path}: not a readable image ({_oiio_reason(oiio.geterror())})")
    spec = inp.spec()
    inp.close()
    base = spec.format.basetype
    if base not in (oiio.UINT8, oiio.UINT16):
        raise HdrMergeError(f"{path}: {spec.format} pixels are not supported; give 8- or 16-bit integer images")
    container = 8 if base == oiio.UINT8 else 16
    bits = spec.get_int_attribute("oiio:BitsPerSample", container) or container
    channels = 1 if spec.nchannels <= 2 else 3  # colour; a second or fourth channel is alpha
    alpha = spec.alpha_channel if spec.alpha_channel >= channels else None
    if alpha is None and spec.nchannels > channels:
        log.warning("%s: its channel %d is not marked as alpha; ignored", path, channels + 1)
    white = 2.0**container - 1
    iso = _image_iso({k: spec.getattribute(k) for k in ("Exif:PhotographicSensitivity", "Exif:ISOSpeedRatings")})
    stamp = spec.getattribute("Exif:DateTimeOriginal") or spec.getattribute("DateTime")
    orientation = spec.get_int_attribute("Orientation", 1)
    return Frame(
        path=path, kind="image", width=spec.width, height=spec.height,
        exposure_time=_positive(spec.getattribute("ExposureTime")), iso=iso,
        aperture=_positive(spec.getattribute("FNumber")), make=str(spec.getattribute("Make") or ""),
        model=str(spec.getattribute("Model") or ""), timestamp=str(stamp) if stamp else None,
        bits=bits, n_codes=2**container, black=np.zeros(channels), white=np.full(channels, white),
        channels=channels, channel_colors="RGB"[:channels] if channels == 3 else "Y",
        orientation=orientation if 1 <= orientation <= 8 else 1, alpha_channel=alpha, style=_style(spec),
        alpha_associated=alpha is not None and spec.get_int_attribute("oiio:UnassociatedAlpha", 0) != 1,
        auto_bracket=spec.get_int_attribute("Exif:ExposureMode", 0) == 2, exposure_bias=_finite(
            spec.getattribute("Exif:ExposureBiasValue")),
    )


def _finite(value) -> float | None:
    """``value`` as a finite float, or None."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        return None
    return x if np.isfinite(x) else None


#: EXIF tags that describe how a camera processed an image (its picture style)
STYLE_TAGS = ("Exif:Contrast", "Exif:Saturation", "Exif:Sharpness", "Exif:CustomRendered", "Software")


def _style(spec) -> str:
    """The :attr:`Frame.style` of an image's header."""
    values = ((tag.split(":")[-1].lower(), spec.getattribute(tag)) for tag in STYLE_TAGS)
    return ",".join(f"{name}={str(v).strip()}" for name, v in values if v is not None and str(v).strip())


def _image_iso(meta: dict) -> float | None:
    """ISO from EXIF PhotographicSensitivity or the older ISOSpeedRatings (maybe a tuple)."""
    for key in ("Exif:PhotographicSensitivity", "Exif:ISOSpeedRatings"):
        value = meta.get(key)
        if isinstance(value, (tuple, list)):
            value = value[0] if value else None
        if _positive(value):
            return _positive(value)
    return None


def _oiio_reason(message: str) -> str:
    line = (message or "unknown error").strip().splitlines()[-1]
    return line.replace("\n", " ")[:200]


def load_codes(frame: Frame) -> np.ndarray:
    """Decode the stored code values: ``(H, W)`` uint16 for RAW (visible area, before
    black-level subtraction), ``(H, W, C)`` uint8/uint16 for images (colour only; 0 where
    the alpha channel is 0, see :func:`decode`) and for linear RAW
    data, whose codes are returned with the file's black level subtracted and scaled to
    0..65535 at its white level (so the linear frame reads like a linear 16-bit TIFF:
    black 0, clipping at 65535)."""
    return decode(frame)[0]


def decode(frame: Frame) -> tuple[np.ndarray, np.ndarray | None]:
    """One decode of a frame: ``(codes, validity)``, the codes of :func:`load_codes` and how
    much of each pixel a frame with an alpha channel measured: ``(H, W)`` float32 in [0, 1],
    its alpha over full scale (0 outside a remapped or masked frame, as Hugin's ``nona``
    and image editors write them; partial at a feathered edge); None where every pixel is
    opaque or the frame has no alpha."""
    if frame.kind in ("raw", "linear"):
        import rawpy

        try:
            with quiet_c_stderr():
                codes = _visible(rawpy.imread(frame.path))
        except rawpy.LibRawError as exc:
            raise HdrMergeError(f"{frame.path}: not a readable RAW file ({_libraw_reason(exc, frame.path)})") from None
        return (linear_codes(codes, frame) if frame.kind == "linear" else codes), None
    alpha = frame.alpha_channel
    pixels = _read_channels(frame, 0, frame.channels if alpha is None else max(alpha + 1, frame.channels))
    if alpha is not None:
        colour = np.ascontiguousarray(pixels[..., : frame.channels])
        a = pixels[..., alpha]
        if frame.alpha_associated:  # stored multiplied by alpha: the straight colour, as codes
            top = np.float32(frame.n_codes - 1)
            partial = (a > 0) & (a < top)
            straight = colour[partial].astype(np.float32) * (top / a[partial, None].astype(np.float32))
            colour[partial] = np.clip(np.rint(straight), 0, top).astype(colour.dtype)
        colour[a == 0] = 0  # transparent pixels read black, below every statistic's dark floor
        top = frame.n_codes - 1
        return colour, None if np.all(a == top) else a.astype(np.float32) / np.float32(top)
    return pixels, None


class HeldCodes:
    """``frame -> codes``: each frame of a bracket decoded once and held, read-only, with
    its alpha's validity (:func:`decode`), for every later pass (the samples, registration,
    noise, ghosts, the merge and its re-weighting, the output's alpha); keyed by the frame
    object itself, not its path or position.  Safe to call from several threads: two
    threads asking for one frame share one decode.  A RAW frame's codes can be handed over
    by :func:`read_frame`, from the open that read its metadata (:meth:`hold`).  ``load``:
    a ``frame -> codes`` decoder in place of :func:`decode` (its frames fully valid)."""

    def __init__(self, load=None):
        self.decode = decode if load is None else (lambda frame: (load(frame), None))
        self._codes: dict[int, tuple[Frame, np.ndarray]] = {}  # id -> (the frame, kept alive: its id stays its own)
        self._validity: dict[int, np.ndarray | None] = {}  # id -> validity, kept when the codes are dropped
        self._lock = threading.Lock()
        self._decoding: dict[int, threading.Lock] = {}

    def hold(self, frame: Frame, codes: np.ndarray, validity: np.ndarray | None = None) -> None:
        """Keep ``codes`` (and ``validity``) as ``frame``'s, handed out as a read-only view
        (the caller's array keeps its own flags)."""
        codes = codes.view()
        codes.flags.writeable = False
        with self._lock:
            self._codes[id(frame)] = (frame, codes)
            self._validity[id(frame)] = validity

    def drop(self, frame: Frame) -> None:
        """Forget ``frame``'s codes (a caller that keeps what it made of them instead); a later
        call decodes again.  Its validity is kept."""
        with self._lock:
            self._codes.pop(id(frame), None)

    def _held(self, frame: Frame) -> np.ndarray | None:
        with self._lock:
            entry = self._codes.get(id(frame))
        return None if entry is None else entry[1]

    def __call__(self, frame: Frame) -> np.ndarray:
        codes = self._held(frame)
        if codes is not None:
            return codes
        with self._lock:
            one = self._decoding.setdefault(id(frame), threading.Lock())
        with one:  # two threads asking for one frame: one decode
            if self._held(frame) is None:
                self.hold(frame, *self.decode(frame))
            return self._held(frame)

    def validity(self, frame: Frame) -> np.ndarray | None:
        """The frame's alpha as :func:`decode` gives it (from the decode that gave its codes)."""
        with self._lock:
            if id(frame) in self._validity:
                return self._validity[id(frame)]
        self(frame)
        return self._validity[id(frame)]


def _read_channels(frame: Frame, begin: int, end: int) -> np.ndarray:
    """Channels ``begin`` to ``end`` (exclusive) of an image frame, ``(H, W, end - begin)``
    uint8/uint16 as stored."""
    import OpenImageIO as oiio

    inp = _open_image(frame.path)
    if inp is None:
        raise HdrMergeError(f"{frame.path}: not a readable image ({_oiio_reason(oiio.geterror())})")
    try:
        pixels = inp.read_image(0, 0, begin, end, format=oiio.UINT8 if frame.n_codes == 256 else oiio.UINT16)
        err = inp.geterror()
    finally:
        inp.close()
    if pixels is None or (err and "error" in err.lower()):
        raise HdrMergeError(f"{frame.path}: could not decode the pixels ({_oiio_reason(err)})")
    return pixels[..., None] if pixels.ndim == 2 else pixels


def linear_codes(stored: np.ndarray, frame: Frame) -> np.ndarray:
    """A linear frame's ``(H, W, C)`` uint16 codes from LibRaw's visible ``(H, W, 4)`` colour
    stack (or ``(H, W)`` monochrome data): ``(stored - black) * 65535 / (white - black)``
    per channel, rounded and clipped to 0..65535 (values at or above the white level clip)."""
    data = stored[..., : frame.channels] if stored.ndim == 3 else stored[..., None]
    if data.shape[-1] != frame.channels:
        raise HdrMergeError(f"{frame.path}: decoded {data.shape[-1]} colour channels, expected {frame.channels}")
    black, white = frame.file_levels
    black = np.asarray(black, np.float32)[: frame.channels]
    out = np.empty(data.shape, np.uint16)
    for c in range(frame.channels):
        scale = np.float32(65535.0 / (float(white) - float(black[c])))
        v = (data[..., c].astype(np.float32) - black[c]) * scale
        np.rint(v, out=v)
        np.clip(v, 0, 65535, out=v)
        out[..., c] = v
    return out


def cfa_corner(frame: Frame) -> np.ndarray:
    """The top-left 2 x 2 cell of a RAW frame's colour index map (0..3, LibRaw's order)."""
    return frame.cfa_cell if frame.cfa_cell is not None else raw_channel_window(frame.path)[:2, :2]


#: rows and columns of the colour index map :func:`raw_channel_window` reads: a multiple of
#: every CFA period in use (2 x 2 Bayer, 6 x 6 X-Trans, 4 x 4 quad Bayer)
CFA_WINDOW = 12


def _channel_window(raw, size: int = CFA_WINDOW) -> np.ndarray:
    """:func:`raw_channel_window` of an open ``rawpy.RawPy`` (unpacks it if needed)."""
    top, left = raw.sizes.top_margin, raw.sizes.left_margin
    return np.array([[raw.raw_color(top + i, left + j) for j in range(size)] for i in range(size)], np.uint8)


def raw_channel_window(path: str, size: int = CFA_WINDOW) -> np.ndarray:
    """LibRaw's raw colour index (0..3) of the top-left ``size`` x ``size`` visible sites,
    uint8, from the colour at each position (``raw_color``): the CFA is periodic, so this
    window tells its layout and period without the whole map (``raw_colors_visible``,
    ~0.1 s at 24 MP)."""
    import rawpy

    try:
        with quiet_c_stderr(), rawpy.imread(path) as raw:
            return _channel_window(raw, size)
    except rawpy.LibRawError as exc:
        raise HdrMergeError(f"{path}: not a readable RAW file ({_libraw_reason(exc, path)})") from None
